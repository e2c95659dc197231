"""Pictures of one measurement cell (``roadgonio render``): the detector's view of the sample
(the field of view, with the luminance of the road sample) and the horizontal illuminance on
the sample around the detector footprint; OpenEXR (float32) and PNG (colour bar, footprint
outline). When the scene makes stray light (reflecting parts: an XML scene's walls, the
[housing]), also where the stray light enters the detector's view and which part it comes from
(:func:`stray_picture`: ``stray.png``, ``stray.exr``).

Units: 1 lx normal to the source's axis at the sample centre from the cell's source, so the
illuminance is in lx per lx and luminances in cd/m^2 per lx (the scene's source gives that at the
distance :func:`~roadgonio.engines.mitsuba.scene.source_radiance` takes; a fixed-height path's farther
cells are scaled to it, :func:`unit_scale`, with the exact solid angle of the disc and its beam
profile, so E_h is 1 at the centre of a cell at tan eps 0).

A source with a beam profile (docs/conventions.md section 4.1), a hard beam cone or a point source
(R_S = 0: I_0 cos theta about the axis, section 5) is rendered with the k_A engine's ``kabatch``
integrator for this one cell (:class:`~roadgonio.engines.mitsuba.engine.BatchEngine`: the scene's
own source moved out of the way, the cell's source sampled with its profile), so all three pictures
and the k_A estimate include it; a uniform disc with Mitsuba's ``direct`` integrator and the scene's
own disc (the two are the same physics: tests/plugin/test_engine.py).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from roadgonio.fileio import atomic_write
from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel
from roadgonio.instrument.optics import footprint_boundary
from roadgonio.engines.mitsuba.scene import LAMBERT, ROAD, build_scene


def write_exr(path: Path, channels: dict[str, np.ndarray], attributes: dict[str, Any] | None = None) -> Path:
    """Float32 channels into an OpenEXR file; ``attributes``: text (or float lists) kept in its header,
    so that the file says what it holds without render.json (user audit, session 38)."""
    import OpenEXR
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (attributes or {}).items():
        header[k] = v if isinstance(v, str) else np.asarray(v, dtype=np.float32)
    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    return atomic_write(path, lambda p: OpenEXR.File(header, data).write(str(p)))


def _ortho_sensor(mi, x0, x1, y0, y1, nx, ny, spp, z_top=0.0):
    """Orthographic camera looking straight down on the region [x0, x1] x [y0, y1]; its rays
    start just above ``z_top`` (the top of the sample), so the source and other parts of the
    scene above the sample do not hide it."""
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    sx, sy = 0.5 * (x1 - x0), 0.5 * (y1 - y0)
    # camera frame: looks along -z; film x -> world +x, film y (down) -> world -y. Mitsuba's
    # orthographic camera spans [-1, 1] across the film's width and [-1, 1] / aspect across its
    # height (aspect = nx / ny), so the y scale carries the aspect: the film then covers y0 ... y1
    # (it covered a band 1/aspect as tall, drawn and recorded as y0 ... y1)
    m = np.array([[-sx, 0, 0, cx], [0, sy * nx / ny, 0, cy], [0, 0, -1.0, 10.0], [0, 0, 0, 1]])
    return mi.load_dict({"type": "orthographic", "to_world": mi.ScalarTransform4f(m.tolist()),
                         "near_clip": 10.0 - (z_top + 1e-3), "far_clip": 20.0,
                         "film": {"type": "hdrfilm", "width": nx, "height": ny, "rfilter": {"type": "box"},
                                  "pixel_format": "rgb"},
                         "sampler": {"type": "multijitter", "sample_count": spp}})


#: The units of the rendered images (module docstring), in render.json and the EXR files' headers.
EXR_UNITS = ("relative to 1 lx normal to the source's axis at the sample centre: illuminance in lx per lx, "
             "luminance in cd/m^2 per lx")

#: Fewer detector samples than this (resolution^2 x spp) give no k_A estimate: the ratio of the two
#: signals and its delta-method SE are unreliable there (audit 21, the wide instrument at tan eps 12,
#: beta 0: 8 x 8 pixels at 1 spp gave 0.43 on average against 0.256, 6 of 20 seeds beyond 4 SE;
#: from 32 x 32 x 4 = 4096 on every seed was within 2 SE)
RENDER_MIN_KA_SAMPLES = 4096

#: Every file ``roadgonio render`` writes (the last two only when the scene makes stray light).
RENDER_FILES = ("view.exr", "illuminance.exr", "render.png", "render.json", "stray.png", "stray.exr")


def unit_scale(instrument: Instrument, tan_eps: float, beta_deg: float) -> float:
    """The factor that puts a render of this cell in :data:`EXR_UNITS`: 1 / E_normal, E_normal the
    illuminance normal to the axis at the sample centre from this cell's source at the scene's radiance
    :func:`~roadgonio.engines.mitsuba.scene.source_radiance`: L_0 Omega_S(D_S), D_S the cell's source
    distance (a fixed-height path's source is farther than its height off tan eps 0) and Omega_S the
    exact projected solid angle with the beam profile
    (:func:`~roadgonio.engines.calibration.profiled_solid_angle`). User audit, session 42: the scale was
    (D_S / length)^2 alone, as if every source point sent its on-axis radiance to the centre: a Gaussian
    beam of 2 deg on the portable's disc rendered E 12 % low, of 0.5 deg 4.1 times low, and a uniform
    disc 6e-4 low (pi R^2 / D^2 for pi R^2 / (R^2 + D^2)). A point source: I_0 / D_S^2."""
    from roadgonio.engines.calibration import profiled_solid_angle
    from roadgonio.engines.mitsuba.scene import source_radiance
    from roadgonio.instrument.optics import source_frames
    src = instrument.source
    d = float(source_frames(instrument, tan_eps, beta_deg).distance_m)
    if src.is_point:
        return (d / src.length_m) ** 2
    at_d = instrument if d == src.length_m else instrument.with_changes(source={src.length_key: d})
    return 1.0 / (source_radiance(instrument) * profiled_solid_angle(at_d))


def kabatch_lit(instrument: Instrument) -> bool:
    """Whether the cell's source is lit by the k_A engine's ``kabatch`` integrator: a beam profile, a
    hard cone, or a point source (R_S = 0 is I_0 cos theta about the axis, docs/conventions.md section 5;
    Mitsuba's ``point`` emitter of the scene is isotropic and lit a housing behind the source), and any
    scene whose shapes shade the footprint (``[scene]`` parts, a ``[housing]``, a mesh sample): Mitsuba's
    ``direct`` integrator spawns its shadow rays lifted off the surface, which moved the holder's
    shadow edge by ~0.1 mm and its k_A by 2.5e-5, 50 of its stated SEs (user audit, session 44; the
    kabatch integrator's shadow ray, validation.md "Parts that shade the footprint")."""
    src = instrument.source
    shaded = bool(instrument.scene_parts()) or instrument.sample.mesh is not None
    return bool(src.profiled or src.beam_half_angle_deg is not None or src.is_point or shaded)


def render_cell_images(instrument: Instrument, model: RoadModel, tan_eps: float, beta_deg: float, out_dir,
                       *, resolution: int = 256, spp: int = 64, seed: int = 0, mitsuba_variant: str | None = None,
                       sample_name: str = "sample") -> dict[str, Any]:
    """Render the detector's view and the illuminance for one cell; write EXR, PNG and JSON."""
    out_dir = Path(out_dir)
    rs = build_scene(instrument, model, resolution=resolution, mitsuba_variant=mitsuba_variant, sampler="multijitter")
    import mitsuba as mi
    if kabatch_lit(instrument):
        from roadgonio.engines.mitsuba.engine import BatchEngine, cell_sources
        # the profiled source of the cell, one with a hard cone or a point source, lit by the kabatch
        # integrator (the scene's own emitter has no profile, no cone, and its point is isotropic)
        engine = BatchEngine(rs)
        engine.check_cells([(tan_eps, beta_deg)])
        engine.integrator.set_cells(*cell_sources(instrument, [(tan_eps, beta_deg)]))
        rs.integrator = engine.integrator        # its cell 0
        rs.cell = (float(tan_eps), float(beta_deg))
    else:
        rs.place_source(tan_eps, beta_deg)
    # the signal (concentric film) and its k_A estimate
    from roadgonio.engines.result import ideal_ratio
    from roadgonio.engines.mitsuba.backend import pooled_ratio
    # the scene's source gives ~1 lx at its nearest distance (scene.source_radiance); a fixed-height
    # path's source is farther at this cell: the pictures are scaled to the unit they state, 1 lx normal
    # to the axis at the sample centre from this cell's source (user audit, session 40: 10x too dark at
    # tan eps 3 on the corridor preset)
    unit = unit_scale(instrument, tan_eps, beta_deg)
    sig = rs.render(seed, spp) * unit
    ratio, se, mg = pooled_ratio([(spp, sig[..., ROAD], sig[..., LAMBERT])])
    ideal = ideal_ratio(model, instrument, tan_eps, beta_deg)
    # picture of the field of view
    rs.sensor.mapping = "square"
    try:
        view = rs.render(seed, spp) * unit      # the same seed: seed + 1 would be another seed's signal stream
    finally:
        rs.sensor.mapping = "concentric"
    # illuminance around the footprint, seen from above (Lambert channel: L = E_h / pi)
    fx, fy = footprint_boundary(instrument)
    x0, x1 = float(fx.min()), float(fx.max())
    y0, y1 = float(fy.min()), float(fy.max())
    mx = 0.15 * (x1 - x0) + 1e-3
    half_y = max(3.0 * 0.5 * (y1 - y0), 0.06 * (x1 - x0), 1e-3)
    cy = 0.5 * (y0 + y1)
    ex0, ex1, ey0, ey1 = x0 - mx, x1 + mx, cy - half_y, cy + half_y
    nx, ny = 512, 128
    z_top = float(rs.sample_shape.bbox().max.z)
    cam = _ortho_sensor(mi, ex0, ex1, ey0, ey1, nx, ny, 16, z_top)
    top = np.array(mi.render(rs.scene, sensor=cam, integrator=rs.integrator, seed=seed, spp=16), dtype=np.float64) * unit
    E = math.pi * top[..., LAMBERT]
    L_top = top[..., ROAD]

    stray = stray_picture(rs, tan_eps, beta_deg, seed=seed, scale=unit) if rs.stray else None

    from roadgonio.fileio import OutputGroup
    files = {"view_exr": str(out_dir / "view.exr"), "illuminance_exr": str(out_dir / "illuminance.exr"),
             "png": str(out_dir / "render.png"), "json": str(out_dir / "render.json")}
    if stray is not None:
        files.update(stray_png=str(out_dir / "stray.png"), stray_exr=str(out_dir / "stray.exr"))
    from roadgonio.provenance import provenance
    prov = provenance(instrument=instrument, model=model, backend="mitsuba",
                      settings={"resolution": resolution, "spp": spp, "seed": seed, "sampler": "multijitter",
                                "integrator": "kabatch" if kabatch_lit(instrument) else "direct",
                                "mitsuba_variant": mi.variant(), "illuminance_resolution": [nx, ny],
                                "illuminance_spp": 16})
    info = {"provenance": prov,
            "sample": sample_name, "tan_eps": tan_eps, "beta_deg": beta_deg,
            "resolution": resolution, "spp": spp, "seed": seed,
            "signal_road": float(np.mean(sig[..., ROAD])), "signal_lambert": mg,
            "ratio": ratio, "ratio_se": se, "ideal_ratio": ideal,
            "k_a_estimate": ratio / ideal if ideal > 0 else None,
            "k_a_se": se / ideal if ideal > 0 else None,
            "footprint_m": {"x": [x0, x1], "y": [y0, y1]},
            "illuminance_window_m": {"x": [ex0, ex1], "y": [ey0, ey1]},
            "units": EXR_UNITS}
    definitions = {
        "signal_road": "mean detector signal of the road sample over the view (this render, light straight from "
                       "the source), in the units above",
        "signal_lambert": "the same for the instrument's calibration (a perfect diffuser)",
        "ratio": "the road's reading over the calibration's, as the instrument computes q; ratio_se its standard error",
        "ideal_ratio": "the same ratio of the ideal point geometry (eq. 2)",
        "k_a_estimate": "ratio / ideal_ratio: this render's k_A (one render; 'roadgonio ka' for tables); k_a_se its "
                        "standard error"}
    if stray is not None:
        info["stray"] = stray["summary"]
        # everything without a suffix is what the instrument measures (stray light included); the direct
        # integrator's numbers above carry _direct
        tot = stray["summary"]
        for old_key, new_key in (("signal_road", "signal_road_direct"), ("signal_lambert", "signal_lambert_direct"),
                                 ("ratio", "ratio_direct"), ("ratio_se", "ratio_direct_se")):
            info[new_key] = info.pop(old_key)
        info["ratio"], info["ratio_se"] = tot["ratio"], tot["ratio_se"]
        info["k_a_direct_estimate"], info["k_a_direct_se"] = info["k_a_estimate"], info["k_a_se"]
        if ideal > 0:
            info["k_a_estimate"], info["k_a_se"] = tot["ratio"] / ideal, tot["ratio_se"] / ideal
        definitions = {
            "ratio": "the road's reading over the calibration's with the stray light (both see the housing), from the "
                     "stray-light paths (stray.ratio); ratio_se its standard error",
            "ideal_ratio": definitions["ideal_ratio"],
            "k_a_estimate": "ratio / ideal_ratio: this render's k_A with the stray light; k_a_se its standard error",
            "signal_road_direct": "mean detector signal of the road sample over the view, light straight from the "
                                  "source only (the picture render.png), in the units above",
            "signal_lambert_direct": "the same for the calibration (a perfect diffuser)",
            "ratio_direct": "signal_road_direct / signal_lambert_direct; ratio_direct_se its standard error",
            "k_a_direct_estimate": "ratio_direct / ideal_ratio: k_A of the direct light alone; k_a_direct_se its "
                                   "standard error",
            "stray": "the stray light of this cell: fractions of each signal and the shares by housing part"}
    if resolution * resolution * spp < RENDER_MIN_KA_SAMPLES:
        # the estimate of this render's own samples (with stray light, the stray paths' fixed sample
        # count gives k_A itself; the direct light's estimate is this render's)
        keys = ("k_a_direct_estimate", "k_a_direct_se") if stray is not None else ("k_a_estimate", "k_a_se")
        for key in keys:
            info[key] = None
        info["k_a_note"] = (f"no k_A{' of the direct light' if stray is not None else ''} estimate from "
                            f"{resolution * resolution * spp} samples (resolution^2 x spp): {RENDER_MIN_KA_SAMPLES} "
                            "or more give one with an SE that holds")
    info["definitions"] = definitions
    info["files"] = files
    # all or none; a render without stray light removes an earlier housed render's stray.png and
    # stray.exr (trial 10 D4: they stayed beside the new pictures, of another instrument and cell)
    with OutputGroup(out_dir, replaces=RENDER_FILES) as stage:
        what = {"roadgonio_instrument": instrument.name, "roadgonio_sample": str(sample_name),
                "roadgonio_cell": f"tan eps {tan_eps:g}, beta {beta_deg:g} deg",
                "roadgonio_units": EXR_UNITS}
        write_exr(stage.path("view.exr"), {"RGB": view, "L_road": view[..., ROAD], "L_lambert": view[..., LAMBERT]},
                  {**what, "comments": "the detector's view inside the field stop (square mapping): L_road the road "
                                       "sample's luminance, L_lambert the calibration's (a perfect diffuser)"})
        write_exr(stage.path("illuminance.exr"), {"E_h": E, "L_road_top": L_top},
                  {**what, "roadgonio_window_m": [ex0, ex1, ey0, ey1],
                   "comments": "seen from above over roadgonio_window_m (x0, x1, y0, y1 in m; image rows from y1 "
                               "down to y0): E_h the horizontal illuminance, L_road_top the road's luminance "
                               "towards +z"})
        _png(stage.path("render.png"), instrument, view, E, (ex0, ex1, ey0, ey1), (fx, fy), info)
        if stray is not None:
            write_exr(stage.path("stray.exr"), stray["images"], {**what, "comments": "where the stray light enters the detector's view (stray.png; docs/straylight.md)"})
            _stray_png(stage.path("stray.png"), instrument, stray, info)
        stage.json("render.json", info)
    return info


#: Points of one replicate of the stray picture, the replicates (many small lattices: the per-pixel
#: means of one large lattice show its stripes), and the replicates per launch.
STRAY_PICTURE_LOG2 = 12
STRAY_PICTURE_REPLICATES = 256
STRAY_PICTURE_BATCH = 32
#: Pixels per side of the stray picture.
STRAY_PICTURE_RESOLUTION = 96


def stray_picture(rs, tan_eps: float, beta_deg: float, *, seed: int = 0, log2n: int = STRAY_PICTURE_LOG2,
                  replicates: int = STRAY_PICTURE_REPLICATES, resolution: int = STRAY_PICTURE_RESOLUTION,
                  scale: float = 1.0) -> dict:
    """Where the stray light enters the detector's view and which part it comes from: the view of the
    field stop (square mapping, as view.exr) sampled with the batched engine's paths for this one
    cell (:meth:`KaBatch.picture_lanes`): per pixel the direct and the stray road luminance, the
    stray luminance by the part of the last reflection before the footprint, and the road and
    Lambert signals of the whole view with their stray parts (SE from ``replicates`` replicates).
    Changes the scene's source placement (the engine's own source replaces it)."""
    import drjit as dr

    from roadgonio.engines.mitsuba import lattice as lat
    from roadgonio.engines.mitsuba.engine import BatchEngine, cell_sources
    from roadgonio.engines.mitsuba.plugins.ka_batch import _u32
    eng = BatchEngine(rs)
    integ = eng.integrator
    eng.check_cells([(tan_eps, beta_deg)])
    integ.set_cells(*cell_sources(rs.instrument, [(tan_eps, beta_deg)]))
    n = 1 << int(log2n)
    z = lat.generating_vector(n, lat.DIMENSIONS + integ.qmc_dims)
    shifts = np.concatenate([lat.shifts(seed, 0, log2n, replicates),
                             lat.walk_shifts(seed, 0, log2n, replicates, integ.qmc_dims)], axis=1)
    keys_all = lat.walk_keys(seed, 0, log2n, replicates, integ.walk_dims)
    ids = [SAMPLE_LABEL] + list(rs.part_ids)
    P = len(ids)
    res = int(resolution)
    sums = np.zeros((2 + P, res * res))             # direct road, stray road, stray road by part
    counts = np.zeros(res * res)
    reps = np.zeros((replicates, 4))                # direct road, direct Lambert, stray road, stray Lambert
    by_part = np.zeros((replicates, P, 2))
    rs.sensor.mapping = "square"
    try:
        for b0 in range(0, replicates, STRAY_PICTURE_BATCH):
            b1 = min(replicates, b0 + STRAY_PICTURE_BATCH)
            lattice = integ.lattice_params(n, z, shifts[b0:b1])
            keys = [_u32(keys_all[b0:b1, d]) for d in range(keys_all.shape[1])]
            lanes = integ.picture_lanes(rs.scene, rs.sensor, lattice, keys, reps=b1 - b0)
            rep = b0 + lanes["rep"].astype(np.int64)
            pix = (np.minimum((lanes["v"] * res).astype(np.int64), res - 1) * res
                   + np.minimum((lanes["u"] * res).astype(np.int64), res - 1))
            counts += np.bincount(pix, minlength=res * res)
            sums[0] += np.bincount(pix, lanes["direct_road"], minlength=res * res)
            reps[:, 0] += np.bincount(rep, lanes["direct_road"], minlength=replicates)
            reps[:, 1] += np.bincount(rep, lanes["direct_lambert"], minlength=replicates)
            q = 0
            while f"road_{q}" in lanes:
                part = np.minimum(lanes[f"part_{q}"].astype(np.int64), P - 1)
                road, lamb = lanes[f"road_{q}"], lanes[f"lambert_{q}"]
                sums[1] += np.bincount(pix, road, minlength=res * res)
                for p_ in range(P):
                    m = part == p_
                    sums[2 + p_] += np.bincount(pix[m], road[m], minlength=res * res)
                    by_part[:, p_, 0] += np.bincount(rep[m], road[m], minlength=replicates)
                    by_part[:, p_, 1] += np.bincount(rep[m], lamb[m], minlength=replicates)
                reps[:, 2] += np.bincount(rep, road, minlength=replicates)
                reps[:, 3] += np.bincount(rep, lamb, minlength=replicates)
                q += 1
            del lanes
            dr.flush_malloc_cache()
    finally:
        rs.sensor.mapping = "concentric"
    with np.errstate(invalid="ignore", divide="ignore"):
        # ``scale``: the luminances in the render's unit (:func:`unit_scale`); the summary's ratios need none
        img = (sums / np.maximum(counts, 1.0)).reshape(2 + P, res, res) * scale
    from roadgonio.engines.mitsuba.passes import strata_ratio_se
    R, G = reps[:, 0] + reps[:, 2], reps[:, 1] + reps[:, 3]
    # the engine's ratio estimator over the independent replicates (one stratum)
    ratio, ratio_se_ = strata_ratio_se([(R, G)])
    q_road, q_road_se = strata_ratio_se([(reps[:, 0], R)])
    q_lam, q_lam_se = strata_ratio_se([(reps[:, 1], G)])
    shares = by_part.sum(axis=0)
    summary = {"cell": [float(tan_eps), float(beta_deg)], "max_bounces": eng.max_bounces,
               "stray_fraction_road": 1.0 - q_road, "stray_fraction_road_se": q_road_se,
               "stray_fraction_lambert": 1.0 - q_lam, "stray_fraction_lambert_se": q_lam_se,
               "ratio": ratio, "ratio_se": ratio_se_,
               "parts": {ids[p_]: {"road": float(shares[p_, 0] / R.sum()), "lambert": float(shares[p_, 1] / G.sum())}
                         for p_ in range(P)},
               "samples": int(n * replicates), "resolution": res,
               "note": "shares of the whole signal (direct + stray) by the part of the last reflection before the "
                       "footprint; road = the sample's channel, lambert = the calibration's perfect diffuser"}
    images = {"L_direct": img[0], "L_stray": img[1], **{f"L_{ids[p_]}": img[2 + p_] for p_ in range(P)}}
    words = _part_labels(rs)
    summary["part_labels"] = {i: words.get(i, i) for i in ids}       # the words stray.png and the printout use
    return {"summary": summary, "images": images, "ids": ids, "stack": img}


#: Name of the sample in the stray picture (the part of a path's last reflection may be the sample).
SAMPLE_LABEL = "sample"


def _part_labels(rs) -> dict[str, str]:
    """The words for the housing's parts in stray.png by id: each panel's own label ("wall y = -0.075 m",
    "baffle 0 (x = ...)", numbered as the field housing.baffles.0); an XML part has none and keeps its id
    (user audit, session 40: the key showed ids such as housing_baffle_1 beside errors that call it
    baffle 0). render.json and stray.exr keep the ids. The panels are built once."""
    if rs.housing is None:
        return {}
    from roadgonio.instrument.enclosure import housing_panels
    return {p.id: p.label for p in housing_panels(rs.instrument, rs.housing) if p.label}


def _stray_png(path: Path, instrument: Instrument, stray: dict, info) -> Path:
    """stray.png: the stray fraction over the detector's view, the view in false colour by the part
    the stray light last left before the footprint, and each part's share of the signal."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import colormaps

    from roadgonio.fileio import atomic_savefig
    img, ids, summ = stray["stack"], stray["ids"], stray["summary"]
    names = [summ["part_labels"][i] for i in ids]
    gamma = instrument.detector.field_half_angle_deg
    ext = gamma if gamma > 0 else 1.0
    res = img.shape[-1]
    yy, xx = np.mgrid[0:res, 0:res]
    inside = ((2 * (xx + 0.5) / res - 1) ** 2 + (2 * (yy + 0.5) / res - 1) ** 2) <= 1.0
    total = img[0] + img[1]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(inside & (total > 0), img[1] / total, np.nan)
    parts = img[2:]
    colours = np.array([colormaps["tab10"](k % 10)[:3] for k in range(len(ids))])
    stray_lum = parts.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mix = np.einsum("pij,pc->ijc", parts, colours) / np.maximum(stray_lum, 1e-300)[..., None]
    scale = float(np.nanpercentile(stray_lum[inside], 99.0)) if np.any(stray_lum[inside] > 0) else 1.0
    bright = np.clip(stray_lum / max(scale, 1e-300), 0.0, 1.0) ** 0.5
    rgb = np.where(inside[..., None], mix * bright[..., None], 1.0)
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2), gridspec_kw={"width_ratios": [1, 1, 1.1]})
    ax = axes[0]
    im = ax.imshow(100 * frac, extent=(-ext, ext, -ext, ext), origin="upper", cmap="magma", vmin=0)
    fig.colorbar(im, ax=ax, shrink=0.8).set_label("stray light, % of the road luminance")
    ax.set_title("Stray fraction over the detector's view", fontsize=10)
    ax = axes[1]
    ax.imshow(rgb, extent=(-ext, ext, -ext, ext), origin="upper")
    ax.set_title("The road sample's stray light by the part it last left\n(colour: part, key below; brightness: "
                 "its luminance, to the 99th percentile)", fontsize=10)
    # the key of the colours in the panel itself (user audit, session 38: only the bar chart had them)
    from matplotlib.patches import Patch
    # every part coloured in the panel, below it (user audit, session 43: the four brightest only, inside
    # the view over its near edge, while a fifth part's colour was in the mix)
    lit = [k for k in np.argsort(-parts.reshape(len(ids), -1).sum(axis=1)) if parts[k].sum() > 0]
    if lit:
        ax.legend(handles=[Patch(color=colours[k], label=names[k]) for k in lit], fontsize=7, loc="upper center",
                  bbox_to_anchor=(0.5, -0.2), ncol=3, frameon=False)
    for a in axes[:2]:
        t = np.linspace(0, 2 * np.pi, 200)
        a.plot(ext * np.cos(t), ext * np.sin(t), color="cyan", lw=1.0)
        # oriented as render.png's view (user audit, session 40: no orientation here)
        a.set_xlabel("field angle, horizontal (deg; right = +y, as the meter looks)\nnear edge of the footprint at the "
                     "bottom, far edge at the top", fontsize=9)
        a.set_ylabel("field angle, vertical (deg)")
        a.set_aspect("equal")
    ax = axes[2]
    road = np.array([100 * summ["parts"][i]["road"] for i in ids])
    lam = np.array([100 * summ["parts"][i]["lambert"] for i in ids])
    order = np.argsort(-(road + lam))
    keep = [k for k in order if road[k] + lam[k] > 0]
    yk = np.arange(len(keep))
    ax.barh(yk - 0.2, road[keep], height=0.4, color=colours[keep], label="road sample")
    ax.barh(yk + 0.2, lam[keep], height=0.4, color=colours[keep], alpha=0.45, hatch="//",
            label="Lambert calibration (perfect diffuser)")
    ax.set_yticks(yk, [names[k] for k in keep], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("share of the detector signal (%)")
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title("Which part the stray light comes from", fontsize=10)
    ka = info.get("k_a_estimate")
    kd = info.get("k_a_direct_estimate")
    fig.suptitle(f"{instrument.name}, sample {info['sample']}: tan eps = {info['tan_eps']:g}, beta = {info['beta_deg']:g} deg: "
                 f"stray light {100 * summ['stray_fraction_road']:.2f} % of the road signal, "
                 f"{100 * summ['stray_fraction_lambert']:.2f} % of the Lambert calibration's"
                 + (f"\nk_A ~ {ka:.4f} with the stray light, {kd:.4f} of the direct light (this render)"
                    if ka is not None and kd is not None else ""), fontsize=11)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=100, bbox_inches="tight")      # the key below the middle panel
    plt.close(fig)
    return path


def _hull(x, y):
    """Closed outline (convex hull) of the footprint's extreme-ray hit points."""
    pts = np.stack([x, y], -1)
    try:
        from scipy.spatial import ConvexHull
        # scale y so a very elongated footprint is not a degenerate hull
        sc = max(np.ptp(x), 1e-12) / max(np.ptp(y), 1e-12)
        v = ConvexHull(pts * [1.0, sc]).vertices
    except Exception:  # degenerate (a single ray): draw the points
        return x, y
    v = np.append(v, v[0])
    return pts[v, 0], pts[v, 1]


#: render.png's colour of unlit ground (E_h = 0) on its log-scale illuminance panel: outside the scale
UNLIT_GREY = "0.75"
#: render.png draws E_h on a log scale when its largest value is E_LOG_SPAN times the footprint's median
#: E_h; the smallest value it shows is at least the largest / E_LOG_DECADES_MAX (1e4: four decades)
E_LOG_SPAN = 20.0
E_LOG_DECADES_MAX = 1e4

#: The illuminance panel's title says here which axis is stretched, once the panel is laid out (_png).
STRETCH_WORDS = " (not to scale: y stretched)"


def panel_words(instrument: Instrument, info: dict[str, Any]) -> dict[str, str]:
    """Words of render.png that depend on the scene: ``stray`` (added to both panels' titles in a
    reflecting housing, where they show the direct light only: user audit, a view and an illuminance
    1.36 x too low titled as the whole), ``illuminance_title`` and ``x_label`` (the sample's frame: the
    detector is towards +x only at delta = 0; user audit, at delta 30 the footprint ran along 30 deg
    under the label 'detector towards +x')."""
    stray = info.get("stray")
    words = ("" if stray is None else
             f"\nthe direct light only: the stray light ({100 * stray['stray_fraction_road']:.1f} % of the road "
             "signal) is in stray.png")
    delta = instrument.observation.delta_deg
    return {"stray": words,
            "illuminance_title": "Horizontal illuminance on the sample" + (" straight from the source" if stray
                                                                           is not None else "")
                                 + f"{STRETCH_WORDS}{words}",
            "x_label": ("x on the sample (m; detector towards +x)" if delta == 0 else
                        f"x on the sample (m; the detector at azimuth delta = {delta:g} deg from +x)")}


def _png(path: Path, instrument: Instrument, view, E, window, outline, info) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from roadgonio.fileio import atomic_savefig
    gamma = instrument.detector.field_half_angle_deg
    point = gamma <= 0                      # a zero field: no view to draw, a short top panel saying so
    words = panel_words(instrument, info)
    stray_words = words["stray"]
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.8 if point else 8.5),
                             gridspec_kw={"height_ratios": [0.3 if point else 1.25, 1]})
    ax = axes[0]
    L = view[..., ROAD]
    if not point:
        vmax = float(np.percentile(L[L > 0], 99.5)) if np.any(L > 0) else 1.0
        im = ax.imshow(L, extent=(-gamma, gamma, -gamma, gamma), origin="upper", cmap="magma", vmin=0, vmax=vmax)
        t = np.linspace(0, 2 * np.pi, 200)
        ax.plot(gamma * np.cos(t), gamma * np.sin(t), color="cyan", lw=1.0, label="field stop")
        ax.set_aspect("equal")
        ax.set_xlabel("field angle, horizontal (deg; right = +y, as the meter looks)")
        ax.set_ylabel("field angle, vertical (deg)")
        # with a sensitivity over the field the view is what the meter weighs: luminance x k_D (audit 27:
        # a map darkened half of a view labelled "luminance")
        weighted = instrument.detector.field_map is not None or instrument.detector.field_edge_sensitivity != 1.0
        # in a reflecting housing these two panels are the direct light only; the stray light is in
        # stray.png (user audit: a view and an illuminance 1.36 x too low, titled as the whole)
        ax.set_title(f"Detector's view: luminance of the sample{' x its sensitivity k_D' if weighted else ''} "
                     f"(field half-angle {gamma:g} deg){stray_words}", fontsize=10)
        # the colour bar beside the square view, both centred (fig.colorbar(ax=ax) anchors the square view
        # at the right of its wide slot: a large blank area on its left)
        from mpl_toolkits.axes_grid1 import make_axes_locatable
        cb = fig.colorbar(im, cax=make_axes_locatable(ax).append_axes("right", size="4%", pad=0.15))
        cb.set_label("luminance x k_D (cd/m$^2$ per lx)" if weighted else "luminance (cd/m$^2$ per lx)")
        # on a dark box: white text alone vanished on a bright view
        ax.text(0.02, 0.03, "near edge of the footprint at the bottom,\nfar edge at the top", transform=ax.transAxes,
                color="white", fontsize=8, va="bottom",
                bbox={"facecolor": "black", "edgecolor": "none", "alpha": 0.6, "pad": 2.0})
    else:
        # a zero field sees one point of the sample: there is no view to draw (a +-1 deg disc was drawn)
        ax.set_axis_off()
        ax.set_title("Detector's view (field half-angle 0 deg)", fontsize=10)
        ax.text(0.5, 0.5, "point field: no image\n(the detector sees one point of the sample)", ha="center",
                va="center", fontsize=11, transform=ax.transAxes)

    ax = axes[1]
    x0, x1, y0, y1 = window
    unlit: list = []          # a legend entry for unlit ground on the log scale
    fx, fy = outline
    # a logarithmic scale where E spans decades over the footprint: at grazing light on the wide preset the
    # spot under the source's foot (E 56) left the rest of the footprint (0.01-0.6) uniformly dark on a
    # linear scale (user audit, session 40)
    ny_, nx_ = E.shape
    cols = (np.arange(nx_) + 0.5) / nx_ * (x1 - x0) + x0
    rows = y1 - (np.arange(ny_) + 0.5) / ny_ * (y1 - y0)
    near = (((cols >= fx.min()) & (cols <= fx.max()))[None, :] & ((rows >= fy.min()) & (rows <= fy.max()))[:, None])
    lit = E[near & (E > 0)]
    top_e = float(np.max(E))
    log = lit.size > 0 and top_e > E_LOG_SPAN * float(np.median(lit))
    if log:
        from matplotlib.colors import LogNorm
        norm = LogNorm(vmin=max(float(np.percentile(lit, 1.0)), top_e / E_LOG_DECADES_MAX), vmax=top_e)
        from matplotlib import colormaps
        base = colormaps["viridis"]
        # unlit (E = 0) in grey, apart from the scale, and E below its bottom as the bar's extension: both
        # were the scale's darkest colour, which stands for light (user audit, session 44: 60 % of the
        # wide preset's window, behind the source disc's plane, looked dimly lit)
        cmap = base.with_extremes(bad=UNLIT_GREY, under=base(0.0))
        im = ax.imshow(np.where(E > 0, E, np.nan), extent=(x0, x1, y0, y1), origin="upper", cmap=cmap,
                       aspect="auto", norm=norm)
        if np.any(E <= 0):
            from matplotlib.patches import Patch
            unlit = [Patch(facecolor=UNLIT_GREY, edgecolor="0.4", label="unlit (E$_h$ = 0)")]
        below = bool(np.any((E > 0) & (E < norm.vmin)))
    else:
        im = ax.imshow(E, extent=(x0, x1, y0, y1), origin="upper", cmap="viridis", aspect="auto", vmin=0)
    if max(np.ptp(fx), np.ptp(fy)) <= 1e-9 * max(x1 - x0, y1 - y0):
        # zero pupil and field: the footprint is a point (a zero-size outline drew nothing but its legend)
        ax.plot([np.mean(fx)], [np.mean(fy)], "r+", ms=12, mew=1.5, ls="none", label="detector footprint (a point)")
    else:
        hx, hy = _hull(fx, fy)
        ax.plot(hx, hy, color="red", lw=1.2, label="detector footprint")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_xlabel(words["x_label"])
    ax.set_ylabel("y (m)")
    ax.set_title(words["illuminance_title"], fontsize=10)
    ax.legend(handles=ax.get_legend_handles_labels()[0] + unlit, loc="upper right", fontsize=8)
    cb = fig.colorbar(im, ax=ax, shrink=0.9, extend="min" if log and below else "neither")
    # two lines: on one the label ran off the figure at its start (user audit, session 40)
    cb.set_label("illuminance E$_h$ (lx per lx normal\nto the source axis at the sample centre"
                 + (")\nlog scale" if log else ")"))
    ka = info["k_a_estimate"]
    ka_txt = (f"k_A ~ {ka:.4f} +- {info['k_a_se']:.1e} (this render)" if ka is not None
              else "no k_A estimate (too few samples)" if "k_a_note" in info else "k_A undefined")
    if "stray" in info:
        # the headline is the stray-light run's; the two panels below are the direct light (user audit,
        # session 40: their own k_A was not in the picture)
        kd = info.get("k_a_direct_estimate")
        ka_txt = (ka_txt.replace("(this render)", "with the stray light (stray.png)") + "; the panels: direct light, "
                  + (f"k_A ~ {kd:.4f} +- {info['k_a_direct_se']:.1e}" if kd is not None
                     else "no k_A of it (too few samples)" if "k_a_note" in info else "k_A of it undefined"))
    fig.suptitle(f"{instrument.name}, sample {info['sample']}: tan eps = {info['tan_eps']:g}, "
                 f"beta = {info['beta_deg']:g} deg, alpha = {instrument.observation.alpha_deg:g} deg\n{ka_txt}",
                 fontsize=11)
    fig.tight_layout()
    # which axis the window's stretch is along, from the laid-out panel (user audit, session 40: "y
    # stretched" over a point footprint's 2 x 2 mm window, stretched in x)
    box = ax.get_window_extent()
    shown, data = box.width / max(box.height, 1e-9), (x1 - x0) / max(y1 - y0, 1e-300)
    stretch = "y" if data > 1.05 * shown else "x" if data < shown / 1.05 else None
    ax.set_title(words["illuminance_title"].replace(STRETCH_WORDS, "" if stretch is None else
                                                    f" (not to scale: {stretch} stretched)"), fontsize=10)
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return path
