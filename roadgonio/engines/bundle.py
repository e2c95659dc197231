"""The forward model of a measurement: what the instrument reports for a BRDF model, per cell, as a
smooth function of the model's parameters (docs/conventions.md sections 4-5; paper eq. 2-3).

The detector signal is linear in the BRDF. For a **fixed** set of rays per cell (a ray bundle:
pupil point, field point, hit point, source point, with their weights, sampled once in float64 by
:mod:`roadgonio.instrument.optics`, the same geometry code the numpy Monte Carlo backend uses) the
instrument's reading of any BRDF f is a weighted mean over the same rays (common random numbers)::

    <f>_c = sum_k a_ck f(w_i,ck, w_o,ck),      a_ck = w_ck G_ck / sum_k w_ck G_ck

(w the detector's etendue x k_D weight, G the source coupling), so the simulated table is a smooth
function of the parameters and linear in the four coefficients k_diff, k_phong, k_retro, k_exp.
Under the instrument's calibration (:mod:`roadgonio.engines.calibration`) the reported r and k_A are::

    r_sim,c = cos^3(eps_c) kappa_c <f>_c,        k_A,c = kappa_c <f>_c / f_c(nominal)

with kappa_c = 1 (lambert), eta_c = <E>/E_0 (absolute; from
:func:`roadgonio.engines.calibration.illuminance_ratio`) or f_ref,c(nominal) / <f_ref>_c (reference,
over the same rays). The BRDF is evaluated only by :func:`roadgonio.surface.model.road_brdf`, one
term at a time with unit coefficient (a term's column), so a change of one shape parameter
re-evaluates only the term that uses it.

Sampling: each cell's rays are ``replicates`` randomised quasi-Monte Carlo point sets in the 6-D
unit cube (a scrambled Sobol' net per replicate under a random shift per cell; two coordinates per
disc, concentric map), seeded by (seed, cell index): a cell's rays
do not depend on the other cells, and the cell of the same index in a perturbed instrument (a
misalignment) gets the same unit points, so differences are smooth. The replicates give the
bundle's own standard error by the delta method (:func:`roadgonio.engines.ratio_se`). Where the
detected rays' illuminance weights are very uneven (effective sample size below half the rays: a
wide footprint that reaches under the source) a cell gets up to ``max_factor`` times more rays.

:class:`BundleBackend` exposes the bundle as a k_A backend (``CellResult`` with a standard error);
the correction uses it for derivatives (parameter covariance, misalignment sensitivities), never
for the reported factor, which comes from the chosen backend.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from roadgonio.engines import CellResult, ratio_se
from roadgonio.engines.calibration import apply_calibration, centre_coupling, illuminance_ratio
from roadgonio.engines.cellcheck import check_cells, no_light
from roadgonio.errors import InputError
from roadgonio.seeds import seed_entropy
from roadgonio.geometry import cos3_eps
from roadgonio.instrument import optics
from roadgonio.instrument.config import Instrument
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import (G_PARAMS, LINEAR_TERMS, SHAPE_TERM, TERM_SHAPE, RoadModel, modifier_terms,
                                     road_brdf, road_brdf_with_shape_grad)

DEFAULT_RAYS = 512
DEFAULT_REPLICATES = 4
DEFAULT_MAX_FACTOR = 8
#: A cell whose illuminance-weighted effective sample size is below this fraction of its rays gets more.
ESS_TARGET = 0.5


@lru_cache(maxsize=64)
def _sobol_net(seed: int, replicate: int, n: int) -> np.ndarray:
    """A scrambled Sobol' net of n = 2^m points in [0, 1)^6 (read-only, cached)."""
    from scipy.stats import qmc
    m = int(round(math.log2(n)))
    u = qmc.Sobol(6, scramble=True, seed=np.random.default_rng(seed_entropy(seed, replicate, n))).random_base2(m)
    u.setflags(write=False)
    return u


