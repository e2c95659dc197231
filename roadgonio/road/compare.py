"""Side-by-side comparison of two r-tables: the ratio map B / A and S1, S2, Q0 of both."""
from __future__ import annotations

import io
import math

import numpy as np

from roadgonio.errors import InputError
from roadgonio.surface.cie import s1_text
from roadgonio.surface.rtable import RTable

#: Every file ``roadgonio compare`` writes: a run removes those it does not write (``--no-plots``:
#: compare.png), so an earlier run's picture of other tables never stays beside the new files.
COMPARE_FILES = ("compare.csv", "compare.json", "compare.png")
#: A largest |ln ratio| at or below this is no change: the float noise of one table read at two
#: scales (user audit, session 44: the same R3 from an RTB in sr^-1 and one in r x 1e4 had a
#: "largest change x1" of 1 - 2.2e-16); a stored table has 6 significant digits.
RATIO_EQUAL_REL = 1e-12


def compare_tables(a: RTable, b: RTable) -> dict:
    """The ratio r(B)/r(A) over the cells both tables hold and the largest change (|ln ratio|).
    r(B) = 0 < r(A) gives a ratio of 0 and r(A) = 0 < r(B) an infinite one (in ``ratio``, not in the
    range, the median nor ``cells_compared``, which are of the finite ratios): both are infinite
    changes, counted apart (``cells_zero_in_B``, ``cells_zero_in_A``); a cell 0 in both has no ratio
    (``cells_ratio_undefined``). ``largest_change_at`` is None when every compared cell is equal (within
    :data:`RATIO_EQUAL_REL`)."""
    if not a.same_grid(b):
        raise InputError(f"tables {a.name} and {b.name} are not on the same grid")
    both = a.mask & b.mask
    zero_a, zero_b = both & (a.r == 0), both & (b.r == 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(both, b.r / a.r, np.nan)                 # x/0 = inf, 0/0 = NaN
        change = np.abs(np.log(ratio))                            # 0 or inf: an infinite change
    got = ratio[np.isfinite(ratio)]
    if got.size == 0:
        raise InputError(f"tables {a.name} and {b.name} share no cell with r(A) > 0: there is no ratio to compare; "
                         "expected tables with common tabulated cells", field="b")
    k = np.unravel_index(np.nanargmax(change), ratio.shape)
    from roadgonio.surface.rtable import q0_coverage_note
    char = {}
    for t in (a, b):
        char[t.name] = {"S1": _try(t.s1), "S2": _try(t.s2), "Q0": _try(t.q0), "cells": int(t.mask.sum())}
    notes = [n for n in (q0_coverage_note(a), q0_coverage_note(b)) if n]
    largest = None if change[k] <= RATIO_EQUAL_REL else {"tan_eps": float(a.tan_eps[k[0]]), "beta_deg": float(a.beta_deg[k[1]]),
                                           "ratio": float(ratio[k])}
    return {"A": a.name, "B": b.name, "ratio": ratio, "characteristics": char, "notes": notes,
            "ratio_min": float(got.min()), "ratio_max": float(got.max()), "ratio_median": float(np.median(got)),
            "largest_change_at": largest,
            "cells_compared": int(got.size),
            "cells_zero_in_A": int((zero_a & ~zero_b).sum()), "cells_zero_in_B": int((zero_b & ~zero_a).sum()),
            "cells_ratio_undefined": int((zero_a & zero_b).sum()),
            "cells_only_in_A": int((a.mask & ~b.mask).sum()), "cells_only_in_B": int((b.mask & ~a.mask).sum())}


def ratio_text(v: float) -> str:
    """A ratio B/A with 3 significant digits, or as many more (up to 9) as it takes to show that it is
    not 1 (user audit: a cell changed by 0.34 % read 'largest change x1')."""
    p = 3
    while v != 1.0 and math.isfinite(v) and p < 9 and float(f"{v:.{p}g}") == 1.0:
        p += 1
    return f"{v:.{p}g}"


def range_text(result: dict) -> str:
    """'0.995 ... 1.0034 (median 1)' of a comparison (:func:`ratio_text` for each)."""
    return (f"{ratio_text(result['ratio_min'])} ... {ratio_text(result['ratio_max'])} "
            f"(median {ratio_text(result['ratio_median'])})")


def largest_change_text(result: dict) -> str:
    """'largest change x1.23 at tan eps 0.5, beta 2 deg' (r(A) = 0 < r(B): 'from 0'), or that the
    compared cells are all equal: one wording for the command's line and the picture."""
    lc = result["largest_change_at"]
    if lc is None:
        return "every compared cell equal"
    what = "from r(A) = 0" if math.isinf(lc["ratio"]) else f"x{ratio_text(lc['ratio'])}"
    return f"largest change {what} at tan eps {lc['tan_eps']:g}, beta {lc['beta_deg']:g} deg"


def _try(fn):
    """A characteristic, or None when the table lacks the cells it needs (missing, never NaN)."""
    v = float(fn())
    return v if np.isfinite(v) else None


def compare_csv(a: RTable, b: RTable, ratio: np.ndarray) -> str:
    out = io.StringIO()
    out.write(f"tan_eps,beta_deg,r_{_safe(a.name)}_x1e4,r_{_safe(b.name)}_x1e4,ratio_B_over_A\n")
    for i, t in enumerate(a.tan_eps):
        for j, be in enumerate(a.beta_deg):
            if not (a.mask[i, j] or b.mask[i, j]):
                continue
            ra = "" if not a.mask[i, j] else f"{a.r[i, j] * 1e4:.6g}"
            rb = "" if not b.mask[i, j] else f"{b.r[i, j] * 1e4:.6g}"
            q = "" if not np.isfinite(ratio[i, j]) else f"{ratio[i, j]:.6g}"     # r(A) = 0: the r columns say
            out.write(f"{t:g},{be:g},{ra},{rb},{q}\n")
    return out.getvalue()


def _safe(name: str) -> str:
    from roadgonio.fileio import safe_name
    return safe_name(name, "table")


def compare_png(result: dict, a: RTable, b: RTable) -> bytes:
    from roadgonio.plots import _plt, draw_table_map
    plt = _plt()
    fig = plt.figure(figsize=(15, 9.5))
    ax = fig.add_axes([0.05, 0.07, 0.66, 0.85])
    ratio = result["ratio"]
    draw_table_map(ax, np.where(np.isinf(ratio), np.nan, ratio), label=f"r({b.name}) / r({a.name})", centre=1.0,
                   log=True, fmt="{:.2f}", fontsize=6.0, tick_fontsize=8, grey_blanks=True)
    for i, j in zip(*np.nonzero(np.isinf(ratio))):       # r(A) = 0 < r(B): no colour, but not a blank
        ax.text(j, i, "A=0", ha="center", va="center", fontsize=6.0, color="black", fontweight="bold")
    why = "grey: not in both tables" + (", or 0 in both" if result["cells_ratio_undefined"] else "")
    if result["cells_zero_in_A"]:
        why += "; A=0: r(A) = 0 < r(B), an infinite ratio"
    ax.set_title(f"{b.name} / {a.name}: ratio of r, cell by cell ({why})", fontsize=11)
    tx = fig.add_axes([0.77, 0.35, 0.22, 0.5])
    tx.axis("off")
    rows = [["", _short(a.name), _short(b.name)]]
    ca, cb = result["characteristics"][a.name], result["characteristics"][b.name]
    for key, fmt in (("S1", "{:.3f}"), ("S2", "{:.3f}"), ("Q0", "{:.4f}"), ("cells", "{:d}")):
        label = "Q0 (sr^-1)" if key == "Q0" else key                 # its unit (user audit, session 41)
        rows.append([label] + [("missing" if c[key] is None else s1_text(c[key]) if key == "S1" else fmt.format(c[key]))
                               for c in (ca, cb)])
    tab = tx.table(cellText=rows, loc="upper center", cellLoc="center")
    tab.scale(1.0, 1.8)
    tab.set_fontsize(11)
    tx.text(0.0, 0.25, f"ratio {ratio_text(result['ratio_min'])} ... {ratio_text(result['ratio_max'])}\n"
            f"median {ratio_text(result['ratio_median'])}\n" + largest_change_text(result).replace(" at tan", "\nat tan"),
            fontsize=10, va="top", transform=tx.transAxes)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def _short(name: str, n: int = 18) -> str:
    """A table's name for a narrow cell: a file's stored name ``measured.rtb (R3)`` dropped first."""
    if len(name) > n and " (" in name:
        name = name.split(" (")[0]
    return name if len(name) <= n else name[:n - 3] + "..."
