"""Instrument description (docs/conventions.md section 4): frozen dataclasses that
validate themselves on construction, built from TOML or a plain dict, units in the names.

.. code-block:: toml

    [instrument]                 # optional
    name = "portable"
    description = "..."
    [observation]
    alpha_deg = 1.0              # delta_deg = 0.0
    [source]
    distance_m = 3.0
    radius_m = 0.02              # radius of the exit aperture; 0 = point source
    # beam_half_angle_deg = 5.0  # optional: emission limited to a cone about the source axis
    # beam_sigma_deg = 10.0      # optional angular profile: radiance exp(-theta^2 / 2 sigma^2), or
    #                            # beam_cos_power = n (radiance cos^n), or beam_intensity_file = "led.ldt"
    # aperture_edge_radiance = 0.7  # optional: radiance 1 - (1 - e) rho^2 over the exit aperture,
    #                            # or aperture_radiance_file = "aperture.csv" (rho, relative_radiance)
    [detector]
    distance_m = 5.0
    pupil_radius_m = 0.01        # radius of the entrance pupil; 0 = pinhole
    field_half_angle_deg = 0.15
    focus_m = 5.0                # default: distance_m; "inf" (or TOML inf) = angular field
    # field_edge_sensitivity = 0.8  # k_D at the field-stop edge relative to the centre (default 1)
    # field_sensitivity = "map.csv"  # or a 2-D map of k_D over the field stop (CSV grid or image)
    [sample]
    size_x_m = 6.0               # along the observation azimuth
    size_y_m = 2.0               # or mesh = "file.ply" (relative to the TOML file)

Whatever is not declared is not modelled: a zero radius is a point, no beam limit is no limit.

Every dataclass checks its own values in ``__post_init__`` (``Source(distance_m=-1)`` raises an
:class:`~roadgonio.errors.InputError` naming ``source.distance_m``), so an instrument built in
Python is held to the same rules as one read from a file; :meth:`Instrument.from_dict` adds the
file name to the error. A detector focused at infinity (an angular field) has
``focus_m = math.inf``; files spell it ``"inf"`` (or TOML's bare ``inf``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from roadgonio.errors import InputError
from roadgonio.fileio import read_toml
from roadgonio.geometry import w_detector, w_source
from roadgonio.geometry import MAX_LENGTH_M as _MAX_LENGTH_M
from roadgonio.instrument.calibration import Calibration
from roadgonio.instrument.coverage import MeasuredCells

_INF_WORDS = ("inf", "+inf", "infinity")
#: The longest length of an instrument (:data:`roadgonio.geometry.MAX_LENGTH_M`, where the housing
#: takes it from too).
MAX_LENGTH_M = _MAX_LENGTH_M
#: The smallest non-zero aperture radius, m: below a micrometre a disc is no aperture of an
#: instrument (give 0 for a point source or a pinhole), and its area underflows (1e-300 m).
MIN_APERTURE_M = 1e-6


def _number(v: Any, name: str, *, allow_inf: bool = False) -> float:
    """``v`` as a float, or an InputError naming the field ``name``; ``"inf"`` where allowed."""
    if allow_inf and isinstance(v, str) and v.strip().lower() in _INF_WORDS:
        return math.inf
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        extra = ' or "inf"' if allow_inf else ""
        raise InputError(f"expected a number{extra}, got {v!r}", field=name)
    v = float(v)
    if math.isnan(v) or (v == -math.inf) or (math.isinf(v) and not allow_inf):
        raise InputError(f"expected a finite number, got {v}", field=name)
    return v


def _checked(obj, attr: str, name: str, *, lo=None, hi=None, lo_open=False, hi_open=False,
             allow_inf=False, optional=False, length=False, aperture=False) -> None:
    """Validate (and normalise to float) the field ``attr`` of the frozen dataclass ``obj``;
    ``length``: at most :data:`MAX_LENGTH_M` (unless infinite where allowed); ``aperture``: 0 or
    at least :data:`MIN_APERTURE_M`."""
    v = getattr(obj, attr)
    if v is None and optional:
        return
    v = _number(v, name, allow_inf=allow_inf)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise InputError(f"expected a value {'>' if lo_open else '>='} {lo:g}, got {v:g}", field=name)
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise InputError(f"expected a value {'<' if hi_open else '<='} {hi:g}, got {v:g}", field=name)
    if length and math.isfinite(v) and v > MAX_LENGTH_M:
        raise InputError(f"expected at most {MAX_LENGTH_M:g} m (no instrument is larger)"
                         + (', or "inf" for a focus at infinity' if allow_inf else "") + f", got {v:g}", field=name)
    if aperture and 0.0 < v < MIN_APERTURE_M:
        raise InputError(f"expected 0 (a point) or a radius of at least {MIN_APERTURE_M:g} m, got {v:g}", field=name)
    object.__setattr__(obj, attr, v)


def _check_keys(d: Mapping[str, Any], allowed: set[str], section: str, path) -> None:
    extra = sorted(set(d) - allowed)
    if extra:
        # the field names the first unknown key in its section, as the study and layout files do
        # (review, session 39: 'detector' alone)
        raise InputError(f"unknown key(s) {', '.join(extra)}; expected some of {', '.join(sorted(allowed))}",
                         path=path, field=f"{section}.{extra[0]}")


@dataclass(frozen=True)
class Observation:
    """Observation direction: elevation ``alpha_deg`` above the surface (0 < alpha < 90) and
    azimuth ``delta_deg`` (docs/conventions.md section 1)."""

    alpha_deg: float = 1.0
    delta_deg: float = 0.0

    def __post_init__(self):
        _checked(self, "alpha_deg", "observation.alpha_deg", lo=0.0, hi=90.0, lo_open=True, hi_open=True)
        _checked(self, "delta_deg", "observation.delta_deg", lo=-360.0, hi=360.0)

    @property
    def w_o(self) -> np.ndarray:
        return w_detector(self.alpha_deg, self.delta_deg)


#: The source paths (docs/conventions.md section 4): ``arc`` keeps the source at ``distance_m`` from
#: the sample centre for every cell (a goniometer arm); ``fixed_height`` moves it along a straight
#: line at ``height_m`` above the sample plane (a corridor goniophotometer), so its distance is
#: ``height_m / cos eps`` (:func:`roadgonio.instrument.optics.source_distance_m`).
SOURCE_PATHS = ("arc", "fixed_height")


#: The keys of [source] that shape its beam (docs/conventions.md section 4; roadgonio.instrument.profiles):
#: the angular profile (at most one of the first three) and the aperture profile (at most one of the last two).
BEAM_KEYS = ("beam_sigma_deg", "beam_cos_power", "beam_intensity_file")
APERTURE_KEYS = ("aperture_edge_radiance", "aperture_radiance_file")


def _file_key(obj, attr: str, name: str) -> None:
    """Normalise the file-name field ``attr`` to an absolute Path (None stays None): a file named
    relative to the working folder is the file read now, wherever the instrument goes next (a Dask
    worker, a rewritten instrument file)."""
    v = getattr(obj, attr)
    if v is None:
        return
    if not isinstance(v, (str, Path)) or not str(v):
        raise InputError(f"expected a file name, got {v!r}", field=name)
    object.__setattr__(obj, attr, Path(v).absolute())


def _digests(obj, attrs) -> dict[str, str]:
    """sha256 of the content of the files named by ``attrs`` of ``obj`` (those given)."""
    from roadgonio.instrument.profiles import file_digest
    return {a: file_digest(getattr(obj, a)) for a in attrs if getattr(obj, a) is not None}


@dataclass(frozen=True)
class Source:
    """Disc exit aperture of radius ``radius_m`` (0 = point source) facing the sample centre; optional
    beam cone of half-angle ``beam_half_angle_deg`` (None = no beam limit). Its centre is at
    ``distance_m`` from the sample centre for every cell (``path = "arc"``, the default) or at
    ``height_m`` above the sample plane (``path = "fixed_height"``: distance ``height_m / cos eps``,
    so the source's solid angle and the illuminated area change with eps); the distance of a cell is
    :func:`roadgonio.instrument.optics.source_distance_m`.

    Its radiance is uniform (a Lambertian area emitter) unless a profile is given
    (:mod:`roadgonio.instrument.profiles`: ``L = L_0 A(rho) P(theta)``): an angular profile P, one of
    ``beam_sigma_deg`` (Gaussian in radiance, sigma in deg), ``beam_cos_power`` (radiance cos^n) or
    ``beam_intensity_file`` (a tabulated intensity distribution, EULUMDAT .ldt or CSV ``theta_deg,
    I``), and an aperture profile A, one of ``aperture_edge_radiance`` (``1 - (1 - e) rho^2``) or
    ``aperture_radiance_file`` (CSV ``rho, relative_radiance``). Files are read on construction
    (a file name relative to an instrument file is resolved by :meth:`Instrument.from_dict`)."""

    distance_m: float | None = None
    radius_m: float = 0.0
    beam_half_angle_deg: float | None = None
    beam_sigma_deg: float | None = None
    beam_cos_power: float | None = None
    beam_intensity_file: Path | None = None
    aperture_edge_radiance: float = 1.0
    aperture_radiance_file: Path | None = None
    path: str = "arc"
    height_m: float | None = None

    def __post_init__(self):
        if self.path not in SOURCE_PATHS:
            raise InputError(f"expected one of {', '.join(map(repr, SOURCE_PATHS))}, got {self.path!r}",
                             field="source.path")
        if self.path == "arc":
            if self.height_m is not None:
                raise InputError('height_m belongs to path = "fixed_height"; an arc has distance_m',
                                 field="source.height_m")
            if self.distance_m is None:
                object.__setattr__(self, "distance_m", 3.0)
            _checked(self, "distance_m", "source.distance_m", lo=0.0, lo_open=True, length=True)
        else:
            if self.distance_m is not None:
                raise InputError('a fixed-height source has height_m, not distance_m (its distance is '
                                 'height_m / cos eps)', field="source.distance_m")
            if self.height_m is None:
                raise InputError('missing (required for path = "fixed_height")', field="source.height_m")
            _checked(self, "height_m", "source.height_m", lo=0.0, lo_open=True, length=True)
        _checked(self, "radius_m", "source.radius_m", lo=0.0, aperture=True)
        _checked(self, "beam_half_angle_deg", "source.beam_half_angle_deg", lo=0.0, hi=90.0, lo_open=True,
                 optional=True)
        if self.radius_m >= self.length_m:
            raise InputError(f"the source radius ({self.radius_m:g} m) must be smaller than its "
                             f"{self.length_key[:-2]} ({self.length_m:g} m)", field="source.radius_m")
        from roadgonio.instrument import profiles
        _checked(self, "beam_sigma_deg", "source.beam_sigma_deg", lo=0.0, lo_open=True, hi=1e6, optional=True)
        _checked(self, "beam_cos_power", "source.beam_cos_power", lo=0.0, hi=1e6, optional=True)
        _file_key(self, "beam_intensity_file", "source.beam_intensity_file")
        _checked(self, "aperture_edge_radiance", "source.aperture_edge_radiance", lo=0.0, hi=10.0)
        _file_key(self, "aperture_radiance_file", "source.aperture_radiance_file")
        given = [k for k in BEAM_KEYS if getattr(self, k) is not None]
        if len(given) > 1:
            raise InputError(f"give at most one angular profile, not {' and '.join(given)}", field=f"source.{given[1]}")
        if self.aperture_radiance_file is not None and self.aperture_edge_radiance != 1.0:
            raise InputError("give either aperture_edge_radiance or aperture_radiance_file, not both",
                             field="source.aperture_radiance_file")
        if self.beam_intensity_file is not None:
            beam = profiles.intensity_profile(self.beam_intensity_file)
        elif self.beam_sigma_deg is not None:
            beam = profiles.BeamProfile(kind="gaussian", sigma_rad=math.radians(self.beam_sigma_deg))
        elif self.beam_cos_power is not None and self.beam_cos_power != 0.0:
            beam = profiles.BeamProfile(kind="cos_power", power=self.beam_cos_power)
        else:
            beam = profiles.BeamProfile()
        if self.aperture_radiance_file is not None:
            aperture = profiles.aperture_table(self.aperture_radiance_file)
        elif self.aperture_edge_radiance != 1.0:
            aperture = profiles.ApertureProfile(kind="quadratic", edge=self.aperture_edge_radiance)
        else:
            aperture = profiles.ApertureProfile()
        object.__setattr__(self, "_beam", beam)
        object.__setattr__(self, "_aperture", aperture)
        object.__setattr__(self, "_digests", _digests(self, ("beam_intensity_file", "aperture_radiance_file")))

    @property
    def is_point(self) -> bool:
        return self.radius_m == 0.0

    @property
    def length_key(self) -> str:
        """The key of the source's one length: ``distance_m`` (arc) or ``height_m`` (fixed height)."""
        return "distance_m" if self.path == "arc" else "height_m"

    @property
    def length_m(self) -> float:
        """That length (m): D_S of an arc, the height of a fixed-height path (its distance at eps = 0,
        the nearest the source comes). A distance error of the uncertainty budget is an error of this
        length (every cell's distance scales with it)."""
        return self.distance_m if self.path == "arc" else self.height_m

    @property
    def beam(self):
        """The angular profile P(theta) (:class:`roadgonio.instrument.profiles.BeamProfile`)."""
        return self._beam

    @property
    def aperture(self):
        """The aperture profile A(rho) (:class:`roadgonio.instrument.profiles.ApertureProfile`)."""
        return self._aperture

    @property
    def profiled(self) -> bool:
        """True when the radiance is not uniform (an angular or an aperture profile is given)."""
        return not (self._beam.uniform and self._aperture.uniform)

    @property
    def profile_keys(self) -> list[str]:
        """The keys that give this source a profile (for messages: ``source.beam_sigma_deg``, ...)."""
        keys = [k for k in BEAM_KEYS if getattr(self, k) is not None and not (k == "beam_cos_power"
                                                                              and self.beam_cos_power == 0.0)]
        if self.aperture_radiance_file is not None:
            keys.append("aperture_radiance_file")
        elif self.aperture_edge_radiance != 1.0:
            keys.append("aperture_edge_radiance")
        return [f"source.{k}" for k in keys]


@dataclass(frozen=True)
class Detector:
    """Luminance meter: entrance pupil disc of radius ``pupil_radius_m`` (0 = pinhole) at
    ``distance_m``, circular field stop of half-angle ``field_half_angle_deg`` conjugate to the plane
    at ``focus_m`` (None = not given: the focus follows ``distance_m``, i.e. the meter is focused on
    the sample centre; ``math.inf`` = an angular field).

    Sensitivity over the field (k_D of paper eq. 3): ``k_D(rho) = 1 - (1 - e) rho^2`` with rho the
    distance from the field centre as a fraction of the field radius and ``e`` =
    ``field_edge_sensitivity`` (k_D at the field-stop edge relative to the centre; 1 = uniform, the
    default); or a 2-D map ``field_sensitivity`` (a CSV grid or a greyscale image over the field
    stop, :mod:`roadgonio.instrument.profiles`; read on construction). The two are exclusive.
    """

    distance_m: float = 5.0
    pupil_radius_m: float = 0.0
    field_half_angle_deg: float = 0.0
    focus_m: float | None = None
    field_edge_sensitivity: float = 1.0
    field_sensitivity: Path | None = None

    def __post_init__(self):
        _checked(self, "distance_m", "detector.distance_m", lo=0.0, lo_open=True, length=True)
        _checked(self, "pupil_radius_m", "detector.pupil_radius_m", lo=0.0, aperture=True)
        _checked(self, "field_half_angle_deg", "detector.field_half_angle_deg", lo=0.0, hi=45.0, hi_open=True)
        _checked(self, "focus_m", "detector.focus_m", lo=0.0, lo_open=True, allow_inf=True, optional=True,
                 length=True)
        _checked(self, "field_edge_sensitivity", "detector.field_edge_sensitivity", lo=0.0, hi=2.0)
        _file_key(self, "field_sensitivity", "detector.field_sensitivity")
        fmap = None
        if self.field_sensitivity is not None:
            if self.field_edge_sensitivity != 1.0:
                raise InputError("give either field_edge_sensitivity or a field_sensitivity map, not both",
                                 field="detector.field_sensitivity")
            from roadgonio.instrument.profiles import read_field_map
            fmap = read_field_map(self.field_sensitivity)
        object.__setattr__(self, "_field_map", fmap)
        object.__setattr__(self, "_digests", _digests(self, ("field_sensitivity",)))
        if self.pupil_radius_m >= self.distance_m:
            raise InputError(f"the pupil radius ({self.pupil_radius_m:g} m) must be smaller than the "
                             f"detector distance ({self.distance_m:g} m)", field="detector.pupil_radius_m")

    @property
    def field_map(self):
        """The sensitivity map (:class:`roadgonio.instrument.profiles.FieldMap`), or None."""
        return self._field_map

    @property
    def focus_distance_m(self) -> float:
        """The distance (m) of the plane the field stop is conjugate to: ``focus_m``, or
        ``distance_m`` when not given; ``math.inf`` for an angular field."""
        return self.distance_m if self.focus_m is None else self.focus_m

    @property
    def angular_field(self) -> bool:
        """True when the meter is focused at infinity (its field is a cone of directions)."""
        return math.isinf(self.focus_distance_m)

    @property
    def is_single_ray(self) -> bool:
        return self.pupil_radius_m == 0.0 and self.field_half_angle_deg == 0.0


@dataclass(frozen=True)
class SampleGeometry:
    """A flat rectangle ``size_x_m`` x ``size_y_m`` centred on the origin (x along the observation
    azimuth; default 6 m x 2 m), or a trimesh-readable mesh file (then no sizes)."""

    size_x_m: float | None = None
    size_y_m: float | None = None
    mesh: Path | None = None

    def __post_init__(self):
        if self.mesh is not None:
            if self.size_x_m is not None or self.size_y_m is not None:
                raise InputError("give either a mesh or the sizes of a rectangle, not both", field="sample.mesh")
            if not isinstance(self.mesh, (str, Path)) or not str(self.mesh):
                raise InputError(f"expected a file name, got {self.mesh!r}", field="sample.mesh")
            mesh = Path(self.mesh)
            if mesh.is_dir():
                raise InputError(f"{str(mesh)!r} is a directory; expected a mesh file", field="sample.mesh")
            if not mesh.exists():
                raise InputError(f"mesh file {str(mesh)!r} does not exist", field="sample.mesh")
            object.__setattr__(self, "mesh", mesh)
            return
        for attr, default in (("size_x_m", 6.0), ("size_y_m", 2.0)):
            if getattr(self, attr) is None:
                object.__setattr__(self, attr, default)
            _checked(self, attr, f"sample.{attr}", lo=0.0, lo_open=True, length=True)


def _resolve_file(sec: dict, key: str, section: str, path: Path | None) -> None:
    """A file name in ``sec[key]`` relative to the instrument file ``path``, made absolute (so that
    to_dict/from_dict, with_changes and best.toml never join it twice)."""
    if key not in sec:
        return
    v = sec[key]
    if not isinstance(v, (str, Path)) or not str(v):
        raise InputError(f"expected a file name, got {v!r}", field=f"{section}.{key}")
    f = Path(v)
    if not f.is_absolute() and path is not None:
        f = (path.parent / f).absolute()
    sec[key] = f


_SECTIONS = ("observation", "source", "detector", "sample", "instrument")
#: Sections kept as they are for the parts that read them: [scene] (the Mitsuba XML scene and the
#: light paths, roadgonio.engines.mitsuba.scene) and [housing] (roadgonio.instrument.housing); both
#: are checked on construction. [calibration] (docs/conventions.md section 5) is the field
#: ``calibration`` (roadgonio.instrument.calibration; k_A in its mode: roadgonio.engines.calibration).
EXTRA_SECTIONS = ("scene", "housing")
#: Keys of [scene]: the XML file, its $parameters, and the reflections followed per light path.
SCENE_KEYS = ("xml", "params", "max_bounces")
#: Largest [scene] max_bounces.
MAX_BOUNCES_LIMIT = 64


def check_extra_sections(extra: Mapping[str, Any]) -> None:
    """Check [scene] (known keys; ``xml`` a file name, ``params`` a table and only with ``xml``,
    ``max_bounces`` a whole number 1 ... 64; an empty [scene] is no scene) and [housing] (:class:`roadgonio.instrument.housing.Housing`)."""
    scene = extra.get("scene")
    if scene is not None:
        if not isinstance(scene, Mapping):
            raise InputError("expected a table [scene]", field="scene")
        _check_keys(scene, set(SCENE_KEYS), "scene", None)
        if "xml" in scene and (not isinstance(scene["xml"], (str, Path)) or not str(scene["xml"])):
            raise InputError(f"expected a file name (text), got {scene['xml']!r}", field="scene.xml")
        if "params" in scene and not isinstance(scene["params"], Mapping):
            raise InputError("expected a table [scene.params]", field="scene.params")
        for k, v in (scene.get("params") or {}).items():
            # a number that is not finite reached the XML as "nan" and Mitsuba dropped the part it placed
            if isinstance(v, float) and not math.isfinite(v):
                raise InputError(f"expected a finite number, got {v!r}", field=f"scene.params.{k}")
        if "params" in scene and "xml" not in scene:
            # its $parameters would be ignored without the XML file they fill in
            raise InputError('[scene.params] without the Mitsuba XML file they are for; expected xml = "FILE.xml"',
                             field="scene.xml")
        if "max_bounces" in scene:
            v = scene["max_bounces"]
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= MAX_BOUNCES_LIMIT:
                raise InputError(f"expected a whole number of reflections 1 ... {MAX_BOUNCES_LIMIT} (1 = the "
                                 f"sample's own only), got {v!r}", field="scene.max_bounces")
    if extra.get("housing") is not None:
        from roadgonio.instrument.housing import Housing
        Housing.from_dict(extra["housing"])


class FrozenDict(dict):
    """A read-only ``dict`` (nested mappings frozen too): an instrument's extra sections cannot be
    changed after construction, like its other fields. A ``dict`` subclass, so it pickles (Dask
    workers receive instruments), compares and serialises like a plain dict."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        for k, v in list(dict.items(self)):
            if isinstance(v, Mapping) and not isinstance(v, FrozenDict):
                dict.__setitem__(self, k, FrozenDict(v))
            elif isinstance(v, list):
                dict.__setitem__(self, k, tuple(v))

    def _refuse(self, *args, **kwargs):
        raise TypeError("an instrument is frozen: build a new one (dataclasses.replace or "
                        "Instrument.with_changes) instead of changing its sections")

    __setitem__ = __delitem__ = clear = pop = popitem = setdefault = update = _refuse
    __ior__ = _refuse

    def __reduce__(self):
        return (FrozenDict, (dict(self),))

    def __hash__(self):  # immutable, so hashable
        return hash(tuple(sorted((k, repr(v)) for k, v in self.items())))


@dataclass(frozen=True)
class Instrument:
    observation: Observation = field(default_factory=Observation)
    source: Source = field(default_factory=Source)
    detector: Detector = field(default_factory=Detector)
    sample: SampleGeometry = field(default_factory=SampleGeometry)
    name: str = "instrument"
    description: str = ""
    path: Path | None = None
    #: How a signal becomes q: [calibration] (docs/conventions.md section 5; roadgonio.instrument.calibration).
    calibration: Calibration = field(default_factory=Calibration)
    #: The cells it measures and how it fills the rest of its reported table: [cells]
    #: (roadgonio.instrument.coverage; default: it measures every cell asked).
    cells: MeasuredCells = field(default_factory=MeasuredCells)
    #: Extra sections not interpreted here (kept for backends and provenance).
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        for attr, cls in (("observation", Observation), ("source", Source), ("detector", Detector),
                          ("sample", SampleGeometry)):
            if not isinstance(getattr(self, attr), cls):
                raise InputError(f"expected a {cls.__name__}, got {type(getattr(self, attr)).__name__}", field=attr)
        for key in ("name", "description"):
            if not isinstance(getattr(self, key), str):
                raise InputError(f"expected text, got {type(getattr(self, key)).__name__} {getattr(self, key)!r}",
                                 field=f"instrument.{key}")
        if self.path is not None:
            object.__setattr__(self, "path", Path(self.path))
        if not isinstance(self.calibration, Calibration):
            raise InputError(f"expected a Calibration, got {type(self.calibration).__name__}", field="calibration")
        if not isinstance(self.cells, MeasuredCells):
            raise InputError(f"expected a MeasuredCells, got {type(self.cells).__name__}", field="cells")
        if not isinstance(self.extra, Mapping):
            raise InputError(f"expected a mapping of extra sections, got {self.extra!r}", field="extra")
        object.__setattr__(self, "extra", FrozenDict(self.extra))
        if self.calibration.mode == "absolute" and self.sample.mesh is not None:
            # audit 22: eta = <E>/E_0 is computed on the plane z = 0, so a mesh's tilt or reversed
            # faces never entered: a Lambertian sample gave the flat plane's k_A on every mesh
            raise InputError("the absolute calibration (eta = <E>/E_0 over the footprint) is computed for the flat "
                             "sample plane and not for a mesh sample; expected mode = \"lambert\" or \"reference\" "
                             "with [sample] mesh", path=self.path, field="calibration.mode")
        clash = sorted(set(self.extra) & set(_SECTIONS + ("calibration", "cells")))
        if clash:
            raise InputError(f"section(s) {', '.join(clash)} are fields of the instrument, not extra sections",
                             field="extra")
        try:
            check_extra_sections(self.extra)
        except InputError as err:
            raise InputError(err.reason, path=self.path, field=err.field) from None

    # -- nominal geometry --------------------------------------------------------------------
    def w_o(self) -> np.ndarray:
        return self.observation.w_o

    def w_i(self, tan_eps, beta_deg) -> np.ndarray:
        """Unit direction towards the source at (tan eps, beta): shape (3,), or (..., 3) for arrays."""
        eps = np.arctan(np.asarray(tan_eps, dtype=np.float64)) if np.ndim(tan_eps) else math.atan(tan_eps)
        return w_source(eps, beta_deg, self.observation.delta_deg)

    def is_ideal(self) -> bool:
        """True if every aperture is zero (point source, single-ray detector)."""
        return self.source.is_point and self.detector.is_single_ray

    def scene_parts(self) -> list[tuple[str, str, str]]:
        """The parts beyond the sample and the apertures, as (section, what it is, what of it
        matters): a ``[scene]`` (its extra geometry) and a ``[housing]`` (its walls' shade and stray
        light); an empty [scene] is none. One rule for the backends that cannot model them
        (:func:`roadgonio.engines.registry.unmodelled_parts`), ``render``'s integrator and what the
        second aperture's prediction leaves out."""
        extra = self.extra if hasattr(self.extra, "get") else {}
        out = []
        scene = extra.get("scene")
        if scene:
            out.append(("scene", "a Mitsuba XML scene" if hasattr(scene, "get") and "xml" in scene
                        else "a [scene] section", "its extra geometry"))
        if extra.get("housing") is not None:
            out.append(("housing", "a [housing]", "its walls' shade and stray light"))
        return out

    def file_digests(self) -> dict[str, str]:
        """sha256 of the content of every file the instrument reads numbers from (the source's and
        the detector's tables, the sample mesh), by key: what a fingerprint of "what determines the
        numbers" adds to :meth:`to_dict`, which names the files only."""
        out = {f"source.{k}": v for k, v in self.source._digests.items()}
        out.update({f"detector.{k}": v for k, v in self.detector._digests.items()})
        if self.sample.mesh is not None:
            from roadgonio.instrument.profiles import file_digest
            out["sample.mesh"] = file_digest(self.sample.mesh)
        return out

    def with_changes(self, **sections: Mapping[str, Any]) -> "Instrument":
        """A copy with some keys changed, e.g. ``with_changes(source={"radius_m": 0})``."""
        d = self.to_dict()
        for sec, changes in sections.items():
            d.setdefault(sec, {}).update(changes)
        return Instrument.from_dict(d, path=self.path)

    def to_dict(self) -> dict[str, Any]:
        """The instrument in the form of its file (TOML/JSON): defaults left out, focus at infinity
        spelled ``"inf"`` (JSON has no infinity); ``from_dict(to_dict())`` gives it back."""
        det = asdict(self.detector)
        if det["focus_m"] is None:
            del det["focus_m"]
        elif math.isinf(det["focus_m"]):
            det["focus_m"] = "inf"
        if det["field_edge_sensitivity"] == 1.0:
            del det["field_edge_sensitivity"]
        if det["field_sensitivity"] is None:
            del det["field_sensitivity"]
        else:
            det["field_sensitivity"] = str(det["field_sensitivity"])
        src = asdict(self.source)
        for k in ("beam_half_angle_deg", "beam_sigma_deg", "beam_cos_power", "beam_intensity_file",
                  "aperture_radiance_file"):
            if src[k] is None:
                del src[k]
            elif isinstance(src[k], Path):
                src[k] = str(src[k])
        if src["aperture_edge_radiance"] == 1.0:
            del src["aperture_edge_radiance"]
        for k in ("distance_m", "height_m"):
            if src[k] is None:
                del src[k]
        if src["path"] == "arc":
            del src["path"]
        smp = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self.sample).items() if v is not None}
        d = {"instrument": {"name": self.name, "description": self.description},
             "observation": asdict(self.observation), "source": src, "detector": det, "sample": smp}
        if not self.calibration.is_default:   # the default is left out, so Lambert fingerprints do not change
            d["calibration"] = self.calibration.to_dict()
        if not self.cells.is_default:       # left out by default, like the calibration
            d["cells"] = self.cells.to_dict()
        d.update({k: dict(v) if isinstance(v, Mapping) else v for k, v in self.extra.items()})
        return d

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, path: str | Path | None = None) -> "Instrument":
        """An instrument from the dict of an instrument file (unknown keys are errors; errors name
        ``path``, the field and what was expected)."""
        path = Path(path) if path is not None else None
        try:
            return cls._from_dict(d, path)
        except InputError as err:
            if err.path is not None:
                raise
            raise InputError(err.reason, path=path, line=err.line, field=err.field) from None

    @classmethod
    def _from_dict(cls, d: Mapping[str, Any], path: Path | None) -> "Instrument":
        for sec in _SECTIONS:
            if sec in d and not isinstance(d[sec], Mapping):
                raise InputError(f"expected a table [{sec}]", field=sec)
        ob = d.get("observation", {})
        _check_keys(ob, {"alpha_deg", "delta_deg"}, "observation", None)
        observation = Observation(**ob)
        if "source" not in d:
            raise _missing_section("source", d)
        s = dict(d["source"])
        _check_keys(s, {"distance_m", "radius_m", "beam_half_angle_deg", "path", "height_m", *BEAM_KEYS,
                        *APERTURE_KEYS}, "source", None)
        if "distance_m" not in s and s.get("path", "arc") == "arc":
            if "height_m" in s:
                # user audit, session 43: a corridor file without its path was told to add a distance
                raise InputError('missing (required); height_m belongs to path = "fixed_height": add path = '
                                 '"fixed_height" for a source on a rail at that height, or give distance_m for an arc',
                                 field="source.distance_m")
            raise InputError("missing (required)", field="source.distance_m")
        for k in ("beam_intensity_file", "aperture_radiance_file"):
            _resolve_file(s, k, "source", path)
        source = Source(**s)
        if "detector" not in d:
            raise _missing_section("detector", d)
        t = dict(d["detector"])
        _check_keys(t, {"distance_m", "pupil_radius_m", "field_half_angle_deg", "focus_m", "field_edge_sensitivity",
                        "field_sensitivity"}, "detector", None)
        if "distance_m" not in t:
            raise InputError("missing (required)", field="detector.distance_m")
        _resolve_file(t, "field_sensitivity", "detector", path)
        detector = Detector(**t)
        sm = dict(d.get("sample", {}))
        _check_keys(sm, {"size_x_m", "size_y_m", "mesh"}, "sample", None)
        if "mesh" in sm:
            if not isinstance(sm["mesh"], (str, Path)) or not str(sm["mesh"]):
                raise InputError(f"expected a file name, got {sm['mesh']!r}", field="sample.mesh")
            mesh = Path(sm["mesh"])
            if not mesh.is_absolute() and path is not None:
                # absolute, so that to_dict/from_dict (with_changes, best.toml) never joins it twice
                mesh = (path.parent / mesh).absolute()
            sm["mesh"] = mesh
        sample = SampleGeometry(**sm)
        meta = d.get("instrument", {})
        _check_keys(meta, {"name", "description"}, "instrument", None)
        for key in ("name", "description"):
            if key in meta and not isinstance(meta[key], str):
                raise InputError(f"expected text (a quoted string), got {type(meta[key]).__name__} {meta[key]!r}",
                                 field=f"instrument.{key}")
        name = meta.get("name", path.stem if path is not None else "instrument")
        calibration = Calibration.from_dict(d.get("calibration", {}), path=path)
        cells = MeasuredCells.from_dict(d.get("cells", {}))
        extra = {k: v for k, v in d.items() if k not in _SECTIONS and k not in ("calibration", "cells")}
        unknown = sorted(set(extra) - set(EXTRA_SECTIONS))
        if unknown:
            raise InputError(f"unknown section(s) [{'], ['.join(unknown)}]; expected some of "
                             f"[{'], ['.join(_SECTIONS + EXTRA_SECTIONS + ('calibration', 'cells'))}]", field=unknown[0])
        for sec in EXTRA_SECTIONS:
            if sec in extra and not isinstance(extra[sec], Mapping):
                raise InputError(f"expected a table [{sec}]", field=sec)
        return cls(observation=observation, source=source, detector=detector, sample=sample, name=name,
                   description=meta.get("description", ""), path=path, calibration=calibration, cells=cells,
                   extra=extra)

    def to_toml(self, header: str = "") -> str:
        """The instrument file's text (:meth:`to_dict` written as TOML by :func:`toml_text`, with
        ``header`` as comment lines): ``Instrument.load`` of it gives this instrument back."""
        return toml_text(self.to_dict(), header)

    @classmethod
    def load(cls, path: str | Path) -> "Instrument":
        """Load a TOML instrument file; errors name the file, the line or field, and what was expected."""
        path = Path(path)
        return cls.from_dict(read_toml(path, "instrument file"), path=path)


