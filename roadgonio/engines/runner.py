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

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from roadgonio.errors import count
from roadgonio.fileio import atomic_write, atomic_write_text, check_run_folder, fingerprint as _fingerprint, output_error, read_journal, to_json
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
from roadgonio.interrupts import critical
from roadgonio.instrument.config import Instrument
from roadgonio.provenance import provenance
from roadgonio.surface.model import RoadModel
from roadgonio.surface.rtable import KA_HEADER, grid_coords
from roadgonio.engines.cells import grid_index
from roadgonio.engines.result import CellResult, KaBackend

JOURNAL = "ka_cells.jsonl"
META = "ka.json"
#: A batched backend's state between passes (the cells not finished yet), so that a table cut short
#: resumes from its last pass instead of from nothing; removed when the table is done.
PASSES = "ka_passes.json"
#: The journal is rewritten at most this often (seconds) while cells arrive.
FLUSH_SECONDS = 1.0


def fingerprint(instrument: Instrument, model: RoadModel, backend: KaBackend) -> str:
    """Fingerprint of everything that determines the numbers of a run (:func:`roadgonio.fileio.fingerprint`:
    the instrument, the model's variant and parameters -- or a surface outside eq. 4 by its
    ``to_json_dict()`` -- the backend and its settings, the version)."""
    files = instrument.file_digests()        # only when it reads files: other fingerprints stay as they were
    surface = ({"variant": model.variant, "params": model.params.to_dict()} if isinstance(model, RoadModel)
               else model.to_json_dict())
    return _fingerprint({"instrument": instrument.to_dict(), **({"files": files} if files else {}),
                         "model": surface,
                         "backend": backend.name, "settings": backend.settings()})


@dataclass
class KaRun:
    """A finished (or partly finished) k_A computation: ``results`` the cells asked, in their order
    (computed now or ``resumed`` from the journal); ``table`` every cell of this run the output
    folder's journal holds (the cells asked and those of earlier runs with the same fingerprint, so
    a subset run into a folder with a larger table does not shrink the table files; None without a
    folder: the cells asked)."""

    results: list[CellResult]
    seconds: float
    resumed: int
    table: list[CellResult] | None = None
    #: cells of the rest that went on from their state after pass ``resumed_from_pass`` (a batched
    #: backend's ``ka_passes.json``) instead of starting over; 0 and None when none did
    resumed_pass_cells: int = 0
    resumed_from_pass: int | None = None

    @property
    def table_cells(self) -> list[CellResult]:
        return self.results if self.table is None else self.table

    def grid(self, attr: str = "k_a") -> np.ndarray:
        """``attr`` of the table's cells on the CIE grid (NaN where no cell is; cells off the grid left out)."""
        out = np.full((len(TAN_EPS_GRID), len(BETA_GRID_DEG)), np.nan)
        for c in self.table_cells:
            ij = grid_index(c.tan_eps, c.beta_deg)
            if ij is not None:
                out[ij] = getattr(c, attr)
        return out


def _on_grid(c: CellResult) -> bool:
    return grid_index(c.tan_eps, c.beta_deg) is not None


def _cell_key(t: float, b: float) -> tuple[float, float]:
    return (round(float(t), 9), round(float(b), 9))


def _journal_record(d: dict) -> tuple[tuple[float, float], CellResult]:
    """One journalled cell; a value no backend writes (k_A negative, infinite, or missing without the
    backend's note that it is undefined; a negative or infinite SE) is not a record, so the journal is
    refused rather than resumed with it (the user audit of session 19: a k_A of -5 went into ka.csv)."""
    if d.get("k_a", 0.0) is None and _not_measured(d.get("extra")):
        # strict JSON writes a NaN as null: a cell the backend could not measure (k_A NaN with its
        # reason) is a result of this run, resumed as it was (session 45: the run after such a table
        # refused its own journal as corrupt)
        d = {**d, "k_a": math.nan, "se": math.nan if d.get("se") is None else d["se"]}
    c = CellResult(**d)
    k, se = c.k_a, c.se
    if not isinstance(k, (int, float)) or isinstance(k, bool) or not isinstance(se, (int, float)):
        raise TypeError("k_a and se must be numbers")
    undefined = isinstance(c.extra, dict) and "undefined" in str(c.extra.get("note", ""))
    if (math.isnan(k) and not (undefined or _not_measured(c.extra))) or math.isinf(k) or k < 0.0 \
            or math.isinf(se) or se < 0.0:
        raise ValueError(f"k_a {k!r} with se {se!r} is not a result")
    return _cell_key(c.tan_eps, c.beta_deg), c


