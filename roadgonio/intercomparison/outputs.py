"""The outputs of ``roadgonio intercompare``: intercompare.nc, the CSV summaries and the pictures.

``intercompare.nc`` (CF-style attributes, units; provenance in ``attrs["provenance"]``):

* ``truth`` (tan_eps, beta): r of the surface at the nominal geometry, sr^-1;
* ``r_reported``, ``u_stated`` (scenario, participant, realisation, tan_eps, beta): what each
  participant reports and the standard uncertainty it states;
* ``k_a_nominal`` (participant, tan_eps, beta): its instrument's k_A at the nominal geometry, and
  ``k_a_nominal_u``: that value's standard uncertainty from the k_A backend (the standard error, or a
  quadrature's error bound / sqrt 3);
* ``reference_value``, ``u_reference_value``, ``tau2`` (scenario, consensus, realisation, tan_eps,
  beta): the weighted mean, Mandel-Paule and DerSimonian-Laird consensus;
* ``birge_ratio``, ``consistent`` (scenario, realisation, tan_eps, beta);
* ``d``, ``U_d``, ``E_n`` (scenario, reference, participant, realisation, tan_eps, beta): degrees of
  equivalence w.r.t. each consensus and the truth (float32 on disk, computed in float64).

Cells outside the comparison's cell set are NaN. ``intercompare.csv``: one row per scenario and
participant (repeatability, stated u, error against the truth, share of |E_n| <= 1 per reference
with its standard error over realisations) and one per scenario for the comparison (Birge ratio,
share of consistent cells, error of each consensus against the truth, tau). ``sensitivity.csv``:
the ranking of the characteristics. ``validation.csv``: the frozen correction factor against the
full corrections (figures of merit per realisation with both on the same realisations, their
means over the realisations, the mean paired difference and the standard errors; its header row only when fewer than two realisations have every
participant's full correction). ``correlation.csv``: per pair of participants the correlation of their
errors over the realisations beside the one their stated covariance declares. Pictures: ``en_map_declared.png``, ``en_map_all_corrected.png``
(median E_n against the weighted mean per cell and participant), ``specular_row.png`` (degrees of
equivalence with U along beta = 0), ``sensitivity.png`` (the ranking) and ``compatibility.png``.
"""
from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np


#: The columns of validation.csv (its header also when no realisation allows the check). Each figure is
#: computed per realisation and its mean over the realisations is given (``*_mean``, the figure's
#: name ending ``_per_realisation``): intercompare.csv's figures of the same root name pool the cells
#: of every realisation instead, so they differ (audit 21: 0.2876 % there, 0.2765 % here)
VALIDATION_COLUMNS = ("figure", "participant", "realisations", "full_mean", "frozen_mean", "difference_mean",
                      "difference_se", "full_mean_se")
#: The columns of correlation.csv (its header also when too few realisations give a correlation).
CORRELATION_COLUMNS = ("scenario", "participant_a", "participant_b", "realisations", "simulated_median",
                       "simulated_p05", "simulated_p95", "stated_median", "stated_p05", "stated_p95")

SCENARIO_TITLE = {"declared": "as declared", "all_corrected": "every participant corrects (roadgonio correct --reference self)"}


def output_files() -> tuple[str, ...]:
    """Every file ``roadgonio intercompare`` writes: a run removes those it does not write this time
    (``--no-plots``, a scenario without E_n), so an earlier run's picture never stays beside the new
    results (audit 22)."""
    from roadgonio.intercomparison.simulate import FROZEN, SCENARIOS
    return ("intercompare.nc", "intercompare.csv", "sensitivity.csv", "validation.csv", "correlation.csv",
            "intercompare.json", *(f"en_map_{s}.png" for s in (*SCENARIOS, FROZEN)), "specular_row.png",
            "sensitivity.png", "compatibility.png")


