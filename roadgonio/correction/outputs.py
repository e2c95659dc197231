"""What a correction writes: its outputs together or not at all (:class:`roadgonio.fileio.OutputGroup`).

In the output folder (the first eight files are one group: a full disk or a failing picture
leaves none of them, and the folder's previous set stays as it was)::

    corrected.csv        corrected r x 1e4, the r-table layout
    corrected_u.csv      its standard uncertainty, r x 1e4, same layout
    corrected.rtb        the corrected table as DIALux RTB (r x 1e4)
    correct.json         summary (S1, S2, Q0 before/after with u, CIE classes), budget, fit, provenance
    correct_cells.csv    per cell: measured, k_A, corrected, every uncertainty component
    corrected_corr.csv   correlation matrix of the corrected cells (labels "tan eps/beta")
    before_after.png     the 20 beta columns, measured and corrected with the 95 % band
    correction_map.png   k_A and the relative uncertainty of the corrected table, cell by cell
    forward-N/           journalled k_A tables of the fitted model (resumable, like `roadgonio ka`)
    fit_state.json       checkpoint of the fitted models (a rerun with the same inputs reuses them)

The journals (``forward-N/``, ``alternative-N/``) and ``fit_state.json`` are written while the
correction runs, outside the group: they survive a failed output write, so the same command
afterwards resumes and writes the whole set.
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from roadgonio.fileio import OutputGroup
from roadgonio.surface.fit import model_r_on_grid
from roadgonio.surface.rtable import R_SCALE, grid_csv_text

FILES = {"corrected": "corrected.csv", "u": "corrected_u.csv", "rtb": "corrected.rtb", "json": "correct.json",
         "cells": "correct_cells.csv", "correlation": "corrected_corr.csv", "picture": "before_after.png",
         "map": "correction_map.png"}


def u_csv_text(res) -> str:
    """The corrected table's standard uncertainties in the r-table CSV layout (r x 1e4, 4 digits)."""
    table = res.corrected
    return grid_csv_text(res.u_corrected, "standard uncertainty of " + table.source, scale=R_SCALE, digits=4,
                         tan_eps=table.tan_eps, beta_deg=table.beta_deg)


def write_correction(res, out_dir: str | Path, *, plots: bool = True) -> list[Path]:
    """Write every output of a :class:`~roadgonio.correction.run.CorrectionResult` to ``out_dir``,
    together or not at all (module docstring); an OSError is the one-line InputError naming the
    file. Returns the paths (corrected.csv, corrected_u.csv, corrected.rtb, correct.json, ...)."""
    with OutputGroup(out_dir) as group:
        paths = [group.text(FILES["corrected"], res.corrected.to_csv_text()),
                 group.text(FILES["u"], u_csv_text(res)),
                 group.text(FILES["rtb"], res.corrected.to_rtb_text()),
                 group.text(FILES["cells"], cells_csv(res)),
                 group.text(FILES["correlation"], correlation_csv(res))]
        if plots:
            paths.append(_group_figure(group, FILES["picture"], draw_before_after(res)))
            paths.append(_group_figure(group, FILES["map"], draw_correction_map(res)))
        paths.insert(3, group.json(FILES["json"], _json_doc(res, plots)))
    return paths


def _group_figure(group: OutputGroup, name: str, fig) -> Path:
    from roadgonio.plots import _plt
    try:
        return group.figure(name, lambda p: fig.savefig(p, format="png", dpi=100))
    finally:
        _plt().close(fig)


def _json_doc(res, plots: bool) -> dict[str, Any]:
    return {"summary": res.summary(), "provenance": res.provenance,
            "files": {k: v for k, v in FILES.items() if plots or k not in ("picture", "map")},
            "definitions": {
                "corrected": "r_corrected = r_measured / k_A (k_A of the model under the instrument's calibration)",
                "u": "standard uncertainty (k = 1) of r_corrected; relative components add in quadrature, with "
                     "correlations between cells (corrected_corr.csv)",
                "S1": "r(beta 0, tan 2) / r(beta 0, tan 0)", "Q0": "CIE 144 average luminance coefficient (sr^-1)",
                "S2": "Q0 / r(0, 0)", "class": "CIE 144 by S1: R1 < 0.42 <= R2 < 0.85 <= R3 < 1.35 <= R4; "
                                             "C1 < 0.40 <= C2; nearest_table by (S1, Q0)",
                "before": "the measured table as reported, with the measurement's (and misalignment) uncertainty"}}


