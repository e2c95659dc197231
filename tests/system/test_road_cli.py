"""`roadgonio road`, `compare` and `classify` from the command line (issue 13)."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from roadgonio.cli import main
from roadgonio.road.evaluate import Installation
from roadgonio.road.layout import load_layout
from roadgonio.road.luminaire import load_luminaire
from roadgonio.surface.rtable import BUNDLED, bundled_table


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    """Commands run without --out write to their default folder (out/road-TABLES) under the current
    folder: the test's, not the checkout's (they had left out/road-R3, road-hole, ... in it)."""
    monkeypatch.chdir(tmp_path)


def test_road_out_of_the_box_json(tmp_path, capsys):
    assert main(["road", "--table", "R3", "--out", str(tmp_path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert {"table", "L_av", "U_o", "U_l", "TI", "class"} <= set(d)
    want = Installation(load_layout(), load_luminaire()).evaluate(bundled_table("R3")).values
    assert d["table"] == "R3" and d["L_av"] == pytest.approx(want["L_av"]) and d["class"] == "M3"
    assert len(d["U_l_per_lane"]) == 2 and d["U_l"] == min(d["U_l_per_lane"])
    names = {p.name for p in tmp_path.iterdir()}
    assert names == {"road.json", "road_metrics.csv", "road_luminance.csv", "road_metrics.png", "road_luminance.png"}
    assert (tmp_path / "road_metrics.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = list(csv.DictReader((tmp_path / "road_luminance.csv").read_text().splitlines()))
    assert len(rows) == 2 * 60 and float(rows[0]["L_cd_m2"]) > 0


def test_road_says_when_the_spacing_leaves_points_without_a_counted_luminaire(tmp_path, capsys):
    """(user audit) S = 300 m printed U_o 0.000 without a word: one note line in the text, and in --json."""
    lay = tmp_path / "wide.toml"
    lay.write_text("[installation]\nspacing_m = 300.0\n")
    assert main(["road", "--table", "R3", "--layout", str(lay), "--no-plots", "--out", str(tmp_path / "o")]) == 0
    notes = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("note:")]
    assert len(notes) == 1 and "258 of 600 grid points have no luminaire" in notes[0], notes
    assert main(["road", "--table", "R3", "--layout", str(lay), "--no-plots", "--out", str(tmp_path / "o"),
                 "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["U_o"] == 0.0 and len(d["notes"]) == 1 and "258 of 600" in d["notes"][0]
    assert main(["road", "--table", "R3", "--no-plots", "--out", str(tmp_path / "d"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["notes"] == []


def test_road_with_nothing_counted_lists_every_missing_metric_and_says_nothing_is_lit(tmp_path, capsys):
    """(audit 27) no luminaire counted anywhere: R_EI was null without a reason, `missing` left out
    TI and R_EI, and the note said "U_o is 0" beside U_o null."""
    lay = tmp_path / "zero.toml"
    lay.write_text("[calculation]\nluminaires_before_h = 0\nluminaires_after_h = 0\n")
    assert main(["road", "--table", "R3", "--layout", str(lay), "--no-plots", "--out", str(tmp_path / "o"),
                 "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["L_av"] == 0.0 and d["U_o"] is None and d["TI"] is None and d["R_EI"] is None and d["class"] is None
    assert {"U_o", "U_l", "TI", "R_EI", "class"} <= set(d["missing"]["metrics"])
    assert "TI needs L_av > 0" in d["missing"]["reason"] and "R_EI needs light" in d["missing"]["reason"]
    assert len(d["notes"]) == 1 and "nothing is lit" in d["notes"][0] and "U_o is 0" not in d["notes"][0]


def test_road_notes_a_hole_in_the_table_that_it_interpolates_across(tmp_path, capsys):
    """(audit 27) a blank cell inside the region the CIE tables tabulate (tan eps 2, beta 10) is
    interpolated across from its neighbours (the interpolation's stencil among the cells given):
    the metrics are given, with a note naming the cell, printed whichever place the table has."""
    t = bundled_table("R3")
    r = t.r.copy()
    i, j = int(np.argmin(abs(t.tan_eps - 2.0))), int(np.argmin(abs(t.beta_deg - 10.0)))
    r[i, j] = np.nan
    t.with_values(r).write_csv(tmp_path / "hole.csv")
    assert main(["road", "--table", "R3", "--table", str(tmp_path / "hole.csv"), "--no-plots",
                 "--out", str(tmp_path / "o")]) == 0
    notes = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("note:")]
    assert len(notes) == 1 and "hole.csv: 1 cell(s)" in notes[0] and "2:10" in notes[0], notes
    assert main(["road", "--table", str(tmp_path / "hole.csv"), "--no-plots", "--out", str(tmp_path / "p"),
                 "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["L_av"] is not None and d["missing"] is None and "2:10" in d["notes"][0]


def test_road_several_tables_and_uncertainty(tmp_path, capsys):
    t = bundled_table("R3")
    measured = t.with_values(t.r * 1.2, name="R3_measured")
    measured.write_csv(tmp_path / "R3_measured.csv")
    t.with_values(t.r * 0.02).write_csv(tmp_path / "corrected_u.csv")
    out = tmp_path / "o"
    assert main(["road", "--table", str(tmp_path / "R3_measured.csv"), "--table", "R3", "--u",
                 str(tmp_path / "corrected_u.csv"), "--trials", "2000", "--out", str(out), "--json", "--no-plots"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert [x["table"] for x in d] == ["R3_measured.csv", "R3"]          # a file is named by its file name
    assert d[0]["L_av"] == pytest.approx(1.2 * d[1]["L_av"]) and d[0]["U_o"] == pytest.approx(d[1]["U_o"])
    assert "uncertainty" not in d[0]
    u = d[1]["uncertainty"]
    assert u["trials"] == 2000 and set(u) >= {"independent", "correlated"}
    assert u["correlated"]["L_av"]["u"] == pytest.approx(0.02 * d[1]["L_av"], rel=0.1)
    lo, hi = u["independent"]["U_o"]["coverage_interval_95"]
    assert lo < d[1]["U_o"] + 1e-9 and hi > lo
    assert 0 <= u["independent"]["P_meets_target"] <= 1
    rows = list(csv.DictReader((out / "road_metrics.csv").read_text().splitlines()))
    assert [r["correlation"] for r in rows] == ["", "independent", "correlated"]


def test_road_u_goes_with_the_table_just_before_it(tmp_path, capsys):
    """Trial 7, defect 8: --u went to the last --table wherever it stood, so `--table A --u uA
    --table B` put A's uncertainty on B without a word."""
    t = bundled_table("R3")
    t.with_values(t.r * 1.2, name="R3_measured").write_csv(tmp_path / "R3_measured.csv")
    t.with_values(t.r * 0.02).write_csv(tmp_path / "u.csv")
    assert main(["road", "--table", str(tmp_path / "R3_measured.csv"), "--u", str(tmp_path / "u.csv"), "--table", "R3",
                 "--trials", "500", "--out", str(tmp_path / "o"), "--json", "--no-plots"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert [x["table"] for x in d] == ["R3_measured.csv", "R3"]
    assert d[0]["uncertainty"]["file"] == str(tmp_path / "u.csv") and "uncertainty" not in d[1]


def test_road_u_before_any_table_is_an_error(tmp_path, capsys):
    rc = main(["road", "--u", str(tmp_path / "u.csv"), "--table", "R3", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "--u" in err and "comes before any --table" in err, err
    assert not (tmp_path / "o").exists()


def test_road_u_naming_another_table_is_an_error(tmp_path, capsys):
    """A u file whose header names its table ('standard uncertainty of <header>', as correct writes
    corrected_u.csv) put after a CSV table with another header: an error naming both."""
    t = bundled_table("R3")
    t.with_values(t.r, source="R3 corrected for the aperture effect").write_csv(tmp_path / "corrected.csv")
    t.with_values(t.r, source="the true table").write_csv(tmp_path / "truth.csv")
    t.with_values(t.r * 0.02, source="standard uncertainty of R3 corrected for the aperture effect").write_csv(
        tmp_path / "corrected_u.csv")
    base = ["road", "--trials", "500", "--no-plots", "--json"]
    rc = main(base + ["--table", str(tmp_path / "corrected.csv"), "--table", str(tmp_path / "truth.csv"),
                      "--u", str(tmp_path / "corrected_u.csv"), "--out", str(tmp_path / "bad")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err, err
    for w in ("--u", "corrected_u.csv", "'R3 corrected for the aperture effect'", "truth.csv", "'the true table'"):
        assert w in err, (w, err)
    assert not (tmp_path / "bad").exists()
    assert main(base + ["--table", str(tmp_path / "truth.csv"), "--table", str(tmp_path / "corrected.csv"),
                        "--u", str(tmp_path / "corrected_u.csv"), "--out", str(tmp_path / "good")]) == 0
    assert "uncertainty" in json.loads(capsys.readouterr().out)[1]


def test_road_u_naming_another_bundled_table_is_an_error(tmp_path, capsys):
    """(user audit, session 45) a u whose header names bundled R3 passed after bundled R1 (a bundled table
    has no header to compare), while uncertainty's u of sample R3 was refused there; its own table takes it."""
    t = bundled_table("R3")
    t.with_values(t.r * 0.03, source="standard uncertainty of R3 (3 % of r)").write_csv(tmp_path / "u3.csv")
    base = ["road", "--trials", "500", "--no-plots", "--json"]
    assert main(base + ["--table", "R1", "--u", str(tmp_path / "u3.csv"), "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "u3.csv" in err and "'R3 (3 % of r)'" in err and "bundled table R1" in err, err
    assert not (tmp_path / "bad").exists()
    assert main(base + ["--table", "R3", "--u", str(tmp_path / "u3.csv"), "--out", str(tmp_path / "good")]) == 0
    assert "uncertainty" in json.dumps(json.loads(capsys.readouterr().out))


def test_road_u_written_by_uncertainty_must_go_with_its_sample(tmp_path, capsys):
    """A u file as `roadgonio uncertainty` writes it names its sample (trial 9: R3's u put on R2
    passed without a word): after the table of another name it is an error naming both, after its
    own table (bundled, or a file of that name) it is used, and its _mean.csv is refused as a u."""
    from roadgonio.uncertainty.report import table_header
    t = bundled_table("R3")
    for sample, key in (("R3", "u"), ("R3", "mean"), ("myr3", "u")):
        t.with_values(t.r * (0.01 if key == "u" else 1.0),
                      source=table_header("aperture", 10_000, 1, sample, key)).write_csv(
            tmp_path / f"{sample}_aperture_{key}.csv")
    t.write_csv(tmp_path / "myr3.csv")
    base = ["road", "--trials", "500", "--no-plots", "--json"]
    for tables, u, words in ((["R3", "R2"], "R3_aperture_u.csv", ["'R3'", "R2", "R3_aperture_u.csv"]),
                             (["R2"], "myr3_aperture_u.csv", ["'myr3'", "R2"]),
                             (["R3"], "R3_aperture_mean.csv", ["mean table", "R3_aperture_mean.csv", "_u.csv"])):
        args = [a for x in tables for a in ("--table", x)] + ["--u", str(tmp_path / u), "--out", str(tmp_path / "bad")]
        rc = main(base + args)
        err = capsys.readouterr().err.strip()
        assert rc == 2 and "\n" not in err and "--u" in err, err
        for w in words:
            assert w in err, (w, err)
        assert not (tmp_path / "bad").exists()
    for table, u in (("R3", "R3_aperture_u.csv"), (str(tmp_path / "myr3.csv"), "myr3_aperture_u.csv")):
        assert main(base + ["--table", "R2", "--table", table, "--u", str(tmp_path / u)]) == 0
        assert "uncertainty" in json.loads(capsys.readouterr().out)[1]


def test_road_text_output(tmp_path, capsys):
    assert main(["road", "--table", "R2", "--table", "R3", "--out", str(tmp_path), "--no-plots"]) == 0
    text = capsys.readouterr().out
    assert "R3 vs R2: L_av" in text and "M3" in text and "wrote 3 files" in text
    assert main(["road", "--table", "R3", "--out", str(tmp_path / "q"), "--quiet", "--no-plots"]) == 0
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize("extra,words", [
    (["--u", "a.csv", "--u", "b.csv"], ["--u", "--u a.csv and --u b.csv both follow --table R2"]),
    (["--class", "M9"], ["unknown class", "M9"]),
    (["--layout", "missing.toml"], ["missing.toml", "no such layout file"]),
    (["--luminaire", "missing.ldt"], ["missing.ldt", "no such luminaire file"]),
    (["--u", "nothere.csv"], ["--u", "nothere.csv"]),
    (["--trials", "5", "--u", "U"], ["at least 100 trials"]),
])
def test_road_bad_input_is_one_line_exit_2(tmp_path, capsys, monkeypatch, extra, words):
    monkeypatch.chdir(tmp_path)
    t = bundled_table("R3")
    t.with_values(t.r * 0.02).write_csv(tmp_path / "U")
    args = ["road", "--table", "R3", "--table", "R2", "--out", str(tmp_path / "o")] + extra
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("roadgonio: error:") and "\n" not in err
    for w in words:
        assert w in err, err
    assert not (tmp_path / "o").exists()


def test_compare_writes_ratio_map_and_characteristics(tmp_path, capsys):
    assert main(["compare", "R3", "R4", "--out", str(tmp_path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    a, b = bundled_table("R3"), bundled_table("R4")
    assert d["characteristics"]["R3"]["S1"] == pytest.approx(a.s1())
    assert d["characteristics"]["R4"]["Q0"] == pytest.approx(b.q0())
    rows = list(csv.DictReader((tmp_path / "compare.csv").read_text().splitlines()))
    assert len(rows) == int(a.mask.sum())
    r0 = next(r for r in rows if r["tan_eps"] == "12" and r["beta_deg"] == "0")
    assert float(r0["ratio_B_over_A"]) == pytest.approx(b.value(12, 0) / a.value(12, 0), rel=1e-5)
    assert d["ratio_max"] == pytest.approx(np.nanmax(b.r / a.r))
    assert (tmp_path / "compare.png").stat().st_size > 10_000


def test_compare_without_plots_removes_an_earlier_runs_picture(tmp_path, capsys):
    """Trial 11 D4: `compare --no-plots` into a folder of an earlier comparison left its compare.png
    (of other tables) beside the new CSV and JSON. The earlier picture is stood in for by a file of
    that name; a run that fails (an unknown table) leaves the folder as it was."""
    out = tmp_path / "stale"
    out.mkdir()
    (out / "compare.png").write_bytes(b"picture of R3 / R2")
    (out / "notes.txt").write_text("the user's own file")
    assert main(["compare", "R1", "nonexistent.rtb", "--no-plots", "--out", str(out), "-q"]) == 2
    assert (out / "compare.png").exists()
    assert main(["compare", "R1", "R4", "--no-plots", "--out", str(out), "-q"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["compare.csv", "compare.json", "notes.txt"]


def test_table_and_compare_print_s1_on_its_side_of_a_class_limit_and_missing_in_words(tmp_path, capsys):
    """(user audit, session 44) S1 = 0.84997, class R2 (R3 from 0.85), printed "0.850" by table and
    compare (classify's digits were mended in session 41 alone); compare printed "-" for a missing S1
    where the docs and the other commands say "missing"; the same table read at two scales (a ratio
    1 - 2.2e-16) had a "largest change x1"."""
    from roadgonio.road.compare import compare_tables
    t = bundled_table("R3")
    r = t.r.copy()
    r[0, 0], r[list(t.tan_eps).index(2.0), 0] = 300e-4, 254.99e-4
    t.with_values(r, name="edge").write_csv(tmp_path / "edge.csv")
    assert main(["table", str(tmp_path / "edge.csv")]) == 0
    assert "S1 = 0.84997," in capsys.readouterr().out
    assert main(["compare", "R3", str(tmp_path / "edge.csv"), "--no-plots", "--out", str(tmp_path / "c")]) == 0
    assert " 0.84997" in capsys.readouterr().out.splitlines()[1]
    r[0, 0] = np.nan
    t.with_values(r, name="no00").write_csv(tmp_path / "no00.csv")
    assert main(["compare", "R3", str(tmp_path / "no00.csv"), "--no-plots", "--out", str(tmp_path / "d")]) == 0
    assert capsys.readouterr().out.splitlines()[1].split()[-1] == "missing"
    assert compare_tables(t, t.with_values(t.r * (1 - 2.2e-16), name="again"))["largest_change_at"] is None
    assert compare_tables(t, t.with_values(t.r * (1 + 1e-6), name="scaled"))["largest_change_at"] is not None


def test_table_to_says_when_the_written_values_move_s1_across_a_class_limit(tmp_path, capsys):
    """(user audit, session 44) S1 3.3e-7 below 0.85 (R2) became 0.85 (R3) in the file `table --to`
    wrote (6 significant digits), without a word."""
    t = bundled_table("R3")
    r = t.r.copy()
    r[0, 0], r[list(t.tan_eps).index(2.0), 0] = 300e-4, 254.9999e-4
    t.with_values(r, name="edge").write_csv(tmp_path / "edge.csv", digits=9)
    assert main(["table", str(tmp_path / "edge.csv"), "--to", str(tmp_path / "edge.rtb"), "--json"]) == 0
    notes = json.loads(capsys.readouterr().out)["notes"]
    assert len(notes) == 1 and "across a class limit: R2 -> R3" in notes[0] and "N3" not in notes[0]
    assert main(["table", "R3", "--to", str(tmp_path / "r3.rtb"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["notes"] == []


@pytest.mark.parametrize("name", BUNDLED)
def test_classify_bundled_tables_fall_in_their_own_class(capsys, name):
    assert main(["classify", name, "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    system = name[0]
    assert d["classes"][system]["class"] == name
    assert d["nearest_bundled"][0]["table"] == name and d["nearest_bundled"][0]["distance"] == pytest.approx(0)
    # the class standard's Q0 by the same rule as the table's: a standard table is x1 of itself (user audit,
    # session 44: R1 was "x1.035", its Q0 by roadgonio's rule over the published 0.10 of the CIE's weights)
    assert d["classes"][system]["Q0_scale"] == pytest.approx(1.0, rel=1e-12)


def test_classify_q0_scale_is_the_ratio_of_q0s_by_one_rule_and_a_partial_table_gets_none(tmp_path, capsys):
    """A table 0.8 times C2 is "x0.8" of C2 in the C system, N3's (not bundled) standard is its published
    Q0, said so; R3's cells tan eps <= 2, beta <= 5 alone (S1 R3's) have a Q0 no standard's is comparable
    with: no scale, and the nearest table by S1 alone is R3 (user audit, session 44: "nearest R1", "x1.753")."""
    from roadgonio.surface.rtable import bundled_table
    c2 = bundled_table("C2")
    c2.with_values(0.8 * c2.r).write_csv(tmp_path / "dark.csv")
    assert main(["classify", str(tmp_path / "dark.csv"), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["classes"]["C"]["Q0_scale"] == pytest.approx(0.8, rel=1e-9)
    assert d["classes"]["N"]["standard_Q0"] == 0.07 and "published" in d["classes"]["N"]["standard_Q0_from"]
    t = bundled_table("R3")
    keep = (t.tan_eps[:, None] <= 2.0) & (t.beta_deg[None, :] <= 5.0)
    t.with_values(np.where(keep, t.r, np.nan)).write_csv(tmp_path / "corner.csv")
    assert main(["classify", str(tmp_path / "corner.csv"), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["S1"] == pytest.approx(t.s1(), rel=1e-12) and d["Q0"] is not None
    assert all(c["Q0_scale"] is None for c in d["classes"].values())
    assert d["nearest_bundled"][0]["table"] == "R3" and d["nearest_basis"].startswith("by S1 alone")
    assert main(["classify", str(tmp_path / "corner.csv")]) == 0
    out = capsys.readouterr().out
    assert "not comparable (note)" in out and "nearest bundled table by S1 alone" in out



def test_classify_refuses_a_zero_r_at_tan_2_and_prints_s1_on_its_side_of_a_limit(tmp_path, capsys):
    """(user audit, session 41) r(beta 0, tan eps 2) = 0 gave S1 = 0 and the classes R1 / C1 / N1, where fit
    refuses the same file (a 0 is not a reading); S1 = 0.4199966 printed as 0.420 beside R1 (whose limit is
    S1 < 0.42) with a margin of 0.000, and the JSON margin carried float noise."""
    from roadgonio.surface.rtable import bundled_table
    t = bundled_table("R3")
    i, j = int(np.argmin(np.abs(t.tan_eps - 2.0))), 0
    r = t.r.copy()
    r[i, j] = 0.0
    t.with_values(r).write_csv(tmp_path / "zero.csv")
    assert main(["classify", str(tmp_path / "zero.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "r(beta 0, tan eps 2) is 0" in err
    r = t.r.copy()
    r[i, j] = 0.419996599 * t.r[0, 0]
    t.with_values(r).write_csv(tmp_path / "edge.csv")
    assert main(["classify", str(tmp_path / "edge.csv")]) == 0
    out = capsys.readouterr().out
    assert "S1 = 0.419997" in out and "R system: R1 (S1 0.000 (3.4e-06) from the nearest class limit)" in out
    assert main(["classify", str(tmp_path / "edge.csv"), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["classes"]["R"]["S1_margin_to_limit"] == round(d["classes"]["R"]["S1_margin_to_limit"], 9) > 0

def test_output_error_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["road", "--table", "R3", "--out", str(blocker / "sub"), "--no-plots"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("roadgonio: error:") and "file/sub" in err and "\n" not in err
    assert f"expected a folder for the results, but {blocker} is a file" in err
    from roadgonio.errors import InputError
    from roadgonio.road import report
    out = tmp_path / "o"
    import errno
    from pathlib import Path
    real_write = Path.write_bytes
    written = []

    def fills_up(self, data):  # the disk fills up while the second file is staged
        if written:
            raise OSError(errno.ENOSPC, "No space left on device", str(self))
        written.append(self)
        return real_write(self, data)
    monkeypatch.setattr(Path, "write_bytes", fills_up)
    with pytest.raises(InputError, match="No space left") as info:
        report.write_together(out, {"a.txt": "1", "b.txt": "2", "c.txt": "3"})
    assert "b.txt" in str(info.value)
    assert list(out.iterdir()) == []   # no result and no staged temporary file left


def test_road_says_why_ti_is_missing_and_u_files_speak_of_u(tmp_path, capsys):
    """A blank cell the luminance needs (tan eps 5, beta 0): TI's note says why TI is missing (before:
    'initial values (MF = 1 ...)', the note of a computed TI). A negative value in a --u file says u
    (before: 'r must be >= 0')."""
    t = bundled_table("R3")
    r = t.r.copy()
    i = int(np.argmin(abs(t.tan_eps - 5.0)))
    r[i, 0] = np.nan
    t.with_values(r).write_csv(tmp_path / "hole.csv")
    assert main(["road", "--table", str(tmp_path / "hole.csv"), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["TI"] is None and "TI" in d["missing"]["metrics"]
    assert "needs L_av" in d["TI_note"] and "initial values" not in d["TI_note"]
    assert main(["road", "--table", str(tmp_path / "hole.csv")]) == 0
    assert "TI not computed: it needs L_av, which is unknown" in capsys.readouterr().out
    assert main(["road", "--table", "R3", "--json"]) == 0                 # a computed TI keeps its note
    assert json.loads(capsys.readouterr().out)["TI_note"] == "initial values (MF = 1 in L_v and L_av)"
    u = t.r * 0.01
    u[i, 0] = -u[i, 0]
    (tmp_path / "u.csv").write_text(t.with_values(np.abs(u)).to_csv_text().replace(
        f"\n5,{t.r[i, 0] * 0.01 * 1e4:g},", f"\n5,{-t.r[i, 0] * 0.01 * 1e4:g},"))
    assert ",-" in (tmp_path / "u.csv").read_text()
    rc = main(["road", "--table", "R3", "--u", str(tmp_path / "u.csv"), "--trials", "2000"])
    err = capsys.readouterr().err
    assert rc == 2 and "u must not be negative" in err and "r must" not in err


def test_road_and_compare_record_their_input_files(tmp_path, capsys):
    """road.json and compare.json name the files compared (absolute path, sha256 of the content),
    and a table read from a file is labelled by the file, with an RTB's stored name in brackets
    (before: the RTB's stored name 'R3' everywhere, no input file in either JSON)."""
    import hashlib
    t = bundled_table("R3")
    rtb = t.write_rtb(tmp_path / "measured.rtb")                   # stores the surface name R3
    csv_path = t.with_values(t.r * 1.1, name="x").write_csv(tmp_path / "corrected.csv")
    u_path = t.with_values(t.r * 0.01).write_csv(tmp_path / "corrected_u.csv")
    sha = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in (rtb, csv_path, u_path)}
    assert main(["road", "--table", str(rtb), "--table", str(csv_path), "--u", str(u_path), "--trials", "2000",
                 "--out", str(tmp_path / "road"), "--no-plots"]) == 0
    text = capsys.readouterr().out
    assert "corrected.csv vs measured.rtb (R3)" in text
    d = json.loads((tmp_path / "road" / "road.json").read_text())
    assert [s["table"] for s in d["tables"]] == ["measured.rtb (R3)", "corrected.csv"]
    got = {(r["argument"], r["path"], r["sha256"]) for r in d["provenance"]["inputs"]}
    assert got == {("table", str(rtb.absolute()), sha[rtb]), ("table", str(csv_path.absolute()), sha[csv_path]),
                   ("u", str(u_path.absolute()), sha[u_path])}
    assert main(["compare", str(rtb), str(csv_path), "--out", str(tmp_path / "cmp"), "--no-plots"]) == 0
    capsys.readouterr()
    c = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert (c["A"], c["B"]) == ("measured.rtb (R3)", "corrected.csv")
    assert [(r["argument"], r["path"], r["sha256"]) for r in c["provenance"]["inputs"]] == [
        ("a", str(rtb.absolute()), sha[rtb]), ("b", str(csv_path.absolute()), sha[csv_path])]
    assert main(["compare", "R3", str(csv_path), "--out", str(tmp_path / "cmp2"), "--no-plots"]) == 0
    c = json.loads((tmp_path / "cmp2" / "compare.json").read_text())
    assert c["A"] == "R3" and c["provenance"]["inputs"][0] == {"argument": "a", "name": "R3", "label": "R3"}   # a bundled name


def test_a_metric_with_its_u_is_printed_to_the_decimal_place_of_u():
    """u to two significant digits, the value and the interval to the same decimal place: three
    significant digits printed 'L_av 1.11 ± 0.0012 [1.11, 1.11]' (trial 9)."""
    from roadgonio.cli.road import _with_u
    assert _with_u("L_av", 1.10761, 0.0012, (1.10534, 1.10981)) == "L_av 1.1076 ± 0.0012 [1.1053, 1.1098]"
    assert _with_u("TI", 9.83, 2.3, (5.4, 14.2)) == "TI 9.8 ± 2.3 [5.4, 14.2]"
    assert _with_u("U_o", 0.557, 0.0, (0.557, 0.557)) == "U_o 0.557 (unchanged in every trial)"
    # audit 21: fully correlated cells leave U_o unchanged but for round-off, which was printed to 17 digits
    assert _with_u("U_o", 0.55664775358929475, 1.8e-16, (0.55664775358929430, 0.55664775358929497),
                   0.55664775358929464) == "U_o 0.5566 (unchanged in every trial)"
    assert _with_u("U_o", 0.5566, 1e-9, (0.5565, 0.5567)).startswith("U_o 0.5566000000 ± 1e-09")
    # trial 11 D5: the trials' mean beside the nominal value when they differ by more than u / 10
    assert _with_u("U_l", 0.6186, 0.088, (0.241, 0.584), 0.4187) == "U_l 0.619 nominal, MC 0.419 ± 0.088 [0.241, 0.584]"
    assert _with_u("L_av", 1.10761, 0.0012, (1.10534, 1.10981), 1.10770) == "L_av 1.1076 ± 0.0012 [1.1053, 1.1098]"
    assert _with_u("L_av", 1.10761, 0.0012, (1.10534, 1.10981), 1.10761 + 0.00013) == \
        "L_av 1.1076 nominal, MC 1.1077 ± 0.0012 [1.1053, 1.1098]"


def test_road_refuses_a_correlation_file_that_names_another_table(tmp_path, capsys):
    """corrected_corr.csv names its table on its first line, as corrected_u.csv's header does: road
    uses a named file with its own table, and stops in one line naming the file and both tables
    (exit 2, nothing written) when it goes with another: after a CSV whose header names another
    table, or after an RTB (no header to compare) whose u names another."""
    from roadgonio.surface.rtable import correlation_text
    t = bundled_table("R3")
    n = int(t.mask.sum())
    folders = {}
    for name in ("R3", "R2"):
        head = f"{name} corrected for the aperture effect (r / k_A; reference self; instrument portable)"
        f = folders[name] = tmp_path / name
        f.mkdir()
        t.with_values(t.r, source=head).write_csv(f / "corrected.csv")
        t.with_values(t.r, source=head).write_rtb(f / "corrected.rtb")
        t.with_values(0.03 * t.r, source="standard uncertainty of " + head).write_csv(f / "corrected_u.csv")
        (f / "corrected_corr.csv").write_text(correlation_text(t.cells, np.eye(n), table=head))
    r3, r2 = folders["R3"], folders["R2"]
    assert main(["road", "--table", str(r3 / "corrected.csv"), "--u", str(r3 / "corrected_u.csv"), "--trials", "500",
                 "--no-plots", "--json", "--out", str(tmp_path / "o")]) == 0
    d = json.loads(capsys.readouterr().out)["uncertainty"]
    assert d["correlation_file"] == str(r3 / "corrected_corr.csv") and "given" in d
    for table in ("corrected.csv", "corrected.rtb"):
        rc = main(["road", "--table", str(r3 / table), "--u", str(r3 / "corrected_u.csv"), "--corr",
                   str(r2 / "corrected_corr.csv"), "--trials", "500", "--no-plots", "--out", str(tmp_path / "bad")])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and "\n" not in err, err
        for w in (f"{r2 / 'corrected_corr.csv'}:1", "--corr", "correlation of the cells of 'R2 corrected",
                  "header says 'R3 corrected"):
            assert w in err, (w, err)
        assert not (tmp_path / "bad").exists()


def test_road_prints_the_correlation_cases_in_the_order_of_report_modes(monkeypatch, capsys):
    """The text gives the Monte Carlo's cases in the order of road.report.MODES (the order of
    road_metrics.csv and the picture's legend), which the CLI reads through api.ROAD_MODES: it had
    written the order out a second time, so a change of MODES left the terminal in the old order."""
    from roadgonio import api
    from roadgonio.cli.road import _print
    from roadgonio.road import report
    case = {"L_av": None, "U_o": None, "U_l": None, "TI": None, "P_meets_target": 0.5}
    summary = {"table": "T", "L_av": 1.0, "U_o": 0.5, "U_l": 0.6, "TI": 5.0, "R_EI": 0.7, "class": "M3",
               "U_l_per_lane": [0.6], "neglected_contributions": 0, "layout": "a layout", "written": [], "out": "o",
               "luminaire": {"name": "lum", "flux_lm": 1000.0},
               "uncertainty": {"file": "u.csv", "trials": 10, "target_class": "M3",
                               **{mode: dict(case) for mode in report.MODES}}}
    for order in (report.MODES, report.MODES[::-1], report.MODES[1:] + report.MODES[:1]):
        monkeypatch.setattr(report, "MODES", order)
        assert api.ROAD_MODES == order
        _print([summary])
        out = capsys.readouterr().out
        at = [out.index(f"  {mode:11}: ") for mode in order]
        assert at == sorted(at), out


def test_road_prints_the_monte_carlo_mean_beside_an_interval_that_excludes_the_nominal(tmp_path, capsys):
    """Trial 11 D5: with u = 30 % of r in independent cells the trials' U_o and U_l fall far below
    the nominal values (min/max ratios under noise), and the line read 'U_l 0.619 ± 0.088 [0.241,
    0.584]'. The line now says which is which (nominal, MC mean), road_metrics.csv has the means, and
    road_metrics.png draws the interval about the mean (about the nominal value it needed a negative
    error bar: a traceback)."""
    t = bundled_table("R3")
    t.with_values(0.3 * t.r).write_csv(tmp_path / "u.csv")
    out = tmp_path / "o"
    assert main(["road", "--table", "R3", "--u", str(tmp_path / "u.csv"), "--correlation", "independent",
                 "--trials", "500", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    d = json.loads((out / "road.json").read_text())["tables"][0]["uncertainty"]["independent"]
    for k in ("U_o", "U_l"):
        m = d[k]
        assert m["coverage_interval_95"][1] < m["nominal"]          # the case: the interval excludes the nominal
        assert f"{k} {m['nominal']:.3f} nominal, MC {m['mean']:.3f} ± " in text, text
    assert "(nominal: the table's own value; MC: the trials' mean" in text
    row = list(csv.DictReader((out / "road_metrics.csv").read_text().splitlines()))[-1]
    for k in ("L_av", "U_o", "U_l", "TI"):
        assert float(row[f"mean_{k}"]) == pytest.approx(d[k]["mean"], rel=1e-5)
    assert (out / "road_metrics.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_road_without_plots_removes_an_earlier_runs_pictures(tmp_path, capsys):
    """Trial 11 D4: `road --table R2 --no-plots` into the folder of a `road --table R3` kept R3's
    road_metrics.png and road_luminance.png beside R2's road.json. The pictures the new run does not
    write go (the OutputGroup's 'replaces', as render does); a file of the user's stays."""
    from roadgonio.road.report import ROAD_FILES
    out = tmp_path / "o"
    assert main(["road", "--table", "R3", "--out", str(out), "-q"]) == 0
    assert {p.name for p in out.iterdir()} == set(ROAD_FILES)
    (out / "notes.txt").write_text("mine")
    assert main(["road", "--table", "R2", "--out", str(out), "-q", "--no-plots"]) == 0
    assert {p.name for p in out.iterdir()} == {"road.json", "road_metrics.csv", "road_luminance.csv", "notes.txt"}
    assert json.loads((out / "road.json").read_text())["tables"][0]["table"] == "R2"


def test_road_refuses_an_r_table_as_its_u(tmp_path, capsys):
    """Trial 11 D3: `--u corrected.csv` (or corrected.rtb), tab completion's neighbours of
    corrected_u.csv, ran with u = 100 % of r and P(meets M3) = 0. An r-table given as u is refused in
    one line naming the file and what to give: the table file itself, an RTB (a format for r only),
    a CSV whose header says it is a corrected r-table (a copy elsewhere) and a bundled table."""
    t = bundled_table("R3")
    head = "R3 corrected for the aperture effect (r / k_A; reference self; instrument portable)"
    corrected = t.with_values(t.r, source=head).write_csv(tmp_path / "corrected.csv")
    t.with_values(t.r * 0.01, source="standard uncertainty of " + head).write_csv(tmp_path / "corrected_u.csv")
    t.write_rtb(tmp_path / "corrected.rtb")
    (tmp_path / "elsewhere").mkdir()
    copy = tmp_path / "elsewhere" / "table.csv"
    copy.write_bytes(corrected.read_bytes())
    base = ["road", "--trials", "200", "--no-plots", "--out", str(tmp_path / "bad")]
    for table, u, words in ((corrected, corrected, ["itself", "give corrected_u.csv beside it"]),
                            (corrected, tmp_path / "corrected.rtb", ["RTB", "give corrected_u.csv beside it"]),
                            ("R3", copy, ["is an r-table ('R3 corrected for the aperture effect", "corrected_u.csv"]),
                            (corrected, "R3", ["bundled r-table R3"])):
        rc = main(base + ["--table", str(table), "--u", str(u)])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and "\n" not in err and "--u" in err and "not a standard uncertainty" in err, err
        assert str(u) in err or f"'{u}'" in err, err
        for w in words:
            assert w in err, (w, err)
        assert not (tmp_path / "bad").exists()
    assert main(["road", "--trials", "200", "--no-plots", "--table", str(corrected), "--u",
                 str(tmp_path / "corrected_u.csv"), "--json"]) == 0
    assert "uncertainty" in json.loads(capsys.readouterr().out)


def test_road_says_how_many_trials_had_no_light(tmp_path, capsys):
    """Trial 11 D1 from the command line: fully correlated u = 60 % of r, so some trials clip every
    cell to 0; U_o, U_l and TI are still printed, with a note giving the number of trials without a
    value, and road_metrics.csv has that number (trials_without_value)."""
    t = bundled_table("R3")
    t.with_values(0.6 * t.r).write_csv(tmp_path / "u.csv")
    assert main(["road", "--table", "R3", "--u", str(tmp_path / "u.csv"), "--correlation", "correlated",
                 "--trials", "2000", "--seed", "3", "--no-plots", "--out", str(tmp_path / "o")]) == 0
    text = capsys.readouterr().out
    d = json.loads((tmp_path / "o" / "road.json").read_text())["tables"][0]["uncertainty"]["correlated"]
    dark = d["U_o"]["undefined_trials"]
    assert dark > 0 and "U_o 0.5" in text and "U_l 0.6" in text and "; TI " in text, text
    assert f"note: U_o, U_l and TI have no value in {dark} of 2000 trials" in text, text
    rows = list(csv.DictReader((tmp_path / "o" / "road_metrics.csv").read_text().splitlines()))
    assert rows[-1]["trials_without_value"] == str(dark) and rows[-1]["u_U_o"] != ""


def test_road_repeats_the_note_of_its_u_file(tmp_path, capsys):
    """Trial 11 D7: correct's "the data reject the eq. 4 fit" did not reach road --u. The note
    corrected_u.csv's header carries (a 'note:' line after the line naming the table) is printed with
    the Monte Carlo and kept in road.json (uncertainty.notes); a u file without one has none."""
    t = bundled_table("R3")
    head = "R3 corrected for the aperture effect (r / k_A; reference self; instrument portable)"
    note = "the data reject the eq. 4 fit (Birge ratio 17.10, chi^2 113189 on 387 degrees of freedom)"
    t.with_values(t.r, source=head).write_csv(tmp_path / "corrected.csv")
    t.with_values(t.r * 0.01, source=f"standard uncertainty of {head}\nnote: {note}").write_csv(tmp_path / "u.csv")
    assert f"# note: {note}" in (tmp_path / "u.csv").read_text()
    t.with_values(t.r * 0.01, source=f"standard uncertainty of {head}").write_csv(tmp_path / "plain_u.csv")
    for u, said in (("u.csv", [note]), ("plain_u.csv", [])):
        assert main(["road", "--table", str(tmp_path / "corrected.csv"), "--u", str(tmp_path / u), "--trials", "200",
                     "--no-plots", "--out", str(tmp_path / u[:-4])]) == 0
        text = capsys.readouterr().out
        assert (f"note in {tmp_path / u}: {note}" in text) is bool(said), text
        d = json.loads((tmp_path / u[:-4] / "road.json").read_text())["tables"][0]["uncertainty"]
        assert d["notes"] == said


def test_road_takes_the_cells_correlation_from_correct(tmp_path, capsys):
    """Trial 11 D6: correct writes the cells' correlation (corrected_corr.csv) beside corrected_u.csv,
    road could not read it. In a correct folder road takes it (case 'given', said in the terminal and
    road.json); --corr gives it explicitly (here another file: the one used is the one named);
    --correlation both keeps the two limiting cases; a --corr the chosen cases do not use, or one
    before any --table, is refused in one line; a u file not named corrected_u.csv has no
    correlation found for it."""
    from roadgonio.surface.rtable import correlation_text
    t = bundled_table("R3")
    folder = tmp_path / "correct"
    folder.mkdir()
    head = "R3 corrected for the aperture effect (r / k_A; reference self; instrument portable)"
    table = t.with_values(t.r, source=head).write_csv(folder / "corrected.csv")
    u = t.with_values(0.03 * t.r, source="standard uncertainty of " + head).write_csv(folder / "corrected_u.csv")
    n = int(t.mask.sum())
    (folder / "corrected_corr.csv").write_text(correlation_text(t.cells, np.ones((n, n))))
    (tmp_path / "indep_corr.csv").write_text(correlation_text(t.cells, np.eye(n)))
    base = ["road", "--table", str(table), "--u", str(u), "--trials", "500", "--no-plots"]

    def run(*extra, out="o"):
        rc = main(base + list(extra) + ["--out", str(tmp_path / out)])
        return rc, capsys.readouterr()

    rc, cap = run()
    assert rc == 0, cap.err
    assert f"cells' correlation from {folder / 'corrected_corr.csv'} (beside the u file)" in cap.out, cap.out
    d = json.loads((tmp_path / "o" / "road.json").read_text())["tables"][0]["uncertainty"]
    assert "given" in d and "independent" not in d and "correlated" not in d
    assert d["correlation_file"] == str(folder / "corrected_corr.csv") and d["correlation_found_beside_u"] is True
    assert d["given"]["U_o"]["u"] < 1e-9                         # all ones: the fully correlated case
    rc, cap = run("--corr", str(tmp_path / "indep_corr.csv"), out="o2")
    d = json.loads((tmp_path / "o2" / "road.json").read_text())["tables"][0]["uncertainty"]
    assert rc == 0 and d["correlation_file"] == str(tmp_path / "indep_corr.csv") and not d["correlation_found_beside_u"]
    assert d["given"]["U_o"]["u"] > 1e-3                          # the identity: independent cells
    rc, cap = run("--correlation", "both", out="o3")
    d = json.loads((tmp_path / "o3" / "road.json").read_text())["tables"][0]["uncertainty"]
    assert rc == 0 and set(d) >= {"independent", "correlated"} and "given" not in d and d.get("correlation_file") is None
    rows = list(csv.DictReader((tmp_path / "o" / "road_metrics.csv").read_text().splitlines()))
    assert [r["correlation"] for r in rows] == ["given"]
    for extra, words in ((["--corr", str(tmp_path / "indep_corr.csv"), "--correlation", "both"],
                         ["--corr", "indep_corr.csv", "not used with correlation 'both'"]),
                         (["--corr", str(tmp_path / "nothere.csv")], ["nothere.csv", "no such correlation file"])):
        rc, cap = run(*extra, out="bad")
        err = cap.err.strip()
        assert rc == 2 and "\n" not in err, err
        for w in words:
            assert w in err, (w, err)
        assert not (tmp_path / "bad").exists()
    rc = main(["road", "--corr", str(tmp_path / "indep_corr.csv"), "--table", "R3", "--out", str(tmp_path / "bad")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "--corr" in err and "comes before any --table" in err, err
    other = tmp_path / "u_elsewhere.csv"
    other.write_bytes(u.read_bytes())
    assert main(["road", "--table", str(table), "--u", str(other), "--trials", "500", "--no-plots", "--json",
                 "--out", str(tmp_path / "o4")]) == 0
    d = json.loads(capsys.readouterr().out)["uncertainty"]
    assert {"independent", "correlated"} <= set(d) and "given" not in d


@pytest.mark.parametrize("option", [["--trials", "500"], ["--seed", "5"], ["--correlation", "independent"],
                                    ["--class", "M1"]])
def test_monte_carlo_options_without_u_are_errors(tmp_path, capsys, option):
    """(audit 21, 3) `road --table r3.csv --trials 100 --class M1 --seed 5 --correlation independent`
    ran without a word: with no --u there is no Monte Carlo, and nothing used them."""
    rc = main(["road", "--table", "R3", *option, "--no-plots", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and option[0] in err and "--u" in err, err
    assert not (tmp_path / "o").exists()


def test_the_default_folder_is_named_by_the_files(tmp_path, capsys):
    """User audit, session 29: an RTB stores its surface's name, so `road --table measured.rtb --table
    corrected.csv` wrote to out/road-R3-corrected, the folder of `--table R3 --table corrected.csv`, and the
    second run replaced the first's results. A table from a file names the folder by the file."""
    t = bundled_table("R3")
    rtb = t.write_rtb(tmp_path / "measured.rtb")                   # stores the surface name R3
    t.write_csv(tmp_path / "corrected.csv")
    assert main(["road", "--table", str(rtb), "--table", str(tmp_path / "corrected.csv"), "--no-plots"]) == 0
    assert main(["road", "--table", "R3", "--table", str(tmp_path / "corrected.csv"), "--no-plots"]) == 0
    made = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert made == ["road-R3-corrected", "road-measured-corrected"], made
