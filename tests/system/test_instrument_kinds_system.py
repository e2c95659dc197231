"""The corridor (fixed-height source) and fixed-LED presets through every verb, like any other
instrument: ka (the table equals the arc instrument at each cell's distance), correct (the classic
route with the true surface as reference gives the truth back), design (the signal scales as the
source's solid angle at its height), render (the one-render k_A agrees with the quadrature; at the
corridor's cell the arc at the height would not) and uncertainty (a height error gives the closed-form
2 sigma_h / h in r)."""
from __future__ import annotations

import math

import numpy as np
import pytest

import roadgonio.api as rg
from roadgonio.engines import make_backend
from roadgonio.instrument.config import Instrument, load_instrument
from roadgonio.surface.rtable import RTable
from roadgonio.surface.sample import resolve_sample

from tolerances import N_SIGMA

KINDS = ["corridor", "fixed-led"]
CELLS = [(0.0, 0.0), (1.0, 0.0), (2.0, 0.0), (4.0, 10.0), (12.0, 0.0)]


def arc_at(inst: Instrument, tan_eps: float) -> Instrument:
    """The arc instrument at the source's distance of that cell (the geometry, not the formula)."""
    d = inst.to_dict()
    h = inst.source.length_m
    dist = math.hypot(h, h * tan_eps) if inst.source.path == "fixed_height" else h
    d["source"] = {"distance_m": dist, "radius_m": inst.source.radius_m}
    return Instrument.from_dict(d)


@pytest.mark.parametrize("kind", KINDS)
def test_ka_table_is_the_arc_instrument_at_each_cells_distance(kind):
    ds = rg.ka_table(kind, "R3", backend="quadrature", accuracy="fast", cells=CELLS)
    model = resolve_sample("R3").model
    inst = load_instrument(kind)
    for t, b in CELLS:
        k = float(ds.k_a.sel(tan_eps=t, beta=b))
        ref = make_backend("quadrature", arc_at(inst, t), model, accuracy="fast").compute([(t, b)])[0]
        assert k == pytest.approx(ref.k_a, rel=1e-9), (kind, t, b)


@pytest.mark.parametrize("kind", KINDS)
def test_correct_with_the_true_surface_as_reference_gives_the_truth(kind):
    """The classic route (reference = the true surface): r_measured / k_A(reference) is the truth
    wherever the measured table is the truth times the instrument's k_A (over the tabulated region:
    the correction's Q0 and S1 need it)."""
    truth = resolve_sample("R3")
    inst = load_instrument(kind)
    cells = truth.table.cells
    k = make_backend("quadrature", inst, truth.model, accuracy="fast").compute(cells)
    r = np.full(truth.table.r.shape, np.nan)
    true_r = np.full_like(r, np.nan)
    for c, (t, b) in zip(k, cells):
        i = int(np.argmin(np.abs(truth.table.tan_eps - t)))
        j = int(np.argmin(np.abs(truth.table.beta_deg - b)))
        true_r[i, j] = float(np.asarray(truth.model.r(t, b)))
        r[i, j] = true_r[i, j] * c.k_a
    meas = RTable(r, name=f"measured-by-{kind}")
    res = rg.correct(meas, inst, reference=truth.model, alternatives="none", backend="quadrature", accuracy="fast",
                     u_measured="1%")
    m = meas.mask
    before = np.max(np.abs(meas.r[m] / true_r[m] - 1))
    after = np.max(np.abs(res.corrected.r[m] / true_r[m] - 1))
    assert before > 0.02 and after <= 2e-3, (kind, before, after)


@pytest.mark.parametrize("kind,key,values", [("corridor", "source.height_m", [0.8, 1.6]),
                                             ("fixed-led", "source.radius_m", [0.0025, 0.005])])
def test_design_signal_follows_the_solid_angle_at_the_cells_source_distance(kind, key, values):
    """The signal's Omega_S at the requested cells' source distances, the smallest (the design's
    metrics): an arc's (fixed-led) is the same at every cell; on the corridor's fixed-height path
    D_S = height / cos eps, farthest (smallest Omega_S of the uniform disc) at tan eps 4 (session 43:
    it was the height's, tan eps 0's, whatever the cells)."""
    ds = rg.design_study(kind, vary={key: values}, samples="R3", cells="0:0,4:10", backend="quadrature",
                         accuracy="fast", workers=0, plots=False)
    inst = load_instrument(kind)
    omega = []
    for v in values:
        x = inst.with_changes(source={key.split(".")[1]: v})
        R, L = x.source.radius_m, x.source.length_m
        D = [L * math.hypot(1.0, t) if x.source.path == "fixed_height" else L for t in (0.0, 4.0)]
        omega.append(min(math.pi * R * R / (R * R + d * d) for d in D))
    sig = np.asarray(ds["signal"]).ravel()
    assert bool(np.all(np.asarray(ds["geometry_ok"]))), ds["reason"].values
    assert sig[1] / sig[0] == pytest.approx(omega[1] / omega[0], rel=1e-9)
    dev = np.asarray(ds["max_abs_dev"]).ravel()
    assert dev[0] != dev[1]                       # the varied length or radius reaches the k_A engine


@pytest.mark.parametrize("kind,cell", [("corridor", (4.0, 10.0)), ("fixed-led", (2.0, 0.0))])
def test_render_ka_estimate_agrees_with_the_quadrature(mi, tmp_path, kind, cell):
    info = rg.render(kind, "R3", cell[0], cell[1], tmp_path / kind, resolution=32, spp=16)
    model = resolve_sample("R3").model
    q = make_backend("quadrature", load_instrument(kind), model, rtol=1e-4).compute([cell])[0]
    assert abs(info["k_a_estimate"] - q.k_a) <= N_SIGMA * info["k_a_se"] + q.error_bound, (info["k_a_estimate"], q)
    if kind == "corridor":       # the arc at the rail height is far outside: the source was placed per cell
        wrong = make_backend("quadrature", arc_at(load_instrument(kind), 0.0), model, rtol=1e-4).compute([cell])[0]
        assert abs(info["k_a_estimate"] - wrong.k_a) > 10 * N_SIGMA * info["k_a_se"]


@pytest.mark.parametrize("kind", KINDS)
def test_uncertainty_of_a_length_error_is_twice_its_relative_size(kind):
    """Without the aperture effect, r_meas = f cos eps (D0 / D)^2 cos^2 eps with every D scaling with the
    source's length L: u(r) / r = 2 sigma_L / L to first order in every cell (GUM)."""
    sigma = 0.002
    res = rg.estimate_uncertainty(kind, "R3", f"source_distance_m={sigma}", trials=2000, aperture=False,
                                  cells="standard")
    case = res.cases["no_aperture"]
    L = load_instrument(kind).source.length_m
    n = len(res.cells)                            # the cells (then Q0, S1: S1 is a ratio, the error cancels)
    rel = case.gum["u"][:n] / case.nominal[:n]
    assert case.gum["u"][-1] < 1e-9 * case.nominal[-1]
    assert np.allclose(rel, 2 * sigma / L, rtol=1e-3), (kind, rel.min(), rel.max(), 2 * sigma / L)
