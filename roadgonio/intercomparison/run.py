"""Running a study: the participants' k_A, the corrections, the realisations, the statistics.

Three stages, each a list of independent tasks mapped on Dask with
:func:`roadgonio.design.cluster.map_calls` (a local cluster by default, ``workers`` / ``scheduler``
like ``roadgonio design``; ``workers=0`` computes here):

1. **k_A of every participant** (one task each, plus one per idealised characteristic): the
   surrogate of k_A(X) over its misalignment (:func:`roadgonio.uncertainty.run.build_surrogate`,
   validated against held-out exact tables), and the nominal k_A of its instrument with one
   aperture zero or calibrated against a Lambertian (the sensitivity ranking);
2. **corrections**: one task per (participant, realisation) that corrects its table with
   ``roadgonio correct --reference self`` (:func:`roadgonio.correction.correct_measured`; the raw
   table of that realisation is regenerated in the task from the seed), and one per participant
   that corrects with its own reference sample (the k_A it divides by does not depend on the table);
3. **realisations** (one task each, :func:`roadgonio.intercomparison.simulate.realisation`): every
   participant's reported table and stated uncertainty in both scenarios, and the metrics of every
   idealisation (common random numbers).

Journal: ``DIR/intercompare_journal.jsonl``, one JSON line per finished task (flushed and fsync'ed
as it arrives), headed by the fingerprint of everything that determines the numbers except the
number of realisations (a realisation depends only on the seed and its index, so a rerun with more
realisations reuses the finished ones). Running the same command again resumes; a journal of a
different study is never mixed in (clear error; ``fresh=True`` or another folder). Arrays travel in
the journal as base64 of little-endian float64, so a resumed run gives the same numbers bit for bit.

The statistics (:mod:`roadgonio.intercomparison.statistics`) are computed at the end over all
realisations and cells at once (:func:`assemble`).
"""
from __future__ import annotations

import base64
import dataclasses
import hashlib
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from roadgonio.errors import InputError
from roadgonio.fileio import output_error, read_journal, to_json
from roadgonio.intercomparison import simulate as sim
from roadgonio.intercomparison import statistics as st
from roadgonio.intercomparison.study import Study, load_study

JOURNAL = "intercompare_journal.jsonl"
#: Held-out exact k_A tables that validate each participant's surrogate.
SURROGATE_VALIDATION = 4
#: Reference values of the comparison (the consensus methods, then the truth only a simulation has).
REFERENCES = st.METHODS + ("truth",)
#: Fewest participants with which a random-effects consensus can leave a participant incompatible:
#: its tau^2 is chosen so that the results' scatter equals its expectation, which with 2
#: participants keeps every |E_n| <= 0.58 (both methods) and with 3 (Mandel-Paule) every |E_n| <= 1
#: for independent results (1.08 at most over 20,000 random correlated ones); below these counts
#: the share of |E_n| <= 1 against that consensus is 1 by construction and is left blank (user
#: audit, session 37: printed as 1 with an SE of 0).
RANDOM_EFFECTS_MIN_PARTICIPANTS = {"mandel_paule": 4, "dersimonian_laird": 3}
#: Step (deg, or m for the distances) of the central differences of the sensitivities d ln r / d X_k.
SENS_STEP = 1e-5
#: Version of the realisation records (what they hold); records of another version are computed again.
#: 3: the fixed-height source's item is its distance idealised (trial 11 D9), no longer an arc.
#: 4: an arc source's distance is an item too (session 13).
#: 5: a [housing]'s stray light is an item, and the misaligned instruments keep the housing's box (session 39).
REALISATION_FORMAT = 5


# ----------------------------------------------------------------------------------------------
# Arrays in JSON
# ----------------------------------------------------------------------------------------------

def pack(a) -> dict[str, Any] | None:
    """A float64 array as JSON: shape and base64 of its little-endian bytes (exact round trip)."""
    if a is None:
        return None
    a = np.ascontiguousarray(np.asarray(a, dtype="<f8"))
    return {"shape": list(a.shape), "f8": base64.b64encode(a.tobytes()).decode("ascii")}


def unpack(d) -> np.ndarray | None:
    if d is None:
        return None
    return np.frombuffer(base64.b64decode(d["f8"]), dtype="<f8").reshape(d["shape"]).copy()


# ----------------------------------------------------------------------------------------------
# What the tasks share
# ----------------------------------------------------------------------------------------------

@dataclass
class Context:
    """The resolved study for the stage-1 tasks (picklable)."""

    study: Study
    model: Any                       # RoadModel of the true surface
    cells: Any                       # CellSet
    backend: str
    settings: dict[str, Any]         # k_A tables of the surrogates and idealisations
    correction_settings: dict[str, Any]
    progress: bool = False           # cell bars inside a stage-1 task (in this process only, not on Dask)


def _cells(which: str):
    from roadgonio.uncertainty.cells import CellSet
    return CellSet.make(which)


def total_spec(study: Study, p: int):
    """The participant's own SPEC and the angle standards it shares, as one SPEC (standard
    deviations added in quadrature): what its geometry and its k_A surrogate must cover."""
    from roadgonio.uncertainty.spec import SigmaSpec
    part = study.participants[p]
    sig = np.array(part.sigma.sigma, dtype=np.float64) ** 2
    dist = list(part.sigma.distribution)
    for s in study.shared:
        if s.kind == "angle_standard" and part.name in s.participants:
            sig = sig + np.array(s.sigma.sigma) ** 2
            dist = ["normal" if s.sigma.sigma[k] > 0 else dist[k] for k in range(len(dist))]
    return SigmaSpec(tuple(float(v) for v in np.sqrt(sig)), tuple(dist), source=f"participant {part.name} (total)")


def _measurement_model(ctx: Context, p: int):
    from roadgonio.uncertainty.measurement import MeasurementModel
    part = ctx.study.participants[p]
    return MeasurementModel(ctx.model, part.instrument, ctx.cells, part.illuminance)


def _k_table(ctx: Context, instrument, desc: str = "k_A") -> tuple[np.ndarray, np.ndarray]:
    """k_A of ``instrument`` over the study's cells and its standard uncertainty from the backend
    (:meth:`~roadgonio.engines.result.CellResult.standard_uncertainty`; 0 for an ideal instrument)."""
    from roadgonio.engines import make_backend
    from roadgonio.progress import bar as progress_bar
    if instrument.is_ideal():
        return np.ones(len(ctx.cells)), np.zeros(len(ctx.cells))
    be = make_backend(ctx.backend, instrument, ctx.model, **ctx.settings)
    bar = progress_bar(len(ctx.cells), desc, unit="cell", enabled=ctx.progress, leave=False)
    try:
        res = be.compute(list(zip(ctx.cells.tan_eps.tolist(), ctx.cells.beta_deg.tolist())),
                         on_cell=None if bar is None else (lambda _r: bar.update(1)))
    finally:
        if bar is not None:
            bar.close()
    k = np.array([c.k_a for c in res])
    if not (np.all(np.isfinite(k)) and np.all(k > 0)):
        raise InputError(f"the k_A backend returned a non-positive or non-finite value for {instrument.name}",
                         field="k_A")
    return k, np.array([c.standard_uncertainty() for c in res])


