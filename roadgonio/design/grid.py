"""The design grid: ``--vary KEY=LO:HI:N[:log]`` specifications, the tolerance and the cells.

Every grid point is a complete instrument: the base instrument file with the varied keys changed
(:meth:`roadgonio.instrument.config.Instrument.with_changes`). KEY is an instrument-file key
``section.key`` (docs/conventions.md section 4), for example ``source.radius_m``, ``source.distance_m``,
``detector.distance_m``, ``detector.pupil_radius_m``, ``detector.field_half_angle_deg``,
``observation.alpha_deg``, the widths of the source's beam profile ``source.beam_sigma_deg``,
``source.beam_cos_power``, ``source.aperture_edge_radiance``; the housing's ``housing.wall_reflectance``,
``housing.baffle_reflectance``, ``housing.height_m``, ``housing.margin_m`` and, for a baffle declared in
the base instrument's ``[housing] baffles`` (index N from 0; a height of 0 is no baffle),
``housing.baffles.N.x_m`` and ``housing.baffles.N.height_m`` (the housing keys only for a base
instrument with a ``[housing]``: :func:`check_vary` refuses the others before any computation). Values:

* ``LO:HI:N``      N values evenly spaced from LO to HI (both included);
* ``LO:HI:N:log``  N values evenly spaced in log(value) (LO, HI > 0); ``LO:HI:N:lin`` (or ``:linear``) is ``LO:HI:N``;
* ``V1,V2,...``    the listed values.

Each axis is kept in ascending order, whatever order its values were given in.

Values are rounded to 12 significant digits (0.02, not 0.019999999999999997), so the CSV, the
instrument file of the best design and ``roadgonio ka`` all see the same numbers.

Focus: a base instrument focused on the sample centre (``focus_m`` absent or equal to
``distance_m``) stays focused on it when ``detector.distance_m`` is varied (unless
``detector.focus_m`` is varied too); an instrument focused elsewhere, or at infinity, keeps its focus.
"""
from __future__ import annotations

import itertools
import math
import re
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from roadgonio.errors import InputError
from roadgonio.instrument.config import APERTURE_KEYS, BEAM_KEYS, Instrument

#: The numeric instrument keys a design may vary (section -> keys), docs/conventions.md section 4.
VARIABLE_KEYS: dict[str, tuple[str, ...]] = {
    "observation": ("alpha_deg", "delta_deg"),
    "source": ("distance_m", "height_m", "radius_m", "beam_half_angle_deg", "beam_sigma_deg", "beam_cos_power",
               "aperture_edge_radiance"),
    "detector": ("distance_m", "pupil_radius_m", "field_half_angle_deg", "focus_m", "field_edge_sensitivity"),
    "sample": ("size_x_m", "size_y_m"),
    "housing": ("wall_reflectance", "baffle_reflectance", "height_m", "margin_m"),
}
ALL_KEYS = tuple(f"{s}.{k}" for s, keys in VARIABLE_KEYS.items() for k in keys)
#: Keys of the baffles declared in the base instrument's [housing] (N = 0, 1, ...).
BAFFLE_KEY = re.compile(r"^housing\.baffles\.(\d+)\.(x_m|height_m)$")
SYNTAX = "KEY=LO:HI:N, KEY=LO:HI:N:log or KEY=V1,V2,... (e.g. source.radius_m=0.01:0.04:4)"


def _round(v: float) -> float:
    return float(f"{v:.12g}")


@dataclass(frozen=True)
class VarySpec:
    """One varied instrument key and its values."""

    key: str
    values: tuple[float, ...]
    log: bool = False
    text: str = ""

    @property
    def section(self) -> str:
        return self.key.split(".", 1)[0]

    @property
    def name(self) -> str:
        return self.key.split(".", 1)[1]


def _number(text: str, spec: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"expected a number, got {text!r} in {spec!r}; syntax {SYNTAX}", field="vary") from None
    if not math.isfinite(v):
        # the instrument file allows focus_m = inf, a design axis cannot: the grid, the surrogate and
        # the plots interpolate over the values (user audit, session 19)
        hint = (": a design axis needs finite values (its grid and surrogate interpolate over them); the "
                "largest focus, 1000 m, approaches the angular field (compare the inf instrument with "
                "`roadgonio ka`)"
                if spec.split("=", 1)[0].strip() == "detector.focus_m" else "")
        raise InputError(f"expected a finite number, got {text!r} in {spec!r}{hint}", field="vary")
    return v


