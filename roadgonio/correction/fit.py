"""Fitting the BRDF model *through the instrument*: the parameters whose simulated measurement best
matches a measured table, weighted by the measurement's standard uncertainty::

    minimise  chi^2(p) = sum_c ( (r_sim,c(p) - r_meas,c) / u_c )^2,      r_sim,c = rho_c cos^3(eps_c) kappa_c <f_p>_c

with the forward model of :mod:`roadgonio.engines.bundle` (fixed float64 ray bundles, so
r_sim is smooth in p, and linear in the four coefficients k_*) and ``rho_c`` the correction of
the bundle's own error by an exact backend table (1 until one is known; see
:func:`roadgonio.correction.run`). Every model parameter has the bounds of
:data:`roadgonio.surface.model.PARAM_BOUNDS` (k_* >= 0, mu >= 0, ...); the grazing attenuation g is
held at its given value (a user input, docs/conventions.md section 3).

Method (variable projection, like :mod:`roadgonio.surface.fit`): for given shape parameters z
(``n_phong, n_retro, p, h, mu`` and the variant's own, in the transformed coordinates of
:mod:`roadgonio.surface.fit`: log10 n, log10 mu, asinh h) the coefficients are the non-negative least
squares solution (:func:`scipy.optimize.nnls`); z is found by :func:`scipy.optimize.least_squares`
(trust region reflective, bounded; its Jacobian the variable-projection derivative of the columns'
analytic shape derivatives, :meth:`_Problem.jacobian`, since session 31: finite differences before,
which re-solved the problem once per shape parameter) in two stages:

* stage A, multi-start (cheap): the measured table against ``k_c r_c(p)`` with k frozen at its
  current estimate, from the given starting models and a Latin-hypercube set of starts over the
  search box; the best distinct minima go on to
* stage B (through the bundles): chi^2 itself, k_A(p) varying with p.

The parameters' covariance is ``s^2 (J^T J)^-1`` over the free parameters (those not at a bound),
J the Jacobian of the weighted residuals (analytic: the coefficients' columns, and the shape
parameters' derivatives of :func:`roadgonio.surface.model.road_brdf_with_shape_grad` through the
bundles), ``s^2 = max(1, chi^2 / dof)`` (the Birge ratio squared: when
the model cannot follow the table within its stated uncertainty, the parameters are less certain
than the noise alone says). The Jacobian of ln k_A over the same parameters propagates it to k_A.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy.optimize import least_squares, lsq_linear, nnls
from scipy.stats import chi2 as chi2_dist

from roadgonio.engines.bundle import ForwardModel
from roadgonio.errors import InputError
from roadgonio.seeds import seed_entropy
from roadgonio.surface.fit import AT_BOUND, _dz_dp, _from_z, _to_z, _z_box, nonlinear_params
from roadgonio.surface.model import G_PARAMS, LINEAR_TERMS, PARAM_BOUNDS, PARAM_NAMES, SHAPE_TERM, RoadModel, RoadParams

#: Starts of stage A (Latin hypercube over the search box), in addition to the given models.
DEFAULT_STARTS = 16
#: Distinct stage-A minima polished through the bundles (stage B).
DEFAULT_POLISH = 2
#: Stage A: iterations of the short run from every start, and how many runs continue to convergence.
COARSE_NFEV = 25
REFINE = 4
#: Stage B (through the bundles, each evaluation costs a pass over the rays): iterations at most and
#: the relative change of chi^2 at which it stops (1e-8 of chi^2 is far below any stated uncertainty).
STAGE_B_NFEV = 60
STAGE_B_FTOL = 1e-8


#: Significance level at which the fit's chi^2 says the model does not describe the measured table
#: (``ThroughFit.misfit``; ``correct`` then points to ``--forward surface``).
MISFIT_P = 0.01


def misfit_note(fit: dict | None) -> str | None:
    """The note that the data reject the eq. 4 fit (:attr:`ThroughFit.misfit`), from a fit's
    summary; None when they do not, or when a correction surface follows the misfit (its summary has
    ``cells_widened``). ``correct`` prints it and writes it into corrected_u.csv's header, which
    ``road --u`` repeats (trial 11 D7: the note did not travel with the u)."""
    if not fit or not fit.get("misfit") or "cells_widened" in fit:
        return None
    text = (f"the data reject the eq. 4 fit (Birge ratio {fit['birge_ratio']:.2f}, chi^2 {fit['chi2']:.0f} on "
            f"{fit['dof']} degrees of freedom, p = {fit['chi2_p_value']:.1e}, under the stated u): either this surface "
            "is not eq. 4, and k_A inherits the misfit where the table matters, as does the misalignment component "
            "(--sigma), whose sensitivities are the fitted model's slopes, or the stated measurement u "
            "(--u-measured) is too small")
    if fit.get("misfit_cells_widened") is not None:
        text += (f"; u includes a misfit component where the residuals exceed that u "
                 f"({fit['misfit_cells_widened']} cells: u_measured sqrt(B^2 - 1), B the local Birge ratio), "
                 "conservative for a surface outside eq. 4")
    return text


@dataclass
class ThroughFit:
    """A model fitted through the instrument, with its parameter covariance."""

    model: RoadModel
    chi2: float
    dof: int
    cells: int
    free: list[str]
    cov: np.ndarray                  # covariance of the free parameters (natural units), Birge-scaled
    simulated: np.ndarray            # r_sim per cell (sr^-1)
    k_a: np.ndarray                  # k_A per cell from the forward model (rho applied)
    lnk_jac: np.ndarray              # d ln k_A / d free parameter, (cells, free)
    residual: np.ndarray             # (r_sim - r_meas) / u per cell
    starts: int
    nfev: int
    seconds: float
    stage_a: list[float] = field(default_factory=list)   # chi^2 of the distinct stage-A minima, best first
    #: cells where the correction's ``misfit`` component widened u (None: no such component)
    misfit_cells_widened: int | None = None

    @property
    def birge(self) -> float:
        return math.sqrt(self.chi2 / self.dof) if self.dof > 0 else math.inf

    @property
    def chi2_p_value(self) -> float:
        """Pr{chi^2(dof) >= chi2}: how probable a misfit this large is if the model were right and
        the measurement's stated u were its true standard uncertainty (nan without degrees of freedom)."""
        return float(chi2_dist.sf(self.chi2, self.dof)) if self.dof > 0 else math.nan

    @property
    def misfit(self) -> bool:
        """True when the data reject the model at :data:`MISFIT_P` (under the stated u)."""
        return bool(self.chi2_p_value < MISFIT_P)

    def lnk_cov(self) -> np.ndarray:
        """Covariance of ln k_A between cells from the parameters: J C J^T."""
        if not self.free:
            return np.zeros((self.cells, self.cells))
        return self.lnk_jac @ self.cov @ self.lnk_jac.T

    def param_uncertainty(self) -> dict[str, float]:
        return {n: float(math.sqrt(max(self.cov[i, i], 0.0))) for i, n in enumerate(self.free)}

    def summary(self) -> dict[str, Any]:
        out = {"variant": self.model.variant, "chi2": self.chi2, "dof": self.dof, "birge_ratio": self.birge,
               "chi2_p_value": self.chi2_p_value, "misfit": self.misfit,
               "rms_normalised_residual": float(math.sqrt(np.mean(self.residual ** 2))),
               "params": self.model.params.to_dict(), "u_params": self.param_uncertainty(),
               "free": list(self.free), "stage_a_minima_chi2": self.stage_a}
        if self.starts or self.nfev:
            out.update(starts=self.starts, nfev=self.nfev, seconds=self.seconds)
        else:
            # audit 28: "starts: 0, nfev: 0, seconds: 0.0005" read as the fit's cost; this fit is the
            # final model assessed, not searched
            out["searched"] = ("no: the final model assessed (chi^2, covariance, k_A); the searches' starts, "
                               "evaluations and seconds are in provenance.searches")
        if self.misfit_cells_widened is not None:
            out["misfit_cells_widened"] = self.misfit_cells_widened
        out["misfit_note"] = misfit_note(out)
        return out


