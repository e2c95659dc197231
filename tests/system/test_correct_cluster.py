"""``roadgonio correct`` on Dask (issue 12: ``--workers N`` / ``--scheduler``) and the generic
:func:`roadgonio.engines.cluster.map_calls` under it: on a local cluster of two worker processes
(started by the command, on the loopback interface, torn down by it) the corrected tables of two
measured files are byte for byte those of the in-process run. The deterministic quadrature and
small ray bundles keep it short; the same seeds and the same shipped bundles make Monte Carlo
backends identical too (tests/system/test_design_cluster.py checks that for Mitsuba tables)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from roadgonio.cli import main
from roadgonio.surface.rtable import read_table


DATA = Path(__file__).resolve().parents[1] / "data"
#: Every file correct writes per folder with pictures (the journals and fit_state.json aside).
OUTPUTS = ["before_after.png", "correct.json", "correct_cells.csv", "corrected.csv", "corrected.rtb",
           "corrected_corr.csv", "corrected_u.csv", "correction_map.png"]


def small_tables(tmp_path):
    """Two measured files of the synthetic medium-instrument measurement (tests/data), cut to beta
    0 and 2 and every other tan eps (30 cells, S1 cells kept); the second one 1 % noisier."""
    meas = read_table(DATA / "synthetic_medium_lambert.csv")
    keep = meas.r.copy()
    keep[:, 2:] = np.nan
    keep[[i for i in range(keep.shape[0]) if i % 3 and i != 8], :] = np.nan
    assert np.isfinite(keep).sum() >= 12 and np.isfinite(keep[[0, 8], 0]).all()   # tan eps 0 and 2, beta 0
    rng = np.random.default_rng(11)
    a = meas.with_values(keep, name="a").write_csv(tmp_path / "a.csv")
    b = meas.with_values(keep * (1 + 0.01 * rng.standard_normal(keep.shape)), name="b").write_csv(tmp_path / "b.csv")
    return a, b


def correct_argv(files, out):
    return ["correct", "--measured", *map(str, files), "--instrument", str(DATA / "medium.toml"), "--backend",
            "quadrature", "--accuracy", "fast", "--rays", "64", "--model-variant", "power", "--out", str(out), "--json"]


@pytest.mark.timeout(300)
@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_correct_two_files_on_two_workers_is_identical_to_in_process(tmp_path, capsys):
    files = small_tables(tmp_path)
    assert main(correct_argv(files, tmp_path / "here") + ["--no-plots"]) == 0
    here = json.loads(capsys.readouterr().out)
    assert main(correct_argv(files, tmp_path / "dask") + ["--workers", "2"]) == 0
    dask = json.loads(capsys.readouterr().out)
    assert [s["out"] for s in dask] == [str(tmp_path / "dask" / n) for n in ("a", "b")]
    for name in ("a", "b"):
        d, h = tmp_path / "dask" / name, tmp_path / "here" / name
        assert sorted(p.name for p in d.iterdir() if p.is_file()) == sorted(OUTPUTS + ["fit_state.json"])
        for f in ("corrected.csv", "corrected_u.csv", "corrected.rtb", "correct_cells.csv", "corrected_corr.csv"):
            assert (d / f).read_bytes() == (h / f).read_bytes(), (name, f)
        prov = json.loads((d / "correct.json").read_text())["provenance"]
        assert prov["cluster"]["mode"] == "dask" and prov["cluster"]["workers"] == 2
        host, pid = prov["cluster"]["computed_by"].rsplit(":", 1)
        assert int(pid) != os.getpid()                      # computed on a worker process, not here
        assert "cluster" not in json.loads((h / "correct.json").read_text())["provenance"]
    for s, t in zip(here, dask):
        assert {k: s[k] for k in ("S1", "u_S1", "Q0", "k_a_min", "k_a_max", "fit")} == \
               {k: t[k] for k in ("S1", "u_S1", "Q0", "k_a_min", "k_a_max", "fit")}
    # a correction that does something (a real aperture effect), and two different tables
    assert here[0]["k_a_max"] - here[0]["k_a_min"] > 0.02
    assert here[0]["S1"] != here[1]["S1"]


@pytest.fixture(scope="module")
def client():
    from roadgonio.engines.cluster import open_client
    with open_client(workers=2, backend=None) as c:
        yield c


def test_map_calls_order_shared_object_and_errors(client):
    """map_calls: results in the order of the items whatever order they finish in, the shared
    object reaches every call, a RoadgonioError raised on a worker arrives here whole (message
    and fields), and the in-process route gives the same results."""
    import operator

    from roadgonio.engines.cluster import _check_address, map_calls
    from roadgonio.errors import InputError
    items = list(range(12))
    seen = []
    got = map_calls(operator.add, items, client, shared=1000, on_result=lambda i, r: seen.append(i))
    assert got == [1000 + i for i in items]
    assert sorted(seen) == items
    assert map_calls(operator.add, items, None, shared=1000) == got
    assert map_calls(abs, [-3, 4], client) == [3, 4]
    with pytest.raises(InputError) as e:
        map_calls(_check_address, ["tcp://127.0.0.1:8786", "no-port-here"], client)
    assert e.value.field == "scheduler" and "no-port-here" in str(e.value)


def test_correct_api_refuses_a_custom_factory_on_dask(tmp_path):
    from roadgonio.correction import correct_files
    from roadgonio.errors import InputError
    from roadgonio.instrument.config import load_instrument
    a, _ = small_tables(tmp_path)
    with pytest.raises(InputError, match="custom backend factory"):
        correct_files([read_table(a)], load_instrument(DATA / "medium.toml"), tmp_path / "o",
                      factory=lambda inst, model: None, workers=2)
