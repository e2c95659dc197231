"""Outputs of a design study (all written atomically, :mod:`roadgonio.fileio`):

* ``design.nc``: the xarray Dataset (netCDF3 via scipy; booleans as int8, provenance as JSON in the
  attributes ``provenance`` and ``base_instrument_json``);
* ``design.csv``: one row per design point: one column per varied key (named exactly as the key),
  then ``max_abs_dev, rms_dev, signal, feasible, reason``, then ``kind, worst_tan_eps,
  worst_beta_deg, worst_sample, worst_u, footprint_length_m, seed``, then the stray light
  (:func:`roadgonio.design.metrics.stray_metrics`) ``max_abs_dev_direct, max_stray_fraction,
  max_stray_tan_eps, max_stray_beta_deg, max_stray_sample, max_stray_u``, then the worst cell's
  precision by kind ``worst_se, worst_error_bound`` (``worst_u`` is their standard uncertainty) and
  ``worst_converged`` (0: the backend stopped at its cap there; a deterministic backend's bound is
  then an estimate);
* ``best.toml``: the feasible design with the most signal (:func:`roadgonio.design.dataset.best_point`), a complete instrument file (opens with
  ``roadgonio ka --instrument best.toml``; the header says how to reproduce its row);
* ``pareto.png``: max |k_A - 1| against the signal, feasible points marked, the Pareto front, the
  best labelled; when every point has the same signal (:func:`roadgonio.design.dataset.same_signal`:
  a housing's paint and baffles), max |k_A - 1| point by point instead, with max |k_A,direct - 1|
  beside it when there is stray light, and the title says why;
* ``tolerance_map.png`` (two or more varied keys of more than one value): max |k_A - 1| over the plane of the first two
  varied keys, one panel per value of a third of at most MAX_MAP_PANELS values (others at the best
  design's values), with the tolerance contour (or, when there is none, the legend says on which
  side of the tolerance every point is) and iso-signal lines (interpolated as power laws of the
  keys between the grid values: :func:`_signal_field`); cells as :func:`_edges` draws them.
"""
from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from roadgonio.errors import InputError
from roadgonio.fileio import atomic_savefig, atomic_write_text, read_netcdf, write_netcdf
from roadgonio.instrument.config import toml_text

CSV_TAIL = ("max_abs_dev", "rms_dev", "signal", "feasible", "reason")
CSV_EXTRA = ("kind", "worst_tan_eps", "worst_beta_deg", "worst_sample", "worst_u", "footprint_length_m", "seed",
             "max_abs_dev_direct", "max_stray_fraction", "max_stray_tan_eps", "max_stray_beta_deg", "max_stray_sample",
             "max_stray_u", "worst_se", "worst_error_bound", "worst_converged")


#: Every file ``roadgonio design`` writes: a run removes those it does not write this time
#: (``--no-plots``, no feasible design, no tolerance map), so an earlier run's picture never stays
#: beside the new results (audit 22: pareto.png of a 5 % run beside a 3 % run's best.toml).
DESIGN_FILES = ("design.nc", "design.csv", "best.toml", "pareto.png", "tolerance_map.png")


def write_outputs(ds, out_dir: str | Path, *, plots: bool = True) -> list[Path]:
    """design.nc, design.csv, best.toml and the pictures, together or not at all
    (:class:`roadgonio.fileio.OutputGroup`; the journal stays outside, so a failed write resumes)."""
    from roadgonio.fileio import OutputGroup
    out_dir = Path(out_dir)
    with OutputGroup(out_dir, replaces=DESIGN_FILES) as g:
        files = [write_netcdf(ds, g.path("design.nc")), write_csv(ds, g.path("design.csv"))]
        best = write_best(ds, g.path("best.toml"))
        if best is None:
            g.names.remove("best.toml")
        else:
            files.append(best)
        if plots:
            files.append(plot_pareto(ds, g.path("pareto.png")))
            tm = plot_tolerance_map(ds, g.path("tolerance_map.png"))
            if tm is None:
                g.names.remove("tolerance_map.png")
            else:
                files.append(tm)
    return [out_dir / Path(f).name for f in files]


# ----------------------------------------------------------------------------------------------
def read_design(path: str | Path):
    """Open a ``design.nc`` (booleans come back as booleans)."""
    return read_netcdf(path, booleans=("feasible", "geometry_ok"))


def _fmt(v) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (float, np.floating)):
        return "" if not math.isfinite(float(v)) else repr(float(v))
    if isinstance(v, (np.integer,)):
        return str(int(v))
    return str(v)


