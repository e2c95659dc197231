"""Deterministic float64 quadrature of the detector signal (paper eq. 3; docs/conventions.md sections 4-5).

The signal of the instrument for a sample with BRDF f is the six-fold integral of eq. 3 over the
detector's entrance pupil (disc), its field stop (disc) and the source's exit aperture (disc)::

    S[f] = int_pupil int_field  w(p, q)  L(x(p, q), w_o)   dA_p dA_q
    L(x, w_o) = int_source  f(w_i(x, s), w_o)  G(x, s)  dA_s

with the detector ray of the pair (pupil point p, field point q), its etendue weight w, the hit
point x on the sample plane, w_o = minus the ray direction, and the source coupling G (all from
:mod:`roadgonio.instrument.optics`, the one definition of the instrument's ray geometry). The BRDF is the one
definition in :mod:`roadgonio.surface.model`. k_A follows docs/conventions.md section 5::

    k_A = ( S[f_road] / S[1/pi] ) / ( pi f_road(nominal) )

Quadrature. Each disc is integrated with a product rule that is exact in its boundary (no mask of
a square): the disc is the smooth image of a rectangle, ``(x, y) = (s cos phi, sin phi)``, with
Gauss-Legendre nodes in ``phi`` and in ``s`` (:func:`roadgonio.engines.rules.disc_rule`). Each disc has two directions
(along its t axis and its s axis), refined independently, so the six directions (pupil, field,
source x 2) get only the nodes the integrand needs: the long axis of a grazing footprint gets many,
the short axis few. A disc of radius 0 (point source, pinhole, zero field) is a single node. A
coarse probe locates the integrand mass on each disc and the rule is bent towards it (a 1-D Moebius
map along the direction of the mass centroid, still smooth and exact in the boundary). With a
single-ray detector (pupil and field 0) and an f with a kink on the mirror plane (|beta| in the
empirical term) the source disc is cut on that plane's chord and each segment gets its own rule
(:func:`split_disc_rule`, no focus): across the kink the whole-disc rule converges only as n^-2,
and its level-to-level change then understates the error (trial 7).

Error control ("two successive estimates agree"): the error share of each direction is the change
of k_A when that direction alone drops one level; directions whose share exceeds ``rtol / n`` are
refined until the sum of the shares is below ``rtol * k_A`` (shares of directions not refined lately
are re-checked at the final levels), and the converged estimate is then confirmed one level finer in
the directions that carry the error (:data:`CONFIRM_SHARE`): where the integrand has a kink the coarser
rules can agree by chance, and a finer estimate that moves by more than the tolerance sends the
refinement on from there. The reported value is the finest estimate and
``CellResult.error_bound`` is the sum of the shares (or the confirming change, if larger), an estimate of the error of the next coarser rules, so
conservative for spectrally converging integrands (bench: true errors 2-10x below it; not always
where a kink crosses the source disc and no chord cuts it: on the portable preset with the bench's
R3-like model at tan eps 0, rtol 1e-4, the error was 1.03x this estimate, the |beta| kink of the
empirical term crossing the disc through its centre; at rtol 3e-5 and 2e-4 0.25x and 0.27x, session 37). A cell whose
integrand has a kink or a jump (the footprint crossing the plane of the source disc, a source beam
edge, g's kink at theta_l) converges only algebraically; refinement stops at ``max_evals``
integrand evaluations per estimate and the cell reports ``extra["converged"] = False`` with the sum
of the shares at its last levels in ``error_bound``: an estimate, **not a bound** (the rules had not
settled; on the wide preset at tan eps 6, beta 0, rtol 1e-6 it said 0.0100 where the error was 0.0177,
user audit of session 24). The note says so; ``validate`` takes such a reference as inconclusive.

A detector sensitivity map (``field_sensitivity``) is bilinear between its pixel centres and flat
beyond the outermost ones: its slope jumps on those lines across the field disc, where a rule over
the whole disc converges only algebraically and successive rules can agree by chance (a map
stepping from 1 to 0.1 across the field: bounds 2.4-2.8x below the errors, audit of session 27).
With a map the field's rule is cut along the lines where it changes slope
(:func:`roadgonio.engines.rules.map_disc_rule`, no focus; only the outermost ones for a linear map):
on each piece the map is one bilinear function, the integrand is smooth, and the error control above
holds as for a uniform field (step, linear and random 9 x 9 maps: true errors 0.01-0.2 of the bound
against the RQMC reference). Each piece costs at least 2 x 2 nodes, so a map whose lines cut the
disc into more than :data:`~roadgonio.engines.rules.MAP_PIECES_MAX` pieces (a smooth 33 x 33 map:
1,472) is integrated over the whole disc as before, and its cells report ``converged = False`` with
a note: their error is an estimate, not a bound (``--backend reference`` gives a confidence bound).
So do the cells of a source whose angular beam profile falls to exp(-1/2) of its peak within
:data:`NARROW_BEAM_DEG` (the rules' first levels miss it and two levels can agree by chance:
docs/validation.md).

Only flat rectangular samples: the footprint check (:func:`roadgonio.instrument.optics.check_detector`) proves
that every detected ray hits the sample, so the integral runs over the plane z = 0. A mesh sample
needs the Mitsuba backend.
"""
from __future__ import annotations

