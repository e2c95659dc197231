"""Pictures shared by the commands (matplotlib, Agg backend, written atomically)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from roadgonio.fileio import atomic_savefig
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plain_colorbar_labels(cb) -> None:
    """Plain numbers on a colour bar (a log scale would otherwise print 9x10^-1)."""
    from matplotlib import ticker
    cb.ax.yaxis.set_major_formatter(ticker.FormatStrFormatter("%.3g"))
    cb.ax.yaxis.set_minor_formatter(ticker.FormatStrFormatter("%.2g"))


def draw_table_map(ax, values: np.ndarray, *, label: str, centre: float | None = 1.0, log: bool = True,
                   fmt: str = "{:.2f}", text=None, fontsize: float = 6.5, tick_fontsize: float | None = None,
                   tan_eps=TAN_EPS_GRID, beta_deg=BETA_GRID_DEG):
    """Draw an r-table-shaped map (rows tan eps, columns beta) on ``ax`` with its colour bar;
    returns the image. Cells show ``fmt.format(value)`` or ``text(i, j)``; blank (NaN) cells stay
    white. ``centre`` puts a diverging colour map's midpoint at that value (k_A = 1: no aperture
    effect); ``log`` uses a logarithmic colour scale (k_A spans 0.3 ... 5)."""
    plt = _plt()
    from matplotlib import colors
    v = np.asarray(values, dtype=np.float64)
    finite = v[np.isfinite(v)]
    if finite.size:
        lo, hi = float(finite.min()), float(finite.max())
        if centre is not None:
            if log and lo > 0:
                span = max(abs(np.log10(lo / centre)), abs(np.log10(hi / centre)), 1e-3)
                norm = colors.LogNorm(vmin=centre / 10 ** span, vmax=centre * 10 ** span)
            else:
                span = max(abs(lo - centre), abs(hi - centre), 1e-6)
                norm = colors.Normalize(vmin=centre - span, vmax=centre + span)
            cmap = plt.get_cmap("RdBu_r")
        else:
            norm = colors.LogNorm(vmin=lo, vmax=hi) if (log and lo > 0) else colors.Normalize(vmin=lo, vmax=hi)
            cmap = plt.get_cmap("viridis")
    else:
        norm, cmap = colors.Normalize(0, 1), plt.get_cmap("viridis")
    im = ax.imshow(np.ma.masked_invalid(v), cmap=cmap, norm=norm, aspect="auto", interpolation="nearest")
    ax.set_xticks(range(len(beta_deg)), [f"{b:g}" for b in beta_deg], fontsize=tick_fontsize)
    ax.set_yticks(range(len(tan_eps)), [f"{t:g}" for t in tan_eps], fontsize=tick_fontsize)
    ax.set_xlabel("beta (deg)")
    ax.set_ylabel("tan eps")
    for i, j in zip(*np.nonzero(np.isfinite(v))):
        rgba = cmap(norm(v[i, j]))
        lum = 0.299 * rgba[0] + 0.587 * rgba[1] + 0.114 * rgba[2]
        ax.text(j, i, text(i, j) if text is not None else fmt.format(v[i, j]), ha="center", va="center",
                fontsize=fontsize, color="white" if lum < 0.45 else "black")
    cb = ax.figure.colorbar(im, ax=ax, fraction=0.035, pad=0.02)
    cb.set_label(label)
    plain_colorbar_labels(cb)
    return im


def table_map(values: np.ndarray, path: str | Path, *, title: str, label: str, centre: float | None = 1.0,
              fmt: str = "{:.2f}", log: bool = True, annotate: bool = True,
              tan_eps=TAN_EPS_GRID, beta_deg=BETA_GRID_DEG, subtitle: str = "") -> Path:
    """An r-table-shaped map like the paper's Figure 4 (:func:`draw_table_map`) as a PNG."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(12, 10))
    draw_table_map(ax, values, label=label, centre=centre, log=log, fmt=fmt,
                   text=None if annotate else (lambda i, j: ""), tan_eps=tan_eps, beta_deg=beta_deg)
    ax.set_title(title + (f"\n{subtitle}" if subtitle else ""), fontsize=11)
    fig.tight_layout()
    out = atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return out
