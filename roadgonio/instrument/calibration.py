"""How the instrument turns a detector signal into a luminance coefficient (docs/conventions.md section 5):
the ``[calibration]`` section of an instrument file, as a frozen, validated dataclass.

.. code-block:: toml

    [calibration]
    mode = "lambert"       # default: calibrated cell by cell against a perfect diffuser
    # mode = "absolute"    # paper eq. 2: luminance meter in cd/m^2, illuminance E_0 at the sample centre
    # mode = "reference"   # cell by cell against a certified reference sample ...
    # reference = "R3"     # ... given as a SAMPLE (bundled table, table file, model.json, lambert)

This module only describes the calibration; the k_A that follows from it is computed in one place,
:mod:`roadgonio.engines.calibration` (a wrapper around any k_A backend, applied by
:func:`roadgonio.engines.make_backend`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from roadgonio.errors import InputError
from roadgonio.surface.sample import EXPECTED, is_named_sample

#: Calibration modes (docs/conventions.md section 5).
MODES = ("lambert", "absolute", "reference")
DEFAULT_MODE = "lambert"
#: Suffixes of a reference that is a file (resolved relative to the instrument file).
_FILE_SUFFIXES = (".json", ".csv", ".rtb")


@dataclass(frozen=True)
class Calibration:
    """The instrument's calibration: ``mode`` and, for ``"reference"``, the reference ``SAMPLE``.

    ``reference`` is kept as the user wrote it, except that a relative file name is made relative
    to the instrument file's folder (like ``[sample] mesh``)."""

    mode: str = DEFAULT_MODE
    reference: str | None = None

    def __post_init__(self):
        if not isinstance(self.mode, str) or self.mode.strip().lower() not in MODES:
            raise InputError(f"expected one of {', '.join(repr(m) for m in MODES)}, got {self.mode!r}",
                             field="calibration.mode")
        object.__setattr__(self, "mode", self.mode.strip().lower())
        if self.mode == "reference":
            if not isinstance(self.reference, (str, Path)) or not str(self.reference).strip():
                raise InputError("mode = \"reference\" needs reference = SAMPLE (a bundled table name such as "
                                 "\"R3\", a table file, a model.json or \"lambert\")", field="calibration.reference")
            object.__setattr__(self, "reference", str(self.reference).strip())
        elif self.reference is not None:
            raise InputError(f"reference is only used with mode = \"reference\" (mode is {self.mode!r})",
                             field="calibration.reference")

    @property
    def is_default(self) -> bool:
        return self.mode == DEFAULT_MODE

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"mode": self.mode}
        if self.reference is not None:
            d["reference"] = self.reference
        return d

    def reference_model(self, variant: str | None = None):
        """The reference sample's BRDF model (:func:`roadgonio.surface.sample.resolve_sample`)."""
        if self.mode != "reference" or self.reference is None:
            raise InputError("the instrument is not calibrated against a reference sample", field="calibration.mode")
        from roadgonio.surface.sample import resolve_sample
        try:
            return resolve_sample(self.reference, variant).model
        except InputError as err:
            raise InputError(f"[calibration] reference: {err.reason}", path=err.path, line=err.line,
                             field="calibration.reference") from None

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, path: str | Path | None = None) -> "Calibration":
        if not isinstance(d, Mapping):
            raise InputError("expected a table [calibration]", path=path, field="calibration")
        extra = sorted(set(d) - {"mode", "reference"})
        if extra:
            raise InputError(f"unknown key(s) {', '.join(extra)}; expected some of mode, reference",
                             path=path, field=f"calibration.{extra[0]}")
        try:
            cal = cls(mode=d.get("mode", DEFAULT_MODE), reference=d.get("reference"))
        except InputError as err:
            raise InputError(err.reason, path=path, field=err.field) from None
        if cal.reference is not None:
            p = Path(cal.reference).expanduser()
            if p.suffix.lower() in _FILE_SUFFIXES:
                if not p.is_absolute() and path is not None:
                    p = Path(path).parent / p
                if p.is_dir():
                    raise InputError(f"{str(p)!r} is a directory; expected a reference file", path=path,
                                     field="calibration.reference")
                if not p.exists():
                    raise InputError(f"reference file {str(p)!r} does not exist", path=path,
                                     field="calibration.reference")
                cal = cls(mode=cal.mode, reference=str(p))
            elif not is_named_sample(cal.reference):
                raise InputError(f"unknown sample {cal.reference!r}; expected {EXPECTED}", path=path,
                                 field="calibration.reference")
        return cal
