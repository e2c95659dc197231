"""A virtual intercomparison (key comparison) of road-surface goniophotometers (docs/intercomparison.md).

Several participants (an instrument each, with its misalignment, repeatability, calibration and
what it does with its table) measure one surface in many simulated realisations of a comparison;
per cell: the reference values (weighted mean, Mandel-Paule and DerSimonian-Laird consensus, the
truth), every participant's degree of equivalence with U, E_n, the Birge ratio, the share of
compatible cells, why they disagree (each characteristic idealised in turn), and the same
comparison with every participant correcting with ``roadgonio correct --reference self``.

Rooms: :mod:`.statistics` (the comparison's statistics, pure numpy), :mod:`.study` (the study
file), :mod:`.simulate` (the participants' tables in one realisation), :mod:`.run` (the stages on
Dask, the journal, the Dataset), :mod:`.outputs` (intercompare.nc, CSV, pictures). The command is
``roadgonio intercompare STUDY --out DIR``, the API :func:`roadgonio.api.intercompare`. This room
imports from engines, uncertainty and correction, never the other way.
"""
