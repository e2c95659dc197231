"""The instrument: what a goniophotometer is (docs/conventions.md section 4).

* :mod:`.config` -- the instrument file (TOML) as frozen, validated dataclasses
  (:class:`Instrument`, :class:`Source`, :class:`Detector`, :class:`SampleGeometry`), presets, loading;
* :mod:`.optics` -- the ray geometry of the source disc and the luminance meter (pupil x field),
  written once over an array namespace for numpy and Dr.Jit, and the geometry checks (footprint
  on the sample, source above the horizon, beam limit, the verdict of a traced hit check);
* :mod:`.mesh` -- the sample surface as triangles (rectangle or mesh file, read with trimesh,
  one-sided orientation check).

Angles follow :mod:`roadgonio.geometry` (``w_source``/``w_detector``), the one place the
azimuth convention is written.

Nothing here imports mitsuba or drjit.
"""
from roadgonio.instrument.config import (  # noqa: F401
    Detector, Instrument, Observation, SampleGeometry, Source, bundled_instruments, load_instrument)
