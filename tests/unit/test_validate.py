"""roadgonio validate: the verdicts (agree / disagree / inconclusive) and the statistics behind them
(the command, its outputs and exit statuses are tests/system/test_validate_system.py; the Mitsuba
comparison itself is tests/plugin/test_stability_plugin.py)."""
from __future__ import annotations

import math

import pytest

from roadgonio.engines import CellResult
from roadgonio.engines import validate as V


def mc_cell(k, se, converged=True):
    return CellResult(tan_eps=4.0, beta_deg=2.0, k_a=k, se=se, samples=10, seconds=0.1, converged=converged)


def ref_cell(k, bound, converged=True):
    return CellResult(tan_eps=4.0, beta_deg=2.0, k_a=k, se=math.nan, error_bound=bound, samples=10, seconds=0.1,
                      converged=converged)


def test_pass_band_adds_the_bound_as_a_bound():
    q = ref_cell(0.5, 0.0)
    assert V.compare(q, mc_cell(0.5 + 3.9e-3, 1e-3)).verdict == "agree"
    assert V.compare(q, mc_cell(0.5 + 4.1e-3, 1e-3)).verdict == "disagree"
    # the float32 floor widens the band by floor * k
    assert V.compare(q, mc_cell(0.5 + 4.1e-3, 1e-3), floor=1e-3).verdict == "agree"
    # allowed = 4 SE + bound (never sqrt(SE^2 + bound^2))
    r = V.compare(ref_cell(0.5, 1e-4), mc_cell(0.501, 4e-4))
    assert r.sigma == pytest.approx(4e-4) and r.allowed == pytest.approx(4 * 4e-4 + 1e-4) and r.ok
    assert V.compare(ref_cell(0.5, 1e-4), mc_cell(0.5 + 4 * 4e-4 + 1.1e-4, 4e-4)).verdict == "disagree"
    assert V.compare(q, mc_cell(math.nan, 1e-3)).verdict == "disagree"


def test_a_monte_carlo_without_sampling_noise_is_judged_on_its_difference():
    """(audit 21, 7) a zero-aperture instrument's Monte Carlo has SE 0: validate printed diff/SE -inf,
    allowed inf, and the reason "-inf SE, within inf" for a round-off difference. z is undefined
    (NaN) there and the verdict's reason is the difference against the allowed band."""
    q = ref_cell(1.0, 1e-9)
    ok = V.compare(q, mc_cell(1.0 - 8.9e-16, 0.0), floor=1e-5)
    assert ok.verdict == "agree" and math.isnan(ok.z) and "inf" not in ok.reason and "SE 0" in ok.reason
    bad = V.compare(q, mc_cell(1.0 + 1e-4, 0.0), floor=1e-5)
    assert bad.verdict == "disagree" and math.isnan(bad.z) and "inf" not in bad.reason
    assert V.compare(q, mc_cell(1.0, 0.0)).z == 0.0


def test_reference_that_did_not_converge_is_inconclusive_never_agree():
    """The landed defect: a quadrature stopped at its cap with a 13 % error estimate made every
    cell 'agree'. A reference that did not converge says nothing: inconclusive, whatever the values."""
    r = V.compare(ref_cell(0.2979, 0.129, converged=False), mc_cell(0.2746, 2.7e-4))
    assert r.verdict == "inconclusive" and "did not converge" in r.reason
    # not even an exact match is an agreement then
    assert V.compare(ref_cell(0.5, 1e-6, converged=False), mc_cell(0.5, 1e-3)).verdict == "inconclusive"


def test_bound_wider_than_the_test_needs_is_inconclusive():
    se = 1e-3
    band = V.N_SIGMA * se
    ok = V.compare(ref_cell(0.5, 0.99 * V.REF_SHARE * band), mc_cell(0.5, se))
    wide = V.compare(ref_cell(0.5, 1.01 * V.REF_SHARE * band), mc_cell(0.5, se))
    assert ok.verdict == "agree" and wide.verdict == "inconclusive" and "wider than the test needs" in wide.reason
    # but a difference beyond even the wide band is a real disagreement
    assert V.compare(ref_cell(0.5, 2e-3), mc_cell(0.5 + 6.1e-3, se)).verdict == "disagree"


