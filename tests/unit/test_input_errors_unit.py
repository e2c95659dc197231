"""Bad input and failure handling below the command line: frozen configs, SPECs against the
geometry, seeds, output permissions, message formatting (the command line's:
tests/system/test_input_errors.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.errors import InputError


def test_instrument_is_frozen():
    from dataclasses import FrozenInstanceError

    from roadgonio.instrument.config import load_instrument
    inst = load_instrument("lab")
    with pytest.raises((FrozenInstanceError, TypeError)):
        inst.extra["scene"] = {"xml": "x.xml"}


def test_spec_out_of_the_footprint_is_refused_for_the_aperture_case(r3like):
    """With the aperture effect the perturbed instrument is rebuilt: a detector-distance error that
    pushes the footprint off the sample is a SPEC error naming the key, before any k_A work."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.uncertainty.cells import CellSet
    from roadgonio.uncertainty.measurement import MeasurementModel
    from roadgonio.uncertainty.spec import check_spec_geometry, parse_sigma_spec
    mm = MeasurementModel(r3like, load_instrument("lab"), CellSet.make("standard"))
    check_spec_geometry(parse_sigma_spec("detector_distance_m=0.005"), mm, aperture=True)   # fine
    with pytest.raises(InputError, match="detector_distance_m"):
        check_spec_geometry(parse_sigma_spec("detector_distance_m=2"), mm, aperture=True)


