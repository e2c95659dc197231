"""``roadgonio render``: pictures of one measurement cell rendered with Mitsuba - the detector's view
of the sample (its field of view with the road luminance) and the illuminance on the sample around
the detector footprint - as OpenEXR (float32) and PNG, with a one-render k_A estimate."""
from __future__ import annotations

from roadgonio import api
from roadgonio.cli._common import (
    add_instrument_argument,
    add_mitsuba_variant,
    add_model_variant,
    add_output_options,
    add_sample_argument,
    print_json,
    text_output,
)


def register(sub) -> None:
    p = sub.add_parser("render", help="render the detector's view and the illuminance of one cell (EXR + PNG)",
                       description="Render one measurement cell of an instrument with Mitsuba: the detector's "
                                   "view of the sample (luminance inside the field stop) and the horizontal "
                                   "illuminance around the detector footprint (footprint outlined). Writes "
                                   "view.exr, illuminance.exr, render.png and render.json to --out, and stray.png and "
                                   "stray.exr (where the stray light enters the view) when the scene makes stray "
                                   "light (a reflecting [housing] or [scene], docs/straylight.md). With stray light "
                                   "the k_A estimate and stray.png come from a fixed stray-light run (96 x 96 "
                                   "pixels, 2^20 samples) that --resolution and --spp do not change; they set "
                                   "view.exr, render.png and k_A of the direct light.")
    add_instrument_argument(p)
    add_sample_argument(p)
    add_model_variant(p)
    p.add_argument("--tan-eps", dest="tan_eps", type=float, required=True, metavar="T", help="tan(epsilon) of the source")
    p.add_argument("--beta", type=float, required=True, metavar="B", help="beta of the source (deg)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--resolution", type=int, default=256, help="detector-view pixels per side (default 256; not "
                   "stray.png's, see above)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel (a square; default 64; not the stray-light "
                   "run's, see above)")
    p.add_argument("--seed", type=int, default=0, help="seed of the renders (0 ... 2^32 - 1: Mitsuba's samplers take a "
                   "32-bit seed; default 0)")
    add_mitsuba_variant(p)
    add_output_options(p, "print render.json (provenance, footprint, the k_A estimate, files) to stdout")
    p.set_defaults(func=run, on_interrupt="interrupted: the pictures of this cell were not written (render starts "
                                        "over when run again)")


def run(args) -> int:
    info = api.render(args.instrument, args.sample, args.tan_eps, args.beta, args.out, resolution=args.resolution,
                      spp=args.spp, seed=args.seed, mitsuba_variant=args.mitsuba_variant,
                      model_variant=args.model_variant)
    if args.json:
        print_json(info)
        return 0
    say = text_output(args)
    ka = info["k_a_estimate"]
    say(f"{info['provenance']['instrument']['instrument']['name']}, sample {info['sample']}, tan eps = {args.tan_eps:g}, "
        f"beta = {args.beta:g} deg: footprint x = {info['footprint_m']['x'][0]:.3f} ... "
        f"{info['footprint_m']['x'][1]:.3f} m; "
        + (f"k_A ~ {ka:.4f} +- {info['k_a_se']:.1e} (one render; use 'roadgonio ka' for tables)"
           if ka is not None else info.get("k_a_note", "k_A undefined (model is 0 at the nominal geometry)")))
    if "stray" in info:
        st = info["stray"]
        top = max(st["parts"], key=lambda k: st["parts"][k]["road"])
        name = st["part_labels"][top]        # as stray.png names it (review, session 40)
        most = f" (most from {name})" if st["parts"][top]["road"] > 0 else ""      # none at 0 % (audit 22)
        say(f"stray light: {100 * st['stray_fraction_road']:.2f} % of the road signal{most}, "
            f"{100 * st['stray_fraction_lambert']:.2f} % of the Lambert calibration's"
            + (f"; k_A of the direct light alone ~ {info['k_a_direct_estimate']:.4f}"
               if info.get("k_a_direct_estimate") is not None
               else f"; {info['k_a_note']}" if info.get("k_a_note") else "")      # why it is missing (user audit)
            + " (stray.png shows where it enters the view)")
        # trial 10 D5: the headline k_A and stray.png do not follow --resolution/--spp; say what they used
        say(f"k_A with stray light and stray.png: the stray-light run's {st['resolution']} x {st['resolution']} "
            f"pixels and {st['samples']} samples (fixed; --resolution {args.resolution} and --spp {args.spp} "
            "set view.exr, render.png and the direct k_A)")
    for v in info["files"].values():
        say(f"wrote {v}")
    return 0
