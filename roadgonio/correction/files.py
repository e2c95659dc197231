"""Correcting measured tables, the entry of the correction room: one table
(:func:`correct_measured`: ``reference = "self"`` with the eq. 4 forward model,
:func:`roadgonio.correction.run.correct_self`, or with eq. 4 times the correction surface,
:func:`roadgonio.correction.outside.correct_surface`; or ``reference = SAMPLE``), several tables of
one instrument (:func:`correct_files`, in this process or one Dask task per table), and several
instruments that measured one surface (:func:`correct_joint`; docs/correction.md, "Outside eq. 4").

It sits above :mod:`.run` (the eq. 4 procedure and its helpers) and :mod:`.outside` (the
correction surface), which both use the helpers of :mod:`.run`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from roadgonio.engines.bundle import DEFAULT_RAYS
from roadgonio.correction.budget import DEFAULT_U_MEASURED
from roadgonio.correction.outside import DEFAULT_VARIANTS, SurfaceCorrection, correct_surface, to_correction_result
from roadgonio.correction.run import (FORWARDS, CorrectionResult, InstrumentArtefacts, _check_fit_cells, _sigma,
                                      check_measured, correct_self, correct_with_reference, measured_uncertainty)
from roadgonio.errors import InputError
from roadgonio.fileio import safe_name
from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel
from roadgonio.surface.rtable import RTable


def correct_self_surface(measured: RTable, instrument: Instrument, *, model_variant: str | None = None,
                         artefacts: InstrumentArtefacts | None = None, max_outer: int | None = None,
                         tol: float | None = None, **options: Any) -> CorrectionResult:
    """``reference = "self"`` with the forward model that can follow a surface outside eq. 4: the
    backbone variants times the correction surface (:func:`roadgonio.correction.outside.correct_surface`
    through this one instrument), as a :class:`CorrectionResult`. ``model_variant`` None or
    ``"auto"`` weighs every variant of :data:`roadgonio.correction.outside.DEFAULT_VARIANTS` by its
    evidence; a variant name uses that one alone."""
    variants = DEFAULT_VARIANTS if model_variant in (None, "auto") else (model_variant,)
    res = correct_surface([measured], [instrument], artefacts=None if artefacts is None else [artefacts],
                          variants=variants, max_outer=max_outer, tol=tol, **options)
    return to_correction_result(res)



def correct_measured(measured: RTable, instrument: Instrument, *, reference: Any = "self",
                     reference_name: str | None = None, alternatives: Any = "auto", model_variant: str | None = None,
                     **options: Any) -> CorrectionResult:
    """Correct one measured table: ``reference="self"`` (default) fits the model through the
    instrument (:func:`correct_self`; ``model_variant`` None = ``"auto"``); a SAMPLE (text) or a
    :class:`RoadModel` takes the classic route (:func:`correct_with_reference`, ``alternatives`` as
    :func:`roadgonio.correction.reference.resolve_alternatives`). ``options`` go to either."""
    from roadgonio.correction.reference import resolve_alternatives, sample_name
    forward = options.pop("forward", "eq4")
    if forward not in FORWARDS:
        raise InputError(f"unknown forward model {forward!r}; expected one of {', '.join(FORWARDS)}", field="forward")
    if isinstance(reference, str) and reference.strip().lower() == "self":
        if forward == "surface":
            return correct_self_surface(measured, instrument, model_variant=model_variant, **options)
        return correct_self(measured, instrument, variant=model_variant or "auto", **options)
    if isinstance(reference, RoadModel):
        ref_model, name = reference, reference_name or reference.name or "reference"
    else:
        from roadgonio.surface.sample import resolve_sample
        ref_model, name = resolve_sample(str(reference), model_variant).model, reference_name or sample_name(str(reference))
    alts = alternatives if isinstance(alternatives, Mapping) else resolve_alternatives(
        alternatives, measured, reference_name=name, model_variant=model_variant)
    keep = {k: v for k, v in options.items() if k in ("u_measured", "sigma", "backend", "backend_settings",
                                                      "accuracy", "factory", "out_dir", "misalignment_rays",
                                                      "seed", "progress")}
    return correct_with_reference(measured, instrument, ref_model, reference_name=name, alternatives=alts, **keep)


def folder_names(tables: Sequence[RTable], measured_files: Sequence[str | None] | None = None) -> list[str]:
    """The name of each table's sub-folder: the file's stem when it was read from a file (an RTB stores
    a surface name: two files storing "R3" became R3 and R3-2, and site2.rtb's results sat in R3, user
    audit 29), else the table's name (a bundled table, an object)."""
    given = list(measured_files or [None] * len(tables))
    return [Path(str(f)).stem if f is not None else t.name for t, f in zip(tables, given)]


