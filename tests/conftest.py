"""Shared fixtures, and the tiers of the tests.

A test's tier is the folder it sits in, and is marked here from that folder (never by a decorator):

* ``tests/unit`` -- marked ``unit``: numpy only, in this process, fast (and the lint, which runs
  ruff); it never imports mitsuba or drjit (tests/unit/conftest.py makes them unimportable while a
  unit test runs);
* ``tests/plugin`` -- marked ``plugin``: Mitsuba and Dr.Jit in this process; every test gets the
  Mitsuba variant of the ``mi`` fixture, and the tier is skipped, saying why, without LLVM >= 16;
* ``tests/system`` -- marked ``system``: the command line, subprocesses, Dask clusters, end-to-end
  runs; a system test that needs Mitsuba asks for the ``mi`` fixture (so it is skipped with it).

Long runs are also marked ``slow`` (a decorator: slowness is not a tier) and left out of the
default run; ``pytest -m slow`` runs them. Tolerances are in tests/tolerances.py, helpers shared by
files of different tiers in tests/helpers.py.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from helpers import R3LIKE

TIERS = ("unit", "plugin", "system")
_HERE = Path(__file__).resolve().parent


def pytest_sessionstart(session):
    """Fail at once, saying how to fix it, when the tests would run code of another checkout:
    roadgonio imported from elsewhere than this checkout (a git worktree without
    ``PYTHONPATH=<worktree>``), or a subpackage installed from a top-level folder (plugins/, scenes/,
    docs/, studies/: pyproject.toml's package-dir) imported from another checkout than roadgonio
    itself (an editable install's mapping; roadgonio._checkout binds them to roadgonio's own)."""
    import importlib

    import roadgonio
    checkout = _HERE.parent
    root = Path(roadgonio.__file__).resolve().parents[1]
    if (checkout / "pyproject.toml").is_file() and root != checkout:
        raise pytest.UsageError(f"these tests are in {checkout} but roadgonio is imported from {root}: "
                                f"run them with PYTHONPATH={checkout}")
    for name in ("roadgonio.engines.mitsuba.plugins", "roadgonio.scenes", "roadgonio.docs", "roadgonio.studies"):
        where = Path(importlib.import_module(name).__file__).resolve()
        if not where.is_relative_to(root):
            raise pytest.UsageError(f"{name} is imported from {where.parent}, not from roadgonio's checkout {root} "
                                    "(an editable install of another checkout?); roadgonio/_checkout.py binds it "
                                    "to roadgonio's own folder when pyproject.toml maps it there")


def pytest_collection_modifyitems(config, items):
    """Mark each test with its folder's tier and run the tiers in the order unit, plugin, system
    (the fast ones first). A test outside the tier folders is an error."""
    order = {}
    for item in items:
        try:
            tier = Path(item.path).resolve().relative_to(_HERE).parts[0]
        except ValueError:          # not under tests/ (e.g. a path given on the command line)
            continue
        if tier not in TIERS:
            raise pytest.UsageError(f"{item.nodeid}: tests live in tests/unit, tests/plugin or tests/system "
                                    "(see tests/conftest.py)")
        item.add_marker(getattr(pytest.mark, tier))
        order[item.nodeid] = TIERS.index(tier)
    items.sort(key=lambda it: order.get(it.nodeid, len(TIERS)))     # stable: file order kept within a tier



@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the CPU variant chosen here (never as an import side effect: scene and backend
    constructors only check the variant, :func:`roadgonio.engines.mitsuba.require_variant`).

    Skips the test, with the reason, where the variant cannot be used: no mitsuba/drjit, or Dr.Jit's
    LLVM older than 16 (:func:`roadgonio.engines.mitsuba.set_variant` checks it before any kernel
    runs; LLVM 15 would abort the process at the first kernel)."""
    from roadgonio.engines.mitsuba import set_variant
    from roadgonio.errors import BackendError
    try:
        return set_variant("llvm_ad_rgb")
    except BackendError as err:
        pytest.skip(f"Mitsuba's CPU variant is not usable here: {err}")


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
    lines = bundled_table("R3").to_csv_text().splitlines()  # '# ...' comment lines, the header, data
    h = next(k for k, ln in enumerate(lines) if ln.startswith("tan_eps"))  # the header's index
    no_header = "\n".join(lines[:h] + lines[h + 1:])
    non_numeric = list(lines)
    cells = non_numeric[h + 5].split(",")
    cells[3] = "abc"
    non_numeric[h + 5] = ",".join(cells)
    wrong_grid = list(lines)
    wrong_grid[h] = wrong_grid[h].replace(",45,", ",50,")
    negative = list(lines)
    cells = negative[h + 9].split(",")
    cells[5] = "-12"
    negative[h + 9] = ",".join(cells)
    rtb = bundled_table("R3").to_rtb_text().splitlines()
    rtb_neg = list(rtb)
    rtb_neg[54] = "-5"  # line 55: the first r value (DIALux layout, one value per line)
    return [
        ("missing header", ".csv", no_header, h + 1, ["header", "tan_eps"]),
        ("non-numeric cell", ".csv", "\n".join(non_numeric), h + 6, ["expected a number", "abc"]),
        ("wrong grid", ".csv", "\n".join(wrong_grid), h + 1, ["standard grid"]),
        ("negative value", ".csv", "\n".join(negative), h + 10, ["must not be negative", "-12"]),
        ("empty file", ".csv", "", None, ["empty"]),
        ("comments only", ".csv", "# nothing\n", None, ["empty"]),
        ("semicolons", ".csv", "\n".join(ln.replace(",", ";") for ln in lines), h + 1, ["separator", "comma",
                                                                                       "semicolons"]),
        ("rtb missing header", ".rtb", "\n".join(rtb[1:]), 1, ["RTable.v1"]),
        ("rtb negative", ".rtb", "\n".join(rtb_neg), 55, ["must not be negative", "0 is a blank in RTB"]),
        ("rtb empty", ".rtb", "", None, ["empty"]),
    ]


_BAD_IDS = ["missing header", "non-numeric cell", "wrong grid", "negative value", "empty file", "comments only",
            "semicolons", "rtb missing header", "rtb negative", "rtb empty"]


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
