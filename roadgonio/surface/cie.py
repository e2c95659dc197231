"""CIE road-surface classes of an r-table by its specular factor S1 and the nearest bundled CIE
standard table: written once here, used by ``roadgonio classify``, the correction's report and its
choice of alternative references.

Class limits (CIE 144:2001 and CIE 66:1984):

    R1  S1 < 0.42          R2  0.42 <= S1 < 0.85   R3  0.85 <= S1 < 1.35   R4  1.35 <= S1
    C1  S1 < 0.40          C2  0.40 <= S1
    N1  S1 < 0.28          N2  0.28 <= S1 < 0.60   N3  0.60 <= S1 < 1.30   N4  1.30 <= S1

with class-standard Q0: R1 0.10, R2 0.07, R3 0.07, R4 0.08, C1 0.10, C2 0.07, N1 0.10, N2 0.07,
N3 0.07, N4 0.08 sr^-1 (the published Q0 of the standard tables, roadgonio/data/rtables/SOURCES.md).
A surface of class X is represented by the standard table X scaled by Q0 / Q0_standard, both Q0 by
one rule: for the bundled standards (R1-R4, C1, C2) Q0_standard is the bundled table's own Q0 by
:meth:`RTable.q0` (the published values come from the CIE's weights and differ from it by up to
3.5 %, R1's 0.1035 against 0.10; user audit, session 44: R1 classified as "x1.035" of itself); the
N standard tables are not bundled (no public source, SOURCES.md), so theirs is the published value,
said so. The "nearest" bundled table is the
one closest in (S1, Q0), each coordinate scaled by its spread (population standard deviation) over
the six bundled tables.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Any, Sequence

from roadgonio.errors import InputError
from roadgonio.surface.rtable import BUNDLED, PUBLISHED_Q0, RTable, bundled_table

#: system -> [(class, lower S1 limit inclusive, upper limit exclusive)]
CLASS_LIMITS = {
    "R": [("R1", -math.inf, 0.42), ("R2", 0.42, 0.85), ("R3", 0.85, 1.35), ("R4", 1.35, math.inf)],
    "C": [("C1", -math.inf, 0.40), ("C2", 0.40, math.inf)],
    "N": [("N1", -math.inf, 0.28), ("N2", 0.28, 0.60), ("N3", 0.60, 1.30), ("N4", 1.30, math.inf)],
}
STANDARD_Q0 = {**PUBLISHED_Q0, "N1": 0.10, "N2": 0.07, "N3": 0.07, "N4": 0.08}
#: S1 is judged against the class limits rounded to this many decimals: dividing the stored r can land
#: an ulp off a limit (135 / 100 gave 1.3499999999999999 and R3 where 1.35 <= R4; audit 21). So an S1
#: within 5e-10 below a limit (r(2, 0) given to 10 significant digits, 123.4799999 / 294) takes the
#: class above it, a difference no measurement of r resolves (user audit, session 41)
S1_CLASS_DECIMALS = 9


def class_by_s1(s1: float, system: str) -> tuple[str, float]:
    """(class, distance of S1 to the nearest class limit) in ``system`` ('R', 'C' or 'N'); S1 rounded
    to :data:`S1_CLASS_DECIMALS` decimals first."""
    s1 = round(s1, S1_CLASS_DECIMALS)
    for name, lo, hi in CLASS_LIMITS[system]:
        if lo <= s1 < hi:
            # the margin to the same decimals as S1 (0.24115646300000004 was its float noise)
            return name, round(min(abs(s1 - lo), abs(hi - s1)), S1_CLASS_DECIMALS)
    raise ValueError(f"S1 = {s1} outside every class")  # pragma: no cover (limits cover the line)


def s1_text(s1: float) -> str:
    """S1 to three decimals, or to as many as show its side of a class limit it would round onto:
    "S1 = 0.420" beside R1, whose limit is S1 < 0.42, read as a contradiction (user audit, session 41)."""
    limits = {hi for rows in CLASS_LIMITS.values() for _, _, hi in rows if hi != float("inf")}
    for decimals in range(3, S1_CLASS_DECIMALS + 1):
        text = f"{s1:.{decimals}f}"
        if not any(float(text) == lim and s1 != lim for lim in limits):
            return text
    return text


def class_probabilities(s1: float, u_s1: float, system: str) -> dict[str, float]:
    """The probability of each class of ``system`` for S1 distributed as N(s1, u_s1^2)."""
    from scipy.stats import norm
    return {name: float(norm.cdf(hi, s1, u_s1) - norm.cdf(lo, s1, u_s1)) for name, lo, hi in CLASS_LIMITS[system]}


def cie_class(s1: float, u_s1: float | None = None) -> dict[str, Any]:
    """The R, C and N classes of S1 (``{"R": "R3", "C": "C2", "N": "N3"}``) and, with a finite
    u(S1) > 0, the probability of each class (``p_R``, ``p_C``, ``p_N``) under N(S1, u^2)."""
    if not math.isfinite(s1):          # S1 missing (a blank r(0, 0) or r(2, 0)): no class
        return {system: None for system in CLASS_LIMITS}
    out: dict[str, Any] = {system: class_by_s1(s1, system)[0] for system in CLASS_LIMITS}
    if u_s1 is not None and u_s1 > 0 and math.isfinite(u_s1):
        for system in CLASS_LIMITS:
            out[f"p_{system}"] = class_probabilities(s1, u_s1, system)
    return out


@lru_cache(maxsize=1)
def _bundled_s1_q0() -> dict[str, tuple[float, float]]:
    return {n: (bundled_table(n).s1(), bundled_table(n).q0()) for n in BUNDLED}


def standard_q0(name: str) -> tuple[float, str]:
    """(Q0 of the class standard ``name``, where it comes from): the bundled table's own Q0 by
    :meth:`RTable.q0`, the rule a table's Q0 is computed by, or for a standard not bundled its
    published value (module docstring)."""
    if name in BUNDLED:
        return _bundled_s1_q0()[name][1], "the bundled standard table, by the same Q0 rule"
    return STANDARD_Q0[name], ("published (the standard table is not bundled; the CIE's weights, another Q0 rule, "
                               "up to ~3.5 % apart)")


def nearest_bundled(s1: float, q0: float, k: int | None = None,
                    exclude: Sequence[str] = ()) -> list[tuple[str, float]]:
    """The bundled CIE tables ordered by their distance to (S1, Q0), each coordinate scaled by its
    spread over the six tables (module docstring): ``[(name, distance), ...]``, the first ``k``
    (all with ``k=None``), without the names in ``exclude``. A missing (NaN) S1 or Q0 is left out
    of the distance; with both missing the list is empty."""
    stats = _bundled_s1_q0()
    s1s = [v[0] for v in stats.values()]
    q0s = [v[1] for v in stats.values()]
    ss, sq = _spread(s1s), _spread(q0s)
    ex = {e.upper() for e in exclude}
    # a missing coordinate (NaN: S1 or Q0 the table lacks the cells for) is left out of the distance
    use_s1, use_q0 = math.isfinite(s1), math.isfinite(q0)
    if not (use_s1 or use_q0):
        return []
    d = sorted(((math.hypot((v[0] - s1) / ss if use_s1 else 0.0, (v[1] - q0) / sq if use_q0 else 0.0), n)
                for n, v in stats.items() if n not in ex))
    out = [(n, dist) for dist, n in d]
    return out if k is None else out[:k]


def nearest_basis(s1: float, q0: float) -> str:
    """What :func:`nearest_bundled` measured its distance on: "" for S1 and Q0, else which one alone
    (user audit, session 29: a table without S1 named a nearest table by Q0, whose six values differ
    by 2 %, and it changed between before and after without a word)."""
    use_s1, use_q0 = math.isfinite(s1), math.isfinite(q0)
    if use_s1 and use_q0:
        return ""
    if use_q0:
        return "by Q0 alone: S1 missing"
    return "by S1 alone: Q0 missing" if use_s1 else ""


def classify(table: RTable) -> dict[str, Any]:
    """S1, Q0, S2 of ``table``, its class in each system with the margin of S1 to the nearest class
    limit and the Q0 scale of the class standard, and the bundled tables by distance.

    The class is defined by S1: a table without it (r(beta 0, tan 0) blank or 0, or r(beta 0,
    tan 2) blank) is an :class:`InputError` naming what is missing. Without Q0 (no grid cell with
    four tabulated corners) Q0, the Q0 scale and the nearest tables are None / empty (missing)."""
    s1, q0 = table.s1(), table.q0()
    if s1 == 0.0:
        # a 0 is not a reading (docs/inputs-outputs.md): S1 = 0 gave R1 / C1 / N1 from it, where fit refuses
        # the same file (user audit, session 41)
        raise InputError("cannot classify: r(beta 0, tan eps 2) is 0, and S1 = r(beta 0, tan eps 2) / r(beta 0, "
                         "tan eps 0) defines the class; a 0 is not a reading: expected r > 0 there (blank it, or give "
                         "the reading)", field="S1")
    if not math.isfinite(s1):
        r00, r20 = table.value(0.0, 0.0), table.value(2.0, 0.0)
        lack = [f"r(beta 0, tan eps 0) is {'blank' if math.isnan(r00) else f'{r00:g}'}"] if not r00 > 0 else []
        if math.isnan(r20):
            lack.append("r(beta 0, tan eps 2) is blank")
        raise InputError("cannot classify: the CIE class is defined by S1 = r(beta 0, tan eps 2) / r(beta 0, tan eps 0), "
                         f"and {' and '.join(lack)}; expected both cells, r(0, 0) > 0", field="S1")
    from roadgonio.surface.rtable import q0_coverage_note
    note = q0_coverage_note(table)
    q0_ok = math.isfinite(q0)
    # a Q0 over other cells than the standard tables' is no standard's Q0 (the note says so): no scale
    # from it, and the nearest table by S1 alone (user audit, session 44: R3's cells tan eps <= 2,
    # beta <= 5 alone, S1 R3's exactly, were "nearest R1" by that Q0, "x1.753")
    comparable = q0_ok and note is None
    out: dict[str, Any] = {"table": table.name, "S1": s1, "Q0": q0 if q0_ok else None,
                           "S2": table.s2() if q0_ok else None, "classes": {}}
    for system in CLASS_LIMITS:
        name, margin = class_by_s1(s1, system)
        q0_std, q0_from = standard_q0(name)
        out["classes"][system] = {"class": name, "S1_margin_to_limit": margin,
                                  "standard_Q0": q0_std, "standard_Q0_from": q0_from,
                                  "Q0_scale": q0 / q0_std if comparable else None,
                                  "bundled": name in BUNDLED}
    stats = _bundled_s1_q0()
    out["nearest_bundled"] = [{"table": n, "distance": d, "S1": stats[n][0], "Q0": stats[n][1]}
                              for n, d in nearest_bundled(s1, q0 if comparable else math.nan)]
    out["nearest_basis"] = "" if comparable else "by S1 alone: " + (
        "Q0 missing" if not q0_ok else "Q0 over other cells than the standard tables'")
    if not q0_ok:
        out["missing"] = "Q0 (no grid cell with four tabulated corners): no Q0 scale, nearest bundled table by S1 alone"
    out["notes"] = [note + "; no Q0 scale, nearest bundled table by S1 alone"] if note else []
    return out


def _spread(v: Sequence[float]) -> float:
    m = sum(v) / len(v)
    return math.sqrt(sum((x - m) ** 2 for x in v) / len(v))
