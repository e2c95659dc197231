"""Road BRDFs *outside* the paper's eq. 4: known surfaces for round trips of the correction
(``bench/bench_outside.py``, ``tests/system/test_correct_outside.py``). They are not fitted to
anything and make no claim to describe a real pavement; each is smooth, positive, isotropic and
differs from eq. 4 in a way the issue names (docs/correction.md, "How well it works (outside eq. 4)").

The interface is the one the float64 backends evaluate (:mod:`roadgonio.engines.montecarlo`,
:mod:`roadgonio.engines.reference`) and :class:`roadgonio.surface.model.RoadModel` provides too:

* ``evaluate(xp, wi, wo)`` -- f_r (sr^-1) for component triples of unit vectors (towards the
  source, towards the detector), 0 below the horizon;
* ``brdf(wi, wo)`` -- the same for numpy arrays of shape (..., 3);
* ``mirror_kink`` -- whether f has a kink on the mirror plane (|beta| = 0) that an integrator should
  split on (none of these does);
* ``name``, ``to_json_dict()``, ``q(tan_eps, beta_deg)``, ``r(tan_eps, beta_deg)``;
* ``numpy_only`` -- whether ``evaluate`` runs in numpy alone; the others run unchanged over the
  Dr.Jit namespace too, so the Mitsuba backend renders them (the ``roadbsdf`` plugin's
  ``set_surface``), housings and stray light included;
* ``sampling_lobe_exponent`` -- the exponent n of the (cos Omega)^n lobe about the mirror direction
  that the Mitsuba plugin mixes with cosine sampling for this surface (a choice of importance
  sampling only: any n > 0 gives the same expectation; 0 = cosine sampling alone).

Surfaces (``make_truth(kind)``; angles as in docs/conventions.md section 1):

``microfacet``
    a diffuse term plus a GGX (Trowbridge-Reitz) microfacet lobe with Smith height-correlated
    masking-shadowing (the published form and its source: docs/correction.md, "How well it works
    (outside eq. 4)")::

        f = k_d + k_s D(h) G2(w_i, w_o) / (4 cos ti cos tr)
        D = a^2 / (pi (a^2 cos^2 th + sin^2 th)^2),  G2 = 1 / (1 + L(w_i) + L(w_o)),
        L(w) = (sqrt(1 + a^2 tan^2 theta) - 1) / 2

    Its lobe lives in the half vector, not the mirror direction, and its masking gives it an
    alpha dependence eq. 4 (without g) does not have.
``two_lobes``
    a diffuse term, a Beckmann lobe in the half vector and a Cauchy lobe in the angle Omega to the
    mirror direction (a narrow peak with heavy tails, unlike Phong's cos^n)::

        f = k_d + k_b exp(-tan^2 th / m^2) / (pi m^2 cos^4 th) + k_c / (1 + (Omega / w)^2)^(3/2)

``table``
    a CIE table (default R3) made a BRDF: the table's ln r, smoothed on its grid to the precision of
    its 2-3 printed digits (:func:`_smoothed_ln_r`: 3.1 % RMS, at most 23 %, from R3 -- the grazing cells printed with one or two digits move most), is interpolated by a
    bicubic spline over (ln sec eps, ln(1 + beta / 20 deg)), even in beta at 0 and 180 deg, continued beyond tan eps 12 with its slope in ln sec eps bending to at
    most -2 (q grows at most like 1 / cos eps); q = r / cos^3 theta_i. Off alpha = 1 deg the table
    follows the mirror direction: r is read at the polar angle ``theta_i + kappa (alpha - 1 deg)``
    (kappa = 1; eq. 4's empirical term moves the other way, e = theta_i theta_r / theta_r*), and
    the whole BRDF is scaled by ``(sin alpha / sin 1 deg)^gamma`` (gamma = 0.5, a masking-like law).

``eq4``
    inside the family, for comparison: the paper's eq. 4 (power reading) with parameters close to
    the fit of CIE R3 (:data:`R3LIKE`), as a :class:`~roadgonio.surface.model.RoadModel`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from roadgonio.errors import InputError
from roadgonio.geometry import (ALPHA_STANDARD_DEG, BETA_GRID_DEG, TAN_EPS_GRID, cos3_eps, eps_from_tan, pair_angles,
                                w_detector, w_source)
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import RoadModel, RoadParams

#: eq. 4 (power reading) close to the fit of CIE R3: the truth inside the family.
R3LIKE = dict(k_diff=0.028937, k_phong=1.8147, n_phong=34.467, k_retro=0.052577, n_retro=11.307,
              k_exp=0.088927, p=2.137, h=0.49843, mu=0.03123)
KINDS = ("microfacet", "two_lobes", "table", "eq4")


def _s_beta(beta_deg):
    """ln(1 + beta / 20 deg): a beta coordinate in which the CIE columns are about evenly spaced."""
    return np.log1p(np.asarray(beta_deg, dtype=np.float64) / 20.0)


def _ln_sec(eps_deg):
    """ln(1 / cos eps): the coordinate in which the table truth's spline runs along eps."""
    return -np.log(np.cos(np.radians(eps_deg)))


