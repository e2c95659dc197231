"""Long randomised-QMC runs of k_A on the wide instrument (scenes/wide.toml, R3-like model): the
"truth" that bench/bench_reference.py measures the reference's error against.

Each cell is computed with the reference integrator (roadgonio.engines.reference) at a fixed, much
larger budget than the default (32 replicates of 2^18 scrambled Sobol' points, a map trained on
5 x 2^15 pilot points, 128 bins), from seed streams disjoint from the defaults (seed 900001), so its
errors are independent of the runs it judges; its own 99.9 % confidence bound is written beside it
(``bound_long``). That bound is not negligible: relative to k_A it reaches 4.8e-5 in the stored
file, 0.48 of the default target (1e-4), so bench_reference.py judges with it. Writes
bench/results/reference_long.csv and the printed table as reference_long.txt (under the machine and
the load average). Runs for about 30-60 minutes on the loaded 2-core machine.

    python bench/make_reference_long.py [--cells 12:0,4:2 ...]
"""
from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from conftest import R3LIKE  # noqa: E402  (the R3-like model of the tests)

from roadgonio.engines.reference import make_backend  # noqa: E402
from roadgonio.engines.cells import select_cells as parse_cells  # noqa: E402
from roadgonio.instrument.config import load_instrument  # noqa: E402
from roadgonio.surface.model import RoadModel, RoadParams  # noqa: E402

from machine import Printout, load_after  # noqa: E402  (bench/machine.py)


def r3like() -> RoadModel:
    return RoadModel(RoadParams(**R3LIKE), name="R3-like")

#: The bench cells: the strong-aperture corner (beta 0-10, tan eps 2-12) where the quadrature fails,
#: and easy cells elsewhere in the table.
BENCH_CELLS = ("12:0,12:2,12:5,12:10,10:0,10:2,8:0,8:2,8:5,5:0,5:2,5:10,3.5:0,3.5:2,2:0,2:5,1:0,"
               "0:0,1:45,2:90,4:180,12:180,6:30,12:60")
LONG = dict(replicates=32, min_log2=18, max_log2=18, rtol=1e-12, max_evals=10 ** 12, seed=900001,
            pilot_iterations=5, pilot_points=1 << 15, map_bins=128)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default=BENCH_CELLS)
    ap.add_argument("--out", default=str(HERE / "results" / "reference_long.csv"))
    args = ap.parse_args(argv)
    inst = load_instrument(HERE.parent / "scenes" / "wide.toml")
    ref = make_backend(inst, r3like(), **LONG)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    say = Printout(f"make_reference_long: the RQMC reference at {LONG} on {inst.name}, R3-like")
    say(f"{'tan eps':>7} {'beta':>5} {'k_long':>12} {'bound':>9} {'evals':>11} {'s':>7}  load")
    for cell in parse_cells(args.cells):
        r = ref.compute([cell])[0]
        load = os.getloadavg()
        bound = r.confidence_bound     # the reference's 99.9 % bound (its error_bound is NaN since the split)
        rows.append({"tan_eps": r.tan_eps, "beta_deg": r.beta_deg, "k_long": f"{r.k_a:.10f}",
                     "bound_long": f"{bound:.3e}", "replicate_se": f"{r.extra['replicate_se']:.3e}",
                     "evals": r.samples, "seconds": f"{r.seconds:.1f}", "load1": f"{load[0]:.2f}"})
        say(f"{r.tan_eps:7g} {r.beta_deg:5g} {r.k_a:12.9f} {bound / r.k_a:9.2e} {r.samples:11d} "
            f"{r.seconds:7.1f}  {load[0]:.2f}")
        with out.open("w", newline="") as f:       # rewritten after every cell: a partial run keeps its cells
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    say(f"{load_after()}; {time.strftime('%Y-%m-%d %H:%M')}")
    out.with_suffix(".txt").write_text(say.text() + "\n")
    print(f"wrote {out} and {out.with_suffix('.txt')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
