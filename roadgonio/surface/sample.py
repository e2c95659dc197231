"""THE resolver of a SAMPLE (what every command's ``--sample`` and every API function's ``sample``
takes): :func:`resolve_sample` turns it into a :class:`ResolvedSample` (name, model, table), and
nothing else in roadgonio decides what a sample is or what it is called.

A sample is one of:

* ``"lambert"``: a perfect diffuser (:meth:`RoadModel.lambert`);
* a bundled table name (``R1`` ... ``R4``, ``C1``, ``C2``, any case) or a table file (``.csv`` /
  ``.rtb``): the table is fitted on the fly (:func:`roadgonio.surface.fit.fit_table`) and the fit
  is cached;
* a model file (``.json``, as written by ``roadgonio fit``; loaded with :meth:`RoadModel.load`);
* in Python also a :class:`RoadModel`, an :class:`RTable`, an r-table ``xarray.DataArray`` (dims
  ``tan_eps``, ``beta``; :meth:`RTable.from_dataarray`) or a fit result (``.model``, ``.table``).

A text is a file when it has a suffix (``.json``: a model; ``.csv``/``.rtb``: a table), else a
bundled table name or ``lambert`` (:func:`roadgonio.surface.rtable.load_table` uses the same rule).
Its name (outputs, folders, provenance) is the bundled name in capitals, ``lambert``, or the
file's stem.

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
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roadgonio.errors import InputError, ModelWarning
from roadgonio.geometry import TAN_EPS_GRID
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


def is_named_sample(text: str) -> bool:
    """``lambert`` or a bundled table name (any case): a SAMPLE that names no file."""
    s = str(text).strip()
    return s.lower() == "lambert" or s.upper() in BUNDLED


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


#: A model whose r at alpha = 1 deg falls by more than SPIKE_DROP of its value at beta = 0 within
#: SPIKE_WIDTH_DEG of beta = 0 has a peak there narrower than any instrument's aperture (the lab
#: preset's source subtends 0.06 deg): what an instrument measures of it is the fit's artefact, not
#: the surface's. The paper's power reading fitted to CIE R2 and R4 does this (the exponent
#: exp(1 + h f^2) of eq. 4's empirical term reaches ~1e14 at grazing incidence); the bundled tables'
#: other fits lose at most 0.4 % within 0.01 deg.
SPIKE_WIDTH_DEG = 0.01
SPIKE_DROP = 0.1


def unresolved_spike(model: RoadModel) -> tuple[np.ndarray, np.ndarray]:
    """The tan eps of the standard grid (> 0) where ``model``'s r(beta, tan eps) at alpha = 1 deg
    falls by more than :data:`SPIKE_DROP` within :data:`SPIKE_WIDTH_DEG` of beta = 0, and the ratio
    r(SPIKE_WIDTH_DEG) / r(0) there. (It is not k_A: an aperture averages r over the spike's
    neighbourhood, which for a narrow lobe off the nominal direction can be far above r(0): k_A 1.8
    to 730 at tan eps 12 for the Phong lobe of exponent 1e4 at its bound, audit 21.)"""
    t = TAN_EPS_GRID[TAN_EPS_GRID > 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        r0 = np.asarray(model.r(t, 0.0), dtype=np.float64)
        ratio = np.asarray(model.r(t, SPIKE_WIDTH_DEG), dtype=np.float64) / r0
    bad = (r0 > 0) & (ratio < 1.0 - SPIKE_DROP)
    return t[bad], ratio[bad]


def note_unresolved_spike(model: RoadModel, name: str, *, fitted: bool, option: str = "--model-variant") -> None:
    """Warn (:class:`ModelWarning`) when ``model`` has a spike at beta = 0 no aperture resolves
    (:func:`unresolved_spike`); ``fitted``: the model was fitted to a table here, so another
    variant is the way out, by the command's ``option`` (``fit``'s is ``--variant``)."""
    t, ratio = unresolved_spike(model)
    if not t.size:
        return
    # a model file's name is the table it was fitted to (model.json's "name"), not the file's stem
    own = getattr(model, "name", None) or name
    what = f"{name} ({model.variant} fit)" if fitted else f"the model of {own} ({model.variant})"
    way = (f"; {option} smooth fits {name} without it" if fitted and model.variant != "smooth" else "")
    warnings.warn(ModelWarning(
        f"{what}: r at beta = 0 is a spike narrower than {SPIKE_WIDTH_DEG:g} deg for tan eps {t.min():g} ... "
        f"{t.max():g} (r falls to {ratio.min():.2f} of its value within {SPIKE_WIDTH_DEG:g} deg), finer than any "
        f"aperture resolves: k_A and corrections there are artefacts of the fit (an aperture measures how much of "
        f"the spike it averages in, not the surface){way} (docs/conventions.md, section 3)"), stacklevel=3)


def capped_cells(model: RoadModel) -> list[tuple[float, float]]:
    """The cells (tan eps, beta) of the standard grid where ``model``'s empirical term is held at the
    exponent's cap (:meth:`RoadModel.exponent_capped`)."""
    from roadgonio.geometry import BETA_GRID_DEG
    t, b = np.meshgrid(TAN_EPS_GRID, BETA_GRID_DEG, indexing="ij")
    hit = model.exponent_capped(t, b)
    return [(float(x), float(y)) for x, y in zip(t[hit], b[hit])]


