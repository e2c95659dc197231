"""The Mitsuba k_A backend (``--backend mitsuba``): DESIGN.md section 5, paper eq. 2-3.

For each cell (tan eps, beta) the source is moved in the once-built scene
(:mod:`roadgonio.engines.mitsuba.scene`) and passes of a fixed-size render are made. The road BSDF runs
with its channel trick, so every pixel carries S[f_road] (channel 0) and S[f_lambert] (channel 1)
from the **same rays**. Statistics are float64 numpy:

    ratio = <R> / <G>,   k_A = ratio / ideal_ratio(model, instrument, tan, beta)

with ``ideal_ratio`` = pi f_road(nominal) in float64 (:func:`roadgonio.engines.ideal_ratio`), never
rendered. Passes with different spp are pooled weighted by their sample counts.

Standard error from a single pass: the pixels stratify the field of view (the film is
concentric-mapped onto the field disc), so the pixel values are independent but not identically
distributed; treating them as i.i.d. would add the between-pixel spread of the footprint
radiance to the error. The variance of a pass mean is instead estimated from differences of
horizontally adjacent pixels (paired strata) of the delta-method residual z = R - ratio G::

    Var(mean z) ~= sum over pairs (z_a - z_b)^2 / P^2          (P pixels)

which is unbiased for i.i.d. pixels and conservative (by the squared difference of neighbouring
stratum means) otherwise; ``tests/test_render_backend.py`` checks it against the scatter over
seeds.

Stopping rule: after each pass, stop when rel SE(ratio) <= ``rel_se`` (and at least
``min_passes`` passes); otherwise the next pass is sized from the 1/N law to reach the target
(times 1.15, spp rounded up to spp x 4^k, between ``spp`` and ``max_spp``), within
``max_samples``. The default sampler (multijitter) stratifies every pixel's pupil, field and
source samples; the paired-pixel SE stays valid because pixels are seeded independently. A cell that stops at ``max_samples`` keeps its (larger) SE and is flagged
``converged = False`` in ``CellResult.extra``.
"""
from __future__ import annotations

import math
import time
import zlib
from typing import Any, Sequence

import numpy as np

from roadgonio.errors import GeometryError, InputError
from roadgonio.instrument.config import Instrument
from roadgonio.engines import CellByCellBackend, CellResult, ideal_ratio
from roadgonio.surface.model import RoadModel
from roadgonio.engines.mitsuba.scene import LAMBERT, ROAD, build_scene

NAME = "mitsuba"
#: Samplers that stratify the samples of each pixel and want a square sample count.
SQUARE_SAMPLERS = ("multijitter", "stratified")
#: Default sampler: multijitter stratifies the pupil, field (within each pixel) and source samples;
#: on the portable preset with the R3 fit it needs 4-13x fewer samples than independent sampling
#: for the same SE (bench/bench_ka_mitsuba.py).
DEFAULT_SAMPLER = "multijitter"


def pair_variance(z: np.ndarray) -> float:
    """Variance of the mean of the pixel values ``z`` (H, W) from horizontally adjacent pairs."""
    z = np.asarray(z, dtype=np.float64)
    w = z.shape[1] - z.shape[1] % 2
    if w < 2:
        zz = z.ravel()
        n = zz.size
        return float(np.var(zz, ddof=1) / n) if n > 1 else math.inf
    d = z[:, 0:w:2] - z[:, 1:w:2]
    n = z.size
    return float(np.sum(d * d) / (n * n)) * (n / (z.shape[0] * w))


def pooled_ratio(passes: Sequence[tuple[int, np.ndarray, np.ndarray]]) -> tuple[float, float, float]:
    """Ratio of pooled means and its SE from ``(spp, R image, G image)`` passes; also <G>."""
    n_tot = float(sum(spp for spp, _, _ in passes))
    mr = sum(spp * float(np.mean(r)) for spp, r, _ in passes) / n_tot
    mg = sum(spp * float(np.mean(g)) for spp, _, g in passes) / n_tot
    if mg <= 0.0:
        return math.nan, math.inf, mg
    ratio = mr / mg
    var = sum((spp / n_tot) ** 2 * pair_variance(r - ratio * g) for spp, r, g in passes)
    return ratio, math.sqrt(var) / mg, mg


