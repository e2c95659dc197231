"""Luminance-meter sensor as a Mitsuba 3 Python plugin (plugin name ``lummeter``); docs/conventions.md
section 4, the detector domain of paper eq. 3.

Entrance pupil: a disc of radius R_D centred at D_D w_o(alpha, delta), normal to the axis towards
the sample centre. Field stop: a circular disc of angular half-size gamma_D, conjugate to the plane
normal to the axis at the focus distance F (``focus_m``; default D_D; ``inf`` = angular field).
The rays and their etendue weights come from :func:`roadgonio.instrument.optics.detector_ray`, evaluated with
the Dr.Jit namespace (nothing of the geometry is repeated here).

Sampling: the film position sample (u in [0, 1]^2, one pixel = one stratum) is concentric-mapped
to the unit field disc, so the pixels stratify the field exactly; the aperture sample is
concentric-mapped to the unit pupil disc. Each ray's weight is the etendue factor normalised to 1
on the axis; with a box reconstruction filter every pixel is the mean of its samples, and the
**mean over all pixels** (reduce in float64) is the detector signal S[f] up to a constant
(pupil area x field area x radiance units), the same constant for every BSDF.

Zero pupil radius = pinhole (every ray starts at the pupil centre); zero field = a single
direction (the axis, or for a pupil with a field of zero size, the rays of the pupil converging
on the focus point).

Properties: ``alpha_deg``, ``delta_deg`` (the observation direction), ``distance_m``,
``pupil_radius_m``, ``field_half_angle_deg``, ``focus_m`` (float > 0; ``inf`` = an angular
field, in XML ``value="inf"``; default = ``distance_m``), ``field_edge_sensitivity`` or ``field_sensitivity`` (the file of a
sensitivity map, :mod:`roadgonio.instrument.profiles`); ``mapping`` =
``"concentric"`` (default, the signal) or ``"square"`` (film = picture of the field plane, pixels
outside the field stop 0; for images); plus the usual ``film`` and ``sampler`` children. They
are validated like the ``[observation]``/``[detector]`` sections of an instrument file
(:class:`~roadgonio.instrument.config.Observation`, :class:`~roadgonio.instrument.config.Detector`).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from roadgonio.errors import InputError
from roadgonio.instrument.config import Detector, Observation
from roadgonio.instrument.optics import DetectorGeometry, concentric_disc, detector_ray, meter_geometry
from roadgonio.engines.mitsuba.ops import DrJitOps

DETECTOR_KEYS = ("distance_m", "pupil_radius_m", "field_half_angle_deg", "focus_m", "field_edge_sensitivity",
                 "field_sensitivity")


def _python_floats(v) -> np.ndarray:
    """A float64 vector as an object array of Python floats: it still supports ``k * v`` and
    ``v[i]``, but its elements combine with Dr.Jit arrays as Python scalars (a numpy float64
    times a Dr.Jit array would turn into a numpy array)."""
    return np.array([float(x) for x in v], dtype=object)


def _opaque_floats(v) -> np.ndarray:
    """A float64 vector as an object array of opaque 1-wide ``mi.Float`` (kernel parameters, not
    literals: a kernel traced with them is reused, without recompiling, for another instrument)."""
    out = np.empty(len(v), dtype=object)
    for i, x in enumerate(v):          # element by element: numpy would unpack a Dr.Jit array
        out[i] = dr.opaque(mi.Float, float(x))
    return out


def jit_geometry(geo: DetectorGeometry, opaque: bool = True) -> DetectorGeometry:
    """Copy of ``geo`` for Dr.Jit kernels. With ``opaque`` (default) the centre, axis, frame,
    pupil radius, field and a finite focus distance are opaque ``mi.Float`` values, so changing the
    instrument (uncertainty design points, instrument design) never recompiles a kernel; otherwise
    Python floats (see :func:`_python_floats`), baked into the kernel as literals. Structural in
    either case: whether the field is angular (focus at infinity) and whether k_D is uniform. A
    sensitivity map goes to the device as an array the kernel gathers from (its size is structural)."""
    kd_map = None if geo.kd_map is None else _JitFieldMap(geo.kd_map)
    if not opaque:
        return DetectorGeometry(centre=_python_floats(geo.centre), axis=_python_floats(geo.axis),
                                s=_python_floats(geo.s), t=_python_floats(geo.t),
                                pupil_radius_m=float(geo.pupil_radius_m), focus_m=float(geo.focus_m),
                                tan_field=float(geo.tan_field), kd_edge=float(geo.kd_edge), kd_map=kd_map,
                                map_axes=tuple(float(v) for v in geo.map_axes))
    focus = math.inf if geo.angular else dr.opaque(mi.Float, float(geo.focus_m))
    return _OpaqueDetectorGeometry(centre=_opaque_floats(geo.centre), axis=_opaque_floats(geo.axis),
                                   s=_opaque_floats(geo.s), t=_opaque_floats(geo.t),
                                   pupil_radius_m=dr.opaque(mi.Float, float(geo.pupil_radius_m)),
                                   focus_m=focus, tan_field=dr.opaque(mi.Float, float(geo.tan_field)),
                                   kd_edge=float(geo.kd_edge), kd_map=kd_map,
                                   map_axes=tuple(_opaque_floats(geo.map_axes)), is_angular=geo.angular)


class _JitFieldMap:
    """A :class:`~roadgonio.instrument.profiles.FieldMap` for Dr.Jit kernels: the same ``nx``,
    ``ny`` and the values (row by row) as a device array that
    :func:`~roadgonio.instrument.optics.map_bilinear` gathers from."""

    def __init__(self, fmap):
        self.nx, self.ny = fmap.nx, fmap.ny
        self.flat = mi.Float(np.ascontiguousarray(fmap.flat, dtype=np.float32))


class _OpaqueDetectorGeometry(DetectorGeometry):
    """:class:`DetectorGeometry` whose numbers are opaque Dr.Jit scalars; ``angular`` is kept as a
    Python bool (it decides which code is traced)."""

    def __init__(self, *, is_angular: bool, **fields):
        super().__init__(**fields)
        object.__setattr__(self, "_angular", bool(is_angular))

    @property
    def angular(self) -> bool:
        return self._angular


def meter_from_props(props) -> tuple[Observation, Detector]:
    """The observation and the detector of the sensor's properties (validated dataclasses)."""
    obs = {key: float(props.get(key)) for key in ("alpha_deg", "delta_deg") if key in props}
    det = {key: props.get(key) for key in DETECTOR_KEYS if key in props}
    if "field_sensitivity" in det:
        det["field_sensitivity"] = str(det["field_sensitivity"])
    det.setdefault("distance_m", 5.0)
    return Observation(**obs), Detector(**det)


