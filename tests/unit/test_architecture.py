"""The rooms of the package import only downwards: Mitsuba (mitsuba, drjit and
roadgonio.engines.mitsuba) is imported only by its own room, the plugins and the entry points
(the command line and the Python API), so everything else runs without it."""
from __future__ import annotations

import ast
from pathlib import Path



ROOT = Path(__file__).resolve().parents[2]
MITSUBA_MODULES = ("mitsuba", "drjit", "roadgonio.engines.mitsuba")
#: Who may import them: the Mitsuba room itself and the entry points that choose the variant.
ALLOWED = ("roadgonio/engines/mitsuba/", "plugins/", "roadgonio/cli/", "roadgonio/api.py")


def _imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.lineno, node.module))
    return out


def test_only_the_mitsuba_room_and_the_entry_points_import_mitsuba():
    bad = []
    for path in sorted((ROOT / "roadgonio").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith(ALLOWED):
            continue
        for line, mod in _imports(path):
            if any(mod == m or mod.startswith(m + ".") for m in MITSUBA_MODULES):
                bad.append(f"{rel}:{line} imports {mod}")
    assert not bad, "upward imports of the Mitsuba room:\n" + "\n".join(bad)