def _not_measured(extra) -> bool:
    """Whether a journalled cell is one its backend said it could not measure (the float32 renderer
    losing a lobe: ``float32_underflow`` with the reason in ``note``)."""
    return isinstance(extra, dict) and bool(extra.get("float32_underflow")) and bool(extra.get("note"))


def _read_journal(path: Path, fp: str) -> dict[tuple[float, float], CellResult]:
    return read_journal(path, fp, record=_journal_record,
                        different="results of a different run (instrument, model, backend or settings differ)")


def _check_finished_run(out_dir: Path, fp: str) -> None:
    """Refuse to overwrite the outputs of a different finished run (its ka.json fingerprint):
    :func:`roadgonio.fileio.check_run_folder`."""
    check_run_folder(out_dir, META, fp, what="run")


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
              progress: bool = True, field: str | None = None, step_progress: bool | None = None) -> KaRun:
    """Compute k_A at ``cells`` with ``backend``; with ``out_dir``, journal the cells (batched atomic
    rewrites, module docstring) and resume. Every OSError on the journal (its folder cannot be
    made, read-only or full disk, unreadable) is the one-line :class:`InputError` naming the file.
    ``field``: the argument that chose the cells; with it every cell still to compute is checked
    first (:func:`roadgonio.engines.cellcheck.check_requested`), so a cell the backend refuses is an
    InputError naming it before anything is computed or journalled. ``progress``: the table's bar of
    cells; ``step_progress`` (default ``progress``): a backend's bar of one long cell
    (:func:`roadgonio.progress.steps_shown`), both only on a terminal."""
    t0 = time.perf_counter()
    journal = None
    done: dict[tuple[float, float], CellResult] = {}
    fp = fingerprint(instrument, model, backend)
    header = {"fingerprint": fp, "backend": backend.name}
    new_journal = made_dir = False
    if out_dir is not None:
        out_dir = Path(out_dir)
        journal = out_dir / JOURNAL
        if not fresh and out_dir.is_dir():        # read only: the refusals of a folder in use come first
            _check_finished_run(out_dir, fp)
            done = _read_journal(journal, fp)
    # the geometry every backend refuses (:func:`roadgonio.engines.cellcheck.check_cells`), for all the
    # cells still to compute at once (the first bad cell and how many more), before the folder is touched
    still = [c for c in cells if _cell_key(*c) not in done]
    if field is None:
        from roadgonio.instrument.optics import check_source_cells
        check_source_cells(instrument, still)
    else:
        from roadgonio.engines.cellcheck import check_requested
        check_requested(backend, instrument, model, still, field=field)
    if out_dir is not None:
        made_dir = not out_dir.exists()
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise output_error(journal, err) from None
        if fresh:
            for old in (journal, out_dir / PASSES, *(out_dir / name for name in TABLE_FILES)):
                try:
                    if old.exists():
                        old.unlink()
                except OSError as err:
                    raise output_error(old, err) from None
        # the folder's run was checked and its journal read above (none when fresh or just made)
        new_journal = not journal.exists()
        # (re)write the header and the finished cells, dropping a cut-short last line
        _write_journal(journal, header, list(done.values()))
    todo = [c for c in cells if _cell_key(*c) not in done]
    resumed = len(cells) - len(todo)
    from roadgonio.progress import bar as progress_bar
    bar = progress_bar(len(cells), f"k_A ({backend.name})", unit="cell", initial=resumed, enabled=progress)
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

    passes = None
    if journal is not None and todo and getattr(backend, "checkpoints_passes", False):
        # the journal is written with every pass's state (the finished cells, then the others'
        # state): a run stopped at once between two passes resumes from both
        passes = PassCheckpoint(out_dir / PASSES, fp, flush=flush)
    from roadgonio.progress import steps_shown
    try:
        if todo:
            with steps_shown(progress if step_progress is None else step_progress):
                returned = (backend.compute(todo, on_cell=on_cell) if passes is None
                            else backend.compute(todo, on_cell=on_cell, checkpoint=passes))
            for c in returned:   # backends that do not call on_cell
                if _cell_key(c.tan_eps, c.beta_deg) not in done:
                    on_cell(c)
    except Exception:
        # refused (or failed) before anything was done: leave no journal of only a header, nor a
        # folder this run made ("nothing half-written"); a Ctrl-C keeps them (it says it resumes)
        if new_journal and not done and not (passes is not None and passes.path.exists()):
            _discard(journal, out_dir if made_dir else None)
        raise
    finally:
        flush()
        if bar is not None:
            bar.close()
    if passes is not None:
        passes.clear()
    results = [done[_cell_key(*c)] for c in cells if _cell_key(*c) in done]
    return KaRun(results=results, seconds=time.perf_counter() - t0, resumed=resumed,
                 table=list(done.values()) if journal is not None else None,
                 resumed_pass_cells=passes.reused_cells if passes is not None else 0,
                 resumed_from_pass=passes.reused_pass if passes is not None else None)


