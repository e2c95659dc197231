"""EN 13201-3 calculation: field, grid, observers, luminaires counted, and the luminance of every
grid point as a linear operator on the r-table.

What each rule follows (EN 13201-3:2015, CIE 140:2000; the clause numbers are those of
EN 13201-3:2015):

* Field of calculation (7.1.3): between two consecutive luminaires of the same row (row 1),
  x = 0 ... S, over the whole carriageway.
* Grid (7.1.4): longitudinal spacing D = S / N, N = 10 for S <= 30 m, otherwise the smallest
  integer with D <= 3 m, the first transverse row at D / 2 beyond the first luminaire; across each
  lane 3 points at d = W_L / 3, the outer ones d / 2 from the lane's edges (the middle one is on the
  lane's centre line).
* Observer (the observer clause): eye 1.5 m above the road, 60 m before the field (x = -60 m), one
  observer per lane on its centre line. The r-table is the 1 deg table; the real observation angle
  to the grid points (0.9 ... 1.4 deg at 60 ... 95 m) is not corrected for, as the standard does.
* Luminance at a point (7.1.1, 7.1.2): L = MF sum_k I_k(C, gamma) r(beta, tan epsilon) / H^2 with
  I from the luminaire's I-table (bilinear), r in sr^-1 (the file's r x 1e4 is divided on reading),
  interpolated by :mod:`roadgonio.road.interp`; epsilon is the angle of incidence at the point (tan
  epsilon = horizontal distance / H; equal to the luminaire's gamma when the tilt is 0), beta the
  angle between the vertical plane observer-point and the vertical plane point-luminaire (beta = 0:
  the luminaire beyond the point, in line with the observer).
* Luminaires counted: those within 5 H before the point (towards the observer) and 12 H beyond it
  (away from the observer), in every row (the rule of CIE 140 as we read it; set by
  ``luminaires_before_h`` / ``luminaires_after_h``). 12 H in line is tan epsilon = 12, the end of
  the r-table. Contributions whose (beta, tan epsilon) has no r in the CIE standard tables either
  (their blank region at tan >= 5.5 and large beta, tan > 12) are neglected and counted, as the
  standard tables leave them. A contribution whose direction the standard tables tabulate but this
  table leaves blank makes that point's luminance unknown (``LuminanceOperator.incomplete``): the
  metrics that need the point are missing (:mod:`roadgonio.road.evaluate`), never computed without
  the light.
* Horizontal illuminance (for R_EI): E = MF sum_k I_k cos^3(epsilon) / H^2, luminaires within
  5 H (``luminaires_before_h``) on either side of the point.
* Threshold increment: see :func:`veiling_luminance`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from roadgonio.errors import InputError
from roadgonio.geometry import cos3_eps, source_cell
from roadgonio.road.interp import r_weights
from roadgonio.road.layout import Layout
from roadgonio.road.luminaire import Luminaire
from roadgonio.surface.rtable import RTable, standard_mask

#: Threshold increment (CIE 140 / EN 13201-3): screening angle of the car roof, line of sight,
#: range of luminaires counted, the observer's start distance factor and the veiling constant.
TI_SCREEN_DEG = 20.0
TI_SIGHT_DOWN_DEG = 1.0
TI_RANGE_M = 500.0
TI_START_FACTOR = 2.75
#: L_v = K sum E / theta^2 (theta in deg): 10 in CIE 31 / CIE 140; the age-dependent form
#: 9.86 [1 + (A / 66.4)^4] gives 10.0 at the standard age A = 23 years.
VEILING_K = 10.0


@dataclass(frozen=True)
class Field:
    """Grid points, observers and luminaires of a layout."""

    x: np.ndarray            # (n_p,) along the road
    y: np.ndarray            # (n_p,) across
    lane: np.ndarray         # (n_p,) lane index of each point
    centre: np.ndarray       # (n_p,) True on a lane's centre line
    observers: np.ndarray    # (n_lanes, 3)
    luminaires: np.ndarray   # (n_l, 3)
    rotation_deg: np.ndarray  # (n_l,)
    n_long: int
    spacing_d_m: float


def build_field(layout: Layout, x_extent: tuple[float, float] | None = None) -> Field:
    n = layout.n_longitudinal
    d_long = layout.spacing_m / n
    wl = layout.lane_width_m
    xs = (np.arange(n) + 0.5) * d_long
    xx, yy, ll, cc = [], [], [], []
    for k in range(layout.lanes):
        for m in range(3):
            yv = k * wl + (m + 0.5) * wl / 3.0
            xx.append(xs)
            yy.append(np.full(n, yv))
            ll.append(np.full(n, k))
            cc.append(np.full(n, m == 1))
    obs = np.array([[-layout.observer_distance_m, (k + 0.5) * wl, layout.eye_height_m] for k in range(layout.lanes)])
    h = layout.mounting_height_m
    lo, hi = x_extent or (-layout.observer_distance_m - TI_START_FACTOR * h - 5 * h,
                          layout.spacing_m + TI_RANGE_M + layout.spacing_m)
    lo = min(lo, -max(layout.before_h, 5.0) * h - layout.spacing_m)
    hi = max(hi, layout.spacing_m + max(layout.after_h, 5.0) * h + layout.spacing_m)
    lums, rots = [], []
    for y_row, x_off, rot in layout.rows():
        m = np.arange(math.floor((lo - x_off) / layout.spacing_m), math.ceil((hi - x_off) / layout.spacing_m) + 1)
        for xv in m * layout.spacing_m + x_off:
            lums.append((xv, y_row, h))
            rots.append(rot)
    return Field(np.concatenate(xx), np.concatenate(yy), np.concatenate(ll), np.concatenate(cc), obs,
                 np.array(lums), np.array(rots, dtype=float), n, d_long)


def luminaire_angles(lum: np.ndarray, rotation_deg, tilt_deg: float, target: np.ndarray):
    """(C, gamma) in degrees of the direction from luminaire(s) ``lum`` (..., 3) to ``target``
    (..., 3), in the luminaire frame (EN 13201-3 clause 6: C = 0 along the row's road axis, C = 90
    towards the road, gamma from the downward axis, which the tilt swings towards C = 90)."""
    d = np.asarray(target, float) - np.asarray(lum, float)
    rot = np.radians(np.asarray(rotation_deg, float))
    t = math.radians(tilt_deg)
    e0 = np.stack(np.broadcast_arrays(np.cos(rot), np.sin(rot), 0.0 * rot), axis=-1)       # C = 0
    e90h = np.stack(np.broadcast_arrays(-np.sin(rot), np.cos(rot), 0.0 * rot), axis=-1)    # towards road
    z = np.array([0.0, 0.0, 1.0])
    e90 = math.cos(t) * e90h + math.sin(t) * z
    down = -math.cos(t) * z + math.sin(t) * e90h
    norm = np.linalg.norm(d, axis=-1)
    cg = np.clip(np.sum(d * down, axis=-1) / norm, -1.0, 1.0)
    gamma = np.degrees(np.arccos(cg))
    c = np.degrees(np.arctan2(np.sum(d * e90, axis=-1), np.sum(d * e0, axis=-1))) % 360.0
    return c, gamma


def incidence(lum: np.ndarray, point: np.ndarray, observer: np.ndarray) -> tuple[float, float]:
    """(beta in deg, tan epsilon) at a road point (z = 0) lit from ``lum``, seen from ``observer``:
    :func:`roadgonio.geometry.source_cell` of the direction towards the luminaire, with the
    observation azimuth delta that of the observer seen from the point (0 where beta is undefined:
    the luminaire overhead, or the observer above the point)."""
    h = lum[2] - point[2]
    v = np.asarray(lum[:2], float) - np.asarray(point[:2], float)
    u = np.asarray(point[:2], float) - np.asarray(observer[:2], float)
    tan_e, beta = source_cell(np.array([v[0], v[1], h]), math.degrees(math.atan2(-u[1], -u[0])))
    if float(np.hypot(*v)) < 1e-9 or np.hypot(*u) < 1e-9:
        return 0.0, float(tan_e)
    return float(beta), float(tan_e)


@dataclass
class LuminanceOperator:
    """``L[o, p] = W[o, p, :] @ r.ravel()`` (cd/m^2, r in sr^-1; blank cells have weight 0)."""

    W: np.ndarray
    field: Field
    neglected: int = 0          # contributions without r in the standard tables either (their blanks, tan > 12)
    evaluated: int = 0
    max_tan: float = 0.0
    notes: list = field(default_factory=list)
    #: (n_obs, n_p): the point's luminance lacks a contribution whose direction the CIE standard
    #: tables tabulate but this table leaves blank (the point's L is not known: missing)
    incomplete: np.ndarray | None = None
    #: (beta deg, tan eps) of such contributions (the first few, for the note)
    missing_directions: list = field(default_factory=list)
    missing_count: int = 0

    def luminance(self, table: RTable | np.ndarray) -> np.ndarray:
        """L (cd/m^2) per observer and point; a negative value (the quadratic interpolation
        overshooting near zero r) is 0: no luminance is negative."""
        r = table.r if isinstance(table, RTable) else np.asarray(table)
        flat = np.nan_to_num(r.reshape(-1), nan=0.0)
        return np.maximum(self.W @ flat, 0.0)

    @property
    def used_cells(self) -> np.ndarray:
        return np.nonzero(np.any(self.W != 0, axis=(0, 1)))[0]


def _counted(layout: Layout, x_point: float, x_lums: np.ndarray) -> np.ndarray:
    h = layout.mounting_height_m
    return (x_lums >= x_point - layout.before_h * h - 1e-9) & (x_lums <= x_point + layout.after_h * h + 1e-9)


def uncounted_points(layout: Layout, fld: Field) -> np.ndarray:
    """(n_p,) True where a grid point has no luminaire of any row within the counted range
    (``luminaires_before_h`` H before it, ``luminaires_after_h`` H beyond: the rule above). Such a
    point's luminance is 0 by the rule, not by the lighting: a spacing longer than the counted range
    (S > (5 + 12) H for one row) leaves points unlit and U_o = 0."""
    return np.array([not np.any(_counted(layout, x, fld.luminaires[:, 0])) for x in fld.x], dtype=bool)


def uncounted_note(layout: Layout, fld: Field) -> str | None:
    """One line saying that the layout leaves grid points without a counted luminaire (None: it
    leaves none)."""
    bare = uncounted_points(layout, fld)
    if not bare.any():
        return None
    h = layout.mounting_height_m
    reach = (layout.before_h + layout.after_h) * h
    return (f"{int(bare.sum())} of {bare.size} grid points have no luminaire in the counted range "
            f"(luminaires_before_h {layout.before_h:g} H = {layout.before_h * h:g} m before the point, "
            f"luminaires_after_h {layout.after_h:g} H = {layout.after_h * h:g} m beyond it; CIE 140's rule as "
            f"roadgonio reads it): the spacing S = {layout.spacing_m:g} m leaves gaps longer than those "
            f"{reach:g} m, so their luminance is 0 by the rule and "
            + ("U_o is 0" if not bare.all() else "nothing is lit (the uniformities are undefined)"))


def range_note(layout: Layout) -> str | None:
    """One line when the counted range reaches beyond tan epsilon = 12, where r-tables end: those
    luminaires' light is neglected (no r), so the range above 12 H changes no metric (user audit,
    session 37: ``luminaires_after_h = 15`` gave the default's numbers digit for digit, the terminal
    silent). None within 12 H."""
    far = max(layout.before_h, layout.after_h)
    if far <= 12.0:
        return None
    return (f"luminaires_before_h {layout.before_h:g} H / luminaires_after_h {layout.after_h:g} H reach beyond "
            "tan eps = 12, the end of the r-table: a luminaire more than 12 H along the road from the point has tan eps "
            "> 12, no r, and its light is neglected (road.json's neglected_contributions), so the range beyond 12 H changes no metric")


def contribution(luminaire: Luminaire, lum: np.ndarray, rotation_deg: float, tilt_deg: float, point: np.ndarray,
                 observer: np.ndarray, table: RTable, order: str = "quadratic"):
    """One luminaire's luminance at a road point for an observer (EN 13201-3 7.1.1), without the
    maintenance factor, as weights on the table's cells: L = sum(w * r.ravel()[cells]) with
    w = I(C, gamma) x (interpolation weight) / H^2. Returns (cells, w, tan epsilon); cells is None
    where the table has no r for this (beta, tan epsilon)."""
    beta, tan_e = incidence(lum, point, observer)
    got = r_weights(table, beta, tan_e, order)
    if got is None:
        return None, None, tan_e
    c, g = luminaire_angles(lum, rotation_deg, tilt_deg, point)
    intens = float(luminaire.intensity(c, g))
    if not np.isfinite(intens):
        raise InputError(f"the luminaire data cover gamma up to {luminaire.gamma_max_deg:g} deg; this layout needs "
                         f"gamma = {float(g):.1f} deg (C = {float(c):.1f} deg)", path=luminaire.source or None,
                         field="gamma angles")
    h = lum[2] - point[2]
    cells, w = got
    return cells, intens * w / (h * h), tan_e


def luminance_operator(layout: Layout, luminaire: Luminaire, table: RTable, fld: Field | None = None) -> LuminanceOperator:
    """The EN 13201-3 luminance of every grid point for every observer, as weights on the cells of
    ``table``'s grid (the values of ``table`` are not used: only its grid and blank pattern)."""
    fld = fld or build_field(layout)
    n_obs, n_p = len(fld.observers), len(fld.x)
    W = np.zeros((n_obs, n_p, table.r.size))
    incomplete = np.zeros((n_obs, n_p), dtype=bool)
    missing: list[tuple[float, float]] = []
    standard = RTable(np.where(standard_mask(), 1.0, np.nan))
    neglected = evaluated = 0
    max_tan = 0.0
    mf = layout.maintenance_factor
    for p in range(n_p):
        point = np.array([fld.x[p], fld.y[p], 0.0])
        sel = np.nonzero(_counted(layout, fld.x[p], fld.luminaires[:, 0]))[0]
        for o in range(n_obs):
            for li in sel:
                got = contribution(luminaire, fld.luminaires[li], fld.rotation_deg[li], layout.tilt_deg, point,
                                   fld.observers[o], table, layout.interpolation)
                evaluated += 1
                max_tan = max(max_tan, got[2])
                if got[0] is None:
                    beta, tan_e = incidence(fld.luminaires[li], point, fld.observers[o])
                    if r_weights(standard, beta, tan_e, layout.interpolation) is not None:
                        # the standard tables have r here, this table has not: L at the point is unknown
                        incomplete[o, p] = True
                        missing.append((beta, tan_e))
                    else:
                        neglected += 1      # outside the standard tables too: neglected, as they do
                    continue
                np.add.at(W[o, p], got[0], mf * got[1])
    return LuminanceOperator(W, fld, neglected, evaluated, max_tan, incomplete=incomplete,
                             missing_directions=missing[:5], missing_count=len(missing))