def _smoothed_ln_r(r: np.ndarray, mu: float) -> np.ndarray:
    """ln r of a CIE table on its full grid, smoothed (a Whittaker smoother: weighted least squares
    with ``mu`` times the squared second differences along tan eps and, from beta = 10 deg on, along
    beta, so the peak at beta 0-5 deg keeps its shape). The weight of a cell is 1 / sigma^2 with
    sigma = 0.01 + 0.5 / (r x 1e4), the precision of a table printed to 2-3 digits; blank cells get
    the last complete row's beta profile with sigma = 0.3, enough to steer the extrapolation."""
    filled = r.copy()
    full = np.all(np.isfinite(r), axis=1)
    last = int(np.max(np.nonzero(full)[0]))
    for i in range(r.shape[0]):
        blank = ~np.isfinite(r[i])
        if blank.any():
            jl = int(np.max(np.nonzero(~blank)[0]))
            filled[i, blank] = r[i, jl] * r[last, blank] / r[last, jl]
    nt, nb = r.shape
    sigma = np.where(np.isfinite(r), 0.01 + 0.5 / (filled * 1e4), 0.3)
    w = (1.0 / sigma ** 2).ravel()
    idx = np.arange(nt * nb).reshape(nt, nb)
    rows = [(idx[i - 1, j], idx[i, j], idx[i + 1, j]) for i in range(1, nt - 1) for j in range(nb)]
    rows += [(idx[i, j - 1], idx[i, j], idx[i, j + 1]) for i in range(nt) for j in range(3, nb - 1)]
    D = np.zeros((len(rows), nt * nb))
    for k, (a, b, c) in enumerate(rows):
        D[k, a], D[k, b], D[k, c] = 1.0, -2.0, 1.0
    s = np.linalg.solve(np.diag(w) + mu * D.T @ D, w * np.log(filled).ravel())
    return s.reshape(nt, nb)


def _np_triple(w) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = np.asarray(w, dtype=np.float64)
    return w[..., 0], w[..., 1], w[..., 2]


def renders_in_drjit(surface) -> bool:
    """Whether the Mitsuba ``roadbsdf`` can render ``surface`` through its ``set_surface``: it has
    ``evaluate(xp, wi, wo)`` and is not ``numpy_only`` (module docstring). Eq. 4 itself (a
    :class:`~roadgonio.surface.model.RoadModel`) goes through ``set_model`` and is not asked here."""
    return hasattr(surface, "evaluate") and not getattr(surface, "numpy_only", True)


class EvaluatedBRDF:
    """``brdf``, ``q`` and ``r`` of a surface from its ``evaluate(xp, wi, wo)`` (module docstring): the
    truths below and the correction's fitted surface
    (:class:`roadgonio.surface.correction_surface.CorrectedSurface`) share them."""

    def evaluate(self, xp, wi, wo):  # pragma: no cover - abstract
        raise NotImplementedError

    def brdf(self, wi, wo) -> np.ndarray:
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        wi, wo = np.broadcast_arrays(wi, wo)
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            return np.asarray(self.evaluate(NumpyOps, _np_triple(wi), _np_triple(wo)), dtype=np.float64)

    def q(self, tan_eps, beta_deg, alpha_deg=ALPHA_STANDARD_DEG, delta_deg=0.0) -> np.ndarray:
        return self.brdf(w_source(eps_from_tan(tan_eps), beta_deg, delta_deg), w_detector(alpha_deg, delta_deg))

    def r(self, tan_eps, beta_deg, alpha_deg=ALPHA_STANDARD_DEG, delta_deg=0.0) -> np.ndarray:
        return self.q(tan_eps, beta_deg, alpha_deg, delta_deg) * cos3_eps(tan_eps)


