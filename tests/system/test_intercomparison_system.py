"""roadgonio intercompare end to end: the command's one-line error, two Dask workers against the
in-process run, the output files."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from helpers_intercomparison import coll, make_study, write_collimated
from roadgonio.intercomparison.run import run_study


@pytest.fixture()
def collimated(tmp_path):
    return write_collimated(tmp_path)


def test_cli_bad_study_exits_2_with_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[study]\nsurface = "R3"\n[[participant]]\nname = "A"\ninstrument = "lab"\nnoise = 1\n')
    r = subprocess.run([sys.executable, "-m", "roadgonio", "intercompare", str(bad), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "participant[1].noise" in lines[0] and str(bad) in lines[0]


@pytest.mark.timeout(600)
def test_two_dask_workers_give_the_numbers_of_the_in_process_run_and_the_outputs(tmp_path, collimated):
    parts = [coll("A", 0.01), coll("B", 0.02, calibration_u_rel=0.005), coll("C", 0.01)]
    shared = [{"name": "tile", "kind": "reference_tile", "u_rel": 0.004, "participants": ["A", "C"]}]
    here = run_study(make_study(tmp_path, parts, shared, realisations=5), workers=0, progress=False, plots=False).dataset
    out = tmp_path / "dask"
    dask = run_study(make_study(tmp_path, parts, shared, realisations=5), out, workers=2, progress=False).dataset
    for v in ("r_reported", "u_stated", "d", "E_n", "reference_value"):
        assert np.array_equal(here[v].values, dask[v].values, equal_nan=True), v
    names = {p.name for p in out.iterdir()}
    assert {"intercompare.nc", "intercompare.csv", "sensitivity.csv", "validation.csv", "intercompare.json",
            "en_map_declared.png", "specular_row.png", "sensitivity.png", "compatibility.png"} <= names
    head = (out / "intercompare.csv").read_text().splitlines()[0].split(",")
    assert {"scenario", "participant", "share_En_le_1_weighted_mean", "birge_ratio_median"} <= set(head)
    prov = json.loads((out / "intercompare.json").read_text())["provenance"]
    assert prov["cluster"]["workers"] == 2 and prov["versions"]["roadgonio"]
    from roadgonio.intercomparison.outputs import read_intercomparison
    nc = read_intercomparison(out / "intercompare.nc")
    assert nc["truth"].attrs["units"] == "sr-1" and nc["E_n"].attrs["units"] == "1"
    assert set(nc["E_n"].dims) == {"scenario", "reference", "participant", "realisation", "tan_eps", "beta"}
