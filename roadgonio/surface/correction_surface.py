"""The correction surface: a smooth factor over the incident direction that lets the BRDF model
follow a surface eq. 4 cannot, and its derivative in the observation elevation (docs/correction.md,
"Outside eq. 4: `--forward surface` and `--joint`").

    f(w_i, w_o) = f_0(w_i, w_o) exp( g_C(beta, eps_i) + l(alpha) g_D(beta, eps_i) )

f_0 is the backbone (paper eq. 4, :mod:`roadgonio.surface.model`); ``beta`` is the angle between
the vertical planes of illumination and observation of the ray pair, ``eps_i`` the polar angle of
w_i (docs/conventions.md section 1; isotropic, beta folded to [0, 180 deg]), ``alpha`` the
elevation of w_o and ``l(alpha) = ln(sin alpha / sin 1 deg)``. At alpha = 1 deg (the r-table's
observation) the factor is ``exp(g_C)``: g_C is the correction of the table's shape; g_D is how much
faster (per unit ln alpha) the BRDF changes off alpha = 1 deg than the backbone says, which only a
second aperture setting can measure (docs/design.md, "Which second aperture?"). Without g_D the behaviour off 1 deg is the
backbone's.

Each of g_C, g_D is a tensor-product cubic B-spline on unit-spaced knots in two smooth coordinates
(:class:`SplineGrid`):

* ``s_beta = S_beta ln(1 + beta / b0) / ln(1 + 180 deg / b0)``: knots dense at the mirror plane
  (beta = 0), where road BRDFs have their narrow peak, sparse behind the source;
* ``s_t = S_t raw(eps) / raw(eps_max)``, ``raw(eps) = eps / step - gain ln cos eps``: a knot every
  ``step`` degrees far from grazing, denser towards grazing incidence (the ln cos term), held at
  eps_max beyond it.

Boundary conditions, by reflecting the coefficients: even in beta at 0 and 180 deg (the surface is
mirror symmetric about the plane of observation, so g is smooth across it); even at eps_max; at the
pole (eps = 0, where beta is undefined) the row of coefficients is one value ``c`` and the row beyond
it is ``2c - a_1``, so g takes one value at the pole whatever beta and grows from it linearly; the
roughness penalty includes the second difference through the pole (from beta to 180 deg - beta), so
the slopes at opposite azimuths agree, as those of a function smooth over the sphere do (a slope
the same way on both sides is a cone). The correction penalises that difference of the whole ln f,
backbone and g together (:func:`roadgonio.correction.flexible.pole_offsets`), since eq. 4's backbone
has a cone there.

The free coefficients theta (``c``, then the rows 1..S_t of S_beta + 1 nodes each) enter g
linearly, ``g = sum_p theta_p phi_p``: the simulated measurement through fixed ray bundles is
``sum_k a_k f_0,k exp(g_k)``, whose Jacobian in theta is again a sum over the same rays
(:mod:`roadgonio.correction.flexible`).

The spline is written once, over an array namespace ``xp`` (:func:`surface_coordinates`,
:func:`bspline_weights`, :func:`lookup`, :func:`spline_value`): the names of
:class:`roadgonio.arrays.NumpyOps`, whose ``floor`` and ``take(table, index)`` (a gather) the
B-spline lookup uses. The factor ``exp(g_C + l(alpha) g_D)`` itself (:func:`alpha_coordinate` for
l, the exponent clipped at 50) is assembled in one place, over the forward model's cached lookups
of its rays: ``FlexPart.g_rays`` and ``FlexPart.ray_weights`` in :mod:`roadgonio.correction.flexible`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from roadgonio.arrays import NumpyOps
from roadgonio.geometry import ALPHA_STANDARD_DEG, pair_angles
from roadgonio.surface.truths import EvaluatedBRDF

#: sin of the r-tables' observation elevation (alpha = 1 deg).
SIN_ALPHA0 = math.sin(math.radians(ALPHA_STANDARD_DEG))


@dataclass(frozen=True)
class SplineGrid:
    """The knots of one surface (module docstring). Plain floats, hashable (cached matrices)."""

    s_beta: int = 32
    beta_scale_deg: float = 8.0
    s_t: int = 40
    eps_step_deg: float = 3.0
    sec_gain: float = 3.0
    eps_max_deg: float = 89.0

    @property
    def pad_shape(self) -> tuple[int, int]:
        """Shape of the padded coefficient grid: indices -1 .. S + 2 in each direction."""
        return (self.s_beta + 4, self.s_t + 4)

    @property
    def n_params(self) -> int:
        return 1 + self.s_t * (self.s_beta + 1)

    def _raw_t(self, xp, eps_deg):
        e = xp.minimum(eps_deg, self.eps_max_deg)
        return e * (1.0 / self.eps_step_deg) - self.sec_gain * xp.log(xp.cos(e * (math.pi / 180.0)))

    def s_beta_of(self, xp, beta_deg):
        """The beta coordinate of the knots (module docstring), beta in degrees."""
        return (self.s_beta / math.log(1.0 + 180.0 / self.beta_scale_deg)) * xp.log(
            1.0 + beta_deg * (1.0 / self.beta_scale_deg))

    def s_t_of(self, xp, eps_deg):
        """The eps coordinate of the knots (module docstring), eps in degrees."""
        return (self.s_t / float(self._raw_t(NumpyOps, np.float64(self.eps_max_deg)))) * self._raw_t(xp, eps_deg)

    # -- the linear map theta -> padded grid, and the penalties -----------------------------
    def padded_matrix(self) -> np.ndarray:
        """(padded nodes, n_params): the padded coefficient grid is ``T @ theta`` (flattened row-major)."""
        return _padded_matrix(self)

    def penalties(self) -> tuple[np.ndarray, np.ndarray]:
        """(P_beta, P_t): theta^T P theta = the sum of squared second differences of the node values
        along beta and along eps (reflected neighbours included at the boundaries). Only the
        constant is in the null space of P_beta + P_t."""
        (Db, _), (Dt, _) = _differences(self)
        return Db.T @ Db, Dt.T @ Dt

    def differences(self):
        """((D_beta, centre_beta), (D_t, centre_t)): the second-difference operators over theta, one
        row per difference, and the (beta index, eps index) of each difference's centre node."""
        return _differences(self)

    def through_pole_rows(self) -> np.ndarray:
        """Which rows of D_t (:meth:`differences`) are the differences through the pole,
        a_1(beta) - 2 c + a_1(180 deg - beta): the last S_beta + 1, as :func:`_differences` appends them."""
        (_, _), (Dt, _) = _differences(self)
        rows = np.zeros(Dt.shape[0], dtype=bool)
        rows[-(self.s_beta + 1):] = True
        return rows

    def coefficient_index(self, i: int, j: int) -> int:
        """The index in theta of the node at beta index ``i`` and eps index ``j`` >= 1 (0 is the
        pole's one value ``c``)."""
        return _theta_index(self, i, j)

    def node_coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        """(beta_deg, eps_deg) of the node lines (inverse of the coordinate maps)."""
        sb = np.arange(self.s_beta + 1, dtype=np.float64)
        beta = self.beta_scale_deg * np.expm1(sb * math.log(1.0 + 180.0 / self.beta_scale_deg) / self.s_beta)
        e = np.linspace(0.0, self.eps_max_deg, 20001)
        st = self.s_t_of(NumpyOps, e)
        eps = np.interp(np.arange(self.s_t + 1, dtype=np.float64), st, e)
        return beta, eps


