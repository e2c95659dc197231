"""From the r-table to the road: a synthetic wide-instrument measurement of CIE R3, corrected, through
the default EN 13201 layout (docs/road.md, "Measured vs corrected").

1. k_A of an instrument for the R3 model (default: the wide instrument of issue 10,
   scenes/wide.toml, Mitsuba backend; ``--instrument portable --backend quadrature`` for
   the portable preset): ``roadgonio ka --instrument I --sample R3 --backend B``.
2. The "measured" table: what that instrument reports for a true R3 surface, r_measured = k_A r_R3.
3. ``roadgonio correct --measured measured.csv --instrument I --reference R3 --backend B``: the
   corrected table and its per-cell relative uncertainty u_rel (backend error and
   reference-model spread over the two nearest CIE tables). Its standard uncertainty in the r-table
   layout is ``corrected_u.csv``, written by `correct`.
4. ``roadgonio road --table measured --table corrected --table R3 --u corrected_u.csv --correlation
   all``: the cells' correlation correct wrote (corrected_corr.csv, beside the u) and the two
   limiting cases, independent and fully correlated cells.

Prints the metrics side by side under the machine and the load average; writes
bench/results/road_measured_vs_corrected_<instrument>.csv (``_wide.csv`` by default, ``_portable.csv``
with ``--instrument portable``; the instrument file's stem) and the printed table beside it as .txt
(``--results DIR`` elsewhere).
Run: python bench/bench_road.py [--work DIR] [--trials N] [--instrument I] [--backend B] [--results DIR]
"""
from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import Printout, load_after  # noqa: E402  (bench/machine.py)


def roadgonio(*args: str) -> str:
    cmd = [sys.executable, "-m", "roadgonio", *args]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{p.stderr}")
    return p.stdout


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", default=str(ROOT / "out" / "bench-road"))
    ap.add_argument("--trials", type=int, default=20000)
    ap.add_argument("--instrument", default=str(ROOT / "scenes" / "wide.toml"))
    ap.add_argument("--backend", default="mitsuba", choices=["mitsuba", "quadrature"])
    ap.add_argument("--results", default=str(ROOT / "bench" / "results"), help="folder of the CSV and .txt")
    a = ap.parse_args()
    label = Path(a.instrument).stem if Path(a.instrument).suffix else a.instrument
    say = Printout(f"bench_road: CIE R3 measured by {label} ({a.backend}), corrected, through the default "
                   f"EN 13201 layout, {a.trials} trials")
    work = Path(a.work) / f"{label}-{a.backend}"
    # from scratch every run: `ka --out` and `correct --out` resume from their journals, so a second
    # run in the same folder timed the resumption (ka 2 s, correct 2 s instead of 3 s and 6 s)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    from roadgonio.surface.rtable import bundled_table, read_table

    t0 = time.time()
    roadgonio("ka", "--instrument", a.instrument, "--sample", "R3", "--backend", a.backend, "--out", str(work / "ka-R3"))
    t_ka = time.time() - t0
    ka = read_table(work / "ka-R3" / "ka.csv")         # k_A in the r-table layout, unscaled
    r3 = bundled_table("R3")
    k = ka.r * 1e4                                     # read_table divides by 1e4; ka.csv is unscaled
    mname = f"R3_measured_{label}"
    measured = r3.with_values(r3.r * k, name=mname, source=f"synthetic: CIE R3 x k_A({label}, R3 model, {a.backend})")
    measured.write_csv(work / f"{mname}.csv")
    t1 = time.time()
    roadgonio("correct", "--measured", str(work / f"{mname}.csv"), "--instrument", a.instrument,
              "--reference", "R3", "--backend", a.backend, "--out", str(work / "corrected"), "--no-plots")
    t_corr = time.time() - t1
    corr_csv = work / "corrected" / "corrected.csv"          # correct's outputs (docs/correction.md, Outputs)
    u_csv = work / "corrected" / "corrected_u.csv"
    u_source = "corrected_u.csv written by roadgonio correct"
    t2 = time.time()
    # each --u right after its --table (trial 7 D8; the three --u after the three tables are refused)
    out = json.loads(roadgonio("road", "--table", str(work / f"{mname}.csv"), "--table", str(corr_csv),
                               "--u", str(u_csv), "--table", "R3", "--trials", str(a.trials),
                               "--correlation", "all",       # correct's corrected_corr.csv and both limiting cases
                               "--out", str(work / "road"), "--json"))
    t_road = time.time() - t2
    say(f"k_A {label} x R3 ({a.backend}): {np.nanmin(k):.3f} ... {np.nanmax(k):.3f}; uncertainty of the corrected "
        f"table: {u_source}")
    say(f"{'table':34} {'L_av':>7} {'U_o':>6} {'U_l':>6} {'TI %':>6} class")
    rows = []
    for d in out:
        say(f"{d['table'][:34]:34} {d['L_av']:7.4f} {d['U_o']:6.4f} {d['U_l']:6.4f} {d['TI']:6.2f} {d['class']}")
        row = {k2: d[k2] for k2 in ("table", "L_av", "U_o", "U_l", "TI", "class")}
        u = d.get("uncertainty")
        if u:
            for mode in ("given", "independent", "correlated"):
                for m in ("L_av", "U_o", "U_l", "TI"):
                    row[f"u_{m}_{mode}"] = u[mode][m]["u"]
                    row[f"cov95_{m}_{mode}"] = "{:.4g}..{:.4g}".format(*u[mode][m]["coverage_interval_95"])
                row[f"P_meets_{u['target_class']}_{mode}"] = u[mode]["P_meets_target"]
                say(f"  {mode:11} u: L_av {u[mode]['L_av']['u']:.4f} [{u[mode]['L_av']['coverage_interval_95'][0]:.4f}, "
                      f"{u[mode]['L_av']['coverage_interval_95'][1]:.4f}], U_o {u[mode]['U_o']['u']:.4f}, U_l {u[mode]['U_l']['u']:.4f}, "
                      f"TI {u[mode]['TI']['u']:.3f}; P(meets {u['target_class']}) {u[mode]['P_meets_target']:.3f}")
        rows.append(row)
    m, c = out[0], out[1]
    say(f"measured -> corrected: L_av {100 * (c['L_av'] / m['L_av'] - 1):+.2f} %, U_o {c['U_o'] - m['U_o']:+.4f}, "
        f"U_l {c['U_l'] - m['U_l']:+.4f}, TI {c['TI'] - m['TI']:+.2f} points")
    say(f"time: ka {t_ka:.0f} s, correct {t_corr:.0f} s, road (with {a.trials} trials x 3) {t_road:.1f} s")
    say(load_after())
    res = Path(a.results) / f"road_measured_vs_corrected_{label}.csv"
    res.parent.mkdir(parents=True, exist_ok=True)
    keys = sorted({k2 for r in rows for k2 in r}, key=lambda s: (s not in ("table", "L_av", "U_o", "U_l", "TI", "class"), s))
    with open(res, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    res.with_suffix(".txt").write_text(say.text() + "\n")
    print(f"wrote {res} and {res.with_suffix('.txt')}")


if __name__ == "__main__":
    main()