def idealised_instrument(instrument, key: str):
    """The instrument with one characteristic idealised: an aperture zero, Lambert calibration, no
    ``housing`` (its stray light), or (``source_distance``) its source's nearness: the source
    :data:`~roadgonio.intercomparison.simulate.SOURCE_FAR_M` away with its aperture scaled alike
    (:func:`~roadgonio.intercomparison.simulate.far_source`; an arc's distance or a rail's height),
    so every cell sees the source at the same angular size from the same direction, but each point
    of the footprint is lit from (nearly) that one direction, not from eps +- tens of degrees as by
    a rail 1 m high (or +- 6 deg by an arc of 5 m).

    Trial 11 D9: for a rail this item was an arc of radius the rail's height, the source at its
    nearest everywhere, a far worse instrument at grazing cells than the rail that reaches 12 m (RMS
    |k_A - 1| of the corridor preset on R3 over the 396 cells: 18.5 % against 3.4 %), so its
    "idealised" error was five times the real one. The nearness is what costs the corridor its
    error: far away at the same angular size the RMS is 0.22 %, the same at 100 and 1000 m (the rest
    is the angular size and the detector's), and the source's radius alone barely matters (3.44 %
    with a point source on the rail). An arc source's distance had no item until session 13."""
    if key == "source_distance":
        return instrument.with_changes(source=sim.far_source(instrument.source))
    if key == "housing":
        # the instrument without its [housing] (nor the reflections its stray light was followed to)
        d = instrument.to_dict()
        d.pop("housing", None)
        if isinstance(d.get("scene"), dict) and not d["scene"].get("xml"):      # an XML scene keeps its reflections
            d["scene"] = {k: v for k, v in d["scene"].items() if k != "max_bounces"}
            if not d["scene"]:
                del d["scene"]
        from roadgonio.instrument.config import Instrument
        return Instrument.from_dict(d, path=instrument.path)
    if key == "calibration_mode":
        d = instrument.to_dict()
        d.pop("calibration", None)
        from roadgonio.instrument.config import Instrument
        return Instrument.from_dict(d, path=instrument.path)
    sec, attr, _ = sim.APERTURES[key]
    return instrument.with_changes(**{sec: {attr: 0.0}})


def _stage1_task(item: tuple, ctx: Context) -> dict[str, Any]:
    """k_A of participant p: ("surrogate", p) or ("ideal", p, key)."""
    kind, p = item[0], item[1]
    part = ctx.study.participants[p]
    t0 = time.perf_counter()
    if kind == "ideal":
        k, _u = _k_table(ctx, idealised_instrument(part.instrument, item[2]), f"k_A of {part.name}, {item[2]} idealised")
        return {"kind": "ideal", "key": [p, item[2]], "k": pack(k), "seconds": time.perf_counter() - t0}
    inst = part.instrument
    if inst.is_ideal():
        return {"kind": "surrogate", "key": [p], "k_nominal": pack(np.ones(len(ctx.cells))),
                "k_nominal_u": pack(np.zeros(len(ctx.cells))), "surrogate": None,
                "note": "ideal (collimated) instrument: k_A = 1", "seconds": time.perf_counter() - t0}
    spec = total_spec(ctx.study, p)
    if not any(s > 0 for s in spec.sigma):
        k, u = _k_table(ctx, inst, f"k_A of {part.name}")
        return {"kind": "surrogate", "key": [p], "k_nominal": pack(k), "k_nominal_u": pack(u), "surrogate": None,
                "note": "no misalignment: nominal k_A table", "seconds": time.perf_counter() - t0}
    from roadgonio.uncertainty.run import build_surrogate, default_backend_factory
    mm = _measurement_model(ctx, p)
    factory = default_backend_factory(ctx.backend, ctx.settings)
    rep = build_surrogate(mm, spec, factory, seed_seq=np.random.SeedSequence([ctx.study.seed, p]),
                          n_validation=SURROGATE_VALIDATION, progress=ctx.progress, backend_settings=ctx.settings)
    s = rep.surrogate
    sur = {"scale": pack(s.scale), "active": [int(a) for a in s.active], "coef": pack(s.coef),
           "ka_nominal": pack(s.ka_nominal), "fit_rms_log": pack(s.fit_rms_log), "kind": s.kind,
           "fold": None if s.fold is None else [bool(f) for f in s.fold]}
    return {"kind": "surrogate", "key": [p], "k_nominal": pack(s.ka_nominal), "k_nominal_u": pack(rep.ka_nominal_u),
            "surrogate": sur,
            "summary": rep.summary(), "seconds": time.perf_counter() - t0}


def _surrogate_from(d: Mapping[str, Any]):
    from roadgonio.uncertainty.surrogate import KaSurrogate
    return KaSurrogate(scale=unpack(d["scale"]), active=np.array(d["active"], dtype=np.int64), coef=unpack(d["coef"]),
                       ka_nominal=unpack(d["ka_nominal"]), fit_rms_log=unpack(d["fit_rms_log"]), kind=d["kind"],
                       fold=None if d["fold"] is None else np.array(d["fold"], dtype=bool))


def build_setup(ctx: Context, stage1: Mapping[tuple, dict]) -> sim.Setup:
    """The :class:`~roadgonio.intercomparison.simulate.Setup` from the stage-1 records."""
    from roadgonio.uncertainty.gum import gum_propagation
    study = ctx.study
    pms = []
    for p, part in enumerate(study.participants):
        rec = stage1[("surrogate", p)]
        mm = _measurement_model(ctx, p)

        def ln_r(X, mm=mm):
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.log(mm.r_measured(np.atleast_2d(X)))
        # d ln r / d X_k, (7, n): central differences at +-1e-5 (deg or m) about the nominal geometry
        sens = gum_propagation(ln_r, np.full(7, SENS_STEP / 1e-2))["sensitivity"]
        k_ideal = {key: unpack(r["k"]) for (kind, q, *rest), r in stage1.items()
                   if kind == "ideal" and q == p for key in rest}
        pms.append(sim.ParticipantModel(
            name=part.name, report=part.report, mm=mm, spec=part.sigma, noise_rel=part.noise_rel,
            calibration_u_rel=part.calibration_u_rel, stated=part.stated, stated_extra_rel=part.stated_extra_rel,
            surrogate=None if rec["surrogate"] is None else _surrogate_from(rec["surrogate"]),
            k_nominal=unpack(rec["k_nominal"]), k_ideal=k_ideal, sens=sens, ideal=part.instrument.is_ideal()))
    shared = [sim.SharedModel(name=s.name, kind=s.kind, members=tuple(study.index(n) for n in s.participants),
                              u_rel=s.u_rel, spec=s.sigma) for s in study.shared]
    return sim.Setup(cells=ctx.cells, truth=truth_table(ctx), participants=pms, shared=shared, seed=study.seed,
                     realisations=study.realisations, coverage_factor=study.coverage_factor)


