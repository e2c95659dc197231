"""The subpackages whose source lies outside ``roadgonio/``, taken from the checkout roadgonio
itself was imported from.

pyproject.toml's ``[tool.setuptools] package-dir`` installs four top-level folders inside the
package: ``plugins/`` as ``roadgonio.engines.mitsuba.plugins``, ``scenes/`` as ``roadgonio.scenes``,
``docs/`` as ``roadgonio.docs`` and ``studies/`` as ``roadgonio.studies``. A wheel has them in
place, and an editable install maps them to the folders of the checkout it was installed from.
With a second checkout on ``PYTHONPATH`` (a git worktree), ``roadgonio`` comes from that checkout
but the editable install's mapping still points at the first one: the worktree's tests would run
the other checkout's plugins and read its presets.

:func:`bind` loads such a subpackage from the folder that the pyproject.toml *next to this
package* maps it to, when there is one (roadgonio was imported from a source checkout); otherwise
(an installed wheel, no pyproject.toml beside the package) it does nothing and the import system's
own mapping applies. It imports only the standard library and the subpackage's ``__init__.py``.
"""
from __future__ import annotations

import functools
import importlib.util
import sys
from pathlib import Path

_PACKAGE_DIR = Path(__file__).resolve().parent


@functools.cache
def mapped_folders() -> dict[str, Path]:
    """``{subpackage name: folder}`` of pyproject.toml's package-dir for the subpackages outside
    ``roadgonio/``, read from the checkout this package lies in; empty when this package does not
    lie in a roadgonio source checkout (its pyproject.toml must name the project roadgonio and map
    ``roadgonio`` to this very folder)."""
    import tomllib
    root = _PACKAGE_DIR.parent
    try:
        with open(root / "pyproject.toml", "rb") as f:
            meta = tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError):
        return {}
    if meta.get("project", {}).get("name") != "roadgonio":
        return {}
    dirs = meta.get("tool", {}).get("setuptools", {}).get("package-dir", {})
    if not isinstance(dirs, dict) or (root / str(dirs.get("roadgonio", "roadgonio"))).resolve() != _PACKAGE_DIR:
        return {}
    return {name: (root / str(folder)).resolve() for name, folder in dirs.items()
            if name.startswith("roadgonio.") and (root / str(folder) / "__init__.py").is_file()}


def bind(name: str) -> None:
    """Import the subpackage ``name`` from this checkout's folder for it (:func:`mapped_folders`)
    and set it as its parent's attribute; nothing when it is already imported or when roadgonio
    was not imported from a source checkout. The parent package must be imported (call this from
    the parent's ``__init__``)."""
    folder = mapped_folders().get(name)
    if folder is None or name in sys.modules:
        return
    spec = importlib.util.spec_from_file_location(name, folder / "__init__.py",
                                                  submodule_search_locations=[str(folder)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    parent, _, child = name.rpartition(".")
    setattr(sys.modules[parent], child, module)
