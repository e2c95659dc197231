"""The Python API (roadgonio.api, exported from roadgonio): what a notebook user calls."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import roadgonio as rg
from roadgonio.errors import InputError
from roadgonio.geometry import BETA_GRID_DEG, TAN_EPS_GRID
from roadgonio.surface.rtable import RTable, bundled_table
from tolerances import FILE_RTOL


#: float64 round-off allowed beside the quadrature's error bound of a Lambertian k_A (= 1 exactly).
ROUNDOFF = 4 * 2.2e-16


def test_ka_table_of_a_lambertian_sample_is_one_within_its_bound():
    """The issue's acceptance line: rg.ka_table('portable', 'lambert', backend='quadrature', accuracy='fast')."""
    ds = rg.ka_table("portable", "lambert", backend="quadrature", accuracy="fast")
    assert dict(ds.sizes) == {"tan_eps": 29, "beta": 20}
    assert set(ds.data_vars) == {"k_a", "se", "error_bound", "confidence_bound", "confidence_level", "samples",
                                 "seconds", "converged", "k_a_direct", "k_a_direct_se", "stray_fraction",
                                 "stray_fraction_se", "se_dof"}
    assert np.array_equal(ds.tan_eps, TAN_EPS_GRID) and np.array_equal(ds.beta, BETA_GRID_DEG)
    # no stray light: the direct light is everything, the stray fraction 0 exactly
    assert np.array_equal(ds.k_a_direct, ds.k_a) and (ds.stray_fraction.values == 0.0).all()
    bound = ds.error_bound.values
    assert np.isfinite(bound).all() and np.isnan(ds.se).all()          # deterministic: a bound, no SE
    assert np.isnan(ds.se_dof).all()                                     # ... and no degrees of freedom
    assert (np.abs(ds.k_a.values - 1.0) <= bound + ROUNDOFF).all()
    assert ds.converged.values.all()
    prov = json.loads(ds.attrs["provenance"])
    assert prov["backend"] == "quadrature" and prov["instrument"]["instrument"]["name"] == "portable"
    assert {"roadgonio", "numpy", "mitsuba", "drjit"} <= set(prov["versions"])
    assert ds.attrs["instrument"] == "portable" and ds.attrs["cells_computed"] == 580
    for v in ds.attrs.values():                      # netCDF-safe attributes: text and numbers only
        assert isinstance(v, (str, int, float)) and not isinstance(v, bool)
    assert "seed" not in ds.attrs                    # a deterministic backend takes no seed (was -1)
    assert ds.attrs["accuracy"] == "fast"            # the preset; none without one (audit 22: was '')
    assert "accuracy" not in rg.ka_table("portable", "lambert", backend="quadrature", cells=[(1.0, 0.0)]).attrs
    # the SE fields without stray light: k_a_direct is k_a with its se (none here: the bound covers it),
    # the stray fraction is 0 exactly; both descriptions say so
    assert np.isnan(ds.k_a_direct_se).all() and (ds.stray_fraction_se.values == 0.0).all()
    assert "error_bound" in ds.k_a_direct_se.attrs["description"]
    assert "exactly" in ds.stray_fraction_se.attrs["description"]


def test_ka_table_records_the_seed_the_backend_used():
    """Without a seed a Monte Carlo backend uses its default (0), and the Dataset says 0 (was -1)."""
    for seed in (None, 5):
        ds = rg.ka_table("portable", "lambert", backend="reference", accuracy="fast", cells=[(12, 0)], seed=seed)
        assert ds.attrs["seed"] == (0 if seed is None else seed)
        assert json.loads(ds.attrs["provenance"])["settings"]["seed"] == ds.attrs["seed"]


def test_ka_table_some_cells_nan_elsewhere(r3like):
    ds = rg.ka_table("portable", r3like, backend="quadrature", accuracy="fast", cells=[(12, 0), (0, 0)])
    done = ds.k_a.notnull()
    assert int(done.sum()) == 2 and bool(done.sel(tan_eps=12, beta=0)) and bool(done.sel(tan_eps=0, beta=0))
    assert int(ds.converged.sum()) == 2 and np.isnan(ds.error_bound.values[~done.values]).all()
    cell = rg.ka_cell("portable", r3like, 12, 0, backend="quadrature", accuracy="fast")
    assert cell.k_a == float(ds.k_a.sel(tan_eps=12, beta=0))          # same backend, same settings
    assert cell.k_a < 1.0 - 10 * cell.error_bound                   # an aperture effect, resolved


