"""roadgonio intercompare in this process with collimated participants (no k_A backend): the study
file's one-line errors, the comparison's hand-checkable cases (consistent participants, a shared
tile's correlation), the sensitivity ranking, resume."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from helpers import on_a_zero_size_terminal
from helpers_intercomparison import COLLIMATED, P_EN, coll, make_study, per_realisation_share, write_collimated
from roadgonio.errors import InputError
from roadgonio.intercomparison.run import run_study
from roadgonio.intercomparison.study import load_study, study_from_dict


@pytest.fixture()
def collimated(tmp_path):
    return write_collimated(tmp_path)


@pytest.mark.parametrize("change, field, words", [
    (lambda d: d["participant"][0].update(noise=0.1), "participant[1].noise", "unknown key"),
    (lambda d: d["study"].update(realisation=3), "study.realisation", "unknown key"),
    (lambda d: d.update(extra={}), "extra", "unknown key"),
    (lambda d: d["participant"][1].update(report="reference"), "participant[2].reference", "needs reference"),
    (lambda d: d["participant"][1].update(report="self", noise_rel=0.0), "participant[2].noise_rel", "noise_rel >= 1e-06"),
    (lambda d: d["participant"][1].update(report="self", noise_rel=1e-9), "participant[2].noise_rel", "noise_rel >= 1e-06"),
    # user audit: a raw participant with an aperture and no repeatability was accepted, then the all-corrected
    # scenario's correction refused 'u_measured' after the k_A work, naming neither the file nor the participant
    (lambda d: d["participant"][1].update(instrument="lab", noise_rel=0.0, calibration_u_rel=0.002,
                                          stated=["calibration"]), "participant[2].noise_rel", "all-corrected scenario"),
    (lambda d: d["participant"][0].update(sigma="alpha=0.1"), "participant[1].sigma alpha", "unknown key"),
    (lambda d: d["participant"][0].update(stated=["aperture"]), "participant[1].stated", "unknown stated"),
    (lambda d: d["participant"][1].update(name="A"), "participant.name", "two participants"),
    # the file looked for named (user audit, session 44)
    (lambda d: d["participant"][0].update(instrument="nope.toml"), "participant[1].instrument",
     "nope.toml: no such instrument file"),
    (lambda d: d["shared"].append({"name": "t", "kind": "reference_tile", "u_rel": 0.01, "participants": ["A", "Z"]}),
     "shared[1].participants", "no participant named"),
    (lambda d: d["shared"].append({"name": "t", "kind": "angle_standard", "u_rel": 0.01, "participants": ["A", "B"]}),
     "shared[1].u_rel", "not u_rel"),
    (lambda d: d["study"].update(realisations=1), "study.realisations", ">= 2"),
    (lambda d: d["study"].pop("surface"), "study.surface", "missing"),
    # audit 22: 0 corrected realisations with a participant reporting "self" crashed or compared nothing
    (lambda d: (d["participant"][0].update(report="self", noise_rel=0.002), d["study"].update(
        realisations=4, corrected_realisations=0)), "study.corrected_realisations", "corrected_realisations >= 2"),
    # audit 22: 1e12 realisations were accepted (and hung), 6.0 taken as 6, 2^63 named no file
    (lambda d: d["study"].update(realisations=10 ** 12), "study.realisations", "<= 100000"),
    (lambda d: d["study"].update(realisations=6.0), "study.realisations", "whole number"),
    (lambda d: d["study"].update(seed=7.0), "study.seed", "whole number"),
    (lambda d: d["study"].update(seed=2 ** 63), "study.seed", "<= 9223372036854775807"),
    # audit 27: a raw table stated with u = 0 was accepted and refused after the k_A work, naming nothing
    (lambda d: d["participant"][0].update(stated=[]), "participant[1].stated", "uncertainty that is 0"),
    # audit 27: an inline sigma table's error named the key alone ('eps_deg'), not whose
    (lambda d: d["participant"][1].update(sigma={"eps_deg": "0.02:tri"}), "participant[2].sigma.eps_deg",
     "unknown distribution"),
    (lambda d: d["participant"][1].update(noise_rel=0.0), "participant[2].stated", "uncertainty that is 0"),
])
def test_bad_study_files_are_one_line_errors_naming_file_and_field(tmp_path, collimated, change, field, words):
    d = {"study": {"surface": "R3"}, "participant": [coll("A"), coll("B")], "shared": []}
    change(d)
    with pytest.raises(InputError) as err:
        study_from_dict(d, path=tmp_path / "study.toml")
    assert err.value.field == field
    assert str(tmp_path / "study.toml") in str(err.value)
    assert words in err.value.reason
    assert "\n" not in str(err.value)


def test_a_participant_without_repeatability_is_accepted_where_nothing_corrects_its_table(tmp_path, collimated):
    """The all-corrected scenario's need of noise_rel is the only one: without corrected realisations,
    or for a collimated instrument (nothing to correct), noise_rel = 0 with another stated component is a study."""
    lab = dict(instrument="lab", noise_rel=0.0, calibration_u_rel=0.002, stated=["calibration"])
    d = {"study": {"surface": "R3", "realisations": 4, "corrected_realisations": 0},
         "participant": [coll("A"), coll("B", **lab)], "shared": []}
    assert study_from_dict(d, path=tmp_path / "study.toml").participants[1].noise_rel == 0.0
    d = {"study": {"surface": "R3"}, "participant": [coll("A"), coll("B", **{**lab, "instrument": "collimated.toml"})],
         "shared": []}
    assert study_from_dict(d, path=tmp_path / "study.toml").participants[1].noise_rel == 0.0


def test_a_study_takes_the_backends_and_default_tolerances_of_the_uncertainty_command(tmp_path, collimated):
    """The study listed its backends and their default tolerances itself (a copy of the uncertainty
    room's table) and wrote the quadrature's rtol to its provenance as "rel_se". Both now come from
    the registry's study_tolerance, and the provenance names the setting."""
    from roadgonio import api
    from roadgonio.engines.registry import BACKENDS
    tolerances = api.study_tolerances()
    assert list(tolerances) == list(api.backends("uncertainty")) == ["mitsuba", "quadrature"]
    for name, (setting, value) in tolerances.items():
        st = make_study(tmp_path, [coll("A"), coll("B")], backend=name)
        assert st.tolerance == value and setting == BACKENDS[name].tolerance
        assert st.to_dict()["tolerance"] == {setting: value} and "rel_se" not in st.to_dict()
    assert make_study(tmp_path, [coll("A"), coll("B")], backend="quadrature", rel_se=1e-5).to_dict()["tolerance"] == \
        {"rtol": 1e-5}
    with pytest.raises(InputError, match="expected one of mitsuba, quadrature"):
        make_study(tmp_path, [coll("A"), coll("B")], backend="numpy-mc")


def test_the_bundled_study_loads_and_participants_must_observe_alike(tmp_path, collimated):
    st = load_study("r3-comparison")
    assert [p.instrument.name for p in st.participants] == ["lab", "corridor", "fixed-led", "collimated"]
    assert {s.kind for s in st.shared} == {"reference_tile", "angle_standard"}
    other = tmp_path / "other.toml"
    other.write_text(COLLIMATED.replace('[source]', '[observation]\nalpha_deg = 1.5\n[source]'))
    study = make_study(tmp_path, [coll("A"), coll("B", instrument="other.toml")])
    with pytest.raises(InputError, match="different directions"):
        run_study(study, workers=0, progress=False, plots=False)


def test_a_stated_uncertainty_that_misses_some_cells_is_refused_naming_participant_and_cells(tmp_path, collimated):
    """A participant stating only its misalignment, with a beta error alone: its table does not move
    with beta at tan eps 0, so it states u = 0 there. Refused after the nominal sensitivities (no
    realisation run) by a line naming the file, the participant and the cells (audit 27: "every
    stated standard uncertainty must be positive", naming neither)."""
    study = make_study(tmp_path, [coll("A", stated=["misalignment"], sigma="beta_deg=0.05"), coll("B")])
    with pytest.raises(InputError) as err:
        run_study(study, workers=0, progress=False, plots=False)
    assert err.value.field == "participant[1].stated"
    assert str(tmp_path / "study.toml") in str(err.value) and "'A'" in err.value.reason
    assert "0:0" in err.value.reason and "\n" not in str(err.value)
    # with its repeatability stated as well, the same study runs
    ok = make_study(tmp_path, [coll("A", stated=["misalignment", "repeatability"], sigma="beta_deg=0.05"), coll("B")])
    assert run_study(ok, workers=0, progress=False, plots=False).dataset is not None


def test_identical_collimated_participants_are_compatible_as_expected(tmp_path, collimated):
    """Four collimated participants (k_A = 1) whose only error is independent noise that they
    state: d_i / u(d_i) is N(0, 1), so |E_n| <= 1 in P(|Z| <= 2) = 95.45 % of the cells (against
    the weighted mean and against the truth), the Birge ratio^2 has mean 1, the consistency check
    passes in 95 %, and both consensus values carry tau^2 = 0 in most cells."""
    R = 40
    study = make_study(tmp_path, [coll(n, noise) for n, noise in (("A", 0.01), ("B", 0.02), ("C", 0.01), ("D", 0.03))],
                   realisations=R)
    ds = run_study(study, workers=0, progress=False, plots=False).dataset
    for ref in ("weighted_mean", "truth"):
        share = per_realisation_share(ds["E_n"].sel(scenario="declared", reference=ref)
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
    assert np.nanmax(np.abs(ds["k_a_nominal_u"].values)) == 0.0 and np.isfinite(ds["k_a_nominal_u"].values).sum() > 0
    # the all-corrected scenario of collimated instruments is the same comparison (nothing to correct)
    a = ds["r_reported"].sel(scenario="declared").values
    b = ds["r_reported"].sel(scenario="all_corrected").values
    assert np.array_equal(a, b, equal_nan=True)
    # ... and the summary says so: a collimated participant reports its table raw there, not 'self'
    rows = json.loads(ds.attrs["summary_json"])
    ours = [r for r in rows if r["participant"] != "ALL"]
    assert {r["scenario"] for r in ours} >= {"declared", "all_corrected"}
    assert all(r["reports"] == "raw" and r["full_corrections"] is None for r in ours)


@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_a_shared_reference_tile_correlates_the_participants_as_it_should(tmp_path, collimated):
    """x_i = r (1 + c)(1 + e_i) with a tile error c ~ N(0, u_t^2) shared by A and B and independent
    noise e_i ~ N(0, s^2): corr(x_A, x_B) = u_t^2 / (u_t^2 + s^2 + u_t^2 s^2) in every cell; C,
    without the tile, is uncorrelated. The stated covariance carries the same u_t^2 x_A x_B."""
    R, ut, s = 400, 0.01, 0.005
    study = make_study(tmp_path, [coll("A", s, stated=["repeatability", "calibration"]),
                              coll("B", s, stated=["repeatability", "calibration"]), coll("C", s)],
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
    rows = {(r["participant_a"], r["participant_b"]): r for r in json.loads(run.dataset.attrs["correlation_json"])
            if r["scenario"] == "declared"}
    assert abs(np.arctanh(rows[("A", "B")]["simulated_median"]) - np.arctanh(expected)) < 4 * se_z
    assert rows[("A", "B")]["stated_median"] == pytest.approx(ut ** 2 / (ut ** 2 + s ** 2), rel=1e-12)
    assert abs(rows[("A", "C")]["simulated_median"]) < 4 * se_z and rows[("A", "C")]["stated_median"] == 0.0
    from roadgonio.intercomparison.simulate import shared_components
    g = shared_components(run.setup)
    assert g.shape == (1, 3, len(run.setup.truth)) and np.all(g[0, :2] == ut) and np.all(g[0, 2] == 0)
    # with the correlation in the stated covariance, E_n against the weighted mean is as expected
    en = run.dataset["E_n"].sel(scenario="declared", reference="weighted_mean").transpose("realisation", ...).values
    share = per_realisation_share(en)
    assert abs(share.mean() - P_EN) < 4 * share.std(ddof=1) / math.sqrt(R) + 1e-3


def test_sensitivity_ranks_the_dominant_characteristic_first(tmp_path, collimated):
    """A participant whose calibration standard is 10x its noise: idealising the calibration
    lowers its RMS(d) most; a characteristic it does not have is not listed."""
    study = make_study(tmp_path, [coll("A", 0.001, calibration_u_rel=0.01, stated=["repeatability", "calibration"]),
                              coll("B", 0.002), coll("C", 0.002)], realisations=30)
    run = run_study(study, workers=0, progress=False, plots=False)
    sens = [r for r in json.loads(run.dataset.attrs["sensitivity_json"])
            if r["scenario"] == "declared" and r["participant"] == "A"]
    assert [r["characteristic"] for r in sens] == ["calibration", "noise"]
    assert sens[0]["drop_pct"] > 4 * sens[0]["drop_se_pct"] > 0
    assert sens[0]["rms_error_vs_truth_idealised_pct"] < 0.2 * sens[0]["rms_error_vs_truth_pct"]


def test_resume_reuses_finished_realisations_and_gives_the_same_numbers(tmp_path, collimated):
    parts = [coll("A", 0.01), coll("B", 0.02, calibration_u_rel=0.005)]
    out = tmp_path / "out"
    run_study(make_study(tmp_path, parts, realisations=4), out, workers=0, progress=False, plots=False)
    journal = out / "intercompare_journal.jsonl"
    lines4 = journal.read_text().splitlines()
    # an interruption cut the last line short: it is dropped and its work done again
    journal.write_text("\n".join(lines4[:-1]) + "\n" + lines4[-1][: len(lines4[-1]) // 2])
    run_study(make_study(tmp_path, parts, realisations=6), out, workers=0, progress=False, plots=False)
    lines6 = journal.read_text().splitlines()
    assert lines6[:len(lines4) - 1] == lines4[:-1]                  # finished work kept as it was
    assert len([ln for ln in lines6 if '"realisation"' in ln]) == 6
    fresh = run_study(make_study(tmp_path, parts, realisations=6), tmp_path / "fresh", workers=0, progress=False,
                      plots=False).dataset
    from roadgonio.intercomparison.outputs import read_intercomparison
    resumed = read_intercomparison(out / "intercompare.nc")
    assert np.array_equal(resumed["r_reported"].values, fresh["r_reported"].values, equal_nan=True)
    # a different study in the same folder is refused
    with pytest.raises(InputError, match="different study"):
        run_study(make_study(tmp_path, parts, realisations=6, seed=8), out, workers=0, progress=False, plots=False)
    run_study(make_study(tmp_path, parts, realisations=3, seed=8), out, workers=0, progress=False, plots=False, fresh=True)


def test_a_fixed_led_participant_reports_its_measured_cells_and_the_fill_of_them(tmp_path, collimated):
    """A collimated instrument that measures only some cells ([cells], zero apertures, tiny noise):
    its measured cells are the truth x (1 + noise), every other cell is the fill of them
    (roadgonio.instrument.coverage, checked there), so its error against the truth is the fill's error
    of the true table; idealising the fill removes it (the sensitivity ranking puts it first)."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.uncertainty.cells import CellSet
    led = load_instrument("fixed-led")
    cells = ",\n".join(f"[{t}, {b}]" for t, b in led.cells.measured)
    (tmp_path / "led.toml").write_text(COLLIMATED.replace('name = "collimated"', 'name = "led"')
                                       + f"[cells]\nmeasured = [\n{cells}\n]\n")
    study = make_study(tmp_path, [coll("A", 1e-6), coll("LED", 1e-6, instrument="led.toml")], realisations=4)
    run = run_study(study, workers=0, progress=False, plots=False)
    ds = run.dataset
    cs = CellSet.make("standard")
    truth = ds["truth"].values[cs.ii, cs.jj]
    fill = led.cells.fill_table(cs.tan_eps, cs.beta_deg, truth)
    x = ds["r_reported"].sel(scenario="declared", participant="LED").values[..., cs.ii, cs.jj]
    assert np.max(np.abs(x / fill - 1)) < 1e-5                        # the fill of the (noise-free) truth
    measured = np.array([cs.index(t, b) for t, b in led.cells.measured])
    assert np.max(np.abs(x[..., measured] / truth[measured] - 1)) < 1e-5
    assert np.sqrt(np.mean((fill / truth - 1) ** 2)) > 0.05         # and the fill is far from the truth
    sens = [r for r in json.loads(ds.attrs["sensitivity_json"])
            if r["scenario"] == "declared" and r["participant"] == "LED"]
    assert sens[0]["characteristic"] == "fill", sens[:3]
    assert sens[0]["rms_error_vs_truth_idealised_pct"] < 0.01 * sens[0]["rms_error_vs_truth_pct"]


def test_every_instrument_with_an_aperture_effect_has_a_source_distance_item_arc_or_rail():
    """The ranking's `source_distance` item is one definition for both source paths (session 13):
    an arc source's distance (the lab's 5 m, the fixed-LED device's 0.6 m) had no item, only a
    rail's; a collimated instrument (k_A = 1 at any distance) has none. The study's k_A tables and
    the ranking's rows come from the same list (k_characteristics)."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.intercomparison.simulate import k_characteristics
    keys = {n: [k for k, _ in k_characteristics(load_instrument(n))]
            for n in ("lab", "fixed-led", "corridor", "collimated")}
    assert keys["lab"] == ["source_aperture", "detector_pupil", "detector_field", "source_distance"]
    assert "source_distance" in keys["fixed-led"] and "source_distance" in keys["corridor"]
    assert keys["collimated"] == []


@pytest.mark.parametrize("preset", ["lab", "corridor"])
def test_the_source_distance_idealised_is_the_source_far_away_at_the_same_angular_size(preset):
    """The ranking's `source_distance` item (trial 11 D9 for a rail, session 13 for an arc): the
    source's one length (an arc's distance, a rail's height) made SOURCE_FAR_M and its aperture
    scaled alike, so the source has the same angular size at every cell, and an idealised instrument
    that is better than the real one, not worse (for the rail it was an arc of radius its height:
    the source at its nearest everywhere, k_A 5x farther from 1, 18.5 % against 3.4 % RMS over R3's
    cells). Quadrature: deterministic, every difference below beyond its error bounds."""
    import roadgonio as rg
    from roadgonio.instrument.config import load_instrument
    from roadgonio.instrument.optics import source_distance_m
    from roadgonio.intercomparison.run import idealised_instrument
    from roadgonio.intercomparison.simulate import SOURCE_FAR_M
    inst = load_instrument(preset)
    far = idealised_instrument(inst, "source_distance")
    assert far.source.path == inst.source.path and far.detector == inst.detector
    assert far.calibration == inst.calibration and far.observation == inst.observation
    assert far.source.length_m == SOURCE_FAR_M
    for t in (0.0, 2.0, 12.0):
        d0, d1 = source_distance_m(inst.source, t), source_distance_m(far.source, t)
        assert d1 == pytest.approx(SOURCE_FAR_M / inst.source.length_m * d0, rel=1e-12)
        assert far.source.radius_m / d1 == pytest.approx(inst.source.radius_m / d0, rel=1e-12)
    cells = "0:0,2:0,5:0,1:30"
    k = {n: rg.ka_table(i, "R3", backend="quadrature", accuracy="default", cells=cells)
         for n, i in (("near", inst), ("far", far))}
    dev = {n: np.abs(d.k_a.values - 1)[np.isfinite(d.k_a.values)] for n, d in k.items()}
    bound = {n: d.error_bound.values[np.isfinite(d.k_a.values)] for n, d in k.items()}
    assert np.all(dev["far"] + bound["far"] < dev["near"] - bound["near"]), (dev, bound)


@pytest.mark.parametrize("preset", ["lab", "corridor"])
def test_the_far_source_keeps_the_solid_angle_and_lights_the_footprint_uniformly(preset):
    """The two limits of the `source_distance` item, arc and rail alike. (1) A single-ray detector
    sees only the sample centre, which sees the far source's disc exactly as the near one (same
    direction, same angular size): k_A is the same up to the quadrature's bounds, while a point
    source there (the aperture not scaled with the distance) gives another k_A. (2) Absolute
    calibration, Lambertian sample: k_A = <E>/E_0 (conventions section 5), and to first order
    E(x)/E_0 = 1 + 3 (x . s_hat)/D for a footprint point x and a source D away, so the far source's
    k_A is 1 within 3 L / D_far (L: the footprint's half-length, (D_D tan gamma + R_D) / sin alpha),
    where the near source's is not."""
    import roadgonio as rg
    from roadgonio.engines.calibration import illuminance_ratio
    from roadgonio.instrument.config import load_instrument
    from roadgonio.intercomparison.run import idealised_instrument
    from roadgonio.intercomparison.simulate import SOURCE_FAR_M
    from tolerances import ROUND_TOL
    inst = load_instrument(preset)
    ray = inst.with_changes(detector={"pupil_radius_m": 0.0, "field_half_angle_deg": 0.0})
    cells = "0:0,5:0,1:30,12:0"
    k = {n: rg.ka_table(i, "R3", backend="quadrature", accuracy="default", cells=cells)
         for n, i in (("near", ray), ("far", idealised_instrument(ray, "source_distance")),
                      ("point", ray.with_changes(source={"radius_m": 0.0})))}
    val = {n: d.k_a.values[np.isfinite(d.k_a.values)] for n, d in k.items()}
    bnd = {n: d.error_bound.values[np.isfinite(d.k_a.values)] for n, d in k.items()}
    assert np.all(np.abs(val["far"] - val["near"]) <= bnd["far"] + bnd["near"] + ROUND_TOL), val
    assert np.max(np.abs(val["point"] - val["near"]) - bnd["near"]) > 1e-3, val
    absolute = inst.with_changes(calibration={"mode": "absolute"})
    far = idealised_instrument(absolute, "source_distance")
    d, obs = inst.detector, inst.observation
    half_length = ((d.distance_m * math.tan(math.radians(d.field_half_angle_deg)) + d.pupil_radius_m)
                   / math.sin(math.radians(obs.alpha_deg)))
    limit = 3 * half_length / SOURCE_FAR_M
    for t, b in ((0.0, 0.0), (2.0, 0.0), (5.0, 0.0), (1.0, 30.0), (12.0, 0.0)):
        eta_far, err_far, _ = illuminance_ratio(far, t, b)
        eta_near, err_near, _ = illuminance_ratio(absolute, t, b)
        assert abs(eta_far - 1) + err_far <= limit < abs(eta_near - 1) - err_near, (t, b, eta_near, eta_far)


def test_intercompare_shows_tasks_done_over_total_evenon_a_zero_size_terminal(tmp_path, collimated, monkeypatch):
    """The progress of every stage (tasks done / total) on a terminal, also one that reports 0 x 0,
    where tqdm's own sizing drew nothing at all (before: a 277 s run silent under `script`)."""
    study = make_study(tmp_path, [coll("A"), coll("B")], realisations=6)
    text = on_a_zero_size_terminal(monkeypatch, lambda: run_study(study, workers=0, progress=True, plots=False))
    assert "k_A of the participants: 100%" in text and "2/2" in text
    assert "realisations: 100%" in text and "6/6" in text
    quiet = on_a_zero_size_terminal(monkeypatch, lambda: run_study(study, workers=0, progress=False, plots=False))
    assert quiet == ""


def test_the_csv_files_have_their_header_row_even_without_rows(tmp_path, collimated):
    """validation.csv of a study without corrections was one newline (pandas: EmptyDataError);
    so is correlation.csv with fewer than 3 realisations."""
    import pandas as pd
    from roadgonio.intercomparison.outputs import CORRELATION_COLUMNS, VALIDATION_COLUMNS, rows_csv
    empty = pd.read_csv(__import__("io").StringIO(rows_csv([], VALIDATION_COLUMNS)))
    assert list(empty.columns) == list(VALIDATION_COLUMNS) and len(empty) == 0
    out = tmp_path / "out"
    run_study(make_study(tmp_path, [coll("A"), coll("B")], realisations=2), out, workers=0, progress=False, plots=False)
    corr = pd.read_csv(out / "correlation.csv")                # 2 realisations: no correlation to give
    assert list(corr.columns) == list(CORRELATION_COLUMNS) and len(corr) == 0
    # collimated under a Lambert calibration: no correction changes a table, so there is nothing to check
    # (user audit: rows of differences 0 +- 0 looked like a check that passed)
    valid = pd.read_csv(out / "validation.csv")
    assert list(valid.columns) == list(VALIDATION_COLUMNS) and len(valid) == 0


def test_the_command_says_why_validation_csv_is_empty_when_nothing_is_corrected(tmp_path, collimated, capsys):
    """Collimated participants under a Lambert calibration: the command says that no correction
    changes a table (not that too few realisations were corrected, which is not the reason)."""
    from roadgonio.cli import main
    study = tmp_path / "study.toml"
    study.write_text('[study]\nsurface = "R3"\nrealisations = 3\nseed = 7\nbackend = "quadrature"\n' + "".join(
        f'[[participant]]\nname = "{n}"\ninstrument = "collimated.toml"\nnoise_rel = 0.01\nstated = ["repeatability"]\n'
        for n in "AB"))
    assert main(["intercompare", str(study), "--out", str(tmp_path / "o"), "--workers", "0", "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert "validation.csv has its header only: no participant's correction changes its table" in out
    assert "needs at least 2 realisations" not in out


def test_a_scenario_no_realisation_compared_gets_no_bars_in_compatibility_png():
    from roadgonio.intercomparison.outputs import compared_scenarios
    rows = [{"scenario": "declared", "participant": "A"}, {"scenario": "declared", "participant": "ALL", "realisations": 20},
            {"scenario": "all_corrected", "participant": "A"},
            {"scenario": "all_corrected", "participant": "ALL", "realisations": 0}]
    assert compared_scenarios(rows) == ["declared"]
    rows[-1]["realisations"] = 2
    assert compared_scenarios(rows) == ["declared", "all_corrected"]


def test_the_frozen_factor_is_the_geometric_mean_of_every_correction_and_the_rms_of_their_u():
    """The frozen factor of a self-correcting participant (scenario all_corrected_frozen): the
    geometric mean of the k of all its corrections (realisations 0 ... n_corrected - 1) and the RMS
    of their relative u, per cell; a participant without corrections has none. Written out with
    numpy over 3 corrections of 2 cells (mutation audit 9b: a factor leaving out the last
    correction passed every test but a Mitsuba plugin test)."""
    from types import SimpleNamespace

    from roadgonio.intercomparison.run import frozen_factors, pack
    rng = np.random.default_rng(5)
    ks = rng.uniform(0.8, 1.3, (3, 2))
    us = rng.uniform(0.005, 0.03, (3, 2))
    records = {("self", 0, m): {"k": pack(ks[m]), "u_rel": pack(us[m])} for m in range(3)}
    setup = SimpleNamespace(participants=[SimpleNamespace(k_frozen=None, u_frozen_rel=None),
                                          SimpleNamespace(k_frozen=np.ones(2), u_frozen_rel=np.ones(2))])
    ident = frozen_factors(setup, records, 3)
    a, b = setup.participants
    want_k = np.array([math.prod(ks[:, j]) ** (1 / 3) for j in range(2)])
    want_u = np.array([math.sqrt(sum(us[:, j] ** 2) / 3) for j in range(2)])
    np.testing.assert_allclose(a.k_frozen, want_k, rtol=1e-12, atol=0.0)
    np.testing.assert_allclose(a.u_frozen_rel, want_u, rtol=1e-12, atol=0.0)
    assert b.k_frozen is None and b.u_frozen_rel is None
    # the identifier changes with the factors (realisations computed with other factors are redone)
    records[("self", 0, 2)] = {"k": pack(ks[2] * 1.01), "u_rel": pack(us[2])}
    assert frozen_factors(setup, records, 3) != ident


def test_a_shared_effects_draws_are_independent_of_every_participants_own_draws():
    """The draws of one realisation: each participant's misalignment, noise and calibration variates
    and each shared effect's variate come from streams of their own, so a shared tile is
    uncorrelated with every participant's own errors (mutation audit 9b: a tile drawn from the first
    participant's stream, equal to its first misalignment variate, passed every test: the tile test
    has participants without misalignment). Fisher's z of the correlation over 400 realisations,
    each of the 2 x 9 checks at the family-wise threshold."""
    from types import SimpleNamespace

    from roadgonio.intercomparison import simulate as sim
    from roadgonio.uncertainty.spec import INPUTS, SigmaSpec
    from tolerances import z_family
    spec = SigmaSpec(sigma=tuple(0.1 * (k + 1) for k in range(len(INPUTS))), distribution=("normal",) * len(INPUTS))
    m = 400
    setup = SimpleNamespace(seed=3, realisations=m, P=2, participants=[SimpleNamespace(spec=spec, n=3)] * 2,
                            shared=[SimpleNamespace(kind="reference_tile")])
    d = [sim.draws(setup, i) for i in range(m)]
    tile = np.array([x.shared[0] for x in d])
    z_lim = z_family(2 * (len(INPUTS) + 2))
    for p in range(2):
        own = np.column_stack([np.array([x.X[p] for x in d]), [x.z_noise[p][0] for x in d], [x.z_cal[p] for x in d]])
        for k in range(own.shape[1]):
            r = np.corrcoef(tile, own[:, k])[0, 1]
            assert abs(math.atanh(r)) * math.sqrt(m - 3) < z_lim, (p, k, r)


def _csv_rows(path):
    import csv
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_the_csv_summaries_are_the_numbers_of_intercompare_nc(tmp_path, collimated):
    """intercompare.csv, correlation.csv and sensitivity.csv against the same figures recomputed
    with numpy from the arrays of intercompare.nc (reported r, stated u, E_n, d, Birge ratio,
    consistency, consensus values and tau^2); the sensitivity's unidealised figures are the
    summary's, its ranks count 1, 2, ... in order of the drop. Three collimated participants, A and C
    sharing a reference tile (a stated correlation), B with an unstated calibration error (tau^2 >
    0). Mutation audit 11: SEs over R instead of sqrt(R), an RMS as a mean |error|, the stated u
    not in %, tau^2 for tau, every consensus' error as the weighted mean's, the correlation's
    percentiles mislabelled or its errors not centred, the pair's names swapped, a share of the
    weighted mean's compatibility for the truth's, and ranks all 1 passed every test."""
    from roadgonio.intercomparison.run import RANDOM_EFFECTS_MIN_PARTICIPANTS, REFERENCES
    from roadgonio.intercomparison.statistics import METHODS
    R, ut = 5, 0.01
    noise = {"A": 0.005, "B": 0.01, "C": 0.004}
    parts = [coll("A", noise["A"], stated=["repeatability", "calibration"]),
             coll("B", noise["B"], calibration_u_rel=0.03),
             coll("C", noise["C"], stated=["repeatability", "calibration"])]
    study = make_study(tmp_path, parts, [{"name": "tile", "kind": "reference_tile", "u_rel": ut,
                                          "participants": ["A", "C"]}], realisations=R)
    out = tmp_path / "out"
    ds = run_study(study, out, workers=0, progress=False, plots=False).dataset
    truth = ds["truth"].values
    cell = np.isfinite(truth)
    t = truth[cell]
    dec = ds.sel(scenario="declared")
    summary = {r["participant"]: r for r in _csv_rows(out / "intercompare.csv") if r["scenario"] == "declared"}

    def near(row, want):
        for key, v in want.items():
            assert float(row[key]) == pytest.approx(float(v), rel=1e-5, abs=1e-12), (key, row[key], v)

    X = dec["r_reported"].values[:, :, cell]                        # (participant, realisation, cell)
    U = dec["u_stated"].values[:, :, cell] / X                       # relative
    for p, name in enumerate(noise):
        err = X[p] / t - 1.0
        d = dec["d"].sel(reference="weighted_mean", participant=name).values[:, cell].astype(np.float64)
        want = {"realisations": R, "repeatability_pct": 100 * noise[name], "stated_u_median_pct": 100 * np.median(U[p]),
                "rms_error_vs_truth_pct": 100 * np.sqrt(np.mean(err ** 2)),
                "max_abs_mean_error_vs_truth_pct": 100 * np.max(np.abs(err.mean(axis=0))),
                "rms_d_weighted_mean_pct": 100 * np.sqrt(np.mean((d / t) ** 2))}
        for ref in REFERENCES:
            if len(noise) < RANDOM_EFFECTS_MIN_PARTICIPANTS.get(ref, 0):       # 1 by construction: blank
                assert summary[name][f"share_En_le_1_{ref}"] == summary[name][f"share_En_le_1_{ref}_se"] == ""
                continue
            share = np.mean(np.abs(dec["E_n"].sel(reference=ref, participant=name).values[:, cell]) <= 1.0, axis=1)
            want[f"share_En_le_1_{ref}"] = share.mean()
            want[f"share_En_le_1_{ref}_se"] = share.std(ddof=1) / math.sqrt(R)
        near(summary[name], want)
    cons = dec["consistent"].values[:, cell].mean(axis=1)
    en = dec["E_n"].sel(reference="weighted_mean").values[:, :, cell]
    want = {"birge_ratio_median": np.median(dec["birge_ratio"].values[:, cell]), "share_consistent_cells": cons.mean(),
            "share_consistent_cells_se": cons.std(ddof=1) / math.sqrt(R),
            "share_all_compatible_weighted_mean": np.mean(np.all(np.abs(en) <= 1.0, axis=0)),
            "share_all_compatible_weighted_mean_se": np.mean(np.all(np.abs(en) <= 1.0, axis=0), axis=1).std(ddof=1)
            / math.sqrt(R)}
    for m in METHODS:
        v = dec["reference_value"].sel(consensus=m).values[:, cell]
        want[f"rms_error_{m}_vs_truth_pct"] = 100 * np.sqrt(np.mean((v / t - 1.0) ** 2))
    for m in ("mandel_paule", "dersimonian_laird"):
        want[f"tau_rel_median_{m}_pct"] = 100 * np.median(np.sqrt(dec["tau2"].sel(consensus=m).values[:, cell]) / t)
        assert want[f"tau_rel_median_{m}_pct"] > 0.0                 # B's unstated error: the case shows tau
    near(summary["ALL"], want)
    # correlation.csv: per pair, the errors' correlation over the realisations and the stated one
    e = X / t - 1.0
    e = e - e.mean(axis=1, keepdims=True)
    sd = np.sqrt(np.mean(e * e, axis=1))
    u_med = np.median(U, axis=1)
    g = np.array([ut, 0.0, ut])
    corr = [r for r in _csv_rows(out / "correlation.csv") if r["scenario"] == "declared"]
    assert [(r["participant_a"], r["participant_b"]) for r in corr] == [("A", "B"), ("A", "C"), ("B", "C")]
    for r, (i, j) in zip(corr, ((0, 1), (0, 2), (1, 2))):
        emp = np.mean(e[i] * e[j], axis=0) / (sd[i] * sd[j])
        stated = g[i] * g[j] / (u_med[i] * u_med[j])
        want = {"realisations": R}
        for key, v in (("simulated", emp), ("stated", stated)):
            lo, med, hi = np.percentile(v, [5, 50, 95])
            want.update({f"{key}_median": med, f"{key}_p05": lo, f"{key}_p95": hi})
        near(r, want)
    assert float(corr[1]["stated_median"]) > 0.5 and u_med[0, 0] != u_med[2, 0]    # A, C: a tile, their own u
    # sensitivity.csv: the figures before idealising are the summary's; ranked by the drop
    sens = [r for r in _csv_rows(out / "sensitivity.csv") if r["scenario"] == "declared"]
    for name in noise:
        mine = [r for r in sens if r["participant"] == name]
        assert [int(r["rank"]) for r in mine] == list(range(1, len(mine) + 1)) and len(mine) >= 2
        drops = [float(r["drop_pct"]) for r in mine]
        assert drops == sorted(drops, reverse=True)
        s = summary[name]
        for r in mine:
            near(r, {"rms_error_vs_truth_pct": s["rms_error_vs_truth_pct"],
                     "rms_d_weighted_mean_pct": s["rms_d_weighted_mean_pct"],
                     "share_compatible_truth": s["share_En_le_1_truth"],
                     "share_compatible_weighted_mean": s["share_En_le_1_weighted_mean"], "realisations": R})


def test_validation_rows_pair_the_full_and_the_frozen_figures():
    """validation.csv's rows from known full and frozen tables: per figure and participant the mean
    over the realisations where every participant has its full correction (realisation 1 lacks one:
    left out), the mean paired difference frozen - full, its SE and the full figure's SE; no rows
    with fewer than two such realisations (mutation audit 11: the difference's sign, full and
    frozen swapped and full_se as the difference's SE passed every test). The figures are named
    `_per_realisation` and the columns `*_mean` (audit 21: intercompare.csv's figure of the same name
    pools the cells of every realisation and differed)."""
    from types import SimpleNamespace

    from roadgonio.intercomparison import simulate as sim
    from roadgonio.intercomparison.outputs import VALIDATION_COLUMNS
    from roadgonio.intercomparison.run import comparison, validation_rows
    rng = np.random.default_rng(2)
    R, P, n = 6, 3, 8
    truth = rng.uniform(0.01, 0.05, n)
    urel = np.full((R, P, n), 0.01)
    xs = {"all_corrected": truth * (1 + 0.01 * rng.standard_normal((R, P, n)))}
    xs[sim.FROZEN] = xs["all_corrected"] * (1 + 0.004 + 0.002 * rng.standard_normal((R, P, n)))
    stats = {s: comparison(xs[s], urel, np.zeros((0, P, n)), truth, 2.0) for s in xs}
    full = {"all_corrected": np.ones((R, P), dtype=bool)}
    full["all_corrected"][1, 2] = False
    from roadgonio.instrument.config import load_instrument
    lab = SimpleNamespace(instrument=load_instrument("lab"))                # an instrument whose correction does something
    setup = SimpleNamespace(truth=truth, participants=[SimpleNamespace(name=c, mm=lab) for c in "ABC"])
    rows = validation_rows(setup, xs, stats, full)
    assert rows and all(list(r) == list(VALIDATION_COLUMNS) for r in rows)
    by = {(r["figure"], r["participant"]): r for r in rows}
    keep = np.arange(R) != 1
    m = int(keep.sum())

    def check(row, a, b):
        assert row["realisations"] == m
        want = {"full_mean": a.mean(), "frozen_mean": b.mean(), "difference_mean": (b - a).mean(),
                "difference_se": (b - a).std(ddof=1) / math.sqrt(m), "full_mean_se": a.std(ddof=1) / math.sqrt(m)}
        for key, v in want.items():
            assert row[key] == pytest.approx(v, rel=1e-12, abs=1e-15), key
        assert abs(want["difference_mean"]) > 1e-6                             # the frozen tables are 0.4 % higher
    for p, name in enumerate("ABC"):
        rms = {s: 100 * np.sqrt(np.mean((xs[s][keep, p] / truth - 1.0) ** 2, axis=1)) for s in xs}
        check(by[("rms_error_vs_truth_pct_per_realisation", name)], rms["all_corrected"], rms[sim.FROZEN])
    allc = {s: np.mean(np.all(np.abs(stats[s]["equivalence"]["weighted_mean"]["E_n"][keep]) <= 1.0, axis=1), axis=1)
            for s in xs}
    row = by[("share_all_compatible_weighted_mean_per_realisation", "ALL")]
    assert row["full_mean"] == pytest.approx(allc["all_corrected"].mean(), rel=1e-12)
    assert row["frozen_mean"] == pytest.approx(allc[sim.FROZEN].mean(), rel=1e-12)
    full["all_corrected"][3:, 0] = False                                     # two realisations left: rows
    assert validation_rows(setup, xs, stats, full)
    full["all_corrected"][0, 0] = False                                      # one: none
    assert validation_rows(setup, xs, stats, full) == []


def test_a_reference_sample_that_names_nothing_is_refused_before_any_work(tmp_path, collimated):
    """(audit 22) report = "reference" with reference = "R9" or a missing file failed after the
    journal was written, naming neither the study file nor the field."""
    from roadgonio.intercomparison.run import run_study
    for ref, words in (("R9", "unknown sample 'R9'"), ("nofile.csv", "no such table or model file")):
        p = coll("B")
        p.update(report="reference", reference=ref, noise_rel=0.002)
        study = study_from_dict({"study": {"surface": "R3", "realisations": 2}, "participant": [coll("A"), p]},
                                path=tmp_path / "study.toml")
        with pytest.raises(InputError, match=words) as err:
            run_study(study, tmp_path / "out", workers=0, progress=False, plots=False)
        assert err.value.field == "participant[2].reference" and str(tmp_path / "study.toml") in str(err.value)
        assert not (tmp_path / "out").exists()


def test_each_simulated_correction_has_its_own_seed(monkeypatch):
    """(audit 22) every correction of every realisation ran with seed 0: its Monte Carlo error was
    one stream shared by all realisations, and the study's seed never changed it. The seeds now
    differ by participant and realisation, follow the study's seed, and stage 2 uses them."""
    from roadgonio.intercomparison import run as runmod
    seeds = {(s, p, m): runmod.correction_seed(s, p, m) for s in (1, 2) for p in (0, 1) for m in (None, 0, 1, 7)}
    assert len(set(seeds.values())) == len(seeds)
    got = []

    class Stop(Exception):
        pass

    def fake(*args, seed, **kw):
        got.append(seed)
        raise Stop

    import roadgonio.correction.files as files
    monkeypatch.setattr(files, "correct_measured", fake)
    monkeypatch.setattr(runmod.sim, "raw_table", lambda setup, d, p: (np.ones(3), None))
    monkeypatch.setattr(runmod.sim, "draws", lambda setup, m: None)

    class Cells:
        ii = jj = np.zeros(3, dtype=int)

        @staticmethod
        def to_grid(raw):
            return np.full((29, 20), 0.01)

    setup = type("S", (), {"participants": [type("P", (), {"name": "A"})()] * 2, "cells": Cells})()
    study = type("St", (), {"seed": 5, "participants": [type("Q", (), {"instrument": None, "noise_rel": 0.01,
                                                                         "reference": None})()] * 2})()
    for m in (0, 3):
        with pytest.raises(Stop):
            runmod._stage2_task(("self", 1, m), {"setup": setup, "study": study, "backend": "quadrature",
                                                 "correction_settings": {}})
    assert got == [runmod.correction_seed(5, 1, 0), runmod.correction_seed(5, 1, 3)]


def test_a_rerun_without_pictures_removes_the_earlier_runs_pictures(tmp_path, collimated):
    """(audit 22) intercompare --no-plots into the folder of an earlier run left that run's
    pictures (of other realisations) beside the new results; the user's own files stay."""
    from roadgonio.intercomparison.run import run_study
    from helpers_intercomparison import make_study
    out = tmp_path / "out"
    study = make_study(tmp_path, [coll("A"), coll("B")], realisations=3)
    run_study(study, out, workers=0, progress=False, plots=True)
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert "specular_row.png" in pngs and "compatibility.png" in pngs
    (out / "notes.txt").write_text("mine")
    run_study(make_study(tmp_path, [coll("A"), coll("B")], realisations=4), out, workers=0, progress=False,
              plots=False)
    assert not list(out.glob("*.png")) and (out / "notes.txt").read_text() == "mine"
    assert (out / "intercompare.nc").exists()


def test_a_random_effects_consensus_cannot_leave_two_or_three_participants_incompatible():
    """Why RANDOM_EFFECTS_MIN_PARTICIPANTS (user audit, session 37): over random independent results
    the largest |E_n| against Mandel-Paule is below 1 with 2 and 3 participants and above 1 with 4;
    against DerSimonian-Laird below 1 with 2 and above with 3. With fewer participants than the
    constant names, the share of |E_n| <= 1 is 1 by construction."""
    from roadgonio.intercomparison import statistics as st
    from roadgonio.intercomparison.run import RANDOM_EFFECTS_MIN_PARTICIPANTS as MIN
    rng = np.random.default_rng(11)
    for P in (2, 3, 4):
        x = rng.normal(size=(5000, P)) * rng.lognormal(0, 1.5, size=(5000, 1))
        u = 0.3 * rng.lognormal(0, 1, size=(5000, P))
        V = np.zeros((5000, P, P))
        V[:, np.arange(P), np.arange(P)] = u ** 2
        sp = st.Spectral(x, V)
        for m in MIN:
            worst = float(np.max(np.abs(st.equivalence_to(x, V, st.consensus(sp, m)).e_n)))
            assert (worst <= 1.0 + 1e-9) == (P < MIN[m]), (P, m, worst)


def test_with_two_participants_the_random_effects_shares_are_blank_and_a_note_says_why(tmp_path, collimated):
    """User audit, session 37: with 2 or 3 participants share_En_le_1_mandel_paule was 1 with an SE
    of 0, a check that cannot fail; it is now blank (NaN) and intercompare.json's notes say why;
    the weighted mean's share, and the SE of 'every participant compatible', are kept."""
    from roadgonio.intercomparison.outputs import write_outputs
    study = make_study(tmp_path, [coll("A", 0.01), coll("B", 0.02)], realisations=6)
    run = run_study(study, workers=0, progress=False, plots=False)
    rows = json.loads(run.dataset.attrs["summary_json"])
    parts = [r for r in rows if r["participant"] != "ALL" and r["scenario"] == "declared"]
    assert len(parts) == 2
    for r in parts:
        for m in ("mandel_paule", "dersimonian_laird"):
            assert r[f"share_En_le_1_{m}"] is None and r[f"share_En_le_1_{m}_se"] is None      # NaN: blank
        assert 0.0 < r["share_En_le_1_weighted_mean"] <= 1.0 and r["share_En_le_1_weighted_mean_se"] >= 0.0
    allr = next(r for r in rows if r["participant"] == "ALL" and r["scenario"] == "declared")
    assert allr["share_all_compatible_weighted_mean_se"] is not None and allr["share_all_compatible_weighted_mean_se"] >= 0
    notes = json.loads(run.dataset.attrs["notes_json"])
    assert len(notes) == 1 and "Mandel-Paule or DerSimonian-Laird" in notes[0] and "2 participants" in notes[0]
    write_outputs(run, tmp_path / "out", plots=False)
    assert json.loads((tmp_path / "out" / "intercompare.json").read_text())["notes"] == notes
    # four participants: the shares are numbers, no note
    study4 = make_study(tmp_path, [coll(n, 0.01) for n in "ABCD"], realisations=4)
    ds4 = run_study(study4, workers=0, progress=False, plots=False).dataset
    rows4 = [r for r in json.loads(ds4.attrs["summary_json"]) if r["participant"] != "ALL"]
    assert all(r["share_En_le_1_mandel_paule"] is not None for r in rows4 if "repeatability_pct" in r)
    assert json.loads(ds4.attrs["notes_json"]) == []


def test_a_reference_sample_with_an_unresolved_spike_is_noted_naming_the_participant(tmp_path, collimated):
    """User audit, session 37: a participant correcting with R2's power fit (a spike at beta 0 no
    aperture resolves) was 97-138 % off along beta 0, the warning reached the terminal only; the
    study's notes keep it, naming the participant. R3 (no spike) gives no note."""
    from roadgonio.intercomparison.run import study_notes
    study = make_study(tmp_path, [coll("A"), coll("B"), coll("C"), coll("D"),
                                  {"name": "LAB", "instrument": "collimated.toml", "noise_rel": 0.01,
                                   "stated": ["repeatability"], "report": "reference", "reference": "R2"}])

    class _Setup:                                        # study_notes reads the number of participants only
        P = 5
    notes = study_notes(study, _Setup())
    assert len(notes) == 1 and notes[0].startswith("participant LAB (report = reference, R2): ") and "spike" in notes[0]
    study3 = make_study(tmp_path, [coll(n) for n in "ABCD"] + [{"name": "LAB", "instrument": "collimated.toml",
                                                                "noise_rel": 0.01, "stated": ["repeatability"],
                                                                "report": "reference", "reference": "R3"}])
    assert study_notes(study3, _Setup()) == []


def test_a_housing_that_reflects_is_an_item_and_its_idealisation_drops_the_housing_alone():
    """(user audit, session 39) the ranking could not name a housing's stray light (at walls of 0.2 it
    made 13.8 of a participant's 17.7 points of RMS error, and the summary blamed the source distance and
    the detector field). Idealised, the instrument is the same without its [housing]; a black housing
    (reflectance 0: shadows only) and a bare instrument have no such item."""
    from roadgonio.instrument.config import Instrument, load_instrument
    from roadgonio.instrument.housing import Housing
    from roadgonio.intercomparison.run import idealised_instrument
    from roadgonio.intercomparison.simulate import k_characteristics
    housed = load_instrument("portable_housed")
    assert [k for k, _ in k_characteristics(housed)][-1] == "housing"
    assert "housing" not in [k for k, _ in k_characteristics(load_instrument("portable"))]
    d = housed.to_dict()
    d["housing"] = {**d["housing"], "wall_reflectance": 0.0}
    assert "housing" not in [k for k, _ in k_characteristics(Instrument.from_dict(d, path=housed.path))]
    bare = idealised_instrument(housed, "housing")
    assert "housing" not in bare.to_dict() and Housing.of(bare) is None
    assert (bare.source, bare.detector, bare.observation, bare.calibration, bare.sample) == \
        (housed.source, housed.detector, housed.observation, housed.calibration, housed.sample)


def test_the_aperture_effect_item_of_a_housed_participant_says_it_holds_the_stray_light():
    """(user audit, session 44) "aperture effect as a whole (k_A = 1)" took most of a bright housing's
    +19 pp under the apertures' name: a housed participant's k_A carries its stray light (a black
    housing, which only shades, does not)."""
    from types import SimpleNamespace

    from roadgonio.instrument.config import Instrument, load_instrument
    from roadgonio.intercomparison.simulate import ParticipantModel, Setup
    from roadgonio.uncertainty.spec import parse_sigma_spec
    housed = load_instrument("portable_housed")
    d = housed.to_dict()
    d["housing"] = {**d["housing"], "wall_reflectance": 0.0}
    black = Instrument.from_dict(d, path=housed.path)

    def pm(inst):
        return ParticipantModel("X", "raw", SimpleNamespace(instrument=inst, cells=[0]), parse_sigma_spec("alpha_deg=0"),
                                0.01, 0.0, ("repeatability",), 0.0)
    setup = Setup(None, None, [pm(i) for i in (housed, load_instrument("portable"), black)], [], 0, 1, 2.0)
    labels = [dict(setup.characteristics(k, corrected=False))["aperture_effect"] for k in range(3)]
    assert labels == ["aperture effect and the housing's stray light as a whole (k_A = 1)",
                      "aperture effect as a whole (k_A = 1)", "aperture effect as a whole (k_A = 1)"]


def test_a_misaligned_housed_instrument_keeps_its_housing_where_it_was_built():
    """(user audit, session 39) the default box follows the parts, so the uncertainty's (and the
    intercomparison's) perturbed instruments carried the walls along with a misplaced source: d ln k_A /
    d D_S 0.07 /m against 0.35 /m with the box fixed (walls 0.2, tan 11, beta 40). The measurement model's
    instrument has the nominal box written out; perturbed, the box stays."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.instrument.enclosure import housing_box
    from roadgonio.instrument.housing import Housing
    from roadgonio.uncertainty.cells import CellSet
    from roadgonio.uncertainty.measurement import MeasurementModel
    from roadgonio.surface.sample import resolve_sample
    housed = load_instrument("portable_housed")
    mm = MeasurementModel(resolve_sample("R3").model, housed, CellSet.make("standard"))
    box = housing_box(housed, Housing.of(housed))
    moved = mm.instrument.with_changes(source={"distance_m": mm.ds0 + 0.02}, detector={"distance_m": mm.dd0 - 0.01},
                                       observation={"alpha_deg": mm.alpha0 + 0.05})
    assert housing_box(moved, Housing.of(moved)) == box == housing_box(mm.instrument, Housing.of(mm.instrument))
    loose = housed.with_changes(source={"distance_m": mm.ds0 + 0.02})
    assert housing_box(loose, Housing.of(loose)) != box        # what the default box did


def test_an_error_inside_a_participants_instrument_file_names_that_file_and_its_field(tmp_path, collimated):
    """(user audit, session 39) a wall reflectance of 1.5 in a participant's own instrument file was told
    as the study's field 'participant[2].instrument'; `ka` on the same file names the file and
    'housing.wall_reflectance'. Now the study names them too, and whose instrument it is."""
    text = (Path(__file__).resolve().parents[2] / "scenes" / "portable_housed.toml").read_text()
    bad = tmp_path / "inst" / "wr15.toml"
    bad.parent.mkdir()
    bad.write_text(text.replace("wall_reflectance = 0.05", "wall_reflectance = 1.5"))
    assert "wall_reflectance = 1.5" in bad.read_text()
    d = {"study": {"surface": "R3"}, "participant": [coll("A"), coll("B", instrument=str(bad))], "shared": []}
    with pytest.raises(InputError) as err:
        study_from_dict(d, path=tmp_path / "study.toml")
    assert err.value.field == "housing.wall_reflectance" and err.value.path == str(bad), str(err.value)
    assert "participant[2]" in str(err.value) and str(tmp_path / "study.toml") in str(err.value)
    assert "\n" not in str(err.value)
