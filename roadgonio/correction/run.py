"""Correcting a measured r-table: the whole procedure, for one table or several.

``reference = "self"`` (the default; the only reference a user of an unknown surface really has):

1. fit the BRDF model through the instrument (:mod:`roadgonio.correction.fit`) with the forward
   model of fixed ray bundles (:mod:`roadgonio.engines.bundle`), for each model variant asked
   (``"auto"``: ``power`` and ``smooth``; the better fit, by chi^2, is used, the other one measures
   the model dependence); while the data reject the fit, the search runs again with fresh starts
   (:func:`search_through_instrument`);
2. compute k_A of the fitted model with the chosen backend (``mitsuba`` by default), journalled
   and resumable like ``roadgonio ka`` (:func:`roadgonio.engines.runner.run_cells`,
   ``DIR/forward-N/``);
3. correct the bundles' own error with that table, ``rho = k_backend / k_bundle``, and refit from
   the model (stage B only); if the refit changes the predicted k_A by more than ``tol`` times the
   measurement's relative uncertainty in some cell, take the refitted model to step 2 (at most
   ``max_outer`` tables), otherwise stop;
4. corrected r = measured r / k_A(backend, final model): the measured detail is kept, the model is
   used only for the factor;
5. the budget (:mod:`roadgonio.correction.budget`) and S1, S2, Q0 before and after with their
   standard uncertainties and CIE classes.

``reference = SAMPLE`` keeps the classic route (paper section 4.1): k_A of a given reference
model (bundled table fitted on the fly, table file, model.json), with the model dependence from
alternative references (by default the two CIE tables nearest to the measured one).

Several measured tables share the instrument's artefacts (:class:`InstrumentArtefacts`: ray
bundles, eta, the reference calibration's columns), computed once; each table's correction is
one call, in this process or one Dask task per table on worker processes (:func:`correct_files`),
with the same results.
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from roadgonio.correction.budget import DEFAULT_U_MEASURED, Budget, functionals, misalignment_covariance, misfit_covariance, systematic_delta
from roadgonio.correction.fit import (DEFAULT_POLISH, DEFAULT_STARTS, ThroughFit, assess_fit, chi2_of,
                                      fit_through_instrument)
from roadgonio.engines.bundle import DEFAULT_RAYS, ForwardModel, RayBundles
from roadgonio.errors import InputError
from roadgonio.fileio import atomic_write_json, fingerprint
from roadgonio.instrument.config import Instrument
from roadgonio.instrument.housing import REFLECTANCES_EXACT
from roadgonio.surface.fit import check_rows
from roadgonio.surface.model import VARIANTS, RoadModel
from roadgonio.surface.rtable import CORRECTED_R, U_REL_MIN, RTable, check_positive, measured_label, read_table

#: Variants fitted by ``variant = "auto"``.
AUTO_VARIANTS = ("power", "smooth")
#: Outer steps (backend tables) at most, and the stopping tolerance in units of the measurement's u.
DEFAULT_MAX_OUTER = 3
DEFAULT_TOL = 0.1
#: Fit rounds with k frozen at the previous round's k_A in stage A (see fit_self).
DEFAULT_ROUNDS = 2
#: Latin-hypercube starts of the later rounds (which also start from the previous round's model).
LATER_ROUND_STARTS = 4
#: When the data reject the fitted eq. 4 model (chi^2 p-value below :data:`~roadgonio.correction.fit.MISFIT_P`),
#: the multi-start search may have missed the model's basin rather than the model the data: a
#: noise-free table of the R3 fit through the portable preset under the absolute calibration was
#: fitted at Birge ratio 12.8 (k_A off by up to 13.5 %) where the truth itself gives 0.03, because
#: stage A's 16 starts missed (6 % of such searches over ten perturbed bundled fits, none with 32).
#: Before a misfit is believed the search runs again, up to ``RETRY_SEARCHES`` times, each with
#: ``RETRY_STARTS`` fresh starts (another stream of the seed), and the best fit is kept; a repeated
#: search that finds nothing better ends it (the misfit is then the model's: one repetition for a
#: surface outside eq. 4) (audit 23). 32 rather than 48 starts: the backbones of ``--forward surface``
#: are searched the same way, once per rounding (repeated at most once there:
#: roadgonio.correction.flexible.BACKBONE_RETRIES), and 32 missed none of those 80 searches.
RETRY_SEARCHES = 2
RETRY_STARTS = 32
#: Offset of a repeated search's seed streams (its rounds use restarts from attempt x this on).
_RETRY_STREAM = 1000
FIT_STATE = "fit_state.json"
#: Forward models of ``reference = "self"``: eq. 4 alone (docs/correction.md, "The method"), or eq. 4 times the correction
#: surface (:mod:`roadgonio.correction.outside`).
FORWARDS = ("eq4", "surface")

BackendFactory = Callable[[Instrument, RoadModel], Any]


# ----------------------------------------------------------------------------------------------
# Inputs
# ----------------------------------------------------------------------------------------------

class Laps:
    """Wall time per named step of a correction (seconds, summed over repeats): ``lap("fit")``
    charges the time since the previous lap to "fit"; ``timings`` holds the sums."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self._tick = time.perf_counter()

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + now - self._tick
        self._tick = now


def forward_model_limits(instruments, *, fitted: bool = True) -> str | None:
    """What the fit's ray bundles leave out of an instrument and the k_A backend keeps: the parts of
    a ``[scene]`` or a ``[housing]`` (their shade and stray light). None when nothing is left out.
    Recorded in the provenance (correct.json), never silent. ``fitted`` False (``--reference
    SAMPLE``: no model is fitted through the instrument): only that the backend's k_A models them."""
    left = sorted({sec for inst in instruments for sec in ("scene", "housing")
                   if hasattr(inst.extra, "get") and inst.extra.get(sec)})
    if not left:
        return None
    # the parts' reflectances are inputs without an uncertainty (user audit, session 38: walls 0.05 +- 0.01
    # move k_A by 0.4 % (median) and up to 2.5 % at grazing cells; none of it was in u, and nothing said so)
    exact = f" {REFLECTANCES_EXACT_NOTE[0].upper()}{REFLECTANCES_EXACT_NOTE[1:]}."
    if not fitted:       # the fit's note did not apply to the reference route (user audit, session 38)
        return (f"the instrument's [{'], ['.join(left)}] (their shade and stray light) are in the backend's k_A of the "
                "reference, which corrects the table." + exact)
    return (f"the fit's ray bundles do not model the instrument's [{'], ['.join(left)}] (their shade and "
            "stray light); a model fitted through the instrument (--reference self) has the backend's k_A, which "
            "models them, in its fit as a factor per cell (rho = k_backend / k_bundle), refitted until the k_A it "
            "predicts holds still ('steps'), and the k_A that corrects the table is the backend's." + exact)