def _discard(journal: Path, folder: Path | None) -> None:
    """Remove a journal that holds only its header, and ``folder`` when it is left empty."""
    try:
        journal.unlink(missing_ok=True)
        if folder is not None and not any(folder.iterdir()):
            folder.rmdir()
    except OSError:
        pass        # the refusal being raised is what the user must read


class PassCheckpoint:
    """The state a batched backend saves after each pass (``ka_passes.json``: the cells not
    finished yet and their statistics, :meth:`roadgonio.engines.mitsuba.engine.BatchEngine.run`),
    under the run's fingerprint: a table interrupted mid-way resumes from its last completed pass
    with the same numbers. A state of another run, or unreadable, is ignored (the cells are
    computed again); JSON with every float exact.

    ``flush`` (the runner's journal writer) runs before each state is saved, in the same
    :func:`roadgonio.interrupts.critical` block, so the journal always holds the cells the state
    left out; :meth:`kept` says so for the line of a stop at once. The backend reports a state it
    carried on with :meth:`reused` (``reused_cells`` from pass ``reused_pass``: the summary's
    "continued after their pass N")."""

    def __init__(self, path: Path, fp: str, *, flush: Callable[[], None] | None = None):
        self.path, self.fp = Path(path), fp
        self.flush = flush
        self.reused_cells, self.reused_pass = 0, None
        self.saved_pass: int | None = None      # the pass of the state on disk, saved or carried on by this run

    def load(self) -> dict | None:
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        return doc.get("state") if isinstance(doc, dict) and doc.get("fingerprint") == self.fp else None

    def save(self, state: dict) -> None:
        """The journal (``flush``), then the state; a state of no cells (the last pass) removes the file."""
        with critical():
            if self.flush is not None:
                self.flush()
            if not state.get("cells"):
                self.clear()
                self.saved_pass = None
                return
            atomic_write_text(self.path, to_json({"fingerprint": self.fp, "state": state}, indent=None))
            self.saved_pass = int(state["pass"])

    def reused(self, cells: int, after_pass: int) -> None:
        """The backend carried ``cells`` cells on from the saved state after pass ``after_pass``."""
        self.reused_cells, self.reused_pass = int(cells), int(after_pass)
        self.saved_pass = int(after_pass)

    def kept(self) -> str:
        """What a stop at once keeps (the line of a second Ctrl-C during a pass: roadgonio.interrupts)."""
        journal = f"the finished cells ({self.path.parent / JOURNAL})"
        if self.saved_pass is None:
            return f"kept: {journal}; the other cells had no completed pass; run the same command again to resume"
        return (f"kept: {journal} and the other cells' state after pass {self.saved_pass} ({self.path.name}); "
                "run the same command again to resume")

    def clear(self) -> None:
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass
        except OSError as err:
            raise output_error(self.path, err) from None


