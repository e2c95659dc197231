"""The k_A backends and what each can do: ONE registry that the command line, the Python API,
``design``, ``uncertainty``, ``correct`` and ``validate`` all read (docs/architecture.md, "How to
add a backend").

Each :class:`BackendInfo` says how to build the backend (a lazy ``"module:function"`` factory, so a
numpy-only run never imports mitsuba; the ``bundle`` backend is the correction's forward model of
fixed ray bundles, which applies the calibration itself), what its precision is (a standard error, a deterministic
bound, or a standard error with a statistical confidence bound: :mod:`roadgonio.engines.result`),
whether it takes a seed, its accuracy presets, what its one tolerance is called (``rel_se`` or
``rtol``), and which instruments it models (mesh samples, Mitsuba XML scenes, a beam limit that
clips the footprint). :func:`make_backend` resolves everything a backend needs in one place:
preset < tolerance < explicit settings, the seed, the Mitsuba variant, the capability checks, and
the instrument's calibration (:mod:`roadgonio.engines.calibration`).

Accuracy presets, placed on the measured speed-accuracy frontier (bench/bench_accuracy.py,
bench/results/accuracy.csv and pareto.png; portable preset, R3-like model, 7 cells including the
specular peak tan 12 / beta 0 and 2, max relative error against quadrature at rtol 1e-7; session 25):

========  ==============================  ==============================  ==============================
preset    quadrature                      mitsuba (float32, batched)      numpy-mc (float64 oracle)
========  ==============================  ==============================  ==============================
fast      rtol 1e-3: err 5.9e-5           rel_se 3e-3, first pass 4096:   rel_se 3e-3, batch 12^2:
                                          err 2.0e-4 (SE 3.2e-4)          err 2.6e-4
default   rtol 1e-4: err 1.8e-5           rel_se 1e-3, first pass 4096:   rel_se 1e-3, batch 45^2:
                                          err 2.0e-4 (SE 3.2e-4)          err 1.4e-4
precise   rtol 1e-6: err 2.9e-7           rel_se 1e-4, first pass 4096:   rel_se 1e-4, batch 64^2:
                                          err 1.1e-4                      err 9.7e-5
========  ==============================  ==============================  ==============================

Every Mitsuba preset starts with 16 lattices of 256 points (fast had 256 samples, default 1024 until
session 25: on the wide preset the smaller lattices gave skewed replicate sums and, at the beta 180
cells, SEs 1.4-1.5 times too small with a bias of 6 SEMs; docs/validation.md, "Small lattices on the
wide preset"). On these cells fast and default are then the same run (each cell meets either target
in its first pass), at the time the smaller first passes took (bare tables: the table's fixed cost
dominates). numpy-mc takes at least 64 batches (the SE's degrees of freedom,
:data:`roadgonio.engines.montecarlo.DEFAULT_MIN_BATCHES`), about fast 9216, default 129600, precise
>= 262144 samples.

The ``bundle`` backend (the correction's fixed ray bundles, 4 replicates) has no stopping rule; its
presets are rays per cell, measured on the portable table of R3 (396 cells) against the quadrature
at rtol 1e-6: fast 128 rays, max error 9.3e-3 (max rel SE 6.0e-3); default 512, 2.3e-3 (1.5e-3);
precise 4096, 2.8e-4 (2.1e-4).

The batched Mitsuba engine stops every cell at its target (a first pass of 4096 samples, then the 1/N rule per
cell), so its presets sit on the measured front by construction; ``first_pass`` only matters for
the easy cells. The reference's presets are the same tolerances as the quadrature's (its ``rtol``
is the target of its confidence bound), the mesh Monte Carlo's the same ``rel_se`` as numpy-mc's
in batches of its own (:data:`NUMPY_MC_MESH_PRESETS`). Timings of each preset: docs/benchmarks.md.
"""
from __future__ import annotations

import importlib
import math
import numbers
from dataclasses import dataclass, field
from typing import Any, Mapping

from roadgonio.errors import InputError
from roadgonio.seeds import SEED_MAX, check_seed  # noqa: F401 - the seed range, written once in roadgonio.seeds

#: The accuracy presets, by name.
PRESETS = ("fast", "default", "precise")


