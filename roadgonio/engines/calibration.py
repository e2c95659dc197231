"""k_A under the instrument's calibration (docs/conventions.md section 5), for any backend, in one place.

Every backend computes k_A under Lambert calibration (the ratio of the rendered signals of the
sample and of a perfect diffuser, over the ideal point geometry)::

    k_lam[f] = ( S[f] / S[1/pi] ) / ( pi f(nominal) )

:class:`CalibratedBackend` wraps a backend and returns :class:`~roadgonio.engines.CellResult` in
the instrument's ``[calibration] mode`` (:mod:`roadgonio.instrument.calibration`);
:func:`roadgonio.engines.make_backend` applies it, so ``ka``, ``uncertainty``, ``correct``,
``validate`` and the API all see the same k_A.

* ``lambert``: the backend's result, unchanged.
* ``absolute`` (paper eq. 2): the luminance meter reads L_D = S[f] / S_unif, S_unif the signal of a
  uniform unit luminance over the field (same etendue and k_D weighting), and the illuminance is E_0,
  the horizontal illuminance at the sample centre from the source disc. With E(x) the horizontal
  illuminance at a point x of the sample (uniform source radiance L_e), S[1/pi] = S_unif <E> / pi, so::

      k_abs = L_D / (E_0 f(nominal)) = k_lam * eta,      eta = <E> / E_0

  where <E> is the etendue- and k_D-weighted mean illuminance over the detected footprint.
  eta is pure geometry (independent of the BRDF): a Lambertian sample gives k_abs = eta, not 1.
  It is computed here in float64 by a product Gauss rule over pupil x field x source disc
  (:func:`illuminance_ratio`, the disc rules of :mod:`roadgonio.engines.rules`), refined
  until two successive rules agree to ``eta_rtol``.
  Limitation: eta is the bare geometry's; parts of a ``[scene] xml`` that shade the footprint or the
  sample centre from the source are not in it (the backend's k_lam does see them, as a ratio).
  Stray light (a backend that reports ``stray_fraction`` > 0): the meter reads the total signal,
  S_total[f] = S_direct[f] / (1 - stray_fraction), against the source's E_0 (no housing in its
  calibration), so ``k_abs = k_lam_direct * eta / (1 - stray_fraction)``, and ``k_a_direct`` is
  k_lam_direct * eta. That is k_abs = eta (S_total[f] / S_direct[f_lambert]) / (f(nominal) pi): a
  backend that can (Mitsuba: ``converge_on("absolute")``) converges each cell on this ratio and gives
  its standard error by the delta method over its replicates; otherwise the relative standard errors
  of k_lam_direct and 1 - stray_fraction are combined as if independent.
* ``reference`` (reference = SAMPLE with BRDF f_ref): q = (S[f] / S[f_ref]) f_ref(nominal), so::

      k_ref = k_lam[f] / k_lam[f_ref]

  with both k_lam from the same backend and settings (same seed: common random numbers). A
  reference equal to the sample (same variant and parameters) gives exactly 1 (not computed).
  Precision: for Monte Carlo backends the relative standard error is combined as if the two errors
  were independent, ``rel_se = sqrt(rel_se_f^2 + rel_se_ref^2)``; the common random numbers make them
  positively correlated, so this overstates the error (conservative). For deterministic backends the
  relative bounds add (first-order worst case). ``k_a_direct`` is formed the same way from the direct
  light of both; the stray fraction is the sample's.

A confidence bound with its level (the RQMC reference) is carried like the deterministic bound: in
``absolute`` ``b * eta + |k_lam| eta_error`` at the same level; in ``reference`` the relative bounds
add, at level at least 1 - (1 - L_f) - (1 - L_ref) (both hold with that probability, Bonferroni).
"""
from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import numpy as np

from roadgonio.engines.result import CellResult, KaBackend, welch_satterthwaite
from roadgonio.engines.rules import ORDERS, DetectorNodes, disc_rule
from roadgonio.errors import GeometryError, InputError
from roadgonio.fileio import fingerprint
from roadgonio.instrument import optics
from roadgonio.instrument.config import Instrument
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import RoadModel

#: Default relative tolerance of eta.
ETA_RTOL = 1e-6
#: Cap on the integrand evaluations of one eta estimate (detector nodes x source nodes).
ETA_MAX_EVALS = 6_000_000
#: Cells computed per chunk in the reference mode (reference first, then the sample).
REFERENCE_CHUNK = 16

