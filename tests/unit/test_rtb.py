"""DIALux RTB: the layout of DIALux's documentation (one value per line, 634 lines for the standard
grid), a zero that is never a blank in disguise, and the scale of a read file checked against its
own q0 line (issue 13 item 5, issue 10 item 5)."""
from __future__ import annotations

import numpy as np
import pytest

from roadgonio.errors import InputError
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
from roadgonio.surface.rtable import RTB_Q0_AGREE, RTable, bundled_table, parse_rtb, read_table


def test_layout_is_dialux_one_value_per_line():
    t = bundled_table("R3")
    lines = t.to_rtb_text().splitlines()
    # DIALux support article "R-Tables in DIALux": 634 lines for 29 tan eps x 20 beta
    assert len(lines) == 634
    assert lines[0] == "RTable.v1" and lines[1] == "R3"
    assert lines[2] == "29" and [float(v) for v in lines[3:32]] == list(TAN_EPS_GRID)
    assert lines[32] == "20" and [float(v) for v in lines[33:53]] == list(BETA_GRID_DEG)
    assert float(lines[53]) == pytest.approx(t.q0(), rel=1e-5)  # line 54: q0 in sr^-1
    assert all(len(l.split()) == 1 for l in lines)
    # line 55 = R(eps_01, beta_01), line 56 = R(eps_02, beta_01), line 83 = R(eps_29, beta_01),
    # line 84 = R(eps_01, beta_02), line 634 = R(eps_29, beta_20); values r x 1e4, blank = 0
    assert float(lines[54]) == t.value(0, 0) * 1e4 == 294
    assert float(lines[55]) == pytest.approx(t.value(0.25, 0) * 1e4)
    assert float(lines[82]) == pytest.approx(t.value(12, 0) * 1e4)
    assert float(lines[83]) == pytest.approx(t.value(0, 2) * 1e4)
    assert lines[633] == "0" and not t.mask[-1, -1]


def test_round_trip_keeps_values_blanks_and_name(tmp_path):
    t = bundled_table("C2").with_values(bundled_table("C2").r, name="my surface (wet?) 2")
    back = read_table(t.write(tmp_path / "c2.rtb"))
    assert back.name == "my surface (wet?) 2"
    np.testing.assert_array_equal(back.mask, t.mask)
    np.testing.assert_array_equal(back.r[t.mask], t.r[t.mask])  # whole numbers survive exactly


def test_zero_is_refused_when_writing(tmp_path):
    r = bundled_table("R3").r.copy()
    r[4, 7] = 0.0
    t = RTable(r, name="z")
    with pytest.raises(InputError) as ei:
        t.write(tmp_path / "z.rtb")
    msg = str(ei.value)
    assert "tan eps = 1" in msg and "beta = 30" in msg and "CSV" in msg and "\n" not in msg
    assert not (tmp_path / "z.rtb").exists()
    back = read_table(t.write(tmp_path / "z.csv"))  # CSV keeps the zero as a zero
    assert back.r[4, 7] == 0.0 and back.mask[4, 7]


def test_zero_read_is_blank():
    lines = bundled_table("R3").to_rtb_text().splitlines()
    lines[54 + 3] = "0"  # R(tan 0.75, beta 0)
    t = parse_rtb("\n".join(lines))
    assert not t.mask[3, 0] and t.mask[2, 0]


def test_reader_is_tolerant_of_layout():
    t = bundled_table("R2")
    lines = t.to_rtb_text().splitlines()
    # roadgonio's older layout: grid values on one line, one beta column per line; CRLF; decimal comma
    old = [lines[0], lines[1], lines[2], " ".join(lines[3:32]), lines[32], " ".join(lines[33:53]),
           lines[53].replace(".", ",")]
    old += [" ".join(lines[54 + 29 * j: 54 + 29 * (j + 1)]) for j in range(20)]
    back = parse_rtb("\r\n".join(old).replace("\r\n", "\n") + "\n\n")
    np.testing.assert_array_equal(back.r[t.mask], t.r[t.mask])
    back2 = parse_rtb("\n\n" + "\n".join(lines))  # leading blank lines
    assert back2.name == "R2"


def _with_q0(q0: float, values_scale: float = 1e4) -> str:
    t = bundled_table("R3")
    lines = t.to_rtb_text().splitlines()
    lines[53] = f"{q0:.6g}"
    if values_scale != 1e4:
        lines[54:] = ["0" if not np.isfinite(v) else f"{v * values_scale:.6g}" for v in t.r.T.ravel()]
    return "\n".join(lines)