def note_unobserved_road(name: str) -> None:
    """The note of an eq. 4 correction through an instrument with stray light: the stray light reads
    the road beyond the observation elevations the table measures, where the fit assumes eq. 4, and
    u does not include that (the surface route's "unobserved" component does; docs/correction.md,
    "The road beyond the observation elevations")."""
    import warnings

    from roadgonio.errors import ModelWarning
    warnings.warn(ModelWarning(f"{name}: {UNOBSERVED_ROAD_NOTE}"), stacklevel=3)


#: What an eq. 4 correction through stray light leaves out of u (:func:`note_unobserved_road`; repeated
#: in corrected_u.csv's header, which ``road --u`` prints).
UNOBSERVED_ROAD_NOTE = (
    "the instrument's stray light reads the road beyond the observation elevations the table measures; the eq. 4 "
    "fit assumes eq. 4 there and u does not include that assumption (--forward surface adds it as the 'unobserved' "
    "component: docs/correction.md, \"The road beyond the observation elevations\")")
#: What no u holds for an instrument with reflecting parts (corrected_u.csv's header; user audit, session 39:
#: the caveat reached correct's terminal and correct.json, but not the u file that ``road`` reads).
REFLECTANCES_EXACT_NOTE = f"{REFLECTANCES_EXACT} (docs/correction.md, 'A housed instrument')"


def measured_uncertainty(spec: Any, table: RTable) -> tuple[np.ndarray, str]:
    """Standard uncertainty (sr^-1, grid of ``table``) of every measured cell from ``spec``:
    ``"1%"`` or a number in (0, 1) (relative), an :class:`RTable`, or the path of an r-table file
    (CSV/RTB, r x 1e4) of standard uncertainties. At least :data:`U_REL_MIN` of each
    value. Returns (grid, description)."""
    grid, what, path = _measured_uncertainty(spec, table)
    with np.errstate(invalid="ignore"):
        tiny = table.mask & (grid < U_REL_MIN * table.r)
    if tiny.any():
        i, j = np.argwhere(tiny)[0]
        raise InputError(f"a standard uncertainty below {U_REL_MIN:g} of the value (tan eps = {table.tan_eps[i]:g}, "
                         f"beta = {table.beta_deg[j]:g}; {int(tiny.sum())} cells): no goniophotometer measures that "
                         f"well, and the fit's weights 1/u^2 would overflow; expected at least {100 * U_REL_MIN:g} %",
                         path=path, **_u_where(path))
    return grid, what


def _u_where(path: Path | None, name: str = "u_measured") -> dict:
    """Where an error about input ``name`` is: the argument that named the file, or the argument itself."""
    return {"argument": name} if path is not None else {"field": name}


def _measured_uncertainty(spec: Any, table: RTable) -> tuple[np.ndarray, str, Path | None]:
    if isinstance(spec, RTable):
        grid, what = spec.r, f"per-cell table {spec.name}"
        path = None
    elif isinstance(spec, (int, float)) and not isinstance(spec, bool):
        return _relative(float(spec), table, "u_measured"), f"{100 * float(spec):g} % of each value", None
    else:
        text = str(spec).strip()
        path = None
        if text.endswith("%"):
            try:
                v = float(text[:-1]) / 100.0
            except ValueError:
                raise InputError(f"expected a percentage like '1%' or a table file, got {text!r}",
                                 field="u_measured") from None
            return (_relative(v, table, "u_measured", text), f"{100 * v:g} % of each value (relative, independent cells)",
                    None)
        try:
            v = float(text)
        except ValueError:
            v = None
        if v is not None:
            return (_relative(v, table, "u_measured", text), f"{100 * v:g} % of each value (relative, independent cells)",
                    None)
        path = Path(text)
        try:
            u_table = read_table(path, quantity="u")
        except InputError as err:
            raise InputError(f"{err.reason} (expected a relative standard uncertainty like '1%' or 0.01, or an "
                             "r-table file of per-cell standard uncertainties)", path=err.path, line=err.line,
                             field=err.field, argument="u_measured") from None
        from roadgonio.surface.rtable import check_not_ka
        try:            # ka.csv (k_A unscaled) read as r x 1e4 (user audit, session 24: it was taken as u)
            check_not_ka(u_table, path)
        except InputError as err:
            raise InputError(f"{err.reason}; expected a table of per-cell standard uncertainties",
                             path=path, argument="u_measured") from None
        grid, what = u_table.r, f"per-cell standard uncertainties from {path.name} (independent cells)"
    missing = table.mask & ~(np.isfinite(grid) & (grid > 0))
    if missing.any():
        i, j = np.argwhere(missing)[0]
        raise InputError(f"no positive standard uncertainty for the measured cell tan eps = {table.tan_eps[i]:g}, "
                         f"beta = {table.beta_deg[j]:g} ({int(missing.sum())} measured cells lack one); expected "
                         "the r-table layout with r x 1e4 values", path=path, **_u_where(path))
    from roadgonio.surface.rtable import check_u_scale
    check_u_scale(grid, table, path, **_u_where(path))          # a table of u (a percentage returned above)
    # a measurement's u is below its value, as the relative form's 0 < u < 100 % (user audit: a file of
    # '1' everywhere, meant as 1 %, was read as 1e-4 and ran with u up to 604 % of r, exit 0)
    # (the API's RTable of u as well: review, session 36)
    over = table.mask & np.isfinite(grid) & (grid >= table.r)
    if over.any():
        i, j = np.argwhere(over)[0]
        layout = "u x 1e4 in the r-table layout" if path is not None else "an RTable of u in sr^-1"
        raise InputError(f"a standard uncertainty at or above the measured value at tan eps = {table.tan_eps[i]:g}, "
                         f"beta = {table.beta_deg[j]:g} ({1e4 * grid[i, j]:.4g} against r x 1e4 = {1e4 * table.r[i, j]:.4g}; "
                         f"{int(over.sum())} cells like it): expected {layout}, below each value "
                         "(a relative u is given as '1%', not as a table of percentages)", path=path, **_u_where(path))
    return np.where(table.mask, grid, np.nan), what, path


