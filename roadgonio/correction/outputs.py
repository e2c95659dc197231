"""What a correction writes: its outputs together or not at all (:class:`roadgonio.fileio.OutputGroup`).

In the output folder (the first ten files are one group: a full disk or a failing picture
leaves none of them, and the folder's previous set stays as it was; once the new set is in, a file
of the previous set that this run did not write, e.g. a picture under --no-plots, is removed)::

    corrected.csv        corrected r x 1e4, the r-table layout
    corrected_u.csv      its standard uncertainty, r x 1e4, same layout
    corrected.rtb        the corrected table as DIALux RTB (r x 1e4)
    correct.json         summary (S1, S2, Q0 before/after with u, CIE classes), budget, fit, provenance
    correct_cells.csv    per cell: measured, k_A, corrected, every uncertainty component
    corrected_corr.csv   correlation matrix of the corrected cells (labels "tan eps/beta")
    before_after.png     the 20 beta columns, measured and corrected with the 95 % band
    correction_map.png   k_A and the relative uncertainty of the corrected table, cell by cell
    residual_map.png     (forward model "surface") the fit's residual in units of u and the local Birge ratio
    correction_surface.png  (forward model "surface") the correction surface at the cells, its posterior
                         sd, and g_D, the behaviour off alpha = 1 deg beyond the backbone's
    forward-N/           journalled k_A tables of the fitted model (resumable, like `roadgonio ka`)
    fit_state.json       checkpoint of the fitted models and correction surfaces (a rerun with the same inputs reuses them)

The journals (``forward-N/``, ``alternative-N/``) and ``fit_state.json`` are written while the
correction runs, outside the group: they survive a failed output write, so the same command
afterwards resumes and writes the whole set.

Several instruments, one surface (:func:`write_surface_correction`): the same files for the one
corrected table, ``correct_cells.csv`` with every instrument's measured r, k_A, corrected r and
residual, and the pictures for all instruments.
"""
from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import numpy as np

from roadgonio.fileio import OutputGroup
from roadgonio.surface.fit import model_r_on_grid
from roadgonio.surface.rtable import NOTE_PREFIX, R_SCALE, U_HEADER, correlation_text, grid_csv_text, header_line

PICTURES = ("picture", "map", "residuals", "surface")
FILES = {"corrected": "corrected.csv", "u": "corrected_u.csv", "rtb": "corrected.rtb", "json": "correct.json",
         "cells": "correct_cells.csv", "correlation": "corrected_corr.csv", "picture": "before_after.png",
         "map": "correction_map.png", "residuals": "residual_map.png", "surface": "correction_surface.png"}
#: The writers' ``replaces`` (:class:`~roadgonio.fileio.OutputGroup`, as render and road do): an earlier
#: run's output that this run does not write (a picture under --no-plots, the --forward surface
#: pictures after an eq. 4 run, an RTB the new table cannot have) is removed once the new files are in.
REPLACES = tuple(FILES.values())


def has_rtb(table) -> bool:
    """Whether the corrected table can be written as RTB: the format needs Q0, which a table without
    a grid cell of four tabulated corners does not have (the CSV is always written; correct.json
    lists the files written)."""
    return math.isfinite(table.q0())


def u_csv_text(res) -> str:
    """The corrected table's standard uncertainties in the r-table CSV layout (r x 1e4, 4 digits); the
    header names the table and, when the data reject the fit, says so (a ``note:`` line,
    :func:`~roadgonio.correction.fit.misfit_note`, which ``road --u`` repeats)."""
    from roadgonio.correction.run import REFLECTANCES_EXACT_NOTE
    table = res.corrected
    fit = getattr(res, "fit", None)
    note = (fit.summary() if fit is not None else {}).get("misfit_note")
    if note is not None and (fit.summary().get("misfit_cells_widened") is None):
        note += ", and this u may not cover that error"
    notes = [] if note is None else [f"{note} (roadgonio correct; docs/correction.md, \"Outside eq. 4\")"]
    # what this u leaves out for an instrument with parts (user audit, session 39: said by correct, lost
    # on the way to road, which repeats these lines)
    notes += list((getattr(res, "extra", None) or {}).get("u_notes", ()))
    if (getattr(res, "provenance", None) or {}).get("forward_model_limits"):
        notes.append(REFLECTANCES_EXACT_NOTE)
    head = U_HEADER + table.source + "".join(f"\n{NOTE_PREFIX}{n}" for n in notes)
    return grid_csv_text(res.u_corrected, head, scale=R_SCALE, digits=4,
                         tan_eps=table.tan_eps, beta_deg=table.beta_deg)


