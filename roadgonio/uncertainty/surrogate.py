"""A validated local surrogate of the aperture-effect factor k_A around each r-table cell.

The Monte Carlo evaluation of the measurement uncertainty with the aperture effect
(:mod:`roadgonio.uncertainty`) needs k_A of the *perturbed* instrument in every trial and every
cell: 10,000 trials x 396 cells of exact k_A evaluations (paper eq. 3, a six-fold integral each)
are out of reach. The perturbations are small (hundredths of a degree, millimetres), so k_A is a
smooth function of them near the nominal geometry; this module fits that function per cell from
a small shared design of exact evaluations and measures how wrong the fit is.

Coordinates (per cell, all zero at the nominal geometry):

* ``x1`` = alpha_loc - alpha0 (deg): elevation of the detector direction in the (tilted) sample frame;
* ``x2``, ``x3`` (deg of arc): components of the source direction's offset from the nominal
  direction along e_eps (polar) and e_phi (azimuthal) at the nominal direction, after the sample
  frame is turned about its normal so that the detector azimuth is the nominal one (the road
  BRDF is isotropic). Unlike (d eps, d beta) these stay regular at eps = 0;
* ``x4`` = D_S - D_S0, ``x5`` = D_D - D_D0 (m): source and detector distances.

Surrogate: ln k_A = quadratic polynomial in the scaled coordinates z = x / s (s = a spread scale
of each coordinate over the Monte Carlo trials). Two designs, shared by all cells:

* ``star`` (default of the command: 2d + 1 exact tables): the centre and 2d axial points at
  +-``axial``; ln k_A = c0 + sum_j (b_j z_j + a_j z_j^2) (gradient and curvature of each
  coordinate, no interactions), an exact fit;
* ``ccd``: full quadratic, fitted by least squares over a central composite design: the centre,
  2d axial points at +-``axial`` and a two-level
factorial at +-``factorial`` (full for d <= 4, the resolution-V half fraction x5 = x1 x2 x3 x4 for
d = 5), so all 1 + d + d(d+1)/2 coefficients are estimable. Coordinates whose spread is zero
are left out. Because one design point has the same (x1, x4, x5) in every cell, a design point
is one perturbed instrument and one backend call over all cells.

Cells on the mirror plane (beta0 = 0 or 180 deg, tan eps > 0) are *folded*: the instrument and the
BRDF are mirror symmetric about the plane of observation, so there k_A is an even function of the
azimuthal offset x3, and the model's empirical term depends on |beta|, which puts a kink in it at
x3 = 0 that no quadratic can follow (measured: the surrogate error reached 1.3 u(r) at tan eps
2-4, beta 0 for a Phong exponent of 300). In folded cells the surrogate uses |x3| instead of x3
(for ``star`` only linearly: its design has one level of |x3| besides 0).

The surrogate's own error is measured against exact evaluations at held-out trials drawn from
the actual input distribution (:func:`roadgonio.uncertainty.run_uncertainty` reports it).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

#: Names of the surrogate coordinates, in order.
COORDS = ("alpha_loc_deg", "src_eps_offset_deg", "src_phi_offset_deg", "source_distance_m",
          "detector_distance_m")
N_COORDS = len(COORDS)


DESIGNS = ("star", "ccd")


def design_points(d: int, axial: float = 2.5, factorial: float = 1.5, kind: str = "ccd") -> np.ndarray:
    """Central composite design in d scaled coordinates, shape (K, d).

    Centre, 2d axial points at +-axial, two-level factorial points at +-factorial (full for
    d <= 4, the half fraction with the last column the product of the others for d = 5, which
    has resolution V: main effects and two-factor interactions are not aliased with each other).
    """
    if d == 0:
        return np.zeros((1, 0))
    pts = [np.zeros(d)]
    for j in range(d):
        for sgn in (-1.0, 1.0):
            p = np.zeros(d)
            p[j] = sgn * axial
            pts.append(p)
    if kind == "star":
        return np.asarray(pts, dtype=np.float64)
    if d <= 4:
        levels = list(itertools.product((-1.0, 1.0), repeat=d))
    elif d == 5:
        levels = [lv + (float(np.prod(lv)),) for lv in itertools.product((-1.0, 1.0), repeat=4)]
    else:  # pragma: no cover - the surrogate has at most 5 coordinates
        raise ValueError("at most 5 coordinates")
    pts.extend(factorial * np.asarray(lv) for lv in levels)
    return np.asarray(pts, dtype=np.float64)


def n_features(d: int, kind: str = "ccd") -> int:
    return 1 + 2 * d if kind == "star" else 1 + d + d * (d + 1) // 2


def features(z: np.ndarray, kind: str = "ccd") -> np.ndarray:
    """Quadratic features of scaled coordinates z (..., d): full [1, z_j, z_j z_k (j <= k)] for
    ``ccd``, diagonal [1, z_j, z_j^2] for ``star`` (no interactions)."""
    z = np.asarray(z, dtype=np.float64)
    d = z.shape[-1]
    cols = [np.ones(z.shape[:-1])]
    cols.extend(z[..., j] for j in range(d))
    if kind == "star":
        cols.extend(z[..., j] * z[..., j] for j in range(d))
    else:
        cols.extend(z[..., j] * z[..., k] for j in range(d) for k in range(j, d))
    return np.stack(cols, axis=-1)


@dataclass
class KaSurrogate:
    """ln k_A = quadratic in z = x[active] / scale, one coefficient row per cell."""

    scale: np.ndarray          # (5,) spread scale of each coordinate (0 = inactive)
    active: np.ndarray         # indices of the active coordinates
    coef: np.ndarray           # (n_cells, F)
    ka_nominal: np.ndarray     # (n_cells,) exact k_A at the nominal geometry
    fit_rms_log: np.ndarray    # (n_cells,) RMS residual of ln k_A over the design points
    kind: str = "ccd"
    fold: np.ndarray | None = None   # (n_cells,) True: the cell uses |x3| (module docstring)

    @staticmethod
    def _z(x: np.ndarray, scale: np.ndarray, active: np.ndarray, fold: np.ndarray | None) -> np.ndarray:
        """Scaled active coordinates, with |x3| in folded cells; x is (..., n_cells, 5)."""
        x = np.array(x, dtype=np.float64)
        if fold is not None and np.any(fold):
            x[..., fold, 2] = np.abs(x[..., fold, 2])
        return x[..., active] / scale[active]

    @staticmethod
    def _features(z: np.ndarray, kind: str, active: np.ndarray, fold: np.ndarray | None) -> np.ndarray:
        phi = features(z, kind)
        if kind == "star" and fold is not None and np.any(fold) and 2 in active:
            # one level of |x3| besides 0 in the star design: keep |x3| linear in folded cells
            j = int(np.nonzero(active == 2)[0][0])
            phi[..., fold, 1 + len(active) + j] = 0.0
        return phi

    @classmethod
    def fit(cls, scale: np.ndarray, x_design: np.ndarray, ka_design: np.ndarray, kind: str = "ccd",
            fold: np.ndarray | None = None) -> "KaSurrogate":
        """Least-squares fit.

        ``x_design``: (K, n_cells, 5) coordinates of the design points in each cell;
        ``ka_design``: (K, n_cells) exact k_A there (row 0 must be the nominal geometry);
        ``fold``: (n_cells,) cells on the mirror plane, fitted in |x3|.
        """
        scale = np.asarray(scale, dtype=np.float64)
        active = np.nonzero(scale > 0)[0]
        ka_design = np.asarray(ka_design, dtype=np.float64)
        if not np.all(np.isfinite(ka_design)) or np.any(ka_design <= 0):
            bad = np.argwhere(~(np.isfinite(ka_design) & (ka_design > 0)))[0]
            raise ValueError(f"k_A must be finite and positive to fit the surrogate (design point {bad[0]}, "
                             f"cell {bad[1]}: {ka_design[tuple(bad)]!r})")
        y = np.log(ka_design)
        n_cells = ka_design.shape[1]
        F = n_features(len(active), kind)
        coef = np.empty((n_cells, F))
        rms = np.empty(n_cells)
        fold = None if fold is None else np.asarray(fold, dtype=bool)
        phi_all = cls._features(cls._z(x_design, scale, active, fold), kind, active, fold)   # (K, n_cells, F)
        for c in range(n_cells):
            phi = phi_all[:, c, :]
            sol, *_ = np.linalg.lstsq(phi, y[:, c], rcond=None)
            coef[c] = sol
            res = phi @ sol - y[:, c]
            rms[c] = math.sqrt(float(np.mean(res * res)))
        return cls(scale=scale, active=active, coef=coef, ka_nominal=ka_design[0].copy(), fit_rms_log=rms, kind=kind,
                   fold=fold)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """k_A at coordinates x (..., n_cells, 5) -> (..., n_cells)."""
        z = self._z(x, self.scale, self.active, self.fold)
        phi = self._features(z, self.kind, self.active, self.fold)
        return np.exp(np.einsum("...cf,cf->...c", phi, self.coef))
