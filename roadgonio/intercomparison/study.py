"""The study file of ``roadgonio intercompare``: frozen, validated dataclasses built from TOML.

.. code-block:: toml

    [study]
    name = "R3 comparison"            # labels for the outputs
    description = "..."
    surface = "R3"                    # the true surface: any SAMPLE (bundled table, table file, model.json)
    # model_variant = "power"         # when the surface is a table to fit
    cells = "standard"                # the CIE tabulated region (396 cells) or "all" (580)
    realisations = 200                # simulated outcomes of the comparison
    # corrected_realisations = 200    # of them, how many are corrected by roadgonio (default: all); a
                                      # participant with report = "self" has a table only in these
    seed = 1
    coverage_factor = 2.0             # k of U(d_i) and E_n
    backend = "mitsuba"               # k_A backend: mitsuba, or quadrature (deterministic, ~50x slower
                                      # here: docs/intercomparison.md, Time)
    # rel_se = 3e-3                   # its tolerance for the participants' k_A (mitsuba: target relative
                                      # SE; quadrature: rtol)
    # correction_rel_se = 1e-3        # the tolerance of the corrections' k_A (default: roadgonio correct's)

    [[participant]]
    name = "NMI-A"
    instrument = "lab"                # preset name or instrument file (relative to the study file)
    # calibration = {mode = "absolute"}   # overrides the instrument's [calibration]
    sigma = "alpha_deg=0.005,eps_deg=0.02"   # misalignment SPEC as in `roadgonio uncertainty --sigma`
                                      # (or an inline table of the same keys)
    noise_rel = 0.002                 # repeatability: relative standard deviation of each cell
    calibration_u_rel = 0.005         # its own calibration standard: a relative scale error
    # illuminance = "nominal"         # or "measured" (docs of roadgonio.uncertainty)
    report = "raw"                    # raw | self (roadgonio correct --reference self) | reference
    # reference = "R2"                # the SAMPLE it corrects with (report = "reference")
    stated = ["repeatability", "misalignment", "calibration"]   # its stated uncertainty
    # stated_extra_rel = 0.0          # any further relative standard uncertainty it states

    [[shared]]                        # effects participants share: correlations between them
    name = "tile"
    kind = "reference_tile"           # a common reference: one relative scale error u_rel
    u_rel = 0.005
    participants = ["NMI-A", "NMI-D"]

    [[shared]]
    name = "angles"
    kind = "angle_standard"           # a common angle standard: one error set (SPEC) for all
    sigma = "eps_deg=0.02"
    participants = ["NMI-B", "NMI-C"]

Unknown sections and keys are errors naming the file and the field (``participant[2].noise_rel``),
like instrument files.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument, load_instrument
from roadgonio.surface.rtable import U_REL_MIN

REPORTS = ("raw", "self", "reference")
STATED = ("repeatability", "misalignment", "calibration")
SHARED_KINDS = ("reference_tile", "angle_standard")
CELL_CHOICES = ("standard", "all")
#: The backends of a study and their default tolerance: the registry's ``study_tolerance``
#: (:func:`roadgonio.engines.registry.backends_with`), shared with ``uncertainty``.

#: The most realisations a study may ask for: each is a table per participant and per scenario
#: (200 is the default; 1e12 was accepted and hung, audit 22).
MAX_REALISATIONS = 100_000

_STUDY_KEYS = {"name", "description", "surface", "model_variant", "cells", "realisations", "corrected_realisations",
               "seed", "coverage_factor", "backend", "rel_se", "correction_rel_se"}
_PARTICIPANT_KEYS = {"name", "instrument", "calibration", "sigma", "noise_rel", "calibration_u_rel", "illuminance",
                     "report", "reference", "stated", "stated_extra_rel"}
_SHARED_KEYS = {"name", "kind", "u_rel", "sigma", "participants"}


def _number(v: Any, fld: str, path, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
            integer: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"expected a {'whole ' if integer else ''}number, got {v!r}", path=path, field=fld)
    if integer and not isinstance(v, int):      # audit 22: 6.0 passed (the API refuses seed=1.0)
        raise InputError(f"expected a whole number (without a decimal point), got {v!r}", path=path, field=fld)
    if integer and v > 2 ** 63 - 1:            # float(v) would round it: compare exactly
        raise InputError(f"expected a value <= {hi if hi is not None else 2 ** 63 - 1}, got {v}", path=path, field=fld)
    x = float(v)
    if not math.isfinite(x):
        raise InputError(f"expected a finite number, got {v!r}", path=path, field=fld)
    if lo is not None and (x < lo or (lo_open and x == lo)):
        raise InputError(f"expected a value {'>' if lo_open else '>='} {lo:g}, got {x:g}", path=path, field=fld)
    if hi is not None and x > hi:
        raise InputError(f"expected a value <= {hi:g}, got {x:g}", path=path, field=fld)
    return x


def _text(v: Any, fld: str, path, *, choices: tuple[str, ...] | None = None) -> str:
    if not isinstance(v, str) or not v.strip():
        raise InputError(f"expected text, got {v!r}", path=path, field=fld)
    s = v.strip()
    if choices is not None and s not in choices:
        raise InputError(f"expected one of {', '.join(choices)}, got {s!r}", path=path, field=fld)
    return s


def _keys(d: Any, allowed: set[str], fld: str, path) -> None:
    if not isinstance(d, Mapping):
        raise InputError("expected a table", path=path, field=fld)
    extra = sorted(set(d) - allowed)
    if extra:
        raise InputError(f"unknown key(s) {', '.join(extra)}; expected some of {', '.join(sorted(allowed))}",
                         path=path, field=f"{fld}.{extra[0]}" if fld else extra[0])


def _sigma(v: Any, fld: str, path):
    """A SigmaSpec from a SPEC text or an inline table (errors name the study file and field)."""
    from roadgonio.uncertainty.spec import parse_sigma_spec
    if isinstance(v, Mapping):
        spec_in: Any = dict(v)
    elif isinstance(v, str):
        spec_in = v
        p = Path(v.strip())
        if p.suffix.lower() == ".toml" and not p.is_absolute() and path is not None:
            spec_in = str(Path(path).parent / p)
    else:
        raise InputError(f"expected a SPEC text (KEY=SIGMA[:DIST],...) or a table of the same keys, got {v!r}",
                         path=path, field=fld)
    try:
        return parse_sigma_spec(spec_in, option=fld)
    except InputError as err:
        raise InputError(err.reason, path=err.path or path, line=err.line, field=err.field or fld) from None


@dataclass(frozen=True)
class Participant:
    """One laboratory: its instrument, misalignment, repeatability, calibration, what it does with
    its table, and what it states as its uncertainty (module docstring)."""

    name: str
    instrument: Instrument
    instrument_spec: str
    sigma: Any                       # roadgonio.uncertainty.SigmaSpec
    noise_rel: float = 0.0
    calibration_u_rel: float = 0.0
    illuminance: str = "nominal"
    report: str = "raw"
    reference: str | None = None
    stated: tuple[str, ...] = STATED
    stated_extra_rel: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "instrument": self.instrument.to_dict(), "instrument_spec": self.instrument_spec,
                "sigma": self.sigma.to_dict(), "noise_rel": self.noise_rel,
                "calibration_u_rel": self.calibration_u_rel, "illuminance": self.illuminance, "report": self.report,
                "reference": self.reference, "stated": list(self.stated), "stated_extra_rel": self.stated_extra_rel}


@dataclass(frozen=True)
class SharedEffect:
    """An effect several participants share: a reference tile (one relative scale error u_rel) or
    an angle standard (one error set drawn from ``sigma`` for all of them)."""

    name: str
    kind: str
    participants: tuple[str, ...]
    u_rel: float = 0.0
    sigma: Any = None                # SigmaSpec for an angle standard

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name, "kind": self.kind, "participants": list(self.participants)}
        if self.kind == "reference_tile":
            d["u_rel"] = self.u_rel
        else:
            d["sigma"] = self.sigma.to_dict()
        return d


@dataclass(frozen=True)
class Study:
    name: str
    surface: str
    participants: tuple[Participant, ...]
    shared: tuple[SharedEffect, ...] = ()
    description: str = ""
    model_variant: str | None = None
    cells: str = "standard"
    realisations: int = 200
    corrected_realisations: int | None = None
    seed: int = 1
    coverage_factor: float = 2.0
    backend: str = "mitsuba"
    rel_se: float | None = None
    correction_rel_se: float | None = None
    path: Path | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def n_corrected(self) -> int:
        return self.realisations if self.corrected_realisations is None else self.corrected_realisations

    @property
    def tolerance(self) -> float:
        """The relative target of the participants' k_A tables: ``rel_se`` as given, else the
        backend's default (the registry's ``study_tolerance``); a ``rel_se`` or an ``rtol`` as the
        backend takes it (:attr:`tolerance_setting`)."""
        from roadgonio.engines.registry import backend_info
        return backend_info(self.backend).study_tolerance if self.rel_se is None else self.rel_se

    @property
    def tolerance_setting(self) -> dict[str, float]:
        """:attr:`tolerance` under the backend's name for it: ``{"rel_se": ...}`` or ``{"rtol": ...}``."""
        from roadgonio.engines.registry import tolerance_setting
        return tolerance_setting(self.backend, self.tolerance, "study.rel_se")

    def index(self, name: str) -> int:
        return [p.name for p in self.participants].index(name)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "description": self.description, "surface": self.surface,
                "model_variant": self.model_variant, "cells": self.cells, "realisations": self.realisations,
                "corrected_realisations": self.n_corrected, "seed": self.seed,
                "coverage_factor": self.coverage_factor, "backend": self.backend, "tolerance": self.tolerance_setting,
                "correction_rel_se": self.correction_rel_se,
                "participants": [p.to_dict() for p in self.participants],
                "shared": [s.to_dict() for s in self.shared], "file": str(self.path) if self.path else None}


