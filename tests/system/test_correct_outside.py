"""`roadgonio correct --forward surface` and `--joint` (issue 19): bad inputs, the outputs and
round trips of a known surface through one instrument and through two."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from roadgonio import api
from roadgonio.cli import main
from roadgonio.correction.synthetic import r2_like_truth, synthesize
from roadgonio.instrument.config import Instrument, load_instrument
from roadgonio.surface.rtable import read_table
from tolerances import FILE_RTOL, N_SIGMA, z_family

DATA = Path(__file__).resolve().parents[1] / "data"
MEDIUM = DATA / "medium.toml"
MEASURED = DATA / "synthetic_medium_lambert.csv"
TRUTH = DATA / "synthetic_medium_lambert_truth.csv"
#: The true k_A of MEASURED (lambert calibration), by the quadrature at rtol 1e-5 (the file's header):
#: its relative error bound.
TRUE_KA = DATA / "synthetic_medium_lambert_ka.csv"
TRUE_KA_RTOL = 1e-5
#: The float64 reference integrator's rtol for the k_A of the two-instrument synthetic measurements
#: (two_instruments): their relative error bound.
REFERENCE_RTOL = 1e-3
FAST = ["--backend", "quadrature", "--accuracy", "fast", "--rays", "64", "--model-variant", "power"]


def one_line_error(capsys, rc, *must):
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("roadgonio: error:"), err
    for m in must:
        assert m in lines[0], (m, lines[0])


@pytest.mark.parametrize("argv, must", [
    (["--measured", str(MEASURED), str(MEASURED), "--instrument", str(MEDIUM), "--joint"],
     ("--instrument", "one instrument per measured table")),
    (["--measured", str(MEASURED), "--instrument", str(MEDIUM), "--instrument", str(MEDIUM)], ("--instrument", "--joint")),
    (["--measured", str(MEASURED), "--instrument", str(MEDIUM), "--forward", "surface", "--reference", "R3"],
     ("forward", "self")),
    (["--measured", str(MEASURED), "--instrument", str(MEDIUM), "--measured", str(MEASURED), "--instrument",
      str(MEDIUM), "--joint", "--reference", "R3"], ("--reference",)),
    # trial 10 D7: an explicit --forward eq4 was dropped without a word and the surface fitted
    (["--measured", str(MEASURED), "--instrument", str(MEDIUM), "--measured", str(MEASURED), "--instrument",
      str(MEDIUM), "--joint", "--forward", "eq4"], ("field '--forward'", "eq4 cannot be used")),
    # --alternatives with the self route was accepted and ignored (user audit, session 19)
    (["--measured", str(MEASURED), "--instrument", str(MEDIUM), "--alternatives", "R2"],
     ("field '--alternatives'", "--reference SAMPLE")),
    # ... and with --joint (session 39's review: accepted and ignored after the check moved to the API)
    (["--measured", str(MEASURED), "--instrument", str(MEDIUM), "--measured", str(MEASURED), "--instrument",
      "portable", "--joint", "--alternatives", "R2"], ("field '--alternatives'", "--reference SAMPLE")),
    # the same data twice was fitted as two instruments, halving its noise (user audit, session 19)
    (["--measured", str(MEASURED), "--instrument", str(MEDIUM), "--measured", str(MEASURED), "--instrument",
      str(MEDIUM), "--joint"], ("same table through the same instrument", "pairs 1 and 2")),
    # one file for two instruments was fitted as two measurements (user audit, session 38)
    (["--measured", str(MEASURED), "--instrument", str(MEDIUM), "--measured", str(MEASURED), "--instrument",
      "portable", "--joint"], ("same values through two instruments", "pairs 1 and 2")),
])
def test_joint_and_forward_bad_inputs(tmp_path, capsys, argv, must):
    rc = main(["correct", *argv, *FAST, "--out", str(tmp_path / "o")])
    one_line_error(capsys, rc, *must)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("args, kwargs, field", [
    ([[MEASURED, MEASURED], [MEDIUM]], {}, "instrument"),
    ([[MEASURED, MEASURED], [MEDIUM, MEDIUM]], {"reference": "R3"}, "reference"),
    ([[MEASURED, MEASURED], [MEDIUM, MEDIUM]], {"forward": "eq4"}, "forward"),
    ([[MEASURED, MEASURED], [MEDIUM, MEDIUM]], {"workers": 2}, "workers"),
])
def test_api_errors_name_the_api_arguments(tmp_path, args, kwargs, field):
    """trial 10 D11: from Python the refusals named the command line's options ('--instrument',
    '--reference'); the API names its arguments and the CLI (above) its options. trial 10 D7: an
    explicit forward='eq4' with joint=True is refused, not replaced by the surface fit."""
    from roadgonio.errors import InputError
    with pytest.raises(InputError) as err:
        api.correct(*args, joint=True, out=tmp_path / "o", **kwargs)
    assert err.value.field == field and "--" not in str(err.value).split(":")[0]
    assert not (tmp_path / "o").exists()



HOUSED = Path(__file__).resolve().parents[2] / "scenes" / "portable_housed.toml"


@pytest.mark.parametrize("argv, must", [
    (["design", "--second-aperture", "--instrument", str(MEDIUM), "--sample", "R3", "--vary",
      "detector.field_half_angle_deg=0.1", "--cells", "12:0"], ("--cells", "not used with --second-aperture")),
    (["design", "--second-aperture", "--instrument", str(MEDIUM), "--sample", "R3", "--vary",
      "detector.field_half_angle_deg=0.1", "--backend", "quadrature", "--workers", "2"],
     ("--backend, --workers", "not used with --second-aperture")),
    (["design", "--second-aperture", "--instrument", str(MEDIUM), "--sample", "R3", "--vary",
      "housing.wall_reflectance=0.1"], ("--vary", "housing.wall_reflectance", "does not model a housing")),
    # user audit, session 37: the sample's size was ranked as a second aperture (the same blur)
    (["design", "--second-aperture", "--instrument", str(MEDIUM), "--sample", "R3", "--vary",
      "sample.size_x_m=2"], ("--vary", "sample.size_x_m", "does not change the instrument's blur")),
    # ... and a --vary value no instrument can take named the instrument file
    (["design", "--second-aperture", "--instrument", str(MEDIUM), "--sample", "R3", "--vary",
      "source.radius_m=-0.01,0.02"], ("--vary", "source.radius_m=-0.01", "is not an instrument")),
    (["design", "--instrument", str(MEDIUM), "--sample", "R3", "--vary", "detector.field_half_angle_deg=0.1",
      "--min-signal", "0.1"], ("--min-signal", "not used without --second-aperture")),
    (["correct", "--measured", str(MEASURED), "--instrument", str(HOUSED), "--forward", "surface", "--backend",
      "quadrature"], ("portable_housed.toml", "housing", "does not model a [housing]")),
])
def test_options_a_command_would_ignore_are_refused_before_any_work(tmp_path, capsys, argv, must):
    """An option the command does not use is an error, not silently dropped; a backend that cannot
    model the instrument is refused before the surface is fitted (the user's report: 5 s of fitting
    first, and a fit_state.json left behind)."""
    rc = main([*argv, "--out", str(tmp_path / "o")])
    one_line_error(capsys, rc, *must)
    assert not (tmp_path / "o").exists()

def _scores(corrected, u_rel, truth):
    m = corrected.mask
    err = np.log(corrected.r[m] / truth.r[m])
    return float(np.sqrt(np.mean(err ** 2))), float(np.mean(np.abs(err) <= 2 * u_rel)), err / u_rel


def assert_k_a_within_its_u(k_a, k_true, budget, bound):
    """An instrument's k_A of the corrected model (cells of its measured table) against the true k_A
    (deterministic relative error ``bound``), judged with the uncertainty of ln k_A the correction
    reports: its budget less the measurement's own component (ln r / k_A = ln y - ln k_A, y
    independent). Per cell at z_family(cells); the mean over the cells (a bias, which an RMS
    bound hides) at N_SIGMA with its standard error from the full covariance (the surface's
    posterior correlates the cells)."""
    d = np.log(k_a / k_true)
    C = budget.total() - budget.components["measurement"]
    u = np.sqrt(np.diag(C))
    n = d.size
    assert np.all(np.abs(d) <= z_family(n) * u + bound), np.max(np.abs(d) / u)
    se_mean = math.sqrt(float(np.ones(n) @ C @ np.ones(n))) / n
    assert abs(d.mean()) <= N_SIGMA * se_mean + bound, (d.mean(), se_mean)


def assert_functionals_within_their_u(after, corrected, truth):
    """S1 and Q0 of the corrected table against the truth's over the same cells, each at N_SIGMA of
    the u the budget gives them (which carries the cells' correlations): a bias of the whole table
    shows here even where the per-cell RMS hides it."""
    m = corrected.mask
    true = truth.with_values(np.where(m, truth.r, np.nan))
    for name, value in (("S1", true.s1()), ("Q0", true.q0())):
        assert abs(after[name] / value - 1.0) <= N_SIGMA * after[f"u_{name}"] / after[name], \
            (name, after[name], value, after[f"u_{name}"])


#: Quality floors of the corrected tables' RMS log error against the truth: measured numbers with
#: margin, not statistical bounds (the functionals and k_A are judged from their u below). Measured at
#: 91a5b6b: one instrument, --forward surface 0.52 %, --forward eq4 0.93 % (ratio 0.56); through both
#: instruments (test_joint_correction_of_two_instruments) 0.16 %. A 1 % bias of the forward simulation
#: gives 1.27 % and 0.97 % (and, in the joint case, Q0 10 u off).
RMS_SURFACE_MAX = 0.012
RMS_SURFACE_OVER_EQ4_MAX = 0.7
RMS_JOINT_MAX = 0.015


@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_forward_surface_round_trip_inside_eq4_writes_the_diagnostics(tmp_path, capsys):
    """An eq. 4 surface (the medium synthetic measurement of the smooth-variant R2-like truth, 1 %
    noise): the flexible model must not over-fit it (issue 19: no loss of accuracy inside the
    family: its RMS error no worse than eq. 4's alone, + 0.2 %), its u
    covers the error, and the outputs carry the Birge ratio, the widening and the two diagnostic
    pictures. 256 rays a cell (at 64 the bundles' own error, 0.95 % a cell, shows). The table's
    S1 and Q0 and the k_A it was divided by are judged against the truth's with the u the correction
    reports (k_A's from the same correction through the API, resumed from the folder's journals).
    With one instrument that u is about 1 % a cell and 0.5 % on the mean, so a 1 % error of k_A alone
    is beyond this test; test_joint_correction_of_two_instruments sees it."""
    rms = {}
    for forward in ("eq4", "surface"):
        out = tmp_path / forward
        rc = main(["correct", "--measured", str(MEASURED), "--instrument", str(MEDIUM), "--forward", forward,
                   "--u-measured", "1%", "--backend", "quadrature", "--accuracy", "fast", "--rays", "256",
                   "--model-variant", "smooth", "--out", str(out)])
        said = capsys.readouterr()
        assert rc == 0, said.err
        assert ("the fitted surface's own value" in said.out) == (forward == "surface"), said.out
        corrected, u = read_table(out / "corrected.csv"), read_table(out / "corrected_u.csv")
        m = corrected.mask
        rms[forward], within, z = _scores(corrected, u.r[m] / corrected.r[m], read_table(TRUTH))
        doc = json.loads((out / "correct.json").read_text())
        assert_functionals_within_their_u(doc["summary"], corrected, read_table(TRUTH))
    assert rms["surface"] <= RMS_SURFACE_MAX and rms["surface"] <= rms["eq4"] + 0.002
    # the table weighs the fitted surface's own value (docs/correction.md): on an eq. 4 surface it
    # carries most cells and removes most of the noise that r / k_A keeps
    assert rms["surface"] <= RMS_SURFACE_OVER_EQ4_MAX * rms["eq4"], rms
    assert within >= 0.90 and np.max(np.abs(z)) <= 4.0
    for name in ("residual_map.png", "correction_surface.png", "before_after.png", "correct.json"):
        assert (out / name).stat().st_size > 1000
    doc = json.loads((out / "correct.json").read_text())
    fit = doc["summary"]["fit"]
    assert 0.7 < fit["birge_ratio"] < 1.3                     # an eq. 4 surface: the model fits
    assert fit["cells_widened"] < 0.1 * doc["summary"]["cells"]
    assert {"surface", "model", "measurement", "discrepancy"} <= set(doc["summary"]["budget"])
    # the discrepancy (docs/correction.md, "What the instruments cannot see"): its own column, and on an
    # eq. 4 surface (the evidence smooths the correction surface to its bound) next to nothing
    header = [ln for ln in (out / "correct_cells.csv").read_text().splitlines() if not ln.startswith("#")][0]
    assert "u_rel_discrepancy" in header.split(",")
    lines = [ln for ln in (out / "correct_cells.csv").read_text().splitlines() if not ln.startswith("#")]
    cols = lines[0].split(",")
    vals = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    cells = {c: vals[:, k] for k, c in enumerate(cols)}
    assert np.median(cells["w_model"]) > 0.5
    # r / k_A is still there, cell by cell (6 significant digits in the file)
    assert np.allclose(cells["r_over_k_a_x1e4"], cells["r_measured_x1e4"] / cells["k_a"], rtol=2e-5, atol=0)
    assert doc["summary"]["model_estimate"]["weight_median"] == pytest.approx(np.median(cells["w_model"]), abs=1e-3)
    # an eq. 4 surface is smooth away from the peak quadrant (beta <= 12, eps >= 45 deg: b0e1)
    away = {k: v for k, v in fit["discrepancy"]["sigma_by_region"].items() if k != "b0e1"}
    assert len(away) == 3 and max(away.values()) < 0.002, fit["discrepancy"]["sigma_by_region"]
    # the k_A the table was divided by, against the truth's: the same correction through the API (it
    # resumes from the folder's journals and must give the file's k_A), judged with its reported u
    res = api.correct(MEASURED, MEDIUM, forward="surface", u_measured="1%", backend="quadrature", accuracy="fast",
                      rays=256, model_variant="smooth", out=out, plots=False)
    mask = res.measured.mask
    np.testing.assert_allclose(res.k_a[mask], cells["k_a"], rtol=FILE_RTOL, atol=0)
    part = res.extra["surface"].parts[0]
    assert_k_a_within_its_u(part.k_a[mask], read_table(TRUE_KA).r[mask] * 1e4, part.budget, TRUE_KA_RTOL)
    # one backbone per variant and rounding at the mirror plane of the settings (by default the cusp
    # and the rounding over one knot, weighed), each carrying its rounding, the weights summing to 1;
    # correct.json says so in its model
    from roadgonio.correction.flexible import SurfaceSettings
    rounds = SurfaceSettings().backbone_rounds_deg
    got = sorted((v.variant, v.round_deg, v.backbone.params.beta_round_deg) for v in res.extra["surface"].variants)
    assert got == sorted(("smooth", r, r) for r in rounds)
    assert sum(v.weight for v in res.extra["surface"].variants) == pytest.approx(1.0, abs=1e-12)
    assert sorted(v["backbone"]["params"]["beta_round_deg"] for v in fit["variants"]) == sorted(rounds)
    # (user audit, session 40) every other backbone has its own k_a_ column, named by its rounding (keyed by
    # the variant alone, the roundings overwrote one another: one k_a_smooth for two backbones)
    from roadgonio.correction.outside import backbone_column
    best = res.extra["surface"].best
    others = {f"k_a_{backbone_column('smooth', r)}" for r in rounds if r != best.round_deg}
    assert len(others) == len(rounds) - 1 and others <= set(cols)
    assert all(c in others | {"k_a", "k_a_direct"} for c in cols if c.startswith("k_a"))
    # the corrected table's header names the measured table (road matches a u file to its table by it: two
    # sites through one instrument wrote the same header), and the u file names that header
    from roadgonio.surface.rtable import header_line, measured_label, u_names_table
    head = header_line(read_table(out / "corrected.csv"))
    assert head.startswith(f"{measured_label(read_table(MEASURED))}: ") and u_names_table(read_table(out / "corrected_u.csv")) == head
    # the combination is defined as what it is (non-negative weights; "generalised least squares" alone was wrong)
    assert "non-negative weights" in doc["definitions"]["corrected"]


@pytest.fixture(scope="module")
def two_instruments():
    """The R2-like surface measured by medium and by medium with a narrower field stop and pupil,
    k_A by the float64 reference integrator (not the code under test), 1 % noise."""
    a = load_instrument(MEDIUM)
    d = a.to_dict()
    d["instrument"]["name"] = "medium-narrow"
    d["detector"]["field_half_angle_deg"] = 0.1
    d["detector"]["pupil_radius_m"] = 0.0025
    b = Instrument.from_dict(d)
    mask = read_table(MEASURED).mask
    sa = synthesize(r2_like_truth(), a, noise=0.01, seed=5, backend="reference",
                    backend_settings={"rtol": REFERENCE_RTOL}, mask=mask, name="medium")
    sb = synthesize(r2_like_truth(), b, noise=0.01, seed=6, backend="reference", backend_settings={"rtol": REFERENCE_RTOL},
                    mask=mask, name="narrow")
    return a, b, sa, sb


@pytest.fixture(scope="module")
def joint_and_alone(two_instruments):
    a, b, sa, sb = two_instruments
    opts = dict(u_measured="1%", backend="quadrature", accuracy="fast", rays=256, model_variant="smooth")
    joint = api.correct([sa.measured, sb.measured], [a, b], joint=True, **opts)
    alone = api.correct(sa.measured, a, forward="surface", **opts)
    return joint, alone


@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_joint_correction_of_two_instruments(two_instruments, joint_and_alone):
    """One surface through both: one table, each instrument's k_A, the u of the joint table below
    the first instrument's own (the second aperture adds information), and its error covered."""
    a, b, sa, sb = two_instruments
    joint, alone = joint_and_alone
    assert [p.name for p in joint.parts] == ["medium", "medium-narrow"]
    for p, s in zip(joint.parts, (sa, sb)):            # each instrument's k_A against the reference's
        m = s.measured.mask
        assert_k_a_within_its_u(p.k_a[m], s.k_a[m], p.budget, REFERENCE_RTOL)
    u_joint = joint.budget.u_rel()
    rms, within, z = _scores(joint.corrected, u_joint, sa.truth)
    assert rms <= RMS_JOINT_MAX and within >= 0.90 and np.max(np.abs(z)) <= 4.0
    assert_functionals_within_their_u(joint.after, joint.corrected, sa.truth)
    assert np.median(u_joint) < np.median(alone.budget.u_rel())
    s = joint.summary()
    assert len(s["per_instrument"]) == 2 and math.isfinite(s["u_S1"])


@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_second_aperture_predicts_the_joint_u_and_ranks_by_it(tmp_path, two_instruments, joint_and_alone):
    """design --second-aperture: the expected median u of the joint table with the narrow setting
    (predicted from the measured table of the first instrument, before the second measures) is
    the u the joint correction then reports, within 30 % (both with the discrepancy; the prediction leaves out the backend,
    the bundles' and the variants' spread); the best candidate has the least u among those with
    enough signal, and every candidate beats the instrument alone."""
    a, b, sa, sb = two_instruments
    joint, alone = joint_and_alone
    res = api.second_aperture(a, ["detector.field_half_angle_deg=0.1,0.2", "detector.pupil_radius_m=0.0025"],
                              measured=sa.measured, u_measured="1%", rays=256, model_variant="smooth", min_signal=0.0,
                              out=tmp_path / "sa", plots=False)
    narrow = [c for c in res.candidates if abs(c.changes["detector.field_half_angle_deg"] - 0.1) < 1e-9][0]
    actual = float(np.median(joint.budget.u_rel()))
    assert abs(narrow.u_median / actual - 1) < 0.30, (narrow.u_median, actual)
    ok = [c for c in res.candidates if math.isfinite(c.u_median)]
    assert res.best.u_median == min(c.u_median for c in ok)
    assert all(c.u_median < res.baselines[0].u_median for c in ok)
    assert (tmp_path / "sa" / "best_second.toml").exists()


@pytest.mark.slow            # two backbone fits and a correction, ~60 s: in CI by -m slow
def test_second_aperture_takes_the_backbone_the_correction_takes(two_instruments):
    """Without --model-variant the prediction fits the backbone variants `correct --forward surface`
    weighs and takes the one of larger evidence, the one the correction then weighs ~1 (trial 7,
    defect 4: it took `smooth` always and predicted 4.6 times the u of a correction that chose
    `power`); its baseline "alone" is the u the correction through the instrument alone reports,
    within 30 % as above, and the output says which backbone it took and why."""
    a, b, sa, sb = two_instruments
    alone = api.correct(sa.measured, a, forward="surface", u_measured="1%", backend="quadrature", accuracy="fast",
                        rays=256)
    chosen = alone.extra["surface"].best.variant
    res = api.second_aperture(a, ["detector.field_half_angle_deg=0.1"], measured=sa.measured, u_measured="1%",
                              rays=256, min_signal=0.0, plots=False)
    assert res.settings["backbone_variant"] == chosen and "evidence" in res.settings["backbone_choice"]
    actual = float(np.median(alone.budget.u_rel()))
    assert abs(res.baselines[0].u_median / actual - 1) < 0.30, (res.baselines[0].u_median, actual, chosen)


@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_a_rerun_resumes_the_correction_surface_and_gives_the_same_table(tmp_path, capsys):
    """A finished `correct --forward surface` rerun in the same folder takes the k_A table and the
    correction surface from the folder's journals (fit_state.json) and writes the same numbers;
    the terminal and --json say what was resumed; so does a rerun with another --unobserved-road."""
    out = tmp_path / "out"
    argv = ["correct", "--measured", str(MEASURED), "--instrument", str(MEDIUM), "--forward", "surface",
            "--u-measured", "1%", *FAST, "--no-plots", "--out", str(out)]
    assert main(argv + ["--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    table = (out / "correct_cells.csv").read_bytes()
    assert first["resumed_surfaces"] == 0
    state = json.loads((out / "fit_state.json").read_text())
    from roadgonio.correction.flexible import SurfaceSettings
    from roadgonio.correction.outside import _state_name
    # one surface per backbone: the variant asked for (FAST) at each rounding of the default
    rounds = SurfaceSettings().backbone_rounds_deg
    assert sorted(state["surfaces"]) == sorted(f"surface-{_state_name('power', r)}" for r in rounds)
    assert main(argv) == 0
    said = capsys.readouterr().out
    n = len(rounds)
    assert f"{n} correction surface{'s' if n > 1 else ''} from the output folder's journals" in said, said
    assert (out / "correct_cells.csv").read_bytes() == table
    # the factor on the road beyond the observation elevations enters the budget only: another one
    # resumes every fit too (session 20), and without stray light it changes nothing and says so
    assert main(argv + ["--unobserved-road", "3"]) == 0
    said = capsys.readouterr()
    assert f"{n} correction surface{'s' if n > 1 else ''} from the output folder's journals" in said.out, said.out
    assert "changed nothing" in said.err
    assert (out / "correct_cells.csv").read_bytes() == table


#: Trial 7, defect 1: CIE R3 read as measured by the portable instrument. With the smoothing chosen
#: at the stated u the surface oscillated between the cells (ln k_A's second difference along tan eps
#: up to ~0.5 in a beta column, median u 15 %, GLS weights of the model's value down to -0.6). The
#: bounds below are several times what the fixed fit gives (0.12 and 2.7 %) and well under the defect's.
MAX_LNK_SECOND_DIFFERENCE = 0.25
MAX_MEDIAN_U = 0.06


@pytest.mark.slow            # moved to the slow tier (CI runs it by -m slow): the default run must stay under 15 min
def test_a_real_table_through_a_small_instrument_gives_a_smooth_k_a_and_a_convex_table():
    """A real table (CIE R3, two-digit values that eq. 4 leaves at Birge ratio ~3) corrected with
    --forward surface through the portable: k_A smooth down every beta column, the table's u of the
    order of the misfit (not 15 %), every weight of the model's own value in [0, 1] (the combination
    never leaves the range of r / k_A and the model's value), and the fit reports the noise scale
    it chose the smoothing with (phi > 1: the residuals are larger than the stated 1 %)."""
    res = api.correct("R3", "portable", forward="surface", accuracy="fast", u_measured="1%", plots=False)
    sc = res.extra["surface"]
    d2 = np.abs(np.diff(np.log(np.asarray(res.k_a, dtype=float)), n=2, axis=0))
    assert np.nanmax(d2) <= MAX_LNK_SECOND_DIFFERENCE, np.nanmax(d2)
    u_rel = (res.u_corrected / res.corrected.r)[res.corrected.mask]
    assert np.median(u_rel) <= MAX_MEDIAN_U, np.median(u_rel)
    w = sc.model_weight[np.isfinite(sc.model_weight)]
    assert w.size > 0 and w.min() >= 0.0 and w.max() <= 1.0
    assert sc.best.fit.phi > 1.0


def test_an_outer_loop_stopped_before_it_holds_still_puts_its_last_change_into_u():
    """`max_outer` and `tol` reach the surface route (they were dropped there before the backbone
    had an outer loop), and a loop stopped before the k_A it predicts holds still (one backend
    table, a tolerance no refit meets) reports steps[-1] as not converged and adds the
    `convergence` component: per cell the last refit's predicted change of ln k_A over sqrt(3),
    whose largest value is the step's refit_change_over_u_max in units of the measured u (1 %)."""
    res = api.correct(MEASURED, MEDIUM, forward="surface", u_measured="1%", backend="quadrature", accuracy="fast",
                      rays=256, model_variant="power", plots=False, max_outer=1, tol=1e-9)
    steps = res.extra["surface"].steps
    assert len(steps) == 1 and not steps[0]["converged"], steps
    part = res.extra["surface"].parts[0]
    conv = np.sqrt(np.diag(part.budget.components["convergence"]))
    assert conv.max() * math.sqrt(3.0) / 0.01 == pytest.approx(steps[0]["refit_change_over_u_max"], rel=1e-9)
    assert "convergence" in res.budget.components


def test_a_backbone_search_that_missed_the_basin_is_repeated():
    """Audit 23: the noise-free eq. 4 table of tests/data/make_noisefree_portable_absolute.py through
    ``--forward surface``. The cusp backbone's one search missed the model's basin and the correction
    surface followed the data from the wrong backbone: k_A off by up to 7.2 % (the quadrature's k_A),
    at chi^2 10.8 for 396 cells, the rounded backbone weighed 1. The repeated search finds the basin:
    k_A within the bundle backend's own error (rays 512) of the exact one, the cusp backbone weighed."""
    from roadgonio.surface.rtable import RTable
    stored = np.load(DATA / "noisefree_portable_absolute.npz")
    meas = RTable(stored["r"], name="noise-free")
    inst = load_instrument("portable").with_changes(calibration={"mode": "absolute"})
    res = api.correct(meas, inst, u_measured="1%", backend="bundle", forward="surface", plots=False)
    m = meas.mask
    err = np.log(res.k_a[m] / stored["k_a"][m])
    assert np.max(np.abs(err)) < 0.003, np.max(np.abs(err))
    searches = res.provenance["backbone_searches"]["backbone"]          # the cusp's
    assert searches[-1]["chi2_p_value"] > 0.5, searches
    best = max(res.summary()["fit"]["variants"], key=lambda v: v["weight"])
    assert best["mirror_round_deg"] == 0.0 and best["variant"] == "power", best


@pytest.mark.slow            # six corrections with Mitsuba, ~2 min: in CI by -m slow
def test_the_stated_backend_u_of_a_surface_correction_is_its_scatter_over_the_backends_seeds(monkeypatch):
    """User audit, session 24: the backend's error of k_A was counted on r / k_A alone and as independent
    cells, so the table of a surface correction (mostly the fitted surface's own value, which the error
    reaches through rho and the fit, and a common error does not average away) moved with the seed 40-70
    times more than its stated backend u. Six corrections of one table whose backend alone draws other
    random numbers (the fit's seed, and so its starts and ray bundles, fixed): the RMS over the cells of
    the per-cell standard deviation is the RMS of the stated backend u, within what six draws allow (the
    ratio's square is at worst chi^2_5 / 5, cells fully correlated: [0.083, 3.3] at 99 %, so [0.25, 2]
    on the ratio; measured 1.19)."""
    import roadgonio.engines.registry as registry
    resolve, backend_seed = registry.resolve_settings, [0]

    def settings_with_the_backends_own_seed(*a, **k):
        if k.get("seed") is not None:
            k["seed"] = backend_seed[0]
        return resolve(*a, **k)
    monkeypatch.setattr(registry, "resolve_settings", settings_with_the_backends_own_seed)
    runs = []
    for s in range(6):
        backend_seed[0] = 1000 + s
        runs.append(api.correct(MEASURED, MEDIUM, forward="surface", u_measured="1%", backend="mitsuba",
                                accuracy="fast", rays=512, model_variant="power", seed=0, progress=False))
    ln = np.log([r.corrected.r[r.corrected.mask] for r in runs])
    sd = ln.std(axis=0, ddof=1)
    ub = np.array([np.sqrt(np.diag(r.budget.components["backend"])) for r in runs])
    ratio = math.sqrt(np.mean(sd ** 2) / np.mean(ub ** 2))
    assert 0.25 < ratio < 2.0, (ratio, float(np.sqrt(np.mean(sd ** 2))), float(np.sqrt(np.mean(ub ** 2))))
    assert all("correlation between cells the backend measured" in r.budget.notes["backend"] for r in runs)


@pytest.mark.slow            # six corrections with Mitsuba, ~1 min: in CI by -m slow
def test_the_stated_bundle_u_of_a_surface_correction_is_its_scatter_over_the_bundles_seeds(monkeypatch):
    """Session 26: the `bundle` component was the bundles' error of k_A's change at a fixed surface
    (0.014 % RMS here), while with only the ray bundles drawing other numbers (backend and fit starts
    at seed 0) the table moved by 0.36 % RMS: their noise reaches the table through the fit. The
    component now follows it to first order (:func:`roadgonio.correction.outside.bundle_noise_covariance`):
    0.50 % stated. Six corrections: the RMS over the cells of the per-cell standard deviation against
    the RMS of the stated component, within what six draws (a common mode dominates: sqrt(chi^2_5 / 5)
    in [0.29, 1.8] at 99 %) and the first order (0.72 here, 1.42 at 2048 rays) allow: [0.25, 2.5]. The
    old component fails it (ratio 25)."""
    from roadgonio.engines.bundle import RayBundles
    build, bundle_seed = RayBundles.build.__func__, [0]

    def bundles_with_their_own_seed(cls, *a, **k):
        k["seed"] = bundle_seed[0]
        return build(cls, *a, **k)
    monkeypatch.setattr(RayBundles, "build", classmethod(bundles_with_their_own_seed))
    runs = []
    for s in range(6):
        bundle_seed[0] = 1000 + s
        runs.append(api.correct(MEASURED, MEDIUM, forward="surface", u_measured="1%", backend="mitsuba",
                                accuracy="fast", rays=512, model_variant="power", seed=0, plots=False,
                                progress=False))
    m = runs[0].corrected.mask
    sd = np.log([r.corrected.r[m] for r in runs]).std(axis=0, ddof=1)
    stated = np.sqrt(np.mean([np.diag(r.budget.components["bundle"]) for r in runs]))
    ratio = float(np.sqrt(np.mean(sd ** 2)) / stated)
    assert 0.25 < ratio < 2.5, (ratio, float(np.sqrt(np.mean(sd ** 2))), float(stated))
    assert all("through the fit" in r.budget.notes["bundle"] for r in runs)


def test_a_smooth_surface_is_right_at_the_pole():
    """A user audit's surface outside eq. 4, smooth in the incident direction at normal incidence (its
    k_A at the pole 1.003), measured through `portable` by the auditor's own float64 integrator (tests/
    data/pole_audit, written apart from roadgonio), corrected with the defaults. Before session 41 the
    fitted backbone's cone at the pole (eq. 4's empirical term, one-sided over the detector's footprint)
    put the tan eps = 0 row 16 % low (z about -3 in all 20 cells, k_A used 1.18) and S1 2.1 u(S1) high;
    with the penalty through the pole on the whole ln f (pole_offsets) the row is within its u, and so
    is S1 (docs/correction.md, "Smooth through the pole")."""
    folder = DATA / "pole_audit"
    measured, truth = read_table(folder / "measured_portable.csv"), read_table(folder / "truth.csv")
    res = api.correct(measured, load_instrument("portable"), forward="surface", u_measured="1%", seed=0)
    m = res.corrected.mask
    z = np.full(m.shape, np.nan)
    z[m] = np.log(res.corrected.r[m] / truth.r[m]) / res.budget.u_rel()
    assert np.all(np.abs(z[0][m[0]]) <= 2.0), z[0][m[0]]             # one direction: its 20 cells, one error
    s1_true = truth.s1()
    assert abs(res.after["S1"] - s1_true) <= 2.0 * res.after["u_S1"], (res.after["S1"], res.after["u_S1"], s1_true)
