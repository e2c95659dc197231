"""The Mitsuba backend refuses a horizon, a line-of-sight and a zero-nominal cell with exactly the
message of the one preamble (tests/unit/test_cellcheck.py: the numpy backends), and models a beam
limit that clips the footprint as the quadrature does."""
from __future__ import annotations

import math

import pytest

from roadgonio.engines import make_backend
from roadgonio.engines.cellcheck import check_cell
from roadgonio.errors import GeometryError
from roadgonio.instrument.config import load_instrument
from roadgonio.surface.model import RoadModel, RoadParams

from helpers import FAST_SETTINGS

LAB = load_instrument("lab")
BAD = {
    "horizon": (LAB.with_changes(source={"distance_m": 0.5, "radius_m": 0.1}), RoadModel.lambert(), (12.0, 0.0)),
    "line of sight": (LAB.with_changes(source={"distance_m": 2.0, "radius_m": 0.03}), RoadModel.lambert(),
                      (math.tan(math.radians(88.5)), 180.0)),
    "nominal": (LAB, RoadModel(RoadParams(k_phong=1.0, n_phong=1e5)), (0.0, 0.0)),
}


@pytest.mark.parametrize("check", list(BAD))
def test_the_mitsuba_backend_refuses_with_the_same_message(check):
    inst, model, cell = BAD[check]
    with pytest.raises(GeometryError) as err:
        check_cell(inst, model, *cell)
    with pytest.raises(GeometryError) as got:
        make_backend("mitsuba", inst, model, settings=FAST_SETTINGS["mitsuba"]).compute([cell])
    assert str(got.value) == str(err.value)


def test_a_clipping_beam_limit_is_modelled_by_the_mitsuba_backend():
    """(session 22) The kabatch integrator applies the hard cone (``beam_half_angle_deg``) to every
    source sample, so a cone that clips the footprint is modelled, no longer refused: on the wide
    instrument with a 10 deg cone, where the cut changes k_A by up to 24 % (0.80 uncut against
    1.04 at tan eps 1, beta 0), k_A agrees with the float64 Monte Carlo (numpy-mc, which applies
    the cone in its own statement, roadgonio.instrument.optics.source_coupling) within the combined
    SE, both converged. (The quadrature does not converge on the cone's jump at these cells: its
    estimate is no check here.)"""
    from roadgonio.instrument.optics import beam_clips_cells
    from roadgonio.surface.sample import resolve_sample
    from tolerances import n_sigma
    model = resolve_sample("R3").model
    wide = load_instrument("wide")
    inst = wide.with_changes(source={"beam_half_angle_deg": 10.0})
    cells = [(0.0, 0.0), (1.0, 0.0), (3.0, 30.0)]
    assert beam_clips_cells(inst, cells).all()
    ref = make_backend("numpy-mc", inst, model, rel_se=1e-3, seed=2).compute(cells)
    mit = make_backend("mitsuba", inst, model, rel_se=1e-3, seed=1).compute(cells)
    uncut = make_backend("mitsuba", wide, model, rel_se=1e-3, seed=1).compute(cells)
    for q, m in zip(ref, mit):
        assert m.converged and q.converged
        tol = n_sigma(min(m.se_dof, q.se_dof)) * math.hypot(m.se, q.se)
        assert abs(m.k_a - q.k_a) <= tol, (q.tan_eps, q.beta_deg, m.k_a, q.k_a, tol)
    assert abs(uncut[1].k_a - ref[1].k_a) > 20 * n_sigma(uncut[1].se_dof) * math.hypot(uncut[1].se, ref[1].se)

def test_a_model_that_underflows_float32_is_not_measured_rather_than_zero():
    """User audit, session 24: pure Phong of exponent 1e4 at tan eps 12, beta 10 through the portable
    preset is 5e-76 of the Lambertian at the nominal geometry in float64 and 0 in float32 over the whole
    aperture: the Mitsuba backend printed k_A = 0 +- 0, converged. It is NaN, not converged, with a
    note naming the underflow; a cell on the lobe of the same model is measured as before."""
    inst = load_instrument("portable")
    model = RoadModel(RoadParams(k_phong=1.0, n_phong=1e4))
    under, on_lobe = make_backend("mitsuba", inst, model, rel_se=1e-2, seed=0).compute([(12.0, 10.0), (12.0, 0.0)])
    assert math.isnan(under.k_a) and math.isnan(under.se) and not under.converged
    assert under.extra["float32_underflow"] and "underflow the float32 renderer" in under.extra["note"]
    assert math.isfinite(on_lobe.k_a) and on_lobe.k_a > 0 and "float32_underflow" not in on_lobe.extra
    assert math.isnan(under.se_dof)           # no degrees of freedom without an SE (user audit: 15)


def test_a_lobe_whose_tail_float32_loses_in_part_is_not_measured():
    """User audit, session 35: pure Phong of exponent 1e5 (k_phong 10) with the mirror direction on
    the cell tan eps 12, beta 0 (the lab preset observing at alpha 4.763642 deg): at beta 2.6 deg the
    rendered road signal is 4e-41 a sample, below float32's smallest normal number but not 0, and the
    renderer said 11434 +- 11, converged, where the float64 backends give 30516. Now such a cell is not
    measured; nearer the lobe (beta 2, 4e-24 a sample) the renderer agrees with the quadrature."""
    from tolerances import n_sigma
    inst = load_instrument("lab").with_changes(observation={"alpha_deg": 4.763642})
    model = RoadModel(RoadParams(k_phong=10.0, n_phong=1e5))
    near, tail = make_backend("mitsuba", inst, model, rel_se=2e-3, seed=0).compute([(12.0, 2.0), (12.0, 2.6)])
    assert math.isnan(tail.k_a) and math.isnan(tail.se) and math.isnan(tail.se_dof) and not tail.converged
    assert tail.extra["float32_underflow"] and "smallest normal number" in tail.extra["note"]
    q = make_backend("quadrature", inst, model, rtol=1e-3).compute([(12.0, 2.0)])[0]
    assert q.converged and near.converged and "float32_underflow" not in near.extra
    assert abs(near.k_a - q.k_a) <= n_sigma(near.se_dof) * near.se + q.error_bound, (near.k_a, near.se, q.k_a)
