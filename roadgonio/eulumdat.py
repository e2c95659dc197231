"""EULUMDAT (.ldt) intensity tables I(C, gamma): the one reader of the package (base room, so the
instrument's source profile and the road luminaires read their files the same way).

Parsing is done by the ``eulumdat-py`` library (import name ``pyldt``, MIT, pure Python, PyPI;
it expands the file's symmetry ISYM 0-4 to the full C range). Other candidates were looked at:
``eulumdat`` (Rust bindings) has no wheel for this platform and needs a Rust toolchain to build,
``luxpy`` is a large colour-science package with many dependencies. This module adds what a
calculation needs on top of the parser: checks with one-line errors naming the file and the field
(the library turns missing numbers into 0 and short files into short lists, and stops reading
where the header's counts end: a file's numbers are counted against its header), absolute
intensities, and interpolation.

Conventions (EN 13201-3:2015 clause 6, EULUMDAT): gamma from the downward vertical of the
luminaire (for an instrument's source: from its axis), C the azimuth. Absolute intensity = file
value (cd per 1000 lm of lamp flux) x flux of the first lamp set / 1000 x the file's conversion
factor.

Interpolation in the I-table (EN 13201-3:2015 clause 5.3.2): linear in C and in gamma (bilinear),
C periodic over 360 deg. Outside the file's gamma range the intensity is unknown (NaN): a
calculation that needs it says so.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from roadgonio.errors import InputError

_trapezoid = getattr(np, "trapezoid", None) or np.trapz


@dataclass(frozen=True)
class Luminaire:
    """An intensity table: ``cd_per_klm[i, j]`` at C = ``c_deg[i]``, gamma = ``g_deg[j]``."""

    c_deg: np.ndarray
    g_deg: np.ndarray
    cd_per_klm: np.ndarray
    flux_lm: float
    conversion: float = 1.0
    name: str = "luminaire"
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        c = np.asarray(self.c_deg, dtype=np.float64)
        g = np.asarray(self.g_deg, dtype=np.float64)
        i = np.asarray(self.cd_per_klm, dtype=np.float64)
        object.__setattr__(self, "c_deg", c)
        object.__setattr__(self, "g_deg", g)
        object.__setattr__(self, "cd_per_klm", i)
        where = self.source or self.name
        if i.shape != (len(c), len(g)):
            raise InputError(f"intensity table has shape {i.shape}, expected {(len(c), len(g))} (C x gamma)",
                             path=where, field="intensities")
        if len(g) < 2 or np.any(np.diff(g) <= 0) or g[0] < 0 or g[-1] > 180:
            raise InputError("gamma angles must increase within 0 ... 180 deg (at least two)", path=where,
                             field="gamma angles")
        if len(c) < 1 or np.any(np.diff(c) <= 0) or c[0] < 0 or c[-1] >= 360:
            raise InputError("C angles must increase within 0 ... 360 deg", path=where, field="C angles")
        if not np.all(np.isfinite(i)) or np.any(i < 0):
            raise InputError("intensities must be finite and >= 0", path=where, field="intensities")
        if not (np.isfinite(self.flux_lm) and self.flux_lm > 0):
            raise InputError(f"lamp flux must be > 0 lm, got {self.flux_lm:g}", path=where, field="lamp flux")
        if not (np.isfinite(self.conversion) and self.conversion > 0):
            raise InputError(f"conversion factor must be > 0, got {self.conversion:g}", path=where,
                             field="conversion factor")

    @property
    def scale_cd(self) -> float:
        """cd per file unit: flux / 1000 x conversion factor."""
        return self.flux_lm / 1000.0 * self.conversion

    @property
    def gamma_max_deg(self) -> float:
        return float(self.g_deg[-1])

    def intensity(self, c_deg, g_deg) -> np.ndarray:
        """Absolute intensity (cd) by bilinear interpolation; NaN outside the gamma range."""
        return self.scale_cd * self.interpolate(c_deg, g_deg)

    def interpolate(self, c_deg, g_deg) -> np.ndarray:
        """File-unit intensity (cd/klm) by bilinear interpolation (C periodic); NaN outside gamma."""
        c = np.mod(np.asarray(c_deg, dtype=np.float64), 360.0)
        g = np.asarray(g_deg, dtype=np.float64)
        c, g = np.broadcast_arrays(c, g)
        if len(self.c_deg) == 1:  # rotationally symmetric
            cg, table = np.array([0.0, 360.0]), np.vstack([self.cd_per_klm, self.cd_per_klm])
        else:
            cg = np.append(self.c_deg, self.c_deg[0] + 360.0)
            table = np.vstack([self.cd_per_klm, self.cd_per_klm[:1]])
            c = np.where(c < cg[0], c + 360.0, c)
        i = np.clip(np.searchsorted(cg, c, side="right") - 1, 0, len(cg) - 2)
        tc = (c - cg[i]) / (cg[i + 1] - cg[i])
        gg = self.g_deg
        inside = (g >= gg[0] - 1e-9) & (g <= gg[-1] + 1e-9)
        gcl = np.clip(g, gg[0], gg[-1])
        j = np.clip(np.searchsorted(gg, gcl, side="right") - 1, 0, len(gg) - 2)
        tg = (gcl - gg[j]) / (gg[j + 1] - gg[j])
        v = ((1 - tc) * (1 - tg) * table[i, j] + tc * (1 - tg) * table[i + 1, j]
             + (1 - tc) * tg * table[i, j + 1] + tc * tg * table[i + 1, j + 1])
        return np.where(inside, v, np.nan)

    def flux_from_table(self) -> float:
        """Luminaire flux (lm) integrated from the table (trapezoidal in gamma, C periodic)."""
        g = np.radians(self.g_deg)
        if len(self.c_deg) == 1:
            dc = np.array([2 * np.pi])
        else:
            cg = np.radians(np.append(self.c_deg, self.c_deg[0] + 360.0))
            dc = 0.5 * (np.diff(cg) + np.roll(np.diff(cg), 1))
        per_plane = _trapezoid(self.cd_per_klm * np.sin(g)[None, :], g, axis=1)
        return float(np.sum(per_plane * dc) * self.scale_cd)


def read_ldt(path: str | Path, *, shape_only: bool = False) -> Luminaire:
    """Read an EULUMDAT file through ``pyldt`` (eulumdat-py) and check it. ``shape_only``: only the
    distribution's shape is used (an instrument's beam profile), so absolute photometry (a negative
    number of lamps) is read too (user audit, session 45: common in LED files, and refused); the
    intensities are then the file's, unscaled."""
    from pyldt import LdtReader

    path = Path(path)
    if not path.exists():
        raise InputError("no such luminaire file (expected an EULUMDAT .ldt file)", path=path)
    try:
        text = _text(path.read_bytes())
    except OSError as err:
        raise InputError(f"cannot read the luminaire file ({err.strerror or err})", path=path) from None
    if not text.strip():        # said before the parser, which reads an empty file as a header of zeros
        raise InputError("the file is empty: expected an EULUMDAT .ldt file", path=path)
    _precheck_counts(text, path)
    _precheck_header(text, path)
    # The parser reads the file a second time: eulumdat-py's only entry, LdtReader.read, takes a path
    # and opens it itself (no text or stream), and it does not keep the text, which the count check
    # (_check_count) walks.
    try:
        ldt = LdtReader.read(path)
    except (ValueError, IndexError, ZeroDivisionError) as err:
        raise InputError(f"not a readable EULUMDAT file ({err})", path=path) from None
    except OSError as err:
        raise InputError(f"cannot read the luminaire file ({err.strerror or err})", path=path) from None
    h = ldt.header
    if h.isym not in (0, 1, 2, 3, 4):
        raise InputError(f"symmetry indicator Isym must be 0 ... 4, got {h.isym}", path=path, field="Isym (line 3)")
    if h.mc < 1 or h.ng < 2:
        raise InputError(f"expected Mc >= 1 C planes and Ng >= 2 gamma angles, got Mc = {h.mc}, Ng = {h.ng}",
                         path=path, field="Mc/Ng (lines 4, 6)")
    if h.isym in (2, 3) and h.mc % 2 or h.isym == 4 and h.mc % 4:
        raise InputError(f"Mc = {h.mc} does not fit symmetry Isym = {h.isym}", path=path, field="Mc (line 4)")
    _check_count(h, text, path)
    if len(h.c_angles) != h.mc or len(h.g_angles) != h.ng:
        raise InputError(f"expected {h.mc} C angles and {h.ng} gamma angles, one number per line as EULUMDAT "
                         "lays them out", path=path, field="angles")
    rows = ldt.intensities
    if len(rows) != h.mc or any(len(r) != h.ng for r in rows):
        raise InputError(f"expected the intensities of {h.mc} x {h.ng} (C x gamma) after symmetry expansion, one "
                         "number per line as EULUMDAT lays them out", path=path, field="intensities")
    if h.n_sets < 1 or not h.lamp_flux:
        raise InputError("no lamp set: expected at least one set with its luminous flux", path=path,
                         field="number of lamp sets (line 26)")
    _check_header(h, path, absolute_ok=shape_only)
    flux = float(h.lamp_flux[0])
    if shape_only and not (math.isfinite(flux) and flux > 0.0):
        flux = 1000.0         # the scale is not used
    conv = float(h.conv_factor) if h.conv_factor else 1.0
    c = np.asarray(h.c_angles, dtype=np.float64)
    i = np.asarray(rows, dtype=np.float64)
    if h.mc > 1 and np.allclose(c, 0.0):  # some writers leave the C list at 0 for Isym 1; rebuild it
        c = np.arange(h.mc) * 360.0 / h.mc
    order = np.argsort(np.mod(c, 360.0), kind="stable")
    c = np.mod(c, 360.0)[order]
    i = i[order]
    if h.isym == 1:
        c, i = c[:1] * 0.0, i[:1]
    name = (h.luminaire_name or path.stem).strip()
    meta = {"file": str(path), "isym": h.isym, "mc": h.mc, "ng": h.ng, "lamp_flux_lm": flux,
            "conversion_factor": conv, "lorl_pct": h.lorl, "luminaire_number": h.luminaire_number,
            "parser": "eulumdat-py (pyldt)"}
    try:
        return Luminaire(c, np.asarray(h.g_angles, dtype=np.float64), i, flux, conv, name=name,
                         source=str(path), meta=meta)
    except InputError as err:
        raise InputError(err.reason, path=path, field=err.field) from None


