"""``roadgonio design``: sweep instrument parameters on Dask; tolerance map, Pareto front, best design."""
from __future__ import annotations

import sys

from roadgonio import api
from roadgonio.errors import count
from roadgonio.cli._common import (
    add_accuracy,
    add_backend,
    add_dask_arguments,
    add_instrument_argument,
    add_mitsuba_variant,
    add_model_variant,
    add_output_options,
    out_arg,
    print_json,
    show_progress,
    text_output,
)


def register(sub) -> None:
    keys = api.design_keys()
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
                    "Resumes an interrupted run. Keys: " + ", ".join(keys)
                    + ", housing.baffles.N.x_m, housing.baffles.N.height_m (N: a baffle of the base [housing]).")
    add_instrument_argument(p)
    p.add_argument("--vary", action="append", default=[], metavar="KEY=LO:HI:N",
                   help="an instrument key and its values: LO:HI:N (linear), LO:HI:N:log, or V1,V2,...; repeat for "
                        "more keys (the grid is their product)")
    p.add_argument("--sample", dest="samples", action="append", default=[], metavar="SAMPLE",
                   help="bundled table name (R1..R4, C1, C2), an r-table file, a model.json or 'lambert'; repeat for "
                        "the surfaces you expect (max |k_A - 1| is over all of them)")
    add_model_variant(p)
    p.add_argument("--second-aperture", action="store_true",
                   help="instead of the k_A sweep: which second aperture setting (each point of the --vary grid applied "
                        "to the instrument) minimises the u of the table a joint correction (`correct --joint`) of the "
                        "two would give; the surface from --measured (a table this instrument measured) or one "
                        "--sample; writes second_aperture.csv/.json/.png and best_second.toml (no journal: an interrupted run "
                        "starts again)")
    p.add_argument("--measured", metavar="FILE", help="with --second-aperture: a table the instrument measured")
    p.add_argument("--u-measured", default=None, metavar="U",
                   help="with --second-aperture: the measurement's relative standard uncertainty (default 1%%, as correct's)")
    p.add_argument("--min-signal", default=None, metavar="F",
                   help="with --second-aperture: least signal of the second setting, relative to the instrument's: "
                        "a fraction (0.25) or a percentage (25%%); default 0.25 (smaller apertures always blur less)")
    p.add_argument("--rays", type=int, default=512, metavar="N",
                   help="with --second-aperture: rays per cell of the forward model (default 512)")
    p.add_argument("--tolerance", default="5%", metavar="T",
                   help="largest acceptable |k_A - 1|: a fraction (0.05) or a percentage (5%%); default 5%%")
    p.add_argument("--cells", default="all", metavar="all|table|LIST",
                   help="all = the 580-cell grid (default); table = the cells tabulated in each sample's r-table; "
                        "LIST = T:B,T:B,... (tan eps : beta deg), e.g. 12:0,12:2,4:0")
    add_backend(p, "design", help_text="k_A backend (default mitsuba)")
    add_accuracy(p)
    p.add_argument("--rel-se", type=float, metavar="E", help="target relative SE per cell (overrides --accuracy)")
    p.add_argument("--seed", type=int, default=0, help="root seed (0 ... 2^63 - 1); design point k gets its own seed point_seed(seed, k), in design.csv")
    add_mitsuba_variant(p)
    add_dask_arguments(p, "default: a local cluster with one worker per core")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/design-INSTRUMENT)")
    p.add_argument("--fresh", action="store_true", help="discard the partial results in --out instead of resuming (with "
                   "--second-aperture: replace another second-aperture study's results there)")
    p.add_argument("--no-plots", action="store_true", help="do not draw pareto.png / tolerance_map.png")
    add_output_options(p, "print the summary as JSON")
    p.set_defaults(func=run, _defaults={d: p.get_default(d) for d in _SWEEP_ONLY + _SECOND_ONLY})


#: options of the k_A sweep that --second-aperture does not use (it predicts u from ray bundles of
#: the whole table, no k_A backend, no tolerance) and the other way round
_SWEEP_ONLY = ("tolerance", "cells", "backend", "accuracy", "rel_se", "workers", "scheduler", "mitsuba_variant")
_SECOND_ONLY = ("measured", "u_measured", "min_signal", "rays")


