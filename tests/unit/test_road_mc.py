"""The road Monte Carlo (roadgonio/road/mc.py) beyond linear propagation (tests/unit/test_road.py):
the clipping of trial values at r = 0 against the truncated normal in closed form, what is counted
as clipped, each lane's U_l against an independent simulation, TI's spread, the seed, the class
asked for, the probability's standard error and the class shares, metrics the nominal table lacks,
and the input checks. Mutation audit 10: each of these could be changed without any test failing."""
from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import pytest

from roadgonio.errors import InputError
from roadgonio.road import metrics
from roadgonio.road.evaluate import Installation
from roadgonio.road.layout import layout_from_dict, load_layout
from roadgonio.road.luminaire import load_luminaire
from roadgonio.road.mc import MIN_TRIALS, propagate
from roadgonio.surface.rtable import bundled_table

REL = 1e-12         # deterministic float64 arithmetic
N_SIGMA = 5.0       # a Monte Carlo mean or standard deviation against its exact value, in standard errors


@pytest.fixture(scope="module")
def default_installation():
    return Installation(load_layout(), load_luminaire())


def _truncated_moments(a: float, b: float) -> tuple[float, float]:
    """Mean and variance of max(a + b Z, 0), Z standard normal (b > 0)."""
    nd = NormalDist()
    k = a / b
    mean = a * nd.cdf(k) + b * nd.pdf(k)
    second = (a * a + b * b) * nd.cdf(k) + a * b * nd.pdf(k)
    return mean, second - mean * mean


def test_trial_values_below_zero_are_clipped_cell_by_cell():
    """One lane (one observer: L_av = a . r, linear) and linear interpolation (weights >= 0, so no
    luminance is ever negative and only the clipping of r acts). With u = 2 r and independent cells
    every trial cell is r max(1 + 2 z, 0): E[L_av] = L_av0 E[max(1 + 2 z, 0)] = 1.395 L_av0 and
    Var(L_av) = sum (a_c r_c)^2 Var(max(1 + 2 z, 0)). Without the clipping the mean stays at L_av0.
    The clipped count is that of the cells (with r > 0) drawn below zero: a fraction Phi(-1/2)."""
    lay = layout_from_dict({"road": {"lanes": 1}, "calculation": {"interpolation": "linear"}})
    inst = Installation(lay, load_luminaire())
    t = bundled_table("R3")
    op = inst.operator(t)
    assert op.W.shape[0] == 1 and op.W.min() >= 0.0
    n = 20000
    res = propagate(inst, t, t.with_values(2.0 * t.r), trials=n, seed=11, correlations=("independent",))
    a = op.W[0].mean(axis=0)                                  # dL_av / dr per cell (one observer)
    r = np.nan_to_num(t.r.ravel())
    l0 = float(a @ r)
    assert res["independent"]["L_av"]["nominal"] == pytest.approx(l0, rel=1e-9, abs=0.0)
    m1, var1 = _truncated_moments(1.0, 2.0)
    want_mean, want_u = l0 * m1, math.sqrt(var1 * float(np.sum((a * r) ** 2)))
    got = res["independent"]["L_av"]
    assert abs(got["mean"] - want_mean) < N_SIGMA * want_u / math.sqrt(n), (got["mean"], want_mean, l0)
    assert abs(got["u"] - want_u) < N_SIGMA * want_u / math.sqrt(2 * (n - 1)) * 1.5, (got["u"], want_u)
    used = op.used_cells
    positive = int(np.sum(r[used] > 0))
    p = NormalDist().cdf(-0.5)
    frac = res["independent"]["clipped_values"] / (n * positive)
    assert abs(frac - p) < N_SIGMA * math.sqrt(p * (1 - p) / (n * positive)), frac


