"""Accuracy presets of the k_A backends, placed on the measured speed-accuracy frontier
(bench/bench_accuracy.py, bench/results/accuracy.csv and pareto.png).

``ACCURACY[preset][backend]`` holds the settings passed to the backend factory: for the quadrature
backend a relative tolerance ``rtol``, for the Monte Carlo backends (``mitsuba``, ``numpy-mc``) a
target relative standard error ``rel_se``.

Measured points (bench/bench_accuracy.py, portable preset, R3-like model, 6 cells including the
specular peak tan 12 / beta 2; max relative error against quadrature rtol 1e-7, itself good to
<= 9.5e-5 on those cells; seconds on a shared, loaded 2-core machine):

========  ==========================================  ==========================================
preset    quadrature                                  mitsuba
========  ==========================================  ==========================================
fast      rtol 1e-3: 1.1 s, max err 9.7e-5;           rel_se 3e-3: 0.15 s, max err 1.2e-3
          full 580-cell table 34 s, all converged
default   rtol 1e-4: 4.8 s, max err 1.5e-5            rel_se 1e-3: 0.9 s, max err 1.2e-3
precise   rtol 1e-6: 9.2 s, max err 3.1e-6 (below     rel_se 3e-4: 11 s, max err 4.7e-5 (smaller
          the reference's own error)                  rel_se hits the renderer's sample cap)
========  ==========================================  ==========================================

numpy-mc (float64 oracle) at rel_se 1e-3 took 8.0 s for the same cells (max err 1.2e-3).
"""
from __future__ import annotations

from typing import Any

from ..errors import InputError

ACCURACY: dict[str, dict[str, dict[str, Any]]] = {
    "fast": {"quadrature": {"rtol": 1e-3}, "mitsuba": {"rel_se": 3e-3}, "numpy-mc": {"rel_se": 3e-3}},
    "default": {"quadrature": {"rtol": 1e-4}, "mitsuba": {"rel_se": 1e-3}, "numpy-mc": {"rel_se": 1e-3}},
    "precise": {"quadrature": {"rtol": 1e-6}, "mitsuba": {"rel_se": 3e-4}, "numpy-mc": {"rel_se": 3e-4}},
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
