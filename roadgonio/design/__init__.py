"""Instrument design: sweeps of instrument parameters, the Pareto front of signal against
|k_A - 1|, tolerance maps and the best design. The API is :func:`roadgonio.api.design_study`
(``roadgonio design``), which resolves the inputs and calls :func:`.run.run_design`.

Modules:

* :mod:`.grid`: ``--vary KEY=LO:HI:N[:log]`` and the tolerance; every grid point is a full
  instrument (``Instrument.with_changes``);
* :mod:`.feasibility`: geometry checks of a point with the reason it is impossible (never a crash);
* :mod:`.metrics`: the signal (etendue x source solid angle, formula documented there) and the
  deviations of k_A from 1;
* :mod:`.run`: the journal (resume), the Dataset; :mod:`.dataset`: the Dataset assembled and read
  back; :mod:`.outputs`: design.nc, design.csv, best.toml, pareto.png, tolerance_map.png. The Dask
  plumbing is :mod:`roadgonio.engines.cluster`;
* :mod:`.second_aperture`: which second aperture an instrument should have (``roadgonio design
  --second-aperture``).

``design.nc`` layout: ``k_a``, ``se``, ``error_bound``, ``confidence_*`` and the stray light
``k_a_direct``, ``stray_fraction`` (with their ``_se``) over (varied keys..., sample, tan_eps, beta);
per point ``max_abs_dev``, ``rms_dev``, ``worst_*``, ``max_abs_dev_direct``, ``max_stray_*``,
``signal``, ``footprint_length_m``, ``geometry_ok``, ``feasible``, ``kind``, ``reason``, ``seed``;
provenance in the attributes.
"""
