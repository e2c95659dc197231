"""What a cluster task carries (roadgonio/engines/cluster.py), in this process: a TableTask's
instrument, model, settings and seed arrive whole, and an instrument's files travel as absolute
paths (mutation audit 9b: dropping the task's seed, or resolving a relative [scene] xml against the
working folder instead of the instrument file's, passed every unit test)."""
from __future__ import annotations

from helpers import SCENES, preset
from roadgonio.engines import cluster
from roadgonio.engines.registry import make_backend
from roadgonio.instrument.config import Instrument

CELLS = ((2.0, 0.0), (0.5, 30.0))
SETTINGS = {"rel_se": 0.05, "batch": 32 ** 2}


def _task(inst, model, seed):
    return cluster.TableTask(instrument=cluster.absolute_instrument_dict(inst), model=model.to_json_dict(),
                             cells=CELLS, backend="numpy-mc", settings=SETTINGS, seed=seed, key=("k", seed))


def test_a_table_task_computes_what_the_backend_computes_here_with_its_seed(r3like):
    inst = preset("portable")
    here = make_backend("numpy-mc", inst, r3like, seed=5, settings=SETTINGS).compute(list(CELLS))
    got = cluster.compute_table(_task(inst, r3like, 5), prepare=False)
    assert got.ok and got.key == ("k", 5)
    assert [(c.tan_eps, c.beta_deg, c.k_a, c.se, c.samples) for c in got.cells] == \
        [(c.tan_eps, c.beta_deg, c.k_a, c.se, c.samples) for c in here]
    other = cluster.compute_table(_task(inst, r3like, 6), prepare=False)
    assert [c.k_a for c in other.cells] != [c.k_a for c in got.cells]


def test_a_relative_scene_file_is_resolved_against_the_instrument_file_not_the_working_folder(tmp_path,
                                                                                              monkeypatch):
    inst = Instrument.load(SCENES / "holder.toml")
    monkeypatch.chdir(tmp_path)
    d = cluster.absolute_instrument_dict(inst)
    assert d["scene"]["xml"] == str((SCENES / "holder.xml").resolve())


def test_the_source_digest_covers_the_plugins_folder_by_name_and_content(tmp_path, monkeypatch):
    """Workers running other source are refused by their source digest: the plugins (the Mitsuba
    BSDF, sensor and integrator the workers load) are part of it, by file name and content."""
    import roadgonio._checkout as checkout
    plug = tmp_path / "plugins"
    plug.mkdir()
    (plug / "a.py").write_text("x = 1\n")
    monkeypatch.setattr(checkout, "mapped_folders", lambda: {"roadgonio.engines.mitsuba.plugins": plug})

    import roadgonio.provenance as prov

    def digest():
        monkeypatch.setattr(prov, "_SOURCE_DIGEST", None)
        return prov.source_digest()
    first = digest()
    assert digest() == first                               # a function of the files only
    (plug / "a.py").write_text("x = 2\n")
    edited = digest()
    (plug / "a.py").rename(plug / "b.py")
    renamed = digest()
    assert len({first, edited, renamed}) == 3


def _run_script(tmp_path, name, text):
    import os
    import subprocess
    import sys
    from pathlib import Path

    import roadgonio
    script = tmp_path / name
    script.write_text(text)
    env = {**os.environ, "PYTHONPATH": str(Path(roadgonio.__file__).parents[1])}
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=120)


UNGUARDED = """\
from roadgonio.engines.cluster import open_client
with open_client(workers=1, backend=None):
    print("cluster started")
"""


def test_an_unguarded_local_cluster_is_refused_before_any_worker_starts(tmp_path):
    """Trial 11 D8: a script calling the API with workers=N at top level printed a ~25-line traceback
    from every spawned worker (each imports the script again and fails there) before the script's
    own error. Now the call is refused before any process starts: the script's one traceback, whose
    last line names the script's line, the guard and workers=0."""
    res = _run_script(tmp_path, "noguard.py", UNGUARDED)
    assert res.returncode == 1 and "cluster started" not in res.stdout
    assert res.stderr.count("Traceback") == 1, res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("roadgonio.errors.InputError: ") and "noguard.py:2, field 'workers'" in last, last
    assert "if __name__ == \"__main__\":" in last and "workers=0" in last, last


def test_the_guard_check_sees_the_guard_around_the_calls_line(tmp_path):
    """The check's verdict by where the script's top-level code is: under the guard (either way round,
    through a function) or after it; nothing is judged in a process without a script (python -c) or
    from a package's __main__.py (python -m roadgonio), which the workers do not run again."""
    res = _run_script(tmp_path, "guard.py", """\
from roadgonio.engines.cluster import _unguarded_main_call as check
def through_a_function():
    return check()
if __name__ == "__main__":
    print("guarded", check(), through_a_function())
if "__main__" == __name__:
    print("reversed", check())
print("top", check()[1])
""")
    assert res.returncode == 0, res.stderr
    assert res.stdout.split("\n")[:3] == ["guarded None None", "reversed None", "top 8"]
    import subprocess
    import sys
    code = "from roadgonio.engines.cluster import _unguarded_main_call as c; print(c())"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout.strip() == "None"
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "__main__.py").write_text(code.replace("; ", "\n") + "\n")
    import os
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    res = subprocess.run([sys.executable, "-m", "pkg"], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert res.stdout.strip() == "None", res.stdout + res.stderr


def test_tables_per_task_groups_only_when_every_worker_keeps_enough_tasks():
    from roadgonio.engines.cluster import TABLES_PER_TASK_MAX, TASKS_PER_WORKER_MIN, tables_per_task
    assert tables_per_task(60, 2) == 3                       # bench_design's 60-point design
    assert tables_per_task(10, 2) == 1
    assert tables_per_task(0, 2) == 1 and tables_per_task(5, 0) == 1
    assert tables_per_task(10_000, 1) == TABLES_PER_TASK_MAX
    for n in range(1, 400):
        for w in (1, 2, 3, 8):
            per = tables_per_task(n, w)
            assert 1 <= per <= TABLES_PER_TASK_MAX
            if per > 1:                                      # grouping never leaves a worker short of tasks
                assert -(-n // per) >= TASKS_PER_WORKER_MIN * w