def test_ka_table_input_errors(r3like):
    with pytest.raises(InputError, match="'table' needs"):
        rg.ka_table("portable", "lambert", backend="quadrature", cells="table")
    with pytest.raises(InputError, match="not on the CIE grid"):
        rg.ka_table("portable", r3like, backend="quadrature", cells=[(3.3, 0)])
    with pytest.raises(InputError) as err:
        rg.ka_table("portable", r3like, backend="quadrature", rel_se=2.0, cells=[(0, 0)])
    assert err.value.field == "rel_se"
    with pytest.raises(InputError, match="instrument"):
        rg.ka_table(3, r3like, backend="quadrature")
    with pytest.raises(InputError) as err:
        rg.ka_cell("portable", r3like, -1, 0, backend="quadrature")
    assert err.value.field == "tan_eps"


def test_read_table_is_r_on_the_cie_grid(tmp_path):
    da = rg.read_table("R3")
    t = bundled_table("R3")
    assert da.dims == ("tan_eps", "beta") and da.attrs["name"] == "R3" and da.attrs["units"] == "sr^-1"
    assert np.array_equal(np.isnan(da.values), ~t.mask) and np.allclose(da.values[t.mask], t.r[t.mask], rtol=0)
    assert 0.0005 < float(da.sel(tan_eps=0, beta=0)) < 0.05     # r itself (R3: 0.0294 sr^-1), not r x 1e4
    for suffix in (".csv", ".rtb"):
        path = rg.write_table(da, tmp_path / f"r3{suffix}")
        back = rg.read_table(path)
        assert np.allclose(back.values[t.mask], t.r[t.mask], rtol=FILE_RTOL) and np.isnan(back.values[~t.mask]).all()
    with pytest.raises(InputError, match="CIE grid"):
        rg.write_table(da.isel(beta=slice(0, 10)), tmp_path / "cut.csv")
    # a suffix no command reads back is refused, not written as CSV text (trial 9: 'x.xlsx')
    for name in ("r3.xlsx", "r3"):
        with pytest.raises(InputError, match=r"expected a \.csv or \.rtb file") as err:
            rg.table_info("R3", to=tmp_path / name)
        assert err.value.field == "to" and not (tmp_path / name).exists()


def _refused_as_r_table(path) -> str:
    with pytest.raises(InputError) as err:
        rg.read_table(path)
    msg = str(err.value)
    assert err.value.path == str(path) and "\n" not in msg
    assert "this is a k_A table" in msg and "not an r-table" in msg and "multiply" not in msg
    return msg


def test_a_ka_table_is_not_read_as_an_r_table_but_as_k_a(tmp_path):
    """(trial 10 D2) ka.csv has the r-table layout with k_A unscaled: rg.read_table divided it by 1e4
    and labelled it sr^-1 (k_A of a Lambert sample, all 1, passed the scale check), and refused one
    whose k_A are all below 1 with the advice to multiply by 1e4. It is refused as a k_A table, and
    rg.read_ka_table reads it unscaled: the ka writer's own file, the bench's cached k_A tables and
    a table reading low."""
    from pathlib import Path
    from roadgonio.surface.rtable import KA_HEADER, grid_csv_text
    out = tmp_path / "ka"
    ds = rg.ka_table("portable", "lambert", backend="quadrature", accuracy="fast", cells=[(0, 0), (12, 0)], out=out,
                     plot=False)
    _refused_as_r_table(out / "ka.csv")
    k = rg.read_ka_table(out / "ka.csv")
    assert k.attrs["units"] == "1" and k.dims == ("tan_eps", "beta")
    assert np.array_equal(np.isnan(k.values), np.isnan(ds.k_a.values))
    ok = np.isfinite(k.values)
    assert np.allclose(k.values[ok], ds.k_a.values[ok], rtol=1e-6, atol=0)     # ka.csv holds 7 digits
    bench = Path(__file__).resolve().parents[2] / "bench" / "data" / "outside_ka_table_A.csv"
    _refused_as_r_table(bench)
    assert float(rg.read_ka_table(bench).sel(tan_eps=0, beta=0)) == 1.023537187     # as written, unscaled
    low = tmp_path / "ka_below1.csv"
    low.write_text(grid_csv_text(np.full((29, 20), 0.95), f"{KA_HEADER}instrument 'low' for sample 'R3'"))
    _refused_as_r_table(low)
    assert np.all(rg.read_ka_table(low).values == 0.95)
    r3 = rg.write_table(rg.read_table("R3"), tmp_path / "r3.csv")
    with pytest.raises(InputError, match="not a k_A table") as err:
        rg.read_ka_table(r3)                               # an r-table never passes as k_A (1e4 too large)
    assert err.value.path == str(r3)


