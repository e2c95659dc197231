"""The road and its lighting installation: a frozen, validated :class:`Layout` from a TOML file.

Road frame: x along the road in the drivers' direction, y across it (y = 0 at the edge of the
carriageway on the side of the first luminaire row, y = W at the other edge), z up; the road is
the plane z = 0. Lanes are numbered from y = 0. Row 1 stands at the y = 0 edge; with
``arrangement = "opposite"`` or ``"staggered"`` a second row stands at the y = W edge (staggered:
shifted by half a spacing). Luminaires of row 1 are at x = m S (m integer); the calculation field
runs from x = 0 to x = S (EN 13201-3:2015 clause 7.1.3).

``overhang_m`` is the horizontal distance from the edge of the carriageway to the luminaire,
positive over the road. ``tilt_deg`` turns the luminaire about its C0-C180 axis so that its
downward axis swings towards the road (the usual "upcast" tilt). The luminaire's C = 0 direction
is along +x for row 1 (C = 90 deg towards the road); row 2 is turned by 180 deg.

File keys (every section and key optional; an unknown section or key is an error)::

    [road]
    lanes = 2                    # number of driving lanes (all of one width)
    lane_width_m = 3.5
    [installation]
    arrangement = "single-sided" # "single-sided" | "opposite" | "staggered"
    mounting_height_m = 10.0
    spacing_m = 30.0
    overhang_m = 1.0
    tilt_deg = 0.0
    maintenance_factor = 0.8
    [observer]
    distance_m = 60.0            # before the start of the field (EN 13201-3)
    eye_height_m = 1.5
    [calculation]
    interpolation = "quadratic"  # r-table interpolation: "quadratic" (EN 13201-3 5.5) | "linear"
    luminaires_before_h = 5.0    # luminaires counted towards the observer, in mounting heights
    luminaires_after_h = 12.0    # ... and away from the observer
    edge_strip_m = 0             # width of the R_EI strips; 0 = min(5 m, half the carriageway)
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

from roadgonio.errors import InputError
from roadgonio.fileio import read_toml

ARRANGEMENTS = ("single-sided", "opposite", "staggered")
INTERPOLATIONS = ("quadratic", "linear")
DEFAULT_LAYOUT = "default_layout.toml"

#: section -> key -> (attribute, type)
_SCHEMA: dict[str, dict[str, tuple[str, type]]] = {
    "road": {"lanes": ("lanes", int), "lane_width_m": ("lane_width_m", float)},
    "installation": {"arrangement": ("arrangement", str), "mounting_height_m": ("mounting_height_m", float),
                     "spacing_m": ("spacing_m", float), "overhang_m": ("overhang_m", float),
                     "tilt_deg": ("tilt_deg", float), "maintenance_factor": ("maintenance_factor", float)},
    "observer": {"distance_m": ("observer_distance_m", float), "eye_height_m": ("eye_height_m", float)},
    "calculation": {"interpolation": ("interpolation", str), "luminaires_before_h": ("before_h", float),
                    "luminaires_after_h": ("after_h", float), "edge_strip_m": ("edge_strip_m", float)},
}


@dataclass(frozen=True)
class Layout:
    """A straight road with one or two rows of identical luminaires (module docstring)."""

    lanes: int = 2
    lane_width_m: float = 3.5
    arrangement: str = "single-sided"
    mounting_height_m: float = 10.0
    spacing_m: float = 30.0
    overhang_m: float = 1.0
    tilt_deg: float = 0.0
    maintenance_factor: float = 0.8
    observer_distance_m: float = 60.0
    eye_height_m: float = 1.5
    interpolation: str = "quadratic"
    before_h: float = 5.0
    after_h: float = 12.0
    edge_strip_m: float = 0.0
    name: str = "layout"
    source: str = ""

    def __post_init__(self):
        where = self.source or None

        def bad(key: str, expected: str, value: Any):
            fld = next((f"[{s}] {k}" for s, keys in _SCHEMA.items() for k, (a, _) in keys.items() if a == key), key)
            raise InputError(f"expected {expected}, got {value!r}", path=where, field=fld)

        if not (isinstance(self.lanes, int) and 1 <= self.lanes <= 12):
            bad("lanes", "a whole number of lanes 1 ... 12", self.lanes)
        for key, lo, hi in (("lane_width_m", 1.0, 10.0), ("mounting_height_m", 2.0, 60.0), ("spacing_m", 1.0, 300.0),
                            ("observer_distance_m", 10.0, 500.0), ("eye_height_m", 0.3, 5.0),
                            ("before_h", 0.0, 50.0), ("after_h", 0.0, 50.0)):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                bad(key, f"a number in [{lo:g}, {hi:g}]", v)
        if not (math.isfinite(self.overhang_m) and abs(self.overhang_m) <= self.width_m + 20):
            bad("overhang_m", f"a distance within +-{self.width_m + 20:g} m of the edge", self.overhang_m)
        if not (math.isfinite(self.tilt_deg) and -30 <= self.tilt_deg <= 60):
            bad("tilt_deg", "a tilt in [-30, 60] deg", self.tilt_deg)
        if not (math.isfinite(self.maintenance_factor) and 0 < self.maintenance_factor <= 1):
            bad("maintenance_factor", "a factor in (0, 1]", self.maintenance_factor)
        if not (math.isfinite(self.edge_strip_m) and 0 <= self.edge_strip_m <= 20):
            bad("edge_strip_m", "a width in [0, 20] m (0 = automatic)", self.edge_strip_m)
        if self.arrangement not in ARRANGEMENTS:
            bad("arrangement", " | ".join(ARRANGEMENTS), self.arrangement)
        if self.interpolation not in INTERPOLATIONS:
            bad("interpolation", " | ".join(INTERPOLATIONS), self.interpolation)
        if self.mounting_height_m <= self.eye_height_m + 0.5:
            bad("mounting_height_m", f"a mounting height above the eye height + 0.5 m ({self.eye_height_m + 0.5:g} m)",
                self.mounting_height_m)

    # -- derived ---------------------------------------------------------------------------------
    @property
    def width_m(self) -> float:
        return self.lanes * self.lane_width_m

    @property
    def n_longitudinal(self) -> int:
        """Points along the field (EN 13201-3:2015 7.1.4): N = 10 for S <= 30 m, otherwise the
        smallest integer giving a spacing D = S / N <= 3 m."""
        s = self.spacing_m
        return 10 if s <= 30.0 else int(math.ceil(s / 3.0 - 1e-9))

    @property
    def strip_m(self) -> float:
        """Width of the edge strips for R_EI: 5 m or half the carriageway, whichever is less
        (unless set)."""
        return self.edge_strip_m or min(5.0, self.width_m / 2.0)

    def rows(self) -> list[tuple[float, float, float]]:
        """(y of the row, x offset of its luminaires, rotation of the luminaires about z in deg)."""
        r = [(self.overhang_m, 0.0, 0.0)]
        if self.arrangement == "opposite":
            r.append((self.width_m - self.overhang_m, 0.0, 180.0))
        elif self.arrangement == "staggered":
            r.append((self.width_m - self.overhang_m, 0.5 * self.spacing_m, 180.0))
        return r

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("source")
        return d

    def describe(self) -> str:
        return (f"{self.arrangement}, {self.lanes} x {self.lane_width_m:g} m lanes, H = {self.mounting_height_m:g} m, "
                f"S = {self.spacing_m:g} m, overhang {self.overhang_m:g} m, tilt {self.tilt_deg:g} deg, "
                f"MF {self.maintenance_factor:g}")


def layout_from_dict(data: Mapping[str, Any], *, path: str | Path | None = None, name: str = "layout") -> Layout:
    """Build a :class:`Layout` from the TOML structure (unknown sections/keys are errors)."""
    kw: dict[str, Any] = {}
    for sec, body in data.items():
        if sec not in _SCHEMA:
            raise InputError(f"unknown section [{sec}]; expected one of {', '.join('[' + s + ']' for s in _SCHEMA)}",
                             path=path, field=f"[{sec}]")
        if not isinstance(body, Mapping):
            raise InputError(f"[{sec}] must be a table of keys", path=path, field=sec)
        for key, value in body.items():
            if key not in _SCHEMA[sec]:
                raise InputError(f"unknown key; [{sec}] takes {', '.join(_SCHEMA[sec])}", path=path,
                                 field=f"[{sec}] {key}")
            attr, typ = _SCHEMA[sec][key]
            if typ is float:
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise InputError(f"expected a number, got {value!r}", path=path, field=f"[{sec}] {key}")
                value = float(value)
            elif typ is int:
                if isinstance(value, bool) or not isinstance(value, int):
                    raise InputError(f"expected a whole number, got {value!r}", path=path, field=f"[{sec}] {key}")
            elif not isinstance(value, str):
                raise InputError(f"expected a string, got {value!r}", path=path, field=f"[{sec}] {key}")
            kw[attr] = value
    return Layout(**kw, name=name, source="" if path is None else str(path))


def read_layout(path: str | Path) -> Layout:
    path = Path(path)
    data = read_toml(path, "layout file", missing="no such layout file (expected a TOML file)")
    return layout_from_dict(data, path=path, name=path.stem)


def default_layout_path() -> Path:
    return Path(str(resources.files("roadgonio.data").joinpath("road", DEFAULT_LAYOUT)))


def load_layout(spec: str | Path | None = None) -> Layout:
    """The bundled default layout (``None``) or a layout TOML file."""
    return read_layout(default_layout_path() if spec is None else spec)
