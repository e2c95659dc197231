"""References for a correction: the CIE tables nearest to a measured one, SAMPLE names, and the
alternative references whose k_A measures the model dependence of the classic route
(``roadgonio correct --reference SAMPLE``; paper section 4.1)."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence


from roadgonio.surface.model import RoadModel
from roadgonio.surface.cie import nearest_bundled
from roadgonio.surface.rtable import RTable


def sample_name(spec: str) -> str:
    """Short name of a SAMPLE argument: a file's stem, else the argument (``R3``, ``lambert``)."""
    return Path(spec).stem if Path(spec).suffix else spec


def resolve_alternatives(spec: str | Sequence[str] | None, measured: RTable, *, reference_name: str,
                         model_variant: str | None = None) -> dict[str, RoadModel]:
    """The alternative references for the model uncertainty: ``"auto"`` = the two CIE tables
    nearest to ``measured`` in (S1, Q0), the reference excluded (without ``model_variant`` never a
    fit with an unresolved spike: :func:`_auto_alternative`); ``"none"``/``None`` = none; a
    comma-separated text or a list of SAMPLEs = those (fitted or loaded like the reference)."""
    from roadgonio.surface.sample import resolve_sample
    if spec is None:
        return {}
    if isinstance(spec, str) and spec.strip().lower() == "auto":
        names = [n for n, _ in nearest_bundled(measured.s1(), measured.q0(), 2, exclude=[reference_name])]
        if model_variant is None:                       # roadgonio's choice: never a spike fit
            return {sample_name(n): _auto_alternative(n) for n in names}
    elif isinstance(spec, str):
        text = spec.strip()
        names = [] if text.lower() == "none" else [s.strip() for s in text.split(",") if s.strip()]
        if not names and text.lower() != "none":
            # "" or "," named none: the model component would vanish without a word (audit 21)
            from roadgonio.errors import InputError
            raise InputError(f"no sample named in {spec!r}; expected auto, none, or SAMPLEs separated by commas",
                             field="--alternatives")
    elif isinstance(spec, (list, tuple)):
        names = [str(s) for s in spec]
    else:
        from roadgonio.errors import InputError
        raise InputError(f"expected auto, none, a text of SAMPLEs separated by commas or a list of them, got "
                         f"{type(spec).__name__}", field="--alternatives")
    # every name resolved before any note is said: a mistake in the last is one line, not the notes
    # of the others before it (trial 12 D8: R2's spike note, then the error about R9)
    from roadgonio.errors import InputError, notes_held
    with notes_held():
        try:
            models = {sample_name(n): resolve_sample(n, model_variant).model for n in names}
        except InputError as err:
            if err.path is not None or err.field not in (None, "sample"):
                raise
            # the mistake is in the alternatives, not in --sample (user audit, session 19)
            raise InputError(err.reason, field="--alternatives") from None
    return models


def _auto_alternative(name: str) -> RoadModel:
    """A bundled table chosen as an alternative by roadgonio (not by the user): its default fit,
    unless that fit has a spike at beta 0 that no aperture resolves (the power fits of R2 and R4,
    :func:`roadgonio.surface.sample.unresolved_spike`), whose k_A (0.26-0.43 at grazing beta 0 for
    any instrument) would pass the fit's artefact off as model uncertainty; then its smooth fit, and
    a note says so."""
    import warnings

    from roadgonio.errors import ModelWarning
    from roadgonio.surface.sample import resolve_sample, unresolved_spike
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        model = resolve_sample(name).model
    if not unresolved_spike(model)[0].size:
        return model
    warnings.warn(ModelWarning(
        f"the alternative reference {name} (chosen as one of the two CIE tables nearest to the measured one) uses "
        f"its smooth fit: its {model.variant} fit has a spike at beta 0 that no aperture resolves, which would pass "
        "the fit's artefact off as model uncertainty (docs/inputs-outputs.md, \"A peak no instrument resolves\")"),
        stacklevel=2)
    return resolve_sample(name, "smooth").model