def test_a_spec_that_moves_the_source_behind_a_baffle_is_the_specs_error(r3like):
    """User audit, session 37: portable_housed_baffle with a 40 mm baffle measures every table cell,
    but eps_deg = 0.1 moves the grazing source behind the baffle in the surrogate's tables; that was
    refused after ~5 s of computation as the instrument file's baffle at tan eps 12.672 (no cell of
    any table). It is a SPEC error naming the key, up front; a SPEC without eps leaves it be."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.uncertainty.cells import CellSet
    from roadgonio.uncertainty.measurement import MeasurementModel
    from roadgonio.uncertainty.spec import check_spec_geometry, parse_sigma_spec
    inst = load_instrument("portable_housed_baffle").with_changes(housing={"baffles": [{"x_m": -0.5, "height_m": 0.04}]})
    mm = MeasurementModel(r3like, inst, CellSet.make("standard"))
    check_spec_geometry(parse_sigma_spec("eps_deg=0.1"), mm, aperture=False)          # no rebuilt instrument
    check_spec_geometry(parse_sigma_spec("alpha_deg=0.01"), mm, aperture=True)        # fine
    with pytest.raises(InputError, match=r"sigma eps_deg = 0\.1.*housing blocks the source") as err:
        check_spec_geometry(parse_sigma_spec("eps_deg=0.1"), mm, aperture=True)
    assert err.value.field == "sigma eps_deg"


def test_an_instrument_that_cannot_measure_is_its_own_error_not_the_specs(r3like, tmp_path):
    """A footprint that leaves the sample at the nominal geometry is the instrument's fault: any
    SPEC, however small, was refused as "expected smaller standard deviations" (audit, session 27);
    now the instrument's GeometryError names its file and field, with and without the aperture
    effect."""
    from roadgonio.errors import GeometryError
    from roadgonio.instrument.config import load_instrument
    from roadgonio.uncertainty.cells import CellSet
    from roadgonio.uncertainty.measurement import MeasurementModel
    from roadgonio.uncertainty.spec import check_spec_geometry, parse_sigma_spec
    small = load_instrument("lab").with_changes(sample={"size_x_m": 0.5, "size_y_m": 0.5})
    spec = parse_sigma_spec("eps_deg=0.0001")
    mm = MeasurementModel(r3like, small, CellSet.make("standard"))
    for aperture in (True, False):
        try:
            check_spec_geometry(spec, mm, aperture=aperture)
        except GeometryError as err:
            assert err.field == "sample" and "footprint leaves the sample" in str(err)
        else:
            assert not aperture, "the footprint off the sample was not refused"
    # the nominal detector below the horizon is refused without the aperture effect as well
    low = MeasurementModel(r3like, load_instrument("lab"), CellSet.make("standard"))
    low.alpha0 = -1.0
    with pytest.raises(GeometryError, match="nominal geometry"):
        check_spec_geometry(spec, low, aperture=False)


def test_a_housing_that_blocks_the_nominal_source_is_the_instruments_error_not_the_specs(r3like):
    """(user audit, session 44) a lid of 0.3 m over the portable's sources blocks them at no error at
    all; intercompare and uncertainty blamed the smallest sigma ("expected smaller standard
    deviations", sigma eps_deg = 0.0001 too). Now the instrument's error, naming housing.height_m."""
    from roadgonio.errors import GeometryError
    from roadgonio.instrument.config import load_instrument
    from roadgonio.uncertainty.cells import CellSet
    from roadgonio.uncertainty.measurement import MeasurementModel
    from roadgonio.uncertainty.spec import check_spec_geometry, parse_sigma_spec
    low = load_instrument("portable_housed").with_changes(housing={"height_m": 0.3})
    mm = MeasurementModel(r3like, low, CellSet.make("standard"))
    with pytest.raises((GeometryError, InputError), match="housing blocks the source") as err:
        check_spec_geometry(parse_sigma_spec("eps_deg=0.0001"), mm, aperture=True)
    assert err.value.field == "housing.height_m"
    check_spec_geometry(parse_sigma_spec("eps_deg=0.0001"), MeasurementModel(
        r3like, load_instrument("portable_housed"), CellSet.make("standard")), aperture=True)


def test_every_trial_is_checked(r3like):
    from roadgonio.instrument.config import load_instrument
    from roadgonio.uncertainty.cells import CellSet
    from roadgonio.uncertainty.measurement import MeasurementModel
    from roadgonio.uncertainty.spec import INPUTS, check_trials, parse_sigma_spec
    spec = parse_sigma_spec("alpha_deg=0.1")
    mm = MeasurementModel(r3like, load_instrument("lab"), CellSet.make("standard"))
    X = np.zeros((5, len(INPUTS)))
    check_trials(spec, mm, X)
    X[3, 0] = -1.2      # 12 sigma: the detector below the horizon
    with pytest.raises(InputError, match=r"trial 4 draws alpha_deg = -1\.2"):
        check_trials(spec, mm, X)


def test_backend_api_rejects_negative_seeds(r3like):
    from roadgonio.engines import make_backend
    from roadgonio.instrument.config import load_instrument
    for name in ("numpy-mc", "reference"):
        with pytest.raises(InputError, match="seed"):
            make_backend(name, load_instrument("lab"), r3like, seed=-5)


def test_outputs_are_world_readable(tmp_path):
    import os

    from roadgonio.fileio import OutputGroup, atomic_write_text
    mask = os.umask(0o022)
    try:
        p = atomic_write_text(tmp_path / "a.txt", "x")
        with OutputGroup(tmp_path / "g") as g:
            g.text("b.txt", "y")
        assert (p.stat().st_mode & 0o777) == 0o644
        assert ((tmp_path / "g" / "b.txt").stat().st_mode & 0o777) == 0o644
        assert not [q for q in (tmp_path / "g").iterdir() if q.name.startswith(".")]
    finally:
        os.umask(mask)


def test_percentages_in_messages_are_plain_numbers():
    """A fraction near 1 in a message reads 99.7 %, not 1e+02 % (the source-occlusion error did)."""
    from roadgonio.errors import percent
    assert percent(0.997) == "99.7 %"
    assert percent(1.0) == "100 %"
    assert percent(0.0123) == "1.23 %"
    assert "e" not in percent(2e-5)
    assert percent(2e-5) == "0.00200 %"
    assert percent(1.3e-9) == "<0.001 %" and percent(-1.3e-9) == ">-0.001 %"   # (before: 0.000000130 %)


def test_q0_of_a_table_without_a_complete_grid_cell_is_nan_without_a_warning():
    import warnings

    import numpy as np

    from roadgonio.surface.rtable import RTable
    t = RTable(np.full((29, 20), np.nan), name="x")
    t.r[5, 3] = 0.01
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert math.isnan(t.q0())
