"""Generator of the synthetic measurements in tests/data (run: python tests/data/make_synthetic_measurements.py).

A known surface (roadgonio.correction.synthetic.r2_like_truth: the smooth variant with hand-chosen
parameters, not the fit of any table) measured by tests/data/medium.toml under Lambert and under
absolute calibration, k_A by the float64 quadrature (rtol 1e-5; every cell converged), 1 % normal
noise (seed 1), on 12 of the 20 beta columns of the standard cells (a smaller table keeps the
default test run short). Writes synthetic_medium_<mode>.csv (measured, r x 1e4) and
synthetic_medium_<mode>_truth.csv (true r and true k_A per cell) next to this script.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
BETAS = (0, 2, 5, 10, 15, 20, 30, 45, 60, 90, 135, 180)


def mask() -> np.ndarray:
    from roadgonio.correction.synthetic import standard_mask
    from roadgonio.geometry import BETA_GRID_DEG
    m = standard_mask()
    m[:, ~np.isin(BETA_GRID_DEG, BETAS)] = False
    return m


def main() -> int:
    from roadgonio.correction.synthetic import r2_like_truth, synthesize
    from roadgonio.instrument.config import Instrument
    from roadgonio.surface.rtable import RTable
    base = Instrument.load(HERE / "medium.toml")
    for mode in ("lambert", "absolute"):
        inst = base.with_changes(calibration={"mode": mode})
        s = synthesize(r2_like_truth(), inst, noise=0.01, seed=1, backend="quadrature",
                       backend_settings={"rtol": 1e-5}, mask=mask(), name=f"synthetic_medium_{mode}")
        s.measured.write_csv(HERE / f"synthetic_medium_{mode}.csv")
        RTable(s.truth.r, name="truth", source=f"true r of {r2_like_truth().name} (nominal geometry)").write_csv(
            HERE / f"synthetic_medium_{mode}_truth.csv", digits=10)
        RTable(s.k_a, name="k_a", source=f"true k_A ({mode} calibration, quadrature rtol 1e-5)").write_csv(
            HERE / f"synthetic_medium_{mode}_ka.csv", scale=1.0, digits=10)
        print(mode, "k_A", np.nanmin(s.k_a), np.nanmax(s.k_a), "cells", int(np.isfinite(s.k_a).sum()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
