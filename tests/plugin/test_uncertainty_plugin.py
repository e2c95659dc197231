"""The uncertainty's aperture case with the Mitsuba backend (slow)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.instrument.config import load_instrument
from roadgonio.uncertainty import parse_sigma_spec, run_uncertainty

from helpers import UNCERTAINTY_MODEL as MODEL
from helpers import UNCERTAINTY_SPEC as SPEC
from tolerances import z_family


@pytest.mark.slow
def test_aperture_case_with_the_mitsuba_backend(mi):
    """The whole aperture path with the renderer: at zero error the aperture case is the no-aperture
    table times k_A, and k_A there agrees with an independent render (another seed) within their
    standard errors plus the surrogate's measured error; the surrogate stays below u(r)."""
    from roadgonio.engines import make_backend
    inst = load_instrument("portable")
    res = run_uncertainty(MODEL, inst, parse_sigma_spec(SPEC), trials=4000, seed=3, backend="mitsuba",
                          backend_settings={"rel_se": 1e-3, "seed": 11}, progress=False, n_validation=3)
    ap, no = res.cases["aperture"], res.cases["no_aperture"]
    cells = res.cells
    picks = [k for k, (t, b) in enumerate(zip(cells.tan_eps, cells.beta_deg))
             if (t, b) in {(12.0, 0.0), (12.0, 10.0), (4.0, 2.0), (1.0, 45.0), (0.0, 0.0)}]
    assert len(picks) == 5
    independent = make_backend("mitsuba", inst, MODEL, rel_se=1e-3, seed=12).compute(
        [(float(cells.tan_eps[k]), float(cells.beta_deg[k])) for k in picks])
    for k, ref in zip(picks, independent):
        ka_in_table = ap.nominal[k] / no.nominal[k]
        allowed = z_family(len(picks)) * math.sqrt(2) * ref.se + res.surrogate.rel_err_max[k] * ref.k_a
        assert abs(ka_in_table - ref.k_a) <= allowed, (cells.tan_eps[k], cells.beta_deg[k], ka_in_table, ref.k_a)
    u_rel = ap.mc["u"][: len(cells.tan_eps)] / np.abs(ap.mc["mean"][: len(cells.tan_eps)])
    assert res.surrogate.summary(u_rel)["err_over_u_max"] < 1.0
