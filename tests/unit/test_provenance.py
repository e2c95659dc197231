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
