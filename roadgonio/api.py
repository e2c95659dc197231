"""The Python API of roadgonio: one function per command, for notebooks, scripts and the command
line (every ``roadgonio`` command parses its arguments and calls one function here; nothing
under :mod:`roadgonio.cli` resolves an input itself).

.. code-block:: python

    import roadgonio as rg
    ds = rg.ka_table("portable", "R3", backend="quadrature", accuracy="fast")   # xarray.Dataset
    ds.k_a.sel(tan_eps=12, beta=0)

=======================  ======================================================================
function                 what (command)
=======================  ======================================================================
:func:`list_tables`      the bundled CIE tables with Q0, S1, S2 (``tables``)
:func:`table_info`       one table's characteristics, optionally converted (``table``)
:func:`read_table`       an r-table as an ``xarray.DataArray`` of r (sr^-1); :func:`write_table`
:func:`read_ka_table`    a k_A table (``ka.csv``) as an ``xarray.DataArray`` of k_A
:func:`fit`              fit the road BRDF model (paper eq. 4) to a table (``fit``)
:func:`ka_table`         k_A over the CIE grid as an ``xarray.Dataset`` (``ka``)
:func:`ka_cell`          k_A at one cell, a :class:`~roadgonio.engines.result.CellResult` (``ka --tan-eps``)
:func:`render`           pictures of one cell with Mitsuba (``render``)
:func:`validate`         a Monte Carlo backend judged against a float64 reference (``validate``)
:func:`estimate_uncertainty`  JCGM 101 Monte Carlo uncertainty of the measured table (``uncertainty``)
:func:`correct`          correct measured tables for the aperture effect (``correct``)
:func:`design_study`     k_A over a grid of instruments on Dask (``design``)
:func:`intercompare`     a virtual key comparison of several instruments on Dask (``intercompare``)
:func:`road_metrics`     EN 13201 road metrics of a layout with r-tables (``road``; not ``road``: that
                         name is the room :mod:`roadgonio.road`)
:func:`compare_tables`   two tables side by side (``compare``)
:func:`classify_table`   the CIE class of a table (``classify``)
=======================  ======================================================================

Inputs are resolved in ONE place (the section "Inputs" below), each by its room's one resolver: an
instrument is a preset name (``"lab"``, ``"portable"``, ``"wide"``), a TOML file or an
:class:`~roadgonio.instrument.config.Instrument`; a sample is anything
:func:`roadgonio.surface.sample.resolve_sample` takes (``"lambert"``, a bundled table name, a
table or model file, a RoadModel, an RTable, an r-table DataArray, a fit result); cells are what
:func:`roadgonio.engines.cells.select_cells` takes; a backend, its accuracy preset, tolerance, seed
and Mitsuba variant are resolved by :mod:`roadgonio.engines.registry`. ``model_variant`` is the
road BRDF variant fitted to a table, ``mitsuba_variant`` the Mitsuba variant. Errors are
:class:`~roadgonio.errors.InputError` naming the argument (the command line shows the option).

The Mitsuba variant is process state: with a backend that needs Mitsuba these functions keep a
variant you already selected, else select ``mitsuba_variant`` (default ``llvm_ad_rgb``): they are
the entry point, like the ``roadgonio`` command. Nothing heavy is imported until a function runs.

``out``: a folder to write the outputs to (None: write nothing), or :data:`AUTO` for the default
folder the command uses (``out/ka-INSTRUMENT-SAMPLE``...; names made safe with
:func:`roadgonio.fileio.safe_name`).
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

from roadgonio.errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    import xarray as xr

    from roadgonio.engines.result import CellResult
    from roadgonio.instrument.config import Instrument
    from roadgonio.surface.fit import FitResult
    from roadgonio.surface.rtable import RTable
    from roadgonio.surface.sample import ResolvedSample
    from roadgonio.uncertainty.run import UncertaintyResult

__all__ = ["AUTO", "list_tables", "table_info", "read_table", "read_ka_table", "write_table", "fit", "ka_table", "ka_cell", "render",
           "validate", "estimate_uncertainty", "correct", "design_study", "second_aperture", "intercompare",
           "road_metrics", "compare_tables",
           "classify_table"]


class _Auto:
    """The default output folder of a command (``out=AUTO``)."""

    def __repr__(self) -> str:
        return "AUTO"


AUTO = _Auto()


# ----------------------------------------------------------------------------------------------
# Inputs: resolved here, once, by the rooms' resolvers
# ----------------------------------------------------------------------------------------------

def _instrument(instrument, field: str = "instrument") -> "Instrument":
    """An Instrument from a preset name, a TOML file or an Instrument (a file's path made absolute,
    so that relative mesh and XML paths never depend on the working folder later)."""
    from roadgonio.instrument.config import Instrument, load_instrument
    if isinstance(instrument, Instrument):
        return instrument
    if isinstance(instrument, (str, Path)) and str(instrument).strip():
        p = Path(instrument).expanduser()
        return load_instrument(p.resolve() if p.exists() else instrument)
    raise InputError("expected an instrument preset name, a TOML file or an Instrument, got "
                     f"{type(instrument).__name__} {instrument!r}", field=field)


def _sample(sample, model_variant: str | None = None, field: str = "sample") -> "ResolvedSample":
    from roadgonio.surface.sample import resolve_sample
    return resolve_sample(sample, model_variant, field=field)


def _table(table, field: str = "table", quantity: str = "r") -> "RTable":
    """An RTable from a bundled name, a .csv/.rtb file, an RTable or an r-table DataArray
    (``quantity="u"``: a table of standard uncertainties, :func:`~roadgonio.surface.rtable.load_table`)."""
    from roadgonio.surface.rtable import load_table
    from roadgonio.surface.sample import _as_table
    t = _as_table(table)
    if t is not None:
        return t
    if isinstance(table, (str, Path)):
        try:
            return load_table(table, quantity)
        except InputError as err:
            if err.path is not None:
                raise err.with_argument(field) from None
            raise InputError(err.reason, field=field) from None
    raise InputError("expected a bundled table name, a .csv/.rtb file, an RTable or an r-table DataArray, got "
                     f"{type(table).__name__}", field=field)


def _table_and_notes(table, field: str = "table") -> "tuple[RTable, list[str]]":
    """:func:`_table` and how the file was read (:class:`~roadgonio.errors.ReadingNote`s, kept for a
    command that lists its notes in its result instead of saying them; other notes are said)."""
    import warnings

    from roadgonio.errors import ReadingNote
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        t = _table(table, field)
    notes = []
    for w in said:
        if issubclass(w.category, ReadingNote):
            notes.append(str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return t, notes


def _labelled(table, t: "RTable") -> "RTable":
    """A table read from a file, named by the file (``measured.rtb (R3)`` when the file stores another
    name, as an RTB does; ``r3.csv``): the results of road and compare say which file they compared."""
    if not isinstance(table, (str, Path)) or not Path(str(table)).suffix:
        return t
    p = Path(str(table))
    label = p.name if t.name == p.stem else f"{p.name} ({t.name})"
    return t.with_values(t.r, name=label)


def _check_int(value, field: str, lo: int = 0, hi: int | None = None) -> int:
    """A whole number lo <= value <= hi (not a bool, not a float), or an InputError naming ``field``."""
    import numbers
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InputError(f"expected a whole number, got {value!r}", field=field)
    v = int(value)
    if v < lo or (hi is not None and v > hi):
        raise InputError(f"expected a whole number from {lo} to {hi}, got {v}" if hi is not None
                         else f"expected a whole number >= {lo}, got {v}", field=field)
    return v


def _backend(backend: str, instrument, model, *, accuracy: str | None = None, rel_se=None, seed=None,
             mitsuba_variant: str | None = None, settings: Mapping[str, Any] | None = None):
    """The backend, built through the registry after the entry point's choice of the Mitsuba variant."""
    from roadgonio.engines.registry import backend_info, make_backend, prepare_entry_point
    backend_info(backend)
    prepare_entry_point(backend, mitsuba_variant)
    return make_backend(backend, instrument, model, accuracy=accuracy, tolerance=rel_se, seed=seed,
                        mitsuba_variant=mitsuba_variant, settings=settings, fields={"tolerance": "rel_se"})


def _out(out, kind: str, *names: str, auto: Path | None = None) -> Path | None:
    """The output folder: None, the given folder, or for :data:`AUTO` ``auto`` (default
    ``out/KIND-NAME-...``), checked by :func:`_results_folder`."""
    if out is None:
        return None
    if isinstance(out, _Auto):
        from roadgonio.fileio import safe_name
        return _results_folder(auto or Path("out") / "-".join([kind] + [safe_name(n) for n in names]))
    if not isinstance(out, (str, Path)) or not str(out).strip():
        raise InputError(f"expected a folder name, got {out!r}", field="out")
    return _results_folder(Path(out))


def _results_folder(folder: Path) -> Path:
    """Every command's check of its output folder (trial 11 D10): a folder, or a path where one can
    be made; a file there (or in place of a folder above it) is the one-line error saying a folder
    was expected, instead of the system's "File exists" about the first output file."""
    if folder.exists() and not folder.is_dir():
        raise InputError("expected a folder for the results, but it is a file", path=folder, field="out")
    for above in folder.parents:
        if above.exists():
            if not above.is_dir():
                raise InputError(f"expected a folder for the results, but {above} is a file", path=folder,
                                 field="out")
            break
    return folder


def _show(progress) -> bool:
    return bool(progress)


def _check_flags(**flags) -> None:
    """Each of ``flags`` True or False (a numpy bool too), or an InputError naming it (audit 22:
    design_study(fresh="no") threw the journal away, plots="no" drew the pictures)."""
    import numpy as np
    for name, value in flags.items():
        if not isinstance(value, (bool, np.bool_)):
            raise InputError(f"expected True or False, got {value!r}", field=name)


def _check_cluster(workers, client) -> None:
    """``workers`` None or a whole number >= 0, ``client`` None or a Dask client (audit 22:
    workers=True was taken as one worker, client="x" ended in an AttributeError)."""
    if workers is not None:
        _check_int(workers, "workers", 0)
    if client is not None and not (hasattr(client, "submit") and hasattr(client, "scheduler_info")):
        raise InputError(f"expected a dask.distributed Client, got {type(client).__name__}", field="client")


# ----------------------------------------------------------------------------------------------
# What there is to choose from (the command line's choices)
# ----------------------------------------------------------------------------------------------

def max_local_workers() -> int:
    """The most worker processes a local Dask cluster may have on this machine (``--workers``):
    :func:`roadgonio.engines.cluster.max_local_workers`."""
    from roadgonio.engines.cluster import max_local_workers as most
    return most()


#: What a command needs of its k_A backend, as capabilities of the registry
#: (:func:`roadgonio.engines.registry.backends_with`): the command line's ``--backend`` choices
#: (:func:`backends`) and this module's check (:func:`_command_backend`) are the same query.
BACKEND_NEEDS: dict[str, dict[str, Any]] = {"ka": {}, "design": {}, "correct": {},
                                            "uncertainty": {"study_tolerance": True},
                                            "intercompare": {"study_tolerance": True}}


def backends(command: str | None = None) -> dict[str, str]:
    """The k_A backends of the registry (those ``command`` takes: :data:`BACKEND_NEEDS`), name ->
    one-line summary."""
    from roadgonio.engines.registry import BACKENDS, backends_with
    return {n: BACKENDS[n].summary for n in backends_with(**(BACKEND_NEEDS[command] if command else {}))}


def validate_backends(role: str) -> tuple[str, ...]:
    """The backends ``validate`` takes as ``against`` (``role="checked"``) or as its float64
    ``reference`` (``role="reference"``), from the registry."""
    from roadgonio.engines.registry import validate_backends as of_role
    return of_role(role)


