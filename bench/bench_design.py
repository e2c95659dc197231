"""Design throughput: full k_A tables per hour in this process and on a local Dask cluster of 1 and 2
worker processes, and Dask's per-task overhead.

    python bench/bench_design.py                  # 6 design points x 580 cells, default accuracy, 3 rounds
    python bench/bench_design.py --points 4 --cells 12:0,4:2,0:0 --accuracy fast   # a quick look

The design family is the portable preset with the source radius and the pupil varied around it
(every point a full instrument, sample R3, Mitsuba backend). The three runs compute the same
tables with the same seeds; the script checks that their k_A are identical. ``--repeats`` rounds of
the three runs, one after the other; the speed-up from 1 to 2 workers is the median of the rounds'
ratios with their range. Prints a table under
the machine and the load average, with os.getloadavg() beside every row (the machine is shared),
and writes bench/results/design.csv and the printed table as design.txt (``--out`` elsewhere).
"""
from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path

import numpy as np
from machine import Printout, load_after  # bench/machine.py (the script's folder is on sys.path)


def _noop(x):
    return x


def dask_overhead(n_tasks: int = 400) -> dict:
    """Round trip of trivial tasks on a 2-process local cluster: seconds per task."""
    from roadgonio.engines.cluster import open_client
    with open_client(2, backend=None) as c:
        c.gather(c.map(_noop, range(20), pure=False))          # warm up
        t0 = time.perf_counter()
        c.gather(c.map(_noop, range(n_tasks), pure=False))
        bulk = (time.perf_counter() - t0) / n_tasks
        t0 = time.perf_counter()
        for k in range(50):
            c.submit(_noop, k, pure=False).result()
        serial = (time.perf_counter() - t0) / 50
    return {"bulk_s_per_task": bulk, "roundtrip_s_per_task": serial}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=6, help="design points (default 6)")
    ap.add_argument("--cells", default="all", help="cells per table (default all = 580)")
    ap.add_argument("--accuracy", default="default", help="accuracy preset (default 'default')")
    ap.add_argument("--repeats", type=int, default=3,
                    help="rounds of (in-process, 1 worker, 2 workers), one after the other (default 3): the "
                         "speed-up is the median of the rounds' ratios, with their range (one round moved "
                         "1.59-1.78x on an idle 2-core machine, session 38)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "design.csv"))
    args = ap.parse_args(argv)

    from roadgonio.api import design_study as run_design      # the one way in (roadgonio.design exports no run_design)
    from roadgonio.engines.mitsuba import set_variant
    set_variant("llvm_ad_rgb")
    n_r = max(1, args.points // 2)
    n_p = max(1, args.points // n_r)
    # one value of a key is LO = HI (the grid's rule)
    vary = [f"source.radius_m=0.015:0.03:{n_r}" if n_r > 1 else "source.radius_m=0.02:0.02:1",
            f"detector.pupil_radius_m=0.003:0.005:{n_p}" if n_p > 1 else "detector.pupil_radius_m=0.004:0.004:1"]
    kw = dict(samples=["R3"], cells=args.cells, backend="mitsuba", accuracy=args.accuracy, seed=1,
              progress=False, plots=False, tolerance="50%")
    say = Printout(f"roadgonio design throughput: portable family ({' x '.join(vary)}), sample R3, "
                   f"cells {args.cells}, accuracy {args.accuracy}")
    rows, ref = [], None
    # warm up this process (variant, plugins, first kernel) so the in-process row measures work, not start-up
    run_design("portable", None, workers=0, **{**kw, "cells": "4:2"})
    from roadgonio.engines.cluster import open_client
    rounds = [(rep, label, workers) for rep in range(max(1, args.repeats))
              for label, workers in (("in-process", 0), ("dask 1 worker", 1), ("dask 2 workers", 2))]
    for rep, label, workers in rounds:
        t_start = time.perf_counter()
        with open_client(workers) as client:
            # warm every worker (variant, plugins, first kernels): measured as start-up, not throughput
            if client is not None:
                run_design("portable", [f"source.radius_m=0.02:0.025:{2 * workers}"], client=client,
                           **{**kw, "cells": "4:2"})
            startup = time.perf_counter() - t_start
            load0 = os.getloadavg()
            t0 = time.perf_counter()
            ds = run_design("portable", vary, client=client, workers=0, **kw)
            wall = time.perf_counter() - t0
            load1 = os.getloadavg()
        tables = int(ds.attrs["tables_computed"])
        cells = int(np.isfinite(ds["k_a"].values).sum())
        task_s = float(ds["seconds"].values.sum())
        k = ds["k_a"].values
        same = "reference" if ref is None else ("yes" if np.array_equal(ref, k, equal_nan=True) else "NO")
        ref = k if ref is None else ref
        rows.append({"run": label, "round": rep + 1, "workers": workers, "tables": tables,
                     "cells_per_table": cells // max(tables, 1),
                     "wall_s": wall, "startup_s": startup, "sum_task_s": task_s,
                     "tables_per_hour": 3600 * tables / wall, "identical_k_a": same,
                     "overhead_s_per_task": (wall * max(workers, 1) - task_s) / tables,
                     "load_before": " ".join(f"{v:.2f}" for v in load0),
                     "load_after": " ".join(f"{v:.2f}" for v in load1)})
    for r in rows:          # against the 1-worker run of the same round
        base1 = next(q for q in rows if q["workers"] == 1 and q["round"] == r["round"])["tables_per_hour"]
        r["speedup_vs_1_worker"] = r["tables_per_hour"] / base1
    load0 = os.getloadavg()
    ov = dask_overhead()
    load1 = os.getloadavg()

    cols = ["run", "round", "tables", "cells_per_table", "wall_s", "startup_s", "tables_per_hour",
            "speedup_vs_1_worker", "overhead_s_per_task", "identical_k_a", "load_before", "load_after"]
    widths = [max(len(c), 14) for c in cols]
    say("  ".join(c.ljust(w) for c, w in zip(cols, widths)))
    for r in rows:
        say("  ".join((f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c])).ljust(w) for c, w in zip(cols, widths)))
    for label in ("in-process", "dask 1 worker", "dask 2 workers"):
        mine = [r for r in rows if r["run"] == label]
        rate = sorted(r["tables_per_hour"] for r in mine)
        sp = sorted(r["speedup_vs_1_worker"] for r in mine)
        say(f"{label}: median {float(np.median(rate)):.4g} tables/hour over {len(mine)} round(s); speed-up vs 1 "
            f"worker median {float(np.median(sp)):.3g} (range {sp[0]:.3g} ... {sp[-1]:.3g})")
    say(f"Dask per-task overhead (no-op tasks, 2 workers): bulk map {ov['bulk_s_per_task'] * 1e3:.2f} ms/task, "
        f"one-at-a-time round trip {ov['roundtrip_s_per_task'] * 1e3:.2f} ms/task; load "
        f"{' '.join(f'{v:.2f}' for v in load0)} -> {' '.join(f'{v:.2f}' for v in load1)}")
    say(load_after())
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]) + ["noop_bulk_ms", "noop_roundtrip_ms", "accuracy", "cells",
                                                         "created"])
        w.writeheader()
        for r in rows:
            w.writerow({**r, "noop_bulk_ms": ov["bulk_s_per_task"] * 1e3,
                        "noop_roundtrip_ms": ov["roundtrip_s_per_task"] * 1e3, "accuracy": args.accuracy,
                        "cells": args.cells, "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
    out.with_suffix(".txt").write_text(say.text() + "\n")     # the table as printed (design.txt was hand-pasted)
    print(f"wrote {out} and {out.with_suffix('.txt')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