# ----------------------------------------------------------------------------------------------
# Writing TOML (the reader is Python's tomllib): what the writer writes, the reader reads back
# ----------------------------------------------------------------------------------------------

_BARE_KEY = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-")
_ESCAPES = {"\\": "\\\\", '"': '\\"', "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def toml_string(s: str) -> str:
    """A TOML basic string: backslash, quote and control characters (U+0000-U+001F, U+007F)
    escaped, everything else as it is (TOML files are UTF-8). A lone surrogate has no TOML form."""
    out = []
    for ch in s:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        elif 0xD800 <= ord(ch) <= 0xDFFF:
            raise InputError(f"cannot write {s!r} to TOML: it holds a lone surrogate (U+{ord(ch):04X}), which no "
                             "TOML (UTF-8) text can hold", field="text")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_key(k) -> str:
    k = str(k)
    return k if k and set(k) <= _BARE_KEY else toml_string(k)


def toml_value(v) -> str:
    """A scalar, a list of scalars or of inline tables as TOML (an infinite float as the text "inf", as instrument
    files spell a focus at infinity; NaN has no TOML form in roadgonio's files)."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            raise InputError("cannot write NaN to an instrument file", field="value")
        if math.isinf(v):
            return '"inf"' if v > 0 else '"-inf"'
        return repr(v)
    if isinstance(v, str):
        return toml_string(v)
    if isinstance(v, Path):
        return toml_string(str(v))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, Mapping):          # an inline table inside a list (a [housing] baffle)
        return "{" + ", ".join(f"{_toml_key(k)} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def toml_text(d: Mapping[str, Any], header: str = "") -> str:
    """A TOML document of tables of scalars (nested tables as ``[a.b]``), ``header`` as comment lines."""
    lines = [("# " + ln).rstrip() for ln in header.splitlines()] if header else []

    def table(name: str, t: Mapping[str, Any]) -> None:
        scalars = {k: v for k, v in t.items() if not isinstance(v, Mapping)}
        subs = {k: v for k, v in t.items() if isinstance(v, Mapping)}
        if lines:
            lines.append("")
        lines.append(f"[{name}]")
        for k, v in scalars.items():
            lines.append(f"{_toml_key(k)} = {toml_value(v)}")
        for k, v in subs.items():
            table(f"{name}.{_toml_key(k)}", v)

    for name, t in d.items():
        if isinstance(t, Mapping):
            table(_toml_key(name), t)
    return "\n".join(lines) + "\n"


def bundled_instruments() -> list[str]:
    """Names of the instrument presets shipped in scenes/ (installed as roadgonio.scenes)."""
    from importlib import resources
    return sorted(p.name[:-5] for p in resources.files("roadgonio.scenes").iterdir() if p.name.endswith(".toml"))


def load_instrument(spec: str | Path) -> Instrument:
    """An instrument from a TOML file path, or a bundled preset by name (``lab``, ``portable``)."""
    p = Path(spec)
    if p.exists():
        return Instrument.load(p)
    names = bundled_instruments()
    if str(spec) in names:
        from importlib import resources
        res = resources.files("roadgonio.scenes").joinpath(f"{spec}.toml")
        return Instrument.load(Path(str(res)))
    raise InputError(f"no such instrument file, and not a bundled preset ({', '.join(names)})", path=p)


def _missing_section(section: str, d: Mapping[str, Any]) -> InputError:
    """The error for a required table the file lacks, naming a section of a similar name it has
    instead (audit 28: '[detecter]' gave 'missing table [detector]' without pointing at the typo)."""
    import difflib
    unknown = [k for k in d if k not in _SECTIONS and k not in EXTRA_SECTIONS]
    near = difflib.get_close_matches(section, unknown, n=1, cutoff=0.6)
    hint = f" (the file has a table [{near[0]}]: a misspelling of [{section}]?)" if near else ""
    return InputError(f"missing table [{section}]{hint}", field=section)
