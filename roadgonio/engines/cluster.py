"""Dask for roadgonio: many independent k_A tables over worker processes.

Used by ``roadgonio design`` (one table per design point and sample, a few consecutive tables per
Dask task when every worker still gets enough tasks: :func:`tables_per_task`), by ``roadgonio
uncertainty`` (the exact tables of the surrogate design) and by ``roadgonio correct`` (one task per measured
table). :func:`map_calls` is the one piece of Dask plumbing: *call a module-level function for
every item, one task each, on the client's workers (or here when the client is ``None``)*, with
an optional object shipped once to every worker, results in order, progress callbacks in
completion order, cancellation on errors. The unit of work of the k_A tables is
:class:`TableTask`: *compute a k_A table for (instrument dict, model dict, cells, backend,
settings, seed)*; :func:`compute_table` does it in whatever process it runs in, :func:`map_tables`
maps it with :func:`map_calls`.

Clusters (:func:`open_client`):

* ``workers=N`` (default: the number of cores): a ``dask.distributed.LocalCluster`` of N worker
  **processes** with one thread each, on the loopback interface, no dashboard;
* ``scheduler="tcp://HOST:PORT"``: an existing cluster started with the standard commands
  (``dask scheduler`` / ``dask worker tcp://HOST:PORT --nthreads 1``); the workers must import the
  same roadgonio (same version; start them from the same environment);
* ``workers=0``: no Dask, everything in the calling process.

Mitsuba variants and Python plugins are per process (and, in some builds, per thread): every
worker sets the variant and registers the plugins itself. A :class:`EngineSetup` worker plugin
does it in the worker's task thread when the worker starts (and sets Dr.Jit's thread pool to the
worker's thread count, so N one-thread workers use N cores, not N^2 threads), and every task
checks it again (idempotent), so a worker that joins late or restarts is never left without them.

Results do not depend on where a task runs: a task carries its seed, and the backend's own
seeding is per cell (``tests/system/test_design_cluster.py`` compares a 2-worker cluster started with
``dask scheduler`` / ``dask worker`` against the in-process run, bit for bit).
"""
from __future__ import annotations

import logging
import math
import os
import socket
import sys
import threading
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

from roadgonio.errors import BackendError, InputError, RoadgonioError, WorkLostError

#: Seconds to wait for a scheduler to answer and for its first worker to join.
CONNECT_TIMEOUT_S = 30.0
#: Seconds beyond that before a connection that has not returned is given up (a service that accepts
#: and never answers).
CONNECT_GRACE_S = 5.0


@dataclass(frozen=True)
class TableTask:
    """Compute k_A at ``cells`` for one instrument and one sample model.

    ``instrument`` is :meth:`Instrument.to_dict` (with absolute file paths), ``model`` is
    :meth:`RoadModel.to_json_dict`; ``accuracy`` a preset name, ``settings`` explicit backend
    settings (they override the preset), ``seed`` the backend seed (Monte Carlo backends only).
    ``key`` is the caller's identifier, returned unchanged in the result.
    """

    instrument: Mapping[str, Any]
    model: Mapping[str, Any]
    cells: tuple[tuple[float, float], ...]
    backend: str = "mitsuba"
    accuracy: str | None = None
    settings: Mapping[str, Any] = field(default_factory=dict)
    seed: int | None = None
    instrument_path: str | None = None
    key: Any = None


@dataclass
class TableResult:
    """What :func:`compute_table` returns: the cells, or the reason it could not compute them."""

    key: Any
    cells: list                       # list[CellResult], in the order of the task's cells
    settings: dict[str, Any] = field(default_factory=dict)
    error: str | None = None          # one-line reason (RoadgonioError message) when nothing was computed
    error_kind: str | None = None     # GeometryError | InputError | BackendError | WorkerError
    seconds: float = 0.0
    worker: str = ""

    @property
    def ok(self) -> bool:
        return self.error is None


# ----------------------------------------------------------------------------------------------
# In the worker
# ----------------------------------------------------------------------------------------------

#: "module:function" preparing a worker process for a backend that needs Mitsuba (the registry's
#: ``mitsuba`` capability; lazy, so only the Mitsuba room imports mitsuba): ``function(variant,
#: render_threads)``; and the one checking (never changing) the driver's own process.
MITSUBA_SETUP = "roadgonio.engines.mitsuba.worker:prepare_process"
MITSUBA_CHECK = "roadgonio.engines.mitsuba.worker:check_process"

