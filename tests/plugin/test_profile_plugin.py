"""The detector's sensitivity map in the Mitsuba backend (the lummeter sensor evaluates the same
map_bilinear as the numpy backends, over Dr.Jit arrays), and the source's beam profile, which the
Mitsuba scene refuses until its kernel models it (docs/conventions.md section 4)."""
from __future__ import annotations

import numpy as np
import pytest

from helpers import ROAD, preset, write_map_csv
from roadgonio.engines import make_backend
from roadgonio.errors import InputError
from tolerances import z_family

CELLS = [(12.0, 0.0), (4.0, 2.0), (1.0, 30.0)]


def test_a_gradient_map_agrees_with_the_quadrature(mi, tmp_path):
    """A non-radial map (a gradient up and to the right of the field): the float32 kernel's k_A agrees
    with the float64 quadrature within z_family SE + its error bound, and differs from the uniform
    field's by far more (the map is read, oriented and gathered on the device)."""
    p = write_map_csv(tmp_path / "grad.csv", lambda x, y: 1.0 + 0.3 * x + 0.5 * y, 41)
    base = preset("portable")
    inst = base.with_changes(detector={"field_sensitivity": str(p)})
    q = make_backend("quadrature", inst, ROAD, rtol=1e-5, max_evals=20_000_000).compute(CELLS)
    u = make_backend("quadrature", base, ROAD, rtol=1e-5).compute(CELLS)
    m = make_backend("mitsuba", inst, ROAD, rel_se=5e-4, seed=2).compute(CELLS)
    for a, b, c in zip(q, m, u):
        assert a.converged and b.converged and c.converged
        assert abs(a.k_a - b.k_a) <= z_family(len(CELLS)) * b.se + a.error_bound, (a.k_a, b.k_a, b.se)
    assert max(abs(a.k_a - c.k_a) for a, c in zip(q, u)) > 20 * max(b.se for b in m)


def test_a_uniform_map_is_no_map_bit_for_bit(mi, tmp_path):
    p = write_map_csv(tmp_path / "flat.csv", lambda x, y: 2.5 + 0.0 * x, 5)
    base = preset("portable")
    a = make_backend("mitsuba", base.with_changes(detector={"field_sensitivity": str(p)}), ROAD, rel_se=1e-3,
                     seed=4).compute(CELLS)
    b = make_backend("mitsuba", base, ROAD, rel_se=1e-3, seed=4).compute(CELLS)
    assert [(r.k_a, r.se) for r in a] == [(r.k_a, r.se) for r in b]


@pytest.mark.parametrize("changes, key", [({"beam_sigma_deg": 5.0}, "source.beam_sigma_deg"),
                                          ({"aperture_edge_radiance": 0.5}, "source.aperture_edge_radiance")])
def test_a_profiled_source_is_refused_with_one_line(mi, tmp_path, changes, key):
    """Until the kabatch kernel models the beam profile, the Mitsuba backend (through the registry
    or built directly) and `render` refuse it, naming the key."""
    import roadgonio as rg
    from roadgonio.engines.mitsuba.backend import MitsubaBackend
    inst = preset("portable").with_changes(source=changes)
    for build in (lambda: make_backend("mitsuba", inst, ROAD), lambda: MitsubaBackend(inst, ROAD),
                  lambda: rg.render(inst, "R3", 4.0, 2.0, tmp_path / "r")):
        with pytest.raises(InputError) as err:
            build()
        assert err.value.field == key and "\n" not in str(err.value)
    assert not (tmp_path / "r").exists()
    assert np.isfinite(make_backend("quadrature", inst, ROAD, rtol=1e-3).compute_cell(4.0, 2.0).k_a)
