"""Compute a k_A table (or one cell) with any backend: progress, resume, outputs, provenance.

Output folder (``--out DIR``):

* ``ka_cells.jsonl`` - the journal: one JSON line per finished cell, headed by the fingerprint of
  the run (instrument, model, backend, settings, roadgonio version). Backends report cells in
  batches; the journal is rewritten atomically (temporary file, fsync, rename) at most every
  :data:`FLUSH_SECONDS` and when the run ends or is interrupted, so it is always a complete file and
  a run killed at any point loses at most the cells of the last interval: it resumes from the
  journal. A journal of a *different* run is never mixed in (clear error, use another folder or
  ``--fresh``).
* ``ka.csv`` / ``ka_se.csv`` - k_A and its standard error in the r-table layout (rows tan eps,
  columns beta; cells not computed stay blank).
* ``ka.png`` - a map like the paper's Figure 4.
* ``ka.json`` - provenance (:func:`roadgonio.provenance.provenance`: instrument, model, backend and
  settings, versions), summary, and the run's ``fingerprint``: a finished run is never overwritten
  by a different one, even when its journal is gone (clear error; ``--fresh`` discards it).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from roadgonio.errors import InputError
from roadgonio.fileio import atomic_write, output_error, read_journal, to_json
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
from roadgonio.instrument.config import Instrument
from roadgonio.provenance import provenance
from roadgonio.surface.model import RoadModel
from roadgonio.surface.rtable import RTable
from roadgonio.engines.result import CellResult, KaBackend

JOURNAL = "ka_cells.jsonl"
META = "ka.json"
#: The journal is rewritten at most this often (seconds) while cells arrive.
FLUSH_SECONDS = 1.0


def fingerprint(instrument: Instrument, model: RoadModel, backend: KaBackend) -> str:
    """Hash of everything that determines the numbers of a run, the roadgonio version included."""
    from roadgonio import _version
    payload = {"instrument": instrument.to_dict(), "model": {"variant": model.variant,
                                                              "params": model.params.to_dict()},
               "backend": backend.name, "settings": backend.settings(), "roadgonio": _version.__version__}
    return hashlib.sha256(to_json(payload, indent=None).encode()).hexdigest()[:16]


@dataclass
class KaRun:
    """A finished (or partly finished) k_A computation."""

    results: list[CellResult]
    seconds: float
    resumed: int

    def grid(self, attr: str = "k_a") -> np.ndarray:
        out = np.full((len(TAN_EPS_GRID), len(BETA_GRID_DEG)), np.nan)
        for c in self.results:
            i = int(np.argmin(np.abs(TAN_EPS_GRID - c.tan_eps)))
            j = int(np.argmin(np.abs(BETA_GRID_DEG - c.beta_deg)))
            if abs(TAN_EPS_GRID[i] - c.tan_eps) < 1e-9 and abs(BETA_GRID_DEG[j] - c.beta_deg) < 1e-9:
                out[i, j] = getattr(c, attr)
        return out


def _cell_key(t: float, b: float) -> tuple[float, float]:
    return (round(float(t), 9), round(float(b), 9))


def _journal_record(d: dict) -> tuple[tuple[float, float], CellResult]:
    c = CellResult(**d)
    return _cell_key(c.tan_eps, c.beta_deg), c


def _read_journal(path: Path, fp: str) -> dict[tuple[float, float], CellResult]:
    return read_journal(path, fp, record=_journal_record,
                        different="results of a different run (instrument, model, backend or settings differ)")


def _check_finished_run(out_dir: Path, fp: str) -> None:
    """Refuse to overwrite the outputs of a different finished run (its ka.json fingerprint)."""
    meta = out_dir / META
    if not meta.exists():
        return
    try:
        old = json.loads(meta.read_text(encoding="utf-8")).get("fingerprint")
    except OSError as err:
        raise InputError(f"cannot read this file ({err.strerror or err}) to check which run it belongs to; "
                         "use another --out folder, or --fresh to discard it", path=meta) from None
    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
        old = None
    if old != fp:
        why = ("holds the results of a different run (instrument, model, backend, settings or roadgonio version "
               "differ)" if old else "holds results without a run fingerprint (an older roadgonio or another tool)")
        raise InputError(f"this folder {why}; use another --out folder, or --fresh to discard them", path=meta)


def _write_journal(journal: Path, header: dict, cells: Sequence[CellResult]) -> None:
    """The whole journal, atomically and durably (temporary file, fsync, rename)."""
    text = to_json(header, indent=None) + "\n" + "".join(to_json(c.to_dict(), indent=None) + "\n" for c in cells)

    def writer(tmp: Path) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
    atomic_write(journal, writer)


def run_cells(backend: KaBackend, cells: Sequence[tuple[float, float]], *, instrument: Instrument,
              model: RoadModel, out_dir: str | Path | None = None, fresh: bool = False,
              progress: bool = True) -> KaRun:
    """Compute k_A at ``cells`` with ``backend``; with ``out_dir``, journal the cells (batched atomic
    rewrites, module docstring) and resume. Every OSError on the journal (its folder cannot be
    made, read-only or full disk, unreadable) is the one-line :class:`InputError` naming the file."""
    t0 = time.perf_counter()
    journal = None
    done: dict[tuple[float, float], CellResult] = {}
    fp = fingerprint(instrument, model, backend)
    header = {"fingerprint": fp, "backend": backend.name}
    if out_dir is not None:
        out_dir = Path(out_dir)
        journal = out_dir / JOURNAL
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise output_error(journal, err) from None
        if fresh:
            for old in (journal, out_dir / META):
                try:
                    if old.exists():
                        old.unlink()
                except OSError as err:
                    raise output_error(old, err) from None
        _check_finished_run(out_dir, fp)
        done = _read_journal(journal, fp)
        # (re)write the header and the finished cells, dropping a cut-short last line
        _write_journal(journal, header, list(done.values()))
    todo = [c for c in cells if _cell_key(*c) not in done]
    resumed = len(cells) - len(todo)
    bar = None
    if progress and todo:
        from tqdm import tqdm
        bar = tqdm(total=len(cells), initial=resumed, unit="cell", desc=f"k_A ({backend.name})",
                   file=sys.stderr, dynamic_ncols=True, disable=None)
    pending = [0]
    last_flush = [time.monotonic()]

    def flush() -> None:
        if journal is not None and pending[0]:
            _write_journal(journal, header, list(done.values()))
            pending[0] = 0
            last_flush[0] = time.monotonic()

    def on_cell(c: CellResult) -> None:
        done[_cell_key(c.tan_eps, c.beta_deg)] = c
        pending[0] += 1
        if time.monotonic() - last_flush[0] >= FLUSH_SECONDS:
            flush()
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"tan={c.tan_eps:g} beta={c.beta_deg:g} k_A={c.k_a:.4g}")

    try:
        if todo:
            returned = backend.compute(todo, on_cell=on_cell)
            for c in returned:   # backends that do not call on_cell
                if _cell_key(c.tan_eps, c.beta_deg) not in done:
                    on_cell(c)
    finally:
        flush()
        if bar is not None:
            bar.close()
    results = [done[_cell_key(*c)] for c in cells if _cell_key(*c) in done]
    return KaRun(results=results, seconds=time.perf_counter() - t0, resumed=resumed)


def _precision_text(summary: dict[str, Any]) -> str:
    """'worst rel. SE 1.5e-04' or 'worst rel. error bound 9.9e-04' (never one for the other)."""
    for key, name in (("worst_rel_se", "worst rel. SE"), ("worst_rel_error_bound", "worst rel. error bound")):
        if summary.get(key) is not None:
            text = f"{name} {summary[key]:.1e}"
            if summary.get("not_converged"):
                text += f", {summary['not_converged']} cells NOT converged"
            return text
    return ""


def write_outputs(run: KaRun, out_dir: str | Path, *, instrument: Instrument, model: RoadModel,
                  backend: KaBackend, sample_spec: str, plot: bool = True, figures=None) -> dict[str, Any]:
    """Write ka.csv, ka_se.csv (or ka_bound.csv), ka.png and ka.json together or not at all
    (:class:`roadgonio.fileio.OutputGroup`: a failed or full disk leaves the folder's previous
    results and the journal as they were); returns the ka.json content. ``figures``
    (:class:`roadgonio.plotproc.FigureProcess`) draws the map in a helper process."""
    from roadgonio.fileio import OutputGroup
    out_dir = Path(out_dir)
    ka = run.grid("k_a")
    label = f"k_A of instrument '{instrument.name}' for sample '{sample_spec}' ({backend.name} backend)"
    with OutputGroup(out_dir) as group:      # all files or none
        RTable(ka, name="k_A", source=label).write_csv(group.path("ka.csv"), scale=1.0, digits=7)
        # a standard error (Monte Carlo) and a deterministic error bound (quadrature) go to different files
        deterministic = bool(run.results) and all(c.deterministic for c in run.results)
        prec_field, prec_file, prec_name = (("error_bound", "ka_bound.csv", "k_A error bound") if deterministic
                                            else ("se", "ka_se.csv", "k_A standard error"))
        RTable(run.grid(prec_field), name=prec_name, source=f"{prec_name} of " + label).write_csv(
            group.path(prec_file), scale=1.0, digits=4)
        rel = np.array([getattr(c, prec_field) / abs(c.k_a) if c.k_a else math.inf for c in run.results])
        finite_ka = np.array([c.k_a for c in run.results])
        summary = {
            "cells": len(run.results),
            "k_a_min": float(finite_ka.min()) if finite_ka.size else None,
            "k_a_max": float(finite_ka.max()) if finite_ka.size else None,
            ("worst_rel_error_bound" if deterministic else "worst_rel_se"): float(rel.max()) if rel.size else None,
            "not_converged": int(sum(not c.converged for c in run.results)),
            "samples": int(sum(c.samples for c in run.results)),
            "seconds_total": float(sum(c.seconds for c in run.results)),
            "seconds_wall_this_run": run.seconds,
            "resumed_cells": run.resumed,
        }
        meta = {
            "quantity": "k_A = (S[f_road]/S[f_lambert]) / (f_road(nominal)/f_lambert) (docs/conventions.md section 5)",
            "fingerprint": fingerprint(instrument, model, backend),
            **provenance(instrument=instrument, model=model, backend=backend.name, settings=backend.settings()),
            "sample": sample_spec,
            "summary": summary,
            "files": {"ka": "ka.csv", prec_field: prec_file, "map": "ka.png" if plot else None, "journal": JOURNAL},
        }
        group.json(META, meta)
        if plot:
            from roadgonio.plotproc import InProcess
            (figures or InProcess()).call(
                "table_map", ka, group.path("ka.png"), title=f"Aperture-effect factor k_A: {instrument.name} x {sample_spec}",
                subtitle=f"{backend.name} backend, {summary['cells']} cells, " + _precision_text(summary),
                label="k_A (1 = no aperture effect)")
    return meta
