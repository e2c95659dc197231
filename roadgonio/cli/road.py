"""``roadgonio road``: EN 13201-3 road-surface luminance metrics of a lighting layout computed with one
or several r-tables (e.g. measured and corrected), with the table's uncertainty propagated."""
from __future__ import annotations

import argparse
import sys

from roadgonio import api
from roadgonio.cli._common import add_output_options, out_arg, print_json
from roadgonio.errors import InputError


class _InOrder(argparse.Action):
    """Keeps --table, --u and --corr in the order they were given (``args.table_u``: (option,
    value)), so that a --u or --corr goes with the --table just before it."""

    def __call__(self, parser, namespace, values, option_string=None):
        order = list(getattr(namespace, "table_u", None) or [])
        order.append((self.dest, values))
        namespace.table_u = order
        if self.dest == "tables":
            namespace.tables = [v for k, v in order if k == "tables"]


def tables_and_u(order) -> tuple[list[str], list[str | None], list[str | None]]:
    """The tables and, per table, the --u and the --corr that follow it (None where none does); a --u
    or --corr before any --table, or two of one after one --table, is an :class:`InputError` naming
    the option."""
    tables: list[str] = []
    given: dict[str, list[str | None]] = {"u": [], "corr": []}
    for option, value in order:
        if option == "tables":
            tables.append(value)
            for v in given.values():
                v.append(None)
            continue
        flag, mine = f"--{option}", given[option]
        if not tables:
            raise InputError(f"{flag} {value} comes before any --table: give it right after the --table it belongs to",
                             field=flag)
        if mine[-1] is not None:
            raise InputError(f"{flag} {mine[-1]} and {flag} {value} both follow --table {tables[-1]}: give one {flag} "
                             "right after the --table it belongs to", field=flag)
        mine[-1] = value
    return tables, *([None if x in ("-", "") else x for x in given[k]] for k in ("u", "corr"))


def register(sub) -> None:
    p = sub.add_parser(
        "road", help="EN 13201 road luminance metrics (L_av, U_o, U_l, TI, class) of a layout with r-tables",
        description="Compute the road-surface luminance quantities of EN 13201-3 (average luminance L_av, overall "
                    "uniformity U_o, longitudinal uniformity U_l per lane, threshold increment TI, edge illuminance "
                    "ratio R_EI) for a luminaire layout, and the EN 13201-2 M class met, with one or several r-tables "
                    "side by side. With --u (the table's standard uncertainty, r x 1e4 in the r-table CSV layout, as "
                    "`roadgonio correct` writes it) a Monte Carlo gives u(L_av), u(U_o), u(U_l), the trials' means "
                    "(printed beside the nominal value where they differ by more than u/10), 95 % intervals and the "
                    "probability of meeting the class, with the cells' correlation `roadgonio correct` writes (--corr, or "
                    "corrected_corr.csv beside corrected_u.csv), else for independent and for fully correlated "
                    "cells. Without "
                    "--luminaire/--layout: roadgonio's illustrative cut-off luminaire and its default layout "
                    "(single-sided, 2 x 3.5 m lanes, H 10 m, S 30 m).")
    p.add_argument("--table", dest="tables", action=_InOrder, required=True, metavar="T",
                   help="r-table: bundled name (R1..R4, C1, C2) or .csv/.rtb file (r x 1e4); repeat for side by side")
    p.add_argument("--u", dest="u", action=_InOrder, metavar="FILE",
                   help="standard uncertainty of the --table just before it (r x 1e4, r-table CSV layout, as "
                        "`roadgonio correct` writes corrected_u.csv), e.g. --table measured.csv --table "
                        "corrected.csv --u corrected_u.csv; at most one per --table. When the file's header "
                        "names its table ('standard uncertainty of ...') and that table's CSV header names "
                        "another, it is an error; so is an r-table given as u (the table's own file, an RTB, a "
                        "bundled table, a corrected.csv)")
    p.add_argument("--corr", dest="corr", action=_InOrder, metavar="FILE",
                   help="the correlation between the cells of the --table just before it (as `roadgonio correct` "
                        "writes corrected_corr.csv), used in the Monte Carlo; without it a --u named corrected_u.csv "
                        "takes the corrected_corr.csv beside it (a correct folder)")
    p.add_argument("--luminaire", metavar="FILE", help="EULUMDAT .ldt file (default: the bundled illustrative luminaire)")
    p.add_argument("--layout", metavar="FILE", help="layout TOML (default: the bundled default layout)")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/road-TABLES)")
    p.add_argument("--class", dest="target_class", metavar="M", help="class to test in the Monte Carlo (default: the class "
                   "the table meets, M6 when it meets none)")
    p.add_argument("--trials", type=int, help=f"Monte Carlo trials (default {api.ROAD_MC_DEFAULTS['trials']}; "
                   "with --u only, as --seed, --correlation and --class)")
    p.add_argument("--seed", type=int, help=f"Monte Carlo seed (default {api.ROAD_MC_DEFAULTS['seed']})")
    p.add_argument("--correlation", choices=list(api.ROAD_CORRELATIONS),
                   help="the cells' correlation in the Monte Carlo: auto (default: the given correlation, --corr or "
                        "found beside corrected_u.csv, else both), given, both (independent and fully correlated "
                        "cells: limiting cases, not bounds for U_o and U_l), independent, correlated, all (the three)")
    p.add_argument("--no-plots", action="store_true", help="do not draw the pictures")
    add_output_options(p, json_help="print the results as JSON (a list with several tables)")
    p.set_defaults(func=run)