def test_scale_checked_against_q0_line():
    t = bundled_table("R3")
    # values r x 1e4 and q0 in sr^-1: the documented case, no note
    ok = parse_rtb(_with_q0(t.q0()))
    np.testing.assert_allclose(ok.r[t.mask], t.r[t.mask])
    assert ok.source == "R3 read from <table>"          # the stored name kept (session 41)
    # values in sr^-1 (another writer), q0 in sr^-1: read at that scale, said so
    plain = parse_rtb(_with_q0(t.q0(), values_scale=1.0))
    np.testing.assert_allclose(plain.r[t.mask], t.r[t.mask], rtol=1e-5)
    assert "sr^-1" in plain.source
    # q0 written at the values' scale (x 1e4)
    big = parse_rtb(_with_q0(t.q0() * 1e4))
    np.testing.assert_allclose(big.r[t.mask], t.r[t.mask])
    assert "x 1e4" in big.source
    # the nominal class q0 (0.07 for R3, 0.3 % off) passes silently; 25 % off is read but noted
    assert "differs" not in parse_rtb(_with_q0(0.07)).source
    off = parse_rtb(_with_q0(t.q0() * (1 + RTB_Q0_AGREE + 0.10)))
    np.testing.assert_allclose(off.r[t.mask], t.r[t.mask])
    assert "differs" in off.source and "+25 %" in off.source


@pytest.mark.parametrize("q0", [0.007, 0.7, 70.0])
def test_q0_line_that_fits_no_scale_is_refused(tmp_path, q0):
    path = tmp_path / "bad.rtb"
    path.write_text(_with_q0(q0))
    with pytest.raises(InputError) as ei:
        read_table(path)
    msg = str(ei.value)
    assert f"{path}:54" in msg and "q0" in msg and "\n" not in msg


@pytest.mark.parametrize("edit,line,words", [
    (lambda L: L.__setitem__(2, "29.5"), 3, ["whole number"]),
    (lambda L: L.__setitem__(100, "abc"), 101, ["expected a number", "abc"]),
    (lambda L: L.append("5"), 635, ["unexpected"]),
    (lambda L: L.pop(), 633, ["ends early"]),
])
def test_bad_rtb_names_file_and_line(tmp_path, edit, line, words):
    lines = bundled_table("R3").to_rtb_text().splitlines()
    edit(lines)
    path = tmp_path / "bad.rtb"
    path.write_text("\n".join(lines))
    with pytest.raises(InputError) as ei:
        read_table(path)
    msg = str(ei.value)
    assert f"{path}:{line}" in msg, msg
    for w in words:
        assert w in msg


def test_q0_line_0_with_values_in_sr_is_refused_not_read_1e4_too_small(tmp_path):
    """(audit 22) a q0 line of 0 (not given) skipped every check of the scale: values in sr^-1 were
    read as r x 1e4, 10^4 too small, without a word. The values' own scale decides then, as a CSV's
    does; values in r x 1e4 with q0 0 still read. A negative q0 is refused."""
    t = bundled_table("R3")
    lines = t.to_rtb_text().splitlines()
    lines[53] = "0"
    np.testing.assert_allclose(parse_rtb("\n".join(lines)).r[t.mask], t.r[t.mask])
    sr = lines[:54] + [f"{float(v) / 1e4:.8g}" for v in lines[54:]]
    with pytest.raises(InputError, match="looks like r in sr\\^-1") as ei:
        parse_rtb("\n".join(sr), path=tmp_path / "sr.rtb")
    assert ei.value.line == 54 and ei.value.field == "q0"
    lines[53] = "-0.07"
    with pytest.raises(InputError, match="expected q0 >= 0"):
        parse_rtb("\n".join(lines))


def test_blank_lines_before_the_surface_name_are_skipped():
    """(audit 22) the docs accept blank lines, but the name was taken from line 2 by position: a
    blank line 2 made the name the number of tan eps values. A blank name line followed by the
    numbers still names the table by its file."""
    lines = bundled_table("R3").to_rtb_text().splitlines()
    t = parse_rtb("\n".join(lines[:1] + ["", "  "] + lines[1:]), path="x.rtb")
    assert t.name == "R3"
    np.testing.assert_allclose(t.r[t.mask], bundled_table("R3").r[t.mask])
    assert parse_rtb("\n".join(lines[:1] + [""] + lines[2:]), path="dir/x.rtb").name == "x"
