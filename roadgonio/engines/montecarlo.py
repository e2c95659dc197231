"""Plain float64 numpy Monte Carlo of the detector signal (paper eq. 3; docs/conventions.md sections 4-5).

The same integral as :mod:`roadgonio.engines.quadrature` and the same estimator as the Mitsuba
renderer: uniform points on the pupil, field and source discs (area-preserving concentric map of
:mod:`roadgonio.instrument.optics`), the detector ray of the pair (pupil point, field point) with its etendue
weight, the hit point x, the source coupling G and the road BRDF (:mod:`roadgonio.surface.model`). Each
sample contributes the paired values::

    road = w f_road(w_i, w_o) G        lambert = w G / pi

Samples come in batches of ``batch = m^2``; within a batch each disc is stratified (an m x m
jittered grid on the unit square, randomly permuted per disc so the discs are not correlated),
so the batch means are independent and identically distributed and the ratio of means
<road>/<lambert> gets its standard error by the delta method over batches
(:func:`roadgonio.engines.ratio_se`). Batches are added until the relative standard error of k_A is
below ``rel_se`` (at least ``min_batches`` batches, at most ``max_samples`` samples). The SE has
``batches - 1`` degrees of freedom, so at least 64 batches by default (:data:`DEFAULT_MIN_BATCHES`):
with few batch means the estimated SE scatters and z = error / SE has Student's heavier tails.

Every cell has its own random stream, seeded by (seed, tan eps, beta): a cell's result does not
depend on which other cells are computed or in what order. This backend is the oracle and the
speed baseline of the Mitsuba backend; it also handles the flat rectangular sample only.
"""
from __future__ import annotations

import math
import numbers
import time
from typing import Any, Callable

import numpy as np

from roadgonio.instrument import optics
from roadgonio.seeds import cell_key, check_seed, seed_entropy
from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import RoadModel
from roadgonio.engines.result import (RATIO_DENOMINATOR_REL_SE_MAX, CellByCellBackend, CellResult, mean_rel_se,
                                      ratio_se, sparse_light_note)
from roadgonio.engines.cellcheck import check_cell

DEFAULT_REL_SE = 1e-3
DEFAULT_BATCH = 45 ** 2
#: The SE comes from the scatter of the batch means, with (batches - 1) degrees of freedom, and a z
#: computed with it follows Student's t, not a normal law: with 8 batches t_7 (RMS z 1.18, |z| > 4
#: 80 times as often as a normal z; trial 7 measured RMS 1.35 at the fast preset). With 64 batches
#: t_63 is within 2 % of normal in RMS, and the stopping rule (stop once the estimated SE meets
#: rel_se) selects little on a low estimate (its relative scatter is 9 %).
DEFAULT_MIN_BATCHES = 64
DEFAULT_MAX_SAMPLES = 200_000_000
#: Points per evaluation chunk of a batch (arrays of 32 KiB: reused by the allocator, not mapped).
CHUNK = 4096


