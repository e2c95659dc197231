"""``roadgonio compare A B``: two r-tables side by side (ratio map B / A, S1, S2, Q0), PNG + CSV."""
from __future__ import annotations

from pathlib import Path

from roadgonio.cli._common import add_output_options


def register(sub) -> None:
    p = sub.add_parser("compare", help="compare two r-tables: ratio map B/A and S1/S2/Q0 side by side",
                       description="Compare two r-tables (bundled names or .csv/.rtb files) cell by cell: writes the "
                                   "ratio map r(B)/r(A) as PNG and CSV, and prints S1, S2, Q0 of both.")
    p.add_argument("a", metavar="A", help="first table (the reference of the ratio)")
    p.add_argument("b", metavar="B", help="second table")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/compare-A-B)")
    p.add_argument("--no-plots", action="store_true", help="do not draw the ratio map")
    add_output_options(p, json_help="print the comparison as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from roadgonio.fileio import to_json
    from roadgonio.road.compare import compare_csv, compare_png, compare_tables, default_out
    from roadgonio.road.report import write_together
    from roadgonio.surface.rtable import load_table

    a, b = load_table(args.a), load_table(args.b)
    if a.name == b.name:
        b = b.with_values(b.r, name=b.name + "#2")
    res = compare_tables(a, b)
    out = Path(args.out) if args.out else default_out(a, b)
    summary = {k: v for k, v in res.items() if k != "ratio"}
    from roadgonio.provenance import provenance
    files = {"compare.csv": compare_csv(a, b, res["ratio"]),
             "compare.json": to_json({**summary, **provenance()}) + "\n"}
    if not args.no_plots:
        files["compare.png"] = compare_png(res, a, b)
    written = write_together(out, files)
    if args.json:
        print(to_json({**summary, "written": [str(p) for p in written]}))
    elif not args.quiet:
        ca, cb = res["characteristics"][a.name], res["characteristics"][b.name]
        print(f"{'':8} {a.name[:16]:>16} {b.name[:16]:>16}")
        for key, fmt in (("S1", "{:16.3f}"), ("S2", "{:16.3f}"), ("Q0", "{:16.4f}"), ("cells", "{:16d}")):
            print(f"{key:8} " + " ".join("-".rjust(16) if c[key] is None else fmt.format(c[key]) for c in (ca, cb)))
        lc = res["largest_change_at"]
        print(f"r({b.name}) / r({a.name}) over {res['cells_compared']} cells: {res['ratio_min']:.3g} ... "
              f"{res['ratio_max']:.3g} (median {res['ratio_median']:.3g}); largest change x{lc['ratio']:.3g} at "
              f"tan eps {lc['tan_eps']:g}, beta {lc['beta_deg']:g} deg")
        print(f"wrote {len(written)} files to {out}")
    return 0