def write_correction(res, out_dir: str | Path, *, plots: bool = True) -> list[Path]:
    """Write every output of a :class:`~roadgonio.correction.run.CorrectionResult` to ``out_dir``,
    together or not at all (module docstring); an OSError is the one-line InputError naming the
    file. Returns the paths (corrected.csv, corrected_u.csv, corrected.rtb, correct.json, ...)."""
    with OutputGroup(out_dir, replaces=REPLACES) as group:
        paths = [group.text(FILES["corrected"], res.corrected.to_csv_text()),
                 group.text(FILES["u"], u_csv_text(res)),
                 group.text(FILES["cells"], cells_csv(res)),
                 group.text(FILES["correlation"], correlation_csv(res))]
        if has_rtb(res.corrected):
            paths.insert(2, group.text(FILES["rtb"], res.corrected.to_rtb_text()))
        if plots:
            paths.append(_group_figure(group, FILES["picture"], draw_before_after(res)))
            paths.append(_group_figure(group, FILES["map"], draw_correction_map(res)))
            sc = res.extra.get("surface")
            if sc is not None:
                paths.append(_group_figure(group, FILES["residuals"], draw_residual_map(sc)))
                paths.append(_group_figure(group, FILES["surface"], draw_surface_map(sc)))
        paths.insert(3 if has_rtb(res.corrected) else 2, group.json(FILES["json"], _json_doc(res, plots)))
    return paths


def _style_beta_panel(ax, j: int) -> None:
    """One beta column's panel of the 4 x 5 before/after grids: log r axis, labels on the edges."""
    from matplotlib import ticker
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


def _group_figure(group: OutputGroup, name: str, fig) -> Path:
    from roadgonio.plots import _plt
    try:
        return group.figure(name, lambda p: fig.savefig(p, format="png", dpi=100))
    finally:
        _plt().close(fig)


#: What the corrected table of a surface correction is, when it weighs the model's own value.
MODEL_ESTIMATE_DEFINITION = (
    "per cell, the least-variance combination with non-negative weights (generalised least squares with the full "
    "covariance where no weight is negative) of r_measured / k_A (k_A of the eq. 4 backbone x correction surface "
    "fitted through the instrument(s)) and the fitted surface's own value at the nominal geometry; w_model "
    "(correct_cells.csv) is the latter's weight")


def _corrected_definition(sc, joint: bool) -> str:
    if sc is not None and sc.model_weight is not None:
        return MODEL_ESTIMATE_DEFINITION
    if joint:
        return ("one table: per instrument r_measured / k_A (k_A of the eq. 4 backbone x correction surface fitted "
                "through all instruments), combined cell by cell with the least-variance non-negative weights "
                "(generalised least squares with the full covariance between the instruments where no weight is "
                "negative)")
    return "r_corrected = r_measured / k_A (k_A of the model under the instrument's calibration)"


def _json_doc(res, plots: bool) -> dict[str, Any]:
    return {"summary": res.summary(), "provenance": res.provenance,
            "files": {k: v for k, v in FILES.items() if (plots or k not in PICTURES)
                      and (k not in ("residuals", "surface") or res.extra.get("surface") is not None)
                      and (k != "rtb" or has_rtb(res.corrected))},
            "definitions": {
                "corrected": _corrected_definition(res.extra.get("surface"), joint=False),
                "u": "standard uncertainty (k = 1) of r_corrected; relative components add in quadrature, with "
                     "correlations between cells (corrected_corr.csv)",
                "S1": "r(beta 0, tan 2) / r(beta 0, tan 0)", "Q0": "CIE 144 average luminance coefficient (sr^-1)",
                "S2": "Q0 / r(0, 0)", "class": "CIE 144 by S1: R1 < 0.42 <= R2 < 0.85 <= R3 < 1.35 <= R4; "
                                             "C1 < 0.40 <= C2; nearest_table by (S1, Q0), or by the one of them the table has "
                                             "(nearest_table_basis),",
                "before": "the measured table as reported, with the measurement's (and misalignment) uncertainty",
                "correct_cells.csv": _column_definitions(_cells_head(res))}}


def _k_text(v) -> str:
    """A k_A in correct_cells.csv: the shortest text that reads back as the same float64 (``repr``). Its
    standard uncertainty (u_k_a_backend: an SE, or a bound / sqrt 3) goes down to 1e-7 and below (a
    converged quadrature, a zero aperture: 0), so any fixed number of digits (%.6g rounds by up to
    5e-6) could be coarser than the value's uncertainty."""
    return repr(float(v))


