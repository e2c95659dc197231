"""The road BRDF model (roadgonio.surface.model): limiting cases, the documented variants, the grazing
attenuation g, finiteness within the documented bounds and parameter validation."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from roadgonio.errors import InputError
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID, pair_angles, w_detector, w_source
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import (PARAM_BOUNDS, SHAPE_TERM, THETA_R_STAR, VARIANTS, RoadModel, RoadParams,
                             phong_lobe, road_brdf, road_brdf_with_shape_grad)
from helpers import _hemisphere, _model, _unit, rand_dirs, rand_params
from tolerances import ROUND_TOL as RTOL_EXACT  # float64 evaluation of closed forms


#: Closed forms that go through exp/log of large exponents.
RTOL_EXPLOG = 1e-9


def _dir(theta_deg, phi_deg):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.stack(np.broadcast_arrays(np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)), axis=-1)


# ----------------------------------------------------------------------------------------------
# limiting cases
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("variant", VARIANTS)
def test_lambertian_only_is_constant(variant):
    rng = np.random.default_rng(1)
    m = _model(variant, k_diff=0.123)
    f = m.brdf(_hemisphere(2000, rng), _hemisphere(2000, rng))
    np.testing.assert_allclose(f, 0.123, rtol=RTOL_EXACT, atol=0)
    T, B = np.meshgrid(TAN_EPS_GRID, BETA_GRID_DEG, indexing="ij")
    np.testing.assert_allclose(m.q(T, B), 0.123, rtol=RTOL_EXACT)
    assert RoadModel.lambert(0.8).brdf([0, 0, 1], [1, 0, 0.1]) == pytest.approx(0.8 / math.pi, rel=RTOL_EXACT, abs=0.0)


@pytest.mark.parametrize("theta_o,phi_o", [(60.0, 0.0), (89.0, 30.0), (20.0, 200.0)])
def test_phong_peak_at_mirror_direction(theta_o, phi_o):
    m = _model(k_phong=2.0, n_phong=200.0)
    wo = _dir(theta_o, phi_o)
    th, ph = np.meshgrid(np.linspace(0.5, 89.5, 179), np.linspace(0, 359.5, 720), indexing="ij")
    wi = _dir(th, ph)
    f = m.brdf(wi, wo)
    i = np.unravel_index(np.argmax(f), f.shape)
    # the mirror of w_o is (theta_o, phi_o + 180)
    assert th[i] == pytest.approx(theta_o, abs=0.5)
    assert (ph[i] - phi_o - 180.0) % 360.0 == pytest.approx(0.0, abs=0.5) or \
        (ph[i] - phi_o - 180.0) % 360.0 == pytest.approx(360.0, abs=0.5)
    assert m.brdf(_dir(theta_o, phi_o + 180.0), wo) == pytest.approx(2.0, rel=RTOL_EXACT)
    assert f.max() <= 2.0 * (1 + RTOL_EXACT)


@pytest.mark.parametrize("theta_o,phi_o", [(60.0, 0.0), (89.0, 30.0), (20.0, 200.0)])
def test_retro_peak_towards_the_source(theta_o, phi_o):
    m = _model(k_retro=1.5, n_retro=150.0)
    wo = _dir(theta_o, phi_o)
    th, ph = np.meshgrid(np.linspace(0.5, 89.5, 179), np.linspace(0, 359.5, 720), indexing="ij")
    f = m.brdf(_dir(th, ph), wo)
    i = np.unravel_index(np.argmax(f), f.shape)
    assert th[i] == pytest.approx(theta_o, abs=0.5)
    assert min((ph[i] - phi_o) % 360.0, 360 - (ph[i] - phi_o) % 360.0) == pytest.approx(0.0, abs=0.5)
    assert m.brdf(wo, wo) == pytest.approx(1.5, rel=RTOL_EXACT)


def _turned(v, omega_deg, towards):
    """The unit vector at the angle ``omega_deg`` from the unit vector ``v``, turned towards the
    normal (``"normal"``) or sideways (``"side"``, about the normal's plane): both stay above the
    surface for the angles used here."""
    v = np.asarray(v, float)
    z = np.array([0.0, 0.0, 1.0])
    u = z - (z @ v) * v if towards == "normal" else np.cross(z, v)
    u = u / np.linalg.norm(u)
    w = math.cos(math.radians(omega_deg)) * v + math.sin(math.radians(omega_deg)) * u
    assert w[2] > 0.0
    return w


LOBES = {"phong": ("k_phong", "n_phong"), "retro": ("k_retro", "n_retro")}


def _lobe_peak(lobe, wo):
    """Where the lobe peaks for the detector direction ``wo``: the mirror direction (-x, -y, z)
    of w_o for the Phong lobe, w_o itself for the retro lobe."""
    return np.array([-wo[0], -wo[1], wo[2]]) if lobe == "phong" else np.array(wo, float)


@pytest.mark.parametrize("lobe", sorted(LOBES))
@pytest.mark.parametrize("n", [30.0, 200.0])
@pytest.mark.parametrize("omega_deg", [2.0, 5.0, 10.0])
@pytest.mark.parametrize("towards", ["normal", "side"])
def test_lobe_shape_off_the_peak(lobe, n, omega_deg, towards):
    """Away from its peak each lobe is k (cos Omega)^n, Omega the angle between w_i and the peak
    direction, here from an explicit dot product (the model uses the half-chord form): checks the
    exponent, which the peak tests (cos^n = 1 there) and the plugin tests (the same road_brdf) do not."""
    k_name, n_name = LOBES[lobe]
    m = _model(**{k_name: 1.7, n_name: n})
    for theta_o, phi_o in [(60.0, 0.0), (85.0, 30.0), (20.0, 200.0)]:
        wo = _dir(theta_o, phi_o)
        wi = _turned(_lobe_peak(lobe, wo), omega_deg, towards)
        cos_omega = wi @ _lobe_peak(lobe, wo)
        assert math.degrees(math.acos(min(cos_omega, 1.0))) == pytest.approx(omega_deg, rel=1e-9)
        assert m.brdf(wi, wo) == pytest.approx(1.7 * cos_omega ** n, rel=RTOL_EXPLOG, abs=0.0), (theta_o, phi_o)


@pytest.mark.parametrize("lobe", sorted(LOBES))
@pytest.mark.parametrize("n", [30.0, 200.0])
def test_lobe_half_width(lobe, n):
    """Each lobe falls to half its peak at cos Omega = 2^(-1/n)."""
    k_name, n_name = LOBES[lobe]
    m = _model(**{k_name: 1.7, n_name: n})
    half_deg = math.degrees(math.acos(2.0 ** (-1.0 / n)))
    for theta_o, phi_o in [(60.0, 0.0), (20.0, 200.0)]:
        wo = _dir(theta_o, phi_o)
        wi = _turned(_lobe_peak(lobe, wo), half_deg, "side")
        assert m.brdf(wi, wo) == pytest.approx(1.7 / 2.0, rel=RTOL_EXPLOG)


def test_phong_lobe_is_the_models_lobe():
    """phong_lobe (the lobe's shape, shared with the plugin's lobe sampling) is the Phong term of
    road_brdf exactly, and (cos Omega)^n about the mirror direction R(w_i) = (-x, -y, z)."""
    rng = np.random.default_rng(14)
    wi, wo = _hemisphere(3000, rng), _hemisphere(3000, rng)
    triple = (lambda w: (w[:, 0], w[:, 1], w[:, 2]))
    lobe = phong_lobe(NumpyOps, triple(wi), triple(wo), 40.0)
    np.testing.assert_array_equal(lobe, _model(k_phong=1.0, n_phong=40.0).brdf(wi, wo))
    cos_omega = np.einsum("ij,ij->i", wo, wi * np.array([-1.0, -1.0, 1.0]))
    np.testing.assert_allclose(lobe, np.where(cos_omega > 0.0, np.maximum(cos_omega, 0.0) ** 40.0, 0.0),
                               rtol=RTOL_EXPLOG, atol=1e-300)


def test_pair_angles_invert_the_cell_directions():
    """geometry.pair_angles (the angles of a ray pair, once) gives back eps, 90 deg - alpha and beta
    of w_source / w_detector at any observation azimuth, beta folded to [0, 180], and the caller's
    pole value where beta is undefined; road_brdf's empirical term sees beta = 180 deg there."""
    T, B = np.meshgrid(TAN_EPS_GRID[1:], np.r_[BETA_GRID_DEG, 200.0, 300.0], indexing="ij")
    for delta in (0.0, 37.0):
        wi, wo = w_source(np.arctan(T), B, delta), w_detector(1.0, delta)
        wo = np.broadcast_to(wo, wi.shape)
        ti, tr, beta = pair_angles(NumpyOps, tuple(np.moveaxis(wi, -1, 0)), tuple(np.moveaxis(wo, -1, 0)), pole=-1.0)
        np.testing.assert_allclose(ti, np.arctan(T), rtol=RTOL_EXACT, atol=RTOL_EXACT)
        np.testing.assert_allclose(tr, math.radians(89.0), rtol=RTOL_EXACT)
        folded = np.where(B > 180.0, 360.0 - B, B)
        np.testing.assert_allclose(np.degrees(beta), folded, rtol=RTOL_EXACT, atol=1e-9)
    up, side = (0.0, 0.0, 1.0), (0.6, 0.0, 0.8)
    for pole in (0.0, math.pi):
        assert pair_angles(NumpyOps, up, side, pole=pole)[2] == pole
        assert pair_angles(NumpyOps, side, up, pole=pole)[2] == pole
    # at the pole the empirical term is E(beta = 180 deg) = 0: only k_diff is left
    m = _model(k_diff=0.02, k_exp=1.0, p=1.0)
    assert m.brdf(np.array(up), np.array(side)) == pytest.approx(0.02, rel=RTOL_EXACT, abs=0.0)


@pytest.mark.parametrize("variant", VARIANTS)
def test_r_is_q_cos3_eps(variant):
    m = _model(variant, k_diff=0.02, k_phong=1.0, n_phong=30, k_retro=0.05, n_retro=10, k_exp=0.1, p=2,
               h=0.5, mu=0.03)
    T, B = np.meshgrid(TAN_EPS_GRID, BETA_GRID_DEG, indexing="ij")
    eps = np.arctan(T)
    np.testing.assert_allclose(m.r(T, B), m.q(T, B) * np.cos(eps) ** 3, rtol=RTOL_EXACT)
    # q is f_r for the source at (eps, beta) and the detector at alpha = 1 deg
    np.testing.assert_allclose(m.q(T, B), m.brdf(w_source(eps, B), w_detector(1.0)), rtol=RTOL_EXACT)


# ----------------------------------------------------------------------------------------------
# grazing attenuation g
# ----------------------------------------------------------------------------------------------

#: a strong attenuation that starts just above the paper's 85.3 deg limit
G_STRONG = dict(theta_l_deg=85.31, g_a=-0.5, g_b=0.0, g_c=1.6, g_t=6.0)


@pytest.mark.parametrize("variant", VARIANTS)
def test_g_never_changes_a_one_degree_table_cell(variant):
    base = dict(k_diff=0.02, k_phong=1.0, n_phong=30, k_retro=0.05, n_retro=10, k_exp=0.1, p=2, h=0.5, mu=0.03)
    plain = _model(variant, **base)
    att = _model(variant, **base, **G_STRONG)
    T, B = np.meshgrid(TAN_EPS_GRID, BETA_GRID_DEG, indexing="ij")
    assert T.size == 580
    np.testing.assert_array_equal(att.r(T, B), plain.r(T, B))
    # ... but it changes the BRDF near grazing observation (what the aperture effect samples)
    for alpha in (0.3, 0.6, 2.0):
        ratio = att.q(T, B, alpha_deg=alpha) / plain.q(T, B, alpha_deg=alpha)
        assert np.max(np.abs(ratio - 1.0)) > 0.05, alpha
    # and the factor is the documented one: g(theta_i) g(theta_r) / g(theta_r*)
    g = lambda th: np.where(th > np.radians(85.31), (-0.5 * th * th + 1.6) ** 6.0, 1.0)  # noqa: E731
    wi, wo = _dir(87.0, 180.0), _dir(89.6, 0.0)
    expected = plain.brdf(wi, wo) * g(np.radians(87.0)) * g(np.radians(89.6)) / g(THETA_R_STAR)
    assert att.brdf(wi, wo) == pytest.approx(expected, rel=RTOL_EXPLOG, abs=0.0)


# ----------------------------------------------------------------------------------------------
# the empirical term E, as documented for each variant
# ----------------------------------------------------------------------------------------------

def _E_reference(variant, k, p, h, mu, theta_i, theta_r, beta, n_beta=1.0):
    """E of docs/conventions.md section 3 / the roadgonio.surface.model docstring, written from the formulas."""
    e = theta_i * theta_r / THETA_R_STAR
    f = math.sin(e) * math.cos(e) / (math.cos(e) ** 2 + mu)
    x = (math.pi - beta) / math.pi
    if variant == "power":
        return k * f ** p * x ** math.exp(1 + h * f * f)
    if variant == "product":
        return k * f ** p * x * math.exp(1 + h * f * f)
    if variant == "smooth":
        xs = math.cos(beta / 2) ** 2
        W = math.exp(1 + h * math.sqrt(f))
        return k * f ** p * math.exp(-W * (-math.log(xs)) ** n_beta)
    raise AssertionError(variant)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("ti,tr,beta_deg,p,h,mu", [
    (60.0, 89.0, 0.0, 2.0, 0.5, 0.03), (80.0, 89.0, 10.0, 2.1, 0.5, 0.03), (30.0, 70.0, 100.0, 1.0, -2.0, 0.0),
    (84.0, 89.0, 2.0, 2.5, 0.02, 0.005), (75.0, 89.0, 5.0, 2.5, 2.5, 0.005), (45.0, 45.0, 170.0, 3.0, 1.0, 1.0)])
def test_empirical_term_matches_documented_formula(variant, ti, tr, beta_deg, p, h, mu):
    m = _model(variant, k_exp=0.7, p=p, h=h, mu=mu)
    wi = _dir(ti, 180.0 - beta_deg)
    wo = _dir(tr, 0.0)
    ref = _E_reference(variant, 0.7, p, h, mu, math.radians(ti), math.radians(tr), math.radians(beta_deg))
    assert m.brdf(wi, wo) == pytest.approx(ref, rel=RTOL_EXPLOG, abs=1e-300)


@pytest.mark.parametrize("n_beta", [0.5, 0.8, 1.7, 4.0])
@pytest.mark.parametrize("ti,tr,beta_deg,p,h,mu", [
    (60.0, 89.0, 0.5, 2.0, 0.5, 0.03), (80.0, 89.0, 10.0, 2.1, 1.6, 0.002), (84.0, 89.0, 2.0, 2.5, 2.5, 0.005),
    (30.0, 70.0, 100.0, 1.0, -2.0, 0.0), (45.0, 45.0, 170.0, 3.0, 1.0, 1.0)])
def test_smooth_beta_profile_exponent(n_beta, ti, tr, beta_deg, p, h, mu):
    m = _model("smooth", k_exp=0.7, p=p, h=h, mu=mu, n_beta=n_beta)
    ref = _E_reference("smooth", 0.7, p, h, mu, math.radians(ti), math.radians(tr), math.radians(beta_deg), n_beta)
    assert m.brdf(_dir(ti, 180.0 - beta_deg), _dir(tr, 0.0)) == pytest.approx(ref, rel=RTOL_EXPLOG, abs=1e-300)


def test_smooth_profile_shapes_and_limits():
    """n_beta = 1 is x_s^W (Gaussian near beta = 0), n_beta = 1/2 (the bound) a cusp exp(-W beta/2);
    the peak value at beta = 0 is k f^p for every n_beta; E falls monotonically in beta."""
    T = np.full(7, 3.0)
    B = np.array([0.0, 0.01, 0.1, 1.0, 5.0, 30.0, 180.0])
    e = np.arctan(3.0) * math.radians(89.0) / THETA_R_STAR
    f = math.sin(e) * math.cos(e) / (math.cos(e) ** 2 + 0.01)
    W = math.exp(1 + 0.8 * math.sqrt(f))
    for nb in (0.5, 1.0, 2.0, 4.0):
        q = _model("smooth", k_exp=1.0, p=2.0, h=0.8, mu=0.01, n_beta=nb).q(T, B)
        assert q[0] == pytest.approx(f ** 2, rel=RTOL_EXPLOG, abs=0.0), nb
        assert np.all(np.diff(q) <= 0.0), nb
    b = np.radians(B[1:4])
    gauss = _model("smooth", k_exp=1.0, p=2.0, h=0.8, mu=0.01, n_beta=1.0).q(T[1:4], B[1:4])
    np.testing.assert_allclose(gauss, f ** 2 * np.cos(b / 2) ** (2 * W), rtol=RTOL_EXPLOG)
    cusp = _model("smooth", k_exp=1.0, p=2.0, h=0.8, mu=0.01, n_beta=0.5).q(T[1:3], B[1:3])
    np.testing.assert_allclose(cusp, f ** 2 * np.exp(-W * b[:2] / 2), rtol=1e-6)
    # the paper's variants ignore n_beta
    for v in ("power", "product"):
        kw = dict(k_exp=1.0, p=2.0, h=0.8, mu=0.01)
        np.testing.assert_array_equal(_model(v, **kw, n_beta=0.6).q(T, B), _model(v, **kw).q(T, B))


def test_product_and_power_differ_as_documented():
    """At beta = 0 (x = 1) the power reading is k f^p while the product carries exp(1 + h f^2);
    at beta = 90 deg (x = 1/2) the power reading is k f^p 2^-W, the product k f^p exp(1+hf^2)/2."""
    kw = dict(k_exp=1.0, p=2.0, h=0.5, mu=0.03)
    pw, pr = _model("power", **kw), _model("product", **kw)
    T = np.array([1.0, 3.0, 8.0])
    e = np.arctan(T) * math.radians(89.0) / THETA_R_STAR
    f = np.sin(e) * np.cos(e) / (np.cos(e) ** 2 + 0.03)
    W = np.exp(1 + 0.5 * f * f)
    np.testing.assert_allclose(pw.q(T, 0.0), f ** 2, rtol=RTOL_EXPLOG)
    np.testing.assert_allclose(pr.q(T, 0.0), f ** 2 * W, rtol=RTOL_EXPLOG)
    np.testing.assert_allclose(pw.q(T, 90.0), f ** 2 * 0.5 ** W, rtol=RTOL_EXPLOG)
    np.testing.assert_allclose(pr.q(T, 90.0), f ** 2 * 0.5 * W, rtol=RTOL_EXPLOG)
    assert np.all(pr.q(T, 0.0) > pw.q(T, 0.0))


# ----------------------------------------------------------------------------------------------
# finite and non-negative within the documented bounds
# ----------------------------------------------------------------------------------------------

def _finite_nonneg(model, wi, wo):
    f = model.brdf(wi, wo)
    assert np.all(np.isfinite(f)), (model.params, model.variant)
    assert np.all(f >= 0.0), (model.params, model.variant)


def _extreme_directions():
    th = [0.0, 1e-7, 30.0, 85.24, 89.0, 89.9999, 90.0 - 1e-9]
    ph = [0.0, 1e-9, 90.0, 180.0, 180.0 - 1e-9, 270.0]
    d = np.array([_dir(t, p) for t in th for p in ph])
    d[:, 2] = np.maximum(d[:, 2], 1e-12)  # upper hemisphere, however grazing
    d = _unit(d)
    ii, jj = np.meshgrid(np.arange(len(d)), np.arange(len(d)), indexing="ij")
    return d[ii.ravel()], d[jj.ravel()]


EXTREMES = {
    "k_diff": [0.0, 1e6], "k_phong": [0.0, 1e6], "k_retro": [0.0, 1e6], "k_exp": [0.0, 1e6],
    "n_phong": [0.0, 1e5], "n_retro": [0.0, 1e5], "p": [0.0, 50.0], "h": [-1e3, 0.0, 1e3], "mu": [0.0, 1e3],
    "n_beta": [0.5, 1.0, 4.0],
}


@pytest.mark.parametrize("variant", VARIANTS)
def test_finite_at_extreme_parameters_and_directions(variant):
    wi, wo = _extreme_directions()
    # every lobe at full strength, each shape parameter at each of its extremes
    names = ["n_phong", "n_retro", "p", "h", "mu"] + (["n_beta"] if variant == "smooth" else [])
    for combo in itertools.product(*(EXTREMES[n] for n in names)):
        P = dict(k_diff=1e6, k_phong=1e6, k_retro=1e6, k_exp=1e6, **dict(zip(names, combo)))
        _finite_nonneg(_model(variant, **P), wi, wo)
        _finite_nonneg(_model(variant, **P, **G_STRONG), wi, wo)
    # beta exactly 0 and 180 on the table grid, theta_i = 0 (tan = 0)
    T, B = np.meshgrid(TAN_EPS_GRID, [0.0, 180.0], indexing="ij")
    for nb in EXTREMES["n_beta"]:
        m = _model(variant, k_exp=1e6, p=0.0, h=1e3, mu=0.0, k_phong=1e6, n_phong=1e5, n_beta=nb)
        q = m.q(T, B)
        assert np.all(np.isfinite(q)) and np.all(q >= 0)


@pytest.mark.parametrize("variant", VARIANTS)
def test_finite_random_parameters_and_directions(variant):
    hyp = pytest.importorskip("hypothesis")
    st = pytest.importorskip("hypothesis.strategies")

    def bounded(name):
        lo, hi = PARAM_BOUNDS[name]
        return st.floats(lo, hi, allow_nan=False, allow_infinity=False)

    @hyp.settings(max_examples=150, deadline=None, derandomize=True)
    @hyp.given(st.fixed_dictionaries({n: bounded(n) for n in EXTREMES}), st.integers(0, 2 ** 31 - 1))
    def check(P, seed):
        rng = np.random.default_rng(seed)
        wi, wo = _hemisphere(64, rng, 1e-9), _hemisphere(64, rng, 1e-9)
        _finite_nonneg(_model(variant, **P), wi, wo)

    check()


def test_below_horizon_is_zero():
    m = _model(k_diff=1.0, k_phong=1.0, k_exp=1.0)
    assert m.brdf([0.3, 0, -0.5], [0, 0, 1]) == 0.0
    assert m.brdf([0, 0, 1], [0.3, 0.1, -0.01]) == 0.0


# ----------------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("field,value", [
    ("k_diff", -1e-3), ("k_phong", 2e6), ("n_phong", -1.0), ("n_retro", 1e6), ("p", 51.0), ("h", -1001.0),
    ("mu", -0.1), ("n_beta", 0.45), ("n_beta", 4.5), ("g_t", 101.0), ("theta_l_deg", 85.3), ("theta_l_deg", 91.0), ("k_exp", float("nan")),
    ("h", float("inf")), ("p", "two")])
