"""The product Gauss rules over the instrument's discs (docs/conventions.md section 4), shared by the
quadrature backend, eta of the absolute calibration and the design's metrics, so that none of them
depends on a backend module for them.

* :func:`disc_rule`: a product rule on the unit disc, exact in its boundary, refined separately in
  two directions, optionally crowded towards a boundary point;
* :func:`detector_nodes`: the detected rays of the pupil x field product rule: their hit points on
  the sample plane, their directions and normalised weights (etendue x k_D x rule), and
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


def rule_size(level_v: int, level_h: int) -> int:
    """Number of nodes of a disc rule."""
    return 1 if level_v < 0 or level_h < 0 else ORDERS[level_v] * ORDERS[level_h]


def size(levels) -> int:
    """Number of integrand evaluations of the product rule at the six direction ``levels``."""
    return rule_size(levels[0], levels[1]) * rule_size(levels[2], levels[3]) * rule_size(levels[4], levels[5])


def detector_nodes(det: optics.DetectorGeometry, lp: tuple[int, int], lf: tuple[int, int], fp: complex = 0j,
                   ff: complex = 0j) -> dict[str, Any]:
    """The detected rays of the pupil rule ``disc_rule(*lp, fp)`` x the field rule
    ``disc_rule(*lf, ff)`` (every pupil node with every field node, pupil-major): ``x``, ``y`` their
    hits on the sample plane, ``wo`` minus their directions (towards the detector), ``w`` their
    weights (etendue x k_D x rule) normalised to sum 1, and the node counts ``np``, ``nf``."""
    px, py, wp = disc_rule(*lp, fp)
    fx, fy, wf = disc_rule(*lf, ff)
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
