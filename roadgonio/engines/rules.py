"""The product Gauss rules over the instrument's discs (docs/conventions.md section 4), shared by the
quadrature backend, eta of the absolute calibration and the design's metrics, so that none of them
depends on a backend module for them.

* :func:`disc_rule`: a product rule on the unit disc, exact in its boundary, refined separately in
  two directions, optionally crowded towards a boundary point;
* :func:`map_disc_rule`: a product rule on the unit disc cut along the lines of a sensitivity map's
  pixel centres, where its bilinear interpolation has its kinks, so that every piece is smooth;
* :func:`detector_nodes`: the detected rays of the pupil x field product rule (the field's rule cut
  along the map's lines when the detector has a sensitivity map): their hit points on the sample
  plane, their directions and normalised weights (etendue x k_D x rule), and
  :class:`DetectorNodes`, the same cached by levels (the nodes do not depend on the cell).
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np

from roadgonio.arrays import NumpyOps
from roadgonio.errors import GeometryError
from roadgonio.instrument import optics

#: Gauss-Legendre orders of one direction of a disc rule, by level.
ORDERS = (1, 2, 3, 4, 6, 8, 11, 16, 22, 32, 45, 64, 90, 128, 180, 256)


@lru_cache(maxsize=None)
def gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes and weights of the n-point Gauss-Legendre rule on [-1, 1] (cached)."""
    z, w = np.polynomial.legendre.leggauss(n)
    return z, w


