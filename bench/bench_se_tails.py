"""Are the Mitsuba backend's standard errors right in their tails? (session 12, helper-42)

Over many seeds x the 580 cells of the CIE grid, z = (k_A - k_A,ref) / SE for

* ``portable``: the bare portable preset (scenes/portable.toml), k_a;
* ``housed``: the portable preset in a housing with walls of reflectance 0.02 and a 1 cm baffle at
  x = -0.5 m (scenes/portable_housed_baffle.toml with the design point of trial 11 whose tan 5 /
  beta 0 cell came out 4.3 SE off), k_a_direct (the direct light, whose float64 value is the bare
  instrument's k_A),

* ``wide``: the wide preset (scenes/wide.toml), k_a, whose beta 180 cells have skewed replicate
  sums on small lattices (session 25: ``--first-pass`` to compare first passes; the reference is
  the quadrature at rtol 1e-5, ``se_tails_reference_wide.csv``),

all for the fitted CIE R3 at ``--accuracy fast`` and ``default``. The reference is the float64
quadrature at rtol 1e-6 (``se_tails_reference.csv``, computed once; its 23 unconverged beta 0 cells
checked against the RQMC reference at rtol 1e-5: within 5e-6 relative, against relative SEs of
3e-4 and more).

Each row also carries the SE's effective degrees of freedom (Welch-Satterthwaite over the cell's
strata, :func:`roadgonio.engines.mitsuba.passes.strata_ratio_se_dof_many` when it exists, else the
formula below) and the cell's passes, so the z distribution is compared with N(0, 1) and with
Student's t of that many degrees of freedom.

    python bench/bench_se_tails.py run --instrument portable --accuracy fast --seeds 0:400
    python bench/bench_se_tails.py analyse            # every se_tails_*.csv in out/se_tails
    python bench/bench_se_tails.py analyse --instrument wide     # -> bench/results/se_tails_wide.txt

Writes out/se_tails/se_tails_<instrument>_<accuracy>[_r<min replicates>][_f<first pass>].csv (one
row per cell and seed, appending seeds not yet in it; out/ is not kept in git; runs with the presets
before session 25 are to be named with the first pass they had, _f256 at fast and _f1024 at default)
and, with ``analyse``, bench/results/se_tails.txt (or se_tails_<instrument>.txt): the tails over all
cells, by passes, the stopping rule's selection, and per cell (the cells whose own mean z^2 over the
seeds is outside its chi-square band, and their bias in SEMs: what a user of one cell sees).
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
from machine import header, load_after  # bench/machine.py (the script's folder is on sys.path)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
REFERENCE = RESULTS / "se_tails_reference.csv"
#: The wide preset's reference (its own geometry; the housed instrument's direct light is the bare
#: portable one's, so those two share REFERENCE).
REFERENCES = {"portable": REFERENCE, "housed": REFERENCE, "wide": RESULTS / "se_tails_reference_wide.csv"}
#: Tolerance of each reference: the wide preset's specular cells reach the quadrature's cap at 1e-6
#: (more than 20 min for the table); 1e-5 is 20 x below the SE at default's rel SE 1e-3 already.
REFERENCE_RTOL = {"portable": 1e-6, "housed": 1e-6, "wide": 1e-5}
#: The per-run rows (~20 MB per 400 tables): out/ is not kept in git; the seeds make them again.
RAW = ROOT / "out" / "se_tails"
FIELDS = ("seed", "tan_eps", "beta", "k", "se", "dof", "passes", "replicates", "ref")


def load() -> str:
    return "/".join(f"{v:.1f}" for v in os.getloadavg())


def instrument(name: str):
    from roadgonio.api import _instrument
    if name in ("portable", "wide"):
        return _instrument(name)
    base = _instrument("portable_housed_baffle")
    return base.with_changes(housing={"wall_reflectance": 0.02, "baffles": [{"x_m": -0.5, "height_m": 0.01}]})


def grid_cells() -> list[tuple[float, float]]:
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    return [(float(t), float(b)) for t in TAN_EPS_GRID for b in BETA_GRID_DEG]


def reference(model, name: str = "portable") -> dict[tuple[float, float], tuple[float, float]]:
    """(k_A, error bound) of every cell from the float64 quadrature at :data:`REFERENCE_RTOL` (cached)."""
    path = REFERENCES[name]
    if not path.exists():
        from roadgonio.engines.registry import make_backend
        t0 = time.perf_counter()
        res = make_backend("quadrature", instrument("portable" if name == "housed" else name), model,
                           rtol=REFERENCE_RTOL[name]).compute(grid_cells())
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["tan_eps", "beta", "k_a", "error_bound", "converged"])
            for r in res:
                w.writerow([r.tan_eps, r.beta_deg, repr(r.k_a), repr(r.error_bound), int(r.converged)])
        print(f"reference: {time.perf_counter() - t0:.0f} s", flush=True)
    with open(path) as fh:
        return {(float(r["tan_eps"]), float(r["beta"])): (float(r["k_a"]), float(r["error_bound"]))
                for r in csv.DictReader(fh)}


def satterthwaite(strata) -> tuple[float, float, float]:
    """(ratio, SE, effective dof) of paired replicate sums over independent strata, written apart
    from the engine: v_q = B_q var(A - r B) per stratum, SE^2 = sum v_q / (sum B)^2,
    dof = (sum v_q)^2 / sum v_q^2 / (B_q - 1)."""
    sa = sum(float(np.sum(a)) for a, _ in strata)
    sb = sum(float(np.sum(b)) for _, b in strata)
    r = sa / sb
    v = np.array([len(a) * np.var(a - r * b, ddof=1) for a, b in strata])
    n = np.array([len(a) for a, _ in strata], dtype=float)
    dof = v.sum() ** 2 / np.sum(v * v / (n - 1.0)) if v.sum() > 0 else math.inf
    return r, math.sqrt(v.sum()) / abs(sb), float(dof)


def run(args) -> None:
    from roadgonio.api import _sample
    from roadgonio.engines.registry import make_backend, prepare_entry_point
    prepare_entry_point("mitsuba")
    model = _sample("R3").model
    ref = reference(model, args.instrument)
    inst = instrument(args.instrument)
    cells = grid_cells()
    tag = ("" if args.min_replicates is None else f"_r{args.min_replicates}") + \
          ("" if args.first_pass is None else f"_f{args.first_pass}")
    RAW.mkdir(parents=True, exist_ok=True)
    out = RAW / f"se_tails_{args.instrument}_{args.accuracy}{tag}.csv"
    have = set()
    if out.exists():
        with open(out) as fh:
            have = {int(r["seed"]) for r in csv.DictReader(fh)}
    lo, hi = (int(x) for x in args.seeds.split(":"))
    seeds = [s for s in range(lo, hi) if s not in have]
    extra = {} if args.min_replicates is None else {"min_replicates": args.min_replicates}
    if args.first_pass is not None:
        extra["first_pass"] = args.first_pass
    b = make_backend("mitsuba", inst, model, accuracy=args.accuracy, seed=0, **extra)
    new = not out.exists()
    t0 = time.perf_counter()
    with open(out, "a", newline="") as fh:
        w = csv.writer(fh)
        if new:
            w.writerow(FIELDS)
        for s in seeds:
            b.seed = s
            res = b.compute(cells)
            for i, r in enumerate(res):
                st = b.last_run.stats[i]
                strata = st.direct_strata() if st.direct else [(R, G) for _, R, G in
                                                                 (st.strata[k] for k in sorted(st.strata))]
                ratio, se_ratio, dof = satterthwaite(strata)
                k, se = (r.k_a_direct, r.k_a_direct_se) if st.direct else (r.k_a, r.se)
                assert math.isclose(se_ratio / r.extra["ideal_ratio"], se, rel_tol=1e-9), (se_ratio, se)
                dof_engine = getattr(r, "se_dof", None)
                if dof_engine is not None and not st.direct:
                    assert math.isclose(dof_engine, dof, rel_tol=1e-9), (dof_engine, dof)
                w.writerow([s, r.tan_eps, r.beta_deg, repr(k), repr(se), repr(dof), r.extra["passes"],
                            r.extra["replicates"], repr(ref[(r.tan_eps, r.beta_deg)][0])])
            fh.flush()
    print(f"{args.instrument} {args.accuracy}: {len(seeds)} seeds in {time.perf_counter() - t0:.0f} s "
          f"(load {load()})", flush=True)


def tail_line(label: str, z: np.ndarray, dof: np.ndarray, seed: np.ndarray) -> str:
    """mean z^2 and the fractions beyond 2, 3, 4 against N(0,1) and t_dof, with the binomial SE
    and the SE from the seeds as blocks (cells of one run are correlated)."""
    from scipy.stats import norm, t as student
    m = z.size
    parts = [f"{label:34s} {m:7d}  z2 {np.mean(z * z):5.3f}"
             f" (t {np.mean(np.where(dof > 2, dof / np.maximum(dof - 2, 1e-9), np.nan)):5.3f})"]
    seeds = np.unique(seed)
    for k in (2.0, 3.0, 4.0):
        hit = np.abs(z) > k
        frac = hit.mean()
        p_n = 2 * norm.sf(k)
        p_t = float(np.mean(2 * student.sf(k, dof)))
        binom = math.sqrt(p_t * (1 - p_t) / m)
        per = np.array([hit[seed == s].sum() for s in seeds], dtype=float)
        n_per = np.array([(seed == s).sum() for s in seeds], dtype=float)
        block = per.std(ddof=1) * math.sqrt(len(seeds)) / n_per.sum() if len(seeds) > 1 else math.nan
        parts.append(f"|z|>{k:g}: {100 * frac:6.3f}% (N {100 * p_n:5.3f}, t {100 * p_t:5.3f}; "
                     f"+-{100 * binom:5.3f} binom, +-{100 * block:5.3f} seeds)")
    return "  ".join(parts)


#: The renderer's relative float32 floor (roadgonio.engines.validate: 1e-5 for Mitsuba).
FLOAT32_FLOOR = 1e-5
#: A cell tests the SE only where the SE is this many times the other errors of z's numerator
#: (the reference's error bound and the float32 floor): where the fitted R3 is nearly flat over the
#: apertures (beta 60-90 at tan eps 3-9) the SE is ~1e-8 relative and z measures the floor, not the SE.
SE_OVER_FLOOR = 20.0


def kept(a: dict, bound: dict) -> np.ndarray:
    """The results that test the SE: SE >= SE_OVER_FLOOR (bound + floor), and at tan eps 0 only
    beta 0 (every beta is the same geometry there, computed with the same random numbers)."""
    eb = np.array([bound[(t, b)] for t, b in zip(a["tan_eps"], a["beta"])])
    return (a["se"] >= SE_OVER_FLOOR * (eb + FLOAT32_FLOOR * np.abs(a["ref"]))) & ((a["tan_eps"] > 0) | (a["beta"] == 0))


def analyse(args) -> None:
    bounds = {}
    for name, path in REFERENCES.items():
        if path.exists():
            with open(path) as fh:
                bounds[name] = {(float(r["tan_eps"]), float(r["beta"])): float(r["error_bound"])
                                for r in csv.DictReader(fh)}
    lines = header(f"bench/bench_se_tails.py analyse --instrument {args.instrument}")
    lines += ["group                                    cells  mean z^2 (t expectation)  fractions beyond 2, 3, 4"]
    for path in sorted(RAW.glob(f"se_tails_{args.instrument}_*.csv")):
        with open(path) as fh:
            rows = list(csv.DictReader(fh))
        if not rows:
            continue
        a = {f: np.array([float(r[f]) for r in rows]) for f in FIELDS}
        m_all = a["k"].size
        bound = bounds[path.stem.removeprefix("se_tails_").split("_")[0]]
        a = {f: v[kept(a, bound)] for f, v in a.items()}
        z = (a["k"] - a["ref"]) / a["se"]
        name = path.stem.removeprefix("se_tails_")
        nseeds = len(np.unique(a["seed"]))
        lines.append(f"{name} ({nseeds} seeds; {a['k'].size} of {m_all} results kept (SE >= {SE_OVER_FLOOR:g} x "
                     f"(reference bound + float32 floor)); dof median {np.median(a['dof']):.1f}, "
                     f"5-95 % {np.percentile(a['dof'], 5):.1f}-{np.percentile(a['dof'], 95):.1f})")
        lines.append(tail_line("  all cells", z, a["dof"], a["seed"]))
        for p in sorted(set(a["passes"].astype(int))):
            sel = a["passes"] == p
            if sel.sum() >= 1000:
                lines.append(tail_line(f"  {p} pass(es)", z[sel], a["dof"][sel], a["seed"][sel]))
        # z scaled to the normal by its own t: Phi^-1(F_t(z)); honest dof => N(0,1)
        from scipy.stats import norm, t as student
        u = norm.isf(student.sf(z, a["dof"]))          # N(0, 1) if z is t_dof
        lines.append(tail_line("  z mapped through its t_dof", u, np.full(z.size, 1e9), a["seed"]))
        lines.extend(selection(z, u, a))
        lines.extend(per_cell(u, a))
        lines.extend(clumping(z, a))
    lines.append(load_after())
    text = "\n".join(lines)
    print(text)
    (RESULTS / ("se_tails.txt" if args.instrument == "*" else f"se_tails_{args.instrument}.txt")).write_text(text + "\n")


def selection(z: np.ndarray, u: np.ndarray, a: dict) -> list[str]:
    """The stopping rule's selection: a cell leaves after a pass once its estimated SE meets the
    target, so at a cell that needs a second pass in some runs and not in others, the runs that
    stopped after the first had an SE estimate on the low side (and those that went on, on the high
    side). Cells grouped by how often they stopped after their first pass; z^2 and z mapped through
    its t_dof (u) of the runs that stopped then and of those that went on."""
    keys = list(zip(a["tan_eps"], a["beta"]))
    first = a["passes"] == 1
    cells: dict = {}
    for i, k in enumerate(keys):
        cells.setdefault(k, []).append(i)
    p1 = {k: float(np.mean(first[idx])) for k, idx in cells.items()}
    share = np.array([p1[k] for k in keys])
    out = ["  the stopping rule's selection, cells by the share of runs that stopped after pass 1:"]
    for lo, hi in ((0.0, 0.05), (0.05, 0.5), (0.5, 0.95), (0.95, 1.01)):
        sel = (share >= lo) & (share < hi)
        parts = []
        for label, s in (("stopped after pass 1", sel & first), ("went on", sel & ~first)):
            parts.append(f"{label}: {s.sum():6d}, z2 {np.mean(z[s] ** 2):6.3f} u2 {np.mean(u[s] ** 2):6.3f} "
                         f"|u|>3 {100 * np.mean(np.abs(u[s]) > 3):6.3f}%" if s.sum() else f"{label}: none")
        ncell = sum(lo <= v < hi for v in p1.values())
        out.append(f"    share in [{lo:.2f}, {min(hi, 1.0):.2f}) ({ncell:3d} cells): " + "; ".join(parts))
    return out


def per_cell(u: np.ndarray, a: dict, worst: int = 6) -> list[str]:
    """What a user of one cell sees: per cell (at least 50 seeds), the mean square of z mapped
    through its t_dof (u) over the seeds against the chi-square band of 0.1 % either side, and the
    mean error in standard errors of the mean (the scatter over the seeds)."""
    from scipy.stats import chi2
    cells: dict = {}
    for i, key in enumerate(zip(a["tan_eps"], a["beta"])):
        cells.setdefault(key, []).append(i)
    rows = []
    for key, idx in cells.items():
        if len(idx) < 50:
            continue
        d = a["k"][idx] - a["ref"][idx]
        rows.append((float(np.mean(u[idx] ** 2)), key, len(idx),
                     float(d.mean() / (a["k"][idx].std(ddof=1) / math.sqrt(len(idx)))), float(np.mean(a["passes"][idx] == 1))))
    if not rows:
        return ["  per cell: no cell with 50 seeds"]
    rows.sort(reverse=True)
    m = int(np.median([r[2] for r in rows]))
    lo, hi = chi2.ppf(0.001, m) / m, chi2.isf(0.001, m) / m
    out_hi = sum(r[0] > hi for r in rows)
    out_lo = sum(r[0] < lo for r in rows)
    return [f"  per cell ({len(rows)} cells, ~{m} seeds each): mean u^2 above its 0.1 % band ({hi:.2f}) in {out_hi}, "
            f"below ({lo:.2f}) in {out_lo}; the worst: " + "; ".join(
                f"{k[0]:g}:{k[1]:g} u2 {v:.2f}, mean error {b:+.1f} SEM, done in pass 1 in {100 * p1:.0f} %"
                for v, k, _, b, p1 in rows[:worst])]


def clumping(z: np.ndarray, a: dict) -> list[str]:
    """Do the cells of one run (one seed: one Mitsuba launch) err together? The correlation of z
    between cells over the seeds, and the spread of the per-run count of |z| > 3 against the
    binomial spread it would have if the cells were independent."""
    seeds = np.unique(a["seed"])
    keys = sorted({(t, b) for t, b in zip(a["tan_eps"], a["beta"])})
    index = {k: j for j, k in enumerate(keys)}
    Z = np.full((len(seeds), len(keys)), np.nan)
    srow = {s: i for i, s in enumerate(seeds)}
    for s, t, b, zz in zip(a["seed"], a["tan_eps"], a["beta"], z):
        Z[srow[s], index[(t, b)]] = zz
    ok = np.all(np.isfinite(Z), axis=0)
    Zc = Z[:, ok] - Z[:, ok].mean(axis=0)
    C = np.corrcoef(Zc, rowvar=False)
    off = C[~np.eye(C.shape[0], dtype=bool)]
    # neighbours: the same beta, adjacent tan eps
    k_ok = [k for k, good in zip(keys, ok) if good]
    pos = {k: j for j, k in enumerate(k_ok)}
    from roadgonio.geometry import TAN_EPS_GRID
    tans = list(TAN_EPS_GRID)
    nb = [C[pos[(t, b)], pos[(tans[i + 1], b)]] for (t, b) in k_ok
          for i in [tans.index(t)] if i + 1 < len(tans) and (tans[i + 1], b) in pos]
    out = [f"  correlation of z between cells over {len(seeds)} seeds: mean {off.mean():+.3f} (all pairs), "
           f"{np.mean(nb):+.3f} (neighbours in tan eps), 99th pct {np.percentile(off, 99):+.3f}"]
    for k in (2.0, 3.0):
        per = np.sum(np.abs(Z) > k, axis=1)
        m = Z.shape[1]
        p = per.sum() / (m * len(seeds))
        out.append(f"  |z|>{k:g} per run: mean {per.mean():.2f}, variance {per.var(ddof=1):.2f} "
                   f"(independent cells: {m * p * (1 - p):.2f}), max {per.max()}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--instrument", choices=("portable", "housed", "wide"), required=True)
    r.add_argument("--accuracy", choices=("fast", "default"), required=True)
    r.add_argument("--seeds", default="0:100", help="LO:HI")
    r.add_argument("--min-replicates", type=int, default=None, help="the Mitsuba backend's (default: its own, 16)")
    r.add_argument("--first-pass", type=int, default=None, help="the Mitsuba backend's (default: the preset's)")
    a = sub.add_parser("analyse")
    a.add_argument("--instrument", default="*", help="only this instrument's runs, written to se_tails_INSTRUMENT.txt "
                   "(default: every run, se_tails.txt)")
    args = ap.parse_args()
    (run if args.cmd == "run" else analyse)(args)


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
