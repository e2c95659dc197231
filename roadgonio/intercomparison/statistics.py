"""The statistics of a key comparison, each formula once, float64, vectorised over cells.

Every function takes the participants' results on the LAST axis: ``x`` of shape (..., P) (P >= 2
participants, any leading shape: realisations x cells) and their stated covariance ``V`` of shape
(..., P, P) (:func:`covariance`; independent results: ``V = diag(u^2)``). Correlations between
participants (a reference tile or an angle standard they share) enter through ``V``.

The methods, their published sources and the published examples they are checked against are in
docs/intercomparison.md ("The statistics").

Every consensus is a generalised least-squares (GLS) mean with the weight matrix
``W = (V + tau^2 I)^-1``::

    x_ref = 1^T W x / 1^T W 1,    u^2(x_ref) = 1 / 1^T W 1,    weights a = W 1 / 1^T W 1

* ``tau^2 = 0``: the weighted mean of the comparison (Cox's procedure A; with correlated results
  the generalised weighted mean). For ``V = diag(u^2)`` it is sum(x/u^2) / sum(1/u^2) with
  u^2 = 1/sum(1/u^2).
* DerSimonian-Laird: the moment estimator ``tau^2 = max(0, (Q - (P - 1)) / c)``
  with Cochran's ``Q = (x - x_w 1)^T V^-1 (x - x_w 1)`` (x_w the weighted mean) and
  ``c = tr(V^-1) - 1^T V^-2 1 / 1^T V^-1 1``, which is ``E[Q] = (P - 1) + c tau^2`` for results
  ``x = mu 1 + b + e``, ``b ~ (0, tau^2 I)``, ``e ~ (0, V)``; for ``V = diag(u^2)``,
  ``c = sum w - sum w^2 / sum w`` (w = 1/u^2), their formula.
* Mandel-Paule: the ``tau^2 >= 0`` at which the generalised
  ``Q(tau^2) = (x - x_ref 1)^T W (x - x_ref 1)`` equals its expectation ``P - 1`` (0 when
  ``Q(0) <= P - 1``). ``Q`` decreases monotonically in ``tau^2`` (dQ/dtau^2 = -r^T W^2 r), so the
  root is unique; it is found by bracketing and bisection to full float64 precision.

Birge ratio: ``R_B = sqrt(Q / (P - 1))`` with Q of the
weighted mean; Cox's chi-squared consistency check passes where
``Pr{chi^2(P - 1) > Q} >= 0.05``.

Degree of equivalence of participant i with respect to a reference value ``x_ref = a^T x`` (CIPM
MRA, technical supplement T.2): ``d_i = x_i - x_ref`` with::

    u^2(d_i) = (e_i - a)^T V (e_i - a) + tau^2 a^T a + u_ext^2

the variance of ``x_i - a^T x`` under the stated covariance (the participant's correlation with a
reference value it contributes to is the ``-2 (V a)_i`` in it), plus the consensus's own
between-laboratory term ``tau^2 a^T a``, plus ``u_ext^2`` for a reference value that does not come
from the participants (``a = 0``; the truth of a simulation has ``u_ext = 0``). For the weighted
mean ``V a = u^2(x_ref) 1``, so ``u^2(d_i) = u_i^2 - u^2(x_ref)`` (docs/intercomparison.md). ``U(d_i) = k
u(d_i)`` and the E_n number ``E_n = d_i / U(d_i)`` (ISO 13528:2015 E_n with k = 2); the participant
is compatible where ``|E_n| <= 1``.

The eigen-decomposition ``V = E diag(lambda) E^T`` of every cell is computed once
(:class:`Spectral`); with it every quantity above is a sum over P of elementwise terms.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roadgonio.errors import InputError

#: Coverage factor of U(d_i) and E_n (ISO 13528: E_n with expanded uncertainties, k = 2).
COVERAGE_FACTOR = 2.0
#: Significance level of the chi-squared consistency check (Cox's procedure A).
CHI2_ALPHA = 0.05
#: Bisection steps of the Mandel-Paule root (each halves the bracket: 2^-80 of it is below float64).
MP_BISECTIONS = 80
#: Doublings of the Mandel-Paule upper bracket at most (from the largest squared spread of x).
MP_DOUBLINGS = 200
#: Names of the consensus methods (the order of the outputs).
METHODS = ("weighted_mean", "mandel_paule", "dersimonian_laird")


# ----------------------------------------------------------------------------------------------
# Covariance of the participants
# ----------------------------------------------------------------------------------------------

def covariance(u: np.ndarray, shared: np.ndarray | None = None) -> np.ndarray:
    """The stated covariance (..., P, P) of the participants from their stated standard
    uncertainties ``u`` (..., P) and the components they share, ``shared`` (S, ..., P): component
    s contributes ``g_s g_s^T`` (fully correlated between the participants with g != 0; g_si = 0
    where participant i does not take part). Each u_i must already include its shared components
    (``u_i^2 >= sum_s g_si^2``): the diagonal is u^2, the off-diagonal sum_s g_si g_sj."""
    u = np.asarray(u, dtype=np.float64)
    if u.shape[-1] < 2:
        raise InputError(f"a comparison needs at least 2 participants, got {u.shape[-1]}", field="participants")
    if not np.all(np.isfinite(u)) or np.any(u <= 0):
        raise InputError("every stated standard uncertainty must be positive and finite", field="u")
    V = u[..., :, None] * u[..., None, :] * np.eye(u.shape[-1])
    if shared is None:
        return V
    g = np.asarray(shared, dtype=np.float64)
    if g.shape[1:] != u.shape:
        raise ValueError(f"shared components of shape {g.shape}, expected (S,) + {u.shape}")
    own = u * u - np.sum(g * g, axis=0)
    if np.any(own < -1e-12 * u * u):
        raise InputError("a participant's stated uncertainty is smaller than the components it shares with "
                         "others; expected u_i^2 >= sum of its shared components squared", field="u")
    V = np.einsum("s...i,s...j->...ij", g, g)
    idx = np.arange(u.shape[-1])
    V[..., idx, idx] = u * u
    return V


def correlation(V: np.ndarray) -> np.ndarray:
    """The correlation matrix (..., P, P) of a covariance (..., P, P)."""
    s = np.sqrt(np.diagonal(V, axis1=-2, axis2=-1))
    return V / (s[..., :, None] * s[..., None, :])


# ----------------------------------------------------------------------------------------------
# GLS machinery
# ----------------------------------------------------------------------------------------------

class Spectral:
    """The eigen-decomposition of the stated covariance of every cell and the participants'
    results in its basis: ``lam`` (..., P), ``E`` (..., P, P) (columns are eigenvectors),
    ``o = E^T 1`` and ``y = E^T x``. ``V`` must be positive definite."""

    def __init__(self, x: np.ndarray, V: np.ndarray):
        x = np.asarray(x, dtype=np.float64)
        V = np.asarray(V, dtype=np.float64)
        if x.shape[-1] < 2:
            raise InputError(f"a comparison needs at least 2 participants, got {x.shape[-1]}", field="participants")
        if V.shape != x.shape + (x.shape[-1],):
            raise ValueError(f"V of shape {V.shape}, expected {x.shape + (x.shape[-1],)}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(V))):
            raise InputError("the participants' results and their covariance must be finite", field="x")
        lam, E = np.linalg.eigh(V)
        scale = np.max(np.abs(lam), axis=-1, keepdims=True)
        if np.any(lam <= 1e-13 * scale):
            raise InputError("the stated covariance of the participants is not positive definite (a participant "
                             "without uncertainty, or two fully correlated ones)", field="u")
        self.x = x
        self.V = V
        self.lam = lam
        self.E = E
        self.o = E.sum(axis=-2)                                  # E^T 1
        self.y = np.einsum("...ij,...i->...j", E, x)             # E^T x
        self.n = x.shape[-1]

    def _h(self, tau2) -> np.ndarray:
        return 1.0 / (self.lam + np.asarray(tau2, dtype=np.float64)[..., None])

    def gls(self, tau2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x_ref, u(x_ref), Q) of the GLS mean with W = (V + tau^2 I)^-1."""
        h = self._h(tau2)
        s11 = np.sum(self.o * self.o * h, axis=-1)
        s1x = np.sum(self.o * self.y * h, axis=-1)
        sxx = np.sum(self.y * self.y * h, axis=-1)
        mean = s1x / s11
        q = np.maximum(sxx - s1x * mean, 0.0)
        return mean, 1.0 / np.sqrt(s11), q

    def weights(self, tau2) -> np.ndarray:
        """a = W 1 / 1^T W 1, shape (..., P) (sum a = 1)."""
        h = self._h(tau2)
        ho = h * self.o
        return np.einsum("...ij,...j->...i", self.E, ho) / np.sum(self.o * ho, axis=-1)[..., None]

    def q_trace(self) -> np.ndarray:
        """c = tr(V^-1) - 1^T V^-2 1 / 1^T V^-1 1 (the DerSimonian-Laird denominator)."""
        h = 1.0 / self.lam
        return np.sum(h, axis=-1) - np.sum(self.o ** 2 * h * h, axis=-1) / np.sum(self.o ** 2 * h, axis=-1)


