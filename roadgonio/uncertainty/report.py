"""Reports of an uncertainty run: JSON dict, CSV, PNG maps, summary lines."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from roadgonio.errors import EXIT_INCONCLUSIVE, count
from roadgonio.uncertainty.run import UncertaintyResult
from roadgonio.uncertainty.spec import INPUTS
from roadgonio.uncertainty.statistics import ROUND_OFF_REL

# ----------------------------------------------------------------------------------------------
# Results: summary, files, pictures
# ----------------------------------------------------------------------------------------------

OUTPUT_NAMES = ("Q0", "S1")


def gum_verdict(validation: Mapping[str, np.ndarray], k: int) -> str:
    """The JCGM 101 section 8 verdict of output ``k``: "validated", "not validated" or "not judged"
    (the Monte Carlo interval's ends too noisy to decide: :func:`~roadgonio.uncertainty.gum.gum_validation`)."""
    if validation["validated"][k]:
        return "validated"
    return "not validated" if validation["judged"][k] else "not judged"


def _validated_or_none(validation: Mapping[str, np.ndarray], k: int) -> bool | None:
    """uncertainty.json's ``gum_validated``: true, false, or null where not judged."""
    return bool(validation["validated"][k]) if validation["judged"][k] else None


def verdict_counts(validation: Mapping[str, np.ndarray], n: int) -> str:
    """``validated in 30, not validated in 12, not judged in 354 of 396 cells``."""
    ok = int(np.sum(validation["validated"][:n]))
    judged = int(np.sum(validation["judged"][:n]))
    text = f"validated in {ok}, not validated in {judged - ok}"
    if judged < n:
        text += f", not judged in {n - judged}"
    return text + f" of {n} cells"


def _mc_se(c, key: str, k: int) -> float:
    """The Monte Carlo's standard error ``key`` (mean_se, u_se: run.py's batch_noise) of output ``k``;
    NaN where the case was not given one."""
    v = c.mc.get(key)
    return float("nan") if v is None else float(v[k])


def at_round_off(c, k: int) -> bool:
    """Output ``k`` of case ``c`` is not changed by the errors: its u is round-off (:data:`ROUND_OFF_REL`)."""
    return bool(abs(c.mc["u"][k]) <= ROUND_OFF_REL * abs(c.mc["mean"][k]))


def result_dict(res: UncertaintyResult, *, cells: bool = True) -> dict[str, Any]:
    """JSON-ready results (per-cell arrays when ``cells``) with provenance."""
    n = len(res.cells)
    d: dict[str, Any] = {"trials": res.trials, "seed": res.seed, "coverage": res.coverage, "n_dig": res.n_dig,
                         "adaptive": res.adaptive, "seconds": res.seconds, "provenance": res.provenance,
                         "cases": {}}
    for name, c in res.cases.items():
        case: dict[str, Any] = {}
        for k, label in ((n, "Q0"), (n + 1, "S1")):
            case[label] = {"nominal": c.nominal[k], "mean": c.mc["mean"][k], "u": c.mc["u"][k],
                           "symmetric_interval": [c.mc["sym_low"][k], c.mc["sym_high"][k]],
                           "shortest_interval": [c.mc["short_low"][k], c.mc["short_high"][k]],
                           "gum_u": c.gum["u"][k], "gum_interval": [c.gum["low"][k], c.gum["high"][k]],
                           "gum_validated": _validated_or_none(c.validation, k),
                           "d_low": c.validation["d_low"][k], "d_high": c.validation["d_high"][k],
                           "delta": c.validation["delta"][k], "mc_end_noise": c.validation["end_noise"][k],
                           "mc_mean_se": _mc_se(c, "mean_se", k), "mc_u_se": _mc_se(c, "u_se", k),
                           "gum_contributions": dict(zip(INPUTS, c.gum["contribution"][:, k].tolist()))}
        with np.errstate(divide="ignore", invalid="ignore"):
            u_rel = c.mc["u"][:n] / np.abs(c.mc["mean"][:n])
        case["cells_summary"] = {"u_rel_max": float(np.nanmax(u_rel)), "u_rel_median": float(np.nanmedian(u_rel)),
                                 "gum_validated_fraction": float(np.mean(c.validation["validated"][:n])),
                                 "gum_not_judged": int(np.sum(~c.validation["judged"][:n])),
                                 "u_mc_over_u_gum_max": float(np.nanmax(c.mc["u"][:n] / c.gum["u"][:n]))
                                 if np.all(c.gum["u"][:n] > 0) else None}
        if cells:
            case["cells"] = {"tan_eps": res.cells.tan_eps, "beta_deg": res.cells.beta_deg,
                             "nominal": c.nominal[:n], "mean": c.mc["mean"][:n], "u": c.mc["u"][:n],
                             "sym_low": c.mc["sym_low"][:n], "sym_high": c.mc["sym_high"][:n],
                             "short_low": c.mc["short_low"][:n], "short_high": c.mc["short_high"][:n],
                             "gum_u": c.gum["u"][:n],
                             "gum_validated": [_validated_or_none(c.validation, k) for k in range(n)]}
        d["cases"][name] = case
    if res.surrogate is not None:
        ap = res.cases.get("aperture")
        u_rel = None
        if ap is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                u_rel = ap.mc["u"][:n] / np.abs(ap.mc["mean"][:n])
        d["surrogate"] = res.surrogate.summary(u_rel, res.cells)
    return d


#: cells.csv's first line: its units (the r-tables beside it hold r x 1e4; trial 12 D8).
CELLS_UNITS = ("# r_nominal, mean, u, the intervals and gum_u/low/high in sr^-1 (r itself, not r x 1e4 as in the "
               "<case>_mean.csv and <case>_u.csv tables); u_rel a fraction; on the Q0 rows in sr^-1, on the S1 rows "
               "dimensionless; mc_mean_se and mc_u_se the Monte Carlo's standard errors of mean and u (from 20 "
               "batches of the trials), in the unit of mean")


def cells_csv_text(res: UncertaintyResult) -> str:
    n = len(res.cells)
    lines = [CELLS_UNITS, "case,tan_eps,beta_deg,r_nominal,mean,u,u_rel,sym_low,sym_high,short_low,short_high,"
             "gum_u,gum_low,gum_high,gum_validated,d_low,d_high,delta,mc_end_noise,mc_mean_se,mc_u_se"]
    labels = [f"{t:g},{b:g}" for t, b in zip(res.cells.tan_eps, res.cells.beta_deg)] + ["Q0,", "S1,"]
    for name, c in res.cases.items():
        for k in range(n + 2):
            mean = c.mc["mean"][k]
            u_rel = c.mc["u"][k] / abs(mean) if mean != 0 else float("nan")
            vals = [c.nominal[k], mean, c.mc["u"][k], u_rel, c.mc["sym_low"][k], c.mc["sym_high"][k],
                    c.mc["short_low"][k], c.mc["short_high"][k], c.gum["u"][k], c.gum["low"][k], c.gum["high"][k]]
            v = c.validation
            lines.append(f"{name},{labels[k]}," + ",".join(f"{x:.8g}" for x in vals)
                         + f",{int(bool(v['validated'][k])) if v['judged'][k] else ''},{v['d_low'][k]:.4g},"
                         f"{v['d_high'][k]:.4g},{v['delta'][k]:.4g},{v['end_noise'][k]:.4g},"
                         f"{_mc_se(c, 'mean_se', k):.4g},{_mc_se(c, 'u_se', k):.4g}")
    return "\n".join(lines) + "\n"


#: The files an uncertainty run may write (``--fresh`` removes an earlier run's).
OUTPUT_FILES = ("uncertainty.json", "cells.csv", "no_aperture_mean.csv", "no_aperture_u.csv", "aperture_mean.csv",
                "aperture_u.csv", "u_rel_no_aperture.png", "u_rel_aperture.png", "q0_s1_hist.png")


def table_header(case: str, trials: int, seed: int, sample_name: str, key: str) -> str:
    """The header line of ``<case>_<key>.csv`` (key ``mean`` or ``u``): it names the sample, so that
    ``roadgonio road --u`` can tell which table a u belongs to
    (:data:`roadgonio.surface.rtable.UNCERTAINTY_HEADER` reads it back)."""
    label = {"mean": "mean r x 1e4", "u": "standard uncertainty u(r) x 1e4"}[key]
    return f"roadgonio uncertainty: {case.replace('_', ' ')}, {trials} trials, seed {seed}, sample {sample_name}: {label}"


def write_results(res: UncertaintyResult, out_dir: str | Path, *, sample_name: str = "sample",
                  plots: bool = True, figures=None, fingerprint: str | None = None) -> list[Path]:
    """Write uncertainty.json, cells.csv, r-table CSVs of the mean and u per case, and the pictures,
    all or none (:class:`roadgonio.fileio.OutputGroup`: a full disk leaves the folder as it was).
    ``figures`` (:class:`roadgonio.plotproc.FigureProcess`) draws the pictures in a helper process;
    uncertainty.json carries the run's ``fingerprint`` (:func:`roadgonio.fileio.check_run_folder`)."""
    from roadgonio.fileio import OutputGroup
    from roadgonio.plotproc import InProcess
    figures = figures or InProcess()
    from roadgonio.surface.rtable import R_SCALE, grid_csv_text
    out = Path(out_dir)
    with OutputGroup(out, replaces=OUTPUT_FILES) as g:
        doc = result_dict(res)
        if fingerprint is not None:
            doc["fingerprint"] = fingerprint
        written = [g.json("uncertainty.json", doc), g.text("cells.csv", cells_csv_text(res))]
        n = len(res.cells)
        for name, c in res.cases.items():
            for key in ("mean", "u"):
                g.text(f"{name}_{key}.csv", grid_csv_text(res.cells.to_grid(c.mc[key][:n]),
                                                          table_header(name, res.trials, res.seed, sample_name, key),
                                                          scale=R_SCALE))
                written.append(out / f"{name}_{key}.csv")
        if plots:
            maps = figures.call("roadgonio.uncertainty.report:plot_uncertainty_maps", res, g.stage)
            written.extend(out / p.name for p in maps)
            written.append(out / figures.call("roadgonio.uncertainty.report:plot_q0_s1", res,
                                              g.path("q0_s1_hist.png")).name)
            for p in written:
                g.path(p.name)      # every picture is part of the group
    return written


def plot_uncertainty_maps(res: UncertaintyResult, out: Path) -> list[Path]:
    from roadgonio.plots import table_map
    n = len(res.cells)
    paths = []
    for name, c in res.cases.items():
        with np.errstate(divide="ignore", invalid="ignore"):
            u_rel = 100.0 * c.mc["u"][:n] / np.abs(c.mc["mean"][:n])
        title = (f"Relative standard uncertainty u(r)/r (%), {name.replace('_', ' ')}: "
                 f"{res.trials} trials, seed {res.seed}")
        sub = (f"GUM first-order result (JCGM 101 s. 8, {count(res.n_dig, 'digit')}): {verdict_counts(c.validation, n)}; "
               f"Q0 = {c.mc['mean'][n]:.4g} +- {c.mc['u'][n]:.2g}, S1 = {c.mc['mean'][n + 1]:.4g} +- {c.mc['u'][n + 1]:.2g}")
        paths.append(table_map(res.cells.to_grid(u_rel), out / f"u_rel_{name}.png", title=title,
                               label="u(r)/r (%)", centre=None, log=False, fmt="{:.2f}", subtitle=sub))
    return paths


def plot_q0_s1(res: UncertaintyResult, path: Path) -> Path:
    """Histograms of Q0 and S1 (each case) with both coverage intervals and the GUM normal pdf."""
    from roadgonio.fileio import atomic_savefig
    from roadgonio.plots import _plt
    plt = _plt()
    n = len(res.cells)
    cases = list(res.cases.items())
    fig, axes = plt.subplots(len(cases), 2, figsize=(12, 4.2 * len(cases)), squeeze=False)
    for row, (name, c) in enumerate(cases):
        for col, (k, label, samples) in enumerate(((n, "Q0 (sr$^{-1}$)", c.q0_samples),
                                                   (n + 1, "S1", c.s1_samples))):
            ax = axes[row][col]
            s = samples[np.isfinite(samples)]
            if at_round_off(c, k):
                # an output the errors do not change (S1 under a distance error alone: both its cells
                # scale alike) spreads over round-off, where 80 bins cannot be drawn: the run crashed
                # after its work and wrote nothing (user audit, session 41). Said in words instead
                ax.axvline(c.nominal[k], color="k", lw=0.8, ls=":", label=f"nominal {c.nominal[k]:.5g}")
                ax.text(0.5, 0.5, f"{label.split(' ')[0]} = {c.mc['mean'][k]:.6g}\nnot changed by these errors\n"
                        f"(u at round-off, {abs(c.mc['u'][k]):.1g})", transform=ax.transAxes, ha="center",
                        va="center", fontsize=10, bbox={"facecolor": "white", "edgecolor": "none"})
                ax.set_title(f"{label.split(' ')[0]}, {name.replace('_', ' ')}", fontsize=10)
                ax.set_xlabel(label)
                ax.set_yticks([])
                continue
            ax.hist(s, bins=80, density=True, color="0.75", edgecolor="0.6", linewidth=0.3, label="Monte Carlo")
            y, u = c.gum["y"][k], c.gum["u"][k]
            if u > 0:
                xs = np.linspace(min(s.min(), y - 4 * u), max(s.max(), y + 4 * u), 400)
                ax.plot(xs, np.exp(-0.5 * ((xs - y) / u) ** 2) / (u * math.sqrt(2 * math.pi)), "C0-", lw=1.3,
                        label=f"GUM normal, u = {u:.3g}")
            top = ax.get_ylim()[1]
            for lo, hi, style, lab, h in ((c.mc["sym_low"][k], c.mc["sym_high"][k], "C3--", "symmetric", 0.30),
                                          (c.mc["short_low"][k], c.mc["short_high"][k], "C2-", "shortest", 0.22)):
                ax.plot([lo, hi], [h * top, h * top], style, lw=2.2,
                        label=f"{100 * res.coverage:g} % {lab}: [{lo:.5g}, {hi:.5g}]")
            ax.axvline(c.nominal[k], color="k", lw=0.8, ls=":", label=f"nominal {c.nominal[k]:.5g}")
            valid = gum_verdict(c.validation, k).replace("not validated", "NOT validated")
            ax.set_title(f"{label.split(' ')[0]}, {name.replace('_', ' ')}: mean {c.mc['mean'][k]:.5g}, "
                         f"u = {c.mc['u'][k]:.3g} (GUM {valid})", fontsize=10)
            ax.set_xlabel(label)
            ax.set_ylabel("probability density")
            ax.legend(fontsize=7.5, loc="best", framealpha=0.85)
            ax.ticklabel_format(axis="x", style="sci", scilimits=(-3, 4), useOffset=False)
            # at most 5 ticks: S1's six-digit labels ran into each other (user audit, session 37)
            from matplotlib.ticker import MaxNLocator
            ax.xaxis.set_major_locator(MaxNLocator(nbins=5))
    fig.suptitle(f"Distributions of Q0 and S1 over {res.trials} Monte Carlo trials (seed {res.seed})", fontsize=11)
    fig.tight_layout()
    p = atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return p


#: The exit status of ``roadgonio uncertainty --adaptive`` when the run stopped at --max-trials before
#: the JCGM 101 7.9 rule was met: inconclusive, as ``roadgonio validate``'s 3 (the results are written).
NOT_CONVERGED_EXIT_STATUS = EXIT_INCONCLUSIVE


def not_converged_line(res: UncertaintyResult) -> str | None:
    """One line saying which target an adaptive run did not meet and at what cap (None when it met it,
    or was not adaptive): ``roadgonio uncertainty`` prints it on stderr and exits with
    :data:`NOT_CONVERGED_EXIT_STATUS`."""
    a = res.adaptive
    if not a or a["converged"]:
        return None
    unstable = sum(a.get("unstable_outputs") or [])
    outputs = (len(res.cells) + 2) * len(a.get("unstable_outputs") or [])      # the cells, Q0 and S1 per case
    worst = max(a.get("worst_ratio") or [math.nan])
    return (f"NOT CONVERGED: the adaptive run stopped at its cap of {a['max_trials']} trials (--max-trials; "
            f"{a['batches']} batches of {a['batch']}) before the mean, u and {100 * res.coverage:g} % interval ends of "
            f"every output were stable to {a['n_dig']} significant digits of u (JCGM 101 7.9): {unstable} of "
            f"{outputs} outputs were not (worst 2s/delta = {worst:.2f}); the results are written; raise --max-trials or lower --digits")


def summary_lines(res: UncertaintyResult) -> list[str]:
    n = len(res.cells)
    lines = [f"{res.trials} trials (seed {res.seed}), {n} cells, coverage {100 * res.coverage:g} %"]
    if res.adaptive:
        a = res.adaptive
        lines.append(f"adaptive (JCGM 101 7.9, {count(a['n_dig'], 'digit')}): {a['batches']} batches of {a['batch']}, "
                     + ("converged" if a["converged"] else f"NOT converged at the cap of {a['max_trials']} trials "
                        f"(worst 2s/delta = {max(a['worst_ratio'] or [0]):.2f}; about "
                        f"{max(a['worst_ratio'] or [1]) ** 2:.0f}x more trials would be needed: raise --max-trials "
                        f"(memory grows with trials x cells) or ask for fewer --digits)"))
    for name, c in res.cases.items():
        with np.errstate(divide="ignore", invalid="ignore"):
            u_rel = c.mc["u"][:n] / np.abs(c.mc["mean"][:n])
        lines.append(f"{name.replace('_', ' ')}: u(r)/r median {100 * np.nanmedian(u_rel):.3g} %, max "
                     f"{100 * np.nanmax(u_rel):.3g} %; GUM {verdict_counts(c.validation, n)}")
        # outputs of round-off are not judged either, but not for noise: no "more --trials" for them
        if np.any(~c.validation["judged"][:n + 2] & ~c.validation["round_off"][:n + 2]):
            # what can still be done: an adaptive run is on already, and 1 digit is the fewest (user audit,
            # session 41: the advice named both after an adaptive run at --digits 1)
            # (an adaptive run stops once the ends' 2 s is within the tolerance, where a GUM difference
            # near the tolerance still cannot be decided: a longer fixed run narrows the ends' noise)
            ways = (["more --trials", "--adaptive"] if not res.adaptive else
                    ["a longer run without --adaptive (more --trials than its " + f"{res.trials})"])
            if res.n_dig > 1:
                ways.append("fewer --digits")
            lines.append(f"  not judged: the Monte Carlo interval's ends are too noisy to decide against a tolerance of "
                         f"{res.n_dig} digit(s) of u (their 2 s from 20 batches, JCGM 101 7.9.4): "
                         + (", ".join(ways[:-1]) + ", or " + ways[-1] if len(ways) > 1 else ways[0]))
        for k, label in ((n, "Q0"), (n + 1, "S1")):
            if at_round_off(c, k):
                # the errors do not change it: a u of round-off, which the GUM validation would judge
                lines.append(f"  {label}: {c.mc['mean'][k]:.5g}, not changed by these errors (u at round-off, "
                             f"{c.mc['u'][k]:.1g})")
                continue
            u_se = _mc_se(c, "u_se", k) / c.mc["u"][k] if c.mc["u"][k] > 0 else float("nan")
            lines.append(f"  {label}: {c.mc['mean'][k]:.5g} u = {c.mc['u'][k]:.3g} (Monte Carlo SE of u "
                         f"{100 * u_se:.2g} %) [{c.mc['sym_low'][k]:.5g}, {c.mc['sym_high'][k]:.5g}] "
                         f"(GUM u = {c.gum['u'][k]:.3g}, {gum_verdict(c.validation, k)})")
    if res.surrogate is not None:
        s = result_dict(res, cells=False).get("surrogate", {})
        error = ("its error not measured (--validation 0: no held-out exact k_A)" if s["rel_err_max"] is None else
                 f"error vs held-out exact k_A: max {100 * s['rel_err_max']:.3g} %, rms {100 * s['rel_err_rms']:.3g} %"
                 + (f", max/u(r) = {s['err_over_u_max']:.2g}" if "err_over_u_max" in s else ""))
        lines.append(f"k_A surrogate: {s['exact_evaluations']} exact evaluations in {s['seconds']:.0f} s; {error}")
        rel_u = s.get("backend_rel_u_max")
        if rel_u is not None and rel_u > 0:
            # audit 22: the exact tables' own Monte Carlo error moved the nominal values, means and
            # intervals with --seed by up to about one u, and was said only in the JSON
            from roadgonio.engines.registry import BACKENDS
            info = BACKENDS.get((s.get("backend") or {}).get("backend", ""))
            # audit 27: a deterministic backend's bound was called "its Monte Carlo error" and its "seed"
            # (user audit, session 37: "the surrogate's error above" when --validation 0 measured none)
            what = ("its Monte Carlo error, common to every trial: not in u or the intervals"
                    + ("; the surrogate's error above is against tables of the same seed" if s["rel_err_max"] is not None
                       else "") if info is None or info.seeded else
                    "its error bound / sqrt(3), a rectangular distribution (a cell stopped at its cap: its estimate "
                    "whole), common to every trial: not in u or the intervals")
            lines.append(f"k_A backend: relative standard uncertainty up to {100 * rel_u:.2g} % per cell ({what}; "
                         "--rel-se lowers it)")
        if s.get("not_converged"):
            # audit 27: in the JSON only
            lines.append(f"note: {s['not_converged']} of the {s['exact_evaluations']} exact k_A evaluations stopped "
                         "before their backend's target (not converged): the surrogate's error above is against them")
        note = s.get("err_over_u_note")
        if note:
            worst = "; ".join(f"tan eps {w['tan_eps']:g}, beta {w['beta_deg']:g}: {w['err_over_u']:.2g} u(r)"
                              for w in note["worst"])
            lines.append(f"note: the surrogate's error exceeds {note['threshold']:g} u(r) in {note['cells_above']} of "
                         f"{n} cells (worst: {worst}); the aperture case's u(r) there does not include it")
    return lines
