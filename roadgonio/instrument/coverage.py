"""Which cells an instrument really measures, and how it fills the rest of its reported table
(docs/conventions.md section 4, ``[cells]``).

A portable device with fixed LEDs (COLUROUTE-like: one LED per measured cell, each with its own
calibration) measures a few cells and reports a full r-table; every other cell of its table is made
from the measured ones. ``[cells] measured = [[tan_eps, beta_deg], ...]`` names the measured cells,
``fill`` how the rest is made. Without ``[cells]`` an instrument measures every cell asked.

``fill = "tan_eps_then_beta"`` (the one rule; :func:`fill_cells`), on the logarithm of the reduced
luminance coefficient, ln r (r is smoother than q = r / cos^3 eps, and ln r keeps an interpolated
specular peak, which spans orders of magnitude within a few degrees of beta, positive and within the
range of its neighbours; linear interpolation of r itself overestimated the CIE R3 table's grazing
cells next to the peak twenty-fold):

1. **tan eps = 0 is one direction**: r(0, beta) does not depend on beta (the source is at the
   zenith), so the measured cells at tan eps = 0 (their mean if several) give the point tan eps = 0
   of every beta column.
2. **In tan eps, per measured column**: for every beta that has measured cells, ln r is interpolated
   piecewise linearly in tan eps through that column's points (with the point at tan eps = 0), and
   beyond the column's largest measured tan eps it continues along the line through its last two
   points (holding a column's end value instead overestimated R3's grazing cells at beta 25-30,
   where r falls fast with tan eps, twenty-five-fold).
3. **Then in beta, per row**: at a cell (tan eps, beta), every column gives its value at that tan
   eps, and ln r is interpolated piecewise linearly in beta between the two nearest columns (held
   constant beyond the first and last of them).

So a measured cell is reported as measured, and a table whose logarithm is linear in tan eps for every
beta and linear in beta for every tan eps (ln r = a + tan eps (b + c beta)) is reproduced exactly.
Piecewise linear interpolation is the simplest rule a device could publish; the interpolation error is part of
what such an instrument reports, and the comparison (:mod:`roadgonio.intercomparison`) shows it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from roadgonio.errors import InputError

#: Fill rules of ``[cells] fill``.
FILL_RULES = ("tan_eps_then_beta",)
#: Two tan eps (or beta) closer than this are the same row (column).
SAME_TOL = 1e-9


@dataclass(frozen=True)
class MeasuredCells:
    """``measured``: the (tan eps, beta deg) the instrument measures (None: every cell asked);
    ``fill``: the rule that makes the rest of its reported table (:data:`FILL_RULES`)."""

    measured: tuple[tuple[float, float], ...] | None = None
    fill: str = "tan_eps_then_beta"

    def __post_init__(self):
        if self.fill not in FILL_RULES:
            raise InputError(f"expected one of {', '.join(map(repr, FILL_RULES))}, got {self.fill!r}",
                             field="cells.fill")
        if self.measured is None:
            return
        if isinstance(self.measured, (str, bytes)) or not hasattr(self.measured, "__iter__"):
            raise InputError(f"expected a list of [tan_eps, beta_deg] pairs, got {self.measured!r}",
                             field="cells.measured")
        cells = []
        for k, c in enumerate(self.measured):
            ok = (not isinstance(c, (str, bytes)) and hasattr(c, "__len__") and len(c) == 2
                  and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in c))
            if not ok:
                raise InputError(f"entry {k + 1}: expected [tan_eps, beta_deg] (two numbers), got {c!r}",
                                 field="cells.measured")
            t, b = float(c[0]), float(c[1])
            if t < 0 or not 0.0 <= b <= 180.0:
                raise InputError(f"entry {k + 1}: expected tan_eps >= 0 and 0 <= beta_deg <= 180, got {[t, b]}",
                                 field="cells.measured")
            cells.append((t, b))
        if not cells:
            raise InputError("expected at least one cell (leave [cells] out for an instrument that measures "
                             "every cell)", field="cells.measured")
        if not any(abs(t) < SAME_TOL for t, _ in cells):
            raise InputError("expected a cell at tan_eps = 0 (the fill starts every beta column there)",
                             field="cells.measured")
        if len({(round(t, 9), round(b, 9)) for t, b in cells}) != len(cells):
            raise InputError("a cell is listed twice", field="cells.measured")
        object.__setattr__(self, "measured", tuple(cells))

    @property
    def all_cells(self) -> bool:
        return self.measured is None

    @property
    def is_default(self) -> bool:
        return self.measured is None and self.fill == FILL_RULES[0]

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"fill": self.fill}
        if self.measured is not None:
            d["measured"] = [list(c) for c in self.measured]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "MeasuredCells":
        if not isinstance(d, Mapping):
            raise InputError("expected a table [cells]", field="cells")
        extra = sorted(set(d) - {"measured", "fill"})
        if extra:
            raise InputError(f"unknown key(s) {', '.join(extra)}; expected some of fill, measured",
                             field=f"cells.{extra[0]}")
        m = d.get("measured")
        return cls(measured=None if m is None else m, fill=d.get("fill", FILL_RULES[0]))

    def fill_table(self, tan_eps, beta_deg, r) -> np.ndarray:
        """The reported table at the cells (tan_eps, beta_deg) (1-d arrays) from ``r``, the values at
        those same cells, of which only the measured ones are used (every measured cell must be among
        them). Without measured cells: ``r`` itself."""
        r = np.asarray(r, dtype=np.float64)
        if self.measured is None:
            return r.copy()
        t = np.asarray(tan_eps, dtype=np.float64)
        b = np.asarray(beta_deg, dtype=np.float64)
        idx = []
        for mt, mb in self.measured:
            k = np.nonzero((np.abs(t - mt) < SAME_TOL) & (np.abs(b - mb) < SAME_TOL))[0]
            if not len(k):
                raise InputError(f"the measured cell (tan eps {mt:g}, beta {mb:g}) is not among the cells "
                                 "of the table", field="cells.measured")
            idx.append(int(k[0]))
        idx = np.array(idx)
        return fill_cells(t[idx], b[idx], r[idx], t, b)


def fill_cells(tan_m, beta_m, r_m, tan_eps, beta_deg) -> np.ndarray:
    """r at the cells (tan_eps, beta_deg) from the measured (tan_m, beta_m, r_m) by the rule
    ``tan_eps_then_beta`` (module docstring). Pure numpy, float64; vectorised over the targets."""
    tan_m, beta_m, r_m = (np.asarray(a, dtype=np.float64).ravel() for a in (tan_m, beta_m, r_m))
    tan_eps = np.asarray(tan_eps, dtype=np.float64)
    beta_deg = np.asarray(beta_deg, dtype=np.float64)
    zero = np.abs(tan_m) < SAME_TOL
    if not zero.any():
        raise InputError("expected a measured cell at tan_eps = 0", field="cells.measured")
    if not np.all(r_m > 0):
        raise InputError("the fill interpolates ln r: every measured r must be positive", field="cells.measured")
    r_m = np.log(r_m)
    r0 = float(np.mean(r_m[zero]))
    cols = np.unique(np.round(beta_m[~zero], 9))
    # step 2: per column, its points in tan eps (with tan eps = 0), extended along its last segment
    tt, bb = np.broadcast_arrays(tan_eps, beta_deg)
    shape = tt.shape
    tt, bb = tt.ravel(), bb.ravel()
    if not len(cols):
        return np.exp(np.full(tt.shape, r0)).reshape(shape)
    vals = np.empty((len(cols), len(tt)))
    for j, cb in enumerate(cols):
        k = (~zero) & (np.abs(beta_m - cb) < SAME_TOL)
        o = np.argsort(tan_m[k])
        ct = np.concatenate([[0.0], tan_m[k][o]])
        cr = np.concatenate([[r0], r_m[k][o]])
        v = np.interp(tt, ct, cr)
        beyond = tt > ct[-1]
        v[beyond] = cr[-1] + (tt[beyond] - ct[-1]) * (cr[-1] - cr[-2]) / (ct[-1] - ct[-2])
        vals[j] = v
    # step 3: per cell, in beta between the columns (held beyond the first and the last)
    out = np.empty(len(tt))
    for i in range(len(tt)):
        out[i] = np.interp(bb[i], cols, vals[:, i])
    out[tt < SAME_TOL] = r0
    return np.exp(out).reshape(shape)
