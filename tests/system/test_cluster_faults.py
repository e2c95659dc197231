"""A Dask worker that dies on a task: the task gets ``error_kind = "WorkerError"`` (never a hang or
a traceback), the other tasks finish, and `design` reports the point as failed with a retry hint."""
from __future__ import annotations

import textwrap
from pathlib import Path
import time

import numpy as np
import pytest

from roadgonio.errors import InputError


CRASH_MODULE = textwrap.dedent('''
    """Test helper installed in the Dask workers: a backend that kills its process."""
    import os

    import dataclasses

    from roadgonio.engines.registry import BACKENDS

    BACKENDS["crash-worker"] = dataclasses.replace(BACKENDS["quadrature"], name="crash-worker",
                                                   factory="rg_crash_backend:make_backend")


    def make_backend(*args, **kwargs):
        os._exit(7)
''')


@pytest.mark.timeout(300)
def test_dead_worker_is_a_worker_error_and_the_rest_finishes(tmp_path):
    import dask

    from roadgonio.engines import cluster
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.model import RoadModel
    (tmp_path / "rg_crash_backend.py").write_text(CRASH_MODULE)
    inst = cluster.absolute_instrument_dict(load_instrument("lab"))
    model = RoadModel.lambert().to_json_dict()
    cells = ((1.0, 0.0), (2.0, 30.0))
    tasks = [cluster.TableTask(instrument=inst, model=model, cells=cells, backend="quadrature", key="before"),
             cluster.TableTask(instrument=inst, model=model, cells=cells, backend="crash-worker", key="crash"),
             cluster.TableTask(instrument=inst, model=model, cells=cells, backend="quadrature", key="after")]
    here = cluster.map_tables([tasks[0]], None)[0]
    # one failure is enough for Dask to give up on a task (the default retries it on 3 workers)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        with cluster.open_client(workers=2, backend=None) as client:
            client.run(exec, f"import sys; sys.path.insert(0, {str(tmp_path)!r}); import rg_crash_backend")
            results = cluster.map_tables(tasks, client)
    by_key = {r.key: r for r in results}
    assert [r.key for r in results] == ["before", "crash", "after"]          # the order of the tasks
    crash = by_key["crash"]
    assert not crash.ok and crash.error_kind == "WorkerError" and "worker died" in crash.error
    for k in ("before", "after"):
        r = by_key[k]
        assert r.ok, r.error
        assert np.array_equal([c.k_a for c in r.cells], [c.k_a for c in here.cells])   # deterministic backend


@pytest.mark.timeout(300)
def test_tables_grouped_per_task_keep_order_and_a_dead_worker_loses_only_its_group(tmp_path):
    """With many tables per worker a Dask task computes several (``tables_per_task``): the results
    are those of the in-process run, in the order of the tasks; a worker dying on one table loses the
    tables of its group (each a WorkerError, to be computed again), whole groups only (with
    allowed-failures 0 Dask also fails a group it had queued on that worker), the rest finish."""
    import dask

    from roadgonio.engines import cluster
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.model import RoadModel
    (tmp_path / "rg_crash_backend.py").write_text(CRASH_MODULE)
    inst = cluster.absolute_instrument_dict(load_instrument("lab"))
    model = RoadModel.lambert().to_json_dict()
    n = 2 * cluster.TASKS_PER_WORKER_MIN * 2 + 1                 # 33 tables on 2 workers: 2 a task
    per = cluster.tables_per_task(n, 2)
    assert per == 2
    crash_at = 7                                               # the second table of the group (6, 7)
    tasks = [cluster.TableTask(instrument=inst, model=model, cells=((1.0 + 0.1 * k, 0.0),),
                               backend="crash-worker" if k == crash_at else "quadrature", key=k) for k in range(n)]
    here = cluster.map_tables([t for t in tasks if t.key != crash_at], None)
    arrived = []
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        with cluster.open_client(workers=2, backend=None) as client:
            client.run(exec, f"import sys; sys.path.insert(0, {str(tmp_path)!r}); import rg_crash_backend")
            results = cluster.map_tables(tasks, client, on_result=arrived.append)
    assert [r.key for r in results] == list(range(n))
    assert sorted(r.key for r in arrived) == list(range(n))     # every table reported once
    lost = {r.key for r in results if not r.ok}
    assert {6, 7} <= lost and len(lost) <= 3 * per, lost
    assert all({k - k % per, k - k % per + 1} <= lost for k in lost if k < n - 1), lost    # whole groups
    assert all(r.error_kind == "WorkerError" for r in results if not r.ok)
    ok = [r for r in results if r.ok]
    ref = {r.key: r for r in here}
    assert len(ok) >= n - 3 * per
    for a in ok:
        assert [c.k_a for c in a.cells] == [c.k_a for c in ref[a.key].cells]          # deterministic backend


