"""Correction of a measured r-table for the aperture effect (paper eq. 2; docs/conventions.md
section 5): ``r_true = r_measured / k_A`` with k_A under the instrument's calibration, and one
uncertainty of the corrected table with correlations. The forward model (fixed float64 ray bundles
per cell, common random numbers: the simulated measurement and k_A of any BRDF model, smooth in its
parameters) is :mod:`roadgonio.engines.bundle`.

Modules:

* :mod:`.fit` -- fitting the model *through the instrument* (variable projection, multi-start,
  parameter covariance);
* :mod:`.budget` -- the uncertainty budget (measurement, backend, parameters, model variant,
  misalignment), S1 / S2 / Q0 with their standard uncertainties, CIE classes;
* :mod:`.run` -- the procedure (``reference = "self"``: fit through the instrument, k_A by the
  chosen backend, journalled; ``reference = SAMPLE``: the classic route);
* :mod:`.flexible`, :mod:`.outside` -- the forward model that follows a surface outside eq. 4 (eq. 4
  backbone x correction surface, fitted linearly with the evidence choosing the smoothing), through
  one instrument or several (docs/correction.md, "Outside eq. 4");
* :mod:`.discrepancy` -- the model-discrepancy component of a surface correction's budget (what the
  instruments cannot see);
* :mod:`.files` -- the entry: one table, several tables of one instrument, several instruments;
* :mod:`.reference` -- the alternative references (the nearest CIE tables: :mod:`roadgonio.surface.cie`);
* :mod:`.outputs` -- the files and pictures;
* :mod:`.synthetic` -- synthetic measurements of a known surface (round trips).
"""
from roadgonio.correction.reference import resolve_alternatives, sample_name  # noqa: F401
from roadgonio.correction.run import (  # noqa: F401
    CorrectionResult, InstrumentArtefacts, correct_self, correct_with_reference, measured_uncertainty)
from roadgonio.correction.files import correct_files, correct_joint, correct_measured  # noqa: F401
from roadgonio.correction.outputs import write_correction  # noqa: F401
