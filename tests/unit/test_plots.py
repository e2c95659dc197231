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