def horizontal_illuminance(layout: Layout, luminaire: Luminaire, x: np.ndarray, y: np.ndarray,
                           fld: Field, mf: float | None = None) -> np.ndarray:
    """E_h (lx) at road points (x, y); luminaires within ``before_h`` H on either side."""
    mf = layout.maintenance_factor if mf is None else mf
    h = layout.mounting_height_m
    out = np.zeros(len(x))
    for p in range(len(x)):
        sel = np.abs(fld.luminaires[:, 0] - x[p]) <= layout.before_h * h + 1e-9
        lums = fld.luminaires[sel]
        point = np.array([x[p], y[p], 0.0])
        c, g = luminaire_angles(lums, fld.rotation_deg[sel], layout.tilt_deg, point)
        i = luminaire.intensity(c, g)
        if np.any(np.isnan(i)):
            raise InputError(f"the luminaire data cover gamma up to {luminaire.gamma_max_deg:g} deg; the illuminance "
                             "needs more", path=luminaire.source or None, field="gamma angles")
        hz = lums[:, 2]
        dist_h = np.hypot(lums[:, 0] - x[p], lums[:, 1] - y[p])
        cos3 = cos3_eps(dist_h / hz)
        out[p] = mf * np.sum(i * cos3 / hz ** 2)
    return out


