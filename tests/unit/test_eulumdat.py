"""roadgonio/eulumdat.py beyond the bundled file (tests/unit/test_road.py reads that one): the
interpolation's edges (the last gamma angle, a C grid that does not start at 0), the flux of an
uneven C grid, which lamp set scales the intensities, and the header checks. Mutation audit 10:
each of these could be changed without any test failing."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from helpers import ldt_text, refused_in_one_line
from roadgonio.eulumdat import Luminaire, read_ldt
from roadgonio.road.luminaire import bundled_luminaire_path

REL = 1e-12


def _lines():
    return bundled_luminaire_path().read_bytes().decode("latin-1").split("\r\n")


def _write(tmp_path, lines, name="edit.ldt"):
    p = tmp_path / name
    p.write_bytes("\r\n".join(lines).encode("latin-1"))
    return p


# 0-based line indices of the EULUMDAT header (LiTG layout): DFF line 22, LORL 23, conversion factor
# 24, tilt 25, number of lamp sets 26, then per set: number of lamps, type, flux, colour, CRI, watts
DFF, LORL, CONV, TILT, SETS, LAMPS, FLUX = 21, 22, 23, 24, 25, 26, 28


def test_the_header_lines_are_where_these_tests_edit_them():
    lines = _lines()
    assert [lines[k].strip() for k in (DFF, LORL, CONV, TILT, SETS, LAMPS, FLUX)] == \
        ["100", "100", "1", "0", "1", "1", "10000"]


def test_the_last_gamma_angle_is_inside_the_table():
    """The table's last gamma angle is a node: its value, not 'outside the range' (NaN); just beyond
    it the intensity is unknown."""
    c, g = np.array([0.0, 90.0, 180.0, 270.0]), np.array([0.0, 30.0, 60.0, 80.0])
    table = np.arange(16.0).reshape(4, 4) + 1.0
    lum = Luminaire(c, g, table, 1000.0)
    np.testing.assert_allclose(lum.interpolate(c, np.full(4, 80.0)), table[:, -1], rtol=REL, atol=0.0)
    assert float(lum.interpolate(45.0, 0.0)) == pytest.approx(0.5 * (table[0, 0] + table[1, 0]), rel=REL, abs=0.0)
    assert np.isnan(float(lum.interpolate(0.0, 80.01)))


def test_c_is_periodic_when_the_first_plane_is_not_at_zero():
    """C planes 10 ... 350: C = 5 lies between C = 350 and C = 370 (= 10), three quarters of the way
    to 10; C = 355 and -5 are the same direction."""
    c = np.arange(10.0, 351.0, 20.0)
    g = np.array([0.0, 45.0, 90.0])
    table = np.outer(1.0 + c / 100.0, [1.0, 2.0, 3.0])
    lum = Luminaire(c, g, table, 1000.0)
    want = 0.25 * table[-1, 1] + 0.75 * table[0, 1]
    assert float(lum.interpolate(5.0, 45.0)) == pytest.approx(want, rel=REL, abs=0.0)
    assert float(lum.interpolate(-5.0, 45.0)) == pytest.approx(float(lum.interpolate(355.0, 45.0)), rel=REL, abs=0.0)
    assert float(lum.interpolate(355.0, 45.0)) == pytest.approx(0.75 * table[-1, 1] + 0.25 * table[0, 1], rel=REL,
                                                                abs=0.0)


def test_flux_of_an_uneven_c_grid_is_the_integral_of_the_interpolated_table():
    """The flux is the integral of I sin(gamma) over the sphere of the table as interpolated
    (piecewise linear in C, periodic): the C integral at each gamma node by adaptive quadrature of
    :meth:`Luminaire.interpolate` itself, then the trapezoidal rule in gamma (the method's own rule
    in gamma). C planes unevenly spaced and intensities that vary with C."""
    c = np.array([0.0, 20.0, 30.0, 90.0, 150.0, 200.0, 300.0])
    g = np.array([0.0, 20.0, 40.0, 60.0, 75.0, 90.0])
    table = 100.0 + 80.0 * np.cos(np.radians(c))[:, None] * np.sin(np.radians(g))[None, :] + 3.0 * g[None, :]
    lum = Luminaire(c, g, table, 2000.0, conversion=1.5)
    per_gamma = [quad(lambda cc, gv=gv: float(lum.interpolate(cc, gv)), 0.0, 360.0, points=list(c), limit=200,
                      epsabs=0.0, epsrel=1e-12)[0] for gv in g]
    gr = np.radians(g)
    inner = np.array(per_gamma) * np.pi / 180.0 * np.sin(gr)
    want = float(np.sum(0.5 * (inner[1:] + inner[:-1]) * np.diff(gr))) * 2000.0 / 1000.0 * 1.5
    assert lum.flux_from_table() == pytest.approx(want, rel=1e-9, abs=0.0)


def test_the_first_lamp_set_scales_the_intensities(tmp_path):
    """EULUMDAT: cd per 1000 lm of the lamp flux; with two lamp sets the first one's flux (10000 lm)
    scales the table, not the sum of the sets."""
    lines = _lines()
    lines[SETS] = "2"
    second = ["2", "LED spare", "5000", "3000", "80", "40"]
    lines = lines[:FLUX + 4] + second + lines[FLUX + 4:]
    two = read_ldt(_write(tmp_path, lines))
    one = read_ldt(bundled_luminaire_path())
    assert two.flux_lm == 10000.0 and two.scale_cd == pytest.approx(10.0, rel=REL, abs=0.0)
    for cg in ((0.0, 65.0), (90.0, 30.0), (195.0, 40.0)):
        assert float(two.intensity(*cg)) == pytest.approx(float(one.intensity(*cg)), rel=REL, abs=0.0)


@pytest.mark.parametrize("index,value,words", [
    (DFF, "101", ["DFF (line 22)", "0 ... 100"]),
    (LORL, "150", ["LORL (line 23)", "0 ... 100"]),
    (LAMPS, "-1", ["number of lamps (line 27)", "absolute photometry"]),
    (TILT, "-5", ["tilt during measurement (line 25)", "-5"]),
    (TILT, "5", ["tilt during measurement (line 25)", "5"]),
])
def test_header_values_outside_what_is_modelled_are_refused(tmp_path, index, value, words):
    lines = _lines()
    lines[index] = value
    p = _write(tmp_path, lines)
    refused_in_one_line(lambda: read_ldt(p), p, words)


def _count_case(tmp_path, edit):
    """A four-plane table (C 0, 90, 180, 270; gamma 0 ... 90 every 30 deg), written with Isym 0, then
    edited as a bad export would: the file's numbers no longer match what its header announces."""
    g = np.array([0.0, 30.0, 60.0, 90.0])
    planes = np.arange(16.0).reshape(4, 4) + 1.0
    lines = ldt_text(g, planes, c_deg=(0.0, 90.0, 180.0, 270.0), isym=0).split("\r\n")
    return _write(tmp_path, edit(lines))