def write_csv(ds, path: Path) -> Path:
    dims = json.loads(ds.attrs["varied"])
    from roadgonio.design.dataset import point_index
    n = int(ds.attrs["points"])
    # a design.nc written before a column was kept: the column empty (NaN)
    flat = {c: ds[c].values.reshape(-1) if c in ds else np.full(n, np.nan) for c in CSV_TAIL + CSV_EXTRA}
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(list(dims) + list(CSV_TAIL) + list(CSV_EXTRA))
    for i in range(n):
        p = point_index(ds, i)
        w.writerow([_fmt(p[d]) for d in dims] + [_fmt(flat[c][i]) for c in CSV_TAIL + CSV_EXTRA])
    return atomic_write_text(path, buf.getvalue())


# ----------------------------------------------------------------------------------------------
# best.toml: written by the instrument room's TOML writer (roadgonio.instrument.config.toml_text)

def write_best(ds, path: Path) -> Path | None:
    from roadgonio.engines.cluster import absolute_instrument_dict
    from roadgonio.design.dataset import SAME_SIGNAL_RTOL, best_instrument, point_index, summary
    inst = best_instrument(ds)
    if inst is None:
        return None
    s = summary(ds)["best"]
    point = point_index(ds, s["index"])
    d = absolute_instrument_dict(inst)
    changes = ", ".join(f"{k} = {v:g}" for k, v in point.items())
    d["instrument"] = {"name": f"{inst.name}-best",
                       "description": f"best design of a roadgonio design study of '{inst.name}': {changes}"}
    prov = json.loads(ds.attrs.get("provenance", "{}"))
    acc = prov.get("accuracy")
    # what the row was computed with (audit 22: --rel-se and --cells were left out, and the printed
    # line gave another k_A, 2.4 of its own SEs away): the preset, or the tolerance given instead
    from roadgonio.engines.registry import backend_info
    info = backend_info(prov["backend"]) if prov.get("backend") else None
    tol_key = info.tolerance if info is not None else None
    seeded = info is None or info.seeded          # a deterministic backend refuses --seed
    tol = (prov.get("requested_settings") or {}).get(tol_key) if tol_key else None
    how = f" --accuracy {acc}" if acc else (f" --rel-se {tol:g}" if tol is not None else "")
    cells = prov.get("cells")
    how += f" --cells {cells}" if isinstance(cells, str) and cells != "all" else ""
    one = ""
    if isinstance(cells, str) and cells not in ("all", "table"):
        from roadgonio.engines.cells import on_the_grid, select_cells
        try:
            listed = select_cells(cells)
        except InputError:
            listed = []
        if any(not on_the_grid(*c) for c in listed):
            # `ka --cells` takes grid cells only (its tables are on the CIE grid); design takes any
            # (audit 27: the line it printed was refused): the worst cell alone, --tan-eps / --beta
            how = how.replace(f" --cells {cells}", f" --tan-eps {s['worst_tan_eps']:g} --beta {s['worst_beta_deg']:g}")
            one = (f" (its worst cell alone, by --tan-eps/--beta: the design's cells {cells} are not all on the "
                   "CIE grid, which ka --cells needs)")
    samples = json.loads(ds.attrs["samples"])
    header = (f"The feasible design with the most signal, of signals equal within {SAME_SIGNAL_RTOL:g} the least max |k_A - 1| (roadgonio design; {ds.attrs.get('created', '')}).\n"
              f"Varied: {changes}\n"
              f"max |k_A - 1| = {s['max_abs_dev']:.5g} (tolerance {ds.attrs['tolerance']:g}) at tan eps "
              f"{s['worst_tan_eps']:g}, beta {s['worst_beta_deg']:g} ({s['worst_sample']}); rms {s['rms_dev']:.4g}; "
              f"signal {s['signal']:.4g} x base\n"
              f"Reproduce its row: roadgonio ka --instrument best.toml --sample {(prov.get('samples') or {}).get(s['worst_sample'], {}).get('spec') or s['worst_sample']} --backend {prov.get('backend')}"
              + how
              + (f" --model-variant {prov['model_variant']}" if prov.get("model_variant") else "") + (f" --seed {s['seed']}" if seeded else "") + f" (the sample of its worst cell; the study's samples: {', '.join(samples)})" + one)
    return atomic_write_text(path, toml_text(d, header))


# ----------------------------------------------------------------------------------------------
def _plt():
    from roadgonio.plots import _plt as p
    return p()


