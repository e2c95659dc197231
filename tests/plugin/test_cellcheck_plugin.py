"""The Mitsuba backend refuses a horizon, a line-of-sight and a zero-nominal cell with exactly the
message of the one preamble (tests/unit/test_cellcheck.py: the numpy backends)."""
from __future__ import annotations

import math

import pytest

from roadgonio.engines import make_backend
from roadgonio.engines.cellcheck import check_cell
from roadgonio.errors import BackendError, GeometryError
from roadgonio.instrument.config import load_instrument
from roadgonio.surface.model import RoadModel, RoadParams

from helpers import FAST_SETTINGS

LAB = load_instrument("lab")
BAD = {
    "horizon": (LAB.with_changes(source={"distance_m": 0.5, "radius_m": 0.1}), RoadModel.lambert(), (12.0, 0.0)),
    "line of sight": (LAB.with_changes(source={"distance_m": 2.0, "radius_m": 0.03}), RoadModel.lambert(),
                      (math.tan(math.radians(88.5)), 180.0)),
    "nominal": (LAB, RoadModel(RoadParams(k_phong=1.0, n_phong=1e5)), (0.0, 0.0)),
}


@pytest.mark.parametrize("check", list(BAD))
def test_the_mitsuba_backend_refuses_with_the_same_message(check):
    inst, model, cell = BAD[check]
    with pytest.raises(GeometryError) as err:
        check_cell(inst, model, *cell)
    with pytest.raises(GeometryError) as got:
        make_backend("mitsuba", inst, model, settings=FAST_SETTINGS["mitsuba"]).compute([cell])
    assert str(got.value) == str(err.value)


def test_a_clipping_beam_limit_is_refused_by_the_mitsuba_backend():
    inst = LAB.with_changes(source={"beam_half_angle_deg": 0.01})
    with pytest.raises(BackendError, match="the mitsuba backend does not model beam limits"):
        make_backend("mitsuba", inst, RoadModel.lambert(), settings=FAST_SETTINGS["mitsuba"]).compute([(4.0, 0.0)])