def write_outputs(run, out_dir: str | Path, *, plots: bool = True) -> list[Path]:
    """intercompare.nc, intercompare.csv, sensitivity.csv, intercompare.json and the pictures,
    together or not at all (:class:`roadgonio.fileio.OutputGroup`; the journal stays outside)."""
    from roadgonio.fileio import OutputGroup
    ds = run.dataset
    out_dir = Path(out_dir)
    summ = json.loads(ds.attrs["summary_json"])
    sens = json.loads(ds.attrs["sensitivity_json"])
    valid = json.loads(ds.attrs.get("validation_json", "[]"))
    corr = json.loads(ds.attrs.get("correlation_json", "[]"))
    with OutputGroup(out_dir, replaces=output_files()) as g:
        files = [write_netcdf(ds, g.path("intercompare.nc")),
                 g.text("intercompare.csv", rows_csv(summ)), g.text("sensitivity.csv", rows_csv(sens)),
                 g.text("validation.csv", rows_csv(valid, VALIDATION_COLUMNS)), g.text("correlation.csv", rows_csv(corr, CORRELATION_COLUMNS)),
                 g.json("intercompare.json", {"notes": json.loads(ds.attrs.get("notes_json", "[]")),
                                              "summary": summ, "sensitivity": sens, "validation": valid,
                                              "correlation": corr,
                                              "seconds": json.loads(ds.attrs.get("seconds", "{}")),
                                              "provenance": json.loads(ds.attrs["provenance"])})]
        if plots:
            for scen in ds.scenario.values.tolist():
                if np.isfinite(ds["E_n"].sel(scenario=scen)).any():
                    files.append(plot_en_maps(ds, str(scen), g.path(f"en_map_{scen}.png")))
            files.append(plot_specular_row(ds, g.path("specular_row.png")))
            files.append(plot_sensitivity(sens, g.path("sensitivity.png")))
            files.append(plot_compatibility(summ, g.path("compatibility.png")))
    return [out_dir / Path(f).name for f in files]


def write_netcdf(ds, path: Path) -> Path:
    """intercompare.nc by the one netCDF writer (:func:`roadgonio.fileio.write_netcdf`)."""
    from roadgonio.fileio import write_netcdf as write
    return write(ds, path)


def read_intercomparison(path: str | Path):
    """Open an ``intercompare.nc`` (:func:`roadgonio.fileio.read_netcdf`)."""
    from roadgonio.fileio import read_netcdf
    return read_netcdf(path)


def rows_csv(rows: Sequence[dict[str, Any]], columns: Sequence[str] = ()) -> str:
    """CSV text of ``rows`` with a header row: ``columns`` first, then any other key in the order
    met."""
    keys: list[str] = list(columns)
    for r in rows:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


# ----------------------------------------------------------------------------------------------
# Pictures
# ----------------------------------------------------------------------------------------------

def _colours(n: int):
    from matplotlib import colormaps
    cmap = colormaps["tab10"]
    return [cmap(i % 10) for i in range(n)]


def _draw_en_map(ax, med: np.ndarray, tan_eps, beta, labels, limit: float = 5.0):
    """One participant's map of median E_n: a fixed diverging scale -limit ... +limit (clipped), the
    cells where |E_n| <= 1 light, the median value printed in every cell."""
    from matplotlib import colormaps, colors
    norm = colors.Normalize(vmin=-limit, vmax=limit)
    cmap = colormaps["RdBu_r"]
    im = ax.imshow(np.ma.masked_invalid(np.clip(med, -limit, limit)), cmap=cmap, norm=norm, aspect="auto",
                   interpolation="nearest")
    ax.set_xticks(range(len(beta)), [f"{b:g}" for b in beta], fontsize=6.5)
    ax.set_yticks(range(len(tan_eps)), [f"{t:g}" for t in tan_eps], fontsize=6.5)
    ax.set_xlabel("beta (deg)")
    ax.set_ylabel("tan eps")
    rgba = np.asarray(cmap(norm(np.clip(np.nan_to_num(med), -limit, limit))))
    for i, j in zip(*np.nonzero(np.isfinite(med))):
        v = med[i, j]
        dark = 0.299 * rgba[i, j, 0] + 0.587 * rgba[i, j, 1] + 0.114 * rgba[i, j, 2] < 0.45
        labels.add(ax, float(j), float(i), f"{v:.0f}" if abs(v) >= 9.5 else f"{v:.1f}",
                   (255, 255, 255) if dark else (0, 0, 0), 5.0)
    return im


def plot_en_maps(ds, scenario: str, path: Path) -> Path:
    """Median over the realisations of E_n against the weighted mean, per cell and participant
    (one colour scale for all, clipped at +-5; the numbers are the medians)."""
    import warnings
    from roadgonio.plots import CellLabels, new_figure, save_figure
    names = ds.participant.values.tolist()
    P = len(names)
    ncol = 2 if P > 1 else 1
    nrow = (P + ncol - 1) // ncol
    fig = new_figure((9.0 * ncol, 7.6 * nrow))
    labels = CellLabels()
    en = ds["E_n"].sel(scenario=scenario, reference="weighted_mean")
    im = None
    for p, name in enumerate(names):
        ax = fig.add_subplot(nrow, ncol, p + 1)
        v = en.sel(participant=name).values.astype(np.float64)          # (realisation, tan_eps, beta)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)              # cells outside the comparison: NaN
            med = np.nanmedian(v, axis=0)
        fin = np.isfinite(v)
        share = float(np.mean(np.abs(v[fin]) <= 1.0)) if fin.any() else float("nan")
        im = _draw_en_map(ax, med, ds.tan_eps.values, ds.beta.values, labels)
        ax.set_title(f"{name}: |E_n| <= 1 in {100 * share:.0f} % of cells x realisations", fontsize=10)
    fig.suptitle(f"Median E_n = d_i / U(d_i) against the weighted mean: {SCENARIO_TITLE.get(scenario, scenario)}",
                 fontsize=12)
    fig.subplots_adjust(left=0.05, right=0.9, bottom=0.05, top=0.93, wspace=0.15, hspace=0.15)
    if im is not None:
        cax = fig.add_axes((0.92, 0.25, 0.015, 0.5))
        cb = fig.colorbar(im, cax=cax)
        cb.set_label("median E_n (clipped at +-5); |E_n| <= 1: compatible")
    return save_figure(fig, path, dpi=90, labels=labels)


