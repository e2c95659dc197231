"""The discrepancy component of a surface correction (roadgonio/correction/discrepancy.py):
var(delta(c) - (K delta)(c)) / sigma^2 through known blurs, against closed forms and a float64
numeric integral written here apart from the code; the limiting cases (a delta-function instrument
gives 0, a blur much wider than the correlation length gives sigma^2)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from roadgonio.correction.discrepancy import (BIN_FRACTION, amplitude_from_penalty, beyond_nyquist_variance,
                                              discrepancy_correlation, make_blur)

#: Rounding every ray to the nearest lattice point (spacing BIN_FRACTION ell) moves it by a uniform
#: error of variance h^2 / 12 per coordinate: the bracket changes by O((h / ell)^2 / 12) per term it enters;
#: the tolerance allows (h / ell)^2 for the three terms (absolute, on a bracket in [0, 2]).
COMPRESSION_TOL = BIN_FRACTION ** 2
#: Gauss-Hermite nodes per dimension of the Gaussian blurs (exact for these smooth integrands to ~1e-12).
GH_NODES = 40


def gauss_blur(centre, sd, n=GH_NODES):
    """Points and weights of a 2-D isotropic Gaussian blur (tensor Gauss-Hermite rule)."""
    t, w = np.polynomial.hermite_e.hermegauss(n)
    w = w / w.sum()
    X, Y = np.meshgrid(centre[0] + sd * t, centre[1] + sd * t, indexing="ij")
    return np.stack([X.ravel(), Y.ravel()], axis=1), np.outer(w, w).ravel()


def blur_one_cell(x0, pts, wts, ell):
    return make_blur(np.array([x0], dtype=float), pts, wts, np.zeros(len(wts), dtype=np.int64), ell)


@pytest.mark.parametrize("ell, sd, shift", [(1.0, 0.3, 0.0), (1.0, 1.0, 0.0), (0.5, 2.0, 0.0), (1.0, 0.7, 0.8)])
def test_gaussian_blur_against_the_closed_form(ell, sd, shift):
    """Blur N(x0 + mu, sd^2 I), squared-exponential rho of length ell:
    E[delta(x0) K delta] = l^2 / (l^2 + s^2) exp(-mu^2 / (2 (l^2 + s^2))), E[(K delta)^2] = l^2 / (l^2 + 2 s^2)."""
    x0 = np.array([3.0, 5.0])
    pts, wts = gauss_blur(x0 + [shift, 0.0], sd)
    R = discrepancy_correlation([blur_one_cell(x0, pts, wts, ell)], ell)
    l2, s2 = ell ** 2, sd ** 2
    expect = 1.0 - 2.0 * l2 / (l2 + s2) * math.exp(-0.5 * shift ** 2 / (l2 + s2)) + l2 / (l2 + 2.0 * s2)
    assert R.shape == (1, 1)
    assert abs(R[0, 0] - expect) <= COMPRESSION_TOL, (R[0, 0], expect)


def test_two_instruments_on_one_cell_correlate_through_the_nominal_value():
    """cov(e_A, e_B) / sigma^2 = 1 - l^2/(l^2+a^2) - l^2/(l^2+b^2) + l^2/(l^2+a^2+b^2) for Gaussian blurs a, b."""
    ell, a, b = 1.0, 0.5, 1.5
    x0 = np.array([2.0, 2.0])
    A = blur_one_cell(x0, *gauss_blur(x0, a), ell)
    B = blur_one_cell(x0, *gauss_blur(x0, b), ell)
    R = discrepancy_correlation([A, B], ell)
    l2 = ell ** 2
    cross = 1.0 - l2 / (l2 + a * a) - l2 / (l2 + b * b) + l2 / (l2 + a * a + b * b)
    assert abs(R[0, 1] - cross) <= COMPRESSION_TOL and abs(R[1, 0] - R[0, 1]) < 1e-15
    assert abs(R[0, 0] - (1 - 2 * l2 / (l2 + a * a) + l2 / (l2 + 2 * a * a))) <= COMPRESSION_TOL


def test_box_blur_against_a_numeric_integral():
    """A uniform square blur of side L centred on x0: the bracket is 1 - 2 m1^2 + m2^2 with
    m1 = (1/L) int rho_1(x) dx and m2 = (1/L^2) int int rho_1(x - y) dx dy per dimension
    (rho separable), both integrated here by scipy in float64."""
    ell, L = 1.0, 2.5
    rho1 = lambda d: math.exp(-0.5 * d * d / ell ** 2)
    m1 = integrate.quad(lambda x: rho1(x), -L / 2, L / 2, epsabs=1e-13)[0] / L
    m2 = integrate.dblquad(lambda y, x: rho1(x - y), -L / 2, L / 2, -L / 2, L / 2, epsabs=1e-12)[0] / L ** 2
    expect = 1.0 - 2.0 * m1 ** 2 + m2 ** 2
    n = 400
    g = (np.arange(n) + 0.5) / n * L - L / 2
    X, Y = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel()], axis=1) + [10.0, 7.0]
    R = discrepancy_correlation([blur_one_cell([10.0, 7.0], pts, np.full(n * n, 1.0 / n ** 2), ell)], ell)
    assert abs(R[0, 0] - expect) <= COMPRESSION_TOL, (R[0, 0], expect)


def test_limiting_cases():
    """A delta-function instrument (every ray at the nominal point) gives exactly 0, and no covariance
    with anything; a blur far wider than ell (sd 15 ell: 1 - 2/226 + 1/451 = 0.9934) gives nearly the
    prior variance (1 in units of sigma^2); cells further apart than the cut-off do not correlate."""
    ell = 1.0
    x0 = np.array([[1.0, 1.0], [40.0, 40.0], [400.0, 400.0]])
    wide = gauss_blur(x0[1], 15.0)
    pts = np.concatenate([np.repeat(x0[:1], 50, axis=0), wide[0], x0[2:] + [[0.5, 0.0], [-0.5, 0.0]]])
    wts = np.concatenate([np.full(50, 1 / 50), wide[1], [0.5, 0.5]])
    cell_of = np.concatenate([np.zeros(50, dtype=np.int64), np.ones(GH_NODES ** 2, dtype=np.int64), [2, 2]])
    R = discrepancy_correlation([make_blur(x0, pts, wts, cell_of, ell)], ell)
    assert R[0, 0] == pytest.approx(0.0, abs=1e-14)
    assert abs(R[0, 1]) < 1e-10 and R[0, 2] == 0.0          # 0 up to the rounding of the sums
    assert R[1, 1] == pytest.approx(1.0 - 2.0 / 226.0 + 1.0 / 451.0, abs=COMPRESSION_TOL)
    assert R[1, 2] == 0.0
    # two rays at +-ell/2 (on the lattice: exact): 1 - 2 rho(1/2) + (1 + rho(1)) / 2
    assert R[2, 2] == pytest.approx(1.0 - 2.0 * math.exp(-0.125) + 0.5 * (1.0 + math.exp(-0.5)), rel=1e-12, abs=0.0)
    assert np.all(np.linalg.eigvalsh(R) >= -1e-12)


@pytest.mark.parametrize("lam_b, lam_t", [(5.0, 5.0), (8.0, 40.0), (100.0, 3.0)])
def test_beyond_nyquist_variance_against_a_cartesian_integral(lam_b, lam_t):
    """sigma^2 = int over the plane outside the square |k_b|, |k_t| <= pi of
    1 / (4 pi^2 (lam_b k_b^4 + lam_t k_t^4)), written here in Cartesian coordinates (4 quadrants):
    the strip k_b > pi over all k_t >= 0 in closed form (int_0^inf dk / (A + B k^4) =
    pi / (2 sqrt 2) A^(-3/4) B^(-1/4)), plus k_b < pi with k_t > pi by scipy after k_t = pi / t."""
    a = math.pi / (2 * math.sqrt(2)) * lam_b ** -0.75 * lam_t ** -0.25 / (2 * math.pi ** 2) / (4 * math.pi ** 2)
    f = lambda t, kb: (math.pi / t ** 2) / (4 * math.pi ** 2 * (lam_b * kb ** 4 + lam_t * (math.pi / t) ** 4))
    b = integrate.dblquad(f, 0.0, math.pi, 0.0, 1.0, epsabs=1e-14, epsrel=1e-11)[0]
    assert beyond_nyquist_variance(lam_b, lam_t) == pytest.approx(4 * (a + b), rel=1e-6)


def test_amplitude_scales_as_one_over_lambda_and_follows_the_region():
    """Doubling both smoothing parameters halves sigma^2 (the density is 1 / lambda); the peak
    cells take the peak blocks' value, the others the rest's; no peak blocks: the rest's for all."""
    assert beyond_nyquist_variance(10.0, 30.0) == pytest.approx(beyond_nyquist_variance(5.0, 15.0) / 2, rel=1e-12, abs=0.0)
    lam = {"beta_peak": 4.0, "eps_peak": 16.0, "beta_rest": 100.0, "eps_rest": 400.0}
    s2 = amplitude_from_penalty(lam, np.array(["peak", "rest"]))
    assert s2[0] == pytest.approx(beyond_nyquist_variance(4.0, 16.0), rel=1e-14, abs=0.0)
    assert s2[1] == pytest.approx(beyond_nyquist_variance(100.0, 400.0), rel=1e-14, abs=0.0)
    only = amplitude_from_penalty({"beta_rest": 100.0, "eps_rest": 400.0}, np.array(["peak", "rest"]))
    assert np.all(only == s2[1])