def parse_vary(spec: str) -> VarySpec:
    """``"source.radius_m=0.01:0.04:4"`` -> :class:`VarySpec` (see the module docstring)."""
    text = str(spec).strip()
    if "=" not in text:
        raise InputError(f"expected {SYNTAX}; got {text!r}", field="vary")
    key, rhs = (s.strip() for s in text.split("=", 1))
    if key not in ALL_KEYS and not BAFFLE_KEY.match(key):
        raise InputError(f"unknown instrument key {key!r}; expected one of {', '.join(ALL_KEYS)}, "
                         "housing.baffles.N.x_m, housing.baffles.N.height_m", field="vary")
    if not rhs:
        raise InputError(f"no values for {key}; expected {SYNTAX}", field="vary")
    log = False
    if ":" in rhs:
        parts = [p.strip() for p in rhs.split(":")]
        if len(parts) == 4 and parts[3].lower() == "log":
            log = True
            parts = parts[:3]
        elif len(parts) == 4 and parts[3].lower() in ("lin", "linear"):
            parts = parts[:3]
        if len(parts) != 3:
            raise InputError(f"expected LO:HI:N, LO:HI:N:log or LO:HI:N:lin for {key}, got {rhs!r}", field="vary")
        lo, hi = _number(parts[0], text), _number(parts[1], text)
        try:
            n = int(parts[2])
        except ValueError:
            raise InputError(f"expected a whole number of values N, got {parts[2]!r} in {text!r}", field="vary") from None
        if n < 1:
            raise InputError(f"expected N >= 1 values, got {n} in {text!r}", field="vary")
        from roadgonio.limits import check_size
        check_size(n, "design_points", "vary")
        if n == 1 and lo != hi:
            raise InputError(f"one value (N = 1) needs LO = HI, got {text!r}", field="vary")
        if log:
            if lo <= 0 or hi <= 0:
                raise InputError(f"a log grid needs LO, HI > 0, got {text!r}", field="vary")
            vals = np.geomspace(lo, hi, n)
        else:
            vals = np.linspace(lo, hi, n)
        values = tuple(_round(v) for v in vals)
    else:
        values = tuple(_round(_number(v.strip(), text)) for v in rhs.split(",") if v.strip())
    if len(set(values)) != len(values):
        raise InputError(f"repeated values for {key} in {text!r}", field="vary")
    # a grid axis in ascending order whatever order the values were given in: the tolerance map's
    # cells, contours and iso-signal lines are drawn between neighbouring values (user audit:
    # 0.02,0.002,0.01 painted 4 of 9 cells and put a point's value at another radius)
    return VarySpec(key=key, values=tuple(sorted(values)), log=log, text=text)


def as_vary_specs(vary: Sequence[str | VarySpec] | Mapping[str, Sequence[float]] | None) -> list[VarySpec]:
    """Vary specifications from strings, :class:`VarySpec` objects or a ``{key: values}`` mapping;
    a key may appear once."""
    if vary is None:
        return []
    if isinstance(vary, (str, VarySpec)):          # one specification (not its characters)
        vary = [vary]
    specs: list[VarySpec] = []
    if isinstance(vary, Mapping):
        for key, values in vary.items():
            if isinstance(values, str):
                specs.append(parse_vary(f"{key}={values}"))
            else:
                if isinstance(values, (int, float)):
                    values = [values]
                bad = [v for v in values if isinstance(v, bool) or not isinstance(v, (int, float, np.integer,
                                                                                      np.floating))]
                if bad:
                    raise InputError(f"expected numbers as the values of {key}, got {bad[0]!r}", field="vary")
                specs.append(parse_vary(f"{key}=" + ",".join(repr(float(v)) for v in values)))
    elif isinstance(vary, (list, tuple)):
        for v in vary:
            if not isinstance(v, (str, VarySpec)):
                raise InputError(f"expected 'key=values' texts, got {type(v).__name__} {v!r}", field="vary")
            specs.append(v if isinstance(v, VarySpec) else parse_vary(v))
    else:
        # (audit 21: an int gave TypeError 'int' object is not iterable)
        raise InputError(f"expected 'key=values' texts, a list of them or a {{key: values}} mapping, got "
                         f"{type(vary).__name__}", field="vary")
    seen = set()
    for s in specs:
        if s.key in seen:
            raise InputError(f"{s.key} is varied twice; give each key once", field="vary")
        seen.add(s.key)
    return specs


