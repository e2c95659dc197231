"""Benchmark: fit every bundled CIE table with every fitted model variant, side by side.

Prints (table, variant, max %, RMS %, seconds, paper target met?, beats the task's plain fit?,
beats this run's plain fit?) under the machine and load average, and writes bench/results/fit.csv
(with the fitted parameters; n_beta is used by "smooth" only) and the printed table as fit.txt.
Deviations in % of the table's max r (the paper's statistic). Both "beats" columns are strict: RMS
and max both below the plain least-squares fit of the paper's model ("power"):

* "task target": the plain fit's numbers quoted in the task statement (``PLAIN_FIT``, given to
  0.1 %), the issue's stated target;
* "this run": the ``power`` rows this run fitted itself, side by side (empty where ``power`` is not
  among ``--variants``, and for the ``power`` rows themselves).

    python bench/bench_fit.py [--variants power,smooth] [--seed 0]
"""
from __future__ import annotations

import argparse
import platform
import sys
from pathlib import Path

from machine import Printout, load_after, write_rows  # bench/machine.py (the script's folder is on sys.path)

from roadgonio._version import __version__
from roadgonio.surface.fit import fit_table, max_weight
from roadgonio.surface.rtable import BUNDLED, bundled_table

#: paper: max within 9 %, RMS within 2.6 % of max r on R1, C2, R3, R4
PAPER_TABLES = ("R1", "C2", "R3", "R4")
PAPER_MAX, PAPER_RMS = 9.0, 2.6
#: plain global least-squares fit of the "power" model (task statement; the issue's stated target): RMS, max
PLAIN_FIT = {"R1": (1.5, 6.4), "R2": (2.8, 9.6), "R3": (3.9, 12.2), "R4": (5.0, 19.8), "C1": (1.1, 3.9),
             "C2": (3.1, 9.1)}


def beats_words(r, rms: float, mx: float) -> tuple[bool, str]:
    """Whether a fit beats a plain fit of that RMS and max (strictly, both), and the words."""
    beats = r.rms_dev_pct < rms and r.max_dev_pct < mx
    return beats, "yes" if beats else ("max only" if r.max_dev_pct < mx else
                                       ("RMS only" if r.rms_dev_pct < rms else "NO"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default="power,smooth")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "fit.csv"))
    args = ap.parse_args(argv)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    rows = []
    say = Printout(f"bench_fit: every bundled CIE table x variants {','.join(variants)}, seed {args.seed}; "
                   f"roadgonio {__version__}, python {platform.python_version()}")
    hdr = (f"{'table':5} {'variant':8} {'max %':>7} {'RMS %':>7} {'sec':>6}  {'paper target':12}  "
           f"{'beats plain fit: task target':28}  {'beats plain fit: this run':25}")
    say(hdr)
    say("-" * len(hdr))
    for name in BUNDLED:
        t = bundled_table(name)
        fits = {}
        if "power" in variants:          # this run's plain fit first, to compare the others with it
            fits["power"] = fit_table(t, "power", seed=args.seed)
        for v in variants:
            r = fits[v] if v in fits else fit_table(t, v, seed=args.seed)
            target = (r.max_dev_pct <= PAPER_MAX and r.rms_dev_pct <= PAPER_RMS)
            target_s = ("yes" if target else "NO") + ("" if name in PAPER_TABLES else " (n/a)")
            prms, pmax = PLAIN_FIT[name]
            beats, beats_s = beats_words(r, prms, pmax)
            plain = fits.get("power")                 # this run's plain fit (None: power not among --variants)
            own = plain if v != "power" else None     # nothing to compare the power row itself with
            own_rms, own_max = (plain.rms_dev_pct, plain.max_dev_pct) if plain is not None else (float("nan"),) * 2
            beats_own, beats_own_s = beats_words(r, own_rms, own_max) if own is not None else ("", "-")
            say(f"{name:5} {v:8} {r.max_dev_pct:7.2f} {r.rms_dev_pct:7.2f} {r.seconds:6.1f}  {target_s:12}  "
                f"{beats_s:28}  {beats_own_s:25}")
            P = r.model.params
            rows.append({"table": name, "variant": v, "max_dev_pct": f"{r.max_dev_pct:.4f}",
                         "rms_dev_pct": f"{r.rms_dev_pct:.4f}", "seconds": f"{r.seconds:.2f}",
                         "paper_target_met": int(target), "paper_table": int(name in PAPER_TABLES),
                         "task_plain_fit_rms": prms, "task_plain_fit_max": pmax,
                         "beats_task_plain_fit": int(beats),
                         "run_plain_fit_rms": f"{own_rms:.4f}", "run_plain_fit_max": f"{own_max:.4f}",
                         "beats_run_plain_fit": "" if own is None else int(beats_own),
                         "seed": args.seed, "max_weight": max_weight(v),
                         **{k: f"{getattr(P, k):.8g}" for k in
                            ("k_diff", "k_phong", "n_phong", "k_retro", "n_retro", "k_exp", "p", "h", "mu",
                             "n_beta")}})
    say(load_after())
    out = Path(args.out)
    write_rows(out, rows, say.text())
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