def cells_csv(res) -> str:
    m = res.measured.mask
    ii, jj = np.nonzero(m)
    comps = list(res.budget.components)
    u_comp = {c: res.budget.u_rel(c) for c in comps}
    u_tot = res.budget.u_rel()
    model_r = model_r_on_grid(res.model, res.measured)
    sim = res.fit.simulated if res.fit is not None else None
    head = ["tan_eps", "beta_deg", "r_measured_x1e4", "u_measured_x1e4", "k_a", "u_k_a_backend",
            "r_corrected_x1e4", "u_corrected_x1e4", "u_rel_total"] + [f"u_rel_{c}" for c in comps] \
        + [f"k_a_{n}" for n in res.alternatives] + ["r_model_ideal_x1e4"] + (["r_simulated_x1e4"] if sim is not None else [])
    buf = io.StringIO()
    buf.write("# " + res.corrected.source + "\n")
    buf.write(",".join(head) + "\n")
    for k, (i, j) in enumerate(zip(ii, jj)):
        row = [f"{res.measured.tan_eps[i]:g}", f"{res.measured.beta_deg[j]:g}", f"{res.measured.r[i, j] * 1e4:.6g}",
               f"{res.u_measured[i, j] * 1e4:.4g}", f"{res.k_a[i, j]:.6g}", f"{res.k_se[i, j]:.3g}",
               f"{res.corrected.r[i, j] * 1e4:.6g}", f"{res.u_corrected[i, j] * 1e4:.4g}", f"{u_tot[k]:.4g}"]
        row += [f"{u_comp[c][k]:.3g}" for c in comps]
        row += [f"{a[i, j]:.6g}" for a in res.alternatives.values()]
        row.append(f"{model_r[i, j] * 1e4:.6g}")
        if sim is not None:
            row.append(f"{sim[k] * 1e4:.6g}")
        buf.write(",".join(row) + "\n")
    return buf.getvalue()


def correlation_csv(res) -> str:
    m = res.measured.mask
    ii, jj = np.nonzero(m)
    labels = [f"{res.measured.tan_eps[i]:g}/{res.measured.beta_deg[j]:g}" for i, j in zip(ii, jj)]
    c = res.budget.correlation()
    buf = io.StringIO()
    buf.write("# correlation of the corrected cells (rows and columns labelled tan eps/beta)\n")
    buf.write("cell," + ",".join(labels) + "\n")
    for k, lab in enumerate(labels):
        buf.write(lab + "," + ",".join(f"{v:.4f}" for v in c[k]) + "\n")
    return buf.getvalue()


def _fmt_u(v: float | None, u: float | None, digits: int = 3) -> str:
    if u is None or not np.isfinite(u):
        return f"{v:.{digits}g}"
    return f"{v:.{digits}g} +- {u:.2g}"


def _functional_text(f: dict[str, Any]) -> str:
    cls = f["class"]
    return (f"S1 = {_fmt_u(f['S1'], f.get('u_S1'))}   Q0 = {_fmt_u(f['Q0'], f.get('u_Q0'))} sr^-1   "
            f"S2 = {_fmt_u(f['S2'], f.get('u_S2'))}   class {cls['R']} / {cls['C']}, nearest CIE table {f['nearest_table']}")


