"""``roadgonio ka``: the aperture-effect factor k_A of an instrument for a sample, one cell or a table."""
from __future__ import annotations

import json
import math

from roadgonio import api
from roadgonio.cli._common import (
    add_accuracy,
    add_backend,
    add_instrument_argument,
    add_mitsuba_variant,
    add_model_variant,
    add_output_options,
    add_sample_argument,
    out_arg,
    print_json,
    show_progress,
    text_output,
)
from roadgonio.errors import EXIT_INCONCLUSIVE, InputError, count


def register(sub) -> None:
    p = sub.add_parser(
        "ka", help="aperture-effect factor k_A of an instrument (one cell or the whole r-table)",
        description="Compute k_A = (what the instrument reports as q) / f_road(nominal) for an instrument and a "
                    "sample (docs/conventions.md section 5), by the instrument's [calibration] mode: lambert (the "
                    "default) k_A = (S[f_road]/S[f_lambert]) / (f_road(nominal)/f_lambert); absolute (the paper's "
                    "eq. 2) k_A = L_D / (E_0 f_road(nominal)), L_D the meter's reading calibrated on a uniform "
                    "luminance and E_0 the source's illuminance at the sample centre; reference = SAMPLE k_A = "
                    "(S[f_road]/S[f_ref]) / (f_road(nominal)/f_ref(nominal)). Without --tan-eps/--beta the whole 580-cell grid is "
                    "computed and written to --out (ka.nc, ka.csv, ka_se.csv or ka_bound.csv, ka.png, ka.json; when "
                    "the scene makes stray light, a reflecting [housing] or [scene] (docs/straylight.md), also "
                    "ka_direct.csv, ka_direct_se.csv, stray_fraction.csv and stray_fraction_se.csv); an "
                    "interrupted table resumes when the same command is run again.")
    add_instrument_argument(p)
    add_sample_argument(p)
    add_model_variant(p)
    add_backend(p, "ka")
    add_accuracy(p)
    p.add_argument("--rel-se", type=float, metavar="E",
                   help="target relative standard error per cell (Monte Carlo backends) or relative tolerance "
                        "(quadrature, reference); default from --accuracy")
    p.add_argument("--seed", type=int, help="random seed of the Monte Carlo and RQMC backends (default 0)")
    add_mitsuba_variant(p)
    p.add_argument("--tan-eps", type=float, metavar="T", help="one cell: tan(epsilon)")
    p.add_argument("--beta", type=float, metavar="B", help="one cell: beta in degrees")
    p.add_argument("--cells", default="all", metavar="all|table|LIST",
                   help="all = the full 580-cell grid (default); table = only the cells tabulated in the "
                        "sample's r-table (blank cells stay blank); LIST = T:B,T:B,... (tan eps : beta deg) "
                        "on the CIE grid, e.g. 12:0,12:2,4:0 (--tan-eps/--beta take any one cell)")
    p.add_argument("--out", metavar="DIR", help="output folder for a table (default: out/ka-INSTRUMENT-SAMPLE)")
    p.add_argument("--fresh", action="store_true", help="discard the partial results in --out instead of resuming")
    add_output_options(p, 'one cell: print {"k_a", "se", "se_dof", "error_bound", "confidence_bound", "confidence_level", '
                          '"converged", "samples", "seconds", ...}; table: print the summary as JSON')
    p.set_defaults(func=run)


