"""Deterministic float64 quadrature of the detector signal (paper eq. 3; DESIGN.md sections 4-5).

The signal of the instrument for a sample with BRDF f is the six-fold integral of eq. 3 over the
detector's entrance pupil (disc), its field stop (disc) and the source's exit aperture (disc)::

    S[f] = int_pupil int_field  w(p, q)  L(x(p, q), w_o)   dA_p dA_q
    L(x, w_o) = int_source  f(w_i(x, s), w_o)  G(x, s)  dA_s

with the detector ray of the pair (pupil point p, field point q), its etendue weight w, the hit
point x on the sample plane, w_o = minus the ray direction, and the source coupling G (all from
:mod:`roadgonio.optics`, the one definition of the instrument's ray geometry). The BRDF is the one
definition in :mod:`roadgonio.model`. k_A follows DESIGN.md section 5::

    k_A = ( S[f_road] / S[1/pi] ) / ( pi f_road(nominal) )

Quadrature. Each disc is integrated with a polar product rule that is exact in its boundary (no
mask of a square): Gauss-Jacobi in the radius (weight r dr, so the area element is built in) times
the trapezoidal rule in the angle (spectrally accurate for periodic integrands). A disc of radius
0 (point source, pinhole, zero field) is a single node, so only the dimensions the scene needs are
integrated. The three discs are refined independently (adaptive per disc): at the current levels
``(l_pupil, l_field, l_source)`` the estimate Q is compared with Q refined in one disc at a time;
the differences ``d_g`` estimate each disc's share of the error. The discs whose share exceeds
``rtol / n_discs`` are refined until ``sum |d_g| <= rtol * |Q|``. The reported value is the
combination ``Q + sum d_g`` and the reported error (``CellResult.se``) is ``sum |d_g|``, an
estimate of the (larger) error of Q itself. A cell whose integrand has a discontinuity (beam
limit of the source, the kink of g at theta_l) converges slowly; the refinement then stops at
``max_evals`` integrand evaluations per estimate and the cell reports the error it achieved and
``extra["converged"] = False``.

Only flat rectangular samples: the footprint check (:func:`roadgonio.optics.check_detector`) proves
that every detected ray hits the sample, so the integral runs over the plane z = 0. A mesh sample
needs the Mitsuba backend.
"""
from __future__ import annotations

import math
import time
from functools import lru_cache
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import GeometryError, InputError
from ..instrument import Instrument
from ..model import NumpyOps, RoadModel, road_brdf
from .. import optics
from . import CellResult, ideal_ratio

#: Radial orders of the disc rule by level (the angular order is twice the radial one).
RADIAL_ORDERS = (1, 2, 3, 4, 6, 8, 11, 16, 22, 32, 45, 64, 90, 128)
#: Number of integrand evaluations held in memory at once.
CHUNK = 1 << 18
#: Default cap on integrand evaluations of one estimate (pupil x field x source nodes).
MAX_EVALS = 4_000_000
#: Relative tolerance of the default preset.
DEFAULT_RTOL = 1e-4
#: Disc names in the order of the level tuples.
DISCS = ("pupil", "field", "source")
#: Level of the coarse rule that locates the integrand mass on each disc (see ``_focus``).
FOCUS_PROBE_LEVEL = 2
#: Centroids closer to the disc centre than this leave the rule unmoved; larger ones are capped.
FOCUS_MIN = 0.05
FOCUS_MAX = 0.8


