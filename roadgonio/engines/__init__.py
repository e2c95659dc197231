"""The aperture-effect factor k_A (paper eq. 2-3; docs/conventions.md section 5) and its backends.

    k_A(eps, beta) = ( S[f_road] / S[f_lambert] ) / ( f_road(nominal) / f_lambert )

S[f] is the detector signal of the real instrument for a sample with BRDF f (eq. 3). The
denominator is the ideal point geometry, always computed in float64 numpy
(:func:`~roadgonio.engines.result.ideal_ratio`), never rendered.

This room owns: what a backend returns (:mod:`.result`), which backends exist and what they can do
(:mod:`.registry`: the one registry), which cells to compute (:mod:`.cells`), the calibration modes
(:mod:`.calibration`), running a table with journal and resume into one ``xarray.Dataset``
(:mod:`.runner`), the Dask plumbing every room uses (:mod:`.cluster`), validation against float64
references (:mod:`.validate`), the per-cell preamble of every backend (:mod:`.cellcheck`), the
product Gauss rules over the discs (:mod:`.rules`), the backends: :mod:`.quadrature`,
:mod:`.montecarlo`, :mod:`.reference`, :mod:`.meshmc` and :mod:`roadgonio.engines.mitsuba` (the only
subpackage that imports mitsuba or drjit), and the correction's forward model over fixed ray
bundles (:mod:`.bundle`). :mod:`.strayref` is a test oracle: the independent float64 check of the
stray light, written apart from the Mitsuba backend; production code never imports it. Modules of this room import from :mod:`.result` and :mod:`.registry`,
never from this package's ``__init__``.
"""
from roadgonio.engines.cells import full_grid_cells  # noqa: F401
from roadgonio.engines.registry import BACKENDS, PRESETS, backend_info, make_backend  # noqa: F401
from roadgonio.engines.result import (CellByCellBackend, CellResult, KaBackend, ideal_ratio,  # noqa: F401
                                      ideal_ratios, ratio_se)
