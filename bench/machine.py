"""What machine a bench ran on, as its output quotes it (benchmarks are quoted with the machine)."""
from __future__ import annotations

import os
from pathlib import Path


def mem_gib() -> float:
    """Physical memory in GiB (NaN where the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 ** 30
    except (ValueError, OSError, AttributeError):
        return float("nan")


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo ("unknown CPU" elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def describe() -> str:
    """Cores, CPU model and memory in one phrase."""
    return f"{os.cpu_count()} cores, {cpu_model()}, {mem_gib():.0f} GiB"