def test_monte_carlo_at_its_cap_is_inconclusive_unless_it_disagrees():
    assert V.compare(ref_cell(0.5, 1e-5), mc_cell(0.5001, 1e-3, converged=False)).verdict == "inconclusive"
    assert V.compare(ref_cell(0.5, 1e-5), mc_cell(0.51, 1e-3, converged=False)).verdict == "disagree"


def test_reference_with_a_standard_error_combines_in_quadrature():
    ref = CellResult(tan_eps=4.0, beta_deg=2.0, k_a=0.5, se=3e-4, samples=10, seconds=0.1)
    r = V.compare(ref, mc_cell(0.5 + 1e-3, 4e-4))
    assert r.sigma == pytest.approx(5e-4) and r.allowed == pytest.approx(4 * 5e-4) and r.verdict == "agree"
    # a reference noisier than the tested backend cannot vouch for it
    ref2 = CellResult(tan_eps=4.0, beta_deg=2.0, k_a=0.5, se=5e-4, samples=10, seconds=0.1)
    assert V.compare(ref2, mc_cell(0.5, 4e-4)).verdict == "inconclusive"


def test_an_se_of_few_degrees_of_freedom_gets_the_t_quantile():
    """An SE from 16 replicates (15 degrees of freedom: the Mitsuba backend's first pass) makes z a
    t_15 variable, beyond 4 in 0.12 % of cells: the band is the t quantile of the probability of
    4 normal SEs, 5.48 SE (docs/validation.md, "How heavy are the tails"); an SE without degrees of
    freedom keeps 4; with a reference SE (the mesh Monte Carlo) the combined SE's degrees of freedom
    are Welch-Satterthwaite's."""
    from scipy.stats import norm, t as student_t
    q = ref_cell(0.5, 0.0)

    def mc(k, dof=15.0, se=1e-3):
        return CellResult(tan_eps=4.0, beta_deg=2.0, k_a=k, se=se, samples=10, seconds=0.1, se_dof=dof)
    a = V.compare(q, mc(0.5 + 5.4e-3))
    assert a.verdict == "agree" and a.dof == 15.0
    assert 2 * student_t.sf(a.n_sigma, 15) == pytest.approx(2 * norm.sf(V.N_SIGMA), rel=1e-9)
    assert a.n_sigma == pytest.approx(5.4804, abs=1e-4) and a.allowed == pytest.approx(a.n_sigma * 1e-3)
    assert V.compare(q, mc(0.5 + 5.6e-3)).verdict == "disagree"
    assert V.compare(q, mc(0.5 + 4.1e-3, dof=math.nan)).verdict == "disagree"       # no dof: a normal z
    assert V.compare(q, mc(0.5 + 4.1e-3, dof=1e6)).verdict == "disagree"            # many: as good as normal
    ref = CellResult(tan_eps=4.0, beta_deg=2.0, k_a=0.5, se=3e-4, samples=10, seconds=0.1, se_dof=63.0)
    r = V.compare(ref, mc(0.5, se=4e-4))
    want = (4e-4 ** 2 + 3e-4 ** 2) ** 2 / (4e-4 ** 4 / 15 + 3e-4 ** 4 / 63)
    assert r.dof == pytest.approx(want, rel=1e-12)
    assert r.allowed == pytest.approx(student_t.isf(norm.sf(V.N_SIGMA), want) * 5e-4, rel=1e-9)
    report = {"rows": [a], "n_sigma": V.N_SIGMA}
    assert V.band_text(report) == "5.48 SE (4 sigma at 15 degrees of freedom)"
    assert V.band_text({"rows": [V.compare(q, mc(0.5, dof=math.nan))], "n_sigma": V.N_SIGMA}) == "4 SE"


