"""The [housing] table (roadgonio/instrument/housing.py) and the housing as design keys
(roadgonio/design/grid.py): validation, the box and its panels, the geometry checks that name the
cell and the part, and the docs' key table. Numpy only."""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from roadgonio.errors import GeometryError, InputError
from roadgonio.instrument.config import Instrument, load_instrument
from roadgonio.instrument.enclosure import check_detector_view, check_sources, housing_box, housing_panels, parts_bounds
from roadgonio.instrument.housing import Baffle, Housing

ROOT = Path(__file__).resolve().parents[2]
HOUSED = ROOT / "scenes" / "portable_housed.toml"


def housed(**housing) -> Instrument:
    d = load_instrument(str(HOUSED)).to_dict()
    d["housing"] = {**d["housing"], **housing}
    return Instrument.from_dict(d, path=HOUSED)


@pytest.mark.parametrize("table, field", [
    ({}, "housing.wall_reflectance"),
    ({"wall_reflectance": -0.1}, "housing.wall_reflectance"),
    ({"wall_reflectance": 0.1, "baffle_reflectance": 1.5}, "housing.baffle_reflectance"),
    ({"wall_reflectance": 0.1, "x_m": [1.0]}, "housing.x_m"),
    ({"wall_reflectance": 0.1, "height_m": 0}, "housing.height_m"),
    ({"wall_reflectance": 0.1, "lid": "yes"}, "housing.lid"),
    ({"wall_reflectance": 0.1, "baffles": {"x_m": 0.1}}, "housing.baffles"),
    ({"wall_reflectance": 0.1, "baffles": [{"x_m": 0.1, "height": 0.1}]}, "housing.baffles.0"),
    ({"wall_reflectance": 0.1, "baffles": [{"x_m": "a", "height_m": 0.1}]}, "housing.baffles.0.x_m"),
    ({"wall_reflectance": 0.1, "walls": 0.1}, "housing.walls"),
    # mutation audit 11: each of these was accepted by a changed reader and passed every test
    ({"wall_reflectance": True}, "housing.wall_reflectance"),
    ({"wall_reflectance": 0.1, "margin_m": -0.01}, "housing.margin_m"),
    ({"wall_reflectance": 0.1, "height_m": float("inf")}, "housing.height_m"),
    ({"wall_reflectance": 0.1, "x_m": [0.5, 0.5]}, "housing.x_m"),
    ({"wall_reflectance": 0.1, "y_m": [1.0, -1.0]}, "housing.y_m"),
    ({"wall_reflectance": 0.1, "x_m": [-1.0, 0.0, 1.0]}, "housing.x_m"),
    ({"wall_reflectance": 0.1, "baffles": [{"x_m": 0.1}]}, "housing.baffles.0"),
    ({"wall_reflectance": 0.1, "baffles": [{"x_m": 0.1, "height_m": -0.01}]}, "housing.baffles.0.height_m"),
    # audit 28: lengths beyond an instrument's size (1e6 failed later, naming no field)
    ({"wall_reflectance": 0.1, "margin_m": 1001.0}, "housing.margin_m"),
    ({"wall_reflectance": 0.1, "y_m": [-1e6, 1.0]}, "housing.y_m"),
])
def test_bad_housing_is_one_error_naming_the_file_and_field(table, field):
    d = load_instrument("portable").to_dict()
    with pytest.raises(InputError) as err:
        Instrument.from_dict({**d, "housing": table}, path="box.toml")
    assert err.value.field == field and str(err.value).startswith("box.toml")