def check_stated(setup: sim.Setup, study, cells) -> None:
    """Every participant that states its raw table's uncertainty alone
    (:func:`~roadgonio.intercomparison.study.states_raw`) states a positive one at every cell: a
    stated ``misalignment`` alone whose angles do not move some cells (beta errors at tan eps 0)
    leaves u = 0 there, which the statistics cannot weigh (audit 27: refused only at the end, by a
    line naming no file, participant or cell)."""
    from roadgonio.engines.cells import cells_text
    from roadgonio.intercomparison.study import states_raw
    for p, part in enumerate(study.participants):
        if not states_raw(part):
            continue
        u = sim.stated_rel(setup, p)
        zero = np.flatnonzero(~(u > 0.0))
        if zero.size:
            where = cells_text(zip(cells.tan_eps[zero], cells.beta_deg[zero]))
            raise InputError(f"participant {part.name!r} states a standard uncertainty of 0 at {zero.size} of "
                             f"{u.size} cells (tan eps:beta {where}): its stated components ({', '.join(part.stated)}) "
                             "do not reach them; expected a component that does ('repeatability', 'calibration' or "
                             "stated_extra_rel > 0)", path=study.path, field=f"participant[{p + 1}].stated")


def truth_table(ctx: Context) -> np.ndarray:
    """r of the surface at the nominal geometry of the comparison's cells (sr^-1): f cos^3 eps with
    the participants' observation direction (the same for all, checked)."""
    from roadgonio.uncertainty.measurement import MeasurementModel
    inst = ctx.study.participants[0].instrument
    mm = MeasurementModel(ctx.model, inst, ctx.cells, "measured")
    return mm.r_measured(np.zeros((1, 7)))[0]


# ----------------------------------------------------------------------------------------------
# Stage 2: corrections
# ----------------------------------------------------------------------------------------------

def _stage2_task(item: tuple, shared: Mapping[str, Any]) -> dict[str, Any]:
    """("self", p, m): correct realisation m's raw table of participant p through roadgonio;
    ("reference", p): the k_A of p's reference sample and the budget of that correction."""
    from roadgonio.correction.files import correct_measured
    from roadgonio.surface.rtable import RTable
    setup: sim.Setup = shared["setup"]
    study: Study = shared["study"]
    kind, p = item[0], item[1]
    pm = setup.participants[p]
    part = study.participants[p]
    t0 = time.perf_counter()
    if kind == "reference":
        raw = pm.mm.r_measured(np.zeros((1, 7)))[0] * pm.k_nominal
        name, ref = f"{pm.name}_nominal", part.reference
    else:
        m = item[2]
        raw, _ = sim.raw_table(setup, sim.draws(setup, m), p)
        name, ref = f"{pm.name}_{m + 1}", "self"
    table = RTable(setup.cells.to_grid(raw), name=name, source=f"simulated table of participant {pm.name}")
    res = correct_measured(table, part.instrument, reference=ref, u_measured=part.noise_rel,
                           backend=shared["backend"], backend_settings=shared["correction_settings"],
                           seed=correction_seed(study.seed, p, None if kind == "reference" else item[2]),
                           progress=False)
    ii, jj = setup.cells.ii, setup.cells.jj
    comp = {k: v for k, v in res.budget.components.items() if k != "measurement"}
    var = np.zeros(len(ii))
    for c in comp.values():
        var = var + np.diag(c)
    rec = {"kind": kind, "key": [p] if kind == "reference" else [p, item[2]], "k": pack(res.k_a[ii, jj]),
           "u_rel": pack(np.sqrt(np.maximum(var, 0.0))), "reference": res.reference,
           "seconds": time.perf_counter() - t0}
    if res.fit is not None:
        rec["fit"] = {"chi2": float(res.fit.chi2), "birge": float(getattr(res.fit, "birge", float("nan")))}
    return rec


# ----------------------------------------------------------------------------------------------
# Stage 3: realisations
# ----------------------------------------------------------------------------------------------

def _stage3_task(item: tuple, setup: sim.Setup) -> dict[str, Any]:
    m, corr, frozen_id = item
    corrections = {(name, m): (unpack(k), unpack(u)) for name, (k, u) in corr.items()}
    out = sim.realisation(setup, m, corrections)
    rec: dict[str, Any] = {"kind": "realisation", "key": [m], "frozen_id": frozen_id, "format": REALISATION_FORMAT}
    for scen in sim.SCENARIOS + (sim.FROZEN,):
        o = out[scen]
        rec[scen] = {"x": pack(o["x"]), "u_rel": pack(o["u_rel"]), "full": o["full"],
                     "baseline": pack(o.get("baseline")), "variants": pack(o.get("variants"))}
    return rec


def frozen_factors(setup: sim.Setup, records: Mapping[tuple, dict], n_corrected: int) -> str:
    """Set every self-correcting participant's frozen factor from its corrections: the geometric
    mean of their k and the RMS of their relative u (used only by the check of that linearisation,
    :data:`~roadgonio.intercomparison.simulate.FROZEN`); returns an identifier of the factors
    (realisations computed with other factors are computed again)."""
    h = hashlib.sha256()
    for p, pm in enumerate(setup.participants):
        ks = [unpack(records[("self", p, m)]["k"]) for m in range(n_corrected) if ("self", p, m) in records]
        us = [unpack(records[("self", p, m)]["u_rel"]) for m in range(n_corrected) if ("self", p, m) in records]
        if ks:
            pm.k_frozen = np.exp(np.mean(np.log(np.array(ks)), axis=0))
            pm.u_frozen_rel = np.sqrt(np.mean(np.array(us) ** 2, axis=0))
            h.update(pm.k_frozen.astype("<f8").tobytes() + pm.u_frozen_rel.astype("<f8").tobytes())
        else:
            pm.k_frozen = pm.u_frozen_rel = None
        h.update(f"|{len(ks)}|".encode())
    return h.hexdigest()[:16]


# ----------------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------------

def _fingerprint(study: Study, model, backend: str, settings, correction_settings) -> str:
    """Everything that determines the numbers except the number of realisations (and the labels):
    the study, the surface model's variant and parameters (not its fit's metadata), the backend and
    its settings, with the roadgonio version (:func:`roadgonio.fileio.fingerprint`)."""
    from roadgonio.fileio import fingerprint
    d = study.to_dict()
    for k in ("realisations", "corrected_realisations", "file", "name", "description"):
        d.pop(k, None)
    return fingerprint({"study": d, "model": {"variant": model.variant, "params": model.params.to_dict()},
                        "backend": backend, "settings": settings, "correction_settings": correction_settings,
                        "correction_seeds": CORRECTION_SEEDS})


#: How the simulated corrections are seeded (part of the journal's fingerprint): each its own seed,
#: from the study's seed, the participant and the realisation (audit 22: every correction ran with
#: seed 0, so its Monte Carlo k_A error was one stream shared by every realisation and the study's
#: seed never changed it).
CORRECTION_SEEDS = ("point_seed(point_seed(study.seed, participant), realisation + 1); its reference sample's "
                    "correction: point_seed(point_seed(study.seed, participant), 0)")


def correction_seed(study_seed: int, p: int, m: int | None) -> int:
    """The seed of participant ``p``'s correction of realisation ``m`` (None: of its reference
    sample's correction): :data:`CORRECTION_SEEDS`."""
    from roadgonio.seeds import point_seed
    return point_seed(point_seed(study_seed, p), 0 if m is None else m + 1)