#: The data variables of a k_A Dataset from the fields of CellResult: (long name, units, description).
FIELD_ATTRS: dict[str, tuple[str, str, str]] = {
    "k_a": ("aperture-effect factor k_A", "1",
            "what the instrument reports as q over f(nominal), under its calibration (docs/conventions.md section 5); "
            "r_true = r_measured / k_A"),
    "se": ("standard error of k_A", "1", "a standard error (Monte Carlo, randomised QMC); NaN where the backend gives "
           "none; inf where too few samples carried the light for one (the cell is not converged; ka.json's summary "
           "counts them as cells_without_se)"),
    "error_bound": ("deterministic error bound of k_A", "1",
                    "a deterministic bound on |k_A - true k_A| (quadrature) where converged is true; where it is "
                    "false (stopped at the evaluation cap) an estimate that can understate the error; NaN otherwise"),
    # the same field beside a standard error: a Monte Carlo backend under absolute calibration (audit 28:
    # files called eta's bound a bound on k_A, 200 times smaller than its SE)
    "error_bound_eta": ("deterministic error bound of the eta part of k_A (beside its standard error)", "1",
                        "under absolute calibration with a Monte Carlo backend: the part of k_A's error that is not "
                        "statistical, |k_A| times the error bound of eta = <E>/E_0 (float64 rules, not sampled); the "
                        "statistical part is se, so |k_A - true k_A| is at most error_bound plus a multiple of se"),
    "confidence_bound": ("confidence bound of k_A", "1",
                         "a statistical bound on |k_A - true k_A| holding with probability confidence_level (RQMC "
                         "reference); NaN otherwise"),
    "confidence_level": ("confidence level of confidence_bound", "1", "NaN where there is no confidence bound"),
    "samples": ("samples or integrand evaluations of the cell", "1", ""),
    "seconds": ("compute time of the cell", "s", "the pass's wall time shared out for batched backends"),
    "converged": ("the cell was computed and reached its target", "", "false where not computed or stopped at a cap"),
    # stray light (docs/conventions.md section 5; docs/straylight.md): without it k_a_direct = k_a, stray_fraction = 0
    "k_a_direct": (f"{KA_HEADER}the direct light", "1", "the light that reaches the footprint straight from the source "
                                                 "only (no stray light from the scene's reflecting parts)"),
    "k_a_direct_se": ("standard error of k_a_direct", "1",
                      "a standard error, as se; without stray light traced k_a_direct is k_a and this is se: NaN "
                      "for a backend that gives a deterministic error_bound instead (quadrature), which then "
                      "bounds k_a_direct too"),
    "stray_fraction": ("stray fraction of the road signal (a fraction: 0.3 is 30 %)", "1",
                       "1 - S_direct[f] / S_total[f]; 0 without stray light"),
    "stray_fraction_se": ("standard error of stray_fraction", "1",
                          "a standard error, as se; 0 without stray light traced, where the stray fraction is 0 "
                          "exactly (no reflecting parts: not an estimate)"),
    "se_dof": ("degrees of freedom of the standard errors", "1",
               "of se, k_a_direct_se and stray_fraction_se as estimates (the smallest of the three): n - 1 for n "
               "independent replicates or batches, the Welch-Satterthwaite value over the Mitsuba backend's passes "
               "(15 for a cell that converged in its first pass). An error over such an SE follows Student's t with "
               "this many degrees of freedom: a coverage interval or a pass/fail takes the t quantile "
               "(docs/validation.md). NaN where no SE is estimated"),
}
#: The stray-light outputs (written when the scene made stray light): field -> file.
STRAY_FILES = {"k_a_direct": "ka_direct.csv", "k_a_direct_se": "ka_direct_se.csv",
               "stray_fraction": "stray_fraction.csv", "stray_fraction_se": "stray_fraction_se.csv"}


#: every file a k_A table can write (:func:`write_outputs`), journal and pass state aside: a table
#: written removes those of an earlier one it does not write (a ka_se.csv beside a new ka_bound.csv),
#: and ``fresh`` removes them with the journal (a table of cells the journal no longer holds)
TABLE_FILES = ("ka.nc", "ka.csv", "ka_se.csv", "ka_bound.csv", "ka_confidence_bound.csv", *STRAY_FILES.values(),
               "ka.png", META)


def field_attrs(name: str) -> dict[str, str]:
    """The attributes (long name, units, description) of a field of the k_A result as a data variable
    (:data:`FIELD_ATTRS`): of the k_A Dataset, and of the same fields in design.nc."""
    long_name, units, description = FIELD_ATTRS.get(name, (name.replace("_", " "), "1", ""))
    return {"long_name": long_name, **({"units": units} if units else {}),
            **({"description": description} if description else {})}