@dataclass(frozen=True)
class BackendInfo:
    """One backend of the registry (module docstring)."""

    name: str
    factory: str                     # "module:function(instrument, model, **settings)"
    summary: str                     # one line for --help and the docs
    precision: str                   # "se" | "error_bound" | "se+confidence_bound"
    seeded: bool                     # takes a seed (Monte Carlo / randomised QMC)
    tolerance: str | None            # the setting one relative target maps to: "rel_se", "rtol", or None (none)
    presets: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    meshes: bool = False             # models a mesh sample ([sample] mesh)
    xml_scenes: bool = False         # models the extra parts of a Mitsuba XML scene ([scene] xml)
    beam_clipping: bool = True       # models a beam limit that clips the light on the footprint
    beam_profile: bool = True        # models a source radiance profile ([source] beam_* / aperture_* keys)
    field_map: bool = True           # models a detector sensitivity map ([detector] field_sensitivity)
    #: the source paths it models ([source] path: "arc", "fixed_height"; docs/conventions.md section 4)
    source_paths: tuple[str, ...] = ("arc", "fixed_height")
    mitsuba: bool = False            # needs mitsuba/drjit and a selected variant (Dask workers set one up)
    calibrates: bool = False         # applies the instrument's [calibration] itself (make_backend must not wrap it)
    #: the default relative target (of its ``tolerance`` setting) of the many k_A tables of perturbed
    #: instruments that ``uncertainty`` (the exact tables behind its surrogate) and ``intercompare``
    #: compute; None: those commands do not offer the backend
    study_tolerance: float | None = None
    cell_correlation: str = ("independent: each cell has its own random numbers, seeded by (seed, tan eps, beta)")
    #: its part in ``roadgonio validate``: "checked" (a float32/Monte Carlo backend it checks, --against),
    #: "reference" (a float64 reference it checks against, --reference), or None
    validate_role: str | None = None

    @property
    def deterministic(self) -> bool:
        return self.precision == "error_bound"


#: numpy-mc's presets: about the sample counts of before (fast 9216, default 129600, precise from
#: 262144), cut into montecarlo.DEFAULT_MIN_BATCHES = 64 batches at least (an SE from 8 batch means
#: had 7 degrees of freedom, and its z a t_7 distribution: RMS 1.18, trial 7 defect 3).
NUMPY_MC_PRESETS = {"fast": {"rel_se": 3e-3, "batch": 12 ** 2}, "default": {"rel_se": 1e-3, "batch": 45 ** 2},
                    "precise": {"rel_se": 1e-4, "batch": 64 ** 2}}

#: numpy-mc-mesh's presets, the same way: about the sample counts of before at the minimum (fast
#: 64 x 11^2 = 7744 for 8 x 32^2 = 8192; default and precise 64 x 23^2 = 33856 for 8 x 64^2 = 32768),
#: in meshmc.DEFAULT_MIN_BATCHES = 64 batches at least: it stopped at 8, with the same t_7 z (mean z^2
#: 1.40 over 720 results at fast, tests/unit/test_meshmc.py).
NUMPY_MC_MESH_PRESETS = {"fast": {"rel_se": 3e-3, "batch": 11 ** 2}, "default": {"rel_se": 1e-3, "batch": 23 ** 2},
                         "precise": {"rel_se": 1e-4, "batch": 23 ** 2}}


