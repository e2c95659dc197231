"""The batched Mitsuba engine with a fixed-height source (plugins/ka_batch.py: one D_S per cell in
one launch) against the float64 quadrature of the arc instrument at each cell's distance."""
from __future__ import annotations

import math

from roadgonio.instrument.config import Instrument

from helpers import ROAD, preset
from tolerances import z_family

#: cells of very different D_S (1 m ... 12 m) batched together
CELLS = [(12.0, 2.0), (0.0, 0.0), (4.0, 10.0), (1.0, 45.0), (8.0, 5.0), (2.0, 180.0)]


def test_batched_fixed_height_cells_agree_with_the_arc_quadrature_at_their_distance():
    from roadgonio.engines import make_backend
    from roadgonio.engines.validate import FLOAT32_FLOOR
    inst = preset("corridor")
    m = make_backend("mitsuba", inst, ROAD, rel_se=1e-3, seed=3).compute(CELLS)
    z = z_family(len(CELLS))
    for (t, b), a in zip(CELLS, m):
        d = inst.to_dict()
        d["source"] = {"distance_m": math.hypot(1.0, 1.0 * t), "radius_m": inst.source.radius_m}
        q = make_backend("quadrature", Instrument.from_dict(d), ROAD, rtol=1e-4).compute([(t, b)])[0]
        assert a.converged and math.isfinite(q.error_bound)   # a bound, reached or not, is still a bound
        assert abs(a.k_a - q.k_a) <= z * a.se + q.error_bound + FLOAT32_FLOOR["mitsuba"] * abs(q.k_a), (t, b, a, q)
