"""Progress bars of long work: on stderr, only when it is a terminal (developers' guide).

:func:`bar` is a ``tqdm`` bar, or ``None`` when there is nothing to show (progress off, stderr not a
terminal, nothing left to do). A terminal that reports a size of 0 x 0 (the pseudo-terminal of
``script``, some CI runners and IDE consoles) gets a fixed size (``$COLUMNS`` x ``$LINES``, else
80 x 24) instead of the dynamic one: tqdm draws nothing at all at 0 columns or 0 rows, and a long
run looked silent there.

Work inside one step can be long too (a Monte Carlo cell at its sample cap: 2e8 samples, tens of
minutes): such a backend draws a bar of that step with :func:`step_bar`, which shows only inside
:func:`steps_shown` (the caller that shows its own bar, or a command on a terminal, turns it on) and
only once the step has run :data:`STEP_BAR_DELAY` seconds, so the many short steps of a table draw none.
"""
from __future__ import annotations

import shutil
import sys
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any, Iterator

#: Seconds a step runs before its own bar (:func:`step_bar`) is drawn.
STEP_BAR_DELAY = 2.0
_STEP_BARS: ContextVar[bool] = ContextVar("roadgonio_step_bars", default=False)


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
        leave: bool = True, delay: float = 0.0, unit_scale: bool = False) -> Any:
    """A progress bar of ``total`` steps (``initial`` already done) on stderr, or None when
    ``enabled`` is false, stderr is not a terminal, or nothing is left to do. ``delay``: seconds
    before it is drawn; ``unit_scale``: counts as 1.2M instead of 1200000."""
    if not enabled or not sys.stderr.isatty() or (total is not None and total <= initial):
        return None
    from tqdm import tqdm
    fixed = _fixed_size()
    size = {"dynamic_ncols": True} if fixed is None else {"ncols": fixed[0], "nrows": fixed[1]}
    return tqdm(total=total, initial=initial, desc=desc, unit=unit, file=sys.stderr, leave=leave, delay=delay,
                unit_scale=unit_scale, **size)


@contextmanager
def steps_shown(enabled: bool = True) -> Iterator[None]:
    """Inside the block, :func:`step_bar` draws the bars of long steps (on a terminal)."""
    token = _STEP_BARS.set(bool(enabled))
    try:
        yield
    finally:
        _STEP_BARS.reset(token)


def step_bar(total: int, desc: str, *, unit: str = "sample") -> Any:
    """The bar of the work inside one long step (``total`` units at most), cleared when it ends; None
    outside :func:`steps_shown` or off a terminal (:func:`bar`). Drawn after :data:`STEP_BAR_DELAY` s."""
    return bar(total, desc, unit=unit, enabled=_STEP_BARS.get(), leave=False, delay=STEP_BAR_DELAY,
               unit_scale=True)
