"""``roadgonio correct``: divide a measured r-table by k_A of a reference model, with the
uncertainty of the correction (backend error and reference-model dependence)."""
from __future__ import annotations

from pathlib import Path

from roadgonio.errors import InputError
from roadgonio.surface.model import VARIANTS
from roadgonio.cli._common import (
    add_instrument_argument,
    check_seed,
    add_output_options,
    rel_se_setting,
    select_variant,
    show_progress,
    text_output,
)


def register(sub) -> None:
    p = sub.add_parser(
        "correct", help="correct a measured r-table for the aperture effect (r / k_A of a reference model)",
        description="Divide a measured r-table (CSV or DIALux RTB, standard grid) by k_A computed for a reference "
                    "BRDF model close to the sample, and state the uncertainty of that correction: the backend's "
                    "error of k_A and how much k_A changes when the reference changes (by default the two CIE "
                    "standard tables nearest to the measured table in S1/Q0; u_model = largest deviation / sqrt 3). "
                    "Writes the corrected table (CSV and RTB), per-cell CSV, JSON with provenance and a "
                    "before/after plot.")
    p.add_argument("--measured", required=True, metavar="FILE", help="measured r-table (.csv or .rtb, r x 1e4)")
    add_instrument_argument(p)
    p.add_argument("--reference", required=True, metavar="SAMPLE",
                   help="reference sample: bundled table (R1..R4, C1, C2, fitted on the fly), r-table file, model.json")
    p.add_argument("--alternatives", default="auto", metavar="LIST",
                   help="alternative references for the model uncertainty: 'auto' (default: the two nearest CIE "
                        "tables by S1/Q0), 'none', or a comma-separated list of SAMPLEs")
    p.add_argument("--model-variant", choices=list(VARIANTS), help="model variant when fitting a table")
    p.add_argument("--backend", default="mitsuba", choices=["mitsuba", "quadrature"],
                   help="k_A backend (default mitsuba)")
    p.add_argument("--rel-se", type=float, metavar="E",
                   help="target relative SE (mitsuba, default 1e-3) or relative tolerance (quadrature, default 1e-4)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the mitsuba backend")
    p.add_argument("--out", metavar="DIR", help="output folder (default out/correct-MEASURED)")
    p.add_argument("--no-plots", action="store_true", help="do not draw the before/after picture")
    add_output_options(p, "print the summary as JSON")
    p.set_defaults(func=run, on_interrupt="interrupted: nothing was written, and the k_A table computed so far is "
                                        "not kept (correct starts over when run again)")


def run(args) -> int:
    from roadgonio.correction import correct_table, resolve_alternatives, sample_name, write_correction
    from roadgonio.fileio import to_json
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.rtable import read_table
    from roadgonio.uncertainty import resolve_sample_spec

    try:
        measured = read_table(args.measured)
    except InputError as err:
        raise InputError(f"--measured: {err.reason}", path=err.path, line=err.line, field=err.field) from None
    check_seed(args.seed)
    settings: dict = {}
    if args.rel_se is not None:
        settings.update(rel_se_setting(args.backend, args.rel_se))
    if args.backend == "mitsuba":
        settings["seed"] = args.seed
    for key in ("0,0", "2,0"):
        t, b = (float(v) for v in key.split(","))
        if not measured.mask[int((abs(measured.tan_eps - t) < 1e-9).argmax()), int((abs(measured.beta_deg - b) < 1e-9).argmax())]:
            raise InputError(f"the measured table has no value at tan eps = {t:g}, beta = {b:g} (needed for S1)",
                             path=args.measured)
    instrument = load_instrument(args.instrument)
    reference = resolve_sample_spec(args.reference, args.model_variant)
    select_variant(args.backend)
    ref_name = sample_name(args.reference)
    alternatives = resolve_alternatives(args.alternatives, measured, reference_name=ref_name,
                                        model_variant=args.model_variant)
    c = correct_table(measured, instrument, reference, reference_name=ref_name, alternatives=alternatives,
                      backend=args.backend, backend_settings=settings, progress=show_progress(args))
    c.provenance["measured_file"] = str(args.measured)
    out = Path(args.out) if args.out else Path("out") / f"correct-{measured.name}"
    written = write_correction(c, out, plots=not args.no_plots)
    s = c.summary()
    if args.json:
        print(to_json({**s, "written": [str(p) for p in written]}))
    else:
        say = text_output(args)
        say(f"{measured.name}: {s['cells']} cells corrected with k_A of {ref_name} "
            f"(k_A {s['k_a_min']:.3g} ... {s['k_a_max']:.3g})")
        say(f"  S1 {s['S1_before']:.4g} -> {s['S1_after']:.4g}, Q0 {s['Q0_before']:.4g} -> {s['Q0_after']:.4g}")
        alts = ", ".join(f"{n} (max dev {100 * v['max_rel_dev']:.2g} %)" for n, v in s["alternatives"].items()) or "none"
        say(f"  correction uncertainty u_rel: median {100 * s['u_rel_median']:.3g} %, max {100 * s['u_rel_max']:.3g} %; "
            f"backend error max {100 * s['backend_rel_se_max']:.2g} %; alternative references: {alts}")
        say(f"wrote {len(written)} files to {out}")
    return 0
