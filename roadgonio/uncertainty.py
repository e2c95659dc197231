"""Measurement uncertainty of an r-table from the instrument's geometric errors: Monte Carlo
propagation of distributions (JCGM 101:2008, "GUM Supplement 1") beside the first-order GUM
uncertainty framework (JCGM 100:2008), with the JCGM 101 section 8 validation of the GUM result
and the JCGM 101 section 7.9 adaptive stopping rule. Paper section 4.1: "Without aperture effect,
a loop over a large number (typically 5000-50000) generates random angles of specified standard
deviations and distributions".

Inputs (SPEC, :func:`parse_sigma_spec`)
---------------------------------------
Seven independent errors of the instrument, zero mean, each with a standard deviation and a
distribution (normal, or rectangular with that standard deviation, half-width sigma sqrt 3):

=====================  ====================================================================
``alpha_deg``          observation elevation error (detector arm)
``eps_deg``            source polar-angle error
``beta_deg``           source azimuth (beta) error
``tilt_x_deg``         sample tilt about the x axis (x = observation azimuth, in the sample
                       plane): tilts the normal sideways, towards +-y
``tilt_y_deg``         sample tilt about the y axis: tilts the normal towards/away from the
                       detector (changes the local alpha to first order)
``source_distance_m``  source distance error D_S - D_S0
``detector_distance_m`` detector distance error D_D - D_D0
=====================  ====================================================================

One trial draws ONE error set and applies it to every cell of the table: the errors of one
instrument setting are shared by all the cells it measures (fully correlated across the table),
so the distributions of table functionals (Q0, S1) come out right.

Measurement model (one trial)
-----------------------------
The instrument believes it measures at the nominal (alpha0, delta0) and (eps0, beta0) of the cell.
True geometry: detector direction ``w_o(alpha0 + d_alpha, delta0)``, source direction
``w_i(eps0 + d_eps, beta0 + d_beta)`` (DESIGN.md section 1), both in the laboratory frame; the
sample is tilted by ``R = R_y(tilt_y) R_x(tilt_x)`` (normal ``R e_z``), so the directions in the
sample's own frame are ``w' = R^T w``. The road BRDF is evaluated only through
:meth:`roadgonio.model.RoadModel.brdf` on ``(w_i', w_o')``.

Illuminance normalisation (``illuminance``):

* ``"nominal"`` (default): the instrument is calibrated at the nominal geometry: it knows the
  normal illuminance E_perp of its source at the nominal distance D_S0 and computes
  q = L / (E_perp cos eps0). Really, the source is at D_S = D_S0 + dD_S (inverse-square law:
  E_perp,true = E_perp (D_S0/D_S)^2) and lights the sample at the local incidence angle theta_i'
  (L = f E_perp,true cos theta_i'). So the reported value is
  ``r_meas = f(w_i', w_o') cos(theta_i') (D_S0 / D_S)^2 cos^2(eps0)``
  (= q_meas cos^3 eps0). At grazing incidence the cosine ratio cos(theta_i')/cos(eps0) is the
  largest contributor (relative sensitivity tan eps per radian of d eps).
* ``"measured"``: the horizontal illuminance is measured in situ, in the sample plane, for every
  cell, so the illuminance errors cancel: ``r_meas = f(w_i', w_o') cos^3(eps0)``.

The detector distance does not enter without the aperture effect (luminance does not depend on
distance). With the aperture effect, ``r_meas`` is multiplied by k_A of the perturbed geometry:
the instrument with elevation alpha' (detector direction in the sample frame), source direction
(eps', beta') in the sample frame, distances D_S and D_D (the detector's focus setting of the
instrument file is kept; if the file gives none the focus follows the distance). The sample tilt
enters k_A through the local angles only (the tilt of the footprint plane itself is second order
and not modelled). k_A comes from a validated surrogate (:mod:`roadgonio.surrogate`) fitted to
exact evaluations of a k_A backend (:func:`roadgonio.ka.make_backend`); its error against
held-out exact evaluations is measured and reported.

Outputs per cell, and for Q0 (CIE 144, over the standard tabulated region, :meth:`RTable.q0`) and
S1: mean, standard uncertainty, 95 % probabilistically symmetric and shortest coverage intervals
(JCGM 101 7.7), the GUM first-order estimate y = f(0), u(y) from finite-difference sensitivity
coefficients, y +- k u(y), and the JCGM 101 section 8 comparison (d_low, d_high vs delta).
"""
from __future__ import annotations

import math
import os
import platform
import time
import tomllib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .errors import InputError
from .geometry import BETA_GRID_DEG, TAN_EPS_GRID, cos3_eps, eps_from_tan, w_detector, w_source
from .instrument import Instrument
from .model import NumpyOps, RoadModel, road_brdf
from .surrogate import DESIGNS, N_COORDS, KaSurrogate, design_points

#: Input names of a SPEC, in the column order of the trial matrices.
INPUTS = ("alpha_deg", "eps_deg", "beta_deg", "tilt_x_deg", "tilt_y_deg", "source_distance_m",
          "detector_distance_m")
INPUT_HELP = {
    "alpha_deg": "observation elevation error (deg)",
    "eps_deg": "source polar angle error (deg)",
    "beta_deg": "source azimuth (beta) error (deg)",
    "tilt_x_deg": "sample tilt about x (observation azimuth axis; normal tilts sideways) (deg)",
    "tilt_y_deg": "sample tilt about y (normal tilts towards the detector) (deg)",
    "source_distance_m": "source distance error (m)",
    "detector_distance_m": "detector distance error (m)",
}
DISTRIBUTIONS = {"normal": "normal", "gauss": "normal", "gaussian": "normal",
                 "rect": "rect", "rectangular": "rect", "uniform": "rect"}
ILLUMINANCE = ("nominal", "measured")
CELL_SETS = ("standard", "all")
SPEC_HELP = (
    "SPEC is a comma-separated list KEY=SIGMA[:DIST] or the path of a TOML file with the same keys "
    "(KEY = SIGMA, KEY = \"SIGMA:DIST\" or KEY = {sigma = SIGMA, distribution = \"DIST\"}, at top level "
    "or in a [sigma] table). SIGMA is a standard deviation (>= 0) in the key's unit; DIST is normal "
    "(default) or rect (rectangular with that standard deviation, half-width SIGMA*sqrt(3)). Keys: "
    + ", ".join(INPUTS) + "; keys left out are 0. Example: "
    "alpha_deg=0.01,eps_deg=0.05:rect,beta_deg=0.1,tilt_x_deg=0.02,tilt_y_deg=0.02,"
    "source_distance_m=0.002,detector_distance_m=0.005")