def _error_bars(ds) -> tuple[np.ndarray, str]:
    """The half-lengths (%) of the error bars of max |k_A - 1| and what they are, by the kind of
    precision the backend gave (user audit: a quadrature study's bars, its bound / sqrt 3 x 2, were
    called '2 SE'): 2 SE, the deterministic error bound, or 2 u where a table has both (a Monte
    Carlo table under absolute calibration: its SE and eta's bound / sqrt 3 in quadrature)."""
    se = ds["worst_se"].values.reshape(-1) if "worst_se" in ds else None
    eb = ds["worst_error_bound"].values.reshape(-1) if "worst_error_bound" in ds else None
    u = ds["worst_u"].values.reshape(-1)
    if se is None or eb is None:                       # a design.nc written before these were kept
        return 2 * np.nan_to_num(u) * 100, "error bars 2 u (standard uncertainty)"
    from roadgonio.design.dataset import precision_kind
    kind = precision_kind(np.isfinite(se).any(), np.isfinite(eb).any())
    if kind == "both":
        return 2 * np.nan_to_num(u) * 100, "error bars 2 u (the SE and the error bound / sqrt 3)"
    if kind == "bound":
        conv = ds["worst_converged"].values.reshape(-1) if "worst_converged" in ds else np.ones_like(eb)
        stopped = int(np.sum(np.isfinite(eb) & (conv == 0)))
        return np.nan_to_num(eb) * 100, ("error bars: the deterministic error bound" if not stopped else
                                         f"error bars: the error bound (an estimate at {stopped} point(s) whose worst "
                                         "cell stopped at the cap)")
    return 2 * np.nan_to_num(se) * 100, "error bars 2 SE"