def test_one_setting_twice_keeps_its_whole_discrepancy(r3like):
    """parts_discrepancy: the same instrument part twice (one setting measured twice) has the same
    blur, so the two blocks of the covariance and the block between them are equal (fully
    correlated: repetition cannot average the discrepancy away), and the GLS combination of the two
    keeps the single measurement's discrepancy variance exactly; a second part with a narrower
    field stop correlates less with the first (a second aperture sees other detail)."""
    from roadgonio.correction.flexible import FlexPart, SurfaceSettings
    from roadgonio.correction.outside import combine, parts_discrepancy
    from roadgonio.engines.bundle import ForwardModel, RayBundles
    from roadgonio.instrument.config import load_instrument
    cells = [(12.0, 0.0), (8.0, 2.0), (4.0, 10.0), (1.0, 30.0), (0.25, 90.0)]
    settings = SurfaceSettings()
    inst = load_instrument("wide")
    a = FlexPart(ForwardModel(RayBundles.build(inst, cells, rays=64)), r3like, settings)
    b = FlexPart(ForwardModel(RayBundles.build(inst.with_changes(detector={"field_half_angle_deg": 0.05}), cells,
                                               rays=64, seed=1)), r3like, settings)
    theta = np.zeros(a.n_params)
    lam = {"beta_peak": 1.0, "eps_peak": 1.0, "beta_rest": 10.0, "eps_rest": 10.0}
    n = len(cells)
    twice, _ = parts_discrepancy([a, a], theta, [(1.0, lam)], settings)
    assert np.allclose(twice[:n, :n], twice[n:, n:], rtol=0, atol=1e-15)
    assert np.allclose(twice[:n, n:], twice[:n, :n], rtol=0, atol=1e-15)
    assert np.all(np.diag(twice[:n, :n]) > 0)
    # GLS of two equal measurements with an equal-weight covariance: G picks 1/2 and 1/2, and
    # G D G^T of a fully correlated D is D's own block
    big = twice + np.eye(2 * n) * 1e-4
    _, G = combine([np.zeros(n), np.zeros(n)], [cells, cells], big, cells)
    assert np.allclose(np.diag(G @ twice @ G.T), np.diag(twice[:n, :n]), rtol=1e-12, atol=0)
    pair, _ = parts_discrepancy([a, b], theta, [(1.0, lam)], settings)
    corr = np.diag(pair[:n, n:]) / np.sqrt(np.diag(pair[:n, :n]) * np.diag(pair[n:, n:]))
    assert np.all(corr < 1.0 - 1e-6), corr
    # the cache (``blurs``) holds a part's blur under the part, not under id(part): the second
    # aperture design drops each setting's part after evaluating it, and CPython may give a freed
    # object's id to a later one, which would then take the freed part's blur (here: a's blur left
    # under b's id, as such a reuse would leave it)
    from roadgonio.correction.discrepancy import part_blurs
    left = {id(b): part_blurs(a, theta, settings.discrepancy_ell)}
    again, _ = parts_discrepancy([a, b], theta, [(1.0, lam)], settings, left)
    assert np.array_equal(again, pair)