# ----------------------------------------------------------------------------------------------
# SPEC
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SigmaSpec:
    """Standard deviations and distributions of the seven input errors (order :data:`INPUTS`)."""

    sigma: tuple[float, ...]
    distribution: tuple[str, ...]
    source: str = ""

    @property
    def sigmas(self) -> np.ndarray:
        return np.asarray(self.sigma, dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {k: {"sigma": s, "distribution": "rectangular" if d == "rect" else "normal"}
                for k, s, d in zip(INPUTS, self.sigma, self.distribution)}

    def draw(self, rng: np.random.Generator, m: int) -> np.ndarray:
        """m trials of the seven errors, shape (m, 7). Both a normal and a uniform variate are drawn
        for every input, so the stream does not depend on the distributions chosen."""
        z = rng.standard_normal((m, len(INPUTS)))
        u = rng.random((m, len(INPUTS)))
        rect = np.array([d == "rect" for d in self.distribution])
        x = np.where(rect[None, :], (2.0 * u - 1.0) * math.sqrt(3.0), z)
        return x * self.sigmas[None, :]


def _parse_entry(key: str, value: Any, *, path, field_prefix: str = "") -> tuple[float, str]:
    fld = f"{field_prefix}{key}"
    dist = "normal"
    if isinstance(value, Mapping):
        extra = sorted(set(value) - {"sigma", "distribution"})
        if extra or "sigma" not in value:
            raise InputError("expected {sigma = NUMBER, distribution = \"normal\"|\"rect\"}", path=path, field=fld)
        dist_text = str(value.get("distribution", "normal"))
        value = value["sigma"]
    elif isinstance(value, str):
        text, _, dist_text = value.partition(":")
        value = text.strip()
        dist_text = dist_text.strip() or "normal"
    else:
        dist_text = "normal"
    if isinstance(value, bool):
        raise InputError(f"expected a number (standard deviation), got {value!r}", path=path, field=fld)
    try:
        sigma = float(value)
    except (TypeError, ValueError):
        raise InputError(f"expected a number (standard deviation), got {value!r}", path=path, field=fld) from None
    if not math.isfinite(sigma):
        raise InputError(f"expected a finite standard deviation, got {value!r}", path=path, field=fld)
    if sigma < 0:
        raise InputError(f"a standard deviation must be >= 0, got {sigma:g}", path=path, field=fld)
    d = DISTRIBUTIONS.get(dist_text.lower())
    if d is None:
        raise InputError(f"unknown distribution {dist_text!r}; expected normal or rect", path=path, field=fld)
    dist = d
    return sigma, dist


def _spec_from_mapping(d: Mapping[str, Any], *, path, field_prefix: str, source: str) -> SigmaSpec:
    unknown = sorted(set(d) - set(INPUTS))
    if unknown:
        raise InputError(f"unknown key(s) {', '.join(unknown)}; expected some of {', '.join(INPUTS)}",
                         path=path, field=field_prefix + unknown[0])
    sig, dist = [], []
    for k in INPUTS:
        if k in d:
            s, t = _parse_entry(k, d[k], path=path, field_prefix=field_prefix)
        else:
            s, t = 0.0, "normal"
        sig.append(s)
        dist.append(t)
    return SigmaSpec(tuple(sig), tuple(dist), source=source)


def parse_sigma_spec(spec: str | Path | Mapping[str, Any], *, option: str = "--sigma") -> SigmaSpec:
    """Parse a SPEC (see :data:`SPEC_HELP`): a string ``KEY=SIGMA[:DIST],...``, a TOML file path,
    or a mapping. Unknown keys, bad numbers, negative sigmas and unknown distributions raise
    :class:`InputError` naming the option or file and the key."""
    if isinstance(spec, Mapping):
        return _spec_from_mapping(spec, path=None, field_prefix="", source="mapping")
    text = str(spec).strip()
    p = Path(text)
    if text.lower().endswith(".toml") or (p.suffix and p.exists()):
        try:
            raw = p.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise InputError(f"no such SPEC file (given to {option})", path=p) from None
        except (OSError, UnicodeDecodeError) as err:
            raise InputError(f"cannot read the SPEC file ({err})", path=p) from None
        try:
            d = tomllib.loads(raw)
        except tomllib.TOMLDecodeError as err:
            raise InputError(f"not valid TOML: {getattr(err, 'msg', str(err))}", path=p,
                             line=getattr(err, "lineno", None)) from None
        if "sigma" in d and isinstance(d["sigma"], Mapping):
            if set(d) - {"sigma"}:
                raise InputError("expected only a [sigma] table", path=p, field=sorted(set(d) - {"sigma"})[0])
            return _spec_from_mapping(d["sigma"], path=p, field_prefix="sigma.", source=str(p))
        return _spec_from_mapping(d, path=p, field_prefix="", source=str(p))
    if not text:
        raise InputError(f"empty SPEC; {SPEC_HELP}", field=option)
    d: dict[str, str] = {}
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        key, eq, val = part.partition("=")
        key = key.strip()
        if not eq:
            raise InputError(f"expected KEY=SIGMA[:DIST], got {part!r} (keys: {', '.join(INPUTS)})", field=option)
        if key in d:
            raise InputError(f"key {key!r} given twice", field=option)
        d[key] = val.strip()
    try:
        return _spec_from_mapping(d, path=None, field_prefix=f"{option} ", source=text)
    except InputError as err:
        raise InputError(err.reason, field=err.field) from None


# ----------------------------------------------------------------------------------------------
# Cells, Q0 weights
# ----------------------------------------------------------------------------------------------

@lru_cache(maxsize=1)
def standard_mask() -> np.ndarray:
    """Tabulated cells of the CIE standard tables (the blank pattern is the same in every one)."""
    from .rtable import bundled_table
    return bundled_table("R3").mask.copy()


@lru_cache(maxsize=1)
def q0_weights() -> np.ndarray:
    """Weights w (29 x 20) with Q0 = sum w r over the standard tabulated region.

    :meth:`RTable.q0` is linear in r, so w[i, j] is Q0 of the table that is 1 at (i, j) and 0
    elsewhere in the region (derived from RTable.q0 itself; the formula is not repeated here).
    """
    from .rtable import RTable
    mask = standard_mask()
    w = np.zeros(mask.shape)
    base = np.where(mask, 0.0, np.nan)
    for i, j in zip(*np.nonzero(mask)):
        t = base.copy()
        t[i, j] = 1.0
        w[i, j] = RTable(t).q0()
    return w


@dataclass(frozen=True)
class CellSet:
    """The cells of the table that are computed, with their grid indices."""

    tan_eps: np.ndarray
    beta_deg: np.ndarray
    ii: np.ndarray
    jj: np.ndarray
    which: str

    @classmethod
    def make(cls, which: str = "standard") -> "CellSet":
        if which not in CELL_SETS:
            raise InputError(f"unknown cell set {which!r}; expected standard or all", field="--cells")
        mask = standard_mask() if which == "standard" else np.ones((len(TAN_EPS_GRID), len(BETA_GRID_DEG)), bool)
        ii, jj = np.nonzero(mask)
        return cls(TAN_EPS_GRID[ii].copy(), BETA_GRID_DEG[jj].copy(), ii, jj, which)

    def __len__(self) -> int:
        return len(self.ii)

    def index(self, tan_eps: float, beta_deg: float) -> int:
        k = np.nonzero((np.abs(self.tan_eps - tan_eps) < 1e-9) & (np.abs(self.beta_deg - beta_deg) < 1e-9))[0]
        if len(k) == 0:
            raise InputError(f"cell (tan eps {tan_eps:g}, beta {beta_deg:g}) not in the cell set", field="cells")
        return int(k[0])

    def to_grid(self, values: np.ndarray) -> np.ndarray:
        g = np.full((len(TAN_EPS_GRID), len(BETA_GRID_DEG)), np.nan)
        g[self.ii, self.jj] = values
        return g


# ----------------------------------------------------------------------------------------------
# The measurement model of one trial
# ----------------------------------------------------------------------------------------------

def _rotations(tilt_x_deg: np.ndarray, tilt_y_deg: np.ndarray) -> np.ndarray:
    """R = R_y(tilt_y) R_x(tilt_x), shape (m, 3, 3)."""
    tx = np.radians(tilt_x_deg)
    ty = np.radians(tilt_y_deg)
    cx, sx, cy, sy = np.cos(tx), np.sin(tx), np.cos(ty), np.sin(ty)
    z, o = np.zeros_like(tx), np.ones_like(tx)
    rx = np.stack([np.stack([o, z, z], -1), np.stack([z, cx, -sx], -1), np.stack([z, sx, cx], -1)], -2)
    ry = np.stack([np.stack([cy, z, sy], -1), np.stack([z, o, z], -1), np.stack([-sy, z, cy], -1)], -2)
    return ry @ rx


class MeasurementModel:
    """r as the instrument reports it for error sets X (m, 7) over a cell set (module docstring)."""

    def __init__(self, model: RoadModel, instrument: Instrument, cells: CellSet,
                 illuminance: str = "nominal"):
        if illuminance not in ILLUMINANCE:
            raise InputError(f"unknown illuminance normalisation {illuminance!r}; expected nominal or measured",
                             field="--illuminance")
        self.model = model
        self.instrument = instrument
        self.cells = cells
        self.illuminance = illuminance
        self.alpha0 = instrument.observation.alpha_deg
        self.delta0 = instrument.observation.delta_deg
        self.ds0 = instrument.source.distance_m
        self.dd0 = instrument.detector.distance_m
        self.eps0 = eps_from_tan(cells.tan_eps)
        self.cos2 = 1.0 / (1.0 + cells.tan_eps ** 2)
        self.cos3 = cos3_eps(cells.tan_eps)
        # nominal source direction and its tangent basis (surrogate coordinates)
        self.wi0 = w_source(self.eps0, cells.beta_deg, self.delta0)
        phi = np.radians(self.delta0 + 180.0 - cells.beta_deg)
        self.e_eps = w_source(self.eps0 + 0.5 * math.pi, cells.beta_deg, self.delta0)  # d w / d eps
        self._w0T = np.ascontiguousarray(self.wi0.T)
        self._e0T = np.ascontiguousarray(self.e_eps.T)
        self._P = model.params.to_dict()
        self._terms = model.terms()
        self.e_phi = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], -1)
        w = q0_weights()
        self.q0_w = w[cells.ii, cells.jj]
        self.i_00 = cells.index(0.0, 0.0)
        self.i_20 = cells.index(2.0, 0.0)

    # -- directions ----------------------------------------------------------------------------
    def local_directions(self, X: np.ndarray) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
        """Source and detector directions in the sample frame: ``((wix, wiy, wiz), (wox, woy, woz))``,
        source components (m, n), detector components (m, 1).

        Exact rotations, no small-angle approximation: moving the source by d_eps along its
        meridian is ``w(eps0 + d) = cos d w(eps0) + sin d w(eps0 + 90 deg)`` (both from
        :func:`~roadgonio.geometry.w_source`), a beta error d_beta is a rotation about the normal
        by -d_beta (phi_i = delta + 180 deg - beta), and the tilt applies ``R^T``.
        """
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        m = len(X)
        wo = w_detector(self.alpha0 + X[:, 0], self.delta0)                            # (m, 3)
        de = np.radians(X[:, 1])[:, None]
        db = -np.radians(X[:, 2])
        c, s = np.cos(db), np.sin(db)
        z, o = np.zeros(m), np.ones(m)
        rz = np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)
        R = _rotations(X[:, 3], X[:, 4])
        Rt = np.swapaxes(R, -1, -2)
        A = Rt @ rz                                                                   # (m, 3, 3)
        P = A @ self._w0T                                                              # (m, 3, n)
        Q = A @ self._e0T
        cd, sd = np.cos(de), np.sin(de)
        wi = tuple(cd * P[:, k, :] + sd * Q[:, k, :] for k in range(3))
        wol = np.einsum("mij,mj->mi", Rt, wo)
        return wi, tuple(wol[:, k:k + 1] for k in range(3))

    def r_measured(self, X: np.ndarray, dirs=None) -> np.ndarray:
        """r_meas without the aperture effect, (m, n) in sr^-1 (module docstring)."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        wi, wo = self.local_directions(X) if dirs is None else dirs
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            f = road_brdf(NumpyOps, self._P, wi, wo, self.model.variant, self._terms)
        f = np.broadcast_to(f, wi[2].shape)
        if self.illuminance == "nominal":
            ds = self.ds0 + X[:, 5]
            return f * wi[2] * ((self.ds0 / ds) ** 2)[:, None] * self.cos2[None, :]
        return f * self.cos3[None, :]

    def surrogate_coords(self, X: np.ndarray, dirs=None) -> tuple[np.ndarray, np.ndarray]:
        """Surrogate coordinates (m, n, 5) (see :mod:`roadgonio.surrogate`) and the source
        directions turned so the detector azimuth is delta0 (m, n, 3)."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        (wix, wiy, wiz), (wox, woy, woz) = self.local_directions(X) if dirs is None else dirs
        alpha = np.degrees(np.arcsin(np.clip(woz[:, 0], -1.0, 1.0)))
        gamma = math.radians(self.delta0) - np.arctan2(woy, wox)                      # (m, 1)
        c, s = np.cos(gamma), np.sin(gamma)
        wr = np.stack([c * wix - s * wiy, s * wix + c * wiy, wiz], -1)
        x = np.empty(wr.shape[:2] + (N_COORDS,))
        x[..., 0] = (alpha - self.alpha0)[:, None]
        x[..., 1:3] = self._tangent(wr)
        x[..., 3] = X[:, 5][:, None]
        x[..., 4] = X[:, 6][:, None]
        return x, wr

    def _tangent(self, w: np.ndarray) -> np.ndarray:
        d = w - self.wi0
        return np.degrees(np.stack([np.sum(d * self.e_eps, -1), np.sum(d * self.e_phi, -1)], -1))

    def dirs_from_offsets(self, off_eps_deg: float, off_phi_deg: float) -> np.ndarray:
        """Unit source directions (n, 3) offset from the nominal ones along e_eps, e_phi."""
        w = self.wi0 + math.radians(off_eps_deg) * self.e_eps + math.radians(off_phi_deg) * self.e_phi
        return w / np.linalg.norm(w, axis=-1, keepdims=True)

    def cells_of(self, w: np.ndarray) -> list[tuple[float, float]]:
        """(tan eps, beta deg) of source directions w (n, 3) in a frame where the detector azimuth
        is delta0; beta folded to [0, 180] (the BRDF and the instrument are mirror symmetric)."""
        tan = np.hypot(w[:, 0], w[:, 1]) / w[:, 2]
        phi = np.degrees(np.arctan2(w[:, 1], w[:, 0]))
        beta = np.abs((self.delta0 + 180.0 - phi + 180.0) % 360.0 - 180.0)
        return [(float(t), float(b)) for t, b in zip(tan, beta)]

    def functionals(self, r: np.ndarray) -> np.ndarray:
        """(m, n) -> (m, n + 2): the cells, then Q0 and S1."""
        q0 = r @ self.q0_w
        with np.errstate(divide="ignore", invalid="ignore"):
            s1 = r[:, self.i_20] / r[:, self.i_00]
        return np.concatenate([r, q0[:, None], s1[:, None]], axis=1)


