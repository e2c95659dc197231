"""The source path (docs/conventions.md section 4): ``[source] path = "arc"`` (the default) keeps D_S
for every cell; ``"fixed_height"`` moves the source at ``height_m`` above the sample, D_S = h / cos eps.
A fixed-height instrument at a cell is the arc instrument whose distance is that cell's D_S: every
numpy backend is checked against that equivalence (the arc is the independently validated case), and
the formula against an independent float64 construction (the source centre's height is h)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.engines import make_backend
from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument, Source
from roadgonio.instrument.optics import source_distance_m, source_geometry

from helpers import ROAD, preset
from tolerances import ROUND_TOL, z_family

CELLS = [(0.0, 0.0), (1.0, 10.0), (4.0, 2.0), (12.0, 0.0), (3.0, 180.0)]


def corridor(**changes) -> Instrument:
    return preset("corridor").with_changes(**changes) if changes else preset("corridor")


def arc_at(inst: Instrument, tan_eps: float) -> Instrument:
    """The arc instrument whose distance is the fixed-height source's distance at ``tan_eps``,
    written from the geometry (hypotenuse of height h and horizontal run h tan eps), not the formula."""
    h = inst.source.height_m
    d = math.hypot(h, h * tan_eps)
    src = {"distance_m": d, "radius_m": inst.source.radius_m}
    dd = inst.to_dict()
    dd["source"] = src
    return Instrument.from_dict(dd)


def test_distance_is_height_over_cos_eps_and_the_centre_stays_at_the_height():
    inst = corridor()
    h = inst.source.height_m
    for t, b in CELLS:
        c = source_geometry(inst, t, b).centre
        assert abs(c[2] - h) <= ROUND_TOL * h                       # the rail is at height h
        assert abs(math.hypot(c[0], c[1]) - h * t) <= 1e-12 * max(1.0, h * t)  # horizontal run h tan eps
    t = np.array([c[0] for c in CELLS])
    assert np.allclose(source_distance_m(inst.source, t), [math.hypot(h, h * x) for x in t], rtol=ROUND_TOL)
    arc = Source(distance_m=2.0)
    assert source_distance_m(arc, 7.0) == 2.0 and np.all(source_distance_m(arc, t) == 2.0)


def test_the_arc_is_the_default_and_files_round_trip():
    lab = preset("lab")
    assert lab.source.path == "arc" and lab.source.length_m == lab.source.distance_m
    assert "path" not in lab.to_dict()["source"]                    # arc fingerprints do not change
    c = corridor()
    assert Instrument.from_dict(c.to_dict()).source == c.source
    assert c.source.length_key == "height_m" and c.source.length_m == 1.0


@pytest.mark.parametrize("source,field", [
    ({"path": "line", "distance_m": 1.0}, "source.path"),
    ({"path": "fixed_height"}, "source.height_m"),
    ({"path": "fixed_height", "height_m": 1.0, "distance_m": 1.0}, "source.distance_m"),
    ({"distance_m": 1.0, "height_m": 1.0}, "source.height_m"),
    ({"path": "fixed_height", "height_m": -1.0}, "source.height_m"),
    ({"path": "fixed_height", "height_m": 0.0}, "source.height_m"),     # mutation audit 11: 0 was accepted
    ({"path": "fixed_height", "height_m": 0.01, "radius_m": 0.02}, "source.radius_m"),
])
def test_bad_source_paths_are_one_line_errors(source, field):
    d = preset("lab").to_dict()
    d["source"] = source
    with pytest.raises(InputError) as e:
        Instrument.from_dict(d, path="x.toml")
    assert e.value.field == field and "x.toml" in str(e.value) and "\n" not in str(e.value)


def test_a_rail_height_without_its_path_says_which_path_it_belongs_to():
    """(User audit, session 43) The corridor's file without ``path`` but with ``height_m`` was told
    only that source.distance_m is missing: the error now names the path height_m belongs to."""
    d = preset("lab").to_dict()
    d["source"] = {"height_m": 1.0, "radius_m": 0.01}
    with pytest.raises(InputError) as e:
        Instrument.from_dict(d, path="x.toml")
    assert e.value.field == "source.distance_m" and 'path = "fixed_height"' in str(e.value)


def test_quadrature_of_a_fixed_height_cell_is_the_arc_at_its_distance():
    inst = corridor()
    q = make_backend("quadrature", inst, ROAD, rtol=1e-4).compute(CELLS)
    for (t, b), r in zip(CELLS, q):
        a = make_backend("quadrature", arc_at(inst, t), ROAD, rtol=1e-4).compute([(t, b)])[0]
        assert r.k_a == pytest.approx(a.k_a, rel=1e-9), (t, b)
    # the path matters: the same source on an arc at its tan-eps-0 distance differs at grazing light
    arc0 = make_backend("quadrature", arc_at(inst, 0.0), ROAD, rtol=1e-4).compute([(12.0, 0.0)])[0]
    assert abs(arc0.k_a - q[3].k_a) > 10 * (arc0.error_bound + q[3].error_bound)


def test_numpy_mc_of_a_fixed_height_instrument_agrees_with_the_arc_quadrature():
    inst = corridor()
    m = make_backend("numpy-mc", inst, ROAD, rel_se=3e-3, seed=5).compute(CELLS)
    z = z_family(len(CELLS))
    for (t, b), r in zip(CELLS, m):
        a = make_backend("quadrature", arc_at(inst, t), ROAD, rtol=1e-5).compute([(t, b)])[0]
        assert abs(r.k_a - a.k_a) <= z * r.se + a.error_bound, (t, b, r, a)


def test_a_backend_without_the_path_refuses_in_one_line(monkeypatch):
    from dataclasses import replace
    from roadgonio.engines import registry
    monkeypatch.setitem(registry.BACKENDS, "quadrature", replace(registry.BACKENDS["quadrature"], source_paths=("arc",)))
    with pytest.raises(InputError, match='does not model source.path = "fixed_height"') as e:
        make_backend("quadrature", corridor(), ROAD)
    assert e.value.field == "source.path"
