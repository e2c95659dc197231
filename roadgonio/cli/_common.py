"""Helpers shared by the commands (not a command: modules starting with '_' are not discovered)."""
from __future__ import annotations

import math

from ..errors import InputError


def rel_se_setting(backend: str, value: float) -> dict[str, float]:
    """The backend keyword for ``--rel-se``: a relative tolerance ``rtol`` for the quadrature, a
    target relative standard error ``rel_se`` for the Monte Carlo backends. Checks 0 < value < 1."""
    if not (math.isfinite(value) and 0 < value < 1):
        raise InputError(f"expected a relative error in (0, 1), got {value}", field="--rel-se")
    return {"rtol" if backend == "quadrature" else "rel_se": value}