#: What each column of correct_cells.csv holds (correct.json's ``definitions["correct_cells.csv"]``,
#: the columns the file has; user audit, session 38: the file's columns were defined nowhere).
CELL_COLUMNS = {
    "tan_eps": "tan(epsilon) of the cell", "beta_deg": "beta of the cell (deg)",
    "r_measured_x1e4": "the measured r x 1e4", "u_measured_x1e4": "its standard uncertainty x 1e4",
    "k_a": "k_A that corrects the cell (the backend's, under the instrument's calibration; every digit)",
    "u_k_a_backend": "the backend's standard uncertainty of k_a",
    "r_corrected_x1e4": "the corrected r x 1e4", "u_corrected_x1e4": "its standard uncertainty x 1e4",
    "u_rel_total": "relative standard uncertainty of r_corrected",
    "u_rel_<component>": "one component of it (definitions in docs/correction.md, 'The uncertainty')",
    "k_a_<alternative>": "k_A of an alternative model or reference (the model component's spread); through a "
                         "fitted surface, k_A of another backbone (variant, and its rounding at the mirror plane when "
                         "the name says so) with its own correction surface, where k_a is the evidence-weighted k_A "
                         "of all of them",
    "r_model_ideal_x1e4": "the fitted model's (or reference's) ideal r x 1e4 at alpha = 1 deg",
    "r_simulated_x1e4": "the fitted model's simulated measurement through the instrument x 1e4",
    "r_over_k_a_x1e4": "r_measured / k_a x 1e4 (the measurement's own estimate)",
    "w_model": "weight of the fitted surface's own value in r_corrected (the rest: r_over_k_a)",
    "dlnk_a_dlnf_unobserved": "d ln k_A / d ln f of the road beyond the observation elevations (stray light)",
    "k_a_direct": "k_A of the light straight from the source alone (without stray light)",
    "stray_fraction": "1 - S_direct / S_total of the road signal (the stray light's share)",
}


def _column_definitions(head: list[str], columns: dict[str, str] = CELL_COLUMNS,
                        named: dict[str, str] | None = None) -> dict[str, str]:
    """The definition of each column of ``head`` from ``columns``: its own, or its template's
    (``u_rel_<component>``, ``k_a_<alternative>``, or the template ``named`` gives it: a joint
    correction's per-instrument columns)."""
    out = {}
    for c in head:
        key = (named or {}).get(c) or (c if c in columns else "u_rel_<component>" if c.startswith("u_rel_")
                                       else "k_a_<alternative>" if c.startswith("k_a_") else c)
        out[c] = columns.get(key, "")
    return out


def _cells_head(res) -> list[str]:
    """The columns of correct_cells.csv for ``res`` (:func:`cells_csv`; correct.json defines them)."""
    sc = res.extra.get("surface")
    head = ["tan_eps", "beta_deg", "r_measured_x1e4", "u_measured_x1e4", "k_a", "u_k_a_backend",
            "r_corrected_x1e4", "u_corrected_x1e4", "u_rel_total"] + [f"u_rel_{c}" for c in res.budget.components] \
        + [f"k_a_{n}" for n in res.alternatives] + ["r_model_ideal_x1e4"] \
        + (["r_simulated_x1e4"] if res.fit is not None and res.fit.simulated is not None else [])
    if sc is not None and sc.model_weight is not None:
        head += ["r_over_k_a_x1e4", "w_model"]
    if sc is not None and sc.parts[0].unobserved_sensitivity is not None:
        head += ["dlnk_a_dlnf_unobserved"]
    if res.extra.get("stray") is not None:
        head += ["k_a_direct", "stray_fraction"]
    return head


