"""Independent float64 check of the stray light (docs/straylight.md, "Checks"): one diffuse wall beside the footprint,
by plain Monte Carlo in numpy, written apart from the Mitsuba backend (it shares only the
instrument's ray geometry, :mod:`roadgonio.instrument.optics`, and the BRDF model,
:mod:`roadgonio.surface.model`).

The scene: the flat sample z = 0 (x in [-a, a], y in [-b, b]), the instrument's source disc and
luminance meter (docs/conventions.md section 4), and one Lambertian wall of reflectance rho: the
rectangle y = y_w, x in [x_0, x_1], z in [0, h], reflecting towards +y (the sample's side, the
source's side: every source of the table has y >= 0, docs/conventions.md section 1). The sample
is one-sided and flat, the wall one-sided and planar, so light reaches the detector along exactly
three kinds of paths with at most three reflections (the sample's own included):

* direct: source -> x0 -> detector;
* ``wall``: source -> wall y -> x0 -> detector (first order in rho);
* ``sample_wall``: source -> sample z -> wall y -> x0 -> detector (first order in rho).

Longer paths alternate wall and sample (source -> wall -> sample -> wall -> x0, ...), are of order
rho^2 and need four reflections or more: a backend that follows at most three reflections
(``[scene] max_bounces = 3``) has exactly these three terms, with no bound to add.

With uniform radiance L of the source disc (area A_S), the detector signal of a sample with BRDF f
is the etendue-weighted mean over detector rays (weight w, hit x0, towards the detector w_o) of::

    direct       f(x0; s -> x0, w_o) L cos_x0 cos_s / |s - x0|^2 A_S                     (s on the disc)
    wall         f(x0; y -> x0, w_o) G(x0, y) A_W (rho / pi) L G(y, s) A_S               (y on the wall)
    sample_wall  f(x0; y -> x0, w_o) G(x0, y) A_W (rho / pi) f(z; s -> z, z -> y) G(y, z) A_Z L G(z, s) A_S

with G(p, q) = cos_p cos_q / |p - q|^2 and z uniform on the sample (area A_Z), and G(., s) 0 where
the source's hard cone (``beam_half_angle_deg``) does not emit, cos_s below its cosine; nothing in this
scene shades another part (the wall faces the sample and every source). The road channel uses
f = the model at x0 and at z, the Lambert channel f = 1/pi at both (a perfect diffuser in the same
scene). The estimates are means over independent batches, so their standard errors, and those of
the ratios, come from the spread of the batch sums (delta method), in float64.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from roadgonio.engines.result import ratio_se
from roadgonio.instrument import optics
from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import NumpyOps, RoadModel


@dataclass(frozen=True)
class Wall:
    """One Lambertian wall: the rectangle y = ``y_m``, ``x0_m`` <= x <= ``x1_m``, 0 <= z <=
    ``height_m``, reflecting towards +y with ``reflectance``."""

    y_m: float
    x0_m: float
    x1_m: float
    height_m: float
    reflectance: float

    @property
    def area(self) -> float:
        return (self.x1_m - self.x0_m) * self.height_m


#: Terms of the estimate (module docstring), each in the road and the Lambert channel.
TERMS = ("direct", "wall", "sample_wall")


def _disc(rng, n):
    r = np.sqrt(rng.random(n))
    a = 2.0 * np.pi * rng.random(n)
    return r * np.cos(a), r * np.sin(a)


def _g(p, q, n_p, n_q):
    """G(p, q) = |cos_p| |cos_q| / |p - q|^2 for the unit normals n_p, n_q (only where both faces
    look at each other, else 0) and the unit direction p -> q."""
    v = q - p
    d2 = np.einsum("ij,ij->i", v, v)
    u = v / np.sqrt(d2)[:, None]
    cp = u @ n_p if n_p.ndim == 1 else np.einsum("ij,ij->i", u, n_p)
    cq = -(u @ n_q) if n_q.ndim == 1 else -np.einsum("ij,ij->i", u, n_q)
    return np.where((cp > 0) & (cq > 0), cp * cq / d2, 0.0), u


def batch_terms(instrument: Instrument, model: RoadModel, wall: Wall, tan_eps: float, beta_deg: float,
                n: int, rng) -> np.ndarray:
    """Sums over ``n`` independent samples of the three terms in the road and Lambert channels:
    array (3 terms, 2 channels), float64 (module docstring; the source radiance is 1)."""
    smp = instrument.sample
    if smp.mesh is not None:
        raise ValueError("the reference needs the flat rectangular sample")
    up = np.array([0.0, 0.0, 1.0])
    wall_n = np.array([0.0, 1.0, 0.0])
    det = optics.detector_geometry(instrument)
    src = optics.source_geometry(instrument, tan_eps, beta_deg)
    # detector rays and their hits x0
    o, d, w = optics.detector_ray(NumpyOps, det, _disc(rng, n), _disc(rng, n))
    x, y, valid = optics.hit_plane(NumpyOps, o, d)
    if not np.all(valid):
        raise ValueError("detector rays that miss the sample plane")
    x0 = np.stack([x, y, np.zeros(n)], -1)
    wo = -np.stack([np.broadcast_to(c, (n,)) for c in d], -1)      # towards the detector, per ray
    w = np.asarray(w, dtype=np.float64) * np.ones(n)
    area_s = math.pi * src.radius_m ** 2
    if instrument.source.profiled:
        raise ValueError("the reference knows the uniform source and its hard cone, not a beam profile")
    cone = instrument.source.beam_half_angle_deg
    cos_cone = -1.0 if cone is None else math.cos(math.radians(cone))

    def g_source(p, n_p, s):
        """G(p, s) towards the source point s, 0 outside the source's cone."""
        g, u = _g(p, s, n_p, src.axis)
        return np.where(-(u @ src.axis) >= cos_cone, g, 0.0), u

    def source_points():
        sx, sy = _disc(rng, n)
        return src.centre[None, :] + src.radius_m * (sx[:, None] * src.s[None, :] + sy[:, None] * src.t[None, :])

    def f_both(p_in_dir, p_out_dir):
        """(road, Lambert) BRDF of the sample for incident and outgoing unit directions."""
        return model.brdf(p_in_dir, p_out_dir), np.full(len(p_in_dir), 1.0 / math.pi)

    out = np.zeros((3, 2))
    # direct
    s = source_points()
    g, u = g_source(x0, up, s)
    fr, fl = f_both(u, wo)
    out[0] = [np.sum(w * fr * g) * area_s, np.sum(w * fl * g) * area_s]
    # wall: y uniform on the wall
    yw = np.stack([wall.x0_m + (wall.x1_m - wall.x0_m) * rng.random(n), np.full(n, wall.y_m),
                   wall.height_m * rng.random(n)], -1)
    g_xy, u_xy = _g(x0, yw, up, wall_n)
    fr, fl = f_both(u_xy, wo)
    s = source_points()
    g_ys, _ = g_source(yw, wall_n, s)
    k = w * g_xy * wall.area * (wall.reflectance / math.pi)
    out[1] = [np.sum(k * fr * g_ys) * area_s, np.sum(k * fl * g_ys) * area_s]
    # sample -> wall: z uniform on the sample, another wall point and source point
    yw = np.stack([wall.x0_m + (wall.x1_m - wall.x0_m) * rng.random(n), np.full(n, wall.y_m),
                   wall.height_m * rng.random(n)], -1)
    g_xy, u_xy = _g(x0, yw, up, wall_n)
    fr, fl = f_both(u_xy, wo)
    hx, hy = 0.5 * smp.size_x_m, 0.5 * smp.size_y_m
    z = np.stack([-hx + 2 * hx * rng.random(n), -hy + 2 * hy * rng.random(n), np.zeros(n)], -1)
    g_yz, u_zy = _g(z, yw, up, wall_n)
    s = source_points()
    g_zs, u_zs = g_source(z, up, s)
    fzr, fzl = f_both(u_zs, u_zy)
    k = w * g_xy * wall.area * (wall.reflectance / math.pi) * g_yz * (4 * hx * hy) * g_zs * area_s
    out[2] = [np.sum(k * fr * fzr), np.sum(k * fl * fzl)]
    return out


