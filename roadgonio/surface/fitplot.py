"""The outputs of a fit (``roadgonio fit --out DIR``): model.json, residuals.csv and fit.png, the
picture of the table and the model as solid r-table surfaces (as in the paper's Figure 2: r over
beta and tan eps) with a map of the residuals in % of max r."""
from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from roadgonio.fileio import atomic_savefig


def plot_fit(result, path: str | Path) -> Path:
    """Write ``fit.png`` for a :class:`~roadgonio.surface.fit.FitResult`."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    table = result.table
    r_tab = table.r * 1e4
    r_mod = result.r_model * 1e4
    res = result.residual_pct
    tan = table.tan_eps
    beta = table.beta_deg
    B, T = np.meshgrid(beta, tan)
    zmax = float(np.nanmax([np.nanmax(r_tab), np.nanmax(r_mod)])) * 1.05

    fig = plt.figure(figsize=(16, 5.6))
    title = (f"{table.name}: model '{result.model.variant}'  -  max |dev| {result.max_dev_pct:.2f} %, "
             f"RMS {result.rms_dev_pct:.2f} % of max r ({table.r_max * 1e4:.4g} x 1e-4 sr^-1)")
    fig.suptitle(title, fontsize=12)
    for k, (data, label) in enumerate([(r_tab, f"table {table.name}"), (r_mod, "model")]):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        Z = np.ma.masked_invalid(data)
        ax.plot_surface(B, T, Z.filled(np.nan), cmap="viridis", vmin=0, vmax=zmax, rstride=1, cstride=1,
                        linewidth=0.2, edgecolor="k", antialiased=True)
        ax.set_xlabel("beta [deg]")
        ax.set_ylabel("tan eps")
        ax.set_zlabel("r x 1e4 [sr^-1]")
        ax.set_zlim(0, zmax)
        ax.set_title(label)
        ax.view_init(elev=28, azim=-128)
    ax = fig.add_subplot(1, 3, 3)
    lim = max(float(np.nanmax(np.abs(res))), 1e-6)
    im = ax.pcolormesh(np.arange(len(beta) + 1), np.arange(len(tan) + 1), np.ma.masked_invalid(res),
                       cmap="RdBu_r", norm=TwoSlopeNorm(0.0, -lim, lim), edgecolors="face")
    ax.set_xticks(np.arange(len(beta)) + 0.5)
    ax.set_xticklabels([f"{b:g}" for b in beta], rotation=90, fontsize=7)
    ax.set_yticks(np.arange(len(tan)) + 0.5)
    ax.set_yticklabels([f"{t:g}" for t in tan], fontsize=7)
    ax.set_xlabel("beta [deg]")
    ax.set_ylabel("tan eps")
    ax.invert_yaxis()
    ax.set_facecolor("0.85")
    i, j = np.unravel_index(np.nanargmax(np.abs(res)), res.shape)
    ax.plot(j + 0.5, i + 0.5, marker="o", mfc="none", mec="k", ms=9)
    ax.set_title(f"residual (model - table) in % of max r\nworst cell: tan {tan[i]:g}, beta {beta[j]:g} deg: "
                 f"{res[i, j]:+.1f} %  (grey = blank)", fontsize=9)
    fig.colorbar(im, ax=ax, label="% of max r", shrink=0.85)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    try:
        return atomic_savefig(fig, path)
    finally:
        plt.close(fig)


def residuals_csv(result) -> str:
    """The residuals of a fit, one tabulated cell per row: tan eps, beta, r of the table and of the
    model (x 1e4), the deviation in % of the table's maximum r."""
    t = result.table
    rm = result.r_model
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["tan_eps", "beta_deg", "r_table_x1e4", "r_model_x1e4", "dev_pct_of_max_r"])
    for i, te in enumerate(t.tan_eps):
        for j, b in enumerate(t.beta_deg):
            if not t.mask[i, j]:
                continue
            w.writerow([f"{te:g}", f"{b:g}", f"{t.r[i, j] * 1e4:.6g}", f"{rm[i, j] * 1e4:.6g}",
                        f"{result.residual_pct[i, j]:.4f}"])
    return out.getvalue()


#: The files a fit writes (``--fresh`` removes an earlier run's).
FIT_FILES = ("model.json", "residuals.csv", "fit.png")


def write_fit(result, out_dir: str | Path, *, plot: bool = True, fingerprint: str | None = None,
              provenance: dict | None = None) -> list[Path]:
    """model.json, residuals.csv and (``plot``) fit.png in ``out_dir``, all or none; model.json
    carries the run's ``fingerprint`` (:func:`roadgonio.fileio.check_run_folder`) and its
    ``provenance`` (:func:`roadgonio.provenance.provenance`)."""
    from roadgonio.fileio import OutputGroup
    out_dir = Path(out_dir)
    doc = result.model.to_json_dict()
    if fingerprint is not None:
        doc["fingerprint"] = fingerprint
    if provenance is not None:
        doc["provenance"] = provenance
    with OutputGroup(out_dir, replaces=FIT_FILES) as g:
        g.json("model.json", doc)
        g.text("residuals.csv", residuals_csv(result))
        if plot:
            plot_fit(result, g.path("fit.png"))
    return [out_dir / n for n in ("model.json", "residuals.csv", "fit.png")[:3 if plot else 2]]
