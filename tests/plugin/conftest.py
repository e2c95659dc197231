"""The plugin tier: every test here builds Mitsuba scenes, so each gets the variant of the ``mi``
fixture (tests/conftest.py), which skips the test, saying why, without a usable LLVM >= 16."""
from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _mitsuba_variant(mi):
    """The Mitsuba variant for every plugin test (or the skip, with its reason)."""
    return mi
