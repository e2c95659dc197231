"""``roadgonio intercompare``: a virtual key comparison of road-surface goniophotometers."""
from __future__ import annotations

from roadgonio import api
from roadgonio.errors import count
from roadgonio.cli._common import (
    add_dask_arguments,
    add_mitsuba_variant,
    add_output_options,
    out_arg,
    print_json,
    show_progress,
    text_output,
)


def register(sub) -> None:
    p = sub.add_parser(
        "intercompare", help="a virtual intercomparison: several instruments measure one surface; compatibility, "
                             "degrees of equivalence and why they disagree",
        description="Simulate a key comparison: every participant of STUDY (its instrument, misalignment SPEC, "
                    "repeatability, calibration, and whether it reports its table raw or corrects it) measures the "
                    "study's surface in many realisations, each stating its own uncertainty. Per cell: the weighted "
                    "mean, Mandel-Paule and DerSimonian-Laird reference values (with tau), the truth, every "
                    "participant's degree of equivalence d_i with U(d_i), E_n, the Birge ratio and the share of "
                    "compatible cells; the ranking of the characteristics that cause each participant's error; and "
                    "the same comparison with every participant correcting with 'roadgonio correct --reference "
                    "self'. Writes intercompare.nc, intercompare.csv, sensitivity.csv, validation.csv, "
                    "intercompare.json and pictures. Resumes an interrupted run. The study file: "
                    "docs/intercomparison.md.")
    p.add_argument("study", metavar="STUDY", help="study TOML file, or the name of a bundled study (r3-comparison)")
    p.add_argument("--out", metavar="DIR", help="output folder: journal and results (default out/intercompare-NAME)")
    add_dask_arguments(p, "default: a local cluster with one worker per core")
    add_mitsuba_variant(p)
    p.add_argument("--fresh", action="store_true", help="discard the partial results in --out instead of resuming")
    p.add_argument("--no-plots", action="store_true", help="do not draw the pictures")
    add_output_options(p, "print the summary as JSON")
    p.set_defaults(func=run, on_interrupt="interrupted: the finished tasks are in the journal of the output "
                                          "folder; run the same command again to resume")


def run(args) -> int:
    res = api.intercompare(args.study, out_arg(args), workers=args.workers, scheduler=args.scheduler,
                           fresh=args.fresh, progress=show_progress(args), plots=not args.no_plots,
                           mitsuba_variant=args.mitsuba_variant)
    s = api.intercomparison_summary(res)
    if args.json:
        print_json(s)
        return 0
    say = text_output(args)
    summary, sens = s["summary"], s["sensitivity"]
    for scen in dict.fromkeys(r["scenario"] for r in summary):
        rows = [r for r in summary if r["scenario"] == scen]
        allr = next(r for r in rows if r["participant"] == "ALL")
        if not allr.get("realisations"):
            say(f"{scen}: not compared (no realisation has every participant's table)")
            continue
        say(f"{scen} ({count(allr['realisations'], 'realisation')}): Birge ratio median {allr['birge_ratio_median']:.2f}, "
            f"consistent cells {100 * allr['share_consistent_cells']:.0f} %, every participant compatible with the "
            f"weighted mean in {100 * allr['share_all_compatible_weighted_mean']:.0f} % of the cells; RMS error "
            f"against the truth: weighted mean {allr['rms_error_weighted_mean_vs_truth_pct']:.2f} %, Mandel-Paule "
            f"{allr['rms_error_mandel_paule_vs_truth_pct']:.2f} %, DerSimonian-Laird "
            f"{allr['rms_error_dersimonian_laird_vs_truth_pct']:.2f} %")
        for r in rows:
            if r["participant"] == "ALL" or "repeatability_pct" not in r:
                continue
            top = [x for x in sens if x["scenario"] == scen and x["participant"] == r["participant"]][:2]
            why = "; ".join(f"{x['label']} ({x['drop_pct']:+.2f} pp)" for x in top)
            say(f"  {r['participant']:<18} {r['reports']:<5} repeatability {r['repeatability_pct']:.2g} %, stated u "
                f"{r['stated_u_median_pct']:.2g} %, RMS error {r['rms_error_vs_truth_pct']:.2f} %, compatible with "
                f"the truth in {100 * r['share_En_le_1_truth']:.0f} % and with the weighted mean in "
                f"{100 * r['share_En_le_1_weighted_mean']:.0f} % of the cells" + (f"; most of it: {why}" if why else ""))
    corrects = any(r["scenario"] == "all_corrected" and r["participant"] != "ALL" and r["reports"] == "self"
                   for r in summary)
    if not s["validation"] and not corrects:
        say("validation.csv has its header only: no participant's correction changes its table (collimated "
            "instruments under a Lambert calibration, k_A = 1), so there is no frozen correction factor to check")
    elif not s["validation"]:
        n = next((r.get("realisations") or 0 for r in summary if r["scenario"] == "all_corrected"
                  and r["participant"] == "ALL"), 0)
        say(f"validation.csv has its header only: checking the frozen correction factor against the full corrections "
            f"needs at least 2 realisations in which every participant corrects (here {n}; the study's "
            "corrected_realisations)")
    for note in s["notes"]:
        say(f"note: {note}")
    secs = s["seconds"]
    say(f"{secs['total']:.0f} s (k_A {secs.get('k_a', 0):.0f} s, corrections {secs.get('corrections', 0):.0f} s, "
        f"realisations {secs.get('realisations', 0):.0f} s); wrote {s['out']}/" + s["files"])
    return 0
