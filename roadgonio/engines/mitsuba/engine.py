"""The batched k_A engine: all cells of a table in a few Mitsuba launches, passes sized from the
target (docs/architecture.md, "How the k_A engine works"). The Mitsuba side is the ``kabatch`` integrator plugin
(:mod:`roadgonio.engines.mitsuba.plugins.ka_batch`); the pass plan and the float64 statistics are
:mod:`roadgonio.engines.mitsuba.passes`; the sample points :mod:`roadgonio.engines.mitsuba.lattice`.

One pass: the active cells are grouped by the lattice size the planner chose for them; per group
the detector rays of its replicates are traced once (chunks of at most :data:`MAX_RAYS` rays) and
every cell's source is sampled at the same hits in one shading launch (chunks of at most
:data:`MAX_LANES` lanes); the per-block road and Lambert sums come back to the host and are
accumulated in float64. Dr.Jit's LLVM backend splits every large launch over its thread pool
(``dr.thread_count()``, all cores by default); nothing here is specific to the CPU, so a CUDA
variant runs the same code (not tested here: this machine has no GPU).

Geometry checks (errors, not wrong numbers): the preamble of every backend
(:func:`roadgonio.engines.cellcheck.check_cells`: the source above the horizon, its disc out of the
detector's view, the model positive at the nominal geometry; a beam limit that clips the footprint
is modelled: the integrator applies the cone to every source sample and light path); every traced
detector ray must hit the sample (counted in every launch).
"""
from __future__ import annotations

import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from roadgonio.errors import GeometryError
from roadgonio.interrupts import critical, deferred
from roadgonio.engines.mitsuba import lattice as lat
from roadgonio.engines.mitsuba.passes import CellStats, Plan, Planner, add_strata, covariance
from roadgonio.engines.mitsuba.scene import RoadScene, source_radiance
from roadgonio.instrument.config import Instrument
from roadgonio.instrument.optics import source_frames
from roadgonio.engines.cellcheck import check_cells, unsampled_beam
from roadgonio.engines.registry import backend_info

#: Largest number of detector rays traced (and stored: 13 floats each) per launch.
MAX_RAYS = 1 << 21
#: Largest number of (ray, cell) lanes per shading launch (their road and Lambert values are stored,
#: 8 bytes a lane, for the evaluated block sums).
MAX_LANES = 1 << 23
#: With stray light, the largest number of paths traced per launch (each further vertex stores 19
#: floats a path: 2^19 paths x 2 vertices take 80 MB).
MAX_PATHS = 1 << 19


