"""Benchmark: the full 580-cell k_A table of the housed portable example (scenes/portable_housed.toml)
at worst relative SE 1e-3, side by side with the same instrument without the housing
(scenes/portable.toml: only [housing] differs), both cores used (Dr.Jit's thread pool), R3.
Target (issue 18): the housed table within 10x the time of the bare one.

    python bench/bench_straylight.py                  # 3 runs each, the median run's wall time
    python bench/bench_straylight.py --reflectance 0.02 0.05 0.2
    python bench/bench_straylight.py --command        # also the command a user runs, end to end

Each instrument is built and run once untimed first (the kernels compile into Dr.Jit's cache),
then ``--repeats`` times; the table reports the median run (the low median,
``statistics.median_low``: with an even ``--repeats`` the faster of the two middle runs, so that the
row is one run's wall time, CPU time and results, never an average of two): its wall time of the
table (compute), its CPU time / wall time, the samples, the worst relative SE and the largest stray fraction, and the
ratio to the bare instrument measured in the same run. Prints the table and the machine's load
(measure on an idle machine: ``uptime`` load < 0.5) under the machine, and writes bench/results/straylight.csv and
straylight.txt.

``--command`` adds what a user waits for: ``roadgonio ka --instrument FILE --sample R3 --rel-se E
--fresh -q`` in a fresh process (start-up, scene build, kernels from Dr.Jit's on-disk cache, the
table, the files), bare and housed side by side, one untimed run each first, then the median of
``--repeats`` (the low median, as above); written to bench/results/straylight_command.csv and
straylight_command.txt. The two ratios answer different
questions (the computation itself, the command end to end) and are quoted apart.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from machine import header, load_after, write_rows  # bench/machine.py (the script's folder is on sys.path)

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rel-se", type=float, default=1e-3)
    ap.add_argument("--sample", default="R3")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--reflectance", type=float, nargs="*", default=[],
                    help="more rows: the housed example with these wall reflectances")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "straylight.csv"))
    ap.add_argument("--command", action="store_true",
                    help="also time the roadgonio ka command end to end in fresh processes")
    args = ap.parse_args(argv)

    import drjit as dr

    from roadgonio.engines import full_grid_cells
    from roadgonio.engines.mitsuba import set_variant
    from roadgonio.engines.mitsuba.backend import make_backend
    from roadgonio.instrument.config import Instrument
    from roadgonio.surface.sample import resolve_sample

    set_variant()                      # the script is the entry point: it chooses the variant
    model = resolve_sample(args.sample).model
    cells = full_grid_cells()
    housed = Instrument.load(ROOT / "scenes" / "portable_housed.toml")
    runs = [("portable (no housing)", Instrument.load(ROOT / "scenes" / "portable.toml")),
            (f"portable_housed (walls {housed.extra['housing']['wall_reflectance']:g})", housed)]
    for rho in args.reflectance:
        d = housed.to_dict()
        d["housing"] = {**d["housing"], "wall_reflectance": rho}
        runs.append((f"portable_housed (walls {rho:g})", Instrument.from_dict(d, path=housed.path)))
    lines = header(f"bench_straylight: {len(cells)} cells, {args.sample}, worst rel SE {args.rel_se:g}, "
                   f"{dr.thread_count()} Dr.Jit threads; median_low of {args.repeats} runs each")
    rows = []
    for name, inst in runs:
        b = make_backend(inst, model, rel_se=args.rel_se, seed=0)
        b.compute(cells)                               # compile and warm up
        walls, cpus = [], []
        for _ in range(args.repeats):
            c0, t0 = time.process_time(), time.perf_counter()
            res = b.compute(cells)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        k = walls.index(statistics.median_low(walls))   # a run's own time (module docstring), any --repeats
        rows.append({"instrument": name, "wall_s": walls[k], "cpu_s": cpus[k], "cpu_per_wall": cpus[k] / walls[k],
                     "samples": sum(r.samples for r in res),
                     "worst_rel_se": max(r.se / abs(r.k_a) for r in res),
                     "not_converged": sum(not r.converged for r in res),
                     "stray_fraction_max": max(r.stray_fraction for r in res),
                     "k_a_min": min(r.k_a for r in res), "k_a_max": max(r.k_a for r in res),
                     "walls_s": " ".join(f"{w:.3f}" for w in walls)})
    base = rows[0]["wall_s"]
    for r in rows:
        r["ratio_to_bare"] = r["wall_s"] / base
    lines += [f"{'instrument':34s} {'wall s':>8s} {'ratio':>7s} {'cpu/wall':>8s} {'samples':>11s} {'worst rel SE':>12s} "
             f"{'max stray':>9s} {'k_A range':>15s}"]
    for r in rows:
        lines.append(f"{r['instrument']:34s} {r['wall_s']:8.2f} {r['ratio_to_bare']:7.1f} {r['cpu_per_wall']:8.2f} "
                     f"{r['samples']:11.3e} {r['worst_rel_se']:12.2e} {100 * r['stray_fraction_max']:8.1f}% "
                     f"{r['k_a_min']:7.3f}-{r['k_a_max']:.3f}")
    lines.append(load_after())
    text = "\n".join(lines)
    print(text)
    out = Path(args.out)
    write_rows(out, rows, text)
    if args.command:
        _command_rows(args, out)
    return 0


def _command_rows(args, out: Path) -> None:
    """The ``roadgonio ka`` command end to end (module docstring), bare and housed."""
    import subprocess
    import tempfile
    files = [("portable (no housing)", ROOT / "scenes" / "portable.toml"),
             ("portable_housed (walls 0.05)", ROOT / "scenes" / "portable_housed.toml")]
    lines = header(f"roadgonio ka end to end (fresh process each, median_low of {args.repeats})")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, f in files:
            cmd = [sys.executable, "-m", "roadgonio", "ka", "--instrument", str(f), "--sample", args.sample,
                   "--rel-se", f"{args.rel_se:g}", "--out", str(Path(tmp) / f.stem), "--fresh", "-q"]
            walls = []
            for i in range(args.repeats + 1):
                t0 = time.perf_counter()
                subprocess.run(cmd, check=True, capture_output=True)
                if i:
                    walls.append(time.perf_counter() - t0)
            rows.append({"instrument": name, "command_wall_s": statistics.median_low(walls),
                         "walls_s": " ".join(f"{w:.2f}" for w in walls)})
    for r in rows:
        r["ratio_to_bare"] = r["command_wall_s"] / rows[0]["command_wall_s"]
    lines.append(f"{'instrument':34s} {'wall s':>8s} {'ratio':>7s}  runs")
    lines += [f"{r['instrument']:34s} {r['command_wall_s']:8.2f} {r['ratio_to_bare']:7.2f}  {r['walls_s']}" for r in rows]
    lines.append(load_after())
    print("\n".join(lines))
    write_rows(out.with_name("straylight_command.csv"), rows, "\n".join(lines))


if __name__ == "__main__":
    sys.exit(main())
