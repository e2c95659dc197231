"""What every k_A backend checks at a cell before (and after) it integrates, written once.

Before: the whole source disc above the sample plane (:func:`roadgonio.instrument.optics.check_source_cells`);
for a backend that does not model a source beam limit, no beam limit that clips the light reaching the
footprint (:func:`roadgonio.instrument.optics.beam_clips_footprint`); the source disc out of the
detector's view (:func:`roadgonio.instrument.optics.check_line_of_sight`); and a positive, finite model
value at the nominal geometry, since k_A = measured / nominal (paper eq. 2): :func:`check_cell` returns
that nominal value, pi f_road(nominal) (:func:`roadgonio.engines.ideal_ratio`), the denominator of k_A.

After: a cell at which no detected ray receives light has no k_A (:func:`no_light`).

Errors, not wrong numbers: :class:`~roadgonio.errors.GeometryError` (the geometry cannot be measured)
or :class:`~roadgonio.errors.BackendError` (this backend cannot compute it), naming the cell.

A command asked for a list of cells checks them all with :func:`check_requested` before it computes or
writes anything: a cell-by-cell backend checks each cell only when it reaches it, so a refused cell
late in the list failed the run after the cells before it were computed and journalled (user audit,
session 24: ``ka --backend reference --cells 12:0,0:0`` on a narrow lobe).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from roadgonio.errors import BackendError, GeometryError, InputError, count
from roadgonio.instrument import optics
from roadgonio.instrument.config import BEAM_KEYS, Instrument
from roadgonio.surface.model import RoadModel
from roadgonio.engines.cells import cells_text
from roadgonio.engines.result import ideal_ratio, ideal_ratios


def check_beam(instrument: Instrument, cells: Sequence[tuple[float, float]], backend: str) -> None:
    """For a backend that does not model a source beam limit: refuse the first cell whose beam limit
    clips the light reaching the footprint (:func:`roadgonio.instrument.optics.beam_clips_cells`)."""
    clips = np.flatnonzero(optics.beam_clips_cells(instrument, cells))
    if len(clips):
        t, b = cells[clips[0]]
        raise BackendError(f"the source beam limit ({instrument.source.beam_half_angle_deg:g} deg) clips the "
                           f"light reaching the detector footprint at tan eps = {t:g}, beta = {b:g}; the "
                           f"{backend} backend does not model beam limits: use the quadrature backend")


def _check_geometry(instrument: Instrument, cells: Sequence[tuple[float, float]], models_beam: bool,
                    backend: str) -> None:
    optics.check_source_cells(instrument, cells)      # names the first bad cell and how many more
    if not models_beam:
        check_beam(instrument, cells, backend)
    optics.check_line_of_sight(instrument, cells)


def check_nominal(nominal: float, tan_eps: float, beta_deg: float) -> None:
    """k_A = measured / nominal needs a positive, finite model value at the nominal geometry
    (``nominal`` = pi f_road(nominal), :func:`roadgonio.engines.ideal_ratio`)."""
    if not (nominal > 0.0 and math.isfinite(nominal)):
        raise GeometryError(f"the model is {nominal / math.pi:g} at the nominal geometry (tan eps = {tan_eps:g}, "
                            f"beta = {beta_deg:g}): k_A = measured/nominal is undefined there")


def check_cell(instrument: Instrument, model: RoadModel, tan_eps: float, beta_deg: float, *,
               models_beam: bool = True, backend: str = "this") -> float:
    """The checks of the module docstring at one cell; returns pi f_road(nominal) (float64).
    ``models_beam``: the backend integrates a source beam limit (else a clipping one is refused)."""
    _check_geometry(instrument, [(tan_eps, beta_deg)], models_beam, backend)
    nominal = ideal_ratio(model, instrument, tan_eps, beta_deg)
    check_nominal(nominal, tan_eps, beta_deg)
    return nominal


def check_cells(instrument: Instrument, model: RoadModel, cells: Sequence[tuple[float, float]], *,
                models_beam: bool = True, backend: str = "this") -> np.ndarray:
    """:func:`check_cell` for a list of cells at once (the line of sight and the nominal values
    vectorised): raises for the first cell that fails, the horizon and beam first, then the line of
    sight, then the nominal value; returns pi f_road(nominal) per cell
    (:func:`roadgonio.engines.ideal_ratios`)."""
    cells = [(float(t), float(b)) for t, b in cells]
    if not cells:
        return np.zeros(0)
    _check_geometry(instrument, cells, models_beam, backend)
    nominal = ideal_ratios(model, instrument, cells)
    for (t, b), v in zip(cells, nominal):
        check_nominal(float(v), t, b)
    return nominal


def beam_key(instrument: Instrument) -> str | None:
    """The instrument's key that narrows its source's beam (an angular profile or a hard cone), as
    ``source.<key>``, or None for a disc that emits into the whole hemisphere."""
    src = instrument.source
    for key in BEAM_KEYS + ("beam_half_angle_deg",):
        if getattr(src, key, None) is not None:
            return f"source.{key}"
    return None


def unsampled_beam(instrument: Instrument, tan_eps: float, beta_deg: float, backend: str) -> GeometryError | None:
    """The error of a cell where no sample met the source's light although its beam does light the
    footprint: a beam's axis points at the sample centre, so a narrow beam lights the footprint along
    it, only in directions too few for ``backend`` to meet (user audit, session 42: sigma 1e-4 deg was
    said to "miss the detector footprint", and the Mitsuba backend asked whether a part of the scene
    shaded it, in a scene without parts). None for a source without a beam key."""
    key = beam_key(instrument)
    if key is None:
        return None
    value = getattr(instrument.source, key.split(".")[1])
    return GeometryError(f"no sample of the {backend} backend met the source's light at tan eps = {tan_eps:g}, beta = "
                         f"{beta_deg:g}: the beam ({key} = {value}) is too narrow for it to find; it does light the "
                         "footprint along its axis, so k_A is near its collimated limit there (docs/beam.md): "
                         "widen the beam, or leave the key out for the uniform disc",
                         path=instrument.path, field=key)


def no_light(tan_eps: float, beta_deg: float, why: str = "") -> GeometryError:
    """The error of a cell at which no detected ray receives light from the source (k_A undefined);
    ``why`` a parenthesised reason, e.g. ``"(the source beam misses the detector footprint)"``."""
    return GeometryError(f"no detected ray receives light from the source at tan eps = {tan_eps:g}, beta = "
                         f"{beta_deg:g}{' ' + why if why else ''}: k_A is undefined")


def refusals(instrument: Instrument, models: Sequence[RoadModel], cells: Sequence[tuple[float, float]], *,
             models_beam: bool = True) -> dict[str, np.ndarray]:
    """Per reason, which of ``cells`` :func:`check_cells` refuses past the horizon: ``"line of sight"``
    (the source disc in the detector's view), ``"beam"`` (a clipping beam limit the backend does not
    model), ``"nominal value"`` (a model value at the nominal geometry that is not positive and
    finite, for some model of ``models``); boolean masks in the cells' order."""
    tb = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    out = {"line of sight": optics.source_blocks_view(instrument, tb),
           "beam": optics.beam_clips_cells(instrument, cells) if not models_beam else np.zeros(len(cells), dtype=bool),
           "nominal value": np.zeros(len(cells), dtype=bool)}
    for m in models:
        v = ideal_ratios(m, instrument, cells)
        out["nominal value"] |= ~(np.isfinite(v) & (v > 0.0))
    return out