def test_the_tables_written_beside_k_a_are_not_read_as_r_or_its_uncertainty(tmp_path):
    """(audit 21, 1) `road --u ka_se.csv` read k_A's standard error (~1e-3, unscaled) as u(r) x 1e4 and
    reported L_av +- 2e-6: only ka.csv's own header was known. Every table a k_A run writes (its
    bound, SE, direct light, stray fraction) is now refused as an r-table and as u(r), with one line."""
    from roadgonio.cli import main
    from roadgonio.surface.rtable import grid_csv_text, ka_output_header
    out = tmp_path / "ka"
    rg.ka_table("portable", "R3", backend="quadrature", accuracy="fast", cells=[(0, 0), (12, 0)], out=out, plot=False)
    files = [out / "ka_bound.csv"]
    for what, value in (("standard error of k_A", 1e-3), ("stray fraction of the road signal", 0.2)):
        f = tmp_path / f"{value}.csv"
        f.write_text(grid_csv_text(np.full((29, 20), value), ka_output_header(what, "portable", "R3", "mitsuba")))
        files.append(f)
    for f in files:
        assert f.exists()
        with pytest.raises(InputError, match="this is a table of a k_A run") as err:
            rg.read_table(f)
        assert err.value.path == str(f) and "\n" not in str(err.value)
    rc = main(["road", "--table", "R3", "--u", str(files[1]), "--out", str(tmp_path / "road"), "--no-plots"])
    assert rc == 2 and not (tmp_path / "road").exists()


@pytest.mark.parametrize("largest", [0.0335, 0.999, 1.001])
def test_write_table_refuses_what_read_table_refuses(tmp_path, largest):
    """(trial 10 D3) rg.write_table wrote a CSV whose largest value (r x 1e4) was 0.0335, which
    rg.read_table then refused as r in sr^-1: the writer's read-back lacked the reader's scale check.
    Either side of the threshold the writer and the reader now agree: refused when written (one
    line, the reader's reason, nothing on disk) or read back as written."""
    from roadgonio.surface.rtable import R_SCALE, grid_csv_text
    r3 = rg.read_table("R3")
    da = (r3 * (largest / R_SCALE / float(r3.max()))).assign_attrs(name="x")
    path = tmp_path / "x.csv"
    by_hand = tmp_path / "by_hand.csv"
    by_hand.write_text(grid_csv_text(da.values, "by hand", scale=R_SCALE))
    try:
        rg.read_table(by_hand)
        reader_refuses = None
    except InputError as err:
        reader_refuses = err.reason
    if reader_refuses is None:
        back = rg.write_table(da, path)
        assert np.allclose(rg.read_table(back).values, da.values, rtol=FILE_RTOL, equal_nan=True)
        assert largest > 1
        return
    assert largest < 1 and "looks like r in sr^-1" in reader_refuses
    with pytest.raises(InputError) as err:
        rg.write_table(da, path)
    assert "would not read back" in str(err.value) and reader_refuses in str(err.value)
    assert "\n" not in str(err.value) and not path.exists()


def test_write_table_refuses_a_ka_table_as_r(tmp_path):
    """(trial 10 D3) The writer's read-back is the reader's: a k_A DataArray (header 'k_A of ...')
    written as an r-table would be refused by rg.read_table, so it is refused when written."""
    from pathlib import Path
    bench = Path(__file__).resolve().parents[2] / "bench" / "data" / "outside_ka_table_A.csv"
    with pytest.raises(InputError, match=r"would not read back \(this is a k_A table") as err:
        rg.write_table(rg.read_ka_table(bench), tmp_path / "k.csv")
    assert "\n" not in str(err.value) and not (tmp_path / "k.csv").exists()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), blank=st.floats(0.0, 0.6), suffix=st.sampled_from([".csv", ".rtb"]),
       spread=st.floats(0.0, 1.0))
