"""The goniophotometer as a Mitsuba 3 scene (docs/conventions.md section 4).

Parts of a scene, by id (the same ids for a scene built from a TOML instrument and for an XML scene):

* ``"source"``: the source. A ``disk`` shape carrying an ``area`` emitter of uniform radiance
  (the exit aperture, radius R_S, facing the sample centre), or a ``point`` emitter when R_S = 0.
  Its placement is set per cell from the instrument's nominal geometry (``to_world`` /
  ``position`` through ``mi.traverse``), so the scene is built and compiled once per instrument.
  Units: the radiance is D_S^2 / (pi R_S^2) (point: intensity D_S^2), so the illuminance normal
  to the source axis at the sample centre is about 1 lx.
* ``"sample"``: the sample shape, carrying the road BSDF (``roadbsdf``). From a TOML instrument:
  the instrument's sample as triangles (:func:`roadgonio.instrument.mesh.sample_triangles`: its
  rectangle or its checked mesh file), converted to a ``mi.Mesh`` here.
* ``"detector"``: the luminance meter (``lummeter`` sensor, :mod:`roadgonio.engines.mitsuba.plugins.lummeter`).

The integrator is always ``direct`` with ``emitter_samples = 1``, ``bsdf_samples = 0`` (emitter
sampling only: the small source disc is found by every sample; mitsuba-cpu notes, section 7).

**XML scenes.** An instrument TOML file may add ``[scene] xml = "file.xml"`` (relative to the TOML
file). The TOML file still gives the nominal geometry (alpha, D_S, R_S, detector...): it defines
the ideal geometry of k_A, the source placement per cell and the geometry checks. The XML file is
loaded with ``mi.load_file`` and these parameters (usable as ``$name`` in the XML; give them
``<default>`` values so the file also opens alone)::

    alpha_deg delta_deg source_distance_m source_radius_m source_radiance detector_distance_m
    pupil_radius_m field_half_angle_deg focus_m (inf = angular field) field_edge_sensitivity sample_size_x_m sample_size_y_m
    field_sensitivity (only when the detector has a sensitivity map: its file)
    sample_half_x_m sample_half_y_m

plus every key of an optional ``[scene.params]`` table (e.g. ``rim_height_m = 0.05``). The XML
must contain the three parts above by id: a shape ``sample`` with a ``roadbsdf`` BSDF (its
parameters are replaced by the model being computed), a ``lummeter`` sensor ``detector`` (its
geometry must equal the TOML's ``[detector]``/``[observation]``), and a ``source`` (disk shape
with an area emitter, or a point emitter). Everything else in the XML (baffles, housings, a sample
holder, a non-flat sample) is simulated as it is. Example: ``scenes/holder.toml`` with
``scenes/holder.xml``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from roadgonio.engines.mitsuba import require_variant
from roadgonio.errors import BackendError, InputError
from roadgonio.instrument.config import Detector, Instrument, Observation
from roadgonio.instrument.mesh import sample_triangles
from roadgonio.instrument.optics import (
    beam_clips_footprint,
    check_detector,
    check_source,
    detector_geometry,
    detector_ray,
    footprint_boundary,
    hit_check_points,
    judge_hits,
    source_geometry,
)
from roadgonio.surface.model import RoadModel

#: Ids of the scene parts (TOML-built and XML scenes alike).
SOURCE_ID, SAMPLE_ID, DETECTOR_ID = "source", "sample", "detector"
#: Sources closer than this to the line of sight get the detector-ray check again per cell.
SOURCE_NEAR_SIGHT_DEG = 10.0
#: Channels of the road BSDF in the backend scene: R = f_road, G = B = 1/pi (perfect diffuser).
ROAD, LAMBERT = 0, 1

_XML_PARAM_KEYS = ("alpha_deg", "delta_deg", "source_distance_m", "source_radius_m", "source_radiance",
                   "sample_half_x_m", "sample_half_y_m",
                   "detector_distance_m", "pupil_radius_m", "field_half_angle_deg", "focus_m",
                   "field_edge_sensitivity", "field_sensitivity", "sample_size_x_m", "sample_size_y_m")


def _mi():
    import mitsuba as mi
    return mi


def film_dict(resolution: int, spp: int, sampler: str = "independent") -> tuple[dict, dict]:
    film = {"type": "hdrfilm", "width": int(resolution), "height": int(resolution),
            "rfilter": {"type": "box"}, "pixel_format": "rgb", "component_format": "float32"}
    return film, {"type": sampler, "sample_count": int(spp)}


def detector_props(observation: Observation, detector: Detector) -> dict[str, Any]:
    """Properties of the ``lummeter`` sensor for this meter (focus at infinity passes as ``math.inf``;
    a sensitivity map as its file name)."""
    props = {"alpha_deg": float(observation.alpha_deg), "delta_deg": float(observation.delta_deg),
             "distance_m": float(detector.distance_m), "pupil_radius_m": float(detector.pupil_radius_m),
             "field_half_angle_deg": float(detector.field_half_angle_deg),
             "focus_m": float(detector.focus_distance_m),
             "field_edge_sensitivity": float(detector.field_edge_sensitivity)}
    if detector.field_sensitivity is not None:
        props["field_sensitivity"] = str(detector.field_sensitivity)
    return props


def source_radiance(instrument: Instrument) -> float:
    """Radiance (disc) or intensity (point) giving ~1 lx normal to the axis at the sample centre."""
    src = instrument.source
    d2 = src.distance_m ** 2
    return d2 if src.is_point else d2 / (math.pi * src.radius_m ** 2)


def to_mitsuba_mesh(mesh, bsdf, name: str = SAMPLE_ID):
    """Convert a triangle mesh (anything with ``vertices`` and ``faces``: a trimesh, or
    :class:`roadgonio.instrument.mesh.Triangles`) to a ``mi.Mesh`` carrying ``bsdf``."""
    mi = _mi()
    import drjit as dr
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.uint32)
    props = mi.Properties()
    props["bsdf"] = bsdf
    m = mi.Mesh(name, len(v), len(f), props)
    p = mi.traverse(m)
    p["vertex_positions"] = dr.ravel(mi.Point3f(v[:, 0].astype(np.float32), v[:, 1].astype(np.float32),
                                                v[:, 2].astype(np.float32)))
    p["faces"] = dr.ravel(mi.Vector3u(f[:, 0], f[:, 1], f[:, 2]))
    p.update()
    return m


def source_transform(instrument: Instrument, tan_eps: float, beta_deg: float):
    """``to_world`` of the unit disc: centre D_S w_i, normal towards the sample centre, radius R_S."""
    mi = _mi()
    g = source_geometry(instrument, tan_eps, beta_deg)
    r = max(g.radius_m, 0.0)
    m = np.eye(4)
    m[:3, 0] = r * g.s
    m[:3, 1] = r * g.t
    m[:3, 2] = g.axis
    m[:3, 3] = g.centre
    return mi.ScalarTransform4f(m.tolist())


def check_beam(instrument: Instrument, tan_eps: float, beta_deg: float) -> None:
    """The Mitsuba area emitter has no beam limit: accept a beam limit only where it cannot clip
    (:func:`roadgonio.instrument.optics.beam_clips_footprint`)."""
    if beam_clips_footprint(instrument, tan_eps, beta_deg):
        raise BackendError(f"the source beam limit ({instrument.source.beam_half_angle_deg:g} deg) clips the light "
                           f"reaching the detector footprint at tan eps = {tan_eps:g}, beta = {beta_deg:g}; the "
                           "mitsuba backend does not model beam limits: use the quadrature backend")


@dataclass
class RoadScene:
    """A built Mitsuba scene of one instrument and one road model (road + Lambert channels)."""

    instrument: Instrument
    model: RoadModel
    scene: Any
    params: Any
    integrator: Any
    sensor: Any
    bsdf: Any
    sample_shape: Any
    source_kind: str                    # "disk" or "point"
    resolution: int
    xml: Path | None = None
    flat_rectangle: bool = True
    cell: tuple[float, float] | None = None
    footprint: tuple[float, float, float, float] | None = None
    info: dict = field(default_factory=dict)
    checked: bool = False

    # -- per cell --------------------------------------------------------------------------
    def place_source(self, tan_eps: float, beta_deg: float) -> None:
        """Move the source to the cell (no recompile); checks the horizon and beam limit."""
        check_source(self.instrument, tan_eps, beta_deg)
        check_beam(self.instrument, tan_eps, beta_deg)
        if self.source_kind == "point":
            c = self.instrument.source_centre(tan_eps, beta_deg)
            self.params[f"{SOURCE_ID}.position"] = _mi().Point3f(*[float(v) for v in c])
        else:
            self.params[f"{SOURCE_ID}.to_world"] = source_transform(self.instrument, tan_eps, beta_deg)
        self.params.update()
        self.cell = (float(tan_eps), float(beta_deg))
        if self.checked:
            # a source close to the line of sight could hide part of the footprint: check the rays again
            cos_sep = float(np.dot(self.instrument.w_i(tan_eps, beta_deg), self.instrument.w_o()))
            if cos_sep > math.cos(math.radians(SOURCE_NEAR_SIGHT_DEG)):
                self.check_hits(n_random=1 << 12, n_rim=64)

    def render(self, seed: int, spp: int) -> np.ndarray:
        """One pass: the film as float64 (H, W, 3); channel 0 = road, 1 = Lambert (see :data:`ROAD`)."""
        mi = _mi()
        img = mi.render(self.scene, sensor=self.sensor, integrator=self.integrator, seed=int(seed), spp=int(spp))
        return np.array(img, dtype=np.float64)

    # -- checks ----------------------------------------------------------------------------
    def check_hits(self, n_random: int = 1 << 16, n_rim: int = 128, seed: int = 7) -> dict:
        """Render-time footprint check: the rays of :func:`~roadgonio.instrument.optics.hit_check_points`
        (extreme rays of the detector bundle and ``n_random`` random ones) are traced through the
        scene and must all land on the sample shape (:func:`~roadgonio.instrument.optics.judge_hits`)."""
        mi = _mi()
        import drjit as dr
        from roadgonio.engines.mitsuba.ops import DrJitOps
        from roadgonio.engines.mitsuba.plugins.lummeter import jit_geometry
        pu, fu = hit_check_points(n_random, n_rim, seed)
        geo = jit_geometry(detector_geometry(self.instrument))
        # gathered, not loaded: a load's alignment hint depends on the buffer's address, so every
        # new scene could compile its own kernel
        idx = dr.arange(mi.UInt32, len(pu))
        px, py, fx, fy = (dr.gather(mi.Float, mi.Float(v.astype(np.float32)), idx)
                          for v in (pu[:, 0], pu[:, 1], fu[:, 0], fu[:, 1]))
        o, d, _ = detector_ray(DrJitOps, geo, (px, py), (fx, fy))
        si = self.scene.ray_intersect(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d)))
        # opaque: the shape pointer as a literal would make every new scene compile its own kernel
        on_sample = si.is_valid() & (si.shape == dr.opaque(mi.ShapePtr, self.sample_shape))
        src_shape = next((s for s in self.scene.shapes() if s.id() == SOURCE_ID), None)
        if src_shape is not None:
            # the source disc in the line of sight is its own error, with the cell (not "enlarge the sample")
            on_src = np.array(si.is_valid() & (si.shape == dr.opaque(mi.ShapePtr, src_shape)), dtype=bool)
            if on_src.any():
                from roadgonio.errors import GeometryError
                cell = f" at tan eps = {self.cell[0]:g}, beta = {self.cell[1]:g}" if self.cell is not None else ""
                raise GeometryError(
                    f"the source disc blocks the detector's line of sight{cell}: {int(on_src.sum())} of "
                    f"{on_src.size} detector rays hit the source before the sample (the source sits between "
                    "the detector and its footprint); this cell cannot be measured with this geometry")
        return judge_hits(np.array(on_sample, dtype=bool), np.array(si.is_valid(), dtype=bool),
                          np.array(si.p.x), np.array(si.p.y))


def _integrator():
    return _mi().load_dict({"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})


def _bsdf_dict(model: RoadModel, channels: str) -> dict:
    d = {"type": "roadbsdf", "variant": model.variant, "channels": channels}
    d.update(model.params.to_dict())
    return d


def build_scene(instrument: Instrument, model: RoadModel, *, resolution: int = 64, spp: int = 16,
                mitsuba_variant: str | None = None, sampler: str = "independent", channels: str = "road_lambert",
                check: bool = True, hit_rays: int = 1 << 16) -> RoadScene:
    """Build the scene of ``instrument`` with a sample of BSDF ``model`` (XML scene if the
    instrument has ``[scene] xml``). Checks the detector footprint (errors, not wrong numbers):
    the extreme rays of the detector bundle and ``hit_rays`` random ones must hit the sample (the
    batched engine, which counts every ray it traces, asks for fewer)."""
    require_variant(mitsuba_variant)
    from roadgonio.engines.mitsuba.plugins import register_plugins
    register_plugins()
    if check:
        if instrument.sample.mesh is None:
            footprint = check_detector(instrument)
        else:
            footprint_boundary(instrument)           # the detector must at least look downwards
            footprint = None
    scene_sec = instrument.extra.get("scene") if isinstance(instrument.extra, dict) else None
    if scene_sec is not None and not hasattr(scene_sec, "get"):
        raise InputError("expected a table [scene]", path=instrument.path, field="scene")
    if scene_sec and scene_sec.get("xml"):
        rs = _build_xml(instrument, model, scene_sec, resolution=resolution, spp=spp, sampler=sampler,
                        channels=channels)
    else:
        rs = _build_toml(instrument, model, resolution=resolution, spp=spp, sampler=sampler, channels=channels)
    if check:
        rs.footprint = footprint
        rs.place_source(0.0, 0.0)              # the source out of the way (XML files may leave it anywhere)
        rs.info["hit_check"] = rs.check_hits(n_random=int(hit_rays))
        rs.checked = True
    return rs


def _build_toml(instrument, model, *, resolution, spp, sampler, channels) -> RoadScene:
    mi = _mi()
    bsdf = mi.load_dict(_bsdf_dict(model, channels))
    smp = instrument.sample
    shape = to_mitsuba_mesh(sample_triangles(instrument), bsdf)
    film, samp = film_dict(resolution, spp, sampler)
    det = dict(type="lummeter", film=film, sampler=samp, **detector_props(instrument.observation, instrument.detector))
    src = instrument.source
    if src.is_point:
        source = {"type": "point", "position": [0.0, 0.0, src.distance_m],
                  "intensity": {"type": "uniform", "value": source_radiance(instrument)}}
    else:
        source = {"type": "disk", "to_world": source_transform(instrument, 0.0, 0.0),
                  "emitter": {"type": "area", "radiance": {"type": "uniform", "value": source_radiance(instrument)}}}
    scene = mi.load_dict({"type": "scene", DETECTOR_ID: det, SOURCE_ID: source, SAMPLE_ID: shape})
    sensor = scene.sensors()[0]
    return RoadScene(instrument=instrument, model=model, scene=scene, params=mi.traverse(scene),
                     integrator=_integrator(), sensor=sensor, bsdf=bsdf, sample_shape=shape,
                     source_kind="point" if src.is_point else "disk", resolution=resolution,
                     flat_rectangle=smp.mesh is None)


def xml_parameters(instrument: Instrument, scene_sec) -> dict[str, str]:
    det, src, smp = instrument.detector, instrument.source, instrument.sample
    p = {"alpha_deg": instrument.observation.alpha_deg, "delta_deg": instrument.observation.delta_deg,
         "source_distance_m": src.distance_m, "source_radius_m": src.radius_m,
         "source_radiance": source_radiance(instrument),
         "detector_distance_m": det.distance_m, "pupil_radius_m": det.pupil_radius_m,
         "field_half_angle_deg": det.field_half_angle_deg, "focus_m": det.focus_distance_m,
         "field_edge_sensitivity": det.field_edge_sensitivity,
         "sample_size_x_m": smp.size_x_m or 0.0, "sample_size_y_m": smp.size_y_m or 0.0,
         "sample_half_x_m": 0.5 * (smp.size_x_m or 0.0), "sample_half_y_m": 0.5 * (smp.size_y_m or 0.0)}
    if det.field_sensitivity is not None:
        p["field_sensitivity"] = str(det.field_sensitivity)
    extra = scene_sec.get("params", {})
    if not isinstance(extra, dict):
        raise InputError("expected a table [scene.params]", path=instrument.path, field="scene.params")
    for k, v in extra.items():
        if k in _XML_PARAM_KEYS:
            raise InputError(f"{k!r} is set from the instrument sections; remove it from [scene.params]",
                             path=instrument.path, field=f"scene.params.{k}")
        if isinstance(v, bool) or not isinstance(v, (int, float, str)):
            raise InputError(f"expected a number or string, got {v!r}", path=instrument.path,
                             field=f"scene.params.{k}")
        p[k] = v
    return {k: (repr(float(v)) if isinstance(v, (int, float)) else str(v)) for k, v in p.items()}


def xml_path(instrument: Instrument, scene_sec) -> Path:
    xml = scene_sec.get("xml")
    if not isinstance(xml, str):
        raise InputError(f"expected a file name, got {xml!r}", path=instrument.path, field="scene.xml")
    path = Path(xml)
    if not path.is_absolute() and instrument.path is not None:
        path = Path(instrument.path).parent / path
    if not path.exists():
        raise InputError(f"XML scene {str(path)!r} does not exist", path=instrument.path, field="scene.xml")
    return path


def _build_xml(instrument, model, scene_sec, *, resolution, spp, sampler, channels) -> RoadScene:
    mi = _mi()
    path = xml_path(instrument, scene_sec)
    params = xml_parameters(instrument, scene_sec)
    import re
    used = set(re.findall(r"\$(\w+)", path.read_text(encoding="utf-8", errors="replace")))
    unused = sorted(k for k in scene_sec.get("params", {}) if k not in used)
    if unused:
        raise InputError(f"[scene.params] key(s) {', '.join(unused)} are not used as $name in {path.name}",
                         path=instrument.path, field="scene.params")
    params = {k: v for k, v in params.items() if k in used}   # Mitsuba refuses unused parameters
    try:
        scene = mi.load_file(str(path), **params)
    except Exception as err:
        msg = str(err).strip().splitlines()
        raise InputError(f"Mitsuba cannot load the XML scene: {msg[-1] if msg else err}", path=path) from None
    shapes = {s.id(): s for s in scene.shapes()}
    emitters = {e.id(): e for e in scene.emitters()}
    sensors = {s.id(): s for s in scene.sensors()}
    missing = []
    if SAMPLE_ID not in shapes:
        missing.append(f"a shape with id=\"{SAMPLE_ID}\"")
    if DETECTOR_ID not in sensors:
        missing.append(f"a sensor with id=\"{DETECTOR_ID}\" (type lummeter)")
    source_kind = None
    if SOURCE_ID in shapes and shapes[SOURCE_ID].emitter() is not None:
        source_kind = "disk"
    elif SOURCE_ID in emitters and emitters[SOURCE_ID].class_name() == "PointLight":
        source_kind = "point"
    else:
        missing.append(f"a source with id=\"{SOURCE_ID}\" (a disk shape with an area emitter, or a point emitter)")
    if missing:
        raise InputError("the XML scene lacks " + "; ".join(missing), path=path)
    sample = shapes[SAMPLE_ID]
    sensor = sensors[DETECTOR_ID]
    from roadgonio.engines.mitsuba.plugins import register_plugins
    classes = register_plugins()
    bsdf = sample.bsdf()
    if not isinstance(bsdf, classes["roadbsdf"]):
        raise InputError(f"the shape \"{SAMPLE_ID}\" must carry a BSDF of type roadbsdf, not {bsdf.class_name()}",
                         path=path)
    if not isinstance(sensor, classes["lummeter"]):
        raise InputError(f"the sensor \"{DETECTOR_ID}\" must be of type lummeter, not {sensor.class_name()}",
                         path=path)
    if (source_kind == "point") != instrument.source.is_point:
        raise InputError(f"the XML source is a {source_kind} source but the instrument's source radius is "
                         f"{instrument.source.radius_m:g} m", path=path)
    want = detector_props(instrument.observation, instrument.detector)
    got = detector_props(sensor.observation, sensor.detector)

    def same(k):
        a, b = want.get(k), got.get(k)
        if isinstance(a, str) or isinstance(b, str) or a is None or b is None:
            return a == b
        return a == b or math.isclose(float(a), float(b), rel_tol=1e-6, abs_tol=1e-12)
    bad = [k for k in sorted(set(want) | set(got)) if not same(k)]
    if bad:
        raise InputError("the XML detector differs from the instrument file in " +
                         ", ".join(f"{k} ({got.get(k, 'none')} vs {want.get(k, 'none')})" for k in bad) +
                         "; use the $parameters (e.g. value=\"$alpha_deg\")", path=path)
    film = sensor.film()
    if tuple(film.size()) != (resolution, resolution):
        p = mi.traverse(scene)
        p[f"{DETECTOR_ID}.film.size"] = mi.ScalarVector2u(resolution, resolution)
        p[f"{DETECTOR_ID}.film.crop_size"] = mi.ScalarVector2u(resolution, resolution)
        p.update()
    bsdf.channels = channels
    bsdf.set_model(model.params, model.variant)
    if source_kind == "disk":
        shapes[SOURCE_ID].emitter()  # present (checked above)
    rs = RoadScene(instrument=instrument, model=model, scene=scene, params=mi.traverse(scene),
                   integrator=_integrator(), sensor=sensor, bsdf=bsdf, sample_shape=sample,
                   source_kind=source_kind, resolution=resolution, xml=path, flat_rectangle=False)
    rs.info["xml_parameters"] = params
    return rs
