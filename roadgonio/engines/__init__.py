"""The aperture-effect factor k_A (paper eq. 2-3; docs/conventions.md section 5) and its backends.

    k_A(eps, beta) = ( S[f_road] / S[f_lambert] ) / ( f_road(nominal) / f_lambert )

S[f] is the detector signal of the real instrument for a sample with BRDF f (eq. 3). The
denominator is the ideal point geometry, always computed here in float64 numpy
(:func:`ideal_ratio`), never rendered.

A backend computes, for a list of cells (tan eps, beta), the ratio S[f_road]/S[f_lambert] and
turns it into :class:`CellResult` objects. Backends register themselves in :data:`BACKENDS` (name ->
factory ``factory(instrument, model, **settings) -> KaBackend``); the Mitsuba backend lives in
:mod:`roadgonio.engines.mitsuba` (the only subpackage that imports mitsuba), the quadrature backend in
:mod:`roadgonio.engines.quadrature`.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel


@dataclass(frozen=True)
class CellResult:
    """k_A at one cell with its precision; each field has one meaning.

    ``se`` is a standard error (Monte Carlo backends; NaN for a deterministic backend) and
    ``error_bound`` a deterministic bound on |k_A - true k_A| (quadrature; NaN for Monte Carlo).
    ``converged`` is False when the backend stopped (sample or evaluation cap) before reaching its
    target; such a value must never be reported as agreeing with anything.

    Stray light (issue 18): ``k_a`` is everything the scene does; ``k_a_direct`` the k_A of the
    light that reaches the footprint straight from the source alone, and ``stray_fraction`` =
    1 - S_direct[f] / S_total[f] of the road sample, each with its standard error (``k_a_direct_se``,
    ``stray_fraction_se``). A backend that traces no stray light leaves them out: then
    ``k_a_direct`` is ``k_a`` (with ``se``) and the stray fraction is 0 exactly.
    """

    tan_eps: float
    beta_deg: float
    k_a: float
    se: float             # standard error of k_a (Monte Carlo); NaN if deterministic
    samples: int          # MC samples, or integrand evaluations for quadrature
    seconds: float
    extra: dict[str, Any] | None = None
    error_bound: float = math.nan   # deterministic error bound of k_a; NaN for Monte Carlo
    converged: bool = True
    k_a_direct: float | None = None          # None: no stray light traced, = k_a
    k_a_direct_se: float | None = None       # None: = se
    stray_fraction: float | None = None      # None: 0 (no stray light traced)
    stray_fraction_se: float | None = None   # None: 0

    def __post_init__(self):
        # JSON (journal, outputs) carries NaN as null: read it back as NaN
        for name in ("se", "error_bound"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, math.nan)
        for name, default in (("k_a_direct", self.k_a), ("k_a_direct_se", self.se), ("stray_fraction", 0.0),
                              ("stray_fraction_se", 0.0)):
            if getattr(self, name) is None:
                object.__setattr__(self, name, float(default))

    @property
    def deterministic(self) -> bool:
        """True when the precision is an error bound (quadrature), False for a standard error."""
        return not math.isfinite(self.se) and math.isfinite(self.error_bound)

    def standard_uncertainty(self) -> float:
        """The standard uncertainty of k_a for an uncertainty budget: the standard error, or for a
        deterministic bound b the rectangular-distribution value b / sqrt(3) (GUM, JCGM 100 4.3.7)."""
        if math.isfinite(self.se):
            return float(self.se)
        return float(self.error_bound) / math.sqrt(3.0)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if d["extra"] is None:
            del d["extra"]
        return d


class KaBackend(Protocol):
    """What a k_A backend provides."""

    name: str

    def settings(self) -> dict[str, Any]:
        """Settings for provenance (sample counts, tolerances, variant, seed...)."""

    def compute(self, cells: Sequence[tuple[float, float]],
                on_cell: Callable[[CellResult], None] | None = None) -> list[CellResult]:
        """k_A for each (tan eps, beta deg) cell; calls ``on_cell`` as each cell finishes."""


class CellByCellBackend:
    """Base of the backends that compute one cell at a time: subclasses define
    ``compute_cell(tan_eps, beta_deg) -> CellResult``; :meth:`compute` runs the cells in order and
    reports each as it finishes (so the table runner can journal it)."""

    def compute(self, cells: Sequence[tuple[float, float]],
                on_cell: Callable[[CellResult], None] | None = None) -> list[CellResult]:
        out = []
        for tan_eps, beta_deg in cells:
            res = self.compute_cell(float(tan_eps), float(beta_deg))
            out.append(res)
            if on_cell is not None:
                on_cell(res)
        return out


def ideal_ratio(model: RoadModel, instrument: Instrument, tan_eps: float, beta_deg: float) -> float:
    """f_road(nominal) / f_lambert = pi f_road(w_i(eps, beta), w_o(alpha, delta)), float64."""
    wi = instrument.w_i(tan_eps, beta_deg)
    wo = instrument.w_o()
    return float(math.pi * model.brdf(wi, wo))


def ideal_ratios(model: RoadModel, instrument: Instrument, cells: Sequence[tuple[float, float]]) -> np.ndarray:
    """:func:`ideal_ratio` of many cells at once (float64 array, one value per cell)."""
    from roadgonio.geometry import eps_from_tan, w_source
    c = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    wi = w_source(eps_from_tan(c[:, 0]), c[:, 1], instrument.observation.delta_deg)
    return math.pi * model.brdf(wi, instrument.w_o()[None, :])


#: name -> "module:function" of the backend factories (imported lazily).
BACKENDS: dict[str, str] = {
    "mitsuba": "roadgonio.engines.mitsuba.backend:make_backend",
    "quadrature": "roadgonio.engines.quadrature:make_backend",
    "numpy-mc": "roadgonio.engines.montecarlo:make_backend",
    "reference": "roadgonio.engines.reference:make_backend",
    "numpy-mc-mesh": "roadgonio.engines.meshmc:make_backend",
}


def make_backend(name: str, instrument: Instrument, model: RoadModel, *, accuracy: str | None = None,
                 **settings) -> KaBackend:
    """Create a backend by name (lazy import, so numpy-only runs never import mitsuba).

    ``accuracy`` (``"fast"``, ``"default"``, ``"precise"``) applies the preset of
    :mod:`roadgonio.engines.accuracy` for this backend; explicit ``settings`` override it.
    The backend returns k_A in the instrument's ``[calibration]`` mode
    (:mod:`roadgonio.engines.calibration`; Lambert: the backend itself).
    """
    import importlib

    from roadgonio.errors import InputError
    if name not in BACKENDS:
        raise InputError(f"unknown backend {name!r}; expected one of {', '.join(BACKENDS)}", field="--backend")
    if accuracy is not None:
        from roadgonio.engines.accuracy import preset
        settings = {**preset(accuracy, name), **settings}
    mod_name, func = BACKENDS[name].split(":")
    try:
        mod = importlib.import_module(mod_name)
    except ModuleNotFoundError as err:
        if err.name and err.name.startswith("roadgonio"):
            raise InputError(f"backend {name!r} is not available in this version", field="--backend") from None
        raise
    factory = getattr(mod, func)
    from roadgonio.engines.calibration import calibrated   # the instrument's [calibration] mode (DESIGN 5)
    return calibrated(lambda inst, m: factory(inst, m, **settings), instrument, model)


def full_grid_cells() -> list[tuple[float, float]]:
    """All 580 (tan eps, beta) cells of the standard grid, row by row."""
    from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
    return [(float(t), float(b)) for t in TAN_EPS_GRID for b in BETA_GRID_DEG]


def ratio_se(road: np.ndarray, lam: np.ndarray) -> tuple[float, float]:
    """Ratio of means <road>/<lam> of paired per-batch (or per-pixel) values and its standard error
    by the delta method, float64."""
    road = np.asarray(road, dtype=np.float64).ravel()
    lam = np.asarray(lam, dtype=np.float64).ravel()
    n = road.size
    mr, ml = road.mean(), lam.mean()
    ratio = mr / ml
    if n < 2:
        return float(ratio), float("inf")
    resid = road - ratio * lam
    se = math.sqrt(np.sum(resid * resid) / (n - 1) / n) / abs(ml)
    return float(ratio), float(se)
