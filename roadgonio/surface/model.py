"""The road BRDF model (paper eq. 4 and Figure 3; docs/conventions.md section 3).

    f_r = [ k_diff + k_phong (cos Omega)^n_phong + k_retro (cos Omega')^n_retro + E ]
          * g(theta_i) g(theta_r) / g(theta_r*)

This module holds the **one** definition of the model: :func:`road_brdf` is a pure function over
an array namespace ``xp`` (:class:`NumpyOps` here; the Dr.Jit plugin passes its own namespace with
the same names), so the numpy quadrature integrator, the fitter and the Mitsuba plugin evaluate
exactly the same formula.

Numerical form (chosen so that float32 is accurate near the lobe peaks and nothing overflows):

* lobes: ``cos Omega = 1 - h`` with the half-chord ``h = |w_o - R(w_i)|^2 / 2``
  (``R`` = mirror about the normal), and ``cos^n = exp(n log(1 - h))``. A negative cosine
  (``h >= 1``) contributes 0.
* theta_i, theta_r and beta: :func:`roadgonio.geometry.pair_angles` (beta =
  ``atan2(|w_i x w_o|_z, -(w_i . w_o)_xy)``, exact near 0 and 180 deg); where the azimuth is
  undefined (``theta_i = 0`` or ``theta_r = 0``) beta is taken as 180 deg, so E = 0 there.
* E in log space: ``E = k_exp exp(p ln f + W ln x)`` with ``W = exp(min(1 + h f^2, 80))`` (power
  reading) or ``W = 1`` and an extra factor ``exp(min(1 + h f^2, 80))`` (product reading);
  the total exponent is capped at 80, so E never overflows float32. ``ln x`` and the smooth
  extension's ``L = -ln x_s`` are ``log1m(beta/pi)`` and ``-log1m(sin^2(beta/2))`` below beta =
  90 deg (accurate near 0) and ``ln(beta_s/pi)``, ``-ln sin^2(beta_s/2)`` above it, with ``beta_s =
  pi - beta`` from :func:`roadgonio.geometry.pair_angles` (``atan2`` of the same cross product,
  accurate near 180 deg), x and x_s floored at :data:`X_FLOOR`; ``W L^n_beta`` is
  ``exp(min(ln W + n_beta ln L, 80))`` (0 where L = 0). Until session 13 x and x_s near 180 deg
  were ``1 - beta/pi`` and ``1 - sin^2(beta/2)``: in float32 they cancelled and their floor
  ``1 - 1e-7`` became 1.19e-7, so the plugin's E was up to 3 % off there (the float64 values agree
  with today's to 1e-7 relative, today's being the more accurate against 80-bit arithmetic).

Variants:

* ``"power"`` (default): ``E = k_exp f(e)^p x^(exp(1 + h f(e)^2))``, ``x = (pi - beta)/pi``.
* ``"product"``: the printed paper read literally, ``E = k_exp f(e)^p x exp(1 + h f(e)^2)``.
  docs/conventions.md section 3 explains why the power reading is the default.
* ``"smooth"`` (roadgonio extension, not in the paper):
  ``E = k_exp f(e)^p exp(-W L(beta)^n_beta)``, ``W = exp(1 + h sqrt(f(e)))``,
  ``L(beta) = -ln x_s``, ``x_s = cos^2(beta/2) = (1 + cos beta)/2``.
  With ``n_beta = 1`` (its default) this is ``k_exp f^p x_s^W``. It uses one parameter more than
  the paper's model, ``n_beta``, the exponent of the beta profile; the other variants ignore it
  (:class:`RoadModel` holds it at its default there, and their model files refuse another value).
  Why: the paper's model (fitted by roadgonio.surface.fit) misses the paper's own target (max 9 %, RMS
  2.6 % of max r) on R3 and R4. Where its residual sits (``roadgonio fit R3 --variant power``
  prints the worst cells; residuals.csv / fit.png hold the map): ~45 % of the squared residual in
  the peak columns beta = 0...10 deg at tan eps >= 1.5 (signs alternating from column to column,
  and the beta = 0 peak 11-16 % too low at tan eps >= 9), ~40 % at tan eps <= 1.25 (the model
  is up to 12 % too high at beta = 15...75 deg, tan eps = 1...1.5), the rest < 20 %. ``x^W``
  has one fixed peak shape (a cusp, ``exp(-W beta/pi)`` near beta = 0) and ``exp(h f^2)``
  narrows it too fast towards grazing, so one W cannot fit the broad hump at tan eps ~ 1 and
  the narrow grazing peak at once. ``L`` is ``sin^2(beta/2)`` near 0, so ``L^n_beta`` is a
  stretched profile between a Gaussian (``n_beta = 1``, flat top) and a cusp (``n_beta = 1/2``:
  ``L^(1/2) ~ beta/2``, the lower bound) - the fits choose 0.5 (R1) ... 1.06 (C1); ``sqrt(f)`` slows the
  narrowing. ``L`` grows to ``-ln(1e-7)`` at beta = 180 deg (``x_s`` is floored at 1e-7, as
  ``x`` is), so E is ~0 there unless W is tiny.
  Measured fits (bench/bench_fit.py), max / RMS in % of max r, power -> smooth:
  R1 4.2/1.55 -> 4.3/1.47, R2 9.1/3.0 -> 5.5/1.85, R3 12.3/4.0 -> 7.2/2.27,
  R4 16.6/5.4 -> 7.7/2.12, C1 3.5/1.17 -> 2.7/0.77, C2 8.8/3.1 -> 7.8/2.21.

Rounding at the mirror plane (roadgonio extension, every variant): ``beta_round_deg`` = b_c > 0
replaces the empirical term's beta by ``beta^2 / sqrt(beta^2 + b_c^2)`` (:func:`rounded_beta`), so
its cusp at beta = 0 (the power reading's ``exp(-W beta / pi)``, the smooth one's at n_beta < 1)
becomes a smooth top of width ~b_c, as the term of any BRDF differentiable in the direction is;
0 (the default) is the paper's model. The fits of tables never change it; the correction's
backbone can hold it (docs/correction-record.md, "The backbone's cusp at the mirror plane").

Parameter bounds (checked by :class:`RoadParams`): every ``k_*`` in [0, 1e6] sr^-1;
``n_phong``, ``n_retro`` in [0, 1e5]; ``p`` in [0, 50]; ``h`` in [-1e3, 1e3]; ``mu`` in [0, 1e3];
``g_a``, ``g_b``, ``g_c`` finite with ``g_a t^2 + g_b t + g_c > 0`` on [theta_l, pi/2]; ``g_t`` in
[-100, 100]; ``theta_l_deg`` in (85.3, 90]; ``beta_round_deg`` in [0, 10]; ``n_beta`` in [0.5, 4] (dimensionless; below 1/2
the profile would be steeper than a cusp at beta = 0, where a rounding-level beta would change E).
Within these bounds and for directions in the upper hemisphere the model is finite and
non-negative (tested); below the horizon it is 0.
"""
from __future__ import annotations

