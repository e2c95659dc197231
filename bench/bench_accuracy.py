"""Speed-accuracy trade of the k_A backends (not a test): error against a converged reference
(precise float64 quadrature) versus seconds, over a ladder of tolerances (quadrature) and a ladder
of fixed sample counts per cell (mitsuba, numpy-mc: one pass / a fixed number of batches), plus the
accuracy presets fast/default/precise of every backend as their own points, on representative cells
of the portable preset with an R3-like model (the hardest specular cells included), plus the full
580-cell table for the quadrature. Writes bench/results/accuracy.csv and bench/results/pareto.png and prints the table.

    python bench/bench_accuracy.py [--instrument portable] [--no-mitsuba] [--no-full] [--quick]

Error of a setting = max over the cells of |k - k_ref| / k_ref (and the RMS); "claimed" = the
largest relative error/SE the backend reported. Errors below the reference's own error estimate
are not resolved (the column ref_err says how far the reference can be trusted).
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

import numpy as np

from roadgonio.instrument.config import load_instrument
from roadgonio.engines import full_grid_cells, make_backend
from roadgonio.surface.model import RoadModel, RoadParams

#: R3-like model: least-squares fit of the power variant to CIE R3 (RMS 3.9 % of max r); the same
#: numbers as tests/unit/test_quadrature.py::R3LIKE.
R3LIKE = dict(k_diff=0.028937, k_phong=1.8147, n_phong=34.467, k_retro=0.052577, n_retro=11.307,
              k_exp=0.088927, p=2.137, h=0.49843, mu=0.03123)
#: Representative cells: specular peak (tan 4-12, beta 0-10), mid, tan 0 and beta 180.
CELLS = [(12.0, 0.0), (12.0, 2.0), (8.0, 10.0), (4.0, 2.0), (1.0, 90.0), (0.0, 0.0), (2.0, 180.0)]
#: Fixed sample budgets per cell: Mitsuba one pass of this many samples (16 replicates of a lattice
#: of samples/16 points); numpy-mc batch sizes (m^2) with 8 batches.
MITSUBA_BUDGETS = [256, 1024, 4096, 16384, 65536, 262144, 1 << 20, 1 << 22]
NUMPY_BATCHES = [16 ** 2, 32 ** 2, 64 ** 2, 128 ** 2, 256 ** 2]
OUT = Path(__file__).resolve().parent / "results"
FIELDS = ["backend", "setting", "value", "scope", "cells", "seconds", "max_rel_err", "rms_rel_err",
          "max_claimed", "not_converged", "samples", "ref_err"]


def precision(r) -> float:
    """The claimed relative precision of a cell: its error bound (quadrature) or standard error."""
    return (r.error_bound if r.deterministic else r.se) / abs(r.k_a)


def run_setting(backend, cells, ref):
    t0 = time.perf_counter()
    res = backend.compute(cells)
    sec = time.perf_counter() - t0
    rel = np.array([abs(r.k_a - ref[(r.tan_eps, r.beta_deg)].k_a) / ref[(r.tan_eps, r.beta_deg)].k_a
                    for r in res])
    claimed = max(precision(r) for r in res)
    notconv = sum(1 for r in res if not r.converged)
    return sec, float(rel.max()), float(np.sqrt(np.mean(rel ** 2))), claimed, notconv, sum(r.samples for r in res)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--instrument", default="portable")
    ap.add_argument("--no-mitsuba", action="store_true")
    ap.add_argument("--no-numpy-mc", action="store_true")
    ap.add_argument("--no-full", action="store_true", help="skip the full-table quadrature runs")
    ap.add_argument("--quick", action="store_true", help="shorter ladders")
    args = ap.parse_args(argv)
    inst = load_instrument(args.instrument)
    model = RoadModel(RoadParams(**R3LIKE), name="R3-like")
    rows = []

    print(f"reference: quadrature rtol 1e-7 on {len(CELLS)} cells of {inst.name} ...", file=sys.stderr)
    refb = make_backend("quadrature", inst, model, rtol=1e-7, max_evals=12_000_000)
    t0 = time.perf_counter()
    ref = {(r.tan_eps, r.beta_deg): r for r in refb.compute(CELLS)}
    ref_err = max(precision(r) for r in ref.values())
    print(f"  {time.perf_counter() - t0:.1f} s, reference error <= {ref_err:.1e}", file=sys.stderr)

    # the presets of the backends compared, as the registry holds them (roadgonio.engines.accuracy,
    # which this script read, became the registry's BackendInfo.presets)
    from roadgonio.engines.registry import BACKENDS, PRESETS
    ACCURACY = {p: {name: dict(BACKENDS[name].presets[p]) for name in ("quadrature", "mitsuba", "numpy-mc")}
                for p in PRESETS}
    # (backend, setting name, value, backend settings); "preset" rows are the accuracy presets
    ladder = [("quadrature", "rtol", v, {"rtol": v})
              for v in ([1e-2, 1e-3, 1e-4, 1e-5] if args.quick else [1e-2, 1e-3, 3e-4, 1e-4, 1e-5, 1e-6])]
    if not args.no_mitsuba:
        from roadgonio.engines.mitsuba import set_variant
        set_variant()
        budgets = MITSUBA_BUDGETS[:4] if args.quick else MITSUBA_BUDGETS
        # rel_se 0.5 with min_passes 1: exactly one pass of that many samples per cell
        ladder += [("mitsuba", "samples", n, {"rel_se": 0.5, "first_pass": n, "seed": 1}) for n in budgets]
    if not args.no_numpy_mc:
        batches = NUMPY_BATCHES[:3] if args.quick else NUMPY_BATCHES
        ladder += [("numpy-mc", "samples", 8 * m2, {"rel_se": 0.5, "batch": m2, "min_batches": 8, "seed": 1})
                   for m2 in batches]
    for preset, per_backend in ACCURACY.items():
        for name, settings in per_backend.items():
            if (name == "mitsuba" and args.no_mitsuba) or (name == "numpy-mc" and args.no_numpy_mc):
                continue
            extra = {} if name == "quadrature" else {"seed": 1}
            ladder.append((name, "preset", preset, {**settings, **extra}))
    for name, key, v, settings in ladder:
        b = make_backend(name, inst, model, **settings)
        if name == "mitsuba":      # compile outside the timing
            b.compute([CELLS[-1]])
        sec, mx, rms, claimed, nc, n = run_setting(b, CELLS, ref)
        rows.append(dict(backend=name, setting=key, value=v, scope="cells", cells=len(CELLS), seconds=sec,
                         max_rel_err=mx, rms_rel_err=rms, max_claimed=claimed, not_converged=nc, samples=n,
                         ref_err=ref_err))
        print(f"  {name:10s} {key}={v!s:<7} {sec:8.2f} s  max err {mx:.2e}  claimed {claimed:.2e}",
              file=sys.stderr, flush=True)

    if not args.no_full:
        cells = full_grid_cells()
        if not args.no_mitsuba:
            for preset_name in ACCURACY:
                b = make_backend("mitsuba", inst, model, accuracy=preset_name, seed=1)
                b.compute(cells[:2])
                t0 = time.perf_counter()
                res = b.compute(cells)
                sec = time.perf_counter() - t0
                claimed = max(precision(r) for r in res)
                nc = sum(1 for r in res if not r.converged)
                rows.append(dict(backend="mitsuba", setting="preset", value=preset_name, scope="full table",
                                 cells=len(cells), seconds=sec, max_rel_err=math.nan, rms_rel_err=math.nan,
                                 max_claimed=claimed, not_converged=nc, samples=sum(r.samples for r in res),
                                 ref_err=math.nan))
                print(f"  mitsuba full table preset={preset_name}: {sec:.2f} s, worst claimed {claimed:.1e}",
                      file=sys.stderr, flush=True)
        for rtol in ([1e-3] if args.quick else [1e-3, 1e-4]):
            b = make_backend("quadrature", inst, model, rtol=rtol)
            t0 = time.perf_counter()
            res = b.compute(cells)
            sec = time.perf_counter() - t0
            claimed = max(precision(r) for r in res)
            nc = sum(1 for r in res if not r.converged)
            rows.append(dict(backend="quadrature", setting="rtol", value=rtol, scope="full table", cells=len(cells),
                             seconds=sec, max_rel_err=math.nan, rms_rel_err=math.nan, max_claimed=claimed,
                             not_converged=nc, samples=sum(r.samples for r in res), ref_err=math.nan))
            print(f"  full table rtol={rtol:g}: {sec:.1f} s, {nc} cells not converged, worst claimed {claimed:.1e}",
                  file=sys.stderr, flush=True)

    OUT.mkdir(parents=True, exist_ok=True)
    with open(OUT / "accuracy.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})

    import os
    print(f"\nk_A speed-accuracy, {inst.name} preset, R3-like model, {len(CELLS)} cells (reference: quadrature "
          f"rtol 1e-7, its error <= {ref_err:.1e}); load {os.getloadavg()}")
    print(f"{'backend':10s} {'setting':>16s} {'scope':>10s} {'seconds':>8s} {'max err':>9s} {'rms err':>9s} "
          f"{'claimed':>9s} {'not conv':>8s} {'samples':>10s}")
    for r in rows:
        print(f"{r['backend']:10s} {r['setting'] + '=' + format(r['value'], 'g' if not isinstance(r['value'], str) else ''):>16s} {r['scope']:>10s} "
              f"{r['seconds']:8.2f} {r['max_rel_err']:9.2e} {r['rms_rel_err']:9.2e} {r['max_claimed']:9.2e} "
              f"{r['not_converged']:8d} {r['samples']:10.3g}")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7.5, 5.2))
    marks = {"quadrature": "o-", "mitsuba": "s-", "numpy-mc": "^-"}
    for name in ("quadrature", "mitsuba", "numpy-mc"):
        rr = [r for r in rows if r["backend"] == name and r["scope"] == "cells" and r["setting"] != "preset"]
        pp = [r for r in rows if r["backend"] == name and r["setting"] == "preset" and r["scope"] == "cells"]
        if not rr:
            continue
        line, = ax.loglog([r["seconds"] for r in rr], [max(r["max_rel_err"], 1e-9) for r in rr], marks[name],
                          label=f"{name} ({'rtol' if name == 'quadrature' else 'samples per cell'})")
        for r in rr:
            txt = f"{r['value']:g}" if name == "quadrature" else f"{r['value'] / 1024:.0f}k"
            ax.annotate(txt, (r["seconds"], max(r["max_rel_err"], 1e-9)), fontsize=7, xytext=(4, 3),
                        textcoords="offset points")
        for r in pp:
            ax.loglog(r["seconds"], max(r["max_rel_err"], 1e-9), "*", ms=13, color=line.get_color(), mec="k", mew=0.6)
            dy = -10 - 9 * list(ACCURACY).index(r["value"])   # presets on one point stay legible
            ax.annotate(r["value"], (r["seconds"], max(r["max_rel_err"], 1e-9)), fontsize=8, xytext=(5, dy),
                        textcoords="offset points", color=line.get_color(), weight="bold")
    ax.axhline(ref_err, color="0.6", ls=":", lw=1, label=f"reference error {ref_err:.0e}")
    ax.set_xlabel(f"seconds for {len(CELLS)} cells (2-core machine)")
    ax.set_ylabel("max relative error of k_A vs reference")
    ax.set_title(f"k_A speed-accuracy: {inst.name} preset, R3-like model, {len(CELLS)} cells\n"
                 "(stars: the --accuracy presets fast / default / precise)",
                 fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "pareto.png", dpi=120)
    print(f"wrote {OUT / 'accuracy.csv'} and {OUT / 'pareto.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
