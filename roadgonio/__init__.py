"""roadgonio: ray-tracing simulator of road-surface goniophotometers.

The physics conventions (angles, BRDF model, instrument, k_A) are those of DESIGN.md, from
Bernasconi et al., "Geometrical errors and their uncertainty in goniophotometers: an
application to road surface photometry". Importing this package never imports mitsuba or
drjit: only :mod:`roadgonio.engines.mitsuba` does, and only when the caller asks for a variant.
"""
__version__ = "0.1.0"