def test_housing_values_at_their_limits_are_accepted_and_round_trip():
    """Reflectances 0 and 1, a margin of 0 and a baffle of height 0 are valid; to_dict gives back
    every key that differs from its default (mutation audit 11: refusing each limit, or dropping
    lid = false from to_dict, passed every test)."""
    for table in ({"wall_reflectance": 0.0, "baffle_reflectance": 1.0, "margin_m": 0.0},
                  {"wall_reflectance": 1.0, "baffles": [{"x_m": 0.1, "height_m": 0.0}]},
                  {"wall_reflectance": 0.2, "baffle_reflectance": 0.4, "x_m": [-1.2, 1.1], "y_m": [-0.3, 1.2],
                   "height_m": 1.3, "margin_m": 0.02, "lid": False, "baffles": [{"x_m": 0.6, "height_m": 0.01}]}):
        h = Housing.from_dict(table)
        assert h.to_dict() == table and Housing.from_dict(h.to_dict()) == h


def test_default_box_holds_every_part_with_the_margin():
    """The default box is the bounding box of every grid cell's source disc, the pupil and the
    footprint, plus margin_m on every side (and above); the portable's sources reach x = -D_S sin eps
    at tan 12, y = D_S sin eps at beta 90, z = D_S at tan 0."""
    inst = housed()
    lo, hi = parts_bounds(inst)
    box = housing_box(inst, Housing.of(inst))
    assert box.x == pytest.approx((lo[0] - 0.05, hi[0] + 0.05)) and box.y == pytest.approx((lo[1] - 0.05, hi[1] + 0.05))
    assert box.height == pytest.approx(hi[2] + 0.05)
    sin12 = math.sin(math.atan(12.0))
    assert lo[0] < -sin12 and hi[1] > sin12 and hi[2] == pytest.approx(1.0)


def test_panels_face_into_the_box_and_the_floor_is_road_around_the_sample():
    inst = housed(baffles=[{"x_m": -0.6, "height_m": 0.02}, {"x_m": -0.7, "height_m": 0.0}], baffle_reflectance=0.3)
    h = Housing.of(inst)
    box = housing_box(inst, h)
    centre = np.array([sum(box.x) / 2, sum(box.y) / 2, box.height / 2])
    panels = {p.id: p for p in housing_panels(inst, h)}
    assert "housing_baffle_2" not in panels                 # height 0: no plate
    for p in panels.values():
        m = p.to_world()
        assert np.allclose(np.cross(m[:3, 0], m[:3, 1]) / np.linalg.norm(np.cross(m[:3, 0], m[:3, 1])), p.normal)
        if p.id.startswith("housing_wall") or p.id == "housing_lid":
            assert np.dot(centre - np.array(p.centre), p.normal) > 0      # reflecting face inwards
            assert p.reflectance == 0.05 and not p.road
    assert panels["housing_baffle_1"].two_sided and panels["housing_baffle_1"].centre[0] == -0.6
    assert panels["housing_baffle_1"].reflectance == 0.3              # its own reflectance, not the walls'
    open_top = housed(lid=False)
    assert "housing_lid" not in {p.id for p in housing_panels(open_top, Housing.of(open_top))}
    floor = {k: p for k, p in panels.items() if p.road}
    # the sample is 1 m x 0.3 m: road strips at x < -0.5, x > 0.5 and y > 0.15 (the box starts at y = -0.075)
    assert sorted(floor) == ["housing_floor_x_max", "housing_floor_x_min", "housing_floor_y_max"]
    area = sum(4 * np.linalg.norm(p.u) * np.linalg.norm(p.v) for p in floor.values())
    inside = (box.x[1] - box.x[0]) * (box.y[1] - box.y[0]) - 1.0 * (0.15 - box.y[0])
    assert area == pytest.approx(inside, rel=2e-3)                  # up to the seams' overlap


