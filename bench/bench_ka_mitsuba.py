"""Benchmark: the full 580-cell k_A table of the portable preset for the R3 fit with the Mitsuba
backend, side by side with the float64 numpy Monte Carlo of the same integral at the same
relative standard error (roadgonio.engines.montecarlo). Superseded by bench/bench_engine.py (the
batched engine with its bare-kernel limit, the wide instrument and the whole-process times); kept
for the Mitsuba-vs-numpy agreement check on the same cells. Per-cell seconds of the batched engine
are its pass times shared out over the cells that finished in them.

    python bench/bench_ka_mitsuba.py                 # numpy MC on every 10th cell (extrapolated)
    python bench/bench_ka_mitsuba.py --mc-stride 1   # numpy MC on the full table too (slow)

Targets (2-core machine): the Mitsuba table in under 60 s, and at least 5x faster than numpy MC
at the same error. Prints a table under the machine and the load average and writes
bench/results/ka_mitsuba.csv and the printed table as ka_mitsuba.txt (``--out`` elsewhere).
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

import numpy as np
from machine import Printout, load_after  # bench/machine.py (the script's folder is on sys.path)

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rel-se", type=float, default=1e-3)
    ap.add_argument("--sample", default="R3")
    ap.add_argument("--instrument", default=str(ROOT / "scenes" / "portable.toml"))
    ap.add_argument("--mc-stride", type=int, default=10, help="numpy MC on every N-th cell (1 = all)")
    ap.add_argument("--first-pass", type=int, default=None, help="Mitsuba samples per cell in the first pass")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "ka_mitsuba.csv"))
    args = ap.parse_args(argv)

    from roadgonio.instrument.config import Instrument
    from roadgonio.engines import full_grid_cells
    from roadgonio.engines.montecarlo import make_backend as make_mc
    from roadgonio.engines.mitsuba.backend import make_backend as make_mitsuba
    from roadgonio.engines.mitsuba import set_variant
    from roadgonio.surface.sample import resolve_sample

    inst = Instrument.load(args.instrument)
    model = resolve_sample(args.sample).model
    cells = full_grid_cells()
    say = Printout(f"k_A table: instrument {inst.name}, sample {args.sample} ({model.variant}), target rel SE "
                   f"{args.rel_se:g}; Mitsuba vs numpy-mc on every {args.mc_stride}th cell")

    settings = {"rel_se": args.rel_se}
    if args.first_pass:
        settings["first_pass"] = args.first_pass
    set_variant()                      # the script is the entry point: it chooses the variant
    t0 = time.perf_counter()
    mb = make_mitsuba(inst, model, **settings)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    mres = mb.compute(cells)
    t_table = time.perf_counter() - t0
    by_cell = {(r.tan_eps, r.beta_deg): r for r in mres}

    sub = cells[:: args.mc_stride]
    nb = make_mc(inst, model, rel_se=args.rel_se)
    t0 = time.perf_counter()
    nres = nb.compute(sub)
    t_np = time.perf_counter() - t0

    m_sub = [by_cell[c] for c in sub]
    t_m_sub = sum(r.seconds for r in m_sub)
    from roadgonio.engines.validate import FLOAT32_FLOOR, N_SIGMA
    floor = FLOAT32_FLOOR["mitsuba"]
    # z in combined standard errors; cells whose k_A is known to ~1e-9 (purely diffuse there) are
    # judged like `roadgonio validate`: |d| <= N_SIGMA * SE + float32 floor * |k|
    z = [abs(a.k_a - b.k_a) / math.hypot(a.se, b.se) for a, b in zip(m_sub, nres) if a.se > 0 or b.se > 0]
    beyond = sum(abs(a.k_a - b.k_a) > N_SIGMA * math.hypot(a.se, b.se) + floor * abs(b.k_a)
                 for a, b in zip(m_sub, nres))
    rel_m = max(r.se / abs(r.k_a) for r in mres)
    rel_n = max(r.se / abs(r.k_a) for r in nres)
    samples_m = sum(r.samples for r in mres)
    samples_n = sum(r.samples for r in nres)
    passes = [r.extra["passes"] for r in mres]

    rows = [
        {"backend": "mitsuba", "cells": len(cells), "seconds": round(t_table, 2), "build_s": round(t_build, 2),
         "samples": samples_m, "samples_per_s": round(samples_m / t_table), "worst_rel_se": f"{rel_m:.3e}",
         "passes": sum(passes), "max_passes": max(passes), "sampler": "lattice",
         "k_a_min": f"{min(r.k_a for r in mres):.4f}", "k_a_max": f"{max(r.k_a for r in mres):.4f}"},
        {"backend": "mitsuba (MC subset)", "cells": len(sub), "seconds": round(t_m_sub, 2), "build_s": "",
         "samples": sum(r.samples for r in m_sub), "samples_per_s": round(sum(r.samples for r in m_sub) / t_m_sub),
         "worst_rel_se": f"{max(r.se / abs(r.k_a) for r in m_sub):.3e}", "passes": sum(r.extra["passes"] for r in m_sub),
         "max_passes": max(r.extra["passes"] for r in m_sub), "sampler": "lattice", "k_a_min": "", "k_a_max": ""},
        {"backend": "numpy-mc (float64)", "cells": len(sub), "seconds": round(t_np, 2), "build_s": "",
         "samples": samples_n, "samples_per_s": round(samples_n / t_np), "worst_rel_se": f"{rel_n:.3e}",
         "passes": "", "max_passes": "", "sampler": "stratified batches", "k_a_min": "", "k_a_max": ""},
    ]
    speedup = t_np / t_m_sub
    # Both backends stop at or below the target; an MC cell's cost scales as 1/SE^2, so the time
    # each would need to stop exactly at the target error is t * (achieved rel SE / target)^2.
    def at_target(results):
        return sum(r.seconds * (r.se / abs(r.k_a) / args.rel_se) ** 2 for r in results)
    t_np_eq, t_m_eq = at_target(nres), at_target(m_sub)
    speedup_eq = t_np_eq / t_m_eq
    hdr = f"{'backend':22} {'cells':>5} {'seconds':>8} {'samples':>12} {'samples/s':>11} {'worst relSE':>11}"
    say(hdr)
    say("-" * len(hdr))
    for r in rows:
        say(f"{r['backend']:22} {r['cells']:5d} {r['seconds']:8.2f} {r['samples']:12d} {r['samples_per_s']:11.3g} "
              f"{r['worst_rel_se']:>11}")
    say(f"scene build {t_build:.2f} s; Mitsuba passes {sum(passes)} (max {max(passes)} per cell); "
          f"k_A {rows[0]['k_a_min']} ... {rows[0]['k_a_max']}")
    say(f"speed-up on the same {len(sub)} cells at the same target error: {speedup:.1f}x "
          f"(numpy full table extrapolated: {t_np * len(cells) / len(sub):.0f} s)")
    say(f"speed-up at equal error (each cell's time scaled by (achieved rel SE / target)^2): {speedup_eq:.1f}x")
    zz = np.array(z)
    say(f"agreement Mitsuba vs numpy on those cells: fraction |z| > 2: {np.mean(zz > 2):.2f} (expected ~0.05); "
          f"cells beyond {N_SIGMA:g} SE + float32 floor {floor:g}: {beyond} of {len(m_sub)} (max |z| {zz.max():.1f})")
    say(f"targets: table < 60 s: {'yes' if t_table < 60 else 'NO'} ({t_table:.1f} s); "
          f">= 5x numpy: {'yes' if speedup >= 5 else 'NO'} ({speedup:.1f}x)")
    say(load_after())
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]) + ["speedup_vs_numpy", "speedup_equal_error", "max_abs_z",
                                                     "cells_beyond_4se_plus_floor"])
        w.writeheader()
        for r in rows:
            w.writerow({**r, "speedup_vs_numpy": f"{speedup:.2f}",
                        "speedup_equal_error": f"{speedup_eq:.2f}", "max_abs_z": f"{max(z):.2f}",
                        "cells_beyond_4se_plus_floor": beyond})
    out.with_suffix(".txt").write_text(say.text() + "\n")
    print(f"wrote {out} and {out.with_suffix('.txt')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
