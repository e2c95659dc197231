"""The simulated participants: the table each one reports in one realisation of the comparison,
the uncertainty it states, and the same table with one of its characteristics idealised.

Reported table of participant p in realisation m (all cells of the comparison at once)::

    raw = r_meas(X) * k_A(X) * (1 + c_p) * prod_tiles (1 + c_t) * (1 + e)

* ``X = X_p + sum of the angle standards' draws`` (seven errors, :mod:`roadgonio.uncertainty.spec`),
  ``X_p`` drawn from the participant's SPEC, each angle standard drawn once per realisation and
  added for every participant that shares it (a correlation between them);
* ``r_meas(X)``: r the misaligned instrument reports without the aperture effect
  (:class:`roadgonio.uncertainty.MeasurementModel`, its illuminance normalisation);
* ``k_A(X)``: the aperture effect of its instrument, under its calibration mode, at the perturbed
  geometry (the uncertainty room's validated surrogate, :func:`roadgonio.uncertainty.run.build_surrogate`;
  1 for an ideal, collimated instrument);
* ``c_p ~ N(0, calibration_u_rel^2)``: its own calibration standard, ``c_t ~ N(0, u_t^2)`` a
  reference tile it shares with others (one draw per realisation for all of them);
* ``e ~ N(0, noise_rel^2)`` independently in every cell: the repeatability.

An instrument that measures only some cells (``[cells] measured``, a fixed-LED device) reports
``raw`` at those cells and fills the others from them (:mod:`roadgonio.instrument.coverage`); its
noise, misalignment and aperture effect at a filled cell are those of the measured cells it is
interpolated from, and idealising ``fill`` (the sensitivity ranking) reports every cell measured.

What it reports: ``raw`` (report = raw), ``raw / k_ref`` with k_ref the k_A of its instrument for
its reference sample (``roadgonio correct --reference SAMPLE``: independent of the measured table),
or ``raw / k_self`` with k_self the k_A of the model ``roadgonio correct --reference self`` fits to
that very table (:func:`roadgonio.correction.correct_measured`, one correction per realisation).

Stated relative standard uncertainty (what the participant would state, its own budget)::

    u_rel^2 = [repeatability] noise_rel^2 + [misalignment] sum_k (s_k sigma_k)^2
              + [calibration] (calibration_u_rel^2 + sum_tiles u_t^2) + stated_extra_rel^2
              (+ the correction's budget without its measurement term, when it corrects)

with ``s_k = d ln r_meas / d X_k`` at the nominal geometry (first-order GUM, JCGM 100 eq. 10,
central differences: :func:`roadgonio.uncertainty.gum_propagation`) and sigma_k of its own SPEC and
of the angle standards it shares. The stated covariance between two participants is the sum over
the effects they share of ``g_i g_j`` (tile: ``g = u_t x``; angle standard: ``g = s_k sigma_k x`` per
input), counted where both state that component.

Idealising a characteristic (the sensitivity ranking) changes only that participant's table in
the same realisation (common random numbers): a misalignment input, the noise, its calibration
standard or a shared effect is set to zero; an aperture (source radius, pupil radius, field), a
calibration mode other than Lambert or the source's distance multiplies k_A(X) by
k_ideal / k_A(0), the nominal k_A of the instrument with that aperture zero (or calibrated against
a Lambertian, or its source :data:`SOURCE_FAR_M` away, arc or rail, with its aperture scaled alike:
:func:`far_source`) over its own nominal k_A
(the misalignment dependence of k_A is kept from the full instrument: a second-order term); the
aperture effect as a whole sets k_A(X) = 1 (a collimated instrument);
for a participant that corrects, the aperture effect is one characteristic, idealised as a perfect
correction (``raw / k_A(X)``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from roadgonio.errors import InputError
from roadgonio.instrument.config import MAX_LENGTH_M
from roadgonio.intercomparison import statistics as st
from roadgonio.intercomparison.study import corrects_nothing

#: Scenarios of a study: as declared, and every participant correcting with roadgonio.
SCENARIOS = ("declared", "all_corrected")
#: The linearisation's check: every participant that corrects itself divides by its frozen factor
#: (the geometric mean of its full corrections' k) instead of its own correction of the realisation.
FROZEN = "all_corrected_frozen"
#: Apertures that can be idealised: key -> (instrument section, key, label).
APERTURES = {"source_aperture": ("source", "radius_m", "source aperture"),
             "detector_pupil": ("detector", "pupil_radius_m", "detector pupil"),
             "detector_field": ("detector", "field_half_angle_deg", "detector field")}
#: Where the ranking's ``source_distance`` item puts the source (m): an arc's distance or a rail's
#: height made this length, the aperture scaled alike (:func:`far_source`). 1 km, the longest length
#: an instrument may have (:data:`roadgonio.instrument.config.MAX_LENGTH_M`): the spread of
#: illumination directions over a footprint of +-0.5 m is then +-0.03 deg (the corridor preset's RMS
#: |k_A - 1| on R3 is the same with its rail 100 m and 1000 m high to 0.001 points).
SOURCE_FAR_M = MAX_LENGTH_M
#: Per-variant metrics of the realisation tasks (summed over the cells of one realisation): against
#: the truth (the participant's own error) and against the weighted mean.
METRICS = ("sum_err_rel2", "n_compatible_truth", "sum_d_rel2", "n_compatible", "n_cells")


# ----------------------------------------------------------------------------------------------
# The participants' models (built once, shipped to the workers)
# ----------------------------------------------------------------------------------------------

@dataclass
class ParticipantModel:
    """What a realisation needs of one participant (picklable: plain arrays and dataclasses)."""

    name: str
    report: str
    mm: Any                          # MeasurementModel of its instrument on the comparison's cells
    spec: Any                        # SigmaSpec: its own misalignment
    noise_rel: float
    calibration_u_rel: float
    stated: tuple[str, ...]
    stated_extra_rel: float
    surrogate: Any = None            # KaSurrogate of k_A(X) (None: an ideal instrument, k_A = 1)
    k_nominal: np.ndarray | None = None       # k_A at the nominal geometry, per cell
    k_ideal: dict[str, np.ndarray] = field(default_factory=dict)   # characteristic -> nominal k_A idealised
    k_reference: np.ndarray | None = None     # report = reference: the k_A it divides by
    u_reference_rel: np.ndarray | None = None # ... and the relative u of that correction (no measurement term)
    sens: np.ndarray | None = None            # (7, n) d ln r_meas / d X_k at the nominal geometry
    ideal: bool = False
    k_frozen: np.ndarray | None = None        # the frozen correction factor (scenario FROZEN only): the
    u_frozen_rel: np.ndarray | None = None    # geometric mean of its full corrections' k, their RMS u

    @property
    def n(self) -> int:
        return len(self.mm.cells)


@dataclass
class SharedModel:
    name: str
    kind: str
    members: tuple[int, ...]
    u_rel: float = 0.0
    spec: Any = None


@dataclass
class Setup:
    """Everything the realisations need: cells, truth, participants, shared effects, seed."""

    cells: Any                       # CellSet
    truth: np.ndarray                # (n,) r of the surface at the nominal geometry, sr^-1
    participants: list[ParticipantModel]
    shared: list[SharedModel]
    seed: int
    realisations: int
    coverage_factor: float

    @property
    def P(self) -> int:
        return len(self.participants)

    def characteristics(self, p: int, corrected: bool) -> list[tuple[str, str]]:
        """(key, label) of the characteristics of participant p that can be idealised."""
        pm = self.participants[p]
        out: list[tuple[str, str]] = []
        inst = pm.mm.instrument
        if corrected:
            if not pm.ideal or inst.calibration.mode != "lambert":
                out.append(("correction", "aperture effect left by the correction"))
        else:
            apertures = k_characteristics(inst)
            if not pm.ideal:
                # a housed instrument's k_A carries its stray light (user audit, session 44: this label
                # took most of a bright housing's +19 pp under the apertures' name)
                housed = any(k == "housing" for k, _ in apertures)
                out.append(("aperture_effect", "aperture effect and the housing's stray light as a whole (k_A = 1)"
                            if housed else "aperture effect as a whole (k_A = 1)"))
            out += apertures
        if not inst.cells.all_cells:
            out.append(("fill", f"cells filled by {inst.cells.fill} ({len(inst.cells.measured)} of {pm.n} measured)"))
        from roadgonio.uncertainty.spec import INPUTS
        for k, name in enumerate(INPUTS):
            if pm.spec.sigma[k] > 0:
                out.append((f"misalignment:{name}", f"misalignment {name} (sigma {pm.spec.sigma[k]:g})"))
        if pm.noise_rel > 0:
            out.append(("noise", f"repeatability ({100 * pm.noise_rel:g} %)"))
        if pm.calibration_u_rel > 0:
            out.append(("calibration", f"calibration standard ({100 * pm.calibration_u_rel:g} %)"))
        for s in self.shared:
            if p in s.members:
                out.append((f"shared:{s.name}", f"shared {s.kind.replace('_', ' ')} '{s.name}'"))
        return out

    def variants(self, scenario: str) -> list[tuple[int, str, str]]:
        """(participant, key, label) of every idealisation in a scenario (baseline not included)."""
        out = []
        for p, pm in enumerate(self.participants):
            corrected = scenario == "all_corrected" or pm.report != "raw"
            out += [(p, key, label) for key, label in self.characteristics(p, corrected)]
        return out


def k_characteristics(inst) -> list[tuple[str, str]]:
    """(key, label) of the characteristics of an instrument that are idealised through the nominal
    k_A of the instrument without them (:func:`roadgonio.intercomparison.run.idealised_instrument`,
    one k_A table each): every non-zero aperture, a calibration mode other than Lambert, and the
    source's distance (:func:`far_source`) of any instrument that is not ideal, whether its source
    moves on an arc or on a rail."""
    out = []
    for key, (sec, attr, label) in APERTURES.items():
        if getattr(getattr(inst, sec), attr) > 0:
            out.append((key, f"{label} ({_aperture_text(inst, key)})"))
    if inst.calibration.mode != "lambert":
        out.append(("calibration_mode", f"calibration mode {inst.calibration.mode} (vs lambert)"))
    if not inst.is_ideal():
        src = inst.source
        where = f"rail {src.height_m:g} m high" if src.path == "fixed_height" else f"arc {src.distance_m:g} m"
        out.append(("source_distance", f"source distance ({where}; vs {SOURCE_FAR_M:g} m at the same angular size)"))
    from roadgonio.instrument.housing import Housing
    housing = Housing.of(inst)
    if housing is not None and (housing.wall_reflectance > 0 or housing.baffle_reflectance_value > 0):
        # the stray light of a [housing] (user audit, session 39: no item could name it, and at walls of
        # 0.2 it made 13.8 of a participant's 17.7 points of RMS error)
        baffles = (f", baffles {housing.baffle_reflectance_value:g}"
                   if housing.baffles and housing.baffle_reflectance_value != housing.wall_reflectance else "")
        out.append(("housing", f"housing's stray light (walls {housing.wall_reflectance:g}{baffles}; vs no housing)"))
    return out


def far_source(source) -> dict[str, float]:
    """The ``[source]`` changes of the ranking's ``source_distance`` item: the source's one length
    (an arc's distance, a rail's height: ``Source.length_key``) made :data:`SOURCE_FAR_M` and its
    aperture radius scaled by the same factor, so every cell sees it at the same angular size and
    from the same direction at the sample centre (an arc's distance and a rail's distance at every
    eps scale alike), while each point of the footprint is lit from (nearly) that one direction: the
    parallax of the footprint seen from the source, and the spread of its illuminance, are gone."""
    f = SOURCE_FAR_M / source.length_m
    return {source.length_key: SOURCE_FAR_M, "radius_m": source.radius_m * f}


def _aperture_text(inst, key: str) -> str:
    if key == "source_aperture":
        if inst.source.path == "fixed_height":
            return (f"R_S/h = {math.degrees(inst.source.radius_m / inst.source.length_m):.3g} deg at tan eps 0, "
                    f"x cos eps beyond")
        return f"R_S/D_S = {math.degrees(inst.source.radius_m / inst.source.length_m):.3g} deg"
    if key == "detector_pupil":
        return f"R_D/D_D = {math.degrees(inst.detector.pupil_radius_m / inst.detector.distance_m):.3g} deg"
    return f"gamma_D = {inst.detector.field_half_angle_deg:g} deg"


# ----------------------------------------------------------------------------------------------
# One realisation
# ----------------------------------------------------------------------------------------------

@dataclass
class Draws:
    """The random numbers of one realisation: per participant its own errors X (7,), the
    standard-normal noise (n,) and calibration variate; per shared effect its variate(s)."""

    X: list[np.ndarray]
    z_noise: list[np.ndarray]
    z_cal: list[float]
    shared: list[Any]                # float (tile) or (7,) errors (angle standard)


def draws(setup: Setup, m: int) -> Draws:
    """The random numbers of realisation m: ``SeedSequence(seed).spawn(realisations)[m]``, then one
    child per participant and per shared effect in study order, so they depend only on (seed, m)."""
    # the same SeedSequence as SeedSequence(seed).spawn(realisations)[m], without spawning all the
    # others first (that made a study quadratic in its realisations, audit 22)
    ss = np.random.SeedSequence(int(setup.seed), spawn_key=(int(m),))
    kids = ss.spawn(setup.P + len(setup.shared))
    X, zn, zc = [], [], []
    for p, pm in enumerate(setup.participants):
        rng = np.random.default_rng(kids[p])
        X.append(pm.spec.draw(rng, 1)[0])
        zn.append(rng.standard_normal(pm.n))
        zc.append(float(rng.standard_normal()))
    sh = []
    for s, sm in enumerate(setup.shared):
        rng = np.random.default_rng(kids[setup.P + s])
        sh.append(float(rng.standard_normal()) if sm.kind == "reference_tile" else sm.spec.draw(rng, 1)[0])
    return Draws(X=X, z_noise=zn, z_cal=zc, shared=sh)


def raw_table(setup: Setup, d: Draws, p: int, idealise: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(raw reported r, k_A(X)) of participant p in the realisation of ``d``, with the
    characteristic ``idealise`` idealised (module docstring)."""
    pm = setup.participants[p]
    X = d.X[p].copy()
    if idealise is not None and idealise.startswith("misalignment:"):
        from roadgonio.uncertainty.spec import INPUTS
        X[INPUTS.index(idealise.split(":", 1)[1])] = 0.0
    scale = 1.0 + (0.0 if idealise == "calibration" else pm.calibration_u_rel * d.z_cal[p])
    for s, sm in enumerate(setup.shared):
        if p not in sm.members or idealise == f"shared:{sm.name}":
            continue
        if sm.kind == "angle_standard":
            X = X + d.shared[s]
        else:
            scale *= 1.0 + sm.u_rel * d.shared[s]
    X2 = X[None, :]
    r = pm.mm.r_measured(X2)[0]
    if pm.surrogate is not None:
        k = pm.surrogate(pm.mm.surrogate_coords(X2)[0])[0]
    else:
        k = np.ones(pm.n) if pm.k_nominal is None else pm.k_nominal.copy()
    k_used = k
    if idealise == "aperture_effect":
        k_used = np.ones(pm.n)
    elif idealise is not None and idealise in pm.k_ideal:
        k_used = k * (pm.k_ideal[idealise] / pm.k_nominal)
    noise = 1.0 + (0.0 if idealise == "noise" else pm.noise_rel) * d.z_noise[p]
    raw = r * k_used * scale * noise
    cov = pm.mm.instrument.cells
    if not cov.all_cells and idealise != "fill":
        # the device reports its measured cells and fills the rest (roadgonio.instrument.coverage);
        # k_used stays what a perfect correction divides by: raw / k_used = fill(raw_measured / k_measured)
        t, b = pm.mm.cells.tan_eps, pm.mm.cells.beta_deg
        filled = cov.fill_table(t, b, raw)
        k_used = filled / cov.fill_table(t, b, raw / k_used)
        raw = filled
    return raw, k_used


