"""numpy-mc on every 7th cell of the portable x R3 table at rel SE 1e-3 for a ladder of batch sizes: which
batch is numpy-mc's best at this target (bench_engine.py measures it at that batch). Prints one line per batch
(batch, seconds on the cells, extrapolated to 580, worst rel SE, cells not converged) under the machine and
the load average, and writes the printed lines to bench/results/numpy_batch_sweep.txt (``--out`` elsewhere).

    python bench/numpy_batch_sweep.py [--out TXT]
"""
import argparse
import time
from pathlib import Path

from machine import Printout, load_after  # bench/machine.py (the script's folder is on sys.path)

from roadgonio.engines import full_grid_cells, make_backend
from roadgonio.instrument.config import load_instrument
from roadgonio.surface.sample import resolve_sample

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "numpy_batch_sweep.txt"))
args = ap.parse_args()
inst = load_instrument("portable")
model = resolve_sample("R3").model
cells = full_grid_cells()[::7]
say = Printout(f"numpy_batch_sweep: numpy-mc, portable x R3, rel SE 1e-3, {len(cells)} cells (every 7th); "
               "batch, seconds on those cells, extrapolated to 580, worst rel SE")
for batch in (16, 64, 256, 1024, 4096):
    b = make_backend("numpy-mc", inst, model, rel_se=1e-3, seed=1, batch=batch, max_samples=1 << 22)
    t = time.perf_counter()
    r = b.compute(cells)
    w = time.perf_counter() - t
    say(f"{batch} {w:.2f} s, table {w * 580 / len(cells):.1f} s, worst {max(c.se / abs(c.k_a) for c in r):.2e}, "
        f"not conv {sum(not c.converged for c in r)}")
say(load_after())
Path(args.out).write_text(say.text() + "\n")
print(f"wrote {args.out}")
