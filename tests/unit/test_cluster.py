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

    def digest():
        monkeypatch.setattr(cluster, "_SOURCE_DIGEST", None)
        return cluster.source_digest()
    first = digest()
    assert digest() == first                               # a function of the files only
    (plug / "a.py").write_text("x = 2\n")
    edited = digest()
    (plug / "a.py").rename(plug / "b.py")
    renamed = digest()
    assert len({first, edited, renamed}) == 3