def plot_pareto(ds, path: Path) -> Path:
    from roadgonio.design.dataset import same_signal
    same = same_signal(ds)
    if same is not None:
        return plot_points(ds, path, same)
    plt = _plt()
    dev = ds["max_abs_dev"].values.reshape(-1) * 100
    sig = ds["signal"].values.reshape(-1)
    feas = ds["feasible"].values.reshape(-1).astype(bool)
    geo = ds["geometry_ok"].values.reshape(-1).astype(bool)
    bars, bars_text = _error_bars(ds)
    tol = float(ds.attrs["tolerance"]) * 100
    best = int(ds.attrs["best_index"])
    from roadgonio.design.metrics import pareto_front
    from roadgonio.design.dataset import point_index
    fig, ax = plt.subplots(figsize=(8, 5.5))
    ok = np.isfinite(dev) & np.isfinite(sig)
    kinds = ds["kind"].values.reshape(-1).astype(str)
    bad = ok & ~feas & (kinds != "signal")
    dark = ok & ~feas & (kinds == "signal")
    ax.errorbar(sig[bad], dev[bad], yerr=bars[bad], fmt="o", mfc="none", color="tab:red",
                ms=6, lw=0.8, label=f"over tolerance ({int(bad.sum())})")
    if dark.any():          # within tolerance or not, it detects no light (user audit, session 40: drawn as over it)
        ax.errorbar(sig[dark], dev[dark], yerr=bars[dark], fmt="s", mfc="none", color="0.45",
                    ms=6, lw=0.8, label=f"no signal: not an instrument ({int(dark.sum())})")
    ax.errorbar(sig[feas & ok], dev[feas & ok], yerr=bars[feas & ok], fmt="o", color="tab:green",
                ms=6, lw=0.8, label=f"feasible ({int((feas & ok).sum())})")
    front = pareto_front(np.where(dark, np.nan, sig), dev)       # a design that detects no light is on no front
    if front.size > 1:
        ax.step(sig[front], dev[front], where="pre", color="0.4", lw=1, ls="--",
                label="Pareto front (least deviation for at least that signal)")
    ax.axhline(tol, color="tab:orange", lw=1.2, label=f"tolerance {tol:g} %")
    finite = sig[ok]
    if finite.size and finite.min() > 0 and finite.max() / finite.min() > 20:
        ax.set_xscale("log")
    if dev[ok].size and np.nanmin(dev[ok]) > 0 and np.nanmax(dev[ok]) / np.nanmin(dev[ok]) > 10:
        from matplotlib import ticker
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(ticker.FormatStrFormatter("%g"))
    if best >= 0:
        p = point_index(ds, best)
        txt = "best: " + ", ".join(f"{k.split('.', 1)[1]}={v:g}" for k, v in p.items())
        ax.plot([sig[best]], [dev[best]], marker="*", color="gold", mec="k", ms=16, ls="none", zorder=5)
        # the label towards the free side of the axes (trial 12 D6: the best design at the left edge put it
        # over the y label and squeezed the axes into the right half)
        ax.autoscale_view()
        fx, fy = ax.transAxes.inverted().transform(ax.transData.transform((sig[best], dev[best])))
        right, below = fx < 0.5, fy > 0.6
        ax.annotate(txt + f"\nsignal {sig[best]:.3g} x base, max |k_A-1| {dev[best]:.3g} %", (sig[best], dev[best]),
                    xytext=(10 if right else -10, -30 if below else 22), textcoords="offset points",
                    ha="left" if right else "right", va="top" if below else "bottom", fontsize=8,
                    arrowprops={"arrowstyle": "-", "color": "0.3"})
    ax.set_xlabel("signal (detected flux for a Lambertian sample, relative to the base design)")
    ax.set_ylabel("max |k_A - 1| over cells and samples (%)")
    n_geo = int((~geo).sum())
    samples = ", ".join(json.loads(ds.attrs["samples"]))
    ax.set_title(f"{ds.attrs['title']}\nsamples {samples}; {int(ds.attrs['points'])} points, "
                 f"{n_geo} geometrically impossible (not shown); {bars_text}", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    out = atomic_savefig(fig, path, dpi=120)
    plt.close(fig)
    return out


#: More design points than this: pareto.png by point labels every k-th point only.
MAX_POINT_LABELS = 40


def plot_points(ds, path: Path, signal: float) -> Path:
    """pareto.png of a design whose points all have the same signal: max |k_A - 1| (bars: :func:`_error_bars`)
    point by point, feasible or not, the tolerance, max |k_A,direct - 1| (the aperture effect
    without the stray light) beside it when some point has stray light, the best starred; the
    title says that there is no trade-off of signal to draw."""
    plt = _plt()
    from roadgonio.design.dataset import point_index
    dev = ds["max_abs_dev"].values.reshape(-1) * 100
    feas = ds["feasible"].values.reshape(-1).astype(bool)
    bars, bars_text = _error_bars(ds)
    tol = float(ds.attrs["tolerance"]) * 100
    best = int(ds.attrs["best_index"])
    idx = np.nonzero(np.isfinite(dev))[0]
    x = np.arange(idx.size)
    fig, ax = plt.subplots(figsize=(max(8.0, min(16.0, 3.0 + 0.35 * idx.size)), 6.0))
    kinds = ds["kind"].values.reshape(-1).astype(str)[idx]
    for sel, style, label in ((~feas[idx] & (kinds != "signal"), dict(fmt="o", mfc="none", color="tab:red"),
                               "over tolerance"),
                              (kinds == "signal", dict(fmt="s", mfc="none", color="0.45"), "no signal: not an instrument"),
                              (feas[idx], dict(fmt="o", color="tab:green"), "feasible")):
        if not sel.any() and label.startswith("no signal"):
            continue
        ax.errorbar(x[sel], dev[idx][sel], yerr=bars[idx][sel], ms=6, lw=0.8,
                    label=f"max |k_A - 1|, {label} ({int(sel.sum())})", **style)
    if "max_stray_fraction" in ds and np.nanmax(np.append(ds["max_stray_fraction"].values.reshape(-1)[idx], 0.0)) > 0:
        direct = ds["max_abs_dev_direct"].values.reshape(-1)[idx] * 100
        ax.plot(x, direct, "x", color="0.35", ms=7, label="max |k_A,direct - 1| (without the stray light)")
    ax.axhline(tol, color="tab:orange", lw=1.2, label=f"tolerance {tol:g} %")
    if best >= 0 and best in set(idx.tolist()):
        k = int(np.nonzero(idx == best)[0][0])
        ax.plot([k], [dev[best]], marker="*", color="gold", mec="k", ms=16, ls="none", zorder=5, label="best design")
    step = max(1, math.ceil(idx.size / MAX_POINT_LABELS))
    labels = [", ".join(f"{v:g}" for v in point_index(ds, int(i)).values()) for i in idx]
    ax.set_xticks(x[::step], labels[::step], rotation=60, ha="right", fontsize=7)
    dims = json.loads(ds.attrs["varied"])
    ax.set_xlabel("design point: " + ", ".join(dims), fontsize=9)
    ax.set_ylabel("max |k_A - 1| over cells and samples (%)")
    n_geo = int((~ds["geometry_ok"].values.reshape(-1).astype(bool)).sum())
    samples = ", ".join(json.loads(ds.attrs["samples"]))
    import textwrap
    width = int(fig.get_size_inches()[0] * 13)          # characters of a 9 pt line across the figure
    ax.set_title("\n".join(textwrap.wrap(
        f"{ds.attrs['title']}: every point has the same signal ({signal:.4g} x base), so there is no trade-off of "
        f"signal against |k_A - 1| to draw: max |k_A - 1| point by point. Samples {samples}; "
        f"{int(ds.attrs['points'])} points, {n_geo} geometrically impossible (not shown); {bars_text}", width)),
        fontsize=9)
    ax.set_xlim(-0.5, idx.size - 0.5)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    out = atomic_savefig(fig, path, dpi=120)
    plt.close(fig)
    return out


def _edges(v: np.ndarray, log: bool) -> np.ndarray:
    """The cell edges of a map axis: midpoints between the grid values (geometric on a log axis) and
    the outer edges half a step beyond the first and last value. On a linear axis of a key whose
    values are all >= 0 (a radius, a field angle) an outer edge goes no further than half way to 0
    from its value, so a coarse grid's first cell does not reach radius 0 (user audit: 0.004, 0.012,
    ... drew the first cell from 0, as if a zero aperture had been computed), and a grid whose value
    is 0 starts its cell at 0, never below. The map keeps the axis the grid was given on (a log axis
    for a ``LO:HI:N:log`` key): the cells then read as the computed points."""
    v = np.asarray(v, dtype=np.float64)
    if v.size == 1:
        return np.array([v[0] * 0.9, v[0] * 1.1]) if log else np.array([v[0] - 0.5, v[0] + 0.5])
    x = np.log(v) if log else v
    mid = (x[1:] + x[:-1]) / 2
    out_lo, out_hi = x[0] - mid[0], x[-1] - mid[-1]            # half a step outwards (signed)
    if not log and (v >= 0).all():                             # at most half way to 0
        out_lo = math.copysign(min(abs(out_lo), x[0] / 2), out_lo)
        out_hi = math.copysign(min(abs(out_hi), x[-1] / 2), out_hi)
    e = np.concatenate([[x[0] + out_lo], mid, [x[-1] + out_hi]])
    return np.exp(e) if log else e


#: The iso-signal lines are drawn on the design grid cut into at most this many steps per cell and
#: axis (:func:`_signal_field`; fewer when the axis has many values, so it stays under
#: SIGNAL_FIELD_MAX points).
SIGNAL_SUBDIVISIONS = 16
SIGNAL_FIELD_MAX = 481


def _fine_axis(v) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fine positions along one map axis (:func:`_signal_field`), with the grid cell of each and
    its fraction t across that cell: in log(value) when both of the cell's values are > 0, in the
    value otherwise (a cell that starts at 0)."""
    v = np.asarray(v, dtype=np.float64)
    n = SIGNAL_SUBDIVISIONS if v.size < 2 else max(2, min(SIGNAL_SUBDIVISIONS, (SIGNAL_FIELD_MAX - 1) // (v.size - 1)))
    t = np.arange(n) / n
    pos, cell, frac = [], [], []
    for i in range(v.size - 1):
        a, b = v[i], v[i + 1]
        pos.append(a * (b / a) ** t if a > 0 and b > 0 else a + (b - a) * t)
        cell.append(np.full(n, i))
        frac.append(t)
    pos.append(v[-1:])
    cell.append(np.array([max(v.size - 2, 0)]))
    frac.append(np.array([1.0 if v.size > 1 else 0.0]))
    return np.concatenate(pos), np.concatenate(cell), np.concatenate(frac)


def _signal_field(x, y, sig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The signal between the design's grid values, on a grid up to SIGNAL_SUBDIVISIONS times finer
    (``X, Y, S``, S NaN where a corner of its cell has no signal > 0), to contour the iso-signal lines.

    The signal grows as a power of each key (the square of a source or pupil radius, about the square
    of a small field angle, the inverse square of a distance: :data:`roadgonio.design.metrics.SIGNAL_FORMULA`),
    so within each cell log(signal) is interpolated bilinearly over log(key value) (over the value
    for a cell that starts at 0). A product of power laws comes out exact; the contour of the grid
    values themselves put each line at the linear interpolation of r^2, too close to the smaller
    radius on a coarse grid (user audit: x0.2 / x0.1 / x0.05 at 0.0100 / 0.0069 / 0.0053 m where
    the square law puts them at 0.0112 / 0.0079 / 0.0056 m)."""
    xf, ix, tx = _fine_axis(x)
    yf, iy, ty = _fine_axis(y)
    sig = np.asarray(sig, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ls = np.where(np.isfinite(sig) & (sig > 0), np.log(np.where(sig > 0, sig, 1.0)), np.nan)
    acc = np.zeros((yf.size, xf.size))
    bad = np.zeros((yf.size, xf.size), dtype=bool)
    for dy, wy in ((0, 1 - ty), (1, ty)):
        for dx, wx in ((0, 1 - tx), (1, tx)):
            w = wy[:, None] * wx[None, :]
            jy = np.minimum(iy + dy, sig.shape[0] - 1)[:, None]
            jx = np.minimum(ix + dx, sig.shape[1] - 1)[None, :]
            c = ls[jy, jx]
            used = w > 0                                   # a corner of weight 0 does not mask the point
            bad |= used & np.isnan(c)
            acc += np.where(used & ~np.isnan(c), w * np.nan_to_num(c), 0.0)
    X, Y = np.meshgrid(xf, yf)
    return X, Y, np.where(bad, np.nan, np.exp(acc))


#: An iso-signal line shorter than this fraction of the map's diagonal is left out (a level that
#: only clips a corner of the grid drew an unlabelled fragment).
MIN_CONTOUR_FRACTION = 0.1


def _visible_levels(X, Y, Z, levels, xlog: bool, ylog: bool) -> np.ndarray:
    """The levels whose iso-lines over the grid are at least MIN_CONTOUR_FRACTION of the map's
    diagonal long (lengths in axis units: log axes in decades of their span)."""
    gx = np.log10(np.asarray(X, dtype=float)) if xlog else np.asarray(X, dtype=float)
    gy = np.log10(np.asarray(Y, dtype=float)) if ylog else np.asarray(Y, dtype=float)
    sx, sy = float(np.ptp(gx)) or 1.0, float(np.ptp(gy)) or 1.0
    keep = []
    for lv in levels:
        length = sum(float(np.sum(np.hypot(*np.diff(seg, axis=0).T)))
                     for seg in _contour_segments(gx / sx, gy / sy, Z, float(lv)))
        if length >= MIN_CONTOUR_FRACTION * math.sqrt(2.0):
            keep.append(lv)
    return np.asarray(keep, dtype=float)


def _contour_segments(gx, gy, z, level: float) -> list[np.ndarray]:
    """The iso-line of ``z`` at ``level`` over the coordinates ``gx``, ``gy`` (the axes as drawn: log
    of the value along a log axis), as (n, 2) segments of at least two points; NaN in ``z`` is not
    computed. None drawn where contourpy cannot (fewer than 2 x 2 values)."""
    import contourpy
    try:
        gen = contourpy.contour_generator(gx, gy, np.ma.masked_invalid(np.asarray(z, dtype=float)))
        lines = gen.lines(float(level))
    except (ValueError, TypeError):
        return []
    return [seg for seg in (np.asarray(s, dtype=float) for s in lines) if len(seg) > 1]


def _signal_levels(lo: float, hi: float, n_max: int = 7) -> np.ndarray:
    """Round iso-signal levels strictly inside (lo, hi): 1-2-5 per decade, thinned to <= n_max."""
    out = []
    for e in range(int(np.floor(np.log10(lo))), int(np.ceil(np.log10(hi))) + 1):
        out += [m * 10.0 ** e for m in (1, 2, 5) if lo < m * 10.0 ** e < hi]
    lv = np.array(out)
    while lv.size > n_max:
        lv = lv[::2]
    return lv


#: A third varied key with at most this many values gets one tolerance-map panel per value; with more,
#: the map is the best design's slice (the title says which).
MAX_MAP_PANELS = 4


def plot_tolerance_map(ds, path: Path) -> Path | None:
    """max |k_A - 1| over the plane of the first two varied keys (None if fewer than two vary); a third
    varied key of at most MAX_MAP_PANELS values gets one panel per value (trial 12 D1: only the best's
    slice was drawn, and a better point on another slice was in no picture); further keys, or a third
    of more values, at the best design's values."""
    dims = json.loads(ds.attrs["varied"])
    dims2 = [d for d in dims if ds.sizes[d] > 1]
    if len(dims2) < 2:
        return None
    xk, yk = dims2[0], dims2[1]
    best = int(ds.attrs["best_index"])
    from roadgonio.design.dataset import point_index
    anchor = point_index(ds, best) if best >= 0 else {}
    others = [d for d in dims if d not in (xk, yk)]
    panel_key = next((d for d in others if 1 < ds.sizes[d] <= MAX_MAP_PANELS), None)
    sels: list[dict[str, int]] = []
    for v in (range(ds.sizes[panel_key]) if panel_key else [None]):
        sel: dict[str, int] = {}
        for d in others:
            if d == panel_key:
                sel[d] = int(v)
            else:
                vals = ds[d].values
                sel[d] = int(np.argmin(np.abs(vals - anchor[d]))) if d in anchor else 0
        sels.append(sel)
    plt = _plt()
    n = len(sels)
    fig, axes = plt.subplots(1, n, figsize=(8.5 if n == 1 else 6.2 * n, 6.2), squeeze=False)
    fin_all = ds["max_abs_dev"].values[np.isfinite(ds["max_abs_dev"].values)] * 100
    for ax, sel in zip(axes[0], sels):
        is_best = best >= 0 and all(float(ds[d].values[k]) == anchor.get(d) for d, k in sel.items())
        _tolerance_panel(fig, ax, ds, sel, xk, yk, anchor if is_best else {}, fin_all, title=n == 1)
    if n > 1:
        samples = ", ".join(json.loads(ds.attrs["samples"]))
        fixed = ", ".join(f"{d} = {anchor[d]:g}" for d in others if d != panel_key and d in anchor)
        fig.suptitle(f"{ds.attrs['title']}: max |k_A - 1| over cells and samples ({samples}), one panel per "
                     f"{panel_key}" + (f", at {fixed}" if fixed else "")
                     + "\ngrey letters: geometrically impossible (F footprint, H horizon, L line of sight, I instrument, "
                       "W housing, B backend); dots: feasible; star: the best design", fontsize=9)
    fig.tight_layout()
    out = atomic_savefig(fig, path, dpi=120)
    plt.close(fig)
    return out


def _level_lines(x, y, z, level: float, xlog: bool, ylog: bool) -> list[tuple[np.ndarray, np.ndarray]]:
    """The iso-line of ``z`` (rows y, columns x; NaN where not computed) at ``level``, as the map draws
    its axes: interpolated linearly in log(value) along a log axis, where the grid's values are evenly
    spaced (user audit: interpolated in the value, the tolerance line on a log radius axis was drawn
    ~25 px from where the points put it). Lines of one point are left out."""
    gx = np.log(np.asarray(x, dtype=float)) if xlog else np.asarray(x, dtype=float)
    gy = np.log(np.asarray(y, dtype=float)) if ylog else np.asarray(y, dtype=float)
    gx, gy = np.meshgrid(gx, gy)
    return [(np.exp(seg[:, 0]) if xlog else seg[:, 0], np.exp(seg[:, 1]) if ylog else seg[:, 1])
            for seg in _contour_segments(gx, gy, z, level)]


#: At most this many labelled ticks on a log-varied key's axis.
MAX_VALUE_TICKS = 7


def _value_ticks(axis, values) -> None:
    """A log axis labelled at the design's own values ('0.00431', 3 digits), at most :data:`MAX_VALUE_TICKS`
    of them, without minor labels: matplotlib's minor labels (2x10^-3, 3x10^-3, ...) ran into each
    other on a decade-wide axis (audit 22)."""
    from matplotlib import ticker
    v = np.asarray(values, dtype=float)
    if v.size > MAX_VALUE_TICKS:
        v = v[np.unique(np.round(np.linspace(0, v.size - 1, MAX_VALUE_TICKS)).astype(int))]
    axis.set_major_locator(ticker.FixedLocator(v))
    axis.set_major_formatter(ticker.FixedFormatter([f"{x:.3g}" for x in v]))
    axis.set_minor_locator(ticker.NullLocator())


def _tolerance_panel(fig, ax, ds, sel, xk, yk, anchor, fin_all, *, title: bool) -> None:
    """One tolerance-map panel: the plane (xk, yk) at the indices ``sel`` of the other keys; the star at
    ``anchor`` when the best design is on it; one colour scale over all panels (``fin_all``)."""
    sub = ds.isel(sel) if sel else ds
    dev = sub["max_abs_dev"].transpose(yk, xk).values * 100
    sig = sub["signal"].transpose(yk, xk).values
    geo = sub["geometry_ok"].transpose(yk, xk).values.astype(bool)
    kind = sub["kind"].transpose(yk, xk).values
    x, y = ds[xk].values, ds[yk].values
    logs = json.loads(ds.attrs.get("log_axes", "[]"))
    tol = float(ds.attrs["tolerance"]) * 100
    plt = _plt()
    from matplotlib import colors
    fin = fin_all
    vmax = max(float(fin.max()) if fin.size else 2 * tol, tol * 1.05)
    vmin = min(float(fin.min()) if fin.size else tol / 10, tol * 0.95)
    norm = colors.LogNorm(vmin=max(vmin, 1e-4), vmax=vmax) if vmin > 0 and vmax / max(vmin, 1e-12) > 10 else \
        colors.Normalize(vmin=0, vmax=vmax)
    cmap = plt.get_cmap("viridis").with_extremes(bad="0.85")
    im = ax.pcolormesh(_edges(x, xk in logs), _edges(y, yk in logs), np.ma.masked_invalid(dev), cmap=cmap,
                       norm=norm, shading="flat")
    cb = fig.colorbar(im, ax=ax, pad=0.02)
    cb.set_label("max |k_A - 1| (%)")
    from roadgonio.plots import plain_colorbar_labels
    plain_colorbar_labels(cb)
    X, Y = np.meshgrid(x, y)
    handles = []
    if np.isfinite(dev).sum() >= 4 and len(x) > 1 and len(y) > 1:
        from matplotlib.lines import Line2D
        drawn = False
        for lx, ly in _level_lines(x, y, dev, tol, xk in logs, yk in logs):
            ax.plot(lx, ly, color="tab:orange", lw=2.2)
            drawn = True
        if drawn:
            # named in the legend, not inline: an inline label cuts the line where it is drawn, which
            # could be beside the best design (user audit, session 24: the star looked outside)
            handles.append(Line2D([], [], color="tab:orange", lw=2.2, label=f"tolerance {tol:g} %"))
        else:
            # no line: the legend says why, and names no line that is not drawn (user audit)
            fd = dev[np.isfinite(dev)]
            if (fd <= tol).all():
                handles.append(Line2D([], [], ls="none", label=f"every point within the tolerance {tol:g} %"))
            elif (fd > tol).all():
                handles.append(Line2D([], [], ls="none", label=f"no point within the tolerance {tol:g} %"))
        fs = sig[np.isfinite(sig) & (sig > 0)]
        if fs.size >= 4 and fs.max() / fs.min() > 1.5:
            lv = _signal_levels(float(fs.min()), float(fs.max()))
            SX, SY, SS = _signal_field(x, y, sig)
            lv = _visible_levels(SX, SY, SS, lv, xk in logs, yk in logs)
            if lv.size:
                cs2 = ax.contour(SX, SY, np.ma.masked_invalid(SS), levels=lv, colors="white", linewidths=0.9,
                                 linestyles="--")
                ax.clabel(cs2, fmt=lambda v: f"signal x{v:g}", fontsize=7)
    for (iy, ix) in zip(*np.nonzero(~geo)):
        ax.text(x[ix], y[iy], {"footprint": "F", "horizon": "H", "line_of_sight": "L", "instrument": "I",
                               "housing": "W", "backend": "B"}.get(str(kind[iy, ix]), "x"), ha="center", va="center", fontsize=8,
                color="0.35")
    feas = sub["feasible"].transpose(yk, xk).values.astype(bool)
    ax.plot(X[feas], Y[feas], ".", color="white", ms=3, ls="none")
    if anchor:
        handles += ax.plot([anchor[xk]], [anchor[yk]], marker="*", color="gold", mec="k", ms=18, ls="none",
                           label="best design")
    if handles:
        ax.legend(handles=handles, loc="upper right", fontsize=8)
    if xk in logs:
        ax.set_xscale("log")
        _value_ticks(ax.xaxis, x)
    else:
        # a panel of several is narrow: matplotlib's default of ~8 labels like 0.0025 ran together
        # into one string there (user audit, session 29)
        from matplotlib import ticker
        ax.xaxis.set_major_locator(ticker.MaxNLocator(nbins=6 if title else 4, min_n_ticks=2))
    if not title:
        ax.tick_params(axis="x", labelrotation=30)
    if yk in logs:
        ax.set_yscale("log")
        _value_ticks(ax.yaxis, y)
    ax.set_xlabel(xk)
    ax.set_ylabel(yk)
    fixed = ", ".join(f"{d} = {float(ds[d].values[k]):g}" for d, k in sel.items())
    samples = ", ".join(json.loads(ds.attrs["samples"]))
    if title:
        ax.set_title(f"{ds.attrs['title']}: max |k_A - 1| over cells and samples ({samples})"
                     + (f"\nat {fixed}" if fixed else "")
                     + "\ngrey letters: geometrically impossible (F footprint, H horizon, L line of sight, I instrument, "
                       "W housing, B backend); dots: feasible", fontsize=8.5)
    else:
        ax.set_title(f"at {fixed}", fontsize=9)
