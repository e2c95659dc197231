"""roadgonio.engines.result.ratio_se, the standard error of a ratio of means of paired batch values
(the numpy Monte Carlo backend's and the stray-light reference's SE), against closed forms written
here: with a constant denominator the ratio is a plain mean and its SE is the sample standard
deviation (ddof 1) over sqrt(n); and, with fixed seeds, SE^2 is an unbiased estimate of the ratio's
variance. The other tests of the SE (the Mitsuba passes, the backends' z-scores) run with 16...64
batches, where an SE from the biased variance (ddof 0) is 1.6...3 % too small and passes unseen."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.engines.result import RATIO_DENOMINATOR_REL_SE_MAX, mean_rel_se, ratio_se
from tolerances import N_SIGMA, ROUND_TOL


@pytest.mark.parametrize("n", [2, 3, 5, 64])
def test_constant_denominator_gives_the_se_of_a_plain_mean(n):
    rng = np.random.default_rng(n)
    road = rng.normal(3.0, 0.5, n)
    c = 0.7
    r, se = ratio_se(road, np.full(n, c))
    mean = math.fsum(road) / n
    s2 = math.fsum((x - mean) ** 2 for x in road) / (n - 1)      # sample variance, ddof 1
    assert r == pytest.approx(mean / c, rel=ROUND_TOL)
    assert se == pytest.approx(math.sqrt(s2 / n) / c, rel=ROUND_TOL)


def test_se_squared_is_unbiased_for_the_variance_of_the_ratio():
    """n = 4 batches, constant denominator: E[SE^2] = Var(ratio) exactly (the ddof-1 variance is
    unbiased); over N runs both sides are estimated and compared within N_SIGMA of their combined
    standard error (an SE from the ddof-0 variance gives E[SE^2] = 3/4 Var, ~7 SE off)."""
    rng = np.random.default_rng(11)
    n, runs = 4, 4000
    lam = np.full(n, 2.0)
    ratios, se2 = np.empty(runs), np.empty(runs)
    for k in range(runs):
        ratios[k], se = ratio_se(rng.normal(1.0, 0.3, n), lam)
        se2[k] = se * se
    var_hat = np.var(ratios, ddof=1)
    mean_se2 = se2.mean()
    # standard errors of the two estimates (normal data: Var(s^2) = 2 sigma^4 / (N - 1))
    sd_var = var_hat * math.sqrt(2.0 / (runs - 1))
    sd_mean = se2.std(ddof=1) / math.sqrt(runs)
    assert abs(mean_se2 - var_hat) <= N_SIGMA * math.hypot(sd_var, sd_mean), (mean_se2, var_hat)


def test_welch_satterthwaite_degrees_of_freedom():
    """The effective degrees of freedom of a sum of independent variance estimates (JCGM 100
    G.4.1), against closed forms: one term keeps its own; k equal terms of nu add to k nu; a term
    known exactly (nu infinite) or absent (NaN) adds nothing to the denominator; never below the
    smallest nu of a term that counts; NaN when nothing is estimated."""
    from roadgonio.engines.result import welch_satterthwaite
    assert welch_satterthwaite([2.0], [15.0]) == pytest.approx(15.0, rel=ROUND_TOL)
    assert welch_satterthwaite([3.0, 3.0, 3.0], [9.0, 9.0, 9.0]) == pytest.approx(27.0, rel=ROUND_TOL)
    assert welch_satterthwaite([1.0, 4.0], [15.0, 63.0]) == pytest.approx(25.0 / (1 / 15 + 16 / 63), rel=ROUND_TOL)
    assert welch_satterthwaite([1.0, 1.0], [15.0, math.inf]) == pytest.approx(60.0, rel=ROUND_TOL)
    assert welch_satterthwaite([1.0, math.nan], [15.0, 9.0]) == pytest.approx(15.0, rel=ROUND_TOL)
    assert welch_satterthwaite([0.0, 0.0], [15.0, 15.0]) == 30.0            # every estimate 0: the count
    assert math.isnan(welch_satterthwaite([1.0], [math.nan]))
    rng = np.random.default_rng(9)
    for _ in range(100):
        v, nu = rng.uniform(0, 1, 4), rng.integers(2, 60, 4).astype(float)
        assert nu.min() - 1e-9 <= welch_satterthwaite(v, nu) <= nu.sum() + 1e-9


def test_no_standard_error_where_few_batches_carry_the_denominator():
    """Session 34's audit: a Gaussian beam of 0.01 deg lit a few lanes of one replicate in 16; the 15
    empty replicates' residuals are exactly 0, and the delta method gave an SE of 1e-16 ("converged",
    5000 SE from the truth). Where the denominator's mean is itself known to worse than
    RATIO_DENOMINATOR_REL_SE_MAX the SE is inf; at the edge it is the plain delta-method SE."""
    road, lam = np.zeros(16), np.zeros(16)
    road[3], lam[3] = 4.7e-30, 5.8e-31
    r, se = ratio_se(road, lam)
    assert r == pytest.approx(road[3] / lam[3], rel=ROUND_TOL) and se == math.inf
    assert mean_rel_se(lam) == pytest.approx(1.0, rel=ROUND_TOL)       # one value of n: exactly 1, whatever n
    # a denominator whose mean is known to just below / above the limit (its rel. SE = c / sqrt(n))
    rng = np.random.default_rng(5)
    n = 64
    z = np.tile([1.0, -1.0], n // 2)
    z /= z.std(ddof=1)
    for c, finite in ((0.99, True), (1.01, False)):
        lam = 1.0 + c * RATIO_DENOMINATOR_REL_SE_MAX * math.sqrt(n) * z
        road = 0.8 * lam + 0.01 * rng.standard_normal(n)
        assert mean_rel_se(lam) == pytest.approx(c * RATIO_DENOMINATOR_REL_SE_MAX, rel=ROUND_TOL)
        r, se = ratio_se(road, lam)
        if finite:
            res = road - r * lam
            assert se == pytest.approx(math.sqrt(res @ res / (n - 1) / n) / lam.mean(), rel=ROUND_TOL)
        else:
            assert se == math.inf


@pytest.mark.parametrize("scale", [1e-170, 1e-300, 1e150])
def test_the_standard_error_does_not_underflow_for_values_near_the_ends_of_float64(scale):
    """A BRDF of 1e-170 in a lobe's far tail: the residuals' squares underflowed to 0, and numpy-mc
    and the RQMC reference stated an SE of exactly 0 for results far from the truth (user audit:
    4.01e18 +- 0 where the truth is 2.77e18). The ratio's SE scales with the numerator."""
    rng = np.random.default_rng(4)
    road = 1.0 + 0.3 * rng.standard_normal(64)
    lam = 2.0 + 0.1 * rng.standard_normal(64)
    k1, se1 = ratio_se(road, lam)
    k, se = ratio_se(scale * road, lam)
    assert se1 > 0 and k == pytest.approx(scale * k1, rel=1e-13)
    assert se == pytest.approx(scale * se1, rel=1e-12)
    assert mean_rel_se(scale * lam) == pytest.approx(mean_rel_se(lam), rel=1e-12)
