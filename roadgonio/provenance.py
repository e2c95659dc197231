"""Provenance of a result, built in one place (developers' guide, rule 7).

Every output that carries results (``ka.json`` of a k_A table, ``validate.json``,
``uncertainty.json``, ``correction.json``, ``render.json``, the attrs of
:func:`roadgonio.ka_table`) takes its provenance from :func:`provenance`, so they all say the
same things in the same keys:

* ``versions``: roadgonio, python, platform, numpy, scipy, mitsuba, drjit (and, when a Mitsuba
  variant is active, the variant and Dr.Jit's LLVM). Package versions come from the installed
  distributions' metadata (:func:`importlib.metadata.version`): nothing is imported to learn a
  version, so a numpy-only run never loads mitsuba or drjit;
* ``instrument`` (the instrument in its file form) and ``instrument_file``;
* ``model`` (the road BRDF model: variant, parameters and its own metadata);
* ``backend`` and ``settings`` (everything that determines the numbers);
* ``created`` (local time, ISO 8601), plus any keys the caller adds.
"""
from __future__ import annotations

import platform
import sys
import time
from importlib import metadata
from typing import Any

#: Distributions whose versions every result carries (name in the result -> distribution name).
PACKAGES = {"numpy": "numpy", "scipy": "scipy", "mitsuba": "mitsuba", "drjit": "drjit"}


def _dist_version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def versions() -> dict[str, str | None]:
    """Versions of the software that produced a result (None for a package that is not installed)."""
    from roadgonio._version import __version__
    v: dict[str, str | None] = {"roadgonio": __version__, "python": platform.python_version(),
                                "platform": platform.platform()}
    v.update({name: _dist_version(dist) for name, dist in PACKAGES.items()})
    mi = sys.modules.get("mitsuba")
    if mi is not None:             # only what is already loaded: never import mitsuba to ask
        try:
            variant = mi.variant()
        except Exception:  # noqa: BLE001 - provenance only
            variant = None
        if variant:
            v["mitsuba_variant"] = variant
            dr = sys.modules.get("drjit")
            if dr is not None and variant.startswith("llvm"):
                try:
                    v["llvm"] = ".".join(map(str, dr.detail.llvm_version()))
                except Exception:  # noqa: BLE001 - provenance only
                    pass
    return v


def provenance(*, instrument=None, model=None, backend: str | None = None,
               settings: dict[str, Any] | None = None, **extra: Any) -> dict[str, Any]:
    """The provenance block of a result (module docstring); ``extra`` keys are added as given.

    ``instrument`` is an :class:`~roadgonio.instrument.config.Instrument`, ``model`` a
    :class:`~roadgonio.surface.model.RoadModel` (or an already JSON-ready dict), ``backend`` the
    backend's name and ``settings`` its settings (``KaBackend.settings()``).
    """
    out: dict[str, Any] = {"versions": versions(), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    if instrument is not None:
        out["instrument"] = instrument.to_dict()
        out["instrument_file"] = str(instrument.path) if instrument.path else None
    if model is not None:
        out["model"] = model if isinstance(model, dict) else model.to_json_dict()
    if backend is not None:
        out["backend"] = backend
    if settings is not None:
        out["settings"] = dict(settings)
    out.update(extra)
    return out