def _refuse_unused(args, names, why: str) -> None:
    from roadgonio.errors import InputError
    given = [n for n in names if getattr(args, n) != args._defaults[n]]
    if given:
        opts = ", ".join("--" + ("variant" if n == "mitsuba_variant" else n.replace("_", "-")) for n in given)
        raise InputError(f"{opts} {'is' if len(given) == 1 else 'are'} not used {why}", field=opts.split(", ")[0])


def run(args) -> int:
    if args.second_aperture:
        _refuse_unused(args, _SWEEP_ONLY, "with --second-aperture (it predicts the corrected table's u over the "
                                          "whole table from ray bundles: no k_A backend, cells or tolerance)")
        return _run_second(args)
    _refuse_unused(args, _SECOND_ONLY, "without --second-aperture")
    if not args.samples:
        from roadgonio.errors import InputError
        raise InputError("expected at least one --sample (the surfaces you expect)", field="--sample")
    ds = api.design_study(args.instrument, args.vary, args.samples, tolerance=args.tolerance, cells=args.cells,
                          backend=args.backend, accuracy=args.accuracy, rel_se=args.rel_se, seed=args.seed,
                          workers=args.workers, scheduler=args.scheduler, out=out_arg(args), fresh=args.fresh,
                          plots=not args.no_plots, model_variant=args.model_variant,
                          mitsuba_variant=args.mitsuba_variant, progress=show_progress(args))
    s = api.design_summary(ds)
    rc = 1 if s["tables_failed"] else 0
    if s["tables_failed"] and not args.quiet:
        print(f"roadgonio: {s['tables_failed']} tables failed (a worker died): run the same command again to retry "
              "them", file=sys.stderr)
    if args.json:
        print_json(s)
        return rc
    say = text_output(args)
    say(f"design of '{s['instrument']}': {count(s['points'], 'point')} ({' x '.join(s['varied']) or 'base only'}), "
        f"{s['geometry_ok']} geometrically possible, {s['feasible']} within the tolerance {s['tolerance']:g}; "
        f"{s['tables_computed']} tables computed, {s['tables_resumed']} resumed in {s['wall_s']:.1f} s"
        + (f" (the tables {s['compute_wall_s']:.1f} s{', after the cluster' + chr(39) + 's start' if s.get('on_cluster') else ''}: "
           f"{s['design_points_per_hour']:.0f} design points/hour)" if "design_points_per_hour" in s else ""))
    if s["not_feasible_by_kind"]:
        say("not feasible: " + ", ".join(f"{k} {v}" for k, v in sorted(s["not_feasible_by_kind"].items())))
    if s.get("points_not_converged"):
        say(f"not converged: {count(s['points_not_converged'], 'point')} with cells whose backend stopped before its "
            "target (not_converged in design.nc; their max |k_A - 1| carries the SE or bound they stopped at)")
    b = s["best"]
    dark = s["not_feasible_by_kind"].get("signal", 0)
    if b is None and dark and not s["not_feasible_by_kind"].get("tolerance"):
        # (user audit: a pinhole base whose points were all refused for no signal, one of them 2.8 % off,
        # was told that no design meets the tolerance)
        say(f"no design to build: {count(dark, 'point')} detect no light (signal 0: a zero source radius, field or "
            "pupil, the ideal point geometry) and no other point is possible; their max |k_A - 1| is in design.csv")
    elif b is None:
        say("no design meets the tolerance: see " + ("design.csv (max_abs_dev)" if args.no_plots else "pareto.png")
            + " for the closest ones" + (f" ({count(dark, 'point')} detect no light: signal 0, no design)" if dark else ""))
    else:
        vals = ", ".join(f"{k} = {b[k]:g}" for k in s["varied"]) or "the base design"
        say(f"best: {vals}: signal {b['signal']:.3g} x base, max |k_A - 1| = {b['max_abs_dev']:.4f} "
            f"({b['precision']}) at tan eps {b['worst_tan_eps']:g}, beta {b['worst_beta_deg']:g} "
            f"({b['worst_sample']}), footprint {b['footprint_length_m']:.3f} m")
        if b.get("not_converged"):
            say(f"  {count(int(b['not_converged']), 'cell')} of it did not converge (the precision above is the SE or "
                "error estimate the backend stopped at)")
        if s.get("equally_bright", 1) > 1:
            say(f"  the least max |k_A - 1| of {s['equally_bright']} feasible designs with the most signal (signals within "
                f"{s['same_signal_rtol']:.1g} relative count as equal: design.csv has them all)")
        if s.get("indistinct_from_best"):
            say(f"  note: {count(s['indistinct_from_best'], 'other design')} as bright within the precision of its max "
                "|k_A - 1| (2 SE, or the error bounds): the computation does not tell them apart from the best "
                "(design.csv); a finer --accuracy may")
        if b["precision_kind"] == "bound":
            bound = b["worst_error_bound"]
            what = b["bound_words"]
            if b["max_abs_dev"] + bound > s["tolerance"]:
                say(f"  note: its max |k_A - 1| is within its {what} ({bound:.1g}) of the tolerance: the {what} "
                    "does not decide that it is within; recompute the candidates at a finer --accuracy before "
                    "building it")
        elif b["max_abs_dev"] + b["worst_u"] > s["tolerance"]:
            say(f"  note: its max |k_A - 1| is within one standard uncertainty ({b['worst_u']:.1g}) of the tolerance: "
                "recompute the candidates at a finer --accuracy (e.g. default) before building it")
        if (b.get("max_stray_fraction") or 0.0) > 0.0:
            say(f"  its stray light: up to {100 * b['max_stray_fraction']:.2f} % (+- {100 * b['max_stray_u']:.1g}) of the "
                f"road signal at tan eps {b['max_stray_tan_eps']:g}, beta {b['max_stray_beta_deg']:g} "
                f"({b['max_stray_sample']}); without it max |k_A,direct - 1| = {b['max_abs_dev_direct']:.4f} "
                "(every point's: design.csv)")
    if s.get("points_beam_dim"):
        say(f"note: in {count(s['points_beam_dim'], 'point')} the source's beam lights the detected footprint's edge at "
            "less than half its centre's radiance (or not at all: a beam limit): the signal counts the light at the "
            "footprint's centre, so there the detected flux is less than it says (roadgonio render shows the lit part)")
    if s.get("same_signal") is not None and not args.no_plots:
        say(f"every design point has the same signal ({s['same_signal']:.4g} x base): pareto.png shows max |k_A - 1| "
            "point by point instead of against the signal")
    say(f"wrote {ds.attrs['out']}/" + ds.attrs.get("files", ""))
    return rc