def has_stray_light(ds) -> bool:
    """Whether a k_A Dataset holds stray light (some cell's stray fraction is not 0)."""
    sf = ds["stray_fraction"].values
    return bool(np.any(np.nan_to_num(sf) != 0.0))
#: Fields of CellResult that are not data variables.
_NOT_DATA = ("tan_eps", "beta_deg", "extra")


def ka_dataset(run: KaRun, *, instrument: Instrument, model: RoadModel, backend: KaBackend, sample: str,
               accuracy: str | None = None, seed: int | None = None, cells_asked: int | None = None):
    """THE k_A result (built once, here): an ``xarray.Dataset`` over ``tan_eps`` (29) x ``beta``
    (20, degrees) with one data variable per field of :class:`CellResult` (``k_a``, ``se``,
    ``error_bound``, ``confidence_bound``, ``confidence_level``, ``samples``, ``seconds``,
    ``converged``, and any field a backend adds), NaN (``converged`` False) where not computed.
    CF-style attributes: units and long names per variable; on the Dataset the title, the source
    (roadgonio's version), the seed the backend used (none for a deterministic backend: no ``seed``
    attribute), the precision kind of the backend and the cells' correlation, the
    provenance (:func:`roadgonio.provenance.provenance`, as JSON text) and the run's fingerprint.
    ``ka.nc`` is this Dataset (:func:`write_outputs`); the CSVs and ``ka.json`` are written from it."""
    import dataclasses

    import xarray as xr

    from roadgonio.engines.registry import BACKENDS
    from roadgonio.fileio import to_json
    names = [f.name for f in dataclasses.fields(CellResult) if f.name not in _NOT_DATA]
    dims = ("tan_eps", "beta")
    data = {}
    for name in names:
        grid = run.grid(name)
        if name == "converged":
            grid = np.nan_to_num(grid, nan=0.0).astype(bool)
        data[name] = (dims, grid, field_attrs(name))
    if eta_bound_beside_se(data["se"][1], data["error_bound"][1]):
        data["error_bound"] = (dims, data["error_bound"][1], field_attrs("error_bound_eta"))
    info = BACKENDS.get(backend.name)
    settings = backend.settings()
    prov = provenance(instrument=instrument, model=model, backend=backend.name, settings=settings, sample=sample,
                      accuracy=accuracy, cells=cells_asked if cells_asked is not None else len(run.results))
    computed = [c for c in run.table_cells if _on_grid(c)]     # the cells of the Dataset (the folder's table)
    attrs = {
        "Conventions": "CF-1.8",
        "title": f"{KA_HEADER}instrument '{instrument.name}' for sample '{sample}' ({backend.name} backend)",
        "source": f"roadgonio {prov['versions']['roadgonio']}",
        "history": f"{prov['created']} computed by roadgonio",
        "references": "Bernasconi et al., Geometrical errors and their uncertainty in goniophotometers: an application "
                      "to road surface photometry (paper eq. 2-3); roadgonio docs/conventions.md section 5",
        "quantity": "k_A = (S[f_road]/S[f_lambert]) / (f_road(nominal)/f_lambert) (docs/conventions.md section 5)",
        "instrument": instrument.name, "sample": sample, "backend": backend.name,
        # the preset when one was named; none with --rel-se or the backend's default (audit 22: was '')
        **({"accuracy": str(accuracy)} if accuracy is not None else {}),
        # the seed the backend used (its default when none was given); a deterministic backend takes
        # none and its Dataset has no seed attribute (was -1: a sentinel read as a seed)
        **({"seed": int(settings.get("seed", seed))} if settings.get("seed", seed) is not None else {}),
        "precision": info.precision if info else "",
        "cell_correlation": info.cell_correlation if info else "",
        "cells_computed": len(computed),
        "cells_asked": int(cells_asked if cells_asked is not None else len(run.results)),
        "cells_not_converged": int(sum(not c.converged for c in computed)),
        # cells the backend could not measure (k_A NaN: a float32 renderer that loses the lobe), with the
        # first one's reason (user audit, session 44: the reason was in the journal alone, and a table of
        # no measured cell crashed the command's summary)
        **_not_measured_attrs(computed),
        # absolute calibration: the cells whose eta = <E>/E_0 stopped at its cap, and eta's largest
        # relative error estimate (a deterministic estimate an SE does not hold; audit 21)
        **_eta_attrs(computed),
        "resumed_cells": int(run.resumed),
        # of the others, those carried on from their state after a pass (ka_passes.json); the pass
        # only when there were some (no sentinel)
        "resumed_pass_cells": int(run.resumed_pass_cells),
        **({"resumed_from_pass": int(run.resumed_from_pass)} if run.resumed_pass_cells else {}),
        "seconds_wall": float(run.seconds),
        "fingerprint": fingerprint(instrument, model, backend),
        "created": prov["created"],
        "provenance": to_json(prov, indent=None),
    }
    return xr.Dataset(data, coords=grid_coords(), attrs=attrs)


