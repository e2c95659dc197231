"""The Python API (roadgonio.api) with the Mitsuba backend."""
from __future__ import annotations

import math


import roadgonio as rg
from tolerances import n_sigma


def test_mitsuba_backend_keeps_the_selected_variant(mi, r3like):
    c = rg.ka_cell("portable", r3like, 4, 0, accuracy="fast", seed=3)
    assert mi.variant() == "llvm_ad_rgb" and math.isfinite(c.se) and math.isnan(c.error_bound)
    q = rg.ka_cell("portable", r3like, 4, 0, backend="quadrature", rel_se=1e-4)
    assert c.converged and q.converged
    # N_SIGMA SE (the t quantile of the SE's degrees of freedom) + float32 floor
    assert abs(c.k_a - q.k_a) <= n_sigma(c.se_dof) * c.se + q.error_bound + 1e-5 * q.k_a