import math
import time
from functools import lru_cache
from typing import Any

import numpy as np

from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import RoadModel, road_brdf
from roadgonio.instrument import optics
from roadgonio.engines.registry import check_relative
from roadgonio.engines.result import CellByCellBackend, CellResult
from roadgonio.engines.cellcheck import check_cell, no_light, unsampled_beam
from roadgonio.engines.rules import (MAP_PIECES_MAX, ORDERS, DetectorNodes, disc_rule, field_rule_size, gauss_legendre,
                                     map_kinks, map_piece_count, map_unsplit, rule_size)

#: Number of integrand evaluations held in memory at once.
CHUNK = 1 << 18
#: Default cap on integrand evaluations of one estimate (pupil x field x source nodes).
MAX_EVALS = 4_000_000
#: Relative tolerance of the default preset.
DEFAULT_RTOL = 1e-4
#: A source beam whose angular profile falls to exp(-1/2) of its peak within this angle
#: (:func:`roadgonio.instrument.profiles.beam_half_width_rad`) is narrower than the rules' first
#: levels resolve: two levels can agree by chance (sigma 1 deg on a point source: bound 2.7e-6 for
#: an error of 1.7e-4, session 39; sigma 0.1 deg on the corridor at tan eps 12: error 2.2x the
#: bound, user audit of session 43), so its cells report an estimate, not a bound (not converged).
NARROW_BEAM_DEG = 2.0
#: A direction whose error share is at least this fraction of its part of the tolerance
#: (rtol |k_A| / number of directions) is raised one level to confirm a converged estimate.
CONFIRM_SHARE = 0.25
#: Disc names; each disc has two directions (v: along the disc's t axis, h: along its s axis).
DISCS = ("pupil", "field", "source")
DIRS = ("pupil_v", "pupil_h", "field_v", "field_h", "source_v", "source_h")
#: Level (both directions) of the coarse rule that locates the integrand mass on each disc.
FOCUS_PROBE_LEVEL = 3
#: Centroids closer to the disc centre than this leave the rule unmoved; larger ones are capped.
FOCUS_MIN = 0.05
FOCUS_MAX = 0.8


