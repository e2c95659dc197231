"""The instrument: what a goniophotometer is (docs/conventions.md section 4).

* :mod:`.config` -- the instrument file (TOML) as frozen, validated dataclasses
  (:class:`Instrument`, :class:`Source`, :class:`Detector`, :class:`SampleGeometry`), presets, loading;
* :mod:`.optics` -- the ray geometry of the source disc and the luminance meter (pupil x field),
  written once over an array namespace for numpy and Dr.Jit, and the geometry checks (footprint
  on the sample, source above the horizon, beam limit, the verdict of a traced hit check);
* :mod:`.mesh` -- the sample surface as triangles (rectangle or mesh file, read with trimesh,
  one-sided orientation check);
* :mod:`.profiles` -- the source's radiance profiles (over the aperture, with the emission angle)
  and the detector's sensitivity map;
* :mod:`.calibration` -- the ``[calibration]`` section: how a detector signal becomes a luminance
  coefficient;
* :mod:`.coverage` -- ``[cells]``: the cells an instrument really measures and how it fills the rest
  of its reported table;
* :mod:`.housing` -- the ``[housing]`` table: a box with Lambertian inner walls and baffles;
* :mod:`.enclosure` -- the housing's geometry: its panels and the checks that it holds the
  detector's view and every requested cell's source.

Angles follow :mod:`roadgonio.geometry` (``w_source``/``w_detector``), the one place the
azimuth convention is written.

Nothing here imports mitsuba or drjit.
"""
from roadgonio.instrument.config import (  # noqa: F401
    Detector, Instrument, Observation, SampleGeometry, Source, bundled_instruments, load_instrument)