BACKENDS: dict[str, BackendInfo] = {b.name: b for b in (
    BackendInfo("mitsuba", "roadgonio.engines.mitsuba.backend:make_backend",
                "float32 ray tracing with Mitsuba 3 (the default; batched, many cells per launch)",
                precision="se", seeded=True, tolerance="rel_se",
                # first pass 16 lattices of 256 points at every preset: smaller lattices left the
                # wide preset's beta 180 cells with skewed replicate sums whose SE, selected by
                # the stopping rule, was too small (docs/validation.md, session 25)
                presets={"fast": {"rel_se": 3e-3, "first_pass": 4096}, "default": {"rel_se": 1e-3, "first_pass": 4096},
                         "precise": {"rel_se": 1e-4, "first_pass": 4096}},
                # beam_clipping: the kabatch integrator applies the hard cone to every source sample
                # and light path (session 22; agrees with the quadrature where it clips the footprint)
                meshes=True, xml_scenes=True, beam_clipping=True, mitsuba=True,
                # one seed for every perturbed instrument: the noise largely cancels in the differences
                # the uncertainty surrogate fits
                study_tolerance=3e-3, validate_role="checked",
                cell_correlation="correlated: the cells computed in one run share the detector rays and replicates, "
                                 "so their errors are positively correlated; each cell's SE is its marginal SE, a "
                                 "table functional needs the covariance (MitsubaBackend.covariance())"),
    BackendInfo("quadrature", "roadgonio.engines.quadrature:make_backend",
                "deterministic float64 tensor Gauss rules with an error bound (flat samples)",
                precision="error_bound", seeded=False, tolerance="rtol",
                presets={"fast": {"rtol": 1e-3}, "default": {"rtol": 1e-4}, "precise": {"rtol": 1e-6}},
                study_tolerance=1e-4, validate_role="reference",
                cell_correlation="deterministic: no random error; each cell's error is within its error_bound"),
    BackendInfo("numpy-mc", "roadgonio.engines.montecarlo:make_backend",
                "plain float64 Monte Carlo (slow; an oracle; flat samples)",
                precision="se", seeded=True, tolerance="rel_se", presets=NUMPY_MC_PRESETS, validate_role="checked"),
    BackendInfo("bundle", "roadgonio.engines.bundle:make_backend",
                "float64 fixed ray bundles (randomised QMC, common random numbers): the forward model of `correct` "
                "(flat samples)",
                precision="se", seeded=True, tolerance=None,
                presets={"fast": {"rays": 128}, "default": {"rays": 512}, "precise": {"rays": 4096}},
                calibrates=True,
                cell_correlation="independent: each cell's rays are seeded by (seed, the cell's index in the request); "
                                 "the SE is the spread of 4 replicates (3 degrees of freedom)"),
    BackendInfo("reference", "roadgonio.engines.reference:make_backend",
                "float64 randomised QMC with the kinks split off: SE and a 99.9 % confidence bound (flat samples)",
                precision="se+confidence_bound", seeded=True, tolerance="rtol",
                presets={"fast": {"rtol": 1e-3}, "default": {"rtol": 1e-4}, "precise": {"rtol": 1e-5}},
                validate_role="reference"),
    BackendInfo("numpy-mc-mesh", "roadgonio.engines.meshmc:make_backend",
                "float64 Monte Carlo with ray casting and shadow rays (mesh samples)",
                precision="se", seeded=True, tolerance="rel_se", presets=NUMPY_MC_MESH_PRESETS, meshes=True,
                validate_role="reference"),
)}


def validate_backends(role: str) -> tuple[str, ...]:
    """The backends with ``role`` in ``roadgonio validate`` ("checked" or "reference"), in the
    registry's order."""
    return tuple(n for n, b in BACKENDS.items() if b.validate_role == role)


def backend_info(name: str, field: str = "backend") -> BackendInfo:
    """The registry entry of ``name`` (an InputError listing the backends otherwise)."""
    if not isinstance(name, str) or name not in BACKENDS:
        raise InputError(f"unknown backend {name!r}; expected one of {', '.join(BACKENDS)}", field=field)
    return BACKENDS[name]


def _has(info: BackendInfo, capability: str, want) -> bool:
    have = getattr(info, capability)          # an AttributeError for a capability that does not exist
    if want is True and not isinstance(have, bool):
        return have is not None               # e.g. study_tolerance=True: has one
    return have == want


def backends_with(**capabilities) -> tuple[str, ...]:
    """The backends (in registry order) with each of ``capabilities``: a :class:`BackendInfo` field
    and the value it must have (``seeded=True``, ``precision="se"``, ``mitsuba=False``);
    ``True`` for a field that is not a flag means "has one" (``study_tolerance=True``). The one
    query behind a command's ``--backend`` choices and the API's check (:func:`check_backend`)."""
    return tuple(n for n, b in BACKENDS.items() if all(_has(b, k, v) for k, v in capabilities.items()))