def study_tolerances() -> dict[str, tuple[str, float]]:
    """The default tolerance of the k_A tables of ``uncertainty`` and ``intercompare``, by backend:
    name -> (its setting, ``rel_se`` or ``rtol``; the value)."""
    from roadgonio.engines.registry import BACKENDS, backends_with
    return {n: (BACKENDS[n].tolerance, BACKENDS[n].study_tolerance) for n in backends_with(study_tolerance=True)}


def _command_backend(command: str, backend: str, field: str = "backend"):
    """The registry entry of ``backend`` if ``command`` takes it (an InputError listing those it takes)."""
    from roadgonio.engines.registry import check_backend
    return check_backend(backend, field, purpose=command, **BACKEND_NEEDS[command])


def accuracy_presets() -> tuple[str, ...]:
    from roadgonio.engines.registry import PRESETS
    return PRESETS


def model_variants() -> tuple[str, ...]:
    from roadgonio.surface.model import VARIANTS
    return VARIANTS


def instrument_presets() -> list[str]:
    from roadgonio.instrument.config import bundled_instruments
    return bundled_instruments()


def figure_process(enabled: bool = True):
    """A helper process that draws the pictures while the computation runs (a context manager,
    :class:`roadgonio.plotproc.FigureProcess`): pass it as ``figures=`` to the functions that draw."""
    from roadgonio.plotproc import FigureProcess
    return FigureProcess(enabled=enabled)


def validation_report_json(report: Mapping[str, Any]) -> dict[str, Any]:
    """The JSON document of a :func:`validate` report (validate.json, ``--json``)."""
    from roadgonio.engines.validate import report_json
    return report_json(report)


def validation_summary_line(report: Mapping[str, Any]) -> str:
    from roadgonio.engines.validate import summary_line
    return summary_line(report)


def validation_failed_line(report: Mapping[str, Any]) -> str:
    """The ``FAILED:`` line of a :func:`validate` report: the cells that disagree, each by its
    difference in SE, or as not measured (a NaN k_A)."""
    from roadgonio.engines.validate import failed_line
    return failed_line(report["rows"])


def sigma_spec_help() -> tuple[str, dict[str, str]]:
    """The help text of a misalignment SPEC and of its keys (``roadgonio uncertainty --help``)."""
    from roadgonio.uncertainty.spec import INPUT_HELP, SPEC_HELP
    return SPEC_HELP, dict(INPUT_HELP)


def uncertainty_result_json(res, cells: bool = False) -> dict[str, Any]:
    """The JSON summary of an :func:`estimate_uncertainty` result (uncertainty.json without the cells)."""
    from roadgonio.uncertainty.report import result_dict
    return result_dict(res, cells=cells)


def uncertainty_summary_lines(res) -> list[str]:
    from roadgonio.uncertainty.report import summary_lines
    return list(summary_lines(res))


def uncertainty_not_converged(res) -> tuple[int, str | None]:
    """The exit status of ``roadgonio uncertainty`` for a result (3 when an adaptive run stopped at its
    cap before its target, else 0) and the one line that says which target and at what cap (None when 0)."""
    from roadgonio.uncertainty.report import NOT_CONVERGED_EXIT_STATUS, not_converged_line
    line = not_converged_line(res)
    return (0, None) if line is None else (NOT_CONVERGED_EXIT_STATUS, line)


def design_keys() -> tuple[str, ...]:
    """The instrument keys a design study can vary (``--vary KEY=...``)."""
    from roadgonio.design.grid import ALL_KEYS
    return tuple(ALL_KEYS)


def design_summary(ds) -> dict[str, Any]:
    """The summary of a :func:`design_study` Dataset: points, feasible, best design, timings."""
    from roadgonio.design.dataset import summary
    import json
    s = summary(ds)
    s.setdefault("instrument", json.loads(ds.attrs["base_instrument_json"]).get("instrument", {}).get("name", ""))
    return s


def precision_text(summary: Mapping[str, Any]) -> str:
    """'worst rel. SE 1.5e-04' or 'worst rel. error bound 9.9e-04' of a k_A summary."""
    from roadgonio.engines.runner import precision_text as _text
    return _text(summary)


def to_json(obj, indent: int | None = 2) -> str:
    """JSON text of a result (NaN and infinity as null): :func:`roadgonio.fileio.to_json`."""
    from roadgonio.fileio import to_json as _to_json
    return _to_json(obj, indent=indent)


# ----------------------------------------------------------------------------------------------
# r-tables
# ----------------------------------------------------------------------------------------------

def list_tables() -> list[dict[str, Any]]:
    """The bundled CIE tables R1-R4, C1, C2: Q0, S1, S2 computed beside the published values, and
    the number of tabulated cells (``roadgonio tables``)."""
    from roadgonio.surface.rtable import BUNDLED, PUBLISHED_Q0, PUBLISHED_S1, bundled_table
    rows = []
    for name in BUNDLED:
        t = bundled_table(name)
        rows.append({"table": name, "Q0": _value(t.q0()), "Q0_published": PUBLISHED_Q0[name], "S1": _value(t.s1()),
                     "S1_published": PUBLISHED_S1[name], "S2": _value(t.s2()), "cells": int(t.mask.sum())})
    return rows


def table_info(table, to: str | Path | None = None) -> dict[str, Any]:
    """A table's Q0, S1, S2, cells and max r (``roadgonio table``); with ``to`` it is also written
    there (``.rtb``: DIALux RTB, ``.csv``: CSV) and ``written`` names the file. A characteristic the
    table lacks the cells for (S1 without r(0, 0) > 0 and r(2, 0); Q0 without a grid cell with four
    tabulated corners; S2 without both) is None (missing), never NaN or infinity."""
    t, read = _table_and_notes(table)
    info = {"table": t.name, "Q0": _value(t.q0()), "S1": _value(t.s1()), "S2": _value(t.s2()),
            "cells": int(t.mask.sum()), "r_max": _value(t.r_max)}
    # a Q0 over other cells than the standard tables' is said here too, as classify and compare say it
    # (user audit, session 41: two blank cells gave Q0 2.9 % low without a word)
    from roadgonio.surface.rtable import q0_coverage_note
    note = q0_coverage_note(t)
    info["notes"] = [note] if note else []
    # how an RTB file was read, when the reader had something to say (its scale told by the q0 line,
    # a q0 line off the values' Q0): audit 22, it was only in the table's source. Of the RTB file
    # itself only: a CSV converted from it keeps that source as its header, and its values need no note
    if read:        # the RTB reader's own words, without the file's name the note adds
        from roadgonio.surface.rtable import rtb_reading_note
        info["reading_note"] = rtb_reading_note(t, Path(str(table)))
    if to is not None:
        info["written"] = str(t.write(_table_file(to, "to")))
        # 6 significant digits can move S1 across a class limit it sits on (user audit, session 44:
        # S1 3.3e-7 below 0.85 was R2, the file written R3): said, not silently changed
        from roadgonio.surface.cie import cie_class
        back, _ = _table_and_notes(info["written"], "to")
        before, after = cie_class(t.s1()), cie_class(back.s1())
        moved = [f"{before[k]} -> {after[k]}" for k in before if before[k] != after[k]]
        if moved:
            info["notes"].append(f"the file written has S1 {back.s1():.9g} for {t.s1():.9g} (values to 6 significant "
                                 f"digits), across a class limit: {', '.join(moved)}")
    return info


def _table_file(path, field: str) -> Path:
    """A file an r-table is written to: .csv or .rtb (the two formats every command reads back;
    'x.xlsx' got CSV text that `ka --sample` then refused)."""
    if not isinstance(path, (str, Path)):       # audit 22: table_info(to=5) raised a TypeError
        raise InputError(f"expected the path of a .csv or .rtb file, got {type(path).__name__}", field=field)
    if not str(path).strip():       # Path("") is "." (user audit, session 44: the error named the file ".")
        raise InputError("expected the path of a .csv or .rtb file to write the table to, got an empty text",
                         field=field)
    path = Path(path)
    if path.suffix.lower() not in (".csv", ".rtb"):
        raise InputError(f"expected a .csv or .rtb file to write the table to, got '{path.suffix or path.name}'",
                         path=path, field=field)
    return path


def _value(v) -> float | None:
    """A quantity of a result: a finite float, or None when it is missing (never NaN or infinity)."""
    return float(v) if v is not None and math.isfinite(v) else None


def read_table(path_or_name) -> "xr.DataArray":
    """An r-table (bundled name ``"R3"``, or a .csv/.rtb file) as an ``xarray.DataArray`` of r in
    sr^-1 (not r x 10^4) with the CIE grid coordinates ``tan_eps`` and ``beta`` (degrees); blank
    cells are NaN; ``attrs`` name and source."""
    return _table(path_or_name).to_dataarray()


def read_ka_table(path) -> "xr.DataArray":
    """A k_A table file (``ka.csv`` or ``ka_direct.csv`` of ``roadgonio ka``: the r-table layout,
    k_A unscaled, its header ``# k_A of ...``) as an ``xarray.DataArray`` of k_A on the CIE grid,
    NaN where not computed. :func:`read_table` refuses such a file (it is not an r-table), and this
    refuses a file without that header."""
    from roadgonio.surface.rtable import read_ka_table as _read
    if not isinstance(path, (str, Path)):
        raise InputError(f"expected the path of a k_A table (ka.csv), got {type(path).__name__}", field="path")
    try:
        return _read(Path(path).expanduser())
    except InputError as err:
        raise err.with_argument("path") from None


def write_table(da, path) -> Path:
    """Write an r-table DataArray (as from :func:`read_table`; an RTable works too) to ``path``:
    ``.rtb`` as DIALux RTB, ``.csv`` as CSV (both store r x 10^4, as published tables do; another
    suffix is an :class:`InputError`). The CSV header is ``attrs["source"]`` (the RTB's name line
    ``attrs["name"]``): a table computed from another keeps that one's attrs (xarray arithmetic),
    so give it its own ``source`` (README's example)."""
    return _table(da).write(_table_file(path, "path"))     # a path of another type: _table_file's InputError


# ----------------------------------------------------------------------------------------------
# fit
# ----------------------------------------------------------------------------------------------