import json
import math
import numbers
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from roadgonio.arrays import NumpyOps
from roadgonio.errors import InputError
from roadgonio.geometry import ALPHA_STANDARD_DEG, cos3_eps, eps_from_tan, pair_angles, w_detector, w_source

#: Observation polar angle of the fitted tables, theta_r* (paper, Figure 3).
THETA_R_STAR_DEG = 89.0
THETA_R_STAR = math.radians(THETA_R_STAR_DEG)
#: Smallest positive number used to keep logarithms finite (fits float32's normal range).
TINY = 1e-30
#: Cap on exponents, so that exp() never overflows float32 (exp(88.7) does).
EXP_CAP = 80.0
#: An exponent within this of :data:`EXP_CAP` counts as reaching it (:meth:`RoadModel.exponent_capped`):
#: a fit pressed against the cap sits there to ~1e-7.
EXP_CAP_REACHED = 1e-4
#: Floor of the empirical term's x and x_s, which vanish at beta = 180 deg (so ln x, ln x_s stay
#: finite). 1e-7 is one number in float32 and float64 alike (relative difference 1.2e-8).
X_FLOOR = 1e-7

VARIANTS = ("power", "product", "smooth")
DEFAULT_VARIANT = "power"

PARAM_NAMES = ("k_diff", "k_phong", "n_phong", "k_retro", "n_retro", "k_exp", "p", "h", "mu",
               "g_a", "g_b", "g_c", "g_t", "theta_l_deg", "n_beta", "beta_round_deg")
#: Parameters used only by some variants (the others ignore them, and the fit leaves them alone).
VARIANT_PARAMS: dict[str, tuple[str, ...]] = {"power": (), "product": (), "smooth": ("n_beta",)}


def variant_param_names(variant: str) -> tuple[str, ...]:
    """The parameters ``variant`` uses, in :data:`PARAM_NAMES` order: every one but the other
    variants' own (:data:`VARIANT_PARAMS`), e.g. all but ``n_beta`` for ``power``."""
    others = {k for v, own in VARIANT_PARAMS.items() if v != variant for k in own}
    return tuple(k for k in PARAM_NAMES if k not in others or k in VARIANT_PARAMS.get(variant, ()))


#: Lower and upper bounds of each parameter (inclusive unless noted in the module docstring).
PARAM_BOUNDS: dict[str, tuple[float, float]] = {
    "k_diff": (0.0, 1e6), "k_phong": (0.0, 1e6), "k_retro": (0.0, 1e6), "k_exp": (0.0, 1e6),
    "n_phong": (0.0, 1e5), "n_retro": (0.0, 1e5), "p": (0.0, 50.0), "h": (-1e3, 1e3),
    "mu": (0.0, 1e3), "g_a": (-1e6, 1e6), "g_b": (-1e6, 1e6), "g_c": (-1e6, 1e6),
    "g_t": (-100.0, 100.0), "theta_l_deg": (85.3, 90.0), "n_beta": (0.5, 4.0),
    "beta_round_deg": (0.0, 10.0),
}


