"""Bad inputs and faults (issue 10's probe classes): each gets a clear one-line error naming the
file, the field and what was expected (exit 2), or a correct result - never a traceback, a NaN
or a silently wrong number. Each test failed on the code before issues 8 and 10."""
from __future__ import annotations

import errno
import json
import math

import numpy as np
import pytest

from roadgonio.cli import main
from helpers import GOOD_INSTRUMENT


def one_line_error(capsys, rc, *must):
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("roadgonio: error:"), err
    for m in must:
        assert m in lines[0], (m, lines[0])
    return lines[0]


@pytest.fixture
def r3_file(tmp_path, r3like):
    p = tmp_path / "r3like.json"
    r3like.save(p)
    return p


def write_instrument(tmp_path, text, name="inst.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


GOOD = GOOD_INSTRUMENT


# -- instrument files ------------------------------------------------------------------------------

def test_misspelt_section_is_an_error(tmp_path, capsys):
    p = write_instrument(tmp_path, GOOD.replace("[observation]", "[observaton]"))
    rc = main(["ka", "--instrument", str(p), "--sample", "lambert", "--backend", "quadrature", "--tan-eps", "1",
               "--beta", "0"])
    one_line_error(capsys, rc, "observaton")


def test_unknown_key_in_any_section_is_an_error(tmp_path, capsys):
    p = write_instrument(tmp_path, "[instrument]\nnmae = \"x\"\n" + GOOD)
    rc = main(["ka", "--instrument", str(p), "--sample", "lambert", "--backend", "quadrature", "--tan-eps", "1",
               "--beta", "0"])
    one_line_error(capsys, rc, "nmae")


def test_conflicting_mesh_and_size_is_an_error(tmp_path, capsys):
    (tmp_path / "m.ply").write_text("ply\n")
    p = write_instrument(tmp_path, GOOD.replace("size_y_m = 0.5", "size_y_m = 0.5\nmesh = \"m.ply\""))
    rc = main(["ka", "--instrument", str(p), "--sample", "lambert", "--backend", "quadrature", "--tan-eps", "1",
               "--beta", "0"])
    one_line_error(capsys, rc, "mesh")


def test_denormal_radius_is_an_error_or_a_point(tmp_path, capsys, r3_file):
    p = write_instrument(tmp_path, GOOD.replace("radius_m = 0.005", "radius_m = 1e-300"))
    rc = main(["ka", "--instrument", str(p), "--sample", str(r3_file), "--backend", "numpy-mc", "--tan-eps",
               "1", "--beta", "0", "--json"])
    cap = capsys.readouterr()
    assert rc in (0, 2) and "Traceback" not in cap.err
    if rc == 0:
        assert math.isfinite(json.loads(cap.out)["k_a"])


# -- uncertainty SPECs against the geometry ------------------------------------------------------

@pytest.mark.parametrize("spec, key", [("alpha_deg=10", "alpha_deg"), ("source_distance_m=5", "source_distance_m"),
                                       ("tilt_y_deg=0.5", "tilt_y_deg"), ("detector_distance_m=3", "detector_distance_m")])
def test_spec_out_of_the_geometry_is_refused_up_front(tmp_path, capsys, spec, key):
    rc = main(["uncertainty", "--instrument", "lab", "--sample", "R3", "--sigma", spec, "--trials", "200",
               "--no-aperture", "--out", str(tmp_path / "u")])
    one_line_error(capsys, rc, key, "out of validity")
    assert not (tmp_path / "u").exists() or not any((tmp_path / "u").iterdir())


def test_no_nan_statistic(tmp_path, capsys):
    """A model with r(0, 0) = 0 (a narrow specular lobe only) makes S1 infinite in every trial: an
    error naming S1, not NaN statistics written with exit 0."""
    p = tmp_path / "spec.json"
    p.write_text(json.dumps({"variant": "power", "params": {"k_phong": 1.0, "n_phong": 2000.0}}))
    rc = main(["uncertainty", "--instrument", "lab", "--sample", str(p), "--sigma", "alpha_deg=0.01", "--trials",
               "200", "--no-aperture", "--out", str(tmp_path / "u")])
    one_line_error(capsys, rc, "S1", "not finite")


# -- degenerate models, absurd tables, seeds -------------------------------------------------------

@pytest.mark.parametrize("backend", ["numpy-mc", "quadrature", "reference"])
def test_all_zero_model_is_an_error_not_nan(tmp_path, capsys, backend):
    p = tmp_path / "zero.json"
    p.write_text(json.dumps({"variant": "power", "params": {}}))
    rc = main(["ka", "--instrument", "lab", "--sample", str(p), "--backend", backend, "--tan-eps", "2", "--beta",
               "0", "--json"])
    line = one_line_error(capsys, rc, "zero.json", "params", "reflects nothing")
    assert "nan" not in line.lower()


def test_table_with_an_absurd_value_is_an_error(tmp_path, capsys):
    from roadgonio.surface.rtable import load_table
    text = load_table("R3").to_csv_text()
    lines = text.splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("1,") or ln.startswith("1.0,"))
    cells = lines[k].split(",")
    cells[3] = "1e300"
    lines[k] = ",".join(cells)
    p = tmp_path / "bad.csv"
    p.write_text("\n".join(lines) + "\n")
    rc = main(["fit", str(p), "--out", str(tmp_path / "f")])
    one_line_error(capsys, rc, "bad.csv", "1e300", "plausible")


@pytest.mark.parametrize("argv", [
    ["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "numpy-mc", "--tan-eps", "1", "--beta", "0"],
    ["uncertainty", "--instrument", "lab", "--sample", "lambert", "--sigma", "alpha_deg=0.01", "--no-aperture"],
    ["fit", "R3"],
    ["validate", "--instrument", "lab", "--sample", "lambert", "--against", "numpy-mc"],
])
def test_negative_seed_is_an_error(tmp_path, capsys, argv):
    rc = main(argv + ["--seed", "-1", "--out", str(tmp_path / "o")])
    one_line_error(capsys, rc, "--seed", ">= 0")


# -- outputs: one line, exit 2, all or nothing -------------------------------------------------

def _validate_argv(model, out):
    return ["validate", "--instrument", "lab", "--sample", str(model), "--against", "numpy-mc", "--cells", "2:90",
            "--rel-se", "1e-2", "--out", str(out)]


def test_output_under_a_file_is_one_line(tmp_path, capsys, r3_file):
    f = tmp_path / "plain.txt"
    f.write_text("x")
    rc = main(_validate_argv(r3_file, f / "sub"))
    one_line_error(capsys, rc, "plain.txt/sub", "field 'out'", f"expected a folder for the results, but {f} is a file")


#: One cheap call of every command that takes --out (the check comes before any work).
OUT_COMMANDS = {
    "fit": ["fit", "R3"],
    "ka": ["ka", "--instrument", "portable", "--sample", "R3", "--backend", "quadrature", "--accuracy", "fast"],
    "render": ["render", "--instrument", "portable", "--sample", "R3", "--tan-eps", "1", "--beta", "0"],
    "validate": ["validate", "--instrument", "portable", "--sample", "R3"],
    "uncertainty": ["uncertainty", "--instrument", "portable", "--sample", "R3", "--sigma", "alpha_deg=0.01"],
    "correct": ["correct", "--measured", "R3", "--instrument", "portable"],
    "road": ["road", "--table", "R3"],
    "compare": ["compare", "R3", "R2"],
    "design": ["design", "--instrument", "portable", "--vary", "source.radius_m=0.01:0.02:2", "--sample", "R3"],
    "intercompare": ["intercompare", "r3-comparison"],
}


def test_every_command_with_an_out_folder_is_in_the_list():
    from roadgonio.cli import build_parser
    sub = next(a for a in build_parser()._actions if hasattr(a, "choices") and isinstance(a.choices, dict))
    takes_out = {name for name, p in sub.choices.items() if any("--out" in a.option_strings for a in p._actions)}
    assert takes_out == set(OUT_COMMANDS)


@pytest.mark.parametrize("argv", [OUT_COMMANDS[k] for k in sorted(OUT_COMMANDS)] +
                         [OUT_COMMANDS["ka"] + ["--tan-eps", "1", "--beta", "0"]], ids=lambda a: " ".join(a[:2]))
def test_out_that_is_a_file_says_a_folder_was_expected(tmp_path, capsys, monkeypatch, argv):
    """Trial 11 D10: every command but fit said "cannot write this output file (File exists)" about
    the file or about a file inside it; one check (api._out) now says a folder was expected, as fit
    did, and nothing is written."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("hi")
    rc = main(argv + ["--out", "afile"])
    one_line_error(capsys, rc, "afile, field 'out': expected a folder for the results, but it is a file")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"] and (tmp_path / "afile").read_text() == "hi"


def test_table_to_a_file_under_a_file_or_to_nothing_says_what_is_wrong(tmp_path, capsys, monkeypatch):
    """(user audit, session 44) `table R3 --to afile/x.csv` said "cannot write this output file (File
    exists)" where afile is a file; `--to ""` named the file "."."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("hi")
    rc = main(["table", "R3", "--to", "afile/sub/x.csv"])
    one_line_error(capsys, rc, "afile/sub/x.csv: cannot write this output file: afile is a file, not a folder")
    rc = main(["table", "R3", "--to", ""])
    one_line_error(capsys, rc, "field '--to': expected the path of a .csv or .rtb file to write the table to, got an "
                               "empty text")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"] and (tmp_path / "afile").read_text() == "hi"