def test_table_file_round_trip_property(tmp_path_factory, seed, blank, suffix, spread):
    """Property: any road-like r-table (R3's values each scaled by up to 10^spread either way, so a
    plausible Q0 < 1 sr^-1 as the RTB reader expects; blanks anywhere but (0, 0)) survives
    write_table + read_table to 6 significant digits, blanks staying blank."""
    rng = np.random.default_rng(seed)
    r = bundled_table("R3").r * 10.0 ** rng.uniform(-spread, spread, size=(29, 20))
    r[rng.random((29, 20)) < blank] = np.nan
    r[0, 0] = 0.03
    path = tmp_path_factory.mktemp("rt") / f"t{suffix}"
    rg.write_table(RTable(r, name="prop"), path)
    back = rg.read_table(path).values
    assert np.array_equal(np.isnan(back), np.isnan(r))
    ok = np.isfinite(r)
    assert np.allclose(back[ok], r[ok], rtol=FILE_RTOL, atol=0)


def test_fit_wrapper_and_fit_result_as_a_sample():
    res = rg.fit(rg.read_table("R3"), fixed={"n_phong": 30.0, "n_retro": 10.0, "p": 2.0, "h": 0.5, "mu": 0.03})
    assert res.model.params.n_phong == 30.0 and res.rms_dev_pct < 10.0
    c = rg.ka_cell("lab", res, 2, 0, backend="quadrature", accuracy="fast")   # a fit result is a sample
    assert math.isfinite(c.k_a) and c.converged


def test_correct_with_a_lambertian_reference_changes_nothing(tmp_path):
    """k_A of a Lambertian reference is 1: the corrected table equals the measured one (quadrature bound)."""
    t = bundled_table("C2")
    sub = np.full_like(t.r, np.nan)
    keep = [(0, 0), (0, 1), (1, 0), (1, 1), (8, 0), (8, 1)]   # a Q0 patch, (2, 0) for S1, a specular cell
    for i, j in keep:
        sub[i, j] = t.r[i, j]
    c = rg.correct(RTable(sub, name="m"), "portable", reference="lambert", alternatives="none",
                   backend="quadrature", accuracy="fast")
    m = np.isfinite(sub)
    assert np.allclose(c.corrected.r[m], sub[m], rtol=1e-12) and np.isnan(c.corrected.r[~m]).all()
    assert c.provenance["backend"] == "quadrature" and c.summary()["cells"] == 6


def test_estimate_uncertainty_matches_the_room():
    """rg.estimate_uncertainty is run_uncertainty with the command's defaults: same seed, same numbers."""
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.model import RoadModel, RoadParams
    from roadgonio.uncertainty import parse_sigma_spec, run_uncertainty
    model = RoadModel(RoadParams(k_diff=0.05, k_phong=0.3, n_phong=30))
    a = rg.estimate_uncertainty("portable", model, {"alpha_deg": 0.01, "eps_deg": "0.05:rect"}, trials=500, aperture=False)
    b = run_uncertainty(model, load_instrument("portable"), parse_sigma_spec("alpha_deg=0.01,eps_deg=0.05:rect"),
                        trials=500, aperture=False, progress=False)
    assert np.array_equal(a.cases["no_aperture"].mc["u"], b.cases["no_aperture"].mc["u"])
    assert a.spec.to_dict()["eps_deg"]["distribution"] == "rectangular"


# ----------------------------------------------------------------------------------------------
# A command's backends: the command line offers exactly what the API takes
# ----------------------------------------------------------------------------------------------

class _Reached(Exception):
    """The command got past its checks of the arguments to its work (stopped there by the test)."""


def _stop(*_a, **_k):
    raise _Reached


#: per command: the command line without --backend, the API call, and the work both reach (stopped)
_BACKEND_COMMANDS = {
    "design": (["design", "--instrument", "portable", "--vary", "source.radius_m=0.02", "--sample", "lambert",
                "--cells", "4:0", "--workers", "0", "--no-plots", "--quiet"],
               lambda b, out: rg.design_study("portable", ["source.radius_m=0.02"], "lambert", cells="4:0",
                                              backend=b, workers=0, out=out, plots=False),
               ("roadgonio.design.run", "run_design")),
    "uncertainty": (["uncertainty", "--instrument", "portable", "--sample", "lambert", "--sigma", "alpha_deg=0.01",
                     "--no-plots", "--quiet"],
                    lambda b, out: rg.estimate_uncertainty("portable", "lambert", "alpha_deg=0.01", backend=b,
                                                           out=out, plots=False),
                    ("roadgonio.uncertainty.run", "run_uncertainty")),
    "correct": (["correct", "--measured", "R3", "--instrument", "portable", "--no-plots", "--quiet"],
                lambda b, out: rg.correct("R3", "portable", backend=b, out=out, plots=False),
                ("roadgonio.correction", "correct_files")),
}


