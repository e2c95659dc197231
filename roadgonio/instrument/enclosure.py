"""The geometry of the instrument's housing (the ``[housing]`` table:
:class:`roadgonio.instrument.housing.Housing`): the box it makes around the parts, its panels, and the
checks that the box holds the detector's view and every requested cell's source (errors naming the
cell and the wall, never silent numbers). Float64 numpy; nothing here imports mitsuba.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from roadgonio.errors import GeometryError, InputError
from roadgonio.instrument.housing import SEAM_M, Box, Housing, Panel


def housing_box(instrument, housing: Housing) -> Box:
    """The inner extent: the given bounds, else the bounding box of the parts (module
    docstring) plus ``margin_m`` (the lid: above the highest part)."""
    lo, hi = parts_bounds(instrument)
    m = housing.margin_m
    x = housing.x_m if housing.x_m is not None else (lo[0] - m, hi[0] + m)
    y = housing.y_m if housing.y_m is not None else (lo[1] - m, hi[1] + m)
    h = housing.height_m if housing.height_m is not None else hi[2] + m
    return Box(x=(float(x[0]), float(x[1])), y=(float(y[0]), float(y[1])), height=float(h))


def with_fixed_housing(instrument):
    """``instrument`` with its housing's box written out (``x_m``, ``y_m``, ``height_m`` as
    :func:`housing_box` resolves them), or itself without a housing or with every bound given. A
    misaligned part moves inside a housing that stays where it was built; the default box follows the
    parts, so a perturbed copy of the instrument would carry its walls along with a misplaced source
    (user audit, session 39: d ln k_A / d D_S 0.07 /m with the box following, 0.35 /m with it fixed, at
    tan eps 11, beta 40 with walls of 0.2). Same box, so the nominal numbers do not change."""
    housing = Housing.of(instrument)
    if housing is None or (housing.x_m is not None and housing.y_m is not None and housing.height_m is not None):
        return instrument
    box = housing_box(instrument, housing)
    return instrument.with_changes(housing={"x_m": list(box.x), "y_m": list(box.y), "height_m": box.height})


def housing_panels(instrument, housing: Housing) -> list[Panel]:
    """The panels of the housing (module docstring): walls, lid (if any) and baffles of
    height > 0, reflecting faces turned into the box."""
    b = housing_box(instrument, housing)
    (x0, x1), (y0, y1), h = b.x, b.y, b.height
    e = SEAM_M
    xc, yc = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    hx, hy = 0.5 * (x1 - x0) + e, 0.5 * (y1 - y0) + e
    zc, hz = 0.5 * (h - e), 0.5 * (h + e)            # from z = -e to h
    rw = housing.wall_reflectance
    out = [
        Panel("housing_wall_x_min", (x0, yc, zc), (0.0, hy, 0.0), (0.0, 0.0, hz), (1.0, 0.0, 0.0), rw,
              label=f"wall x = {x0:.3g} m"),
        Panel("housing_wall_x_max", (x1, yc, zc), (0.0, -hy, 0.0), (0.0, 0.0, hz), (-1.0, 0.0, 0.0), rw,
              label=f"wall x = {x1:.3g} m"),
        Panel("housing_wall_y_min", (xc, y0, zc), (-hx, 0.0, 0.0), (0.0, 0.0, hz), (0.0, 1.0, 0.0), rw,
              label=f"wall y = {y0:.3g} m"),
        Panel("housing_wall_y_max", (xc, y1, zc), (hx, 0.0, 0.0), (0.0, 0.0, hz), (0.0, -1.0, 0.0), rw,
              label=f"wall y = {y1:.3g} m"),
    ]
    if housing.lid:
        out.append(Panel("housing_lid", (xc, yc, h), (hx, 0.0, 0.0), (0.0, -hy, 0.0), (0.0, 0.0, -1.0), rw,
                         label=f"lid z = {h:.3g} m"))
    smp = instrument.sample
    if smp.mesh is None:
        # the road around a rectangular sample, up to the walls: four strips of the floor z = 0
        a, b = 0.5 * smp.size_x_m, 0.5 * smp.size_y_m
        xa, xb = max(x0, -a), min(x1, a)
        strips = [("housing_floor_x_min", (x0 - e, min(-a, x1)), (y0 - e, y1 + e)),
                  ("housing_floor_x_max", (max(a, x0), x1 + e), (y0 - e, y1 + e)),
                  ("housing_floor_y_min", (xa, xb), (y0 - e, min(-b, y1))),
                  ("housing_floor_y_max", (xa, xb), (max(b, y0), y1 + e))]
        for pid, (u0, u1), (v0, v1) in strips:
            if u1 - u0 > e and v1 - v0 > e:
                out.append(Panel(pid, (0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.0), (0.5 * (u1 - u0), 0.0, 0.0),
                                 (0.0, 0.5 * (v1 - v0), 0.0), (0.0, 0.0, 1.0), 0.0, road=True,
                                 label=f"road floor x = {u0:.3g} ... {u1:.3g} m, y = {v0:.3g} ... {v1:.3g} m"))
    rb = housing.baffle_reflectance_value
    for k, bf in enumerate(housing.baffles, start=1):
        if bf.height_m <= 0.0:
            continue
        out.append(Panel(f"housing_baffle_{k}", (bf.x_m, yc, 0.5 * (bf.height_m - e)), (0.0, hy, 0.0),
                         (0.0, 0.0, 0.5 * (bf.height_m + e)), (1.0, 0.0, 0.0), rb, two_sided=True,
                         label=f"baffle {k - 1} (x = {bf.x_m:.3g} m, {1000 * bf.height_m:.3g} mm high)"))
    return out


# ----------------------------------------------------------------------------------------------
# The parts the box must hold, and the checks
# ----------------------------------------------------------------------------------------------

def _disc_rim(centre, normal, radius: float, n: int = 64) -> np.ndarray:
    """(n + 1, 3): n points on the rim of a disc and its centre."""
    from roadgonio.instrument.optics import orthonormal_frame
    s, t = orthonormal_frame(normal)
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    rim = np.asarray(centre)[None, :] + radius * (np.cos(a)[:, None] * s + np.sin(a)[:, None] * t)
    return np.concatenate([rim, np.asarray(centre, dtype=np.float64)[None, :]])


def source_discs(instrument, cells: Sequence[tuple[float, float]]) -> np.ndarray:
    """(cells, 65, 3): rim points and centre of every cell's source disc (float64)."""
    tb = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    w = instrument.w_i(tb[:, 0], tb[:, 1]).reshape(-1, 3)
    r = instrument.source.radius_m
    from roadgonio.instrument.optics import source_distance_m
    dist = np.atleast_1d(source_distance_m(instrument.source, tb[:, 0]))
    return np.stack([_disc_rim(d * wi, -wi, r) for d, wi in zip(dist, w)])