def test_a_source_through_a_wall_names_the_cell_and_the_wall():
    inst = housed(x_m=[-0.99, 1.05])
    with pytest.raises(GeometryError, match=r"tan eps = 12, beta = 0 \(and 1 more cells\).*housing_wall_x_min"):
        check_sources(inst, Housing.of(inst), [(1.0, 0.0), (12.0, 0.0), (11.5, 0.0)])
    check_sources(inst, Housing.of(inst), [(1.0, 0.0), (5.0, 90.0)])
    # the wall at the disc's edge: 0.5 mm inside it blocks, 0.5 mm outside not (mutation audit 11:
    # a wall 1 mm into the disc passed every test)
    from roadgonio.instrument.enclosure import source_discs
    edge = float(source_discs(inst, [(12.0, 0.0)])[0][:, 0].min())
    for shift, blocks in ((5e-4, True), (-5e-4, False)):
        at = housed(x_m=[edge + shift, 1.05])
        if blocks:
            with pytest.raises(GeometryError, match=r"tan eps = 12, beta = 0:.*housing_wall_x_min"):
                check_sources(at, Housing.of(at), [(12.0, 0.0)])
        else:
            check_sources(at, Housing.of(at), [(12.0, 0.0)])
    inst = housed(height_m=0.9)
    with pytest.raises(GeometryError, match=r"tan eps = 0, beta = 0.*housing_lid"):
        check_sources(inst, Housing.of(inst), [(0.0, 0.0)])
    # the zenith source's disc is level at z = D_S = 1 m: a lid 5 mm lower blocks it, 5 mm higher not;
    # an open top never does (mutation audit 11: a 1 cm tolerance and a lid that blocks when open passed)
    inst = housed(height_m=0.995)
    with pytest.raises(GeometryError, match=r"tan eps = 0, beta = 0.*housing_lid"):
        check_sources(inst, Housing.of(inst), [(0.0, 0.0)])
    check_sources(housed(height_m=1.005), Housing.of(housed(height_m=1.005)), [(0.0, 0.0)])
    check_sources(housed(height_m=0.9, lid=False), Housing.of(housed(height_m=0.9, lid=False)), [(0.0, 0.0)])
    inst = housed(baffles=[{"x_m": -0.97, "height_m": 0.3}])       # through the disc at tan 4 (x = -0.970 m)
    with pytest.raises(GeometryError, match=r"tan eps = 4, beta = 0: its disc \(radius .*\) reaches baffle 0"):
        check_sources(inst, Housing.of(inst), [(4.0, 0.0)])



def test_a_baffle_in_the_sources_line_of_sight_to_the_sample_centre_is_an_error():
    """At beta = 0 the source lies in the x-z plane and the line from it to the sample centre rises
    1 / tan eps per metre of x, whatever the source distance: at x = -0.5 m it passes 0.5 / 12 =
    41.7 mm above the floor for tan eps 12. A 40 mm baffle there only shades part of the footprint
    (numbers); a 43 mm one stands in the nominal direction (an error naming the cell and the baffle;
    the user's report: a 0.5 m baffle gave k_A 0.015 and no direct light)."""
    for h in (0.043, 0.5):
        inst = housed(baffles=[{"x_m": -0.5, "height_m": h}])
        with pytest.raises(GeometryError, match=r"tan eps = 12, beta = 0.*baffle 0.*line of sight to the sample centre"):
            check_sources(inst, Housing.of(inst), [(1.0, 0.0), (12.0, 0.0)])
    inst = housed(baffles=[{"x_m": -0.5, "height_m": 0.040}])
    check_sources(inst, Housing.of(inst), [(1.0, 0.0), (12.0, 0.0), (10.0, 0.0)])
    inst = housed(baffles=[{"x_m": -0.5, "height_m": 0.043}])
    check_sources(inst, Housing.of(inst), [(10.0, 0.0), (12.0, 90.0)])     # 50 mm; beta 90: the line is at x = 0

