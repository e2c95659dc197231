"""Running a design: grid points -> geometry checks -> k_A tables on Dask -> metrics -> Dataset.

The journal ``DIR/design_points.jsonl`` holds one line per finished (design point, sample) table,
flushed and fsync'ed as it arrives, headed by a fingerprint of everything that determines the
numbers (base instrument, varied keys and values, sample models, cells, backend, accuracy,
settings, seed). Running the same command again resumes: finished tables are read back, only the
rest is computed; a journal of a different design is never mixed in (clear error; ``--fresh`` or
another ``--out``). The tolerance is not part of the fingerprint: a rerun with another tolerance
re-judges the finished tables at no cost.

Seeds: design point k (C order of the grid) gets ``SeedSequence(seed).spawn(n_points)[k]``
(:func:`roadgonio.engines.cluster.seeds_for`) for all its samples, so the numbers do not depend on the
number of workers, on the cluster or on the order in which tables finish, and ``roadgonio ka --seed
S`` on ``best.toml`` reproduces the best design's tables exactly (S is in ``design.csv``).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from roadgonio.errors import InputError
from roadgonio.fileio import atomic_write_text, output_error, read_journal, to_json
from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel
from roadgonio.engines import cluster as _cluster
from roadgonio.design.feasibility import check_point
from roadgonio.design.grid import VarySpec, as_vary_specs, grid_points, grid_shape, parse_tolerance
from roadgonio.design.metrics import SIGNAL_FORMULA, deviations, detector_etendue, signal_product, source_solid_angle

JOURNAL = "design_points.jsonl"
DEFAULT_TOLERANCE = 0.05
#: The per-cell fields kept in the journal (in the order of the task's cells).
_CELL_FIELDS = ("k_a", "se", "error_bound", "converged", "samples")


@dataclass(frozen=True)
class SampleSpec:
    name: str
    spec: str
    model: RoadModel
    cells: tuple[tuple[float, float], ...]


def resolve_samples(samples, cells, *, field: str = "cells") -> list[SampleSpec]:
    """The samples of a study (:class:`~roadgonio.surface.sample.ResolvedSample`, resolved by the
    caller: :func:`roadgonio.surface.sample.resolve_sample`) with the cells to compute for each
    (:func:`roadgonio.engines.cells.select_cells`; ``"table"`` = each sample's tabulated cells)."""
    from roadgonio.engines.cells import select_cells
    if not samples:
        raise InputError("give at least one sample", field="sample")
    out = [SampleSpec(name=r.name, spec=r.spec or r.name, model=r.model,
                      cells=tuple(select_cells(cells, r.table, on_grid=False, field=field))) for r in samples]
    names = [s.name for s in out]
    if len(set(names)) != len(names):
        raise InputError(f"two samples share the name {sorted(n for n in names if names.count(n) > 1)[0]!r}",
                         field="sample")
    return out


def _fingerprint(payload: Mapping[str, Any]) -> str:
    return hashlib.sha256(to_json(payload, indent=None).encode()).hexdigest()[:16]


def _read_journal(path: Path, fp: str) -> dict[tuple[int, int], dict]:
    return read_journal(path, fp, record=lambda d: ((int(d["point"]), int(d["sample"])), d),
                        different="a different design (base instrument, varied keys, samples, cells, backend, "
                                  "accuracy or seed differ)")


def _record(r: _cluster.TableResult, point: int, sample: int, seed: int) -> dict[str, Any]:
    rec = {"point": point, "sample": sample, "seed": seed, "error": r.error, "error_kind": r.error_kind,
           "seconds": r.seconds, "worker": r.worker}
    if r.ok:
        for f in _CELL_FIELDS:
            rec[f] = [getattr(c, f) for c in r.cells]
        rec["settings"] = r.settings
    return rec


def run_design(base: Instrument, vary, samples, *, tolerance: float | str = DEFAULT_TOLERANCE,
               cells="all", backend: str = "mitsuba", accuracy: str | None = None,
               settings: Mapping[str, Any] | None = None, seed: int = 0, workers: int | None = None,
               scheduler: str | None = None, client=None, out: str | Path | None = None, fresh: bool = False,
               progress: bool = True, plots: bool = True, model_variant: str | None = None):
    """Run a design study and return it as an ``xarray.Dataset`` (the API is
    :func:`roadgonio.api.design_study`, which resolves the inputs).

    ``base``: the base design; ``vary``: ``["KEY=LO:HI:N", ...]`` or ``{key: values}``
    (:mod:`roadgonio.design.grid`); ``samples``: resolved samples
    (:class:`~roadgonio.surface.sample.ResolvedSample`); ``tolerance`` on |k_A - 1| (a fraction or
    ``"5%"``); ``cells``: a cell selection (:mod:`roadgonio.engines.cells`); ``backend``,
    ``accuracy``, ``settings``: as :func:`roadgonio.engines.registry.make_backend` (settings resolved,
    without the seed); ``seed``: root of the per-point seeds. Distribution: ``client`` (an existing
    ``distributed.Client``), else ``workers``/``scheduler`` as
    :func:`roadgonio.engines.cluster.open_client` (default: a local cluster, one process per core;
    ``workers=0`` computes here). With ``out``, journals every table (resumable) and writes
    design.nc, design.csv, best.toml, pareto.png and tolerance_map.png (``plots``).
    ``model_variant``: the variant the samples were fitted with (provenance, best.toml's header).
    """
    from roadgonio.engines.registry import backend_info, preset
    t_start = time.perf_counter()
    backend_info(backend)
    if accuracy is not None:
        preset(accuracy, backend)                       # a clear error now, not on every worker
    settings = dict(settings or {})
    tol = parse_tolerance(tolerance)
    specs: list[VarySpec] = as_vary_specs(vary)
    points = grid_points(specs)
    shape = grid_shape(specs)
    smp = resolve_samples(samples, cells)
    union = sorted({c for s in smp for c in s.cells})
    seeds = _cluster.seeds_for(seed, len(points))

    # -- geometry of every point (here: cheap, and never a crash) --------------------------------
    n = len(points)
    inst_of: list[Instrument | None] = []
    feas = []
    for p in points:
        inst, f = check_point(base, p, union)
        inst_of.append(inst)
        feas.append(f)

    # -- journal -----------------------------------------------------------------------------
    # what determines the numbers: not the instrument's name and description, nor the model's metadata
    base_numbers = {k: v for k, v in _cluster.absolute_instrument_dict(base).items() if k != "instrument"}
    fp_payload = {"base": base_numbers, "vary": [[s.key, list(s.values)] for s in specs],
                  "samples": [[s.name, {"variant": s.model.variant, "params": s.model.params.to_dict()},
                               [list(c) for c in s.cells]] for s in smp],
                  "backend": backend, "accuracy": accuracy, "settings": settings, "seed": int(seed)}
    fp = _fingerprint(fp_payload)
    done: dict[tuple[int, int], dict] = {}
    fh = None
    out_dir = Path(out) if out is not None else None
    if out_dir is not None:
        journal = out_dir / JOURNAL
        try:                  # an OSError here is the one-line error naming the journal (exit 2)
            out_dir.mkdir(parents=True, exist_ok=True)
            if fresh and journal.exists():
                journal.unlink()
            done = _read_journal(journal, fp)
            atomic_write_text(journal, to_json({"fingerprint": fp, "kind": "roadgonio design journal", "points": n,
                                                "samples": [s.name for s in smp]}, indent=None) + "\n"
                              + "".join(to_json(d, indent=None) + "\n" for d in done.values()))
            fh = journal.open("a", encoding="utf-8")
        except OSError as err:
            raise output_error(journal, err) from None
    resumed = len(done)

    tasks: list[_cluster.TableTask] = []
    for i, (inst, f) in enumerate(zip(inst_of, feas)):
        if not f.ok:
            continue
        idict = _cluster.absolute_instrument_dict(inst)
        ipath = str(Path(inst.path).resolve()) if inst.path is not None else None
        for j, s in enumerate(smp):
            if (i, j) in done:
                continue
            tasks.append(_cluster.TableTask(instrument=idict, model=s.model.to_json_dict(), cells=s.cells,
                                            backend=backend, accuracy=accuracy, settings=settings, seed=seeds[i],
                                            instrument_path=ipath, key=(i, j)))
    # failed (not journaled) tables of this run
    failed: dict[tuple[int, int], dict] = {}
    remaining = {i: sum((i, j) not in done for j in range(len(smp))) for i in range(n) if feas[i].ok}
    n_done0 = sum(1 for i in range(n) if not feas[i].ok or remaining.get(i, 0) == 0)
    bar = None
    if progress and tasks:
        from tqdm import tqdm
        bar = tqdm(total=n, initial=n_done0, unit="point", desc=f"design ({backend})", file=sys.stderr,
                   dynamic_ncols=True, disable=None)

    def on_result(r: _cluster.TableResult) -> None:
        i, j = r.key
        rec = _record(r, i, j, seeds[i])
        if r.error_kind == "WorkerError":
            failed[(i, j)] = rec
        else:
            done[(i, j)] = rec
            if fh is not None:
                try:
                    fh.write(to_json(rec, indent=None) + "\n")
                    fh.flush()
                    os.fsync(fh.fileno())
                except OSError as err:
                    raise output_error(journal, err) from None
        remaining[i] -= 1
        if bar is not None and remaining[i] == 0:
            bar.update(1)

    cluster_info: dict[str, Any] = {"mode": "none (nothing to compute)"}
    t_compute = time.perf_counter()
    try:
        if tasks:
            if client is not None:
                cluster_info = _cluster.describe(client)
                _cluster.map_tables(tasks, client, on_result=on_result)
            else:
                with _cluster.open_client(workers, scheduler, backend=backend, variant=settings.get("variant")) as c:
                    if c is None:
                        _cluster.check_engine(backend, settings.get("variant"))
                    cluster_info = _cluster.describe(c)
                    t_compute = time.perf_counter()
                    _cluster.map_tables(tasks, c, on_result=on_result)
    finally:
        if fh is not None:
            fh.close()
        if bar is not None:
            bar.close()
    compute_wall = time.perf_counter() - t_compute

    ds = assemble(base=base, specs=specs, shape=shape, points=points, samples=smp, union=union, feas=feas,
                  inst_of=inst_of, done={**done, **failed}, seeds=seeds, tol=tol)
    from roadgonio.provenance import provenance
    used = next((d.get("settings") for d in done.values() if d.get("settings")), None)
    prov = provenance(instrument=base, backend=backend, settings=used or settings,
                      quantity="roadgonio design: k_A tables over a grid of instruments (roadgonio.design)",
                      fingerprint=fp, accuracy=accuracy, requested_settings=settings, seed=int(seed), cells=str(cells),
                      vary=[s.text or f"{s.key}=" + ",".join(map(repr, s.values)) for s in specs],
                      samples={s.name: {"spec": s.spec, "model": s.model.to_json_dict()} for s in smp},
                      seeds="SeedSequence(seed).spawn(points)[k], 31 bits, for every sample of point k",
                      cluster=cluster_info, tolerance=tol, model_variant=model_variant)
    computed_now = len(tasks) - len(failed)
    ds.attrs.update({
        "provenance": to_json(prov, indent=None),
        "tables_computed": int(computed_now), "tables_resumed": int(resumed), "tables_failed": len(failed),
        "compute_wall_s": float(compute_wall), "wall_s": float(time.perf_counter() - t_start),
        "created": prov["created"],
    })
    if computed_now and compute_wall > 0:
        pts_now = computed_now / max(len(smp), 1)
        ds.attrs["design_points_per_hour"] = float(3600.0 * pts_now / compute_wall)
    if out_dir is not None:
        from roadgonio.design.outputs import write_outputs
        files = write_outputs(ds, out_dir, plots=plots)
        ds.attrs["files"] = ", ".join(str(f.name) for f in files)
        ds.attrs["out"] = str(out_dir)
    return ds


def assemble(*, base: Instrument, specs: Sequence[VarySpec], shape: tuple[int, ...], points, samples, union,
             feas, inst_of, done: Mapping[tuple[int, int], dict], seeds, tol: float):
    """The Dataset of a design (layout in :mod:`roadgonio.design`)."""
    import xarray as xr
    n, ns = len(points), len(samples)
    tans = np.array(sorted({t for t, _ in union}), dtype=np.float64)
    betas = np.array(sorted({b for _, b in union}), dtype=np.float64)
    ti = {float(t): k for k, t in enumerate(tans)}
    bi = {float(b): k for k, b in enumerate(betas)}
    k_a = np.full((n, ns, len(tans), len(betas)), np.nan)
    se = np.full_like(k_a, np.nan)
    bound = np.full_like(k_a, np.nan)
    not_conv = np.zeros(n, dtype=np.int32)
    seconds = np.zeros(n)
    geometry_ok = np.array([f.ok for f in feas], dtype=bool)
    kind = np.array([f.kind for f in feas], dtype=object)
    reason = np.array([f.reason for f in feas], dtype=object)
    for i in range(n):
        if not feas[i].ok:
            continue
        for j, s in enumerate(samples):
            rec = done.get((i, j))
            if rec is None:
                kind[i], reason[i] = "failed", "not computed (interrupted); run the same command again to finish"
                continue
            seconds[i] += float(rec.get("seconds") or 0.0)
            if rec.get("error"):
                if rec.get("error_kind") == "WorkerError":
                    kind[i], reason[i] = "failed", f"{rec['error']}; run the same command again to retry"
                else:
                    geometry_ok[i] = False
                    kind[i] = "backend"
                    reason[i] = f"{samples[j].name}: {rec['error']}"
                continue
            for c, (t, b) in enumerate(s.cells):
                a, bb = ti[float(t)], bi[float(b)]
                k_a[i, j, a, bb] = _f(rec["k_a"][c])
                se[i, j, a, bb] = _f(rec["se"][c])
                bound[i, j, a, bb] = _f(rec["error_bound"][c])
                not_conv[i] += 0 if rec["converged"][c] else 1
    max_dev = np.full(n, np.nan)
    rms = np.full(n, np.nan)
    worst_t = np.full(n, np.nan)
    worst_b = np.full(n, np.nan)
    worst_se = np.full(n, np.nan)
    worst_s = np.array([""] * n, dtype=object)
    max_dev_s = np.full((n, ns), np.nan)
    computed = np.zeros(n, dtype=bool)
    for i in range(n):
        if kind[i] in ("failed",) or not geometry_ok[i]:
            continue
        u = np.where(np.isfinite(se[i]), se[i], bound[i] / math.sqrt(3.0))
        d = deviations(k_a[i], u)
        if d["cells"] == 0:
            continue
        computed[i] = True
        max_dev[i], rms[i], worst_se[i] = d["max_abs_dev"], d["rms_dev"], d["worst_se"]
        js, a, bb = np.unravel_index(d["worst"], k_a[i].shape)
        worst_t[i], worst_b[i], worst_s[i] = tans[a], betas[bb], samples[js].name
        for j in range(ns):
            v = np.abs(k_a[i, j] - 1.0)
            max_dev_s[i, j] = np.nanmax(v) if np.isfinite(v).any() else np.nan
    feasible = geometry_ok & computed & (max_dev <= tol)
    for i in range(n):
        if geometry_ok[i] and computed[i] and not feasible[i]:
            kind[i] = "tolerance"
            reason[i] = (f"max |k_A - 1| = {max_dev[i]:.4g} > tolerance {tol:g} at tan eps {worst_t[i]:g}, "
                         f"beta {worst_b[i]:g} ({worst_s[i]})")
    signal_abs = np.array([signal_product(x) if x is not None else np.nan for x in inst_of])
    sb = signal_product(base)
    signal = signal_abs / sb if sb > 0 else np.full(n, np.nan)
    omega = np.array([source_solid_angle(x.source.radius_m, x.source.distance_m) if x is not None else np.nan
                      for x in inst_of])
    etendue = np.array([detector_etendue(x) if x is not None else np.nan for x in inst_of])
    fp_len = np.array([f.footprint_length_m for f in feas])
    fp_min = np.array([f.footprint[0] if f.footprint else np.nan for f in feas])
    fp_max = np.array([f.footprint[1] if f.footprint else np.nan for f in feas])

    dims = [s.key for s in specs]
    coords: dict[str, Any] = {s.key: np.array(s.values, dtype=np.float64) for s in specs}
    coords.update({"sample": np.array([s.name for s in samples], dtype=object), "tan_eps": tans, "beta": betas})

    def grid(v):
        return np.asarray(v).reshape(shape + np.asarray(v).shape[1:])

    cell_dims = dims + ["sample", "tan_eps", "beta"]
    data = {
        "k_a": (cell_dims, grid(k_a), {"long_name": "aperture-effect factor k_A (DESIGN.md section 5)", "units": "1"}),
        "se": (cell_dims, grid(se), {"long_name": "standard error of k_A (Monte Carlo; NaN for deterministic backends)"}),
        "error_bound": (cell_dims, grid(bound), {"long_name": "deterministic error bound of k_A (quadrature; NaN for "
                                                              "Monte Carlo)"}),
        "max_abs_dev": (dims, grid(max_dev), {"long_name": "max |k_A - 1| over the cells and samples"}),
        "max_abs_dev_sample": (dims + ["sample"], grid(max_dev_s), {"long_name": "max |k_A - 1| over the cells, per sample"}),
        "rms_dev": (dims, grid(rms), {"long_name": "root mean square of k_A - 1 over the cells and samples"}),
        "worst_tan_eps": (dims, grid(worst_t), {"long_name": "tan eps of the worst cell"}),
        "worst_beta_deg": (dims, grid(worst_b), {"long_name": "beta (deg) of the worst cell"}),
        "worst_sample": (dims, grid(worst_s.astype(str)), {"long_name": "sample of the worst cell"}),
        "worst_se": (dims, grid(worst_se), {"long_name": "standard uncertainty of k_A at the worst cell (SE, or bound/sqrt 3)"}),
        "not_converged": (dims, grid(not_conv), {"long_name": "cells whose backend stopped before its target"}),
        "signal": (dims, grid(signal), {"long_name": "detected flux for a Lambertian sample relative to the base design",
                                        "formula": SIGNAL_FORMULA}),
        "source_solid_angle_sr": (dims, grid(omega), {"long_name": "projected solid angle of the source disc at the sample"}),
        "detector_etendue_m2sr": (dims, grid(etendue), {"long_name": "etendue of the luminance meter (pupil x field)"}),
        "footprint_length_m": (dims, grid(fp_len), {"long_name": "length of the detector footprint along the observation azimuth"}),
        "footprint_x_min_m": (dims, grid(fp_min), {}),
        "footprint_x_max_m": (dims, grid(fp_max), {}),
        "geometry_ok": (dims, grid(geometry_ok), {"long_name": "the instrument can measure every requested cell"}),
        "feasible": (dims, grid(feasible), {"long_name": "geometry_ok and max_abs_dev <= tolerance"}),
        "kind": (dims, grid(kind.astype(str)), {"long_name": "why not feasible: instrument, footprint, horizon, "
                                                              "line_of_sight, backend, tolerance, failed"}),
        "reason": (dims, grid(reason.astype(str)), {"long_name": "why not feasible (empty if feasible)"}),
        "seed": (dims, grid(np.array(seeds, dtype=np.int32)), {"long_name": "backend seed of the design point "
                                                                               "(roadgonio ka --seed)"}),
        "seconds": (dims, grid(seconds), {"long_name": "compute time of the point's tables (s)"}),
    }
    ds = xr.Dataset({k: xr.Variable(d, v, a) for k, (d, v, a) in data.items()}, coords=coords)
    feasible_idx = np.nonzero(feasible)[0]
    best = -1
    if feasible_idx.size:
        order = sorted(feasible_idx, key=lambda i: (-signal_abs[i], max_dev[i], i))
        best = int(order[0])
    ds.attrs.update({
        "title": f"roadgonio design study of instrument '{base.name}'",
        "tolerance": float(tol),
        "varied": json.dumps(dims),
        "samples": json.dumps([s.name for s in samples]),
        "base_instrument_json": to_json(_cluster.absolute_instrument_dict(base), indent=None),
        "base_instrument_path": str(Path(base.path).resolve()) if base.path is not None else "",
        "base_signal_product": float(sb),
        "signal_formula": SIGNAL_FORMULA,
        "points": int(n), "points_geometry_ok": int(geometry_ok.sum()), "points_feasible": int(feasible.sum()),
        "best_index": int(best),
        "best_point_json": to_json(points[best] if best >= 0 else None, indent=None),
        "log_axes": json.dumps([s.key for s in specs if s.log]),
    })
    return ds


def _f(v) -> float:
    return math.nan if v is None else float(v)


def best_instrument(ds) -> Instrument | None:
    """The best design of a design Dataset as a complete Instrument (None if no point is feasible)."""
    point = json.loads(ds.attrs["best_point_json"])
    if point is None:
        return None
    from roadgonio.design.grid import build_instrument
    return build_instrument(base_instrument(ds), point)


def base_instrument(ds) -> Instrument:
    path = ds.attrs.get("base_instrument_path") or None
    return Instrument.from_dict(json.loads(ds.attrs["base_instrument_json"]), path=path)


def point_index(ds, i: int) -> dict[str, float]:
    """The varied values of flat point ``i`` (C order)."""
    dims = json.loads(ds.attrs["varied"])
    shape = tuple(ds.sizes[d] for d in dims)
    idx = np.unravel_index(i, shape) if dims else ()
    return {d: float(ds[d].values[k]) for d, k in zip(dims, idx)}


def summary(ds) -> dict[str, Any]:
    """A short JSON-able summary of a design Dataset."""
    dims = json.loads(ds.attrs["varied"])
    best = int(ds.attrs["best_index"])
    flat = {v: ds[v].values.reshape(-1) for v in ("max_abs_dev", "rms_dev", "signal", "feasible", "kind",
                                                    "worst_tan_eps", "worst_beta_deg", "worst_sample", "worst_se",
                                                    "seed", "footprint_length_m")}
    kinds: dict[str, int] = {}
    for k in flat["kind"]:
        if k:
            kinds[str(k)] = kinds.get(str(k), 0) + 1
    s: dict[str, Any] = {"points": int(ds.attrs["points"]), "feasible": int(ds.attrs["points_feasible"]),
                         "geometry_ok": int(ds.attrs["points_geometry_ok"]), "not_feasible_by_kind": kinds,
                         "tolerance": float(ds.attrs["tolerance"]), "varied": dims,
                         "tables_computed": int(ds.attrs.get("tables_computed", 0)),
                         "tables_resumed": int(ds.attrs.get("tables_resumed", 0)),
                         "tables_failed": int(ds.attrs.get("tables_failed", 0)),
                         "wall_s": float(ds.attrs.get("wall_s", math.nan)),
                         "compute_wall_s": float(ds.attrs.get("compute_wall_s", math.nan))}
    if "design_points_per_hour" in ds.attrs:
        s["design_points_per_hour"] = float(ds.attrs["design_points_per_hour"])
    if best >= 0:
        s["best"] = {"index": best, **point_index(ds, best),
                     **{k: (v[best].item() if hasattr(v[best], "item") else v[best]) for k, v in flat.items()
                        if k not in ("feasible", "kind")}}
    else:
        s["best"] = None
    if "out" in ds.attrs:
        s["out"] = ds.attrs["out"]
    return s