def plot_specular_row(ds, path: Path) -> Path:
    """Degrees of equivalence along beta = 0 relative to the truth: against the weighted mean (what
    the pilot of a comparison sees, top) and against the truth (what only a simulation knows,
    bottom); median d_i with the median U(d_i) as error bar, and the 5-95 % spread of d_i over the
    realisations (band)."""
    from roadgonio.plots import new_figure, save_figure
    scen = [s for s in ds.scenario.values.tolist() if np.isfinite(ds["d"].sel(scenario=s)).any()]
    refs = [("weighted_mean", "against the weighted mean"), ("truth", "against the truth")]
    width = 7.0 * len(scen)
    fig = new_figure((width, 5.2 * len(refs)))
    names = ds.participant.values.tolist()
    cols = _colours(len(names))
    t = ds.tan_eps.values
    truth = ds["truth"].sel(beta=0.0).values
    ok = np.isfinite(truth)
    k = float(ds.attrs.get("coverage_factor", 2.0))
    for b, (ref, ref_text) in enumerate(refs):
        for a, s in enumerate(scen):
            ax = fig.add_subplot(len(refs), len(scen), b * len(scen) + a + 1)
            for p, name in enumerate(names):
                d = ds["d"].sel(scenario=s, reference=ref, participant=name, beta=0.0).values.astype(float)
                U = ds["U_d"].sel(scenario=s, reference=ref, participant=name, beta=0.0).values.astype(float)
                good = np.isfinite(d[:, ok]).all(axis=1)
                d, U = d[good][:, ok], U[good][:, ok]
                if not len(d):
                    continue
                rel = 100 * d / truth[ok]
                Urel = 100 * U / truth[ok]
                x = t[ok] + (p - (len(names) - 1) / 2) * 0.06
                lo, hi = np.percentile(rel, [5, 95], axis=0)
                ax.fill_between(x, lo, hi, color=cols[p], alpha=0.18, lw=0)
                ax.errorbar(x, np.median(rel, axis=0), yerr=np.median(Urel, axis=0), fmt="o-", ms=3, lw=1,
                            capsize=2, color=cols[p], label=name)
            ax.axhline(0.0, color="k", lw=0.7)
            ax.set_xlabel("tan eps (beta = 0, the specular row)")
            ax.set_ylabel(f"d_i / r_true (% of r) {ref_text}")
            ax.set_title(f"{SCENARIO_TITLE.get(s, s)}: {ref_text}\n(points: median d_i; bars: median U(d_i), "
                         f"k = {k:g}; band: 5-95 % of d_i over the realisations)", fontsize=9)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8, loc="best")
    # 0.95 in on the left: the tick labels (-17.5) and the y label (0.08 of one 7 in column cut it off)
    fig.subplots_adjust(left=0.95 / width, right=1.0 - 0.15 / width, bottom=0.06, top=0.94, wspace=0.25,
                        hspace=0.35)
    return save_figure(fig, path, dpi=95)


