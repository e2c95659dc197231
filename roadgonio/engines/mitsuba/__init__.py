"""The Mitsuba 3 side of roadgonio: the only subpackage that imports mitsuba and drjit.

* :mod:`.scene` -- the goniophotometer as a Mitsuba scene (source, sample mesh, luminance meter);
* :mod:`.backend` -- the k_A backend ``mitsuba``;
* :mod:`.engine` -- the batched engine: all cells of a table in a few launches of the ``kabatch``
  integrator;
* :mod:`.passes` -- its passes and float64 statistics (the ratio estimator, its SE and covariance);
* :mod:`.lattice` -- its sample points: randomly shifted rank-1 lattices;
* :mod:`.worker` -- Mitsuba in a worker process (Dask);
* :mod:`.images` -- pictures of one cell (``roadgonio render``);
* :mod:`.ops` -- the Dr.Jit array namespace of the shared formulas;
* ``plugins`` (the top-level ``plugins/`` folder) -- the ``roadbsdf`` BSDF and ``lummeter`` sensor.

Nothing here runs at import time of :mod:`roadgonio`. The variant is process state, so it is
chosen once by the entry point (the ``roadgonio`` command, :func:`roadgonio.ka_table`, a bench
script, the tests' ``mi`` fixture) with :func:`set_variant`, which checks Dr.Jit's LLVM backend
right after choosing the variant and before any kernel runs: with LLVM < 16 the first kernel
would abort the whole process (LLVM 15: "Cannot select ... fminimum"), so we fail with a clear
message instead. Everything else (scene building, backends) only *checks* the chosen variant with
:func:`require_variant` and never changes it or the environment.
"""
from __future__ import annotations

import glob
import os
import re

from roadgonio._checkout import bind as _bind
from roadgonio.errors import BackendError, InputError

# the plugins of this checkout (plugins/), not of the one an editable install points at (roadgonio._checkout);
# this imports plugins/__init__.py only, never mitsuba
_bind(f"{__name__}.plugins")

#: Default variant on a CPU machine; a CUDA variant is chosen when asked for and available.
DEFAULT_VARIANT = "llvm_ad_rgb"
#: The variants roadgonio runs on: the JIT RGB variants. The plugins carry f_road and 1/pi in two
#: colour channels (a mono or spectral variant has not the same channels), and trace their
#: Python code into kernels (a scalar variant runs it per ray, about 300x slower, and fails on
#: the vector code).
SUPPORTED_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")


def check_variant_name(variant, field: str = "mitsuba_variant") -> str:
    """``variant`` if roadgonio supports it (:data:`SUPPORTED_VARIANTS`), else the one-line
    :class:`InputError` naming ``field``; imports nothing."""
    if not isinstance(variant, str) or variant not in SUPPORTED_VARIANTS:
        why = (" (a scalar variant runs the plugins per ray and is not supported)"
               if isinstance(variant, str) and variant.startswith("scalar") else "")
        raise InputError(f"Mitsuba variant {variant!r} is not one roadgonio runs on{why}; expected "
                         f"{' or '.join(SUPPORTED_VARIANTS)} (default {DEFAULT_VARIANT})", field=field)
    return variant
MIN_LLVM = (16,)
_INSTALL_HINT = ("install a newer libLLVM (Debian/Ubuntu: 'apt-get install -y libllvm19') or point "
                 "DRJIT_LIBLLVM_PATH at a libLLVM.so of version 16 or newer")


def _newest_system_llvm() -> str | None:
    """Path of the newest libLLVM >= 16 in the usual system folders, or None."""
    best = None
    for pattern in ("/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
                    "/usr/lib64/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*"):
        for p in glob.glob(pattern):
            m = re.search(r"libLLVM[-.]?(\d+)", os.path.basename(p))
            if m and int(m.group(1)) >= MIN_LLVM[0]:
                v = int(m.group(1))
                if best is None or v > best[0]:
                    best = (v, p)
    return None if best is None else best[1]


