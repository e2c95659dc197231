"""The tolerances module (tests/tolerances.py): one N_SIGMA, and the family threshold keeps the
family-wise false-alarm probability of m cells at that of one N_SIGMA check."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm

from tolerances import ALPHA, N_SIGMA, n_sigma, z_family


def test_one_cell_is_one_n_sigma_check():
    assert z_family(1) == pytest.approx(N_SIGMA, rel=1e-12)
    assert ALPHA == pytest.approx(2 * norm.sf(N_SIGMA), rel=1e-12, abs=0.0)


@pytest.mark.parametrize("m", [2, 5, 30, 580, 10_000])
def test_family_wise_false_alarm_is_that_of_one_check(m):
    z = z_family(m)
    per_cell = 2 * norm.sf(z)
    assert 1 - (1 - per_cell) ** m == pytest.approx(ALPHA, rel=1e-9, abs=0.0)
    assert z > z_family(m - 1)                      # more cells, a wider per-cell band


def test_family_threshold_by_simulation():
    """Independent normal cells: the share of families of 30 with any |z| > z_family(30, alpha) is
    the level (simulated at alpha = 0.05 instead of ALPHA, where it is measurable)."""
    rng = np.random.default_rng(5)
    m, families, alpha = 30, 200_000, 0.05
    z = z_family(m, alpha)
    hits = (np.abs(rng.standard_normal((families, m))) > z).any(axis=1).mean()
    assert abs(hits - alpha) < N_SIGMA * math.sqrt(alpha * (1 - alpha) / families)


def test_no_family_of_nothing():
    with pytest.raises(ValueError):
        z_family(0)


def test_degrees_of_freedom_give_the_t_quantile_of_the_same_probability():
    """An SE of few degrees of freedom: the threshold a Student-t error exceeds with the same
    probability (n_sigma(15) = 5.48 for N_SIGMA = 4), the normal one without (or NaN / inf) dof, and
    by simulation: t_15 errors beyond n_sigma(15) SE as often as ALPHA (at alpha = 0.05, measurable)."""
    from scipy.stats import t as student_t
    assert n_sigma() == z_family(1) == n_sigma(float("nan")) == n_sigma(math.inf) == pytest.approx(N_SIGMA, rel=1e-12)
    assert n_sigma(15) == pytest.approx(5.4804, abs=1e-4)
    assert 2 * student_t.sf(n_sigma(15), 15) == pytest.approx(ALPHA, rel=1e-9)
    k = z_family(30, dof=np.array([15.0, 63.0, np.nan]))
    assert k[0] > k[1] > k[2] == z_family(30)
    rng = np.random.default_rng(6)
    z = z_family(10, 0.05, dof=15)
    hits = (np.abs(rng.standard_t(15, (100_000, 10))) > z).any(axis=1).mean()
    assert abs(hits - 0.05) < N_SIGMA * math.sqrt(0.05 * 0.95 / 100_000)