def _brute_bracket(comps_rays, comps_x0, w, ell):
    """sum over the components of g0^2 - 2 g0 sum_k w_k g_k rho(x_k, x0) + sum_kl w_k w_l g_k g_l rho(x_k, x_l),
    a float64 double sum over the rays themselves (no lattice), written apart from the code."""
    total = 0.0
    for (x, g), (x0, g0) in zip(comps_rays, comps_x0):
        d0 = np.sum((x - x0) ** 2, axis=1)
        dd = np.sum((x[:, None, :] - x[None, :, :]) ** 2, axis=2)
        rho = lambda d2: np.exp(-0.5 * d2 / ell ** 2)
        wg = w * g
        total += g0 * g0 - 2.0 * g0 * float(wg @ rho(d0)) + float(wg @ rho(dd) @ wg)
    return total


def test_the_pole_is_one_point():
    """pole_components: every point keeps the variance sigma^2 (g_P^2 + g_K^2 = 1); at s_t = 0 the
    coordinates of every beta are one point, so rays at the pole spread over every beta are the
    nominal direction itself (bracket 0, where the knot coordinates alone made it about 1); beyond
    the first knot ring only the knot-coordinate process is left. The weighted bracket of a cell near
    normal incidence (rays within s_t 0.4, every beta) agrees with a float64 double sum over its rays."""
    from roadgonio.correction.discrepancy import pole_components
    rng = np.random.default_rng(5)
    n, ell = 300, 1.0 / math.pi
    sb = rng.uniform(0.0, 24.0, n)
    beta = rng.uniform(0.0, 180.0, n)
    for st in (rng.uniform(0.0, 3.0, n), np.zeros(n)):
        (y, gp), (x, gk) = pole_components(sb, st, beta)
        assert np.allclose(gp ** 2 + gk ** 2, 1.0, rtol=0, atol=1e-12)
    (y, gp), (x, gk) = pole_components(sb, np.zeros(n), beta)
    assert np.all(y == 0.0) and np.all(gk == 0.0)
    w = np.full(n, 1.0 / n)
    x0c = pole_components(np.array([0.0]), np.array([0.0]), np.array([0.0]))
    cell = np.zeros(n, dtype=np.int64)
    R = sum(discrepancy_correlation([make_blur(c0[0], c[0], w, cell, ell, g=c[1], g0=c0[1])], ell)[0, 0]
            for c, c0 in zip(pole_components(sb, np.zeros(n), beta), x0c))
    raw = discrepancy_correlation([make_blur(np.array([[12.0, 0.0]]), np.stack([sb, np.zeros(n)], 1), w, cell,
                                             ell)], ell)[0, 0]
    assert R == pytest.approx(0.0, abs=1e-12) and raw > 0.9
    # beyond the first ring: the knot-coordinate bracket alone
    st = rng.uniform(1.0, 3.0, n)
    comps, comps0 = pole_components(sb, st, beta), pole_components(np.array([12.0]), np.array([2.0]), np.array([90.0]))
    two = sum(discrepancy_correlation([make_blur(c0[0], c[0], w, cell, ell, g=c[1], g0=c0[1])], ell)[0, 0]
              for c, c0 in zip(comps, comps0))
    one = discrepancy_correlation([make_blur(comps0[1][0], comps[1][0], w, cell, ell)], ell)[0, 0]
    assert two == pytest.approx(one, abs=1e-12)
    # near normal incidence: against the double sum over the rays
    st = rng.uniform(0.0, 0.4, n)
    comps, comps0 = pole_components(sb, st, beta), pole_components(np.array([0.0]), np.array([0.0]), np.array([0.0]))
    got = sum(discrepancy_correlation([make_blur(c0[0], c[0], w, cell, ell, g=c[1], g0=c0[1])], ell)[0, 0]
              for c, c0 in zip(comps, comps0))
    expect = _brute_bracket(comps, [(c0[0][0], c0[1][0]) for c0 in comps0], w, ell)
    assert abs(got - expect) <= COMPRESSION_TOL, (got, expect)
    assert got < 0.5 * raw


