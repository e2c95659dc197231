"""The lint: ruff, with the small rule set of [tool.ruff.lint] in pyproject.toml (each group is
explained there), finds nothing in the package, the tests, the benchmarks and the plugins."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = ("roadgonio", "tests", "bench", "plugins")


def test_ruff_finds_nothing():
    if importlib.util.find_spec("ruff") is None:
        pytest.fail("ruff is not installed: pip install -e '.[test]' (the test extra has it)")
    r = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", *FOLDERS],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"ruff check {' '.join(FOLDERS)}:\n{r.stdout}{r.stderr}"