def run(args) -> int:
    tables, us, corrs = tables_and_u(args.table_u)
    summaries = api.road_metrics(tables, u=us if any(u is not None for u in us) else None,
                                 corr=corrs if any(c is not None for c in corrs) else None,
                                 luminaire=args.luminaire, layout=args.layout,
                         target_class=args.target_class, trials=args.trials, seed=args.seed,
                         correlation=args.correlation, out=out_arg(args), plots=not args.no_plots)
    if args.json:
        keep = ("table", "L_av", "U_o", "U_l", "TI", "R_EI", "class", "U_l_per_lane", "uncertainty",
                "neglected_contributions", "TI_note", "missing", "notes")
        rows = [{k: s[k] for k in keep if k in s} for s in summaries]
        print_json(rows[0] if len(rows) == 1 else rows)
    elif not args.quiet:
        _print(summaries)
    return 0


def _v(v, fmt: str) -> str:
    """A metric for the text table: '-' when missing."""
    return "-" if v is None else format(v, fmt)


def _print(summaries) -> None:
    w = sys.stdout.write
    first = summaries[0]
    w(f"layout: {first['layout']}\nluminaire: {first['luminaire']['name']} ({first['luminaire']['flux_lm']:g} lm)\n")
    n = max([14] + [len(s["table"]) for s in summaries])       # a file's name in full (measured.rtb (R3))
    w(f"{'table':{n}} {'L_av':>7} {'U_o':>6} {'U_l':>6} {'TI %':>6} {'R_EI':>6}  class  U_l per lane\n")
    for s in summaries:
        lanes = " ".join(_v(v, ".3f") for v in s["U_l_per_lane"])
        cls = "-" if s.get("missing") else (s["class"] or "none")
        w(f"{s['table']:{n}} {_v(s['L_av'], '.3f'):>7} {_v(s['U_o'], '.3f'):>6} {_v(s['U_l'], '.3f'):>6} "
          f"{_v(s['TI'], '.1f'):>6} {_v(s['R_EI'], '.3f'):>6}  {cls:5}  {lanes}\n")
    base = summaries[0]
    for s in summaries[1:]:
        parts = []
        if s["L_av"] is not None and base["L_av"]:
            parts.append(f"L_av {100 * (s['L_av'] / base['L_av'] - 1):+.1f} %")
        for k in ("U_o", "U_l"):
            if s[k] is not None and base[k] is not None:
                parts.append(f"{k} {s[k] - base[k]:+.3f}")
        if parts:
            w(f"  {s['table']} vs {base['table']}: {', '.join(parts)}\n")
    printed: set = set()
    for s in summaries:        # the layout's (the same for every table, printed once), then each table's
        for note in s.get("notes") or ():
            if note not in printed:
                printed.add(note)
                w(f"note: {note}\n")
    for s in summaries:
        if s.get("missing"):
            w(f"{s['table']}: missing {', '.join(s['missing']['metrics'])}: {s['missing']['reason']}\n")
    shifted = False
    for s in summaries:
        u = s.get("uncertainty")
        if not u:
            continue
        cf = u.get("correlation_file")
        w(f"{s['table']}: Monte Carlo of u from {u['file']} ({u['trials']} trials), class {u['target_class']}"
          + ("" if cf is None else f", cells' correlation from {cf}"
             + (" (beside the u file)" if u.get("correlation_found_beside_u") else "")) + ":\n")
        for note in u.get("notes") or ():
            w(f"  note in {u['file']}: {note}\n")
        for mode in api.ROAD_MODES:
            if mode not in u:
                continue
            m = u[mode]
            parts = []
            for k in ("L_av", "U_o", "U_l", "TI"):
                if m[k]:
                    parts.append(_with_u(k, m[k]['nominal'], m[k]['u'], m[k]['coverage_interval_95'], m[k]['mean']))
                    shifted = shifted or "nominal" in parts[-1]
            p = m["P_meets_target"]
            w(f"  {mode:11}: " + "; ".join(parts)
              + (f"; P(meets {u['target_class']}) = {p:.3f}" if p is not None else "; P(meets class): missing") + "\n")
            if m.get("note"):
                w(f"  {'':11}  note: {m['note']}\n")
    if shifted:
        w("  (nominal: the table's own value; MC: the trials' mean ± their standard deviation [95 % interval], JCGM "
          "101's estimate; under noise the min/max ratios U_o and U_l fall below the nominal value, and TI, convex in L_av, "
          "above it, so an interval can exclude the nominal value)\n")
    if any(s["neglected_contributions"] for s in summaries):
        w(f"note: {max(s['neglected_contributions'] for s in summaries)} luminaire contributions fell outside the "
          "CIE standard tables' region (their blank cells or tan > 12) and were neglected, as those tables do\n")
    if base["TI"] is None:
        w(f"TI not computed: {base['TI_note']}\n")
    w(f"wrote {len(first['written'])} files to {first['out']}\n")


