"""What a k_A backend returns (docs/conventions.md section 5): :class:`CellResult`, one cell with
its precision, the :class:`KaBackend` protocol, the ideal point geometry (paper eq. 2, computed in
float64 numpy, never rendered) and the ratio-of-means standard error shared by the Monte Carlo
backends.

Each precision field has ONE meaning:

* ``se``: a standard error (Monte Carlo and randomised quasi-Monte Carlo backends);
* ``error_bound``: a deterministic bound on the part of the error that is not statistical: on
  |k_A - true k_A| for the quadrature (no ``se``); under absolute calibration a Monte Carlo result
  has one beside its ``se``, the error of eta = <E>/E_0, computed by float64 rules, not sampled (its
  files say so: ``runner.FIELD_ATTRS["error_bound_eta"]``);
* ``confidence_bound`` with ``confidence_level``: a statistical bound that holds with that
  probability (the RQMC reference: a Student-t interval of its replicates, beside its ``se``);
* ``se_dof``: the degrees of freedom of the standard errors as estimates (n - 1 for n independent
  replicates or batches, the Welch-Satterthwaite value over independent strata of them: the Mitsuba
  engine's passes). An error divided by an SE of few degrees of freedom follows Student's t, not a
  normal law (with 15, |z| > 4 in 0.12 % of cells, not 0.006 %): a coverage statement or a
  pass/fail from an SE takes the t quantile (:func:`t_equivalent`). NaN where there is no SE, or it
  is not an estimate (an exact 0).

Stray light (docs/conventions.md section 5, docs/straylight.md): ``k_a`` is everything the scene does; ``k_a_direct`` the k_A of the light
that reaches the footprint straight from the source alone, and ``stray_fraction`` =
1 - S_direct[f] / S_total[f] of the road sample, each with its standard error (``k_a_direct_se``,
``stray_fraction_se``). A backend that traces no stray light leaves them out: then ``k_a_direct``
is ``k_a`` (with ``se``: NaN for the quadrature, whose ``error_bound`` then bounds it) and the
stray fraction is 0 exactly (``stray_fraction_se`` = 0: an exact value, not a missing SE).

Fields that do not apply are NaN. A budget takes its standard uncertainty from
:meth:`CellResult.standard_uncertainty` (the SE, or a deterministic bound as a rectangular
distribution); a confidence bound is never divided by sqrt 3 or treated as an SE.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel


@dataclass(frozen=True)
class CellResult:
    """k_A at one cell with its precision (module docstring: each field has one meaning).

    ``converged`` is False when the backend stopped (sample or evaluation cap) before reaching its
    target; such a value must never be reported as agreeing with anything.
    """

    tan_eps: float
    beta_deg: float
    k_a: float
    se: float             # standard error of k_a; NaN if the backend gives none
    samples: int          # MC samples, or integrand evaluations for quadrature
    seconds: float
    extra: dict[str, Any] | None = None
    error_bound: float = math.nan         # deterministic bound of |k_a - true|; NaN otherwise
    converged: bool = True
    confidence_bound: float = math.nan    # statistical bound of |k_a - true| at confidence_level; NaN otherwise
    confidence_level: float = math.nan    # probability of confidence_bound (e.g. 0.999); NaN otherwise
    k_a_direct: float | None = None          # None: no stray light traced, = k_a
    k_a_direct_se: float | None = None       # None: = se
    stray_fraction: float | None = None      # None: 0 (no stray light traced)
    stray_fraction_se: float | None = None   # None: 0
    #: degrees of freedom of se (and of k_a_direct_se and stray_fraction_se, estimated from the same
    #: replicates: the smallest of their values); NaN where no SE is estimated (module docstring)
    se_dof: float = math.nan

    def __post_init__(self):
        # JSON (journal, outputs) carries NaN as null: read it back as NaN
        for name in ("k_a", "se", "error_bound", "confidence_bound", "confidence_level", "se_dof"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, math.nan)
        for name, default in (("k_a_direct", self.k_a), ("k_a_direct_se", self.se), ("stray_fraction", 0.0),
                              ("stray_fraction_se", 0.0)):
            if getattr(self, name) is None:
                object.__setattr__(self, name, float(default))
        if self.se == 0.0 and self.k_a_direct_se == 0.0 and self.stray_fraction_se == 0.0:
            # an exact 0 (a Lambertian sample under a Lambert calibration: every replicate the same) is no
            # estimate, so it has no degrees of freedom (user audit, session 29: se_dof 15 beside se 0)
            object.__setattr__(self, "se_dof", math.nan)

    @property
    def deterministic(self) -> bool:
        """True when the precision is a deterministic error bound (quadrature), not a standard error."""
        return not math.isfinite(self.se) and math.isfinite(self.error_bound)

    def standard_uncertainty(self) -> float:
        """The standard uncertainty of k_a for an uncertainty budget: the standard error, or for a
        deterministic bound b the rectangular-distribution value b / sqrt(3) (GUM, JCGM 100 4.3.7),
        or both in quadrature when a result has both (:func:`standard_uncertainty`). A confidence
        bound is not a standard uncertainty: a result that has one also has its SE."""
        return float(standard_uncertainty(self.se, self.error_bound, self.converged))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if d["extra"] is None:
            del d["extra"]
        for name in ("confidence_bound", "confidence_level", "se_dof"):   # journals of backends without one stay as they were
            if not math.isfinite(d[name]):
                del d[name]
        return d


def standard_uncertainty(se, error_bound, converged=True) -> np.ndarray:
    """:meth:`CellResult.standard_uncertainty` of arrays of ``se`` and ``error_bound`` (any shape,
    elementwise): the SE where it is finite, else the rectangular value ``error_bound / sqrt 3``; where
    both are finite (a Monte Carlo result under absolute calibration, its bound eta's error) the two
    in quadrature (GUM, independent components). Where a deterministic backend did not converge
    (``converged`` False, no SE) its ``error_bound`` is an estimate that can understate the error, no
    bound: it is taken whole, not as a rectangular half-width (review, session 39: divided by sqrt 3,
    an estimate of 0.0100 for an error of 0.0177 became a u of 0.0058)."""
    se = np.asarray(se, dtype=np.float64)
    bound = np.asarray(error_bound, dtype=np.float64)
    estimate = ~np.asarray(converged, dtype=bool) & ~np.isfinite(se)
    rect = np.where(estimate, bound, bound / math.sqrt(3.0))
    return np.where(np.isfinite(se), np.where(np.isfinite(rect), np.hypot(se, rect), se), rect)


class KaBackend(Protocol):
    """What a k_A backend provides. A backend whose ``compute`` also takes ``checkpoint=`` (a
    :class:`roadgonio.engines.runner.PassCheckpoint`, its state saved after every pass of a
    batched run) says so with the class attribute ``checkpoints_passes = True``; the table runner
    passes one only then (absent: False)."""

    name: str

    def settings(self) -> dict[str, Any]:
        """Settings for provenance (sample counts, tolerances, variant, seed...)."""

    def compute(self, cells: Sequence[tuple[float, float]],
                on_cell: Callable[[CellResult], None] | None = None) -> list[CellResult]:
        """k_A for each (tan eps, beta deg) cell; calls ``on_cell`` as each cell finishes."""


class CellByCellBackend:
    """Base of the backends that compute one cell at a time: subclasses define
    ``compute_cell(tan_eps, beta_deg) -> CellResult``; :meth:`compute` runs the cells in order and
    reports each as it finishes (so the table runner can journal it)."""

    def compute(self, cells: Sequence[tuple[float, float]],
                on_cell: Callable[[CellResult], None] | None = None) -> list[CellResult]:
        out = []
        for tan_eps, beta_deg in cells:
            res = self.compute_cell(float(tan_eps), float(beta_deg))
            out.append(res)
            if on_cell is not None:
                on_cell(res)
        return out


def ideal_ratio(model: RoadModel, instrument: Instrument, tan_eps: float, beta_deg: float) -> float:
    """f_road(nominal) / f_lambert = pi f_road(w_i(eps, beta), w_o(alpha, delta)), float64."""
    wi = instrument.w_i(tan_eps, beta_deg)
    wo = instrument.w_o()
    return float(math.pi * model.brdf(wi, wo))


def ideal_ratios(model: RoadModel, instrument: Instrument, cells: Sequence[tuple[float, float]]) -> np.ndarray:
    """:func:`ideal_ratio` of many cells at once (float64 array, one value per cell)."""
    from roadgonio.geometry import eps_from_tan, w_source
    c = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    wi = w_source(eps_from_tan(c[:, 0]), c[:, 1], instrument.observation.delta_deg)
    return math.pi * model.brdf(wi, instrument.w_o()[None, :])


def welch_satterthwaite(variances: Sequence[float], dofs: Sequence[float]) -> float:
    """Effective degrees of freedom of a sum of independent variance estimates v_i with nu_i
    degrees of freedom each (Welch-Satterthwaite, JCGM 100 G.4.1): (sum v_i)^2 / sum v_i^2 / nu_i.
    Terms with v_i = 0, or not finite, or with nu_i infinite (known exactly) add nothing to the
    denominator; NaN when no term has finite degrees of freedom (nothing estimated), and the sum of
    the nu_i when every estimate is 0. Never below the smallest nu_i of a term that counts. One
    group of :func:`welch_satterthwaite_many`."""
    v = np.asarray(variances, dtype=np.float64).ravel()
    if v.size == 0:
        return math.nan
    return float(welch_satterthwaite_many(v, dofs, np.zeros(1, dtype=np.int64))[0])


def welch_satterthwaite_many(variances, dofs, starts) -> np.ndarray:
    """:func:`welch_satterthwaite` of many groups of terms at once: the terms of group g are
    ``variances[starts[g]:starts[g + 1]]`` (``starts`` increasing, the first 0, every group
    non-empty), with their ``dofs``; an array of one value per group (a table's cells: their SEs
    sum independent strata, :func:`roadgonio.engines.mitsuba.passes.se_dof_many`)."""
    v = np.asarray(variances, dtype=np.float64).ravel()
    nu = np.asarray(dofs, dtype=np.float64).ravel()
    starts = np.asarray(starts, dtype=np.int64).ravel()
    ok_v = np.isfinite(v) & (v >= 0.0)
    est = ok_v & np.isfinite(nu) & (nu > 0.0)
    v0 = np.where(ok_v, v, 0.0)
    n_est = np.add.reduceat(est.astype(np.int64), starts)
    total = np.add.reduceat(v0, starts)
    with np.errstate(divide="ignore", invalid="ignore"):
        den = np.add.reduceat(np.where(est, v0 * v0 / np.where(est, nu, 1.0), 0.0), starts)
        nu_sum = np.add.reduceat(np.where(est, nu, 0.0), starts)
        out = np.where(den == 0.0, np.where(total == 0.0, nu_sum, math.inf), total * total / np.where(den == 0.0, 1.0, den))
    return np.where(n_est > 0, out, math.nan)


def t_equivalent(n_sigma: float, dof) -> np.ndarray | float:
    """The multiple of a standard error with ``dof`` degrees of freedom that a Student-t error
    exceeds (two-sided) with the probability a normal error exceeds ``n_sigma``: the threshold of a
    pass/fail or the coverage factor of an interval from such an SE (15 degrees of freedom: 4 ->
    5.48, 3 -> 3.76, 2 -> 2.20). ``n_sigma`` itself where ``dof`` is NaN or infinite (an SE without
    a count, or known exactly); elementwise over arrays."""
    from scipy.stats import norm, t as student_t
    d = np.asarray(dof, dtype=np.float64)
    p = float(norm.sf(n_sigma))
    with np.errstate(invalid="ignore"):
        k = np.where(np.isfinite(d) & (d > 0.0), student_t.isf(p, np.where(np.isfinite(d) & (d > 0.0), d, 1.0)),
                     float(n_sigma))
    return float(k) if k.ndim == 0 else k


#: The delta method's standard error of a ratio of means is an estimate only while the denominator's
#: mean is itself known well: at most this relative standard error (docs/validation.md, "When few
#: samples carry the light"). Beyond it the linearisation fails, and where most batches hold almost
#: no light (a beam far narrower than the angles at which the source sees the footprint) the
#: residuals of the dark batches are almost exactly 0 and the SE comes out near 0: k_A 1.0075 +-
#: 1.5e-16 for one lit replicate of 16 (session 34). Measured (``bench/bench_sparse_light.py``, 200
#: seeds): a beam of sigma 0.03 deg gave mean z^2 up to 367 without the limit, 1.0-1.2 with 0.05, 0.1
#: or 0.2; the wide preset's grazing cells reach 0.084 in the first pass (honest there: mean z^2
#: 1.17), where 0.05 cost 47 % more samples for nothing and 0.1 under 1 %.
RATIO_DENOMINATOR_REL_SE_MAX = 0.1


def denominator_rel_se(sum_sq_dev: float, total: float) -> float:
    """Relative standard error of a sum of independent batch values (or of their mean) from the
    unbiased variance estimate of that sum (``sum_sq_dev``) and the sum itself; inf where the sum is
    not positive. Compared with :data:`RATIO_DENOMINATOR_REL_SE_MAX` by every ratio-of-means SE."""
    if not total > 0.0:
        return math.inf
    return math.sqrt(max(float(sum_sq_dev), 0.0)) / float(total)


def _unit_scaled(values: np.ndarray) -> tuple[np.ndarray, float]:
    """``values / s`` and ``s``, the largest |value| (1 when that is 0 or not finite): squares of values
    near float64's smallest (a BRDF of 1e-170 in a lobe's far tail) underflow to 0, and an SE of 0 was
    stated for a result far from the truth (user audit: numpy-mc 4.01e18 +- 0 where the truth is 2.77e18)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    s = float(np.max(np.abs(v))) if v.size else 0.0
    if not (s > 0.0 and math.isfinite(s)):
        s = 1.0
    return v / s, s