def fit(table, model_variant: str | None = None, *, seed: int = 0, fixed: Mapping[str, float] | None = None,
        out=None, fresh: bool = False, plot: bool = True,
        progress: bool | Callable[[int, int], None] = False) -> "FitResult":
    """Fit the road BRDF model (paper eq. 4; ``model_variant`` default ``"power"``) to an r-table
    (name, file, RTable or DataArray). Returns the :class:`~roadgonio.surface.fit.FitResult`:
    ``.model`` (a RoadModel, usable as a sample), ``.max_dev_pct``, ``.rms_dev_pct`` (% of the
    table's max r). With ``out`` (a folder or :data:`AUTO` = ``fit-TABLE-VARIANT``) it writes
    model.json, residuals.csv and (``plot``) fit.png, all or none; ``.written`` lists them. A
    folder holding a different fit's results (model.json's fingerprint: table, variant, seed,
    fixed parameters, roadgonio version) is refused before the fit unless ``fresh``, which
    replaces them. ``progress``: True shows a bar on a terminal (as every command's), or a callable
    ``progress(done, total)`` called as the global search advances."""
    from roadgonio.engines.registry import check_seed
    from roadgonio.surface.model import DEFAULT_VARIANT, PARAM_NAMES, VARIANTS
    from roadgonio.surface.sample import check_not_degenerate, note_capped_exponent, note_unresolved_spike
    variant = model_variant or DEFAULT_VARIANT
    if variant not in VARIANTS:
        raise InputError(f"unknown model variant {variant!r}; expected one of {', '.join(VARIANTS)}",
                         field="model_variant")
    seed = check_seed(seed)
    fixed = dict(fixed or {})
    for name, value in fixed.items():
        if name not in PARAM_NAMES:
            raise InputError(f"expected NAME=VALUE with NAME one of {', '.join(PARAM_NAMES)}, got {name!r}",
                             field="fixed")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"expected a finite number for {name}, got {value!r}", field="fixed")
    t = _table(table)
    from roadgonio.surface.rtable import check_positive
    check_positive(t, table if isinstance(table, (str, Path)) and Path(str(table)).suffix else None, field="table")
    folder = None
    if out is not None:
        folder = _out(out, "fit", auto=Path(f"fit-{_safe(t.name)}-{variant}"))
    from roadgonio.fileio import check_run_folder, fingerprint
    from roadgonio.surface.fit import FIT_METHOD_VERSION, table_hash
    fp = fingerprint({"table": table_hash(t), "name": t.name, "variant": variant, "seed": seed,
                      "fixed": dict(sorted(fixed.items())), "fit": FIT_METHOD_VERSION})
    if folder is not None:
        from roadgonio.fileio import check_writable
        check_run_folder(folder, "model.json", fp, what="fit", fresh=bool(fresh))
        check_writable(folder)          # an unwritable folder fails now, not after the fit
    result = _fit_with_progress(t, variant, seed, fixed, progress)
    check_not_degenerate(result.model, path=table if isinstance(table, (str, Path)) and Path(table).suffix else None)
    note_unresolved_spike(result.model, t.name, fitted=True, option="--variant")   # fit's own option (audit, session 41)
    note_capped_exponent(result.model, t.name, fitted=True)
    if folder is not None:
        import dataclasses

        from roadgonio.provenance import input_record, provenance
        from roadgonio.surface.fitplot import write_fit
        prov = provenance(inputs=[input_record("table", table)],
                          settings={"model_variant": variant, "seed": seed, "fixed": dict(sorted(fixed.items())),
                                    "method_version": FIT_METHOD_VERSION})
        result = dataclasses.replace(result, written=write_fit(result, folder, plot=plot, fingerprint=fp,
                                                               provenance=prov))
    return result


def _fit_with_progress(t, variant: str, seed: int, fixed: dict, progress):
    """fit_table with ``progress`` a callable, or True for a bar (closed however the fit ends)."""
    from roadgonio.surface.fit import fit_table
    if callable(progress) or not progress:
        return fit_table(t, variant, seed=seed, fixed=fixed, progress=progress or None)
    from roadgonio.progress import bar
    b = bar(1, f"fit {t.name} ({variant})", unit="gen", leave=False)

    def tick(done: int, total: int) -> None:
        if b is not None:
            b.total, b.n = total, done
            b.refresh()
    try:
        return fit_table(t, variant, seed=seed, fixed=fixed, progress=tick)
    finally:
        if b is not None:
            b.close()


def _safe(name: str) -> str:
    from roadgonio.fileio import safe_name
    return safe_name(name)


# ----------------------------------------------------------------------------------------------
# k_A
# ----------------------------------------------------------------------------------------------

def ka_table(instrument, sample, *, backend: str = "mitsuba", accuracy: str | None = None, cells="all",
             seed: int | None = None, mitsuba_variant: str | None = None, rel_se: float | None = None,
             settings: Mapping[str, Any] | None = None, model_variant: str | None = None, out=None,
             fresh: bool = False, progress: bool = False, plot: bool = True, figures=None) -> "xr.Dataset":
    """The aperture-effect factor k_A of ``instrument`` for ``sample`` over the CIE grid.

    Parameters
    ----------
    instrument, sample:
        As on the command line, or objects (module docstring).
    backend:
        A backend of the registry (:data:`roadgonio.engines.registry.BACKENDS`): ``"mitsuba"``
        (float32 ray tracing), ``"quadrature"`` (deterministic float64), ``"reference"`` (float64
        randomised QMC), ``"numpy-mc"``, ``"numpy-mc-mesh"``.
    accuracy:
        ``"fast"``, ``"default"`` or ``"precise"`` (the backend's presets); None = the backend's
        defaults (= ``"default"``). ``rel_se`` (the one relative target: a standard error or a
        tolerance, as the backend takes it) and ``settings`` (backend keywords) override it.
    cells:
        ``"all"`` (580 cells), ``"table"`` (the cells tabulated in the sample's r-table), a text
        ``"T:B,..."`` or a list of (tan_eps, beta) grid cells.
    seed:
        Seed of the Monte Carlo and RQMC backends (same seed, same numbers; default 0); an error for
        a deterministic backend.
    out, fresh:
        With ``out`` the cells are journalled (an interrupted run resumes; ``fresh`` discards an
        earlier run's results) and ka.nc, ka.csv, ka_se.csv / ka_bound.csv, ka.png, ka.json are
        written (:func:`roadgonio.engines.runner.write_outputs`). The folder keeps one table per
        run: the files hold every cell its journal holds for this run (same instrument, model,
        backend and settings), the cells asked (computed now or read back) and those of earlier
        runs, so ``cells`` asking for a few cells into a folder with the full table leaves the full
        table in the files.

    Returns
    -------
    xarray.Dataset
        What ka.nc holds (:func:`roadgonio.engines.runner.ka_dataset`): ``k_a``, ``se`` (standard
        error), ``error_bound`` (deterministic bound), ``confidence_bound`` and ``confidence_level``,
        ``samples``, ``seconds``, ``converged`` over ``tan_eps`` (29) x ``beta`` (20, degrees), at
        the cells asked and, with ``out``, every other cell the folder's table holds for this run
        (above); NaN where not computed. ``attrs["cells_asked"]`` and ``attrs["resumed_cells"]``
        count this call's selection and the part of it read back, ``attrs["cells_computed"]`` the
        table's cells; the provenance in ``attrs["provenance"]`` (JSON), the summary in
        ``attrs["summary"]`` and the output folder in ``attrs["out"]`` when written.
    """
    from roadgonio.engines.cells import select_cells
    from roadgonio.engines.runner import ka_dataset, run_cells, summary, write_outputs
    inst = _instrument(instrument)
    smp = _sample(sample, model_variant)
    todo = select_cells(cells, smp.table, on_grid=True)
    b = _backend(backend, inst, smp.model, accuracy=accuracy, rel_se=rel_se, seed=seed,
                 mitsuba_variant=mitsuba_variant, settings=settings)
    folder = _out(out, "ka", inst.name, smp.name)
    run = run_cells(b, todo, instrument=inst, model=smp.model, out_dir=folder, fresh=fresh, progress=_show(progress),
                    field="cells")
    ds = ka_dataset(run, instrument=inst, model=smp.model, backend=b, sample=smp.name, accuracy=accuracy, seed=seed,
                    cells_asked=len(todo))
    if folder is not None:
        meta = write_outputs(ds, folder, plot=plot, figures=figures)
        ds.attrs["out"] = str(folder)
        ds.attrs["files"] = ", ".join(f for k, f in meta["files"].items() if f and k != "journal")
    from roadgonio.fileio import to_json
    ds.attrs["summary"] = to_json(summary(ds), indent=None)
    return ds


def ka_cell(instrument, sample, tan_eps: float, beta: float, *, backend: str = "mitsuba",
            accuracy: str | None = None, seed: int | None = None, mitsuba_variant: str | None = None,
            rel_se: float | None = None, model_variant: str | None = None,
            settings: Mapping[str, Any] | None = None, out=None, fresh: bool = False,
            progress: bool = False) -> "CellResult":
    """k_A at one cell (tan eps, beta in degrees; any cell, not only the grid's) as a
    :class:`~roadgonio.engines.result.CellResult` (``k_a``, ``se``, ``error_bound``,
    ``confidence_bound``, ``converged``, ``samples``, ``seconds``). Arguments as for
    :func:`ka_table`; with ``out`` the cell is journalled there (run again: read back).
    ``progress``: a backend that works long on the cell shows its bar (on a terminal)."""
    from roadgonio.engines.cells import check_cell
    from roadgonio.engines.runner import run_cells
    t, bdeg = check_cell(tan_eps, beta, "tan_eps", "beta")
    inst = _instrument(instrument)
    smp = _sample(sample, model_variant)
    b = _backend(backend, inst, smp.model, accuracy=accuracy, rel_se=rel_se, seed=seed,
                 mitsuba_variant=mitsuba_variant, settings=settings)
    _note_beyond_the_table(inst, smp, [(t, bdeg)])
    folder = _out(out, "ka", inst.name, smp.name)
    run = run_cells(b, [(t, bdeg)], instrument=inst, model=smp.model, out_dir=folder, fresh=fresh, progress=False,
                    field="tan_eps/beta", step_progress=_show(progress))
    cell = run.results[0]
    if run.resumed:
        object.__setattr__(cell, "extra", {**(cell.extra or {}), "resumed": True})
    return cell


def _note_beyond_the_table(inst, smp, cells) -> None:
    """The note for cells beyond the r-tables' last row (tan eps 12) when the sample's model is a
    table's fit (its values there are an extrapolation), said once for the farthest cell; one rule
    for ``ka``, ``render``, ``validate`` and ``design`` (user audit, session 19). The geometry's refusal comes
    first: a note and then an error were two lines for one mistake (tan eps 100 puts the source below
    the horizon). ``inst`` None (``design``, whose points' geometry is judged point by point)
    skips the geometry."""
    from roadgonio.geometry import TAN_EPS_GRID
    beyond = [c for c in cells if c[0] > TAN_EPS_GRID[-1]]
    if not beyond or (smp.table is None and not (smp.model.meta or {}).get("table")):
        return
    import warnings

    from roadgonio.errors import ModelWarning
    if inst is not None:
        from roadgonio.instrument.optics import check_source_cells
        check_source_cells(inst, beyond)
    t = max(c[0] for c in beyond)
    warnings.warn(ModelWarning(f"tan eps {t:g} is beyond the r-tables' last row (tan eps {TAN_EPS_GRID[-1]:g}): "
                               f"the model of {smp.name} there is an extrapolation of its fit, not a "
                               "measured value"), stacklevel=3)


def render(instrument, sample, tan_eps: float, beta: float, out, *, resolution: int = 256, spp: int = 64,
           seed: int = 0, mitsuba_variant: str | None = None, model_variant: str | None = None) -> dict[str, Any]:
    """Pictures of one measurement cell with Mitsuba (``roadgonio render``): the detector's view of the
    sample (luminance inside the field stop) and the horizontal illuminance around the footprint, as
    view.exr, illuminance.exr, render.png and render.json in ``out``; returns render.json's content
    (provenance, footprint, a one-render k_A estimate, files). ``seed``: 0 ... 2^32 - 1 (Mitsuba's
    samplers take a 32-bit seed)."""
    from roadgonio.engines.cells import check_cell
    from roadgonio.engines.registry import prepare_entry_point
    from roadgonio.seeds import MITSUBA_SEED_MAX, check_seed
    t, bdeg = check_cell(tan_eps, beta, "tan_eps", "beta")
    resolution = _check_int(resolution, "resolution", 8, 2048)
    spp = _check_int(spp, "spp", 1)
    from roadgonio.limits import check_size
    check_size(resolution * resolution * spp, "render_samples", "spp")
    if math.isqrt(spp) ** 2 != spp:
        raise InputError(f"expected a square number of samples per pixel (4, 16, 64...), got {spp}", field="spp")
    seed = check_seed(seed, maximum=MITSUBA_SEED_MAX)
    inst = _instrument(instrument)
    smp = _sample(sample, model_variant)
    _note_beyond_the_table(inst, smp, [(t, bdeg)])
    folder = _out(out, "render", inst.name, smp.name)
    if folder is None:
        raise InputError("render writes pictures: give an output folder", field="out")
    prepare_entry_point("mitsuba", mitsuba_variant)
    from roadgonio.engines.mitsuba.images import render_cell_images
    return render_cell_images(inst, smp.model, t, bdeg, folder, resolution=resolution, spp=spp, seed=seed,
                              mitsuba_variant=mitsuba_variant, sample_name=smp.name)


