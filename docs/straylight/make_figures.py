"""Figures and tables of docs/straylight.md (the housed portable example, scenes/portable_housed.toml).

    python docs/straylight/make_figures.py            # everything (a few minutes on 2 cores)
    python docs/straylight/make_figures.py --skip-render --skip-design

Writes into docs/straylight/:

* ``stray_fraction.png``: the stray fraction of the road signal over the table, for wall
  reflectances 0.02, 0.05, 0.2 (columns) and the bundled road tables R2, R3 (rows);
* ``ka_change.png``: what the stray light does to k_A (Lambert calibration): 100 (k_A / k_A,direct - 1);
* ``tables.csv``: per (table, reflectance) the largest stray fraction, the largest change of k_A and
  max |k_A - 1| with and without the stray light, and their cells;
* ``stray_12_0.png``, ``stray_11_40.png``: ``roadgonio render`` stray pictures of two cells;
* ``design.csv``, ``design_tolerance_map.png``, ``design_pareto.png``: the design study of the wall
  paint and a baffle (max |k_A - 1| point by point: the housing does not change the signal).

Every number comes from the Mitsuba backend at the stated target (seed 0); rerun after a change.
"""
from __future__ import annotations

import argparse
import csv
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
REFLECTANCES = (0.02, 0.05, 0.2)
TABLES = ("R2", "R3")


def tables(rel_se: float) -> None:
    from roadgonio.api import ka_table
    from roadgonio.engines.mitsuba import set_variant
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    from roadgonio.instrument.config import Instrument
    from roadgonio.plots import draw_table_map, new_figure, save_figure
    set_variant()
    base = Instrument.load(ROOT / "scenes" / "portable_housed.toml")
    grids = {}
    rows = []
    for t in TABLES:
        for rho in REFLECTANCES:
            d = base.to_dict()
            d["housing"] = {**d["housing"], "wall_reflectance": rho}
            inst = Instrument.from_dict(d, path=base.path)
            ds = ka_table(inst, t, rel_se=rel_se, seed=0)
            sf, ka, kd = (ds[v].values for v in ("stray_fraction", "k_a", "k_a_direct"))
            change = 100.0 * (ka / kd - 1.0)
            grids[t, rho] = (100.0 * sf, change)

            def where(a, fn):
                i, j = np.unravel_index(fn(a), a.shape)
                return f"tan eps {TAN_EPS_GRID[i]:g}, beta {BETA_GRID_DEG[j]:g}"
            rows.append({"table": t, "wall_reflectance": rho,
                         "stray_fraction_max_pct": round(float(np.nanmax(100 * sf)), 2),
                         "at": where(sf, np.nanargmax),
                         "ka_change_min_pct": round(float(np.nanmin(change)), 2), "at_min": where(change, np.nanargmin),
                         "ka_change_max_pct": round(float(np.nanmax(change)), 2), "at_max": where(change, np.nanargmax),
                         "max_abs_ka_minus_1": round(float(np.nanmax(np.abs(ka - 1))), 4),
                         "max_abs_ka_direct_minus_1": round(float(np.nanmax(np.abs(kd - 1))), 4),
                         "worst_rel_se": float(np.nanmax(ds["se"].values / np.abs(ka)))})
            print(rows[-1], flush=True)
    with open(HERE / "tables.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    for k, (name, label, centre) in enumerate((("stray_fraction.png", "stray light, % of the road signal", None),
                                               ("ka_change.png", "100 (k_A / k_A,direct - 1)  (%)", 0.0))):
        fig = new_figure((18, 10.5))
        vals = [grids[key][k] for key in grids]
        lo, hi = min(np.nanmin(v) for v in vals), max(np.nanmax(v) for v in vals)
        for r, t in enumerate(TABLES):
            for c, rho in enumerate(REFLECTANCES):
                ax = fig.add_axes((0.045 + c * 0.33, 0.53 - r * 0.47, 0.235, 0.39))
                v = grids[t, rho][k]
                draw_table_map(ax, v, label=label, centre=centre, log=False, text=lambda i, j: "",
                               tick_fontsize=6)
                ax.images[-1].set_clim(*(((0.0, hi) if centre is None else (-max(-lo, hi), max(-lo, hi)))))
                ax.set_title(f"{t}, wall reflectance {rho:g}: max {np.nanmax(np.abs(v)):.1f} %", fontsize=10)
        fig.suptitle("portable_housed: " + ("stray fraction of the road signal" if k == 0 else
                                            "change of k_A by the stray light (Lambert calibration)"), fontsize=12)
        save_figure(fig, HERE / name, dpi=80)


def renders() -> None:
    for t, b in ((12, 0), (11, 40)):
        with tempfile.TemporaryDirectory() as tmp:
            subprocess.run([sys.executable, "-m", "roadgonio", "render", "--instrument",
                            str(ROOT / "scenes" / "portable_housed.toml"), "--sample", "R3", "--tan-eps", str(t),
                            "--beta", str(b), "--out", tmp, "--resolution", "64", "--spp", "4"], check=True)
            shutil.copy(Path(tmp) / "stray.png", HERE / f"stray_{t}_{b}.png")


def design() -> None:
    base = ROOT / "scenes" / "portable_housed_baffle.toml"
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "roadgonio", "design", "--instrument", str(base), "--sample", "R3",
                        "--vary", "housing.wall_reflectance=0.005,0.01,0.02,0.05,0.1",
                        "--vary", "housing.baffles.0.height_m=0,0.01,0.02,0.03",
                        "--tolerance", "19%", "--accuracy", "fast", "--workers", "1", "--out", tmp], check=True)
        shutil.copy(Path(tmp) / "design.csv", HERE / "design.csv")
        shutil.copy(Path(tmp) / "tolerance_map.png", HERE / "design_tolerance_map.png")
        shutil.copy(Path(tmp) / "pareto.png", HERE / "design_pareto.png")
        if (Path(tmp) / "best.toml").exists():
            shutil.copy(Path(tmp) / "best.toml", HERE / "design_best.toml")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rel-se", type=float, default=3e-3)
    ap.add_argument("--skip-tables", action="store_true")
    ap.add_argument("--skip-render", action="store_true")
    ap.add_argument("--skip-design", action="store_true")
    args = ap.parse_args(argv)
    if not args.skip_tables:
        tables(args.rel_se)
    if not args.skip_render:
        renders()
    if not args.skip_design:
        design()
    return 0


if __name__ == "__main__":
    sys.exit(main())
