"""The batched k_A integrator as a Mitsuba 3 Python plugin (plugin name ``kabatch``): the detector
signal S[f_road] and S[f_lambert] (docs/conventions.md section 5, paper eq. 3) of **many cells per launch**.

What a cell is made of (docs/conventions.md section 4), all Mitsuba objects:

* the detector: the ``lummeter`` sensor of the scene (:mod:`.lummeter`); its rays are traced once
  per launch with ``scene.ray_intersect`` and must all hit the sample (a ray that misses is counted
  and reported, never silently dropped);
* the sample: the scene's ``sample`` shape with its ``roadbsdf`` BSDF (:mod:`.road_bsdf`) in the
  ``road_lambert`` channels, so every contribution carries f_road (R) and 1/pi (G) from the same rays;
* the source of each cell: a ``disk`` shape with a uniform ``area`` emitter of radius R_S, centred at
  D_S w_i(eps, beta) and facing the sample centre (a ``point`` emitter when R_S = 0, weighted by
  cos theta_s about the axis: the limit of a small Lambertian disc, docs/conventions.md section 5).

Every cell's source is one rigid placement of the same disc: the integrator holds **one** area
emitter at a canonical placement (centre at the origin, normal +z) and, per cell, the axis a and
D_S (float32 arrays, one entry per cell), from which the kernel builds the rigid frame: centre
c = -D_S a and axes s, t (:func:`frame_from_axis`). A hit point p is expressed in the
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

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from roadgonio.engines.mitsuba.ops import DrJitOps
from roadgonio.errors import BackendError
from roadgonio.instrument.optics import source_radiance_factor


#: The shadow ray from the source towards a lit point stops this fraction of their distance short of
#: the point (:func:`shadow_ray`): 10 um at 1 m, where float32 puts the plane's intersection within
#: ~1 um even at tan eps 12, so the point's own surface is not hit.
SHADOW_END_REL = 1e-5


def shadow_ray(p_hit, p_src):
    """The shadow ray between a lit point ``p_hit`` of the sample and a source point ``p_src``, traced
    from the source (which lies on no shape of the scene) and stopped SHADOW_END_REL of the distance short of
    the point. ``SurfaceInteraction.spawn_ray_to`` instead lifts its origin off the surface by
    Mitsuba's ray epsilon times (1 + |p|), ~1e-4 m: a part shading the footprint stood 0.1 mm
    lower, and k_A was 1-2e-4 low, 12-25 of its SEs at a tight target (user audit: the holder
    preset at tan eps 12, beta 0, rel-se 1e-5: 1.044140 +- 4.7e-6 against an independent float64
    1.044252)."""
    src = mi.Point3f(p_src)
    v = mi.Vector3f(p_hit) - mi.Vector3f(src)
    dist = dr.norm(v)
    ray = mi.Ray3f(src, v / dist)
    ray.maxt = dist * (1.0 - SHADOW_END_REL)
    return ray

#: Lanes summed per device bin (float32); the host sums bins in float64.
BIN_LOG2 = 12
#: Data stored per detector ray between the ray kernel and the shading kernel: hit point,
#: geometric and shading normals, ray direction, detector weight...
RAY_FIELDS = ("px", "py", "pz", "nx", "ny", "nz", "sx", "sy", "sz", "dx", "dy", "dz", "w")
#: ... and for a flat sample in the plane z = 0 (both normals +z) without the normals.
FLAT_RAY_FIELDS = ("px", "py", "pz", "dx", "dy", "dz", "w")


#: A ray that misses the sample is traced once more from an origin moved sideways by this fraction of
#: its distance from the origin of the scene (about 8 float32 ulps): Embree's ray-triangle test is
#: not watertight, so a ray that lands exactly on an edge or a vertex shared by two triangles of the
#: sample mesh (common in symmetric scan meshes, and the rectangle's own diagonal passes the sample
#: centre, where a focused detector's rays meet) can slip between them. A ray that really misses
#: the sample misses it again.
RETRY_NUDGE = 1e-6


def intersect_sample(scene, ray, flags, sample_shape, active=True):
    """``(si, hit)``: the first intersection of ``ray`` and whether it is on ``sample_shape``,
    with the one retry of :data:`RETRY_NUDGE` for a ray that slipped through an edge."""
    sample = dr.opaque(mi.ShapePtr, sample_shape)
    si = scene.ray_intersect(ray, flags, False, active)
    hit = si.is_valid() & (si.shape == sample)
    retry = active & ~hit
    s, t = mi.coordinate_system(ray.d)
    # the crack is as wide as a few ulps of the triangles' coordinates: for a sample mesh larger than the
    # distance to the origin (400 m, a 2x2 grid with a vertex at the centre: user audit, session 45) the
    # nudge scales with the sample's extent (0.4 mm there, against a footprint of centimetres)
    extent = _extent(sample_shape)
    scale = dr.maximum(dr.norm(mi.Vector3f(ray.o)), 1.0)
    nudge = RETRY_NUDGE * (dr.maximum(scale, extent) if extent > 1.0 else scale)
    ray2 = mi.Ray3f(ray.o + (s + t) * nudge, ray.d)
    si2 = scene.ray_intersect(ray2, flags, False, retry)
    hit2 = retry & si2.is_valid() & (si2.shape == sample)
    return dr.select(hit2, si2, si), hit | hit2


def _extent(shape) -> float:
    """The diagonal of ``shape``'s bounding box (m)."""
    bb = shape.bbox()
    return float(dr.norm(bb.max - bb.min))


