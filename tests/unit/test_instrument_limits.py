"""The limits and keys of an instrument file (roadgonio/instrument/config.py) at their edges: open
and closed bounds, the largest length, the range of the observation azimuth, an unknown key of
[observation]. Mutation audit 10: each of these could be changed without any test failing."""
from __future__ import annotations

import math

import pytest

from roadgonio.errors import InputError
from roadgonio.instrument.config import MAX_LENGTH_M, Detector, Instrument, Observation, SampleGeometry, Source

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
[sample]
size_x_m = 6.0
size_y_m = 2.0
"""


def _refused(make, field: str) -> InputError:
    with pytest.raises(InputError) as err:
        make()
    assert err.value.field == field and field in str(err.value) and "\n" not in str(err.value)
    return err.value


@pytest.mark.parametrize("make, field", [
    (lambda: Observation(alpha_deg=90.0), "observation.alpha_deg"),              # 0 < alpha < 90: both open
    (lambda: Detector(distance_m=5.0, field_half_angle_deg=45.0), "detector.field_half_angle_deg"),   # < 45
    (lambda: Source(distance_m=1.0, beam_half_angle_deg=90.1), "source.beam_half_angle_deg"),        # <= 90
    (lambda: Observation(delta_deg=-360.5), "observation.delta_deg"),
    (lambda: Observation(delta_deg=360.5), "observation.delta_deg"),
])
def test_open_and_closed_bounds(make, field):
    _refused(make, field)


def test_values_just_inside_the_bounds_are_accepted():
    assert Observation(alpha_deg=89.999).alpha_deg == 89.999
    assert Detector(distance_m=5.0, field_half_angle_deg=44.999).field_half_angle_deg == 44.999
    assert Source(distance_m=1.0, beam_half_angle_deg=90.0).beam_half_angle_deg == 90.0
    for d in (-360.0, -90.0, 360.0):                      # the azimuth may be given either way round
        assert Observation(delta_deg=d).delta_deg == d


@pytest.mark.parametrize("make, field", [
    (lambda: Source(distance_m=MAX_LENGTH_M * 1.001), "source.distance_m"),
    (lambda: Source(path="fixed_height", height_m=MAX_LENGTH_M * 2), "source.height_m"),
    (lambda: Detector(distance_m=MAX_LENGTH_M * 1.001), "detector.distance_m"),
    (lambda: Detector(distance_m=5.0, focus_m=1e7), "detector.focus_m"),
    (lambda: SampleGeometry(size_x_m=MAX_LENGTH_M * 1.001), "sample.size_x_m"),
])
def test_no_length_beyond_the_largest_instrument(make, field):
    err = _refused(make, field)
    assert f"at most {MAX_LENGTH_M:g} m" in str(err)


def test_the_largest_length_itself_and_a_focus_at_infinity_are_accepted():
    assert Source(distance_m=MAX_LENGTH_M).distance_m == MAX_LENGTH_M
    assert math.isinf(Detector(distance_m=MAX_LENGTH_M, focus_m=math.inf).focus_m)


def test_the_source_radius_must_be_below_its_distance():
    _refused(lambda: Source(distance_m=1.0, radius_m=1.0), "source.radius_m")
    assert Source(distance_m=1.0, radius_m=0.999).radius_m == 0.999


def test_an_unknown_key_of_observation_is_a_one_line_error(tmp_path):
    p = tmp_path / "inst.toml"
    p.write_text(GOOD.replace("alpha_deg = 1.0", "alpha_deg = 1.0\nalpah_deg = 2.0"))
    with pytest.raises(InputError) as err:
        Instrument.load(p)
    assert err.value.field == "observation.alpah_deg" and str(p) in str(err.value)


def test_the_detector_distance_is_required(tmp_path):
    """[detector] without distance_m: an error, not the dataclass's default of 5 m."""
    p = tmp_path / "inst.toml"
    p.write_text(GOOD.replace("[detector]\ndistance_m = 5.0\n", "[detector]\n"))
    with pytest.raises(InputError) as err:
        Instrument.load(p)
    assert err.value.field == "detector.distance_m" and "missing" in str(err.value)


@pytest.mark.parametrize("value", [0, 65, -1])
def test_scene_max_bounces_outside_1_to_64_is_refused(tmp_path, value):
    p = tmp_path / "inst.toml"
    p.write_text(GOOD + f"[scene]\nmax_bounces = {value}\n")
    with pytest.raises(InputError) as err:
        Instrument.load(p)
    assert err.value.field == "scene.max_bounces" and "1 ... 64" in str(err.value)


def test_scene_max_bounces_1_and_64_are_accepted(tmp_path):
    for v in (1, 64):
        p = tmp_path / f"inst{v}.toml"
        p.write_text(GOOD + f"[scene]\nmax_bounces = {v}\n")
        assert Instrument.load(p).extra["scene"]["max_bounces"] == v


def test_an_instrument_file_written_and_read_back_is_the_same_to_the_last_bit(tmp_path):
    """to_toml writes every float in full (repr): design's best.toml must give back the design's
    instrument exactly, not to 6 digits; a name and description with quotes, a backslash and a
    line break come back as they were."""
    inst = Instrument.from_dict({
        "instrument": {"name": 'lab "B"', "description": "tilted 0.1\u00b0 \\ second line\nthird"},
        "observation": {"alpha_deg": 1.0000000123, "delta_deg": -0.123456789012},
        "source": {"distance_m": 3.1415926535897, "radius_m": 0.0123456789},
        "detector": {"distance_m": 5.000000001, "pupil_radius_m": 1.23456789e-3, "field_half_angle_deg": 0.1500001,
                     "focus_m": 123.456789012},
        "sample": {"size_x_m": 6.00000001, "size_y_m": 2.0}})
    p = tmp_path / "back.toml"
    p.write_text(inst.to_toml("written by a test"))
    back = Instrument.load(p)
    assert back.to_dict() == inst.to_dict()
    assert back.source.distance_m == 3.1415926535897 and back.detector.focus_m == 123.456789012
    assert back.name == 'lab "B"' and back.description == "tilted 0.1\u00b0 \\ second line\nthird"
