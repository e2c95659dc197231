"""Which second aperture should my instrument have? (docs/design.md, "Which second aperture?"; docs/correction.md,
"Two instruments, one surface").

One instrument cannot tell the BRDF's behaviour off alpha = 1 deg from its shape in (beta, eps):
both blur the same way. A second aperture setting (another field stop, pupil or source aperture of
the same instrument, or another instrument) blurs differently, and the correction through both
(:func:`roadgonio.correction.outside.correct_surface` with two tables) pins the surface down better.
This design mode ranks candidate second settings by the uncertainty of the one corrected table they
would give, before anything is measured:

1. the surface: the correction surface (eq. 4 backbone x correction surface,
   :mod:`roadgonio.correction.flexible`) fitted through the instrument to a measured table (``measured``),
   or to what the instrument would measure of a SAMPLE (``sample``: any BRDF model; noise-free, with
   the relative uncertainty ``u_measured``), its smoothing parameters by the evidence;
2. per candidate (every point of the ``vary`` grid of :mod:`roadgonio.design.grid`, applied to the
   instrument), the posterior covariance the two measurements would give at that surface
   (:func:`roadgonio.correction.flexible.expected_posterior`: a linearised Gaussian posterior does
   not depend on the measured values), hence each instrument's ln k_A covariance, and the
   generalised-least-squares combination of the two corrected tables
   (:func:`roadgonio.correction.outside.combine`);
3. the candidates ranked by the median relative u of the combined table (u(S1) beside it, indicative
   only: :data:`U_S1_PAIR_RATIO`), among
   those whose signal (:func:`roadgonio.design.metrics.relative_signal`, relative to the instrument)
   is at least ``min_signal`` (default 0.25: smaller apertures always blur less, so without a floor
   on the light the answer is "the smallest"; a second field stop that keeps a quarter of the light
   is a plausible one), with two baselines: the instrument alone, and the instrument measuring twice
   (what a repetition buys without a second aperture).

The expected u holds the measurement, the surface's posterior (the backbone's parameters free,
:func:`roadgonio.correction.flexible.posterior_with_backbone`) and the ``discrepancy`` (what both
blurs hide below the knots, :func:`roadgonio.correction.outside.parts_discrepancy`; fully correlated
between two measurements with one setting, so measuring twice does not average it away, while a
second aperture that resolves more does), of the table the correction gives: the instruments'
r / k_A and the fitted surface's own value combined by generalised least squares. Left out: the
backend's and the ray bundles' own errors (on the tests' medium table 0.1 % and, at 512 rays, 0.5 %
RMS of a total u of ~2.5 %: docs/correction.md, "What the ray bundles move"), the spread of the backbone variants (the backbone
is the variant of larger evidence, the one the correction weighs ~1, or the one asked for), the
misalignment, and for an instrument with stray light the ``unobserved`` component (the road beyond
the observation elevations: the correction renders it, this ranking renders nothing). g_D's prior
keeps the scale of the fit through the instrument alone (held there: ``SurfaceSettings.d_prior_scale``
"joint"); the joint correction lets the evidence of both measurements choose it, which on the bench's
out-of-family truths narrowed it and lowered u(S1) by up to 6 % of itself (eq. 4: by a third), so the
forecast is on the side of caution there.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from roadgonio.correction.budget import DEFAULT_U_MEASURED
from roadgonio.errors import InputError
from roadgonio.instrument.config import Instrument

#: The measurement's relative u when none is given: correct's default (one default, audit 28).
DEFAULT_U = DEFAULT_U_MEASURED
#: Least signal of a second setting, relative to the instrument's (module docstring).
DEFAULT_MIN_SIGNAL = 0.25
#: The least relative reduction of the median u against measuring twice that is called a gain. The
#: prediction agrees with the correction it predicts within 30 % (docs/correction-record.md, "Which
#: second aperture?"); two settings predicted at the same surface differ more exactly than that, by
#: how much is not measured, so a best setting within 10 % of a repetition is reported as no better
#: (user audit, session 24: 0.5 % was called the best second setting without a word).
MIN_GAIN_OVER_TWICE = 0.10
#: What a pair's predicted u(S1) is worth: the joint correction's evidence chooses its own smoothing
#: (and since session 33 g_D's prior scale) from both tables, and the u(S1) it states was 0.57-1.74
#: times the prediction with a second setting over eight noise realisations (session 29), 0.37 and
#: 1.95 in two (session 37), 0.32-0.66 over four and 0.90-1.04 measured twice over two (session 42,
#: an eq. 4 truth), 0.44-0.82 over three outside eq. 4 (session 42's user audit); docs/correction.md,
#: "Its u(S1) for a pair is indicative only". The ranking is by the median u.
U_S1_PAIR_RATIO = (0.32, 1.95)
#: The median u the full ``correct --joint`` states, over the predicted one (docs/correction.md,
#: "Measured again with the full correct --joint"), re-measured in session 42 against the prediction
#: as it is now (it had moved 18 % since session 37's 0.216 %, user audit): R3's fit (eq. 4) through
#: `portable` and its 20 mm setting, 0.42-0.45 over four realisations (the joint evidence narrows g_D's
#: prior, which the prediction holds), measuring twice 0.90 and 1.72 over two; outside eq. 4 (the
#: audit's own truth and forward model, a 0.08 deg field as the second setting) 0.89-0.98 over three.
#: The ranking is by the predicted u.
U_MEDIAN_PAIR_RATIO = (0.42, 1.72)
#: Predicted median u within this fraction of the lowest are not told apart: the ray bundles' seed
#: moved the "measured twice" baseline by 6e-4 of itself (user audit, session 44: 0.13196 against
#: 0.13202 % for 16 times the light); the brightest of them is the best (:func:`prefer_brightest`).
U_SAME_REL = 1e-3


@dataclass
class Candidate:
    label: str
    changes: dict[str, float]
    instrument: Instrument | None
    u_median: float
    u_rms: float
    u_max: float
    u_s1_rel: float
    signal: float = 1.0
    note: str = ""
    #: the instrument's own setting: measuring it again is the "twice" baseline, not a second aperture
    own: bool = False

    def ranked(self, min_signal: float) -> bool:
        """A second aperture the ranking takes: another setting, with enough signal, that measures every cell."""
        return not self.own and self.signal >= min_signal and math.isfinite(self.u_median)

    def row(self) -> dict[str, Any]:
        return {"candidate": self.label, **{k: v for k, v in self.changes.items()}, "u_median_pct": 100 * self.u_median,
                "u_rms_pct": 100 * self.u_rms, "u_max_pct": 100 * self.u_max, "u_S1_pct": 100 * self.u_s1_rel,
                "signal": self.signal, "note": self.note}


@dataclass
class SecondApertureResult:
    instrument: Instrument
    surface_from: str
    candidates: list[Candidate]          # ranked, best first (baselines excluded)
    baselines: list[Candidate]           # the instrument alone, and measuring twice
    keys: list[str]
    seconds: float
    settings: dict[str, Any] = field(default_factory=dict)
    out: Path | None = None
    written: list = field(default_factory=list)

    @property
    def best(self) -> Candidate:
        return self.candidates[0]

    @property
    def gain_over_twice(self) -> float:
        """1 - (best median u) / (median u measured twice): what the second aperture buys beyond a
        repetition of the instrument's own setting."""
        return 1.0 - self.best.u_median / self.baselines[1].u_median

    @property
    def beats_twice(self) -> bool:
        """Whether the best second setting buys more than a repetition (:data:`MIN_GAIN_OVER_TWICE`)."""
        return bool(self.gain_over_twice >= MIN_GAIN_OVER_TWICE)

    def verdict(self) -> str:
        """One sentence on the best second setting against measuring twice (terminal, TOML, picture)."""
        g = self.gain_over_twice
        if self.beats_twice:
            return f"median u {100 * g:.0f} % below measuring the instrument's own setting twice"
        where = f"only {100 * g:.1f} % below it" if g > 0 else f"{100 * -g:.1f} % above it"
        return (f"no better than measuring the instrument's own setting twice (median u {where}; "
                f"a gain under {100 * MIN_GAIN_OVER_TWICE:.0f} % is within what the prediction can tell): "
                "a repetition buys as much")

    def counts(self) -> dict[str, int]:
        """How many candidates the ranking took, and why the others are not ranked."""
        floor = float(self.settings.get("min_signal", DEFAULT_MIN_SIGNAL))
        c = self.candidates
        return {"ranked": sum(x.ranked(floor) for x in c), "own_setting": sum(x.own for x in c),
                "not_feasible": sum(not x.own and not math.isfinite(x.u_median) for x in c),
                "below_min_signal": sum(not x.own and math.isfinite(x.u_median) and not x.signal >= floor for x in c)}

    @staticmethod
    def u_s1_note() -> str:
        """What the u(S1) of a pair is worth (:data:`U_S1_PAIR_RATIO`): terminal and JSON."""
        lo, hi = U_S1_PAIR_RATIO
        return (f"u(S1) of a pair is indicative: a joint correction's evidence chooses its own smoothing from both "
                f"tables, and its u(S1) was {lo:g}-{hi:g} x the prediction (measured, docs/correction.md); "
                "the ranking is by the median u")

    @staticmethod
    def u_note() -> str:
        """What the predicted median u is worth against what ``correct --joint`` then states
        (:data:`U_MEDIAN_PAIR_RATIO`): terminal and JSON."""
        lo, hi = U_MEDIAN_PAIR_RATIO
        return (f"the median u that correct --joint states for a pair was {lo:g}-{hi:g} x this prediction (about "
                "half for a second setting on an eq. 4 surface, where the joint evidence narrows the model and "
                "that u was calibrated; 0.9-1.0 x on a surface outside eq. 4; 0.9-1.7 x for measuring twice, "
                "where it was conservative; measured, docs/correction.md)")

    def scope_notes(self) -> list[str]:
        """What the prediction leaves out of this instrument (terminal and JSON ``notes``)."""
        notes = []
        cells = self.instrument.cells
        if not cells.all_cells:
            # user audit, session 44: fixed-led measures 27 cells and fills the rest, and the prediction
            # spoke for a table measured in every cell without a word
            notes.append(f"the prediction assumes every cell of the table is measured; '{self.instrument.name}' "
                         f"measures {len(cells.measured)} and fills the rest ({cells.fill}), so its corrected table's "
                         "u is larger than predicted")
        if self.instrument.scene_parts():
            notes.append("the prediction's ray bundles leave out the instrument's housing / scene parts (their shade "
                         "and stray light), as the surface fit of `correct` does")
        return notes

    def summary(self) -> dict[str, Any]:
        return {"instrument": self.instrument.name, "surface_from": self.surface_from, "keys": self.keys,
                "notes": self.scope_notes(),
                "best": self.best.row(), "baselines": [b.row() for b in self.baselines], "counts": self.counts(),
                "gain_over_twice": self.gain_over_twice, "beats_twice": self.beats_twice, "verdict": self.verdict(),
                "u_S1_note": self.u_s1_note(), "u_note": self.u_note(),
                "candidates": [c.row() for c in self.candidates], "seconds": self.seconds, "settings": self.settings}