def incident_angles(xp, wi, wo):
    """(beta, eps) in degrees of ray pairs: ``wi``, ``wo`` component triples of unit vectors towards
    the source and the detector. beta as in :func:`roadgonio.surface.model.road_brdf` (exact near 0
    and 180 deg; 0 where the azimuth is undefined, at the pole, where g does not depend on it):
    :func:`roadgonio.geometry.pair_angles`, eps its theta_i."""
    eps, _, beta = pair_angles(xp, wi, wo, pole=0.0)
    return beta * (180.0 / math.pi), eps * (180.0 / math.pi)


def surface_coordinates(xp, grid: SplineGrid, wi, wo):
    """(s_beta, s_t) of ray pairs (:func:`incident_angles` on the knot grid)."""
    beta_deg, eps_deg = incident_angles(xp, wi, wo)
    return grid.s_beta_of(xp, beta_deg), grid.s_t_of(xp, eps_deg)


def alpha_coordinate(xp, wo):
    """l(alpha) = ln(sin alpha / sin 1 deg) of the detector directions ``wo`` (component triple)."""
    return xp.log(xp.maximum(wo[2], 1e-12) * (1.0 / SIN_ALPHA0))


def bspline_weights(xp, s, upper: int):
    """(i0, (w0, w1, w2, w3)): the uniform cubic B-spline basis at ``s`` clamped to [0, upper]:
    the value is ``sum_k w_k a[i0 - 1 + k]`` over the padded coefficients (index shift +1)."""
    s = xp.minimum(xp.maximum(s, 0.0), upper * (1.0 - 1e-12))
    i0 = xp.floor(s)
    u = s - i0
    u2 = u * u
    u3 = u2 * u
    v = 1.0 - u
    return i0, (v * v * v * (1.0 / 6.0), (3.0 * u3 - 6.0 * u2 + 4.0) * (1.0 / 6.0),
                (-3.0 * u3 + 3.0 * u2 + 3.0 * u + 1.0) * (1.0 / 6.0), u3 * (1.0 / 6.0))


