"""``roadgonio ka``: the aperture-effect factor k_A of an instrument for a sample, one cell or a table."""
from __future__ import annotations

import math
import time
from pathlib import Path

from roadgonio.errors import InputError
from roadgonio.fileio import to_json
from roadgonio.engines.accuracy import PRESETS
from roadgonio.surface.model import VARIANTS
from roadgonio.cli._common import (
    add_instrument_argument,
    add_output_options,
    add_sample_argument,
    check_seed,
    load_inputs,
    rel_se_setting,
    select_variant,
    show_progress,
    text_output,
)


def register(sub) -> None:
    p = sub.add_parser(
        "ka", help="aperture-effect factor k_A of an instrument (one cell or the whole r-table)",
        description="Compute k_A = (S[f_road]/S[f_lambert]) / (f_road(nominal)/f_lambert) for an instrument "
                    "and a sample (docs/conventions.md section 5). Without --tan-eps/--beta the whole 580-cell grid is "
                    "computed and written to --out (ka.csv, ka_se.csv, ka.png, ka.json); an interrupted table "
                    "resumes when the same command is run again.")
    add_instrument_argument(p)
    add_sample_argument(p)
    p.add_argument("--model-variant", choices=list(VARIANTS),
                   help="model variant used when SAMPLE is a table to fit (default: the paper's 'power')")
    p.add_argument("--backend", default="mitsuba", choices=["mitsuba", "quadrature", "numpy-mc", "reference", "numpy-mc-mesh"],
                   help="mitsuba (default; float32 ray tracing), quadrature (deterministic float64), "
                        "numpy-mc (plain float64 Monte Carlo, slow; an oracle), reference (float64 randomised "
                        "QMC with the kinks split off and a 99.9 %% error bound; converges on wide instruments), "
                        "numpy-mc-mesh (float64 Monte Carlo with ray casting: mesh samples)")
    p.add_argument("--accuracy", choices=list(PRESETS),
                   help="preset on the measured speed-accuracy frontier (README); --rel-se overrides it")
    p.add_argument("--rel-se", type=float, metavar="E",
                   help="target relative standard error per cell (Monte Carlo backends) or relative tolerance "
                        "(quadrature); default from --accuracy")
    p.add_argument("--seed", type=int, default=0, help="random seed (Monte Carlo backends)")
    p.add_argument("--variant", help="Mitsuba variant (default llvm_ad_rgb; cuda_ad_rgb on a GPU machine)")
    p.add_argument("--tan-eps", type=float, metavar="T", help="one cell: tan(epsilon)")
    p.add_argument("--beta", type=float, metavar="B", help="one cell: beta in degrees")
    p.add_argument("--cells", default="all", metavar="all|table|LIST",
                   help="all = the full 580-cell grid (default); table = only the cells tabulated in the "
                        "sample's r-table (blank cells stay blank); LIST = T:B,T:B,... (tan eps : beta deg), "
                        "e.g. 12:0,12:2,4:0")
    p.add_argument("--out", metavar="DIR", help="output folder for a table (default: out/ka-INSTRUMENT-SAMPLE)")
    p.add_argument("--fresh", action="store_true", help="discard the partial results in --out instead of resuming")
    add_output_options(p, 'one cell: print {"k_a", "se", "error_bound", "converged", "samples", "seconds"}; '
                          "table: print the summary as JSON")
    p.set_defaults(func=run)


def backend_settings(args) -> dict:
    """Backend keyword arguments from --rel-se / --seed / --variant (--accuracy goes to make_backend,
    which applies the preset under these)."""
    settings: dict = {}
    check_seed(args.seed)
    if args.rel_se is not None:
        settings.update(rel_se_setting(args.backend, args.rel_se))
    if args.backend in ("mitsuba", "numpy-mc", "reference", "numpy-mc-mesh"):
        settings["seed"] = args.seed
    if args.backend == "mitsuba" and args.variant:
        settings["variant"] = args.variant
    return settings


def run(args) -> int:
    from roadgonio.plotproc import FigureProcess
    single = args.tan_eps is not None or args.beta is not None
    # a table's map is drawn by a helper process that loads matplotlib while the table is computed
    # (roadgonio.plotproc: 0.7 s of start-up a thread cannot hide)
    with FigureProcess(enabled=not single) as figures:
        return _run(args, single, figures)


