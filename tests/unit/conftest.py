"""The unit tier: numpy only. mitsuba and drjit are unimportable while a unit test runs (and while
a unit test file is imported), so a unit test that reaches them, even through roadgonio code that
imports them inside a function, fails instead of silently needing them."""
from __future__ import annotations

import sys

import pytest

_BLOCKED = ("mitsuba", "drjit")


class _Blocked:
    """``import mitsuba`` / ``import drjit`` raise ImportError inside the block (a ``None`` in
    sys.modules makes the import system raise); what was imported before is put back after."""

    def __enter__(self):
        self.saved = {name: sys.modules.get(name) for name in _BLOCKED}
        for name in _BLOCKED:
            sys.modules[name] = None
        return self

    def __exit__(self, *exc):
        for name, module in self.saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module
        return False


@pytest.hookimpl(wrapper=True)
def pytest_make_collect_report(collector):
    """Collecting a unit test file (importing it) happens with mitsuba and drjit blocked."""
    with _Blocked():
        return (yield)


@pytest.fixture(autouse=True)
def _no_mitsuba():
    """mitsuba and drjit cannot be imported during a unit test."""
    with _Blocked():
        yield
