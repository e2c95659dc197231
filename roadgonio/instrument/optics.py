"""Ray geometry of the instrument (docs/conventions.md section 4; the integration domains of paper eq. 3),
written once over an array namespace ``xp`` like :mod:`roadgonio.surface.model`, so the Mitsuba sensor
plugin, the numpy Monte Carlo and the quadrature integrator share it.

Vectors are ``(x, y, z)`` triples of arrays (or of Python floats). Per-instrument constants
(centres, axes, frames) are float64 numpy, computed once by :func:`detector_geometry` and
:func:`source_geometry`; only the per-sample arithmetic runs in ``xp``.

Detector (luminance meter). A detected ray runs from a pupil point ``p`` (disc of radius R_D
about the pupil centre, normal to the axis ``a`` = -w_o) to a field point ``q`` on the field stop's
conjugate plane at the focus distance F (disc of radius F tan gamma_D about the axis). Its weight
is the etendue factor of the pair, normalised to 1 on the axis, times the field sensitivity k_D
(:class:`~roadgonio.instrument.config.Detector`)::

    finite F:  weight = (F cos theta / |q - p|)^2        (= cos^2 theta dA_p dA_q / |q-p|^2 / (dA_p dA_q / F^2))
    F = inf:   weight = cos^4 theta                      (direction a + tan(gamma) u; cos theta dOmega = cos^4 theta du)

where theta is the angle between the ray and the axis. Source: a Lambertian disc of radius R_S at
distance D_S along w_i, facing the sample centre; a sample point ``x`` receives from a source
point ``s`` the geometric factor ``cos theta_i cos theta_s / |s - x|^2`` (times L_S dA_s).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from roadgonio.errors import GeometryError
from roadgonio.instrument.config import Detector, Instrument, Observation


def orthonormal_frame(n) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (s, t) completing the unit vector ``n`` to a right-handed frame (float64)."""
    n = np.asarray(n, dtype=np.float64)
    helper = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    s = np.cross(helper, n)
    s /= np.linalg.norm(s)
    t = np.cross(n, s)
    return s, t


def concentric_disc(xp, u1, u2):
    """Shirley-Chiu concentric map of the unit square to the unit disc (area preserving)."""
    a = 2.0 * u1 - 1.0
    b = 2.0 * u2 - 1.0
    first = xp.abs(a) > xp.abs(b)
    big = xp.where(first, a, b)
    small = xp.where(first, b, a)
    safe = xp.where(xp.abs(big) > 0.0, big, 1.0 + 0.0 * big)
    phi = (math.pi / 4.0) * small / safe
    r = big
    c, s = xp.cos(phi), xp.sin(phi)
    x = xp.where(first, r * c, r * s)
    y = xp.where(first, r * s, r * c)
    zero = xp.abs(big) == 0.0
    return xp.where(zero, 0.0 * a, x), xp.where(zero, 0.0 * a, y)


@dataclass(frozen=True)
class DetectorGeometry:
    """Constants of the luminance meter (float64)."""

    centre: np.ndarray       # pupil centre (m)
    axis: np.ndarray         # unit vector from the detector towards the sample (= -w_o)
    s: np.ndarray            # pupil/field plane frame
    t: np.ndarray
    pupil_radius_m: float
    focus_m: float           # math.inf = angular field
    tan_field: float         # tan(gamma_D)
    kd_edge: float = 1.0     # k_D at the field-stop edge (1 = uniform field sensitivity)

    @property
    def angular(self) -> bool:
        return math.isinf(self.focus_m)


@dataclass(frozen=True)
class SourceGeometry:
    """Constants of the source disc for one cell (float64)."""

    centre: np.ndarray       # disc centre (m)
    axis: np.ndarray         # unit emission axis, towards the sample centre (= -w_i)
    s: np.ndarray
    t: np.ndarray
    radius_m: float
    cos_beam: float | None   # cos of the beam half-angle; None: no beam limit


def detector_geometry(instrument: Instrument) -> DetectorGeometry:
    """Constants of the instrument's luminance meter."""
    return meter_geometry(instrument.observation, instrument.detector)


