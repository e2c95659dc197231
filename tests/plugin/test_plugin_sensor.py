"""The luminance-meter sensor plugin (plugins/lummeter.py): its rays against roadgonio.instrument.optics in
float64 numpy, and its Lambert signal against a float64 quadrature of the same ray bundle."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.instrument.config import Instrument
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import RoadModel
from roadgonio.instrument.optics import (concentric_disc, detector_geometry, detector_ray, hit_plane, source_coupling,
                              source_geometry, source_point)
from tolerances import N_SIGMA


#: float32 positions: ~6e-8 relative of coordinates up to D_D (m) -> absolute tolerance per metre.
POS_TOL_PER_M = 1e-6
#: float32 unit directions and weights.
DIR_TOL = 1e-6
WEIGHT_RTOL = 1e-6
#: Quadrature orders of the float64 reference (radial Gauss x angular trapezoid on each disc);
#: the test uses twice these orders; the change from these orders bounds the reference's error.
QUAD = {"pupil": (4, 8), "field": (10, 24), "source": (4, 8)}

BASE = {"observation": {"alpha_deg": 1.0}, "source": {"distance_m": 1.0, "radius_m": 0.02},
        "detector": {"distance_m": 2.0, "pupil_radius_m": 0.01, "field_half_angle_deg": 0.25},
        "sample": {"size_x_m": 6.0, "size_y_m": 0.5}}


def instrument(**det):
    d = {k: dict(v) for k, v in BASE.items()}
    d["detector"].update(det)
    return Instrument.from_dict(d)


CASES = {"focused": {}, "angular": {"focus_m": "inf"}, "pinhole": {"pupil_radius_m": 0.0},
         "single_direction": {"field_half_angle_deg": 0.0}, "off_focus": {"focus_m": 1.5}}


@pytest.fixture(scope="module")
def make_sensor(mi):
    from roadgonio.engines.mitsuba.plugins import register_plugins
    from roadgonio.engines.mitsuba.scene import detector_props, film_dict
    register_plugins()

    def make(inst, res=8):
        film, sampler = film_dict(res, 4)
        return mi.load_dict({"type": "lummeter", "film": film, "sampler": sampler, **detector_props(inst.observation, inst.detector)})
    return make


@pytest.mark.parametrize("case", list(CASES))
def test_rays_match_optics(mi, make_sensor, case, rng_seed):
    inst = instrument(**CASES[case])
    sensor = make_sensor(inst)
    rng = np.random.default_rng(rng_seed)
    n = 20000
    u = rng.random((n, 2)).astype(np.float32)
    v = rng.random((n, 2)).astype(np.float32)
    ray, w = sensor.sample_ray(0.0, 0.5, mi.Point2f(u[:, 0], u[:, 1]), mi.Point2f(v[:, 0], v[:, 1]))
    o = np.stack([np.array(ray.o.x), np.array(ray.o.y), np.array(ray.o.z)], -1)
    d = np.stack([np.array(ray.d.x), np.array(ray.d.y), np.array(ray.d.z)], -1)
    w = np.array(w, dtype=np.float64)[0]
    geo = detector_geometry(inst)
    field = concentric_disc(NumpyOps, u[:, 0].astype(np.float64), u[:, 1].astype(np.float64))
    pupil = concentric_disc(NumpyOps, v[:, 0].astype(np.float64), v[:, 1].astype(np.float64))
    o_ref, d_ref, w_ref = detector_ray(NumpyOps, geo, pupil, field)
    np.testing.assert_allclose(o, np.stack(o_ref, -1), atol=POS_TOL_PER_M * inst.detector.distance_m)
    np.testing.assert_allclose(d, np.stack(d_ref, -1), atol=DIR_TOL)
    np.testing.assert_allclose(w, w_ref, rtol=WEIGHT_RTOL)
    # the pupil and the field are exact discs: extreme rays reach their rims
    if inst.detector.pupil_radius_m > 0:
        radial = np.linalg.norm(o - geo.centre, axis=1) / inst.detector.pupil_radius_m
        assert radial.max() <= 1 + 1e-4 and radial.max() > 0.99


def _disc_nodes(nr, nt):
    """Polar Gauss-Legendre (radius, weight r dr) x trapezoid (angle) nodes of the unit disc;
    weights sum to 1 (mean over the disc)."""
    x, wx = np.polynomial.legendre.leggauss(nr)
    r = 0.5 * (x + 1.0)
    wr = 0.5 * wx * r
    t = (np.arange(nt) + 0.5) * 2 * np.pi / nt
    R, T = np.meshgrid(r, t, indexing="ij")
    W = np.meshgrid(wr, np.full(nt, 2 * np.pi / nt), indexing="ij")
    w = (W[0] * W[1]).ravel() / np.pi
    return R.ravel() * np.cos(T.ravel()), R.ravel() * np.sin(T.ravel()), w


def lambert_signal_quadrature(inst, tan_eps, beta, scale=1):
    """float64: mean over pupil x field of weight x E(x)/pi, E from the source disc (radiance
    D_S^2/(pi R_S^2), the scene's units)."""
    geo = detector_geometry(inst)
    src = source_geometry(inst, tan_eps, beta)
    from roadgonio.engines.mitsuba.scene import source_radiance
    L = source_radiance(inst)
    ppx, ppy, pw = _disc_nodes(QUAD["pupil"][0] * scale, QUAD["pupil"][1] * scale)
    fx, fy, fw = _disc_nodes(QUAD["field"][0] * scale, QUAD["field"][1] * scale)
    sx, sy, sw = _disc_nodes(QUAD["source"][0] * scale, QUAD["source"][1] * scale)
    P, F = np.meshgrid(np.arange(len(ppx)), np.arange(len(fx)), indexing="ij")
    P, F = P.ravel(), F.ravel()
    o, d, w = detector_ray(NumpyOps, geo, (ppx[P], ppy[P]), (fx[F], fy[F]))
    x, y, _ = hit_plane(NumpyOps, o, d)
    sp = source_point(src, (sx, sy))
    _, g = source_coupling(NumpyOps, src, x[:, None], y[:, None], tuple(c[None, :] for c in sp))
    area = math.pi * src.radius_m ** 2
    E = L * area * (g * sw[None, :]).sum(axis=1)
    return float(np.sum(pw[P] * fw[F] * w * E / math.pi))


# Cells where the source is far from the footprint, so the quadrature converges fast (with the
# source at 1 m, cells such as tan 12, beta 0 put part of the footprint almost under the source:
# correct for the renderer, slow for a fixed-order quadrature).
@pytest.mark.parametrize("case,cell", [("focused", (0.0, 0.0)), ("focused", (12.0, 90.0)),
                                       ("angular", (12.0, 120.0)), ("off_focus", (2.0, 180.0))])
def test_lambert_signal_matches_float64_quadrature(mi, case, cell):
    from roadgonio.engines.mitsuba.backend import pair_variance
    from roadgonio.engines.mitsuba.scene import build_scene
    inst = instrument(**CASES[case])
    ref1 = lambert_signal_quadrature(inst, *cell)
    ref = lambert_signal_quadrature(inst, *cell, scale=2)
    quad_err = abs(ref - ref1)                         # error estimate of the lower order
    assert quad_err <= 2e-5 * abs(ref)                 # the reference is converged
    rs = build_scene(inst, RoadModel.lambert(), resolution=64)
    rs.place_source(*cell)
    img = rs.render(seed=3, spp=64)
    g = img[..., 1]
    mean = float(g.mean())
    se = math.sqrt(pair_variance(g))
    assert se < 1e-3 * mean
    assert abs(mean - ref) <= N_SIGMA * se + quad_err + 2e-6 * ref, (mean, ref, se, quad_err)


def test_sensor_properties_are_validated_like_an_instrument_file(mi, make_sensor):
    """focus_m = inf is an angular field (no -1 sentinel any more): a focus <= 0 is an error naming the key."""
    from roadgonio.engines.mitsuba.scene import film_dict
    film, sampler = film_dict(8, 4)
    angular = mi.load_dict({"type": "lummeter", "film": film, "sampler": sampler, "distance_m": 5.0,
                            "focus_m": math.inf, "field_half_angle_deg": 0.1})
    assert angular.geometry.angular and angular.detector.focus_m == math.inf and "F=inf" in angular.to_string()
    with pytest.raises(Exception, match="detector.focus_m"):
        mi.load_dict({"type": "lummeter", "film": film, "sampler": sampler, "distance_m": 5.0, "focus_m": -1.0})


@pytest.mark.parametrize("dark, rows, cols", [("left", slice(None), slice(0, 14)), ("top", slice(0, 14), slice(None))])
def test_the_square_view_is_the_field_as_the_meter_sees_it(mi, tmp_path, dark, rows, cols):
    """The ``square`` mapping (render's view.exr) is a picture of the field plane oriented like a
    field sensitivity map (docs/conventions.md: x to the right as the meter looks, y up, rows from
    the top): a map that is 0 on the left (top) half leaves the left (top) of the 32 x 32 view
    black and the rest lit. Mutation audit 9b: a view mirrored left-right passed every test."""
    from helpers import ROAD, preset, write_map_csv
    from roadgonio.engines.mitsuba.scene import LAMBERT, build_scene
    fn = {"left": lambda x, y: np.where(x < 0, 0.0, 1.0) + 0 * y, "top": lambda x, y: np.where(y > 0, 0.0, 1.0) + 0 * x}
    path = write_map_csv(tmp_path / f"{dark}.csv", fn[dark], 64)
    rs = build_scene(preset("lab").with_changes(detector={"field_sensitivity": str(path)}), ROAD, resolution=32)
    rs.place_source(2.0, 0.0)
    rs.sensor.mapping = "square"
    img = rs.render(1, 16)[..., LAMBERT]
    flipped = img[::-1, ::-1]
    assert np.all(img[rows, cols] == 0.0) and flipped[rows, cols].mean() > 0.0


def test_the_square_views_right_is_plus_y_as_its_label_says(mi):
    """(audit 22) render.png labelled the view's horizontal axis 'left = +y'; the view's right
    (film u > 1/2, drawn on the right) looks at the sample's +y side, the map's x to the right as
    the meter looks (docs/conventions.md)."""
    import inspect

    from helpers import ROAD, preset
    from roadgonio.engines.mitsuba import images
    from roadgonio.engines.mitsuba.scene import build_scene
    rs = build_scene(preset("portable"), ROAD, resolution=8)
    rs.sensor.mapping = "square"
    ys = []
    for u in (0.1, 0.9):
        o, d, _ = rs.sensor.rays(mi.Point2f(u, 0.5), mi.Point2f(0.5, 0.5))
        k = -o[2][0] / d[2][0]                       # the ray's hit on the sample plane z = 0
        ys.append(o[1][0] + k * d[1][0])
    assert ys[0] < 0.0 < ys[1], ys
    assert "right = +y" in inspect.getsource(images) and "left = +y" not in inspect.getsource(images)