@dataclass(frozen=True)
class Consensus:
    """A reference value of the comparison per cell: value, standard uncertainty, the
    between-laboratory variance tau^2 it assumed (0 for the weighted mean) and the participants'
    weights a (..., P)."""

    method: str
    value: np.ndarray
    u: np.ndarray
    tau2: np.ndarray
    weights: np.ndarray


def weighted_mean(sp: Spectral) -> Consensus:
    """The (generalised) weighted mean (GLS with correlations; docs/intercomparison.md)."""
    z = np.zeros(sp.x.shape[:-1])
    v, u, _ = sp.gls(z)
    return Consensus("weighted_mean", v, u, z, sp.weights(z))


def chi2_observed(sp: Spectral) -> np.ndarray:
    """Cochran's Q = chi^2_obs = (x - x_w 1)^T V^-1 (x - x_w 1) of the weighted mean."""
    return sp.gls(np.zeros(sp.x.shape[:-1]))[2]


def birge_ratio(sp: Spectral) -> np.ndarray:
    """R_B = sqrt(chi^2_obs / (P - 1)); about 1 for results consistent with their u."""
    return np.sqrt(chi2_observed(sp) / (sp.n - 1))


def consistent(sp: Spectral, alpha: float = CHI2_ALPHA) -> np.ndarray:
    """Cox's procedure A: True where Pr{chi^2(P - 1) > chi^2_obs} >= alpha."""
    from scipy.stats import chi2
    return chi2.sf(chi2_observed(sp), sp.n - 1) >= alpha


