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

where theta is the angle between the ray and the axis, times k_D: the radial profile
``1 - (1 - e) rho^2`` or the sensitivity map (:func:`field_map_value`). Source: a disc of radius R_S
at distance D_S along w_i, facing the sample centre; a sample point ``x`` receives from a source
point ``s`` the geometric factor ``cos theta_i cos theta_s / |s - x|^2`` times the source's relative
radiance ``L / L_0`` at ``s`` in that direction (:func:`source_radiance_factor`: 1 for the uniform
Lambertian disc; the profiles of :mod:`roadgonio.instrument.profiles`), times L_0 dA_s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple, Sequence

import numpy as np

from roadgonio.errors import GeometryError
from roadgonio.instrument.config import Detector, Instrument, Observation, Source
from roadgonio.instrument.mesh import mesh_location
from roadgonio.instrument.profiles import ApertureProfile, BeamProfile, FieldMap, UniformTable, quadratic_edge


def source_distance_m(source: Source, tan_eps, xp=np):
    """D_S of the cell at ``tan_eps`` (m; a float for a float, an array for an array): the source's
    ``distance_m`` on an arc, ``height_m / cos eps = height_m sqrt(1 + tan^2 eps)`` on a
    fixed-height path (docs/conventions.md section 4, the corridor goniophotometer). The one formula
    every backend, the measurement model and the design's metrics use."""
    if source.path == "arc":
        if isinstance(tan_eps, (int, float)):
            return float(source.distance_m)
        return source.distance_m + 0.0 * xp.asarray(tan_eps)
    if isinstance(tan_eps, (int, float)):
        return float(source.height_m) * math.sqrt(1.0 + float(tan_eps) ** 2)
    t = xp.asarray(tan_eps)
    return source.height_m * xp.sqrt(1.0 + t * t)


