"""Correcting a surface that is not eq. 4, with one instrument or several (docs/correction.md,
"Outside eq. 4"): the backbone (eq. 4, each variant fitted through the instruments) times the
correction surface (:mod:`roadgonio.correction.flexible`), and an uncertainty that covers the model.

Procedure (:func:`correct_surface`):

1. the backbone: every variant of ``variants`` fitted through all the instruments at once
   (:class:`roadgonio.engines.bundle.StackedForward`; stage A multi-start, the best by chi^2
   polished, at every rounding of the mirror plane (:func:`search_backbones`): the first rounding
   searched again while the data reject it (``SurfaceSettings.backbone_retries`` times at most, once
   by default: outside eq. 4 they always do), a later one started from the previous rounding's fits
   (``SurfaceSettings.warm_round_starts``);
2. k_A of the best backbone by the chosen backend through each instrument (journalled like
   ``roadgonio ka``), and the bundles' own error of it, ``rho = k_backend / k_bundle``;
3. for every variant, the correction surface through all the instruments (one surface shared by
   them), its smoothing parameters by the evidence; the variants are then weighed by their
   evidence (posterior model probabilities under equal priors; docs/correction.md), so a variant that fits
   much worse gets no weight; where the backend traces stray light (a housing), k_A depends on the
   surface beyond the footprint, so the backend renders the best variant's fitted surface
   (:class:`roadgonio.surface.correction_surface.CorrectedSurface`), rho is taken from that and the
   surfaces are refitted until a refit holds still (``surface_steps``);
4. per instrument, ln k_A and its covariance: the weighted mean over the variants of ln k_A of the
   corrected model (times rho); the covariance is the weighted posterior covariance of the surface
   and the backbone's coordinates (``surface``; :func:`roadgonio.correction.flexible.posterior_with_backbone`)
   plus the spread of the variants about the mean (``model``); where the normalised residuals have
   structure the two are widened by the local Birge ratio (``max(1, B_c)``, B_c^2 the
   leverage-corrected mean squared normalised residual over the neighbouring cells); plus the
   ray bundles' own noise through the fit (``bundle``, :func:`bundle_noise_covariance`), the backend's (``backend``) and
   what the instruments' blur hides below the surface's knots (``discrepancy``,
   :func:`discrepancy_covariance`, :mod:`roadgonio.correction.discrepancy`);
5. per instrument the corrected table r / k_A, and one table: per cell the generalised least
   squares combination of the instruments' r / k_A and (``SurfaceSettings.model_estimate``, the
   default) the fitted model's own value at the nominal geometry, with the full covariance between
   them (their surfaces are one, so their errors correlate). The model's value has no measurement
   noise; its errors are the surface's posterior and the discrepancy at the nominal direction,
   ``-delta(x0)`` (:func:`roadgonio.correction.discrepancy.nominal_blur`). Where the data show the
   surface smooth (small discrepancy) the model's value carries the cell and the table loses the
   noise; where the instrument resolves structure the knots cannot carry, r / k_A does.

Results: :class:`SurfaceCorrection` (the combined table, its budget, each instrument's
:class:`InstrumentPart`, the fits and their diagnostics); :func:`to_correction_result` gives the
classic :class:`roadgonio.correction.run.CorrectionResult` of a single instrument.
"""
from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from roadgonio.correction.budget import DEFAULT_U_MEASURED, Budget, functionals, local_birge, misalignment_covariance
from roadgonio.correction.fit import chi2_of
from roadgonio.correction.flexible import (SURFACE_FIT_VERSION, FlexPart, SurfaceFit, SurfaceSettings, fit_surface, one_blas_thread,
                                          posterior_with_backbone)
from roadgonio.engines.bundle import DEFAULT_RAYS, StackedForward
from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import VARIANTS, RoadModel
from roadgonio.surface.rtable import CORRECTED_R, RTable, measured_label

#: The backbone variants fitted and weighed by default.
DEFAULT_VARIANTS = ("power", "smooth")
#: A backbone whose evidence weight is below this adds nothing a printed digit could show to the
#: estimates or their covariance (its terms are the weight times ln k_A differences of order 1, and
#: its posterior covariance times the weight: below 1e-9 of the least u of 1e-3 relative): its
#: posterior over (theta, q), ln k_A Jacobians and model values are not computed, and it is left out
#: of the weighted sums (the weights of the rest are not renormalised; they sum to 1 - at most
#: 1e-9 per backbone left out). Its fit, evidence and weight are reported as every other's.
NEGLIGIBLE_WEIGHT = 1e-9
#: The factor on the fitted surface beyond the observation elevations the instruments saw whose
#: rendering gives k_A's sensitivity to the road there (d ln k_A / d ln f_r as the secant over ln 2;
#: single-bounce stray light is linear in it, paths that meet the road twice are not, and a secant
#: over a factor of 2 is about the range the component's ln 2 describes).
UNOBSERVED_PROBE = 2.0


@dataclass
class VariantFit:
    """One backbone (a model variant at one rounding of the mirror plane) with its correction surface."""

    variant: str
    backbone: RoadModel
    backbone_chi2: float
    fit: SurfaceFit
    parts: list[FlexPart]
    weight: float = 0.0
    #: posterior covariance over (theta, q), the backbone's coordinates free too
    #: (:func:`roadgonio.correction.flexible.posterior_with_backbone`)
    cov_full: np.ndarray | None = None
    #: the backbone's rounding at the mirror plane (deg; 0 = the cusp), held in its fit
    round_deg: float = 0.0

    @property
    def label(self) -> str:
        """The variant, and its rounding at the mirror plane where it has one."""
        return backbone_label(self.variant, self.round_deg)

    def summary(self) -> dict[str, Any]:
        return {"variant": self.variant, "mirror_round_deg": self.round_deg, "label": self.label,
                "weight": self.weight, "backbone_chi2": self.backbone_chi2,
                "backbone": self.backbone.to_json_dict(), **self.fit.summary()}


def backbone_label(variant: str, round_deg: float) -> str:
    """A backbone's name: its variant, with its rounding at the mirror plane when it is rounded."""
    return variant if round_deg == 0 else f"{variant} (rounded {round_deg:.3g} deg)"


def backbone_column(variant: str, round_deg: float) -> str:
    """:func:`backbone_label` as a column name (``k_a_<this>`` in correct_cells.csv): ``smooth``,
    ``smooth_rounded_1.12455deg`` (six digits: roundings 1.121 and 1.124 deg gave one name at three,
    one column overwriting the other)."""
    return variant if round_deg == 0 else f"{variant}_rounded_{round_deg:.6g}deg"


@dataclass
class InstrumentPart:
    """One instrument's view: its measured table, k_A and its corrected table."""

    instrument: Instrument
    measured: RTable
    u_measured: np.ndarray            # grid (sr^-1)
    u_what: str
    k_a: np.ndarray                   # grid, k_A of the corrected model (weighted over variants)
    k_backend: np.ndarray             # grid, backend k_A of the best backbone
    u_k_a_backend: np.ndarray         # grid, backend standard uncertainty of that k_A
    corrected: RTable
    u_corrected: np.ndarray           # grid (sr^-1), standard uncertainty of ``corrected``
    budget: Budget                    # of this instrument's own corrected table
    residual: np.ndarray              # grid, (simulated - measured) / u of the best variant
    birge_local: np.ndarray           # grid, local Birge ratio
    widening: np.ndarray              # grid, the factor on the surface and model components (>= 1)
    simulated: np.ndarray             # grid, simulated measured r of the best variant's corrected model
    model_r: np.ndarray               # grid, r of the best variant's corrected model at the nominal geometry
    surfaces: dict[str, np.ndarray]   # grids of g_C, its posterior sd and g_D at the cells (best variant)
    backend_info: dict[str, Any]
    before: dict[str, Any]
    after: dict[str, Any]
    #: grid, d ln k_A / d ln f_r of the road beyond the observation elevations the instruments saw
    #: (rendered; the budget's "unobserved" component); None where the backend traces no stray light
    unobserved_sensitivity: np.ndarray | None = None
    #: the part's name in the outputs when it is not its instrument's own (:func:`part_names`)
    label: str | None = None

    @property
    def name(self) -> str:
        """The instrument's name, unique among the parts of one correction (:func:`part_names`)."""
        return self.label or self.instrument.name


