"""JCGM 101:2008 statistics of the Monte Carlo trials: coverage intervals, numerical tolerance."""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from roadgonio.errors import InputError

# ----------------------------------------------------------------------------------------------
# Statistics (JCGM 101 7.6-7.7)
# ----------------------------------------------------------------------------------------------

def coverage_indices(M: int, p: float) -> tuple[int, int]:
    """(q, r) of JCGM 101 7.7: q = pM rounded (pM if integer, else floor(pM + 1/2)); the
    probabilistically symmetric interval is [y_(r), y_(r+q)] with r = (M - q)/2 if integer, else
    (M - q + 1)/2 (1-based order statistics)."""
    pm = p * M
    q = int(round(pm)) if abs(pm - round(pm)) < 1e-9 else int(math.floor(pm + 0.5))
    q = min(max(q, 1), M - 1)
    r = (M - q) // 2 if (M - q) % 2 == 0 else (M - q + 1) // 2
    return q, max(r, 1)


def summarize(Y: np.ndarray, p: float = 0.95, threads: int = 1, rows: int = 8) -> dict[str, np.ndarray]:
    """Mean, standard uncertainty (ddof 1), probabilistically symmetric and shortest 100p %
    coverage intervals of each row of Y (n_out, M) (JCGM 101 7.6, 7.7).

    Only the lowest and the highest M - q values of each row are sorted (np.partition first),
    which is all the two intervals need. Rows are processed in small blocks (cache), optionally
    in threads; the result does not depend on ``threads`` or ``rows``.
    """
    Y = np.asarray(Y, dtype=np.float64)
    n, M = Y.shape
    if M < 2:
        raise InputError(f"expected at least 2 Monte Carlo values, got {M}", field="trials")
    q, r = coverage_indices(M, p)
    k = M - q                        # number of candidate lower ends
    out = {key: np.empty(n) for key in ("mean", "u", "sym_low", "sym_high", "short_low", "short_high")}

    def block(a: int) -> None:
        b = min(n, a + rows)
        y = Y[a:b]
        mean = y.mean(axis=1)
        d = y - mean[:, None]
        out["mean"][a:b] = mean
        out["u"][a:b] = np.sqrt(np.einsum("ij,ij->i", d, d) / (M - 1))
        part = np.partition(y, [k - 1, q], axis=1)
        low = np.sort(part[:, :k], axis=1)       # y_(1) .. y_(k)
        high = np.sort(part[:, q:], axis=1)      # y_(q+1) .. y_(M)
        out["sym_low"][a:b] = low[:, r - 1]
        out["sym_high"][a:b] = high[:, r - 1]    # y_(r+q)
        js = np.argmin(high - low, axis=1)       # shortest y_(j+q) - y_(j), j = 1..k
        idx = np.arange(b - a)
        out["short_low"][a:b] = low[idx, js]
        out["short_high"][a:b] = high[idx, js]

    starts = range(0, n, rows)
    if threads > 1 and n > rows:
        with ThreadPoolExecutor(threads) as ex:
            list(ex.map(block, starts))
    else:
        for a in starts:
            block(a)
    return out


#: a u below this fraction of the value is round-off of float64 arithmetic, not an uncertainty
#: (Q0 under errors of the source distance with the illuminance measured in situ: 1e-17)
ROUND_OFF_REL = 1e-12

#: The batches a run's trials are split into to measure the Monte Carlo noise of its interval ends
#: (JCGM 101 7.9.4 compares h batches the same way): 20, so that s itself has 19 degrees of freedom
#: (an adaptive run's own batches can be as few as 2).
END_NOISE_BATCHES = 20


def batch_spread(values: np.ndarray) -> np.ndarray:
    """s of JCGM 101 7.9.4 f): the standard deviation of h batch results (rows) over sqrt(h), per
    column; exactly 0 where every batch gave the same number (an output the trials do not move: the
    standard deviation of equal floats is round-off, 1e-18, not 0, which made a tolerance of 0 fail)."""
    v = np.asarray(values, dtype=np.float64)
    h = v.shape[0]
    s = v.std(axis=0, ddof=1) / math.sqrt(h)
    return np.where(np.ptp(v, axis=0) == 0, 0.0, s)


def batch_noise(Y: np.ndarray, p: float, batches: int = END_NOISE_BATCHES) -> dict[str, np.ndarray]:
    """The Monte Carlo's own noise per row of Y (n_out, M), from ``batches`` contiguous equal batches
    of the trials (:func:`batch_spread`, JCGM 101 7.9.4): ``end_noise``, 2 s of the probabilistically
    symmetric interval's ends, the larger of the two (the comparison of JCGM 101 section 8 is decided
    by it where it exceeds the tolerance delta); ``mean_se`` and ``u_se``, s of the mean and of u, their
    standard errors (user audit, session 41: no output gave the standard error of u). Fewer than 2
    trials a batch: inf."""
    Y = np.asarray(Y, dtype=np.float64)
    M = Y.shape[1]
    h = min(int(batches), M // 2)
    if h < 2:
        inf = np.full(Y.shape[0], np.inf)
        return {"end_noise": inf, "mean_se": inf.copy(), "u_se": inf.copy()}
    m = M // h
    parts = [summarize(Y[:, b * m:(b + 1) * m], p) for b in range(h)]
    lo = batch_spread(np.stack([e["sym_low"] for e in parts]))
    hi = batch_spread(np.stack([e["sym_high"] for e in parts]))
    return {"end_noise": 2.0 * np.maximum(lo, hi), "mean_se": batch_spread(np.stack([e["mean"] for e in parts])),
            "u_se": batch_spread(np.stack([e["u"] for e in parts]))}


def numerical_tolerance(u: np.ndarray, n_dig: int) -> np.ndarray:
    """delta of JCGM 101 7.9.2: u = c x 10^l with c an n_dig-digit integer, delta = 10^l / 2."""
    u = np.asarray(u, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ell = np.floor(np.log10(np.abs(u))) - (n_dig - 1)
        c = np.round(np.abs(u) / 10.0 ** ell)
        ell = np.where(c >= 10 ** n_dig, ell + 1, ell)
        delta = 0.5 * 10.0 ** ell
    return np.where(np.isfinite(delta) & (u > 0), delta, 0.0)