def cell_sources(instrument: Instrument, cells: Sequence[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """(axes (cells, 3), D_S (cells,)), float64: what the ``kabatch`` plugin takes of every cell's
    source disc (:meth:`KaBatch.set_cells`; it rebuilds the disc's frame from the axis). The
    placement itself is :func:`roadgonio.instrument.optics.source_frames`, the numpy backends' too."""
    c = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    place = source_frames(instrument, c[:, 0], c[:, 1])
    return place.axis, place.distance_m


@dataclass
class EngineRun:
    """Result of :meth:`BatchEngine.run`: per cell (in the order asked) its statistics, whether it
    reached the target, and the plan that was followed."""

    stats: list[CellStats]
    converged: list[bool]
    plan: Plan
    seconds: float
    passes: int
    launches: int
    info: dict[str, Any] = field(default_factory=dict)

    def ratios(self) -> list[tuple[float, float, float]]:
        return [s.ratio_se() for s in self.stats]

    def covariance(self) -> np.ndarray:
        return covariance(self.stats, [r for r, _, _ in self.ratios()])


class BatchEngine:
    """The batched engine over one built scene (:class:`~roadgonio.engines.mitsuba.scene.RoadScene`)."""

    def __init__(self, rs: RoadScene, *, shadow: bool | None = None, tent: bool = False,
                 max_bounces: int | None = None):
        import drjit as dr
        import mitsuba as mi

        from roadgonio.engines.mitsuba.plugins import register_plugins
        from roadgonio.engines.mitsuba.plugins.ka_batch import canonical_source
        register_plugins()
        self.rs = rs
        self.instrument = rs.instrument
        self.tent = bool(tent)
        # the scene's own source is replaced by one per cell (not part of the scene): move it
        # far below the sample plane, where no shadow ray can meet it
        if rs.source_kind == "point":
            rs.params["source.position"] = mi.Point3f(0.0, 0.0, -1e4)
        else:
            rs.params["source.to_world"] = mi.ScalarTransform4f().translate([0.0, 0.0, -1e4]).scale(
                [max(rs.instrument.source.radius_m, 1e-6)] * 3)
        rs.params.update()
        rs.cell = None
        flat = rs.flat_rectangle and rs.xml is None
        self._checked: set[tuple] = set()
        self.integrator = mi.load_dict({"type": "kabatch", "flat": bool(flat),
                                        "shadow": bool(self.can_occlude() if shadow is None else shadow)})
        self.integrator.set_sample(rs.sample_shape)
        src = rs.instrument.source
        # the disc shape is kept here: an area emitter only points back to its shape, which must outlive it
        self.emitter, self._emitter_shape = canonical_source(src.radius_m, source_radiance(rs.instrument))
        self.integrator.set_source(self.emitter)
        self.integrator.set_profile(src)
        self.threads = int(dr.thread_count()) if hasattr(dr, "thread_count") else 1
        # stray light: paths through the reflecting parts (the scene decides, rs.stray; ``max_bounces``
        # forces the paths, e.g. to show that black parts give the direct engine's numbers bit for bit)
        self.max_bounces = int(max_bounces) if max_bounces is not None else rs.max_bounces
        self.stray = bool(rs.stray or (max_bounces is not None and max_bounces > 1))
        if self.stray:
            if self.max_bounces < 2:
                raise ValueError("stray light needs max_bounces >= 2")
            self.integrator.set_parts([rs.sample_shape] + list(rs.parts), self.max_bounces, src.radius_m,
                                      source_radiance(rs.instrument))

    def can_occlude(self) -> bool:
        """Whether anything in the scene can shade the light reaching the sample: a flat rectangle
        alone cannot (the sources are above its plane); meshes, XML scenes and housings can."""
        return not (self.rs.flat_rectangle and self.rs.xml is None and self.rs.housing is None)

    # -- checks --------------------------------------------------------------------------------
    def check_cells(self, cells: Sequence[tuple[float, float]]) -> None:
        """The preamble of every backend (:func:`roadgonio.engines.cellcheck.check_cells`; a clipping
        beam limit is modelled, the registry's ``beam_clipping``); a housing must hold every cell's
        source (:func:`roadgonio.instrument.enclosure.check_sources`). The scene, the instrument and
        the model are fixed for the engine's life, so cells that passed once are not checked again
        (the housing's check takes 0.065 s for the full table, 3 % of the housed example's table at
        rel. SE 1e-3, at load 2.5)."""
        key = (id(self.rs.model), tuple((float(t), float(b)) for t, b in cells))
        if key in self._checked:
            return
        check_cells(self.instrument, self.rs.model, cells, models_beam=backend_info("mitsuba").beam_clipping,
                    backend="mitsuba")
        if self.rs.housing is not None:
            from roadgonio.instrument.enclosure import check_sources
            check_sources(self.instrument, self.rs.housing, cells)
        self._checked.add(key)

    # -- the passes ----------------------------------------------------------------------------
    def run(self, cells: Sequence[tuple[float, float]], planner: Planner, *, seed: int = 0,
            plan: Plan | dict | None = None,
            on_done: Callable[[list[int], EngineRun], None] | None = None,
            resume: dict | None = None, on_pass: Callable[[dict], None] | None = None,
            kept: str | Callable[[], str] | None = None) -> EngineRun:
        """Compute the statistics of every cell; ``on_done(indices, run)`` is called after each pass
        with the cells that left the active set. With ``plan`` the recorded schedule is replayed
        (no adaptation; a cell is converged if it meets the target at the end).

        ``on_pass(state)`` (without ``plan``) is called after each pass, after ``on_done``, with the
        cells still active (none after the last pass), their statistics and plan so far and the
        next pass's requests, plain JSON types; the two calls of a pass run inside
        :func:`roadgonio.interrupts.critical` (a stop at once waits for what they write).
        ``resume`` is such a state: when its cells are ``cells`` (same order) and its seed is
        ``seed``, the run continues from that pass, and since a cell's numbers depend only on
        (seed, pass, lattice size, its replicates) it ends with the same numbers, bit for bit, as
        the run that was cut short would have (else ``resume`` is ignored). ``kept`` says what a
        stop at once keeps (a second Ctrl-C during a pass: roadgonio.interrupts; a function is
        called then)."""
        t0 = time.perf_counter()
        cells = [(float(t), float(b)) for t, b in cells]
        n = len(cells)
        self.check_cells(cells)
        self.integrator.set_cells(*cell_sources(self.instrument, cells))
        stats = [CellStats() for _ in range(n)]
        run = EngineRun(stats=stats, converged=[False] * n, plan=Plan([[] for _ in range(n)]), seconds=0.0,
                        passes=0, launches=0)
        run.info["misses"] = 0
        if plan is not None:
            plan = Plan.from_dict(plan)
            if len(plan.cells) != n:
                raise ValueError(f"the plan is for {len(plan.cells)} cells, not {n}")
        active = list(range(n))
        requests = planner.first(n) if plan is None else plan.pass_requests(0)
        p = 0
        restored = self._restore(resume, cells, seed) if resume is not None and plan is None else None
        if restored is not None:
            stats[:], run.plan, p, requests = restored
            run.stats = stats
            run.info["resumed_from_pass"] = p
        # a Ctrl-C or SIGTERM on the command line stops after the pass under way, once its state is
        # saved; a second one at once, losing that pass (roadgonio.interrupts; only when there is a
        # state to save)
        with deferred("pass of the Mitsuba table", kept) if on_pass is not None and plan is None \
                else nullcontext() as stop:
            self._passes(cells, planner, plan, seed, stats, run, active, requests, p, on_done, on_pass, stop)
        run.seconds = time.perf_counter() - t0
        return run

    def _passes(self, cells, planner, plan, seed, stats, run, active, requests, p, on_done, on_pass, stop) -> None:
        while requests:
            self._pass(p, requests, stats, run, seed)
            p += 1
            if plan is None:
                requests, done = planner.next(stats, active)
                left = done["converged"] + done["capped"]
                for i in done["converged"]:
                    run.converged[i] = True
            else:
                requests = plan.pass_requests(p) if p < plan.passes else {}
                left = [i for i in active if i not in requests]
                for i in left:
                    run.converged[i] = planner.cell_rel(stats[i]) <= planner.rel_se
            gone = set(left)
            active = [i for i in active if i not in gone]
            for i in left:
                self._check_lit(cells[i], stats[i])
            # the finished cells and the state of the others are written as one (a second Ctrl-C,
            # which stops at once, finds both of this pass or both of the one before)
            with critical():
                if on_done is not None and left:
                    on_done(sorted(left), run)
                if on_pass is not None and plan is None:
                    on_pass({"pass": p, "seed": int(seed), "cells": [list(cells[i]) for i in active],
                             "stats": [stats[i].to_dict() for i in active],
                             "plan": [[list(e) for e in run.plan.cells[i]] for i in active],
                             "requests": [[k, *requests[i]] for k, i in enumerate(active) if i in requests]})
            if stop is not None and requests:
                stop.check()
        run.passes = p

    @staticmethod
    def _restore(state: dict, cells: list[tuple[float, float]], seed: int):
        """(stats, plan, pass, requests) of a saved state of exactly these cells and this seed, else
        None (another run's state, or one that does not restore: the cells are computed afresh)."""
        try:
            if int(state.get("seed", -1)) != int(seed) or \
                    [tuple(float(x) for x in c) for c in state.get("cells", [])] != cells:
                return None
            stats = [CellStats.from_dict(d) for d in state["stats"]]
            plan = Plan([[tuple(int(x) for x in e) for e in c] for c in state["plan"]])
            requests = {int(i): (int(a), int(b)) for i, a, b in state["requests"]}
        except (TypeError, ValueError, KeyError, AttributeError):
            return None
        if len(stats) != len(cells) or len(plan.cells) != len(cells) or not requests:
            return None
        return stats, plan, int(state["pass"]), requests

    def _check_lit(self, cell, st: CellStats) -> None:
        _, sg = st.totals()
        if not sg > 0.0:
            if not self.can_occlude():
                # nothing in the scene can shade the footprint: a beam too narrow to be met (user audit,
                # session 42: it asked whether a part of the scene shaded it, in a scene without parts)
                err = unsampled_beam(self.instrument, cell[0], cell[1], "mitsuba")
                if err is not None:
                    raise err
            mesh = self.instrument.sample.mesh
            why = ("is it shaded by a part of the scene" + (", or does the detector see the back of the sample mesh "
                   "(a face reflects towards the side its normal points to)" if mesh is not None else "") + "?")
            # the mesh named, where it is the likely cause (user audit, session 45: numpy-mc-mesh named it)
            from roadgonio.instrument.mesh import mesh_location
            raise GeometryError(f"the source lights none of the detector footprint at tan eps = {cell[0]:g}, "
                                f"beta = {cell[1]:g} (Lambert signal {sg:g}): {why}",
                                **(mesh_location(mesh) if mesh is not None else {}))

    def _pass(self, p: int, requests: dict[int, tuple[int, int]], stats, run: EngineRun, seed: int) -> None:
        groups: dict[int, list[tuple[int, int]]] = {}
        for i, (log2n, reps) in requests.items():
            groups.setdefault(log2n, []).append((i, reps))
            run.plan.cells[i].append((p, log2n, reps))
        run.info.setdefault("passes", []).append(
            {"cells": len(requests), "groups": len(groups),
             "samples": int(sum(reps << log2n for log2n, reps in requests.values()))})
        # every group's kernels are launched before any result is read back: Dr.Jit launches
        # asynchronously, so Python traces the next kernels while the previous ones run
        pending = [self._group(p, log2n, members, stats, run, seed) for log2n, members in sorted(groups.items())]
        for finish in pending:
            finish()

    def _group(self, p: int, log2n: int, members: list[tuple[int, int]], stats, run: EngineRun,
               seed: int) -> Callable[[], None]:
        """Launch the kernels of one lattice size's group; returns the function that reads their
        sums back (waiting for them), checks the detector rays and adds the strata to ``stats``."""
        rs, integ = self.rs, self.integrator
        n = 1 << log2n
        idx = np.array([i for i, _ in members], dtype=np.int64)
        want = np.array([r for _, r in members], dtype=np.int64)
        max_reps = int(want.max())
        shifts = lat.shifts(seed, p, log2n, max_reps)
        z = lat.generating_vector(n)
        if self.stray and integ.qmc_dims:
            # the paths' first dimensions continue the lattice (shifts of their own)
            z = lat.generating_vector(n, lat.DIMENSIONS + integ.qmc_dims)
            shifts = np.concatenate([shifts, lat.walk_shifts(seed, p, log2n, max_reps, integ.qmc_dims)], axis=1)
        reps_per_chunk = max(1, (MAX_PATHS if self.stray else MAX_RAYS) >> log2n)
        got_cell, got_rep, got, got_stray, got_misses = [], [], [], [], []
        if self.stray:
            from roadgonio.engines.mitsuba.plugins.ka_batch import _u32
            keys_all = lat.walk_keys(seed, p, log2n, max_reps, integ.walk_dims)
        for r0 in range(0, max_reps, reps_per_chunk):
            r1 = min(max_reps, r0 + reps_per_chunk)
            lattice = integ.lattice_params(n, z, shifts[r0:r1], self.tent)
            if self.stray:
                keys = [_u32(keys_all[r0:r1, d]) for d in range(keys_all.shape[1])]
                rays, verts, misses = integ.trace_paths(rs.scene, rs.sensor, lattice, r1 - r0, keys, defer=True)
                run.launches += len(verts)
            else:
                rays, misses = integ.trace_detector(rs.scene, rs.sensor, lattice, r1 - r0, defer=True)
            run.launches += 1
            got_misses.append((misses, (r1 - r0) * n))
            # blocks replicate-major: the rays of one replicate serve consecutive blocks
            reps = np.arange(r0, r1)
            mask = want[None, :] > reps[:, None]
            bc = np.broadcast_to(idx[None, :], mask.shape)[mask]
            br = np.broadcast_to(reps[:, None], mask.shape)[mask]
            per_launch = max(1, MAX_LANES >> log2n)
            for k0 in range(0, len(bc), per_launch):
                k1 = min(len(bc), k0 + per_launch)
                got.append(integ.block_sums(rs.scene, rays, lattice, bc[k0:k1], br[k0:k1] - r0, defer=True))
                run.launches += 1
                got_cell.append(bc[k0:k1])
                got_rep.append(br[k0:k1])
                if self.stray:
                    # the light through each further path vertex, next-event estimation to the block's cell
                    ind = []
                    for k in integ.eye_vertices():
                        ind.append(integ.stray_sums(rs.scene, verts[k - 1], lattice, bc[k0:k1], br[k0:k1] - r0, keys,
                                                    k, defer=True))
                        run.launches += 1
                    if integ.light_depth:
                        ind.append(integ.light_sums(rs.scene, rays, verts[0], lattice, bc[k0:k1], br[k0:k1] - r0,
                                                    keys, defer=True))
                        run.launches += 1
                    got_stray.append((k1 - k0, ind))
            if self.stray:
                del verts

        def finish() -> None:
            for read_misses, rays in got_misses:
                misses = read_misses()
                if misses:
                    raise GeometryError(f"{misses} of {rays} detector rays do not hit the sample: the detector "
                                        "footprint must lie on the sample; enlarge the sample or narrow the field")
            cell, rep = np.concatenate(got_cell), np.concatenate(got_rep)
            val = np.concatenate([out().astype(np.float64).sum(axis=1) for out in got])      # (blocks, 2)
            order = np.lexsort((rep, cell))
            if self.stray:
                # the stray sums in the order they were added before (vertex 1, vertex 2, light paths)
                stray = []
                for blocks, ind in got_stray:
                    acc = np.zeros((blocks, 2))
                    for out in ind:
                        acc += out().astype(np.float64).sum(axis=1)
                    stray.append(acc)
                # totals (direct + stray; exactly the direct sums where the stray sums are 0) and the direct light
                tot = val + np.concatenate(stray)
                add_strata(stats, p, log2n, cell[order], rep[order], tot[order, 0], tot[order, 1],
                           val[order, 0], val[order, 1])
            else:
                add_strata(stats, p, log2n, cell[order], rep[order], val[order, 0], val[order, 1])
        return finish
