"""The picture helper process (roadgonio.plotproc) and the fast table map (roadgonio.plots)."""
from __future__ import annotations

import numpy as np
import pytest

from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
from roadgonio.plotproc import FigureProcess, InProcess
from helpers import _pixels


def _values(seed=0):
    rng = np.random.default_rng(seed)
    v = 0.5 + rng.random((len(TAN_EPS_GRID), len(BETA_GRID_DEG)))
    v[3, 4] = np.nan                       # a blank cell stays white
    return v


def test_child_process_draws_the_same_picture_as_this_process(tmp_path):
    v = _values()
    kw = dict(title="k_A test", label="k_A")
    InProcess().call("table_map", v, tmp_path / "here.png", **kw)
    with FigureProcess() as fp:
        assert fp.proc is not None
        fp.call("table_map", v, tmp_path / "there.png", **kw)
        assert fp.fallbacks == 0           # drawn by the child, not by the fallback
    a, b = _pixels(tmp_path / "here.png"), _pixels(tmp_path / "there.png")
    assert a.shape == b.shape
    assert np.array_equal(a, b)


def test_dead_child_falls_back_to_this_process(tmp_path):
    v = _values(1)
    with FigureProcess() as fp:
        fp.proc.kill()
        fp.proc.wait()
        fp.call("table_map", v, tmp_path / "x.png", title="t", label="k")
        assert fp.fallbacks == 1
    assert (tmp_path / "x.png").stat().st_size > 10_000


def test_error_in_the_child_is_raised_by_the_fallback(tmp_path):
    """A picture that cannot be written is the command's error, exactly as without the helper."""
    from roadgonio.errors import InputError
    (tmp_path / "a-file").write_text("not a folder")
    with FigureProcess() as fp:
        with pytest.raises(InputError, match="a-file"):
            fp.call("table_map", _values(), tmp_path / "a-file" / "x.png", title="t", label="k")
        assert fp.fallbacks == 1
    with pytest.raises(AttributeError):
        InProcess().call("no_such_picture")


def test_uncertainty_pictures_drawn_by_the_child_equal_those_drawn_here(tmp_path):
    """`roadgonio uncertainty` sends its whole result to the figure process: it must pickle, and
    the child's pictures are those this process draws."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.model import RoadModel
    from roadgonio.uncertainty import parse_sigma_spec, run_uncertainty, write_results
    res = run_uncertainty(RoadModel.lambert(), load_instrument("portable"), parse_sigma_spec("eps_deg=0.01"),
                          trials=2000, seed=1, aperture=False, progress=False)
    write_results(res, tmp_path / "here", plots=True)
    with FigureProcess() as fp:
        write_results(res, tmp_path / "there", plots=True, figures=fp)
        assert fp.fallbacks == 0
    pngs = sorted(p.name for p in (tmp_path / "here").glob("*.png"))
    assert pngs == sorted(p.name for p in (tmp_path / "there").glob("*.png")) and len(pngs) >= 2
    for name in pngs:
        if name.startswith("u_rel"):     # the Agg+Pillow maps are deterministic pixel for pixel
            assert np.array_equal(_pixels(tmp_path / "here" / name), _pixels(tmp_path / "there" / name))