def _not_measured_attrs(cells) -> dict[str, Any]:
    """``cells_not_measured`` and, when there are some, the first one's cell and reason."""
    bad = [c for c in cells if not np.isfinite(c.k_a)]
    if not bad:
        return {"cells_not_measured": 0}
    first = bad[0]
    why = (first.extra or {}).get("note", "no value")
    return {"cells_not_measured": len(bad),
            "not_measured_note": f"tan eps = {first.tan_eps:g}, beta = {first.beta_deg:g}: {why}"}


def eta_bound_beside_se(se: np.ndarray, bound: np.ndarray) -> bool:
    """Whether ``error_bound`` sits beside a standard error (a Monte Carlo backend under absolute
    calibration: eta's part of the error, :mod:`roadgonio.engines.calibration`), not alone (the
    quadrature's bound on the whole error)."""
    both = np.isfinite(np.asarray(se, dtype=np.float64)) & np.isfinite(np.asarray(bound, dtype=np.float64))
    return bool(both.any())


def summary(ds) -> dict[str, Any]:
    """The summary of a k_A Dataset (``ka.json``, the command's last line): cells (of the table:
    with an output folder, every cell its journal holds for this run), ``cells_asked`` (this run's
    selection; ``resumed_cells`` of them were read back, ``resumed_pass_cells`` more carried on from
    their state after pass ``resumed_from_pass``), k_A range, the worst relative precision of
    the kind the backend gives, cells not converged, samples, times (all over the table's cells)."""
    done = np.isfinite(ds["k_a"].values)
    k = ds["k_a"].values[done]
    out: dict[str, Any] = {"cells": int(done.sum()),
                           "cells_asked": int(ds.attrs.get("cells_asked", done.sum())),
                           "k_a_min": float(k.min()) if k.size else None,
                           "k_a_max": float(k.max()) if k.size else None}
    for field, key in (("se", "worst_rel_se"), ("error_bound", "worst_rel_error_bound"),
                       ("confidence_bound", "worst_rel_confidence_bound")):
        v, kv = ds[field].values[done], k
        if field == "se" and v.size and not np.isnan(v).any() and np.isinf(v).any():
            # an SE that could not be stated (too few samples carried the light: engines.result,
            # RATIO_DENOMINATOR_REL_SE_MAX) is inf; the worst of the others, and how many
            out["cells_without_se"] = int(np.isinf(v).sum())
            kv, v = k[np.isfinite(v)], v[np.isfinite(v)]
        if v.size and np.isfinite(v).all():
            with np.errstate(divide="ignore", invalid="ignore"):
                rel = np.where(kv != 0, v / np.abs(kv), np.inf)
            out[key] = float(rel.max())
    if "worst_rel_error_bound" in out and eta_bound_beside_se(ds["se"].values, ds["error_bound"].values):
        out["error_bound_of"] = "eta = <E>/E_0 of the absolute calibration (beside the standard error)"
    if "cells_eta_not_converged" in ds.attrs:
        out.update(eta_not_converged=int(ds.attrs["cells_eta_not_converged"]),
                   eta_worst_rel_error=float(ds.attrs["eta_worst_rel_error"]))
    if int(ds.attrs.get("cells_not_measured", 0)):
        out.update(not_measured=int(ds.attrs["cells_not_measured"]), not_measured_note=ds.attrs["not_measured_note"])
    out.update(not_converged=int(ds.attrs["cells_not_converged"]),
               samples=int(np.nansum(ds["samples"].values)),
               seconds_total=float(np.nansum(ds["seconds"].values)),
               seconds_wall_this_run=float(ds.attrs["seconds_wall"]),
               resumed_cells=int(ds.attrs["resumed_cells"]),
               resumed_pass_cells=int(ds.attrs.get("resumed_pass_cells", 0)))
    if out["resumed_pass_cells"]:
        out["resumed_from_pass"] = int(ds.attrs["resumed_from_pass"])
    if has_stray_light(ds):
        kd = ds["k_a_direct"].values[done]
        ok = np.isfinite(kd)
        out.update(stray_fraction_max=float(np.nanmax(ds["stray_fraction"].values[done])),
                   k_a_direct_min=float(kd[ok].min()) if ok.any() else None,
                   k_a_direct_max=float(kd[ok].max()) if ok.any() else None,
                   cells_without_direct_light=int((~ok).sum()))
    return out


