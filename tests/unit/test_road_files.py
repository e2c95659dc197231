"""What `roadgonio road` and `compare` write, column by column (roadgonio/road/report.py,
roadgonio/road/compare.py), and the layout file's types and ranges (roadgonio/road/layout.py).
The system tests count rows and read one cell; mutation audit 10 swapped columns, took one
observer's luminance for every row, numbered lanes from 0 and wrote table A's r as B's without
any test failing."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from roadgonio.road.compare import compare_csv, compare_tables
from roadgonio.road.evaluate import Installation
from roadgonio.road.layout import load_layout, read_layout
from roadgonio.road.luminaire import load_luminaire
from roadgonio.road.mc import propagate
from roadgonio.road.report import luminance_csv, metrics_csv
from roadgonio.surface.rtable import bundled_table

CSV_DIGITS = 5e-6        # cells written with 6 significant digits (%.6g): relative rounding <= 5e-6
XY_DIGITS = 5e-4         # coordinates written with 4 significant digits (%.4g)


@pytest.fixture(scope="module")
def installation():
    return Installation(load_layout(), load_luminaire())


def _rows(text: str) -> list[dict]:
    return list(csv.DictReader(text.splitlines()))


def test_luminance_csv_gives_each_observer_and_point_its_own_row(installation):
    """Two lanes (two observers) x 60 points: observer and lane numbered from 1, x along and y
    across the road, the centre-line flag, and L of that observer at that point."""
    res = installation.evaluate(bundled_table("R3"))
    fld = installation.fld
    rows = _rows(luminance_csv([res]))
    n_obs, n_p = res.L.shape
    assert n_obs == 2 and len(rows) == n_obs * n_p
    assert np.ptp(fld.x) > 0 and np.ptp(fld.y) > 0 and not np.allclose(res.L[0], res.L[1], rtol=1e-3)
    for k, row in enumerate(rows):
        o, p = divmod(k, n_p)
        assert row["table"] == "R3" and int(row["observer_lane"]) == o + 1
        assert float(row["x_m"]) == pytest.approx(fld.x[p], rel=XY_DIGITS, abs=0.0)
        assert float(row["y_m"]) == pytest.approx(fld.y[p], rel=XY_DIGITS, abs=0.0)
        assert int(row["lane"]) == int(fld.lane[p]) + 1 and int(row["centre_line"]) == int(fld.centre[p])
        assert float(row["L_cd_m2"]) == pytest.approx(res.L[o, p], rel=CSV_DIGITS, abs=0.0)
    assert {int(r["lane"]) for r in rows} == {1, 2}


def test_metrics_csv_puts_each_number_under_its_own_header(installation):
    """A table without and one with uncertainty: the nominal metrics on every row of their table,
    then per correlation mode u and the 95 % coverage interval of L_av, U_o, U_l and TI and the
    probability of meeting the class, each under its header."""
    t = bundled_table("R3")
    plain = installation.evaluate(bundled_table("R2")).summary()
    res = installation.evaluate(t)
    s = res.summary()
    s["uncertainty"] = unc = propagate(installation, t, t.with_values(0.1 * t.r), trials=500, seed=4)
    rows = _rows(metrics_csv([plain, s]))
    assert [(r["table"], r["correlation"]) for r in rows] == [("R2", ""), ("R3", "independent"), ("R3", "correlated")]
    assert rows[0]["u_L_av"] == "" and rows[0]["P_meets"] == ""
    for r in rows[1:]:
        for k in ("L_av", "U_o", "U_l", "TI", "R_EI", "table_Q0", "table_S1"):
            assert float(r[k]) == pytest.approx(s[k], rel=CSV_DIGITS, abs=0.0), k
        assert r["class"] == s["class"]
        m = unc[r["correlation"]]
        for k in ("L_av", "U_o", "U_l", "TI"):
            assert float(r[f"u_{k}"]) == pytest.approx(m[k]["u"], rel=CSV_DIGITS, abs=0.0), k
        for k in ("L_av", "U_o", "U_l", "TI"):            # TI's interval too (audit 21: printed, not written)
            lo, hi = (float(v) for v in r[f"cov95_{k}"].split(".."))
            np.testing.assert_allclose([lo, hi], m[k]["coverage_interval_95"], rtol=5e-5, atol=0.0)
        assert float(r["P_meets"]) == pytest.approx(m["P_meets_target"], rel=CSV_DIGITS, abs=0.0)
    assert unc["independent"]["P_meets_target"] != unc["correlated"]["P_meets_target"]


def test_compare_csv_has_each_tables_own_r_and_the_ratio(tmp_path):
    """Every cell tabulated in A or B: r x 1e4 of A and of B in their own columns (blank where the
    table is), and B / A where both are; a cell blank in both is left out."""
    a = bundled_table("R3")
    rb = bundled_table("R4").r.copy()
    rb[3, 4] = np.nan                         # only in A
    ra = a.r.copy()
    ra[5, 6] = np.nan                         # only in B
    a = a.with_values(ra, name="A")
    b = a.with_values(rb, name="B")
    res = compare_tables(a, b)
    rows = _rows(compare_csv(a, b, res["ratio"]))
    assert list(rows[0]) == ["tan_eps", "beta_deg", "r_A_x1e4", "r_B_x1e4", "ratio_B_over_A"]
    assert len(rows) == int((a.mask | b.mask).sum())
    seen = set()
    for r in rows:
        i = int(np.argmin(abs(a.tan_eps - float(r["tan_eps"]))))
        j = int(np.argmin(abs(a.beta_deg - float(r["beta_deg"]))))
        seen.add((i, j))
        for col, t in (("r_A_x1e4", a), ("r_B_x1e4", b)):
            if t.mask[i, j]:
                assert float(r[col]) == pytest.approx(t.r[i, j] * 1e4, rel=CSV_DIGITS, abs=0.0), (col, i, j)
            else:
                assert r[col] == ""
        if a.mask[i, j] and b.mask[i, j]:
            assert float(r["ratio_B_over_A"]) == pytest.approx(b.r[i, j] / a.r[i, j], rel=CSV_DIGITS, abs=0.0)
        else:
            assert r["ratio_B_over_A"] == ""
    assert (3, 4) in seen and (5, 6) in seen


def test_compare_counts_a_zero_in_either_table_as_an_infinite_change():
    """(audit 22) r(A) = 0 < r(B) was dropped from the ratio: two tables differing there were
    reported as identical, the 'largest change x1' placed at the first cell. It is now an infinite
    ratio and the largest change; r(B) = 0 < r(A) a ratio of 0; 0 in both has no ratio; equal
    tables have no largest change."""
    a = bundled_table("R3")
    ra, rb = a.r.copy(), a.r.copy()
    ra[0, 0] = 0.0                            # r(A) = 0 < r(B)
    rb[4, 5] = 0.0                            # r(B) = 0 < r(A)
    ra[7, 2] = rb[7, 2] = 0.0                 # 0 in both
    A, B = a.with_values(ra, name="A"), a.with_values(rb, name="B")
    res = compare_tables(A, B)
    assert np.isinf(res["ratio"][0, 0]) and res["ratio"][4, 5] == 0.0 and np.isnan(res["ratio"][7, 2])
    assert (res["cells_zero_in_A"], res["cells_zero_in_B"], res["cells_ratio_undefined"]) == (1, 1, 1)
    assert res["cells_compared"] == int(a.mask.sum()) - 2
    assert res["ratio_min"] == 0.0 and res["ratio_max"] == pytest.approx(1.0, abs=0.0)
    assert res["largest_change_at"]["ratio"] in (0.0, np.inf)
    rows = {(r["tan_eps"], r["beta_deg"]): r["ratio_B_over_A"] for r in _rows(compare_csv(A, B, res["ratio"]))}
    assert rows[("0", "0")] == "" and float(rows[(f"{a.tan_eps[4]:g}", f"{a.beta_deg[5]:g}")]) == 0.0
    only_a = compare_tables(A, a.with_values(a.r, name="B"))
    assert only_a["largest_change_at"] == {"tan_eps": 0.0, "beta_deg": 0.0, "ratio": np.inf}
    assert compare_tables(a, a.with_values(a.r, name="B"))["largest_change_at"] is None


def test_a_small_change_is_not_printed_as_x1():
    """(user audit) one cell of R3 changed by 0.34 % read 'largest change x1' and '1 ... 1': a ratio
    that is not 1 gets the digits it takes to show it; 3 significant digits otherwise."""
    from roadgonio.road.compare import largest_change_text, range_text, ratio_text
    a = bundled_table("R3")
    rb = a.r.copy()
    rb[0, 1] *= 295.0 / 294.0
    res = compare_tables(a, a.with_values(rb, name="B"))
    assert largest_change_text(res).startswith("largest change x1.003 ")
    assert range_text(res) == "1 ... 1.003 (median 1)"
    assert (ratio_text(1.0), ratio_text(0.4286), ratio_text(1.72), ratio_text(0.99996)) == ("1", "0.429", "1.72", "0.99996")
    assert ratio_text(1.0 + 1e-7) == "1.0000001"


def test_layout_tilt_limits_are_inclusive(tmp_path):
    for v in (-30, 60):
        p = tmp_path / f"t{v}.toml"
        p.write_text(f"[installation]\ntilt_deg = {v}\n")
        assert read_layout(p).tilt_deg == float(v)


def test_unknown_luminances_are_blank_cells(installation):
    """A table blank where the luminance needs it (tan eps 5, beta 0): the points whose L is unknown
    are blank in road_luminance.csv (a CSV has no NaN), the others keep their number."""
    t = bundled_table("R3")
    r = t.r.copy()
    r[int(np.argmin(abs(t.tan_eps - 5.0))), 0] = np.nan
    res = installation.evaluate(t.with_values(r))
    unknown = np.isnan(res.L)
    assert unknown.any() and not unknown.all()
    text = luminance_csv([res])
    assert "nan" not in text.lower()
    rows = _rows(text)
    n_p = res.L.shape[1]
    for k, row in enumerate(rows):
        o, p = divmod(k, n_p)
        assert (row["L_cd_m2"] == "") == bool(unknown[o, p])