def test_the_model_value_sees_nothing_of_delta():
    """nominal_blur: the fitted model's own value at x0 has the error -delta(x0), so its bracket is
    1 with itself, and with an instrument of Gaussian blur a at the same cell
    cov(-delta(x0), K delta - delta(x0)) / sigma^2 = 1 - l^2 / (l^2 + a^2) (closed form); the GLS
    of the two, with noise s^2 on the instrument only, has the weight of the closed-form 2x2 BLUE."""
    from roadgonio.correction.discrepancy import nominal_blur
    from roadgonio.correction.outside import combine
    ell, a = 1.0, 0.8
    x0 = np.array([2.0, 3.0])
    A = blur_one_cell(x0, *gauss_blur(x0, a), ell)
    R = discrepancy_correlation([A, nominal_blur(A, [0])], ell)
    l2 = ell ** 2
    assert R[1, 1] == pytest.approx(1.0, abs=1e-15)
    assert abs(R[0, 1] - (1.0 - l2 / (l2 + a * a))) <= COMPRESSION_TOL
    s2 = 0.3
    C = R + np.diag([s2, 0.0])
    _, G = combine([np.zeros(1), np.zeros(1)], [[(1.0, 0.0)], [(1.0, 0.0)]], C, [(1.0, 0.0)])
    v_bb, v_aa, v_ab = C[0, 0], C[1, 1], C[0, 1]          # b: the instrument, a: the model's value
    w_b = (v_aa - v_ab) / (v_aa + v_bb - 2.0 * v_ab)
    assert G[0, 0] == pytest.approx(w_b, rel=1e-12) and G[0, 1] == pytest.approx(1.0 - w_b, rel=1e-12)


