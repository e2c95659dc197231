"""Instrument files: presets load, bad input gets errors naming the file, field or line."""
from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from roadgonio.errors import InputError
from roadgonio.instrument.config import (
    Detector,
    Instrument,
    Observation,
    SampleGeometry,
    Source,
    bundled_instruments,
    load_instrument,
)


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
    assert lab.name == "lab" and lab.source.radius_m > 0 and lab.detector.focus_distance_m == lab.detector.distance_m
    portable = load_instrument(Path(__file__).resolve().parents[2] / "scenes" / "portable.toml")
    assert portable.name == "portable" and portable.detector.pupil_radius_m > 0 and portable.source.radius_m > 0


def test_good_file_round_trips(tmp_path):
    ins = Instrument.load(write(tmp_path, GOOD))
    assert math.isinf(ins.detector.focus_distance_m) and ins.detector.focus_m == math.inf
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
    (("size_x_m = 6.0", "size_x_m = 6.0\ncolour = 3"), "sample.colour"),
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


# -- the dataclasses validate themselves -------------------------------------------------------

@pytest.mark.parametrize("make, field", [
    (lambda: Source(distance_m=-1), "source.distance_m"),
    (lambda: Source(distance_m=1.0, radius_m=-0.01), "source.radius_m"),
    (lambda: Source(distance_m=1.0, radius_m=1.0), "source.radius_m"),
    (lambda: Source(distance_m=1.0, beam_half_angle_deg=0.0), "source.beam_half_angle_deg"),
    (lambda: Source(distance_m="far"), "source.distance_m"),
    (lambda: Detector(distance_m=5.0, focus_m=-1.0), "detector.focus_m"),
    (lambda: Detector(distance_m=5.0, focus_m=0.0), "detector.focus_m"),
    (lambda: Detector(distance_m=5.0, field_half_angle_deg=50.0), "detector.field_half_angle_deg"),
    (lambda: Detector(distance_m=5.0, pupil_radius_m=6.0), "detector.pupil_radius_m"),
    (lambda: Detector(distance_m=5.0, field_edge_sensitivity=2.5), "detector.field_edge_sensitivity"),
    (lambda: Detector(distance_m=5.0, field_edge_sensitivity=-0.1), "detector.field_edge_sensitivity"),
    (lambda: Detector(distance_m=math.nan), "detector.distance_m"),
    (lambda: Observation(alpha_deg=0.0), "observation.alpha_deg"),
    (lambda: Observation(alpha_deg=True), "observation.alpha_deg"),
    (lambda: SampleGeometry(size_x_m=0.0), "sample.size_x_m"),
    (lambda: SampleGeometry(mesh="no-such-file.ply"), "sample.mesh"),
    (lambda: Instrument(source={"distance_m": 1.0}), "source"),
])
def test_dataclasses_validate_on_construction(make, field):
    with pytest.raises(InputError) as err:
        make()
    assert err.value.field == field and field in str(err.value)


def test_dataclasses_are_frozen_and_normalise_numbers():
    s = Source(distance_m=2, radius_m=0)
    assert isinstance(s.distance_m, float) and s.is_point
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.distance_m = 3.0  # type: ignore[misc]
    assert SampleGeometry().size_x_m == 6.0 and SampleGeometry().size_y_m == 2.0


def test_focus_at_infinity_is_math_inf():
    """math.inf from Python, "inf" or TOML's bare inf from a file; written back as "inf"."""
    assert Detector(distance_m=5.0, focus_m="inf").focus_m == math.inf
    assert Detector(distance_m=5.0, focus_m=math.inf).angular_field
    assert not Detector(distance_m=5.0).angular_field and Detector(distance_m=5.0).focus_distance_m == 5.0
    ins = Instrument.from_dict(tomllib.loads(GOOD.replace('focus_m = "inf"', "focus_m = inf")))
    assert ins.detector.focus_m == math.inf and ins.to_dict()["detector"]["focus_m"] == "inf"
    assert Instrument.from_dict(ins.to_dict()).detector.focus_m == math.inf


def test_errors_from_a_file_name_the_file(tmp_path):
    p = write(tmp_path, GOOD.replace("distance_m = 3.0", "distance_m = -3.0"))
    with pytest.raises(InputError) as err:
        Instrument.load(p)
    assert err.value.field == "source.distance_m" and err.value.path == str(p)


finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(distance=finite, radius=finite)
def test_source_accepts_exactly_the_valid_discs(distance, radius):
    """Property: a Source exists iff 0 <= radius < distance and a non-zero radius is at least
    MIN_APERTURE_M (1 um: a point is radius 0); otherwise the error names the field."""
    from roadgonio.instrument.config import MIN_APERTURE_M
    valid = distance > 0 and 0 <= radius < distance and (radius == 0 or radius >= MIN_APERTURE_M)
    if valid:
        s = Source(distance_m=distance, radius_m=radius)
        assert s.distance_m == distance and s.radius_m == radius
    else:
        with pytest.raises(InputError) as err:
            Source(distance_m=distance, radius_m=radius)
        assert err.value.field in ("source.distance_m", "source.radius_m")


