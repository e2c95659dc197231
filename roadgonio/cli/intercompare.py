"""``roadgonio intercompare``: a virtual key comparison of road-surface goniophotometers."""
from __future__ import annotations

from roadgonio.cli._common import add_dask_arguments, add_output_options, show_progress, text_output


def register(sub) -> None:
    p = sub.add_parser(
        "intercompare", help="a virtual intercomparison: several instruments measure one surface; compatibility, "
                             "degrees of equivalence and why they disagree",
        description="Simulate a key comparison: every participant of STUDY (its instrument, misalignment SPEC, "
                    "repeatability, calibration, and whether it reports its table raw or corrects it with roadgonio) "
                    "measures the study's surface in many realisations, each stating its own uncertainty. Per cell: "
                    "the weighted mean, Mandel-Paule and DerSimonian-Laird reference values (with tau), the truth, "
                    "every participant's degree of equivalence d_i with U(d_i), E_n, the Birge ratio and the share "
                    "of compatible cells; the ranking of the characteristics that cause the disagreement; and the "
                    "same comparison with every participant correcting with 'roadgonio correct --reference self'. "
                    "Writes intercompare.nc, intercompare.csv, sensitivity.csv, intercompare.json and pictures. "
                    "Resumes an interrupted run. The study file: docs/intercomparison.md.")
    p.add_argument("study", metavar="STUDY", help="study TOML file, or the name of a bundled study (r3-comparison)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (journal and results)")
    add_dask_arguments(p, "default: a local cluster with one worker per core")
    p.add_argument("--variant", metavar="NAME", help="Mitsuba variant (default $ROADGONIO_VARIANT or llvm_ad_rgb)")
    p.add_argument("--fresh", action="store_true", help="discard the partial results in --out instead of resuming")
    p.add_argument("--no-plots", action="store_true", help="do not draw the pictures")
    add_output_options(p, "print the summary as JSON")
    p.set_defaults(func=run, on_interrupt="interrupted: the finished tasks are in the journal of --out; run the same "
                                          "command again to resume")


def run(args) -> int:
    import json

    from roadgonio.api import intercompare
    res = intercompare(args.study, args.out, workers=args.workers, scheduler=args.scheduler, fresh=args.fresh,
                       progress=show_progress(args), plots=not args.no_plots, variant=args.variant)
    ds = res.dataset
    summary = json.loads(ds.attrs["summary_json"])
    sens = json.loads(ds.attrs["sensitivity_json"])
    if args.json:
        from roadgonio.fileio import to_json
        print(to_json({"summary": summary, "sensitivity": sens, "seconds": json.loads(ds.attrs["seconds"]),
                       "out": ds.attrs.get("out")}))
        return 0
    say = text_output(args)
    for scen in dict.fromkeys(r["scenario"] for r in summary):
        rows = [r for r in summary if r["scenario"] == scen]
        allr = next(r for r in rows if r["participant"] == "ALL")
        if not allr.get("realisations"):
            say(f"{scen}: not compared (no realisation has every participant's table)")
            continue
        say(f"{scen} ({allr['realisations']} realisations): Birge ratio median {allr['birge_ratio_median']:.2f}, "
            f"consistent cells {100 * allr['share_consistent_cells']:.0f} %, every participant compatible in "
            f"{100 * allr['share_all_compatible_weighted_mean']:.0f} % of the cells; RMS error against the truth: "
            f"weighted mean {allr['rms_error_weighted_mean_vs_truth_pct']:.2f} %, Mandel-Paule "
            f"{allr['rms_error_mandel_paule_vs_truth_pct']:.2f} %, DerSimonian-Laird "
            f"{allr['rms_error_dersimonian_laird_vs_truth_pct']:.2f} %")
        for r in rows:
            if r["participant"] == "ALL" or "repeatability_pct" not in r:
                continue
            top = [s for s in sens if s["scenario"] == scen and s["participant"] == r["participant"]][:2]
            why = "; ".join(f"{s['label']} ({s['drop_pct']:+.2f} pp)" for s in top)
            say(f"  {r['participant']:<18} {r['reports']:<9} repeatability {r['repeatability_pct']:.2g} %, stated u "
                f"{r['stated_u_median_pct']:.2g} %, |E_n| <= 1 in {100 * r['share_En_le_1_weighted_mean']:.0f} % of the "
                f"cells, RMS d/r {r['rms_d_weighted_mean_pct']:.2f} %" + (f"; most of it: {why}" if why else ""))
    secs = json.loads(ds.attrs["seconds"])
    say(f"{secs['total']:.0f} s (k_A {secs.get('k_a', 0):.0f} s, corrections {secs.get('corrections', 0):.0f} s, "
        f"realisations {secs.get('realisations', 0):.0f} s); wrote {ds.attrs.get('out')}/" + ds.attrs.get("files", ""))
    return 0