class _Problem:
    """The measured cells, their uncertainty and the forward model's columns."""

    def __init__(self, forward: ForwardModel, y: np.ndarray, u: np.ndarray, variant: str,
                 fixed: Mapping[str, float], rho: np.ndarray | None, k_frozen: np.ndarray | None):
        self.fm = forward
        self.y = np.asarray(y, dtype=np.float64)
        self.u = np.asarray(u, dtype=np.float64)
        if self.y.shape != (forward.bundles.n_cells,) or self.u.shape != self.y.shape:
            raise InputError("expected one measured value and one uncertainty per cell of the forward model",
                             field="measured")
        if not (np.all(np.isfinite(self.u)) and np.all(self.u > 0)):
            raise InputError("every measured cell needs a positive standard uncertainty", field="u_measured")
        self.w = 1.0 / self.u
        self.variant = variant
        self.fixed = dict(fixed)
        self.free_lin = [k for k in LINEAR_TERMS if k not in self.fixed]
        self.free_nl = [k for k in nonlinear_params(variant) if k not in self.fixed]
        self.rho = np.ones_like(self.y) if rho is None else np.asarray(rho, dtype=np.float64)
        self.k_frozen = np.ones_like(self.y) if k_frozen is None else np.asarray(k_frozen, dtype=np.float64)
        self.base = RoadParams().to_dict()
        self.base.update(self.fixed)
        self.box = [_z_box(n) for n in self.free_nl]
        self.lo = np.array([b[0] for b in self.box])
        self.hi = np.array([b[1] for b in self.box])
        self.nfev = 0
        #: the last solve's (stage, z bytes, coefficients, weighted columns, residual, the coefficients
        #: the fit moves, the weighted columns' shape derivatives) for :meth:`jacobian` at the same point
        self._last: tuple | None = None

    def params(self, z) -> dict[str, float]:
        P = dict(self.base)
        for name, zi in zip(self.free_nl, z):
            P[name] = _from_z(name, float(zi))
        return P

    def z_of(self, model: RoadModel) -> np.ndarray:
        P = model.params.to_dict()
        return np.clip([_to_z(n, P[n]) for n in self.free_nl], self.lo, self.hi)

    def scale(self, stage: str) -> np.ndarray:
        """The factor per cell from a unit-coefficient column to simulated r: ``cos^3 eps k_frozen``
        (stage A, nominal columns) or ``cos^3 eps kappa rho`` (stage B, bundle means)."""
        fm = self.fm
        if stage == "A":
            return fm.bundles.cos3 * self.k_frozen
        return fm.bundles.cos3 * fm.kappa * self.rho

    def sim_columns(self, P: Mapping[str, float], stage: str) -> tuple[np.ndarray, np.ndarray]:
        """(cells, 4) simulated-r columns of the unit-coefficient terms, and (cells, free shape
        parameters) their derivatives, each of the column of the term it shapes (natural units)."""
        if stage == "A":
            _, cols, _, d = self.fm.columns_and_shape_derivatives(P, self.variant, self.free_nl, bundle=False)
        else:
            cols, _, d, _ = self.fm.columns_and_shape_derivatives(P, self.variant, self.free_nl)
        sc = self.scale(stage)[:, None]
        return sc * cols, sc * d

    def solve(self, z, stage: str) -> tuple[dict[str, float], np.ndarray] | None:
        """NNLS coefficients and the weighted residual vector; None if not evaluable."""
        self.nfev += 1
        self._last = None
        P = self.params(z)
        sim, dsim = self.sim_columns(P, stage)
        A = sim * self.w[:, None]
        target = self.y * self.w
        ks = {k: float(self.fixed[k]) for k in LINEAR_TERMS if k in self.fixed}
        for j, k in enumerate(LINEAR_TERMS):
            if k in self.fixed:
                target = target - self.fixed[k] * A[:, j]
        use, cols = [], []
        for j, k in enumerate(LINEAR_TERMS):
            if k in self.fixed:
                continue
            c = A[:, j]
            if not np.all(np.isfinite(c)):
                return None
            s = float(np.max(np.abs(c)))
            if s == 0.0 or s * PARAM_BOUNDS[k][1] < 1e-9 * float(np.max(np.abs(target))):
                ks[k] = 0.0
                continue
            use.append((k, j, s))
            cols.append(c / s)
        model = np.zeros_like(target)
        if cols:
            M = np.stack(cols, axis=1)
            ub = np.array([PARAM_BOUNDS[k][1] * sc for k, _, sc in use])
            try:
                x, _ = nnls(M, target, maxiter=50 * len(cols))
            except RuntimeError:
                x = np.full(len(cols), np.inf)
            if not np.all(np.isfinite(x) & (x <= ub)):
                # a coefficient beyond its bound (k_* <= 1e6): the bounded least squares instead
                x = lsq_linear(M, target, bounds=(np.zeros(len(cols)), ub), method="bvls").x
            for (k, _j, sc), xi in zip(use, x):
                ks[k] = float(min(max(xi / sc, 0.0), PARAM_BOUNDS[k][1]))
        for j, k in enumerate(LINEAR_TERMS):
            model = model + ks[k] * A[:, j]
        res = model - self.y * self.w
        if not np.all(np.isfinite(res)):
            return None
        # the coefficients the least squares moves at this point: free, positive, below their bound
        moving = [j for k, j, _ in use if 0.0 < ks[k] < PARAM_BOUNDS[k][1]]
        self._last = (stage, np.asarray(z, dtype=np.float64).tobytes(), dict(ks), A, res, moving,
                      dsim * self.w[:, None])
        P.update(ks)
        return P, res

    def jacobian(self, z, stage: str) -> np.ndarray:
        """d(weighted residual)/dz of :meth:`residual` (the coefficients re-solved at every z: variable
        projection), from the columns' analytic shape derivatives that :meth:`solve` keeps
        (:meth:`roadgonio.engines.bundle.ForwardModel.columns_and_shape_derivatives`). With ``A_S`` the weighted
        columns of the coefficients the least squares moves (the others held at 0, a bound or their
        fixed value), ``x`` all coefficients, ``r`` the residual and ``dA`` a shape parameter's
        derivative of the columns (Golub and Pereyra's derivative of the projected residual)::

            dr = (I - A_S A_S^+) dA x - (A_S^+)^T dA_S^T r

        the derivative that finite differences of :meth:`residual` approximate wherever the set of
        moving coefficients does not change within the step. A point the model cannot evaluate
        (residual 1e6 everywhere) has the derivative 0."""
        z = np.asarray(z, dtype=np.float64)
        if self._last is None or self._last[:2] != (stage, z.tobytes()):
            if self.solve(z, stage) is None:
                return np.zeros((self.y.size, z.size))
        _, _, ks, A, res, moving, D = self._last
        if moving:
            # columns scaled to unit maximum first (as the solve scales them): the columns' sizes
            # differ by up to 1e36 where a term is nearly switched off, and A_S^+ = diag(1/sc) pinv_n
            sc = np.max(np.abs(A[:, moving]), axis=0)
            A_n = A[:, moving] / sc
            pinv_n = np.linalg.pinv(A_n)
        J = np.zeros((self.y.size, z.size))
        for i, name in enumerate(self.free_nl):
            term = SHAPE_TERM[name]
            j = LINEAR_TERMS.index(term)
            col = D[:, i]
            d = ks[term] * col
            if moving:
                d = d - A_n @ (pinv_n @ d)
                if j in moving:
                    k = moving.index(j)
                    d = d - pinv_n[k] * (float(col @ res) / sc[k])
            J[:, i] = d * _dz_dp(name, float(z[i]))
        return J

    def residual(self, z, stage: str) -> np.ndarray:
        out = self.solve(z, stage)
        if out is None:
            return np.full(self.y.size, 1e6)
        return out[1]

    def run_ls(self, z0, stage: str, max_nfev: int) -> tuple[np.ndarray, float]:
        if not self.free_nl:
            return np.zeros(0), float(np.sum(self.residual(np.zeros(0), stage) ** 2))
        z0 = np.clip(np.asarray(z0, dtype=np.float64), self.lo, self.hi)
        tol = 1e-10 if stage == "A" else STAGE_B_FTOL
        r = least_squares(lambda z: self.residual(z, stage), z0, jac=lambda z: self.jacobian(z, stage),
                          bounds=(self.lo, self.hi), method="trf",
                          x_scale=np.maximum(self.hi - self.lo, 1e-6) * 0.1, max_nfev=max_nfev,
                          xtol=1e-8, ftol=tol, gtol=1e-8)
        return r.x, float(2.0 * r.cost)