def _key(rec: Mapping[str, Any]) -> tuple:
    return (rec["kind"], *rec["key"])


class _Journal:
    """The run's journal: finished records by key, new ones appended (flush + fsync per line)."""

    def __init__(self, out_dir: Path | None, fp: str, fresh: bool):
        self.path = None if out_dir is None else Path(out_dir) / JOURNAL
        self.done: dict[tuple, dict] = {}
        self.fh = None
        if self.path is None:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if fresh and self.path.exists():
                self.path.unlink()
        except OSError as err:
            raise output_error(self.path, err) from None
        self.done = read_journal(self.path, fp, record=lambda d: (_key(d), d),
                                 different="a different study (participants, surface, cells, seed, backend or "
                                           "roadgonio version differ)")
        try:
            # rewrite the header and the finished records, dropping a cut-short last line
            from roadgonio.fileio import atomic_write_text
            atomic_write_text(self.path, "".join(to_json(x, indent=None) + "\n"
                                                 for x in [{"fingerprint": fp}, *self.done.values()]))
            self.fh = open(self.path, "a", encoding="utf-8")
        except OSError as err:
            raise output_error(self.path, err) from None

    def add(self, rec: dict) -> None:
        self.done[_key(rec)] = rec
        if self.fh is not None:
            try:
                self.fh.write(to_json(rec, indent=None) + "\n")
                self.fh.flush()
                os.fsync(self.fh.fileno())
            except OSError as err:
                raise output_error(self.path, err) from None

    def close(self) -> None:
        if self.fh is not None:
            self.fh.close()
            self.fh = None


def _bar(progress: bool, total: int, desc: str, initial: int = 0):
    """Tasks done / total of one stage (:func:`roadgonio.progress.bar`)."""
    from roadgonio.progress import bar
    return bar(total, desc, unit="task", initial=initial, enabled=progress)


def _map(func, items, client, shared, journal: _Journal, bar, backend: str | None, variant: str | None,
         name: str) -> None:
    from roadgonio.engines import cluster as _cluster

    def done(_i, rec):
        journal.add(rec)
        if bar is not None:
            bar.update(1)
    try:
        _cluster.map_calls(func, items, client, shared=shared, backend=backend, variant=variant, name=name,
                           on_result=done)
    finally:
        if bar is not None:
            bar.close()


@dataclass
class StudyRun:
    """A finished study: its Dataset (``intercompare.nc``) and what produced it."""

    dataset: Any
    setup: sim.Setup
    study: Study
    records: dict[tuple, dict]
    seconds: dict[str, float]


def check_study(study: Study) -> None:
    """What the file checks cannot: every participant observes in the same direction (the truth
    is one table) and its misalignment keeps its geometry valid (up front)."""
    obs = {(p.instrument.observation.alpha_deg, p.instrument.observation.delta_deg) for p in study.participants}
    if len(obs) > 1:
        raise InputError("the participants observe in different directions (alpha, delta): a comparison of r needs "
                         "one observation direction", path=study.path, field="participant.instrument")


def _check_references(study: Study) -> None:
    """Each reference sample (``report = "reference"``) names something before any work starts: a
    bundled table or 'lambert', or a file that exists; errors name the study file and the
    participant's field (audit 22: they came after the journal was written, naming neither)."""
    from roadgonio.surface.rtable import BUNDLED
    for p, part in enumerate(study.participants):
        ref = part.reference
        if part.report != "reference" or ref is None:
            continue
        fld = f"participant[{p + 1}].reference"
        rp = Path(str(ref)).expanduser()
        if rp.suffix:
            if not rp.is_file():
                raise InputError(f"no such table or model file: {ref}", path=study.path, field=fld)
        elif str(ref).strip().upper() not in BUNDLED and str(ref).strip().lower() != "lambert":
            raise InputError(f"unknown sample {ref!r}; expected a bundled table ({', '.join(BUNDLED)}), 'lambert', or a "
                             "table or model file", path=study.path, field=fld)


