"""Generator of tests/data/noisefree_portable_absolute.npz (run: python tests/data/make_noisefree_portable_absolute.py).

An eq. 4 surface (the power model with the parameters below: CIE R3's power fit of session 22, written
out so that a later fit of R3 does not change the fixture) measured without noise by the bundled
``portable`` preset under the absolute calibration (paper eq. 2), k_A by the float64 quadrature
(rtol 1e-6), on the standard cells. Until audit 23, ``correct --reference self`` fitted this table at a
Birge ratio of 12.8 with k_A off by up to 13.5 %: stage A's multi-start search had missed the
model's basin (docs/correction.md, "The method"). Stored exactly (binary, ``.npz``): the search is
chaotic, and the same table written to 12 digits (4.5e-12 relative) leads the first search into the
basin. Writes noisefree_portable_absolute.npz (``r``: the measured r in sr^-1 on the 29 x 20 grid of
tan eps x beta, NaN where not measured; ``k_a``: the exact k_A) next to this script.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
TRUTH = {"k_diff": 0.02916325830338534, "k_phong": 2.24629829695249, "n_phong": 43.334513669098484,
         "k_retro": 0.05078351374226545, "n_retro": 11.271000192662314, "k_exp": 0.08999940427520779,
         "p": 2.258542810139304, "h": 0.5059878709969758, "mu": 0.031711466340741006}


def truth():
    from roadgonio.surface.model import RoadModel, RoadParams
    return RoadModel(RoadParams(**TRUTH), "power", name="R3-power-session-22")


def main() -> int:
    from roadgonio.correction.synthetic import synthesize
    from roadgonio.instrument.config import load_instrument
    inst = load_instrument("portable").with_changes(calibration={"mode": "absolute"})
    s = synthesize(truth(), inst, noise=0.0, backend="quadrature", backend_settings={"rtol": 1e-6},
                   name="noisefree_portable_absolute")
    np.savez(HERE / "noisefree_portable_absolute.npz", r=s.measured.r, k_a=s.k_a)
    print("k_A", np.nanmin(s.k_a), np.nanmax(s.k_a), "cells", int(np.isfinite(s.k_a).sum()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
