"""The model-discrepancy component of a surface correction's budget: what the instruments cannot
see (docs/correction.md, "What the instruments cannot see").

The fitted model (backbone times correction surface, :mod:`roadgonio.correction.flexible`) can only
follow the true BRDF as finely as its knots and its evidence-chosen smoothness allow. Write the rest
as a discrepancy of the logarithm over the incident direction,

    ln f_true(w_i, w_o) = ln f_model(w_i, w_o) + delta(x(w_i, w_o)),   x = (s_beta, s_t)

(x the knot coordinates of the correction surface g_C, :func:`roadgonio.surface.correction_surface.surface_coordinates`;
one unit = one knot spacing), delta a zero-mean Gaussian process with the squared-exponential
correlation ``rho(x, x') = exp(-|x - x'|^2 / (2 ell^2))`` and variance sigma^2. Linearised about the
model, an instrument's reading of cell c is multiplied by ``exp((K delta)_c)``, with

    (K delta)_c = sum_k w_k delta(x_k),   w_k = a_k f_model,k / sum_l a_l f_model,l

over the cell's fixed rays (their illuminance weights a_k, :class:`roadgonio.engines.bundle.RayBundles`),
while the table wants ``delta(x0_c)`` at the nominal direction. Structure the fit cannot follow
leaves the corrected ln r off by

    e_c = (K delta)_c - delta(x0_c),
    cov(e_c, e_d) = sigma^2 [ rho(x0_c, x0_d) - w_c . rho(X_c, x0_d) - w_d . rho(x0_c, X_d) + w_c^T rho(X_c, X_d) w_d ]

(:func:`discrepancy_correlation`, the bracket): zero for an instrument that sees only the nominal
direction (a delta function), sigma^2 for one whose blur is much wider than ell (its reading
averages delta away, the table keeps it), and in between as the blur compares with ell. It
correlates cells whose blurs overlap, and the same cell seen by two instruments (through delta(x0_c)).

The rays of a cell are binned before the double sum: each goes to the nearest point of a square
lattice of spacing ``h = BIN_FRACTION * ell`` in x; the double sum over the lattice images is then
two small matrix products (rho is separable). Moving a point by at most h/2 in each coordinate changes
the bracket by about ``(h / ell)^2 / 12`` (the variance of the rounding, h^2 / 12 per coordinate, in
units of ell^2).

**The pole.** In the knot coordinates the pole (eps = 0, where beta is undefined) is a line: every
s_beta at s_t = 0 is the same direction, and the rays of a cell at or near normal incidence, whose
beta runs over 0-180 deg, would look many correlation lengths apart. g_C closes the pole (one value
there, growing linearly from it), and so does delta: it is the sum of two independent processes of
variance sigma^2, ``delta = sqrt(1 - tau^2) delta_P(y) + tau delta_K(s_beta, s_t)`` with
``tau = min(s_t, 1)`` and the polar coordinates ``y = s_t (cos beta, sin beta)`` (in eps knot
spacings: the distance of two directions near the pole), so every point keeps the variance sigma^2,
the pole is one point, and beyond the first knot ring delta is the knot-coordinate process alone
(:func:`pole_components`). Their brackets add.

The discrepancy is assumed: independent of the observation direction (g_D and the backbone carry
that), stationary in x, zero-mean (the fit takes out what it can see), and not seen by the fit (the
data are not used to shrink it: where the instruments resolve, e is small anyway).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from roadgonio.arrays import NumpyOps
from roadgonio.surface.correction_surface import SplineGrid, incident_angles, surface_coordinates

#: Side of the lattice the rays are binned on, in units of ell.
BIN_FRACTION = 0.25
#: Cell pairs whose supports are further apart than this many ell are uncorrelated (rho < 4e-6).
CUTOFF_ELL = 5.0


def se_correlation(xp, d2, ell: float):
    """The squared-exponential correlation exp(-d^2 / (2 ell^2)) of delta at squared distance ``d2``."""
    return xp.exp(d2 * (-0.5 / (ell * ell)))


@dataclass(frozen=True)
class Blur:
    """One instrument's blur of delta on a lattice of spacing ``h`` (shared by every cell): per
    cell the nominal point ``x0[c]`` and the image ``images[c]`` of the ray weights (summing to 1),
    its element (a, b) the lattice point ``h (origins[c] + (a, b))``. For one component of a sum of
    processes (:func:`pole_components`) the rays carry the component's weight g: the image sums to
    sum w g and the nominal point has ``x0_weight[c]`` = g(x0_c) (None: 1)."""

    x0: np.ndarray
    origins: np.ndarray
    images: tuple
    h: float
    x0_weight: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.x0.shape[0])


def make_blur(x0: np.ndarray, x: np.ndarray, w: np.ndarray, cell_of: np.ndarray, ell: float,
              bin_fraction: float = BIN_FRACTION, g: np.ndarray | None = None,
              g0: np.ndarray | None = None) -> Blur:
    """A :class:`Blur` from flat rays: coordinates ``x`` (rays, 2), weights ``w`` (rays,), the cell of
    each ray ``cell_of`` and the cells' nominal points ``x0`` (cells, 2); each ray goes to its nearest
    lattice point (spacing ``bin_fraction * ell``). ``g``, ``g0``: a component's weight at the rays
    and at the nominal points (:func:`pole_components`); the images are normalised by w alone."""
    x0 = np.asarray(x0, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    cell_of = np.asarray(cell_of)
    h = bin_fraction * ell
    k = np.rint(x / h).astype(np.int64)
    order = np.argsort(cell_of, kind="stable")
    bounds = np.searchsorted(cell_of[order], np.arange(x0.shape[0] + 1))
    origins, images = [], []
    for c in range(x0.shape[0]):
        sel = order[bounds[c]:bounds[c + 1]]
        kc, wc = k[sel], w[sel]
        o = kc.min(axis=0)
        shape = tuple(kc.max(axis=0) - o + 1)
        img = np.zeros(shape)
        np.add.at(img, (kc[:, 0] - o[0], kc[:, 1] - o[1]), wc if g is None else wc * g[sel])
        origins.append(o)
        images.append(img / wc.sum())
    return Blur(x0=x0, origins=np.array(origins, dtype=np.int64).reshape(-1, 2), images=tuple(images), h=h,
                x0_weight=None if g0 is None else np.asarray(g0, dtype=np.float64))


def nominal_blur(blur: Blur, idx: Sequence[int]) -> Blur:
    """The blur of an estimate that sees nothing of delta: the fitted model's own value at the
    nominal directions of the cells ``idx`` of ``blur`` (no rays, an image of zeros), so its error
    is ``-delta(x0_c)`` and :func:`discrepancy_correlation` gives it the bracket 1 with itself and
    ``rho(x0_c, x0_d) - w_d . rho(x0_c, X_d)`` with an instrument's cell d."""
    idx = np.asarray(idx, dtype=np.int64)
    x0 = blur.x0[idx]
    return Blur(x0=x0, origins=np.rint(x0 / blur.h).astype(np.int64).reshape(-1, 2),
                images=tuple(np.zeros((1, 1)) for _ in idx), h=blur.h,
                x0_weight=None if blur.x0_weight is None else blur.x0_weight[idx])


