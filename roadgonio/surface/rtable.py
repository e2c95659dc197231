"""r-tables: reading and writing (CSV and DIALux RTB), the CIE 144 characteristics S1, S2, Q0,
and the bundled CIE standard tables R1-R4, C1, C2.

Internally an :class:`RTable` holds r in sr^-1 (float64) on the standard grid
(:data:`~roadgonio.geometry.TAN_EPS_GRID` x :data:`~roadgonio.geometry.BETA_GRID_DEG`), with
NaN for blank ("not measured") cells. Files hold r x 10^4, as the published tables do.

CSV layout (that of ``data/rtables/``)::

    # source: ...            (optional comment lines starting with '#')
    tan_eps,0,2,5,...,180    (header: beta in degrees)
    0,294,294,...            (29 rows, first cell tan eps, then r x 1e4; empty cell = blank)

RTB layout (DIALux ``.rtb``): "For every single information a new line will be used" (DIAL's
support article "R-Tables in DIALux", DIALux 4.6 and later, English and German versions, and the
"R-table in DIALux (engl)" PDF: https://evo.support-en.dial.de/support/solutions/articles/9000073306).
For the 29 x 20 standard grid that is 634 lines::

    line 1        RTable.v1                 (must not be changed)
    line 2        <name of the surface>     (shown in DIALux, e.g. "CIE R3")
    line 3        <nEps>                    (number of tan eps values, 29)
    lines 4-32    tan eps, one value per line
    line 33       <nBeta>                   (number of beta values, 20)
    lines 34-53   beta in degrees, one value per line
    line 54       q0                        (Q0 in sr^-1)
    lines 55-634  R(tan eps_i, beta_j), one value per line, tan eps varying fastest:
                  R(eps_01, beta_01), R(eps_02, beta_01), ... R(eps_29, beta_01), R(eps_01, beta_02), ...

(The article's example numbers the last value of the first beta column "line 84"; counting its own
list it is line 83.) The article does not state the scale of the R values; it says the layout follows
the r-tables of EN 13201, which print r x 10^4, and roadgonio writes r x 10^4 (so an RTB file reads
like the printed table) with q0 in sr^-1. The reader checks the scale of a file against its own q0
line (:func:`parse_rtb`).

RTB has no blank marker. Blank ("not measured") cells are written as 0 and every 0 read is a blank,
as in the electronic copies of the CIE tables (SOURCES.md). So that a 0 is never a blank in disguise,
writing refuses a table with a real r = 0 cell (write CSV, which keeps 0 and blank apart).
The reader is tolerant: values may share lines (roadgonio's older layout, one beta column per line),
blank lines are skipped, CR/CRLF line ends and a decimal comma are accepted.
"""
from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from roadgonio.errors import InputError
from roadgonio.fileio import atomic_write_text, read_user_text
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID, nearest_grid_node

#: Scale of r in files (published tables store r x 10^4).
R_SCALE = 1e4
#: The largest r accepted from a table file (sr^-1): 125 times the largest CIE value (C1: 0.077), so a
#: table in the wrong scale or an exponent typo (1e300) is an error, not a fit to nonsense.
R_MAX_PLAUSIBLE = 10.0
#: A CSV r-table whose largest value (r x 10^4) is below this is refused as written in sr^-1: 1 is the
#: smallest value of any cell of the bundled CIE tables (C1; their largest values are 362 (R3) to 770
#: (C1)), so any table holding even one CIE-like cell passes, while the same tables written in sr^-1
#: have largest values 0.036 to 0.077. Not applied to tables of standard uncertainties (``quantity="u"``).
R_X1E4_LARGEST_MIN = 1.0
#: The largest reflectance over the tabulated incidence directions (:meth:`RTable.reflectance`) an
#: r-table may have: no surface reflects more light than reaches it. The CIE tables have 0.15
#: (R3) to 0.27 (C1); the same tables read as r x 1e6 have 15-27 and tables of q = r / cos^3 eps read
#: as r 5-10 (audit 28: both were accepted, fitted and corrected, and failed when written as RTB).
REFLECTANCE_MAX = 1.0
BUNDLED = ("R1", "R2", "R3", "R4", "C1", "C2")
#: Published CIE values (docs/conventions.md section 2).
PUBLISHED_S1 = {"R1": 0.25, "R2": 0.58, "R3": 1.11, "R4": 1.55, "C1": 0.24, "C2": 0.97}
PUBLISHED_Q0 = {"R1": 0.10, "R2": 0.07, "R3": 0.07, "R4": 0.08, "C1": 0.10, "C2": 0.07}
GRID_TOL = 1e-9


#: S1's cells (tan eps, beta deg): numerator r(tan 2, beta 0), denominator r(tan 0, beta 0) (CIE 144),
#: for every computation of S1 (the table's, the Monte Carlo's vectors, the correction's u(S1)).
S1_CELLS = ((2.0, 0.0), (0.0, 0.0))


