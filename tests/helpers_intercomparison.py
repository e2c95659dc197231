"""Helpers of the intercomparison tests of every tier (tests/unit, tests/plugin, tests/system):
collimated participants (zero apertures: k_A = 1, no k_A backend) keep most of them numpy-only.
tests/ is on sys.path: ``from helpers_intercomparison import ...``."""
from __future__ import annotations

import numpy as np
from scipy.stats import norm

from roadgonio.intercomparison.study import study_from_dict

COLLIMATED = """[instrument]
name = "collimated"
[source]
distance_m = 5.0
[detector]
distance_m = 10.0
[sample]
size_x_m = 2.0
size_y_m = 0.5
"""
#: P(|Z| <= 2): the share of |E_n| <= 1 (k = 2) of results consistent with their stated u
P_EN = 2 * norm.cdf(2.0) - 1


def write_collimated(folder):
    p = folder / "collimated.toml"
    p.write_text(COLLIMATED)
    return p


def make_study(tmp_path, participants, shared=(), **settings):
    """A Study of ``participants`` (dicts of the study file) on R3, 20 realisations, seed 7, as if
    read from tmp_path/study.toml (instrument files relative to tmp_path)."""
    d = {"study": {"surface": "R3", "realisations": 20, "seed": 7, **settings}, "participant": list(participants),
         "shared": list(shared)}
    return study_from_dict(d, path=tmp_path / "study.toml")


def coll(name, noise=0.01, **kw):
    """A collimated participant stating its repeatability only."""
    return {"name": name, "instrument": "collimated.toml", "noise_rel": noise, "stated": ["repeatability"], **kw}


def per_realisation_share(en: np.ndarray) -> np.ndarray:
    """Share of |E_n| <= 1 per realisation over the finite cells; en is (realisation, ..., cells)."""
    fin = np.isfinite(en)
    ok = (np.abs(np.where(fin, en, 0.0)) <= 1.0) & fin
    axes = tuple(range(1, en.ndim))
    return ok.sum(axis=axes) / fin.sum(axis=axes)
