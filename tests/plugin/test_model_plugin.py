"""The "smooth" extension of the model in the Dr.Jit plugin (float32) against the float64 numpy model."""
from __future__ import annotations

import numpy as np
import pytest

from helpers import _hemisphere, _model, _unit
from tolerances import F32_EVAL_ATOL as SMOOTH_F32_ABS_TOL
from tolerances import F32_EVAL_RTOL as SMOOTH_F32_REL_TOL
from tolerances import F32_KAPPA_TOL as SMOOTH_F32_KAPPA_TOL



def _kappa(model, wi, wo, ref, rng, d=1e-6):
    k = np.zeros(len(ref))
    for _ in range(3):
        ti = _unit(wi + d * rng.normal(size=wi.shape))
        to = _unit(wo + d * rng.normal(size=wo.shape))
        ti[:, 2] = np.abs(ti[:, 2])
        to[:, 2] = np.abs(to[:, 2])
        ang = np.maximum(np.linalg.norm(ti - wi, axis=1) + np.linalg.norm(to - wo, axis=1), 1e-300)
        k = np.maximum(k, np.abs(model.brdf(ti, to) - ref) / (np.maximum(ref, 1e-300) * ang))
    return k


def test_smooth_variant_in_plugin_matches_numpy(mi, rng_seed):
    """The plugin's float32 values within F32_EVAL_RTOL + F32_KAPPA_TOL kappa of the float64 model at
    the same directions: random ones, a half near beta = 0 (the peak) and a quarter near beta = 180
    deg, where the formula's x_s = cos^2(beta/2) vanishes (session 13: formed as 1 - sin^2(beta/2),
    and floored at 1 - 1e-7, which float32 rounds to 1 - 1.19e-7, it was beyond the band in 21 of 160
    trials of 20 other seeds, up to 156x, where a draw happened to fall there; with this quarter, 280x
    at this seed; see roadgonio.surface.model's X_FLOOR)."""
    import drjit as dr

    from roadgonio.engines.mitsuba.plugins import register_plugins
    register_plugins()
    rng = np.random.default_rng(rng_seed + 101)
    rng_round = np.random.default_rng(rng_seed + 102)       # apart, so the directions drawn stay the same
    for trial in range(8):
        P = dict(k_diff=rng.uniform(0, 0.1), k_phong=rng.uniform(0, 1), n_phong=10 ** rng.uniform(0, 2),
                 k_retro=rng.uniform(0, 0.1), n_retro=10 ** rng.uniform(0, 2), k_exp=rng.uniform(0.01, 0.2),
                 p=rng.uniform(1, 3), h=rng.uniform(-2, 3), mu=10 ** rng.uniform(-4, 0),
                 n_beta=float(rng.choice([0.5, 4.0])) if trial < 2 else rng.uniform(0.5, 2.0))
        if trial % 2:                           # the mirror plane's cusp rounded (beta_round_deg)
            P["beta_round_deg"] = float(rng_round.uniform(0.2, 5.0))
        bsdf = mi.load_dict({"type": "roadbsdf", "variant": "smooth", **P})
        assert float(mi.traverse(bsdf)["n_beta"][0]) == pytest.approx(P["n_beta"], rel=1e-6)
        n = 6000
        wl = _hemisphere(n, rng, 1e-3).astype(np.float32).astype(np.float64)   # towards the light
        ws = _hemisphere(n, rng, 1e-3)
        ws[: n // 2, :2] = -wl[: n // 2, :2] * rng.uniform(0.9, 1.1, (n // 2, 1))  # near beta = 0
        k = 3 * n // 4      # the last quarter 1e-7 ... 0.1 rad from beta = 180 deg, where x_s = cos^2(beta/2)
        phi = np.arctan2(wl[k:, 1], wl[k:, 0]) + 10 ** rng.uniform(-7, -1, n - k) * rng.choice([-1, 1], n - k)
        ws[k:, :2] = np.sqrt(1 - ws[k:, 2:] ** 2) * np.stack([np.cos(phi), np.sin(phi)], axis=1)   # vanishes
        ws = _unit(ws).astype(np.float32).astype(np.float64)
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = mi.Vector3f(ws[:, 0], ws[:, 1], ws[:, 2])
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        ev = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wl[:, 0], wl[:, 1], wl[:, 2])), dtype=np.float64)
        got = ev[0] / wl[:, 2].astype(np.float32)
        model = _model("smooth", **P)
        ref = model.brdf(wl, ws)
        assert np.all(np.isfinite(got)) and np.all(got >= 0)
        tol = (SMOOTH_F32_REL_TOL + SMOOTH_F32_KAPPA_TOL * _kappa(model, wl, ws, ref, rng)) * ref + SMOOTH_F32_ABS_TOL
        assert np.all(np.abs(got - ref) <= tol), (trial, P, float((np.abs(got - ref) / tol).max()))
    # a changed n_beta reaches the kernel through traverse / parameters_changed
    params = mi.traverse(bsdf)
    before = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wl[:, 0], wl[:, 1], wl[:, 2])))[0]
    params["n_beta"] = 0.5 if P["n_beta"] > 1.0 else 2.0
    params.update()
    after = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wl[:, 0], wl[:, 1], wl[:, 2])))[0]
    ref2 = _model("smooth", **{**P, "n_beta": float(params["n_beta"][0])}).brdf(wl, ws)
    assert np.max(np.abs(after - before)) > 0
    np.testing.assert_allclose(after / wl[:, 2].astype(np.float32), ref2, rtol=1e-3, atol=SMOOTH_F32_ABS_TOL)
    # so does a changed rounding, which switches the "round" term on or off (a re-trace)
    params["beta_round_deg"] = 0.0 if P.get("beta_round_deg", 0.0) > 0.0 else 3.0
    params.update()
    again = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wl[:, 0], wl[:, 1], wl[:, 2])))[0]
    ref3 = _model("smooth", **{**P, "n_beta": float(params["n_beta"][0]),
                               "beta_round_deg": float(params["beta_round_deg"][0])}).brdf(wl, ws)
    assert np.max(np.abs(again - after)) > 0
    np.testing.assert_allclose(again / wl[:, 2].astype(np.float32), ref3, rtol=1e-3, atol=SMOOTH_F32_ABS_TOL)
