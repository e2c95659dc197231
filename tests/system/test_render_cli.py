"""``roadgonio render``: files written, EXR readable, numbers consistent; bad input is one line."""
from __future__ import annotations

import json

import numpy as np
import pytest

from roadgonio.cli import main


def test_render_writes_exr_png_json(mi, tmp_path, capsys):
    out = tmp_path / "r"
    out.mkdir()                 # an earlier housed render's stray pictures, and a file of the user's
    for name in ("stray.png", "stray.exr", "notes.txt"):
        (out / name).write_text("earlier")
    rc = main(["render", "--instrument", "lab", "--sample", "lambert", "--tan-eps", "0", "--beta", "0",
               "--out", str(out), "--resolution", "32", "--spp", "4"])
    assert rc == 0
    info = json.loads((out / "render.json").read_text())
    assert abs(info["k_a_estimate"] - 1.0) < 1e-5           # Lambert: exactly 1 up to float32
    # without a housing there is no stray light and no _direct twin; every field is defined
    assert "ratio_direct" not in info and "stray" not in info
    assert {"signal_road", "signal_lambert", "ratio", "k_a_estimate"} <= set(info["definitions"])
    prov = info["provenance"]           # the common block, as in every result file
    assert prov["versions"]["mitsuba"] and prov["versions"]["mitsuba_variant"] == "llvm_ad_rgb"
    assert prov["instrument"]["source"]["radius_m"] == 0.005 and prov["settings"]["spp"] == 4
    import OpenEXR
    E = OpenEXR.File(str(out / "illuminance.exr")).channels()["E_h"].pixels
    assert E.dtype == np.float32
    # source overhead at 5 m, ~1 lx normal at the centre: E_h within 1 % over the small window
    assert abs(float(np.median(E)) - 1.0) < 0.01
    view = OpenEXR.File(str(out / "view.exr")).channels()["RGB"].pixels
    assert view.shape == (32, 32, 3) and view[0, 0, 1] == 0.0 and view[16, 16, 1] > 0  # outside/inside the field stop
    assert (out / "render.png").stat().st_size > 10_000
    assert "k_A ~" in capsys.readouterr().out
    # trial 10 D4: a render without stray light removes the earlier run's stray pictures, nothing else
    assert not (out / "stray.png").exists() and not (out / "stray.exr").exists()
    assert (out / "notes.txt").read_text() == "earlier"


