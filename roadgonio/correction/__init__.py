"""Correction of a measured r-table for the aperture effect (paper eq. 2; docs/conventions.md section 5):
``r_true = r_measured / k_A``, with k_A computed for a reference BRDF model close to the sample
(paper section 4.1: "choosing the reference r-table closest to the sample behaviour").

Uncertainty of the correction factor, per cell (relative, combined in quadrature):

* numerical: the backend's standard error (Monte Carlo) or error estimate (quadrature) of k_A;
* reference model: k_A depends on the BRDF, which is only approximately known. k_A is also
  computed for alternative references (by default the two CIE standard tables nearest to the
  measured table in (S1, Q0), each coordinate scaled by its spread over the six standard tables,
  the reference itself excluded) and the largest deviation |k_alt - k_ref| is taken as the
  half-width of a rectangular distribution: u_model = max |k_alt - k_ref| / sqrt(3).

Every cell of the corrected table also carries the relative standard uncertainty of the correction
``u_rel = sqrt(se^2 + u_model^2) / k_ref`` (the measurement's own uncertainty, e.g. from
``roadgonio uncertainty``, adds to it).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel
from roadgonio.surface.rtable import BUNDLED, RTable, bundled_table

Factory = Callable[[Instrument, RoadModel], Any]


def nearest_standard_tables(table: RTable, k: int = 2, exclude: Sequence[str] = ()) -> list[tuple[str, float]]:
    """The k bundled CIE tables nearest to ``table`` in (S1, Q0), each scaled by its standard
    deviation over the six tables; returns (name, distance)."""
    stats = {n: (bundled_table(n).s1(), bundled_table(n).q0()) for n in BUNDLED}
    s1s = np.array([v[0] for v in stats.values()])
    q0s = np.array([v[1] for v in stats.values()])
    ss, sq = s1s.std(), q0s.std()
    s1, q0 = table.s1(), table.q0()
    ex = {e.upper() for e in exclude}
    d = [(n, math.hypot((v[0] - s1) / ss, (v[1] - q0) / sq)) for n, v in stats.items() if n not in ex]
    d.sort(key=lambda t: t[1])
    return d[:k]


def sample_name(spec: str) -> str:
    """Short name of a SAMPLE argument: a file's stem, else the argument (``R3``, ``lambert``)."""
    return Path(spec).stem if Path(spec).suffix else spec


def resolve_alternatives(spec: str | Sequence[str] | None, measured: RTable, *, reference_name: str,
                         model_variant: str | None = None) -> dict[str, RoadModel]:
    """The alternative references for the model uncertainty: ``"auto"`` = the two CIE tables
    nearest to ``measured`` in (S1, Q0), the reference excluded; ``"none"``/``None`` = none; a
    comma-separated text or a list of SAMPLEs = those (fitted or loaded like the reference)."""
    from roadgonio.surface.sample import resolve_sample
    if spec is None:
        return {}
    if isinstance(spec, str):
        text = spec.strip()
        if text.lower() == "auto":
            names = [n for n, _ in nearest_standard_tables(measured, 2, exclude=[reference_name])]
        elif text.lower() in ("none", ""):
            names = []
        else:
            names = [s.strip() for s in text.split(",") if s.strip()]
    else:
        names = [str(s) for s in spec]
    return {sample_name(n): resolve_sample(n, model_variant) for n in names}


