"""``roadgonio design``: sweep instrument parameters on Dask; tolerance map, Pareto front, best design."""
from __future__ import annotations

import sys
from pathlib import Path

from roadgonio.engines.accuracy import PRESETS
from roadgonio.surface.model import VARIANTS
from roadgonio.cli._common import (
    add_dask_arguments,
    add_instrument_argument,
    add_output_options,
    rel_se_setting,
    select_variant,
    show_progress,
    text_output,
)


def register(sub) -> None:
    from roadgonio.design.grid import ALL_KEYS
    p = sub.add_parser(
        "design", help="instrument design: sweep instrument parameters (on Dask), tolerance map, Pareto front, "
                       "best design",
        description="Compute k_A tables for every point of a grid of instrument designs (every point is a complete "
                    "instrument: the base file with the varied keys changed), for one or more samples. Per point: "
                    "max |k_A - 1| over cells and samples, rms, the worst cell, the signal (detected flux for a "
                    "Lambertian sample relative to the base design, from the etendue and the source's solid angle) "
                    "and whether it is feasible (geometry valid and max |k_A - 1| <= tolerance); geometrically "
                    "impossible points are kept with their reason. Writes design.nc, design.csv, best.toml (the "
                    "feasible design with the most signal), pareto.png and, for two varied keys, tolerance_map.png. "
                    "Resumes an interrupted run. Keys: " + ", ".join(ALL_KEYS)
                    + ", housing.baffles.N.x_m, housing.baffles.N.height_m (N: a baffle of the base [housing]).")
    add_instrument_argument(p)
    p.add_argument("--vary", action="append", default=[], metavar="KEY=LO:HI:N",
                   help="an instrument key and its values: LO:HI:N (linear), LO:HI:N:log, or V1,V2,...; repeat for "
                        "more keys (the grid is their product)")
    p.add_argument("--sample", action="append", required=True, metavar="SAMPLE",
                   help="bundled table name (R1..R4, C1, C2), an r-table file, a model.json or 'lambert'; repeat for "
                        "the surfaces you expect (max |k_A - 1| is over all of them)")
    p.add_argument("--model-variant", choices=list(VARIANTS), help="model variant when a sample is a table to fit")
    p.add_argument("--tolerance", default="5%", metavar="T",
                   help="largest acceptable |k_A - 1|: a fraction (0.05) or a percentage (5%%); default 5%%")
    p.add_argument("--cells", default="all", metavar="all|table|LIST",
                   help="all = the 580-cell grid (default); table = the cells tabulated in each sample's r-table; "
                        "LIST = T:B,T:B,... (tan eps : beta deg), e.g. 12:0,12:2,4:0")
    p.add_argument("--backend", default="mitsuba", choices=["mitsuba", "quadrature", "numpy-mc"],
                   help="k_A backend (default mitsuba)")
    p.add_argument("--accuracy", choices=list(PRESETS), help="accuracy preset (default: the backend's default)")
    p.add_argument("--rel-se", type=float, metavar="E", help="target relative SE per cell (overrides --accuracy)")
    p.add_argument("--seed", type=int, default=0, help="root seed; design point k gets SeedSequence(seed).spawn(n)[k]")
    add_dask_arguments(p, "default: a local cluster with one worker per core")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/design-INSTRUMENT)")
    p.add_argument("--fresh", action="store_true", help="discard the partial results in --out instead of resuming")
    p.add_argument("--no-plots", action="store_true", help="do not draw pareto.png / tolerance_map.png")
    add_output_options(p, "print the summary as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from roadgonio.design.run import _load_base, run_design, summary
    base = _load_base(args.instrument)
    settings: dict = {}
    if args.rel_se is not None:
        settings.update(rel_se_setting(args.backend, args.rel_se))
    out = Path(args.out) if args.out else Path("out") / f"design-{base.name}"
    if args.workers == 0:
        select_variant(args.backend)        # in this process: the command is its entry point
    ds = run_design(base, args.vary, args.sample, tolerance=args.tolerance, cells=args.cells, backend=args.backend,
                    accuracy=args.accuracy, settings=settings, seed=args.seed, workers=args.workers,
                    scheduler=args.scheduler, out=out, fresh=args.fresh, plots=not args.no_plots,
                    model_variant=args.model_variant, progress=show_progress(args))
    s = summary(ds)
    rc = 1 if s["tables_failed"] else 0
    if s["tables_failed"] and not args.quiet:
        print(f"roadgonio: {s['tables_failed']} tables failed (a worker died): run the same command again to retry "
              "them", file=sys.stderr)
    if args.json:
        from roadgonio.fileio import to_json
        print(to_json(s))
        return rc
    say = text_output(args)
    say(f"design of '{base.name}': {s['points']} points ({' x '.join(s['varied']) or 'base only'}), "
        f"{s['geometry_ok']} geometrically possible, {s['feasible']} within the tolerance {s['tolerance']:g}; "
        f"{s['tables_computed']} tables computed, {s['tables_resumed']} resumed in {s['wall_s']:.1f} s"
        + (f" (the tables {s['compute_wall_s']:.1f} s, after the cluster's start: "
           f"{s['design_points_per_hour']:.0f} design points/hour)" if "design_points_per_hour" in s else ""))
    if s["not_feasible_by_kind"]:
        say("not feasible: " + ", ".join(f"{k} {v}" for k, v in sorted(s["not_feasible_by_kind"].items())))
    b = s["best"]
    if b is None:
        say("no design meets the tolerance: see pareto.png for the closest ones")
    else:
        vals = ", ".join(f"{k} = {b[k]:g}" for k in s["varied"]) or "the base design"
        say(f"best: {vals}: signal {b['signal']:.3g} x base, max |k_A - 1| = {b['max_abs_dev']:.4f} "
            f"(+- {b['worst_se']:.1g}) at tan eps {b['worst_tan_eps']:g}, beta {b['worst_beta_deg']:g} "
            f"({b['worst_sample']}), footprint {b['footprint_length_m']:.3f} m")
    say(f"wrote {out}/" + ds.attrs.get("files", ""))
    return rc