def cells_csv(res) -> str:
    m = res.measured.mask
    ii, jj = np.nonzero(m)
    comps = list(res.budget.components)
    u_comp = {c: res.budget.u_rel(c) for c in comps}
    u_tot = res.budget.u_rel()
    sc = res.extra.get("surface")
    model_r = sc.parts[0].model_r if sc is not None else model_r_on_grid(res.model, res.measured)
    sim = res.fit.simulated if res.fit is not None else None
    weight = sc.model_weight if sc is not None else None
    unobserved = sc.parts[0].unobserved_sensitivity if sc is not None else None
    stray = res.extra.get("stray")
    head = _cells_head(res)
    buf = io.StringIO()
    buf.write("# " + res.corrected.source + "\n")
    buf.write(",".join(head) + "\n")
    for k, (i, j) in enumerate(zip(ii, jj)):
        row = [f"{res.measured.tan_eps[i]:g}", f"{res.measured.beta_deg[j]:g}", f"{res.measured.r[i, j] * 1e4:.6g}",
               f"{res.u_measured[i, j] * 1e4:.4g}", _k_text(res.k_a[i, j]), f"{res.u_k_a_backend[i, j]:.3g}",
               f"{res.corrected.r[i, j] * 1e4:.6g}", f"{res.u_corrected[i, j] * 1e4:.4g}", f"{u_tot[k]:.4g}"]
        row += [f"{u_comp[c][k]:.3g}" for c in comps]
        row += [_k_text(a[i, j]) for a in res.alternatives.values()]
        row.append(f"{model_r[i, j] * 1e4:.6g}")
        if sim is not None:
            row.append(f"{sim[k] * 1e4:.6g}")
        if weight is not None:
            row += [f"{sc.parts[0].corrected.r[i, j] * 1e4:.6g}", f"{weight[i, j]:.4g}"]
        if unobserved is not None:
            row.append(f"{unobserved[i, j]:.4g}")
        if stray is not None:
            row += [_k_text(stray["k_a_direct"][i, j]), f"{stray['stray_fraction'][i, j]:.4g}"]
        buf.write(",".join(row) + "\n")
    return buf.getvalue()


def correlation_csv(res) -> str:
    return _correlation_text(res.measured, res.budget, res.corrected)


def _fmt_u(v: float | None, u: float | None, digits: int = 3) -> str:
    if u is None or not np.isfinite(u):
        return f"{v:.{digits}g}"
    return f"{v:.{digits}g} +- {u:.2g}"


def _functional_text(f: dict[str, Any]) -> str:
    cls = f["class"]
    return (f"S1 = {_fmt_u(f['S1'], f.get('u_S1'))}   Q0 = {_fmt_u(f['Q0'], f.get('u_Q0'))} sr^-1   "
            f"S2 = {_fmt_u(f['S2'], f.get('u_S2'))}   class {cls['R']} / {cls['C']}, nearest CIE table {f['nearest_table']}"
            + (f" ({f['nearest_table_basis']})" if f.get("nearest_table_basis") else ""))


def draw_before_after(res):
    """The 20 beta columns: r x 1e4 against tan eps, as measured and as corrected (95 % band)."""

    from roadgonio.plots import _plt
    plt = _plt()
    meas, corr = res.measured, res.corrected
    sc = res.extra.get("surface")
    model_r = sc.parts[0].model_r if sc is not None else model_r_on_grid(res.model, meas)
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
        _style_beta_panel(ax, j)
    handles = [plt.Line2D([], [], color="0.45", marker="o", ls="--", ms=3, label="measured (as the instrument reported)"),
               plt.Line2D([], [], color="C0", lw=1.6, label=("corrected (measured / k_A and the fitted surface, "
                                                             "weighed by their u)" if sc is not None and
                                                             sc.model_weight is not None else "corrected = measured / k_A")),
               plt.matplotlib.patches.Patch(color="C0", alpha=0.25, label="corrected +- 2 u (about 95 %)"),
               plt.Line2D([], [], color="C3", ls=":", label=(f"model used for k_A ({res.model.variant}"
                                                             + (" x correction surface" if sc is not None else "")
                                                             + "), ideal geometry"))]
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
    """k_A per cell and the relative standard uncertainty of the corrected table, as maps; laid out as
    the joint map is (:func:`draw_joint_map`: constrained layout, JOINT_MAP_PANEL_IN panels, cell numbers
    at JOINT_MAP_CELL_FONT pt; trial 12 D8: the left colour bar's label touched the right panel's axis
    label and the 5 pt cell numbers were ~5 px high)."""
    from roadgonio.plots import _plt, draw_table_map
    plt = _plt()
    w, h = JOINT_MAP_PANEL_IN
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(2 * w, h), layout="constrained")
    fs = JOINT_MAP_CELL_FONT
    k = res.k_a[np.isfinite(res.k_a)]
    wide = float(k.max() / k.min()) > 1.5
    draw_table_map(a1, res.k_a, label="k_A (measured / true; 1 = no aperture effect)", fontsize=fs, tick_fontsize=8,
                   log=wide, fmt="{:.2f}" if wide else "{:.3f}")
    # with --forward surface the table also weighs the fitted surface's own value (user audit, session 24:
    # the title said corrected = measured / k_A where that value carries most of the table)
    how = ("corrected: measured / k_A and the fitted surface's own value, weighed by their u"
           if (getattr(res, "extra", None) or {}).get("surface") is not None else "corrected = measured / k_A")
    a1.set_title(f"{res.measured.name}: k_A of the instrument ({how})", fontsize=10)
    u = np.full(res.k_a.shape, np.nan)
    u[res.measured.mask] = 100.0 * res.budget.u_rel()
    draw_table_map(a2, u, label="relative standard uncertainty of the corrected r (%)", centre=None, log=False,
                   fmt="{:.1f}", fontsize=fs, tick_fontsize=8)
    comps = ", ".join(res.budget.components)
    a2.set_title(f"u of the corrected table (%), components: {comps}", fontsize=10)
    fig.get_layout_engine().set(w_pad=0.15, wspace=0.04)
    return fig


