"""roadgonio intercompare: the study file, the simulated participants, the comparison's hand-checkable
cases, resume, Dask and the outputs. Collimated participants (zero apertures: k_A = 1, no k_A
backend) keep most of these numpy-only; the aperture-effect and correction cases need Mitsuba."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import norm

from roadgonio.errors import InputError
from roadgonio.intercomparison.run import run_study
from roadgonio.intercomparison.study import load_study, study_from_dict

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


@pytest.fixture()
def collimated(tmp_path) -> Path:
    p = tmp_path / "collimated.toml"
    p.write_text(COLLIMATED)
    return p


def _study(tmp_path, participants, shared=(), **study):
    d = {"study": {"surface": "R3", "realisations": 20, "seed": 7, **study}, "participant": list(participants),
         "shared": list(shared)}
    return study_from_dict(d, path=tmp_path / "study.toml")


def _coll(name, noise=0.01, **kw):
    return {"name": name, "instrument": "collimated.toml", "noise_rel": noise, "stated": ["repeatability"], **kw}


def _per_realisation_share(en: np.ndarray) -> np.ndarray:
    """Share of |E_n| <= 1 per realisation over the finite cells; en is (realisation, ..., cells)."""
    fin = np.isfinite(en)
    ok = (np.abs(np.where(fin, en, 0.0)) <= 1.0) & fin
    axes = tuple(range(1, en.ndim))
    return ok.sum(axis=axes) / fin.sum(axis=axes)


# ---- the study file -------------------------------------------------------------------------------

@pytest.mark.unit
@pytest.mark.parametrize("change, field, words", [
    (lambda d: d["participant"][0].update(noise=0.1), "participant[1].noise", "unknown key"),
    (lambda d: d["study"].update(realisation=3), "study.realisation", "unknown key"),
    (lambda d: d.update(extra={}), "extra", "unknown key"),
    (lambda d: d["participant"][1].update(report="reference"), "participant[2].reference", "needs reference"),
    (lambda d: d["participant"][1].update(report="self", noise_rel=0.0), "participant[2].noise_rel", "noise_rel > 0"),
    (lambda d: d["participant"][0].update(sigma="alpha=0.1"), "participant[1].sigma alpha", "unknown key"),
    (lambda d: d["participant"][0].update(stated=["aperture"]), "participant[1].stated", "unknown stated"),
    (lambda d: d["participant"][1].update(name="A"), "participant.name", "two participants"),
    (lambda d: d["participant"][0].update(instrument="nope.toml"), "participant[1].instrument", "no such"),
    (lambda d: d["shared"].append({"name": "t", "kind": "reference_tile", "u_rel": 0.01, "participants": ["A", "Z"]}),
     "shared[1].participants", "no participant named"),
    (lambda d: d["shared"].append({"name": "t", "kind": "angle_standard", "u_rel": 0.01, "participants": ["A", "B"]}),
     "shared[1].u_rel", "not u_rel"),
    (lambda d: d["study"].update(realisations=1), "study.realisations", ">= 2"),
    (lambda d: d["study"].pop("surface"), "study.surface", "missing"),
])
def test_bad_study_files_are_one_line_errors_naming_file_and_field(tmp_path, collimated, change, field, words):
    d = {"study": {"surface": "R3"}, "participant": [_coll("A"), _coll("B")], "shared": []}
    change(d)
    with pytest.raises(InputError) as err:
        study_from_dict(d, path=tmp_path / "study.toml")
    assert err.value.field == field
    assert str(tmp_path / "study.toml") in str(err.value)
    assert words in err.value.reason
    assert "\n" not in str(err.value)


@pytest.mark.system
def test_cli_bad_study_exits_2_with_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[study]\nsurface = "R3"\n[[participant]]\nname = "A"\ninstrument = "lab"\nnoise = 1\n')
    r = subprocess.run([sys.executable, "-m", "roadgonio", "intercompare", str(bad), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "participant[1].noise" in lines[0] and str(bad) in lines[0]


@pytest.mark.unit
def test_the_bundled_study_loads_and_participants_must_observe_alike(tmp_path, collimated):
    st = load_study("r3-comparison")
    assert [p.instrument.name for p in st.participants] == ["lab", "portable", "wide-road", "collimated"]
    assert {s.kind for s in st.shared} == {"reference_tile", "angle_standard"}
    other = tmp_path / "other.toml"
    other.write_text(COLLIMATED.replace('[source]', '[observation]\nalpha_deg = 1.5\n[source]'))
    study = _study(tmp_path, [_coll("A"), _coll("B", instrument="other.toml")])
    with pytest.raises(InputError, match="different directions"):
        run_study(study, workers=0, progress=False, plots=False)


# ---- what a comparison of consistent participants must show -------------------------------------

@pytest.mark.unit
def test_identical_collimated_participants_are_compatible_as_expected(tmp_path, collimated):
    """Four collimated participants (k_A = 1) whose only error is independent noise that they
    state: d_i / u(d_i) is N(0, 1), so |E_n| <= 1 in P(|Z| <= 2) = 95.45 % of the cells (against
    the weighted mean and against the truth), the Birge ratio^2 has mean 1, the consistency check
    passes in 95 %, and both consensus values carry tau^2 = 0 in most cells."""
    R = 40
    study = _study(tmp_path, [_coll(n, noise) for n, noise in (("A", 0.01), ("B", 0.02), ("C", 0.01), ("D", 0.03))],
                   realisations=R)
    ds = run_study(study, workers=0, progress=False, plots=False).dataset
    for ref in ("weighted_mean", "truth"):
        share = _per_realisation_share(ds["E_n"].sel(scenario="declared", reference=ref)
                                       .transpose("realisation", ...).values)
        assert abs(share.mean() - P_EN) < 4 * share.std(ddof=1) / math.sqrt(R) + 1e-3
    z = (ds["d"] / (ds["U_d"] / 2)).sel(scenario="declared", reference="weighted_mean").values
    z = z[np.isfinite(z)]
    assert float(np.std(z)) == pytest.approx(1.0, abs=4 / math.sqrt(2 * z.size / 4))
    rb2 = ds["birge_ratio"].sel(scenario="declared").values ** 2
    per = np.nanmean(rb2.reshape(R, -1), axis=1)
    assert abs(per.mean() - 1.0) < 4 * per.std(ddof=1) / math.sqrt(R)
    cons = np.nanmean(ds["consistent"].sel(scenario="declared").values.reshape(R, -1), axis=1)
    assert abs(cons.mean() - 0.95) < 4 * cons.std(ddof=1) / math.sqrt(R) + 1e-3
    # the truth is what an ideal instrument measures without error
    assert np.nanmax(np.abs(ds["k_a_nominal"].values - 1.0)) == 0.0
    # the all-corrected scenario of collimated instruments is the same comparison (nothing to correct)
    a = ds["r_reported"].sel(scenario="declared").values
    b = ds["r_reported"].sel(scenario="all_corrected").values
    assert np.array_equal(a, b, equal_nan=True)


@pytest.mark.unit
def test_a_shared_reference_tile_correlates_the_participants_as_it_should(tmp_path, collimated):
    """x_i = r (1 + c)(1 + e_i) with a tile error c ~ N(0, u_t^2) shared by A and B and independent
    noise e_i ~ N(0, s^2): corr(x_A, x_B) = u_t^2 / (u_t^2 + s^2 + u_t^2 s^2) in every cell; C,
    without the tile, is uncorrelated. The stated covariance carries the same u_t^2 x_A x_B."""
    R, ut, s = 400, 0.01, 0.005
    study = _study(tmp_path, [_coll("A", s, stated=["repeatability", "calibration"]),
                              _coll("B", s, stated=["repeatability", "calibration"]), _coll("C", s)],
                   [{"name": "tile", "kind": "reference_tile", "u_rel": ut, "participants": ["A", "B"]}],
                   realisations=R)
    run = run_study(study, workers=0, progress=False, plots=False)
    x = run.dataset["r_reported"].sel(scenario="declared").values         # (P, R, 29, 20)
    rel = x / run.dataset["truth"].values - 1.0
    expected = ut ** 2 / (ut ** 2 + s ** 2 + ut ** 2 * s ** 2)
    se_z = 1 / math.sqrt(R - 3)                                          # Fisher z of one cell
    for (i, j) in ((0, 0), (12, 3), (28, 0)):
        rab = np.corrcoef(rel[0, :, i, j], rel[1, :, i, j])[0, 1]
        rac = np.corrcoef(rel[0, :, i, j], rel[2, :, i, j])[0, 1]
        assert abs(np.arctanh(rab) - np.arctanh(expected)) < 4 * se_z
        assert abs(np.arctanh(rac)) < 4 * se_z
    from roadgonio.intercomparison.simulate import shared_components
    g = shared_components(run.setup)
    assert g.shape == (1, 3, len(run.setup.truth)) and np.all(g[0, :2] == ut) and np.all(g[0, 2] == 0)
    # with the correlation in the stated covariance, E_n against the weighted mean is as expected
    en = run.dataset["E_n"].sel(scenario="declared", reference="weighted_mean").transpose("realisation", ...).values
    share = _per_realisation_share(en)
    assert abs(share.mean() - P_EN) < 4 * share.std(ddof=1) / math.sqrt(R) + 1e-3


@pytest.mark.unit
def test_sensitivity_ranks_the_dominant_characteristic_first(tmp_path, collimated):
    """A participant whose calibration standard is 10x its noise: idealising the calibration
    lowers its RMS(d) most; a characteristic it does not have is not listed."""
    study = _study(tmp_path, [_coll("A", 0.001, calibration_u_rel=0.01, stated=["repeatability", "calibration"]),
                              _coll("B", 0.002), _coll("C", 0.002)], realisations=30)
    run = run_study(study, workers=0, progress=False, plots=False)
    sens = [r for r in json.loads(run.dataset.attrs["sensitivity_json"])
            if r["scenario"] == "declared" and r["participant"] == "A"]
    assert [r["characteristic"] for r in sens] == ["calibration", "noise"]
    assert sens[0]["drop_pct"] > 4 * sens[0]["drop_se_pct"] > 0
    assert sens[0]["rms_error_vs_truth_idealised_pct"] < 0.2 * sens[0]["rms_error_vs_truth_pct"]


# ---- resume, Dask, outputs ------------------------------------------------------------------------

@pytest.mark.unit
def test_resume_reuses_finished_realisations_and_gives_the_same_numbers(tmp_path, collimated):
    parts = [_coll("A", 0.01), _coll("B", 0.02, calibration_u_rel=0.005)]
    out = tmp_path / "out"
    run_study(_study(tmp_path, parts, realisations=4), out, workers=0, progress=False, plots=False)
    journal = out / "intercompare_journal.jsonl"
    lines4 = journal.read_text().splitlines()
    # an interruption cut the last line short: it is dropped and its work done again
    journal.write_text("\n".join(lines4[:-1]) + "\n" + lines4[-1][: len(lines4[-1]) // 2])
    run_study(_study(tmp_path, parts, realisations=6), out, workers=0, progress=False, plots=False)
    lines6 = journal.read_text().splitlines()
    assert lines6[:len(lines4) - 1] == lines4[:-1]                  # finished work kept as it was
    assert len([ln for ln in lines6 if '"realisation"' in ln]) == 6
    fresh = run_study(_study(tmp_path, parts, realisations=6), tmp_path / "fresh", workers=0, progress=False,
                      plots=False).dataset
    from roadgonio.intercomparison.outputs import read_intercomparison
    resumed = read_intercomparison(out / "intercompare.nc")
    assert np.array_equal(resumed["r_reported"].values, fresh["r_reported"].values, equal_nan=True)
    # a different study in the same folder is refused
    with pytest.raises(InputError, match="different study"):
        run_study(_study(tmp_path, parts, realisations=6, seed=8), out, workers=0, progress=False, plots=False)
    run_study(_study(tmp_path, parts, realisations=3, seed=8), out, workers=0, progress=False, plots=False, fresh=True)


@pytest.mark.system
@pytest.mark.timeout(600)
def test_two_dask_workers_give_the_numbers_of_the_in_process_run_and_the_outputs(tmp_path, collimated):
    parts = [_coll("A", 0.01), _coll("B", 0.02, calibration_u_rel=0.005), _coll("C", 0.01)]
    shared = [{"name": "tile", "kind": "reference_tile", "u_rel": 0.004, "participants": ["A", "C"]}]
    here = run_study(_study(tmp_path, parts, shared, realisations=5), workers=0, progress=False, plots=False).dataset
    out = tmp_path / "dask"
    dask = run_study(_study(tmp_path, parts, shared, realisations=5), out, workers=2, progress=False).dataset
    for v in ("r_reported", "u_stated", "d", "E_n", "reference_value"):
        assert np.array_equal(here[v].values, dask[v].values, equal_nan=True), v
    names = {p.name for p in out.iterdir()}
    assert {"intercompare.nc", "intercompare.csv", "sensitivity.csv", "validation.csv", "intercompare.json",
            "en_map_declared.png", "specular_row.png", "sensitivity.png", "compatibility.png"} <= names
    head = (out / "intercompare.csv").read_text().splitlines()[0].split(",")
    assert {"scenario", "participant", "share_En_le_1_weighted_mean", "birge_ratio_median"} <= set(head)
    prov = json.loads((out / "intercompare.json").read_text())["provenance"]
    assert prov["cluster"]["workers"] == 2 and prov["versions"]["roadgonio"]
    from roadgonio.intercomparison.outputs import read_intercomparison
    nc = read_intercomparison(out / "intercompare.nc")
    assert nc["truth"].attrs["units"] == "sr-1" and nc["E_n"].attrs["units"] == "1"
    assert set(nc["E_n"].dims) == {"scenario", "reference", "participant", "realisation", "tan_eps", "beta"}


# ---- instruments with an aperture effect (Mitsuba) ----------------------------------------------

@pytest.mark.plugin
@pytest.mark.timeout(600)
def test_a_participant_with_an_aperture_effect_shows_d_equal_to_its_k_a_bias(tmp_path, collimated, mi):
    """The lab preset without misalignment reports r_true k_A (1 + e): its degree of equivalence
    against the truth averages to r_true (k_A - 1) within its simulated spread; its nominal k_A
    agrees with an independent computation (the float64 quadrature) within both precisions; and
    idealising its apertures (k_A = 1) is the characteristic that matters most."""
    R, s = 30, 0.002
    study = _study(tmp_path, [{"name": "LAB", "instrument": "lab", "noise_rel": s}, _coll("REF", 0.002)],
                   realisations=R, corrected_realisations=0)
    run = run_study(study, workers=0, progress=False, plots=False)
    ds = run.dataset
    d = ds["d"].sel(scenario="declared", reference="truth", participant="LAB").values.astype(np.float64)
    t = ds["truth"].values
    k = ds["k_a_nominal"].sel(participant="LAB").values
    mean_rel = np.mean(d, axis=0) / t
    se = np.std(d / t, axis=0, ddof=1) / math.sqrt(R)
    fin = np.isfinite(k)
    # 396 cells, each a t statistic with 29 degrees of freedom: 5 SE (P(|t_29| > 5) = 2.4e-5 a cell);
    # d is stored as float32: 1e-7 relative of the value
    assert np.all(np.abs(mean_rel[fin] - (k[fin] - 1.0)) <= 5 * se[fin] + 4e-7 * (1 + np.abs(k[fin])))
    z = (mean_rel[fin] - (k[fin] - 1.0)) / se[fin]
    assert abs(float(np.std(z)) - math.sqrt(29 / 27)) < 4 * 1.04 / math.sqrt(2 * z.size)
    assert np.nanmax(np.abs(k - 1)) > 0.02            # the lab's aperture effect is real (specular cells)
    from roadgonio.engines import make_backend
    i, j = np.unravel_index(np.nanargmax(np.abs(k - 1)), k.shape)
    cells = [(float(ds.tan_eps[i]), float(ds.beta[j])), (2.0, 0.0), (0.0, 0.0)]
    quad = make_backend("quadrature", load_study_instrument(), run.setup.participants[0].mm.model, rtol=1e-4).compute(cells)
    for (tt, bb), c in zip(cells, quad):
        ki = float(ds["k_a_nominal"].sel(participant="LAB", tan_eps=tt, beta=bb))
        tol = 4 * (3e-3 * ki + c.standard_uncertainty())
        assert abs(ki - c.k_a) <= tol, (tt, bb, ki, c.k_a)
    sens = [r for r in json.loads(ds.attrs["sensitivity_json"]) if r["scenario"] == "declared"
            and r["participant"] == "LAB"]
    assert sens[0]["characteristic"] == "aperture_effect" and sens[0]["drop_pct"] > 0


def load_study_instrument():
    from roadgonio.instrument.config import load_instrument
    return load_instrument("lab")


@pytest.mark.plugin
@pytest.mark.timeout(900)
def test_participants_correcting_through_roadgonio_and_the_frozen_factor(tmp_path, collimated, mi):
    """The lab participant corrects its table (roadgonio correct --reference self) in the first two
    realisations; the corrected comparison is made there only (the others are NaN); the corrected
    tables are closer to the truth than the raw ones where k_A matters; the check of the frozen
    factor compares both on those realisations."""
    study = _study(tmp_path, [{"name": "LAB", "instrument": "lab", "noise_rel": 0.002,
                               "sigma": "alpha_deg=0.005,eps_deg=0.02"}, _coll("REF", 0.002)],
                   realisations=4, corrected_realisations=2)
    run = run_study(study, tmp_path / "out", workers=0, progress=False, plots=False)
    ds = run.dataset
    assert ds["full_correction"].sel(scenario="all_corrected", participant="LAB").values.tolist() == [1, 1, 0, 0]
    raw = ds["r_reported"].sel(scenario="declared", participant="LAB").values
    cor = ds["r_reported"].sel(scenario="all_corrected", participant="LAB").values
    t = ds["truth"].values
    assert np.isfinite(cor[:2][:, np.isfinite(t)]).all() and not np.isfinite(cor[2:]).any()
    cor, raw = cor[:2], raw[:2]
    k = ds["k_a_nominal"].sel(participant="LAB").values
    big = np.abs(k - 1) > 0.015
    assert big.sum() >= 3
    assert np.mean(np.abs(cor[:, big] / t[big] - 1)) < 0.5 * np.mean(np.abs(raw[:, big] / t[big] - 1))
    valid = json.loads(ds.attrs["validation_json"])
    assert {r["figure"] for r in valid} >= {"share_En_le_1_weighted_mean", "share_consistent_cells"}
    assert all(r["realisations"] == 2 for r in valid)


@pytest.mark.plugin
@pytest.mark.timeout(600)
def test_a_participant_correcting_with_the_surface_as_its_own_reference_reports_the_truth(tmp_path, collimated, mi):
    """report = "reference" with the true surface as the reference sample: r / k_A(reference) is
    r_true (1 + e) up to the k_A's own Monte Carlo error (the same backend computes both, with
    different seeds), and the stated u adds that correction's budget to the repeatability."""
    R, s = 20, 0.002
    study = _study(tmp_path, [{"name": "LAB", "instrument": "lab", "noise_rel": s, "report": "reference",
                               "reference": "R3", "stated": ["repeatability"]}, _coll("REF", 0.002)],
                   realisations=R, corrected_realisations=0)
    ds = run_study(study, workers=0, progress=False, plots=False).dataset
    x = ds["r_reported"].sel(scenario="declared", participant="LAB").values
    t = ds["truth"].values
    fin = np.isfinite(t)                                       # the comparison's cells
    rel = np.full(t.shape, np.nan)
    rel[fin] = np.mean(x[:, fin], axis=0) / t[fin] - 1
    # k_A with rel. SE 3e-3 (the study's tables) and 1e-3 (the correction's): 4 sigma, plus the noise
    assert np.all(np.abs(rel[fin]) <= 4 * math.hypot(3e-3, 1e-3, s / math.sqrt(R)))
    u = ds["u_stated"].sel(scenario="declared", participant="LAB").values / x
    assert np.all(u[np.isfinite(u)] > s)                       # the correction's budget is stated on top