InnerFactory = Callable[[Instrument, RoadModel], KaBackend]


# ----------------------------------------------------------------------------------------------
# The modes: k_A under the calibration from k_A under Lambert calibration (the one dispatch)
# ----------------------------------------------------------------------------------------------

def apply_calibration(mode: str, k_lam, *, eta=None, reference_reading=None, reference_nominal=1.0):
    """k_A in calibration ``mode`` from the Lambert-calibrated ``k_lam`` (module docstring), floats or
    arrays (one value per cell); the one definition of the modes, used by :class:`CalibratedBackend`
    and by the correction's forward model (``k_lam = 1`` there gives its factor kappa)::

        lambert     k_lam
        absolute    k_lam * eta                                   (eta = <E>/E_0, :func:`illuminance_ratio`)
        reference   k_lam * reference_nominal / reference_reading

    ``reference_reading / reference_nominal`` is the reference's own k_lam over the same rays (same
    backend and seed): its k_lam with ``reference_nominal = 1``, or its Lambert-calibrated reading
    <f_ref> with ``reference_nominal`` = f_ref(nominal)."""
    if mode == "lambert":
        return k_lam
    if mode == "absolute":
        if eta is None:
            raise ValueError("the absolute calibration needs eta = <E>/E_0")
        return k_lam * eta
    if mode == "reference":
        if reference_reading is None:
            raise ValueError("the reference calibration needs the reference's reading")
        return k_lam * reference_nominal / reference_reading
    raise InputError(f"unknown calibration mode {mode!r}; expected one of lambert, absolute, reference",
                     field="calibration.mode")


def centre_coupling(src: optics.SourceGeometry, level_v: int = 6, level_h: int = 6) -> float:
    """E_0 / (L_e A_S): the mean source coupling G at the sample centre over the source disc (the
    horizontal illuminance E_0 of eta's denominator per unit radiance and area; with the source's
    beam profile, docs/conventions.md section 4.1), float64, by the
    product Gauss rule :func:`roadgonio.engines.rules.disc_rule` at ``(level_v, level_h)``
    (a point source: its single node).

    A beam limit (``cos_beam``) is a jump on the disc that a Gauss rule over the whole disc does not
    integrate (user audit: a 0.5 deg cone on a disc of 25 mm at 1 m, which lights the centre from its
    inner 8.7 mm only, gave the design the uncut disc's signal): the sample centre is on the source's
    axis, so the disc point at radius rho emits towards it at atan(rho / D) from the axis and the
    lit part is the concentric disc of radius :func:`beam_cut_fraction` x R_S, over which the rule
    then runs (the rule's mean over that disc times its share of the area)."""
    if not src.radius_m > 0:
        level_v = level_h = -1
    sx, sy, ws = disc_rule(level_v, level_h)
    cut = beam_cut_fraction(src)
    if cut < 1.0:
        sx, sy = sx * cut, sy * cut
    sp = optics.source_point(src, (sx, sy))
    sp = tuple(np.broadcast_to(np.asarray(c, dtype=np.float64), sx.shape) for c in sp)
    with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
        _, g = optics.source_coupling(NumpyOps, src, np.zeros(1), np.zeros(1), sp, (sx, sy))
    return float(np.asarray(g) @ ws) * cut * cut


def source_solid_angle(radius_m: float, distance_m: float) -> float:
    """Projected solid angle (sr) of a Lambertian disc seen on its axis: E_normal / L_S (exact)."""
    r2 = radius_m * radius_m
    return math.pi * r2 / (r2 + distance_m * distance_m)


#: Level of the Gauss disc rules of the profiled source's Omega_S and a sensitivity map's mean (45 x 45 nodes).
PROFILE_RULE_LEVEL = 10


