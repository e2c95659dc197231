"""Pass planning and float64 statistics of the batched engine (roadgonio/engines/mitsuba/passes.py),
on synthetic replicate sums with known distributions: the ratio SE from moments equals the direct
delta-method formula and matches the scatter of the ratio; the covariance estimate matches the
correlation built in; the planner follows the 1/N rule, never shrinks a cell's lattice, caps its
growth, and stops cells at the target or the sample cap; a plan survives a round trip."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.engines.result import RATIO_DENOMINATOR_REL_SE_MAX
from roadgonio.engines.mitsuba.passes import (MAX_GROWTH, SAFETY, CellStats, Plan, Planner, add_strata, se_dof_many,
                                              covariance, relative, strata_ratio_se, strata_ratio_se_dof_many,
                                              strata_ratio_se_many, stray_ratios)


def synthetic(rng, reps, ratio=0.8, rel=0.05, rho=0.9, n=1024):
    """Replicate sums of n points: G around n, R = ratio G + noise (correlated with G)."""
    G = n * (1.0 + rel * rng.standard_normal(reps))
    R = ratio * G * (1.0 + rel * np.sqrt(1 - rho * rho) * rng.standard_normal(reps))
    return R, G


def direct_se(strata):
    R = np.concatenate([s[0] for s in strata])
    G = np.concatenate([s[1] for s in strata])
    r = R.sum() / G.sum()
    var = sum(len(a) * np.var(a - r * b, ddof=1) for a, b in strata)
    return r, math.sqrt(var) / G.sum()


def direct_dof(strata):
    """Welch-Satterthwaite degrees of freedom of direct_se: each stratum's variance term
    v = B var(A - r B) has B - 1; dof = (sum v)^2 / sum v^2 / (B - 1)."""
    r = sum(a.sum() for a, _ in strata) / sum(b.sum() for _, b in strata)
    v = np.array([len(a) * np.var(a - r * b, ddof=1) for a, b in strata])
    nu = np.array([len(a) - 1.0 for a, _ in strata])
    return float(v.sum() ** 2 / np.sum(v * v / nu))


def test_moment_se_equals_direct_formula():
    rng = np.random.default_rng(1)
    st = CellStats()
    strata = []
    for p, (log2n, reps) in enumerate([(6, 16), (9, 20), (12, 16)]):
        R, G = synthetic(rng, reps, n=1 << log2n)
        st.add(p, log2n, np.arange(reps), R, G)
        strata.append((R, G))
    r, se, _ = st.ratio_se()
    r2, se2 = direct_se(strata)
    assert r == pytest.approx(r2, rel=1e-14, abs=0.0)
    assert se == pytest.approx(se2, rel=1e-9)
    assert st.samples == 16 * 64 + 20 * 512 + 16 * 4096 and st.passes == 3


def test_se_matches_scatter_of_the_ratio():
    rng = np.random.default_rng(2)
    rs, ses = [], []
    for _ in range(400):
        st = CellStats()
        R, G = synthetic(rng, 16, rel=0.1, rho=0.5)
        st.add(0, 10, np.arange(16), R, G)
        r, se, _ = st.ratio_se()
        rs.append(r)
        ses.append(se)
    ratio = np.std(rs, ddof=1) / math.sqrt(np.mean(np.square(ses)))
    assert 0.9 < ratio < 1.1


def test_single_replicate_has_no_se_and_zero_signal_has_no_ratio():
    st = CellStats()
    st.add(0, 8, np.arange(1), np.array([2.0]), np.array([4.0]))
    assert st.ratio_se()[1] == math.inf
    dark = CellStats()
    dark.add(0, 8, np.arange(4), np.zeros(4), np.zeros(4))
    r, se, g = dark.ratio_se()
    assert math.isnan(r) and se == math.inf and g == 0.0
    assert relative(0.0, 0.0) == 0.0 and relative(0.0, 1.0) == math.inf
    # without stray light traced: the direct light is the cell's own ratio, the stray fraction exactly 0
    st = CellStats()
    st.add(0, 8, np.arange(16), *synthetic(np.random.default_rng(4), 16))
    assert st.direct_ratio_se() == st.ratio_se()[:2] and st.stray_fraction_se() == (0.0, 0.0)


def test_a_cell_whose_light_few_replicates_carry_has_no_se_and_grows_by_the_lambert_sums_rule():
    """One replicate of 16 lit (a beam far narrower than the footprint's angles; session 34's audit:
    k_A 1.0075 +- 1.5e-16 "converged"): no SE (the Lambert sum known to a relative SE of
    1 > RATIO_DENOMINATOR_REL_SE_MAX), in the cell's own statistics and the vectorised
    strata; the planner does not converge it and asks for the samples that bring the Lambert sum to
    the limit by the 1/N rule (capped at MAX_GROWTH), then converges it on its SE as usual."""
    R, G = np.zeros(16), np.zeros(16)
    R[5], G[5] = 4.7e-30, 5.8e-31
    st = CellStats()
    st.add(0, 8, np.arange(16), R, G)
    assert st.lambert_rel_se() == pytest.approx(1.0, rel=1e-12)       # one sum of n: exactly 1
    r, se, _ = st.ratio_se()
    assert r == pytest.approx(R[5] / G[5], rel=1e-12) and se == math.inf
    r2, se2, dof2 = strata_ratio_se_dof_many([[(R, G)]])
    assert r2[0] == pytest.approx(r, rel=1e-12) and se2[0] == math.inf and math.isnan(dof2[0])
    pl = Planner(1e-3, first_pass=4096, min_replicates=16)
    req, done = pl.next([st], [0])
    assert not done["converged"] and not done["capped"]
    log2n, reps = req[0]
    assert (reps << log2n) >= MAX_GROWTH * st.samples - (1 << log2n)    # (1 / 0.1)^2 - 1 = 99: capped
    # a Lambert sum known to 0.15: (0.15 / 0.1)^2 - 1 = 1.25 times the samples again, with the safety factor
    z = np.tile([1.0, -1.0], 8)
    z /= z.std(ddof=1)
    G = 256.0 * (1.0 + 0.6 * z)                          # rel. SE of the sum: 0.6 sqrt(16) / 16 = 0.15
    mid = CellStats()
    mid.add(0, 8, np.arange(16), 0.8 * G, G)
    assert mid.lambert_rel_se() == pytest.approx(0.15, rel=1e-12) and mid.ratio_se()[1] == math.inf
    req, done = pl.next([mid], [0])
    log2n, reps = req[0]
    want = mid.samples * ((0.15 / RATIO_DENOMINATOR_REL_SE_MAX) ** 2 - 1.0) * SAFETY
    assert want <= reps << log2n < want + (16 << log2n)
    # and where the Lambert sum is known, the usual SE (R = 0.8 G exactly: 0, converged)
    ok = CellStats()
    ok.add(0, 8, np.arange(16), 0.8 * 256.0 * (1 + 0.01 * z), 256.0 * (1 + 0.01 * z))
    assert ok.ratio_se()[1] == pytest.approx(0.0, abs=1e-12)
    assert pl.next([ok], [0])[1]["converged"] == [0]


def test_strata_ratio_se_of_many_cells_equals_each_cell_alone():
    """The vectorised ratio and SE over many cells (the direct light and the stray fraction of a
    table at once) are each cell's delta-method formula (strata of different sizes, cells of
    different numbers of strata, ratios 0.3-3); a stratum with one replicate or none gives SE inf,
    a cell without signal or without strata (nan, inf), without disturbing its neighbours."""
    rng = np.random.default_rng(7)
    cells = []
    for _ in range(40):
        cells.append([synthetic(rng, int(rng.integers(2, 40)), ratio=float(rng.uniform(0.3, 3.0)),
                                n=1 << int(rng.integers(6, 12)))
                      for _ in range(int(rng.integers(1, 5)))])
    special = {3: cells[3] + [(np.array([1.0]), np.array([2.0]))],        # one replicate
               8: cells[8] + [(np.zeros(0), np.zeros(0))],                  # none
               11: [(np.zeros(5), np.zeros(5))],                           # no signal
               20: []}                                                     # no strata
    cells = [special.get(i, c) for i, c in enumerate(cells)]
    r, se = strata_ratio_se_many(cells)
    for i, c in enumerate(cells):
        if i in (11, 20):
            assert math.isnan(r[i]) and se[i] == math.inf
            continue
        if i in (3, 8):
            assert r[i] == pytest.approx(sum(a.sum() for a, _ in c) / sum(b.sum() for _, b in c), rel=1e-14, abs=0.0)
            assert se[i] == math.inf
        else:
            r2, se2 = direct_se(c)
            assert r[i] == pytest.approx(r2, rel=1e-14, abs=0.0)
            assert se[i] == pytest.approx(se2, rel=1e-12, abs=0.0)
        assert (r[i], se[i]) == strata_ratio_se(c)            # one cell alone: the same numbers


def test_stray_ratios_are_the_cells_own():
    """:func:`stray_ratios` (a table's direct light and stray fraction at once) against each cell's
    :meth:`CellStats.direct_ratio_se` / :meth:`CellStats.stray_fraction_se`, and the formulas."""
    rng = np.random.default_rng(8)
    stats = []
    for _ in range(12):
        st = CellStats()
        for p in range(int(rng.integers(1, 4))):
            reps = int(rng.integers(2, 30))
            Rd, Gd = synthetic(rng, reps, ratio=float(rng.uniform(0.5, 2.0)))
            stray = np.abs(rng.normal(0.2, 0.05, reps)) * Rd
            add_strata([st], p, 8, np.zeros(reps, dtype=np.int64), np.arange(reps), Rd + stray, Gd + 0.5 * stray, Rd, Gd)
        stats.append(st)
    rd, rd_se, sf, sf_se, dof = stray_ratios(stats)
    for k, st in enumerate(stats):
        keys = sorted(st.strata)
        assert (rd[k], rd_se[k]) == st.direct_ratio_se()
        assert (sf[k], sf_se[k]) == st.stray_fraction_se()
        r2, se2 = direct_se([st.direct[q] for q in keys])
        assert rd[k] == pytest.approx(r2, rel=1e-14, abs=0.0) and rd_se[k] == pytest.approx(se2, rel=1e-12, abs=0.0)
        q2, qse2 = direct_se([(st.direct[q][0], st.strata[q][1]) for q in keys])
        assert sf[k] == pytest.approx(1.0 - q2, rel=1e-13, abs=0.0) and sf_se[k] == pytest.approx(qse2, rel=1e-12, abs=0.0)
        # one number of degrees of freedom for both SEs: the smaller of the two
        want = min(direct_dof([st.direct[q] for q in keys]), direct_dof([(st.direct[q][0], st.strata[q][1]) for q in keys]))
        assert dof[k] == pytest.approx(want, rel=1e-12, abs=0.0)


def test_se_dof_is_welch_satterthwaite_over_the_strata():
    """The SE's degrees of freedom (module docstring): B - 1 for one stratum of B replicates,
    2 (B - 1) for two strata with the same variance, near the dominant stratum's B - 1 when one
    stratum carries the variance; the moments of CellStats, the vectorised strata and the formula
    written here agree; NaN without an SE."""
    rng = np.random.default_rng(11)
    R, G = synthetic(rng, 16)
    one = CellStats()
    one.add(0, 8, np.arange(16), R, G)
    assert one.se_dof() == pytest.approx(15.0, rel=1e-12)
    twice = CellStats()
    twice.add(0, 8, np.arange(16), R, G)
    twice.add(1, 8, np.arange(16), R, G)                       # the same sums again: equal variances
    assert twice.se_dof() == pytest.approx(30.0, rel=1e-12)
    small, big = synthetic(rng, 40, rel=1e-4), synthetic(rng, 16, rel=0.1)
    lop = CellStats()
    lop.add(0, 8, np.arange(40), *small)
    lop.add(1, 8, np.arange(16), *big)
    assert 15.0 <= lop.se_dof() < 15.01
    cells, stats = [], []
    for _ in range(30):
        st = CellStats()
        strata = []
        for p in range(int(rng.integers(1, 5))):
            reps = int(rng.integers(2, 40))
            A, B = synthetic(rng, reps, ratio=float(rng.uniform(0.3, 3.0)), rel=float(rng.uniform(0.01, 0.2)))
            st.add(p, 8, np.arange(reps), A, B)
            strata.append((A, B))
        assert st.se_dof() == pytest.approx(direct_dof(strata), rel=1e-9)
        assert min(len(a) - 1 for a, _ in strata) <= st.se_dof() <= sum(len(a) - 1 for a, _ in strata) + 1e-9
        cells.append(strata)
        stats.append(st)
    _, _, dof = strata_ratio_se_dof_many(cells)
    assert np.allclose(dof, [direct_dof(c) for c in cells], rtol=1e-12, atol=0.0)
    single = CellStats()
    single.add(0, 8, np.arange(1), np.array([2.0]), np.array([4.0]))
    assert math.isnan(single.se_dof())
    # a table's cells at once (what the backend asks after each pass), a cell without an SE among them
    many = se_dof_many(stats[:13] + [single] + stats[13:])
    assert math.isnan(many[13])
    assert np.allclose(np.delete(many, 13), [direct_dof(c) for c in cells], rtol=1e-9, atol=0.0)
    assert list(np.delete(many, 13)) == [st.se_dof() for st in stats]
    assert se_dof_many([]).shape == (0,)
    assert math.isnan(strata_ratio_se_dof_many([[(np.array([1.0]), np.array([2.0]))]])[2][0])


def test_z_of_the_se_follows_student_t_of_its_degrees_of_freedom():
    """What the degrees of freedom are for: over 6000 synthetic cells (one stratum of 16
    replicates, or 16 + 24 of unequal variance) z = (r - true r) / SE is heavier-tailed than a
    normal law (mean z^2 ~ dof / (dof - 2), 1.15 at 15), and mapped through Student's t of the
    reported dof to a normal quantile it is N(0, 1): mean square within the chi-square band of ALPHA,
    |z| beyond the t quantile of 3 sigma as often as a normal beyond 3 (binomial band). With the dof
    taken as infinite (a normal z) the first check fails."""
    from scipy.stats import chi2, norm, t as student_t
    from tolerances import ALPHA
    rng = np.random.default_rng(12)
    m = 6000
    cells = []
    for i in range(m):
        strata = [synthetic(rng, 16, ratio=0.8, rel=0.05)]
        if i % 2:
            strata.append(synthetic(rng, 24, ratio=0.8, rel=0.08))
        cells.append(strata)
    r, se, dof = strata_ratio_se_dof_many(cells)
    z = (r - 0.8) / se
    assert np.all((dof >= 15.0 - 1e-9) & (dof <= 38.0 + 1e-9))
    u = norm.isf(student_t.sf(z, dof))                   # z mapped through its own t to N(0, 1)
    lo, hi = chi2.ppf(ALPHA / 2, m) / m, chi2.isf(ALPHA / 2, m) / m
    assert lo < float(np.mean(u * u)) < hi, float(np.mean(u * u))
    assert float(np.mean(z * z)) > hi                    # a normal reading of z: too many large |z|
    p = 2 * norm.sf(3.0)
    beyond = int(np.sum(np.abs(z) > student_t.isf(p / 2, dof)))
    band = 4.0 * math.sqrt(m * p * (1 - p))
    assert abs(beyond - m * p) <= band, (beyond, m * p)


def test_add_strata_vectorised_equals_one_by_one_and_refuses_duplicates():
    rng = np.random.default_rng(3)
    owner = np.repeat([0, 2, 3], [16, 20, 16])
    reps = np.concatenate([np.arange(16), np.arange(20), np.arange(16)])
    R, G = synthetic(rng, len(owner))
    Rd, Gd = 0.8 * R, 0.9 * G                   # with stray light: each cell's own direct sums
    many = [CellStats() for _ in range(4)]
    add_strata(many, 0, 8, owner, reps, R, G, Rd, Gd)
    for c in (0, 2, 3):
        one = CellStats()
        m = owner == c
        one.add(0, 8, reps[m], R[m], G[m])
        assert many[c].ratio_se() == pytest.approx(one.ratio_se(), rel=1e-12, abs=0.0)
        # mutation audit 11: every cell getting the first cell's direct sums passed every test
        np.testing.assert_array_equal(many[c].direct[(0, 8)][0], Rd[m])
        np.testing.assert_array_equal(many[c].direct[(0, 8)][1], Gd[m])
    assert many[1].samples == 0
    with pytest.raises(ValueError, match="twice"):
        add_strata(many, 0, 8, owner, reps, R, G)
    with pytest.raises(ValueError, match="sorted"):
        add_strata(many, 1, 8, owner[::-1], reps, R, G)


def test_covariance_of_cells_sharing_replicates():
    """Two cells whose replicate sums share a common factor (as cells sharing detector rays do):
    the estimated correlation of their ratios matches the scatter over many runs; cells in
    different strata have zero covariance; the diagonal is SE^2."""
    rng = np.random.default_rng(4)
    ra, rb, est = [], [], []
    for _ in range(300):
        common = rng.standard_normal(16)
        G = 1024 * (1 + 0.05 * rng.standard_normal(16))
        Ra = 0.8 * G * (1 + 0.02 * (common + 0.5 * rng.standard_normal(16)))
        Rb = 1.2 * G * (1 + 0.02 * (common + 0.5 * rng.standard_normal(16)))
        s = [CellStats(), CellStats(), CellStats()]
        add_strata(s, 0, 10, np.repeat([0, 1], 16), np.tile(np.arange(16), 2), np.r_[Ra, Rb], np.r_[G, G])
        s[2].add(1, 10, np.arange(16), Ra, G)          # another pass: independent shifts
        ratios = [x.ratio_se()[0] for x in s]
        cov = covariance(s, ratios)
        assert cov[0, 0] == pytest.approx(s[0].ratio_se()[1] ** 2, rel=1e-9, abs=0.0)
        assert cov[0, 2] == 0.0 and cov[1, 2] == 0.0
        ra.append(ratios[0])
        rb.append(ratios[1])
        est.append(cov[0, 1] / math.sqrt(cov[0, 0] * cov[1, 1]))
    emp = np.corrcoef(ra, rb)[0, 1]
    assert emp > 0.5 and abs(np.mean(est) - emp) < 0.1


def stats_with(rel, samples, log2n=6):
    """A CellStats whose relative SE is about ``rel`` after ``samples`` samples of lattice 2^log2n."""
    st = CellStats()
    reps = samples >> log2n
    k = np.arange(reps)
    dev = np.where(k % 2 == 0, 1.0, -1.0) * rel * math.sqrt(reps)
    G = np.full(reps, float(1 << log2n))
    R = G * (1.0 + dev)
    st.add(0, log2n, k, R, G)
    return st


def test_planner_first_pass_and_one_over_n_rule():
    pl = Planner(1e-3, first_pass=1024, min_replicates=16)
    assert pl.first(3) == {0: (6, 16), 1: (6, 16), 2: (6, 16)}
    st = [stats_with(0.5e-3, 1024), stats_with(2e-3, 1024), stats_with(1e-2, 1024)]
    rel = [relative(*s.ratio_se()[:2]) for s in st]
    req, done = pl.next(st, [0, 1, 2])
    assert done["converged"] == [0] and 0 not in req
    log2n, reps = req[1]
    want = 1024 * ((rel[1] / 1e-3) ** 2 - 1) * SAFETY
    assert want <= reps << log2n < want + (16 << log2n) and log2n >= 6 and reps >= 16
    log2n, reps = req[2]                                   # needs ~100x: capped at MAX_GROWTH
    assert (reps << log2n) <= MAX_GROWTH * 1024 + (1 << log2n)


def test_planner_never_shrinks_a_lattice_and_caps_samples():
    pl = Planner(1e-3, first_pass=1024, min_replicates=16, max_samples=1 << 16)
    st = [stats_with(1.05e-3, 1 << 14, log2n=10)]       # just above the target, on a large lattice
    req, _ = pl.next(st, [0])
    assert req[0][0] >= 10
    capped = [stats_with(5e-3, 1 << 16, log2n=10)]
    req, done = pl.next(capped, [0])
    assert done["capped"] == [0] and not req
    near = [stats_with(5e-3, (1 << 16) - 1024, log2n=6)]
    req, _ = pl.next(near, [0])
    assert sum(r << k for k, r in req.values()) <= 1024


def test_min_passes_keeps_a_converged_cell():
    pl = Planner(1e-3, first_pass=1024, min_passes=2)
    req, done = pl.next([stats_with(1e-4, 1024)], [0])
    assert 0 in req and not done["converged"]


def test_plan_round_trip_and_requests():
    plan = Plan([[(0, 6, 16), (1, 9, 20)], [(0, 6, 16)]])
    again = Plan.from_dict(plan.to_dict())
    assert again.cells == plan.cells and again.passes == 2
    assert again.pass_requests(1) == {0: (9, 20)} and again.pass_requests(0) == {0: (6, 16), 1: (6, 16)}


def test_cell_stats_survive_the_checkpoint_round_trip_exactly():
    """A table cut short between passes is resumed from CellStats.to_dict() (JSON): the ratio, its
    SE, the per-point variances, the covariance and the single-replicate flag come back exactly,
    and the resumed cell goes on as the uninterrupted one (mutation audit 9b: a reader dropping
    the flag of a stratum with one replicate, which turns an unknown SE into a finite one, passed
    every unit test)."""
    import json
    rng = np.random.default_rng(11)
    full = [CellStats() for _ in range(2)]
    for p, (log2n, b) in enumerate([(6, 16), (8, 20)]):
        R, G = synthetic(rng, 2 * b, n=1 << log2n)
        add_strata(full, p, log2n, np.repeat([0, 1], b), np.tile(np.arange(b), 2), R, G)
    one = CellStats()
    one.add(0, 6, np.arange(16), *synthetic(rng, 16, n=64))
    one.add(1, 9, np.arange(1), *synthetic(rng, 1, n=512))         # a stratum of one replicate
    stray = CellStats()                                              # with stray light: the direct sums too
    for p in range(2):
        R, G = synthetic(rng, 16)
        add_strata([stray], p, 8, np.zeros(16, dtype=np.int64), np.arange(16), R, G, 0.7 * R, 0.9 * G)
    for st in (*full, one, stray):
        back = CellStats.from_dict(json.loads(json.dumps(st.to_dict())))
        assert back.ratio_se() == st.ratio_se() and back.single == st.single
        # mutation audit 11: a reader swapping or dropping the direct sums passed every test
        assert back.direct_ratio_se() == st.direct_ratio_se() and back.stray_fraction_se() == st.stray_fraction_se()
        assert back.point_variances() == st.point_variances()
        assert (back.samples, back.passes, back.r0, back.sum_r, back.sum_g) == \
            (st.samples, st.passes, st.r0, st.sum_r, st.sum_g)
        np.testing.assert_array_equal(back.b, st.b)
    assert one.ratio_se()[1] == math.inf
    ratios = [s.ratio_se()[0] for s in full]
    back = [CellStats.from_dict(json.loads(json.dumps(s.to_dict()))) for s in full]
    np.testing.assert_array_equal(covariance(back, ratios), covariance(full, ratios))
    R, G = synthetic(rng, 32, n=1 << 10)                              # the next pass, on both
    add_strata(full, 2, 10, np.repeat([0, 1], 16), np.tile(np.arange(16), 2), R, G)
    add_strata(back, 2, 10, np.repeat([0, 1], 16), np.tile(np.arange(16), 2), R, G)
    assert [s.ratio_se() for s in back] == [s.ratio_se() for s in full]


def test_with_reflecting_parts_a_cell_converges_only_when_its_stray_light_is_seen():
    """(audit 22) Rare stray paths (a reflecting holder lit from few directions) left most replicate
    sums without stray light, so a cell met its SE target on the direct light and stopped with an
    SE that ignored the stray light (rms z 2.35 over 30 seeds). With ``stray_search`` a cell goes on,
    growing by MAX_GROWTH, until every replicate sum of its newest lattice carries stray light; at
    STRAY_SEARCH_MAX samples it stops as not converged (capped), or as converged when no replicate
    ever saw any (a part that sends nothing). Without reflecting parts nothing changes."""
    from roadgonio.engines.mitsuba.passes import STRAY_SEARCH_MAX
    rng = np.random.default_rng(3)

    def cell(seen: int, reps: int = 16, log2n: int = 6, passes: int = 1) -> CellStats:
        st = CellStats()
        for p in range(passes):
            Rd, Gd = synthetic(rng, reps, rel=1e-4, n=1 << log2n)
            stray = np.where(np.arange(reps) < seen, 1e-3, 0.0)
            add_strata([st], p, log2n + p, np.zeros(reps, dtype=np.int64), np.arange(reps),
                       Rd + stray, Gd + stray, Rd, Gd)
        return st

    planner = Planner(1e-2, first_pass=1024, stray_search=True)
    stats = [cell(16), cell(4), cell(0)]
    assert [s.stray_seen() for s in stats] == [1.0, 0.25, 0.0]
    req, done = planner.next(stats, [0, 1, 2])
    assert done == {"converged": [0], "capped": []} and set(req) == {1, 2}
    for i in (1, 2):
        log2n, reps = req[i]
        assert reps << log2n == pytest.approx(MAX_GROWTH * stats[i].samples, rel=0.01)
    # at the search's end: seen rarely, not converged; never seen, converged
    big = int(math.log2(STRAY_SEARCH_MAX // 16))
    late = [cell(4, log2n=big), cell(0, log2n=big)]
    req, done = planner.next(late, [0, 1])
    assert done == {"converged": [1], "capped": [0]} and not req
    assert late[1].stray_never_seen() and not late[0].stray_never_seen()
    # without reflecting parts (stray_search off) the SE alone decides, as before
    assert Planner(1e-2, first_pass=1024).next(stats, [0, 1, 2])[1]["converged"] == [0, 1, 2]