def part_names(instruments: Sequence[Instrument]) -> list[str]:
    """The name of each instrument of a correction in its outputs: its own, or where two share one (one
    instrument measuring twice, the case ``design --second-aperture`` compares against) the name and
    the measured table's place on the command line, ``portable_1``, ``portable_2`` (user audit, session
    42: correct_cells.csv had each of their columns twice, and a CSV reader kept the second only)."""
    names = [i.name for i in instruments]
    taken = {n for n in names if names.count(n) == 1}
    out = []
    for k, n in enumerate(names):
        if names.count(n) > 1:
            n = f"{n}_{k + 1}"
            while n in taken:                # the suffixed name is another instrument's own
                n += "_"
        taken.add(n)
        out.append(n)
    return out


@dataclass
class SurfaceCorrection:
    """The result of :func:`correct_surface`."""

    parts: list[InstrumentPart]
    corrected: RTable
    u_corrected: np.ndarray           # grid (sr^-1), standard uncertainty of ``corrected``
    budget: Budget                    # of the combined table (its measured cells, row-major)
    after: dict[str, Any]
    variants: list[VariantFit]
    settings: SurfaceSettings
    provenance: dict[str, Any]
    seconds: float
    timings: dict[str, float] = field(default_factory=dict)
    out: Path | None = None            # where the files were written (correction.files.correct_joint)
    written: list = field(default_factory=list)
    #: the backbone's outer steps (backend k_A, rho, the refit's predicted change; as correct_self's)
    steps: list = field(default_factory=list)
    #: with stray light in the backend: the fitted surface's own renderings, after each of which the
    #: surfaces were refitted with its rho (the rendered variant, rho, the refit's change of k_A over u,
    #: converged; empty without stray light)
    surface_steps: list = field(default_factory=list)
    #: grid: the weight of the fitted model's own value at the nominal geometry in the combined table
    #: (the rest is the instruments' r / k_A); None without SurfaceSettings.model_estimate
    model_weight: np.ndarray | None = None

    @property
    def best(self) -> VariantFit:
        return max(self.variants, key=lambda v: v.weight)

    @property
    def joint(self) -> bool:
        return len(self.parts) > 1

    def model_estimate_summary(self) -> dict[str, Any] | None:
        """How much the fitted surface's own value weighs in the corrected table (None without it)."""
        if self.model_weight is None:
            return None
        return {"what": "per cell, the weight of the fitted surface's own value at the nominal geometry in the "
                        "corrected table (the least-variance convex combination with the instruments' r / k_A: "
                        "generalised least squares where no weight is negative)",
                "weight_median": float(np.nanmedian(self.model_weight)),
                "weight_min": float(np.nanmin(self.model_weight)),
                "weight_max": float(np.nanmax(self.model_weight))}

    def summary(self) -> dict[str, Any]:
        a = self.after
        m = self.corrected.mask
        u = self.budget.u_rel()
        out = {"instruments": [p.name for p in self.parts], "cells": int(m.sum()),
               "S1": a["S1"], "u_S1": a.get("u_S1"), "Q0": a["Q0"], "u_Q0": a.get("u_Q0"), "S2": a["S2"],
               "u_S2": a.get("u_S2"), "class_R": a["class"]["R"], "class_C": a["class"]["C"],
               "nearest_table": a["nearest_table"], "nearest_table_basis": a.get("nearest_table_basis", ""),
               "Q0_note": a.get("Q0_note"), "u_rel_median": float(np.median(u)),
               "u_rel_max": float(np.max(u)), "budget": self.budget.summary(),
               "variants": [v.summary() for v in self.variants], "discrepancy": self.provenance.get("discrepancy"),
               "model_estimate": self.model_estimate_summary(),
               "backbone_steps": [{k: st[k] for k in ("step", "rho_min", "rho_max", "refit_change_over_u_max", "converged")}
                                  for st in self.steps],
               "surface_steps": [{k: st[k] for k in ("step", "variant", "rho_min", "rho_max",
                                                     "refit_change_over_u_max", "converged")}
                                 for st in self.surface_steps],
               "seconds": self.seconds, "timings": self.timings}
        out["per_instrument"] = [{
            "instrument": p.name, "measured": measured_label(p.measured), "cells": int(p.measured.mask.sum()),
            "k_a_min": float(np.nanmin(p.k_a)), "k_a_max": float(np.nanmax(p.k_a)),
            "birge_ratio": float(math.sqrt(np.nanmean(p.residual ** 2))),
            "birge_local_max": float(np.nanmax(p.birge_local)),
            "before": {k: p.before.get(k) for k in ("S1", "u_S1", "Q0", "u_Q0")},
            # its Q0 over its own cells only, when it measured part of the table (user audit, session 42)
            "Q0_note": p.before.get("Q0_note"),
            "after": {k: p.after.get(k) for k in ("S1", "u_S1", "Q0", "u_Q0")},
            "u_rel_median": float(np.median(p.budget.u_rel())), "backend": p.backend_info,
            "unobserved_sensitivity_max": (None if p.unobserved_sensitivity is None
                                           else float(np.nanmax(np.abs(p.unobserved_sensitivity))))}
            for p in self.parts]
        return out


# ----------------------------------------------------------------------------------------------
# Pieces
# ----------------------------------------------------------------------------------------------

def _grid(table: RTable, values: np.ndarray) -> np.ndarray:
    g = np.full(table.r.shape, np.nan)
    g[table.mask] = values
    return g


def _state_name(variant: str, round_deg: float) -> str:
    """The journal's name of a backbone (the cusp's as before the roundings, so old journals resume)."""
    return variant if round_deg == 0 else f"{variant}-round{round_deg:.6g}"


def _weights(log_ev: Sequence[float]) -> np.ndarray:
    a = np.asarray(log_ev, dtype=np.float64)
    w = np.exp(a - a.max())
    return w / w.sum()


def contributing(vfits: Sequence[VariantFit]) -> list[VariantFit]:
    """The backbones whose evidence weight reaches :data:`NEGLIGIBLE_WEIGHT`, in their order: the
    ones whose posterior, ln k_A and model values the estimates and their covariance are built
    from (the best always: its weight is at least 1 / len(vfits))."""
    return [vf for vf in vfits if vf.weight >= NEGLIGIBLE_WEIGHT]


def cell_key(cell) -> tuple[float, float]:
    """A (tan eps, beta) cell as a dictionary key that two tables' grids share (rounded to 1e-9)."""
    return (round(cell[0], 9), round(cell[1], 9))


def cell_index(cells) -> dict[tuple[float, float], int]:
    """Where each cell of ``cells`` is, by :func:`cell_key`."""
    return {cell_key(c): k for k, c in enumerate(cells)}