# ----------------------------------------------------------------------------------------------
# The model, written once
# ----------------------------------------------------------------------------------------------

def active_terms(params: Mapping[str, Any]) -> frozenset[str]:
    """Terms that cost something: the lobes/E with a non-zero coefficient and g if theta_l < 90.

    Only usable with plain-float parameters; the Dr.Jit plugin computes it once from the
    float values and re-traces when it changes.
    """
    terms = {name for name in LINEAR_TERMS if float(params[name]) != 0.0}
    return frozenset(terms) | modifier_terms(params)


def modifier_terms(params: Mapping[str, Any]) -> frozenset[str]:
    """The structural terms that shape the others rather than add to them: "g" (the grazing
    attenuation) if theta_l < 90 deg, "round" (the mirror plane's rounding) if beta_round_deg > 0.
    A caller evaluating one term at a time (a column of a fit) adds these to it."""
    terms = set()
    if float(params["theta_l_deg"]) < 90.0:
        terms.add("g")
    if float(params.get("beta_round_deg", 0.0)) > 0.0:
        terms.add("round")
    return frozenset(terms)


def rounded_beta(xp, beta, beta_round_deg, supplement=None):
    """The empirical term's beta with its mirror-plane cusp rounded (docs/conventions.md section 3):
    ``beta^2 / sqrt(beta^2 + b_c^2)``, b_c = ``beta_round_deg`` (radians in, radians out). Quadratic
    in beta below b_c (so the term is smooth across the mirror plane), beta - b_c^2 / (2 beta) above
    it; beta itself at b_c = 0 (up to rounding, so :func:`road_brdf` applies it only where
    ``beta_round_deg > 0``).

    With ``supplement`` (pi - beta, :func:`roadgonio.geometry.pair_angles`): the pair (rounded beta,
    pi - rounded beta), the latter formed as ``(pi - beta) + beta b_c^2 / (s (s + beta))``, s =
    ``sqrt(beta^2 + b_c^2)``: a sum of two non-negative terms, so it keeps its relative precision
    near beta = pi, where ``pi - rounded beta`` would cancel."""
    bc = beta_round_deg * (math.pi / 180.0)
    b2 = beta * beta
    s = xp.sqrt(xp.maximum(b2 + bc * bc, TINY))
    rounded = b2 / s
    if supplement is None:
        return rounded
    return rounded, supplement + beta * (bc * bc) / (s * (s + beta))


def _lobe_base(xp, h):
    """What a lobe (:func:`_lobe`) takes from its half-chord h alone: (cos Omega > 0, ln cos Omega, a zero)."""
    hc = xp.minimum(h, 0.9999999)
    return h < 1.0, xp.log1m(hc), 0.0 * h


def _lobe_of(xp, base, n):
    """(cos Omega)^n from :func:`_lobe_base`."""
    inside, ln_cos, zero = base
    return xp.where(inside, xp.exp(n * ln_cos), zero)


def _lobe(xp, h, n):
    """(cos Omega)^n with cos Omega = 1 - h; 0 where the cosine is not positive."""
    return _lobe_of(xp, _lobe_base(xp, h), n)


def _phong_h(xp, wi, wo):
    wix, wiy, wiz = wi
    wox, woy, woz = wo
    return 0.5 * ((wox + wix) ** 2 + (woy + wiy) ** 2 + (woz - wiz) ** 2)


def phong_lobe(xp, wi, wo, n):
    """(cos Omega)^n of the Phong lobe about the mirror direction ``R(w_i) = (-x, -y, z)``:
    ``cos Omega = 1 - h`` with the half-chord ``h = |w_o - R(w_i)|^2 / 2`` (module docstring);
    ``wi``, ``wo`` component triples. The lobe's shape, once: :func:`road_brdf` and the density
    of the plugin's lobe sampling (``plugins/road_bsdf.py``) both take it from here."""
    return _lobe(xp, _phong_h(xp, wi, wo), n)


def _kept(pairs, key, make):
    """``make()``, kept in ``pairs`` under ``key`` when the caller keeps one (:func:`road_brdf`)."""
    if pairs is None or key is None:
        return make()
    v = pairs.get(key)
    if v is None:
        v = pairs[key] = make()
    return v


def _round_key(v):
    """A parameter as a key of :func:`road_brdf`'s ``pairs``: plain numbers only (None: not kept)."""
    return float(v) if isinstance(v, (int, float, np.floating)) and not isinstance(v, bool) else None


def g_attenuation(xp, P: Mapping[str, Any], theta):
    """Grazing attenuation g(theta) = (a theta^2 + b theta + c)^t for theta > theta_l, else 1
    (paper, Figure 3); theta in radians."""
    theta_l = P["theta_l_deg"] * (math.pi / 180.0)
    base = xp.maximum((P["g_a"] * theta + P["g_b"]) * theta + P["g_c"], TINY)
    return xp.where(theta > theta_l, xp.exp(P["g_t"] * xp.log(base)), 1.0 + 0.0 * theta)


