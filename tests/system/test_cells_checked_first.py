"""A cell the backend refuses is refused before anything is computed or written (user audit,
session 24): ``ka --backend reference`` (and every cell-by-cell backend) and ``validate`` checked each
cell only when they reached it, so ``--cells 12:0,0:0`` computed and journalled 12:0 (validate
printed its row) and then failed at 0:0. Now: one line naming --cells, the refused cells and what
was expected, exit status 2, and no journal, output folder or row."""
from __future__ import annotations

import json

import pytest

from roadgonio.cli import main
from helpers import GOOD_INSTRUMENT

#: A pure Phong lobe of exponent 2000: 0.04 pi at the nominal geometry of 12:0, 0 (underflow) at 0:0.
NARROW = {"variant": "power", "params": {"k_phong": 1.0, "n_phong": 2000.0}}


def one_line(capsys, rc, *must) -> str:
    cap = capsys.readouterr()
    assert rc == 2, cap.err
    lines = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("roadgonio: error:"), cap.err
    for m in must:
        assert m in lines[0], (m, lines[0])
    assert not cap.out.strip(), cap.out        # no row, no table: nothing was computed
    return lines[0]


@pytest.fixture
def narrow(tmp_path):
    p = tmp_path / "narrow.json"
    p.write_text(json.dumps(NARROW))
    return p


@pytest.mark.parametrize("backend", ["reference", "numpy-mc", "quadrature"])
def test_ka_refuses_a_cell_at_a_zero_nominal_value_before_computing(backend, narrow, tmp_path, capsys):
    out = tmp_path / "o"
    rc = main(["ka", "--instrument", "lab", "--sample", str(narrow), "--backend", backend, "--accuracy", "fast",
               "--cells", "12:0,0:0,0:2", "--out", str(out)])
    one_line(capsys, rc, "--cells", f"the {backend} backend cannot compute cells 0:0, 0:2 (2 of the 3 cells asked)",
             "the model is 0 at the nominal geometry", "expected only cells it can compute")
    assert not out.exists()


def test_ka_refuses_a_blocked_cell_before_computing_and_keeps_the_journal(tmp_path, capsys):
    """The source disc in the detector's view at 12:180; a folder with a finished cell keeps its journal as it was."""
    p = tmp_path / "near.toml"
    p.write_text(GOOD_INSTRUMENT.replace("distance_m = 5.0\nradius_m = 0.005", "distance_m = 1.0\nradius_m = 0.08"))
    out = tmp_path / "o"
    args = ["ka", "--instrument", str(p), "--sample", "lambert", "--backend", "reference", "--accuracy", "fast",
            "--out", str(out)]
    assert main(args + ["--cells", "0:0"]) == 0
    capsys.readouterr()
    before = {f.name: f.read_bytes() for f in out.iterdir()}
    rc = main(args + ["--cells", "0:0,2:0,12:180"])
    one_line(capsys, rc, "--cells", "cannot compute cell 12:180 (1 of the 2 cells asked)",
             "blocks the detector's line of sight at tan eps = 12, beta = 180", "leave it out")
    assert {f.name: f.read_bytes() for f in out.iterdir()} == before


def test_validate_refuses_a_cell_before_computing(narrow, tmp_path, capsys):
    out = tmp_path / "v"
    rc = main(["validate", "--instrument", "lab", "--sample", str(narrow), "--against", "numpy-mc", "--rel-se", "1e-2",
               "--cells", "12:0,0:0", "--out", str(out)])
    one_line(capsys, rc, "--cells", "the numpy-mc backend cannot compute cell 0:0 (1 of the 2 cells asked)",
             "the model is 0 at the nominal geometry", "expected only cells it can compute")
    assert not out.exists()


def test_cells_refused_for_different_reasons_are_counted_by_reason(narrow, tmp_path, capsys):
    """The source disc in the detector's view at 12:180 and a model that is 0 at 0:0: the line counts
    each reason and quotes the first refusal as such (user audit: 537 cells, 536 of them with a model
    of 0, were all given the one blocked cell's reason)."""
    p = tmp_path / "near.toml"
    p.write_text(GOOD_INSTRUMENT.replace("distance_m = 5.0\nradius_m = 0.005", "distance_m = 1.0\nradius_m = 0.08"))
    rc = main(["ka", "--instrument", str(p), "--sample", str(narrow), "--backend", "quadrature", "--accuracy", "fast",
               "--cells", "12:0,0:0,12:180", "--out", str(tmp_path / "o")])
    line = one_line(capsys, rc, "--cells", "cannot compute cells 0:0, 12:180 (2 of the 3 cells asked), ",
                    "where the model is not positive at the nominal geometry",
                    "1 where the source disc is in the detector's view", "; the first checked: ")
    assert "the first checked: the source disc blocks" in line, line
