"""What `roadgonio correct` writes, column by column (roadgonio/correction/outputs.py): with a
backend of known k_A and SE per cell every number of correct_cells.csv and corrected_u.csv is
known in closed form. Mutation audit 10: u_measured written in sr^-1 instead of x 1e4, and the
k_A and SE columns swapped, passed every test."""
from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest

from roadgonio.correction.outputs import cells_csv, u_csv_text
from roadgonio.correction.run import correct_with_reference
from roadgonio.engines.result import CellResult
from roadgonio.errors import InputError
from roadgonio.instrument.config import load_instrument
from roadgonio.surface.model import RoadModel
from roadgonio.surface.rtable import load_table, parse_csv
from tolerances import ROUND_TOL

DIGITS_6 = 5e-6      # %.6g
DIGITS_4 = 5e-4      # %.4g
DIGITS_3 = 5e-3      # %.3g


def k_of(t, b):
    return 1.0 + 0.02 * t - 0.001 * b


def se_of(t, b):
    return 0.003 + 0.0005 * t


class Known:
    name = "known"

    def __init__(self, inst, model):
        pass

    def settings(self):
        return {"backend": self.name}

    def compute(self, cells, on_cell=None):
        out = [CellResult(t, b, k_of(t, b), se_of(t, b), 1, 0.0) for t, b in cells]
        for c in out:
            if on_cell is not None:
                on_cell(c)
        return out


@pytest.fixture(scope="module")
def corrected():
    table = load_table("R3")
    res = correct_with_reference(table, load_instrument("portable"), RoadModel.lambert(), u_measured="2%",
                                 factory=Known, progress=False)
    return table, res


def test_cells_csv_columns_in_closed_form(corrected):
    table, res = corrected
    rows = list(csv.DictReader([ln for ln in cells_csv(res).splitlines() if not ln.startswith("#")]))
    assert len(rows) == int(table.mask.sum())
    for row in rows:
        t, b = float(row["tan_eps"]), float(row["beta_deg"])
        m = table.value(t, b)
        k, se = k_of(t, b), se_of(t, b)
        rc = m / k
        assert float(row["r_measured_x1e4"]) == pytest.approx(m * 1e4, rel=DIGITS_6, abs=0.0)
        assert float(row["u_measured_x1e4"]) == pytest.approx(0.02 * m * 1e4, rel=DIGITS_4, abs=0.0)
        assert float(row["k_a"]) == pytest.approx(k, rel=DIGITS_6, abs=0.0)
        assert float(row["u_k_a_backend"]) == pytest.approx(se, rel=DIGITS_3, abs=0.0)
        assert float(row["r_corrected_x1e4"]) == pytest.approx(rc * 1e4, rel=DIGITS_6, abs=0.0)
        u = rc * math.hypot(0.02, se / k)
        assert float(row["u_corrected_x1e4"]) == pytest.approx(u * 1e4, rel=DIGITS_4, abs=0.0)
        assert float(row["u_rel_total"]) == pytest.approx(u / rc, rel=DIGITS_4, abs=0.0)


class Precise(Known):
    """k_A known to 1e-9 with an SE of 2e-7 (a converged quadrature's size)."""
    name = "precise"

    def compute(self, cells, on_cell=None):
        return [CellResult(t, b, k_of(t, b) + 1.234567891e-6 * (1 + t), PRECISE_SE, 1, 0.0) for t, b in cells]


PRECISE_SE = 2e-7
#: how much of its smallest uncertainty the rounding of a k_A written to correct_cells.csv may take
ROUNDING_SHARE = 0.01


def test_cells_csv_k_a_is_written_finer_than_its_uncertainty():
    """(user audit) k_a was written with 6 significant digits (5 decimals, rounding up to 5e-6), coarser
    than its own u_k_a_backend column (2e-7 here): the rounding stays far below the smallest u."""
    res = correct_with_reference(load_table("R3"), load_instrument("portable"), RoadModel.lambert(),
                                 u_measured="2%", factory=Precise, progress=False)
    rows = list(csv.DictReader([ln for ln in cells_csv(res).splitlines() if not ln.startswith("#")]))
    u_min = min(float(row["u_k_a_backend"]) for row in rows)
    assert u_min == pytest.approx(PRECISE_SE, rel=DIGITS_3, abs=0.0)
    worst = max(abs(float(row["k_a"]) - (k_of(float(row["tan_eps"]), float(row["beta_deg"]))
                                         + 1.234567891e-6 * (1 + float(row["tan_eps"])))) for row in rows)
    assert worst <= ROUNDING_SHARE * u_min, worst