def confidence_text(ds) -> str:
    """' at confidence level 0.999' (the levels of a k_A Dataset's confidence bounds): a confidence
    bound means nothing without its level, and ka_confidence_bound.csv has no column for it."""
    levels = sorted({float(x) for x in np.asarray(ds["confidence_level"].values).ravel() if np.isfinite(x)})
    if not levels:
        return ""
    if len(levels) == 1:
        return f" at confidence level {levels[0]:g}"
    return " at confidence levels " + ", ".join(f"{x:g}" for x in levels) + " (per cell: confidence_level in ka.nc)"


def _eta_attrs(results) -> dict[str, Any]:
    """The Dataset attributes of eta (absolute calibration) over ``results``: the cells whose eta did
    not converge and eta's largest relative error estimate; none without absolute calibration."""
    ex = [c.extra for c in results if c.extra and "eta_converged" in c.extra]
    if not ex:
        return {}
    rel = [e["eta_error"] / e["eta"] for e in ex if e.get("eta")]
    return {"cells_eta_not_converged": int(sum(not e["eta_converged"] for e in ex)),
            "eta_worst_rel_error": float(max(rel)) if rel else float("nan")}


def precision_text(summary: dict[str, Any]) -> str:
    """'worst rel. SE 1.5e-04' or 'worst rel. error bound 9.9e-04' (never one for the other; a Monte
    Carlo table under absolute calibration gives its SE and, beside it, eta's bound); cells whose SE
    could not be stated are counted apart ('(2 cells without one)'; all of them: 'no standard error in
    any of its 3 cells')."""
    without = summary.get("cells_without_se") or 0
    for key, name in (("worst_rel_se", "worst rel. SE"), ("worst_rel_error_bound", "worst rel. error bound")):
        if summary.get(key) is not None:
            estimated = key == "worst_rel_error_bound" and bool(summary.get("not_converged"))
            # the error_bound of a cell not converged is an estimate (a cell at the cap, or across a
            # map's kinks): the table's line called the worst of them a bound (audit 27)
            text = f"{'worst rel. error' if estimated else name} {summary[key]:.1e}"
            if key == "worst_rel_se" and without:
                text += f" ({count(without, 'cell')} without one)"
            if key == "worst_rel_se" and summary.get("worst_rel_error_bound") is not None:
                # absolute calibration of a Monte Carlo table: eta's error, a bound beside the SE
                text += f" (and eta's worst rel. error bound {summary['worst_rel_error_bound']:.1e})"
            return text + _not_converged_part(summary, key, estimated)
    if without:
        return f"no standard error in any of its {count(without, 'cell')}" + _not_converged_part(summary, "", False)
    return ""


def _not_converged_part(summary: dict[str, Any], key: str, estimated: bool) -> str:
    if not summary.get("not_converged"):
        return ""
    text = f", {count(summary['not_converged'], 'cell')} NOT converged"
    if estimated:
        text += " (there an estimate, not a bound)"
    if summary.get("eta_not_converged"):
        text += (f" (in {summary['eta_not_converged']} of them eta of the absolute calibration stopped at "
                 f"its cap: relative error up to {summary['eta_worst_rel_error']:.1e}, "
                 + ("the error bound beside the SE)" if key == "worst_rel_se" else "included in the bound)"))
    return text