def profiled_solid_angle(instrument: Instrument) -> float:
    """Omega_S = E_normal / L_0 of the instrument's source, the illuminance on its axis at the sample
    centre per unit on-axis radiance: the closed form of :func:`source_solid_angle` for the uniform
    disc, otherwise the mean source coupling over the disc (:func:`centre_coupling`, eta's E_0,
    profile included, docs/conventions.md section 4.1) times its area, for the source overhead at its
    ``length_m`` (a fixed-height source is then at its height, where its signal is largest; for another
    distance pass the instrument with that length). A beam limit ``beam_half_angle_deg`` lets only the
    inner disc of radius min(R_S, D_S tan theta) light the centre (:func:`beam_cut_fraction`): the
    closed form of that disc, or the rule over it. 0 for a point source (no disc)."""
    src = instrument.source
    if src.radius_m == 0.0:
        return 0.0
    g = optics.source_geometry(instrument, 0.0, 0.0)
    if not src.profiled:
        return source_solid_angle(src.radius_m * beam_cut_fraction(g), src.length_m)
    return centre_coupling(g, PROFILE_RULE_LEVEL, PROFILE_RULE_LEVEL) * math.pi * src.radius_m ** 2


def beam_cut_fraction(src: optics.SourceGeometry) -> float:
    """The radius, as a fraction of the disc's, of the part of the source disc whose light reaches
    the sample centre inside the beam limit: min(1, D tan(theta_beam) / R_S), D the distance of the
    disc's centre from the sample centre (1 without a beam limit)."""
    if src.cos_beam is None or not src.radius_m > 0:
        return 1.0
    c = float(src.cos_beam)
    if c <= 0.0:
        return 1.0
    tan_beam = math.sqrt(max(1.0 - c * c, 0.0)) / c
    dist = float(np.sqrt(np.dot(src.centre, src.centre)))
    return min(1.0, dist * tan_beam / src.radius_m)


# ----------------------------------------------------------------------------------------------
# eta = <E> / E_0 (absolute calibration)
# ----------------------------------------------------------------------------------------------

