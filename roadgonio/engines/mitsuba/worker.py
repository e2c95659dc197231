"""Mitsuba in a worker process (Dask worker or any process that computes tables for a driver).

A worker process is an entry point of its own: Mitsuba variants and the Python plugins are process
(and, in some builds, thread) state, so each worker chooses the variant, registers the roadgonio
plugins and sizes Dr.Jit's thread pool itself (:func:`prepare_process`). In the driver's own
process nothing is changed: :func:`check_process` only checks what its entry point chose.
Used by :mod:`roadgonio.engines.cluster` through its lazy ``PROCESS_SETUP`` table, like the backends.
"""
from __future__ import annotations

import os
from typing import Any

from roadgonio.engines.mitsuba import require_variant, set_variant


def prepare_process(variant: str | None = None, render_threads: int | None = None) -> dict[str, Any]:
    """In a worker: select ``variant`` (default: ``$ROADGONIO_VARIANT`` or llvm_ad_rgb) unless it
    (or, with ``variant=None``, any variant) is already selected, register the plugins, and with
    ``render_threads`` set Dr.Jit's thread pool size. Idempotent; returns what is set."""
    import mitsuba as mi

    from roadgonio.engines.mitsuba.plugins import register_plugins
    current = mi.variant()
    if current is None or (variant is not None and variant != current):
        set_variant(variant)
    else:
        require_variant(variant)
    register_plugins()
    info: dict[str, Any] = {"variant": mi.variant(), "pid": os.getpid()}
    if render_threads:
        import drjit as dr
        dr.set_thread_count(int(render_threads))
        info["render_threads"] = int(render_threads)
    return info


def check_process(variant: str | None = None) -> None:
    """In the driver's process: the variant its entry point chose must be usable (BackendError
    saying what to call otherwise); nothing is changed."""
    require_variant(variant)
