"""The Python API (roadgonio.api) seen from a fresh interpreter: what `import roadgonio` loads."""
from __future__ import annotations

import subprocess
import sys

import roadgonio as rg


def test_import_is_light_and_the_api_is_exported():
    """`import roadgonio` imports neither mitsuba nor drjit (nor numpy/xarray); __all__ resolves."""
    code = ("import sys, roadgonio as rg\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('mitsuba', 'drjit', 'numpy', 'xarray')))\n"
            "print(all(callable(getattr(rg, n)) for n in rg.__all__ if n not in ('__version__', 'AUTO')))\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('mitsuba', 'drjit')))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["[]", "True", "[]"]
    assert {"ka_table", "ka_cell", "read_table", "write_table", "fit", "correct", "estimate_uncertainty",
            "design_study"} <= set(rg.__all__)
