"""Benchmark of ``roadgonio uncertainty`` (issue 5 targets), measured side by side in one run.

* no aperture effect: 50,000 Monte Carlo trials of the full table (the 396 tabulated cells of the
  CIE tables, and the 580-cell grid), statistics included (target: < 5 s);
* aperture effect: 10,000 trials with the validated k_A surrogate, the exact k_A evaluations of the
  surrogate's design and of its held-out validation trials included, with the surrogate's own error
  against the held-out exact evaluations.

What is timed is the computation alone, ``run_uncertainty`` called inside this process (no start-up,
no files, no pictures), and each row's ``target`` says which target it is held to: issue 5's
"computation < 5 s" without the aperture effect and "computation < 10 min" with it. That is not the
run bench/bench_engine.py times: the whole ``roadgonio uncertainty`` command in a fresh process
(aperture, 10,000 trials, CLI defaults), against issue 9's "whole process <= 15 s".

Sample: CIE R3 fitted on the fly (roadgonio.surface.sample); instrument: the bundled portable preset.
Prints a table under the machine and the load average and writes bench/results/uncertainty.csv and
the printed table as uncertainty.txt (``--out`` elsewhere). Usage::

    python bench/bench_uncertainty.py [--quick] [--backend mitsuba|quadrature] [--no-aperture]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from machine import Printout, load_after, write_rows  # bench/machine.py (the script's folder is on sys.path)

SPEC = ("alpha_deg=0.01,eps_deg=0.05:rect,beta_deg=0.1,tilt_x_deg=0.02,tilt_y_deg=0.02,"
        "source_distance_m=0.002,detector_distance_m=0.005")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer trials (smoke test, not the targets)")
    ap.add_argument("--backend", default="mitsuba", choices=["mitsuba", "quadrature"])
    ap.add_argument("--rel-se", type=float, default=None, help="backend tolerance (default 3e-3 mitsuba, 1e-4 quadrature)")
    ap.add_argument("--no-aperture", action="store_true", help="only the no-aperture rows")
    ap.add_argument("--sample", default="R3")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "uncertainty.csv"))
    args = ap.parse_args()

    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.sample import resolve_sample
    from roadgonio.uncertainty import parse_sigma_spec, run_uncertainty

    model = resolve_sample(args.sample).model
    inst = load_instrument("portable")
    spec = parse_sigma_spec(SPEC)
    n_no = 5_000 if args.quick else 50_000
    n_ap = 1_000 if args.quick else 10_000
    rows = []
    say = Printout(f"bench_uncertainty: sample {args.sample} (fitted), instrument portable, SPEC {SPEC}; "
                   "computation in this process (run_uncertainty)")

    for cells in ("standard", "all"):
        t = time.perf_counter()
        res = run_uncertainty(model, inst, spec, trials=n_no, seed=1, cells=cells, aperture=False, progress=False)
        dt = time.perf_counter() - t
        c = res.cases["no_aperture"]
        n = len(res.cells)
        rows.append({"case": "no_aperture", "cells": n, "trials": n_no, "backend": "-", "seconds": dt,
                     "seconds_exact_ka": 0.0, "seconds_mc": res.seconds["monte_carlo"],
                     "seconds_stats": res.seconds["statistics"], "target_s": 5.0,
                     "target": "issue 5: computation < 5 s",
                     "u_rel_median_pct": 100 * float(np.median(c.mc["u"][:n] / c.mc["mean"][:n])),
                     "sur_err_max_pct": "", "sur_err_rms_pct": "", "sur_err_over_u_max": "",
                     "backend_rel_u_max": ""})

    if not args.no_aperture:
        if args.backend == "mitsuba":
            from roadgonio.engines.mitsuba import set_variant
            set_variant()              # the script is the entry point: it chooses the variant
        settings = {"rel_se": args.rel_se or 3e-3, "seed": 0} if args.backend == "mitsuba" else {"rtol": args.rel_se or 1e-4}
        t = time.perf_counter()
        res = run_uncertainty(model, inst, spec, trials=n_ap, seed=1, cells="standard", aperture=True,
                              backend=args.backend, backend_settings=settings, n_validation=4, progress=True)
        dt = time.perf_counter() - t
        c = res.cases["aperture"]
        n = len(res.cells)
        u_rel = c.mc["u"][:n] / np.abs(c.mc["mean"][:n])
        s = res.surrogate.summary(u_rel)
        rows.append({"case": "aperture", "cells": n, "trials": n_ap, "backend": f"{args.backend} {settings}",
                     "seconds": dt, "seconds_exact_ka": res.seconds["surrogate"],
                     "seconds_mc": res.seconds["monte_carlo"], "seconds_stats": res.seconds["statistics"],
                     "target_s": 600.0, "target": "issue 5: computation < 10 min", "u_rel_median_pct": 100 * float(np.median(u_rel)),
                     "sur_err_max_pct": 100 * s["rel_err_max"], "sur_err_rms_pct": 100 * s["rel_err_rms"],
                     "sur_err_over_u_max": s["err_over_u_max"], "backend_rel_u_max": s["backend_rel_u_max"]})

    for r in rows:
        # --quick runs fewer trials than the targets are stated for: no verdict on them
        r["pass"] = "n/a (--quick)" if args.quick else ("yes" if r["seconds"] < r["target_s"] else "NO")
    hdr = ("case", "cells", "trials", "seconds", "target_s", "target", "pass", "seconds_exact_ka", "seconds_mc",
           "seconds_stats", "u_rel_median_pct", "sur_err_max_pct", "sur_err_rms_pct", "sur_err_over_u_max",
           "backend_rel_u_max")
    say(" | ".join(hdr))
    for r in rows:
        say(" | ".join(f"{r[k]:.4g}" if isinstance(r[k], float) else str(r[k]) for k in hdr))
    say(load_after())
    out = Path(args.out)
    write_rows(out, [{k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()} for r in rows],
               say.text())
    print(f"wrote {out} and {out.with_suffix('.txt')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
