"""The Mitsuba k_A backend's checks that run before Mitsuba: the LLVM version, unknown settings, a
surface it cannot render."""
from __future__ import annotations

import pytest

from roadgonio.errors import BackendError, InputError

from helpers import ROAD, preset


def test_llvm_older_than_16_is_refused():
    from roadgonio.engines.mitsuba import check_llvm_version
    with pytest.raises(BackendError, match="LLVM >= 16"):
        check_llvm_version((15, 0, 6))
    check_llvm_version((16, 0, 0))
    check_llvm_version((19, 1, 7))


def test_unknown_setting_is_an_input_error():
    from roadgonio.engines.mitsuba.backend import make_backend
    with pytest.raises(InputError, match="unknown setting"):
        make_backend(preset("portable"), ROAD, samples_per_pixel=3)
    with pytest.raises(InputError, match="per-cell renderer.*first_pass"):
        make_backend(preset("portable"), ROAD, spp=16)


def test_a_surface_only_numpy_evaluates_is_refused_by_name():
    """A surface that evaluates in numpy only (the bench's table truth) reached the scene's BSDF and
    failed with an AttributeError deep in it; it is refused up front, naming it and the backends that
    can. (Surfaces that evaluate over Dr.Jit arrays, the microfacet truth among them, are rendered:
    tests/plugin/test_surface_bsdf.py.)"""
    from roadgonio.engines.mitsuba.backend import make_backend
    from roadgonio.surface.truths import make_truth
    with pytest.raises(InputError, match="'table' is a TableTruth.*reference, numpy-mc"):
        make_backend(preset("portable"), make_truth("table"))


@pytest.mark.parametrize("name", ["collimated", "portable"])
def test_render_png_of_a_point_field_says_so_and_draws_the_point_footprint(monkeypatch, tmp_path, name):
    """render.png of the collimated preset (zero field, pupil, source) drew its view as a +-1 deg
    disc, the white footnote on the pale disc, and a legend entry for a footprint of zero size."""
    import numpy as np

    import roadgonio.fileio
    from roadgonio.engines.mitsuba.images import _png
    from roadgonio.instrument.optics import footprint_boundary
    figs = []
    monkeypatch.setattr(roadgonio.fileio, "atomic_savefig", lambda fig, path, **kw: figs.append(fig))
    inst = preset(name)
    fx, fy = footprint_boundary(inst)
    window = (float(fx.min()) - 1e-3, float(fx.max()) + 1e-3, float(fy.min()) - 1e-3, float(fy.max()) + 1e-3)
    view = np.full((16, 16, 3), 0.006)
    info = {"k_a_estimate": 1.0, "k_a_se": 0.0, "sample": "R3", "tan_eps": 12.0, "beta_deg": 180.0}
    _png(tmp_path / "render.png", inst, view, np.full((8, 32), 0.08), window, (fx, fy), info)
    top, bottom = figs[0].axes[:2]
    texts = " ".join(t.get_text() for t in top.texts)
    point = name == "collimated"
    assert ("point field: no image" in texts) == point and (not top.images) == point
    if not point:                                    # the footnote on a dark box, readable on a bright view
        foot = next(t for t in top.texts if "near edge" in t.get_text())
        assert foot.get_bbox_patch() is not None
    # every legend entry of the illuminance panel is drawn: a point footprint as a marker
    for line in bottom.get_lines():
        if line.get_label().startswith("detector footprint"):
            x, y = line.get_data()
            assert (np.ptp(x) > 0 or np.ptp(y) > 0) or line.get_marker() not in ("None", None, "")
            assert ("(a point)" in line.get_label()) == point