@dataclass(frozen=True)
class RTable:
    """An r-table: ``r[i, j]`` = r(tan_eps[i], beta[j]) in sr^-1, NaN where blank."""

    r: np.ndarray
    name: str = "table"
    source: str = ""
    tan_eps: np.ndarray = field(default_factory=lambda: TAN_EPS_GRID.copy())
    beta_deg: np.ndarray = field(default_factory=lambda: BETA_GRID_DEG.copy())

    def __post_init__(self):
        r = np.asarray(self.r, dtype=np.float64)
        object.__setattr__(self, "r", r)
        if r.shape != (len(self.tan_eps), len(self.beta_deg)):
            raise InputError(f"r has shape {r.shape}, expected {(len(self.tan_eps), len(self.beta_deg))}",
                             field="r")

    # -- derived -----------------------------------------------------------------------------
    @property
    def mask(self) -> np.ndarray:
        """True where the cell is tabulated."""
        return np.isfinite(self.r)

    @property
    def cells(self) -> list[tuple[float, float]]:
        """(tan eps, beta deg) of every tabulated cell, row by row."""
        ii, jj = np.nonzero(self.mask)
        return [(float(self.tan_eps[i]), float(self.beta_deg[j])) for i, j in zip(ii, jj)]

    @property
    def r_max(self) -> float:
        """The largest tabulated r (NaN for a table without values)."""
        return float(np.max(self.r[self.mask])) if self.mask.any() else math.nan

    def value(self, tan_eps: float, beta_deg: float) -> float:
        i = _index(self.tan_eps, tan_eps, "tan_eps")
        j = _index(self.beta_deg, beta_deg, "beta")
        return float(self.r[i, j])

    def s1(self) -> float:
        """Specular factor S1 = r(beta=0, tan=2) / r(beta=0, tan=0) (CIE 144; :data:`S1_CELLS`); NaN
        (missing) when r(0, 0) is blank or 0 or r(2, 0) is blank: a quantity that needs a missing value
        is missing, never a division by zero (:func:`missing_ratio`)."""
        (tn, bn), (td, bd) = S1_CELLS
        return missing_ratio(self.value(tn, bn), self.value(td, bd))

    def q0(self) -> float:
        """Average luminance coefficient Q0 (sr^-1): mean of q over the solid angle of the
        tabulated illumination directions (CIE 144), ``sum(q0_weights(mask) * r)``
        (:func:`q0_weights`); NaN when no grid cell has four tabulated corners."""
        w = q0_weights(self.mask, self.tan_eps, self.beta_deg)
        if w is None:
            return math.nan
        return float(np.sum(np.where(w > 0.0, w * self.r, 0.0)))

    def reflectance(self) -> float:
        """The light the surface reflects towards the observer (alpha = 1 deg) for a uniform radiance
        from the tabulated incidence directions, by reciprocity its directional reflectance towards
        the source side: ``int f cos eps d omega`` with f = q = r / cos^3 eps, ``d omega = sin eps
        d eps d beta``, i.e. ``int int r tan eps cos eps d(tan eps) d beta`` over beta in [0, pi]
        twice (the table is symmetric), trapezoids over the table's grid with blanks as 0. At most 1
        for any surface (energy conservation), so above 1 the values are not r (docs/inputs-outputs.md,
        "r-tables: CSV")."""
        t = np.asarray(self.tan_eps, dtype=np.float64)
        b = np.radians(np.asarray(self.beta_deg, dtype=np.float64))
        g = np.nan_to_num(self.r, nan=0.0) * (t / np.sqrt(1.0 + t * t))[:, None]
        inner = 2.0 * np.trapezoid(g, b, axis=1) if b.size > 1 else np.zeros(t.size)
        return float(np.trapezoid(inner, t)) if t.size > 1 else 0.0

    def s2(self) -> float:
        """S2 = Q0 / r(0, 0) (CIE 144); NaN (missing) when Q0 is undefined or r(0, 0) is blank or 0."""
        return missing_ratio(self.q0(), self.value(0.0, 0.0))

    # -- xarray (the Python API's r-table) ----------------------------------------------------
    def to_dataarray(self):
        """The table as an ``xarray.DataArray`` of r in sr^-1 (not r x 10^4) over ``tan_eps`` x
        ``beta`` (degrees), NaN where blank; ``attrs`` name and source."""
        import xarray as xr
        return xr.DataArray(
            self.r.copy(), dims=("tan_eps", "beta"),
            coords=grid_coords(self.tan_eps, self.beta_deg), name="r", attrs={"name": self.name, "source": self.source, "units": "sr^-1",
                             "long_name": "reduced luminance coefficient r = q cos^3(epsilon)",
                             "note": "r itself, not r x 10^4; NaN = not measured"})

    @classmethod
    def from_dataarray(cls, da, what: str = "table") -> "RTable":
        """An RTable from an r-table DataArray (dims ``tan_eps`` and ``beta`` on the CIE grid, r in
        sr^-1); errors name ``what``."""
        if set(da.dims) != {"tan_eps", "beta"}:
            raise InputError(f"expected a DataArray with dims (tan_eps, beta), got {da.dims}", field=what)
        da = da.transpose("tan_eps", "beta")
        for dim, grid in (("tan_eps", TAN_EPS_GRID), ("beta", BETA_GRID_DEG)):
            got = np.asarray(da[dim].values, dtype=np.float64)
            if got.shape != grid.shape or np.max(np.abs(got - grid)) > GRID_TOL:
                raise InputError(f"the {dim} coordinate is not the CIE grid ({', '.join(f'{v:g}' for v in grid)})",
                                 field=what)
        name = da.attrs.get("name", da.name if da.name is not None else "table")
        source = da.attrs.get("source", "")
        for key, v in (("name", name), ("source", source)):
            if not isinstance(v, str):
                raise InputError(f"expected text for the table's {key} (attrs['{key}']), got {type(v).__name__} {v!r}",
                                 field=f"{what}.{key}")
        try:
            r = np.asarray(da.values, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"expected numbers (r in sr^-1), got values of dtype {da.dtype}", field=what) from None
        check_r_values(r, what)
        table = cls(r, name=name, source=source)
        if not (names_ka(table) or names_ka_output(table) or names_u(table)):   # (what they are is said later)
            check_reflectance(table, field=what)
        return table

    def same_grid(self, other: "RTable") -> bool:
        return (self.r.shape == other.r.shape
                and np.allclose(self.tan_eps, other.tan_eps, atol=GRID_TOL, rtol=0)
                and np.allclose(self.beta_deg, other.beta_deg, atol=GRID_TOL, rtol=0))

    def digest(self) -> str:
        """Eight hex digits of SHA-256 over the grid and the values (float64 bytes, every missing cell
        one NaN): what tells two tables of one name apart, e.g. two sites' measured.csv in the header
        ``roadgonio correct`` writes (:func:`measured_label`)."""
        import hashlib
        h = hashlib.sha256()
        for a in (self.tan_eps, self.beta_deg, np.where(np.isfinite(self.r), self.r, np.nan)):
            h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
        return h.hexdigest()[:8]

    def with_values(self, r: np.ndarray, name: str | None = None, source: str | None = None) -> "RTable":
        return RTable(np.asarray(r, dtype=np.float64), name=self.name if name is None else name,
                      source=self.source if source is None else source,
                      tan_eps=self.tan_eps.copy(), beta_deg=self.beta_deg.copy())

    # -- writing -----------------------------------------------------------------------------
    def to_csv_text(self, scale: float = R_SCALE, digits: int = 6) -> str:
        """The CSV text (module docstring). An r-table (``scale`` = :data:`R_SCALE`) is read back as
        :func:`load_table` reads it (:func:`parse_csv`, then :func:`check_csv_table`) before it is
        returned: a table the reader would refuse (negative, infinite, implausible values, no value
        at all, a largest value that looks like sr^-1, a k_A header) raises the reader's reason as an
        :class:`InputError` instead of being written."""
        _check_finite(self.r, self.tan_eps, self.beta_deg, "CSV")
        source = self.source or f"roadgonio table {self.name}"
        # a table of standard uncertainties (its header says so) is read back as one
        quantity = "u" if names_u(self) else "r"
        if scale == R_SCALE and not any(line.lstrip("# ").startswith(UNITS_LINE_START)
                                        for line in source.splitlines()):
            # the scale said in the file itself, for a reader with a spreadsheet (session 44's open item:
            # a CSV from `table --to` did not say its values are r x 1e4); read back as a comment
            source = f"{source}\n{units_line(quantity)}"
        text = grid_csv_text(self.r, source, scale=scale, digits=digits,
                             tan_eps=self.tan_eps, beta_deg=self.beta_deg)
        if scale == R_SCALE:
            _reads_back(lambda: check_csv_table(parse_csv(text, path="<table>", name=self.name, quantity=quantity),
                                                "<table>", quantity), "CSV", text, self.r, digits)
        return text

    def write_csv(self, path: str | Path, scale: float = R_SCALE, digits: int = 6) -> Path:
        return atomic_write_text(path, self.to_csv_text(scale, digits))

    def to_rtb_text(self) -> str:
        """DIALux RTB text: one value per line (module docstring), r x 1e4, blanks as 0.

        Raises :class:`InputError` if a cell holds r = 0 (RTB would read it back as a blank), if Q0
        is undefined (the q0 line), or if :func:`parse_rtb` would refuse the text (its reason)."""
        _check_finite(self.r, self.tan_eps, self.beta_deg, "RTB")
        zero = np.argwhere(self.r == 0.0)
        if len(zero):
            i, j = zero[0]
            raise InputError(f"cannot write RTB: r = 0 at tan eps = {self.tan_eps[i]:g}, beta = {self.beta_deg[j]:g} "
                             f"({len(zero)} zero cell(s)); RTB stores blanks as 0, so a zero would come back as "
                             "'not measured'. Write CSV (.csv), which keeps 0 and blank apart (fit, correct and the commands "
                             "that take a sample refuse a 0: no road's r is 0; blank it, or give the reading)", field="r")
        q0 = self.q0()
        if not math.isfinite(q0):
            raise InputError("cannot write RTB: Q0 is undefined (no grid cell has four tabulated corners) and RTB "
                             "needs its q0 line. Write CSV (.csv), which needs no Q0", field="q0")
        name = " ".join(self.name.split()) or "table"
        lines = ["RTable.v1", name, str(len(self.tan_eps)), *(_fmt(t, 6) for t in self.tan_eps),
                 str(len(self.beta_deg)), *(_fmt(b, 6) for b in self.beta_deg), _fmt(self.q0(), 6)]
        for j in range(len(self.beta_deg)):
            lines.extend("0" if np.isnan(v) else _fmt(v, 6) for v in self.r[:, j] * R_SCALE)
        text = "\n".join(lines) + "\n"
        _reads_back(lambda: check_rtb_table(parse_rtb(text, path="<table>")), "RTB", None, self.r, 6)
        return text

    def write_rtb(self, path: str | Path) -> Path:
        try:
            text = self.to_rtb_text()
        except InputError as err:
            if err.path is not None:
                raise
            # the file being written is named (user audit, session 29: 'field r: cannot write RTB' named none)
            raise InputError(err.reason, path=path, line=err.line, field=err.field, argument=err.argument) from None
        return atomic_write_text(path, text)

    def write(self, path: str | Path) -> Path:
        """Write by suffix: ``.rtb`` as DIALux RTB, anything else as CSV."""
        return self.write_rtb(path) if Path(path).suffix.lower() == ".rtb" else self.write_csv(path)


