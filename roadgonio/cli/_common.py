"""Helpers shared by the commands (not a command: modules starting with '_' are not discovered).

The commands only parse arguments, call one function of :mod:`roadgonio.api` and print; the
choices they offer (backends, presets, model variants) come from the API too."""
from __future__ import annotations

import sys

from roadgonio import api

INSTRUMENT_HELP = ("instrument TOML file (keys and units: docs/conventions.md section 4; apertures are radii) or a "
                   "bundled preset name (" + ", ".join(api.instrument_presets()) + ")")
SAMPLE_HELP = ("bundled table name (R1..R4, C1, C2: fitted on the fly), an r-table file (.csv/.rtb), "
               "a model.json, or 'lambert'")


def add_instrument_argument(p) -> None:
    p.add_argument("--instrument", required=True, metavar="FILE", help=INSTRUMENT_HELP)


def add_sample_argument(p, name: str = "--sample", what: str = "") -> None:
    p.add_argument(name, required=True, metavar="SAMPLE", help=(what + ": " if what else "") + SAMPLE_HELP)


def add_model_variant(p, help_text: str = "model variant fitted when SAMPLE is a table (default: the paper's "
                                          "'power')", extra: tuple[str, ...] = ()) -> None:
    p.add_argument("--model-variant", dest="model_variant", choices=list(extra) + list(api.model_variants()),
                   help=help_text)


def add_backend(p, command: str, default: str = "mitsuba", help_text: str | None = None) -> None:
    """``--backend``: the choices are the backends the API takes for ``command`` (:func:`api.backends`)."""
    backends = api.backends(command)
    p.add_argument("--backend", default=default, choices=list(backends),
                   help=(help_text + ": " if help_text else "")
                   + "; ".join(f"{n}: {s}" for n, s in backends.items()).replace("%", "%%"))


def add_accuracy(p) -> None:
    p.add_argument("--accuracy", choices=list(api.accuracy_presets()),
                   help="preset on the measured speed-accuracy frontier (docs/benchmarks.md); --rel-se overrides it")


def add_mitsuba_variant(p) -> None:
    p.add_argument("--variant", dest="mitsuba_variant", metavar="VARIANT",
                   help="Mitsuba variant (default llvm_ad_rgb; cuda_ad_rgb on a GPU machine)")


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


def print_json(obj) -> None:
    """The result as JSON on stdout, written by the one JSON writer (NaN/inf as null)."""
    print(api.to_json(obj))


def out_arg(args):
    """``--out DIR``, else the command's default folder (:data:`roadgonio.api.AUTO`). An empty
    ``--out ''`` is an error, not the default folder (user audit, session 19)."""
    out = getattr(args, "out", None)
    if out is not None and not str(out).strip():
        from roadgonio.errors import InputError
        raise InputError("expected a folder name, got an empty one (leave --out out for the default folder)",
                         field="--out")
    return out if out else api.AUTO


# -- Dask: --workers N | --scheduler ADDRESS (design, uncertainty, correct) ------------------------

def _workers(text: str) -> int:
    import argparse
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {v}")
    most = api.max_local_workers()
    if v > most:
        raise argparse.ArgumentTypeError(f"expected at most {most} on this machine (8 a core), got {v}; "
                                         "for more machines give --scheduler")
    return v


def positive_int(text: str) -> int:
    import argparse
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {v}")
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
