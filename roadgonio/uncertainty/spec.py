"""Input distributions of the instrument's geometric errors (the SPEC of ``--sigma``): parsing and validation."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from roadgonio.errors import InputError
from roadgonio.fileio import read_toml

#: Input names of a SPEC, in the column order of the trial matrices.
INPUTS = ("alpha_deg", "eps_deg", "beta_deg", "tilt_x_deg", "tilt_y_deg", "source_distance_m",
          "detector_distance_m")
INPUT_HELP = {
    "alpha_deg": "observation elevation error (deg)",
    "eps_deg": "source polar angle error (deg)",
    "beta_deg": "source azimuth (beta) error (deg)",
    "tilt_x_deg": "sample tilt about x (observation azimuth axis; normal tilts sideways) (deg)",
    "tilt_y_deg": "sample tilt about y (normal tilts towards the detector) (deg)",
    "source_distance_m": "source distance error (m)",
    "detector_distance_m": "detector distance error (m)",
}
DISTRIBUTIONS = {"normal": "normal", "gauss": "normal", "gaussian": "normal",
                 "rect": "rect", "rectangular": "rect", "uniform": "rect"}
ILLUMINANCE = ("nominal", "measured")
CELL_SETS = ("standard", "all")
SPEC_HELP = (
    "SPEC is a comma-separated list KEY=SIGMA[:DIST] or the path of a TOML file with the same keys "
    "(KEY = SIGMA, KEY = \"SIGMA:DIST\" or KEY = {sigma = SIGMA, distribution = \"DIST\"}, at top level "
    "or in a [sigma] table). SIGMA is a standard deviation (>= 0) in the key's unit; DIST is normal "
    "(default; also gauss, gaussian) or rect (also rectangular, uniform: rectangular with that standard "
    "deviation, half-width SIGMA*sqrt(3)). Keys: "
    + ", ".join(INPUTS) + "; keys left out are 0. Example: "
    "alpha_deg=0.01,eps_deg=0.05:rect,beta_deg=0.1,tilt_x_deg=0.02,tilt_y_deg=0.02,"
    "source_distance_m=0.002,detector_distance_m=0.005")


# ----------------------------------------------------------------------------------------------
# SPEC
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SigmaSpec:
    """Standard deviations and distributions of the seven input errors (order :data:`INPUTS`)."""

    sigma: tuple[float, ...]
    distribution: tuple[str, ...]
    source: str = ""

    @property
    def sigmas(self) -> np.ndarray:
        return np.asarray(self.sigma, dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {k: {"sigma": s, "distribution": "rectangular" if d == "rect" else "normal"}
                for k, s, d in zip(INPUTS, self.sigma, self.distribution)}

    def draw(self, rng: np.random.Generator, m: int) -> np.ndarray:
        """m trials of the seven errors, shape (m, 7). Both a normal and a uniform variate are drawn
        for every input, so the stream does not depend on the distributions chosen."""
        z = rng.standard_normal((m, len(INPUTS)))
        u = rng.random((m, len(INPUTS)))
        rect = np.array([d == "rect" for d in self.distribution])
        x = np.where(rect[None, :], (2.0 * u - 1.0) * math.sqrt(3.0), z)
        return x * self.sigmas[None, :]


def _parse_entry(key: str, value: Any, *, path, field_prefix: str = "") -> tuple[float, str]:
    fld = f"{field_prefix}{key}"
    dist = "normal"
    if isinstance(value, Mapping):
        extra = sorted(set(value) - {"sigma", "distribution"})
        if extra or "sigma" not in value:
            raise InputError("expected {sigma = NUMBER, distribution = \"normal\"|\"rect\"}", path=path, field=fld)
        dist_text = value.get("distribution", "normal")
        value = value["sigma"]
        if not isinstance(dist_text, str):
            raise InputError(f"expected text (normal or rect), got {dist_text!r}", path=path, field=fld + ".distribution")
        if isinstance(value, bool) or not isinstance(value, (int, float)):     # a table holds numbers as numbers
            raise InputError(f"expected a number (standard deviation), got {value!r}", path=path, field=fld + ".sigma")
    elif isinstance(value, str):
        text, _, dist_text = value.partition(":")
        value = text.strip()
        dist_text = dist_text.strip() or "normal"
    else:
        dist_text = "normal"
    if isinstance(value, bool):
        raise InputError(f"expected a number (standard deviation), got {value!r}", path=path, field=fld)
    try:
        sigma = float(value)
    except (TypeError, ValueError):
        raise InputError(f"expected a number (standard deviation), got {value!r}", path=path, field=fld) from None
    if not math.isfinite(sigma):
        raise InputError(f"expected a finite standard deviation, got {value!r}", path=path, field=fld)
    if sigma < 0:
        raise InputError(f"a standard deviation must be >= 0, got {sigma:g}", path=path, field=fld)
    d = DISTRIBUTIONS.get(dist_text.lower())
    if d is None:
        raise InputError(f"unknown distribution {dist_text!r}; expected normal (gauss, gaussian) or rect "
                         "(rectangular, uniform)", path=path, field=fld)
    dist = d
    return sigma, dist


def _spec_from_mapping(d: Mapping[str, Any], *, path, field_prefix: str, source: str) -> SigmaSpec:
    unknown = sorted(set(d) - set(INPUTS))
    reflectance = [k for k in unknown if "reflectance" in k]
    if reflectance:
        # (user audit, session 39) a housing's paint is no input error here: say so, not "unknown key"
        raise InputError(f"{reflectance[0]}: the reflectance of a housing's parts has no input error in this "
                         f"Monte Carlo (it is taken as exact; docs/uncertainty.md, 'A housed instrument'); expected "
                         f"some of {', '.join(INPUTS)}", path=path, field=field_prefix + reflectance[0])
    if unknown:
        raise InputError(f"unknown key(s) {', '.join(unknown)}; expected some of {', '.join(INPUTS)}",
                         path=path, field=field_prefix + unknown[0])
    sig, dist = [], []
    for k in INPUTS:
        if k in d:
            s, t = _parse_entry(k, d[k], path=path, field_prefix=field_prefix)
        else:
            s, t = 0.0, "normal"
        sig.append(s)
        dist.append(t)
    return SigmaSpec(tuple(sig), tuple(dist), source=source)


def parse_sigma_spec(spec: str | Path | Mapping[str, Any], *, option: str = "sigma") -> SigmaSpec:
    """Parse a SPEC (see :data:`SPEC_HELP`): a string ``KEY=SIGMA[:DIST],...``, a TOML file path,
    or a mapping. Unknown keys, bad numbers, negative sigmas and unknown distributions raise
    :class:`InputError` naming the option or file and the key."""
    if isinstance(spec, Mapping):
        return _spec_from_mapping(spec, path=None, field_prefix=f"{option}.", source="mapping")
    text = str(spec).strip()
    p = Path(text)
    if text.lower().endswith(".toml") or (p.suffix and p.exists()):
        d = read_toml(p, "SPEC file", missing=f"no such SPEC file (given to {option})")
        if "sigma" in d and isinstance(d["sigma"], Mapping):
            if set(d) - {"sigma"}:
                raise InputError("expected only a [sigma] table", path=p, field=sorted(set(d) - {"sigma"})[0])
            return _spec_from_mapping(d["sigma"], path=p, field_prefix="sigma.", source=str(p))
        return _spec_from_mapping(d, path=p, field_prefix="", source=str(p))
    if not text:
        raise InputError(f"empty SPEC; {SPEC_HELP}", field=option)
    d: dict[str, str] = {}
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        key, eq, val = part.partition("=")
        key = key.strip()
        if not eq:
            raise InputError(f"expected KEY=SIGMA[:DIST], got {part!r} (keys: {', '.join(INPUTS)})", field=option)
        if key in d:
            raise InputError(f"key {key!r} given twice", field=option)
        d[key] = val.strip()
    try:
        return _spec_from_mapping(d, path=None, field_prefix=f"{option} ", source=text)
    except InputError as err:
        raise InputError(err.reason, field=err.field) from None




# ----------------------------------------------------------------------------------------------
# The SPEC against the geometry: up front, and every trial
# ----------------------------------------------------------------------------------------------

#: A normal error is checked up front out to this many standard deviations (a rectangular one to
#: its half-width sqrt(3) sigma); beyond it a trial is still checked when it is drawn.
CHECK_SIGMAS = 6.0


def extents(spec: SigmaSpec) -> np.ndarray:
    """The largest error of each input that the up-front check covers (0 for sigma = 0)."""
    return np.array([s * (math.sqrt(3.0) if d == "rect" else CHECK_SIGMAS)
                     for s, d in zip(spec.sigma, spec.distribution)])


#: Trials per chunk of :func:`geometry_problems` (4096 x 580 cells x 8 bytes = 19 MB an array).
GEOMETRY_CHUNK = 4096


def geometry_problems(mm, X: np.ndarray, *, aperture: bool = False) -> tuple[np.ndarray, list[str]]:
    """For trials X (m, 7) of a :class:`~roadgonio.uncertainty.measurement.MeasurementModel`: a mask
    of the trials whose perturbed geometry is not valid, and for each of them what is wrong."""
    X = np.atleast_2d(np.asarray(X, dtype=np.float64))
    inst = mm.instrument
    # the heights (z) of the detector and of the lowest source direction, in chunks of trials: the
    # full directions of 50,000 trials x 396 cells are 0.5 GB per component
    woz = np.empty(len(X))
    low = np.empty(len(X))
    low_cell = np.empty(len(X), dtype=np.int64)
    for a in range(0, len(X), GEOMETRY_CHUNK):
        wiz, woz[a:a + GEOMETRY_CHUNK] = mm.heights(X[a:a + GEOMETRY_CHUNK])
        low_cell[a:a + GEOMETRY_CHUNK] = np.argmin(wiz, axis=1)
        low[a:a + GEOMETRY_CHUNK] = np.take_along_axis(wiz, low_cell[a:a + GEOMETRY_CHUNK, None], axis=1)[:, 0]
    bad = np.zeros(len(X), dtype=bool)
    why = [""] * len(X)

    def flag(mask, text_of):
        for k in np.nonzero(mask & ~bad)[0]:
            why[k] = text_of(k)
        bad[:] = bad | mask

    alpha = mm.alpha0 + X[:, 0]
    flag((alpha <= 0.0) | (alpha >= 90.0), lambda k: f"the observation angle alpha = {alpha[k]:.4g} deg is not in (0, 90)")
    flag(woz <= 0.0, lambda k: "the detector is at or below the (tilted) sample's horizon")
    cells = mm.cells

    def src_text(k):
        j = int(low_cell[k])
        return (f"the source is at or below the (tilted) sample's horizon at tan eps = {cells.tan_eps[j]:g}, "
                f"beta = {cells.beta_deg[j]:g}")
    flag(low <= 0.0, src_text)
    ds = mm.ds0 + X[:, 5]
    flag(ds <= inst.source.radius_m, lambda k: f"the source {inst.source.length_key[:-2]} {ds[k]:.4g} m is not larger than its radius "
                                               f"({inst.source.radius_m:g} m)")
    dd = mm.dd0 + X[:, 6]
    flag(dd <= inst.detector.pupil_radius_m, lambda k: f"the detector distance {dd[k]:.4g} m is not larger than its "
                                                       f"pupil radius ({inst.detector.pupil_radius_m:g} m)")
    if aperture and bool(np.any(~bad)):
        from roadgonio.errors import GeometryError
        from roadgonio.instrument.enclosure import check_detector_view, check_sources
        from roadgonio.instrument.housing import Housing
        from roadgonio.instrument.optics import check_detector, check_source
        housing = Housing.of(inst)
        for k in np.nonzero(~bad)[0]:
            try:
                pert = inst.with_changes(observation={"alpha_deg": float(alpha[k])},
                                         source={inst.source.length_key: float(ds[k])}, detector={"distance_m": float(dd[k])})
                if pert.sample.mesh is None:
                    check_detector(pert)
                for t, b in zip(cells.tan_eps, cells.beta_deg):
                    check_source(pert, float(t), float(b))
                if housing is not None:
                    # the source's perturbed directions, as the surrogate's exact tables place it (user
                    # audit, session 37: a source pushed behind a baffle by eps_deg was refused after the
                    # computation, naming the instrument file's baffle and a cell of no table)
                    _, wr = mm.surrogate_coords(X[k:k + 1])
                    check_sources(pert, housing, mm.cells_of(wr[0]))
                    # ... and the detector's, inside the housing as built (session 39's review: a detector
                    # moved through the wall by detector_distance_m was computed, or refused mid-run)
                    check_detector_view(pert, housing)
            except (GeometryError, InputError) as err:
                bad[k] = True
                why[k] = str(getattr(err, "reason", err))
    return bad, why


def check_nominal_geometry(mm, *, aperture: bool) -> None:
    """The instrument of ``mm`` at its nominal geometry on ``mm``'s cells: the checks of
    :func:`geometry_problems` for no error at all, raised as the instrument's
    :class:`~roadgonio.errors.GeometryError` (its file, and the field where the check knows it)."""
    from roadgonio.errors import GeometryError
    from roadgonio.instrument.optics import check_detector, check_source
    inst = mm.instrument
    bad, why = geometry_problems(mm, np.zeros((1, len(INPUTS))), aperture=False)
    if bad[0]:
        raise GeometryError(f"the instrument's nominal geometry is not valid: {why[0]}", path=inst.path)
    if aperture:
        if inst.sample.mesh is None:
            check_detector(inst)
        for t, b in zip(mm.cells.tan_eps, mm.cells.beta_deg):
            check_source(inst, float(t), float(b))
        from roadgonio.instrument.housing import Housing
        housing = Housing.of(inst)
        if housing is not None:
            # the housing as built, at no error (user audit, session 44: a lid that blocks the nominal
            # source was blamed on the smallest sigma of the SPEC, which no sigma could satisfy)
            from roadgonio.instrument.enclosure import check_detector_view, check_sources
            check_detector_view(inst, housing)
            check_sources(inst, housing, [(float(t), float(b)) for t, b in zip(mm.cells.tan_eps, mm.cells.beta_deg)])


def check_spec_geometry(spec: SigmaSpec, mm, *, aperture: bool, option: str = "sigma") -> None:
    """Validate a SPEC against the instrument up front: every input alone at +- its checked extent
    (:data:`CHECK_SIGMAS` sigma, or the rectangular half-width) and the inputs together at that
    distance in every sign combination must keep the geometry valid (detector and source above
    the tilted horizon, distances larger than the apertures, the footprint on the sample and the
    source above the plane with the aperture effect). Raises :class:`InputError` naming the key;
    first the nominal geometry (no error at all) itself, whose problem is the instrument's and not
    the SPEC's: the instrument's own :class:`~roadgonio.errors.GeometryError` naming its file and
    field (an instrument whose footprint leaves the sample was reported as a sigma to make smaller,
    which no sigma could satisfy)."""
    check_nominal_geometry(mm, aperture=aperture)
    ext = extents(spec)
    active = [i for i in range(len(INPUTS)) if ext[i] > 0]
    if not active:
        return
    trials, who = [], []
    for i in active:
        for sign in (-1.0, 1.0):
            x = np.zeros(len(INPUTS))
            x[i] = sign * ext[i]
            trials.append(x)
            who.append([i])
    if len(active) > 1:
        k = len(active)
        for code in range(2 ** k):
            x = np.zeros(len(INPUTS))
            for b, i in enumerate(active):
                x[i] = (1.0 if code >> b & 1 else -1.0) * ext[i] / math.sqrt(k)
            trials.append(x)
            who.append(active)
    X = np.array(trials)
    bad, why = geometry_problems(mm, X, aperture=False)
    if aperture:
        # the aperture case rebuilds the instrument per trial: check the single-input extremes
        single = np.array([len(w) == 1 for w in who]) & ~bad
        b2, w2 = geometry_problems(mm, X[single], aperture=True)
        idx = np.nonzero(single)[0]
        for j, k in enumerate(idx):
            if b2[j]:
                bad[k], why[k] = True, w2[j]
    if np.any(bad):
        k = int(np.nonzero(bad)[0][0])
        keys = [INPUTS[i] for i in who[k]]
        what = (f"{keys[0]} = {spec.sigma[who[k][0]]:g} ({spec.distribution[who[k][0]]})" if len(keys) == 1
                else "the errors together (" + ", ".join(f"{INPUTS[i]} = {spec.sigma[i]:g}" for i in who[k]) + ")")
        field = f"{option} {keys[0]}" if len(keys) == 1 else option
        raise InputError(f"sigma {what} takes the geometry out of validity within {CHECK_SIGMAS:g} standard "
                         f"deviations ({why[k]}); expected smaller standard deviations", field=field)


def check_trials(spec: SigmaSpec, mm, X: np.ndarray, *, first_index: int = 0, option: str = "sigma") -> None:
    """Every drawn trial must have a valid geometry (the up-front check covers 6 sigma; a trial
    beyond that is still caught here, never turned into a NaN or a silent zero)."""
    bad, why = geometry_problems(mm, X)
    if np.any(bad):
        k = int(np.nonzero(bad)[0][0])
        with np.errstate(divide="ignore", invalid="ignore"):
            zs = np.where(spec.sigmas > 0, np.abs(X[k]) / spec.sigmas, 0.0)
        i = int(np.argmax(zs))
        raise InputError(f"trial {first_index + k + 1} draws {INPUTS[i]} = {X[k, i]:+.4g} ({zs[i]:.1f} sigma), "
                         f"where {why[k]}; {int(bad.sum())} of {len(X)} trials of this batch are invalid: expected "
                         "standard deviations that keep the geometry valid", field=f"{option} {INPUTS[i]}")
