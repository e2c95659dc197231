"""The unit tier: numpy only. mitsuba and drjit are unimportable while a unit test runs (and while
a unit test file is imported), so a unit test that reaches them, even through roadgonio code that
imports them inside a function, fails instead of silently needing them."""
from __future__ import annotations

import sys

import pytest

_BLOCKED = ("mitsuba", "drjit")


class _Blocked:
    """``import mitsuba`` / ``import drjit`` raise ImportError inside the block (a ``None`` in
    sys.modules makes the import system raise), and their submodules already imported (by a plugin
    test earlier in this process: under pytest-xdist the tiers mix in a worker) are out of
    sys.modules too: a lazy submodule's attribute access imports its parent, which hypothesis does
    when it scans sys.modules for constants. What was imported before is put back after."""

    def __enter__(self):
        prefixes = tuple(f"{name}." for name in _BLOCKED)
        self.saved = {name: mod for name, mod in list(sys.modules.items())
                      if name in _BLOCKED or name.startswith(prefixes)}
        for name in self.saved:
            del sys.modules[name]
        for name in _BLOCKED:
            sys.modules[name] = None
        return self

    def __exit__(self, *exc):
        for name in _BLOCKED:
            if sys.modules.get(name, 0) is None:
                del sys.modules[name]
        sys.modules.update(self.saved)
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