def meter_geometry(observation: Observation, detector: Detector) -> DetectorGeometry:
    """Constants of a luminance meter looking along ``observation`` (no source needed: the
    sensor plugin knows only its own part of the instrument)."""
    w_o = observation.w_o
    axis = -w_o
    s, t = orthonormal_frame(axis)
    return DetectorGeometry(centre=detector.distance_m * w_o, axis=axis, s=s, t=t,
                            pupil_radius_m=detector.pupil_radius_m, focus_m=detector.focus_distance_m,
                            tan_field=math.tan(math.radians(detector.field_half_angle_deg)),
                            kd_edge=float(detector.field_edge_sensitivity))


def source_geometry(instrument: Instrument, tan_eps: float, beta_deg: float) -> SourceGeometry:
    src = instrument.source
    w_i = instrument.w_i(tan_eps, beta_deg)
    axis = -w_i
    s, t = orthonormal_frame(axis)
    cos_beam = None if src.beam_half_angle_deg is None else math.cos(math.radians(src.beam_half_angle_deg))
    return SourceGeometry(centre=src.distance_m * w_i, axis=axis, s=s, t=t, radius_m=src.radius_m,
                          cos_beam=cos_beam)


def _comb(c0, v1, k1, v2, k2):
    """c0 + k1 v1 + k2 v2 component-wise (v1, v2, c0 float64 triples; k1, k2 arrays)."""
    return tuple(c0[i] + v1[i] * k1 + v2[i] * k2 for i in range(3))


def detector_ray(xp, geo: DetectorGeometry, pupil_xy, field_xy):
    """Ray of the pair (pupil point, field point).

    ``pupil_xy`` and ``field_xy`` are points of the unit disc (e.g. from :func:`concentric_disc`).
    Returns ``(origin, direction, weight)``: origin on the pupil, unit direction towards the
    sample, etendue weight normalised to 1 on the axis (module docstring). The direction is
    formed without subtracting nearby large coordinates, so it is accurate in float32.
    """
    px, py = pupil_xy
    fx, fy = field_xy
    rd = geo.pupil_radius_m
    a, s, t = geo.axis, geo.s, geo.t
    origin = _comb(geo.centre, s, rd * px, t, rd * py)
    if geo.angular:
        k1, k2 = geo.tan_field * fx, geo.tan_field * fy
        d = _comb(a, s, k1, t, k2)
        length = xp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        cos_t = 1.0 / length
        weight = cos_t * cos_t * cos_t * cos_t
    else:
        f = geo.focus_m
        ft = f * geo.tan_field
        # q - p = F a + F tan(gamma) (fx s + fy t) - R_D (px s + py t)
        fa = (a[0] * f, a[1] * f, a[2] * f)     # component-wise: F may be an opaque Dr.Jit scalar
        d = _comb(fa, s, ft * fx - rd * px, t, ft * fy - rd * py)
        length = xp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        cos_t = f / length
        weight = cos_t * cos_t * cos_t * cos_t
    if geo.kd_edge != 1.0:
        # field sensitivity k_D(rho) = 1 - (1 - e) rho^2 (paper eq. 3; Detector docstring)
        weight = weight * (1.0 - (1.0 - geo.kd_edge) * (fx * fx + fy * fy))
    inv = 1.0 / length
    direction = (d[0] * inv, d[1] * inv, d[2] * inv)
    return origin, direction, weight


def hit_plane(xp, origin, direction):
    """Intersection with the sample plane z = 0: ``(x, y, valid)``."""
    dz = direction[2]
    valid = dz < 0.0
    tt = -origin[2] / xp.where(valid, dz, -1.0 + 0.0 * dz)
    return origin[0] + tt * direction[0], origin[1] + tt * direction[1], valid


def source_point(src: SourceGeometry, disc_xy):
    """Point of the source disc for a unit-disc point (float64 constants, xp arrays)."""
    dx, dy = disc_xy
    return _comb(src.centre, src.s, src.radius_m * dx, src.t, src.radius_m * dy)


