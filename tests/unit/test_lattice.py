"""Rank-1 lattices of the batched engine (roadgonio/engines/mitsuba/lattice.py): the stored
generating vectors are what their search gives, every one-dimensional projection is the full grid
j/n, a randomly shifted lattice is an unbiased rule with a smaller error than independent points on
a smooth integrand, and the shifts depend only on (seed, pass, size)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.engines.mitsuba import lattice as lat
from tolerances import N_SIGMA


@pytest.mark.parametrize("log2n", [4, 5, 6, 7, 8, 9, 10])
def test_table_is_the_search_result(log2n):
    assert lat.KOROBOV[log2n] == lat.search_korobov(log2n)


def test_table_covers_every_size_and_beats_random_multipliers():
    assert sorted(lat.KOROBOV) == list(range(lat.MIN_LOG2, lat.MAX_LOG2 + 1))
    rng = np.random.default_rng(3)
    for log2n in (8, 11):
        n = 1 << log2n
        best = lat.p2_criterion(n, lat.generating_vector(n))
        others = [lat.p2_criterion(n, lat.korobov_vector(n, int(a)))
                  for a in rng.choice(np.arange(3, n // 2, 2), size=40, replace=False)]
        assert best <= np.quantile(others, 0.1), (log2n, best, np.quantile(others, [0.1, 0.5]))


@pytest.mark.parametrize("n", [16, 256, 1 << 14])
def test_every_projection_is_the_full_grid(n):
    pts = lat.lattice_points(n, np.zeros(lat.DIMENSIONS))
    for d in range(lat.DIMENSIONS):
        assert np.array_equal(np.sort(np.round(pts[:, d] * n).astype(int)), np.arange(n))


def test_bad_sizes_are_refused():
    for n in (3, 1000, 1 << 21, 8):
        with pytest.raises(ValueError):
            lat.generating_vector(n)


def test_shifted_lattice_is_unbiased_and_beats_independent_points():
    """A smooth non-periodic integrand over [0,1)^6 with known mean: the mean over 200 random
    shifts is within N_SIGMA SE of the truth, and the spread per rule is far below that of n
    independent points."""
    def f(u):
        return np.prod(1.0 + 0.5 * (u - 0.5) + 0.3 * np.cos(2.0 * u), axis=1)
    truth = np.prod([1.0 + 0.3 * math.sin(2.0) / 2.0] * lat.DIMENSIONS)
    n = 1024
    rng = np.random.default_rng(11)
    est = np.array([f(lat.lattice_points(n, rng.random(lat.DIMENSIONS))).mean() for _ in range(200)])
    se = est.std(ddof=1) / math.sqrt(len(est))
    assert abs(est.mean() - truth) <= N_SIGMA * se
    iid = np.array([f(rng.random((n, lat.DIMENSIONS))).mean() for _ in range(200)])
    assert est.std() < 0.3 * iid.std()


def test_shifts_depend_on_seed_pass_size_only():
    a = lat.shifts(5, 2, 10, 8)
    b = lat.shifts(5, 2, 10, 20)
    assert np.array_equal(a, b[:8])                  # replicate b is the same however many are drawn
    assert not np.allclose(a, lat.shifts(6, 2, 10, 8))
    assert not np.allclose(a, lat.shifts(5, 3, 10, 8))
    assert not np.allclose(a, lat.shifts(5, 2, 11, 8))
    assert a.shape == (8, 6) and np.all((a >= 0) & (a < 1))


def test_the_path_keys_and_the_path_shifts_of_a_replicate_are_independent():
    """Stray-light paths: a replicate's hash keys (walk_keys) and the shifts of its lattice
    dimensions beyond six (walk_shifts) come from streams of their own. Drawn from one stream, a
    key and a shift are the same 64 random bits (mutation audit 9b: key 1 equalled shift 0 to
    rounding, and every test passed). Fisher's z of the correlation of each key / 2^32 with each
    shift over 500 seeds, at the family-wise threshold of the 16 pairs."""
    from tolerances import z_family
    m, dims = 500, 4
    keys = np.array([lat.walk_keys(s, 0, 10, 1, dims)[0] for s in range(m)], dtype=np.float64) / 2.0 ** 32
    shifts = np.array([lat.walk_shifts(s, 0, 10, 1, dims)[0] for s in range(m)])
    z_lim = z_family(dims * dims)
    for i in range(dims):
        for j in range(dims):
            r = np.corrcoef(keys[:, i], shifts[:, j])[0, 1]
            assert abs(math.atanh(r)) * math.sqrt(m - 3) < z_lim, (i, j, r)


def test_the_paths_of_seeds_apart_by_2_to_the_32_differ_and_smaller_seeds_keep_their_stream():
    """(review, session 39) the path keys and shifts took the seed's low 32 bits: seeds 5 and 5 + 2^32
    traced the same stray-light paths. A seed below 2^32 keeps the stream it had (numbers unchanged)."""
    big = 5 + (1 << 32)
    assert not np.array_equal(lat.walk_keys(5, 0, 10, 4, 8), lat.walk_keys(big, 0, 10, 4, 8))
    assert not np.array_equal(lat.walk_shifts(5, 0, 10, 4, 8), lat.walk_shifts(big, 0, 10, 4, 8))
    old = np.random.default_rng([5, 0, 10, lat.WALK_STREAM]).integers(0, 1 << 32, size=(4, 8), dtype=np.uint64)
    np.testing.assert_array_equal(lat.walk_keys(5, 0, 10, 4, 8), old.astype(np.uint32))
    old = np.random.default_rng([2 ** 32 - 1, 1, 11, lat.WALK_STREAM, 1]).random((3, 5))
    np.testing.assert_array_equal(lat.walk_shifts(2 ** 32 - 1, 1, 11, 3, 5), old)
