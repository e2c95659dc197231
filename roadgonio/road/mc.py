"""Monte Carlo propagation of an r-table's standard uncertainty into L_av, U_o, U_l, TI and the class.

Every trial draws a table r + u z (z standard normal) and evaluates the road with the same
luminance operator (luminance is linear in r, so a trial is one matrix product). Trial values
below 0 are set to 0 (r >= 0; the count is reported); a trial left without light on the field
or a lane's centre line has no uniformity and no TI there, and is counted, not dropped silently
(``undefined_trials``, ``note``). The cells' correlation: given, or, when it is not known, two
limiting cases (a table's cells share calibration and reference-model errors but also have
independent noise):

* ``independent``: every cell its own z (uncorrelated cells, e.g. Monte Carlo noise of k_A);
* ``correlated``: one z for all cells (fully correlated: every cell moves by its own u in the
  same direction, e.g. a common calibration or reference-model error);
* ``given``: z with the correlation matrix of the cells that ``roadgonio correct`` writes
  (corrected_corr.csv), through a square root of the matrix (:func:`correlation_factor`).

The first two are limiting cases, not bounds: for L_av (and TI, which follows it) they bound u when
every correlation and every cell's weight in the luminance is >= 0 (the quadratic interpolation's
negative weights carry ~4 % of the default layout's luminance: approximately), but for the
uniformities the fully correlated case gives the smaller u (a common factor cancels in a ratio),
and a correlation of mixed signs can give a u outside both (docs/road.md).

Reported per metric: the nominal value, the trials' mean and standard deviation (the standard
uncertainty), the 2.5 / 97.5 % quantiles (``coverage_interval_95``: JCGM 101's probabilistically
symmetric 95 % coverage interval, not a confidence interval), and the probability that the design
meets a class (the fraction of trials that meet every computable criterion). The Monte Carlo
standard error of a probability P from n trials is sqrt(P (1 - P) / n).
"""
from __future__ import annotations

import numpy as np

from roadgonio.errors import InputError
from roadgonio.road import metrics
from roadgonio.surface.rtable import CORR_DIGITS, CORR_ROUNDING, RTable

#: The cases of the cells' correlation: independent cells, fully correlated cells (one z for all),
#: and a given correlation matrix (``roadgonio correct``'s corrected_corr.csv).
CORRELATIONS = ("independent", "correlated", "given")
BATCH = 4000


def correlation_factor(cells, corr: np.ndarray, table: RTable, used: np.ndarray, path=None) -> np.ndarray:
    """F with F F^T the correlation of the ``used`` cells (flat indices into ``table``'s grid), from a
    correlation matrix over ``cells`` ((tan eps, beta) pairs), so that F g (g standard normal) are
    correlated unit normals. Eigenvalues below 0 down to -n :data:`CORR_ROUNDING` (what rounding the
    stored values can make of a positive semidefinite matrix of n cells) and those below the
    matrix's numerical rank (n eps of the largest) are set to 0 and each row scaled back to unit
    variance; a more negative one means the file is no correlation matrix: an
    :class:`InputError`. A used cell the file lacks is one too."""
    at = {(round(float(t), 6), round(float(b), 6)): k for k, (t, b) in enumerate(cells)}
    ii, jj = np.unravel_index(used, table.r.shape)
    idx = [at.get((round(float(table.tan_eps[i]), 6), round(float(table.beta_deg[j]), 6)), -1) for i, j in zip(ii, jj)]
    lacking = [k for k, x in enumerate(idx) if x < 0]
    if lacking:
        i, j = ii[lacking[0]], jj[lacking[0]]
        raise InputError(f"no row for tan eps {table.tan_eps[i]:g}, beta {table.beta_deg[j]:g}, a cell the road uses "
                         f"({len(lacking)} such cells); expected the correlation of the table's cells, as correct "
                         "writes corrected_corr.csv beside corrected_u.csv", path=path, argument="corr")
    c = corr[np.ix_(idx, idx)]
    c = 0.5 * (c + c.T)
    lam, vec = np.linalg.eigh(c)
    floor = -len(idx) * CORR_ROUNDING
    if lam[0] < floor:
        raise InputError(f"not a correlation matrix: over the {len(idx)} cells the road uses its smallest eigenvalue "
                         f"is {lam[0]:.3g} (expected >= {floor:.3g}, what the rounding to {CORR_DIGITS} decimals can "
                         "give a positive semidefinite matrix)", path=path, argument="corr")
    keep = lam > len(idx) * np.finfo(float).eps * lam[-1]      # the matrix's numerical rank: the rest is rounding
    f = vec[:, keep] * np.sqrt(lam[keep])
    return f / np.linalg.norm(f, axis=1, keepdims=True)


