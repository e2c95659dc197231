"""Instrument description (DESIGN.md section 4): frozen, validated dataclasses built from TOML or a
plain dict, units in the names.

.. code-block:: toml

    [instrument]                 # optional
    name = "portable"
    description = "..."
    [observation]
    alpha_deg = 1.0              # delta_deg = 0.0
    [source]
    distance_m = 3.0
    radius_m = 0.02              # 0 = point source
    # beam_half_angle_deg = 5.0  # optional: emission limited to a cone about the source axis
    [detector]
    distance_m = 5.0
    pupil_radius_m = 0.01        # 0 = pinhole
    field_half_angle_deg = 0.15
    focus_m = 5.0                # default: distance_m; "inf" = angular field
    # field_edge_sensitivity = 0.8  # k_D at the field-stop edge relative to the centre (default 1)
    [sample]
    size_x_m = 6.0               # along the observation azimuth
    size_y_m = 2.0               # or mesh = "file.ply" (relative to the TOML file)

Whatever is not declared is not modelled: a zero radius is a point, no beam limit is no limit.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from roadgonio.errors import InputError
from roadgonio.geometry import w_detector, w_source
from roadgonio.instrument.calibration import Calibration


def _num(d: Mapping[str, Any], key: str, section: str, path, *, default=None, required=False,
         lo=None, hi=None, lo_open=False, hi_open=False, allow_inf=False) -> float | None:
    field_name = f"{section}.{key}"
    if key not in d:
        if required:
            raise InputError("missing (required)", path=path, field=field_name)
        return default
    v = d[key]
    if allow_inf and isinstance(v, str) and v.strip().lower() in ("inf", "infinity"):
        return math.inf
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        extra = ' or "inf"' if allow_inf else ""
        raise InputError(f"expected a number{extra}, got {v!r}", path=path, field=field_name)
    v = float(v)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise InputError(f"expected a finite number, got {v}", path=path, field=field_name)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise InputError(f"expected a value {'>' if lo_open else '>='} {lo:g}, got {v:g}", path=path, field=field_name)
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise InputError(f"expected a value {'<' if hi_open else '<='} {hi:g}, got {v:g}", path=path, field=field_name)
    return v


def _check_keys(d: Mapping[str, Any], allowed: set[str], section: str, path) -> None:
    extra = sorted(set(d) - allowed)
    if extra:
        raise InputError(f"unknown key(s) {', '.join(extra)}; expected some of {', '.join(sorted(allowed))}",
                         path=path, field=section)


@dataclass(frozen=True)
class Observation:
    alpha_deg: float = 1.0
    delta_deg: float = 0.0

    @property
    def w_o(self) -> np.ndarray:
        return w_detector(self.alpha_deg, self.delta_deg)


@dataclass(frozen=True)
class Source:
    """Disc exit aperture of radius ``radius_m`` at ``distance_m`` from the sample centre, facing
    it, uniform radiance (Lambertian area emitter); optional beam cone."""

    distance_m: float = 3.0
    radius_m: float = 0.0
    beam_half_angle_deg: float | None = None

    @property
    def is_point(self) -> bool:
        return self.radius_m == 0.0


@dataclass(frozen=True)
class Detector:
    """Luminance meter: entrance pupil disc (``pupil_radius_m``) at ``distance_m``, circular field
    stop of half-angle ``field_half_angle_deg`` conjugate to the plane at ``focus_m``.

    Sensitivity over the field (k_D of paper eq. 3): ``k_D(rho) = 1 - (1 - e) rho^2`` with rho the
    distance from the field centre as a fraction of the field radius and ``e`` =
    ``field_edge_sensitivity`` (k_D at the field-stop edge relative to the centre; 1 = uniform, the
    default).
    """

    distance_m: float = 5.0
    pupil_radius_m: float = 0.0
    field_half_angle_deg: float = 0.0
    focus_m: float | None = None  # None -> distance_m; math.inf -> angular field
    field_edge_sensitivity: float = 1.0

    @property
    def focus(self) -> float:
        return self.distance_m if self.focus_m is None else self.focus_m

    @property
    def is_pinhole(self) -> bool:
        return self.pupil_radius_m == 0.0

    @property
    def is_single_ray(self) -> bool:
        return self.pupil_radius_m == 0.0 and self.field_half_angle_deg == 0.0


@dataclass(frozen=True)
class Sample:
    """A flat rectangle ``size_x_m`` x ``size_y_m`` centred on the origin (x along the observation
    azimuth), or a trimesh-readable mesh file."""

    size_x_m: float | None = 6.0
    size_y_m: float | None = 2.0
    mesh: Path | None = None


@dataclass(frozen=True)
class Instrument:
    observation: Observation = field(default_factory=Observation)
    source: Source = field(default_factory=Source)
    detector: Detector = field(default_factory=Detector)
    sample: Sample = field(default_factory=Sample)
    name: str = "instrument"
    description: str = ""
    path: Path | None = None
    #: How a signal becomes q: [calibration] (DESIGN.md section 5; roadgonio.instrument.calibration).
    calibration: Calibration = field(default_factory=Calibration)
    #: Extra sections not interpreted here (kept for backends and provenance).
    extra: Mapping[str, Any] = field(default_factory=dict)

    # -- nominal geometry --------------------------------------------------------------------
    def w_o(self) -> np.ndarray:
        return self.observation.w_o

    def w_i(self, tan_eps: float, beta_deg: float) -> np.ndarray:
        return w_source(math.atan(tan_eps), beta_deg, self.observation.delta_deg)

    def source_centre(self, tan_eps: float, beta_deg: float) -> np.ndarray:
        return self.source.distance_m * self.w_i(tan_eps, beta_deg)

    def detector_centre(self) -> np.ndarray:
        return self.detector.distance_m * self.w_o()

    def is_ideal(self) -> bool:
        """True if every aperture is zero (point source, single-ray detector)."""
        return self.source.is_point and self.detector.is_single_ray

    def with_changes(self, **sections: Mapping[str, Any]) -> "Instrument":
        """A copy with some keys changed, e.g. ``with_changes(source={"radius_m": 0})``."""
        d = self.to_dict()
        for sec, changes in sections.items():
            d.setdefault(sec, {}).update(changes)
        return Instrument.from_dict(d, path=self.path)

    def to_dict(self) -> dict[str, Any]:
        det = asdict(self.detector)
        if det["focus_m"] is not None and math.isinf(det["focus_m"]):
            det["focus_m"] = "inf"
        if det["focus_m"] is None:
            del det["focus_m"]
        if det["field_edge_sensitivity"] == 1.0:
            del det["field_edge_sensitivity"]
        src = asdict(self.source)
        if src["beam_half_angle_deg"] is None:
            del src["beam_half_angle_deg"]
        smp = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self.sample).items() if v is not None}
        d = {"instrument": {"name": self.name, "description": self.description},
             "observation": asdict(self.observation), "source": src, "detector": det, "sample": smp}
        if not self.calibration.is_default:   # the default is left out, so Lambert fingerprints do not change
            d["calibration"] = self.calibration.to_dict()
        d.update({k: dict(v) if isinstance(v, Mapping) else v for k, v in self.extra.items()})
        return d

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, path: str | Path | None = None) -> "Instrument":
        path = Path(path) if path is not None else None
        for sec in ("observation", "source", "detector", "sample", "instrument"):
            if sec in d and not isinstance(d[sec], Mapping):
                raise InputError(f"expected a table [{sec}]", path=path, field=sec)
        ob = d.get("observation", {})
        _check_keys(ob, {"alpha_deg", "delta_deg"}, "observation", path)
        observation = Observation(
            alpha_deg=_num(ob, "alpha_deg", "observation", path, default=1.0, lo=0.0, hi=90.0, lo_open=True, hi_open=True),
            delta_deg=_num(ob, "delta_deg", "observation", path, default=0.0, lo=-360.0, hi=360.0))
        if "source" not in d:
            raise InputError("missing table [source]", path=path, field="source")
        s = d["source"]
        _check_keys(s, {"distance_m", "radius_m", "beam_half_angle_deg"}, "source", path)
        source = Source(
            distance_m=_num(s, "distance_m", "source", path, required=True, lo=0.0, lo_open=True),
            radius_m=_num(s, "radius_m", "source", path, default=0.0, lo=0.0),
            beam_half_angle_deg=_num(s, "beam_half_angle_deg", "source", path, default=None, lo=0.0,
                                     hi=90.0, lo_open=True))
        if source.radius_m >= source.distance_m:
            raise InputError(f"the source radius ({source.radius_m:g} m) must be smaller than its distance "
                             f"({source.distance_m:g} m)", path=path, field="source.radius_m")
        if "detector" not in d:
            raise InputError("missing table [detector]", path=path, field="detector")
        t = d["detector"]
        _check_keys(t, {"distance_m", "pupil_radius_m", "field_half_angle_deg", "focus_m", "field_edge_sensitivity"},
                    "detector", path)
        detector = Detector(
            distance_m=_num(t, "distance_m", "detector", path, required=True, lo=0.0, lo_open=True),
            pupil_radius_m=_num(t, "pupil_radius_m", "detector", path, default=0.0, lo=0.0),
            field_half_angle_deg=_num(t, "field_half_angle_deg", "detector", path, default=0.0, lo=0.0,
                                      hi=45.0, hi_open=True),
            focus_m=_num(t, "focus_m", "detector", path, default=None, lo=0.0, lo_open=True, allow_inf=True),
            field_edge_sensitivity=_num(t, "field_edge_sensitivity", "detector", path, default=1.0, lo=0.0, hi=2.0))
        if detector.pupil_radius_m >= detector.distance_m:
            raise InputError(f"the pupil radius ({detector.pupil_radius_m:g} m) must be smaller than the "
                             f"detector distance ({detector.distance_m:g} m)", path=path, field="detector.pupil_radius_m")
        sm = d.get("sample", {})
        _check_keys(sm, {"size_x_m", "size_y_m", "mesh"}, "sample", path)
        if "mesh" in sm:
            if not isinstance(sm["mesh"], str) or not sm["mesh"]:
                raise InputError(f"expected a file name, got {sm['mesh']!r}", path=path, field="sample.mesh")
            mesh = Path(sm["mesh"])
            if not mesh.is_absolute() and path is not None:
                mesh = path.parent / mesh
            if not mesh.exists():
                raise InputError(f"mesh file {str(mesh)!r} does not exist", path=path, field="sample.mesh")
            sample = Sample(size_x_m=None, size_y_m=None, mesh=mesh)
        else:
            sample = Sample(size_x_m=_num(sm, "size_x_m", "sample", path, default=6.0, lo=0.0, lo_open=True),
                            size_y_m=_num(sm, "size_y_m", "sample", path, default=2.0, lo=0.0, lo_open=True))
        meta = d.get("instrument", {})
        name = str(meta.get("name", path.stem if path is not None else "instrument"))
        calibration = Calibration.from_dict(d.get("calibration", {}), path=path)
        extra = {k: v for k, v in d.items()
                 if k not in ("observation", "source", "detector", "sample", "instrument", "calibration")}
        return cls(observation=observation, source=source, detector=detector, sample=sample, name=name,
                   description=str(meta.get("description", "")), path=path, calibration=calibration, extra=extra)

    @classmethod
    def load(cls, path: str | Path) -> "Instrument":
        """Load a TOML instrument file; errors name the file, the line or field, and what was expected."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise InputError("no such instrument file", path=path) from None
        except (OSError, UnicodeDecodeError) as err:
            raise InputError(f"cannot read the instrument file ({err})", path=path) from None
        try:
            d = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            line = getattr(err, "lineno", None)
            if line is None:  # Python 3.11: only in the message, "(at line 5, column 14)"
                import re
                m = re.search(r"at line (\d+)", str(err))
                line = int(m.group(1)) if m else None
            raise InputError(f"not valid TOML: {getattr(err, 'msg', str(err))}", path=path, line=line) from None
        return cls.from_dict(d, path=path)


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