def run_study(study: Study | str | Path, out: str | Path | None = None, *, workers: int | None = None,
              scheduler: str | None = None, client=None, fresh: bool = False, progress: bool = True,
              plots: bool = True, mitsuba_variant: str | None = None) -> StudyRun:
    """Run a study (module docstring) and return it; with ``out`` journal every task (resumable)
    and write intercompare.nc, intercompare.csv, sensitivity.csv and the pictures
    (:mod:`roadgonio.intercomparison.outputs`)."""
    from roadgonio.engines import cluster as _cluster
    from roadgonio.engines.registry import backend_info, resolve_settings, tolerance_setting
    from roadgonio.surface.sample import resolve_sample
    from roadgonio.uncertainty.measurement import MeasurementModel
    from roadgonio.uncertainty.spec import check_spec_geometry
    t_start = time.perf_counter()
    if not isinstance(study, Study):
        study = load_study(study)
    check_study(study)
    try:
        model = resolve_sample(study.surface, study.model_variant, field="study.surface").model
    except InputError as err:
        raise InputError(err.reason, path=err.path or study.path, field="study.surface") from None
    _check_references(study)
    cells = _cells(study.cells)
    for p, part in enumerate(study.participants):
        mm = MeasurementModel(model, part.instrument, cells, part.illuminance)
        try:
            check_spec_geometry(total_spec(study, p), mm, aperture=not part.instrument.is_ideal(),
                                option=f"participant[{p + 1}].sigma")
        except InputError as err:
            raise InputError(f"{part.name}: {err.reason}", path=study.path, field=err.field) from None
    seeded = backend_info(study.backend).seeded
    settings = resolve_settings(study.backend, tolerance=study.tolerance, seed=study.seed if seeded else None,
                                mitsuba_variant=mitsuba_variant,
                                fields={"tolerance": "study.rel_se", "seed": "study.seed"})
    correction_settings = ({} if study.correction_rel_se is None else
                           tolerance_setting(study.backend, study.correction_rel_se, "study.correction_rel_se"))
    ctx = Context(study=study, model=model, cells=cells, backend=study.backend, settings=dict(settings),
                  correction_settings=correction_settings)
    fp = _fingerprint(study, model, study.backend, settings, correction_settings)
    out_dir = Path(out) if out is not None else None
    if out_dir is not None:
        from roadgonio.fileio import check_writable
        check_writable(out_dir)
    journal = _Journal(out_dir, fp, fresh)
    seconds: dict[str, float] = {}
    distributed = client is not None or scheduler is not None or workers not in (None, 0)
    mvariant = mitsuba_variant
    # collimated participants need no k_A backend (k_A = 1, nothing to correct)
    engine = study.backend if any(not p.instrument.is_ideal() or p.report == "reference"
                                  for p in study.participants) else None
    try:
        if distributed and client is None:
            with _cluster.open_client(workers, scheduler, backend=engine, variant=mvariant) as c:
                setup = _stages(ctx, journal, c, progress, seconds, mvariant)
                cluster = _cluster.describe(c)
        else:
            if client is None and engine is not None:
                _cluster.check_engine(engine, mvariant)
            setup = _stages(ctx, journal, client, progress, seconds, mvariant)
            cluster = _cluster.describe(client)
    finally:
        journal.close()
    t = time.perf_counter()
    ds = assemble(study, setup, journal.done, model=model, cluster=cluster, settings=settings,
                  correction_settings=correction_settings, fingerprint=fp)
    seconds["statistics"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t_start
    ds.attrs["seconds"] = to_json(seconds, indent=None)
    run = StudyRun(dataset=ds, setup=setup, study=study, records=journal.done, seconds=seconds)
    if out_dir is not None:
        from roadgonio.intercomparison.outputs import write_outputs
        files = write_outputs(run, out_dir, plots=plots)
        ds.attrs["files"] = ", ".join(f.name for f in files)
        ds.attrs["out"] = str(out_dir)
    return run


def _stages(ctx: Context, journal: _Journal, client, progress: bool, seconds: dict, mvariant) -> sim.Setup:
    study = ctx.study
    # 1. k_A of every participant
    t = time.perf_counter()
    items1: list[tuple] = []
    for p, part in enumerate(study.participants):
        items1.append(("surrogate", p))
        if part.instrument.is_ideal():
            continue
        items1 += [("ideal", p, key) for key, _ in sim.k_characteristics(part.instrument)]
    todo = [it for it in items1 if it not in journal.done]
    ctx1 = dataclasses.replace(ctx, progress=bool(progress) and client is None)     # cell bars: in this process
    _map(_stage1_task, todo, client, ctx1, journal, _bar(progress, len(items1), "k_A of the participants",
                                                          len(items1) - len(todo)),
         study.backend, mvariant, "intercompare-ka")
    setup = build_setup(ctx, {it: journal.done[it] for it in items1})
    check_stated(setup, study, ctx.cells)
    seconds["k_a"] = time.perf_counter() - t
    # 2. corrections
    t = time.perf_counter()
    items2: list[tuple] = []
    for p, part in enumerate(study.participants):
        pm = setup.participants[p]
        if part.report == "reference":
            items2.append(("reference", p))
        needs_self = not (pm.ideal and part.instrument.calibration.mode == "lambert")
        if needs_self:
            items2 += [("self", p, m) for m in range(study.n_corrected)]
    todo = [it for it in items2 if it not in journal.done]
    shared2 = {"setup": setup, "study": study, "backend": study.backend,
               "correction_settings": ctx.correction_settings}
    _map(_stage2_task, todo, client, shared2, journal, _bar(progress, len(items2), "corrections",
                                                             len(items2) - len(todo)),
         study.backend, mvariant, "intercompare-correct")
    for p, part in enumerate(study.participants):
        if part.report == "reference":
            rec = journal.done[("reference", p)]
            setup.participants[p].k_reference = unpack(rec["k"])
            setup.participants[p].u_reference_rel = unpack(rec["u_rel"])
    frozen_id = frozen_factors(setup, journal.done, study.n_corrected)
    seconds["corrections"] = time.perf_counter() - t
    # 3. realisations (one computed with other frozen factors is computed again)
    t = time.perf_counter()
    items3 = []
    for m in range(study.realisations):
        rec = journal.done.get(("realisation", m))
        if rec is not None and rec.get("frozen_id") == frozen_id and rec.get("format") == REALISATION_FORMAT:
            continue
        corr = {}
        for p, pm in enumerate(setup.participants):
            rec = journal.done.get(("self", p, m))
            if rec is not None:
                corr[pm.name] = (rec["k"], rec["u_rel"])
        items3.append((m, corr, frozen_id))
    _map(_stage3_task, items3, client, setup, journal, _bar(progress, study.realisations, "realisations",
                                                             study.realisations - len(items3)),
         None, None, "intercompare-realisation")
    seconds["realisations"] = time.perf_counter() - t
    return setup


# ----------------------------------------------------------------------------------------------
# Statistics over all realisations and cells
# ----------------------------------------------------------------------------------------------

def comparison(x: np.ndarray, urel: np.ndarray, g_rel: np.ndarray, truth: np.ndarray, k: float) -> dict[str, Any]:
    """All statistics of the comparison for x, urel of shape (R, P, n) (NaN realisations allowed:
    they stay NaN). Returns arrays with the participant axis second: reference values (R, n), tau^2,
    Birge ratio, consistency, and per reference d, U(d), E_n (R, P, n)."""
    R, P, n = x.shape
    ok = np.all(np.isfinite(x), axis=(1, 2))
    out: dict[str, Any] = {"ok": ok}
    nanRn = np.full((R, n), np.nan)
    nanRPn = np.full((R, P, n), np.nan)
    res = {m: {"value": nanRn.copy(), "u": nanRn.copy(), "tau2": nanRn.copy()} for m in st.METHODS}
    eqs = {r: {"d": nanRPn.copy(), "U": nanRPn.copy(), "E_n": nanRPn.copy()} for r in REFERENCES}
    birge, cons, chi2 = nanRn.copy(), np.zeros((R, n), dtype=bool), nanRn.copy()
    if np.any(ok):
        xs = np.moveaxis(x[ok], 1, -1)                              # (R', n, P)
        us = np.moveaxis(urel[ok] * x[ok], 1, -1)
        gs = np.moveaxis(g_rel[:, None] * x[ok][None], 2, -1)       # (S, R', n, P)
        V = st.covariance(us, gs if len(g_rel) else None)
        sp = st.Spectral(xs, V)
        chi2[ok] = st.chi2_observed(sp)
        birge[ok] = st.birge_ratio(sp)
        cons[ok] = st.consistent(sp)
        for m in st.METHODS:
            c = st.consensus(sp, m)
            res[m]["value"][ok], res[m]["u"][ok], res[m]["tau2"][ok] = c.value, c.u, c.tau2
            eq = st.equivalence_to(xs, V, c, k)
            for f, a in (("d", eq.d), ("U", eq.U), ("E_n", eq.e_n)):
                eqs[m][f][ok] = np.moveaxis(a, -1, 1)
        eq = st.degrees_of_equivalence(xs, V, np.broadcast_to(truth, xs.shape[:-1]), None, 0.0, 0.0, k)
        for f, a in (("d", eq.d), ("U", eq.U), ("E_n", eq.e_n)):
            eqs["truth"][f][ok] = np.moveaxis(a, -1, 1)
    out.update(consensus=res, equivalence=eqs, birge=birge, consistent=cons, chi2=chi2)
    return out


def assemble(study: Study, setup: sim.Setup, records: Mapping[tuple, dict], *, model, cluster, settings,
             correction_settings, fingerprint: str):
    """The Dataset of intercompare.nc (layout in :mod:`roadgonio.intercomparison.outputs`)."""
    import xarray as xr
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    from roadgonio.provenance import provenance
    R, P, n = study.realisations, setup.P, len(setup.truth)
    cells = setup.cells
    names = [pm.name for pm in setup.participants]
    g_rel = sim.shared_components(setup)
    k = study.coverage_factor
    grid = (len(TAN_EPS_GRID), len(BETA_GRID_DEG))

    def to_grid(a: np.ndarray) -> np.ndarray:
        """(..., n) -> (..., 29, 20), NaN outside the comparison's cells."""
        g = np.full(a.shape[:-1] + grid, np.nan, dtype=np.float64)
        g[..., cells.ii, cells.jj] = a
        return g

    data: dict[str, Any] = {}
    stats = {}
    xs, us, full = {}, {}, {}
    for scen in sim.SCENARIOS + (sim.FROZEN,):
        x = np.full((R, P, n), np.nan)
        u = np.full((R, P, n), np.nan)
        f = np.zeros((R, P), dtype=bool)
        for m in range(R):
            rec = records[("realisation", m)][scen]
            x[m], u[m], f[m] = unpack(rec["x"]), unpack(rec["u_rel"]), rec["full"]
        xs[scen], us[scen], full[scen] = x, u, f
        stats[scen] = comparison(x, u, g_rel, setup.truth, k)
    S = sim.SCENARIOS
    dims5 = ("scenario", "participant", "realisation", "tan_eps", "beta")
    data["truth"] = (("tan_eps", "beta"), to_grid(setup.truth),
                     {"long_name": "reduced luminance coefficient r of the surface at the nominal geometry (the truth)",
                      "units": "sr-1"})
    data["r_reported"] = (dims5, to_grid(np.stack([np.moveaxis(xs[s], 0, 1) for s in S])),
                          {"long_name": "r reported by the participant", "units": "sr-1"})
    data["u_stated"] = (dims5, to_grid(np.stack([np.moveaxis(us[s] * xs[s], 0, 1) for s in S])),
                        {"long_name": "standard uncertainty stated by the participant", "units": "sr-1"})
    data["k_a_nominal"] = (("participant", "tan_eps", "beta"),
                           to_grid(np.array([pm.k_nominal for pm in setup.participants])),
                           {"long_name": "aperture-effect factor k_A of the participant's instrument at the nominal "
                                         "geometry, under its calibration mode (docs/conventions.md section 5)",
                            "units": "1"})
    # its standard uncertainty from the backend (user audit, session 41: the value came without one); NaN
    # where the stage-1 record predates it (a journal written before session 42)
    k_u = [unpack(records[("surrogate", p)].get("k_nominal_u")) for p in range(P)]
    data["k_a_nominal_u"] = (("participant", "tan_eps", "beta"),
                             to_grid(np.array([np.full(n, np.nan) if u is None else u for u in k_u])),
                             {"long_name": "standard uncertainty of k_a_nominal from the k_A backend (its standard "
                                           "error, or a deterministic error bound taken as a rectangular "
                                           "distribution, bound / sqrt 3); 0 for an ideal instrument",
                              "units": "1"})
    meth = list(st.METHODS)
    data["reference_value"] = (("scenario", "consensus", "realisation", "tan_eps", "beta"),
                               to_grid(np.stack([np.stack([stats[s]["consensus"][m]["value"] for m in meth])
                                                 for s in S])),
                               {"long_name": "reference value of the comparison (consensus of the participants)",
                                "units": "sr-1"})
    data["u_reference_value"] = (("scenario", "consensus", "realisation", "tan_eps", "beta"),
                                 to_grid(np.stack([np.stack([stats[s]["consensus"][m]["u"] for m in meth])
                                                   for s in S])),
                                 {"long_name": "standard uncertainty of the reference value", "units": "sr-1"})
    data["tau2"] = (("scenario", "consensus", "realisation", "tan_eps", "beta"),
                    to_grid(np.stack([np.stack([stats[s]["consensus"][m]["tau2"] for m in meth]) for s in S])),
                    {"long_name": "between-laboratory variance tau^2 of the consensus (0 for the weighted mean)",
                     "units": "sr-2"})
    data["birge_ratio"] = (("scenario", "realisation", "tan_eps", "beta"),
                           to_grid(np.stack([stats[s]["birge"] for s in S])),
                           {"long_name": "Birge ratio sqrt(chi2_obs / (P - 1)) of the weighted mean", "units": "1"})
    data["consistent"] = (("scenario", "realisation", "tan_eps", "beta"),
                          to_grid(np.stack([np.where(stats[s]["ok"][:, None], stats[s]["consistent"], np.nan)
                                            for s in S])),
                          {"long_name": "1 where Cox's chi-squared consistency check passes at the 5 % level",
                           "units": "1"})
    # NaN where the participant reported no table in that realisation (a scenario that corrects only the
    # first ones): 0 said "divided by the frozen factor" of a table that is not there (user audit, session 41)
    data["full_correction"] = (("scenario", "participant", "realisation"),
                               np.stack([np.where(np.isnan(xs[s]).all(axis=2), np.nan, full[s]).T
                                         for s in S]).astype(np.float32),
                               {"long_name": "1: the reported table is the participant's own (raw, or corrected by a "
                                             "full roadgonio correction of this realisation); 0: divided by the "
                                             "participant's frozen correction factor; NaN: no table reported",
                                "units": "1"})
    dims6 = ("scenario", "reference", "participant", "realisation", "tan_eps", "beta")
    for f, long, units in (("d", "degree of equivalence d_i = x_i - x_ref", "sr-1"),
                           ("U_d", "expanded uncertainty U(d_i) = k u(d_i)", "sr-1"),
                           ("E_n", "E_n = d_i / U(d_i)", "1")):
        key = "U" if f == "U_d" else f
        a = np.stack([np.stack([np.moveaxis(stats[s]["equivalence"][r][key], 0, 1) for r in REFERENCES]) for s in S])
        data[f] = (dims6, to_grid(a).astype(np.float32),
                   {"long_name": long, "units": units, "note": "computed in float64, stored as float32"})
    coords = {"scenario": list(S), "participant": names, "realisation": np.arange(R), "tan_eps": TAN_EPS_GRID,
              "beta": BETA_GRID_DEG, "consensus": meth, "reference": list(REFERENCES)}
    ds = xr.Dataset({k_: xr.Variable(d, v, a) for k_, (d, v, a) in data.items()}, coords=coords)
    ds["tan_eps"].attrs.update(long_name="tangent of the illumination polar angle eps", units="1")
    ds["beta"].attrs.update(long_name="angle between the planes of illumination and observation", units="degree")
    sens = sensitivity(study, setup, records)
    summ = summary_rows(study, setup, xs, us, stats, full)
    valid = validation_rows(setup, xs, stats, full)
    corr = correlation_rows(setup, xs, us, g_rel)
    prov = provenance(model=model, backend=study.backend, settings=settings,
                      quantity="roadgonio intercompare: a simulated key comparison of r-tables (issue 20)",
                      study=study.to_dict(), correction_settings=correction_settings, fingerprint=fingerprint,
                      cluster=cluster, seeds="realisation m: SeedSequence(seed).spawn(realisations)[m], then one "
                                             "child per participant and per shared effect",
                      surrogates={names[p]: records[("surrogate", p)].get("summary") or records[("surrogate", p)].get("note")
                                  for p in range(P)})
    ds.attrs.update({"title": f"roadgonio intercomparison '{study.name}'", "Conventions": "CF-1.8",
                     "institution": "simulation (roadgonio)", "source": "roadgonio intercompare",
                     "coverage_factor": float(k), "participants": to_json(names, indent=None),
                     "scenarios": "declared: as the study declares; all_corrected: every participant corrects with "
                                  "roadgonio correct --reference self",
                     "provenance": to_json(prov, indent=None), "created": prov["created"]})
    return ds.assign_attrs(notes_json=to_json(study_notes(study, setup), indent=None),
                           summary_json=to_json(summ, indent=None), sensitivity_json=to_json(sens, indent=None),
                           validation_json=to_json(valid, indent=None), correlation_json=to_json(corr, indent=None))


def correlation_rows(setup: sim.Setup, xs, us, g_rel: np.ndarray) -> list[dict[str, Any]]:
    """Per scenario and pair of participants: the correlation of their errors ``x / r_true - 1``
    over the realisations (what the simulation produces), and the correlation their stated
    covariance declares (``sum_s g_si g_sj / (u_i u_j)``, from the effects they share); each as the
    median, 5 % and 95 % over the cells."""
    out = []
    names = [pm.name for pm in setup.participants]
    for scen in sim.SCENARIOS:
        x, u = xs[scen], us[scen]
        ok = np.all(np.isfinite(x), axis=(1, 2))
        R = int(ok.sum())
        if R < 3:
            continue
        e = x[ok] / setup.truth - 1.0                              # (R, P, n)
        e = e - e.mean(axis=0)
        sd = np.sqrt(np.mean(e * e, axis=0))                       # (P, n)
        declared_u = np.median(u[ok], axis=0)                      # (P, n) relative
        for i in range(len(names)):
            for j in range(i + 1, len(names)):
                with np.errstate(divide="ignore", invalid="ignore"):
                    emp = np.mean(e[:, i] * e[:, j], axis=0) / (sd[i] * sd[j])
                    dec = np.sum(g_rel[:, i] * g_rel[:, j], axis=0) / (declared_u[i] * declared_u[j])
                emp, dec = emp[np.isfinite(emp)], dec[np.isfinite(dec)]
                row = {"scenario": scen, "participant_a": names[i], "participant_b": names[j], "realisations": R}
                for key, v in (("simulated", emp), ("stated", dec)):
                    if v.size:
                        lo, med, hi = np.percentile(v, [5, 50, 95])
                        row.update({f"{key}_median": float(med), f"{key}_p05": float(lo), f"{key}_p95": float(hi)})
                out.append(row)
    return out


def _figures(setup: sim.Setup, x: np.ndarray, st_: Mapping[str, Any], rows: np.ndarray) -> dict[str, np.ndarray]:
    """Per-realisation figures of merit over the realisations ``rows``: per participant (R', P) the
    share of |E_n| <= 1 against the weighted mean, the RMS of d / r_true and of x / r_true - 1; for
    the comparison (R',) the share of consistent cells, of cells where all are compatible, the
    median Birge ratio and the RMS error of each consensus against the truth."""
    t = setup.truth
    en = st_["equivalence"]["weighted_mean"]["E_n"][rows]
    d = st_["equivalence"]["weighted_mean"]["d"][rows]
    out = {"share_En_le_1_weighted_mean": np.mean(np.abs(en) <= 1.0, axis=2),
           "rms_d_weighted_mean_pct": 100 * np.sqrt(np.mean((d / t) ** 2, axis=2)),
           "rms_error_vs_truth_pct": 100 * np.sqrt(np.mean((x[rows] / t - 1.0) ** 2, axis=2)),
           "share_consistent_cells": np.mean(st_["consistent"][rows], axis=1),
           "share_all_compatible_weighted_mean": np.mean(np.all(np.abs(en) <= 1.0, axis=1), axis=1),
           "birge_ratio_median": np.median(st_["birge"][rows], axis=1)}
    for m in st.METHODS:
        out[f"rms_error_{m}_vs_truth_pct"] = 100 * np.sqrt(np.mean((st_["consensus"][m]["value"][rows] / t - 1.0) ** 2,
                                                                   axis=1))
    return out


def validation_rows(setup: sim.Setup, xs, stats, full) -> list[dict[str, Any]]:
    """The frozen correction factor against the full corrections, on the realisations where every
    participant that corrects has a full correction: each figure of merit (:func:`_figures`) with
    the full corrections and with the frozen factors, their mean paired difference and its standard
    error over those realisations. Empty when no realisation has both, and when no participant's
    correction changes its table (every instrument collimated under a Lambert calibration): the
    frozen factor is then 1 as the full one, and rows of differences of 0 would look like a check
    that passed (user audit)."""
    from roadgonio.intercomparison.outputs import VALIDATION_COLUMNS
    if all(sim.reports_as(setup, p, "all_corrected") == "raw" for p in range(len(setup.participants))):
        return []
    rows_ok = np.all(full["all_corrected"], axis=1) & stats["all_corrected"]["ok"] & stats[sim.FROZEN]["ok"]
    R = int(rows_ok.sum())
    if R < 2:
        return []
    a = _figures(setup, xs["all_corrected"], stats["all_corrected"], rows_ok)
    b = _figures(setup, xs[sim.FROZEN], stats[sim.FROZEN], rows_ok)
    out = []
    names = [pm.name for pm in setup.participants]
    for key in a:
        va, vb = a[key], b[key]
        cols = [(names[p], va[:, p], vb[:, p]) for p in range(va.shape[1])] if va.ndim == 2 else [("ALL", va, vb)]
        for who, x1, x2 in cols:
            diff = x2 - x1
            row = {"figure": f"{key}_per_realisation", "participant": who, "realisations": R,
                   "full_mean": float(x1.mean()), "frozen_mean": float(x2.mean()),
                   "difference_mean": float(diff.mean()), "difference_se": float(diff.std(ddof=1) / math.sqrt(R)),
                   "full_mean_se": float(x1.std(ddof=1) / math.sqrt(R))}
            out.append({k: row[k] for k in VALIDATION_COLUMNS})
    return out


def study_notes(study: Study, setup: sim.Setup) -> list[str]:
    """What a reader of the results must know that no figure says: the consensus shares left blank
    (:data:`RANDOM_EFFECTS_MIN_PARTICIPANTS`), and a participant's reference sample whose model has
    a spike at beta 0 no aperture resolves (:func:`roadgonio.surface.sample.unresolved_spike`: its
    k_A and so that participant's corrections there are artefacts of the fit; user audit, session 37:
    the warning reached the terminal only, and the summary showed 92 % compatible with the truth
    for a participant 97-138 % off along beta 0)."""
    import warnings

    from roadgonio.errors import ModelWarning
    from roadgonio.surface.sample import resolve_sample
    notes = []
    blank = [m for m, n in RANDOM_EFFECTS_MIN_PARTICIPANTS.items() if setup.P < n]
    if blank:
        names = {"mandel_paule": "Mandel-Paule", "dersimonian_laird": "DerSimonian-Laird"}
        notes.append(f"with {setup.P} participants a {' or '.join(names[m] for m in blank)} consensus makes every "
                     "participant compatible by construction (its tau^2 absorbs the scatter): the shares of |E_n| <= 1 "
                     f"against it are left blank (share_En_le_1_{blank[0]} ...); the weighted mean's and the truth's "
                     "are kept")
    for part in study.participants:
        if part.report != "reference" or part.reference is None:
            continue
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ModelWarning)
            resolve_sample(part.reference)                   # the fit is cached by the correction that used it
        for w in caught:
            if issubclass(w.category, ModelWarning):
                notes.append(f"participant {part.name} (report = reference, {part.reference}): {w.message}")
    return notes