def _run(args, single: bool, figures) -> int:
    from roadgonio.engines import full_grid_cells, make_backend
    from roadgonio.engines.runner import _precision_text, run_cells, write_outputs
    if single and (args.tan_eps is None or args.beta is None):
        raise InputError("give both --tan-eps and --beta for one cell (or neither for the whole table)",
                         field="--tan-eps/--beta")
    if single:
        if not (math.isfinite(args.tan_eps) and args.tan_eps >= 0):
            raise InputError(f"expected tan eps >= 0, got {args.tan_eps}", field="--tan-eps")
        if not (math.isfinite(args.beta) and 0 <= args.beta <= 180):
            raise InputError(f"expected 0 <= beta <= 180 deg, got {args.beta}", field="--beta")
    instrument, model = load_inputs(args)
    select_variant(args.backend, args.variant)
    backend = make_backend(args.backend, instrument, model, accuracy=args.accuracy, **backend_settings(args))
    if single and not args.out:
        args.on_interrupt = "interrupted: nothing was written (a single cell without --out does not resume)"
    else:
        args.on_interrupt = ("interrupted: the finished cells are kept in the output folder's journal; run the same "
                             "command again to resume")

    if single:
        t0 = time.perf_counter()
        out_dir = Path(args.out) if args.out else None
        run_ = run_cells(backend, [(args.tan_eps, args.beta)], instrument=instrument, model=model,
                         out_dir=out_dir, fresh=args.fresh, progress=False)
        c = run_.results[0]
        seconds = c.seconds if run_.resumed else time.perf_counter() - t0
        if args.json:
            print(to_json({"k_a": c.k_a, "se": c.se, "error_bound": c.error_bound, "converged": c.converged,
                           "samples": c.samples, "seconds": seconds}, indent=None))
        else:
            prec = (f"+- {c.error_bound:.2g} (error bound" if c.deterministic else f"+- {c.se:.2g} (standard error")
            text_output(args)(f"k_A(tan eps = {c.tan_eps:g}, beta = {c.beta_deg:g}) = {c.k_a:.6f} {prec}; "
                              f"{c.samples} samples, {seconds:.2f} s, {backend.name} backend)"
                              + ("" if c.converged else _not_converged_text(c, args.rel_se)))
        return 0

    if args.cells == "table":
        from roadgonio.surface.rtable import load_table
        try:
            table = load_table(args.sample)
        except InputError:
            raise InputError("--cells table needs a sample that is an r-table (bundled name or table file)",
                             field="--cells") from None
        cells = table.cells
    elif args.cells.strip() == "all":
        cells = full_grid_cells()
    else:
        from roadgonio.engines.validate import parse_cells
        cells = parse_cells(args.cells)
    sample_name = Path(args.sample).stem if Path(args.sample).exists() else args.sample
    out_dir = Path(args.out) if args.out else Path("out") / f"ka-{instrument.name}-{sample_name}"
    run_ = run_cells(backend, cells, instrument=instrument, model=model, out_dir=out_dir, fresh=args.fresh,
                     progress=show_progress(args))
    meta = write_outputs(run_, out_dir, instrument=instrument, model=model, backend=backend,
                         sample_spec=sample_name, figures=figures)
    s = meta["summary"]
    say = text_output(args)
    if args.json:
        print(to_json({"out": str(out_dir), **s}))
    else:
        say(f"k_A for {instrument.name} x {sample_name} ({backend.name}): {s['cells']} cells "
            f"({s['resumed_cells']} resumed), k_A from {s['k_a_min']:.3f} to {s['k_a_max']:.3f}, "
            f"{_precision_text(s)}, {run_.seconds:.1f} s.")
        say(f"wrote {out_dir}/" + ", ".join(f for f in meta["files"].values() if f and f != "ka_cells.jsonl")
            + ", ka.json")
    return 0


def _not_converged_text(c, target) -> str:
    """What a cell that stopped at its cap achieved, against what was asked."""
    if c.deterministic:
        got = f"relative error bound {c.error_bound / abs(c.k_a):.2g}" if c.k_a else "no bound"
    else:
        got = f"relative SE {c.se / abs(c.k_a):.2g}" if c.k_a else "no SE"
    asked = f" (target {target:g})" if target is not None else ""
    return (f" -- NOT converged: stopped at the backend's sample/evaluation cap with {got}{asked}; the value above "
            "carries that larger uncertainty")