def test_parts_discrepancy_puts_the_model_values_after_the_cells_in_their_order(r3like):
    """parts_discrepancy(nominal=...): the model's values (bracket 1: their variance is sigma_c^2
    itself) follow the instruments' cells in the order asked; asking in another order permutes them."""
    from roadgonio.correction.discrepancy import amplitude_from_penalty
    from roadgonio.correction.flexible import FlexPart, SurfaceSettings, penalty_region
    from roadgonio.correction.outside import parts_discrepancy
    from roadgonio.engines.bundle import ForwardModel, RayBundles
    from roadgonio.instrument.config import load_instrument
    cells = [(12.0, 0.0), (8.0, 2.0), (4.0, 10.0), (0.0, 0.0)]
    settings = SurfaceSettings(regions="peak")
    a = FlexPart(ForwardModel(RayBundles.build(load_instrument("wide"), cells, rays=64)), r3like, settings)
    theta = np.zeros(a.n_params)
    lam = {"beta_peak": 1.0, "eps_peak": 1.0, "beta_rest": 10.0, "eps_rest": 10.0}
    n = len(cells)
    plain, _ = parts_discrepancy([a], theta, [(1.0, lam)], settings)
    ordered, _ = parts_discrepancy([a], theta, [(1.0, lam)], settings, nominal=[(0, k) for k in range(n)])
    shuffled, _ = parts_discrepancy([a], theta, [(1.0, lam)], settings, nominal=[(0, 2), (0, 0), (0, 3), (0, 1)])
    assert np.allclose(ordered[:n, :n], plain, rtol=0, atol=1e-15)
    eps = np.degrees(np.arctan([t for t, _ in cells]))
    peak = penalty_region(settings, np.array([b for _, b in cells]), eps)
    assert peak.tolist() == ["peak", "peak", "peak", "rest"]
    assert np.allclose(np.diag(ordered)[n:], amplitude_from_penalty(lam, peak), rtol=1e-12, atol=0)
    perm = np.array([0, 1, 2, 3, n + 2, n + 0, n + 3, n + 1])
    assert np.allclose(shuffled, ordered[np.ix_(perm, perm)], rtol=0, atol=1e-15)
    # the instrument's error and the model's are positively correlated (both miss delta(x0))
    assert np.all(np.diag(ordered[:n, n:]) > 0)


