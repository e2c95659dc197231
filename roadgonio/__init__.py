"""roadgonio: ray-tracing simulator of road-surface goniophotometers.

The Python API (:mod:`roadgonio.api`, one function per command)::

    import roadgonio as rg
    ds = rg.ka_table("portable", "R3", backend="quadrature", accuracy="fast")   # xarray.Dataset
    r3 = rg.read_table("R3")                                                   # xarray.DataArray of r

The physics conventions (angles, BRDF model, instrument, k_A, calibration) are those of
``docs/conventions.md``, from Bernasconi et al., "Geometrical errors and their uncertainty in
goniophotometers: an application to road surface photometry". Importing this package imports
nothing heavy and never mitsuba or drjit: only :mod:`roadgonio.engines.mitsuba` does, and only
when the caller asks for a variant. The rooms, in import order (docs/architecture.md): the base
modules, :mod:`roadgonio.surface`, :mod:`roadgonio.instrument`, :mod:`roadgonio.engines`,
:mod:`roadgonio.uncertainty`, :mod:`roadgonio.correction`, :mod:`roadgonio.design`,
:mod:`roadgonio.road`, :mod:`roadgonio.intercomparison`, then :mod:`roadgonio.api` and
:mod:`roadgonio.cli`.
"""
from roadgonio._version import __version__
from roadgonio._checkout import bind as _bind

# the data subpackages of this checkout, not of the one an editable install points at (_checkout)
for _name in ("scenes", "docs", "studies"):
    _bind(f"{__name__}.{_name}")
del _name

__all__ = ["AUTO", "list_tables", "table_info", "read_table", "read_ka_table", "write_table", "fit", "ka_table", "ka_cell", "render",
           "validate", "estimate_uncertainty", "correct", "design_study", "second_aperture", "intercompare",
           "road_metrics", "compare_tables", "classify_table", "__version__"]
_API = frozenset(__all__) - {"__version__"}


def __getattr__(name: str):
    # lazy: the API (and xarray, numpy...) load on first use, so `import roadgonio` stays light
    if name in _API:
        from roadgonio import api
        return getattr(api, name)
    raise AttributeError(f"module 'roadgonio' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