def _positive(v) -> bool:
    """Whether a parameter value (a number or a float64 array) is positive anywhere; opaque values
    (the plugin's) say nothing, and the plugin passes its terms explicitly."""
    try:
        return bool(np.any(np.asarray(v, dtype=np.float64) > 0.0))
    except (TypeError, ValueError):
        return False


def road_brdf(xp, P: Mapping[str, Any], wi, wo, variant: str = DEFAULT_VARIANT,
              terms: frozenset[str] | None = None, *, pairs: dict | None = None):
    """The road BRDF f_r (sr^-1) of paper eq. 4, for local unit vectors.

    Parameters
    ----------
    xp:
        Array namespace (:class:`NumpyOps` or the Dr.Jit one).
    P:
        Parameters by their docs/conventions.md names (floats, arrays or opaque Dr.Jit values).
    wi, wo:
        ``(x, y, z)`` component triples of the unit directions towards the source (``wi``) and
        towards the detector (``wo``), in a frame whose z axis is the surface normal.
    variant:
        ``"power"`` (default), ``"product"`` or ``"smooth"`` (extension) form of the empirical term.
    terms:
        Which terms to evaluate (see :func:`active_terms`); ``None`` means all. A term left out
        costs nothing.
    pairs:
        A dict that a caller evaluating the model many times on the same numpy directions keeps
        for them (a fit: one per set of directions, never shared between two): what depends on the
        directions alone (the angles, the lobes' ln cos, ln x or L at each rounding) is computed on
        the first call and taken from it after, the same arrays, so the same numbers. None (the
        plugin, single calls): everything computed.
    """
    return _road_brdf(xp, P, wi, wo, variant, terms, pairs, ())[0]


#: The terms of eq. 4 that carry a linear coefficient (the fitter's NNLS unknowns, the forward model's
#: columns), the shape parameters of each, and the grazing attenuation g's parameters (user inputs,
#: never fitted; g enters every term): written here once for the fitter, the forward model and the
#: correction (review, session 39: three copies had drifted, beta_round_deg missing from one).
LINEAR_TERMS = ("k_diff", "k_phong", "k_retro", "k_exp")
TERM_SHAPE = {"k_diff": (), "k_phong": ("n_phong",), "k_retro": ("n_retro",),
              "k_exp": ("p", "h", "mu", "n_beta", "beta_round_deg")}
G_PARAMS = ("g_a", "g_b", "g_c", "g_t", "theta_l_deg")

#: The shape parameters :func:`road_brdf_with_shape_grad` differentiates, and the term each one shapes.
SHAPE_TERM = {"n_phong": "k_phong", "n_retro": "k_retro", "p": "k_exp", "h": "k_exp", "mu": "k_exp",
              "n_beta": "k_exp"}


def road_brdf_with_shape_grad(xp, P: Mapping[str, Any], wi, wo, variant: str, terms: frozenset[str],
                              wrt: Sequence[str], *, pairs: dict | None = None) -> tuple[Any, list]:
    """:func:`road_brdf` (same arguments) and its partial derivatives with respect to the shape
    parameters ``wrt`` (names of :data:`SHAPE_TERM`; natural units), one array each, from the same
    intermediate values in one pass (one definition of the model: the derivatives are taken inside
    :func:`road_brdf`'s own body, and the value is exactly :func:`road_brdf`'s):

    * a lobe, ``d/dn (cos Omega)^n = (cos Omega)^n ln cos Omega``;
    * the empirical term ``E = exp(expo)``, ``dE = E d(expo)``, with ``f = sin e cos e / (cos^2 e + mu)``
      so ``df/dmu = -f / (cos^2 e + mu)``, and ``d(expo)`` of the variant's exponent (module docstring:
      ``p ln f + W ln x``, ``W = exp(1 + h f^2)``, power; ``p ln f + ln x + 1 + h f^2``, product;
      ``p ln f - exp(1 + h sqrt f) L^n_beta``, smooth);
    * times the grazing attenuation, as the value is.

    Where a cap (:data:`EXP_CAP`) or a floor (:data:`TINY`) holds a quantity constant its derivative
    is 0, as the capped formula's is. For the fits' Jacobians (numpy, float64); a term not in
    ``terms`` contributes 0."""
    unknown = [n for n in wrt if n not in SHAPE_TERM]
    if unknown:
        raise InputError(f"no derivative with respect to {', '.join(unknown)}; expected names of "
                         f"{', '.join(SHAPE_TERM)}", field="wrt")
    return _road_brdf(xp, P, wi, wo, variant, terms, pairs, tuple(wrt))