def _participant(k: int, d: Any, path) -> Participant:
    fld = f"participant[{k + 1}]"
    _keys(d, _PARTICIPANT_KEYS, fld, path)
    for req in ("name", "instrument"):
        if req not in d:
            raise InputError("missing (required)", path=path, field=f"{fld}.{req}")
    name = _text(d["name"], f"{fld}.name", path)
    spec = _text(d["instrument"], f"{fld}.instrument", path)
    p = Path(spec).expanduser()
    if p.suffix.lower() == ".toml" and not p.is_absolute() and path is not None:
        p = Path(path).parent / p
    try:
        inst = load_instrument(p if p.suffix.lower() == ".toml" else spec)
    except InputError as err:
        if err.path is not None and Path(err.path).is_file():
            # an error inside the instrument file names that file and its field (user audit, session 39:
            # an error in the participant's own file was told as the study's field 'participant[k].instrument')
            raise InputError(f"{err.reason} ({fld}'s instrument, from {path if path is not None else 'the study'})",
                             path=err.path, line=err.line, field=err.field) from None
        # the file looked for, by its path (user audit, session 44: 'no such instrument file' named none)
        looked = f" {err.path}:" if err.path is not None else ""
        raise InputError(f"{looked} {err.reason} (the participant's instrument)".lstrip(), path=path,
                         field=f"{fld}.instrument") from None
    if "calibration" in d:
        cal = d["calibration"]
        if not isinstance(cal, Mapping):
            raise InputError("expected a table {mode = \"lambert\"|\"absolute\"|\"reference\", reference = SAMPLE}",
                             path=path, field=f"{fld}.calibration")
        idict = inst.to_dict()
        idict["calibration"] = dict(cal)
        try:
            inst = Instrument.from_dict(idict, path=inst.path)
        except InputError as err:
            raise InputError(err.reason, path=path, field=f"{fld}.{err.field or 'calibration'}") from None
    sigma = _sigma(d.get("sigma", {}), f"{fld}.sigma", path)
    noise = _number(d.get("noise_rel", 0.0), f"{fld}.noise_rel", path, lo=0.0, hi=0.5)
    cal_u = _number(d.get("calibration_u_rel", 0.0), f"{fld}.calibration_u_rel", path, lo=0.0, hi=0.5)
    illum = _text(d.get("illuminance", "nominal"), f"{fld}.illuminance", path, choices=("nominal", "measured"))
    report = _text(d.get("report", "raw"), f"{fld}.report", path, choices=REPORTS)
    reference = d.get("reference")
    if report == "reference":
        if reference is None:
            raise InputError("report = \"reference\" needs reference = SAMPLE (a bundled table name, a table file or "
                             "a model.json)", path=path, field=f"{fld}.reference")
        reference = _text(reference, f"{fld}.reference", path)
        rp = Path(reference).expanduser()
        if rp.suffix and not rp.is_absolute() and path is not None:
            reference = str(Path(path).parent / rp)
    elif reference is not None:
        raise InputError(f"reference is only used with report = \"reference\" (report is {report!r})", path=path,
                         field=f"{fld}.reference")
    if report != "raw" and noise < U_REL_MIN:
        raise InputError(f"a participant that corrects its table needs noise_rel >= {U_REL_MIN:g} (its measurement "
                         f"uncertainty weights the correction), got {noise:g}", path=path, field=f"{fld}.noise_rel")
    stated = d.get("stated", list(STATED))
    if not isinstance(stated, (list, tuple)) or not all(isinstance(s, str) for s in stated):
        raise InputError(f"expected a list of some of {', '.join(STATED)}", path=path, field=f"{fld}.stated")
    bad = sorted(set(stated) - set(STATED))
    if bad:
        raise InputError(f"unknown stated component(s) {', '.join(bad)}; expected some of {', '.join(STATED)}",
                         path=path, field=f"{fld}.stated")
    extra = _number(d.get("stated_extra_rel", 0.0), f"{fld}.stated_extra_rel", path, lo=0.0, hi=0.5)
    return Participant(name=name, instrument=inst, instrument_spec=spec, sigma=sigma, noise_rel=noise,
                       calibration_u_rel=cal_u, illuminance=illum, report=report, reference=reference,
                       stated=tuple(s for s in STATED if s in stated), stated_extra_rel=extra)