_READY: set[tuple[int, str, str | None]] = set()
_READY_LOCK = threading.Lock()


def _resolve(ref: str):
    import importlib
    mod, func = ref.split(":")
    return getattr(importlib.import_module(mod), func)


def init_engine(backend: str = "mitsuba", variant: str | None = None,
                render_threads: int | None = None) -> dict[str, Any]:
    """Prepare this worker process and thread for ``backend`` (Mitsuba: the variant, the plugins,
    Dr.Jit's pool); idempotent. Only for worker processes: they are entry points of their own."""
    from roadgonio.engines.registry import backend_info
    info: dict[str, Any] = {"pid": os.getpid()}
    if backend_info(backend).mitsuba:
        info.update(_resolve(MITSUBA_SETUP)(variant, render_threads))
    with _READY_LOCK:
        _READY.add((threading.get_ident(), backend, variant))
    return info


def check_engine(backend: str, variant: str | None = None) -> None:
    """In the driver's process: check (never change) what its entry point chose for ``backend``."""
    from roadgonio.engines.registry import backend_info
    if backend_info(backend).mitsuba:
        _resolve(MITSUBA_CHECK)(variant)


def _ensure_engine(backend: str, variant: str | None) -> None:
    if (threading.get_ident(), backend, variant) not in _READY:
        init_engine(backend, variant)


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def compute_table(task: TableTask, *, prepare: bool = True) -> TableResult:
    """Compute one :class:`TableTask` in this process. On a worker (``prepare=True``) the process is
    first prepared for the backend (:func:`init_engine`, idempotent); in the driver's own process
    (``prepare=False``, :func:`map_tables` without a client) it is used as its entry point set it up.
    A :class:`~roadgonio.errors.RoadgonioError` (impossible geometry, bad settings, missing backend)
    becomes the result's ``error``; anything else is a bug and propagates."""
    from roadgonio.engines.registry import backend_info, make_backend
    from roadgonio.instrument.config import Instrument
    from roadgonio.surface.model import RoadModel
    t0 = time.perf_counter()
    try:
        inst = Instrument.from_dict(task.instrument, path=task.instrument_path)
        model = RoadModel.from_json_dict(task.model)
        settings = dict(task.settings)
        seed = task.seed if (task.seed is not None and backend_info(task.backend).seeded) else None
        if prepare:
            _ensure_engine(task.backend, settings.get("mitsuba_variant"))
        backend = make_backend(task.backend, inst, model, accuracy=task.accuracy, seed=seed, settings=settings)
        cells = backend.compute([(float(t), float(b)) for t, b in task.cells])
        try:
            used = dict(backend.settings())
        except Exception:  # noqa: BLE001 - provenance only
            used = {"backend": task.backend}
        return TableResult(key=task.key, cells=list(cells), settings=used, seconds=time.perf_counter() - t0,
                           worker=_worker_name())
    except RoadgonioError as err:
        return TableResult(key=task.key, cells=[], error=str(err), error_kind=type(err).__name__,
                           seconds=time.perf_counter() - t0, worker=_worker_name())


def _worker_versions() -> dict[str, Any]:
    import roadgonio._version as version
    from roadgonio.provenance import source_digest
    return {"roadgonio": version.__version__, "pid": os.getpid(), "file": version.__file__, "source": source_digest()}


try:  # the plugin class needs distributed; roadgonio itself does not import it
    from distributed import WorkerPlugin as _WorkerPlugin
except ImportError:  # pragma: no cover
    _WorkerPlugin = object


class EngineSetup(_WorkerPlugin):
    """Worker plugin: prepare the worker for a backend when it starts (Mitsuba: set the variant,
    register the plugins and size Dr.Jit's pool, in the worker's task thread). Failures (no
    mitsuba on that worker) are kept in ``info`` and surface as the tasks' clear errors instead of
    killing the worker."""

    name = "roadgonio-engine"

    def __init__(self, backend: str = "mitsuba", variant: str | None = None, render_threads: int | None = None):
        self.backend = backend
        self.variant = variant
        self.render_threads = render_threads
        self.info: dict[str, Any] = {}

    async def setup(self, worker):
        import asyncio
        n = self.render_threads or getattr(getattr(worker, "state", None), "nthreads", None) or 1
        executor = worker.executors.get("default")
        try:
            self.info = await asyncio.get_running_loop().run_in_executor(executor, init_engine, self.backend,
                                                                         self.variant, n)
        except RoadgonioError as err:
            self.info = {"error": str(err)}


