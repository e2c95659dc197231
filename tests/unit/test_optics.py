"""The instrument's ray geometry (roadgonio.instrument.optics) against independent results."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from roadgonio.errors import GeometryError
from roadgonio.instrument import optics
from roadgonio.instrument.config import load_instrument
from roadgonio.arrays import NumpyOps as xp
from roadgonio.instrument.optics import (check_detector, check_source, concentric_disc, detector_geometry,
                              detector_ray, hit_plane, source_coupling, source_geometry, source_point)
from tolerances import ALPHA, N_SIGMA

SEED = 20261122


def coaxial_disc_view_factor(r1, r2, h):
    """View factor from disc 1 (radius r1) to a coaxial parallel disc 2 (radius r2) at distance h
    (standard radiative-exchange result)."""
    R1, R2 = r1 / h, r2 / h
    X = 1.0 + (1.0 + R2 * R2) / (R1 * R1)
    q = (R2 / R1) ** 2
    return 2.0 * q / (X + math.sqrt(X * X - 4.0 * q))   # = (X - sqrt(X^2 - 4q))/2 without cancellation


def test_concentric_map_is_uniform_on_the_disc():
    u = np.random.default_rng(SEED).random((2, 200_000))
    x, y = concentric_disc(xp, u[0], u[1])
    r2 = x * x + y * y
    assert r2.max() <= 1.0 + 1e-12
    # area preserving: r^2 and the angle are uniform
    assert stats.kstest(r2, "uniform").pvalue > ALPHA
    assert stats.kstest((np.arctan2(y, x) + np.pi) / (2 * np.pi), "uniform").pvalue > ALPHA


@pytest.mark.parametrize("pupil, field_deg, focus", [(0.01, 0.3, 2.0), (0.05, 1.0, 1.0), (0.002, 0.05, 10.0)])
def test_mean_etendue_weight_matches_coaxial_discs(pupil, field_deg, focus):
    """Mean ray weight over pupil x field = G F^2 / (A_p A_q) with the exact etendue G of two
    coaxial discs: checks the weight, the disc sampling and the pairing together."""
    ins = load_instrument("portable").with_changes(detector={"pupil_radius_m": pupil, "field_half_angle_deg": field_deg,
                                                             "focus_m": focus, "distance_m": max(focus, 2.0)})
    geo = detector_geometry(ins)
    n = 400_000
    u = np.random.default_rng(SEED).random((4, n))
    _, _, w = detector_ray(xp, geo, concentric_disc(xp, u[0], u[1]), concentric_disc(xp, u[2], u[3]))
    rho = focus * math.tan(math.radians(field_deg))
    exact = focus ** 2 * coaxial_disc_view_factor(pupil, rho, focus) / rho ** 2
    se = w.std() / math.sqrt(n)
    assert abs(w.mean() - exact) < N_SIGMA * se + 1e-12


def test_axis_ray_hits_the_sample_centre_and_source_coupling_is_cos_eps_over_d2():
    ins = load_instrument("portable")
    geo = detector_geometry(ins)
    zero = np.zeros(1)
    o, d, w = detector_ray(xp, geo, (zero, zero), (zero, zero))
    x, y, ok = hit_plane(xp, o, d)
    assert ok.all() and abs(x[0]) < 1e-12 and abs(y[0]) < 1e-12 and w[0] == pytest.approx(1.0, abs=1e-15)
    for t, b in [(0.0, 0.0), (1.0, 30.0), (12.0, 0.0)]:
        src = source_geometry(ins, t, b)
        sp = source_point(src, (zero, zero))
        wdir, g = source_coupling(xp, src, zero, zero, sp)
        assert np.allclose(np.array(wdir).ravel(), ins.w_i(t, b), atol=1e-14)
        assert g[0] == pytest.approx(math.cos(math.atan(t)) / ins.source.distance_m ** 2, rel=1e-12, abs=0.0)


def test_source_coupling_at_a_point_above_the_plane_with_a_tilted_normal():
    """source_coupling's optional point z and normal (a mesh face): the default is the plane z = 0
    with the normal +z, bit for bit; otherwise G = (w . n)(-w . a) / d^2, 0 where the source is
    behind the face or outside the beam, against an independent float64 evaluation."""
    ins = load_instrument("portable").with_changes(source={"beam_half_angle_deg": 6.0})
    src = source_geometry(ins, 1.0, 30.0)
    rng = np.random.default_rng(SEED)
    n_pts = 4000
    x, y, z = rng.uniform(-0.2, 0.2, n_pts), rng.uniform(-0.1, 0.1, n_pts), rng.uniform(-0.01, 0.01, n_pts)
    disc = concentric_disc(xp, rng.random(n_pts), rng.random(n_pts))
    sp = source_point(src, disc)
    w0, g0 = source_coupling(xp, src, x, y, sp, disc)
    w1, g1 = source_coupling(xp, src, x, y, sp, disc, z=0.0 * x, normal=(0.0, 0.0, 1.0))
    np.testing.assert_array_equal(g1, g0)
    normal = rng.normal(size=(n_pts, 3)) * 0.5 + [0.0, 0.0, 1.0]
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    away = -ins.w_i(1.0, 30.0)[:2] / np.linalg.norm(ins.w_i(1.0, 30.0)[:2])
    normal[:50] = [0.95 * away[0], 0.95 * away[1], math.sqrt(1.0 - 0.95 ** 2)]   # faces turned away from the source
    _, g = source_coupling(xp, src, x, y, sp, disc, z=z, normal=tuple(normal.T))
    v = np.stack(sp, 1) - np.stack([x, y, z], 1)
    d = np.linalg.norm(v, axis=1)
    u = v / d[:, None]
    cos_i, cos_s = np.einsum("ij,ij->i", u, normal), -(u @ src.axis)
    want = np.where((cos_i > 0) & (cos_s >= math.cos(math.radians(6.0))), cos_i * cos_s / d ** 2, 0.0)
    np.testing.assert_allclose(g, want, rtol=1e-12, atol=0.0)
    assert (g == 0).any() and (g > 0).any() and np.all(g[:50] == 0.0)


def test_source_frames_of_many_cells_are_those_of_each_cell():
    """optics.source_frames (the disc's placement, once): over arrays of cells it gives each cell's
    source_geometry bit for bit (the Mitsuba engine and the numpy backends place the same disc), the
    centre at D_S along w_i, the axis -w_i and (s, t, axis) a right-handed orthonormal frame; a
    fixed-height path has its D_S per cell."""
    for ins in (load_instrument("portable"), load_instrument("corridor")):
        T, B = np.meshgrid([0.0, 0.5, 2.0, 12.0], [0.0, 45.0, 180.0], indexing="ij")
        place = optics.source_frames(ins, T.ravel(), B.ravel())
        for k, (t, b) in enumerate(zip(T.ravel(), B.ravel())):
            one = source_geometry(ins, t, b)
            for got, want in ((place.centre[k], one.centre), (place.axis[k], one.axis), (place.s[k], one.s),
                              (place.t[k], one.t)):
                np.testing.assert_array_equal(got, want)
            assert place.distance_m[k] == optics.source_distance_m(ins.source, float(t))
            np.testing.assert_allclose(place.centre[k], -place.distance_m[k] * place.axis[k], rtol=1e-15, atol=1e-15)
        frame = np.stack([place.s, place.t, place.axis], axis=1)
        np.testing.assert_allclose(frame @ np.swapaxes(frame, 1, 2), np.broadcast_to(np.eye(3), frame.shape), atol=1e-15)
        np.testing.assert_allclose(np.linalg.det(frame), 1.0, rtol=1e-14)


def test_angular_field_weight_is_cos4():
    ins = load_instrument("portable").with_changes(detector={"focus_m": "inf", "pupil_radius_m": 0.0})
    geo = detector_geometry(ins)
    fx = np.array([0.0, 1.0, 0.5])
    o, d, w = detector_ray(xp, geo, (np.zeros(3), np.zeros(3)), (fx, np.zeros(3)))
    cos_t = np.array(d).T @ geo.axis
    assert np.allclose(w, cos_t ** 4, rtol=1e-14)
    assert math.degrees(math.acos(cos_t[1])) == pytest.approx(ins.detector.field_half_angle_deg, rel=1e-9)


def test_geometry_errors():
    ins = load_instrument("portable")
    check_detector(ins)
    with pytest.raises(GeometryError, match="leaves the sample"):
        check_detector(ins.with_changes(sample={"size_x_m": 0.3}))
    with pytest.raises(GeometryError, match="below"):
        check_detector(ins.with_changes(observation={"alpha_deg": 0.2}, detector={"pupil_radius_m": 0.01}))
    check_source(ins, 12.0, 0.0)
    with pytest.raises(GeometryError, match="below the horizon"):
        check_source(ins.with_changes(source={"radius_m": 0.5}), 12.0, 0.0)


@pytest.mark.parametrize("edge", [0.0, 0.5, 1.7])
def test_field_sensitivity_profile_kd(edge):
    """k_D(rho) = 1 - (1 - e) rho^2 over the field: with a pinhole and a tiny angular field (cos^4 = 1
    to 1e-10) the mean weight over the field disc is the disc average of k_D, 1 - (1 - e)/2."""
    ins = load_instrument("portable").with_changes(detector={"pupil_radius_m": 0.0, "focus_m": "inf",
                                                             "field_half_angle_deg": 0.001,
                                                             "field_edge_sensitivity": edge})
    geo = detector_geometry(ins)
    n = 200_000
    u = np.random.default_rng(SEED).random((2, n))
    zero = np.zeros(n)
    _, _, w = detector_ray(xp, geo, (zero, zero), concentric_disc(xp, u[0], u[1]))
    exact = 1.0 - (1.0 - edge) / 2.0
    assert abs(w.mean() - exact) < N_SIGMA * w.std() / math.sqrt(n) + 1e-9
    # the profile is exactly 1 at the centre and e at the edge
    _, _, w_c = detector_ray(xp, geo, (np.zeros(2), np.zeros(2)), (np.array([0.0, 1.0]), np.zeros(2)))
    cos4 = math.cos(math.radians(0.001)) ** 4          # etendue factor at the field edge
    assert w_c[0] == pytest.approx(1.0, abs=1e-12) and w_c[1] == pytest.approx(edge * cos4, abs=1e-12)


# -- the checks of the instrument room (used by the Mitsuba scene, numpy here) ------------------

def test_beam_clip_check():
    inst = load_instrument("portable")
    assert not optics.beam_clips_footprint(inst, 4.0, 0.0)                             # no beam limit
    assert optics.beam_clips_footprint(inst.with_changes(source={"beam_half_angle_deg": 0.01}), 4.0, 0.0)
    assert not optics.beam_clips_footprint(inst.with_changes(source={"beam_half_angle_deg": 60.0}), 4.0, 0.0)


def _brute_emission_angle_deg(inst, tan_eps, beta_deg, n=32):
    """The largest angle from the source axis over the rays from the disc's n rim points and centre
    to every point of the footprint boundary (what the beam check computed at each cell before
    trial 10 D14), written apart from the code under test."""
    g = source_geometry(inst, tan_eps, beta_deg)
    x, y = optics.footprint_boundary(inst)
    worst = -1.0
    for k in range(n + 1):
        ang = 2 * math.pi * k / n
        sp = g.centre + (g.radius_m * (math.cos(ang) * g.s + math.sin(ang) * g.t) if k < n else 0.0)
        d = np.stack([x - sp[0], y - sp[1], -sp[2] + 0 * x], axis=-1)
        worst = max(worst, float(np.degrees(np.arccos(np.clip(d @ g.axis / np.sqrt((d * d).sum(-1)), -1, 1))).max()))
    return worst


def _centre_angle_deg(inst, tan_eps, beta_deg):
    """The largest angle over the rays from the disc's centre alone (the quick lower bound)."""
    g = source_geometry(inst, tan_eps, beta_deg)
    x, y = optics.footprint_boundary(inst)
    d = np.stack([x - g.centre[0], y - g.centre[1], -g.centre[2] + 0 * x], axis=-1)
    return float(np.degrees(np.arccos(np.clip(d @ g.axis / np.sqrt((d * d).sum(-1)), -1, 1))).max())


#: float64 round-off of an angle of a few degrees through acos (the hull and the brute force sum
#: their dot products in different orders)
ANGLE_TOL_DEG = 1e-9
BEAM_CELLS = [(0.0, 0.0), (5.0, 0.0), (12.0, 30.0), (2.0, 90.0), (1.0, 180.0)]


def test_beam_clip_check_agrees_with_every_footprint_point():
    """trial 10 D14: the check now looks at the footprint's convex hull after quick bounds from the
    disc's centre; its angles and verdicts must be those of every boundary point, also just either
    side of a cell's angle and where only the full computation can tell (a limit between the
    centre's angle and the disc's), and above 90 deg (wide preset: no convex cone)."""
    inst = load_instrument("portable")
    brute = [_brute_emission_angle_deg(inst, t, b) for t, b in BEAM_CELLS]
    got = optics.footprint_emission_angles_deg(inst, BEAM_CELLS)
    assert np.allclose(got, brute, rtol=0, atol=ANGLE_TOL_DEG)
    for limit in (90.0, 10.0, 5.0):
        clips = optics.beam_clips_cells(inst.with_changes(source={"beam_half_angle_deg": limit}), BEAM_CELLS)
        assert clips.tolist() == [a > limit for a in brute]
    t, b = BEAM_CELLS[1]
    lo, full = _centre_angle_deg(inst, t, b), brute[1]
    assert full - lo > 0.5                                     # the disc adds ~1.4 deg at 1 m
    for limit, clip in (((lo + full) / 2, True), (full - 1e-6, True), (full + 1e-6, False)):
        assert optics.beam_clips_footprint(inst.with_changes(source={"beam_half_angle_deg": limit}), t, b) is clip
    wide = load_instrument("wide")
    assert optics.footprint_emission_angle_deg(wide, 12.0, 0.0) == pytest.approx(
        _brute_emission_angle_deg(wide, 12.0, 0.0), abs=ANGLE_TOL_DEG)
    assert _brute_emission_angle_deg(wide, 12.0, 0.0) > 90.0


def test_beam_clip_check_of_a_table_reads_the_footprint_once(monkeypatch):
    """trial 10 D14: a 90 deg limit made a table 13-80x slower, the footprint's ~9300 boundary points
    being traced and compared with 33 source points at each of the 580 cells. Now the footprint is
    traced once per table and a limit that clips nowhere is settled by the quick bounds alone."""
    inst = load_instrument("portable").with_changes(source={"beam_half_angle_deg": 90.0})
    cells = [(t, b) for t in (0.0, 0.5, 1.0, 2.0, 5.0, 8.0, 12.0) for b in (0.0, 10.0, 30.0, 90.0, 180.0)]
    calls = {"boundary": 0, "full": 0}
    boundary, full = optics.footprint_boundary, optics.footprint_emission_angles_deg

    def count(name, f):
        def wrapped(*a, **k):
            calls[name] += 1
            return f(*a, **k)
        return wrapped
    monkeypatch.setattr(optics, "footprint_boundary", count("boundary", boundary))
    monkeypatch.setattr(optics, "footprint_emission_angles_deg", count("full", full))
    assert not optics.beam_clips_cells(inst, cells).any()
    assert calls == {"boundary": 1, "full": 0}
    # a limit at one cell's own angle leaves that cell to the full computation, which takes the
    # outline the quick bounds traced instead of tracing it again
    limit = float(full(load_instrument("portable"), [(5.0, 0.0)])[0])
    calls.update(boundary=0, full=0)
    optics.beam_clips_cells(inst.with_changes(source={"beam_half_angle_deg": limit}), cells)
    assert calls == {"boundary": 1, "full": 1}


def test_hit_check_points_and_verdict():
    pu, fu = optics.hit_check_points(n_random=100, n_rim=8, seed=1)
    assert pu.shape == fu.shape == (9 * 8 + 100, 2)
    assert np.allclose(np.hypot(*fu[:72].T), 1.0) and np.all(np.hypot(*pu.T) <= 1.0 + 1e-12)
    x, y = np.linspace(-1.0, 1.0, 5), np.zeros(5)
    ok = optics.judge_hits(np.ones(5, bool), np.ones(5, bool), x, y)
    assert ok == {"rays": 5, "x_range": (-1.0, 1.0), "y_range": (0.0, 0.0)}
    on = np.array([True, True, False, True, True])
    with pytest.raises(GeometryError, match="1 of 5 detector rays .*hit another part.*x = 0.000"):
        optics.judge_hits(on, np.ones(5, bool), x, y)
    with pytest.raises(GeometryError, match="miss every part"):
        optics.judge_hits(on, on, x, y)
    with pytest.raises(GeometryError, match="miss every part") as err:     # a mesh sample: its file is named
        optics.judge_hits(on, on, x, y, "scenes/road.ply")
    assert (err.value.path, err.value.field) == ("scenes/road.ply", "sample.mesh")
    with pytest.raises(GeometryError) as err:
        optics.judge_hits(on, on, x, y)
    assert err.value.path is None


# -- the rectangle's x runs along the observation azimuth (docs/conventions.md section 4) ---------

@pytest.mark.parametrize("delta", [0.0, 37.0, 90.0, -135.0, 270.0])
def test_the_rectangle_turns_with_the_observation_azimuth(delta):
    """Turning the whole instrument about the vertical turns its footprint and its rectangle alike:
    the footprint bounds in the rectangle's frame are those at delta = 0, the 2 m x 0.5 m lab
    sample holds the footprint at every delta, and the rectangle's corners, projected on the
    azimuth direction written here, are +-size_x/2 (its vertices computed by the instrument room)."""
    from roadgonio.instrument.mesh import rectangle_triangles
    inst = load_instrument("lab").with_changes(observation={"delta_deg": delta})
    ref = check_detector(load_instrument("lab"))
    got = check_detector(inst)
    assert got == pytest.approx(ref, abs=1e-9)
    t = rectangle_triangles(2.0, 0.5, delta)
    a = np.array([math.cos(math.radians(delta)), math.sin(math.radians(delta))])
    b = np.array([-a[1], a[0]])
    along, across = t.vertices[:, :2] @ a, t.vertices[:, :2] @ b
    assert sorted(np.round(along, 12)) == [-1.0, -1.0, 1.0, 1.0] and sorted(np.round(across, 12)) == [-0.25, -0.25, 0.25, 0.25]
    # a rectangle too short along the azimuth is refused whatever delta is
    with pytest.raises(GeometryError, match="leaves the sample"):
        check_detector(inst.with_changes(sample={"size_x_m": 0.01, "size_y_m": 2.0}))