# ----------------------------------------------------------------------------------------------
# Statistics (JCGM 101 7.6-7.7)
# ----------------------------------------------------------------------------------------------

def coverage_indices(M: int, p: float) -> tuple[int, int]:
    """(q, r) of JCGM 101 7.7: q = pM rounded (pM if integer, else floor(pM + 1/2)); the
    probabilistically symmetric interval is [y_(r), y_(r+q)] with r = (M - q)/2 if integer, else
    (M - q + 1)/2 (1-based order statistics)."""
    pm = p * M
    q = int(round(pm)) if abs(pm - round(pm)) < 1e-9 else int(math.floor(pm + 0.5))
    q = min(max(q, 1), M - 1)
    r = (M - q) // 2 if (M - q) % 2 == 0 else (M - q + 1) // 2
    return q, max(r, 1)


def summarize(Y: np.ndarray, p: float = 0.95, threads: int = 1, rows: int = 8) -> dict[str, np.ndarray]:
    """Mean, standard uncertainty (ddof 1), probabilistically symmetric and shortest 100p %
    coverage intervals of each row of Y (n_out, M) (JCGM 101 7.6, 7.7).

    Only the lowest and the highest M - q values of each row are sorted (np.partition first),
    which is all the two intervals need. Rows are processed in small blocks (cache), optionally
    in threads; the result does not depend on ``threads`` or ``rows``.
    """
    Y = np.asarray(Y, dtype=np.float64)
    n, M = Y.shape
    if M < 2:
        raise InputError(f"expected at least 2 Monte Carlo values, got {M}", field="trials")
    q, r = coverage_indices(M, p)
    k = M - q                        # number of candidate lower ends
    out = {key: np.empty(n) for key in ("mean", "u", "sym_low", "sym_high", "short_low", "short_high")}

    def block(a: int) -> None:
        b = min(n, a + rows)
        y = Y[a:b]
        mean = y.mean(axis=1)
        d = y - mean[:, None]
        out["mean"][a:b] = mean
        out["u"][a:b] = np.sqrt(np.einsum("ij,ij->i", d, d) / (M - 1))
        part = np.partition(y, [k - 1, q], axis=1)
        low = np.sort(part[:, :k], axis=1)       # y_(1) .. y_(k)
        high = np.sort(part[:, q:], axis=1)      # y_(q+1) .. y_(M)
        out["sym_low"][a:b] = low[:, r - 1]
        out["sym_high"][a:b] = high[:, r - 1]    # y_(r+q)
        js = np.argmin(high - low, axis=1)       # shortest y_(j+q) - y_(j), j = 1..k
        idx = np.arange(b - a)
        out["short_low"][a:b] = low[idx, js]
        out["short_high"][a:b] = high[idx, js]

    starts = range(0, n, rows)
    if threads > 1 and n > rows:
        with ThreadPoolExecutor(threads) as ex:
            list(ex.map(block, starts))
    else:
        for a in starts:
            block(a)
    return out


