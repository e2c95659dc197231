"""The per-cell preamble (roadgonio.engines.cellcheck): every backend refuses the same cells with
the same message, before it integrates anything."""
from __future__ import annotations

import math

import pytest

from roadgonio.engines import ideal_ratio, ideal_ratios, make_backend
from roadgonio.engines.cellcheck import check_cell, check_cells
from roadgonio.errors import BackendError, GeometryError
from roadgonio.instrument.config import Instrument, load_instrument
from roadgonio.surface.model import RoadModel, RoadParams

from helpers import FAST_SETTINGS, flat_mesh

LAB = load_instrument("lab")
#: A pure Phong lobe of huge exponent: 0 (underflow) at the nominal geometry of tan eps 0.
ZERO_AT_NOMINAL = RoadModel(RoadParams(k_phong=1.0, n_phong=1e5))
LAMBERT = RoadModel.lambert()
#: (instrument, model, cell, the words of the error): one cell per check.
BAD = {
    "horizon": (LAB.with_changes(source={"distance_m": 0.5, "radius_m": 0.1}), LAMBERT, (12.0, 0.0),
                "below the horizon"),
    "line of sight": (LAB.with_changes(source={"distance_m": 2.0, "radius_m": 0.03}), LAMBERT,
                      (math.tan(math.radians(88.5)), 180.0), "blocks the detector's line of sight"),
    "nominal": (LAB, ZERO_AT_NOMINAL, (0.0, 0.0), "k_A = measured/nominal is undefined"),
}
def backend(name: str, inst: Instrument, model: RoadModel, tmp_path):
    if name == "bundle":
        from roadgonio.engines.bundle import BundleBackend
        return BundleBackend(inst, model, rays=64)
    if name == "numpy-mc-mesh":
        inst = flat_mesh(tmp_path / "flat.ply", inst)
    return make_backend(name, inst, model, settings=FAST_SETTINGS[name])


def test_check_cell_returns_the_nominal_value_and_raises_in_order():
    r3 = RoadModel(RoadParams(k_diff=0.03, k_phong=2.2, n_phong=43.0))
    assert check_cell(LAB, r3, 2.0, 30.0) == ideal_ratio(r3, LAB, 2.0, 30.0)
    cells = [(2.0, 30.0), (12.0, 180.0)]
    assert (check_cells(LAB, r3, cells) == ideal_ratios(r3, LAB, cells)).all()
    for inst, model, cell, words in BAD.values():
        with pytest.raises(GeometryError, match=words):
            check_cell(inst, model, *cell)
        with pytest.raises(GeometryError, match=words):
            check_cells(inst, model, [(1.0, 0.0), cell])
    # the horizon first: a cell both below the horizon and at a zero model value
    below = LAB.with_changes(source={"distance_m": 0.5, "radius_m": 0.1})
    with pytest.raises(GeometryError, match="horizon"):
        check_cell(below, ZERO_AT_NOMINAL, 12.0, 0.0)


def test_a_clipping_beam_limit_is_refused_only_where_the_backend_cannot_model_it():
    inst = LAB.with_changes(source={"beam_half_angle_deg": 0.01})
    check_cell(inst, LAMBERT, 4.0, 0.0)                        # the numpy backends integrate the beam
    with pytest.raises(BackendError, match="the mitsuba backend does not model beam limits"):
        check_cell(inst, LAMBERT, 4.0, 0.0, models_beam=False, backend="mitsuba")
    check_cell(LAB.with_changes(source={"beam_half_angle_deg": 60.0}), LAMBERT, 4.0, 0.0, models_beam=False)


@pytest.mark.parametrize("check", list(BAD))
@pytest.mark.parametrize("name", ["quadrature", "numpy-mc", "reference", "numpy-mc-mesh", "bundle"])
def test_every_numpy_backend_refuses_with_the_same_message(name, check, tmp_path):
    inst, model, cell, words = BAD[check]
    with pytest.raises(GeometryError) as err:
        check_cell(inst, model, *cell)
    with pytest.raises(GeometryError) as got:
        backend(name, inst, model, tmp_path).compute([cell])
    # the same reason (the location may differ: the mesh backend's instrument is built here, without a file)
    assert got.value.reason == err.value.reason and words in str(got.value)