def tau2_dersimonian_laird(sp: Spectral) -> np.ndarray:
    """The DerSimonian-Laird between-laboratory variance (module docstring), >= 0."""
    q = chi2_observed(sp)
    return np.maximum((q - (sp.n - 1)) / sp.q_trace(), 0.0)


def tau2_mandel_paule(sp: Spectral) -> np.ndarray:
    """The Mandel-Paule between-laboratory variance: Q(tau^2) = P - 1, or 0 when Q(0) <= P - 1."""
    target = sp.n - 1
    shape = sp.x.shape[:-1]
    lo = np.zeros(shape)
    q0 = sp.gls(lo)[2]
    need = q0 > target
    if not np.any(need):
        return lo
    spread = np.max(sp.x, axis=-1) - np.min(sp.x, axis=-1)
    hi = np.where(need, np.maximum(spread * spread, np.max(sp.lam, axis=-1)), 0.0)
    for _ in range(MP_DOUBLINGS):
        low_enough = sp.gls(hi)[2] <= target
        if np.all(low_enough | ~need):
            break
        hi = np.where(need & ~low_enough, 2.0 * hi, hi)
    else:  # pragma: no cover - Q -> 0 as tau^2 grows, so the bracket always closes
        raise RuntimeError("the Mandel-Paule bracket did not close")
    for _ in range(MP_BISECTIONS):
        mid = 0.5 * (lo + hi)
        above = sp.gls(mid)[2] > target
        lo = np.where(need & above, mid, lo)
        hi = np.where(need & ~above, mid, hi)
    return np.where(need, 0.5 * (lo + hi), 0.0)


