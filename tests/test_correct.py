"""Tests of roadgonio.correction (r / k_A with the uncertainty of the correction) and the command.
A stand-in k_A backend (analytic, model-dependent) replaces the exact backends in the unit tests."""
from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from roadgonio.correction import correct_table, nearest_standard_tables, write_correction
from roadgonio.instrument.config import load_instrument
from roadgonio.engines import CellResult
from roadgonio.surface.model import RoadModel, RoadParams
from roadgonio.surface.rtable import bundled_table, read_table

EXACT_TOL = 1e-12
#: Correction files store 6 significant digits.
FILE_RTOL = 1e-5


class StandIn:
    name = "stand-in"

    def __init__(self, inst, model):
        self.kp = model.params.k_phong

    def settings(self):
        return {"backend": self.name}

    def compute(self, cells, on_cell=None):
        out = []
        for t, b in cells:
            c = CellResult(t, b, 1.0 + self.kp * t / 12 * math.exp(-b / 10), 1e-4, 1, 0.0)
            out.append(c)
            if on_cell:
                on_cell(c)
        return out


def model(kp):
    return RoadModel(RoadParams(k_diff=0.02, k_phong=kp, n_phong=40), name=f"kp{kp}")


@pytest.mark.unit
def test_correction_divides_by_ka_and_states_model_uncertainty():
    meas = bundled_table("R3")
    c = correct_table(meas, load_instrument("portable"), model(0.5), reference_name="ref",
                      alternatives={"a": model(0.4), "b": model(0.8)}, factory=StandIn, progress=False)
    m = meas.mask
    ii, jj = np.nonzero(m)
    k = 1 + 0.5 * meas.tan_eps[ii] / 12 * np.exp(-meas.beta_deg[jj] / 10)
    assert np.max(np.abs(c.corrected.r[m] / (meas.r[m] / k) - 1)) < EXACT_TOL
    dev = np.maximum(np.abs(0.1 * meas.tan_eps[ii] / 12 * np.exp(-meas.beta_deg[jj] / 10)),
                     np.abs(0.3 * meas.tan_eps[ii] / 12 * np.exp(-meas.beta_deg[jj] / 10)))
    assert np.allclose(c.u_model[m], dev / math.sqrt(3), rtol=EXACT_TOL, atol=1e-15)  # k_alt - k round-off
    assert np.allclose(c.u_rel[m], np.sqrt(1e-8 + (dev / math.sqrt(3)) ** 2) / k, rtol=1e-9)
    assert np.isnan(c.corrected.r[~m]).all()


@pytest.mark.unit
def test_nearest_standard_tables():
    assert nearest_standard_tables(bundled_table("R3"), 1)[0] == ("R3", 0.0)
    near = nearest_standard_tables(bundled_table("R3"), 2, exclude=["R3"])
    assert len(near) == 2 and "R3" not in [n for n, _ in near] and near[0][1] <= near[1][1]


@pytest.mark.system
def test_outputs_roundtrip(tmp_path):
    meas = bundled_table("C2")
    c = correct_table(meas, load_instrument("portable"), model(0.5), alternatives={"a": model(0.6)},
                      factory=StandIn, progress=False)
    paths = write_correction(c, tmp_path)
    names = {p.name for p in paths}
    assert {"C2_corrected.csv", "C2_corrected.rtb", "correction.json", "before_after.png"} <= names
    back = read_table(tmp_path / "C2_corrected.rtb")
    m = meas.mask
    assert np.allclose(back.r[m], c.corrected.r[m], rtol=1e-5)       # 6 significant digits in the file


