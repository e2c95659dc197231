"""The house rules of the package, read from the source (imports inside functions included):

* the rooms import only downwards, in the order of docs/architecture.md, and the module import graph
  has no circle;
* only the Mitsuba room (roadgonio.engines.mitsuba and the plugins) imports mitsuba or drjit, so
  everything else runs without them;
* the command line has one way in: its modules import roadgonio.api (and the errors), never a room,
  so no command resolves an input itself.
"""
from __future__ import annotations

import ast
from pathlib import Path



ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "roadgonio"

#: The layers, lowest first. A module may import from its own room and from rooms of a lower rank;
#: rooms of the same rank are independent of each other.
RANK = {"base": 0, "surface": 1, "instrument": 2, "engines": 3, "road": 4, "uncertainty": 4, "correction": 5,
        "design": 6, "intercomparison": 7, "api": 8, "cli": 9}
#: The modules of the base layer (everything else at the top of the package is named here too).
BASE = {"_version", "errors", "arrays", "geometry", "fileio", "provenance", "plots", "plotproc", "data", "seeds",
        "limits", "eulumdat", "progress", "_checkout", "interrupts"}
#: Modules that are entry points above the API: the package's lazy exports and ``python -m roadgonio``.
TOP = {"roadgonio": "api", "roadgonio.__main__": "cli"}


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def room(module: str) -> str:
    if module in TOP:
        return TOP[module]
    parts = module.split(".")
    if len(parts) == 1 or parts[0] != "roadgonio":
        raise AssertionError(f"not a roadgonio module: {module}")
    head = parts[1]
    if head in RANK:
        return head
    if head in BASE:
        return "base"
    raise AssertionError(f"module {module} is in no room: add it to the layers (docs/architecture.md)")


