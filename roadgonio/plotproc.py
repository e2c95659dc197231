"""Draw a command's pictures in a helper process that loads matplotlib while the command computes.

Importing matplotlib and Pillow takes ~0.7 s, a quarter of a `roadgonio ka` run on the portable
preset (measured, 2-core machine); Python threads cannot hide it (imports hold the GIL), a second
process can: :class:`FigureProcess` starts ``python -m roadgonio.plotproc`` at the beginning of a
command, the child imports :mod:`roadgonio.plots` and waits; the command later asks it to run a
function of :mod:`roadgonio.plots` by name and waits for the answer, so the outputs are complete
(and grouped, :class:`roadgonio.fileio.OutputGroup`) when the command returns.

The helper is an optimisation only: if it cannot start, dies, or reports an error, the same
function runs in the command's own process (an error there is the command's error, as without the
helper). The child gets its jobs as pickles on stdin and answers on stdout; it exits when stdin
closes, so it never outlives the command.
"""
from __future__ import annotations

import os
import pickle
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

_LEN = struct.Struct("<Q")


def _send(stream, obj: Any) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_LEN.pack(len(data)) + data)
    stream.flush()


def _recv(stream) -> Any:
    head = stream.read(_LEN.size)
    if len(head) < _LEN.size:
        raise EOFError("the figure process closed its pipe")
    n = _LEN.unpack(head)[0]
    data = stream.read(n)
    if len(data) < n:
        raise EOFError("the figure process closed its pipe")
    return pickle.loads(data)


def resolve(name: str):
    """The drawing function ``name``: a function of :mod:`roadgonio.plots`, or ``"module:function"``
    in a roadgonio module (e.g. ``"roadgonio.uncertainty.report:plot_q0_s1"``)."""
    import importlib
    module, _, func = name.rpartition(":") if ":" in name else ("roadgonio.plots", ":", name)
    if module != "roadgonio" and not module.startswith("roadgonio."):
        raise ValueError(f"only roadgonio's own drawing functions run in the figure process, got {name!r}")
    return getattr(importlib.import_module(module), func)


class FigureProcess:
    """A child process ready to draw (see the module docstring). Use as a context manager, or call
    :meth:`close`. ``call(name, *args, **kwargs)`` runs the drawing function ``name`` (:func:`resolve`) there
    (or here, if the child is unavailable) and returns its result."""

    def __init__(self, enabled: bool = True):
        self.proc: subprocess.Popen | None = None
        self.fallbacks = 0
        if not enabled:
            return
        env = dict(os.environ)
        pkg_root = str(Path(__file__).resolve().parents[1])      # a source checkout works uninstalled
        env["PYTHONPATH"] = pkg_root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env.setdefault("MPLBACKEND", "Agg")
        try:
            self.proc = subprocess.Popen([sys.executable, "-m", "roadgonio.plotproc"], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)
        except OSError:
            self.proc = None

    def __enter__(self) -> "FigureProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def call(self, name: str, *args, **kwargs) -> Any:
        func = resolve(name)                  # fails here, before any work, on a wrong name
        if self.proc is not None and self.proc.poll() is None:
            try:
                _send(self.proc.stdin, (name, args, kwargs))
                status, value = _recv(self.proc.stdout)
                if status == "ok":
                    return value
            except (OSError, EOFError, pickle.PickleError):
                self.close()
        self.fallbacks += 1
        return func(*args, **kwargs)

    def close(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()
            proc.wait(timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait()
        finally:
            if proc.stdout is not None:
                proc.stdout.close()


class InProcess:
    """The same interface as :class:`FigureProcess`, drawing in this process (API callers, tests)."""

    fallbacks = 0

    def call(self, name: str, *args, **kwargs) -> Any:
        return resolve(name)(*args, **kwargs)

    def close(self) -> None:
        pass


def _serve() -> int:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import colormaps, colors  # noqa: F401  (loaded now, while the parent computes)
    from matplotlib.backends import backend_agg  # noqa: F401
    from matplotlib.figure import Figure  # noqa: F401
    from PIL import Image, ImageDraw, ImageFont  # noqa: F401
    from roadgonio import plots  # noqa: F401
    stdin = sys.stdin.buffer
    stdout = os.fdopen(os.dup(1), "wb")      # the protocol's own channel; stray prints go to stderr
    os.dup2(2, 1)
    while True:
        try:
            name, args, kwargs = _recv(stdin)
        except EOFError:
            stdout.close()
            os._exit(0)       # every answer is sent and every file closed: skip 0.2 s of interpreter teardown
        try:
            _send(stdout, ("ok", resolve(name)(*args, **kwargs)))
        except Exception as err:  # the parent redraws in its own process and reports any error itself
            _send(stdout, ("error", f"{type(err).__name__}: {err}"))


if __name__ == "__main__":
    sys.exit(_serve())
