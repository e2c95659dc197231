"""Instrument design (issue 12): sweeps of instrument parameters, the Pareto front of signal
against |k_A - 1|, tolerance maps and the best design.

Rooms:

* :mod:`.grid`: ``--vary KEY=LO:HI:N[:log]``, the tolerance, the cells; every grid point is a full
  instrument (``Instrument.with_changes``);
* :mod:`.feasibility`: geometry checks of a point with the reason it is impossible (never a crash);
* :mod:`.metrics`: the signal (etendue x source solid angle, formula documented there) and the
  deviations of k_A from 1;
* :mod:`.cluster`: Dask (local cluster of worker processes or an existing scheduler), the
  :class:`~.cluster.TableTask` unit "k_A table of (instrument, model, cells, backend, settings,
  seed)" that ``uncertainty`` and ``correct`` reuse;
* :mod:`.run`: the journal (resume), the Dataset; :mod:`.outputs`: design.nc, design.csv, best.toml,
  pareto.png, tolerance_map.png.

``design.nc`` layout: ``k_a``, ``se``, ``error_bound`` over (varied keys..., sample, tan_eps,
beta_deg); per point ``max_abs_dev``, ``rms_dev``, ``worst_*``, ``signal``, ``footprint_length_m``,
``geometry_ok``, ``feasible``, ``kind``, ``reason``, ``seed``; provenance in the attributes.

The API is :func:`run_design` (``roadgonio.design.run_design(...)``); the package itself is
callable too, so ``roadgonio.design(...)`` is the same call.
"""
from __future__ import annotations

import sys
import types


def run_design(*args, **kwargs):
    """Run a design study; see :func:`roadgonio.design.run.run_design`."""
    from roadgonio.design.run import run_design as _run
    return _run(*args, **kwargs)


run_design.__doc__ = "Run a design study and return its xarray Dataset (roadgonio.design.run.run_design)."


class _CallableModule(types.ModuleType):
    """``roadgonio.design(...)`` calls :func:`run_design` while ``roadgonio.design`` stays the package
    (a function of that name in ``roadgonio`` would be replaced by the package on its first import)."""

    def __call__(self, *args, **kwargs):
        return run_design(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