def test_corrected_u_csv_is_u_times_1e4_in_the_table_layout(corrected):
    table, res = corrected
    u = parse_csv(u_csv_text(res), path="corrected_u.csv", quantity="u")
    for (t, b), m in zip(table.cells, table.r[table.mask]):
        k, se = k_of(t, b), se_of(t, b)
        assert u.value(t, b) == pytest.approx(m / k * math.hypot(0.02, se / k), rel=DIGITS_4, abs=0.0)


def test_corrected_table_and_its_uncertainty_in_closed_form():
    """correct_with_reference with a backend of known k_A and SE per cell and no other component:
    r_c = m / k and u(r_c) = r_c sqrt(u_m^2 + (se / k)^2) (relative uncertainties of independent
    inputs add in quadrature, GUM), written out here cell by cell. The other tests of the corrected
    u compare the files with the result object or only ask for u > 0: a u without its square root
    (r_c u_rel^2, ~100 times too small at 1 %) passed them."""
    table = load_table("R3")
    res = correct_with_reference(table, load_instrument("portable"), RoadModel.lambert(), u_measured="2%",
                                 factory=Known, progress=False)
    for (t, b), m in zip(table.cells, table.r[table.mask]):
        i, j = list(table.tan_eps).index(t), list(table.beta_deg).index(b)
        k, se = k_of(t, b), se_of(t, b)
        rc = m / k
        assert res.corrected.r[i, j] == pytest.approx(rc, rel=ROUND_TOL, abs=0.0)
        assert res.u_corrected[i, j] == pytest.approx(rc * math.hypot(0.02, se / k), rel=ROUND_TOL, abs=0.0)


def test_a_run_removes_the_earlier_runs_files_it_does_not_write(corrected, tmp_path, monkeypatch):
    """correct --no-plots into the folder of an earlier run with pictures (and the --forward surface
    pictures) left them beside the new tables, showing another correction; the writers now give
    their names to OutputGroup's replaces, as render and road do. The journals and the fit's
    checkpoint, outside the group, stay. The joint writer (--joint) replaces the same names."""
    from types import SimpleNamespace

    from roadgonio.correction import outputs
    _, res = corrected
    pictures = [outputs.FILES[k] for k in outputs.PICTURES]
    assert {"before_after.png", "correction_map.png", "residual_map.png", "correction_surface.png"} == set(pictures)
    for name in pictures + ["fit_state.json"]:
        (tmp_path / name).write_bytes(b"an earlier run's")
    (tmp_path / "forward-1").mkdir()
    (tmp_path / "forward-1" / "ka_cells.jsonl").write_text("{}\n")
    written = outputs.write_correction(res, tmp_path, plots=False)
    assert {p.name for p in tmp_path.iterdir()} == {p.name for p in written} | {"fit_state.json", "forward-1"}
    assert not set(pictures) & {p.name for p in written}

    class Refused(Exception):
        pass

    class Recorder:
        def __init__(self, out_dir, *, replaces=()):
            self.replaces = tuple(replaces)
            raise Refused(self.replaces)
    monkeypatch.setattr(outputs, "OutputGroup", Recorder)
    with pytest.raises(Refused) as got:
        outputs.write_surface_correction(SimpleNamespace(corrected=res.corrected), tmp_path, plots=False)
    assert set(got.value.args[0]) == set(outputs.FILES.values())


