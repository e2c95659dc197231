"""The float64 quadrature backend of k_A (roadgonio.engines.quadrature): disc rules, error control,
Lambert = 1 for any instrument, the ideal limit, geometry and input errors."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.errors import GeometryError, InputError
from roadgonio.instrument.config import Instrument, load_instrument
from roadgonio.engines import ideal_ratio, make_backend
from roadgonio.engines.quadrature import disc_rule, split_disc_rule
from roadgonio.surface.model import RoadModel, RoadParams
from tolerances import z_family

#: Disc-rule exactness checked at this tolerance (float64 rounding of a few hundred nodes).
RULE_TOL = 1e-12
#: Lambertian sample: k_A = 1 up to float64 rounding of the two sums (identical up to 1/pi).
LAMBERT_TOL = 1e-12
#: The claimed error of a cell (CellResult.error_bound) may underestimate the true error by at most this factor.
SE_HONESTY = 3.0


@pytest.mark.parametrize("focus", [0j, 0.6j, 0.3 - 0.5j])
def test_disc_rule_moments(focus):
    x, y, w = disc_rule(12, 12, focus)
    assert np.all(x * x + y * y <= 1.0 + 1e-15)
    assert w.sum() == pytest.approx(1.0, abs=RULE_TOL)
    assert np.all(w > 0)
    # mean of r^2 over the unit disc = 1/2, of x^4 = 1/8, of x y = 0; of (x + 2y)^2 = 5/4
    assert w @ (x * x + y * y) == pytest.approx(0.5, abs=1e-9)
    assert w @ x ** 4 == pytest.approx(1 / 8, abs=1e-9)
    assert w @ (x + 2 * y) ** 2 == pytest.approx(5 / 4, abs=1e-9)


@pytest.mark.parametrize("chord", [(1.0, 0.0, 0.0), (0.6, -0.8, 0.35), (0.0, 1.0, -0.9)])
def test_split_disc_rule_moments(chord):
    """The disc cut on a chord: both segments together are the whole disc (the same moments)."""
    x, y, w = split_disc_rule(10, 10, chord)
    assert np.all(x * x + y * y <= 1.0 + 1e-15) and np.all(w > 0)
    assert w.sum() == pytest.approx(1.0, abs=RULE_TOL)
    assert w @ (x * x + y * y) == pytest.approx(0.5, abs=1e-9)
    assert w @ (x + 2 * y) ** 2 == pytest.approx(5 / 4, abs=1e-9)
    # the mean of |n . p - c| (a kink on the chord) is exact too: a polynomial on each segment
    nx, ny, c = chord
    g = lambda px, py: np.abs(nx * px + ny * py - c)
    fine_x, fine_y, fine_w = disc_rule(14, 14)
    assert w @ g(x, y) == pytest.approx(fine_w @ g(fine_x, fine_y), rel=1e-4)


def test_disc_rule_point_and_anisotropy():
    x, y, w = disc_rule(-1, -1)
    assert x.tolist() == [0.0] and y.tolist() == [0.0] and w.tolist() == [1.0]
    x, y, w = disc_rule(5, 1)        # 8 x 2 nodes
    assert x.size == 16


def test_detector_nodes_are_written_once_for_the_quadrature_and_eta():
    """The detected rays of the pupil x field rule (engines.rules.detector_nodes): weights that sum
    to 1, hits on the sample plane along the rays, and the very nodes both the quadrature backend
    and eta integrate over; neither eta nor the design's metrics import a backend module for them."""
    import ast
    from pathlib import Path

    from roadgonio.arrays import NumpyOps
    from roadgonio.engines import rules
    from roadgonio.engines.calibration import _EtaIntegrator
    from roadgonio.instrument import optics
    inst = load_instrument("portable")
    det = optics.detector_geometry(inst)
    nodes = rules.detector_nodes(det, (3, 2), (2, 3), 0.3j, 0j)
    assert nodes["x"].size == nodes["np"] * nodes["nf"] == 4 * 3 * 3 * 4
    assert nodes["w"].sum() == pytest.approx(1.0, rel=RULE_TOL) and np.all(nodes["w"] > 0)
    # each hit lies on its ray: from the pupil point along -wo down to z = 0
    px, py, _ = disc_rule(3, 2, 0.3j)
    o, _, _ = optics.detector_ray(NumpyOps, det, (np.repeat(px, nodes["nf"]), np.repeat(py, nodes["nf"])),
                                  (np.zeros(nodes["x"].size), np.zeros(nodes["x"].size)))
    t = o[2] / nodes["wo"][2]
    np.testing.assert_allclose(nodes["x"], o[0] - t * nodes["wo"][0], atol=1e-12)
    quad = make_backend("quadrature", inst, RoadModel.lambert())
    quad = getattr(quad, "inner", quad)
    eta = _EtaIntegrator(inst)
    for lp, lf in [((2, 2), (3, 1)), ((-1, -1), (4, 4))]:
        a, b = quad._detector(lp, lf), eta.detector_nodes(lp, lf)
        for k in ("x", "y", "w"):
            np.testing.assert_array_equal(a[k], b[k])
    root = Path(rules.__file__).resolve().parents[2]
    for rel in ("roadgonio/engines/calibration.py", "roadgonio/design/metrics.py"):
        tree = ast.parse((root / rel).read_text(encoding="utf-8"))
        mods = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert "roadgonio.engines.quadrature" not in mods, rel