def check_r_values(r: np.ndarray, field: str = "table") -> None:
    """The values of an r-table given as an array (r in sr^-1, NaN = blank) obey the rules of the
    table files' readers: finite where given, >= 0, at most :data:`R_MAX_PLAUSIBLE`, at least one."""
    def where(mask) -> str:
        i, j = np.argwhere(mask)[0]
        return f"at tan eps = {TAN_EPS_GRID[i]:g}, beta = {BETA_GRID_DEG[j]:g}" if r.shape == (
            len(TAN_EPS_GRID), len(BETA_GRID_DEG)) else f"at index ({i}, {j})"
    if r.ndim != 2:
        raise InputError(f"expected a 2-D table (tan_eps x beta), got shape {r.shape}", field=field)
    if np.isinf(r).any():
        raise InputError(f"expected finite r (NaN = blank), got {r[np.isinf(r)][0]} {where(np.isinf(r))}", field=field)
    if (r < 0).any():
        raise InputError(f"r must not be negative, got {r[r < 0][0]:g} {where(r < 0)} (a cell not measured is blank, "
                         "NaN; fit and correct refuse a 0 too)", field=field)
    if (r > R_MAX_PLAUSIBLE).any():
        raise InputError(f"r = {r[r > R_MAX_PLAUSIBLE][0]:g} sr^-1 {where(r > R_MAX_PLAUSIBLE)} is not a plausible road "
                         f"value (expected r <= {R_MAX_PLAUSIBLE:g} sr^-1; r itself, not r x 1e4)", field=field)
    if not np.isfinite(r).any():
        raise InputError("the table has no values (every cell is blank)", field=field)


def _check_finite(r: np.ndarray, tan_eps: np.ndarray, beta_deg: np.ndarray, fmt: str) -> None:
    """An infinite r is no table value (NaN is a blank; a CSV would write it as one)."""
    bad = np.argwhere(np.isinf(r))
    if len(bad):
        i, j = bad[0]
        raise InputError(f"cannot write this r-table as {fmt}: r = {r[i, j]} at tan eps = {tan_eps[i]:g}, beta = "
                         f"{beta_deg[j]:g} ({len(bad)} cell(s)); expected a finite number", field="r")


def _reads_back(read, fmt: str, csv_text: str | None = None, r: np.ndarray | None = None, digits: int = 6) -> None:
    """Run the reader on a text about to be written: its refusal becomes the writer's, one line
    with the reader's reason (a writer never writes what its reader refuses); for CSV the row's
    tan eps is named. The table read back must hold the blanks and the values ``r`` (within the
    ``digits`` written)."""
    try:
        back = read()
        if r is not None:
            same = back.mask == np.isfinite(r)
            close = np.isclose(back.r, r, rtol=10.0 ** (1 - digits), atol=1e-300) | ~np.isfinite(r)
            if not (same.all() and close.all()):
                i, j = np.argwhere(~(same & close))[0]
                raise InputError(f"tan eps = {TAN_EPS_GRID[i]:g}, beta = {BETA_GRID_DEG[j]:g} would read back as "
                                 f"{back.r[i, j]:g} instead of {r[i, j]:g}", field="r")
    except InputError as err:
        where = ""
        if csv_text is not None and err.line is not None:
            lines = csv_text.splitlines()
            if 0 < err.line <= len(lines) and not lines[err.line - 1].startswith(("#", "tan_eps")):
                where = f"tan eps = {lines[err.line - 1].split(',')[0]}, "
        raise InputError(f"cannot write this r-table as {fmt}: the file would not read back ({where}{err.reason})",
                         field=err.field or "r") from None


def missing_ratio(num, den):
    """``num / den`` of two table quantities, or NaN (missing) when either is missing (NaN) or the
    denominator is not > 0 (a characteristic such as S1 of a table with r(0, 0) = 0 is undefined,
    not infinite). Elementwise for arrays (a float for two numbers)."""
    n, d = np.asarray(num, dtype=np.float64), np.asarray(den, dtype=np.float64)
    ok = np.isfinite(n) & np.isfinite(d) & (d > 0.0)
    out = np.where(ok, n / np.where(ok, d, 1.0), np.nan)
    return float(out) if out.ndim == 0 else out


#: The first words of the header of a table's standard uncertainties (``corrected_u.csv``): the rest
#: of the line is the header of the table it belongs to (:func:`u_names_table`).
U_HEADER = "standard uncertainty of "
#: The smallest relative standard uncertainty of a measured cell (0.0001 %): far below any
#: goniophotometer's, far above where a fit's weights 1/u^2 overflow (roadgonio correct's, and the
#: repeatability of a participant of an intercomparison, whose tables it corrects).
U_REL_MIN = 1e-6


def header_line(t: "RTable") -> str:
    """The first line of a table's header (its ``source``), "" when it has none."""
    return t.source.splitlines()[0].strip() if t.source else ""


#: The header ``roadgonio uncertainty`` writes on its tables (``<case>_u.csv``, ``<case>_mean.csv``,
#: :func:`roadgonio.uncertainty.report.write_results`): the sample's name and what the table holds.
UNCERTAINTY_HEADER = re.compile(r"^roadgonio uncertainty: .*, sample (?P<sample>.+): (?P<what>mean r x 1e4|"
                                r"standard uncertainty u\(r\) x 1e4)$")


def u_names_sample(u: "RTable") -> tuple[str, bool] | None:
    """(sample name, whether it is a standard uncertainty) of a table ``roadgonio uncertainty`` wrote
    (:data:`UNCERTAINTY_HEADER`; False: its mean table), or None for any other header."""
    m = UNCERTAINTY_HEADER.match(header_line(u))
    return None if m is None else (m["sample"], m["what"].startswith("standard"))


#: The file of the correlation between a table's cells (``roadgonio correct``'s corrected_corr.csv,
#: read by ``road --corr``): a comment line, then ``cell,<label>,...`` and one row per cell, labelled
#: ``tan eps/beta`` (:func:`cell_label`), values to :data:`CORR_DIGITS` decimals.
CORR_COMMENT = "correlation of the corrected cells (rows and columns labelled tan eps/beta)"
#: The first words of the first line of a correlation file that names its table (correct's
#: corrected_corr.csv, as corrected_u.csv's :data:`U_HEADER` does): the rest of the line is the
#: header of that table; the next line says how the cells are labelled (:data:`CORR_LABELS`).
CORR_HEADER = "correlation of the cells of "
CORR_LABELS = "rows and columns labelled tan eps/beta"
CORR_DIGITS = 4
#: The largest error of a stored correlation: half its last decimal.
CORR_ROUNDING = 0.5 * 10.0 ** -CORR_DIGITS


#: How far a grid label written in a file (a tan eps or beta of a table's header or rows, a cell of
#: a correlation file) may be from the standard grid's value and still be that value (text rounding).
GRID_LABEL_TOL = 1e-6


def cell_label(tan_eps: float, beta_deg: float) -> str:
    """A cell's label in a correlation file: ``tan eps/beta`` (``0.25/10``)."""
    return f"{tan_eps:g}/{beta_deg:g}"


def correlation_text(cells, corr: np.ndarray, table: str | None = None) -> str:
    """The correlation matrix ``corr`` of ``cells`` ((tan eps, beta) pairs) as a correlation file;
    ``table``: the header (first line) of the table the cells are of, named on the file's first line
    (:data:`CORR_HEADER`; without it, :data:`CORR_COMMENT`)."""
    labels = [cell_label(t, b) for t, b in cells]
    buf = io.StringIO()
    buf.write(f"# {CORR_HEADER}{table}\n# {CORR_LABELS}\n" if table else f"# {CORR_COMMENT}\n")
    buf.write("cell," + ",".join(labels) + "\n")
    for k, lab in enumerate(labels):
        buf.write(lab + "," + ",".join(f"{v:.{CORR_DIGITS}f}" for v in corr[k]) + "\n")
    return buf.getvalue()


def _grid_cell(label: str, path, line: int) -> tuple[float, float]:
    """(tan eps, beta) of a label ``tan eps/beta`` on the standard grid, or an InputError."""
    parts = label.strip().split("/")
    if len(parts) != 2:
        raise InputError(f"expected a cell label 'tan eps/beta' (e.g. 0.25/10), got {label!r}", path=path, line=line)
    t = _parse_number(parts[0], path, line, f"cell {label!r}, tan eps")
    b = _parse_number(parts[1], path, line, f"cell {label!r}, beta")
    i, j, off = nearest_grid_node(t, b)
    if off > GRID_LABEL_TOL:
        raise InputError(f"cell {label!r} is not on the standard grid (tan eps 0 ... 12, beta 0 ... 180)", path=path,
                         line=line)
    return float(TAN_EPS_GRID[i]), float(BETA_GRID_DEG[j])


