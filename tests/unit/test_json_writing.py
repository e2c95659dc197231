"""The one JSON writer (roadgonio.fileio.to_json): strict JSON, a non-finite number written as null,
everywhere (files, netCDF attributes, --json on stdout)."""
from __future__ import annotations

import ast
import json
import math
from pathlib import Path

import numpy as np

from roadgonio.fileio import to_json

PACKAGE = Path(__file__).resolve().parents[2] / "roadgonio"
#: The only json.dump(s) calls allowed outside the writer itself: (file, function, why).
ALLOWED = {("design/outputs.py", "_toml_value")}     # quoting a TOML basic string, not writing JSON


def strict(text: str):
    """Parse as strict JSON: NaN and Infinity are not JSON."""
    def refuse(name):
        raise ValueError(f"{name} is not JSON")
    return json.loads(text, parse_constant=refuse)


def test_non_finite_numbers_are_null_and_numpy_values_numbers():
    doc = {"a": math.nan, "b": [1.0, math.inf, -math.inf], "c": np.float64(np.nan), "d": np.array([1.5, np.nan]),
           "e": np.int64(3), "f": {"g": (np.float32(0.5), None)}, 4: True, "p": Path("x/y")}
    for indent in (None, 2):
        back = strict(to_json(doc, indent=indent))
        assert back == {"a": None, "b": [1.0, None, None], "c": None, "d": [1.5, None], "e": 3,
                        "f": {"g": [0.5, None]}, "4": True, "p": "x/y"}


def test_no_other_json_writer_in_the_package():
    """Every JSON text roadgonio writes goes through fileio.to_json: no json.dump/json.dumps call
    elsewhere (outside the allowed TOML quoting)."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel == "fileio.py":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        funcs = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        for node in ast.walk(tree):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr in ("dump", "dumps") and isinstance(node.func.value, ast.Name)
                    and node.func.value.id == "json"):
                owner = next((f.name for f in funcs if f.lineno <= node.lineno <= (f.end_lineno or f.lineno)), "")
                if (rel, owner) not in ALLOWED:
                    found.append(f"{rel}:{node.lineno} ({owner})")
    assert not found, found