def set_variant(variant: str | None = None):
    """Select a Mitsuba variant for this process and check the backend; returns ``mitsuba``.

    The variant is ``variant``, else ``$ROADGONIO_VARIANT``, else ``llvm_ad_rgb``. This is the one
    function of roadgonio that changes process state, and only entry points call it (the CLI, the
    Python API, bench scripts, test fixtures). Before the first LLVM variant it may point
    ``DRJIT_LIBLLVM_PATH`` at a libLLVM >= 16 outside the folders Dr.Jit searches itself (conda,
    /usr/lib64, llvm-*/lib): Dr.Jit reads it only then.

    Raises :class:`~roadgonio.errors.InputError` for a variant roadgonio does not run on
    (:data:`SUPPORTED_VARIANTS`), before anything changes, and
    :class:`~roadgonio.errors.BackendError` with an install hint when mitsuba is missing, the
    variant does not exist in this build, or Dr.Jit's LLVM backend is older than 16.
    """
    if variant:
        check_variant_name(variant)
    else:
        variant = check_variant_name(os.environ.get("ROADGONIO_VARIANT", DEFAULT_VARIANT), "ROADGONIO_VARIANT")
    if variant.startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in os.environ:
        # drjit picks the newest system libLLVM by itself; help it where the library lives elsewhere
        path = _newest_system_llvm()
        if path is not None and not path.startswith(("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu")):
            os.environ["DRJIT_LIBLLVM_PATH"] = path
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as err:  # pragma: no cover - depends on the install
        raise BackendError(f"the Mitsuba backend needs the packages mitsuba and drjit ({err}); "
                           "run 'pip install mitsuba drjit'") from None
    if variant not in mi.variants():
        raise BackendError(f"Mitsuba variant {variant!r} is not available; this build has "
                           f"{', '.join(mi.variants())}")
    try:
        mi.set_variant(variant)
    except (ImportError, RuntimeError) as err:
        if variant.startswith("cuda"):
            # not an LLVM problem: no usable NVIDIA GPU / CUDA driver here
            raise BackendError(f"cannot use Mitsuba variant {variant!r}: it needs an NVIDIA GPU with a working CUDA "
                               f"driver, and none was found ({str(err).strip().rstrip('.')}); use the CPU variant "
                               "llvm_ad_rgb (--variant llvm_ad_rgb, the default)") from None
        raise BackendError(f"cannot use Mitsuba variant {variant!r}: {err}. {_INSTALL_HINT}") from None
    if variant.startswith("llvm"):
        check_llvm_version(tuple(dr.detail.llvm_version()))
    return mi


def choose_variant(variant: str | None = None):
    """The entry point's choice (the ``roadgonio`` command, the Python API): keep the variant already
    selected in this process when none or the same is asked for (a notebook that chose one keeps
    it), else :func:`set_variant`. Returns ``mitsuba``."""
    import sys
    mi = sys.modules.get("mitsuba")
    current = mi.variant() if mi is not None else None
    if current is not None and variant in (None, current):
        return require_variant(current)
    return set_variant(variant)


def require_variant(variant: str | None = None):
    """``mitsuba`` with a variant already chosen by the entry point (:func:`set_variant`); if
    ``variant`` is given it must be the chosen one. Changes nothing: a scene or backend built
    in the middle of a program must not switch the variant under the code around it.

    Raises :class:`~roadgonio.errors.BackendError` saying what to call when no variant (or
    another one) is selected, or when the LLVM backend is older than 16.
    """
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as err:  # pragma: no cover - depends on the install
        raise BackendError(f"the Mitsuba backend needs the packages mitsuba and drjit ({err}); "
                           "run 'pip install mitsuba drjit'") from None
    current = mi.variant()
    if current is None:
        raise BackendError("no Mitsuba variant is selected: call roadgonio.engines.mitsuba.set_variant() "
                           f"(e.g. set_variant({variant or DEFAULT_VARIANT!r})) first; the roadgonio command and "
                           "roadgonio.ka_table do this for you")
    if variant is not None and variant != current:
        raise BackendError(f"the Mitsuba variant {current!r} is selected but {variant!r} was asked for: call "
                           f"roadgonio.engines.mitsuba.set_variant({variant!r}) first")
    if current.startswith("llvm"):
        check_llvm_version(tuple(dr.detail.llvm_version()))
    return mi


def check_llvm_version(version: tuple[int, ...]) -> None:
    """Raise :class:`BackendError` (with an install hint) if Dr.Jit's LLVM is older than 16."""
    if tuple(version) < MIN_LLVM:
        raise BackendError(f"Dr.Jit found LLVM {'.'.join(map(str, version))}, but roadgonio needs "
                           f"LLVM >= 16 (older versions abort on the first kernel): {_INSTALL_HINT}")


def llvm_version() -> tuple[int, ...] | None:
    """LLVM version Dr.Jit uses (after :func:`set_variant` with an llvm variant), else None."""
    import drjit as dr
    try:
        return tuple(dr.detail.llvm_version())
    except Exception:  # pragma: no cover
        return None
