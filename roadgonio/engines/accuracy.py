"""Accuracy presets of the k_A backends, placed on the measured speed-accuracy frontier
(bench/bench_accuracy.py, bench/results/accuracy.csv and pareto.png).

``ACCURACY[preset][backend]`` holds the settings that ``roadgonio.engines.make_backend(name, ...,
accuracy=preset)`` passes to the backend factory (explicit settings override them): for the
quadrature backend a relative tolerance ``rtol``, for the Monte Carlo backends (``mitsuba``,
``numpy-mc``) a target relative standard error ``rel_se`` and the size of the first pass.

Measured points (bench/bench_accuracy.py on the idle 2-core machine, portable preset, R3-like
model, 7 cells including the specular peak tan 12 / beta 0 and 2; max relative error against
quadrature at rtol 1e-7, itself good to 8e-7):

========  ==============================  ==============================  ==============================
preset    quadrature                      mitsuba (float32)               numpy-mc (float64 oracle)
========  ==============================  ==============================  ==============================
fast      rtol 1e-3: 0.07 s, err 6.0e-5;  3e-3, 32^2 x 4 first pass:      3e-3, 8 batches of 32^2:
          full table 5.4-6.4 s            0.02 s, err 7.1e-4              0.03 s, err 4.8e-4
default   rtol 1e-4: 0.45 s, err 2.3e-5;  1e-3, 64^2 x 16: 0.04 s,        1e-3, 8 x 128^2: 0.4 s,
          full table 26-28 s              err 9.4e-5                      err 1.1e-4
precise   rtol 1e-6: 4.9 s, err 2.9e-7    1e-4, 64^2 x 16 adaptive:       1e-4, 8 x 128^2 adaptive:
                                          0.06 s, err 9.4e-5 (SE 6.8e-5)  0.5 s, err 1.1e-4
========  ==============================  ==============================  ==============================

A fixed-budget Mitsuba pass of 4096k samples per cell reaches 3e-6 in 1.2 s for the 7 cells; on
smooth samples the renderer's first pass already meets "precise"; on stiff lobes the adaptive
passes grow (bench/results/accuracy.csv has the whole ladder).
"""
from __future__ import annotations

import math
from typing import Any

from roadgonio.errors import InputError

#: The Monte Carlo presets also set the size of the first pass (Mitsuba: resolution^2 x spp samples;
#: numpy-mc: batch x 8): with the default pass of 64^2 x 16 every target down to ~1e-4 is already met
#: after one pass on smooth samples, so a target alone cannot make "fast" faster. "default" equals
#: the backends' own defaults (what runs without --accuracy).
ACCURACY: dict[str, dict[str, dict[str, Any]]] = {
    "fast": {"quadrature": {"rtol": 1e-3},
             "mitsuba": {"rel_se": 3e-3, "resolution": 32, "spp": 4},
             "numpy-mc": {"rel_se": 3e-3, "batch": 32 ** 2}},
    "default": {"quadrature": {"rtol": 1e-4},
                "mitsuba": {"rel_se": 1e-3, "resolution": 64, "spp": 16},
                "numpy-mc": {"rel_se": 1e-3, "batch": 128 ** 2}},
    "precise": {"quadrature": {"rtol": 1e-6},
                "mitsuba": {"rel_se": 1e-4, "resolution": 64, "spp": 16},
                "numpy-mc": {"rel_se": 1e-4, "batch": 128 ** 2}},
}

PRESETS = tuple(ACCURACY)


def preset(name: str, backend: str) -> dict[str, Any]:
    """Settings of ``backend`` for the accuracy preset ``name``."""
    if name not in ACCURACY:
        raise InputError(f"unknown accuracy preset {name!r}; expected one of {', '.join(PRESETS)}",
                         field="--accuracy")
    table = ACCURACY[name]
    if backend not in table:
        raise InputError(f"no accuracy preset for backend {backend!r}; presets exist for "
                         f"{', '.join(table)}", field="--backend")
    return dict(table[backend])


def rel_se_setting(backend: str, value: float, field: str = "--rel-se") -> dict[str, float]:
    """The backend keyword for one relative precision target: a relative tolerance ``rtol`` for the
    quadrature and the RQMC reference (its target error bound), a target relative standard error ``rel_se`` for the Monte Carlo backends. Checks
    0 < value < 1 (errors name ``field``: the option or the API argument)."""
    if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            and 0 < value < 1):
        raise InputError(f"expected a relative error in (0, 1), got {value}", field=field)
    return {"rtol" if backend in ("quadrature", "reference") else "rel_se": float(value)}