def _shared(k: int, d: Any, names: list[str], path) -> SharedEffect:
    fld = f"shared[{k + 1}]"
    _keys(d, _SHARED_KEYS, fld, path)
    for req in ("name", "kind", "participants"):
        if req not in d:
            raise InputError("missing (required)", path=path, field=f"{fld}.{req}")
    name = _text(d["name"], f"{fld}.name", path)
    kind = _text(d["kind"], f"{fld}.kind", path, choices=SHARED_KINDS)
    who = d["participants"]
    if not isinstance(who, (list, tuple)) or len(who) < 2 or not all(isinstance(w, str) for w in who):
        raise InputError("expected a list of at least two participant names", path=path, field=f"{fld}.participants")
    unknown = [w for w in who if w not in names]
    if unknown:
        raise InputError(f"no participant named {unknown[0]!r}; expected some of {', '.join(names)}", path=path,
                         field=f"{fld}.participants")
    if len(set(who)) != len(who):
        raise InputError("a participant is listed twice", path=path, field=f"{fld}.participants")
    if kind == "reference_tile":
        if "sigma" in d:
            raise InputError("a reference tile has u_rel, not sigma", path=path, field=f"{fld}.sigma")
        if "u_rel" not in d:
            raise InputError("missing (required for a reference tile)", path=path, field=f"{fld}.u_rel")
        u = _number(d["u_rel"], f"{fld}.u_rel", path, lo=0.0, hi=0.5, lo_open=True)
        return SharedEffect(name=name, kind=kind, participants=tuple(who), u_rel=u)
    if "u_rel" in d:
        raise InputError("an angle standard has sigma (a SPEC), not u_rel", path=path, field=f"{fld}.u_rel")
    if "sigma" not in d:
        raise InputError("missing (required for an angle standard)", path=path, field=f"{fld}.sigma")
    sig = _sigma(d["sigma"], f"{fld}.sigma", path)
    if not any(s > 0 for s in sig.sigma):
        raise InputError("expected at least one standard deviation > 0", path=path, field=f"{fld}.sigma")
    return SharedEffect(name=name, kind=kind, participants=tuple(who), sigma=sig)


