"""``roadgonio compare A B``: two r-tables side by side (ratio map B / A, S1, S2, Q0), PNG + CSV."""
from __future__ import annotations

from roadgonio import api
from roadgonio.cli._common import add_output_options, out_arg, print_json
from roadgonio.errors import count


def register(sub) -> None:
    p = sub.add_parser("compare", help="compare two r-tables: ratio map B/A and S1/S2/Q0 side by side",
                       description="Compare two r-tables (bundled names or .csv/.rtb files) cell by cell: writes the "
                                   "ratio map r(B)/r(A) as PNG and CSV, and prints S1, S2, Q0 of both.")
    p.add_argument("a", metavar="A", help="first table (the reference of the ratio)")
    p.add_argument("b", metavar="B", help="second table")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/compare-A-B)")
    p.add_argument("--no-plots", action="store_true", help="do not draw the ratio map (an earlier run's compare.png in --out is "
                                                                   "removed)")
    add_output_options(p, json_help="print the comparison as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    res = api.compare_tables(args.a, args.b, out=out_arg(args), plots=not args.no_plots)
    if args.json:
        print_json({k: v for k, v in res.items() if k not in ("a", "b", "out", "ratio")})
    elif not args.quiet:
        a, b = res["a"], res["b"]
        ca, cb = res["characteristics"][a], res["characteristics"][b]
        n = max(16, len(a), len(b))        # a file's name in full (measured.rtb (R3))
        print(f"{'':8} {a:>{n}} {b:>{n}}")
        for key, fmt in (("S1", ".3f"), ("S2", ".3f"), ("Q0", ".4f"), ("cells", "d")):
            # S1 to the digits that show its side of a class limit, as classify prints it; a missing one
            # in words (user audit, session 44: S1 0.84997, class R2, printed 0.850; '-' for missing)
            print(f"{key:8} " + " ".join("missing".rjust(n) if c[key] is None
                                         else api.s1_text(c[key]).rjust(n) if key == "S1"
                                         else format(c[key], f"{n}{fmt}") for c in (ca, cb)))
        print(f"r({b}) / r({a}) over {res['cells_compared']} cells: {api.ratio_range_text(res)}; "
              f"{api.largest_change_text(res)}")
        # cells one table has and the other lacks (user audit, session 37: in the JSON only)
        for key, what in (("cells_zero_in_A", f"with r({a}) = 0 < r({b})"), ("cells_zero_in_B", f"with r({b}) = 0 < r({a})"),
                          ("cells_ratio_undefined", "with 0 in both: no ratio"), ("cells_only_in_A", f"only in {a}"),
                          ("cells_only_in_B", f"only in {b}")):
            if res[key]:
                print(f"  {count(res[key], 'cell')} {what}")
        for note in res.get("notes", ()):
            print(f"  note: {note}")
        print(f"wrote {len(res['written'])} files to {res['out']}")
    return 0
