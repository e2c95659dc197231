"""Profiles of the instrument beyond the uniform discs (docs/conventions.md section 4; the E(x_E, y_E)
and k_D(x_D, y_D) of paper eq. 3): the source's radiance over its exit aperture and with the emission
angle, and the detector's sensitivity map over its field stop.

This module holds the profiles as data (frozen, float64, read-only) and reads the files that give
them; the formulas that evaluate them are written once in :mod:`roadgonio.instrument.optics`
(:func:`~roadgonio.instrument.optics.source_radiance_factor`,
:func:`~roadgonio.instrument.optics.field_map_value`), over the array namespace, so the numpy
integrators and the Mitsuba plugins evaluate the same code.

**The source.** Its radiance at a point s of the exit aperture (``rho`` = |s - centre| / R_S) in an
emission direction at the angle ``theta`` from the source axis is

    L(s, theta) = L_0 * A(rho) * P(theta)

(the uniform Lambertian disc: A = P = 1). The intensity of an element of the aperture is then
``dI = L dA cos theta``, so its relative intensity distribution is ``i(theta) = P(theta) cos theta``.

* ``A``: ``1 - (1 - e) rho^2`` with ``e = aperture_edge_radiance`` (the form of the detector's
  ``field_edge_sensitivity``), or a table ``rho, relative_radiance`` (CSV, rho from 0 to 1).
* ``P``: ``exp(-theta^2 / (2 sigma^2))`` (``beam_sigma_deg``: a Gaussian in radiance, so a wide one
  is the uniform disc), ``cos^n theta`` (``beam_cos_power``: radiance, so the element's intensity is
  ``cos^(n+1)``, the "generalised Lambertian" cos^m LED model with m = n + 1), or a tabulated
  intensity distribution ``I(theta)`` (``beam_intensity_file``: EULUMDAT .ldt, rotationally
  symmetric, gamma = theta, or a CSV ``theta_deg, I``), for which ``P = I(theta) / (I(0) cos theta)``.

**Tables.** A table read from a file is interpolated by a cubic spline through its nodes,
mirrored about 0 (C2, flat at the axis or the aperture's centre as an even profile is; error
~h^4 |f''''| / 384 for nodes h apart: 1e-8 for a cos^6 beam tabulated every 0.5 deg), set to 0
where it would dip below, and sampled once, in float64, on a uniform grid (:data:`ANGLE_STEP_DEG`,
:data:`RHO_STEP`): the shared formula interpolates linearly between those samples
(:class:`UniformTable`), which differs from the spline by at most step^2 / 8 max|f''| (1.5e-8
max|P''| for angles in radians). Linear interpolation on a fine uniform grid costs a kernel two
gathers and no search, and keeps the integrand smooth to that level (the quadrature and the
reference converge as for a smooth profile). A table is read as a smooth function: a kink or a
cut-off in it rings over about one node spacing (give nodes densely there).

A tabulated intensity distribution covers the emission angles of its file only (at most
:data:`THETA_END_MAX_DEG`); beyond them it is unknown, and a cell whose detector footprint is seen
at larger angles from the source is refused (:func:`roadgonio.instrument.optics.check_source`).

**The detector's sensitivity map** (``field_sensitivity``): relative sensitivity k_D over the field
stop, a square grid of n x n values (n >= 2) like an image of the field as the meter sees it: rows
from the top (y = +1) down, columns from the left (x = -1) to the right, at the centres of the
square pixels of the square [-1, 1]^2 that circumscribes the field stop (x, y in units of the
field-stop radius; x horizontal, to the right as the meter looks at the sample, y up). A CSV of n
lines of n comma-separated numbers and nothing else (no header line: a line that is not numbers
is an error, so neither a header nor a point list ``x,y,k`` passes as a map), or a greyscale image
(PNG, TIFF: 8 or 16 bit, or 32-bit float, or 8-bit RGB(A) with equal R, G, B; OpenEXR: one channel, Y, or
equal R, G, B). Bilinear between the pixel centres, the border values
extended to the edges. The map is divided by its largest value (only relative sensitivities
matter), so a uniform map is exactly 1 everywhere: the same instrument as no map.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roadgonio.errors import InputError


def quadratic_edge(edge, rho2):
    """The radial law 1 - (1 - e) rho^2 of a quantity that is 1 at the centre and ``edge`` at the rim
    (rho = 1): the detector's field sensitivity k_D (paper eq. 3) and the source aperture's radiance
    profile share it. Plain arithmetic: numpy or Dr.Jit arrays, or floats."""
    return 1.0 - (1.0 - edge) * rho2


def quadratic_edge_mean(edge: float) -> float:
    """The area mean of :func:`quadratic_edge` over the unit disc, int_0^1 (1 - (1 - e) rho^2) 2 rho d rho
    = 1 - (1 - e) / 2."""
    return 1.0 - 0.5 * (1.0 - edge)

#: Grid step (deg) of a tabulated intensity distribution, as the formulas evaluate it.
ANGLE_STEP_DEG = 0.01
#: Grid step (fraction of the aperture radius) of a tabulated aperture radiance.
RHO_STEP = 1e-3
#: Emission angles beyond this (deg) are never tabulated: P = I / (I(0) cos theta) grows without
#: bound towards 90 deg (and no footprint of a source that faces the sample is seen there).
THETA_END_MAX_DEG = 89.0
#: Largest sensitivity map accepted (values): a map finer than this is no more accurate.
MAP_MAX_VALUES = 4096 * 4096


def file_digest(path: str | Path) -> str:
    """sha256 of a file's content (the identity of a table: same path, new content = new instrument)."""
    from roadgonio.provenance import file_sha256
    return file_sha256(path)


