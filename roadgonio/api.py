"""The Python API of roadgonio, for notebooks and scripts (exported from :mod:`roadgonio`).

.. code-block:: python

    import roadgonio as rg
    ds = rg.ka_table("portable", "R3", backend="quadrature", accuracy="fast")   # xarray.Dataset
    ds.k_a.sel(tan_eps=12, beta=0)

* :func:`ka_table` -- k_A over the CIE grid as an ``xarray.Dataset`` (``k_a``, ``se``,
  ``error_bound``, ``converged`` over ``tan_eps`` x ``beta``; NaN where not computed; provenance in
  ``attrs``);
* :func:`ka_cell` -- k_A at one cell (a :class:`~roadgonio.engines.CellResult`);
* :func:`read_table` / :func:`write_table` -- an r-table as an ``xarray.DataArray`` of r in sr^-1
  (not r x 10^4) on the CIE grid;
* :func:`fit` -- fit the road BRDF model to an r-table;
* :func:`correct` -- correct a measured r-table for the aperture effect;
* :func:`uncertainty` -- Monte Carlo (JCGM 101) and GUM uncertainty of a measured r-table.

Instruments and samples are given as the command line takes them: an instrument is a preset
name (``"lab"``, ``"portable"``), a TOML file or an :class:`~roadgonio.instrument.config.Instrument`;
a sample is ``"lambert"``, a bundled table name (``"R3"``: fitted on the fly, cached), a table
file (.csv/.rtb), a model file (.json), a :class:`~roadgonio.surface.model.RoadModel`, an
:class:`~roadgonio.surface.rtable.RTable`, an r-table ``DataArray`` or a fit result. Conventions
(angles, quantities, k_A, calibration): ``docs/conventions.md``.

The Mitsuba variant is process state: with ``backend="mitsuba"`` these functions keep a variant
you already selected, else select ``variant`` (default ``llvm_ad_rgb``) -- they are the entry
point, like the ``roadgonio`` command. Nothing heavy is imported until a function runs.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

from roadgonio.errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    import xarray as xr

    from roadgonio.correction import CorrectionResult
    from roadgonio.engines import CellResult
    from roadgonio.instrument.config import Instrument
    from roadgonio.surface.fit import FitResult
    from roadgonio.surface.model import RoadModel
    from roadgonio.surface.rtable import RTable
    from roadgonio.uncertainty.run import UncertaintyResult

__all__ = ["ka_table", "ka_cell", "read_table", "write_table", "fit", "correct", "uncertainty", "design",
           "intercompare"]

#: Names of the Dataset / DataArray dimensions (the r-table rows and columns).
TAN_EPS, BETA = "tan_eps", "beta"


# ----------------------------------------------------------------------------------------------
# Inputs: what the command line accepts, plus the objects
# ----------------------------------------------------------------------------------------------

def _instrument(instrument) -> "Instrument":
    from roadgonio.instrument.config import Instrument, load_instrument
    if isinstance(instrument, Instrument):
        return instrument
    if isinstance(instrument, (str, Path)):
        return load_instrument(instrument)
    raise InputError(f"expected an instrument preset name, a TOML file or an Instrument, got {type(instrument).__name__}",
                     field="instrument")


def _table(table, what: str = "table") -> "RTable":
    """An RTable from a bundled name, a file, an RTable or an r-table DataArray."""
    from roadgonio.surface.rtable import RTable, load_table
    if isinstance(table, RTable):
        return table
    if isinstance(table, (str, Path)):
        return load_table(table)
    if _is_dataarray(table):
        return _rtable_from_dataarray(table, what)
    raise InputError(f"expected a bundled table name, a .csv/.rtb file, an RTable or an r-table DataArray, "
                     f"got {type(table).__name__}", field=what)


def _sample(sample, model_variant: str | None = None) -> tuple["RoadModel", str, "RTable | None"]:
    """(model, a short name, the r-table if the sample is one)."""
    from roadgonio.surface.fit import FitResult
    from roadgonio.surface.model import RoadModel
    from roadgonio.surface.rtable import BUNDLED, RTable
    from roadgonio.surface.sample import TABLE_SUFFIXES, fitted_model, resolve_sample
    if isinstance(sample, RoadModel):
        return sample, sample.name or "model", None
    if isinstance(sample, FitResult):
        return sample.model, sample.table.name, sample.table
    if isinstance(sample, RTable) or _is_dataarray(sample):
        table = _table(sample, "sample")
        return fitted_model(table, model_variant), table.name, table
    if isinstance(sample, (str, Path)):
        spec = str(sample)
        model = resolve_sample(spec, model_variant)
        p = Path(spec).expanduser()
        is_table = (spec.strip().upper() in BUNDLED and not p.exists()) or p.suffix.lower() in TABLE_SUFFIXES
        table = _table(spec, "sample") if is_table else None
        return model, p.stem if p.suffix else spec, table
    raise InputError("expected 'lambert', a bundled table name, a table or model file, a RoadModel, an RTable or "
                     f"an r-table DataArray, got {type(sample).__name__}", field="sample")


def _choose_variant(backend: str, variant: str | None) -> None:
    """Entry-point choice of the Mitsuba variant: keep the caller's if one is selected and none is
    asked for, else select the one asked for (default llvm_ad_rgb)."""
    if backend != "mitsuba":
        return
    mi = sys.modules.get("mitsuba")
    current = mi.variant() if mi is not None else None
    if current is not None and variant in (None, current):
        return
    from roadgonio.engines.mitsuba import set_variant
    set_variant(variant)


def _backend(backend: str, instrument, model, *, accuracy: str | None, seed: int, variant: str | None,
             rel_se: float | None, settings: Mapping[str, Any] | None = None):
    from roadgonio.engines import make_backend
    from roadgonio.engines.accuracy import rel_se_setting
    kw: dict[str, Any] = dict(settings or {})
    if rel_se is not None:
        kw.update(rel_se_setting(backend, rel_se, field="rel_se"))
    if backend in ("mitsuba", "numpy-mc"):
        kw.setdefault("seed", int(seed))
    if backend == "mitsuba" and variant is not None:
        kw.setdefault("variant", variant)
    _choose_variant(backend, variant)
    return make_backend(backend, instrument, model, accuracy=accuracy, **kw)


def _grid_cells(cells, table: "RTable | None") -> list[tuple[float, float]]:
    from roadgonio.engines import full_grid_cells
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    if isinstance(cells, str):
        if cells == "all":
            return full_grid_cells()
        if cells == "table":
            if table is None:
                raise InputError("cells='table' needs a sample that is an r-table (bundled name, table file, RTable)",
                                 field="cells")
            return table.cells
        raise InputError(f"expected 'all', 'table' or a list of (tan_eps, beta) cells, got {cells!r}", field="cells")
    out = []
    for c in cells:
        try:
            t, b = (float(v) for v in c)
        except (TypeError, ValueError):
            raise InputError(f"expected (tan_eps, beta) pairs, got {c!r}", field="cells") from None
        if not (abs(TAN_EPS_GRID - t) < 1e-9).any() or not (abs(BETA_GRID_DEG - b) < 1e-9).any():
            raise InputError(f"cell ({t:g}, {b:g}) is not on the CIE grid; use ka_cell for other cells",
                             field="cells")
        out.append((t, b))
    return out


# ----------------------------------------------------------------------------------------------
# k_A
# ----------------------------------------------------------------------------------------------

def ka_table(instrument, sample, *, backend: str = "mitsuba", accuracy: str | None = "default",
             cells: str | Sequence[tuple[float, float]] = "all", seed: int = 0, variant: str | None = None,
             rel_se: float | None = None, progress: bool = False, model_variant: str | None = None,
             settings: Mapping[str, Any] | None = None) -> "xr.Dataset":
    """The aperture-effect factor k_A of ``instrument`` for ``sample`` over the CIE grid.

    Parameters
    ----------
    instrument, sample:
        As on the command line, or objects (module docstring).
    backend:
        ``"mitsuba"`` (float32 ray tracing), ``"quadrature"`` (deterministic float64) or
        ``"numpy-mc"`` (float64 Monte Carlo, slow; an oracle).
    accuracy:
        ``"fast"``, ``"default"`` or ``"precise"`` (the presets of :mod:`roadgonio.engines.accuracy`);
        ``rel_se`` (target relative standard error, or the quadrature's relative tolerance) and
        ``settings`` (backend keywords) override it.
    cells:
        ``"all"`` (580 cells), ``"table"`` (the cells tabulated in the sample's r-table) or a list of
        (tan_eps, beta) grid cells.
    seed:
        Seed of the Monte Carlo backends (same seed, same numbers).
    variant:
        Mitsuba variant (default: the selected one, else ``llvm_ad_rgb``).
    progress:
        Show a progress bar (on a terminal only).

    Returns
    -------
    xarray.Dataset
        Data variables ``k_a``, ``se`` (standard error; NaN for a deterministic backend),
        ``error_bound`` (deterministic bound; NaN for Monte Carlo) and ``converged`` (True where
        the cell was computed and reached its target) over dims ``tan_eps`` (29) and ``beta`` (20,
        degrees); NaN (``converged`` False) where not computed. ``attrs["provenance"]`` holds the
        provenance (:mod:`roadgonio.provenance`) as a JSON string; ``attrs`` also has flat keys
        (instrument, sample, backend, accuracy, seed, roadgonio_version, created, ...).
    """
    import numpy as np
    import xarray as xr

    from roadgonio.engines.runner import run_cells
    from roadgonio.fileio import to_json
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    from roadgonio.provenance import provenance
    inst = _instrument(instrument)
    model, name, table = _sample(sample, model_variant)
    todo = _grid_cells(cells, table)
    b = _backend(backend, inst, model, accuracy=accuracy, seed=seed, variant=variant, rel_se=rel_se,
                 settings=settings)
    run = run_cells(b, todo, instrument=inst, model=model, out_dir=None, progress=progress)
    converged = np.nan_to_num(run.grid("converged"), nan=0.0).astype(bool)
    coords = {TAN_EPS: (TAN_EPS, TAN_EPS_GRID.copy(), {"long_name": "tan(epsilon)", "units": "1"}),
              BETA: (BETA, BETA_GRID_DEG.copy(), {"long_name": "beta", "units": "deg"})}
    dims = (TAN_EPS, BETA)
    data = {
        "k_a": (dims, run.grid("k_a"), {"long_name": "aperture-effect factor k_A", "units": "1",
                                        "description": "reported q / f(nominal); r_true = r_measured / k_A"}),
        "se": (dims, run.grid("se"), {"long_name": "standard error of k_A", "units": "1",
                                      "description": "Monte Carlo standard error; NaN for a deterministic backend"}),
        "error_bound": (dims, run.grid("error_bound"),
                        {"long_name": "error bound of k_A", "units": "1",
                         "description": "deterministic bound on |k_A - true k_A|; NaN for Monte Carlo"}),
        "converged": (dims, converged, {"long_name": "the cell was computed and reached its target"}),
    }
    prov = provenance(instrument=inst, model=model, backend=b.name, settings=b.settings(), sample=name,
                      accuracy=accuracy, cells=len(todo))
    attrs = {"title": f"k_A of instrument '{inst.name}' for sample '{name}' ({b.name} backend)",
             "quantity": "k_A = (S[f_road]/S[f_lambert]) / (f_road(nominal)/f_lambert) (docs/conventions.md)",
             "instrument": inst.name, "sample": name, "backend": b.name, "accuracy": str(accuracy),
             "seed": int(seed), "cells_computed": len(run.results),
             "cells_not_converged": int(sum(not c.converged for c in run.results)),
             "roadgonio_version": prov["versions"]["roadgonio"], "created": prov["created"],
             "provenance": to_json(prov, indent=None)}
    return xr.Dataset(data, coords=coords, attrs=attrs)


def ka_cell(instrument, sample, tan_eps: float, beta: float, *, backend: str = "mitsuba",
            accuracy: str | None = "default", seed: int = 0, variant: str | None = None,
            rel_se: float | None = None, model_variant: str | None = None,
            settings: Mapping[str, Any] | None = None) -> "CellResult":
    """k_A at one cell (tan eps, beta in degrees; any cell, not only the grid's) as a
    :class:`~roadgonio.engines.CellResult` (``k_a``, ``se``, ``error_bound``, ``converged``,
    ``samples``, ``seconds``). Arguments as for :func:`ka_table`."""
    for v, fld, ok in ((tan_eps, "tan_eps", lambda x: x >= 0), (beta, "beta", lambda x: 0 <= x <= 180)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not ok(v):
            raise InputError(f"expected {'tan eps >= 0' if fld == 'tan_eps' else '0 <= beta <= 180 deg'}, got {v!r}",
                             field=fld)
    inst = _instrument(instrument)
    model, _, _ = _sample(sample, model_variant)
    b = _backend(backend, inst, model, accuracy=accuracy, seed=seed, variant=variant, rel_se=rel_se,
                 settings=settings)
    return b.compute([(float(tan_eps), float(beta))])[0]


# ----------------------------------------------------------------------------------------------
# r-tables
# ----------------------------------------------------------------------------------------------

def _is_dataarray(obj) -> bool:
    xr = sys.modules.get("xarray")
    return xr is not None and isinstance(obj, xr.DataArray)


def _rtable_from_dataarray(da, what: str = "table") -> "RTable":
    import numpy as np

    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    from roadgonio.surface.rtable import RTable
    if set(da.dims) != {TAN_EPS, BETA}:
        raise InputError(f"expected a DataArray with dims ({TAN_EPS}, {BETA}), got {da.dims}", field=what)
    da = da.transpose(TAN_EPS, BETA)
    for dim, grid in ((TAN_EPS, TAN_EPS_GRID), (BETA, BETA_GRID_DEG)):
        got = np.asarray(da[dim].values, dtype=np.float64)
        if got.shape != grid.shape or np.max(np.abs(got - grid)) > 1e-9:
            raise InputError(f"the {dim} coordinate is not the CIE grid ({', '.join(f'{v:g}' for v in grid)})",
                             field=what)
    return RTable(np.asarray(da.values, dtype=np.float64), name=str(da.attrs.get("name", da.name or "table")),
                  source=str(da.attrs.get("source", "")))


def _dataarray(table: "RTable") -> "xr.DataArray":
    import xarray as xr
    return xr.DataArray(
        table.r.copy(), dims=(TAN_EPS, BETA),
        coords={TAN_EPS: (TAN_EPS, table.tan_eps.copy(), {"long_name": "tan(epsilon)", "units": "1"}),
                BETA: (BETA, table.beta_deg.copy(), {"long_name": "beta", "units": "deg"})},
        name="r", attrs={"name": table.name, "source": table.source, "units": "sr^-1",
                         "long_name": "reduced luminance coefficient r = q cos^3(epsilon)",
                         "note": "r itself, not r x 10^4; NaN = not measured"})


def read_table(path_or_name) -> "xr.DataArray":
    """An r-table (bundled name ``"R3"``, or a .csv/.rtb file) as an ``xarray.DataArray`` of r in
    sr^-1 (not r x 10^4) with the CIE grid coordinates ``tan_eps`` and ``beta`` (degrees); blank
    cells are NaN; ``attrs`` name and source."""
    from roadgonio.surface.rtable import RTable, load_table
    table = path_or_name if isinstance(path_or_name, RTable) else load_table(path_or_name)
    return _dataarray(table)


def write_table(da, path) -> Path:
    """Write an r-table DataArray (as from :func:`read_table`; an RTable works too) to ``path``:
    ``.rtb`` as DIALux RTB, anything else as CSV (both store r x 10^4, as published tables do)."""
    return _table(da).write(path)


# ----------------------------------------------------------------------------------------------
# fit, correct, uncertainty: thin wrappers of the rooms
# ----------------------------------------------------------------------------------------------

def fit(table, variant: str | None = None, *, seed: int = 0, fixed: Mapping[str, float] | None = None) -> "FitResult":
    """Fit the road BRDF model (paper eq. 4; ``variant`` default ``"power"``) to an r-table (name,
    file, RTable or DataArray). Returns the :class:`~roadgonio.surface.fit.FitResult`: ``.model``
    (a RoadModel, usable as a sample), ``.max_dev_pct``, ``.rms_dev_pct`` (% of the table's max r)."""
    from roadgonio.surface.fit import fit_table
    from roadgonio.surface.model import DEFAULT_VARIANT
    return fit_table(_table(table), variant or DEFAULT_VARIANT, seed=seed, fixed=dict(fixed or {}))


def correct(measured, instrument, *, reference="self", alternatives: str | Sequence[str] | None = "auto",
            u_measured: Any = "1%", sigma: Any = None, backend: str = "mitsuba", accuracy: str | None = None,
            rel_se: float | None = None, seed: int = 0, variant: str | None = None,
            model_variant: str | None = None, out: str | Path | None = None, progress: bool = False,
            **options: Any) -> "CorrectionResult":
    """Correct a measured r-table (name, file, RTable or DataArray) for the aperture effect, as
    ``roadgonio correct``: ``reference="self"`` (default) fits the model through the instrument, a
    SAMPLE (or a model) takes the classic route with ``alternatives`` (``"auto"``, ``"none"`` or
    SAMPLEs). ``u_measured`` (``"1%"``, a fraction, or an r-table file of standard uncertainties)
    and ``sigma`` (a misalignment SPEC) enter the uncertainty. Returns the
    :class:`~roadgonio.correction.CorrectionResult` (``.corrected`` and ``.u_corrected`` RTables,
    ``.k_a``, ``.budget``, ``.before`` / ``.after`` with S1, S2, Q0 and their u, ``.summary()``);
    with ``out`` its files are written there (``roadgonio.correction.write_correction``)."""
    from roadgonio.correction import correct_measured, write_correction
    from roadgonio.surface.model import RoadModel
    table = _table(measured, "measured")
    inst = _instrument(instrument)
    if isinstance(reference, str) and reference.strip().lower() == "self":
        ref: Any = "self"
        ref_name = None
    else:
        ref, ref_name, _ = _sample(reference, model_variant)
        if not isinstance(ref, RoadModel):  # pragma: no cover - _sample returns models
            raise InputError("expected a SAMPLE or 'self'", field="reference")

    def factory(ins, model):
        return _backend(backend, ins, model, accuracy=accuracy, seed=seed, variant=variant, rel_se=rel_se)
    _choose_variant(backend, variant)
    res = correct_measured(table, inst, reference=ref, reference_name=ref_name, alternatives=alternatives,
                           model_variant=model_variant, u_measured=u_measured, sigma=sigma, backend=backend,
                           factory=factory, seed=seed, out_dir=out, progress=progress, **options)
    if out is not None:
        write_correction(res, out)
    return res


def uncertainty(instrument, sample, sigma, *, trials: int = 50_000, adaptive: bool = False, seed: int = 1,
                coverage: float = 0.95, cells: str = "standard", aperture: bool = True, backend: str = "mitsuba",
                rel_se: float | None = None, illuminance: str = "nominal", surrogate: str = "ccd",
                validation: int = 4, model_variant: str | None = None, progress: bool = False,
                **options: Any) -> "UncertaintyResult":
    """Monte Carlo (JCGM 101) and GUM uncertainty of the r-table that ``instrument`` measures on
    ``sample`` for the instrument errors ``sigma`` (a SPEC text like ``"alpha_deg=0.01,eps_deg=0.05:rect"``,
    a TOML file, a mapping of the same keys, or a SigmaSpec), without and (``aperture=True``) with
    the aperture effect. Options as ``roadgonio uncertainty`` (more keywords of
    :func:`roadgonio.uncertainty.run_uncertainty` pass through ``options``). Returns the
    :class:`~roadgonio.uncertainty.UncertaintyResult`."""
    from roadgonio.engines.accuracy import rel_se_setting
    from roadgonio.uncertainty.run import DEFAULT_BACKEND_TOLERANCE, run_uncertainty
    from roadgonio.uncertainty.spec import SigmaSpec, parse_sigma_spec
    if isinstance(sigma, SigmaSpec):
        spec = sigma
    elif isinstance(sigma, (str, Path, Mapping)):
        spec = parse_sigma_spec(str(sigma) if isinstance(sigma, Path) else sigma, option="sigma")
    else:
        raise InputError(f"expected a SPEC text, a TOML file, a mapping or a SigmaSpec, got {type(sigma).__name__}",
                         field="sigma")
    inst = _instrument(instrument)
    model, _, _ = _sample(sample, model_variant)
    if backend not in DEFAULT_BACKEND_TOLERANCE:
        raise InputError(f"expected backend mitsuba or quadrature, got {backend!r}", field="backend")
    settings = rel_se_setting(backend, DEFAULT_BACKEND_TOLERANCE[backend] if rel_se is None else rel_se,
                              field="rel_se")
    if backend == "mitsuba":
        settings["seed"] = int(seed)
    if aperture:
        _choose_variant(backend, options.pop("variant", None))
    return run_uncertainty(model, inst, spec, trials=trials, adaptive=adaptive, seed=seed, coverage=coverage,
                           cells=cells, aperture=aperture, backend=backend, backend_settings=settings,
                           illuminance=illuminance, surrogate_design=surrogate, n_validation=validation,
                           progress=progress, **options)


def design(instrument, vary=None, samples="R3", *, tolerance: float | str = "5%", cells="all",
           backend: str = "mitsuba", accuracy: str | None = None, rel_se: float | None = None, seed: int = 0,
           workers: int | None = None, scheduler: str | None = None, client=None, out=None, fresh: bool = False,
           progress: bool = False, plots: bool = True, model_variant: str | None = None,
           variant: str | None = None) -> "xr.Dataset":
    """A design study (``roadgonio design``): k_A tables over a grid of instruments, on Dask.

    ``vary``: ``["source.radius_m=0.01:0.04:4", ...]`` or ``{key: values}``; ``samples``: one or more
    samples; ``cells``: ``"all"``, ``"table"`` or ``"T:B,T:B,..."``; ``workers``/``scheduler``/``client``:
    a local cluster of worker processes (default: one per core), an existing cluster, or
    ``workers=0`` for this process. Returns the ``xarray.Dataset`` of ``design.nc`` (``k_a``, ``se``
    over the varied keys x sample x tan_eps x beta; ``max_abs_dev``, ``signal``, ``feasible``,
    ``reason``... per point; provenance in ``attrs["provenance"]``); with ``out`` also writes
    design.csv, best.toml and the pictures (:mod:`roadgonio.design`). Scripts that start a local
    cluster must guard the call with ``if __name__ == "__main__":``.
    """
    from roadgonio.design.run import run_design
    from roadgonio.engines.accuracy import rel_se_setting
    settings: dict[str, Any] = {}
    if rel_se is not None:
        settings.update(rel_se_setting(backend, rel_se, field="rel_se"))
    if backend == "mitsuba" and variant is not None:
        settings["variant"] = variant
    if workers == 0 and scheduler is None and client is None:
        _choose_variant(backend, variant)          # this process computes: it is the entry point

    def one(x):
        if isinstance(x, (str, Path)):
            return str(x)
        model, name, _ = _sample(x, model_variant)       # RoadModel, RTable, DataArray, fit result
        return (name, model)

    many = isinstance(samples, (list, tuple)) and not (len(samples) == 2 and isinstance(samples[0], str)
                                                         and not isinstance(samples[1], (str, Path)))
    samples = [one(x) if not isinstance(x, tuple) else x for x in samples] if many else [
        samples if isinstance(samples, tuple) else one(samples)]
    return run_design(_instrument(instrument), vary, samples,
                      tolerance=tolerance, cells=cells, backend=backend, accuracy=accuracy, settings=settings,
                      seed=seed, workers=workers, scheduler=scheduler, client=client, out=out, fresh=fresh,
                      progress=progress, plots=plots, model_variant=model_variant)


def intercompare(study, out=None, *, workers: int | None = None, scheduler: str | None = None, client=None,
                 fresh: bool = False, progress: bool = False, plots: bool = True, variant: str | None = None):
    """A virtual intercomparison (``roadgonio intercompare STUDY --out DIR``): every participant of
    the study (a TOML file, a bundled study name or a :class:`roadgonio.intercomparison.study.Study`)
    measures its surface in many realisations; returns the
    :class:`~roadgonio.intercomparison.run.StudyRun` (``.dataset``: the ``xarray.Dataset`` of
    intercompare.nc). ``workers``/``scheduler``/``client`` as :func:`design` (default: a local
    cluster, one worker per core; ``workers=0`` computes here). With ``out`` the run is journalled
    (resumable) and its files are written there (:mod:`roadgonio.intercomparison.outputs`)."""
    from roadgonio.intercomparison.run import run_study
    from roadgonio.intercomparison.study import Study, load_study
    st = study if isinstance(study, Study) else load_study(study)
    if workers == 0 and scheduler is None and client is None:
        _choose_variant(st.backend, variant)          # this process computes: it is the entry point
    return run_study(st, out, workers=workers, scheduler=scheduler, client=client, fresh=fresh, progress=progress,
                     plots=plots, variant=variant)