def orthonormal_frame(n) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (s, t) completing the unit vector(s) ``n`` (shape (3,) or (..., 3)) to a
    right-handed frame, float64: ``s = normalise(h x n)`` with the helper h = +z, or +x where
    |n_z| >= 0.9, and ``t = n x s``. The one rule of the numpy side (the detector, the source
    discs, a mesh face's local frame); ``plugins/ka_batch.py``'s ``frame_from_axis`` is its twin on
    the device. The norm is a dot product per vector, so one vector and a stack of them give the
    same bits."""
    n = np.asarray(n, dtype=np.float64)
    helper = np.where(np.abs(n[..., 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    s = np.cross(helper, n)
    s = s / np.sqrt(np.matmul(s[..., None, :], s[..., :, None])[..., 0, :])
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
    kd_map: FieldMap | None = None   # k_D as a map over the field stop (exclusive with kd_edge)
    #: field-disc coordinates (along s, t) -> map coordinates (x right, y up as the meter looks):
    #: x = m[0] f_s + m[1] f_t, y = m[2] f_s + m[3] f_t
    map_axes: tuple = (-1.0, 0.0, 0.0, 1.0)

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
    beam: BeamProfile = BeamProfile()              # angular profile P(theta) of the radiance
    aperture: ApertureProfile = ApertureProfile()  # profile A(rho) of the radiance over the aperture

    @property
    def profiled(self) -> bool:
        return not (self.beam.uniform and self.aperture.uniform)


def detector_geometry(instrument: Instrument) -> DetectorGeometry:
    """Constants of the instrument's luminance meter."""
    return meter_geometry(instrument.observation, instrument.detector)


def meter_geometry(observation: Observation, detector: Detector) -> DetectorGeometry:
    """Constants of a luminance meter looking along ``observation`` (no source needed: the
    sensor plugin knows only its own part of the instrument)."""
    w_o = observation.w_o
    axis = -w_o
    s, t = orthonormal_frame(axis)
    # the map's axes: x horizontal to the right as the meter looks along its axis, y up
    d = math.radians(observation.delta_deg)
    right = np.array([-math.sin(d), math.cos(d), 0.0])
    up = np.cross(right, axis)
    return DetectorGeometry(centre=detector.distance_m * w_o, axis=axis, s=s, t=t,
                            pupil_radius_m=detector.pupil_radius_m, focus_m=detector.focus_distance_m,
                            tan_field=math.tan(math.radians(detector.field_half_angle_deg)),
                            kd_edge=float(detector.field_edge_sensitivity), kd_map=detector.field_map,
                            map_axes=(float(s @ right), float(t @ right), float(s @ up), float(t @ up)))


class SourcePlacement(NamedTuple):
    """Where the source disc of a cell is (float64; one cell: vectors (3,) and a float D_S; many:
    (..., 3) and (...,))."""

    centre: np.ndarray       # D_S w_i
    axis: np.ndarray         # -w_i, the emission axis, towards the sample centre
    s: np.ndarray            # the disc's plane (:func:`orthonormal_frame` of the axis)
    t: np.ndarray
    distance_m: Any          # D_S (:func:`source_distance_m`)


def source_frames(instrument: Instrument, tan_eps, beta_deg) -> SourcePlacement:
    """The placement of the source disc of the cell(s) (tan eps, beta), written once
    (docs/conventions.md section 4): centre ``D_S w_i`` at the cell's D_S, facing the sample centre
    (axis ``-w_i``), with the frame (s, t) of :func:`orthonormal_frame`. Numbers (a float tan eps
    is taken through :meth:`Instrument.w_i`'s scalar path) or arrays (broadcast). Used by
    :func:`source_geometry` (one cell, the numpy backends) and by the Mitsuba engine (every cell
    of a launch)."""
    w_i = instrument.w_i(tan_eps, beta_deg)
    axis = -w_i
    s, t = orthonormal_frame(axis)
    if np.ndim(tan_eps) or np.ndim(beta_deg):
        dist = np.broadcast_to(source_distance_m(instrument.source, np.asarray(tan_eps, dtype=np.float64)),
                               w_i.shape[:-1])
        centre = dist[..., None] * w_i
    else:
        dist = source_distance_m(instrument.source, float(tan_eps))
        centre = dist * w_i
    return SourcePlacement(centre, axis, s, t, dist)


def source_geometry(instrument: Instrument, tan_eps: float, beta_deg: float) -> SourceGeometry:
    """Constants of the source disc of one cell (its placement: :func:`source_frames`)."""
    src = instrument.source
    place = source_frames(instrument, tan_eps, beta_deg)
    cos_beam = None if src.beam_half_angle_deg is None else math.cos(math.radians(src.beam_half_angle_deg))
    return SourceGeometry(centre=place.centre, axis=place.axis, s=place.s, t=place.t,
                          radius_m=src.radius_m, cos_beam=cos_beam, beam=src.beam, aperture=src.aperture)


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
        weight = weight * quadratic_edge(geo.kd_edge, fx * fx + fy * fy)
    if geo.kd_map is not None:
        # field sensitivity k_D(x_D, y_D) from the map (paper eq. 3)
        weight = weight * field_map_value(xp, geo, fx, fy)
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


def mirror_line(src: SourceGeometry, x, y, wo):
    """The mirror plane of a detector ray (the vertical plane through its hit point (x, y, 0)
    containing w_o, where beta = 0 or 180 deg and an empirical term in |beta| has its kink) on the
    source disc: ``(a0, a1, a2)`` with ``a0 + a1 dx + a2 dy = 0`` in the unit-disc coordinates
    (``(s - x)_x w_o,y - (s - x)_y w_o,x`` is linear in them)."""
    r = src.radius_m
    a0 = (src.centre[0] - x) * wo[1] - (src.centre[1] - y) * wo[0]
    a1 = r * (src.s[0] * wo[1] - src.s[1] * wo[0])
    a2 = r * (src.t[0] * wo[1] - src.t[1] * wo[0])
    return a0, a1, a2


def source_coupling(xp, src: SourceGeometry, x, y, spoint, disc_xy=None, *, z=None, normal=None):
    """From sample point (x, y, z) to source point ``spoint``: the unit direction ``w`` towards the
    source and the geometric factor ``G = cos theta_i cos theta_s / |s - x|^2`` times the source's
    relative radiance at ``spoint`` in that direction (:func:`source_radiance_factor`; the source
    point's unit-disc coordinates ``disc_xy`` are needed for an aperture profile); 0 outside the
    beam or below the sample point's horizon. The one statement of eq. 3's source term. By default
    the point is on the plane z = 0 with the normal +z; a mesh sample passes the point's ``z`` and
    its unit ``normal`` (a component triple)."""
    vx, vy = spoint[0] - x, spoint[1] - y
    vz = spoint[2] + 0.0 * x if z is None else spoint[2] - z
    d2 = vx * vx + vy * vy + vz * vz
    inv = 1.0 / xp.sqrt(d2)
    w = (vx * inv, vy * inv, vz * inv)
    cos_i = w[2] if normal is None else w[0] * normal[0] + w[1] * normal[1] + w[2] * normal[2]
    cos_s = -(w[0] * src.axis[0] + w[1] * src.axis[1] + w[2] * src.axis[2])
    ok = (cos_i > 0.0) & (cos_s > 0.0)
    if src.cos_beam is not None:
        ok = ok & (cos_s >= src.cos_beam)
    g = cos_i * cos_s / d2
    factor = source_radiance_factor(xp, src.beam, src.aperture, w, src.axis, disc_xy)
    if factor is not None:
        g = g * factor
    g = xp.where(ok, g, 0.0 * d2)
    return w, g


def table_value(xp, table: UniformTable, x):
    """The tabulated function at ``x``: linear interpolation between the samples of the uniform
    grid (:class:`roadgonio.instrument.profiles.UniformTable`), ``x`` clamped to the grid. The
    table's ``values`` are a numpy array for numpy and a Dr.Jit array inside a kernel."""
    last = table.n - 1.0
    t = xp.minimum(xp.maximum((x - table.x0) * (1.0 / table.step), 0.0), last)
    k = xp.minimum(xp.floor(t), last - 1.0)
    frac = t - k
    v0 = xp.take(table.values, k)
    v1 = xp.take(table.values, k + 1.0)
    return v0 + frac * (v1 - v0)


def source_radiance_factor(xp, beam: BeamProfile, aperture: ApertureProfile, w, axis, disc_xy=None):
    """``L(s, theta) / L_0 = A(rho) P(theta)``: the relative radiance of the source point with
    unit-disc coordinates ``disc_xy`` (rho^2 = x^2 + y^2) in the emission direction ``-w`` (``w``:
    unit vector from the lit point towards the source point; ``axis``: the source's unit emission
    axis); docs/conventions.md section 4, :mod:`roadgonio.instrument.profiles`. ``None`` for the
    uniform Lambertian disc (factor 1, so the uniform source costs nothing and stays bit for bit).

    The emission angle is formed without cancellation near the axis (float32 kernels): its sine
    from the cross product ``|w x axis|`` and the half chord ``h = |w + axis|^2 / 2 = 1 - cos theta``
    (the half-chord form of :mod:`roadgonio.surface.model`: ``cos^n = exp(n log(1 - h))``).
    A tabulated profile is 0 beyond its last angle (a cell that needs it there is refused by
    :func:`check_source`)."""
    factor = None
    if not beam.uniform:
        if beam.kind == "cos_power":
            hx, hy, hz = w[0] + axis[0], w[1] + axis[1], w[2] + axis[2]
            h = xp.minimum(0.5 * (hx * hx + hy * hy + hz * hz), 1.0)
            factor = xp.exp(beam.power * xp.log1m(h))
        else:
            cx = w[1] * axis[2] - w[2] * axis[1]
            cy = w[2] * axis[0] - w[0] * axis[2]
            cz = w[0] * axis[1] - w[1] * axis[0]
            sin_t = xp.sqrt(cx * cx + cy * cy + cz * cz)
            cos_t = -(w[0] * axis[0] + w[1] * axis[1] + w[2] * axis[2])
            theta = xp.atan2(sin_t, cos_t)
            if beam.kind == "gaussian":
                u = theta * (1.0 / beam.sigma_rad)
                factor = xp.exp(-0.5 * (u * u))
            elif beam.kind == "table":
                factor = xp.where(theta <= beam.theta_end_rad, table_value(xp, beam.table, theta), 0.0 * theta)
            else:
                raise ValueError(f"unknown angular profile {beam.kind!r}")
    if not aperture.uniform:
        if disc_xy is None:
            raise ValueError("an aperture profile needs the source point's disc coordinates (disc_xy)")
        rho2 = disc_xy[0] * disc_xy[0] + disc_xy[1] * disc_xy[1]
        if aperture.kind == "quadratic":
            a = quadratic_edge(aperture.edge, rho2)
        elif aperture.kind == "table":
            a = table_value(xp, aperture.table, xp.sqrt(rho2))
        else:
            raise ValueError(f"unknown aperture profile {aperture.kind!r}")
        factor = a if factor is None else factor * a
    return factor


def map_bilinear(xp, fmap: FieldMap, mx, my):
    """The sensitivity map at map coordinates (mx, my) in [-1, 1]^2 (x right, y up): bilinear
    between the pixel centres (row 0 at the top), the border values extended to the edges.
    Written as nested lerps, so a uniform map gives its value exactly."""
    nx, ny = float(fmap.nx), float(fmap.ny)
    u = xp.minimum(xp.maximum((mx + 1.0) * (0.5 * nx) - 0.5, 0.0), nx - 1.0)     # column
    v = xp.minimum(xp.maximum((1.0 - my) * (0.5 * ny) - 0.5, 0.0), ny - 1.0)     # row from the top
    i = xp.minimum(xp.floor(u), nx - 2.0)
    j = xp.minimum(xp.floor(v), ny - 2.0)
    a = u - i
    b = v - j
    k = j * nx + i
    v00 = xp.take(fmap.flat, k)
    v01 = xp.take(fmap.flat, k + 1.0)
    v10 = xp.take(fmap.flat, k + nx)
    v11 = xp.take(fmap.flat, k + (nx + 1.0))
    top = v00 + a * (v01 - v00)
    bottom = v10 + a * (v11 - v10)
    return top + b * (bottom - top)


def field_map_value(xp, geo: DetectorGeometry, fx, fy):
    """k_D of the sensitivity map at the field-disc point (fx, fy) (unit disc along the meter's s, t
    axes; :mod:`roadgonio.instrument.profiles` for the map's orientation)."""
    m = geo.map_axes
    return map_bilinear(xp, geo.kd_map, m[0] * fx + m[1] * fy, m[2] * fx + m[3] * fy)


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
        raise GeometryError(f"the detector does not see the sample plane: some detected rays point upwards "
                            f"(alpha = {instrument.observation.alpha_deg:g} deg minus the field and pupil angles must "
                            f"stay above the horizon: narrow the field, shrink the pupil or raise observation.alpha_deg)",
                            path=instrument.path, field="detector.field_half_angle_deg")
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
                            f"at {det.distance_m:g} m)", path=instrument.path, field="detector.pupil_radius_m")
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
                "[sample] or narrow the field", path=instrument.path, field="sample")
    return bounds


