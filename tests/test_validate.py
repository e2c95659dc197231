"""roadgonio validate: comparison logic, outputs and exit status (against the float64 numpy MC, so
no Mitsuba is needed; the Mitsuba comparison itself is tests/test_stability.py, marked plugin)."""
from __future__ import annotations

import csv
import json
import math

import pytest

from roadgonio.cli import main
from roadgonio.engines import CellResult
from roadgonio.engines import validate as V



def cell(k, se):
    return CellResult(tan_eps=4.0, beta_deg=2.0, k_a=k, se=se, samples=10, seconds=0.1)


def quad_cell(k, bound):
    return CellResult(tan_eps=4.0, beta_deg=2.0, k_a=k, se=math.nan, error_bound=bound, samples=10, seconds=0.1)


@pytest.mark.unit
def test_compare_pass_band():
    q = quad_cell(0.5, 0.0)
    assert V.compare(q, cell(0.5 + 3.9e-3, 1e-3)).ok
    assert not V.compare(q, cell(0.5 + 4.1e-3, 1e-3)).ok
    # the float32 floor widens the band by floor * k
    assert V.compare(q, cell(0.5 + 4.1e-3, 1e-3), floor=1e-3).ok
    # the quadrature's bound widens the band as a bound, it is not an SE: allowed = 4 SE + bound
    r = V.compare(quad_cell(0.5, 3e-4), cell(0.501, 4e-4))
    assert r.sigma == pytest.approx(4e-4) and r.allowed == pytest.approx(4 * 4e-4 + 3e-4) and r.ok
    assert not V.compare(quad_cell(0.5, 3e-4), cell(0.5 + 4 * 4e-4 + 3.1e-4, 4e-4)).ok
    assert not V.compare(q, cell(math.nan, 1e-3)).ok


@pytest.mark.unit
def test_parse_cells():
    assert V.parse_cells(None) == list(V.DEFAULT_CELLS)
    assert V.parse_cells("12:0, 4:2.5") == [(12.0, 0.0), (4.0, 2.5)]
    assert len(V.parse_cells("all")) == 580
    cells = V.parse_cells("extremes")
    for must in [(0.0, 0.0), (0.0, 180.0), (12.0, 0.0), (12.0, 180.0)]:
        assert must in cells
    from roadgonio.errors import InputError
    for bad in ("12", "a:b", "1:200", "-1:0"):
        with pytest.raises(InputError):
            V.parse_cells(bad)


@pytest.mark.system
def test_cli_passes_and_writes_outputs(tmp_path, capsys, r3like):
    model = tmp_path / "r3like.json"
    r3like.save(model)
    out = tmp_path / "val"
    rc = main(["validate", "--instrument", "lab", "--sample", str(model), "--against", "numpy-mc",
               "--cells", "12:0,0:180,4:2", "--rel-se", "3e-3", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "3 of 3 cells agree" in text
    rows = list(csv.DictReader(open(out / "validate.csv")))
    assert [(float(r["tan_eps"]), float(r["beta_deg"])) for r in rows] == [(12, 0), (0, 180), (4, 2)]
    assert all(r["ok"] == "True" for r in rows)
    doc = json.loads((out / "validate.json").read_text())
    assert doc["ok"] is True and doc["against"] == "numpy-mc" and len(doc["cells"]) == 3
    assert "quadrature" in doc["settings"] and doc["model"]["params"]["n_phong"] == pytest.approx(34.467)
    assert {"roadgonio", "mitsuba", "drjit", "numpy"} <= set(doc["versions"]) and doc["instrument"]["source"]
    assert (out / "validate.png").stat().st_size > 10_000


@pytest.mark.system
def test_cli_exit_1_on_disagreement(tmp_path, monkeypatch, capsys, r3like):
    """With a zero-width pass band any Monte Carlo noise is a disagreement: exit status 1."""
    model = tmp_path / "m.json"
    r3like.save(model)
    monkeypatch.setattr(V, "N_SIGMA", 0.0)
    rc = main(["validate", "--instrument", "lab", "--sample", str(model), "--against", "numpy-mc",
               "--cells", "8:5", "--rel-se", "1e-2", "--floor", "0", "--out", str(tmp_path / "v")])
    assert rc == 1
    assert "FAILED" in capsys.readouterr().err


@pytest.mark.system
def test_cli_bad_input_is_exit_2(tmp_path):
    assert main(["validate", "--instrument", "lab", "--sample", "lambert", "--against", "numpy-mc",
                 "--cells", "12", "--out", str(tmp_path)]) == 2
    assert main(["validate", "--instrument", "nope.toml", "--sample", "lambert", "--against", "numpy-mc",
                 "--out", str(tmp_path)]) == 2