@pytest.mark.parametrize("preset, changes", [
    ("lab", {}),
    ("portable", {}),
    ("lab", {"detector": {"focus_m": "inf"}}),
    ("lab", {"source": {"radius_m": 0.0}}),
    ("lab", {"detector": {"pupil_radius_m": 0.0}}),
    ("lab", {"detector": {"field_half_angle_deg": 0.0}}),
    ("lab", {"source": {"beam_half_angle_deg": 2.0}}),
])
def test_lambert_is_one_for_any_instrument(preset, changes):
    inst = load_instrument(preset).with_changes(**changes)
    b = make_backend("quadrature", inst, RoadModel.lambert())
    for res in b.compute([(0.0, 0.0), (12.0, 0.0), (3.0, 180.0)]):
        assert res.k_a == pytest.approx(1.0, abs=LAMBERT_TOL)
        assert math.isfinite(res.error_bound) and res.error_bound <= 1e-10 and math.isnan(res.se)


def test_ideal_instrument_gives_one(lab, r3like):
    inst = lab(source={"radius_m": 0.0}, detector={"pupil_radius_m": 0.0, "field_half_angle_deg": 0.0})
    b = make_backend("quadrature", inst, r3like)
    for res in b.compute([(0.0, 0.0), (12.0, 0.0), (4.0, 5.0), (1.0, 180.0)]):
        assert res.k_a == pytest.approx(1.0, abs=1e-12)
        assert res.samples <= 2            # nothing to integrate: one node (plus the focus probe)


def test_error_estimate_is_honest_and_meets_rtol(lab, r3like):
    """rtol 1e-4 and 1e-3 results against a converged reference (rtol 1e-7) on the lab preset."""
    model = r3like
    ref = make_backend("quadrature", lab(), model, rtol=1e-7)
    cells = [(12.0, 0.0), (4.0, 10.0), (0.0, 0.0)]
    refs = {c: ref.compute_cell(*c) for c in cells}
    for rtol in (1e-3, 1e-4):
        b = make_backend("quadrature", lab(), model, rtol=rtol)
        for c in cells:
            r = b.compute_cell(*c)
            true_err = abs(r.k_a - refs[c].k_a)
            assert r.extra["converged"]
            assert r.error_bound <= rtol * r.k_a
            assert true_err <= SE_HONESTY * r.error_bound + 1e-12, (c, rtol, true_err, r.error_bound)


def test_focus_and_plain_rules_agree(r3like):
    model = r3like
    inst = load_instrument("portable")
    a = make_backend("quadrature", inst, model, rtol=1e-5, focus=True).compute_cell(3.0, 20.0)
    b = make_backend("quadrature", inst, model, rtol=1e-5, focus=False).compute_cell(3.0, 20.0)
    assert a.k_a == pytest.approx(b.k_a, abs=a.error_bound + b.error_bound)