@pytest.mark.parametrize("command", list(_BACKEND_COMMANDS))
def test_the_command_line_takes_the_backends_the_api_takes(command, tmp_path, monkeypatch, capsys):
    """design and correct listed four backends and uncertainty two by hand, while the API took every
    backend of the registry (design, correct) or checked its own copy of the list (uncertainty): the
    two entry points took different arguments. For every registered backend (and an unknown name)
    either both reach the command's work or both refuse with a one-line message listing the same
    backends."""
    import importlib
    from roadgonio.cli import main
    from roadgonio.engines import registry
    argv, call, (module, work) = _BACKEND_COMMANDS[command]
    monkeypatch.setattr(importlib.import_module(module), work, _stop)
    monkeypatch.setattr(registry, "prepare_entry_point", lambda *a, **k: None)    # no Mitsuba variant needed
    takes, refused = [], {}
    for name in [*registry.BACKENDS, "nope"]:
        try:
            call(name, tmp_path / f"api-{name}")
            raise AssertionError(f"{command}: the API neither refused {name} nor reached its work")
        except _Reached:
            api_takes = True
        except InputError as err:
            api_takes, refused[name] = False, str(err)
        capsys.readouterr()
        try:
            rc = main(argv + ["--backend", name, "--out", str(tmp_path / f"cli-{name}")])
        except _Reached:
            cli_takes = True
        except SystemExit as exc:          # argparse: --backend not among the choices
            cli_takes, rc = False, exc.code
        else:
            cli_takes = False
        err = capsys.readouterr().err.strip()
        assert cli_takes == api_takes, (command, name, err, refused.get(name))
        if api_takes:
            takes.append(name)
        else:
            assert rc == 2 and "backend" in err and "error" in err.splitlines()[-1], err
            refused[name] = (refused[name], err)
    assert "quadrature" in takes and "nope" in refused
    import re
    for api_msg, err in refused.values():           # both refusals name exactly the backends taken
        assert "\n" not in api_msg
        assert api_msg.split("expected one of ")[1].split(", ") == takes, api_msg
        assert re.findall(r"'([^']+)'", re.search(r"choose from ([^)]*)\)", err).group(1)) == takes, err
    from roadgonio import api
    assert list(api.backends(command)) == takes     # the choices the help offers


def test_a_cell_beyond_the_tables_last_row_notes_the_extrapolation(r3like):
    """tan eps 100 for a sample fitted to a table: computed, with a note that the model is there an
    extrapolation of the fit (trial 9: no word); none for a model that is no fit (Lambert)."""
    from roadgonio.errors import ModelWarning
    with pytest.warns(ModelWarning, match="beyond the r-tables' last row"):
        c = rg.ka_cell("lab", "R3", 100.0, 0.0, backend="quadrature", accuracy="fast")
    assert np.isfinite(c.k_a)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error", ModelWarning)
        rg.ka_cell("lab", "lambert", 100.0, 0.0, backend="quadrature", accuracy="fast")
        rg.ka_cell("lab", "R3", 12.0, 0.0, backend="quadrature", accuracy="fast")



@pytest.mark.parametrize("command", ["validate", "render", "design"])
def test_validate_render_and_design_note_a_cell_beyond_the_table_as_ka_does(command, monkeypatch, tmp_path):
    """User audits, sessions 19 and 24: `validate --cells 13:0`, `render --tan-eps 13` and `design --cells
    13:0` computed a cell beyond the table's last row with no word, while `ka` says it is an
    extrapolation of the fit. One rule for the four; a cell within the table says nothing. (The
    computation itself is stopped right after the note: what is checked is what the user is told
    first.)"""
    from roadgonio.design import run as D
    from roadgonio.engines import validate as V
    from roadgonio.engines.mitsuba import images
    from roadgonio.errors import ModelWarning

    class Stop(Exception):
        pass

    def stop(*a, **k):
        raise Stop
    monkeypatch.setattr(V, "validate", stop)
    monkeypatch.setattr(images, "render_cell_images", stop)
    monkeypatch.setattr(D, "run_design", stop)
    monkeypatch.setattr("roadgonio.engines.registry.prepare_entry_point", lambda *a, **k: None)

    def run(t):
        if command == "validate":
            rg.validate("lab", "R3", cells=f"{t:g}:0,2:0", against="numpy-mc")
        elif command == "design":
            rg.design_study("lab", ["source.radius_m=0.01,0.02"], "R3", cells=f"2:0,{t:g}:1", workers=0)
        else:
            rg.render("lab", "R3", t, 0.0, tmp_path / "r")
    with pytest.warns(ModelWarning, match="tan eps 13 is beyond the r-tables' last row"), pytest.raises(Stop):
        run(13.0)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error", ModelWarning)
        with pytest.raises(Stop):
            run(12.0)


