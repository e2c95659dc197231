"""The road BSDF plugin rendering a surface other than eq. 4 (``RoadBSDF.set_surface``): the truths of
roadgonio/surface/truths.py that evaluate over any array namespace, and the fitted backbone times its
correction surface (roadgonio/surface/correction_surface.py, ``CorrectedSurface``). The full BSDF
test set: eval against the float64 numpy evaluation of the same surface, a degenerate case equal to
Mitsuba's own ``diffuse``, reciprocity where the surface is reciprocal, the sample weight equal to
eval / pdf, a chi-square test of the sampling; and k_A through the Mitsuba backend against the
float64 reference integrator (roadgonio/engines/reference.py, independent of the plugin)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from helpers import kappa, near_mirror, rand_dirs
from tolerances import F32_EVAL_ATOL as EVAL_ABS_TOL
from tolerances import F32_EVAL_RTOL as EVAL_REL_TOL
from tolerances import F32_KAPPA_TOL as KAPPA_TOL

from roadgonio.surface.model import RoadModel, RoadParams
from roadgonio.surface.truths import R3LIKE, make_truth

#: As tests/plugin/test_plugin_bsdf.py: two float32 evaluations of one quantity in different orders.
F32_PAIR_REL_TOL = 2e-4
#: Mitsuba k_A against the float64 reference: at most this many standard errors at any cell (a few
#: cells, fixed seed; the reference's own error is below 1e-6, its rtol).
Z_KA = 4.0
#: Sub-samples per histogram cell (each way) of the chi-square test's integration of the pdf.
CHI2_IRES = 16


def corrected_surface(rng, scale_c=0.1, scale_d=0.2, alpha_range=None, unobserved_factor=1.0):
    from roadgonio.correction.flexible import SurfaceSettings
    from roadgonio.surface.correction_surface import CorrectedSurface
    s = SurfaceSettings()
    grids = [s.c_grid] + ([s.d_grid] if s.d_grid is not None else [])
    thetas = [scale_c * rng.standard_normal(s.n_c)] + ([scale_d * rng.standard_normal(s.n_d)] if s.n_d else [])
    return CorrectedSurface(RoadModel(RoadParams(**R3LIKE), "power", name="r3like"), grids, thetas,
                            alpha_range=alpha_range, unobserved_factor=unobserved_factor)


def _surfaces(rng):
    return [make_truth("microfacet"), make_truth("two_lobes"), make_truth("microfacet", a=0.08),
            corrected_surface(rng), corrected_surface(rng, alpha_range=(-0.2, 0.3)),
            # the correction's probe of the road beyond the observation elevations (outside.UNOBSERVED_PROBE)
            corrected_surface(rng, alpha_range=(-0.2, 0.3), unobserved_factor=2.0)]


def test_eval_matches_the_numpy_surface(plug, rng_seed):
    rng = np.random.default_rng(rng_seed)
    worst = 0.0
    for trial, surf in enumerate(_surfaces(rng)):
        b = plug.make(surface=surf)
        n = 8000
        ws = rand_dirs(rng, n, 0.1 if trial % 2 else 1.0)      # grazing observations too
        wl = rand_dirs(rng, n)
        wl[: n // 2] = near_mirror(rng, ws[: n // 2], 0.02)
        got = plug.eval(b, ws, wl)[0] / wl[:, 2].astype(np.float32)
        ref = surf.brdf(wl, ws)                                  # wi = light, wo = sensor
        assert np.all(np.isfinite(got)) and np.all(ref > 0)
        err = np.abs(got - ref)
        tol = (EVAL_REL_TOL + KAPPA_TOL * kappa(surf, wl, ws, ref)) * ref + EVAL_ABS_TOL
        assert np.all(err <= tol), (surf.name, float((err / tol).max()))
        worst = max(worst, float((err / ref).max()))
    assert worst > 0.0        # float32 rounding was seen: not a value compared with itself


def test_a_lambertian_surface_equals_mitsuba_diffuse(mi, plug, rng_seed):
    """The degenerate case: a Lambertian backbone with a correction surface of zero and no Phong lobe
    (so cosine sampling alone) is Mitsuba's diffuse BSDF in eval, pdf and sampling."""
    from roadgonio.correction.flexible import SurfaceSettings
    from roadgonio.surface.correction_surface import CorrectedSurface
    rng = np.random.default_rng(rng_seed + 1)
    rho = 0.37
    s = SurfaceSettings()
    grids = [s.c_grid] + ([s.d_grid] if s.d_grid is not None else [])
    surf = CorrectedSurface(RoadModel(RoadParams(k_diff=rho / math.pi)), grids, [np.zeros(g.n_params) for g in grids])
    road = plug.make(surface=surf)
    diff = mi.load_dict({"type": "diffuse", "reflectance": {"type": "uniform", "value": rho}})
    w_r = plug.assert_same(road, diff, rng)
    np.testing.assert_allclose(w_r[0], rho, rtol=1e-6)