def plane_clearance_text(height_m: float) -> str:
    """How far a point at ``height_m`` (m, <= 0) reaches below the sample plane, for messages: in mm
    with its real sign, or "down to the sample plane" within a nanometre (a disc whose rim just
    touches the plane gives -1e-18 m from round-off: was printed as ``-0.0000 m below/at``)."""
    if height_m > -1e-9:
        return "down to the sample plane (its lowest point lies on it, to within 1 nm)"
    return f"{-1000.0 * height_m:.4g} mm below the sample plane"


def _cells_more(cells: Sequence[tuple[float, float]]) -> str:
    """'tan eps = 5, beta = 0' for the first cell, '(and N more cells)' when there are others."""
    t, b = cells[0]
    more = f" (and {len(cells) - 1} more cells)" if len(cells) > 1 else ""
    return f"tan eps = {t:g}, beta = {b:g}{more}"


def check_source(instrument: Instrument, tan_eps: float, beta_deg: float) -> None:
    """The whole source disc must be above the sample plane (:func:`check_source_cells` at one cell)."""
    check_source_cells(instrument, [(tan_eps, beta_deg)])


def check_source_cells(instrument: Instrument, cells: Sequence[tuple[float, float]]) -> None:
    """At every cell the whole source disc must be above the sample plane, and a tabulated beam
    (``source.beam_intensity_file``) must reach every angle at which the source lights the detector
    footprint. A :class:`GeometryError` naming the instrument file, the key to change, the first
    such cell and how many more there are (the horizon first, then the table)."""
    src = instrument.source
    below: list[tuple[float, float]] = []
    lowest_first = dist_first = 0.0
    for tan_eps, beta_deg in cells:
        if not math.isfinite(tan_eps) or tan_eps < 0:
            raise GeometryError(f"tan eps = {tan_eps} is not a valid illumination angle (expected 0 <= tan eps < inf)")
        eps = math.atan(tan_eps)
        dist = source_distance_m(src, float(tan_eps))
        lowest = dist * math.cos(eps) - src.radius_m * math.sin(eps)
        if lowest <= 0.0:
            if not below:
                lowest_first, dist_first = lowest, dist
            below.append((float(tan_eps), float(beta_deg)))
    if below:
        raise GeometryError(f"the source is below the horizon at {_cells_more(below)}: its disc (radius "
                            f"{src.radius_m:g} m at {dist_first:g} m) reaches {plane_clearance_text(lowest_first)}",
                            path=instrument.path, field="source.radius_m")
    if src.beam.kind != "table" or not cells:
        return
    have = math.degrees(src.beam.theta_end_rad)
    short: list[tuple[float, float]] = []
    need_first = 0.0
    for (tan_eps, beta_deg), need in zip(cells, footprint_emission_angles_deg(instrument, cells)):
        if need > have:
            if not short:
                need_first = need
            short.append((float(tan_eps), float(beta_deg)))
    if short:
        raise GeometryError(f"the source's intensity table ({src.beam_intensity_file}) ends at theta = {have:.4g} deg, "
                            f"but the detector footprint is seen at up to {need_first:.4g} deg from the source axis at "
                            f"{_cells_more(short)}: extend the table or leave those cells out",
                            path=instrument.path, field="source.beam_intensity_file")