def test_invalid_parameter_raises_naming_the_field(field, value):
    with pytest.raises(InputError) as ei:
        RoadParams(**{field: value})
    assert ei.value.field == field
    assert field in str(ei.value)


def test_negative_g_polynomial_is_rejected():
    with pytest.raises(InputError) as ei:
        RoadParams(theta_l_deg=86.0, g_a=0.0, g_b=-1.0, g_c=1.0)  # 1 - theta < 0 at 90 deg
    assert "g_" in ei.value.field


def test_unknown_variant_and_parameter():
    with pytest.raises(InputError) as ei:
        RoadModel(RoadParams(), "nope")
    assert ei.value.field == "variant"
    with pytest.raises(InputError) as ei:
        road_brdf(NumpyOps, RoadParams().to_dict(), (0, 0, 1), (0, 0, 1), "nope")
    assert ei.value.field == "variant"
    with pytest.raises(InputError) as ei:
        RoadParams.from_dict({"k_dif": 1.0})
    assert "k_dif" in str(ei.value)


def test_model_json_round_trip(tmp_path):
    m = RoadModel(RoadParams(k_diff=0.01, k_phong=1.2, n_phong=33.0, p=2.5, h=-3.0, mu=0.2, **G_STRONG),
                  "product", name="x", meta={"fit": {"rms_dev_pct": 1.0}})
    path = m.save(tmp_path / "m.json")
    m2 = RoadModel.load(path)
    assert m2.params == m.params and m2.variant == "product" and m2.name == "x"
    assert m2.meta["fit"]["rms_dev_pct"] == 1.0