def check_u_table(table: RTable, u: RTable, cells: np.ndarray, path=None) -> np.ndarray:
    """u (sr^-1) on ``cells`` (flat indices); every cell the road uses needs a finite u >= 0."""
    if not table.same_grid(u):
        raise InputError("the uncertainty table is not on the table's grid", path=path)
    uv = u.r.reshape(-1)[cells]
    bad = ~np.isfinite(uv) | (uv < 0)
    if np.any(bad):
        i, j = np.unravel_index(cells[np.nonzero(bad)[0][0]], table.r.shape)
        raise InputError(f"no standard uncertainty at tan eps = {table.tan_eps[i]:g}, beta = {table.beta_deg[j]:g}, "
                         f"a cell the road calculation uses ({int(bad.sum())} such cells); expected u >= 0 (r x 1e4) "
                         "in every tabulated cell", path=path)
    return uv


#: The fewest Monte Carlo trials that give a 95 % interval at all.
MIN_TRIALS = 100


def _statistics(v: np.ndarray, nominal: float) -> dict | None:
    """Mean, u and 95 % interval of one metric over the trials in which it has a value: a
    uniformity of a trial without light on the field or a lane's centre line is 0/0 and its TI
    infinite (trial 11 D1: one fully correlated trial with z < -1/u_rel clips every cell to 0).
    Those trials are counted (``undefined_trials``), never a reason to drop the metric; with fewer
    than :data:`MIN_TRIALS` trials with a value there is no interval: None."""
    ok = np.isfinite(v)
    if int(ok.sum()) < MIN_TRIALS:
        return None
    w = v[ok]
    lo, hi = np.quantile(w, [0.025, 0.975])
    return {"nominal": nominal, "mean": float(w.mean()), "u": float(w.std(ddof=1)),
            "coverage_interval_95": [float(lo), float(hi)], "undefined_trials": int(v.size - w.size)}


def _lane_statistics(v: np.ndarray, nominal: float) -> dict | None:
    """One lane's U_l: nominal and u over the trials with light on its centre line (:func:`_statistics`)."""
    st = _statistics(v, nominal)
    return None if st is None else {"nominal": nominal, "u": st["u"], "undefined_trials": st["undefined_trials"]}


def _undefined_note(undefined: dict, trials: int, target: str) -> str | None:
    """What the trials without a value of some metric mean for the results (None when there are none)."""
    if not undefined:
        return None
    keys = list(undefined)
    names = keys[0] if len(keys) == 1 else ", ".join(keys[:-1]) + " and " + keys[-1]
    counts = sorted(set(undefined.values()))
    n = " to ".join(str(c) for c in (counts[0], counts[-1])) if len(counts) > 1 else str(counts[0])
    return (f"{names} {'has' if len(undefined) == 1 else 'have'} no value in {n} of {trials} trials (no light on the "
            f"field or on a lane's centre line: the cells the road uses drawn at or below r = 0): "
            f"{'its' if len(undefined) == 1 else 'their'} mean, u and interval are of the other trials "
            f"(none where fewer than {MIN_TRIALS} are left), and P(meets {target}) counts those trials as failing")


