"""Errors that a user sees as a clear message instead of a traceback.

Every input error names the file (or the option), the line or field, and what was expected.
The CLI catches :class:`RoadgonioError` and prints ``roadgonio: error: <message>`` with exit
status 2 (4 for :class:`WorkLostError`: work lost on a cluster, not bad input; `validate` uses 1 and 3 for its verdicts).
"""
from __future__ import annotations

import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


class RoadgonioError(Exception):
    """Base class of the errors that are reported to the user without a traceback."""


def _located(message: str, *, path: str | None = None, line: int | None = None, field: str | None = None,
             argument: str | None = None) -> str:
    """``FILE:LINE, field 'F', ARGUMENT: message`` with whatever of them is known (the one layout of
    every located error)."""
    where = []
    if path is not None:
        where.append(path if line is None else f"{path}:{line}")
    elif line is not None:
        where.append(f"line {line}")
    if field is not None:
        where.append(f"field '{field}'")
    if argument is not None:
        where.append(argument)
    return f"{', '.join(where)}: {message}" if where else message


class InputError(RoadgonioError, ValueError):
    """Bad input: names where (file, line, field) and what was expected.

    Parameters
    ----------
    message:
        What is wrong and what was expected.
    path:
        The file the input came from, or ``None`` for a command-line option or an API value.
    line:
        1-based line number in ``path``, if known.
    field:
        The key, column or option that is wrong, if known.
    argument:
        The argument (an API parameter, or the command's option) that named the file, when the
        error is about a file's content: ``odd.csv:1: --measured: the header's beta ...``.
    """

    def __init__(self, message: str, *, path: str | Path | None = None,
                 line: int | None = None, field: str | None = None, argument: str | None = None):
        self.path = None if path is None else str(path)
        self.line = line
        self.field = field
        self.reason = message
        self.argument = argument
        super().__init__(_located(message, path=self.path, line=line, field=field, argument=argument))

    def with_argument(self, argument: str) -> "InputError":
        """The same error, saying which argument named the file (kept if one is said already)."""
        if self.argument is not None:
            return self
        return InputError(self.reason, path=self.path, line=self.line, field=self.field, argument=argument)


class GeometryError(RoadgonioError):
    """The instrument geometry cannot be measured as asked (footprint off the sample,
    source below the horizon, detector that does not see the sample...). ``path`` (the instrument
    file) and ``field`` (the key to change), where the raiser knows them, lead the message as in
    :class:`InputError`."""

    def __init__(self, message: str, *, path: str | Path | None = None, field: str | None = None):
        self.path = None if path is None else str(path)
        self.field = field
        self.reason = message
        super().__init__(_located(message, path=self.path, field=field))


class BackendError(RoadgonioError):
    """A compute backend cannot run here (for example Dr.Jit's LLVM backend needs LLVM >= 16)."""


class WorkLostError(BackendError):
    """Work lost outside the user's input: a Dask worker that died on a task more often than the
    work retries it, a cluster that went away. Not bad input, so the command line exits with
    status 4 (:data:`EXIT_WORK_LOST`), not 2 (bad input) or 3 (`validate`: inconclusive); run the same
    command again (the commands with a journal resume from it)."""


#: the command line's exit status for :class:`WorkLostError` (2 is bad input, 130 an interruption)
EXIT_WORK_LOST = 4
#: the command line's exit status when the results are written but not every one was reached:
#: ``validate``'s inconclusive verdict, ``uncertainty --adaptive`` stopped at its cap, a cell ``ka``
#: could not measure
EXIT_INCONCLUSIVE = 3


class ModelWarning(UserWarning):
    """Something about an input the user should read although the work goes on (a fitted model whose
    specular peak no instrument can resolve, for instance): a Python warning in the API, printed once
    by the command line as ``roadgonio: note: <message>`` on standard error."""


class ReadingNote(ModelWarning):
    """How an input file was read, when the reader had to decide something (an RTB file's scale told
    by its q0 line): a note like any other, which the commands that list their notes in their results
    (``classify``, ``compare``) also put there."""


@contextmanager
def notes_held() -> Iterator[None]:
    """Hold the warnings (the notes) said inside the block and say them when it ends; an error in the
    block drops them, so a mistake is one line, not the notes of what was resolved before it (trial 12
    D8; the reference and alternatives of ``correct``)."""
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        yield
    for w in said:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


class StoppedByCaller(RoadgonioError):
    """Work on a Dask worker stopped at a boundary because the command that asked for it was
    interrupted (:class:`roadgonio.engines.cluster.CallerStop`): what it had written at its last
    boundary is kept (journals, a pass's state) and nothing more is written."""


class Interrupted(KeyboardInterrupt):
    """A Ctrl-C that says what the interrupted work kept: the CLI prints ``roadgonio: <note>`` and
    exits with status 130 (``note``: e.g. how many finished points a journal keeps)."""

    def __init__(self, note: str):
        super().__init__(note)
        self.note = note


def is_interrupt(err: BaseException) -> bool:
    """A Ctrl-C: a KeyboardInterrupt, or the RuntimeError Mitsuba raises when the KeyboardInterrupt
    arrives while it builds a scene (its message holds the wrapped ``KeyboardInterrupt``, e.g.
    ``[parser.cpp:...] failed to instantiate ... KeyboardInterrupt``)."""
    return isinstance(err, KeyboardInterrupt) or (isinstance(err, RuntimeError) and "KeyboardInterrupt" in str(err))


def percent(fraction: float, digits: int = 3) -> str:
    """A fraction as a percentage for messages: ``percent(0.997) == '99.7 %'`` (``:.2g`` would
    print 1e+02 %), ``percent(2e-5) == '0.00200 %'``; below 10^-digits % it says so,
    ``percent(1.3e-9) == '<0.001 %'`` (not 0.000000130 %)."""
    import math
    p = 100.0 * float(fraction)
    if not math.isfinite(p):
        return f"{p} %"
    if p == 0.0:
        return "0 %"
    floor = 10.0 ** -digits
    if abs(p) < floor:
        return f"<{floor:.{digits}f} %" if p > 0 else f">-{floor:.{digits}f} %"
    decimals = max(0, digits - 1 - int(math.floor(math.log10(abs(p))))) if abs(p) < 10 ** digits else 0
    return f"{p:.{decimals}f} %"


def count(n: int, noun: str) -> str:
    """'1 cell', '2 cells' for messages and pictures (nouns with a plain -s plural)."""
    return f"{n} {noun}" + ("" if n == 1 else "s")
