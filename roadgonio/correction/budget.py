"""The uncertainty of a corrected r-table (JCGM 100: GUM law of propagation, with correlations).

The corrected table is ``r_c = m_c / k_c`` (m the measured r, k the aperture factor k_A under the
instrument's calibration), so its relative covariance between cells c, d is the sum of the
relative covariances of m and of k from independent sources::

    C_cd = sum over components  cov( ln x_c, ln x_d )

Components (each a covariance matrix over the measured cells, :class:`Budget`):

* ``measurement``: the measurement's own standard uncertainty (``--u-measured``), independent
  between cells (diagonal);
* ``backend``: the k_A backend's standard uncertainty (``CellResult.standard_uncertainty()``:
  standard error, or bound / sqrt 3; a quadrature cell's estimate whole where it did not converge)
  with the correlation between cells the backend measured
  (:func:`roadgonio.correction.run.backend_covariance`; independent cells when it measured none);
* ``parameters``: the fitted model's parameter covariance through the Jacobian of ln k_A
  (:class:`roadgonio.correction.fit.ThroughFit`), correlated;
* ``model``: the model dependence of k_A, a rectangular distribution of half-width delta_c = ln k_alt,c
  - ln k_c (the other model variant, or the largest deviation over alternative references), one
  underlying choice for the whole table: ``delta delta^T / 3`` (fully correlated);
* ``misalignment``: the instrument's geometric errors (``--sigma SPEC``), first-order GUM with
  sensitivities of ln(measured r) by central differences
  (:func:`roadgonio.uncertainty.gum_propagation`), correlated;
* ``convergence``: what the fit's last outer step still changed in k_A (rectangular, diagonal);
* ``misfit`` (eq. 4 fitted through the instrument, when the data reject it:
  :attr:`roadgonio.correction.fit.ThroughFit.misfit`): where the normalised residuals exceed the
  noise locally (:func:`local_birge`), the measurement's u times ``sqrt(B_c^2 - 1)``, correlated over
  the same neighbourhood (:func:`misfit_covariance`): what the model does not follow there, which
  k_A inherits, or a stated measurement u that is too small.

The measurement noise also enters the fitted parameters; that cross-covariance is left out (it is
of the order of the number of parameters over the number of cells of the measurement term).

S1, S2 and Q0 (CIE 144) are functions of the table; their standard uncertainties follow from C by
the same law: Q0 is linear in r (weights of :meth:`roadgonio.surface.rtable.RTable.q0`), S1 and S2
are ratios.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from roadgonio.surface.cie import cie_class, nearest_basis, nearest_bundled
from roadgonio.surface.rtable import S1_CELLS, RTable, q0_weights, standard_mask

#: The measurement's relative standard uncertainty when none is stated (``--u-measured``): the
#: default of ``correct`` and of ``design --second-aperture``'s forecast alike (audit 28: the forecast
#: took 1.5 %, so a prediction and a correction made with the defaults did not compare).
DEFAULT_U_MEASURED = "1%"
#: Width (in grid cells) of the neighbourhood of the local Birge ratio.
BIRGE_WIDTH_CELLS = 2.0


@dataclass
class Budget:
    """Relative covariance components over the measured cells (module docstring)."""

    n: int
    components: dict[str, np.ndarray] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)

    def add(self, name: str, cov_or_u: np.ndarray, note: str = "") -> None:
        """Add a component: a (n, n) covariance of ln x, or a (n,) vector of relative standard
        uncertainties of independent cells."""
        a = np.asarray(cov_or_u, dtype=np.float64)
        if a.shape == (self.n,):
            a = np.diag(a * a)
        if a.shape != (self.n, self.n):
            raise ValueError(f"component {name}: expected ({self.n},) or ({self.n}, {self.n}), got {a.shape}")
        self.components[name] = 0.5 * (a + a.T)
        if note:
            self.notes[name] = note

    def add_systematic(self, name: str, delta: np.ndarray, note: str = "") -> None:
        """A rectangular systematic of half-width ``delta`` (relative, per cell), one underlying
        choice for all cells: delta delta^T / 3."""
        d = np.asarray(delta, dtype=np.float64)
        self.add(name, np.outer(d, d) / 3.0, note)

    def total(self) -> np.ndarray:
        out = np.zeros((self.n, self.n))
        for c in self.components.values():
            out = out + c
        return out

    def u_rel(self, name: str | None = None) -> np.ndarray:
        c = self.total() if name is None else self.components[name]
        return np.sqrt(np.maximum(np.diag(c), 0.0))

    def correlation(self) -> np.ndarray:
        c = self.total()
        u = np.sqrt(np.maximum(np.diag(c), 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            r = c / np.outer(u, u)
        r[~np.isfinite(r)] = 0.0
        np.fill_diagonal(r, 1.0)
        return r

    def summary(self) -> dict[str, Any]:
        out = {}
        for name, c in self.components.items():
            u = np.sqrt(np.maximum(np.diag(c), 0.0))
            out[name] = {"u_rel_median": float(np.median(u)), "u_rel_max": float(np.max(u)),
                         "note": self.notes.get(name, "")}
        u = self.u_rel()
        out["total"] = {"u_rel_median": float(np.median(u)), "u_rel_max": float(np.max(u))}
        return out


def local_birge(table: RTable, residual: np.ndarray, leverage: np.ndarray,
                width: float = BIRGE_WIDTH_CELLS) -> tuple[np.ndarray, np.ndarray]:
    """Per measured cell, the local Birge ratio B_c: the square root of the mean over the neighbouring
    cells (Gaussian weights of ``width`` grid cells) of ``r^2 / (1 - h)``, r the normalised residual
    and h the cell's leverage (its expected r^2 under the model is 1 - h); and the widening factor:
    B_c where B_c^2 exceeds what noise alone gives at two standard deviations,
    ``1 + 2 sqrt(2 / n_eff)`` (n_eff the effective number of cells in the neighbourhood), else 1.
    The cells of the pole (tan eps = 0: one direction whatever beta) take the mean of b2 and n_eff over
    the pole's row, the ring of directions around it (their neighbourhoods on the grid differ by beta:
    one direction had u 5.9 % at most beta and 7.3 % at beta 5-15 deg, user audit, session 40).
    Returns (B, widening)."""
    r2 = residual ** 2 / np.clip(1.0 - leverage, 0.05, 1.0)
    K = _neighbourhood(table, width)
    b2 = K @ r2 / K.sum(axis=1)
    n_eff = K.sum(axis=1) ** 2 / (K * K).sum(axis=1)
    pole = _pole_cells(table)
    if pole.sum() > 1:
        b2[pole], n_eff[pole] = b2[pole].mean(), n_eff[pole].mean()
    widen = np.where(b2 > 1.0 + 2.0 * np.sqrt(2.0 / n_eff), np.sqrt(b2), 1.0)
    return np.sqrt(b2), widen


def _pole_cells(table: RTable) -> np.ndarray:
    """Which measured cells (row-major, as :func:`_neighbourhood`) are at the pole, tan eps = 0."""
    return np.asarray(table.tan_eps, dtype=np.float64)[np.nonzero(table.mask)[0]] == 0.0


def _neighbourhood(table: RTable, width: float = BIRGE_WIDTH_CELLS) -> np.ndarray:
    """Gaussian weights of ``width`` grid cells between the measured cells (positive semidefinite)."""
    ii, jj = np.nonzero(table.mask)
    d2 = (ii[:, None] - ii[None, :]) ** 2 + (jj[:, None] - jj[None, :]) ** 2
    return np.exp(-0.5 * d2 / width ** 2)


def misfit_covariance(table: RTable, residual: np.ndarray, n_free: int,
                      u_measured_rel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``misfit`` component of a fit the data reject (module docstring): per measured cell the
    local Birge ratio of the normalised ``residual`` (:func:`local_birge`, every cell's leverage
    taken as the mean, ``n_free`` / cells), and where its widening exceeds 1 the relative u
    ``u_measured_rel sqrt(widening^2 - 1)``, the excess of the residuals over the stated noise;
    correlated between cells as their neighbourhoods overlap (the Gaussian weights of
    :func:`local_birge`, a correlation matrix). Returns (covariance, widening)."""
    res = np.asarray(residual, dtype=np.float64)
    lev = np.full(res.shape, min(float(n_free) / max(res.size, 1), 0.95))
    _, widen = local_birge(table, res, lev)
    d = np.asarray(u_measured_rel, dtype=np.float64) * np.sqrt(np.maximum(widen ** 2 - 1.0, 0.0))
    return np.outer(d, d) * pole_as_one(table, _neighbourhood(table)), widen