#: C planes stored in the file for each symmetry indicator Isym (EULUMDAT): all Mc, one, the half
#: plus one (2: C 0 ... 180; 3: C 270 ... 90), the quarter plus one (C 0 ... 90)
_STORED_PLANES = {0: lambda mc: mc, 1: lambda mc: 1, 2: lambda mc: mc // 2 + 1, 3: lambda mc: mc // 2 + 1,
                  4: lambda mc: mc // 4 + 1}


def _text(raw: bytes) -> str:
    """The file's text as the parser decodes it (a UTF-8 BOM dropped, Latin-1)."""
    return (raw[3:] if raw[:3] == b"\xef\xbb\xbf" else raw).decode("latin-1")


def _values_after_lamp_sets(text: str, n_sets: int) -> int:
    """How many values (blank-separated; any text counts) follow the lamp sets (direct ratios, C
    angles, gamma angles, intensities): lines 1-12 are one line each, lines 13-26 one number each
    (blank lines skipped), then 6 lines per lamp set, as the parser walks them."""
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    i = 12
    for _ in range(14):
        while i < len(lines) and not lines[i].strip():
            i += 1
        i += 1
    i += 6 * max(1, n_sets)
    return sum(len(line.split()) for line in lines[i:])


#: The header lines (1-based) of the counts the parser sizes its arrays by.
_COUNT_LINES = {"Isym": 3, "Mc": 4, "Ng": 6}


#: The numbers of an EULUMDAT header, by line (the lines between are text: company, report number,
#: luminaire name and number, file name, date/user).
_HEADER_NUMBERS = {2: "Ityp", 3: "Isym", 4: "Mc", 5: "Dc", 6: "Ng", 7: "Dg", 13: "length/diameter of the luminaire",
                   14: "width of the luminaire", 15: "height of the luminaire", 16: "length/diameter of the luminous area",
                   17: "width of the luminous area", 18: "height of the luminous area C0", 19: "... C90", 20: "... C180",
                   21: "... C270", 22: "downward flux fraction DFF", 23: "light output ratio LORL",
                   24: "conversion factor", 25: "tilt during measurement", 26: "number of lamp sets"}


def _precheck_header(text: str, path: Path) -> None:
    """Before the parser: every number of the fixed header (lines 2-7, 13-26, and each lamp set's
    number, flux and wattage) is a number, else the line and its field are named (user audit, session 37: a text line deleted moved the luminaire's
    name to a number's line, and the parser's "could not convert string to float: 'LED module'"
    named neither). A decimal comma is a number."""
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    numbers = dict(_HEADER_NUMBERS)
    try:                             # each lamp set's six lines: number, type, flux, colour, CRI, wattage
        sets = int(float(lines[25].strip().replace(",", "."))) if len(lines) >= 26 else 0
    except ValueError:
        sets = 0
    for k in range(max(0, min(sets, 20))):
        base = 27 + 6 * k
        numbers.update({base: f"number of lamps of set {k + 1}", base + 2: f"luminous flux of set {k + 1}",
                        base + 5: f"wattage of set {k + 1}"})
    for line, name in sorted(numbers.items()):
        raw = lines[line - 1].strip() if len(lines) >= line else ""
        try:
            float(raw.replace(",", "."))
        except ValueError:
            raise InputError(f"expected a number, got {raw!r} (a text line of the header missing or added above "
                             "it?)", path=path, field=f"{name} (line {line})") from None


def _precheck_counts(text: str, path: Path) -> None:
    """Before the parser: Isym, Mc and Ng are whole numbers and no count exceeds the values the
    file holds (the parser sizes its arrays by them: Ng = 1e11 ran out of memory, a count of 73.9
    was read as 73)."""
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    total = len(text.split())
    for name, line in _COUNT_LINES.items():
        raw = lines[line - 1].strip() if len(lines) >= line else ""
        field = f"{name} (line {line})"
        try:
            v = float(raw)
        except ValueError:
            raise InputError(f"expected a whole number, got {raw!r}", path=path, field=field) from None
        if not math.isfinite(v) or v != int(v):
            raise InputError(f"expected a whole number, got {raw}", path=path, field=field)
        if name != "Isym" and v > total:
            raise InputError(f"the header announces {name} = {int(v)}, but the whole file holds {total} values",
                             path=path, field=field)


def _check_count(h, text: str, path: Path) -> None:
    """The EULUMDAT layout fixes the file's length from Isym, Mc and Ng: 10 direct ratios, Mc C
    angles, Ng gamma angles and the stored planes' Ng intensities each. A file with fewer values
    ends early; one with more (a full table labelled Isym 1, an Ng one short) would be read shifted
    or in part, so both are refused."""
    planes = _STORED_PLANES[h.isym](h.mc)
    want = 10 + h.mc + h.ng + planes * h.ng
    got = _values_after_lamp_sets(text, h.n_sets)
    layout = (f"10 direct ratios, {h.mc} C angles, {h.ng} gamma angles and the intensities of Isym {h.isym}: "
              f"{planes} x {h.ng}")
    if got < want:
        raise InputError(f"file ends early: {got} values after the lamp sets, the header announces {want} "
                         f"({layout})", path=path, field="intensities (Isym, Mc, Ng: lines 3, 4, 6)")
    if got > want:
        extra = got - want
        raise InputError(f"{extra} value{'s' if extra > 1 else ''} after the intensities the header announces "
                         f"({layout}); expected the file to end there", path=path,
                         field="intensities (Isym, Mc, Ng: lines 3, 4, 6)")


def _check_header(h, path: Path, *, absolute_ok: bool = False) -> None:
    """Header values a road calculation depends on and that can be impossible or say something
    this module does not model: one-line errors naming the file and the EULUMDAT line."""
    if h.ityp not in (0, 1, 2, 3):
        raise InputError(f"type indicator Ityp must be 0 ... 3, got {h.ityp}", path=path, field="Ityp (line 2)")
    for name, v, line in (("DFF", h.dff, 22), ("LORL", h.lorl, 23)):
        if not (np.isfinite(v) and 0.0 <= v <= 100.0):
            raise InputError(f"{name} is a percentage of the lamp flux: expected 0 ... 100, got {v:g}", path=path,
                             field=f"{name} (line {line})")
    if h.tilt != 0.0:
        raise InputError(f"the luminaire was measured tilted by {h.tilt:g} deg; the intensities would have to be "
                         "turned back, which is not modelled: expected a tilt of 0 (a road luminaire's tilt goes in "
                         "the layout file; an instrument's source is aimed by the instrument's geometry)", path=path, field="tilt during measurement (line 25)")
    lamps = list(h.num_lamps or [])
    if lamps and lamps[0] < 0 and not absolute_ok:
        raise InputError(f"number of lamps {lamps[0]} < 0 marks absolute photometry (intensities in cd, not cd per "
                         "1000 lm of lamp flux), which is not supported: expected relative photometry (a number of "
                         "lamps >= 1)", path=path, field="number of lamps (line 27)")
    if lamps and lamps[0] == 0:
        raise InputError("expected a number of lamps >= 1 in the first lamp set, got 0", path=path,
                         field="number of lamps (line 27)")