def _relative(v: float, table: RTable, fld: str, given: str | None = None) -> np.ndarray:
    """``v`` x each value; ``given`` is what the user wrote (``"150%"``), echoed by the error."""
    if not (math.isfinite(v) and 0.0 < v < 1.0):
        raise InputError("expected a relative standard uncertainty between 0 and 100 % (exclusive: a fraction "
                         f"0 < u < 1 or a percentage 0% < u < 100%), got {given if given is not None else f'{v:g}'}",
                         field=fld)
    return np.where(table.mask, v * table.r, np.nan)


def check_measured(table: RTable, path: str | Path | None = None) -> None:
    """The measured table's values must be positive (a cell not measured is blank). A table without
    the S1 cells (tan eps 0 and 2 at beta 0) is corrected; S1, S2 and the class are then reported as
    missing (docs/inputs-outputs.md, "Missing values")."""
    check_positive(table, path, "measured table", **_u_where(path, "measured"))


def _check_fit_cells(table: RTable) -> None:
    if int(table.mask.sum()) < 12:
        raise InputError(f"the measured table has {int(table.mask.sum())} values; a fit through the instrument "
                         "needs at least 12 (or give --reference SAMPLE)", field="measured")
    check_rows(table, "measured")


# ----------------------------------------------------------------------------------------------
# Instrument artefacts (computed once for several tables)
# ----------------------------------------------------------------------------------------------

class InstrumentArtefacts:
    """What depends only on the instrument: ray bundles and forward models per cell set (with eta
    or the reference calibration's columns)."""

    def __init__(self, instrument: Instrument, *, rays: int = DEFAULT_RAYS, seed: int = 0):
        self.instrument = instrument
        self.rays = int(rays)
        self.seed = int(seed)
        self._forward: dict[tuple, ForwardModel] = {}
        self.seconds = 0.0

    def forward(self, cells: Sequence[tuple[float, float]]) -> ForwardModel:
        key = tuple((round(t, 9), round(b, 9)) for t, b in cells)
        if key not in self._forward:
            t0 = time.perf_counter()
            bundles = RayBundles.build(self.instrument, cells, rays=self.rays, seed=self.seed)
            self._forward[key] = ForwardModel(bundles)
            self.seconds += time.perf_counter() - t0
        return self._forward[key]


# ----------------------------------------------------------------------------------------------
# Result
# ----------------------------------------------------------------------------------------------

@dataclass
class CorrectionResult:
    measured: RTable
    corrected: RTable
    u_corrected: np.ndarray          # grid (sr^-1), the corrected table's standard uncertainty
    u_measured: np.ndarray           # grid (sr^-1)
    k_a: np.ndarray                  # grid, backend k_A under the instrument's calibration
    u_k_a_backend: np.ndarray        # grid, backend standard uncertainty of k_A
    budget: Budget
    reference: str
    model: RoadModel
    fit: ThroughFit | None
    alternatives: dict[str, np.ndarray]   # name -> grid of k_A of the alternative model(s)
    before: dict[str, Any]
    after: dict[str, Any]
    steps: list[dict[str, Any]]
    provenance: dict[str, Any]
    seconds: float
    extra: dict[str, Any] = field(default_factory=dict)
    #: where its files were written (:func:`roadgonio.api.correct` with ``out``)
    out: Path | None = None
    written: list = field(default_factory=list)

    @property
    def cells(self) -> list[tuple[float, float]]:
        return self.measured.cells

    def summary(self) -> dict[str, Any]:
        a, b = self.after, self.before
        m = self.measured.mask
        k = self.k_a[m]
        out = {"measured": self.measured.name, "reference": self.reference,
               "calibration": self.provenance.get("calibration", {}).get("mode", "lambert"),
               "cells": int(m.sum()), "k_a_min": float(np.min(k)), "k_a_max": float(np.max(k)),
               "S1": a["S1"], "u_S1": a.get("u_S1"), "Q0": a["Q0"], "u_Q0": a.get("u_Q0"),
               "S2": a["S2"], "u_S2": a.get("u_S2"), "class_R": a["class"]["R"], "class_C": a["class"]["C"],
               "nearest_table": a["nearest_table"], "nearest_table_basis": a.get("nearest_table_basis", ""),
               "before": {"S1": b["S1"], "u_S1": b.get("u_S1"), "Q0": b["Q0"], "u_Q0": b.get("u_Q0"), "S2": b["S2"],
                          "u_S2": b.get("u_S2"), "class_R": b["class"]["R"], "class_C": b["class"]["C"],
                          "nearest_table": b["nearest_table"], "nearest_table_basis": b.get("nearest_table_basis", "")},
               "Q0_note": a.get("Q0_note"),
               "u_rel_median": float(np.median(self.budget.u_rel())), "u_rel_max": float(np.max(self.budget.u_rel())),
               "budget": self.budget.summary(), "seconds": self.seconds}
        if self.fit is not None:
            out["fit"] = self.fit.summary()
        sc = self.extra.get("surface")
        if sc is not None:
            out["model_estimate"] = sc.model_estimate_summary()
            # the surface's own loop through a housing and the road beyond the observation elevations,
            # as the joint summary gives them (audit 21: docs/correction.md names them, correct.json of
            # one instrument had neither)
            full = sc.summary()
            out["surface_steps"] = full["surface_steps"]
            out["per_instrument"] = [{k: p[k] for k in ("instrument", "unobserved_sensitivity_max")}
                                     for p in full["per_instrument"]]
        out["steps"] = self.steps
        return out


