"""One fingerprint of "what determines the numbers" (roadgonio.fileio.fingerprint), used by the k_A
journal, the design journal, the correction's fit checkpoint and the fit cache."""
from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

import roadgonio._version as version
from roadgonio.fileio import fingerprint
from roadgonio.instrument.config import load_instrument
from roadgonio.surface.model import RoadModel, RoadParams

def test_fingerprint_is_the_sha256_of_the_payload_and_the_version():
    payload = {"instrument": {"alpha_deg": 1.0, "focus_m": "inf"}, "seed": 3, "settings": {"rel_se": 1e-3}}
    text = json.dumps({**payload, "roadgonio": version.__version__}, allow_nan=False)
    assert fingerprint(payload) == hashlib.sha256(text.encode()).hexdigest()[:16]
    assert fingerprint(payload, length=64) == hashlib.sha256(text.encode()).hexdigest()
    # numpy values hash like the numbers they hold, non-finite ones like the written JSON (null)
    assert fingerprint({"a": np.array([1.5, np.nan])}) == fingerprint({"a": [1.5, None]})
    assert fingerprint({"seed": np.int64(3)}) == fingerprint({"seed": 3})


def test_every_user_changes_with_the_version_and_the_numbers(monkeypatch, tmp_path):
    from roadgonio.correction.run import _state_key
    from roadgonio.engines import make_backend
    from roadgonio.engines.runner import fingerprint as ka_fingerprint
    from roadgonio.surface.rtable import bundled_table
    from roadgonio.surface.sample import cache_key
    inst = load_instrument("portable")
    model = RoadModel(RoadParams(k_diff=0.03, k_phong=2.2, n_phong=43.0))
    table = bundled_table("R3")
    u = np.full(table.r.shape, 0.01)

    def all_keys():
        be = make_backend("quadrature", inst, model, rtol=1e-3)
        return {"ka": ka_fingerprint(inst, model, be), "correction": _state_key(table, u, inst, {"rays": 64}),
                "fit cache": cache_key(table, "power")}

    before = all_keys()
    assert all_keys() == before                                      # deterministic
    monkeypatch.setattr(version, "__version__", version.__version__ + "+other")
    after = all_keys()
    assert all(after[k] != before[k] for k in before), (before, after)
    monkeypatch.undo()
    # the numbers: another source radius, another measured value
    other = inst.with_changes(source={"radius_m": 0.026})
    be = make_backend("quadrature", other, model, rtol=1e-3)
    assert ka_fingerprint(other, model, be) != before["ka"]
    bumped = table.with_values(np.where(table.mask, table.r * (1 + 1e-9), np.nan))
    assert _state_key(bumped, u, inst, {"rays": 64}) != before["correction"]


def test_a_design_journal_of_another_version_is_not_resumed(monkeypatch, tmp_path):
    from roadgonio.api import design_study
    from roadgonio.errors import InputError
    kw = dict(cells="4:2", out=tmp_path, plots=False, backend="quadrature", accuracy="fast", workers=0,
              progress=False)
    design_study("portable", ["source.radius_m=0.01"], ["lambert"], **kw)
    design_study("portable", ["source.radius_m=0.01"], ["lambert"], **kw)          # the same: resumed
    monkeypatch.setattr(version, "__version__", version.__version__ + "+other")
    with pytest.raises(InputError, match="different design"):
        design_study("portable", ["source.radius_m=0.01"], ["lambert"], **kw)
