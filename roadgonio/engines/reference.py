"""Float64 reference of k_A: randomised quasi-Monte Carlo with the integrand's kinks split off
(paper eq. 3; docs/conventions.md sections 3-5). The reference that ``roadgonio validate`` judges the
renderers against.

Why not the tensor Gauss quadrature (:mod:`roadgonio.engines.quadrature`)? Its rules converge
spectrally only for smooth integrands. On a wide instrument at grazing incidence the integrand of
eq. 3 is not smooth in two places, and the product rule converges only algebraically across them
(it stops at its evaluation cap 9-13 % off in the beta = 0 column of scenes/wide.toml):

1. **The mirror plane (|beta| kink).** The empirical term depends on
   ``beta = atan2(|(w_i x w_o)_z|, -(w_i . w_o)_xy)`` (docs/conventions.md section 3): for a fixed detector
   ray (hit point x, direction w_o) it has a kink where the source point s crosses the vertical
   plane through x that contains w_o, i.e. on the line ``(s - x)_x w_o,y - (s - x)_y w_o,x = 0``.
   That condition is *linear* in the source-disc coordinates, so on the disc it is a chord.
2. **The plane of the source disc.** A sample point behind the plane of the (one-sided) source disc
   gets no light: ``G = cos theta_i cos theta_s / d^2`` goes to 0 with a kink where the hit point
   crosses ``(x - c) . a_S = 0`` (c the disc centre, a_S its axis; on the wide instrument the
   footprint runs 3.5 m beyond the source). For a fixed pupil point the rays that hit that line of
   the sample plane form a plane, so on the field disc the condition is again a chord.

The reference splits the domain on both, so that every piece it integrates is smooth: for each
pupil point the field disc is cut on the chord of (2) and only the lit segment is integrated; for
each detector ray the source disc is cut on the chord of (1) and both segments are integrated
(both evaluated at every point, their weights the segment areas). Every disc or segment
``{v >= c}`` of the unit disc is the smooth image of the unit square (:func:`segment_map`)::

    v = sin(phi), phi = phi_0 + (pi/2 - phi_0) u_1,  w = cos(phi) (2 u_2 - 1),  phi_0 = asin(c)

with density ``2 cos^2(phi) (pi/2 - phi_0) / pi`` relative to the uniform measure of the disc
(exact in the boundary, no mask; the full disc is c = -1). The lit part of the field disc is
parametrised in *level coordinates* of the distance ``h = (x - c) . a_S`` of the hit point from the
disc plane (:meth:`ReferenceBackend._field_points`: for a fixed pupil point ``h`` is a ratio of two
linear functions of the field point, so its level sets are chords): the light of the bright strip
in front of the source's foot (on the wide instrument half of the Lambert signal comes from 2 %
of the rays) then lies at a fixed value of one coordinate. On top, a smooth (C^1) separable
adaptive map (:class:`AdaptiveMap`, VEGAS-like, trained on a pilot run of an independent stream
and kept only if it halves the pilot variance) moves points to where the integrand is large. The
cut positions depend smoothly on the outer coordinates, so the composed integrand over the unit
cube [0, 1)^d (d = 2 per active disc, at most 6) is smooth wherever both chords cut their discs.

Why RQMC and not a finer product rule: measured on scenes/wide.toml at tan eps 12 / beta 0, the
kink-split, mapped integrand converges like N^-1.3 ... N^-1.5 under scrambled Sobol' points
(error x 2.5-3 down per doubling), the tensor rule stops at its cap 8.6 % off, and the replicates
give an error bar that needs no smoothness assumption (the quadrature's "two estimates agree"
does).

Randomised QMC with replicate error bars. ``replicates`` (R, default 10) independent scrambled
Sobol' sequences (scipy.stats.qmc.Sobol, linear matrix scrambling with a digital shift) each give
the paired means <w f G> and <w G / pi> over their first 2^m points; m grows by one until the
error bound meets ``rtol``. The estimate is the ratio of the pooled means and its standard error
the delta-method SE over the R replicate pairs (:func:`roadgonio.engines.result.ratio_se`); the reported
``CellResult.confidence_bound`` is::

    bound = t_(R-1)(1 - (1 - confidence)/2) * SE       (confidence 0.999: 4.78 SE for R = 10)

the Student-t interval of the R i.i.d. replicate estimates (each an unbiased RQMC average), so it
is a *statistical* bound at the stated confidence, honest up to a 1e-3 chance per cell; the bench
(bench/bench_reference.py) checks true error <= bound on every cell against a long run
(bench/make_reference_long.py). Against a lucky small SE at the stopping level (sequential
stopping), a cell stops only when the bound meets the target *and* the previous level's estimate
lies within its own bound of the new one. A cell that reaches ``max_evals`` integrand evaluations
or ``max_log2`` reports ``converged = False`` with the bound it achieved. The result carries both,
each with its one meaning (:mod:`roadgonio.engines.result`): ``se`` is the replicate standard error
(what an uncertainty budget uses), ``confidence_bound`` the Student-t bound at
``confidence_level`` (what the validator adds as a bound); ``error_bound`` (deterministic) is NaN.

What this reference does not split: a source beam limit (``beam_half_angle_deg``: a jump on a
cone) and g's kink at theta_l are integrated as they are (RQMC stays unbiased and its error bars
honest there, it converges more slowly). Only flat rectangular samples: the footprint check
(:func:`roadgonio.instrument.optics.check_detector`) proves that every detected ray hits the
sample. A mesh sample is checked by :mod:`roadgonio.engines.meshmc`; an XML scene is refused.
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from roadgonio.seeds import cell_key, check_seed, seed_entropy
from roadgonio.errors import InputError
from roadgonio.instrument import optics
from roadgonio.instrument.config import Instrument
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import RoadModel
from roadgonio.engines.result import CellByCellBackend, CellResult, ratio_se
from roadgonio.engines.cellcheck import check_cell, no_light

#: Default target of the relative error bound of each k_A.
DEFAULT_RTOL = 1e-4
#: Number of independent scrambled sequences (replicates) per cell.
DEFAULT_REPLICATES = 10
#: Confidence of the reported error bound (two-sided Student-t interval of the replicates).
DEFAULT_CONFIDENCE = 0.999
#: First and last log2 of the points per replicate.
DEFAULT_MIN_LOG2 = 10
#: Cap on integrand evaluations per cell (all replicates, both source segments).
DEFAULT_MAX_EVALS = 200_000_000
#: Points evaluated at once (memory: ~40 arrays of this length).
CHUNK = 1 << 16


def segment_map(u1, u2, c):
    """Points of the unit-disc segment ``{(v, w): v >= c}`` from the unit square, smooth and exact
    in the boundary (module docstring): returns ``(v, w, density)`` with ``density`` relative to
    the uniform measure of the whole disc, so its mean over the square is the segment's share of
    the disc area. ``c`` broadcasts; ``c <= -1`` is the whole disc, ``c >= 1`` the empty segment."""
    c = np.clip(c, -1.0, 1.0)
    phi0 = np.arcsin(c)
    span = 0.5 * math.pi - phi0
    phi = phi0 + span * u1
    cphi = np.cos(phi)
    v = np.sin(phi)
    w = cphi * (2.0 * u2 - 1.0)
    dens = (2.0 / math.pi) * span * cphi * cphi
    return v, w, dens


def _chord(a0, a1, a2):
    """A half-plane ``a0 + a1 x + a2 y >= 0`` of the unit disc as (unit normal n, offset c) with
    the half-plane ``n . (x, y) >= c``; a degenerate one (a1 = a2 = 0) is all (c = -2) or nothing
    (c = 2)."""
    norm = np.hypot(a1, a2)
    ok = norm > 0.0
    safe = np.where(ok, norm, 1.0)
    nx = np.where(ok, a1 / safe, 1.0)
    ny = np.where(ok, a2 / safe, 0.0)
    c = np.where(ok, -a0 / safe, np.where(a0 >= 0.0, -2.0, 2.0))
    return nx, ny, c


class AdaptiveMap:
    """A separable, smooth (C^1), monotone map of [0, 1)^d onto itself, adapted to the integrand
    (the idea of VEGAS, Lepage 1978, with a smooth map). Coordinate j is the inverse CDF of a
    density ``p_j`` that is piecewise linear and continuous over ``bins`` equal bins of [0, 1], so
    ``y_j = T_j(u_j)`` solves a quadratic in its bin and ``dT_j/du = 1 / p_j(y_j)`` is continuous:
    the mapped integrand ``F(T(u)) / prod p_j`` has no jumps (a piecewise-linear VEGAS map would put
    a jump of its Jacobian on every knot, which costs randomised QMC its rate). A change of
    variables with its exact Jacobian: the integral is unchanged whatever the training did."""

    def __init__(self, dim: int, bins: int = 64):
        self.bins = int(bins)
        self.p = np.ones((dim, self.bins + 1))     # density at the knots k / bins
        self._tables()

    def _tables(self) -> None:
        K = self.bins
        w = 1.0 / K
        area = 0.5 * w * (self.p[:, :-1] + self.p[:, 1:])
        self.p /= area.sum(axis=1, keepdims=True)
        area = 0.5 * w * (self.p[:, :-1] + self.p[:, 1:])
        self.cdf = np.concatenate([np.zeros((self.p.shape[0], 1)), np.cumsum(area, axis=1)], axis=1)
        self.cdf[:, -1] = 1.0

    @property
    def identity(self) -> bool:
        return bool(np.all(self.p == self.p[:, :1]))

    def __call__(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(y, jacobian) of the points ``u`` (n x dim)."""
        K = self.bins
        w = 1.0 / K
        y = np.empty_like(u)
        jac = np.ones(u.shape[0])
        for j in range(u.shape[1]):
            k = np.clip(np.searchsorted(self.cdf[j], u[:, j], side="right") - 1, 0, K - 1)
            p0 = self.p[j, k]
            slope = (self.p[j, k + 1] - p0) / w
            r = u[:, j] - self.cdf[j, k]
            # p0 t + slope t^2 / 2 = r, the root in [0, w] in the cancellation-free form
            t = 2.0 * r / (p0 + np.sqrt(np.maximum(p0 * p0 + 2.0 * slope * r, 0.0)))
            t = np.clip(t, 0.0, w)
            y[:, j] = k * w + t
            jac /= p0 + slope * t
        return y, jac

    def refine(self, y: np.ndarray, fj: np.ndarray, damping: float = 0.7, floor: float = 0.05) -> None:
        """Move density to where ``fj`` (the mapped integrand at points ``y = T(u)``, ``u``
        uniform) is large: for each coordinate the new bin density is ``sqrt(E[(f J)^2 p | y])``
        (the separable variance-optimal density, estimated from the pilot), mixed geometrically with
        the old one (``damping``), smoothed over neighbouring bins and kept above ``floor`` of its
        mean, so that no region is ever dropped from the sampling."""
        K = self.bins
        f2 = fj * fj
        for j in range(self.p.shape[0]):
            k = np.minimum((y[:, j] * K).astype(np.int64), K - 1)
            pold = 0.5 * (self.p[j, :-1] + self.p[j, 1:])
            t = y[:, j] * K - k
            pj = self.p[j, k] * (1.0 - t) + self.p[j, k + 1] * t
            g = np.bincount(k, weights=f2 * pj, minlength=K)
            if not np.sum(g) > 0.0:
                continue
            q = np.sqrt(g)
            q = q / q.mean()
            q = np.where(q > 0, q, 0.0) ** damping * (pold / pold.mean()) ** (1.0 - damping)
            q = np.convolve(np.r_[q[0], q, q[-1]], np.array([0.25, 0.5, 0.25]), mode="valid")
            q = q + floor * q.mean()
            self.p[j] = np.r_[q[0], 0.5 * (q[:-1] + q[1:]), q[-1]]
        self._tables()


