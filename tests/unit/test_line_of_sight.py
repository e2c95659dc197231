"""The one line-of-sight test (roadgonio.instrument.optics.source_blocks_view): checked against
rays written out here, and applied alike by every backend and by the design's pre-filter.

The cells near the blocking edge below are where the three checks the project had before
(a 48x5 grid of rays in the reference backend, 32x32 rim rays plus 1024 random rays in the
Mitsuba engine, 32 rim rays plus a 5x5 grid in the design) gave different answers, e.g. at
(9.5406, 179.5) the reference refused the cell and the design and the Mitsuba engine accepted it,
at (9.6622, 179.0) the other way round, and at (9.9954, 178.3) all three missed a disc that reaches
1.6 um into the bundle; with a 0.1 mm source deep inside the bundle (tan eps 47.74, beta 179.9)
the design's check missed it.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.arrays import NumpyOps
from roadgonio.instrument import optics
from roadgonio.instrument.config import Instrument, load_instrument

from helpers import backend_refuses, line_of_sight_edge_cells

PORTABLE = load_instrument("portable")
EDGE_CELLS = line_of_sight_edge_cells()
#: A 4 cm source at 0.5 m: for beta near 180 deg at tan eps ~ 9.5 its rim cuts the detector's bundle.
NEAR = EDGE_CELLS[0][0]
#: A 0.1 mm source at 0.5 m: near the line of sight it sits wholly inside the bundle.
SPECK = EDGE_CELLS[-1][0]


# ----------------------------------------------------------------------------------------------
# an independent account of the bundle: the ray through a point, pupil point by pupil point
# ----------------------------------------------------------------------------------------------

def margin(inst: Instrument, x: np.ndarray, *, behind: float = np.inf) -> np.ndarray:
    """How far (m, radially) the points x lie outside the detector's bundle. From a pupil point p the
    ray through x (axial distance zeta from the pupil) reaches the focus plane (axial distance F)
    at q = p + (x - p) F / zeta: with k = F / zeta, q_r = k x_r + (1 - k) p_r, whose smallest distance
    from the axis over the pupil disc is k rho - |1 - k| R_D; x is in the bundle when that is at most
    the field radius F tan(gamma), i.e. rho <= zeta tan(gamma) + |zeta / F - 1| R_D. Angular field:
    the ray p + zeta (a + tan(gamma) u), |u| <= 1, reaches rho <= R_D + zeta tan(gamma). Points behind
    the pupil plane get ``behind`` (default +inf: no ray passes there)."""
    det = inst.detector
    a = -inst.w_o()
    rel = x - det.distance_m * inst.w_o()
    zeta = rel @ a
    rho = np.linalg.norm(rel - zeta[:, None] * a, axis=1)
    rd, tan_g, f = det.pupil_radius_m, math.tan(math.radians(det.field_half_angle_deg)), det.focus_distance_m
    z = np.maximum(zeta, 0.0)
    reach = rd + z * tan_g if math.isinf(f) else z * tan_g + np.abs(z / f - 1.0) * rd
    m = rho - reach
    return m if behind is None else np.where(zeta >= 0.0, m, behind)


def lipschitz(inst: Instrument) -> float:
    """A Lipschitz constant of :func:`margin` (``behind=None``): rho is 1-Lipschitz, the reach's slope
    in zeta is tan(gamma) + R_D / F at most."""
    det = inst.detector
    return 1.0 + math.tan(math.radians(det.field_half_angle_deg)) + det.pupil_radius_m / det.focus_distance_m


def clearance_bounds(inst: Instrument, cell, n: int = 15, gap_abs: float = 1e-7, gap_rel: float = 1e-3,
                     max_levels: int = 8):
    """(lower, upper, deepest point): rigorous bounds on the minimum of :func:`margin` over the
    source disc (its part in front of the pupil), by a grid refined where the minimum can be.

    Squares of side s cover the disc; each square's centre is within s/sqrt(2) of every point of
    the square, so (margin being L-Lipschitz) a square whose centre's margin exceeds the best value
    found on the disc by more than L s/sqrt(2) cannot hold the minimum; the others are split into
    n x n squares, until the bounds are within ``gap_abs`` + ``gap_rel`` |upper| of each other. The
    best value at a centre inside the disc is the upper bound, the smallest centre value minus
    L s/sqrt(2) over the last squares the lower bound."""
    g = optics.source_geometry(inst, *cell)
    R = g.radius_m
    L = lipschitz(inst)
    k = (np.arange(n) - (n - 1) / 2.0) / n                 # sub-square centres of a unit square
    cu, cv, side = np.zeros(1), np.zeros(1), 2.0 * R       # one square holding the disc
    upper, best, lower = math.inf, None, -math.inf
    for _ in range(max_levels):
        U = (cu[:, None, None] + side * k[None, :, None] + 0.0 * k[None, None, :]).ravel()
        V = (cv[:, None, None] + 0.0 * k[None, :, None] + side * k[None, None, :]).ravel()
        side /= n
        keep = np.hypot(U, V) <= R + side / math.sqrt(2.0)        # squares that reach the disc
        U, V = U[keep], V[keep]
        x = g.centre + U[:, None] * g.s + V[:, None] * g.t
        m = margin(inst, x, behind=None)
        mu = np.where(np.hypot(U, V) <= R, margin(inst, x), np.inf)
        j = int(np.argmin(mu))
        if mu[j] < upper:
            upper, best = float(mu[j]), x[j]
        slack = L * side / math.sqrt(2.0)
        live = m - slack <= upper
        assert live.sum() <= 200_000, "too many squares to refine"
        cu, cv = U[live], V[live]
        lower = float(m[live].min() - slack) if live.any() else upper
        if upper - lower <= gap_abs + gap_rel * abs(upper):
            break
    return min(lower, upper), upper, best


def witness_ray(inst: Instrument, x: np.ndarray):
    """A ray of the detector's bundle through the point x of the bundle (pupil and field points in
    unit-disc coordinates), built from the construction in :func:`margin`."""
    det = inst.detector
    geo = optics.detector_geometry(inst)
    rel = x - geo.centre
    zeta = rel @ geo.axis
    xr = rel - zeta * geo.axis
    rho = np.linalg.norm(xr)
    e = np.array([xr @ geo.s, xr @ geo.t]) / rho if rho > 0 else np.array([1.0, 0.0])
    rd, tan_g, f = det.pupil_radius_m, geo.tan_field, geo.focus_m
    if math.isinf(f):
        s = rho / (rd + zeta * tan_g)
        pupil, field = s * e, s * e
    else:
        t = zeta / f
        s = rho / (abs(1.0 - t) * rd + t * f * tan_g)
        pupil, field = (s * e if t <= 1.0 else -s * e), s * e
    assert s <= 1.0 + 1e-12, "the point is not in the bundle"
    o, d, _ = optics.detector_ray(NumpyOps, geo, (pupil[0], pupil[1]), (field[0], field[1]))
    return np.array([float(v) for v in o]), np.array([float(v) for v in d])


def ray_meets_disc(inst: Instrument, cell, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Rays (o, d: (n, 3)) that cross the source disc before the sample plane."""
    g = optics.source_geometry(inst, *cell)
    o, d = np.atleast_2d(o), np.atleast_2d(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((g.centre - o) @ g.axis) / (d @ g.axis)
    p = o + t[:, None] * d
    t_plane = -o[:, 2] / d[:, 2]
    return (t > 0) & (t < t_plane) & (np.linalg.norm(p - g.centre, axis=1) <= g.radius_m * (1 + 1e-12))


def probe_rays(inst: Instrument, n_random: int = 100_000, n_rim: int = 64, seed: int = 5):
    """Rim x rim rays of the pupil and field discs plus random ones."""
    geo = optics.detector_geometry(inst)
    ang = np.linspace(0, 2 * np.pi, n_rim, endpoint=False)
    rim = np.stack([np.cos(ang), np.sin(ang)], 1)
    rng = np.random.default_rng(seed)

    def disc(n):
        r, a = np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
        return np.stack([r * np.cos(a), r * np.sin(a)], 1)
    pu = np.concatenate([np.repeat(rim, n_rim, 0), disc(n_random)])
    fi = np.concatenate([np.tile(rim, (n_rim, 1)), disc(n_random)])
    o, d, _ = optics.detector_ray(NumpyOps, geo, (pu[:, 0], pu[:, 1]), (fi[:, 0], fi[:, 1]))
    return np.stack([np.broadcast_to(v, (len(pu),)) for v in o], 1), np.stack(d, 1)


# ----------------------------------------------------------------------------------------------
# the test against the independent account
# ----------------------------------------------------------------------------------------------

#: name: (instrument, range of eps (deg) and half-width of beta about 180 deg of the cells near the line of sight)
INSTRUMENTS = {
    "focused": (NEAR, (83.0, 89.8), 3.0),
    "angular field": (NEAR.with_changes(detector={"focus_m": math.inf}), (83.0, 89.8), 3.0),
    "focus before the sample, field < pupil": (NEAR.with_changes(detector={"focus_m": 0.4, "pupil_radius_m": 0.01}),
                                               (83.0, 89.8), 3.0),
    "pinhole": (NEAR.with_changes(detector={"pupil_radius_m": 0.0, "field_half_angle_deg": 0.5}), (83.0, 89.8), 3.0),
    "small source": (SPECK, (88.0, 89.6), 0.5),
}


@pytest.mark.parametrize("name", list(INSTRUMENTS))
def test_clearance_is_the_minimum_over_the_disc(name):
    """sight_clearance lies between rigorous bounds of the independent margin's minimum over the
    disc, and where it is negative a real ray of the bundle crosses the disc."""
    inst, eps_range, half_beta = INSTRUMENTS[name]
    rng = np.random.default_rng(11)
    # cells around the line of sight (eps = 89 deg, beta 180) and two far from it
    eps = rng.uniform(*eps_range, 20)
    cells = [(math.tan(math.radians(e)), float(b)) for e, b in zip(eps, 180.0 + rng.uniform(-half_beta, half_beta, 20))]
    cells += [(1.0, 0.0), (12.0, 90.0)]
    exact = optics.sight_clearance(inst, cells)
    n_blocked = 0
    for cell, ex in zip(cells, exact):
        lower, upper, deepest = clearance_bounds(inst, cell)
        assert lower - 1e-12 <= ex <= upper + 1e-12, (cell, lower, ex, upper)
        assert upper - lower <= 1e-7 + 1e-3 * abs(upper) or upper == math.inf
        if upper < 0.0:
            o, d = witness_ray(inst, deepest)
            assert ray_meets_disc(inst, cell, o, d).all(), cell
            n_blocked += 1
    assert 0 < n_blocked < len(cells), "the cells must include blocked and clear ones"


def test_a_point_source_and_a_disc_behind_the_pupil_never_block():
    assert np.isinf(optics.sight_clearance(NEAR.with_changes(source={"radius_m": 0.0}), [(9.6, 180.0)])).all()
    # a source farther than the detector, right behind it: behind the pupil plane
    far = PORTABLE.with_changes(source={"distance_m": 3.0, "radius_m": 0.04})
    assert not optics.source_blocks_view(far, [(math.tan(math.radians(89.0)), 180.0)]).any()


def test_the_pre_filter_never_clears_a_blocking_disc():
    """source_blocks_view (bounding-sphere pre-filter, then the exact clearance) flags exactly the
    cells whose exact clearance is <= the tolerance, over a sweep through and beyond the edge."""
    for inst in (NEAR, SPECK, INSTRUMENTS["angular field"][0]):
        cells = [(float(t), float(b)) for t in np.linspace(4.0, 80.0, 60) for b in np.linspace(150.0, 210.0, 31)]
        exact = optics.sight_clearance(inst, cells) <= optics.SIGHT_TOL_M
        assert exact.any() and not exact.all()
        assert (optics.source_blocks_view(inst, cells) == exact).all()


@pytest.mark.parametrize("inst, cell, blocked", EDGE_CELLS)
def test_edge_cells_against_rays(inst, cell, blocked):
    """Near the edge: a blocked cell has a ray of the bundle that crosses the disc; a clear one has
    a positive lower bound of its clearance, and none of 4096 rim x rim and 10^5 random rays (the
    kind of probes the old checks traced) crosses the disc."""
    assert bool(optics.source_blocks_view(inst, [cell])[0]) is blocked
    lower, upper, deepest = clearance_bounds(inst, cell)
    assert abs(upper) < 2.5e-3, "a cell near the edge"
    if blocked:
        assert upper < 0.0
        o, d = witness_ray(inst, deepest)
        assert ray_meets_disc(inst, cell, o, d).all()
    else:
        assert lower > 0.0
        o, d = probe_rays(inst)
        assert not ray_meets_disc(inst, cell, o, d).any()


# ----------------------------------------------------------------------------------------------
# every backend and the design's pre-filter give the same answer, cell by cell
# ----------------------------------------------------------------------------------------------

def design_refuses(inst: Instrument, cell) -> bool:
    from roadgonio.design.feasibility import check_geometry
    f = check_geometry(inst, [cell])
    assert f.ok or f.kind == "line_of_sight", f
    return not f.ok


@pytest.mark.parametrize("inst, cell, blocked", EDGE_CELLS)
def test_backends_and_design_agree_cell_by_cell(inst, cell, blocked, tmp_path):
    from roadgonio.surface.model import RoadModel
    model = RoadModel.lambert()
    got = {name: backend_refuses(name, inst, cell, model, tmp_path)
           for name in ("quadrature", "numpy-mc", "reference", "numpy-mc-mesh")}
    got["design"] = design_refuses(inst, cell)
    assert got == {k: blocked for k in got}