def _u_of(parts, theta, cov, u_rel, tables, extra=None, nominal=()) -> tuple[np.ndarray, float, float]:
    """(relative u per cell of the combined table, u(S1)/S1, S1) for parts sharing the surface;
    ``extra``: a further covariance over the estimates (the discrepancy); ``nominal``: the fitted
    model's own estimates at the nominal geometry, after the parts' cells
    (:func:`roadgonio.correction.outside.model_estimate_cells`), combined with them as the correction does."""
    from roadgonio.correction.budget import functionals
    from roadgonio.correction.outside import cell_key, combine, nominal_estimate
    lp, Jp = nominal_estimate(parts, theta, nominal)
    J = np.vstack([-p.lnk_full_jacobian(theta) for p in parts] + [Jp])
    big = J @ cov @ J.T
    big += np.diag(np.concatenate([np.asarray(u, dtype=np.float64) ** 2 for u in u_rel] + [np.zeros(len(lp))]))
    if extra is not None:
        big += extra
    union = [cell_key(c) for c in tables[0].cells]
    ests = [p.ln_r_nominal(theta) for p in parts] + ([lp] if len(lp) else [])
    lnr, G = combine(ests, [t.cells for t in tables] + ([union] if len(lp) else []), big, tables[0].cells)
    C = G @ big @ G.T
    u = np.sqrt(np.maximum(np.diag(C), 0.0))
    grid = np.full(tables[0].r.shape, np.nan)
    grid[tables[0].mask] = np.exp(lnr)
    f = functionals(tables[0].with_values(grid), C)
    return u, f["u_S1"] / f["S1"], f["S1"]