class _Deferred:
    """A value still being computed on the device (``defer=True`` of the launch methods): calling it
    waits for the kernels and returns it. Dr.Jit's LLVM backend launches asynchronously (so does
    CUDA), so Python traces the next kernel while this one runs."""

    def __init__(self, read):
        self._read = read

    def __call__(self):
        return self._read()


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
        self.point = False          # a point emitter (R_S = 0): see set_source
        self.frames = None          # 12 mi.Float arrays: c, s, t, a of every cell's source
        self.n_cells = 0
        #: the cell shaded by :meth:`sample` (index into the frames)
        self.cell = dr.opaque(mi.UInt32, 0)
        self.bsdf = None
        self.sample_shape = None
        #: stray light (:meth:`set_parts`): the reflecting parts and the reflections per path
        self.parts = []
        self.max_bounces = 1
        self.light_depth = 0
        self.profile = None         # (beam, aperture, 1 / R_S) for Dr.Jit, or None: a uniform source
        self.cos_beam = None        # cos of the source's beam half-angle (a hard cone), or None: no cone
        #: the light paths' reflection at their first vertex l_1 samples the part's own BSDF (True;
        #: the road's forward lobe) or a cosine-distributed direction (False: the former strategy,
        #: kept so that the tests can compare the two estimators)
        self.light_lobe = True

    # -- set-up --------------------------------------------------------------------------------
    def set_sample(self, shape) -> None:
        """The sample shape (its BSDF is evaluated at every detector hit)."""
        self.sample_shape = shape
        self.bsdf = shape.bsdf()

    def set_source(self, emitter) -> None:
        """The canonical source: the area emitter of a disk centred at the origin with normal +z
        (radius R_S), or a point emitter at the origin (:func:`canonical_source`). An area emitter
        only points back to its disk shape: the caller keeps the shape alive."""
        self.emitter = emitter
        #: a point source (R_S = 0) is the limit of a small Lambertian disc: intensity I_0 cos theta_s
        #: about its axis, nothing behind it (docs/conventions.md section 5); Mitsuba's point emitter
        #: is isotropic, so :meth:`source_sample` applies the cosine (user audit, session 39: the
        #: isotropic point lit a housing's walls and lid behind the source, stray light 80 % against
        #: 64 % at R_S = 1 mm)
        self.point = bool(mi.has_flag(emitter.flags(), mi.EmitterFlags.DeltaPosition))

    def set_profile(self, source) -> None:
        """The beam profile of the instrument's ``source`` (:class:`~roadgonio.instrument.config.Source`),
        as kernel parameters: its numbers opaque (a new width reuses the kernel), its tables device
        arrays; the kinds of profile are structural. Nothing for a uniform source (bit for bit as
        before)."""
        self.profile = None if not source.profiled else (
            jit_beam(source.beam), jit_aperture(source.aperture),
            dr.opaque(mi.Float, 1.0 / source.radius_m if source.radius_m > 0 else 0.0))
        # the hard cone (beam_half_angle_deg) on every source sample and light path: the footprint
        # lies inside it (checked per cell), a housing's walls need not (audit 22: it was ignored there)
        self.cos_beam = None if source.beam_half_angle_deg is None else \
            dr.opaque(mi.Float, math.cos(math.radians(source.beam_half_angle_deg)))

    def set_cells(self, axes: np.ndarray, distances: np.ndarray) -> None:
        """The cells' sources, float64: unit axes (n_cells, 3), pointing from the source towards the
        sample centre, and D_S (n_cells,), which may differ between cells (a fixed-height source
        path); the centre is -D_S times the axis
        (:func:`roadgonio.engines.mitsuba.engine.cell_sources`). The kernel rebuilds the disc's
        frame from the axis (:func:`frame_from_axis`)."""
        axes = np.asarray(axes, dtype=np.float64)
        distances = np.asarray(distances, dtype=np.float64)
        if axes.ndim != 2 or axes.shape[1] != 3 or distances.shape != (len(axes),):
            raise BackendError(f"expected source axes of shape (cells, 3) and distances of shape (cells,), got "
                               f"{axes.shape} and {distances.shape}")
        if len(axes) and (np.abs(np.linalg.norm(axes, axis=1) - 1.0).max() > 1e-9 or not np.all(distances > 0.0)):
            raise BackendError("the source axes must be unit vectors and the distances positive")
        # gathered per lane, so these are never loaded contiguously (no alignment-dependent kernels)
        self.frames = [_f32(axes[:, k]) for k in range(3)]
        self.distance = _f32(distances)      # D_S per cell
        self.n_cells = len(axes)

    # -- shading -------------------------------------------------------------------------------
    def source_sample(self, si, cell, u, active):
        """A point of the source disc of ``cell`` sampled from the points ``si.p`` (uniform on the
        disc area, module docstring): world direction towards it, the point, the emitter weight
        L cos theta_s A / d^2 and the lanes where it is valid."""
        a = mi.Vector3f(*[dr.gather(mi.Float, v, cell, active) for v in self.frames])
        s, t = frame_from_axis(a)
        c = -dr.gather(mi.Float, self.distance, cell, active) * a
        v = mi.Vector3f(si.p) - c
        local = dr.zeros(mi.SurfaceInteraction3f)
        local.p = mi.Point3f(dr.dot(s, v), dr.dot(t, v), dr.dot(a, v))
        local.n = mi.Normal3f(dr.dot(s, si.n), dr.dot(t, si.n), dr.dot(a, si.n))
        local.time = si.time
        local.wavelengths = si.wavelengths
        ds, weight = self.emitter.sample_direction(local, u, active)
        active = active & (ds.pdf > 0.0)
        if self.point:                      # I_0 cos theta_s (set_source): emitted along -ds.d
            active = active & (-ds.d.z > 0.0)
            weight = weight * dr.maximum(-ds.d.z, 0.0)
        if self.cos_beam is not None:       # emitted along -ds.d: its cosine to the axis (+z) is -ds.d.z
            active = active & (-ds.d.z >= self.cos_beam)
        if self.profile is not None:
            # the source's relative radiance at the sampled point, in the canonical frame (axis +z)
            beam, aperture, inv_r = self.profile
            factor = source_radiance_factor(DrJitOps, beam, aperture, (ds.d.x, ds.d.y, ds.d.z),
                                            (0.0, 0.0, 1.0), (ds.p.x * inv_r, ds.p.y * inv_r))
            weight = weight * factor
        d = s * ds.d.x + t * ds.d.y + a * ds.d.z
        p_src = c + s * ds.p.x + t * ds.p.y + a * ds.p.z
        return d, p_src, weight, active, a

    def shade(self, scene, si, cell, u, active):
        """Road (x) and Lambert (y) contributions (``mi.Color3f``) of the source of ``cell`` at the
        hits ``si``, for the unit-square source samples ``u``; without the detector weight."""
        d, p_src, weight, active, _ = self.source_sample(si, cell, u, active)
        ctx = mi.BSDFContext()
        value = self.bsdf.eval(ctx, si, si.to_local(d), active)
        if self.shadow:
            active = active & ~scene.ray_test(shadow_ray(si.p, p_src), active)
        return dr.select(active, value * weight, 0.0)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        """``SamplingIntegrator`` interface: the signal of the cell :attr:`cell` along ``ray``."""
        si, hit = intersect_sample(scene, ray, mi.RayFlags.All, self.sample_shape, active)
        hit = active & hit
        cell = mi.UInt32(0) + self.cell
        value = self.shade(scene, si, cell, sampler.next_2d(hit), hit)
        return mi.Spectrum(value), hit, []

    def aov_names(self):
        return []

    # -- batched launches ----------------------------------------------------------------------
    def _ray_data(self, si, ray, w) -> dict:
        """The detector rays' fields (:data:`FLAT_RAY_FIELDS` on a flat sample, else
        :data:`RAY_FIELDS` with the geometric and shading normals) at their sample hits ``si``."""
        if self.flat:
            return dict(zip(FLAT_RAY_FIELDS, (si.p.x, si.p.y, si.p.z, ray.d.x, ray.d.y, ray.d.z, w)))
        ns = si.sh_frame.n
        return dict(zip(RAY_FIELDS, (si.p.x, si.p.y, si.p.z, si.n.x, si.n.y, si.n.z, ns.x, ns.y, ns.z,
                                     ray.d.x, ray.d.y, ray.d.z, w)))

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

    def trace_detector(self, scene, sensor, lattice: dict, reps: int, defer: bool = False) -> tuple[dict, int]:
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
        si, hit = intersect_sample(scene, ray, flags, self.sample_shape)
        w = dr.select(hit, mi.Float(w.x), 0.0)
        data = self._ray_data(si, ray, w)
        miss = ~hit
        dr.eval(data, miss)                 # one kernel traces the rays; the count reads the stored mask
        count = _Deferred(lambda: int(dr.count(miss)[0]) if dr.width(miss) else 0)
        return data, (count if defer else count())

    def block_sums(self, scene, rays: dict, lattice: dict, block_cell: np.ndarray,
                   block_rep: np.ndarray, defer: bool = False) -> np.ndarray:
        """Road and Lambert sums over the blocks (float32 numpy, (blocks, bins per block, 2)):
        block k is the n lattice points of replicate ``block_rep[k]`` (an index into ``rays``) for
        the source of cell ``block_cell[k]``. With ``defer`` a :class:`_Deferred` (the kernels run
        while Python traces the next ones; calling it waits and returns the array)."""
        _, j, cell, rep, r = self._blocks(lattice, block_cell, block_rep)
        si, w = self.vertex0(rays, r)
        active = w > 0.0
        u4, u5 = self._lattice(j, rep, lattice, (4, 5))
        value = self.shade(scene, si, cell, mi.Point2f(u4, u5), active) * w
        return self._bin_sums(mi.Float(value.x), mi.Float(value.y), len(block_cell), lattice, defer)

    # -- stray light: paths through the reflecting parts of the scene --------------------------
    def set_parts(self, shapes, max_bounces: int, source_radius: float = 0.0, source_radiance: float = 0.0) -> None:
        """The reflecting parts of the scene (shapes, the sample first), the number of reflections
        followed per light path, the sample's own included (``[scene] max_bounces``), and the
        source's radius and radiance (for the light paths of :meth:`light_sums`; a point source has
        none). See :meth:`trace_paths` for the two ways a path is found."""
        if int(max_bounces) < 2:
            raise BackendError(f"stray light needs max_bounces >= 2, got {max_bounces}")
        self.parts = list(shapes)
        # opaque: a pointer literal would make every scene compile its own kernel
        self._part_ptrs = [dr.opaque(mi.ShapePtr, sh) for sh in self.parts]
        self._sample_bsdf_ptr = dr.opaque(mi.BSDFPtr, self.bsdf)
        self.max_bounces = int(max_bounces)
        self.light_depth = min(self.max_bounces - 1, LIGHT_DEPTH) if source_radius > 0.0 else 0
        self.source_radius = dr.opaque(mi.Float, float(source_radius))
        # power of the Lambertian disc into its hemisphere: pi L A
        self.flux = dr.opaque(mi.Float, float(math.pi * source_radiance * math.pi * source_radius ** 2))

    @property
    def walk_dims(self) -> int:
        """Random dimensions a path uses beyond the lattice's six: per further eye vertex three to
        sample the reflection that reaches it and two for its next-event estimation; for the light
        paths two for the source point, two for the emitted direction, three per further reflection
        (:meth:`_light_reflect`)."""
        return WALK_DIMS_PER_VERTEX * (self.max_bounces - 1) + self.light_dims

    @property
    def light_dims(self) -> int:
        """Random dimensions of a light path (:attr:`walk_dims`)."""
        return (4 + 3 * (self.light_depth - 1)) if self.light_depth else 0

    def reflecting(self, shape):
        """Mask: the lanes' shapes are reflecting parts."""
        m = mi.Bool(False)
        for ptr in self._part_ptrs:
            m = m | (shape == ptr)
        return m

    def part_index(self, shape):
        """Index of each lane's shape in :attr:`parts` (``len(parts)`` for any other shape)."""
        idx = mi.UInt32(len(self._part_ptrs))
        for k in reversed(range(len(self._part_ptrs))):
            idx = dr.select(shape == self._part_ptrs[k], k, idx)
        return idx

    @staticmethod
    def channels(is_sample, value):
        """(road, Lambert) of a BSDF value: at the sample its road (x) and Lambert (y) channels;
        elsewhere the part's own value in both (its luminance if it is coloured)."""
        grey = dr.select((value.x == value.y) & (value.y == value.z), value.x, mi.luminance(value))
        return dr.select(is_sample, value.x, grey), dr.select(is_sample, value.y, grey)

    def walk_u(self, lattice: dict, keys, dim: int, rep, j):
        """Uniform numbers of the path dimension ``dim`` for the points j of replicates ``rep``: a
        coordinate of the lattice beyond its first six for the dimensions of :meth:`qmc_index` (the
        lattice then has :attr:`qmc_dims` more), else a counter-based hash (TEA) of the replicate's key
        and j. Either way a path is a function of (seed, pass, lattice size, replicate, j) only."""
        q = self.qmc_index(dim)
        if q is not None:
            return self._lattice(j, rep, lattice, (LATTICE_DIMS + q,))[0]
        return mi.sample_tea_float32(dr.gather(mi.UInt32, keys[dim], rep), j, TEA_ROUNDS)

    def qmc_index(self, dim: int) -> int | None:
        """Which path dimensions come from the lattice (index among them), else None: the first
        :data:`QMC_EYE_VERTICES` eye vertices' and all of the light path's (source point, emitted
        direction, the reflection at l_1). Measured on the housed portable instrument: lattice
        coordinates for every dimension (the further eye vertices' too) left more variance than
        hashed ones; for the light path's
        reflection at l_1 they left more while it was cosine-distributed, and 1.4-2.3x less at the
        limiting cells since it samples the part's BSDF (:meth:`_light_reflect`)."""
        eye = WALK_DIMS_PER_VERTEX * (self.max_bounces - 1)
        n_eye = min(eye, WALK_DIMS_PER_VERTEX * QMC_EYE_VERTICES)
        if dim < n_eye:
            return dim
        if eye <= dim < eye + self.light_dims:
            return n_eye + dim - eye
        return None

    @property
    def qmc_dims(self) -> int:
        """Path dimensions taken from the lattice (the rest are hashed)."""
        eye = WALK_DIMS_PER_VERTEX * (self.max_bounces - 1)
        return min(eye, WALK_DIMS_PER_VERTEX * QMC_EYE_VERTICES) + self.light_dims

    def _reflect(self, scene, si, bsdf, is_sample, tr, tg, pf, alive, u1, u2):
        """One reflection of the eye paths ``si``: sample the BSDF, multiply the road and Lambert
        throughputs by the weight f cos / pdf (:meth:`channels`), trace to the next vertex (a
        reflecting part, else the path ends), and the densities of the MIS weights
        (:meth:`trace_paths`): ``pf`` times this step's density in area measure, and ``pr`` the
        geometric factor |cos| / d^2 at ``si`` of the reverse step (a light path from the new vertex
        back to ``si``; its density in solid angle, :meth:`_light_pdf`, depends on the direction the
        light came from, so on the cell: :meth:`vertex_light` multiplies it in)."""
        bs, w = bsdf.sample(mi.BSDFContext(), si, u1, u2, alive)
        wr, wg = self.channels(is_sample, w)
        alive = alive & (bs.pdf > 0.0) & (mi.Frame3f.cos_theta(bs.wo) * mi.Frame3f.cos_theta(si.wi) > 0.0)
        tr, tg = tr * wr, tg * wg
        d = si.to_world(bs.wo)
        nxt = scene.ray_intersect(si.spawn_ray(d), mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame,
                                  False, alive)
        alive = alive & nxt.is_valid() & self.reflecting(nxt.shape) & ((tr > 0.0) | (tg > 0.0))
        inv_d2 = dr.rcp(dr.maximum(dr.square(nxt.t), MIN_D2))
        pf = pf * bs.pdf * dr.abs(dr.dot(nxt.n, d)) * inv_d2
        pr = dr.abs(dr.dot(si.n, d)) * inv_d2
        zero = mi.Float(0.0)
        return nxt, dr.select(alive, tr, zero), dr.select(alive, tg, zero), pf, pr

    def trace_paths(self, scene, sensor, lattice: dict, reps: int, keys, defer: bool = False) -> tuple[dict, list, int]:
        """:meth:`trace_detector` plus the further vertices of every eye path (one launch per
        reflection).

        Stray light reaches the footprint along paths source -> y_m -> ... -> y_1 -> x0 ->
        detector (x0 the detector ray's hit on the sample; y the reflecting parts, the sample
        included). Two strategies find them, combined by multiple importance sampling (balance
        heuristic; Veach 1997, ch. 9): **eye paths** (these, independent of the cell): y_1 ... by
        sampling each part's BSDF from x0, with next-event estimation to each cell's source at every
        vertex (:meth:`stray_sums`); and **light paths** (per cell, :meth:`light_sums`): from a
        point of the cell's source disc along a cosine-distributed direction to y_m, ..., then
        connected to x0 by a shadow ray. Eye paths find the light that the sample's BRDF favours,
        light paths the bright spots the source makes on the parts next to it. Light paths are
        used for m <= :data:`LIGHT_DEPTH` (longer ones come from eye paths alone).

        Returns the per-ray data of vertex 0 (exactly as :meth:`trace_detector`), the list of
        further vertices ``(fields, shapes)`` (:data:`VERTEX_FIELDS`: position, normals, shading
        frame, uv, the local direction back along the path, the road and Lambert throughputs up to
        the vertex, the detector weight included (0 where the path has ended), and the densities
        ``pf``, ``pr``) and the number of detector rays that missed the sample. ``keys``: per path
        dimension a UInt32 array of one key per replicate (:meth:`walk_u`)."""
        i = dr.arange(mi.UInt32, int(reps) * lattice["n"])
        j = i & lattice["mask"]
        rep = i >> lattice["shift_log2"]
        u0, u1, u2, u3 = self._lattice(j, rep, lattice, (0, 1, 2, 3))
        ray, w = sensor.sample_ray(0.0, 0.0, mi.Point2f(u2, u3), mi.Point2f(u0, u1))
        si = scene.ray_intersect(ray, mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame, False)
        hit = si.is_valid() & (si.shape == dr.opaque(mi.ShapePtr, self.sample_shape))
        w = dr.select(hit, mi.Float(w.x), 0.0)
        data = self._ray_data(si, ray, w)
        miss = ~hit
        verts = []
        u = [self.walk_u(lattice, keys, d, rep, j) for d in range(3)]
        one = mi.Float(1.0)
        nxt, tr, tg, pf, pr = self._reflect(scene, si, self.bsdf, mi.Bool(True), w, w, one, hit, u[0],
                                            mi.Point2f(u[1], u[2]))
        vert, shape = vertex_fields(nxt, tr, tg, pf, one, pr), nxt.shape
        dr.eval(data, miss, vert, shape)       # one kernel: the detector rays and their first reflection
        misses = _Deferred(lambda: int(dr.count(miss)[0]) if dr.width(miss) else 0)
        verts.append((vert, shape))
        for k in range(2, max(self.eye_vertices()) + 1):
            prev, pshape = verts[-1]
            si = vertex_interaction(prev, pshape)
            bsdf = si.bsdf()
            base = WALK_DIMS_PER_VERTEX * (k - 1)
            u = [self.walk_u(lattice, keys, base + d, rep, j) for d in range(3)]
            alive = (prev["tr"] > 0.0) | (prev["tg"] > 0.0)
            nxt, tr, tg, pf, pr = self._reflect(scene, si, bsdf, bsdf == self._sample_bsdf_ptr, prev["tr"],
                                                prev["tg"], prev["pf"], alive, u[0], mi.Point2f(u[1], u[2]))
            vert, shape = vertex_fields(nxt, tr, tg, pf, prev["pf"], pr), nxt.shape
            dr.eval(vert, shape)
            verts.append((vert, shape))
        return data, verts, (misses if defer else misses())

    def vertex_light(self, scene, si, g, cell, u, active, mis: int):
        """Next-event estimation at eye-path vertices ``si`` (any reflecting part; ``g`` the
        stored fields, throughputs and densities): road and Lambert contributions of the source of
        ``cell``, a shadow ray always (the housing can shade), the part's BSDF by dispatch, and with
        ``mis`` the balance-heuristic weight against the light path of the same vertices."""
        d, p_src, weight, active, a = self.source_sample(si, cell, u, active)
        bsdf = si.bsdf()
        value = bsdf.eval(mi.BSDFContext(), si, si.to_local(d), active)
        vr, vg = self.channels(bsdf == self._sample_bsdf_ptr, value)
        # a part's vertex keeps Mitsuba's spawned ray (lifted along the part's normal): from the source,
        # a ray grazing a wall near it (a hood's inside) could meet that wall within the 1e-5 margin
        # of :func:`shadow_ray`, float32's error of a grazing intersection being larger
        active = active & ~scene.ray_test(si.spawn_ray_to(mi.Point3f(p_src)), active)
        if mis:
            # against the light paths of the same vertices (:meth:`path_light`): ls = the density
            # with which the source's cosine emission reaches this vertex
            v = mi.Vector3f(p_src) - mi.Vector3f(si.p)
            inv_d2 = dr.rcp(dr.maximum(dr.dot(v, v), MIN_D2))
            ls = dr.maximum(-dr.dot(a, d), 0.0) * INV_PI * dr.abs(dr.dot(si.n, d)) * inv_d2
            if mis == 1:
                others = ls
            else:           # y_2: the eye prefix to y_1 + the light vertex; the light path through both,
                # which reflects at y_2 (the light from this cell's source) towards y_1 (si.wi)
                w_eye = mi.Vector3f(si.wi)         # a copy: assigning si.wi writes into the field's storage
                si.wi = si.to_local(d)
                l12 = self._light_pdf(bsdf, si, w_eye, active) * g["pr"]
                si.wi = w_eye
                others = g["pp"] * ls + ls * l12
            wgt = weight.x * g["pf"] / dr.maximum(g["pf"] + others, MIN_PDF)
        else:
            wgt = weight.x
        zero = mi.Float(0.0)
        return dr.select(active, vr * wgt * g["tr"], zero), dr.select(active, vg * wgt * g["tg"], zero)

    def _blocks(self, lattice: dict, block_cell: np.ndarray, block_rep: np.ndarray):
        """Lanes of a shading launch: (lanes, point j, cell, replicate, ray index) of the blocks."""
        n = lattice["n"]
        lanes = len(block_cell) * n
        if lanes >= 1 << 32:
            raise BackendError(f"a launch of {lanes} lanes exceeds 2^32; split it")
        l = dr.arange(mi.UInt32, lanes)
        kb = l >> lattice["shift_log2"]
        j = l & lattice["mask"]
        cell = dr.gather(mi.UInt32, _u32(block_cell), kb)
        rep = dr.gather(mi.UInt32, _u32(block_rep), kb)
        return lanes, j, cell, rep, (rep << lattice["shift_log2"]) + j

    @staticmethod
    def _bin_sums(road, lam, blocks: int, lattice: dict, defer: bool = False):
        """Per-bin sums of the lanes' road and Lambert values, (blocks, bins per block, 2) float32
        numpy, or with ``defer`` a :class:`_Deferred` of it: the launch and the reduction are
        asynchronous on the LLVM backend, and only reading them back waits."""
        bin_log2 = min(lattice["log2n"], BIN_LOG2)
        # evaluated block sums, not atomic scatters: the order of the float32 additions is then fixed,
        # so a run repeats bit for bit whatever the thread count
        dr.eval(road, lam)                                   # one kernel for both channels
        sums = [dr.block_sum(v, 1 << bin_log2, mode="evaluated") for v in (road, lam)]

        def read():
            out = np.stack([np.array(sums[0], dtype=np.float32), np.array(sums[1], dtype=np.float32)], axis=-1)
            return out.reshape(blocks, lattice["n"] >> bin_log2, 2)
        return _Deferred(read) if defer else read()

    def eye_light(self, scene, vertex: tuple, lattice: dict, r, j, cell, rep, keys, k: int):
        """Per lane, the road and Lambert light reaching the detector through eye-path vertex
        ``k`` >= 1 (``vertex`` = ``(fields, shapes)`` of :meth:`trace_paths`, ``r`` the lanes' path
        indices); also the lanes' path fields."""
        fields, shapes = vertex
        g = {key: dr.gather(mi.Float, fields[key], r) for key in fields}
        si = vertex_interaction(g, dr.gather(mi.ShapePtr, shapes, r))
        active = (g["tr"] > 0.0) | (g["tg"] > 0.0)
        base = WALK_DIMS_PER_VERTEX * (k - 1) + 3
        u = mi.Point2f(self.walk_u(lattice, keys, base, rep, j), self.walk_u(lattice, keys, base + 1, rep, j))
        road, lam = self.vertex_light(scene, si, g, cell, u, active, mis=k if k <= self.light_depth else 0)
        return road, lam, si

    def stray_sums(self, scene, vertex: tuple, lattice: dict, block_cell: np.ndarray, block_rep: np.ndarray,
                   keys, k: int, defer: bool = False) -> np.ndarray:
        """Road and Lambert sums over the blocks (as :meth:`block_sums`) of the eye paths' light
        through vertex ``k`` >= 1 (:meth:`eye_light`), each block for its own cell."""
        _, j, cell, rep, r = self._blocks(lattice, block_cell, block_rep)
        road, lam, _ = self.eye_light(scene, vertex, lattice, r, j, cell, rep, keys, k)
        return self._bin_sums(road, lam, len(block_cell), lattice, defer)

    def vertex0(self, rays: dict, r):
        """The detector rays' hits on the sample (vertex 0) rebuilt from the stored ray data."""
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
        return si, g["w"]

    def _footprint_link(self, scene, x0, w0, y, wl, ok, onward: bool = False):
        """Connection of light-path vertices ``y`` (``wl``: local direction towards the light) with
        the detector hits ``x0`` (weights ``w0``): road and Lambert values of the link (x0's BRDF
        cos, y's BRDF cos towards x0, 1/d^2; the light's flux and the MIS weight left out), the
        density with which an eye path from x0 reaches y (area measure), with ``onward`` the density
        with which it would go on from y along ``wl`` (solid angle; else None) and the visible lanes."""
        ctx = mi.BSDFContext()
        v = mi.Vector3f(x0.p) - mi.Vector3f(y.p)
        d2 = dr.dot(v, v)
        ok = ok & (d2 > MIN_D2)
        inv_d2 = dr.rcp(dr.maximum(d2, MIN_D2))
        e = v * dr.rsqrt(dr.maximum(d2, MIN_D2))                 # from y towards x0
        wo0 = x0.to_local(-e)
        f0, p0 = self.bsdf.eval_pdf(ctx, x0, wo0, ok)            # (f_road, 1/pi) cos at x0, and its density
        p_eye = p0 * dr.abs(dr.dot(y.n, e)) * inv_d2
        y.wi = y.to_local(e)                                     # towards the eye (x0)
        bsdf = y.bsdf()
        if onward:
            value, p_on = bsdf.eval_pdf(ctx, y, wl, ok)
        else:
            value, p_on = bsdf.eval(ctx, y, wl, ok), None
        fr, fg = self.channels(bsdf == self._sample_bsdf_ptr, value)
        out = dr.abs(mi.Frame3f.cos_theta(y.wi)) / dr.maximum(dr.abs(mi.Frame3f.cos_theta(wl)), MIN_COS) * inv_d2
        vis = ok & ~scene.ray_test(y.spawn_ray_to(mi.Point3f(x0.p)), ok)
        return w0 * f0.x * fr * out, w0 * f0.y * fg * out, p_eye, p_on, vis

    def _light_pdf(self, bsdf, si, w_out, active):
        """Density (solid angle) with which a light path that reached ``si`` (``si.wi``: local
        direction towards the light) reflects along the local direction ``w_out``
        (:meth:`_light_reflect`): the density of ``bsdf.sample`` with ``si.wi`` towards the light, or
        with :attr:`light_lobe` off the cosine about the normal. The MIS weights of every strategy
        that finds the same two-reflection path use this function (:meth:`vertex_light`,
        :meth:`path_light`)."""
        if not self.light_lobe:
            return dr.abs(mi.Frame3f.cos_theta(w_out)) * INV_PI
        return bsdf.pdf(mi.BSDFContext(), si, w_out, active)

    def _light_reflect(self, bsdf, si, u1, u2, active):
        """The light path's reflection at ``si`` (``si.wi``: local direction towards the light):
        a local direction and its density (:meth:`_light_pdf`). The part's own BSDF sampling
        (Mitsuba's ``sample`` with the light's direction in the place of the sensor's: the road
        BSDF samples its Phong lobe about the mirror direction of the light, i.e. the forward lobe
        a grazing source lights, mixed with the cosine; a diffuse part the cosine), or with
        :attr:`light_lobe` off a cosine-distributed direction on the side the light came from."""
        if not self.light_lobe:
            wn = mi.warp.square_to_cosine_hemisphere(u2)
            wn.z = dr.select(mi.Frame3f.cos_theta(si.wi) < 0.0, -wn.z, wn.z)
            return wn, dr.abs(wn.z) * INV_PI
        bs, _ = bsdf.sample(mi.BSDFContext(), si, u1, u2, active)
        return bs.wo, bs.pdf

    def path_light(self, scene, rays: dict, vertex1: tuple, lattice: dict, r, j, cell, rep, keys):
        """Per lane, the stray light that the light paths carry (:meth:`trace_paths`), as
        (road, Lambert, part index of the last reflection before the footprint) triples.

        A light path starts at a uniform point s of the cell's source disc along a cosine-
        distributed direction (power pi L A, times the source's relative radiance there for a
        profiled source) and meets the part l_1. Light with one reflection
        (s -> y_1 -> x0): l_1 is connected with the detector hit x0, weighted against the eye path
        x0 -> y_1 + next-event estimation (:meth:`eye_light`). Light with two reflections
        (s -> y_2 -> y_1 -> x0) has three strategies, weighted by the balance heuristic over the
        densities (area measure; the source point's 1/A is common to all): the eye path
        x0 -> y_1 -> y_2 + next-event estimation (e1 e2); the eye path's y_1 connected with the light
        vertex y_2 = l_1 (e1 ls); the light path s -> l_1 = y_2 -> l_2 = y_1 (cosine reflection at
        l_1) connected with x0 (ls l12). e1, e2: BSDF sampling from x0 and y_1; ls: the source's
        cosine emission to y_2; l12: the light path's reflection at y_2 towards y_1
        (:meth:`_light_reflect`: the part's BSDF sampling with the light's direction, so the road's
        forward lobe; this density depends on where the light came from, so it is computed per cell
        in every strategy's weight, :meth:`_light_pdf`)."""
        ctx = mi.BSDFContext()
        flags = mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame
        zero = mi.Float(0.0)
        x0, w0 = self.vertex0(rays, r)
        alive = w0 > 0.0
        a = mi.Vector3f(*[dr.gather(mi.Float, v, cell, alive) for v in self.frames])
        s_ax, t_ax = frame_from_axis(a)
        c = -dr.gather(mi.Float, self.distance, cell, alive) * a      # D_S of the lane's cell
        base = WALK_DIMS_PER_VERTEX * (self.max_bounces - 1)
        u = [self.walk_u(lattice, keys, base + q, rep, j) for q in range(4)]
        disk = mi.warp.square_to_uniform_disk_concentric(mi.Point2f(u[0], u[1])) * self.source_radius
        dl = mi.warp.square_to_cosine_hemisphere(mi.Point2f(u[2], u[3]))
        d = s_ax * dl.x + t_ax * dl.y + a * dl.z
        l1 = scene.ray_intersect(mi.Ray3f(mi.Point3f(c + s_ax * disk.x + t_ax * disk.y), d), flags, False, alive)
        alive = alive & l1.is_valid() & self.reflecting(l1.shape) & (dl.z > 0.0)
        if self.cos_beam is not None:       # the hard cone, as in next-event estimation (:meth:`source_sample`)
            alive = alive & (dl.z >= self.cos_beam)
        ls = dl.z * INV_PI * dr.abs(dr.dot(l1.n, d)) * dr.rcp(dr.maximum(dr.square(l1.t), MIN_D2))
        flux = mi.Float(0.0) + self.flux
        if self.profile is not None:
            # the source's relative radiance at the path's start and emission direction (canonical
            # frame, axis +z; w points back towards the source): the same factor as next-event estimation
            beam, aperture, inv_r = self.profile
            factor = source_radiance_factor(DrJitOps, beam, aperture, (-dl.x, -dl.y, -dl.z), (0.0, 0.0, 1.0),
                                            (disk.x * inv_r, disk.y * inv_r))
            if factor is not None:
                flux = flux * factor
        wl1 = l1.to_local(-d)                                      # at l_1, towards the source
        out = []
        # one reflection: l_1 -> x0 (against the eye path: e1)
        road, lam, e1, _, vis = self._footprint_link(scene, x0, w0, l1, wl1, alive)
        mis = flux * ls / dr.maximum(ls + e1, MIN_PDF)
        out.append((dr.select(vis, road * mis, zero), dr.select(vis, lam * mis, zero), self.part_index(l1.shape)))
        if self.light_depth < 2:
            return out
        bsdf_l1 = l1.bsdf()
        sample_l1 = bsdf_l1 == self._sample_bsdf_ptr
        cos_l1 = dr.maximum(dr.abs(mi.Frame3f.cos_theta(wl1)), MIN_COS)
        # two reflections, the eye path's vertex y_1 connected with y_2 = l_1
        fields, shapes = vertex1
        g = {key: dr.gather(mi.Float, fields[key], r) for key in fields}
        y1 = vertex_interaction(g, dr.gather(mi.ShapePtr, shapes, r))
        ok = alive & ((g["tr"] > 0.0) | (g["tg"] > 0.0))
        v = mi.Vector3f(l1.p) - mi.Vector3f(y1.p)
        d2 = dr.dot(v, v)
        ok = ok & (d2 > MIN_D2)
        inv_d2 = dr.rcp(dr.maximum(d2, MIN_D2))
        e = v * dr.rsqrt(dr.maximum(d2, MIN_D2))                   # from y_1 towards l_1
        bsdf_y1 = y1.bsdf()
        wo1 = y1.to_local(e)
        value, p1 = bsdf_y1.eval_pdf(ctx, y1, wo1, ok)
        f1r, f1g = self.channels(bsdf_y1 == self._sample_bsdf_ptr, value)
        e2 = p1 * dr.abs(dr.dot(l1.n, e)) * inv_d2
        l1.wi = l1.to_local(-e)                                    # at l_1, towards y_1 (the eye side)
        flr, flg = self.channels(sample_l1, bsdf_l1.eval(ctx, l1, wl1, ok))
        cos_out = dr.abs(mi.Frame3f.cos_theta(l1.wi))
        w_eye = mi.Vector3f(l1.wi)                                 # a copy (l1.wi is overwritten in place)
        l1.wi = wl1                                                # the light path's view of l_1
        l12 = self._light_pdf(bsdf_l1, l1, w_eye, ok) * dr.abs(dr.dot(y1.n, e)) * inv_d2
        e1 = g["pf"]
        mis = flux * e1 * ls / dr.maximum(e1 * e2 + e1 * ls + ls * l12, MIN_PDF)
        link = cos_out / cos_l1 * inv_d2 * mis
        vis = ok & ~scene.ray_test(y1.spawn_ray_to(mi.Point3f(l1.p)), ok)
        out.append((dr.select(vis, g["tr"] * f1r * flr * link, zero), dr.select(vis, g["tg"] * f1g * flg * link, zero),
                    self.part_index(y1.shape)))
        # two reflections, l_1 reflects (:meth:`_light_reflect`) to l_2 -> x0
        q = base + 4
        l1.wi = wl1
        wn, p_wn = self._light_reflect(bsdf_l1, l1, self.walk_u(lattice, keys, q, rep, j),
                                       mi.Point2f(self.walk_u(lattice, keys, q + 1, rep, j),
                                                  self.walk_u(lattice, keys, q + 2, rep, j)), alive)
        alive = alive & (p_wn > 0.0)
        l1.wi = wn
        tr_, tg_ = self.channels(sample_l1, bsdf_l1.eval(ctx, l1, wl1, alive))
        # f cos_out / p_wn, f = eval / cos_in
        scale = flux * dr.abs(wn.z) / (cos_l1 * dr.maximum(p_wn, MIN_PDF))
        br, bg = tr_ * scale, tg_ * scale
        d = l1.to_world(wn)
        l2 = scene.ray_intersect(l1.spawn_ray(d), flags, False, alive)
        alive = alive & l2.is_valid() & self.reflecting(l2.shape) & ((br > 0.0) | (bg > 0.0))
        inv_t2 = dr.rcp(dr.maximum(dr.square(l2.t), MIN_D2))
        l12 = p_wn * dr.abs(dr.dot(l2.n, d)) * inv_t2
        road, lam, e1, p_on, vis = self._footprint_link(scene, x0, w0, l2, l2.to_local(-d), alive, onward=True)
        e2 = p_on * dr.abs(dr.dot(l1.n, d)) * inv_t2
        mis = ls * l12 / dr.maximum(e1 * e2 + e1 * ls + ls * l12, MIN_PDF)
        out.append((dr.select(vis, road * br * mis, zero), dr.select(vis, lam * bg * mis, zero),
                    self.part_index(l2.shape)))
        return out

    def eye_vertices(self) -> list[int]:
        """Eye-path vertices whose next-event estimation is used (all of them)."""
        return list(range(1, self.max_bounces))

    def light_sums(self, scene, rays: dict, vertex1: tuple, lattice: dict, block_cell: np.ndarray,
                   block_rep: np.ndarray, keys, defer: bool = False) -> np.ndarray:
        """Road and Lambert sums over the blocks (as :meth:`block_sums`) of the light paths
        (:meth:`path_light`), each block for its own cell."""
        _, j, cell, rep, r = self._blocks(lattice, block_cell, block_rep)
        out = self.path_light(scene, rays, vertex1, lattice, r, j, cell, rep, keys)
        road = sum((o[0] for o in out[1:]), out[0][0])
        lam = sum((o[1] for o in out[1:]), out[0][1])
        return self._bin_sums(road, lam, len(block_cell), lattice, defer)

    def picture_lanes(self, scene, sensor, lattice: dict, keys, cell: int = 0, reps: int = 1) -> dict:
        """``reps`` replicates of a one-cell launch (``roadgonio render``), per lane as float64 numpy
        (``rep``: the lane's replicate):
        the film position (``u``, ``v``: the lattice's dimensions 2, 3, as :meth:`trace_paths` passes
        them to the sensor), the direct road and Lambert values (detector weight included), and the
        stray light as ``(road, Lambert, part)`` triples, one per contribution (next-event estimation
        at each eye vertex, the light-path strategies); ``part`` indexes :attr:`parts` by the last
        reflection before the footprint."""
        rays, verts, _ = self.trace_paths(scene, sensor, lattice, int(reps), keys)
        r = dr.arange(mi.UInt32, int(reps) * lattice["n"])
        j = r & lattice["mask"]
        rep = r >> lattice["shift_log2"]
        c = mi.UInt32(int(cell)) + 0 * j
        u, v = self._lattice(j, rep, lattice, (2, 3))
        u4, u5 = self._lattice(j, rep, lattice, (4, 5))
        x0, w0 = self.vertex0(rays, r)
        direct = self.shade(scene, x0, c, mi.Point2f(u4, u5), w0 > 0.0) * w0
        part1 = self.part_index(dr.gather(mi.ShapePtr, verts[0][1], r))
        out = [(road, lam, part1) for road, lam, _ in
               (self.eye_light(scene, verts[k - 1], lattice, r, j, c, rep, keys, k) for k in self.eye_vertices())]
        if self.light_depth:
            out += self.path_light(scene, rays, verts[0], lattice, r, j, c, rep, keys)
        res = {"u": u, "v": v, "rep": mi.Float(rep), "direct_road": mi.Float(direct.x),
               "direct_lambert": mi.Float(direct.y)}
        for q, (road, lam, part) in enumerate(out):
            res[f"road_{q}"], res[f"lambert_{q}"], res[f"part_{q}"] = road, lam, part
        dr.eval(res)
        return {k: np.array(val, dtype=np.float64) for k, val in res.items()}

    def to_string(self):
        return f"KaBatch[cells={self.n_cells}, shadow={self.shadow}]"