def output_folders(names: Sequence[str], out_dir: str | Path) -> list[Path]:
    """One folder per measured table: ``out_dir`` itself for one table, else ``out_dir/NAME``
    (``NAME-2``, ... when two files share a name)."""
    out = Path(out_dir)
    if len(names) == 1:
        return [out]
    seen: dict[str, int] = {}
    folders = []
    for n in names:
        safe = safe_name(n, "table")
        seen[safe] = seen.get(safe, 0) + 1
        folders.append(out / (safe if seen[safe] == 1 else f"{safe}-{seen[safe]}"))
    return folders


def _is_self(reference: Any) -> bool:
    return isinstance(reference, str) and reference.strip().lower() == "self"


def _absolute_file(spec: Any) -> Any:
    """A --u-measured text naming an existing file, as an absolute path (workers may run in another
    folder); a percentage, a number or an RTable unchanged."""
    if isinstance(spec, (str, Path)) and str(spec).strip() and not str(spec).strip().endswith("%"):
        p = Path(str(spec).strip()).expanduser()
        if p.suffix and p.exists():
            return str(p.absolute())
    return spec


def _correct_task(job: tuple, shared: Mapping[str, Any]) -> tuple[CorrectionResult, list[Path]]:
    """One measured table, start to finish: :func:`correct_measured` then :func:`write_correction`
    into its folder (in this process, or as one Dask task on a worker: :func:`correct_files`)."""
    from roadgonio.correction.outputs import write_correction
    table, folder, alternatives, measured_file = job
    options = dict(shared["options"])
    if shared["artefacts"] is not None:
        options["artefacts"] = shared["artefacts"]
    if not _is_self(shared["reference"]):
        options["alternatives"] = alternatives
    res = correct_measured(table, shared["instrument"], reference=shared["reference"],
                           reference_name=shared["reference_name"], out_dir=folder, **options)
    if shared.get("cluster") is not None:
        from roadgonio.engines.cluster import _worker_name
        res.provenance["cluster"] = {**shared["cluster"], "computed_by": _worker_name()}
    if measured_file is not None:
        res.provenance["measured_file"] = measured_file
    if shared.get("inputs") is not None:
        res.provenance["inputs"] = shared["inputs"][measured_file]
    if folder is None:                      # nothing to write (the Python API without out)
        return res, []
    from roadgonio.interrupts import stop_asked_by_caller
    if stop_asked_by_caller(fresh=True):
        # on a Dask worker whose command was interrupted meanwhile: its journals are kept, no results
        from roadgonio.errors import StoppedByCaller
        raise StoppedByCaller("stopped before writing the results: the command that asked for them was interrupted")
    return res, write_correction(res, folder, plots=shared["plots"])


def input_records(measured_file: str | Path | None, u_measured: Any = None) -> list[dict[str, Any]]:
    """The provenance records (:func:`roadgonio.provenance.input_record`: absolute path and sha256) of a
    measured table's file and of its ``u_measured`` when that is a file, made where the command runs
    (user audit: correct.json named 'meas.csv' and 'ok1pct.csv' only, so a finished result could not
    say which contents it corrected)."""
    from roadgonio.provenance import input_record
    out = []
    if measured_file is not None:
        out.append(input_record("measured", str(measured_file), "the measured table"))
    if isinstance(u_measured, (str, Path)) and Path(u_measured).is_file():
        out.append(input_record("u_measured", str(u_measured), "its per-cell standard uncertainties"))
    return out