@dataclass(frozen=True)
class TruthBRDF(EvaluatedBRDF):
    """Base of the surfaces of this module (module docstring): subclasses define :meth:`evaluate`."""

    name: str = "truth"
    params: Mapping[str, float] = field(default_factory=dict)

    kind = "truth"
    mirror_kink = False
    is_lambertian = False
    variant = "truth"
    numpy_only = False

    @property
    def sampling_lobe_exponent(self) -> float:
        return 0.0

    def to_json_dict(self) -> dict[str, Any]:
        return {"truth": self.kind, "name": self.name, "params": dict(self.params)}


def _upper(xp, wi, wo, f):
    zero = 0.0 * (wi[2] + wo[2])
    return xp.where((wi[2] > 0.0) & (wo[2] > 0.0), f, zero)


@dataclass(frozen=True)
class MicrofacetTruth(TruthBRDF):
    """Diffuse + GGX lobe with Smith height-correlated masking-shadowing (module docstring)."""

    kind = "microfacet"

    @property
    def sampling_lobe_exponent(self) -> float:
        """A GGX lobe of roughness a is about a wide in the half vector, 2a about the mirror
        direction: n ~ 2 / (2a)^2 (the width of (cos Omega)^n is sqrt(2 / n))."""
        a = float(self.params["a"])
        return max(1.0, 0.5 / (a * a))

    def evaluate(self, xp, wi, wo):
        k_d, k_s, a = self.params["k_d"], self.params["k_s"], self.params["a"]
        ci, co = wi[2], wo[2]
        hx, hy, hz = wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]
        h2 = hx * hx + hy * hy + hz * hz
        c2 = hz * hz / h2                                     # cos^2 theta_h
        a2 = a * a
        den = a2 * c2 + (1.0 - c2)
        d = a2 / (math.pi * den * den)

        def lam(z):
            z2 = xp.maximum(z * z, 1e-300)
            return 0.5 * (xp.sqrt(1.0 + a2 * (1.0 - z2) / z2) - 1.0)
        g2 = 1.0 / (1.0 + lam(ci) + lam(co))
        f = k_d + k_s * d * g2 / (4.0 * xp.maximum(ci * co, 1e-300))
        return _upper(xp, wi, wo, f)


@dataclass(frozen=True)
class TwoLobesTruth(TruthBRDF):
    """Diffuse + Beckmann lobe (half vector) + Cauchy lobe (angle to the mirror direction)."""

    kind = "two_lobes"

    @property
    def sampling_lobe_exponent(self) -> float:
        """The narrow Cauchy lobe, of half-width w about the mirror direction: n ~ 2 / w^2."""
        w = float(self.params["w_rad"])
        return 2.0 / (w * w)

    def evaluate(self, xp, wi, wo):
        P = self.params
        m2 = P["m"] * P["m"]
        hx, hy, hz = wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]
        h2 = hx * hx + hy * hy + hz * hz
        c2 = hz * hz / h2
        tan2 = (1.0 - c2) / c2
        beck = xp.exp(-tan2 / m2) / (math.pi * m2 * c2 * c2)
        # angle to the mirror direction R(w_i) = (-x, -y, z): Omega = 2 asin(|w_o - R(w_i)| / 2)
        chord = xp.sqrt((wo[0] + wi[0]) ** 2 + (wo[1] + wi[1]) ** 2 + (wo[2] - wi[2]) ** 2)
        s = xp.minimum(0.5 * chord, 1.0)
        omega = 2.0 * xp.atan2(s, xp.sqrt(xp.maximum(1.0 - s * s, 0.0)))
        x = omega / P["w_rad"]
        cauchy = xp.exp(-1.5 * xp.log(1.0 + x * x))
        f = P["k_d"] + P["k_b"] * beck + P["k_c"] * cauchy
        return _upper(xp, wi, wo, f)