def test_design_reports_a_worker_error_as_failed_with_a_retry_hint(tmp_path, monkeypatch):
    """The design room's handling of a WorkerError result: the point is 'failed' (not infeasible,
    not a backend refusal), the reason says to run again, and nothing is journalled for it, so
    the next run computes it."""
    from roadgonio import design_study as run_design
    from roadgonio.engines import cluster

    real = cluster.map_tables
    calls = {"n": 0}

    def flaky(tasks, client=None, *, on_result=None):
        tasks = list(tasks)
        first, rest = tasks[0], tasks[1:]
        calls["n"] += 1
        if calls["n"] == 1:
            dead = cluster.TableResult(key=first.key, cells=[], error="a Dask worker died computing this table (test)",
                                       error_kind="WorkerError")
            if on_result is not None:
                on_result(dead)
            return [dead] + real(rest, client, on_result=on_result)
        return real(tasks, client, on_result=on_result)

    monkeypatch.setattr(cluster, "map_tables", flaky)
    kw = dict(samples=["lambert"], cells="1:0,2:30", backend="quadrature", progress=False, plots=False, workers=0,
              out=tmp_path / "d")
    ds = run_design("lab", ["source.radius_m=0.002,0.004"], **kw)
    reasons = [str(r) for r in ds["reason"].values]
    assert any("worker died" in r and "again" in r for r in reasons), reasons
    assert int(np.isfinite(ds["k_a"].values).sum()) == 2          # the other point's two cells
    ds2 = run_design("lab", ["source.radius_m=0.002,0.004"], **kw)   # resume: the failed point is computed now
    assert int(np.isfinite(ds2["k_a"].values).sum()) == 4
    assert not any("worker died" in str(r) for r in ds2["reason"].values)


SCRIPT_CALL = ('rg.design_study("lab", ["source.radius_m=0.002,0.004"], "lambert", cells="1:0", backend="quadrature", '
               'workers=1, progress=False, plots=False)')
STUDY = """[study]
surface = "lambert"
realisations = 2
[[participant]]
name = "A"
instrument = "collimated"
noise_rel = 0.01
[[participant]]
name = "B"
instrument = "collimated"
noise_rel = 0.01
"""


@pytest.mark.timeout(300)
@pytest.mark.parametrize("guarded, call", [(False, "design"), (False, "intercompare"), (True, "design")])
def test_a_script_starting_a_local_cluster_needs_the_main_guard(tmp_path, guarded, call):
    """A script calling the API with workers=N at module level (the docs' snippet as first
    written): each spawned worker imports the script again and would start its own cluster. Before:
    ~60 lines of multiprocessing and Dask tracebacks ending in 'RuntimeError: Nanny failed to
    start'. Now the error's last line is the InputError that names the guard, and the guarded
    script runs."""
    import subprocess
    import sys
    body = f"import roadgonio.api as rg\nds = {SCRIPT_CALL}\nprint('k_a', float(ds['k_a'].max()))\n"
    if call == "intercompare":                # the docs' snippet (docs/intercomparison.md)
        (tmp_path / "study.toml").write_text(STUDY)
        body = 'import roadgonio.api as rg\nrun = rg.intercompare("study.toml", "out", workers=1)\n'
    if guarded:
        body = 'if __name__ == "__main__":\n' + textwrap.indent(body, "    ")
    (tmp_path / "script.py").write_text(body)
    r = subprocess.run([sys.executable, "script.py"], cwd=tmp_path, capture_output=True, text=True, timeout=240)
    if guarded:
        assert r.returncode == 0, r.stderr
        assert r.stdout.startswith("k_a 1.0")              # Lambert sample: k_A = 1
        return
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 1 and last.startswith("roadgonio.errors.InputError: "), r.stderr
    assert "script.py:2, field 'workers': " in last, last
    assert "if __name__ == \"__main__\":" in last and "workers=0" in last
    assert "An attempt has been made to start a new process" not in r.stderr     # the children stop first
    assert r.stderr.count("Traceback") == 1, r.stderr       # no worker started (trial 11 D8)


