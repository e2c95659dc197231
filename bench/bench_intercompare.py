"""Time of the bundled example study (studies/r3-comparison.toml) on a local Dask cluster.

    python bench/bench_intercompare.py                      # both runs, 200 realisations, 2 workers
    python bench/bench_intercompare.py --corrected 200      # every realisation corrected

Run A, raw tables: 4 participants x 200 realisations x 396 cells (the CIE tabulated region), the
comparison as declared (every participant reports its table raw), no corrections
(``corrected_realisations = 0``). Target (issue 20): within 10 minutes on 2 workers.

Run B, every participant correcting: the same study; every participant with an aperture effect
corrects its table with ``roadgonio correct --reference self`` in the first ``--corrected``
realisations (default 30: the corrected comparison is made on those; the raw one on all 200), the
study file's setting. validation.csv compares the figures of merit with the full corrections and
with a frozen correction factor (the geometric mean of those corrections' k_A) on the same
realisations: the check of that linearisation. Target: within 30 minutes on 2 workers.

Both runs start from an empty folder (nothing resumed). Prints a table and writes
bench/results/intercompare.csv and .txt, under the machine (bench/machine.py), with
os.getloadavg() before and after each run (the machine is shared: quote only runs started at a load below 0.5). ``--keep DIR`` keeps the outputs of run B
(intercompare.nc, CSVs, pictures) in DIR.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import Printout, load_after  # noqa: E402  (bench/machine.py)

TARGETS = {"raw": 600.0, "corrected": 1800.0}


def one_run(study, out: Path, workers: int) -> dict:
    from roadgonio.api import intercompare
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    run = intercompare(study, out, workers=workers, progress=sys.stderr.isatty())
    wall = time.perf_counter() - t0
    load1 = os.getloadavg()
    summary = json.loads(run.dataset.attrs["summary_json"])
    return {"wall_s": wall, "seconds": run.seconds, "load_before": load0, "load_after": load1, "summary": summary,
            "validation": json.loads(run.dataset.attrs.get("validation_json", "[]"))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--realisations", type=int, default=200)
    ap.add_argument("--corrected", type=int, default=30, help="corrected realisations per participant in run B")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--only", choices=["raw", "corrected"], help="run only one of the two")
    ap.add_argument("--keep", metavar="DIR", help="keep the outputs of run B (and of run A in DIR/raw)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "intercompare.csv"))
    args = ap.parse_args(argv)
    from roadgonio.intercomparison.study import load_study
    base = load_study("r3-comparison")
    runs = {"raw": dataclasses.replace(base, realisations=args.realisations, corrected_realisations=0),
            "corrected": dataclasses.replace(base, realisations=args.realisations,
                                             corrected_realisations=min(args.corrected, args.realisations))}
    say = Printout(f"roadgonio intercompare, bundled study r3-comparison (4 participants, 396 cells, "
                   f"{args.realisations} realisations), {args.workers} Dask workers; Python {platform.python_version()}")
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="bench-intercompare-"))
    try:
        for name, study in runs.items():
            if args.only and name != args.only:
                continue
            out = Path(args.keep) / ("raw" if name == "raw" else "") if args.keep else tmp / name
            if out.exists() and any(out.glob("intercompare_journal.jsonl")):
                (out / "intercompare_journal.jsonl").unlink()        # from scratch: nothing resumed
            r = one_run(study, out, args.workers)
            s = r["seconds"]
            allrows = {x["scenario"]: x for x in r["summary"] if x["participant"] == "ALL"}
            row = {"run": name, "realisations": study.realisations, "full_corrections": study.n_corrected,
                   "workers": args.workers, "wall_s": round(r["wall_s"], 1), "target_s": TARGETS[name],
                   "met": "yes" if r["wall_s"] <= TARGETS[name] else "NO",
                   "k_a_s": round(s.get("k_a", 0.0), 1), "corrections_s": round(s.get("corrections", 0.0), 1),
                   "realisations_s": round(s.get("realisations", 0.0), 1),
                   "statistics_s": round(s.get("statistics", 0.0), 1),
                   "load_before": "/".join(f"{v:.2f}" for v in r["load_before"]),
                   "load_after": "/".join(f"{v:.2f}" for v in r["load_after"])}
            for scen, a in allrows.items():
                if a.get("realisations"):
                    row[f"{scen}_consistent_cells"] = round(a["share_consistent_cells"], 4)
                    row[f"{scen}_all_compatible"] = round(a["share_all_compatible_weighted_mean"], 4)
            rows.append(row)
            text = (f"  run {name:<9}: {row['wall_s']:8.1f} s (target {TARGETS[name]:.0f} s: {row['met']}); "
                    f"k_A {row['k_a_s']} s, corrections {row['corrections_s']} s ({study.n_corrected} per "
                    f"participant), realisations {row['realisations_s']} s, statistics {row['statistics_s']} s; "
                    f"load {row['load_before']} -> {row['load_after']}")
            say(text)
            if name == "corrected" and r["validation"]:
                say("  frozen factor against full corrections (same realisations; difference +- its SE):")
                for v in r["validation"]:
                    if v["figure"].removesuffix("_per_realisation") in (
                            "share_En_le_1_weighted_mean", "share_consistent_cells",
                            "share_all_compatible_weighted_mean", "rms_error_vs_truth_pct"):
                        t = (f"    {v['figure']:<52} {v['participant']:<18} full {v['full_mean']:.4f}  frozen "
                             f"{v['frozen_mean']:.4f}  diff {v['difference_mean']:+.4f} +- {v['difference_se']:.4f} "
                             f"(spread of the figure over realisations: SE {v['full_mean_se']:.4f})")
                        say(t)
    finally:
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(out, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    say(load_after())
    out.with_suffix(".txt").write_text(say.text() + "\n")
    print(f"wrote {out} and {out.with_suffix('.txt')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
