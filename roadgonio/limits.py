"""Limits on sizes that would exhaust the machine: a typo such as ``--trials 10000000000`` is a
one-line error that says the limit and how to raise it, not an out-of-memory kill or a run of days.

Each limit has a default sized for a workstation (measured on the 2-core, 24 GiB machine the
project is developed on: at the default, a computation holds at most about 5 GiB) and an environment
variable that raises (or lowers) it:

=======================  ============================  =============  ===========================================
limit                    environment variable          default        what it bounds (memory at the default)
=======================  ============================  =============  ===========================================
Monte Carlo trials       ``ROADGONIO_MAX_TRIALS``      1,000,000      ``uncertainty --trials/--max-trials/--batch``
                                                                      (3-8 kB a trial: <= 8 GB with the aperture
                                                                      case on all 580 cells), ``road --trials``
rays per cell            ``ROADGONIO_MAX_RAYS``        32,768         ``correct --rays`` (about 0.36 kB a ray and
                                                                      cell: 4.7 GB for 396 cells)
samples per batch        ``ROADGONIO_MAX_BATCH``       4,194,304      the ``batch`` of numpy-mc (0.15 kB a sample)
                                                                      and numpy-mc-mesh (0.64 kB: 2.7 GB)
design points            ``ROADGONIO_MAX_DESIGN_POINTS``  100,000     ``design --vary`` grids (the k_A tables of
                                                                      all points are held: 18 kB a point and sample)
render samples           ``ROADGONIO_MAX_RENDER_SAMPLES``  2^30       ``render``: resolution^2 x spp (time: 2^30
                                                                      samples take about 3 minutes here)
=======================  ============================  =============  ===========================================
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from roadgonio.errors import InputError


@dataclass(frozen=True)
class Limit:
    env: str           # the environment variable that sets it
    default: int
    what: str          # what is counted, for messages


LIMITS: dict[str, Limit] = {
    "trials": Limit("ROADGONIO_MAX_TRIALS", 1_000_000, "Monte Carlo trials"),
    "rays": Limit("ROADGONIO_MAX_RAYS", 32_768, "rays per cell"),
    "batch": Limit("ROADGONIO_MAX_BATCH", 1 << 22, "samples per batch"),
    "design_points": Limit("ROADGONIO_MAX_DESIGN_POINTS", 100_000, "design points"),
    "render_samples": Limit("ROADGONIO_MAX_RENDER_SAMPLES", 1 << 30, "samples per render (resolution^2 x spp)"),
}


def limit(name: str) -> int:
    """The limit ``name`` of :data:`LIMITS`: its environment variable if set (a whole number >= 1),
    else the default."""
    lim = LIMITS[name]
    text = os.environ.get(lim.env, "").strip()
    if not text:
        return lim.default
    try:
        v = int(text.replace("_", ""))
    except ValueError:
        raise InputError(f"expected a whole number >= 1, got {text!r}", field=lim.env) from None
    if v < 1:
        raise InputError(f"expected a whole number >= 1, got {v}", field=lim.env)
    return v


def check_size(value: int, name: str, field: str) -> int:
    """``value`` if it is within the limit ``name``, else the one-line error naming ``field``, the
    limit and how to raise it."""
    top = limit(name)
    if value > top:
        lim = LIMITS[name]
        raise InputError(f"{value:,} {lim.what} is more than this machine's limit of {top:,} (a run that size would "
                         f"exhaust its memory or take days); raise the limit with the environment variable "
                         f"{lim.env}=N if the machine can take it", field=field)
    return value