def _lhs(rng: np.random.Generator, n: int, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    d = lo.size
    u = (np.argsort(rng.random((d, n)), axis=1).T + rng.random((n, d))) / n
    return lo + (hi - lo) * u


def fit_through_instrument(forward: ForwardModel, measured: np.ndarray, u: np.ndarray, *, variant: str,
                           rho: np.ndarray | None = None, start_models: Sequence[RoadModel] = (),
                           starts: int = DEFAULT_STARTS, polish: int = DEFAULT_POLISH, seed: int = 0,
                           restart: int = 0, fixed: Mapping[str, float] | None = None, k_frozen: np.ndarray | None = None,
                           stage_a: bool = True, stage_b: bool = True, max_nfev: int = 400,
                           progress: Callable[[str], None] | None = None, name: str = "fit") -> ThroughFit:
    """Fit the model ``variant`` to the measured r per cell (``measured``, sr^-1, with standard
    uncertainties ``u``) through ``forward`` (module docstring). ``k_frozen`` is stage A's estimate
    of k_A per cell (default: the forward model's k_A of the first start model, else 1).
    ``stage_a=False`` polishes only from ``start_models`` (a refit after ``rho`` changed). The
    start points of stage A are drawn from the stream (``seed``, ``restart``) of
    :func:`roadgonio.seeds.seed_entropy` (another seed never repeats them)."""
    t0 = time.perf_counter()
    fx = dict(fixed or {})
    unknown = sorted(set(fx) - set(PARAM_NAMES))
    if unknown:
        raise InputError(f"unknown parameter(s) {', '.join(unknown)}", field="fixed")
    if k_frozen is None:
        k_frozen = forward.k_a(start_models[0], rho) if start_models else None
    prob = _Problem(forward, measured, u, variant, fx, rho, k_frozen)
    cand: list[tuple[float, np.ndarray]] = []
    z_starts = [prob.z_of(m) for m in start_models]
    if stage_a and prob.free_nl:
        rng = np.random.default_rng(seed_entropy(seed, int(restart), 11))
        z_starts = z_starts + list(_lhs(rng, int(starts), prob.lo, prob.hi))
        span = np.maximum(prob.hi - prob.lo, 1e-12)

        def distinct(cands):
            out: list[tuple[float, np.ndarray]] = []
            for cost, z in sorted(cands, key=lambda c: c[0]):
                if all(np.max(np.abs(z - z2) / span) > 0.02 for _, z2 in out):
                    out.append((cost, z))
            return out

        # a short run from every start, then the most promising ones to convergence
        for k, z0 in enumerate(z_starts):
            z, cost = prob.run_ls(z0, "A", COARSE_NFEV)
            cand.append((cost, z))
            if progress is not None:
                progress(f"{name}: stage A start {k + 1}/{len(z_starts)}")
        refined = []
        for _, z0 in distinct(cand)[:REFINE]:
            z, cost = prob.run_ls(z0, "A", max_nfev)
            refined.append((cost, z))
        best_a = distinct(refined)
        stage_a_costs = [c for c, _ in best_a[:5]]
        seeds_b = [z for _, z in best_a[:max(1, int(polish))]]
    else:
        stage_a_costs = []
        seeds_b = z_starts or [np.zeros(len(prob.free_nl))]
    if not stage_b:
        return _stage_a_result(prob, seeds_b[0], forward, name, len(z_starts), stage_a_costs, t0)
    best = None
    for k, z0 in enumerate(seeds_b):
        z, cost = prob.run_ls(z0, "B", STAGE_B_NFEV)
        if best is None or cost < best[0]:
            best = (cost, z)
        if progress is not None:
            progress(f"{name}: stage B {k + 1}/{len(seeds_b)}")
    cost, z = best
    sol = prob.solve(z, "B")
    if sol is None:
        raise InputError("the fit through the instrument found no finite model", field="measured")
    P, res = sol
    params = RoadParams(**{k: (float(min(max(P[k], PARAM_BOUNDS[k][0]), PARAM_BOUNDS[k][1]))
                               if k != "theta_l_deg" else float(P[k])) for k in PARAM_NAMES})
    model = RoadModel(params, variant, name=name)
    free, cov, lnk_jac = _covariance(prob, z, params, res)
    n = prob.y.size
    dof = max(n - len(free), 1)
    chi2 = float(np.sum(res ** 2))
    return ThroughFit(model=model, chi2=chi2, dof=dof, cells=n, free=free, cov=cov,
                      simulated=forward.r_measured(model, prob.rho), k_a=forward.k_a(model, prob.rho),
                      lnk_jac=lnk_jac, residual=res, starts=len(z_starts), nfev=prob.nfev,
                      seconds=time.perf_counter() - t0, stage_a=stage_a_costs)


def chi2_of(forward: ForwardModel, measured: np.ndarray, u: np.ndarray, model: RoadModel,
            rho: np.ndarray | None = None) -> float:
    """chi^2 of a model through ``forward`` (one pass over the rays)."""
    return float(np.sum(((forward.r_measured(model, rho) - measured) / u) ** 2))


def _stage_a_result(prob: _Problem, z, forward: ForwardModel, name: str, starts: int, costs, t0) -> ThroughFit:
    """The stage-A optimum as a ThroughFit, chi^2 through the bundles, no covariance."""
    P, _ = prob.solve(z, "A")
    model = RoadModel(RoadParams(**{k: (float(min(max(P[k], PARAM_BOUNDS[k][0]), PARAM_BOUNDS[k][1]))
                                        if k != "theta_l_deg" else float(P[k])) for k in PARAM_NAMES}),
                      prob.variant, name=name)
    sim = forward.r_measured(model, prob.rho)
    res = (sim - prob.y) * prob.w
    n = prob.y.size
    return ThroughFit(model=model, chi2=float(np.sum(res ** 2)), dof=n, cells=n, free=[], cov=np.zeros((0, 0)),
                      simulated=sim, k_a=forward.k_a(model, prob.rho), lnk_jac=np.zeros((n, 0)), residual=res,
                      starts=starts, nfev=prob.nfev, seconds=time.perf_counter() - t0, stage_a=list(costs))


def assess_fit(forward: ForwardModel, measured: np.ndarray, u: np.ndarray, model: RoadModel, *,
               rho: np.ndarray | None = None, fixed: Mapping[str, float] | None = None, name: str = "fit") -> ThroughFit:
    """A :class:`ThroughFit` of a given ``model`` (no optimisation): chi^2, residuals, parameter
    covariance and the Jacobian of ln k_A at exactly that model, through ``forward`` with ``rho``."""
    t0 = time.perf_counter()
    G = {k: v for k, v in model.params.to_dict().items() if k in G_PARAMS}
    prob = _Problem(forward, measured, u, model.variant, {**G, **dict(fixed or {})}, rho, None)
    z = prob.z_of(model)
    sim = forward.r_measured(model, prob.rho)
    res = (sim - prob.y) * prob.w
    free, cov, lnk_jac = _covariance(prob, z, model.params, res)
    n = prob.y.size
    return ThroughFit(model=model, chi2=float(np.sum(res ** 2)), dof=max(n - len(free), 1), cells=n, free=free,
                      cov=cov, simulated=sim, k_a=forward.k_a(model, prob.rho), lnk_jac=lnk_jac, residual=res,
                      starts=0, nfev=0, seconds=time.perf_counter() - t0)


def _covariance(prob: _Problem, z: np.ndarray, params: RoadParams, res: np.ndarray):
    """(free names, covariance of the free natural parameters, d ln k / d free) at the optimum."""
    fm = prob.fm
    P = params.to_dict()
    theta = np.array([P[k] for k in LINEAR_TERMS])
    # the columns and their shape derivatives from one pass per term
    B, N, dB, dN = fm.columns_and_shape_derivatives(P, prob.variant, prob.free_nl)
    mean, nom = B @ theta, N @ theta
    scale = fm.bundles.cos3 * fm.kappa * prob.rho * prob.w
    free: list[str] = []
    J_cols: list[np.ndarray] = []
    K_cols: list[np.ndarray] = []
    for j, k in enumerate(LINEAR_TERMS):
        if k in prob.fixed or theta[j] <= 0.0:
            continue
        free.append(k)
        J_cols.append(scale * B[:, j])
        K_cols.append(B[:, j] / mean - N[:, j] / nom)
    for i, name in enumerate(prob.free_nl):
        zi = _to_z(name, P[name])
        if zi - prob.lo[i] < AT_BOUND or prob.hi[i] - zi < AT_BOUND:
            continue                     # at (or beyond) a bound of the search box: held there
        c = theta[LINEAR_TERMS.index(SHAPE_TERM[name])]
        free.append(name)
        J_cols.append(scale * c * dB[:, i])
        K_cols.append(c * (dB[:, i] / mean - dN[:, i] / nom))
    n_free = len(free)
    if n_free == 0:
        return [], np.zeros((0, 0)), np.zeros((prob.y.size, 0))
    J = np.stack(J_cols, axis=1)
    K = np.stack(K_cols, axis=1)
    dof = max(prob.y.size - n_free, 1)
    s2 = max(1.0, float(np.sum(res ** 2)) / dof)
    # scale columns for conditioning, pseudo-inverse for (near-)degenerate directions
    cs = np.linalg.norm(J, axis=0)
    cs[cs == 0] = 1.0
    Jn = J / cs
    cov = np.linalg.pinv(Jn.T @ Jn, rcond=1e-12, hermitian=True) / np.outer(cs, cs) * s2
    return free, cov, K