def _hull_vertices(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Indices of the vertices of the convex hull of the points (x, y) (monotone chain over the
    points sorted by x then y; points on an edge are dropped). Written here rather than taken
    from scipy.spatial, whose import alone (0.6 s) costs more than a bare k_A table. The points
    strictly inside the polygon of the extreme points in 16 directions are no vertices and are
    left out first (the chain then walks a few hundred points instead of ~9300)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    phi = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    ext = np.argmax(np.cos(phi)[:, None] * x[None, :] + np.sin(phi)[:, None] * y[None, :], axis=1)
    ext = ext[np.r_[True, ext[1:] != ext[:-1]]]                          # counter-clockwise, no repeats
    if len(ext) > 1 and ext[0] == ext[-1]:
        ext = ext[:-1]
    keep = np.ones(len(x), dtype=bool)
    if len(ext) >= 3:
        inside = np.ones(len(x), dtype=bool)
        for a, b in zip(ext, np.roll(ext, -1)):
            inside &= (x[b] - x[a]) * (y - y[a]) - (y[b] - y[a]) * (x - x[a]) > 0.0
        keep = ~inside
    cand = np.flatnonzero(keep)
    x, y = x[cand], y[cand]
    order = np.lexsort((y, x))
    px, py = x[order].tolist(), y[order].tolist()

    def chain(idx):
        out: list[int] = []
        for k in idx:
            while len(out) >= 2:
                a, b = out[-2], out[-1]
                if (px[b] - px[a]) * (py[k] - py[a]) - (py[b] - py[a]) * (px[k] - px[a]) > 0.0:
                    break
                out.pop()
            out.append(k)
        return out[:-1]

    idx = range(len(px))
    hull = (chain(idx) + chain(reversed(idx))) or [0]          # collinear points: the two ends; one point: it
    return cand[order[np.asarray(hull, dtype=np.intp)]]


def footprint_hull(instrument: Instrument, n: int = 96) -> tuple[tuple[np.ndarray, np.ndarray],
                                                                  tuple[np.ndarray, np.ndarray]]:
    """``(boundary, hull)``: the points of :func:`footprint_boundary` and the vertices of their
    convex hull (a few dozen of the ~9300 points)."""
    x, y = footprint_boundary(instrument, n)
    v = _hull_vertices(x, y)
    return (x, y), (x[v], y[v])


def _emission_angles_deg(instrument: Instrument, tb: np.ndarray, n: int,
                         pts_xy: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Per cell of ``tb`` (rows tan eps, beta), the largest angle (deg) from the source axis of the
    rays from the disc's ``n`` rim points and centre to the points ``pts_xy`` of the sample plane."""
    place = source_frames(instrument, tb[:, 0], tb[:, 1])
    c, a = place.centre.reshape(-1, 3), place.axis.reshape(-1, 3)
    s, t = place.s.reshape(-1, 3), place.t.reshape(-1, 3)
    r = float(instrument.source.radius_m)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    sp = c[:, None, :] + r * (np.cos(ang)[None, :, None] * s[:, None, :] + np.sin(ang)[None, :, None] * t[:, None, :])
    sp = np.concatenate([sp, c[:, None, :]], axis=1)                              # (cells, n + 1, 3)
    x, y = pts_xy
    pts = np.stack([x, y, np.zeros_like(x)], axis=-1)
    d = pts[None, None, :, :] - sp[:, :, None, :]                                 # (cells, n + 1, points, 3)
    cosang = np.einsum("cspk,ck->csp", d, a) / np.sqrt(np.einsum("cspk,cspk->csp", d, d))
    return np.degrees(np.arccos(np.clip(cosang.min(axis=(1, 2)), -1.0, 1.0)))


def _hull_angles_deg(instrument: Instrument, tb: np.ndarray, n: int,
                     hull: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """:func:`_emission_angles_deg` over the hull's vertices, in blocks of ~1e6 rays."""
    out = np.zeros(len(tb))
    chunk = max(1, (1 << 20) // (len(hull[0]) * (n + 1)))
    for i in range(0, len(tb), chunk):
        out[i:i + chunk] = _emission_angles_deg(instrument, tb[i:i + chunk], n, hull)
    return out


def footprint_emission_angles_deg(instrument: Instrument, cells: Sequence[tuple[float, float]],
                                  n: int = 32, outline=None) -> np.ndarray:
    """Per cell, the largest angle (deg) from the source axis at which the source sends light to the
    detector footprint: over the rays from the disc's rim points and centre to the footprint
    boundary (:func:`footprint_boundary`).

    Computed over the vertices of the boundary's convex hull (:func:`footprint_hull`), which gives
    the same angle: the directions within theta <= 90 deg of the axis form a convex cone, so the
    points of the plane seen from a source point within theta of the axis form a convex set, and
    when every hull vertex lies in it so does every boundary point. A cell whose angle is 90 deg or
    more (no such cone) is recomputed over all the boundary points. (Over all the points at every
    cell this took ~20 ms a cell, 12 s for a table: trial 10 D14.) ``outline``: the result of
    :func:`footprint_hull` when the caller has it."""
    tb = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    if not len(tb):
        return np.zeros(0)
    boundary, hull = footprint_hull(instrument) if outline is None else outline
    out = _hull_angles_deg(instrument, tb, n, hull)
    for i in np.flatnonzero(out >= 90.0):
        out[i] = _emission_angles_deg(instrument, tb[i:i + 1], n, boundary)[0]
    return out


def footprint_emission_angle_deg(instrument: Instrument, tan_eps: float, beta_deg: float, n: int = 32) -> float:
    """:func:`footprint_emission_angles_deg` at one cell."""
    return float(footprint_emission_angles_deg(instrument, [(tan_eps, beta_deg)], n)[0])


# ----------------------------------------------------------------------------------------------
# Line of sight: does the source disc block part of the detector's view? (the one test)
# ----------------------------------------------------------------------------------------------

#: A source disc closer than this (m) to the detector's ray bundle counts as blocking it: the
#: margin absorbs floating-point round-off on the conservative side (a nanometre).
SIGHT_TOL_M = 1e-9
#: Golden-section steps of the one-dimensional convex minimisation (0.618^90 ~ 1e-19 of the disc
#: diameter: the minimum to float64 precision).
_SIGHT_STEPS = 90


def bundle_cones(geo: DetectorGeometry) -> tuple[tuple[float, float], ...]:
    """The detector's ray bundle as a solid of revolution about its axis: the points of the rays
    at axial distance zeta >= 0 from the pupil plane form the disc ``rho <= max_k (a_k + b_k zeta)``
    (rho the distance from the axis). Returns the ``(a_k, b_k)``.

    Focused at F: the ray of the pupil point p and field point q passes through ``(1 - t) p + t q``
    at zeta = t F; over the pupil disc (radius R_D) and the field disc (radius R_F = F tan gamma),
    both centred on the axis and normal to it, these points fill the Minkowski sum of two centred
    discs, the disc of radius ``|1 - t| R_D + t R_F = max(R_D + t (R_F - R_D), t (R_F + R_D) - R_D)``
    (two cones: pupil rim to field rim on the same side, and across the axis). Angular field: the
    ray ``p + zeta (a + tan gamma u)`` fills the disc of radius ``R_D + zeta tan gamma`` (one cone).
    """
    rd = float(geo.pupil_radius_m)
    if geo.angular:
        return ((rd, float(geo.tan_field)),)
    f = float(geo.focus_m)
    rf = f * float(geo.tan_field)
    return ((rd, (rf - rd) / f), (-rd, (rf + rd) / f))


def _sight_frames(instrument: Instrument, cells) -> dict[str, np.ndarray]:
    """Per cell (float64 arrays), the source disc in the detector's axial coordinates: its centre's
    axial distance ``zc`` and radial offset ``U`` (3-vector), and two unit vectors of its plane,
    ``E1`` (along which zeta grows, at the rate ``G`` = |d zeta / d sigma|) and ``E2`` (zeta constant)."""
    geo = detector_geometry(instrument)
    tb = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    a = np.asarray(geo.axis, dtype=np.float64)
    w = np.atleast_2d(instrument.w_i(tb[:, 0], tb[:, 1]))
    c = source_distance_m(instrument.source, tb[:, 0])[:, None] * w      # disc centres
    n = -w                                                     # disc normals (towards the sample centre)
    # a unit vector of the disc plane along which zeta grows: the axis projected onto the plane
    ap = a[None, :] - (n @ a)[:, None] * n
    G = np.linalg.norm(ap, axis=1)
    ok = G > 1e-12
    s, _ = orthonormal_frame(a)            # any in-plane direction where the plane is normal to the axis
    fallback = s[None, :] - (n @ s)[:, None] * n
    fallback /= np.linalg.norm(fallback, axis=1, keepdims=True)
    E1 = np.where(ok[:, None], ap / np.where(ok, G, 1.0)[:, None], fallback)
    G = np.where(ok, G, 0.0)
    E2 = np.cross(n, E1)
    rel = c - geo.centre[None, :]
    zc = rel @ a
    U = rel - zc[:, None] * a[None, :]
    V = E1 - G[:, None] * a[None, :]      # radial part of E1 (E2 has none: a . E2 = 0)
    return {"zc": zc, "U": U, "V": V, "E2": E2, "G": G}


def sight_clearance(instrument: Instrument, cells) -> np.ndarray:
    """Radial clearance (m) between the source disc and the detector's ray bundle at each cell
    (float64, one value per cell): the minimum over the points x of the disc in front of the pupil
    plane of ``rho(x) - r(zeta(x))``, ``r`` the bundle's radius at axial distance zeta
    (:func:`bundle_cones`). Positive: the disc stays that far outside the bundle; zero or negative:
    it meets (reaches that deep into) the rays between the pupil and the sample plane.
    ``+inf`` for a point source (it is no object of the scene) or a disc wholly behind the pupil.

    Exact, not sampled: the rays' points between the pupil and the sample are exactly the points
    with zeta > 0, z > 0 and ``rho <= r(zeta)`` (each ray leaves the pupil above the sample plane and
    descends to it: :func:`check_detector`); the disc lies above the plane (:func:`check_source`,
    a precondition), so only zeta >= 0 and ``rho <= r(zeta)`` remain. ``rho - (a_k + b_k zeta)`` is
    convex over the disc (a distance to a line minus a linear function), and so is its minimum over
    each chord of constant zeta (a point-to-segment distance, closed form) as a function of the
    chord's position sigma: a golden-section search in sigma finds the minimum to float64 precision.
    """
    cells = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(cells), np.inf)
    R = float(instrument.source.radius_m)
    if R <= 0.0 or not len(cells):
        return out
    fr = _sight_frames(instrument, cells)
    zc, U, V, E2, G = fr["zc"], fr["U"], fr["V"], fr["E2"], fr["G"]
    # the part of the disc in front of the pupil plane: zeta = zc + G sigma >= 0
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = np.where(G > 0.0, np.maximum(-R, -zc / np.where(G > 0.0, G, 1.0)), np.where(zc >= 0.0, -R, np.inf))
    hi = np.full_like(lo, R)
    live = lo <= hi
    if not live.any():
        return out
    zc, U, V, E2, G, lo, hi = (v[live] for v in (zc, U, V, E2, G, lo, hi))

    def rho_min(sig):
        """Distance from the axis of the nearest point of the disc's chord at sigma."""
        base = U + sig[:, None] * V
        h = np.sqrt(np.maximum(R * R - sig * sig, 0.0))
        tau = np.clip(-np.einsum("ij,ij->i", base, E2), -h, h)
        return np.linalg.norm(base + tau[:, None] * E2, axis=1)

    best = np.full(len(lo), np.inf)
    phi = (math.sqrt(5.0) - 1.0) / 2.0
    for ak, bk in bundle_cones(detector_geometry(instrument)):
        def f(sig, ak=ak, bk=bk):
            return rho_min(sig) - (ak + bk * (zc + G * sig))
        a_, b_ = lo.copy(), hi.copy()
        best = np.minimum(best, np.minimum(f(a_), f(b_)))
        x1, x2 = b_ - phi * (b_ - a_), a_ + phi * (b_ - a_)
        f1, f2 = f(x1), f(x2)
        for _ in range(_SIGHT_STEPS):
            left = f1 <= f2                      # the minimum lies in [a, x2]
            best = np.minimum(best, np.minimum(f1, f2))
            b_ = np.where(left, x2, b_)
            a_ = np.where(left, a_, x1)
            x1n = np.where(left, b_ - phi * (b_ - a_), x2)
            x2n = np.where(left, x1, a_ + phi * (b_ - a_))
            new = np.where(left, x1n, x2n)
            fn = f(new)
            f1, f2 = np.where(left, fn, f2), np.where(left, f1, fn)
            x1, x2 = x1n, x2n
        best = np.minimum(best, np.minimum(f1, f2))
    out[live] = best
    return out


def source_blocks_view(instrument: Instrument, cells) -> np.ndarray:
    """True per cell where the source disc blocks part of the detector's view of the sample (it
    stands between the detector and its footprint): the one line-of-sight test of every backend
    and of the design's pre-filter. :func:`sight_clearance` <= :data:`SIGHT_TOL_M`, computed only
    for the cells a bounding-sphere test cannot clear: a disc of radius R_S about c has every
    point within R_S of c, so (rho and zeta being 1-Lipschitz and r convex) no point of it is in
    the bundle when ``rho(c) - R_S > max(r(zeta(c) - R_S), r(zeta(c) + R_S))`` or
    ``zeta(c) + R_S < 0``. The pre-filter is exact (it never clears a blocking disc)."""
    cells = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    blocked = np.zeros(len(cells), dtype=bool)
    R = float(instrument.source.radius_m)
    if R <= 0.0 or not len(cells):
        return blocked
    geo = detector_geometry(instrument)
    w = np.atleast_2d(instrument.w_i(cells[:, 0], cells[:, 1]))
    rel = source_distance_m(instrument.source, cells[:, 0])[:, None] * w - geo.centre[None, :]
    zc = rel @ geo.axis
    rho_c = np.linalg.norm(rel - zc[:, None] * geo.axis[None, :], axis=1)
    reach = np.max([np.maximum(ak + bk * (zc - R), ak + bk * (zc + R)) for ak, bk in bundle_cones(geo)], axis=0)
    near = (zc + R >= 0.0) & (rho_c - R <= reach + SIGHT_TOL_M)
    if near.any():
        blocked[near] = sight_clearance(instrument, cells[near]) <= SIGHT_TOL_M
    return blocked


def check_line_of_sight(instrument: Instrument, cells) -> None:
    """Raise :class:`GeometryError` naming the first cell (tan eps, beta) of ``cells`` at which the
    source disc blocks the detector's view (:func:`source_blocks_view`)."""
    cells = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    blocked = np.flatnonzero(source_blocks_view(instrument, cells))
    if blocked.size:
        t, b = cells[blocked[0]]
        depth = -float(sight_clearance(instrument, cells[blocked[:1]])[0])
        more = f" (and {blocked.size - 1} more of the {len(cells)} cells)" if blocked.size > 1 else ""
        raise GeometryError(f"the source disc blocks the detector's line of sight at tan eps = {t:g}, beta = {b:g}"
                            f"{more}: it reaches {max(depth, 0.0) * 1e3:.3g} mm into the detector's ray bundle "
                            "between the pupil and the sample; this cell cannot be measured with this geometry")


#: Cells whose quick bounds on the emission angle (:func:`beam_clips_cells`) are within this many
#: degrees of the beam limit get the full computation (the float64 round-off of an angle near
#: zero, through acos, is ~1e-6 deg).
_BEAM_MARGIN_DEG = 1e-5


def beam_clips_cells(instrument: Instrument, cells: Sequence[tuple[float, float]], n: int = 32) -> np.ndarray:
    """Per cell, True if the source's beam limit (``beam_half_angle_deg``) cuts off light that
    reaches the detector footprint: some ray from the source disc (rim points and centre) to the
    footprint boundary leaves the cone, i.e. :func:`footprint_emission_angles_deg` exceeds the limit.
    All False when the source has no beam limit.

    Quick bounds first, from the disc's centre c alone (one ray per hull vertex p instead of
    ``n + 1``): the angle of p - c is one of the rays' angles (a lower bound), and every disc point
    lies within R_S of c, so its ray to p is within asin(R_S / |p - c|) of p - c (an upper bound).
    Only cells whose bounds straddle the limit get the full computation (trial 10 D14: a 90 deg
    limit, which clips nothing, made a table 13-80x slower)."""
    tb = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    clips = np.zeros(len(tb), dtype=bool)
    theta = instrument.source.beam_half_angle_deg
    if theta is None or not len(tb):
        return clips
    outline = footprint_hull(instrument)
    hull = outline[1]
    place = source_frames(instrument, tb[:, 0], tb[:, 1])
    c, a = place.centre.reshape(-1, 3), place.axis.reshape(-1, 3)
    pts = np.stack([hull[0], hull[1], np.zeros_like(hull[0])], axis=-1)
    d = pts[None, :, :] - c[:, None, :]                                              # (cells, vertices, 3)
    dist = np.sqrt(np.einsum("cpk,cpk->cp", d, d))
    centre_deg = np.degrees(np.arccos(np.clip(np.einsum("cpk,ck->cp", d, a) / dist, -1.0, 1.0)))
    r = float(instrument.source.radius_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        off_deg = np.where(dist > r, np.degrees(np.arcsin(np.minimum(r / dist, 1.0))), np.inf)
    lo, hi = centre_deg.max(axis=1), (centre_deg + off_deg).max(axis=1)
    clips[lo > theta + _BEAM_MARGIN_DEG] = True
    unsure = np.flatnonzero((lo <= theta + _BEAM_MARGIN_DEG) & (hi >= theta - _BEAM_MARGIN_DEG))
    if unsure.size:
        clips[unsure] = footprint_emission_angles_deg(instrument, tb[unsure], n, outline=outline) > theta
    return clips


def beam_clips_footprint(instrument: Instrument, tan_eps: float, beta_deg: float, n: int = 32) -> bool:
    """:func:`beam_clips_cells` at one cell."""
    return bool(beam_clips_cells(instrument, [(tan_eps, beta_deg)], n)[0])


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


def judge_hits(on_sample, hit_anything, x, y, mesh_path=None) -> dict:
    """Verdict of a footprint check over traced rays (boolean arrays: the ray hit the sample / hit
    some part of the scene; x, y the hit points): every detected ray must land on the sample, else
    a :class:`GeometryError` saying what the missing rays hit (naming ``mesh_path``, the sample's mesh
    file, when it has one). Returns the ray count and the footprint's extent."""
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
            + "): the detector footprint must lie on the sample; enlarge the sample or narrow the field",
            **mesh_location(mesh_path))
    return {"rays": int(on_sample.size), "x_range": (float(x.min()), float(x.max())),
            "y_range": (float(y.min()), float(y.max()))}