def validate(instrument, sample, *, against: str = "mitsuba", reference: str = "auto", cells="extremes",
             rel_se: float = 1e-3, rtol: float | None = None, ref_max_evals: int | None = None, seed: int = 0,
             floor: float | None = None, mitsuba_variant: str | None = None, model_variant: str | None = None,
             out=None, on_cell: Callable | None = None) -> dict[str, Any]:
    """A Monte Carlo backend (``against``) judged cell by cell against a float64 reference
    (:mod:`roadgonio.engines.validate`): returns the report (``verdict``, ``exit_status``,
    ``counts``, ``rows``...); with ``out`` writes validate.csv, validate.json and validate.png.
    ``on_cell(row)`` is called as each cell is judged."""
    from roadgonio.engines import validate as V
    from roadgonio.engines.cells import select_cells
    from roadgonio.engines.registry import check_relative, check_seed, prepare_entry_point
    check_relative(rel_se, "rel_se")
    if rtol is not None:
        check_relative(rtol, "rtol")
    if floor is not None and not (isinstance(floor, (int, float)) and not isinstance(floor, bool)
                                  and math.isfinite(floor) and floor >= 0):
        # (user audit: floor='1' said "got 1", as if the value were wrong and not its type)
        raise InputError(f"expected a number >= 0 (a relative floor), got {type(floor).__name__} {floor!r}",
                         field="floor")
    ref_settings = {}
    if ref_max_evals is not None:
        ref_settings["max_evals"] = _check_int(ref_max_evals, "ref_max_evals", 1)
    seed = check_seed(seed)
    todo = select_cells(cells, None)
    inst = _instrument(instrument)
    smp = _sample(sample, model_variant)
    _note_beyond_the_table(inst, smp, todo)
    folder = _out(out, "validate", inst.name, smp.name)
    if folder is not None:
        from roadgonio.fileio import check_writable
        check_writable(folder)          # an unwritable folder fails now, not after the computation
    prepare_entry_point(against, mitsuba_variant)
    report = V.validate(inst, smp.model, todo, against=against, reference=reference, rel_se=rel_se, rtol=rtol,
                        seed=seed, floor=floor, mitsuba_variant=mitsuba_variant, ref_settings=ref_settings,
                        on_cell=on_cell)
    from roadgonio.provenance import provenance
    report["provenance"] = provenance(instrument=inst, model=smp.model, settings=report["settings"])
    report["sample"] = smp.name
    if folder is not None:
        report["files"] = {k: str(v) for k, v in V.write_outputs(report, folder).items()}
        report["out"] = str(folder)
    return report


# ----------------------------------------------------------------------------------------------
# uncertainty, correction, design
# ----------------------------------------------------------------------------------------------

#: ``estimate_uncertainty``'s options of the case with the aperture effect (the surrogate's exact k_A
#: tables), with their defaults; given with ``aperture=False`` they are an error (nothing uses them)
UNCERTAINTY_APERTURE_DEFAULTS = {"backend": "mitsuba", "rel_se": None, "surrogate": "ccd", "validation": 4,
                                 "workers": None, "scheduler": None, "mitsuba_variant": None}


#: The adaptive uncertainty run's cap on trials when none is given (``max_trials``).
MAX_TRIALS_DEFAULT = 200_000


def estimate_uncertainty(instrument, sample, sigma, *, trials: int = 50_000, adaptive: bool = False,
                         digits: int = 2, max_trials: int | None = None, batch: int | None = None, seed: int = 1,
                         coverage: float = 0.95, cells: str = "standard", aperture: bool = True,
                         backend: str | None = None, rel_se: float | None = None, illuminance: str = "nominal",
                         surrogate: str | None = None, validation: int | None = None, threads: int | None = None,
                         workers: int | None = None, scheduler: str | None = None,
                         mitsuba_variant: str | None = None, model_variant: str | None = None,
                         out=None, fresh: bool = False, plots: bool = True, figures=None,
                         progress: bool = False) -> "UncertaintyResult":
    """Monte Carlo (JCGM 101) and GUM uncertainty of the r-table that ``instrument`` measures on
    ``sample`` for the instrument errors ``sigma`` (a SPEC text like ``"alpha_deg=0.01,eps_deg=0.05:rect"``,
    a TOML file, a mapping of the same keys, or a SigmaSpec), without and (``aperture``) with the
    aperture effect (``roadgonio uncertainty``). Returns the
    :class:`~roadgonio.uncertainty.run.UncertaintyResult`; with ``out`` (a folder or :data:`AUTO`)
    writes uncertainty.json, cells.csv, the r-table CSVs and the pictures (``.written``). A folder
    holding a different run's results (uncertainty.json's fingerprint of the inputs and settings)
    is refused before the work unless ``fresh``, which replaces them. The options of the aperture
    case (:data:`UNCERTAINTY_APERTURE_DEFAULTS`: backend, rel_se, surrogate, validation, workers,
    scheduler, mitsuba_variant) given with ``aperture=False`` are an error; None is their default."""
    from roadgonio.engines.registry import check_seed, prepare_entry_point, resolve_settings
    given = {"backend": backend, "rel_se": rel_se, "surrogate": surrogate, "validation": validation,
             "workers": workers, "scheduler": scheduler, "mitsuba_variant": mitsuba_variant}
    if not aperture:
        for name, value in given.items():
            if value is not None:
                raise InputError("an option of the case with the aperture effect (the surrogate's exact k_A tables), "
                                 "which --no-aperture skips: leave it out, or compute that case",
                                 field=name)
    backend, surrogate, validation = (UNCERTAINTY_APERTURE_DEFAULTS[k] if given[k] is None else given[k]
                                      for k in ("backend", "surrogate", "validation"))
    from roadgonio.uncertainty.run import run_uncertainty
    from roadgonio.uncertainty.spec import SigmaSpec, parse_sigma_spec
    if isinstance(sigma, SigmaSpec):
        spec = sigma
    elif isinstance(sigma, (str, Path, Mapping)):
        spec = parse_sigma_spec(str(sigma) if isinstance(sigma, Path) else sigma, option="sigma")
    else:
        raise InputError(f"expected a SPEC text, a TOML file, a mapping or a SigmaSpec, got {type(sigma).__name__}",
                         field="sigma")
    if not any(s > 0 for s in spec.sigma):
        # an empty spec, or only zeros: every trial is the nominal table, and the surrogate's check
        # printed max/u(r) = inf, 0 / 0 (audit 21)
        raise InputError("every input error's sigma is 0 (or none is given): there is nothing to propagate; expected "
                         "at least one positive sigma" + (f" (from {spec.source})" if spec.source else ""),
                         field="sigma")
    names = {"max_trials": "cap on trials (--max-trials)", "batch": "batch size (--batch)"}
    unused = [o for o, v in (("max_trials", max_trials), ("batch", batch)) if v is not None]
    if unused and not adaptive:
        # they shape the adaptive rule only: a fixed run ignored them (user audit, session 19; refused by the
        # command line alone until the review of session 39, and batch entered the run's fingerprint)
        raise InputError(f"the {' and '.join(names[u] for u in unused)} "
                         f"{'are' if len(unused) > 1 else 'is'} for an adaptive run (--adaptive); expected an adaptive "
                         "run, or a fixed number of trials (--trials N) without them", field=unused[0])
    if max_trials is None:
        max_trials = MAX_TRIALS_DEFAULT
    seed = check_seed(seed)
    from roadgonio.limits import check_size
    trials = check_size(_check_int(trials, "trials", 1), "trials", "trials")
    max_trials = check_size(_check_int(max_trials, "max_trials", 1), "trials", "max_trials")
    if batch is not None:
        batch = check_size(_check_int(batch, "batch", 1), "trials", "batch")
    digits = _check_int(digits, "digits", 1, 3)
    validation = _check_int(validation, "validation", 0)
    if threads is not None:
        threads = _check_int(threads, "threads", 1)
    if isinstance(coverage, bool) or not isinstance(coverage, (int, float)) or not (0.5 < coverage < 1.0):
        raise InputError(f"expected a coverage probability between 0.5 and 1, got {coverage!r}", field="coverage")
    info = _command_backend("uncertainty", backend)
    settings = resolve_settings(backend, tolerance=info.study_tolerance if rel_se is None else rel_se,
                                seed=seed if info.seeded else None, mitsuba_variant=mitsuba_variant,
                                fields={"tolerance": "rel_se"})
    inst = _instrument(instrument)
    smp = _sample(sample, model_variant)
    folder = _out(out, "uncertainty", inst.name, smp.name)
    fp = None
    if folder is not None:
        from roadgonio.engines.cluster import absolute_instrument_dict
        from roadgonio.fileio import check_run_folder, fingerprint
        fp = fingerprint({
            "instrument": {k: v for k, v in absolute_instrument_dict(inst).items() if k != "instrument"},
            "model": {"variant": smp.model.variant, "params": smp.model.params.to_dict()}, "sigma": spec.to_dict(),
            "trials": trials, "adaptive": bool(adaptive), "digits": digits, "max_trials": max_trials, "batch": batch,
            "seed": seed, "coverage": coverage, "cells": cells, "aperture": bool(aperture), "backend": backend,
            "settings": settings, "illuminance": illuminance, "surrogate": surrogate, "validation": validation})
        check_run_folder(folder, "uncertainty.json", fp, what="uncertainty run", fresh=bool(fresh))
        from roadgonio.fileio import check_writable
        check_writable(folder)          # an unwritable folder fails now, not after the Monte Carlo
    if aperture:
        # this process computes: every table in one process, and on Dask the Mitsuba engine's first
        # table too (its pass plan goes with the other tables, the common random numbers)
        prepare_entry_point(backend, mitsuba_variant)
    res = run_uncertainty(smp.model, inst, spec, trials=trials, adaptive=adaptive, seed=seed, coverage=coverage,
                          n_dig=digits, max_trials=max_trials, batch=batch, illuminance=illuminance, cells=cells,
                          aperture=aperture, backend=backend, backend_settings=settings, n_validation=validation,
                          surrogate_design=surrogate, threads=threads, progress=_show(progress), workers=workers,
                          scheduler=scheduler)
    res.provenance["sample"] = smp.spec or smp.name
    if folder is not None:
        from roadgonio.uncertainty.report import write_results
        res.written = write_results(res, folder, sample_name=smp.name, plots=plots, figures=figures, fingerprint=fp)
        res.out = folder
    return res


def _without_fresh(f):
    """``f`` whose errors about a folder of another run say to use another folder or remove it, not
    --fresh: ``correct`` has none (:func:`roadgonio.fileio.without_fresh`; audit 21)."""
    import functools

    @functools.wraps(f)
    def wrapped(*args, **kwargs):
        from roadgonio.fileio import without_fresh
        try:
            return f(*args, **kwargs)
        except InputError as err:
            raise without_fresh(err) from None
    return wrapped


