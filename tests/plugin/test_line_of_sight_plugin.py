"""The Mitsuba engine refuses exactly the cells the one line-of-sight test refuses, near the blocking
edge (tests/unit/test_line_of_sight.py checks the test itself and the numpy backends)."""
from __future__ import annotations

import pytest

from roadgonio.surface.model import RoadModel

from helpers import backend_refuses, line_of_sight_edge_cells


@pytest.mark.parametrize("inst, cell, blocked", line_of_sight_edge_cells())
def test_the_mitsuba_engine_agrees_cell_by_cell(inst, cell, blocked):
    assert backend_refuses("mitsuba", inst, cell, RoadModel.lambert()) is blocked