def pole_as_one(table: RTable, K: np.ndarray) -> np.ndarray:
    """The correlation matrix ``K`` (over the measured cells) with the pole's cells (tan eps = 0: one
    direction whatever beta) made one: T K T^T, T replacing each pole cell by the normalised mean of
    them, so they correlate 1 with one another and alike with every other cell, and the matrix stays
    positive semidefinite with a unit diagonal (user review, session 40: one direction's misfit, one
    error, correlated 1e-18 between beta 0 and 180)."""
    pole = _pole_cells(table)
    n_pole = int(pole.sum())
    if n_pole < 2:
        return K
    T = np.eye(K.shape[0])
    mean = pole / n_pole
    norm = math.sqrt(float(mean @ K @ mean))
    T[pole] = mean / norm
    return T @ K @ T.T


def functionals(table: RTable, cov_rel: np.ndarray | None) -> dict[str, Any]:
    """S1, S2, Q0 of ``table`` with standard uncertainties from the relative covariance of its
    tabulated cells (row-major order), and the CIE classes."""
    mask = table.mask
    r = table.r[mask]
    ii, jj = np.nonzero(mask)
    s1, q0 = table.s1(), table.q0()
    s2 = table.s2()
    out: dict[str, Any] = {"S1": s1, "Q0": q0, "S2": s2}
    if cov_rel is not None:
        # a functional whose cells are missing is missing (None), never a traceback or NaN as a result
        i20, i00 = (_cell(table, ii, jj, *c) for c in S1_CELLS)
        w = q0_weights(mask, table.tan_eps, table.beta_deg)
        out.update(u_S1=None, u_Q0=None, u_S2=None)
        if i00 is not None and i20 is not None and math.isfinite(s1):
            var_lns1 = float(cov_rel[i20, i20] + cov_rel[i00, i00] - 2 * cov_rel[i20, i00])
            out["u_S1"] = s1 * math.sqrt(max(var_lns1, 0.0))
        if w is not None and math.isfinite(q0) and q0 > 0:
            g = w[mask] * r / q0                               # d ln Q0 / d ln r_c
            var_lnq0 = float(g @ cov_rel @ g)
            out["u_Q0"] = q0 * math.sqrt(max(var_lnq0, 0.0))
            if i00 is not None and math.isfinite(s2):
                var_lns2 = float(var_lnq0 + cov_rel[i00, i00] - 2 * float(g @ cov_rel[:, i00]))
                out["u_S2"] = s2 * math.sqrt(max(var_lns2, 0.0))
    note = q0_blank_note(table)
    if note is not None:
        out["Q0_note"] = note
    out["class"] = cie_class(s1, out.get("u_S1"))
    near = nearest_bundled(s1, q0, 1)
    out["nearest_table"], out["nearest_distance"] = near[0] if near else (None, None)
    basis = nearest_basis(s1, q0)
    if near and basis:
        out["nearest_table_basis"] = basis
    return out


