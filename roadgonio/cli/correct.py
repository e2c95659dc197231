"""``roadgonio correct``: correct measured r-tables for the aperture effect, with one uncertainty of
the corrected table (roadgonio.correction)."""
from __future__ import annotations

import math

from roadgonio import api
from roadgonio.cli._common import (
    add_accuracy,
    add_backend,
    add_dask_arguments,
    add_mitsuba_variant,
    add_model_variant,
    add_output_options,
    out_arg,
    print_json,
    show_progress,
    text_output,
)
from roadgonio.errors import count, percent as _percent


def register(sub) -> None:
    p = sub.add_parser(
        "correct", help="correct measured r-tables for the aperture effect, with the uncertainty of the result",
        description="Correct a measured r-table (CSV or DIALux RTB, standard grid) for the aperture effect of the "
                    "instrument that measured it: corrected r = measured r / k_A. With --reference self (the "
                    "default) the road BRDF model is fitted THROUGH the instrument (the parameters whose simulated "
                    "measurement, ideal r times k_A under the instrument's [calibration], best matches the table "
                    "weighted by its uncertainty), and k_A of that model is computed with --backend; the measured "
                    "detail is kept, the model gives only the factor. With --reference SAMPLE k_A is that of a given "
                    "reference (paper section 4.1). One standard uncertainty per corrected cell, with correlations: "
                    "the measurement's (--u-measured), the backend's, the fitted parameters', the model variant's "
                    "(power vs smooth), the instrument's misalignment (--sigma) and, when the data reject the eq. 4 "
                    "fit, the misfit (where the residuals exceed the stated noise). Reports S1, S2, Q0 before and "
                    "after with their uncertainties and the CIE class. Writes corrected.csv, corrected_u.csv, "
                    "corrected.rtb, correct.json, correct_cells.csv, corrected_corr.csv, before_after.png and "
                    "correction_map.png, with --forward surface or --joint also residual_map.png and "
                    "correction_surface.png (one sub-folder per file when several are given); the k_A tables are "
                    "journalled and an interrupted run resumes.")
    p.add_argument("--measured", required=True, nargs="+", action="extend", metavar="FILE",
                   help="measured r-table(s) (.csv or .rtb, r x 1e4); several files share the instrument's work; "
                        "with --joint, repeat --measured FILE --instrument FILE per instrument")
    p.add_argument("--instrument", required=True, action="append", metavar="FILE",
                   help="instrument preset or TOML file (with --joint: one per --measured, in the same order)")
    p.add_argument("--forward", choices=["eq4", "surface"], default=None,
                   help="forward model fitted with --reference self: eq4 (default) the paper's eq. 4; surface: eq. 4 "
                        "times a smooth correction surface over the incident direction whose smoothing the data "
                        "choose, for surfaces outside eq. 4 (its u includes the surface's posterior, and is widened "
                        "by the local Birge ratio where the residuals have structure); --joint fits surface (eq4 is refused "
                        "with it)")
    p.add_argument("--mirror-plane", choices=["cusp", "rounded", "both", "three"], default=None,
                   help="with --forward surface or --joint: the backbone's shape at the mirror plane (beta 0): cusp "
                        "(eq. 4's), rounded (over one knot of the correction surface), both (the two, weighed by "
                        "their evidence) or three (the cusp and the roundings over one and two knots, weighed; the "
                        "default; both takes ~0.85 of its time, cusp ~0.5, docs/correction.md)")
    p.add_argument("--gd-prior", choices=["joint", "fixed", "evidence"], default=None,
                   help="with --forward surface or --joint: who chooses the scale of the prior of g_D (how much "
                        "faster than eq. 4 the BRDF changes off alpha = 1 deg): joint (the default) lets the "
                        "evidence choose it where two or more instruments see the surface and holds sd 1 with one; "
                        "fixed holds sd 1 (what it was until session 33); evidence frees it through one instrument "
                        "too (measured unsafe there, docs/correction-record.md)")
    p.add_argument("--unobserved-road", type=float, default=None, metavar="F",
                   help="with --forward surface or --joint, where the backend traces stray light (a housing): the "
                        "factor within which the road's BRDF beyond the observation elevations the instruments saw "
                        "is known, one standard uncertainty (default 2; 1 leaves the 'unobserved' component out): "
                        "stray light reads the road there and no r-table measures it (docs/correction.md)")
    p.add_argument("--joint", action="store_true",
                   help="the --measured tables are ONE surface measured by the --instrument(s) (one per table, or one "
                        "instrument with several aperture settings as several files): one surface is fitted through "
                        "all of them and one corrected table written, with each instrument's k_A")
    p.add_argument("--reference", default="self", metavar="self|SAMPLE",
                   help="self (default): fit the model through the instrument; or a reference SAMPLE (bundled table "
                        "R1..R4, C1, C2 fitted on the fly, an r-table file, a model.json, lambert)")
    p.add_argument("--alternatives", default=None, metavar="LIST",
                   help="with --reference SAMPLE: alternative references for the model dependence, 'auto' (default: "
                        "the two CIE tables nearest to the measured one by S1/Q0), 'none', or SAMPLEs separated by commas")
    p.add_argument("--u-measured", default=None, metavar="U",
                   help="standard uncertainty of the measured values: relative ('1%%' or 0.01, independent cells) or "
                        "an r-table file (CSV/RTB, r x 1e4) of per-cell standard uncertainties; default 1%% (said in "
                        "the output: give your own)")
    p.add_argument("--sigma", metavar="SPEC",
                   help="the instrument's misalignment, as for `roadgonio uncertainty` (e.g. 'alpha_deg=0.01,"
                        "eps_deg=0.05:rect,beta_deg=0.1,tilt_x_deg=0.02', or a TOML file); default: not included")
    add_model_variant(p, "model variant fitted: auto (default with --reference self: power and smooth, the better "
                         "fit is used and the other measures the model dependence), or one variant", extra=("auto",))
    add_backend(p, "correct",
                help_text="k_A backend of the reported factor (default mitsuba; quadrature: deterministic float64)")
    add_accuracy(p)
    p.add_argument("--rel-se", type=float, metavar="E",
                   help="target relative SE (Monte Carlo backends) or relative tolerance (quadrature)")
    p.add_argument("--seed", type=int, default=0, help="random seed (backends and ray bundles)")
    add_mitsuba_variant(p)
    p.add_argument("--rays", type=int, default=512, metavar="N",
                   help="rays per cell of the fit's forward model (power of two times 4; default 512)")
    add_dask_arguments(p, "default: in this process; with several --measured files each file is one task on a "
                          "worker, with the same results")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/correct-NAME)")
    p.add_argument("--no-plots", action="store_true", help="do not draw the pictures")
    add_output_options(p, "print the summary as JSON (a list for several files)")
    p.set_defaults(func=run, on_interrupt="interrupted: the finished k_A cells and fitted models are kept in the "
                                        "output folder (forward-N/ journals, fit_state.json) and the files already "
                                        "corrected keep their outputs; run the same command again to resume")


