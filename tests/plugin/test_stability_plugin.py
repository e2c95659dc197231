"""Numerical stability with the renderer: Mitsuba's float32 k_A against the float64 quadrature."""
from __future__ import annotations

import pytest

from roadgonio.engines import make_backend


def test_mitsuba_float32_against_quadrature(mi, lab, r3like):
    """The float32 renderer against float64 quadrature: within 4 SE plus the measured float32 floor."""
    from roadgonio.engines.validate import FLOAT32_FLOOR, compare
    pytest.importorskip("roadgonio.engines.mitsuba.backend")
    model = r3like
    inst = lab()
    quad = make_backend("quadrature", inst, model, rtol=1e-6)
    mit = make_backend("mitsuba", inst, model, rel_se=1e-3, seed=3)
    for cell in [(12.0, 0.0), (4.0, 2.0), (0.0, 0.0), (2.0, 180.0)]:
        row = compare(quad.compute_cell(*cell), mit.compute([cell])[0], FLOAT32_FLOOR["mitsuba"])
        assert row.ok, row