def test_k_a_matches_ratio_definition_at_small_apertures(lab, r3like):
    """With tiny apertures the signal ratio tends to the ideal ratio: k_A -> 1."""
    inst = lab(source={"radius_m": 1e-5}, detector={"pupil_radius_m": 1e-5, "field_half_angle_deg": 1e-4})
    r = make_backend("quadrature", inst, r3like, rtol=1e-8).compute_cell(6.0, 2.0)
    assert r.k_a == pytest.approx(1.0, abs=1e-6)


def test_settings_and_presets(lab, r3like):
    b = make_backend("quadrature", lab(), r3like, accuracy="fast")
    from roadgonio.engines.registry import BACKENDS
    assert b.settings()["rtol"] == BACKENDS["quadrature"].presets["fast"]["rtol"]
    assert b.name == "quadrature"
    assert make_backend("quadrature", lab(), r3like, rtol=3e-5).settings()["rtol"] == 3e-5


@pytest.mark.parametrize("kwargs", [{"rtol": 0.0}, {"rtol": 2.0}, {"rtol": "x"}, {"rtol": "0.01"}, {"rtol": True},
                                    {"bogus": 1}, {"accuracy": "ultra"}])
def test_bad_settings(kwargs, lab, r3like):
    with pytest.raises(InputError):
        make_backend("quadrature", lab(), r3like, **kwargs)


def test_mesh_sample_points_to_mitsuba(tmp_path, lab, r3like):
    mesh = tmp_path / "s.ply"
    mesh.write_text("ply\n")
    d = lab().to_dict()
    d["sample"] = {"mesh": str(mesh)}
    inst = Instrument.from_dict(d)
    with pytest.raises(InputError, match="mitsuba"):
        make_backend("quadrature", inst, r3like)


def test_geometry_errors(lab, r3like):
    with pytest.raises(GeometryError, match="footprint"):
        make_backend("quadrature", lab(sample={"size_x_m": 0.2}), r3like)
    inst = lab(source={"distance_m": 0.5, "radius_m": 0.1})
    b = make_backend("quadrature", inst, r3like)
    with pytest.raises(GeometryError, match="horizon"):
        b.compute_cell(12.0, 0.0)


def test_zero_nominal_brdf_is_an_error(lab):
    # a pure Phong lobe of huge exponent is 0 (underflow) at the nominal geometry of tan 0
    model = RoadModel(RoadParams(k_phong=1.0, n_phong=1e5))
    assert ideal_ratio(model, lab(), 0.0, 0.0) == 0.0
    with pytest.raises(GeometryError, match="undefined"):
        make_backend("quadrature", lab(), model).compute_cell(0.0, 0.0)


def test_on_cell_callback_and_order(lab, r3like):
    seen = []
    cells = [(2.0, 5.0), (0.0, 0.0)]
    out = make_backend("quadrature", lab(), r3like).compute(cells, on_cell=seen.append)
    assert [(r.tan_eps, r.beta_deg) for r in out] == cells
    assert seen == out


def test_field_sensitivity_profile_in_the_quadrature_and_monte_carlo(r3like_params):
    """With k_D falling to 0.3 at the field edge: Lambert still gives k_A = 1, the quadrature and the
    float64 Monte Carlo agree within 4 SE, and k_A moves away from the uniform-field value."""
    from roadgonio.engines import make_backend
    inst = load_instrument("portable")
    vign = inst.with_changes(detector={"field_edge_sensitivity": 0.3})
    lam = make_backend("quadrature", vign, RoadModel.lambert(), rtol=1e-8).compute([(4.0, 0.0)])[0]
    assert abs(lam.k_a - 1.0) < 1e-9
    model = RoadModel(RoadParams(**r3like_params))
    cells = [(4.0, 0.0), (12.0, 2.0)]
    # rtol 1e-4: at 1e-6 the vignetted cell (4, 0) stops at the cap (5e-6 reached), at 1e-5 the
    # uniform one (2.8e-5); a comparison with a reference that did not converge proves nothing
    q = make_backend("quadrature", vign, model, rtol=1e-4).compute(cells)
    m = make_backend("numpy-mc", vign, model, rel_se=1e-3, seed=3).compute(cells)
    for a, b in zip(q, m):
        assert a.converged and b.converged, (a, b)
        assert abs(a.k_a - b.k_a) <= z_family(len(cells)) * b.se + a.error_bound
    uniform = make_backend("quadrature", inst, model, rtol=1e-4).compute(cells)
    assert all(u.converged for u in uniform)
    assert all(abs(a.k_a - u.k_a) > 10 * (a.error_bound + u.error_bound) for a, u in zip(q, uniform))