#: Keys of which an instrument gives at most one (:mod:`roadgonio.instrument.config`): the source's
#: angular profile, its aperture profile, the detector's field sensitivity.
ALTERNATIVES: tuple[tuple[str, tuple[str, ...], str], ...] = (
    ("source", BEAM_KEYS, "at most one angular profile"),
    ("source", APERTURE_KEYS, "an edge radiance or a radiance file, not both"),
    ("detector", ("field_edge_sensitivity", "field_sensitivity"), "an edge sensitivity or a sensitivity map, not both"),
)


def _gives(base: Instrument, section: str, key: str) -> bool:
    """Whether the base instrument's file gives ``section.key`` (a value other than the default)."""
    import dataclasses
    obj = getattr(base, section)
    default = next(f.default for f in dataclasses.fields(obj) if f.name == key)
    return getattr(obj, key) != default


def check_vary(base: Instrument, specs: Sequence[VarySpec]) -> None:
    """Refuse, before any computation, a varied key the base instrument cannot take: a ``housing.*``
    key when the base has no ``[housing]`` (a design varies a housing, it does not add one: the
    box's size, lid and baffles would be defaults nobody chose), or a baffle the base's
    ``[housing] baffles`` does not declare, or their reflectance when it declares none; a key whose alternative (:data:`ALTERNATIVES`) the base
    gives or the design varies too. ``detector.field_edge_sensitivity`` on a base with a
    ``field_sensitivity`` map is refused for every value, 1 included: the value 1 would silently
    keep the map (1 is the default, read as "not given"), so a point labelled e = 1 would not be
    an instrument with a uniform edge; the map is not dropped behind the user's back either."""
    where = f" ({base.path})" if base.path is not None else ""
    varied = {s.key for s in specs}
    for s in specs:
        for section, keys, why in ALTERNATIVES:
            if s.section != section or s.name not in keys:
                continue
            for other in keys:
                if other == s.name:
                    continue
                if f"{section}.{other}" in varied:
                    raise InputError(f"{s.key} and {section}.{other} cannot be varied together ({why}); vary one of "
                                     "them", field="vary")
                if _gives(base, section, other):
                    raise InputError(f"{s.key}: the base instrument{where} gives {section}.{other} ({why}): a value "
                                     f"of {s.name} would conflict with it or, at the default, leave {other} in place "
                                     f"under a label that says otherwise; remove {section}.{other} from the base "
                                     f"file to vary {s.key}", field="vary")
    sec = base.extra.get("housing") if hasattr(base.extra, "get") else None
    for s in specs:
        if s.section != "housing":
            continue
        if sec is None:
            raise InputError(f"{s.key}: the base instrument{where} has no [housing]; declare one in its file "
                             "(docs/straylight.md) to vary the housing's keys", field="vary")
        if s.key == "housing.baffle_reflectance" and not (sec.get("baffles", ()) or ()):
            # audit 28: accepted on a housing without baffles, every point the same instrument, and the
            # tables' noise read as an effect of the baffles' paint
            raise InputError(f"{s.key}: the base instrument{where} declares no baffles in [housing], so their "
                             "reflectance changes nothing; declare them there, e.g. baffles = [{x_m = -0.5, "
                             "height_m = 0.02}]", field="vary")
        m = BAFFLE_KEY.match(s.key)
        if m:
            n = len(sec.get("baffles", ()) or ())
            k = int(m.group(1))
            if k >= n:
                raise InputError(f"{s.key}: the base instrument{where} declares {n} baffle(s) in [housing] baffles "
                                 f"(N = 0 ... {n - 1}); declare baffle {k} there (height_m = 0 is no baffle)"
                                 if n else
                                 f"{s.key}: the base instrument{where} declares no baffles in [housing]; declare "
                                 "them there, e.g. baffles = [{x_m = -0.5, height_m = 0.0}] (height_m = 0 is no "
                                 "baffle)", field="vary")
    # a baffle of height 0 is no plate: its position or its paint changes nothing unless the design
    # varies its height too (user audit, session 29: housing.baffles.0.x_m = -2 and 5 m on the bundled
    # baffle base, height 0, computed three identical instruments outside the box and showed noise as
    # an effect)
    baffles = list((sec.get("baffles", ()) or ()) if sec is not None else ())

    def flat(k: int) -> bool:           # (a baffle the base does not declare was refused above)
        b = baffles[k]
        h = b.get("height_m", 0.0) if hasattr(b, "get") else 0.0
        return float(h or 0.0) == 0.0 and f"housing.baffles.{k}.height_m" not in varied

    for s in specs:
        m = BAFFLE_KEY.match(s.key)
        if m and m.group(2) == "x_m" and flat(int(m.group(1))):
            raise InputError(f"{s.key}: baffle {m.group(1)} of the base instrument{where} has height_m = 0 (no plate), "
                             f"so its position changes nothing; vary housing.baffles.{m.group(1)}.height_m too, or "
                             "give it a height in the base file", field="vary")
        if s.key == "housing.baffle_reflectance" and baffles and all(flat(k) for k in range(len(baffles))):
            raise InputError(f"{s.key}: every baffle of the base instrument{where} has height_m = 0 (no plate), so "
                             "their reflectance changes nothing; vary a baffle's height too, or give one a height "
                             "in the base file", field="vary")


