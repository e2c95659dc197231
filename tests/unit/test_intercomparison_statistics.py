"""The statistics of a key comparison (roadgonio.intercomparison.statistics) against printed
examples, hand-computable cases, independent matrix computations written here, and their
sampling distributions.

Printed examples (the digits below are the printed ones; results are compared after rounding to
the printed number of decimals):

* BCG vaccine trials (13 studies; Colditz et al. 1994), as printed in W. Viechtbauer, "Conducting
  meta-analyses in R with the metafor package", J. Stat. Softw. 36(3) (2010), section 3.4, p. 14:
  the 2x2 counts (also printed with the log relative risks yi and variances vi in the metafor
  documentation of dat.bcg) and Cochran's "Q(df = 12) = 152.2330". That paper prints the REML fit
  only (tau^2 = 0.3132), which roadgonio does not implement; for DerSimonian-Laird the numbers
  are those of metafor's own check against Stata's metan (metafor test suite,
  tests/testthat/test_misc_metan_vs_rma.uni_with_dat.bcg.r: "metan tpos tneg cpos cneg, randomi"):
  tau^2 = 0.3088, estimate -0.7141, 95 % CI -1.0644 ... -0.3638, and the fixed-effect estimate
  -0.4303 (CI -0.5097 ... -0.3509).
* Paule-Mandel and DerSimonian-Laird both printed: R. DerSimonian, R. Kacker, "Random-effects
  model for meta-analysis of clinical trials: an update", Contemporary Clinical Trials 28 (2007)
  105-114, Tables 3 and 4 (pp. 111-112), the CLASP example (6 trials, log odds ratios):
  PM tau = 0.3681, mu = -0.3811, se = 0.2060; DL tau = 0.2323, mu = -0.3240, se = 0.1540 (the data
  and these values as transcribed in metafor's test_analysis_example_dersimonian2007.r).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm

from roadgonio.errors import InputError
from roadgonio.intercomparison import statistics as st


# ---- BCG (Viechtbauer 2010, p. 14; metafor dat.bcg) ---------------------------------------------
TPOS = np.array([4, 6, 3, 62, 33, 180, 8, 505, 29, 17, 186, 5, 27], dtype=float)
TNEG = np.array([119, 300, 228, 13536, 5036, 1361, 2537, 87886, 7470, 1699, 50448, 2493, 16886], dtype=float)
CPOS = np.array([11, 29, 11, 248, 47, 372, 10, 499, 45, 65, 141, 3, 29], dtype=float)
CNEG = np.array([128, 274, 209, 12619, 5761, 1079, 619, 87892, 7232, 1600, 27197, 2338, 17825], dtype=float)
#: yi and vi as printed in the metafor documentation of dat.bcg (escalc(measure = "RR"))
YI_PRINTED = [-0.8893, -1.5854, -1.3481, -1.4416, -0.2175, -0.7861, -1.6209, 0.0120, -0.4694, -1.3713, -0.3394,
              0.4459, -0.0173]
VI_PRINTED = [0.3256, 0.1946, 0.4154, 0.0200, 0.0512, 0.0069, 0.2230, 0.0040, 0.0564, 0.0730, 0.0124, 0.5325, 0.0714]

# ---- CLASP (DerSimonian & Kacker 2007) --------------------------------------------------------
N1 = np.array([156, 303, 565, 1570, 103, 4659], dtype=float)
N2 = np.array([74, 303, 477, 1565, 105, 4650], dtype=float)
A = np.array([5, 5, 12, 69, 9, 313], dtype=float)
C = np.array([8, 17, 9, 94, 11, 352], dtype=float)

Z975 = float(norm.ppf(0.975))


def log_rr(a, b, c, d):
    """Log relative risk and its large-sample variance (the yi, vi of metafor's escalc RR)."""
    return np.log(a / (a + b)) - np.log(c / (c + d)), 1 / a - 1 / (a + b) + 1 / c - 1 / (c + d)


def log_or(a, n1, c, n2):
    b, d = n1 - a, n2 - c
    return np.log(a * d / (b * c)), 1 / a + 1 / b + 1 / c + 1 / d


def spectral_of(y, v):
    return st.Spectral(np.asarray(y), st.covariance(np.sqrt(np.asarray(v))))


def test_bcg_data_reproduce_the_printed_log_relative_risks():
    y, v = log_rr(TPOS, TNEG, CPOS, CNEG)
    assert np.round(y, 4).tolist() == pytest.approx(YI_PRINTED, abs=0)
    assert np.round(v, 4).tolist() == pytest.approx(VI_PRINTED, abs=0)


def test_bcg_cochran_q_is_the_printed_152_2330_and_the_birge_ratio_follows():
    sp = spectral_of(*log_rr(TPOS, TNEG, CPOS, CNEG))
    assert round(float(st.chi2_observed(sp)), 4) == 152.2330
    assert float(st.birge_ratio(sp)) == pytest.approx(math.sqrt(152.2330 / 12), abs=1e-4)
    assert not st.consistent(sp)             # p < .0001 printed


def test_bcg_weighted_mean_is_metafors_fixed_effect():
    sp = spectral_of(*log_rr(TPOS, TNEG, CPOS, CNEG))
    wm = st.weighted_mean(sp)
    assert round(float(wm.value), 4) == -0.4303
    assert round(float(wm.value - Z975 * wm.u), 4) == -0.5097
    assert round(float(wm.value + Z975 * wm.u), 4) == -0.3509


def test_bcg_dersimonian_laird_matches_metafor_and_metan():
    sp = spectral_of(*log_rr(TPOS, TNEG, CPOS, CNEG))
    dl = st.dersimonian_laird(sp)
    assert round(float(dl.tau2), 4) == 0.3088
    assert round(float(dl.value), 4) == -0.7141
    assert round(float(dl.value - Z975 * dl.u), 4) == -1.0644
    assert round(float(dl.value + Z975 * dl.u), 4) == -0.3638


def test_clasp_paule_mandel_and_dersimonian_laird_match_dersimonian_kacker_2007_tables_3_4():
    sp = spectral_of(*log_or(A, N1, C, N2))
    pm, dl = st.mandel_paule(sp), st.dersimonian_laird(sp)
    assert [round(float(np.sqrt(pm.tau2)), 4), round(float(pm.value), 4), round(float(pm.u), 4)] == \
        [0.3681, -0.3811, 0.2060]
    assert [round(float(np.sqrt(dl.tau2)), 4), round(float(dl.value), 4), round(float(dl.u), 4)] == \
        [0.2323, -0.3240, 0.1540]


# ---- hand-computable cases ----------------------------------------------------------------------

def test_two_participants_by_hand():
    """x = (1, 3), u = (1, 1): x_w = 2, u_w^2 = 1/2, chi2 = 2, R_B = sqrt 2; d = -+1 with
    u^2(d) = 1 - 1/2 (Cox 2002 eq. 8), E_n = -+1/(2 sqrt(1/2)); DL: c = 2 - 2/2 = 1, tau^2 =
    (2 - 1)/1 = 1; MP: 2/(1 + tau^2) = 1, tau^2 = 1; their consensus 2 with u^2 = 1/(2/2) = 1."""
    x, V = np.array([1.0, 3.0]), st.covariance(np.array([1.0, 1.0]))
    sp = st.Spectral(x, V)
    wm = st.weighted_mean(sp)
    assert (wm.value, wm.u ** 2) == pytest.approx((2.0, 0.5), abs=1e-15)
    assert float(st.chi2_observed(sp)) == pytest.approx(2.0, abs=1e-14)
    assert float(st.birge_ratio(sp)) == pytest.approx(math.sqrt(2.0), abs=1e-14)
    eq = st.equivalence_to(x, V, wm)
    assert eq.d.tolist() == pytest.approx([-1.0, 1.0], abs=1e-15)
    assert eq.u_d.tolist() == pytest.approx([math.sqrt(0.5)] * 2, abs=1e-15)
    assert eq.e_n.tolist() == pytest.approx([-1 / (2 * math.sqrt(0.5)), 1 / (2 * math.sqrt(0.5))], abs=1e-14)
    for c in (st.dersimonian_laird(sp), st.mandel_paule(sp)):
        assert (float(c.tau2), float(c.value), float(c.u)) == pytest.approx((1.0, 2.0, 1.0), abs=1e-12)
    # u^2(d) with tau: (e_i - a)^T V (e_i - a) + tau^2 a^T a = 1/2 + 1/2
    eq = st.equivalence_to(x, V, st.mandel_paule(sp))
    assert eq.u_d.tolist() == pytest.approx([1.0, 1.0], abs=1e-12)


def test_correlated_pair_by_hand():
    """x = (1, 3), V = [[1, .5], [.5, 4]]: W = [[4, -.5], [-.5, 1]] / 3.75, a = (7/8, 1/8),
    x_ref = 1.25, u^2 = 3.75/4 = 0.9375; V a = u^2 1 so u^2(d_i) = V_ii - u^2: 0.0625, 3.0625."""
    x = np.array([1.0, 3.0])
    V = np.array([[1.0, 0.5], [0.5, 4.0]])
    sp = st.Spectral(x, V)
    wm = st.weighted_mean(sp)
    assert wm.weights.tolist() == pytest.approx([0.875, 0.125], abs=1e-15)
    assert (float(wm.value), float(wm.u) ** 2) == pytest.approx((1.25, 0.9375), abs=1e-14)
    eq = st.equivalence_to(x, V, wm)
    assert (eq.u_d ** 2).tolist() == pytest.approx([0.0625, 3.0625], abs=1e-14)
    # chi2 = r^T W r with r = x - 1.25 = (-0.25, 1.75): (4*0.0625 - 2*0.5*(-0.25*1.75) + 3.0625)/3.75
    assert float(st.chi2_observed(sp)) == pytest.approx((0.25 + 0.4375 + 3.0625) / 3.75, abs=1e-14)


def test_covariance_from_shared_components():
    u = np.array([0.02, 0.03, 0.01])
    g = np.array([[0.01, 0.02, 0.0]])                 # shared by participants 1 and 2 only
    V = st.covariance(u, g)
    assert np.allclose(V, [[4e-4, 2e-4, 0], [2e-4, 9e-4, 0], [0, 0, 1e-4]], rtol=0, atol=1e-18)
    with pytest.raises(InputError, match="smaller than the components"):
        st.covariance(np.array([0.01, 0.03, 0.01]), np.array([[0.02, 0.02, 0.0]]))
    with pytest.raises(InputError, match="positive"):
        st.covariance(np.array([0.0, 0.03]))
    with pytest.raises(InputError, match="at least 2"):
        st.covariance(np.array([0.01]))


def test_fully_correlated_participants_are_a_clear_error():
    V = np.array([[1.0, 1.0], [1.0, 1.0]])
    with pytest.raises(InputError, match="not positive definite"):
        st.Spectral(np.array([1.0, 2.0]), V)


# ---- independent computations -------------------------------------------------------------------

def _random_case(rng, P, correlated):
    x = rng.normal(10.0, 1.0, P)
    if correlated:
        L = rng.normal(0.0, 0.4, (P, P))
        V = L @ L.T + np.diag(rng.uniform(0.05, 0.5, P))
    else:
        V = np.diag(rng.uniform(0.05, 0.8, P))
    return x, V


def _gls_direct(x, V, tau2):
    """GLS mean, its u and the generalised Q with W = inv(V + tau^2 I), by matrix inversion."""
    W = np.linalg.inv(V + tau2 * np.eye(len(x)))
    one = np.ones(len(x))
    s = one @ W @ one
    mu = one @ W @ x / s
    r = x - mu
    return mu, 1 / math.sqrt(s), float(r @ W @ r), W @ one / s


@pytest.mark.parametrize("correlated", [False, True])
def test_consensus_matches_direct_matrix_computation(rng_seed, correlated):
    rng = np.random.default_rng(rng_seed)
    for _ in range(20):
        P = int(rng.integers(2, 7))
        x, V = _random_case(rng, P, correlated)
        sp = st.Spectral(x, V)
        mu, u, q, a = _gls_direct(x, V, 0.0)
        wm = st.weighted_mean(sp)
        assert (float(wm.value), float(wm.u)) == pytest.approx((mu, u), rel=1e-11, abs=0.0)
        # Q is a sum of weighted squared residuals of x ~ 10 about their mean: its rounding error is
        # absolute (~eps x^T W x ~ 1e-13), so Q near 0 (here down to 5e-3) gets an absolute tolerance
        assert float(st.chi2_observed(sp)) == pytest.approx(q, rel=1e-11, abs=1e-11)
        assert wm.weights.tolist() == pytest.approx(a.tolist(), abs=1e-11)
        # DerSimonian-Laird: (Q - (P - 1)) / (tr W - 1^T W^2 1 / 1^T W 1), W = inv(V)
        W = np.linalg.inv(V)
        one = np.ones(P)
        c = np.trace(W) - one @ W @ W @ one / (one @ W @ one)
        assert float(st.tau2_dersimonian_laird(sp)) == pytest.approx(max(0.0, (q - (P - 1)) / c), rel=1e-10, abs=1e-14)
        # Mandel-Paule: Q(tau^2) = P - 1 where it is positive, Q(0) <= P - 1 where it is 0
        t2 = float(st.tau2_mandel_paule(sp))
        if t2 > 0:
            assert _gls_direct(x, V, t2)[2] == pytest.approx(P - 1, rel=1e-10)
        else:
            assert q <= P - 1
        mp = st.mandel_paule(sp)
        mu2, u2, _, a2 = _gls_direct(x, V, t2)
        assert (float(mp.value), float(mp.u)) == pytest.approx((mu2, u2), rel=1e-10, abs=0.0)
        # u^2(d_i) = var(x_i - a^T x) under V, plus tau^2 a^T a
        eq = st.equivalence_to(x, V, mp)
        for i in range(P):
            e = -a2.copy()
            e[i] += 1.0
            assert float(eq.u_d[i]) ** 2 == pytest.approx(e @ V @ e + t2 * a2 @ a2, rel=1e-9)


def test_diagonal_dersimonian_laird_is_their_1986_formula(rng_seed):
    rng = np.random.default_rng(rng_seed + 1)
    x = rng.normal(0, 1, 9)
    v = rng.uniform(0.01, 0.3, 9)
    w = 1 / v
    mu = np.sum(w * x) / np.sum(w)
    q = np.sum(w * (x - mu) ** 2)
    expected = max(0.0, (q - 8) / (np.sum(w) - np.sum(w ** 2) / np.sum(w)))
    assert float(st.tau2_dersimonian_laird(spectral_of(x, v))) == pytest.approx(expected, rel=1e-12, abs=0.0)


def test_vectorised_over_cells_equals_cell_by_cell(rng_seed):
    rng = np.random.default_rng(rng_seed + 2)
    cases = [_random_case(rng, 4, True) for _ in range(12)]
    X = np.array([c[0] for c in cases]).reshape(3, 4, 4)
    V = np.array([c[1] for c in cases]).reshape(3, 4, 4, 4)
    sp = st.Spectral(X, V)
    batch = {m: st.consensus(sp, m) for m in st.METHODS}
    for k, (x, v) in enumerate(cases):
        one = st.Spectral(x, v)
        for m in st.METHODS:
            c = st.consensus(one, m)
            b = batch[m]
            assert float(b.value.reshape(-1)[k]) == pytest.approx(float(c.value), rel=1e-12, abs=0.0)
            assert float(b.tau2.reshape(-1)[k]) == pytest.approx(float(c.tau2), rel=1e-9, abs=1e-15)


def test_mandel_paule_zero_when_consistent_and_monotone_q():
    x, V = np.array([1.0, 1.1, 0.95]), st.covariance(np.array([0.2, 0.2, 0.2]))
    sp = st.Spectral(x, V)
    assert float(st.chi2_observed(sp)) <= 2
    assert float(st.tau2_mandel_paule(sp)) == 0.0
    assert float(st.tau2_dersimonian_laird(sp)) == 0.0
    sp2 = st.Spectral(np.array([1.0, 5.0, 2.0, 9.0]), st.covariance(np.array([0.3, 0.5, 0.2, 0.4])))
    qs = [float(sp2.gls(t)[2]) for t in (0.0, 0.5, 1.0, 5.0, 50.0)]
    assert all(a > b for a, b in zip(qs, qs[1:]))


# ---- sampling distributions -----------------------------------------------------------------------

def test_en_and_birge_ratio_of_consistent_participants_are_distributed_as_expected(rng_seed):
    """Four participants measuring the same value with their stated u as the true standard
    deviation: against the weighted mean E_n = d / (2 u(d)) is N(0, 1/4), so |E_n| <= 1 with
    probability P(|Z| <= 2) = 0.9545; chi2_obs follows chi2(3), so R_B^2 has mean 1 and the
    consistency check passes with probability 0.95."""
    rng = np.random.default_rng(rng_seed + 3)
    N = 20000
    u = np.array([0.01, 0.02, 0.015, 0.03])
    x = 1.0 + rng.standard_normal((N, 4)) * u
    V = st.covariance(np.broadcast_to(u, (N, 4)))
    sp = st.Spectral(x, V)
    eq = st.equivalence_to(x, V, st.weighted_mean(sp))
    p = 2 * norm.cdf(2.0) - 1
    share = float(st.compatible_share(eq.e_n))
    se = math.sqrt(p * (1 - p) / N)              # per participant; the mean over 4 is no noisier
    assert abs(share - p) < 4 * se
    assert float(np.std(eq.e_n)) == pytest.approx(0.5, abs=4 * 0.5 / math.sqrt(2 * N))
    rb2 = st.birge_ratio(sp) ** 2
    assert abs(float(rb2.mean()) - 1.0) < 4 * math.sqrt(2 / 3 / N)
    ok = float(np.mean(st.consistent(sp)))
    assert abs(ok - 0.95) < 4 * math.sqrt(0.95 * 0.05 / N)
    # and against the truth: E_n = (x - 1) / (2 u)
    eq_t = st.degrees_of_equivalence(x, V, np.ones(N))
    assert abs(float(st.compatible_share(eq_t.e_n)) - p) < 4 * se


def test_correlated_participants_en_is_distributed_as_expected(rng_seed):
    """With a shared component (a common reference tile) in both the data and the stated
    covariance, d_i / u(d_i) is still N(0, 1): the covariance accounts for the correlation."""
    rng = np.random.default_rng(rng_seed + 4)
    N = 20000
    u_own = np.array([0.01, 0.01, 0.02])
    g = np.array([0.02, 0.02, 0.0])                  # participants 1 and 2 share a 2 % tile
    x = 1.0 + rng.standard_normal((N, 3)) * u_own + rng.standard_normal((N, 1)) * g
    u = np.sqrt(u_own ** 2 + g ** 2)
    V = st.covariance(np.broadcast_to(u, (N, 3)), np.broadcast_to(g, (1, N, 3)))
    sp = st.Spectral(x, V)
    eq = st.equivalence_to(x, V, st.weighted_mean(sp))
    z = eq.d / eq.u_d
    for i in range(3):
        assert float(np.std(z[:, i])) == pytest.approx(1.0, abs=4 / math.sqrt(2 * N))
    assert abs(float(np.mean(st.chi2_observed(sp))) - 2.0) < 4 * math.sqrt(4 / N)
    # ignoring the correlation lowers chi2 below its expectation: the shared error looks like agreement
    spi = st.Spectral(x, st.covariance(np.broadcast_to(u, (N, 3))))
    assert float(np.mean(st.chi2_observed(spi))) < 2.0 - 10 * math.sqrt(4 / N)