def _model_file(tmp_path, doc):
    import json
    path = tmp_path / "m.json"
    path.write_text(json.dumps(doc))
    return path


def test_model_file_refuses_a_parameter_its_variant_does_not_use(tmp_path, capsys):
    """(user audit) n_beta in a power model file did nothing without a word: an error naming the
    file, the key and the variant's parameters, one line and exit status 2 on the command line."""
    from roadgonio.cli import main
    path = _model_file(tmp_path, {"variant": "power", "params": {"k_diff": 0.03, "n_beta": 0.6}})
    with pytest.raises(InputError) as ei:
        RoadModel.load(path)
    assert ei.value.field == "params.n_beta" and str(path) in str(ei.value)
    assert "'power'" in ei.value.reason and "k_diff, k_phong" in ei.value.reason and "n_beta" not in ei.value.reason.split("takes")[1]
    rc = main(["ka", "--instrument", "lab", "--sample", str(path), "--backend", "reference", "--tan-eps", "2",
               "--beta", "0", "--json"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1 and err[0].startswith("roadgonio: error:") and "n_beta" in err[0], err
    # the same key is smooth's own; at its default it is what roadgonio wrote for every variant before
    assert RoadModel.load(_model_file(tmp_path, {"variant": "smooth", "params": {"k_diff": 0.03, "n_beta": 0.6}})
                          ).params.n_beta == 0.6
    assert RoadModel.load(_model_file(tmp_path, {"variant": "power", "params": {"k_diff": 0.03, "n_beta": 1.0}})
                          ).params.k_diff == 0.03


def test_model_file_holds_only_its_variants_parameters(tmp_path):
    """What roadgonio writes reads back: a power model's file has no n_beta (an unused n_beta given in
    Python is held at its default, so the model and its file agree), a smooth model's has."""
    import json
    power = RoadModel(RoadParams(k_diff=0.03, n_beta=2.0), "power")
    assert power.params.n_beta == 1.0
    assert "n_beta" not in json.loads(power.save(tmp_path / "p.json").read_text())["params"]
    assert RoadModel.load(tmp_path / "p.json").params == power.params
    smooth = RoadModel(RoadParams(k_diff=0.03, n_beta=2.0), "smooth")
    assert json.loads(smooth.save(tmp_path / "s.json").read_text())["params"]["n_beta"] == 2.0


def test_model_file_without_a_variant_is_refused(tmp_path):
    """(user audit) a file without 'variant' was read as power, silently; every model file roadgonio
    writes names it, so a missing one is an error naming the file and the variants."""
    path = _model_file(tmp_path, {"params": {"k_diff": 0.03}})
    with pytest.raises(InputError) as ei:
        RoadModel.load(path)
    assert ei.value.field == "variant" and str(path) in str(ei.value)
    assert all(v in ei.value.reason for v in VARIANTS)


# ----------------------------------------------------------------------------------------------
# reciprocity of the model as written (the plugin's is tests/plugin/test_plugin_bsdf.py)
# ----------------------------------------------------------------------------------------------

def test_numpy_model_is_reciprocal(rng_seed):
    """Every term of the model as written (lobes, E with e = theta_i theta_r / theta_r*, beta,
    g(theta_i) g(theta_r)) is symmetric in (w_i, w_o): the full model is reciprocal."""
    rng = np.random.default_rng(rng_seed + 3)
    for variant in ("power", "product"):
        m = RoadModel(RoadParams(**rand_params(rng)), variant)
        a, b = rand_dirs(rng, 2000), rand_dirs(rng, 2000)
        np.testing.assert_allclose(m.brdf(a, b), m.brdf(b, a), rtol=1e-10, atol=1e-14)


# ----------------------------------------------------------------------------------------------
# the rounding of the mirror-plane cusp (beta_round_deg)
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("b_c", [0.3, 1.12, 4.0])
@pytest.mark.parametrize("ti,tr,beta_deg,p,h,mu", [
    (60.0, 89.0, 0.0, 2.0, 0.5, 0.03), (80.0, 89.0, 0.7, 2.1, 0.5, 0.03), (84.0, 89.0, 2.0, 2.5, 0.02, 0.005),
    (75.0, 89.0, 5.0, 2.5, 2.5, 0.005), (45.0, 45.0, 170.0, 3.0, 1.0, 1.0)])
def test_rounded_empirical_term_matches_documented_formula(variant, b_c, ti, tr, beta_deg, p, h, mu):
    """E with beta_round_deg = b_c is E of the documented formula at beta^2 / sqrt(beta^2 + b_c^2)."""
    m = _model(variant, k_exp=0.7, p=p, h=h, mu=mu, n_beta=0.5, beta_round_deg=b_c)
    b, c = math.radians(beta_deg), math.radians(b_c)
    ref = _E_reference(variant, 0.7, p, h, mu, math.radians(ti), math.radians(tr), b * b / math.hypot(b, c),
                       n_beta=0.5 if variant == "smooth" else 1.0)
    assert m.brdf(_dir(ti, 180.0 - beta_deg), _dir(tr, 0.0)) == pytest.approx(ref, rel=RTOL_EXPLOG, abs=1e-300)


@pytest.mark.parametrize("variant", ("power", "smooth"))
def test_rounding_makes_the_mirror_plane_smooth(variant):
    """The cusp (power reading; smooth at n_beta = 1/2): E(0) - E(beta) ~ beta without rounding, ~ beta^2
    well inside b_c with it (halving beta quarters the drop); far outside b_c the two agree; the peak
    value at beta = 0 and the other terms are unchanged; 0 is the paper's model exactly."""
    kw = dict(k_exp=1.0, p=2.0, h=0.3, mu=0.05, n_beta=0.5, k_diff=0.01, k_phong=0.2, n_phong=30.0)
    T = np.full(4, 3.0)
    B = np.array([0.0, 0.005, 0.01, 60.0])
    cusp = _model(variant, **kw).q(T, B)
    round_ = _model(variant, **kw, beta_round_deg=2.0).q(T, B)
    assert round_[0] == pytest.approx(cusp[0], rel=RTOL_EXACT)
    drop_c, drop_r = cusp[0] - cusp[1:3], round_[0] - round_[1:3]
    assert drop_c[1] / drop_c[0] == pytest.approx(2.0, rel=1e-2)      # linear: a cusp
    assert drop_r[1] / drop_r[0] == pytest.approx(4.0, rel=1e-2)      # quadratic: a smooth top
    assert round_[3] == pytest.approx(cusp[3], rel=1e-2)    # beta 60 deg >> b_c: beta shifted by b_c^2 / 2 beta
    T2, B2 = np.meshgrid(TAN_EPS_GRID, BETA_GRID_DEG, indexing="ij")
    np.testing.assert_array_equal(_model(variant, **kw, beta_round_deg=0.0).q(T2, B2), _model(variant, **kw).q(T2, B2))
    assert "round" in _model(variant, **kw, beta_round_deg=2.0).terms()
    assert "round" not in _model(variant, **kw).terms()


@pytest.mark.parametrize("bad", [-0.1, 10.5, float("nan")])
def test_beta_round_deg_out_of_bounds_is_refused(bad):
    with pytest.raises(InputError) as e:
        RoadParams(k_exp=1.0, beta_round_deg=bad)
    assert e.value.field == "beta_round_deg"


# ----------------------------------------------------------------------------------------------
# float32 near beta = 180 deg (the plugin evaluates the same formula in float32)
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("b_c", [0.0, 2.0])
def test_empirical_term_in_float32_near_beta_180_is_as_good_as_its_conditioning(variant, b_c):
    """E evaluated in float32 (numpy float32 through the shared formula, as the Dr.Jit plugin does)
    at float32 directions, against float64 at the same directions, as w_o's azimuth approaches w_i's
    (beta = 180 deg - gamma, gamma 1e-7 ... 0.3 rad; theta_i 70, theta_r 80 deg; h < 0, so E is
    not negligible there): within the plugin test's band F32_EVAL_RTOL + F32_KAPPA_TOL kappa, kappa =
    |d ln E / d angle| (float64 central difference). x = (pi - beta)/pi and x_s = cos^2(beta/2) vanish
    there: formed as 1 - beta/pi and 1 - sin^2(beta/2) in float32 they cancelled (1.2e-7 / gamma
    relative from beta itself, 6e-8 / x absolute from the subtraction), and their floor 1 - 1e-7 is
    1 - 1.19e-7 in float32, so L at the floor was 15.94 instead of 16.12: errors of 1e-3 ... 0.8
    relative, 50 ... 4e4 times the band (session 13)."""
    from tolerances import F32_EVAL_RTOL, F32_KAPPA_TOL
    P = RoadParams(k_exp=0.1, p=2.0, h=-2.0, mu=0.005, n_beta=0.5, beta_round_deg=b_c).to_dict()
    ti, tr, phi = math.radians(70.0), math.radians(80.0), 0.3

    def dirs(gamma):
        wi = np.array([math.sin(ti) * math.cos(phi), math.sin(ti) * math.sin(phi), math.cos(ti)])
        wo = np.stack([math.sin(tr) * np.cos(phi + gamma), math.sin(tr) * np.sin(phi + gamma),
                       np.full_like(gamma, math.cos(tr))])
        return tuple(np.broadcast_to(wi[:, None], wo.shape)), tuple(wo)

    gamma = np.concatenate([[0.0], np.logspace(-7, -0.5, 300)])
    wi32, wo32 = (tuple(c.astype(np.float32) for c in w) for w in dirs(gamma))
    ref = road_brdf(NumpyOps, P, tuple(c.astype(np.float64) for c in wi32), tuple(c.astype(np.float64) for c in wo32),
                    variant)
    with np.errstate(all="ignore"):      # the unselected branch of a where
        got = road_brdf(NumpyOps, {k: np.float32(v) for k, v in P.items()}, wi32, wo32, variant)
    assert got.dtype == np.float32 and np.all(ref > 0)
    d = np.maximum(1e-3 * gamma, 1e-10)
    kappa = (np.abs(np.log(road_brdf(NumpyOps, P, *dirs(gamma + d), variant))
                    - np.log(road_brdf(NumpyOps, P, *dirs(np.abs(gamma - d)), variant))) / (2 * d) / math.sin(tr))
    ratio = np.abs(got / ref - 1) / (F32_EVAL_RTOL + F32_KAPPA_TOL * kappa)
    assert ratio.max() <= 1.0, (float(ratio.max()), float(gamma[np.argmax(ratio)]))


@pytest.mark.parametrize("variant", VARIANTS)
def test_what_a_fit_keeps_of_its_directions_gives_the_same_numbers(variant):
    """road_brdf's ``pairs`` (a fit's dict of what the directions alone determine: the angles, the
    lobes' ln cos, ln x or L at each rounding) gives bit for bit what a call without it gives, over
    a fit-like sequence of parameters on the same directions: every term alone and together, three
    roundings of the mirror plane met in turn and again, g on and off."""
    rng = np.random.default_rng(11)
    n = 400
    wi, wo = rand_dirs(rng, n), rand_dirs(rng, n)
    wo[:20] = wi[:20] * np.array([-1.0, -1.0, 1.0])          # the mirror direction: beta = 0
    wo[20:40] = wi[20:40]                                    # the source direction: beta = 180 deg
    wi[40:45] = (0.0, 0.0, 1.0)                              # azimuth undefined: beta the pole
    wi_t, wo_t = tuple(wi.T), tuple(wo.T)
    pairs: dict = {}
    for rounding in (0.0, 1.12, 0.0, 0.5, 1.12):
        P = {**rand_params(rng, h_max=5.0), "n_beta": rng.uniform(0.5, 4.0), "beta_round_deg": rounding}
        terms = [None, *(frozenset({k}) | (frozenset({"round"}) if rounding > 0 else frozenset())
                         for k in ("k_diff", "k_phong", "k_retro", "k_exp"))]
        for t in terms:
            with np.errstate(all="ignore"):
                kept = road_brdf(NumpyOps, P, wi_t, wo_t, variant, t, pairs=pairs)
                fresh = road_brdf(NumpyOps, P, wi_t, wo_t, variant, t)
            np.testing.assert_array_equal(kept, fresh, err_msg=f"rounding {rounding}, terms {t}")
    assert ("beta", ("round", 0.5)) in pairs and ("beta", ("round", 1.12)) in pairs


def test_a_forward_model_keeps_what_its_rays_directions_give_across_fits(monkeypatch):
    """ForwardModel keeps road_brdf's ``pairs`` for its rays and its nominal directions (the
    correction's fits evaluate the same rays thousands of times: the pair angles were 10.9 s of a
    57.6 s correction, two_lobes through A). Its columns and its f_r at the rays (``ray_brdf``,
    the correction surface's backbone) are bit for bit those computed afresh,
    over the three variants in turn, two roundings and g on and off, and the angles of its rays and
    of its nominal directions are computed once each, not at every new set of parameters."""
    from roadgonio.engines.bundle import ForwardModel, RayBundles, _terms_for
    from roadgonio.surface.model import LINEAR_TERMS
    from roadgonio.engines.bundle import _unit as unit_coefficients
    from roadgonio.instrument.config import load_instrument
    import roadgonio.surface.model as M
    cells = [(6.0, 0.0), (2.0, 0.0), (1.0, 30.0), (12.0, 5.0), (0.5, 180.0)]
    fm = ForwardModel(RayBundles.build(load_instrument("wide"), cells, rays=64))
    b = fm.bundles
    calls = []
    real = M.pair_angles
    monkeypatch.setattr(M, "pair_angles", lambda *a, **k: calls.append(1) or real(*a, **k))
    rng = np.random.default_rng(5)
    own = 0
    for variant, rounding, g_t in (("power", 0.0, 0.0), ("smooth", 1.12, -2.0), ("product", 0.0, 0.0),
                                   ("power", 1.12, -2.0), ("smooth", 0.0, 0.0)):
        P = {**RoadParams().to_dict(), **rand_params(rng, h_max=5.0), "n_beta": rng.uniform(0.5, 4.0),
             "beta_round_deg": rounding, "g_t": g_t, "g_c": 1.0, "g_a": 0.1, "g_b": 0.0, "theta_l_deg": 60.0}
        n0 = len(calls)
        B, N = fm.columns(P, variant)
        nominal = fm.nominal_columns(P, variant)
        model = RoadModel(RoadParams(**{**{k: v for k, v in P.items() if k in RoadParams().to_dict()},
                                        "theta_l_deg": 88.0}), variant=variant)     # (RoadParams: > 85.3 deg)
        at_rays = fm.ray_brdf(model)
        own += len(calls) - n0
        with np.errstate(all="ignore"):
            np.testing.assert_array_equal(at_rays, model.evaluate(NumpyOps, b.wi, b.wo), err_msg=variant)
        Q = unit_coefficients(P)
        for j, t in enumerate(LINEAR_TERMS):
            with np.errstate(all="ignore"):
                f = M.road_brdf(NumpyOps, Q, b.wi, b.wo, variant, _terms_for(t, P))
                f0 = M.road_brdf(NumpyOps, Q, fm.wi0, fm.wo0, variant, _terms_for(t, P))
            np.testing.assert_array_equal(B[:, j], b.cell_sum(np.broadcast_to(f, b.a.shape)),
                                          err_msg=f"{variant}, rounding {rounding}, {t}")
            np.testing.assert_array_equal(N[:, j], np.broadcast_to(f0, (b.n_cells,)), err_msg=f"{variant}, {t}")
            np.testing.assert_array_equal(nominal[:, j], N[:, j])
    assert own == 2, own                     # once for the rays, once for the nominal directions


# ----------------------------------------------------------------------------------------------
# The shape derivatives (the fits' Jacobians)
# ----------------------------------------------------------------------------------------------

#: Central differences of relative step FD_REL in a shape parameter: truncation ~ FD_REL^2 and
#: rounding ~ 1e-16 / FD_REL of the scale, so FD_TOL of the largest derivative is far above both
#: (measured: <= 1e-7 with these parameters) and far below any error of a term or a factor.
FD_REL = 1e-6
FD_TOL = 1e-5


def _shape_names(variant):
    return ["n_phong", "n_retro", "p", "h", "mu"] + (["n_beta"] if variant == "smooth" else [])


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("extra", [{}, G_STRONG, {"beta_round_deg": 2.0}], ids=["plain", "g", "rounded"])
def test_shape_derivatives_are_the_central_differences_of_the_model(variant, extra):
    rng = np.random.default_rng(7)
    wi, wo = rand_dirs(rng, 4000), rand_dirs(rng, 4000)
    wi, wo = tuple(wi.T), tuple(wo.T)
    P = dict(RoadParams().to_dict(), k_diff=0.1, k_phong=0.5, n_phong=30.0, k_retro=0.2, n_retro=8.0, k_exp=0.7,
             p=1.3, h=0.7, mu=0.05, n_beta=0.8, **extra)
    terms = frozenset({"k_diff", "k_phong", "k_retro", "k_exp"} | ({"g"} if extra is G_STRONG else set())
                      | ({"round"} if "beta_round_deg" in extra else set()))
    names = _shape_names(variant)
    with np.errstate(all="ignore"):
        f, grads = road_brdf_with_shape_grad(NumpyOps, P, wi, wo, variant, terms, names)
        assert np.array_equal(f, road_brdf(NumpyOps, P, wi, wo, variant, terms))      # the value is road_brdf's
        for name, g in zip(names, grads):
            step = FD_REL * P[name]
            up, down = dict(P), dict(P)
            up[name] += step
            down[name] -= step
            fd = (road_brdf(NumpyOps, up, wi, wo, variant, terms) - road_brdf(NumpyOps, down, wi, wo, variant, terms)) \
                / (2 * step)
            scale = np.max(np.abs(fd))
            assert scale > 0, name                       # every parameter moves the model somewhere here
            assert np.max(np.abs(g - fd)) <= FD_TOL * scale, (name, float(np.max(np.abs(g - fd)) / scale))


@pytest.mark.parametrize("variant", VARIANTS)
def test_a_term_left_out_has_no_shape_derivative_and_an_unknown_name_is_refused(variant):
    rng = np.random.default_rng(8)
    wi, wo = tuple(rand_dirs(rng, 200).T), tuple(rand_dirs(rng, 200).T)
    P = dict(RoadParams().to_dict(), k_phong=1.0, n_phong=30.0, k_exp=1.0, p=1.3, h=0.7, mu=0.05)
    names = _shape_names(variant)
    _, grads = road_brdf_with_shape_grad(NumpyOps, P, wi, wo, variant, frozenset({"k_phong"}), names)
    for name, g in zip(names, grads):
        assert np.any(g != 0.0) == (SHAPE_TERM[name] == "k_phong"), name
    with pytest.raises(InputError, match="k_exp"):
        road_brdf_with_shape_grad(NumpyOps, P, wi, wo, variant, frozenset({"k_phong"}), ["k_exp"])


@pytest.mark.parametrize("variant", VARIANTS)
def test_shape_derivatives_are_finite_at_the_extremes(variant):
    wi, wo = _extreme_directions()
    wi, wo = tuple(np.asarray(wi, dtype=np.float64).T), tuple(np.asarray(wo, dtype=np.float64).T)
    names = _shape_names(variant)
    terms = frozenset({"k_diff", "k_phong", "k_retro", "k_exp", "g"})
    for combo in itertools.product(*(EXTREMES[n] for n in names)):
        P = dict(RoadParams().to_dict(), k_diff=1.0, k_phong=1.0, k_retro=1.0, k_exp=1.0, **G_STRONG,
                 **dict(zip(names, combo)))
        with np.errstate(all="ignore"):
            _, grads = road_brdf_with_shape_grad(NumpyOps, P, wi, wo, variant, terms, names)
        for name, g in zip(names, grads):
            assert np.all(np.isfinite(g)), (name, dict(zip(names, combo)))


def test_the_mirror_plane_column_is_at_beta_zero_exactly():
    """The beta = 0 and 180 deg columns' source directions lie in the plane of observation exactly
    (pair_angles gives 0 and pi), so eq. 4's x^W is 1 at beta = 0 however large W is. Through radians,
    phi_i = 180 deg had sin 1.2e-16: beta 1.2e-16 rad, and with W = exp(1 + h f^2) ~ 1e16 at tan eps 12
    x^W lost 8-32 % (the fits of R2 and R4 wrote values that were not eq. 4 there: user audit, session 41)."""
    eps = np.arctan(TAN_EPS_GRID)
    wo = np.broadcast_to(w_detector(1.0), (eps.size, 3))
    for beta_deg, expected in ((0.0, 0.0), (180.0, math.pi)):
        wi = w_source(eps, np.full(eps.size, beta_deg))
        _, _, beta, _ = pair_angles(NumpyOps, tuple(wi.T), tuple(wo.T), pole=math.pi, supplement=True)
        assert np.all(np.asarray(beta)[1:] == expected)
    # r at beta = 0 does not depend on h (x = 1), where W reaches ~1e16 at tan eps 12 with h = 0.25
    steep, flat = (RoadModel(RoadParams(k_diff=0.01, k_exp=0.1, p=1.0, h=h), "power") for h in (0.25, 0.0))
    assert math.exp(1 + 0.25 * 12.0 ** 2) > 1e15
    np.testing.assert_allclose(steep.q(TAN_EPS_GRID, np.zeros_like(TAN_EPS_GRID)),
                               flat.q(TAN_EPS_GRID, np.zeros_like(TAN_EPS_GRID)), rtol=RTOL_EXACT)


def test_where_the_empirical_exponent_is_capped_and_the_note_says_so():
    """(user audit, session 45) roadgonio caps the empirical term's exponent at 80 (float32), so a model
    of tiny k_exp and large p is not eq. 4 where the cap binds, and nothing said so. Independently: at
    alpha = 1 deg and beta = 0, e = theta_i (theta_r = theta_r*), f = tan e with mu = 0, ln x = 0, so the
    exponent is p ln(tan eps); the cells with p ln(tan eps) >= 80 are the capped ones at beta = 0."""
    import warnings

    from roadgonio.errors import ModelWarning
    from roadgonio.surface.model import EXP_CAP, RoadModel, RoadParams
    from roadgonio.surface.sample import note_capped_exponent
    t = np.array([5.0, 7.0, 7.5, 10.0, 12.0])
    m = RoadModel(RoadParams(k_diff=0.03, k_exp=1e-40, p=40.0, h=0.01, mu=0.0), "power")
    assert list(m.exponent_capped(t, 0.0)) == list(40.0 * np.log(t) >= EXP_CAP)   # 7.5 and beyond
    # below the cap the value is the formula's: r = k_diff + k_exp tan^40 (no g, beta 0), q = r/cos^3 not needed
    q = m.q(7.0, 0.0)
    assert abs(q / (0.03 + 1e-40 * 7.0 ** 40) - 1.0) < 1e-12
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        note_capped_exponent(m, "m", fitted=False)
        note_capped_exponent(RoadModel(RoadParams(k_diff=0.03, k_exp=1.0, p=2.0, h=0.01, mu=0.0), "power"), "ok",
                             fitted=False)
    said = [str(x.message) for x in w if issubclass(x.category, ModelWarning)]
    assert len(said) == 1 and "cap (80)" in said[0] and "7.5/0" in said[0], said
