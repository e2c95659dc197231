"""Synthetic measurements for round trips: what an instrument would report for a known surface.

``measured r = r_true(nominal) x k_A(true model) x (1 + noise)``, k_A from an exact backend
(the float64 quadrature or numpy Monte Carlo by default, never the correction's ray bundles) under
the instrument's calibration, noise relative, normal, independent between cells, seeded. Used by
the tests and ``bench/bench_correct.py``, and by instrument makers who want to see what their
instrument does to a surface they know.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel, RoadParams
from roadgonio.surface.rtable import RTable, bundled_table


def r2_like_truth() -> RoadModel:
    """A surface that is not the fit of any bundled table: the ``smooth`` variant with hand-chosen
    parameters (S1 = 0.53, Q0 = 0.074 on the standard cells: R2-like)."""
    return RoadModel(RoadParams(k_diff=0.03, k_phong=0.5, n_phong=25.0, k_retro=0.05, n_retro=12.0, k_exp=0.03,
                                p=2.0, h=0.3, mu=0.01, n_beta=0.9), "smooth", name="synthetic-R2-like")


def standard_mask() -> np.ndarray:
    return bundled_table("R3").mask.copy()


@dataclass
class SyntheticMeasurement:
    truth: RTable          # r of the true model at the nominal geometry
    measured: RTable       # what the instrument reports (with noise)
    k_a: np.ndarray        # grid of the exact k_A used
    u_k_a_backend: np.ndarray   # its standard uncertainty
    settings: dict[str, Any]


def synthesize(truth: RoadModel, instrument: Instrument, *, noise: float = 0.01, seed: int = 1,
               backend: str = "numpy-mc", backend_settings: Mapping[str, Any] | None = None,
               mask: np.ndarray | None = None, name: str = "synthetic") -> SyntheticMeasurement:
    """A measured table of ``truth`` by ``instrument`` (module docstring)."""
    from roadgonio.engines import make_backend
    from roadgonio.surface.fit import model_r_on_grid
    mask = standard_mask() if mask is None else np.asarray(mask, bool)
    base = RTable(np.where(mask, 1.0, np.nan))
    r_true = np.where(mask, model_r_on_grid(truth, base), np.nan)
    settings = dict(backend_settings or ({"rel_se": 1e-3, "seed": 12345} if backend == "numpy-mc" else {"rtol": 1e-5}))
    b = make_backend(backend, instrument, truth, **settings)
    res = b.compute(base.cells)
    k = np.full(mask.shape, np.nan)
    se = np.full(mask.shape, np.nan)
    ii, jj = np.nonzero(mask)
    for i, j, c in zip(ii, jj, res):
        k[i, j], se[i, j] = c.k_a, c.standard_uncertainty()
    rng = np.random.default_rng(seed)
    eps = np.zeros(mask.shape)
    eps[mask] = rng.standard_normal(int(mask.sum())) * noise
    meas = np.where(mask, r_true * k * (1.0 + eps), np.nan)
    return SyntheticMeasurement(truth=RTable(r_true, name=f"{name}-truth", source=f"true r of {truth.name}"),
                                measured=RTable(meas, name=name, source=f"synthetic measurement of {truth.name} by "
                                                f"{instrument.name} ({backend}, {100 * noise:g} % noise, seed {seed})"),
                                k_a=k, u_k_a_backend=se, settings={"backend": b.settings(), "noise": noise, "seed": seed})