def test_road_metrics_refuses_a_list_of_u_of_another_length_than_the_tables():
    """Trial 11 D11: u=['corrected_u.csv'] for two tables was put on the last table, while the
    docs say a list has one entry per table; a list of 1 for 2 tables is refused like one of 3 (before
    any file is read: the u named here does not exist)."""
    for us in (["no_such_u.csv"], ["no_such_u.csv"] * 3):
        with pytest.raises(InputError, match=f"one entry per table .*: expected 2, got {len(us)}") as err:
            rg.road_metrics(["R3", "R2"], u=us)
        assert err.value.field == "u"


def test_correct_refuses_what_it_would_drop_or_misread(tmp_path):
    """(audit 21, correct and the API) each was accepted, dropped or a traceback: a misspelt keyword
    (u_measurd='5%' gave 1 %), alternatives 3 or ',' (the model component vanished), joint='no'
    (truthy), workers=-1 (an error about 'out'), u_measured as an ndarray (read as a file name, a
    several-kB message). Each is now one InputError naming the argument."""
    m = rg.read_table("R3")
    for kwargs, fld in (({"u_measurd": "5%"}, "u_measurd"), ({"alternatives": 3}, "--alternatives"),
                        ({"alternatives": ","}, "--alternatives"), ({"joint": "no"}, "joint"),
                        ({"workers": -1}, "workers"), ({"u_measured": np.ones(3)}, "u_measured")):
        args = {"reference": "R3", "alternatives": "none", "backend": "quadrature", **kwargs}
        with pytest.raises(InputError) as err:
            rg.correct(m, "portable", out=tmp_path / "c", **args)
        assert err.value.field == fld and "\n" not in str(err.value) and len(str(err.value)) < 400, str(err.value)
    assert not (tmp_path / "c").exists()
    # a DataArray (or a numpy number) of u is taken as the API takes tables everywhere else
    res = rg.correct(m, "portable", reference="R3", alternatives="none", u_measured=m * 0.02, backend="quadrature",
                     accuracy="fast")
    meas = res.budget.components["measurement"]
    assert np.allclose(np.sqrt(np.diag(meas)), 0.02, rtol=1e-9)


def test_correct_refuses_a_k_a_table_as_the_measurements_uncertainty(tmp_path):
    """User audit, session 24: `correct --u-measured ka.csv` read k_A (unscaled) as u x 1e4: u of 1e-4 r
    and a false misfit note, exit 0, while `road --u ka.csv` refuses it. One line naming the file and
    the argument, as every other reader of r-tables gives; a table of u is still taken."""
    from roadgonio.surface.rtable import KA_HEADER, grid_csv_text
    m = rg.read_table("R3")
    ka = tmp_path / "ka.csv"
    ka.write_text(grid_csv_text(np.full((29, 20), 0.97), f"{KA_HEADER}instrument 'portable' for sample 'R3'"))
    se = tmp_path / "ka_se.csv"
    from roadgonio.surface.rtable import ka_output_header
    se.write_text(grid_csv_text(np.full((29, 20), 0.001), ka_output_header("standard error", "portable", "R3",
                                                                            "mitsuba")))
    for path in (ka, se):
        with pytest.raises(InputError) as err:
            rg.correct(m, "portable", reference="R3", alternatives="none", backend="quadrature", u_measured=str(path),
                       out=tmp_path / "c")
        msg = str(err.value)
        assert err.value.path == str(path) and err.value.argument == "u_measured" and "\n" not in msg, msg
        assert "k_A" in msg and "expected a table of per-cell standard uncertainties" in msg
    assert not (tmp_path / "c").exists()
    u = rg.write_table(m * 0.02, tmp_path / "u.csv")
    res = rg.correct(m, "portable", reference="R3", alternatives="none", u_measured=str(u), backend="quadrature",
                     accuracy="fast")
    assert np.allclose(np.sqrt(np.diag(res.budget.components["measurement"])), 0.02, rtol=1e-5)