def run(args) -> int:
    if args.joint:
        return _run_joint(args)
    if len(args.instrument) != 1:
        from roadgonio.errors import InputError
        raise InputError(f"{len(args.instrument)} --instrument given without --joint: several instruments that "
                         "measured one surface are corrected together with --joint", field="--instrument")
    results = api.correct(list(args.measured), args.instrument[0], forward=args.forward or "eq4", reference=args.reference,
                          alternatives=args.alternatives, u_measured=args.u_measured, sigma=args.sigma,
                          backend=args.backend, accuracy=args.accuracy, rel_se=args.rel_se, seed=args.seed,
                          mitsuba_variant=args.mitsuba_variant, model_variant=args.model_variant, rays=args.rays,
                          workers=args.workers, scheduler=args.scheduler, out=out_arg(args),
                          plots=not args.no_plots, progress=show_progress(args), mirror_plane=args.mirror_plane,
                          unobserved_road=args.unobserved_road, gd_prior=args.gd_prior)
    summaries = []
    for res in results:
        s = _json_summary(res)
        s["written"] = [str(p) for p in res.written]
        summaries.append(s)
    if args.json:
        print_json(summaries[0] if len(summaries) == 1 else summaries)
        return 0
    say = text_output(args)
    if args.u_measured is None:
        say("note: no --u-measured given; the measurement's standard uncertainty was taken as 1 % of each value")
    limits = {(getattr(r, "provenance", None) or {}).get("forward_model_limits") for r in results} - {None}
    for text in sorted(limits):
        say(f"note: {text}")
    for s in summaries:
        b = s["before"]
        say(f"{s['measured']}: {s['cells']} cells corrected (reference {s['reference']}, calibration "
            f"{s['calibration']}; k_A {s['k_a_min']:.3f} ... {s['k_a_max']:.3f})")
        say(f"  before: S1 {_pm(b['S1'], b['u_S1'])}, Q0 {_pm(b['Q0'], b['u_Q0'])}, S2 {_pm(b['S2'], b['u_S2'])}: "
            f"{_classes(b)}, nearest CIE table {_nearest(b)}")
        say(f"  after:  S1 {_pm(s['S1'], s['u_S1'])}, Q0 {_pm(s['Q0'], s['u_Q0'])}, S2 {_pm(s['S2'], s['u_S2'])}: "
            f"{_classes(s)}, nearest CIE table {_nearest(s)}")
        if s.get("Q0_note"):
            say(f"  note: {s['Q0_note']}")
        comps = ", ".join(f"{k} {_percent(v['u_rel_max'])}" for k, v in s["budget"].items() if k != "total")
        say(f"  u of the corrected r: median {100 * s['u_rel_median']:.3g} %, max {100 * s['u_rel_max']:.3g} % "
            f"(largest per component: {comps}); {s['seconds']:.1f} s")
        f = s.get("fit") or {}
        note = f.get("misfit_note")
        if note:
            say(f"  note: {note}; --forward surface fits a model that can follow it (docs/correction.md, \"Outside "
                "eq. 4\"); corrected_u.csv's header carries this note, and road --u repeats it")
        if "cells_widened" in f:
            say(f"  fit: {f.get('backbone', f['variant'])} backbone x correction surface, Birge ratio {f['birge_ratio']:.2f} "
                f"(local max {f['birge_local_max']:.2f}); u widened by the local Birge ratio in {f['cells_widened']} "
                f"cells (at most x{f['widening_max']:.2f})")
        if s.get("model_estimate"):
            say(_model_estimate_line(s["model_estimate"]))
        line = _resumed_line(s["resumed_cells"], s["resumed_surfaces"], s["resumed_pass_cells"])
        if line:
            say(line)
        say(f"  wrote {len(s['written'])} files to {s['out']}")
    cluster = results[0].provenance.get("cluster") if results else None
    if cluster:
        say(f"computed as {len(results)} Dask tasks on {cluster['workers']} workers ({cluster['scheduler']})")
    return 0


