"""Speed-accuracy trade of the k_A backends (not a test): error against a converged reference
(precise float64 quadrature) versus seconds, over a ladder of tolerances (quadrature) and a ladder
of fixed sample counts per cell (mitsuba, numpy-mc: one pass / a fixed number of batches), plus the
accuracy presets fast/default/precise of every backend as their own points, on representative cells
of the portable preset with an R3-like model (the hardest specular cells included), plus the full
580-cell table for the quadrature. Writes bench/results/accuracy.csv, the printed table as
bench/results/accuracy.txt and bench/results/pareto.png.

    python bench/bench_accuracy.py [--instrument portable] [--no-mitsuba] [--no-full] [--quick]

Error of a setting = max over the cells of |k - k_ref| / k_ref (and the RMS). What the backend
claimed, the largest relative value over the cells, one kind per column (NaN where the backend
claims none of that kind; the kinds are never mixed):

* ``claimed_se``: a standard error (Monte Carlo backends);
* ``claimed_estimate``: the quadrature's error estimate (``CellResult.error_bound`` of a result
  without SE; an estimate of the error of the next coarser rules, not a guaranteed bound:
  roadgonio/engines/quadrature.py);
* ``claimed_bound``: a deterministic bound beside a standard error (eta's, under absolute
  calibration).

The reference is itself a quadrature (rtol 1e-7): ``ref_err`` is its largest relative error
estimate. A cell's error is resolved only where it exceeds the reference's own estimate at that
cell; ``resolved`` counts those cells, and the error/claim ratios (``max_err_over_se``, a z;
``max_err_over_estimate``: below 1 means the estimate held, its inverse how conservative it was)
are taken over the resolved cells only (NaN where none is resolved: an error that small says
nothing about the claim).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from machine import Printout, load_after, write_rows  # bench/machine.py (the script's folder is on sys.path)

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
#: the kinds of claimed precision, one column each (module docstring)
KINDS = ("se", "estimate", "bound")


def claims(r) -> dict[str, float]:
    """The claimed relative precision of a cell by kind (NaN where it has none of that kind): its
    standard error, its quadrature error estimate (a result without SE), its deterministic bound
    beside an SE."""
    k = abs(r.k_a)
    has_se, has_eb = math.isfinite(r.se), math.isfinite(r.error_bound)
    return {"se": r.se / k if has_se else math.nan,
            "estimate": r.error_bound / k if (has_eb and not has_se) else math.nan,
            "bound": r.error_bound / k if (has_eb and has_se) else math.nan}


def worst_claims(res) -> dict[str, float]:
    """The largest claim of each kind over the cells (NaN where no cell claims that kind)."""
    out = {}
    for kind in KINDS:
        v = [c[kind] for c in map(claims, res) if math.isfinite(c[kind])]
        out[f"claimed_{kind}"] = max(v) if v else math.nan
    return out


def ref_estimate(r) -> float:
    """The reference's relative error estimate at its cell (it is a quadrature)."""
    return r.error_bound / abs(r.k_a)


def run_setting(backend, cells, ref):
    t0 = time.perf_counter()
    res = backend.compute(cells)
    sec = time.perf_counter() - t0
    rel, resolved, over = [], 0, {"se": [], "estimate": []}
    for r in res:
        rf = ref[(r.tan_eps, r.beta_deg)]
        e = abs(r.k_a - rf.k_a) / rf.k_a
        rel.append(e)
        if e > ref_estimate(rf):         # resolved: the error exceeds the reference's own estimate
            resolved += 1
            c = claims(r)
            for kind in over:
                if math.isfinite(c[kind]) and c[kind] > 0:
                    over[kind].append(e / c[kind])
    rel = np.array(rel)
    notconv = sum(1 for r in res if not r.converged)
    return dict(seconds=sec, max_rel_err=float(rel.max()), rms_rel_err=float(np.sqrt(np.mean(rel ** 2))),
                **worst_claims(res), resolved=resolved,
                max_err_over_se=max(over["se"]) if over["se"] else math.nan,
                max_err_over_estimate=max(over["estimate"]) if over["estimate"] else math.nan,
                not_converged=notconv, samples=sum(r.samples for r in res))


def claimed_text(r) -> str:
    """A row's claims for the progress lines, each with its kind."""
    return ", ".join(f"claimed {kind} {r['claimed_' + kind]:.2e}" for kind in KINDS
                     if math.isfinite(r["claimed_" + kind])) or "no claim"


