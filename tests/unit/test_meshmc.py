"""The numpy ray-casting Monte Carlo for mesh samples (roadgonio.engines.meshmc): the ray caster,
agreement with the flat-plane numpy MC on a triangulated plane, self-shadowing, and (plugin) with
the Mitsuba renderer on a corrugated mesh."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.engines import make_backend
from roadgonio.engines.meshmc import MeshCaster
from roadgonio.errors import GeometryError, InputError
from roadgonio.instrument.config import load_instrument
from helpers import grid_mesh, with_mesh
from tolerances import z_family



def test_caster_first_hit_and_shadow():
    tri = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                    [[0.0, 0.0, 0.5], [1.0, 0.0, 0.5], [0.0, 1.0, 0.5]]])
    c = MeshCaster(tri)
    o = np.array([[0.2, 0.2, 1.0], [0.2, 0.2, 1.0], [0.9, 0.9, 1.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    t, idx = c.first_hit(o, d)
    assert t[0] == pytest.approx(0.5) and idx[0] == 1          # the upper triangle first
    assert math.isinf(t[1]) and idx[1] == -1                   # pointing away
    assert math.isinf(t[2]) and idx[2] == -1                   # outside both triangles
    blocked = c.blocked(np.array([[0.2, 0.2, 0.1], [0.2, 0.2, 0.1]]), np.array([[0, 0, 1.0], [0, 0, 1.0]]),
                        np.array([0.3, 0.5]))
    assert blocked.tolist() == [False, True]
    # a grazing ray along a long thin slab finds the far triangle
    long = np.array([[[-5.0, -1.0, 0.0], [5.0, -1.0, 0.0], [5.0, 1.0, 0.0]],
                     [[-5.0, -1.0, 0.0], [5.0, 1.0, 0.0], [-5.0, 1.0, 0.0]]])
    c2 = MeshCaster(np.concatenate([long, tri + [0.0, 0.0, 0.0]]))
    a = math.radians(1.0)
    t2, i2 = c2.first_hit(np.array([[4.0, 0.0, 8.0 * math.tan(a)]]), np.array([[-math.cos(a), 0.0, -math.sin(a)]]))
    assert i2[0] in (0, 1) and t2[0] == pytest.approx(8.0 / math.cos(a), rel=1e-12)


def test_triangulated_plane_matches_the_flat_monte_carlo(tmp_path, r3like):
    """A plane cut into 800 shuffled triangles is the flat sample: both Monte Carlo estimators agree
    within their combined SE (the cell with the specular peak and a diffuse-like one)."""
    inst = load_instrument("lab")
    mesh = grid_mesh(tmp_path / "flat.ply", np.linspace(-1, 1, 41), np.linspace(-0.25, 0.25, 11), shuffle_seed=3)
    mi = with_mesh(inst, mesh)
    model = r3like
    cells = [(12.0, 0.0), (2.0, 90.0)]
    for cell in cells:
        a = make_backend("numpy-mc-mesh", mi, model, rel_se=3e-3, seed=1).compute([cell])[0]
        b = make_backend("numpy-mc", inst, model, rel_se=3e-3, seed=2).compute([cell])[0]
        z = (a.k_a - b.k_a) / math.hypot(a.se, b.se)
        assert abs(z) < z_family(len(cells)), (cell, a.k_a, b.k_a, z)
        assert a.se > 0 and a.converged


def test_self_shadowing_is_modelled(tmp_path, r3like):
    """A wall between the source and the footprint shades it: the mesh Monte Carlo says no light
    reaches the detected area (without shadow rays it would return a plausible k_A)."""
    import trimesh
    inst = load_instrument("lab")
    plane = trimesh.load(grid_mesh(tmp_path / "p.ply", np.linspace(-1, 1, 5), np.linspace(-0.25, 0.25, 3)))
    # a vertical wall at x = -0.9, 0.3 m high, facing +x (towards the footprint)
    wall = trimesh.Trimesh([[-0.9, -0.25, 0.0], [-0.9, 0.25, 0.0], [-0.9, 0.25, 0.3], [-0.9, -0.25, 0.3]],
                           [[0, 1, 2], [0, 2, 3]], process=False)
    both = trimesh.util.concatenate([plane, wall])
    both.export(tmp_path / "walled.ply")
    mi = with_mesh(inst, tmp_path / "walled.ply")
    with pytest.raises(GeometryError, match="no detected ray receives light"):
        make_backend("numpy-mc-mesh", mi, r3like, rel_se=1e-2, min_batches=2).compute([(12.0, 0.0)])
    # lit from behind the detector the wall does not matter
    r = make_backend("numpy-mc-mesh", mi, r3like, rel_se=1e-2, min_batches=2).compute([(1.0, 180.0)])[0]
    assert r.k_a > 0.5


def test_mesh_off_the_footprint_and_xml_are_errors(tmp_path, r3like):
    inst = load_instrument("lab")
    small = grid_mesh(tmp_path / "small.ply", np.linspace(-0.05, 0.05, 3), np.linspace(-0.05, 0.05, 3))
    with pytest.raises(GeometryError, match="miss the sample mesh") as err:
        make_backend("numpy-mc-mesh", with_mesh(inst, small), r3like, min_batches=2).compute([(2.0, 90.0)])
    # the error names the mesh file (user audit, session 19)
    assert (err.value.path, err.value.field) == (str(small), "sample.mesh")
    with pytest.raises(InputError, match="does not model a Mitsuba XML scene"):
        make_backend("numpy-mc-mesh", load_instrument("holder"), r3like)
    with pytest.raises(InputError, match="numpy-mc-mesh"):
        make_backend("numpy-mc", with_mesh(inst, small), r3like)


def test_results_do_not_depend_on_the_grouping_of_batches(tmp_path, r3like, monkeypatch):
    """Batches are evaluated several at a time (meshmc.GROUP_SAMPLES); their points are drawn batch
    by batch and the stopping rule is applied after each batch, so k_A, its SE and the number of
    batches are those of one batch at a time, bit for bit: at the minimum, past it (the 1/N rule),
    and at max_samples."""
    from roadgonio.engines import meshmc
    inst = load_instrument("portable")
    half_x, half_y = inst.sample.size_x_m / 2, inst.sample.size_y_m / 2
    mi = with_mesh(inst, grid_mesh(tmp_path / "flat.ply", np.linspace(-half_x, half_x, 5),
                                   np.linspace(-half_y, half_y, 3), shuffle_seed=2))
    runs = [dict(rel_se=3e-3, min_batches=16), dict(rel_se=3e-4, min_batches=4),
            dict(rel_se=1e-5, min_batches=4, max_samples=64 * 40)]
    cells = [(12.0, 0.0), (2.0, 0.0)]
    got = {}
    for group in (64, 64 * 7, 64 * 1000):
        monkeypatch.setattr(meshmc, "GROUP_SAMPLES", group)
        got[group] = [(r.k_a, r.se, r.extra["batches"], r.converged) for kw in runs
                      for r in make_backend("numpy-mc-mesh", mi, r3like, batch=64, seed=9, **kw).compute(cells)]
    assert got[64] == got[64 * 7] == got[64 * 1000]
    batches, converged = [g[2] for g in got[64]], [g[3] for g in got[64]]
    assert batches[:2] == [16, 16] and all(b > 4 for b in batches[2:4]) and batches[4:] == [40, 40], batches
    assert converged == [True] * 4 + [False] * 2


@pytest.mark.slow            # 720 runs, ~28 s: in CI by -m slow, out of the README's default run
def test_se_is_honest_at_the_fast_preset(tmp_path, r3like):
    """The mesh Monte Carlo's SE, as numpy-mc's (tests/unit/test_montecarlo.py): from 8 batch means
    it had 7 degrees of freedom and z = error / SE a t_7 law (mean z^2 7/5, far tails). On a flat
    mesh (8 shuffled triangles over the portable preset's sample) the float64 reference of the flat
    sample at precise is an independent truth (its SE added in quadrature, ~1 % of the mesh SE).
    Over m = 720 results (120 seeds x 6 cells at --accuracy fast) the sum of z^2 of a correct
    normal z is chi-square with m degrees of freedom: mean z^2 <= chi2.isf(ALPHA, m) / m (1.215),
    and no |z| beyond z_family(m)."""
    from helpers import assert_se_is_honest
    inst = load_instrument("portable")
    half_x, half_y = inst.sample.size_x_m / 2, inst.sample.size_y_m / 2
    mi = with_mesh(inst, grid_mesh(tmp_path / "flat.ply", np.linspace(-half_x, half_x, 3),
                                   np.linspace(-half_y, half_y, 3), shuffle_seed=4))
    assert_se_is_honest(lambda seed: make_backend("numpy-mc-mesh", mi, r3like, accuracy="fast", seed=seed),
                        make_backend("reference", inst, r3like, accuracy="precise", seed=5), range(1, 121))


def test_a_mesh_seen_from_below_is_an_error_not_k_a_zero(tmp_path, r3like):
    """(audit 22) a plane rising 2 deg towards a detector at alpha 1 deg is seen from below: the road
    channel was 0 and the Lambert one not, so k_A = 0 +- 0 'converged'. A back face reflects nothing
    in either channel; every ray on a back face is one GeometryError naming the mesh file."""
    inst = load_instrument("portable")
    mesh = grid_mesh(tmp_path / "rising.ply", np.linspace(-1, 1, 5), np.linspace(-0.3, 0.3, 3),
                     height=lambda x, y: math.tan(math.radians(2.0)) * x)
    with pytest.raises(GeometryError, match="back of the sample mesh") as err:
        make_backend("numpy-mc-mesh", with_mesh(inst, mesh), r3like, rel_se=1e-2, seed=1).compute([(2.0, 0.0)])
    assert "rising.ply" in str(err.value) and err.value.field == "sample.mesh"


def test_mesh_files_out_of_kind_are_named_for_what_they_are(tmp_path):
    """(audit 22) a mesh in millimetres passed where the same rectangle in metres is refused, and a
    closed solid was told to reverse its winding; absolute calibration ignored the mesh (eta is
    computed on the plane z = 0): refused with a mesh."""
    import trimesh
    from roadgonio.instrument.config import Instrument
    inst = load_instrument("portable")
    mm = grid_mesh(tmp_path / "mm.ply", np.linspace(-1000, 1000, 3), np.linspace(-300, 300, 3))
    from roadgonio.instrument.mesh import sample_trimesh
    with pytest.raises(InputError, match="millimetres") as err:
        sample_trimesh(with_mesh(inst, mm))
    assert err.value.field == "sample.mesh"
    # (user audit, session 38) 0.5 m x 0.2 m drawn in mm is under the 1000 m limit: a note, not silence
    from roadgonio.errors import ModelWarning
    small_mm = grid_mesh(tmp_path / "small_mm.ply", np.linspace(-250, 250, 3), np.linspace(-100, 100, 3))
    with pytest.warns(ModelWarning, match=r"spans 500 m, 500 times .* millimetres"):
        sample_trimesh(with_mesh(inst, small_mm))
    lab_mm = grid_mesh(tmp_path / "lab_mm.ply", np.linspace(-150, 150, 3), np.linspace(-100, 100, 3))
    with pytest.warns(ModelWarning, match=r"spans 300 m, 30 times"):      # missed at 50x (audit, session 38)
        sample_trimesh(with_mesh(load_instrument("lab"), lab_mm))
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error", ModelWarning)        # a sample in metres says nothing
        sample_trimesh(with_mesh(inst, grid_mesh(tmp_path / "m.ply", np.linspace(-0.5, 0.5, 3),
                                                 np.linspace(-0.15, 0.15, 3))))
    trimesh.creation.box(extents=(1.0, 0.5, 0.1)).export(tmp_path / "box.stl")
    with pytest.raises(InputError, match="closed solid"):
        sample_trimesh(with_mesh(inst, tmp_path / "box.stl"))
    flat = grid_mesh(tmp_path / "flat.ply", np.linspace(-1, 1, 3), np.linspace(-0.3, 0.3, 3))
    d = with_mesh(inst, flat).to_dict()
    d["calibration"] = {"mode": "absolute"}
    with pytest.raises(InputError, match="absolute calibration .* not for a mesh sample") as err:
        Instrument.from_dict(d)
    assert err.value.field == "calibration.mode"


def test_a_mesh_vertex_that_is_not_a_number_is_named(tmp_path):
    """(audit 28) trimesh drops the triangles of a NaN vertex, and the hole was reported as '10310 of
    20608 detector rays do not hit the sample': the vertex is named instead."""
    from roadgonio.instrument.mesh import sample_trimesh
    obj = tmp_path / "nan.obj"
    obj.write_text("v -1 -0.5 0\nv nan -0.5 0\nv 1 0.5 0\nv -1 0.5 0\nf 1 2 3\nf 1 3 4\n")
    with pytest.raises(InputError, match=r"1 triangle\(s\) .*\(vertex 2") as err:
        sample_trimesh(with_mesh(load_instrument("portable"), obj))
    assert err.value.field == "sample.mesh"
