"""Helpers shared by the commands (not a command: modules starting with '_' are not discovered)."""
from __future__ import annotations

import math

from roadgonio.errors import InputError


def rel_se_setting(backend: str, value: float) -> dict[str, float]:
    """The backend keyword for ``--rel-se``: a relative tolerance ``rtol`` for the quadrature and the
    RQMC reference (its target error bound), a
    target relative standard error ``rel_se`` for the Monte Carlo backends. Checks 0 < value < 1."""
    if not (math.isfinite(value) and 0 < value < 1):
        raise InputError(f"expected a relative error in (0, 1), got {value}", field="--rel-se")
    return {"rtol" if backend in ("quadrature", "reference") else "rel_se": value}


def check_seed(value: int, option: str = "--seed") -> int:
    """A random seed must be >= 0 (numpy's SeedSequence takes none below)."""
    if value is None or int(value) < 0:
        raise InputError(f"expected a seed >= 0, got {value}", field=option)
    return int(value)


INSTRUMENT_HELP = "instrument TOML file (scenes/*.toml) or a bundled preset name (lab, portable)"
SAMPLE_HELP = ("bundled table name (R1..R4, C1, C2: fitted on the fly), an r-table file (.csv/.rtb), "
               "a model.json, or 'lambert'")


def add_instrument_argument(p) -> None:
    p.add_argument("--instrument", required=True, metavar="FILE", help=INSTRUMENT_HELP)


def add_sample_argument(p, name: str = "--sample", what: str = "") -> None:
    p.add_argument(name, required=True, metavar="SAMPLE", help=(what + ": " if what else "") + SAMPLE_HELP)


def load_inputs(args):
    """(instrument, model) from --instrument and --sample (and --model-variant where offered)."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.sample import resolve_sample
    instrument = load_instrument(args.instrument)
    model = resolve_sample(args.sample, getattr(args, "model_variant", None))
    return instrument, model