def propagate(installation, table: RTable, u: RTable, *, trials: int = 20000, seed: int = 0,
              correlations=("independent", "correlated"), target_class: str | None = None, u_path=None,
              corr=None, corr_path=None) -> dict:
    """Monte Carlo of the road metrics under the table's standard uncertainty ``u`` (an RTable of
    u in sr^-1 on the same grid), for each case of ``correlations`` (:data:`CORRELATIONS`; "given"
    needs ``corr``: (cells, matrix) of :func:`roadgonio.surface.rtable.read_cell_correlation`, read
    from ``corr_path``). Returns a JSON-ready dict."""
    if trials < MIN_TRIALS:
        raise InputError(f"expected at least {MIN_TRIALS} trials, got {trials}", field="trials")
    if seed < 0:
        raise InputError(f"expected a seed >= 0, got {seed}", field="seed")
    op = installation.operator(table)
    cells = op.used_cells
    r0 = np.nan_to_num(table.r.reshape(-1)[cells], nan=0.0)
    uv = check_u_table(table, u, cells, u_path)
    n_obs, n_p = op.W.shape[:2]
    Wc = op.W.reshape(n_obs * n_p, -1)[:, cells]
    fld = installation.fld
    nominal = installation.evaluate(table)
    target = target_class or nominal.cls or "M6"
    if target not in metrics.M_CLASSES:
        raise InputError(f"unknown class {target!r}; expected one of {', '.join(metrics.M_CLASSES)}", field="class")
    out = {"trials": trials, "seed": seed, "target_class": target, "u_cells_used": int(len(cells)),
           "u_rel_median_used_cells": float(np.median(uv / np.where(r0 > 0, r0, np.nan))),
           "method": "Monte Carlo, r + u z per trial, r clipped at 0; luminance linear in r"}
    for mode in correlations:
        if mode not in CORRELATIONS:
            raise InputError(f"unknown correlation {mode!r}; expected {' | '.join(CORRELATIONS)}", field="correlation")
    factor = None
    if "given" in correlations:
        if corr is None:
            raise InputError("the correlation 'given' needs the cells' correlation (corr: a file as correct writes "
                             "corrected_corr.csv)", field="correlation")
        factor = correlation_factor(*corr, table, cells, path=corr_path)
        out["correlation_file"] = None if corr_path is None else str(corr_path)
    rng = np.random.default_rng(seed)
    for mode in correlations:
        acc = {k: [] for k in ("L_av", "U_o", "U_l", "TI")}
        lanes = []
        clipped = 0
        for start in range(0, trials, BATCH):
            n = min(BATCH, trials - start)
            if mode == "given":
                z = rng.standard_normal((n, factor.shape[1])) @ factor.T
            else:
                z = rng.standard_normal((n, len(cells)) if mode == "independent" else (n, 1))
            r = r0 + uv * z
            clipped += int(np.sum(r < 0))
            r = np.maximum(r, 0.0)
            L = np.maximum(r @ Wc.T, 0.0).reshape(n, n_obs, n_p)     # as the nominal: no negative luminance
            m = metrics.luminance_metrics(L, fld.lane, fld.centre)
            for k in ("L_av", "U_o", "U_l"):
                acc[k].append(m[k])
            ti = installation.ti(m["L_av"])
            acc["TI"].append(None if ti is None else np.asarray(ti))
            lanes.append(m["U_l_lane"])
        vals = {k: (np.concatenate(v) if v[0] is not None else None) for k, v in acc.items()}
        vals["R_EI"] = installation.edge["R_EI"]
        res = {}
        gone = set((nominal.missing or {}).get("metrics", ()))
        undefined = {}
        for k in ("L_av", "U_o", "U_l", "TI"):
            v = vals[k]
            if v is None or k in gone:    # not computable, or missing in the nominal table itself
                res[k] = None
                continue
            res[k] = _statistics(v, nominal.values[k])
            if res[k] is None or res[k]["undefined_trials"]:
                undefined[k] = int(np.sum(~np.isfinite(v)))
        ul = np.concatenate(lanes)
        res["U_l_per_lane"] = [None if not np.isfinite(nominal.per_observer["U_l_lane"][k]) else
                               _lane_statistics(ul[:, k], float(nominal.per_observer["U_l_lane"][k]))
                               for k in range(ul.shape[1])]
        res["undefined_trials"] = undefined
        res["note"] = _undefined_note(undefined, trials, target)
        if gone:          # the class needs every metric: no probability of meeting it
            res["P_meets_target"] = res["P_meets_target_se"] = res["best_class_share"] = None
        else:
            p = float(np.mean(metrics.meets_array(target, vals)))
            res["P_meets_target"] = p
            res["P_meets_target_se"] = float(np.sqrt(p * (1 - p) / trials))
            best = metrics.best_class_array(vals)
            names = list(metrics.M_CLASSES) + ["none"]
            res["best_class_share"] = {names[k]: float(np.mean(best == k)) for k in range(len(names))
                                       if np.any(best == k)}
        res["clipped_values"] = clipped
        out[mode] = res
    return out
