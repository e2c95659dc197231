"""``roadgonio validate``: the float64 quadrature against a Monte Carlo backend on the extreme cells."""
from __future__ import annotations

import math
import sys
from pathlib import Path

from roadgonio.errors import InputError
from roadgonio.cli._common import (
    add_instrument_argument,
    add_output_options,
    add_sample_argument,
    load_inputs,
    select_variant,
    text_output,
)


def register(sub) -> None:
    p = sub.add_parser(
        "validate", help="check the Mitsuba (or numpy Monte Carlo) k_A against the float64 quadrature",
        description="Compute k_A with the deterministic float64 quadrature and with a Monte Carlo backend on a set "
                    "of cells that includes the extremes (tan eps 0 and 12, beta 0 and 180, the specular peak "
                    "tan 4-12 x beta 0-10, mid cells); print each difference in standard errors; write "
                    "validate.csv, validate.json and validate.png. Exit status 1 when a cell disagrees by more than "
                    "4 standard errors plus the float32 floor of the renderer.")
    add_instrument_argument(p)
    add_sample_argument(p)
    p.add_argument("--against", choices=["mitsuba", "numpy-mc"], default="mitsuba",
                   help="Monte Carlo backend to check (default mitsuba)")
    p.add_argument("--cells", metavar="LIST",
                   help="TAN:BETA[,TAN:BETA...], 'extremes' (default) or 'all'")
    p.add_argument("--rel-se", type=float, default=1e-3, metavar="E",
                   help="target relative standard error of the Monte Carlo backend (default 1e-3)")
    p.add_argument("--rtol", type=float, default=1e-5, metavar="R",
                   help="relative tolerance of the quadrature (default 1e-5)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the Monte Carlo backend")
    p.add_argument("--floor", type=float, metavar="F",
                   help="relative float32 floor added to the allowed difference (default: the measured value "
                        "for the backend, 0 for numpy-mc)")
    p.add_argument("--variant", help="Mitsuba variant (default llvm_ad_rgb)")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/validate-INSTRUMENT-SAMPLE)")
    add_output_options(p, "print {ok, against, n_sigma, floor, seconds, cells: [...]} as JSON at the end "
                          "(no per-cell lines)")
    p.set_defaults(func=run)


def run(args) -> int:
    from roadgonio.engines.validate import parse_cells, validate, write_outputs
    for name, v in (("--rel-se", args.rel_se), ("--rtol", args.rtol)):
        if not (math.isfinite(v) and 0 < v < 1):
            raise InputError(f"expected a relative value in (0, 1), got {v}", field=name)
    if args.floor is not None and not (math.isfinite(args.floor) and args.floor >= 0):
        raise InputError(f"expected a floor >= 0, got {args.floor}", field="--floor")
    cells = parse_cells(args.cells)
    instrument, model = load_inputs(args)
    select_variant(args.against, args.variant)
    mc_settings = {}
    if args.against == "mitsuba":
        if args.variant:
            mc_settings["variant"] = args.variant
    sample_name = Path(args.sample).stem if Path(args.sample).exists() else args.sample
    out_dir = Path(args.out) if args.out else Path("out") / f"validate-{instrument.name}-{sample_name}"

    say = text_output(args)
    say(f"{'tan eps':>7} {'beta':>5} {'k_quad':>10} {'k_' + args.against:>12} {'diff/SE':>8} {'allowed':>8}  ok",
        flush=True)

    def show(r):
        allowed = r.allowed / r.sigma if r.sigma > 0 else math.inf
        say(f"{r.tan_eps:7g} {r.beta_deg:5g} {r.k_quad:10.6f} {r.k_mc:12.6f} {r.z:+8.2f} {allowed:8.2f}  "
            f"{'yes' if r.ok else 'NO'}", flush=True)

    report = validate(instrument, model, cells, against=args.against, rel_se=args.rel_se, rtol=args.rtol,
                      seed=args.seed, floor=args.floor, mc_settings=mc_settings, on_cell=show)
    from roadgonio.provenance import provenance
    report.update(provenance(instrument=instrument, model=model, settings=report["settings"]))
    report["sample"] = sample_name
    paths = write_outputs(report, out_dir)
    rows = report["rows"]
    bad = [r for r in rows if not r.ok]
    worst = max(rows, key=lambda r: abs(r.z))
    if args.json:
        from dataclasses import asdict

        from roadgonio.fileio import to_json
        print(to_json({"ok": report["ok"], "against": report["against"], "n_sigma": report["n_sigma"],
                       "floor": report["floor"], "seconds": report["seconds"], "out": str(out_dir),
                       "cells": [asdict(r) for r in rows]}))
    say(f"{len(rows) - len(bad)} of {len(rows)} cells agree within {report['n_sigma']:g} SE + float32 floor "
        f"{report['floor']:.1e} (worst {worst.z:+.2f} SE at tan eps {worst.tan_eps:g}, beta {worst.beta_deg:g}); "
        f"{report['seconds']:.1f} s. Wrote {paths['csv']}, {paths['json'].name}, {paths['png'].name}.")
    if bad:
        print("roadgonio validate: FAILED: " + ", ".join(f"({r.tan_eps:g}, {r.beta_deg:g}) {r.z:+.1f} SE"
                                                         for r in bad), file=sys.stderr)
        return 1
    return 0
