"""Where the time of the housed portable table goes (issue 18's time target; benchmarks are not
tests): the full 580-cell table of scenes/portable_housed.toml at worst relative SE --rel-se, R3.

1. **Launches**: wall seconds per engine step (trace_paths: the detector rays and the eye paths;
   block_sums: the direct light; stray_sums: next-event estimation at eye vertices 1 and 2;
   light_sums: the light paths' three strategies; the engine reads the sums back only after a
   pass's last launch, so this is the Python tracing and launching of each step, the kernels run
   meanwhile), and Dr.Jit's kernel history of the same run: execution vs code generation (tracing
   into IR) per kernel, backend compilations (cache misses).
2. **The planner**: samples per pass, passes per cell, the cells that need the most samples, and
   the samples a planner that gave every cell exactly the target would have used
   (samples x (achieved rel SE / target)^2 summed; a lower bound, no pass can know it).
3. **What the variance is made of**, at chosen cells: one launch of the stray picture's lanes
   (:meth:`KaBatch.picture_lanes`: the direct light and each stray strategy separately, ``--log2n``
   points x ``--replicates`` replicates): per strategy its share of the road and Lambert signals and
   the variance per point of its residual y = road - r Lambert (from replicate sums; what the
   lattice leaves) and its mean square (what it would leave as plain Monte Carlo), relative to the
   variance per point V of the whole residual.

    python bench/profile_straylight.py [--reflectance 0.05] [--rel-se 1e-3]
    python bench/profile_straylight.py --variance-only --cells 12 60 12 105   # section 3 at these cells

Prints the tables and writes bench/results/straylight_profile.txt.
"""
from __future__ import annotations

import argparse
import collections
import functools
import sys
import time
from pathlib import Path

import numpy as np

from machine import header, load_after  # bench/machine.py (bench_straylight's _load moved there and is gone)

ROOT = Path(__file__).resolve().parents[1]
STEPS = ("trace_paths", "block_sums", "stray_sums", "light_sums")
STRATEGIES = ("direct", "eye vertex 1 (NEE)", "eye vertex 2 (NEE)", "light path, 1 reflection",
              "light path, 2: eye y1 + light y2", "light path, 2 reflections")
