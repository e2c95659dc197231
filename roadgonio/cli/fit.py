"""``roadgonio fit TABLE``: fit the road BRDF model to an r-table."""
from __future__ import annotations


from roadgonio import api
from roadgonio.cli._common import add_output_options, out_arg, print_json, show_progress, text_output
from roadgonio.errors import InputError


def register(sub) -> None:
    p = sub.add_parser(
        "fit", help="fit the road BRDF model to an r-table (bundled name or .csv/.rtb file)",
        description="Fit the road BRDF model (paper eq. 4) to an r-table, skipping blank cells. Writes "
                    "DIR/model.json (loadable with RoadModel.load), DIR/residuals.csv and DIR/fit.png. "
                    "Deviations are in % of the table's maximum r, as in the paper.")
    p.add_argument("table", help="bundled table name (R1..R4, C1, C2) or a .csv/.rtb file")
    p.add_argument("--variant", dest="model_variant", default="power", choices=api.model_variants(),
                   help="model variant (default 'power', the paper's model)")
    p.add_argument("--out", metavar="DIR", help="output folder (default fit-<table>-<variant>)")
    add_output_options(p, "print {table, variant, max_dev_pct, rms_dev_pct, params, descriptors, seconds} as JSON")
    p.add_argument("--seed", type=int, default=0, help="seed of the global search (default 0)")
    p.add_argument("--fix", dest="fixed", metavar="NAME=VALUE", action="append", default=[],
                   help="hold a parameter at a value (repeatable), e.g. --fix n_phong=50; the grazing "
                        "attenuation g_a..g_t, theta_l_deg is never fitted, set it here")
    p.add_argument("--no-plot", action="store_true", help="do not write fit.png")
    p.add_argument("--fresh", action="store_true",
                   help="replace the results of a different fit in --out (without it such a folder is refused)")
    p.set_defaults(func=run, on_interrupt="interrupted: no model was written (fit starts over when run again)")


def _parse_fix(items: list[str]) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise InputError(f"expected NAME=VALUE, got {item!r}", field="--fix")
        try:
            v = float(value)
        except ValueError:
            raise InputError(f"expected a number after '=', got {value!r}", field=f"--fix {name.strip()}") from None
        if name.strip() in out and out[name.strip()] != v:
            # the last one won without a word (user audit, session 19)
            raise InputError(f"{name.strip()} is fixed twice, at {out[name.strip()]:g} and {v:g}; expected one value",
                             field=f"--fix {name.strip()}")
        out[name.strip()] = v
    return out


def run(args) -> int:
    result = api.fit(args.table, args.model_variant, seed=args.seed, fixed=_parse_fix(args.fixed),
                     out=out_arg(args), fresh=args.fresh, plot=not args.no_plot, progress=show_progress(args))
    if args.json:
        print_json(result.to_json_dict())
        return 0
    say = text_output(args)
    P = result.model.params
    say(f"{result.table.name} ({result.variant}): max |dev| {result.max_dev_pct:.2f} %, RMS {result.rms_dev_pct:.2f} % "
        f"of max r, {int(result.table.mask.sum())} cells, {result.seconds:.1f} s")
    shown = result.shown_params()
    say("  " + ", ".join(f"{k}={getattr(P, k):.5g}" for k in shown))
    d = result.descriptors()

    def pair(k: str) -> str:
        t, m = d["table"][k], d["model"][k]
        text = f"{k} table {'missing' if t is None else f'{t:.4g}'}, model {'missing' if m is None else f'{m:.4g}'}"
        return text if t is None or m is None else f"{text} ({100 * (m / t - 1):+.1f} %)"
    say("  " + "; ".join(pair(k) for k in ("Q0", "S1", "S2")) + " (CIE 144; the model is the sample later "
        "commands use)")
    say("  worst cells (model - table, % of max r): " + "; ".join(
        f"tan eps {t:g}, beta {b:g} deg: {d:+.2f} %" for t, b, d in result.worst_cells(3)))
    for note in result.notes():
        say(f"  note: {note}")
    say("wrote " + ", ".join(str(p) for p in result.written))
    return 0
