"""Angles and directions of road photometry (docs/conventions.md section 1).

Frame: sample in the plane z = 0, normal +z, origin at the nominal measurement point. Direction
vectors point away from the surface.

* Observation: elevation ``alpha`` above the surface, azimuth ``delta`` (0 by default):
  ``w_o = (cos a cos d, cos a sin d, sin a)``.
* Illumination: polar angle ``epsilon`` from the zenith and ``beta``, the angle between the
  vertical planes of observation and illumination; beta = 0 is the far (forward, specular) side.
  Source azimuth ``phi_i = delta + 180 deg - beta`` (:func:`source_azimuth_deg`, written only there):
  ``w_i = (sin e cos phi_i, sin e sin phi_i, cos e)``.

All functions are float64 numpy and broadcast over their arguments, except :func:`pair_angles`,
which is written over an array namespace ``xp`` so that the Dr.Jit plugins evaluate it too.
"""
from __future__ import annotations

import math

import numpy as np

#: The longest length of an instrument (distances, a finite focus, the sample's sides, a housing), m:
#: no goniophotometer is larger, and beyond it float arithmetic of the ray geometry overflows
#: (1e300 m) or loses the sample (float32 rays of the renderer).
MAX_LENGTH_M = 1000.0

#: Standard r-table grid (CIE 144): 29 rows of tan(epsilon)...
TAN_EPS_GRID = np.array([0, 0.25, 0.5, 0.75, 1, 1.25, 1.5, 1.75, 2, 2.5, 3, 3.5, 4, 4.5, 5, 5.5, 6,
                         6.5, 7, 7.5, 8, 8.5, 9, 9.5, 10, 10.5, 11, 11.5, 12], dtype=np.float64)
#: ... and 20 columns of beta in degrees.
BETA_GRID_DEG = np.array([0, 2, 5, 10, 15, 20, 25, 30, 35, 40, 45, 60, 75, 90, 105, 120, 135, 150,
                          165, 180], dtype=np.float64)
#: Standard observation elevation of the r-tables (deg).
ALPHA_STANDARD_DEG = 1.0


def nearest_grid_node(tan_eps: float, beta_deg: float) -> tuple[int, int, float]:
    """The (row, column) of the standard grid's node nearest to (tan eps, beta), and how far the
    cell is from it: the larger of |tan eps - the row's| and |beta - the column's| (deg). The one
    lookup of a cell on the grid; its callers judge the distance with their own tolerance
    (:func:`roadgonio.engines.cells.grid_index`; the labels of a correlation file,
    :func:`roadgonio.surface.rtable.read_cell_correlation`)."""
    i = int(np.argmin(np.abs(TAN_EPS_GRID - tan_eps)))
    j = int(np.argmin(np.abs(BETA_GRID_DEG - beta_deg)))
    return i, j, float(max(abs(TAN_EPS_GRID[i] - tan_eps), abs(BETA_GRID_DEG[j] - beta_deg)))


def w_detector(alpha_deg, delta_deg=0.0) -> np.ndarray:
    """Unit direction from the sample towards the detector, shape ``(..., 3)``."""
    a = np.radians(np.asarray(alpha_deg, dtype=np.float64))
    d = np.radians(np.asarray(delta_deg, dtype=np.float64))
    a, d = np.broadcast_arrays(a, d)
    return np.stack([np.cos(a) * np.cos(d), np.cos(a) * np.sin(d), np.sin(a)], axis=-1)


def w_source(eps_rad, beta_deg, delta_deg=0.0) -> np.ndarray:
    """Unit direction from the sample towards the source, shape ``(..., 3)``.

    ``eps_rad`` is the polar angle epsilon in radians (use :func:`eps_from_tan` for a tan eps
    grid); beta in degrees as in the r-tables.
    """
    e = np.asarray(eps_rad, dtype=np.float64)
    cos_phi, sin_phi = cos_sin_deg(source_azimuth_deg(beta_deg, delta_deg))
    e, cos_phi, sin_phi = np.broadcast_arrays(e, cos_phi, sin_phi)
    s = np.sin(e)
    return np.stack([s * cos_phi, s * sin_phi, np.cos(e)], axis=-1)


def cos_sin_deg(angle_deg) -> tuple[np.ndarray, np.ndarray]:
    """(cos, sin) of an angle in degrees, exact (0, +-1) at the multiples of 90 deg: the azimuth of
    the beta = 0 column, 180 deg, gave sin = 1.2e-16 through radians, so that column's beta came out
    1.2e-16 rad, not 0, and eq. 4's empirical term x^W with W ~ 1e15 at grazing incidence (R2, R4) lost
    8 % there (user audit, session 41)."""
    d = np.mod(np.asarray(angle_deg, dtype=np.float64), 360.0)
    q = np.round(d / 90.0)
    exact = d == 90.0 * q
    quarter = q.astype(np.int64) % 4
    rad = np.radians(d)
    c = np.where(exact, np.array([1.0, 0.0, -1.0, 0.0])[quarter], np.cos(rad))
    s = np.where(exact, np.array([0.0, 1.0, 0.0, -1.0])[quarter], np.sin(rad))
    return c, s


