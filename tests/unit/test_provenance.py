"""The one provenance builder (roadgonio.provenance) and the outputs that carry it."""
from __future__ import annotations

import json
from importlib import metadata


from roadgonio._version import __version__
from roadgonio.instrument.config import load_instrument
from roadgonio.provenance import provenance, versions
from roadgonio.surface.model import RoadModel, RoadParams
from helpers import VERSION_KEYS


def test_versions_name_the_installed_packages():
    v = versions()
    assert VERSION_KEYS <= set(v)
    assert v["roadgonio"] == __version__
    for name in ("numpy", "scipy", "mitsuba", "drjit"):
        assert v[name] == metadata.version(name)


def test_provenance_block():
    inst = load_instrument("portable")
    model = RoadModel(RoadParams(k_diff=0.05, k_phong=0.3, n_phong=30))
    p = provenance(instrument=inst, model=model, backend="quadrature", settings={"rtol": 1e-4}, sample="x")
    assert set(p) == {"versions", "created", "instrument", "instrument_file", "model", "backend", "settings", "sample"}
    assert p["instrument"] == inst.to_dict() and p["instrument_file"].endswith("portable.toml")
    assert p["model"]["params"]["n_phong"] == 30 and p["settings"] == {"rtol": 1e-4}
    json.dumps(p)                                     # JSON-ready as it is


def test_uncertainty_result_carries_the_provenance(tmp_path):
    from roadgonio.uncertainty import parse_sigma_spec, result_dict, run_uncertainty
    model = RoadModel(RoadParams(k_diff=0.05, k_phong=0.3, n_phong=30))
    res = run_uncertainty(model, load_instrument("portable"), parse_sigma_spec("alpha_deg=0.01"), trials=500,
                          aperture=False, progress=False)
    d = json.loads(json.dumps(result_dict(res, cells=False)))
    prov = d["provenance"]
    assert VERSION_KEYS <= set(prov["versions"]) and prov["instrument"]["source"]["distance_m"] == 1.0
    assert prov["model"]["params"]["k_phong"] == 0.3 and prov["sigma"]["alpha_deg"]["sigma"] == 0.01


def test_a_fitted_model_file_carries_the_common_provenance(tmp_path):
    """model.json of `fit` built its own block (meta.fit.versions, no created, no inputs) in keys no
    other output uses; it now carries provenance() with the table as an input (its file and sha256)
    and the fit's settings. validate.json and ka.nc no longer repeat roadgonio's version beside it."""
    import roadgonio as rg
    from roadgonio.engines.validate import report_json
    from roadgonio.provenance import file_sha256
    from roadgonio.surface.rtable import bundled_table
    table = tmp_path / "r3.csv"
    bundled_table("R3").write(table)
    res = rg.fit(str(table), seed=3, fixed={"theta_l_deg": 88.0}, out=tmp_path / "f", plot=False)
    doc = json.loads((tmp_path / "f" / "model.json").read_text())
    prov = doc["provenance"]
    assert {"versions", "created", "inputs", "settings"} <= set(prov) and prov["versions"]["roadgonio"] == __version__
    assert prov["inputs"] == [{"argument": "table", "path": str(table.absolute()), "sha256": file_sha256(table)}]
    assert prov["settings"]["model_variant"] == "power" and prov["settings"]["seed"] == 3
    assert prov["settings"]["fixed"] == {"theta_l_deg": 88.0}
    assert "versions" not in doc["fit"] and "versions" not in res.model.meta["fit"]
    assert RoadModel.load(tmp_path / "f" / "model.json").params == res.model.params       # still a model file
    assert "roadgonio_version" not in report_json({"rows": [], "settings": {}})
    ds = rg.ka_table("portable", "lambert", backend="quadrature", accuracy="fast", cells="4:0")
    assert "roadgonio_version" not in ds.attrs and json.loads(ds.attrs["provenance"])["versions"]["roadgonio"]


def test_the_source_digest_names_the_code_that_ran():
    """(audit 28) provenance said only roadgonio 0.1.0, which an edited checkout does not change: it
    carries the digest of the Python source the Dask check compares (which moves with any file:
    tests/unit/test_cluster.py)."""
    from roadgonio.provenance import source_digest, versions
    d = versions()["roadgonio_source"]
    assert d == source_digest() and len(d) == 16 and int(d, 16) >= 0


def test_a_renderer_that_ran_elsewhere_is_named_from_the_backend_settings(monkeypatch):
    """(User audit, session 43) A design computed on Dask workers said which mitsuba but not which
    variant nor LLVM (the calling process never loads the renderer): the backend's settings, recorded
    by the worker, name them; a process that rendered itself keeps its own."""
    import roadgonio.provenance as P
    monkeypatch.setattr(P, "versions", lambda: {"roadgonio": "x", "mitsuba": "3.x"})
    v = P.provenance(settings={"backend": "mitsuba", "mitsuba_variant": "llvm_ad_rgb", "llvm": "19.1.7"})["versions"]
    assert v["mitsuba_variant"] == "llvm_ad_rgb" and v["llvm"] == "19.1.7" and "another process" in v["renderer_from"]
    assert "mitsuba_variant" not in P.provenance(settings={"backend": "quadrature"})["versions"]
    monkeypatch.setattr(P, "versions", lambda: {"roadgonio": "x", "mitsuba_variant": "cuda_ad_rgb"})
    v = P.provenance(settings={"mitsuba_variant": "llvm_ad_rgb"})["versions"]
    assert v["mitsuba_variant"] == "cuda_ad_rgb" and "renderer_from" not in v
