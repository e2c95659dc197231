"""The road BSDF plugin (plugins/road_bsdf.py) against the float64 numpy model: the full BSDF test set
(eval vs reference, Lambert = Mitsuba's diffuse, reciprocity, chi-square test of the sampling,
sample weight = eval/pdf, no NaN/Inf at extremes).

The eval and reciprocity tests compare the plugin with the same ``road_brdf`` evaluated by numpy: they
check the Dr.Jit port (float32, the w_i/w_o convention), not the formula; the formula (the lobes' shape,
E, g) is checked in tests/unit/test_model.py."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.surface.model import RoadModel, RoadParams
from helpers import kappa, near_mirror, rand_dirs, rand_params
from tolerances import F32_EVAL_ATOL as EVAL_ABS_TOL
from tolerances import F32_EVAL_RTOL as EVAL_REL_TOL
from tolerances import F32_KAPPA_TOL as KAPPA_TOL


#: Tolerance of comparisons between two float32 evaluations of the same quantity in different
#: orders (reciprocity, weight vs eval/pdf): a few float32 ulps amplified as above.
F32_PAIR_REL_TOL = 2e-4


def test_eval_matches_numpy_model(plug, rng_seed):
    rng = np.random.default_rng(rng_seed)
    worst = 0.0
    for trial in range(16):
        P = rand_params(rng)
        variant = ("power", "product")[trial % 2]
        if trial % 4 >= 2:                      # the mirror plane's cusp rounded (beta_round_deg)
            P["beta_round_deg"] = float(rng.uniform(0.2, 5.0))
        model = RoadModel(RoadParams(**P), variant)
        bsdf = plug.make(variant, **P)
        n = 8000
        ws = rand_dirs(rng, n, 0.1 if trial % 3 == 0 else 1.0)     # a third of the trials grazing
        wl = rand_dirs(rng, n)
        wl[: n // 2] = near_mirror(rng, ws[: n // 2], 0.02)          # half of them near the lobe peak
        got = plug.eval(bsdf, ws, wl)[0] / wl[:, 2].astype(np.float32)
        ref = model.brdf(wl, ws)                                     # model: wi = light, wo = sensor
        assert np.all(np.isfinite(got))
        err = np.abs(got - ref)
        kap = kappa(model, wl, ws, ref)
        tol = (EVAL_REL_TOL + KAPPA_TOL * kap) * ref + EVAL_ABS_TOL
        assert np.all(err <= tol), (trial, P, float((err / tol).max()))
        worst = max(worst, float((err / np.maximum(ref, 1e-30)).max()))
    assert worst > 0.0      # the comparison saw float32 rounding: it is not comparing a value with itself


def test_eval_steep_empirical_term(plug, rng_seed):
    """Large h: the float32 error is bounded by the conditioning of E itself."""
    rng = np.random.default_rng(rng_seed + 7)
    for variant in ("power", "product"):
        P = dict(k_diff=0.05, k_exp=0.5, p=1.0, h=12.0, mu=0.05)
        model = RoadModel(RoadParams(**P), variant)
        ws, wl = rand_dirs(rng, 8000), rand_dirs(rng, 8000)
        got = plug.eval(plug.make(variant, **P), ws, wl)[0] / wl[:, 2].astype(np.float32)
        ref = model.brdf(wl, ws)
        kap = kappa(model, wl, ws, ref)
        err = np.abs(got - ref) / ref
        assert np.all(np.isfinite(got))
        assert np.all(err <= EVAL_REL_TOL + KAPPA_TOL * kap), float((err / (1 + kap)).max())


def test_eval_is_zero_below_horizon_and_channels(plug, rng_seed):
    rng = np.random.default_rng(rng_seed + 1)
    P = dict(k_diff=0.2, k_phong=3.0, n_phong=200.0)
    ws, wl = rand_dirs(rng, 1000), rand_dirs(rng, 1000)
    below = wl * np.array([1, 1, -1.0])
    b = plug.make(**P)
    assert np.all(plug.eval(b, ws, below) == 0.0)
    assert np.all(plug.eval(b, ws * np.array([1, 1, -1.0]), wl) == 0.0)
    lam = plug.make(channels="road_lambert", **P)
    v = plug.eval(lam, ws, wl)
    np.testing.assert_allclose(v[0], plug.eval(b, ws, wl)[0], rtol=1e-6)
    np.testing.assert_allclose(v[1], wl[:, 2] / math.pi, rtol=1e-6)
    np.testing.assert_allclose(v[2], wl[:, 2] / math.pi, rtol=1e-6)


def test_lambert_equals_mitsuba_diffuse(mi, plug, rng_seed):
    rng = np.random.default_rng(rng_seed + 2)
    rho = 0.37
    road = plug.make(k_diff=rho / math.pi)
    diff = mi.load_dict({"type": "diffuse", "reflectance": {"type": "uniform", "value": rho}})
    w_r = plug.assert_same(road, diff, rng)
    np.testing.assert_allclose(w_r[0], rho, rtol=1e-6)


def test_plugin_reciprocity(plug, rng_seed):
    rng = np.random.default_rng(rng_seed + 4)
    for trial in range(6):
        P = rand_params(rng)
        plug.assert_reciprocal(plug.make(("power", "product")[trial % 2], **P), rng, F32_PAIR_REL_TOL, EVAL_ABS_TOL)


def test_sample_weight_is_eval_over_pdf(plug, rng_seed):
    rng = np.random.default_rng(rng_seed + 5)
    P = rand_params(rng)
    b = plug.make(channels="road_lambert", **P)
    n = 20000
    ws = rand_dirs(rng, n)
    wo, pdf, w = plug.sample(b, ws, rng.random(n), rng.random((n, 2)))
    ok = pdf > 0
    # cosine samples are all valid; lobe samples (half of them when the model has a Phong lobe) only
    # above the horizon; an invalid sample has weight 0
    assert ok.mean() > (0.999 if P["k_phong"] == 0 else 0.5)
    assert np.all(w[:, ~ok] == 0.0)
    wo32 = wo.astype(np.float32).astype(np.float64)
    ev = plug.eval(b, ws[ok], wo32[ok])
    pd = plug.pdf(b, ws[ok], wo32[ok])
    np.testing.assert_allclose(pd, pdf[ok], rtol=1e-5)
    np.testing.assert_allclose(w[:, ok], ev / pd, rtol=F32_PAIR_REL_TOL, atol=EVAL_ABS_TOL)
    # the Lambert channel: 1/pi cos / pdf (exactly reflectance 1 where the sampling is cosine alone)
    np.testing.assert_allclose(w[1, ok], wo32[ok, 2] / math.pi / pdf[ok], rtol=1e-5)


@pytest.mark.parametrize("wi", [[0.0, 0.0, 1.0], [0.70710678, 0.0, 0.70710678], [0.99984770, 0.0, 0.01745241]])
def test_chi2_sampling(mi, plug, wi):
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain
    extra = ('<float name="k_diff" value="0.1"/><float name="k_phong" value="2"/>'
             '<float name="n_phong" value="50"/><float name="k_exp" value="0.3"/>')
    sample_func, pdf_func = BSDFAdapter("roadbsdf", extra, wi=wi)
    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, sample_count=200_000, res=51)
    assert chi2.run(), chi2.messages


def test_no_nan_or_inf_at_extremes(plug):
    cases = [dict(k_diff=1e6, k_phong=1e6, n_phong=1e4, k_retro=1e6, n_retro=1e4),
             dict(k_phong=1.0, n_phong=1e5),
             # E is capped at k_exp e^80 (model.EXP_CAP); with k_exp = 1e6 that is 5.5e40, beyond
             # float32's 3.4e38 (not representable, so not tested); k_exp = 1 reaches 5.5e34
             dict(k_exp=1.0, p=50.0, h=1e3, mu=0.0),
             dict(k_exp=1e6, p=0.0, h=-1e3, mu=1e3),
             dict(k_diff=0.1, g_a=0.0, g_b=0.0, g_c=0.5, g_t=100.0, theta_l_deg=85.31),
             dict(k_diff=0.1, g_a=0.0, g_b=0.0, g_c=0.5, g_t=-100.0, theta_l_deg=85.31)]
    c = [1.0, 0.5, 1e-3, 1e-6, 1e-7, 0.0]
    zs = np.array(c)
    dirs = [np.array([math.sqrt(1 - z * z), 0.0, z]) for z in zs]
    dirs += [np.array([-math.sqrt(1 - z * z), 0.0, z]) for z in zs]
    A = np.array([a for a in dirs for _ in dirs])
    B = np.array([b for _ in dirs for b in dirs])
    for variant in ("power", "product"):
        for P in cases:
            b = plug.make(variant, channels="road_lambert", **P)
            v = plug.eval(b, A, B)
            assert np.all(np.isfinite(v)) and np.all(v >= 0.0), (variant, P)
            wo, pdf, w = plug.sample(b, A, np.full(len(A), 0.5), np.full((len(A), 2), 0.25))
            assert np.all(np.isfinite(w)) and np.all(w >= 0.0) and np.all(np.isfinite(pdf))


def test_parameters_update_without_rebuild(mi, plug, rng_seed):
    """traverse/update changes values (opaque, no recompile) and switches terms on and off."""
    rng = np.random.default_rng(rng_seed + 6)
    b = plug.make(k_diff=0.1)
    ws, wl = rand_dirs(rng, 500), rand_dirs(rng, 500)
    wl[:250] = near_mirror(rng, ws[:250], 0.05)
    params = mi.traverse(b)
    params["k_phong"] = 2.0            # a term that was off
    params["n_phong"] = 300.0
    params.update()
    assert "k_phong" in b.terms
    ref = RoadModel(RoadParams(k_diff=0.1, k_phong=2.0, n_phong=300.0)).brdf(wl, ws)
    got = plug.eval(b, ws, wl)[0] / wl[:, 2].astype(np.float32)
    np.testing.assert_allclose(got, ref, rtol=EVAL_REL_TOL, atol=EVAL_ABS_TOL)
    params["n_phong"] = -1.0
    from roadgonio.errors import InputError
    with pytest.raises(InputError):
        params.update()


def test_bad_properties_are_input_errors(mi, plug):
    from roadgonio.errors import InputError
    with pytest.raises((InputError, RuntimeError), match="variant"):
        plug.make(variant="sum")
    with pytest.raises((InputError, RuntimeError), match="n_phong"):
        plug.make(n_phong=-3.0)
