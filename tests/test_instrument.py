"""Instrument files: presets load, bad input gets errors naming the file, field or line."""
from __future__ import annotations

import math

import pytest

from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument, bundled_instruments, load_instrument

pytestmark = pytest.mark.unit

GOOD = """
[observation]
alpha_deg = 1.0
[source]
distance_m = 3.0
radius_m = 0.02
[detector]
distance_m = 5.0
pupil_radius_m = 0.01
field_half_angle_deg = 0.15
focus_m = "inf"
[sample]
size_x_m = 6.0
size_y_m = 2.0
"""


def write(tmp_path, text, name="inst.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_presets_load_by_name_and_path():
    assert {"lab", "portable"} <= set(bundled_instruments())
    lab = load_instrument("lab")
    assert lab.name == "lab" and lab.source.radius_m > 0 and lab.detector.focus == lab.detector.distance_m
    portable = load_instrument("scenes/portable.toml")
    assert portable.name == "portable" and portable.detector.pupil_radius_m > 0 and portable.source.radius_m > 0


def test_good_file_round_trips(tmp_path):
    ins = Instrument.load(write(tmp_path, GOOD))
    assert math.isinf(ins.detector.focus)
    again = Instrument.from_dict(ins.to_dict())
    assert again.to_dict() == ins.to_dict()
    changed = ins.with_changes(source={"radius_m": 0.0})
    assert changed.source.is_point and not ins.source.is_point


@pytest.mark.parametrize("edit, field", [
    (("radius_m = 0.02", "radius_m = -0.02"), "source.radius_m"),
    (("distance_m = 3.0", "distance_m = 0"), "source.distance_m"),
    (("alpha_deg = 1.0", "alpha_deg = 95"), "observation.alpha_deg"),
    (("alpha_deg = 1.0", 'alpha_deg = "one"'), "observation.alpha_deg"),
    (('focus_m = "inf"', 'focus_m = "far"'), "detector.focus_m"),
    (("size_x_m = 6.0", "size_x_m = 6.0\ncolour = 3"), "sample"),
    (("radius_m = 0.02", "radius_m = 3.5"), "source.radius_m"),
])
def test_bad_values_name_file_and_field(tmp_path, edit, field):
    p = write(tmp_path, GOOD.replace(*edit))
    with pytest.raises(InputError) as err:
        Instrument.load(p)
    assert err.value.field == field
    assert str(p) in str(err.value)


def test_missing_section_and_bad_toml(tmp_path):
    with pytest.raises(InputError, match=r"\[source\]"):
        Instrument.load(write(tmp_path, GOOD.replace("[source]\ndistance_m = 3.0\nradius_m = 0.02\n", "")))
    with pytest.raises(InputError) as err:
        Instrument.load(write(tmp_path, GOOD.replace("distance_m = 3.0", "distance_m = = 3")))
    assert err.value.line == 5
    with pytest.raises(InputError, match="no such instrument"):
        load_instrument(tmp_path / "nothing.toml")
    with pytest.raises(InputError, match="does not exist"):
        Instrument.load(write(tmp_path, GOOD.replace("size_x_m = 6.0\nsize_y_m = 2.0", 'mesh = "none.ply"')))