def test_overall_verdict_and_exit_status():
    a = V.compare(ref_cell(0.5, 0.0), mc_cell(0.5, 1e-3))
    d = V.compare(ref_cell(0.5, 0.0), mc_cell(0.6, 1e-3))
    i = V.compare(ref_cell(0.5, 0.0, converged=False), mc_cell(0.5, 1e-3))
    assert V.overall([a, a]) == "agree" and V.EXIT_STATUS["agree"] == 0
    assert V.overall([a, i]) == "inconclusive" and V.EXIT_STATUS["inconclusive"] == 3
    assert V.overall([a, i, d]) == "disagree" and V.EXIT_STATUS["disagree"] == 1
    assert V.counts([a, i, d, a]) == {"agree": 2, "disagree": 1, "inconclusive": 1}


def test_failed_line_says_a_cell_without_a_value_was_not_measured():
    """(user audit) a NaN k_A (the Mitsuba backend's where float32 underflows) printed "SE 0" on the
    FAILED line, as if the backend had measured it without noise; it says the cell was not measured.
    A real SE 0 and a difference in SE are printed as before."""
    q = ref_cell(0.5, 0.0)
    nan = V.compare(q, mc_cell(math.nan, math.nan))
    se0 = V.compare(q, mc_cell(0.5 + 1e-4, 0.0))
    far = V.compare(q, mc_cell(0.6, 1e-3))
    assert [r.verdict for r in (nan, se0, far)] == ["disagree"] * 3
    assert V.failed_cell_text(nan) == "(4, 2) not measured (its k_A or SE is NaN)"
    assert V.failed_cell_text(se0) == "(4, 2) diff +0.0001, SE 0"
    assert V.failed_cell_text(far) == "(4, 2) +100.0 SE"
    line = V.failed_line([nan, V.compare(q, mc_cell(0.5, 1e-3)), far])
    assert line == "FAILED: (4, 2) not measured (its k_A or SE is NaN), (4, 2) +100.0 SE"


def test_a_cell_the_backend_says_it_cannot_measure_is_inconclusive(tmp_path):
    """(user audit) a Mitsuba cell that stopped with no SE (too few samples carried the light: SE inf,
    not converged) or no value (float32 underflow: NaN, not converged) was 'disagree', exit 1, and
    with SE inf the plot failed (a singular matrix) and nothing was written. The backend said it could
    not measure the cell: inconclusive, with its note; a non-finite value it called converged stays a
    disagreement; the plot draws no bar for an infinite SE."""
    q = ref_cell(0.5, 0.0)
    mc = CellResult(tan_eps=4.0, beta_deg=2.0, k_a=0.49, se=math.inf, samples=10, seconds=0.1, converged=False,
                    extra={"note": "too few samples carried the light"})
    no_se = V.compare(q, mc)
    assert no_se.verdict == "inconclusive" and "stated no SE" in no_se.reason and "too few samples" in no_se.reason
    no_value = V.compare(q, mc_cell(math.nan, math.nan, converged=False))
    assert no_value.verdict == "inconclusive" and "stated no value" in no_value.reason
    assert V.compare(q, mc_cell(math.nan, math.nan)).verdict == "disagree"
    V.plot({"rows": [no_se, no_value], "n_sigma": V.N_SIGMA, "against": "mitsuba", "reference": "quadrature",
            "verdict": "inconclusive", "counts": V.counts([no_se, no_value])}, tmp_path / "v.png")
    assert (tmp_path / "v.png").stat().st_size > 10_000