def summary_rows(study: Study, setup: sim.Setup, xs, us, stats, full) -> list[dict[str, Any]]:
    """The CSV summary: one row per (scenario, participant) and one for the comparison."""
    rows = []
    t = setup.truth
    for scen in sim.SCENARIOS:
        st_ = stats[scen]
        ok = st_["ok"]
        R = int(ok.sum())
        for p, pm in enumerate(setup.participants):
            row: dict[str, Any] = {"scenario": scen, "participant": pm.name,
                                   "reports": sim.reports_as(setup, p, scen), "realisations": R}
            row["full_corrections"] = int(np.sum(full[scen][ok, p])) if row["reports"] == "self" else None
            if R == 0:
                rows.append(row)
                continue
            x = xs[scen][ok, p]
            err = x / t - 1.0
            row["repeatability_pct"] = 100 * pm.noise_rel
            row["stated_u_median_pct"] = 100 * float(np.median(us[scen][ok, p]))
            row["rms_error_vs_truth_pct"] = 100 * float(np.sqrt(np.mean(err ** 2)))
            row["max_abs_mean_error_vs_truth_pct"] = 100 * float(np.max(np.abs(np.mean(err, axis=0))))
            for ref in REFERENCES:
                if setup.P < RANDOM_EFFECTS_MIN_PARTICIPANTS.get(ref, 0):
                    row[f"share_En_le_1_{ref}"] = row[f"share_En_le_1_{ref}_se"] = float("nan")
                    continue
                e = st_["equivalence"][ref]["E_n"][ok, p]
                share = np.mean(np.abs(e) <= 1.0, axis=1)              # per realisation
                row[f"share_En_le_1_{ref}"] = float(share.mean())
                row[f"share_En_le_1_{ref}_se"] = float(share.std(ddof=1) / math.sqrt(R)) if R > 1 else float("nan")
            d = st_["equivalence"]["weighted_mean"]["d"][ok, p]
            row["rms_d_weighted_mean_pct"] = 100 * float(np.sqrt(np.mean((d / t) ** 2)))
            rows.append(row)
        row = {"scenario": scen, "participant": "ALL", "reports": "", "realisations": R}
        if R:
            row["birge_ratio_median"] = float(np.median(st_["birge"][ok]))
            cons = np.mean(st_["consistent"][ok], axis=1)
            row["share_consistent_cells"] = float(cons.mean())
            row["share_consistent_cells_se"] = float(cons.std(ddof=1) / math.sqrt(R)) if R > 1 else float("nan")
            allc = np.all(np.abs(st_["equivalence"]["weighted_mean"]["E_n"][ok]) <= 1.0, axis=1)
            allc_r = np.mean(allc, axis=1)                                    # per realisation
            row["share_all_compatible_weighted_mean"] = float(allc_r.mean())
            row["share_all_compatible_weighted_mean_se"] = (float(allc_r.std(ddof=1) / math.sqrt(R)) if R > 1
                                                            else float("nan"))
            for m in st.METHODS:
                v = st_["consensus"][m]["value"][ok]
                row[f"rms_error_{m}_vs_truth_pct"] = 100 * float(np.sqrt(np.mean((v / t - 1.0) ** 2)))
            for m in ("mandel_paule", "dersimonian_laird"):
                tau = np.sqrt(st_["consensus"][m]["tau2"][ok]) / t
                row[f"tau_rel_median_{m}_pct"] = 100 * float(np.median(tau))
        rows.append(row)
    return rows