def combine(lnr: Sequence[np.ndarray], cells: Sequence[list], cov_big: np.ndarray,
            union: list) -> tuple[np.ndarray, np.ndarray]:
    """Per cell of ``union``, the least-variance convex combination (:func:`convex_weights`: the GLS
    one where no weight is negative) of the instruments' ln r that have the cell, with the 2x2 (or larger) covariance between them taken from ``cov_big`` (over the concatenated cells
    of all instruments). Returns (ln r combined, G) with combined = G @ concatenated ln r, so the
    combined covariance of any component C_big is ``G C_big G^T``."""
    offsets = np.cumsum([0] + [len(c) for c in cells])
    index = [cell_index(c) for c in cells]
    G = np.zeros((len(union), int(offsets[-1])))
    x = np.concatenate([np.asarray(v, dtype=np.float64) for v in lnr])
    for n, cell in enumerate(union):
        key = cell_key(cell)
        rows = [offsets[i] + index[i][key] for i in range(len(cells)) if key in index[i]]
        G[n, rows] = convex_weights(cov_big[np.ix_(rows, rows)])
    return G @ x, G


def convex_weights(S: np.ndarray) -> np.ndarray:
    """The weights w >= 0, sum 1, of the least-variance combination w^T x of estimates x with
    covariance ``S``: the GLS (best linear unbiased) weights when none is negative, else the best
    over the subsets of the estimates. Strongly correlated estimates of unequal variance give GLS
    weights outside [0, 1], a combined value outside the range of the estimates ("Peelle's
    pertinent puzzle" of data evaluation), which follows the covariance model exactly where it is
    least sure (a surface that does not fit: docs/correction.md, "The corrected table weighs the
    model's own value"); a convex combination never extrapolates, and its variance w^T S w,
    which the budget carries through G, is still exact for the weights used."""
    k = S.shape[0]
    best_w, best_v = np.full(k, 1.0 / k), math.inf
    for size in range(k, 0, -1):
        for subset in itertools.combinations(range(k), size):
            sub = np.ix_(subset, subset)
            try:
                v = np.linalg.solve(S[sub], np.ones(size))
            except np.linalg.LinAlgError:
                continue
            if not np.all(np.isfinite(v)) or v.sum() == 0:
                continue
            v = v / v.sum()
            if np.any(v < 0):
                continue
            w = np.zeros(k)
            w[list(subset)] = v
            var = float(w @ S @ w)
            if var < best_v:
                best_w, best_v = w, var
        if size == k and best_v < math.inf:
            return best_w               # the GLS weights are all >= 0: they are the optimum
    return best_w


def model_estimate_cells(cells: Sequence[list], union: list) -> list[tuple[int, int]]:
    """Per cell of ``union``, (part, index) of the first part whose ``cells`` have it: where the
    fitted model's own value at the nominal geometry is taken (it is the same surface in every part)."""
    index = [cell_index(c) for c in cells]
    out = []
    for key in union:
        i = next(i for i, ix in enumerate(index) if key in ix)
        out.append((i, index[i][key]))
    return out