class IgnoreInterrupt(_WorkerPlugin):
    """Worker plugin of a LOCAL cluster: its worker processes ignore SIGINT. A Ctrl-C on the terminal
    reaches the whole process group; the driver stops the work and closes the cluster, and the
    workers, interrupted too, only added a KeyboardInterrupt traceback each after its one line."""

    name = "roadgonio-ignore-interrupt"

    async def setup(self, worker):
        import signal
        import threading
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)


# ----------------------------------------------------------------------------------------------
# In the caller
# ----------------------------------------------------------------------------------------------

#: What a script must do to start a local cluster (its workers are spawned processes that import
#: the script again, so an unguarded module-level call would start a cluster in every worker).
MAIN_GUARD = ('a script that starts a local Dask cluster (workers=N, or the default) must make the call under '
              '\'if __name__ == "__main__":\' (each worker process imports the script again), or pass workers=0 '
              'to compute in this process')


def _bootstrapping() -> bool:
    """True in a process that multiprocessing's spawn is still starting: it is importing the parent's
    main module (a script calling roadgonio at module level), where starting processes is forbidden.
    The same test as ``multiprocessing.spawn._check_not_importing_main``."""
    import multiprocessing
    return bool(getattr(multiprocessing.current_process(), "_inheriting", False))


def _unguarded_main_call() -> tuple[str, int] | None:
    """(script, line) when this call comes from a script's top-level code outside ``if __name__ ==
    "__main__":``, else None. A local cluster's worker processes are spawned: each runs the script
    again (as ``__mp_main__``), so an unguarded call starts there too and fails there, each worker
    printing its own traceback before the cluster gives up (trial 11 D8). Looked at before any
    process is started: the top-level frame of the ``__main__`` module on the stack, and the
    script's syntax tree for a guard around that frame's line. No judgement (None) without a
    script file (a notebook, ``python -c``), for what multiprocessing does not run again (a
    package's ``__main__.py``: ``python -m roadgonio``; the ``ipython`` script), without that frame
    (the script's code has finished: a thread, a callback) or when the file cannot be read back."""
    import ast
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if main is None or not path:
        return None
    name = getattr(getattr(main, "__spec__", None), "name", None)
    if name is not None and (name == "__main__" or name.endswith(".__main__")):
        return None
    if name is None and Path(path).stem == "ipython":
        return None
    frame, line = sys._getframe(), None
    while frame is not None:
        if frame.f_code.co_name == "<module>" and frame.f_globals is vars(main):
            line = frame.f_lineno
        frame = frame.f_back
    if line is None:
        return None
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError, ValueError):
        return None

    def is_guard(test) -> bool:
        if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
            return False
        sides = [test.left, test.comparators[0]]
        return (any(isinstance(x, ast.Name) and x.id == "__name__" for x in sides)
                and any(isinstance(x, ast.Constant) and x.value == "__main__" for x in sides))

    for node in ast.walk(tree):
        if isinstance(node, ast.If) and is_guard(node.test) and node.body:
            if node.body[0].lineno <= line <= (node.body[-1].end_lineno or node.body[-1].lineno):
                return None
    return str(path), line


#: A local cluster of more worker processes than this many a core is refused (user audit, session 43:
#: --workers 1000000 built Nanny objects for minutes without a word, then a traceback on Ctrl-C).
LOCAL_WORKERS_PER_CORE = 8


def max_local_workers() -> int:
    """The most worker processes :func:`open_client` starts on this machine."""
    return LOCAL_WORKERS_PER_CORE * (os.cpu_count() or 1)


def _check_address(address: str) -> str:
    a = str(address).strip()
    if "://" not in a:
        a = "tcp://" + a
    proto, rest = a.split("://", 1)
    host, _, port = rest.rpartition(":")
    if proto not in ("tcp", "tls", "inproc", "ws", "wss") or not host or not port.isdigit():
        raise InputError(f"expected a scheduler address tcp://HOST:PORT (as printed by 'dask scheduler'), got "
                         f"{address!r}", field="scheduler")
    if not 0 < int(port) <= 65535:
        # user audit, session 43: :99999 waited 30 s for a connection no port can take
        raise InputError(f"expected a port from 1 to 65535 in the scheduler address, got {port} in {address!r}",
                         field="scheduler")
    return a