# ----------------------------------------------------------------------------------------------
# The procedure
# ----------------------------------------------------------------------------------------------

def default_factory(backend: str, settings: Mapping[str, Any] | None = None,
                    accuracy: str | None = None) -> BackendFactory:
    from roadgonio.engines import make_backend

    def factory(instrument: Instrument, model: RoadModel):
        return make_backend(backend, instrument, model, accuracy=accuracy, **dict(settings or {}))
    return factory


#: The backend's correlation between the cells of one k_A table, kept beside the table's journal so
#: that a resumed correction states the same budget (:func:`backend_covariance`).
BACKEND_CORRELATION = "k_a_correlation.npz"


def backend_covariance(k: np.ndarray, se: np.ndarray, corr: np.ndarray | None) -> np.ndarray:
    """Relative covariance of ln k_A over the cells of one backend table: the cells' relative standard
    uncertainties ``se / k`` with the correlation ``corr`` the backend measured between them (the
    cells of one Mitsuba table share the lattice's random shifts: neighbouring cells correlate ~0.9,
    the whole table 0.15-0.8, docs/validation.md), or independent cells when it measured none (the
    float64 backends: numpy Monte Carlo draws each cell apart, a deterministic bound has no
    correlation to state)."""
    u = np.asarray(se, dtype=np.float64) / np.asarray(k, dtype=np.float64)
    if corr is None:
        return np.diag(u * u)
    return np.asarray(corr, dtype=np.float64) * np.outer(u, u)


def _backend_correlation(backend, run, k: np.ndarray, out_dir: Path | None) -> np.ndarray | None:
    """The correlation between the cells of this table that the backend measured (its ``covariance()``
    after computing every cell in one call), journalled in ``out_dir`` with the k_A it belongs to; a
    resumed table takes the journalled one when its k_A are the same, otherwise None (independent)."""
    path = None if out_dir is None else Path(out_dir) / BACKEND_CORRELATION
    corr = None
    if run.resumed == 0 and callable(getattr(backend, "covariance", None)):
        try:
            c = np.asarray(backend.covariance(), dtype=np.float64)
        except RuntimeError:
            c = None
        if c is not None and c.shape == (k.size, k.size):
            d = np.sqrt(np.clip(np.diag(c), 0.0, None))
            with np.errstate(divide="ignore", invalid="ignore"):
                corr = np.where(np.outer(d, d) > 0, c / np.outer(d, d), 0.0)
            corr = np.clip(0.5 * (corr + corr.T), -1.0, 1.0)
            np.fill_diagonal(corr, 1.0)
            if path is not None:
                from roadgonio.fileio import atomic_write
                def write(tmp: Path) -> None:
                    with open(tmp, "wb") as f:
                        np.savez(f, k_a=k, correlation=corr)
                atomic_write(path, write)
    elif path is not None and path.exists():
        try:
            with np.load(path) as z:
                if z["k_a"].shape == k.shape and np.array_equal(z["k_a"], k):
                    corr = np.array(z["correlation"])
        except (OSError, ValueError, KeyError):
            corr = None
    return corr


def _backend_note(backend: str, info: Mapping[str, Any]) -> str:
    """The budget's note on the ``backend`` component of one table (:func:`backend_covariance`)."""
    return (f"{backend} k_A standard uncertainty (SE, or bound/sqrt 3), "
            + ("with the correlation between cells the backend measured (they share its random numbers)"
               if info.get("cells_correlated") else "independent cells"))


def _backend_k(factory: BackendFactory, instrument: Instrument, model: RoadModel, cells, out_dir: Path | None,
               progress: bool, cell_results: list | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, Any], np.ndarray]:
    """The backend's k_A of ``model`` at ``cells`` (journalled in ``out_dir``), its standard
    uncertainty, the run's info and the relative covariance of ln k_A over the cells
    (:func:`backend_covariance`). ``cell_results``: a list that receives the cells' results
    (their k_a_direct and stray_fraction for correct_cells.csv)."""
    from roadgonio.engines.runner import run_cells
    backend = factory(instrument, model)
    run = run_cells(backend, cells, instrument=instrument, model=model, out_dir=out_dir, progress=progress)
    if cell_results is not None:
        cell_results[:] = list(run.results)
    k = np.array([c.k_a for c in run.results])
    se = np.array([c.standard_uncertainty() for c in run.results])
    if not (np.all(np.isfinite(k)) and np.all(k > 0)):
        raise InputError("the backend returned a non-positive or non-finite k_A; cannot correct", field="k_A")
    corr = _backend_correlation(backend, run, k, out_dir)
    info = {"backend": backend.name, "settings": backend.settings(), "seconds": run.seconds,
            "resumed_cells": run.resumed, "resumed_pass_cells": run.resumed_pass_cells,
            "not_converged": int(sum(not c.converged for c in run.results)),
            "journal": str(out_dir) if out_dir is not None else None,
            # the backend traced light the ray bundles leave out (a housing's stray light)
            "stray": bool(any((c.stray_fraction or 0.0) > 0.0 for c in run.results)),
            "cells_correlated": corr is not None}
    return k, se, info, backend_covariance(k, se, corr)


def _say(progress: bool, text: str) -> None:
    if progress and sys.stderr.isatty():
        print(f"roadgonio correct: {text}", file=sys.stderr, flush=True)