# ----------------------------------------------------------------------------------------------
# The correction surface (one instrument or several): diagnostics and the joint outputs
# ----------------------------------------------------------------------------------------------

def draw_residual_map(sc):
    """Per instrument: the fit's residual (simulated - measured) in units of the measurement's u, and
    the local Birge ratio that widens u where the residuals have structure."""
    from roadgonio.plots import _plt, draw_table_map
    plt = _plt()
    n = len(sc.parts)
    fig, axes = plt.subplots(n, 2, figsize=(20, 8.5 * n), squeeze=False)
    best = sc.best
    for (a1, a2), p in zip(axes, sc.parts):
        r = np.clip(p.residual, -4.0, 4.0)
        draw_table_map(a1, r, label="(simulated - measured) / u  (clipped at +-4)", centre=0.0, log=False,
                       fmt="{:+.1f}", fontsize=5, tick_fontsize=7)
        rms = float(np.sqrt(np.nanmean(p.residual ** 2)))
        a1.set_title(f"{p.name}: residual of the fit in units of u (RMS {rms:.2f}; {best.label} backbone x "
                     f"correction surface, Birge ratio {best.fit.birge:.2f})", fontsize=10)
        draw_table_map(a2, p.birge_local, label="local Birge ratio B", centre=1.0, log=False, fmt="{:.2f}",
                       fontsize=5, text=lambda i, j, p=p: f"{p.birge_local[i, j]:.2f}" + ("*" if p.widening[i, j] > 1 else ""),
                       tick_fontsize=7)
        a2.set_title(f"{p.name}: local Birge ratio over the neighbouring cells (max {np.nanmax(p.birge_local):.2f}; "
                     f"* = u widened by B, {int(np.sum(p.widening > 1))} cells)", fontsize=10)
    fig.subplots_adjust(left=0.04, right=0.97, bottom=0.05, top=0.95, wspace=0.12, hspace=0.25)
    return fig


def draw_surface_map(sc):
    """The correction surface at the table's cells (best variant): the factor exp(g_C) it applies to
    the backbone at alpha = 1 deg, its posterior standard deviation, and g_D, the extra
    d ln f / d ln alpha (the behaviour off 1 deg that only a second aperture measures); and, when the
    table weighs it, the weight of the surface's own value in the corrected table."""
    from roadgonio.plots import _plt, draw_table_map
    plt = _plt()
    p = sc.parts[0]
    best = sc.best
    if sc.model_weight is None:
        fig, axes = plt.subplots(1, 3, figsize=(28, 9))
    else:
        fig, axes = plt.subplots(2, 2, figsize=(20, 18))
        axes = axes.ravel()
    draw_table_map(axes[0], np.exp(p.surfaces["g_c"]), label="exp(g_C): factor on the backbone at alpha = 1 deg",
                   centre=1.0, log=True, fmt="{:.2f}", fontsize=4.5, tick_fontsize=7)
    axes[0].set_title(f"correction surface over the {best.label} backbone (weight {best.weight:.2f})", fontsize=10)
    draw_table_map(axes[1], 100.0 * p.surfaces.get("sd_g_c", np.full_like(p.k_a, np.nan)),
                   label="posterior standard deviation of g_C (%)", centre=None, log=False, fmt="{:.1f}",
                   fontsize=4.5, tick_fontsize=7)
    axes[1].set_title("how well the data pin the surface down at each cell", fontsize=10)
    how = best.fit.d_prior_chosen_by
    draw_table_map(axes[2], p.surfaces["g_d"], label="g_D: extra d ln f / d ln alpha (prior sd "
                   f"{best.fit.d_prior_sd:.2g}" + ("" if how.startswith("held") else f", chosen by the {how}") + ")", centre=0.0, log=False, fmt="{:+.2f}", fontsize=4.5, tick_fontsize=7)
    axes[2].set_title("behaviour off alpha = 1 deg beyond the backbone's" + (
        " (measured: several aperture settings)" if sc.joint else " (one aperture: mostly the prior)"), fontsize=10)
    if sc.model_weight is not None:
        draw_table_map(axes[3], sc.model_weight, label="w_model: weight of the surface's own value (rest: r / k_A)",
                       centre=0.5, log=False, fmt="{:.2f}", fontsize=4.5, tick_fontsize=7)
        axes[3].set_title("where the corrected table follows the fitted surface (1) or the measurement (0)",
                          fontsize=10)
    lam = ", ".join(f"{k} {v:.3g}" for k, v in best.fit.lam.items())
    import textwrap
    title = (f"{' + '.join(q.measured.name for q in sc.parts)}: the correction surface (smoothing parameters by the "
             f"evidence: {lam}; edf {best.fit.edf:.0f} of {best.fit.n} cells)")
    fig.suptitle("\n".join(textwrap.wrap(title, 190 if sc.model_weight is None else 150)), fontsize=11)
    if sc.model_weight is None:
        fig.subplots_adjust(left=0.03, right=0.97, bottom=0.07, top=0.88, wspace=0.12)
    else:
        # the colour bars' tick labels (a minus sign for a negative weight) need room on the right
        fig.subplots_adjust(left=0.04, right=0.95, bottom=0.04, top=0.94, wspace=0.17, hspace=0.12)
    return fig