class _EtaIntegrator:
    """eta of one instrument, cell by cell (module docstring). Each disc (pupil, field, source) has
    two directions of the product rule :func:`roadgonio.engines.rules.disc_rule`, refined
    separately: the error share of a direction is the change of eta when that direction alone
    drops one level; directions whose share exceeds ``rtol / n`` are refined until the sum of the
    shares is below ``rtol * eta`` (the estimate reported as the error). The detector nodes do not
    depend on the cell and are cached."""

    def __init__(self, instrument: Instrument):
        optics.check_detector(instrument)
        self.instrument = instrument
        self.det = optics.detector_geometry(instrument)
        d = instrument.detector
        self.active = (d.pupil_radius_m > 0.0, d.field_half_angle_deg > 0.0, instrument.source.radius_m > 0.0)
        #: the hit points and weights of the pupil x field rule, by levels (the quadrature's nodes)
        self.detector_nodes = DetectorNodes(self.det)

    def _eta(self, src, levels) -> float:
        """<E> / E_0 with the product rule at the six direction ``levels``."""
        nodes = self.detector_nodes(tuple(levels[0:2]), tuple(levels[2:4]))
        x, y, w = nodes["x"], nodes["y"], nodes["w"]
        sx, sy, ws = disc_rule(levels[4], levels[5])
        sp = optics.source_point(src, (sx, sy))
        sp = tuple(np.broadcast_to(np.asarray(c, dtype=np.float64), sx.shape)[None, :] for c in sp)
        sd = (sx[None, :], sy[None, :])
        rows = max(1, (1 << 17) // sx.size)
        mean = 0.0
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            for a in range(0, x.size, rows):
                b = min(x.size, a + rows)
                _, g = optics.source_coupling(NumpyOps, src, x[a:b, None], y[a:b, None], sp, sd)
                mean += float(w[a:b] @ (g @ ws))
        e0 = centre_coupling(src, levels[4], levels[5])
        if not e0 > 0.0:
            raise GeometryError(f"the source does not light the sample centre at tan eps = {self._cell[0]:g}, "
                                f"beta = {self._cell[1]:g} (E_0 = 0): absolute calibration is undefined there")
        return mean / e0

    def __call__(self, tan_eps: float, beta_deg: float, rtol: float = ETA_RTOL,
                 max_evals: int = ETA_MAX_EVALS) -> tuple[float, float, bool]:
        """(eta, error estimate, converged) at one cell."""
        optics.check_source(self.instrument, tan_eps, beta_deg)
        self._cell = (tan_eps, beta_deg)
        src = optics.source_geometry(self.instrument, tan_eps, beta_deg)
        act = [2 * k + j for k, a in enumerate(self.active) if a for j in (0, 1)]
        cache: dict[tuple[int, ...], float] = {}

        def q(levels):
            levels = tuple(levels)
            if levels not in cache:
                cache[levels] = self._eta(src, levels)
            return cache[levels]

        lv = [2 if i in act else -1 for i in range(6)]
        if not act:
            return q(lv), 0.0, True
        converged = True
        while True:
            base = q(lv)
            shares = {}
            for i in act:
                down = list(lv)
                down[i] -= 1
                shares[i] = abs(base - q(down))
            err = sum(shares.values())
            if err <= rtol * abs(base) and base != 0.0:
                break
            limit = rtol * abs(base) / len(act)
            # no node lit at all (a beam limit whose spot falls between the nodes): every direction
            # is refined (user audit: eta 0 with an error of 0 was taken as converged, k_A 0)
            refine = ([i for i, d in shares.items() if d > limit] or [max(shares, key=shares.get)]) if base != 0.0 \
                else list(act)
            nxt = list(lv)
            for i in refine:
                nxt[i] += 1
            if max(nxt) >= len(ORDERS) or self.detector_nodes.size(nxt) > max_evals:
                i = max(shares, key=shares.get)
                nxt = list(lv)
                nxt[i] += 1
                if nxt[i] >= len(ORDERS) or self.detector_nodes.size(nxt) > max_evals:
                    converged = False
                    break
            lv = nxt
        if base == 0.0:
            cone = self.instrument.source.beam_half_angle_deg
            raise GeometryError(
                f"the calibration's quadrature finds no light of the source on the detected footprint at tan eps = "
                f"{tan_eps:g}, beta = {beta_deg:g} (eta = <E>/E_0 = 0 at every level up to its cap, while the source "
                "lights the sample centre" + (f": the beam limit of {cone:g} deg lights spots its nodes do not "
                                              "resolve" if cone is not None else "") + "): absolute calibration cannot "
                "be computed there")
        return float(base), float(err), converged


_ETA_CACHE: dict[tuple[str, float, float, float], tuple[float, float, bool]] = {}


def illuminance_ratio(instrument: Instrument, tan_eps: float, beta_deg: float, *,
                      rtol: float = ETA_RTOL) -> tuple[float, float, bool]:
    """eta = <E> / E_0 at one cell (module docstring), float64: ``(eta, error estimate, converged)``.

    <E> is the mean horizontal illuminance over the detected footprint, weighted like the detector
    signal (etendue x k_D); E_0 the horizontal illuminance at the sample centre; both from the
    uniform source disc (a point source if its radius is 0). Cached per instrument and cell."""
    key = (fingerprint({"instrument": instrument.to_dict(), "files": instrument.file_digests()}), round(float(tan_eps), 9),
           round(float(beta_deg), 9), float(rtol))
    if key not in _ETA_CACHE:
        integ = _INTEGRATORS.get(key[0])
        if integ is None:
            integ = _INTEGRATORS[key[0]] = _EtaIntegrator(instrument)
            if len(_INTEGRATORS) > 8:
                _INTEGRATORS.pop(next(iter(_INTEGRATORS)))
        _ETA_CACHE[key] = integ(float(tan_eps), float(beta_deg), rtol)
    return _ETA_CACHE[key]


_INTEGRATORS: dict[str, _EtaIntegrator] = {}


def illuminance(instrument: Instrument, tan_eps: float, beta_deg: float, x, y, *, level: int = 9) -> np.ndarray:
    """The horizontal illuminance E(x_E, y_E) (paper eq. 3) at the points (x, y) of the sample plane
    from the source of cell (tan eps, beta), in units of its on-axis radiance L_0 (lx per cd/m^2; a
    point source: of its on-axis intensity, lx per cd, with its intensity cos theta P(theta)): the
    shared source coupling (:func:`roadgonio.instrument.optics.source_coupling`, beam profile
    included) integrated over the disc by the quadrature's product Gauss rule at ``level`` (the rule
    of eta and the quadrature backend; 45 x 45 nodes at 9, converged to ~1e-10 for the smooth
    profiles). float64, the shape of ``x``."""
    src = optics.source_geometry(instrument, tan_eps, beta_deg)
    lv = level if src.radius_m > 0 else -1
    sx, sy, ws = disc_rule(lv, lv)
    sp = tuple(np.broadcast_to(np.asarray(c, dtype=np.float64), sx.shape)[None, :]
               for c in optics.source_point(src, (sx, sy)))
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    out = np.empty(x.size)
    xf, yf = x.ravel(), y.ravel()
    rows = max(1, (1 << 17) // sx.size)
    with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
        for a in range(0, xf.size, rows):
            _, g = optics.source_coupling(NumpyOps, src, xf[a:a + rows, None], yf[a:a + rows, None], sp,
                                          (sx[None, :], sy[None, :]))
            out[a:a + rows] = g @ ws
    area = math.pi * src.radius_m ** 2 if src.radius_m > 0 else 1.0
    return (out * area).reshape(x.shape)


# ----------------------------------------------------------------------------------------------
# The wrapper
# ----------------------------------------------------------------------------------------------

def same_model(a: RoadModel, b: RoadModel) -> bool:
    """Same BRDF: same variant and parameters (names and metadata do not matter)."""
    return a.variant == b.variant and a.params.to_dict() == b.params.to_dict()


class CalibratedBackend:
    """A k_A backend in the instrument's calibration mode around a Lambert-calibrated backend
    (module docstring). ``make_inner(instrument, model)`` builds the wrapped backend; it is called
    for the sample and, in the reference mode, once more for the reference. ``deterministic``: the
    wrapped backend's precision is a deterministic bound (the registry's ``BackendInfo.deterministic``)."""

    def __init__(self, make_inner: InnerFactory, instrument: Instrument, model: RoadModel, *,
                 inner: KaBackend | None = None, eta_rtol: float = ETA_RTOL, deterministic: bool = False):
        self.instrument = instrument
        self.model = model
        self.calibration = instrument.calibration
        self.mode = self.calibration.mode
        self.eta_rtol = float(eta_rtol)
        self.inner = inner if inner is not None else make_inner(instrument, model)
        self.name = self.inner.name
        self.deterministic = bool(deterministic)
        self.reference_model: RoadModel | None = None
        self.reference_inner: KaBackend | None = None
        self.identical = False
        if self.mode == "absolute":
            optics.check_detector(instrument)
            if hasattr(self.inner, "converge_on"):
                # with stray light the reported k_A is not the Lambert ratio the backend would stop on
                self.inner.converge_on("absolute")
        elif self.mode == "reference":
            self.reference_model = self.calibration.reference_model()
            self.identical = same_model(model, self.reference_model)
            if not self.identical:
                self.reference_inner = make_inner(instrument, self.reference_model)

    def settings(self) -> dict[str, Any]:
        s = dict(self.inner.settings())
        cal: dict[str, Any] = self.calibration.to_dict()
        if self.mode == "absolute":
            cal.update(eta="<E>/E_0 by float64 product Gauss rules (pupil x field x source)", eta_rtol=self.eta_rtol,
                       # (in the settings, so that journals from before it are not resumed without it)
                       eta_error="a deterministic bound: added to a bound, beside a standard error")
        if self.mode == "reference":
            cal.update(reference_model=self.reference_model.to_json_dict() if self.reference_model else None,
                       se="independent-errors delta method (conservative under common random numbers)")
        s["calibration"] = cal
        return s

    # -- one cell ---------------------------------------------------------------------------
    def _absolute(self, c: CellResult) -> CellResult:
        eta, eta_err, eta_ok = illuminance_ratio(self.instrument, c.tan_eps, c.beta_deg, rtol=self.eta_rtol)
        if math.isfinite(c.error_bound):
            bound = c.error_bound * eta + abs(c.k_a) * eta_err
        elif math.isfinite(c.se) and not math.isfinite(c.confidence_bound):
            # a Monte Carlo result (an SE alone): eta's error is deterministic, so it is a bound beside
            # the SE, not a part of it (audit 21: it was dropped; 0.78 % at tan 12 on the wide preset)
            bound = abs(c.k_a) * eta_err
        else:
            bound = math.nan
        # a confidence bound (the RQMC reference) is scaled like the deterministic bound, at its own level
        conf = dict(confidence_bound=c.confidence_bound * eta + abs(c.k_a) * eta_err
                    if math.isfinite(c.confidence_bound) else math.nan, confidence_level=c.confidence_level)
        # the backend's own convergence apart from eta's, so that a cell that stopped says which did
        # (audit 21: "stopped at the sample cap with relative SE 0.0024", the SE at its target, eta not)
        extra = {**(c.extra or {}), "calibration": "absolute", "k_a_lambert": c.k_a, "eta": eta,
                 "eta_error": eta_err, "eta_converged": eta_ok, "backend_converged": bool(c.converged)}
        if c.stray_fraction != 0.0:
            # the meter reads the total signal against the source's own E_0 (module docstring)
            kd = apply_calibration("absolute", c.k_a_direct, eta=eta)
            k = kd / (1.0 - c.stray_fraction)
            if "absolute_ratio_se" in extra:
                # = eta R / G_d / ideal: its SE by the delta method over the replicates (the backend's)
                se = abs(k) * _rel(extra["absolute_ratio_se"], extra["absolute_ratio"])
            else:
                se = abs(k) * math.hypot(_rel(c.k_a_direct_se, c.k_a_direct),
                                         c.stray_fraction_se / (1.0 - c.stray_fraction))
            # (SEs of the same replicates, each with at least se_dof degrees of freedom)
            return CellResult(c.tan_eps, c.beta_deg, k, se, c.samples, c.seconds, extra, error_bound=bound,
                              converged=c.converged and eta_ok, k_a_direct=kd, k_a_direct_se=c.k_a_direct_se * eta,
                              stray_fraction=c.stray_fraction, stray_fraction_se=c.stray_fraction_se,
                              se_dof=c.se_dof, **conf)
        # eta is computed, not sampled: the SE keeps its degrees of freedom
        return CellResult(c.tan_eps, c.beta_deg, apply_calibration("absolute", c.k_a, eta=eta), c.se * eta,
                          c.samples, c.seconds, extra,
                          error_bound=bound, converged=c.converged and eta_ok, se_dof=c.se_dof, **conf)

    def _reference(self, c: CellResult, r: CellResult) -> CellResult:
        k = apply_calibration("reference", c.k_a, reference_reading=r.k_a)
        dof = math.nan
        if math.isfinite(c.se) or math.isfinite(r.se):
            rel = math.hypot(_rel(c.se, c.k_a), _rel(r.se, r.k_a))
            se, bound = abs(k) * rel, math.nan
            # two independent estimates: the effective degrees of freedom of their sum of variances
            dof = welch_satterthwaite([_rel(c.se, c.k_a) ** 2, _rel(r.se, r.k_a) ** 2], [c.se_dof, r.se_dof])
        else:
            se, bound = math.nan, abs(k) * (_rel(c.error_bound, c.k_a) + _rel(r.error_bound, r.k_a))
        # confidence bounds (the RQMC reference) add like the deterministic bounds; the sum holds
        # whenever both hold, so its level is at least 1 - (1 - L_c) - (1 - L_r) (Bonferroni)
        conf = {}
        if math.isfinite(c.confidence_bound) and math.isfinite(r.confidence_bound):
            conf = dict(confidence_bound=abs(k) * (_rel(c.confidence_bound, c.k_a) + _rel(r.confidence_bound, r.k_a)),
                        confidence_level=1.0 - ((1.0 - c.confidence_level) + (1.0 - r.confidence_level)))
        extra = {**(c.extra or {}), "calibration": "reference", "k_a_lambert": c.k_a,
                 "k_a_lambert_reference": r.k_a}
        stray = {}
        if c.stray_fraction != 0.0 or r.stray_fraction != 0.0:
            kd = apply_calibration("reference", c.k_a_direct, reference_reading=r.k_a_direct)
            stray = dict(k_a_direct=kd, k_a_direct_se=abs(kd) * math.hypot(_rel(c.k_a_direct_se, c.k_a_direct),
                                                                          _rel(r.k_a_direct_se, r.k_a_direct)),
                         stray_fraction=c.stray_fraction, stray_fraction_se=c.stray_fraction_se)
            dof = float(np.fmin(dof, welch_satterthwaite(
                [_rel(c.k_a_direct_se, c.k_a_direct) ** 2, _rel(r.k_a_direct_se, r.k_a_direct) ** 2],
                [c.se_dof, r.se_dof])))
        return CellResult(c.tan_eps, c.beta_deg, k, se, c.samples + r.samples, c.seconds + r.seconds, extra,
                          error_bound=bound, converged=c.converged and r.converged, se_dof=dof, **conf, **stray)

    def _unity(self, tan_eps: float, beta_deg: float, c: CellResult | None = None) -> CellResult:
        """k_A = 1 exactly (the reference is the sample); with stray light the sample's stray fraction
        from its own computation ``c``."""
        deterministic = self.deterministic     # the registry's BackendInfo.deterministic (make_backend)
        stray = {} if c is None else dict(k_a_direct=1.0, k_a_direct_se=0.0, stray_fraction=c.stray_fraction,
                                           stray_fraction_se=c.stray_fraction_se)
        return CellResult(float(tan_eps), float(beta_deg), 1.0, math.nan if deterministic else 0.0,
                          0 if c is None else c.samples, 0.0 if c is None else c.seconds,
                          {"calibration": "reference", "note": "the reference is the sample: k_A = 1 exactly"},
                          error_bound=0.0 if deterministic else math.nan, converged=True, **stray)

    @property
    def rtol(self) -> float:
        """The wrapped backend's target (the RQMC reference's ``rtol``, for the validator)."""
        return self.inner.rtol

    def compute_cell(self, tan_eps: float, beta_deg: float, rtol: float | None = None) -> CellResult:
        """One cell with the wrapped backend's target ``rtol`` for this cell (the validator asks the
        RQMC reference for the bound each cell's test needs); in the reference mode each of the two
        readings is asked for half of it, since their bounds add. Only a wrapped backend with its own
        ``compute_cell`` has one (user audit: ``validate`` of an instrument calibrated absolute or
        against a reference ended in an AttributeError traceback with the exit status of a disagreement)."""
        t, b = float(tan_eps), float(beta_deg)
        if self.mode == "lambert":
            return self.inner.compute_cell(t, b, rtol=rtol)
        if self.mode == "absolute":
            return self._absolute(self.inner.compute_cell(t, b, rtol=rtol))
        if self.identical:
            return self._unity(t, b)
        half = None if rtol is None else 0.5 * rtol
        r = self.reference_inner.compute_cell(t, b, rtol=half)
        return self._reference(self.inner.compute_cell(t, b, rtol=half), r)

    # -- the KaBackend interface --------------------------------------------------------------
    def compute(self, cells: Sequence[tuple[float, float]],
                on_cell: Callable[[CellResult], None] | None = None) -> list[CellResult]:
        cells = [(float(t), float(b)) for t, b in cells]
        if self.mode == "lambert":
            return self.inner.compute(cells, on_cell=on_cell)
        out: list[CellResult] = []

        def emit(c: CellResult) -> None:
            out.append(c)
            if on_cell is not None:
                on_cell(c)

        if self.mode == "absolute":
            self.inner.compute(cells, on_cell=lambda c: emit(self._absolute(c)))
            return out
        if self.identical:
            if getattr(self.inner, "stray_light", False):
                # k_A = 1, but the stray fraction of the sample is still to be computed
                self.inner.compute(cells, on_cell=lambda c: emit(self._unity(c.tan_eps, c.beta_deg, c)))
                return out
            for t, b in cells:
                emit(self._unity(t, b))
            return out
        for a in range(0, len(cells), REFERENCE_CHUNK):
            chunk = cells[a:a + REFERENCE_CHUNK]
            refs = {_key(r.tan_eps, r.beta_deg): r for r in self.reference_inner.compute(chunk)}
            # on_cell is called inside compute(), in this iteration, with this chunk's refs (B023 cannot tell)
            self.inner.compute(chunk, on_cell=lambda c: emit(self._reference(c, refs[_key(c.tan_eps, c.beta_deg)])))  # noqa: B023
        return out


def _key(t: float, b: float) -> tuple[float, float]:
    return (round(float(t), 9), round(float(b), 9))


def _rel(err: float, k: float) -> float:
    return abs(err / k) if math.isfinite(err) and k != 0 else (0.0 if not math.isfinite(err) else math.inf)


def calibrated(make_inner: InnerFactory, instrument: Instrument, model: RoadModel,
               inner: KaBackend | None = None, *, deterministic: bool = False) -> KaBackend:
    """``make_inner(instrument, model)`` in the instrument's calibration mode: the plain backend for
    ``lambert``, a :class:`CalibratedBackend` otherwise (``deterministic``: as there)."""
    if instrument.calibration.is_default:
        return inner if inner is not None else make_inner(instrument, model)
    return CalibratedBackend(make_inner, instrument, model, inner=inner, deterministic=deterministic)
