"""``roadgonio render``: files written, EXR readable, numbers consistent; bad input is one line."""
from __future__ import annotations

import json

import numpy as np

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
