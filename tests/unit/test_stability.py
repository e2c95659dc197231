"""Numerical stability of k_A at the extremes (quadrature; float32 renderer against it as a plugin test):
grazing illumination up to eps = 89.9 deg, observation from 0.1 to 90 deg, beta exactly 0 and 180,
lobe exponents up to 1e4, mu = 0, the g factor across theta_l, apertures from zero to large
(k_A - 1 ~ aperture^2), a sample that barely covers the footprint. No NaN or Inf anywhere."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.instrument import optics
from roadgonio.errors import GeometryError
from roadgonio.engines import make_backend
from roadgonio.surface.model import RoadModel, RoadParams
from tolerances import N_SIGMA, z_family


#: |k_A - 1| must scale as aperture^EXPONENT within this tolerance (smooth BRDF, small apertures).
EXPONENT = 2.0
EXPONENT_TOL = 0.1
#: Two beta values this close must give k_A this close (continuity at beta = 0 and 180).
CONTINUITY_TOL = 1e-6


def finite_result(r, max_rel_err: float | None = None):
    """A finite k_A with a finite precision (SE for Monte Carlo, error bound for the quadrature)."""
    prec = r.error_bound if r.deterministic else r.se
    assert math.isfinite(r.k_a) and math.isfinite(prec), r
    assert r.k_a > 0.0 and prec >= 0.0
    if max_rel_err is not None:
        assert prec <= max_rel_err * r.k_a, r


@pytest.mark.parametrize("eps_deg", [80.0, 85.236, 88.0, 89.0, 89.9])
def test_grazing_illumination(eps_deg, lab, r3like):
    tan = math.tan(math.radians(eps_deg))
    b = make_backend("quadrature", lab(), r3like, rtol=1e-4)
    for beta in (0.0, 90.0, 180.0):
        if source_in_line_of_sight(lab(), tan, beta):
            # eps 89 deg, beta 180: the source disc sits on the detector's line of sight (issue 10)
            with pytest.raises(GeometryError, match="line of sight"):
                b.compute_cell(tan, beta)
            continue
        finite_result(b.compute_cell(tan, beta), 1e-4)


def source_in_line_of_sight(inst, tan, beta) -> bool:
    """The source disc is seen within its angular radius of the detector's axis (plus the field and
    pupil angles): it stands between the detector and the sample."""
    wi, wo = inst.w_i(tan, beta), inst.w_o()
    sep = math.acos(min(1.0, float(wi @ wo)))
    det = inst.detector
    reach = (inst.source.radius_m / inst.source.distance_m + math.radians(det.field_half_angle_deg)
             + det.pupil_radius_m / det.distance_m)
    return sep < reach


def test_grazing_source_below_horizon_is_an_error(lab, r3like):
    # lab source: 5 mm radius at 5 m; its rim dips below the plane once 5 cos(eps) < 0.005 sin(eps)
    b = make_backend("quadrature", lab(), r3like)
    with pytest.raises(GeometryError):
        b.compute_cell(math.tan(math.radians(89.95)), 0.0)


@pytest.mark.parametrize("alpha", [0.1, 0.5, 1.0, 10.0, 45.0, 89.0, 89.99])
def test_observation_angles(alpha, lab, r3like):
    """From nearly grazing to the zenith; the sample is made large enough for the footprint."""
    inst = lab(observation={"alpha_deg": alpha}, sample={"size_x_m": 60.0, "size_y_m": 2.0},
               detector={"field_half_angle_deg": 0.01})
    b = make_backend("quadrature", inst, r3like, rtol=1e-4)
    for cell in [(0.0, 0.0), (12.0, 0.0), (3.0, 180.0)]:
        if source_in_line_of_sight(inst, *cell):
            # alpha 89.99 deg and the source at the zenith: the source is between the detector and the sample
            with pytest.raises(GeometryError, match="line of sight"):
                b.compute_cell(*cell)
            continue
        finite_result(b.compute_cell(*cell), 1e-4)


def test_grazing_observation_leaves_a_small_sample(lab, r3like):
    inst = lab(observation={"alpha_deg": 0.1})
    with pytest.raises(GeometryError, match="footprint"):
        make_backend("quadrature", inst, r3like)


@pytest.mark.parametrize("beta0", [0.0, 180.0])
@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_beta_exactly_0_and_180_are_continuous(beta0, lab, r3like):
    b = make_backend("quadrature", lab(), r3like, rtol=1e-7)
    step = 1e-7 if beta0 == 0.0 else -1e-7
    for tan in (0.5, 12.0):
        a = b.compute_cell(tan, beta0)
        c = b.compute_cell(tan, beta0 + step)
        finite_result(a)
        assert a.k_a == pytest.approx(c.k_a, abs=CONTINUITY_TOL)


@pytest.mark.parametrize("base, params", [
    ({}, dict(k_diff=0.01, k_phong=1.0, n_phong=1e4)),                 # very sharp specular lobe
    ({}, dict(k_diff=0.01, k_retro=1.0, n_retro=1e4)),                 # very sharp retro lobe
    ("R3-like", dict(mu=0.0)),                                         # mu at its lower bound
    ("R3-like", dict(p=0.0, h=-5.0)),
    ("R3-like", dict(theta_l_deg=85.5, g_a=0.0, g_b=-10.0, g_c=16.5, g_t=2.0)),   # g across theta_l
    ("R3-like", dict(theta_l_deg=88.9, g_a=1.0, g_b=0.0, g_c=0.0, g_t=-3.0)),
])
def test_extreme_models_stay_finite(base, params, r3like_params, lab):
    model = RoadModel(RoadParams(**{**(r3like_params if base else {}), **params}))
    b = make_backend("quadrature", lab(), model, rtol=1e-3, max_evals=500_000)
    for cell in [(12.0, 0.0), (4.0, 2.0), (0.0, 0.0), (1.0, 180.0)]:
        r = b.compute_cell(*cell)
        finite_result(r)
        if r.converged:
            assert r.error_bound <= 1e-3 * r.k_a


def test_sharp_lobe_agrees_with_monte_carlo(lab):
    """n_phong = 1e4: quadrature and float64 MC agree within 4 SE (fixed seed)."""
    model = RoadModel(RoadParams(k_diff=0.01, k_phong=1.0, n_phong=1e4))
    inst = lab()
    q = make_backend("quadrature", inst, model, rtol=1e-4).compute_cell(0.0, 0.0)
    m = make_backend("numpy-mc", inst, model, rel_se=2e-3, seed=4).compute_cell(0.0, 0.0)
    assert q.converged and m.converged, (q, m)
    assert abs(m.k_a - q.k_a) <= N_SIGMA * m.se + q.error_bound


def scaled(lab, s: float):
    """The lab preset with every aperture (source radius, pupil radius, field) scaled by s."""
    return lab(source={"radius_m": 0.005 * s}, sample={"size_x_m": 6.0},
               detector={"pupil_radius_m": 0.005 * s, "field_half_angle_deg": 0.05 * s})


@pytest.mark.parametrize("cell", [(2.0, 0.0), (6.0, 10.0), (10.0, 0.0)])
def test_k_a_minus_one_scales_as_aperture_squared(cell, lab, r3like_params):
    """For a smooth BRDF, k_A - 1 = c s^2 + O(s^4) in the aperture scale s (even in s: the
    first-order terms cancel over the symmetric discs). Fit the log-log slope."""
    model = RoadModel(RoadParams(**dict(r3like_params, k_exp=0.0)))     # lobes + diffuse: smooth
    scales = np.array([0.125, 0.25, 0.5, 1.0])
    dev = []
    for s in scales:
        r = make_backend("quadrature", scaled(lab, s), model, rtol=1e-11).compute_cell(*cell)
        finite_result(r)
        dev.append(abs(r.k_a - 1.0))
        assert r.error_bound < 1e-3 * dev[-1]       # the quadrature resolves k_A - 1 itself
    slope = np.polyfit(np.log(scales), np.log(dev), 1)[0]
    assert slope == pytest.approx(EXPONENT, abs=EXPONENT_TOL)


#: The quadrature's rtol for the large apertures, and the SE asked of the Monte Carlo it is compared with.
LARGE_RTOL = 1e-3


def test_large_apertures(lab, r3like):
    """A large source, pupil, field and alpha: the quadrature meets its rtol and agrees with numpy-mc
    (an independent integrator) within z_family SE + its error bound."""
    inst = lab(source={"radius_m": 0.3}, detector={"pupil_radius_m": 0.2, "field_half_angle_deg": 1.0},
               sample={"size_x_m": 20.0, "size_y_m": 2.0}, observation={"alpha_deg": 5.0})
    b = make_backend("quadrature", inst, r3like, rtol=LARGE_RTOL)
    mc = make_backend("numpy-mc", inst, r3like, rel_se=LARGE_RTOL, seed=9)
    cells = [(12.0, 0.0), (2.0, 90.0)]
    for cell in cells:
        q, m = b.compute_cell(*cell), mc.compute_cell(*cell)
        finite_result(q, max_rel_err=LARGE_RTOL)
        assert q.converged and m.converged, (cell, q, m)
        assert abs(m.k_a - q.k_a) <= z_family(len(cells)) * m.se + q.error_bound, (cell, q, m)


def test_sample_that_barely_covers_the_footprint(lab, r3like):
    inst = lab()
    xmin, xmax, ymin, ymax = optics.check_detector(inst)
    need_x = 2 * max(-xmin, xmax)
    need_y = 2 * max(-ymin, ymax)
    inside = inst.with_changes(sample={"size_x_m": need_x * (1 + 1e-9), "size_y_m": need_y * (1 + 1e-9)})
    r = make_backend("quadrature", inside, r3like).compute_cell(8.0, 2.0)
    finite_result(r)
    for changes in ({"size_x_m": need_x * (1 - 1e-6)}, {"size_y_m": need_y * (1 - 1e-6)}):
        outside = inside.with_changes(sample=changes)
        with pytest.raises(GeometryError, match="footprint leaves the sample"):
            make_backend("quadrature", outside, r3like)
        with pytest.raises(GeometryError):
            make_backend("numpy-mc", outside, r3like)


@pytest.mark.parametrize("changes", [{"source": {"radius_m": 0.0}}, {"detector": {"focus_m": "inf"}},
                                     {"source": {"beam_half_angle_deg": 3.0}}])
def test_degenerate_and_limited_instruments_agree_with_mc(changes, lab, r3like):
    inst = lab(**changes)
    model = r3like
    cells = [(10.0, 0.0), (2.0, 20.0)]
    for cell in cells:
        q = make_backend("quadrature", inst, model, rtol=1e-5).compute_cell(*cell)
        m = make_backend("numpy-mc", inst, model, rel_se=1e-3, seed=9).compute_cell(*cell)
        finite_result(q)
        assert q.converged and m.converged, (cell, q, m)
        assert abs(m.k_a - q.k_a) <= z_family(len(cells)) * m.se + q.error_bound, (cell, q, m)
