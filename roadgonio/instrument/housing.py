"""The instrument's housing: a box standing on the sample plane around the source and detector
positions, with Lambertian inner walls and optional baffles (the ``[housing]`` table of an
instrument file; docs/conventions.md section 4). Float64 numpy; nothing here imports mitsuba.

.. code-block:: toml

    [housing]
    wall_reflectance = 0.05          # Lambertian reflectance of the inner walls and the lid, 0 ... 1
    # baffle_reflectance = 0.05      # of both faces of every baffle (default: wall_reflectance)
    # x_m = [-1.1, 1.1]              # inner extent along x (default: the parts + margin_m)
    # y_m = [-0.1, 1.1]              # inner extent along y (default: the parts + margin_m)
    # height_m = 1.1                 # inner height of the lid above the sample plane (default: the parts + margin_m)
    # margin_m = 0.05                # clearance of the default box around the parts
    # lid = true                     # false: an open top
    baffles = [{x_m = 0.6, height_m = 0.01}]   # plates across the box (all of y) at x, from the sample plane up;
                                               # each at its own x, strictly between the walls x_min < x < x_max

What the box must hold (the "parts"): the source disc of every cell of the standard grid
(docs/conventions.md section 2; the instrument measures the whole table), the detector's entrance
pupil and the detector footprint. Every detected ray must reach the footprint without meeting a
baffle (an error, never a silent number).

The floor of the box is the road the instrument stands on: the sample ([sample], the surface
measured, and the one a Lambert calibration replaces with a perfect diffuser) and, where the box
is larger than a rectangular sample, the same road around it (panels ``housing_floor_*`` with the
sample's BRDF, which a calibration leaves as it is). A mesh sample has to cover the floor itself.

The box is made of thin panels (:class:`Panel`), each a rectangle with its reflecting face
turned into the box: the walls at x = x_min, x_max, y = y_min, y_max (ids ``housing_wall_x_min``
...), the lid at z = height (``housing_lid``), the baffles (``housing_baffle_1`` ..., both
faces reflect) and the road floor around the sample. The box, its panels and the geometry checks
are in :mod:`roadgonio.instrument.enclosure` (they need the optics; this module, the table alone,
is what instrument.config checks on construction); the Mitsuba backend builds the panels into its
scene (:mod:`roadgonio.engines.mitsuba.scene`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from roadgonio.errors import InputError
from roadgonio.geometry import MAX_LENGTH_M

#: What no uncertainty holds of an instrument with reflecting parts: the caveat `correct` (its note and
#: corrected_u.csv, which `road` repeats) and `uncertainty` state, each with its docs page.
REFLECTANCES_EXACT = ("the reflectances of the instrument's parts are taken as exact: their uncertainty is in no "
                      "component of this u")
#: Keys of the [housing] table.
HOUSING_KEYS = ("wall_reflectance", "baffle_reflectance", "x_m", "y_m", "height_m", "margin_m", "lid", "baffles")
#: Keys of one baffle.
BAFFLE_KEYS = ("x_m", "height_m")
#: Default clearance of the box around the parts (m).
DEFAULT_MARGIN_M = 0.05
#: Panels overlap their neighbours (and reach below the sample plane) by this much, so that no ray
#: slips through a seam in float32.
SEAM_M = 1e-4


def _num(v: Any, name: str) -> float:
    """A finite number; a length (a name ending in ``_m``) at most the instrument's limit in size
    (audit 28: margin_m = 1e6 failed later as detector rays meeting a floor, naming no field)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise InputError(f"expected a number, got {v!r}", field=name)
    v = float(v)
    if not math.isfinite(v):
        raise InputError(f"expected a finite number, got {v}", field=name)
    if name.endswith("_m") and abs(v) > MAX_LENGTH_M:
        raise InputError(f"expected at most {MAX_LENGTH_M:g} m (no instrument is larger), got {v:g}", field=name)
    return v


def _pair(v: Any, name: str) -> tuple[float, float]:
    if isinstance(v, (str, bytes)) or not hasattr(v, "__len__") or len(v) != 2:
        raise InputError(f"expected [lower, upper] in metres, got {v!r}", field=name)
    lo, hi = _num(v[0], name), _num(v[1], name)
    if not lo < hi:
        raise InputError(f"expected lower < upper, got [{lo:g}, {hi:g}]", field=name)
    return lo, hi


@dataclass(frozen=True)
class Baffle:
    """A vertical plate across the box (over its whole y extent) at ``x_m``, from the sample
    plane up to ``height_m`` (0 = no plate: a design may vary a baffle down to nothing)."""

    x_m: float
    height_m: float

    def __post_init__(self):
        object.__setattr__(self, "x_m", _num(self.x_m, "housing.baffles.x_m"))
        h = _num(self.height_m, "housing.baffles.height_m")
        if h < 0.0:
            raise InputError(f"expected a height >= 0, got {h:g}", field="housing.baffles.height_m")
        object.__setattr__(self, "height_m", h)


@dataclass(frozen=True)
class Panel:
    """A rectangle of the housing: centre, half-axes ``u`` and ``v`` (m) and the unit normal of
    its reflecting face (``u x v`` points along it: a right-handed frame); float64."""

    id: str
    centre: tuple[float, float, float]
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    normal: tuple[float, float, float]
    reflectance: float                  # Lambertian reflectance; unused for the road floor
    two_sided: bool = False
    label: str = ""
    road: bool = False                  # the road floor around the sample (the sample's BRDF)

    def to_world(self) -> np.ndarray:
        """4x4 matrix taking the unit square [-1, 1]^2 (z = 0, normal +z) onto the panel."""
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = self.u, self.v, self.normal, self.centre
        return m