def test_render_bad_input_is_one_line(tmp_path, capsys):
    rc = main(["render", "--instrument", "lab", "--sample", "lambert", "--tan-eps", "1", "--beta", "0",
               "--out", str(tmp_path), "--spp", "5"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--spp" in err[0]


def test_render_of_a_beam_cone_that_clips_the_footprint(mi, tmp_path):
    """(session 22) A hard cone that clips the footprint was refused by render as by ka; both now
    light the cell through the kabatch integrator, which applies the cone. The illuminance is 0
    outside the cone's spot and the render's k_A agrees with the float64 Monte Carlo within the
    combined SE."""
    import math
    from pathlib import Path

    from roadgonio.engines import make_backend
    from roadgonio.instrument.config import load_instrument
    from roadgonio.instrument.optics import beam_clips_cells
    from roadgonio.surface.sample import resolve_sample
    from tolerances import n_sigma
    text = (Path(__file__).resolve().parents[2] / "scenes" / "portable.toml").read_text()
    path = tmp_path / "cone.toml"
    path.write_text(text.replace("[source]\n", "[source]\nbeam_half_angle_deg = 5.0\n", 1))
    inst = load_instrument(str(path))
    assert inst.source.beam_half_angle_deg == 5.0 and beam_clips_cells(inst, [(1.0, 0.0)]).all()
    out = tmp_path / "r"
    assert main(["render", "--instrument", str(path), "--sample", "R3", "--tan-eps", "1", "--beta", "0",
                 "--out", str(out), "--resolution", "64", "--spp", "16", "-q"]) == 0
    info = json.loads((out / "render.json").read_text())
    # the float64 Monte Carlo applies the cone in its own statement (the quadrature does not converge
    # on the cone's jump here: no check); render's SE has the 15 degrees of freedom of its replicates
    q = make_backend("numpy-mc", inst, resolve_sample("R3").model, rel_se=1e-3, seed=2).compute([(1.0, 0.0)])[0]
    assert q.converged and info["k_a_estimate"] is not None
    assert abs(info["k_a_estimate"] - q.k_a) <= n_sigma(15) * math.hypot(info["k_a_se"], q.se)
    import OpenEXR
    exr = OpenEXR.File(str(out / "illuminance.exr"))
    E = exr.channels()["E_h"].pixels
    assert E.max() > 0 and (E == 0).mean() > 0.2        # the spot: lit inside the cone only
    # the EXR says what it holds without render.json (user audit, session 38: no window, units, instrument)
    h = exr.header()
    assert h["roadgonio_units"] == info["units"] and "lx per lx" in h["roadgonio_units"]
    assert h["roadgonio_cell"] == "tan eps 1, beta 0 deg" and h["roadgonio_instrument"] == inst.name
    w = info["illuminance_window_m"]
    assert np.allclose(h["roadgonio_window_m"], [*w["x"], *w["y"]], rtol=1e-6)


def _illuminance(out):
    """render.json, illuminance.exr's E_h (float64) and its pixels' centres (x along the columns, y down
    the rows from the window's y1) from the window render.json records."""
    import OpenEXR
    info = json.loads((out / "render.json").read_text())
    with OpenEXR.File(str(out / "illuminance.exr")) as f:
        E = np.asarray(f.channels()["E_h"].pixels, dtype=np.float64)
    (x0, x1), (y0, y1) = info["illuminance_window_m"]["x"], info["illuminance_window_m"]["y"]
    ny, nx = E.shape
    return info, E, (x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx, y1 - (np.arange(ny) + 0.5) * (y1 - y0) / ny)


def test_render_of_a_point_source_lights_as_i0_cos_theta(mi, tmp_path):
    """(session 40) R_S = 0 is the limit of a small Lambertian disc: I_0 cos theta about the source's
    axis (docs/conventions.md section 5). render lit the cell with Mitsuba's isotropic ``point``
    emitter (the k_A engine was mended in session 39), so the illuminance picture of a source 0.3 m
    above the sample was 1 / cos theta too bright off the axis (1.5x at the window's edge). The
    closed form of a point at height h straight above: E_h = I_0 (h / d) (h / d) / d^2, with render's
    I_0 = h^2 (~1 lx at the centre): E_h = (h / d)^4."""
    from pathlib import Path
    text = (Path(__file__).resolve().parents[2] / "scenes" / "portable.toml").read_text()
    text = text.replace("distance_m = 1.0\nradius_m = 0.025", "distance_m = 0.3\nradius_m = 0.0", 1)
    path = tmp_path / "point.toml"
    path.write_text(text)
    out = tmp_path / "r"
    assert main(["render", "--instrument", str(path), "--sample", "lambert", "--tan-eps", "0", "--beta", "0",
                 "--out", str(out), "--resolution", "16", "--spp", "4", "-q"]) == 0
    info, E, (x, y) = _illuminance(out)
    X, Y = np.meshgrid(x, y)
    h = 0.3
    ref = (h / np.sqrt(X ** 2 + Y ** 2 + h ** 2)) ** 4
    assert ref.min() < 0.5                      # the window reaches far off the axis: the test can tell
    assert np.abs(E / ref - 1.0).max() < 2e-3   # float32 and the pixel's own spread of E
    assert info["provenance"]["settings"]["integrator"] == "kabatch"


def test_render_of_a_fixed_height_source_is_in_the_unit_it_states(mi, tmp_path):
    """(user audit, session 40) The pictures' unit is 1 lx normal to the source's axis at the sample
    centre (render.json ``units``); a fixed-height path's source was normalised at its height (tan eps
    0), so at tan eps 3 on the corridor preset (1 m rail) every picture was (1 / sqrt 10)^2 = 10x too
    dark. In the stated unit the horizontal illuminance at the sample centre is cos(incidence) =
    1 / sqrt(1 + tan^2 eps) (the disc's own 1 / (1 + R^2 / D^2) is 1e-5 here)."""
    import math
    out = tmp_path / "r"
    assert main(["render", "--instrument", "corridor", "--sample", "lambert", "--tan-eps", "3", "--beta", "0",
                 "--out", str(out), "--resolution", "32", "--spp", "4", "-q"]) == 0
    info, E, (x, y) = _illuminance(out)
    j, i = int(np.argmin(np.abs(x))), int(np.argmin(np.abs(y)))
    assert E[i, j] == pytest.approx(1.0 / math.sqrt(10.0), rel=0.01)
    assert abs(info["k_a_estimate"] - 1.0) < 1e-5          # a ratio: the unit does not enter it


def test_render_png_says_which_axis_of_the_illuminance_is_stretched(mi, tmp_path, monkeypatch):
    """(user audit, session 40) the illuminance panel said "y stretched" whatever the window: a long
    footprint's window is stretched in y, a point footprint's 2 x 2 mm window in x."""
    from pathlib import Path

    import roadgonio.fileio as fileio
    titles = []

    def keep(fig, path, **kw):
        titles.extend(a.get_title() for a in fig.axes)
        Path(path).write_bytes(b"png")
        return Path(path)
    monkeypatch.setattr(fileio, "atomic_savefig", keep)
    text = (Path(__file__).resolve().parents[2] / "scenes" / "portable.toml").read_text()
    point = tmp_path / "point.toml"
    point.write_text(text.replace("pupil_radius_m = 0.005", "pupil_radius_m = 0.0")
                     .replace("field_half_angle_deg = 0.15", "field_half_angle_deg = 0.0"))
    for inst, out in (("portable", "long"), (str(point), "point")):
        assert main(["render", "--instrument", inst, "--sample", "R3", "--tan-eps", "2", "--beta", "0",
                     "--out", str(tmp_path / out), "--resolution", "8", "--spp", "4", "-q"]) == 0
    illum = [t for t in titles if t.startswith("Horizontal illuminance")]
    assert len(illum) == 2 and "y stretched" in illum[0] and "x stretched" in illum[1], titles


def test_render_of_parts_that_shade_the_footprint_has_the_k_a_engines_shadow_edge(mi, tmp_path):
    """(user audit, session 44) the holder's wall shades the footprint at tan eps 12: render lit it
    with Mitsuba's `direct` integrator, whose shadow rays start lifted off the sample, so its k_A at
    12 / 2 was 1.0100789 +- 4.6e-7 where the auditor's float64 integral gives 1.0101046 +- 3.8e-7
    (2.6e-5, ~50 SE; the engine's shadow ray is checked at its edge in tests/plugin/test_shadow_ray.py).
    A shaded scene is now lit by the k_A engine's integrator: render and `ka` agree within their SEs."""
    from roadgonio import api
    out = tmp_path / "r"
    assert main(["render", "--instrument", "holder", "--sample", "R3", "--tan-eps", "12", "--beta", "2",
                 "--out", str(out), "--resolution", "128", "--spp", "64", "-q"]) == 0
    info = json.loads((out / "render.json").read_text())
    cell = api.ka_cell("holder", "R3", 12.0, 2.0, rel_se=3e-6)
    assert cell.converged and info["k_a_se"] is not None      # both sides reached their precision
    se = float(np.hypot(info["k_a_se"], cell.se))
    assert se < 5e-6                              # the old render's 2.6e-5 would be beyond 5 of these
    assert abs(info["k_a_estimate"] - cell.k_a) < 5.0 * se, (info["k_a_estimate"], cell.k_a, se)
    assert info["provenance"]["settings"]["integrator"] == "kabatch"


def test_render_png_draws_unlit_ground_apart_from_the_log_scale(mi, tmp_path):
    """(user audit, session 44) on the log-scale illuminance panel, unlit ground (E_h = 0: the wide preset
    at tan eps 12, behind the source disc's plane, 60 % of the window) was drawn in the scale's darkest
    colour, which stands for ~0.02 lx/lx: it looked dimly lit. It is grey now, with a legend entry."""
    import matplotlib.image as mpimg
    from roadgonio.engines.mitsuba.images import UNLIT_GREY
    out = tmp_path / "w"
    assert main(["render", "--instrument", "wide", "--sample", "lambert", "--tan-eps", "12", "--beta", "0",
                 "--out", str(out), "--resolution", "16", "--spp", "4", "-q"]) == 0
    png = mpimg.imread(out / "render.png")[..., :3]
    grey = np.all(np.abs(png - float(UNLIT_GREY)) < 0.01, axis=-1)
    lower = grey[png.shape[0] // 2:]             # the illuminance panel
    assert lower.mean() > 0.2, lower.mean()      # the unlit part of the window, and the legend's patch