#: How an error names each reason of :func:`refusals`.
REFUSAL_TEXT = {"line of sight": "where the source disc is in the detector's view",
                "beam": "where a beam limit this backend does not model clips the source",
                "nominal value": "where the model is not positive at the nominal geometry"}


def refused_cells(instrument: Instrument, models: Sequence[RoadModel], cells: Sequence[tuple[float, float]], *,
                  models_beam: bool = True) -> list[tuple[float, float]]:
    """The cells of ``cells`` that :func:`check_cells` refuses for some model of ``models`` past the
    horizon (:func:`refusals`, any reason), in order."""
    return _refused(cells, refusals(instrument, models, cells, models_beam=models_beam))


def _refused(cells: Sequence[tuple[float, float]], why: dict[str, np.ndarray]) -> list[tuple[float, float]]:
    """The cells that some reason of ``why`` (:func:`refusals`) refuses, in order."""
    return [cells[i] for i in np.flatnonzero(np.logical_or.reduce(list(why.values())))]


def _checked_models(backend, model: RoadModel) -> list[RoadModel]:
    """The models whose nominal values ``backend`` divides by: the sample's, and under a
    ``reference`` calibration the reference's too; none when the reference is the sample itself and
    nothing is computed (k_A = 1 by definition, :class:`~roadgonio.engines.calibration.CalibratedBackend`)."""
    from roadgonio.engines.calibration import CalibratedBackend
    if not isinstance(backend, CalibratedBackend) or backend.mode != "reference":
        return [model]
    if backend.identical:
        return [model] if getattr(backend.inner, "stray_light", False) else []
    return [model, backend.reference_model]


