"""``roadgonio uncertainty``: Monte Carlo (JCGM 101) and GUM uncertainty of an r-table from the
instrument's angle and position errors, with and without the aperture effect."""
from __future__ import annotations

import sys

from roadgonio import api
from roadgonio.cli._common import (
    add_backend,
    add_dask_arguments,
    add_instrument_argument,
    add_mitsuba_variant,
    add_model_variant,
    add_output_options,
    add_sample_argument,
    out_arg,
    positive_int,
    print_json,
    show_progress,
    text_output,
)


def register(sub) -> None:
    spec_help, input_help = api.sigma_spec_help()
    keys = "; ".join(f"{k}: {v}" for k, v in input_help.items())
    p = sub.add_parser(
        "uncertainty", help="Monte Carlo (GUM Supplement 1) uncertainty of a measured r-table from the "
                            "instrument's angle/position errors",
        description="Propagate the instrument's geometric errors to the r-table it measures, by the Monte Carlo "
                    "method of JCGM 101:2008 beside the first-order GUM (with the JCGM 101 section 8 validation). "
                    "Each trial draws ONE error set shared by every cell (errors of one instrument are correlated "
                    "across the table) and computes the measured table without and with the aperture effect "
                    "(k_A of the perturbed geometry from a validated surrogate over exact backend evaluations). "
                    "Outputs per cell: mean, standard uncertainty, 95 % probabilistically symmetric and shortest "
                    "coverage intervals, GUM u and its validation; distributions of Q0 and S1. "
                    f"{spec_help}. Input keys: {keys}.",
        epilog="Exit status 0 when done; 3 when an --adaptive run stopped at --max-trials before every output "
               "was stable to --digits (inconclusive, as for 'roadgonio validate': the results are written, and one "
               "line on stderr says which target was not met and at what cap); 2 for bad input, 4 for work lost "
               "on a Dask cluster.")
    add_instrument_argument(p)
    add_sample_argument(p)
    add_model_variant(p)
    p.add_argument("--sigma", required=True, metavar="SPEC",
                   help="standard deviations and distributions of the errors, e.g. 'alpha_deg=0.01,eps_deg=0.05:rect,"
                        "beta_deg=0.1,tilt_x_deg=0.02,tilt_y_deg=0.02,source_distance_m=0.002,"
                        "detector_distance_m=0.005', or a TOML file with the same keys")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--trials", type=positive_int, default=50_000, metavar="N",
                   help="number of Monte Carlo trials (default 50000)")
    g.add_argument("--adaptive", action="store_true",
                   help="adaptive Monte Carlo, JCGM 101 7.9: batches until the mean, u and interval ends of every "
                        "output are stable to --digits significant digits of u (at most --max-trials; stopped there "
                        "before, exit status 3)")
    p.add_argument("--digits", type=int, default=2, choices=[1, 2, 3],
                   help="n_dig, significant digits of u for the adaptive rule and the GUM validation (default 2)")
    p.add_argument("--max-trials", type=positive_int, metavar="N",
                   help="cap of the adaptive run (default 200000; with --adaptive only)")
    p.add_argument("--batch", type=positive_int, metavar="N",
                   help="adaptive batch size (default max(100/(1-p), 10^4); with --adaptive only)")
    p.add_argument("--coverage", type=float, default=0.95, metavar="P", help="coverage probability (default 0.95)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1); the same seed repeats the result")
    p.add_argument("--illuminance", choices=["nominal", "measured"], default="nominal",
                   help="nominal (default): the instrument is calibrated at the nominal geometry, so a source "
                        "distance error scales E by (D_S0/D_S)^2 and the local incidence angle enters via "
                        "cos(theta_i'); measured: horizontal illuminance measured in situ for every cell")
    p.add_argument("--cells", choices=["standard", "all"], default="standard",
                   help="standard (default): the tabulated cells of the CIE tables (396); all: the 580-cell grid")
    p.add_argument("--no-aperture", action="store_true", help="skip the case with the aperture effect")
    add_backend(p, "uncertainty", default=None,
                help_text="k_A backend of the surrogate's exact evaluations (default mitsuba with ONE seed for every "
                          "design point, so the Monte Carlo noise largely cancels in the differences the surrogate "
                          "fits; quadrature: deterministic float64, slower)")
    p.add_argument("--rel-se", type=float, metavar="E",
                   help="backend tolerance (default " + ", ".join(
                       f"{n}: {k} {v:g}" for n, (k, v) in api.study_tolerances().items()) + ")")
    p.add_argument("--surrogate", choices=["star", "ccd"],
                   help="design of exact k_A tables: ccd (default: full quadratic with interactions, 27 tables for "
                        "5 coordinates) or star (2d+1 = 11 tables: gradient and curvature per coordinate, about "
                        "half the time; in bench/bench_uncertainty.py its worst-cell error was 0.43 u(r) against 0.07 u(r) "
                        "for ccd)")
    p.add_argument("--validation", type=int, metavar="N",
                   help="held-out trials with exact k_A to measure the surrogate's error (default 4)")
    p.add_argument("--threads", type=positive_int, metavar="N", help="worker threads (default: up to 2)")
    add_mitsuba_variant(p)
    add_dask_arguments(p, "for the exact k_A tables of the surrogate design; default: in this process")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/uncertainty-INSTRUMENT-SAMPLE)")
    p.add_argument("--no-plots", action="store_true", help="do not draw the PNG pictures")
    p.add_argument("--fresh", action="store_true", help="replace the results of a different run in --out (without it "
                                                        "such a folder is refused)")
    add_output_options(p, "print the summary as JSON instead of text")
    p.set_defaults(func=run, on_interrupt="interrupted: nothing was written; an uncertainty run keeps no partial "
                                        "results and starts over when run again")


def run(args) -> int:
    # the pictures are drawn by a helper process that loads matplotlib while the trials run
    with api.figure_process(enabled=not args.no_plots) as figures:
        res = api.estimate_uncertainty(
            args.instrument, args.sample, args.sigma, trials=args.trials, adaptive=args.adaptive, digits=args.digits,
            batch=args.batch, seed=args.seed, coverage=args.coverage, cells=args.cells,
            aperture=not args.no_aperture, backend=args.backend, rel_se=args.rel_se, illuminance=args.illuminance,
            surrogate=args.surrogate, validation=args.validation, threads=args.threads, workers=args.workers,
            scheduler=args.scheduler, mitsuba_variant=args.mitsuba_variant, model_variant=args.model_variant,
            out=out_arg(args), fresh=args.fresh, plots=not args.no_plots, figures=figures,
            progress=show_progress(args), max_trials=args.max_trials)
    if args.json:
        d = api.uncertainty_result_json(res)
        d["written"] = [str(p) for p in res.written]
        print_json(d)
    else:
        say = text_output(args)
        for line in api.uncertainty_summary_lines(res):
            say(line)
        say(f"wrote {len(res.written)} files to {res.out}")
    status, line = api.uncertainty_not_converged(res)
    if line:
        # inconclusive, as validate's 3: a script must not take a capped run for a converged one (user audit)
        print(f"roadgonio uncertainty: {line}", file=sys.stderr)
    return status
