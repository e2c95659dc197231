"""Round trips: a known surface measured by an instrument with an aperture effect, 1 % noise, then
corrected by `roadgonio correct` (reference self). The synthetic measurements were made by the
float64 quadrature, not by the code under test (tests/data/make_synthetic_measurements.py:
tests/data/medium.toml, Lambert and absolute calibration, the surface
roadgonio.correction.synthetic.r2_like_truth, which is not the fit of any table).

Targets (issue 11): corrected RMS log error <= 1.5 %, max <= 6 %, >= 90 % of the cells within
2 stated standard uncertainties, S1 within 2 u(S1); and the classic route with the nearest CIE
table as reference is worse (shown beside it)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from roadgonio.surface.cie import nearest_bundled
from roadgonio.correction.files import correct_measured
from roadgonio.instrument.config import Instrument
from roadgonio.surface.rtable import read_table

DATA = Path(__file__).resolve().parents[1] / "data"
RMS_MAX, MAX_MAX, COVERAGE_MIN, S1_Z_MAX = 0.015, 0.06, 0.90, 2.0


def scores(res, truth) -> dict:
    m = res.measured.mask
    err = np.log(res.corrected.r[m] / truth.r[m])
    u = res.budget.u_rel()
    return {"rms": float(np.sqrt(np.mean(err ** 2))), "max": float(np.max(np.abs(err))),
            "coverage": float(np.mean(np.abs(err) <= 2 * u)),
            "s1_z": (res.after["S1"] - truth.s1()) / res.after["u_S1"]}


@pytest.mark.parametrize("mode", ["lambert", "absolute"])
@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_round_trip_reference_self(mode):
    inst = Instrument.load(DATA / "medium.toml").with_changes(calibration={"mode": mode})
    meas = read_table(DATA / f"synthetic_medium_{mode}.csv")
    truth = read_table(DATA / f"synthetic_medium_{mode}_truth.csv")
    k_true = read_table(DATA / f"synthetic_medium_{mode}_ka.csv").r * 1e4     # stored unscaled
    m = meas.mask
    before = float(np.sqrt(np.mean(np.log(meas.r[m] / truth.r[m]) ** 2)))
    assert before > 0.03                                   # the aperture effect is there to correct
    res = correct_measured(meas, inst, u_measured="1%", backend="quadrature", accuracy="fast", rays=256,
                           progress=False)
    s = scores(res, truth)
    assert s["rms"] <= RMS_MAX and s["max"] <= MAX_MAX, s
    assert s["coverage"] >= COVERAGE_MIN and abs(s["s1_z"]) <= S1_Z_MAX, s
    # the factor itself: within its stated uncertainty of the true k_A (backend + parameters + model)
    k_err = np.log(res.k_a[m] / k_true[m])
    u_k = np.sqrt(np.maximum(res.budget.u_rel() ** 2 - res.budget.u_rel("measurement") ** 2, 0.0))
    assert np.mean(np.abs(k_err) <= 2 * u_k + 2e-3) >= COVERAGE_MIN
    # the classic route with the nearest CIE table as reference, beside it: clearly worse
    near = nearest_bundled(meas.s1(), meas.q0(), 1)[0][0]
    ref = correct_measured(meas, inst, reference=near, alternatives="none", u_measured="1%", backend="quadrature",
                           accuracy="fast", progress=False)
    r = scores(ref, truth)
    assert r["rms"] > 2 * s["rms"] and r["max"] > s["max"], (near, r, s)
    assert res.steps[-1]["converged"] and res.provenance["calibration"]["mode"] == mode


def test_synthetic_data_reproduce():
    """The stored measurements are what their generator makes (five cells, noise removed): the true r
    digit for digit, k_A within the quadrature's error bound and the stored table's (rtol 1e-5, its
    header): session 24's confirmation one level finer moved the quadrature's k_A within them (3e-7)."""
    from roadgonio.correction.synthetic import r2_like_truth
    from roadgonio.engines import make_backend
    inst = Instrument.load(DATA / "medium.toml")
    k_true = read_table(DATA / "synthetic_medium_lambert_ka.csv").r * 1e4
    truth = read_table(DATA / "synthetic_medium_lambert_truth.csv")
    cells = [(0.0, 0.0), (2.0, 0.0), (12.0, 0.0), (6.0, 10.0), (1.0, 180.0)]
    got = make_backend("quadrature", inst, r2_like_truth(), rtol=1e-5).compute(cells)
    for c in got:
        i = int(np.argmin(abs(truth.tan_eps - c.tan_eps)))
        j = int(np.argmin(abs(truth.beta_deg - c.beta_deg)))
        assert c.converged and abs(c.k_a - k_true[i, j]) <= c.error_bound + 1e-5 * abs(k_true[i, j]), (c, k_true[i, j])
        assert r2_like_truth().r(c.tan_eps, c.beta_deg) == pytest.approx(truth.r[i, j], rel=1e-9, abs=0.0)
    assert math.isfinite(truth.s1())


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["lambert", "absolute"])
def test_round_trip_wide_instrument_with_mitsuba(mi, mode):
    """The wide-ish instrument of the issue (bench/data/wide.toml: k_A 0.30 ... 1.14, the footprint
    reaching under the source at grazing incidence); the measurement's k_A from the numpy Monte
    Carlo (bench/data/wide_r2like_ka_numpymc.csv, made by bench/bench_correct.py), absolute = that
    x eta; corrected with the default backend (Mitsuba)."""
    from roadgonio.correction.synthetic import r2_like_truth, standard_mask
    from roadgonio.engines.calibration import illuminance_ratio
    from roadgonio.surface.fit import model_r_on_grid
    from roadgonio.surface.rtable import RTable
    bench = Path(__file__).resolve().parents[2] / "bench" / "data"
    inst = Instrument.load(bench / "wide.toml").with_changes(calibration={"mode": mode})
    k = read_table(bench / "wide_r2like_ka_numpymc.csv").r * 1e4
    m = standard_mask()
    if mode == "absolute":
        for i, j in zip(*np.nonzero(m)):
            k[i, j] *= illuminance_ratio(inst, float(k_grid_t(i)), float(k_grid_b(j)))[0]
    truth = RTable(np.where(m, model_r_on_grid(r2_like_truth(), RTable(np.where(m, 1.0, np.nan))), np.nan))
    rng = np.random.default_rng(1)
    noise = np.zeros(m.shape)
    noise[m] = 0.01 * rng.standard_normal(int(m.sum()))
    meas = RTable(np.where(m, truth.r * k * (1 + noise), np.nan), name=f"wide_{mode}")
    res = correct_measured(meas, inst, u_measured="1%", backend="mitsuba", progress=False)
    s = scores(res, truth)
    assert s["rms"] <= RMS_MAX and s["max"] <= MAX_MAX, s
    assert s["coverage"] >= COVERAGE_MIN and abs(s["s1_z"]) <= S1_Z_MAX, s
    # before: S1 far off, below the truth with the Lambert calibration (k_A(2, 0) < k_A(0, 0)) and
    # above it with the absolute one (k_A x eta, and eta(2, 0) / eta(0, 0) = 1.76 on this instrument)
    side = 1.0 if mode == "absolute" else -1.0
    assert side * (meas.s1() - truth.s1()) > 5 * res.after["u_S1"], (meas.s1(), truth.s1(), res.after["u_S1"])


def k_grid_t(i: int) -> float:
    from roadgonio.geometry import TAN_EPS_GRID
    return TAN_EPS_GRID[i]


def k_grid_b(j: int) -> float:
    from roadgonio.geometry import BETA_GRID_DEG
    return BETA_GRID_DEG[j]