#: The Monte Carlo mean is printed beside the nominal value when they differ by more than this
#: fraction of u (and in the digits printed): trial 11 D5 read "U_l 0.619 ± 0.088 [0.241, 0.584]",
#: the nominal value beside an interval of the trials (mean 0.42) that excludes it.
MEAN_SHIFT_SHOWN = 0.1
#: a u at or below this fraction of the value is round-off of a metric the trials do not move (U_o
#: and U_l, ratios of luminances, with every cell's r scaled by one common factor): printed as the
#: value alone, "unchanged", not to 17 digits beside a "nominal, MC" of round-off (audit 21)
ROUND_OFF_REL = 1e-12


def _with_u(name: str, value: float, u: float, interval, mean: float | None = None) -> str:
    """``L_av 1.1076 ± 0.0012 [1.1053, 1.1098]``: u to two significant digits, the value and the
    interval's ends to the same decimal place (three significant digits printed [1.11, 1.11] for an
    interval of width 0.005, trial 9). When the trials' ``mean`` differs from the nominal ``value``
    by more than :data:`MEAN_SHIFT_SHOWN` u: ``U_l 0.619 nominal, MC 0.419 ± 0.088 [0.241, 0.584]``."""
    import math
    if math.isfinite(u) and u <= ROUND_OFF_REL * abs(value):
        return f"{name} {value:.4g} (unchanged in every trial)"
    decimals = max(0, 1 - math.floor(math.log10(u))) if u > 0 and math.isfinite(u) else 3
    lo, hi = interval
    est = f"{value:.{decimals}f}"
    if mean is not None and abs(mean - value) > MEAN_SHIFT_SHOWN * u and f"{mean:.{decimals}f}" != est:
        est = f"{est} nominal, MC {mean:.{decimals}f}"
    return f"{name} {est} ± {u:.2g} [{lo:.{decimals}f}, {hi:.{decimals}f}]"