def corrects_nothing(instrument: Instrument) -> bool:
    """A collimated (ideal) instrument calibrated against a Lambertian standard: k_A = 1, its
    correction changes nothing (it reports its table raw whatever it is asked)."""
    return instrument.is_ideal() and instrument.calibration.mode == "lambert"


def states_raw(part: Participant) -> bool:
    """The participant states its raw table's uncertainty alone in some scenario (it reports raw,
    or its correction changes nothing, :func:`corrects_nothing`): that uncertainty must then be
    positive at every cell, nothing else adds to it."""
    return part.report == "raw" or corrects_nothing(part.instrument)


def _stated_can_be_positive(part: Participant, shared: Sequence[SharedEffect]) -> bool:
    """At least one stated component of ``part`` has a positive value (the components of
    :func:`roadgonio.intercomparison.simulate.stated_rel`)."""
    mine = [x for x in shared if part.name in x.participants]
    angles = [part.sigma] + [x.sigma for x in mine if x.kind == "angle_standard"]
    return bool(part.stated_extra_rel > 0
                or ("repeatability" in part.stated and part.noise_rel > 0)
                or ("calibration" in part.stated
                    and (part.calibration_u_rel > 0 or any(x.u_rel > 0 for x in mine if x.kind == "reference_tile")))
                or ("misalignment" in part.stated
                    and any(sp is not None and bool(np.any(np.asarray(sp.sigmas) > 0)) for sp in angles)))


