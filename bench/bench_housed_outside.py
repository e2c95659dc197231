"""Benchmark: `roadgonio correct --forward surface` of surfaces measured through a housed instrument
(issues 18 and 19 together; docs/correction.md, "A surface outside eq. 4 through a housing").

Each truth (the microfacet and two-lobe truths outside eq. 4, the eq. 4 truth inside it; all of
roadgonio/surface/truths.py) is measured through scenes/portable_housed.toml with its walls' reflectance
set to each value asked (0 = no stray light, the bare instrument's k_A with the housing's shade), 1.5 %
noise (numpy, seed 5), the measurement's k_A by the Mitsuba backend at rel. SE 3e-4 and seed 777 (the
stray light exists only there; the backend itself is checked against float64 integrals in
tests/plugin/test_straylight.py and tests/plugin/test_surface_bsdf.py), and corrected with the
Mitsuba backend at its defaults (seed 0). Scores are |ln(corrected / true)| and z = error / u.

    python bench/bench_housed_outside.py [--truths microfacet,two_lobes,eq4] [--walls 0.2,0.05,0] [--out CSV]

Prints a table under the machine and the load average and writes bench/results/housed_outside.csv and
the printed table as housed_outside.txt (``--out`` elsewhere).
"""
from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

import numpy as np
from machine import Printout, load_after  # bench/machine.py (the script's folder is on sys.path)

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "housed_outside.csv"
NOISE, NOISE_SEED = 0.015, 5
TRUTH_REL_SE = 3e-4                       # the measurement's k_A target; its worst cell is printed beside it


def instrument(walls: float):
    from roadgonio.fileio import read_toml
    from roadgonio.instrument.config import Instrument
    path = ROOT / "scenes" / "portable_housed.toml"
    d = read_toml(path, "instrument file")
    d["housing"]["wall_reflectance"] = walls
    return Instrument.from_dict(d, path=path)


def run(kind: str, walls: float) -> dict:
    from roadgonio import api
    from roadgonio.correction.synthetic import standard_mask, synthesize
    from roadgonio.surface.fit import model_r_on_grid
    from roadgonio.surface.rtable import RTable
    from roadgonio.surface.truths import make_truth
    inst = instrument(walls)
    m = standard_mask()
    truth = make_truth(kind)
    s = synthesize(truth, inst, noise=0.0, backend="mitsuba", backend_settings={"rel_se": TRUTH_REL_SE, "seed": 777}, mask=m)
    r_true = np.where(m, model_r_on_grid(truth, RTable(np.where(m, 1.0, np.nan))), np.nan)
    rng = np.random.default_rng(NOISE_SEED)
    eps = np.zeros(m.shape)
    eps[m] = NOISE * rng.standard_normal(int(m.sum()))
    meas = RTable(np.where(m, r_true * s.k_a * (1 + eps), np.nan), name=f"{kind}_housed")
    t0 = time.perf_counter()
    res = api.correct(meas, inst, forward="surface", u_measured="1.5%", backend="mitsuba", seed=0, plots=False)
    seconds = time.perf_counter() - t0
    c = res.corrected
    mm = c.mask
    err = np.log(c.r[mm] / r_true[mm])
    z = err / (res.u_corrected[mm] / c.r[mm])
    sc = res.extra["surface"]
    return {"truth": kind, "walls": walls, "rms_pct": 100 * float(np.sqrt(np.mean(err ** 2))),
            "max_pct": 100 * float(np.max(np.abs(err))), "within_2u_pct": 100 * float(np.mean(np.abs(z) <= 2)),
            "beyond_4u": int(np.sum(np.abs(z) > 4)), "rms_z": float(np.sqrt(np.mean(z ** 2))),
            "S1": float(res.after["S1"]), "u_S1": float(res.after["u_S1"]), "S1_true": float(RTable(r_true).s1()),
            "truth_worst_rel_se": float(np.nanmax(s.u_k_a_backend / s.k_a)),
            "renderings": len(sc.surface_steps),
            "converged": bool(sc.surface_steps[-1]["converged"]) if sc.surface_steps else None,
            "seconds": seconds}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--truths", default="microfacet,two_lobes,eq4")
    ap.add_argument("--walls", default="0.2,0.05,0")
    ap.add_argument("--out", default=str(OUT))
    a = ap.parse_args(argv)
    out = Path(a.out)
    from roadgonio.engines.mitsuba import set_variant
    set_variant("llvm_ad_rgb")
    rows = []
    say = Printout(f"bench_housed_outside: truths {a.truths} through portable_housed, walls {a.walls}")
    head = (f"{'truth':11s} {'walls':>5s} {'RMS %':>6s} {'max %':>6s} {'2u %':>6s} {'>4u':>4s} {'RMS z':>6s} "
            f"{'S1 (true)':>17s} {'u(S1)':>6s} {'rend.':>5s} {'s':>5s} {'truth SE':>8s}")
    say(head)
    for kind in a.truths.split(","):
        for w in (float(x) for x in a.walls.split(",")):
            r = run(kind, w)
            rows.append(r)
            say(f"{r['truth']:11s} {r['walls']:5.2f} {r['rms_pct']:6.2f} {r['max_pct']:6.2f} {r['within_2u_pct']:6.1f} "
                  f"{r['beyond_4u']:4d} {r['rms_z']:6.2f} {r['S1']:7.4f} ({r['S1_true']:.4f}) "
                  f"{100 * r['u_S1'] / r['S1']:5.2f}% {r['renderings']:5d} {r['seconds']:5.0f} {r['truth_worst_rel_se']:8.1e}"
                  + ("" if r["truth_worst_rel_se"] <= TRUTH_REL_SE * (1 + 1e-9) else "  (truth's k_A above its SE target)"))
    say(load_after())
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    os.replace(tmp, out)
    out.with_suffix(".txt").write_text(say.text() + "\n")
    print(f"wrote {out} and {out.with_suffix('.txt')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