@pytest.mark.timeout(300)
def test_ctrl_c_with_scattered_data_closes_the_cluster_quietly(capfd):
    """Ctrl-C while a local cluster holds scattered data and runs a task: the caller's one line is
    the last word (before: Dask logged 'Removing worker ... lose scattered data' at ERROR after
    it); the workers ignore SIGINT (a terminal's Ctrl-C reaches them too; before: a
    KeyboardInterrupt traceback from each); Dask's log levels are restored afterwards."""
    import logging
    import os
    import signal
    import time

    from roadgonio.engines import cluster
    before = logging.getLogger("distributed.scheduler").level
    with pytest.raises(KeyboardInterrupt):
        with cluster.open_client(workers=1, backend=None) as client:
            client.scatter([np.zeros(1000)], broadcast=True, hash=False)
            for pid in client.run(os.getpid).values():       # the terminal's Ctrl-C reaches the workers too
                os.kill(pid, signal.SIGINT)
            time.sleep(3.0)                                   # (an idle worker died of it within a second)
            raise KeyboardInterrupt
    err = capfd.readouterr().err
    assert "lose scattered data" not in err and "ERROR" not in err and "Traceback" not in err, err
    assert logging.getLogger("distributed.scheduler").level == before


KILL_MODULE = textwrap.dedent('''
    """Test helper installed in the Dask workers: a task function that kills its process."""
    import os


    def die(item, shared):
        os._exit(7)
''')


DIE_ONCE_MODULE = textwrap.dedent('''
    """Test helper installed in the Dask workers: a task that kills its process the first time it
    sees an item (a marker file remembers), and computes the second time."""
    import os
    from pathlib import Path

    MARKERS = Path(__file__).parent / "markers"


    def die_once(item, shared):
        marker = MARKERS / f"died-{item}"
        if not marker.exists():
            marker.touch()
            os._exit(7)
        return item * 10 + float(shared.sum())
''')


def _with_module(tmp_path, name, text, client):
    """``name`` importable here and in the workers (the restarted ones too: a spawned worker gets
    this process's sys.path)."""
    import importlib
    import sys
    (tmp_path / f"{name}.py").write_text(text)
    sys.path.insert(0, str(tmp_path))
    client.run(exec, f"import sys; sys.path.insert(0, {str(tmp_path)!r})")
    return importlib.import_module(name)


@pytest.mark.timeout(300)
def test_a_worker_dying_with_the_scattered_input_is_computed_again():
    """A task whose shared input was scattered to a worker that then dies: Dask cannot recompute
    scattered data and forgets the task ('already forgotten'); the client got a
    FutureCancelledError traceback (trial 8, `correct --scheduler`), then stopped the whole run
    (trial 9, `intercompare --scheduler`, exit 2 as if the input were bad) while the nanny had the
    worker back within a second. The task is now submitted again with its input scattered again,
    saying so, and the results are those of an undisturbed run."""
    import sys
    import tempfile
    from pathlib import Path

    from roadgonio.engines import cluster
    shared = np.arange(4.0)
    said: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        (tmp_path / "markers").mkdir()
        try:
            with cluster.open_client(workers=1, backend=None) as client:
                mod = _with_module(tmp_path, "rg_die_once", DIE_ONCE_MODULE, client)
                got = cluster.map_calls(mod.die_once, [1, 2], client, shared=shared, name="item", say=said.append)
        finally:
            sys.path.remove(str(tmp_path))
            sys.modules.pop("rg_die_once", None)
        assert sorted(p.name for p in (tmp_path / "markers").iterdir()) == ["died-1", "died-2"]  # both died once
    assert got == [10 + 6.0, 20 + 6.0]
    # item 2's task is lost with item 1's death too (one worker, one scattered input), so it may
    # take a second round; never more, since each item dies once
    retries = [s for s in said if "died" in s]
    assert retries and all("computing it again (retry " in s and s.endswith(" of 2)") for s in retries), said


