"""Mitsuba 3 Python plugins of roadgonio (installed as ``roadgonio.engines.mitsuba.plugins``).

* ``roadbsdf`` (:mod:`.road_bsdf`): the road BSDF of paper eq. 4 from :mod:`roadgonio.surface.model`;
* ``lummeter`` (:mod:`.lummeter`): the luminance-meter sensor (circular pupil x circular field);
* ``kabatch`` (:mod:`.ka_batch`): the batched k_A integrator (many cells' sources per launch).

Call :func:`register_plugins` after :func:`roadgonio.engines.mitsuba.set_variant`; it is idempotent per
variant. Importing this package does not import mitsuba.
"""
from __future__ import annotations

import importlib

_REGISTERED: dict[str, dict[str, type]] = {}

#: plugin name -> (module, class name, kind)
PLUGINS = {"roadbsdf": ("road_bsdf", "RoadBSDF", "bsdf"),
           "lummeter": ("lummeter", "LumMeter", "sensor"),
           "kabatch": ("ka_batch", "KaBatch", "integrator")}


def register_plugins() -> dict[str, type]:
    """Register the plugins for the current Mitsuba variant (once per variant); returns
    ``{plugin name: class}`` for that variant."""
    import mitsuba as mi

    from roadgonio.errors import BackendError
    variant = mi.variant()
    if variant is None:
        raise BackendError("no Mitsuba variant is set: call roadgonio.engines.mitsuba.set_variant() first")
    if variant in _REGISTERED:
        return _REGISTERED[variant]
    classes = {}
    for name, (modname, clsname, kind) in PLUGINS.items():
        mod = importlib.import_module(f"{__name__}.{modname}")
        if getattr(mod, "_VARIANT", None) != variant:
            # the classes subclass the variant's mi.BSDF / mi.Sensor: define them for this variant
            if hasattr(mod, "_VARIANT"):
                mod = importlib.reload(mod)
            mod._VARIANT = variant
        cls = getattr(mod, clsname)
        register = {"bsdf": mi.register_bsdf, "sensor": mi.register_sensor,
                    "integrator": mi.register_integrator}[kind]
        register(name, lambda props, cls=cls: cls(props))
        classes[name] = cls
    _REGISTERED[variant] = classes
    return classes