class ReferenceBackend(CellByCellBackend):
    """k_A by kink-split randomised QMC in float64 (see the module docstring)."""

    name = "reference"

    def __init__(self, instrument: Instrument, model: RoadModel, *, rtol: float = DEFAULT_RTOL,
                 replicates: int = DEFAULT_REPLICATES, confidence: float = DEFAULT_CONFIDENCE,
                 min_log2: int = DEFAULT_MIN_LOG2, max_evals: int = DEFAULT_MAX_EVALS, seed: int = 0,
                 split: bool = True, max_log2: int = 26, pilot_iterations: int = 3, pilot_points: int = 1 << 12,
                 map_bins: int = 64):
        from roadgonio.engines.registry import check_relative
        rtol = check_relative(rtol, "rtol")
        confidence = _number(confidence, "confidence")
        if not (0.5 <= confidence < 1.0):
            raise InputError(f"expected a confidence in [0.5, 1), got {confidence:g}", field="confidence")
        replicates = _integer(replicates, "replicates")
        if replicates < 4:
            raise InputError(f"expected at least 4 replicates (for an error bar), got {replicates}",
                             field="replicates")
        min_log2 = _integer(min_log2, "min_log2")
        if not (4 <= min_log2 <= 24):
            raise InputError(f"expected 4 <= min_log2 <= 24, got {min_log2}", field="min_log2")
        max_log2 = _integer(max_log2, "max_log2")
        if not (min_log2 <= max_log2 <= 30):
            raise InputError(f"expected min_log2 <= max_log2 <= 30, got {max_log2}", field="max_log2")
        max_evals = _integer(max_evals, "max_evals")
        if max_evals < 1:
            raise InputError(f"expected a positive number of evaluations, got {max_evals}", field="max_evals")
        seed = check_seed(seed)
        optics.check_detector(instrument)
        from scipy.stats import t as student_t
        self.instrument = instrument
        self.model = model
        self.rtol = rtol
        self.replicates = replicates
        self.confidence = confidence
        self.t_factor = float(student_t.ppf(1.0 - 0.5 * (1.0 - confidence), replicates - 1))
        self.min_log2 = min_log2
        self.max_log2 = max_log2
        self.max_evals = max_evals
        self.seed = seed
        self.split = bool(split)
        self.pilot_iterations = _integer(pilot_iterations, "pilot_iterations")
        self.pilot_points = _integer(pilot_points, "pilot_points")
        self.map_bins = _integer(map_bins, "map_bins")
        self._det = optics.detector_geometry(instrument)
        det = instrument.detector
        self.active = (det.pupil_radius_m > 0.0, det.field_half_angle_deg > 0.0, instrument.source.radius_m > 0.0)
        self.dim = 2 * sum(self.active)
        self._level_coords = False

    def settings(self) -> dict[str, Any]:
        return {"backend": self.name, "rtol": self.rtol, "replicates": self.replicates,
                "confidence": self.confidence, "min_log2": self.min_log2, "max_log2": self.max_log2,
                "max_evals": self.max_evals, "pilot_iterations": self.pilot_iterations,
                "pilot_points": self.pilot_points, "map_bins": self.map_bins,
                "seed": self.seed, "split": self.split,
                "method": "randomised QMC (scrambled Sobol'), field disc cut at the source-disc plane, "
                          "source disc cut on the mirror plane (|beta| kink)",
                "precision": "float64"}

    # -- integrand ------------------------------------------------------------------------------
    def _values(self, u: np.ndarray, src: optics.SourceGeometry) -> tuple[np.ndarray, np.ndarray, int]:
        """Per point of ``u`` (n x dim, in [0, 1)^dim): ``w f G`` and ``w G / pi`` (both source
        segments summed, segment densities included), and the number of BRDF evaluations."""
        n = u.shape[0]
        det = self._det
        col = 0
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            # pupil: the whole disc
            if self.active[0]:
                px, py, wp = segment_map(u[:, col], u[:, col + 1], -1.0)
                col += 2
            else:
                px = py = np.zeros(n)
                wp = 1.0
            # field: the segment lit from the front of the source disc (cut 2 of the docstring)
            if self.active[1]:
                if self.split and self._level_coords:
                    fx, fy, wf = self._field_points(u[:, col], u[:, col + 1], px, py, src)
                else:
                    fx, fy, wf = segment_map(u[:, col], u[:, col + 1], -1.0)
                col += 2
            else:
                fx = fy = np.zeros(n)
                wf = 1.0
            o, d, wgt = optics.detector_ray(NumpyOps, det, (px, py), (fx, fy))
            x, y, _ = optics.hit_plane(NumpyOps, o, d)
            wo = (-d[0], -d[1], -d[2])
            wdet = wp * wf * wgt
            road = np.zeros(n)
            lam = np.zeros(n)
            evals = 0
            if not self.active[2]:
                sides = [(None, None)]
            elif self.split and self.model.mirror_kink:
                # both halves of the source disc cut on the mirror plane, each evaluated only where
                # it is not empty (the chord misses the disc for most rays off the mirror plane)
                mx, my, cm = self._mirror_chord(x, y, wo, src)
                sides = [(np.nonzero(cm < 1.0)[0], (mx, my, cm)), (np.nonzero(cm > -1.0)[0], (-mx, -my, -cm))]
            else:
                sides = [(None, (1.0, 0.0, -1.0))]
            for idx, side in sides:
                if idx is None:
                    xs, ys, wos, wd = x, y, wo, wdet
                else:
                    if idx.size == 0:
                        continue
                    xs, ys, wos, wd = x[idx], y[idx], tuple(c[idx] for c in wo), wdet[idx]
                if side is None:
                    sdisc, ws = (0.0, 0.0), 1.0
                else:
                    sx, sy, cs = side
                    if idx is not None:
                        sx, sy, cs = sx[idx], sy[idx], cs[idx]
                    us1, us2 = u[:, col], u[:, col + 1]
                    if idx is not None:
                        us1, us2 = us1[idx], us2[idx]
                    v, w, ws = segment_map(us1, us2, cs)
                    sdisc = (v * sx - w * sy, v * sy + w * sx)
                sp = optics.source_point(src, sdisc)
                wi, g = optics.source_coupling(NumpyOps, src, xs, ys, sp, sdisc)
                f = self.model.evaluate(NumpyOps, wi, wos)
                wg = wd * ws * g
                if idx is None:
                    road += wg * f
                    lam += wg
                else:
                    road[idx] += wg * f
                    lam[idx] += wg
                evals += xs.size
        return road, lam * (1.0 / math.pi), evals

    def _field_points(self, u1, u2, px, py, src: optics.SourceGeometry):
        """Field-disc points of the lit part, in coordinates aligned with the distance of the hit
        point from the source-disc plane, ``h = (x - c) . a_S``: for a fixed pupil point ``h`` is a
        ratio of two linear functions of the field point, ``L(f) / D(f)`` (``D = -d_z > 0``), so
        its level sets are chords of the field disc. ``u1`` picks the level ``h`` over the lit range
        ``[max(h_min, 0), h_max]`` (a cosine substitution, smooth at the tangent ends), ``u2`` the
        point along its chord. The light of the bright strip in front of the source's foot then
        sits at fixed ``u1``, where the adaptive map can follow it. Returns ``(fx, fy, density)``,
        the density relative to the uniform measure of the field disc."""
        a0, a1, a2, b0, b1, b2 = self._field_linear(px, py, src)
        # extremes of h over the disc: (a0 - h b0)^2 = |a - h b|^2 (the tangent level lines)
        qa = b0 * b0 - (b1 * b1 + b2 * b2)        # > 0: D > 0 on the whole disc
        qb = -2.0 * (a0 * b0 - (a1 * b1 + a2 * b2))
        qc = a0 * a0 - (a1 * a1 + a2 * a2)
        disc = np.sqrt(np.maximum(qb * qb - 4.0 * qa * qc, 0.0))
        h_lo = np.maximum((-qb - disc) / (2.0 * qa), 0.0)
        h_hi = (-qb + disc) / (2.0 * qa)
        span = np.maximum(h_hi - h_lo, 0.0)
        h = h_lo + span * 0.5 * (1.0 - np.cos(math.pi * u1))
        dh = span * (0.5 * math.pi) * np.sin(math.pi * u1)
        nx, ny = a1 - h * b1, a2 - h * b2
        o = a0 - h * b0
        nn = np.maximum(np.hypot(nx, ny), 1e-300)
        nx, ny = nx / nn, ny / nn
        rho = np.clip(-o / nn, -1.0, 1.0)
        half = np.sqrt(1.0 - rho * rho)
        t = half * (2.0 * u2 - 1.0)
        fx = rho * nx - t * ny
        fy = rho * ny + t * nx
        # Jacobian of (h, t) -> f: |rho' - t theta'| (n' = -b, |n|' = -n.b)
        nb = nx * b1 + ny * b2
        pb = -ny * b1 + nx * b2
        drho = (b0 * nn - o * nb) / (nn * nn)
        dtheta = -pb / nn
        dens = np.abs(drho - t * dtheta) * dh * (2.0 * half) * (1.0 / math.pi)
        return fx, fy, dens

    def _h_varies(self, src: optics.SourceGeometry) -> bool:
        """Whether the distance of the hit points from the source-disc plane varies over the field
        enough to define the level coordinates of :meth:`_field_points` (it does not when the source
        is overhead, tan eps = 0: then the plane is horizontal, the whole field is lit or none).
        Checked on the pupil rim and centre."""
        if not self.active[1]:
            return False
        ang = np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False)
        px = np.r_[0.0, np.cos(ang)] if self.active[0] else np.zeros(1)
        py = np.r_[0.0, np.sin(ang)] if self.active[0] else np.zeros(1)
        a0, a1, a2, b0, b1, b2 = self._field_linear(px, py, src)
        # h over the field disc ranges over (a0 -+ |a - h b|) / b0 roughly; compare the spread with h
        spread = np.hypot(a1 - (a0 / b0) * b1, a2 - (a0 / b0) * b2) / b0
        scale = np.maximum(np.abs(a0 / b0), spread)
        if not np.all(scale > 0):
            return False
        if np.all(a0 - np.hypot(a1, a2) > 0) and np.all(spread < 1e-3 * scale):
            return False
        return bool(np.all(spread > 1e-9 * scale))

    def _field_linear(self, px, py, src: optics.SourceGeometry):
        """For each pupil point, the coefficients of ``L(f) = a0 + a1 fx + a2 fy`` (> 0: the ray
        through the field point hits the sample in front of the source-disc plane; ``L / D`` is that
        distance) and of ``D(f) = b0 + b1 fx + b2 fy = -d_z`` (d the ray direction before
        normalisation; the ray through the field point ``f`` of the unit field disc)."""
        det = self._det
        a, s, t = det.axis, det.s, det.t
        rd = det.pupil_radius_m
        p = [det.centre[i] + rd * (s[i] * px + t[i] * py) for i in range(3)]
        if det.angular:
            d0 = [a[i] + 0.0 * px for i in range(3)]
            k = det.tan_field
        else:
            d0 = [det.focus_m * a[i] - rd * (s[i] * px + t[i] * py) for i in range(3)]
            k = det.focus_m * det.tan_field
        ax = src.axis
        A = sum((p[i] - src.centre[i]) * ax[i] for i in range(3))
        d0a = sum(d0[i] * ax[i] for i in range(3))
        # hit x = p + tau d with tau = -p_z / d_z > 0: (x - c).a_S = (p_z (d.a_S) - A d_z) / (-d_z)
        a0 = p[2] * d0a - A * d0[2]
        a1 = k * (p[2] * float(s @ ax) - A * s[2])
        a2 = k * (p[2] * float(t @ ax) - A * t[2])
        b0 = -d0[2]
        b1 = -k * s[2] + 0.0 * px
        b2 = -k * t[2] + 0.0 * px
        return a0, a1, a2, b0, b1, b2

    def _lit_chord(self, px, py, src: optics.SourceGeometry):
        """Chord of the field disc, for each pupil point, between the rays that hit the sample in
        front of the source-disc plane (lit) and behind it: ``(x - c) . a_S > 0`` at the hit point
        x is linear in the field-disc coordinates (module docstring): the sign of L of
        :meth:`_field_linear`."""
        a0, a1, a2, _b0, _b1, _b2 = self._field_linear(px, py, src)
        return _chord(a0, a1, a2)

    def _mirror_chord(self, x, y, wo, src: optics.SourceGeometry):
        """Chord of the source disc on the mirror plane of each detector ray (the vertical plane
        through the hit point containing w_o): ``(s - x)_x w_o,y - (s - x)_y w_o,x`` is linear in
        the source-disc coordinates. Returns the half ``>= 0`` as (n, c); the other half is (-n, -c)."""
        return _chord(*optics.mirror_line(src, x, y, wo))

    # -- one cell -----------------------------------------------------------------------------
    def _train(self, src, ss: np.random.SeedSequence) -> tuple[AdaptiveMap, int, dict[str, Any]]:
        """A smooth adaptive map trained on pilot points of an independent random stream (so the
        replicates stay i.i.d. given the map). Each pilot iteration measures the variance of the
        ratio's linearised integrand ``road/<road> - lam/<lam>`` under the current map; the map
        with the smallest variance is kept (the identity if training does not halve it). Returns
        the map, the evaluations spent and a summary."""
        amap = AdaptiveMap(self.dim, self.map_bins)
        info: dict[str, Any] = {"map": "identity"}
        if self.dim == 0 or self.pilot_iterations == 0:
            return amap, 0, info
        rng = np.random.default_rng(ss)
        evals = 0
        best, best_var, var0 = amap.p.copy(), math.inf, math.inf
        size = self.pilot_points
        for it in range(self.pilot_iterations):
            u = rng.random((size, self.dim))
            y, jac = amap(u)
            road, lam, e = self._values(y, src)
            evals += e
            sr, sl = np.mean(road * jac), np.mean(lam * jac)
            if not (sr > 0 and sl > 0):
                continue
            var = float(np.var(road * jac / sr - lam * jac / sl))
            if it == 0:
                var0 = var
                if var > 1.0:          # a peaked integrand: train the map on more points
                    size *= 4
            if var < best_var:
                best, best_var = amap.p.copy(), var
            if it < self.pilot_iterations - 1:
                amap.refine(y, (road / sr + lam / sl) * jac)
        if not best_var < 0.5 * var0:
            best = np.ones_like(best)
            best_var = var0
        amap.p = best
        amap._tables()
        info = {"map": "identity" if amap.identity else "adapted",
                "pilot_rel_var": {"identity": var0, "chosen": best_var}}
        return amap, evals, info

    def compute_cell(self, tan_eps: float, beta_deg: float, rtol: float | None = None) -> CellResult:
        """k_A at one cell; ``rtol`` overrides the backend's target for this cell (the validator
        asks each cell for the bound its comparison needs)."""
        from scipy.stats import qmc
        target = self.rtol if rtol is None else float(rtol)
        t0 = time.perf_counter()
        tan_eps, beta_deg = float(tan_eps), float(beta_deg)
        nominal = check_cell(self.instrument, self.model, tan_eps, beta_deg)
        src = optics.source_geometry(self.instrument, tan_eps, beta_deg)
        self._level_coords = self._h_varies(src)
        R = self.replicates
        ss = np.random.SeedSequence(seed_entropy(self.seed, cell_key(tan_eps), cell_key(beta_deg)))
        pilot_ss, *rep_ss = ss.spawn(R + 1)
        amap, evals, map_info = self._train(src, pilot_ss)
        dim = max(self.dim, 1)
        engines = [qmc.Sobol(dim, scramble=True, rng=np.random.default_rng(child)) for child in rep_ss]
        road = np.zeros(R)
        lam = np.zeros(R)
        npts = 0
        m = self.min_log2
        k = bound = se = math.nan
        history = []
        converged = False
        while True:
            add = (1 << m) - npts
            for r, eng in enumerate(engines):
                for start in range(0, add, CHUNK):
                    u = eng.random(min(CHUNK, add - start))[:, :self.dim]
                    y, jac = amap(u)
                    a, b, e = self._values(y, src)
                    road[r] += float(a @ jac)
                    lam[r] += float(b @ jac)
                    evals += e
            npts = 1 << m
            if np.all(lam > 0.0):
                ratio, rse = ratio_se(road / npts, lam / npts)
                k, se = ratio / nominal, rse / nominal
                bound = self.t_factor * se
                # stop when the bound meets the target and the previous estimate lies within its own
                # bound of this one (a cheap guard against a replicate SE that came out too small)
                consistent = bool(history) and abs(k - history[-1][1]) <= history[-1][2]
                history.append((npts, float(k), float(bound)))
                if self.dim == 0 or (bound <= target * abs(k) and consistent):
                    converged = True
                    break
            elif self.dim == 0 or m >= 30:
                raise no_light(tan_eps, beta_deg, "(the footprint lies behind the source disc, or the source beam misses it)")
            if 2 * evals > self.max_evals or m >= self.max_log2:   # the next level doubles the work
                break
            m += 1
        if not math.isfinite(k):
            raise no_light(tan_eps, beta_deg, "(the footprint lies behind the source disc, or the source beam misses it)")
        extra = {"points_per_replicate": npts, "replicates": R, "replicate_se": float(se),
                 "confidence": self.confidence, "t_factor": self.t_factor, "converged": converged,
                 "history": history[-4:], **map_info}
        if not converged:
            extra["note"] = (f"stopped at its cap (max_evals = {self.max_evals}, max_log2 = {self.max_log2}): the "
                             f"relative error bound {bound / abs(k):.2e} exceeds rtol = {target:g}")
        extra["rtol"] = target
        # no SE, no bound: no degrees of freedom or confidence level either (user audit: se null beside
        # se_dof 9 and confidence_level 0.999 with a null bound, for a beam the replicates rarely hit)
        stated = math.isfinite(se)
        return CellResult(tan_eps=tan_eps, beta_deg=beta_deg, k_a=float(k), se=float(se), confidence_bound=float(bound),
                          confidence_level=self.confidence if math.isfinite(bound) else math.nan,
                          converged=converged, samples=int(evals),
                          seconds=time.perf_counter() - t0, extra=extra, se_dof=float(R - 1) if stated else math.nan)