@pytest.mark.timeout(300)
def test_a_task_whose_worker_always_dies_is_work_lost_after_its_retries(tmp_path):
    """A task that kills every worker it runs on: after ``TASK_RETRIES`` retries one line that says
    to run the command again, a WorkLostError (exit status 4, not 2: it is not bad input; 3 is validate's inconclusive)."""
    import sys

    from roadgonio.engines import cluster
    from roadgonio.errors import WorkLostError
    said: list[str] = []
    try:
        with cluster.open_client(workers=1, backend=None) as client:
            mod = _with_module(tmp_path, "rg_kill_task", KILL_MODULE, client)
            with pytest.raises(WorkLostError, match="run the same command again"):
                cluster.map_calls(mod.die, [1], client, shared=np.zeros(1000), name="kill", say=said.append)
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("rg_kill_task", None)
    assert [s for s in said if "died" in s][-1].endswith(f"(retry {cluster.TASK_RETRIES} of {cluster.TASK_RETRIES})")


def test_work_lost_exits_with_status_4_and_bad_input_with_2(monkeypatch, capsys):
    """The command line tells the two apart (scripts retry the one and fix the other)."""
    from roadgonio import api
    from roadgonio.cli import main
    from roadgonio.errors import InputError, WorkLostError

    def lost():
        raise WorkLostError("a Dask worker died computing table 1 of 1; run the same command again")
    monkeypatch.setattr(api, "list_tables", lost)
    assert main(["tables"]) == 4
    assert capsys.readouterr().err.strip() == ("roadgonio: error: a Dask worker died computing table 1 of 1; "
                                               "run the same command again")

    def bad():
        raise InputError("expected something else", field="x")
    monkeypatch.setattr(api, "list_tables", bad)
    assert main(["tables"]) == 2


@pytest.mark.timeout(300)
def test_the_last_worker_gone_is_said_once_and_its_return_too():
    """With no worker left Dask waits silently for one (trial 8: `design --scheduler` waited over a
    minute without a word after its only worker was killed): the watch says so once, not at every
    look, and says when workers are back; with workers it says nothing."""
    import time

    from roadgonio.engines import cluster
    said: list[str] = []
    with cluster.open_client(workers=1, backend=None) as client:
        watch = cluster.WorkerWatch(client, say=said.append)
        watch.check()
        assert said == []
        client.retire_workers(list(client.scheduler_info()["workers"]))
        t0 = time.monotonic()
        while client.scheduler_info()["workers"] and time.monotonic() - t0 < 30:
            time.sleep(0.2)
        watch.check()
        watch.check()
        assert len(said) == 1 and "no Dask worker left" in said[0] and "dask worker" in said[0]

    class Back:                                  # the scheduler answers with a worker again
        def scheduler_info(self):
            return {"workers": {"w": {}}}
    watch.client = Back()
    watch.check()
    assert len(said) == 2 and "back" in said[1]


def _pretend_other_source():
    import roadgonio.provenance as p
    p._SOURCE_DIGEST = "0123456789abcdef"


@pytest.mark.timeout(300)
def test_workers_running_other_source_are_refused_in_one_line():
    """A cluster started before the code changed (same version string, other source) gave a
    KeyError or Dask's 'different environments' traceback mid-run (trial 8, defect 4): the workers'
    source digest is checked with the version, and a mismatch is one line saying to restart them."""
    from roadgonio.engines import cluster
    from roadgonio.errors import BackendError
    with cluster.open_client(workers=1, backend=None) as client:
        cluster._check_workers(client)                       # the same source: accepted
        client.run(_pretend_other_source)
        with pytest.raises(BackendError, match="restart the scheduler and the workers") as err:
            cluster._check_workers(client)
        assert "\n" not in str(err.value)