def prefer_brightest(cands: list[Candidate], min_signal: float) -> None:
    """Among the ranked settings whose median u is within :data:`U_SAME_REL` of the lowest (sorted
    first), put the one with the most signal first, with a note: the prediction does not tell them
    apart (user audit, session 44: 5 mm over 20 mm, u 0.131961 against 0.132020 %, 16x less light)."""
    ranked = [c for c in cands if c.ranked(min_signal)]
    if not ranked:
        return
    same = [c for c in ranked if c.u_median <= ranked[0].u_median * (1.0 + U_SAME_REL)]
    bright = max(same, key=lambda c: c.signal)
    if bright is ranked[0]:
        return
    bright.note = ((bright.note + "; ") if bright.note else "") + (
        f"median u within {100 * U_SAME_REL:g} % of the lowest ({100 * ranked[0].u_median:.4g} %, "
        f"{_changes(ranked[0].changes)}), which the prediction does not tell apart: the one with the most signal")
    cands.remove(bright)
    cands.insert(0, bright)


def _changes(changes: dict[str, float]) -> str:
    return ", ".join(f"{k} = {v:g}" for k, v in changes.items())


def _refuse(min_signal: float, own: bool, closest: tuple[dict[str, float], float] | None,
            why: tuple[dict[str, float], str] | None = None) -> NoReturn:
    """No second setting to rank: one line, naming the brightest that can measure (``closest``:
    its changes and signal) when there is one, and why the first that keeps the signal cannot
    (``why``: its changes and the reason)."""
    raise InputError("no second setting of the --vary grid " + ("other than the instrument's own " if own else "")
                     + f"keeps {min_signal:g} of the instrument's signal and can measure every cell"
                     + (f" ({_changes(why[0])} keeps it but is {why[1]})" if why is not None else "")
                     + (f" (the brightest, {_changes(closest[0])}, keeps {closest[1]:.3g}; a lower --min-signal "
                        "ranks it)" if closest is not None else ""), field="vary")