@lru_cache(maxsize=512)
def disc_rule(level_v: int, level_h: int, focus: complex = 0j) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Product rule on the unit disc: nodes (x, y) and weights summing to 1.

    The disc is the image of the rectangle (s, phi) in [-1, 1] x [-pi/2, pi/2] under
    ``(x, y) = (s cos phi, sin phi)`` (area element ``cos^2 phi ds dphi``): a smooth map onto the
    disc that is exact in its boundary (no mask of a square), with Gauss-Legendre nodes in phi
    (``ORDERS[level_v]``, the y direction, crowded towards y = +-1) and in s (``ORDERS[level_h]``,
    the x direction). The two directions are refined independently, so an integrand that varies
    along one axis only (the long axis of a grazing footprint) costs few nodes across it.
    ``level_v < 0`` is the centre alone (a disc of radius 0).

    ``focus`` (complex c, ``|c| < 1``) crowds the nodes towards the boundary point ``c / |c|``:
    the rule is built along a rotated axis v = c/|c| with ``v = (sin phi + b) / (1 + b sin phi)``,
    ``b = |c|`` (a 1-D Moebius map of [-1, 1] onto itself, so the rule's centre goes to c and the
    node density near the boundary point grows by ``(1 + b) / (1 - b)``), and the chord
    coordinate ``x = s sqrt(1 - v^2)``. The map stays smooth (analytic) and onto the disc, exact in
    the boundary; the weights carry its Jacobian ``(1 - b^2)^(3/2) cos^2 phi / (1 + b sin phi)^3``.
    """
    if level_v < 0 or level_h < 0:
        x, y, w = np.zeros(1), np.zeros(1), np.ones(1)
    else:
        if max(level_v, level_h) >= len(ORDERS):
            raise ValueError(f"disc rule level beyond the table ({len(ORDERS) - 1})")
        zv, wv = gauss_legendre(ORDERS[level_v])
        zh, wh = gauss_legendre(ORDERS[level_h])
        phi = 0.5 * math.pi * zv
        c, sn = np.cos(phi), np.sin(phi)
        b = abs(complex(focus))
        den = 1.0 + b * sn
        v = (sn + b) / den                       # along the focus axis
        half = math.sqrt(1.0 - b * b) * c / den  # half chord sqrt(1 - v^2)
        jac = (1.0 - b * b) ** 1.5 * c * c / den ** 3
        xl = (half[:, None] * zh[None, :]).ravel()
        yl = np.repeat(v, zh.size)
        w = ((wv * jac)[:, None] * wh[None, :]).ravel()
        if b > 0.0:
            # rotate the local +y axis onto the focus direction
            ux, uy = complex(focus).real / b, complex(focus).imag / b
            x, y = xl * uy + yl * ux, -xl * ux + yl * uy
        else:
            x, y = xl, yl
        w = w / w.sum()       # the rule of the constant: exact up to rounding (and the focus map)
    x, y, w = np.array(x, dtype=np.float64), np.array(y, dtype=np.float64), np.array(w, dtype=np.float64)
    for arr in (x, y, w):
        arr.setflags(write=False)
    return x, y, w


#: A sensitivity map whose kink lines cut the field disc into more pieces than this is integrated
#: over the whole disc (each piece costs at least 2 x 2 nodes, multiplied by the pupil's and the
#: source's: a smooth 33 x 33 map's 1,472 pieces did not converge within the quadrature's
#: ``max_evals`` where the whole-disc rule's estimate was within 2.5e-6 of the reference).
MAP_PIECES_MAX = 512
#: Breakpoints closer than this (in x = sin phi) are one.
_SAME_BREAK = 1e-13


@lru_cache(maxsize=64)
def map_pieces(xlines: tuple[float, ...], ylines: tuple[float, ...]) -> tuple[tuple[float, float, tuple[float, ...]], ...]:
    """The pieces of the unit disc cut along the lines ``x = c`` (``xlines``) and ``y = d``
    (``ylines``), as strips ``(phi_a, phi_b, inner)`` with ``x = sin phi``: between
    two neighbouring breakpoints (the x lines and the abscissae where the circle crosses a y line) no
    line ends inside the strip, the y lines ``inner`` cross it from side to side, and they cut it into
    ``len(inner) + 1`` pieces bounded by ``y = -cos phi``, the lines and ``y = cos phi``."""
    xl = np.asarray(xlines, dtype=np.float64)
    yl = np.asarray(ylines, dtype=np.float64)
    yl = yl[np.abs(yl) < 1.0]
    cross = np.sqrt(np.clip(1.0 - yl * yl, 0.0, None))
    br = np.unique(np.concatenate([[-1.0, 1.0], xl, cross, -cross]))
    br = br[(br >= -1.0) & (br <= 1.0)]
    keep = np.concatenate([[True], np.diff(br) > _SAME_BREAK])
    phi = np.arcsin(br[keep])
    out = []
    for a, b in zip(phi[:-1], phi[1:]):
        h = math.cos(0.5 * (a + b))
        inner = tuple(float(d) for d in yl if -h < d < h)
        out.append((float(a), float(b), inner))
    return tuple(out)


@lru_cache(maxsize=128)
def map_disc_rule(level_v: int, level_h: int, xlines: tuple[float, ...],
                  ylines: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Product rule on the unit disc cut into the pieces of :func:`map_pieces` (a map's kink lines,
    :meth:`~roadgonio.instrument.profiles.FieldMap.kink_lines`), nodes (x, y) in the map's
    coordinates and weights summing to 1.

    A map is bilinear between its pixel centres and flat beyond the outermost ones: its slope jumps
    on those lines (where it is not linear across them), where a rule over the whole disc converges only algebraically and its successive
    levels can agree by chance (audit of session 27). On each piece here the map is one bilinear
    function and the rest of the integrand is as smooth as on the whole disc, so the rule converges
    spectrally again. Each strip ``x = sin phi`` gets ``ORDERS[level_v]`` Gauss-Legendre nodes in phi
    (``dx = cos phi dphi``, no square-root end point at the rim), each of its pieces
    ``ORDERS[level_h]`` nodes in y between its two bounds (a line or the circle ``y = +-cos phi``).
    """
    if max(level_v, level_h) >= len(ORDERS):
        raise ValueError(f"disc rule level beyond the table ({len(ORDERS) - 1})")
    zv, wv = gauss_legendre(ORDERS[level_v])
    zh, wh = gauss_legendre(ORDERS[level_h])
    xs, ys, ws = [], [], []
    for a, b, inner in map_pieces(tuple(xlines), tuple(ylines)):
        phi = a + 0.5 * (b - a) * (zv + 1.0)
        c = np.cos(phi)
        wx = wv * 0.5 * (b - a) * c                      # weight of x = sin phi
        bounds = [-c] + [np.full_like(c, d) for d in inner] + [c]
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            half = 0.5 * (hi - lo)
            ys.append((lo[:, None] + half[:, None] * (zh[None, :] + 1.0)).ravel())
            xs.append(np.repeat(np.sin(phi), zh.size))
            ws.append(((wx * half)[:, None] * wh[None, :]).ravel())
    x, y, w = (np.concatenate(v) for v in (xs, ys, ws))
    w = w / w.sum()
    for arr in (x, y, w):
        arr.setflags(write=False)
    return x, y, w