def lookup(xp, grid: SplineGrid, wi, wo):
    """The 16 (flat index into the padded grid, weight) pairs of the spline at ray pairs: its value
    is ``sum_k weight_k padded[index_k]`` (indices as floats holding integers; row-major over
    :attr:`SplineGrid.pad_shape`). The forward model accumulates the same pairs into its Jacobian."""
    sb, st = surface_coordinates(xp, grid, wi, wo)
    ib, wb = bspline_weights(xp, sb, grid.s_beta)
    it, wt = bspline_weights(xp, st, grid.s_t)
    n_t = float(grid.pad_shape[1])
    return [((ib + a) * n_t + (it + b), wb[a] * wt[b]) for a in range(4) for b in range(4)]


def spline_value(xp, grid: SplineGrid, padded, wi, wo):
    """g at ray pairs for the padded coefficient grid ``padded`` (:meth:`SplineGrid.padded_matrix`
    times theta)."""
    out = None
    for idx, w in lookup(xp, grid, wi, wo):
        term = w * xp.take(padded, idx)
        out = term if out is None else out + term
    return out


def _reflect(i: int, hi: int) -> int:
    if i < 0:
        return -i
    if i > hi:
        return 2 * hi - i
    return i


def _theta_index(grid: SplineGrid, i: int, j: int) -> int:
    return 1 + (j - 1) * (grid.s_beta + 1) + i


@lru_cache(maxsize=8)
def _padded_matrix(grid: SplineGrid) -> np.ndarray:
    nb, nt = grid.pad_shape
    T = np.zeros((nb * nt, grid.n_params))
    for pi in range(nb):
        i = _reflect(pi - 1, grid.s_beta)
        for pj in range(nt):
            j = pj - 1
            row = pi * nt + pj
            if j == 0:
                T[row, 0] = 1.0
            elif j == -1:                     # 2 c - a_{i,1}: odd about the pole value
                T[row, 0] = 2.0
                T[row, _theta_index(grid, i, 1)] = -1.0
            else:
                T[row, _theta_index(grid, i, _reflect(j, grid.s_t))] = 1.0
    T.setflags(write=False)
    return T


@lru_cache(maxsize=8)
def _differences(grid: SplineGrid):
    nb, nt = grid.pad_shape
    T = _padded_matrix(grid)
    rows_b, rows_t, cb, ct = [], [], [], []
    for i in range(grid.s_beta + 1):
        for j in range(grid.s_t + 1):
            c = (i + 1) * nt + (j + 1)
            if j > 0:                          # the pole row is one value: no beta difference there
                rows_b.append((c - nt, c, c + nt))
                cb.append((i, j))
            rows_t.append((c - 1, c, c + 1))
            ct.append((i, j))

    def op(rows):
        D = np.zeros((len(rows), nb * nt))
        for k, (a, b, c) in enumerate(rows):
            D[k, a] += 1.0
            D[k, b] -= 2.0
            D[k, c] += 1.0
        return D @ T

    Dt = op(rows_t)
    # through the pole: the eps difference at the pole along the great circle from beta to
    # 180 deg - beta (the node there interpolated linearly in beta): a_1(beta) - 2 c + a_1(180 - beta),
    # so the slopes at opposite azimuths agree, as those of a function smooth over the sphere do
    beta, _ = grid.node_coordinates()
    pole = []
    for i in range(grid.s_beta + 1):
        row = np.zeros(grid.n_params)
        row[_theta_index(grid, i, 1)] += 1.0
        row[0] -= 2.0
        other = 180.0 - beta[i]
        k = int(np.clip(np.searchsorted(beta, other) - 1, 0, grid.s_beta - 1))
        w = (other - beta[k]) / (beta[k + 1] - beta[k])
        row[_theta_index(grid, k, 1)] += 1.0 - w
        row[_theta_index(grid, k + 1, 1)] += w
        pole.append(row)
    Dt = np.vstack([Dt, np.array(pole)])
    ct = ct + [(i, 0) for i in range(grid.s_beta + 1)]
    Db = op(rows_b)
    Db.setflags(write=False)
    Dt.setflags(write=False)
    return (Db, np.array(cb)), (Dt, np.array(ct))


