"""Measurement uncertainty of an r-table from the instrument's geometric errors: Monte Carlo
propagation of distributions (JCGM 101:2008, "GUM Supplement 1") beside the first-order GUM
uncertainty framework (JCGM 100:2008), with the JCGM 101 section 8 validation of the GUM result
and the JCGM 101 section 7.9 adaptive stopping rule. Paper section 4.1: "Without aperture effect,
a loop over a large number (typically 5000-50000) generates random angles of specified standard
deviations and distributions".

Inputs (SPEC, :func:`parse_sigma_spec`)
---------------------------------------
Seven independent errors of the instrument, zero mean, each with a standard deviation and a
distribution (normal, or rectangular with that standard deviation, half-width sigma sqrt 3):

=====================  ====================================================================
``alpha_deg``          observation elevation error (detector arm)
``eps_deg``            source polar-angle error
``beta_deg``           source azimuth (beta) error
``tilt_x_deg``         sample tilt about the x axis (x = observation azimuth, in the sample
                       plane): tilts the normal sideways, towards +-y
``tilt_y_deg``         sample tilt about the y axis: tilts the normal towards/away from the
                       detector (changes the local alpha to first order)
``source_distance_m``  source distance error D_S - D_S0 (a fixed-height source: its height error, every D_S scaling with it)
``detector_distance_m`` detector distance error D_D - D_D0
=====================  ====================================================================

One trial draws ONE error set and applies it to every cell of the table: the errors of one
instrument setting are shared by all the cells it measures (fully correlated across the table),
so the distributions of table functionals (Q0, S1) come out right.

Measurement model (one trial)
-----------------------------
The instrument believes it measures at the nominal (alpha0, delta0) and (eps0, beta0) of the cell.
True geometry: detector direction ``w_o(alpha0 + d_alpha, delta0)``, source direction
``w_i(eps0 + d_eps, beta0 + d_beta)`` (docs/conventions.md section 1), both in the laboratory frame; the
sample is tilted by ``R = R_y(tilt_y) R_x(tilt_x)`` (normal ``R e_z``), so the directions in the
sample's own frame are ``w' = R^T w``. The road BRDF is evaluated only through
:meth:`roadgonio.surface.model.RoadModel.brdf` on ``(w_i', w_o')``.

Illuminance normalisation (``illuminance``):

* ``"nominal"`` (default): the instrument is calibrated at the nominal geometry: it knows the
  normal illuminance E_perp of its source at the nominal distance D_S0 and computes
  q = L / (E_perp cos eps0). Really, the source is at D_S = D_S0 + dD_S (inverse-square law:
  E_perp,true = E_perp (D_S0/D_S)^2) and lights the sample at the local incidence angle theta_i'
  (L = f E_perp,true cos theta_i'). So the reported value is
  ``r_meas = f(w_i', w_o') cos(theta_i') (D_S0 / D_S)^2 cos^2(eps0)``
  (= q_meas cos^3 eps0). At grazing incidence the cosine ratio cos(theta_i')/cos(eps0) is the
  largest contributor (relative sensitivity tan eps per radian of d eps).
* ``"measured"``: the horizontal illuminance is measured in situ, in the sample plane, for every
  cell, so the illuminance errors cancel: ``r_meas = f(w_i', w_o') cos^3(eps0)``.

The detector distance does not enter without the aperture effect (luminance does not depend on
distance). With the aperture effect, ``r_meas`` is multiplied by k_A of the perturbed geometry:
the instrument with elevation alpha' (detector direction in the sample frame), source direction
(eps', beta') in the sample frame, distances D_S and D_D (the detector's focus setting of the
instrument file is kept; if the file gives none the focus follows the distance). The sample tilt
enters k_A through the local angles only (the tilt of the footprint plane itself is second order
and not modelled). k_A comes from a validated surrogate (:mod:`roadgonio.uncertainty.surrogate`) fitted to
exact evaluations of a k_A backend (:func:`roadgonio.engines.make_backend`); its error against
held-out exact evaluations is measured and reported.

Outputs per cell, and for Q0 (CIE 144, over the standard tabulated region, :meth:`RTable.q0`) and
S1: mean, standard uncertainty, 95 % probabilistically symmetric and shortest coverage intervals
(JCGM 101 7.7), the GUM first-order estimate y = f(0), u(y) from finite-difference sensitivity
coefficients, y +- k u(y), and the JCGM 101 section 8 comparison (d_low, d_high vs delta).

The API is :func:`roadgonio.api.estimate_uncertainty`. Modules: :mod:`.spec`, :mod:`.cells`, :mod:`.measurement`, :mod:`.statistics`, :mod:`.gum`, :mod:`.run`, :mod:`.report`.
"""
from roadgonio.uncertainty.spec import (CELL_SETS, DISTRIBUTIONS, ILLUMINANCE, INPUT_HELP, INPUTS,  # noqa: F401
                                        SPEC_HELP, SigmaSpec, parse_sigma_spec)
from roadgonio.uncertainty.cells import CellSet, standard_mask, standard_q0_weights  # noqa: F401
from roadgonio.uncertainty.measurement import MeasurementModel  # noqa: F401
from roadgonio.uncertainty.statistics import coverage_indices, numerical_tolerance, summarize  # noqa: F401
from roadgonio.uncertainty.gum import gum_propagation, gum_validation  # noqa: F401
from roadgonio.uncertainty.run import (BackendFactory, CaseResult, SurrogateReport,  # noqa: F401
                                       UncertaintyResult, build_surrogate, default_backend_factory, run_uncertainty)
from roadgonio.uncertainty.report import (OUTPUT_NAMES, cells_csv_text, plot_q0_s1,  # noqa: F401
                                          plot_uncertainty_maps, result_dict, summary_lines, write_results)