def draw_joint_before_after(sc):
    """The 20 beta columns: every instrument's measured table and the one corrected table with its
    95 % band."""

    from roadgonio.plots import _plt
    plt = _plt()
    corr, u = sc.corrected, sc.u_corrected
    fig, axes = plt.subplots(4, 5, figsize=(17, 13.5), sharex=True)
    markers = "osd^v<>"
    for j, ax in enumerate(axes.ravel()):
        beta = corr.beta_deg[j]
        ok = corr.mask[:, j]
        if not ok.any():
            ax.set_title(f"beta = {beta:g} deg   (not measured)", fontsize=8)
            continue
        t = corr.tan_eps[ok]
        rc = corr.r[ok, j] * 1e4
        band = 2.0 * u[ok, j] * 1e4
        ax.fill_between(t, rc - band, rc + band, color="C0", alpha=0.25, lw=0)
        for k, p in enumerate(sc.parts):
            okp = p.measured.mask[:, j]
            ax.plot(p.measured.tan_eps[okp], p.measured.r[okp, j] * 1e4, markers[k % len(markers)] + "--",
                    color=f"C{k + 1}", ms=3, lw=0.8)
        ax.plot(t, rc, "-", color="C0", lw=1.6)
        ax.set_title(f"beta = {beta:g} deg", fontsize=8)
        _style_beta_panel(ax, j)
    handles = [plt.Line2D([], [], color=f"C{k + 1}", marker=markers[k % len(markers)], ls="--", ms=3,
                          label=f"measured by {p.name}") for k, p in enumerate(sc.parts)]
    handles += [plt.Line2D([], [], color="C0", lw=1.6, label="corrected (one table from all instruments)"),
                plt.matplotlib.patches.Patch(color="C0", alpha=0.25, label="corrected +- 2 u (about 95 %)")]
    fig.suptitle(f"{' + '.join(p.measured.name for p in sc.parts)}: one surface, {len(sc.parts)} instruments, one "
                 "corrected table", fontsize=11, y=0.99)
    lines = [f"{p.name:>12}: " + _functional_text(p.before) + "  (as measured)" for p in sc.parts]
    lines.append(f"{'corrected':>12}: " + _functional_text(sc.after))
    fig.text(0.5, 0.962, "\n".join(lines), ha="center", va="top", fontsize=8.5, family="monospace")
    fig.legend(handles=handles, loc="upper center", ncol=len(handles), fontsize=9, bbox_to_anchor=(0.5, 0.9),
               frameon=False)
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.05, top=0.86, wspace=0.22, hspace=0.3)
    return fig