def test_a_correction_folder_of_another_run_says_what_correct_can_do(tmp_path):
    """(audit 21, 2) a rerun with other alternatives said 'use another --out folder, or --fresh to
    discard it'; correct has no --fresh (the command and the API refused it)."""
    from roadgonio.fileio import FRESH_HINT, MOVE_HINT, NO_FRESH_HINTS, without_fresh
    NO_FRESH_HINT = NO_FRESH_HINTS[FRESH_HINT]
    m = rg.read_table("R3")
    common = dict(reference="R3", backend="quadrature", accuracy="fast", out=tmp_path / "c", plots=False)
    rg.correct(m, "portable", alternatives="R2", **common)
    with pytest.raises(InputError) as err:
        rg.correct(m, "portable", alternatives="R4", **common)
    assert NO_FRESH_HINT in str(err.value) and "--fresh" not in str(err.value)
    e = InputError(f"this folder holds x; {FRESH_HINT}", path="p", line=1)
    assert without_fresh(e).reason == f"this folder holds x; {NO_FRESH_HINT}" and without_fresh(e).path == "p"
    # the journal's own troubles (unreadable, corrupt) say what to do without --fresh too
    e = InputError(f"corrupt journal line; {MOVE_HINT}", path="p", line=3)
    assert without_fresh(e).reason == "corrupt journal line; move the folder away" and without_fresh(e).line == 3


def test_api_arguments_of_the_wrong_type_are_one_input_error(tmp_path):
    """(audit 21, 4-5) write_table(da, None), design_study(vary=3) and second_aperture(sample=3) ended
    in TypeError / AttributeError tracebacks; second_aperture refused the RTable and DataArray its
    docstring promises (AttributeError 'evaluate')."""
    da = rg.read_table("R3")
    for call, fld in ((lambda: rg.write_table(da, None), "path"), (lambda: rg.write_table(da, 3), "path"),
                      (lambda: rg.design_study("portable", 3, "R3", cells=[(12, 0)], backend="quadrature",
                                               accuracy="fast", workers=0), "vary"),
                      (lambda: rg.design_study("portable", [3], "R3", cells=[(12, 0)], backend="quadrature",
                                               accuracy="fast", workers=0), "vary"),
                      (lambda: rg.second_aperture("portable", ["detector.field_half_angle_deg=0.05"], sample=3),
                       "sample")):
        with pytest.raises(InputError) as err:
            call()
        assert err.value.field == fld, str(err.value)
    res = rg.second_aperture("portable", ["detector.field_half_angle_deg=0.05"], sample=da, rays=64, min_signal=0.05)
    assert res.best is not None


def test_the_measured_table_given_as_its_own_u_is_refused(tmp_path):
    """(audit 21) `correct --u-measured meas.csv` with meas.csv the measured table ran with u = 100 %
    of r; road --u refuses the same mistake. An RTB (a format for r only) is refused too."""
    meas = rg.write_table(rg.read_table("R3"), tmp_path / "meas.csv")
    for u, words in ((meas, "is the table file"), (tmp_path / "u.rtb", "an RTB file holds an r-table")):
        with pytest.raises(InputError, match=words) as err:
            rg.correct(str(meas), "portable", reference="R3", alternatives="none", u_measured=str(u),
                       backend="quadrature", out=tmp_path / "c")
        assert err.value.argument == "u_measured"
    assert not (tmp_path / "c").exists()


def test_a_measured_table_given_as_a_u_of_the_joint_fit_is_refused(tmp_path):
    """(session 22) the joint route did not check its u files: either measured table, given as a u of
    one of them (in a list, one per table), or an RTB, ran with u = 100 % of r."""
    a = rg.write_table(rg.read_table("R3"), tmp_path / "a.csv")
    b = rg.write_table(rg.read_table("R3"), tmp_path / "b.csv")
    for u, words in (([str(a), "1%"], "is the table file"), (["1%", str(a)], "is the table file"),
                     (str(tmp_path / "u.rtb"), "an RTB file holds an r-table")):
        with pytest.raises(InputError, match=words) as err:
            rg.correct([str(a), str(b)], ["portable", "wide"], joint=True, u_measured=u, backend="quadrature",
                       out=tmp_path / "c")
        assert err.value.argument == "u_measured"
    assert not (tmp_path / "c").exists()


def test_compare_tables_returns_the_ratio_map():
    """(audit 22) the docstring promised the ratio cell by cell; the summary dropped it."""
    res = rg.compare_tables("R3", "R4")
    a, b = rg.read_table("R3"), rg.read_table("R4")
    assert res["ratio"].dims == ("tan_eps", "beta")
    assert float(res["ratio"].sel(tan_eps=12, beta=0)) == pytest.approx(
        float(b.sel(tan_eps=12, beta=0) / a.sel(tan_eps=12, beta=0)), rel=1e-12)
    assert int(np.isfinite(res["ratio"].values).sum()) == res["cells_compared"]