def check_backend(name: str, field: str = "backend", purpose: str = "", **capabilities) -> BackendInfo:
    """The registry entry of ``name`` if it has ``capabilities`` (:func:`backends_with`), else an
    InputError listing the backends that do (``purpose``: what they are for, e.g. "uncertainty")."""
    allowed = backends_with(**capabilities)
    if not isinstance(name, str) or name not in allowed:
        what = "unknown backend" if not (isinstance(name, str) and name in BACKENDS) else "backend"
        raise InputError(f"{what} {name!r}{' for ' + purpose if purpose and what == 'backend' else ''}; expected "
                         f"one of {', '.join(allowed)}", field=field)
    return BACKENDS[name]


def check_relative(value, field: str) -> float:
    """A relative target (standard error or tolerance): a finite number in (0, 1)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (math.isfinite(value) and 0 < value < 1):
        raise InputError(f"expected a relative error in (0, 1), got {value!r}", field=field)
    return float(value)


def preset(name: str, backend: str, field: str = "accuracy") -> dict[str, Any]:
    """Settings of ``backend`` for the accuracy preset ``name``."""
    info = backend_info(backend)
    if name not in PRESETS:
        raise InputError(f"unknown accuracy preset {name!r}; expected one of {', '.join(PRESETS)}", field=field)
    if name not in info.presets:
        raise InputError(f"the {backend} backend has no accuracy presets; give its settings", field=field)
    return dict(info.presets[name])


def tolerance_setting(backend: str, value, field: str = "rel_se") -> dict[str, float]:
    """The backend keyword of one relative target: ``rtol`` (quadrature, reference: a relative
    error bound) or ``rel_se`` (Monte Carlo: a relative standard error)."""
    info = backend_info(backend)
    if info.tolerance is None:
        raise InputError(f"the {backend} backend has no relative target (it draws a fixed number of rays per "
                         "cell); give an accuracy preset or its settings (rays)", field=field)
    return {info.tolerance: check_relative(value, field)}


def unmodelled_parts(info: BackendInfo, instrument) -> list[tuple[str, str, str]]:
    """The instrument's parts beyond the flat sample and its apertures that ``info`` does not model,
    as (section, what it is, what of it matters): a ``[scene]`` (its extra geometry) and a ``[housing]`` (its walls' shade
    and stray light) need a backend that models XML scenes. One rule for :func:`check_capabilities`
    and for ``validate``'s refusal (which gives its own advice)."""
    return [] if info.xml_scenes else instrument.scene_parts()


def check_capabilities(info: BackendInfo, instrument) -> None:
    """Refuse an instrument the backend does not model (never ignore part of it): a Mitsuba XML
    scene's extra parts, a [housing] (the backends that model XML scenes model it), a mesh sample, a
    source radiance profile, a detector sensitivity map, a source path it does not move its
    source along. (A beam limit that clips the footprint is
    refused per cell by the backends that cannot model it.)"""
    for sec, what, part in unmodelled_parts(info, instrument):
        alt = ", ".join(n for n, b in BACKENDS.items() if b.xml_scenes)
        raise InputError(f"the {info.name} backend does not model {what} ({part} would be ignored, giving a "
                         f"different instrument); use a backend that does ({alt})"
                         + (", or an instrument file without [scene]" if sec == "scene" else ""),
                         path=instrument.path, field=sec)
    if instrument.source.profiled and not info.beam_profile:
        key = instrument.source.profile_keys[0]
        alt = ", ".join(n for n, b in BACKENDS.items() if b.beam_profile)
        raise InputError(f"the {info.name} backend does not model a source radiance profile ({key}); use a "
                         f"backend that does ({alt}), or a source without it", path=instrument.path, field=key)
    if instrument.detector.field_map is not None and not info.field_map:
        alt = ", ".join(n for n, b in BACKENDS.items() if b.field_map)
        raise InputError(f"the {info.name} backend does not model a detector sensitivity map; use a backend that does ({alt})",
                         path=instrument.path, field="detector.field_sensitivity")
    if instrument.sample.mesh is not None and not info.meshes:
        alt = " or ".join(n for n, b in BACKENDS.items() if b.meshes)
        raise InputError(f"the {info.name} backend integrates over a flat rectangular sample only; for a mesh "
                         f"sample use a backend that models one ({alt})", path=instrument.path, field="sample.mesh")
    path = instrument.source.path
    if path not in info.source_paths:
        alt = " or ".join(n for n, b in BACKENDS.items() if path in b.source_paths)
        raise InputError(f"the {info.name} backend does not model source.path = \"{path}\"; use the {alt} backend",
                         path=instrument.path, field="source.path")