ISYM, MC, NG = 2, 3, 5   # 0-based line indices of Isym, Mc and Ng


def _set(index, value):
    def edit(lines):
        lines = list(lines)
        lines[index] = value
        return lines
    return edit


def test_a_file_whose_numbers_match_its_header_is_read(tmp_path):
    lum = read_ldt(_count_case(tmp_path, lambda lines: lines))
    assert lum.cd_per_klm.shape == (4, 4)


@pytest.mark.parametrize("edit,words", [
    # a full table labelled Isym 1 (a known bad export): 4 x 4 intensities where 1 x 4 are announced
    (_set(ISYM, "1"), ["12 values after the intensities", "Isym 1: 1 x 4", "expected the file to end"]),
    # Ng one short: every intensity would be read one place off, the last 4 + 1 numbers left over
    (_set(NG, "3"), ["5 values after the intensities", "Isym 0: 4 x 3", "expected the file to end"]),
    # one stray number at the end
    (lambda lines: lines[:-1] + ["7", ""], ["1 value after the intensities", "expected the file to end"]),
    # one intensity missing
    (lambda lines: lines[:-2] + [""], ["file ends early", "33 values", "announces 34", "4 x 4"]),
])
def test_a_file_with_more_or_fewer_numbers_than_its_header_announces_is_refused(tmp_path, edit, words):
    """The EULUMDAT layout fixes how many numbers follow the lamp sets (10 direct ratios, Mc C angles,
    Ng gamma angles, the stored planes' intensities): trial 11 D2, where the parser read the first Mc
    x Ng and ignored the rest."""
    p = _count_case(tmp_path, edit)
    refused_in_one_line(lambda: read_ldt(p), p, ["intensities (Isym, Mc, Ng: lines 3, 4, 6)"] + words)


def test_an_empty_file_is_called_empty_before_it_is_parsed(tmp_path, monkeypatch):
    """The empty file is refused before eulumdat-py parses it (the check ran after the parse, which
    reads an empty file as a header of zeros; a parser that failed on it would have said "not a
    readable EULUMDAT file" instead)."""
    import pyldt

    def parse(*args, **kwargs):
        raise AssertionError("an empty file was given to the parser")
    monkeypatch.setattr(pyldt.LdtReader, "read", parse)
    for name, raw in (("empty.ldt", b""), ("blank.ldt", b"\r\n \r\n\t\n")):
        p = tmp_path / name
        p.write_bytes(raw)
        refused_in_one_line(lambda p=p: read_ldt(p), p, ["the file is empty", "EULUMDAT"])


@pytest.mark.parametrize("edit,words", [
    (_set(NG, "100000000000"), ["Ng (line 6)", "Ng = 100000000000", "holds"]),
    (_set(MC, "100000000000"), ["Mc (line 4)", "Mc = 100000000000", "holds"]),
    (_set(NG, "73.9"), ["Ng (line 6)", "whole number", "73.9"]),
    (_set(MC, "4.5"), ["Mc (line 4)", "whole number"]),
    (_set(ISYM, "x"), ["Isym (line 3)", "whole number"]),
])
def test_counts_the_parser_sizes_its_arrays_by_are_checked_before_it_runs(tmp_path, monkeypatch, edit, words):
    """The user audit of session 19: Ng = 1e11 ended in a MemoryError traceback, Mc = 1e11 in the
    kernel killing the process (the parser sizes its arrays by them), and Ng = 73.9 was read as 73.
    Refused before the parser runs."""
    import pyldt

    def parse(*args, **kwargs):
        raise AssertionError("the parser ran on a header it cannot size")
    p = _count_case(tmp_path, edit)
    monkeypatch.setattr(pyldt.LdtReader, "read", parse)
    refused_in_one_line(lambda: read_ldt(p), p, words)