def run(args) -> int:
    single = args.tan_eps is not None or args.beta is not None
    if single and (args.tan_eps is None or args.beta is None):
        raise InputError("give both --tan-eps and --beta for one cell (or neither for the whole table)",
                         field="--tan-eps/--beta")
    if single and args.cells != "all":
        raise InputError("--cells chooses the cells of a table, --tan-eps/--beta one cell: give one of them",
                         field="--cells")
    common = dict(backend=args.backend, accuracy=args.accuracy, seed=args.seed, mitsuba_variant=args.mitsuba_variant,
                  rel_se=args.rel_se, model_variant=args.model_variant, fresh=args.fresh)
    if single:
        args.on_interrupt = ("interrupted: nothing was written (a single cell without --out does not resume)"
                             if not args.out else "interrupted: run the same command again to resume")
        c = api.ka_cell(args.instrument, args.sample, args.tan_eps, args.beta, out=args.out,
                        progress=show_progress(args), **common)
        if args.json:
            print_json({"k_a": c.k_a, "se": c.se, "se_dof": c.se_dof, "error_bound": c.error_bound,
                        "confidence_bound": c.confidence_bound,
                        "confidence_level": c.confidence_level, "converged": c.converged, "samples": c.samples, "seconds": c.seconds,
                        "k_a_direct": c.k_a_direct, "k_a_direct_se": c.k_a_direct_se,
                        "stray_fraction": c.stray_fraction, "stray_fraction_se": c.stray_fraction_se,
                        # absolute calibration: eta = <E>/E_0 and its error estimate (deterministic)
                        **{k: (c.extra or {})[k] for k in ("eta", "eta_error", "eta_converged", "max_bounces", "note")
                           if k in (c.extra or {})}})
        else:
            # a deterministic cell that stopped at its cap has an error estimate, not a bound
            bound_name = "error bound" if c.converged else "error estimate, not a bound"
            stated = f"+- {c.se:.2g} (standard error" if math.isfinite(c.se) else "(no standard error"
            prec = (f"+- {c.error_bound:.2g} ({bound_name}" if c.deterministic else stated
                    + (f" with {c.se_dof:.0f} degrees of freedom" if math.isfinite(c.se_dof) else "")
                    # absolute calibration: eta's deterministic error beside the SE
                    + (f", and +- {c.error_bound:.2g} error bound of the calibration's eta"
                       if math.isfinite(c.error_bound) else ""))
            text_output(args)(f"k_A(tan eps = {c.tan_eps:g}, beta = {c.beta_deg:g}) = {c.k_a:.6f} {prec}; "
                              f"{c.samples} samples, {c.seconds:.2f} s, {args.backend} backend)"
                              + ("" if c.converged else _not_converged_text(c, args.rel_se))
                              + (f"; stray light {100 * c.stray_fraction:.2f} % +- {100 * c.stray_fraction_se:.2g} % of "
                                 f"the signal, direct light alone k_A = {c.k_a_direct:.6f} +- {c.k_a_direct_se:.2g}"
                                 if c.stray_fraction != 0.0 else "")
                              # a converged cell's note (a not converged one says it above)
                              + (f". Note: {c.extra['note']}" if c.converged and (c.extra or {}).get("note") else ""))
        # a cell the backend could not measure is no result: exit 3, as validate's inconclusive (user
        # audit, session 44: under -q a NaN k_A exited 0, and -q says the exit status tells the result)
        return 0 if math.isfinite(c.k_a) else EXIT_INCONCLUSIVE

    args.on_interrupt = ("interrupted: the finished cells are kept in the output folder's journal (with the Mitsuba "
                         "backend also the other cells' last completed pass, ka_passes.json); run the same command "
                         "again to resume")
    # a table's map is drawn by a helper process that loads matplotlib while the table is computed
    # (roadgonio.plotproc: 0.7 s of start-up a thread cannot hide)
    with api.figure_process() as figures:
        ds = api.ka_table(args.instrument, args.sample, cells=args.cells, out=out_arg(args),
                          progress=show_progress(args), figures=figures, **common)
    s = json.loads(ds.attrs["summary"])
    rc = EXIT_INCONCLUSIVE if s.get("not_measured") else 0
    if args.json:
        print_json({"out": ds.attrs["out"], **s})
        return rc
    say = text_output(args)
    resumed = _resumed_text(s)
    held = s["cells"] + s.get("not_measured", 0)  # the cells measured and those said not measured
    if s["cells_asked"] == held:
        cells = f"{count(held, 'cell')} ({resumed}), "
    else:   # a subset of a larger table in the folder: the files hold the whole table
        cells = (f"{count(s['cells_asked'], 'cell')} asked ({resumed}); the folder's table holds "
                 f"{count(held, 'cell')}: ")
    # k_A over decades (a lobe far narrower than the apertures) in exponent form (user audit, session 44: a
    # 71-digit fixed-point number)
    k_range = ("no cell measured" if s["k_a_min"] is None else
               f"k_A from {_k_text(s['k_a_min'])} to {_k_text(s['k_a_max'])}, {api.precision_text(s)}")
    say(f"k_A for {ds.attrs['instrument']} x {ds.attrs['sample']} ({ds.attrs['backend']}): {cells}"
        f"{k_range}; computing the cells took {s['seconds_wall_this_run']:.1f} s."
        + (_stray_text(s) if "stray_fraction_max" in s else ""))
    if s.get("not_measured"):
        say(f"  {count(s['not_measured'], 'cell')} NOT measured (k_A blank in the files; exit status "
            f"{EXIT_INCONCLUSIVE}), the first at {s['not_measured_note']}")
    say(f"wrote {ds.attrs['out']}/{ds.attrs['files']}")
    return rc


