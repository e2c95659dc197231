"""Shared fixtures. Tests are tiered by markers: unit (numpy), plugin (Mitsuba), system (CLI);
slow ones are also marked ``slow`` and left out of the default run (``pytest -m slow``)."""
from __future__ import annotations

import pytest


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
