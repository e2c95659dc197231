"""The k_A table runner: journal, resume after an interruption, refusal to mix runs, outputs."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from roadgonio.errors import InputError
from roadgonio.instrument.config import load_instrument
from roadgonio.engines import CellResult, full_grid_cells
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
from roadgonio.engines.runner import JOURNAL, ka_dataset, run_cells, write_outputs
from roadgonio.surface.model import RoadModel, RoadParams
from roadgonio.surface.rtable import read_table


class Interrupted(Exception):
    pass


class StandIn:
    """A deterministic backend whose k_A is a known function of the cell; can fail after N cells."""

    name = "stand-in"

    def __init__(self, fail_after=None, tag=0):
        self.fail_after = fail_after
        self.calls = []
        self.tag = tag

    def settings(self):
        return {"tag": self.tag}

    @staticmethod
    def value(t, b):
        return 1.0 + 0.01 * t * np.cos(np.radians(b))

    def compute(self, cells, on_cell=None):
        out = []
        for k, (t, b) in enumerate(cells):
            if self.fail_after is not None and k >= self.fail_after:
                raise Interrupted()
            self.calls.append((t, b))
            c = CellResult(t, b, self.value(t, b), 1e-4, 1000, 0.001)
            out.append(c)
            if on_cell:
                on_cell(c)
        return out


@pytest.fixture
def setup():
    return load_instrument("portable"), RoadModel(RoadParams(k_diff=0.05, k_phong=0.3, n_phong=200))


def test_full_grid_has_580_cells():
    cells = full_grid_cells()
    assert len(cells) == 580 and len(set(cells)) == 580


def test_the_grid_index_of_a_cell_is_written_once():
    """engines.cells.grid_index is the one (row, column) of a cell on the CIE grid (the runner had its
    own copy; the one in cells had no caller): every grid cell maps to its place, a cell off the grid to None."""
    from roadgonio.engines.cells import full_grid_cells, grid_index
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    for t, b in full_grid_cells():
        i, j = grid_index(t, b)
        assert TAN_EPS_GRID[i] == t and BETA_GRID_DEG[j] == b
    assert grid_index(0.3, 0.0) is None and grid_index(1.0, 3.0) is None and grid_index(1.0 + 1e-6, 0.0) is None


def test_one_grid_lookup_each_caller_with_its_tolerance(tmp_path):
    """geometry.nearest_grid_node is the one lookup of a cell on the grid (rtable's correlation
    reader had its own copy of grid_index's): the nearest node and the farther label's distance
    (tan eps or beta, deg). Each caller keeps its tolerance: grid_index takes a cell closer than
    CELL_TOL (1e-9, strictly), a correlation file's label within GRID_LABEL_TOL (1e-6, inclusive)."""
    from helpers import refused_in_one_line

    from roadgonio.engines.cells import CELL_TOL, grid_index, on_the_grid
    from roadgonio.geometry import nearest_grid_node
    from roadgonio.surface.rtable import GRID_LABEL_TOL, read_cell_correlation
    assert nearest_grid_node(0.3, 3.0) == (1, 1, pytest.approx(1.0, abs=1e-12))      # 0.25 (0.05 off), 2 deg (1 off)
    assert nearest_grid_node(12.2, 178.0) == (28, 19, pytest.approx(2.0, abs=1e-12))
    assert nearest_grid_node(11.1, 180.0) == (26, 19, pytest.approx(0.1, abs=1e-12))
    assert grid_index(0.5 * CELL_TOL, 0.0) == (0, 0) and grid_index(CELL_TOL, 0.0) is None
    assert on_the_grid(0.5 * CELL_TOL, 180.0) and not on_the_grid(12.0, CELL_TOL)
    path = tmp_path / "corr.csv"
    for label, ok in ((f"{GRID_LABEL_TOL:.6f}/0", True), ("0/179.999999", True), ("0.000002/0", False),
                      ("0/179.999998", False)):
        path.write_text(f"cell,{label}\n{label},1.0000\n")
        if ok:
            cells, _ = read_cell_correlation(path)
            assert cells in ([(0.0, 0.0)], [(0.0, 180.0)]), cells
        else:
            refused_in_one_line(lambda: read_cell_correlation(path), path, [f"cell '{label}' is not on the standard grid"])


def test_resume_after_interruption_computes_each_cell_once(tmp_path, setup):
    ins, model = setup
    cells = full_grid_cells()[:50]
    first = StandIn(fail_after=20)
    with pytest.raises(Interrupted):
        run_cells(first, cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    assert len(first.calls) == 20
    second = StandIn()
    run = run_cells(second, cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    assert run.resumed == 20
    assert second.calls == cells[20:]                      # nothing computed twice
    assert [(c.tan_eps, c.beta_deg) for c in run.results] == cells
    assert all(c.k_a == StandIn.value(c.tan_eps, c.beta_deg) for c in run.results)


class CheckpointingStandIn(StandIn):
    """A stand-in that declares pass checkpoints (KaBackend.checkpoints_passes) and records what it got."""

    checkpoints_passes = True

    def compute(self, cells, on_cell=None, checkpoint=None):
        self.checkpoint = checkpoint
        return super().compute(cells, on_cell)


def test_the_runner_hands_a_pass_checkpoint_only_to_a_backend_that_declares_it(tmp_path, setup):
    """A backend that says checkpoints_passes gets a PassCheckpoint in the run's folder (and the file
    is gone after a finished run); one that does not is called without the keyword (StandIn.compute
    would raise TypeError on it); no folder, no checkpoint."""
    from roadgonio.engines.runner import PassCheckpoint
    ins, model = setup
    cells = full_grid_cells()[:4]
    b = CheckpointingStandIn()
    run_cells(b, cells, instrument=ins, model=model, out_dir=tmp_path / "a", progress=False)
    assert isinstance(b.checkpoint, PassCheckpoint)
    assert b.checkpoint.path.parent == tmp_path / "a" and not b.checkpoint.path.exists()
    plain = StandIn()
    run = run_cells(plain, cells, instrument=ins, model=model, out_dir=tmp_path / "b", progress=False)
    assert len(run.results) == 4
    c = CheckpointingStandIn()
    run_cells(c, cells, instrument=ins, model=model, out_dir=None, progress=False)
    assert c.checkpoint is None


class PassesStandIn(StandIn):
    """A batched stand-in as the Mitsuba backend behaves with a checkpoint: half the cells finish in
    pass 1, whose state (the other half) is saved; pass 2 finishes the rest and saves a state of no
    cells. A saved state of exactly its cells is carried on (``reused``). ``stop`` stops it right
    after pass 1's state is saved; ``on_disk`` is what the folder held at that moment, where a
    second Ctrl-C (os._exit, no cleanup) would leave it."""

    checkpoints_passes = True

    def __init__(self, stop=False):
        super().__init__()
        self.stop = stop

    def _cell(self, t, b, on_cell):
        c = CellResult(t, b, self.value(t, b), 1e-4, 1000, 0.001)
        self.calls.append((t, b))
        on_cell(c)
        return c

    def compute(self, cells, on_cell=None, checkpoint=None):
        self.kept = [checkpoint.kept()]
        state = checkpoint.load()
        if state is not None and [tuple(c) for c in state["cells"]] == list(cells):
            checkpoint.reused(len(cells), state["pass"])
            self.kept.append(checkpoint.kept())
            rest = list(cells)
            out = []
        else:
            half = len(cells) // 2
            out = [self._cell(t, b, on_cell) for t, b in cells[:half]]
            rest = list(cells[half:])
            checkpoint.save({"pass": 1, "cells": [list(c) for c in rest]})
            self.on_disk = ((checkpoint.path.parent / JOURNAL).read_text().splitlines()[1:],
                            checkpoint.load())
            self.kept.append(checkpoint.kept())
            if self.stop:
                raise Interrupted()
        out += [self._cell(t, b, on_cell) for t, b in rest]
        checkpoint.save({"pass": 2, "cells": []})
        self.state_after_last = checkpoint.path.exists()
        return out


def test_a_pass_state_is_saved_with_the_journal_of_the_cells_it_leaves_out(tmp_path, setup):
    """A second Ctrl-C stops a Mitsuba table at once (os._exit: no cleanup, roadgonio.interrupts), so
    the folder must be whole at every pass boundary: the runner's checkpoint writes the journal of
    the cells finished so far before the state of the others (the journal alone was written at most
    once a second, the rest of a pass's cells when the run ended, so the state of the others did
    not match the cells left to compute and was thrown away). The resumed run carries the state on
    and says how many cells it continued (trial 12: "(N resumed)" counted finished cells only); the
    state of no cells after the last pass removes the file."""
    from roadgonio.cli.ka import _resumed_text
    from roadgonio.engines.runner import summary
    ins, model = setup
    cells = full_grid_cells()[:10]
    first = PassesStandIn(stop=True)
    with pytest.raises(Interrupted):
        run_cells(first, cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    journal, state = first.on_disk
    assert [tuple(json.loads(line)[k] for k in ("tan_eps", "beta_deg")) for line in journal] == cells[:5]
    assert state["pass"] == 1 and [tuple(c) for c in state["cells"]] == cells[5:]
    # the line of a second Ctrl-C says what is on disk at that moment
    assert first.kept == [f"kept: the finished cells ({tmp_path / JOURNAL}); the other cells had no completed pass; run "
                          "the same command again to resume",
                          f"kept: the finished cells ({tmp_path / JOURNAL}) and the other cells' state after pass 1 "
                          "(ka_passes.json); run the same command again to resume"]
    again = PassesStandIn()
    run = run_cells(again, cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    assert again.calls == cells[5:] and not again.state_after_last
    assert again.kept[1] == first.kept[1]           # carried on: the state on disk is still pass 1's
    assert (run.resumed, run.resumed_pass_cells, run.resumed_from_pass) == (5, 5, 1)
    s = summary(ka_dataset(run, instrument=ins, model=model, backend=again, sample="s"))
    assert (s["resumed_cells"], s["resumed_pass_cells"], s["resumed_from_pass"]) == (5, 5, 1)
    assert _resumed_text(s) == "5 resumed, 5 continued after their pass 1"
    fresh = PassesStandIn()
    run = run_cells(fresh, cells, instrument=ins, model=model, out_dir=tmp_path / "b", progress=False)
    s = summary(ka_dataset(run, instrument=ins, model=model, backend=fresh, sample="s"))
    assert (run.resumed_pass_cells, run.resumed_from_pass) == (0, None) and "resumed_from_pass" not in s
    assert _resumed_text(s) == "0 resumed" and not fresh.state_after_last


def test_correct_says_how_many_k_a_cells_continued_from_their_pass_state(tmp_path, setup):
    """correct's k_A tables go through the same runner: each step's backend info counts the cells
    carried on from a saved pass state beside those read back, and the terminal's "resumed:" line
    says both (trial 12: the cells of the interrupted passes were kept, and nothing said so)."""
    from roadgonio.cli.correct import _resumed, _resumed_line
    from roadgonio.correction.run import _backend_k
    ins, model = setup
    cells = full_grid_cells()[:10]
    with pytest.raises(Interrupted):
        _backend_k(lambda i, m: PassesStandIn(stop=True), ins, model, cells, tmp_path, progress=False)
    _, _, info, _ = _backend_k(lambda i, m: PassesStandIn(), ins, model, cells, tmp_path, progress=False)
    assert (info["resumed_cells"], info["resumed_pass_cells"]) == (5, 5)
    _, _, done, _ = _backend_k(lambda i, m: PassesStandIn(), ins, model, cells, tmp_path, progress=False)
    assert (done["resumed_cells"], done["resumed_pass_cells"]) == (10, 0)
    steps = [info, done]
    assert _resumed_line(_resumed(steps), 1, _resumed(steps, "resumed_pass_cells")) == (
        "  resumed: 15 k_A cells and 1 correction surface from the output folder's journals; 5 k_A cells "
        "continued after their last completed pass")
    assert _resumed_line(0, 0, 1) == "  resumed: 1 k_A cell continued after its last completed pass"
    # correct --json counts both from the same steps (one list: a generator built once and summed
    # twice would give 0 continued cells the second time)
    from collections import defaultdict
    from types import SimpleNamespace
    from roadgonio.cli.correct import _json_summary
    res = SimpleNamespace(summary=lambda: defaultdict(float, steps=[{"backend": info}, {"backend": done}]), out=tmp_path)
    got = _json_summary(res)
    assert (got["resumed_cells"], got["resumed_pass_cells"], got["resumed_surfaces"]) == (15, 5, 0)
    assert _resumed_line(0, 0, 0) is None


def test_cut_short_last_line_is_recomputed(tmp_path, setup):
    ins, model = setup
    cells = full_grid_cells()[:5]
    run_cells(StandIn(), cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    j = tmp_path / JOURNAL
    text = j.read_text()
    j.write_text(text[: len(text) - 15])                   # the last line cut mid-way
    again = StandIn()
    run = run_cells(again, cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    assert again.calls == [cells[-1]] and len(run.results) == 5


def test_journal_of_another_run_is_refused(tmp_path, setup):
    ins, model = setup
    cells = full_grid_cells()[:3]
    run_cells(StandIn(tag=0), cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    with pytest.raises(InputError, match="different run"):
        run_cells(StandIn(tag=1), cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    other_model = RoadModel(RoadParams(k_diff=0.06))
    with pytest.raises(InputError, match="different run"):
        run_cells(StandIn(tag=0), cells, instrument=ins, model=other_model, out_dir=tmp_path, progress=False)
    fresh = StandIn(tag=1)
    run_cells(fresh, cells, instrument=ins, model=model, out_dir=tmp_path, fresh=True, progress=False)
    assert fresh.calls == cells


def test_outputs_layout_and_provenance(tmp_path, setup):
    ins, model = setup
    cells = [c for c in full_grid_cells() if c[0] <= 1.0]
    backend = StandIn()
    run = run_cells(backend, cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    ds = ka_dataset(run, instrument=ins, model=model, backend=backend, sample="test")
    meta = write_outputs(ds, tmp_path)
    ka = read_table(tmp_path / "ka.csv")
    se = read_table(tmp_path / "ka_se.csv")
    # the CSV reader scales by 1e-4 (r x 1e4 layout); k_A files are written unscaled
    got = ka.r * 1e4
    rows = ka.tan_eps <= 1.0
    expect = StandIn.value(ka.tan_eps[:, None], ka.beta_deg[None, :])
    assert np.allclose(got[rows], expect[rows], rtol=1e-6)
    assert np.all(np.isnan(got[~rows]))                    # not computed -> blank, never zero
    assert np.allclose(se.r[rows] * 1e4, 1e-4)
    saved = json.loads((tmp_path / "ka.json").read_text())
    assert saved["backend"] == "stand-in" and saved["settings"] == {"tag": 0}
    assert saved["instrument"]["source"]["radius_m"] == ins.source.radius_m
    assert saved["model"]["params"]["n_phong"] == 200
    assert saved["summary"]["cells"] == len(cells)
    assert (tmp_path / "ka.png").stat().st_size > 10_000
    assert {"roadgonio", "mitsuba", "drjit", "numpy", "scipy"} <= set(meta["versions"])
    # ka.nc is the Dataset the CSVs were written from: the same numbers, units and meanings
    from roadgonio.fileio import read_netcdf
    nc = read_netcdf(tmp_path / "ka.nc", booleans=("converged",))
    assert np.array_equal(nc.k_a.values, ds.k_a.values, equal_nan=True)
    assert nc.k_a.attrs["units"] == "1" and "standard error" in nc.se.attrs["long_name"]
    assert nc.attrs["Conventions"] == "CF-1.8" and json.loads(nc.attrs["provenance"])["backend"] == "stand-in"
    assert nc.attrs["fingerprint"] == meta["fingerprint"] and "cell_correlation" in nc.attrs
    assert int(nc.converged.sum()) == len(cells)


def test_journal_is_written_in_batches_and_stays_complete(tmp_path, setup, monkeypatch):
    """Cells reported in quick succession are journalled by a few atomic rewrites, not one fsync per
    cell; an interruption still leaves every reported cell in a journal that parses completely."""
    import roadgonio.engines.runner as runner
    ins, model = setup
    writes = []
    real = runner._write_journal
    monkeypatch.setattr(runner, "_write_journal", lambda j, h, c: (writes.append(len(c)), real(j, h, c)))
    monkeypatch.setattr(runner, "FLUSH_SECONDS", 3600.0)
    cells = full_grid_cells()[:60]
    with pytest.raises(Interrupted):
        run_cells(StandIn(fail_after=45), cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    assert writes == [0, 45]                                # the header, then once when interrupted
    lines = (tmp_path / JOURNAL).read_text().splitlines()
    assert len(lines) == 46 and all(json.loads(line) for line in lines)
    monkeypatch.setattr(runner, "FLUSH_SECONDS", 0.0)       # every report flushes: the journal grows
    writes.clear()
    run = run_cells(StandIn(), cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    assert run.resumed == 45 and writes[0] == 45 and writes[-1] == 60


def test_finished_run_is_never_overwritten_by_another_even_without_its_journal(tmp_path, setup, monkeypatch):
    ins, model = setup
    cells = full_grid_cells()[:4]
    b = StandIn(tag=0)
    run = run_cells(b, cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    meta = write_outputs(ka_dataset(run, instrument=ins, model=model, backend=b, sample="test"), tmp_path, plot=False)
    assert len(meta["fingerprint"]) == 16
    (tmp_path / JOURNAL).unlink()
    with pytest.raises(InputError, match="different run"):
        run_cells(StandIn(tag=1), cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    # the same run again (journal gone): allowed, recomputed
    again = StandIn(tag=0)
    run_cells(again, cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    assert again.calls == cells
    # another roadgonio version is another run
    from roadgonio import _version
    monkeypatch.setattr(_version, "__version__", _version.__version__ + ".dev-other")
    (tmp_path / JOURNAL).unlink()
    with pytest.raises(InputError, match="different run"):
        run_cells(StandIn(tag=0), cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    fresh = StandIn(tag=0)
    run_cells(fresh, cells, instrument=ins, model=model, out_dir=tmp_path, fresh=True, progress=False)
    assert fresh.calls == cells and not (tmp_path / "ka.json").exists()


def test_a_subset_run_keeps_the_folders_whole_table(tmp_path, setup):
    """Trial 7, defect 9: asking a few cells of a folder that holds a larger table of the same run
    read them back and rewrote ka.csv/ka.nc with those cells only. The cells asked are the run's
    ``results``; the table files (and the Dataset) keep every cell the journal holds."""
    from roadgonio.engines.runner import summary
    ins, model = setup
    cells = full_grid_cells()[:30]
    run_cells(StandIn(), cells, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    subset = [cells[3], cells[7]]
    again = StandIn()
    run = run_cells(again, subset, instrument=ins, model=model, out_dir=tmp_path, progress=False)
    assert again.calls == [] and run.resumed == 2
    assert [(c.tan_eps, c.beta_deg) for c in run.results] == subset
    ds = ka_dataset(run, instrument=ins, model=model, backend=again, sample="test", cells_asked=len(subset))
    write_outputs(ds, tmp_path, plot=False)
    ka = read_table(tmp_path / "ka.csv").r * 1e4
    assert int(np.isfinite(ka).sum()) == len(cells)
    for t, b in cells:
        i, j = list(TAN_EPS_GRID).index(t), list(BETA_GRID_DEG).index(b)
        assert ka[i, j] == pytest.approx(StandIn.value(t, b), rel=1e-6)
    s = summary(ds)
    assert (s["cells"], s["cells_asked"], s["resumed_cells"]) == (len(cells), 2, 2)
    assert json.loads((tmp_path / "ka.json").read_text())["summary"]["cells"] == len(cells)



def test_cells_without_a_standard_error_are_counted_not_hidden(tmp_path, setup):
    """A Monte Carlo cell whose light too few samples carried has no SE (inf, session 34): the table's
    worst rel. SE is that of the others, its line counts the cells without one (before, a single inf
    dropped the worst rel. SE and the NOT converged count from the line: "k_A from 1.000 to 1.004, ;"),
    ka_se.csv leaves them blank, and a table with no SE at all says so."""
    from roadgonio.engines.runner import precision_text, summary
    ins, model = setup

    class Sparse(StandIn):
        def compute(self, cells, on_cell=None):
            out = []
            for t, b in cells:
                dark = t >= 0.75
                c = CellResult(t, b, self.value(t, b), math.inf if dark else 2e-4 * (1 + t), 1000, 0.001,
                               converged=not dark)
                out.append(c)
                if on_cell:
                    on_cell(c)
            return out

    cells = [c for c in full_grid_cells() if c[0] <= 1.0]
    b = Sparse()
    run = run_cells(b, cells, instrument=ins, model=model, progress=False)
    s = summary(ka_dataset(run, instrument=ins, model=model, backend=b, sample="s"))
    dark = sum(t >= 0.75 for t, _ in cells)
    lit = [c for c in cells if c[0] < 0.75]
    assert s["cells_without_se"] == dark and s["not_converged"] == dark
    assert s["worst_rel_se"] == pytest.approx(max(2e-4 * (1 + t) / StandIn.value(t, b_) for t, b_ in lit), rel=1e-12)
    text = precision_text(s)
    assert text == f"worst rel. SE {s['worst_rel_se']:.1e} ({dark} cells without one), {dark} cells NOT converged"
    write_outputs(ka_dataset(run, instrument=ins, model=model, backend=b, sample="s"), tmp_path, plot=False)
    se = read_table(tmp_path / "ka_se.csv")
    rows = (se.tan_eps >= 0.75) & (se.tan_eps <= 1.0)
    assert np.all(~np.isfinite(se.r[rows])) and np.all(np.isfinite(se.r[se.tan_eps < 0.75]))
    none = precision_text({"cells_without_se": 3, "not_converged": 3})
    assert none == "no standard error in any of its 3 cells, 3 cells NOT converged"