@_without_fresh
def correct(measured, instrument, *, reference="self", alternatives: str | Sequence[str] | None = None,
            u_measured: Any = None, sigma: Any = None, backend: str = "mitsuba", accuracy: str | None = None,
            rel_se: float | None = None, seed: int = 0, mitsuba_variant: str | None = None,
            model_variant: str | None = None, rays: int = 512, workers: int | None = None,
            scheduler: str | None = None, out=None, plots: bool = True, progress: bool = False,
            forward: str | None = None, joint: bool = False, mirror_plane: str | None = None,
            unobserved_road: float | None = None, gd_prior: str | None = None, **options: Any):
    """Correct measured r-tables for the aperture effect (``roadgonio correct``). ``measured``: one
    table (name, file, RTable or DataArray) or a list of them (they share the instrument's work);
    ``reference="self"`` (default) fits the model through the instrument, a SAMPLE takes the classic
    route with ``alternatives`` (``"auto"``, the default there, ``"none"`` or SAMPLEs; refused with ``"self"``,
    which has no reference to vary). ``u_measured`` (``"1%"``, the
    default; a fraction; or an r-table file of standard uncertainties) and ``sigma`` (a misalignment
    SPEC) enter the uncertainty. Returns the :class:`~roadgonio.correction.CorrectionResult`
    (``.corrected``, ``.u_corrected``, ``.k_a``, ``.budget``, ``.before`` / ``.after``, ``.summary()``),
    a list for a list; with ``out`` (a folder or :data:`AUTO`) the files are written (one sub-folder
    per table for several), ``.out`` and ``.written`` say where. ``workers``/``scheduler``: one
    Dask task per table (same results).

    ``forward`` (``reference="self"``): ``"eq4"`` (the default, None) fits eq. 4 through the instrument;
    ``"surface"`` fits eq. 4 times a smooth correction surface whose smoothing the data choose,
    for surfaces outside eq. 4, with an uncertainty that includes the surface's posterior and the
    Birge widening (docs/correction.md, "Outside eq. 4"). ``joint=True``: ``measured`` and
    ``instrument`` are lists of equal length (at least two), the tables one surface measured by
    the instruments (or aperture settings); one surface (eq. 4 times the correction surface: ``forward``
    None or ``"surface"``; ``"eq4"`` is refused) is fitted through all of them and one
    corrected table returned (a :class:`~roadgonio.correction.outside.SurfaceCorrection`: ``.corrected``,
    ``.u_corrected``, ``.budget``, ``.parts[i].k_a`` per instrument, ``.summary()``). ``mirror_plane``
    (with the surface): the backbone's shape at the mirror plane, ``"cusp"`` (eq. 4's), ``"rounded"``
    (over one knot of the correction surface), ``"both"`` (the two, weighed by their evidence) or
    ``"three"`` (the cusp and the roundings over one and two knots, weighed; None: the default of
    :class:`~roadgonio.correction.flexible.SurfaceSettings`, ``"three"``; docs/correction.md).
    ``unobserved_road`` (with the surface, where the backend traces stray light): the factor F within
    which the road's BRDF beyond the observation elevations the instruments saw is known, one standard
    uncertainty of ln F (None: 2; 1 leaves the budget's "unobserved" component out; docs/correction.md,
    "The road beyond the observation elevations"). ``gd_prior`` (with the surface): who chooses the
    scale of the prior of g_D (the BRDF's dependence on alpha beyond the backbone's), ``"joint"`` (the
    evidence where two or more distinct instruments see the surface, else held; None: the default of
    :class:`~roadgonio.correction.flexible.SurfaceSettings`), ``"fixed"`` (sd 1) or ``"evidence"``
    (also through one instrument; measured unsafe there, docs/correction-record.md)."""
    _check_correct_options(options)
    if isinstance(joint, str) or joint not in (True, False):
        raise InputError(f"expected True or False, got {joint!r}", field="joint")
    if workers is not None:
        _check_int(workers, "workers", 0)
    if mirror_plane is not None:
        options["settings"] = _surface_settings(options.get("settings"), mirror_plane, joint or forward == "surface")
    if gd_prior is not None:
        options["settings"] = _gd_prior_settings(options.get("settings"), gd_prior, joint or forward == "surface")
    if unobserved_road is not None:
        options["settings"] = _unobserved_settings(options.get("settings"), unobserved_road,
                                                   joint or forward == "surface")
    self_ref = isinstance(reference, str) and reference.strip().lower() == "self"
    if alternatives is not None and (joint or self_ref):
        # they were accepted and ignored: the self route and the joint fit have no reference to vary (user
        # audit, session 19; refused by the command line alone until session 39's review, which then found
        # the joint route accepting them)
        raise InputError("the alternative references are for a correction with a reference sample (--reference "
                         "SAMPLE); a fit through the instrument (--reference self, --joint) has none: its model term is "
                         "the spread of the fitted variants", field="alternatives")
    if joint:
        return _said_unused(unobserved_road, _correct_joint(
                              measured, instrument, u_measured=_u_measured(u_measured), sigma=sigma, backend=backend,
                              accuracy=accuracy, rel_se=rel_se, seed=seed, mitsuba_variant=mitsuba_variant,
                              model_variant=model_variant, rays=rays, out=out, plots=plots, progress=progress,
                              workers=workers, scheduler=scheduler, reference=reference, forward=forward, **options))
    forward = "eq4" if forward is None else forward
    if forward not in ("eq4", "surface"):
        raise InputError(f"unknown forward model {forward!r}; expected eq4 or surface", field="forward")
    if isinstance(instrument, (list, tuple)):
        if len(instrument) != 1:
            raise InputError(f"{len(instrument)} instruments given without joint: several instruments correct one "
                             "surface together (joint=True, --joint)", field="instrument")
        instrument = instrument[0]
    from roadgonio.correction import correct_files
    from roadgonio.engines.registry import check_seed, prepare_entry_point, resolve_settings
    many = isinstance(measured, (list, tuple))
    items = list(measured) if many else [measured]
    if not items:
        raise InputError("expected at least one measured table", field="measured")
    tables = _measured_tables(items)
    for item in items:
        _check_u_file(item, u_measured, "u_measured")
    seed = check_seed(seed)
    inst = _instrument(instrument)
    if alternatives is None:
        alternatives = "auto"
    if model_variant == "auto" and not self_ref:
        raise InputError("model_variant 'auto' is for reference 'self'; give one variant for fitting a reference "
                         "table", field="model_variant")
    from roadgonio.limits import check_size
    rays = check_size(_check_int(rays, "rays", 8), "rays", "rays")
    from roadgonio.engines.registry import check_capabilities
    info = _command_backend("correct", backend)
    check_capabilities(info, inst)      # before any fitting, not after it
    settings = resolve_settings(backend, tolerance=rel_se, seed=seed if info.seeded else None, mitsuba_variant=mitsuba_variant,
                                fields={"tolerance": "rel_se"})
    if scheduler is None and workers in (None, 0):
        prepare_entry_point(backend, mitsuba_variant)     # in this process: the API is the entry point
    opts = dict(u_measured=_u_measured(u_measured), sigma=sigma, backend=backend,
                backend_settings=settings, accuracy=accuracy, model_variant=model_variant, seed=seed,
                progress=_show(progress), **options)
    if forward == "surface" and not self_ref:
        raise InputError("the forward model 'surface' is fitted through the instrument: use it with reference "
                         "'self'", field="forward")
    if self_ref:
        opts["rays"] = rays
        if forward != "eq4":
            opts["forward"] = forward
        ref: Any = "self"
    else:
        ref_sample, opts["alternatives"] = _reference_and_alternatives(reference, alternatives, tables[0],
                                                                       model_variant)
        ref = ref_sample.model
        opts["reference_name"] = ref_sample.name
    folder = _out(out, "correct", tables[0].name if len(tables) == 1 else "tables")
    if out is not None and isinstance(out, _Auto) and len(tables) > 1:
        folder = Path("out") / "correct"
    files = [str(m) if isinstance(m, (str, Path)) else None for m in items]
    done = correct_files(tables, inst, folder, plots=plots, reference=ref, workers=workers, scheduler=scheduler,
                         measured_files=files, **opts)
    results = []
    for res, sub, written in done:
        res.out, res.written = sub, written
        results.append(_said_unused(unobserved_road, res))
    return results if many else results[0]


def _u_measured(u_measured: Any) -> Any:
    """``correct``'s ``u_measured`` as :func:`roadgonio.correction.run.measured_uncertainty` takes it:
    None is "1%"; a number (numpy's too), a text or a path as given; an RTable or a DataArray of u in
    sr^-1 as an RTable (audit 21: a DataArray was read as a file name, the error several kB long)."""
    import numbers
    if u_measured is None:
        from roadgonio.correction.budget import DEFAULT_U_MEASURED
        return DEFAULT_U_MEASURED
    if isinstance(u_measured, (list, tuple)):             # one per table of a joint correction
        return [_u_measured(x) for x in u_measured]
    if isinstance(u_measured, numbers.Real) and not isinstance(u_measured, bool):
        return float(u_measured)
    if isinstance(u_measured, (str, Path)):
        return u_measured
    from roadgonio.surface.sample import _as_table
    t = _as_table(u_measured)
    if t is None:
        raise InputError(f"expected '1%', a fraction, an r-table file of standard uncertainties, an RTable or a "
                         f"DataArray of them, got {type(u_measured).__name__}", field="u_measured")
    return t


def _check_correct_options(options: Mapping[str, Any]) -> None:
    """The keyword arguments of :func:`correct` beyond its named ones are the expert options of the
    procedures it calls (``starts``, ``tol``, ``settings``, ...); any other is a misspelling, which
    was passed on and dropped without a word (audit 21: ``u_measurd='5%'`` gave 1 %)."""
    import inspect

    from roadgonio.correction.outside import correct_surface
    from roadgonio.correction.run import correct_self, correct_with_reference
    allowed: set[str] = set()
    for f in (correct_self, correct_surface, correct_with_reference):
        allowed |= set(inspect.signature(f).parameters)
    allowed -= set(inspect.signature(correct).parameters) | {
        "measured", "tables", "instruments", "out_dir", "artefacts", "backend_settings", "variant",
        "reference_name"}
    bad = sorted(set(options) - allowed)
    if bad:
        raise InputError(f"unknown argument {bad[0]!r} of correct; expected its named arguments or one of "
                         f"{', '.join(sorted(allowed))}", field=bad[0])


def _said_unused(unobserved_road, res):
    """``res``, after a note when ``unobserved_road`` was given but the backend traced no stray light
    (the factor then changes nothing: no rendering reads the road beyond the observation elevations)."""
    if unobserved_road is not None and "unobserved" not in res.budget.components and \
            float(unobserved_road) != 1.0:
        import warnings

        from roadgonio.errors import ModelWarning
        warnings.warn(ModelWarning(f"the factor {float(unobserved_road):g} on the road beyond the observation elevations "
                                   "(--unobserved-road) changed nothing: the backend traced no stray light, so "
                                   "nothing read the road there"), stacklevel=3)
    return res


def _reference_and_alternatives(reference, alternatives, measured, model_variant):
    """The reference SAMPLE and the alternatives of the classic route (:func:`correct`), both resolved
    before either says a note: a mistake in ``alternatives`` is one line, not the reference's spike
    note and then the error (user audit, session 19). Named alternatives do not depend on the measured
    table and are returned resolved; ``"auto"`` (the tables nearest each measured one) stays a spec."""
    from roadgonio.correction.reference import resolve_alternatives
    from roadgonio.errors import notes_held
    with notes_held():
        ref_sample = _sample(reference, model_variant, field="reference")
        if not (isinstance(alternatives, str) and alternatives.strip().lower() == "auto"):
            alternatives = resolve_alternatives(alternatives, measured, reference_name=ref_sample.name,
                                                model_variant=model_variant)
    return ref_sample, alternatives


