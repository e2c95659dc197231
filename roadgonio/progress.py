"""Progress bars of long work: on stderr, only when it is a terminal (developers' guide).

:func:`bar` is a ``tqdm`` bar, or ``None`` when there is nothing to show (progress off, stderr not a
terminal, nothing left to do). A terminal that reports a size of 0 x 0 (the pseudo-terminal of
``script``, some CI runners and IDE consoles) gets a fixed size (``$COLUMNS`` x ``$LINES``, else
80 x 24) instead of the dynamic one: tqdm draws nothing at all at 0 columns or 0 rows, and a long
run looked silent there.
"""
from __future__ import annotations

import shutil
import sys
from typing import Any


def _fixed_size() -> tuple[int, int] | None:
    """None when the terminal reports its size (tqdm then follows it), else (columns, rows)."""
    import os
    try:
        size = os.get_terminal_size(sys.stderr.fileno())
    except (OSError, ValueError, AttributeError):
        size = os.terminal_size((0, 0))
    if size.columns > 0 and size.lines > 0:
        return None
    fallback = shutil.get_terminal_size()              # $COLUMNS / $LINES, else 80 x 24
    return fallback.columns, fallback.lines


def bar(total: int | None, desc: str, *, unit: str = "task", initial: int = 0, enabled: bool = True,
        leave: bool = True) -> Any:
    """A progress bar of ``total`` steps (``initial`` already done) on stderr, or None when
    ``enabled`` is false, stderr is not a terminal, or nothing is left to do."""
    if not enabled or not sys.stderr.isatty() or (total is not None and total <= initial):
        return None
    from tqdm import tqdm
    fixed = _fixed_size()
    size = {"dynamic_ncols": True} if fixed is None else {"ncols": fixed[0], "nrows": fixed[1]}
    return tqdm(total=total, initial=initial, desc=desc, unit=unit, file=sys.stderr, leave=leave, **size)