def grid_points(specs: Sequence[VarySpec]) -> list[dict[str, float]]:
    """All combinations, the last key varying fastest (C order: the layout of ``design.nc``)."""
    return [dict(zip((s.key for s in specs), combo)) for combo in itertools.product(*(s.values for s in specs))]


def grid_shape(specs: Sequence[VarySpec]) -> tuple[int, ...]:
    return tuple(len(s.values) for s in specs)


def point_changes(base: Instrument, point: Mapping[str, float]) -> dict[str, dict[str, Any]]:
    """The ``with_changes`` sections of a grid point (with the focus rule of the module docstring)."""
    changes: dict[str, dict[str, Any]] = {}
    baffles = None
    for key, value in point.items():
        m = BAFFLE_KEY.match(key)
        if m:
            # one baffle of the base instrument's [housing] list
            if baffles is None:
                sec = base.extra.get("housing") or {}
                baffles = [dict(b) for b in sec.get("baffles", ())]
            k = int(m.group(1))
            if k >= len(baffles):
                raise InputError(f"{key}: the base instrument declares {len(baffles)} baffle(s) in [housing] "
                                 f"baffles; declare baffle {k} there (height_m = 0 is no baffle)", field="vary")
            baffles[k][m.group(2)] = float(value)
            continue
        sec, name = key.split(".", 1)
        changes.setdefault(sec, {})[name] = float(value)
    if baffles is not None:
        changes.setdefault("housing", {})["baffles"] = baffles
    det = changes.get("detector", {})
    if "distance_m" in det and "focus_m" not in det:
        f = base.detector.focus_m
        if f is not None and math.isfinite(f) and f == base.detector.distance_m:
            det["focus_m"] = det["distance_m"]
    return changes


def build_instrument(base: Instrument, point: Mapping[str, float]) -> Instrument:
    """The instrument of a grid point; raises :class:`InputError` for an invalid one (for example a
    source radius larger than its distance)."""
    return base.with_changes(**point_changes(base, point))


def parse_fraction(text: str | float, field: str, example: float) -> tuple[float, bool]:
    """A fraction given as a number or as text, ``"0.05"`` or a percentage ``"5%"`` (-> 0.05), and
    whether it was a percentage; anything else is one :class:`InputError` naming ``field`` with
    ``example`` written both ways."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        return float(text), False
    s = str(text).strip()
    pct = s.endswith("%")
    try:
        v = float(s[:-1] if pct else s)
    except ValueError:
        raise InputError(f"expected a fraction ({example:g}) or a percentage ({100 * example:g}%), got {text!r}",
                         field=field) from None
    return (v / 100.0 if pct else v), pct


def parse_tolerance(text: str | float) -> float:
    """``"5%"`` -> 0.05, ``"0.05"`` -> 0.05: a tolerance on |k_A - 1|, a fraction or a percentage."""
    v, pct = parse_fraction(text, "tolerance", 0.05)
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"expected a tolerance > 0, got {text!r}", field="tolerance")
    if v >= 1 and not pct:
        raise InputError(f"a tolerance of {v:g} on |k_A - 1| would accept k_A = 0; for a percentage write "
                         f"'{v:g}%'", field="tolerance")
    if v >= 1:
        # the same tolerance written as a percentage accepts k_A = 0 just as well (user audit, session 19)
        raise InputError(f"a tolerance of {text} on |k_A - 1| would accept k_A = 0; expected less than 100%",
                         field="tolerance")
    return v
