"""Colour bars of the table maps (roadgonio.plots)."""
from __future__ import annotations

import numpy as np


def test_a_log_colour_bar_under_a_decade_has_ticks_over_its_whole_range():
    """k_A up to 1.41 (housed portable, walls 0.2): the bar (0.71 ... 1.41 about 1) had tick labels
    at 0.8, 0.9 and 1 only, none above 1."""
    from roadgonio.plots import _plt, draw_table_map
    plt = _plt()
    fig, ax = plt.subplots()
    v = np.array([[0.9, 1.0], [1.2, 1.41]])
    im = draw_table_map(ax, v, label="k_A", centre=1.0, log=True, tan_eps=[0, 1], beta_deg=[0, 2])
    cb = im.colorbar
    ticks = [t for t in cb.get_ticks() if cb.norm.vmin <= t <= cb.norm.vmax]
    lo, hi = cb.norm.vmin, cb.norm.vmax
    assert min(ticks) - lo < 0.2 * (hi - lo) and hi - max(ticks) < 0.2 * (hi - lo), (ticks, lo, hi)
    assert sum(t > 1.0 for t in ticks) >= 3
    fig.canvas.draw()
    labels = [t.get_text() for t in cb.ax.yaxis.get_ticklabels() if t.get_text()]
    assert "1.4" in labels and "1" in labels, labels
    plt.close(fig)


def test_a_k_a_colour_bar_has_a_tick_at_1():
    """User audit, session 29: ka.png of the housed portable (k_A 0.790 ... 1.201) had ticks 0.84, 0.90,
    0.96, 1.02 ... and none at 1, the value its label names ("1 = no aperture effect"). Now a tick at
    the centre, and none within half a tick spacing of it (labels that would overlap)."""
    from roadgonio.plots import _plt, draw_table_map
    plt = _plt()
    for v, log in ((np.array([[0.790, 0.95], [1.05, 1.201]]), True), (np.array([[0.79, 0.95], [1.05, 1.23]]), False)):
        fig, ax = plt.subplots()
        cb = draw_table_map(ax, v, label="k_A (1 = no aperture effect)", centre=1.0, log=log, tan_eps=[0, 1],
                            beta_deg=[0, 2]).colorbar
        ticks = sorted(t for t in cb.get_ticks() if cb.norm.vmin <= t <= cb.norm.vmax)
        assert any(abs(t - 1.0) < 1e-12 for t in ticks), ticks
        step = np.median(np.diff(ticks))
        assert all(abs(t - 1.0) >= 0.45 * step for t in ticks if abs(t - 1.0) > 1e-12), ticks
        fig.canvas.draw()
        assert "1" in [t.get_text() for t in cb.ax.yaxis.get_ticklabels()], ticks
        plt.close(fig)


def test_tick_labels_get_the_digits_that_tell_the_ticks_apart():
    """A one-cell k_A map (0.9976 ... 1.0024) had colour-bar labels 1, 1, 1, 1, 0.999, 0.999, 0.998."""
    from roadgonio.plots import tick_labels
    ticks = [0.998, 0.9985, 0.999, 0.9995, 1.0, 1.0005, 1.001]
    labels = tick_labels(ticks)
    assert len(set(labels)) == len(ticks), labels
    assert [float(x) for x in labels] == ticks
    assert tick_labels([0.8, 0.9, 1.0, 1.2]) == ["0.8", "0.9", "1", "1.2"]        # no digits added when not needed
    assert tick_labels([1.0, 1.0]) == ["1", "1"]                                  # equal values stay equal


def test_a_colour_bar_of_a_nearly_constant_k_a_has_distinct_tick_labels():
    from roadgonio.plots import _plt, draw_table_map
    plt = _plt()
    for v in (np.array([[0.99705, np.nan], [np.nan, np.nan]]), np.array([[1.0, 1.0], [np.nan, np.nan]])):
        fig, ax = plt.subplots()
        im = draw_table_map(ax, v, label="k_A", centre=1.0, log=True, tan_eps=[0, 1], beta_deg=[0, 2])
        fig.canvas.draw()
        labels = [t.get_text() for t in im.colorbar.ax.yaxis.get_ticklabels() if t.get_text()]
        assert len(labels) >= 3 and len(set(labels)) == len(labels), labels
        plt.close(fig)


def test_blank_cells_are_grey_not_white_like_k_a_1(tmp_path):
    """ka.png: cells not computed were white, the colour of k_A = 1 on the diverging map."""
    from PIL import Image
    from matplotlib import colors
    from roadgonio.plots import BLANK_COLOUR, table_map
    v = np.full((29, 20), np.nan)
    v[28, 19] = 0.997
    path = table_map(v, tmp_path / "ka.png", title="k_A", label="k_A", subtitle="1 cell", blank="not computed")
    img = np.asarray(Image.open(path).convert("RGB"))
    grey = np.round(255 * np.array(colors.to_rgb(BLANK_COLOUR)))
    h, w, _ = img.shape
    assert np.abs(img[int(0.3 * h), int(0.4 * w)] - grey).max() <= 2        # a blank cell mid-map
    from roadgonio.errors import count
    assert (count(1, "cell"), count(579, "cell")) == ("1 cell", "579 cells")


def test_the_measured_text_width_is_what_matplotlib_draws():
    """sensitivity.png sizes its left margin from text_width_in; a 72-dpi measure was 8 % short at
    95 dpi and cut the labels off."""
    from roadgonio.plots import new_figure, text_width_in
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    labels = ["misalignment alpha_deg (sigma 0.005)", "detector pupil (R_D/D_D = 0.0286 deg)", "x"]
    for dpi in (95, 110):
        fig = new_figure((5, 3))
        fig.set_dpi(dpi)
        canvas = FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        ax.set_yticks(range(3), labels, fontsize=7)
        canvas.draw()
        drawn = max(t.get_window_extent().width for t in ax.get_yticklabels()) / dpi
        assert abs(text_width_in(labels, 7, dpi=dpi) - drawn) < 0.01, (dpi, drawn)
