"""The Dr.Jit array namespace of the model and the optics (same names as
:class:`roadgonio.arrays.NumpyOps`), so :func:`roadgonio.surface.model.road_brdf` and
:mod:`roadgonio.instrument.optics` run unchanged inside Mitsuba kernels (float32).

Only this subpackage imports drjit, and only when :class:`DrJitOps` is first used.

Numerics: ``log1m(h) = log(1 - h)`` uses a 7-term series for ``h < 0.05``
(truncation error < h^8/8 absolute, relative error < h^7/8 ~ 1e-10 at h = 0.05, far below
float32's 6e-8), and
``log(1 - h)`` above. The road model writes its lobes as ``exp(n log1m(h))`` with the half-chord
``h = 1 - cos Omega``, so a Phong lobe with n = 1e4 keeps float32 accuracy at its peak
(the naive ``cos^n`` of a float32 cosine near 1 is off by about n * 1e-7, since 1 - cos Omega is
quantised in steps of 6e-8 there).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

#: Below this half-chord, log(1 - h) is evaluated by its series.
LOG1M_SERIES_BELOW = 0.05


class DrJitOps:
    """Array namespace over Dr.Jit arrays (any variant's Float)."""

    sqrt = staticmethod(dr.sqrt)
    sin = staticmethod(dr.sin)
    cos = staticmethod(dr.cos)
    exp = staticmethod(dr.exp)
    log = staticmethod(dr.log)
    atan2 = staticmethod(dr.atan2)
    abs = staticmethod(dr.abs)
    maximum = staticmethod(dr.maximum)
    minimum = staticmethod(dr.minimum)
    floor = staticmethod(dr.floor)

    @staticmethod
    def where(cond, a, b):
        return dr.select(cond, a, b)

    @staticmethod
    def take(table, index):
        """``table[index]`` for a Float array ``index`` of whole numbers within the table: a gather
        from ``table``, a Dr.Jit array of the type of ``index`` or a float64 numpy array (made one:
        the spline coefficients of :class:`roadgonio.surface.correction_surface.CorrectedSurface`)."""
        if isinstance(table, np.ndarray):
            table = type(index)(np.ascontiguousarray(table, dtype=np.float32))
        return dr.gather(type(index), table, dr.uint32_array_t(type(index))(index))

    @staticmethod
    def log1m(h):
        """log(1 - h), float32-accurate for small h (series below :data:`LOG1M_SERIES_BELOW`)."""
        series = -h * (1.0 + h * (1.0 / 2.0 + h * (1.0 / 3.0 + h * (1.0 / 4.0 + h * (
            1.0 / 5.0 + h * (1.0 / 6.0 + h * (1.0 / 7.0)))))))
        return dr.select(h < LOG1M_SERIES_BELOW, series, dr.log(1.0 - h))
