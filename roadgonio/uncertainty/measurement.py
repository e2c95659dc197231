"""The measurement model of one trial: perturbed geometry -> reported r (paper section 4.1)."""
from __future__ import annotations

import math

import numpy as np

from roadgonio.errors import InputError
from roadgonio.geometry import (
    beta_rotation,
    cos3_eps,
    eps_from_tan,
    source_azimuth_tangent,
    source_cell,
    w_detector,
    w_source,
)
from roadgonio.instrument.config import Instrument
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import RoadModel, road_brdf
from roadgonio.surface.rtable import S1_CELLS, missing_ratio
from roadgonio.uncertainty.surrogate import N_COORDS
from roadgonio.uncertainty.cells import CellSet, standard_q0_weights
from roadgonio.uncertainty.spec import ILLUMINANCE

# ----------------------------------------------------------------------------------------------
# The measurement model of one trial
# ----------------------------------------------------------------------------------------------

def _rotations(tilt_x_deg: np.ndarray, tilt_y_deg: np.ndarray) -> np.ndarray:
    """R = R_y(tilt_y) R_x(tilt_x), shape (m, 3, 3)."""
    tx = np.radians(tilt_x_deg)
    ty = np.radians(tilt_y_deg)
    cx, sx, cy, sy = np.cos(tx), np.sin(tx), np.cos(ty), np.sin(ty)
    z, o = np.zeros_like(tx), np.ones_like(tx)
    rx = np.stack([np.stack([o, z, z], -1), np.stack([z, cx, -sx], -1), np.stack([z, sx, cx], -1)], -2)
    ry = np.stack([np.stack([cy, z, sy], -1), np.stack([z, o, z], -1), np.stack([-sy, z, cy], -1)], -2)
    return ry @ rx