def _run_second(args) -> int:
    from roadgonio.errors import InputError
    if len(args.samples) > 1:
        raise InputError("--second-aperture designs for one surface: give one --sample or --measured", field="--sample")
    res = api.second_aperture(args.instrument, args.vary, measured=args.measured,
                              sample=args.samples[0] if args.samples else None, u_measured=args.u_measured,
                              rays=args.rays, seed=args.seed, model_variant=args.model_variant,
                              min_signal=args.min_signal, out=out_arg(args), plots=not args.no_plots,
                              progress=show_progress(args), fresh=args.fresh)
    s = res.summary()
    s["out"], s["written"] = str(res.out), [str(p) for p in res.written]
    if args.json:
        print_json(s)
        return 0
    say = text_output(args)
    a, t, b = res.baselines[0], res.baselines[1], res.best
    say(f"second aperture for '{res.instrument.name}' (surface from {res.surface_from}; {res.settings['backbone_variant']} "
        f"backbone, {res.settings['backbone_choice']}): {len(res.candidates)} setting"
        f"{'' if len(res.candidates) == 1 else 's'}, {res.seconds:.1f} s")
    n = s["counts"]
    say(f"  ranked {n['ranked']}; not ranked: {n['below_min_signal']} below --min-signal "
        f"{res.settings['min_signal']:g} of the instrument's signal, {n['not_feasible']} unable to measure every cell"
        + (", the instrument's own setting (its second measurement is 'measured twice')" if n["own_setting"] else ""))
    for note in res.scope_notes():
        say(f"  note: {note}")
    say(f"  alone: median u {100 * a.u_median:.2f} %, u(S1) {100 * a.u_s1_rel:.2f} %; measured twice: "
        f"{100 * t.u_median:.2f} %, {100 * t.u_s1_rel:.2f} %")
    say("  best second setting: " + ", ".join(f"{k} = {v:g}" for k, v in b.changes.items())
        + f": median u {100 * b.u_median:.2f} %, u(S1) {100 * b.u_s1_rel:.2f} %, signal {b.signal:.2g} x")
    say(f"  {res.verdict()}")
    say(f"  note: {res.u_note()}")
    say(f"  note: {res.u_s1_note()}")
    say(f"  wrote {len(s['written'])} files to {s['out']}")
    return 0
