"""The design Dataset (``design.nc``): assembled from the grid, the geometry checks and the tables
(:func:`assemble`), and read back (:func:`point_index`, :func:`best_instrument`, :func:`summary`).
:mod:`.run` builds it, :mod:`.outputs` writes it; both read it through this module.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from roadgonio.fileio import to_json
from roadgonio.instrument.config import Instrument
from roadgonio.engines import cluster as _cluster
from roadgonio.engines.result import standard_uncertainty
from roadgonio.engines.runner import STRAY_FILES, field_attrs
from roadgonio.design.grid import VarySpec
from roadgonio.design.metrics import (DIM_EDGE, SIGNAL_FORMULA, deviations, detector_etendue, footprint_edge_radiance,
                                      signal_product, signal_solid_angle, stray_metrics)

def assemble(*, base: Instrument, specs: Sequence[VarySpec], shape: tuple[int, ...], points, samples, union,
             feas, inst_of, done: Mapping[tuple[int, int], dict], seeds, tol: float):
    """The Dataset of a design (layout in :mod:`roadgonio.design`)."""
    import xarray as xr
    n, ns = len(points), len(samples)
    tans = np.array(sorted({t for t, _ in union}), dtype=np.float64)
    betas = np.array(sorted({b for _, b in union}), dtype=np.float64)
    ti = {float(t): k for k, t in enumerate(tans)}
    bi = {float(b): k for k, b in enumerate(betas)}
    k_a = np.full((n, ns, len(tans), len(betas)), np.nan)
    se = np.full_like(k_a, np.nan)
    dof = np.full_like(k_a, np.nan)          # NaN for tables journaled before it was kept
    bound = np.full_like(k_a, np.nan)
    conf = np.full_like(k_a, np.nan)
    level = np.full_like(k_a, np.nan)
    conv = np.ones(k_a.shape, dtype=bool)    # False where the backend stopped short (its bound an estimate)
    # stray light (CellResult: 0 and k_a without it); NaN for tables journaled before they were kept
    stray = {f: np.full_like(k_a, np.nan) for f in STRAY_CELL_FIELDS}
    seconds = np.zeros(n)
    geometry_ok = np.array([f.ok for f in feas], dtype=bool)
    kind = np.array([f.kind for f in feas], dtype=object)
    reason = np.array([f.reason for f in feas], dtype=object)
    for i in range(n):
        if not feas[i].ok:
            continue
        for j, s in enumerate(samples):
            rec = done.get((i, j))
            if rec is None:
                kind[i], reason[i] = "failed", "not computed (interrupted); run the same command again to finish"
                continue
            seconds[i] += float(rec.get("seconds") or 0.0)
            if rec.get("error"):
                if rec.get("error_kind") == "WorkerError":
                    kind[i], reason[i] = "failed", f"{rec['error']}; run the same command again to retry"
                else:
                    geometry_ok[i] = False
                    kind[i] = "backend"
                    reason[i] = f"{samples[j].name}: {rec['error']}"
                continue
            for c, (t, b) in enumerate(s.cells):
                a, bb = ti[float(t)], bi[float(b)]
                k_a[i, j, a, bb] = _f(rec["k_a"][c])
                se[i, j, a, bb] = _f(rec["se"][c])
                dof[i, j, a, bb] = _f((rec.get("se_dof") or [None] * len(s.cells))[c])
                bound[i, j, a, bb] = _f(rec["error_bound"][c])
                # journals written before the confidence bound was kept have neither field
                conf[i, j, a, bb] = _f((rec.get("confidence_bound") or [None] * len(s.cells))[c])
                level[i, j, a, bb] = _f((rec.get("confidence_level") or [None] * len(s.cells))[c])
                for f, arr in stray.items():
                    arr[i, j, a, bb] = _f((rec.get(f) or [None] * len(s.cells))[c])
                conv[i, j, a, bb] = bool(rec["converged"][c])
    max_dev = np.full(n, np.nan)
    rms = np.full(n, np.nan)
    worst_t = np.full(n, np.nan)
    worst_b = np.full(n, np.nan)
    worst_u = np.full(n, np.nan)
    worst_se = np.full(n, np.nan)
    worst_eb = np.full(n, np.nan)
    worst_conv = np.full(n, np.nan)
    worst_s = np.array([""] * n, dtype=object)
    max_dev_s = np.full((n, ns), np.nan)
    max_stray = np.full(n, np.nan)
    stray_t = np.full(n, np.nan)
    stray_b = np.full(n, np.nan)
    stray_u = np.full(n, np.nan)
    stray_s = np.array([""] * n, dtype=object)
    max_dev_direct = np.full(n, np.nan)
    computed = np.zeros(n, dtype=bool)
    for i in range(n):
        if kind[i] in ("failed",) or not geometry_ok[i]:
            continue
        d = deviations(k_a[i], standard_uncertainty(se[i], bound[i], conv[i]))
        if d["cells"] == 0:
            continue
        computed[i] = True
        max_dev[i], rms[i], worst_u[i] = d["max_abs_dev"], d["rms_dev"], d["worst_u"]
        js, a, bb = np.unravel_index(d["worst"], k_a[i].shape)
        worst_t[i], worst_b[i], worst_s[i] = tans[a], betas[bb], samples[js].name
        worst_se[i], worst_eb[i] = se[i, js, a, bb], bound[i, js, a, bb]
        worst_conv[i] = float(conv[i, js, a, bb])
        st = stray_metrics(stray["stray_fraction"][i], stray["k_a_direct"][i], stray["stray_fraction_se"][i])
        max_stray[i], stray_u[i], max_dev_direct[i] = st["max_stray_fraction"], st["stray_u"], st["max_abs_dev_direct"]
        if st["stray_worst"] >= 0:
            js, a, bb = np.unravel_index(st["stray_worst"], k_a[i].shape)
            stray_t[i], stray_b[i], stray_s[i] = tans[a], betas[bb], samples[js].name
        for j in range(ns):
            v = np.abs(k_a[i, j] - 1.0)
            max_dev_s[i, j] = np.nanmax(v) if np.isfinite(v).any() else np.nan
    # at the requested cells' source distances (a fixed-height path: D_S = height / cos eps)
    signal_abs = np.array([signal_product(x, union) if x is not None else np.nan for x in inst_of])
    # a design that detects no light (a point source, a zero field or pupil: the paper's ideal
    # geometry, k_A = 1 by definition) is no instrument to build: it was picked as the best when
    # nothing else met the tolerance (audit 21)
    dark = ~(signal_abs > 0)
    feasible = geometry_ok & computed & (max_dev <= tol) & ~dark
    for i in range(n):
        if geometry_ok[i] and computed[i] and not feasible[i]:
            if dark[i]:
                kind[i] = "signal"
                reason[i] = ("detects no light (signal 0: a zero source radius, field or pupil is the ideal point "
                             "geometry, not an instrument)")
                continue
            kind[i] = "tolerance"
            reason[i] = (f"max |k_A - 1| = {max_dev[i]:.4g} > tolerance {tol:g} at tan eps {worst_t[i]:g}, "
                         f"beta {worst_b[i]:g} ({worst_s[i]})")
    sb = signal_product(base, union)
    signal = signal_abs / sb if sb > 0 else np.full(n, np.nan)
    # the signal is the light at the footprint's centre (metrics): where the beam leaves part of the
    # footprint dark (a beam limit that clips it, a narrow profile), the detected flux is less (user audit)
    dim = np.array([x is not None and computed[i] and footprint_edge_radiance(x, union) < DIM_EDGE
                    for i, x in enumerate(inst_of)])
    omega = np.array([signal_solid_angle(x, union) if x is not None else np.nan
                      for x in inst_of])
    etendue = np.array([detector_etendue(x) if x is not None else np.nan for x in inst_of])
    fp_len = np.array([f.footprint_length_m for f in feas])
    fp_min = np.array([f.footprint[0] if f.footprint else np.nan for f in feas])
    fp_max = np.array([f.footprint[1] if f.footprint else np.nan for f in feas])

    dims = [s.key for s in specs]
    coords: dict[str, Any] = {s.key: np.array(s.values, dtype=np.float64) for s in specs}
    coords.update({"sample": np.array([s.name for s in samples], dtype=object), "tan_eps": tans, "beta": betas})

    def grid(v):
        return np.asarray(v).reshape(shape + np.asarray(v).shape[1:])

    cell_dims = dims + ["sample", "tan_eps", "beta"]
    conv_grid = grid(np.where(np.isfinite(k_a), conv.astype(np.float64), np.nan))
    data = {
        "k_a": (cell_dims, grid(k_a), {"long_name": "aperture-effect factor k_A (docs/conventions.md section 5)", "units": "1"}),
        "se": (cell_dims, grid(se), {"long_name": "standard error of k_A (Monte Carlo; NaN for deterministic backends)"}),
        "se_dof": (cell_dims, grid(dof), field_attrs("se_dof")),          # as in the k_A Dataset
        "error_bound": (cell_dims, grid(bound), {"long_name": "deterministic error bound of k_A (quadrature; beside se "
                                                              "under absolute calibration: eta's part of the error; "
                                                              "where converged is false an estimate that can understate "
                                                              "the error, not a bound; NaN otherwise)"}),
        "converged": (cell_dims, conv_grid, {"long_name": "the backend reached its target at the cell (false: stopped at "
                                                         "its cap; NaN where not computed)"}),
        "confidence_bound": (cell_dims, grid(conf), {"long_name": "statistical bound of |k_A - true k_A| holding with "
                                                                  "probability confidence_level (RQMC reference; NaN "
                                                                  "otherwise)"}),
        "confidence_level": (cell_dims, grid(level), {"long_name": "confidence level of confidence_bound (NaN without "
                                                                   "one)"}),
        **{f: (cell_dims, grid(arr), field_attrs(f)) for f, arr in stray.items()},   # as in the k_A Dataset
        "max_abs_dev": (dims, grid(max_dev), {"long_name": "max |k_A - 1| over the cells and samples"}),
        "max_abs_dev_sample": (dims + ["sample"], grid(max_dev_s), {"long_name": "max |k_A - 1| over the cells, per sample"}),
        "rms_dev": (dims, grid(rms), {"long_name": "root mean square of k_A - 1 over the cells and samples"}),
        "worst_tan_eps": (dims, grid(worst_t), {"long_name": "tan eps of the worst cell"}),
        "worst_beta_deg": (dims, grid(worst_b), {"long_name": "beta (deg) of the worst cell"}),
        "worst_sample": (dims, grid(worst_s.astype(str)), {"long_name": "sample of the worst cell"}),
        "worst_u": (dims, grid(worst_u), {"long_name": "standard uncertainty of k_A at the worst cell (its SE, or its "
                                                      "deterministic error bound / sqrt 3, or a cell's estimate whole "
                                                      "where the backend did not converge)"}),
        "worst_se": (dims, grid(worst_se), {"long_name": "standard error of k_A at the worst cell (NaN for a "
                                                        "deterministic backend)"}),
        "worst_error_bound": (dims, grid(worst_eb), {"long_name": "deterministic error bound of k_A at the worst cell "
                                                                  "(quadrature; beside worst_se under absolute "
                                                                  "calibration: eta's part; where worst_converged is 0 "
                                                                  "without worst_se an estimate, not a bound; NaN "
                                                                  "otherwise)"}),
        "worst_converged": (dims, grid(worst_conv), {"long_name": "the backend reached its target at the worst cell (0: "
                                                                  "stopped at its cap; a deterministic backend's error "
                                                                  "bound is then an estimate; NaN where not computed)"}),
        "max_abs_dev_direct": (dims, grid(max_dev_direct), {
            "long_name": "max |k_A,direct - 1| over the cells and samples: the aperture effect without the stray "
                         "light (= max_abs_dev without stray light)", "units": "1"}),
        "max_stray_fraction": (dims, grid(max_stray), {
            "long_name": "largest stray fraction of the road signal over the cells and samples (a fraction: 0.3 is "
                         "30 %; 0 without stray light)", "units": "1"}),
        "max_stray_tan_eps": (dims, grid(stray_t), {"long_name": "tan eps of the cell of max_stray_fraction (NaN "
                                                                 "without stray light)"}),
        "max_stray_beta_deg": (dims, grid(stray_b), {"long_name": "beta of the cell of max_stray_fraction (NaN "
                                                                  "without stray light)", "units": "deg"}),
        "max_stray_sample": (dims, grid(stray_s.astype(str)), {"long_name": "sample of the cell of max_stray_fraction "
                                                                           "(empty without stray light)"}),
        "max_stray_u": (dims, grid(stray_u), {"long_name": "standard error of max_stray_fraction at its cell",
                                              "units": "1"}),
        "not_converged": (dims, grid((~conv).reshape(n, -1).sum(axis=1).astype(np.int32)), {"long_name": "cells whose backend stopped before its target"}),
        "signal": (dims, grid(signal), {"long_name": "detected flux for a Lambertian sample relative to the base design",
                                        "formula": SIGNAL_FORMULA}),
        "source_solid_angle_sr": (dims, grid(omega), {"long_name": "projected solid angle of the source disc at the sample "
                                                                               "(E_normal / L_0 with its beam profile), at the "
                                                                               "requested cells' source distances, the smallest"}),
        "detector_etendue_m2sr": (dims, grid(etendue), {"long_name": "etendue of the luminance meter (pupil x field)"}),
        "footprint_length_m": (dims, grid(fp_len), {"long_name": "length of the detector footprint along the observation azimuth"}),
        "footprint_x_min_m": (dims, grid(fp_min), {}),
        "footprint_x_max_m": (dims, grid(fp_max), {}),
        "geometry_ok": (dims, grid(geometry_ok), {"long_name": "the instrument can measure every requested cell"}),
        "feasible": (dims, grid(feasible), {"long_name": "geometry_ok and max_abs_dev <= tolerance and signal > 0"}),
        "kind": (dims, grid(kind.astype(str)), {"long_name": "why not feasible: instrument, footprint, horizon, "
                                                              "line_of_sight, housing, backend, tolerance, signal, failed"}),
        "reason": (dims, grid(reason.astype(str)), {"long_name": "why not feasible (empty if feasible)"}),
        # 63-bit seeds as decimal text: netCDF-3 has no 64-bit integers (roadgonio.seeds.point_seed)
        "seed": (dims, grid(np.array([str(int(v)) for v in seeds])), {"long_name": "backend seed of the design point "
                                                                               "(roadgonio ka --seed)"}),
        "seconds": (dims, grid(seconds), {"long_name": "compute time of the point's tables (s)"}),
    }
    ds = xr.Dataset({k: xr.Variable(d, v, a) for k, (d, v, a) in data.items()}, coords=coords)
    best = best_point(signal_abs, max_dev, feasible)
    ds.attrs.update({
        "title": f"roadgonio design study of instrument '{base.name}'",
        "tolerance": float(tol),
        "varied": to_json(dims, indent=None),
        "samples": to_json([s.name for s in samples], indent=None),
        "base_instrument_json": to_json(_cluster.absolute_instrument_dict(base), indent=None),
        "base_instrument_path": str(Path(base.path).resolve()) if base.path is not None else "",
        "base_signal_product": float(sb),
        "signal_formula": SIGNAL_FORMULA,
        "points": int(n), "points_geometry_ok": int(geometry_ok.sum()), "points_feasible": int(feasible.sum()),
        "points_beam_dim": int(dim.sum()),
        "best_index": int(best),
        "best_point_json": to_json(points[best] if best >= 0 else None, indent=None),
        "log_axes": to_json([s.key for s in specs if s.log], indent=None),
    })
    return ds


#: The stray-light fields of a table's cells kept in the journal and design.nc: those the k_A table
#: writes (:data:`roadgonio.engines.runner.STRAY_FILES`; :class:`roadgonio.engines.result.CellResult`).
STRAY_CELL_FIELDS = tuple(STRAY_FILES)


def _f(v) -> float:
    return math.nan if v is None else float(v)


def best_instrument(ds) -> Instrument | None:
    """The best design of a design Dataset as a complete Instrument (None if no point is feasible)."""
    point = json.loads(ds.attrs["best_point_json"])
    if point is None:
        return None
    from roadgonio.design.grid import build_instrument
    return build_instrument(base_instrument(ds), point)


def base_instrument(ds) -> Instrument:
    path = ds.attrs.get("base_instrument_path") or None
    return Instrument.from_dict(json.loads(ds.attrs["base_instrument_json"]), path=path)


def point_index(ds, i: int) -> dict[str, float]:
    """The varied values of flat point ``i`` (C order)."""
    dims = json.loads(ds.attrs["varied"])
    shape = tuple(ds.sizes[d] for d in dims)
    idx = np.unravel_index(i, shape) if dims else ()
    return {d: float(ds[d].values[k]) for d, k in zip(dims, idx)}


#: Signals within this relative spread are one signal (:func:`best_point`, :func:`same_signal`). The
#: signal is a model of the detected flux (:mod:`roadgonio.design.metrics`) that is no more accurate
#: than this: it neglects the illuminance gradient over the footprint, and it calls the etendue
#: independent of the detector distance, while the exact disc-to-disc etendue it evaluates keeps
#: terms of relative order (R_D / F)^2 and tan^2 gamma_D that change with the distance (1.1e-5 between
#: the portable's 2.5 mm pupil at 0.6 m and at 1 m; 7.6e-4 between a 16.5 mm pupil at 0.6 m and far away). Two designs whose
#: signals differ by less are equally bright for any lamp, and a difference that small must not
#: decide the best design over max |k_A - 1| (trial 12 D1: 1e-5 chose a design on the tolerance's
#: edge over an equally bright one 1.7 points inside it).
SAME_SIGNAL_RTOL = 1e-3


def best_point(signal, max_dev, feasible) -> int:
    """Flat index of the best design: of the feasible points, those whose signal is within
    SAME_SIGNAL_RTOL of the largest count as the most signal, and of them the one of least max
    |k_A - 1| wins (then the larger signal, then the first); -1 when none is feasible."""
    sig = np.asarray(signal, dtype=np.float64).reshape(-1)
    dev = np.asarray(max_dev, dtype=np.float64).reshape(-1)
    idx = np.nonzero(np.asarray(feasible, dtype=bool).reshape(-1) & np.isfinite(sig) & np.isfinite(dev))[0]
    if not idx.size:
        return -1
    top = float(np.max(sig[idx]))
    bright = [int(i) for i in idx if sig[i] >= top - SAME_SIGNAL_RTOL * abs(top)]
    return min(bright, key=lambda i: (dev[i], -sig[i], i))


def same_signal(ds) -> float | None:
    """The signal (x base) that every design point with a max |k_A - 1| shares, when there are two or
    more such points and their signals agree within SAME_SIGNAL_RTOL (a design of keys that do not
    change the detected flux: the housing's paint and baffles, the sample size): there is then no
    trade-off of signal against |k_A - 1| to draw. None otherwise."""
    sig = np.asarray(ds["signal"].values, dtype=np.float64).reshape(-1)
    dev = np.asarray(ds["max_abs_dev"].values, dtype=np.float64).reshape(-1)
    s = sig[np.isfinite(sig) & np.isfinite(dev)]
    if s.size < 2 or not np.all(np.abs(s - s[0]) <= SAME_SIGNAL_RTOL * abs(s[0])):
        return None
    return float(s[0])


def indistinct(flat: Mapping[str, np.ndarray], best: int) -> np.ndarray:
    """Per point (flat arrays ``max_abs_dev``, ``worst_se``, ``worst_error_bound``), True where its max
    |k_A - 1| and the best's differ by no more than their precision says: with standard errors,
    2 x the two SEs in quadrature; with deterministic bounds, the two bounds together (both when a
    table has both: Monte Carlo under absolute calibration). The best itself is not counted; points
    without a max |k_A - 1| are not."""
    dev = np.asarray(flat["max_abs_dev"], dtype=np.float64)
    missing = np.full(dev.shape, np.nan)             # a design.nc written before these were kept
    se = np.nan_to_num(np.asarray(flat.get("worst_se", missing), dtype=np.float64))
    eb = np.nan_to_num(np.asarray(flat.get("worst_error_bound", missing), dtype=np.float64))
    reach = INDISTINCT_SE * np.hypot(se, se[best]) + eb + eb[best]
    out = np.isfinite(dev) & (np.abs(dev - dev[best]) <= reach)
    out[best] = False
    return out


def precision_kind(has_se: bool, has_bound: bool) -> str:
    """The kind of a max |k_A - 1|'s precision, the one decision of the words, the error bars and the
    tolerance note: ``"se"`` (Monte Carlo), ``"bound"`` (a deterministic bound, never called a
    standard error: user audit), ``"both"`` (Monte Carlo under absolute calibration: its SE and eta's
    bound) or ``""`` (neither kept: a design.nc written before they were)."""
    return {(True, True): "both", (False, True): "bound", (True, False): "se"}.get((bool(has_se), bool(has_bound)), "")


def _finite(v) -> bool:
    return v is not None and math.isfinite(float(v))


def bound_words(kind: str, converged) -> str:
    """What a deterministic error bound of precision ``kind`` is called: "error estimate" where the
    backend stopped at its cap (``converged`` 0) and the bound stands alone; "error bound" otherwise
    (under absolute calibration a Monte Carlo cell stopped at its cap keeps eta's bound a bound,
    engines.result.standard_uncertainty)."""
    return "error estimate" if kind == "bound" and _finite(converged) and not float(converged) else "error bound"


def precision_words(se, error_bound, u, converged=None) -> str:
    """What the precision of a max |k_A - 1| is (:func:`precision_kind`), in words with its value:
    'SE 1e-04', 'error bound 2e-04', 'SE 1e-04 and eta's error bound 3e-06', or the standard
    uncertainty 'u 1e-04' of a design.nc written before the kinds were kept. Where the worst cell did
    not converge (``converged`` 0) its bound is an estimate and called so (user audit, session 40)."""
    kind = precision_kind(_finite(se), _finite(error_bound))
    what = bound_words(kind, converged)
    if kind == "both":
        return f"SE {float(se):.1g} and eta's error bound {float(error_bound):.1g}"
    if kind == "bound":
        return f"{what} {float(error_bound):.1g}"
    if kind == "se":
        return f"SE {float(se):.1g}"
    return f"u {float(u):.1g}" if _finite(u) else "no SE"


#: Two max |k_A - 1| within this many standard errors (of their difference) are not told apart.
INDISTINCT_SE = 2.0


def summary(ds) -> dict[str, Any]:
    """A short JSON-able summary of a design Dataset."""
    dims = json.loads(ds.attrs["varied"])
    best = int(ds.attrs["best_index"])
    flat = {v: ds[v].values.reshape(-1) for v in ("max_abs_dev", "rms_dev", "signal", "feasible", "kind",
                                                    "worst_tan_eps", "worst_beta_deg", "worst_sample", "worst_u",
                                                    "worst_se", "worst_error_bound", "worst_converged",
                                                    "seed", "footprint_length_m", "max_stray_fraction",
                                                    "max_stray_tan_eps", "max_stray_beta_deg", "max_stray_sample",
                                                    "max_stray_u", "max_abs_dev_direct", "not_converged") if v in ds}
    kinds: dict[str, int] = {}
    for k in flat["kind"]:
        if k:
            kinds[str(k)] = kinds.get(str(k), 0) + 1
    s: dict[str, Any] = {"points": int(ds.attrs["points"]), "feasible": int(ds.attrs["points_feasible"]),
                         "geometry_ok": int(ds.attrs["points_geometry_ok"]), "not_feasible_by_kind": kinds,
                         "tolerance": float(ds.attrs["tolerance"]), "varied": dims,
                         "same_signal_rtol": SAME_SIGNAL_RTOL,
                         "tables_computed": int(ds.attrs.get("tables_computed", 0)),
                         "tables_resumed": int(ds.attrs.get("tables_resumed", 0)),
                         "tables_failed": int(ds.attrs.get("tables_failed", 0)),
                         "wall_s": float(ds.attrs.get("wall_s", math.nan)),
                         "compute_wall_s": float(ds.attrs.get("compute_wall_s", math.nan))}
    s["same_signal"] = same_signal(ds)
    s["points_beam_dim"] = int(ds.attrs.get("points_beam_dim", 0))
    if "not_converged" in flat:
        # points with cells whose backend stopped before its target (their u is what it stopped at;
        # audit 21: only design.nc said so)
        s["points_not_converged"] = int(np.sum(flat["not_converged"] > 0))
    if best >= 0:
        # the feasible points as bright as the best (within SAME_SIGNAL_RTOL): the best is the least
        # max |k_A - 1| of them, which the summary says when there is a choice
        sig, dev = flat["signal"].astype(np.float64), flat["max_abs_dev"].astype(np.float64)
        feas = flat["feasible"].astype(bool) & np.isfinite(sig) & np.isfinite(dev)
        top = float(np.max(sig[feas]))
        bright = feas & (sig >= top - SAME_SIGNAL_RTOL * abs(top))
        s["equally_bright"] = int(np.sum(bright))
        # the equally bright designs the computation cannot tell from the best (user audit: of three
        # lid heights of one black housing, physically one instrument, the seed chose the best)
        s["indistinct_from_best"] = int(np.sum(bright & indistinct(flat, best)))
    if "design_points_per_hour" in ds.attrs:
        s["design_points_per_hour"] = float(ds.attrs["design_points_per_hour"])
    cluster = json.loads(ds.attrs.get("provenance", "{}")).get("cluster") or {}
    s["on_cluster"] = cluster.get("mode") == "dask"
    if best >= 0:
        s["best"] = {"index": best, **point_index(ds, best),
                     **{k: (v[best].item() if hasattr(v[best], "item") else v[best]) for k, v in flat.items()
                        if k not in ("feasible", "kind")}}
        s["best"]["seed"] = int(s["best"]["seed"])
        se, bound = s["best"].get("worst_se"), s["best"].get("worst_error_bound")
        s["best"]["precision"] = precision_words(se, bound, s["best"]["worst_u"], s["best"].get("worst_converged"))
        s["best"]["precision_kind"] = precision_kind(_finite(se), _finite(bound))
        s["best"]["bound_words"] = bound_words(s["best"]["precision_kind"], s["best"].get("worst_converged"))
    else:
        s["best"] = None
    if "out" in ds.attrs:
        s["out"] = ds.attrs["out"]
    return s
