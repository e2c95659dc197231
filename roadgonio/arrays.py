"""The array namespace of the shared physics formulas (developers' guide, rule 1).

The road BRDF (:func:`roadgonio.surface.model.road_brdf`), the instrument optics
(:mod:`roadgonio.instrument.optics`) and every other formula written once take the namespace
``xp`` as their first argument: :class:`NumpyOps` (float64 numpy, here: the integrators, the
fitter, the checks) or ``DrJitOps`` (:mod:`roadgonio.engines.mitsuba.ops`: the same names over
Dr.Jit arrays, inside Mitsuba kernels). It lives in the base layer so every room can use it.
"""
from __future__ import annotations

import numpy as np


class NumpyOps:
    """The array namespace of the shared formulas, float64 numpy. The Dr.Jit namespace in
    :mod:`roadgonio.engines.mitsuba.ops` provides the same names."""

    sqrt = staticmethod(np.sqrt)
    sin = staticmethod(np.sin)
    cos = staticmethod(np.cos)
    exp = staticmethod(np.exp)
    log = staticmethod(np.log)
    atan2 = staticmethod(np.arctan2)
    abs = staticmethod(np.abs)
    maximum = staticmethod(np.maximum)
    minimum = staticmethod(np.minimum)
    floor = staticmethod(np.floor)

    @staticmethod
    def where(cond, a, b):
        return np.where(cond, a, b)

    @staticmethod
    def take(table, index):
        """``table[index]`` for a float array ``index`` of whole numbers within the table (a gather)."""
        return np.take(table, np.asarray(index).astype(np.int64))

    @staticmethod
    def log1m(h):
        """log(1 - h), accurate for small h."""
        return np.log1p(-h)
