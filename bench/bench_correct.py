"""Benchmark of `roadgonio correct` (issue 11): synthetic round trips and the time of one table.

A known surface (roadgonio.correction.synthetic.r2_like_truth: the smooth variant with hand-chosen
parameters, S1 0.53, not the fit of any bundled table) is "measured" by an instrument, 1 % normal
noise, and corrected with --reference self (the default) and, beside it, with the nearest CIE table
as reference (the classic route, its model dependence from the two next nearest tables).

* wide (bench/data/wide.toml: source radius 4 cm at 1.2 m, pupil radius 2 cm at 2 m, field 0.3 deg,
  sample 12 x 6 m), Lambert and absolute calibration. The measured table's k_A under Lambert
  calibration comes from the float64 numpy Monte Carlo (rel. SE 1e-3, seed 12345; not the code under
  test), cached in bench/data/wide_r2like_ka_numpymc.csv (made by this script when missing or with
  --regenerate: about 15 min idle, 45 min loaded); absolute = that k_A x eta = <E>/E_0.
* portable (the preset), Lambert: the time of one 396-cell table, measured by the quadrature
  (rtol 1e-5), corrected end to end with the default backend (mitsuba) and written out (target
  <= 60 s), and once more with a misalignment SPEC.

Targets: corrected RMS log error <= 1.5 %, max <= 6 %, >= 90 % of cells within 2 stated u, S1 within
2 u(S1). Prints a table under the machine and the load average (and the load beside every row),
writes bench/results/correct.csv and the printed table as correct.txt.

    python bench/bench_correct.py [--regenerate] [--only wide|portable]
"""
from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from machine import Printout, load_after  # bench/machine.py (the script's folder is on sys.path)

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
RESULTS = HERE / "results"
KA_CACHE = DATA / "wide_r2like_ka_numpymc.csv"
SIGMA = "alpha_deg=0.01,eps_deg=0.05:rect,beta_deg=0.1,tilt_x_deg=0.02,tilt_y_deg=0.02"


def load():
    return "%.1f/%.1f/%.1f" % os.getloadavg()


def wide_ka(regenerate: bool) -> np.ndarray:
    """k_A (Lambert calibration) of the truth for the wide instrument, numpy Monte Carlo, cached."""
    from roadgonio.correction.synthetic import r2_like_truth, synthesize
    from roadgonio.instrument.config import Instrument
    from roadgonio.surface.rtable import KA_HEADER, RTable, read_table
    if KA_CACHE.exists() and not regenerate:
        return read_table(KA_CACHE, quantity="k_A").r
    inst = Instrument.load(DATA / "wide.toml")
    t0 = time.perf_counter()
    s = synthesize(r2_like_truth(), inst, backend="numpy-mc", backend_settings={"rel_se": 1e-3, "seed": 12345})
    RTable(s.k_a, name="k_a", source=f"{KA_HEADER}{r2_like_truth().name} by {inst.name} (Lambert calibration), numpy "
                                     f"Monte Carlo rel. SE 1e-3 seed 12345, {time.perf_counter() - t0:.0f} s; made by "
                                     "bench/bench_correct.py").write_csv(KA_CACHE, scale=1.0, digits=10)
    return s.k_a


def measured_from(k: np.ndarray, name: str, seed: int = 1, noise: float = 0.01):
    from roadgonio.correction.synthetic import r2_like_truth, standard_mask
    from roadgonio.surface.fit import model_r_on_grid
    from roadgonio.surface.rtable import RTable
    m = standard_mask()
    r_true = np.where(m, model_r_on_grid(r2_like_truth(), RTable(np.where(m, 1.0, np.nan))), np.nan)
    rng = np.random.default_rng(seed)
    eps = np.zeros(m.shape)
    eps[m] = noise * rng.standard_normal(int(m.sum()))
    return RTable(np.where(m, r_true * k * (1 + eps), np.nan), name=name), RTable(r_true, name="truth")


def scores(res, truth) -> dict:
    m = res.measured.mask
    err = np.log(res.corrected.r[m] / truth.r[m])
    u = res.budget.u_rel()
    return {"rms_pct": 100 * float(np.sqrt(np.mean(err ** 2))), "max_pct": 100 * float(np.max(np.abs(err))),
            "within_2u_pct": 100 * float(np.mean(np.abs(err) <= 2 * u)), "S1_true": truth.s1(),
            "S1": res.after["S1"], "u_S1": res.after["u_S1"], "z_S1": (res.after["S1"] - truth.s1()) / res.after["u_S1"],
            "u_median_pct": 100 * float(np.median(u)), "u_max_pct": 100 * float(np.max(u)),
            "class": f"{res.after['class']['R']}/{res.after['class']['C']}"}


def before_scores(meas, truth) -> dict:
    m = meas.mask
    err = np.log(meas.r[m] / truth.r[m])
    return {"rms_pct": 100 * float(np.sqrt(np.mean(err ** 2))), "max_pct": 100 * float(np.max(np.abs(err))),
            "S1": meas.s1(), "S1_true": truth.s1()}


def row(case, calib, method, s, seconds, k_range=(np.nan, np.nan)) -> dict:
    return {"case": case, "calibration": calib, "method": method, **s, "k_a_min": k_range[0], "k_a_max": k_range[1],
            "seconds": seconds, "load": load()}