def _connect(Client, address: str):
    """A Client of the scheduler at ``address``, or the one-line InputError naming ``--scheduler``.
    Connecting runs in a thread with a deadline: a service that is no Dask scheduler (its dashboard's
    port, a web server) can accept the connection and never answer, and Dask then waited without end;
    one that answers with something else made Dask read its bytes as a frame length and fail with a
    traceback asking for exbibytes (audit 28)."""
    box: dict[str, Any] = {}

    def run():
        try:
            box["client"] = Client(address, timeout=f"{CONNECT_TIMEOUT_S:g}s")
        except BaseException as err:  # noqa: BLE001 - reported below as the address's fault
            box["error"] = err
    t = threading.Thread(target=run, name="roadgonio-dask-connect", daemon=True)
    t.start()
    t.join(CONNECT_TIMEOUT_S + CONNECT_GRACE_S)
    hint = ("start one with 'dask scheduler' and workers with 'dask worker ADDRESS --nthreads 1', and give the "
            "address it prints (port 8786 by default; 8787 is its dashboard)")
    if t.is_alive():
        raise InputError(f"{address} did not answer as a Dask scheduler within {CONNECT_TIMEOUT_S + CONNECT_GRACE_S:g} s "
                         f"(another service, or a dashboard?); {hint}", field="scheduler")
    err = box.get("error")
    if isinstance(err, (OSError, TimeoutError)):
        raise InputError(f"cannot connect to the Dask scheduler at {address} ({err}); {hint}", field="scheduler")
    if err is not None:
        raise InputError(f"{address} is not a Dask scheduler (connecting failed with {type(err).__name__}: "
                         f"{str(err)[:100]}); {hint}", field="scheduler")
    return box["client"]


@contextmanager
def open_client(workers: int | None = None, scheduler: str | None = None, *, backend: str | None = "mitsuba",
                variant: str | None = None, quiet: bool = True) -> Iterator[Any]:
    """A Dask client for :func:`map_tables` (module docstring), closed (with its local cluster) on
    exit; yields ``None`` for ``workers=0`` (compute in this process). With ``backend`` (default
    mitsuba) every worker is prepared for it by the :class:`EngineSetup` plugin (``variant``: the
    Mitsuba variant, default ``$ROADGONIO_VARIANT`` or llvm_ad_rgb)."""
    if workers is not None and scheduler is not None:
        raise InputError("give --workers (a local cluster) or --scheduler (an existing one), not both",
                         field="workers/scheduler")
    if scheduler is None and workers == 0:
        yield None
        return
    if workers is not None and (not isinstance(workers, int) or workers < 0):
        raise InputError(f"expected a number of workers >= 0, got {workers!r}", field="workers")
    if workers is not None and workers > (most := max_local_workers()):
        raise InputError(f"expected at most {most} worker processes on this machine "
                         f"({os.cpu_count() or 1} cores; {LOCAL_WORKERS_PER_CORE} a core at most), got {workers}; "
                         "for more machines start a cluster and give --scheduler", field="workers")
    try:
        from distributed import Client, LocalCluster
    except ImportError:  # pragma: no cover
        raise BackendError("running on Dask needs the package dask[distributed] ('pip install \"dask[distributed]\"')") from None
    cluster = None
    if scheduler is not None:
        address = _check_address(scheduler)
        client = _connect(Client, address)
        try:
            client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        except (TimeoutError, OSError):
            client.close()
            raise InputError(f"no worker joined the Dask scheduler at {address} within {CONNECT_TIMEOUT_S:g} s; "
                             "start some with 'dask worker ADDRESS --nthreads 1'", field="scheduler") from None
    else:
        if _bootstrapping():
            raise InputError(MAIN_GUARD, field="workers")
        unguarded = _unguarded_main_call()
        if unguarded is not None:       # say it here, before each worker process says it in a traceback
            raise InputError(f"this call is not under 'if __name__ == \"__main__\":'; {MAIN_GUARD}",
                             path=unguarded[0], line=unguarded[1], field="workers")
        n = workers if workers is not None else (os.cpu_count() or 1)
        # no dashboard; the scheduler's HTTP server (health routes) still starts, on a free loopback
        # port instead of 8787, which another cluster may hold (Dask then warns and leaks a socket)
        try:
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                   dashboard_address=None, worker_dashboard_address=None,
                                   scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                                   silence_logs=logging.ERROR if quiet else logging.WARNING)
        except RuntimeError as err:
            if "failed to start" not in str(err):
                raise
            # the usual cause: each worker process imports the caller's script again (spawn), and
            # the script, unguarded, starts a cluster there too (which multiprocessing forbids)
            why = str(err).rstrip(".")
            raise InputError(f"the local Dask cluster's worker processes did not start ({why}); {MAIN_GUARD}",
                             field="workers") from None
        client = Client(cluster)
    try:
        _check_workers(client)
        from roadgonio.engines.registry import backend_info
        if cluster is not None:
            client.register_plugin(IgnoreInterrupt(), name=IgnoreInterrupt.name)
        if backend is not None and backend_info(backend).mitsuba:
            client.register_plugin(EngineSetup(backend, variant), name=EngineSetup.name)
    except BaseException as err:
        with _dask_logs_silenced():
            _close(client, cluster)
        from distributed.comm.core import CommClosedError
        if isinstance(err, (CommClosedError, OSError)):
            # a worker or the scheduler went away while the workers were being prepared
            raise WorkLostError(f"the Dask cluster closed a connection while its workers were being prepared ({err}); "
                               "run the same command again") from None
        raise
    try:
        yield client
    except BaseException:
        # Ctrl-C or an error: the caller says what happened; closing the cluster with tasks and
        # scattered data still on it makes Dask log "Removing worker ... lose scattered data" (ERROR)
        # after that one line, so Dask's own log is silenced while the cluster closes
        with _dask_logs_silenced():
            _close(client, cluster)
        raise
    else:
        _close(client, cluster)