def fit_self(fm: ForwardModel, y: np.ndarray, u: np.ndarray, variant: str, *, rho=None, seed: int = 0,
             starts: int = DEFAULT_STARTS, polish: int = DEFAULT_POLISH, rounds: int = DEFAULT_ROUNDS,
             stage_b: bool = True, name: str = "fit", fixed: Mapping[str, float] | None = None,
             first_restart: int = 0, start: RoadModel | None = None) -> ThroughFit:
    """The multi-start fit through the instrument in ``rounds`` of stage A: the first freezes k_A
    at 1 (the measured table fitted as if the instrument were ideal), each later one at the previous
    round's k_A (the table that model would correct to), starting also from that model; then
    stage B from the best distinct stage-A minima (``polish``). ``stage_b=False`` stops after stage
    A (chi^2 through the bundles, no covariance). ``fixed``: parameters held (as in
    :func:`roadgonio.correction.fit.fit_through_instrument`). ``first_restart``: the seed stream of the
    first round (a repeated search starts another). ``start``: a model to start from (a neighbouring
    fit): the first round starts from it too, with k_A frozen at its k_A instead of 1."""
    k_frozen = np.ones_like(y) if start is None else fm.k_a(start, rho)
    best = None
    for r in range(int(rounds)):
        first = [] if start is None else [start]
        res = fit_through_instrument(fm, y, u, variant=variant, rho=rho, polish=polish, seed=seed,
                                     restart=int(first_restart) + r,
                                     starts=starts if best is None else LATER_ROUND_STARTS, k_frozen=k_frozen,
                                     stage_b=False, name=name, start_models=first if best is None else [best.model],
                                     fixed=fixed)
        if best is not None and res.chi2 >= best.chi2 * (1.0 - 1e-6):
            break
        best = res
        k_frozen = fm.k_a(best.model, rho)
    if not stage_b:
        return best
    return fit_through_instrument(fm, y, u, variant=variant, rho=rho, start_models=[best.model], stage_a=False,
                                  name=name, fixed=fixed)


def search_through_instrument(fm: ForwardModel, y: np.ndarray, u: np.ndarray, variants: Sequence[str], *,
                              state: "_FitState | None" = None, seed: int = 0, starts: int = DEFAULT_STARTS,
                              polish: int = DEFAULT_POLISH, rounds: int = DEFAULT_ROUNDS, name: str = "fit",
                              say: Callable[[str], None] | None = None, fixed: Mapping[str, float] | None = None,
                              state_name: Callable[[str], str] = str,
                              describe: Callable[[str], str] = lambda v: f"{v} model",
                              retries: int = RETRY_SEARCHES, start_models: Mapping[str, RoadModel] | None = None
                              ) -> tuple[dict[str, RoadModel], dict[str, float], RoadModel, list[dict[str, Any]]]:
    """The eq. 4 fit of ``correct --reference self`` through the bundles (no backend yet), and the
    backbones of ``--forward surface`` (one call per rounding, ``fixed`` its parameters): stage A of
    every variant (:func:`fit_self`), the best variant's start of this search polished (stage B); while the data reject the result
    (:attr:`~roadgonio.correction.fit.ThroughFit.misfit`), the search again with fresh starts
    (at most ``retries`` times, default :data:`RETRY_SEARCHES`). ``start_models``: a model per variant
    that the first search starts from besides its ``starts`` fresh ones (:func:`fit_self`'s ``start``). Journalled in ``state`` (if given) under ``stage-a-NAME`` and ``fit-NAME`` (NAME
    ``state_name(variant)``; ``search-N-`` before them for a repeated search). Returns (the best model of each
    variant, their chi^2 through the bundles, the fitted model, one record per search)."""
    fits: dict[str, RoadModel] = {}
    chi2: dict[str, float] = {}
    searches: list[dict[str, Any]] = []
    model = None
    state = state if state is not None else _FitState(None, "")
    for attempt in range(int(retries) + 1):
        tag = "" if attempt == 0 else f"search-{attempt}-"
        n_starts = starts if attempt == 0 else RETRY_STARTS
        fresh: dict[str, RoadModel] = {}
        for v in variants:       # stage A of every variant (cheap), the better one goes on
            m = state.get(f"{tag}stage-a-{state_name(v)}")
            if m is None:
                if say is not None:
                    say(f"{name}: fitting the {describe(v)} through the instrument(s)"
                        + ("" if attempt == 0 else f" (search {attempt + 1}: the data rejected the fit)"))
                m = fit_self(fm, y, u, v, seed=seed, starts=n_starts, polish=polish, rounds=rounds, stage_b=False,
                             name=name, fixed=fixed, first_restart=attempt * _RETRY_STREAM,
                             start=(start_models or {}).get(v) if attempt == 0 else None).model
                state.put(f"{tag}stage-a-{state_name(v)}", m)
            fresh[v] = m
            c = chi2_of(fm, y, u, m)
            if v not in fits or c < chi2[v]:
                fits[v], chi2[v] = m, c
        main_v = min(chi2, key=chi2.get)
        model = state.get(f"{tag}fit-{state_name(main_v)}")
        if model is None:
            # a repeated search polishes its own start: the best so far was polished already, and the
            # fresh one's chi^2 before the polish (stage A's k_A frozen) can rank its basin far below
            # where the polish takes it (session 31: an eq. 4 table through the medium instrument,
            # search 2's start at chi^2 3e8 polished to 372, the best so far stuck at 990)
            model = fit_through_instrument(fm, y, u, variant=main_v, start_models=[fresh[main_v]], stage_a=False,
                                           seed=seed, name=name, fixed=fixed).model
            state.put(f"{tag}fit-{state_name(main_v)}", model)
        c = chi2_of(fm, y, u, model)
        if c < chi2[main_v]:
            fits[main_v], chi2[main_v] = model, c
        else:      # a polish that found nothing better keeps the better start
            model = fits[main_v]
        judged = assess_fit(fm, y, u, model, name=name, fixed=fixed)      # its dof and p-value, once
        searches.append({"search": attempt + 1, "starts": n_starts, "variant": main_v, "chi2": judged.chi2,
                         "chi2_p_value": judged.chi2_p_value})
        # a search that found no better fit than the one before says the misfit is the model's
        if not judged.misfit or (attempt > 0 and judged.chi2 >= searches[-2]["chi2"] * (1.0 - 1e-6)):
            break
    return fits, chi2, model, searches