def correct_files(tables: Sequence[RTable], instrument: Instrument, out_dir: str | Path | None, *, plots: bool = True,
                  reference: Any = "self", workers: int | None = None, scheduler: str | None = None, client=None,
                  measured_files: Sequence[str | None] | None = None,
                  **options: Any) -> list[tuple[CorrectionResult, Path | None, list[Path]]]:
    """Correct several measured tables with one instrument; returns (result, folder, files) per table.
    With ``out_dir=None`` nothing is journalled or written (folder None, no files). ``measured_files``
    (the files the tables were read from) go into each result's provenance before it is written.

    Everything that does not depend on the table is done once, here, before any table: the
    checks of every table and of ``u_measured`` / ``sigma``, the reference model and each table's
    alternatives (``reference=SAMPLE``), the instrument's artefacts (``reference="self"``: the ray
    bundles of every distinct cell set).

    Each table's correction and outputs (:func:`correct_measured`, :func:`write_correction`) is
    one call of :func:`_correct_task`: one after the other in this process by default, or one
    Dask task each with ``client``, ``workers`` (a local cluster of that many worker processes;
    0 = here) or ``scheduler`` (an existing cluster), through
    :func:`roadgonio.engines.cluster.map_calls`. The artefacts are built here and shipped to the
    workers once (they pickle: plain numpy arrays and frozen dataclasses), so every table gets
    the same bundles and the same seeds wherever it runs: the results are identical to the
    in-process run whatever the number of workers. The workers write the journals and outputs
    themselves, so with ``scheduler`` the output folder must be on a file system they share at
    the same path (checked: a file the workers wrote that is not here is a clear error).
    ``options["progress"]``: in this process the steps and k_A bars of each table; on Dask a bar
    over the tables.
    """
    tables = list(tables)
    folders = (output_folders(folder_names(tables, measured_files), out_dir) if out_dir is not None
               else [None] * len(tables))
    self_ref = _is_self(reference)
    progress = bool(options.get("progress", True))
    distributed = client is not None or scheduler is not None or workers not in (None, 0)
    if distributed and out_dir is None:
        raise InputError("tables corrected on Dask workers are written by the workers: give an output folder",
                         field="out")
    if distributed and options.get("factory") is not None:
        raise InputError("a custom backend factory cannot run on Dask workers; give a backend name",
                         field="workers")
    # checks and table-independent work, once and before any table
    for t in tables:
        check_measured(t)
        if self_ref:
            _check_fit_cells(t)
        measured_uncertainty(options.get("u_measured", DEFAULT_U_MEASURED), t)
    options["sigma"] = _sigma(options.get("sigma"))
    model_variant = options.pop("model_variant", None)
    alternatives = options.pop("alternatives", "auto")
    ref_name = options.pop("reference_name", None)
    alts: list[Any] = [None] * len(tables)
    if self_ref:
        options["model_variant"] = model_variant
        artefacts = options.pop("artefacts", None) or InstrumentArtefacts(
            instrument, rays=options.pop("rays", DEFAULT_RAYS), seed=options.get("seed", 0))
        options.pop("rays", None)
        # the ray bundles of every cell set, built here once. They pickle (numpy arrays and frozen
        # dataclasses), so on Dask they are shipped to the workers (map_calls(shared=...)), not rebuilt there
        for t in tables:
            artefacts.forward(t.cells)
    else:
        from roadgonio.correction.reference import resolve_alternatives, sample_name
        from roadgonio.surface.sample import resolve_sample
        artefacts = None
        if not isinstance(reference, RoadModel):
            ref_name = ref_name or sample_name(str(reference))
            reference = resolve_sample(str(reference), model_variant).model
        ref_name = ref_name or reference.name or "reference"
        alts = [alternatives if isinstance(alternatives, Mapping) else resolve_alternatives(
            alternatives, t, reference_name=ref_name, model_variant=model_variant) for t in tables]
        for k in ("rays", "artefacts", "starts", "polish", "rounds", "max_outer", "tol"):
            options.pop(k, None)
    files = [None if f is None else str(f) for f in (measured_files or [None] * len(tables))]
    shared = {"instrument": instrument, "artefacts": artefacts, "reference": reference, "reference_name": ref_name,
              "plots": plots, "options": options, "cluster": None,
              "inputs": {f: input_records(f, options.get("u_measured")) for f in files}}
    jobs = list(zip(tables, folders, alts, files))
    if not distributed:
        from roadgonio.engines.cluster import map_calls
        return [(res, job[1], written) for job, (res, written) in zip(jobs, map_calls(_correct_task, jobs, None,
                                                                                     shared=shared))]
    return _correct_on_dask(jobs, shared, client=client, workers=workers, scheduler=scheduler, progress=progress)


