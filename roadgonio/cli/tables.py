"""``roadgonio tables`` (list the bundled tables) and ``roadgonio table`` (show or convert one)."""
from __future__ import annotations

from roadgonio import api
from roadgonio.cli._common import add_output_options, print_json, text_output


def register(sub) -> None:
    p = sub.add_parser("tables", help="list the bundled CIE r-tables with Q0, S1 and S2",
                       description="List the bundled CIE standard r-tables with their computed Q0, S1, S2 "
                                   "beside the published values.")
    add_output_options(p, "print JSON instead of a table")
    p.set_defaults(func=run_tables)

    p = sub.add_parser("table", help="show or convert an r-table (bundled name or file)",
                       description="Show an r-table's characteristics, or convert it with --to "
                                   "(.rtb = DIALux RTB, .csv = CSV).")
    p.add_argument("table", help="bundled table name (R1..R4, C1, C2) or a .csv/.rtb file")
    p.add_argument("--to", metavar="FILE", help="write the table to FILE (.rtb or .csv)")
    add_output_options(p, "print the characteristics as JSON")
    p.set_defaults(func=run_table)


def run_tables(args) -> int:
    rows = api.list_tables()
    if args.json:
        print_json(rows)
        return 0
    say = text_output(args)
    say(f"{'table':6} {'Q0':>7} {'(CIE)':>6} {'S1':>7} {'(CIE)':>6} {'S2':>6} {'cells':>6}")
    for r in rows:
        say(f"{r['table']:6} {r['Q0']:7.4f} {r['Q0_published']:6.2f} {r['S1']:7.3f} "
            f"{r['S1_published']:6.2f} {r['S2']:6.2f} {r['cells']:6d}")
    say("Q0 by the trapezoidal rule over the tabulated cells (CIE 144 weights differ by a few %).")
    return 0


def run_table(args) -> int:
    info = api.table_info(args.table, to=args.to)
    if args.json:
        print_json(info)
        return 0
    say = text_output(args)
    q0 = "missing" if info["Q0"] is None else f"{info['Q0']:.4f} sr^-1"      # not 'missing sr^-1' (audit 22)
    say(f"{info['table']}: Q0 = {q0}, S1 = {'missing' if info['S1'] is None else api.s1_text(info['S1'])}, S2 = {_f(info['S2'], '.2f')}, "
        f"{info['cells']} tabulated cells, max r = {_f(None if info['r_max'] is None else info['r_max'] * 1e4, '.4g')} "
        "x 1e-4 sr^-1")
    missing = [k for k in ("S1", "Q0", "S2") if info[k] is None]
    if missing:
        say(f"  missing: {', '.join(missing)} ({_why_missing(missing)})")
    for note in info["notes"]:
        say(f"  note: {note}")
    if info.get("reading_note"):
        say(f"  read: {info['reading_note']}")
    if "written" in info:
        say(f"wrote {info['written']}")
    return 0


def _why_missing(missing) -> str:
    why = []
    if "S1" in missing:
        why.append("S1 = r(beta 0, tan 2) / r(beta 0, tan 0) needs both cells, r(0, 0) > 0")
    if "Q0" in missing:
        why.append("Q0 needs a grid cell with four tabulated corners")
    if "S2" in missing and "Q0" not in missing:
        why.append("S2 = Q0 / r(0, 0) needs r(0, 0) > 0")
    return "; ".join(why)


def _f(v, fmt: str) -> str:
    """A characteristic, or 'missing' when the table lacks the cells it needs (NaN)."""
    return "missing" if v is None or v != v else format(v, fmt)