@pytest.mark.system
def test_cli_measured_table_on_another_grid(tmp_path):
    f = tmp_path / "odd.csv"
    f.write_text("tan_eps,0,5,10\n0,300,300,300\n")
    p = subprocess.run([sys.executable, "-m", "roadgonio", "correct", "--measured", str(f), "--instrument", "portable",
                        "--reference", "lambert", "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert str(f) in p.stderr and "--measured" in p.stderr and "standard grid" in p.stderr


@pytest.mark.system
def test_cli_missing_measured_file(tmp_path):
    p = subprocess.run([sys.executable, "-m", "roadgonio", "correct", "--measured", str(tmp_path / "none.csv"),
                        "--instrument", "portable", "--reference", "lambert"], capture_output=True, text=True)
    assert p.returncode == 2 and "none.csv" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.system
def test_cli_correct_runs_and_its_numbers_check_against_an_independent_backend(tmp_path, r3like):
    """``roadgonio correct`` to success: corrected = measured / k_A, with k_A checked against the
    float64 numpy Monte Carlo (an independent integrator) within 4 SE + the quadrature's bound +
    the 6-digit file rounding; no progress bar into a pipe."""
    from roadgonio.engines import make_backend
    from roadgonio.surface.rtable import RTable
    cells = [(0.0, 0.0), (0.0, 2.0), (0.25, 0.0), (0.25, 2.0), (2.0, 0.0), (12.0, 0.0), (12.0, 2.0), (8.0, 5.0)]
    r3 = bundled_table("R3")
    r = np.full_like(r3.r, np.nan)
    for t, b in cells:
        i, j = int(np.argmin(abs(r3.tan_eps - t))), int(np.argmin(abs(r3.beta_deg - b)))
        r[i, j] = r3.r[i, j]
    measured = RTable(r, name="meas").write_csv(tmp_path / "meas.csv")
    model = tmp_path / "ref.json"
    r3like.save(model)
    p = subprocess.run([sys.executable, "-m", "roadgonio", "correct", "--measured", str(measured), "--instrument",
                        "portable", "--reference", str(model), "--alternatives", "none", "--backend", "quadrature",
                        "--rel-se", "1e-4", "--out", str(tmp_path / "o"), "--no-plots", "--json"],
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr
    assert p.stderr == ""                                  # no progress bar, no warning into a pipe
    summary = json.loads(p.stdout)
    assert summary["cells"] == len(cells) and summary["alternatives"] == {}
    rows = list(csv.DictReader(open(tmp_path / "o" / "correction_cells.csv")))
    assert sorted((float(x["tan_eps"]), float(x["beta_deg"])) for x in rows) == sorted(cells)
    mc = {(c.tan_eps, c.beta_deg): c for c in
          make_backend("numpy-mc", load_instrument("portable"), r3like, rel_se=1e-3, seed=5).compute(cells)}
    back = read_table(tmp_path / "o" / "meas_corrected.csv")
    for x in rows:
        t, b = float(x["tan_eps"]), float(x["beta_deg"])
        k, u = float(x["k_a"]), float(x["k_a_se"])          # quadrature: u = bound / sqrt(3)
        bound = u * math.sqrt(3.0)
        meas, corr = float(x["r_measured_x1e4"]), float(x["r_corrected_x1e4"])
        assert corr == pytest.approx(meas / k, rel=FILE_RTOL)                    # corrected = measured / k_A
        c = mc[(t, b)]
        assert abs(meas / corr - c.k_a) <= 4 * c.se + bound + 2 * FILE_RTOL * c.k_a, (t, b, meas / corr, c)
        assert float(x["u_rel_correction"]) == pytest.approx(u / k, rel=5e-3)   # u_rel = u / k (u has 3 digits)
        i, j = int(np.argmin(abs(back.tan_eps - t))), int(np.argmin(abs(back.beta_deg - b)))
        assert back.r[i, j] * 1e4 == pytest.approx(corr, rel=FILE_RTOL)
    k = {(float(x["tan_eps"]), float(x["beta_deg"])): float(x["k_a"]) for x in rows}
    assert summary["S1_after"] == pytest.approx(summary["S1_before"] * k[(0.0, 0.0)] / k[(2.0, 0.0)], rel=1e-4)
    prov = json.loads((tmp_path / "o" / "correction.json").read_text())["provenance"]
    assert prov["backend"] == "quadrature" and prov["settings"]["rtol"] == 1e-4 and prov["versions"]["numpy"]
