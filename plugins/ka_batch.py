"""The batched k_A integrator as a Mitsuba 3 Python plugin (plugin name ``kabatch``): the detector
signal S[f_road] and S[f_lambert] (docs/conventions.md section 5, paper eq. 3) of **many cells per launch**.

What a cell is made of (docs/conventions.md section 4), all Mitsuba objects:

* the detector: the ``lummeter`` sensor of the scene (:mod:`.lummeter`); its rays are traced once
  per launch with ``scene.ray_intersect`` and must all hit the sample (a ray that misses is counted
  and reported, never silently dropped);
* the sample: the scene's ``sample`` shape with its ``roadbsdf`` BSDF (:mod:`.road_bsdf`) in the
  ``road_lambert`` channels, so every contribution carries f_road (R) and 1/pi (G) from the same rays;
* the source of each cell: a ``disk`` shape with a uniform ``area`` emitter of radius R_S, centred at
  D_S w_i(eps, beta) and facing the sample centre (a ``point`` emitter when R_S = 0).

Every cell's source is one rigid placement of the same disc: the integrator holds **one** area
emitter at a canonical placement (centre at the origin, normal +z) and, per cell, the rigid frame
(centre c, axes s, t, a; float32 arrays, one entry per cell). A hit point p is expressed in the
cell's source frame, p' = (s.(p-c), t.(p-c), a.(p-c)), the area emitter samples its disc as seen
from p' (``Emitter.sample_direction``: uniform on the disc area, weight L cos theta_s A / d^2), and
the sampled direction and point go back to the world frame. Distances and angles are invariant under
the rigid motion, so this is exactly the emitter placed at the cell, without one emitter object (and
one virtual call) per cell. A source with a beam profile (docs/conventions.md section 4.1) weighs the
sample by its relative radiance ``A(rho) P(theta)`` at the sampled point in the sampled direction,
:func:`roadgonio.instrument.optics.source_radiance_factor` over Dr.Jit arrays in the canonical frame
(axis +z, disc coordinates = the sampled point / R_S): the numpy backends' formula. The BSDF is evaluated for the world direction, and a shadow ray to the
sampled source point is traced through the scene wherever the scene can occlude (XML scenes with
holders, housings, baffles; mesh samples); the per-cell sources are not part of the scene, so they
never shade each other.

Sample points: the launch evaluates randomly shifted rank-1 lattices
(:mod:`roadgonio.engines.mitsuba.lattice`): point j of replicate b is
u = frac(((j z) mod n) / n + Delta_b) in [0, 1)^6 (pupil 2, field 2, source 2); the lattice size n,
the generating vector z and the shifts are opaque kernel parameters (no recompilation between
passes or instruments). Per replicate the ``n`` detector rays are traced once and shared by every
cell of the launch; every (replicate, cell) pair is a block of n lanes whose road and Lambert sums
are reduced on the device (``dr.block_sum`` over bins of at most 2^12 lanes, float32, in a fixed
order: a run repeats bit for bit) and returned to the host, which accumulates them in float64
(:mod:`roadgonio.engines.mitsuba.passes`).

:meth:`KaBatch.sample` is the same shading for one cell (:attr:`KaBatch.cell`) as an ordinary
``SamplingIntegrator``, so ``mi.render`` with this integrator renders the signal of one cell
(tests/plugin/test_engine.py compares it with the batched sums and with Mitsuba's ``direct`` integrator).

Registration: :func:`roadgonio.engines.mitsuba.plugins.register_plugins` after ``set_variant``.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from roadgonio.engines.mitsuba.ops import DrJitOps
from roadgonio.errors import BackendError
from roadgonio.instrument.optics import source_radiance_factor

#: Lanes summed per device bin (float32); the host sums bins in float64.
BIN_LOG2 = 12
#: Data stored per detector ray between the ray kernel and the shading kernel: hit point,
#: geometric and shading normals, ray direction, detector weight...
RAY_FIELDS = ("px", "py", "pz", "nx", "ny", "nz", "sx", "sy", "sz", "dx", "dy", "dz", "w")
#: ... and for a flat sample in the plane z = 0 (both normals +z) without the normals.
FLAT_RAY_FIELDS = ("px", "py", "pz", "dx", "dy", "dz", "w")


def _u32(values) -> mi.UInt32:
    return mi.UInt32(np.ascontiguousarray(values, dtype=np.uint32))


def _f32(values) -> mi.Float:
    return mi.Float(np.ascontiguousarray(values, dtype=np.float32))


class KaBatch(mi.SamplingIntegrator):
    """Batched k_A integrator (see the module docstring)."""

    def __init__(self, props):
        mi.SamplingIntegrator.__init__(self, props)
        #: trace shadow rays (False only where nothing can occlude the source: a flat sample alone)
        self.shadow = bool(props.get("shadow", True)) if "shadow" in props else True
        #: the sample is the flat rectangle z = 0 facing +z (no normals stored per ray)
        self.flat = bool(props.get("flat", False)) if "flat" in props else False
        self.emitter = None         # the canonical source (area emitter of a disk, or point emitter)
        self.frames = None          # 12 mi.Float arrays: c, s, t, a of every cell's source
        self.n_cells = 0
        #: the cell shaded by :meth:`sample` (index into the frames)
        self.cell = dr.opaque(mi.UInt32, 0)
        self.bsdf = None
        self.sample_shape = None
        self.profile = None         # (beam, aperture, 1 / R_S) for Dr.Jit, or None: a uniform source

    # -- set-up --------------------------------------------------------------------------------
    def set_sample(self, shape) -> None:
        """The sample shape (its BSDF is evaluated at every detector hit)."""
        self.sample_shape = shape
        self.bsdf = shape.bsdf()

    def set_source(self, emitter, shape=None) -> None:
        """The canonical source: the area emitter of a disk centred at the origin with normal +z
        (radius R_S) and that disk ``shape``, or a point emitter at the origin. The shape is kept
        here: an area emitter only points back to its shape, which must outlive it."""
        self.emitter = emitter
        self._source_shape = shape

    def set_profile(self, source) -> None:
        """The beam profile of the instrument's ``source`` (:class:`~roadgonio.instrument.config.Source`),
        as kernel parameters: its numbers opaque (a new width reuses the kernel), its tables device
        arrays; the kinds of profile are structural. Nothing for a uniform source (bit for bit as
        before)."""
        self.profile = None if not source.profiled else (
            jit_beam(source.beam), jit_aperture(source.aperture),
            dr.opaque(mi.Float, 1.0 / source.radius_m if source.radius_m > 0 else 0.0))

    def set_cells(self, frames: np.ndarray) -> None:
        """Source frames of the cells, float64 (n_cells, 12): centre, s, t, axis (the axis points
        from the source towards the sample centre, the centre is D_S times minus the axis). Only the
        axis goes to the device: the kernel rebuilds the frame from it
        (:func:`frame_from_axis`, the rule of :func:`roadgonio.engines.mitsuba.engine.source_frames`)."""
        frames = np.asarray(frames, dtype=np.float64)
        if frames.ndim != 2 or frames.shape[1] != 12:
            raise BackendError(f"expected source frames of shape (cells, 12), got {frames.shape}")
        axis = frames[:, 9:12]
        dist = np.linalg.norm(frames[:, 0:3], axis=1)
        if len(frames) and (np.ptp(dist) > 1e-9 * max(dist.max(), 1.0)
                            or np.abs(frames[:, 0:3] + dist[:, None] * axis).max() > 1e-9 * max(dist.max(), 1.0)):
            raise BackendError("the source frames must be centred at one distance along minus their axes")
        # gathered per lane, so these are never loaded contiguously (no alignment-dependent kernels)
        self.frames = [_f32(axis[:, k]) for k in range(3)]
        self.distance = dr.opaque(mi.Float, float(dist[0]) if len(dist) else 0.0)
        self.n_cells = len(frames)

    # -- shading -------------------------------------------------------------------------------
    def shade(self, scene, si, cell, u, active):
        """Road (x) and Lambert (y) contributions (``mi.Color3f``) of the source of ``cell`` at the
        hits ``si``, for the unit-square source samples ``u``; without the detector weight."""
        a = mi.Vector3f(*[dr.gather(mi.Float, v, cell, active) for v in self.frames])
        s, t = frame_from_axis(a)
        c = -self.distance * a
        v = mi.Vector3f(si.p) - c
        local = dr.zeros(mi.SurfaceInteraction3f)
        local.p = mi.Point3f(dr.dot(s, v), dr.dot(t, v), dr.dot(a, v))
        local.n = mi.Normal3f(dr.dot(s, si.n), dr.dot(t, si.n), dr.dot(a, si.n))
        local.time = si.time
        local.wavelengths = si.wavelengths
        ds, weight = self.emitter.sample_direction(local, u, active)
        active = active & (ds.pdf > 0.0)
        if self.profile is not None:
            # the source's relative radiance at the sampled point, in the canonical frame (axis +z)
            beam, aperture, inv_r = self.profile
            factor = source_radiance_factor(DrJitOps, beam, aperture, (ds.d.x, ds.d.y, ds.d.z),
                                            (0.0, 0.0, 1.0), (ds.p.x * inv_r, ds.p.y * inv_r))
            weight = weight * factor
        d = s * ds.d.x + t * ds.d.y + a * ds.d.z
        p_src = c + s * ds.p.x + t * ds.p.y + a * ds.p.z
        ctx = mi.BSDFContext()
        value = self.bsdf.eval(ctx, si, si.to_local(d), active)
        if self.shadow:
            active = active & ~scene.ray_test(si.spawn_ray_to(mi.Point3f(p_src)), active)
        return dr.select(active, value * weight, 0.0)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        """``SamplingIntegrator`` interface: the signal of the cell :attr:`cell` along ``ray``."""
        si = scene.ray_intersect(ray, active)
        hit = active & si.is_valid() & (si.shape == dr.opaque(mi.ShapePtr, self.sample_shape))
        cell = mi.UInt32(0) + self.cell
        value = self.shade(scene, si, cell, sampler.next_2d(hit), hit)
        return mi.Spectrum(value), hit, []

    def aov_names(self):
        return []

    # -- batched launches ----------------------------------------------------------------------
    @staticmethod
    def _lattice(j, rep, lattice, dims):
        """Lattice coordinates ``dims`` of point j of replicate ``rep`` (see the module docstring)."""
        out = []
        for d in dims:
            shift = dr.gather(mi.Float, lattice["shift"][d], rep)
            v = mi.Float((j * lattice["z"][d]) & lattice["mask"]) * lattice["inv_n"] + shift
            v = v - dr.floor(v)
            if lattice.get("tent"):
                v = 1.0 - dr.abs(2.0 * v - 1.0)       # baker's transform (periodises the integrand)
            out.append(v)
        return out

    @staticmethod
    def lattice_params(n: int, z, shifts: np.ndarray, tent: bool = False) -> dict:
        """See :func:`lattice_params`."""
        return lattice_params(n, z, shifts, tent)

    def trace_detector(self, scene, sensor, lattice: dict, reps: int) -> tuple[dict, int]:
        """Trace the n x ``reps`` detector rays of a lattice (replicates 0 ... reps-1 of
        ``lattice["shift"]``); returns the evaluated per-ray data and the number of rays that
        missed the sample."""
        i = dr.arange(mi.UInt32, int(reps) * lattice["n"])
        j = i & lattice["mask"]
        rep = i >> lattice["shift_log2"]
        u0, u1, u2, u3 = self._lattice(j, rep, lattice, (0, 1, 2, 3))
        # lummeter: sample2 = film position -> field disc, sample3 = aperture -> pupil disc
        ray, w = sensor.sample_ray(0.0, 0.0, mi.Point2f(u2, u3), mi.Point2f(u0, u1))
        # a flat sample needs only the hit point (its normals are +z); otherwise the shading frame too
        flags = mi.RayFlags.Minimal if self.flat else (mi.RayFlags.Minimal | mi.RayFlags.ShadingFrame)
        si = scene.ray_intersect(ray, flags, False)
        hit = si.is_valid() & (si.shape == dr.opaque(mi.ShapePtr, self.sample_shape))
        w = dr.select(hit, mi.Float(w.x), 0.0)
        if self.flat:
            data = dict(zip(FLAT_RAY_FIELDS, (si.p.x, si.p.y, si.p.z, ray.d.x, ray.d.y, ray.d.z, w)))
        else:
            ns = si.sh_frame.n
            data = dict(zip(RAY_FIELDS, (si.p.x, si.p.y, si.p.z, si.n.x, si.n.y, si.n.z, ns.x, ns.y, ns.z,
                                         ray.d.x, ray.d.y, ray.d.z, w)))
        miss = ~hit
        dr.eval(data, miss)                 # one kernel traces the rays; the count reads the stored mask
        return data, int(dr.count(miss)[0]) if dr.width(miss) else 0

    def block_sums(self, scene, rays: dict, lattice: dict, block_cell: np.ndarray,
                   block_rep: np.ndarray) -> np.ndarray:
        """Road and Lambert sums over the blocks (float32 numpy, (blocks, bins per block, 2)):
        block k is the n lattice points of replicate ``block_rep[k]`` (an index into ``rays``) for
        the source of cell ``block_cell[k]``."""
        n, log2n = lattice["n"], lattice["log2n"]
        blocks = len(block_cell)
        lanes = blocks * n
        if lanes >= 1 << 32:
            raise BackendError(f"a launch of {lanes} lanes exceeds 2^32; split it")
        bin_log2 = min(log2n, BIN_LOG2)
        l = dr.arange(mi.UInt32, lanes)
        k = l >> lattice["shift_log2"]
        j = l & lattice["mask"]
        cell = dr.gather(mi.UInt32, _u32(block_cell), k)
        rep = dr.gather(mi.UInt32, _u32(block_rep), k)
        r = (rep << lattice["shift_log2"]) + j
        g = {key: dr.gather(mi.Float, rays[key], r) for key in rays}
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.t = mi.Float(1.0)
        si.p = mi.Point3f(g["px"], g["py"], g["pz"])
        if self.flat:
            si.n = mi.Normal3f(0.0, 0.0, 1.0)
            si.sh_frame = mi.Frame3f(mi.Vector3f(1.0, 0.0, 0.0), mi.Vector3f(0.0, 1.0, 0.0), mi.Vector3f(0.0, 0.0, 1.0))
        else:
            si.n = mi.Normal3f(g["nx"], g["ny"], g["nz"])
            si.sh_frame = mi.Frame3f(mi.Vector3f(g["sx"], g["sy"], g["sz"]))
        si.wi = si.sh_frame.to_local(-mi.Vector3f(g["dx"], g["dy"], g["dz"]))
        active = g["w"] > 0.0
        u4, u5 = self._lattice(j, rep, lattice, (4, 5))
        value = self.shade(scene, si, cell, mi.Point2f(u4, u5), active) * g["w"]
        # evaluated block sums, not atomic scatters: the order of the float32 additions is then fixed,
        # so a run repeats bit for bit whatever the thread count
        road, lam = mi.Float(value.x), mi.Float(value.y)
        dr.eval(road, lam)                                   # one kernel for both channels
        sums = [dr.block_sum(v, 1 << bin_log2, mode="evaluated") for v in (road, lam)]
        out = np.stack([np.array(sums[0], dtype=np.float32), np.array(sums[1], dtype=np.float32)], axis=-1)
        return out.reshape(blocks, n >> bin_log2, 2)

    def to_string(self):
        return f"KaBatch[cells={self.n_cells}, shadow={self.shadow}]"


def frame_from_axis(a):
    """Unit vectors (s, t) completing the unit axis ``a`` to a right-handed frame, on the device:
    s = normalise(h x a) with h = +z, or +x when |a_z| >= 0.9; t = a x s."""
    use_z = dr.abs(a.z) < 0.9
    h = mi.Vector3f(dr.select(use_z, 0.0, 1.0), 0.0, dr.select(use_z, 1.0, 0.0))
    s = dr.normalize(dr.cross(h, a))
    return s, dr.cross(a, s)


class _JitTable:
    """A :class:`~roadgonio.instrument.profiles.UniformTable` for kernels: values on the device,
    origin and step opaque, the size structural."""

    def __init__(self, table):
        self.values = mi.Float(np.ascontiguousarray(table.values, dtype=np.float32))
        self.x0 = dr.opaque(mi.Float, float(table.x0))
        self.step = dr.opaque(mi.Float, float(table.step))
        self.n = int(table.n)


class _JitProfile:
    """A beam or aperture profile with its numbers as opaque kernel parameters (same attributes)."""

    def __init__(self, profile, **numbers):
        self.kind = profile.kind
        self.uniform = profile.uniform
        for k, v in numbers.items():
            setattr(self, k, dr.opaque(mi.Float, float(v)))
        self.table = None if profile.table is None else _JitTable(profile.table)


def jit_beam(beam):
    """:class:`~roadgonio.instrument.profiles.BeamProfile` for Dr.Jit kernels."""
    return _JitProfile(beam, sigma_rad=beam.sigma_rad if np.isfinite(beam.sigma_rad) else 1e30, power=beam.power,
                       theta_end_rad=beam.theta_end_rad)


def jit_aperture(aperture):
    """:class:`~roadgonio.instrument.profiles.ApertureProfile` for Dr.Jit kernels."""
    return _JitProfile(aperture, edge=aperture.edge)


_LATTICE_CACHE: dict = {}


def lattice_params(n: int, z, shifts: np.ndarray, tent: bool = False) -> dict:
    """Opaque kernel parameters of a lattice of size n (a power of two) with generating vector z
    and shifts (replicates, 6); ``tent`` applies the baker's transform to every coordinate. The
    per-size constants are made once per variant (opaque values are device allocations)."""
    log2n = int(n).bit_length() - 1
    key = (mi.variant(), int(n), tuple(int(v) for v in z))
    if key not in _LATTICE_CACHE:
        _LATTICE_CACHE[key] = {"n": int(n), "log2n": log2n, "mask": dr.opaque(mi.UInt32, int(n) - 1),
                               "inv_n": dr.opaque(mi.Float, 1.0 / n), "shift_log2": dr.opaque(mi.UInt32, log2n),
                               "z": [dr.opaque(mi.UInt32, int(v) & 0xFFFFFFFF) for v in z]}
    return {**_LATTICE_CACHE[key], "tent": bool(tent),
            "shift": [_f32(shifts[:, d]) for d in range(shifts.shape[1])]}


def canonical_source(radius_m: float, radiance: float):
    """The canonical source of :class:`KaBatch`: a disk of radius ``radius_m`` at the origin with
    normal +z carrying a uniform area emitter (returns the emitter), or for radius 0 a point
    emitter of intensity ``radiance`` at the origin."""
    if radius_m > 0.0:
        shape = mi.load_dict({"type": "disk",
                              "to_world": mi.ScalarTransform4f().scale([radius_m, radius_m, 1.0]),
                              "emitter": {"type": "area", "radiance": {"type": "uniform", "value": radiance}}})
        return shape.emitter(), shape
    em = mi.load_dict({"type": "point", "position": [0.0, 0.0, 0.0],
                       "intensity": {"type": "uniform", "value": radiance}})
    return em, None


def source_frames(centres, s, t, axes) -> np.ndarray:
    """Stack per-cell source frames (each (cells, 3), float64) into the (cells, 12) layout."""
    return np.concatenate([np.asarray(v, dtype=np.float64) for v in (centres, s, t, axes)], axis=1)