def test_scattering_the_shared_input_waits_for_a_worker():
    """With no worker running, Dask's scatter gives up after its connect timeout ('No valid workers
    found'), and `intercompare --scheduler` crashed with that traceback when its retry re-scattered
    the shared input while a new worker was starting (trial 9, D9). The scatter now waits for a
    worker as the tasks do; any other error is raised."""
    from roadgonio.engines.cluster import scatter_shared

    class Client:
        def __init__(self, failures):
            self.failures = list(failures)
            self.waits = self.scatters = 0

        def wait_for_workers(self, n):
            assert n == 1
            self.waits += 1

        def scatter(self, data, broadcast, hash):
            assert broadcast and not hash and len(data) == 1
            self.scatters += 1
            if self.failures:
                raise self.failures.pop(0)
            return ["future of " + data[0]]

    c = Client([TimeoutError("No valid workers found"), ValueError("No valid workers found")])
    assert scatter_shared(c, "shared") == "future of shared"
    assert c.scatters == 3 and c.waits == 3
    with pytest.raises(ValueError, match="something else"):
        scatter_shared(Client([ValueError("something else")]), "shared")


PROBE_NOT_DASK = textwrap.dedent('''
    """Serve PORT with a service that is no Dask scheduler and connect roadgonio to it (in a process of
    its own: the connection given up lives on in a daemon thread)."""
    import socket, sys, threading, time
    from roadgonio.engines import cluster
    from roadgonio.errors import InputError
    reply = sys.argv[1].encode() if len(sys.argv) > 1 else None
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    held = []

    def serve():
        while True:
            conn, _ = srv.accept()
            held.append(conn)
            if reply is not None:
                conn.sendall(reply)
    threading.Thread(target=serve, daemon=True).start()
    cluster.CONNECT_TIMEOUT_S = 2.0
    cluster.CONNECT_GRACE_S = 2.0
    t0 = time.perf_counter()
    try:
        with cluster.open_client(scheduler=f"tcp://127.0.0.1:{srv.getsockname()[1]}"):
            print("CONNECTED")
    except InputError as err:
        print(f"FIELD={err.field} SECONDS={time.perf_counter() - t0:.1f} {err}")
''')


@pytest.mark.parametrize("reply", [None, "HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n"])
def test_an_address_that_is_no_dask_scheduler_is_one_line_naming_scheduler(tmp_path, reply):
    """(audit 28) --scheduler at a service that is no Dask scheduler: one that accepts and never
    answers (the dashboard's port, a web server) made Dask wait without end; one that answers read its
    bytes as a frame length and failed with a traceback allocating 3 EiB. Both are one InputError
    naming the scheduler now, within the connect timeout and its grace."""
    import subprocess
    import sys
    script = tmp_path / "probe.py"
    script.write_text(PROBE_NOT_DASK)
    out = subprocess.run([sys.executable, str(script), *([reply] if reply else [])], capture_output=True, text=True,
                         timeout=120)
    assert out.stdout.startswith("FIELD=scheduler"), (out.stdout, out.stderr[-2000:])
    assert "8786" in out.stdout and float(out.stdout.split("SECONDS=")[1].split()[0]) < 30.0


