"""numpy-mc on every 7th cell of the portable x R3 table at rel SE 1e-3 for a ladder of batch sizes: which
batch is numpy-mc's best at this target (bench_engine.py measures it at that batch). Prints one line per batch."""
import time
from roadgonio.engines import make_backend, full_grid_cells
from roadgonio.instrument.config import load_instrument
from roadgonio.surface.sample import resolve_sample
inst=load_instrument("portable"); model=resolve_sample("R3").model
cells=full_grid_cells()[::7]
for batch in (16, 64, 256, 1024, 4096):
    b=make_backend("numpy-mc", inst, model, rel_se=1e-3, seed=1, batch=batch, max_samples=1<<22)
    t=time.perf_counter(); r=b.compute(cells); w=time.perf_counter()-t
    print(batch, f"{w:.2f} s, table {w*580/len(cells):.1f} s, worst {max(c.se/abs(c.k_a) for c in r):.2e}, not conv {sum(not c.converged for c in r)}")