class LumMeter(mi.Sensor):
    """Luminance meter: exact circular pupil x circular field (see the module docstring)."""

    def __init__(self, props):
        mi.Sensor.__init__(self, props)
        try:
            self.observation, self.detector = meter_from_props(props)
        except InputError as err:
            raise InputError(f"lummeter sensor: {err}") from None
        self.geometry = meter_geometry(self.observation, self.detector)
        self._geo = jit_geometry(self.geometry)
        self.m_needs_sample_3 = True
        #: "concentric" (pixels stratify the field disc: the signal) or "square" (a picture of the field)
        self.mapping = str(props.get("mapping", "concentric")) if "mapping" in props else "concentric"
        if self.mapping not in ("concentric", "square"):
            raise InputError(f"lummeter sensor: mapping must be 'concentric' or 'square', got {self.mapping!r}")

    def rays(self, field_u, pupil_u):
        """Origin, direction and etendue weight of the rays for unit-square samples
        (field: film position, pupil: aperture sample); Dr.Jit arrays."""
        px, py = concentric_disc(DrJitOps, pupil_u.x, pupil_u.y)
        if self.mapping == "square":
            # picture of the field as the detector sees it: film (u, v) -> (1 - 2u, 1 - 2v) on the
            # field plane (s, t) (t is "up" for delta = 0 and s points to the viewer's left), weight
            # 0 outside the field stop; the mean over pixels is then pi/4 x the signal
            fx, fy = 1.0 - 2.0 * field_u.x, 1.0 - 2.0 * field_u.y
            o, d, w = detector_ray(DrJitOps, self._geo, (px, py), (fx, fy))
            return o, d, dr.select(fx * fx + fy * fy <= 1.0, w, 0.0)
        fx, fy = concentric_disc(DrJitOps, field_u.x, field_u.y)
        return detector_ray(DrJitOps, self._geo, (px, py), (fx, fy))

    def sample_ray(self, time, sample1, sample2, sample3, active=True):
        o, d, w = self.rays(sample2, sample3)
        ray = mi.Ray3f(mi.Point3f(o[0], o[1], o[2]), mi.Vector3f(d[0], d[1], d[2]))
        ray.time = time
        return ray, mi.Spectrum(w)

    def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
        ray, weight = self.sample_ray(time, sample1, sample2, sample3, active)
        rd = mi.RayDifferential3f(ray)
        rd.has_differentials = False
        return rd, weight

    def bbox(self):
        c = self.geometry.centre
        r = max(self.geometry.pupil_radius_m, 1e-6)
        return mi.ScalarBoundingBox3f(mi.ScalarPoint3f(*(c - r)), mi.ScalarPoint3f(*(c + r)))

    def to_string(self):
        g = self.geometry
        focus = "inf" if g.angular else f"{g.focus_m:g} m"
        return (f"LumMeter[alpha={self.observation.alpha_deg:g} deg, "
                f"D={self.detector.distance_m:g} m, R_D={g.pupil_radius_m:g} m, "
                f"gamma={self.detector.field_half_angle_deg:g} deg, F={focus}]")