#: A pair beyond the cut-off (CUTOFF_ELL correlation lengths) is set to 0; its bracket is below
#: 3 exp(-CUTOFF_ELL^2 / 2) < 1.2e-5 in absolute value.
CUTOFF_TOL = 1.2e-5


def test_the_bracket_of_binned_blurs_is_the_plain_double_sum():
    """discrepancy_correlation over several blurs (weighted nominal points, empty images of the
    model's own value, images of every shape) against the bracket summed here lattice point by
    lattice point in float64, without a cut-off: within the cut-off's bound (the truncated kernel and
    the pairs set to 0) everywhere."""
    from roadgonio.correction.discrepancy import Blur, CUTOFF_ELL
    assert 3 * math.exp(-CUTOFF_ELL ** 2 / 2) < CUTOFF_TOL
    rng = np.random.default_rng(7)
    ell = 1.0
    h = BIN_FRACTION * ell
    blurs = []
    for b in range(3):
        n = 9
        x0 = rng.uniform(0.0, 6.0, size=(n, 2))
        org = np.rint(x0 / h).astype(np.int64) + rng.integers(-6, 3, size=(n, 2))
        imgs = []
        for c in range(n):
            if b == 2 and c % 3 == 0:
                imgs.append(np.zeros((1, 1)))            # the model's own value: sees nothing
                continue
            img = rng.uniform(0.0, 1.0, size=tuple(rng.integers(1, 9, size=2)))
            img[rng.uniform(size=img.shape) < 0.3] = 0.0
            imgs.append(img / max(img.sum(), 1e-300) * rng.uniform(0.5, 1.0))
        blurs.append(Blur(x0=x0, origins=org, images=tuple(imgs), h=h,
                          x0_weight=None if b == 0 else rng.uniform(0.0, 1.0, size=n)))
    R = discrepancy_correlation(blurs, ell)

    pts, g0s = [], []
    for bl in blurs:
        for c in range(bl.n):
            a, bb = np.nonzero(np.ones(bl.images[c].shape))
            lat = h * (bl.origins[c] + np.stack([a, bb], axis=1))
            pts.append((bl.x0[c], lat, bl.images[c][a, bb]))
            g0s.append(1.0 if bl.x0_weight is None else bl.x0_weight[c])

    def rho(p, q):
        d = p[:, None, :] - q[None, :, :]
        return np.exp(-0.5 * np.sum(d * d, axis=2) / ell ** 2)

    N = len(pts)
    ref = np.zeros((N, N))
    for i, (xi, Xi, wi) in enumerate(pts):
        for j, (xj, Xj, wj) in enumerate(pts):
            ref[i, j] = (g0s[i] * g0s[j] * rho(xi[None], xj[None])[0, 0] - g0s[i] * (rho(xi[None], Xj)[0] @ wj)
                         - g0s[j] * (rho(xj[None], Xi)[0] @ wi) + wi @ rho(Xi, Xj) @ wj)
    assert R.shape == (N, N) and np.array_equal(R, R.T)
    assert np.sum(np.abs(ref) > 0.05) > 2 * N            # the cells overlap: the test has pairs to check
    assert np.max(np.abs(R - ref)) < CUTOFF_TOL