@pytest.mark.parametrize("kind", ["microfacet", "two_lobes"])
def test_reciprocal_truths_stay_reciprocal(plug, rng_seed, kind):
    """The microfacet and two-lobe truths are reciprocal (each lobe symmetric in w_i, w_o); the
    corrected surface is not (g reads the incident direction), so it is not tested here."""
    rng = np.random.default_rng(rng_seed + 2)
    plug.assert_reciprocal(plug.make(surface=make_truth(kind)), rng, F32_PAIR_REL_TOL, EVAL_ABS_TOL)


def test_sample_weight_is_eval_over_pdf(plug, rng_seed):
    rng = np.random.default_rng(rng_seed + 3)
    for surf in _surfaces(rng):
        b = plug.make(surface=surf, channels="road_lambert")
        n = 20000
        ws = rand_dirs(rng, n)
        wo, pdf, w = plug.sample(b, ws, rng.random(n), rng.random((n, 2)))
        ok = pdf > 0
        assert ok.mean() > 0.5 and np.all(w[:, ~ok] == 0.0)
        wo32 = wo.astype(np.float32).astype(np.float64)
        ev, pd = plug.eval(b, ws[ok], wo32[ok]), plug.pdf(b, ws[ok], wo32[ok])
        np.testing.assert_allclose(pd, pdf[ok], rtol=1e-5)
        np.testing.assert_allclose(w[:, ok], ev / pd, rtol=F32_PAIR_REL_TOL, atol=EVAL_ABS_TOL)


@pytest.mark.parametrize("kind", ["microfacet", "two_lobes", "corrected"])
@pytest.mark.parametrize("wi", [[0.0, 0.0, 1.0], [0.99984770, 0.0, 0.01745241]])
def test_chi2_sampling(mi, plug, rng_seed, kind, wi):
    """Mitsuba's chi-square test of the sampling against the pdf (its own adapter builds BSDFs from
    XML, which cannot carry a Python surface: the same functors over one built instance)."""
    import drjit as dr
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain
    surf = corrected_surface(np.random.default_rng(rng_seed + 4)) if kind == "corrected" else make_truth(kind)
    b = plug.make(surface=surf)

    def context(n):
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = mi.Vector3f(*wi)
        return si

    def sample_func(sample, *args):
        bs, weight = b.sample(mi.BSDFContext(), context(dr.width(sample)), sample[0],
                              mi.Vector2f(sample[1], sample[2]))
        w = dr.full(mi.Float, 1.0, dr.width(weight))
        w[dr.all(weight == 0)] = 0
        return bs.wo, w

    def pdf_func(wo, *args):
        return b.pdf(mi.BSDFContext(), context(dr.width(wo)), wo)

    # the two-lobe truth's sampled lobe is narrow (n ~ 100, 8 deg): the pdf is integrated over the
    # histogram's cells more finely than the default (ires 4), or the quadrature, not the sampling, errs
    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, sample_count=400_000, res=51, ires=CHI2_IRES)
    assert chi2.run(), chi2.messages


def test_a_numpy_only_surface_is_refused_by_name(plug):
    from roadgonio.errors import InputError
    with pytest.raises(InputError, match="numpy only"):
        plug.make(surface=make_truth("table"))


def test_set_model_returns_to_eq4(plug, rng_seed):
    rng = np.random.default_rng(rng_seed + 5)
    b = plug.make(surface=make_truth("microfacet"))
    model = RoadModel(RoadParams(**R3LIKE), "power")
    b.set_model(model.params, model.variant)
    ws, wl = rand_dirs(rng, 2000), rand_dirs(rng, 2000)
    got = plug.eval(b, ws, wl)[0] / wl[:, 2].astype(np.float32)
    np.testing.assert_allclose(got, model.brdf(wl, ws), rtol=1e-4, atol=EVAL_ABS_TOL)


@pytest.mark.parametrize("kind", ["microfacet", "two_lobes", "corrected"])
def test_ka_of_a_surface_matches_the_float64_reference(mi, rng_seed, kind):
    """k_A of a surface outside eq. 4 by the Mitsuba backend (the plugin's set_surface) against the
    float64 reference integrator, at cells on and off the specular plane, grazing included."""
    from roadgonio.engines.registry import make_backend
    from roadgonio.instrument import load_instrument
    surf = corrected_surface(np.random.default_rng(rng_seed + 6)) if kind == "corrected" else make_truth(kind)
    inst = load_instrument("portable")
    cells = [(0.0, 0.0), (2.0, 0.0), (5.0, 0.0), (12.0, 0.0), (3.0, 10.0), (12.0, 90.0)]
    res = make_backend("mitsuba", inst, surf, settings={"rel_se": 5e-4, "seed": 3}).compute(cells)
    ref = make_backend("reference", inst, surf)
    z = [(r.k_a - ref.compute_cell(t, b).k_a) / r.se for (t, b), r in zip(cells, res)]
    assert np.all(np.abs(z) <= Z_KA), z
    # not a comparison of 1 with 1: the surfaces' apertures effects are resolved
    assert max(abs(r.k_a - 1.0) for r in res) > 20 * max(r.se for r in res)