def test_a_baffle_in_the_line_of_sight_is_an_error_and_a_low_one_is_not():
    """The lowest detected ray passes about (x - x_near) tan(alpha - field) above the sample at x."""
    inst = housed(baffles=[{"x_m": 0.6, "height_m": 0.01}])
    with pytest.raises(InputError, match=r"baffle 0 \(housing_baffle_1: x = 0.6 m, 10 mm high\) blocks the "
                                         r"detector's view") as err:
        check_detector_view(inst, Housing.of(inst))
    assert err.value.field == "housing.baffles.0.height_m" and err.value.path == str(HOUSED)
    inst = housed(baffles=[{"x_m": 0.6, "height_m": 0.004}])
    check_detector_view(inst, Housing.of(inst))
    # a baffle beyond the footprint (the rays end on the sample before it) does not block the view
    # (mutation audit 11: rays followed through the sample plane passed every test)
    inst = housed(baffles=[{"x_m": -0.6, "height_m": 0.02}])
    check_detector_view(inst, Housing.of(inst))
    inst = housed(x_m=[-1.05, 0.9])
    with pytest.raises(InputError, match="pupil.*housing_wall_x_max") as err:
        check_detector_view(inst, Housing.of(inst))
    assert err.value.field == "housing.x_m" and str(err.value).startswith(f"{HOUSED}, field 'housing.x_m': ")


def test_a_baffle_on_a_wall_is_refused_with_the_open_bounds():
    """(trial 10 D12) A baffle at x = -1.05 in a box from -1.05 was refused as 'outside', the message
    saying 'inside x = -1.05 ... 1.05': the bounds are excluded, and the message says so exactly. Just
    inside them it is no error of the box."""
    for x in (-1.05, 1.05, -1.2):
        inst = housed(x_m=[-1.05, 1.05], baffles=[{"x_m": x, "height_m": 0.004}])
        with pytest.raises(InputError) as err:
            check_detector_view(inst, Housing.of(inst))
        assert err.value.field == "housing.baffles.0.x_m" and "\n" not in str(err.value)
        assert "strictly between the walls, -1.05 < x_m < 1.05 m" in err.value.reason
        assert f"at x = {x:g} m is not inside" in err.value.reason
    inst = housed(x_m=[-1.05, 1.05], baffles=[{"x_m": -1.0499, "height_m": 0.004}])
    check_detector_view(inst, Housing.of(inst))


def test_two_baffles_at_the_same_x_are_refused_naming_both():
    """(trial 10 D12) Two baffles at one x (coplanar plates) were accepted without a word."""
    with pytest.raises(InputError) as err:
        housed(baffles=[{"x_m": -0.7, "height_m": 0.0}, {"x_m": -0.5, "height_m": 0.02},
                        {"x_m": -0.5, "height_m": 0.01}])
    assert err.value.field == "housing.baffles.2.x_m" and err.value.path == str(HOUSED)
    assert "baffles 1 and 2" in err.value.reason and "same x = -0.5 m" in err.value.reason
    housed(baffles=[{"x_m": -0.5, "height_m": 0.02}, {"x_m": -0.499, "height_m": 0.01}])     # 1 mm apart: two plates


@pytest.mark.parametrize("housing, field", [
    ({"baffles": [{"x_m": 0.3, "height_m": 0.0}, {"x_m": -5.0, "height_m": 0.02}]}, "housing.baffles.1.x_m"),
    ({"x_m": [-0.5, 0.5], "y_m": [0.0, 1.05]}, "housing.x_m"),
    ({"y_m": [0.0, 1.05]}, "housing.y_m"),
    ({"margin_m": 0.0}, "housing.margin_m"),
    ({"baffles": [{"x_m": -0.3, "height_m": 1.2}]}, "housing.baffles.0.height_m"),     # through the lid
    ({"baffles": [{"x_m": 1.06, "height_m": 0.02}]}, "housing.baffles.0.x_m"),         # 1 cm beyond the wall
])
def test_a_housing_that_cannot_hold_the_view_names_the_file_and_field(housing, field):
    """Checks of the instrument file (no computation): the file and the [housing] field, like any
    other bad input (the default box's walls come from margin_m)."""
    inst = housed(**housing)
    with pytest.raises(InputError) as err:
        check_detector_view(inst, Housing.of(inst))
    assert err.value.field == field and str(err.value).startswith(f"{HOUSED}, field '{field}': "), str(err.value)