def mean_rel_se(values: np.ndarray) -> float:
    """Relative standard error of the mean of independent batch values (:func:`denominator_rel_se`
    of their |sum|; inf with fewer than 2 values or a mean of 0)."""
    v, _ = _unit_scaled(values)
    n = v.size
    if n < 2:
        return math.inf
    dev = v - v.mean()
    return denominator_rel_se(n * float(dev @ dev) / (n - 1), abs(float(v.sum())))


def sparse_light_note(rel: float) -> str:
    """What a cell whose Lambert signal is known to worse than :data:`RATIO_DENOMINATOR_REL_SE_MAX`
    says (every Monte Carlo backend)."""
    return (f"the source's light reached the detector's footprint in too few samples for a standard error (the "
            f"Lambert signal itself is known to a relative SE of {rel:.2g}, more than "
            f"{RATIO_DENOMINATOR_REL_SE_MAX:g}): a beam much narrower than the angles at which the source sees the "
            "footprint, or a shade that lets light through rarely; no standard error can be stated for the value "
            "(docs/validation.md, \"When few samples carry the light\")")


def ratio_se(road: np.ndarray, lam: np.ndarray) -> tuple[float, float]:
    """Ratio of means <road>/<lam> of paired per-batch (or per-pixel) values and its standard error
    by the delta method, float64 (inf with fewer than 2 pairs, and inf where <lam> is itself known
    to worse than :data:`RATIO_DENOMINATOR_REL_SE_MAX`: no standard error can be stated there). The
    one statement for independent batches; :func:`roadgonio.engines.mitsuba.passes.strata_ratio_se`
    is its generalisation to independent strata of replicates (the Mitsuba engine's passes)."""
    road = np.asarray(road, dtype=np.float64).ravel()
    lam = np.asarray(lam, dtype=np.float64).ravel()
    n = road.size
    with np.errstate(invalid="ignore", divide="ignore"):       # 0/0: no light in any batch, NaN said
        ratio = road.mean() / lam.mean()
    if n < 2:
        return float(ratio), float("inf")
    if not mean_rel_se(lam) <= RATIO_DENOMINATOR_REL_SE_MAX:
        return float(ratio), float("inf")
    # the residuals in units of the largest values (:func:`_unit_scaled`), then scaled back
    r, sr = _unit_scaled(road)
    g, sg = _unit_scaled(lam)
    resid = r - (r.mean() / g.mean()) * g
    se = math.sqrt(np.sum(resid * resid) / (n - 1) / n) / abs(g.mean()) * (sr / sg)
    return float(ratio), float(se)