def source_coupling(xp, src: SourceGeometry, x, y, spoint):
    """From sample point (x, y, 0) to source point ``spoint``: the unit direction ``w`` towards the
    source and the geometric factor ``G = cos theta_i cos theta_s / |s - x|^2`` (0 outside the beam
    or below the horizon)."""
    vx, vy, vz = spoint[0] - x, spoint[1] - y, spoint[2] + 0.0 * x
    d2 = vx * vx + vy * vy + vz * vz
    inv = 1.0 / xp.sqrt(d2)
    w = (vx * inv, vy * inv, vz * inv)
    cos_i = w[2]
    cos_s = -(w[0] * src.axis[0] + w[1] * src.axis[1] + w[2] * src.axis[2])
    ok = (cos_i > 0.0) & (cos_s > 0.0)
    if src.cos_beam is not None:
        ok = ok & (cos_s >= src.cos_beam)
    g = xp.where(ok, cos_i * cos_s / d2, 0.0 * d2)
    return w, g


# ----------------------------------------------------------------------------------------------
# Geometry checks (float64 numpy): errors, not wrong numbers
# ----------------------------------------------------------------------------------------------

def footprint_boundary(instrument: Instrument, n: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """Points (x, y) on the boundary of the detector footprint on the plane z = 0: the rays from
    the pupil rim and centre through the field-stop rim (extreme rays of the bundle)."""
    geo = detector_geometry(instrument)
    ang = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    px = np.concatenate([np.cos(ang), [0.0]])
    py = np.concatenate([np.sin(ang), [0.0]])
    fx, fy = np.cos(ang), np.sin(ang)
    PX, FX = np.meshgrid(px, fx, indexing="ij")
    PY, FY = np.meshgrid(py, fy, indexing="ij")
    from roadgonio.arrays import NumpyOps
    o, d, _ = detector_ray(NumpyOps, geo, (PX.ravel(), PY.ravel()), (FX.ravel(), FY.ravel()))
    if np.any(np.asarray(d[2]) >= 0.0):
        raise GeometryError("the detector does not see the sample plane: some detected rays point upwards "
                            "(alpha minus the field and pupil angles must stay above the horizon)")
    x, y, _ = hit_plane(NumpyOps, o, d)
    return np.asarray(x), np.asarray(y)


def along_azimuth(x, y, delta_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (x, y) of the sample plane in the frame whose x runs along the observation azimuth
    ``delta_deg`` (the frame of the rectangular sample: docs/conventions.md section 4)."""
    c, s = math.cos(math.radians(delta_deg)), math.sin(math.radians(delta_deg))
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    return c * x + s * y, -s * x + c * y


def footprint_along_azimuth(instrument: Instrument, n: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """:func:`footprint_boundary` in the frame of :func:`along_azimuth`: x along the observation
    azimuth, y across it."""
    x, y = footprint_boundary(instrument, n)
    return along_azimuth(x, y, instrument.observation.delta_deg)


def check_detector(instrument: Instrument) -> tuple[float, float, float, float]:
    """Check that the detector sees the sample and that the footprint stays on a rectangular
    sample; returns the footprint bounds (xmin, xmax, ymin, ymax) in m, x along the observation
    azimuth (the rectangle's frame: its side ``size_x_m`` runs along the azimuth delta, as
    docs/conventions.md section 4 says, so turning the instrument about the vertical turns the
    rectangle with it)."""
    det = instrument.detector
    a = math.radians(instrument.observation.alpha_deg)
    if det.distance_m * math.sin(a) - det.pupil_radius_m * math.cos(a) <= 0.0:
        raise GeometryError(f"the detector pupil reaches below the sample plane (alpha = "
                            f"{instrument.observation.alpha_deg:g} deg, pupil radius {det.pupil_radius_m:g} m "
                            f"at {det.distance_m:g} m)")
    x, y = footprint_along_azimuth(instrument)
    bounds = (float(x.min()), float(x.max()), float(y.min()), float(y.max()))
    smp = instrument.sample
    if smp.mesh is None:
        hx, hy = smp.size_x_m / 2, smp.size_y_m / 2
        if bounds[0] < -hx or bounds[1] > hx or bounds[2] < -hy or bounds[3] > hy:
            raise GeometryError(
                f"the detector footprint leaves the sample: it spans x = {bounds[0]:.3f} ... {bounds[1]:.3f} m, "
                f"y = {bounds[2]:.3f} ... {bounds[3]:.3f} m, but the sample is {smp.size_x_m:g} m x "
                f"{smp.size_y_m:g} m (x = +-{hx:g}, y = +-{hy:g}; x along the observation azimuth); enlarge "
                "[sample] or narrow the field")
    return bounds


def check_source(instrument: Instrument, tan_eps: float, beta_deg: float) -> None:
    """The whole source disc must be above the sample plane."""
    if not math.isfinite(tan_eps) or tan_eps < 0:
        raise GeometryError(f"tan eps = {tan_eps} is not a valid illumination angle (expected 0 <= tan eps < inf)")
    src = instrument.source
    eps = math.atan(tan_eps)
    lowest = src.distance_m * math.cos(eps) - src.radius_m * math.sin(eps)
    if lowest <= 0.0:
        raise GeometryError(f"the source is below the horizon at tan eps = {tan_eps:g}, beta = {beta_deg:g}: "
                            f"its disc (radius {src.radius_m:g} m at {src.distance_m:g} m) reaches "
                            f"{lowest:.4f} m below/at the sample plane")


def beam_clips_footprint(instrument: Instrument, tan_eps: float, beta_deg: float, n: int = 32) -> bool:
    """True if the source's beam limit (``beam_half_angle_deg``) cuts off light that reaches the
    detector footprint at this cell: some ray from the source disc (rim points and centre) to the
    footprint boundary leaves the cone. False when the source has no beam limit."""
    src = instrument.source
    if src.beam_half_angle_deg is None:
        return False
    g = source_geometry(instrument, tan_eps, beta_deg)
    x, y = footprint_boundary(instrument)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    sp = g.centre[None, :] + g.radius_m * (np.cos(ang)[:, None] * g.s + np.sin(ang)[:, None] * g.t)
    pts = np.stack([x, y, np.zeros_like(x)], axis=-1)
    d = pts[None, :, :] - np.concatenate([sp, g.centre[None, :]])[:, None, :]
    cosang = (d @ g.axis) / np.linalg.norm(d, axis=-1)
    return bool(float(cosang.min()) < g.cos_beam)


def hit_check_points(n_random: int = 1 << 16, n_rim: int = 128, seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Unit-disc points ``(pupil (N, 2), field (N, 2))`` of the rays a footprint check must trace:
    the extreme rays of the detector bundle (pupil rim and centre x field rim) and ``n_random``
    random pairs (uniform over both discs). Feed them to :func:`detector_ray`."""
    ang = np.linspace(0.0, 2 * np.pi, n_rim, endpoint=False)
    rim = np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    pupil = np.concatenate([rim, [[0.0, 0.0]]])
    P, F = np.meshgrid(np.arange(len(pupil)), np.arange(len(rim)), indexing="ij")
    pu, fu = pupil[P.ravel()], rim[F.ravel()]
    rng = np.random.default_rng(seed)
    r1, r2 = np.sqrt(rng.random(n_random)), np.sqrt(rng.random(n_random))
    a1, a2 = rng.random(n_random) * 2 * np.pi, rng.random(n_random) * 2 * np.pi
    pu = np.concatenate([pu, np.stack([r1 * np.cos(a1), r1 * np.sin(a1)], -1)])
    fu = np.concatenate([fu, np.stack([r2 * np.cos(a2), r2 * np.sin(a2)], -1)])
    return pu, fu


def judge_hits(on_sample, hit_anything, x, y) -> dict:
    """Verdict of a footprint check over traced rays (boolean arrays: the ray hit the sample / hit
    some part of the scene; x, y the hit points): every detected ray must land on the sample, else
    a :class:`GeometryError` saying what the missing rays hit. Returns the ray count and the
    footprint's extent."""
    on_sample = np.asarray(on_sample, dtype=bool)
    hit_anything = np.asarray(hit_anything, dtype=bool)
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    miss = ~on_sample
    n_miss = int(miss.sum())
    if n_miss:
        elsewhere = hit_anything[miss]
        what = "hit another part of the scene" if elsewhere.any() else "miss every part of the scene"
        raise GeometryError(
            f"{n_miss} of {on_sample.size} detector rays do not hit the sample ({what}"
            + (f", e.g. at x = {x[miss][elsewhere][0]:.3f} m" if elsewhere.any() else "")
            + "): the detector footprint must lie on the sample; enlarge the sample or narrow the field")
    return {"rays": int(on_sample.size), "x_range": (float(x.min()), float(x.max())),
            "y_range": (float(y.min()), float(y.max()))}