def sensitivity(study: Study, setup: sim.Setup, records: Mapping[tuple, dict]) -> list[dict[str, Any]]:
    """The ranking: per scenario and participant, each characteristic idealised in turn, ranked by
    the drop of the RMS of the participant's own error ``x_i / r_true - 1`` (its degree of
    equivalence against the truth, which only a simulation has) over cells and realisations, with
    its standard error over realisations; beside it the share of cells where it is compatible with
    the truth (|x_i - r_true| <= k u_i) and, against the weighted mean, the RMS of d_i / r_true and
    the share of |E_n| <= 1, before and after."""
    M = {m: i for i, m in enumerate(sim.METRICS)}
    out = []
    for scen in sim.SCENARIOS:
        variants = setup.variants(scen)
        base, var = [], []
        for m in range(study.realisations):
            rec = records[("realisation", m)][scen]
            if rec.get("variants") is None:
                continue
            base.append(unpack(rec["baseline"]))          # (P, metrics)
            var.append(unpack(rec["variants"]))           # (V, metrics)
        if not base:
            continue
        B, Vv = np.array(base), np.array(var).reshape(len(base), len(variants), len(sim.METRICS))
        R = len(base)
        for v, (p, key, label) in enumerate(variants):
            b, x = B[:, p], Vv[:, v]
            n_b, n_x = b[:, M["n_cells"]], x[:, M["n_cells"]]

            def rms(a, n, key_):
                return 100 * float(np.sqrt(a[:, M[key_]].sum() / n.sum()))
            delta = np.sqrt(b[:, M["sum_err_rel2"]] / n_b) - np.sqrt(x[:, M["sum_err_rel2"]] / n_x)
            out.append({"scenario": scen, "participant": setup.participants[p].name, "characteristic": key,
                        "label": label,
                        "rms_error_vs_truth_pct": rms(b, n_b, "sum_err_rel2"),
                        "rms_error_vs_truth_idealised_pct": rms(x, n_x, "sum_err_rel2"),
                        "drop_pct": 100 * float(delta.mean()),
                        "drop_se_pct": 100 * float(delta.std(ddof=1) / math.sqrt(R)) if R > 1 else float("nan"),
                        "share_compatible_truth": float(b[:, M["n_compatible_truth"]].sum() / n_b.sum()),
                        "share_compatible_truth_idealised": float(x[:, M["n_compatible_truth"]].sum() / n_x.sum()),
                        "rms_d_weighted_mean_pct": rms(b, n_b, "sum_d_rel2"),
                        "rms_d_weighted_mean_idealised_pct": rms(x, n_x, "sum_d_rel2"),
                        "share_compatible_weighted_mean": float(b[:, M["n_compatible"]].sum() / n_b.sum()),
                        "share_compatible_weighted_mean_idealised": float(x[:, M["n_compatible"]].sum() / n_x.sum()),
                        "realisations": R})
    # ranked: largest drop first within each (scenario, participant)
    names = [pm.name for pm in setup.participants]
    out.sort(key=lambda r: (sim.SCENARIOS.index(r["scenario"]), names.index(r["participant"]), -r["drop_pct"]))
    for i, r in enumerate(out):
        prev = out[i - 1] if i else None
        r["rank"] = 1 if prev is None or (prev["scenario"], prev["participant"]) != (r["scenario"], r["participant"]) \
            else prev["rank"] + 1
    return out
