"""From the r-table to the road (issue 13): hand calculations of the EN 13201-3 luminance, a layout
with an analytic answer, the r-table interpolation rule, TI, classes, the luminaire file, layouts,
and the Monte Carlo judged against linear propagation."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from helpers import refused_in_one_line
from roadgonio.errors import InputError
from roadgonio.road import calc, interp, metrics
from roadgonio.road.evaluate import Installation
from roadgonio.road.layout import Layout, layout_from_dict, load_layout, read_layout
from roadgonio.road.luminaire import Luminaire, bundled_luminaire_path, load_luminaire, read_ldt
from roadgonio.road.mc import propagate
from roadgonio.surface.rtable import bundled_table

REL = 1e-9          # deterministic arithmetic, float64
FILE_ROUNDING = 5e-4  # the .ldt stores cd/klm with 3 decimals


# ----------------------------------------------------------------------------------------------
# an independent reader of the bundled EULUMDAT file (the LiTG line layout, by hand)
# ----------------------------------------------------------------------------------------------

def _hand_ldt(path: Path):
    lines = path.read_bytes().decode("latin-1").replace("\r\n", "\n").split("\n")
    isym, mc, ng = int(lines[2]), int(lines[3]), int(lines[5])
    n_sets = int(lines[25])
    flux = float(lines[26 + 2])                # 26c of the first set
    conv = float(lines[23])
    k = 26 + 6 * n_sets + 10                   # after the lamp sets and the 10 direct ratios
    c = [float(v) for v in lines[k:k + mc]]
    g = [float(v) for v in lines[k + mc:k + mc + ng]]
    vals = [float(v) for v in lines[k + mc + ng:] if v.strip()]
    assert isym == 3 and len(vals) == (mc // 2 + 1) * ng
    stored = {(270.0 + i * 360.0 / mc) % 360.0: vals[i * ng:(i + 1) * ng] for i in range(mc // 2 + 1)}

    def intensity_file(cc: float, gg: float) -> float:  # at nodes only, symmetry I(C) = I(180 - C)
        cc = cc % 360.0
        row = stored.get(cc) or stored[(180.0 - cc) % 360.0]
        return row[g.index(gg)]
    return intensity_file, flux * conv / 1000.0, c, g


def test_bundled_luminaire_is_its_generator_output_and_reads_right():
    from roadgonio.data.road import make_luminaire as gen
    path = bundled_luminaire_path()
    assert path.read_bytes() == gen.ldt_text().encode("latin-1")   # the committed file is the script's output
    lum = read_ldt(path)
    hand, scale, c, g = _hand_ldt(path)
    assert lum.flux_lm == 10000.0 and lum.scale_cd == pytest.approx(scale)
    cc, gg = np.meshgrid(c, g, indexing="ij")
    np.testing.assert_allclose(lum.cd_per_klm, gen.intensity_cd_per_klm(cc, gg), atol=FILE_ROUNDING)
    for cv, gv in ((0, 65), (15, 65), (165, 65), (195, 40), (270, 30), (90, 80), (300, 87.5)):
        assert lum.interpolate(cv, gv) == pytest.approx(hand(cv, gv), abs=1e-12)
    # the documented distribution emits the lamp flux (LORL 100 %) and nothing above the horizontal
    assert lum.flux_from_table() == pytest.approx(10000.0, rel=2e-3)
    assert np.all(lum.cd_per_klm[:, np.asarray(g) >= 90] == 0)


def test_bilinear_intensity_between_nodes():
    lum = load_luminaire()
    hand, scale, *_ = _hand_ldt(bundled_luminaire_path())
    c, g = 12.5, 66.25                                   # between C 10/15 and gamma 65/67.5
    tc, tg = 0.5, 0.5
    want = ((1 - tc) * (1 - tg) * hand(10, 65) + tc * (1 - tg) * hand(15, 65) + (1 - tc) * tg * hand(10, 67.5)
            + tc * tg * hand(15, 67.5)) * scale
    assert float(lum.intensity(c, g)) == pytest.approx(want, rel=REL)
    assert math.isnan(float(Luminaire([0.0], [0.0, 80.0], [[1.0, 1.0]], 1000.0).intensity(0, 85)))


@pytest.mark.parametrize("edit,words", [
    (lambda L: L[:200], ["file ends early"]),
    (lambda L: L[:28] + ["0"] + L[29:], ["lamp flux", "> 0"]),
    (lambda L: L[:3] + ["abc"] + L[4:], ["Mc (line 4)", "whole number"]),
    (lambda L: L[:2] + ["7"] + L[3:], ["Isym"]),
    # user audit, session 37: a text line of the header deleted gave the parser's "could not convert
    # string to float: 'LED module'", naming no line
    (lambda L: L[:8] + L[9:], ["number of lamps of set 1 (line 27)", "expected a number, got 'LED module'",
                               "text line of the header missing"]),
])
def test_bad_luminaire_file(tmp_path, edit, words):
    lines = bundled_luminaire_path().read_bytes().decode("latin-1").split("\r\n")
    p = tmp_path / "bad.ldt"
    p.write_text("\r\n".join(edit(lines)), encoding="latin-1")
    refused_in_one_line(lambda: read_ldt(p), p, words)


# ----------------------------------------------------------------------------------------------
# luminance at one grid point from one luminaire, by hand
# ----------------------------------------------------------------------------------------------

def test_luminance_one_luminaire_on_nodes_by_hand():
    """Luminaire 10 m beyond the point, in line with the observer: C = 180, gamma = 45 deg
    (nodes of the I-table), beta = 0, tan eps = 1 (a cell of the r-table)."""
    lum = load_luminaire()
    hand, scale, *_ = _hand_ldt(bundled_luminaire_path())
    t = bundled_table("R3")
    h = 10.0
    L_lum = np.array([30.0, 1.0, h])
    point = np.array([20.0, 1.0, 0.0])
    observer = np.array([-60.0, 1.0, 1.5])
    cells, w, tan_e = calc.contribution(lum, L_lum, 0.0, 0.0, point, observer, t)
    L = float(np.dot(t.r.ravel()[cells], w))
    csv_text = (Path(__file__).resolve().parents[2] / "roadgonio/data/rtables/R3.csv").read_text()
    row = next(l for l in csv_text.splitlines() if l.startswith("1,"))
    r_file = float(row.split(",")[1])  # R3.csv, tan eps = 1, beta = 0: r x 1e4 as printed
    assert r_file == 362.0
    want = hand(180.0, 45.0) * scale * (r_file / 1e4) / h ** 2
    assert tan_e == pytest.approx(1.0) and L == pytest.approx(want, rel=REL)


def test_luminance_one_luminaire_off_nodes_by_hand():
    lum = load_luminaire()
    t = bundled_table("R3")
    L_lum, point, obs = np.array([33.0, 1.0, 9.0]), np.array([21.3, 4.1, 0.0]), np.array([-60.0, 5.25, 1.5])
    d = point - L_lum
    gamma = math.degrees(math.acos(-d[2] / np.linalg.norm(d)))
    c = math.degrees(math.atan2(d[1], d[0])) % 360
    tan_e = math.hypot(d[0], d[1]) / 9.0
    u, v = point[:2] - obs[:2], L_lum[:2] - point[:2]
    beta = math.degrees(math.acos(np.dot(u, v) / np.linalg.norm(u) / np.linalg.norm(v)))
    # quadratic Lagrange by hand: tan nodes 1.25, 1.5, 1.75 and in each row beta nodes around beta
    def three(grid, x):  # the two bracketing nodes and the nearer of their outer neighbours
        g = list(grid)
        i = max(k for k in range(len(g)) if g[k] <= x)
        return [g[i - 1], g[i], g[i + 1]] if x - g[i - 1] <= g[i + 2] - x else [g[i], g[i + 1], g[i + 2]]
    tn, bn = three(t.tan_eps, tan_e), three(t.beta_deg, beta)
    assert tn == [1.0, 1.25, 1.5] and tn[1] <= tan_e <= tn[2]

    def lag(nodes, x):
        return [np.prod([(x - nodes[m]) / (nodes[k] - nodes[m]) for m in range(3) if m != k]) for k in range(3)]
    r = sum(wt * sum(wb * t.value(tt, bb) for wb, bb in zip(lag(bn, beta), bn)) for wt, tt in zip(lag(tn, tan_e), tn))
    want = float(lum.intensity(c, gamma)) * r / 81.0
    cells, w, _ = calc.contribution(lum, L_lum, 0.0, 0.0, point, obs, t)
    assert float(np.dot(t.r.ravel()[cells], w)) == pytest.approx(want, rel=REL)


def test_angles_rotation_and_tilt():
    lum = np.array([0.0, 0.0, 10.0])
    c, g = calc.luminaire_angles(lum, 0.0, 0.0, np.array([0.0, 10.0, 0.0]))   # towards the road
    assert (float(c), float(g)) == pytest.approx((90.0, 45.0))
    c, g = calc.luminaire_angles(lum, 180.0, 0.0, np.array([-10.0, 0.0, 0.0]))  # row 2: C0 along -x
    assert (float(c), float(g)) == pytest.approx((0.0, 45.0))
    c, g = calc.luminaire_angles(lum, 0.0, 10.0, np.array([0.0, 10.0 * math.tan(math.radians(10)), 0.0]))
    assert float(g) == pytest.approx(0.0, abs=1e-5)                            # tilt swings nadir to the road
    beta, t = calc.incidence(lum, np.array([-10.0, 0.0, 0.0]), np.array([-70.0, 0.0, 1.5]))
    assert (beta, t) == pytest.approx((0.0, 1.0))
    beta, t = calc.incidence(lum, np.array([10.0, 0.0, 0.0]), np.array([-70.0, 0.0, 1.5]))
    assert beta == pytest.approx(180.0)


# ----------------------------------------------------------------------------------------------
# r-table interpolation (EN 13201-3 5.5: quadratic)
# ----------------------------------------------------------------------------------------------

def _poly_table(f):
    t = bundled_table("C2")
    T, B = np.meshgrid(t.tan_eps, t.beta_deg, indexing="ij")
    return t.with_values(np.where(t.mask, f(T, B), np.nan))


def test_quadratic_interpolation_is_exact_for_quadratics_and_linear_for_lines():
    quad = _poly_table(lambda T, B: 0.01 + 0.002 * T + 0.0003 * T ** 2 + 1e-5 * B + 2e-7 * B ** 2 + 1e-6 * T * B)
    f = lambda t, b: 0.01 + 0.002 * t + 0.0003 * t ** 2 + 1e-5 * b + 2e-7 * b ** 2 + 1e-6 * t * b  # noqa: E731
    rng = np.random.default_rng(1)
    for _ in range(200):
        t, b = rng.uniform(0, 4.5), rng.uniform(0, 180)   # stencil rows up to tan 5: no blank cells
        assert interp.r_value(quad, b, t) == pytest.approx(f(t, b), rel=1e-11, abs=0.0)
    cells, w = interp.r_weights(quad, 130.0, 4.8)           # row 5.5 blank at beta 130: linear fallback
    assert len(cells) == 4 and np.all(quad.mask.ravel()[cells])
    assert abs(interp.r_value(quad, 33.0, 2.6, "linear") - f(2.6, 33.0)) > 1e-7   # linear is not exact
    lin = _poly_table(lambda T, B: 0.02 + 0.001 * T + 3e-5 * B)
    assert interp.r_value(lin, 33.0, 2.6, "linear") == pytest.approx(0.02 + 0.0026 + 3e-5 * 33, rel=1e-12, abs=0.0)


def test_interpolation_never_uses_blank_cells():
    t = bundled_table("R3")
    assert interp.r_value(t, 5.0, 0.3) == pytest.approx(
        sum(w * v for w, v in zip(interp._lagrange(np.array([0.0, 0.25, 0.5]), 0.3),
                                   [t.value(x, 5.0) for x in (0.0, 0.25, 0.5)])), rel=1e-12, abs=0.0)
    assert interp.r_value(t, 2.0, 1.0) == t.value(1.0, 2.0)           # a node takes the node alone
    assert math.isnan(interp.r_value(t, 90.0, 6.0))                   # blank region: no r
    assert math.isnan(interp.r_value(t, 0.0, 12.5))                   # beyond tan 12
    v = interp.r_value(t, 38.0, 5.5)                                   # row 5.5 tabulated up to 40 only
    assert np.isfinite(v) and v > 0
    cells, _ = interp.r_weights(t, 38.0, 5.5)
    assert np.all(t.mask.ravel()[cells])


# ----------------------------------------------------------------------------------------------
# a layout with an analytic answer: constant r, isotropic luminaire
# ----------------------------------------------------------------------------------------------

def _isotropic(i0_cd=800.0):
    return Luminaire([0.0], [0.0, 90.0, 180.0], [[i0_cd] * 3], 1000.0, name="isotropic")


def test_constant_r_isotropic_luminaire_analytic_metrics():
    """Every counted luminaire then gives L = MF r0 I0 / H^2, so L(point) = MF r0 I0 n(point) / H^2
    with n the number of luminaires in [x - 5 H, x + 12 H] (tan eps <= 12)."""
    lay = Layout(spacing_m=30.0, mounting_height_m=10.0, overhang_m=1.0, maintenance_factor=0.8)
    r0 = 0.05
    t = bundled_table("R3")
    const = t.with_values(np.where(t.mask, r0, np.nan))
    res = Installation(lay, _isotropic(800.0)).evaluate(const)
    k = 0.8 * r0 * 800.0 / 100.0
    xs = (np.arange(10) + 0.5) * 3.0
    n = np.array([sum(1 for m in range(-5, 10) if x - 50 <= 30 * m <= x + 120) for x in xs])
    assert list(n) == [6] * 7 + [5] * 3
    lav, uo, ul = k * n.mean(), n.min() / n.mean(), n.min() / n.max()
    assert res.values["L_av"] == pytest.approx(lav, rel=REL)
    assert res.values["U_o"] == pytest.approx(uo, rel=REL)
    assert res.values["U_l"] == pytest.approx(ul, rel=REL)
    np.testing.assert_allclose(res.L, np.broadcast_to(k * np.tile(n, 6), res.L.shape), rtol=REL)


def test_a_spacing_beyond_the_counted_range_is_said_not_silent():
    """(user audit) S = 300 m with H = 10 m gave U_o = 0 without a word: the counting rule (5 H before,
    12 H beyond) leaves points x in (50, 180) m without a luminaire. The summary (road.json, --json and
    the text) says how many points and why; a layout whose every point counts a luminaire says nothing."""
    r0 = 0.05
    t = bundled_table("R3")
    const = t.with_values(np.where(t.mask, r0, np.nan))
    res = Installation(Layout(spacing_m=300.0, mounting_height_m=10.0), _isotropic(800.0)).evaluate(const)
    xs = (np.arange(100) + 0.5) * 3.0
    bare = int(np.sum((xs > 50.0) & (xs < 180.0))) * 6                 # 2 lanes x 3 points across
    assert bare == 258 and res.values["U_o"] == 0.0
    notes = res.summary()["notes"]
    assert len(notes) == 1 and f"{bare} of 600 grid points have no luminaire" in notes[0], notes
    assert "S = 300 m" in notes[0] and "U_o is 0" in notes[0] and "\n" not in notes[0]
    assert Installation(Layout(spacing_m=170.0, mounting_height_m=10.0), _isotropic(800.0)).notes == []
    assert Installation(Layout(spacing_m=180.0, mounting_height_m=10.0), _isotropic(800.0)).notes != []


def test_a_counted_range_beyond_12_h_is_said_to_change_nothing():
    """User audit, session 37: luminaires_after_h = 15 gave the default layout's metrics digit for
    digit with nothing said (a luminaire more than 12 H along the road has tan eps > 12, beyond
    every r-table). The metrics are those of 12 H and a note says why; 12 H says nothing."""
    t = bundled_table("R3")
    lum = load_luminaire()
    base = Installation(load_layout(), lum)
    import dataclasses
    far = Installation(dataclasses.replace(load_layout(), after_h=15.0), lum)
    a, b = base.evaluate(t), far.evaluate(t)
    for key in ("L_av", "U_o", "U_l", "TI"):
        assert b.values[key] == a.values[key]
    assert b.summary()["neglected_contributions"] > a.summary()["neglected_contributions"]
    assert base.notes == []
    assert len(far.notes) == 1 and "luminaires_after_h 15 H" in far.notes[0] and "changes no metric" in far.notes[0]
    assert b.summary()["notes"] == far.notes


def test_l_av_scales_with_the_table_uniformities_do_not():
    inst = Installation(load_layout(), load_luminaire())
    t = bundled_table("R3")
    a = inst.evaluate(t).values
    b = inst.evaluate(t.with_values(t.r * 1.7)).values
    assert b["L_av"] == pytest.approx(1.7 * a["L_av"], rel=REL)
    assert b["U_o"] == pytest.approx(a["U_o"], rel=REL) and b["U_l"] == pytest.approx(a["U_l"], rel=REL)
    assert b["TI"] == pytest.approx(a["TI"] * 1.7 ** -0.8, rel=REL)       # TI = 65 L_v / L_av^0.8
    c = inst.evaluate(bundled_table("R1")).values
    assert abs(c["U_o"] - a["U_o"]) > 0.05                                 # the shape of the table matters


def test_grid_rule_of_en_13201_3():
    assert Layout(spacing_m=30).n_longitudinal == 10
    assert Layout(spacing_m=24).n_longitudinal == 10
    assert Layout(spacing_m=30.5).n_longitudinal == 11
    assert Layout(spacing_m=45).n_longitudinal == 15
    f = calc.build_field(Layout(spacing_m=36, lanes=3, lane_width_m=3.6))
    assert f.n_long == 12 and f.spacing_d_m == pytest.approx(3.0)
    assert f.x.min() == pytest.approx(1.5) and sorted(set(np.round(f.y, 9)))[:3] == pytest.approx([0.6, 1.8, 3.0])
    assert list(f.observers[:, 0]) == [-60.0] * 3 and list(f.observers[:, 1]) == pytest.approx([1.8, 5.4, 9.0])
    assert np.sum(f.centre) == 3 * 12


# ----------------------------------------------------------------------------------------------
# TI and R_EI by hand
# ----------------------------------------------------------------------------------------------

def test_veiling_luminance_by_hand():
    lay = Layout(lanes=1, spacing_m=30.0, mounting_height_m=10.0, overhang_m=0.0)
    i0 = 800.0
    fld = calc.build_field(lay)
    v = calc.veiling_luminance(lay, _isotropic(i0), fld)
    x0 = -2.75 * 8.5
    eye = np.array([x0, 1.75, 1.5])
    sight = np.array([math.cos(math.radians(1)), 0, -math.sin(math.radians(1))])
    lv = 0.0
    for m in range(-3, 20):
        d = np.array([30.0 * m, 0.0, 10.0]) - eye
        if d[0] <= 0 or d[0] > 500 or d[2] > math.tan(math.radians(20)) * d[0] + 1e-9:
            continue
        dist = np.linalg.norm(d)
        th = math.degrees(math.acos(d @ sight / dist))
        lv += 10 * i0 * math.cos(math.radians(th)) / dist ** 2 / th ** 2
    assert v["L_v"][0, 0] == pytest.approx(lv, rel=REL)
    assert calc.threshold_increment(0.1, 1.0) == pytest.approx(6.5)
    assert calc.threshold_increment(0.1, 6.0) == pytest.approx(95 * 0.1 / 6.0 ** 1.05)


def test_ti_not_computable_without_luminaire_data_above_70_deg():
    short = Luminaire([0.0], [0.0, 30.0, 60.0, 70.0], [[500.0] * 4], 1000.0)
    lay = Layout(spacing_m=12.0, mounting_height_m=4.0, overhang_m=0.0, lanes=1)
    v = calc.veiling_luminance(lay, short, calc.build_field(lay))
    assert not v["computable"] and "70" in v["reason"]


def test_a_class_is_not_given_when_ti_cannot_be_computed():
    """(user audit, session 42) luminaire data that stop at gamma 87.5 deg: TI was null, `missing` null and
    the class given (M-class limits on TI never checked). TI and the class are listed as missing, with
    the reason; the other metrics are still given."""
    short = Luminaire([0.0], [0.0, 30.0, 60.0, 87.5], [[800.0] * 4], 1000.0)
    lay = Layout(spacing_m=30.0, mounting_height_m=10.0, overhang_m=1.0)
    t = bundled_table("R3")
    const = t.with_values(np.where(t.mask, 0.05, np.nan))
    res = Installation(lay, short).evaluate(const)
    s = res.summary()
    assert s["TI"] is None and s["class"] is None and s["L_av"] > 0 and s["R_EI"] is not None
    assert s["missing"]["metrics"] == ["TI", "class"] and "87.5" in s["missing"]["reason"]
    # the same layout with data to 90 deg has a class and nothing missing
    full = Installation(lay, _isotropic(800.0)).evaluate(const).summary()
    assert full["missing"] is None and full["TI"] is not None


def test_a_missing_metric_is_listed_once_with_its_reason_once():
    """`missing` lists a metric once, before "class", and its reason once, whichever check adds it first
    (the two R_EI checks, one beside the other, listed R_EI twice and its reason twice when both fired)."""
    from roadgonio.road.evaluate import with_missing
    a = with_missing(None, "R_EI", "R_EI needs light")
    assert a == {"metrics": ["R_EI", "class"], "reason": "R_EI needs light"}
    assert with_missing(a, "R_EI", "R_EI needs light") == a
    b = with_missing({"metrics": ["U_o", "TI", "class"], "reason": "dark", "points_unknown": 3}, "TI", "TI: no data")
    assert b == {"metrics": ["U_o", "TI", "class"], "reason": "dark; TI: no data", "points_unknown": 3}


def test_horizontal_illuminance_by_hand():
    lay = Layout(spacing_m=30.0, mounting_height_m=10.0, overhang_m=1.0, maintenance_factor=0.9)
    fld = calc.build_field(lay)
    e = calc.horizontal_illuminance(lay, _isotropic(500.0), np.array([7.0]), np.array([-2.0]), fld)
    want = 0.9 * sum(500.0 * (1 + ((30 * m - 7.0) ** 2 + 9.0) / 100.0) ** -1.5 / 100.0
                     for m in range(-5, 6) if abs(30 * m - 7.0) <= 50)
    assert float(e[0]) == pytest.approx(want, rel=REL)


# ----------------------------------------------------------------------------------------------
# classes (EN 13201-2:2015 Table 1)
# ----------------------------------------------------------------------------------------------

def test_m_classes():
    v = {"L_av": 1.0, "U_o": 0.40, "U_l": 0.60, "TI": 15.0, "R_EI": 0.30}
    assert metrics.best_class(v) == "M3"                         # limits are inclusive
    assert metrics.best_class({**v, "U_l": 0.599}) == "M5"
    assert metrics.best_class({**v, "TI": 15.01}) == "M6"
    assert metrics.best_class({**v, "TI": None}) == "M3"         # TI not computable: left out
    assert metrics.best_class({**v, "L_av": 0.29}) is None
    assert metrics.limiting_criteria("M2", v) == ["L_av", "U_l", "R_EI", "TI"]
    arr = {k: np.array([x, x]) for k, x in v.items()}
    arr["U_l"] = np.array([0.6, 0.3])
    assert list(metrics.best_class_array(arr)) == [2, 6]


# ----------------------------------------------------------------------------------------------
# layouts
# ----------------------------------------------------------------------------------------------

def test_default_layout_is_the_documented_one():
    lay = load_layout()
    assert (lay.lanes, lay.lane_width_m, lay.arrangement, lay.mounting_height_m, lay.spacing_m, lay.overhang_m,
            lay.tilt_deg, lay.maintenance_factor) == (2, 3.5, "single-sided", 10.0, 30.0, 1.0, 0.0, 0.8)


@pytest.mark.parametrize("text,words", [
    ("[raod]\nlanes = 2\n", ["unknown section [raod]"]),
    ("[road]\nlane = 2\n", ["[road] lane", "unknown key"]),
    ("[road]\nlanes = 2.5\n", ["[road] lanes", "whole number"]),
    ("[installation]\nspacing_m = 'x'\n", ["spacing_m", "number"]),
    ("[installation]\narrangement = 'twin'\n", ["arrangement", "single-sided"]),
    ("[installation]\nmaintenance_factor = 1.3\n", ["maintenance_factor"]),
    ("[installation]\nmounting_height_m = 1.8\n", ["mounting_height_m"]),
    ("[road\n", ["not valid TOML"]),
    # a value of the wrong type or outside its range (mutation audit 10)
    ("[installation]\nspacing_m = true\n", ["[installation] spacing_m", "number"]),
    ("[road]\nlanes = true\n", ["[road] lanes", "whole number"]),
    ("[installation]\ntilt_deg = 61\n", ["[installation] tilt_deg", "[-30, 60]"]),
    ("[installation]\ntilt_deg = -31\n", ["[installation] tilt_deg", "[-30, 60]"]),
])
def test_bad_layout(tmp_path, text, words):
    p = tmp_path / "lay.toml"
    p.write_text(text)
    refused_in_one_line(lambda: read_layout(p), p, words)


def test_arrangements_place_rows():
    base = {"installation": {"spacing_m": 30.0, "overhang_m": 0.5}}
    assert layout_from_dict(base).rows() == [(0.5, 0.0, 0.0)]
    st = layout_from_dict({"installation": {**base["installation"], "arrangement": "staggered"}})
    assert st.rows() == [(0.5, 0.0, 0.0), (6.5, 15.0, 180.0)]
    op = Installation(layout_from_dict({"installation": {**base["installation"], "arrangement": "opposite"}}),
                      load_luminaire()).evaluate(bundled_table("R3"))
    one = Installation(layout_from_dict(base), load_luminaire()).evaluate(bundled_table("R3"))
    assert op.values["L_av"] > 1.5 * one.values["L_av"]


# ----------------------------------------------------------------------------------------------
# Monte Carlo of the table's uncertainty
# ----------------------------------------------------------------------------------------------

def test_monte_carlo_matches_linear_propagation():
    inst = Installation(load_layout(), load_luminaire())
    t = bundled_table("R3")
    u = t.with_values(t.r * 0.03)
    n = 20000
    res = propagate(inst, t, u, trials=n, seed=7)
    op = inst.operator(t)
    nominal = inst.evaluate(t)
    o = int(np.argmin(nominal.per_observer["L_av_obs"]))      # the observer giving the operative L_av
    a = op.W[o].mean(axis=0)                                  # dL_av / dr per cell
    ur = np.nan_to_num(u.r.ravel())
    for mode, want in (("independent", math.sqrt(np.sum((a * ur) ** 2))), ("correlated", float(np.sum(a * ur)))):
        got = res[mode]["L_av"]["u"]
        se = want / math.sqrt(2 * (n - 1))                    # standard error of a standard deviation
        assert abs(got - want) < 4 * se, (mode, got, want, se)
    # fully correlated and proportional: L scales, uniformities do not move
    assert res["correlated"]["U_o"]["u"] < 1e-12 and res["correlated"]["U_l"]["u"] < 1e-12
    # P(meets M3) under full correlation: L_av = L0 (1 + 0.03 z) >= 1.0 (U's fixed, TI far from 15 %)
    from statistics import NormalDist
    p = 1 - NormalDist().cdf((1.0 / nominal.values["L_av"] - 1) / 0.03)
    got = res["correlated"]["P_meets_target"]
    assert res["target_class"] == "M3" and abs(got - p) < 4 * math.sqrt(p * (1 - p) / n) + 1e-4
    # the 2.5 / 97.5 % quantiles are a Monte Carlo coverage interval (JCGM 101), named so (was "ci95"):
    # under full correlation L_av is normal, L0 (1 + 0.03 z)
    m = res["correlated"]["L_av"]
    assert "ci95" not in m
    sigma = 0.03 * nominal.values["L_av"]
    z = NormalDist().inv_cdf(0.975)
    q_se = math.sqrt(0.025 * 0.975 / n) / NormalDist().pdf(z) * sigma       # standard error of a quantile
    for got_q, want_q in zip(m["coverage_interval_95"], (m["mean"] - z * sigma, m["mean"] + z * sigma)):
        assert abs(got_q - want_q) < 4 * q_se, (got_q, want_q, q_se)


def test_monte_carlo_input_checks():
    inst = Installation(load_layout(), load_luminaire())
    t = bundled_table("R3")
    used = inst.operator(t).used_cells
    i, j = np.unravel_index(used[len(used) // 2], t.r.shape)
    ur = t.r * 0.01
    ur[i, j] = np.nan
    u = t.with_values(ur)
    with pytest.raises(InputError, match=f"tan eps = {t.tan_eps[i]:g}, beta = {t.beta_deg[j]:g}"):
        propagate(inst, t, u, trials=200)
    with pytest.raises(InputError, match="seed"):
        propagate(inst, t, t.with_values(t.r * 0.01), trials=200, seed=-1)


def test_classify_limits(tmp_path):
    from roadgonio.surface.cie import class_by_s1
    assert class_by_s1(0.4199, "R")[0] == "R1" and class_by_s1(0.42, "R")[0] == "R2"
    assert class_by_s1(0.85, "R")[0] == "R3" and class_by_s1(1.35, "R")[0] == "R4"
    assert class_by_s1(0.399, "C")[0] == "C1" and class_by_s1(0.40, "C")[0] == "C2"
    assert class_by_s1(1.30, "N")[0] == "N4"


def test_class_limit_labels_stay_inside_their_panel(monkeypatch):
    """road_metrics.png: 'M3 min 0.6' ran over the U_l panel's frame and 'M3 max 15' sat outside
    the TI axes at the image edge. Every label of a limit is inside its own axes."""
    from roadgonio.road import report
    figs = []
    monkeypatch.setattr(report, "_png", lambda fig: figs.append(fig) or b"")
    rows = [{"table": name, "L_av": 1.1, "U_o": 0.55, "U_l": 0.62, "TI": 14.6, "class": "M3"} for name in ("R3", "corrected")]
    report.metrics_png(rows, "M3", "layout")
    fig = figs[0]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for ax, (key, _, kind) in zip(fig.axes, report.METRICS):
        frame = ax.get_window_extent(renderer)
        texts = [t for t in ax.texts + (ax.get_legend().texts if ax.get_legend() else []) if "M3" in t.get_text()]
        assert [t.get_text() for t in texts] == [f"M3 {kind} {report.M_CLASSES['M3'][key]:g}"]
        box = texts[0].get_window_extent(renderer)
        assert frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1, key


def test_bilinear_intensity_reproduces_a_bilinear_table_exactly():
    """Bilinear interpolation is exact for I = a + b C + c gamma + d C gamma on any grid (unequal
    steps here), at points with tc != tg: written out, not interpolated. The other test takes the
    cell's centre (tc = tg = 1/2), where the two cross terms' weights are equal and a swap of their
    table entries (I(C_1, gamma_0) <-> I(C_0, gamma_1)) does not show."""
    def f(c, g):
        return 100.0 + 2.0 * c + 3.0 * g + 0.05 * c * g
    c_grid = np.array([0.0, 10.0, 15.0, 30.0, 60.0, 90.0, 180.0, 270.0, 300.0])
    g_grid = np.array([0.0, 20.0, 45.0, 50.0, 65.0, 67.5, 80.0, 90.0])
    cc, gg = np.meshgrid(c_grid, g_grid, indexing="ij")
    lum = Luminaire(c_grid, g_grid, f(cc, gg), 1000.0)
    rng = np.random.default_rng(8)
    c = rng.uniform(0.0, 300.0, 200)                     # inside the C range: no periodic wrap
    g = rng.uniform(0.0, 90.0, 200)
    np.testing.assert_allclose(lum.interpolate(c, g), f(c, g), rtol=REL, atol=0.0)


# ----------------------------------------------------------------------------------------------
# U_l, the centre lines, the TI formula's boundary and R_EI by hand (mutation audit 9b: each of
# these could be changed without any test failing)
# ----------------------------------------------------------------------------------------------

def test_u_l_is_each_lanes_centre_line_seen_by_that_lanes_observer_and_the_lowest_lane():
    """EN 13201-3: U_l = L_min / L_max along the centre line of a lane, for the observer in that
    lane; the operative U_l is the lowest over the lanes. A field of 2 lanes x 3 rows x 4 points
    whose luminance differs per observer, row and point; the expected values are written out."""
    lane = np.repeat([0, 0, 0, 1, 1, 1], 4)
    centre = np.tile(np.repeat([False, True, False], 4), 2)
    L = np.full((2, 24), 5.0)                  # (observer, point); the outer rows are never used
    L[0, 4:8] = [1.0, 2.0, 4.0, 2.0]           # lane 1's centre line seen from lane 1: U_l = 1/4
    L[1, 4:8] = [3.0, 3.0, 3.0, 3.0]           # ... seen from lane 2's observer: not lane 1's U_l
    L[0, 16:20] = [9.0, 9.0, 9.0, 9.0]         # lane 2's centre line seen from lane 1's observer
    L[1, 16:20] = [2.0, 3.0, 5.0, 4.0]         # ... from lane 2's own observer: U_l = 2/5
    L[:, 0:4] = 0.5                            # an outer row of lane 1: in U_o, never in U_l
    m = metrics.luminance_metrics(L, lane, centre)
    np.testing.assert_allclose(m["U_l_lane"], [1.0 / 4.0, 2.0 / 5.0], rtol=REL, atol=0.0)
    assert m["U_l"] == pytest.approx(1.0 / 4.0, rel=REL, abs=0.0)
    # and over Monte Carlo trials (leading axis), lane by lane
    both = metrics.luminance_metrics(np.stack([L, L[::-1]]), lane, centre)
    np.testing.assert_allclose(both["U_l_lane"][0], [1.0 / 4.0, 2.0 / 5.0], rtol=REL, atol=0.0)
    np.testing.assert_allclose(both["U_l_lane"][1], [3.0 / 3.0, 9.0 / 9.0], rtol=REL, atol=0.0)


def test_the_centre_points_are_on_each_lanes_centre_line():
    """EN 13201-3 7.1.4: 3 points across each lane, the middle one on the lane's centre line
    (y = (k + 1/2) W_L), which is the line U_l is taken along; the observers stand on it too."""
    lay = Layout(spacing_m=30.0, lanes=3, lane_width_m=3.6)
    f = calc.build_field(lay)
    want = {k: (k + 0.5) * 3.6 for k in range(3)}
    assert np.sum(f.centre) == 3 * f.n_long
    for k in range(3):
        on = f.centre & (f.lane == k)
        np.testing.assert_allclose(f.y[on], want[k], rtol=0.0, atol=1e-12)
        assert f.observers[k, 1] == pytest.approx(want[k], rel=0.0, abs=1e-12)


def test_threshold_increment_at_its_boundary_is_the_low_luminance_formula():
    """CIE 140 / EN 13201-3: TI = 65 L_v / L_av^0.8 for L_av <= 5 cd/m^2 (the boundary included),
    95 L_v / L_av^1.05 above; the two differ at 5 (17.95 vs 17.56 L_v)."""
    assert float(calc.threshold_increment(0.3, 5.0)) == pytest.approx(65 * 0.3 / 5.0 ** 0.8, rel=REL, abs=0.0)
    assert float(calc.threshold_increment(0.3, 5.0 + 1e-9)) == pytest.approx(95 * 0.3 / (5.0 + 1e-9) ** 1.05,
                                                                             rel=REL, abs=0.0)


def test_edge_illuminance_ratio_by_hand():
    """R_EI (EN 13201-2:2015): on each edge, mean E_h over a strip just outside over that over a
    strip just inside, strips min(5 m, W / 2) wide with ceil(w / 1.5 m) >= 3 points across at the
    centres of equal parts and the field's longitudinal points; the operative value is the lower
    edge. One row over the road at y = 1 m (isotropic luminaire, E_h = I cos^3 eps / H^2 from the
    luminaires within 5 H along the road): the two edges differ, so the minimum matters."""
    lay = Layout(spacing_m=30.0, mounting_height_m=10.0, overhang_m=1.0, lanes=2, lane_width_m=3.5,
                 maintenance_factor=0.8)
    i0, h, width = 700.0, 10.0, 7.0
    strip = 3.5                                          # min(5, 7 / 2)
    off = np.array([0.5, 1.5, 2.5]) * strip / 3          # ceil(3.5 / 1.5) = 3 points across
    xs = (np.arange(10) + 0.5) * 3.0                     # the field's 10 points along (S = 30 m)

    def e_mean(ys):
        total = 0.0
        for x in xs:
            for y in ys:
                for m in range(-3, 5):
                    if abs(30.0 * m - x) <= 5 * h:
                        d2 = (30.0 * m - x) ** 2 + (1.0 - y) ** 2
                        total += 0.8 * i0 * (1 + d2 / h ** 2) ** -1.5 / h ** 2
        return total / (len(xs) * len(ys))
    low = e_mean(-off) / e_mean(off)                     # y = 0 edge: outside / inside
    high = e_mean(width + off) / e_mean(width - off)     # y = W edge
    got = calc.edge_illuminance_ratio(lay, _isotropic(i0), calc.build_field(lay))
    assert abs(low - high) > 0.05
    assert got["per_edge"]["y = 0 edge"] == pytest.approx(low, rel=REL, abs=0.0)
    assert got["per_edge"]["y = W edge"] == pytest.approx(high, rel=REL, abs=0.0)
    assert got["R_EI"] == pytest.approx(min(low, high), rel=REL, abs=0.0)


def test_the_conversion_factor_of_an_eulumdat_file_scales_its_intensities(tmp_path):
    """EULUMDAT line 24, the conversion factor for luminous intensities: I (cd) = table (cd/klm) x
    lamp flux / 1000 x factor. The bundled file has factor 1, where leaving it out does not show;
    the same file with 2.5 gives 2.5 times the intensities (and the luminances)."""
    src = bundled_luminaire_path()
    lines = src.read_bytes().decode("latin-1").split("\r\n")
    assert lines[23].strip() == "1"
    lines[23] = "2.5"
    path = tmp_path / "factor.ldt"
    path.write_bytes("\r\n".join(lines).encode("latin-1"))
    hand, scale, *_ = _hand_ldt(path)
    assert scale == pytest.approx(10000.0 / 1000.0 * 2.5, rel=REL, abs=0.0)
    one, two = read_ldt(src), read_ldt(path)
    for c, g in ((0.0, 65.0), (90.0, 30.0), (195.0, 40.0)):
        assert float(two.intensity(c, g)) == pytest.approx(hand(c, g) * scale, rel=REL, abs=0.0)
        assert float(two.intensity(c, g)) == pytest.approx(2.5 * float(one.intensity(c, g)), rel=REL, abs=0.0)