def edge_strips(layout: Layout, fld: Field) -> list[dict]:
    """The four R_EI strips (inside / outside each edge): points with spacing <= 1.5 m across
    (at least 3) and the field's longitudinal spacing along."""
    w = layout.strip_m
    n = max(3, math.ceil(w / 1.5 - 1e-9))
    off = (np.arange(n) + 0.5) * w / n
    xs = (np.arange(fld.n_long) + 0.5) * fld.spacing_d_m
    strips = []
    for edge, y0, inward in (("y = 0 edge", 0.0, 1.0), ("y = W edge", layout.width_m, -1.0)):
        for where, sign in (("inside", inward), ("outside", -inward)):
            yy = y0 + sign * off
            X, Y = np.meshgrid(xs, yy, indexing="ij")
            strips.append({"edge": edge, "where": where, "x": X.ravel(), "y": Y.ravel()})
    return strips


def edge_illuminance_ratio(layout: Layout, luminaire: Luminaire, fld: Field) -> dict:
    """R_EI (EN 13201-2:2015): mean E_h on the strip just outside each edge over that on the strip
    just inside it; the operative value is the lower of the two edges."""
    strips = edge_strips(layout, fld)
    mean = {}
    for s in strips:
        mean[(s["edge"], s["where"])] = float(np.mean(horizontal_illuminance(layout, luminaire, s["x"], s["y"], fld)))
    per_edge = {e: mean[(e, "outside")] / mean[(e, "inside")] if mean[(e, "inside")] > 0 else float("nan")
                for e in ("y = 0 edge", "y = W edge")}
    return {"R_EI": float(min(per_edge.values())), "per_edge": per_edge, "strip_m": layout.strip_m,
            "E_mean_lx": {f"{e} {w}": v for (e, w), v in mean.items()}}