def field_rule(det: optics.DetectorGeometry, level_v: int, level_h: int,
               focus: complex = 0j) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The field disc's rule of a detector, in field-disc coordinates (along its s, t axes): with a
    sensitivity map that has kinks, :func:`map_disc_rule` on its kink lines (no focus: its pieces
    follow the map), turned from the map's axes to the field's; otherwise :func:`disc_rule`."""
    lines = map_kinks(det)
    if lines is None or level_v < 0 or level_h < 0:
        return disc_rule(level_v, level_h, focus)
    mx, my, w = map_disc_rule(level_v, level_h, *lines)
    m = np.array(det.map_axes, dtype=np.float64).reshape(2, 2)     # field -> map
    inv = np.linalg.inv(m)
    return inv[0, 0] * mx + inv[0, 1] * my, inv[1, 0] * mx + inv[1, 1] * my, w


def map_kinks(det: optics.DetectorGeometry) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    """The kink lines of the detector's sensitivity map (map coordinates) along which its field rule
    is cut, or None: no map, one without kinks (uniform), or one whose lines cut the disc into more
    than :data:`MAP_PIECES_MAX` pieces (the rule over the whole disc is used, and it is no bound:
    :func:`map_unsplit`)."""
    if det.kd_map is None:
        return None
    xs, ys = det.kd_map.kink_lines()
    if not (xs or ys) or map_piece_count(xs, ys) > MAP_PIECES_MAX:
        return None
    return xs, ys


def map_piece_count(xlines: tuple[float, ...], ylines: tuple[float, ...]) -> int:
    """Number of pieces of :func:`map_pieces`."""
    return sum(len(inner) + 1 for _, _, inner in map_pieces(tuple(xlines), tuple(ylines)))


def map_unsplit(det: optics.DetectorGeometry) -> bool:
    """Whether the detector's sensitivity map has kinks that its field rule does not follow (too many
    pieces, :func:`map_kinks`): across them a product rule's successive levels can agree by chance."""
    return det.kd_map is not None and any(det.kd_map.kink_lines()) and map_kinks(det) is None


def field_rule_size(det: optics.DetectorGeometry, level_v: int, level_h: int) -> int:
    """Number of nodes of :func:`field_rule`."""
    lines = map_kinks(det)
    if lines is None or level_v < 0 or level_h < 0:
        return rule_size(level_v, level_h)
    return len(map_disc_rule(level_v, level_h, *lines)[2])


def rule_size(level_v: int, level_h: int) -> int:
    """Number of nodes of a disc rule."""
    return 1 if level_v < 0 or level_h < 0 else ORDERS[level_v] * ORDERS[level_h]


def detector_nodes(det: optics.DetectorGeometry, lp: tuple[int, int], lf: tuple[int, int], fp: complex = 0j,
                   ff: complex = 0j) -> dict[str, Any]:
    """The detected rays of the pupil rule ``disc_rule(*lp, fp)`` x the field rule
    ``field_rule(det, *lf, ff)`` (every pupil node with every field node, pupil-major): ``x``, ``y`` their
    hits on the sample plane, ``wo`` minus their directions (towards the detector), ``w`` their
    weights (etendue x k_D x rule) normalised to sum 1, and the node counts ``np``, ``nf``."""
    px, py, wp = disc_rule(*lp, fp)
    fx, fy, wf = field_rule(det, *lf, ff)
    PX = np.repeat(px, fx.size)
    PY = np.repeat(py, fx.size)
    FX = np.tile(fx, px.size)
    FY = np.tile(fy, px.size)
    W = np.repeat(wp, fx.size) * np.tile(wf, px.size)
    o, d, wgt = optics.detector_ray(NumpyOps, det, (PX, PY), (FX, FY))
    x, y, valid = optics.hit_plane(NumpyOps, o, d)
    if not np.all(valid):   # excluded by check_detector; kept as a guard
        raise GeometryError("some detected rays do not reach the sample plane")
    wd = W * wgt
    return {"x": x, "y": y, "wo": (-d[0], -d[1], -d[2]), "w": wd / wd.sum(), "np": px.size, "nf": fx.size}


class DetectorNodes:
    """:func:`detector_nodes` of one detector, cached by levels and focus (cleared when it holds
    more than ``limit`` rules)."""

    def __init__(self, det: optics.DetectorGeometry, limit: int = 64):
        self.det = det
        self.limit = int(limit)
        self._cache: dict[tuple, dict[str, Any]] = {}

    def __call__(self, lp: tuple[int, int], lf: tuple[int, int], fp: complex = 0j, ff: complex = 0j) -> dict[str, Any]:
        key = (tuple(lp), tuple(lf), fp, ff)
        if key not in self._cache:
            if len(self._cache) > self.limit:
                self._cache.clear()
            self._cache[key] = detector_nodes(self.det, key[0], key[1], fp, ff)
        return self._cache[key]

    def size(self, levels) -> int:
        """Number of integrand evaluations of the product rule at the six direction ``levels``
        (pupil, field, source: the disc rules' sizes, the field's by this detector's field rule)."""
        return (rule_size(levels[0], levels[1]) * field_rule_size(self.det, levels[2], levels[3])
                * rule_size(levels[4], levels[5]))