def test_validate_plot_draws_infinite_and_unmeasured_cells_distinctly(tmp_path):
    """(user audit) validate.png drew a cell of infinite z as a plain bar at the axis' end (-12), like
    any large difference, and a NaN k_A not at all: z_bars, what the plot draws, clips an infinite z
    at the axis labelled '-inf', a finite one beyond it labelled with its value, and a cell without a
    value gets no bar and the label 'not measured'."""
    from dataclasses import replace
    limit = 3 * V.N_SIGMA
    q = ref_cell(0.5, 0.0)
    near = V.compare(q, mc_cell(0.502, 1e-3))
    far = V.compare(q, mc_cell(0.45, 1e-3))
    infinite = replace(far, z=-math.inf)
    nan = V.compare(q, mc_cell(math.nan, math.nan))
    se0_bad, se0_ok = V.compare(q, mc_cell(0.5 - 1e-4, 0.0)), V.compare(q, mc_cell(0.5, 0.0))
    se0_ok = replace(se0_ok, z=math.nan)
    bars = V.z_bars([near, far, infinite, nan, se0_bad, se0_ok], limit)
    assert bars[0] == (near.z, "") and abs(near.z) < limit
    assert bars[1] == (-limit, "-50") and far.z < -limit
    assert bars[2] == (-limit, "-inf")
    assert bars[3] == (0.0, "not measured")
    assert bars[4] == (-limit, "SE 0") and bars[5] == (0.0, "SE 0")
    V.plot({"rows": [near, far, infinite, nan, se0_bad], "n_sigma": V.N_SIGMA, "against": "mitsuba",
            "reference": "quadrature", "verdict": "disagree",
            "counts": V.counts([near, far, infinite, nan, se0_bad])}, tmp_path / "v.png")   # draws them


