"""CIE road-surface classes of an r-table by its specular factor S1, with its Q0, and the nearest
bundled CIE standard table.

Class limits (CIE 144:2001 and CIE 66:1984; as tabulated in W. van Bommel, Road Lighting:
Fundamentals, Technology and Application, Springer 2015, Table 12.2 "R, C and N-class limits and
class-standards"):

    R1  S1 < 0.42          R2  0.42 <= S1 < 0.85   R3  0.85 <= S1 < 1.35   R4  1.35 <= S1
    C1  S1 < 0.40          C2  0.40 <= S1
    N1  S1 < 0.28          N2  0.28 <= S1 < 0.60   N3  0.60 <= S1 < 1.30   N4  1.30 <= S1

with class-standard Q0: R1 0.10, R2 0.07, R3 0.07, R4 0.08, C1 0.10, C2 0.07, N1 0.10, N2 0.07,
N3 0.07, N4 0.08 sr^-1 (the published Q0 of roadgonio's bundled tables, SOURCES.md). A surface of
class X is represented by the standard table X scaled by Q0 / Q0_standard. The N standard tables are
not bundled (no public source, SOURCES.md). The "nearest" bundled table is the one closest in
(S1, Q0), each coordinate scaled by its spread over the six bundled tables (as the correction's
choice of alternative references).
"""
from __future__ import annotations

import math

from roadgonio.surface.rtable import BUNDLED, PUBLISHED_Q0, RTable, bundled_table

#: system -> [(class, lower S1 limit inclusive, upper limit exclusive)]
CLASS_LIMITS = {
    "R": [("R1", -math.inf, 0.42), ("R2", 0.42, 0.85), ("R3", 0.85, 1.35), ("R4", 1.35, math.inf)],
    "C": [("C1", -math.inf, 0.40), ("C2", 0.40, math.inf)],
    "N": [("N1", -math.inf, 0.28), ("N2", 0.28, 0.60), ("N3", 0.60, 1.30), ("N4", 1.30, math.inf)],
}
STANDARD_Q0 = {**PUBLISHED_Q0, "N1": 0.10, "N2": 0.07, "N3": 0.07, "N4": 0.08}


def class_by_s1(s1: float, system: str) -> tuple[str, float]:
    """(class, distance of S1 to the nearest class limit) in ``system`` ('R', 'C' or 'N')."""
    for name, lo, hi in CLASS_LIMITS[system]:
        if lo <= s1 < hi:
            return name, min(abs(s1 - lo), abs(hi - s1))
    raise ValueError(f"S1 = {s1} outside every class")  # pragma: no cover (limits cover the line)


def classify(table: RTable) -> dict:
    s1, q0 = table.s1(), table.q0()
    out = {"table": table.name, "S1": s1, "Q0": q0, "S2": table.s2(), "classes": {}}
    for system in CLASS_LIMITS:
        name, margin = class_by_s1(s1, system)
        out["classes"][system] = {"class": name, "S1_margin_to_limit": margin,
                                  "standard_Q0": STANDARD_Q0[name], "Q0_scale": q0 / STANDARD_Q0[name],
                                  "bundled": name in BUNDLED}
    stats = {n: (bundled_table(n).s1(), bundled_table(n).q0()) for n in BUNDLED}
    s1s = [v[0] for v in stats.values()]
    q0s = [v[1] for v in stats.values()]
    ss = _std(s1s)
    sq = _std(q0s)
    dist = sorted(((math.hypot((v[0] - s1) / ss, (v[1] - q0) / sq), n) for n, v in stats.items()))
    out["nearest_bundled"] = [{"table": n, "distance": d, "S1": stats[n][0], "Q0": stats[n][1]} for d, n in dist]
    return out


def _std(v):
    m = sum(v) / len(v)
    return math.sqrt(sum((x - m) ** 2 for x in v) / len(v))