def test_output_in_proc_is_one_line(capsys, r3_file):
    rc = main(_validate_argv(r3_file, "/proc/roadgonio-no-such-dir"))
    one_line_error(capsys, rc, "/proc/roadgonio-no-such-dir", "cannot write")


def test_full_disk_leaves_no_partial_outputs(tmp_path, capsys, monkeypatch, r3_file):
    """The disk fills while the JSON is written (after the CSV): one line naming validate.json, exit 2,
    and none of the three outputs appears (before: a traceback and a partial set)."""
    import roadgonio.fileio as F
    real = F.OutputGroup.json

    def full(self, name, obj):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.path(name)))
    monkeypatch.setattr(F.OutputGroup, "json", full)
    out = tmp_path / "v"
    rc = main(_validate_argv(r3_file, out))
    one_line_error(capsys, rc, "validate.json", "No space left")
    assert not out.exists() or sorted(p.name for p in out.iterdir()) == []
    monkeypatch.setattr(F.OutputGroup, "json", real)


@pytest.mark.parametrize("failing", ["table_map", "json"])
def test_ka_table_outputs_appear_together_or_not_at_all(tmp_path, capsys, monkeypatch, failing):
    """ka writes ka.nc, ka.csv, ka_se.csv, ka.json and ka.png as one group: the disk fills while the map
    (the last file) or the JSON is written, and none of them appears; the journal keeps the cells,
    so the same command afterwards resumes them and writes the whole set."""
    import roadgonio.fileio as F
    import roadgonio.plots as P
    import roadgonio.plotproc as PP
    monkeypatch.setattr(PP, "FigureProcess", lambda enabled=True: _NoChild())   # draw in this process

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")
    if failing == "table_map":
        monkeypatch.setattr(P, "table_map", full)
    else:
        monkeypatch.setattr(F.OutputGroup, "json", full)
    out = tmp_path / "t"
    argv = ["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "quadrature", "--cells", "1:0,2:0",
            "--out", str(out)]
    rc = main(argv)
    one_line_error(capsys, rc, "No space left")
    assert not (out / "ka.csv").exists() and not (out / "ka.json").exists() and not (out / "ka_bound.csv").exists()
    assert not (out / "ka.nc").exists()
    assert not [q for q in out.iterdir() if q.name.startswith(".")]      # no staging folder left behind
    monkeypatch.undo()
    monkeypatch.setattr(PP, "FigureProcess", lambda enabled=True: _NoChild())
    assert main(argv + ["--json"]) == 0
    assert json.loads(capsys.readouterr().out)["resumed_cells"] == 2
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "ka.csv", "ka.json", "ka.nc", "ka.png", "ka_bound.csv", "ka_cells.jsonl"]


class _NoChild:
    """FigureProcess stand-in: draws in this process (so a monkeypatched roadgonio.plots applies)."""
    fallbacks = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def call(self, name, *args, **kwargs):
        import roadgonio.plots as P
        return getattr(P, name)(*args, **kwargs)


# -- interruptions say what they keep ---------------------------------------------------------

