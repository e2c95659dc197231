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
        op = self.operator(table)
        L = op.luminance(table)
        m = metrics.luminance_metrics(L, self.fld.lane, self.fld.centre)
        ti = self.ti(m["L_av"])
        values = {"L_av": float(m["L_av"]), "U_o": float(m["U_o"]), "U_l": float(m["U_l"]),
                  "TI": None if ti is None else float(ti), "R_EI": self.edge["R_EI"]}
        return RoadResult(table=table, values=values, L=L, per_observer=m, cls=metrics.best_class(values),
                          installation=self, operator=op)


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

    def summary(self) -> dict[str, Any]:
        inst = self.installation
        lay = inst.layout
        m = self.per_observer
        ti_note = "" if inst.veiling["computable"] else inst.veiling["reason"]
        out = {"table": self.table.name, **self.values, "class": self.cls,
               "U_l_per_lane": [float(v) for v in m["U_l_lane"]],
               "observers": [{"lane": k + 1, "x_m": float(o[0]), "y_m": float(o[1]), "L_av": float(m["L_av_obs"][k]),
                              "U_o": float(m["U_o_obs"][k]), "U_l": float(m["U_l_lane"][k])}
                             for k, o in enumerate(inst.fld.observers)],
               "L_min": float(self.L.min()), "L_max": float(self.L.max()),
               "TI_note": ti_note or "initial values (MF = 1 in L_v and L_av)",
               "L_v_max": inst.l_v_max, "R_EI_per_edge": inst.edge["per_edge"],
               "failed_criteria_of_next_class": None,
               "table_Q0": self.table.q0(), "table_S1": _safe(self.table.s1),
               "neglected_contributions": self.operator.neglected, "evaluated_contributions": self.operator.evaluated,
               "grid": {"n_longitudinal": inst.fld.n_long, "D_m": inst.fld.spacing_d_m, "points_per_lane_across": 3},
               "layout": lay.to_dict(), "luminaire": {"name": inst.luminaire.name, "file": inst.luminaire.source,
                                                      "flux_lm": inst.luminaire.flux_lm}}
        order = list(metrics.M_CLASSES)
        nxt = order[order.index(self.cls) - 1] if self.cls in order[1:] else (order[-1] if self.cls is None else None)
        if nxt:
            out["failed_criteria_of_next_class"] = {"class": nxt, "failed": metrics.limiting_criteria(nxt, self.values)}
        if self.uncertainty is not None:
            out["uncertainty"] = self.uncertainty
        return out


def _safe(fn):
    try:
        return float(fn())
    except Exception:  # a table without the S1 cells
        return None