def read_cell_correlation(path: str | Path, table: str | None = None) -> tuple[list[tuple[float, float]], np.ndarray]:
    """The cells ((tan eps, beta) on the standard grid) and their correlation matrix from a
    correlation file (:data:`CORR_COMMENT`; corrected_corr.csv). ``table``: the header (first line)
    of the table it is used with; a file whose first line names another table (:data:`CORR_HEADER`)
    is refused (a file that names none, as before the name was written, is not checked). Every
    mistake is one :class:`InputError` naming the file, the line and what was expected: labels not
    on the grid or twice, a row not labelled as its column, a value not a number, beyond +-1, a
    diagonal not 1 or an asymmetry larger than the stored rounding (:data:`CORR_ROUNDING`)."""
    p = Path(path)
    if not p.is_file():
        raise InputError("no such correlation file" if not p.exists() else "expected a correlation file, not a folder",
                         path=p)
    text = read_user_text(p, "correlation file")
    labels: list[str] | None = None
    cells: list[tuple[float, float]] = []
    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if lineno == 1 and table and line.startswith("#") and line[1:].strip().startswith(CORR_HEADER):
            named = line[1:].strip()[len(CORR_HEADER):].strip()
            if named != table.strip():
                raise InputError(f"is the correlation of the cells of '{named}', but it goes with the table whose "
                                 f"header says '{table.strip()}': give the correlation file written with that table "
                                 "(correct's corrected_corr.csv beside its corrected_u.csv)", path=p, line=lineno)
        if not line or line.startswith("#"):
            continue
        fields = next(csv.reader([raw]))
        if labels is None:
            if fields[0].strip().lower() != "cell" or len(fields) < 2:
                raise InputError(f"expected a header 'cell,<tan eps/beta>,...' (as correct writes corrected_corr.csv), "
                                 f"got {line[:60]!r}", path=p, line=lineno)
            labels = [f.strip() for f in fields[1:]]
            cells = [_grid_cell(lab, p, lineno) for lab in labels]
            if len(set(cells)) != len(cells):
                dup = next(lab for lab, c in zip(labels, cells) if cells.count(c) > 1)
                raise InputError(f"cell {dup!r} is labelled twice in the header", path=p, line=lineno)
            continue
        k = len(rows)
        if k >= len(labels):
            raise InputError(f"expected {len(labels)} rows, one per cell of the header; found more", path=p,
                             line=lineno)
        if fields[0].strip() != labels[k]:
            raise InputError(f"row {k + 1} must be labelled {labels[k]!r} (the header's cell {k + 1}), got "
                             f"{fields[0].strip()!r}", path=p, line=lineno)
        if len(fields) != len(labels) + 1:
            raise InputError(f"expected {len(labels) + 1} fields (the label and one value per cell), found "
                             f"{len(fields)}", path=p, line=lineno)
        vals = [_parse_number(f.strip(), p, lineno, f"column {lab!r}") for f, lab in zip(fields[1:], labels)]
        bad = next((lab for v, lab in zip(vals, labels) if abs(v) > 1.0 + CORR_ROUNDING), None)
        if bad is not None:
            raise InputError(f"column {bad!r}: a correlation must be between -1 and 1", path=p, line=lineno)
        rows.append(vals)
    if labels is None:
        raise InputError("empty correlation file: expected a header 'cell,<tan eps/beta>,...' and one row per cell",
                         path=p)
    if len(rows) != len(labels):
        raise InputError(f"expected {len(labels)} rows, one per cell of the header; found {len(rows)}", path=p)
    c = np.array(rows)
    k = int(np.argmax(np.abs(np.diag(c) - 1.0)))
    if abs(c[k, k] - 1.0) > CORR_ROUNDING:
        raise InputError(f"cell {labels[k]!r}: the diagonal must be 1 (a cell's correlation with itself), got "
                         f"{c[k, k]:g}", path=p)
    asym = np.abs(c - c.T)
    if asym.max() > 2 * CORR_ROUNDING:
        i, j = np.unravel_index(int(np.argmax(asym)), c.shape)
        raise InputError(f"cells {labels[i]!r} and {labels[j]!r}: the matrix must be symmetric, got {c[i, j]:g} and "
                         f"{c[j, i]:g}", path=p)
    return cells, c


#: The start of a header line that carries a note for the table's readers, one line each after the
#: first: corrected_u.csv's "note: the data reject the eq. 4 fit ...", which ``road --u`` repeats.
NOTE_PREFIX = "note: "


def header_notes(t: "RTable") -> list[str]:
    """The notes (:data:`NOTE_PREFIX` lines after the first) of a table's header, without the prefix."""
    lines = [x.strip() for x in (t.source or "").splitlines()[1:]]
    return [x[len(NOTE_PREFIX):] for x in lines if x.startswith(NOTE_PREFIX)]


#: The words in the header of every table ``roadgonio correct`` corrects (corrected.csv: "R3 corrected
#: for the aperture effect (r / k_A; reference ...)", and the one table of several instruments):
#: what tells a corrected r-table from its standard uncertainty, whose header is :data:`U_HEADER`
#: followed by it (:func:`corrected_r_header`).
CORRECTED_R = "corrected for the aperture effect (r / k_A"


def measured_label(t: "RTable") -> str:
    """A measured table as the header of its correction names it: its name and :meth:`RTable.digest`
    in brackets (``measured [1f03a2c7]``). The name alone let two sites' files of one name (both
    measured.csv) write one header, so ``road --u`` took one site's u for the other's table (user
    audit, session 40)."""
    return f"{t.name} [{t.digest()}]"


def corrected_r_header(t: "RTable") -> str | None:
    """The first header line of a table that says it is a corrected r-table (:data:`CORRECTED_R`,
    not after :data:`U_HEADER`), or None."""
    first = header_line(t)
    return first if CORRECTED_R in first and not first.startswith(U_HEADER) else None


def u_names_table(u: "RTable") -> str | None:
    """The first header line of the table a table of standard uncertainties says it belongs to (its
    header ``standard uncertainty of <that table's header>``, :data:`U_HEADER`), or None."""
    first = header_line(u)
    return first[len(U_HEADER):].strip() if first.startswith(U_HEADER) else None


def grid_coords(tan_eps: np.ndarray = TAN_EPS_GRID, beta_deg: np.ndarray = BETA_GRID_DEG) -> dict:
    """The ``tan_eps`` and ``beta`` coordinates (with their long names and units) of every table
    over the grid as xarray: r-tables, k_A tables and the k_A Dataset."""
    return {"tan_eps": ("tan_eps", np.array(tan_eps, dtype=np.float64), {"long_name": "tan(epsilon)", "units": "1"}),
            "beta": ("beta", np.array(beta_deg, dtype=np.float64), {"long_name": "beta", "units": "deg"})}


#: The first words of the header of a k_A table: the title of a k_A Dataset (``ka.csv``,
#: :func:`roadgonio.engines.runner.ka_dataset`), ``ka_direct.csv`` and the benches' cached k_A
#: tables. A k_A table has the r-table layout but holds k_A unscaled: this header is what tells it
#: from an r-table (:func:`load_table` refuses it, :func:`read_ka_table` reads it).
KA_HEADER = "k_A of "


def names_ka(t: "RTable") -> bool:
    """Whether a table read from a file says it is a k_A table (its header, :data:`KA_HEADER`)."""
    return header_line(t).startswith(KA_HEADER)


def ka_output_header(what: str, instrument: str, sample: str, backend: str) -> str:
    """The header of a table ``roadgonio ka`` writes beside k_A (``ka_se.csv``, ``ka_bound.csv``,
    ``stray_fraction.csv``, ...): ``what`` and the run it belongs to. :func:`names_ka_output` knows it."""
    return f"{what} (instrument '{instrument}', sample '{sample}', {backend} backend)"


_KA_OUTPUT = re.compile(r".* \(instrument '.*', sample '.*', \S+ backend\)$")


def names_ka_output(t: "RTable") -> bool:
    """Whether a table read from a file says it is one of a k_A run's tables (k_A, its standard
    error, bounds, direct light or stray fraction: :func:`names_ka` or :func:`ka_output_header`),
    none of which holds r or u(r)."""
    return names_ka(t) or bool(_KA_OUTPUT.match(header_line(t)))


#: The comment line a written r-table (or u table) CSV carries after its source: its values' scale.
UNITS_LINE_START = "values:"


def units_line(quantity: str = "r") -> str:
    """The scale line of a written CSV (:meth:`RTable.to_csv_text`): r (or u(r)) x 1e4, in sr^-1."""
    if quantity == "u":
        return f"{UNITS_LINE_START} u(r) x 1e4 (u(r) in sr^-1: 12 is 0.0012 sr^-1); blank = none given"
    return f"{UNITS_LINE_START} r x 1e4 (r in sr^-1: 294 is r = 0.0294 sr^-1); blank = not measured"