def _stratified_disc(rng: np.random.Generator, m: int) -> tuple[np.ndarray, np.ndarray]:
    """m^2 stratified uniform points of the unit disc (jittered grid, concentric map), in random order."""
    i = np.arange(m * m)
    u1 = (i % m + rng.random(m * m)) / m
    u2 = (i // m + rng.random(m * m)) / m
    perm = rng.permutation(m * m)
    return optics.concentric_disc(NumpyOps, u1[perm], u2[perm])


class MonteCarloBackend(CellByCellBackend):
    """k_A by float64 Monte Carlo (see the module docstring)."""

    name = "numpy-mc"

    def __init__(self, instrument: Instrument, model: RoadModel, *, rel_se: float = DEFAULT_REL_SE,
                 seed: int = 0, batch: int = DEFAULT_BATCH, min_batches: int = DEFAULT_MIN_BATCHES,
                 max_samples: int = DEFAULT_MAX_SAMPLES):
        from roadgonio.engines.registry import check_relative
        rel_se = check_relative(rel_se, "rel_se")
        seed = check_seed(seed)
        from roadgonio.limits import check_size
        if isinstance(batch, bool) or not isinstance(batch, numbers.Integral):
            raise InputError(f"expected a whole number of samples per batch, got {batch!r}", field="batch")
        m = int(round(math.sqrt(check_size(int(batch), "batch", "batch"))))
        if m < 2:
            raise InputError(f"expected a batch of at least 4 samples, got {batch}", field="batch")
        if int(min_batches) < 2:
            raise InputError(f"expected at least 2 batches (for a standard error), got {min_batches}",
                             field="min_batches")
        # refuse what this backend does not model (an XML scene's extra parts, a mesh sample)
        optics.check_detector(instrument)
        self.instrument = instrument
        self.model = model
        self.rel_se = rel_se
        self.seed = int(seed)
        self.m = m
        self.batch = m * m
        self.min_batches = int(min_batches)
        self.max_samples = int(max_samples)
        self._det = optics.detector_geometry(instrument)
        det = instrument.detector
        self._pupil = det.pupil_radius_m > 0.0
        self._field = det.field_half_angle_deg > 0.0
        self._source = instrument.source.radius_m > 0.0

    def settings(self) -> dict[str, Any]:
        return {"backend": self.name, "rel_se": self.rel_se, "seed": self.seed, "batch": self.batch,
                "min_batches": self.min_batches, "max_samples": self.max_samples,
                "sampling": "stratified m x m jittered grid per disc per batch, concentric map",
                "precision": "float64"}

    def _square(self, rng, k: int, active: bool):
        """The m x m jittered points of disc ``k`` (0 pupil, 1 field, 2 source) on the unit square, in
        random order, drawn exactly as :func:`_stratified_disc` draws them (the same random stream)
        but into buffers reused from batch to batch; the concentric map is applied per chunk."""
        n, m = self.batch, self.m
        if not hasattr(self, "_bufs"):
            i = np.arange(n)
            self._grid = ((i % m).astype(np.float64), (i // m).astype(np.float64))
            self._arange = np.arange(n)
            self._bufs = [{name: np.empty(n) for name in ("r1", "r2", "u1", "u2")} | {"perm": np.empty(n, np.int64)}
                          for _ in range(3)]
            self._zeros = np.zeros(n)
        if not active:
            return self._zeros, self._zeros
        b = self._bufs[k]
        rng.random(out=b["r1"])
        rng.random(out=b["r2"])
        np.copyto(b["perm"], self._arange)
        rng.shuffle(b["perm"])                          # = rng.permutation(n)
        for u, r, g in ((b["u1"], b["r1"], self._grid[0]), (b["u2"], b["r2"], self._grid[1])):
            np.add(g, r, out=r)
            np.multiply(r, 1.0 / m, out=r)
            np.take(r, b["perm"], out=u)
        return b["u1"], b["u2"]

    def _batch(self, rng: np.random.Generator, src: optics.SourceGeometry) -> tuple[float, float]:
        """Mean of w f G and of w G over one batch. The batch's points are drawn at once into reused
        buffers (the same random stream as ever); the integrand is evaluated in chunks of
        :data:`CHUNK` points, so its temporaries stay small enough to be reused by the allocator
        instead of being mapped and unmapped by the kernel for every array."""
        pupil = self._square(rng, 0, self._pupil)
        field = self._square(rng, 1, self._field)
        sdisc = self._square(rng, 2, self._source)
        road = lam = 0.0

        def disc(uv, active, a, b):
            if not active:
                return uv[0][a:b], uv[1][a:b]
            return optics.concentric_disc(NumpyOps, uv[0][a:b], uv[1][a:b])
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            for a in range(0, self.batch, CHUNK):
                b = a + CHUNK
                o, d, w = optics.detector_ray(NumpyOps, self._det, disc(pupil, self._pupil, a, b),
                                              disc(field, self._field, a, b))
                x, y, valid = optics.hit_plane(NumpyOps, o, d)
                sd = disc(sdisc, self._source, a, b)
                sp = optics.source_point(src, sd)
                wi, g = optics.source_coupling(NumpyOps, src, x, y, sp, sd)
                wo = (-d[0], -d[1], -d[2])
                f = self.model.evaluate(NumpyOps, wi, wo)
                wg = np.where(valid, w * g, 0.0)
                road += float(np.dot(wg, f))
                lam += float(np.sum(wg))
        return road / self.batch, lam / self.batch

    def compute_cell(self, tan_eps: float, beta_deg: float,
                     on_progress: Callable[[int, float], None] | None = None) -> CellResult:
        """k_A at one cell. ``on_progress(samples, rel_se)`` is called after every batch with the
        samples so far and the relative SE reached (NaN before ``min_batches``). Inside
        :func:`roadgonio.progress.steps_shown`, on a terminal, a cell that runs more than a few
        seconds draws a bar of its samples against its cap, with the relative SE against the target
        (user audit, session 24: a narrow lobe ran a fast cell 45 minutes to its 2e8-sample cap in
        silence). A cell stopped by the cap says so in ``extra["note"]``."""
        t0 = time.perf_counter()
        tan_eps, beta_deg = float(tan_eps), float(beta_deg)
        ideal = check_cell(self.instrument, self.model, tan_eps, beta_deg)
        src = optics.source_geometry(self.instrument, tan_eps, beta_deg)
        rng = np.random.default_rng(seed_entropy(self.seed, cell_key(tan_eps), cell_key(beta_deg)))
        road, lam = [], []
        k = se = math.nan
        max_batches = max(self.min_batches, self.max_samples // self.batch)
        from roadgonio.progress import step_bar
        bar = step_bar(max_batches * self.batch, f"numpy-mc {tan_eps:g}:{beta_deg:g}")
        said = time.monotonic()
        try:
            while len(road) < max_batches:
                r, l_ = self._batch(rng, src)
                road.append(r)
                lam.append(l_ / math.pi)
                done = False
                if len(road) >= self.min_batches:
                    ratio, rse = ratio_se(np.array(road), np.array(lam))
                    k, se = ratio / ideal, rse / ideal
                    done = bool(se <= self.rel_se * abs(k))
                if on_progress is not None or bar is not None:
                    rel = se / abs(k) if k else math.inf
                    if on_progress is not None:
                        on_progress(len(road) * self.batch, rel)
                    if bar is not None:
                        bar.update(self.batch)
                        if time.monotonic() - said >= 1.0:
                            bar.set_postfix_str(f"rel SE {rel:.2g}, target {self.rel_se:g}", refresh=False)
                            said = time.monotonic()
                if done:
                    break
        finally:
            if bar is not None:
                bar.close()
        n = len(road) * self.batch
        converged = bool(se <= self.rel_se * abs(k))
        extra = {"batches": len(road), "converged": converged, "rel_se": se / abs(k) if k else math.inf}
        if not converged and len(road) >= 2 and (lit := mean_rel_se(lam)) > RATIO_DENOMINATOR_REL_SE_MAX:
            extra["sparse_light"] = lit
            extra["note"] = f"stopped at its cap (max_samples = {self.max_samples}): " + \
                sparse_light_note(extra["sparse_light"])
        elif not converged:
            extra["note"] = (f"stopped at its cap (max_samples = {self.max_samples}: {n} samples in {len(road)} "
                             f"batches): the relative standard error {extra['rel_se']:.2e} exceeds rel_se = "
                             f"{self.rel_se:g}")
        return CellResult(tan_eps=tan_eps, beta_deg=beta_deg, k_a=float(k), se=float(se), converged=converged, samples=int(n),
                          seconds=time.perf_counter() - t0, extra=extra,
                          se_dof=float(len(road) - 1) if math.isfinite(se) else math.nan)



def make_backend(instrument: Instrument, model: RoadModel, *, rel_se: float = DEFAULT_REL_SE, seed: int = 0,
                 batch: int = DEFAULT_BATCH, min_batches: int = DEFAULT_MIN_BATCHES,
                 max_samples: int = DEFAULT_MAX_SAMPLES, **unknown) -> MonteCarloBackend:
    """The float64 numpy Monte Carlo backend (``roadgonio.engines.make_backend("numpy-mc", ...)``).

    Parameters
    ----------
    rel_se:
        Target relative standard error of each k_A (default 1e-3).
    seed:
        Base seed; each cell's stream is seeded by (seed, tan eps, beta).
    batch:
        Samples per batch (rounded to a square m^2; default 45^2 = 2025).
    min_batches, max_samples:
        At least this many batches (default 64: the SE's degrees of freedom plus one), at most this many samples per cell; a cell stopped by
        ``max_samples`` reports its achieved standard error and ``extra["converged"] = False``.
    """
    if unknown:
        raise InputError(f"unknown numpy-mc setting(s) {', '.join(sorted(unknown))}; expected rel_se, seed, "
                         "batch, min_batches, max_samples", field=sorted(unknown)[0])
    return MonteCarloBackend(instrument, model, rel_se=rel_se, seed=seed, batch=batch,
                             min_batches=min_batches, max_samples=max_samples)