def pole_components(sb, st, beta_deg) -> list[tuple[np.ndarray, np.ndarray]]:
    """The discrepancy as a sum of two independent processes of variance sigma^2 each, weighted so
    that every point keeps the variance sigma^2 (module docstring, "the pole"):

        delta(x) = sqrt(1 - tau^2) delta_P(y) + tau delta_K(s_beta, s_t),   tau = min(s_t, 1),
        y = s_t (cos beta, sin beta)

    delta_K over the knot coordinates (one unit = one knot spacing) and delta_P over the polar
    coordinates y about the pole, in units of the eps knot spacing (there the pole is one point,
    as it is one value of g_C, and a distance is the angle between the directions). Beyond the
    first knot ring (s_t >= 1) delta is delta_K alone; at the pole delta_P alone. Returns
    [(x, g), ...] per component: the coordinates (..., 2) and the weight g (...)."""
    sb = np.asarray(sb, dtype=np.float64)
    st = np.asarray(st, dtype=np.float64)
    b = np.radians(np.asarray(beta_deg, dtype=np.float64))
    sb, st, b = np.broadcast_arrays(sb, st, b)
    tau = np.minimum(st, 1.0)
    polar = np.stack([st * np.cos(b), st * np.sin(b)], axis=-1)
    knots = np.stack([sb, st], axis=-1)
    return [(polar, np.sqrt(np.maximum(1.0 - tau * tau, 0.0))), (knots, tau)]