def veiling_luminance(layout: Layout, luminaire: Luminaire, fld: Field) -> dict:
    """Veiling luminance L_v (cd/m^2) of each TI observer position, with initial values (MF = 1).

    Observer: in each lane centre, eye 1.5 m, looking along the road 1 deg down; first position
    2.75 (H - 1.5) m before the field (the first luminaire of the field then sits at the 20 deg
    screening angle), then moved in steps D over one spacing (N positions). Luminaires counted: in
    every row, ahead of the eye up to 500 m, below the 20 deg screening plane (the car roof: a
    plane through the eye, transverse to the road, inclined 20 deg above the horizontal).
    L_v = 10 sum_k E_k / theta_k^2 with E_k the illuminance at the eye on a plane normal to the line
    of sight and theta_k (deg) the angle between the line of sight and the luminaire.
    Returns ``{"L_v": (n_lanes, N) array, "computable": bool, "reason": str}``."""
    h = layout.mounting_height_m
    eye = layout.eye_height_m
    x0 = -TI_START_FACTOR * (h - eye)
    sight = np.array([math.cos(math.radians(TI_SIGHT_DOWN_DEG)), 0.0, -math.sin(math.radians(TI_SIGHT_DOWN_DEG))])
    lv = np.zeros((layout.lanes, fld.n_long))
    tan_screen = math.tan(math.radians(TI_SCREEN_DEG))
    for k in range(layout.lanes):
        for m in range(fld.n_long):
            o = np.array([x0 + m * fld.spacing_d_m, (k + 0.5) * layout.lane_width_m, eye])
            ahead = fld.luminaires[:, 0] - o[0]
            sel = (ahead > 0) & (ahead <= TI_RANGE_M) & (fld.luminaires[:, 2] - eye <= tan_screen * ahead + 1e-9)
            lums = fld.luminaires[sel]
            if len(lums) == 0:
                continue
            c, g = luminaire_angles(lums, fld.rotation_deg[sel], layout.tilt_deg, o)
            i = luminaire.intensity(c, g)
            if np.any(np.isnan(i)):
                return {"L_v": None, "computable": False,
                        "reason": f"the luminaire data stop at gamma = {luminaire.gamma_max_deg:g} deg; TI needs "
                                  f"{np.nanmax(np.where(np.isnan(i), g, np.nan)):.1f} deg"}
            d = lums - o
            dist = np.linalg.norm(d, axis=1)
            cos_t = np.clip(d @ sight / dist, -1.0, 1.0)
            theta = np.degrees(np.arccos(cos_t))
            e_eye = i * cos_t / dist ** 2
            lv[k, m] = VEILING_K * np.sum(e_eye / theta ** 2)
    return {"L_v": lv, "computable": True, "reason": "", "x0_m": x0}


def threshold_increment(l_v, l_av_initial):
    """TI (%) = 65 L_v / L_av^0.8 for L_av <= 5 cd/m^2, 95 L_v / L_av^1.05 above (CIE 140,
    EN 13201-3). Broadcasts."""
    l_v = np.asarray(l_v, float)
    lav = np.asarray(l_av_initial, float)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):   # L_av -> 0: TI -> inf (callers: missing)
        return np.where(lav <= 5.0, 65.0 * l_v / lav ** 0.8, 95.0 * l_v / lav ** 1.05)
