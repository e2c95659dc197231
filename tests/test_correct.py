"""Tests of roadgonio.correction (r / k_A with the uncertainty of the correction) and the command.
A stand-in k_A backend (analytic, model-dependent) replaces the exact backends in the unit tests."""
from __future__ import annotations

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