#: Stored per eye-path vertex beyond the first (stray light): position, geometric normal, shading
#: frame (s and n), uv, the local direction back along the path, the road and Lambert throughputs,
#: and the densities of the MIS weights (:meth:`KaBatch.trace_paths`).
VERTEX_FIELDS = ("px", "py", "pz", "nx", "ny", "nz", "sx", "sy", "sz", "fx", "fy", "fz", "u", "v",
                 "wx", "wy", "wz", "tr", "tg", "pf", "pp", "pr")
#: Path dimensions per further eye vertex: 1 + 2 to sample the reflection, 2 for the source sample.
WALK_DIMS_PER_VERTEX = 5
#: Rounds of the TEA hash of the path dimensions.
TEA_ROUNDS = 8
#: Dimensions of a detector sample (pupil 2, field 2, source 2).
LATTICE_DIMS = 6
#: Eye-path vertices whose dimensions come from the lattice (:meth:`KaBatch.qmc_index`).
QMC_EYE_VERTICES = 2
#: Longest light paths (reflections before the connection to the footprint).
LIGHT_DEPTH = 2
INV_PI = 1.0 / math.pi
#: Guards of divisions (squared distance in m^2, densities, cosines).
MIN_D2, MIN_PDF, MIN_COS = 1e-12, 1e-30, 1e-12