def test_corrected_corr_csv_names_its_table_as_corrected_u_csv_does(corrected, tmp_path):
    """The correlation file correct writes names the corrected table on its first line (as the u
    file's header does), and road's reader takes it for that table and refuses it for another."""
    from roadgonio.correction.outputs import write_correction
    from roadgonio.surface.rtable import header_line, measured_label, read_cell_correlation, read_table, u_names_table
    _, res = corrected
    write_correction(res, tmp_path, plots=False)
    head = header_line(read_table(tmp_path / "corrected.csv"))
    # the measured table by name and digest (two sites' files of one name wrote one header: user audit, session 40)
    assert head.startswith(f"R3 [{res.measured.digest()}] corrected for the aperture effect")
    assert measured_label(res.measured) == f"R3 [{res.measured.digest()}]"
    assert u_names_table(read_table(tmp_path / "corrected_u.csv", "u")) == head
    assert (tmp_path / "corrected_corr.csv").read_text().splitlines()[0] == "# correlation of the cells of " + head
    cells, c = read_cell_correlation(tmp_path / "corrected_corr.csv", table=head)
    assert len(cells) == int(res.measured.mask.sum()) and c.shape == (len(cells), len(cells))
    with pytest.raises(InputError, match=r"header says 'R2 \["):
        read_cell_correlation(tmp_path / "corrected_corr.csv", table=head.replace("R3", "R2"))


def test_correction_map_colour_bar_label_clears_the_next_panel_and_cells_are_readable():
    """trial 12 D8: correction_map.png (one instrument, 2000 x 900 px) had the left colour bar's label
    touching the right panel's "tan eps" and cell numbers ~5 px high. Laid out as the joint map: the
    label ends left of the right panel's axis label, and the cell numbers are JOINT_MAP_CELL_FONT pt
    (~10 px at the PNG's 100 dpi)."""
    from types import SimpleNamespace

    from roadgonio.correction.outputs import JOINT_MAP_CELL_FONT, draw_correction_map
    from roadgonio.plots import _plt
    from roadgonio.surface.rtable import bundled_table
    t = bundled_table("R3")
    k = np.where(t.mask, 1.0 + 0.05 * np.sin(np.arange(t.r.size).reshape(t.r.shape)), np.nan)
    n = int(t.mask.sum())
    res = SimpleNamespace(k_a=k, measured=t, budget=SimpleNamespace(u_rel=lambda: np.full(n, 0.012),
                                                                    components=["measurement", "backend"]))
    fig = draw_correction_map(res)
    try:
        fig.savefig(io.BytesIO(), format="png", dpi=100)
        renderer = fig.canvas.get_renderer()
        a1, a2 = fig.axes[:2]
        colour_bar = [a for a in fig.axes[2:] if "k_A (measured / true" in a.get_ylabel()][0]
        left_label = colour_bar.yaxis.label.get_window_extent(renderer)
        right_label = a2.yaxis.label.get_window_extent(renderer)
        assert left_label.x1 < right_label.x0, (left_label, right_label)
        sizes = {t.get_fontsize() for t in a1.texts} | {t.get_fontsize() for t in a2.texts}
        assert sizes and min(sizes) >= JOINT_MAP_CELL_FONT, sizes
    finally:
        _plt().close(fig)


def test_correction_map_of_a_surface_correction_says_the_table_weighs_the_surfaces_value():
    """User audit, session 24: correction_map.png of `--forward surface` was titled "k_A used for the
    correction (corrected = measured / k_A)", where the fitted surface's own value carries most of the
    table (before_after.png said so). The title says what the table is for each route."""
    from types import SimpleNamespace

    from roadgonio.correction.outputs import draw_correction_map
    from roadgonio.plots import _plt
    from roadgonio.surface.rtable import bundled_table
    t = bundled_table("R3")
    k = np.where(t.mask, 1.02, np.nan)
    n = int(t.mask.sum())
    titles = {}
    for route, extra in (("eq4", {}), ("surface", {"surface": object()})):
        res = SimpleNamespace(k_a=k, measured=t, extra=extra, budget=SimpleNamespace(
            u_rel=lambda: np.full(n, 0.012), components=["measurement", "backend"]))
        fig = draw_correction_map(res)
        titles[route] = fig.axes[0].get_title()
        _plt().close(fig)
    assert "(corrected = measured / k_A)" in titles["eq4"] and "surface" not in titles["eq4"]
    assert "fitted surface's own value" in titles["surface"] and "corrected = measured / k_A" not in titles["surface"]


