"""Pictures shared by the commands (matplotlib, Agg backend, written atomically)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from roadgonio.errors import count
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def tick_labels(values, digits: int = 3, max_digits: int = 12) -> list[str]:
    """Plain labels (``%.Ng``) of tick ``values`` with the fewest significant digits, at least
    ``digits``, that tell every two different values apart: a colour bar over 0.998 ... 1.002 (one
    k_A cell, or an instrument with k_A = 1) read 1, 1, 1, 1, 0.999, 0.999, 0.998 at 3 digits."""
    vals = [float(v) for v in values]
    distinct = len(set(vals))
    n = digits
    while n < max_digits and len({f"{v:.{n}g}" for v in vals}) < distinct:
        n += 1
    return [f"{v:.{n}g}" for v in vals]


def _distinct_formatter(digits: int):
    """A matplotlib tick formatter giving the labels of :func:`tick_labels` (it formats the ticks
    of an axis together, so it can add digits until they differ)."""
    from matplotlib import ticker

    class DistinctFormatter(ticker.Formatter):
        def __call__(self, x, pos=None):
            return f"{x:.{digits}g}"

        def format_ticks(self, values):
            return tick_labels(values, digits)

    return DistinctFormatter()


def text_width_in(texts, fontsize: float, dpi: float = 100) -> float:
    """Width in inches of the widest of ``texts`` at ``fontsize`` points when drawn at ``dpi``
    (matplotlib's own text layout, without drawing a figure; hinting makes it depend on the dpi by
    up to 10 %): to size a margin that holds long tick labels."""
    from matplotlib.backends.backend_agg import RendererAgg
    from matplotlib.font_manager import FontProperties
    renderer = RendererAgg(8, 8, dpi)
    font = FontProperties(size=fontsize)
    widths = [renderer.get_text_width_height_descent(str(t), font, ismath=False)[0] for t in texts]
    return max(widths, default=0.0) / dpi


#: The colour of blank cells (no value: not computed, not tabulated) on table maps, as fit.png has it:
#: on a diverging map white would read as the centre value (k_A = 1).
BLANK_COLOUR = "0.85"


def plain_colorbar_labels(cb) -> None:
    """Plain numbers on a colour bar (a log scale would otherwise print 9x10^-1), with as many
    digits as make the labels differ (:func:`tick_labels`). A log colour bar spanning less than a
    decade gets round ticks over its whole range: its decade and 2 ... 9 ticks would leave a range
    like 0.71 ... 1.41 labelled only at 0.8, 0.9 and 1, nothing above 1."""
    from matplotlib import colors, ticker
    norm = cb.norm
    if isinstance(norm, colors.LogNorm) and norm.vmin is not None and norm.vmin > 0 and norm.vmax < 10 * norm.vmin:
        ticks = [t for t in ticker.MaxNLocator(nbins=8).tick_values(norm.vmin, norm.vmax)
                 if norm.vmin <= t <= norm.vmax]
        cb.set_ticks(ticks)
        cb.minorticks_off()
    cb.ax.yaxis.set_major_formatter(_distinct_formatter(3))
    cb.ax.yaxis.set_minor_formatter(_distinct_formatter(2))


class CellLabels:
    """Text of many table cells, drawn onto the rendered picture by Pillow instead of as one
    matplotlib ``Text`` artist per cell: 580 artists take 1.3 s to lay out and draw (measured,
    2-core machine), Pillow's glyph rendering a few milliseconds. Positions are data coordinates of
    their axes, converted to pixels after matplotlib has drawn the figure (:func:`save_figure`)."""

    def __init__(self):
        self.items: list[tuple[Any, float, float, str, tuple, float]] = []

    def add(self, ax, x: float, y: float, text: str, color, fontsize: float) -> None:
        self.items.append((ax, x, y, text, color, fontsize))


def _font(size_px: float):
    from PIL import ImageFont
    import matplotlib
    path = Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans.ttf"
    return ImageFont.truetype(str(path), size=max(int(round(size_px)), 1))


def save_figure(fig, path: str | Path, *, dpi: float = 110, labels: CellLabels | None = None) -> Path:
    """Render ``fig`` with Agg at ``dpi``, draw ``labels`` on it with Pillow, and write the PNG
    atomically (:func:`roadgonio.fileio.atomic_write`)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image, ImageDraw
    from roadgonio.fileio import atomic_write
    fig.set_dpi(dpi)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    img = Image.fromarray(np.asarray(canvas.buffer_rgba())).convert("RGB")
    if labels is not None and labels.items:
        draw = ImageDraw.Draw(img)
        fonts: dict[float, Any] = {}
        height = img.size[1]
        for ax, x, y, text, color, fontsize in labels.items:
            font = fonts.get(fontsize)
            if font is None:
                font = fonts[fontsize] = _font(fontsize * dpi / 72.0)
            px, py = ax.transData.transform((x, y))
            draw.text((float(px), height - float(py)), text, fill=color, font=font, anchor="mm")
    return atomic_write(path, lambda p: img.save(p, format="PNG", compress_level=3))   # 4x faster than 6, 10 % larger


def new_figure(figsize=(12, 10)):
    """A matplotlib ``Figure`` without pyplot (no global figure manager; importing pyplot costs
    0.5 s of a command's start-up). Close nothing: it is garbage-collected."""
    from matplotlib.figure import Figure
    return Figure(figsize=figsize)


