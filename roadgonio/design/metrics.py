"""Figures of merit of a design point: the signal (from the etendue and the source's solid angle)
and the deviations of k_A from 1.

Signal
------
The detected flux for a Lambertian sample of reflectance rho, lit by the source disc of radiance
L_S at incidence epsilon, seen by the luminance meter of etendue G_D::

    Phi = L_sample * G_D * <k_D>,      L_sample = (rho / pi) * E_h,      E_h = L_S * Omega_S * cos(eps)

    Omega_S = pi R_S^2 / (R_S^2 + D_S^2)        projected solid angle of the source disc seen from the
                                                sample centre on its axis (exact for a Lambertian disc:
                                                E_normal = L_S Omega_S)
    G_D     = pi^2 / 2 * (X - sqrt(X^2 - 4 R_D^2 r_F^2)),  X = R_D^2 + r_F^2 + F^2
                                                etendue of the pupil disc (radius R_D) and the field disc
                                                (radius r_F = F tan gamma_D) on the focus plane at F,
                                                coaxial discs (exact); ~ (pi R_D^2) (pi tan^2 gamma_D)
    G_D     = pi R_D^2 * pi sin^2 gamma_D       for an angular field (F = inf)
    <k_D>   = 1 - (1 - e) / 2                   mean of k_D(rho) = 1 - (1 - e) rho^2 over the field disc
                                                (with a sensitivity map: its mean over the field disc)

A source with a beam profile (radiance L_0 A(rho) P(theta), docs/conventions.md section 4) has
``Omega_S = E_normal / L_0``, the illuminance on its axis at the sample centre per unit on-axis
radiance, integrated over the disc (float64 Gauss rule): a narrower beam or a darker rim gives
less signal from the same lamp. A hard beam limit (``beam_half_angle_deg``) lets only the disc's inner
part of radius min(R_S, D_S tan theta) light the sample centre (R_S there in Omega_S).

For the same lamp (L_S), sample (rho) and cell (eps), the design's ``signal`` is relative to the base
design::

    signal = (Omega_S G_D <k_D>) / (Omega_S G_D <k_D>)_base

with each Omega_S at the source distance D_S of the requested cells, the smallest over them
(:func:`signal_solid_angle`): on an arc D_S is the same for every cell, on a fixed-height path it is
height / cos eps, and the weakest requested cell sets the design's signal (and the base's).

It does not depend on the detector distance (etendue is conserved: a farther luminance meter sees a
larger footprint), and it neglects the illuminance gradient over the footprint (which the Lambert
calibration removes from k_A anyway): it is the light at the footprint's centre, so a beam narrower
than the footprint, which leaves part of it dark, detects less than it says (``roadgonio design``
counts the points whose beam lights the footprint's edge at less than :data:`DIM_EDGE` of its on-axis
radiance, :func:`footprint_edge_radiance`, and says so). A point source or a pinhole detector has signal 0.

Deviations
----------
Over the requested cells of every sample: ``max_abs_dev`` = max |k_A - 1|, ``rms_dev`` = the root
mean square of k_A - 1, and the worst cell (tan eps, beta, sample) with its SE.

Stray light
-----------
Of an instrument with reflecting parts (a ``[housing]``, docs/straylight.md), from the same tables
(:class:`roadgonio.engines.result.CellResult`'s ``stray_fraction`` and ``k_a_direct``, the k_A
Dataset's variables of those names): ``max_stray_fraction`` = the largest stray fraction of the
road signal over the cells and samples (a fraction; the cell where it is, with its SE), and
``max_abs_dev_direct`` = max |k_A,direct - 1|, the instrument's own aperture effect without the
stray light. Without stray light they are 0 and ``max_abs_dev`` (the k_A Dataset's stray fraction is
0 exactly and its k_a_direct is k_a), and the cell of the largest stray fraction is none.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

# the source's solid angle lives with the calibration's E_0 (render's unit needs it too); re-exported here
from roadgonio.engines.calibration import PROFILE_RULE_LEVEL, profiled_solid_angle, source_solid_angle  # noqa: F401
from roadgonio.instrument.config import Instrument

SIGNAL_FORMULA = ("signal = (Omega_S G_D <k_D>) / (Omega_S G_D <k_D>)_base; Omega_S = pi R_S^2/(R_S^2+D_S^2) "
                  "(projected solid angle of the source disc at the requested cells' D_S, the smallest; a beam limit theta: R_S -> min(R_S, D_S tan theta)), G_D = pi^2/2 (X - sqrt(X^2 - 4 R_D^2 r_F^2)), "
                  "X = R_D^2 + r_F^2 + F^2, r_F = F tan gamma_D (etendue of pupil and field discs; pi R_D^2 pi "
                  "sin^2 gamma_D for F = inf), <k_D> = 1 - (1 - e)/2 (roadgonio.design.metrics); a beam profile "
                  "L_0 A(rho) P(theta): Omega_S = E_normal / L_0 integrated over the disc, a sensitivity map: <k_D> "
                  "its mean over the field")


def coaxial_disc_etendue(r1: float, r2: float, d: float) -> float:
    """Etendue (m^2 sr) of two coaxial parallel discs of radii r1, r2 at distance d (exact)."""
    if r1 == 0.0 or r2 == 0.0:
        return 0.0
    x = r1 * r1 + r2 * r2 + d * d
    disc = x * x - 4.0 * r1 * r1 * r2 * r2
    # cancellation-free form of x - sqrt(disc)
    return 0.5 * math.pi ** 2 * (4.0 * r1 * r1 * r2 * r2) / (x + math.sqrt(max(disc, 0.0)))


def detector_etendue(instrument: Instrument) -> float:
    """Etendue (m^2 sr) of the luminance meter: pupil disc x field stop (module docstring)."""
    det = instrument.detector
    gamma = math.radians(det.field_half_angle_deg)
    if det.angular_field:
        return math.pi * det.pupil_radius_m ** 2 * math.pi * math.sin(gamma) ** 2
    f = det.focus_distance_m
    return coaxial_disc_etendue(det.pupil_radius_m, f * math.tan(gamma), f)


def mean_field_sensitivity(instrument: Instrument) -> float:
    """Area mean of k_D over the field disc: 1 - (1 - e)/2 for k_D(rho) = 1 - (1 - e) rho^2, or the
    mean of the sensitivity map (:func:`roadgonio.instrument.optics.field_map_value`)."""
    det = instrument.detector
    if det.field_map is None:
        from roadgonio.instrument.profiles import quadratic_edge_mean
        return quadratic_edge_mean(det.field_edge_sensitivity)
    from roadgonio.arrays import NumpyOps
    from roadgonio.engines.rules import disc_rule
    from roadgonio.instrument.optics import detector_geometry, field_map_value
    fx, fy, w = disc_rule(PROFILE_RULE_LEVEL, PROFILE_RULE_LEVEL)
    return float(field_map_value(NumpyOps, detector_geometry(instrument), fx, fy) @ w)


#: A beam whose radiance towards the footprint's far edge is below this fraction of its on-axis
#: radiance leaves part of the footprint darker than the signal assumes (:func:`footprint_edge_radiance`).
DIM_EDGE = 0.5


def footprint_edge_radiance(instrument: Instrument, cells) -> float:
    """The source's relative radiance P(theta) / P(0) towards the footprint at the largest emission
    angle theta over ``cells`` (:func:`roadgonio.instrument.optics.footprint_emission_angles_deg`,
    from the disc's rim), 0 beyond a beam limit; 1 for a Lambertian disc without one. The signal is
    the light at the footprint's centre (module docstring): below :data:`DIM_EDGE` part of the
    footprint is darker than it assumes, and the detected flux is less than the signal says."""
    src = instrument.source
    if src.beam_half_angle_deg is None and src.beam.uniform:
        return 1.0
    from roadgonio.arrays import NumpyOps
    from roadgonio.instrument import optics
    from roadgonio.instrument.profiles import ApertureProfile
    theta_deg = float(np.max(optics.footprint_emission_angles_deg(instrument, list(cells))))
    if src.beam_half_angle_deg is not None and theta_deg > src.beam_half_angle_deg:
        return 0.0
    if src.beam.uniform:
        return 1.0
    t = math.radians(min(theta_deg, 89.999))
    w = (np.array([math.sin(t)]), np.zeros(1), np.array([math.cos(t)]))      # towards the source
    f = optics.source_radiance_factor(NumpyOps, src.beam, ApertureProfile(), w, (0.0, 0.0, -1.0),
                                      (np.zeros(1), np.zeros(1)))
    return 1.0 if f is None else float(np.asarray(f).reshape(-1)[0])


def signal_solid_angle(instrument: Instrument, cells=None) -> float:
    """Omega_S of the signal (module docstring): :func:`profiled_solid_angle` at the source distance
    D_S of each of ``cells`` ((tan eps, beta) pairs), the smallest. On an arc D_S is the same for every
    cell; on a fixed-height path D_S = height / cos eps, so Omega_S changes from cell to cell (and a
    narrow beam, which cuts a near disc more than a far one, need not be weakest at the farthest cell).
    Without cells: at ``length_m`` (the source overhead). User audit, session 43: a corridor design's
    signal was always that of tan eps 0 (0.51 x base where the cells asked, tan eps 10 and 12, got
    1.54 x)."""
    from roadgonio.instrument.optics import source_frames
    src = instrument.source
    if cells is None or src.radius_m == 0.0 or src.path == "arc":
        return profiled_solid_angle(instrument)         # an arc: the same D_S at every cell
    # D_S depends on eps alone: one placement per distinct tan eps, all at once (a 580-cell table has 29;
    # cell by cell this made a 60-point design 2.2x slower, bench/bench_design.py)
    tans = np.unique(np.asarray([t for t, _ in cells], dtype=np.float64))
    distances = np.unique(np.asarray(source_frames(instrument, tans, np.zeros_like(tans)).distance_m,
                                     dtype=np.float64).ravel())
    return min(profiled_solid_angle(instrument if d == src.length_m else
                                    instrument.with_changes(source={src.length_key: float(d)})) for d in distances)


def signal_product(instrument: Instrument, cells=None) -> float:
    """Omega_S G_D <k_D> (sr m^2 sr): the design's signal up to L_S rho cos(eps) / pi, Omega_S that of
    :func:`signal_solid_angle` over ``cells``."""
    return signal_solid_angle(instrument, cells) * detector_etendue(instrument) * mean_field_sensitivity(instrument)


def relative_signal(instrument: Instrument, base: Instrument, cells=None) -> float:
    """The design's signal relative to the base design's over the same ``cells`` (NaN if the base
    has none)."""
    b = signal_product(base, cells)
    return signal_product(instrument, cells) / b if b > 0 else math.nan


def deviations(k_a: np.ndarray, u: np.ndarray) -> dict[str, float | int]:
    """``max_abs_dev``, ``rms_dev``, the index of the worst entry (flat, over the finite k_A) and its
    standard uncertainty ``worst_u``, of arrays of k_A and its standard uncertainty of any shape;
    NaN entries (cells not requested) are ignored."""
    k = np.asarray(k_a, dtype=np.float64).ravel()
    s = np.asarray(u, dtype=np.float64).ravel()
    ok = np.isfinite(k)
    if not ok.any():
        return {"max_abs_dev": math.nan, "rms_dev": math.nan, "worst": -1, "worst_u": math.nan, "cells": 0}
    dev = np.where(ok, np.abs(k - 1.0), -np.inf)
    i = int(np.argmax(dev))
    return {"max_abs_dev": float(dev[i]), "rms_dev": float(np.sqrt(np.mean((k[ok] - 1.0) ** 2))),
            "worst": i, "worst_u": float(s[i]), "cells": int(ok.sum())}


def stray_metrics(stray_fraction: np.ndarray, k_a_direct: np.ndarray,
                  stray_se: np.ndarray | None = None) -> dict[str, float | int]:
    """``max_stray_fraction`` (over the finite entries), the flat index ``stray_worst`` of where it is
    (-1 when it is not above 0: no stray light, no cell to name) with its SE ``stray_u``, and
    ``max_abs_dev_direct`` = max |k_A,direct - 1|, of arrays of any shape (sample x tan eps x beta);
    NaN entries (cells not requested, or tables journaled before these were kept) are ignored, and
    all-NaN arrays give NaN."""
    sf = np.asarray(stray_fraction, dtype=np.float64).ravel()
    kd = np.asarray(k_a_direct, dtype=np.float64).ravel()
    se = np.full_like(sf, np.nan) if stray_se is None else np.asarray(stray_se, dtype=np.float64).ravel()
    out: dict[str, float | int] = {"max_stray_fraction": math.nan, "stray_worst": -1, "stray_u": math.nan,
                                   "max_abs_dev_direct": math.nan}
    ok = np.isfinite(sf)
    if ok.any():
        i = int(np.argmax(np.where(ok, sf, -np.inf)))
        out["max_stray_fraction"] = float(sf[i])
        if sf[i] > 0.0:
            out["stray_worst"], out["stray_u"] = i, float(se[i])
    okd = np.isfinite(kd)
    if okd.any():
        out["max_abs_dev_direct"] = float(np.max(np.abs(kd[okd] - 1.0)))
    return out


def pareto_front(signal: Sequence[float], dev: Sequence[float]) -> np.ndarray:
    """Indices of the non-dominated points (more signal and less deviation are better), by
    increasing signal; points with a non-finite value are left out."""
    s = np.asarray(signal, dtype=np.float64)
    d = np.asarray(dev, dtype=np.float64)
    idx = np.nonzero(np.isfinite(s) & np.isfinite(d))[0]
    order = idx[np.lexsort((d[idx], -s[idx]))]       # signal descending, then deviation ascending
    front, best = [], math.inf
    for i in order:
        if d[i] < best:
            front.append(i)
            best = d[i]
    return np.array(front[::-1], dtype=int)