def pupil_disc(instrument) -> np.ndarray:
    w_o = instrument.w_o()
    return _disc_rim(instrument.detector.distance_m * w_o, -w_o, instrument.detector.pupil_radius_m)


def parts_bounds(instrument) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners of the bounding box of the parts: every grid cell's source disc,
    the detector pupil and the detector footprint (float64)."""
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    from roadgonio.instrument.optics import footprint_boundary
    grid = [(float(t), float(b)) for t in TAN_EPS_GRID for b in BETA_GRID_DEG]
    pts = [source_discs(instrument, grid).reshape(-1, 3), pupil_disc(instrument)]
    fx, fy = footprint_boundary(instrument)
    pts.append(np.stack([fx, fy, np.zeros_like(fx)], -1))
    p = np.concatenate(pts)
    return p.min(axis=0), p.max(axis=0)


def _floor_check(instrument, box: Box) -> None:
    """A mesh sample must cover the floor of the box (around a rectangle the road floor panels do)."""
    smp = instrument.sample
    if smp.mesh is None:
        return
    from roadgonio.instrument.mesh import sample_triangles
    v = np.asarray(sample_triangles(instrument).vertices, dtype=np.float64)
    lo, hi = tuple(v[:, :2].min(axis=0)), tuple(v[:, :2].max(axis=0))
    what = "the sample mesh"
    tol = 1e-9
    if lo[0] > box.x[0] + tol or hi[0] < box.x[1] - tol or lo[1] > box.y[0] + tol or hi[1] < box.y[1] - tol:
        need_x = 2 * max(abs(box.x[0]), abs(box.x[1]))
        need_y = 2 * max(abs(box.y[0]), abs(box.y[1]))
        raise GeometryError(
            f"{what} does not cover the floor of the housing (x = {box.x[0]:.3f} ... {box.x[1]:.3f} m, "
            f"y = {box.y[0]:.3f} ... {box.y[1]:.3f} m): a gap would let light out through the road; make the mesh "
            f"at least {need_x:.3f} m x {need_y:.3f} m about the origin, or give [housing] x_m / y_m")


def _wall_reached(points: np.ndarray, box: Box, lid: bool) -> tuple[str, str] | None:
    """("label (id)", axis) of the first wall that the points (N, 3) reach or cross (axis "x", "y"
    or "z": the [housing] bound that places it), or None."""
    checks = [(points[:, 0].min() <= box.x[0], "housing_wall_x_min", f"the wall x = {box.x[0]:.3g} m", "x"),
              (points[:, 0].max() >= box.x[1], "housing_wall_x_max", f"the wall x = {box.x[1]:.3g} m", "x"),
              (points[:, 1].min() <= box.y[0], "housing_wall_y_min", f"the wall y = {box.y[0]:.3g} m", "y"),
              (points[:, 1].max() >= box.y[1], "housing_wall_y_max", f"the wall y = {box.y[1]:.3g} m", "y"),
              (lid and points[:, 2].max() >= box.height, "housing_lid", f"the lid z = {box.height:.3g} m", "z")]
    for bad, pid, label, axis in checks:
        if bad:
            return f"{label} ({pid})", axis
    return None


def _bound_field(housing: Housing, axis: str) -> str:
    """The [housing] key that places the walls of ``axis``: x_m, y_m or height_m when given, else
    margin_m (the default box is the parts' bounding box plus the margin)."""
    key = {"x": "x_m", "y": "y_m", "z": "height_m"}[axis]
    return f"housing.{key}" if getattr(housing, key) is not None else "housing.margin_m"


def _detector_rays(instrument, n_random: int = 2048, n_rim: int = 32):
    """Origins (N, 3), unit directions (N, 3) and distances to the sample plane of detector rays:
    the extreme rays of the bundle and ``n_random`` random ones (float64)."""
    from roadgonio.instrument.optics import detector_geometry, detector_ray, hit_check_points
    from roadgonio.surface.model import NumpyOps
    pu, fu = hit_check_points(n_random, n_rim, seed=11)
    o, d, _ = detector_ray(NumpyOps, detector_geometry(instrument), (pu[:, 0], pu[:, 1]), (fu[:, 0], fu[:, 1]))
    o = np.stack([np.broadcast_to(np.asarray(c, dtype=np.float64), pu[:, 0].shape) for c in o], -1)
    d = np.stack([np.asarray(c, dtype=np.float64) for c in d], -1)
    return o, d, -o[:, 2] / d[:, 2]


def check_detector_view(instrument, housing: Housing) -> Box:
    """The housing around the detector: a mesh sample covers the floor, the pupil and the footprint
    lie inside the box, and no baffle meets a detected ray between the pupil and the sample. Returns
    the box. These are checks of the instrument file, known before any computation: an
    :class:`InputError` naming the file and the ``[housing]`` field (``housing.x_m``,
    ``housing.baffles.0.x_m`` ...), never wrong numbers."""
    from roadgonio.instrument.optics import footprint_boundary

    def bad(message: str, field: str) -> InputError:
        return InputError(message, path=instrument.path, field=field)

    box = housing_box(instrument, housing)
    if box.height <= 0.0:
        raise bad("the housing has no height; expected a height > 0", _bound_field(housing, "z"))
    _floor_check(instrument, box)
    hit = _wall_reached(pupil_disc(instrument), box, housing.lid)
    if hit is not None:
        raise bad(f"the detector's entrance pupil (radius {instrument.detector.pupil_radius_m:g} m at "
                  f"{instrument.detector.distance_m:g} m) is not inside the housing: it reaches {hit[0]}; "
                  "expected a housing that holds it (enlarge x_m, y_m, height_m)", _bound_field(housing, hit[1]))
    fx, fy = footprint_boundary(instrument)
    hit = _wall_reached(np.stack([fx, fy, np.zeros_like(fx)], -1), box, False)
    if hit is not None:
        raise bad(f"the detector footprint is not inside the housing: it reaches {hit[0]}; expected a housing "
                  "that holds it", _bound_field(housing, hit[1]))
    o, d, t_plane = _detector_rays(instrument)
    for k, bf in enumerate(housing.baffles, start=1):
        if bf.height_m <= 0.0:
            continue
        field = f"housing.baffles.{k - 1}"
        if not box.x[0] < bf.x_m < box.x[1]:
            raise bad(f"baffle {k - 1} (housing_baffle_{k}) at x = {bf.x_m:.10g} m is not inside the housing; expected "
                      f"x_m strictly between the walls, {box.x[0]:.10g} < x_m < {box.x[1]:.10g} m (a baffle on a "
                      "wall is part of the wall)", f"{field}.x_m")
        if bf.height_m > box.height and housing.lid:
            raise bad(f"baffle {k - 1} (housing_baffle_{k}) is {bf.height_m:g} m high; expected at most the lid's "
                      f"height ({box.height:.3g} m)", f"{field}.height_m")
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (bf.x_m - o[:, 0]) / d[:, 0]
        z = o[:, 2] + t * d[:, 2]
        meet = np.isfinite(t) & (t > 0.0) & (t < t_plane)
        blocked = meet & (z < bf.height_m)
        if blocked.any():
            clear = float(z[meet].min()) if meet.any() else math.nan
            raise bad(
                f"baffle {k - 1} (housing_baffle_{k}: x = {bf.x_m:g} m, {1000 * bf.height_m:.3g} mm high) blocks the "
                f"detector's view: {int(blocked.sum())} of {blocked.size} checked detector rays meet it before the "
                f"sample (the lowest detected ray passes {1000 * clear:.3g} mm above the sample plane there); "
                "expected a lower baffle or another x_m", f"{field}.height_m")
    return box


def check_sources(instrument, housing: Housing, cells: Sequence[tuple[float, float]]) -> None:
    """Every requested cell's source disc lies inside the box, crosses no baffle, and no baffle stands
    in the line from its centre to the sample centre (a baffle may shade part of the footprint, not
    the nominal direction: no direct light there would make k_A meaningless); else a
    :class:`GeometryError` naming the first such cell, the wall or baffle, and how many cells."""
    if not cells:
        return
    box = housing_box(instrument, housing)
    discs = source_discs(instrument, cells)
    bad: list[tuple[tuple[float, float], str, bool, str]] = []
    for cell, pts in zip(cells, discs):
        hit, sight = _wall_reached(pts, box, housing.lid), False
        wall, key = (hit[0], _bound_field(housing, hit[1])) if hit is not None else (None, "housing")
        if wall is None:
            rim = pts[:-1]
            nxt = np.roll(rim, -1, axis=0)
            for k, bf in enumerate(housing.baffles, start=1):
                if bf.height_m <= 0.0:
                    continue
                s0, s1 = rim[:, 0] - bf.x_m, nxt[:, 0] - bf.x_m
                cross = (s0 * s1) <= 0.0
                if cross.any():
                    with np.errstate(divide="ignore", invalid="ignore"):
                        f = np.where(s0 != s1, s0 / (s0 - s1), 0.0)
                    z = rim[:, 2] + f * (nxt[:, 2] - rim[:, 2])
                    if (z[cross] < bf.height_m).any():
                        wall = f"baffle {k - 1} (housing_baffle_{k}: x = {bf.x_m:g} m, {1000 * bf.height_m:.3g} mm high)"
                        key = f"housing.baffles.{k - 1}.height_m"
                        break
                # the line from the disc's centre to the sample centre (the cell's nominal direction)
                c = pts[-1]
                if (c[0] - bf.x_m) * (0.0 - bf.x_m) < 0.0:
                    z_line = c[2] * (bf.x_m / c[0])
                    if z_line < bf.height_m:
                        wall = (f"baffle {k - 1} (housing_baffle_{k}: x = {bf.x_m:g} m, {1000 * bf.height_m:.3g} mm "
                                f"high) stands in the source's line of sight to the sample centre (the line passes "
                                f"{1000 * z_line:.3g} mm above the floor there); lower or move the baffle, or leave the "
                                "cell out")
                        key = f"housing.baffles.{k - 1}.height_m"
                        sight = True
                        break
        if wall is not None:
            bad.append(((float(cell[0]), float(cell[1])), wall, sight, key))
    if bad:
        (t, b), wall, sight, key = bad[0]
        more = f" (and {len(bad) - 1} more cells)" if len(bad) > 1 else ""
        src = instrument.source
        if sight:
            raise GeometryError(f"the housing blocks the source at tan eps = {t:g}, beta = {b:g}{more}: {wall}",
                                path=instrument.path, field=key)
        raise GeometryError(
            f"the housing blocks the source at tan eps = {t:g}, beta = {b:g}{more}: its disc (radius "
            f"{src.radius_m:g} m, {src.length_key[:-2]} {src.length_m:g} m) reaches {wall}; enlarge the housing or leave the cell out",
            path=instrument.path, field=key)