@dataclass(frozen=True)
class TableTruth(TruthBRDF):
    """A CIE table made a BRDF with its own alpha dependence (module docstring). Numpy only."""

    table_name: str = "R3"
    kind = "table"
    numpy_only = True

    def __post_init__(self):
        from scipy.interpolate import RectBivariateSpline

        from roadgonio.surface.rtable import bundled_table
        tab = bundled_table(self.table_name)
        lr = _smoothed_ln_r(tab.r, float(self.params["smoothing"]))
        sb = _s_beta(BETA_GRID_DEG)
        # even in beta about 0 and 180 deg: mirror three columns on each side
        sb_ext = np.r_[-sb[3:0:-1], sb, 2.0 * sb[-1] - sb[-2:-5:-1]]
        lr_ext = np.c_[lr[:, 3:0:-1], lr, lr[:, -2:-5:-1]]
        x = _ln_sec(np.degrees(np.arctan(TAN_EPS_GRID)))
        spline = RectBivariateSpline(x, sb_ext, lr_ext, kx=3, ky=3, s=0)
        object.__setattr__(self, "_spline", spline)
        object.__setattr__(self, "_x_max", float(x[-1]))
        res = (lr - np.log(tab.r))[tab.mask]
        object.__setattr__(self, "residual", (float(np.sqrt(np.mean(res ** 2))), float(np.max(np.abs(res)))))

    def ln_r(self, eps_deg, beta_deg) -> np.ndarray:
        """ln r at alpha = 1 deg. Beyond the last row (tan eps 12, x = ln sec eps = x_e) ln r
        continues with the spline's slope s_e in x, bending (C^1, over 0.5 in x) to the slope
        min(s_e, -2): q = r sec^3 eps grows at most like 1 / cos eps, so q cos eps stays bounded."""
        x = _ln_sec(np.asarray(eps_deg, dtype=np.float64))
        sb = _s_beta(np.asarray(beta_deg, dtype=np.float64))
        xe, w = self._x_max, 0.5
        inside = self._spline.ev(np.minimum(x, xe), sb)
        s_e = self._spline.ev(np.full_like(x, xe), sb, dx=1)
        d = np.minimum(s_e, -2.0) - s_e
        dx = np.maximum(x - xe, 0.0)
        bend = np.minimum(dx, w)
        return inside + s_e * dx + d * (0.5 * bend * bend / w + np.maximum(dx - w, 0.0))

    def evaluate(self, xp, wi, wo):
        if xp is not NumpyOps:
            raise InputError("the table truth evaluates in numpy only", field="xp")
        wix, wiy, wiz = (np.asarray(c, dtype=np.float64) for c in wi)
        wox, woy, woz = (np.asarray(c, dtype=np.float64) for c in wo)
        wix, wiy, wiz, wox, woy, woz = np.broadcast_arrays(wix, wiy, wiz, wox, woy, woz)
        alpha0 = math.radians(ALPHA_STANDARD_DEG)
        sin_ti = np.hypot(wix, wiy)
        theta_i = np.arctan2(sin_ti, wiz)
        alpha = np.arctan2(woz, np.hypot(wox, woy))
        eps_eq = np.degrees(np.clip(theta_i + self.params["kappa"] * (alpha - alpha0), 0.0, math.radians(89.9)))
        eps_i = np.degrees(np.minimum(theta_i, math.radians(89.9)))
        # beta of the pair (0 at the pole, as the correction surface); theta_i stays hypot's (the
        # truth's own form: pair_angles' sqrt(x^2 + y^2) differs from it in the last bit)
        beta = np.degrees(pair_angles(NumpyOps, (wix, wiy, wiz), (wox, woy, woz), pole=0.0)[2])
        mask = (np.maximum(np.sin(alpha), 1e-300) / math.sin(alpha0)) ** self.params["gamma"]
        q = np.exp(self.ln_r(eps_eq, beta) + 3.0 * _ln_sec(eps_i))
        return np.where((wiz > 0.0) & (woz > 0.0), q * mask, 0.0)

    def to_json_dict(self) -> dict[str, Any]:
        return {**super().to_json_dict(), "table": self.table_name}


#: Parameters of the bundled truths (chosen by hand: S1 and Q0 in the range of the CIE tables).
TRUTH_PARAMS: dict[str, dict[str, float]] = {
    "microfacet": {"k_d": 0.026, "k_s": 0.07, "a": 0.35},
    "two_lobes": {"k_d": 0.022, "k_b": 0.12, "m": 0.32, "k_c": 3.0, "w_rad": math.radians(8.0)},
    "table": {"kappa": 1.0, "gamma": 0.5, "smoothing": 10.0},
}


def make_truth(kind: str, **params: float):
    """One of the surfaces of the module docstring, with :data:`TRUTH_PARAMS` changed by ``params``."""
    if kind == "eq4":
        return RoadModel(RoadParams(**{**R3LIKE, **params}), "power", name="eq4-R3-like")
    cls = {"microfacet": MicrofacetTruth, "two_lobes": TwoLobesTruth, "table": TableTruth}.get(kind)
    if cls is None:
        raise InputError(f"unknown truth {kind!r}; expected one of {', '.join(KINDS)}", field="truth")
    unknown = sorted(set(params) - set(TRUTH_PARAMS[kind]))
    if unknown:
        raise InputError(f"unknown parameter(s) {', '.join(unknown)} of the {kind} truth", field="params")
    return cls(name=kind, params={**TRUTH_PARAMS[kind], **params})
