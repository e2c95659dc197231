"""[cells] measured / fill (roadgonio/instrument/coverage.py): the instruments that measure a few cells
and fill the rest of their reported table by interpolation in tan eps then beta. Checked against
hand-computed values and the rule's exactness on tables linear in tan eps (per beta) and in beta (per
tan eps)."""
from __future__ import annotations

import numpy as np
import pytest

from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument, load_instrument
from roadgonio.instrument.coverage import MeasuredCells, fill_cells
from roadgonio.uncertainty.cells import CellSet

from tolerances import ROUND_TOL


def bilinear(t, b):
    """ln r linear in tan eps for every beta, linear in beta for every tan eps, beta-free at tan eps = 0."""
    return np.exp(-2.6 + t * (0.3 - 4e-3 * b))


def test_the_fixed_led_preset_reproduces_its_measured_cells_and_a_bilinear_table():
    inst = load_instrument("fixed-led")
    cs = CellSet.make("standard")
    truth = bilinear(cs.tan_eps, cs.beta_deg)
    noisy = truth * (1 + 0.3 * np.random.default_rng(1).standard_normal(len(cs)))   # unmeasured cells: anything
    m = np.array([cs.index(t, b) for t, b in inst.cells.measured])
    noisy[m] = truth[m]
    filled = inst.cells.fill_table(cs.tan_eps, cs.beta_deg, noisy)
    # the table whose ln r is bilinear comes back exactly, in every cell (the columns continue linearly) ...
    assert np.max(np.abs(filled / truth - 1)) <= 1e-11
    # ... and the measured cells are reported as measured, whatever the others were
    assert np.array_equal(filled[m], truth[m])
    assert len(inst.cells.measured) == 27


def test_hand_computed_fill():
    # measured (ln r): zenith 1.0; beta 0: tan 1 -> 3, tan 2 -> 5; beta 90: tan 1 -> 2
    tm, bm, rm = [0.0, 1.0, 2.0, 1.0], [0.0, 0.0, 0.0, 90.0], np.exp([1.0, 3.0, 5.0, 2.0])
    cases = {(0.0, 45.0): 1.0,          # the zenith for every beta
             (0.5, 0.0): 2.0,           # tan eps: halfway between 1 and 3
             (0.5, 90.0): 1.5,          # halfway between 1 and 2
             (1.0, 45.0): 2.5,          # then beta: halfway between 3 and 2
             (1.0, 180.0): 2.0,         # held beyond the last column
             (1.5, 45.0): 3.25,         # beta 90 continues its last segment to 2.5, beta 0 gives 4
             (3.0, 10.0): 7 - 3 * 10 / 90}  # both continue (7 and 4), then beta
    t = np.array([k[0] for k in cases])
    b = np.array([k[1] for k in cases])
    got = np.log(fill_cells(tm, bm, rm, t, b))
    assert np.allclose(got, list(cases.values()), rtol=0, atol=ROUND_TOL), dict(zip(cases, got))
    # two cells at tan eps = 0 (one direction): their mean starts every column (mutation audit 11: the
    # first of them passed every test)
    two = np.log(fill_cells([0.0, 0.0, 1.0], [0.0, 90.0, 0.0], np.exp([1.0, 2.0, 3.0]), [0.0, 0.5], [45.0, 0.0]))
    assert np.allclose(two, [1.5, 2.25], rtol=0, atol=ROUND_TOL), two
    # a column given out of order is sorted by tan eps: up, down, up again, then on along the last
    # segment (mutation audit 11: the points in the order given passed every test)
    zig = np.log(fill_cells([0.0, 3.0, 1.0, 2.0], [0.0] * 4, np.exp([0.0, 2.0, 3.0, 1.0]), [1.5, 4.0], [0.0, 0.0]))
    assert np.allclose(zig, [2.0, 3.0], rtol=0, atol=ROUND_TOL), zig
    with pytest.raises(InputError, match="positive"):
        fill_cells([0.0, 1.0], [0.0, 0.0], [1.0, 0.0], [0.5], [0.0])


def test_an_instrument_without_cells_reports_what_it_measures():
    inst = load_instrument("lab")
    assert inst.cells.all_cells and "cells" not in inst.to_dict()
    x = np.arange(1.0, 6.0)
    assert np.array_equal(inst.cells.fill_table(x, x, x), x)


@pytest.mark.parametrize("cells,msg", [
    ({"measured": [[1.0, 0.0]]}, "tan_eps = 0"),
    ({"measured": [[0.0, 0.0], [1.0]]}, "entry 2"),
    ({"measured": [[0.0, 0.0], [1.0, 200.0]]}, "beta_deg <= 180"),
    ({"measured": [[0.0, 0.0], [0.0, 0.0]]}, "twice"),
    ({"measured": [[0.0, 0.0]], "fill": "spline"}, "tan_eps_then_beta"),
    ({"measured": []}, "at least one"),
    ({"measure": [[0.0, 0.0]]}, "unknown key"),
    # mutation audit 11: each of these was accepted by a changed reader and passed every test
    ({"measured": [[0.0, 0.0], [-1.0, 0.0]]}, "tan_eps >= 0"),
    ({"measured": [[0.0, 0.0], [True, 0.0]]}, "entry 2"),
    ({"measured": [[0.0, 0.0], [float("inf"), 0.0]]}, "entry 2"),
])
def test_bad_cells_sections_are_one_line_errors(cells, msg):
    d = load_instrument("lab").to_dict()
    d["cells"] = cells
    with pytest.raises(InputError, match=msg) as e:
        Instrument.from_dict(d, path="i.toml")
    assert "i.toml" in str(e.value) and e.value.field.startswith("cells") and "\n" not in str(e.value)


def test_a_measured_cell_outside_the_table_is_an_error():
    mc = MeasuredCells(measured=((0.0, 0.0), (1.0, 7.0)))
    with pytest.raises(InputError, match="tan eps 1, beta 7"):
        mc.fill_table(np.array([0.0, 1.0]), np.array([0.0, 5.0]), np.ones(2))