def _correct_on_dask(jobs, shared, *, client, workers, scheduler, progress) -> list:
    from roadgonio.engines import cluster as _cluster
    options = dict(shared["options"])
    options["progress"] = False                  # no terminal on a worker: the bar over tables is here
    if isinstance(options.get("u_measured"), (str, Path)):
        options["u_measured"] = _absolute_file(options["u_measured"])
    inst = shared["instrument"]
    if inst.path is not None and not Path(inst.path).is_absolute():
        import dataclasses
        inst = dataclasses.replace(inst, path=Path(inst.path).absolute())   # an XML scene beside it
    backend = options.get("backend", "mitsuba")
    variant = dict(options.get("backend_settings") or {}).get("mitsuba_variant")
    work = [(t, Path(f).absolute(), a, m) for t, f, a, m in jobs]
    from roadgonio.progress import bar as progress_bar
    bar = progress_bar(len(work), f"correct ({backend}, Dask)", unit="table", enabled=progress)

    def run(c) -> list:
        info = _cluster.describe(c)
        if bar is not None:
            bar.set_description(f"correct ({backend}, {info['workers']} Dask workers)")
        sh = {**shared, "instrument": inst, "options": options, "cluster": info}
        return _cluster.map_calls(_correct_task, work, c, shared=sh, backend=backend, variant=variant,
                                  name="correct", on_result=lambda i, r: bar.update(1) if bar is not None else None)
    try:
        if client is not None:
            results = run(client)
        else:
            with _cluster.open_client(workers, scheduler, backend=backend, variant=variant) as c:
                results = run(c)
    finally:
        if bar is not None:
            bar.close()
    out = []
    for (_t, folder, _, _), (res, written) in zip(jobs, results):
        here = [Path(folder) / Path(p).name for p in written]
        for p in here:
            if not p.exists():
                raise InputError("a Dask worker wrote this file on its own file system, not here: with --scheduler "
                                 "the --out folder must be shared by the workers at the same path", path=p)
        out.append((res, Path(folder), here))
    return out


def correct_joint(tables: Sequence[RTable], instruments: Sequence[Instrument], out_dir: str | Path | None, *,
                  plots: bool = True, model_variant: str | None = None, measured_files: Sequence[str | None] | None = None,
                  **options: Any) -> SurfaceCorrection:
    """Several instruments (or aperture settings) that measured one surface: one surface (eq. 4
    backbone x correction surface) fitted through all of them, one corrected table with its
    uncertainty and each instrument's k_A (:func:`roadgonio.correction.outside.correct_surface`);
    with ``out_dir`` the files of :func:`roadgonio.correction.outputs.write_surface_correction`
    (``.out`` and ``.written`` on the result). ``model_variant`` None or ``"auto"`` weighs the
    backbone variants by their evidence."""
    from roadgonio.correction.outputs import write_surface_correction
    tables, instruments = list(tables), list(instruments)
    if len(tables) < 2 or len(tables) != len(instruments):
        raise InputError(f"a joint correction takes one --instrument per --measured table, at least two; got "
                         f"{len(tables)} table(s) and {len(instruments)} instrument(s)", field="joint")
    for i in range(len(tables)):
        for j in range(i):
            if not np.array_equal(tables[i].r, tables[j].r, equal_nan=True):
                continue
            if instruments[i].to_dict() == instruments[j].to_dict():
                # the same data counted twice would halve its stated noise (user audit, session 19)
                raise InputError(f"the same table through the same instrument is given twice (pairs {j + 1} and "
                                 f"{i + 1}: {instruments[i].name}); expected each measurement once",
                                 field="joint")
            # two instruments never measure the same values to the last digit: one file given for both
            # (user audit, session 38: it was fitted as two measurements)
            raise InputError(f"pairs {j + 1} and {i + 1} hold the same values through two instruments "
                             f"({instruments[j].name}, {instruments[i].name}); expected each instrument's own "
                             "measurement", field="joint")
    variants = DEFAULT_VARIANTS if model_variant in (None, "auto") else (model_variant,)
    options["sigma"] = _sigma(options.get("sigma")) if not isinstance(options.get("sigma"), (list, tuple)) \
        else [_sigma(s) for s in options["sigma"]]
    for k in ("alternatives", "reference_name", "forward"):
        options.pop(k, None)
    u_given = options.get("u_measured")
    res = correct_surface(tables, instruments, out_dir=out_dir, variants=variants, **options)
    if measured_files is not None:
        res.provenance["measured_files"] = [None if f is None else str(f) for f in measured_files]
        us = u_given if isinstance(u_given, (list, tuple)) else [u_given] * len(measured_files)
        res.provenance["inputs"] = [r for f, u in zip(measured_files, us) for r in input_records(f, u)]
    res.out = None if out_dir is None else Path(out_dir)
    res.written = [] if out_dir is None else write_surface_correction(res, out_dir, plots=plots)
    return res