def _road_brdf(xp, P, wi, wo, variant, terms, pairs, wrt):
    """(f_r, [d f_r / d name for name in wrt]): :func:`road_brdf`'s body (``wrt`` empty: the value
    alone, nothing else computed)."""
    if variant not in VARIANTS:
        raise InputError(f"unknown model variant {variant!r}; expected one of {', '.join(VARIANTS)}",
                         field="variant")
    if terms is None:
        terms = frozenset({"k_diff", "k_phong", "k_retro", "k_exp", "g"} | (
            {"round"} if _positive(P.get("beta_round_deg", 0.0)) else set()))
    wix, wiy, wiz = wi
    wox, woy, woz = wo
    zero = _kept(pairs, "zero", lambda: 0.0 * (wiz + woz))
    f = zero
    grad = {name: zero for name in wrt}
    if "k_diff" in terms:
        f = f + P["k_diff"]
    if "k_phong" in terms:
        base = _kept(pairs, "phong", lambda: _lobe_base(xp, _phong_h(xp, wi, wo)))
        lobe = _lobe_of(xp, base, P["n_phong"])
        f = f + P["k_phong"] * lobe
        if "n_phong" in grad:
            grad["n_phong"] = P["k_phong"] * (lobe * base[1])          # lobe = 0 where cos Omega <= 0
    if "k_retro" in terms:
        # half-chord to the source direction: cos Omega' = 1 - h'
        base = _kept(pairs, "retro", lambda: _lobe_base(
            xp, 0.5 * ((wox - wix) ** 2 + (woy - wiy) ** 2 + (woz - wiz) ** 2)))
        lobe = _lobe_of(xp, base, P["n_retro"])
        f = f + P["k_retro"] * lobe
        if "n_retro" in grad:
            grad["n_retro"] = P["k_retro"] * (lobe * base[1])          # lobe = 0 where cos Omega <= 0
    if "k_exp" in terms or "g" in terms:
        # beta = pi where the azimuth is undefined, so E = 0 there (module docstring)
        theta_i, theta_r, beta, beta_s = _kept(pairs, "angles", lambda: pair_angles(xp, wi, wo, pole=math.pi,
                                                                                    supplement=True))
    if "k_exp" in terms:
        # what follows from beta is kept per rounding of the mirror plane (the cusp's apart)
        rkey = "cusp"
        if "round" in terms:
            rounding = P["beta_round_deg"]
            rkey = None if _round_key(rounding) is None else ("round", _round_key(rounding))
            beta, beta_s = _kept(pairs, None if rkey is None else ("beta", rkey),
                                 lambda: rounded_beta(xp, beta, rounding, beta_s))
        # x (power, product) and x_s (smooth) vanish at beta = pi: their logarithms take 1 - ... from
        # beta below pi/2 (log1m, accurate near 0) and from pi - beta above it (beta_s, accurate near
        # pi), floored at X_FLOOR, a float32 number too (1 - 1e-7 is not: it rounds to 1 - 1.19e-7)
        near_pi = _kept(pairs, None if rkey is None else ("near_pi", rkey), lambda: beta > 0.5 * math.pi)

        def e_terms():
            e = theta_i * theta_r * (1.0 / THETA_R_STAR)
            cos_e = xp.cos(e)
            return cos_e > 0.0, xp.sin(e) * cos_e, cos_e * cos_e
        lit, sin_cos_e, cos2_e = _kept(pairs, "e", e_terms)
        f_e = xp.where(lit, sin_cos_e / (cos2_e + P["mu"]), zero)
        ln_f = xp.log(xp.maximum(f_e, TINY))
        if variant != "smooth":
            # the paper's x = (pi - beta)/pi, ln x = ln(1 - beta/pi), and 1 + h f^2
            ln_x = _kept(pairs, None if rkey is None else ("ln_x", rkey), lambda: xp.where(
                near_pi, xp.log(xp.maximum(beta_s * (1.0 / math.pi), X_FLOOR)),
                xp.log1m(xp.minimum(beta * (1.0 / math.pi), 0.5))))
            arg = xp.minimum(1.0 + P["h"] * f_e * f_e, EXP_CAP)
        if variant == "smooth":
            # extension (module docstring): E = k f^p exp(-W L^n_beta), W = exp(1 + h sqrt f),
            # L = -ln cos^2(beta/2) = -log1m(sin^2(beta/2))
            root_f = xp.sqrt(f_e)
            ln_w = xp.minimum(1.0 + P["h"] * root_f, EXP_CAP)

            def smooth_L():
                s_half = xp.sin(0.5 * beta)                   # sin(beta/2)
                c_half = xp.sin(0.5 * beta_s)                 # cos(beta/2)
                return xp.where(near_pi, -xp.log(xp.maximum(c_half * c_half, X_FLOOR)),
                                -xp.log1m(xp.minimum(s_half * s_half, 0.5)))
            L = _kept(pairs, None if rkey is None else ("L", rkey), smooth_L)
            ln_l = xp.log(xp.maximum(L, TINY))
            ln_wl = xp.minimum(ln_w + P["n_beta"] * ln_l, EXP_CAP)
            w_l = xp.where(L > 0.0, xp.exp(ln_wl), zero)
            expo = P["p"] * ln_f - w_l
        elif variant == "power":
            w_ln_x = xp.exp(arg) * ln_x
            expo = P["p"] * ln_f + w_ln_x
        else:  # product
            expo = P["p"] * ln_f + ln_x + arg
        E = xp.exp(xp.minimum(expo, EXP_CAP))
        f = f + P["k_exp"] * E
        if any(n in grad for n in ("p", "h", "mu", "n_beta")):
            # dE = E d(expo) (road_brdf_with_shape_grad), 0 where expo is capped; with
            # df/dmu = -f / (cos^2 e + mu): dE/dmu = -(p E [f > 0] + c h dE/dh) / (cos^2 e + mu),
            # c = 2 (h f^2 in expo) or 1/2 (h sqrt f, smooth)
            e_live = xp.where(expo < EXP_CAP, E, zero)
            if variant == "smooth":
                d_h = -xp.where((ln_wl < EXP_CAP) & (ln_w < EXP_CAP), e_live * w_l * root_f, zero)
                if "n_beta" in grad:
                    grad["n_beta"] = -xp.where(ln_wl < EXP_CAP, e_live * w_l * ln_l, zero)
                c_h = 0.5
            else:
                d_h = xp.where(arg < EXP_CAP, e_live * (w_ln_x if variant == "power" else 1.0) * (f_e * f_e), zero)
                c_h = 2.0
            if "p" in grad:
                grad["p"] = e_live * ln_f
            if "h" in grad:
                grad["h"] = d_h
            if "mu" in grad:
                grad["mu"] = -(xp.where(f_e > TINY, e_live * P["p"], zero) + (c_h * P["h"]) * d_h) / xp.maximum(
                    cos2_e + P["mu"], TINY)
            if not (isinstance(P["k_exp"], float) and P["k_exp"] == 1.0):
                for n in ("p", "h", "mu", "n_beta"):
                    if n in grad:
                        grad[n] = P["k_exp"] * grad[n]
    if "g" in terms:
        g_star = g_attenuation(xp, P, THETA_R_STAR + zero)
        # g(theta_r)/g* first: the ratio stays near 1 at the observation, so the product does not
        # overflow float32 where the result itself is finite (e.g. g_t = -100 in the plugin)
        g_factor = g_attenuation(xp, P, theta_i) * (g_attenuation(xp, P, theta_r) / g_star)
        f = f * g_factor
        grad = {n: d * g_factor for n, d in grad.items()}
    seen = _kept(pairs, "seen", lambda: (wiz > 0.0) & (woz > 0.0))
    return xp.where(seen, f, zero), [xp.where(seen, grad[n], zero) for n in wrt]


