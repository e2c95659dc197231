"""Instrument design (issue 12): sweeps of instrument parameters, the Pareto front of signal
against |k_A - 1|, tolerance maps and the best design.

Rooms:

* :mod:`.grid`: ``--vary KEY=LO:HI:N[:log]``, the tolerance, the cells; every grid point is a full
  instrument (``Instrument.with_changes``);
* :mod:`.feasibility`: geometry checks of a point with the reason it is impossible (never a crash);
* :mod:`.metrics`: the signal (etendue x source solid angle, formula documented there) and the
  deviations of k_A from 1;
* Dask (local cluster of worker processes or an existing scheduler): :mod:`roadgonio.engines.cluster`,
  :class:`~.cluster.TableTask` unit "k_A table of (instrument, model, cells, backend, settings,
  seed)" that ``uncertainty`` and ``correct`` reuse;
* :mod:`.run`: the journal (resume), the Dataset; :mod:`.outputs`: design.nc, design.csv, best.toml,
  pareto.png, tolerance_map.png.

``design.nc`` layout: ``k_a``, ``se``, ``error_bound`` over (varied keys..., sample, tan_eps, beta);
per point ``max_abs_dev``, ``rms_dev``, ``worst_*``, ``signal``, ``footprint_length_m``,
``geometry_ok``, ``feasible``, ``kind``, ``reason``, ``seed``; provenance in the attributes.

The API is :func:`roadgonio.api.design`; this package is callable, so ``roadgonio.design(...)``
(and :func:`run_design`) is the same call (a function of that name in :mod:`roadgonio` would be
replaced by this package on its first import). It is an entry point: computing in this process with
the Mitsuba backend, it keeps a variant you selected, else selects one (llvm_ad_rgb).
:func:`roadgonio.design.run.run_design` (what the command runs) only checks the variant. Scripts that start a local cluster must guard the call with
``if __name__ == "__main__":`` (worker processes are spawned and import the main module).
"""
from __future__ import annotations

import sys
import types


def run_design(*args, **kwargs):
    """The API entry point :func:`roadgonio.api.design` (``roadgonio.design(...)``): returns the
    design's ``xarray.Dataset``; chooses the Mitsuba variant when it computes in this process."""
    from roadgonio.api import design
    return design(*args, **kwargs)


class _CallableModule(types.ModuleType):
    """``roadgonio.design(...)`` calls :func:`run_design` while ``roadgonio.design`` stays the package."""

    def __call__(self, *args, **kwargs):
        return run_design(*args, **kwargs)

    @property
    def __signature__(self):
        import inspect

        from roadgonio.api import design
        return inspect.signature(design)


sys.modules[__name__].__class__ = _CallableModule