def grid_csv_text(values: np.ndarray, source: str, *, scale: float = 1.0, digits: int = 6,
                  tan_eps: np.ndarray = TAN_EPS_GRID, beta_deg: np.ndarray = BETA_GRID_DEG) -> str:
    """Any quantity over the grid (an r-table, k_A, its standard error...) in the r-table CSV layout
    (module docstring): ``# source`` comment lines, the beta header, one row per tan eps, values
    times ``scale`` (r-tables: :data:`R_SCALE`), a blank where the value is NaN."""
    out = io.StringIO()
    for line in str(source).splitlines() or [""]:
        out.write(f"# {line}\n" if not line.startswith("#") else line + "\n")
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["tan_eps"] + [_fmt(b, 6) for b in beta_deg])
    for i, t in enumerate(tan_eps):
        w.writerow([_fmt(t, 6)] + ["" if not np.isfinite(v) else _fmt(v * scale, digits) for v in values[i]])
    return out.getvalue()


def q0_weights(mask: np.ndarray, tan_eps: np.ndarray = TAN_EPS_GRID,
               beta_deg: np.ndarray = BETA_GRID_DEG) -> np.ndarray | None:
    """Weights w (the grid's shape) with Q0 = sum w r over the tabulated cells ``mask`` (CIE 144;
    the one definition of Q0: :meth:`RTable.q0`, the correction's budget and the uncertainty of Q0
    all use it); None when no grid cell has four tabulated corners (Q0 undefined).

    With t = tan eps, q dOmega = r t dt dbeta. The integral is the trapezoidal rule over every grid
    cell whose four corners are tabulated (each corner carries t/4 of the cell's dt dbeta), divided
    by Omega0, the exact solid angle of the same cells (the area of dOmega = d(1 - cos eps) dbeta).
    CIE 144 uses a table of weighting factors that we do not have, so this agrees with the
    published Q0 to a few percent (roadgonio/data/rtables/SOURCES.md)."""
    mask = np.asarray(mask, dtype=bool)
    t = np.asarray(tan_eps, dtype=np.float64)
    b = np.radians(np.asarray(beta_deg, dtype=np.float64))
    quad = mask[:-1, :-1] & mask[:-1, 1:] & mask[1:, :-1] & mask[1:, 1:]
    area = np.where(quad, np.diff(t)[:, None] * np.diff(b)[None, :] / 4.0, 0.0)
    g = 1.0 - 1.0 / np.sqrt(1.0 + t * t)
    omega = float(np.sum(np.where(quad, np.diff(g)[:, None] * np.diff(b)[None, :], 0.0)))
    if not omega > 0.0:
        return None
    w = np.zeros(mask.shape)
    w[:-1, :-1] += area
    w[:-1, 1:] += area
    w[1:, :-1] += area
    w[1:, 1:] += area
    return w * t[:, None] / omega


def _fmt(v: float, digits: int) -> str:
    s = f"{float(v):.{digits}g}"
    return s


def _index(grid: np.ndarray, value: float, what: str) -> int:
    k = np.nonzero(np.abs(grid - value) <= GRID_TOL)[0]
    if len(k) == 0:
        raise InputError(f"{what} = {value:g} is not on the table grid", field=what)
    return int(k[0])


# ----------------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------------

def _parse_number(text: str, path, line: int, what: str) -> float:
    try:
        if "_" in text:          # Python's float takes '3_26' as 326 (user audit, session 37): not a number in a table
            raise ValueError(text)
        v = float(text)
    except ValueError:
        raise InputError(f"{what}: expected a number, got {text!r}", path=path, line=line) from None
    if not math.isfinite(v):
        raise InputError(f"{what}: expected a finite number, got {text!r}", path=path, line=line)
    return v


def _check_grid(values: list[float], expected: np.ndarray, what: str, path, line: int) -> None:
    if len(values) != len(expected) or not np.allclose(values, expected, atol=GRID_LABEL_TOL, rtol=0):
        exp = ",".join(_fmt(v, 6) for v in expected)
        got = ",".join(_fmt(v, 6) for v in values)
        raise InputError(f"{what} must be the standard grid ({len(expected)} values: {exp}); got "
                         f"{len(values)} values: {got}", path=path, line=line)


def _row_count_hint(rows: list[tuple[int, list[str]]]) -> tuple[str, int]:
    """Which row of a CSV table with the wrong number of rows breaks the tan eps grid, and its line
    (user audit, session 44: "expected 29 data rows, found 28" pointed at the file's end, not at the
    missing tan eps 1.25)."""
    fewer = len(rows) < len(TAN_EPS_GRID)
    for k, (lineno, cells) in enumerate(rows):
        if k >= len(TAN_EPS_GRID):
            return f"a row beyond tan eps = {TAN_EPS_GRID[-1]:g} ({cells[0].strip()!r})", lineno
        try:
            t = float(cells[0].strip())
        except ValueError:
            t = math.nan
        if not abs(t - TAN_EPS_GRID[k]) <= GRID_LABEL_TOL:
            if fewer:
                return f"tan eps = {TAN_EPS_GRID[k]:g} is missing (this row is {cells[0].strip()!r})", lineno
            return (f"tan eps = {cells[0].strip()} where {TAN_EPS_GRID[k]:g} belongs (a repeated or extra row)",
                    lineno)
    return (f"tan eps = {', '.join(f'{t:g}' for t in TAN_EPS_GRID[len(rows):])} is missing at the end", rows[-1][0])


def parse_csv(text: str, *, path: str | Path = "<table>", name: str | None = None, quantity: str = "r") -> RTable:
    """Parse the CSV r-table layout; errors name the file and the line. ``quantity`` is what the values
    are: ``"r"``, or ``"u"`` for a table of standard uncertainties of r (both written x 1e4), or
    ``"k_A"`` (unscaled, no plausibility bound: the returned table's ``r`` holds k_A itself)."""
    scale = 1.0 if quantity == "k_A" else R_SCALE
    scaled = f"{quantity} x 1e4" if scale == R_SCALE else quantity
    lines = text.splitlines()
    comments: list[str] = []
    header_line = None
    rows: list[tuple[int, list[str]]] = []
    for lineno, raw in enumerate(lines, start=1):
        s = raw.strip()
        if not s:
            continue
        if s.startswith("#"):
            if header_line is None:
                comments.append(s.lstrip("#").strip())
            continue
        cells = next(csv.reader([raw]))
        if header_line is None:
            header_line = lineno
            if cells[0].strip().lower() != "tan_eps" and len(cells) == 1 and (";" in s or "\t" in s) \
                    and s.replace("\t", ";").split(";")[0].strip().lower() == "tan_eps":
                # a spreadsheet's export with another separator: the header is there
                raise InputError("the separator must be a comma: this header is split by "
                                 f"{'semicolons' if ';' in s else 'tabs'} ({s[:40]!r}...); export the table as "
                                 "comma-separated CSV", path=path, line=lineno)
            if cells[0].strip().lower() != "tan_eps":
                raise InputError("missing header: expected a first row 'tan_eps,0,2,5,...,180' (beta in "
                                 f"degrees), got {s[:60]!r}", path=path, line=lineno)
            betas = [_parse_number(c.strip(), path, lineno, f"header column {k + 2}")
                     for k, c in enumerate(cells[1:])]
            _check_grid(betas, BETA_GRID_DEG, "the header's beta columns", path, lineno)
            continue
        rows.append((lineno, cells))
    if header_line is None:
        raise InputError("empty table: expected a header 'tan_eps,0,2,...,180' and 29 rows", path=path)
    if not rows:
        raise InputError(f"no data rows after the header: expected 29 rows of tan_eps and {scaled}",
                         path=path, line=header_line)
    if len(rows) != len(TAN_EPS_GRID):
        hint, line = _row_count_hint(rows)
        raise InputError(f"expected {len(TAN_EPS_GRID)} data rows (tan eps = 0 ... 12), found {len(rows)}: {hint}",
                         path=path, line=line)
    r = np.full((len(TAN_EPS_GRID), len(BETA_GRID_DEG)), np.nan)
    for i, (lineno, cells) in enumerate(rows):
        if len(cells) != len(BETA_GRID_DEG) + 1:
            raise InputError(f"expected {len(BETA_GRID_DEG) + 1} cells (tan_eps and {len(BETA_GRID_DEG)} "
                             f"beta columns), found {len(cells)}", path=path, line=lineno)
        t = _parse_number(cells[0].strip(), path, lineno, "tan_eps")
        if abs(t - TAN_EPS_GRID[i]) > GRID_LABEL_TOL:
            raise InputError(f"row {i + 1} must have tan_eps = {TAN_EPS_GRID[i]:g} (standard grid), got {t:g}",
                             path=path, line=lineno)
        for j, c in enumerate(cells[1:]):
            c = c.strip()
            if c == "":
                continue
            v = _parse_number(c, path, lineno, f"beta = {BETA_GRID_DEG[j]:g} column")
            if v < 0:
                # (the wide audit, session 43: ">= 0" read as if a 0 were a reading; fit and correct refuse it)
                raise InputError(f"beta = {BETA_GRID_DEG[j]:g} column: {quantity} must not be negative, got {c}"
                                 + (" (a cell not measured is left empty; fit and correct refuse a 0 too)"
                                    if quantity == "r" else ""),
                                 path=path, line=lineno)
            if scale == R_SCALE and v / R_SCALE > R_MAX_PLAUSIBLE:
                raise InputError(f"beta = {BETA_GRID_DEG[j]:g} column: {quantity} x 1e4 = {c} is not a plausible road "
                                 f"value (expected {quantity} x 1e4 <= {R_MAX_PLAUSIBLE * R_SCALE:.0f}; the CIE tables "
                                 f"peak below 800): a typo, or a table not written as {quantity} x 1e4?", path=path,
                                 line=lineno)
            r[i, j] = v / scale
    if not np.isfinite(r).any():
        raise InputError("the table has no values (every cell is blank)", path=path)
    return RTable(r, name=name or Path(str(path)).stem, source="\n".join(comments))