def draw_before_after(res):
    """The 20 beta columns: r x 1e4 against tan eps, as measured and as corrected (95 % band)."""
    from matplotlib import ticker

    from roadgonio.plots import _plt
    plt = _plt()
    meas, corr = res.measured, res.corrected
    model_r = model_r_on_grid(res.model, meas)
    fig, axes = plt.subplots(4, 5, figsize=(17, 13.5), sharex=True)
    for j, ax in enumerate(axes.ravel()):
        beta = meas.beta_deg[j]
        ok = meas.mask[:, j]
        if not ok.any():
            ax.set_title(f"beta = {beta:g} deg   (not measured)", fontsize=8)
            ax.tick_params(labelsize=7)
            if j >= 15:
                ax.set_xlabel("tan eps", fontsize=8)
            continue
        t = meas.tan_eps[ok]
        rc = corr.r[ok, j] * 1e4
        band = 2.0 * res.u_corrected[ok, j] * 1e4
        ax.fill_between(t, rc - band, rc + band, color="C0", alpha=0.25, lw=0)
        ax.plot(t, meas.r[ok, j] * 1e4, "o--", color="0.45", ms=3, lw=0.9)
        ax.plot(t, rc, "-", color="C0", lw=1.6)
        ax.plot(t, model_r[ok, j] * 1e4, ":", color="C3", lw=1.0)
        change = 100.0 * (corr.r[ok, j] / meas.r[ok, j] - 1.0)
        ax.set_title(f"beta = {beta:g} deg   (correction {change.min():+.1f} ... {change.max():+.1f} %)", fontsize=8)
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(ticker.NullFormatter())
        ax.grid(alpha=0.3, which="major")
        ax.tick_params(labelsize=7)
        if j % 5 == 0:
            ax.set_ylabel("r x 10^4 (sr^-1)", fontsize=8)
        if j >= 15:
            ax.set_xlabel("tan eps", fontsize=8)
    handles = [plt.Line2D([], [], color="0.45", marker="o", ls="--", ms=3, label="measured (as the instrument reported)"),
               plt.Line2D([], [], color="C0", lw=1.6, label="corrected = measured / k_A"),
               plt.matplotlib.patches.Patch(color="C0", alpha=0.25, label="corrected +- 2 u (about 95 %)"),
               plt.Line2D([], [], color="C3", ls=":", label=f"model used for k_A ({res.model.variant}), ideal geometry")]
    fig.suptitle(f"{meas.name}: r-table before and after the aperture-effect correction   (instrument "
                 f"{res.provenance['instrument'].get('instrument', {}).get('name', '?')}, calibration "
                 f"{res.provenance.get('calibration', {}).get('mode', 'lambert')}, reference {res.reference})",
                 fontsize=11, y=0.99)
    fig.text(0.5, 0.962, "before:  " + _functional_text(res.before) + "\nafter:   " + _functional_text(res.after)
             + "\n(+- = standard uncertainty; correction in a panel title = corrected / measured - 1)",
             ha="center", va="top", fontsize=9, family="monospace")
    fig.legend(handles=handles, loc="upper center", ncol=4, fontsize=9, bbox_to_anchor=(0.5, 0.915), frameon=False)
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.05, top=0.875, wspace=0.22, hspace=0.3)
    return fig


def draw_correction_map(res):
    """k_A per cell and the relative standard uncertainty of the corrected table, as maps."""
    from roadgonio.plots import _plt, draw_table_map
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(20, 9))
    k = res.k_a[np.isfinite(res.k_a)]
    wide = float(k.max() / k.min()) > 1.5
    draw_table_map(a1, res.k_a, label="k_A (measured / true; 1 = no aperture effect)", fontsize=5, tick_fontsize=7,
                   log=wide, fmt="{:.2f}" if wide else "{:.3f}")
    a1.set_title(f"{res.measured.name}: k_A used for the correction (corrected = measured / k_A)", fontsize=10)
    u = np.full(res.k_a.shape, np.nan)
    u[res.measured.mask] = 100.0 * res.budget.u_rel()
    draw_table_map(a2, u, label="relative standard uncertainty of the corrected r (%)", centre=None, log=False,
                   fmt="{:.1f}", fontsize=5, tick_fontsize=7)
    comps = ", ".join(res.budget.components)
    a2.set_title(f"u of the corrected table (%), components: {comps}", fontsize=10)
    fig.subplots_adjust(left=0.04, right=0.97, bottom=0.07, top=0.95, wspace=0.12)
    return fig
