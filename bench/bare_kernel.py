"""The limit for bench/bench_engine.py: a bare Dr.Jit kernel of the same integrand as the batched
Mitsuba engine, written from the project's own optics and model code (no Mitsuba scene, no
plugins, no ray tracing): per (lattice point, cell) lane the pupil, field and source points
(:func:`roadgonio.instrument.optics.concentric_disc`), the detector ray and its etendue weight
(:func:`~roadgonio.instrument.optics.detector_ray`), the hit on the plane z = 0
(:func:`~roadgonio.instrument.optics.hit_plane`), the source coupling G, the road BRDF
(:func:`roadgonio.surface.model.road_brdf` with :class:`roadgonio.engines.mitsuba.ops.DrJitOps`), and
the same per-block device sums. It handles the flat rectangular sample only (what the scene would
ray-trace) and uses the same lattices and shifts, so on the same cells and plan its k_A agrees with
the engine's to float32 rounding (checked by the bench).
"""
from __future__ import annotations

import math

import numpy as np


class BareKernel:
    """Signal sums of many cells per launch, without Mitsuba (module docstring)."""

    def __init__(self, instrument, model):
        import drjit as dr
        import mitsuba as mi

        from roadgonio.engines.mitsuba.plugins.lummeter import jit_geometry
        from roadgonio.instrument.optics import detector_geometry
        self.dr, self.mi = dr, mi
        self.instrument, self.model = instrument, model
        self.geo = jit_geometry(detector_geometry(instrument))
        self.P = {k: dr.opaque(mi.Float, v) for k, v in model.params.to_dict().items()}
        self.terms = model.terms()
        self.radius = dr.opaque(mi.Float, instrument.source.radius_m)

    def set_cells(self, place) -> None:
        """The cells' source discs: :func:`roadgonio.instrument.optics.source_frames` of the cells
        (centre, s, t, axis: 12 float32 arrays)."""
        mi = self.mi
        frames = np.concatenate([place.centre, place.s, place.t, place.axis], axis=1)
        self.frames = [mi.Float(np.ascontiguousarray(frames[:, k], dtype=np.float32)) for k in range(12)]

    def block_sums(self, lattice: dict, block_cell: np.ndarray, block_rep: np.ndarray) -> np.ndarray:
        dr, mi = self.dr, self.mi
        from roadgonio.engines.mitsuba.ops import DrJitOps as xp
        from roadgonio.engines.mitsuba.plugins.ka_batch import BIN_LOG2, KaBatch
        from roadgonio.instrument import optics
        from roadgonio.surface.model import road_brdf
        n, log2n = lattice["n"], lattice["log2n"]
        lanes = len(block_cell) * n
        l = dr.arange(mi.UInt32, lanes)
        k = l >> lattice["shift_log2"]
        j = l & lattice["mask"]
        cell = dr.gather(mi.UInt32, mi.UInt32(np.asarray(block_cell, dtype=np.uint32)), k)
        rep = dr.gather(mi.UInt32, mi.UInt32(np.asarray(block_rep, dtype=np.uint32)), k)
        u = KaBatch._lattice(j, rep, lattice, range(6))
        pupil = optics.concentric_disc(xp, u[0], u[1])
        field = optics.concentric_disc(xp, u[2], u[3])
        o, d, w = optics.detector_ray(xp, self.geo, pupil, field)
        x, y, valid = optics.hit_plane(xp, o, d)
        f = [dr.gather(mi.Float, a, cell) for a in self.frames]
        dx, dy = optics.concentric_disc(xp, u[4], u[5])
        sp = tuple(f[i] + self.radius * (dx * f[3 + i] + dy * f[6 + i]) for i in range(3))
        vx, vy, vz = sp[0] - x, sp[1] - y, sp[2]
        d2 = vx * vx + vy * vy + vz * vz
        inv = dr.rsqrt(d2)
        wi = (vx * inv, vy * inv, vz * inv)
        cos_s = -(wi[0] * f[9] + wi[1] * f[10] + wi[2] * f[11])
        g = dr.select(valid & (wi[2] > 0.0) & (cos_s > 0.0), wi[2] * cos_s / d2, 0.0)
        fr = road_brdf(xp, self.P, wi, (-d[0], -d[1], -d[2]), self.model.variant, self.terms)
        wg = w * g
        bin_log2 = min(log2n, BIN_LOG2)
        out = dr.zeros(mi.Float, 2 * (lanes >> bin_log2))
        b = (l >> dr.opaque(mi.UInt32, bin_log2)) * 2
        dr.scatter_reduce(dr.ReduceOp.Add, out, wg * fr, b, mode=dr.ReduceMode.Local)
        dr.scatter_reduce(dr.ReduceOp.Add, out, wg * (1.0 / math.pi), b + 1, mode=dr.ReduceMode.Local)
        return np.array(out, dtype=np.float32).reshape(len(block_cell), n >> bin_log2, 2)