def reference(instrument: Instrument, model: RoadModel, wall: Wall, tan_eps: float, beta_deg: float, *,
              samples: int = 1 << 22, batches: int = 64, seed: int = 0) -> dict:
    """k_A with the wall (``k_a``), of the direct light alone (``k_a_direct``) and the stray
    fraction 1 - S_direct[f] / S_total[f] of the road channel, each with its standard error (with
    ``se_dof`` = batches - 1 degrees of freedom), and the terms' batch sums (``terms``: batches x 3 x
    2), from ``samples`` samples in ``batches`` independent batches."""
    rng = np.random.default_rng([seed, 0x5EF])
    per = max(1, samples // batches)
    t = np.stack([batch_terms(instrument, model, wall, tan_eps, beta_deg, per, rng) for _ in range(batches)])
    ideal = math.pi * float(model.brdf(instrument.w_i(tan_eps, beta_deg), instrument.w_o()))
    tot = t.sum(axis=1)                                   # (batches, 2): road, Lambert
    k, k_se = ratio_se(tot[:, 0], tot[:, 1])
    kd, kd_se = ratio_se(t[:, 0, 0], t[:, 0, 1])
    q, q_se = ratio_se(t[:, 0, 0], tot[:, 0])
    return {"k_a": k / ideal, "se": k_se / ideal, "k_a_direct": kd / ideal, "k_a_direct_se": kd_se / ideal,
            "stray_fraction": 1.0 - q, "stray_fraction_se": q_se, "se_dof": float(batches - 1), "terms": t,
            "samples": per * batches}