CELLS = ((11.0, 35.0), (12.0, 90.0), (12.0, 0.0), (3.0, 30.0), (1.0, 0.0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rel-se", type=float, default=1e-3)
    ap.add_argument("--sample", default="R3")
    ap.add_argument("--reflectance", type=float, default=None, help="the walls' (default: the example's)")
    ap.add_argument("--log2n", type=int, default=10)
    ap.add_argument("--replicates", type=int, default=64)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "straylight_profile.txt"))
    ap.add_argument("--cells", type=float, nargs="*", default=None,
                    help="tan eps, beta pairs for section 3 (default: the limiting cells of the table)")
    ap.add_argument("--variance-only", action="store_true", help="section 3 only")
    args = ap.parse_args(argv)

    import drjit as dr

    from roadgonio.engines import full_grid_cells
    from roadgonio.engines.mitsuba import lattice as lat
    from roadgonio.engines.mitsuba import set_variant
    set_variant()
    from roadgonio.engines.mitsuba.backend import make_backend
    from roadgonio.engines.mitsuba.engine import BatchEngine, cell_sources
    from roadgonio.engines.mitsuba.plugins import ka_batch as kb
    from roadgonio.engines.mitsuba.scene import build_scene
    from roadgonio.instrument.config import Instrument
    from roadgonio.surface.sample import resolve_sample

    model = resolve_sample(args.sample).model
    inst = Instrument.load(ROOT / "scenes" / "portable_housed.toml")
    if args.reflectance is not None:
        d = inst.to_dict()
        d["housing"] = {**d["housing"], "wall_reflectance": args.reflectance}
        inst = Instrument.from_dict(d, path=inst.path)
    rho = inst.extra["housing"]["wall_reflectance"]
    cells = full_grid_cells()
    out = header(f"profile_straylight: portable_housed (walls {rho:g}), {args.sample}, {len(cells)} cells, worst "
                 f"rel SE {args.rel_se:g}, {dr.thread_count()} Dr.Jit threads")

    if not args.variance_only:
        # 1. launches
        spent, calls = collections.defaultdict(float), collections.Counter()
        originals = {name: getattr(kb.KaBatch, name) for name in STEPS}

        def timed(name, f):
            @functools.wraps(f)
            def g(*a, **k):
                t = time.perf_counter()
                r = f(*a, **k)
                spent[name] += time.perf_counter() - t
                calls[name] += 1
                return r
            return g

        for name, f in originals.items():
            setattr(kb.KaBatch, name, timed(name, f))
        try:
            b = make_backend(inst, model, rel_se=args.rel_se, seed=0)
            b.compute(cells)                                       # compile and warm up
            spent.clear()
            calls.clear()
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            dr.kernel_history()                                    # (clears it)
            c0, t0 = time.process_time(), time.perf_counter()
            res = b.compute(cells)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            hist = dr.kernel_history()
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        finally:
            for name, f in originals.items():
                setattr(kb.KaBatch, name, f)
        kernels = [e for e in hist if "codegen_time" in e]
        exe = sum(e.get("execution_time", 0.0) for e in kernels) / 1e3
        gen = sum(e.get("codegen_time", 0.0) for e in kernels) / 1e3
        back = sum(e.get("backend_time", 0.0) for e in kernels) / 1e3
        misses = sum(1 for e in kernels if not e.get("cache_hit", False))
        out.append(f"\n1. launches: table {wall:.2f} s wall, CPU/wall {cpu / wall:.2f}; {len(kernels)} kernels: execution "
                   f"{exe:.2f} s, code generation (tracing to IR) {gen:.2f} s, backend compilation {back:.2f} s "
                   f"({misses} not in the kernel cache); the rest, {wall - exe - gen - back:.2f} s, is Python (tracing, "
                   "planner, statistics) and the reductions")
        out.append(f"   {'step':14s} {'calls':>6s} {'wall s':>8s} {'share':>6s}")
        for name in STEPS:
            out.append(f"   {name:14s} {calls[name]:6d} {spent[name]:8.3f} {spent[name] / wall:6.1%}")
        big = sorted(kernels, key=lambda e: -e.get("execution_time", 0.0))
        by_ops = collections.defaultdict(lambda: [0, 0.0])
        for e in big:
            k = by_ops[e.get("operation_count", 0)]
            k[0] += 1
            k[1] += e.get("execution_time", 0.0) / 1e3
        out.append("   kernels by size (operations: launches, execution s): " + "; ".join(
            f"{ops}: {n}, {t:.3f}" for ops, (n, t) in sorted(by_ops.items(), key=lambda kv: -kv[1][1])[:6]))

        # 2. the planner
        S = np.array([r.samples for r in res], dtype=np.float64)
        rel = np.array([r.se / abs(r.k_a) for r in res])
        ideal = float(np.sum(S * (rel / args.rel_se) ** 2))
        out.append(f"\n2. planner: {S.sum():.3e} samples (median {np.median(S):.0f} a cell, max {S.max():.0f}); every cell "
                   f"exactly at the target: {ideal:.3e} ({S.sum() / ideal:.2f}x fewer)")
        for q, p in enumerate(b.last_run.info["passes"]):
            out.append(f"   pass {q}: {p['cells']} cells, {p['groups']} lattice sizes, {p['samples']:.3e} samples")
        out.append("   passes per cell: " + ", ".join(f"{k}: {v}" for k, v in
                                                       sorted(collections.Counter(r.extra['passes'] for r in res).items())))
        out.append("   most samples: " + "; ".join(
            f"tan {res[i].tan_eps:g} beta {res[i].beta_deg:g}: {S[i]:.0f} (rel SE {rel[i]:.1e}, stray "
            f"{100 * res[i].stray_fraction:.0f} %)" for i in np.argsort(-S)[:5]))

    # 3. the variance by strategy
    rs = build_scene(inst, model, hit_rays=1 << 12)
    eng = BatchEngine(rs)
    integ = eng.integrator
    n, reps = 1 << args.log2n, args.replicates
    out.append(f"\n3. variance by strategy ({reps} replicates of {n} points, seed 0): share of the road / Lambert "
               "signal; variance per point of the residual (lattice) / mean square (plain MC), both / V")
    sec3 = CELLS if not args.cells else tuple(zip(args.cells[0::2], args.cells[1::2]))
    for cell in sec3:
        integ.set_cells(*cell_sources(inst, [cell]))
        z = lat.generating_vector(n, lat.DIMENSIONS + integ.qmc_dims)
        shifts = np.concatenate([lat.shifts(0, 0, args.log2n, reps),
                                 lat.walk_shifts(0, 0, args.log2n, reps, integ.qmc_dims)], axis=1)
        keys_all = lat.walk_keys(0, 0, args.log2n, reps, integ.walk_dims)
        lattice = integ.lattice_params(n, z, shifts)
        keys = [kb._u32(keys_all[:, d]) for d in range(keys_all.shape[1])]
        lanes = integ.picture_lanes(rs.scene, rs.sensor, lattice, keys, reps=reps)
        rep = lanes["rep"].astype(np.int64)
        q = 0
        roads, lams = [lanes["direct_road"]], [lanes["direct_lambert"]]
        while f"road_{q}" in lanes:
            roads.append(lanes[f"road_{q}"])
            lams.append(lanes[f"lambert_{q}"])
            q += 1
        rt, gt = sum(roads), sum(lams)
        r = rt.sum() / gt.sum()

        def point_var(y, rep=rep):
            s = np.bincount(rep, y, minlength=reps)
            return float(np.var(s, ddof=1)) / n

        V = point_var(rt - r * gt)
        rel1 = np.sqrt(V) / (gt.sum() / (reps * n)) / abs(r)
        out.append(f"   tan {cell[0]:g}, beta {cell[1]:g}: rel SE x sqrt(N) = {rel1:.3f} (N = {(rel1 / args.rel_se) ** 2:.0f} "
                   "for the target)")
        second = 0.0
        for k, (a, g) in enumerate(zip(roads, lams)):
            y = a - r * g
            pv = point_var(y) / V
            if k in (2, 4, 5):
                second += pv
            name = STRATEGIES[k] if k < len(STRATEGIES) else f"strategy {k}"
            out.append(f"     {name:34s} {a.sum() / rt.sum():7.2%} / {g.sum() / gt.sum():7.2%}   {pv:6.3f} / "
                       f"{float(np.mean(y * y)) / V:6.3f}")
        out.append(f"     second order (eye vertex 2, both 2-reflection light strategies): {second:.2f} of V")
    text = "\n".join(out + [load_after()])
    print(text)
    Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