#: A read RTB's q0 line agrees with the Q0 of its values within this (relative). Our trapezoidal Q0
#: differs from the CIE 144 weights by up to 3.5 % on the standard tables (SOURCES.md), and files
#: often carry the nominal q0 of their class; beyond this the reader says so in the table's source.
RTB_Q0_AGREE = 0.15
#: Scale candidates are told apart by factors of 10^4; a q0 line within this factor of one of them
#: identifies the scale, otherwise the file is refused.
RTB_Q0_SCALE_FACTOR = 2.0


def _rtb_number(text: str, path, line: int, what: str) -> float:
    if "," in text and "." not in text:  # decimal comma (German locale files)
        if text.count(",") > 1:
            # values separated by commas on one line (user audit, session 44: the message quoted them
            # with the commas turned into points, '294.326.344...', text the file does not hold)
            raise InputError(f"{what}: expected a number, got {text[:40]!r}{'...' if len(text) > 40 else ''}: values "
                             "separated by commas; an RTB file separates its values by line breaks or spaces "
                             "(a comma is a decimal comma)", path=path, line=line)
        text = text.replace(",", ".")
    return _parse_number(text, path, line, what)


#: What an RTB table's source starts with when its stored name would read as a u or k_A table's
#: header (:func:`parse_rtb`).
RTB_R_TABLE = "r-table "


def parse_rtb(text: str, *, path: str | Path = "<table>") -> RTable:
    """Parse a DIALux RTB file (module docstring): R values r x 1e4, 0 = blank.

    Tolerant of layout (one value per line as DIALux documents it, or several per line), blank
    lines, a decimal comma. The scale of the values is checked against the file's own q0 line:
    the values' Q0 read as r x 1e4 must match q0 (in sr^-1); a file whose values are r in sr^-1
    (q0 in sr^-1), or whose q0 is scaled like the values (q0 x 1e4), is recognised by its q0 line
    and read at that scale (the table's ``source`` says so); a q0 line that fits no scale is an error.
    """
    lines = text.splitlines()
    first = next((k for k, l in enumerate(lines) if l.strip()), None)
    if first is None:
        raise InputError("empty file: expected 'RTable.v1' on line 1", path=path)
    if lines[first].strip() != "RTable.v1":
        raise InputError(f"missing header: expected 'RTable.v1' on line 1, got {lines[first].strip()[:40]!r}",
                         path=path, line=first + 1)
    if first + 1 >= len(lines):
        raise InputError("missing surface name on line 2", path=path, line=first + 1)
    at = first + 1        # the name's line; blank lines before it are skipped when a name follows (audit 22)
    nxt = next((k for k in range(first + 1, len(lines)) if lines[k].strip()), None)
    if not lines[at].strip() and nxt is not None and not _looks_numeric(lines[nxt]):
        at = nxt
    name = lines[at].strip() or Path(str(path)).stem
    tokens: list[tuple[int, str]] = [(k, tok) for k, l in enumerate(lines[at + 1:], start=at + 2)
                                     for tok in l.split()]
    pos = 0

    def take(what: str) -> tuple[int, float]:
        nonlocal pos
        if pos >= len(tokens):
            last = tokens[-1][0] if tokens else first + 2
            # one value short at the end: every value after a missing line moved up by one, and the
            # likeliest missing line is the q0 line, which then reads as the first r value (user
            # audit, session 44: "file ends early at line 633" named no cause)
            short = (" (one value short: is a line missing? without its q0 line the first r value reads "
                     "as q0)" if what.startswith("r value (tan eps = 12, beta = 180") else "")
            raise InputError(f"file ends early: expected {what}{short}", path=path, line=last)
        k, tok = tokens[pos]
        pos += 1
        return k, _rtb_number(tok, path, k, what)

    def count(what: str) -> tuple[int, int]:
        k, v = take(what)
        if v != int(v) or v < 1:
            raise InputError(f"{what}: expected a whole number >= 1, got {v:g}", path=path, line=k)
        return k, int(v)

    try:
        k, n_t = count("the number of tan eps values")
        tans = [take(f"tan eps value {i + 1}")[1] for i in range(n_t)]
        _check_grid(tans, TAN_EPS_GRID, "the tan eps values", path, k)
    except InputError:
        if _looks_numeric(lines[at]):
            # the name line missing: the count took its place as the name (user audit, session 44: "the
            # number of tan eps values: expected a whole number >= 1, got 0")
            raise InputError(f"line {at + 1} is {lines[at].strip()!r}, a number where the surface's name belongs "
                             "(line 1 RTable.v1, line 2 the name, then the number of tan eps values): is the name "
                             "line missing?", path=path, line=at + 1) from None
        raise
    k, n_b = count("the number of beta values")
    betas = [take(f"beta value {i + 1}")[1] for i in range(n_b)]
    _check_grid(betas, BETA_GRID_DEG, "the beta values", path, k)
    q0_line, q0 = take("q0")
    v = np.full((len(TAN_EPS_GRID), len(BETA_GRID_DEG)), np.nan)
    for j in range(len(BETA_GRID_DEG)):
        for i in range(len(TAN_EPS_GRID)):
            k, x = take(f"r value (tan eps = {TAN_EPS_GRID[i]:g}, beta = {BETA_GRID_DEG[j]:g})")
            if x < 0:
                raise InputError(f"r must not be negative (tan eps = {TAN_EPS_GRID[i]:g}, beta = {BETA_GRID_DEG[j]:g}; "
                                 "0 is a blank in RTB), "
                                 f"got {x:g}", path=path, line=k)
            if x > 0:
                v[i, j] = x
    if pos != len(tokens):
        raise InputError(f"{len(tokens) - pos} unexpected value(s) after the {v.size} r values",
                         path=path, line=tokens[pos][0])
    if not np.isfinite(v).any():
        raise InputError("the table has no values (every cell is 0 = blank)", path=path)
    scale, note = _rtb_scale(v, q0, path, q0_line)
    big = np.argwhere(v / scale > R_MAX_PLAUSIBLE)
    if len(big):
        i, j = big[0]
        raise InputError(f"r = {v[i, j] / scale:g} sr^-1 at tan eps = {TAN_EPS_GRID[i]:g}, beta = {BETA_GRID_DEG[j]:g} "
                         f"is not a plausible road value (expected r <= {R_MAX_PLAUSIBLE:g} sr^-1; the CIE tables peak "
                         "below 0.08): a typo, or a table in another scale?", path=path, field="r")
    # the surface's stored name kept in the source, so a CSV converted from it names it in its header
    # (user audit, session 41: '# read from r3.rtb' lost 'R3')
    src = f"{name} read from {Path(str(path)).name}" + (f"; {note}" if note else "")
    table = RTable(v / scale, name=name, source=src)
    if names_u(table) or names_ka(table):
        # a stored name that reads like another table's header ("standard uncertainty of road", "k_A of R3")
        # would make the CSV converted from it a u or k_A table to every reader (user audit, session 44:
        # `table x.rtb --to x.csv` wrote a file `table x.csv` then refused): the source says r-table first
        table = table.with_values(table.r, source=RTB_R_TABLE + src)
    return table


