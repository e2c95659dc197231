"""roadgonio: ray-tracing simulator of road-surface goniophotometers.

The Python API (for notebooks and scripts; :mod:`roadgonio.api`)::

    import roadgonio as rg
    ds = rg.ka_table("portable", "R3", backend="quadrature", accuracy="fast")   # xarray.Dataset
    r3 = rg.read_table("R3")                                                   # xarray.DataArray of r

:func:`ka_table`, :func:`ka_cell`, :func:`read_table`, :func:`write_table`, :func:`fit`,
:func:`correct`, :func:`uncertainty` and :func:`design` (the ``roadgonio.uncertainty`` and
``roadgonio.design`` rooms are callable: calling them runs :func:`roadgonio.api.uncertainty` and
:func:`roadgonio.api.design`).

The physics conventions (angles, BRDF model, instrument, k_A, calibration) are those of
``docs/conventions.md``, from Bernasconi et al., "Geometrical errors and their uncertainty in
goniophotometers: an application to road surface photometry". Importing this package imports
nothing heavy and never mitsuba or drjit: only :mod:`roadgonio.engines.mitsuba` does, and only
when the caller asks for a variant. The rooms: :mod:`roadgonio.surface`,
:mod:`roadgonio.instrument`, :mod:`roadgonio.engines`, :mod:`roadgonio.uncertainty`,
:mod:`roadgonio.correction`, :mod:`roadgonio.design`, :mod:`roadgonio.road` (README, Architecture).
"""
from roadgonio._version import __version__

__all__ = ["ka_table", "ka_cell", "read_table", "write_table", "fit", "correct", "uncertainty", "design",
           "__version__"]

_API = ("ka_table", "ka_cell", "read_table", "write_table", "fit", "correct")


def __getattr__(name: str):
    # lazy: the API (and xarray, numpy...) load on first use, so `import roadgonio` stays light
    if name in _API:
        from roadgonio import api
        return getattr(api, name)
    if name in ("uncertainty", "design"):   # the rooms, callable as the API functions
        import importlib
        return importlib.import_module(f"roadgonio.{name}")
    raise AttributeError(f"module 'roadgonio' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
