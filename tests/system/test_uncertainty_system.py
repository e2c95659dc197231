"""`roadgonio uncertainty` from the command line (a subprocess each)."""
from __future__ import annotations

import math
import subprocess
import sys

import pytest
from tolerances import N_SIGMA


@pytest.mark.parametrize("args,words", [
    (["--sigma", "alpha_deg=-1"], "--sigma alpha_deg"),
    (["--sigma", "foo=1"], "unknown key"),
    (["--sigma", "/nonexistent/s.toml"], "no such SPEC file"),
])
def test_cli_bad_input_is_one_line(tmp_path, args, words):
    p = subprocess.run([sys.executable, "-m", "roadgonio", "uncertainty", "--instrument", "portable",
                        "--sample", "lambert", "--no-aperture", "--trials", "200", "--out", str(tmp_path)] + args,
                       capture_output=True, text=True)
    assert p.returncode == 2 and words in p.stderr and "Traceback" not in p.stderr


def test_cli_runs_lambert(tmp_path):
    p = subprocess.run([sys.executable, "-m", "roadgonio", "uncertainty", "--instrument", "lab", "--sample", "lambert",
                        "--sigma", "eps_deg=0.05,source_distance_m=0.005", "--trials", "2000", "--no-aperture",
                        "--no-plots", "--out", str(tmp_path), "--json"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    import json
    d = json.loads(p.stdout)
    assert d["trials"] == 2000 and set(d["cases"]) == {"no_aperture"}
    # Lambert, 5 mm on 5 m: u(r)/r at eps = 0 is 2 u(D)/D = 0.2 % (first order; the eps error is
    # second order there), to the MC standard error of u (1/sqrt(2M))
    rows = [l.split(",") for l in (tmp_path / "cells.csv").read_text().splitlines() if not l.startswith("#")]
    row = next(r for r in rows[1:] if r[0] == "no_aperture" and r[1] == "0" and r[2] == "0")
    u_rel = float(row[rows[0].index("u_rel")])
    assert abs(u_rel / 0.002 - 1) < N_SIGMA / math.sqrt(2 * 2000) + 1e-3


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_cli_mitsuba_tables_on_a_local_cluster(tmp_path):
    """`uncertainty --workers 1` with the default Mitsuba backend, in a fresh process: the first
    exact table is computed in the calling process (its pass plan goes with the others), which had
    no Mitsuba variant selected there (trial 9: every such run stopped with 'no Mitsuba variant is
    selected', exit 2). The API's identity with the in-process run is the slow test of
    test_design_cluster.py; this one is the command as a user runs it."""
    import json
    p = subprocess.run([sys.executable, "-m", "roadgonio", "uncertainty", "--instrument", "portable", "--sample",
                        "R3", "--sigma", "alpha_deg=0.01", "--trials", "500", "--surrogate", "star", "--validation",
                        "1", "--rel-se", "3e-3", "--workers", "1", "--no-plots", "--out", str(tmp_path), "--json"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    d = json.loads((tmp_path / "uncertainty.json").read_text())
    assert any("Dask" in n for n in d["provenance"]["notes"]), d["provenance"]["notes"]
    assert d["surrogate"]["exact_evaluations"] > 0


def test_a_coverage_interval_needs_trials_beyond_its_ends(tmp_path, capsys):
    """(audit 22) 100 trials at --coverage 0.999 printed the trials' minimum and maximum (about a
    98 % interval) labelled 99.9 %. M (1 - p) must be at least MIN_TAIL_TRIALS: one line, exit 2,
    nothing written; at the limit the run goes on."""
    from roadgonio.cli import main
    from roadgonio.uncertainty.run import MIN_TAIL_TRIALS
    base = ["uncertainty", "--instrument", "portable", "--sample", "R3", "--sigma", "alpha_deg=0.01", "--no-aperture",
            "--no-plots"]
    rc = main([*base, "--trials", "100", "--coverage", "0.999", "--out", str(tmp_path / "a")])
    err = capsys.readouterr().err
    assert rc == 2 and "expected at least 10000 trials" in err and err.count("\n") == 1
    assert not (tmp_path / "a").exists()
    # the least number is said once (user audit, session 29: --trials 1 said 'at least 100', then
    # --trials 100 said 'at least 200')
    for n in (1, 100):
        rc = main([*base, "--trials", str(n), "--out", str(tmp_path / "c")])
        err = capsys.readouterr().err
        assert rc == 2 and f"expected at least {int(MIN_TAIL_TRIALS / 0.05)} trials for a 95 % coverage" in err, err
    assert main([*base, "--trials", str(int(MIN_TAIL_TRIALS / 0.05)), "--coverage", "0.95", "--out",
                 str(tmp_path / "b"), "-q"]) == 0


def test_an_adaptive_run_stopped_at_its_cap_exits_3(tmp_path, capsys):
    """User audit: `uncertainty --adaptive` exited 0 when it stopped at --max-trials without
    converging, so a script took it for a result to the digits asked. It exits 3 (inconclusive, as
    validate does) with one line on stderr naming the target and the cap, the results written; a run
    that converges exits 0 and says nothing on stderr."""
    from roadgonio.cli import main
    base = ["uncertainty", "--instrument", "lab", "--sample", "lambert", "--no-aperture", "--no-plots", "-q",
            "--sigma", "alpha_deg=0.01,eps_deg=0.02,source_distance_m=0.002", "--adaptive", "--batch", "2000",
            "--seed", "3"]
    rc = main([*base, "--digits", "3", "--max-trials", "6000", "--out", str(tmp_path / "capped")])
    err = capsys.readouterr().err
    assert rc == 3, err
    assert err.count("\n") == 1 and err.startswith("roadgonio uncertainty: NOT CONVERGED"), err
    assert "cap of 6000 trials" in err and "stable to 3 significant digits" in err, err
    assert {"uncertainty.json", "cells.csv"} <= {f.name for f in (tmp_path / "capped").iterdir()}
    rc = main([*base, "--digits", "1", "--max-trials", "40000", "--out", str(tmp_path / "converged")])
    err = capsys.readouterr().err
    assert rc == 0 and err == "", err


def test_an_output_the_errors_do_not_change_is_drawn_in_words(tmp_path, capsys):
    """(user audit, session 41) a source-distance error alone scales r(0, 0) and r(2, 0) alike, so S1's
    trials spread over round-off (1e-16), where the histogram's 80 bins cannot be drawn: the run crashed
    after all its work (exit 1) and wrote nothing. Now its results are written and the S1 panel says
    why it has no histogram."""
    from roadgonio.cli import main
    out = tmp_path / "u"
    rc = main(["uncertainty", "--instrument", "portable", "--sample", "R3", "--sigma", "source_distance_m=0.002",
               "--trials", "1000", "--no-aperture", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and "S1: 1.116, not changed by these errors" in text
    assert {"q0_s1_hist.png", "uncertainty.json", "cells.csv"} <= {p.name for p in out.iterdir()}
    # the Monte Carlo's own standard error of u is given (session 41): for Q0, moved by the distance,
    # about u / sqrt(2 M), its estimate from 20 batches within 16 % x 4 of that
    import json
    q0 = json.loads((out / "uncertainty.json").read_text())["cases"]["no_aperture"]["Q0"]
    assert abs(q0["mc_u_se"] / (q0["u"] / math.sqrt(2 * 999)) - 1.0) <= N_SIGMA * 0.162


def test_advice_after_an_adaptive_run_names_what_can_still_be_done(tmp_path, capsys):
    """(user audit, session 41) after an adaptive run at --digits 1 with cells not judged, the advice
    was 'more --trials, --adaptive, or fewer --digits': --adaptive was on, --trials is refused with it
    and 1 digit is the fewest. And a case option with --no-aperture was refused in the API's words
    ('aperture=False'); the command line's own option is named."""
    from roadgonio.cli import main
    rc = main(["uncertainty", "--instrument", "portable", "--sample", "R3", "--sigma", "alpha_deg=0.05", "--no-aperture",
               "--adaptive", "--digits", "1", "--no-plots", "--out", str(tmp_path / "a")])
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "not judged:" in ln]
    assert rc == 0 and lines, "expected cells not judged at 1 digit"
    assert all("--adaptive, or" not in ln and "--digits" not in ln and "a longer run without --adaptive" in ln for ln in lines)
    rc = main(["uncertainty", "--instrument", "portable", "--sample", "R3", "--sigma", "alpha_deg=0.05", "--no-aperture",
               "--rel-se", "0.001", "--out", str(tmp_path / "b")])
    err = capsys.readouterr().err
    assert rc == 2 and "--no-aperture skips" in err and "aperture=False" not in err