def _k_text(k: float) -> str:
    """k_A to three decimals, or in exponent form beyond 1e4 (a lobe far narrower than the apertures)."""
    return f"{k:.3f}" if abs(k) < 1e4 else f"{k:.4g}"


def _resumed_text(s) -> str:
    """'118 resumed' (finished cells read back from the journal), and when the others went on from
    their state after a pass (ka_passes.json) instead of starting over, ', 462 continued after their
    pass 1' (trial 12: the count of finished cells alone hid that the interrupted passes were kept)."""
    text = f"{s['resumed_cells']} resumed"
    if s.get("resumed_pass_cells"):
        text += f", {s['resumed_pass_cells']} continued after their pass {s['resumed_from_pass']}"
    return text


def _stray_text(s) -> str:
    text = f" Stray light: up to {100 * s['stray_fraction_max']:.1f} % of the signal; "
    if s.get("k_a_direct_min") is None:
        return text + "no cell gets direct light from its source."
    text += f"the direct light alone gives k_A {s['k_a_direct_min']:.3f} ... {s['k_a_direct_max']:.3f}"
    n = s.get("cells_without_direct_light", 0)
    return text + (f" ({n} cells get no direct light from their source)." if n else ".")


def _not_converged_text(c, target) -> str:
    """What a cell that stopped at its cap achieved, against what was asked; under absolute
    calibration also (or only) eta = <E>/E_0, whose error estimate a standard error does not hold."""
    extra = c.extra or {}
    if extra.get("float32_underflow"):
        return f" -- NOT measured: {extra['note']}"
    if extra.get("sparse_light") is not None:
        return f" -- NOT converged: {extra['note']}"
    if extra.get("map_pieces") is not None or extra.get("narrow_beam_deg") is not None:
        # the quadrature across the kinks of a map of too many pieces: not at a cap, no bound (audit 27)
        return f" -- NOT converged: {extra['note']}"
    eta_text = ""
    if extra.get("eta_converged") is False:
        rel = extra["eta_error"] / extra["eta"] if extra.get("eta") else math.nan
        eta_text = (f" -- NOT converged: eta = <E>/E_0 of the absolute calibration stopped at its cap with relative "
                    f"error {rel:.2g}"
                    + ("" if c.deterministic else " (the error bound beside the standard error above)"))
        if extra.get("backend_converged", True):
            return eta_text
    if c.deterministic:
        # the rules had not settled: the last levels' change is an estimate that can understate the
        # error (quadrature, wide preset, 6:0 at rtol 1e-6: 0.0100 for an error of 0.0177; audit, session 24)
        got = (f"relative error estimate {c.error_bound / abs(c.k_a):.2g}, not a bound (the error can be larger)"
               if c.k_a else "no error estimate")
    else:
        got = f"relative SE {c.se / abs(c.k_a):.2g}" if c.k_a else "no SE"
    asked = f" (target {target:g})" if target is not None else ""
    head = f"{eta_text}; and the backend" if eta_text else " -- NOT converged: the backend"
    return (f"{head} stopped at its sample/evaluation cap with {got}{asked}; the value above carries that larger "
            "uncertainty")