def _measured_tables(items) -> list:
    """The measured tables of a correction (names, files, RTables or DataArrays), each read and checked
    (:func:`roadgonio.correction.run.check_measured`; a file's errors name the file)."""
    from roadgonio.correction.run import check_measured
    tables = []
    for m in items:
        t = _table(m, "measured")
        check_measured(t, m if isinstance(m, (str, Path)) else None)
        tables.append(t)
    return tables


def _require_surface(surface: bool, what: str, field: str) -> None:
    """Refuse a setting of the correction surface (``what``, the argument ``field``) given to a correction
    that fits none (:func:`correct`'s ``mirror_plane``, ``gd_prior``, ``unobserved_road``)."""
    if not surface:
        raise InputError(f"{what} is a setting of the correction surface: give it with the forward model 'surface' "
                         "or a joint correction", field=field)


def _unobserved_settings(settings, factor, surface: bool):
    """The correction surface's settings with the road beyond the observation elevations known within
    ``factor`` (:func:`correct`'s ``unobserved_road``)."""
    _require_surface(surface, "the road beyond the observation elevations", "unobserved_road")
    import numbers
    if isinstance(factor, bool) or not isinstance(factor, numbers.Real) or not (math.isfinite(factor) and factor >= 1.0):
        raise InputError(f"expected a factor of 1 or more (1: the road there taken as fitted, no component), got "
                         f"{factor!r}", field="unobserved_road")
    from dataclasses import replace

    from roadgonio.correction.flexible import SurfaceSettings
    return replace(settings or SurfaceSettings(), unobserved_sd_ln=math.log(float(factor)))


def _gd_prior_settings(settings, gd_prior: str, surface: bool):
    """The correction surface's settings with who chooses g_D's prior scale (:func:`correct`'s ``gd_prior``)."""
    _require_surface(surface, "the scale of g_D's prior", "gd_prior")
    from dataclasses import replace

    from roadgonio.correction.flexible import D_PRIOR_SCALES, SurfaceSettings
    if gd_prior not in D_PRIOR_SCALES:
        raise InputError(f"expected who chooses g_D's prior scale to be one of {', '.join(D_PRIOR_SCALES)}, got "
                         f"{gd_prior!r}", field="gd_prior")
    return replace(settings or SurfaceSettings(), d_prior_scale=gd_prior)


def _surface_settings(settings, mirror_plane: str, surface: bool):
    """The correction surface's settings with the backbone's shape at the mirror plane (:func:`correct`)."""
    _require_surface(surface, "the backbone's shape at the mirror plane", "mirror_plane")
    from roadgonio.correction.flexible import SurfaceSettings
    return (settings or SurfaceSettings()).with_mirror_plane(mirror_plane)


def _correct_joint(measured, instrument, *, u_measured, sigma, backend, accuracy, rel_se, seed, mitsuba_variant,
                   model_variant, rays, out, plots, progress, workers, scheduler, reference, forward, **options):
    """:func:`correct` with ``joint=True`` (one surface through several instruments)."""
    from roadgonio.correction import correct_joint
    from roadgonio.engines.registry import check_capabilities, check_seed, prepare_entry_point, resolve_settings
    if not (isinstance(reference, str) and reference.strip().lower() == "self"):
        raise InputError("a joint correction fits one surface through the instruments: reference must be 'self'",
                         field="reference")
    if forward not in (None, "eq4", "surface"):
        raise InputError(f"unknown forward model {forward!r}; expected eq4 or surface", field="forward")
    if forward == "eq4":      # trial 10 D7: it was dropped without a word and the surface fitted
        raise InputError("a joint correction fits eq. 4 times a correction surface through the instruments "
                         "(docs/correction.md, 'Outside eq. 4'); the forward model eq4 cannot be used with it: "
                         "leave it out or give surface", field="forward")
    if workers not in (None, 0) or scheduler is not None:
        raise InputError("a joint correction is one fit: it runs in this process (no --workers/--scheduler)",
                         field="workers")
    items = list(measured) if isinstance(measured, (list, tuple)) else [measured]
    insts = list(instrument) if isinstance(instrument, (list, tuple)) else [instrument]
    if len(items) < 2 or len(items) != len(insts):
        raise InputError(f"a joint correction takes one instrument per measured table, at least two; got "
                         f"{len(items)} table(s) and {len(insts)} instrument(s)", field="instrument")
    tables = _measured_tables(items)
    # the review of session 21: a measured file (any of them) or an RTB as a u of the joint fit ran with u = 100 %
    for uf in (u_measured if isinstance(u_measured, list) else [u_measured]):
        for item in items:
            _check_u_file(item, uf, "u_measured")
    seed = check_seed(seed)
    instruments = [_instrument(i) for i in insts]
    info = _command_backend("correct", backend)
    for i in instruments:
        check_capabilities(info, i)     # before any fitting, not after it
    rays = _check_int(rays, "rays", 8)
    settings = resolve_settings(backend, tolerance=rel_se, seed=seed if info.seeded else None,
                                mitsuba_variant=mitsuba_variant, fields={"tolerance": "rel_se"})
    prepare_entry_point(backend, mitsuba_variant)
    folder = _out(out, "correct", "joint", *[t.name for t in tables])
    files = [str(m) if isinstance(m, (str, Path)) else None for m in items]
    return correct_joint(tables, instruments, folder, plots=plots, model_variant=model_variant,
                         measured_files=files, u_measured=_u_measured(u_measured), sigma=sigma,
                         backend=backend, backend_settings=settings, accuracy=accuracy, rays=rays, seed=seed,
                         progress=_show(progress), **options)


def second_aperture(instrument, vary, *, measured=None, sample=None, u_measured: Any = None, rays: int = 512,
                    seed: int = 0, model_variant: str | None = None, min_signal: float | None = None, out=None,
                    plots: bool = True, progress: bool = False, fresh: bool = False):
    """Which second aperture setting should the instrument have (``roadgonio design --second-aperture``;
    docs/design.md, "Which second aperture?")? Ranks every point of the ``vary`` grid (applied to ``instrument``) by the median
    relative u of the one corrected table that a joint correction of the instrument and that
    second setting would give (:mod:`roadgonio.design.second_aperture`), among the settings that
    keep at least ``min_signal`` (default 0.25) of the instrument's signal; baselines: the
    instrument alone and measuring twice. The surface: ``measured`` (a table the instrument
    measured) or ``sample`` (anything :func:`roadgonio.surface.sample.resolve_sample` takes, or a
    BRDF model). Returns the :class:`~roadgonio.design.second_aperture.SecondApertureResult`
    (``.best``, ``.candidates``, ``.baselines``, ``.summary()``); with ``out`` second_aperture.csv,
    .json, best_second.toml and second_aperture.png are written (``.out``, ``.written``); a folder
    holding another second-aperture study's results is refused before the work unless ``fresh``."""
    from roadgonio.design.second_aperture import DEFAULT_MIN_SIGNAL, DEFAULT_U, second_aperture as _second
    from roadgonio.design.second_aperture import write_second_aperture
    from roadgonio.engines.registry import check_seed
    inst = _instrument(instrument)
    from roadgonio.design.grid import as_vary_specs
    from roadgonio.design.second_aperture import check_second_keys
    specs = as_vary_specs(vary)
    check_second_keys(inst, specs)                        # before the sample's model is fitted
    table = None if measured is None else _table(measured, "measured")
    if table is not None:
        from roadgonio.correction.run import check_measured
        check_measured(table, measured if isinstance(measured, (str, Path)) else None)
    smp = sample
    if sample is not None and not hasattr(sample, "evaluate"):
        # anything resolve_sample takes (a name, a file, an RTable, a DataArray: audit 21, an RTable
        # or a DataArray ended in AttributeError 'evaluate')
        smp = _sample(sample, model_variant, field="sample").model
    from roadgonio.design.grid import parse_fraction
    ms = DEFAULT_MIN_SIGNAL if min_signal is None else parse_fraction(min_signal, "min_signal", 0.25)[0]
    if not (0.0 <= ms <= 1.0):
        raise InputError(f"expected a least signal between 0 and 1 (of the instrument's), got {min_signal!r}",
                         field="min_signal")
    rays, seed = _check_int(rays, "rays", 8), check_seed(seed)
    # the folder before the work (user audit, session 44: a file as --out was said after 35 s, and a
    # folder of another study's results was overwritten without a word)
    folder = _out(out, "design", inst.name, "second")
    fp = None
    if folder is not None:
        from roadgonio.fileio import check_run_folder, check_writable, fingerprint
        from roadgonio.surface.fit import table_hash
        fp = fingerprint({"instrument": inst.to_dict(), "vary": [str(v) for v in specs],
                          "measured": None if table is None else table_hash(table),
                          "sample": None if smp is None else (smp.to_json_dict() if hasattr(smp, "to_json_dict")
                                                              else repr(smp)),
                          "u_measured": str(u_measured), "rays": rays, "seed": seed,
                          "model_variant": model_variant, "min_signal": ms})
        check_run_folder(folder, "second_aperture.json", fp, what="second-aperture study", fresh=bool(fresh))
        check_writable(folder)
    res = _second(inst, vary, measured=table, sample=smp, u_measured=DEFAULT_U if u_measured is None else u_measured,
                  rays=rays, seed=seed, model_variant=None if model_variant == "auto" else model_variant, min_signal=ms,
                  progress=_show(progress))
    res.out, res.written = folder, []
    if folder is not None:
        res.written = write_second_aperture(res, folder, plots=plots, fingerprint=fp)
    return res


def design_study(instrument, vary=None, samples="R3", *, tolerance: float | str = "5%", cells="all",
                 backend: str = "mitsuba", accuracy: str | None = None, rel_se: float | None = None, seed: int = 0,
                 workers: int | None = None, scheduler: str | None = None, client=None, out=None, fresh: bool = False,
                 progress: bool = False, plots: bool = True, model_variant: str | None = None,
                 mitsuba_variant: str | None = None) -> "xr.Dataset":
    """A design study (``roadgonio design``): k_A tables over a grid of instruments, on Dask.

    ``vary``: ``["source.radius_m=0.01:0.04:4", ...]`` or ``{key: values}``; ``samples``: one sample
    or a list (anything :func:`roadgonio.surface.sample.resolve_sample` takes); ``cells``:
    ``"all"``, ``"table"`` or ``"T:B,T:B,..."``; ``workers``/``scheduler``/``client``: a local
    cluster of worker processes (default: one per core), an existing cluster, or ``workers=0`` for
    this process. Returns the ``xarray.Dataset`` of ``design.nc`` (``k_a``, ``se`` over the varied
    keys x sample x tan_eps x beta; ``max_abs_dev``, ``signal``, ``feasible``, ``reason``... per
    point; provenance in ``attrs["provenance"]``); with ``out`` (a folder or :data:`AUTO`) also
    design.csv, best.toml and the pictures. Scripts that start a local cluster must guard the call
    with ``if __name__ == "__main__":`` (an unguarded call raises
    :class:`~roadgonio.errors.InputError` before any worker starts)."""
    from roadgonio.design.run import run_design
    from roadgonio.engines.registry import check_seed, prepare_entry_point, resolve_settings
    _check_flags(fresh=fresh, progress=progress, plots=plots)
    _check_cluster(workers, client)
    seed = check_seed(seed)
    _command_backend("design", backend)
    settings = resolve_settings(backend, tolerance=rel_se, mitsuba_variant=mitsuba_variant, fields={"tolerance": "rel_se"})
    base = _instrument(instrument)
    from roadgonio.design.grid import as_vary_specs, check_vary
    check_vary(base, as_vary_specs(vary))                 # before the samples are fitted
    items = list(samples) if isinstance(samples, (list, tuple)) else [samples]
    resolved = [_sample(s, model_variant) for s in items]
    if not (isinstance(cells, str) and cells.strip() in ("all", "table")):
        from roadgonio.engines.cells import select_cells
        for smp in resolved:      # the note ka gives (user audit, session 24: design gave none)
            _note_beyond_the_table(None, smp, select_cells(cells, smp.table, on_grid=False))
    folder = _out(out, "design", base.name)
    if workers == 0 and scheduler is None and client is None:
        prepare_entry_point(backend, mitsuba_variant)          # this process computes: it is the entry point
    ds = run_design(base, vary, resolved, tolerance=tolerance, cells=cells, backend=backend, accuracy=accuracy,
                    settings=settings, seed=seed, workers=workers, scheduler=scheduler, client=client, out=folder,
                    fresh=fresh, progress=_show(progress), plots=plots, model_variant=model_variant)
    if folder is not None:
        ds.attrs["out"] = str(folder)
    return ds


