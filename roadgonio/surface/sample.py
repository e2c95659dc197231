"""Resolve a sample specification to a road BRDF model (used by ``roadgonio ka --sample ...``).

A sample is one of:

* ``"lambert"``: a perfect diffuser (:meth:`RoadModel.lambert`);
* a bundled table name (``R1`` ... ``R4``, ``C1``, ``C2``) or a table file (``.csv`` / ``.rtb``):
  the table is fitted on the fly (:func:`roadgonio.surface.fit.fit_table`) and the fit is cached;
* a model file (``.json``, as written by ``roadgonio fit``; loaded with :meth:`RoadModel.load`).

Cache: ``$ROADGONIO_CACHE``, else the platform's cache folder (``platformdirs.user_cache_dir("roadgonio")``:
``~/.cache/roadgonio`` on Linux, ``~/Library/Caches/roadgonio`` on macOS, ``%LOCALAPPDATA%\\roadgonio\\Cache``
on Windows), one JSON model file per fit, keyed
by a SHA-256 of the table values and grid, the variant, the roadgonio version and the fitting
method version. Files are written atomically; an entry that does not parse, does not validate or
carries another key is refitted, never trusted.
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from roadgonio.errors import InputError
from roadgonio.surface.model import DEFAULT_VARIANT, VARIANTS, RoadModel
from roadgonio.surface.rtable import BUNDLED, RTable, load_table

TABLE_SUFFIXES = (".csv", ".rtb")
EXPECTED = (f"'lambert', a bundled table name ({', '.join(BUNDLED)}), a table file (.csv/.rtb) "
            "or a model file (.json)")


def cache_dir() -> Path:
    """The fit cache folder: ``$ROADGONIO_CACHE``, else the platform's user cache folder."""
    env = os.environ.get("ROADGONIO_CACHE")
    if env:
        return Path(env).expanduser()
    import platformdirs
    return Path(platformdirs.user_cache_dir("roadgonio", appauthor=False))


def cache_key(table: RTable, variant: str) -> str:
    """What determines a fit's numbers (:func:`roadgonio.fileio.fingerprint`: the table's values, the
    variant, the fit method's version and roadgonio's)."""
    from roadgonio.fileio import fingerprint
    from roadgonio.surface.fit import FIT_METHOD_VERSION, table_hash
    return fingerprint({"table": table_hash(table), "variant": variant, "fit": FIT_METHOD_VERSION}, length=64)


def _cache_path(table: RTable, variant: str, key: str) -> Path:
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in table.name)[:40] or "table"
    return cache_dir() / f"fit-{safe}-{variant}-{key[:20]}.json"


def _load_cached(path: Path, key: str) -> RoadModel | None:
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(d, dict) or d.get("cache_key") != key:
            return None
        return RoadModel.from_json_dict(d, path=path)
    except FileNotFoundError:
        return None
    except Exception:  # corrupt entry: refit, never trust it
        return None


def fitted_model(table: RTable, variant: str | None = None, *, use_cache: bool = True) -> RoadModel:
    """The fitted model of ``table`` (cached on disk)."""
    from roadgonio.surface.fit import fit_table
    variant = variant or DEFAULT_VARIANT
    if variant not in VARIANTS:
        raise InputError(f"unknown model variant {variant!r}; expected one of {', '.join(VARIANTS)}",
                         field="variant")
    key = cache_key(table, variant)
    path = _cache_path(table, variant, key)
    if use_cache:
        m = _load_cached(path, key)
        if m is not None:
            return m
    res = fit_table(table, variant)
    model = res.model
    if use_cache:
        d = model.to_json_dict()
        d["cache_key"] = key
        try:
            from roadgonio.fileio import atomic_write_json
            atomic_write_json(path, d)
        except OSError as err:  # a read-only cache must not stop the work
            print(f"roadgonio: warning: cannot write the fit cache {path} ({err.strerror})", file=sys.stderr)
    return model


def check_not_degenerate(model: RoadModel, path=None) -> RoadModel:
    """A model whose every coefficient k_diff, k_phong, k_retro, k_exp is 0 reflects nothing:
    k_A = measured/nominal, S1 and the r-table are undefined for it (0/0). A clear error instead
    of NaN results."""
    P = model.params
    if P.k_diff == 0 and P.k_phong == 0 and P.k_retro == 0 and P.k_exp == 0:
        raise InputError("every coefficient (k_diff, k_phong, k_retro, k_exp) is 0: the model reflects nothing, "
                         "so k_A, S1 and the r-table are undefined; expected at least one k_* > 0",
                         path=path, field="params")
    return model


def resolve_sample(spec: str, variant: str | None = None) -> RoadModel:
    """A road BRDF model from a sample specification, checked not to be degenerate (see
    :func:`check_not_degenerate`)."""
    s = str(spec).strip()
    p = Path(s).expanduser()
    return check_not_degenerate(_resolve_sample(spec, variant), path=p if p.suffix else None)


def _resolve_sample(spec: str, variant: str | None = None) -> RoadModel:
    """A road BRDF model from a sample specification (see the module docstring).

    ``variant`` selects the model variant for fitted tables (default ``"power"``); for a model
    file it must match the file's variant if given.
    """
    if variant is not None and variant not in VARIANTS:
        raise InputError(f"unknown model variant {variant!r}; expected one of {', '.join(VARIANTS)}",
                         field="variant")
    s = str(spec).strip()
    if not s:
        raise InputError(f"empty sample; expected {EXPECTED}", field="sample")
    if s.lower() == "lambert":
        return RoadModel.lambert()
    p = Path(s).expanduser()
    suffix = p.suffix.lower()
    if suffix == ".json":
        if not p.exists():
            raise InputError(f"no such model file; expected {EXPECTED}", path=p)
        m = RoadModel.load(p)
        if variant is not None and m.variant != variant:
            raise InputError(f"the model file holds variant {m.variant!r}, but variant {variant!r} was asked",
                             path=p, field="variant")
        return m
    if s.upper() in BUNDLED and not p.exists():
        return fitted_model(load_table(s), variant)
    if suffix in TABLE_SUFFIXES:
        if not p.exists():
            raise InputError(f"no such table file; expected {EXPECTED}", path=p)
        return fitted_model(load_table(p), variant)
    raise InputError(f"unknown sample {s!r}; expected {EXPECTED}", field="sample")
