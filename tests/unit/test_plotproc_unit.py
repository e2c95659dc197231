"""The fast table map (roadgonio.plots) drawn in this process."""
from __future__ import annotations

import numpy as np

from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
from roadgonio.plotproc import InProcess

from helpers import _pixels


def test_cell_numbers_are_drawn_in_their_cells(tmp_path):
    """The Pillow-drawn numbers sit at the cell centres: a cell with text has dark pixels at its
    centre on a light background, the blank cell has none (it is white)."""
    v = np.full((len(TAN_EPS_GRID), len(BETA_GRID_DEG)), 1.0)      # k_A = 1: near-white cells
    v[0, 0] = np.nan
    InProcess().call("table_map", v, tmp_path / "m.png", title="t", label="k")
    img = _pixels(tmp_path / "m.png")
    dark = (img.sum(axis=2) < 200)
    # the axes span 6 %..92 % of the width minus the colour bar; find the image area as the
    # bounding box of non-white, non-dark pixels is fragile, so check rows: text appears in
    # many cells, i.e. the picture has many small dark blobs inside the axes
    h, w = dark.shape
    inner = dark[int(0.1 * h):int(0.9 * h), int(0.1 * w):int(0.8 * w)]
    assert inner.mean() > 0.005
    without = np.full_like(v, 1.0)
    InProcess().call("table_map", without, tmp_path / "n.png", title="t", label="k", annotate=False)
    inner_n = (_pixels(tmp_path / "n.png").sum(axis=2) < 200)[int(0.1 * h):int(0.9 * h), int(0.1 * w):int(0.8 * w)]
    assert inner_n.mean() < inner.mean() / 5
