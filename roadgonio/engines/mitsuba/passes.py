"""Passes of the batched k_A engine and their statistics, in float64 numpy (nothing here imports
mitsuba): how many samples each cell gets in each pass, and the ratio estimator with its standard
error and covariance.

**Replicates.** A cell's samples come in replicates: one replicate is a randomly shifted rank-1
lattice of n = 2^k points (:mod:`roadgonio.engines.mitsuba.lattice`), and in pass p the cell gets
B replicates of one lattice size n. The shifts are a function of (seed, p, n) only
(:func:`~roadgonio.engines.mitsuba.lattice.shifts`), so the replicates of one (pass, n) stratum
are independent and identically distributed, and strata are independent of each other.

**Estimator.** For every replicate the engine returns the sums R and G of the road and Lambert
contributions over its n points; a cell's ratio is r = sum R / sum G over all its replicates, and
k_A = r / ideal_ratio (the ideal in float64, :func:`roadgonio.engines.ideal_ratio`). Its standard
error is the delta-method (linearised ratio) estimate over independent replicates: with
Y = R - r G per replicate and s_q^2 the sample variance of Y over the B_q replicates of stratum q,

    Var(r) ~= sum_q B_q s_q^2 / (sum G)^2        (needs B_q >= 2 in every stratum)

which is unbiased for the variance of the linearised estimator whatever the lattice does within a
replicate (the randomisation is only in the shifts). This is the **marginal** standard error of
each cell. Its degrees of freedom are those of a sum of independent variance estimates, each with
B_q - 1 (Welch-Satterthwaite, :func:`roadgonio.engines.result.welch_satterthwaite`):

    dof = (sum_q v_q)^2 / sum_q v_q^2 / (B_q - 1),    v_q = B_q s_q^2

at least the smallest B_q - 1 (15 for a cell that converged in its first pass of 16 replicates,
most cells at every preset) and at most sum_q (B_q - 1). An error divided by this SE follows
Student's t of that many degrees of freedom (docs/validation.md, "How heavy are the tails").

**Correlation between cells.** Cells in the same launch share the detector rays (and the source
sample of each lattice point), so the errors of cells computed together are correlated (positively
for neighbouring cells: one lattice that happens to over-weight the footprint under the source does
so for all of them). Each cell's SE above stays its correct marginal SE. A functional of the table
(S1, Q0, a fit, a mean over cells) needs the covariance as well: :meth:`RunStats.covariance` estimates
it from the replicates the two cells share (same pass, same lattice size, same replicate index):

    Cov(r_c, r_c') ~= sum_q m_q cov_q(Y_c, Y_c') / (sum G_c sum G_c')

with m_q the number of shared replicates and cov_q their sample covariance; strata that are not
shared are independent. Cells of different tables (other ``compute`` calls) are independent unless
they replay the same plan with the same seed (common random numbers, see :class:`Plan`).

**Passes.** The first pass gives every cell ``first_pass`` samples (B_min replicates of
first_pass / B_min points). After each pass a cell whose relative SE is at or below the target
leaves the active set; for the others the 1/N rule sizes the next pass,

    N_more = N (rel / target)^2 - N, times 1.15 (safety)

but at most :data:`MAX_GROWTH` N, and the cell gets the largest lattice n with B_min replicates of
n <= N_more (at most :data:`MAX_LOG2`), but never a smaller one than it had (larger lattices have
smaller error per point, and the pooled mean weighs every point alike), and ceil(N_more / n)
replicates of it (at least B_min). Cells reaching ``max_samples`` stop and
are flagged not converged. With reflecting parts (``stray_search``) a cell that meets the target
goes on, by MAX_GROWTH, until every replicate sum of its newest lattice carries stray light, up to
:data:`STRAY_SEARCH_MAX` samples (rare stray paths otherwise gave SEs that ignored them). A :class:`Plan` records what every cell got; replaying it (uncertainty
design points) gives every table the same random numbers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from roadgonio.engines.mitsuba.lattice import MAX_LOG2, MIN_LOG2
from roadgonio.engines.result import RATIO_DENOMINATOR_REL_SE_MAX, denominator_rel_se, welch_satterthwaite_many

#: Safety factor on the 1/N rule (the SE estimate itself is noisy).
SAFETY = 1.15
#: Largest rate at which the planner lets the per-point variance of a lattice fall with its size n
#: (variance ~ n^-gamma, gamma measured between the cell's last two sizes, at most this); measured
#: on the wide instrument's specular cells: gamma ~ 0.26 between n = 64 and 2^18.
LATTICE_GAIN_MAX = 0.5
#: A pass gives a cell at most this many times the samples it already has: the lattice's error
#: falls faster than 1/sqrt(N) on smooth parts of the integrand, so a need extrapolated from a small
#: first pass can be much too large; growing in steps re-measures it on the way.
MAX_GROWTH = 8.0


#: With reflecting parts, a cell converges only when every replicate sum of its newest lattice
#: carries stray light (the road's or the Lambert channel's), or ...
STRAY_SEEN_MIN = 1.0
#: ... once it has this many samples: then as not converged, with a note, or as converged if no
#: replicate sum ever saw stray light (a reflecting part the source or the footprint cannot reach:
#: none in 2^20 samples, also noted). Rare stray paths (a
#: reflecting holder an XML scene lights from a few directions) left most replicate sums without
#: any: at 1,024 samples 30 seeds gave rms z 2.35 against a 34M-sample value, 20 % of them beyond 3
#: SE (audit 22); requiring every replicate sum to see it gave rms z 1.07 at 0.77M samples, and
#: left the housed examples' tables unchanged (every replicate sees the housing in the first pass).
STRAY_SEARCH_MAX = 1 << 20


@dataclass
class CellStats:
    """Replicate sums of one cell: per stratum key (pass, log2 n) the replicate indices and the
    float64 sums R, G over each replicate's n points (kept for :func:`covariance`), and the moments
    the standard error needs, centred on the cell's first ratio ``r0`` (no cancellation)."""

    strata: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)
    samples: int = 0
    passes: int = 0
    r0: float | None = None
    sum_r: float = 0.0
    sum_g: float = 0.0
    #: sum over strata of B/(B-1) x centred second moments of (Y0, G): b0 = Y0 Y0, b1 = Y0 G, b2 = G G
    b: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: a stratum with a single replicate (no variance estimate)
    single: bool = False
    #: the same moments per stratum (for the per-point variance of each lattice size)
    strata_b: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    #: with stray light: per stratum the replicate sums of the direct light alone (R_d, G_d); the
    #: sums R, G above are then the totals (direct + stray)
    direct: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Plain JSON types, every float exactly (Python's repr round-trips a float64): the
        checkpoint of a table cut short between passes (``engine.run(on_pass=...)``)."""
        def key(k):
            return f"{k[0]}:{k[1]}"
        return {"strata": {key(k): [v[0].tolist(), v[1].tolist(), v[2].tolist()] for k, v in self.strata.items()},
                "samples": self.samples, "passes": self.passes, "r0": self.r0, "sum_r": self.sum_r,
                "sum_g": self.sum_g, "b": self.b.tolist(), "single": self.single,
                "strata_b": {key(k): v.tolist() for k, v in self.strata_b.items()},
                "direct": {key(k): [v[0].tolist(), v[1].tolist()] for k, v in self.direct.items()}}

    @classmethod
    def from_dict(cls, d: dict) -> "CellStats":
        def key(s):
            a, b = s.split(":")
            return (int(a), int(b))
        f64 = lambda v: np.asarray(v, dtype=np.float64)     # noqa: E731
        return cls(strata={key(k): (np.asarray(v[0], dtype=np.int64), f64(v[1]), f64(v[2]))
                           for k, v in d["strata"].items()},
                   samples=int(d["samples"]), passes=int(d["passes"]),
                   r0=None if d["r0"] is None else float(d["r0"]), sum_r=float(d["sum_r"]), sum_g=float(d["sum_g"]),
                   b=f64(d["b"]), single=bool(d["single"]),
                   strata_b={key(k): f64(v) for k, v in d["strata_b"].items()},
                   direct={key(k): (f64(v[0]), f64(v[1])) for k, v in d["direct"].items()})

    def add(self, pass_index: int, log2n: int, reps: np.ndarray, R: np.ndarray, G: np.ndarray) -> None:
        """Add all replicates of one stratum (at most one call per stratum)."""
        add_strata([self], pass_index, log2n, np.zeros(len(R), dtype=np.int64), reps, R, G)

    def totals(self) -> tuple[float, float]:
        return self.sum_r, self.sum_g

    def ratio_se(self) -> tuple[float, float, float]:
        """(ratio, its standard error, mean Lambert signal per sample); the SE is inf with a stratum
        of one replicate and while the Lambert sum is itself known to worse than
        :data:`~roadgonio.engines.result.RATIO_DENOMINATOR_REL_SE_MAX` (:meth:`lambert_rel_se`)."""
        sr, sg = self.sum_r, self.sum_g
        n = max(self.samples, 1)
        if not sg > 0.0:
            return math.nan, math.inf, sg / n
        ratio = sr / sg
        if self.single or self.lambert_rel_se() > RATIO_DENOMINATOR_REL_SE_MAX:
            return ratio, math.inf, sg / n
        return ratio, math.sqrt(residual_variance(self.b, ratio - self.r0)) / sg, sg / n

    def lambert_rel_se(self) -> float:
        """Relative standard error of the Lambert sum over all replicates (from the moment ``b2``:
        the variance of that sum): how well the light reaching the footprint is sampled at all."""
        return denominator_rel_se(self.b[2], self.sum_g)

    def se_dof(self) -> float:
        """Degrees of freedom of the SE of :meth:`ratio_se` (module docstring: Welch-Satterthwaite
        over the strata); NaN without an SE (a stratum of one replicate, no light). One cell of
        :func:`se_dof_many`."""
        return float(se_dof_many([self])[0])

    def point_variances(self) -> list[tuple[int, float]]:
        """(log2 n, variance per point of Y = R - r G) of each stratum, in pass order: the
        variance of a replicate sum divided by its n points (a lattice's figure of merit)."""
        ratio, _, _ = self.ratio_se()
        if not math.isfinite(ratio):
            return []
        d = ratio - (self.r0 or 0.0)
        out = []
        for key in sorted(self.strata_b):
            b = self.strata_b[key]
            B = len(self.strata[key][0])
            out.append((key[1], residual_variance(b, d) / (B << key[1])))
        return out

    def residuals(self, ratio: float) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
        return {k: (reps, R - ratio * G) for k, (reps, R, G) in self.strata.items()}

    def direct_strata(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per stratum, the replicates' (R_d, G_d) of the direct light alone (with stray light traced)."""
        return [self.direct[k] for k in sorted(self.strata)]

    def stray_strata(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per stratum, the replicates' (R_d, R): the road's direct light against its total, whose
        ratio is 1 - the stray fraction (with stray light traced)."""
        return [(self.direct[k][0], self.strata[k][1]) for k in sorted(self.strata)]

    def direct_ratio_se(self) -> tuple[float, float]:
        """Ratio R_d / G_d of the direct light alone and its standard error (delta method over the
        same replicates); the plain ratio where no stray light was traced."""
        if not self.direct:
            r, se, _ = self.ratio_se()
            return r, se
        return strata_ratio_se(self.direct_strata())

    def absolute_ratio_se(self) -> tuple[float, float]:
        """Ratio R / G_d of the road's total signal (direct + stray) over the Lambert sample's direct
        light, and its standard error (delta method over the same replicates): with stray light, the
        absolute calibration's k_A is eta R / G_d / ideal (:mod:`roadgonio.engines.calibration`: the
        meter reads the total against the source's own E_0). :meth:`ratio_se` without stray light."""
        if not self.direct:
            r, se, _ = self.ratio_se()
            return r, se
        return strata_ratio_se([(self.strata[k][1], self.direct[k][1]) for k in sorted(self.strata)])

    def stray_seen(self) -> float | None:
        """The fraction of the replicate sums of the newest lattice (the largest stratum of the
        last pass) that carry stray light in the road or the Lambert channel (their total differs
        from their direct light); None where no stray light was traced."""
        if not self.direct:
            return None
        key = max(self.strata, key=lambda k: (k[1], k[0]))
        _, R, G = self.strata[key]
        Rd, Gd = self.direct[key]
        return float(np.mean((R != Rd) | (G != Gd)))

    def stray_never_seen(self) -> bool:
        """No replicate sum of any lattice carried stray light (with stray light traced)."""
        return bool(self.direct) and all(np.array_equal(R, self.direct[k][0]) and np.array_equal(G, self.direct[k][1])
                                         for k, (_, R, G) in self.strata.items())

    def stray_fraction_se(self) -> tuple[float, float]:
        """Stray fraction of the road signal, 1 - R_d / R (R = direct + stray), and its standard
        error (delta method); exactly (0, 0) where no stray light was traced."""
        if not self.direct:
            return 0.0, 0.0
        q, se = strata_ratio_se(self.stray_strata())
        return 1.0 - q, se


def residual_variance(b, d: float) -> float:
    """The sample variance sum of the residuals Y = R - r G from the moments ``b`` centred on r0
    (:attr:`CellStats.b`, or one stratum's :attr:`CellStats.strata_b`), with d = r - r0:
    b0 - 2 d b1 + d^2 b2 (module docstring), at least 0."""
    return max(float(b[0] - 2.0 * d * b[1] + d * d * b[2]), 0.0)


def se_dof_many(stats: Sequence[CellStats]) -> np.ndarray:
    """:meth:`CellStats.se_dof` of many cells at once (the Welch-Satterthwaite sums vectorised over
    the cells, :func:`~roadgonio.engines.result.welch_satterthwaite_many`; one by one they were a
    sixth of the portable table's 0.05 s): one value per cell, NaN where the SE is not finite."""
    out = np.full(len(stats), math.nan)
    v, nu, starts, cells = [], [], [], []
    for i, st in enumerate(stats):
        ratio, se, _ = st.ratio_se()
        if not (math.isfinite(ratio) and math.isfinite(se)) or not st.strata_b:
            continue
        d = ratio - st.r0
        starts.append(len(v))
        cells.append(i)
        for k in sorted(st.strata_b):
            v.append(residual_variance(st.strata_b[k], d))
            nu.append(len(st.strata[k][0]) - 1.0)
    if cells:
        out[np.asarray(cells)] = welch_satterthwaite_many(v, nu, starts)
    return out


def strata_ratio_se(strata: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[float, float]:
    """Ratio sum(A) / sum(B) of paired replicate sums over independent strata, and its standard
    error by the delta method (module docstring): Var = sum_q B_q s_q^2(A - r B) / (sum B)^2.
    The stratified generalisation of :func:`roadgonio.engines.result.ratio_se`: with one stratum it
    is that estimator (written with sums, and the residuals' own mean removed); (nan, inf) when
    sum(B) is not positive, inf as the SE when a stratum has fewer than 2 replicates. One cell of
    :func:`strata_ratio_se_many` (the same numbers bit for bit)."""
    r, se = strata_ratio_se_many([strata])
    return float(r[0]), float(se[0])


def strata_ratio_se_many(cells: Sequence[Sequence[tuple[np.ndarray, np.ndarray]]]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`strata_ratio_se` of many cells at once (vectorised over all their strata; a table's
    cells cost ~0.1 s one by one, 7 % of the housed example's table): arrays of the ratios and
    their standard errors. Every sum runs in a fixed order (the replicates of a stratum, then the
    strata of a cell, in the order given), the same as :func:`add_strata`'s totals: a stratum's
    sums are those :class:`CellStats` accumulates, so A = R gives exactly its ratio."""
    ratio, se, _ = strata_ratio_se_dof_many(cells)
    return ratio, se


def strata_ratio_se_dof_many(cells: Sequence[Sequence[tuple[np.ndarray, np.ndarray]]]
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`strata_ratio_se_many` with the degrees of freedom of each SE (module docstring:
    Welch-Satterthwaite over the strata; NaN where the SE is not finite)."""
    m = len(cells)
    ratio, se, dof = np.full(m, math.nan), np.full(m, math.inf), np.full(m, math.nan)
    # a stratum without replicates adds nothing to the sums and leaves no variance estimate (SE inf)
    empty = np.array([any(len(a) == 0 for a, _ in c) for c in cells], dtype=bool)
    kept = [[(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)) for a, b in c if len(a)]
            for c in cells]
    live = [i for i in range(m) if kept[i]]                          # cells without strata: (nan, inf)
    if not live:
        return ratio, se, dof
    strata = [ab for i in live for ab in kept[i]]
    per_cell = np.array([len(kept[i]) for i in live], dtype=np.int64)
    m = len(live)
    counts = np.array([len(a) for a, _ in strata], dtype=np.int64)
    A = np.concatenate([a for a, _ in strata])
    B = np.concatenate([b for _, b in strata])
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    cstarts = np.r_[0, np.cumsum(per_cell)[:-1]]
    sa = np.add.reduceat(np.add.reduceat(A, starts), cstarts)
    sb = np.add.reduceat(np.add.reduceat(B, starts), cstarts)
    ok = sb > 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(ok, sa / np.where(ok, sb, 1.0), math.nan)
    seg = np.repeat(np.arange(len(strata)), counts)                 # stratum of each replicate
    cell_of = np.repeat(np.arange(m), per_cell)                     # cell of each stratum
    y = A - np.where(ok, r, 0.0)[cell_of][seg] * B
    dev = y - (np.add.reduceat(y, starts) / counts)[seg]
    with np.errstate(divide="ignore", invalid="ignore"):
        v = counts * np.add.reduceat(dev * dev, starts) / (counts - 1.0)
    single = (np.add.reduceat((counts < 2).astype(np.int64), cstarts) > 0) | empty[live]
    v0 = np.where(counts < 2, 0.0, v)            # a stratum of one replicate has no variance estimate
    var = np.add.reduceat(v0, cstarts)
    # the denominator's sum must itself be known (RATIO_DENOMINATOR_REL_SE_MAX), else no SE
    devb = B - (np.add.reduceat(B, starts) / counts)[seg]
    with np.errstate(divide="ignore", invalid="ignore"):
        vb = np.where(counts < 2, 0.0, counts * np.add.reduceat(devb * devb, starts) / (counts - 1.0))
        rel_b = np.sqrt(np.add.reduceat(vb, cstarts)) / np.where(ok, sb, 1.0)
    single = single | ~(rel_b <= RATIO_DENOMINATOR_REL_SE_MAX)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_err = np.sqrt(np.maximum(var, 0.0)) / np.abs(np.where(ok, sb, 1.0))
    # Welch-Satterthwaite over the cell's strata, B_q - 1 each (a stratum of one replicate: none)
    d_eff = welch_satterthwaite_many(v0, counts - 1.0, cstarts)
    idx = np.asarray(live)
    ratio[idx[ok]] = r[ok]
    good = ok & ~single
    se[idx[good]] = s_err[good]
    dof[idx[good]] = d_eff[good]
    return ratio, se, dof


def stray_ratios(stats: Sequence["CellStats"]) -> tuple[np.ndarray, ...]:
    """(direct ratio, its SE, stray fraction, its SE, the smaller of the two SEs' degrees of
    freedom) of many cells at once (:meth:`CellStats.direct_ratio_se`,
    :meth:`CellStats.stray_fraction_se`, the same numbers), of cells with stray light traced."""
    rd, rd_se, rd_dof = strata_ratio_se_dof_many([st.direct_strata() for st in stats])
    q, q_se, q_dof = strata_ratio_se_dof_many([st.stray_strata() for st in stats])
    return rd, rd_se, 1.0 - q, q_se, np.fmin(rd_dof, q_dof)


def add_strata(stats: Sequence[CellStats], pass_index: int, log2n: int, owner: np.ndarray, reps: np.ndarray,
               R: np.ndarray, G: np.ndarray, Rd: np.ndarray | None = None, Gd: np.ndarray | None = None) -> None:
    """Add one stratum (pass, log2 n) to several cells at once: replicate k belongs to
    ``stats[owner[k]]``; ``owner`` must be sorted (vectorised over the cells). With stray light,
    R and G are the totals and ``Rd``, ``Gd`` the direct light alone."""
    key = (int(pass_index), int(log2n))
    owner = np.asarray(owner, dtype=np.int64)
    R, G = np.asarray(R, dtype=np.float64), np.asarray(G, dtype=np.float64)
    reps = np.asarray(reps, dtype=np.int64)
    if len(owner) == 0:
        return
    if np.any(owner[1:] < owner[:-1]):
        raise ValueError("owner must be sorted")
    starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    counts = np.diff(np.r_[starts, len(owner)])
    sr, sg = np.add.reduceat(R, starts), np.add.reduceat(G, starts)
    cells = [stats[int(o)] for o in owner[starts]]
    for st in cells:
        if key in st.strata:
            raise ValueError(f"stratum {key} added twice")
    r0 = np.array([st.r0 if st.r0 is not None else (a / b if b > 0.0 else 0.0)
                   for st, a, b in zip(cells, sr, sg)])
    seg = np.repeat(np.arange(len(starts)), counts)
    Y0 = R - r0[seg] * G
    y = Y0 - (np.add.reduceat(Y0, starts) / counts)[seg]
    g = G - (sg / counts)[seg]
    c = np.where(counts > 1, counts / np.maximum(counts - 1.0, 1.0), 0.0)
    moments = np.stack([np.add.reduceat(y * y, starts), np.add.reduceat(y * g, starts),
                        np.add.reduceat(g * g, starts)], axis=1) * c[:, None]
    for k, st in enumerate(cells):
        a, b = starts[k], starts[k] + counts[k]
        st.strata[key] = (reps[a:b], R[a:b], G[a:b])
        if Rd is not None:
            st.direct[key] = (np.asarray(Rd[a:b], dtype=np.float64), np.asarray(Gd[a:b], dtype=np.float64))
        st.samples += int(counts[k]) << key[1]
        st.passes = len({q[0] for q in st.strata})
        st.sum_r += float(sr[k])
        st.sum_g += float(sg[k])
        if st.r0 is None:
            st.r0 = float(r0[k])
        if counts[k] < 2:
            st.single = True
        else:
            st.b = st.b + moments[k]
            st.strata_b[key] = moments[k]


def relative(ratio: float, se: float) -> float:
    if ratio != 0.0 and math.isfinite(ratio):
        return abs(se / ratio)
    return 0.0 if se == 0.0 else math.inf


@dataclass
class Plan:
    """What every cell got: ``cells[i]`` is a list of (pass, log2 n, replicates) for the i-th cell of
    the ``compute`` call. Replaying a plan (same seed) gives the same random numbers to every table
    with the same number of cells (common random numbers)."""

    cells: list[list[tuple[int, int, int]]]

    def to_dict(self) -> dict:
        return {"cells": [[list(e) for e in c] for c in self.cells]}

    @classmethod
    def from_dict(cls, d) -> "Plan":
        if isinstance(d, Plan):
            return d
        return cls([[tuple(int(x) for x in e) for e in c] for c in d["cells"]])

    @property
    def passes(self) -> int:
        return 1 + max((e[0] for c in self.cells for e in c), default=-1)

    def pass_requests(self, p: int) -> dict[int, tuple[int, int]]:
        """cell index -> (log2 n, replicates) in pass p."""
        out = {}
        for i, c in enumerate(self.cells):
            for e in c:
                if e[0] == p:
                    out[i] = (e[1], e[2])
        return out


class Planner:
    """Decides each pass's lattice size and replicates per active cell (module docstring).
    ``first_pass`` has no default here: the backend's (``DEFAULT_FIRST_PASS``) is the one place that
    sets it (an own default of 1024 outlived session 25's change to 4096)."""

    def __init__(self, rel_se: float, *, first_pass: int, min_replicates: int = 16,
                 max_samples: int = 1 << 28, min_passes: int = 1, max_log2: int = MAX_LOG2,
                 max_growth: float = MAX_GROWTH, stray_search: bool = False):
        self.rel_se = float(rel_se)
        #: the statistic a cell converges on: "lambert" (R / G, the Lambert calibration's) or
        #: "absolute" (R / G_d with stray light: :meth:`CellStats.absolute_ratio_se`)
        self.statistic = "lambert"
        #: the scene holds reflecting parts: a cell's stray light must be seen (:data:`STRAY_SEEN_MIN`)
        self.stray_search = bool(stray_search)
        self.max_growth = float(max_growth)
        self.min_replicates = max(2, int(min_replicates))
        self.max_samples = int(max_samples)
        self.min_passes = max(1, int(min_passes))
        self.max_log2 = int(max_log2)
        self.first_log2 = self.log2_for(first_pass / self.min_replicates)

    def log2_for(self, points: float) -> int:
        """log2 of the largest power of two <= ``points``, within the lattice table."""
        k = int(math.floor(math.log2(max(points, 1.0))))
        return int(min(max(k, MIN_LOG2), self.max_log2))

    def cell_rel(self, st: CellStats) -> float:
        """The relative SE of the statistic the cell reports (:attr:`statistic`); inf while the
        Lambert sum itself is not yet known well enough for an SE (:meth:`CellStats.ratio_se`).
        (User audit, session 43: an absolute-calibrated housed cell stopped on the Lambert ratio and
        said "converged" at twice the SE asked for, ten times for a Lambertian sample.)"""
        ratio, se, _ = st.ratio_se()
        if self.statistic == "absolute" and st.direct and math.isfinite(se):
            ratio, se = st.absolute_ratio_se()
        return relative(ratio, se)

    def first(self, n_cells: int) -> dict[int, tuple[int, int]]:
        return {i: (self.first_log2, self.min_replicates) for i in range(n_cells)}

    def next(self, stats: Sequence[CellStats], active: Iterable[int]) -> tuple[dict[int, tuple[int, int]], dict]:
        """Requests of the next pass for the cells still ``active`` and the decisions taken:
        ``{"converged": [...], "capped": [...]}`` (cells leaving the active set)."""
        requests: dict[int, tuple[int, int]] = {}
        done = {"converged": [], "capped": []}
        for i in active:
            st = stats[i]
            rel = self.cell_rel(st)
            room = self.max_samples - st.samples
            last = max((k[1] for k in st.strata), default=self.first_log2)
            if rel <= self.rel_se and st.passes >= self.min_passes:
                seen = st.stray_seen() if self.stray_search else None
                if seen is None or seen >= STRAY_SEEN_MIN:
                    done["converged"].append(i)
                    continue
                if st.samples >= STRAY_SEARCH_MAX or room < (1 << MIN_LOG2) * self.min_replicates:
                    # none ever seen: no stray light to speak of; seen rarely: the SE is not to be trusted
                    done["converged" if st.stray_never_seen() else "capped"].append(i)
                    continue
                want = self.max_growth * st.samples      # the SE is met without the stray light seen: look further
            elif room < (1 << MIN_LOG2) * self.min_replicates:
                done["capped"].append(i)
                continue
            elif math.isfinite(rel) and rel > self.rel_se:
                want = self.more_samples(st, rel, last) * SAFETY
            elif math.isfinite(lit := st.lambert_rel_se()) and lit > RATIO_DENOMINATOR_REL_SE_MAX:
                # too few samples carry the light for an SE: the Lambert sum's 1/N rule
                want = st.samples * ((lit / RATIO_DENOMINATOR_REL_SE_MAX) ** 2 - 1.0) * SAFETY
            else:
                want = st.samples          # min_passes not reached, or no SE yet: as much again
            want = min(max(want, (1 << MIN_LOG2) * self.min_replicates), room, self.max_growth * st.samples)
            # never a smaller lattice than before: its points would be worth less than the ones the
            # cell has, and the pooled mean weighs every point alike
            log2n = max(self.log2_for(want / self.min_replicates), min(last, self.log2_for(room / self.min_replicates)))
            reps = max(self.min_replicates, int(math.ceil(want / (1 << log2n))))
            reps = min(reps, max(self.min_replicates, room >> log2n))
            requests[i] = (log2n, reps)
        return requests, done


    def more_samples(self, st: CellStats, rel: float, last: int) -> float:
        """Samples to add so that the pooled relative SE reaches the target: with a = (rel/target)^2
        and b = a N v_new / V (v_new the per-point variance expected of the new points, V = N v the
        current total), the pooled variance (V + N_new v_new) / (N + N_new)^2 meets the target for
        x = N_new / N >= ((b - 2) + sqrt((b - 2)^2 - 4 (1 - a))) / 2 (x = a - 1 if v_new = v). The
        new points are expected to be as good as the cell's last lattice, or better by the rate
        :data:`LATTICE_GAIN_MAX` at most, as measured between its last two lattice sizes."""
        a = (rel / self.rel_se) ** 2
        pv = st.point_variances()
        N = st.samples
        total = sum(v * (1 << k) * len(st.strata[key][0]) for (k, v), key in zip(pv, sorted(st.strata_b)))
        if not pv or not total > 0.0:
            return N * (a - 1.0)
        v_last = pv[-1][1]
        gamma = 0.0
        sizes = {}
        for k, v in pv:
            sizes[k] = v                                   # the latest estimate of each size
        ks = sorted(sizes)
        if len(ks) >= 2 and sizes[ks[-1]] > 0.0 and sizes[ks[-2]] > 0.0:
            gamma = math.log(sizes[ks[-2]] / sizes[ks[-1]]) / ((ks[-1] - ks[-2]) * math.log(2.0))
            gamma = min(max(gamma, 0.0), LATTICE_GAIN_MAX)
        x = a - 1.0
        for _ in range(2):                                 # the new size depends on the answer
            log2n = max(self.log2_for(N * x / self.min_replicates), last)
            v_new = v_last * 2.0 ** (-gamma * (log2n - pv[-1][0]))
            b = a * N * v_new / total
            disc = (b - 2.0) ** 2 - 4.0 * (1.0 - a)
            x = max(((b - 2.0) + math.sqrt(max(disc, 0.0))) / 2.0, 0.0)
        return N * x


def covariance(stats: Sequence[CellStats], ratios: Sequence[float]) -> np.ndarray:
    """Covariance matrix of the ratios of ``stats`` (module docstring), float64: per stratum (pass,
    lattice size), n_common x the sample covariance of two cells' residuals over the replicates they
    share. Cells with the same replicates form one block, computed as one matrix product (a correction
    asks it of a 396-cell table: the pairwise loop took 2.8 s against the table's 0.04 s)."""
    m = len(stats)
    res = [st.residuals(r) for st, r in zip(stats, ratios)]
    sg = np.array([st.totals()[1] for st in stats])
    cov = np.zeros((m, m))
    keys: dict[tuple[int, int], dict[bytes, list[int]]] = {}
    for i, r in enumerate(res):
        for k, (reps, _) in r.items():
            keys.setdefault(k, {}).setdefault(np.asarray(reps).tobytes(), []).append(i)
    for k, groups in keys.items():
        blocks = []
        for members in groups.values():
            reps = np.asarray(res[members[0]][k][0])
            blocks.append((np.array(members), reps, np.vstack([res[a][k][1] for a in members])))
        for g, (ia, reps_a, ya) in enumerate(blocks):
            for ib, reps_b, yb in blocks[g:]:
                common, ca, cb = np.intersect1d(reps_a, reps_b, return_indices=True)
                n = len(common)
                if n < 2:
                    continue
                a = ya[:, ca] - ya[:, ca].mean(axis=1, keepdims=True)
                b = yb[:, cb] - yb[:, cb].mean(axis=1, keepdims=True)
                block = n * (a @ b.T) / (n - 1)
                cov[np.ix_(ia, ib)] += block
                if ib is not ia:
                    cov[np.ix_(ib, ia)] += block.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return cov / np.outer(sg, sg)