def random_effects(sp: Spectral, tau2: np.ndarray, method: str) -> Consensus:
    """The consensus of the random-effects model with the given tau^2 (GLS with V + tau^2 I)."""
    v, u, _ = sp.gls(tau2)
    return Consensus(method, v, u, np.asarray(tau2, dtype=np.float64), sp.weights(tau2))


def mandel_paule(sp: Spectral) -> Consensus:
    return random_effects(sp, tau2_mandel_paule(sp), "mandel_paule")


def dersimonian_laird(sp: Spectral) -> Consensus:
    return random_effects(sp, tau2_dersimonian_laird(sp), "dersimonian_laird")


def consensus(sp: Spectral, method: str) -> Consensus:
    """One of :data:`METHODS`."""
    funcs = {"weighted_mean": weighted_mean, "mandel_paule": mandel_paule, "dersimonian_laird": dersimonian_laird}
    if method not in funcs:
        raise InputError(f"unknown consensus method {method!r}; expected one of {', '.join(METHODS)}", field="method")
    return funcs[method](sp)


# ----------------------------------------------------------------------------------------------
# Degrees of equivalence, E_n, compatibility
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Equivalence:
    """Degrees of equivalence d (..., P), their standard uncertainty u_d, expanded U = k u_d and
    E_n = d / U."""

    d: np.ndarray
    u_d: np.ndarray
    U: np.ndarray
    e_n: np.ndarray
    k: float

    @property
    def compatible(self) -> np.ndarray:
        return np.abs(self.e_n) <= 1.0


def degrees_of_equivalence(x: np.ndarray, V: np.ndarray, value: np.ndarray, weights: np.ndarray | None = None,
                           tau2: np.ndarray | float = 0.0, u_ext: np.ndarray | float = 0.0,
                           k: float = COVERAGE_FACTOR) -> Equivalence:
    """d_i = x_i - value with u^2(d_i) = (e_i - a)^T V (e_i - a) + tau^2 a^T a + u_ext^2 (module
    docstring). ``weights`` a: the participants' weights in ``value`` (None or zeros for an external
    reference value such as the truth)."""
    x = np.asarray(x, dtype=np.float64)
    V = np.asarray(V, dtype=np.float64)
    d = x - np.asarray(value, dtype=np.float64)[..., None]
    u2 = np.diagonal(V, axis1=-2, axis2=-1).copy()
    if weights is not None:
        a = np.asarray(weights, dtype=np.float64)
        va = np.einsum("...ij,...j->...i", V, a)
        ava = np.einsum("...i,...i->...", a, va)
        u2 = u2 - 2.0 * va + (ava + np.asarray(tau2, dtype=np.float64) * np.sum(a * a, axis=-1))[..., None]
    u2 = u2 + np.square(np.asarray(u_ext, dtype=np.float64))[..., None]
    u_d = np.sqrt(np.maximum(u2, 0.0))
    U = k * u_d
    with np.errstate(divide="ignore", invalid="ignore"):
        e_n = np.where(U > 0, d / U, np.where(d == 0, 0.0, np.sign(d) * np.inf))
    return Equivalence(d=d, u_d=u_d, U=U, e_n=e_n, k=float(k))


def equivalence_to(x: np.ndarray, V: np.ndarray, ref: Consensus, k: float = COVERAGE_FACTOR) -> Equivalence:
    """Degrees of equivalence with respect to a consensus of the same participants."""
    return degrees_of_equivalence(x, V, ref.value, ref.weights, ref.tau2, 0.0, k)


def compatible_share(e_n: np.ndarray, axis=None) -> np.ndarray:
    """The share of |E_n| <= 1 (over ``axis``; all axes by default)."""
    return np.mean(np.abs(np.asarray(e_n)) <= 1.0, axis=axis)