def test_a_model_or_instrument_file_given_as_a_table_is_named_for_what_it_is(tmp_path):
    """(audit 22) model.json given where a table goes was read as CSV: "missing header: expected a
    first row 'tan_eps,...', got '{'". A path that is not a path raised a TypeError."""
    (tmp_path / "model.json").write_text("{}")
    with pytest.raises(InputError, match="a JSON file .* not an r-table"):
        rg.classify_table(str(tmp_path / "model.json"))
    with pytest.raises(InputError, match="expected the path of a .csv or .rtb file") as err:
        rg.table_info("R3", to=5)
    assert err.value.field == "to"


def test_design_and_intercompare_refuse_flags_and_clusters_of_the_wrong_type(tmp_path):
    """(audit 22) design_study(fresh="no") threw the journal away, plots="no" drew the pictures,
    workers=True was one worker, and intercompare(5) / client="x" ended in tracebacks."""
    for kw, field in (({"fresh": "no"}, "fresh"), ({"plots": "no"}, "plots"), ({"progress": "x"}, "progress"),
                      ({"workers": True}, "workers"), ({"client": "x"}, "client")):
        with pytest.raises(InputError) as err:
            rg.design_study("portable", ["source.radius_m=0.005"], "R3", cells="12:0", out=tmp_path / "d", **kw)
        assert err.value.field == field
        with pytest.raises(InputError) as err:
            rg.intercompare("r3-comparison", out=tmp_path / "i", **kw)
        assert err.value.field == field
    for study in (5, None, {"study": {}}):
        with pytest.raises(InputError, match="expected a study file") as err:
            rg.intercompare(study)
        assert err.value.field == "study"
    assert not (tmp_path / "d").exists() and not (tmp_path / "i").exists()


def test_the_api_refuses_what_only_the_command_line_refused():
    """(review, session 39) alternatives with reference 'self', and max_trials or batch without adaptive,
    were refused by the command line but accepted and ignored by the API (batch even entered the run's
    fingerprint). Refused before any work, naming the argument."""
    from roadgonio import api
    with pytest.raises(InputError, match="reference SAMPLE") as err:
        api.correct("R3", "portable", reference="self", alternatives="R2", backend="quadrature", plots=False)
    assert err.value.field == "alternatives"
    # the joint fit has no reference either (session 39's review: it ran 58 s and ignored them)
    with pytest.raises(InputError, match="reference SAMPLE") as err:
        api.correct(["R3", "R2"], ["portable", "wide"], joint=True, alternatives="R4", backend="quadrature",
                    plots=False)
    assert err.value.field == "alternatives"
    for kw, field in ((dict(batch=500), "batch"), (dict(max_trials=1000), "max_trials"),
                      (dict(max_trials=1000, batch=500), "max_trials")):
        with pytest.raises(InputError, match="adaptive") as err:
            api.estimate_uncertainty("portable", "R3", "alpha_deg=0.01", trials=100, aperture=False, **kw)
        assert err.value.field == field


def test_uncertainty_of_a_housed_instrument_says_what_it_holds_fixed():
    """(user audit, session 39) correct said the housing's reflectances are taken as exact, uncertainty
    did not; and a reflectance in --sigma was an 'unknown key' without the reason. The note comes after
    the SPEC's checks (a refused SPEC is one line), before any k_A table."""
    import warnings

    from roadgonio import api
    from roadgonio.errors import ModelWarning
    from roadgonio.instrument.config import load_instrument
    from roadgonio.surface.sample import resolve_sample
    from roadgonio.uncertainty.run import run_uncertainty
    from roadgonio.uncertainty.spec import parse_sigma_spec

    class Stop(Exception):
        pass

    def factory(*a, **k):
        raise Stop
    model = resolve_sample("R3").model
    for name, said_it in (("portable_housed", True), ("portable", False)):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            with pytest.raises(Stop):
                run_uncertainty(model, load_instrument(name), parse_sigma_spec("alpha_deg=0.01"), trials=1000,
                                backend_factory=factory)
        text = [str(w.message) for w in said if issubclass(w.category, ModelWarning)]
        assert any("taken as exact" in t and "inside the housing" in t for t in text) == said_it, text
    with pytest.raises(InputError, match="no input error") as err:
        api.estimate_uncertainty("portable_housed", "R3", "alpha_deg=0.01,wall_reflectance=0.01")
    assert "wall_reflectance" in str(err.value)
