"""``roadgonio classify T``: the CIE road-surface class of an r-table by S1 (R, C and N systems), its Q0,
and the nearest bundled CIE table in (S1, Q0)."""
from __future__ import annotations

from roadgonio import api
from roadgonio.cli._common import add_output_options, print_json


def register(sub) -> None:
    p = sub.add_parser("classify", help="CIE class of an r-table by S1 and Q0 (R1-R4, C1-C2, N1-N4)",
                       description="Classify an r-table by its specular factor S1 with the CIE 144 class limits "
                                   "(R1 < 0.42 <= R2 < 0.85 <= R3 < 1.35 <= R4; C1 < 0.40 <= C2; N1 < 0.28 <= N2 < "
                                   "0.60 <= N3 < 1.30 <= N4) and give its Q0 against the class standard and the "
                                   "nearest bundled CIE table in (S1, Q0): the distance counts each coordinate in "
                                   "standard deviations of that coordinate over the six bundled tables (sd).")
    p.add_argument("table", metavar="T", help="bundled name (R1..R4, C1, C2) or .csv/.rtb file")
    add_output_options(p, json_help="print JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    res = api.classify_table(args.table)
    if args.json:
        print_json(res)
    elif not args.quiet:
        q0 = "missing" if res["Q0"] is None else f"{res['Q0']:.4f} sr^-1"
        s2 = "missing" if res["S2"] is None else f"{res['S2']:.2f}"
        print(f"{res['table']}: S1 = {api.s1_text(res['S1'])}, Q0 = {q0}, S2 = {s2}")
        for system, c in res["classes"].items():
            scale = (f"x{c['Q0_scale']:.3f}" if c["Q0_scale"] is not None
                     else "missing" if res["Q0"] is None else "not comparable (note)")
            margin = c["S1_margin_to_limit"]
            print(f"  {system} system: {c['class']} (S1 {margin:.3f}{'' if margin >= 5e-4 else f' ({margin:.2g})'} "
                  "from the nearest class limit); "
                  f"standard Q0 {c['standard_Q0']:.4f}" + ("" if c["bundled"] else " (published; table not bundled)")
                  + f", this table {scale}")
        if res["nearest_bundled"]:
            near = res["nearest_bundled"][0]
            basis = res["nearest_basis"]
            print(f"  nearest bundled table {basis + ',' if basis else 'in (S1, Q0):'} {near['table']} (S1 "
                  f"{near['S1']:.3f}, Q0 {near['Q0']:.4f}; distance {near['distance']:.2f} sd of the bundled tables' "
                  f"{'S1' if basis else 'S1 and Q0'})")
        if res.get("missing"):
            print(f"  missing: {res['missing']}")
        for note in res.get("notes", ()):
            print(f"  note: {note}")
    return 0