def plot_sensitivity(sens: Sequence[dict[str, Any]], path: Path, top: int = 6) -> Path:
    """Per scenario and participant, the characteristics ranked by how much idealising each one
    lowers the RMS of its own error x_i / r_true - 1 (its degree of equivalence against the truth;
    error bars: standard error over the realisations)."""
    from roadgonio.plots import new_figure, save_figure, text_width_in
    scen = list(dict.fromkeys(r["scenario"] for r in sens))
    parts = list(dict.fromkeys(r["participant"] for r in sens))
    ncol, nrow = max(len(scen), 1), max(len(parts), 1)
    # margins in inches from the longest label (a fixed fraction cut them off in one column)
    label_in = text_width_in([r["label"] for r in sens], 7, dpi=95) + 0.25
    bar_in, right_in = 4.8, 0.25
    width = ncol * (label_in + bar_in) + right_in
    fig = new_figure((width, 2.4 * nrow + 1.0))
    for a, s in enumerate(scen):
        for b, name in enumerate(parts):
            ax = fig.add_subplot(max(len(parts), 1), max(len(scen), 1), b * len(scen) + a + 1)
            rows = [r for r in sens if r["scenario"] == s and r["participant"] == name][:top]
            if not rows:
                ax.set_axis_off()
                continue
            y = np.arange(len(rows))[::-1]
            num = lambda v: np.nan if v is None else float(v)          # noqa: E731 (an SE of one realisation is None)
            ax.barh(y, [num(r["drop_pct"]) for r in rows], xerr=[num(r["drop_se_pct"]) for r in rows], color="tab:blue",
                    alpha=0.8, capsize=2)
            ax.set_yticks(y, [r["label"] for r in rows], fontsize=7)
            ax.axvline(0.0, color="k", lw=0.6)
            ax.set_title(f"{name} ({SCENARIO_TITLE.get(s, s).split(' (')[0]}): RMS error "
                         f"{rows[0]['rms_error_vs_truth_pct']:.2f} %", fontsize=8)
            ax.tick_params(axis="x", labelsize=7)
            if b == len(parts) - 1:
                ax.set_xlabel("drop of RMS(x_i / r_true - 1) when idealised (% of r)", fontsize=8)
    fig.suptitle("Why they disagree: each characteristic idealised in turn (error against the truth)", fontsize=11)
    fig.subplots_adjust(left=label_in / width, right=1.0 - right_in / width, bottom=0.06, top=0.93,
                        wspace=label_in / bar_in, hspace=0.55)
    return save_figure(fig, path, dpi=95)


def compared_scenarios(summary: Sequence[dict[str, Any]]) -> list[str]:
    """The scenarios of the summary rows that some realisation compared (its comparison row has
    realisations > 0), in their order."""
    every = list(dict.fromkeys(r["scenario"] for r in summary))
    compared = {r["scenario"] for r in summary if r["participant"] == "ALL" and r.get("realisations")}
    return [s for s in every if s in compared]


def plot_compatibility(summary: Sequence[dict[str, Any]], path: Path) -> Path:
    """Share of cells with |E_n| <= 1 against the weighted mean, per participant, as declared and
    with every participant correcting; and the share of consistent cells of the comparison. A
    scenario no realisation compared (no corrections) has no bars and no legend entry: the title
    says so."""
    from roadgonio.plots import new_figure, save_figure
    every = list(dict.fromkeys(r["scenario"] for r in summary))
    parts = [r["participant"] for r in summary if r["scenario"] == every[0] and r["participant"] != "ALL"]
    scen = compared_scenarios(summary)
    missing = [s for s in every if s not in scen]
    fig = new_figure((8.5, 4.8))
    ax = fig.add_subplot(1, 1, 1)
    w = 0.8 / max(len(scen), 1)
    cols = ["tab:red", "tab:green", "tab:blue"]
    labels = parts + ["all compatible\n(every participant)", "consistent cells\n(chi2 test)"]
    for a, s in enumerate(scen):
        rows = {r["participant"]: r for r in summary if r["scenario"] == s}
        vals = [rows.get(p, {}).get("share_En_le_1_weighted_mean", np.nan) for p in parts]
        errs = [rows.get(p, {}).get("share_En_le_1_weighted_mean_se", np.nan) for p in parts]
        allr = rows.get("ALL", {})
        vals += [allr.get("share_all_compatible_weighted_mean", np.nan), allr.get("share_consistent_cells", np.nan)]
        errs += [allr.get("share_all_compatible_weighted_mean_se", np.nan), allr.get("share_consistent_cells_se", np.nan)]
        x = np.arange(len(labels)) + (a - (len(scen) - 1) / 2) * w
        v, e = 100 * np.array(vals, dtype=float), 100 * np.array(errs, dtype=float)
        ax.bar(x, v, w, color=cols[a % 3], alpha=0.85, label=SCENARIO_TITLE.get(s, s))
        has = np.isfinite(v) & np.isfinite(e)            # no SE (one realisation): no bar, not a bar of 0 (audit)
        if has.any():
            ax.errorbar(x[has], v[has], yerr=e[has], fmt="none", ecolor="k", elinewidth=1, capsize=2)
    ax.set_xticks(np.arange(len(labels)), labels, fontsize=8)
    ax.set_ylabel("share of cells (%)")
    ax.set_ylim(0, 122)
    ax.set_yticks(range(0, 101, 20))
    ax.set_title("Compatibility: |E_n| <= 1 against the weighted mean (mean over realisations)"
                 + "".join(f"\n{SCENARIO_TITLE.get(s, s).split(' (')[0]}: not compared (no realisation has every "
                           "participant's table)" for s in missing), fontsize=10)
    if scen:
        ax.legend(fontsize=8, loc="upper center", ncol=2)
    ax.grid(True, axis="y", alpha=0.3)
    fig.subplots_adjust(left=0.09, right=0.98, bottom=0.17, top=0.9 - 0.04 * len(missing))
    return save_figure(fig, path, dpi=100)