class MitsubaBackend(CellByCellBackend):
    """k_A by Mitsuba 3 (see the module docstring)."""

    name = NAME

    def __init__(self, instrument: Instrument, model: RoadModel, *, rel_se: float = 1e-3, seed: int = 0,
                 spp: int = 16, resolution: int = 64, min_passes: int = 1, max_samples: int = 1 << 26,
                 max_spp: int = 1024, sampler: str = DEFAULT_SAMPLER, variant: str | None = None):
        for key, v, lo in (("rel_se", rel_se, 0.0), ("spp", spp, 1), ("resolution", resolution, 2),
                           ("min_passes", min_passes, 1), ("max_samples", max_samples, 1), ("max_spp", max_spp, 1)):
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not v >= lo or not math.isfinite(v):
                raise InputError(f"expected a number >= {lo}, got {v!r}", field=key)
        if rel_se <= 0:
            raise InputError(f"expected a relative standard error > 0, got {rel_se}", field="rel_se")
        self.instrument, self.model = instrument, model
        self.rel_se, self.seed = float(rel_se), int(seed)
        self.spp, self.resolution = int(spp), int(resolution)
        self.min_passes, self.max_samples, self.max_spp = int(min_passes), int(max_samples), int(max(max_spp, spp))
        self.sampler = sampler
        if sampler in SQUARE_SAMPLERS and math.isqrt(self.spp) ** 2 != self.spp:
            raise InputError(f"the {sampler} sampler needs a square spp (4, 16, 64...), got {self.spp}", field="spp")
        self.rs = build_scene(instrument, model, resolution=self.resolution, spp=self.spp, variant=variant,
                              sampler=sampler)
        import mitsuba as mi
        self.variant = mi.variant()

    def settings(self) -> dict[str, Any]:
        import drjit as dr
        import mitsuba as mi

        from roadgonio.engines.mitsuba import llvm_version
        s = {"backend": NAME, "variant": self.variant, "rel_se": self.rel_se, "seed": self.seed,
             "spp": self.spp, "resolution": self.resolution, "min_passes": self.min_passes,
             "max_samples": self.max_samples, "max_spp": self.max_spp, "sampler": self.sampler,
             "integrator": "direct (emitter_samples=1, bsdf_samples=0)",
             "detector": "lummeter (concentric-mapped field, pupil disc)",
             "source": self.rs.source_kind, "se_estimator": "adjacent-pixel pairs, delta method",
             "mitsuba": mi.__version__, "drjit": dr.__version__}
        if self.variant.startswith("llvm"):
            s["llvm"] = ".".join(map(str, llvm_version() or ()))
        if self.rs.xml is not None:
            s["xml"] = str(self.rs.xml)
        return s

    def _pass_spp(self, want: float, room: int) -> int:
        """spp of the next pass: ``want`` rounded up on the ladder spp x step^k, within
        [spp, max_spp] and ``room``; step 4 for the stratifying samplers, so every spp stays a
        perfect square when the first one is (multijitter/stratified round other counts)."""
        step = 4 if self.sampler in SQUARE_SAMPLERS else 2
        spp = self.spp
        while spp < want and spp * step <= self.max_spp:
            spp *= step
        while spp > room and spp > 1:
            spp //= step
        return max(spp, 1)

    def _seed(self, tan_eps: float, beta_deg: float, k: int) -> int:
        key = f"{self.seed}:{tan_eps:.9g}:{beta_deg:.9g}:{k}".encode()
        return zlib.crc32(key) & 0x7FFFFFFF

    def compute_cell(self, tan_eps: float, beta_deg: float) -> CellResult:
        t0 = time.perf_counter()
        ideal = ideal_ratio(self.model, self.instrument, tan_eps, beta_deg)
        self.rs.place_source(tan_eps, beta_deg)
        pixels = self.resolution * self.resolution
        passes: list[tuple[int, np.ndarray, np.ndarray]] = []
        n_samples, spp = 0, self.spp
        converged = False
        while True:
            img = self.rs.render(self._seed(tan_eps, beta_deg, len(passes)), spp)
            passes.append((spp, img[..., ROAD], img[..., LAMBERT]))
            n_samples += spp * pixels
            ratio, se, mg = pooled_ratio(passes)
            if not mg > 0.0:
                raise GeometryError(f"the source lights none of the detector footprint at tan eps = {tan_eps:g}, "
                                    f"beta = {beta_deg:g} (Lambert signal {mg:g}): is it shaded by a part of "
                                    "the scene?")
            rel = se / abs(ratio) if ratio != 0.0 else (0.0 if se == 0.0 else math.inf)
            if rel <= self.rel_se and len(passes) >= self.min_passes:
                converged = True
                break
            room = self.max_samples - n_samples
            if room < pixels:
                break
            factor = (rel / self.rel_se) ** 2 if math.isfinite(rel) else 4.0
            need = n_samples * max(factor - 1.0, 0.0) * 1.15
            spp = self._pass_spp(need / pixels, room // pixels)
        if ideal > 0.0:
            k_a, k_se = ratio / ideal, se / ideal
        else:
            k_a, k_se = math.nan, math.nan
        extra = {"ratio": ratio, "ratio_se": se, "ideal_ratio": ideal, "passes": len(passes),
                 "rel_se": rel, "converged": converged}
        if ideal <= 0.0:
            extra["note"] = "the model is 0 at the nominal geometry: k_A is undefined"
        return CellResult(tan_eps=float(tan_eps), beta_deg=float(beta_deg), k_a=float(k_a), se=float(k_se), converged=bool(converged),
                          samples=int(n_samples), seconds=time.perf_counter() - t0, extra=extra)



def make_backend(instrument: Instrument, model: RoadModel, *, rel_se: float = 1e-3, seed: int = 0,
                 spp: int = 16, resolution: int = 64, min_passes: int = 1, max_samples: int = 1 << 26,
                 max_spp: int = 1024, sampler: str = DEFAULT_SAMPLER, variant: str | None = None,
                 **unknown) -> MitsubaBackend:
    """The Mitsuba k_A backend (:class:`MitsubaBackend`); builds and checks the scene now, so
    geometry errors surface before any cell is computed."""
    if unknown:
        raise InputError(f"unknown setting(s) {', '.join(sorted(unknown))} for the mitsuba backend; expected "
                         "rel_se, seed, spp, resolution, min_passes, max_samples, max_spp, sampler, variant")
    return MitsubaBackend(instrument, model, rel_se=rel_se, seed=seed, spp=spp, resolution=resolution,
                          min_passes=min_passes, max_samples=max_samples, max_spp=max_spp, sampler=sampler,
                          variant=variant)
