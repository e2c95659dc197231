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

``design.nc`` layout: ``k_a``, ``se``, ``error_bound`` over (varied keys..., sample, tan_eps, beta);
per point ``max_abs_dev``, ``rms_dev``, ``worst_*``, ``signal``, ``footprint_length_m``,
``geometry_ok``, ``feasible``, ``kind``, ``reason``, ``seed``; provenance in the attributes.

The API is :func:`run_design`; the package itself is callable, so ``roadgonio.design(...)`` is the
same call (a function of that name in :mod:`roadgonio` would be replaced by this package on its
first import). It is an entry point: computing in this process with the Mitsuba backend, it keeps
a variant you selected, else selects one (``variant`` setting, else ``$ROADGONIO_VARIANT``, else
llvm_ad_rgb). Scripts that start a local cluster must guard the call with
``if __name__ == "__main__":`` (worker processes are spawned and import the main module).
"""
from __future__ import annotations

import sys
import types


def run_design(instrument, vary=None, samples="R3", **kwargs):
    """Run a design study and return its ``xarray.Dataset``: the arguments of
    :func:`roadgonio.design.run.run_design` (base instrument, ``vary``, ``samples``, ``tolerance``,
    ``cells``, ``backend``, ``accuracy``, ``settings``, ``seed``, ``workers``/``scheduler``/``client``,
    ``out``, ...)."""
    from roadgonio.design import cluster
    from roadgonio.design.run import run_design as _run
    backend = kwargs.get("backend", "mitsuba")
    here = kwargs.get("workers") == 0 and kwargs.get("scheduler") is None and kwargs.get("client") is None
    if here and backend in cluster.PROCESS_SETUP:
        cluster.init_engine(backend, (kwargs.get("settings") or {}).get("variant"))
    return _run(instrument, vary, samples, **kwargs)


class _CallableModule(types.ModuleType):
    """``roadgonio.design(...)`` calls :func:`run_design` while ``roadgonio.design`` stays the package."""

    def __call__(self, *args, **kwargs):
        return run_design(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
