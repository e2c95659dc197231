"""``roadgonio ka`` as a user runs it: a full table, resuming it, one cell as JSON, clean errors."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from roadgonio.cli import main
from roadgonio.engines.runner import JOURNAL
from roadgonio.surface.rtable import read_table

#: The quadrature backend integrates a Lambertian sample exactly up to round-off.
LAMBERT_TOL = 1e-9


def test_full_table_then_resume(tmp_path, capsys):
    out = tmp_path / "ka"
    args = ["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "quadrature", "--out", str(out)]
    assert main(args) == 0
    ka = read_table(out / "ka.csv").r * 1e4            # k_A files are unscaled; the reader divides by 1e4
    assert ka.shape == (29, 20) and np.isfinite(ka).all()
    assert np.max(np.abs(ka - 1.0)) < LAMBERT_TOL       # a Lambertian sample: k_A = 1 for any instrument
    meta = json.loads((out / "ka.json").read_text())
    assert meta["backend"] == "quadrature" and meta["summary"]["cells"] == 580
    assert meta["instrument"]["detector"]["field_half_angle_deg"] == 0.05
    lines = (out / JOURNAL).read_text().splitlines()
    assert len(lines) == 581
    # drop the last 80 cells from the journal as if interrupted; the same command resumes
    (out / JOURNAL).write_text("\n".join(lines[:-80]) + "\n")
    capsys.readouterr()
    assert main(args + ["--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["resumed_cells"] == 500 and summary["cells"] == 580


def test_cells_table_needs_a_table_sample(tmp_path):
    out = tmp_path / "ka"
    fit = tmp_path / "m.json"
    fit.write_text(json.dumps({"variant": "power", "params": {"k_diff": 0.03, "k_phong": 0.2, "n_phong": 30}}))
    # --cells table needs an r-table sample
    assert main(["ka", "--instrument", "lab", "--sample", str(fit), "--cells", "table", "--backend",
                 "quadrature", "--out", str(out)]) == 2


def test_single_cell_json_keys(capsys):
    assert main(["ka", "--instrument", "portable", "--sample", "lambert", "--backend", "quadrature",
                 "--tan-eps", "12", "--beta", "0", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert set(d) == {"k_a", "se", "se_dof", "error_bound", "confidence_bound", "confidence_level", "converged",
                      "samples", "seconds", "k_a_direct", "k_a_direct_se", "stray_fraction", "stray_fraction_se"}
    assert d["se_dof"] is None                  # a deterministic backend: no SE, no degrees of freedom (null)
    assert abs(d["k_a"] - 1.0) < LAMBERT_TOL and d["samples"] > 0
    # no stray light in this backend: the direct light is everything, the stray fraction 0 exactly
    assert d["k_a_direct"] == d["k_a"] and d["stray_fraction"] == 0.0 and d["stray_fraction_se"] == 0.0


def test_a_confidence_bound_comes_with_its_level(tmp_path, capsys):
    """The one-cell JSON gave confidence_bound without confidence_level, and the header of
    ka_confidence_bound.csv did not state the level."""
    args = ["ka", "--instrument", "portable", "--sample", "R3", "--backend", "reference", "--accuracy", "fast"]
    out = tmp_path / "kref"
    assert main(args + ["--cells", "12:0,5:0", "--out", str(out)]) == 0
    level = json.loads((out / "ka.json").read_text())["settings"]["confidence"]
    assert 0.5 < level < 1
    head = (out / "ka_confidence_bound.csv").read_text().splitlines()[0]
    assert head.startswith("#") and f"confidence level {level:g}" in head
    capsys.readouterr()
    assert main(args + ["--tan-eps", "12", "--beta", "0", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["confidence_level"] == level and d["confidence_bound"] > d["se"] > 0
    # the SE of 10 replicates has 9 degrees of freedom, in the JSON and in ka.nc
    assert d["se_dof"] == 9.0
    import xarray as xr
    with xr.open_dataset(out / "ka.nc") as ds:
        assert float(ds.se_dof.sel(tan_eps=12.0, beta=0.0)) == 9.0 and "Student" in ds.se_dof.attrs["description"]


@pytest.mark.parametrize("extra, needle", [
    (["--tan-eps", "2"], "--beta"),
    (["--tan-eps", "-1", "--beta", "0"], "--tan-eps"),
    (["--tan-eps", "1", "--beta", "200"], "--beta"),
    (["--rel-se", "2", "--tan-eps", "1", "--beta", "0"], "--rel-se"),
])
def test_bad_options_are_one_line_errors(capsys, extra, needle):
    assert main(["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "quadrature"] + extra) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("roadgonio: error:") and needle in err and "\n" not in err


def test_footprint_off_the_sample_is_an_error_not_a_number(tmp_path):
    bad = tmp_path / "small.toml"
    bad.write_text((Path(__file__).resolve().parents[2] / "scenes" / "portable.toml").read_text().replace("size_x_m = 1.0", "size_x_m = 0.3"))
    r = subprocess.run([sys.executable, "-m", "roadgonio", "ka", "--instrument", str(bad), "--sample", "lambert",
                        "--backend", "quadrature", "--tan-eps", "1", "--beta", "0"], capture_output=True, text=True)
    assert r.returncode == 2 and "leaves the sample" in r.stderr and "Traceback" not in r.stderr


def test_a_subset_into_a_folder_with_a_larger_table_says_so_and_keeps_it(tmp_path, capsys):
    """Trial 7, defect 9: `ka --cells SUBSET` into a folder holding a larger table of the same run
    replaced ka.csv with the subset; the files now keep the folder's table and the summary says
    how many cells were asked and how many the table holds. api.ka_table returns what ka.nc holds."""
    from roadgonio import api
    out = tmp_path / "res"
    base = ["ka", "--instrument", "portable", "--sample", "R3", "--backend", "quadrature", "--accuracy", "fast",
            "--out", str(out)]
    assert main(base + ["--cells", "12:0,4:0,4:2,8:0"]) == 0
    capsys.readouterr()
    assert main(base + ["--cells", "12:0,4:0"]) == 0
    said = capsys.readouterr().out
    assert "2 cells asked (2 resumed); the folder's table holds 4 cells" in said, said
    assert int(np.isfinite(read_table(out / "ka.csv").r).sum()) == 4
    ds = api.ka_table("portable", "R3", backend="quadrature", accuracy="fast", cells="12:0", out=out, plot=False)
    assert int(np.isfinite(ds["k_a"].values).sum()) == 4
    assert (ds.attrs["cells_asked"], ds.attrs["resumed_cells"], ds.attrs["cells_computed"]) == (1, 1, 4)


def test_a_cell_the_renderer_cannot_measure_is_said_and_exits_3(mi, tmp_path, capsys):
    """(user audit, session 44) a Phong lobe of exponent 1e5 at tan eps 12, beta 2 seen by a point detector
    underflows the float32 renderer: the table of that one cell crashed the summary (a TypeError formatting
    a k_A range of no cell, exit 1, after the files were written); with a measured cell beside it the
    reason was in the journal alone; one cell under -q exited 0 with k_A NaN. Now the summary says which
    cell and why, ka.json has it, and the exit status is 3 (results written, a cell not measured)."""
    from roadgonio.instrument.config import load_instrument
    d = load_instrument("portable").to_dict()
    d["detector"].update(pupil_radius_m=0.0, field_half_angle_deg=0.0)
    d["instrument"]["name"] = "pointdet"
    from roadgonio.design.outputs import toml_text
    (tmp_path / "pointdet.toml").write_text(toml_text(d))
    (tmp_path / "lobe.json").write_text(json.dumps({"variant": "power", "params": {"k_phong": 1.0, "n_phong": 1e5}}))
    argv = ["ka", "--instrument", str(tmp_path / "pointdet.toml"), "--sample", str(tmp_path / "lobe.json")]
    assert main(argv + ["--cells", "12:2", "--out", str(tmp_path / "t")]) == 3
    out = capsys.readouterr().out
    assert "no cell measured" in out and "1 cell NOT measured" in out and "tan eps = 12, beta = 2: " in out
    assert "quadrature or reference" in out
    summary = json.loads((tmp_path / "t" / "ka.json").read_text())["summary"]
    assert summary["not_measured"] == 1 and summary["k_a_min"] is None
    # the same command again resumes the cell as it was (session 45: its journal was refused as
    # corrupt, exit 2, since strict JSON wrote its NaN as null)
    assert main(argv + ["--cells", "12:2", "--out", str(tmp_path / "t")]) == 3
    out = capsys.readouterr().out
    assert "1 cell (1 resumed), no cell measured" in out and "1 cell NOT measured" in out, out
    assert main(argv + ["--tan-eps", "12", "--beta", "2", "-q"]) == 3
    assert capsys.readouterr().out == ""