@dataclass(frozen=True, eq=False)
class UniformTable:
    """Samples ``values[k]`` of a function at ``x0 + k step`` (k = 0 ... n-1), float64, read-only;
    evaluated by :func:`roadgonio.instrument.optics.table_value` (linear between samples, clamped to
    the grid)."""

    values: np.ndarray
    x0: float
    step: float

    def __post_init__(self):
        v = np.array(self.values, dtype=np.float64)
        if v.ndim != 1 or v.size < 2:
            raise ValueError("a uniform table needs at least two values")
        v.setflags(write=False)
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "x0", float(self.x0))
        object.__setattr__(self, "step", float(self.step))

    @property
    def n(self) -> int:
        return int(self.values.size)


@dataclass(frozen=True, eq=False)
class BeamProfile:
    """The angular factor P(theta) of the source radiance (module docstring): ``kind`` is
    ``"lambertian"`` (P = 1), ``"gaussian"`` (``sigma_rad``), ``"cos_power"`` (``power``) or
    ``"table"`` (``table`` over theta in radians, up to ``theta_end_rad``; 0 beyond)."""

    kind: str = "lambertian"
    sigma_rad: float = math.inf
    power: float = 0.0
    table: UniformTable | None = None
    theta_end_rad: float = 0.5 * math.pi

    @property
    def uniform(self) -> bool:
        return self.kind == "lambertian"


def beam_half_width_rad(beam: BeamProfile) -> float:
    """The smallest emission angle at which the angular profile P(theta) falls to exp(-1/2) of P(0):
    a Gaussian's sigma, acos(exp(-1 / 2n)) for cos^n, for a table its first crossing (linear between
    its samples; its last angle if it never falls that far); inf for the Lambertian disc (P = 1).
    What a backend's rules must resolve (the quadrature's narrow-beam note)."""
    if beam.kind == "gaussian":
        return float(beam.sigma_rad)
    if beam.kind == "cos_power":
        return math.acos(math.exp(-0.5 / beam.power)) if beam.power > 0 else math.inf
    if beam.kind == "table" and beam.table is not None:
        t = beam.table
        v = t.values
        lvl = v[0] * math.exp(-0.5)
        below = np.flatnonzero(v <= lvl)
        if below.size == 0:
            return float(min(beam.theta_end_rad, t.x0 + t.step * (t.n - 1)))
        k = int(below[0])
        if k == 0:
            return float(t.x0)
        frac = (v[k - 1] - lvl) / (v[k - 1] - v[k]) if v[k - 1] != v[k] else 0.0
        return float(t.x0 + t.step * (k - 1 + frac))
    return math.inf


