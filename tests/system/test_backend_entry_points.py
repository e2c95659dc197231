"""Every backend of the registry works through both entry points with the same arguments: the Python
API (roadgonio.ka_table) and the command line (roadgonio ka) give the same numbers for the same seed;
the seed reaches the backends that take one (another seed, other numbers) and is refused by a
deterministic one in both; the accuracy presets exist for every backend."""
from __future__ import annotations

import json

import numpy as np
import pytest

import roadgonio as rg
from roadgonio.cli import main
from roadgonio.engines.registry import BACKENDS, PRESETS
from roadgonio.errors import InputError
from roadgonio.surface.model import RoadModel, RoadParams

pytestmark = pytest.mark.system

MODEL = RoadModel(RoadParams(k_diff=0.02, k_phong=0.4, n_phong=60, k_retro=0.01, n_retro=10), name="entry")
CELL = "4:0"


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "entry.json"
    MODEL.save(path)
    return path


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_every_backend_through_the_api_and_the_command_line(backend, model_file, tmp_path, capsys):
    info = BACKENDS[backend]
    assert set(info.presets) == set(PRESETS), f"{backend} lacks accuracy presets"
    seed = 7 if info.seeded else None
    ds = rg.ka_table("portable", str(model_file), backend=backend, accuracy="fast", cells=CELL, seed=seed)
    k_api = float(ds.k_a.sel(tan_eps=4.0, beta=0.0))
    assert np.isfinite(k_api) and bool(ds.converged.sel(tan_eps=4.0, beta=0.0))
    argv = ["ka", "--instrument", "portable", "--sample", str(model_file), "--backend", backend,
            "--accuracy", "fast", "--cells", CELL, "--out", str(tmp_path / "cli"), "--quiet"]
    assert main(argv + (["--seed", str(seed)] if seed is not None else [])) == 0
    import xarray as xr
    with xr.open_dataset(tmp_path / "cli" / "ka.nc", engine="scipy") as cli:
        k_cli = float(cli.k_a.sel(tan_eps=4.0, beta=0.0))
    assert k_cli == k_api, "the same arguments give the same number through both entry points"
    meta = json.loads((tmp_path / "cli" / "ka.json").read_text())
    if info.seeded:
        assert meta["settings"]["seed"] == seed
        other = rg.ka_table("portable", str(model_file), backend=backend, accuracy="fast", cells=CELL, seed=seed + 1)
        assert float(other.k_a.sel(tan_eps=4.0, beta=0.0)) != k_api, "another seed, other random numbers"
    else:
        with pytest.raises(InputError, match="takes no seed"):
            rg.ka_table("portable", str(model_file), backend=backend, accuracy="fast", cells=CELL, seed=3)
        capsys.readouterr()
        assert main(argv[:-3] + ["--seed", "3", "--out", str(tmp_path / "seeded")]) == 2
        assert "--seed" in capsys.readouterr().err


def test_an_unknown_backend_is_one_line_in_both():
    with pytest.raises(InputError, match="unknown backend"):
        rg.ka_table("portable", "lambert", backend="nope", cells=CELL)