def part_blurs(part, theta: np.ndarray, ell: float) -> list[Blur]:
    """The blurs of a :class:`roadgonio.correction.flexible.FlexPart` at the fitted surface ``theta``,
    one per component of :func:`pole_components`: its rays weighted by a_k f_model,k (module docstring)."""
    b = part.forward.bundles
    grid: SplineGrid = part.settings.c_grid
    sb, st = surface_coordinates(NumpyOps, grid, b.wi, b.wo)
    beta = np.asarray(incident_angles(NumpyOps, b.wi, b.wo)[0], dtype=np.float64)
    shape = b.a.shape
    comps = pole_components(np.broadcast_to(np.asarray(sb, dtype=np.float64), shape),
                            np.broadcast_to(np.asarray(st, dtype=np.float64), shape), np.broadcast_to(beta, shape))
    w = part.ray_weights(theta)
    n = part.n
    wo0 = tuple(np.full(n, b.wo0[k]) for k in range(3))
    wi0 = tuple(b.wi0[:, k] for k in range(3))
    s0b, s0t = surface_coordinates(NumpyOps, grid, wi0, wo0)
    comps0 = pole_components(s0b, s0t, incident_angles(NumpyOps, wi0, wo0)[0])
    return [make_blur(x0, x.reshape(-1, 2), w.ravel(), part.cell_of, ell, g=g.ravel(), g0=g0)
            for (x, g), (x0, g0) in zip(comps, comps0)]


def discrepancy_correlation(blurs: list[Blur], ell: float, cutoff_ell: float = CUTOFF_ELL) -> np.ndarray:
    """The bracket of the module docstring, cov(e_c, e_d) / sigma^2, over the concatenated cells of
    ``blurs`` (several instruments: their cells one after the other; one lattice spacing). The
    squared-exponential correlation is separable, so the double sum is ``sum(I_c * C_d)`` with C_d
    the image of cell d convolved with rho along each lattice direction (out to the cut-off). Pairs of
    cells whose supports (nominal point and image) are further apart than ``cutoff_ell * ell`` get 0."""
    h = blurs[0].h
    if any(abs(b.h - h) > 1e-15 * h for b in blurs):
        raise ValueError("the blurs must share one lattice spacing")
    x0 = np.concatenate([b.x0 for b in blurs], axis=0)
    g0 = np.concatenate([np.ones(b.n) if b.x0_weight is None else b.x0_weight for b in blurs])
    org = np.concatenate([b.origins for b in blurs], axis=0)
    imgs = [im for b in blurs for im in b.images]
    ext = np.array([im.shape for im in imgs], dtype=np.int64)
    n = x0.shape[0]
    lo = np.minimum(org * h, x0) - cutoff_ell * ell
    hi = np.maximum((org + ext - 1) * h, x0)
    close = np.all((lo[:, None, :] <= hi[None, :, :]) & (lo[None, :, :] <= hi[:, None, :]), axis=2)

    K = int(math.ceil(cutoff_ell * ell / h))
    kern = se_correlation(np, (h * np.arange(-K, K + 1, dtype=np.float64)) ** 2, ell)

    def smear(img):                       # the image times rho along both lattice directions, support + K
        a = np.zeros((img.shape[0] + 2 * K, img.shape[1]))
        for d in range(2 * K + 1):        # a[u] = sum_d kern[d] img[u - d]
            a[d:d + img.shape[0]] += kern[d] * img
        out = np.zeros((a.shape[0], img.shape[1] + 2 * K))
        for d in range(2 * K + 1):
            out[:, d:d + img.shape[1]] += kern[d] * a
        return out

    active = (g0 != 0.0) | np.array([bool(np.any(im != 0.0)) for im in imgs], dtype=bool)
    close &= active[:, None] & active[None, :]
    # P[i, j] = g0_i rho(x0_i, X_j) . w_j, the nominal point of i against the image of j, for every
    # close pair in both orders: per image j, all its partners' points at once (rho is separable)
    P = np.zeros((n, n))
    for j in range(n):
        part = np.nonzero(close[:, j])[0]
        if part.size == 0 or not np.any(imgs[j]):
            continue
        lines = [se_correlation(np, (x0[part, k, None] - h * (org[j, k] + np.arange(ext[j, k]))[None, :]) ** 2, ell)
                 for k in (0, 1)]
        P[part, j] = g0[part] * np.sum((lines[0] @ imgs[j]) * lines[1], axis=1)
    R = np.zeros((n, n))
    for j in range(n):
        partners = np.nonzero(close[j, :j + 1])[0]
        if partners.size == 0:
            continue
        Ij = imgs[j]
        Cj = smear(Ij)                    # Cj[a, b] = sum rho(lattice (oj - K + (a, b)), X_j) w_j
        oj = org[j] - K
        r00 = g0[partners] * g0[j] * np.exp(-0.5 * np.sum((x0[partners] - x0[j]) ** 2, axis=1) / (ell * ell))
        for i, r in zip(partners.tolist(), (r00 - P[partners, j] - P[j, partners]).tolist()):
            Ii, oi = imgs[i], org[i]
            lo_ = np.maximum(oi, oj)
            hi_ = np.minimum(oi + ext[i], oj + np.array(Cj.shape))
            rij = 0.0
            if np.all(hi_ > lo_):
                rij = float(np.sum(Ii[lo_[0] - oi[0]:hi_[0] - oi[0], lo_[1] - oi[1]:hi_[1] - oi[1]]
                                   * Cj[lo_[0] - oj[0]:hi_[0] - oj[0], lo_[1] - oj[1]:hi_[1] - oj[1]]))
            R[i, j] = R[j, i] = r + rij
    return R