def _close(client, cluster) -> None:
    client.close()
    if cluster is not None:
        cluster.close()


@contextmanager
def _dask_logs_silenced() -> Iterator[None]:
    """Dask's loggers (``distributed.*``) at CRITICAL for the block, restored after."""
    log = logging.getLogger("distributed")
    children = [logging.getLogger(n) for n in list(logging.root.manager.loggerDict) if n.startswith("distributed.")]
    saved = [(lg, lg.level) for lg in [log, *children]]
    try:
        for lg, _ in saved:
            lg.setLevel(logging.CRITICAL)
        yield
    finally:
        for lg, level in saved:
            lg.setLevel(level)


def _check_workers(client) -> None:
    import roadgonio._version as version
    found = client.run(_worker_versions)
    bad = {w: v["roadgonio"] for w, v in found.items() if v["roadgonio"] != version.__version__}
    if bad:
        raise BackendError(f"Dask workers run another roadgonio version ({', '.join(f'{w}: {v}' for w, v in bad.items())}; "
                           f"this is {version.__version__}): start the workers from the same environment")
    from roadgonio.provenance import source_digest
    mine = source_digest()
    other = sorted(w for w, v in found.items() if v.get("source") != mine)
    try:
        on_scheduler = client.run_on_scheduler(_worker_versions).get("source")
    except Exception:  # noqa: BLE001 - a scheduler that cannot import roadgonio only relays tasks
        on_scheduler = mine
    if other or on_scheduler != mine:
        who = (["the scheduler"] if on_scheduler != mine else []) + other
        raise BackendError(f"the Dask cluster runs other roadgonio source than this process ({', '.join(who)}: the code "
                           "was changed or upgraded after they started): restart the scheduler and the workers")


def describe(client) -> dict[str, Any]:
    """Scheduler address, number of workers and threads (for provenance and summaries)."""
    if client is None:
        return {"mode": "in-process", "workers": 0, "threads": 1}
    info = client.scheduler_info()
    ws = info.get("workers", {})
    return {"mode": "dask", "scheduler": info.get("address"), "workers": len(ws),
            "threads": int(sum(w.get("nthreads", 0) for w in ws.values()))}


#: Seconds between two looks at the cluster's workers while tasks are pending (:class:`WorkerWatch`).
WATCH_INTERVAL_S = 10.0
#: times :func:`map_calls` submits a task again whose scattered input died with its worker
TASK_RETRIES = 2


