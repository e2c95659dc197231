"""Interpolation in the r-table, as weights on its cells (so that luminance is linear in r).

Rule (EN 13201-3:2015 clause 5.5, as CIE 140:2000 prescribes for the r-table): quadratic
(three-point Lagrange) interpolation in beta and in tan gamma. The three nodes are the two that
bracket the value and the next nearest one; a value on a node takes that node alone. The table is
interpolated along beta within each of the three tan rows, then along tan. ``linear`` (two
bracketing nodes in each direction) is available for comparison.

Blank cells (not measured) are never used: in a row, the stencil is taken among the tabulated
beta values only. A (beta, tan) that falls outside the tabulated region of a stencil row (for the
CIE tables: large beta at tan >= 5.5), or beyond tan = 12, has no r: :func:`r_weights` returns no
weights and the caller neglects that contribution and counts it (such directions carry little
light on a road: a luminaire at tan gamma > 5.5 and beta > 40 deg stands more than 40 m to the side).
When a quadratic stencil row is outside, the linear (two-row) stencil is tried before giving up.
"""
from __future__ import annotations

import numpy as np

from roadgonio.surface.rtable import RTable

_TOL = 1e-9


def _lagrange(nodes: np.ndarray, x: float) -> np.ndarray:
    w = np.ones(len(nodes))
    for k in range(len(nodes)):
        for m in range(len(nodes)):
            if m != k:
                w[k] *= (x - nodes[m]) / (nodes[k] - nodes[m])
    return w


def stencil_1d(nodes: np.ndarray, x: float, order: str = "quadratic") -> tuple[np.ndarray, np.ndarray] | None:
    """(indices into ``nodes``, weights) for the value at ``x``; None outside [nodes[0], nodes[-1]].
    ``nodes`` increasing."""
    n = len(nodes)
    if n == 0 or x < nodes[0] - _TOL or x > nodes[-1] + _TOL:
        return None
    hit = np.nonzero(np.abs(nodes - x) <= _TOL)[0]
    if len(hit):
        return hit[:1], np.ones(1)
    if n == 1:
        return None
    i = int(np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, n - 2))
    if order == "linear" or n == 2:
        idx = np.array([i, i + 1])
    else:
        lo_ok, hi_ok = i - 1 >= 0, i + 2 <= n - 1
        if lo_ok and (not hi_ok or x - nodes[i - 1] <= nodes[i + 2] - x):
            idx = np.array([i - 1, i, i + 1])
        elif hi_ok:
            idx = np.array([i, i + 1, i + 2])
        else:
            idx = np.array([i, i + 1])
    return idx, _lagrange(nodes[idx], x)


def _try(table: RTable, beta_deg: float, tan_g: float, order: str):
    rows = stencil_1d(table.tan_eps, tan_g, order)
    if rows is None:
        return None
    cells, weights = [], []
    for i, wi in zip(*rows):
        valid = np.nonzero(table.mask[i])[0]
        st = stencil_1d(table.beta_deg[valid], beta_deg, order)
        if st is None:
            return None
        for j, wj in zip(*st):
            cells.append(i * table.r.shape[1] + valid[j])
            weights.append(wi * wj)
    return np.asarray(cells, dtype=np.int64), np.asarray(weights)


def r_weights(table: RTable, beta_deg: float, tan_g: float, order: str = "quadratic"):
    """(flat cell indices into ``table.r``, weights) with r(beta, tan) = sum w r[cell]; None where
    the table has no value (module docstring)."""
    got = _try(table, beta_deg, tan_g, order)
    if got is None and order == "quadratic":
        got = _try(table, beta_deg, tan_g, "linear")
    return got


def r_value(table: RTable, beta_deg: float, tan_g: float, order: str = "quadratic") -> float:
    """Interpolated r (sr^-1), NaN where the table has no value."""
    got = r_weights(table, beta_deg, tan_g, order)
    if got is None:
        return float("nan")
    cells, w = got
    return float(np.dot(table.r.ravel()[cells], w))
