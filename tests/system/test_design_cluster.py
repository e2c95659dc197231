"""roadgonio design on a real Dask cluster started with the standard commands (``dask scheduler`` /
``dask worker``, run as ``python -m distributed.cli.dask_*`` from this environment so the workers
import this roadgonio), on the loopback interface, torn down in a finally; results must be
identical to the in-process run, whatever the number of workers."""
from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest


START_TIMEOUT_S = 90


def _stop(procs) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)


@pytest.fixture()
def dask_cluster(tmp_path):
    """A scheduler and 2 one-thread worker processes on 127.0.0.1; yields the scheduler address."""
    sched_file = tmp_path / "scheduler.json"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    logs = tmp_path / "logs"
    logs.mkdir()
    procs = []
    files = contextlib.ExitStack()            # the log files, closed once the processes are gone
    try:
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
             "--no-dashboard", "--scheduler-file", str(sched_file)],
            cwd=tmp_path, env=env, stdout=files.enter_context(open(logs / "scheduler.log", "w")),
            stderr=subprocess.STDOUT))
        t0 = time.monotonic()
        while not sched_file.exists():
            if time.monotonic() - t0 > START_TIMEOUT_S or procs[0].poll() is not None:
                raise RuntimeError("the dask scheduler did not start: " + (logs / "scheduler.log").read_text())
            time.sleep(0.2)
        time.sleep(0.2)
        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for k in range(2):
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1", "--host",
                 "127.0.0.1", "--no-dashboard", "--name", f"w{k}", "--local-directory", str(tmp_path / f"w{k}"),
                 "--death-timeout", "60"],
                cwd=tmp_path, env=env, stdout=files.enter_context(open(logs / f"worker{k}.log", "w")),
                stderr=subprocess.STDOUT))
        from distributed import Client
        with Client(address, timeout="30s") as c:
            c.wait_for_workers(2, timeout=START_TIMEOUT_S)
        yield address
    finally:
        _stop(procs[1:])
        _stop(procs[:1])
        files.close()


VARY = ["source.radius_m=0.015:0.035:3", "detector.field_half_angle_deg=0.1,0.15"]
CELLS = "12:0,8:2,2:180"


@pytest.mark.timeout(600)
def test_two_worker_cluster_identical_to_in_process(mi, dask_cluster, tmp_path):
    from roadgonio import design_study as run_design
    kw = dict(samples=["R3"], cells=CELLS, backend="mitsuba", accuracy="fast", seed=5, progress=False, plots=False)
    ds_here = run_design("portable", VARY, workers=0, out=tmp_path / "here", **kw)
    ds_dask = run_design("portable", VARY, scheduler=dask_cluster, out=tmp_path / "dask", **kw)
    assert int(ds_here.attrs["points_geometry_ok"]) == 6
    prov = json.loads(ds_dask.attrs["provenance"])
    assert prov["cluster"]["workers"] == 2 and prov["cluster"]["mode"] == "dask"
    # computed on the two worker processes, not here
    workers = {json.loads(line)["worker"] for line in
               (tmp_path / "dask" / "design_points.jsonl").read_text().splitlines()[1:]}
    here = {json.loads(line)["worker"] for line in
            (tmp_path / "here" / "design_points.jsonl").read_text().splitlines()[1:]}
    assert len(workers) == 2 and not workers & here
    for v in ("k_a", "se", "max_abs_dev", "rms_dev", "signal"):
        a, b = ds_here[v].values, ds_dask[v].values
        assert np.array_equal(a, b, equal_nan=True), v
    assert np.array_equal(ds_here["seed"].values, ds_dask["seed"].values)      # 63-bit seeds, as text
    assert np.isfinite(ds_here["k_a"].values).sum() == 6 * 3
    # the k_A values are real Monte Carlo estimates, not a constant
    assert np.nanstd(ds_here["k_a"].values) > 0.01


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_uncertainty_exact_tables_on_a_local_cluster_are_identical():
    """The surrogate's exact k_A tables are independent instruments: on a 2-process local cluster
    the whole uncertainty result is the same as in this process."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.sample import resolve_sample
    from roadgonio.uncertainty import parse_sigma_spec, run_uncertainty
    spec = parse_sigma_spec("alpha_deg=0.01,eps_deg=0.05,beta_deg=0.1,source_distance_m=0.002,"
                            "detector_distance_m=0.005")
    kw = dict(trials=1000, seed=2, backend="mitsuba", surrogate_design="star", n_validation=1, progress=False,
              backend_settings={"rel_se": 3e-3, "first_pass": 256, "seed": 2})
    inst, model = load_instrument("portable"), resolve_sample("R3").model
    here = run_uncertainty(model, inst, spec, **kw)
    dask = run_uncertainty(model, inst, spec, workers=2, **kw)
    note = next(n for n in dask.provenance["notes"] if "Dask" in n)
    assert "2 workers, 2 threads, scheduler tcp://" in note and "{" not in note      # words, not a dict's repr
    assert np.array_equal(here.surrogate.rel_err_max, dask.surrogate.rel_err_max)
    a, b = here.cases["aperture"], dask.cases["aperture"]
    for k in a.mc:
        assert np.array_equal(a.mc[k], b.mc[k]), k
    assert here.surrogate.exact_evaluations == dask.surrogate.exact_evaluations == 12 * len(here.cells)
