"""Shared fixtures. Tests are tiered by markers: unit (numpy), plugin (Mitsuba), system (CLI);
slow ones are also marked ``slow`` and left out of the default run (``pytest -m slow``)."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the CPU variant chosen here (never as an import side effect)."""
    from roadgonio.engines.mitsuba import set_variant
    return set_variant("llvm_ad_rgb")


@pytest.fixture(scope="session")
def rng_seed():
    return 20261122