def run_wide(rows: list, regenerate: bool, say=print) -> None:
    from roadgonio.correction import correct_files
    from roadgonio.surface.cie import nearest_bundled
    from roadgonio.engines.calibration import illuminance_ratio
    from roadgonio.engines.mitsuba import set_variant
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    from roadgonio.instrument.config import Instrument
    set_variant("llvm_ad_rgb")
    k_lam = wide_ka(regenerate)
    base = Instrument.load(DATA / "wide.toml")
    for mode in ("lambert", "absolute"):
        inst = base.with_changes(calibration={"mode": mode})
        k = k_lam.copy()
        if mode == "absolute":
            for i, j in zip(*np.nonzero(np.isfinite(k))):
                k[i, j] *= illuminance_ratio(inst, float(TAN_EPS_GRID[i]), float(BETA_GRID_DEG[j]))[0]
        meas, truth = measured_from(k, f"wide_{mode}")
        rows.append(row("wide", mode, "measured (uncorrected)", before_scores(meas, truth), 0.0,
                        (np.nanmin(k), np.nanmax(k))))
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            res, _, _ = correct_files([meas], inst, tmp, u_measured="1%", backend="mitsuba", progress=False)[0]
            rows.append(row("wide", mode, "self (fit through the instrument)", scores(res, truth),
                            time.perf_counter() - t0, (np.nanmin(res.k_a), np.nanmax(res.k_a))))
            near = nearest_bundled(meas.s1(), meas.q0(), 1)[0][0]
            t0 = time.perf_counter()
            ref, _, _ = correct_files([meas], inst, Path(tmp) / "ref", reference=near, alternatives="auto",
                                      u_measured="1%", backend="mitsuba", progress=False)[0]
            rows.append(row("wide", mode, f"reference {near} (nearest CIE table)", scores(ref, truth),
                            time.perf_counter() - t0, (np.nanmin(ref.k_a), np.nanmax(ref.k_a))))
        print_rows(rows[-3:], say)


def run_portable(rows: list, say=print) -> None:
    from roadgonio.correction import correct_files
    from roadgonio.correction.synthetic import r2_like_truth, synthesize
    from roadgonio.engines.mitsuba import set_variant
    from roadgonio.instrument.config import load_instrument
    set_variant("llvm_ad_rgb")
    inst = load_instrument("portable")
    s = synthesize(r2_like_truth(), inst, backend="quadrature", backend_settings={"rtol": 1e-5}, name="portable")
    rows.append(row("portable", "lambert", "measured (uncorrected)", before_scores(s.measured, s.truth), 0.0,
                    (np.nanmin(s.k_a), np.nanmax(s.k_a))))
    for label, extra in (("self, default (mitsuba), files written", {}),
                         ("self + --sigma misalignment", {"sigma": SIGMA})):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            res, _, files = correct_files([s.measured], inst, tmp, u_measured="1%", backend="mitsuba", progress=False,
                                          **extra)[0]
            dt = time.perf_counter() - t0
        rows.append(row("portable", "lambert", label, scores(res, s.truth), dt, (np.nanmin(res.k_a), np.nanmax(res.k_a))))
        rows[-1]["timings"] = " ".join(f"{k}={v:.1f}" for k, v in res.provenance["timings"].items())
    print_rows(rows[-3:], say)


COLS = [("case", 9, "s"), ("calibration", 9, "s"), ("method", 38, "s"), ("rms_pct", 6, ".2f"), ("max_pct", 6, ".2f"),
        ("within_2u_pct", 6, ".1f"), ("S1_true", 6, ".3f"), ("S1", 6, ".3f"), ("u_S1", 6, ".3f"), ("z_S1", 6, ".2f"),
        ("u_median_pct", 6, ".2f"), ("u_max_pct", 6, ".2f"), ("k_a_min", 5, ".2f"), ("k_a_max", 5, ".2f"),
        ("seconds", 6, ".1f"), ("load", 14, "s")]
HEAD = {"rms_pct": "RMS%", "max_pct": "max%", "within_2u_pct": "in2u%", "S1_true": "S1true", "u_S1": "u(S1)",
        "z_S1": "z(S1)", "u_median_pct": "u_med%", "u_max_pct": "u_max%", "k_a_min": "kmin", "k_a_max": "kmax",
        "seconds": "sec"}


def print_rows(rows, say=print) -> None:
    for r in rows:
        out = []
        for key, w, f in COLS:
            v = r.get(key, "")
            if isinstance(v, float) and not np.isfinite(v) or v == "":
                out.append(" " * w)
            else:
                out.append(format(v, f).ljust(w) if f == "s" else format(v, f).rjust(w))
        say("  ".join(out) + (f"   [{r['timings']}]" if r.get("timings") else ""))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--regenerate", action="store_true", help="recompute the cached numpy Monte Carlo k_A of wide")
    ap.add_argument("--only", choices=["wide", "portable"])
    args = ap.parse_args()
    say = Printout(f"bench_correct (issue 11): synthetic round trips{'' if args.only is None else ', ' + args.only + ' only'}")
    say("  ".join((HEAD.get(k, k)[:w]).ljust(w) if f == "s" else HEAD.get(k, k)[:w].rjust(w) for k, w, f in COLS))
    rows: list[dict] = []
    if args.only in (None, "portable"):
        run_portable(rows, say=say)
    if args.only in (None, "wide"):
        run_wide(rows, args.regenerate, say=say)
    say(load_after())
    RESULTS.mkdir(exist_ok=True)
    keys = [k for k, _, _ in COLS] + ["timings"]
    with open(RESULTS / "correct.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    (RESULTS / "correct.txt").write_text(say.text() + "\n")
    print(f"wrote {RESULTS / 'correct.csv'} and {RESULTS / 'correct.txt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