def _state_key(measured: RTable, u: np.ndarray, instrument: Instrument, settings: Mapping[str, Any]) -> str:
    return fingerprint({"measured": np.where(measured.mask, measured.r, -1.0), "u": np.where(measured.mask, u, -1.0),
                        "instrument": instrument.to_dict(), **dict(settings)})


def refit_with_rho(state: "_FitState", name: str, forward, y: np.ndarray, u: np.ndarray, start: RoadModel,
                   rho: np.ndarray, *, variant: str, seed: int, label: str,
                   fixed: Mapping[str, float] | None = None) -> RoadModel:
    """``start`` refitted through ``forward`` with the bundles' correction ``rho`` (stage B, one
    polish), journalled in ``state`` under ``name``: the outer loop's refit and the other
    variants' refits with the loop's rho, of both routes (:func:`correct_self`,
    :func:`roadgonio.correction.outside.correct_surface`)."""
    model = state.get(name)
    if model is None:
        model = fit_through_instrument(forward, y, u, variant=variant, rho=rho, start_models=[start], stage_a=False,
                                       polish=1, seed=seed, name=label, fixed=fixed).model
        state.put(name, model)
    return model


def predicted_change(forward, model: RoadModel, rho: np.ndarray, k_backend: np.ndarray) -> np.ndarray:
    """|ln k_A| change per cell that a refitted ``model`` predicts (through ``forward`` with ``rho``)
    against the backend's ``k_backend``: the outer loop's stopping measure and, when it stops
    first, its ``convergence`` component (over sqrt 3, rectangular)."""
    return np.abs(np.log(forward.k_a(model, rho)) - np.log(k_backend))