# ----------------------------------------------------------------------------------------------
# Parameters and model objects (float64 numpy side)
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RoadParams:
    """Parameters of the road BRDF (docs/conventions.md names and defaults), validated on construction."""

    k_diff: float = 0.0
    k_phong: float = 0.0
    n_phong: float = 1.0
    k_retro: float = 0.0
    n_retro: float = 1.0
    k_exp: float = 0.0
    p: float = 1.0
    h: float = 0.0
    mu: float = 0.0
    g_a: float = 0.0
    g_b: float = 0.0
    g_c: float = 1.0
    g_t: float = 1.0
    theta_l_deg: float = 90.0
    n_beta: float = 1.0
    beta_round_deg: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            # a number, not text or a truth value that happens to convert ("0.03", true): no coercion
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
                raise InputError(f"expected a number, got {type(v).__name__} {v!r}", field=f.name)
            v = float(v)
            object.__setattr__(self, f.name, v)
            lo, hi = PARAM_BOUNDS[f.name]
            if not math.isfinite(v):
                raise InputError(f"expected a finite number, got {v}", field=f.name)
            if f.name == "theta_l_deg":
                if not (lo < v <= hi):
                    raise InputError(f"expected {lo} < theta_l_deg <= {hi} (paper: theta_l > 85.3 deg), got {v}",
                                     field=f.name)
            elif not (lo <= v <= hi):
                raise InputError(f"expected a value in [{lo:g}, {hi:g}], got {v:g}", field=f.name)
        if self.theta_l_deg < 90.0:
            tl = math.radians(self.theta_l_deg)
            pts = [tl, math.pi / 2]
            if self.g_a != 0.0:
                vertex = -self.g_b / (2 * self.g_a)
                if tl < vertex < math.pi / 2:
                    pts.append(vertex)
            worst = min(self.g_a * t * t + self.g_b * t + self.g_c for t in pts)
            if worst <= 0.0:
                raise InputError("the grazing-attenuation polynomial g_a*theta^2 + g_b*theta + g_c must be "
                                 f"> 0 for theta in [theta_l, 90 deg]; its minimum there is {worst:.4g}",
                                 field="g_a/g_b/g_c")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, path: str | Path | None = None) -> "RoadParams":
        unknown = sorted(set(d) - set(PARAM_NAMES))
        if unknown:
            raise InputError(f"unknown parameter(s) {', '.join(unknown)}; expected names from "
                             f"{', '.join(PARAM_NAMES)}", path=path, field="params")
        try:
            return cls(**dict(d))
        except InputError as err:
            raise InputError(err.reason, path=path, field=f"params.{err.field}" if err.field else "params") from None

    def to_dict(self) -> dict[str, float]:
        return {name: getattr(self, name) for name in PARAM_NAMES}

    def replace(self, **changes) -> "RoadParams":
        return replace(self, **changes)