def intercompare(study, out=None, *, workers: int | None = None, scheduler: str | None = None, client=None,
                 fresh: bool = False, progress: bool = False, plots: bool = True,
                 mitsuba_variant: str | None = None):
    """A virtual intercomparison (``roadgonio intercompare STUDY``): the participants of the study
    (a TOML file, the name of a bundled study such as ``"r3-comparison"``, or a
    :class:`roadgonio.intercomparison.study.Study`) measure its surface in many realisations; returns
    the :class:`~roadgonio.intercomparison.run.StudyRun` (``.dataset``: the ``xarray.Dataset`` of
    intercompare.nc; :func:`intercomparison_summary`). ``workers``/``scheduler``/``client`` as
    :func:`design_study` (default: a local cluster, one worker per core; ``workers=0`` computes
    here). With ``out`` (a folder or :data:`AUTO`) the run is journalled (resumable) and its files
    are written there (:mod:`roadgonio.intercomparison.outputs`). Scripts that start a local cluster
    must guard the call with ``if __name__ == "__main__":`` (an unguarded call raises
    :class:`~roadgonio.errors.InputError` before any worker starts)."""
    from roadgonio.engines.registry import prepare_entry_point
    from roadgonio.intercomparison.run import run_study
    from roadgonio.intercomparison.study import Study, load_study
    _check_flags(fresh=fresh, progress=progress, plots=plots)
    _check_cluster(workers, client)
    if not isinstance(study, (Study, str, Path)):
        raise InputError(f"expected a study file, the name of a bundled study or a Study, got {type(study).__name__}",
                         field="study")
    st = study if isinstance(study, Study) else load_study(study)
    folder = _out(out, "intercompare", st.name)
    if workers == 0 and scheduler is None and client is None:
        prepare_entry_point(st.backend, mitsuba_variant)       # this process computes: it is the entry point
    return run_study(st, folder, workers=workers, scheduler=scheduler, client=client, fresh=fresh,
                     progress=_show(progress), plots=plots, mitsuba_variant=mitsuba_variant)


def intercomparison_summary(run) -> dict[str, Any]:
    """The summary of an :func:`intercompare` run: the notes a reader must see
    (:func:`roadgonio.intercomparison.run.study_notes`), per scenario and participant (and for the
    comparison) its figures of merit, the ranking of the characteristics, the frozen-factor check,
    the seconds of each stage and the output folder."""
    import json
    ds = run.dataset
    return {"notes": json.loads(ds.attrs.get("notes_json", "[]")),
            "summary": json.loads(ds.attrs["summary_json"]), "sensitivity": json.loads(ds.attrs["sensitivity_json"]),
            "validation": json.loads(ds.attrs.get("validation_json", "[]")),
            "seconds": json.loads(ds.attrs.get("seconds", "{}")), "out": ds.attrs.get("out"),
            "files": ds.attrs.get("files", "")}


# ----------------------------------------------------------------------------------------------
# from the table to the road
# ----------------------------------------------------------------------------------------------

#: The cases of ``road_metrics(correlation=...)``: "auto" is "given" when the cells' correlation is
#: known (``corr``, or corrected_corr.csv beside a corrected_u.csv), else "both".
ROAD_CORRELATIONS = {"auto": None, "given": ("given",), "both": ("independent", "correlated"),
                     "independent": ("independent",), "correlated": ("correlated",),
                     "all": ("independent", "correlated", "given")}


def __getattr__(name: str):
    """``ROAD_MODES``: the Monte Carlo's correlation cases in the order road's outputs give them
    (:data:`roadgonio.road.report.MODES`, the one definition), imported when first asked for so that
    importing the API stays light (as ``roadgonio`` itself does for the API)."""
    if name == "ROAD_MODES":
        from roadgonio.road.report import MODES
        return MODES
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: ``road``'s Monte Carlo of u, when it runs (a table with u): trials, seed and the cells' correlation
ROAD_MC_DEFAULTS = {"trials": 20_000, "seed": 0, "correlation": "auto"}


def road_metrics(tables, *, u=None, corr=None, luminaire=None, layout=None, target_class: str | None = None,
                 trials: int | None = None, seed: int | None = None, correlation: str | None = None, out=None,
                 plots: bool = True) -> list[dict[str, Any]]:
    """EN 13201-3 road-surface luminance metrics of a luminaire layout with one or several r-tables
    side by side (``roadgonio road``). ``u``: the tables' standard uncertainties (r-table files, r x
    1e4): one (not in a list) for the last table, or a list with one entry per table (None or
    ``"-"`` for none); a u file whose header
    names another table than the CSV it goes with is an error (:func:`_check_u_belongs`); a Monte Carlo of
    ``trials`` gives u and 95 % intervals of each metric and P(meets ``target_class``). ``corr``: the
    correlation of the cells of a table with u (a file as correct writes corrected_corr.csv), given
    as u is; without it, a u file named corrected_u.csv takes the corrected_corr.csv beside it (a
    correct folder). ``correlation`` (:data:`ROAD_CORRELATIONS`): "auto" (the given correlation
    when there is one, else both limiting cases), "given", "both" (independent and fully correlated
    cells), "independent", "correlated" or "all" (the three). Without ``luminaire``/``layout``:
    the bundled ones. Returns one summary per table; with ``out`` (a folder or :data:`AUTO`) writes
    road.json, the CSVs and the pictures (the first summary's ``written``). ``trials``, ``seed``,
    ``correlation`` and ``target_class`` are the Monte Carlo's: given without any u they are an error
    (nothing would use them); None is :data:`ROAD_MC_DEFAULTS` (the class: the one the table meets)."""
    from roadgonio.engines.registry import check_seed
    from roadgonio.road import mc, report
    from roadgonio.road.evaluate import Installation
    from roadgonio.road.layout import load_layout
    from roadgonio.road.luminaire import load_luminaire
    from roadgonio.road.metrics import M_CLASSES
    from roadgonio.surface.rtable import header_notes, read_cell_correlation
    items = list(tables) if isinstance(tables, (list, tuple)) else [tables]
    if not items:
        raise InputError("expected at least one table", field="table")
    if target_class is not None and str(target_class).upper() not in M_CLASSES:
        raise InputError(f"unknown class {target_class!r}; expected one of {', '.join(M_CLASSES)}", field="target_class")
    target = str(target_class).upper() if target_class else None
    if correlation is not None and correlation not in ROAD_CORRELATIONS:
        raise InputError(f"expected {', '.join(ROAD_CORRELATIONS)}, got {correlation!r}", field="correlation")
    u_of = _one_per_table(u, len(items), "u")
    if all(uf is None for uf in u_of):
        for name, value in (("trials", trials), ("seed", seed), ("correlation", correlation),
                            ("target_class", target_class)):
            if value is not None:
                raise InputError("an option of the Monte Carlo of the tables' uncertainty, which runs only for a "
                                 "table given with its u (--u FILE): give a u, or leave the option out", field=name)
    trials = ROAD_MC_DEFAULTS["trials"] if trials is None else trials
    seed = ROAD_MC_DEFAULTS["seed"] if seed is None else seed
    correlation = ROAD_MC_DEFAULTS["correlation"] if correlation is None else correlation
    if isinstance(trials, int) and not isinstance(trials, bool) and trials < mc.MIN_TRIALS:
        raise InputError(f"expected at least {mc.MIN_TRIALS} trials, got {trials}", field="trials")
    from roadgonio.limits import check_size
    trials = check_size(_check_int(trials, "trials", mc.MIN_TRIALS), "trials", "trials")
    seed = check_seed(seed)
    corr_of = _one_per_table(corr, len(items), "corr")
    for k, (uf, cf) in enumerate(zip(u_of, corr_of)):
        if cf is not None and uf is None:
            raise InputError(f"{cf} goes with table {k + 1} ({items[k]}), which has no u: give corr with the u of its "
                             "table", field="corr")
        if cf is not None and correlation not in ("auto", "given", "all"):
            raise InputError(f"{cf} is not used with correlation {correlation!r}: expected auto, given or all with a "
                             "correlation file", field="corr")
    loaded = [_table(t) for t in items]
    read_names = [t.name for t in loaded]     # the names the tables were read under
    # the default folder is named by the files (an RTB stores a surface name: measured.rtb + corrected.csv
    # went to out/road-R3-corrected, the folder of --table R3 --table corrected.csv; user audit 29)
    out_names = [Path(str(i)).stem if isinstance(i, (str, Path)) and Path(str(i)).suffix else t.name
                 for i, t in zip(items, loaded)]
    loaded = [_labelled(item, t) for item, t in zip(items, loaded)]
    names = [t.name for t in loaded]
    if len(set(names)) != len(names):  # same name twice (e.g. two files R3.csv): number them
        loaded = [t.with_values(t.r, name=f"{t.name}#{k + 1}") for k, t in enumerate(loaded)]
        names = [t.name for t in loaded]
    from roadgonio.provenance import input_record
    inputs = [input_record("table", item, t.name) for item, t in zip(items, loaded)]
    inst = Installation(load_layout(layout), load_luminaire(luminaire))
    results, summaries = [], []
    for item, t, own_name, uf, cf in zip(items, loaded, read_names, u_of, corr_of):
        res = inst.evaluate(t)
        if uf is not None:
            _check_u_file(item, uf)
            ut = _table(uf, "u", quantity="u")
            _check_u_is_u(uf, ut)
            _check_u_belongs(item, t, uf, ut, own_name)
            from roadgonio.surface.rtable import check_u_scale
            check_u_scale(ut.r, t, **({"path": uf, "argument": "u"} if isinstance(uf, (str, Path)) else {"field": "u"}))
            inputs.append(input_record("u", uf, f"u of {t.name}"))
            found = False
            if cf is None and correlation in ("auto", "given", "all"):
                cf = _correlation_beside(uf)
                found = cf is not None
            modes = ROAD_CORRELATIONS[correlation] or (("given",) if cf is not None else ROAD_CORRELATIONS["both"])
            if "given" in modes and cf is None:
                raise InputError(f"correlation {correlation!r} needs the cells' correlation of {item}: give corr (a file "
                                 "as correct writes corrected_corr.csv)", field="correlation")
            cells_corr = None
            if cf is not None:
                try:
                    cells_corr = read_cell_correlation(cf, table=_header_for_corr(item, t, ut))
                except InputError as err:
                    raise err.with_argument("corr") from None
                inputs.append(input_record("corr", cf, f"correlation of the cells of {t.name}"))
            # what the u file's header says of it (correct: the data reject the fit), repeated (trial 11 D7)
            res.uncertainty = {"file": str(uf), "notes": header_notes(ut),
                               "correlation_found_beside_u": found,
                               **mc.propagate(inst, t, ut, trials=trials, seed=seed, correlations=modes,
                                              target_class=target, u_path=uf if isinstance(uf, (str, Path)) else None,
                                              corr=cells_corr, corr_path=cf)}
        results.append(res)
        summaries.append(res.summary())
    for argument, value in (("layout", layout), ("luminaire", luminaire)):
        if value is not None:
            inputs.append(input_record(argument, value))
    folder = _out(out, "road", *out_names)
    if folder is not None:
        files = report.road_files(results, summaries, target or summaries[0]["class"], plots=plots, inputs=inputs)
        # a --no-plots run removes an earlier run's pictures (trial 11 D4: they showed another table)
        written = report.write_together(folder, files, replaces=report.ROAD_FILES)
        summaries[0]["written"] = [str(p) for p in written]
        summaries[0]["out"] = str(folder)
    summaries[0]["layout"] = inst.layout.describe()
    summaries[0]["luminaire"] = {"name": inst.luminaire.name, "flux_lm": inst.luminaire.flux_lm}
    return summaries


