"""Shared fixtures. Tests are tiered by markers: unit (numpy), plugin (Mitsuba), system (CLI);
slow ones are also marked ``slow`` and left out of the default run (``pytest -m slow``)."""
from __future__ import annotations

import pytest

#: Parameters of a model close to the fit of CIE R3 (paper's power reading), shared by the tests.
R3LIKE = dict(k_diff=0.028937, k_phong=1.8147, n_phong=34.467, k_retro=0.052577, n_retro=11.307,
              k_exp=0.088927, p=2.137, h=0.49843, mu=0.03123)


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the CPU variant chosen here (never as an import side effect: scene and backend
    constructors only check the variant, :func:`roadgonio.engines.mitsuba.require_variant`)."""
    from roadgonio.engines.mitsuba import set_variant
    return set_variant("llvm_ad_rgb")


@pytest.fixture(autouse=True)
def _mitsuba_variant_for_plugin_tests(request):
    """Tests marked ``plugin`` build Mitsuba scenes: they get the variant of the ``mi`` fixture."""
    if request.node.get_closest_marker("plugin") is not None:
        request.getfixturevalue("mi")


@pytest.fixture(scope="session")
def rng_seed():
    return 20261122


@pytest.fixture(scope="session")
def r3like_params() -> dict:
    """The R3-like model parameters (a fresh copy)."""
    return dict(R3LIKE)


@pytest.fixture(scope="session")
def r3like():
    """A RoadModel close to the fit of CIE R3 (no fit needed)."""
    from roadgonio.surface.model import RoadModel, RoadParams
    return RoadModel(RoadParams(**R3LIKE), name="R3-like")


@pytest.fixture(scope="session")
def lab():
    """``lab(**changes)``: the lab preset, with some keys changed (``lab(source={"radius_m": 0})``)."""
    from roadgonio.instrument.config import load_instrument
    inst = load_instrument("lab")

    def make(**changes):
        return inst.with_changes(**changes) if changes else inst
    return make


def _bad_table_cases():
    """(label, suffix, text, expected line or None, words the message must contain): broken
    r-table files, each made from the bundled R3."""
    from roadgonio.surface.rtable import bundled_table
    lines = bundled_table("R3").to_csv_text().splitlines()  # line 1: '# ...', line 2: header, line 3.. data
    no_header = "\n".join(lines[:1] + lines[2:])
    non_numeric = list(lines)
    cells = non_numeric[6].split(",")
    cells[3] = "abc"
    non_numeric[6] = ",".join(cells)
    wrong_grid = list(lines)
    wrong_grid[1] = wrong_grid[1].replace(",45,", ",50,")
    negative = list(lines)
    cells = negative[10].split(",")
    cells[5] = "-12"
    negative[10] = ",".join(cells)
    rtb = bundled_table("R3").to_rtb_text().splitlines()
    rtb_neg = list(rtb)
    rtb_neg[54] = "-5"  # line 55: the first r value (DIALux layout, one value per line)
    return [
        ("missing header", ".csv", no_header, 2, ["header", "tan_eps"]),
        ("non-numeric cell", ".csv", "\n".join(non_numeric), 7, ["expected a number", "abc"]),
        ("wrong grid", ".csv", "\n".join(wrong_grid), 2, ["standard grid"]),
        ("negative value", ".csv", "\n".join(negative), 11, [">= 0", "-12"]),
        ("empty file", ".csv", "", None, ["empty"]),
        ("comments only", ".csv", "# nothing\n", None, ["empty"]),
        ("rtb missing header", ".rtb", "\n".join(rtb[1:]), 1, ["RTable.v1"]),
        ("rtb negative", ".rtb", "\n".join(rtb_neg), 55, [">= 0"]),
        ("rtb empty", ".rtb", "", None, ["empty"]),
    ]


_BAD_IDS = ["missing header", "non-numeric cell", "wrong grid", "negative value", "empty file", "comments only",
            "rtb missing header", "rtb negative", "rtb empty"]


@pytest.fixture(params=range(len(_BAD_IDS)), ids=_BAD_IDS)
def bad_table(request):
    """One broken r-table file case of :func:`_bad_table_cases` (parametrized over all of them)."""
    case = _bad_table_cases()[request.param]
    assert case[0] == _BAD_IDS[request.param]
    return case


@pytest.fixture
def bad_tables():
    """All broken r-table file cases, as a list."""
    return _bad_table_cases()