def test_select_cells_is_the_one_parser():
    """engines.cells.select_cells: the named selections, a TAN:BETA list, pairs; an empty selection,
    a malformed item, a cell off the range, 'table' without a table and an off-grid cell where the
    grid is required are one-line errors naming the field."""
    from roadgonio.engines.cells import EXTREME_CELLS, select_cells
    from roadgonio.errors import InputError
    from roadgonio.surface.rtable import bundled_table
    assert select_cells("extremes") == list(EXTREME_CELLS)
    assert select_cells("12:0, 4:2.5") == [(12.0, 0.0), (4.0, 2.5)]
    assert select_cells([(12, 0), (4.0, 2.5)]) == [(12.0, 0.0), (4.0, 2.5)]
    assert len(select_cells("all")) == 580
    r3 = bundled_table("R3")
    assert select_cells("table", r3) == r3.cells and 300 < len(r3.cells) < 580
    for must in [(0.0, 0.0), (0.0, 180.0), (12.0, 0.0), (12.0, 180.0)]:
        assert must in EXTREME_CELLS
    for bad in ("12", "a:b", "1:200", "-1:0", "", " ", [], [(1, 2, 3)], [(True, 0)], "12:0,4"):
        with pytest.raises(InputError) as e:
            select_cells(bad, field="--cells")
        assert e.value.field == "--cells"
    with pytest.raises(InputError, match="r-table"):
        select_cells("table", None)
    with pytest.raises(InputError, match="not on the CIE grid"):
        select_cells("4:2.5", on_grid=True)
    # a cell given twice was computed and counted twice (user audit, session 19)
    for twice in ("2:0,4:5,2:0", [(2, 0), (2.0, 0.0)]):
        with pytest.raises(InputError, match="2:0 is given twice") as e:
            select_cells(twice, field="--cells")
        assert e.value.field == "--cells"


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_exact_cases_agree_against_the_float64_monte_carlo(seed):
    """A Lambertian sample: k_A = 1 in every backend but for float64 round-off. numpy-mc differed
    from the reference by 1-4 ulp with an 'SE' of round-off size, and with a floor of 0 that was
    '+6.7 SE, disagree' (audit 27, every seed); its round-off floor makes the verdict agree."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.model import RoadModel
    report = V.validate(load_instrument("portable"), RoadModel.lambert(), [(12.0, 0.0), (0.0, 0.0), (4.0, 2.0), (1.0, 30.0)],
                        against="numpy-mc", seed=seed)
    assert report["floor"] == V.FLOAT32_FLOOR["numpy-mc"] > 0
    assert [r.verdict for r in report["rows"]] == ["agree"] * 4, [r.reason for r in report["rows"]]
    assert all(abs(r.k_mc - 1.0) < 1e-13 for r in report["rows"])


@pytest.mark.parametrize("calibration", [{"mode": "absolute"}, {"mode": "reference", "reference": "R1"}])
def test_validate_an_instrument_calibrated_absolute_or_against_a_reference(calibration):
    """The RQMC reference is asked per cell for the bound the test needs, through the calibration's
    wrapper (user audit: AttributeError 'CalibratedBackend' object has no attribute 'compute_cell',
    exit status 1 as for a disagreement). numpy-mc against it on the portable preset, both in the same
    calibration: they agree."""
    from helpers import UNCERTAINTY_MODEL as model
    from roadgonio.instrument.config import load_instrument
    inst = load_instrument("portable").with_changes(calibration=calibration)
    report = V.validate(inst, model, [(4.0, 0.0)], against="numpy-mc", reference="reference", rel_se=3e-3, seed=1)
    row = report["rows"][0]
    assert row.verdict == "agree", row.reason
    assert row.k_ref != 1.0 and abs(row.k_mc / row.k_ref - 1) < 0.02


@pytest.mark.parametrize("floor", ["1", -1.0, math.nan, True])
def test_a_bad_floor_names_its_type_and_value(floor):
    """(user audit) rg.validate(floor='1') said 'expected a floor >= 0, got 1': a text read as a number.
    The error names the type and the value as given, before any work."""
    import roadgonio as rg
    from roadgonio.errors import InputError
    with pytest.raises(InputError) as err:
        rg.validate("portable", "R3", cells="0:0", floor=floor)
    assert err.value.field == "floor" and f"{type(floor).__name__} {floor!r}" in str(err.value)


def test_validate_takes_its_backends_from_the_registry(monkeypatch):
    """(review, session 39) validate, its command line and its reference list named their backends
    themselves, so a backend added to the registry was not available to validate. A registry entry with
    a validate role is now offered by the command line and accepted by the API's check."""
    import dataclasses

    from roadgonio import api
    from roadgonio.cli import build_parser
    from roadgonio.engines import registry
    extra = dataclasses.replace(registry.BACKENDS["numpy-mc"], name="numpy-mc-2")
    monkeypatch.setitem(registry.BACKENDS, "numpy-mc-2", extra)
    assert "numpy-mc-2" in api.validate_backends("checked")
    sub = next(a for a in build_parser()._actions if hasattr(a, "choices") and a.choices and "validate" in a.choices)
    against = next(a for a in sub.choices["validate"]._actions if "--against" in a.option_strings)
    assert "numpy-mc-2" in against.choices
    assert set(api.validate_backends("reference")) == {"reference", "quadrature", "numpy-mc-mesh"}


def test_validate_plot_draws_k_a_over_decades_on_a_log_axis(tmp_path, monkeypatch):
    """(user audit, session 44) k_A 0.82 and 926 in one report (a lobe far narrower than the apertures)
    on a linear axis put the cells near 1 on zero; the axis is logarithmic there, linear otherwise."""
    import roadgonio.fileio as F
    drawn = {}

    def keep(fig, path, **kw):
        drawn["scale"] = fig.axes[1].get_yscale()
        return path
    monkeypatch.setattr(F, "atomic_savefig", keep)
    for ks, scale in (((0.82, 926.0), "log"), ((0.82, 1.05), "linear")):
        rows = [V.compare(ref_cell(k, 1e-4 * k), mc_cell(k, 1e-4 * k)) for k in ks]
        V.plot({"rows": rows, "n_sigma": V.N_SIGMA, "against": "mitsuba", "reference": "quadrature",
                "verdict": "agree", "counts": V.counts(rows)}, tmp_path / "v.png")
        assert drawn["scale"] == scale