def test_nothing_is_clipped_without_uncertainty_even_where_r_is_zero(default_installation):
    """A table with r = 0 in some cells the road uses and u = 0 everywhere: no trial value is below
    zero (0 is not clipped), and every trial is the nominal road."""
    inst = default_installation
    t = bundled_table("R3")
    used = inst.operator(t).used_cells
    r = t.r.copy().ravel()
    r[used[::7]] = 0.0
    t0 = t.with_values(r.reshape(t.r.shape))
    res = propagate(inst, t0, t0.with_values(np.zeros_like(t0.r)), trials=200, seed=1)
    nominal = inst.evaluate(t0).values
    for mode in ("independent", "correlated"):
        assert res[mode]["clipped_values"] == 0
        for k in ("L_av", "U_o", "U_l", "TI"):
            # every trial equal: u is the rounding of the mean of equal numbers
            assert res[mode][k]["u"] <= REL * nominal[k]
            assert res[mode][k]["mean"] == pytest.approx(nominal[k], rel=REL, abs=0.0)


def test_each_lanes_u_l_spread_is_that_lanes(default_installation):
    """U_l of each lane under independent cell noise against an independent simulation with the
    luminance operator (another random stream): the two lanes' spreads differ by about 20 % and each
    reported u must be its own lane's (the standard error of a standard deviation from the
    simulation's kurtosis)."""
    inst = default_installation
    t = bundled_table("R3")
    u = t.with_values(0.03 * t.r)
    n = 20000
    res = propagate(inst, t, u, trials=n, seed=5, correlations=("independent",))
    op = inst.operator(t)
    cells = op.used_cells
    r0 = np.nan_to_num(t.r.ravel()[cells])
    uv = np.nan_to_num(u.r.ravel()[cells])
    n_obs, n_p = op.W.shape[:2]
    wc = op.W.reshape(n_obs * n_p, -1)[:, cells]
    rng = np.random.default_rng(2024)
    ul = []
    for _ in range(n // 4000):
        rr = np.maximum(r0 + uv * rng.standard_normal((4000, len(cells))), 0.0)
        L = np.maximum(rr @ wc.T, 0.0).reshape(4000, n_obs, n_p)
        ul.append(metrics.luminance_metrics(L, inst.fld.lane, inst.fld.centre)["U_l_lane"])
    ul = np.concatenate(ul)
    lanes = res["independent"]["U_l_per_lane"]
    assert len(lanes) == ul.shape[1] == 2
    want = ul.std(axis=0, ddof=1)
    assert abs(want[0] - want[1]) > 0.1 * want.max()            # the lanes can be told apart
    for k in range(2):
        dev = ul[:, k] - ul[:, k].mean()
        kurt = np.mean(dev ** 4) / np.mean(dev ** 2) ** 2
        se_one = want[k] / 2 * math.sqrt((kurt - 1) / n)        # SE of one standard deviation
        assert abs(lanes[k]["u"] - want[k]) < N_SIGMA * math.sqrt(2) * se_one, (k, lanes[k]["u"], want)
        assert lanes[k]["nominal"] == pytest.approx(inst.evaluate(t).per_observer["U_l_lane"][k], rel=REL, abs=0.0)


def test_ti_follows_l_av_in_every_trial(default_installation):
    """Fully correlated u = 3 % r: every trial is L_av0 (1 + 0.03 z), so TI = TI0 (1 + 0.03 z)^-0.8
    (L_av / MF <= 5 cd/m^2): its standard deviation by Gauss-Hermite quadrature. A TI taken from the
    nominal L_av in every trial would have no spread."""
    inst = default_installation
    t = bundled_table("R3")
    n = 20000
    res = propagate(inst, t, t.with_values(0.03 * t.r), trials=n, seed=9, correlations=("correlated",))
    nominal = inst.evaluate(t).values
    assert nominal["L_av"] / inst.layout.maintenance_factor * 1.2 < 5.0
    x, w = np.polynomial.hermite_e.hermegauss(60)
    w = w / w.sum()
    f = (1 + 0.03 * x) ** -0.8
    sd = nominal["TI"] * math.sqrt(float(w @ f ** 2 - (w @ f) ** 2))
    got = res["correlated"]["TI"]
    assert abs(got["u"] - sd) < N_SIGMA * sd / math.sqrt(2 * (n - 1)), (got["u"], sd)
    assert abs(got["mean"] - nominal["TI"] * float(w @ f)) < N_SIGMA * sd / math.sqrt(n)


def test_the_seed_fixes_the_trials(default_installation):
    inst = default_installation
    t = bundled_table("R3")
    u = t.with_values(0.05 * t.r)
    a = propagate(inst, t, u, trials=500, seed=3)
    b = propagate(inst, t, u, trials=500, seed=3)
    c = propagate(inst, t, u, trials=500, seed=4)
    assert a == b
    assert a["independent"]["L_av"]["mean"] != c["independent"]["L_av"]["mean"]


def test_the_class_asked_for_is_the_one_judged(default_installation):
    """--class M1 on a table whose nominal class is M3: P(meets M1) is about that class (0 here: the
    nominal L_av is far below M1's 2 cd/m^2), not about the nominal class."""
    inst = default_installation
    t = bundled_table("R3")
    u = t.with_values(0.03 * t.r)
    assert inst.evaluate(t).cls == "M3"
    res = propagate(inst, t, u, trials=500, seed=2, target_class="M1")
    assert res["target_class"] == "M1" and res["correlated"]["P_meets_target"] == 0.0
    with pytest.raises(InputError, match="M9"):
        propagate(inst, t, u, trials=500, target_class="M9")


def test_probability_se_and_class_shares(default_installation):
    """P_meets_target_se = sqrt(P (1 - P) / n); the best-class shares are fractions of the trials
    (each a whole number of trials, together all of them)."""
    inst = default_installation
    t = bundled_table("R3")
    n = 1000
    res = propagate(inst, t, t.with_values(0.1 * t.r), trials=n, seed=6)
    for mode in ("independent", "correlated"):
        m = res[mode]
        p = m["P_meets_target"]
        assert 0.0 < p < 1.0
        assert m["P_meets_target_se"] == pytest.approx(math.sqrt(p * (1 - p) / n), rel=REL, abs=0.0)
        shares = m["best_class_share"]
        assert sum(shares.values()) == pytest.approx(1.0, rel=0.0, abs=1e-12)
        for v in shares.values():
            assert 0.0 < v <= 1.0 and v * n == pytest.approx(round(v * n), rel=0.0, abs=1e-9)


def test_metrics_the_nominal_table_lacks_have_no_uncertainty(default_installation):
    """A table blank in a cell the road needs: L_av, U_o, U_l, TI and the class are missing for
    the table itself, so the Monte Carlo gives no value or probability for them either (a blank is
    no r = 0)."""
    inst = default_installation
    t = bundled_table("R3")
    r = t.r.copy()
    r[int(np.argmin(abs(t.tan_eps - 5.0))), 0] = np.nan      # tan eps 5, beta 0: the luminance needs it
    tb = t.with_values(r)
    nominal = inst.evaluate(tb)
    assert nominal.missing and {"L_av", "U_o", "TI"} <= set(nominal.missing["metrics"])
    u = np.nan_to_num(0.03 * tb.r)                   # u = 0 at the blank: a number in every used cell
    res = propagate(inst, tb, tb.with_values(u), trials=200, seed=1)
    for mode in ("independent", "correlated"):
        for k in nominal.missing["metrics"]:
            if k != "class":
                assert res[mode][k] is None, (mode, k)
        assert res[mode]["P_meets_target"] is None and res[mode]["best_class_share"] is None


def test_negative_uncertainty_and_too_few_trials_are_refused(default_installation):
    inst = default_installation
    t = bundled_table("R3")
    used = inst.operator(t).used_cells
    i, j = np.unravel_index(used[3], t.r.shape)
    ur = 0.01 * t.r
    ur[i, j] = -1e-4
    with pytest.raises(InputError, match=f"tan eps = {t.tan_eps[i]:g}, beta = {t.beta_deg[j]:g}"):
        propagate(inst, t, t.with_values(ur), trials=200)
    u = t.with_values(0.01 * t.r)
    assert propagate(inst, t, u, trials=MIN_TRIALS, seed=1)["trials"] == MIN_TRIALS
    with pytest.raises(InputError, match=f"at least {MIN_TRIALS} trials"):
        propagate(inst, t, u, trials=MIN_TRIALS - 1)


def test_ti_takes_the_initial_l_av(default_installation):
    """EN 13201-3 / CIE 140: TI from initial values; the layout's L_av is maintained (x MF), so TI =
    65 L_v / (L_av / MF)^0.8 (L_av / MF <= 5 cd/m^2), with L_v the largest veiling luminance of the
    observer positions (initial: computed with MF = 1)."""
    inst = default_installation
    v = inst.evaluate(bundled_table("R3")).values
    mf = inst.layout.maintenance_factor
    assert mf == 0.8 and v["L_av"] / mf <= 5.0
    assert v["TI"] == pytest.approx(65.0 * inst.l_v_max / (v["L_av"] / mf) ** 0.8, rel=REL, abs=0.0)


def test_trials_without_light_are_counted_not_a_reason_to_drop_the_metric(default_installation):
    """Trial 11 D1: fully correlated u, a trial with z < -1/u_rel clips every cell to 0: no light, U_o
    and U_l are 0/0 and TI infinite; that one trial dropped U_o, U_l and TI from the results (null,
    depending on the seed). With u = 0.6 r in every cell, each trial is max(1 + 0.6 z, 0) x the
    nominal luminance: U_o and U_l are the nominal ones in every lit trial (u 0), the unlit trials
    are a fraction Phi(-1/0.6) (binomial), counted per metric and said in a note, and P(meets) counts
    them as failing."""
    inst = default_installation
    t = bundled_table("R3")
    n = 4000
    res = propagate(inst, t, t.with_values(0.6 * t.r), trials=n, seed=3, correlations=("correlated",))
    m = res["correlated"]
    nominal = inst.evaluate(t)
    p = NormalDist().cdf(-1.0 / 0.6)
    dark = m["U_o"]["undefined_trials"]
    assert abs(dark - n * p) < N_SIGMA * math.sqrt(n * p * (1 - p)), dark
    assert dark > 0 and m["undefined_trials"] == {"U_o": dark, "U_l": dark, "TI": dark}
    for k in ("U_o", "U_l"):
        assert m[k]["undefined_trials"] == dark
        assert m[k]["mean"] == pytest.approx(nominal.values[k], rel=REL, abs=0.0)
        assert m[k]["u"] <= REL * nominal.values[k]
    for k, lane in enumerate(m["U_l_per_lane"]):
        assert lane["undefined_trials"] == dark and lane["u"] <= REL
        assert lane["nominal"] == pytest.approx(nominal.per_observer["U_l_lane"][k], rel=REL, abs=0.0)
    assert m["TI"] is not None and m["TI"]["undefined_trials"] == dark and math.isfinite(m["TI"]["u"])
    assert m["L_av"]["undefined_trials"] == 0
    assert m["P_meets_target"] <= 1.0 - dark / n
    assert f"no value in {dark} of {n} trials" in m["note"] and "U_o, U_l and TI" in m["note"]
    quiet = propagate(inst, t, t.with_values(0.03 * t.r), trials=500, seed=3, correlations=("correlated",))
    assert quiet["correlated"]["note"] is None and quiet["correlated"]["undefined_trials"] == {}


# ----------------------------------------------------------------------------------------------
# the cells' correlation given (trial 11 D6: correct writes corrected_corr.csv, road could not read it)
# ----------------------------------------------------------------------------------------------

def _two_groups(t):
    """The tabulated cells of ``t`` and a correlation of two groups, beta < 15 deg and the rest: fully
    correlated within a group, fully anti-correlated between them (rank 1: sign_i sign_j)."""
    ii, jj = np.nonzero(t.mask)
    cells = [(float(t.tan_eps[i]), float(t.beta_deg[j])) for i, j in zip(ii, jj)]
    sign = np.where(t.beta_deg[jj] < 15.0, 1.0, -1.0)
    return cells, np.outer(sign, sign), sign, np.ravel_multi_index((ii, jj), t.r.shape)


def test_a_given_correlation_is_propagated_and_the_limiting_cases_are_no_bounds(default_installation):
    """u = 3 % r, correlation w s s^T + (1 - w) I (s_i the sign of the cell's group in _two_groups,
    plus independent noise): L_av is (nearly) linear, so u(L_av)^2 = w (sum_i c_i s_i)^2 + (1 - w)
    sum_i c_i^2 (c_i = a_i u_i, a_i = dL_av / dr_i of the operative observer). With w = 1 that is
    0.0030: below the independent case's 0.0040 and far below the fully correlated 0.033, and u(U_o)
    is above both limiting cases (independent 0.0094, fully correlated 0). With w = 0.5 (0.0035) the
    eigenvalues differ, so a square root of the matrix taken wrongly (no square root of the
    eigenvalues: 0.0030) fails, as does one that ignores the matrix."""
    inst = default_installation
    t = bundled_table("R3")
    cells, groups, sign, flat = _two_groups(t)
    op = inst.operator(t)
    o = int(np.argmin(inst.evaluate(t).per_observer["L_av_obs"]))
    c = (op.W[o].mean(axis=0) * np.nan_to_num(0.03 * t.r.ravel()))[flat]
    n = 20000
    for w, modes in ((1.0, ("independent", "correlated", "given")), (0.5, ("given",))):
        corr = w * groups + (1 - w) * np.eye(len(cells))
        res = propagate(inst, t, t.with_values(0.03 * t.r), trials=n, seed=7, corr=(cells, corr), correlations=modes)
        want = math.sqrt(w * float(c @ sign) ** 2 + (1 - w) * float(c @ c))
        got = res["given"]["L_av"]["u"]
        assert abs(got - want) < N_SIGMA * want / math.sqrt(2 * (n - 1)), (w, got, want)
        if w == 1.0:        # the case: outside both limiting cases
            assert want < 0.8 * res["independent"]["L_av"]["u"]
            assert res["given"]["U_o"]["u"] > 1.2 * res["independent"]["U_o"]["u"] > 1.2 * res["correlated"]["U_o"]["u"]
        else:
            assert abs(want - abs(float(c @ sign))) > 20 * want / math.sqrt(2 * (n - 1))   # the mutant is told apart


def test_a_fully_correlated_matrix_given_is_the_fully_correlated_case(default_installation):
    """A matrix of ones (every cell fully correlated, all eigenvalues 0 but one) given: every trial
    scales the table, so U_o and U_l do not move (u below rounding), as in the 'correlated' case."""
    inst = default_installation
    t = bundled_table("R3")
    cells, corr, _, _ = _two_groups(t)
    res = propagate(inst, t, t.with_values(0.03 * t.r), trials=500, seed=2, corr=(cells, np.abs(corr)),
                    correlations=("given",))
    nominal = inst.evaluate(t).values
    for k in ("U_o", "U_l"):
        assert res["given"][k]["u"] <= REL * nominal[k]
    assert res["given"]["L_av"]["u"] > 0.01 * nominal["L_av"]


def test_the_correlation_file_correct_writes_is_what_road_reads(tmp_path):
    """corrected_corr.csv (correct's writer, from a budget with a systematic component) read back by
    road's reader: the same cells in the same order and the matrix to the stored rounding."""
    from roadgonio.correction.budget import Budget
    from roadgonio.correction.outputs import _correlation_text
    from roadgonio.surface.rtable import CORR_ROUNDING, read_cell_correlation
    t = bundled_table("R3")
    n = int(t.mask.sum())
    b = Budget(n)
    b.add("measurement", np.full(n, 0.01))
    b.add_systematic("model", np.linspace(-0.02, 0.03, n))
    path = tmp_path / "corrected_corr.csv"
    head = "R3 corrected for the aperture effect (r / k_A; reference self; instrument portable)"
    path.write_text(_correlation_text(t, b, t.with_values(t.r, source=head + "\nsecond line")))
    assert path.read_text().splitlines()[0] == "# correlation of the cells of " + head
    cells, c = read_cell_correlation(path, table=head)
    assert cells == [(float(x), float(y)) for x, y in t.cells]
    assert np.max(np.abs(c - b.correlation())) <= CORR_ROUNDING * (1 + 1e-9)
    assert np.min(c) < -0.5                                      # mixed signs survive the round trip


def test_a_correlation_file_that_names_another_table_is_refused(tmp_path):
    """corrected_corr.csv names its table on its first line, as corrected_u.csv does; read for
    another table it is refused in one line naming the file, the line and both tables. A file
    without the name (before it was written), or read without a table to compare, is read."""
    from helpers import refused_in_one_line

    from roadgonio.surface.rtable import correlation_text, read_cell_correlation
    cells = [(0.0, 0.0), (0.0, 2.0), (0.25, 0.0)]
    named = tmp_path / "named.csv"
    named.write_text(correlation_text(cells, np.eye(3), table="A corrected for the aperture effect (r / k_A; x)"))
    refused_in_one_line(lambda: read_cell_correlation(named, table="B corrected for the aperture effect (r / k_A; x)"),
                        named, [f"{named}:1", "correlation of the cells of 'A corrected", "header says 'B corrected"])
    assert read_cell_correlation(named, table="A corrected for the aperture effect (r / k_A; x)")[0] == cells
    assert read_cell_correlation(named)[0] == cells
    old = tmp_path / "old.csv"
    old.write_text(correlation_text(cells, np.eye(3)))
    assert old.read_text().startswith("# correlation of the corrected cells")
    assert read_cell_correlation(old, table="B corrected for the aperture effect (r / k_A; x)")[0] == cells


@pytest.mark.parametrize("edit,words", [
    (lambda rows: rows[:1] + [rows[1].replace("cell,", "cells,")] + rows[2:], ["header 'cell,"]),
    (lambda rows: rows[:1] + [rows[1].replace(",0/2,", ",0/3,")] + rows[2:], ["'0/3' is not on the standard grid"]),
    (lambda rows: rows[:3] + [rows[3].replace("0/2,", "0/5,", 1)] + rows[4:], ["row 2 must be labelled '0/2'"]),
    (lambda rows: rows[:2] + [rows[2].replace("1.0000", "0.9000", 1)] + rows[3:], ["'0/0'", "diagonal must be 1"]),
    (lambda rows: rows[:2] + [rows[2][:-6] + "0.5000"] + rows[3:], ["symmetric"]),
    (lambda rows: rows[:2] + [rows[2][:-6] + "1.5000"] + rows[3:], ["between -1 and 1"]),
    (lambda rows: rows[:2] + [rows[2][:-6] + "abc"] + rows[3:], ["expected a number"]),
    (lambda rows: rows[:-1], ["expected 3 rows"]),
])
def test_a_bad_correlation_file_is_refused_in_one_line(tmp_path, edit, words):
    from helpers import refused_in_one_line

    from roadgonio.surface.rtable import correlation_text, read_cell_correlation
    rows = correlation_text([(0.0, 0.0), (0.0, 2.0), (0.25, 0.0)], np.eye(3)).splitlines()
    path = tmp_path / "corr.csv"
    path.write_text("\n".join(edit(rows)) + "\n")
    refused_in_one_line(lambda: read_cell_correlation(path), path, words)


def test_a_correlation_that_lacks_a_used_cell_or_is_no_correlation_matrix_is_refused(default_installation, tmp_path):
    """A used cell without a row, and a matrix with an eigenvalue below what the 4-decimal rounding
    can make (three cells pairwise correlated -0.9): one line naming the file and what was expected."""
    from helpers import refused_in_one_line
    inst = default_installation
    t = bundled_table("R3")
    u = t.with_values(0.03 * t.r)
    cells, corr, _, _ = _two_groups(t)
    path = tmp_path / "corrected_corr.csv"
    used = inst.operator(t).used_cells
    at = {c: k for k, c in enumerate(cells)}
    i, j = np.unravel_index(used[0], t.r.shape)
    gone = at[(float(t.tan_eps[i]), float(t.beta_deg[j]))]
    keep = [k for k in range(len(cells)) if k != gone]
    refused_in_one_line(lambda: propagate(inst, t, u, trials=200, corr=([cells[k] for k in keep], corr[np.ix_(keep, keep)]),
                                          corr_path=path, correlations=("given",)),
                        path, [f"no row for tan eps {t.tan_eps[i]:g}, beta {t.beta_deg[j]:g}", "a cell the road uses"])
    bad = np.eye(len(cells))
    ii, jj = np.unravel_index(used[:3], t.r.shape)
    k3 = [at[(float(t.tan_eps[i]), float(t.beta_deg[j]))] for i, j in zip(ii, jj)]
    for x in k3:
        for y in k3:
            if x != y:
                bad[x, y] = -0.9
    refused_in_one_line(lambda: propagate(inst, t, u, trials=200, corr=(cells, bad), corr_path=path,
                                          correlations=("given",)),
                        path, ["not a correlation matrix", "smallest eigenvalue"])
    with pytest.raises(InputError, match="needs the cells' correlation"):
        propagate(inst, t, u, trials=200, correlations=("given",))
