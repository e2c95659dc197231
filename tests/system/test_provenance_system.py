"""Provenance seen from outside: a fresh interpreter's imports, the commands' output files."""
from __future__ import annotations

import json
import subprocess
import sys

from helpers import VERSION_KEYS


def test_versions_do_not_import_mitsuba_or_drjit():
    code = ("import sys\nfrom roadgonio.provenance import versions\nv = versions()\n"
            "print(v['mitsuba'] is not None, v['drjit'] is not None, 'mitsuba' in sys.modules, 'drjit' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["True", "True", "False", "False"]


def test_road_and_compare_outputs_carry_the_versions(tmp_path):
    from roadgonio.cli import main
    assert main(["road", "--table", "R3", "--out", str(tmp_path / "road"), "--no-plots", "--quiet"]) == 0
    road = json.loads((tmp_path / "road" / "road.json").read_text())
    assert VERSION_KEYS <= set(road["provenance"]["versions"]) and "lanes" in road["provenance"]["settings"]["layout"]
    assert main(["compare", "R3", "R2", "--out", str(tmp_path / "cmp"), "--no-plots", "--quiet"]) == 0
    assert VERSION_KEYS <= set(json.loads((tmp_path / "cmp" / "compare.json").read_text())["provenance"]["versions"])
