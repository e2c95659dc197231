"""References for a correction: the CIE tables nearest to a measured one, SAMPLE names, and the
alternative references whose k_A measures the model dependence of the classic route
(``roadgonio correct --reference SAMPLE``; paper section 4.1)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from roadgonio.surface.model import RoadModel
from roadgonio.surface.rtable import BUNDLED, RTable, bundled_table


def nearest_standard_tables(table: RTable, k: int = 2, exclude: Sequence[str] = ()) -> list[tuple[str, float]]:
    """The k bundled CIE tables nearest to ``table`` in (S1, Q0), each scaled by its standard
    deviation over the six tables; returns (name, distance)."""
    stats = {n: (bundled_table(n).s1(), bundled_table(n).q0()) for n in BUNDLED}
    s1s = np.array([v[0] for v in stats.values()])
    q0s = np.array([v[1] for v in stats.values()])
    ss, sq = s1s.std(), q0s.std()
    s1, q0 = table.s1(), table.q0()
    ex = {e.upper() for e in exclude}
    d = [(n, math.hypot((v[0] - s1) / ss, (v[1] - q0) / sq)) for n, v in stats.items() if n not in ex]
    d.sort(key=lambda t: t[1])
    return d[:k]


def sample_name(spec: str) -> str:
    """Short name of a SAMPLE argument: a file's stem, else the argument (``R3``, ``lambert``)."""
    return Path(spec).stem if Path(spec).suffix else spec


def resolve_alternatives(spec: str | Sequence[str] | None, measured: RTable, *, reference_name: str,
                         model_variant: str | None = None) -> dict[str, RoadModel]:
    """The alternative references for the model uncertainty: ``"auto"`` = the two CIE tables
    nearest to ``measured`` in (S1, Q0), the reference excluded; ``"none"``/``None`` = none; a
    comma-separated text or a list of SAMPLEs = those (fitted or loaded like the reference)."""
    from roadgonio.surface.sample import resolve_sample
    if spec is None:
        return {}
    if isinstance(spec, str):
        text = spec.strip()
        if text.lower() == "auto":
            names = [n for n, _ in nearest_standard_tables(measured, 2, exclude=[reference_name])]
        elif text.lower() in ("none", ""):
            names = []
        else:
            names = [s.strip() for s in text.split(",") if s.strip()]
    else:
        names = [str(s) for s in spec]
    return {sample_name(n): resolve_sample(n, model_variant) for n in names}