def _unit_points(seed: int, indices: np.ndarray, replicate: int, n: int) -> np.ndarray:
    """(len(indices), n, 6) points of one replicate for the cells ``indices``: the replicate's
    scrambled net under a random digital shift per cell (XOR of the 32-bit digits, seeded by
    (seed, cell index, replicate)): randomised QMC that keeps the net's structure, independent between
    cells and replicates, and cheap (the net is scrambled once)."""
    net = (_sobol_net(seed, replicate, n) * 2.0 ** 32).astype(np.uint64)
    shifts = np.array([np.random.default_rng(seed_entropy(seed, int(i), replicate, 1)).integers(0, 2 ** 32, 6,
                                                                                            dtype=np.uint64)
                       for i in indices], dtype=np.uint64)
    u = np.bitwise_xor(net[None, :, :], shifts[:, None, :]).astype(np.float64)
    return (u + 0.5) * 2.0 ** -32


def _stacked_source(instrument: Instrument, cells: Sequence[tuple[float, float]], n: int) -> optics.SourceGeometry:
    """The source geometry of several cells as one :class:`~roadgonio.instrument.optics.SourceGeometry`
    whose vectors hold one value per ray (``n`` rays per cell), so the optics code runs once."""
    geos = [optics.source_geometry(instrument, t, b) for t, b in cells]

    def stack(attr):
        v = np.array([getattr(g, attr) for g in geos])          # (cells, 3)
        return tuple(np.repeat(v[:, k], n) for k in range(3))
    return optics.SourceGeometry(centre=stack("centre"), axis=stack("axis"), s=stack("s"), t=stack("t"),
                                 radius_m=geos[0].radius_m, cos_beam=geos[0].cos_beam, beam=geos[0].beam,
                                 aperture=geos[0].aperture)