@dataclass(frozen=True, eq=False)
class ApertureProfile:
    """The factor A(rho) of the source radiance over the exit aperture (module docstring): ``kind``
    is ``"uniform"``, ``"quadratic"`` (``edge``: A = 1 - (1 - edge) rho^2) or ``"table"``
    (``table`` over rho)."""

    kind: str = "uniform"
    edge: float = 1.0
    table: UniformTable | None = None

    @property
    def uniform(self) -> bool:
        return self.kind == "uniform"

    def disc_mean(self) -> float:
        """The mean of A over the unit disc, ``int_0^1 A(rho) 2 rho d rho``: what the exit aperture
        emits relative to a uniform disc of radiance L_0 (1, 1 - (1 - edge) / 2, or the table's,
        linear between its samples and clamped as the formulas evaluate it, by trapezoids on a grid
        20 times finer)."""
        if self.kind == "uniform":
            return 1.0
        if self.kind == "quadratic":
            return quadratic_edge_mean(self.edge)
        t = self.table
        x = t.x0 + t.step * np.arange(t.n)
        r = np.linspace(0.0, 1.0, 20 * max(t.n, 1000) + 1)
        a = np.interp(r, x, t.values)
        return float(np.trapezoid(a * 2.0 * r, r))


#: A slope change of a field map below this fraction of its largest value is round-off, no kink (a
#: linear map sampled in float64 is not exactly linear in its last digits).
MAP_KINK_ROUNDOFF = 1e-9


