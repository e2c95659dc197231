"""The ``roadgonio`` command: one way in. Each command parses its arguments, calls ONE function of
:mod:`roadgonio.api` and prints the result; it resolves no input itself (no instrument, sample,
cells, backend, seed or preset: ``tests/unit/test_layers.py`` holds it to that).

Every module in this package that defines ``register(subparsers)`` adds one or more
sub-commands; ``register`` must call ``parser.set_defaults(func=run)`` where ``run(args)`` returns
the exit status. Ctrl-C and SIGTERM stop a command alike (:mod:`roadgonio.interrupts`: its one line
saying what was kept, exit status 130). Errors of type :class:`~roadgonio.errors.RoadgonioError` are printed as one
line (``roadgonio: error: ...``) with exit status 2 (4 for work lost on a Dask cluster,
:class:`~roadgonio.errors.WorkLostError`: not bad input), never as a traceback; an error the API raised
about an argument names the command's option instead (``rel_se`` -> ``--rel-se``).
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import re
import sys
import warnings
from collections.abc import Sequence

from roadgonio._version import __version__
from roadgonio.errors import EXIT_WORK_LOST, InputError, ModelWarning, RoadgonioError, WorkLostError, is_interrupt

#: Order in which commands are listed in --help (others follow alphabetically).
ORDER = ["tables", "table", "fit", "ka", "render", "validate", "uncertainty", "correct", "design", "road",
         "compare", "classify"]


class _Parser(argparse.ArgumentParser):
    """argparse with the project's error line: a bad option is ONE line (``roadgonio: error: ...``,
    naming the command and the option, with where to read more), exit status 2, like every other
    input error (no usage block above it)."""

    def error(self, message: str):
        # the top-level parser's prog is "roadgonio" itself: no "roadgonio: error: roadgonio: ..."
        where = "" if self.prog == "roadgonio" else f"{self.prog}: "
        self.exit(2, f"roadgonio: error: {where}{message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="roadgonio",
        description="Simulate road-surface goniophotometers: fit road BRDF models to r-tables, compute "
                    "the aperture-effect factor k_A of an instrument, its uncertainty, and correct "
                    "measured r-tables.",
        epilog="Physics conventions (angles, quantities, the BRDF model, instrument keys with units, k_A and the "
               "calibration modes): docs/conventions.md, installed with the package as roadgonio/docs/conventions.md.")
    parser.add_argument("--version", action="version", version=f"roadgonio {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    names = [m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")]
    names.sort(key=lambda n: (ORDER.index(n) if n in ORDER else len(ORDER), n))
    for name in names:
        mod = importlib.import_module(f"{__name__}.{name}")
        if hasattr(mod, "register"):
            mod.register(sub)
    return parser


def _negative_values(argv: Sequence[str]) -> list[str]:
    """``--opt -1%`` as ``--opt=-1%``: argparse takes a value that starts with '-' and is not a plain
    number ('-1%', '-0.5:rect') for an option and says "expected one argument", never the value's
    own error (user audit, session 37: ``--u-measured -1%``). The value then reaches the check that
    names it."""
    out: list[str] = []
    for tok in argv:
        if (out and out[-1].startswith("--") and "=" not in out[-1] and re.match(r"^-\.?\d", tok)
                and not re.fullmatch(r"-\d+|-\d*\.\d+", tok)):
            out[-1] = f"{out[-1]}={tok}"
        else:
            out.append(tok)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = _negative_values(sys.argv[1:] if argv is None else argv)
    args, extra = parser.parse_known_args(argv)
    if extra:
        # argparse reports unrecognised arguments from the top-level parser; name the command they were
        # given to (``roadgonio correct: unrecognized arguments: B.toml``), which the user can look up
        sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        command = sub.choices.get(getattr(args, "command", None)) if sub is not None else None
        (command or parser).error(f"unrecognized arguments: {' '.join(extra)}")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # Ctrl-C and SIGTERM alike: a KeyboardInterrupt (at the Mitsuba engine's next pass boundary when
    # one runs), said at once on stderr (roadgonio.interrupts)
    from roadgonio import interrupts
    interrupts.install()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", ModelWarning)
            warnings.showwarning = _show_note(set())
            return int(args.func(args) or 0)
    except RoadgonioError as err:
        print(f"roadgonio: error: {_as_option(err, parser, args)}", file=sys.stderr)
        return EXIT_WORK_LOST if isinstance(err, WorkLostError) else 2
    except BrokenPipeError:
        # the reader of stdout went away (``roadgonio ... --json | head``): no traceback, the usual
        # status of a process whose pipe closed (128 + SIGPIPE); stdout is pointed at /dev/null so the
        # interpreter's final flush does not fail again
        import os
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except (KeyboardInterrupt, RuntimeError) as err:
        # Ctrl-C, also when Mitsuba wraps it in a RuntimeError while building a scene (is_interrupt).
        # Each command says truthfully what an interruption keeps (the Interrupted's note, raised by the
        # work that knows what it journaled, else ``on_interrupt``, set by the command's parser or by its
        # run() once it knows); no promise of a resume that does not exist
        if not is_interrupt(err):
            raise
        note = getattr(err, "note", None) or getattr(args, "on_interrupt", None) or "interrupted: nothing was written"
        print(f"roadgonio: {note}", file=sys.stderr)
        return 130
    finally:
        interrupts.finished()


def _show_note(said: set):
    """Print a :class:`ModelWarning` as ``roadgonio: note: ...`` on standard error, each text once
    (a sample resolved twice says it once); other warnings as Python shows them."""
    plain = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if not issubclass(category, ModelWarning):
            return plain(message, category, filename, lineno, file, line)
        text = str(message)
        if text not in said:
            said.add(text)
            print(f"roadgonio: note: {text}", file=sys.stderr)
    return show


def _as_option(err: RoadgonioError, parser: argparse.ArgumentParser, args) -> RoadgonioError:
    """An InputError about an API argument (no file) names the command's option for it: the
    argument names are the options' destinations or their names (``rel_se`` -> ``--rel-se``;
    ``measured/sample`` -> ``--measured/--sample``; a positional argument: its metavar, ``b`` -> ``B``). The rooms name API arguments, never options
    (trial 10 D11: ``rg.correct`` said field '--instrument'); this is the one place that maps them."""
    if not isinstance(err, InputError):
        return err
    sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
    command = sub.choices.get(getattr(args, "command", None)) if sub is not None else None
    if command is None:
        return err
    options: dict[str, str] = {}
    for a in command._actions:
        long = [o for o in a.option_strings if o.startswith("--")]
        if long:
            options.setdefault(a.dest, long[0])
            for o in long:
                options.setdefault(o[2:].replace("-", "_"), o)
        elif not a.option_strings and isinstance(a.metavar, str):
            options.setdefault(a.dest, a.metavar)      # a positional argument as --help shows it (compare's B)

    def named(text: str | None) -> str | None:
        if not text:
            return text
        cut = min((i for i in (text.find("."), text.find(" ")) if i >= 0), default=len(text))
        head, rest = text[:cut], text[cut:]
        return "/".join(options.get(h, h) for h in head.split("/")) + rest

    if err.path is not None:       # a file's content: name the option that gave the file
        return InputError(err.reason, path=err.path, line=err.line, field=err.field, argument=named(err.argument))
    return InputError(err.reason, line=err.line, field=named(err.field), argument=named(err.argument))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