@pytest.mark.parametrize("argv, target, must", [
    (["uncertainty", "--instrument", "lab", "--sample", "lambert", "--sigma", "alpha_deg=0.01", "--no-aperture"],
     "roadgonio.uncertainty.run.run_uncertainty", "starts over"),
    (["fit", "R3"], "roadgonio.surface.fit.fit_table", "starts over"),
    (["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "numpy-mc"],
     "roadgonio.engines.runner.run_cells", "resume"),
])
def test_ctrl_c_says_truthfully_what_happens(tmp_path, capsys, monkeypatch, argv, target, must):
    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(target, interrupted)
    rc = main(argv + ["--out", str(tmp_path / "o" / "deeper")])
    err = capsys.readouterr().err
    assert rc == 130 and must in err
    if must == "starts over":       # nothing was written: not even the folders (trial 11 D11)
        assert "run the same command again to resume" not in err
        assert list(tmp_path.iterdir()) == []


# -- messages that name the real cause and the cell ---------------------------------------------

def test_unreachable_rel_se_says_so(tmp_path, capsys, monkeypatch):
    import roadgonio.engines.montecarlo as MC
    real = MC.make_backend
    monkeypatch.setattr(MC, "make_backend", lambda *a, **k: real(*a, **{**k, "max_samples": 1 << 16}))
    rc = main(["ka", "--instrument", "lab", "--sample", "R3", "--backend", "numpy-mc", "--tan-eps", "12", "--beta",
               "0", "--rel-se", "1e-7"])
    out = capsys.readouterr().out
    assert rc == 0 and "NOT converged" in out and "relative SE" in out and "target 1e-07" in out
    rc = main(["ka", "--instrument", "lab", "--sample", "R3", "--backend", "numpy-mc", "--tan-eps", "12", "--beta",
               "0", "--rel-se", "1e-7", "--json"])
    d = json.loads(capsys.readouterr().out)
    assert d["converged"] is False and d["se"] > 1e-7 * d["k_a"]


def test_a_quadrature_cell_at_its_cap_calls_its_error_an_estimate_not_a_bound(capsys, monkeypatch):
    """A quadrature cell stopped at max_evals has the change of its last levels, which can understate
    the error (wide preset, 6:0 at rtol 1e-6: 0.0100 reported, 0.0177 true; audit, session 24): the
    line, the note and the docs say estimate, not bound; a converged cell keeps "error bound"."""
    import roadgonio.engines.quadrature as Q
    real = Q.make_backend
    monkeypatch.setattr(Q, "make_backend", lambda *a, **k: real(*a, **{**k, "max_evals": 5000}))
    argv = ["ka", "--instrument", "portable", "--sample", "R3", "--backend", "quadrature", "--tan-eps", "12",
            "--beta", "0", "--rel-se", "1e-6"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "NOT converged" in out and "error estimate, not a bound" in out and "error bound" not in out, out
    monkeypatch.setattr(Q, "make_backend", real)
    assert main(argv[:-2] + ["--accuracy", "fast"]) == 0
    out = capsys.readouterr().out
    assert "(error bound" in out and "NOT converged" not in out, out


def test_source_in_the_line_of_sight_names_the_cell(tmp_path, capsys):
    p = write_instrument(tmp_path, GOOD.replace("distance_m = 5.0\nradius_m = 0.005",
                                                "distance_m = 1.0\nradius_m = 0.08"))
    rc = main(["ka", "--instrument", str(p), "--sample", "R3", "--backend", "numpy-mc", "--tan-eps", "12", "--beta",
               "180"])
    line = one_line_error(capsys, rc, "blocks the detector's line of sight", "tan eps = 12, beta = 180")
    assert "enlarge" not in line


def test_cuda_variant_without_gpu_says_gpu(capsys):
    rc = main(["ka", "--instrument", "lab", "--sample", "lambert", "--variant", "cuda_ad_rgb", "--tan-eps", "1",
               "--beta", "0"])
    line = one_line_error(capsys, rc, "GPU")
    assert "libLLVM" not in line


def test_single_cell_json_carries_converged(capsys):
    rc = main(["ka", "--instrument", "lab", "--sample", "R3", "--backend", "reference", "--tan-eps", "2", "--beta",
               "5", "--json"])
    d = json.loads(capsys.readouterr().out)
    # one meaning per field: the RQMC reference gives an SE and a confidence bound, no deterministic bound
    assert rc == 0 and d["converged"] is True and d["se"] > 0 and d["error_bound"] is None
    assert d["confidence_bound"] > d["se"]


def test_source_in_the_line_of_sight_names_the_cell_in_the_renderer(mi, tmp_path, capsys):
    """Before: 'rays do not hit the sample ... enlarge the sample', mid-table and without the cell."""
    p = write_instrument(tmp_path, GOOD.replace("distance_m = 5.0\nradius_m = 0.005",
                                                "distance_m = 1.0\nradius_m = 0.08"))
    rc = main(["ka", "--instrument", str(p), "--sample", "lambert", "--backend", "mitsuba", "--tan-eps", "12",
               "--beta", "180", "--rel-se", "1e-2"])
    line = one_line_error(capsys, rc, "line of sight", "tan eps = 12, beta = 180")
    assert "enlarge" not in line


# -- correct: its outputs together or not at all; its journals fail in one line -----------------

#: Every file ``correct`` writes per folder with pictures (journals and fit_state.json aside).
CORRECT_OUTPUTS = ["before_after.png", "correct.json", "correct_cells.csv", "corrected.csv", "corrected.rtb",
                   "corrected_corr.csv", "corrected_u.csv", "correction_map.png"]


def _small_measured(tmp_path):
    """The synthetic medium-instrument measurement (tests/data) cut to beta 0 and 2, every third
    tan eps (22 cells with the S1 cells): a correction through the instrument in a few seconds."""
    from pathlib import Path

    from roadgonio.surface.rtable import read_table
    data = Path(__file__).resolve().parents[1] / "data"
    meas = read_table(data / "synthetic_medium_lambert.csv")
    keep = meas.r.copy()
    keep[:, 2:] = np.nan
    keep[[i for i in range(keep.shape[0]) if i % 3 and i != 8], :] = np.nan
    return meas.with_values(keep, name="small").write_csv(tmp_path / "small.csv"), data / "medium.toml"


def _correct_argv(tmp_path, out, *extra):
    f, inst = _small_measured(tmp_path)
    return ["correct", "--measured", str(f), "--instrument", str(inst), "--backend", "quadrature", "--accuracy",
            "fast", "--rays", "64", "--model-variant", "power", "--out", str(out), *extra]


@pytest.mark.parametrize("failing", ["json", "figure"])
def test_correct_outputs_appear_together_or_not_at_all(tmp_path, capsys, monkeypatch, failing):
    """The disk fills while correct.json (the last file of the group) or before_after.png is
    written: one line naming that file, exit 2, none of the eight outputs appears, no staging
    folder is left; the journal and the fit checkpoint survive, so the same command afterwards
    resumes every k_A cell and writes the whole set (before: the CSVs and the RTB stayed)."""
    import roadgonio.fileio as F

    def full(self, name, *args):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.path(name)))
    monkeypatch.setattr(F.OutputGroup, failing, full)
    out = tmp_path / "o"
    argv = _correct_argv(tmp_path, out)
    one_line_error(capsys, main(argv), "correct.json" if failing == "json" else "before_after.png", "No space left")
    left = sorted(p.name for p in out.iterdir())
    assert not set(left) & set(CORRECT_OUTPUTS) and not [n for n in left if n.startswith(".")], left
    assert (out / "forward-1" / "ka_cells.jsonl").exists() and (out / "fit_state.json").exists()
    if failing == "figure":
        return
    monkeypatch.undo()
    capsys.readouterr()
    assert main(argv) == 0
    assert set(CORRECT_OUTPUTS) <= {p.name for p in out.iterdir()}
    doc = json.loads((out / "correct.json").read_text())
    n = doc["summary"]["cells"]
    assert [s["backend"]["resumed_cells"] for s in doc["summary"]["steps"]][0] == n     # the journal was kept
    said = capsys.readouterr()
    total = sum(s["backend"]["resumed_cells"] for s in doc["summary"]["steps"])
    assert f"resumed: {total} k_A cells" in said.out + said.err                     # and the terminal says so


def _read_only(monkeypatch, folder):
    """Make ``folder`` behave like a read-only file system, even for root: creating, replacing,
    removing or opening for writing anything inside raises EROFS (reading still works)."""
    import builtins
    import io
    import os
    root = os.path.abspath(folder)

    def inside(p) -> bool:
        try:
            return os.path.abspath(os.fspath(p)).startswith(root)
        except TypeError:
            return False

    def ro(p):
        return OSError(errno.EROFS, "Read-only file system", os.fspath(p))
    real_open, real_io_open = os.open, io.open

    def os_open(path, flags, *a, **k):
        if inside(path) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise ro(path)
        return real_open(path, flags, *a, **k)

    def one(name):
        real = getattr(os, name)

        def f(path, *a, **k):
            if inside(path):
                if name == "mkdir" and os.path.isdir(path):
                    raise FileExistsError(errno.EEXIST, "File exists", os.fspath(path))
                raise ro(path)
            return real(path, *a, **k)
        return f

    def two(name):
        real = getattr(os, name)

        def f(src, dst, *a, **k):
            if inside(src) or inside(dst):
                raise ro(dst)
            return real(src, dst, *a, **k)
        return f

    def io_open(file, mode="r", *a, **k):
        if isinstance(file, (str, bytes, os.PathLike)) and inside(file) and any(c in mode for c in "wax+"):
            raise ro(file)
        return real_io_open(file, mode, *a, **k)
    monkeypatch.setattr(os, "open", os_open)
    for n in ("mkdir", "unlink", "remove", "rmdir"):
        monkeypatch.setattr(os, n, one(n))
    for n in ("replace", "rename"):
        monkeypatch.setattr(os, n, two(n))
    monkeypatch.setattr(io, "open", io_open)
    monkeypatch.setattr(builtins, "open", io_open)


