"""The tolerances of the tests, in one place (``from tolerances import N_SIGMA, z_family``; tests/ is
on sys.path, pytest puts the folder of the root conftest.py there).

Statistical tolerances
----------------------
A Monte Carlo result is judged by its standard error (SE): a check reads
``|a - b| <= N_SIGMA * SE`` (plus the other side's deterministic error bound and any named floor,
never an SE standing in for a bound). For a correct estimator with a normal error, one such check
fails with probability ALPHA = 2 (1 - Phi(N_SIGMA)) = 6.3e-5 (two-sided): with fixed seeds a test
is deterministic, and a new seed or platform rarely turns a correct test red.

Table-wide checks. A test that compares m cells (or m values) at once, each against its own SE,
and fails when any one of them is outside, would fail about m times as often (m = 580 cells at
4 SE: 3.6 %). Such a test uses the per-cell threshold ``z_family(m)`` instead: Sidak's correction,
the z with 1 - (1 - ALPHA(z))^m = ALPHA, so that the probability that any of m independent correct
cells fails equals that of a single N_SIGMA check. z_family(1) = 4, z_family(5) = 4.37,
z_family(30) = 4.74, z_family(580) = 5.31. Cells that share random numbers are positively
correlated; for them Sidak's threshold is conservative (the family-wise rate is lower). A test
making a few separate checks by hand (not a loop over cells) uses N_SIGMA for each.

Degrees of freedom. An SE estimated from few replicates is itself uncertain, and an error divided
by it follows Student's t of the SE's degrees of freedom (``CellResult.se_dof``), not a normal law:
the Mitsuba backend's SE from 16 replicates (15 degrees of freedom) exceeds 4 SE in 0.12 % of cells,
20 times ALPHA (docs/validation.md, "How heavy are the tails"). A check of such an SE passes its
``dof`` (a number or an array): ``n_sigma(dof)`` and ``z_family(m, dof=dof)`` are then the t
quantiles of the same probability (n_sigma(15) = 5.48, z_family(7, dof=15) = 6.56); without ``dof``
(or with NaN or infinity) the normal ones.

p-values of goodness-of-fit tests (Kolmogorov-Smirnov, ...) are compared with ALPHA, the same
false-alarm rate.

Deterministic tolerances
------------------------
Named here when more than one test file uses them; a tolerance only one file uses is named in
that file, with the reason for its value.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.stats import norm, t as student_t

#: Standard errors allowed between a Monte Carlo result and what it is compared with (one check).
N_SIGMA = 4.0
#: Two-sided probability that one N_SIGMA check of a correct, normally distributed result fails.
ALPHA = 2.0 * float(norm.sf(N_SIGMA))


def z_family(m: int, alpha: float = ALPHA, dof=None):
    """Per-cell threshold (in SE) for a check of ``m`` cells at once whose family-wise false-alarm
    probability is ``alpha``, by default ALPHA, that of one N_SIGMA check (Sidak:
    1 - (1 - 2 sf(z))^m = alpha); with ``dof`` (the SEs' degrees of freedom, a number or an array)
    the Student-t quantile of the same per-cell probability (module docstring)."""
    if m < 1:
        raise ValueError(f"m must be >= 1, got {m}")
    per_cell = -math.expm1(math.log1p(-alpha) / m)        # 1 - (1 - alpha)^(1/m), without cancellation
    z = float(norm.isf(per_cell / 2.0))
    if dof is None:
        return z
    d = np.asarray(dof, dtype=np.float64)
    finite = np.isfinite(d) & (d > 0)
    k = np.where(finite, student_t.isf(per_cell / 2.0, np.where(finite, d, 1.0)), z)
    return float(k) if k.ndim == 0 else k


def n_sigma(dof=None):
    """The threshold (in SE) of one check of an SE with ``dof`` degrees of freedom: the t quantile
    with the false-alarm probability ALPHA of N_SIGMA normal SEs (N_SIGMA without ``dof``)."""
    return z_family(1, dof=dof)


#: Equal up to float64 rounding of a few operations (closed forms, exact rewrites, ratios).
ROUND_TOL = 1e-12

#: A value written to a file with 6 significant digits (the CSV and RTB tables: r x 1e4 and k_A):
#: rounding error <= 0.5 unit of the 6th digit, <= 5e-6 relative.
FILE_RTOL = 5e-6
#: A value compared with a ratio or product of two such written values: twice FILE_RTOL.
FILE_RATIO_RTOL = 2 * FILE_RTOL

#: One float32 evaluation of the road BSDF plugin against the float64 model at the same (float32)
#: directions: F32_EVAL_RTOL + F32_KAPPA_TOL * kappa relative, plus F32_EVAL_ATOL absolute (sr^-1)
#: for values tiny compared with the coefficients; kappa is the conditioning of the model itself at
#: that point (|d ln f / d angle|, a float64 finite difference). float32 rounds each operation by
#: 6e-8 and the intermediate angles (theta, e = theta_i theta_r / theta_r*, the half-chord h) carry
#: ~1e-7 relative error, which the model amplifies by its own conditioning: a Phong lobe by ~n h, a
#: steep empirical term by p + 2 h f^2 (x W |ln x| in the power reading). Measured over 1.3e5 random
#: evaluations: max err / (1 + kappa) = 2.5e-6. The half-chord lobe form keeps the lobes this good
#: (the naive cos^n is off by ~n 1e-7).
F32_EVAL_RTOL = 2e-5
F32_KAPPA_TOL = 1e-5
F32_EVAL_ATOL = 1e-9

#: float32 rounding of a rendered pixel ratio R/G when every sample carries the same ratio (a
#: Lambertian sample: k_A = 1 up to this).
F32_RATIO_TOL = 1e-5