def check_second_keys(instrument: Instrument, specs) -> None:
    """Refuse, before any work, a varied key the prediction cannot honour: its ray bundles go through
    the optics alone, so no housing or scene key, and (:func:`roadgonio.design.grid.check_vary`)
    none the base instrument cannot take."""
    from roadgonio.design.grid import check_vary
    for s in specs:
        if s.section == "sample":
            # user audit, session 37: sample.size_x_m was ranked as a second aperture, "0.1 % above"
            # measuring twice: the footprint lies on the sample, so its size does not change the blur
            raise InputError(f"{s.key}: the sample's size does not change the instrument's blur (the footprint lies on "
                             "the sample): a second setting of it is the instrument measuring twice; vary the optics "
                             "(source, detector, observation)", field="vary")
        if s.section in ("housing", "scene"):
            raise InputError(f"{s.key}: the second aperture's prediction (ray bundles through the optics) does not "
                             "model a housing or scene parts; vary the optics (source, detector, observation)",
                             field="vary")
    check_vary(instrument, specs)


def second_aperture(instrument: Instrument, vary, *, measured=None, sample=None, u_measured: Any = DEFAULT_U,
                    rays: int | None = None, seed: int = 0, model_variant: str | None = None,
                    min_signal: float = DEFAULT_MIN_SIGNAL, progress: bool = False) -> SecondApertureResult:
    """Rank the second aperture settings of ``vary`` (module docstring). Exactly one of ``measured``
    (an r-table the instrument measured) and ``sample`` (a SAMPLE or a BRDF model) gives the surface."""
    from roadgonio.correction.flexible import FlexPart, SurfaceSettings, expected_posterior, fit_surface
    from roadgonio.correction.outside import (DEFAULT_VARIANTS, cell_key, model_estimate_cells, parts_discrepancy,
                                              search_backbones)
    from roadgonio.engines.bundle import DEFAULT_RAYS, ForwardModel, RayBundles
    from roadgonio.correction.run import measured_uncertainty
    from roadgonio.design.grid import as_vary_specs, build_instrument, grid_points
    from roadgonio.design.metrics import relative_signal
    from roadgonio.surface.rtable import RTable, bundled_table
    t0 = time.perf_counter()
    if (measured is None) == (sample is None):
        raise InputError("give either the measured table of the instrument or a SAMPLE to design for",
                         field="measured/sample")
    specs = as_vary_specs(vary)
    if not specs:
        raise InputError("expected at least one --vary KEY=... for the second aperture", field="vary")
    check_second_keys(instrument, specs)
    if instrument.is_ideal():
        # user audit, session 44: the collimated preset's signal is 0, every relative signal NaN, and the
        # refusal advised a lower --min-signal, which ranks nothing
        raise InputError(f"'{instrument.name}' is an ideal instrument (point source and pinhole: k_A = 1, no signal "
                         "to compare): it has no aperture effect for a second setting to help", field="instrument")
    rays = int(rays or DEFAULT_RAYS)
    settings = SurfaceSettings()
    if measured is not None:
        table = measured
        cells = table.cells
        fm = ForwardModel(RayBundles.build(instrument, cells, rays=rays, seed=seed))
        u_grid, _ = measured_uncertainty(u_measured, table)
        y, u = table.r[table.mask], u_grid[table.mask]
        source = f"measured table {table.name}"
    else:
        from roadgonio.surface.sample import resolve_sample
        model = resolve_sample(sample, model_variant).model if isinstance(sample, str) else sample
        table = RTable(np.where(bundled_table("R3").mask, 1.0, np.nan), name=getattr(model, "name", "sample"))
        cells = table.cells
        fm = ForwardModel(RayBundles.build(instrument, cells, rays=rays, seed=seed))
        from roadgonio.arrays import NumpyOps
        b = fm.bundles
        y = b.cell_sum(np.asarray(model.evaluate(NumpyOps, b.wi, b.wo), dtype=np.float64)) * b.cos3 * fm.kappa
        g = np.full(table.r.shape, np.nan)
        g[table.mask] = y
        table = table.with_values(g)
        u_grid, _ = measured_uncertainty(u_measured, table)
        u = u_grid[table.mask]
        source = f"sample {getattr(model, 'name', sample)} (noise-free, through the instrument)"
    # every grid point's instrument and signal, and whether a second setting that would be ranked can
    # measure every cell, before the surface is fitted (the fits take tens of seconds): none of it needs the
    # surface, and a grid with no second setting to rank is refused at once
    points = grid_points(specs)
    insts = []
    for point in points:
        try:
            insts.append(build_instrument(instrument, point))
        except InputError as err:
            # the value came from --vary, not from the instrument file the error would name (user audit, session 37)
            given = ", ".join(f"{k}={v:g}" for k, v in point.items())
            raise InputError(f"the --vary point {given} is not an instrument: {err.reason}", field="vary") from None
    own = [inst_b.to_dict() == instrument.to_dict() for inst_b in insts]
    signal = [1.0 if own[k] else float(relative_signal(inst_b, instrument, cells)) for k, inst_b in enumerate(insts)]
    forward: dict[int, Any] = {}

    def forward_of(k: int):
        """Grid point k's forward model, or why its setting cannot measure every cell (built once)."""
        if k not in forward:
            try:
                forward[k] = ForwardModel(RayBundles.build(insts[k], cells, rays=rays, seed=seed + 1))
            except InputError as err:
                forward[k] = f"not feasible: {err.reason}"
            except Exception as err:  # noqa: BLE001 - a geometry the second setting cannot measure
                # the reason without the base instrument's file: the setting is the --vary point's
                forward[k] = f"not feasible: {getattr(err, 'reason', None) or err}"
        return forward[k]

    def feasible(k: int) -> bool:
        return not isinstance(forward_of(k), str)

    others = [k for k in range(len(points)) if not own[k]]
    # any() stops at the first that can measure: the others' bundles are built as they are evaluated
    if not any(feasible(k) for k in others if signal[k] >= min_signal):
        dim = sorted((k for k in others if not signal[k] >= min_signal), key=lambda k: -signal[k])
        closest = next((k for k in dim if feasible(k)), None)
        # why the bright ones cannot measure (user audit, session 42: a 0.3 deg field, 4x the signal, was
        # refused in words that spoke of the signal only; its footprint leaves the sample)
        bright = [k for k in others if signal[k] >= min_signal]
        why = None if not bright else (dict(points[bright[0]]), forward_of(bright[0]))
        _refuse(min_signal, any(own), None if closest is None else (dict(points[closest]), signal[closest]), why)

    # the backbone the correction would take: correct --forward surface fits every variant of
    # DEFAULT_VARIANTS at every rounding of the mirror plane and weighs them by their evidence; the
    # prediction takes the one of larger evidence, or the variant asked for
    # (searched as the correction searches them: roadgonio.correction.outside.search_backbones)
    fits = []
    variants = (model_variant,) if model_variant else DEFAULT_VARIANTS
    backbones, _, _ = search_backbones(fm, y, u, variants, settings, seed=seed, name=table.name)
    for (variant, _r), bb in backbones.items():
        pa = FlexPart(fm, bb, settings)
        fits.append((fit_surface([pa], [y], [u]), variant, bb, pa))
    fit, variant, backbone, part_a = max(fits, key=lambda f: f[0].log_evidence)
    theta, lam = fit.theta, fit.lam
    u_rel = u / y

    blurs: dict = {}

    def evaluate(parts, urs, tables, label, changes, inst, note="") -> Candidate:
        cov = expected_posterior(parts, theta, lam, urs, fit.phi, fit.d_scale)
        nominal = (model_estimate_cells([t.cells for t in tables], [cell_key(c) for c in tables[0].cells])
                   if settings.model_estimate else [])
        disc = None
        if settings.discrepancy_ell is not None:
            disc, _ = parts_discrepancy(parts, theta, [(1.0, fit.prior_lam)], settings, blurs, nominal=nominal)
        uu, us1, _ = _u_of(parts, theta, cov, urs, tables, disc, nominal)
        return Candidate(label, changes, inst, float(np.median(uu)), float(np.sqrt(np.mean(uu ** 2))),
                         float(np.max(uu)), float(us1), note=note)

    baselines = [evaluate([part_a], [u_rel], [table], "alone", {}, instrument, "the instrument alone"),
                 evaluate([part_a, part_a], [u_rel, u_rel], [table, table], "twice", {}, instrument,
                          "the same setting measured twice (repetition only)")]
    cands = []
    for k, point in enumerate(points):
        if own[k]:
            # the grid point is the instrument itself: a second measurement with it is the "twice"
            # baseline (trial 12 D2: evaluated again with other bundles it won by noise and was
            # recommended as the "best second setting")
            t = baselines[1]
            cands.append(Candidate(f"setting {k + 1}", dict(point), insts[k], t.u_median, t.u_rms, t.u_max, t.u_s1_rel,
                                   note="the instrument's own setting: measuring it twice (a baseline, not ranked)",
                                   own=True))
            continue
        fm_b = forward_of(k)
        forward.pop(k)                       # evaluated once: its bundles need not outlive it
        if isinstance(fm_b, str):
            # (the reason by name: given eighth it was taken for the signal, and the ranking's
            # signal >= min_signal raised a TypeError for any grid with such a setting)
            cands.append(Candidate(f"setting {k + 1}", dict(point), None, math.inf, math.inf, math.inf, math.inf,
                                   signal=signal[k], note=fm_b))
            continue
        # below min_signal it is evaluated all the same: the table and the plot show what the
        # light given up would buy (what a lower --min-signal would rank)
        part_b = FlexPart(fm_b, backbone, settings)
        c = evaluate([part_a, part_b], [u_rel, u_rel], [table, table], f"setting {k + 1}", dict(point), insts[k])
        blurs.pop(part_b, None)
        c.signal = signal[k]
        if not c.signal >= min_signal:
            c.note = f"signal {c.signal:.3g} below {min_signal:g} of the instrument's"
        cands.append(c)
        if progress:
            import sys
            print(f"roadgonio design: second aperture {k + 1}/{len(points)}", file=sys.stderr, flush=True)
    cands.sort(key=lambda c: (not c.ranked(min_signal), c.u_median, c.u_s1_rel))
    prefer_brightest(cands, min_signal)
    if not (cands and cands[0].ranked(min_signal)):
        # every setting that could measure gave a u that is not finite (not seen): refused as above
        measured_ok = [c for c in cands if not c.own and math.isfinite(c.u_median)]
        closest = max(measured_ok, key=lambda c: c.signal) if measured_ok else None
        _refuse(min_signal, any(own), None if closest is None else (closest.changes, closest.signal))
    return SecondApertureResult(instrument=instrument, surface_from=source, candidates=cands, baselines=baselines,
                                keys=[s.key for s in specs], seconds=time.perf_counter() - t0,
                                settings={"u_measured": str(u_measured), "rays": rays, "seed": seed,
                                          "backbone": backbone.to_json_dict(), "backbone_variant": variant,
                                          "backbone_choice": ("asked for (--model-variant)" if model_variant else
                                                              "the larger evidence of " + ", ".join(DEFAULT_VARIANTS)
                                                              + ", as correct --forward surface weighs them"),
                                          "lambda": lam, "min_signal": min_signal,
                                          "surface": settings.to_dict()})


