"""Every command has --json and --quiet; progress bars appear only when stderr is a terminal."""
from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys

import pytest

from roadgonio.cli import build_parser, main
from roadgonio.cli._common import show_progress


def _subparsers():
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


#: Every command the program has (discovered, so a new command is held to the same rule).
COMMANDS = sorted(_subparsers())


def test_the_commands_are_discovered():
    assert {"tables", "table", "fit", "ka", "render", "validate", "uncertainty", "correct"} <= set(COMMANDS)


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_json_and_quiet(command):
    sub = _subparsers()[command]
    options = {o for a in sub._actions for o in a.option_strings}
    assert {"--json", "--quiet", "-q"} <= options
    with pytest.raises(SystemExit):                  # exclusive: one or the other
        sub.parse_args(["--json", "--quiet"])


def test_progress_only_on_a_terminal(monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True
    quiet, loud = argparse.Namespace(quiet=True), argparse.Namespace(quiet=False)
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert not show_progress(loud)
    monkeypatch.setattr(sys, "stderr", Tty())
    assert show_progress(loud) and not show_progress(quiet)


def test_quiet_prints_nothing_and_json_prints_json(tmp_path, capsys):
    assert main(["table", "R3", "--to", str(tmp_path / "r3.rtb"), "--quiet"]) == 0
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err == "" and (tmp_path / "r3.rtb").exists()
    assert main(["tables", "--json"]) == 0
    assert [r["table"] for r in json.loads(capsys.readouterr().out)] == ["R1", "R2", "R3", "R4", "C1", "C2"]
    args = ["ka", "--instrument", "portable", "--sample", "lambert", "--backend", "quadrature", "--accuracy", "fast",
            "--tan-eps", "12", "--beta", "0"]
    assert main(args + ["--quiet"]) == 0
    assert capsys.readouterr().out == ""
    assert main(args) == 0 and "k_A(tan eps = 12, beta = 0)" in capsys.readouterr().out


def test_no_progress_bar_into_a_pipe(tmp_path):
    """A table run whose stderr is a pipe (a log file, CI) gets no progress bar, only the summary on stdout."""
    r = subprocess.run([sys.executable, "-m", "roadgonio", "ka", "--instrument", "portable", "--sample", "lambert",
                        "--backend", "quadrature", "--accuracy", "fast", "--out", str(tmp_path / "ka")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert r.stderr == "" and "580 cells" in r.stdout


@pytest.mark.parametrize("argv, must", [
    (["correct", "--measured", "a.csv", "b.csv", "--instrument", "A.toml", "B.toml", "--joint"],
     "roadgonio: error: roadgonio correct: unrecognized arguments: B.toml (see 'roadgonio correct --help')"),
    (["--bogus"], "roadgonio: error: unrecognized arguments: --bogus (see 'roadgonio --help')"),
    (["nocommand"], "roadgonio: error: argument COMMAND: invalid choice: 'nocommand'"),
])
def test_a_bad_argument_is_one_line_without_a_doubled_prefix(capsys, argv, must):
    """(before: 'roadgonio: error: roadgonio: unrecognized arguments: B.toml')"""
    from roadgonio.cli import main
    with pytest.raises(SystemExit) as ex:
        main(argv)
    err = capsys.readouterr().err
    assert ex.value.code == 2 and err.count("\n") == 1 and err.startswith(must), err
    assert "roadgonio: error: roadgonio:" not in err


def test_help_names_every_output():
    """ka --help lists the stray-light tables, render --help the stray pictures."""
    text = {c: " ".join(_subparsers()[c].format_help().split()) for c in ("ka", "render")}
    for f in ("ka_direct.csv", "stray_fraction.csv"):
        assert f in text["ka"]
    for f in ("stray.png", "stray.exr", "render.json"):
        assert f in text["render"]


# -- trial 11 D11: small message and help slips ----------------------------------------------

@pytest.mark.parametrize("argv, must", [
    # inf and NaN are not tan eps < 0: the message says finite
    (["ka", "--instrument", "lab", "--sample", "R3", "--tan-eps", "inf", "--beta", "0"],
     "field '--tan-eps': expected a finite tan eps >= 0, got inf"),
    (["ka", "--instrument", "lab", "--sample", "R3", "--tan-eps", "1", "--beta", "nan"],
     "field '--beta': expected a finite beta, 0 <= beta <= 180 deg, got nan"),
    # a positional argument is named as --help shows it (B, not the API's b)
    (["compare", "R3", "no_such_table.rtb"], "no_such_table.rtb, B: no such table file"),
    (["compare", "R9", "R3"], "field 'A': 'R9' is not a bundled table"),
    (["classify", "R9"], "field 'T': 'R9' is not a bundled table"),
])
def test_slips_in_messages(capsys, argv, must):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and must in err, err


def test_classify_says_what_its_distance_counts(capsys):
    """The nearest bundled table's distance was in 'spreads', a word defined nowhere: it is in
    standard deviations of S1 and Q0 over the six bundled tables, and --help says so."""
    assert main(["classify", "R2"]) == 0
    assert "distance 0.00 sd of the bundled tables' S1 and Q0" in capsys.readouterr().out
    text = " ".join(_subparsers()["classify"].format_help().split())
    assert "standard deviations of that coordinate over the six bundled tables (sd)" in text


def test_ka_help_gives_k_a_for_every_calibration_mode():
    text = " ".join(_subparsers()["ka"].format_help().split())
    for words in ("lambert (the default)", "absolute (the paper's eq. 2) k_A = L_D / (E_0 f_road(nominal))",
                  "reference = SAMPLE k_A = (S[f_road]/S[f_ref])"):
        assert words in text, words


def test_ka_summary_says_its_time_is_the_cells_computation(tmp_path, capsys):
    """The table's summary printed the cells' computing time as if it were the command's (0.1 s
    printed, 3 s taken)."""
    assert main(["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "quadrature", "--cells", "1:0",
                 "--out", str(tmp_path)]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert "; computing the cells took " in line and line.endswith(" s."), line


def test_an_empty_out_folder_is_an_error_not_the_default(tmp_path, capsys, monkeypatch):
    """--out '' wrote to the default folder without a word (user audit, session 19)."""
    monkeypatch.chdir(tmp_path)
    rc = main(["compare", "R3", "R2", "--out", ""])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "--out" in err and "empty" in err, err
    assert list(tmp_path.iterdir()) == []


def test_table_says_q0_missing_without_a_unit(tmp_path, capsys):
    """(audit 22) a table without a Q0 printed 'Q0 = missing sr^-1'."""
    import numpy as np

    from roadgonio.surface.rtable import bundled_table
    t = bundled_table("R3")
    r = np.full_like(t.r, np.nan)
    r[0, 0], r[1, 1] = t.r[0, 0], t.r[1, 1]           # no grid cell with four tabulated corners: no Q0
    path = t.with_values(r, name="two").write_csv(tmp_path / "two.csv")
    assert main(["table", str(path)]) == 0
    out = capsys.readouterr().out
    assert "Q0 = missing," in out and "missing sr^-1" not in out
    assert main(["table", "R3"]) == 0
    assert "Q0 = 0.0698 sr^-1," in capsys.readouterr().out


def test_table_says_how_an_rtb_was_read(tmp_path, capsys):
    """(audit 22) an RTB whose scale its q0 line told (values in sr^-1), or whose q0 line is off the
    values' Q0, was read with a note only in the table's source; `table` prints it and --json has it."""
    from roadgonio.surface.rtable import bundled_table
    lines = bundled_table("R3").to_rtb_text().splitlines()
    sr = lines[:54] + [f"{float(v) / 1e4:.8g}" for v in lines[54:]]
    (tmp_path / "sr.rtb").write_text("\n".join(sr))
    assert main(["table", str(tmp_path / "sr.rtb")]) == 0
    assert "  read: values read as r in sr^-1" in capsys.readouterr().out
    assert main(["table", str(tmp_path / "sr.rtb"), "--json"]) == 0
    assert "values read as r in sr^-1" in json.loads(capsys.readouterr().out)["reading_note"]
    # the CSV written from it keeps the RTB's source as its header, but its values are r x 1e4 as read
    assert main(["table", str(tmp_path / "sr.rtb"), "--to", str(tmp_path / "sr.csv"), "-q"]) == 0
    assert main(["table", str(tmp_path / "sr.csv")]) == 0
    assert "read:" not in capsys.readouterr().out
    (tmp_path / "plain.rtb").write_text("\n".join(lines))
    assert main(["table", str(tmp_path / "plain.rtb")]) == 0
    assert "read:" not in capsys.readouterr().out


@pytest.mark.parametrize("stored", ["standard uncertainty of road", "k_A of R3"])
def test_an_rtb_whose_name_reads_like_another_tables_header_converts_to_a_csv_that_reads_back(tmp_path, capsys, stored):
    """(user audit, session 44) an RTB surface named "standard uncertainty of road" was written to a CSV
    whose header made every reader take it for a table of uncertainties (`table` refused the file it had
    just written); "k_A of R3" could not be converted at all."""
    from roadgonio.surface.rtable import bundled_table
    lines = bundled_table("R3").to_rtb_text().splitlines()
    lines[1] = stored
    (tmp_path / "named.rtb").write_text("\n".join(lines))
    assert main(["table", str(tmp_path / "named.rtb"), "--to", str(tmp_path / "named.csv"), "-q"]) == 0
    assert main(["table", str(tmp_path / "named.csv"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["Q0"] == pytest.approx(bundled_table("R3").q0(), rel=1e-5)


def test_every_command_reading_an_rtb_says_how_it_was_read(tmp_path, capsys):
    """(user audit, session 44) an RTB whose q0 line is 29 % off its values' Q0 was said so by
    `table`'s text alone: classify and compare (whose JSON lists notes) and fit read it silently."""
    from roadgonio.surface.rtable import bundled_table
    lines = bundled_table("R3").to_rtb_text().splitlines()
    lines[53] = "0.09"                      # the q0 line (line 54)
    (tmp_path / "off.rtb").write_text("\n".join(lines))
    said = "off.rtb: read: q0 line 0.09 sr^-1 differs from the values' Q0 0.06979 sr^-1 by +29 %"
    assert main(["classify", str(tmp_path / "off.rtb"), "--json"]) == 0
    assert said in json.loads(capsys.readouterr().out)["notes"]
    assert main(["compare", "R3", str(tmp_path / "off.rtb"), "--json", "--no-plots"]) == 0
    assert said in json.loads(capsys.readouterr().out)["notes"]
    assert main(["classify", str(tmp_path / "off.rtb")]) == 0
    assert capsys.readouterr().out.count(said) == 1
    assert main(["fit", str(tmp_path / "off.rtb"), "--out", str(tmp_path / "fit"), "--no-plot", "-q"]) == 0
    assert said in capsys.readouterr().err


def test_eta_s_bound_beside_a_standard_error_is_not_called_a_bound_on_k_a(tmp_path):
    """(audit 28) Mitsuba under absolute calibration: error_bound holds eta's deterministic part of
    the error (7e-7 beside an SE of 1.5e-4), but ka.nc, ka_bound.csv and ka.json called it 'a
    deterministic bound on |k_A - true k_A|'. They say what it is now; the quadrature's, alone, is
    still the bound on k_A."""
    import xarray as xr

    from roadgonio import api
    from roadgonio.instrument.config import load_instrument
    inst = load_instrument("portable").with_changes(calibration={"mode": "absolute"})
    for backend, eta_part in (("mitsuba", True), ("quadrature", False)):
        out = tmp_path / backend
        api.ka_table(inst, "R3", cells=[(12.0, 0.0)], backend=backend, accuracy="fast", out=out, plot=False)
        attrs = xr.open_dataset(out / "ka.nc")["error_bound"].attrs
        head = (out / "ka_bound.csv").read_text().splitlines()[0]
        summary = json.loads((out / "ka.json").read_text())["summary"]
        assert ("eta" in attrs["long_name"] and "eta" in head and "error_bound_of" in summary) is eta_part
        assert ("bound on |k_A - true k_A|" in attrs["description"]) is not eta_part
