"""Benchmark: is the Mitsuba engine's standard error honest where few samples carry the light, and what
does the limit on the Lambert sum's own relative SE (roadgonio.engines.result.RATIO_DENOMINATOR_REL_SE_MAX)
cost? Side by side in one run, per instrument and per value of that limit (inf: no limit, as before
session 34; the module's constant is overridden for the run, which is what this script is for).

    python bench/bench_sparse_light.py                   # 200 seeds, the three instruments below
    python bench/bench_sparse_light.py --seeds 50

Instruments: the portable preset with a Gaussian beam of sigma 0.1 deg and 0.03 deg (each source point
lights the footprint only near the axis: few detector rays meet lit source samples), and the wide
preset (its grazing cells' Lambert sums vary most in the first pass of the bundled instruments).
Six cells each, R3 (fitted), target rel. SE 1e-3, seeds 0..N-1; the reference is one run at rel. SE
5e-5 (limit 0.05, seed 99991). Per row: mean z^2 over all cells and seeds (z = (k_A - ref) / hypot(SE,
SE_ref); an honest SE of 15 degrees of freedom gives about 15/13 = 1.15), the worst cell's mean z^2, the
|z| > 3 count against its expectation under Student's t of each SE's degrees of freedom, the cells with
no SE, and the mean samples per cell against the row without the limit. Prints the table and writes
bench/results/sparse_light.csv and sparse_light.txt.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from machine import header, load_after, write_rows  # bench/machine.py (the script's folder is on sys.path)

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CELLS = [(12.0, 0.0), (8.0, 0.0), (4.0, 2.0), (1.0, 30.0), (12.0, 30.0), (6.0, 10.0)]
LIMITS = (math.inf, 0.2, 0.1, 0.05)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "sparse_light.csv"))
    args = ap.parse_args(argv)

    from scipy.stats import t as student_t

    import roadgonio.engines.mitsuba.passes as passes_mod
    import roadgonio.engines.result as result_mod
    from roadgonio.engines import make_backend
    from roadgonio.engines.mitsuba import set_variant
    from roadgonio.instrument.config import Instrument
    from roadgonio.surface.sample import resolve_sample

    set_variant()                      # the script is the entry point: it chooses the variant
    model = resolve_sample("R3").model
    portable = Instrument.load(ROOT / "scenes" / "portable.toml")
    instruments = [("portable, beam sigma 0.1 deg", portable.with_changes(source={"beam_sigma_deg": 0.1})),
                   ("portable, beam sigma 0.03 deg", portable.with_changes(source={"beam_sigma_deg": 0.03})),
                   ("wide", Instrument.load(ROOT / "scenes" / "wide.toml"))]

    def set_limit(v: float) -> None:
        result_mod.RATIO_DENOMINATOR_REL_SE_MAX = v
        passes_mod.RATIO_DENOMINATOR_REL_SE_MAX = v

    lines = header(f"bench_sparse_light: {len(CELLS)} cells x {args.seeds} seeds, R3, rel SE 1e-3 against a "
                   "reference at 5e-5")
    rows = []
    for name, inst in instruments:
        set_limit(0.05)
        ref = make_backend("mitsuba", inst, model, rel_se=5e-5, seed=99991).compute(CELLS)
        k_ref = np.array([r.k_a for r in ref])
        se_ref = np.array([r.se for r in ref])
        base_samples = None
        for limit in LIMITS:
            set_limit(limit)
            z, dof, samples = [], [], []
            for s in range(args.seeds):
                res = make_backend("mitsuba", inst, model, rel_se=1e-3, seed=s).compute(CELLS)
                z.append([(r.k_a - k) / math.hypot(r.se, e) if math.isfinite(r.se) else math.nan
                          for r, k, e in zip(res, k_ref, se_ref)])
                dof.append([r.se_dof for r in res])
                samples.append([r.samples for r in res])
            z, dof, samples = np.array(z), np.array(dof), np.array(samples, dtype=np.float64)
            ok = np.isfinite(z)
            expected = float(np.sum(2.0 * student_t.sf(3.0, dof[ok])))
            mean_samples = float(samples.mean())
            base_samples = mean_samples if base_samples is None else base_samples
            rows.append({"instrument": name, "limit": limit, "mean_z2": float(np.mean(z[ok] ** 2)),
                         "worst_cell_mean_z2": float(np.nanmax(np.nanmean(z ** 2, axis=0))),
                         "beyond_3": int(np.sum(np.abs(z[ok]) > 3.0)), "beyond_3_expected": expected,
                         "no_se": int(np.sum(~ok)), "results": int(z.size), "mean_samples": mean_samples,
                         "samples_ratio": mean_samples / base_samples})
            print(f"  {name}, limit {limit:g}: mean z^2 {rows[-1]['mean_z2']:.3f}", file=sys.stderr, flush=True)
    set_limit(0.1)
    lines += [f"current limit {result_mod.RATIO_DENOMINATOR_REL_SE_MAX:g}",
              f"{'instrument':32s} {'limit':>6s} {'mean z^2':>9s} {'worst cell':>10s} {'|z|>3':>6s} {'expected':>8s} "
             f"{'no SE':>6s} {'samples':>10s} {'ratio':>6s}"]
    for r in rows:
        lines.append(f"{r['instrument']:32s} {r['limit']:6g} {r['mean_z2']:9.3f} {r['worst_cell_mean_z2']:10.2f} "
                     f"{r['beyond_3']:6d} {r['beyond_3_expected']:8.1f} {r['no_se']:6d} {r['mean_samples']:10.3e} "
                     f"{r['samples_ratio']:6.2f}")
    lines.append(load_after())
    text = "\n".join(lines)
    print(text)
    out = Path(args.out)
    write_rows(out, rows, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