@dataclass
class RayBundles:
    """Fixed float64 ray bundles of one instrument over a list of cells (module docstring).

    Flat arrays over all rays, cell-major, replicate-minor; ``seg`` holds the start of every
    (cell, replicate) segment and ``cell_start`` of every cell. ``a`` are the illuminance weights
    normalised per cell (a cell's ``a`` sum to 1); ``rep_share[c, r]`` is the share of replicate
    r in cell c's weight."""

    instrument: Instrument
    cells: list[tuple[float, float]]
    wi: tuple[np.ndarray, np.ndarray, np.ndarray]
    wo: tuple[np.ndarray, np.ndarray, np.ndarray]
    a: np.ndarray
    seg: np.ndarray
    cell_start: np.ndarray
    rays_per_cell: np.ndarray
    replicates: int
    rep_share: np.ndarray
    ess_fraction: np.ndarray
    eta_bundle: np.ndarray        # <E>/E_0 estimated over the bundle (w-weighted mean of G over G(0))
    wi0: np.ndarray               # (n, 3) nominal source directions
    wo0: np.ndarray               # (3,) nominal detector direction
    cos3: np.ndarray              # (n,) cos^3 eps
    seed: int
    seconds: float

    @property
    def n_cells(self) -> int:
        return len(self.cells)

    @property
    def n_rays(self) -> int:
        return int(self.a.size)

    def cell_sum(self, values: np.ndarray) -> np.ndarray:
        """sum over each cell's rays of a * values: the bundle mean <values>_c."""
        return np.add.reduceat(self.a * values, self.cell_start)

    def segment_sum(self, values: np.ndarray) -> np.ndarray:
        """(n_cells, replicates) sums of a * values per replicate."""
        return np.add.reduceat(self.a * values, self.seg).reshape(self.n_cells, self.replicates)

    @classmethod
    def build(cls, instrument: Instrument, cells: Sequence[tuple[float, float]], *, rays: int = DEFAULT_RAYS,
              replicates: int = DEFAULT_REPLICATES, seed: int = 0, max_factor: int = DEFAULT_MAX_FACTOR,
              sizes: Sequence[int] | None = None) -> "RayBundles":
        """Sample the bundles (module docstring). ``sizes`` fixes the rays per cell (e.g. those of
        the nominal instrument, for a perturbed copy of it)."""
        t0 = time.perf_counter()
        rays, replicates, max_factor = int(rays), int(replicates), int(max_factor)
        per = rays // replicates
        if replicates < 2 or per < 2 or per & (per - 1):
            raise InputError(f"expected rays / replicates to be a power of two >= 2 and at least 2 replicates, "
                             f"got {rays} rays in {replicates} replicates", field="rays")
        if instrument.sample.mesh is not None:
            raise InputError("the forward model of the correction integrates over a flat rectangular sample; a "
                             "mesh sample is not supported by `roadgonio correct` yet", path=instrument.path,
                             field="sample.mesh")
        optics.check_detector(instrument)
        det = optics.detector_geometry(instrument)
        cells = [(float(t), float(b)) for t, b in cells]
        if sizes is not None and len(sizes) != len(cells):
            raise InputError("expected one bundle size per cell", field="sizes")
        for t, b in cells:
            optics.check_source(instrument, t, b)
        n_cells = len(cells)
        g0 = np.array([centre_coupling(optics.source_geometry(instrument, t, b)) for t, b in cells])

        def sample(idx: np.ndarray, n_rep: int):
            """Rays of the cells ``idx`` with n_rep rays per replicate: arrays (len(idx), R * n_rep)."""
            u = np.stack([_unit_points(seed, idx, r, n_rep) for r in range(replicates)], axis=1).reshape(-1, 6)
            pupil = optics.concentric_disc(NumpyOps, u[:, 0], u[:, 1])
            field = optics.concentric_disc(NumpyOps, u[:, 2], u[:, 3])
            sdisc = optics.concentric_disc(NumpyOps, u[:, 4], u[:, 5])
            src = _stacked_source(instrument, [cells[i] for i in idx], replicates * n_rep)
            with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
                o, d, w = optics.detector_ray(NumpyOps, det, pupil, field)
                x, y, valid = optics.hit_plane(NumpyOps, o, d)
                wi, g = optics.source_coupling(NumpyOps, src, x, y, optics.source_point(src, sdisc), sdisc)
            w = np.broadcast_to(np.asarray(w, dtype=np.float64), valid.shape)
            wg = np.where(valid, w * g, 0.0)
            shape = (len(idx), replicates * n_rep)
            full = lambda v: np.broadcast_to(np.asarray(v, dtype=np.float64), valid.shape).reshape(shape)
            return ([full(c) for c in wi], [full(-c) for c in d], wg.reshape(shape), w.reshape(shape))

        if sizes is None:
            base = np.full(n_cells, per, dtype=np.int64)
        else:
            base = np.asarray(sizes, dtype=np.int64) // replicates
        per_cell: list = [None] * n_cells
        for n_rep in np.unique(base):
            idx = np.nonzero(base == n_rep)[0]
            wi, wo, wg, w = sample(idx, int(n_rep))
            for k, i in enumerate(idx):
                per_cell[i] = (int(n_rep), [c[k] for c in wi], [c[k] for c in wo], wg[k], w[k])
        if sizes is None and max_factor > 1:
            ess0 = np.array([_ess(pc[3]) for pc in per_cell])
            factor = np.ones(n_cells, dtype=np.int64)
            low = ess0 < ESS_TARGET
            factor[low] = np.minimum(max_factor, 2 ** np.ceil(np.log2(ESS_TARGET / np.maximum(ess0[low], 1e-12))))
            for f in np.unique(factor[factor > 1]):
                idx = np.nonzero(factor == f)[0]
                wi, wo, wg, w = sample(idx, int(per * f))
                for k, i in enumerate(idx):
                    per_cell[i] = (int(per * f), [c[k] for c in wi], [c[k] for c in wo], wg[k], w[k])
        parts: dict[str, list[np.ndarray]] = {k: [] for k in ("wix", "wiy", "wiz", "wox", "woy", "woz", "a")}
        n_of, ess_of, eta_of, share_of = [], [], [], []
        for i, (n_rep, wi, wo, wg, w) in enumerate(per_cell):
            lam = float(wg.sum())
            if not lam > 0.0:
                t, b = cells[i]
                raise no_light(t, b)
            a = wg / lam
            for k, arr in zip(("wix", "wiy", "wiz", "wox", "woy", "woz"), (*wi, *wo)):
                parts[k].append(arr)
            parts["a"].append(a)
            n_of.append(a.size)
            ess_of.append(_ess(wg))
            eta_of.append(float(np.sum(wg) / np.sum(w)) / g0[i] if g0[i] > 0 else math.nan)
            share_of.append(a.reshape(replicates, n_rep).sum(axis=1))
        sizes_arr = np.array(n_of, dtype=np.int64)
        cell_start = np.concatenate([[0], np.cumsum(sizes_arr)[:-1]]).astype(np.int64)
        seg = (cell_start[:, None] + (sizes_arr // replicates)[:, None] * np.arange(replicates)[None, :]).ravel()
        wi0 = np.array([instrument.w_i(t, b) for t, b in cells]).reshape(-1, 3)
        return cls(instrument=instrument, cells=cells,
                   wi=tuple(np.concatenate(parts[k]) for k in ("wix", "wiy", "wiz")),
                   wo=tuple(np.concatenate(parts[k]) for k in ("wox", "woy", "woz")),
                   a=np.concatenate(parts["a"]), seg=seg, cell_start=cell_start, rays_per_cell=sizes_arr,
                   replicates=replicates, rep_share=np.array(share_of), ess_fraction=np.array(ess_of),
                   eta_bundle=np.array(eta_of), wi0=wi0, wo0=np.asarray(instrument.w_o(), dtype=np.float64),
                   cos3=cos3_eps(np.array([t for t, _ in cells])), seed=int(seed),
                   seconds=time.perf_counter() - t0)

    def summary(self) -> dict[str, Any]:
        return {"cells": self.n_cells, "rays": self.n_rays, "rays_per_cell_min": int(self.rays_per_cell.min()),
                "rays_per_cell_max": int(self.rays_per_cell.max()), "replicates": self.replicates,
                "ess_fraction_min": float(self.ess_fraction.min()), "seed": self.seed,
                "sampling": "scrambled Sobol' net per replicate (scipy.stats.qmc), random shift per cell, concentric map of each disc",
                "seconds": self.seconds}


def _ess(wg: np.ndarray) -> float:
    s2 = float(np.sum(wg * wg))
    return float(np.sum(wg)) ** 2 / (wg.size * s2) if s2 > 0 else 0.0


# ----------------------------------------------------------------------------------------------
# Columns and the forward model
# ----------------------------------------------------------------------------------------------

def _terms_for(term: str, P: Mapping[str, float]) -> frozenset[str]:
    return frozenset({term}) | modifier_terms(P)


def _unit(P: Mapping[str, float]) -> dict[str, float]:
    Q = dict(P)
    for k in LINEAR_TERMS:
        Q[k] = 1.0
    return Q


class ForwardModel:
    """Simulated measured r and k_A of BRDF models through one instrument (module docstring).

    ``kappa`` is the calibration factor per cell (1, eta or the reference's f(nominal)/<f>); ``rho``
    an optional per-cell factor applied to the bundle's reading (the correction of the bundle's
    own error by an exact backend table, :mod:`roadgonio.correction.fit`)."""

    def __init__(self, bundles: RayBundles, *, calibration_mode: str | None = None,
                 reference: RoadModel | None = None, eta: np.ndarray | None = None):
        self.bundles = bundles
        inst = bundles.instrument
        self.mode = calibration_mode or inst.calibration.mode
        n = bundles.n_cells
        self.wi0 = tuple(bundles.wi0[:, k] for k in range(3))
        self.wo0 = tuple(np.full(n, bundles.wo0[k]) for k in range(3))
        self._cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._nominal_cache: dict[tuple, np.ndarray] = {}
        self._grad_cache: dict[tuple, tuple] = {}
        # what road_brdf computes from the (fixed) directions alone, kept across the fits' many
        # evaluations (its ``pairs``): one dict for the rays, one for the nominal directions. A
        # polish through the bundles re-evaluated the pair angles of every ray ~3600 times (10.9 s
        # of a 57.6 s correction, two_lobes through A, cProfile)
        self._pairs_rays: dict = {}
        self._pairs_nominal: dict = {}
        #: What callers above derive from the rays' directions alone and keep with the bundles, keyed
        #: by the caller (the correction surface's sparse operators, :mod:`roadgonio.correction.flexible`:
        #: one build shared by every backbone's fit through these rays)
        self.derived: dict = {}
        mean_ref = nom_ref = None
        if self.mode == "absolute" and eta is None:
            eta = np.array([illuminance_ratio(inst, t, b)[0] for t, b in bundles.cells])
        elif self.mode == "reference":
            reference = reference or inst.calibration.reference_model()
            mean_ref, nom_ref = self.model_columns_total(reference)
        eta = None if eta is None else np.asarray(eta, dtype=np.float64)
        self.kappa = apply_calibration(self.mode, np.ones(n), eta=eta, reference_reading=mean_ref,
                                       reference_nominal=nom_ref)
        self.reference = reference

    # -- columns -----------------------------------------------------------------------------
    def column(self, term: str, P: Mapping[str, float], variant: str) -> tuple[np.ndarray, np.ndarray]:
        """(bundle mean, nominal value) per cell of one term with unit coefficient."""
        hit = self._cache.get(self._key(term, P, variant))
        if hit is not None:
            return hit
        mean, nom, _, _ = self._column_grad(term, P, variant, (), True)
        return mean, nom

    def nominal_columns(self, P: Mapping[str, float], variant: str) -> np.ndarray:
        """(n_cells, 4) values of the unit-coefficient terms at the nominal geometry only (cheap)."""
        N = np.zeros((self.bundles.n_cells, len(LINEAR_TERMS)))
        for j, t in enumerate(LINEAR_TERMS):
            N[:, j] = self._nominal_column(t, P, variant)
        return N

    def _nominal_column(self, term: str, P: Mapping[str, float], variant: str) -> np.ndarray:
        """One term's unit-coefficient values at the nominal geometry (:meth:`nominal_columns`), cached."""
        key = ("nominal",) + self._key(term, P, variant)
        col = self._nominal_cache.get(key)
        if col is None:
            with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
                col = np.broadcast_to(road_brdf(NumpyOps, _unit(P), self.wi0, self.wo0, variant, _terms_for(term, P),
                                                pairs=self._pairs_nominal), (self.bundles.n_cells,)).copy()
            if len(self._nominal_cache) > 4096:
                self._nominal_cache.clear()
            self._nominal_cache[key] = col
        return col

    def columns_and_shape_derivatives(self, P: Mapping[str, float], variant: str, names: Sequence[str],
                                      bundle: bool = True) -> tuple[np.ndarray | None, np.ndarray,
                                                                    np.ndarray | None, np.ndarray]:
        """(B, N, dB, dN): the unit-coefficient columns of :meth:`columns` (``bundle=False``: the nominal
        values alone, B and dB None, as :meth:`nominal_columns`) and their derivatives with respect to
        the shape parameters ``names`` (natural units; (n_cells, len(names)), each the derivative of
        the column of the term it shapes, :data:`roadgonio.surface.model.SHAPE_TERM`), a term's value
        and derivatives from one pass of :func:`roadgonio.surface.model.road_brdf_with_shape_grad`
        (the same values as :meth:`column`). The fits' Jacobians."""
        n = self.bundles.n_cells
        B = np.zeros((n, len(LINEAR_TERMS))) if bundle else None
        dB = np.zeros((n, len(names))) if bundle else None
        N = np.zeros((n, len(LINEAR_TERMS)))
        dN = np.zeros((n, len(names)))
        for j, term in enumerate(LINEAR_TERMS):
            own = [i for i, name in enumerate(names) if SHAPE_TERM.get(name) == term]
            if not own:
                if bundle:
                    B[:, j], N[:, j] = self.column(term, P, variant)
                else:
                    N[:, j] = self._nominal_column(term, P, variant)
                continue
            mean, nom, dmean, dnom = self._column_grad(term, P, variant, tuple(names[i] for i in own), bundle)
            N[:, j], dN[:, own] = nom, dnom
            if bundle:
                B[:, j], dB[:, own] = mean, dmean
        return B, N, dB, dN

    def _column_grad(self, term: str, P: Mapping[str, float], variant: str, wrt: tuple[str, ...], bundle: bool):
        """(mean, nominal, d mean, d nominal) of one term's unit-coefficient column and its derivatives
        with respect to ``wrt`` (:meth:`columns_and_shape_derivatives`; none: the column alone,
        :meth:`column`), cached."""
        key = ("grad", bundle, wrt) + self._key(term, P, variant)
        hit = self._grad_cache.get(key) if wrt else None
        if hit is not None:
            return hit
        Q = _unit(P)
        terms = _terms_for(term, P)
        b = self.bundles
        n = b.n_cells
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            f0, g0 = road_brdf_with_shape_grad(NumpyOps, Q, self.wi0, self.wo0, variant, terms, wrt,
                                               pairs=self._pairs_nominal)
            nom = np.broadcast_to(f0, (n,)).copy()
            dnom = np.stack([np.broadcast_to(g, (n,)) for g in g0], axis=1) if wrt else np.zeros((n, 0))
            mean = dmean = None
            if bundle:
                f, g = road_brdf_with_shape_grad(NumpyOps, Q, b.wi, b.wo, variant, terms, wrt, pairs=self._pairs_rays)
                mean = b.cell_sum(np.broadcast_to(np.asarray(f, dtype=np.float64), b.a.shape))
                dmean = np.stack([b.cell_sum(np.broadcast_to(np.asarray(gk, dtype=np.float64), b.a.shape))
                                  for gk in g], axis=1) if wrt else np.zeros((n, 0))
                if len(self._cache) > 256:
                    self._cache.clear()
                self._cache.setdefault(self._key(term, P, variant), (mean, nom))
        out = (mean, nom, dmean, dnom)
        if wrt:
            if len(self._grad_cache) > 256:
                self._grad_cache.clear()
            self._grad_cache[key] = out
        return out

    @staticmethod
    def _key(term: str, P: Mapping[str, float], variant: str) -> tuple:
        """What a term's column depends on: the term, the variant, its shape parameters and g."""
        shape = tuple(float(P.get(k, 0.0)) for k in TERM_SHAPE[term] if k != "n_beta" or variant == "smooth")
        return (term, variant, shape, tuple(float(P[k]) for k in G_PARAMS))

    def columns(self, P: Mapping[str, float], variant: str,
                terms: Sequence[str] = LINEAR_TERMS) -> tuple[np.ndarray, np.ndarray]:
        """(B, N): (n_cells, 4) bundle means and nominal values of the unit-coefficient terms."""
        B = np.zeros((self.bundles.n_cells, len(LINEAR_TERMS)))
        N = np.zeros_like(B)
        for j, t in enumerate(LINEAR_TERMS):
            if t in terms:
                B[:, j], N[:, j] = self.column(t, P, variant)
        return B, N

    def model_columns_total(self, model: RoadModel) -> tuple[np.ndarray, np.ndarray]:
        """(<f>_c, f_c(nominal)) of a model."""
        P = model.params.to_dict()
        theta = np.array([P[k] for k in LINEAR_TERMS])
        active = [t for t, v in zip(LINEAR_TERMS, theta) if v != 0.0]
        B, N = self.columns(P, model.variant, active)
        return B @ theta, N @ theta

    # -- what the instrument reports ----------------------------------------------------------
    def k_a(self, model: RoadModel, rho: np.ndarray | None = None) -> np.ndarray:
        """k_A per cell under the instrument's calibration (times ``rho`` if given)."""
        mean, nom = self.model_columns_total(model)
        k = self.kappa * mean / nom
        return k if rho is None else k * rho

    def r_measured(self, model: RoadModel, rho: np.ndarray | None = None) -> np.ndarray:
        """The r the instrument reports (sr^-1) per cell."""
        mean, _ = self.model_columns_total(model)
        r = self.bundles.cos3 * self.kappa * mean
        return r if rho is None else r * rho

    def ray_brdf(self, model: RoadModel) -> np.ndarray:
        """f_r of ``model`` at every ray (float64), what the directions alone give taken from the
        kept ``pairs`` (the same numbers as ``model.evaluate`` at the rays)."""
        b = self.bundles
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            return np.asarray(road_brdf(NumpyOps, model.params.to_dict(), b.wi, b.wo, model.variant, model.terms(),
                                        pairs=self._pairs_rays), dtype=np.float64)

    def log_derivatives(self, model: RoadModel, wrt: Sequence[str],
                        nominal: bool = False) -> tuple[list[str], np.ndarray]:
        """At every ray (``nominal``: at the cells' nominal directions) the derivatives of ln f_r of
        ``model``: with respect to ln a_k of every active linear term (``a_k f_k / f``, f_k the term at
        unit coefficient) and to the shape parameters ``wrt`` (natural units, names of
        :data:`roadgonio.surface.model.SHAPE_TERM`), from :func:`road_brdf_with_shape_grad` (no finite
        differences); 0 where f_r is 0. Returns (names: ``ln_<term>`` then ``wrt``, an array
        (len(names), rays) or (len(names), n_cells))."""
        P = model.params.to_dict()
        if nominal:
            wi, wo, pairs = self.wi0, self.wo0, self._pairs_nominal
        else:
            wi, wo, pairs = self.bundles.wi, self.bundles.wo, self._pairs_rays
        active = [k for k in LINEAR_TERMS if P[k] > 0.0]
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            f, g = road_brdf_with_shape_grad(NumpyOps, P, wi, wo, model.variant, model.terms(), tuple(wrt),
                                             pairs=pairs)
            f = np.asarray(f, dtype=np.float64)
            if nominal:
                f = np.broadcast_to(f, (self.bundles.n_cells,))
            parts = [P[k] * np.asarray(road_brdf(NumpyOps, _unit(P), wi, wo, model.variant, _terms_for(k, P),
                                                 pairs=pairs), dtype=np.float64) for k in active]
            parts += [np.asarray(gk, dtype=np.float64) for gk in g]
            safe = np.where(f > 0, f, 1.0)
            out = np.stack([np.where(f > 0, np.broadcast_to(d, f.shape) / safe, 0.0) for d in parts]) if parts \
                else np.zeros((0,) + f.shape)
        return [f"ln_{k}" for k in active] + list(wrt), out

    def k_a_se(self, model: RoadModel) -> np.ndarray:
        """Standard error of the bundle's k_A (spread over the replicates, delta method)."""
        b = self.bundles
        f = self.ray_brdf(model)
        road = b.segment_sum(np.broadcast_to(f, b.a.shape))
        _, nom = self.model_columns_total(model)
        se = np.array([ratio_se(road[c], b.rep_share[c])[1] for c in range(b.n_cells)])
        return self.kappa * se / nom


# ----------------------------------------------------------------------------------------------
# The bundle as a k_A backend (derivatives only)
# ----------------------------------------------------------------------------------------------

class BundleBackend:
    """k_A from fixed ray bundles (:class:`RayBundles`, :class:`ForwardModel`): fast, smooth in
    the parameters and in the instrument's geometry (common random numbers), with the replicates'
    standard error. Built per (instrument, model) like every backend."""

    name = "bundle"

    def __init__(self, instrument: Instrument, model: RoadModel, *, rays: int = DEFAULT_RAYS,
                 replicates: int = DEFAULT_REPLICATES, seed: int = 0, max_factor: int = DEFAULT_MAX_FACTOR,
                 eta_from_bundle: bool = False, sizes_of: Callable[[list], Sequence[int] | None] | None = None):
        self.instrument, self.model = instrument, model
        self.rays, self.replicates, self.seed, self.max_factor = int(rays), int(replicates), int(seed), int(max_factor)
        self.eta_from_bundle = bool(eta_from_bundle)
        self.sizes_of = sizes_of

    def settings(self) -> dict[str, Any]:
        return {"backend": self.name, "rays": self.rays, "replicates": self.replicates, "seed": self.seed,
                "max_factor": self.max_factor, "eta": "bundle" if self.eta_from_bundle else "quadrature",
                "precision": "float64"}

    def compute(self, cells: Sequence[tuple[float, float]],
                on_cell: Callable[[CellResult], None] | None = None) -> list[CellResult]:
        t0 = time.perf_counter()
        cells = [(float(t), float(b)) for t, b in cells]
        check_cells(self.instrument, self.model, cells)          # what every backend checks first
        sizes = self.sizes_of(cells) if self.sizes_of is not None else None
        bundles = RayBundles.build(self.instrument, cells, rays=self.rays, replicates=self.replicates,
                                   seed=self.seed, max_factor=self.max_factor, sizes=sizes)
        eta = bundles.eta_bundle if (self.eta_from_bundle and self.instrument.calibration.mode == "absolute") else None
        fm = ForwardModel(bundles, eta=eta)
        k = fm.k_a(self.model)
        se = fm.k_a_se(self.model)
        dt = (time.perf_counter() - t0) / max(len(cells), 1)
        out = []
        for i, (t, b) in enumerate(cells):
            c = CellResult(t, b, float(k[i]), float(se[i]), int(bundles.rays_per_cell[i]), dt,
                           {"ess_fraction": float(bundles.ess_fraction[i])}, se_dof=float(self.replicates - 1))
            out.append(c)
            if on_cell is not None:
                on_cell(c)
        return out


# ----------------------------------------------------------------------------------------------
# Several instruments, one surface
# ----------------------------------------------------------------------------------------------

class _StackedBundles:
    """What the fitter reads of the bundles of several forward models: the cells and cos^3 eps."""

    def __init__(self, forwards: Sequence[ForwardModel]):
        self.n_cells = int(sum(f.bundles.n_cells for f in forwards))
        self.cos3 = np.concatenate([f.bundles.cos3 for f in forwards])


class StackedForward:
    """Several instruments' forward models (:class:`ForwardModel`) as one: the measured cells of
    every instrument one after the other, so that one BRDF model is fitted through all of them by
    :func:`roadgonio.correction.fit.fit_through_instrument` (it reads only the methods below).
    ``rho`` arguments are the concatenated per-cell factors."""

    def __init__(self, forwards: Sequence[ForwardModel]):
        self.forwards = list(forwards)
        self.bundles = _StackedBundles(self.forwards)
        self.kappa = np.concatenate([f.kappa for f in self.forwards])
        self._splits = np.cumsum([f.bundles.n_cells for f in self.forwards])[:-1]

    def split(self, values: np.ndarray) -> list[np.ndarray]:
        """Per-instrument pieces of a concatenated per-cell array."""
        return np.split(np.asarray(values), self._splits)

    def _rho(self, rho):
        return [None] * len(self.forwards) if rho is None else self.split(rho)

    def columns(self, P: Mapping[str, float], variant: str,
                terms: Sequence[str] = LINEAR_TERMS) -> tuple[np.ndarray, np.ndarray]:
        parts = [f.columns(P, variant, terms) for f in self.forwards]
        return np.vstack([b for b, _ in parts]), np.vstack([n for _, n in parts])

    def nominal_columns(self, P: Mapping[str, float], variant: str) -> np.ndarray:
        return np.vstack([f.nominal_columns(P, variant) for f in self.forwards])

    def columns_and_shape_derivatives(self, P: Mapping[str, float], variant: str, names: Sequence[str],
                                      bundle: bool = True):
        parts = [f.columns_and_shape_derivatives(P, variant, names, bundle) for f in self.forwards]
        return tuple(None if parts[0][k] is None else np.vstack([p[k] for p in parts]) for k in range(4))

    def model_columns_total(self, model: RoadModel) -> tuple[np.ndarray, np.ndarray]:
        parts = [f.model_columns_total(model) for f in self.forwards]
        return np.concatenate([m for m, _ in parts]), np.concatenate([n for _, n in parts])

    def k_a(self, model: RoadModel, rho: np.ndarray | None = None) -> np.ndarray:
        return np.concatenate([f.k_a(model, r) for f, r in zip(self.forwards, self._rho(rho))])

    def r_measured(self, model: RoadModel, rho: np.ndarray | None = None) -> np.ndarray:
        return np.concatenate([f.r_measured(model, r) for f, r in zip(self.forwards, self._rho(rho))])


def make_backend(instrument: Instrument, model: RoadModel, **settings) -> BundleBackend:
    """The registry's factory (:mod:`roadgonio.engines.registry`): a :class:`BundleBackend` with
    ``rays``, ``replicates``, ``seed``, ``max_factor`` (an unknown setting is a one-line error). The
    bundle applies the instrument's calibration itself (:class:`ForwardModel`)."""
    allowed = {"rays", "replicates", "seed", "max_factor"}
    unknown = sorted(set(settings) - allowed)
    if unknown:
        raise InputError(f"unknown setting(s) {', '.join(unknown)} of the bundle backend; expected some of "
                         f"{', '.join(sorted(allowed))}", field=unknown[0])
    for key in ("rays", "replicates", "max_factor"):
        v = settings.get(key)
        least = 2 if key == "replicates" else 1
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least):
            raise InputError(f"expected a whole number >= {least}, got {v!r}", field=key)
    if settings.get("rays") is not None:
        from roadgonio.limits import check_size
        check_size(int(settings["rays"]), "rays", "rays")
    return BundleBackend(instrument, model, **settings)