@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_converged_means_the_estimate_met_rtol_also_at_the_cap():
    """A cell that reaches max_evals while a stale direction share still exceeds its part, but
    whose refreshed estimate meets rtol, is converged (it was reported as not converged with an
    estimate 2.9e-5 below rtol 1e-4: vignetted portable, tan eps 4, beta 0); one whose estimate
    does not meet rtol is not. converged <=> error_bound <= rtol |k_A| in every case."""
    from roadgonio.engines import make_backend
    vign = load_instrument("portable").with_changes(detector={"field_edge_sensitivity": 0.3})
    # a sharp lobe (n_phong 1000; the model of tests/helpers.py ROAD)
    model = RoadModel(RoadParams(k_diff=0.05, k_phong=1.0, n_phong=1000.0, k_retro=0.2, n_retro=50.0, k_exp=0.1,
                                 p=1.0, h=2.0, mu=0.1, g_a=0.0, g_b=-1.0, g_c=2.6, g_t=2.0, theta_l_deg=88.0))
    seen = set()
    for rtol in (1e-4, 1e-6):
        r = make_backend("quadrature", vign, model, rtol=rtol).compute_cell(4.0, 0.0)
        assert r.converged == (r.error_bound <= rtol * abs(r.k_a)), (rtol, r)
        seen.add(r.converged)
    assert seen == {True, False}          # both sides of the rule are exercised


def _bound_holds_against_the_reference(inst, model, family: int) -> None:
    """quadrature at fast and default against the float64 reference at precise (standing for the
    truth, its own SE allowed at the family threshold): |error| <= error_bound on every cell."""
    cells = [(2.0, 0.0), (4.0, 0.0), (8.0, 0.0), (12.0, 0.0), (12.0, 5.0)]
    ref = {(r.tan_eps, r.beta_deg): r for r in
           make_backend("reference", inst, model, accuracy="precise", seed=7).compute(cells)}
    z = z_family(family * len(cells))
    for accuracy in ("fast", "default"):
        for r in make_backend("quadrature", inst, model, accuracy=accuracy).compute(cells):
            c = ref[(r.tan_eps, r.beta_deg)]
            assert r.converged and c.converged, (r, c)
            assert abs(r.k_a - c.k_a) <= r.error_bound + z * c.se, (accuracy, r.tan_eps, r.beta_deg, r.k_a,
                                                                  c.k_a, r.error_bound, c.se)


def test_error_bound_holds_for_a_point_detector(r3like):
    """Trial 7, defect 2: with pupil and field 0 the source disc is the only integral, and the
    empirical term's kink in |beta| lies on one chord of it (through the centre at beta = 0).
    Across the kink the whole-disc Gauss rule converged as n^-2 and the change between two levels
    understated the error (1.1-1.4x beyond error_bound at fast and default). The true error must
    be within the bound (the float64 reference at precise, its SE 1e-8 .. 1e-6, for the truth)."""
    inst = load_instrument("portable").with_changes(detector={"pupil_radius_m": 0.0, "field_half_angle_deg": 0.0})
    assert r3like.mirror_kink
    _bound_holds_against_the_reference(inst, r3like, 1)


@pytest.mark.parametrize("name", ["portable", "lab"])
@pytest.mark.parametrize("detector", [{"pupil_radius_m": 0.0}, {"field_half_angle_deg": 0.0}],
                         ids=["pinhole-with-field", "pupil-without-field"])
