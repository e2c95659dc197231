"""Helpers shared by the commands (not a command: modules starting with '_' are not discovered)."""
from __future__ import annotations

import sys

from roadgonio.engines.accuracy import rel_se_setting  # noqa: F401 - the commands' --rel-se mapping


def check_seed(value: int, option: str = "--seed") -> int:
    """A random seed must be >= 0 (numpy's SeedSequence takes none below)."""
    from roadgonio.errors import InputError
    if value is None or int(value) < 0:
        raise InputError(f"expected a seed >= 0, got {value}", field=option)
    return int(value)


INSTRUMENT_HELP = ("instrument TOML file (keys and units: docs/conventions.md section 4; apertures are radii) or a "
                   "bundled preset name (lab, portable)")
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


def select_variant(backend: str, variant: str | None = None) -> None:
    """The command is the entry point: choose the Mitsuba variant here (``--variant``, else
    ``$ROADGONIO_VARIANT``, else llvm_ad_rgb) when the Mitsuba backend will run. Backends only check it."""
    if backend == "mitsuba":
        from roadgonio.engines.mitsuba import set_variant
        set_variant(variant)


# -- output: every command has --json and --quiet; progress bars only on a terminal -------------

def add_output_options(p, json_help: str = "print the result as JSON instead of text") -> None:
    """``--json`` (machine-readable result on stdout) and ``--quiet`` (nothing but errors), exclusive."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--json", action="store_true", help=json_help)
    g.add_argument("-q", "--quiet", action="store_true",
                   help="print nothing but errors (no summary, no progress bar); the exit status tells the result")


def show_progress(args) -> bool:
    """Progress bars only when stderr is a terminal (never into a log or a pipe), and not with --quiet."""
    return not getattr(args, "quiet", False) and sys.stderr.isatty()


def text_output(args):
    """``print`` for the human-readable summary, or a no-op with --quiet or --json."""
    if getattr(args, "quiet", False) or getattr(args, "json", False):
        return lambda *a, **k: None
    return print


# -- Dask: --workers N | --scheduler ADDRESS (design, uncertainty, correct) ------------------------

def _workers(text: str) -> int:
    import argparse
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {v}")
    return v


def add_dask_arguments(p, default_text: str) -> None:
    """``--workers N | --scheduler ADDRESS`` (shared by the commands that run k_A tables on Dask)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=_workers, metavar="N",
                   help=f"worker processes of a local Dask cluster (one thread each); 0 = compute in this process "
                        f"({default_text})")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on an existing Dask cluster, e.g. tcp://127.0.0.1:8786 (started with 'dask scheduler' "
                        "and 'dask worker ADDRESS --nthreads 1' from the same environment as roadgonio)")