def vertex_fields(si, tr, tg, pf, pp, pr) -> dict:
    """The :data:`VERTEX_FIELDS` of eye-path vertices ``si``."""
    s, n = si.sh_frame.s, si.sh_frame.n
    return dict(zip(VERTEX_FIELDS, (si.p.x, si.p.y, si.p.z, si.n.x, si.n.y, si.n.z, s.x, s.y, s.z, n.x, n.y, n.z,
                                    si.uv.x, si.uv.y, si.wi.x, si.wi.y, si.wi.z, tr, tg, pf, pp, pr)))


def vertex_interaction(g: dict, shape):
    """A ``SurfaceInteraction3f`` rebuilt from stored :data:`VERTEX_FIELDS` and shapes."""
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.t = mi.Float(1.0)
    si.p = mi.Point3f(g["px"], g["py"], g["pz"])
    si.n = mi.Normal3f(g["nx"], g["ny"], g["nz"])
    s, n = mi.Vector3f(g["sx"], g["sy"], g["sz"]), mi.Vector3f(g["fx"], g["fy"], g["fz"])
    si.sh_frame = mi.Frame3f(s, dr.cross(n, s), n)
    si.uv = mi.Point2f(g["u"], g["v"])
    si.wi = mi.Vector3f(g["wx"], g["wy"], g["wz"])
    si.shape = shape
    return si


def frame_from_axis(a):
    """Unit vectors (s, t) completing the unit axis ``a`` to a right-handed frame, on the device:
    s = normalise(h x a) with h = +z, or +x when |a_z| >= 0.9; t = a x s. The device twin of
    :func:`roadgonio.instrument.optics.orthonormal_frame` (same rule, float32)."""
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
