"""Geometric feasibility of a design point, with the reason when it is impossible.

A design point is kept in the results whatever happens; when the instrument cannot measure the
requested cells it is marked ``geometry_ok = False`` with a one-line reason. The checks, in order
(the first that fails gives the reason):

1. ``instrument``: the instrument file is valid (e.g. a source radius smaller than its distance);
2. ``footprint``: the detector looks down at the sample and its footprint stays on a rectangular
   sample (:func:`roadgonio.instrument.optics.check_detector`; for a mesh sample the Mitsuba
   backend checks the hits at render time);
3. ``horizon``: the whole source disc is above the sample plane at every requested cell
   (:func:`roadgonio.instrument.optics.check_source`);
4. ``line_of_sight``: the source disc does not block the detector's view of the footprint at any
   requested cell (:func:`blocked_cells`: the exact test of every backend,
   :func:`roadgonio.instrument.optics.source_blocks_view`, so a point the pre-filter keeps is not
   refused by the backend for this reason, and the reverse). This matters for sources between the
   detector and the sample (beta near 180 deg at grazing incidence).
5. ``housing``: a ``[housing]`` holds the detector's view and every requested cell's source disc
   (:func:`roadgonio.instrument.enclosure.check_detector_view`, :func:`~roadgonio.instrument.enclosure.check_sources`:
   no baffle in the line of sight, no source disc through a wall, the lid or a baffle);
6. ``backend`` (on the worker): whatever the backend itself refuses (render-time ray hits of an
   XML scene or a mesh, an instrument feature the backend cannot model, ...).

The detector's own housing (around its pupil) is not part of the instrument description, so light
it might block on the way from the source to the sample is not checked (an instrument's [housing]
is: check 5).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

from roadgonio.errors import GeometryError, InputError
from roadgonio.instrument.config import Instrument
from roadgonio.instrument import optics


@dataclass(frozen=True)
class Feasibility:
    """Geometry verdict of one design point."""

    ok: bool
    kind: str = ""                  # "" | instrument | footprint | horizon | line_of_sight | housing | backend
    reason: str = ""
    footprint: tuple[float, float, float, float] | None = None   # x_min, x_max, y_min, y_max (m; x along delta)
    field: str = ""                 # kind "instrument": the instrument key the refusal names

    @property
    def footprint_length_m(self) -> float:
        return math.nan if self.footprint is None else self.footprint[1] - self.footprint[0]


def _cells_text(cells: Sequence[tuple[float, float]], n_max: int = 3) -> str:
    """'tan eps 12, beta 0; tan eps 12, beta 2' or '100 cells: tan eps 10 ... 12, beta 0 ... 180'."""
    if len(cells) <= n_max:
        return "; ".join(f"tan eps {t:g}, beta {b:g}" for t, b in cells)
    t = [c[0] for c in cells]
    b = [c[1] for c in cells]
    return f"{len(cells)} cells: tan eps {min(t):g} ... {max(t):g}, beta {min(b):g} ... {max(b):g}"


def blocked_cells(instrument: Instrument, cells: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """Cells at which the source disc blocks the detector's view: the test every backend applies
    (:func:`roadgonio.instrument.optics.source_blocks_view`), so the pre-filter and the backends
    agree cell by cell."""
    if not cells:
        return []
    return [c for c, b in zip(cells, optics.source_blocks_view(instrument, cells)) if b]


def check_geometry(instrument: Instrument, cells: Sequence[tuple[float, float]]) -> Feasibility:
    """Checks 2-4 of the module docstring for ``instrument`` at ``cells``."""
    try:
        if instrument.sample.mesh is None:
            fp = optics.check_detector(instrument)
        else:
            x, y = optics.footprint_along_azimuth(instrument)
            fp = (float(x.min()), float(x.max()), float(y.min()), float(y.max()))
    except GeometryError as err:
        fp = None
        try:
            x, y = optics.footprint_along_azimuth(instrument)
            fp = (float(x.min()), float(x.max()), float(y.min()), float(y.max()))
        except GeometryError:
            pass
        return Feasibility(False, "footprint", str(err), fp)
    below = []
    for t, b in cells:
        try:
            optics.check_source(instrument, t, b)
        except GeometryError:
            below.append((t, b))
    if below:
        src = instrument.source
        return Feasibility(False, "horizon", f"the source disc (radius {src.radius_m:g} m, {src.length_key[:-2]} {src.length_m:g} m) "
                                            f"reaches below the sample plane at {_cells_text(below)}", fp)
    blocked = blocked_cells(instrument, cells)
    if blocked:
        src, det = instrument.source, instrument.detector
        return Feasibility(False, "line_of_sight",
                           f"the source disc (radius {src.radius_m:g} m, {src.length_key[:-2]} {src.length_m:g} m) blocks the detector's "
                           f"view of the sample (pupil {det.pupil_radius_m:g} m at {det.distance_m:g} m) at "
                           f"{_cells_text(blocked)}", fp)
    from roadgonio.instrument.enclosure import check_detector_view, check_sources
    from roadgonio.instrument.housing import Housing
    housing = Housing.of(instrument)
    if housing is not None:
        try:
            check_detector_view(instrument, housing)
            check_sources(instrument, housing, cells)
        except GeometryError as err:
            return Feasibility(False, "housing", str(err), fp)
        except InputError as err:      # the point's [housing] does not hold the detector's view
            return Feasibility(False, "housing", f"{err.field}: {err.reason}" if err.field else err.reason, fp)
    return Feasibility(True, footprint=fp)


def check_point(base: Instrument, point: Mapping[str, float], cells: Sequence[tuple[float, float]]
                ) -> tuple[Instrument | None, Feasibility]:
    """Build the instrument of a grid point and check it; never raises for a bad point."""
    from roadgonio.design.grid import build_instrument
    try:
        inst = build_instrument(base, point)
    except InputError as err:
        reason = err.reason if err.field is None else f"{err.field}: {err.reason}"
        return None, Feasibility(False, "instrument", reason, field=err.field or "")
    return inst, check_geometry(inst, cells)