def check_draws(setup: Setup, d: Draws, m: int) -> None:
    """Every participant's total errors of the realisation keep its geometry valid (never a NaN)."""
    from roadgonio.uncertainty.spec import check_trials
    for p, pm in enumerate(setup.participants):
        X = d.X[p].copy()
        for s, sm in enumerate(setup.shared):
            if p in sm.members and sm.kind == "angle_standard":
                X = X + d.shared[s]
        try:
            check_trials(pm.spec, pm.mm, X[None, :], first_index=m, option=f"participant {pm.name} sigma")
        except InputError as err:
            raise InputError(f"realisation {m + 1}: {err.reason}", field=err.field) from None


def stated_rel(setup: Setup, p: int) -> np.ndarray:
    """The relative standard uncertainty (n,) participant p states for its raw table (module
    docstring; the correction's budget is added by :func:`reported`)."""
    pm = setup.participants[p]
    u2 = np.zeros(pm.n)
    if "repeatability" in pm.stated:
        u2 += pm.noise_rel ** 2
    if "misalignment" in pm.stated:
        for sig in _angle_sigmas(setup, p):
            u2 += np.sum((pm.sens * sig[:, None]) ** 2, axis=0)
    if "calibration" in pm.stated:
        u2 += pm.calibration_u_rel ** 2 + sum(sm.u_rel ** 2 for sm in setup.shared
                                              if sm.kind == "reference_tile" and p in sm.members)
    u2 += pm.stated_extra_rel ** 2
    return np.sqrt(u2)