def _run_joint(args) -> int:
    res = api.correct(list(args.measured), list(args.instrument), joint=True, reference=args.reference,
                      alternatives=args.alternatives,
                      forward=args.forward,
                      u_measured=args.u_measured, sigma=args.sigma, backend=args.backend, accuracy=args.accuracy,
                      rel_se=args.rel_se, seed=args.seed, mitsuba_variant=args.mitsuba_variant,
                      model_variant=args.model_variant, rays=args.rays, workers=args.workers,
                      scheduler=args.scheduler, out=out_arg(args), plots=not args.no_plots,
                      progress=show_progress(args), mirror_plane=args.mirror_plane,
                      unobserved_road=args.unobserved_road, gd_prior=args.gd_prior)
    s = res.summary()
    s["out"] = str(res.out)
    s["written"] = [str(p) for p in res.written]
    if args.json:
        print_json(s)
        return 0
    say = text_output(args)
    if args.u_measured is None:
        say("note: no --u-measured given; the measurement's standard uncertainty was taken as 1 % of each value")
    if (res.provenance or {}).get("forward_model_limits"):
        say(f"note: {res.provenance['forward_model_limits']}")
    best = max(s["variants"], key=lambda v: v["weight"])
    say(f"one surface through {len(res.parts)} instruments ({', '.join(s['instruments'])}): {s['cells']} cells, "
        f"{best.get('label', best['variant'])} backbone x correction surface, Birge ratio {best['birge_ratio']:.2f}, "
        f"g_D's prior sd {best['g_d_prior_sd']:.2g}" + _gd_prior_how(best))
    for p in s["per_instrument"]:
        b = p["before"]
        say(f"  {p['instrument']} ({p['measured']}): k_A {p['k_a_min']:.3f} ... {p['k_a_max']:.3f}; as measured S1 "
            f"{_pm(b['S1'], b['u_S1'])}, Q0 {_pm(b['Q0'], b['u_Q0'])}; its own corrected u median "
            f"{100 * p['u_rel_median']:.3g} %")
        if p.get("Q0_note"):
            say(f"    note: its {p['Q0_note']}")
    say(f"  corrected: S1 {_pm(s['S1'], s['u_S1'])}, Q0 {_pm(s['Q0'], s['u_Q0'])}, S2 {_pm(s['S2'], s['u_S2'])}: "
        f"{_classes(s)}, nearest CIE table {_nearest(s)}")
    if s.get("Q0_note"):
        say(f"  note: {s['Q0_note']}")
    say(f"  u of the corrected r: median {100 * s['u_rel_median']:.3g} %, max {100 * s['u_rel_max']:.3g} %; "
        f"{s['seconds']:.1f} s")
    if s.get("model_estimate"):
        say(_model_estimate_line(s["model_estimate"]))
    backends = [p.get("backend") for p in s["per_instrument"]]
    line = _resumed_line(_resumed(backends), _resumed_surfaces(s["variants"]), _resumed(backends, "resumed_pass_cells"))
    if line:
        say(line)
    say(f"  wrote {len(s['written'])} files to {s['out']}")
    return 0


