"""`roadgonio validate` from the command line: outputs, JSON, exit statuses 0/1/2/3, the wide
instrument (slow)."""
from __future__ import annotations

import csv
import json

import pytest

from roadgonio.cli import main
from roadgonio.engines import validate as V


@pytest.fixture
def model_file(tmp_path, r3like):
    path = tmp_path / "r3like.json"
    r3like.save(path)
    return path


def test_cli_agrees_and_writes_outputs(tmp_path, capsys, model_file):
    out = tmp_path / "val"
    rc = main(["validate", "--instrument", "lab", "--sample", str(model_file), "--against", "numpy-mc",
               "--cells", "12:0,0:180,4:2", "--rel-se", "3e-3", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "validate: 3 agree, 0 disagree, 0 inconclusive (of 3 cells" in text
    rows = list(csv.DictReader((out / "validate.csv").read_text().splitlines()))
    assert [(float(r["tan_eps"]), float(r["beta_deg"])) for r in rows] == [(12, 0), (0, 180), (4, 2)]
    assert all(r["verdict"] == "agree" and r["ref_converged"] == "True" for r in rows)
    # the reference was asked for the bound each test needs, and met it; the RQMC reference's bound
    # is a confidence bound (with its level), never reported as a deterministic error bound
    assert all(float(r["confidence_bound_ref"]) <= float(r["needed_bound"]) for r in rows)
    # a value the reference does not have is a blank cell, never "nan" (docs/inputs-outputs.md)
    assert all(float(r["confidence_level_ref"]) == 0.999 and r["error_bound_ref"] == "" for r in rows)
    assert "nan" not in (out / "validate.csv").read_text().lower()
    assert "against the RQMC reference (99.9 % confidence bound)" in text
    assert "float32" not in text          # numpy-mc computes in float64: no renderer's floor
    doc = json.loads((out / "validate.json").read_text())
    assert doc["verdict"] == "agree" and doc["exit_status"] == 0 and doc["reference"] == "reference"
    assert doc["counts"] == {"agree": 3, "disagree": 0, "inconclusive": 0} and len(doc["cells"]) == 3
    assert "reference" in doc["settings"] and doc["provenance"]["model"]["params"]["n_phong"] == pytest.approx(34.467)
    assert (out / "validate.png").stat().st_size > 10_000
    assert oct((out / "validate.csv").stat().st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask() -> int:
    import os
    m = os.umask(0)
    os.umask(m)
    return m


def test_cli_json_is_the_report(tmp_path, capsys, model_file):
    rc = main(["validate", "--instrument", "lab", "--sample", str(model_file), "--against", "numpy-mc",
               "--cells", "2:90", "--rel-se", "3e-3", "--json", "--out", str(tmp_path / "v")])
    doc = json.loads(capsys.readouterr().out)
    assert rc == 0 and doc["counts"]["agree"] == 1 and doc["cells"][0]["verdict"] == "agree"


def test_cli_exit_1_on_disagreement(tmp_path, monkeypatch, capsys, model_file):
    """With a zero-width pass band any Monte Carlo noise is a disagreement: exit status 1."""
    monkeypatch.setattr(V, "N_SIGMA", 0.0)
    rc = main(["validate", "--instrument", "lab", "--sample", str(model_file), "--against", "numpy-mc",
               "--reference", "quadrature", "--rtol", "1e-9", "--cells", "8:5", "--rel-se", "1e-2", "--floor", "0",
               "--out", str(tmp_path / "v")])
    assert rc == 1
    assert "FAILED" in capsys.readouterr().err
    # the quadrature's bound is deterministic: error_bound_ref, no confidence bound or level
    row = next(csv.DictReader((tmp_path / "v" / "validate.csv").read_text().splitlines()))
    assert float(row["error_bound_ref"]) > 0
    assert row["confidence_bound_ref"] == "" and row["confidence_level_ref"] == ""      # blank: none


def test_cli_exit_3_when_the_reference_does_not_converge(tmp_path, capsys, model_file):
    """A reference capped far below what it needs cannot vouch for the renderer: inconclusive, exit 3."""
    rc = main(["validate", "--instrument", "wide", "--sample", str(model_file), "--against", "numpy-mc",
               "--cells", "2:90", "--rel-se", "1e-2", "--ref-max-evals", "1000", "--out", str(tmp_path / "v")])
    cap = capsys.readouterr()
    assert rc == 3, cap.out + cap.err
    assert "0 agree, 0 disagree, 1 inconclusive" in cap.out and "did not converge" in cap.out
    assert "INCONCLUSIVE" in cap.err


def test_cli_refuses_an_xml_scene_instead_of_blaming_the_renderer(tmp_path, capsys, model_file):
    rc = main(["validate", "--instrument", "holder", "--sample", str(model_file), "--against", "numpy-mc",
               "--cells", "2:90", "--out", str(tmp_path / "v")])
    err = capsys.readouterr().err
    assert rc == 2 and "scene" in err and "does not model" in err and len(err.strip().splitlines()) == 1


def test_cli_bad_input_is_exit_2(tmp_path):
    assert main(["validate", "--instrument", "lab", "--sample", "lambert", "--against", "numpy-mc",
                 "--cells", "12", "--out", str(tmp_path)]) == 2
    assert main(["validate", "--instrument", "nope.toml", "--sample", "lambert", "--against", "numpy-mc",
                 "--out", str(tmp_path)]) == 2
    assert main(["validate", "--instrument", "lab", "--sample", "lambert", "--against", "numpy-mc",
                 "--seed", "-1", "--out", str(tmp_path)]) == 2


@pytest.mark.slow
def test_wide_instrument_quadrature_is_inconclusive_where_it_stops_short(tmp_path, capsys, model_file):
    """The issue's measurement: at tan eps 12 / beta 0 the tensor quadrature stops at its cap ~8 % off;
    judged against numpy-mc that is now 'inconclusive', not 'agree'."""
    rc = main(["validate", "--instrument", "wide", "--sample", str(model_file), "--against", "numpy-mc",
               "--reference", "quadrature", "--cells", "12:0", "--rel-se", "3e-3", "--out", str(tmp_path / "v")])
    assert rc == 3 and "did not converge" in capsys.readouterr().out


@pytest.mark.slow
def test_wide_instrument_agrees_with_a_converged_reference(tmp_path, capsys, model_file):
    """The strong-aperture corner of the wide instrument (where the quadrature fails): numpy-mc agrees
    with the RQMC reference, which converged in every cell."""
    rc = main(["validate", "--instrument", "wide", "--sample", str(model_file), "--against", "numpy-mc",
               "--cells", "12:0,12:2,8:5,4:0", "--rel-se", "2e-3", "--out", str(tmp_path / "v")])
    out = capsys.readouterr().out
    assert rc == 0, out
    rows = list(csv.DictReader((tmp_path / "v" / "validate.csv").read_text().splitlines()))
    assert all(r["ref_converged"] == "True" and r["verdict"] == "agree" for r in rows)