def nominal_estimate(parts: Sequence[FlexPart], theta: np.ndarray,
                     nominal: Sequence[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """The fitted model's own estimate of ln r at the nominal geometry of the cells ``nominal``
    ((part, index) pairs, :func:`model_estimate_cells`) and its Jacobian in (theta, q), (cells,
    n_params + backbone coordinates; :meth:`roadgonio.correction.flexible.FlexPart.nominal_full_jacobian`)."""
    n_full = parts[0].n_params + len(parts[0].backbone_log_derivatives()[0])
    if not nominal:
        return np.zeros(0), np.zeros((0, n_full))
    used = sorted({i for i, _ in nominal})
    ln_r = {i: parts[i].ln_r_nominal(theta) for i in used}
    jac = {i: parts[i].nominal_full_jacobian() for i in used}
    return (np.array([ln_r[i][k] for i, k in nominal]),
            np.vstack([jac[i][k][None, :] for i, k in nominal]))


def _as_list(value, n: int, what: str) -> list:
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise InputError(f"expected one {what} per measured table ({n}), got {len(value)}", field=what)
        return list(value)
    return [value] * n


# ----------------------------------------------------------------------------------------------
# The procedure
# ----------------------------------------------------------------------------------------------

def search_backbones(forward, y: np.ndarray, u: np.ndarray, variants: Sequence[str], settings: SurfaceSettings, *,
                     state=None, seed: int = 0, name: str = "fit", say: Callable[[str], None] | None = None,
                     **fit_opts) -> tuple[dict[tuple[str, float], RoadModel], dict[tuple[str, float], float],
                                          dict[str, list[dict[str, Any]]]]:
    """The backbones of the surface route through ``forward`` (one instrument's or several stacked):
    every variant at every rounding of the mirror plane (``settings.backbone_rounds_deg``), each held
    in its own fit (:func:`roadgonio.correction.run.search_through_instrument`: stage A of every
    variant, the best polished). The first rounding is searched again while the data reject it, at
    most ``settings.backbone_retries`` times; a later one starts from the previous rounding's fit of
    every variant and ``settings.warm_round_starts`` fresh starts, once (None: searched like the
    first). Returns the backbones and their chi^2 by (variant, rounding), and the searches' records by
    rounding. ``fit_opts``: starts, polish, rounds of the search."""
    from roadgonio.correction import run as _run
    backbones: dict[tuple[str, float], RoadModel] = {}
    chi2: dict[tuple[str, float], float] = {}
    records: dict[str, list[dict[str, Any]]] = {}
    previous = None
    for r in settings.backbone_rounds_deg:
        warm = previous is not None and settings.warm_round_starts is not None
        opts = dict(fit_opts, starts=settings.warm_round_starts) if warm else dict(fit_opts)
        fits_r, chi2_r, _, searches = _run.search_through_instrument(
            forward, y, u, variants, state=state, seed=seed, name=name, say=say, fixed=settings.backbone_fixed(r),
            state_name=lambda v, r=r: _state_name(v, r), describe=lambda v, r=r: f"{backbone_label(v, r)} backbone",
            retries=0 if warm else settings.backbone_retries,
            start_models={v: backbones[(v, previous)] for v in variants} if warm else None, **opts)
        for v in variants:
            backbones[(v, r)], chi2[(v, r)] = fits_r[v], chi2_r[v]
        records[_state_name("backbone", r)] = searches
        previous = r
    return backbones, chi2, records


def correct_surface(tables: Sequence[RTable], instruments: Sequence[Instrument], *, u_measured: Any = DEFAULT_U_MEASURED,
                    sigma: Any = None, backend: str = "mitsuba", backend_settings: Mapping[str, Any] | None = None,
                    accuracy: str | None = None, factory=None, out_dir: str | Path | None = None,
                    artefacts: Sequence[Any] | None = None, rays: int = DEFAULT_RAYS, seed: int = 0,
                    starts: int | None = None, polish: int | None = None, rounds: int | None = None,
                    variants: Sequence[str] = DEFAULT_VARIANTS, settings: SurfaceSettings | None = None,
                    misalignment_rays: int = 256, max_outer: int | None = None, tol: float | None = None,
                    progress: bool = True) -> SurfaceCorrection:
    """Correct one measured table per instrument with one surface behind them all (module
    docstring). ``u_measured`` and ``sigma`` may be one value for all or one per table.
    ``max_outer`` (backend tables at most) and ``tol`` (in units of the measurement's u) stop the
    backbone's outer loop of step 2 (None: those of :func:`roadgonio.correction.run.correct_self`). The dense
    algebra runs with one BLAS thread (:func:`roadgonio.correction.flexible.one_blas_thread`)."""
    with one_blas_thread():
        return _correct_surface(tables, instruments, u_measured=u_measured, sigma=sigma, backend=backend,
                                backend_settings=backend_settings, accuracy=accuracy, factory=factory,
                                out_dir=out_dir, artefacts=artefacts, rays=rays, seed=seed, starts=starts,
                                polish=polish, rounds=rounds, variants=variants, settings=settings,
                                misalignment_rays=misalignment_rays, max_outer=max_outer, tol=tol,
                                progress=progress)


def _correct_surface(tables, instruments, *, u_measured, sigma, backend, backend_settings, accuracy, factory,
                     out_dir, artefacts, rays, seed, starts, polish, rounds, variants, settings, misalignment_rays,
                     max_outer, tol, progress) -> SurfaceCorrection:
    from roadgonio.correction import run as _run
    max_outer = _run.DEFAULT_MAX_OUTER if max_outer is None else int(max_outer)
    tol = _run.DEFAULT_TOL if tol is None else float(tol)
    if max_outer < 1 or not tol > 0:
        raise InputError(f"max_outer must be 1 or more and tol positive, got {max_outer} and {tol}", field="max_outer")
    t0 = time.perf_counter()
    tables, instruments = list(tables), list(instruments)
    if not tables or len(tables) != len(instruments):
        raise InputError(f"expected one instrument per measured table, got {len(tables)} table(s) and "
                         f"{len(instruments)} instrument(s)", field="instrument")
    variants = tuple(variants)
    bad = [v for v in variants if v not in VARIANTS]
    if not variants or bad:
        raise InputError(f"unknown model variant(s) {', '.join(bad) or '(none)'}; expected some of "
                         f"{', '.join(VARIANTS)}", field="model_variant")
    settings = settings or SurfaceSettings()
    u_specs = _as_list(u_measured, len(tables), "u_measured")
    for t in tables:
        _run.check_measured(t)
        _run._check_fit_cells(t)
    # each instrument's SPEC checked against its geometry on its cells, as `uncertainty` does (trial 12 D3)
    sigmas = [_run._sigma(s, inst, t) for s, inst, t in zip(_as_list(sigma, len(tables), "sigma"), instruments, tables)]
    u_grids = [_run.measured_uncertainty(s, t) for s, t in zip(u_specs, tables)]
    out = Path(out_dir) if out_dir is not None else None
    arts = list(artefacts) if artefacts is not None else [
        _run.InstrumentArtefacts(inst, rays=rays, seed=seed) for inst in instruments]
    lap = _run.Laps()
    timings = lap.timings

    names = [t.name for t in tables]
    label = " + ".join(names)
    _run._say(progress, f"{label}: ray bundles")
    fms = [a.forward(t.cells) for a, t in zip(arts, tables)]
    ys = [t.r[t.mask] for t in tables]
    us = [g[t.mask] for (g, _), t in zip(u_grids, tables)]
    stacked = StackedForward(fms)
    y_all, u_all = np.concatenate(ys), np.concatenate(us)
    lap("bundles")
    factory = factory or _run.default_factory(backend, backend_settings, accuracy)
    fit_opts = {k: v for k, v in (("starts", starts), ("polish", polish), ("rounds", rounds)) if v is not None}
    key_settings = {"variants": list(variants), "rays": [a.rays for a in arts], "seed": seed, **fit_opts,
                    "backend": backend, "backend_settings": dict(backend_settings or {}), "accuracy": accuracy,
                    # the factor on the unobserved road enters the budget only, after every journalled
                    # fit and rendering (its probe's journal has its own fingerprint): another factor
                    # resumes them all
                    "surface": {k: v for k, v in settings.to_dict().items() if k != "unobserved_sd_ln"},
                    "surface_fit": SURFACE_FIT_VERSION,
                    "max_outer": max_outer, "tol": tol, "instruments": [i.to_dict() for i in instruments[1:]]}
    state = _run._FitState(out, _run._state_key(_stack_tables(tables), np.concatenate(
        [g for g, _ in u_grids], axis=1), instruments[0], key_settings))

    # 1. the backbones through every instrument at once: every variant at every rounding of the
    #    mirror plane (SurfaceSettings.backbone_rounds_deg), each held in its own fit
    #    (search_backbones: stage A of every variant, the best polished; the first rounding searched
    #    again while the data reject it at most SurfaceSettings.backbone_retries times, by default
    #    once; a later one started from the previous rounding's fits). The best
    #    variant of every rounding is polished so that the roundings meet on equal terms (the evidence
    #    of an unpolished backbone's surface is lower: session 13, eq4 through A + B, the cusp's best
    #    unpolished lost to the rounded one polished)
    backbones, chi2, backbone_searches = search_backbones(
        stacked, y_all, u_all, variants, settings, state=state, seed=seed, name=label,
        say=lambda text: _run._say(progress, text), **fit_opts)
    main = min(chi2, key=chi2.get)
    polished = backbones[main]
    main_label = backbone_label(*main)
    lap("backbone")

    # 2. backend k_A of the best backbone through each instrument, the bundles' error rho, and the
    #    best backbone refitted with rho until the k_A it predicts holds still (correct_self's outer
    #    loop, the same tolerance): rho is far from 1 where the scene has light the bundles leave out
    #    (a housing's stray light), and k_A of a backbone fitted without it is then off (docs/correction.md,
    #    "A housed instrument")
    u_rel_all = u_all / y_all
    steps: list[dict[str, Any]] = []
    pred_change = np.zeros_like(y_all)
    def backend_k(models, k_bundles, step: int, what: str, saying: str):
        """The backend's k_A of ``models[i]`` through instrument i (journalled in ``_forward_dir``'s
        folder of ``what`` and ``step``), its SE, the run's info, rho = k_backend / ``k_bundles[i]`` and
        the relative covariance of ln k_A over the cells (:func:`roadgonio.correction.run.backend_covariance`),
        each a list over the instruments."""
        k_out, se_out, info_out, rho_out, cov_out = [], [], [], [], []
        for i, (inst, t, m, kb) in enumerate(zip(instruments, tables, models, k_bundles)):
            _run._say(progress, f"{label}: k_A of the {saying} through {inst.name} ({backend})"
                      + (f", step {step}" if step > 1 or what == "surface" else ""))
            jdir = None if out is None else out / _forward_dir(i, len(tables), step, what)
            k_b, se_b, info, cov_b = _run._backend_k(factory, inst, m, t.cells, jdir, progress)
            cov_out.append(cov_b)
            k_out.append(k_b)
            se_out.append(se_b)
            info_out.append(info)
            rho_out.append(k_b / kb)
        return k_out, se_out, info_out, rho_out, cov_out

    for it in range(1, max_outer + 1):
        k_back, se_back, infos, rhos, cov_back = backend_k([polished] * len(fms), [fm.k_a(polished) for fm in fms],
                                                           it, "backbone", f"{main_label} backbone")
        lap("backend")
        rho_all = np.concatenate(rhos)
        nxt = _run.refit_with_rho(state, f"refit-{it}", stacked, y_all, u_all, polished, rho_all, variant=main[0],
                                  seed=seed, label=label, fixed=settings.backbone_fixed(main[1]))
        pred_change = _run.predicted_change(stacked, nxt, rho_all, np.concatenate(k_back))
        worst = float(np.max(pred_change / u_rel_all))
        steps.append({"step": it, "model": polished.params.to_dict(), "backend": infos[0],
                      "rho_min": float(rho_all.min()), "rho_max": float(rho_all.max()),
                      "refit_change_over_u_max": worst, "converged": worst <= tol})
        lap("refit")
        if worst <= tol or it == max_outer:
            break
        polished = backbones[main] = nxt
    # every other backbone refitted with the same rho, so that the variants meet on equal terms
    # (a backbone fitted without a rho far from 1 loses evidence it would have, and the one that
    # was refitted wins for that alone)
    for key in backbones:
        if key != main:
            backbones[key] = _run.refit_with_rho(state, f"refit-{_state_name(*key)}", stacked, y_all, u_all,
                                                 backbones[key], rho_all, variant=key[0], seed=seed, label=label,
                                                 fixed=settings.backbone_fixed(key[1]))
    chi2 = {key: chi2_of(stacked, y_all, u_all, m, rho_all) for key, m in backbones.items()}
    lap("refit")

    # 3. the correction surface of every variant, and the variants' weights
    def fit_surfaces(rhos: list[np.ndarray], tag: str, starts: dict | None = None) -> list[VariantFit]:
        out_fits: list[VariantFit] = []
        warm: tuple | None = None
        for v, r in sorted(backbones, key=lambda x: x != main):  # the best backbone first: a warm start
            _run._say(progress, f"{label}: the correction surface over the {backbone_label(v, r)} backbone"
                      + (f" ({tag.strip('-')})" if tag else ""))
            parts = [FlexPart(fm, backbones[(v, r)], settings, rho) for fm, rho in zip(fms, rhos)]
            start = (starts or {}).get((v, r), warm)
            name = f"surface-{_state_name(v, r)}{tag}"
            sf = None
            journalled = state.get_surface(name)
            if journalled is not None:
                try:
                    sf = fit_surface(parts, ys, us, state=journalled)
                except (ValueError, KeyError, TypeError):
                    sf = None                      # a journal of other settings: fit again
            if sf is None:
                sf = fit_surface(parts, ys, us, theta0=None if start is None else start[0],
                                 lam0=None if start is None else start[1])
                state.put_surface(name, sf.state())
            if warm is None:
                warm = (sf.theta, list(sf.lam.values()))
            out_fits.append(VariantFit(v, backbones[(v, r)], chi2[(v, r)], sf, parts, round_deg=r))
        for vf, w in zip(out_fits, _weights([vf.fit.log_evidence for vf in out_fits])):
            vf.weight = float(w)
        return out_fits

    vfits = fit_surfaces(rhos, "")
    lap("surface")
    # 3b. where the backend traces light the bundles leave out (a housing's stray light), k_A depends on
    #     the surface beyond the footprint: the walls light it from every direction, and the road around
    #     the sample lights the walls. rho of the backbone is then not rho of the fitted surface (a
    #     surface outside eq. 4 through a bright housing: k_A up to 7 % off, docs/correction.md, "A
    #     surface outside eq. 4 through a housing"). So the backend renders the best variant's fitted surface itself, rho is
    #     taken from that rendering, and the surfaces are refitted with it, until a refit moves the
    #     k_A the fit uses (through the bundles, so that the renderings' noise does not enter the test)
    #     by at most tol u; at most max_outer renderings, the last change into u if it did not hold still.
    surface_steps: list[dict[str, Any]] = []
    surface_change = np.zeros_like(y_all)
    if any(info.get("stray") for info in infos):
        for it in range(1, max_outer + 1):
            cur = max(vfits, key=lambda v: v.weight)
            k_back, se_back, infos, rhos, cov_back = backend_k([p.corrected_surface(cur.fit.theta) for p in cur.parts],
                                                               [p.k_bundle(cur.fit.theta) for p in cur.parts], it,
                                                               "surface", f"fitted surface ({cur.label})")
            lnk_old = _weighted_lnk_bundles(vfits)
            lap("surface-backend")
            vfits = fit_surfaces(rhos, f"-s{it}", {(vf.variant, vf.round_deg): (vf.fit.theta, list(vf.fit.lam.values()))
                                                  for vf in vfits})
            lap("surface")
            surface_change = np.abs(_weighted_lnk_bundles(vfits) - lnk_old)
            worst = float(np.max(surface_change / u_rel_all))
            rr = np.concatenate(rhos)
            surface_steps.append({"step": it, "variant": cur.label, "backend": infos[0],
                                  "rho_min": float(rr.min()), "rho_max": float(rr.max()),
                                  "refit_change_over_u_max": worst, "converged": worst <= tol})
            if worst <= tol:
                break
    # 3c. the road beyond the observation elevations the instruments saw: stray light reads it there,
    #     no r-table measures it, and the fitted surface holds the backbone's behaviour (issue 19). k_A's
    #     sensitivity to it is rendered (the last rendered surface times UNOBSERVED_PROBE there, the same
    #     seed), and a common factor of standard uncertainty settings.unobserved_sd_ln enters the budget
    #     (docs/correction.md, "The road beyond the observation elevations")
    unobserved: list[np.ndarray] | None = None
    if surface_steps and settings.unobserved_sd_ln > 0.0:
        k_probe = backend_k([p.corrected_surface(cur.fit.theta, UNOBSERVED_PROBE) for p in cur.parts],
                            [p.k_bundle(cur.fit.theta) for p in cur.parts], 1, "unobserved",
                            f"fitted surface x {UNOBSERVED_PROBE:g} beyond the observation elevations")[0]
        unobserved = [np.log(kp / kb) / math.log(UNOBSERVED_PROBE) for kp, kb in zip(k_probe, k_back)]
        lap("surface-backend")
    live = contributing(vfits)
    weights = [1.0 / u ** 2 for u in us]          # the fit's, per instrument and cell
    for vf in live:
        vf.cov_full = posterior_with_backbone(vf.parts, vf.fit.theta, vf.fit.lam, weights,
                                              vf.fit.phi, vf.fit.d_scale)
    lap("surface")

    # 4. ln k_A of every instrument, and the covariance components of the estimates of ln r: every
    #    instrument's r / k_A (its cells one after the other), then (settings.model_estimate) the
    #    fitted model's own value at the nominal direction of every cell of the union
    n_i = [len(y) for y in ys]
    off = np.cumsum([0] + n_i)
    N = int(off[-1])
    union = sorted({cell_key(c) for t in tables for c in t.cells})
    nominal = model_estimate_cells([t.cells for t in tables], union) if settings.model_estimate else []
    U = len(nominal)
    lnk, lnp = np.zeros(N), np.zeros(U)
    lnk_v, jac_v, lnp_v, jp_v = [], [], [], []
    for vf in live:
        lk = np.concatenate([np.log(p.k_a(vf.fit.theta)) for p in vf.parts])
        K = np.vstack([p.lnk_full_jacobian(vf.fit.theta) for p in vf.parts])
        lp, Jp = nominal_estimate(vf.parts, vf.fit.theta, nominal)
        lnk_v.append(lk)
        jac_v.append(K)
        lnp_v.append(lp)
        jp_v.append(Jp)
        lnk += vf.weight * lk
        lnp += vf.weight * lp
    best = max(vfits, key=lambda v: v.weight)
    Jb = np.vstack([best.parts[i].simulate(best.fit.theta)[1] for i in range(len(fms))])
    leverage = np.einsum("ij,jk,ik->i", Jb, best.fit.cov, Jb) / u_all ** 2
    resid = np.concatenate(best.fit.residual)
    lb = [local_birge(t, resid[off[i]:off[i + 1]], leverage[off[i]:off[i + 1]]) for i, t in enumerate(tables)]
    birge = np.concatenate([b for b, _ in lb])
    widen = np.concatenate([w for _, w in lb])
    # the model's value at a cell is widened as much as the most widened instrument there
    index = [cell_index(t.cells) for t in tables]
    widen_all = np.concatenate([widen, [max(widen[off[i] + ix[union[j]]] for i, ix in enumerate(index)
                                            if union[j] in ix) for j in range(U)]])
    E = N + U
    surf = np.zeros((E, E))
    model = np.zeros((E, E))
    backend_cov = np.zeros((E, E))
    unobserved_v = np.zeros(E)
    # the backend's error of k_A (correlated between the cells of a table: they share its random
    # numbers) enters every estimate through rho: r / k_A directly, the fitted model's own value through
    # the fit (user audit, session 24: counted on r / k_A alone and as independent cells, the joint
    # table's backend u was 0.001 % while the table moved by 0.09 % with the seed)
    cov_b = np.zeros((N, N))
    for i, c in enumerate(cov_back):
        cov_b[off[i]:off[i + 1], off[i]:off[i + 1]] = c
    bundle_cov = np.zeros((E, E))
    for vf, lk, K, lp, Jp in zip(live, lnk_v, jac_v, lnp_v, jp_v):
        A = rho_shift_map(vf, weights, K, Jp)
        backend_cov += vf.weight * (A @ cov_b @ A.T)
        bundle_cov += vf.weight * bundle_noise_covariance(vf, ys, weights, K, Jp)
        if unobserved is not None:
            unobserved_v += vf.weight * (A @ np.concatenate(unobserved))
        J = np.vstack([-K, Jp])                   # d (ln r estimate) / d (theta, q): ln y - ln k_A, the model's value
        surf += vf.weight * (J @ vf.cov_full @ J.T)
        d = np.concatenate([-(lk - lnk), lp - lnp])
        model += vf.weight * np.outer(d, d)
    surf *= np.outer(widen_all, widen_all)
    model *= np.outer(widen_all, widen_all)
    disc = None
    if settings.discrepancy_ell is not None:
        disc, disc_info = discrepancy_covariance(vfits, best, settings, nominal)
    for vf in vfits:
        for p in vf.parts:
            p.forget_backbone_derivatives()
    lap("covariance")

    # misalignment (per instrument, independent between instruments)
    mis_blocks, mis_info = [], []
    for inst, t, sg in zip(instruments, tables, sigmas):
        if sg is None:
            mis_blocks.append(None)
            mis_info.append(None)
            continue
        _run._say(progress, f"{label}: misalignment sensitivities of {inst.name}")
        c, info = misalignment_covariance(polished, inst, t, sg, rays=misalignment_rays, seed=seed)
        mis_blocks.append(c)
        mis_info.append(info)
    lap("misalignment")

    # 5. the corrected tables, per instrument and combined
    comps: dict[str, np.ndarray] = {}
    meas = np.concatenate([u / y for u, y in zip(us, ys)])
    pad = np.zeros(U)                             # the model's own value has no measurement error
    comps["measurement"] = np.diag(np.concatenate([meas, pad]) ** 2)
    comps["backend"] = backend_cov
    comps["surface"] = surf
    comps["model"] = model
    comps["bundle"] = bundle_cov
    if disc is not None:
        comps["discrepancy"] = disc
    if unobserved is not None:
        comps["unobserved"] = settings.unobserved_sd_ln ** 2 * np.outer(unobserved_v, unobserved_v)
    if surface_steps:                              # the surface's own loop has the last word on k_A
        if not surface_steps[-1]["converged"]:
            comps["convergence"] = np.diag(np.concatenate([surface_change / math.sqrt(3.0), pad]) ** 2)
    elif not steps[-1]["converged"]:
        comps["convergence"] = np.diag(np.concatenate([pred_change / math.sqrt(3.0), pad]) ** 2)
    if any(b is not None for b in mis_blocks):
        M = np.zeros((E, E))
        for i, b in enumerate(mis_blocks):
            if b is not None:
                M[off[i]:off[i + 1], off[i]:off[i + 1]] = b
        comps["misalignment"] = M
    notes = {"measurement": "the measured tables' own standard uncertainty (--u-measured), independent cells",
             "backend": f"{backend} k_A of the " + ("fitted surface" if surface_steps else f"{main_label} backbone")
                        + ": its standard uncertainty, "
                        + ("with the correlation between cells the backend measured (they share its random numbers)"
                           if all(info.get("cells_correlated") for info in infos) else "independent cells")
                        + ", through rho into r / k_A and through the fit into the model's own value",
             "surface": "posterior of the correction surface (evidence-weighted over the variants), widened by "
                        "the local Birge ratio where the residuals have structure",
             "model": "spread of the backbones' (variants', roundings') corrected k_A (and model values) about their "
                      "evidence-weighted mean",
             "bundle": "the ray bundles' own noise (their replicates), through the fit, to first order: into k_A at "
                       "the fitted surface and into the surface and backbone the fit finds, and so into both estimates "
                       "(docs/correction.md, 'What the ray bundles move')",
             "convergence": "change of k_A the last refit (of the backbone, or with stray light of the surfaces) "
                            "still made (rectangular; the fitted model's own value left out)",
             "misalignment": "instrument geometric errors (--sigma), first-order GUM",
             "unobserved": f"the road beyond the observation elevations the instruments saw, which stray light "
                           f"reads and no r-table measures: one factor common to all of it, of standard uncertainty "
                           f"{settings.unobserved_sd_ln:.3g} in ln f_r, times k_A's rendered sensitivity to it",
             "discrepancy": "structure of the surface finer than the correction surface's knots, which the "
                            "instruments blur: var(delta(c) - (K delta)(c)) of a Gaussian process delta over the "
                            "incident direction, its amplitude what the evidence-chosen roughness prior of the surface puts "
                            "beyond the knots' Nyquist wavenumber"}
    lnr = [np.log(y) - lnk[off[i]:off[i + 1]] for i, y in enumerate(ys)]
    parts_out: list[InstrumentPart] = []
    labels = part_names(instruments)
    for i, (inst, t) in enumerate(zip(instruments, tables)):
        sl = slice(off[i], off[i + 1])
        bud = Budget(n_i[i])
        for name, C in comps.items():
            bud.add(name, C[sl, sl], notes[name])
        k_grid = _grid(t, np.exp(lnk[sl]))
        corr = t.with_values(_grid(t, np.exp(lnr[i])), name=f"{t.name}_corrected",
                             source=f"{measured_label(t)} {CORRECTED_R}; eq. 4 x correction surface "
                                    f"fitted through {', '.join(i2.name for i2 in instruments)}; instrument {inst.name})")
        u_abs = _grid(t, np.exp(lnr[i]) * bud.u_rel())
        before_b = Budget(n_i[i])
        before_b.add("measurement", meas[sl])
        if mis_blocks[i] is not None:
            before_b.add("misalignment", mis_blocks[i])
        sim = np.concatenate([p.simulate(best.fit.theta, jacobian=False)[0] for p in best.parts])[sl]
        bp = best.parts[i]
        surfs = {k: _grid(t, v) for k, v in bp.surfaces_at_cells(best.fit.theta, best.fit.cov).items()}
        model_r = _grid(t, np.exp(bp.ln_r_nominal(best.fit.theta)))
        parts_out.append(InstrumentPart(
            instrument=inst, measured=t, u_measured=u_grids[i][0], u_what=u_grids[i][1], k_a=k_grid,
            k_backend=_grid(t, k_back[i]), u_k_a_backend=_grid(t, se_back[i]), corrected=corr,
            u_corrected=u_abs,
            budget=bud, residual=_grid(t, resid[sl]), birge_local=_grid(t, birge[sl]),
            widening=_grid(t, widen[sl]), simulated=_grid(t, sim),
            model_r=model_r, surfaces=surfs, backend_info=infos[i], before=functionals(t, before_b.total()),
            after=functionals(corr, bud.total()),
            unobserved_sensitivity=None if unobserved is None else _grid(t, unobserved[i]),
            label=None if labels[i] == inst.name else labels[i]))
    base = tables[0]
    model_weight = None
    if len(tables) == 1 and not U:
        combined, comb_budget = parts_out[0].corrected, parts_out[0].budget
        u_comb = parts_out[0].u_corrected
    else:
        total = sum(comps.values())
        lnc, G = combine(lnr + ([lnp] if U else []), [t.cells for t in tables] + ([union] if U else []),
                         total, union)
        grid = np.full(base.r.shape, np.nan)
        for (t_, b_), v in zip(union, lnc):
            grid[int(np.argmin(np.abs(base.tan_eps - t_))), int(np.argmin(np.abs(base.beta_deg - b_)))] = math.exp(v)
        # the measured tables first (name and digest): road matches a u file to its table by this line, and
        # two sites' files of one name through one instrument wrote the same one (user audit, session 40)
        src = (f"{' + '.join(measured_label(t) for t in tables)}: one surface measured by {', '.join(i.name for i in instruments)}, {CORRECTED_R} "
               f"per instrument{' and the fitted surface at the nominal geometry' if U else ''}, combined "
               f"cell by cell with the least-variance non-negative weights)")
        combined = base.with_values(grid, name=f"{label}_corrected", source=src)
        # the combined table's cells in row-major order (= union order sorted like RTable.cells)
        at = cell_index(union)
        order = [at[cell_key(c)] for c in combined.cells]
        Gm = G[order]
        comb_budget = Budget(len(order))
        for name, C in comps.items():
            comb_budget.add(name, Gm @ C @ Gm.T, notes[name])
        u_comb = _grid(combined, combined.r[combined.mask] * comb_budget.u_rel())
        if U:
            model_weight = _grid(combined, np.asarray(G[order][:, N:].sum(axis=1)))
    after = functionals(combined, comb_budget.total())
    lap("assemble")
    from roadgonio.provenance import provenance
    prov = provenance(instrument=instruments[0], model=polished, backend=infos[0]["backend"],
                      settings=infos[0]["settings"], reference="self (eq. 4 backbone x correction surface)",
                      instruments=[i.to_dict() for i in instruments], u_measured=[w for _, w in u_grids],
                      surface=settings.to_dict(), variants_asked=list(variants), variant_best_backbone=main[0],
                      mirror_round_best_backbone_deg=main[1],
                      bundles=[fm.bundles.summary() for fm in fms], misalignment=mis_info,
                      calibration=[i.calibration.to_dict() for i in instruments],
                      forward_model_limits=_run.forward_model_limits(instruments),
                      discrepancy=disc_info if disc is not None else None,
                      backbone_searches=backbone_searches)
    return SurfaceCorrection(parts=parts_out, corrected=combined, u_corrected=u_comb, budget=comb_budget, after=after,
                             variants=vfits, settings=settings, provenance=prov, seconds=time.perf_counter() - t0,
                             timings=timings, model_weight=model_weight, steps=steps, surface_steps=surface_steps)


def rho_shift_map(vf: VariantFit, weights: Sequence[np.ndarray], K: np.ndarray, Jp: np.ndarray) -> np.ndarray:
    """d (ln r estimates) / d (ln rho of the parts' cells, concatenated), to first order through the
    fit: when ln rho moves by s (the backend's own error of k_A, or the stray light of a road the
    tables do not measure), the simulated readings move by m s, the surface and the backbone's
    coordinates by d = -C J^T W (m s) (C the posterior covariance over (theta, q), J the readings'
    Jacobian, W the weights), so ln k_A moves by s + K d and the model's own values by Jp d. Returns
    the (instruments' estimates ln y - ln k_A, then the model's values) x (cells) matrix
    [-(I + K D); Jp D], D = -C J^T W m: the model estimate follows the instruments (a surface fitted
    with the wrong rho is off by it), so weighing the two does not dilute this error."""
    cols = []
    for p, w in zip(vf.parts, weights):
        m, J = p.simulate(vf.fit.theta)
        Jq, _, _ = p.backbone_jacobians(vf.fit.theta)
        cols.append(np.hstack([J, Jq]).T * (np.asarray(w) * m)[None, :])
    D = -(vf.cov_full @ np.hstack(cols))
    return np.vstack([-(np.eye(D.shape[1]) + K @ D), Jp @ D])


def bundle_noise_covariance(vf: VariantFit, measured: Sequence[np.ndarray], weights: Sequence[np.ndarray],
                            K: np.ndarray, Jp: np.ndarray) -> np.ndarray:
    """Covariance of the estimates (the instruments' ln y - ln k_A, then the model's values; as
    :func:`rho_shift_map`) from the ray bundles' own noise, to first order through the fit (session
    26: only the bundles' seed varied, the table moved 25-50 times more than their error of k_A at a
    fixed surface, which is all the budget had). Per replicate b of the bundles
    (:meth:`FlexPart.replicate_deviations`, the same replicate of every instrument together: they share
    their unit points), the readings' ln deviation m_b and their Jacobian's J_b move the fit's
    normal equations J^T W (y - s) = Lambda theta, so (theta, q) moves by
    d_b = C (J_b^T W (y - s) - J^T W (s m_b)), C the posterior covariance over (theta, q); ln k_A moves
    by m_b + K d_b and the model's values by Jp d_b. The covariance of the whole bundle's estimate is
    sum_b e_b e_b^T / (R (R - 1)) (the replicates' mean)."""
    devs = [p.replicate_deviations(vf.fit.theta) for p in vf.parts]
    R = devs[0][2].shape[0]
    est = []
    for r in range(R):
        rhs = 0.0
        for (s, Jf, d_ln, d_jac), y, w in zip(devs, measured, weights):
            w = np.asarray(w, dtype=np.float64)
            rhs = rhs + d_jac[r].T @ (w * (np.asarray(y) - s)) - Jf.T @ (w * s * d_ln[r])
        d = vf.cov_full @ rhs
        m = np.concatenate([dev[2][r] for dev in devs])
        est.append(np.concatenate([-(m + K @ d), Jp @ d]))
    E = np.array(est)
    return E.T @ E / (R * (R - 1))


def rho_shift_effect(vf: VariantFit, shift: Sequence[np.ndarray], weights: Sequence[np.ndarray], K: np.ndarray,
                     Jp: np.ndarray) -> np.ndarray:
    """d (ln r estimates) / d x when ln rho of part i's cells moves by ``shift[i]`` x (the stray light
    of a road the tables do not measure: the "unobserved" component): :func:`rho_shift_map` times the
    shift."""
    return rho_shift_map(vf, weights, K, Jp) @ np.concatenate(shift)


def discrepancy_covariance(vfits: Sequence[VariantFit], best: VariantFit, settings: SurfaceSettings,
                           nominal: Sequence[tuple[int, int]] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """The ``discrepancy`` component over the concatenated cells of the instruments
    (:mod:`roadgonio.correction.discrepancy`): the bracket through each instrument's blur at the best
    variant's surface, scaled per cell by sigma_c, sigma_c^2 the evidence-weighted mean over the
    variants of what their smoothing parameters put beyond the knots' Nyquist wavenumber in the
    cell's region; ``nominal``: the model's own estimates after the instruments' cells
    (:func:`parts_discrepancy`). Returns (covariance, info)."""
    return parts_discrepancy(best.parts, best.fit.theta, [(vf.weight, vf.fit.prior_lam) for vf in vfits], settings,
                             nominal=nominal)


def cell_amplitudes(settings: SurfaceSettings, weighted_lam: Sequence[tuple[float, dict]], beta_deg,
                    eps_deg) -> np.ndarray:
    """sigma_c^2 of the discrepancy at cells (beta, eps) in degrees: the evidence-weighted amplitude
    of the cell's penalty region (:func:`roadgonio.correction.discrepancy.amplitude_from_penalty`). At
    the pole (eps = 0) every beta is the same direction, so those cells take the mean over the regions
    that meet there (user audit, session 39: with the quadrants' edge at beta 12 deg, the tan eps = 0
    row of an eq. 4 correction had u 0.07 % up to beta 10 and 1.24 % from beta 15 on)."""
    from roadgonio.correction.discrepancy import amplitude_from_penalty
    from roadgonio.correction.flexible import penalty_region
    from roadgonio.geometry import BETA_GRID_DEG
    beta = np.asarray(beta_deg, dtype=np.float64)
    eps = np.asarray(eps_deg, dtype=np.float64)
    region = penalty_region(settings, beta, eps)
    sig2 = sum(w * amplitude_from_penalty(lam, region) for w, lam in weighted_lam)
    pole = eps == 0.0
    if np.any(pole):
        ring = np.unique(penalty_region(settings, np.asarray(BETA_GRID_DEG, dtype=np.float64),
                                        np.zeros(len(BETA_GRID_DEG))))
        at_pole = sum(w * float(np.mean(amplitude_from_penalty(lam, ring))) for w, lam in weighted_lam)
        sig2 = np.where(pole, at_pole, sig2)
    return np.asarray(sig2, dtype=np.float64)


def parts_discrepancy(parts: Sequence, theta: np.ndarray, weighted_lam: Sequence[tuple[float, dict]],
                      settings: SurfaceSettings, blurs: dict | None = None,
                      nominal: Sequence[tuple[int, int]] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """:func:`discrepancy_covariance` of instrument ``parts`` (:class:`roadgonio.correction.flexible.FlexPart`)
    sharing the surface ``theta``, the amplitude from the (weight, smoothing parameters) pairs.
    ``blurs`` caches each part's blur under the part itself (a design evaluates one part against
    many; not under ``id(part)``: CPython gives a freed object's id to a later one, so a setting's
    part freed after its evaluation could hand its blur to the next);
    the same part twice (one setting measured twice) has the same blur, so its discrepancy is fully
    correlated between the two: repetition does not average it away. ``nominal``: further estimates
    after the parts' cells, the fitted model's own value at the nominal direction of cell k of part
    i for each (i, k) (:func:`roadgonio.correction.discrepancy.nominal_blur`: error -delta(x0))."""
    from roadgonio.correction.discrepancy import discrepancy_correlation, nominal_blur, part_blurs
    from roadgonio.correction.flexible import penalty_region
    ell = float(settings.discrepancy_ell)
    nominal = list(nominal or [])
    cells = [c for p in parts for c in p.forward.bundles.cells] + [parts[i].forward.bundles.cells[k]
                                                                  for i, k in nominal]
    eps = np.degrees(np.arctan([t for t, _ in cells]))
    beta = np.array([b for _, b in cells])
    region = penalty_region(settings, beta, eps)
    sig2 = cell_amplitudes(settings, weighted_lam, beta, eps)
    cache = {} if blurs is None else blurs
    for p in parts:
        if p not in cache:
            cache[p] = part_blurs(p, theta, ell)
    n_comp = len(cache[parts[0]])
    by_part = {}
    for j, (i, k) in enumerate(nominal):
        by_part.setdefault(i, []).append((j, k))
    # the nominal estimates grouped by part; their rows put back in the order of ``nominal``
    groups = sorted(by_part.items())
    order = np.argsort([j for _, g in groups for j, _ in g], kind="stable")
    n_par = sum(p.n for p in parts)
    perm = np.concatenate([np.arange(n_par), n_par + order]).astype(np.int64) if nominal else None
    R = 0.0
    for c in range(n_comp):                # the components of delta (discrepancy.pole_components): brackets add
        bl = [cache[p][c] for p in parts] + [nominal_blur(cache[parts[i]][c], [k for _, k in g])
                                                 for i, g in groups]
        Rc = discrepancy_correlation(bl, ell)
        R = R + (Rc if perm is None else Rc[np.ix_(perm, perm)])
    s = np.sqrt(sig2)
    dR = np.diag(R)[:n_par]
    info = {"ell_knots": ell, "amplitude": "the roughness prior of g_C (evidence-chosen smoothing) beyond the "
                                           "knots' Nyquist wavenumber, per region",
            "sigma_by_region": {str(n): float(np.max(s[region == n])) for n in np.unique(region)},
            "bracket_max": float(np.max(dR)), "bracket_median": float(np.median(dR))}
    return np.outer(s, s) * R, info


def _weighted_lnk_bundles(vfits: Sequence[VariantFit]) -> np.ndarray:
    """The bundles' ln k_A of the fitted surfaces (without rho), every instrument's cells one after
    the other, weighed over the variants as the corrected table weighs them: what a refit with
    another rho moves, free of the backend's noise."""
    return sum(vf.weight * np.concatenate([np.log(p.k_bundle(vf.fit.theta)) for p in vf.parts])
               for vf in vfits if vf.weight > 0.0)


def _forward_dir(i: int, n_tables: int, step: int, what: str = "backbone") -> str:
    """The journal folder of the backend's k_A through instrument ``i`` at outer step ``step`` of the
    backbone (step 1 keeps the names it always had, so such journals resume) or of the fitted
    surface (``what="surface"``: ``forward-N-surface-stepK``) or of its probe beyond the observation
    elevations (``what="unobserved"``: ``forward-N-unobserved``)."""
    base = f"forward-{i + 1}" if n_tables > 1 else "forward-1"
    if what == "surface":
        return f"{base}-surface-step{step}"
    if what == "unobserved":
        return f"{base}-unobserved"
    return base if step == 1 else f"{base}-step{step}"


def _stack_tables(tables: Sequence[RTable]) -> RTable:
    """One RTable-like object for the checkpoint key of several tables (their values one after the other)."""
    r = np.concatenate([t.r for t in tables], axis=1)
    return RTable(r, tan_eps=tables[0].tan_eps, beta_deg=np.arange(r.shape[1], dtype=np.float64))


def to_correction_result(res: SurfaceCorrection):
    """The :class:`roadgonio.correction.run.CorrectionResult` of a single-instrument correction
    (the files and pictures of ``roadgonio correct``), the surface's diagnostics in ``extra``."""
    from roadgonio.correction.run import CorrectionResult
    if res.joint:
        raise InputError("a correction through several instruments has one table per instrument; "
                         "use write_surface_correction", field="joint")
    p = res.parts[0]
    best = res.best
    # one column per other backbone, named by its variant and rounding (keyed by the variant alone, the
    # roundings of a variant overwrote one another: user audit, session 40)
    alternatives = {backbone_column(vf.variant, vf.round_deg): _grid(p.measured, vf.parts[0].k_a(vf.fit.theta))
                    for vf in res.variants if vf is not best}
    steps = res.steps
    prov = dict(res.provenance)
    prov["calibration"] = p.instrument.calibration.to_dict()
    prov["u_measured"] = p.u_what
    prov["timings"] = res.timings
    out = CorrectionResult(measured=p.measured, corrected=res.corrected, u_corrected=res.u_corrected,
                           u_measured=p.u_measured, k_a=p.k_a, u_k_a_backend=p.u_k_a_backend, budget=res.budget,
                           reference=f"self ({best.variant} backbone x correction surface, fitted through the instrument)",
                           model=best.backbone, fit=_FitView(res), alternatives=alternatives, before=p.before,
                           after=res.after, steps=steps, provenance=prov, seconds=res.seconds)
    out.extra["surface"] = res
    return out


class _FitView:
    """What the classic outputs read of a fit (``simulated`` per measured cell, ``summary()``)."""

    def __init__(self, res: SurfaceCorrection):
        p = res.parts[0]
        self.simulated = p.simulated[p.measured.mask]
        self._res = res

    @property
    def birge(self) -> float:
        return self._res.best.fit.birge

    def summary(self) -> dict[str, Any]:
        best = self._res.best
        p = self._res.parts[0]
        return {"model": "eq. 4 backbone x correction surface", "variant": best.variant,
                "mirror_round_deg": best.round_deg, "backbone": best.label, "chi2": best.fit.chi2, "dof": best.fit.dof, "edf": best.fit.edf, "birge_ratio": best.fit.birge,
                "birge_local_max": float(np.nanmax(p.birge_local)),
                "cells_widened": int(np.sum(p.widening > 1.0)),
                "widening_max": float(np.nanmax(p.widening)),
                "widening": "the surface and model components of u are multiplied by the local Birge ratio B_c "
                            "where B_c^2 exceeds 1 + 2 sqrt(2 / n_eff) (noise alone rarely does), else by 1",
                "discrepancy": self._res.provenance.get("discrepancy"),
                "variants": [v.summary() for v in self._res.variants]}