@pytest.mark.parametrize("case", ["correct-reference", "correct-self", "correct-resume", "ka-fresh"])
def test_read_only_journal_is_one_line(tmp_path, capsys, monkeypatch, case):
    """A journal on a read-only folder: the k_A journal of correct's classic route (before: a
    traceback from making forward-1/), the fit checkpoint of the default route, the journal of a
    resumed correction, and `ka --fresh` removing a journal (before: a traceback): one line naming
    the file, exit 2."""
    out = tmp_path / "o"
    ref = ["--reference", "lambert", "--alternatives", "none", "--no-plots"]
    if case == "ka-fresh":
        argv = ["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "quadrature", "--cells", "1:0,2:0",
                "--out", str(out)]
        assert main(argv) == 0
        argv.append("--fresh")
        must = str(out / "ka_cells.jsonl")
    elif case == "correct-self":
        argv = _correct_argv(tmp_path, out, "--no-plots")
        out.mkdir()
        must = str(out / "fit_state.json")
    else:
        argv = _correct_argv(tmp_path, out, *ref)
        if case == "correct-resume":
            assert main(argv) == 0
        else:
            out.mkdir()
        must = str(out / "forward-1" / "ka_cells.jsonl")
    capsys.readouterr()
    _read_only(monkeypatch, out)
    one_line_error(capsys, main(argv), must, "Read-only file system")


def test_unreadable_journal_is_one_line(tmp_path, capsys):
    """A journal that cannot be read (here: a folder where the file should be; before: a traceback)."""
    out = tmp_path / "o"
    (out / "ka_cells.jsonl").mkdir(parents=True)
    rc = main(["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "quadrature", "--cells", "1:0",
               "--out", str(out)])
    one_line_error(capsys, rc, str(out / "ka_cells.jsonl"), "cannot read this journal")


def test_ctrl_c_of_correct_says_it_resumes(tmp_path, capsys, monkeypatch):
    """correct keeps its k_A journals and fitted models (the full-disk test above resumes from
    them): Ctrl-C says so (before: 'nothing was written')."""
    import roadgonio.correction as C

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(C, "correct_files", interrupted)
    rc = main(_correct_argv(tmp_path, tmp_path / "o"))
    err = capsys.readouterr().err
    assert rc == 130 and "run the same command again to resume" in err and "nothing was written" not in err


def test_design_journal_on_a_read_only_folder_is_one_line(tmp_path, capsys, monkeypatch):
    """design's journal (design_points.jsonl) cannot be written: one line naming it, exit 2 (before:
    a traceback)."""
    out = tmp_path / "d"
    out.mkdir()
    _read_only(monkeypatch, out)
    rc = main(["design", "--instrument", "lab", "--sample", "lambert", "--vary", "source.radius_m=0.002,0.004",
               "--cells", "1:0", "--backend", "quadrature", "--workers", "0", "--no-plots", "--out", str(out)])
    one_line_error(capsys, rc, str(out / "design_points.jsonl"), "Read-only file system")


def test_design_outputs_appear_together_or_not_at_all(tmp_path, capsys, monkeypatch):
    """The disk fills while design's last picture is written: none of design.nc, design.csv,
    best.toml, pareto.png appears, one line names the file; the journal keeps the tables, so the
    same command afterwards resumes them and writes the whole set."""
    import roadgonio.design.outputs as O
    real = O.plot_pareto

    def full(ds, path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))
    monkeypatch.setattr(O, "plot_pareto", full)
    out = tmp_path / "d"
    argv = ["design", "--instrument", "lab", "--sample", "lambert", "--vary", "source.radius_m=0.002,0.004",
            "--cells", "1:0", "--backend", "quadrature", "--workers", "0", "--out", str(out)]
    one_line_error(capsys, main(argv), "pareto.png", "No space left")
    assert sorted(p.name for p in out.iterdir()) == ["design_points.jsonl"]
    monkeypatch.setattr(O, "plot_pareto", real)
    assert main(argv + ["--json"]) == 0
    assert json.loads(capsys.readouterr().out)["tables_resumed"] == 2
    assert {"design.nc", "design.csv", "best.toml", "pareto.png"} <= {p.name for p in out.iterdir()}


@pytest.mark.parametrize("instrument, vary, must", [
    ("portable_housed", "housing.baffles.1.height_m=0,0.01", "declares no baffles"),
    ("portable_housed", "housing.baffles.0.x_m=-0.5,-0.4", "declares no baffles"),
    ("portable", "housing.wall_reflectance=0.1,0.2", "has no [housing]"),
    # audit 28: accepted, every point the same instrument, the tables' noise read as a paint effect
    ("portable_housed", "housing.baffle_reflectance=0.1,0.5", "their reflectance changes nothing"),
])
@pytest.mark.parametrize("second", [False, True])
def test_design_key_the_base_cannot_take_is_an_input_error(tmp_path, capsys, instrument, vary, must, second):
    """A varied baffle the base does not declare, or a housing key of a base without [housing], is
    known before any computation: exit 2, one line naming the --vary key (before: exit 0 with every
    point infeasible, or a default housing added silently to best.toml)."""
    argv = ["design", "--instrument", instrument, "--sample", "R3", "--vary", vary, "--no-plots",
            "--out", str(tmp_path / "d")]
    rc = main(argv + (["--second-aperture"] if second else ["--workers", "0"]))
    if second:                       # the second aperture's ray bundles model no housing at all
        must = "does not model a housing"
    one_line_error(capsys, rc, "--vary", vary.split("=")[0], must)
    assert not (tmp_path / "d").exists()


def test_design_baffle_beyond_the_declared_ones_says_how_many(tmp_path):
    from roadgonio.design.grid import as_vary_specs, check_vary
    from roadgonio.errors import InputError
    from roadgonio.instrument.config import Instrument, load_instrument
    d = load_instrument("portable_housed").to_dict()
    d["housing"]["baffles"] = [{"x_m": -0.5, "height_m": 0.0}]
    base = Instrument.from_dict(d, path=tmp_path / "b.toml")
    check_vary(base, as_vary_specs(["housing.baffles.0.height_m=0,0.01"]))
    with pytest.raises(InputError, match=r"housing.baffles.1.height_m: .* declares 1 baffle\(s\) .*declare baffle 1"):
        check_vary(base, as_vary_specs(["housing.baffles.1.height_m=0,0.01"]))


def test_validate_of_a_housed_instrument_says_what_the_user_can_do(tmp_path, capsys):
    """No float64 reference models a [housing]: one line naming the file and the section, and advice
    the command can follow (before: 'use --backend mitsuba', an option validate does not have)."""
    rc = main(["validate", "--instrument", "portable_housed", "--sample", "lambert", "--out", str(tmp_path / "v")])
    line = one_line_error(capsys, rc, "portable_housed.toml", "field 'housing'", "without its [housing]",
                          "roadgonio ka --backend mitsuba")
    assert "use --backend" not in line


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), RuntimeError(
    '[parser.cpp:3350] failed to instantiate unknown plugin of type "lummeter": KeyboardInterrupt: <EMPTY MESSAGE>')])
