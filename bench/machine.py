"""What machine a bench ran on, as its output quotes it (benchmarks are quoted with the machine), and
where a bench writes its rows.

Every bench that prints a results table starts it with :func:`header` (its title, the machine and the
load average before the run) and, where it prints one, ends it with :func:`load_after`; a
:class:`Printout` prints those lines and keeps them, so that the table as printed is saved beside
the CSV (``write_rows(out, rows, printout.text())``)."""
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


def write_rows(out: str | Path, rows: list[dict], text: str | None = None) -> None:
    """A bench's rows as CSV at ``out`` (its folder made), and its printed table beside it as ``.txt``."""
    import csv
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    if text is not None:
        out.with_suffix(".txt").write_text(text + "\n")


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, as a bench prints them before and after its run."""
    try:
        return ", ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:  # pragma: no cover
        return "?"


def header(title: str) -> list[str]:
    """The first lines of a bench's printed output: its title, then the machine (:func:`describe`) and
    the load average before the run (call it before the run starts)."""
    return [title, f"machine: {describe()}; load average before {load_average()}"]


def load_after() -> str:
    """The line a bench prints after its run: the load average then."""
    return f"load average after {load_average()}"


class Printout:
    """Lines printed to stdout and kept, to be saved beside a bench's CSV as its .txt (the table as
    printed). Starts with :func:`header` of ``title``, printed at once."""

    def __init__(self, title: str):
        self.lines: list[str] = []
        for line in header(title):
            self(line)

    def __call__(self, line: str = "") -> None:
        print(line, flush=True)
        self.lines.extend(str(line).split("\n"))

    def text(self) -> str:
        return "\n".join(self.lines)