def _segment_rule(level_v: int, level_h: int, c: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Product rule on the unit-disc segment ``{(v, w): v >= c}``: the map of :func:`disc_rule`
    with phi restricted to ``[asin c, pi/2]`` (``v = sin phi``, ``w = s cos phi``), smooth and exact
    in the boundary; weights summing to the segment's share of the disc area."""
    zv, wv = gauss_legendre(ORDERS[level_v])
    zh, wh = gauss_legendre(ORDERS[level_h])
    phi0 = math.asin(c)
    half_span = 0.5 * (0.5 * math.pi - phi0)
    phi = phi0 + half_span * (zv + 1.0)
    cp = np.cos(phi)
    v = np.repeat(np.sin(phi), zh.size)
    w = (cp[:, None] * zh[None, :]).ravel()
    wt = ((wv * cp * cp)[:, None] * wh[None, :]).ravel()
    share = (math.acos(c) - c * math.sqrt(1.0 - c * c)) / math.pi
    return v, w, wt * (share / wt.sum())


@lru_cache(maxsize=512)
def split_disc_rule(level_v: int, level_h: int, chord: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Product rule on the unit disc cut along the chord ``n . (x, y) = c`` (``chord = (n_x, n_y,
    c)``, unit n, ``|c| < 1``): the two segments each get a :func:`_segment_rule` (``level_v``
    across the chord, ``level_h`` along it), so an integrand with a kink on the chord (f's |beta|
    on the mirror plane) is smooth on each piece and the rule converges spectrally instead of as
    ``n^-2``. Weights sum to 1 (each segment to its exact area share)."""
    nx, ny, c = chord
    xs, ys, ws = [], [], []
    for sign in (1.0, -1.0):
        v, w, wt = _segment_rule(level_v, level_h, sign * c)
        mx, my = sign * nx, sign * ny
        xs.append(v * mx - w * my)
        ys.append(v * my + w * mx)
        ws.append(wt)
    out = tuple(np.concatenate(a) for a in (xs, ys, ws))
    for arr in out:
        arr.setflags(write=False)
    return out


class QuadratureBackend(CellByCellBackend):
    """k_A by adaptive polar Gauss quadrature of eq. 3 in float64 (see the module docstring)."""

    name = "quadrature"

    def __init__(self, instrument: Instrument, model: RoadModel, *, rtol: float = DEFAULT_RTOL,
                 max_evals: int = MAX_EVALS, start_level: int = 1, focus: bool = True):
        rtol = check_relative(rtol, "rtol")
        if int(max_evals) < 1:
            raise InputError(f"expected a positive number of evaluations, got {max_evals}", field="max_evals")
        optics.check_detector(instrument)   # GeometryError: footprint off the sample / upward rays
        self.instrument = instrument
        self.model = model
        self.rtol = rtol
        self.max_evals = int(max_evals)
        self.start_level = int(start_level)
        self.focus = bool(focus)
        self._P = model.params.to_dict()
        self._terms = model.terms()
        self._det = optics.detector_geometry(instrument)
        det = instrument.detector
        #: which discs are integrated (radius > 0); a zero disc is a single node
        self.active = (det.pupil_radius_m > 0.0, det.field_half_angle_deg > 0.0,
                       instrument.source.radius_m > 0.0)
        #: the pupil x field nodes (the field's rule cut along a sensitivity map's lines)
        self._nodes = DetectorNodes(self._det)
        #: a map with kinks fixes the field rule's pieces: no focus on the field disc
        self._field_split = self.active[1] and map_kinks(self._det) is not None
        #: a map with kinks the field rule does not follow (too many pieces): no bound (below)
        self._map_unsplit = self.active[1] and map_unsplit(self._det)
        #: a beam narrower than NARROW_BEAM_DEG: its half-width in deg (no bound, below), else None
        from roadgonio.instrument.profiles import beam_half_width_rad
        width = math.degrees(beam_half_width_rad(instrument.source.beam))
        self._narrow_beam_deg = width if width < NARROW_BEAM_DEG else None
        #: chord of the source disc on which this cell's source rule is cut (None: the whole disc)
        self._chord: tuple[float, float, float] | None = None

    # -- provenance ---------------------------------------------------------------------------
    def settings(self) -> dict[str, Any]:
        return {"backend": self.name, "rtol": self.rtol, "max_evals": self.max_evals,
                "start_level": self.start_level, "focus": self.focus,
                "rule": "polar Gauss-Jacobi (r) x trapezoid (angle) per disc, adaptive per disc"
                        + ("; field cut along the sensitivity map's pixel-centre lines" if self._field_split else ""),
                "discs": [d for d, a in zip(DISCS, self.active) if a], "precision": "float64"}

    # -- integrand ----------------------------------------------------------------------------
    def _detector(self, lp: tuple[int, int], lf: tuple[int, int], fp: complex = 0j,
                  ff: complex = 0j) -> dict[str, Any]:
        return self._nodes(lp, lf, fp, ff)

    def _estimate(self, src: optics.SourceGeometry, levels, focus=(0j, 0j, 0j), marginals: bool = False):
        """(sum w f G, sum w G) over the product rule at the six direction ``levels`` (weights
        normalised); with ``marginals`` also the integrand mass per node of each disc."""
        det = self._detector(tuple(levels[0:2]), tuple(levels[2:4]), focus[0], focus[1])
        if self._chord is not None and levels[4] >= 0:
            sx, sy, ws = split_disc_rule(levels[4], levels[5], self._chord)
        else:
            sx, sy, ws = disc_rule(levels[4], levels[5], focus[2])
        sp = optics.source_point(src, (sx, sy))
        sp = tuple(np.broadcast_to(np.asarray(c, dtype=np.float64), sx.shape)[None, :] for c in sp)
        sd = (sx[None, :], sy[None, :])
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
                wi, g = optics.source_coupling(NumpyOps, src, x, y, sp, sd)
                f = road_brdf(NumpyOps, P, wi, wo, variant, terms)
                wd = det["w"][a:b]
                fg = f * g
                road += float(wd @ (fg @ ws))
                lam += float(wd @ (g @ ws))
                if marginals:
                    m = (fg + g * self._nominal) * ws[None, :] * wd[:, None]
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
        for k, m in enumerate(margs):
            lvv, lvh = levels[2 * k], levels[2 * k + 1]
            tot = m.sum()
            if lvv < 0 or (k == 1 and self._field_split) or not (tot > 0.0 and math.isfinite(tot)):
                out.append(0j)
                continue
            x, y, _ = disc_rule(lvv, lvh)
            c = complex(float(m @ x) / tot, float(m @ y) / tot)
            r = abs(c)
            if r < FOCUS_MIN:
                out.append(0j)
            else:
                c = c * (min(r, FOCUS_MAX) / r)
                out.append(complex(round(c.real, 3), round(c.imag, 3)))
        return tuple(out)

    def _mirror_chord(self, src) -> tuple[float, float, float] | None:
        """The chord on which to cut the source rule, or None. With a single-ray detector (pupil
        and field 0) the source disc is the only integral, and an f with a kink on the mirror plane
        (|beta| in the empirical term, ``RoadModel.mirror_kink``) has it on one chord of that
        disc, through the centre at beta = 0. A product Gauss rule across a kink converges only
        as n^-2, and then the change between two successive levels (the error share) is smaller
        than the error of the finer one (trial 7: 1.1-1.4x beyond error_bound at beta = 0):
        cutting the disc on the chord restores spectral convergence and an honest bound. With an
        extended detector the chord moves from detector node to detector node and the detector
        integral smooths the kink, so the whole-disc rule stays."""
        if not (self.active[2] and not self.active[0] and not self.active[1] and self.model.mirror_kink):
            return None
        det = self._detector((-1, -1), (-1, -1))
        a0, a1, a2 = (float(np.asarray(a).ravel()[0])
                      for a in optics.mirror_line(src, det["x"], det["y"], det["wo"]))
        norm = math.hypot(a1, a2)
        if not norm > 0.0:
            return None
        c = -a0 / norm
        if not abs(c) < 1.0 - 1e-9:    # the mirror plane misses the disc (or only grazes it)
            return None
        return (round(a1 / norm, 15), round(a2 / norm, 15), round(c, 15))

    # -- one cell -----------------------------------------------------------------------------
    def compute_cell(self, tan_eps: float, beta_deg: float) -> CellResult:
        t0 = time.perf_counter()
        tan_eps, beta_deg = float(tan_eps), float(beta_deg)
        nominal = check_cell(self.instrument, self.model, tan_eps, beta_deg) / math.pi
        self._nominal = nominal
        src = optics.source_geometry(self.instrument, tan_eps, beta_deg)
        self._chord = self._mirror_chord(src)
        # six directions (pupil v/h, field v/h, source v/h); a disc of radius 0 is one node
        act = [2 * k + j for k, a in enumerate(self.active) if a for j in (0, 1)]
        evals = 0
        focus = (0j, 0j, 0j)
        if self.focus and act and self._chord is None:
            probe = tuple(FOCUS_PROBE_LEVEL if i in act else -1 for i in range(6))
            focus = self._focus(src, probe)
            evals += self._nodes.size(probe)
        cache: dict[tuple[int, ...], float] = {}

        def q(levels):
            nonlocal evals
            levels = tuple(levels)
            if levels not in cache:
                road, lam = self._estimate(src, levels, focus)
                evals += self._nodes.size(levels)
                cache[levels] = (road / lam) / nominal if lam > 0.0 else math.nan
            return cache[levels]

        lv = [self.start_level if i in act else -1 for i in range(6)]
        converged = True
        deltas: dict[int, float] = {}   # error share of each direction (change from one level down)
        todo = set(act)                 # directions whose share must be (re)computed at lv
        fresh: set[int] = set()
        err = 0.0

        def share_of(i):
            down = list(lv)
            down[i] -= 1
            coarse = q(down)
            # a coarser rule that saw no light at all (narrow beam) says nothing: a full share
            return abs(base - coarse) if math.isfinite(coarse) else abs(base)

        while True:
            base = q(lv)
            if not math.isfinite(base):
                # no node sees light yet (a narrow source beam): refine every direction
                nxt = [lvl + 1 if i in act else lvl for i, lvl in enumerate(lv)]
                if not act or max(nxt) >= len(ORDERS) or self._nodes.size(nxt) > self.max_evals:
                    # a beam's axis points at the sample centre: it lights the footprint, too narrowly
                    raise (unsampled_beam(self.instrument, tan_eps, beta_deg, "quadrature")
                           or no_light(tan_eps, beta_deg, "(the source beam misses the detector footprint)"))
                lv = nxt
                continue
            for i in todo:
                deltas[i] = share_of(i)
                fresh.add(i)
            err = sum(deltas.values())
            if err <= self.rtol * abs(base):
                # shares of directions not refined lately are stale: check them at the final levels
                stale = set(act) - fresh
                for i in stale:
                    deltas[i] = share_of(i)
                    fresh.add(i)
                err = sum(deltas.values())
                if err <= self.rtol * abs(base):
                    # confirmed one level finer in the directions that carry the error: where the
                    # integrand has a kink the coarser rules can agree by chance (user audit, session 24:
                    # the wide preset at tan eps 3, beta 25 changed by 1e-4 one level down and by 1.8e-3
                    # one level up, and reported a bound of 2e-4 for an error of 1.2e-3)
                    up = list(lv)
                    for i in act:
                        if deltas[i] >= CONFIRM_SHARE * self.rtol * abs(base) / len(act):
                            up[i] += 1
                    if up == lv or max(up) >= len(ORDERS) or self._nodes.size(up) > self.max_evals:
                        break
                    fine = q(up)
                    jump = abs(fine - base) if math.isfinite(fine) else math.inf
                    lv = up
                    if jump <= self.rtol * abs(base):
                        base, err = fine, max(err, jump)
                        break
                    todo, fresh = set(act), set()      # the finer rules disagree: go on from them
                    continue
            share = self.rtol * abs(base) / len(act)
            refine = [i for i, d in deltas.items() if d > share] or [max(deltas, key=deltas.get)]
            nxt = list(lv)
            for i in refine:
                nxt[i] += 1
            if max(nxt) >= len(ORDERS) or self._nodes.size(nxt) > self.max_evals:
                # within the cap, refine only the direction with the largest share
                refine = [max(deltas, key=deltas.get)]
                nxt = list(lv)
                nxt[refine[0]] += 1
                if nxt[refine[0]] >= len(ORDERS) or self._nodes.size(nxt) > self.max_evals:
                    for i in set(act) - fresh:
                        deltas[i] = share_of(i)
                    err = sum(deltas.values())
                    # at the cap, judged by the same estimate as above: the stale shares refreshed
                    # at the final levels may meet rtol after all
                    converged = err <= self.rtol * abs(base)
                    break
            lv = nxt
            todo = set(refine)
            fresh = set()
        if (self._map_unsplit or self._narrow_beam_deg is not None) and converged:
            # audit 27: across a map's kinks successive rules agreed by chance (bounds 2.4-2.8x below
            # the errors); the rule follows the kinks only up to MAP_PIECES_MAX pieces. The same for a
            # beam narrower than NARROW_BEAM_DEG (session 39's review, user audit of session 43)
            converged = False
        extra = {"levels": {DIRS[i]: lv[i] for i in act}, "converged": converged,
                 "nodes": {DISCS[k]: (field_rule_size(self._det, lv[2], lv[3]) if k == 1 else
                                      rule_size(lv[2 * k], lv[2 * k + 1])) for k in range(3) if self.active[k]},
                 "focus": {DISCS[k]: [focus[k].real, focus[k].imag] for k in range(3) if self.active[k]}}
        if self._map_unsplit:
            xs, ys = self._det.kd_map.kink_lines()
            extra["map_pieces"] = map_piece_count(xs, ys)
            extra["note"] = (f"the detector's sensitivity map changes slope along {len(xs) + len(ys)} lines of pixel "
                             f"centres, more than a field rule cut along them can afford ({extra['map_pieces']} "
                             f"pieces > {MAP_PIECES_MAX}): across them successive rules can agree by chance, so the "
                             f"estimated relative error {err / abs(base):.2e} is not a bound (not converged); "
                             f"--backend reference gives a confidence bound")
        elif self._narrow_beam_deg is not None:
            extra["narrow_beam_deg"] = self._narrow_beam_deg
            extra["note"] = (f"the source's beam falls to exp(-1/2) of its peak within {self._narrow_beam_deg:.3g} deg, "
                             f"narrower than the {NARROW_BEAM_DEG:g} deg this backend's rules resolve: successive rules "
                             f"can agree by chance, so the estimated relative error {err / abs(base):.2e} is not a "
                             "bound (not converged); --backend reference or mitsuba gives its error statistically")
        elif not converged:
            extra["note"] = (f"stopped at max_evals = {self.max_evals}: the estimated relative error "
                             f"{err / abs(base):.2e} exceeds rtol = {self.rtol:g}; not converged, so this "
                             f"estimate is not a bound (the error can be larger)")
        return CellResult(tan_eps=tan_eps, beta_deg=beta_deg, k_a=float(base), se=math.nan,
                          error_bound=float(err), converged=bool(converged),
                          samples=int(evals), seconds=time.perf_counter() - t0, extra=extra)



def make_backend(instrument: Instrument, model: RoadModel, *, rtol: float = DEFAULT_RTOL,
                 max_evals: int = MAX_EVALS, start_level: int = 1,
                 focus: bool = True, **unknown) -> QuadratureBackend:
    """The quadrature backend (``roadgonio.engines.make_backend("quadrature", ...)``).

    Parameters
    ----------
    rtol:
        Requested relative error of each k_A (default 1e-4).
    max_evals:
        Cap on integrand evaluations of one estimate; a cell that reaches it reports the error it
        achieved with ``extra["converged"] = False``.
    start_level:
        First level of each direction of the disc rules (level l has ORDERS[l] Gauss nodes).
    focus:
        Move each disc rule towards the centroid of the integrand mass on that disc (a disc
        automorphism, see :func:`disc_rule`); ``False`` keeps the centred rules.
    """
    if unknown:
        raise InputError(f"unknown quadrature setting(s) {', '.join(sorted(unknown))}; expected rtol, "
                         "max_evals, start_level, focus", field=sorted(unknown)[0])
    return QuadratureBackend(instrument, model, rtol=rtol, max_evals=max_evals,
                             start_level=start_level, focus=focus)