def _number(v, name: str) -> float:
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise InputError(f"expected a number, got {v!r}", field=name) from None
    if not math.isfinite(v):
        raise InputError(f"expected a finite number, got {v}", field=name)
    return v


def _integer(v, name: str) -> int:
    if isinstance(v, bool):
        raise InputError(f"expected an integer, got {v!r}", field=name)
    try:
        iv = int(v)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"expected an integer, got {v!r}", field=name) from None
    if iv != v:
        raise InputError(f"expected an integer, got {v!r}", field=name)
    return iv




#: Settings a caller may pass (``make_backend("reference", ..., **settings)``).
SETTINGS = ("rtol", "replicates", "confidence", "min_log2", "max_log2", "max_evals", "seed", "split",
            "pilot_iterations", "pilot_points", "map_bins")


def make_backend(instrument: Instrument, model: RoadModel, **settings) -> ReferenceBackend:
    """The float64 RQMC reference (``roadgonio.engines.make_backend("reference", ...)``).

    Settings
    --------
    rtol:
        Target relative error bound of each k_A (default 1e-4).
    replicates, confidence:
        Independent scrambled sequences per cell (default 10) and the confidence of the reported
        bound (default 0.999: bound = Student-t quantile x replicate SE).
    min_log2, max_log2, max_evals:
        First and last 2^m points per replicate, and a cap on integrand evaluations per cell: a
        cell stopped by either cap reports ``converged = False`` with the bound it achieved.
    seed:
        Base seed (>= 0) of the scrambles; each cell's are seeded by (seed, tan eps, beta).
    split:
        Split the domain on the source-disc plane and the mirror plane (default; ``False`` only
        to measure what the split buys).
    pilot_iterations, pilot_points, map_bins:
        Training of the smooth adaptive map (:class:`AdaptiveMap`); 0 iterations = no map.
    """
    unknown = sorted(set(settings) - set(SETTINGS))
    if unknown:
        raise InputError(f"unknown reference setting(s) {', '.join(unknown)}; expected {', '.join(SETTINGS)}",
                         field=unknown[0])
    return ReferenceBackend(instrument, model, **settings)
