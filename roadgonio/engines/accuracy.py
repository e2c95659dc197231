"""Accuracy presets of the k_A backends, placed on the measured speed-accuracy frontier
(bench/bench_accuracy.py, bench/results/accuracy.csv and pareto.png).

``ACCURACY[preset][backend]`` holds the settings that ``roadgonio.engines.make_backend(name, ...,
accuracy=preset)`` passes to the backend factory (explicit settings override them): for the
quadrature backend a relative tolerance ``rtol``, for the Monte Carlo backends (``mitsuba``,
``numpy-mc``) a target relative standard error ``rel_se`` and the size of the first pass.

Measured points (bench/bench_accuracy.py, 2-core machine under load ~6-10 from other work, so the
seconds are 3-5x the idle ones; portable preset, R3-like model, 7 cells including the specular peak
tan 12 / beta 0 and 2; max relative error against quadrature at rtol 1e-7, itself good to 8e-7):

========  ==============================  ==============================  ==============================
preset    quadrature                      mitsuba (float32, batched)      numpy-mc (float64 oracle)
========  ==============================  ==============================  ==============================
fast      rtol 1e-3: 0.6 s, err 6.0e-5;   3e-3, first pass 256:           3e-3, 8 batches of 32^2:
          full table 35 s                 0.05 s, err 1.3e-3;             0.23 s, err 4.8e-4
                                          full table 0.33 s
default   rtol 1e-4: 2.3 s, err 2.3e-5;   1e-3, first pass 1024:          1e-3, 8 x 128^2: 2.0 s,
          full table 118 s                0.01 s, err 1.6e-3 (SE 9.3e-4); err 1.1e-4
                                          full table 0.35 s
precise   rtol 1e-6: 30 s, err 2.9e-7     1e-4, first pass 4096:          1e-4, 8 x 128^2 adaptive:
                                          0.17 s, err 1.1e-4;             2.2 s, err 1.1e-4
                                          full table 2.6 s
========  ==============================  ==============================  ==============================

The batched Mitsuba engine stops every cell at its target (a small first pass, then the 1/N rule
per cell), so its presets sit on the measured front by construction: the ladder of single passes of
256 ... 4M samples per cell (bench/results/accuracy.csv) reaches 1.3e-3 ... 1e-6, and each preset
costs what the ladder point of its error costs. ``first_pass`` only matters for the easy cells
(most of the table), which one first pass of 1024 samples already brings to 1e-3.
"""
from __future__ import annotations

import math
from typing import Any

from roadgonio.errors import InputError

#: The Monte Carlo presets also set the size of the first pass (Mitsuba: samples per cell in the
#: first pass; numpy-mc: batch x 8). "default" equals the backends' own defaults (what runs without
#: --accuracy).
ACCURACY: dict[str, dict[str, dict[str, Any]]] = {
    "fast": {"quadrature": {"rtol": 1e-3},
             "mitsuba": {"rel_se": 3e-3, "first_pass": 256},
             "numpy-mc": {"rel_se": 3e-3, "batch": 32 ** 2}},
    "default": {"quadrature": {"rtol": 1e-4},
                "mitsuba": {"rel_se": 1e-3, "first_pass": 1024},
                "numpy-mc": {"rel_se": 1e-3, "batch": 128 ** 2}},
    "precise": {"quadrature": {"rtol": 1e-6},
                "mitsuba": {"rel_se": 1e-4, "first_pass": 4096},
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