def test_housing_design_keys():
    from roadgonio.design.feasibility import check_point
    from roadgonio.design.grid import build_instrument, parse_vary
    from roadgonio.design.outputs import toml_text
    assert parse_vary("housing.wall_reflectance=0.01:0.1:3:log").values == (0.01, 0.0316227766017, 0.1)
    assert parse_vary("housing.baffles.0.height_m=0,0.01").values == (0.0, 0.01)
    with pytest.raises(InputError, match="unknown instrument key"):
        parse_vary("housing.baffles.x_m=0.1")
    base = housed(baffles=[{"x_m": -0.6, "height_m": 0.0}])
    inst = build_instrument(base, {"housing.wall_reflectance": 0.2, "housing.baffles.0.height_m": 0.02})
    h = Housing.of(inst)
    assert h.wall_reflectance == 0.2 and h.baffles == (Baffle(x_m=-0.6, height_m=0.02),)
    with pytest.raises(InputError, match="declare baffle 1"):
        build_instrument(base, {"housing.baffles.1.x_m": 0.1})
    # best.toml round trip: the baffles as inline tables
    text = toml_text({"housing": dict(inst.to_dict()["housing"])})
    import tomllib
    assert Housing.from_dict(tomllib.loads(text)["housing"]) == h
    # a point whose baffle blocks the grazing sources' disc is infeasible with kind "housing"
    _, f = check_point(base, {"housing.baffles.0.height_m": 0.3, "housing.baffles.0.x_m": -0.97},
                       [(4.0, 0.0), (1.0, 0.0)])
    assert not f.ok and f.kind == "housing" and "baffle 0 (housing_baffle_1" in f.reason


def test_conventions_list_every_housing_and_scene_key():
    from roadgonio.instrument.config import SCENE_KEYS
    from roadgonio.instrument.housing import HOUSING_KEYS
    text = (ROOT / "docs" / "conventions.md").read_text()
    rows = [ln for ln in text.splitlines() if ln.startswith("|")]
    keys = set(re.findall(r"`([a-z_]+)`", "\n".join(rows)))
    assert set(HOUSING_KEYS) <= keys and set(SCENE_KEYS) - {"params"} <= keys


def test_the_source_discs_of_a_fixed_height_source_are_at_its_distance():
    """The housing checks place each cell's source disc at that cell's distance: height / cos eps on
    a fixed-height path (mutation audit 11: the height for every cell passed every test)."""
    from roadgonio.instrument.enclosure import source_discs
    inst = load_instrument("corridor")
    cells = [(0.0, 0.0), (2.0, 30.0), (12.0, 0.0)]
    for (t, _), disc in zip(cells, source_discs(inst, cells)):
        assert np.linalg.norm(disc[-1]) == pytest.approx(inst.source.height_m * math.hypot(1.0, t), rel=1e-12)
        assert np.allclose(np.linalg.norm(disc[:-1] - disc[-1], axis=1), inst.source.radius_m, rtol=1e-12, atol=0.0)


def test_a_mesh_sample_must_cover_the_floor_of_the_housing(tmp_path):
    """A mesh sample is the housing's floor: short of the box in x or in y it is an error (light
    would leave through the gap); covering it, not (mutation audit 11: a check of x alone passed
    every test)."""
    from helpers import grid_mesh, with_mesh
    inst = housed()
    box = housing_box(inst, Housing.of(inst))
    xs, ys = [box.x[0] - 0.01, box.x[1] + 0.01], [box.y[0] - 0.01, box.y[1] + 0.01]
    for k, (mx, my) in enumerate(((xs, [box.y[0] + 0.03, ys[1]]), (xs, [ys[0], 0.15]), ([-0.5, xs[1]], ys))):
        mesh = with_mesh(inst, grid_mesh(tmp_path / f"short{k}.ply", mx, my))
        with pytest.raises(GeometryError, match="does not cover the floor of the housing"):
            check_detector_view(mesh, Housing.of(mesh))
    whole = with_mesh(inst, grid_mesh(tmp_path / "whole.ply", xs, ys))
    check_detector_view(whole, Housing.of(whole))