def test_ctrl_c_of_design_says_what_is_kept_and_resumes(tmp_path, capsys, monkeypatch, exc):
    """Ctrl-C after one of three points: the message counts what the journal keeps and says a rerun
    resumes (before: 'nothing was written'); Mitsuba's RuntimeError wrapping the KeyboardInterrupt is
    the same interrupt (before: a traceback, exit 1). The rerun resumes the kept table."""
    import roadgonio.engines.cluster as CL
    real = CL.map_tables

    def partial(tasks, client, on_result=None, **k):
        real(tasks[:1], client, on_result=on_result, **k)
        raise exc
    monkeypatch.setattr(CL, "map_tables", partial)
    argv = ["design", "--instrument", "lab", "--sample", "lambert", "--vary", "source.radius_m=0.002,0.004,0.006",
            "--cells", "1:0", "--backend", "quadrature", "--workers", "0", "--no-plots", "--json",
            "--out", str(tmp_path / "d")]
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 130 and err.startswith("roadgonio: interrupted: 1 finished table (1 of 3 geometrically possible design points "
                                        "complete) is kept in") and "run the same command again to resume" in err
    assert "Traceback" not in err and "nothing was written" not in err
    monkeypatch.setattr(CL, "map_tables", real)
    assert main(argv) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["tables_resumed"] == 1 and s["tables_computed"] == 2


def test_a_runtime_error_that_is_no_interrupt_is_not_hidden(tmp_path, monkeypatch):
    def broken(*a, **k):
        raise RuntimeError("something else")
    monkeypatch.setattr("roadgonio.surface.fit.fit_table", broken)
    with pytest.raises(RuntimeError, match="something else"):
        main(["fit", "R3", "--out", str(tmp_path / "o")])


