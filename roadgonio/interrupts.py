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
there); the watcher says so with the time the last stretch took; a second signal interrupts as soon
as the main thread runs Python again, without waiting for the boundary (what was saved at the last
boundary is kept). Outside a CLI run (the Python API) nothing is
installed and :func:`deferred` changes nothing.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from contextlib import contextmanager
from typing import Iterator

#: The signals handled as Ctrl-C, with the name the messages give them.
SIGNALS = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}
#: A stop outside a deferred region that has not ended after this long gets its "received" line
#: (a quick stop prints only the command's own line).
QUIET_S = 0.5


class _State:
    def __init__(self) -> None:
        self.installed = False
        self.received = 0               # signals received (the watcher's count)
        self.handled = 0                # signals the handler saw in the main thread
        self.stop_asked = False         # a deferred region was asked to stop at its boundary
        self.region: "Deferred | None" = None
        self.done = threading.Event()   # the command ended (no late "received" line)


_S = _State()


class Deferred:
    """A stretch of main-thread work that stops only at its boundaries (:func:`deferred`)."""

    def __init__(self, what: str):
        self.what = what
        self.last_s: float | None = None
        self._t = time.monotonic()

    def check(self) -> None:
        """At a boundary: raise the KeyboardInterrupt a signal asked for; else time the next stretch."""
        now = time.monotonic()
        self.last_s, self._t = now - self._t, now
        if _S.stop_asked:
            _S.stop_asked = False
            raise KeyboardInterrupt


@contextmanager
def deferred(what: str) -> Iterator[Deferred]:
    """Defer a signal to the region's boundaries (module docstring); ``what`` names a stretch for the
    message ("pass of the Mitsuba table"). Only in the main thread of a CLI run; elsewhere the
    region's :meth:`Deferred.check` times its stretches and never raises."""
    region = Deferred(what)
    if not _S.installed or threading.current_thread() is not threading.main_thread() or _S.region is not None:
        yield region
        return
    _S.region = region
    try:
        yield region
    finally:
        _S.region = None


def _handler(signum, frame) -> None:
    _S.handled += 1
    if _S.region is not None and _S.handled == 1:
        _S.stop_asked = True          # the region raises at its next boundary
        return
    raise KeyboardInterrupt


def _say(text: str) -> None:
    try:
        os.write(sys.stderr.fileno(), f"roadgonio: {text}\n".encode())
    except (OSError, ValueError):
        pass


def _message(signum: int, count: int) -> str:
    name = SIGNALS.get(signum, f"signal {signum}")
    again = "Ctrl-C again" if signum == signal.SIGINT else "send it again"
    region = _S.region
    if region is not None and count == 1:
        took = f" (the last took {region.last_s:.0f} s)" if region.last_s is not None and region.last_s >= 1 else ""
        return (f"{name} received: finishing the current {region.what}{took} to keep it, then stopping; "
                f"{again} not to finish it (the last finished one is kept)")
    if region is not None:
        return (f"{name} received again: stopping as soon as the computation under way returns, without "
                f"finishing the {region.what} (the last finished one is kept)")
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
            _S.received += 1
            if _S.region is not None:
                _say(_message(signum, _S.received))
            elif not _S.done.wait(QUIET_S):
                _say(_message(signum, _S.received))


def install() -> None:
    """Handle SIGINT and SIGTERM as described in the module docstring (main thread only; once)."""
    if threading.current_thread() is not threading.main_thread():
        return
    if _S.installed:                    # another command in the same process (tests): a fresh count
        _S.received = _S.handled = 0
        _S.stop_asked = False
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
    _S.installed = True


def finished() -> None:
    """The command ended: no late "received" line."""
    _S.done.set()