def q0_blank_note(table: RTable) -> str | None:
    """What Q0 (and S2) of a table with blank cells inside the CIE tables' tabulated region mean: the
    mean over the tabulated cells' solid angle only (:func:`~roadgonio.surface.rtable.q0_weights`), not
    the full table's, and their u leaves out what the blank cells would add (audit 28: the tan eps 0
    row blank moved Q0 by 2 %, 30 times its stated u, without a word). None for a full table, one
    off the standard grid, or one without Q0."""
    if table.r.shape != standard_mask().shape or not math.isfinite(table.q0()):
        return None
    blank = int(np.sum(standard_mask() & ~table.mask))
    if not blank:
        return None
    return (f"Q0 and S2 are over the tabulated cells only: {blank} of the CIE tables' {int(standard_mask().sum())} "
            "cells are blank, so they are not the full table's, and their u leaves out what those cells would add")


def _cell(table: RTable, ii, jj, t: float, b: float) -> int | None:
    """The index of cell (t, b) among the tabulated cells, None when it is not tabulated."""
    k = np.nonzero((np.abs(table.tan_eps[ii] - t) < 1e-9) & (np.abs(table.beta_deg[jj] - b) < 1e-9))[0]
    return int(k[0]) if k.size else None


def misalignment_covariance(model, instrument, table: RTable, spec, *, illuminance: str = "nominal",
                            rays: int = 256, seed: int = 0, rel_step: float = 0.5) -> tuple[np.ndarray, dict[str, Any]]:
    """Relative covariance of the measured r over the table's cells from the instrument's
    geometric errors ``spec`` (a :class:`roadgonio.uncertainty.SigmaSpec`), first-order GUM.

    The measurement model is :class:`roadgonio.uncertainty.MeasurementModel` (the local angles of
    a misaligned instrument, the illuminance normalisation), times k_A of the perturbed instrument
    from ray bundles with common random numbers (:class:`roadgonio.engines.bundle.BundleBackend`;
    the perturbed instrument and its cells exactly as :func:`roadgonio.uncertainty.build_surrogate`
    builds them). Sensitivities by central differences of ln r at +- ``rel_step`` sigma."""
    from roadgonio.engines.bundle import BundleBackend, RayBundles
    from roadgonio.uncertainty import CellSet, MeasurementModel, gum_propagation
    mask = table.mask
    ii, jj = np.nonzero(mask)
    cs = CellSet(table.tan_eps[ii].copy(), table.beta_deg[jj].copy(), ii, jj, "measured")
    mm = MeasurementModel(model, instrument, cs, illuminance)
    nominal = RayBundles.build(instrument, table.cells, rays=rays, seed=seed)
    sizes = nominal.rays_per_cell

    def k_of(X: np.ndarray) -> np.ndarray:
        xv, wr = mm.surrogate_coords(X)
        out = np.empty((len(X), len(cs)))
        for t in range(len(X)):
            inst = mm.instrument.with_changes(
                observation={"alpha_deg": mm.alpha0 + float(xv[t, 0, 0]), "delta_deg": mm.delta0},
                source={"distance_m": mm.ds0 + float(X[t, 5])}, detector={"distance_m": mm.dd0 + float(X[t, 6])})
            be = BundleBackend(inst, model, rays=rays, seed=seed, eta_from_bundle=True,
                               sizes_of=lambda _cells: sizes)
            out[t] = [c.k_a for c in be.compute(mm.cells_of(wr[t]))]
        return out

    def func(X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(X)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log(mm.r_measured(X)) + np.log(k_of(X))

    g = gum_propagation(func, spec.sigmas, 0.95, rel_step=rel_step)
    sens = g["sensitivity"]                                 # (7, n) d ln r / d input
    cov = sens.T @ np.diag(spec.sigmas ** 2) @ sens
    from roadgonio.uncertainty import INPUTS
    contrib = {k: float(np.max(np.abs(g["contribution"][i]))) for i, k in enumerate(INPUTS) if spec.sigmas[i] > 0}
    return cov, {"method": "first-order GUM, central differences at +-%g sigma, k_A from ray bundles" % rel_step,
                 "illuminance": illuminance, "max_rel_contribution": contrib, "sigma": spec.to_dict()}


def systematic_delta(k_main: np.ndarray, k_alternatives: Mapping[str, np.ndarray]) -> np.ndarray:
    """Per cell, the signed ln-deviation of the alternative farthest from ``k_main``."""
    if not k_alternatives:
        return np.zeros_like(k_main)
    dev = np.stack([np.log(k) - np.log(k_main) for k in k_alternatives.values()])
    pick = np.argmax(np.abs(dev), axis=0)
    return dev[pick, np.arange(dev.shape[1])]
