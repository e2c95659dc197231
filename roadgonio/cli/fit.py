"""``roadgonio fit TABLE``: fit the road BRDF model to an r-table."""
from __future__ import annotations

import csv
import io
import sys
from pathlib import Path

from roadgonio.cli._common import add_output_options, show_progress, text_output
from roadgonio.errors import InputError
from roadgonio.fileio import to_json
from roadgonio.surface.model import DEFAULT_VARIANT, PARAM_NAMES, VARIANT_PARAMS, VARIANTS


def register(sub) -> None:
    p = sub.add_parser(
        "fit", help="fit the road BRDF model to an r-table (bundled name or .csv/.rtb file)",
        description="Fit the road BRDF model (paper eq. 4) to an r-table, skipping blank cells. Writes "
                    "DIR/model.json (loadable with RoadModel.load), DIR/residuals.csv and DIR/fit.png. "
                    "Deviations are in % of the table's maximum r, as in the paper.")
    p.add_argument("table", help="bundled table name (R1..R4, C1, C2) or a .csv/.rtb file")
    p.add_argument("--variant", default=DEFAULT_VARIANT, choices=VARIANTS,
                   help=f"model variant (default {DEFAULT_VARIANT!r}, the paper's model)")
    p.add_argument("--out", metavar="DIR", help="output folder (default fit-<table>-<variant>)")
    add_output_options(p, "print {table, variant, max_dev_pct, rms_dev_pct, params, seconds} as JSON")
    p.add_argument("--seed", type=int, default=0, help="seed of the global search (default 0)")
    p.add_argument("--fix", metavar="NAME=VALUE", action="append", default=[],
                   help="hold a parameter at a value (repeatable), e.g. --fix n_phong=50; the grazing "
                        "attenuation g_a..g_t, theta_l_deg is never fitted, set it here")
    p.add_argument("--no-plot", action="store_true", help="do not write fit.png")
    p.set_defaults(func=run, on_interrupt="interrupted: no model was written (fit starts over when run again)")


def _parse_fix(items: list[str]) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in PARAM_NAMES:
            raise InputError(f"expected NAME=VALUE with NAME one of {', '.join(PARAM_NAMES)}, got {item!r}",
                             field="--fix")
        try:
            out[name] = float(value)
        except ValueError:
            raise InputError(f"expected a number after '=', got {value!r}", field=f"--fix {name}") from None
    return out


def residuals_csv(result) -> str:
    t = result.table
    rm = result.r_model
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["tan_eps", "beta_deg", "r_table_x1e4", "r_model_x1e4", "dev_pct_of_max_r"])
    for i, te in enumerate(t.tan_eps):
        for j, b in enumerate(t.beta_deg):
            if not t.mask[i, j]:
                continue
            w.writerow([f"{te:g}", f"{b:g}", f"{t.r[i, j] * 1e4:.6g}", f"{rm[i, j] * 1e4:.6g}",
                        f"{result.residual_pct[i, j]:.4f}"])
    return out.getvalue()


def run(args) -> int:
    from roadgonio.surface.fit import fit_table
    from roadgonio.surface.rtable import load_table

    from roadgonio.cli._common import check_seed
    check_seed(args.seed)
    table = load_table(args.table)
    fixed = _parse_fix(args.fix)
    out = Path(args.out) if args.out else Path(f"fit-{table.name}-{args.variant}")
    if out.exists() and not out.is_dir():
        raise InputError("expected a folder for the results, but it is a file", path=out, field="--out")

    bar = None
    if show_progress(args):
        from tqdm import tqdm
        bar = tqdm(total=1, desc=f"fit {table.name} ({args.variant})", unit="gen", file=sys.stderr, leave=False)

    def progress(done: int, total: int) -> None:
        if bar is not None:
            bar.total = total
            bar.n = done
            bar.refresh()

    try:
        result = fit_table(table, args.variant, seed=args.seed, fixed=fixed, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    from roadgonio.fileio import OutputGroup
    from roadgonio.surface.sample import check_not_degenerate
    check_not_degenerate(result.model, path=args.table if Path(args.table).suffix else None)
    with OutputGroup(out) as g:          # model.json, residuals.csv, fit.png: all or none
        g.json("model.json", result.model.to_json_dict())
        g.text("residuals.csv", residuals_csv(result))
        if not args.no_plot:
            from roadgonio.surface.fitplot import plot_fit
            plot_fit(result, g.path("fit.png"))
    say = text_output(args)
    if args.json:
        print(to_json(result.to_json_dict()))
    else:
        P = result.model.params
        say(f"{table.name} ({args.variant}): max |dev| {result.max_dev_pct:.2f} %, RMS {result.rms_dev_pct:.2f} % "
              f"of max r, {int(table.mask.sum())} cells, {result.seconds:.1f} s")
        shown = PARAM_NAMES[:9] + VARIANT_PARAMS.get(args.variant, ())
        say("  " + ", ".join(f"{k}={getattr(P, k):.5g}" for k in shown))
        say("  worst cells (model - table, % of max r): " + "; ".join(
            f"tan eps {t:g}, beta {b:g} deg: {d:+.2f} %" for t, b, d in result.worst_cells(3)))
        say(f"wrote {out / 'model.json'}, {out / 'residuals.csv'}"
              + ("" if args.no_plot else f", {out / 'fit.png'}"))
    return 0
