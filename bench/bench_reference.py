"""Bench of the float64 reference (roadgonio.engines.reference) on the wide instrument
(scenes/wide.toml, R3-like model): its true error against its reported 99.9 % bound, cell by cell,
and its time per cell; beside it the tensor quadrature's true error against its own estimate.

The truth is bench/results/reference_long.csv (bench/make_reference_long.py: 32 replicates of 2^18
points from disjoint seeds; its own bound is printed and is far below the default target). A cell
is honest when |k_ref - k_long| <= bound_ref (+ bound_long, the truth's own uncertainty, shown
separately). Prints a table and os.getloadavg(), writes bench/results/reference_bench.csv.

    python bench/bench_reference.py [--no-quadrature] [--full-table]

``--full-table`` also times the whole 580-cell table at the default target (rtol 1e-4) and
reports the worst bound and the cells that did not converge.
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from conftest import R3LIKE  # noqa: E402  (the R3-like model of the tests)

from roadgonio.engines import full_grid_cells, make_backend  # noqa: E402
from roadgonio.instrument.config import load_instrument  # noqa: E402
from roadgonio.surface.model import RoadModel, RoadParams  # noqa: E402



def _bound(c) -> float:
    """The RQMC reference's bound: its 99.9 % confidence bound (stored as error_bound before the
    precision fields were split into error_bound and confidence_bound)."""
    cb = getattr(c, "confidence_bound", None)
    return cb if cb is not None and math.isfinite(cb) else c.error_bound

def r3like() -> RoadModel:
    return RoadModel(RoadParams(**R3LIKE), name="R3-like")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--truth", default=str(HERE / "results" / "reference_long.csv"))
    ap.add_argument("--no-quadrature", action="store_true")
    ap.add_argument("--full-table", action="store_true")
    args = ap.parse_args(argv)
    inst = load_instrument(HERE.parent / "scenes" / "wide.toml")
    model = r3like()
    truth = list(csv.DictReader(open(args.truth)))
    ref = make_backend("reference", inst, model)                 # the defaults: rtol 1e-4, seed 0
    quad = None if args.no_quadrature else make_backend("quadrature", inst, model)   # default rtol 1e-4
    rows = []
    print(f"load at start {os.getloadavg()}")
    print(f"{'tan':>4} {'beta':>4} {'k_long':>11} {'bnd_long':>8} | {'k_ref':>11} {'bound':>8} {'|err|':>8} "
          f"{'err/bnd':>7} {'conv':>4} {'evals':>9} {'s':>6} | {'quad err':>8} {'q est':>8} {'q conv':>6}", flush=True)
    for t in truth:
        cell = (float(t["tan_eps"]), float(t["beta_deg"]))
        k_long, b_long = float(t["k_long"]), float(t["bound_long"])
        r = ref.compute([cell])[0]
        err = abs(r.k_a - k_long)
        bound = _bound(r)
        row = {"tan_eps": cell[0], "beta_deg": cell[1], "k_long": k_long, "bound_long": b_long, "k_ref": r.k_a,
               "bound_ref": bound, "abs_err": err, "err_over_bound": err / bound,
               "honest": err <= bound + b_long, "honest_strict": err <= bound,
               "converged": r.converged, "evals": r.samples, "seconds": r.seconds, "load1": os.getloadavg()[0]}
        qtxt = ""
        if quad is not None:
            q = quad.compute([cell])[0]
            row.update({"k_quad": q.k_a, "quad_abs_err": abs(q.k_a - k_long), "quad_bound": q.error_bound,
                        "quad_converged": q.converged, "quad_seconds": q.seconds})
            qtxt = f"{abs(q.k_a - k_long) / k_long:8.1e} {q.error_bound / q.k_a:8.1e} {str(q.converged):>6}"
        rows.append(row)
        print(f"{cell[0]:4g} {cell[1]:4g} {k_long:11.8f} {b_long / k_long:8.1e} | {r.k_a:11.8f} "
              f"{bound / r.k_a:8.1e} {err / k_long:8.1e} {err / bound:7.2f} {str(r.converged)[0]:>4} "
              f"{r.samples:9d} {r.seconds:6.2f} | {qtxt}", flush=True)
    out = HERE / "results" / "reference_bench.csv"
    with out.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    n = len(rows)
    honest = sum(r["honest_strict"] for r in rows)
    conv = sum(r["converged"] for r in rows)
    worst = max(rows, key=lambda r: r["err_over_bound"])
    print(f"reference: {honest} of {n} cells with true error <= bound (worst err/bound {worst['err_over_bound']:.2f} at "
          f"tan {worst['tan_eps']:g} / beta {worst['beta_deg']:g}); {conv} of {n} converged to rtol 1e-4; "
          f"{sum(r['seconds'] for r in rows):.1f} s for the {n} cells "
          f"(max {max(r['seconds'] for r in rows):.1f} s); load {os.getloadavg()}")
    if quad is not None:
        bad = [r for r in rows if r["quad_abs_err"] > r["quad_bound"]]
        print(f"quadrature: {sum(not r['quad_converged'] for r in rows)} of {n} cells not converged, {len(bad)} with "
              f"true error > its estimate (worst true error {max(r['quad_abs_err'] / r['k_long'] for r in rows):.1e})")
    print(f"wrote {out}")
    if args.full_table:
        t0 = time.perf_counter()
        res = ref.compute(full_grid_cells())
        wall = time.perf_counter() - t0
        worst_b = max(_bound(c) / c.k_a for c in res)
        nc = [(c.tan_eps, c.beta_deg) for c in res if not c.converged]
        print(f"full table (580 cells, rtol 1e-4): {wall:.0f} s wall, worst relative bound {worst_b:.2e}, "
              f"{len(nc)} not converged {nc[:6]}; {sum(c.samples for c in res)} evaluations; load {os.getloadavg()}")
        with (HERE / "results" / "reference_full_table.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["tan_eps", "beta_deg", "k_a", "confidence_bound", "converged", "evals", "seconds"])
            for c in res:
                w.writerow([c.tan_eps, c.beta_deg, f"{c.k_a:.9f}", f"{_bound(c):.3e}", c.converged, c.samples,
                            f"{c.seconds:.2f}"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
