"""Which cells to compute: THE one parser of a cell selection (``--cells`` of every command, the
``cells`` argument of every API function).

A selection is one of:

* ``"all"``: the 580 cells of the standard grid (docs/conventions.md section 2), row by row;
* ``"table"``: the cells tabulated in the sample's r-table (needs the table);
* ``"extremes"``: :data:`EXTREME_CELLS`, the validation set (tan eps 0 and 12, beta 0 and 180, the
  specular peak tan 4-12 x beta 0-10, mid cells);
* a text ``"T:B,T:B,..."`` (tan eps : beta in degrees), e.g. ``"12:0,12:2,4:0"``;
* a sequence of ``(tan_eps, beta_deg)`` pairs.

An empty selection is an error (never a silent default). ``on_grid=True`` (tables, datasets,
CSV outputs) requires every cell to be a node of the standard grid.
"""
from __future__ import annotations

import math

import numpy as np

from roadgonio.errors import InputError
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID, nearest_grid_node

#: The cells ``roadgonio validate`` checks by default.
EXTREME_CELLS: tuple[tuple[float, float], ...] = (
    (0.0, 0.0), (0.0, 180.0), (12.0, 0.0), (12.0, 180.0),
    (12.0, 2.0), (12.0, 10.0), (8.0, 0.0), (8.0, 5.0), (4.0, 0.0), (4.0, 10.0),
    (2.0, 90.0), (1.0, 45.0),
)
#: The names a selection may be given by.
NAMED = ("all", "table", "extremes")
#: Cells that differ by less than this are the same cell (grid matching, journals).
CELL_TOL = 1e-9


def full_grid_cells() -> list[tuple[float, float]]:
    """All 580 (tan eps, beta) cells of the standard grid, row by row."""
    return [(float(t), float(b)) for t in TAN_EPS_GRID for b in BETA_GRID_DEG]


def on_the_grid(tan_eps: float, beta_deg: float) -> bool:
    return grid_index(tan_eps, beta_deg) is not None


def check_cell(tan_eps, beta_deg, field: str = "cells", beta_field: str | None = None) -> tuple[float, float]:
    """One cell as floats: tan eps >= 0 and 0 <= beta <= 180 deg, finite numbers (not bool); errors
    name ``field`` (and ``beta_field`` for beta when the two are given apart)."""
    beta_field = beta_field or field
    for v, what, f in ((tan_eps, "tan eps", field), (beta_deg, "beta", beta_field)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise InputError(f"expected a number for {what}, got {v!r}", field=f)
    t, b = float(tan_eps), float(beta_deg)
    if not (math.isfinite(t) and t >= 0.0):
        raise InputError(f"expected a finite tan eps >= 0, got {tan_eps!r}", field=field)
    if not (math.isfinite(b) and 0.0 <= b <= 180.0):
        raise InputError(f"expected a finite beta, 0 <= beta <= 180 deg, got {beta_deg!r}", field=beta_field)
    return t, b


def select_cells(selection, table=None, *, on_grid: bool = False, field: str = "cells") -> list[tuple[float, float]]:
    """The cells of ``selection`` (module docstring) as ``[(tan_eps, beta_deg), ...]``; ``table`` is the
    sample's r-table (:class:`~roadgonio.surface.rtable.RTable`, for ``"table"``). Errors name
    ``field`` (the option or argument)."""
    if isinstance(selection, str):
        text = selection.strip()
        if text == "all":
            return full_grid_cells()
        if text == "extremes":
            cells = list(EXTREME_CELLS)
        elif text == "table":
            if table is None:
                raise InputError("'table' needs a sample that is an r-table (a bundled table name, a .csv/.rtb file, "
                                 "an RTable)", field=field)
            cells = list(table.cells)
            if not cells:
                raise InputError(f"the r-table {table.name!r} has no tabulated cell", field=field)
            return cells
        elif not text:
            raise InputError(f"expected {', '.join(NAMED)} or TAN:BETA[,TAN:BETA...], got an empty selection",
                             field=field)
        else:
            cells = []
            for item in text.split(","):
                parts = item.strip().split(":")
                try:
                    if len(parts) != 2:
                        raise ValueError
                    t, b = float(parts[0]), float(parts[1])
                except ValueError:
                    raise InputError(f"expected cells as TAN:BETA[,TAN:BETA...] (e.g. 12:0,4:2) or one of "
                                     f"{', '.join(NAMED)}; got {item.strip()!r}", field=field) from None
                cells.append(check_cell(t, b, field))
    else:
        try:
            pairs = list(selection)
        except TypeError:
            raise InputError(f"expected {', '.join(NAMED)}, a text TAN:BETA,... or (tan_eps, beta) pairs, "
                             f"got {type(selection).__name__}", field=field) from None
        cells = []
        for c in pairs:
            try:
                t, b = c
            except (TypeError, ValueError):
                raise InputError(f"expected (tan_eps, beta) pairs, got {c!r}", field=field) from None
            cells.append(check_cell(t, b, field))
        if not cells:
            raise InputError("expected at least one cell, got an empty list", field=field)
    seen: set[tuple[float, float]] = set()
    for t, b in cells:
        key = (round(float(t), 9), round(float(b), 9))
        if key in seen:
            # it was computed twice and counted twice in the summary (user audit, session 19)
            raise InputError(f"cell {t:g}:{b:g} is given twice; expected each cell once", field=field)
        seen.add(key)
    if on_grid:
        off = [c for c in cells if not on_the_grid(*c)]
        if off:
            raise InputError(f"cell ({off[0][0]:g}, {off[0][1]:g}) is not on the CIE grid (tan eps "
                             f"{', '.join(f'{v:g}' for v in TAN_EPS_GRID)}; beta {', '.join(f'{v:g}' for v in BETA_GRID_DEG)})",
                             field=field)
    return cells


def cells_text(cells, limit: int = 6) -> str:
    """Cells as a message lists them: 'T:B, T:B, ...' (the ``--cells`` syntax), the first ``limit``
    of them and ', ...' when there are more (the message says how many)."""
    cells = list(cells)
    return ", ".join(f"{t:g}:{b:g}" for t, b in cells[:limit]) + (", ..." if len(cells) > limit else "")


def grid_index(tan_eps: float, beta_deg: float) -> tuple[int, int] | None:
    """The (row, column) of a cell on the CIE grid, None for a cell off the grid."""
    i, j, off = nearest_grid_node(tan_eps, beta_deg)
    return (i, j) if off < CELL_TOL else None