def source_azimuth_deg(beta_deg, delta_deg=0.0) -> np.ndarray:
    """Azimuth of the source direction, ``phi_i = delta + 180 deg - beta`` (deg): the one
    statement of the road-photometry azimuth convention (beta = 0 is the far side)."""
    return np.asarray(delta_deg, dtype=np.float64) + 180.0 - np.asarray(beta_deg, dtype=np.float64)


def source_azimuth_rad(beta_deg, delta_deg=0.0) -> np.ndarray:
    """:func:`source_azimuth_deg` in radians."""
    return np.radians(source_azimuth_deg(beta_deg, delta_deg))


def source_azimuth_tangent(beta_deg, delta_deg=0.0) -> np.ndarray:
    """Unit horizontal vector along which the source direction moves as its azimuth phi_i grows
    (i.e. as beta shrinks): ``d w_source / d phi_i / sin(eps)``, shape ``(..., 3)``."""
    cos_phi, sin_phi = cos_sin_deg(source_azimuth_deg(beta_deg, delta_deg))
    return np.stack([-sin_phi, cos_phi, np.zeros_like(cos_phi)], -1)


def beta_rotation(d_beta_deg) -> np.ndarray:
    """Rotations about the normal (shape ``(..., 3, 3)``) taking ``w_source(eps, beta)`` to
    ``w_source(eps, beta + d_beta)``: a turn of the azimuth by -d_beta (phi_i = delta + 180 - beta)."""
    a = -np.radians(np.asarray(d_beta_deg, dtype=np.float64))
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def source_cell(w, delta_deg=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`w_source` for unit vectors ``w`` (..., 3) above the surface:
    ``(tan eps, beta deg)`` with beta folded to [0, 180] (the road BRDF and the instrument are
    mirror symmetric about the plane of observation)."""
    w = np.asarray(w, dtype=np.float64)
    tan = np.hypot(w[..., 0], w[..., 1]) / w[..., 2]
    phi = np.degrees(np.arctan2(w[..., 1], w[..., 0]))
    beta = np.abs((np.asarray(delta_deg, dtype=np.float64) + 180.0 - phi + 180.0) % 360.0 - 180.0)
    return tan, beta


def pair_angles(xp, wi, wo, *, pole: float, supplement: bool = False):
    """(theta_i, theta_r, beta) in radians of ray pairs: ``wi``, ``wo`` component triples of unit
    vectors towards the source and the detector in the sample's frame (z the normal), over the
    array namespace ``xp`` (:class:`roadgonio.arrays.NumpyOps` or the Dr.Jit one). The one
    statement of the angles of a ray pair: theta from the normal, and beta, the angle between the
    vertical planes of illumination and observation (0 on the far side, as in
    :func:`source_azimuth_rad`), folded to [0, pi] and formed as
    ``atan2(|w_i x w_o|_z, -(w_i . w_o)_xy)``, exact near 0 and pi. Where the azimuth of either
    direction is undefined (theta_i = 0 or theta_r = 0) beta is ``pole``: each caller says what it
    needs there (the road BRDF pi, so its empirical term is 0; the correction surface 0).

    ``supplement=True`` adds a fourth array, pi - beta, formed as ``atan2(|w_i x w_o|_z,
    (w_i . w_o)_xy)`` (pi - ``pole`` where beta is the pole): near beta = pi it keeps the relative
    precision that ``pi - beta`` loses in float32, whose beta near pi carries an absolute error of
    half a unit of pi's last place (1.2e-7), i.e. a relative error 1.2e-7 / (pi - beta)."""
    wix, wiy, wiz = wi
    wox, woy, woz = wo
    sin_ti = xp.sqrt(wix * wix + wiy * wiy)
    sin_tr = xp.sqrt(wox * wox + woy * woy)
    theta_i = xp.atan2(sin_ti, wiz)
    theta_r = xp.atan2(sin_tr, woz)
    cross = xp.abs(wix * woy - wiy * wox)
    dot = wix * wox + wiy * woy
    defined = sin_ti * sin_tr > 1e-12
    beta = xp.where(defined, xp.atan2(cross, -dot), pole + 0.0 * (wiz + woz))
    if not supplement:
        return theta_i, theta_r, beta
    return theta_i, theta_r, beta, xp.where(defined, xp.atan2(cross, dot), (math.pi - pole) + 0.0 * (wiz + woz))


def eps_from_tan(tan_eps) -> np.ndarray:
    """epsilon (rad) from tan(epsilon)."""
    return np.arctan(np.asarray(tan_eps, dtype=np.float64))


def cos3_eps(tan_eps) -> np.ndarray:
    """cos^3(epsilon) from tan(epsilon), exact in float64: (1 + t^2)^(-3/2)."""
    t = np.asarray(tan_eps, dtype=np.float64)
    return (1.0 + t * t) ** -1.5