class WorkerWatch:
    """Says once (on stderr, through ``say``) when the cluster has no worker left while tasks wait,
    and once more when workers are back: Dask then waits silently for a worker, which a user cannot
    tell from a slow table (with no progress bar, not on a terminal). Looks every ``interval`` s in a
    daemon thread; :meth:`check` is one look (tested alone)."""

    def __init__(self, client, say: Callable[[str], None] | None = None, interval: float = WATCH_INTERVAL_S):
        self.client = client
        self.say = say or (lambda text: print(text, file=sys.stderr, flush=True))
        self.interval = float(interval)
        self.waiting = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def check(self) -> None:
        try:
            n = len(self.client.scheduler_info().get("workers", {}))
        except Exception:  # noqa: BLE001 - a closed scheduler is the caller's error to report
            return
        if n == 0 and not self.waiting:
            address = getattr(self.client, "scheduler", None)
            address = getattr(address, "address", None) or "the scheduler"
            self.say(f"roadgonio: no Dask worker left on {address}: waiting for one (start one with 'dask worker "
                     f"{address} --nthreads 1'; Ctrl-C stops, finished work is kept)")
            self.waiting = True
        elif n > 0 and self.waiting:
            self.say(f"roadgonio: {n} Dask worker{'s' if n != 1 else ''} back; going on")
            self.waiting = False

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self.check()

    def start(self) -> "WorkerWatch":
        self._thread = threading.Thread(target=self._run, name="roadgonio-worker-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()


#: A task asks the scheduler whether its caller stopped at most this often (each asking is a round trip)
STOP_POLL_S = 0.5


class CallerStop:
    """Whether the command that submitted a task of :func:`map_calls` stopped early (interrupted, or
    failed) and cancelled its work: the Dask Event ``name`` that map_calls then sets. Dask cannot stop
    a task that is running, and on an existing cluster (``--scheduler``) the workers outlive the
    command, so a task asks this, through :func:`roadgonio.interrupts.external_stop`, at its boundaries
    (:meth:`roadgonio.interrupts.Deferred.check`) and, afresh, before it writes results
    (``correct``'s). Between boundaries it asks the scheduler at most every :data:`STOP_POLL_S`
    (``fresh``: ask anyway)."""

    def __init__(self, name: str):
        self.name = name
        self.asked_at = -math.inf

    def __call__(self, *, fresh: bool = False) -> bool:
        now = time.monotonic()
        if not fresh and now - self.asked_at < STOP_POLL_S:
            return False                  # asked a moment ago (a pass of a small table is ~10 ms)
        self.asked_at = now
        try:
            from distributed import Event, get_client
            return bool(Event(self.name, client=get_client()).is_set())
        except Exception:  # noqa: BLE001 - no scheduler to ask: the task goes on as before
            return False


def _call_task(item: Any, *, call: Callable, shared: Any = None, with_shared: bool = False,
               backend: str | None = None, variant: str | None = None, stop_event: str | None = None) -> Any:
    """One task of :func:`map_calls` on a worker: prepare the process for ``backend`` (idempotent),
    then ``call(item)`` or ``call(item, shared)``, stopping at a boundary when ``stop_event`` is set
    (:class:`CallerStop`)."""
    from roadgonio.interrupts import external_stop
    if backend is not None:
        _ensure_engine(backend, variant)
    if stop_event is None:
        return call(item, shared) if with_shared else call(item)
    with external_stop(CallerStop(stop_event)):
        return call(item, shared) if with_shared else call(item)


_NO_SHARED = object()


def scatter_shared(client, shared: Any):
    """``shared`` scattered to every worker (``broadcast``), as one future. With no worker running
    (the last one died, a new one not yet up) Dask's scatter gives up after its connect timeout
    ("No valid workers found"; trial 9: `intercompare --scheduler` then crashed with a traceback
    while a new worker was starting): this waits for a worker, as the tasks do, for as long as it
    takes (:class:`WorkerWatch` says so; Ctrl-C stops)."""
    while True:
        try:
            client.wait_for_workers(1)
            # a list of one: scatter() would scatter a dict or a list element by element
            return client.scatter([shared], broadcast=True, hash=False)[0]
        except (TimeoutError, ValueError) as err:
            if "No valid workers" not in str(err):
                raise


def map_calls(func: Callable, items: Sequence[Any], client=None, *, shared: Any = _NO_SHARED,
              backend: str | None = None, variant: str | None = None,
              on_result: Callable[[int, Any], None] | None = None,
              on_lost: Callable[[int, BaseException], Any] | None = None, name: str = "call",
              retries: int = TASK_RETRIES, say: Callable[[str], None] | None = None) -> list[Any]:
    """``func(item)`` for every item, one Dask task per item on the client's workers (or one after
    the other in this process when ``client`` is None); returns the results in the order of
    ``items`` and calls ``on_result(index, result)`` as each one finishes (completion order).

    * ``func`` must be importable by the workers (a module-level function of roadgonio), ``items``
      and the results picklable.
    * ``shared``: one object every call needs (``func(item, shared)``), shipped once: scattered to
      every worker (``broadcast``) instead of pickled into each task.
    * ``backend`` / ``variant``: on a worker each task first prepares its process for that backend
      (:func:`init_engine`: the Mitsuba variant and plugins; idempotent). In this process nothing
      is prepared (its entry point chose the variant).
    * A worker that dies on a task: Dask computes it again on another (or the restarted) worker;
      when the task's scattered input died with the worker (Dask then forgets the task), it is
      submitted again with its input scattered again, up to ``retries`` times, saying so through
      ``say`` (stderr). Beyond that (or on Dask's KilledWorker, after Dask's own retries)
      ``on_lost(index, error)`` gives that item's result, or without ``on_lost`` a
      :class:`~roadgonio.errors.WorkLostError` is raised (exit status 4). An exception raised by
      ``func`` is raised here (the first one to finish). Unfinished tasks are cancelled when this
      returns or raises (Ctrl-C).
    """
    items = list(items)
    with_shared = shared is not _NO_SHARED
    if client is None:
        out = []
        for i, item in enumerate(items):
            r = func(item, shared) if with_shared else func(item)
            if on_result is not None:
                on_result(i, r)
            out.append(r)
        return out
    from distributed import KilledWorker, as_completed
    from distributed.client import FutureCancelledError
    from distributed.comm.core import CommClosedError
    if not items:
        return []
    say = say or (lambda text: print(text, file=sys.stderr, flush=True))
    token = uuid.uuid4().hex[:12]
    keys = [f"roadgonio-{name}-{token}-{i}" for i in range(len(items))]

    def scatter():
        return scatter_shared(client, shared) if with_shared else None

    shared_future = scatter()

    stop_event = f"roadgonio-stop-{token}"

    def submit(i: int, key: str):
        return client.submit(_call_task, items[i], key=key, pure=False, call=func, shared=shared_future,
                             with_shared=with_shared, backend=backend, variant=variant, stop_event=stop_event)

    futures = [submit(i, keys[i]) for i in range(len(items))]
    index = {f.key: i for i, f in enumerate(futures)}
    live = list(futures)
    attempts = [0] * len(items)
    results: list[Any] = [None] * len(items)
    watch = WorkerWatch(client, say=say).start()
    try:
        done = as_completed(futures)
        for fut in done:
            i = index[fut.key]
            try:
                r = fut.result()
            except (KilledWorker, CommClosedError, FutureCancelledError) as err:
                # FutureCancelledError: the task's input scattered to a worker that died went with it
                # (Dask cannot recompute scattered data), so the scheduler forgot the task; the task
                # is submitted again (its input scattered again) up to ``retries`` times. KilledWorker:
                # Dask itself already retried a task whose workers kept dying
                fut.release()
                if not isinstance(err, KilledWorker) and attempts[i] < retries:
                    attempts[i] += 1
                    say(f"roadgonio: {name} {i + 1} of {len(items)} was lost with a Dask worker that died; computing "
                        f"it again (retry {attempts[i]} of {retries})")
                    if with_shared and shared_future.status != "finished":
                        shared_future.release()
                        shared_future = scatter()
                    again = submit(i, f"{keys[i]}-retry{attempts[i]}")
                    index[again.key] = i
                    live.append(again)
                    done.add(again)
                    continue
                if on_lost is None:
                    raise WorkLostError(f"a Dask worker died computing {name} {i + 1} of {len(items)} ({err}); run "
                                        "the same command again (finished work is kept)") from None
                r = on_lost(i, err)
            results[i] = r
            fut.release()
            if on_result is not None:
                on_result(i, r)
    finally:
        watch.stop()
        pending = [f for f in live if not f.done()]
        if pending:
            # the running ones stop at their next boundary (Dask cancels only those not yet started)
            try:
                from distributed import Event
                Event(stop_event, client=client).set()
            except Exception:  # noqa: BLE001 - a scheduler gone: its workers went with it or will not write
                pass
            client.cancel(pending)
        if shared_future is not None:
            shared_future.release()
    return results


#: Tables per Dask task at most (:func:`tables_per_task`): a portable table at default accuracy is
#: ~0.07-0.09 s of one core, and each task costs the scheduler, the driver and the other worker a few
#: ms of the same two cores; bench/bench_design.py measured 1.66-2.05x from 1 to 2 workers with one
#: table per task and 2.03x twice with three (session 38, docs/benchmarks.md).
TABLES_PER_TASK_MAX = 4
#: Tasks per worker at least, so that the tables still balance over the workers (the last task of
#: one worker is then at most ~1/8 of its share).
TASKS_PER_WORKER_MIN = 8


def tables_per_task(n_tables: int, n_workers: int) -> int:
    """How many tables one Dask task computes: ``n_tables // (TASKS_PER_WORKER_MIN * n_workers)``,
    between 1 and :data:`TABLES_PER_TASK_MAX` (60 tables on 2 workers: 3 a task; 10 tables: 1)."""
    per = int(n_tables) // (TASKS_PER_WORKER_MIN * max(int(n_workers), 1))
    return max(1, min(TABLES_PER_TASK_MAX, per))


def compute_tables(tasks: Sequence[TableTask], *, prepare: bool = True) -> list[TableResult]:
    """:func:`compute_table` of each task, one after the other (one Dask task of several tables)."""
    return [compute_table(t, prepare=prepare) for t in tasks]


def _n_workers(client) -> int:
    try:
        return max(1, len(client.scheduler_info().get("workers", {})))
    except Exception:  # noqa: BLE001 - a count for the chunk size only
        return 1


def map_tables(tasks: Sequence[TableTask], client=None, *,
               on_result: Callable[[TableResult], None] | None = None) -> list[TableResult]:
    """Compute every task (on the client's workers, or here if ``client`` is None); returns the
    results in the order of ``tasks`` and calls ``on_result`` as each one finishes (in completion
    order). A worker that dies on a task gives that task ``error_kind = "WorkerError"``; exceptions
    that are not a RoadgonioError (bugs) are raised here. Unfinished tasks are cancelled when this
    returns or raises (Ctrl-C). (:func:`map_calls` of :func:`compute_tables`: on a cluster, a Dask
    task computes :func:`tables_per_task` consecutive tables, and their results arrive together.)"""
    tasks = list(tasks)
    if client is None:
        func = partial(compute_table, prepare=False)   # it uses what the entry point chose
        return map_calls(func, tasks, None, name="table",
                         on_result=None if on_result is None else (lambda i, r: on_result(r)))
    per = tables_per_task(len(tasks), _n_workers(client))
    chunks = [tasks[i:i + per] for i in range(0, len(tasks), per)]

    def lost(c: int, err: BaseException) -> list[TableResult]:
        return [TableResult(key=t.key, cells=[], error=f"a Dask worker died computing this table ({err})",
                            error_kind="WorkerError") for t in chunks[c]]

    def arrived(c: int, rs: list[TableResult]) -> None:
        for r in rs:
            on_result(r)
    # compute_tables prepares a worker's process itself (compute_table's prepare=True)
    out = map_calls(compute_tables, chunks, client, on_lost=lost, name="table" if per == 1 else "group of tables",
                    on_result=None if on_result is None else arrived)
    return [r for rs in out for r in rs]


def absolute_instrument_dict(instrument) -> dict[str, Any]:
    """``instrument.to_dict()`` with the sample mesh and an XML scene as absolute paths, so a
    worker in another folder (or on another machine with the same files) reads the same files."""
    d = instrument.to_dict()
    smp = d.get("sample", {})
    if smp.get("mesh"):
        smp["mesh"] = str(Path(smp["mesh"]).resolve())
    scene = d.get("scene")
    if isinstance(scene, dict) and scene.get("xml"):
        xml = Path(scene["xml"])
        if not xml.is_absolute() and instrument.path is not None:
            xml = Path(instrument.path).parent / xml
        d["scene"] = {**scene, "xml": str(xml.resolve())}
    return d


def seeds_for(seed: int, n: int) -> list[int]:
    """``n`` backend seeds in the full range 0 ... 2^63 - 1, the k-th :func:`roadgonio.seeds.point_seed`
    (seed, k): it depends only on (seed, k), never on the number of workers or the order in which
    tasks finish; two different root seeds never give point k the same seed, and no two points of
    one root share one."""
    from roadgonio.seeds import point_seed
    return [point_seed(seed, k) for k in range(int(n))]