def note_capped_exponent(model: RoadModel, name: str, *, fitted: bool) -> None:
    """Warn (:class:`ModelWarning`) when ``model``'s empirical term reaches the exponent's cap at a cell
    of the grid (:func:`capped_cells`): there every command computes with the capped value, and the
    parameters evaluated by eq. 4 as written (conventions.md section 3) give another r."""
    cells = capped_cells(model)
    if not cells:
        return
    from roadgonio.surface.model import EXP_CAP
    own = getattr(model, "name", None) or name
    what = f"{name} ({model.variant} fit)" if fitted else f"the model of {own} ({model.variant})"
    first = ", ".join(f"{t:g}/{b:g}" for t, b in cells[:3]) + (" ..." if len(cells) > 3 else "")
    warnings.warn(ModelWarning(
        f"{what}: the empirical term's exponent reaches roadgonio's cap ({EXP_CAP:g}) at {len(cells)} cell"
        f"{'s' if len(cells) != 1 else ''} of the grid (tan eps/beta {first}): E is held at k_exp exp({EXP_CAP:g}) "
        "there, every command computes with the capped model, and its parameters (k_exp = "
        f"{model.params.k_exp:.3g}, p = {model.params.p:.4g}) evaluated by eq. 4 as written give another r"
        + ("; the fit stopped where the cap held it, so they are not the table's own" if fitted else "")
        + " (docs/conventions.md, section 3)"), stacklevel=3)


@dataclass(frozen=True)
class ResolvedSample:
    """A SAMPLE resolved once: ``name`` (for outputs and folders), the road BRDF ``model``, and the
    r-table ``table`` when the sample is one (bundled, file, RTable, DataArray; else None).
    ``spec`` is what was given, as text (provenance)."""

    name: str
    model: RoadModel
    table: RTable | None = None
    spec: str = ""


def _check_variant(model_variant: str | None, field: str = "model_variant") -> None:
    if model_variant is not None and model_variant not in VARIANTS:
        raise InputError(f"unknown model variant {model_variant!r}; expected one of {', '.join(VARIANTS)}",
                         field=field)


def resolve_sample(sample, model_variant: str | None = None, *, field: str = "sample") -> ResolvedSample:
    """The one resolver of a SAMPLE (module docstring): text or object -> :class:`ResolvedSample`,
    the model checked not to be degenerate (:func:`check_not_degenerate`). ``model_variant``
    chooses the variant fitted to a table (default ``"power"``); for a model file or object it
    must equal the model's variant if given. Errors name ``field``."""
    _check_variant(model_variant)
    if isinstance(sample, RoadModel):
        if model_variant is not None and sample.variant != model_variant:
            raise InputError(f"the model has variant {sample.variant!r}, but variant {model_variant!r} was asked",
                             field=field)
        return ResolvedSample(sample.name or "model", check_not_degenerate(sample), None, sample.name or "model")
    table = _as_table(sample)
    if table is not None:
        return _noted(ResolvedSample(table.name, check_not_degenerate(fitted_model(table, model_variant)), table,
                                     table.name), fitted=True)
    if hasattr(sample, "model") and hasattr(sample, "table") and isinstance(sample.model, RoadModel):  # a fit result
        return _noted(ResolvedSample(sample.table.name, check_not_degenerate(sample.model), sample.table,
                                     sample.table.name), fitted=True)
    if not isinstance(sample, (str, Path)):
        raise InputError("expected 'lambert', a bundled table name, a table or model file, a RoadModel, an RTable, "
                         f"an r-table DataArray or a fit result, got {type(sample).__name__}", field=field)
    s = str(sample).strip()
    if not s:
        raise InputError(f"empty sample; expected {EXPECTED}", field=field)
    if s.lower() == "lambert":
        return ResolvedSample("lambert", RoadModel.lambert(), None, s)
    p = Path(s).expanduser()
    suffix = p.suffix.lower()
    if suffix == ".json":
        if not p.exists():
            raise InputError(f"no such model file; expected {EXPECTED}", path=p)
        m = RoadModel.load(p)
        if model_variant is not None and m.variant != model_variant:
            raise InputError(f"the model file holds variant {m.variant!r}, but variant {model_variant!r} was asked",
                             path=p, field="variant")
        return _noted(ResolvedSample(p.stem, check_not_degenerate(m, path=p), None, s), fitted=False)
    if suffix in TABLE_SUFFIXES or (not suffix and is_named_sample(s)):      # ("lambert" returned above)
        if suffix and not p.exists():
            raise InputError(f"no such table file; expected {EXPECTED}", path=p)
        table = load_table(s)
        path = p if suffix else None
        name = p.stem if suffix else s.upper()
        return _noted(ResolvedSample(name, check_not_degenerate(fitted_model(table, model_variant), path=path), table, s),
                      fitted=True)
    raise InputError(f"unknown sample {s!r}; expected {EXPECTED}", field=field)


def _noted(smp: ResolvedSample, *, fitted: bool) -> ResolvedSample:
    note_unresolved_spike(smp.model, smp.name, fitted=fitted)
    note_capped_exponent(smp.model, smp.name, fitted=fitted)
    return smp


def _as_table(obj) -> RTable | None:
    """An RTable from an RTable or an r-table DataArray, else None."""
    if isinstance(obj, RTable):
        return obj
    xr = sys.modules.get("xarray")
    if xr is not None and isinstance(obj, xr.DataArray):
        return RTable.from_dataarray(obj)
    return None
