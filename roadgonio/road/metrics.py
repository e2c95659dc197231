"""Road-surface luminance metrics (EN 13201-3) and the M classes of EN 13201-2.

* L_av: mean luminance over the field's grid (all lanes) for each observer; U_o = L_min / L_av
  over the same points; U_l = L_min / L_max along the centre line of a lane for the observer in
  that lane. The operative values are the lowest over the observers (L_av, U_o) and lanes (U_l);
  TI the highest over the TI observer positions.
* TI uses initial values (maintenance factor 1 in L_v and in L_av: L_av,initial = L_av / MF), our
  reading of CIE 140 / EN 13201-3 (the standard's text was not available to us).
* Classes M1-M6 (EN 13201-2:2015 Table 1): L_av >= (maintained), U_o >=, U_l >=, f_TI <= (%),
  R_EI >=. A design meets the best class all of whose criteria it meets; a criterion that cannot be
  computed (TI without the needed luminaire data) is left out and said so.
"""
from __future__ import annotations

import numpy as np

#: EN 13201-2:2015 Table 1 (M classes, dry road surface): L_av min, U_o min, U_l min, f_TI max, R_EI min.
M_CLASSES = {
    "M1": {"L_av": 2.00, "U_o": 0.40, "U_l": 0.70, "TI": 10.0, "R_EI": 0.35},
    "M2": {"L_av": 1.50, "U_o": 0.40, "U_l": 0.70, "TI": 10.0, "R_EI": 0.35},
    "M3": {"L_av": 1.00, "U_o": 0.40, "U_l": 0.60, "TI": 15.0, "R_EI": 0.30},
    "M4": {"L_av": 0.75, "U_o": 0.40, "U_l": 0.60, "TI": 15.0, "R_EI": 0.30},
    "M5": {"L_av": 0.50, "U_o": 0.35, "U_l": 0.40, "TI": 15.0, "R_EI": 0.30},
    "M6": {"L_av": 0.30, "U_o": 0.35, "U_l": 0.40, "TI": 20.0, "R_EI": 0.30},
}
MINIMA = ("L_av", "U_o", "U_l", "R_EI")


def luminance_metrics(L: np.ndarray, lane: np.ndarray, centre: np.ndarray) -> dict:
    """Metrics from ``L`` of shape (..., n_obs, n_p) (leading axes: Monte Carlo trials).

    Returns arrays with the leading shape: ``L_av``, ``U_o``, ``U_l`` (operative) and
    ``L_av_obs``, ``U_o_obs`` (..., n_obs), ``U_l_lane`` (..., n_lanes)."""
    L = np.asarray(L, float)
    lav_obs = L.mean(axis=-1)
    uo_obs = luminance_ratio(L.min(axis=-1), lav_obs)        # NaN (undefined) without light
    n_lanes = L.shape[-2]
    ul = []
    for k in range(n_lanes):
        line = L[..., k, (lane == k) & centre]
        ul.append(luminance_ratio(line.min(axis=-1), line.max(axis=-1)))
    ul = np.stack(ul, axis=-1)
    return {"L_av": lav_obs.min(axis=-1), "U_o": uo_obs.min(axis=-1), "U_l": ul.min(axis=-1),
            "L_av_obs": lav_obs, "U_o_obs": uo_obs, "U_l_lane": ul}


def unknown(incomplete: np.ndarray | None, lane: np.ndarray, centre: np.ndarray) -> dict:
    """Which metrics of :func:`luminance_metrics` are unknown when the luminance of some points is
    (``incomplete`` (n_obs, n_p): True where a point's L lacks a contribution): an observer's L_av
    and U_o need all its points, a lane's U_l its centre-line points for that lane's observer, the
    operative values all observers / lanes (TI needs L_av). Booleans and per-observer/lane arrays."""
    if incomplete is None or not np.any(incomplete):
        n_obs = 0 if incomplete is None else incomplete.shape[0]
        none = np.zeros(n_obs, dtype=bool)
        return {"L_av": False, "U_o": False, "U_l": False, "TI": False, "obs": none, "lanes": none}
    obs = incomplete.any(axis=1)
    lanes = np.array([bool(incomplete[k, (lane == k) & centre].any()) for k in range(incomplete.shape[0])])
    return {"L_av": bool(obs.any()), "U_o": bool(obs.any()), "U_l": bool(lanes.any()), "TI": bool(obs.any()),
            "obs": obs, "lanes": lanes}


def luminance_ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den where den > 0, else NaN (a uniformity of a field without light is undefined)."""
    num, den = np.broadcast_arrays(np.asarray(num, float), np.asarray(den, float))
    out = np.full(num.shape, np.nan)
    np.divide(num, den, out=out, where=den > 0)
    return out


def meets(cls: str, values: dict) -> bool:
    """True if every computable criterion of ``cls`` is met (``values``: L_av, U_o, U_l, TI, R_EI;
    None = not computable)."""
    lim = M_CLASSES[cls]
    for k in MINIMA:
        v = values.get(k)
        if v is not None and not (v >= lim[k]):
            return False
    ti = values.get("TI")
    return ti is None or ti <= lim["TI"]


def best_class(values: dict) -> str | None:
    for cls in M_CLASSES:
        if meets(cls, values):
            return cls
    return None


def meets_array(cls: str, values: dict) -> np.ndarray:
    """Vectorised :func:`meets` over Monte Carlo trials (arrays; None = not computable)."""
    lim = M_CLASSES[cls]
    ok = None
    for k in MINIMA:
        v = values.get(k)
        if v is None:
            continue
        t = np.asarray(v) >= lim[k]
        ok = t if ok is None else ok & t
    if values.get("TI") is not None:
        t = np.asarray(values["TI"]) <= lim["TI"]
        ok = t if ok is None else ok & t
    return ok


def best_class_array(values: dict) -> np.ndarray:
    """Index of the best class met per trial (0 = M1 ... 5 = M6, 6 = none)."""
    shape = np.shape(values["L_av"])
    out = np.full(shape, len(M_CLASSES), dtype=int)
    for k, cls in reversed(list(enumerate(M_CLASSES))):
        out = np.where(meets_array(cls, values), k, out)
    return out


def limiting_criteria(cls: str, values: dict) -> list[str]:
    """The criteria of ``cls`` that ``values`` fails."""
    lim = M_CLASSES[cls]
    bad = [k for k in MINIMA if values.get(k) is not None and not values[k] >= lim[k]]
    if values.get("TI") is not None and not values["TI"] <= lim["TI"]:
        bad.append("TI")
    return bad