@settings(max_examples=100, deadline=None)
@given(alpha=st.floats(min_value=0.05, max_value=89.0), dist=st.floats(min_value=0.1, max_value=20.0),
       pupil=st.one_of(st.just(0.0), st.floats(min_value=1e-6, max_value=0.05)),
       field_deg=st.floats(min_value=0.0, max_value=2.0),
       focus=st.one_of(st.none(), st.just(math.inf), st.floats(min_value=0.1, max_value=50.0)))
def test_instrument_dict_round_trip(alpha, dist, pupil, field_deg, focus):
    """Property: from_dict(to_dict(x)) == x for valid instruments (the file form loses nothing)."""
    det = {"distance_m": dist, "pupil_radius_m": min(pupil, 0.5 * dist), "field_half_angle_deg": field_deg}
    if focus is not None:
        det["focus_m"] = focus
    ins = Instrument.from_dict({"observation": {"alpha_deg": alpha}, "source": {"distance_m": 2.0},
                                "detector": det})
    again = Instrument.from_dict(ins.to_dict())
    assert again == ins


@pytest.mark.parametrize("extra, field", [
    ("[colour]\nred = 1\n", "colour"),
    ("[instrument]\nnmae = \"x\"\n", "instrument.nmae"),
    ("[calibration]\nmode = \"lamber\"\n", "calibration.mode"),
    ("[calibration]\nmode = \"reference\"\n", "calibration.reference"),
    ("[calibration]\nmode = \"absolute\"\n", None),            # computed (roadgonio.engines.calibration)
    ("[calibration]\nmode = \"absolute\"\nreference = \"R3\"\n", "calibration.reference"),
    ("[scene]\n", None),
    ("[scene]\nxlm = \"holder.xml\"\n", "scene.xlm"),             # a typo of xml: not ignored
    ("[scene.params]\nholder_h_m = 0.1\n", "scene.xml"),          # parameters of no XML file
    ("[scene]\nxml = 5\n", "scene.xml"),
    # a number that is not finite reached the XML and Mitsuba dropped the part (user audit, session 19)
    ("[scene]\nxml = \"holder.xml\"\n[scene.params]\nwall_x_m = nan\n", "scene.params.wall_x_m"),
    ("[scene]\nxml = \"holder.xml\"\n[scene.params]\nwall_x_m = inf\n", "scene.params.wall_x_m"),
    ("[calibration]\nmode = \"lambert\"\n", None),
])
def test_sections_are_checked(tmp_path, extra, field):
    """An unknown section or key is an error (a typo must not change the instrument), and so is a
    calibration that is not one of docs/conventions.md section 5."""
    p = write(tmp_path, GOOD + extra)
    if field is None:
        Instrument.load(p)
        return
    with pytest.raises(InputError) as err:
        Instrument.load(p)
    assert err.value.field == field and str(p) in str(err.value)


def test_relative_mesh_survives_with_changes_and_a_rewrite(tmp_path, monkeypatch):
    """A mesh named relative to an instrument file opened by a relative path: with_changes (what
    `design` does for every grid point) and a to_dict/from_dict round trip keep the same file (the
    path was once joined to the file's folder twice)."""
    import numpy as np
    import trimesh
    folder = tmp_path / "inst"
    folder.mkdir()
    trimesh.Trimesh(vertices=np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]]),
                    faces=np.array([[0, 1, 2], [0, 2, 3]]), process=False).export(folder / "m.ply")
    from roadgonio.design.outputs import toml_text        # the writer of design's best.toml
    d = load_instrument("lab").to_dict()
    d["sample"] = {"mesh": "m.ply"}
    text = toml_text(d)
    (folder / "x.toml").write_text(text)
    monkeypatch.chdir(tmp_path)
    inst = Instrument.load(Path("inst") / "x.toml")           # a relative file name
    assert inst.sample.mesh.resolve() == (folder / "m.ply").resolve()
    moved = inst.with_changes(source={"radius_m": 0.002})
    assert moved.sample.mesh.resolve() == (folder / "m.ply").resolve()
    again = Instrument.from_dict(moved.to_dict(), path=Path("inst") / "x.toml")
    assert again.sample.mesh.resolve() == (folder / "m.ply").resolve()


def test_a_misspelt_required_section_is_pointed_at():
    """(audit 28) '[detecter]' in place of [detector] said 'missing table [detector]' and nothing of
    the typo: the section of a similar name is named."""
    d = load_instrument("portable").to_dict()
    d["detecter"] = d.pop("detector")
    with pytest.raises(InputError, match=r"missing table \[detector\] \(the file has a table \[detecter\]") as err:
        Instrument.from_dict(d, path="x.toml")
    assert err.value.field == "detector"
    d = load_instrument("portable").to_dict()
    del d["source"]
    with pytest.raises(InputError, match=r"missing table \[source\]$"):
        Instrument.from_dict(d, path="x.toml")