@lru_cache(maxsize=None)
def _polar_rule(level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if level < 0:
        return np.zeros(1), np.zeros(1), np.ones(1)
    if level >= len(RADIAL_ORDERS):
        raise ValueError(f"disc rule level {level} beyond the table ({len(RADIAL_ORDERS) - 1})")
    from scipy.special import roots_jacobi
    n_r = RADIAL_ORDERS[level]
    n_t = 2 * n_r
    z, wz = roots_jacobi(n_r, 0.0, 1.0)        # weight (1 + z) on [-1, 1]
    r = 0.5 * (1.0 + z)                         # r dr = (1 + z) dz / 4
    wr = wz / wz.sum()
    t = (np.arange(n_t) + 0.5) * (2.0 * math.pi / n_t)
    R, T = np.meshgrid(r, t, indexing="ij")
    W = np.repeat(wr[:, None] / n_t, n_t, axis=1)
    return (R * np.cos(T)).ravel(), (R * np.sin(T)).ravel(), W.ravel()


@lru_cache(maxsize=256)
def disc_rule(level: int, focus: complex = 0j) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Product rule on the unit disc: nodes (x, y) and weights summing to 1.

    ``level < 0`` is the centre alone (a disc of radius 0). Otherwise ``n_r = RADIAL_ORDERS[level]``
    Gauss-Jacobi nodes in r (weight r dr on [0, 1]) times ``n_t = 2 n_r`` equally spaced angles
    (offset by half a step): exact for polynomials in (x, y) of total degree ``2 n_r - 1``.

    ``focus`` (complex, ``|focus| < 1``) moves the rule by the disc automorphism
    ``T(z) = (z + a) / (1 + conj(a) z)``: the rule's centre goes to ``a`` and the nodes crowd
    towards the boundary point ``a / |a|`` (by ``(1 + |a|) / (1 - |a|)`` in linear density there).
    The map is analytic and maps the disc and its boundary onto themselves, so the rule stays
    exact in the boundary and spectrally convergent; the weights carry the Jacobian ``|T'(z)|^2``.
    """
    x, y, w = _polar_rule(level)
    if focus != 0 and level >= 0:
        a = complex(focus)
        z = x + 1j * y
        den = 1.0 + a.conjugate() * z
        tz = (z + a) / den
        jac = (1.0 - abs(a) ** 2) ** 2 / np.abs(den) ** 4
        x, y, w = tz.real.copy(), tz.imag.copy(), w * jac
        w = w / w.sum()       # exact up to rounding: the map is onto the disc
    x, y, w = np.array(x), np.array(y), np.array(w)
    for arr in (x, y, w):
        arr.setflags(write=False)
    return x, y, w


def rule_size(level: int) -> int:
    """Number of nodes of the disc rule of ``level``."""
    return 1 if level < 0 else 2 * RADIAL_ORDERS[level] ** 2


def size(levels) -> int:
    """Number of integrand evaluations of the product rule at ``levels`` (pupil, field, source)."""
    n = 1
    for lvl in levels:
        n *= rule_size(lvl)
    return n


class QuadratureBackend:
    """k_A by adaptive polar Gauss quadrature of eq. 3 in float64 (see the module docstring)."""

    name = "quadrature"

    def __init__(self, instrument: Instrument, model: RoadModel, *, rtol: float = DEFAULT_RTOL,
                 max_evals: int = MAX_EVALS, start_level: int = 0, accuracy: str | None = None,
                 focus: bool = True):
        if accuracy is not None:
            from .accuracy import preset
            rtol = preset(accuracy, "quadrature")["rtol"]
        try:
            rtol = float(rtol)
        except (TypeError, ValueError):
            raise InputError(f"expected a number, got {rtol!r}", field="rtol") from None
        if not (0.0 < rtol < 1.0):
            raise InputError(f"expected a relative tolerance 0 < rtol < 1, got {rtol:g}", field="rtol")
        if int(max_evals) < 1:
            raise InputError(f"expected a positive number of evaluations, got {max_evals}", field="max_evals")
        if instrument.sample.mesh is not None:
            raise InputError("the quadrature backend integrates over a flat rectangular sample only; for a mesh "
                             "sample use the mitsuba backend (--backend mitsuba)", path=instrument.path,
                             field="sample.mesh")
        optics.check_detector(instrument)   # GeometryError: footprint off the sample / upward rays
        self.instrument = instrument
        self.model = model
        self.rtol = rtol
        self.max_evals = int(max_evals)
        self.accuracy = accuracy
        self.start_level = int(start_level)
        self.focus = bool(focus)
        self._P = model.params.to_dict()
        self._terms = model.terms()
        self._det = optics.detector_geometry(instrument)
        det = instrument.detector
        #: which discs are integrated (radius > 0); a zero disc is a single node
        self.active = (det.pupil_radius_m > 0.0, det.field_half_angle_deg > 0.0,
                       instrument.source.radius_m > 0.0)
        self._det_cache: dict[tuple[int, int], dict[str, Any]] = {}

    # -- provenance ---------------------------------------------------------------------------
    def settings(self) -> dict[str, Any]:
        return {"backend": self.name, "rtol": self.rtol, "max_evals": self.max_evals,
                "accuracy": self.accuracy, "start_level": self.start_level, "focus": self.focus,
                "rule": "polar Gauss-Jacobi (r) x trapezoid (angle) per disc, adaptive per disc",
                "discs": [d for d, a in zip(DISCS, self.active) if a], "precision": "float64"}

    # -- integrand ----------------------------------------------------------------------------
    def _detector(self, lp: int, lf: int, fp: complex = 0j, ff: complex = 0j) -> dict[str, Any]:
        key = (lp, lf, fp, ff)
        if key not in self._det_cache:
            px, py, wp = disc_rule(lp, fp)
            fx, fy, wf = disc_rule(lf, ff)
            PX = np.repeat(px, fx.size)
            PY = np.repeat(py, fx.size)
            FX = np.tile(fx, px.size)
            FY = np.tile(fy, px.size)
            W = np.repeat(wp, fx.size) * np.tile(wf, px.size)
            o, d, wgt = optics.detector_ray(NumpyOps, self._det, (PX, PY), (FX, FY))
            x, y, valid = optics.hit_plane(NumpyOps, o, d)
            if not np.all(valid):   # excluded by check_detector; kept as a guard
                raise GeometryError("some detected rays do not reach the sample plane")
            wd = W * wgt
            if len(self._det_cache) > 24:
                self._det_cache.clear()
            self._det_cache[key] = {"x": x, "y": y, "wo": (-d[0], -d[1], -d[2]), "w": wd / wd.sum(),
                                    "np": px.size, "nf": fx.size}
        return self._det_cache[key]

    def _estimate(self, src: optics.SourceGeometry, levels, focus=(0j, 0j, 0j), marginals: bool = False):
        """(sum w f G, sum w G) over the product rule at ``levels`` (weights normalised); with
        ``marginals`` also the integrand mass per node of each disc."""
        det = self._detector(levels[0], levels[1], focus[0], focus[1])
        sx, sy, ws = disc_rule(levels[2], focus[2])
        sp = optics.source_point(src, (sx, sy))
        sp = tuple(np.broadcast_to(np.asarray(c, dtype=np.float64), sx.shape)[None, :] for c in sp)
        nd, ns = det["x"].size, sx.size
        rows = max(1, CHUNK // ns)
        road = lam = 0.0
        P, terms, variant = self._P, self._terms, self.model.variant
        if marginals:
            m_det = np.zeros(nd)
            m_src = np.zeros(ns)
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            for a in range(0, nd, rows):
                b = min(nd, a + rows)
                x = det["x"][a:b, None]
                y = det["y"][a:b, None]
                wo = tuple(c[a:b, None] for c in det["wo"])
                wi, g = optics.source_coupling(NumpyOps, src, x, y, sp)
                f = road_brdf(NumpyOps, P, wi, wo, variant, terms)
                wd = det["w"][a:b]
                fg = f * g
                road += float(wd @ (fg @ ws))
                lam += float(wd @ (g @ ws))
                if marginals:
                    m = (fg / max(road, 1e-300) + g / max(lam, 1e-300)) * ws[None, :] * wd[:, None]
                    m_det[a:b] += m.sum(axis=1)
                    m_src += m.sum(axis=0)
        if not marginals:
            return road, lam
        m2 = m_det.reshape(det["np"], det["nf"])
        return road, lam, (m2.sum(axis=1), m2.sum(axis=0), m_src)

    def _focus(self, src, levels) -> tuple[complex, complex, complex]:
        """Automorphism parameter of each disc rule: the centroid of the integrand mass on that
        disc (from a coarse rule), so that the nodes crowd where the signal comes from."""
        _, _, margs = self._estimate(src, levels, marginals=True)
        out = []
        for lvl, m in zip(levels, margs):
            x, y, _ = disc_rule(lvl)
            tot = m.sum()
            if lvl < 0 or not (tot > 0.0 and math.isfinite(tot)):
                out.append(0j)
                continue
            c = complex(float(m @ x) / tot, float(m @ y) / tot)
            r = abs(c)
            if r < FOCUS_MIN:
                out.append(0j)
            else:
                r2 = min(r, FOCUS_MAX)
                c = c * (r2 / r)
                out.append(complex(round(c.real, 3), round(c.imag, 3)))
        return tuple(out)

    # -- one cell -----------------------------------------------------------------------------
    def compute_cell(self, tan_eps: float, beta_deg: float) -> CellResult:
        t0 = time.perf_counter()
        tan_eps, beta_deg = float(tan_eps), float(beta_deg)
        optics.check_source(self.instrument, tan_eps, beta_deg)
        nominal = ideal_ratio(self.model, self.instrument, tan_eps, beta_deg) / math.pi
        if not (nominal > 0.0 and math.isfinite(nominal)):
            raise GeometryError(f"the model is {nominal:g} at the nominal geometry (tan eps = {tan_eps:g}, "
                                f"beta = {beta_deg:g}): k_A = measured/nominal is undefined there")
        src = optics.source_geometry(self.instrument, tan_eps, beta_deg)
        act = [i for i, a in enumerate(self.active) if a]
        evals = 0
        focus = (0j, 0j, 0j)
        if self.focus and act:
            probe = tuple(FOCUS_PROBE_LEVEL if a else -1 for a in self.active)
            focus = self._focus(src, probe)
            evals += size(probe)
        cache: dict[tuple[int, int, int], float] = {}

        def q(levels):
            nonlocal evals
            if levels not in cache:
                road, lam = self._estimate(src, levels, focus)
                evals += size(levels)
                cache[levels] = (road / lam) / nominal if lam > 0.0 else math.nan
            return cache[levels]

        lv = [self.start_level if a else -1 for a in self.active]
        converged = True
        deltas: dict[int, float] = {}
        while True:
            base = q(tuple(lv))
            # error share of each disc: the change from the next coarser rule of that disc
            deltas = {}
            for i in act:
                down = list(lv)
                down[i] -= 1
                deltas[i] = abs(base - q(tuple(down)))
            err = sum(deltas.values())
            if not math.isfinite(base):
                converged = False
                break
            if err <= self.rtol * abs(base):
                break
            share = self.rtol * abs(base) / len(act)
            refine = [i for i, d in deltas.items() if d > share] or [max(deltas, key=deltas.get)]
            nxt = list(lv)
            for i in refine:
                nxt[i] += 1
            if max(nxt) >= len(RADIAL_ORDERS) or size(nxt) > self.max_evals:
                # within the cap, refine only the disc with the largest share
                worst = max(deltas, key=deltas.get)
                nxt = list(lv)
                nxt[worst] += 1
                if nxt[worst] >= len(RADIAL_ORDERS) or size(nxt) > self.max_evals:
                    converged = False
                    break
            lv = nxt
        extra = {"levels": {DISCS[i]: lv[i] for i in act}, "converged": converged,
                 "nodes": {DISCS[i]: rule_size(lv[i]) for i in act},
                 "focus": {DISCS[i]: [focus[i].real, focus[i].imag] for i in act}}
        if not converged:
            extra["note"] = (f"stopped at max_evals = {self.max_evals}: the estimated relative error "
                             f"{err / abs(base):.2e} exceeds rtol = {self.rtol:g}")
        return CellResult(tan_eps=tan_eps, beta_deg=beta_deg, k_a=float(base), se=float(err),
                          samples=int(evals), seconds=time.perf_counter() - t0, extra=extra)

    def compute(self, cells: Sequence[tuple[float, float]],
                on_cell: Callable[[CellResult], None] | None = None) -> list[CellResult]:
        out = []
        for tan_eps, beta in cells:
            res = self.compute_cell(tan_eps, beta)
            out.append(res)
            if on_cell is not None:
                on_cell(res)
        return out


def make_backend(instrument: Instrument, model: RoadModel, *, rtol: float = DEFAULT_RTOL,
                 accuracy: str | None = None, max_evals: int = MAX_EVALS, start_level: int = 0,
                 focus: bool = True, **unknown) -> QuadratureBackend:
    """The quadrature backend (``roadgonio.ka.make_backend("quadrature", ...)``).

    Parameters
    ----------
    rtol:
        Requested relative error of each k_A (default 1e-4).
    accuracy:
        ``"fast"``, ``"default"`` or ``"precise"`` (see :mod:`roadgonio.ka.accuracy`); overrides ``rtol``.
    max_evals:
        Cap on integrand evaluations of one estimate; a cell that reaches it reports the error it
        achieved with ``extra["converged"] = False``.
    start_level:
        First level of each disc rule (level l has 2 n_r^2 nodes, n_r = RADIAL_ORDERS[l]).
    focus:
        Move each disc rule towards the centroid of the integrand mass on that disc (a disc
        automorphism, see :func:`disc_rule`); ``False`` keeps the centred polar rules.
    """
    if unknown:
        raise InputError(f"unknown quadrature setting(s) {', '.join(sorted(unknown))}; expected rtol, "
                         "accuracy, max_evals, start_level, focus", field=sorted(unknown)[0])
    return QuadratureBackend(instrument, model, rtol=rtol, accuracy=accuracy, max_evals=max_evals,
                             start_level=start_level, focus=focus)
