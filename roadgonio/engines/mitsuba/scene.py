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
sampling only: the small source disc is found by every sample; the relative SE is that of MIS at
about 1.6x the speed, while BSDF sampling alone almost never hits a 2 cm disc).

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

from roadgonio.engines import cellcheck
from roadgonio.engines.mitsuba import require_variant
from roadgonio.errors import InputError
from roadgonio.instrument.config import Detector, Instrument, Observation
from roadgonio.instrument.mesh import sample_triangles
from roadgonio.instrument.optics import (
    check_detector,
    check_line_of_sight,
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
#: Channels of the road BSDF in the backend scene: R = f_road, G = B = 1/pi (perfect diffuser).
ROAD, LAMBERT = 0, 1
#: Reflections followed per light path (the sample's own included) when the scene holds reflecting
#: parts and ``[scene] max_bounces`` is not given: at least this many, more for brighter parts
#: (:func:`default_max_bounces`).
DEFAULT_MAX_BOUNCES = 3
#: The share of the light that paths cut after K reflections leave out is of order rho^(K - 1) for
#: parts of reflectance up to rho (measured, docs/straylight.md "How many reflections": the portable
#: housing with walls 0.2 at tan eps 5, beta 0 lost 1.7 %, 0.53 %, 0.15 %, 0.04 % of k_A at K = 3 ... 6
#: against rho^(K-1) = 4 %, 0.8 %, 0.16 %, 0.03 %); the default K keeps it below this (user audit,
#: session 38: K = 3 biased k_A by +1.7 % (35 SE) with walls of 0.2, silently).
STRAY_TAIL = 3e-4
#: Lanes of the numerical probe that tells a reflecting BSDF from a black one.
PROBE_LANES = 4096
#: Ids of the housing's road floor around the sample (roadgonio.instrument.housing).
FLOOR_PREFIX = "housing_floor_"

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
    """Radiance L_0 (disc) or intensity (point) giving ~1 lx normal to the axis at the sample centre (at
    the nearest source distance of a fixed-height path: a scale only, k_A is a ratio). A radiance
    profile over the aperture (L = L_0 A(rho)) emits its disc mean of A (audit 28: portable_beam's
    render said ~1 lx where the source gave 0.88 lx, the mean of its 1 - 0.35 rho^4)."""
    src = instrument.source
    d2 = src.length_m ** 2
    return d2 if src.is_point else d2 / (math.pi * src.radius_m ** 2 * src.aperture.disc_mean())


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
    (the one check and text of every backend: :func:`roadgonio.engines.cellcheck.check_beam`)."""
    cellcheck.check_beam(instrument, [(tan_eps, beta_deg)], "mitsuba")


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
    #: stray light: the reflecting parts other than the sample (shapes), their ids, the reflections
    #: followed per path (1 = the sample's own only: direct light) and whether paths are traced
    parts: list = field(default_factory=list)
    part_ids: list = field(default_factory=list)
    max_bounces: int = 1
    stray: bool = False
    housing: Any = None

    # -- per cell --------------------------------------------------------------------------
    def place_source(self, tan_eps: float, beta_deg: float, *, check: bool = True) -> None:
        """Move the source to the cell (no recompile); checks the horizon, the beam limit, the
        line of sight (the one test of every backend: :func:`~roadgonio.instrument.optics.check_line_of_sight`,
        exact for the disc) and the housing. ``check=False`` only parks the source out of the way
        (:func:`build_scene`): that place is no cell the user asked for, so it is not checked (a beam
        table too short for tan eps 0 was refused there, naming a cell nobody asked for)."""
        if check:
            check_source(self.instrument, tan_eps, beta_deg)
            check_beam(self.instrument, tan_eps, beta_deg)
            if self.source_kind != "point":
                check_line_of_sight(self.instrument, [(tan_eps, beta_deg)])
        if check and self.housing is not None and self.checked:
            from roadgonio.instrument.enclosure import check_sources
            check_sources(self.instrument, self.housing, [(tan_eps, beta_deg)])
        if self.source_kind == "point":
            c = source_geometry(self.instrument, tan_eps, beta_deg).centre
            self.params[f"{SOURCE_ID}.position"] = _mi().Point3f(*[float(v) for v in c])
        else:
            self.params[f"{SOURCE_ID}.to_world"] = source_transform(self.instrument, tan_eps, beta_deg)
        self.params.update()
        self.cell = (float(tan_eps), float(beta_deg))

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
        from roadgonio.engines.mitsuba.plugins.ka_batch import intersect_sample
        # an edge or a vertex of the sample mesh under a ray is a hit (one retry, ka_batch.RETRY_NUDGE)
        si, on_sample = intersect_sample(self.scene, mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d)), mi.RayFlags.All,
                                         self.sample_shape)
        other = si.is_valid() & ~on_sample
        if bool(dr.any(other)):
            from roadgonio.errors import GeometryError
            cell = f" at tan eps = {self.cell[0]:g}, beta = {self.cell[1]:g}" if self.cell is not None else ""
            for shape in self.scene.shapes():
                # opaque: the shape pointer as a literal would make every new scene compile its own kernel
                k = int(dr.count(other & (si.shape == dr.opaque(mi.ShapePtr, shape)))[0])
                if not k:
                    continue
                if shape.id() == SOURCE_ID:
                    # the source disc in the line of sight is its own error, with the cell (not "enlarge the sample")
                    raise GeometryError(
                        f"the source disc blocks the detector's line of sight{cell}: {k} of {dr.width(other)} "
                        "detector rays hit the source before the sample (the source sits between the detector "
                        "and its footprint); this cell cannot be measured with this geometry")
                # name the part that stands in the detector's view (a housing wall, a baffle, a holder) and
                # where it is declared; no cell: the detector's view is the same at every cell (user audit:
                # 'at tan eps = 0, beta = 0' for a table of other cells, and no file)
                sec = self.instrument.extra.get("scene") if isinstance(self.instrument.extra, dict) else None
                where = (f" of the scene {xml_path(self.instrument, sec)}" if sec is not None and hasattr(sec, "get")
                         and sec.get("xml") else "")
                raise GeometryError(
                    f"{k} of {dr.width(other)} detector rays meet the part {shape.id()!r}{where} before the sample: "
                    "it blocks the detector's view of its footprint at every cell (a part of the scene must not "
                    "stand between the detector and the sample)", path=self.instrument.path)
        return judge_hits(np.array(on_sample, dtype=bool), np.array(si.is_valid(), dtype=bool),
                          np.array(si.p.x), np.array(si.p.y), self.instrument.sample.mesh)


def _integrator():
    return _mi().load_dict({"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})


def _bsdf_dict(model: RoadModel, channels: str) -> dict:
    d = {"type": "roadbsdf", "variant": model.variant, "channels": channels}
    d.update(model.params.to_dict())
    return d


def road_bsdf(model, channels: str):
    """The sample's ``roadbsdf``: eq. 4 with the model's parameters, or any surface that evaluates
    over the Dr.Jit namespace (a surface of :mod:`roadgonio.surface.truths`, a
    :class:`~roadgonio.surface.correction_surface.CorrectedSurface`: the plugin's ``set_surface``)."""
    mi = _mi()
    if isinstance(model, RoadModel):
        return mi.load_dict(_bsdf_dict(model, channels))
    bsdf = mi.load_dict({"type": "roadbsdf", "channels": channels})
    set_road_surface(bsdf, model)
    return bsdf


def set_road_surface(bsdf, model) -> None:
    """Give a ``roadbsdf`` the sample's surface: eq. 4's parameters and variant (``set_model``) for a
    :class:`RoadModel`, any other surface through ``set_surface`` (which refuses a numpy-only one)."""
    if isinstance(model, RoadModel):
        bsdf.set_model(model.params, model.variant)
    else:
        bsdf.set_surface(model)


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
    from roadgonio.instrument.enclosure import check_detector_view
    from roadgonio.instrument.housing import Housing
    housing = Housing.of(instrument)
    if check and housing is not None:
        check_detector_view(instrument, housing)
    if scene_sec and scene_sec.get("xml"):
        rs = _build_xml(instrument, model, scene_sec, resolution=resolution, spp=spp, sampler=sampler,
                        channels=channels, housing=housing)
    else:
        rs = _build_toml(instrument, model, resolution=resolution, spp=spp, sampler=sampler, channels=channels,
                         housing=housing)
    rs.housing = housing
    _light_paths(rs, scene_sec or {})
    if check:
        rs.footprint = footprint
        rs.place_source(0.0, 0.0, check=False)   # the source out of the way (XML files may leave it anywhere)
        rs.info["hit_check"] = rs.check_hits(n_random=int(hit_rays))
        rs.checked = True
    return rs


def housing_shapes(instrument: Instrument, housing, model: RoadModel) -> dict[str, dict]:
    """The housing's panels (:func:`roadgonio.instrument.enclosure.housing_panels`) as Mitsuba
    ``rectangle`` shapes by id: Lambertian, reflecting towards the inside of the box (walls and
    lid one-sided, baffles two-sided; a panel of reflectance 0 only shades), and the road floor
    around the sample with the sample's BRDF in the ``road`` channels (the same value in the road
    and the Lambert channel: a Lambert calibration replaces the sample, not the road around it)."""
    from roadgonio.instrument.enclosure import housing_panels
    mi = _mi()
    out = {}
    shared: dict[str, Any] = {}
    for p in housing_panels(instrument, housing):
        # panels with the same BSDF share one instance: every distinct instance is traced (a road BSDF
        # in Python) and compiled once more at each place a path vertex calls its part's BSDF
        if p.road:                                # the sample's surface, in the road channels
            key = "road"
            if key not in shared:
                shared[key] = road_bsdf(model, "road")
            bsdf = shared[key]
        else:
            bsdf = {"type": "diffuse", "reflectance": {"type": "uniform", "value": float(p.reflectance)}}
            key = repr(bsdf)
            if key not in shared:
                shared[key] = mi.load_dict(bsdf)
            bsdf = shared[key]
        if p.two_sided:
            key = f"two-sided {key}"
            if key not in shared:
                shared[key] = mi.load_dict({"type": "twosided", "bsdf": bsdf})
            bsdf = shared[key]
        out[p.id] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(p.to_world().tolist()),
                     "bsdf": bsdf}
    return out


def _build_toml(instrument, model, *, resolution, spp, sampler, channels, housing=None) -> RoadScene:
    mi = _mi()
    bsdf = road_bsdf(model, channels)
    smp = instrument.sample
    shape = to_mitsuba_mesh(sample_triangles(instrument), bsdf)
    film, samp = film_dict(resolution, spp, sampler)
    det = dict(type="lummeter", film=film, sampler=samp, **detector_props(instrument.observation, instrument.detector))
    src = instrument.source
    if src.is_point:
        source = {"type": "point", "position": [0.0, 0.0, src.length_m],
                  "intensity": {"type": "uniform", "value": source_radiance(instrument)}}
    else:
        source = {"type": "disk", "to_world": source_transform(instrument, 0.0, 0.0),
                  "emitter": {"type": "area", "radiance": {"type": "uniform", "value": source_radiance(instrument)}}}
    parts = {"type": "scene", DETECTOR_ID: det, SOURCE_ID: source, SAMPLE_ID: shape}
    if housing is not None:
        parts.update(housing_shapes(instrument, housing, model))
    scene = mi.load_dict(parts, optimize=False)          # keep every part (ids) apart: no merged meshes
    sensor = scene.sensors()[0]
    return RoadScene(instrument=instrument, model=model, scene=scene, params=mi.traverse(scene),
                     integrator=_integrator(), sensor=sensor, bsdf=bsdf, sample_shape=shape,
                     source_kind="point" if src.is_point else "disk", resolution=resolution,
                     flat_rectangle=smp.mesh is None)


def xml_parameters(instrument: Instrument, scene_sec) -> dict[str, str]:
    det, src, smp = instrument.detector, instrument.source, instrument.sample
    if src.path != "arc":
        raise InputError(f'a Mitsuba XML scene takes one source_distance_m: source.path = "{src.path}" '
                         'is modelled without [scene] xml only', path=instrument.path, field="source.path")
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
    if path.is_dir():
        raise InputError(f"{str(path)!r} is a directory; expected an XML scene file", path=instrument.path,
                         field="scene.xml")
    if not path.exists():
        raise InputError(f"XML scene {str(path)!r} does not exist", path=instrument.path, field="scene.xml")
    return path


def _build_xml(instrument, model, scene_sec, *, resolution, spp, sampler, channels, housing=None) -> RoadScene:
    mi = _mi()
    path = xml_path(instrument, scene_sec)
    params = xml_parameters(instrument, scene_sec)
    import re
    import xml.etree.ElementTree as ET
    text = path.read_text(encoding="utf-8", errors="replace")
    try:        # audit 28: a truncated file was blamed on [scene.params] (its $names cut off)
        ET.fromstring(text)
    except ET.ParseError as err:
        line = err.position[0] if getattr(err, "position", None) else None
        raise InputError(f"not a well-formed XML scene ({err}); expected Mitsuba's XML format", path=path,
                         line=line) from None
    used = set(re.findall(r"\$(\w+)", text))
    unused = sorted(k for k in scene_sec.get("params", {}) if k not in used)
    if unused:
        raise InputError(f"[scene.params] key(s) {', '.join(unused)} are not used as $name in {path.name}",
                         path=instrument.path, field="scene.params")
    params = {k: v for k, v in params.items() if k in used}   # Mitsuba refuses unused parameters
    try:
        scene = mi.load_file(str(path), optimize=False, **params)    # keep the parts (ids) apart
    except Exception as err:
        msg = str(err).strip().splitlines()
        raise InputError(f"Mitsuba cannot load the XML scene: {msg[-1] if msg else err}", path=path) from None
    if housing is not None:
        # the XML scene's objects and the housing's panels in one scene
        objs: dict[str, Any] = {"type": "scene"}
        # (Emitter.get_shape: audit 22, `e.shape()` does not exist and every XML scene with a [housing] crashed)
        for obj in list(scene.shapes()) + [e for e in scene.emitters() if e.get_shape() is None] + list(scene.sensors()):
            key = obj.id() or f"_part{len(objs)}"
            if key in objs:
                key = f"{key}_{len(objs)}"
            objs[key] = obj
        panels = housing_shapes(instrument, housing, model)
        clash = sorted(set(objs) & set(panels))
        if clash:
            raise InputError(f"the XML scene uses the id(s) {', '.join(clash)} of the [housing] panels", path=path)
        objs.update(panels)
        scene = mi.load_dict(objs, optimize=False)
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
    # audit 22: other emitters (a constant background, a second lit shape) were dropped without a word
    others = [e for e in scene.emitters()
              if not ((e.get_shape() is not None and e.get_shape().id() == SOURCE_ID) or e.id() == SOURCE_ID)]
    if others:
        names = ", ".join(sorted(f"{e.class_name()}" + (f" on shape {e.get_shape().id()!r}" if e.get_shape() is not None
                                                        else f" {e.id()!r}" if e.id() else "") for e in others))
        raise InputError(f"the XML scene holds light other than the source (id=\"{SOURCE_ID}\"): {names}; roadgonio "
                         "simulates the instrument's source only (ambient light is not part of k_A): remove it",
                         path=path)
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
    set_road_surface(bsdf, model)
    if source_kind == "disk":
        shapes[SOURCE_ID].emitter()  # present (checked above)
    rs = RoadScene(instrument=instrument, model=model, scene=scene, params=mi.traverse(scene),
                   integrator=_integrator(), sensor=sensor, bsdf=bsdf, sample_shape=sample,
                   source_kind=source_kind, resolution=resolution, xml=path, flat_rectangle=False)
    rs.info["xml_parameters"] = params
    return rs


# ----------------------------------------------------------------------------------------------
# Stray light: which parts of the scene reflect, and how many reflections a path follows
# ----------------------------------------------------------------------------------------------

def local_interaction(n: int, u, v, wi):
    """``n`` lanes of a surface interaction in a BSDF's local frame (normal +z, at the origin) with
    texture coordinates (``u``, ``v``) and incident direction ``wi``: what :func:`probe_bsdf` and
    :func:`directional_albedo_max` hand to the BSDF."""
    mi = _mi()
    import drjit as dr
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.t = mi.Float(1.0)
    si.p = mi.Point3f(0.0, 0.0, 0.0)
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    si.uv = mi.Point2f(mi.Float(u), mi.Float(v))
    si.wi = wi
    return si


def probe_bsdf(bsdf, n: int = PROBE_LANES, seed: int = 1) -> tuple[float, float, float]:
    """Largest reflected value of a BSDF over ``n`` random (uv, incident, outgoing) triples in the
    upper hemisphere: (max of eval, max of the sample weight, min of eval); the first two 0 for a
    black BSDF, the last negative for a reflectance below 0 (an input error, :func:`classify_parts`)."""
    mi = _mi()
    rng = np.random.default_rng(seed)
    u = rng.random((n, 8)).astype(np.float32)
    si = local_interaction(n, u[:, 0], u[:, 1],
                           mi.warp.square_to_cosine_hemisphere(mi.Point2f(mi.Float(u[:, 2]), mi.Float(u[:, 3]))))
    wo = mi.warp.square_to_cosine_hemisphere(mi.Point2f(mi.Float(u[:, 4]), mi.Float(u[:, 5])))
    ctx = mi.BSDFContext()
    value = bsdf.eval(ctx, si, wo)
    _, weight = bsdf.sample(ctx, si, mi.Float(u[:, 6]), mi.Point2f(mi.Float(u[:, 7]), mi.Float(u[:, 2])))
    v = np.nan_to_num(np.array(value, dtype=np.float64))
    w = np.nan_to_num(np.array(weight, dtype=np.float64))
    return float(v.max(initial=0.0)), float(w.max(initial=0.0)), float(v.min(initial=0.0))


#: A part's BSDF may reflect at most 1 + this of the light it receives (its directional albedo,
#: :func:`directional_albedo_max`; the Monte Carlo estimate's own error is far below it).
ALBEDO_TOL = 1e-3
#: Incidence cosines and lanes of that estimate.
ALBEDO_COS = (1.0, 0.7, 0.3, 0.05)
ALBEDO_LANES = 1 << 14


def directional_albedo_max(bsdf) -> float:
    """The largest directional albedo of ``bsdf`` (the share of the light from one direction that it
    reflects, E[f cos / pdf] over its own sampling, largest colour channel) over incidence cosines
    :data:`ALBEDO_COS`, by Monte Carlo with fixed numbers (a stratified grid of sample points and
    texture coordinates), in float64 numpy from the renderer's weights. Above 1 the part creates
    light: an input error (energy conservation), not a stray-light result."""
    mi = _mi()
    n = ALBEDO_LANES
    k = int(round(n ** 0.5))
    g = (np.arange(k) + 0.5) / k
    u, v = [np.ascontiguousarray(a.ravel()) for a in np.meshgrid(g, g)]
    worst = 0.0
    for c in ALBEDO_COS:
        si = local_interaction(n, np.roll(u, 7), np.roll(v, 3),
                               mi.Vector3f(float(np.sqrt(1.0 - c * c)), 0.0, float(c)))
        _, w = bsdf.sample(mi.BSDFContext(), si, mi.Float(np.roll(u, 11)), mi.Point2f(mi.Float(u), mi.Float(v)))
        # (channels, lanes); a monochrome variant's Float is one channel
        w = np.nan_to_num(np.atleast_2d(np.asarray(w, dtype=np.float64)), nan=0.0, posinf=0.0)
        worst = max(worst, float(np.max(np.mean(w, axis=1))))
    return worst


def default_max_bounces(rho_max: float) -> int:
    """Reflections a light path follows by default when the scene's reflecting parts reflect up to
    ``rho_max`` (directional albedo): the least K >= :data:`DEFAULT_MAX_BOUNCES` with
    rho_max^(K-1) <= :data:`STRAY_TAIL`, at most ``MAX_BOUNCES_LIMIT`` (walls 0.01: 3, 0.02 and 0.05: 4, 0.2: 7,
    0.5: 13; 0.88 and above: 64)."""
    from roadgonio.instrument.config import MAX_BOUNCES_LIMIT
    rho = float(rho_max)
    if not rho > 0.0:
        return DEFAULT_MAX_BOUNCES
    if rho >= 1.0:
        return MAX_BOUNCES_LIMIT
    k = 1 + math.ceil(math.log(STRAY_TAIL) / math.log(rho) - 1e-9)
    return int(min(max(k, DEFAULT_MAX_BOUNCES), MAX_BOUNCES_LIMIT))


def truncation_share(rho_max: float, max_bounces: int) -> float:
    """The order of the share of the light left out by paths cut after ``max_bounces`` reflections
    among parts of reflectance up to ``rho_max``: rho_max^(K-1) (:data:`STRAY_TAIL`)."""
    return float(min(max(rho_max, 0.0), 1.0) ** (int(max_bounces) - 1))


def classify_parts(rs: RoadScene) -> tuple[list, list[str]]:
    """The shapes of the scene other than the sample and the source whose BSDF reflects light
    (:func:`probe_bsdf`), and the ids of those that only shade (black: reflectance 0)."""
    reflecting, black = [], []
    for shape in rs.scene.shapes():
        if shape.id() in (SAMPLE_ID, SOURCE_ID):
            continue
        bsdf = shape.bsdf()
        value, weight, lowest = (0.0, 0.0, 0.0) if bsdf is None else probe_bsdf(bsdf)
        if lowest < 0.0:
            # user audit, session 43: <float name="reflectance" value="-0.5"/> was taken for a black part
            # (stray light silently off); Mitsuba's own parser refuses only a negative RGB
            raise InputError(f"the part {shape.id() or '(a shape without id)'!r} reflects a negative amount of "
                             f"light ({bsdf.class_name()}: BSDF values down to {lowest:.3g}); expected a "
                             "reflectance >= 0 (0 for a part that only shades)",
                             path=rs.xml if rs.xml is not None else rs.instrument.path)
        if max(value, weight) <= 0.0:
            black.append(shape.id())
        else:
            reflecting.append(shape)
    return reflecting, black


def _light_paths(rs: RoadScene, scene_sec) -> None:
    """Decide what the scene requires (model only that; docs/straylight.md, "What is modelled"): the light paths follow
    ``[scene] max_bounces`` reflections (the sample's own included; default
    :data:`DEFAULT_MAX_BOUNCES` when some part other than the sample reflects, else 1: the direct
    light alone, exactly the engine without stray light). Paths are traced (``rs.stray``) when
    max_bounces > 1 and either some part reflects, or max_bounces was given for a sample that is not
    the flat rectangle (a mesh or XML sample may light itself). In that case every reflecting part
    must have a BSDF that the paths can follow: no transmission, no perfectly specular (delta)
    reflection (next-event estimation cannot reach the source through a mirror), no second road
    BSDF in the road/Lambert channels."""
    mi = _mi()
    reflecting, black = classify_parts(rs)
    # the road floor around a flat sample lies in the sample's plane: it sends light to the footprint
    # only through another reflecting part
    lights = [s for s in reflecting if not (rs.flat_rectangle and s.id().startswith(FLOOR_PREFIX))]
    if not lights:
        black += [s.id() for s in reflecting]
        reflecting = []
    given = scene_sec.get("max_bounces") if hasattr(scene_sec, "get") else None
    # the parts' reflectance decides how many reflections the paths need (the road parts reflect
    # as the sample does; they are checked below)
    from roadgonio.engines.mitsuba.plugins import register_plugins
    road_cls = register_plugins()["roadbsdf"]
    # per part, in the order of ``reflecting`` (ids need not be unique: parts of an XML scene may have none)
    albedos = [None if isinstance(s.bsdf(), road_cls) else directional_albedo_max(s.bsdf()) for s in reflecting]
    rho_max = max((a for a in albedos if a is not None), default=0.0)
    k = int(given) if given is not None else (default_max_bounces(rho_max) if reflecting else 1)
    rs.max_bounces = k
    rs.info["part_reflectance_max"] = rho_max
    rs.stray = k > 1 and (bool(reflecting) or (given is not None and not rs.flat_rectangle))
    rs.info["black_parts"] = black
    rs.info["reflecting_parts"] = [s.id() for s in reflecting]
    if not rs.stray:
        return
    where = rs.xml if rs.xml is not None else rs.instrument.path
    for shape, albedo in zip(reflecting + [rs.sample_shape], albedos + [None]):
        bsdf = shape.bsdf()
        flags = int(bsdf.flags())
        name = shape.id() or "(a shape without id)"
        if mi.has_flag(flags, mi.BSDFFlags.Transmission) or mi.has_flag(flags, mi.BSDFFlags.Null):
            raise InputError(f"the part {name!r} transmits light ({bsdf.class_name()}); the stray-light paths follow "
                             "reflections only: give it an opaque BSDF (diffuse, roughplastic, roughconductor...) or "
                             "set [scene] max_bounces = 1", path=where)
        if mi.has_flag(flags, mi.BSDFFlags.Delta):
            raise InputError(f"the part {name!r} has a perfectly specular BSDF ({bsdf.class_name()}): a path ends "
                             "with next-event estimation to the source, which no mirror reflection can reach; use a "
                             "rough BSDF (roughconductor, roughplastic with alpha > 0) or set [scene] max_bounces = 1",
                             path=where)
        if albedo is not None and albedo > 1.0 + ALBEDO_TOL:      # a part other than the sample, not road
            # audit 27: diffuse reflectance = 1.5 ran, the stray light grew by a third, no word
            raise InputError(f"the part {name!r} reflects more light than it receives ({bsdf.class_name()}: "
                             f"directional albedo up to {albedo:.3g}); expected a reflectance <= 1",
                             path=where)
        if shape.id() != SAMPLE_ID and isinstance(bsdf, road_cls) and bsdf.channels != "road":
            raise InputError(f"the part {name!r} carries a road BSDF in the {bsdf.channels!r} channels: only the "
                             "sample has a Lambert channel; give the part channels = \"road\"", path=where)
    rs.parts = reflecting
    rs.part_ids = [s.id() for s in reflecting]
    if reflecting and k > 1 and truncation_share(rho_max, k) > STRAY_TAIL:
        # after the checks above (user audit, session 43: a part then refused for reflecting 1.5 was
        # first warned about as "reflecting up to 1")
        import warnings

        from roadgonio.errors import ModelWarning
        said = (f"[scene] max_bounces = {k}" if given is not None else
                f"the most reflections followed ({k})")
        warnings.warn(ModelWarning(
            f"{said} cuts the light paths among parts reflecting up to {min(rho_max, 1.0):.3g}: what is left out "
            f"can bias k_A by a relative amount of order {truncation_share(rho_max, k):.2g}, in no SE"
            + (f" (this scene's default is {default_max_bounces(rho_max)})" if given is not None else "")
            + " (docs/straylight.md, 'How many reflections')"), stacklevel=2)