def study_from_dict(d: Mapping[str, Any], *, path: str | Path | None = None) -> Study:
    """A :class:`Study` from the dict of a study file (unknown keys are errors naming ``path``)."""
    path = Path(path) if path is not None else None
    _keys(d, {"study", "participant", "shared"}, "", path)
    s = d.get("study", {})
    _keys(s, _STUDY_KEYS, "study", path)
    if "surface" not in s:
        raise InputError("missing (required): the true surface, a SAMPLE", path=path, field="study.surface")
    surface = _text(s["surface"], "study.surface", path)
    sp = Path(surface).expanduser()
    if sp.suffix and not sp.is_absolute() and path is not None:
        surface = str(path.parent / sp)
    from roadgonio.surface.model import VARIANTS
    variant = s.get("model_variant")
    if variant is not None:
        variant = _text(variant, "study.model_variant", path, choices=tuple(VARIANTS))
    cells = _text(s.get("cells", "standard"), "study.cells", path, choices=CELL_CHOICES)
    n = int(_number(s.get("realisations", 200), "study.realisations", path, lo=2, hi=MAX_REALISATIONS, integer=True))
    nc = s.get("corrected_realisations")
    if nc is not None:
        nc = int(_number(nc, "study.corrected_realisations", path, lo=0, hi=n, integer=True))
    from roadgonio.seeds import SEED_MAX
    seed = int(_number(s.get("seed", 1), "study.seed", path, lo=0, hi=SEED_MAX, integer=True))
    k = _number(s.get("coverage_factor", 2.0), "study.coverage_factor", path, lo=0.0, lo_open=True, hi=10.0)
    from roadgonio.engines.registry import backends_with
    backend = _text(s.get("backend", "mitsuba"), "study.backend", path, choices=backends_with(study_tolerance=True))
    rel_se = s.get("rel_se")
    if rel_se is not None:
        rel_se = _number(rel_se, "study.rel_se", path, lo=0.0, lo_open=True, hi=0.1)
    crel = s.get("correction_rel_se")
    if crel is not None:
        crel = _number(crel, "study.correction_rel_se", path, lo=0.0, lo_open=True, hi=0.1)
    plist = d.get("participant", [])
    if not isinstance(plist, list) or not plist:
        raise InputError("expected [[participant]] tables (at least two)", path=path, field="participant")
    participants = tuple(_participant(i, p, path) for i, p in enumerate(plist))
    if len(participants) < 2:
        raise InputError(f"a comparison needs at least two participants, got {len(participants)}", path=path,
                         field="participant")
    selfs = [p.name for p in participants if p.report == "self"]
    if selfs and (n if nc is None else nc) < 2:
        # audit 22: 0 gave a traceback in the pictures, or a study that compared nothing with exit 0
        raise InputError(f"participant(s) {', '.join(selfs)} report their own correction (report = \"self\"), which "
                         "exists only in the corrected realisations: expected corrected_realisations >= 2 (or leave "
                         f"it out: all {n})", path=path, field="study.corrected_realisations")
    names = [p.name for p in participants]
    dup = sorted({x for x in names if names.count(x) > 1})
    if dup:
        raise InputError(f"two participants are named {dup[0]!r}", path=path, field="participant.name")
    slist = d.get("shared", [])
    if not isinstance(slist, list):
        raise InputError("expected [[shared]] tables", path=path, field="shared")
    shared = tuple(_shared(i, x, names, path) for i, x in enumerate(slist))
    snames = [x.name for x in shared]
    if len(set(snames)) != len(snames):
        raise InputError("two shared effects have the same name", path=path, field="shared.name")
    for i, part in enumerate(participants):
        if states_raw(part) and not _stated_can_be_positive(part, shared):
            # audit 27: accepted, then refused after the k_A work with a line naming no file or participant
            raise InputError(f"participant {part.name!r} reports its table raw and states a standard uncertainty that "
                             f"is 0 (stated = {list(part.stated)}, stated_extra_rel = {part.stated_extra_rel:g}); "
                             "expected at least one stated component with a positive value: 'repeatability' with "
                             "noise_rel > 0, 'calibration' with calibration_u_rel > 0 (or a reference tile), "
                             "'misalignment' with a sigma, or stated_extra_rel > 0", path=path,
                             field=f"participant[{i + 1}].stated")
    if (n if nc is None else nc) > 0:
        for i, part in enumerate(participants):
            if not corrects_nothing(part.instrument) and part.noise_rel < U_REL_MIN:
                # user audit: accepted, then refused after the k_A work by the correction, naming u_measured
                # and neither the study file nor the participant
                raise InputError(f"participant {part.name!r}: the all-corrected scenario corrects every "
                                 "participant's table (roadgonio correct --reference self) weighted by its repeatability: "
                                 f"expected noise_rel >= {U_REL_MIN:g} (or corrected_realisations = 0), got "
                                 f"{part.noise_rel:g}", path=path, field=f"participant[{i + 1}].noise_rel")
    name = _text(s.get("name", path.stem if path is not None else "study"), "study.name", path)
    desc = s.get("description", "")
    if not isinstance(desc, str):
        raise InputError(f"expected text, got {desc!r}", path=path, field="study.description")
    return Study(name=name, description=desc, surface=surface, model_variant=variant, cells=cells, realisations=n,
                 corrected_realisations=nc, seed=seed, coverage_factor=k, backend=backend, rel_se=rel_se,
                 correction_rel_se=crel,
                 participants=participants, shared=shared, path=path)


def load_study(spec: str | Path) -> Study:
    """A study from a TOML file, or a bundled example study by name (:func:`bundled_studies`)."""
    p = Path(spec).expanduser()
    if not p.exists():
        names = bundled_studies()
        if str(spec) in names:
            from importlib import resources
            p = Path(str(resources.files("roadgonio.studies").joinpath(f"{spec}.toml")))
        else:
            raise InputError(f"no such study file, and not a bundled study ({', '.join(names) or 'none'})", path=p)
    from roadgonio.fileio import read_toml
    d = read_toml(p, "study file")
    return study_from_dict(d, path=p)


def bundled_studies() -> list[str]:
    """Names of the example studies shipped in studies/ (installed as roadgonio.studies)."""
    from importlib import resources
    try:
        files = resources.files("roadgonio.studies").iterdir()
    except ModuleNotFoundError:
        return []
    return sorted(f.name[:-5] for f in files if f.name.endswith(".toml") and not f.name.startswith("instrument-"))
