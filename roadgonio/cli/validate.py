"""``roadgonio validate``: a Monte Carlo backend judged against a float64 reference on the extreme cells."""
from __future__ import annotations

import math
import sys
from pathlib import Path

from roadgonio.errors import InputError
from roadgonio.cli._common import (
    add_instrument_argument,
    add_output_options,
    add_sample_argument,
    check_seed,
    load_inputs,
    select_variant,
    text_output,
)


def register(sub) -> None:
    p = sub.add_parser(
        "validate", help="check the Mitsuba (or numpy Monte Carlo) k_A against a float64 reference",
        description="Compute k_A with a Monte Carlo backend (Mitsuba by default) and with a float64 reference on "
                    "a set of cells that includes the extremes (tan eps 0 and 12, beta 0 and 180, the specular "
                    "peak tan 4-12 x beta 0-10, mid cells) and judge each cell: agree, disagree (the difference "
                    "exceeds 4 standard errors plus the reference's error bound and the renderer's float32 floor) "
                    "or inconclusive (the reference did not converge, its bound is wider than the test needs, or "
                    "the Monte Carlo backend stopped at its sample cap). Writes validate.csv, validate.json and "
                    "validate.png. Exit status 0 if every cell agrees, 1 if any disagrees, 3 if some are "
                    "inconclusive and none disagrees.")
    add_instrument_argument(p)
    add_sample_argument(p)
    p.add_argument("--against", choices=["mitsuba", "numpy-mc"], default="mitsuba",
                   help="Monte Carlo backend to check (default mitsuba)")
    p.add_argument("--reference", choices=["auto", "reference", "quadrature", "numpy-mc-mesh"], default="auto",
                   help="float64 reference: 'reference' (randomised QMC with a 99.9%% error bound, converges on "
                        "wide instruments), 'quadrature' (tensor Gauss rules; may stop short at grazing cells), "
                        "'numpy-mc-mesh' (numpy ray-casting Monte Carlo, for mesh samples); auto (default) = "
                        "reference for a flat sample, numpy-mc-mesh for a mesh")
    p.add_argument("--cells", metavar="LIST",
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
                   help="relative float32 floor added to the allowed difference (default: the measured value "
                        "for the backend, 0 for numpy-mc)")
    p.add_argument("--variant", help="Mitsuba variant (default llvm_ad_rgb)")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/validate-INSTRUMENT-SAMPLE)")
    add_output_options(p, "print the report (verdict, counts, cells with their verdicts and reasons) as JSON instead "
                          "of the table")
    p.set_defaults(func=run, on_interrupt="interrupted: nothing was written (validate starts over when run again)")


def run(args) -> int:
    from roadgonio.engines.validate import parse_cells, report_json, summary_line, validate, write_outputs
    from roadgonio.fileio import to_json
    for name, v in (("--rel-se", args.rel_se), ("--rtol", args.rtol)):
        if v is not None and not (math.isfinite(v) and 0 < v < 1):
            raise InputError(f"expected a relative value in (0, 1), got {v}", field=name)
    if args.floor is not None and not (math.isfinite(args.floor) and args.floor >= 0):
        raise InputError(f"expected a floor >= 0, got {args.floor}", field="--floor")
    if args.ref_max_evals is not None and args.ref_max_evals < 1:
        raise InputError(f"expected a positive number of evaluations, got {args.ref_max_evals}", field="--ref-max-evals")
    check_seed(args.seed)
    cells = parse_cells(args.cells)
    instrument, model = load_inputs(args)
    select_variant(args.against, args.variant)
    mc_settings = {}
    if args.against == "mitsuba" and args.variant:
        mc_settings["variant"] = args.variant
    ref_settings = {}
    if args.ref_max_evals is not None:
        ref_settings["max_evals"] = args.ref_max_evals
    sample_name = Path(args.sample).stem if Path(args.sample).exists() else args.sample
    out_dir = Path(args.out) if args.out else Path("out") / f"validate-{instrument.name}-{sample_name}"
    from roadgonio.fileio import check_writable
    check_writable(out_dir)          # an unwritable --out fails now, not after the computation
    say = text_output(args)
    say(f"{'tan eps':>7} {'beta':>5} {'k_ref':>10} {'k_' + args.against:>12} {'diff/SE':>8} {'allowed':>8}  verdict",
        flush=True)

    def show(r):
        allowed = r.allowed / r.sigma if r.sigma > 0 else math.inf
        note = "" if r.verdict == "agree" else f"  ({r.reason})"
        say(f"{r.tan_eps:7g} {r.beta_deg:5g} {r.k_ref:10.6f} {r.k_mc:12.6f} {r.z:+8.2f} {allowed:8.2f}  "
            f"{r.verdict}{note}", flush=True)

    report = validate(instrument, model, cells, against=args.against, reference=args.reference, rel_se=args.rel_se,
                      rtol=args.rtol, seed=args.seed, floor=args.floor, mc_settings=mc_settings,
                      ref_settings=ref_settings, on_cell=show)
    from roadgonio.provenance import provenance
    report.update(provenance(instrument=instrument, model=model, settings=report["settings"]))
    report["sample"] = sample_name
    paths = write_outputs(report, out_dir)
    if args.json:
        print(to_json({**report_json(report), "out": str(out_dir)}))
    say(summary_line(report) + f"; wrote {paths['csv']}, {paths['json'].name}, {paths['png'].name}.")
    rows = report["rows"]
    bad = [r for r in rows if r.verdict == "disagree"]
    unsure = [r for r in rows if r.verdict == "inconclusive"]
    if bad:
        print("roadgonio validate: FAILED: " + ", ".join(f"({r.tan_eps:g}, {r.beta_deg:g}) {r.z:+.1f} SE"
                                                         for r in bad), file=sys.stderr)
    elif unsure:
        print("roadgonio validate: INCONCLUSIVE: " + ", ".join(f"({r.tan_eps:g}, {r.beta_deg:g}) {r.reason}"
                                                               for r in unsure), file=sys.stderr)
    return int(report["exit_status"])
