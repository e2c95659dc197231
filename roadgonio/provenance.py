"""Provenance of a result, built in one place (developers' guide, rule 7).

Every output that carries results (``ka.json`` of a k_A table, ``validate.json``,
``uncertainty.json``, ``correction.json``, ``render.json``, ``model.json`` of a fit, the attrs of
:func:`roadgonio.ka_table`) takes its provenance from :func:`provenance`, so they all say the
same things in the same keys:

* ``versions``: roadgonio, ``roadgonio_source`` (a digest of the Python source it ran: the version
  string cannot tell an edited checkout from another, audit 28), python, platform, numpy, scipy,
  mitsuba, drjit (and, when a Mitsuba variant is active, the variant and Dr.Jit's LLVM). Package versions come from the installed
  distributions' metadata (:func:`importlib.metadata.version`): nothing is imported to learn a
  version, so a numpy-only run never loads mitsuba or drjit;
* ``instrument`` (the instrument in its file form) and ``instrument_file``;
* ``model`` (the road BRDF model: variant, parameters and its own metadata);
* ``backend`` and ``settings`` (everything that determines the numbers);
* ``inputs``: the files (absolute path and sha256 of the content) or names the result was computed
  from, each with the argument that named it (:func:`input_record`);
* ``created`` (local time, ISO 8601), plus any keys the caller adds.
"""
from __future__ import annotations

import hashlib
import platform
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any, Sequence

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
    v: dict[str, str | None] = {"roadgonio": __version__, "roadgonio_source": source_digest(),
                                "python": platform.python_version(), "platform": platform.platform()}
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


_SOURCE_DIGEST: str | None = None


def source_digest() -> str:
    """A digest of the Python source this process's roadgonio runs (the package and the plugins'
    folder, file names and contents), taken once per process: the version string cannot tell an
    edited or upgraded checkout from the one a cluster's workers started with."""
    global _SOURCE_DIGEST
    if _SOURCE_DIGEST is None:
        import hashlib

        from roadgonio._checkout import mapped_folders
        roots = [Path(__file__).resolve().parent]            # the roadgonio package
        roots += [f for n, f in sorted(mapped_folders().items()) if n.endswith(".plugins")]
        h = hashlib.sha256()
        for root in roots:
            for f in sorted(root.rglob("*.py")):
                h.update(str(f.relative_to(root)).encode())
                h.update(f.read_bytes())
        _SOURCE_DIGEST = h.hexdigest()[:16]
    return _SOURCE_DIGEST


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's content (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def input_record(argument: str, value: Any, label: str | None = None) -> dict[str, Any]:
    """One input of a result: ``argument`` (what named it: ``--table``, ``--u``...), and for a file
    its absolute ``path`` and ``sha256``, else its ``name`` (a bundled table's, or the object's
    ``name`` / type); ``label``: the name the result shows it under."""
    rec: dict[str, Any] = {"argument": argument}
    if isinstance(value, (str, Path)) and Path(value).is_file():
        rec.update(path=str(Path(value).absolute()), sha256=file_sha256(value))
    elif isinstance(value, (str, Path)):
        rec["name"] = str(value)
    else:
        rec["name"] = str(getattr(value, "name", None) or type(value).__name__)
    if label is not None:
        rec["label"] = label
    return rec


def provenance(*, instrument=None, model=None, backend: str | None = None,
               settings: dict[str, Any] | None = None, inputs: Sequence[dict[str, Any]] | None = None,
               **extra: Any) -> dict[str, Any]:
    """The provenance block of a result (module docstring); ``extra`` keys are added as given.

    ``instrument`` is an :class:`~roadgonio.instrument.config.Instrument`, ``model`` a
    :class:`~roadgonio.surface.model.RoadModel` (or an already JSON-ready dict), ``backend`` the
    backend's name and ``settings`` its settings (``KaBackend.settings()``), ``inputs`` the records
    of :func:`input_record`.
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
        v = out["versions"]
        if "mitsuba_variant" not in v and settings.get("mitsuba_variant"):
            # computed in other processes (Dask workers; user audit, session 43: a design on Dask said
            # which mitsuba but not which variant nor LLVM): the backend's own record of them
            v["mitsuba_variant"] = settings["mitsuba_variant"]
            if settings.get("llvm"):
                v["llvm"] = settings["llvm"]
            v["renderer_from"] = "the backend's settings (computed in another process)"
    if inputs is not None:
        out["inputs"] = [dict(r) for r in inputs]
    out.update(extra)
    return out
