"""The road BSDF as a Mitsuba 3 Python plugin (plugin name ``roadbsdf``).

It evaluates :func:`roadgonio.surface.model.road_brdf` (paper eq. 4, the project's one definition of the
model) with the Dr.Jit namespace :class:`roadgonio.engines.mitsuba.ops.DrJitOps`; nothing of the formula is
repeated here.

Properties (XML or ``mi.load_dict``):

* the model parameters by their names in :data:`roadgonio.surface.model.PARAM_NAMES` (the docs/conventions.md names
  ``k_diff`` ... ``theta_l_deg``, plus ``n_beta`` of the ``smooth`` extension); floats, defaults
  as in :class:`roadgonio.surface.model.RoadParams`, validated;
* ``variant``: one of :data:`roadgonio.surface.model.VARIANTS` (``"power"``, the paper's model, by
  default; ``"product"``; ``"smooth"``), structural;
* ``channels``: ``"road"`` (default: every colour channel is f_road, an ordinary BSDF) or
  ``"road_lambert"`` (rgb variants only): channel 0 = f_road, channels 1 and 2 = 1/pi, the
  perfect diffuser. The detector signal then carries S[f_road] in R and S[f_lambert] in G and B,
  computed from the same rays in the same pass (the k_A ratio of docs/conventions.md section 5).

Calling convention (Mitsuba's, in Radiance mode; checked with a non-reciprocal term): ``si.wi`` is
the local direction towards the sensor (the model's ``wo``), the ``wo`` argument is towards the
light (the model's ``wi``);
:meth:`eval` returns f cos(theta_light); :meth:`sample` draws the light direction from a
cosine-weighted hemisphere (pdf = cos/pi), or, when the model has a Phong lobe, from the mixture
(1 - P) cos/pi + P (n + 1)/(2 pi) (cos Omega)^n with P = :data:`LOBE_SHARE` and the model's own
exponent n_phong about the mirror direction of ``si.wi`` (the stray-light paths meet the road's
forward lobe at grazing angles: cosine sampling alone finds it rarely), and returns the weight
f cos/pdf. :meth:`pdf` is the density of that mixture. The k_A engine samples only the source
(next-event estimation), so neither changes the direct light.

Parameters are stored as opaque ``mi.Float`` (``dr.opaque``), listed by :meth:`traverse` as
non-differentiable, so changing a value never recompiles the kernel. The variant and the set of
active terms (:func:`roadgonio.surface.model.active_terms`) are structural: they decide which code is
traced; the term set is recomputed from the values in :meth:`parameters_changed`.

A surface other than eq. 4 (from Python: :meth:`RoadBSDF.set_surface`, structural): any object
with ``evaluate(xp, wi, wo)`` over an array namespace that is not ``numpy_only`` -- a surface of
:mod:`roadgonio.surface.truths`, or the fitted backbone times its correction surface
(:class:`roadgonio.surface.correction_surface.CorrectedSurface`). The BSDF then evaluates that
surface with :class:`~roadgonio.engines.mitsuba.ops.DrJitOps` (its one definition) and samples the
mixture above with the surface's ``sampling_lobe_exponent`` in place of n_phong; the model
parameters are ignored until :meth:`RoadBSDF.set_model`. This is how the Mitsuba backend measures a
surface outside eq. 4, through a housing too.

Registration: :func:`roadgonio.engines.mitsuba.plugins.register_plugins` after ``set_variant``.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from roadgonio.errors import InputError
from roadgonio.surface.model import (DEFAULT_VARIANT, PARAM_NAMES, VARIANTS, RoadParams, active_terms, phong_lobe,
                                     road_brdf)
from roadgonio.engines.mitsuba.ops import DrJitOps
from roadgonio.surface.truths import renders_in_drjit

CHANNELS = ("road", "road_lambert")
INV_PI = 1.0 / math.pi
#: Share of the Phong-lobe samples in :meth:`RoadBSDF.sample` (models with a Phong lobe).
LOBE_SHARE = 0.5


class RoadBSDF(mi.BSDF):
    """Road BSDF of paper eq. 4 (see the module docstring)."""

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        values = {}
        for name in PARAM_NAMES:
            if name in props:
                values[name] = float(props.get(name))
        variant = str(props.get("variant")) if "variant" in props else DEFAULT_VARIANT
        channels = str(props.get("channels", "road")) if "channels" in props else "road"
        if variant not in VARIANTS:
            raise InputError(f"unknown road BSDF variant {variant!r}; expected one of {', '.join(VARIANTS)}",
                             field="variant")
        if channels not in CHANNELS:
            raise InputError(f"unknown channels {channels!r}; expected one of {', '.join(CHANNELS)}",
                             field="channels")
        if channels == "road_lambert" and not mi.is_rgb:
            raise InputError("channels = 'road_lambert' needs an rgb variant (3 colour channels)",
                             field="channels")
        self.variant = variant
        self.channels = channels
        self.surface = None
        self._surface_lobe = None
        params = RoadParams.from_dict(values)          # validates the bounds
        self._values = params.to_dict()
        for name in PARAM_NAMES:
            setattr(self, name, dr.opaque(mi.Float, self._values[name]))
        self.terms = active_terms(self._values)
        flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        self.m_components = [flags]
        self.m_flags = flags

    # -- parameters --------------------------------------------------------------------------
    def traverse(self, cb):
        for name in PARAM_NAMES:
            cb.put(name, getattr(self, name), mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys=()):
        for name in PARAM_NAMES:
            v = getattr(self, name)
            if not isinstance(v, mi.Float):
                v = mi.Float(v)
                setattr(self, name, v)
            dr.make_opaque(v)
        values = {name: float(getattr(self, name)[0]) for name in PARAM_NAMES}
        RoadParams.from_dict(values)                   # out-of-bounds values are an error, not a NaN
        self._values = values
        self.terms = active_terms(values)

    def set_model(self, params: RoadParams | dict, variant: str | None = None) -> None:
        """Replace all parameters (and optionally the variant) from Python."""
        values = (params if isinstance(params, RoadParams) else RoadParams.from_dict(params)).to_dict()
        if variant is not None:
            if variant not in VARIANTS:
                raise InputError(f"unknown road BSDF variant {variant!r}", field="variant")
            self.variant = variant
        self.surface, self._surface_lobe = None, None     # eq. 4 again
        for name in PARAM_NAMES:
            setattr(self, name, mi.Float(values[name]))
        self.parameters_changed()

    def set_surface(self, surface) -> None:
        """Evaluate ``surface`` (a surface of :mod:`roadgonio.surface.truths` that is not numpy-only)
        instead of eq. 4 (module docstring, ``surface``); structural: the kernels are traced anew."""
        if not renders_in_drjit(surface):
            raise InputError(f"the surface {getattr(surface, 'name', surface)!r} evaluates in numpy only: the Mitsuba "
                             "road BSDF cannot render it (the numpy backends can)", field="surface")
        self.surface = surface
        n = float(surface.sampling_lobe_exponent)
        self._surface_lobe = dr.opaque(mi.Float, n) if n > 0.0 else None

    def model_values(self) -> dict[str, float]:
        return dict(self._values)

    # -- evaluation ----------------------------------------------------------------------------
    def _params(self):
        return {name: getattr(self, name) for name in PARAM_NAMES}

    def _f(self, wi_sensor, wo_light):
        """f_road with the model's convention: wi = towards the light, wo = towards the sensor."""
        if self.surface is not None:
            return self.surface.evaluate(DrJitOps, (wo_light.x, wo_light.y, wo_light.z),
                                         (wi_sensor.x, wi_sensor.y, wi_sensor.z))
        return road_brdf(DrJitOps, self._params(), (wo_light.x, wo_light.y, wo_light.z),
                         (wi_sensor.x, wi_sensor.y, wi_sensor.z), self.variant, self.terms)

    def _spectrum(self, f, scale, active):
        """Colour value: f scale in every channel, or (f, 1/pi, 1/pi) scale (road_lambert)."""
        if self.channels == "road_lambert":
            value = mi.Color3f(f, INV_PI, INV_PI) * scale
        else:
            value = mi.Spectrum(f * scale)
        return dr.select(active, value, 0.0)

    def eval(self, ctx, si, wo, active=True):
        cos_s = mi.Frame3f.cos_theta(si.wi)
        cos_l = mi.Frame3f.cos_theta(wo)
        active = active & (cos_s > 0.0) & (cos_l > 0.0)
        return self._spectrum(self._f(si.wi, wo), cos_l, active)

    @property
    def _lobe_sampling(self) -> bool:
        if self.surface is not None:
            return self._surface_lobe is not None
        return "k_phong" in self.terms

    @property
    def _lobe_n(self):
        """The sampled lobe's exponent: n_phong, or the surface's ``sampling_lobe_exponent``."""
        return self._surface_lobe if self.surface is not None else self.n_phong

    def _lobe_pdf(self, wi_sensor, wo_light):
        """(n + 1)/(2 pi) (cos Omega)^n about the mirror direction of ``wi_sensor`` (n = :attr:`_lobe_n`):
        the model's own lobe (:func:`roadgonio.surface.model.phong_lobe`; the model's wi is the light)."""
        n = self._lobe_n
        lobe = phong_lobe(DrJitOps, (wo_light.x, wo_light.y, wo_light.z), (wi_sensor.x, wi_sensor.y, wi_sensor.z), n)
        return (n + 1.0) * (0.5 * INV_PI) * lobe

    def _pdf(self, wi_sensor, wo_light):
        cosine = mi.warp.square_to_cosine_hemisphere_pdf(wo_light)
        if not self._lobe_sampling:
            return cosine
        return (1.0 - LOBE_SHARE) * cosine + LOBE_SHARE * self._lobe_pdf(wi_sensor, wo_light)

    def pdf(self, ctx, si, wo, active=True):
        cos_s = mi.Frame3f.cos_theta(si.wi)
        active = active & (cos_s > 0.0) & (mi.Frame3f.cos_theta(wo) > 0.0)
        return dr.select(active, self._pdf(si.wi, wo), 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

    def sample(self, ctx, si, sample1, sample2, active=True):
        cos_s = mi.Frame3f.cos_theta(si.wi)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
        if self._lobe_sampling:
            # the Phong lobe about the mirror direction: cos alpha = u^(1/(n+1)) (sample1 picks the strategy)
            mirror = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)
            cos_a = dr.power(sample2.x, dr.rcp(self._lobe_n + 1.0))
            sin_a = dr.safe_sqrt(1.0 - cos_a * cos_a)
            phi = 2.0 * math.pi * sample2.y
            lobe = mi.Frame3f(mirror).to_world(mi.Vector3f(sin_a * dr.cos(phi), sin_a * dr.sin(phi), cos_a))
            bs.wo = dr.select(sample1 < LOBE_SHARE, lobe, bs.wo)
        bs.pdf = self._pdf(si.wi, bs.wo)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        bs.sampled_component = mi.UInt32(0)
        active = active & (cos_s > 0.0) & (bs.pdf > 0.0) & (mi.Frame3f.cos_theta(bs.wo) > 0.0)
        bs.pdf = dr.select(active, bs.pdf, 0.0)        # a lobe sample below the horizon is no sample
        # weight = f cos / pdf
        cos_l = mi.Frame3f.cos_theta(bs.wo)
        return bs, self._spectrum(self._f(si.wi, bs.wo), cos_l / dr.maximum(bs.pdf, 1e-30), active)

    def to_string(self):
        if self.surface is not None:
            return f"RoadBSDF[surface={self.surface.to_json_dict()}, channels={self.channels}]"
        vals = ", ".join(f"{k}={self._values[k]:g}" for k in PARAM_NAMES)
        return f"RoadBSDF[variant={self.variant}, channels={self.channels}, terms={sorted(self.terms)}, {vals}]"