def resolve_settings(name: str, *, accuracy: str | None = None, tolerance=None, seed=None,
                     mitsuba_variant: str | None = None, settings: Mapping[str, Any] | None = None,
                     fields: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The settings a backend is built with, resolved in one place: the accuracy preset, then the
    one relative target ``tolerance`` (a user's "relative SE or tolerance", in (0, 1), mapped to the
    backend's own setting ``rel_se`` or ``rtol``), then explicit ``settings`` (the backend's own
    keywords, checked by the backend); the seed (checked; an error for a deterministic backend),
    the Mitsuba variant (Mitsuba only). ``fields`` maps these argument names to what errors call
    them (``{"tolerance": "rel_se"}``)."""
    f = {"accuracy": "accuracy", "tolerance": "tolerance", "seed": "seed", "mitsuba_variant": "mitsuba_variant",
         "settings": "settings", **(fields or {})}
    info = backend_info(name)
    out: dict[str, Any] = {}
    if accuracy is not None:
        out.update(preset(accuracy, name, f["accuracy"]))
    if tolerance is not None:
        out.update(tolerance_setting(name, tolerance, f["tolerance"]))
    if seed is not None:
        if not info.seeded:
            raise InputError(f"the {name} backend is deterministic and takes no seed", field=f["seed"])
        out["seed"] = check_seed(seed, f["seed"])
    if mitsuba_variant is not None:
        if not info.mitsuba:
            raise InputError(f"a Mitsuba variant is for the mitsuba backend, not {name}", field=f["mitsuba_variant"])
        from roadgonio.engines.mitsuba import check_variant_name
        out["mitsuba_variant"] = check_variant_name(mitsuba_variant, f["mitsuba_variant"])
    if settings:
        if not hasattr(settings, "items"):
            raise InputError(f"expected a mapping of backend settings, got {settings!r}", field=f["settings"])
        if "seed" in settings:
            check_seed(settings["seed"], f["settings"] + ".seed")
        out.update(settings)
    return out


def make_backend(name: str, instrument, model, *, accuracy: str | None = None, tolerance=None, seed=None,
                 mitsuba_variant: str | None = None, settings: Mapping[str, Any] | None = None,
                 fields: Mapping[str, str] | None = None, **more_settings):
    """Build backend ``name`` for ``instrument`` and ``model`` (lazy import of its module), with
    its settings resolved by :func:`resolve_settings` (``more_settings`` are explicit settings too,
    e.g. ``rtol=1e-5``), the instrument checked against the backend's capabilities, in the
    instrument's ``[calibration]`` mode (:func:`roadgonio.engines.calibration.calibrated`). The
    Mitsuba backend needs a variant selected by the entry point first
    (:func:`prepare_entry_point`)."""
    info = backend_info(name, (fields or {}).get("backend", "backend"))
    kw = resolve_settings(name, accuracy=accuracy, tolerance=tolerance, seed=seed, mitsuba_variant=mitsuba_variant,
                          settings={**dict(settings or {}), **more_settings}, fields=fields)
    check_capabilities(info, instrument)
    factory = load_factory(info)
    from roadgonio.engines.calibration import calibrated
    if info.calibrates:
        return factory(instrument, model, **kw)
    return calibrated(lambda inst, m: factory(inst, m, **kw), instrument, model, deterministic=info.deterministic)


def prepare_entry_point(backend: str, mitsuba_variant: str | None = None) -> None:
    """What an entry point (the command, the Python API) does before building a backend that needs
    Mitsuba: keep the variant already selected in this process unless another one is asked for,
    else select ``mitsuba_variant`` (default ``$ROADGONIO_VARIANT`` or llvm_ad_rgb) and check
    Dr.Jit's LLVM. Nothing for the numpy backends."""
    if backend_info(backend).mitsuba:
        from roadgonio.engines.mitsuba import choose_variant
        choose_variant(mitsuba_variant)


def load_factory(info: BackendInfo):
    mod_name, func = info.factory.split(":")
    return getattr(importlib.import_module(mod_name), func)