def _gd_prior_how(variant: dict) -> str:
    """Who chose a variant's g_D prior sd (its summary's ``g_d_prior_chosen_by``: held, the evidence,
    or the evidence stopped at a bound of its search)."""
    how = variant["g_d_prior_chosen_by"]
    return {"held": " (held)", "evidence": " (chosen by the evidence)",
            "evidence at its bound": " (chosen by the evidence, at its bound)",
            "held: the evidence wanted it wider than its bound": " (held: the evidence wanted it wider than sd 2, "
            "where g_D takes up the surface's shape; docs/correction.md)"}[how]


def _model_estimate_line(m: dict) -> str:
    return (f"  the table weighs r / k_A against the fitted surface's own value: its weight median "
            f"{m['weight_median']:.2f} ({m['weight_min']:.2f} ... {m['weight_max']:.2f}; w_model in correct_cells.csv)")


def _nearest(s: dict) -> str:
    """The nearest CIE table, and what it was found by when S1 or Q0 is missing (user audit, session 29)."""
    basis = s.get("nearest_table_basis")
    return f"{s['nearest_table']}" + (f" ({basis})" if basis else "")


def _classes(s: dict) -> str:
    """'R2 / C2', or why there is no class (S1 needs r at tan eps 0 and 2, beta 0)."""
    if s.get("class_R") is None or s.get("class_C") is None:
        return "class missing (S1 missing)"
    return f"{s['class_R']} / {s['class_C']}"


def _pm(v, u) -> str:
    if v is None or not math.isfinite(v):
        return "missing"
    if u is None or not math.isfinite(u):
        return f"{v:.4g}"
    return f"{v:.4g} +- {u:.2g}"


def _json_summary(res) -> dict:
    s = res.summary()
    keep = ("measured", "reference", "calibration", "cells", "S1", "u_S1", "Q0", "u_Q0", "S2", "u_S2", "class_R",
            "class_C", "nearest_table", "k_a_min", "k_a_max", "u_rel_median", "u_rel_max", "before", "budget",
            "seconds")
    out = {k: s[k] for k in keep}
    if s.get("nearest_table_basis"):
        out["nearest_table_basis"] = s["nearest_table_basis"]
    if s.get("model_estimate"):
        out["model_estimate"] = s["model_estimate"]
    if "fit" in s:
        out["fit"] = {k: s["fit"][k] for k in ("variant", "chi2", "dof", "birge_ratio", "chi2_p_value", "misfit", "misfit_note", "birge_local_max",
                                               "cells_widened", "widening_max") if k in s["fit"]}
    infos = [st.get("backend") for st in (s.get("steps") or [])]
    out["resumed_cells"] = _resumed(infos)
    out["resumed_pass_cells"] = _resumed(infos, "resumed_pass_cells")
    out["resumed_surfaces"] = _resumed_surfaces((s.get("fit") or {}).get("variants"))
    out["out"] = str(res.out)
    return out


def _resumed(infos, key: str = "resumed_cells") -> int:
    """k_A cells the backends took from the output folder's journals (a rerun in the same folder);
    with ``key="resumed_pass_cells"``, those that went on from their state after a pass."""
    return sum(int((i or {}).get(key) or 0) for i in infos)


def _resumed_surfaces(variants) -> int:
    """Correction surfaces (``--forward surface``, one a backbone variant) taken from the journal."""
    return sum(bool(v.get("resumed")) for v in (variants or []))


def _resumed_line(cells: int, surfaces: int = 0, pass_cells: int = 0) -> str | None:
    """What a rerun in the same folder took from its journals (None: nothing): the finished k_A cells
    and correction surfaces, and the k_A cells that went on from their last completed pass
    (ka_passes.json) instead of starting over."""
    parts = ([count(cells, "k_A cell")] if cells else []) + ([count(surfaces, "correction surface")] if surfaces else [])
    line = f"{' and '.join(parts)} from the output folder's journals" if parts else ""
    if pass_cells:
        their = "its" if pass_cells == 1 else "their"
        line += ("; " if line else "") + f"{count(pass_cells, 'k_A cell')} continued after {their} last completed pass"
    return f"  resumed: {line}" if line else None