class CorrectedSurface(EvaluatedBRDF):
    """The fitted surface as a BRDF: the backbone times ``exp(g_C + l(alpha) g_D)`` (module
    docstring; the exponent clipped at 50, as the forward model clips it), for the backends that
    render any surface over an array namespace (the Mitsuba ``roadbsdf``'s ``set_surface``, the
    float64 reference). It is what the correction hands a backend when k_A depends on the surface
    beyond the footprint (a housing's stray light: docs/correction.md, "A housed instrument").

    ``grids`` are the surface's spline grids (g_C's, then g_D's if any) and ``thetas`` their free
    coefficients; the interface is that of :mod:`roadgonio.surface.truths` (``evaluate``, and
    ``brdf``, ``q``, ``r`` from it by :class:`~roadgonio.surface.truths.EvaluatedBRDF`;
    ``to_json_dict``, ``numpy_only``, ``sampling_lobe_exponent``, ``mirror_kink``)."""

    kind = "corrected"
    numpy_only = False
    is_lambertian = False

    def __init__(self, backbone, grids, thetas, name: str | None = None,
                 alpha_range: tuple[float, float] | None = None, unobserved_factor: float = 1.0):
        if len(grids) != len(thetas) or not 1 <= len(grids) <= 2:
            raise ValueError("a corrected surface has g_C and optionally g_D: one theta per grid")
        self.backbone = backbone
        self.grids = tuple(grids)
        self.thetas = tuple(np.asarray(t, dtype=np.float64).copy() for t in thetas)
        self.padded = tuple(g.padded_matrix() @ t for g, t in zip(self.grids, self.thetas))
        self.name = name or f"{backbone.name} x exp(g)"
        #: l(alpha) is held within this range (the fitted rays' own): beyond the observation
        #: elevations the instruments saw, the behaviour off alpha = 1 deg is the backbone's
        #: (issue 19) -- a stray-light path reads the road at any elevation, where l g_D would be an
        #: extrapolation by a factor up to ln(1 / sin 1 deg) = 4
        self.alpha_range = None if alpha_range is None else (float(alpha_range[0]), float(alpha_range[1]))
        #: the surface beyond that range times this factor (1: as fitted): how the correction measures
        #: k_A's sensitivity to the road no r-table measures (docs/correction.md, "The road beyond the
        #: observation elevations"); a probe, never a fitted value
        self.unobserved_factor = float(unobserved_factor)
        if not (math.isfinite(self.unobserved_factor) and self.unobserved_factor > 0.0):
            raise ValueError(f"expected a positive factor on the unobserved surface, got {unobserved_factor}")
        if self.unobserved_factor != 1.0 and self.alpha_range is None:
            raise ValueError("a factor on the surface beyond the observation elevations needs their range")
        self.variant = backbone.variant
        self.mirror_kink = backbone.mirror_kink

    @property
    def sampling_lobe_exponent(self) -> float:
        """The backbone's Phong exponent when it has a Phong lobe (the sampling only)."""
        p = self.backbone.params
        return float(p.n_phong) if p.k_phong > 0.0 else 0.0

    def exponent(self, xp, wi, wo):
        """g_C + l(alpha) g_D at ray pairs (component triples; wi towards the source)."""
        g = spline_value(xp, self.grids[0], self.padded[0], wi, wo)
        if len(self.grids) > 1:
            ell = alpha_coordinate(xp, wo)
            if self.alpha_range is not None:
                ell = xp.minimum(xp.maximum(ell, self.alpha_range[0]), self.alpha_range[1])
            g = g + ell * spline_value(xp, self.grids[1], self.padded[1], wi, wo)
        return g

    def evaluate(self, xp, wi, wo):
        f = self.backbone.evaluate(xp, wi, wo) * xp.exp(xp.minimum(self.exponent(xp, wi, wo), 50.0))
        if self.unobserved_factor != 1.0:
            ell = alpha_coordinate(xp, wo)
            beyond = (ell < self.alpha_range[0]) | (ell > self.alpha_range[1])
            f = f * xp.where(beyond, self.unobserved_factor, 1.0)
        return f

    def to_json_dict(self) -> dict:
        from dataclasses import asdict
        return {"surface": self.kind, "name": self.name, "backbone": self.backbone.to_json_dict(),
                "grids": [asdict(g) for g in self.grids], "thetas": [t.tolist() for t in self.thetas],
                "alpha_range": None if self.alpha_range is None else list(self.alpha_range),
                # only when probed: the fitted surface's fingerprint (its journals) stays what it was
                **({"unobserved_factor": self.unobserved_factor} if self.unobserved_factor != 1.0 else {})}