def imports(path: Path, root: Path = ROOT) -> list[tuple[int, str]]:
    """(line, module) of every import in the file, also inside functions; ``from X import Y`` of a
    submodule Y counts as an import of X.Y."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    me = module_name(path, root)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(up + ([node.module] if node.module else []))
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.append((node.lineno, sub if (root / (sub.replace(".", "/") + ".py")).exists()
                            or (root / sub.replace(".", "/") / "__init__.py").exists() else base))
    return out


def _sources(root: Path = ROOT):
    return sorted((root / "roadgonio").rglob("*.py"))


def layer_violations(root: Path = ROOT) -> list[str]:
    bad = []
    for path in _sources(root):
        me = module_name(path, root)
        mine = room(me)
        for line, mod in imports(path, root):
            if mod != "roadgonio" and not mod.startswith("roadgonio."):
                continue
            if mod == "roadgonio" and mine not in ("api", "cli"):
                bad.append(f"{me}:{line} imports the package's API (roadgonio); import the module you need")
                continue
            theirs = room(mod)
            if theirs == mine:
                continue
            if RANK[theirs] >= RANK[mine]:
                bad.append(f"{me}:{line} ({mine}) imports {mod} ({theirs})")
    return bad


def import_circle(root: Path = ROOT) -> list[str] | None:
    graph: dict[str, set[str]] = {}
    for path in _sources(root):
        me = module_name(path, root)
        graph[me] = {m for _, m in imports(path, root) if m.startswith("roadgonio.") and m != me}
    seen: dict[str, int] = {}          # 1 on the stack, 2 done
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        seen[m] = 1
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if seen.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in seen:
                found = visit(n)
                if found:
                    return found
        stack.pop()
        seen[m] = 2
        return None

    for m in sorted(graph):
        if m not in seen:
            circle = visit(m)
            if circle:
                return circle
    return None


def test_rooms_import_only_downwards():
    bad = layer_violations()
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_the_import_graph_has_no_circle():
    circle = import_circle()
    assert circle is None, "import circle: " + " -> ".join(circle)


def test_only_the_mitsuba_room_imports_mitsuba_and_drjit():
    bad = []
    for path in _sources():
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith("roadgonio/engines/mitsuba/"):
            continue
        for line, mod in imports(path):
            if mod.split(".")[0] in ("mitsuba", "drjit"):
                bad.append(f"{rel}:{line} imports {mod}")
    for path in sorted((ROOT / "plugins").rglob("*.py")):   # the plugins are that room's (installed inside it)
        for line, mod in imports(path):
            if mod.startswith("roadgonio.") and room(mod) in ("uncertainty", "correction", "design", "road", "api", "cli"):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "imports of mitsuba/drjit outside the Mitsuba room:\n" + "\n".join(bad)


def test_the_command_line_calls_the_api_and_nothing_else():
    # errors and interrupts: how a command ends (its one-line errors, its Ctrl-C / SIGTERM), no input resolved
    allowed = ("roadgonio.api", "roadgonio.errors", "roadgonio.interrupts", "roadgonio._version", "roadgonio.cli")
    bad = []
    for path in sorted((PKG / "cli").glob("*.py")):
        for line, mod in imports(path):
            if mod.startswith("roadgonio") and not (mod in allowed or mod.startswith("roadgonio.cli.")):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "the command line resolves inputs through roadgonio.api only:\n" + "\n".join(bad)


#: Test oracles: float64 checks written apart from the code they check; production code never imports them.
ORACLES = {"roadgonio.engines.strayref"}
#: Packages whose docstring needs no module list: the commands are found by themselves; data is data.
UNLISTED = {"roadgonio.cli", "roadgonio.data"}


def oracle_imports(root: Path = ROOT) -> list[str]:
    return [f"{module_name(p, root)}:{line} imports {mod}" for p in _sources(root) for line, mod in imports(p, root)
            if mod in ORACLES and module_name(p, root) not in ORACLES]


def room_list_mismatches(root: Path = ROOT) -> list[str]:
    """Each room package's docstring lists its modules: every ``:mod:`` reference names an existing
    module, and every module (and subpackage) of the room is named (``:mod:`.name``` or the full name)."""
    import re
    bad = []
    for init in sorted((root / "roadgonio").rglob("__init__.py")):
        pkg_dir = init.parent
        pkg = module_name(init, root)
        if pkg == "roadgonio" or pkg in UNLISTED or any(pkg.startswith(u + ".") for u in UNLISTED):
            continue
        doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"))) or ""
        named = set()
        for ref in re.findall(r":mod:`~?([\w.]+)`", doc):
            full = pkg + ref if ref.startswith(".") else ref
            path = root / full.replace(".", "/")
            if not (path.with_suffix(".py").exists() or (path / "__init__.py").exists()):
                bad.append(f"{pkg}: its docstring names {ref}, which does not exist")
            named.add(full)
        members = sorted({p.stem for p in pkg_dir.glob("*.py") if p.stem != "__init__"}
                         | {d.name for d in pkg_dir.iterdir() if (d / "__init__.py").exists()})
        bad += [f"{pkg}: its docstring does not name its module {m}" for m in members if f"{pkg}.{m}" not in named]
    return bad


def test_production_code_does_not_import_a_test_oracle():
    bad = oracle_imports()
    assert not bad, "test oracles imported by production code:\n" + "\n".join(bad)


def test_room_docstrings_list_their_modules():
    bad = room_list_mismatches()
    assert not bad, "room docstrings out of date:\n" + "\n".join(bad)


def test_the_rules_can_fail(tmp_path):
    """On a small tree: an upward import inside a function, a relative upward import, a lateral
    import between rooms of the same rank and a circle are all found."""
    pkg = tmp_path / "roadgonio"
    for sub in ("surface", "engines", "road", "uncertainty"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "api.py").write_text("")
    (pkg / "surface" / "a.py").write_text("def f():\n    from roadgonio.engines import b\n    from ..api import x\n")
    (pkg / "engines" / "b.py").write_text("from roadgonio.surface import a\n")
    (pkg / "road" / "c.py").write_text("import roadgonio.uncertainty\n")
    bad = layer_violations(tmp_path)
    assert any("surface.a:2" in b and "engines.b" in b for b in bad)
    assert any("surface.a:3" in b and "roadgonio.api" in b for b in bad)
    assert any("road.c" in b and "uncertainty" in b for b in bad)
    assert import_circle(tmp_path) is not None


def test_the_list_and_oracle_rules_can_fail(tmp_path):
    """On a small tree: a docstring naming a module that does not exist, a module the docstring does
    not name, and an import of a test oracle are all found; a complete list passes."""
    pkg = tmp_path / "roadgonio"
    (pkg / "engines").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "engines" / "__init__.py").write_text('"""Room.\n\n* :mod:`.a` -- a;\n* :mod:`.forward` -- gone.\n"""\n')
    (pkg / "engines" / "a.py").write_text("from roadgonio.engines import strayref\n")
    (pkg / "engines" / "b.py").write_text("")
    (pkg / "engines" / "strayref.py").write_text("")
    bad = room_list_mismatches(tmp_path)
    assert any("forward" in b and "does not exist" in b for b in bad)
    assert any("module b" in b for b in bad) and any("module strayref" in b for b in bad)
    assert not any("module a" in b for b in bad)
    assert oracle_imports(tmp_path) == ["roadgonio.engines.a:1 imports roadgonio.engines.strayref"]