def test_error_bound_holds_for_a_half_degenerate_detector(name, detector, r3like):
    """The two cases between a single-ray detector (the source disc cut on the mirror chord, above)
    and a full one: a zero pupil with a field, or a pupil with a zero field. The detector is then one
    disc, the chord of the mirror plane moves over the source disc from detector node to node, and
    the whole-disc rule stays (QuadratureBackend._mirror_chord). Its error_bound must still bound
    the error at fast and default: measured within 0.75 of the bound on these cells (R3-like) and
    0.71 with the fitted R3, also at precise (0.34), so no cut is needed there; this keeps it so."""
    inst = load_instrument(name).with_changes(detector=detector)
    assert r3like.mirror_kink
    _bound_holds_against_the_reference(inst, r3like, 2)


@pytest.mark.parametrize("cell", [(1.0, 0.5), (2.0, 1.0), (4.0, 0.5), (12.0, 0.2)])
def test_mirror_chord_of_a_point_detector_lies_on_the_mirror_plane(cell, r3like):
    """The chord on which the single-ray detector's source rule is cut (QuadratureBackend._mirror_chord)
    is where the source disc meets the mirror plane, the vertical plane through the hit point (the
    sample centre) containing w_o: every source point on it has (w_i x w_o)_z = 0 (beta = 0 or 180
    deg), written out here from the instrument's w_o and the disc's frame. At these cells the chord
    is off the disc centre (|c| = 0.14 ... 0.62); a chord on the wrong side (c of the other sign)
    integrated as accurately in the end but cut the disc where the integrand is smooth and left the
    kink inside a segment (the n^-2 convergence that made the bound dishonest, trial 7); at beta = 0,
    where the other tests look, c = 0 and the sign does not matter."""
    from roadgonio.engines.quadrature import QuadratureBackend
    from roadgonio.instrument import optics
    inst = load_instrument("portable").with_changes(detector={"pupil_radius_m": 0.0, "field_half_angle_deg": 0.0})
    b = QuadratureBackend(inst, r3like)
    src = optics.source_geometry(inst, *cell)
    nx, ny, c = b._mirror_chord(src)
    assert 0.1 < abs(c) < 0.9
    wo = inst.w_o()
    half = math.sqrt(1.0 - c * c)
    for t in np.linspace(-0.9, 0.9, 7) * half:
        px, py = c * nx - t * ny, c * ny + t * nx
        s = src.centre + inst.source.radius_m * (px * src.s + py * src.t)       # from the hit point (0, 0, 0)
        cross = s[0] * wo[1] - s[1] * wo[0]
        assert abs(cross) <= 1e-12 * np.linalg.norm(s), (t, cross)


def test_a_converged_estimate_is_confirmed_one_level_finer_on_the_wide_preset():
    """User audit, session 24: on the wide preset with R3 the quadrature at `fast` reported tan eps 3,
    beta 25 converged at 1.263803 +- 2.0e-4 (error bound) where the truth is 1.265031: the rules one level
    coarser agreed by chance (changes of 1e-4), one level finer moved by 1.8e-3. A converged estimate is
    now confirmed one level finer in the directions that carry the error; its bound holds against the
    float64 reference (RQMC at rtol 1e-4, its SE allowed at the family threshold) at both cells the
    audit found."""
    from roadgonio.surface.sample import resolve_sample
    inst, model = load_instrument("wide"), resolve_sample("R3").model
    cells = [(3.0, 25.0), (5.0, 30.0)]
    ref = make_backend("reference", inst, model, rtol=1e-4, seed=3).compute(cells)
    z = z_family(len(cells))
    for r, c in zip(make_backend("quadrature", inst, model, accuracy="fast").compute(cells), ref):
        assert r.converged and c.converged, (r, c)
        assert abs(r.k_a - c.k_a) <= r.error_bound + z * c.se, (r.tan_eps, r.beta_deg, r.k_a, c.k_a, r.error_bound,
                                                              c.se)