@dataclass
class Correction:
    measured: RTable
    corrected: RTable
    k_a: np.ndarray              # (29, 20) k_A of the reference, NaN where blank
    se: np.ndarray               # backend error of k_A
    alternatives: dict[str, np.ndarray]
    u_model: np.ndarray          # (29, 20)
    u_rel: np.ndarray            # (29, 20) relative standard uncertainty of the correction
    reference: str
    provenance: dict[str, Any]
    seconds: float

    def summary(self) -> dict[str, Any]:
        m = self.measured.mask
        out = {"reference": self.reference, "cells": int(m.sum()),
               "k_a_min": float(np.nanmin(self.k_a)), "k_a_max": float(np.nanmax(self.k_a)),
               "u_rel_max": float(np.nanmax(self.u_rel)), "u_rel_median": float(np.nanmedian(self.u_rel[m])),
               "u_model_rel_max": float(np.nanmax(self.u_model / self.k_a)),
               "backend_rel_se_max": float(np.nanmax(self.se / self.k_a)),
               "S1_before": self.measured.s1(), "S1_after": self.corrected.s1(),
               "Q0_before": self.measured.q0(), "Q0_after": self.corrected.q0(), "seconds": self.seconds}
        out["alternatives"] = {n: {"max_rel_dev": float(np.nanmax(np.abs(a / self.k_a - 1)))}
                               for n, a in self.alternatives.items()}
        return out


def _grid_ka(factory: Factory, instrument: Instrument, model: RoadModel, table: RTable, bar) -> tuple[np.ndarray, np.ndarray, dict]:
    backend = factory(instrument, model)
    cells = table.cells
    res = backend.compute(cells, on_cell=(lambda _c: bar.update(1)) if bar is not None else None)
    k = np.full(table.r.shape, np.nan)
    se = np.full(table.r.shape, np.nan)
    ii, jj = np.nonzero(table.mask)
    for i, j, c in zip(ii, jj, res):
        k[i, j] = c.k_a
        se[i, j] = c.standard_uncertainty()
    try:
        settings = dict(backend.settings())
    except Exception:  # noqa: BLE001 - provenance only
        settings = {}
    return k, se, settings


def correct_table(measured: RTable, instrument: Instrument, reference: RoadModel, *, reference_name: str = "reference",
                  alternatives: Mapping[str, RoadModel] | None = None, backend: str = "mitsuba",
                  backend_settings: Mapping[str, Any] | None = None, factory: Factory | None = None,
                  progress: bool = True) -> Correction:
    """r_measured / k_A(reference) with the uncertainty of the correction (module docstring)."""
    t0 = time.perf_counter()
    if factory is None:
        from roadgonio.engines import make_backend

        def factory(inst, model):
            return make_backend(backend, inst, model, **dict(backend_settings or {}))
    alternatives = dict(alternatives or {})
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=int(measured.mask.sum()) * (1 + len(alternatives)), desc="k_A", unit="cell", leave=False)
    try:
        k, se, settings = _grid_ka(factory, instrument, reference, measured, bar)
        alts = {n: _grid_ka(factory, instrument, m, measured, bar)[0] for n, m in alternatives.items()}
    finally:
        if bar is not None:
            bar.close()
    if np.any(~np.isfinite(k[measured.mask])) or np.any(k[measured.mask] <= 0):
        raise InputError("the backend returned a non-positive or non-finite k_A; cannot correct", field="k_A")
    u_model = np.zeros_like(k)
    if alts:
        dev = np.max(np.stack([np.abs(a - k) for a in alts.values()]), axis=0)
        u_model = dev / math.sqrt(3.0)
    u_model = np.where(measured.mask, u_model, np.nan)
    u_rel = np.sqrt(se ** 2 + u_model ** 2) / k
    corrected = measured.with_values(measured.r / k, name=f"{measured.name}_corrected",
                                     source=f"{measured.name} corrected for the aperture effect: r / k_A "
                                            f"(reference {reference_name}, instrument {instrument.name})")
    from roadgonio.provenance import provenance
    prov = provenance(instrument=instrument, model=reference, backend=str(settings.get("backend", backend)),
                      settings=settings or {"backend": backend, **dict(backend_settings or {})},
                      reference=reference_name,
                      alternatives={n: m.to_json_dict() for n, m in alternatives.items()},
                      u_model="max |k_A(alternative) - k_A(reference)| / sqrt(3) (rectangular)")
    return Correction(measured=measured, corrected=corrected, k_a=k, se=se, alternatives=alts, u_model=u_model,
                      u_rel=u_rel, reference=reference_name, provenance=prov, seconds=time.perf_counter() - t0)


