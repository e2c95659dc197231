"""The road surface: what is measured (docs/conventions.md sections 2-3).

* :mod:`.model` -- the road BRDF of paper eq. 4 (and its named variants), one definition over an
  array namespace shared by numpy (fitter, integrators) and Dr.Jit (the Mitsuba plugin);
* :mod:`.rtable` -- r-tables: the CIE grid, the bundled R1-R4/C1/C2, CSV and DIALux RTB I/O,
  S1, S2 and Q0;
* :mod:`.fit` -- fitting the model to a table (least squares in % of max r, as the paper);
* :mod:`.sample` -- resolving a SAMPLE argument (bundled name, table file, model.json, lambert)
  to a model;
* :mod:`.fitplot` -- the picture of a fit;
* :mod:`.cie` -- the CIE classes by S1 and the nearest bundled CIE standard table;
* :mod:`.correction_surface` -- the smooth correction factor over the incident direction that lets
  the model follow a surface eq. 4 cannot;
* :mod:`.truths` -- known surfaces outside eq. 4, for round trips of the correction.
"""