def _one_per_table(value, n: int, field: str) -> list:
    """``u`` or ``corr`` of :func:`road_metrics` per table: one value (not in a list) for the last
    table, or a list with exactly one entry per table (None, "" or "-" for none)."""
    if value is None:
        return [None] * n
    if not isinstance(value, (list, tuple)):      # one value: the last table's
        return [None] * (n - 1) + [value]
    if len(value) == n:
        return [None if x in ("-", "", None) else x for x in value]
    # trial 11 D11: a one-entry list for two tables was put on the last table
    raise InputError(f"a list of {field} has one entry per table (None for none): expected {n}, got {len(value)}; "
                     f"a single {field}, not in a list, goes with the last table", field=field)


#: The files of a ``roadgonio correct`` folder that ``road`` pairs: the cells' correlation
#: (corrected_corr.csv) is taken for the u (corrected_u.csv) it was written with.
CORRECT_U, CORRECT_CORR = "corrected_u.csv", "corrected_corr.csv"


def _correlation_beside(uf) -> Path | None:
    """corrected_corr.csv beside a u file named corrected_u.csv (a correct folder), or None."""
    if not isinstance(uf, (str, Path)) or Path(str(uf)).name != CORRECT_U:
        return None
    beside = Path(str(uf)).with_name(CORRECT_CORR)
    return beside if beside.is_file() else None


def _u_instead(uf) -> str:
    """What to give instead of the r-table ``uf`` given as a u: its ``_u.csv`` when one sits beside it."""
    p = Path(str(uf))
    beside = p.with_name(p.stem + "_u.csv")
    return f"give {beside.name} beside it" if beside.is_file() else \
        "give its standard uncertainty (r x 1e4 in the r-table CSV layout, as correct writes corrected_u.csv)"


def _check_u_file(item, uf, arg: str = "u") -> None:
    """A u that is an r-table by its name alone (trial 11 D3: `--u corrected.csv` / `corrected.rtb`,
    tab completion's neighbours of corrected_u.csv, ran with u = 100 % of r): a bundled table, an RTB
    (a format for r only) or the table file itself is an :class:`InputError` naming the file and the
    argument ``arg`` (road's ``u``, correct's ``u_measured``: audit 21, the measured file given as its
    own u ran with u = 100 %)."""
    from roadgonio.surface.rtable import BUNDLED
    if not isinstance(uf, (str, Path)):
        return
    p = Path(str(uf))
    if isinstance(uf, str) and not p.suffix and uf.strip().upper() in BUNDLED:
        raise InputError(f"'{uf}' is the bundled r-table {uf.strip().upper()}, not a standard uncertainty: give a file "
                         "of u (r x 1e4 in the r-table CSV layout, as correct writes corrected_u.csv)", field=arg)
    if p.suffix.lower() == ".rtb":
        raise InputError(f"an RTB file holds an r-table (the format has no standard uncertainties), not a standard "
                         f"uncertainty: {_u_instead(p.with_suffix('.csv'))}", path=uf, argument=arg)
    if isinstance(item, (str, Path)) and Path(str(item)).suffix and p.is_file() and Path(str(item)).is_file() \
            and os.path.samefile(p, Path(str(item))):
        raise InputError(f"is the table file {item} itself, an r-table, not a standard uncertainty: {_u_instead(p)}",
                         path=uf, argument=arg)


def _check_u_is_u(uf, ut: "RTable") -> None:
    """A u file whose header says it is a corrected r-table (``roadgonio correct``'s corrected.csv,
    :func:`~roadgonio.surface.rtable.corrected_r_header`) is an :class:`InputError` naming the file and
    its header, as ``roadgonio uncertainty``'s mean table is (:func:`_check_u_belongs`)."""
    from roadgonio.surface.rtable import corrected_r_header
    head = corrected_r_header(ut)
    if head is not None:
        from roadgonio.surface.rtable import shown_header
        shown = shown_header(head)
        raise InputError(f"is an r-table ('{shown}'), not a standard uncertainty (its header would start "
                         f"'standard uncertainty of'): {_u_instead(uf)}",
                         **({"path": uf, "argument": "u"} if isinstance(uf, (str, Path)) else {"field": "u"}))


def _check_u_belongs(item, t: "RTable", uf, ut: "RTable", own_name: str | None = None) -> None:
    """A table of standard uncertainties whose header names its table (``standard uncertainty of
    <header>``, as ``correct`` writes corrected_u.csv) must go with a table of that header: checked
    when the table is a CSV file with a header of its own (an RTB or a bundled table has none to
    compare). One that ``roadgonio uncertainty`` wrote names its sample (``..., sample R3: standard
    uncertainty u(r) x 1e4``): it must go with the table of that name (``own_name``, the name the
    table was read under: a bundled name or the file's), and its ``_mean.csv`` is not a u at all.
    A mismatch is an :class:`InputError` naming both."""
    from roadgonio.surface.rtable import header_line, u_names_sample, u_names_table
    by_sample = u_names_sample(ut)
    if by_sample is not None:
        sample, is_u = by_sample
        if not is_u:
            raise InputError(f"{uf} is the mean table roadgonio uncertainty wrote for sample '{sample}', not its "
                             "standard uncertainty: give the <case>_u.csv beside it", field="u")
        own = own_name if own_name is not None else t.name
        if sample != own:
            raise InputError(f"{uf} is the standard uncertainty roadgonio uncertainty computed for sample '{sample}', "
                             f"but it goes with the table {item} ('{own}'): give each --u right after the --table "
                             "it belongs to", field="u")
        return
    named = u_names_table(ut)
    if named is None or not isinstance(item, (str, Path)):
        return
    from roadgonio.surface.rtable import BUNDLED
    bundled = str(item).strip().upper()
    first_word = (named.split() or [""])[0].strip(",;:").upper()     # 'R3 (3 % of r)' names R3
    if bundled in BUNDLED and first_word in BUNDLED and first_word != bundled:
        # a bundled table has no header of its own, but a u naming another bundled table is not its u
        # (user audit, session 45: R1 with a u 'of R3' passed, while uncertainty's u of sample R3 was refused)
        raise InputError(f"{uf} is the standard uncertainty of '{named}', but it goes with the bundled table "
                         f"{bundled}: give each --u right after the --table it belongs to", field="u")
    if Path(str(item)).suffix.lower() != ".csv":
        return
    own = header_line(t)
    if own and own != named:
        raise InputError(f"{uf} is the standard uncertainty of '{named}', but it goes with the table {item}, whose "
                         f"header says '{own}': give each --u right after the --table it belongs to", field="u")


def _header_for_corr(item, t: "RTable", ut: "RTable") -> str | None:
    """The header of the table a correlation file (corr) must name when it names one: that of the
    table's CSV file, else the one its u file names (an RTB or a bundled table has no header to
    compare, as in :func:`_check_u_belongs`, which has made the two agree when both are there)."""
    from roadgonio.surface.rtable import header_line, u_names_table
    if isinstance(item, (str, Path)) and Path(str(item)).suffix.lower() == ".csv" and header_line(t):
        return header_line(t)
    return u_names_table(ut)


def compare_tables(a, b, *, out=None, plots: bool = True) -> dict[str, Any]:
    """Two r-tables side by side (``roadgonio compare``): the ratio r(B)/r(A) cell by cell (``ratio``,
    a DataArray over tan_eps x beta) with its range and largest change, S1, S2, Q0 and cells of both;
    with ``out`` (a folder or :data:`AUTO`) writes compare.csv, compare.json and (``plots``)
    compare.png."""
    from roadgonio.fileio import to_json
    from roadgonio.provenance import provenance
    from roadgonio.road.compare import COMPARE_FILES, compare_csv, compare_png
    from roadgonio.road.compare import compare_tables as _compare
    from roadgonio.road.report import write_together
    from roadgonio.provenance import input_record
    (ta, read_a), (tb, read_b) = _table_and_notes(a, "a"), _table_and_notes(b, "b")
    folder = _out(out, "compare", ta.name, tb.name)
    ta, tb = _labelled(a, ta), _labelled(b, tb)
    if ta.name == tb.name:
        tb = tb.with_values(tb.r, name=tb.name + "#2")
    res = _compare(ta, tb)
    res["notes"] = read_a + read_b + res["notes"]
    summary = {k: v for k, v in res.items() if k != "ratio"}
    if folder is not None:
        inputs = [input_record("a", a, ta.name), input_record("b", b, tb.name)]
        files = {"compare.csv": compare_csv(ta, tb, res["ratio"]),
                 "compare.json": to_json({**summary, "provenance": provenance(inputs=inputs)}) + "\n"}
        if plots:
            files["compare.png"] = compare_png(res, ta, tb)
        summary["written"] = [str(p) for p in write_together(folder, files, replaces=COMPARE_FILES)]
        summary["out"] = str(folder)
    summary["a"], summary["b"] = ta.name, tb.name
    import xarray as xr

    from roadgonio.surface.rtable import grid_coords
    summary["ratio"] = xr.DataArray(res["ratio"], dims=("tan_eps", "beta"), coords=grid_coords(ta.tan_eps, ta.beta_deg),
                                    name="ratio", attrs={"units": "1", "long_name": f"r({tb.name}) / r({ta.name})",
                                                         "note": "NaN: not in both tables or 0 in both; inf: r(A) = 0"})
    return summary


def largest_change_text(result: dict) -> str:
    """The largest change of a :func:`compare_tables` result in words (the wording of the command's
    line and of compare.png: :func:`roadgonio.road.compare.largest_change_text`)."""
    from roadgonio.road.compare import largest_change_text as text
    return text(result)


def s1_text(s1: float) -> str:
    """S1 as ``roadgonio classify`` prints it (:func:`roadgonio.surface.cie.s1_text`)."""
    from roadgonio.surface.cie import s1_text as text
    return text(s1)


def ratio_range_text(result: dict) -> str:
    """'0.995 ... 1.0034 (median 1)' of a :func:`compare_tables` result, each ratio with the digits it
    takes to differ from 1 (:func:`roadgonio.road.compare.range_text`)."""
    from roadgonio.road.compare import range_text
    return range_text(result)


def classify_table(table) -> dict[str, Any]:
    """The CIE class of an r-table by S1 in the R, C and N systems, its Q0 against the class
    standard, and the bundled tables nearest in (S1, Q0) (``roadgonio classify``;
    :func:`roadgonio.surface.cie.classify`)."""
    from roadgonio.surface.cie import classify
    try:
        t, read = _table_and_notes(table)
        res = classify(t)
        res["notes"] = read + res["notes"]
        return res
    except InputError as err:
        if isinstance(table, (str, Path)) and Path(str(table)).suffix and err.path is None:
            raise InputError(err.reason, path=table, field=err.field) from None
        raise