def draw_joint_map(sc):
    """k_A of every instrument and the relative u of the corrected table, as maps.

    Constrained layout keeps each colour bar's label clear of the next panel's axis label, and the
    panels are tall enough (JOINT_MAP_PANEL_IN) for the cell numbers at JOINT_MAP_CELL_FONT pt to be
    read at the PNG's 100 dpi (trial 10 D13: 4.5 pt was ~6 px high and the labels overlapped)."""
    from roadgonio.plots import _plt, draw_table_map
    plt = _plt()
    n = len(sc.parts)
    w, h = JOINT_MAP_PANEL_IN
    fig, axes = plt.subplots(1, n + 1, figsize=(w * (n + 1), h), layout="constrained")
    fs = JOINT_MAP_CELL_FONT
    for ax, p in zip(axes, sc.parts):
        k = p.k_a[np.isfinite(p.k_a)]
        wide = float(k.max() / k.min()) > 1.5
        draw_table_map(ax, p.k_a, label="k_A (measured / true)", fontsize=fs, tick_fontsize=8, log=wide,
                       fmt="{:.2f}" if wide else "{:.3f}")
        ax.set_title(f"{p.name}: k_A (its corrected table = measured / k_A)", fontsize=11)
    uu = np.full(sc.corrected.r.shape, np.nan)
    uu[sc.corrected.mask] = 100.0 * sc.budget.u_rel()
    draw_table_map(axes[-1], uu, label="relative standard uncertainty (%)", centre=None, log=False, fmt="{:.1f}",
                   fontsize=fs, tick_fontsize=8)
    import textwrap
    axes[-1].set_title("\n".join(textwrap.wrap("u of the one corrected table (%): " + ", ".join(sc.budget.components),
                                                 90)), fontsize=11)
    fig.get_layout_engine().set(w_pad=0.15, wspace=0.04)
    return fig


#: Size (inches) of one panel of the joint correction_map.png (a 580-cell table: 20 x 29 cells) and
#: the font (pt) of its cell numbers: at 100 dpi a cell is ~45 x 37 px and "0.978" ~30 x 10 px.
JOINT_MAP_PANEL_IN = (11.5, 12.5)
JOINT_MAP_CELL_FONT = 7.0


#: What each column of a joint correction's correct_cells.csv holds (``<instrument>``: each instrument's
#: name; user audit, session 39: the joint route's correct.json defined none of its columns).
JOINT_CELL_COLUMNS = {
    "tan_eps": CELL_COLUMNS["tan_eps"], "beta_deg": CELL_COLUMNS["beta_deg"],
    "r_corrected_x1e4": "the one corrected r x 1e4 (all instruments together)",
    "u_corrected_x1e4": CELL_COLUMNS["u_corrected_x1e4"], "u_rel_total": CELL_COLUMNS["u_rel_total"],
    "u_rel_<component>": CELL_COLUMNS["u_rel_<component>"],
    # not CELL_COLUMNS' "(the rest: r_over_k_a)": a joint file has no such column (user audit, session 42)
    "w_model": "weight of the fitted surface's own value in r_corrected (the rest: the instruments' "
               "r_corrected_<instrument>)",
    "r_measured_<instrument>_x1e4": "that instrument's measured r x 1e4 (empty where it did not measure)",
    "k_a_<instrument>": "that instrument's k_A under its calibration (every digit)",
    "r_corrected_<instrument>_x1e4": "that instrument's r_measured / k_a x 1e4",
    "residual_over_u_<instrument>": "(simulated - measured) / u of the fit for that instrument",
    "dlnk_a_dlnf_unobserved_<instrument>": CELL_COLUMNS["dlnk_a_dlnf_unobserved"] + ", for that instrument",
}

_JOINT_PER_INSTRUMENT = ("r_measured_{}_x1e4", "k_a_{}", "r_corrected_{}_x1e4", "residual_over_u_{}",
                         "dlnk_a_dlnf_unobserved_{}")


def _joint_cells_head(sc) -> list[str]:
    """The columns of a joint correction's correct_cells.csv (:func:`joint_cells_csv`; correct.json
    defines them)."""
    head = ["tan_eps", "beta_deg", "r_corrected_x1e4", "u_corrected_x1e4", "u_rel_total"] \
        + [f"u_rel_{c}" for c in sc.budget.components]
    if sc.model_weight is not None:
        head += ["w_model"]
    for p in sc.parts:
        head += [t.format(p.name) for t in _JOINT_PER_INSTRUMENT[:4]]
        if p.unobserved_sensitivity is not None:
            head += [_JOINT_PER_INSTRUMENT[4].format(p.name)]
    return head


def _joint_column_definitions(sc) -> dict[str, str]:
    per = {t.format(p.name): t.format("<instrument>") for p in sc.parts for t in _JOINT_PER_INSTRUMENT}
    return _column_definitions(_joint_cells_head(sc), JOINT_CELL_COLUMNS, per)