def _looks_numeric(line: str) -> bool:
    """A line of an RTB file that starts with a number (a decimal comma allowed), not a name."""
    tok = line.split()[0].replace(",", ".")
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _rtb_scale(values: np.ndarray, q0_line: float, path, line: int) -> tuple[float, str]:
    """(divisor turning the file's values into r in sr^-1, note) from the file's q0 line."""
    q0_x1e4 = RTable(values / R_SCALE).q0()  # Q0 of the values read as r x 1e4, sr^-1
    if q0_line < 0:
        raise InputError(f"expected q0 >= 0 in sr^-1 (0: not given), got {q0_line:g}", path=path, line=line, field="q0")
    if q0_line == 0:      # no q0 to tell the scale: the values' own, as a CSV's (audit 22: sr^-1 read 1e4 too small)
        largest = float(np.nanmax(values))
        if largest < R_X1E4_LARGEST_MIN:
            raise InputError(f"the q0 line is 0 (not given) and the largest value is {largest:.4g}: this looks like r "
                             f"in sr^-1, but an RTB's values are r x 1e4 (expected a largest value >= "
                             f"{R_X1E4_LARGEST_MIN:g}; the CIE tables' largest are 362 to 770): give the file's q0 "
                             "in sr^-1 on its q0 line or multiply the values by 1e4", path=path, line=line, field="q0")
        return R_SCALE, "q0 line is 0: scale not checked against it, values read as r x 1e4"
    if q0_line > 1.0:  # no road has Q0 > 1 sr^-1: q0 written at the values' scale (x 1e4)
        candidates = [(R_SCALE, q0_line / R_SCALE, "q0 line read as q0 x 1e4 like the values")]
    else:
        candidates = [(R_SCALE, q0_line, ""), (1.0, q0_line, "values read as r in sr^-1 (the scale the q0 line points to, "
                                                 "not r x 1e4)")]
    for scale, q0_ref, note in candidates:
        q0_values = q0_x1e4 * R_SCALE / scale
        ratio = q0_values / q0_ref
        if 1 / RTB_Q0_SCALE_FACTOR <= ratio <= RTB_Q0_SCALE_FACTOR:
            if abs(ratio - 1) > RTB_Q0_AGREE:
                note = (note + "; " if note else "") + (f"q0 line {q0_ref:.4g} sr^-1 differs from the values' Q0 "
                                                        f"{q0_values:.4g} sr^-1 by {100 * (1 / ratio - 1):+.0f} %")
            return scale, note
    raise InputError(f"the q0 line ({q0_line:g}) fits no scale of the values: read as r x 1e4 they give "
                     f"Q0 = {q0_x1e4:.4g} sr^-1, read as r in sr^-1 Q0 = {q0_x1e4 * R_SCALE:.4g} sr^-1; expected "
                     "q0 in sr^-1 (e.g. 0.07) matching the values", path=path, line=line, field="q0")


def read_table(path: str | Path, quantity: str = "r") -> RTable:
    """Read a table file: ``.rtb`` (DIALux) or CSV (anything else; ``quantity`` as :func:`parse_csv`).
    No check of the scale nor of the header: :func:`load_table` is the reader of a user's r-table,
    :func:`read_ka_table` of a k_A table."""
    path = Path(path)
    text = read_user_text(path, "table", missing="no such file")
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    if path.suffix.lower() == ".rtb":
        return parse_rtb(text, path=path)
    return parse_csv(text, path=path, quantity=quantity)


def shown_header(text: str, width: int = 60) -> str:
    """A header line as an error quotes it: whole when short, else cut at a word with " ..." (user
    audit, session 29: '... (mitsuba backen' cut mid-word)."""
    import textwrap
    return textwrap.shorten(" ".join(str(text).split()), width=width, placeholder=" ...")


def check_not_ka(table: RTable, path: str | Path) -> None:
    """Refuse a k_A table (``ka.csv``: its header :data:`KA_HEADER`) or one of the tables written
    beside it (``ka_se.csv``, ...: :func:`names_ka_output`) read as an r-table or its uncertainty:
    they hold k_A or its statistics unscaled, which an r-table reader would divide by 1e4 and call
    r (or u(r)) in sr^-1."""
    if names_ka(table):
        raise InputError(f"this is a k_A table (its header {shown_header(header_line(table))!r}), not an r-table: it holds "
                         "k_A unscaled, not r x 1e4; expected an r-table here (read a k_A table with "
                         "roadgonio.read_ka_table)", path=path)
    if names_ka_output(table):
        raise InputError(f"this is a table of a k_A run (its header {shown_header(header_line(table))!r}), not an r-table "
                         "or its uncertainty: it holds a statistic of k_A unscaled, not r x 1e4", path=path)


def read_ka_table(path: str | Path):
    """A k_A table file (``ka.csv``, ``ka_direct.csv``: the r-table CSV layout with k_A unscaled and
    the header :data:`KA_HEADER`) as an ``xarray.DataArray`` of k_A over ``tan_eps`` x ``beta``
    (degrees), NaN where blank; ``attrs`` name, source, units. A file without that header is
    refused (an r-table read as k_A would be 1e4 too large)."""
    import xarray as xr
    path = Path(path)
    if path.suffix.lower() != ".csv":
        raise InputError(f"expected a k_A table as CSV (.csv, as ka.csv), got {path.suffix or path.name!r}", path=path)
    t = read_table(path, quantity="k_A")
    if not names_ka(t):
        first = header_line(t)
        raise InputError(f"not a k_A table: expected a first comment line '# {KA_HEADER}...' (as roadgonio writes "
                         f"ka.csv), got {('# ' + first) if first else 'none'!r}", path=path)
    return xr.DataArray(
        t.r.copy(), dims=("tan_eps", "beta"),
        coords=grid_coords(t.tan_eps, t.beta_deg), name="k_a", attrs={"name": t.name, "source": t.source, "units": "1",
                           "long_name": "aperture-effect factor k_A", "note": "NaN = not computed"})


def check_csv_table(table: RTable, path: str | Path, quantity: str = "r") -> RTable:
    """The checks of a CSV table file beyond its parsing, once for the reader (:func:`load_table`)
    and the writer's read-back (:meth:`RTable.to_csv_text`), so a table that is written can be read:
    not a k_A table (:func:`check_not_ka`), and for r (not ``quantity="u"``) the scale
    (:func:`check_csv_scale`), not a table of uncertainties (:func:`check_not_u`) and no more light
    than reaches it (:func:`check_reflectance`). Returns the table."""
    check_not_ka(table, path)
    if quantity == "r":
        check_csv_scale(table, path)
        check_not_u(table, path)
        check_reflectance(table, path)
    return table


def check_rtb_table(table: RTable, path: str | Path = "<table>", quantity: str = "r") -> RTable:
    """The checks of an RTB table file beyond its parsing (its scale is its q0 line's, in
    :func:`parse_rtb`), once for the reader (:func:`load_table`) and the writer's read-back
    (:meth:`RTable.to_rtb_text`), as :func:`check_csv_table` for CSV: for r, no more light than
    reaches it (:func:`check_reflectance`). Returns the table."""
    if quantity == "r":
        check_reflectance(table, path)
    return table


def names_u(table: RTable) -> bool:
    """Whether the table's header says it holds standard uncertainties of r (``correct``'s
    corrected_u.csv, :data:`U_HEADER`; ``uncertainty``'s ``<case>_u.csv``)."""
    first = header_line(table)
    return first.startswith(U_HEADER) or "standard uncertainty u(r)" in first


def check_not_u(table: RTable, path: str | Path | None = None) -> None:
    """Refuse a table of standard uncertainties (``corrected_u.csv``: its header :data:`U_HEADER`;
    ``uncertainty``'s ``<case>_u.csv``) read as an r-table (audit 28: one was corrected, fitted and
    classified as R4)."""
    first = header_line(table)
    if names_u(table):
        raise InputError(f"this is a table of standard uncertainties (its header {shown_header(first)!r}), not an r-table; "
                         "expected an r-table here", path=path)


#: A table of standard uncertainties whose median over the measured cells is at least this fraction
#: of r is refused as an r-table (:func:`check_u_scale`): a goniophotometer states a few percent (a
#: u of 60 % still passes: road's tests of extreme u use it).
U_OVER_R_MAX_MEDIAN = 0.9
#: ... and one whose median is below this fraction of r as written in sr^-1 where u x 1e4 belongs
#: (1e-4 of its size: a 2 % u reads as 2e-6 of r; user audit, session 37: road --u took it and
#: stated u(L_av) 2.7e-7). No goniophotometer states 0.01 %.
U_OVER_R_MIN_MEDIAN = 1e-4


