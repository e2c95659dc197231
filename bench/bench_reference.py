"""Bench of the float64 reference (roadgonio.engines.reference) on the wide instrument
(scenes/wide.toml, R3-like model): its true error against its reported 99.9 % bound, cell by cell,
and its time per cell; beside it the tensor quadrature's true error against its own estimate.

The truth is bench/results/reference_long.csv (bench/make_reference_long.py: 32 replicates of 2^18
points from disjoint seeds) with its own 99.9 % bound ``bound_long``, printed beside it. That bound
is not negligible: relative to k_A it reaches 4.8e-5 in the stored file, 0.48 of the default target
(rtol 1e-4) and comparable to the errors it judges. So the measured error |k_ref - k_long| is the
reference's true error only to within bound_long, and each cell's verdict on "true error <= bound"
takes it into account:

* ``honest``: |k_ref - k_long| + bound_long <= bound_ref (the bound holds whatever the truth's
  error within its own bound);
* ``not honest``: |k_ref - k_long| - bound_long > bound_ref (it fails whatever the truth's error);
* ``unresolved``: neither (the truth is too uncertain to tell).

``err_resolved`` says whether the measured error itself exceeds the truth's bound (|err| >
bound_long); the worst err/bound is quoted over those cells only. Prints a table under the machine
and the load average, writes bench/results/reference_bench.csv and the printed table as
reference_bench.txt (``--out`` elsewhere).

    python bench/bench_reference.py [--no-quadrature] [--full-table] [--out CSV]

``--full-table`` also times the whole 580-cell table at the default target (rtol 1e-4) and
reports the worst bound and the cells that did not converge (reference_full_table.csv beside the
output).
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

from machine import Printout, load_after, load_average, write_rows  # noqa: E402  (bench/machine.py)

from conftest import R3LIKE  # noqa: E402  (the R3-like model of the tests)

from roadgonio.engines import full_grid_cells, make_backend  # noqa: E402
from roadgonio.instrument.config import load_instrument  # noqa: E402
from roadgonio.surface.model import RoadModel, RoadParams  # noqa: E402


def verdict(err: float, bound: float, bound_long: float) -> str:
    """Whether the reference's bound held at a cell, the truth's own bound taken into account
    (module docstring): "honest", "not honest" or "unresolved"."""
    if err + bound_long <= bound:
        return "honest"
    if err - bound_long > bound:
        return "not honest"
    return "unresolved"


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
    ap.add_argument("--out", default=str(HERE / "results" / "reference_bench.csv"))
    args = ap.parse_args(argv)
    inst = load_instrument(HERE.parent / "scenes" / "wide.toml")
    model = r3like()
    truth = list(csv.DictReader(open(args.truth)))
    ref = make_backend("reference", inst, model)                 # the defaults: rtol 1e-4, seed 0
    quad = None if args.no_quadrature else make_backend("quadrature", inst, model)   # default rtol 1e-4
    rows = []
    say = Printout(f"bench_reference: the RQMC reference on {inst.name}, R3-like, {len(truth)} cells against "
                   f"{Path(args.truth).name}; relative values below")
    say(f"{'tan':>4} {'beta':>4} {'k_long':>11} {'bnd_long':>8} | {'k_ref':>11} {'bound':>8} {'|err|':>8} "
        f"{'err/bnd':>7} {'verdict':>10} {'conv':>4} {'evals':>9} {'s':>6} | {'quad err':>8} {'q est':>8} {'q conv':>6}")
    for t in truth:
        cell = (float(t["tan_eps"]), float(t["beta_deg"]))
        k_long, b_long = float(t["k_long"]), float(t["bound_long"])
        r = ref.compute([cell])[0]
        err = abs(r.k_a - k_long)
        bound = _bound(r)
        row = {"tan_eps": cell[0], "beta_deg": cell[1], "k_long": k_long, "bound_long": b_long, "k_ref": r.k_a,
               "bound_ref": bound, "abs_err": err, "err_over_bound": err / bound,
               "err_resolved": err > b_long, "verdict": verdict(err, bound, b_long),
               "converged": r.converged, "evals": r.samples, "seconds": r.seconds, "load1": os.getloadavg()[0]}
        qtxt = ""
        if quad is not None:
            q = quad.compute([cell])[0]
            row.update({"k_quad": q.k_a, "quad_abs_err": abs(q.k_a - k_long), "quad_bound": q.error_bound,
                        "quad_converged": q.converged, "quad_seconds": q.seconds})
            qtxt = f"{abs(q.k_a - k_long) / k_long:8.1e} {q.error_bound / q.k_a:8.1e} {str(q.converged):>6}"
        rows.append(row)
        say(f"{cell[0]:4g} {cell[1]:4g} {k_long:11.8f} {b_long / k_long:8.1e} | {r.k_a:11.8f} "
            f"{bound / r.k_a:8.1e} {err / k_long:8.1e} {err / bound:7.2f} {row['verdict']:>10} {str(r.converged)[0]:>4} "
            f"{r.samples:9d} {r.seconds:6.2f} | {qtxt}")
    n = len(rows)
    counts = {v: sum(r["verdict"] == v for r in rows) for v in ("honest", "not honest", "unresolved")}
    conv = sum(r["converged"] for r in rows)
    resolved = [r for r in rows if r["err_resolved"]]
    worst = max(resolved, key=lambda r: r["err_over_bound"]) if resolved else None
    worst_txt = (f"worst err/bound {worst['err_over_bound']:.2f} at tan {worst['tan_eps']:g} / beta "
                 f"{worst['beta_deg']:g} over the {len(resolved)} cells whose error exceeds the truth's bound"
                 if worst else "no cell's error exceeds the truth's bound")
    say(f"reference, true error <= bound with the truth's own bound: {counts['honest']} honest, "
        f"{counts['not honest']} not honest, {counts['unresolved']} unresolved of {n} cells ({worst_txt}); "
        f"{conv} of {n} converged to rtol 1e-4; {sum(r['seconds'] for r in rows):.1f} s for the {n} cells "
        f"(max {max(r['seconds'] for r in rows):.1f} s)")
    if quad is not None:
        bad = [r for r in rows if r["quad_abs_err"] - r["bound_long"] > r["quad_bound"]]
        unres = [r for r in rows if r["quad_abs_err"] + r["bound_long"] > r["quad_bound"] >= r["quad_abs_err"] - r["bound_long"]]
        say(f"quadrature: {sum(not r['quad_converged'] for r in rows)} of {n} cells not converged, {len(bad)} with "
            f"true error > its estimate beyond the truth's bound, {len(unres)} unresolved (worst measured error "
            f"{max(r['quad_abs_err'] / r['k_long'] for r in rows):.1e})")
    say(load_after())
    out = Path(args.out)
    write_rows(out, rows, say.text())
    print(f"wrote {out} and {out.with_suffix('.txt')}")
    if args.full_table:
        t0 = time.perf_counter()
        res = ref.compute(full_grid_cells())
        wall = time.perf_counter() - t0
        worst_b = max(_bound(c) / c.k_a for c in res)
        nc = [(c.tan_eps, c.beta_deg) for c in res if not c.converged]
        say(f"full table (580 cells, rtol 1e-4): {wall:.0f} s wall, worst relative bound {worst_b:.2e}, "
            f"{len(nc)} not converged {nc[:6]}; {sum(c.samples for c in res)} evaluations; load average after "
            f"{load_average()}")
        out.with_suffix(".txt").write_text(say.text() + "\n")    # the printed table with the full table's line
        with out.with_name("reference_full_table.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["tan_eps", "beta_deg", "k_a", "confidence_bound", "converged", "evals", "seconds"])
            for c in res:
                w.writerow([c.tan_eps, c.beta_deg, f"{c.k_a:.9f}", f"{_bound(c):.3e}", c.converged, c.samples,
                            f"{c.seconds:.2f}"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