def _angle_sigmas(setup: Setup, p: int) -> list[np.ndarray]:
    pm = setup.participants[p]
    out = [pm.spec.sigmas]
    out += [sm.spec.sigmas for sm in setup.shared if sm.kind == "angle_standard" and p in sm.members]
    return out


def shared_components(setup: Setup) -> np.ndarray:
    """The relative shared components g (S, P, n) of the stated covariance (module docstring)."""
    rows = []
    for sm in setup.shared:
        if sm.kind == "reference_tile":
            g = np.zeros((setup.P, len(setup.truth)))
            for p in sm.members:
                if "calibration" in setup.participants[p].stated:
                    g[p] = sm.u_rel
            rows.append(g)
        else:
            for k in np.nonzero(sm.spec.sigmas > 0)[0]:
                g = np.zeros((setup.P, len(setup.truth)))
                for p in sm.members:
                    pm = setup.participants[p]
                    if "misalignment" in pm.stated:
                        g[p] = pm.sens[k] * sm.spec.sigmas[k]
                rows.append(g)
    return np.array(rows).reshape(len(rows), setup.P, len(setup.truth))


def reported(setup: Setup, p: int, raw: np.ndarray, k_used: np.ndarray, mode: str,
             correction: tuple[np.ndarray, np.ndarray] | None, idealise: str | None = None,
             frozen: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(reported r, stated relative u) of participant p from its raw table: ``mode`` raw,
    reference or self (``correction`` = (k_self, u_rel) of its correction of that realisation; None:
    not corrected, NaN; ``frozen``: its frozen factor instead)."""
    pm = setup.participants[p]
    base = stated_rel(setup, p)
    if mode == "raw":
        return raw, base
    if mode == "reference":
        k, u = pm.k_reference, pm.u_reference_rel
    else:
        if frozen and not _identity(setup, p):
            correction = None if pm.k_frozen is None else (pm.k_frozen, pm.u_frozen_rel)
        if correction is None:
            nan = np.full(pm.n, np.nan)
            return nan, nan
        k, u = correction
    x = raw / k_used if idealise == "correction" else raw / k
    return x, np.sqrt(base ** 2 + u ** 2)


def mode_of(setup: Setup, p: int, scenario: str) -> str:
    return "self" if scenario in ("all_corrected", FROZEN) else setup.participants[p].report


def reports_as(setup: Setup, p: int, scenario: str) -> str:
    """What participant p reports in ``scenario``, as the summary says it: its :func:`mode_of`,
    except that a collimated instrument (k_A = 1) asked to correct itself has nothing to correct
    and reports its table raw."""
    mode = mode_of(setup, p, scenario)
    return "raw" if mode == "self" and _identity(setup, p) else mode


def realisation(setup: Setup, m: int, corrections: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]],
                scenarios: Sequence[str] = SCENARIOS + (FROZEN,)) -> dict[str, Any]:
    """Realisation m: per scenario the reported tables x (P, n) and stated u (P, n), and the
    per-variant metrics (V, 4) of the idealisations (:data:`METRICS`; d w.r.t. the weighted mean).
    ``corrections[(name, m)]``: the (k_self, u_rel) of the corrections of the participants that
    correct themselves (where a participant has none, the scenario is not compared in this
    realisation). The scenario :data:`FROZEN` uses the frozen factors instead (the check of that
    linearisation; no variants)."""
    d = draws(setup, m)
    check_draws(setup, d, m)
    raws = [raw_table(setup, d, p) for p in range(setup.P)]
    g_rel = shared_components(setup)
    out: dict[str, Any] = {"realisation": m}
    for scen in scenarios:
        modes = [mode_of(setup, p, scen) for p in range(setup.P)]
        corr = [_correction_of(setup, corrections, p, m, modes[p]) for p in range(setup.P)]
        frozen = scen == FROZEN
        xs, us = zip(*[reported(setup, p, raws[p][0], raws[p][1], modes[p], corr[p], frozen=frozen)
                       for p in range(setup.P)])
        x, urel = np.array(xs), np.array(us)
        out[scen] = {"x": x, "u_rel": urel}
        out[scen]["full"] = [modes[p] != "self" or (corr[p] is not None and not (frozen and not _identity(setup, p)))
                             for p in range(setup.P)]
        if not np.all(np.isfinite(x)) or scen == FROZEN:
            out[scen]["variants"] = None          # a participant without its correction here: not compared
            continue
        base = _metrics(setup, x, urel, g_rel)
        rows = [base]
        for p, key, _label in setup.variants(scen):
            raw_v, k_v = raw_table(setup, d, p, key) if key != "correction" else raws[p]
            xv, uv = reported(setup, p, raw_v, k_v, modes[p], corr[p], key)
            xx = x.copy()
            xx[p] = xv
            rows.append(_metrics(setup, xx, urel, g_rel))
        vp = [None] + [p for p, _, _ in setup.variants(scen)]
        # per variant, the metrics of the participant it idealises (baseline: every participant)
        out[scen]["baseline"] = rows[0]
        out[scen]["variants"] = np.array([rows[i + 1][vp[i + 1]] for i in range(len(rows) - 1)]).reshape(-1, len(METRICS))
    return out


def _identity(setup: Setup, p: int) -> bool:
    """A collimated (ideal) instrument: k_A = 1, its correction changes nothing
    (:func:`~roadgonio.intercomparison.study.corrects_nothing` of its instrument)."""
    return corrects_nothing(setup.participants[p].mm.instrument)


def _correction_of(setup: Setup, corrections, p: int, m: int, mode: str):
    if mode != "self":
        return None
    pm = setup.participants[p]
    if _identity(setup, p):
        return np.ones(pm.n), np.zeros(pm.n)      # nothing to correct
    return corrections.get((pm.name, m))


def _metrics(setup: Setup, x: np.ndarray, urel: np.ndarray, g_rel: np.ndarray) -> np.ndarray:
    """(P, 5) metrics of one realisation (:data:`METRICS`): the sum over cells of (x_i / r_true - 1)^2
    and the number of cells where |x_i - r_true| <= k u_i (E_n against the truth <= 1), the sum of
    (d_i / r_true)^2 and the number of |E_n| <= 1 against the weighted mean, the number of cells."""
    xt = x.T                                               # (n, P)
    ut = (urel * x).T
    V = st.covariance(ut, (g_rel * x[None]).transpose(0, 2, 1))
    sp = st.Spectral(xt, V)
    eq = st.equivalence_to(xt, V, st.weighted_mean(sp), setup.coverage_factor)
    t = setup.truth[:, None]
    err = xt - t
    return np.stack([np.sum((err / t) ** 2, axis=0), np.sum(np.abs(err) <= setup.coverage_factor * ut, axis=0),
                     np.sum((eq.d / t) ** 2, axis=0), np.sum(eq.compatible, axis=0),
                     np.full(setup.P, float(len(setup.truth)))], axis=1)
