"""`correct` through a housed instrument (issue 19 kept working once issue 18 landed): the k_A that
divides the table is the Mitsuba backend's, which models the housing's shade and stray light, while
the fit's ray bundles leave them out (and say so)."""
from __future__ import annotations

import numpy as np
import pytest

from roadgonio import api
from roadgonio.surface.rtable import bundled_table

#: k_A of the housed and the bare instrument are judged different where they differ by more than this
#: many combined standard errors (both Monte Carlo, fixed seeds).
Z_DIFFERENT = 4.0


@pytest.mark.slow
def test_a_housed_instrument_is_corrected_with_its_housing():
    """R3's columns beta 0 and 90 deg (where docs/straylight.md finds the stray light: tan eps 5,
    beta 0 through the Lambert calibration's diffuser; tan eps 10.5-12, beta 90-120) measured and
    corrected with --forward surface through scenes/portable_housed.toml and through the bare
    portable instrument: both run end to end, the housed correction's k_A (from the Mitsuba backend)
    differs from the bare one's by more than Z_DIFFERENT combined SEs at some grazing cell, and the
    provenance says what the fit's bundles leave out."""
    t = bundled_table("R3")
    keep = np.zeros(t.r.shape, dtype=bool)
    keep[:, [list(t.beta_deg).index(0.0), list(t.beta_deg).index(90.0)]] = True
    meas = t.with_values(np.where(keep & t.mask, t.r, np.nan), name="r3_two_columns")
    opts = dict(forward="surface", u_measured="1%", backend="mitsuba", rays=64, model_variant="smooth",
                plots=False)
    res = {name: api.correct(meas, name, **opts) for name in ("portable_housed", "portable")}
    parts = {name: r.extra["surface"].parts[0] for name, r in res.items()}
    m = meas.mask
    k_h, se_h = parts["portable_housed"].k_backend[m], parts["portable_housed"].k_se[m]
    k_b, se_b = parts["portable"].k_backend[m], parts["portable"].k_se[m]
    z = (k_h - k_b) / np.sqrt(se_h ** 2 + se_b ** 2)
    assert np.all(np.isfinite(z)) and np.max(np.abs(z)) > Z_DIFFERENT, z
    for r in res.values():
        assert np.all(np.isfinite(r.corrected.r[m])) and np.all(r.u_corrected[m] > 0)
    limits = res["portable_housed"].provenance.get("forward_model_limits")
    assert limits is not None and "[housing]" in limits
    assert res["portable"].provenance.get("forward_model_limits") is None