def test_joint_correct_json_defines_every_column_of_its_cells_csv():
    """(user audit, session 39) the joint route's correct.json defined none of correct_cells.csv's columns:
    every column the file has is defined, per instrument by its name, the unobserved road's only where the
    instrument has it, and the file's rows are as long as its header."""
    from types import SimpleNamespace
    from roadgonio.correction.outputs import _joint_doc, joint_cells_csv
    from roadgonio.surface.rtable import bundled_table
    t = bundled_table("R3")
    grid = np.where(t.mask, 0.5, np.nan)
    n = int(t.mask.sum())

    class Budget:
        components = ("measured", "surface")

        def u_rel(self, c=None):
            return np.full(n, 0.01)

    def part(name, unobserved):
        return SimpleNamespace(name=name, measured=t, k_a=grid, corrected=t, residual=grid,
                               unobserved_sensitivity=grid if unobserved else None)

    sc = SimpleNamespace(corrected=t, budget=Budget(), u_corrected=t.r * 0.01, model_weight=grid,
                         parts=[part("portable", False), part("portable-20mm", True)],
                         summary=lambda: {}, provenance={})
    lines = [ln for ln in joint_cells_csv(sc).splitlines() if not ln.startswith("#")]
    head = lines[0].split(",")
    defs = _joint_doc(sc, False, {})["definitions"]["correct_cells.csv"]
    assert list(defs) == head and all(defs.values()), [c for c, d in defs.items() if not d]
    assert "k_a_portable-20mm" in defs and "dlnk_a_dlnf_unobserved_portable-20mm" in defs
    assert "dlnk_a_dlnf_unobserved_portable" not in defs
    assert defs["u_rel_surface"] == defs["u_rel_measured"] != defs["u_rel_total"]
    assert all(len(ln.split(",")) == len(head) for ln in lines[1:]) and len(lines) == n + 1


def test_one_instrument_measuring_twice_gets_a_column_set_each():
    """(user audit, session 42) the same instrument given twice to a joint correction (the measuring-twice
    case design --second-aperture compares against) wrote each of its columns twice in correct_cells.csv
    and two per_instrument entries of one name: the parts are named apart by their place on the command
    line, an instrument with its own name keeps it, and a joint w_model is defined by columns it has."""
    from types import SimpleNamespace
    from roadgonio.correction.outputs import JOINT_CELL_COLUMNS, _joint_cells_head
    from roadgonio.correction.outside import part_names
    inst = [SimpleNamespace(name=n) for n in ("portable", "wide", "portable")]
    names = part_names(inst)
    assert names == ["portable_1", "wide", "portable_3"]
    assert part_names([SimpleNamespace(name=n) for n in ("a", "a", "a_1")]) == ["a_1_", "a_2", "a_1"]
    parts = [SimpleNamespace(name=n, unobserved_sensitivity=None) for n in names]
    head = _joint_cells_head(SimpleNamespace(budget=SimpleNamespace(components=("measurement",)),
                                             model_weight=None, parts=parts))
    assert len(head) == len(set(head)) and "k_a_portable_3" in head
    rest = JOINT_CELL_COLUMNS["w_model"].split("the rest:")[1]
    assert "r_over_k_a" not in rest and "r_corrected_<instrument>" in rest


def test_corrected_u_carries_what_its_u_leaves_out_for_road():
    """(user audit, session 39) an eq. 4 correction through stray light says u leaves out the road beyond
    the observation elevations, and every instrument with parts that their reflectances are taken as exact:
    both reach corrected_u.csv's header as notes (which `road --u` repeats), one line each."""
    from types import SimpleNamespace
    from roadgonio.correction.run import REFLECTANCES_EXACT_NOTE, UNOBSERVED_ROAD_NOTE
    from roadgonio.surface.rtable import bundled_table, header_notes
    t = bundled_table("R3")
    res = SimpleNamespace(corrected=t, u_corrected=t.r * 0.01, fit=None, extra={"u_notes": [UNOBSERVED_ROAD_NOTE]},
                          provenance={"forward_model_limits": "the fit's ray bundles do not model ..."})
    back = parse_csv(u_csv_text(res), quantity="u")
    assert header_notes(back) == [UNOBSERVED_ROAD_NOTE, REFLECTANCES_EXACT_NOTE]
    np.testing.assert_allclose(back.r[t.mask], t.r[t.mask] * 0.01, rtol=1e-3)
    bare = SimpleNamespace(corrected=t, u_corrected=t.r * 0.01, fit=None, extra={}, provenance={})
    assert header_notes(parse_csv(u_csv_text(bare), quantity="u")) == []