@dataclass(frozen=True)
class Box:
    """The resolved inner extent of the housing (m)."""

    x: tuple[float, float]
    y: tuple[float, float]
    height: float


@dataclass(frozen=True)
class Housing:
    """The ``[housing]`` table (module docstring); validated on construction, errors name
    ``housing.KEY``."""

    wall_reflectance: float
    baffle_reflectance: float | None = None
    x_m: tuple[float, float] | None = None
    y_m: tuple[float, float] | None = None
    height_m: float | None = None
    margin_m: float = DEFAULT_MARGIN_M
    lid: bool = True
    baffles: tuple[Baffle, ...] = field(default_factory=tuple)

    def __post_init__(self):
        for name in ("wall_reflectance", "baffle_reflectance"):
            v = getattr(self, name)
            if v is None and name == "baffle_reflectance":
                continue
            v = _num(v, f"housing.{name}")
            if not 0.0 <= v <= 1.0:
                raise InputError(f"expected a reflectance in [0, 1], got {v:g}", field=f"housing.{name}")
            object.__setattr__(self, name, v)
        for name in ("x_m", "y_m"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _pair(getattr(self, name), f"housing.{name}"))
        if self.height_m is not None:
            h = _num(self.height_m, "housing.height_m")
            if h <= 0.0:
                raise InputError(f"expected a height > 0, got {h:g}", field="housing.height_m")
            object.__setattr__(self, "height_m", h)
        m = _num(self.margin_m, "housing.margin_m")
        if m < 0.0:
            raise InputError(f"expected a margin >= 0, got {m:g}", field="housing.margin_m")
        object.__setattr__(self, "margin_m", m)
        if not isinstance(self.lid, bool):
            raise InputError(f"expected true or false, got {self.lid!r}", field="housing.lid")
        baffles = []
        for k, b in enumerate(self.baffles or ()):
            if isinstance(b, Baffle):
                baffles.append(b)
                continue
            if not isinstance(b, Mapping):
                raise InputError(f"expected a table {{x_m = ..., height_m = ...}}, got {b!r}",
                                 field=f"housing.baffles.{k}")
            extra = sorted(set(b) - set(BAFFLE_KEYS))
            missing = [key for key in BAFFLE_KEYS if key not in b]
            if extra or missing:
                raise InputError(("unknown key(s) " + ", ".join(extra) + "; " if extra else "")
                                 + f"a baffle needs exactly {', '.join(BAFFLE_KEYS)}", field=f"housing.baffles.{k}")
            try:
                baffles.append(Baffle(**b))
            except InputError as err:
                raise InputError(err.reason, field=f"housing.baffles.{k}.{err.field.rsplit('.', 1)[-1]}") from None
        for k, b in enumerate(baffles):
            for j in range(k):
                if abs(b.x_m - baffles[j].x_m) < SEAM_M:
                    raise InputError(f"baffles {j} and {k} (housing_baffle_{j + 1} and housing_baffle_{k + 1}) stand at "
                                     f"the same x = {b.x_m:.10g} m (within {1000 * SEAM_M:g} mm): two plates in one "
                                     "plane; expected each baffle at its own x (give one baffle the larger height)",
                                     field=f"housing.baffles.{k}.x_m")
        object.__setattr__(self, "baffles", tuple(baffles))

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Housing":
        if not isinstance(d, Mapping):
            raise InputError("expected a table [housing]", field="housing")
        extra = sorted(set(d) - set(HOUSING_KEYS))
        if extra:
            raise InputError(f"unknown key(s) {', '.join(extra)}; expected some of {', '.join(HOUSING_KEYS)}",
                             field=f"housing.{extra[0]}")
        if "wall_reflectance" not in d:
            raise InputError("missing (required): the Lambertian reflectance of the inner walls, 0 ... 1",
                             field="housing.wall_reflectance")
        kw = dict(d)
        if "baffles" in kw:
            b = kw["baffles"]
            if isinstance(b, (str, bytes, Mapping)) or not hasattr(b, "__iter__"):
                raise InputError(f"expected a list of tables [{{x_m = ..., height_m = ...}}], got {b!r}",
                                 field="housing.baffles")
            kw["baffles"] = tuple(b)
        return cls(**kw)

    @classmethod
    def of(cls, instrument) -> "Housing | None":
        """The housing of an instrument (its ``[housing]`` table), or None."""
        sec = instrument.extra.get("housing") if hasattr(instrument.extra, "get") else None
        return None if sec is None else cls.from_dict(sec)

    @property
    def baffle_reflectance_value(self) -> float:
        return self.wall_reflectance if self.baffle_reflectance is None else self.baffle_reflectance

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"wall_reflectance": self.wall_reflectance}
        if self.baffle_reflectance is not None:
            d["baffle_reflectance"] = self.baffle_reflectance
        for k in ("x_m", "y_m"):
            if getattr(self, k) is not None:
                d[k] = list(getattr(self, k))
        if self.height_m is not None:
            d["height_m"] = self.height_m
        if self.margin_m != DEFAULT_MARGIN_M:
            d["margin_m"] = self.margin_m
        if not self.lid:
            d["lid"] = False
        if self.baffles:
            d["baffles"] = [{"x_m": b.x_m, "height_m": b.height_m} for b in self.baffles]
        return d