#: How many refused cells the message of :func:`check_requested` lists.
LISTED = 6


def check_requested(backend, instrument: Instrument, model: RoadModel, cells: Sequence[tuple[float, float]], *,
                    field: str = "cells") -> None:
    """Check every cell a command asked ``backend`` for, before anything is computed or written: the
    horizon (:func:`roadgonio.instrument.optics.check_source_cells`, a GeometryError naming the
    instrument's key), then what the backend refuses at a cell (:func:`check_cells`, for each model
    it divides by) as one :class:`InputError` naming ``field`` (the argument that chose the cells),
    the refused cells in ``T:B`` form, the first refusal's reason and what was expected. Whether
    the backend models a beam limit (``models_beam`` of :func:`check_cells`) is its registry entry's
    ``beam_clipping`` (a backend the registry does not know is taken to model it)."""
    from roadgonio.engines.registry import BACKENDS
    info = BACKENDS.get(getattr(backend, "name", None))
    models_beam = info.beam_clipping if info is not None else True
    cells = [(float(t), float(b)) for t, b in cells]
    if not cells:
        return
    optics.check_source_cells(instrument, cells)
    models = _checked_models(backend, model)
    if not models:
        return
    name = getattr(backend, "name", "this")
    try:
        for m in models:
            check_cells(instrument, m, cells, models_beam=models_beam, backend=name)
    except (GeometryError, BackendError) as err:
        reason = getattr(err, "reason", None) or str(err)
        why = refusals(instrument, models, cells, models_beam=models_beam)
        bad = _refused(cells, why)
        if not bad:
            raise InputError(f"the {name} backend cannot compute a cell asked: {reason}", field=field) from None
        listed = cells_text(bad, LISTED)
        which = f"cell {listed}" if len(bad) == 1 else f"cells {listed}"
        if len(cells) > 1:
            which += f" ({len(bad)} of the {count(len(cells), 'cell')} asked)"
        kinds = [(int(m.sum()), REFUSAL_TEXT[k]) for k, m in why.items() if m.any()]
        if len(kinds) > 1:
            # the cells are refused for different reasons: count each, and quote the first refusal as
            # such (user audit: 536 cells whose model is 0 were given the reason of the one cell whose
            # source disc blocks the view)
            which += ", " + " and ".join(f"{n} {text}" for n, text in kinds) + "; the first checked"
        raise InputError(f"the {name} backend cannot compute {which}: {reason}; expected only cells it can compute: "
                         f"leave {'it' if len(bad) == 1 else 'them'} out (nothing was computed)", field=field) from None
