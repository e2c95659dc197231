"""Luminaire photometry for the road calculation: the intensity table I(C, gamma) of an EULUMDAT
(.ldt) file, read by :mod:`roadgonio.eulumdat` (the package's one EULUMDAT reader), and the
illustrative luminaire shipped with roadgonio.

Conventions (EN 13201-3:2015 clause 6, EULUMDAT): gamma from the downward vertical of the
luminaire, C the azimuth, C = 0 along the road axis, C = 90 deg across the road towards the
carriageway. Interpolation in the I-table (EN 13201-3:2015 clause 5.3.2): linear in C and in gamma
(bilinear), C periodic over 360 deg; outside the file's gamma range the intensity is unknown (NaN).
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

from roadgonio.eulumdat import Luminaire, read_ldt

__all__ = ["BUNDLED_LUMINAIRE", "Luminaire", "bundled_luminaire_path", "load_luminaire", "read_ldt"]

#: The illustrative luminaire shipped with roadgonio (made by roadgonio/data/road/make_luminaire.py).
BUNDLED_LUMINAIRE = "roadgonio_cutoff.ldt"


def bundled_luminaire_path() -> Path:
    return Path(str(resources.files("roadgonio.data").joinpath("road", BUNDLED_LUMINAIRE)))


def load_luminaire(spec: str | Path | None = None) -> Luminaire:
    """The bundled illustrative luminaire (``None``) or an .ldt file."""
    return read_ldt(bundled_luminaire_path() if spec is None else spec)
