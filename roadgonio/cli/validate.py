"""``roadgonio validate``: a Monte Carlo backend judged against a float64 reference on the extreme cells."""
from __future__ import annotations

import math
import sys

from roadgonio import api
from roadgonio.cli._common import (
    add_instrument_argument,
    add_mitsuba_variant,
    add_model_variant,
    add_output_options,
    add_sample_argument,
    out_arg,
    print_json,
    text_output,
)


def register(sub) -> None:
    p = sub.add_parser(
        "validate", help="check the Mitsuba (or numpy Monte Carlo) k_A against a float64 reference",
        description="Compute k_A with a Monte Carlo backend (Mitsuba by default) and with a float64 reference on "
                    "a set of cells that includes the extremes (tan eps 0 and 12, beta 0 and 180, the specular "
                    "peak tan 4-12 x beta 0-10, mid cells) and judge each cell: agree, disagree (the difference "
                    "exceeds the t quantile of the SE's degrees of freedom with the two-sided probability of 4 "
                    "normal SEs (5.48 at 15 degrees of freedom, 4 for an SE without them; docs/validation.md) plus the "
                    "reference's bound and the renderer's float32 floor) "
                    "or inconclusive (the reference did not converge, its bound is wider than the test needs, or "
                    "the Monte Carlo backend stopped at its sample cap). Writes validate.csv, validate.json and "
                    "validate.png. Exit status 0 if every cell agrees, 1 if any disagrees, 3 if some are "
                    "inconclusive and none disagrees.")
    add_instrument_argument(p)
    add_sample_argument(p)
    add_model_variant(p)
    p.add_argument("--against", choices=list(api.validate_backends("checked")), default="mitsuba",
                   help="Monte Carlo backend to check (default mitsuba)")
    p.add_argument("--reference", choices=["auto", *api.validate_backends("reference")], default="auto",
                   help="float64 reference: 'reference' (randomised QMC with a 99.9%% confidence bound, converges on "
                        "wide instruments), 'quadrature' (tensor Gauss rules; may stop short at grazing cells), "
                        "'numpy-mc-mesh' (numpy ray-casting Monte Carlo, for mesh samples); auto (default) = "
                        "reference for a flat sample, numpy-mc-mesh for a mesh")
    p.add_argument("--cells", default="extremes", metavar="LIST",
                   help="TAN:BETA[,TAN:BETA...], 'extremes' (default) or 'all'")
    p.add_argument("--rel-se", type=float, default=1e-3, metavar="E",
                   help="target relative standard error of the Monte Carlo backend (default 1e-3)")
    p.add_argument("--rtol", type=float, metavar="R",
                   help="target relative error bound of the reference (default: per cell, a quarter of what "
                        "that cell's test allows, halved; the quadrature: 1e-5)")
    p.add_argument("--ref-max-evals", type=int, metavar="N",
                   help="cap on the reference's integrand evaluations per cell (a cell that reaches it is "
                        "inconclusive)")
    p.add_argument("--seed", type=int, default=0, help="random seed (>= 0) of the Monte Carlo backend")
    p.add_argument("--floor", type=float, metavar="F",
                   help="relative floor added to the allowed difference (default: the measured float32 floor "
                        "for mitsuba, 1e-12, the float64 round-off, for numpy-mc)")
    add_mitsuba_variant(p)
    p.add_argument("--out", metavar="DIR", help="output folder (default out/validate-INSTRUMENT-SAMPLE)")
    add_output_options(p, "print the report (verdict, counts, cells with their verdicts and reasons) as JSON instead "
                          "of the table")
    p.set_defaults(func=run, on_interrupt="interrupted: nothing was written (validate starts over when run again)")


def run(args) -> int:
    say = text_output(args)
    header = [False]

    def show(r):
        if not header[0]:
            say(f"{'tan eps':>7} {'beta':>5} {'k_ref':>10} {'k_' + args.against:>12} {'diff/SE':>8} {'allowed':>8}  "
                "verdict", flush=True)
            header[0] = True
        in_se = r.sigma > 0 and math.isfinite(r.z)
        zs, allowed = (f"{r.z:+8.2f}", f"{r.allowed / r.sigma:8.2f}") if in_se else (f"{'-':>8}", f"{'-':>8}")
        note = "" if r.verdict == "agree" and in_se else f"  ({r.reason})"
        say(f"{r.tan_eps:7g} {r.beta_deg:5g} {r.k_ref:10.6f} {r.k_mc:12.6f} {zs} {allowed}  "
            f"{r.verdict}{note}", flush=True)

    report = api.validate(args.instrument, args.sample, against=args.against, reference=args.reference,
                          cells=args.cells, rel_se=args.rel_se, rtol=args.rtol, ref_max_evals=args.ref_max_evals,
                          seed=args.seed, floor=args.floor, mitsuba_variant=args.mitsuba_variant,
                          model_variant=args.model_variant, out=out_arg(args), on_cell=show)
    if args.json:
        print_json({**api.validation_report_json(report), "out": report["out"]})
    files = report["files"]
    say(api.validation_summary_line(report) + f"; wrote {files['csv']}, validate.json, validate.png.")
    rows = report["rows"]
    bad = [r for r in rows if r.verdict == "disagree"]
    unsure = [r for r in rows if r.verdict == "inconclusive"]
    if bad:
        print("roadgonio validate: " + api.validation_failed_line(report), file=sys.stderr)
    elif unsure:
        print("roadgonio validate: INCONCLUSIVE: " + ", ".join(f"({r.tan_eps:g}, {r.beta_deg:g}) {r.reason}"
                                                               for r in unsure), file=sys.stderr)
    return int(report["exit_status"])