def test_out_of_range_workers_and_ports_are_one_line_at_once(tmp_path, monkeypatch, capsys):
    """(User audit, session 43) --workers 1000000 built Nanny objects for minutes without a word
    (a traceback on Ctrl-C); --scheduler tcp://127.0.0.1:99999 waited 30 s for a port that cannot
    exist. Both are exit 2 with one line naming the option, before anything starts or is written."""
    from roadgonio.cli import main
    from roadgonio.engines import cluster
    base = ["design", "--instrument", "portable", "--sample", "R3", "--cells", "12:0",
            "--vary", "source.radius_m=0.005,0.01", "--backend", "quadrature", "-q"]
    for extra, words in ((["--workers", str(cluster.max_local_workers() + 1)], "--workers"),
                         (["--scheduler", "tcp://127.0.0.1:99999"], "65535")):
        out = tmp_path / extra[0].strip("-")
        t0 = time.perf_counter()
        try:
            rc = main(base + extra + ["--out", str(out)])
        except SystemExit as e:                  # argparse's own exit
            rc = e.code
        err = capsys.readouterr().err.strip()
        assert rc == 2 and words in err and "\n" not in err, err
        assert time.perf_counter() - t0 < 10.0 and not out.exists()
    with pytest.raises(InputError, match="at most"):
        with cluster.open_client(workers=cluster.max_local_workers() + 1):
            pass


def test_a_design_whose_cluster_cannot_be_had_leaves_nothing(tmp_path, monkeypatch):
    """(User audit, session 43) A design given a scheduler nobody listens on exited 2 with its one
    line but left a new folder holding a journal of no table; nothing is left now (a folder that
    existed stays, a journal of earlier tables too)."""
    import socket

    from roadgonio import api as rg
    from roadgonio.engines import cluster
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 2.0)
    monkeypatch.setattr(cluster, "CONNECT_GRACE_S", 1.0)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]            # free once closed: nobody listens there
    for existed in (False, True):
        out = tmp_path / f"design-{existed}"
        if existed:
            out.mkdir()
        with pytest.raises(InputError) as err:
            rg.design_study("portable", vary={"source.radius_m": [0.005, 0.01]}, samples="R3", cells="12:0",
                            backend="quadrature", scheduler=f"tcp://127.0.0.1:{port}", out=out, plots=False)
        assert err.value.field == "scheduler"
        assert out.exists() == existed and (not existed or not any(out.iterdir()))


def _wait_for_stop(item, shared=None):
    """A task of the test below: item (0, path) returns at once; item (1, path) waits at boundaries
    (an interrupts region's check, as the Mitsuba engine's passes) until its caller stops, and writes
    to ``path`` how it ended."""
    from roadgonio.errors import StoppedByCaller
    from roadgonio.interrupts import deferred
    k, path = item
    if k == 0:
        return "done"
    t0 = time.monotonic()
    Path(path + ".started").write_text("")
    try:
        with deferred("test stretch") as region:
            while time.monotonic() - t0 < 30.0:
                time.sleep(0.05)
                region.check()                   # raises StoppedByCaller once the caller stopped
    except StoppedByCaller:
        Path(path).write_text(f"stopped after {time.monotonic() - t0:.2f} s")
        raise
    Path(path).write_text("never stopped")
    return "never stopped"


@pytest.mark.timeout(120)
def test_a_running_task_stops_at_its_boundary_when_its_caller_stops(tmp_path):
    """(User audit, session 43) On an existing cluster the workers outlive the command: after
    `correct --scheduler` said "interrupted" and exited, its running tasks went on and wrote the
    output folder for seconds. map_calls now sets a Dask Event when it leaves with work unfinished;
    a running task sees it at its next boundary (interrupts.Deferred.check) and stops with
    StoppedByCaller, writing nothing more. Checked on an in-process cluster that outlives the call
    (Dask itself does not stop a running task: without the Event it ran its 30 s)."""
    from distributed import Client, LocalCluster

    from roadgonio.engines import cluster
    log = tmp_path / "task.txt"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as lc, \
            Client(lc) as client:
        class Stop(Exception):
            pass

        def first_done(i, r):
            for _ in range(400):             # the other task is running (on a loaded machine it may start late)
                if Path(str(log) + ".started").exists():
                    break
                time.sleep(0.05)
            raise Stop                       # the caller stops (as a Ctrl-C would) after the first result
        with pytest.raises(Stop):
            cluster.map_calls(_wait_for_stop, [(0, str(log)), (1, str(log))], client, on_result=first_done,
                              name="probe")
        for _ in range(200):
            if log.exists():
                break
            time.sleep(0.05)
        assert log.exists() and log.read_text().startswith("stopped after"), log.read_text() if log.exists() else None