class MeasurementModel:
    """r as the instrument reports it for error sets X (m, 7) over a cell set (module docstring)."""

    def __init__(self, model: RoadModel, instrument: Instrument, cells: CellSet,
                 illuminance: str = "nominal"):
        if illuminance not in ILLUMINANCE:
            raise InputError(f"unknown illuminance normalisation {illuminance!r}; expected nominal or measured",
                             field="illuminance")
        self.model = model
        # the perturbed instruments (misalignment) keep the nominal housing's box: the parts move
        # inside it (:func:`~roadgonio.instrument.enclosure.with_fixed_housing`)
        from roadgonio.instrument.enclosure import with_fixed_housing
        self.instrument = with_fixed_housing(instrument)
        self.cells = cells
        self.illuminance = illuminance
        self.alpha0 = instrument.observation.alpha_deg
        self.delta0 = instrument.observation.delta_deg
        #: the source's length: D_S of an arc, the height of a fixed-height path (every cell's D_S
        #: scales with it, so a distance error X[:, 5] changes E by (ds0 / (ds0 + X5))^2 on both)
        self.ds0 = instrument.source.length_m
        self.dd0 = instrument.detector.distance_m
        self.eps0 = eps_from_tan(cells.tan_eps)
        self.cos2 = 1.0 / (1.0 + cells.tan_eps ** 2)
        self.cos3 = cos3_eps(cells.tan_eps)
        # nominal source direction and its tangent basis (surrogate coordinates)
        self.wi0 = w_source(self.eps0, cells.beta_deg, self.delta0)
        self.e_eps = w_source(self.eps0 + 0.5 * math.pi, cells.beta_deg, self.delta0)  # d w / d eps
        self._w0T = np.ascontiguousarray(self.wi0.T)
        self._e0T = np.ascontiguousarray(self.e_eps.T)
        self._P = model.params.to_dict()
        self._terms = model.terms()
        self.e_phi = source_azimuth_tangent(cells.beta_deg, self.delta0)                 # d w / d phi_i
        w = standard_q0_weights()
        self.q0_w = w[cells.ii, cells.jj]
        self.i_20, self.i_00 = (cells.index(*c) for c in S1_CELLS)

    # -- directions ----------------------------------------------------------------------------
    def _directions(self, X: np.ndarray, rows) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
        """The components ``rows`` (a slice or index list of x, y, z) of the source directions,
        each (m, n), and of the detector direction, (m, len(rows)), in the sample frame
        (:meth:`local_directions`)."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        wo = w_detector(self.alpha0 + X[:, 0], self.delta0)                            # (m, 3)
        de = np.radians(X[:, 1])[:, None]
        Rt = np.swapaxes(_rotations(X[:, 3], X[:, 4]), -1, -2)[:, rows, :]
        A = Rt @ beta_rotation(X[:, 2])                                                # (m, r, 3)
        P = A @ self._w0T                                                              # (m, r, n)
        Q = A @ self._e0T
        cd, sd = np.cos(de), np.sin(de)
        wi = tuple(cd * P[:, k, :] + sd * Q[:, k, :] for k in range(P.shape[1]))
        return wi, np.einsum("mij,mj->mi", Rt, wo)

    def heights(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Only the z components of :meth:`local_directions` (source (m, n), detector (m,)): what
        the geometry check of every trial needs, at a third of the work."""
        (wiz,), woz = self._directions(X, [2])
        return wiz, woz[:, 0]

    def local_directions(self, X: np.ndarray) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
        """Source and detector directions in the sample frame: ``((wix, wiy, wiz), (wox, woy, woz))``,
        source components (m, n), detector components (m, 1).

        Exact rotations, no small-angle approximation: moving the source by d_eps along its
        meridian is ``w(eps0 + d) = cos d w(eps0) + sin d w(eps0 + 90 deg)`` (both from
        :func:`~roadgonio.geometry.w_source`), a beta error d_beta is the rotation about the normal
        :func:`~roadgonio.geometry.beta_rotation`, and the tilt applies ``R^T``.
        """
        wi, wol = self._directions(X, slice(None))
        return wi, tuple(wol[:, k:k + 1] for k in range(3))

    def r_measured(self, X: np.ndarray, dirs=None) -> np.ndarray:
        """r_meas without the aperture effect, (m, n) in sr^-1 (module docstring)."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        wi, wo = self.local_directions(X) if dirs is None else dirs
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            f = road_brdf(NumpyOps, self._P, wi, wo, self.model.variant, self._terms)
        f = np.broadcast_to(f, wi[2].shape)
        if self.illuminance == "nominal":
            ds = self.ds0 + X[:, 5]
            return f * wi[2] * ((self.ds0 / ds) ** 2)[:, None] * self.cos2[None, :]
        return f * self.cos3[None, :]

    def surrogate_coords(self, X: np.ndarray, dirs=None) -> tuple[np.ndarray, np.ndarray]:
        """Surrogate coordinates (m, n, 5) (see :mod:`roadgonio.uncertainty.surrogate`) and the source
        directions turned so the detector azimuth is delta0 (m, n, 3)."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        (wix, wiy, wiz), (wox, woy, woz) = self.local_directions(X) if dirs is None else dirs
        alpha = np.degrees(np.arcsin(np.clip(woz[:, 0], -1.0, 1.0)))
        gamma = math.radians(self.delta0) - np.arctan2(woy, wox)                      # (m, 1)
        c, s = np.cos(gamma), np.sin(gamma)
        wr = np.stack([c * wix - s * wiy, s * wix + c * wiy, wiz], -1)
        x = np.empty(wr.shape[:2] + (N_COORDS,))
        x[..., 0] = (alpha - self.alpha0)[:, None]
        x[..., 1:3] = self._tangent(wr)
        x[..., 3] = X[:, 5][:, None]
        x[..., 4] = X[:, 6][:, None]
        return x, wr

    def _tangent(self, w: np.ndarray) -> np.ndarray:
        d = w - self.wi0
        return np.degrees(np.stack([np.sum(d * self.e_eps, -1), np.sum(d * self.e_phi, -1)], -1))

    def dirs_from_offsets(self, off_eps_deg: float, off_phi_deg: float) -> np.ndarray:
        """Unit source directions (n, 3) offset from the nominal ones along e_eps, e_phi."""
        w = self.wi0 + math.radians(off_eps_deg) * self.e_eps + math.radians(off_phi_deg) * self.e_phi
        return w / np.linalg.norm(w, axis=-1, keepdims=True)

    def cells_of(self, w: np.ndarray) -> list[tuple[float, float]]:
        """(tan eps, beta deg) of source directions w (n, 3) in a frame where the detector azimuth
        is delta0; beta folded to [0, 180] (the BRDF and the instrument are mirror symmetric)."""
        tan, beta = source_cell(w, self.delta0)
        return [(float(t), float(b)) for t, b in zip(tan, beta)]

    def functionals(self, r: np.ndarray) -> np.ndarray:
        """(m, n) -> (m, n + 2): the cells, then Q0 and S1."""
        q0 = r @ self.q0_w
        s1 = missing_ratio(r[:, self.i_20], r[:, self.i_00])       # NaN (missing) where r(0, 0) <= 0
        return np.concatenate([r, q0[:, None], s1[:, None]], axis=1)


