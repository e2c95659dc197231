"""Paired A/B of the housed table's launch pattern, in one process (the machine's speed drifts by
20-30 % between runs a minute apart, more than the change measured): A reads every launch's sums
back at once and computes the direct light's ratio and the stray fraction cell by cell with
``np.var`` (what the engine did before launches were deferred and those statistics vectorised),
B is the engine as it is. Tables alternate (ABBA...), the bare and the housed example, full grid,
R3, rel. SE 1e-3, seed 0; every table must give the same k_A, SE and samples (checked). Prints
its lines under the machine and the load average (bench/machine.py); writes no file.

    python bench/ab_straylight.py --pairs 15
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from machine import header, load_after  # bench/machine.py (the script's folder is on sys.path)

ROOT = Path(__file__).resolve().parents[1]
LAUNCHES = ("block_sums", "stray_sums", "light_sums", "trace_paths", "trace_detector")


def _ratio_se_one_by_one(strata):
    """The delta-method ratio and SE of one cell, stratum by stratum with np.var (A's statistics)."""
    sa = sum(float(np.sum(a)) for a, _ in strata)
    sb = sum(float(np.sum(b)) for _, b in strata)
    if not sb > 0.0:
        return math.nan, math.inf
    r, var = sa / sb, 0.0
    for a, b in strata:
        y = a - r * b
        if y.size < 2:
            return r, math.inf
        var += y.size * float(np.var(y, ddof=1))
    return r, math.sqrt(max(var, 0.0)) / abs(sb)


def _stray_ratios_one_by_one(stats):
    out = []
    for st in stats:
        rd, rd_se = _ratio_se_one_by_one(st.direct_strata())
        q, q_se = _ratio_se_one_by_one(st.stray_strata())
        out.append((rd, rd_se, 1.0 - q, q_se))
    return tuple(np.array(v) for v in zip(*out))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=15)
    args = ap.parse_args(argv)

    from roadgonio.engines import full_grid_cells
    from roadgonio.engines.mitsuba import set_variant
    set_variant()
    from roadgonio.engines.mitsuba import passes
    from roadgonio.engines.mitsuba.backend import make_backend
    from roadgonio.engines.mitsuba.plugins import ka_batch as kb
    from roadgonio.instrument.config import Instrument
    from roadgonio.surface.sample import resolve_sample

    model = resolve_sample("R3").model
    cells = full_grid_cells()
    print("\n".join(header(f"ab_straylight: launch pattern A (read at once) vs B (deferred), {args.pairs} pairs, "
                           f"{len(cells)} cells, R3, rel SE 1e-3")), flush=True)
    launches = {name: getattr(kb.KaBatch, name) for name in LAUNCHES}
    vectorised = passes.stray_ratios

    def read_at_once(f):
        def g(*a, defer=False, **k):
            r = f(*a, **k)                     # defer=False: the sums come back before the next launch
            if isinstance(r, tuple):
                return r[:-1] + (kb._Deferred(lambda v=r[-1]: v),)
            return kb._Deferred(lambda v=r: v)
        return g

    def mode(m):
        for name, f in launches.items():
            setattr(kb.KaBatch, name, f if m == "B" else read_at_once(f))
        passes.stray_ratios = vectorised if m == "B" else _stray_ratios_one_by_one

    rows = {}
    try:
        for name in ("portable", "portable_housed"):
            b = make_backend(Instrument.load(ROOT / "scenes" / f"{name}.toml"), model, rel_se=1e-3, seed=0)
            for m in "AB":
                mode(m)
                b.compute(cells)                         # warm-up (kernel cache)
            times, ref = {"A": [], "B": []}, None
            for i in range(args.pairs):
                for m in ("AB" if i % 2 == 0 else "BA"):
                    mode(m)
                    t0 = time.perf_counter()
                    res = b.compute(cells)
                    times[m].append(time.perf_counter() - t0)
                    key = [(r.k_a, r.se, r.samples) for r in res]
                    ref = key if ref is None else ref
                    if key != ref:
                        raise SystemExit(f"{name}: A and B gave different numbers")
            rows[name] = times
            d = np.array(times["A"]) - np.array(times["B"])
            print(f"{name:16s} A median {statistics.median(times['A']):.3f} s, B median "
                  f"{statistics.median(times['B']):.3f} s; A - B paired: mean {d.mean():.3f} s (SE "
                  f"{d.std(ddof=1) / math.sqrt(len(d)):.3f} s), median {np.median(d):.3f} s", flush=True)
    finally:
        mode("B")
    ratio = {m: statistics.median(rows["portable_housed"][m]) / statistics.median(rows["portable"][m]) for m in "AB"}
    print(f"housed / bare (medians): A {ratio['A']:.1f}, B {ratio['B']:.1f}; {args.pairs} pairs each")
    print(load_after())
    return 0


if __name__ == "__main__":
    sys.exit(main())