def joint_cells_csv(sc) -> str:
    """Per cell of the corrected table: the corrected r and u, each budget component, and per
    instrument its measured r, k_A, corrected r and residual (NaN where it did not measure)."""
    corr = sc.corrected
    m = corr.mask
    ii, jj = np.nonzero(m)
    comps = list(sc.budget.components)
    u_comp = {c: sc.budget.u_rel(c) for c in comps}
    u_tot = sc.budget.u_rel()
    head = _joint_cells_head(sc)
    buf = io.StringIO()
    buf.write("# " + corr.source + "\n")
    buf.write(",".join(head) + "\n")
    for k, (i, j) in enumerate(zip(ii, jj)):
        row = [f"{corr.tan_eps[i]:g}", f"{corr.beta_deg[j]:g}", f"{corr.r[i, j] * 1e4:.6g}",
               f"{sc.u_corrected[i, j] * 1e4:.4g}", f"{u_tot[k]:.4g}"] + [f"{u_comp[c][k]:.3g}" for c in comps]
        if sc.model_weight is not None:
            row.append(f"{sc.model_weight[i, j]:.4g}")
        for p in sc.parts:
            row += [f"{p.measured.r[i, j] * 1e4:.6g}", _k_text(p.k_a[i, j]), f"{p.corrected.r[i, j] * 1e4:.6g}",
                    f"{p.residual[i, j]:.3g}"]
            if p.unobserved_sensitivity is not None:
                row.append(f"{p.unobserved_sensitivity[i, j]:.4g}")
        buf.write(",".join("" if v == "nan" else v for v in row) + "\n")
    return buf.getvalue()


def _joint_doc(sc, plots: bool, files: dict[str, str]) -> dict[str, Any]:
    return {"summary": sc.summary(), "provenance": sc.provenance, "files": files,
            "definitions": {
                "corrected": _corrected_definition(sc, joint=True),
                "u": "standard uncertainty (k = 1) of the corrected table; relative components add with correlations "
                     "(corrected_corr.csv)",
                "k_a_<instrument>": "each instrument's k_A under its calibration (correct_cells.csv)",
                "residual_over_u": "(simulated - measured) / u of the fit, per instrument",
                "S1": "r(beta 0, tan 2) / r(beta 0, tan 0)", "Q0": "CIE 144 average luminance coefficient (sr^-1)",
                "correct_cells.csv": _joint_column_definitions(sc)}}


def write_surface_correction(sc, out_dir: str | Path, *, plots: bool = True) -> list[Path]:
    """Write a correction through one or several instruments
    (:class:`roadgonio.correction.outside.SurfaceCorrection`), together or not at all: corrected.csv,
    corrected_u.csv, corrected.rtb, correct.json, correct_cells.csv (every instrument's k_A, measured
    and corrected values and residuals), corrected_corr.csv, and the pictures before_after.png,
    correction_map.png, residual_map.png, correction_surface.png."""
    files = {"corrected": FILES["corrected"], "u": FILES["u"], "rtb": FILES["rtb"], "json": FILES["json"],
             "cells": FILES["cells"], "correlation": FILES["correlation"]}
    if not has_rtb(sc.corrected):
        del files["rtb"]
    if plots:
        files.update({k: FILES[k] for k in PICTURES})
    with OutputGroup(out_dir, replaces=REPLACES) as group:
        paths = [group.text(FILES["corrected"], sc.corrected.to_csv_text()),
                 group.text(FILES["u"], u_csv_text(sc)),
                 group.json(FILES["json"], _joint_doc(sc, plots, files)),
                 group.text(FILES["cells"], joint_cells_csv(sc)),
                 group.text(FILES["correlation"], _correlation_text(sc.corrected, sc.budget, sc.corrected))]
        if "rtb" in files:
            paths.insert(2, group.text(FILES["rtb"], sc.corrected.to_rtb_text()))
        if plots:
            paths.append(_group_figure(group, FILES["picture"], draw_joint_before_after(sc)))
            paths.append(_group_figure(group, FILES["map"], draw_joint_map(sc)))
            paths.append(_group_figure(group, FILES["residuals"], draw_residual_map(sc)))
            paths.append(_group_figure(group, FILES["surface"], draw_surface_map(sc)))
    return paths


def _correlation_text(table, budget, corrected) -> str:
    """corrected_corr.csv: the format ``road --corr`` reads (:func:`roadgonio.surface.rtable.read_cell_correlation`),
    the correlation of ``table``'s cells, its first line naming the ``corrected`` table as corrected_u.csv's does
    (``road`` checks that it goes with that table)."""
    ii, jj = np.nonzero(table.mask)
    return correlation_text([(table.tan_eps[i], table.beta_deg[j]) for i, j in zip(ii, jj)], budget.correlation(),
                            table=header_line(corrected))
