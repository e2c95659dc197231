"""Benchmark of the batched k_A engine (issue 9), side by side in one run, with the machine load
printed beside every row (benchmarks are not tests).

For the portable preset and the wide instrument (scenes/wide.toml), both with the fitted CIE R3,
the full 580-cell table at worst relative SE <= --rel-se (default 1e-3):

* ``engine``: the Mitsuba backend (kabatch integrator): compute seconds, CPU/wall (both threads?),
  samples, samples per second, worst relative SE, passes and launches;
* ``bare kernel``: the limit, a bare Dr.Jit kernel of the same integrand from the project's own
  optics and model code (bench/bare_kernel.py) replaying the engine's plan (same lattices and
  shifts, so the same samples: their k_A must agree to float32 rounding);
* ``numpy-mc``: the float64 numpy Monte Carlo on every --mc-stride-th cell (a stride prime to the 20
  columns samples every column), each cell's time scaled to the target error
  (t (achieved rel SE / target)^2, Monte Carlo cost goes as 1/SE^2) and extrapolated to the table;
* ``process``: ``roadgonio ka`` on the full table as a user runs it (start-up, fit cache, scene,
  table, CSV, PNG), wall and CPU seconds of the whole process (portable only);
* ``large launch``: CPU/wall of one launch of 2^24 lanes (Dr.Jit's thread pool);
* ``uncertainty``: ``roadgonio uncertainty`` with the aperture effect, 10,000 trials, the whole
  process (start-up, the exact k_A tables of the surrogate, the trials, the statistics, the files;
  with and without its pictures), with the surrogate's error against its held-out exact tables.
  Target (issue 9): the whole process <= 15 s. bench/bench_uncertainty.py times a different thing,
  the computation alone inside its own process (``run_uncertainty``), against issue 5's 10 minutes.

    python bench/bench_engine.py [--rel-se 1e-3] [--mc-stride 7] [--no-numpy] [--no-uncertainty]

Prints a table under the machine and the load average and writes bench/results/engine.csv and the
printed table as engine.txt (``--out`` elsewhere).
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import Printout, load_after  # noqa: E402  (bench/machine.py)

SIGMA = ("alpha_deg=0.01,eps_deg=0.05:rect,beta_deg=0.1,tilt_x_deg=0.02,tilt_y_deg=0.02,"
         "source_distance_m=0.002,detector_distance_m=0.005")
TARGETS = {"portable": {"compute_s": 0.5, "process_s": 2.5}, "wide": {"compute_s": 6.0}}


def cpu_self() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def load() -> str:
    return "/".join(f"{v:.1f}" for v in os.getloadavg())


def replay_bare(bare, inst, cells, plan, seed) -> tuple[float, float, np.ndarray]:
    """Run the bare kernel over the engine's plan; returns (wall, cpu, ratios)."""
    import drjit as dr  # noqa: F401

    from roadgonio.engines.mitsuba import lattice as lat
    from roadgonio.engines.mitsuba.engine import MAX_LANES
    from roadgonio.instrument.optics import source_frames
    from roadgonio.engines.mitsuba.plugins.ka_batch import lattice_params
    c = np.asarray(cells, dtype=np.float64)
    bare.set_cells(source_frames(inst, c[:, 0], c[:, 1]))
    sums = np.zeros((len(cells), 2))
    t0, c0 = time.perf_counter(), cpu_self()
    for p in range(plan.passes):
        req = plan.pass_requests(p)
        groups: dict[int, list[tuple[int, int]]] = {}
        for i, (log2n, reps) in req.items():
            groups.setdefault(log2n, []).append((i, reps))
        for log2n, members in groups.items():
            n = 1 << log2n
            idx = np.array([i for i, _ in members])
            want = np.array([r for _, r in members])
            shifts = lat.shifts(seed, p, log2n, int(want.max()))
            params = lattice_params(n, lat.generating_vector(n), shifts)
            reps = np.arange(int(want.max()))
            mask = want[None, :] > reps[:, None]
            bc = np.broadcast_to(idx[None, :], mask.shape)[mask]
            br = np.broadcast_to(reps[:, None], mask.shape)[mask]
            per = max(1, MAX_LANES >> log2n)
            for k0 in range(0, len(bc), per):
                out = bare.block_sums(params, bc[k0:k0 + per], br[k0:k0 + per]).astype(np.float64).sum(axis=1)
                np.add.at(sums, bc[k0:k0 + per], out)
    return time.perf_counter() - t0, cpu_self() - c0, sums[:, 0] / sums[:, 1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rel-se", type=float, default=1e-3)
    ap.add_argument("--sample", default="R3")
    ap.add_argument("--mc-stride", type=int, default=7, help="numpy-mc on every N-th cell (prime to 20)")
    ap.add_argument("--mc-max-samples", type=int, default=1 << 22, help="numpy-mc cap per cell (then scaled)")
    ap.add_argument("--no-numpy", action="store_true")
    ap.add_argument("--no-uncertainty", action="store_true")
    ap.add_argument("--instruments", default="portable,wide")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "engine.csv"))
    args = ap.parse_args(argv)

    from roadgonio.engines.mitsuba import set_variant
    mi = set_variant()                     # the script is the entry point: it chooses the variant
    import drjit as dr

    from bare_kernel import BareKernel
    from roadgonio.engines import full_grid_cells, ideal_ratios, make_backend
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.sample import resolve_sample
    model = resolve_sample(args.sample).model
    cells = full_grid_cells()
    rows = []
    say = Printout(f"k_A engine benchmark: sample {args.sample} ({model.variant}), target worst rel SE "
                   f"{args.rel_se:g}, dr.thread_count() = {dr.thread_count()}, variant {mi.variant()}")

    for name in args.instruments.split(","):
        inst = load_instrument(str(ROOT / "scenes" / f"{name}.toml"))
        b = make_backend("mitsuba", inst, model, rel_se=args.rel_se, seed=1)
        b.compute(cells[:3])                                           # compile outside the timing
        t0, c0 = time.perf_counter(), cpu_self()
        res = b.compute(cells)
        wall, cpu = time.perf_counter() - t0, cpu_self() - c0
        samples = sum(r.samples for r in res)
        worst = max(r.se / abs(r.k_a) for r in res)
        row = {"instrument": name, "what": "engine", "seconds": wall, "cpu_per_wall": cpu / wall, "samples": samples,
               "samples_per_s": samples / wall, "worst_rel_se": worst, "passes": b.last_run.passes,
               "launches": b.last_run.launches, "k_a_min": min(r.k_a for r in res),
               "not_converged": sum(not r.converged for r in res), "target_s": TARGETS[name]["compute_s"],
               "load": load()}
        rows.append(row)
        print(f"  {name}: engine {wall:.2f} s, CPU/wall {cpu / wall:.2f}, {samples:.3g} samples, worst rel SE {worst:.2e}, "
              f"{b.last_run.passes} passes, {b.last_run.launches} launches, k_A >= {row['k_a_min']:.3f} "
              f"(load {load()})", flush=True)

        bare = BareKernel(inst, model)
        replay_bare(bare, inst, cells[:3], b.last_plan.__class__([c[:1] for c in b.last_plan.cells[:3]]), 1)
        bw, bc, ratios = replay_bare(bare, inst, cells, b.last_plan, 1)
        k_bare = ratios / ideal_ratios(model, inst, cells)
        dev = float(np.max(np.abs(k_bare / np.array([r.k_a for r in res]) - 1.0)))
        rows.append({"instrument": name, "what": "bare kernel (same plan)", "seconds": bw, "cpu_per_wall": bc / bw,
                     "samples": samples, "samples_per_s": samples / bw, "worst_rel_se": worst,
                     "max_dev_vs_engine": dev, "speedup_engine": bw / wall, "load": load()})
        print(f"  {name}: bare kernel {bw:.2f} s ({samples / bw:.3g} samples/s; engine reaches "
              f"{bw / wall:.2f} of it), max |k_bare/k_engine - 1| = {dev:.1e} (load {load()})", flush=True)

        # one large launch: both threads busy?
        from roadgonio.engines.mitsuba import lattice as lat
        integ, rs = b.engine.integrator, b.rs
        n = 1 << 12
        lattice = integ.lattice_params(n, lat.generating_vector(n), lat.shifts(9, 0, 12, 16))
        rays, _ = integ.trace_detector(rs.scene, rs.sensor, lattice, 16)
        blocks = (1 << 24) >> 12
        bcell = np.arange(blocks) % len(cells)
        brep = np.arange(blocks) % 16
        t0, c0 = time.perf_counter(), cpu_self()
        integ.block_sums(rs.scene, rays, lattice, bcell, brep)
        lw, lc = time.perf_counter() - t0, cpu_self() - c0
        rows.append({"instrument": name, "what": "large launch (2^24 lanes)", "seconds": lw, "cpu_per_wall": lc / lw,
                     "samples": 1 << 24, "samples_per_s": (1 << 24) / lw, "load": load()})
        print(f"  {name}: one launch of 2^24 lanes {lw:.2f} s, CPU/wall {lc / lw:.2f} (load {load()})", flush=True)

        if not args.no_numpy:
            sub = cells[:: args.mc_stride]
            nb = make_backend("numpy-mc", inst, model, rel_se=args.rel_se, seed=1, max_samples=args.mc_max_samples)
            t0 = time.perf_counter()
            nres = nb.compute(sub)
            nw = time.perf_counter() - t0
            eq = sum(r.seconds * (r.se / abs(r.k_a) / args.rel_se) ** 2 for r in nres) * len(cells) / len(sub)
            raw = nw * len(cells) / len(sub)
            rows.append({"instrument": name, "what": f"numpy-mc at equal error (every {args.mc_stride}th cell, scaled)",
                         "seconds": eq, "measured_s": nw, "cells_measured": len(sub),
                         "samples": sum(r.samples for r in nres), "speedup_engine": eq / wall,
                         "speedup_bare_kernel": eq / bw, "load": load()})
            rows.append({"instrument": name, "what": "numpy-mc as run (its defaults, extrapolated)",
                         "seconds": raw, "speedup_engine": raw / wall, "load": load()})
            print(f"  {name}: numpy-mc {nw:.1f} s on {len(sub)} cells; for the table at equal error (each cell's time "
                  f"scaled by (achieved rel SE / target)^2) {eq:.1f} s: engine {eq / wall:.1f}x faster (the bare "
                  f"kernel, the limit of any Dr.Jit code of this integrand and plan: {eq / bw:.1f}x); as run "
                  f"(8 batches of 16384 at least) {raw:.0f} s: {raw / wall:.0f}x (load {load()})", flush=True)
            if name == "portable":
                # measured, not scaled: numpy-mc with small batches (16^2: its stratification is then
                # coarser, but it stops near the target instead of overshooting it), the same cells
                nb_s = make_backend("numpy-mc", inst, model, rel_se=args.rel_se, seed=1, batch=256,
                                    max_samples=args.mc_max_samples)
                t0 = time.perf_counter()
                sres = nb_s.compute(sub)
                sw = time.perf_counter() - t0
                worst_s = max(r.se / abs(r.k_a) for r in sres)
                rows.append({"instrument": name, "what": "numpy-mc, batches of 16^2 (measured, extrapolated)",
                             "seconds": sw * len(cells) / len(sub), "measured_s": sw, "cells_measured": len(sub),
                             "samples": sum(r.samples for r in sres), "worst_rel_se": worst_s,
                             "speedup_engine": sw * len(cells) / len(sub) / wall, "load": load()})
                print(f"  {name}: numpy-mc with batches of 16^2: {sw:.2f} s on {len(sub)} cells (worst rel SE "
                      f"{worst_s:.2e}), {sw * len(cells) / len(sub):.2f} s for the table: engine "
                      f"{sw * len(cells) / len(sub) / wall:.1f}x faster (load {load()})", flush=True)

        if name == "portable":
            with tempfile.TemporaryDirectory() as tmp:
                cmd = [sys.executable, "-m", "roadgonio", "ka", "--instrument", name, "--sample", args.sample,
                       "--out", tmp, "--fresh", "--rel-se", str(args.rel_se), "--json"]
                t0, c0 = time.perf_counter(), cpu_children()
                out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp)
                pw, pc = time.perf_counter() - t0, cpu_children() - c0
                ok = out.returncode == 0 and (Path(tmp) / "ka.png").exists()
                s = json.loads(out.stdout) if ok else {}
            rows.append({"instrument": name, "what": "process: roadgonio ka (start-up, table, CSV, PNG)",
                         "seconds": pw, "cpu_seconds": pc, "cpu_per_wall": pc / pw, "ok": ok,
                         "target_s": TARGETS[name]["process_s"], "worst_rel_se": s.get("worst_rel_se"),
                         "load": load()})
            print(f"  {name}: whole process {pw:.2f} s wall, {pc:.2f} s CPU ({'ok' if ok else 'FAILED: ' + out.stderr[-300:]}) "
                  f"(load {load()})", flush=True)

    if not args.no_uncertainty:
        for plots in (True, False):
            with tempfile.TemporaryDirectory() as tmp:
                cmd = [sys.executable, "-m", "roadgonio", "uncertainty", "--instrument", "portable", "--sample",
                       args.sample, "--sigma", SIGMA, "--trials", "10000", "--out", tmp, "--json"]
                if not plots:
                    cmd.append("--no-plots")
                t0, c0 = time.perf_counter(), cpu_children()
                out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp)
                uw, uc = time.perf_counter() - t0, cpu_children() - c0
                ok = out.returncode == 0
                d = json.loads(out.stdout) if ok else {}
            sur = (d.get("surrogate") or {}) if ok else {}
            sec = d.get("seconds") or {}
            rows.append({"instrument": "portable",
                         "what": "whole process: roadgonio uncertainty, aperture, 10000 trials" + ("" if plots else ", --no-plots"),
                         "seconds": uw, "cpu_seconds": uc, "cpu_per_wall": uc / uw, "ok": ok, "target_s": 15.0,
                         "exact_tables_s": sec.get("surrogate"), "trials_s": sec.get("monte_carlo"),
                         "statistics_s": sec.get("statistics"),
                         "sur_err_max_pct": 100 * sur["rel_err_max"] if "rel_err_max" in sur else None,
                         "sur_err_over_u_max": sur.get("err_over_u_max"),
                         "backend_rel_u_max": sur.get("backend_rel_u_max"), "load": load()})
            r = rows[-1]
            print(f"  uncertainty{'' if plots else ' --no-plots'}: {uw:.1f} s wall, {uc:.1f} s CPU (exact k_A tables "
                  f"{r['exact_tables_s'] or 0:.1f} s, trials {r['trials_s'] or 0:.1f} s, statistics {r['statistics_s'] or 0:.1f} s), "
                  f"surrogate error max {r['sur_err_max_pct'] or float('nan'):.3g} % = {r['sur_err_over_u_max'] or float('nan'):.2g} u, "
                  f"backend rel u <= {r['backend_rel_u_max'] or float('nan'):.1e} "
                  f"({'ok' if ok else 'FAILED: ' + out.stderr[-300:]}) (load {load()})", flush=True)

    fields = []
    for r in rows:
        fields += [k for k in r if k not in fields]
    out_path = Path(args.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with open(out_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})
    say("")
    hdr = (f"{'instrument':9} {'what':72} {'seconds':>8} {'target':>6} {'CPU/wall':>8} {'samples/s':>10} "
           f"{'worst relSE':>11} {'engine x':>8}  load")
    say(hdr)
    say("-" * len(hdr))
    for r in rows:
        def f(key, spec, r=r):          # called in this iteration only
            v = r.get(key)
            return format(v, spec) if isinstance(v, (int, float)) and v is not None and not (
                isinstance(v, float) and math.isnan(v)) else ""
        say(f"{r['instrument']:9} {r['what'][:72]:72} {f('seconds', '8.2f'):>8} {f('target_s', '6.1f'):>6} "
            f"{f('cpu_per_wall', '8.2f'):>8} {f('samples_per_s', '10.3g'):>10} {f('worst_rel_se', '11.2e'):>11} "
            f"{f('speedup_engine', '8.1f'):>8}  {r['load']}")
    say(load_after())
    out_path.with_suffix(".txt").write_text(say.text() + "\n")
    print(f"wrote {out_path} and {out_path.with_suffix('.txt')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