def beyond_nyquist_variance(lam_beta: float, lam_eps: float, n_phi: int = 4096) -> float:
    """The variance that the roughness prior of g_C puts at wavelengths its knots cannot represent.

    The penalty ``lam_beta sum (Delta_beta^2 a)^2 + lam_eps sum (Delta_eps^2 a)^2`` over the node
    values (unit spacing) is the precision of a Gaussian field whose spectral density, continued off
    the lattice, is ``1 / (4 pi^2 (lam_beta k_b^4 + lam_eps k_t^4))`` (the second difference's
    symbol, ``(2 - 2 cos k)^2``, is k^4 for small k). The knots represent wavenumbers inside the
    Nyquist square |k_b|, |k_t| <= pi; the rest has the variance

        sigma^2 = (1 / 4 pi^2) int_0^{2 pi} dphi / (2 r_0(phi)^2 (lam_beta cos^4 phi + lam_eps sin^4 phi)),

    r_0 = pi / max(|cos phi|, |sin phi|) the square's edge (the radial integral is done exactly;
    the angular one by the midpoint rule on ``n_phi`` points)."""
    phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    c, s_ = np.cos(phi), np.sin(phi)
    r0 = math.pi / np.maximum(np.abs(c), np.abs(s_))
    q = lam_beta * c ** 4 + lam_eps * s_ ** 4
    return float(np.sum(1.0 / (2.0 * r0 ** 2 * q)) * (2.0 * math.pi / n_phi) / (4.0 * math.pi ** 2))


def amplitude_from_penalty(lam: dict, region: np.ndarray) -> np.ndarray:
    """Per cell, sigma^2 of delta: :func:`beyond_nyquist_variance` of the evidence-chosen smoothing
    parameters of the cell's penalty region (``region``: its name per cell,
    :func:`roadgonio.correction.flexible.penalty_region`; the blocks ``beta_<region>`` and
    ``eps_<region>`` of :func:`roadgonio.correction.flexible.penalty_blocks`). A region without its
    own blocks (no difference centred in it) takes the mean variance of the regions that have them."""
    region = np.asarray(region)
    names = {k.split("_", 1)[1] for k in lam if k.startswith("beta_")} & {k.split("_", 1)[1] for k in lam
                                                                         if k.startswith("eps_")}
    v = {n: beyond_nyquist_variance(lam[f"beta_{n}"], lam[f"eps_{n}"]) for n in sorted(names)}
    if not v:
        raise ValueError("no region has smoothing parameters along both beta and eps")
    fallback = float(np.mean(list(v.values())))
    return np.array([v.get(str(n), fallback) for n in region.ravel()], dtype=np.float64).reshape(region.shape)