class _FitState:
    """Checkpoint of the fitted models of one correction (``DIR/fit_state.json``): a rerun with the
    same inputs reuses them, so the journalled backend tables (same model, same fingerprint) resume.
    With ``--forward surface`` it also keeps each variant's correction surface (its mode and smoothing
    parameters, :meth:`roadgonio.correction.flexible.SurfaceFit.state`), so a rerun does not search
    for them again."""

    def __init__(self, out_dir: Path | None, key: str):
        self.path = None if out_dir is None else Path(out_dir) / FIT_STATE
        self.key = key
        self.models: dict[str, dict] = {}
        self.surfaces: dict[str, dict] = {}
        if self.path is not None and self.path.exists():
            try:
                d = json.loads(self.path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                d = None
            if isinstance(d, dict) and d.get("key") == key:
                self.models = dict(d.get("models", {}))
                self.surfaces = dict(d.get("surfaces", {}))
            elif isinstance(d, dict) and d.get("key"):
                # another correction's folder: said now, not after the fit, when its k_A journals refused
                # the new model as 'a different run (instrument, model, backend or settings differ)'
                # (user audit, session 45: a table measured again, corrected into the same folder)
                raise InputError("this folder holds the correction of other inputs (the measured table(s), their "
                                 "uncertainty, the instrument(s) or the settings differ); use another --out folder, "
                                 "or remove this one", path=self.path)

    def get(self, name: str) -> RoadModel | None:
        d = self.models.get(name)
        return RoadModel.from_json_dict(d) if d else None

    def put(self, name: str, model: RoadModel) -> None:
        self.models[name] = {"variant": model.variant, "params": model.params.to_dict(), "name": model.name}
        self._write()

    def get_surface(self, name: str) -> dict | None:
        return self.surfaces.get(name)

    def put_surface(self, name: str, state: Mapping[str, Any]) -> None:
        self.surfaces[name] = dict(state)
        self._write()

    def _write(self) -> None:
        if self.path is not None:
            doc: dict[str, Any] = {"key": self.key, "models": self.models}
            if self.surfaces:
                doc["surfaces"] = self.surfaces
            atomic_write_json(self.path, doc)


def correct_self(measured: RTable, instrument: Instrument, *, u_measured: Any = DEFAULT_U_MEASURED, variant: str = "auto",
                 sigma=None, backend: str = "mitsuba", backend_settings: Mapping[str, Any] | None = None,
                 accuracy: str | None = None, factory: BackendFactory | None = None,
                 out_dir: str | Path | None = None, artefacts: InstrumentArtefacts | None = None,
                 rays: int = DEFAULT_RAYS, seed: int = 0, starts: int = DEFAULT_STARTS, polish: int = DEFAULT_POLISH,
                 rounds: int = DEFAULT_ROUNDS, max_outer: int = DEFAULT_MAX_OUTER, tol: float = DEFAULT_TOL,
                 misalignment_rays: int = 256, progress: bool = True) -> CorrectionResult:
    """Correct ``measured`` with the model fitted through ``instrument`` (module docstring)."""
    t0 = time.perf_counter()
    check_measured(measured)
    _check_fit_cells(measured)
    sigma = _sigma(sigma, instrument, measured)
    if variant != "auto" and variant not in VARIANTS:
        raise InputError(f"unknown model variant {variant!r}; expected auto or one of {', '.join(VARIANTS)}",
                         field="model_variant")
    u_grid, u_what = measured_uncertainty(u_measured, measured)
    out = Path(out_dir) if out_dir is not None else None
    mask = measured.mask
    cells = measured.cells
    y, u = measured.r[mask], u_grid[mask]
    u_rel = u / y
    art = artefacts if artefacts is not None else InstrumentArtefacts(instrument, rays=rays, seed=seed)
    _say(progress, f"{measured.name}: ray bundles of {len(cells)} cells")
    lap = Laps()
    timings = lap.timings
    fm = art.forward(cells)
    lap("bundles")
    factory = factory or default_factory(backend, backend_settings, accuracy)
    settings_key = {"variant": variant, "rays": art.rays, "seed": art.seed, "starts": starts, "polish": polish,
                    "rounds": rounds, "max_outer": max_outer, "tol": tol, "backend": backend,
                    "backend_settings": dict(backend_settings or {}), "accuracy": accuracy}
    state = _FitState(out, _state_key(measured, u_grid, instrument, settings_key))

    # 1. fits through the instrument (bundles only); searched again while the data reject the fit
    variants = AUTO_VARIANTS if variant == "auto" else (variant,)
    fits, chi2, model, searches = search_through_instrument(
        fm, y, u, variants, state=state, seed=seed, starts=starts, polish=polish, rounds=rounds,
        name=measured.name, say=lambda text: _say(progress, text))
    main_v = model.variant
    lap("fit")

    # 2-3. backend tables and the bundles' correction rho
    steps: list[dict[str, Any]] = []
    rho = None
    pred_change = np.zeros_like(y)
    k_b = se_b = None
    cell_results: list = []
    for it in range(1, int(max_outer) + 1):
        _say(progress, f"{measured.name}: k_A of the fitted model ({backend}), step {it}")
        k_b, se_b, info, cov_b = _backend_k(factory, instrument, model, cells,
                                            None if out is None else out / f"forward-{it}", progress, cell_results)
        rho = k_b / fm.k_a(model)
        lap("backend")
        nxt = refit_with_rho(state, f"refit-{it}", fm, y, u, model, rho, variant=main_v, seed=seed,
                             label=measured.name)
        lap("refit")
        pred_change = predicted_change(fm, nxt, rho, k_b)
        worst = float(np.max(pred_change / u_rel))
        steps.append({"step": it, "model": model.params.to_dict(), "backend": info,
                      "rho_min": float(rho.min()), "rho_max": float(rho.max()),
                      "refit_change_over_u_max": worst, "converged": worst <= tol})
        if worst <= tol:
            break
        if it < max_outer:
            model = nxt
    final = assess_fit(fm, y, u, model, rho=rho, name=measured.name)
    unobserved = bool(steps[-1]["backend"].get("stray"))
    if unobserved:
        note_unobserved_road(measured.name)

    # model dependence: the other variant, refitted with the same rho
    alternatives: dict[str, np.ndarray] = {}
    for v, m in fits.items():
        if v == main_v:
            continue
        alt = refit_with_rho(state, f"alt-{v}", fm, y, u, m, rho, variant=v, seed=seed, label=measured.name)
        alternatives[v] = fm.k_a(alt, rho)
    lap("alternative")

    budget = Budget(len(cells))
    budget.add("measurement", u_rel, u_what)
    budget.add("backend", cov_b, _backend_note(backend, info))
    budget.add("parameters", final.lnk_cov(),
               f"fitted {main_v} parameters (Birge ratio {final.birge:.3g}) through d ln k_A / d p")
    if alternatives:
        delta = systematic_delta(fm.k_a(model, rho), alternatives)
        budget.add_systematic("model", delta, "model variant " + ", ".join(alternatives) + f" instead of {main_v}: "
                              "rectangular, half-width |ln k_alt - ln k|, fully correlated")
    lap("budget")
    mis_info = None
    if sigma is not None:
        _say(progress, f"{measured.name}: misalignment sensitivities")
        cov, mis_info = misalignment_covariance(model, instrument, measured, sigma, rays=misalignment_rays, seed=seed)
        budget.add("misalignment", cov, "instrument geometric errors (--sigma), first-order GUM")
        lap("misalignment")
    if not steps[-1]["converged"]:
        budget.add("convergence", pred_change / math.sqrt(3.0),
                   "change of k_A the last refit still predicted (rectangular)")
    if final.misfit:
        # audit 28: a surface outside eq. 4 (Birge 15) kept the u of a good fit, errors up to 14 u;
        # measurement noise stated 3x too small the same (Birge 3, 53 cells beyond 4 u)
        cov_m, widen = misfit_covariance(measured, final.residual, len(final.free), u_rel)
        final.misfit_cells_widened = int(np.sum(widen > 1.0))
        budget.add("misfit", cov_m, "the data reject the fit: where the normalised residuals exceed the noise "
                   "(local Birge ratio B_c over the neighbouring cells), u_measured sqrt(B_c^2 - 1), correlated "
                   f"over the neighbourhood ({final.misfit_cells_widened} cells)")
    reference = f"self ({main_v} model fitted through the instrument)"
    res = _assemble(measured, instrument, u_grid, k_b, se_b, budget, reference, model, final,
                    {k: _grid(measured, v) for k, v in alternatives.items()}, steps, t0)
    _keep_stray(res, cell_results)
    if unobserved:
        res.extra["u_notes"] = [UNOBSERVED_ROAD_NOTE]
    res.provenance.update({"u_measured": u_what, "variant_asked": variant, "variant_used": main_v,
                           "chi2_by_variant": chi2, "fitted_models": {v: m.to_json_dict() for v, m in fits.items()},
                           "searches": searches,
                           "bundles": fm.bundles.summary(), "misalignment": mis_info,
                           "correction_settings": settings_key, "timings": timings})
    return res


def correct_with_reference(measured: RTable, instrument: Instrument, reference: RoadModel, *,
                           reference_name: str = "reference", alternatives: Mapping[str, RoadModel] | None = None,
                           u_measured: Any = DEFAULT_U_MEASURED, sigma=None, backend: str = "mitsuba",
                           backend_settings: Mapping[str, Any] | None = None, accuracy: str | None = None,
                           factory: BackendFactory | None = None, out_dir: str | Path | None = None,
                           misalignment_rays: int = 256, seed: int = 0, progress: bool = True) -> CorrectionResult:
    """r / k_A(reference) with the model dependence from ``alternatives`` (module docstring)."""
    t0 = time.perf_counter()
    check_measured(measured)
    sigma = _sigma(sigma, instrument, measured)
    u_grid, u_what = measured_uncertainty(u_measured, measured)
    out = Path(out_dir) if out_dir is not None else None
    cells = measured.cells
    mask = measured.mask
    factory = factory or default_factory(backend, backend_settings, accuracy)
    cell_results: list = []
    k_b, se_b, info, cov_b = _backend_k(factory, instrument, reference, cells,
                                        None if out is None else out / "forward-1", progress, cell_results)
    alts = {}
    for k, (name, m) in enumerate(dict(alternatives or {}).items()):
        alts[name] = _backend_k(factory, instrument, m, cells, None if out is None else out / f"alternative-{k + 1}",
                                progress)[0]
    budget = Budget(len(cells))
    budget.add("measurement", u_grid[mask] / measured.r[mask], u_what)
    budget.add("backend", cov_b, _backend_note(backend, info))
    if alts:
        budget.add_systematic("model", systematic_delta(k_b, alts),
                              "alternative references " + ", ".join(alts) + ": rectangular, half-width the largest "
                              "|ln k_alt - ln k|, fully correlated")
    mis_info = None
    if sigma is not None:
        cov, mis_info = misalignment_covariance(reference, instrument, measured, sigma, rays=misalignment_rays,
                                                seed=seed)
        budget.add("misalignment", cov, "instrument geometric errors (--sigma), first-order GUM")
    steps = [{"step": 1, "model": reference.params.to_dict(), "backend": info, "converged": True}]
    res = _assemble(measured, instrument, u_grid, k_b, se_b, budget, reference_name, reference, None,
                    {k: _grid(measured, v) for k, v in alts.items()}, steps, t0)
    _keep_stray(res, cell_results)
    res.provenance.update({"u_measured": u_what, "reference_model": reference.to_json_dict(),
                           "alternatives": {n: m.to_json_dict() for n, m in dict(alternatives or {}).items()},
                           "misalignment": mis_info})
    return res


def _keep_stray(res: CorrectionResult, cell_results: list) -> None:
    """Where the backend traced stray light (a housing), the k_A of the direct light and the stray
    fraction of each cell of the k_A that corrected the table, on the grid (``res.extra["stray"]``,
    columns of correct_cells.csv; user audit, session 38: only the journal held them)."""
    if not cell_results or not any((c.stray_fraction or 0.0) > 0.0 for c in cell_results):
        return
    res.extra["stray"] = {
        "k_a_direct": _grid(res.measured, np.array([c.k_a_direct for c in cell_results], dtype=np.float64)),
        "stray_fraction": _grid(res.measured, np.array([c.stray_fraction for c in cell_results], dtype=np.float64))}


def _grid(table: RTable, values: np.ndarray) -> np.ndarray:
    g = np.full(table.r.shape, np.nan)
    g[table.mask] = values
    return g


def _assemble(measured: RTable, instrument: Instrument, u_grid, k_b, se_b, budget: Budget, reference: str,
              model: RoadModel, fit: ThroughFit | None, alternatives, steps, t0) -> CorrectionResult:
    mask = measured.mask
    corrected_r = _grid(measured, measured.r[mask] / k_b)
    label = f"{measured_label(measured)} {CORRECTED_R}; reference {reference}; instrument {instrument.name})"
    corrected = measured.with_values(corrected_r, name=f"{measured.name}_corrected", source=label)
    cov = budget.total()
    u_abs = _grid(measured, corrected_r[mask] * np.sqrt(np.diag(cov)))
    before_budget = Budget(len(mask[mask]))
    before_budget.add("measurement", u_grid[mask] / measured.r[mask])
    if "misalignment" in budget.components:
        before_budget.add("misalignment", budget.components["misalignment"])
    before = functionals(measured, before_budget.total())
    after = functionals(corrected, cov)
    from roadgonio.provenance import provenance
    info = steps[-1]["backend"]
    prov = provenance(instrument=instrument, model=model, backend=info["backend"], settings=info["settings"],
                      calibration=instrument.calibration.to_dict(), reference=reference,
                      forward_model_limits=forward_model_limits([instrument], fitted=fit is not None),
                      before_uncertainty="measurement" + (" and misalignment" if "misalignment" in budget.components
                                                          else "") + " only (the aperture effect is the bias the "
                                                                     "correction removes)")
    return CorrectionResult(measured=measured, corrected=corrected, u_corrected=u_abs, u_measured=u_grid,
                            k_a=_grid(measured, k_b), u_k_a_backend=_grid(measured, se_b), budget=budget, reference=reference,
                            model=model, fit=fit, alternatives=alternatives, before=before, after=after, steps=steps,
                            provenance=prov, seconds=time.perf_counter() - t0)


def _sigma(sigma, instrument: Instrument | None = None, measured: RTable | None = None):
    """A SigmaSpec from a SPEC text, a TOML file, a mapping or a SigmaSpec (None stays None); with
    ``instrument`` and ``measured``, checked against their geometry (:func:`check_sigma`)."""
    if sigma is None:
        return None
    from roadgonio.uncertainty import SigmaSpec, parse_sigma_spec
    spec = sigma if isinstance(sigma, SigmaSpec) else parse_sigma_spec(sigma, option="sigma")
    if instrument is not None and measured is not None:
        check_sigma(spec, instrument, measured)
    return spec


def check_sigma(spec, instrument: Instrument, measured: RTable, option: str = "sigma") -> None:
    """The check `uncertainty` makes of a SPEC, before anything runs
    (:func:`roadgonio.uncertainty.spec.check_spec_geometry`), on the measured table's cells: the
    misalignment's sensitivities are differences at +- sigma / 2 of the same geometry, and a SPEC that
    takes it out of validity gave a u of 121 % with exit 0 (trial 12 D3). The check needs no surface
    (a Lambertian stands in); the cells (0, 0) and (2, 0), which the measurement model normalises
    with, are added (they never leave the geometry's validity before the others do)."""
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID, nearest_grid_node
    from roadgonio.uncertainty.cells import CellSet
    from roadgonio.uncertainty.measurement import MeasurementModel
    from roadgonio.uncertainty.spec import check_spec_geometry
    mask = np.array(measured.mask, dtype=bool)
    for t in (0.0, 2.0):
        mask[nearest_grid_node(t, 0.0)[:2]] = True
    ii, jj = np.nonzero(mask)
    cells = CellSet(TAN_EPS_GRID[ii].copy(), BETA_GRID_DEG[jj].copy(), ii, jj, "measured")
    check_spec_geometry(spec, MeasurementModel(RoadModel.lambert(), instrument, cells),
                        aperture=not instrument.is_ideal(), option=option)