#: Each parameter's default (docs/conventions.md section 3).
_PARAM_DEFAULTS: dict[str, float] = RoadParams().to_dict()


def _is_number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _near_key(key: str, known) -> str | None:
    """The known key that ``key`` is a misspelling of (case, one or two letters off), if any."""
    import difflib
    if not isinstance(key, str):
        return None
    low = key.strip().lower().replace("-", "_")
    for k in known:
        if low == k or low.rstrip("s") == k.rstrip("s"):
            return k
    hit = difflib.get_close_matches(low, list(known), n=1, cutoff=0.75)
    return hit[0] if hit else None


@dataclass(frozen=True)
class RoadModel:
    """A road BRDF: a variant and its parameters. Evaluates in float64 numpy."""

    params: RoadParams
    variant: str = DEFAULT_VARIANT
    name: str = "model"
    meta: Mapping[str, Any] | None = None

    def __post_init__(self):
        if not isinstance(self.params, RoadParams):
            raise InputError(f"expected RoadParams, got {type(self.params).__name__}", field="params")
        if not isinstance(self.name, str):
            raise InputError(f"expected text for the model's name, got {type(self.name).__name__} {self.name!r}",
                             field="name")
        if not isinstance(self.variant, str) or self.variant not in VARIANTS:
            raise InputError(f"unknown model variant {self.variant!r}; expected one of {', '.join(VARIANTS)}",
                             field="variant")
        # a parameter the variant does not use (n_beta of power) does nothing: it is held at its
        # default, so that the model's file (which holds only the variant's parameters) reads back as
        # the model and two models that evaluate alike compare and fingerprint alike
        used = variant_param_names(self.variant)
        unused = {k: _PARAM_DEFAULTS[k] for k in PARAM_NAMES
                  if k not in used and getattr(self.params, k) != _PARAM_DEFAULTS[k]}
        if unused:
            object.__setattr__(self, "params", self.params.replace(**unused))

    @classmethod
    def lambert(cls, reflectance: float = 1.0) -> "RoadModel":
        """A perfect diffuser: f_r = reflectance / pi."""
        return cls(RoadParams(k_diff=reflectance / math.pi), name="lambert")

    @property
    def is_lambertian(self) -> bool:
        P = self.params
        return (P.k_phong == 0 and P.k_retro == 0 and P.k_exp == 0 and P.theta_l_deg >= 90.0)

    def terms(self) -> frozenset[str]:
        return active_terms(self.params.to_dict())

    @property
    def mirror_kink(self) -> bool:
        """Whether f_r has a kink on the mirror plane (|beta| in the empirical term) that an
        integrator should split on."""
        return "k_exp" in self.terms()

    def evaluate(self, xp, wi, wo):
        """f_r for component triples ``wi``, ``wo`` over the array namespace ``xp`` (the interface
        the float64 backends evaluate; :mod:`roadgonio.surface.truths` provides the same)."""
        return road_brdf(xp, self.params.to_dict(), wi, wo, self.variant, self.terms())

    def brdf(self, wi, wo) -> np.ndarray:
        """f_r for direction arrays ``wi`` (towards the source) and ``wo`` (towards the
        detector), shape ``(..., 3)``; broadcasts."""
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        wi, wo = np.broadcast_arrays(wi, wo)
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            out = road_brdf(NumpyOps, self.params.to_dict(), (wi[..., 0], wi[..., 1], wi[..., 2]),
                            (wo[..., 0], wo[..., 1], wo[..., 2]), self.variant, self.terms())
        return np.asarray(out, dtype=np.float64)

    def q(self, tan_eps, beta_deg, alpha_deg=ALPHA_STANDARD_DEG, delta_deg=0.0) -> np.ndarray:
        """Luminance coefficient q = f_r for a source at (eps, beta) and the detector at alpha."""
        wi = w_source(eps_from_tan(tan_eps), beta_deg, delta_deg)
        wo = w_detector(alpha_deg, delta_deg)
        return self.brdf(wi, wo)

    def r(self, tan_eps, beta_deg, alpha_deg=ALPHA_STANDARD_DEG, delta_deg=0.0) -> np.ndarray:
        """Reduced luminance coefficient r = q cos^3(eps) (sr^-1, not x 1e4)."""
        return self.q(tan_eps, beta_deg, alpha_deg, delta_deg) * cos3_eps(tan_eps)

    def exponent_capped(self, tan_eps, beta_deg, alpha_deg=ALPHA_STANDARD_DEG) -> np.ndarray:
        """Where the empirical term's exponent reaches :data:`EXP_CAP` (module docstring; within
        :data:`EXP_CAP_REACHED`), so that E is ``k_exp exp(EXP_CAP)`` there and not eq. 4's value (a
        user audit of session 45: a model p = 40, mu = 0 gave r 49,000 times below the formula at tan
        eps 12, beta 0; a fit to a table made with p = 35 settled on the cap, exponent 80 - 2e-7, its
        parameters not the table's). Boolean, over the broadcast ``tan_eps`` x ``beta_deg``; False
        everywhere without the term. The inner caps (on ``1 + h f^2``, ``ln W + n_beta ln L``) act
        only where ``ln x`` or ``L`` is far from 0, where E underflows to 0 either way."""
        if not (self.params.k_exp > 0.0):
            return np.zeros(np.broadcast_shapes(np.shape(tan_eps), np.shape(beta_deg)), dtype=bool)
        # E alone, of unit coefficient: the other terms and g (theta_l 90 deg) left out
        unit = RoadModel(self.params.replace(k_diff=0.0, k_phong=0.0, k_retro=0.0, k_exp=1.0, theta_l_deg=90.0),
                         self.variant)
        return unit.q(tan_eps, beta_deg, alpha_deg) >= math.exp(EXP_CAP - EXP_CAP_REACHED)

    # -- files -----------------------------------------------------------------------------
    def to_json_dict(self) -> dict[str, Any]:
        P = self.params.to_dict()
        d: dict[str, Any] = {"variant": self.variant, "params": {k: P[k] for k in variant_param_names(self.variant)},
                             "name": self.name}
        if self.meta:
            d.update({k: v for k, v in self.meta.items() if k not in d})
        return d

    @classmethod
    def from_json_dict(cls, d: Mapping[str, Any], *, path: str | Path | None = None) -> "RoadModel":
        if not isinstance(d, Mapping):
            raise InputError("expected a JSON object with keys 'variant' and 'params'", path=path)
        if "params" not in d or not isinstance(d["params"], Mapping):
            raise InputError("missing or non-object 'params' (expected {\"variant\": ..., \"params\": {...}})",
                             path=path, field="params")
        if "variant" not in d:
            # every model file roadgonio writes names its variant; a file without one is not read as
            # the default, which may not be the variant it was fitted with. A misspelt key is named
            # (user audit, session 29: "varaint" said only "missing key 'variant'")
            typo = next((k for k in d if k != "variant" and _near_key(k, ("variant",))), None)
            raise InputError("missing key 'variant'" + (f" (is {typo!r} meant to be 'variant'?)" if typo else "")
                             + f"; expected one of {', '.join(VARIANTS)}", path=path, field="variant")
        variant = d["variant"]
        if not isinstance(variant, str) or variant not in VARIANTS:
            raise InputError(f"unknown variant {variant!r}; expected one of {', '.join(VARIANTS)}",
                             path=path, field="variant")
        used = variant_param_names(variant)
        unknown = sorted(k for k in d["params"] if k not in PARAM_NAMES)
        if unknown:
            # the names of this variant, not of all (user audit, session 29: a typo in a power model
            # listed n_beta, which the next error then called no parameter of power)
            near = [_near_key(k, used) for k in unknown]
            hint = "; ".join(f"did you mean {n!r} for {k!r}?" for k, n in zip(unknown, near) if n)
            raise InputError(f"unknown parameter(s) {', '.join(unknown)}" + (f" ({hint})" if hint else "")
                             + f"; variant {variant!r} takes {', '.join(used)}", path=path, field="params")
        for k, v in d["params"].items():
            # a parameter of another variant does nothing here (n_beta with power): an error, not a
            # silent no-op; at its default it is what roadgonio wrote into every model file before
            # it wrote only the variant's parameters, so that is still read
            if k in PARAM_NAMES and k not in used and not (_is_number(v) and float(v) == _PARAM_DEFAULTS[k]):
                raise InputError(f"{k!r} is not a parameter of variant {variant!r} (it would do nothing); "
                                 f"variant {variant!r} takes {', '.join(used)}", path=path, field=f"params.{k}")
        params = RoadParams.from_dict(d["params"], path=path)
        meta = {k: v for k, v in d.items() if k not in ("variant", "params", "name")}
        for k in meta:
            # further keys (fit statistics, provenance) are allowed (conventions.md section 3), but a
            # misspelt key the reader reads ("varaint": "smooth") would silently leave its default
            near = _near_key(k, ("variant", "params", "name"))
            if near:
                raise InputError(f"unknown key {k!r}; did you mean {near!r}? (a model file's keys are variant, params, "
                                 "name, plus metadata)", path=path, field=k)
        name = d.get("name", Path(path).stem if path else "model")
        if not isinstance(name, str):
            raise InputError(f"expected text for the model's name, got {type(name).__name__} {name!r}", path=path,
                             field="name")
        return cls(params, variant, name=name, meta=meta or None)

    @classmethod
    def load(cls, path: str | Path) -> "RoadModel":
        from roadgonio.fileio import read_user_text
        path = Path(path)
        text = read_user_text(path, "model file")
        try:
            d = json.loads(text)
        except json.JSONDecodeError as err:
            raise InputError(f"not valid JSON: {err.msg}", path=path, line=err.lineno) from None
        return cls.from_json_dict(d, path=path)

    def save(self, path: str | Path) -> Path:
        from roadgonio.fileio import atomic_write_json
        return atomic_write_json(path, self.to_json_dict())