def check_u_scale(u_grid: np.ndarray, table: RTable, path: str | Path | None = None, **where) -> None:
    """Refuse a table given as the standard uncertainties of ``table`` whose values are r's own size
    (median u / r >= :data:`U_OVER_R_MAX_MEDIAN` over the cells both have), or 1e-4 of it (below
    :data:`U_OVER_R_MIN_MEDIAN`: written in sr^-1, not x 1e4): an r-table given where its
    u belongs (user audit, session 29: ``correct --u-measured corrected.csv`` and ``road --u site1.csv``
    ran with u = 100 % of r, exit 0). ``where``: the InputError's ``field`` or ``argument``."""
    u = np.asarray(u_grid, dtype=np.float64)
    both = table.mask & np.isfinite(u) & (table.r > 0)
    if not both.any():
        return
    ratio = float(np.median(u[both] / table.r[both]))
    if ratio < U_OVER_R_MIN_MEDIAN:
        raise InputError(f"its values are {ratio:.2g} of the table's r at the median: standard uncertainties in "
                         "sr^-1, not u x 1e4 (a measurement states a few percent of r, 1e-2 of it); expected u x 1e4 "
                         "in the r-table layout, as correct writes corrected_u.csv", path=path, **where)
    if ratio >= U_OVER_R_MAX_MEDIAN:
        raise InputError(f"its values are {100 * ratio:.0f} % of the table's r at the median: an r-table, not its "
                         "standard uncertainties (a measurement states a few percent of r); expected u x 1e4 in the "
                         "r-table layout, as correct writes corrected_u.csv", path=path, **where)


def check_reflectance(table: RTable, path: str | Path | None = None, field: str = "r") -> None:
    """Refuse an r-table that reflects more light than reaches it (:meth:`RTable.reflectance` above
    :data:`REFLECTANCE_MAX`): its values are not r x 1e4 (r x 1e6, or q = r / cos^3 eps, read as r)."""
    rho = table.reflectance()
    if rho > REFLECTANCE_MAX:
        raise InputError(f"the table reflects more light than reaches it: its reflectance over the tabulated "
                         f"incidence directions is {rho:.3g} (no surface exceeds {REFLECTANCE_MAX:g}; the CIE tables "
                         "have 0.15 to 0.27): expected r x 1e4 (a table of q = r / cos^3 eps, or of r in another "
                         "scale, reads like this)", path=path, field=field)


def check_positive(table: RTable, path: str | Path | None = None, what: str = "table", **where) -> None:
    """Every value of ``table`` is above 0: a cell that was not measured is blank, and a 0 is no road's
    r (audit 28: ``fit`` took one and fitted h = -1000, max deviation 56 %). ``where``: the
    InputError's field/line."""
    bad = table.mask & ~(table.r > 0)
    if bad.any():      # where (user audit, session 24: the message named no cell)
        i, j = np.argwhere(bad)[0]
        raise InputError(f"the {what} has {int(bad.sum())} zero value(s), the first at tan eps = "
                         f"{table.tan_eps[i]:g}, beta = {table.beta_deg[j]:g}; blank a cell that was not measured (a reading "
                         "below the meter's resolution: give its value, or blank it; no road's r is 0)",
                         path=path, **where)


def check_csv_scale(table: RTable, path: str | Path) -> None:
    """Refuse a CSV r-table that looks written in sr^-1 instead of r x 10^4: its largest value x 10^4
    above 0 and below :data:`R_X1E4_LARGEST_MIN` (an RTB file's scale is told by its q0 line instead)."""
    largest = float(np.nanmax(table.r)) * R_SCALE
    if 0 < largest < R_X1E4_LARGEST_MIN:       # all zeros: no scale to judge (S1, Q0 are missing)
        raise InputError(f"the largest value is {largest:.4g}: this looks like r in sr^-1, but a CSV r-table holds "
                         f"r x 1e4 (expected a largest value >= {R_X1E4_LARGEST_MIN:g}; the CIE tables' largest are "
                         "362 to 770): multiply the values by 1e4", path=path)


_STANDARD_MASK: np.ndarray | None = None


def standard_mask() -> np.ndarray:
    """The tabulated cells of the CIE standard tables (R1-R4, C1, C2 share one blank pattern: 396
    cells; rows with tan eps >= 5.5 end before beta = 180 deg). A copy."""
    global _STANDARD_MASK
    if _STANDARD_MASK is None:
        _STANDARD_MASK = bundled_table("R3").mask.copy()
    return _STANDARD_MASK.copy()


def q0_coverage_note(table: RTable) -> str | None:
    """One line when ``table``'s cells are not the CIE standard tables' 396 (some lacking, or more):
    its Q0 (and S2) are then the mean over its own solid angle (:meth:`RTable.q0`), not the standard
    tables', and compare with no standard value (user audit, session 37: R3's rows tan eps 0-2 alone gave Q0 0.042
    against 0.070, "x0.601" of the class standard, without a word). None when it has them all, and when
    it has no Q0 (and no S2) to speak of (user audit, session 41: compare said it of a missing Q0)."""
    std = standard_mask()
    if table.mask.shape != std.shape or not math.isfinite(table.q0()):
        return None
    lack, extra = int(np.sum(std & ~table.mask)), int(np.sum(table.mask & ~std))
    if not lack and not extra:
        return None
    what = (f"lacks {lack} of the CIE standard tables' 396 cells" + (f" and has {extra} beyond them" if extra else "")
            if lack else f"has {extra} cells beyond the CIE standard tables' 396")
    return (f"{table.name} {what}: its Q0 and S2 are over its own cells' solid angle, not the standard tables', "
            "and are not comparable with a standard Q0")


def bundled_table(name: str) -> RTable:
    """One of the bundled CIE tables R1, R2, R3, R4, C1, C2 (case-insensitive)."""
    key = name.strip().upper()
    if key not in BUNDLED:
        raise InputError(f"unknown table {name!r}; bundled tables are {', '.join(BUNDLED)}", field="table")
    res = resources.files("roadgonio.data").joinpath("rtables", f"{key}.csv")
    return parse_csv(res.read_text(encoding="utf-8"), path=f"roadgonio/data/rtables/{key}.csv", name=key)


#: Files roadgonio reads or writes that a table argument may be given by mistake (a SAMPLE takes a
#: model.json, a table argument does not), with what they are.
NOT_TABLE_SUFFIXES = {".json": "a JSON file (a fitted model or a run's record)", ".toml": "a TOML file (an instrument "
                      "or a study)", ".nc": "a netCDF file (a run's result)", ".ldt": "an EULUMDAT file (a luminaire)"}


def load_table(spec: str | Path, quantity: str = "r") -> RTable:
    """A bundled table by name (``R3``, any case) or a table file: a text with a suffix is a file,
    one without is a bundled name (the rule of :mod:`roadgonio.surface.sample`). A CSV r-table
    (``quantity="r"``) is checked for the scale (:func:`check_csv_scale`); ``quantity="u"``: a table
    of standard uncertainties of r (no scale check; messages say u). A k_A table is refused
    (:func:`check_not_ka`). The CSV checks are :func:`check_csv_table`, the RTB ones
    :func:`check_rtb_table`, which the writers apply too."""
    s = str(spec).strip()
    if isinstance(spec, str) and not Path(s).suffix:
        if s.upper() in BUNDLED:
            return bundled_table(s)
        raise InputError(f"{s!r} is not a bundled table ({', '.join(BUNDLED)}) nor a table file (.csv/.rtb)",
                         field="table")
    p = Path(s).expanduser()
    if p.suffix.lower() in NOT_TABLE_SUFFIXES:     # audit 22: model.json was read as CSV ("missing header ... '{'")
        raise InputError(f"{NOT_TABLE_SUFFIXES[p.suffix.lower()]}, not an r-table: expected a table file (.csv or .rtb)",
                         path=p)
    if not p.exists():
        raise InputError("no such table file", path=p)
    table = read_table(p, quantity)
    if p.suffix.lower() == ".rtb":
        table = check_rtb_table(table, p, quantity)
        note = rtb_reading_note(table, p)
        if note:
            # every command that reads the file says it (user audit, session 44: only `table`'s text did;
            # classify, compare and fit read a q0 line 29 % off the values' Q0 without a word)
            import warnings

            from roadgonio.errors import ReadingNote
            warnings.warn(ReadingNote(f"{p.name}: read: {note}"), stacklevel=2)
        return table
    return check_csv_table(table, p, quantity)


def rtb_reading_note(table: RTable, path: str | Path) -> str:
    """How :func:`parse_rtb` read the RTB file ``path`` when it had something to say (the values'
    scale told by the q0 line, a q0 line off the values' Q0), else "": kept in the table's source
    after its name and file."""
    head = f"{table.name} read from {Path(str(path)).name}; "
    at = table.source.find(head)
    return table.source[at + len(head):] if at in (0, len(RTB_R_TABLE)) else ""
