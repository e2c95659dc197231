"""Running a design: grid points -> geometry checks -> k_A tables on Dask -> metrics -> Dataset.

The journal ``DIR/design_points.jsonl`` holds one line per finished (design point, sample) table,
flushed and fsync'ed as it arrives, headed by a fingerprint of everything that determines the
numbers (base instrument, varied keys and values, sample models, cells, backend, accuracy,
settings, seed). Running the same command again resumes: finished tables are read back, only the
rest is computed; a journal of a different design is never mixed in (clear error; ``--fresh`` or
another ``--out``). The tolerance is not part of the fingerprint: a rerun with another tolerance
re-judges the finished tables at no cost.

Seeds: design point k (C order of the grid) gets ``point_seed(seed, k)`` (:func:`roadgonio.seeds.point_seed`,
:func:`roadgonio.engines.cluster.seeds_for`; the full range 0 ... 2^63 - 1, and two different root seeds
never give a point the same seed) for all its samples, so the numbers do not depend on the
number of workers, on the cluster or on the order in which tables finish, and ``roadgonio ka --seed
S`` on ``best.toml`` reproduces the best design's tables exactly (S is in ``design.csv``).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping


from roadgonio.errors import InputError, Interrupted, is_interrupt
from roadgonio.fileio import atomic_write_text, fingerprint, output_error, read_journal, to_json
from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel
from roadgonio.engines import cluster as _cluster
from roadgonio.design.dataset import STRAY_CELL_FIELDS, assemble
from roadgonio.design.feasibility import check_point
from roadgonio.design.grid import VarySpec, as_vary_specs, check_vary, grid_points, grid_shape, parse_tolerance

JOURNAL = "design_points.jsonl"
DEFAULT_TOLERANCE = 0.05
#: The per-cell fields kept in the journal (in the order of the task's cells).
#: The stray-light fields (k_a_direct, stray_fraction and their SEs) are journaled since trial 10
#: D10, the SEs' degrees of freedom (se_dof) since session 12; a journal written before has none and
#: resumes with them NaN in design.nc.
_CELL_FIELDS = ("k_a", "se", "error_bound", "confidence_bound", "confidence_level", "converged", "samples",
                *STRAY_CELL_FIELDS, "se_dof")


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


def _refuse_same_input_error(base: Instrument, specs, feas) -> None:
    """Every point an invalid instrument refused on the same key (e.g. ``source.height_m`` varied on
    an arc source): an input error (exit 2), not a design result, raised before anything is
    computed or written, naming the base file, the key and the --vary keys."""
    if not feas or any(f.ok or f.kind != "instrument" for f in feas):
        return
    fields = {f.field for f in feas}
    if len(fields) != 1:
        return
    reason = feas[0].reason
    if feas[0].field and reason.startswith(feas[0].field + ": "):
        reason = reason[len(feas[0].field) + 2:]
    same = len({f.reason for f in feas}) == 1
    varied = ", ".join(s.key for s in specs) or "nothing"
    raise InputError(f"no design point is a valid instrument: {'every' if same else 'the first'} one of the {len(feas)} "
                     f"is refused with '{reason}' (--vary {varied} on this base instrument); change the base file or "
                     "the --vary keys", path=base.path, field=fields.pop() or None)


#: How a refusal's kind reads in the one line of :func:`_refuse_no_possible_point`.
_KIND_WORDS = {"instrument": "an invalid instrument", "footprint": "the footprint leaves the sample",
               "horizon": "the source dips below the sample plane", "line_of_sight": "a line of sight is blocked",
               "housing": "the housing blocks a source or the detector's view", "backend": "the backend refuses it"}


def _refuse_no_possible_point(base: Instrument, specs, feas) -> None:
    """No point of the grid can measure the requested cells (every one geometrically impossible, for
    whatever reasons): an input error (exit 2), raised before anything is computed or written, with
    the reasons counted and the first point's reason quoted (user audit, session 29: such grids
    -- a housing too low, a sample too small, a source too near -- exited 0 with "no design meets the
    tolerance" and an empty pareto.png on a meaningless signal axis)."""
    if not feas or any(f.ok for f in feas):
        return
    counts: dict[str, int] = {}
    for f in feas:
        counts[f.kind] = counts.get(f.kind, 0) + 1
    why = "; ".join(f"{n} {_KIND_WORDS.get(k, k or 'impossible')}" for k, n in counts.items())
    varied = ", ".join(s.key for s in specs) or "nothing"
    first = feas[0].reason
    if base.path is not None and first.startswith(f"{base.path}, "):       # the line names the file once
        first = first[len(f"{base.path}, "):]
    raise InputError(f"no point of the --vary grid ({varied}) can measure the requested cells: {why} "
                     f"(the first: {first}); change the --vary values, the base file or --cells",
                     path=base.path, field="vary")


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
    check_vary(base, specs)
    from roadgonio.limits import check_size
    check_size(math.prod(len(s.values) for s in specs), "design_points", "vary")   # before the grid is built
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
    _refuse_same_input_error(base, specs, feas)
    _refuse_no_possible_point(base, specs, feas)

    # -- journal -----------------------------------------------------------------------------
    # what determines the numbers: not the instrument's name and description, nor the model's metadata
    base_numbers = {k: v for k, v in _cluster.absolute_instrument_dict(base).items() if k != "instrument"}
    files = base.file_digests()       # the contents of the files the base reads (only when it reads any)
    fp_payload = {"base": base_numbers, **({"files": files} if files else {}), "vary": [[s.key, list(s.values)] for s in specs],
                  "samples": [[s.name, {"variant": s.model.variant, "params": s.model.params.to_dict()},
                               [list(c) for c in s.cells]] for s in smp],
                  "backend": backend, "accuracy": accuracy, "settings": settings, "seed": int(seed),
                  "point_seeds": "roadgonio.seeds.point_seed"}     # how the points' seeds are derived
    fp = fingerprint(fp_payload)
    done: dict[tuple[int, int], dict] = {}
    fh = None
    out_dir = Path(out) if out is not None else None
    new_dir = new_journal = False
    if out_dir is not None:
        journal = out_dir / JOURNAL
        try:                  # an OSError here is the one-line error naming the journal (exit 2)
            new_dir, new_journal = not out_dir.exists(), not journal.exists() or fresh
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
    from roadgonio.progress import bar as progress_bar
    bar = progress_bar(n, f"design ({backend})", unit="point", initial=n_done0, enabled=progress and bool(tasks))

    def on_result(r: _cluster.TableResult) -> None:
        i, j = r.key
        rec = _record(r, i, j, seeds[i])
        if r.error_kind == "WorkerError":
            failed[(i, j)] = rec
        else:
            if fh is not None:
                try:
                    fh.write(to_json(rec, indent=None) + "\n")
                    fh.flush()
                    os.fsync(fh.fileno())
                except OSError as err:
                    raise output_error(journal, err) from None
            done[(i, j)] = rec
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
    except InputError:
        # the cluster could not be had (no scheduler at --scheduler, no worker joined): exit 2 leaves
        # nothing behind, not a journal of no table (user audit, session 43)
        if fh is not None and new_journal and not done:
            fh.close()
            fh = None
            journal.unlink(missing_ok=True)
            if new_dir:
                try:
                    out_dir.rmdir()
                except OSError:
                    pass
        raise
    except (KeyboardInterrupt, RuntimeError) as err:
        if not is_interrupt(err) or out_dir is None:
            raise
        if fh is not None:
            # what the journal holds, which a resume reads (user audit, session 45: an interrupt between a
            # table's entry in `done` and its line in the journal said one table more than was kept)
            fh.close()
            fh = None
            try:
                done = _read_journal(journal, fp)
            except (InputError, OSError):
                pass
        complete = sum(1 for i in range(n) if feas[i].ok and all((i, j) in done for j in range(len(smp))))
        raise Interrupted(f"interrupted: {len(done)} finished table{'' if len(done) == 1 else 's'} ({complete} of {sum(f.ok for f in feas)} "
                          f"geometrically possible design points complete) {'is' if len(done) == 1 else 'are'} kept in {out_dir / JOURNAL}; run the same "
                          "command again to resume them") from None
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
                      seeds="roadgonio.seeds.point_seed(seed, k), 63 bits, for every sample of point k",
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
