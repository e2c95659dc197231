"""Ctrl-C and SIGTERM on the command line (:func:`roadgonio.cli.main` calls :func:`install`).

Both signals stop a command the same way: a ``KeyboardInterrupt`` in the main thread, which each
command turns into its one line saying what was kept (``on_interrupt``, or the work's own
:class:`~roadgonio.errors.Interrupted`) and exit status 130. A batch system's time limit, ``timeout``
and ``kill`` send SIGTERM: the run stops in order (journals flushed, a local Dask cluster shut down)
and resumes like one stopped by Ctrl-C (trial 12 D5: SIGTERM ended every command without a word).

Python runs a signal handler only between two bytecodes of the main thread, so a main thread
waiting in compiled code (a Mitsuba pass: Dr.Jit evaluates its kernels with the GIL released) would
hear the signal only when the wait ends, 40 s later in trial 12 (D4), silently. So the signal also
wakes a watcher thread (``signal.set_wakeup_fd``), which says at once that it was received.

Work that can stop cleanly only at a boundary (the Mitsuba engine between passes, whose state is
then saved) runs inside :func:`deferred`: there the first signal does not interrupt, it asks the
work to stop at its next boundary (:meth:`Deferred.check`, which raises the ``KeyboardInterrupt``
there); the watcher says so with the time the last stretch took, and that a second signal stops at
once. A second signal in the region stops the process at once from the watcher thread
(``os._exit(130)``, one line saying what is kept): the main thread may be waiting in compiled code
for the rest of the pass (trial 12: up to 40 s), where no exception reaches it. Nothing is lost but
the stretch under way: what the region's work writes at a boundary (the journal of the finished
cells, then the state of the others) is written inside :func:`critical`, as is every
:func:`roadgonio.fileio.atomic_write`, and the hard stop waits for that lock, so it never leaves a
file half-written nor a journal and a state of different boundaries. Outside a CLI run (the Python
API) nothing is installed and :func:`deferred` changes nothing.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator

#: The signals handled as Ctrl-C, with the name the messages give them.
SIGNALS = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}
#: A stop outside a deferred region that has not ended after this long gets its "received" line
#: (a quick stop prints only the command's own line).
QUIET_S = 0.5
#: A signal of the same kind this soon after the first is the same request, not a second one: GNU
#: ``timeout`` sends its SIGTERM to the command and then to the command's process group, so the
#: command hears it twice within microseconds (user audit, session 29: 2 of 3 runs under ``timeout``
#: stopped at once, "received again", without finishing the pass the first signal promised). A
#: person's second Ctrl-C, after reading the first one's line, comes much later.
SAME_SIGNAL_S = 0.2


class _State:
    def __init__(self) -> None:
        self.installed = False
        self.received = 0               # signals received (the watcher's count)
        self.handled = 0                # signals the handler saw in the main thread
        self.first_received: "tuple[int, float] | None" = None    # (signum, time) of the watcher's first
        self.first_handled: "tuple[int, float] | None" = None     # (signum, time) of the handler's first
        self.stop_asked = False         # a deferred region was asked to stop at its boundary
        self.region: "Deferred | None" = None
        self.done = threading.Event()   # the command ended (no late "received" line)
        self.watching = False           # the watcher thread runs (it makes the hard stop)
        self.passed_on: "Deferred | None" = None    # the region whose second signal the handler left to the watcher
        self.files = threading.RLock()  # held while files are written (critical): a hard stop waits


_S = _State()
#: per thread: a function saying whether the work's caller asked it to stop (a Dask task whose command
#: was interrupted: :class:`roadgonio.engines.cluster.CallerStop`), consulted at the boundaries
_EXTERNAL = threading.local()


@contextmanager
def external_stop(asked: Callable[..., bool]) -> Iterator[None]:
    """In this thread, :meth:`Deferred.check` also stops (raising
    :class:`~roadgonio.errors.StoppedByCaller`) when ``asked()`` is true (``asked(fresh=True)``: ask
    now, see :func:`stop_asked_by_caller`): a task on a Dask worker
    stops at its next boundary when the command on the other end was interrupted (user audit,
    session 43: `correct --scheduler` said "interrupted" and exited while its tasks went on writing
    the output folder)."""
    before = getattr(_EXTERNAL, "asked", None)
    _EXTERNAL.asked = asked
    try:
        yield
    finally:
        _EXTERNAL.asked = before


def stop_asked_by_caller(*, fresh: bool = False) -> bool:
    """The caller of this thread's work asked it to stop (:func:`external_stop`); False where no caller
    can ask (this process's own work). ``fresh``: ask now, even if the function may answer from its
    last asking (before results are written)."""
    asked = getattr(_EXTERNAL, "asked", None)
    return bool(asked is not None and asked(fresh=fresh))


class Deferred:
    """A stretch of main-thread work that stops only at its boundaries (:func:`deferred`)."""

    def __init__(self, what: str, kept: "str | Callable[[], str] | None" = None):
        self.what = what
        self.kept = kept
        self.last_s: float | None = None
        self._t = time.monotonic()

    def check(self) -> None:
        """At a boundary: raise the KeyboardInterrupt a signal asked for; else time the next stretch."""
        now = time.monotonic()
        self.last_s, self._t = now - self._t, now
        if _S.stop_asked:
            _S.stop_asked = False
            raise KeyboardInterrupt
        if stop_asked_by_caller():
            from roadgonio.errors import StoppedByCaller
            raise StoppedByCaller(f"stopped after a {self.what}: the command that asked for it was interrupted")


@contextmanager
def deferred(what: str, kept: "str | Callable[[], str] | None" = None) -> Iterator[Deferred]:
    """Defer a signal to the region's boundaries (module docstring); ``what`` names a stretch for the
    message ("pass of the Mitsuba table"), ``kept`` says what a stop at once keeps (the line of the
    second signal; a function is called then, with no file being written). Only in the main thread
    of a CLI run; elsewhere the region's :meth:`Deferred.check` times its stretches and never raises."""
    region = Deferred(what, kept)
    if not _S.installed or threading.current_thread() is not threading.main_thread() or _S.region is not None:
        yield region
        return
    _S.region = region
    try:
        yield region
    finally:
        _S.region = None


@contextmanager
def critical() -> Iterator[None]:
    """Files being written: a stop at once (a second signal in a :func:`deferred` region) waits until
    the block ends, so that no file is left half-written and files written together (a journal and
    its pass state) stay together. Re-entrant; nothing outside a CLI run (the Python API)."""
    if not _S.installed:
        yield
        return
    with _S.files:
        yield


def _repeat(first: str, signum: int) -> bool:
    """Whether a signal is the first one heard again (:data:`SAME_SIGNAL_S`), by the handler
    (``first="first_handled"``) or the watcher (``"first_received"``); the first one is recorded."""
    now = time.monotonic()
    seen = getattr(_S, first)
    if seen is None:
        setattr(_S, first, (signum, now))
        return False
    return seen[0] == signum and now - seen[1] < SAME_SIGNAL_S


def _handler(signum, frame) -> None:
    if _repeat("first_handled", signum):
        return                          # the same request twice (timeout's SIGTERM): already acted on
    _S.handled += 1
    if _S.region is not None:
        if _S.handled == 1:
            _S.stop_asked = True      # the region raises at its next boundary
            return
        if _S.watching:
            _S.passed_on = _S.region  # the watcher stops the process at once (_stop_now)
            return
    raise KeyboardInterrupt


def _say(text: str) -> None:
    try:
        os.write(sys.stderr.fileno(), f"roadgonio: {text}\n".encode())
    except (OSError, ValueError):
        pass


def _message(signum: int, count: int, region: "Deferred | None") -> str:
    """The watcher's line: the first signal in a deferred region, the second (:func:`_stop_now`), or
    a signal elsewhere."""
    name = SIGNALS.get(signum, f"signal {signum}")
    again = "Ctrl-C again" if signum == signal.SIGINT else "send it again"
    if region is not None and count == 1:
        took = f" (the last took {region.last_s:.0f} s)" if region.last_s is not None and region.last_s >= 1 else ""
        return (f"{name} received: stopping after the {region.what} under way{took}, which is saved; "
                f"{again} to stop at once, losing only that one")
    if region is not None:
        kept = region.kept() if callable(region.kept) else region.kept
        return (f"{name} received again: stopped at once, without finishing the {region.what} under way; "
                + (kept or "what the last finished one saved is kept"))
    return f"{name} received: stopping (the step under way must end first)"


def _watch(fd: int) -> None:
    while True:
        try:
            data = os.read(fd, 64)
        except OSError:
            return
        if not data:
            return
        for signum in data:
            if signum not in SIGNALS:
                continue
            if _repeat("first_received", signum):
                continue
            _S.received += 1
            region = _S.region or _S.passed_on    # (the handler may have run first, the region ended since)
            if region is not None and _S.received >= 2:
                _stop_now(signum, region)
            elif region is not None:
                _say(_message(signum, _S.received, region))
            elif not _S.done.wait(QUIET_S):
                _say(_message(signum, _S.received, None))


def _stop_now(signum: int, region: Deferred) -> None:
    """A second signal in a deferred region (the watcher thread): once no file is being written
    (:func:`critical`), say what is kept and end the process at once, exit status 130. No cleanup
    runs: the files the work wrote at its last boundary are complete, the stretch under way is lost."""
    with _S.files:
        _say(_message(signum, 2, region))
        for stream in (sys.stdout, sys.stderr):     # what the command printed before (a pipe buffers it)
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
        os._exit(130)


def install() -> None:
    """Handle SIGINT and SIGTERM as described in the module docstring (main thread only; once)."""
    if threading.current_thread() is not threading.main_thread():
        return
    if _S.installed:                    # another command in the same process (tests): a fresh count
        _S.received = _S.handled = 0
        _S.first_received = _S.first_handled = None
        _S.stop_asked = False
        _S.passed_on = None
        _S.done.clear()
        return
    r, w = os.pipe()
    os.set_blocking(w, False)
    try:
        signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    except (ValueError, OSError):
        os.close(r)
        os.close(w)
        r = -1
    for s in SIGNALS:
        if signal.getsignal(s) is not signal.SIG_IGN:     # a signal ignored by whoever started us stays so
            signal.signal(s, _handler)
    if r >= 0:
        threading.Thread(target=_watch, args=(r,), name="roadgonio-signals", daemon=True).start()
        _S.watching = True
    _S.installed = True


def finished() -> None:
    """The command ended: no late "received" line."""
    _S.done.set()