def full_table_row(backend, setting, value, cells, sec, res) -> dict:
    """A full-table run: no reference there, so no error and no error/claim ratio (NaN)."""
    return dict(backend=backend, setting=setting, value=value, scope="full table", cells=len(cells), seconds=sec,
                max_rel_err=math.nan, rms_rel_err=math.nan, **worst_claims(res), resolved=math.nan,
                max_err_over_se=math.nan, max_err_over_estimate=math.nan,
                not_converged=sum(1 for r in res if not r.converged), samples=sum(r.samples for r in res),
                ref_err=math.nan)


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
    say = Printout(f"k_A speed-accuracy, {inst.name} preset, R3-like model, {len(CELLS)} cells "
                   "(bench/bench_accuracy.py)")

    print(f"reference: quadrature rtol 1e-7 on {len(CELLS)} cells of {inst.name} ...", file=sys.stderr)
    refb = make_backend("quadrature", inst, model, rtol=1e-7, max_evals=12_000_000)
    t0 = time.perf_counter()
    ref = {(r.tan_eps, r.beta_deg): r for r in refb.compute(CELLS)}
    ref_err = max(ref_estimate(r) for r in ref.values())
    print(f"  {time.perf_counter() - t0:.1f} s, reference error estimate <= {ref_err:.1e}", file=sys.stderr)

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
        m = run_setting(b, CELLS, ref)
        rows.append(dict(backend=name, setting=key, value=v, scope="cells", cells=len(CELLS), **m, ref_err=ref_err))
        print(f"  {name:10s} {key}={v!s:<7} {m['seconds']:8.2f} s  max err {m['max_rel_err']:.2e}  "
              f"{claimed_text(rows[-1])}", file=sys.stderr, flush=True)

    if not args.no_full:
        cells = full_grid_cells()
        if not args.no_mitsuba:
            for preset_name in ACCURACY:
                b = make_backend("mitsuba", inst, model, accuracy=preset_name, seed=1)
                b.compute(cells[:2])
                t0 = time.perf_counter()
                res = b.compute(cells)
                sec = time.perf_counter() - t0
                rows.append(full_table_row("mitsuba", "preset", preset_name, cells, sec, res))
                print(f"  mitsuba full table preset={preset_name}: {sec:.2f} s, worst {claimed_text(rows[-1])}",
                      file=sys.stderr, flush=True)
        for rtol in ([1e-3] if args.quick else [1e-3, 1e-4]):
            b = make_backend("quadrature", inst, model, rtol=rtol)
            t0 = time.perf_counter()
            res = b.compute(cells)
            sec = time.perf_counter() - t0
            rows.append(full_table_row("quadrature", "rtol", rtol, cells, sec, res))
            print(f"  full table rtol={rtol:g}: {sec:.1f} s, {rows[-1]['not_converged']} cells not converged, "
                  f"worst {claimed_text(rows[-1])}", file=sys.stderr, flush=True)

    say(f"reference: quadrature rtol 1e-7, its relative error estimate <= {ref_err:.1e}; an error is resolved "
        "where it exceeds the reference's estimate at its cell; err/SE and err/estimate over the resolved cells only")
    say(f"{'backend':10s} {'setting':>16s} {'scope':>10s} {'seconds':>8s} {'max err':>9s} {'rms err':>9s} "
        f"{'claim SE':>9s} {'claim est':>9s} {'claim bnd':>9s} {'resolved':>8s} {'err/SE':>7s} {'err/est':>7s} "
        f"{'not conv':>8s} {'samples':>10s}")

    def g(v, spec):
        return format(v, spec) if isinstance(v, (int, float)) and math.isfinite(v) else "-"
    for r in rows:
        setting = r['setting'] + '=' + format(r['value'], 'g' if not isinstance(r['value'], str) else '')
        resolved = f"{r['resolved']}/{r['cells']}" if r["scope"] == "cells" else "-"
        say(f"{r['backend']:10s} {setting:>16s} {r['scope']:>10s} {r['seconds']:8.2f} {g(r['max_rel_err'], '9.2e'):>9s} "
            f"{g(r['rms_rel_err'], '9.2e'):>9s} {g(r['claimed_se'], '9.2e'):>9s} {g(r['claimed_estimate'], '9.2e'):>9s} "
            f"{g(r['claimed_bound'], '9.2e'):>9s} {resolved:>8s} {g(r['max_err_over_se'], '7.2f'):>7s} "
            f"{g(r['max_err_over_estimate'], '7.2f'):>7s} {r['not_converged']:8d} {r['samples']:10.3g}")
    say(load_after())
    write_rows(OUT / "accuracy.csv", [{k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()}
                                       for r in rows], say.text())

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
    ax.axhline(ref_err, color="0.6", ls=":", lw=1, label=f"reference error estimate {ref_err:.0e}")
    ax.set_xlabel(f"seconds for {len(CELLS)} cells (2-core machine)")
    ax.set_ylabel("max relative error of k_A vs reference")
    ax.set_title(f"k_A speed-accuracy: {inst.name} preset, R3-like model, {len(CELLS)} cells\n"
                 "(stars: the --accuracy presets fast / default / precise)",
                 fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "pareto.png", dpi=120)
    print(f"wrote {OUT / 'accuracy.csv'}, {OUT / 'accuracy.txt'} and {OUT / 'pareto.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