def write_second_aperture(res: SecondApertureResult, out_dir: str | Path, *, plots: bool = True,
                          fingerprint: str | None = None) -> list[Path]:
    """second_aperture.csv (every candidate and the baselines), second_aperture.json (with the run's
    ``fingerprint``, which a later run into the folder is checked against), best_second.toml (the
    instrument file of the best second setting) and second_aperture.png, together or not at all."""
    import csv
    import io

    from roadgonio.design.outputs import toml_text
    from roadgonio.fileio import OutputGroup
    rows = [b.row() for b in res.baselines] + [c.row() for c in res.candidates]
    keys = ["candidate"] + res.keys + ["u_median_pct", "u_rms_pct", "u_max_pct", "u_S1_pct", "signal", "note"]
    buf = io.StringIO()
    buf.write(f"# second aperture for {res.instrument.name}: expected relative u of the one corrected table "
              f"(surface from {res.surface_from}); best first after the two baselines\n")
    w = csv.DictWriter(buf, fieldnames=keys, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    from roadgonio.provenance import provenance
    prov = provenance(instrument=res.instrument, settings=res.settings,
                      quantity="roadgonio design --second-aperture: expected u of the corrected table per second "
                               "aperture setting (roadgonio.design.second_aperture)")
    # every file it writes: one not written this time (--no-plots, no best setting) is removed (audit 22)
    with OutputGroup(out_dir, replaces=("second_aperture.csv", "second_aperture.json", "best_second.toml",
                                        "second_aperture.png")) as group:
        paths = [group.text("second_aperture.csv", buf.getvalue()),
                 group.json("second_aperture.json", {**res.summary(), "provenance": prov,
                                                     **({"fingerprint": fingerprint} if fingerprint else {})})]
        if res.best.instrument is not None:
            d = res.best.instrument.to_dict()
            changes = ", ".join(f"{k} = {v:g}" for k, v in res.best.changes.items())
            # the base's description would describe the base (its field, its pupil): say what changed
            d["instrument"] = {**d.get("instrument", {}), "name": f"{res.instrument.name}-second",
                               "description": f"second aperture setting of '{res.instrument.name}' (roadgonio design "
                                              f"--second-aperture): {changes}"}
            paths.append(group.text("best_second.toml", toml_text(d, header=(
                f"Second aperture setting of {res.instrument.name} that minimises the median u of the corrected table "
                f"({100 * res.best.u_median:.2f} %; alone {100 * res.baselines[0].u_median:.2f} %, measured twice "
                f"{100 * res.baselines[1].u_median:.2f} %): {res.verdict()}. Varied: {changes}. Made by roadgonio design "
                "--second-aperture."))))
        if plots:
            from roadgonio.plots import _plt
            fig = draw_second_aperture(res)
            try:
                paths.append(group.figure("second_aperture.png", lambda p: fig.savefig(p, format="png", dpi=100)))
            finally:
                _plt().close(fig)
    return paths


def draw_second_aperture(res: SecondApertureResult):
    """Median u and u(S1) of the corrected table for every candidate, the baselines as lines."""
    from roadgonio.plots import _plt
    plt = _plt()
    ok = [c for c in res.candidates if math.isfinite(c.u_median) and not c.own]   # the own setting: the "twice" line
    ok.sort(key=lambda c: tuple(c.changes[k] for k in res.keys))
    labels = [", ".join(f"{k.split('.')[-1]}={c.changes[k]:g}" for k in res.keys) + f"\n(signal {c.signal:.2g})"
              for c in ok]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(14, 5.5))
    x = np.arange(len(ok))
    for ax, attr, what in ((a1, "u_median", "median relative u of the corrected table (%)"),
                           (a2, "u_s1_rel", "u(S1) / S1 (%)\n(a pair's is indicative: x{:g}-{:g} measured)".format(
                               *U_S1_PAIR_RATIO))):
        vals = [100 * getattr(c, attr) for c in ok]
        kinds = ["best" if c is res.best else ("candidate" if not c.note else "dim") for c in ok]
        bars = ax.bar(x, vals, color=[{"best": "C2", "candidate": "C0", "dim": "0.75"}[k] for k in kinds])
        # 3 significant digits: at 2 decimals the best (0.145) and the next (0.148) both read 0.15 (user audit)
        for b, v in zip(bars, vals):
            ax.text(b.get_x() + b.get_width() / 2, v, f"{v:.3g}", ha="center", va="bottom", fontsize=8)
        for base, style in zip(res.baselines, ("--", ":")):
            ax.axhline(100 * getattr(base, attr), color="0.3", ls=style, lw=1.2,
                       label=f"{base.note} ({100 * getattr(base, attr):.2f})")
        ax.set_xticks(x, labels, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel(what)
        from matplotlib.patches import Patch
        handles, _ = ax.get_legend_handles_labels()
        # only the kinds of bar drawn (user audit: "candidate" and "signal below" named where none was)
        patches = {"best": Patch(color="C2", label="best second setting"), "candidate": Patch(color="C0", label="candidate"),
                   "dim": Patch(color="0.75", label=f"signal below {res.settings.get('min_signal', DEFAULT_MIN_SIGNAL):g} "
                                                    "of the instrument's (not ranked)")}
        handles += [patches[k] for k in ("best", "candidate", "dim") if k in kinds]
        top = max(vals + [100 * getattr(base, attr) for base in res.baselines])
        ax.set_ylim(0.0, 1.6 * top)             # room for the legend above the bars and the baselines
        ax.legend(handles=handles, fontsize=8, loc="upper right")
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle(f"Second aperture for {res.instrument.name} (surface from {res.surface_from}); best: "
                 + ", ".join(f"{k} = {res.best.changes[k]:g}" for k in res.keys) + f"\n{res.verdict()}", fontsize=10)
    fig.tight_layout()
    return fig