@dataclass(frozen=True, eq=False)
class FieldMap:
    """The detector's sensitivity map (module docstring): ``values`` (ny, nx) at the pixel centres
    of [-1, 1]^2, rows from the top, largest value 1; ``flat`` the same values
    row by row (what the formula gathers from)."""

    values: np.ndarray
    source: str = ""

    def __post_init__(self):
        v = np.array(self.values, dtype=np.float64)
        v.setflags(write=False)
        object.__setattr__(self, "values", v)
        flat = v.ravel().copy()
        flat.setflags(write=False)
        object.__setattr__(self, "flat", flat)
        object.__setattr__(self, "_kinks", None)

    @property
    def nx(self) -> int:
        return int(self.values.shape[1])

    @property
    def ny(self) -> int:
        return int(self.values.shape[0])

    def kink_lines(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The lines ``x = c`` and ``y = d`` (map coordinates, [-1, 1]^2, y up) across which the map's
        bilinear interpolation (:func:`roadgonio.instrument.optics.map_bilinear`) changes slope: the
        pixel-centre columns where the second difference along x is not 0 in some row, the outermost
        ones where the map is not flat there (it is flat beyond them), and the same for the rows.
        Neither for a uniform map, only the outermost ones for a linear map. A product Gauss rule's
        successive levels can agree by chance across such lines (:mod:`roadgonio.engines.rules`)."""
        if self._kinks is None:
            object.__setattr__(self, "_kinks", self._find_kink_lines())
        return self._kinks

    def _find_kink_lines(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        v = self.values
        tol = MAP_KINK_ROUNDOFF * float(np.max(np.abs(v)))

        def lines(a: np.ndarray) -> list[int]:     # a: (n along the direction, m across)
            n = a.shape[0]
            d = np.diff(a, axis=0)                 # slopes between centres; 0 beyond the outermost
            padded = np.concatenate([np.zeros((1, a.shape[1])), d, np.zeros((1, a.shape[1]))])
            jump = np.max(np.abs(np.diff(padded, axis=0)), axis=1)
            return [i for i in range(n) if jump[i] > tol]

        cols = lines(v.T)
        rows = lines(v)
        xs = tuple(float(-1.0 + (2 * i + 1) / self.nx) for i in cols)
        ys = tuple(sorted(float(1.0 - (2 * j + 1) / self.ny) for j in rows))
        return xs, ys


# ----------------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------------

#: The header lines of the CSV tables (docs/conventions.md section 4).
INTENSITY_HEADER = ("theta_deg", "I")
APERTURE_HEADER = ("rho", "relative_radiance")


def _err(message: str, path, field: str, line: int | None = None) -> InputError:
    return InputError(message, path=path, line=line, field=field)


def _exists(path, field: str) -> Path:
    if not isinstance(path, (str, Path)) or not str(path):
        raise InputError(f"expected a file name, got {path!r}", field=field)
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{str(p)!r} is a directory; expected a file", field=field)
    if not p.is_file():
        raise InputError(f"file {str(p)!r} does not exist", field=field)
    return p


def read_numbers_csv(path: Path, field: str, columns: int | None = None,
                     header: tuple[str, ...] | None = None,
                     expected: str = "comma-separated numbers") -> tuple[np.ndarray, list[int]]:
    """Rows of numbers of a CSV file (``#`` comments and blank lines skipped): a float64 array (rows,
    columns) and the file's line number of each row. ``columns`` fixes the number of columns;
    otherwise every row must have the same number. ``header``: the column names the file must start
    with (a table of two columns read in the wrong order would otherwise pass or fail by accident);
    it fixes ``columns``. Without ``header`` the file has none: every line is a row of numbers, and
    a line that is not (a header the file should not have) is an error naming it, never skipped;
    ``expected`` says what the rows are in that error."""
    if header is not None:
        columns = len(header)
    want_header = ",".join(header) if header is not None else ""
    from roadgonio.fileio import read_user_text
    try:
        text = read_user_text(path, "file")
    except InputError as err:            # the one reader's words, under this profile's field
        raise _err(err.reason, path, field, err.line) from None
    rows, lines = [], []
    header_seen = False
    for no, raw in enumerate(text.splitlines(), start=1):
        s = raw.split("#", 1)[0].strip()
        if not s:
            continue
        cells = [c.strip() for c in s.split(",")]
        try:
            vals = [float(c) for c in cells]
        except ValueError:
            if header is not None and not rows and not header_seen:
                header_seen = True
                if [c.lower() for c in cells] != [h.lower() for h in header]:
                    raise _err(f"expected the header {want_header}, got {s!r}", path, field, no) from None
                continue
            if header is None and not rows:
                raise _err(f"expected {expected} from the first line on (no header line), got {s!r}", path, field,
                           no) from None
            raise _err(f"expected {columns or 'comma-separated'} numbers, got {s!r}", path, field, no) from None
        if header is not None and not header_seen:
            raise _err(f"expected the header {want_header} first, got {s!r}", path, field, no)
        if not all(math.isfinite(v) for v in vals):
            raise _err(f"expected finite numbers, got {s!r}", path, field, no)
        want = columns if columns is not None else (len(rows[0]) if rows else len(vals))
        if len(vals) != want:
            raise _err(f"expected {want} numbers in a row, got {len(vals)}", path, field, no)
        rows.append(vals)
        lines.append(no)
    if not rows:
        raise _err("no numbers in the file", path, field)
    return np.asarray(rows, dtype=np.float64), lines


def _spline_grid(x: np.ndarray, y: np.ndarray, step: float, end: float) -> np.ndarray:
    """The cubic spline through (x, y), x[0] = 0, sampled at 0, step, ..., end (end a multiple of
    step; module docstring). The nodes are mirrored about 0 first: both profiles are even functions
    (an intensity rotationally symmetric about the axis, a radiance symmetric about the aperture's
    centre), so the spline is flat at 0 as the profile is. Values below 0 are set to 0."""
    from scipy.interpolate import CubicSpline
    n = int(round(end / step)) + 1
    grid = np.arange(n) * step
    grid[-1] = min(grid[-1], x[-1])
    xs = np.concatenate([-x[:0:-1], x])
    ys = np.concatenate([y[:0:-1], y])
    return np.maximum(CubicSpline(xs, ys, bc_type="not-a-knot", extrapolate=False)(grid), 0.0)


def _check_nodes(x: np.ndarray, y: np.ndarray, lines, path, field: str, what: str, lo: float, hi: float) -> None:
    bad = np.flatnonzero(np.diff(x) <= 0)
    if bad.size:
        raise _err(f"the {what} must increase, but {x[bad[0] + 1]:g} follows {x[bad[0]]:g}", path, field,
                   lines[bad[0] + 1])
    if x[0] != lo:
        raise _err(f"the {what} must start at {lo:g}, got {x[0]:g}", path, field, lines[0])
    if x[-1] > hi:
        raise _err(f"the {what} must not exceed {hi:g}, got {x[-1]:g}", path, field, lines[-1])
    neg = np.flatnonzero(y < 0)
    if neg.size:
        raise _err(f"expected values >= 0, got {y[neg[0]]:g}", path, field, lines[neg[0]])


def read_intensity_distribution(path: str | Path, field: str = "source.beam_intensity_file") -> tuple[np.ndarray, np.ndarray]:
    """(theta_deg, I) of a rotationally symmetric intensity distribution: an EULUMDAT file (.ldt,
    read by :func:`roadgonio.eulumdat.read_ldt`; gamma = theta) or a CSV ``theta_deg, I``."""
    p = _exists(path, field)
    if p.suffix.lower() == ".ldt":
        from roadgonio.eulumdat import read_ldt
        try:
            lum = read_ldt(p, shape_only=True)      # the beam's shape: absolute photometry too
        except InputError as err:
            raise _err(err.reason, p, f"{field} ({err.field})" if err.field else field) from None
        table = lum.cd_per_klm
        if table.shape[0] > 1:
            spread = np.max(np.abs(table - table[:1])) / max(float(np.max(table)), 1e-300)
            if spread > 1e-6:
                raise _err(f"the source's intensity distribution must be rotationally symmetric about its axis "
                           f"(Isym 1, or equal C planes), but its C planes differ by {spread:.2g} of the peak "
                           f"(Isym = {lum.meta.get('isym')})", p, field)
        theta, inten, lines = lum.g_deg, table[0], None
    elif p.suffix.lower() == ".csv":
        rows, lines = read_numbers_csv(p, field, header=INTENSITY_HEADER)
        theta, inten = rows[:, 0], rows[:, 1]
    else:
        raise _err(f"expected an EULUMDAT (.ldt) or CSV (.csv) file, got {p.name!r}", p, field)
    lines = lines if lines is not None else [None] * len(theta)
    if len(theta) < 2:
        raise _err("expected at least two angles", p, field)
    _check_nodes(theta, inten, lines, p, field, "angles theta (deg)", 0.0, 180.0)
    if not inten[0] > 0.0:
        raise _err(f"the intensity on the source axis (theta = 0) must be > 0, got {inten[0]:g}", p, field,
                   lines[0])
    return np.asarray(theta, dtype=np.float64), np.asarray(inten, dtype=np.float64)


def intensity_profile(path: str | Path, field: str = "source.beam_intensity_file") -> BeamProfile:
    """The :class:`BeamProfile` of a tabulated intensity distribution (module docstring):
    ``P(theta) = I(theta) / (I(0) cos theta)`` on the uniform grid, up to the file's last angle
    (at most :data:`THETA_END_MAX_DEG`)."""
    theta, inten = read_intensity_distribution(path, field)
    end = min(float(theta[-1]), THETA_END_MAX_DEG)
    end = math.floor(end / ANGLE_STEP_DEG + 1e-9) * ANGLE_STEP_DEG
    if end < ANGLE_STEP_DEG:
        raise _err(f"the angles must reach at least {ANGLE_STEP_DEG:g} deg", path, field)
    i = _spline_grid(theta, inten / inten[0], ANGLE_STEP_DEG, end)
    grid = np.radians(np.arange(i.size) * ANGLE_STEP_DEG)
    p = i / np.cos(grid)
    return BeamProfile(kind="table", table=UniformTable(p, 0.0, math.radians(ANGLE_STEP_DEG)),
                       theta_end_rad=float(grid[-1]))


def aperture_table(path: str | Path, field: str = "source.aperture_radiance_file") -> ApertureProfile:
    """The :class:`ApertureProfile` of a CSV ``rho, relative_radiance`` (rho from 0 to 1, the
    fraction of the aperture radius)."""
    p = _exists(path, field)
    rows, lines = read_numbers_csv(p, field, header=APERTURE_HEADER)
    if len(rows) < 2:
        raise _err("expected at least two rows (rho = 0 and rho = 1)", p, field)
    rho, rad = rows[:, 0], rows[:, 1]
    _check_nodes(rho, rad, lines, p, field, "radii rho (fraction of the aperture radius)", 0.0, 1.0)
    if rho[-1] != 1.0:
        raise _err(f"the radii must end at 1 (the rim of the aperture), got {rho[-1]:g}", p, field, lines[-1])
    if not np.any(rad > 0):
        raise _err("the radiance is 0 over the whole aperture", p, field)
    v = _spline_grid(rho, rad, RHO_STEP, 1.0)
    return ApertureProfile(kind="table", table=UniformTable(v, 0.0, RHO_STEP))


def _read_image(p: Path, field: str) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(p) as img:
            mode = img.mode
            if mode in ("RGB", "RGBA"):      # audit 22: equal R, G, B (a grey map saved as colour), as for EXR
                rgb = np.asarray(img, dtype=np.float64)
                if mode == "RGBA" and np.any(rgb[..., 3] != rgb[..., 3].flat[0]):
                    raise _err("expected a greyscale image: its alpha channel varies (a transparent map)", p, field)
                grey = _grey_of_rgb(rgb)
                if grey is not None:
                    return grey
                raise _err(f"expected a greyscale image (8 or 16 bit, or 32-bit float, or {mode} with equal R, G, B), "
                           f"got {mode} with colour", p, field)
            if mode not in ("L", "I", "I;16", "I;16B", "I;16L", "F"):
                raise _err(f"expected a greyscale image (8 or 16 bit, or 32-bit float), got mode {mode}", p, field)
            return np.asarray(img, dtype=np.float64)
    except UnidentifiedImageError:
        raise _err("not an image that can be read (expected a CSV grid, PNG, TIFF or EXR)", p, field) from None
    except OSError as err:
        raise _err(f"cannot read the image ({err})", p, field) from None


def _grey_of_rgb(rgb: np.ndarray) -> np.ndarray | None:
    """The one channel of an RGB(A) image (rows x columns x 3 or 4) whose R, G and B are equal (a
    grey map saved as colour, PNG or EXR alike), or None when they differ."""
    r = rgb[..., 0]
    return r if np.array_equal(r, rgb[..., 1]) and np.array_equal(r, rgb[..., 2]) else None


def _read_exr(p: Path, field: str) -> np.ndarray:
    """One greyscale channel of an OpenEXR image (rows from the top, like a PNG): its only channel,
    or ``Y``, or an RGB(A) image whose colour channels are equal; anything else is refused."""
    import OpenEXR
    try:
        with OpenEXR.File(str(p)) as f:
            channels = {k: np.asarray(v.pixels, dtype=np.float64) for k, v in f.channels().items()}
    except Exception as err:          # OpenEXR raises plain exceptions for unreadable files
        raise _err(f"cannot read the OpenEXR image ({err})", p, field) from None
    grey = [v for v in channels.values() if v.ndim == 2]
    if "Y" in channels and channels["Y"].ndim == 2:
        return channels["Y"]
    if len(channels) == 1 and len(grey) == 1:
        return grey[0]
    if len(channels) == 1:
        (v,) = channels.values()
        grey = _grey_of_rgb(v) if v.ndim == 3 and v.shape[2] in (3, 4) else None
        if grey is not None:
            return grey
    raise _err("expected a greyscale OpenEXR image (one channel, a Y channel, or equal R, G, B), got channels "
               + ", ".join(sorted(channels)), p, field)


def read_field_map(path: str | Path, field: str = "detector.field_sensitivity") -> FieldMap:
    """The detector's sensitivity map (module docstring) from a CSV grid or a greyscale image
    (PNG, TIFF, or OpenEXR for a measured float map)."""
    p = _exists(path, field)
    if p.suffix.lower() == ".csv":
        values, _ = read_numbers_csv(p, field, expected="rows of sensitivities (the map's grid)")
    elif p.suffix.lower() in (".png", ".tif", ".tiff"):
        values = _read_image(p, field)
    elif p.suffix.lower() == ".exr":
        values = _read_exr(p, field)
    else:
        raise _err(f"expected a CSV grid or a PNG/TIFF/EXR image, got {p.name!r}", p, field)
    if values.ndim != 2 or values.shape[0] < 2 or values.shape[1] < 2:
        raise _err(f"expected a map of at least 2 x 2 values, got {' x '.join(map(str, values.shape))}", p, field)
    if values.shape[0] != values.shape[1]:
        raise _err(f"expected a square map (n rows of n values: square pixels over the square [-1, 1]^2 around "
                   f"the field stop), got {values.shape[0]} rows of {values.shape[1]} values"
                   + (" (a list of points x,y,k is not a map: give the grid)" if values.shape[1] == 3 else ""),
                   p, field)
    if values.size > MAP_MAX_VALUES:
        raise _err(f"expected at most {MAP_MAX_VALUES} values, got {values.size}", p, field)
    if not np.all(np.isfinite(values)) or np.any(values < 0):
        raise _err("expected finite sensitivities >= 0", p, field)
    scale = float(values.max())
    if not scale > 0.0:
        raise _err("the sensitivity is 0 everywhere", p, field)
    if not _reaches_the_field(values):
        raise _err("the sensitivity is 0 everywhere inside the field stop (the circle of radius 1 in the middle "
                   "of the map's square [-1, 1]^2): the detector would see nothing", p, field)
    return FieldMap(values / scale, str(p))


def _reaches_the_field(values: np.ndarray) -> bool:
    """Whether a pixel > 0 of the map reaches inside the field stop (the open unit disc): the map is
    interpolated between pixel centres, so a pixel's value reaches the square of one pixel spacing
    about its centre (to the map's edge for a pixel on the border, whose value is extended there)."""
    ny, nx = values.shape
    rows, cols = np.nonzero(values > 0.0)
    cx = -1.0 + (2.0 * cols + 1.0) / nx
    cy = 1.0 - (2.0 * rows + 1.0) / ny
    dx, dy = 2.0 / nx, 2.0 / ny
    x0 = np.where(cols == 0, -1.0, cx - dx)
    x1 = np.where(cols == nx - 1, 1.0, cx + dx)
    y0 = np.where(rows == ny - 1, -1.0, cy - dy)
    y1 = np.where(rows == 0, 1.0, cy + dy)
    near_x = np.clip(0.0, x0, x1)
    near_y = np.clip(0.0, y0, y1)
    return bool(np.any(near_x ** 2 + near_y ** 2 < 1.0))

