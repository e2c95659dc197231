"""Outputs of ``roadgonio road``: JSON, CSV and pictures (metrics side by side, luminance maps),
rendered in memory and written together."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from roadgonio.fileio import to_json
from roadgonio.provenance import provenance
from roadgonio.road.metrics import M_CLASSES

METRICS = (("L_av", "L_av (cd/m²)", "min"), ("U_o", "U_o", "min"), ("U_l", "U_l", "min"), ("TI", "TI (%)", "max"))

#: The Monte Carlo's correlation cases in the order the outputs give them, with the marker and the
#: offset from the bar of each in road_metrics.png, and the words of its legend.
MODES = ("given", "independent", "correlated")
MODE_MARKS = {"given": ("^", 0.0, "△ the cells' correlation given"), "independent": ("o", -0.14, "o independent cells"),
              "correlated": ("s", 0.14, "□ fully correlated")}

#: Every file ``roadgonio road`` writes (the pictures not with ``--no-plots``).
ROAD_FILES = ("road.json", "road_metrics.csv", "road_luminance.csv", "road_metrics.png", "road_luminance.png")


def write_together(out_dir: Path, files: dict[str, bytes | str], *, replaces=()) -> list[Path]:
    """Write every file or none (:class:`roadgonio.fileio.OutputGroup`); an OSError is the one-line
    error naming the file. ``replaces``: the command's own output names; those not in ``files`` are
    removed once the new ones are in place (an earlier run's picture never stays beside them)."""
    from roadgonio.fileio import OutputGroup
    out_dir = Path(out_dir)
    with OutputGroup(out_dir, replaces=replaces) as g:
        for name, content in files.items():
            g.path(name).write_bytes(content.encode("utf-8") if isinstance(content, str) else content)
    return [out_dir / n for n in files]


def metrics_csv(summaries: list[dict]) -> str:
    cols = ["table", "L_av", "U_o", "U_l", "TI", "R_EI", "class", "table_Q0", "table_S1"]
    extra = ["u_L_av", "cov95_L_av", "u_U_o", "cov95_U_o", "u_U_l", "cov95_U_l", "u_TI", "cov95_TI", "P_meets",
             "trials_without_value", "mean_L_av", "mean_U_o", "mean_U_l", "mean_TI"]
    lines = [",".join(cols + ["correlation"] + extra)]
    for s in summaries:
        base = [s["table"]] + [_f(s[c]) for c in cols[1:]]
        unc = s.get("uncertainty")
        if not unc:
            lines.append(",".join(base + [""] * (1 + len(extra))))
            continue
        for mode in MODES:
            if mode not in unc:
                continue
            m = unc[mode]
            row = []
            for k in ("L_av", "U_o", "U_l", "TI"):
                row += ["", ""] if not m[k] else [_f(m[k]["u"]), f"{_f(m[k]['coverage_interval_95'][0], '.5g')}..{_f(m[k]['coverage_interval_95'][1], '.5g')}"]
            row += [_f(m["P_meets_target"]),
                    str(max((m.get("undefined_trials") or {}).values(), default=0))]
            row += [_f(m[k]["mean"]) if m[k] else "" for k in ("L_av", "U_o", "U_l", "TI")]
            lines.append(",".join(base + [mode] + row))
    return "\n".join(lines) + "\n"


def luminance_csv(results) -> str:
    lines = ["table,observer_lane,x_m,y_m,lane,centre_line,L_cd_m2"]
    for res in results:
        fld = res.installation.fld
        for o in range(res.L.shape[0]):
            for p in range(res.L.shape[1]):
                lines.append(f"{res.table.name},{o + 1},{fld.x[p]:.4g},{fld.y[p]:.4g},{fld.lane[p] + 1},"
                             f"{int(fld.centre[p])},{_f(res.L[o, p])}")
    return "\n".join(lines) + "\n"


def _f(v, fmt: str = ".6g") -> str:
    """A value for a CSV cell: blank when missing (None or NaN)."""
    if v is None:
        return ""
    if isinstance(v, str):
        return v
    return format(v, fmt) if np.isfinite(v) else ""


def _t(v, fmt: str) -> str:
    """A value for a picture's text: 'missing' when missing."""
    return "missing" if v is None or not np.isfinite(v) else format(v, fmt)


def _png(fig) -> bytes:
    from roadgonio.plots import _plt
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    _plt().close(fig)
    return buf.getvalue()


def metrics_png(summaries: list[dict], target: str | None, layout_text: str) -> bytes:
    """Bars of L_av, U_o, U_l, TI per table with their 95 % intervals (both correlation bounds)
    and the limits of the target class."""
    from roadgonio.plots import _plt
    plt = _plt()
    n = len(summaries)
    fig, axes = plt.subplots(1, 4, figsize=(4.2 * 4, 4.6 + 0.25 * n))
    x = np.arange(n)
    names = [s["table"] for s in summaries]
    for ax, (key, label, kind) in zip(axes, METRICS):
        vals = [s[key] if s[key] is not None else np.nan for s in summaries]
        ax.bar(x, vals, color=[f"C{k}" for k in range(n)], alpha=0.75, width=0.6)
        for k, s in enumerate(summaries):
            unc = s.get("uncertainty") or {}
            for mode in MODES:
                mk, off, _ = MODE_MARKS[mode]
                m = (unc.get(mode) or {}).get(key)
                if m:
                    # the interval about the trials' mean, which it holds: the nominal value (the bar) can
                    # lie outside it (trial 11 D5: min/max uniformities are biased down under noise; an
                    # interval drawn about the nominal value needed a negative error and stopped the run)
                    lo, hi = m["coverage_interval_95"]
                    mean = min(max(m["mean"], lo), hi)
                    ax.errorbar(k + off, mean, yerr=[[mean - lo], [hi - mean]], fmt=mk,
                                color="k", ms=3, capsize=3, lw=1)
            v = s[key]
            if v is not None:
                ax.text(k - 0.28, 0.5 * v, f"{v:.3g}", ha="left", va="center", fontsize=8)
        if target and target in M_CLASSES:
            lim = M_CLASSES[target][key]
            # the limit's label in a legend that matplotlib places clear of the bars and error bars
            # (a text at data x = n - 0.5 ran over the axes frame and into the next panel)
            ax.axhline(lim, color="r", ls="--", lw=1, label=f"{target} {'min' if kind == 'min' else 'max'} {lim:g}")
            lo, hi = ax.get_ylim()
            ax.set_ylim(lo, max(hi, lim) * 1.25)                        # room for the legend above the bars
            ax.legend(loc="best", fontsize=8, labelcolor="r", framealpha=0.9)
        ax.set_xticks(x, names, rotation=20 if n > 2 else 0, fontsize=8)
        ax.set_title(label)
        ax.grid(axis="y", alpha=0.3)
    classes = ", ".join(f"{s['table']}: {s['class'] or 'none'}" for s in summaries)
    shown = [MODE_MARKS[m][2] for m in MODES if any(m in (s.get("uncertainty") or {}) for s in summaries)]
    fig.suptitle(f"EN 13201 metrics: {classes}\n{layout_text}"
                 + ("\nbars: the table's values; markers: the Monte Carlo mean with its 95 % interval, " + ", ".join(shown)
                    if shown else ""), fontsize=9)
    fig.tight_layout()
    return _png(fig)


def luminance_png(results) -> bytes:
    """Luminance over the field, one row per table, one column per observer (lane)."""
    from roadgonio.plots import _plt
    plt = _plt()
    n_t = len(results)
    n_o = results[0].L.shape[0]
    fld = results[0].installation.fld
    lay = results[0].installation.layout
    nx = fld.n_long
    vmax = max((float(np.nanmax(r.L)) for r in results if np.isfinite(r.L).any()), default=1.0) or 1.0
    fig, axes = plt.subplots(n_t, n_o, figsize=(5.2 * n_o + 1, 1.2 + 2.3 * n_t), squeeze=False,
                             constrained_layout=True)
    im = None
    for t, res in enumerate(results):
        for o in range(n_o):
            ax = axes[t, o]
            grid = res.L[o].reshape(lay.lanes * 3, nx)   # rows: y order of the points
            ext = [0, lay.spacing_m, 0, lay.width_m]
            im = ax.imshow(grid, origin="lower", extent=ext, aspect="auto", vmin=0, vmax=vmax, cmap="magma")
            for y_row, x_off, _ in lay.rows():
                xs = [x for x in (x_off, x_off + lay.spacing_m) if 0 <= x <= lay.spacing_m]
                ax.plot(xs, [y_row] * len(xs), "c^", ms=7, clip_on=False)
            for k in range(1, lay.lanes):
                ax.axhline(k * lay.lane_width_m, color="w", ls="--", lw=0.8)
            m = res.per_observer
            ax.set_title(f"{res.table.name}, observer lane {o + 1}: L_av {_t(m['L_av_obs'][o], '.3g')}, "
                         f"U_o {_t(m['U_o_obs'][o], '.2f')}, U_l {_t(m['U_l_lane'][o], '.2f')}", fontsize=8)
            ax.set_xlabel("x along the road (m)", fontsize=8)
            ax.set_ylabel("y (m)", fontsize=8)
    cb = fig.colorbar(im, ax=axes.ravel().tolist(), fraction=0.03, pad=0.02)
    cb.set_label("L (cd/m²)")
    fig.suptitle("Road-surface luminance over the EN 13201-3 field (triangles: luminaires)", fontsize=10)
    return _png(fig)


def road_files(results, summaries: list[dict], target: str | None, plots: bool = True,
               inputs: list[dict] | None = None) -> dict[str, bytes | str]:
    """The files of ``roadgonio road``; ``inputs``: the provenance records of the input files
    (:func:`roadgonio.provenance.input_record`)."""
    lay = results[0].installation.layout
    files: dict[str, bytes | str] = {
        "road.json": to_json({"tables": summaries, "provenance": provenance(settings={"layout": lay.describe()},
                                                                              inputs=inputs)})
        + "\n",
        "road_metrics.csv": metrics_csv(summaries),
        "road_luminance.csv": luminance_csv(results),
    }
    if plots:
        files["road_metrics.png"] = metrics_png(summaries, target, lay.describe())
        files["road_luminance.png"] = luminance_png(results)
    return files