def write_correction(c: Correction, out_dir: str | Path, *, plots: bool = True) -> list[Path]:
    from roadgonio.fileio import atomic_write_json, atomic_write_text
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    base = c.measured.name
    paths = [c.corrected.write_csv(out / f"{base}_corrected.csv"), c.corrected.write_rtb(out / f"{base}_corrected.rtb")]
    header = (["tan_eps", "beta_deg", "r_measured_x1e4", "k_a", "k_a_se", "u_model"]
              + [f"k_a_{n}" for n in c.alternatives] + ["r_corrected_x1e4", "u_rel_correction"])
    lines = [",".join(header)]      # (joining the alternatives alone left an empty column when there were none)
    for i, j in zip(*np.nonzero(c.measured.mask)):
        alts = "".join(f",{a[i, j]:.6g}" for a in c.alternatives.values())
        lines.append(f"{TAN_EPS_GRID[i]:g},{BETA_GRID_DEG[j]:g},{c.measured.r[i, j] * 1e4:.6g},{c.k_a[i, j]:.6g},"
                     f"{c.se[i, j]:.3g},{c.u_model[i, j]:.3g}{alts},{c.corrected.r[i, j] * 1e4:.6g},{c.u_rel[i, j]:.4g}")
    paths.append(atomic_write_text(out / "correction_cells.csv", "\n".join(lines) + "\n"))
    paths.append(atomic_write_json(out / "correction.json", {"summary": c.summary(), "provenance": c.provenance}))
    if plots:
        paths.append(plot_before_after(c, out / "before_after.png"))
    return paths


def plot_before_after(c: Correction, path: Path) -> Path:
    """Left: r x 1e4 against tan eps for a few beta columns, measured (dashed) and corrected (solid)
    with the correction's 95 % band. Right: map of k_A with the relative uncertainty of the correction."""
    from roadgonio.fileio import atomic_savefig
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    from roadgonio.plots import _plt
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(15, 6.5), gridspec_kw={"width_ratios": [1, 1.15]})
    for n, beta in enumerate((0, 2, 5, 10, 20, 45)):
        j = int(np.nonzero(BETA_GRID_DEG == beta)[0][0])
        ok = c.measured.mask[:, j]
        t = TAN_EPS_GRID[ok]
        col = f"C{n}"
        a1.plot(t, c.measured.r[ok, j] * 1e4, "--", color=col, lw=1.1, alpha=0.8)
        rc = c.corrected.r[ok, j] * 1e4
        a1.plot(t, rc, "-", color=col, lw=1.6, marker="o", ms=2.5, label=f"beta = {beta} deg")
        band = 1.96 * c.u_rel[ok, j] * rc
        a1.fill_between(t, rc - band, rc + band, color=col, alpha=0.18, lw=0)
    a1.plot([], [], "k--", lw=1.1, label="measured")
    a1.plot([], [], "k-", lw=1.6, label="corrected (band: 95 % of the correction)")
    a1.set_yscale("log")
    a1.set_xlabel("tan eps")
    a1.set_ylabel("r x 10^4 (sr^-1)")
    a1.set_title(f"{c.measured.name}: before / after the aperture-effect correction", fontsize=11)
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3, which="both")
    from roadgonio.plots import draw_table_map
    draw_table_map(a2, c.k_a, label="k_A", fontsize=4.6, tick_fontsize=7,
                   text=lambda i, j: f"{c.k_a[i, j]:.2f}\n{100 * c.u_rel[i, j]:.1f}%")
    alts = ", ".join(c.alternatives) or "none"
    a2.set_title(f"k_A (reference {c.reference}) and u_rel of the correction\n(alternatives: {alts})", fontsize=10)
    fig.tight_layout()
    p = atomic_savefig(fig, path, dpi=120)
    plt.close(fig)
    return p