def numerical_tolerance(u: np.ndarray, n_dig: int) -> np.ndarray:
    """delta of JCGM 101 7.9.2: u = c x 10^l with c an n_dig-digit integer, delta = 10^l / 2."""
    u = np.asarray(u, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ell = np.floor(np.log10(np.abs(u))) - (n_dig - 1)
        c = np.round(np.abs(u) / 10.0 ** ell)
        ell = np.where(c >= 10 ** n_dig, ell + 1, ell)
        delta = 0.5 * 10.0 ** ell
    return np.where(np.isfinite(delta) & (u > 0), delta, 0.0)


# ----------------------------------------------------------------------------------------------
# GUM first-order propagation
# ----------------------------------------------------------------------------------------------

def gum_propagation(func: Callable[[np.ndarray], np.ndarray], sigma: np.ndarray, p: float = 0.95,
                    rel_step: float = 1e-2) -> dict[str, np.ndarray]:
    """First-order GUM (JCGM 100 eq. 10, independent inputs) for y = func(X) at X = 0.

    Sensitivity coefficients by central differences with step ``rel_step * sigma_k``; inputs with
    sigma_k = 0 have no step and no contribution. Coverage factor k_p of the normal distribution.
    """
    from scipy.stats import norm
    sigma = np.asarray(sigma, dtype=np.float64)
    nk = len(sigma)
    rows = [np.zeros(nk)]
    active = [k for k in range(nk) if sigma[k] > 0]
    for k in active:
        for sgn in (1.0, -1.0):
            x = np.zeros(nk)
            x[k] = sgn * rel_step * sigma[k]
            rows.append(x)
    Y = func(np.asarray(rows))
    y = Y[0]
    sens = np.zeros((nk, Y.shape[1]))
    for a, k in enumerate(active):
        h = rel_step * sigma[k]
        sens[k] = (Y[1 + 2 * a] - Y[2 + 2 * a]) / (2.0 * h)
    contrib = sens * sigma[:, None]
    u = np.sqrt(np.sum(contrib * contrib, axis=0))
    kp = float(norm.ppf(0.5 * (1.0 + p)))
    return {"y": y, "u": u, "k": kp, "U": kp * u, "low": y - kp * u, "high": y + kp * u,
            "sensitivity": sens, "contribution": contrib}


def gum_validation(gum: Mapping[str, np.ndarray], mc: Mapping[str, np.ndarray], n_dig: int) -> dict[str, np.ndarray]:
    """JCGM 101 section 8.2: d_low = |y - U_p - y_low|, d_high = |y + U_p - y_high| (GUM interval
    vs the probabilistically symmetric MCM interval); validated where both <= delta, the numerical
    tolerance of the GUM u(y) with n_dig significant digits."""
    delta = numerical_tolerance(gum["u"], n_dig)
    d_low = np.abs(gum["low"] - mc["sym_low"])
    d_high = np.abs(gum["high"] - mc["sym_high"])
    return {"delta": delta, "d_low": d_low, "d_high": d_high,
            "validated": (d_low <= delta) & (d_high <= delta)}


# ----------------------------------------------------------------------------------------------
# Running
# ----------------------------------------------------------------------------------------------

BackendFactory = Callable[[Instrument, RoadModel], Any]


def default_backend_factory(name: str, settings: Mapping[str, Any]) -> BackendFactory:
    from .ka import make_backend

    def factory(instrument: Instrument, model: RoadModel):
        return make_backend(name, instrument, model, **dict(settings))
    return factory


@dataclass
class SurrogateReport:
    surrogate: KaSurrogate
    design_points: int
    validation_trials: int
    exact_evaluations: int
    seconds: float
    rel_err_max: np.ndarray      # (n_cells,) max over validation trials of |k_sur/k_exact - 1|
    rel_err_rms: np.ndarray
    backend_rel_se_max: float    # largest relative error estimate of the backend (se / k_A)
    settings: dict[str, Any]

    def summary(self, u_rel: np.ndarray | None = None) -> dict[str, Any]:
        d = {"design": self.surrogate.kind, "design_points": self.design_points, "validation_trials": self.validation_trials,
             "exact_evaluations": self.exact_evaluations, "seconds": self.seconds,
             "rel_err_max": float(np.max(self.rel_err_max)) if self.rel_err_max.size else 0.0,
             "rel_err_rms": float(math.sqrt(np.mean(self.rel_err_rms ** 2))) if self.rel_err_rms.size else 0.0,
             "backend_rel_se_max": self.backend_rel_se_max,
             "fit_rms_log_max": float(np.max(self.surrogate.fit_rms_log)),
             "coordinate_scales": dict(zip(("alpha_loc_deg", "src_eps_offset_deg", "src_phi_offset_deg",
                                            "source_distance_m", "detector_distance_m"),
                                           self.surrogate.scale.tolist())),
             "backend": self.settings}
        if u_rel is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(u_rel > 0, self.rel_err_max / u_rel, np.inf)
            d["err_over_u_max"] = float(np.max(ratio))
            d["err_over_u_median"] = float(np.median(ratio))
        return d


def build_surrogate(mm: MeasurementModel, spec: SigmaSpec, factory: BackendFactory, *,
                    seed_seq: np.random.SeedSequence, n_validation: int = 8, pilot: int = 2000,
                    backend_settings: Mapping[str, Any] | None = None, progress: bool = True,
                    design: str = "ccd", axial: float | None = None, factorial: float = 1.5) -> SurrogateReport:
    """Fit the k_A surrogate over the perturbed neighbourhood of every cell and validate it against
    exact k_A at ``n_validation`` held-out trials drawn from the input distribution."""
    t0 = time.perf_counter()
    rng_pilot, rng_val = [np.random.default_rng(s) for s in seed_seq.spawn(2)]
    Xp = spec.draw(rng_pilot, pilot)
    xp, _ = mm.surrogate_coords(Xp)
    scale = np.max(np.std(xp, axis=0), axis=0)                  # (5,)
    scale = np.where(scale > 1e-12 * np.maximum(1.0, np.max(np.abs(xp), axis=(0, 1))), scale, 0.0)
    active = np.nonzero(scale > 0)[0]
    if design not in DESIGNS:
        raise InputError(f"unknown surrogate design {design!r}; expected {' or '.join(DESIGNS)}", field="--surrogate")
    if axial is None:
        axial = 2.0 if design == "star" else 2.5
    Z = design_points(len(active), axial, factorial, design)
    pts = []
    for z in Z:
        x = np.zeros(N_COORDS)
        x[active] = z * scale[active]
        pts.append(x)
    Xv = spec.draw(rng_val, n_validation) if len(active) else np.zeros((0, len(INPUTS)))
    n = len(mm.cells)
    total = (len(pts) + len(Xv)) * n
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=total, desc="exact k_A (surrogate design)", unit="cell", leave=False)

    def exact(alpha_loc: float, ds: float, dd: float, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        inst = mm.instrument.with_changes(
            observation={"alpha_deg": alpha_loc, "delta_deg": mm.delta0},
            source={"distance_m": mm.ds0 + ds}, detector={"distance_m": mm.dd0 + dd})
        backend = factory(inst, mm.model)
        if not settings_seen:
            try:
                settings_seen.update(backend.settings())
            except Exception:  # noqa: BLE001 - provenance only
                settings_seen["backend"] = getattr(backend, "name", "?")
        res = backend.compute(mm.cells_of(w), on_cell=(lambda _r: bar.update(1)) if bar is not None else None)
        return np.array([c.k_a for c in res]), np.array([c.se for c in res])

    settings_seen: dict[str, Any] = {}
    x_design = np.empty((len(pts), n, N_COORDS))
    ka_design = np.empty((len(pts), n))
    rel_se = 0.0
    settings: dict[str, Any] = dict(backend_settings or {})
    try:
        for k, x in enumerate(pts):
            w = mm.dirs_from_offsets(x[1], x[2])
            x_design[k, :, 0] = x[0]
            x_design[k, :, 1:3] = mm._tangent(w)
            x_design[k, :, 3] = x[3]
            x_design[k, :, 4] = x[4]
            ka, se = exact(mm.alpha0 + x[0], x[3], x[4], w)
            ka_design[k] = ka
            rel_se = max(rel_se, float(np.max(se / np.abs(ka))))
        # cells on the mirror plane: k_A is even in the azimuthal offset, with a kink (surrogate docstring)
        c = mm.cells
        fold = (c.tan_eps > 0) & ((np.abs(c.beta_deg) < 1e-9) | (np.abs(c.beta_deg - 180.0) < 1e-9))
        sur = KaSurrogate.fit(scale, x_design, ka_design, design, fold=fold)
        err = np.zeros((len(Xv), n))
        if len(Xv):
            xv, wr = mm.surrogate_coords(Xv)
            for t in range(len(Xv)):
                ka, se = exact(mm.alpha0 + xv[t, 0, 0], Xv[t, 5], Xv[t, 6], wr[t])
                rel_se = max(rel_se, float(np.max(se / np.abs(ka))))
                err[t] = sur(xv[t:t + 1])[0] / ka - 1.0
    finally:
        if bar is not None:
            bar.close()
    settings = {**settings, **settings_seen}
    return SurrogateReport(
        surrogate=sur, design_points=len(pts), validation_trials=len(Xv),
        exact_evaluations=(len(pts) + len(Xv)) * n, seconds=time.perf_counter() - t0,
        rel_err_max=np.max(np.abs(err), axis=0) if len(Xv) else np.zeros(n),
        rel_err_rms=np.sqrt(np.mean(err ** 2, axis=0)) if len(Xv) else np.zeros(n),
        backend_rel_se_max=rel_se, settings=settings)


@dataclass
class CaseResult:
    """Results of one case ("no_aperture" or "aperture") for the outputs: cells, then Q0, S1."""

    name: str
    nominal: np.ndarray
    mc: dict[str, np.ndarray]
    gum: dict[str, np.ndarray]
    validation: dict[str, np.ndarray]
    q0_samples: np.ndarray
    s1_samples: np.ndarray


@dataclass
class UncertaintyResult:
    cells: CellSet
    cases: dict[str, CaseResult]
    trials: int
    seed: int
    spec: SigmaSpec
    coverage: float
    n_dig: int
    adaptive: dict[str, Any] | None
    surrogate: SurrogateReport | None
    provenance: dict[str, Any]
    seconds: dict[str, float] = field(default_factory=dict)


class _Evaluator:
    """Evaluates trial blocks into output arrays (threads over chunks of trials)."""

    def __init__(self, mm: MeasurementModel, surrogate: KaSurrogate | None, chunk: int, threads: int):
        self.mm = mm
        self.sur = surrogate
        self.chunk = max(1, int(chunk))
        self.threads = max(1, int(threads))

    def block(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        mm = self.mm
        dirs = mm.local_directions(X)
        r = mm.r_measured(X, dirs)
        out0 = mm.functionals(r)
        if self.sur is None:
            return out0, None
        x, _ = mm.surrogate_coords(X, dirs)
        return out0, mm.functionals(r * self.sur(x))

    def __call__(self, X: np.ndarray, bar=None) -> tuple[np.ndarray, np.ndarray | None]:
        M = len(X)
        n_out = len(self.mm.cells) + 2
        Y0 = np.empty((n_out, M))
        Y1 = np.empty((n_out, M)) if self.sur is not None else None

        def work(a: int) -> int:
            b = min(M, a + self.chunk)
            y0, y1 = self.block(X[a:b])
            Y0[:, a:b] = y0.T
            if Y1 is not None:
                Y1[:, a:b] = y1.T
            return b - a

        starts = range(0, M, self.chunk)
        if self.threads == 1 or M <= self.chunk:
            for a in starts:
                k = work(a)
                if bar is not None:
                    bar.update(k)
        else:
            with ThreadPoolExecutor(self.threads) as ex:
                for k in ex.map(work, starts):
                    if bar is not None:
                        bar.update(k)
        return Y0, Y1


def provenance(instrument: Instrument, model: RoadModel, spec: SigmaSpec, **extra) -> dict[str, Any]:
    import scipy

    from . import __version__
    return {"roadgonio": __version__, "numpy": np.__version__, "scipy": scipy.__version__,
            "python": platform.python_version(), "instrument": instrument.to_dict(),
            "instrument_file": str(instrument.path) if instrument.path else None,
            "model": model.to_json_dict(), "sigma": spec.to_dict(), "sigma_spec": spec.source,
            "method": "JCGM 101:2008 Monte Carlo (propagation of distributions) beside JCGM 100 first-order GUM",
            **extra}


def run_uncertainty(model: RoadModel, instrument: Instrument, spec: SigmaSpec, *, trials: int = 50_000,
                    adaptive: bool = False, seed: int = 1, coverage: float = 0.95, n_dig: int = 2,
                    max_trials: int = 200_000, batch: int | None = None, illuminance: str = "nominal",
                    cells: str = "standard", aperture: bool = True, backend: str = "quadrature",
                    backend_settings: Mapping[str, Any] | None = None,
                    backend_factory: BackendFactory | None = None, n_validation: int = 4,
                    surrogate_design: str = "ccd",
                    threads: int | None = None, chunk: int = 256, progress: bool = True) -> UncertaintyResult:
    """Monte Carlo (and GUM) uncertainty of the r-table that ``instrument`` measures on a sample
    with BRDF ``model``, for the instrument errors ``spec`` (module docstring).

    ``aperture=True`` adds the case with the aperture effect (k_A surrogate from ``backend``;
    skipped with a note for an ideal instrument, where k_A = 1). ``adaptive=True`` applies the
    JCGM 101 7.9 stopping rule (batches of ``batch`` = max(100/(1-p), 10^4) trials, all outputs
    stabilised to ``n_dig`` significant digits of u, at most ``max_trials``).
    """
    if not (0.5 < coverage < 1.0):
        raise InputError(f"expected a coverage probability 0.5 < p < 1, got {coverage:g}", field="--coverage")
    if n_dig not in (1, 2, 3):
        raise InputError(f"expected 1, 2 or 3 significant digits, got {n_dig}", field="--digits")
    trials = int(trials)
    if not adaptive and trials < 100:
        raise InputError(f"expected at least 100 trials, got {trials}", field="--trials")
    if threads is None:
        threads = min(2, os.cpu_count() or 1)
    timings: dict[str, float] = {}
    cs = CellSet.make(cells)
    mm = MeasurementModel(model, instrument, cs, illuminance)
    ss = np.random.SeedSequence(int(seed))
    ss_mc, ss_sur = ss.spawn(2)
    rng = np.random.default_rng(ss_mc)

    sur_report = None
    notes: list[str] = []
    if aperture and instrument.is_ideal():
        notes.append("ideal instrument (point source, single-ray detector): k_A = 1, aperture case skipped")
        aperture = False
    if aperture:
        factory = backend_factory or default_backend_factory(backend, backend_settings or {})
        t = time.perf_counter()
        sur_report = build_surrogate(mm, spec, factory, seed_seq=ss_sur, n_validation=n_validation,
                                     backend_settings={"backend": backend, **dict(backend_settings or {})},
                                     design=surrogate_design, progress=progress)
        timings["surrogate"] = time.perf_counter() - t
    ev = _Evaluator(mm, sur_report.surrogate if sur_report else None, chunk, threads)

    t = time.perf_counter()
    adaptive_info = None
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=None if adaptive else trials, desc="Monte Carlo trials", unit="trial", leave=False)
    try:
        if not adaptive:
            X = spec.draw(rng, trials)
            Y0, Y1 = ev(X, bar)
        else:
            Mb = int(batch) if batch else max(int(math.ceil(100.0 / (1.0 - coverage))), 10_000)
            if Mb < 100:
                raise InputError(f"expected a batch of at least 100 trials, got {Mb}", field="--batch")
            blocks0, blocks1, per_batch = [], [], {"0": [], "1": []}
            h = 0
            converged = False
            while True:
                X = spec.draw(rng, Mb)
                y0, y1 = ev(X, bar)
                blocks0.append(y0)
                per_batch["0"].append(_batch_stats(y0, coverage))
                if y1 is not None:
                    blocks1.append(y1)
                    per_batch["1"].append(_batch_stats(y1, coverage))
                h += 1
                if h >= 2:
                    status = [_stability(per_batch[k], np.concatenate(b, axis=1), n_dig)
                              for k, b in (("0", blocks0), ("1", blocks1)) if b]
                    if all(s["stable"] for s in status):
                        converged = True
                        break
                if (h + 1) * Mb > max_trials:
                    break
            Y0 = np.concatenate(blocks0, axis=1)
            Y1 = np.concatenate(blocks1, axis=1) if blocks1 else None
            st = [_stability(per_batch[k], np.concatenate(b, axis=1), n_dig)
                  for k, b in (("0", blocks0), ("1", blocks1)) if b] if h >= 2 else []
            adaptive_info = {"batch": Mb, "batches": h, "trials": h * Mb, "converged": converged,
                             "n_dig": n_dig, "max_trials": max_trials,
                             "unstable_outputs": [int(s["unstable"]) for s in st],
                             "worst_ratio": [float(s["worst_ratio"]) for s in st]}
    finally:
        if bar is not None:
            bar.close()
    timings["monte_carlo"] = time.perf_counter() - t
    M = Y0.shape[1]

    t = time.perf_counter()
    cases: dict[str, CaseResult] = {}
    funcs = {"no_aperture": lambda X: mm.functionals(mm.r_measured(X))}
    if Y1 is not None:
        funcs["aperture"] = lambda X: ev.block(X)[1]
    for name, Y in (("no_aperture", Y0), ("aperture", Y1)):
        if Y is None:
            continue
        mc = summarize(Y, coverage, threads=threads)
        gum = gum_propagation(funcs[name], spec.sigmas, coverage)
        val = gum_validation(gum, mc, n_dig)
        cases[name] = CaseResult(name=name, nominal=gum["y"], mc=mc, gum=gum, validation=val,
                                 q0_samples=Y[-2].copy(), s1_samples=Y[-1].copy())
    timings["statistics"] = time.perf_counter() - t
    prov = provenance(instrument, model, spec, trials=M, seed=int(seed), coverage=coverage, n_dig=n_dig,
                      illuminance=illuminance, cells=cs.which, adaptive=adaptive, threads=threads,
                      chunk=chunk, rng="numpy PCG64 via SeedSequence(seed).spawn(2)[0]", notes=notes,
                      k_a_backend=(sur_report.settings if sur_report else None))
    return UncertaintyResult(cells=cs, cases=cases, trials=M, seed=int(seed), spec=spec, coverage=coverage,
                             n_dig=n_dig, adaptive=adaptive_info, surrogate=sur_report, provenance=prov,
                             seconds=timings)


def _batch_stats(Y: np.ndarray, p: float) -> dict[str, np.ndarray]:
    s = summarize(Y, p)
    return {"mean": s["mean"], "u": s["u"], "low": s["sym_low"], "high": s["sym_high"]}


def _stability(batches: Sequence[Mapping[str, np.ndarray]], pooled: np.ndarray, n_dig: int) -> dict[str, Any]:
    """JCGM 101 7.9.4 g)-j): 2 s <= delta for the mean, u and both interval ends of every output,
    s the standard deviation of the batch results divided by sqrt(h), delta from the pooled u."""
    h = len(batches)
    u_pooled = pooled.std(axis=1, ddof=1)
    delta = numerical_tolerance(u_pooled, n_dig)
    worst = np.zeros(pooled.shape[0])
    for key in ("mean", "u", "low", "high"):
        v = np.stack([b[key] for b in batches])
        s = v.std(axis=0, ddof=1) / math.sqrt(h)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(delta > 0, 2.0 * s / delta, np.where(s > 0, np.inf, 0.0))
        worst = np.maximum(worst, ratio)
    return {"stable": bool(np.all(worst <= 1.0)), "unstable": int(np.sum(worst > 1.0)),
            "worst_ratio": float(np.max(worst))}


# ----------------------------------------------------------------------------------------------
# Results: summary, files, pictures
# ----------------------------------------------------------------------------------------------

OUTPUT_NAMES = ("Q0", "S1")


def result_dict(res: UncertaintyResult, *, cells: bool = True) -> dict[str, Any]:
    """JSON-ready results (per-cell arrays when ``cells``) with provenance."""
    n = len(res.cells)
    d: dict[str, Any] = {"trials": res.trials, "seed": res.seed, "coverage": res.coverage, "n_dig": res.n_dig,
                         "adaptive": res.adaptive, "seconds": res.seconds, "provenance": res.provenance,
                         "cases": {}}
    for name, c in res.cases.items():
        case: dict[str, Any] = {}
        for k, label in ((n, "Q0"), (n + 1, "S1")):
            case[label] = {"nominal": c.nominal[k], "mean": c.mc["mean"][k], "u": c.mc["u"][k],
                           "symmetric_interval": [c.mc["sym_low"][k], c.mc["sym_high"][k]],
                           "shortest_interval": [c.mc["short_low"][k], c.mc["short_high"][k]],
                           "gum_u": c.gum["u"][k], "gum_interval": [c.gum["low"][k], c.gum["high"][k]],
                           "gum_validated": bool(c.validation["validated"][k]),
                           "d_low": c.validation["d_low"][k], "d_high": c.validation["d_high"][k],
                           "delta": c.validation["delta"][k],
                           "gum_contributions": dict(zip(INPUTS, c.gum["contribution"][:, k].tolist()))}
        with np.errstate(divide="ignore", invalid="ignore"):
            u_rel = c.mc["u"][:n] / np.abs(c.mc["mean"][:n])
        case["cells_summary"] = {"u_rel_max": float(np.nanmax(u_rel)), "u_rel_median": float(np.nanmedian(u_rel)),
                                 "gum_validated_fraction": float(np.mean(c.validation["validated"][:n])),
                                 "u_mc_over_u_gum_max": float(np.nanmax(c.mc["u"][:n] / c.gum["u"][:n]))
                                 if np.all(c.gum["u"][:n] > 0) else None}
        if cells:
            case["cells"] = {"tan_eps": res.cells.tan_eps, "beta_deg": res.cells.beta_deg,
                             "nominal": c.nominal[:n], "mean": c.mc["mean"][:n], "u": c.mc["u"][:n],
                             "sym_low": c.mc["sym_low"][:n], "sym_high": c.mc["sym_high"][:n],
                             "short_low": c.mc["short_low"][:n], "short_high": c.mc["short_high"][:n],
                             "gum_u": c.gum["u"][:n], "gum_validated": c.validation["validated"][:n].tolist()}
        d["cases"][name] = case
    if res.surrogate is not None:
        ap = res.cases.get("aperture")
        u_rel = None
        if ap is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                u_rel = ap.mc["u"][:n] / np.abs(ap.mc["mean"][:n])
        d["surrogate"] = res.surrogate.summary(u_rel)
    return d


def cells_csv_text(res: UncertaintyResult) -> str:
    n = len(res.cells)
    lines = ["case,tan_eps,beta_deg,r_nominal,mean,u,u_rel,sym_low,sym_high,short_low,short_high,"
             "gum_u,gum_low,gum_high,gum_validated,d_low,d_high,delta"]
    labels = [f"{t:g},{b:g}" for t, b in zip(res.cells.tan_eps, res.cells.beta_deg)] + ["Q0,", "S1,"]
    for name, c in res.cases.items():
        for k in range(n + 2):
            mean = c.mc["mean"][k]
            u_rel = c.mc["u"][k] / abs(mean) if mean != 0 else float("nan")
            vals = [c.nominal[k], mean, c.mc["u"][k], u_rel, c.mc["sym_low"][k], c.mc["sym_high"][k],
                    c.mc["short_low"][k], c.mc["short_high"][k], c.gum["u"][k], c.gum["low"][k], c.gum["high"][k]]
            v = c.validation
            lines.append(f"{name},{labels[k]}," + ",".join(f"{x:.8g}" for x in vals)
                         + f",{int(bool(v['validated'][k]))},{v['d_low'][k]:.4g},{v['d_high'][k]:.4g},{v['delta'][k]:.4g}")
    return "\n".join(lines) + "\n"


def write_results(res: UncertaintyResult, out_dir: str | Path, *, sample_name: str = "sample",
                  plots: bool = True) -> list[Path]:
    """Write uncertainty.json, cells.csv, r-table CSVs of the mean and u per case, and the pictures."""
    from .fileio import atomic_write_json, atomic_write_text
    from .rtable import RTable
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [atomic_write_json(out / "uncertainty.json", result_dict(res)),
               atomic_write_text(out / "cells.csv", cells_csv_text(res))]
    n = len(res.cells)
    for name, c in res.cases.items():
        src = (f"roadgonio uncertainty: {name.replace('_', ' ')}, {res.trials} trials, seed {res.seed}, "
               f"sample {sample_name}")
        for key, label in (("mean", "mean r x 1e4"), ("u", "standard uncertainty u(r) x 1e4")):
            t = RTable(res.cells.to_grid(c.mc[key][:n]), name=f"{sample_name}_{key}", source=f"{src}: {label}")
            written.append(t.write_csv(out / f"{name}_{key}.csv"))
    if plots:
        written.extend(plot_uncertainty_maps(res, out))
        written.append(plot_q0_s1(res, out / "q0_s1_hist.png"))
    return written


def plot_uncertainty_maps(res: UncertaintyResult, out: Path) -> list[Path]:
    from .plots import table_map
    n = len(res.cells)
    paths = []
    for name, c in res.cases.items():
        with np.errstate(divide="ignore", invalid="ignore"):
            u_rel = 100.0 * c.mc["u"][:n] / np.abs(c.mc["mean"][:n])
        ok = c.validation["validated"][:n]
        title = (f"Relative standard uncertainty u(r)/r (%), {name.replace('_', ' ')}: "
                 f"{res.trials} trials, seed {res.seed}")
        sub = (f"GUM first-order result validated (JCGM 101 s. 8, {res.n_dig} digits) in {int(ok.sum())} of {n} cells; "
               f"Q0 = {c.mc['mean'][n]:.4g} +- {c.mc['u'][n]:.2g}, S1 = {c.mc['mean'][n + 1]:.4g} +- {c.mc['u'][n + 1]:.2g}")
        paths.append(table_map(res.cells.to_grid(u_rel), out / f"u_rel_{name}.png", title=title,
                               label="u(r)/r (%)", centre=None, log=False, fmt="{:.2f}", subtitle=sub))
    return paths


def plot_q0_s1(res: UncertaintyResult, path: Path) -> Path:
    """Histograms of Q0 and S1 (each case) with both coverage intervals and the GUM normal pdf."""
    from .fileio import atomic_savefig
    from .plots import _plt
    plt = _plt()
    n = len(res.cells)
    cases = list(res.cases.items())
    fig, axes = plt.subplots(len(cases), 2, figsize=(12, 4.2 * len(cases)), squeeze=False)
    for row, (name, c) in enumerate(cases):
        for col, (k, label, samples) in enumerate(((n, "Q0 (sr$^{-1}$)", c.q0_samples),
                                                   (n + 1, "S1", c.s1_samples))):
            ax = axes[row][col]
            s = samples[np.isfinite(samples)]
            ax.hist(s, bins=80, density=True, color="0.75", edgecolor="0.6", linewidth=0.3, label="Monte Carlo")
            y, u = c.gum["y"][k], c.gum["u"][k]
            if u > 0:
                xs = np.linspace(min(s.min(), y - 4 * u), max(s.max(), y + 4 * u), 400)
                ax.plot(xs, np.exp(-0.5 * ((xs - y) / u) ** 2) / (u * math.sqrt(2 * math.pi)), "C0-", lw=1.3,
                        label=f"GUM normal, u = {u:.3g}")
            top = ax.get_ylim()[1]
            for lo, hi, style, lab, h in ((c.mc["sym_low"][k], c.mc["sym_high"][k], "C3--", "symmetric", 0.30),
                                          (c.mc["short_low"][k], c.mc["short_high"][k], "C2-", "shortest", 0.22)):
                ax.plot([lo, hi], [h * top, h * top], style, lw=2.2,
                        label=f"{100 * res.coverage:g} % {lab}: [{lo:.5g}, {hi:.5g}]")
            ax.axvline(c.nominal[k], color="k", lw=0.8, ls=":", label=f"nominal {c.nominal[k]:.5g}")
            valid = "validated" if c.validation["validated"][k] else "NOT validated"
            ax.set_title(f"{label.split(' ')[0]}, {name.replace('_', ' ')}: mean {c.mc['mean'][k]:.5g}, "
                         f"u = {c.mc['u'][k]:.3g} (GUM {valid})", fontsize=10)
            ax.set_xlabel(label)
            ax.set_ylabel("probability density")
            ax.legend(fontsize=7.5, loc="best", framealpha=0.85)
            ax.ticklabel_format(axis="x", style="sci", scilimits=(-3, 4), useOffset=False)
    fig.suptitle(f"Distributions of Q0 and S1 over {res.trials} Monte Carlo trials (seed {res.seed})", fontsize=11)
    fig.tight_layout()
    p = atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return p


def summary_lines(res: UncertaintyResult) -> list[str]:
    n = len(res.cells)
    lines = [f"{res.trials} trials (seed {res.seed}), {n} cells, coverage {100 * res.coverage:g} %"]
    if res.adaptive:
        a = res.adaptive
        lines.append(f"adaptive (JCGM 101 7.9, {a['n_dig']} digits): {a['batches']} batches of {a['batch']}, "
                     + ("converged" if a["converged"] else f"NOT converged at the cap of {a['max_trials']} trials "
                        f"(worst 2s/delta = {max(a['worst_ratio'] or [0]):.2f}; about "
                        f"{max(a['worst_ratio'] or [1]) ** 2:.0f}x more trials would be needed: raise --max-trials "
                        f"(memory grows with trials x cells) or ask for fewer --digits)"))
    for name, c in res.cases.items():
        with np.errstate(divide="ignore", invalid="ignore"):
            u_rel = c.mc["u"][:n] / np.abs(c.mc["mean"][:n])
        lines.append(f"{name.replace('_', ' ')}: u(r)/r median {100 * np.nanmedian(u_rel):.3g} %, max "
                     f"{100 * np.nanmax(u_rel):.3g} %; GUM validated in {int(c.validation['validated'][:n].sum())}"
                     f"/{n} cells")
        for k, label in ((n, "Q0"), (n + 1, "S1")):
            lines.append(f"  {label}: {c.mc['mean'][k]:.5g} u = {c.mc['u'][k]:.3g} "
                         f"[{c.mc['sym_low'][k]:.5g}, {c.mc['sym_high'][k]:.5g}] "
                         f"(GUM u = {c.gum['u'][k]:.3g}, {'validated' if c.validation['validated'][k] else 'not validated'})")
    if res.surrogate is not None:
        s = result_dict(res, cells=False).get("surrogate", {})
        lines.append(f"k_A surrogate: {s['exact_evaluations']} exact evaluations in {s['seconds']:.0f} s; error vs "
                     f"held-out exact k_A: max {100 * s['rel_err_max']:.3g} %, rms {100 * s['rel_err_rms']:.3g} %"
                     + (f", max/u(r) = {s['err_over_u_max']:.2g}" if "err_over_u_max" in s else ""))
    return lines


def resolve_sample_spec(spec: str, variant: str | None = None) -> RoadModel:
    """SAMPLE -> RoadModel via :func:`roadgonio.sample.resolve_sample` (lambert, bundled table fitted on
    the fly, table file, model.json); a minimal fallback (lambert, model.json) if that module is absent."""
    try:
        from .sample import resolve_sample
    except ModuleNotFoundError as err:
        if err.name != "roadgonio.sample":
            raise
        resolve_sample = None
    if resolve_sample is not None:
        return resolve_sample(spec, variant=variant) if variant else resolve_sample(spec)
    if spec.strip().lower() == "lambert":
        return RoadModel.lambert()
    p = Path(spec)
    if p.suffix.lower() == ".json":
        return RoadModel.load(p)
    raise InputError("this installation can only use 'lambert' or a model .json file (roadgonio.sample missing)",
                     field="--sample")