def draw_table_map(ax, values: np.ndarray, *, label: str, centre: float | None = 1.0, log: bool = True,
                   fmt: str = "{:.2f}", text=None, fontsize: float = 6.5, tick_fontsize: float | None = None,
                   tan_eps=TAN_EPS_GRID, beta_deg=BETA_GRID_DEG, labels: CellLabels | None = None,
                   grey_blanks: bool = False):
    """Draw an r-table-shaped map (rows tan eps, columns beta) on ``ax`` with its colour bar;
    returns the image. Cells show ``fmt.format(value)`` or ``text(i, j)``; blank (NaN) cells stay
    white, or with ``grey_blanks`` are :data:`BLANK_COLOUR` (the caller says what grey means). ``centre`` puts a diverging colour map's midpoint at that value (k_A = 1: no aperture
    effect); ``log`` uses a logarithmic colour scale (k_A spans 0.3 ... 5). With ``labels`` the
    cell texts are collected there for :func:`save_figure` (fast) instead of drawn as artists."""
    from matplotlib import colormaps, colors
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
            cmap = colormaps["RdBu_r"]
        else:
            norm = colors.LogNorm(vmin=lo, vmax=hi) if (log and lo > 0) else colors.Normalize(vmin=lo, vmax=hi)
            cmap = colormaps["viridis"]
    else:
        norm, cmap = colors.Normalize(0, 1), colormaps["viridis"]
    im = ax.imshow(np.ma.masked_invalid(v), cmap=cmap, norm=norm, aspect="auto", interpolation="nearest")
    if grey_blanks:
        ax.set_facecolor(BLANK_COLOUR)
    ax.set_xticks(range(len(beta_deg)), [f"{b:g}" for b in beta_deg], fontsize=tick_fontsize)
    ax.set_yticks(range(len(tan_eps)), [f"{t:g}" for t in tan_eps], fontsize=tick_fontsize)
    ax.set_xlabel("beta (deg)")
    ax.set_ylabel("tan eps")
    rgba_all = np.asarray(cmap(norm(np.where(np.isfinite(v), v, 1.0 if centre is None else centre))))
    for i, j in zip(*np.nonzero(np.isfinite(v))):
        rgba = rgba_all[i, j]        # one vectorised colour-map call (per cell: 1 ms each)
        dark = 0.299 * rgba[0] + 0.587 * rgba[1] + 0.114 * rgba[2] < 0.45       # white text on dark cells
        s = text(i, j) if text is not None else fmt.format(v[i, j])
        if not s:
            continue
        if labels is not None:
            labels.add(ax, float(j), float(i), s, (255, 255, 255) if dark else (0, 0, 0), fontsize)
        else:
            ax.text(j, i, s, ha="center", va="center", fontsize=fontsize, color="white" if dark else "black")
    cb = ax.figure.colorbar(im, ax=ax, fraction=0.035, pad=0.02)
    cb.set_label(label)
    plain_colorbar_labels(cb)
    if centre is not None and finite.size:
        centre_tick(cb, float(centre))
    return im


def centre_tick(cb, centre: float) -> None:
    """A tick at the diverging scale's centre (k_A = 1, which the label names) when the bar's ticks
    miss it (user audit, session 29: 0.84, 0.90, 0.96, 1.02 ... and no 1); ticks nearer to it than
    half their spacing are dropped so the labels do not run into each other."""
    lo, hi = sorted((float(cb.norm.vmin), float(cb.norm.vmax)))
    if not lo <= centre <= hi:
        return
    ticks = sorted(float(t) for t in cb.get_ticks() if lo <= t <= hi)
    if any(abs(t - centre) <= 1e-9 * max(1.0, abs(centre)) for t in ticks):
        return
    step = min((b - a for a, b in zip(ticks, ticks[1:])), default=hi - lo)
    cb.set_ticks(sorted([t for t in ticks if abs(t - centre) >= 0.5 * step] + [centre]))


def table_map(values: np.ndarray, path: str | Path, *, title: str, label: str, centre: float | None = 1.0,
              fmt: str = "{:.2f}", log: bool = True, annotate: bool = True,
              tan_eps=TAN_EPS_GRID, beta_deg=BETA_GRID_DEG, subtitle: str = "", blank: str | None = None) -> Path:
    """An r-table-shaped map like the paper's Figure 4 (:func:`draw_table_map`) as a PNG. With
    ``blank`` (e.g. "not computed") the cells without a value are grey and the title says so.

    Fixed margins instead of ``tight_layout`` (which renders the figure once more to measure it)
    and the cell numbers drawn by Pillow (:class:`CellLabels`): 0.5 s instead of 3.1 s for a
    580-cell table."""
    fig = new_figure((12, 10))
    ax = fig.add_axes((0.06, 0.06, 0.86, 0.86))
    labels = CellLabels()
    draw_table_map(ax, values, label=label, centre=centre, log=log, fmt=fmt,
                   text=None if annotate else (lambda i, j: ""), tan_eps=tan_eps, beta_deg=beta_deg,
                   labels=labels, grey_blanks=blank is not None)
    n_blank = int(np.sum(~np.isfinite(np.asarray(values, dtype=np.float64))))
    if blank is not None and n_blank:
        subtitle = (subtitle + "; " if subtitle else "") + f"grey: {blank} ({count(n_blank, 'cell')})"
    # lines wrapped to the figure's width (user audit, session 37: uncertainty's subtitle ran off the left edge)
    import textwrap
    text = "\n".join(textwrap.fill(line, TITLE_WRAP_CHARS) for line in (title, subtitle) if line)
    ax.set_title(text, fontsize=11)
    return save_figure(fig, path, dpi=110, labels=labels)


#: Characters per title line of :func:`table_map` (12 in at fontsize 11).
TITLE_WRAP_CHARS = 150
