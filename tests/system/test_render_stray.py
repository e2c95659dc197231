"""``roadgonio render`` in a reflecting housing (issue 18): stray.png / stray.exr and the stray
summary in render.json, checked against the batched engine."""
from __future__ import annotations

import math
from pathlib import Path

import pytest

from roadgonio.instrument.config import load_instrument

from tolerances import N_SIGMA

SCENES = Path(__file__).resolve().parents[2] / "scenes"


def test_render_shows_the_stray_light_and_agrees_with_the_engine(mi, tmp_path, capsys):
    """``roadgonio render`` in a reflecting housing writes stray.png / stray.exr; its one-render k_A
    with the stray light and its stray fraction (the picture's own paths over the field stop) agree
    with the engine's within 4 combined standard errors, and the parts' shares add up to the stray
    fraction."""
    import json

    from roadgonio.cli import main
    out = tmp_path / "r"
    rc = main(["render", "--instrument", str(SCENES / "portable_housed.toml"), "--sample", "R3", "--tan-eps", "10",
               "--beta", "45", "--out", str(out), "--resolution", "32", "--spp", "4"])
    printed = capsys.readouterr().out
    assert rc == 0 and "stray light:" in printed
    # the part named as stray.png names it, not by its shape's id (review, session 40)
    assert "(most from " in printed and "(most from housing_" not in printed, printed
    info = json.loads((out / "render.json").read_text())
    st = info["stray"]
    # trial 10 D5: the stray part does not follow --resolution 32 / --spp 4, and the output says so
    assert st["resolution"] == 96 and st["samples"] == 1 << 20
    assert "96 x 96 pixels and 1048576 samples (fixed; --resolution 32 and --spp 4" in printed
    from roadgonio.engines.mitsuba import images
    assert (images.STRAY_PICTURE_RESOLUTION, images.STRAY_PICTURE_LOG2 + math.log2(images.STRAY_PICTURE_REPLICATES)) \
        == (96, 20), "render --help and docs/straylight.md quote 96 x 96 pixels, 2^20 samples"
    assert (out / "stray.png").stat().st_size > 20_000
    inst = load_instrument(str(SCENES / "portable_housed.toml"))
    from roadgonio.surface.sample import resolve_sample
    from roadgonio.engines import make_backend
    r = make_backend("mitsuba", inst, resolve_sample("R3").model, rel_se=1e-3, seed=2).compute([(10.0, 45.0)])[0]
    assert abs(info["k_a_estimate"] - r.k_a) <= N_SIGMA * math.hypot(info["k_a_se"], r.se)
    assert abs(st["stray_fraction_road"] - r.stray_fraction) <= N_SIGMA * math.hypot(st["stray_fraction_road_se"],
                                                                                r.stray_fraction_se)
    assert sum(p["road"] for p in st["parts"].values()) == pytest.approx(st["stray_fraction_road"], rel=1e-9)
    assert st["stray_fraction_road"] > 0.05
    # render.png's view and illuminance are the direct light, and their titles say so (user audit)
    words = images.panel_words(inst, info)
    assert "the direct light only" in words["stray"] and f"{100 * st['stray_fraction_road']:.1f} %" in words["stray"]
    assert words["illuminance_title"].startswith("Horizontal illuminance on the sample straight from the source")
    assert images.panel_words(load_instrument("portable"), {})["stray"] == ""
    turned = load_instrument("portable").with_changes(observation={"delta_deg": 30.0})
    assert "delta = 30 deg" in images.panel_words(turned, {})["x_label"]
    assert "towards +x" in images.panel_words(load_instrument("portable"), {})["x_label"]
    # one meaning per field (trial 6): the unsuffixed ratio is the one k_a_estimate is made of (stray
    # light included), the direct integrator's carry _direct, and every field is defined
    assert info["k_a_estimate"] == pytest.approx(info["ratio"] / info["ideal_ratio"], rel=1e-12)
    assert info["k_a_direct_estimate"] == pytest.approx(info["ratio_direct"] / info["ideal_ratio"], rel=1e-12)
    assert info["ratio_direct"] == pytest.approx(info["signal_road_direct"] / info["signal_lambert_direct"], rel=1e-9)
    assert "signal_road" not in info and "signal_lambert" not in info
    assert {"ratio", "k_a_estimate", "ratio_direct", "k_a_direct_estimate"} <= set(info["definitions"])


def test_one_cell_json_says_how_many_reflections(capsys):
    """(user audit, session 38) `ka --tan-eps --beta --json` of a housed instrument did not say how
    many reflections its paths followed (a table's ka.json did): now ``max_bounces``, the walls'
    default (4 for the portable housing's 0.05)."""
    import json

    from roadgonio.cli import main
    assert main(["ka", "--instrument", "portable_housed", "--sample", "R3", "--tan-eps", "2", "--beta", "0",
                 "--rel-se", "1e-2", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["max_bounces"] == 4 and d["stray_fraction"] > 0


def test_stray_png_names_the_housing_parts_as_the_instrument_file_does():
    """(user audit, session 40) stray.png's key showed the shapes' ids (housing_baffle_1 beside errors
    calling it baffle 0, the field housing.baffles.0): it shows the panels' own words; render.json and
    stray.exr keep the ids."""
    from types import SimpleNamespace

    from roadgonio.engines.mitsuba.images import _part_labels
    from roadgonio.instrument.enclosure import housing_panels
    from roadgonio.instrument.housing import Housing
    inst = load_instrument(str(SCENES / "portable_housed_baffle.toml"))
    inst = inst.with_changes(housing={"baffles": [{"x_m": -0.5, "height_m": 0.02}]})     # the declared plate, raised
    housing = Housing.of(inst)
    words = _part_labels(SimpleNamespace(instrument=inst, housing=housing))
    ids = [p.id for p in housing_panels(inst, housing)]
    baffle = [i for i in ids if "baffle" in i]
    assert baffle and words[baffle[0]].startswith("baffle 0 (x = ")
    assert words["housing_wall_y_min"].startswith("wall y = -") and set(words) == set(ids)
    assert _part_labels(SimpleNamespace(instrument=inst, housing=None)) == {}       # XML parts keep their ids


def test_render_says_why_the_direct_k_a_is_missing(mi, tmp_path, capsys):
    """(user audit, session 40) below 4096 samples a housed render has no k_A of the direct light; the
    printed line dropped it without a word (the reason was in render.json only)."""
    from roadgonio.cli import main
    out = tmp_path / "r"
    assert main(["render", "--instrument", str(SCENES / "portable_housed.toml"), "--sample", "lambert", "--tan-eps",
                 "12", "--beta", "75", "--out", str(out), "--resolution", "16", "--spp", "4"]) == 0
    printed = capsys.readouterr().out
    assert "no k_A of the direct light estimate from 1024 samples" in printed, printed
