"""One road evaluation: a layout, a luminaire and an r-table -> L_av, U_o, U_l, TI, R_EI, class.

The table-independent parts (field, veiling luminance, edge illuminance) are computed once per
layout and luminaire in :class:`Installation`; the luminance operator once per table grid and
blank pattern, so several tables and Monte Carlo trials reuse it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from roadgonio.road import calc, metrics
from roadgonio.road.layout import Layout
from roadgonio.road.luminaire import Luminaire
from roadgonio.surface.rtable import RTable


@dataclass
class Installation:
    layout: Layout
    luminaire: Luminaire
    fld: calc.Field = field(init=False)
    veiling: dict = field(init=False)
    edge: dict = field(init=False)
    _ops: dict = field(default_factory=dict, init=False)

    def __post_init__(self):
        self.fld = calc.build_field(self.layout)
        self.veiling = calc.veiling_luminance(self.layout, self.luminaire, self.fld)
        self.edge = calc.edge_illuminance_ratio(self.layout, self.luminaire, self.fld)
        #: what a reader of the metrics must know about the layout (summary()["notes"])
        self.notes = [n for n in (calc.uncounted_note(self.layout, self.fld), calc.range_note(self.layout)) if n]

    def operator(self, table: RTable) -> calc.LuminanceOperator:
        key = (table.r.shape, table.mask.tobytes(), table.tan_eps.tobytes(), table.beta_deg.tobytes())
        if key not in self._ops:
            self._ops[key] = calc.luminance_operator(self.layout, self.luminaire, table, self.fld)
        return self._ops[key]

    @property
    def l_v_max(self) -> float | None:
        return float(np.max(self.veiling["L_v"])) if self.veiling["computable"] else None

    def ti(self, l_av):
        """Operative TI (%) for the maintained operative L_av (initial values: L_av / MF)."""
        if self.l_v_max is None:
            return None
        return calc.threshold_increment(self.l_v_max, np.asarray(l_av) / self.layout.maintenance_factor)

    def evaluate(self, table: RTable) -> "RoadResult":
        """The metrics of ``table``. A metric that needs a point whose luminance is unknown (the
        table lacks r where the CIE standard tables have it: :mod:`roadgonio.road.calc`), or a
        uniformity of a field without light, is None (missing), and then the class is None too."""
        op = self.operator(table)
        L = op.luminance(table)
        m = metrics.luminance_metrics(L, self.fld.lane, self.fld.centre)
        gone = metrics.unknown(op.incomplete, self.fld.lane, self.fld.centre)
        ti = self.ti(m["L_av"]) if m["L_av"] > 0 else None
        ti_overflow = ti is not None and not np.isfinite(ti)      # L_av so small that TI exceeds any float
        if ti_overflow:
            ti = None
        values = {"L_av": _known(m["L_av"], gone["L_av"]), "U_o": _known(m["U_o"], gone["U_o"]),
                  "U_l": _known(m["U_l"], gone["U_l"]),
                  "TI": None if ti is None or gone["TI"] else float(ti), "R_EI": _known(self.edge["R_EI"])}
        m = dict(m, L_av_obs=np.where(gone["obs"], np.nan, m["L_av_obs"]),
                 U_o_obs=np.where(gone["obs"], np.nan, m["U_o_obs"]),
                 U_l_lane=np.where(gone["lanes"], np.nan, m["U_l_lane"]))
        missing = None
        ti_why = None        # why TI is missing when the veiling luminance is computable
        lost = [k for k in ("L_av", "U_o", "U_l") if values[k] is None]
        if gone["L_av"] or gone["U_l"]:
            dirs = "; ".join(f"beta {b:.1f} deg, tan eps {t:.2f}" for b, t in op.missing_directions[:3])
            missing = {"metrics": [k for k in ("L_av", "U_o", "U_l", "TI") if gone[k]] + ["class"],
                       "reason": f"the table has no r at {op.missing_count} luminaire contribution(s) whose direction "
                                 f"the CIE standard tables tabulate (blank cells; e.g. {dirs}): the luminance of "
                                 f"{int(op.incomplete.sum())} of {op.incomplete.size} (observer, point) pairs is "
                                 "unknown, so these metrics cannot be given",
                       "points_unknown": int(op.incomplete.sum())}
            if gone["TI"]:
                ti_why = ("it needs L_av, which is unknown: the table is blank where luminaire contributions fall "
                          "(see missing)")
        elif lost:
            # audit 27: TI (it needs L_av > 0) was null without being listed
            dark = ti is None and not m["L_av"] > 0
            missing = {"metrics": lost + (["TI"] if ti_overflow or dark else []) + ["class"],
                       "reason": "no light where a uniformity needs it (L_av or a lane's L_max is 0): undefined"
                                 + ("; TI needs L_av > 0" if dark else "")}
        elif ti_overflow:
            missing = {"metrics": ["TI", "class"],
                       "reason": f"L_av = {m['L_av']:.3g} cd/m^2 is so small that TI = 65 L_v / L_av^0.8 exceeds any "
                                 "float (is the table r x 1e4?)"}
        if ti_why is None and values["TI"] is None:
            ti_why = (f"L_av = {m['L_av']:.3g} cd/m^2 is so small that TI exceeds any float (see missing)" if ti_overflow
                      else "it needs L_av > 0 (no light on the field)" if not m["L_av"] > 0 else None)
        if values["R_EI"] is None:
            # audit 27: R_EI (no light on the strips inside the edges) was null without being listed
            missing = with_missing(missing, "R_EI", "R_EI needs light on the strips inside the edges, and they have none")
        if not self.veiling["computable"]:
            # user audit, session 42: a class was given (M3, whose limit f_TI <= 15 % was never checked) and
            # `missing` was null when the luminaire data stop before the angles TI needs
            missing = with_missing(missing, "TI", self.veiling["reason"])          # the reason names TI
        cls = None if missing else metrics.best_class(values)
        return RoadResult(table=table, values=values, L=np.where(op.incomplete, np.nan, L), per_observer=m, cls=cls,
                          installation=self, operator=op, missing=missing, ti_missing=ti_why,
                          table_notes=[n for n in (gap_note(table),) if n])


@dataclass
class RoadResult:
    table: RTable
    values: dict
    L: np.ndarray
    per_observer: dict
    cls: str | None
    installation: Installation
    operator: calc.LuminanceOperator
    uncertainty: dict | None = None
    #: which metrics are missing and why (None: every metric is known)
    missing: dict | None = None
    #: why TI is missing although the layout's veiling luminance is computable (None: not missing)
    ti_missing: str | None = None
    #: what a reader of the metrics must know about this table (summary()["notes"], after the layout's)
    table_notes: list = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        inst = self.installation
        lay = inst.layout
        m = self.per_observer
        if not inst.veiling["computable"]:
            ti_note = inst.veiling["reason"]
        elif self.values["TI"] is None:
            ti_note = self.ti_missing or "missing"
        else:
            ti_note = "initial values (MF = 1 in L_v and L_av)"
        out = {"table": self.table.name, **self.values, "class": self.cls,
               "U_l_per_lane": [_known(v) for v in m["U_l_lane"]],
               "observers": [{"lane": k + 1, "x_m": float(o[0]), "y_m": float(o[1]), "L_av": _known(m["L_av_obs"][k]),
                              "U_o": _known(m["U_o_obs"][k]), "U_l": _known(m["U_l_lane"][k])}
                             for k, o in enumerate(inst.fld.observers)],
               "L_min": None if self.missing and self.missing.get("points_unknown") else float(np.nanmin(self.L)),
               "L_max": None if self.missing and self.missing.get("points_unknown") else float(np.nanmax(self.L)),
               "missing": self.missing,
               "notes": list(inst.notes) + list(self.table_notes),
               "TI_note": ti_note,
               "L_v_max": inst.l_v_max, "R_EI_per_edge": inst.edge["per_edge"],
               "failed_criteria_of_next_class": None,
               "table_Q0": _safe(self.table.q0), "table_S1": _safe(self.table.s1),
               "neglected_contributions": self.operator.neglected, "evaluated_contributions": self.operator.evaluated,
               "grid": {"n_longitudinal": inst.fld.n_long, "D_m": inst.fld.spacing_d_m, "points_per_lane_across": 3},
               "layout": lay.to_dict(), "luminaire": {"name": inst.luminaire.name, "file": inst.luminaire.source,
                                                      "flux_lm": inst.luminaire.flux_lm}}
        order = list(metrics.M_CLASSES)
        nxt = order[order.index(self.cls) - 1] if self.cls in order[1:] else (order[-1] if self.cls is None else None)
        if nxt and not self.missing:
            out["failed_criteria_of_next_class"] = {"class": nxt, "failed": metrics.limiting_criteria(nxt, self.values)}
        if self.uncertainty is not None:
            out["uncertainty"] = self.uncertainty
        return out


def _safe(fn):
    """A table characteristic, or None when the table lacks its cells (missing)."""
    return _known(fn())


def gap_note(table: RTable) -> str | None:
    """One line when ``table`` leaves blank cells the CIE standard tables tabulate (a hole in a
    measured table): the interpolation takes its stencil among the tabulated cells
    (:mod:`roadgonio.road.interp`), so a contribution near the hole is interpolated across it from
    the neighbours, and only one with no stencil at all makes its point unknown (``missing``);
    a laboratory should know which of its cells the metrics did without (audit 27: silent)."""
    from roadgonio.surface.rtable import standard_mask
    r = np.asarray(table.r)
    std = standard_mask()
    if r.shape != std.shape:
        return None
    holes = np.argwhere(std & ~np.isfinite(r))
    if not len(holes):
        return None
    cells = ", ".join(f"{table.tan_eps[i]:g}:{table.beta_deg[j]:g}" for i, j in holes[:4]) + \
        (f" and {len(holes) - 4} more" if len(holes) > 4 else "")
    return (f"{table.name}: {len(holes)} cell(s) the CIE standard tables tabulate are blank (tan eps:beta {cells}): "
            "contributions near them are interpolated across the gap from the tabulated neighbours (EN 13201-3 5.5 "
            "among the cells given); only where no stencil remains is a point's luminance unknown")


def with_missing(missing: dict | None, metric: str, why: str) -> dict:
    """``missing`` (a result's ``missing``: metrics and reason, or None) with ``metric`` listed once,
    before ``class``, and ``why`` in its reason once. (It was written twice beside each other for R_EI,
    which then listed R_EI twice and said its reason twice when both fired.)"""
    if missing is None:
        return {"metrics": [metric, "class"], "reason": why}
    listed = [k for k in missing["metrics"] if k not in (metric, "class")] + [metric, "class"]
    reason = missing["reason"] if why in missing["reason"] else f"{missing['reason']}; {why}"
    return dict(missing, metrics=listed, reason=reason)


def _known(v, unknown: bool = False) -> float | None:
    """A metric as a float, or None when it is unknown or undefined (NaN)."""
    v = float(v)
    return None if unknown or not np.isfinite(v) else v
