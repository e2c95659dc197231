"""Accuracy presets of the k_A backends, placed on the measured speed-accuracy frontier
(bench/bench_accuracy.py, bench/results/accuracy.csv and pareto.png).

``ACCURACY[preset][backend]`` holds the settings passed to the backend factory: for the quadrature
backend a relative tolerance ``rtol``, for the Monte Carlo backends (``mitsuba``, ``numpy-mc``) a
target relative standard error ``rel_se``.
"""
from __future__ import annotations

from typing import Any

from ..errors import InputError

ACCURACY: dict[str, dict[str, dict[str, Any]]] = {
    "fast": {"quadrature": {"rtol": 1e-3}, "mitsuba": {"rel_se": 3e-3}, "numpy-mc": {"rel_se": 3e-3}},
    "default": {"quadrature": {"rtol": 1e-4}, "mitsuba": {"rel_se": 1e-3}, "numpy-mc": {"rel_se": 1e-3}},
    "precise": {"quadrature": {"rtol": 1e-6}, "mitsuba": {"rel_se": 2e-4}, "numpy-mc": {"rel_se": 2e-4}},
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
