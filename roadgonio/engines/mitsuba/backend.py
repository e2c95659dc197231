"""The Mitsuba k_A backend (``--backend mitsuba``): docs/conventions.md section 5, paper eq. 2-3.

All cells of a ``compute`` call go through the batched engine (:mod:`roadgonio.engines.mitsuba.engine`,
the ``kabatch`` integrator plugin): the scene is built once per instrument
(:mod:`roadgonio.engines.mitsuba.scene`: road BSDF plugin, luminance-meter sensor, trimesh sample,
disc area emitters), the detector rays are traced once per pass and shared by every cell, each
cell's source is sampled at the same hits, and per-cell road and Lambert sums come back in float64::

    ratio = sum R / sum G,   k_A = ratio / ideal_ratio(model, instrument, tan, beta)

with ``ideal_ratio`` = pi f_road(nominal) in float64 (:func:`roadgonio.engines.ideal_ratio`), never
rendered.

Standard error: the marginal SE of each cell from independent replicates (randomly shifted lattices)
by the delta method (:mod:`roadgonio.engines.mitsuba.passes`), with its degrees of freedom
(``se_dof``: 15 for a cell that converged in its first pass of 16 replicates, more with more
passes; an error over this SE follows Student's t, docs/validation.md); cells computed together share rays, so
their errors are correlated: :meth:`MitsubaBackend.covariance` gives the covariance matrix of the last
``compute`` call (for the SE of a table functional), estimated from the shared replicates.
``tests/plugin/test_engine.py`` checks the SE against the scatter over seeds, for cells batched together too.

Passes sized from the target: a first pass of ``first_pass`` samples per cell, then the 1/N rule per
cell (:class:`~roadgonio.engines.mitsuba.passes.Planner`); cells leave as they reach ``rel_se`` (at
least ``min_passes`` passes) or ``max_samples`` (then ``converged = False``). ``plan`` replays the
schedule of an earlier call (:attr:`MitsubaBackend.last_plan`): the same seed then gives every table
the same random numbers (the uncertainty command's design points).

Reproducibility: the same seed, cells and settings give the same numbers bit for bit, whatever the
thread count (the device sums are evaluated block sums in a fixed order), and a cell's numbers do
not depend on the cells batched with it (its lattices depend on the seed, pass and size only).
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable, Sequence

import numpy as np

from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument
from roadgonio.engines.result import CellResult, ideal_ratios
from roadgonio.surface.model import RoadModel
from roadgonio.surface.truths import renders_in_drjit
from roadgonio.engines.mitsuba.scene import build_scene

NAME = "mitsuba"
#: Defaults of the batched engine.
#: 16 lattices of 256 points (every preset's, registry.py: smaller lattices gave skewed replicate sums)
DEFAULT_FIRST_PASS = 4096
DEFAULT_MIN_REPLICATES = 16
DEFAULT_MAX_SAMPLES = 1 << 28
#: Settings of the per-cell renderer this backend replaced (a clear error instead of a silent no-op).
REMOVED = {"spp": "first_pass", "resolution": "first_pass", "max_spp": "max_samples",
           "sampler": None}


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


#: float32's smallest normal number: below it a value is a denormal (precision lost) or, where the
#: LLVM backend flushes denormals, 0.
FLOAT32_TINY = float(np.finfo(np.float32).tiny)
#: The smallest mean road value a sample that the float32 renderer is trusted with, eight decades above
#: :data:`FLOAT32_TINY`: the contributions it loses are each below about FLOAT32_TINY (times the few
#: factors of a path), so below 1e-8 of such a signal. A lobe of exponent 1e5, 2.6 deg off its mirror
#: direction at tan eps 12, rendered a mean of 3.6e-41 a sample and k_A 11434 +- 11, converged, where the
#: float64 backends give 30516 (user audit, session 35); 0.1 deg nearer, at 1.2e-37, it agreed within
#: 0.2 %: the limit gives up that cell as well.
FLOAT32_SIGNAL_MIN = 1e-30


class MitsubaBackend:
    """k_A by Mitsuba 3, all cells of a call batched (see the module docstring)."""

    name = NAME
    checkpoints_passes = True       # compute(..., checkpoint=) saves and resumes its passes (KaBackend)

    def __init__(self, instrument: Instrument, model: RoadModel, *, rel_se: float = 1e-3, seed: int = 0,
                 first_pass: int = DEFAULT_FIRST_PASS, min_replicates: int = DEFAULT_MIN_REPLICATES,
                 min_passes: int = 1, max_samples: int = DEFAULT_MAX_SAMPLES, plan=None,
                 mitsuba_variant: str | None = None):
        for key, v, lo in (("rel_se", rel_se, 0.0), ("first_pass", first_pass, 32),
                           ("min_replicates", min_replicates, 2), ("min_passes", min_passes, 1),
                           ("max_samples", max_samples, 1)):
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not v >= lo or not math.isfinite(v):
                raise InputError(f"expected a number >= {lo}, got {v!r}", field=key)
        if rel_se <= 0:
            raise InputError(f"expected a relative standard error > 0, got {rel_se}", field="rel_se")
        from roadgonio.engines.mitsuba.passes import Plan, Planner
        self.instrument, self.model = instrument, model
        self.rel_se, self.seed = float(rel_se), int(seed)
        self.first_pass, self.min_replicates = int(first_pass), int(min_replicates)
        self.min_passes, self.max_samples = int(min_passes), int(max_samples)
        self.plan = None if plan is None else Plan.from_dict(plan)
        self.planner = Planner(self.rel_se, first_pass=self.first_pass, min_replicates=self.min_replicates,
                               max_samples=self.max_samples, min_passes=self.min_passes)
        # the engine counts every detector ray it traces: the build-time check needs only the
        # bundle's extreme rays and a few random ones
        self.rs = build_scene(instrument, model, mitsuba_variant=mitsuba_variant, hit_rays=1 << 12)
        from roadgonio.engines.mitsuba.engine import BatchEngine
        self.engine = BatchEngine(self.rs)
        self.planner.stray_search = bool(self.rs.stray)      # reflecting parts (not black ones forced through)
        import mitsuba as mi
        self.variant = mi.variant()
        self.last_run = None
        self._ideal = None
        #: the schedule of the last ``compute`` call (replay it with ``plan=``)
        self.last_plan = None

    @property
    def stray_light(self) -> bool:
        """True when the scene's reflecting parts make stray light (its results then carry
        ``k_a_direct`` and ``stray_fraction``)."""
        return bool(self.engine.stray)

    def converge_on(self, statistic: str) -> None:
        """The statistic each cell converges on (:attr:`Planner.statistic`): ``"absolute"`` when the
        absolute calibration wraps this backend (with stray light it reports eta R / G_d, not the
        Lambert ratio R / G; :class:`roadgonio.engines.calibration.CalibratedBackend`)."""
        if statistic not in ("lambert", "absolute"):
            raise ValueError(f"unknown statistic {statistic!r}")
        self.planner.statistic = statistic

    def settings(self) -> dict[str, Any]:
        import drjit as dr
        import mitsuba as mi

        from roadgonio.engines.mitsuba import llvm_version
        s = {"backend": NAME, "mitsuba_variant": self.variant, "rel_se": self.rel_se, "seed": self.seed,
             "first_pass": self.first_pass, "min_replicates": self.min_replicates,
             "min_passes": self.min_passes, "max_samples": self.max_samples,
             "engine": "batched (kabatch integrator: shared detector rays, one source per cell)",
             "sampling": "randomly shifted rank-1 lattices (Korobov), independent replicates",
             "integrator": "kabatch (emitter sampling, shadow rays " +
                           ("on" if self.engine.integrator.shadow else "off: nothing can occlude") + ")",
             "detector": "lummeter (concentric-mapped field, pupil disc)",
             "source": self.rs.source_kind, "se_estimator": "replicates, delta method (marginal per cell)",
             "mitsuba": mi.__version__, "drjit": dr.__version__}
        if self.plan is not None:
            s["plan"] = "replayed"
        if self.variant.startswith("llvm"):
            s["llvm"] = ".".join(map(str, llvm_version() or ()))
        if self.rs.xml is not None:
            s["xml"] = str(self.rs.xml)
        if self.engine.stray:
            s["stray_light"] = {
                "max_bounces": self.engine.max_bounces, "reflecting_parts": list(self.rs.part_ids),
                "paths": "eye paths (BSDF sampling, next-event estimation at every vertex) and light paths from "
                         f"the source (up to {self.engine.integrator.light_depth} reflections, connected to the "
                         "footprint), balance-heuristic MIS",
                "se_estimator": "replicates, delta method (k_a, k_a_direct, stray_fraction)"}
            if self.planner.statistic == "absolute":
                s["stray_light"]["converges_on"] = ("R / G_d: the road's total over the Lambert sample's direct "
                                                    "light (the absolute calibration's k_A)")
        if self.rs.housing is not None:
            s["housing"] = self.rs.housing.to_dict()
        return s

    def compute(self, cells: Sequence[tuple[float, float]],
                on_cell: Callable[[CellResult], None] | None = None, checkpoint=None) -> list[CellResult]:
        """k_A of every cell (one batched run); ``on_cell`` is called for each cell as it finishes,
        in batches (the cells that left the active set after a pass). ``checkpoint``
        (:class:`roadgonio.engines.runner.PassCheckpoint`): the state is saved after every pass and
        a saved state of these cells is resumed (same numbers as without the interruption; the
        checkpoint is told how many cells it carried on, and from which pass: ``reused``)."""
        from roadgonio.engines.mitsuba.passes import se_dof_many, stray_ratios
        t0 = time.perf_counter()
        cells = [(float(t), float(b)) for t, b in cells]
        if self.is_ideal_geometry:
            return self._ideal_results(cells, on_cell, t0)
        ideal = [float(v) for v in ideal_ratios(self.model, self.instrument, cells)] if cells else []
        results: list[CellResult | None] = [None] * len(cells)
        last = [t0]

        def done(indices, run) -> None:
            now = time.perf_counter()
            share = (now - last[0]) / max(len(indices), 1)     # the pass's wall time, shared out
            last[0] = now
            # the direct light's ratio and the stray fraction of all these cells at once (vectorised)
            with_stray = [i for i in indices if run.stats[i].direct]
            stray = dict(zip(with_stray, zip(*stray_ratios([run.stats[i] for i in with_stray])))) if with_stray else {}
            dofs = se_dof_many([run.stats[i] for i in indices])
            for i, dof in zip(indices, dofs):
                results[i] = self._result(cells[i], ideal[i], run.stats[i], run.converged[i], share, stray.get(i),
                                          dof=float(dof))
                if on_cell is not None:
                    on_cell(results[i])

        run = self.engine.run(cells, self.planner, seed=self.seed, plan=self.plan, on_done=done,
                              resume=None if checkpoint is None else checkpoint.load(),
                              on_pass=None if checkpoint is None else checkpoint.save,
                              kept=getattr(checkpoint, "kept", None))
        self.last_run, self.last_plan = run, run.plan
        if checkpoint is not None and "resumed_from_pass" in run.info:
            checkpoint.reused(len(cells), run.info["resumed_from_pass"])
        self._ideal = np.array(ideal)
        return [r for r in results]

    @property
    def is_ideal_geometry(self) -> bool:
        """Every aperture zero on a bare flat sample (no housing, parts or XML scene): the
        instrument is the ideal point geometry of docs/conventions.md section 5, where k_A = 1 by
        definition. Rendering it would give 1 up to float32 rounding (~1e-7) with an SE of exactly 0
        (every sample is the same ray): a z of infinity against the float64 backends, which give 1."""
        rs = self.rs
        return bool(self.instrument.is_ideal() and rs.flat_rectangle and rs.xml is None and not rs.parts
                    and rs.housing is None and not self.engine.stray)

    def _ideal_results(self, cells, on_cell, t0: float) -> list[CellResult]:
        """k_A = 1 exactly, SE 0, for the ideal geometry (:attr:`is_ideal_geometry`), after the
        checks every float64 backend makes at each cell (horizon, beam, nominal value)."""
        from roadgonio.engines.cellcheck import check_cells
        from roadgonio.engines.registry import backend_info
        check_cells(self.instrument, self.model, cells, models_beam=backend_info(self.name).beam_clipping,
                    backend=self.name)
        self.last_run, self.last_plan = None, None
        self._ideal = np.ones(len(cells))
        out = []
        for t, b in cells:
            r = CellResult(tan_eps=t, beta_deg=b, k_a=1.0, se=0.0, converged=True, samples=0,
                           seconds=(time.perf_counter() - t0) / max(len(cells), 1),
                           extra={"ideal_geometry": True, "converged": True,
                                  "note": "every aperture is zero: the ideal geometry, k_A = 1 by definition"})
            out.append(r)
            if on_cell is not None:
                on_cell(r)
        return out

    def _result(self, cell, ideal: float, st, converged: bool, seconds: float, stray_se=None, *,
                dof: float | None = None) -> CellResult:
        """The cell's result; ``stray_se``: with stray light traced (``st.direct``), its (direct
        ratio, SE, stray fraction, SE), and ``dof``, its SE's degrees of freedom, computed with the
        pass's other cells (:func:`~roadgonio.engines.mitsuba.passes.stray_ratios`,
        :func:`~roadgonio.engines.mitsuba.passes.se_dof_many`; else of this cell alone)."""
        from roadgonio.engines.mitsuba.passes import STRAY_SEEN_MIN, relative
        from roadgonio.engines.result import RATIO_DENOMINATOR_REL_SE_MAX, sparse_light_note
        ratio, se, _ = st.ratio_se()
        dof = st.se_dof() if dof is None else dof
        rel = relative(ratio, se)
        # the model is 0 at the nominal geometry: k_A (with or without stray light) is undefined
        # (divided, not multiplied by 1 / ideal: the same float64 numbers as the engine without stray light)
        div = ideal if ideal > 0.0 else math.nan
        k_a, k_se = ratio / div, se / div
        extra = {"ratio": ratio, "ratio_se": se, "ideal_ratio": ideal, "passes": st.passes,
                 "replicates": int(sum(len(v[0]) for v in st.strata.values())), "rel_se": rel,
                 "converged": bool(converged)}
        mean_road = abs(st.sum_r) / st.samples if st.samples else 0.0
        if ideal <= 0.0:
            extra["note"] = "the model is 0 at the nominal geometry: k_A is undefined"
            dof = math.nan
        elif (zero := ratio == 0.0 and se == 0.0) or 0.0 < mean_road < FLOAT32_SIGNAL_MIN:
            # float32 lost the signal: all of it (0 +- 0 "converged", a lobe exponent of ~1e4 far off the
            # lobe; user audit, session 24), or part of the lobe's tail (11434 +- 11, converged, where the
            # truth is 30516; user audit, session 35)
            k_a = k_se = math.nan
            converged = False
            dof = math.nan
            extra.update(converged=False, float32_underflow=True)
            if zero:
                extra["note"] = (f"the rendered road signal is 0 in every sample while the model is positive at the "
                                 f"nominal geometry ({ideal:.3g} of the Lambertian's): its values underflow the float32 "
                                 "renderer here; k_A is not measured (use a float64 backend: quadrature or reference; numpy-mc samples "
                                 "the same lobe and may not finish)")
            else:
                extra["mean_road"] = mean_road
                extra["note"] = (f"the rendered road signal is {mean_road:.2g} a sample, within eight decades of "
                                 f"float32's smallest normal number ({FLOAT32_TINY:.2g}), where the renderer loses the "
                                 "lobe's tail: k_A is not measured (use a float64 backend: quadrature or reference)")
        elif math.isfinite(ratio) and (lit := st.lambert_rel_se()) > RATIO_DENOMINATOR_REL_SE_MAX:
            # one lit replicate of 16 gave k_A 1.0075 +- 1.5e-16, "converged" (user audit, session 34)
            extra["sparse_light"] = float(lit)
            extra["note"] = sparse_light_note(extra["sparse_light"])
        stray = {}
        if st.direct:
            # the direct light alone (today's k_A) and the stray fraction, from the same replicates
            rd, rd_se, sf, sf_se, stray_dof = (float(v) for v in stray_se)
            stray = dict(k_a_direct=float(rd / div), k_a_direct_se=float(rd_se / div),
                         stray_fraction=float(sf), stray_fraction_se=float(sf_se))
            dof = float(np.fmin(dof, stray_dof))     # one se_dof for the cell's three SEs: the smallest
            extra["max_bounces"] = self.engine.max_bounces
            if self.planner.statistic == "absolute":
                # the absolute calibration's statistic, R / G_d, with its SE from the same replicates
                # (calibration.py reports k_A = eta R / G_d / ideal with this relative SE)
                ra, ra_se = st.absolute_ratio_se()
                extra.update(absolute_ratio=float(ra), absolute_ratio_se=float(ra_se))
            elif k_se == 0.0 and math.isfinite(k_a):
                # a Lambertian sample under the Lambert calibration: k_A = 1 exactly, nothing for
                # --rel-se to reach (user audit, session 43: 1e-4 asked, the first pass's 4096 samples)
                extra["note"] = ("k_A is exact here (the sample reflects like the calibration's Lambertian), so the "
                                 "target SE has nothing to reach and the stray fraction's SE is the first pass's; the "
                                 "absolute calibration's k_A carries the stray light and converges on it")
            seen = st.stray_seen()
            extra["stray_seen"] = seen
            if self.planner.stray_search and st.stray_never_seen():
                extra["note"] = (f"no stray light seen in {st.samples} samples: the reflecting parts send none "
                                 "to this cell's footprint that the paths could find")
            elif self.planner.stray_search and seen < STRAY_SEEN_MIN:
                extra["note"] = (f"stray light seen in only {100 * seen:.0f} % of the replicate sums after "
                                 f"{st.samples} samples (rare paths through the reflecting parts): its standard "
                                 "error may understate the error, so the cell counts as not converged")
        return CellResult(tan_eps=cell[0], beta_deg=cell[1], k_a=float(k_a), se=float(k_se),
                          converged=bool(converged), samples=int(st.samples), seconds=float(seconds), extra=extra,
                          se_dof=float(dof), **stray)

    def compute_cell(self, tan_eps: float, beta_deg: float) -> CellResult:
        """One cell (a batch of one)."""
        return self.compute([(tan_eps, beta_deg)])[0]

    def covariance(self) -> np.ndarray:
        """Covariance matrix of the k_A values of the last ``compute`` call (cells in its order):
        the diagonal is SE^2; off-diagonal terms from the replicates the cells shared
        (:func:`roadgonio.engines.mitsuba.passes.covariance`)."""
        if self.last_run is None:
            if self._ideal is not None and self.is_ideal_geometry:
                return np.zeros((self._ideal.size, self._ideal.size))   # exact results: no covariance
            raise RuntimeError("no compute() call yet")
        cov = self.last_run.covariance()
        return cov / np.outer(self._ideal, self._ideal)


def make_backend(instrument: Instrument, model: RoadModel, *, rel_se: float = 1e-3, seed: int = 0,
                 first_pass: int = DEFAULT_FIRST_PASS, min_replicates: int = DEFAULT_MIN_REPLICATES,
                 min_passes: int = 1, max_samples: int = DEFAULT_MAX_SAMPLES, plan=None,
                 mitsuba_variant: str | None = None, **unknown) -> MitsubaBackend:
    """The Mitsuba k_A backend (:class:`MitsubaBackend`); builds and checks the scene now, so
    geometry errors surface before any cell is computed."""
    removed = sorted(k for k in unknown if k in REMOVED)
    if removed:
        k = removed[0]
        hint = f"; use {REMOVED[k]} (samples per cell in the first pass)" if REMOVED[k] == "first_pass" else (
            f"; use {REMOVED[k]}" if REMOVED[k] else "")
        raise InputError(f"the setting {k!r} belonged to the per-cell renderer and no longer exists: the batched "
                         f"engine samples randomly shifted lattices and sizes its passes from rel_se{hint}",
                         field=k)
    if unknown:
        raise InputError(f"unknown setting(s) {', '.join(sorted(unknown))} for the mitsuba backend; expected "
                         "rel_se, seed, first_pass, min_replicates, min_passes, max_samples, plan, mitsuba_variant")
    if not isinstance(model, RoadModel) and not renders_in_drjit(model):
        raise InputError(f"the mitsuba backend renders the road BSDF of eq. 4 (a RoadModel) or a surface that "
                         f"evaluates over Dr.Jit arrays; {getattr(model, 'name', type(model).__name__)!r} is a "
                         f"{type(model).__name__}, which only the numpy backends evaluate (reference, numpy-mc)",
                         field="sample")
    return MitsubaBackend(instrument, model, rel_se=rel_se, seed=seed, first_pass=first_pass,
                          min_replicates=min_replicates, min_passes=min_passes, max_samples=max_samples,
                          plan=plan, mitsuba_variant=mitsuba_variant)
