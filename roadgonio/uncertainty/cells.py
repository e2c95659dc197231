"""The cells of an uncertainty run (the standard CIE region or all cells) and the Q0 weights (CIE 144)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roadgonio.errors import InputError
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
from roadgonio.uncertainty.spec import CELL_SETS

# ----------------------------------------------------------------------------------------------
# Cells, Q0 weights
# ----------------------------------------------------------------------------------------------

def standard_mask() -> np.ndarray:
    """Tabulated cells of the CIE standard tables (:func:`roadgonio.surface.rtable.standard_mask`)."""
    from roadgonio.surface.rtable import standard_mask as mask
    return mask()


def standard_q0_weights() -> np.ndarray:
    """Weights w (29 x 20) with Q0 = sum w r over the standard tabulated region
    (:func:`roadgonio.surface.rtable.q0_weights`, the one definition of Q0)."""
    from roadgonio.surface.rtable import q0_weights
    return q0_weights(standard_mask())


@dataclass(frozen=True)
class CellSet:
    """The cells of the table that are computed, with their grid indices."""

    tan_eps: np.ndarray
    beta_deg: np.ndarray
    ii: np.ndarray
    jj: np.ndarray
    which: str

    @classmethod
    def make(cls, which: str = "standard") -> "CellSet":
        if which not in CELL_SETS:
            raise InputError(f"unknown cell set {which!r}; expected standard or all", field="cells")
        mask = standard_mask() if which == "standard" else np.ones((len(TAN_EPS_GRID), len(BETA_GRID_DEG)), bool)
        ii, jj = np.nonzero(mask)
        return cls(TAN_EPS_GRID[ii].copy(), BETA_GRID_DEG[jj].copy(), ii, jj, which)

    def __len__(self) -> int:
        return len(self.ii)

    def index(self, tan_eps: float, beta_deg: float) -> int:
        k = np.nonzero((np.abs(self.tan_eps - tan_eps) < 1e-9) & (np.abs(self.beta_deg - beta_deg) < 1e-9))[0]
        if len(k) == 0:
            raise InputError(f"cell (tan eps {tan_eps:g}, beta {beta_deg:g}) not in the cell set", field="cells")
        return int(k[0])

    def to_grid(self, values: np.ndarray) -> np.ndarray:
        g = np.full((len(TAN_EPS_GRID), len(BETA_GRID_DEG)), np.nan)
        g[self.ii, self.jj] = values
        return g


