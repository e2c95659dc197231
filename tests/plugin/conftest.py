"""The plugin tier: every test here builds Mitsuba scenes, so each gets the variant of the ``mi``
fixture (tests/conftest.py), which skips the test, saying why, without a usable LLVM >= 16."""
from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _mitsuba_variant(mi):
    """The Mitsuba variant for every plugin test (or the skip, with its reason)."""
    return mi


class BsdfProbe:
    """Evaluates a BSDF the way Mitsuba's integrators call it, over numpy direction arrays (the BSDF
    tests of tests/plugin/test_plugin_bsdf.py and test_surface_bsdf.py): ``make`` a ``roadbsdf``
    (eq. 4 by its parameters, or ``surface=`` any surface of set_surface), then ``eval`` (= f cos
    theta_light, all channels, shape (3, n)), ``pdf`` and ``sample``."""

    def __init__(self, mi):
        from roadgonio.engines.mitsuba.plugins import register_plugins
        register_plugins()
        self.mi = mi

    def make(self, variant="power", channels="road", surface=None, **params):
        if surface is not None:
            b = self.mi.load_dict({"type": "roadbsdf", "channels": channels})
            b.set_surface(surface)
            return b
        return self.mi.load_dict({"type": "roadbsdf", "variant": variant, "channels": channels, **params})

    def si(self, ws):
        import drjit as dr
        mi = self.mi
        si = dr.zeros(mi.SurfaceInteraction3f, len(ws))
        si.wi = mi.Vector3f(ws[:, 0], ws[:, 1], ws[:, 2])
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        return si

    def vec(self, w):
        return self.mi.Vector3f(w[:, 0], w[:, 1], w[:, 2])

    def eval(self, bsdf, ws, wl):
        import numpy as np
        return np.array(bsdf.eval(self.mi.BSDFContext(), self.si(ws), self.vec(wl)), dtype=np.float64)

    def pdf(self, bsdf, ws, wl):
        import numpy as np
        return np.array(bsdf.pdf(self.mi.BSDFContext(), self.si(ws), self.vec(wl)), dtype=np.float64)

    def sample(self, bsdf, ws, u1, u2):
        import numpy as np
        mi = self.mi
        bs, w = bsdf.sample(mi.BSDFContext(), self.si(ws), mi.Float(u1), mi.Point2f(u2[:, 0], u2[:, 1]))
        wo = np.stack([np.array(bs.wo.x), np.array(bs.wo.y), np.array(bs.wo.z)], -1).astype(np.float64)
        return wo, np.array(bs.pdf, dtype=np.float64), np.array(w, dtype=np.float64)

    def assert_same(self, a, b, rng, n: int = 5000):
        """``a`` and ``b`` give the same eval, pdf and sampling (directions, pdf, weights) over random
        directions (float32 round-off apart); returns the sample weights of ``a``."""
        import numpy as np
        from helpers import rand_dirs
        ws, wl = rand_dirs(rng, n), rand_dirs(rng, n)
        np.testing.assert_allclose(self.eval(a, ws, wl), self.eval(b, ws, wl), rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(self.pdf(a, ws, wl), self.pdf(b, ws, wl), rtol=1e-6, atol=1e-9)
        u1, u2 = rng.random(n), rng.random((n, 2))
        wo_a, pdf_a, w_a = self.sample(a, ws, u1, u2)
        wo_b, pdf_b, w_b = self.sample(b, ws, u1, u2)
        np.testing.assert_allclose(wo_a, wo_b, atol=1e-6)
        np.testing.assert_allclose(pdf_a, pdf_b, rtol=1e-6)
        np.testing.assert_allclose(w_a, w_b, rtol=1e-6)
        return w_a

    def assert_reciprocal(self, bsdf, rng, rtol: float, atol: float, n: int = 4000):
        """f(a, c) = f(c, a) over random pairs, half of them near the mirror direction."""
        import numpy as np
        from helpers import near_mirror, rand_dirs
        a, c = rand_dirs(rng, n), rand_dirs(rng, n)
        c[: n // 2] = near_mirror(rng, a[: n // 2], 0.02)
        f_ac = self.eval(bsdf, a, c)[0] / c[:, 2].astype(np.float32)
        f_ca = self.eval(bsdf, c, a)[0] / a[:, 2].astype(np.float32)
        np.testing.assert_allclose(f_ac, f_ca, rtol=rtol, atol=atol)


@pytest.fixture(scope="module")
def plug(mi):
    """The :class:`BsdfProbe` of the module."""
    return BsdfProbe(mi)