def test_mitsuba_wrapping_the_interrupt_is_the_interrupt(tmp_path, capsys, monkeypatch):
    def wrapped(*a, **k):
        raise RuntimeError('[parser.cpp:3350] failed to instantiate unknown plugin: KeyboardInterrupt')
    monkeypatch.setattr("roadgonio.surface.fit.fit_table", wrapped)
    rc = main(["fit", "R3", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 130 and err == "roadgonio: interrupted: no model was written (fit starts over when run again)\n"


@pytest.mark.parametrize("section, must", [
    ('[scene]\nxml = "DIR"\n', ("scene.xml", "is a directory; expected an XML scene file")),
    ('[calibration]\nmode = "reference"\nreference = "DIR"\n', ("calibration.reference", "is a directory")),
])
def test_a_directory_given_as_an_input_file_says_so(tmp_path, capsys, section, must):
    """A folder where a file is expected is named as a folder (the tester's report: a directory as the
    XML scene failed later with another message; a beam table said 'does not exist')."""
    from pathlib import Path
    d = tmp_path / "inputs.csv"
    d.mkdir()
    text = (Path(__file__).resolve().parents[2] / "scenes" / "portable.toml").read_text()
    inst = tmp_path / "inst.toml"
    inst.write_text(text + "\n" + section.replace("DIR", str(d)))
    rc = main(["ka", "--instrument", str(inst), "--sample", "R3", "--tan-eps", "1", "--beta", "0", "--accuracy",
               "fast"])
    one_line_error(capsys, rc, "inst.toml", *must)


def test_a_directory_given_as_the_mesh_says_so(tmp_path):
    from roadgonio.errors import InputError
    from roadgonio.instrument.config import SampleGeometry
    with pytest.raises(InputError, match="is a directory; expected a mesh file") as err:
        SampleGeometry(mesh=tmp_path)
    assert err.value.field == "sample.mesh"


@pytest.mark.parametrize("command", ["fit", "uncertainty"])
def test_unwritable_out_is_refused_before_the_work(tmp_path, capsys, monkeypatch, command):
    """`fit` and `uncertainty` check --out before computing, as ka/correct/validate/render/
    intercompare do (before: the one-line error came after the whole fit or Monte Carlo)."""
    import roadgonio.surface.fit as F
    import roadgonio.uncertainty.run as U

    def computed(*a, **k):
        raise AssertionError("computed before the output folder was checked")
    monkeypatch.setattr(F, "fit_table", computed)
    monkeypatch.setattr(U, "run_uncertainty", computed)
    ro = tmp_path / "ro"
    ro.mkdir()
    out = ro / "res"
    if command == "fit":
        argv = ["fit", "R3", "--out", str(out)]
    else:
        argv = ["uncertainty", "--instrument", "lab", "--sample", "lambert", "--sigma", "alpha_deg=0.01",
                "--backend", "quadrature", "--out", str(out)]
    _read_only(monkeypatch, ro)
    one_line_error(capsys, main(argv), str(out), "Read-only file system")


@pytest.mark.parametrize("extra, edit, argv, must", [
    ("", ("focus_m = 1.0", 'focus_m = "inf"'), ["--tan-eps", "1", "--beta", "0", "--backend", "quadrature"],
     ("field 'sample'", "the detector footprint leaves the sample")),
    ("\n[housing]\nwall_reflectance = 0.05\nheight_m = 0.1\n", None, ["--cells", "12:0", "--accuracy", "fast"],
     ("field 'housing.height_m'", "the housing blocks the source at tan eps = 12, beta = 0")),
    ('\n[calibration]\nmode = "reference"\nreference = "R9"\n', None,
     ["--tan-eps", "1", "--beta", "0", "--backend", "quadrature"],
     ("field 'calibration.reference'", "unknown sample 'R9'")),
])
def test_geometry_and_calibration_errors_name_the_instrument_file(tmp_path, capsys, extra, edit, argv, must):
    """Trial 6, defect 6: a footprint off the sample, a housing that blocks a source and an unknown
    calibration reference named neither the instrument file nor the key to change."""
    from pathlib import Path
    text = (Path(__file__).resolve().parents[2] / "scenes" / "portable.toml").read_text()
    if edit is not None:
        assert edit[0] in text
        text = text.replace(edit[0], edit[1])
    inst = write_instrument(tmp_path, text + extra, name="my instrument.toml")
    rc = main(["ka", "--instrument", str(inst), "--sample", "R3", *argv,
               "--out", str(tmp_path / "o")])
    line = one_line_error(capsys, rc, *must)
    assert line.startswith(f"roadgonio: error: {inst}, "), line


# -- trial 7, defects 6 and 10: refusals name the file, the field and the cells asked; nothing half-written

def _portable_text(*edits):
    from pathlib import Path
    text = (Path(__file__).resolve().parents[2] / "scenes" / "portable.toml").read_text()
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new)
    return text


def test_detector_looking_upwards_names_the_file_and_field(tmp_path, capsys):
    """Trial 7, defect 6: 'some detected rays point upwards' named neither the instrument file nor
    the key to change (its sibling, the pupil below the plane, did)."""
    p = write_instrument(tmp_path, GOOD.replace("field_half_angle_deg = 0.05", "field_half_angle_deg = 1.5"),
                         name="up.toml")
    rc = main(["ka", "--instrument", str(p), "--sample", "R3", "--backend", "quadrature", "--tan-eps", "1",
               "--beta", "0"])
    line = one_line_error(capsys, rc, "point upwards", "field 'detector.field_half_angle_deg'")
    assert line.startswith(f"roadgonio: error: {p}, "), line


def _short_beam_instrument(tmp_path):
    """The portable with a beam table that ends at 3 deg (every cell needs more)."""
    (tmp_path / "narrow.csv").write_text("theta_deg,I\n0,1\n1,0.9\n2,0.7\n3,0.5\n")
    return write_instrument(tmp_path, _portable_text(("[detector]", 'beam_intensity_file = "narrow.csv"\n\n[detector]')),
                            name="narrow.toml")


@pytest.mark.parametrize("backend", ["quadrature", "mitsuba"])
def test_short_beam_table_names_the_cell_asked_and_the_field(tmp_path, capsys, backend):
    """Trial 7, defect 6: the Mitsuba backend refused a beam table at tan eps 0, beta 0 (where it parks
    the source while building the scene), a cell the user did not ask for, with no field named."""
    p = _short_beam_instrument(tmp_path)
    rc = main(["ka", "--instrument", str(p), "--sample", "R3", "--backend", backend, "--accuracy", "fast",
               "--tan-eps", "1", "--beta", "30"])
    line = one_line_error(capsys, rc, "field 'source.beam_intensity_file'", "at tan eps = 1, beta = 30:",
                          "narrow.csv")
    assert line.startswith(f"roadgonio: error: {p}, ") and "tan eps = 0" not in line, line


@pytest.mark.parametrize("backend", ["quadrature", "mitsuba"])
def test_many_cells_below_the_horizon_say_how_many_and_leave_nothing(tmp_path, capsys, backend):
    """Trial 7, defects 6 and 10: a table with many cells below the horizon named the first only
    (the housing check says how many more), printed '-0.0000 m below/at the sample plane' for a disc
    touching the plane, and left a ka_cells.jsonl of only a header in --out."""
    p = write_instrument(tmp_path, _portable_text(("radius_m = 0.025", "radius_m = 0.2")), name="big.toml")
    out = tmp_path / "o"
    cells = "4:0,5:0,6:0,1:0,12:0"      # tan eps 5 touches the plane exactly (1 m x cos = 0.2 m x sin)
    rc = main(["ka", "--instrument", str(p), "--sample", "R3", "--backend", backend, "--accuracy", "fast",
               "--cells", cells, "--out", str(out)])
    line = one_line_error(capsys, rc, "field 'source.radius_m'", "below the horizon at tan eps = 5, beta = 0 "
                          "(and 2 more cells)", "reaches down to the sample plane")
    assert "-0.0000" not in line
    assert not out.exists()
    out.mkdir()                          # a folder of the user's stays, and stays empty
    rc = main(["ka", "--instrument", str(p), "--sample", "R3", "--backend", backend, "--accuracy", "fast",
               "--cells", "6:0", "--out", str(out)])
    line = one_line_error(capsys, rc, "at tan eps = 6, beta = 0: its disc (radius 0.2 m at 1 m) reaches "
                          f"{1000 * (0.2 * 6 - 1) / 37 ** 0.5:.4g} mm below the sample plane")
    assert list(out.iterdir()) == []


def test_a_refusal_inside_the_backend_leaves_no_journal(tmp_path, capsys):
    """Trial 7, defect 10: a run refused after the journal was opened (here the source in the line of
    sight, the backend's own check) removes the journal of only a header and the folder it made."""
    p = write_instrument(tmp_path, GOOD.replace("distance_m = 5.0\nradius_m = 0.005",
                                                "distance_m = 1.0\nradius_m = 0.08"))
    out = tmp_path / "o"
    rc = main(["ka", "--instrument", str(p), "--sample", "R3", "--backend", "numpy-mc", "--cells", "12:180",
               "--out", str(out)])
    one_line_error(capsys, rc, "blocks the detector's line of sight")
    assert not out.exists()


@pytest.mark.parametrize("extra, vary, must", [
    ('[source]\nbeam_intensity_file = "narrow.csv"', "source.beam_sigma_deg=5,20", "gives source.beam_intensity_file"),
    ('[detector]\nfield_sensitivity = "map.csv"', "detector.field_edge_sensitivity=0.5,1", "gives detector.field_sensitivity"),
    ('[detector]\nfield_sensitivity = "map.csv"', "detector.field_edge_sensitivity=1", "gives detector.field_sensitivity"),
    ("", "source.beam_sigma_deg=5,20 source.beam_cos_power=1,2", "cannot be varied together"),
])
@pytest.mark.parametrize("second", [False, True])
def test_design_varying_an_alternative_of_the_base_is_an_input_error(tmp_path, capsys, extra, vary, must, second):
    """Trial 7, defect 7: beam_sigma_deg varied on a base with a beam_intensity_file made every point
    'infeasible' and exited 0; field_edge_sensitivity = 1 on a base with a sensitivity map was taken as
    'not given' and kept the map under the label e = 1. Both are refused before any computation."""
    (tmp_path / "narrow.csv").write_text("theta_deg,I\n0,1\n30,0.5\n60,0.1\n")
    (tmp_path / "map.csv").write_text("1,1,1\n1,1,1\n1,1,1\n")
    text = _portable_text()
    if extra:
        section, line = extra.split("\n")
        text = text.replace(section, f"{section}\n{line}", 1)
    p = write_instrument(tmp_path, text, name="base.toml")
    argv = ["design", "--instrument", str(p), "--sample", "R3", "--no-plots", "--out", str(tmp_path / "d")]
    for v in vary.split():
        argv += ["--vary", v]
    rc = main(argv + (["--second-aperture"] if second else ["--workers", "0", "--cells", "12:0"]))
    one_line_error(capsys, rc, "--vary", vary.split("=")[0], must)
    assert not (tmp_path / "d").exists()


def test_design_with_every_point_refused_for_one_reason_is_an_input_error(tmp_path, capsys):
    """Trial 7, defect 7: every point an invalid instrument for the same reason (source.height_m varied on
    an arc source) is a user error, exit 2 naming the key, before anything is computed or written
    (before: exit 0, 'no design meets the tolerance', the reason only in design.csv)."""
    p = write_instrument(tmp_path, _portable_text(), name="base.toml")
    rc = main(["design", "--instrument", str(p), "--sample", "R3", "--vary", "source.height_m=1,2", "--cells", "12:0",
               "--workers", "0", "--no-plots", "--out", str(tmp_path / "d")])
    line = one_line_error(capsys, rc, "field 'source.height_m'", "no design point is a valid instrument",
                          "--vary source.height_m")
    assert line.startswith(f"roadgonio: error: {p}, "), line
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("instrument, vary, must", [
    ("portable", "sample.size_x_m=0.1,0.2", ("2 the footprint leaves the sample", "the detector footprint leaves")),
    ("portable", "source.distance_m=0.03,0.04", ("2 the source dips below the sample plane",)),
    ("portable_housed", "housing.height_m=0.05,0.06", ("2 the housing blocks", "reaches the lid")),
])
def test_design_where_no_point_can_measure_is_an_input_error(tmp_path, capsys, instrument, vary, must):
    """User audit, session 29: a grid none of whose points can measure the cells (a sample too small,
    a source too near, a housing too low) exited 0 with 'no design meets the tolerance' and an empty
    pareto.png on a meaningless signal axis. Now one line naming the base file, --vary, the reasons
    counted and the first one; exit 2, nothing computed or written."""
    rc = main(["design", "--instrument", instrument, "--sample", "R3", "--vary", vary, "--workers", "0",
               "--no-plots", "--out", str(tmp_path / "d")])
    one_line_error(capsys, rc, "field 'vary'", "no point of the --vary grid", vary.split("=")[0], *must)
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("vary, must", [
    (["housing.baffles.0.x_m=-0.6,-0.4"], "baffle 0 of the base instrument"),
    (["housing.baffle_reflectance=0.1,0.2"], "every baffle of the base instrument"),
])
def test_design_of_a_baffle_of_height_zero_is_an_input_error(tmp_path, capsys, vary, must):
    """User audit, session 29: the bundled baffle base declares its baffle with height 0 (no plate);
    varying its position (or the baffles' paint) computed identical instruments and showed the tables'
    noise as an effect. Refused unless the design varies the height too."""
    argv = ["design", "--instrument", "portable_housed_baffle", "--sample", "R3", "--workers", "0", "--no-plots",
            "--cells", "12:0", "--out", str(tmp_path / "d")]
    for v in vary:
        argv += ["--vary", v]
    one_line_error(capsys, main(argv), "--vary", must, "height_m = 0 (no plate)")
    assert not (tmp_path / "d").exists()
    # with the height varied too, the position is a design key like any other (checked, not computed here)
    from roadgonio.design.grid import as_vary_specs, check_vary
    from roadgonio.api import _instrument
    check_vary(_instrument("portable_housed_baffle"),
               as_vary_specs(vary + ["housing.baffles.0.height_m=0,0.01"]))


@pytest.mark.parametrize("command", ["correct", "road"])
def test_an_r_table_given_as_u_is_an_input_error(tmp_path, capsys, command):
    """User audit, session 29: an r-table CSV given as the u of a table (correct --u-measured, road
    --u; here another surface's table, R2's, so no header or file identity gives it away) ran with
    u ~ 100 % of r, exit 0. Its values are r's own size: refused (U_OVER_R_MAX_MEDIAN), one line naming
    the file and the argument; a u of 5 % passes the same check."""
    from roadgonio.surface.rtable import U_OVER_R_MAX_MEDIAN, bundled_table, check_u_scale
    r3, r2 = bundled_table("R3"), bundled_table("R2")
    r2.write_csv(tmp_path / "site1.csv")
    r3.write_csv(tmp_path / "site2.csv")
    arg = "--u-measured" if command == "correct" else "--u"
    argv = ([command, "--measured", str(tmp_path / "site2.csv"), "--instrument", "portable", "--backend", "quadrature"]
            if command == "correct" else [command, "--table", str(tmp_path / "site2.csv")])
    rc = main(argv + [arg, str(tmp_path / "site1.csv"), "--out", str(tmp_path / "o")])
    one_line_error(capsys, rc, "site1.csv", arg, "% of the table's r at the median", "not its standard uncertainties")
    assert not (tmp_path / "o").exists()
    check_u_scale(0.05 * r3.r, r3)                                   # a real u passes
    with pytest.raises(Exception, match="at the median"):
        check_u_scale(U_OVER_R_MAX_MEDIAN * r3.r, r3)


def test_a_measured_u_at_or_above_its_value_is_an_input_error(tmp_path, capsys):
    """User audit: `correct --u-measured` with a file of 1 everywhere (a lab's '1 %' per cell) was read
    as u x 1e4 = 1, i.e. u up to 604 % of r, and ran, exit 0, while '150%' is refused (here R3 with 5 everywhere: 37 cells). A measured u at
    or above its value is refused like the relative form, one line naming the file, the argument and
    the first cell; a cell at 99 % of r passes."""
    from roadgonio.correction.run import measured_uncertainty
    from roadgonio.surface.rtable import bundled_table
    r3 = bundled_table("R3")
    r3.write_csv(tmp_path / "site.csv")
    r3.with_values(np.where(r3.mask, 5e-4, np.nan), name="u").write_csv(tmp_path / "percent.csv")   # "5 %"
    rc = main(["correct", "--measured", str(tmp_path / "site.csv"), "--instrument", "portable", "--backend", "quadrature",
               "--u-measured", str(tmp_path / "percent.csv"), "--out", str(tmp_path / "o")])
    over = int(np.sum(r3.mask & (r3.r <= 5e-4)))
    one_line_error(capsys, rc, "percent.csv", "--u-measured", "at or above the measured value", f"{over} cells like it")
    assert over > 0 and not (tmp_path / "o").exists()
    u = 0.05 * r3.r
    u[0, 0] = 0.99 * r3.r[0, 0]
    r3.with_values(u, name="u").write_csv(tmp_path / "high.csv")
    grid, _ = measured_uncertainty(str(tmp_path / "high.csv"), r3)
    assert grid[0, 0] == pytest.approx(0.99 * r3.r[0, 0], rel=1e-4)
    # the API's RTable form is held to the same (review, session 36: only the file form was)
    from roadgonio.errors import InputError
    grid, _ = measured_uncertainty(r3.with_values(u, name="u"), r3)
    assert grid[0, 0] == pytest.approx(0.99 * r3.r[0, 0], rel=1e-12)
    with pytest.raises(InputError, match=f"at or above the measured value.*{over} cells like it.*RTable of u in sr"):
        measured_uncertainty(r3.with_values(np.where(r3.mask, 5e-4, np.nan), name="u"), r3)


def _files(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def test_fresh_with_bad_input_found_late_keeps_the_old_results(tmp_path, capsys):
    """`uncertainty --fresh` removed the folder's results before checking the SPEC against the
    instrument, so a SPEC refused then left an empty folder (trial 9, D2: 9 files -> 0). --fresh
    now replaces the files when the new ones are written: a run that stops before changes nothing;
    one that writes fewer files (no pictures) leaves none of the earlier run's beside its own."""
    out = tmp_path / "U"
    base = ["uncertainty", "--instrument", "lab", "--sample", "lambert", "--no-aperture", "--trials", "500",
            "--out", str(out), "-q"]
    assert main(base + ["--sigma", "alpha_deg=0.01"]) == 0
    before = _files(out)
    assert "u_rel_no_aperture.png" in before and "uncertainty.json" in before
    capsys.readouterr()
    one_line_error(capsys, main(base + ["--sigma", "alpha_deg=5", "--fresh"]), "--sigma alpha_deg")
    assert _files(out) == before
    assert main(base + ["--sigma", "alpha_deg=0.02", "--fresh", "--no-plots"]) == 0
    after = _files(out)
    assert not any(name.endswith(".png") for name in after), sorted(after)
    assert json.loads(after["uncertainty.json"])["fingerprint"] != json.loads(before["uncertainty.json"])["fingerprint"]


def test_ka_fresh_one_cell_leaves_no_table_of_the_discarded_journal(tmp_path, capsys):
    """`ka --fresh --tan-eps T --beta B` into a table's folder removed ka.json and the journal but left
    the old table's ka.csv/ka.nc/ka.png (trial 9, D3): the folder claimed a table without its
    provenance. --fresh now discards the table files with the journal; --cells with one cell is an
    error (it was silently ignored)."""
    out = tmp_path / "K"
    base = ["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "quadrature", "--accuracy", "fast",
            "--out", str(out), "-q"]
    assert main(base + ["--cells", "12:0,4:0"]) == 0
    assert {"ka.csv", "ka.nc", "ka.json", "ka_bound.csv", "ka_cells.jsonl"} <= set(_files(out))
    assert main(base + ["--fresh", "--tan-eps", "1", "--beta", "0"]) == 0
    assert set(_files(out)) == {"ka_cells.jsonl"}
    journal = (out / "ka_cells.jsonl").read_text().splitlines()
    assert len(journal) == 2 and json.loads(journal[1])["tan_eps"] == 1.0
    capsys.readouterr()
    one_line_error(capsys, main(base + ["--cells", "4:0", "--tan-eps", "1", "--beta", "0"]), "--cells")


def test_a_table_written_again_keeps_no_file_of_the_earlier_backend(tmp_path):
    """A Monte Carlo table then, --fresh, a bounded one: ka_se.csv of the first must not stay beside
    the second's ka_bound.csv (the folder would hold two precisions of two runs)."""
    out = tmp_path / "K"
    base = ["ka", "--instrument", "lab", "--sample", "lambert", "--cells", "12:0,4:0", "--out", str(out), "-q"]
    assert main(base + ["--backend", "numpy-mc", "--rel-se", "0.02"]) == 0
    assert "ka_se.csv" in _files(out)
    assert main(base + ["--backend", "quadrature", "--accuracy", "fast", "--fresh"]) == 0
    files = _files(out)
    assert "ka_bound.csv" in files and "ka_se.csv" not in files, sorted(files)


@pytest.mark.parametrize("opts, must", [
    (["--max-trials", "1000"], "--max-trials"),
    (["--batch", "500"], "--batch"),
    (["--trials", "1000", "--max-trials", "1000", "--batch", "500"], "(--max-trials) and batch size (--batch)"),
])
def test_adaptive_options_without_adaptive_are_refused(tmp_path, capsys, opts, must):
    """--max-trials and --batch shape the adaptive rule only; without --adaptive they were accepted and
    ignored (user audit, session 19). Refused before anything runs."""
    rc = main(["uncertainty", "--instrument", "portable", "--sample", "R3", "--sigma", "alpha_deg=0.01",
               "--out", str(tmp_path / "u"), *opts])
    one_line_error(capsys, rc, must, "--adaptive")
    assert not (tmp_path / "u").exists()


def test_a_cell_the_geometry_refuses_beyond_the_table_is_one_line(capsys):
    """ka --tan-eps 100 printed the extrapolation note (tan eps beyond the table's last row) and then
    the geometry's error: two lines for one mistake (user audit, session 19). The refusal comes first."""
    rc = main(["ka", "--instrument", "portable", "--sample", "R3", "--tan-eps", "100", "--beta", "0",
               "--backend", "quadrature"])
    one_line_error(capsys, rc, "source.radius_m", "below the horizon")


@pytest.mark.parametrize("option", [["--backend", "quadrature"], ["--rel-se", "0.01"], ["--surrogate", "star"],
                                    ["--validation", "10"], ["--workers", "2"], ["--variant", "llvm_ad_rgb"]])
def test_uncertainty_options_of_the_aperture_case_with_no_aperture_are_errors(tmp_path, capsys, option):
    """(audit 21, 4) `uncertainty --no-aperture --surrogate star --validation 1000 --rel-se 0.9 ...` ran
    and ignored them all, where --max-trials without --adaptive is refused."""
    out = tmp_path / "U"
    rc = main(["uncertainty", "--instrument", "lab", "--sample", "lambert", "--no-aperture", "--trials", "500",
               "--sigma", "alpha_deg=0.01", *option, "--out", str(out), "-q"])
    one_line_error(capsys, rc, option[0])
    assert not out.exists()


@pytest.mark.parametrize("sigma", ["alpha_deg=0", "alpha_deg=0,eps_deg=0:rect", "EMPTY"])
def test_uncertainty_with_nothing_to_propagate_is_an_error(tmp_path, capsys, sigma):
    """(audit 21, 4) an empty --sigma TOML file or only zeros ran and printed max/u(r) = inf (0 / 0)."""
    if sigma == "EMPTY":
        sigma = str(tmp_path / "empty.toml")
        (tmp_path / "empty.toml").write_text("")
    rc = main(["uncertainty", "--instrument", "lab", "--sample", "lambert", "--no-aperture", "--trials", "500",
               "--sigma", sigma, "--out", str(tmp_path / "U"), "-q"])
    one_line_error(capsys, rc, "--sigma", "nothing to propagate")
    assert not (tmp_path / "U").exists()


def test_a_scene_part_in_the_detectors_view_names_the_files_and_no_cell(mi, tmp_path, capsys):
    """(user audit) a holder wall moved into the detector's view was refused 'at tan eps = 0, beta = 0'
    for a table of other cells, naming neither the instrument nor the scene file. The view does not
    depend on the cell: the message names both files and no cell."""
    from pathlib import Path
    xml = Path(__file__).resolve().parents[2] / "scenes" / "holder.xml"
    inst = tmp_path / "front.toml"
    inst.write_text(f"""[instrument]\nname = "front"\n\n[observation]\nalpha_deg = 1.0\n
[source]\ndistance_m = 5.0\nradius_m = 0.005\n
[detector]\ndistance_m = 10.0\npupil_radius_m = 0.005\nfield_half_angle_deg = 0.05\nfocus_m = 10.0\n
[sample]\nsize_x_m = 2.0\nsize_y_m = 0.5\n
[scene]\nxml = "{xml}"\n
[scene.params]\nwall_x_m = 1.005\nwall_half_height_m = 0.005\nrail_y_m = 0.26\n""")
    rc = main(["ka", "--instrument", str(inst), "--sample", "R3", "--cells", "12:0,4:0", "--out", str(tmp_path / "o")])
    line = one_line_error(capsys, rc, "front.toml", "the part 'wall'", "holder.xml", "at every cell")
    assert "tan eps" not in line


def test_a_value_that_starts_with_a_minus_reaches_its_own_check(tmp_path, capsys):
    """User audit, session 37: ``--u-measured -1%`` gave argparse's "expected one argument" (it took
    '-1%' for an option), never the u's own check; it is now the u's error, naming the option. A
    plain negative number was always taken as a value."""
    from roadgonio.cli import _negative_values
    assert _negative_values(["--u-measured", "-1%", "--tan-eps", "-1", "--fresh", "--x", "-0.5:rect"]) == \
        ["--u-measured=-1%", "--tan-eps", "-1", "--fresh", "--x=-0.5:rect"]
    from roadgonio.surface.rtable import bundled_table
    bundled_table("R3").write_csv(tmp_path / "site.csv")
    rc = main(["correct", "--measured", str(tmp_path / "site.csv"), "--instrument", "portable", "--backend",
               "quadrature", "--u-measured", "-1%", "--out", str(tmp_path / "o")])
    one_line_error(capsys, rc, "--u-measured", "between 0 and 100 %", "got -1%")
    assert not (tmp_path / "o").exists()


def test_a_table_with_a_quadrature_cell_at_its_cap_says_so_in_ka_bound_and_its_u_is_the_estimate(tmp_path, monkeypatch):
    """(review, session 39) ka_bound.csv was headed "deterministic error bound" for every cell, a cell
    stopped at its cap included (its value an estimate that can understate the error), and the cell's
    standard uncertainty divided that estimate by sqrt 3 as if it were a rectangular bound."""
    import roadgonio.engines.quadrature as Q
    from roadgonio.engines.result import CellResult
    real = Q.make_backend
    monkeypatch.setattr(Q, "make_backend", lambda *a, **k: real(*a, **{**k, "max_evals": 5000}))
    out = tmp_path / "k"
    assert main(["ka", "--instrument", "portable", "--sample", "R3", "--backend", "quadrature", "--cells", "12:0,1:0",
                 "--rel-se", "1e-6", "--out", str(out), "-q"]) == 0
    head = (out / "ka_bound.csv").read_text().splitlines()[0]
    assert "not converged" in head and "not a bound" in head, head
    c = CellResult(12.0, 0.0, 0.9, math.nan, 5000, 1.0, error_bound=0.01, converged=False)
    assert c.standard_uncertainty() == pytest.approx(0.01, rel=1e-12)
    ok = CellResult(12.0, 0.0, 0.9, math.nan, 5000, 1.0, error_bound=0.01, converged=True)
    assert ok.standard_uncertainty() == pytest.approx(0.01 / math.sqrt(3.0), rel=1e-12)