def write_outputs(ds, out_dir: str | Path, *, plot: bool = True, figures=None) -> dict[str, Any]:
    """Write the k_A Dataset ``ds`` (:func:`ka_dataset`) to ``out_dir`` together or not at all
    (:class:`roadgonio.fileio.OutputGroup`: a failed or full disk leaves the folder's previous results
    and the journal as they were): ``ka.nc`` (the Dataset), ``ka.csv`` (k_A), its precision in the
    same layout (``ka_se.csv`` for a standard error, ``ka_bound.csv`` for a deterministic bound,
    and ``ka_confidence_bound.csv`` beside ka_se.csv for a confidence bound; with stray light
    ``ka_direct.csv``, ``stray_fraction.csv`` and their ``_se`` files), ``ka.png`` and
    ``ka.json`` (provenance, summary, fingerprint, files); returns the ka.json content. ``figures``
    (:class:`roadgonio.plotproc.FigureProcess`) draws the map in a helper process."""
    import json as _json

    from roadgonio.fileio import OutputGroup, write_netcdf
    from roadgonio.surface.rtable import grid_csv_text, ka_output_header
    out_dir = Path(out_dir)
    label = ds.attrs["title"]
    s = summary(ds)
    files = {"netcdf": "ka.nc", "ka": "ka.csv"}
    with OutputGroup(out_dir, replaces=TABLE_FILES) as group:      # all files or none
        write_netcdf(ds, group.path("ka.nc"))
        group.text("ka.csv", grid_csv_text(ds["k_a"].values, label, digits=7))
        for field, name in (("se", "ka_se.csv"), ("error_bound", "ka_bound.csv"),
                            ("confidence_bound", "ka_confidence_bound.csv")):
            v = ds[field].values
            if np.isfinite(v).any():
                what = ds[field].attrs["long_name"] + (confidence_text(ds) if field == "confidence_bound" else "")
                if field == "error_bound" and "converged" in ds:
                    # the cells that stopped short hold an estimate, not a bound: the file's header said
                    # "deterministic error bound" of every cell (review, session 39)
                    short = int((np.isfinite(v) & ~ds["converged"].values.astype(bool)).sum())
                    if short:
                        what += (f"; in {count(short, 'cell')} not converged (ka.nc's converged) an estimate "
                                 "that can understate the error, not a bound")
                group.text(name, grid_csv_text(v, ka_output_header(what, ds.attrs["instrument"], ds.attrs["sample"],
                                                                   ds.attrs["backend"]), digits=4))
                files[field] = name
        if has_stray_light(ds):
            for field, name in STRAY_FILES.items():
                group.text(name, grid_csv_text(ds[field].values, ka_output_header(
                    ds[field].attrs["long_name"], ds.attrs["instrument"], ds.attrs["sample"], ds.attrs["backend"]),
                    digits=7 if "se" not in field else 4))
                files[field] = name
        if plot:
            files["map"] = "ka.png"
        files["meta"] = META
        files["journal"] = JOURNAL
        meta = {"quantity": ds.attrs["quantity"], "fingerprint": ds.attrs["fingerprint"],
                **_json.loads(ds.attrs["provenance"]), "precision": ds.attrs["precision"],
                "cell_correlation": ds.attrs["cell_correlation"], "summary": s, "files": files}
        group.json(META, meta)
        if plot:
            from roadgonio.plotproc import InProcess
            k = ds["k_a"].values
            # within 0.5 % of 1 everywhere, two decimals would print 1.00 on cells the colours tell apart
            near_one = bool(np.isfinite(k).any()) and float(np.nanmax(np.abs(k - 1.0))) < 0.005
            (figures or InProcess()).call(
                "table_map", k, group.path("ka.png"),
                title=f"Aperture-effect factor k_A: {ds.attrs['instrument']} x {ds.attrs['sample']}"
                      + (" (stray light included; ka_direct.csv without)" if has_stray_light(ds) else ""),
                subtitle=f"{ds.attrs['backend']} backend, {count(s['cells'], 'cell')}, " + precision_text(s),
                label="k_A (1 = no aperture effect)", blank="not computed", fmt="{:.4f}" if near_one else "{:.2f}")
    return meta
