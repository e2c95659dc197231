"""`roadgonio design` and `roadgonio ka` from the command line."""
from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from roadgonio.cli import main
from tolerances import z_family


def _ka_cells(path):
    """The cells of a k_A journal (ka_cells.jsonl) by (tan eps, beta)."""
    lines = path.read_text().splitlines()[1:]
    return {(d["tan_eps"], d["beta_deg"]): d for d in map(json.loads, lines)}


def test_best_design_recomputed_with_ka_matches_its_row(mi, tmp_path, capsys):
    out = tmp_path / "d"
    cells = "12:0,8:2,4:0,1:45"
    rc = main(["design", "--instrument", "portable", "--vary", "source.radius_m=0.015:0.035:3",
               "--vary", "detector.pupil_radius_m=0.003,0.005", "--sample", "R3", "--cells", cells,
               "--accuracy", "fast", "--tolerance", "15%", "--workers", "0", "--seed", "3", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "best:" in text and "design points/hour" in text
    assert "cluster" not in text           # computed in this process (trial 8: "after the cluster's start")
    from roadgonio.design.outputs import read_design
    ds = read_design(out / "design.nc")
    best = int(ds.attrs["best_index"])
    assert best >= 0
    rows = list(csv.DictReader((out / "design.csv").read_text().splitlines()))
    row = rows[best]
    assert row["feasible"] == "true"
    k_row = ds["k_a"].values.reshape(-1, 1, *ds["k_a"].shape[-2:])[best, 0]
    se_row = ds["se"].values.reshape(-1, 1, *ds["se"].shape[-2:])[best, 0]
    tans, betas = ds["tan_eps"].values, ds["beta"].values
    # an independent run (another seed) agrees within z combined SE; the design's own seed repeats it exactly
    for seed, exact in ((12345, False), (int(row["seed"]), True)):
        ka_out = tmp_path / f"ka{seed}"
        assert main(["ka", "--instrument", str(out / "best.toml"), "--sample", "R3", "--cells", cells,
                     "--accuracy", "fast", "--seed", str(seed), "--out", str(ka_out)]) == 0
        got = _ka_cells(ka_out / "ka_cells.jsonl")
        assert len(got) == 4
        for (t, b), c in got.items():
            i, j = int(np.argmin(abs(tans - t))), int(np.argmin(abs(betas - b)))
            if exact:
                assert c["k_a"] == k_row[i, j] and c["se"] == se_row[i, j]
            else:
                assert abs(c["k_a"] - k_row[i, j]) <= z_family(len(got)) * math.hypot(c["se"], se_row[i, j]), (t, b)
    dev = max(abs(c["k_a"] - 1) for c in got.values())
    assert dev == pytest.approx(float(row["max_abs_dev"]), rel=1e-12, abs=0.0)
    header = (out / "best.toml").read_text().splitlines()[:4]
    assert any(f"--seed {row['seed']}" in h for h in header)
    # the command to reproduce the row is complete: the sample, no placeholder (trial 8)
    assert any("--sample R3 " in h for h in header) and not any("SAMPLE" in h for h in header)
    assert any(f"--accuracy fast --cells {cells} " in h for h in header)        # audit 22: --cells was left out


def test_best_toml_reproduces_a_row_computed_with_rel_se(tmp_path, capsys):
    """(audit 22) a design run with --rel-se printed a reproduce line without it: the command gave
    another k_A (2.4 of its own SEs away). The line carries the tolerance and the cells, and running
    it gives the row's k_A."""
    out = tmp_path / "d"
    assert main(["design", "--instrument", "portable", "--sample", "R3", "--backend", "quadrature", "--cells", "4:0",
                 "--vary", "source.radius_m=0.004", "--rel-se", "2e-4", "--tolerance", "20%", "--workers", "0", "--out", str(out),
                 "-q"]) == 0
    line = next(h for h in (out / "best.toml").read_text().splitlines() if "Reproduce its row" in h)
    cmd = line.split("Reproduce its row: roadgonio ")[1].split(" (the sample")[0].split()
    assert "--rel-se" in cmd and cmd[cmd.index("--rel-se") + 1] == "0.0002" and "--cells" in cmd
    assert "--seed" not in cmd and line.endswith("(the sample of its worst cell; the study's samples: R3)")
    cmd[cmd.index("best.toml")] = str(out / "best.toml")
    assert main([*cmd, "--out", str(tmp_path / "k"), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    import xarray as xr
    with xr.open_dataset(out / "design.nc") as ds:
        assert got["k_a_min"] == float(ds["k_a"].values.ravel()[np.isfinite(ds["k_a"].values.ravel())][0])  # one cell


def test_best_toml_reproduces_a_row_of_cells_off_the_grid(tmp_path, capsys):
    """(audit 27) design takes cells off the CIE grid, ka --cells does not: the reproduce line of
    such a design was refused (exit 2). It gives the worst cell by --tan-eps/--beta, which runs and
    gives the row's k_A there."""
    out = tmp_path / "d"
    assert main(["design", "--instrument", "portable", "--sample", "R3", "--backend", "quadrature",
                 "--cells", "3.3:7,12:0", "--vary", "source.radius_m=0.004", "--accuracy", "fast", "--tolerance", "20%",
                 "--workers", "0", "--out", str(out), "-q"]) == 0
    line = next(h for h in (out / "best.toml").read_text().splitlines() if "Reproduce its row" in h)
    cmd = line.split("Reproduce its row: roadgonio ")[1].split(" (the sample")[0].split()
    assert "--cells" not in cmd and "--tan-eps" in cmd and "--beta" in cmd and "not all on the CIE grid" in line
    cmd[cmd.index("best.toml")] = str(out / "best.toml")
    assert main([*cmd, "--out", str(tmp_path / "k"), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    import xarray as xr
    with xr.open_dataset(out / "design.nc") as ds:
        assert abs(got["k_a"] - 1.0) == pytest.approx(float(ds["max_abs_dev"].values.ravel()[0]), rel=1e-12)


@pytest.mark.parametrize("args, words", [
    (["--vary", "source.radius=1:2:3"], "unknown instrument key"),
    (["--vary", "source.radius_m=0.01:0.02:3", "--tolerance", "5"], "--tolerance"),
    (["--vary", "source.radius_m=0.01:0.02:3", "--cells", "12:0,x"], "--cells"),
    (["--vary", "source.radius_m=0.01:0.02:3", "--scheduler", "nonsense"], "--scheduler"),
])
def test_design_cli_bad_input_is_one_line(tmp_path, capsys, args, words):
    rc = main(["design", "--instrument", "portable", "--sample", "R3", "--backend", "quadrature",
               "--out", str(tmp_path), *args])
    err = capsys.readouterr().err
    assert rc == 2 and words in err and err.count("\n") == 1 and "Traceback" not in err


def test_ka_cells_list(mi, tmp_path, capsys):
    out = tmp_path / "ka"
    assert main(["ka", "--instrument", "portable", "--sample", "R3", "--backend", "quadrature", "--accuracy", "fast",
                 "--cells", "12:0,4:2", "--out", str(out), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["cells"] == 2 and set(_ka_cells(out / "ka_cells.jsonl")) == {(12.0, 0.0), (4.0, 2.0)}
    assert main(["ka", "--instrument", "portable", "--sample", "R3", "--cells", "12:0,4", "--out", str(out)]) == 2
    assert "--cells" in capsys.readouterr().err


def test_a_design_rerun_without_pictures_removes_the_earlier_pictures(tmp_path, capsys):
    """(audit 22) design --no-plots (or a run that draws fewer pictures) into an earlier run's
    folder left its pareto.png and tolerance_map.png beside the new best.toml; the user's files stay."""
    out = tmp_path / "d"
    base = ["design", "--instrument", "portable", "--sample", "R3", "--backend", "quadrature", "--cells", "4:0",
            "--vary", "source.radius_m=0.004,0.006", "--tolerance", "20%", "--workers", "0", "--out", str(out), "-q"]
    assert main(base) == 0
    assert (out / "pareto.png").exists() and (out / "best.toml").exists()
    (out / "notes.txt").write_text("mine")
    assert main([*base, "--no-plots", "--tolerance", "1%"]) == 0
    assert not list(out.glob("*.png")) and not (out / "best.toml").exists()     # no design meets 1 %
    assert (out / "notes.txt").read_text() == "mine" and (out / "design.csv").exists()
