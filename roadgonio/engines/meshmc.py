"""Independent float64 numpy Monte Carlo of k_A for a **mesh** sample (paper eq. 3; docs/conventions.md
sections 4-5): the check of mesh scenes that the flat-plane integrators cannot give.

The same estimator as :mod:`roadgonio.engines.montecarlo` (stratified pupil, field and source
points, batches, ratio of means with a delta-method SE), with the plane z = 0 replaced by ray
casting against the sample's triangles (loaded with trimesh, as the Mitsuba scene does):

* the detector ray's first hit on the mesh (either side of a triangle; a back face reflects
  nothing, the road BSDF being one-sided) gives the point x and the face normal n (flat shading,
  as in the Mitsuba mesh built from vertex positions and faces only);
* the BRDF is evaluated in the local frame of n (it depends on the directions relative to n only);
* the source coupling is ``cos theta_i cos theta_s / d^2`` with ``cos theta_i = w . n``, times the
  visibility of the source point from x: a shadow ray against the mesh (self-shadowing of a rough
  surface, exactly what a mesh adds);
* every detector ray must hit the mesh, and the source disc must not block the line of sight
  (:func:`roadgonio.instrument.optics.source_blocks_view`, the test of every backend: it counts a
  disc anywhere in the bundle above the plane z = 0, conservative for a mesh that rises above it):
  otherwise a :class:`~roadgonio.errors.GeometryError` names the cell.

Ray casting is vectorised numpy (Moeller-Trumbore on candidate pairs): triangles are binned on a
uniform grid over the xy plane (bounding boxes dilated by one cell), a ray's candidates are the
triangles of the cells it crosses while it is inside the mesh's bounding box (a thin slab for a
road sample, so grazing rays stay short). No Mitsuba, no float32: an independent implementation.
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from roadgonio.seeds import cell_key, check_seed, seed_entropy
from roadgonio.errors import GeometryError, InputError
from roadgonio.instrument import optics
from roadgonio.instrument.config import Instrument
from roadgonio.instrument.mesh import mesh_location
from roadgonio.arrays import NumpyOps
from roadgonio.surface.model import RoadModel, road_brdf
from roadgonio.engines.result import CellByCellBackend, CellResult, ratio_se
from roadgonio.engines.cellcheck import check_cell, no_light

DEFAULT_REL_SE = 1e-3
DEFAULT_BATCH = 23 ** 2
#: The SE comes from the scatter of the batch means, with (batches - 1) degrees of freedom: as for
#: numpy-mc (:data:`roadgonio.engines.montecarlo.DEFAULT_MIN_BATCHES`), at least 64 batches, so that
#: z = error / SE follows t_63, within 2 % of normal in RMS (with 8 batches t_7: RMS z 1.18).
DEFAULT_MIN_BATCHES = 64
DEFAULT_MAX_SAMPLES = 50_000_000
#: Offset of shadow-ray origins along the normal (m), well above float64 rounding of metre coordinates.
SHADOW_EPS_M = 1e-9
#: Barycentric tolerance of the ray-triangle test: a ray that lands on an edge or a vertex shared by
#: triangles hits them, whatever the rounding of u and v (computed from coordinates of metres, they
#: are off by ~1e-15, more at grazing incidence); 1e-9 of a triangle's size is no hole and no overlap
#: a footprint could notice.
EDGE_TOL = 1e-9
#: Samples evaluated in one vectorised pass (whole batches, at least one): small batches share the
#: fixed cost of an evaluation, and larger passes cost more per sample (the caster's candidate
#: arrays outgrow the caches). Measured on the portable preset, 6 cells (a flat 8-triangle mesh):
#: 64 batches of 121 one at a time 0.46 s, in passes of 1024 0.19 s, of 4096 0.27 s (8 batches of
#: 1024 one at a time: 0.19 s); 64 batches of 529 in passes of 1024 0.92 s (8 of 4096: 1.07 s). The
#: lab preset on a 41 x 11 grid mesh: 1.2 s and 3.7 s (8 x 1024: 1.8 s, 8 x 4096: 6.3 s).
GROUP_SAMPLES = 1 << 10


def load_mesh_triangles(instrument: Instrument) -> np.ndarray:
    """The sample's triangles (T, 3, 3) in float64, from the same checked trimesh the Mitsuba scene
    uses (:func:`roadgonio.instrument.mesh.sample_trimesh`: the rectangle, or the mesh file facing +z)."""
    from roadgonio.instrument.mesh import sample_trimesh
    mesh = sample_trimesh(instrument)
    return np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces, dtype=np.int64)]


class MeshCaster:
    """Ray casting against a triangle set (module docstring): first hits and shadow tests."""

    def __init__(self, triangles: np.ndarray, cells_per_side: int | None = None):
        tri = np.asarray(triangles, dtype=np.float64)
        self.v0 = tri[:, 0]
        self.e1 = tri[:, 1] - tri[:, 0]
        self.e2 = tri[:, 2] - tri[:, 0]
        n = np.cross(self.e1, self.e2)
        area2 = np.linalg.norm(n, axis=1)
        if np.any(area2 <= 0):
            keep = area2 > 0
            self.v0, self.e1, self.e2, n, area2 = self.v0[keep], self.e1[keep], self.e2[keep], n[keep], area2[keep]
        self.normal = n / area2[:, None]
        self.lo = tri.min(axis=(0, 1))
        self.hi = tri.max(axis=(0, 1))
        T = len(self.v0)
        k = cells_per_side or int(min(512, max(1, round(math.sqrt(T)))))
        span = np.maximum(self.hi[:2] - self.lo[:2], 1e-12)
        self.h = float(max(span) / k)
        self.nx = int(math.ceil(span[0] / self.h)) + 1
        self.ny = int(math.ceil(span[1] / self.h)) + 1
        tmin = tri.min(axis=1)[:, :2] - self.h
        tmax = tri.max(axis=1)[:, :2] + self.h
        i0 = np.clip(((tmin[:, 0] - self.lo[0]) / self.h).astype(np.int64), 0, self.nx - 1)
        i1 = np.clip(((tmax[:, 0] - self.lo[0]) / self.h).astype(np.int64), 0, self.nx - 1)
        j0 = np.clip(((tmin[:, 1] - self.lo[1]) / self.h).astype(np.int64), 0, self.ny - 1)
        j1 = np.clip(((tmax[:, 1] - self.lo[1]) / self.h).astype(np.int64), 0, self.ny - 1)
        cells, ids = [], []
        for t in range(len(self.v0)):
            ii, jj = np.meshgrid(np.arange(i0[t], i1[t] + 1), np.arange(j0[t], j1[t] + 1), indexing="ij")
            c = (ii * self.ny + jj).ravel()
            cells.append(c)
            ids.append(np.full(c.size, t))
        cells = np.concatenate(cells)
        ids = np.concatenate(ids)
        order = np.argsort(cells, kind="stable")
        self.cell_tris = ids[order]
        self.cell_start = np.searchsorted(cells[order], np.arange(self.nx * self.ny + 1))

    def _slab(self, o, d):
        """Parameter interval of each ray inside the mesh's bounding box (padded)."""
        pad = 1e-9 + 1e-12 * float(np.max(np.abs(self.hi - self.lo)))
        t0 = np.zeros(len(o))
        t1 = np.full(len(o), np.inf)
        for a in range(3):
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / d[:, a]
                ta = (self.lo[a] - pad - o[:, a]) * inv
                tb = (self.hi[a] + pad - o[:, a]) * inv
            par = d[:, a] == 0.0
            inside = (o[:, a] >= self.lo[a] - pad) & (o[:, a] <= self.hi[a] + pad)
            lo_ = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
            hi_ = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
            t0 = np.maximum(t0, lo_)
            t1 = np.minimum(t1, hi_)
        return t0, t1

    def _candidates(self, o, d, tmax):
        t0, t1 = self._slab(o, d)
        t1 = np.minimum(t1, tmax)
        ok = t1 >= t0
        dxy = np.hypot(d[:, 0], d[:, 1])
        length = np.where(ok, (t1 - t0) * dxy, 0.0)
        steps = np.where(ok, np.ceil(length / (0.5 * self.h)).astype(np.int64) + 1, 0)
        ray = np.repeat(np.arange(len(o)), steps)
        if ray.size == 0:
            return ray, ray
        first = np.cumsum(steps) - steps
        k = np.arange(ray.size) - np.repeat(first, steps)
        frac = k / np.maximum(np.repeat(steps, steps) - 1, 1)
        tt = np.repeat(t0, steps) + frac * (np.repeat(np.where(ok, t1 - t0, 0.0), steps))
        px = o[ray, 0] + tt * d[ray, 0]
        py = o[ray, 1] + tt * d[ray, 1]
        ci = np.clip(((px - self.lo[0]) / self.h).astype(np.int64), 0, self.nx - 1)
        cj = np.clip(((py - self.lo[1]) / self.h).astype(np.int64), 0, self.ny - 1)
        key = ray * (self.nx * self.ny) + ci * self.ny + cj      # in order along each ray
        cell = key[np.r_[True, key[1:] != key[:-1]]]
        ray_c = cell // (self.nx * self.ny)
        c = cell % (self.nx * self.ny)
        cnt = self.cell_start[c + 1] - self.cell_start[c]
        pr = np.repeat(ray_c, cnt)
        base = np.repeat(self.cell_start[c], cnt)
        off = np.arange(pr.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        pt = self.cell_tris[base + off]
        key = np.sort(pr * len(self.v0) + pt)
        key = key[np.r_[True, key[1:] != key[:-1]]] if key.size else key
        return key // len(self.v0), key % len(self.v0)

    def _intersect(self, o, d, ray, tri):
        """Moeller-Trumbore for the pairs (ray, tri): the hit parameter (inf where there is none)."""
        e1, e2 = self.e1[tri], self.e2[tri]
        dd = d[ray]
        pvec = np.cross(dd, e2)
        det = np.einsum("ij,ij->i", e1, pvec)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tvec = o[ray] - self.v0[tri]
            u = np.einsum("ij,ij->i", tvec, pvec) * inv
            qvec = np.cross(tvec, e1)
            v = np.einsum("ij,ij->i", dd, qvec) * inv
            t = np.einsum("ij,ij->i", e2, qvec) * inv
        hit = (det != 0.0) & (u >= -EDGE_TOL) & (v >= -EDGE_TOL) & (u + v <= 1.0 + EDGE_TOL) & (t > 0.0)
        return np.where(hit, t, np.inf)

    def first_hit(self, o, d, chunk: int = 1 << 14):
        """(t, triangle index) of each ray's first hit (t = inf, index -1 for a miss)."""
        n = len(o)
        best = np.full(n, np.inf)
        idx = np.full(n, -1)
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            ray, tri = self._candidates(o[a:b], d[a:b], np.inf)
            if ray.size == 0:
                continue
            t = self._intersect(o[a:b], d[a:b], ray, tri)
            order = np.lexsort((t, ray))
            r_sorted, t_sorted, tri_sorted = ray[order], t[order], tri[order]
            firsts = np.r_[True, r_sorted[1:] != r_sorted[:-1]]
            rr = r_sorted[firsts]
            best[a + rr] = t_sorted[firsts]
            idx[a + rr] = np.where(np.isfinite(t_sorted[firsts]), tri_sorted[firsts], -1)
        return best, idx

    def blocked(self, o, d, tmax, chunk: int = 1 << 14):
        """Whether each ray hits a triangle at 0 < t < tmax."""
        n = len(o)
        out = np.zeros(n, dtype=bool)
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            ray, tri = self._candidates(o[a:b], d[a:b], tmax[a:b])
            if ray.size == 0:
                continue
            t = self._intersect(o[a:b], d[a:b], ray, tri)
            hit = t < tmax[a:b][ray]
            out[a + np.unique(ray[hit])] = True
        return out


class MeshMonteCarloBackend(CellByCellBackend):
    """k_A by float64 Monte Carlo with ray casting against the sample mesh (module docstring)."""

    name = "numpy-mc-mesh"

    def __init__(self, instrument: Instrument, model: RoadModel, *, rel_se: float = DEFAULT_REL_SE, seed: int = 0,
                 batch: int = DEFAULT_BATCH, min_batches: int = DEFAULT_MIN_BATCHES,
                 max_samples: int = DEFAULT_MAX_SAMPLES):
        from roadgonio.engines.reference import _integer
        from roadgonio.engines.registry import check_relative
        rel_se = check_relative(rel_se, "rel_se")
        seed = check_seed(seed)
        from roadgonio.limits import check_size
        m = int(round(math.sqrt(check_size(_integer(batch, "batch"), "batch", "batch"))))
        if m < 2:
            raise InputError(f"expected a batch of at least 4 samples, got {batch}", field="batch")
        if _integer(min_batches, "min_batches") < 2:
            raise InputError(f"expected at least 2 batches (for a standard error), got {min_batches}",
                             field="min_batches")
        optics.footprint_boundary(instrument)    # the detector must look downwards
        self.instrument = instrument
        self.model = model
        self.rel_se = rel_se
        self.seed = seed
        self.m = m
        self.batch = m * m
        self.min_batches = int(min_batches)
        self.max_samples = int(max_samples)
        self._P = model.params.to_dict()
        self._terms = model.terms()
        self._det = optics.detector_geometry(instrument)
        self.caster = MeshCaster(load_mesh_triangles(instrument))
        det = instrument.detector
        self._active = (det.pupil_radius_m > 0.0, det.field_half_angle_deg > 0.0, instrument.source.radius_m > 0.0)
        i = np.arange(self.batch)
        self._grid = (i % m, i // m)
        self._zeros = np.zeros(self.batch)

    def settings(self) -> dict[str, Any]:
        return {"backend": self.name, "rel_se": self.rel_se, "seed": self.seed, "batch": self.batch,
                "min_batches": self.min_batches, "max_samples": self.max_samples,
                "mesh": str(self.instrument.sample.mesh) if self.instrument.sample.mesh else "flat rectangle",
                "triangles": int(len(self.caster.v0)),
                "sampling": "stratified m x m jittered grid per disc per batch; numpy ray casting with shadow rays",
                "precision": "float64"}

    def _square(self, rng, active: bool):
        """One batch's m x m jittered points on the unit square, in random order: the draws of
        :func:`roadgonio.engines.montecarlo._stratified_disc` before its concentric map (zeros for an
        inactive disc, which draws nothing)."""
        if not active:
            return self._zeros, self._zeros
        u1 = (self._grid[0] + rng.random(self.batch)) / self.m
        u2 = (self._grid[1] + rng.random(self.batch)) / self.m
        perm = rng.permutation(self.batch)
        return u1[perm], u2[perm]

    def _disc(self, squares, active: bool):
        """The concentric map of the batches' square points, in one call (elementwise: the points of
        _stratified_disc, bit for bit)."""
        u1, u2 = np.concatenate([q[0] for q in squares]), np.concatenate([q[1] for q in squares])
        return optics.concentric_disc(NumpyOps, u1, u2) if active else (u1, u2)

    def _batches(self, rng, src: optics.SourceGeometry, cell, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Means of w f G and of w G over each of ``count`` batches, evaluated in one vectorised pass.
        The discs are drawn batch by batch in the order one batch at a time draws them (pupil, field,
        source), so a batch's points, and every result, do not depend on how batches are grouped; one
        pass over many small batches saves the fixed cost of the ~100 numpy calls of an evaluation."""
        draws = [[self._square(rng, on) for on in self._active] for _ in range(count)]
        pupil, field, sdisc = (self._disc([d[k] for d in draws], self._active[k]) for k in range(3))
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            o, d, w = optics.detector_ray(NumpyOps, self._det, pupil, field)
            O = np.stack([np.broadcast_to(c, w.shape) for c in o], axis=1).astype(np.float64)
            D = np.stack([np.broadcast_to(c, w.shape) for c in d], axis=1).astype(np.float64)
            t, tri = self.caster.first_hit(O, D)
            if np.any(tri < 0):
                raise GeometryError(f"{int(np.sum(tri < 0))} of {tri.size} detector rays miss the sample mesh at "
                                    f"tan eps = {cell[0]:g}, beta = {cell[1]:g}: the detector footprint must lie on "
                                    "the sample; enlarge the mesh or narrow the field",
                                    **mesh_location(self.instrument.sample.mesh))
            X = O + t[:, None] * D
            n = self.caster.normal[tri]
            sp = tuple(np.broadcast_to(c, w.shape) for c in optics.source_point(src, sdisc))
            # eq. 3's source term at the hit point, with the face's normal (profiles included)
            wt, g = optics.source_coupling(NumpyOps, src, X[:, 0], X[:, 1], sp, sdisc, z=X[:, 2],
                                           normal=(n[:, 0], n[:, 1], n[:, 2]))
            wi = np.stack(wt, axis=1)
            g = np.array(g, dtype=np.float64)
            lit = g > 0.0
            if np.any(lit):
                sel = np.nonzero(lit)[0]
                orig = X[sel] + SHADOW_EPS_M * n[sel]
                dist = np.linalg.norm(np.stack(sp, axis=1)[sel] - X[sel], axis=1)
                shadow = self.caster.blocked(orig, wi[sel], dist - 2 * SHADOW_EPS_M)
                g[sel[shadow]] = 0.0
            # local frame of each face: the BRDF depends on the directions relative to n only
            wo = -D
            s, tt = optics.orthonormal_frame(n)

            def local(vec):
                return (np.einsum("ij,ij->i", vec, s), np.einsum("ij,ij->i", vec, tt), np.einsum("ij,ij->i", vec, n))

            f = road_brdf(NumpyOps, self._P, local(wi), local(wo), self.model.variant, self._terms)
            # a back face reflects nothing in either channel (the Lambert one too: audit 22, a mesh
            # seen from below gave road 0 over Lambert > 0, k_A = 0 +- 0 "converged")
            front = np.einsum("ij,ij->i", wo, n) > 0.0
            if not np.any(front):
                raise GeometryError(f"every detector ray meets the back of the sample mesh at tan eps = {cell[0]:g}, "
                                    f"beta = {cell[1]:g}: the detector is below the mesh's faces there (a face "
                                    "reflects towards the side its normal points to)",
                                    **mesh_location(self.instrument.sample.mesh))
            wg = w * g * front
            shape = (count, self.batch)
            return np.reshape(wg * f, shape).mean(axis=1), np.reshape(wg, shape).mean(axis=1)

    def compute_cell(self, tan_eps: float, beta_deg: float) -> CellResult:
        t0 = time.perf_counter()
        tan_eps, beta_deg = float(tan_eps), float(beta_deg)
        ideal = check_cell(self.instrument, self.model, tan_eps, beta_deg)
        src = optics.source_geometry(self.instrument, tan_eps, beta_deg)
        rng = np.random.default_rng(seed_entropy(self.seed, cell_key(tan_eps), cell_key(beta_deg), 77))
        road = np.empty(0)
        lam = np.empty(0)
        k = se = math.nan
        max_batches = max(self.min_batches, self.max_samples // self.batch)
        group = max(1, GROUP_SAMPLES // self.batch)
        done = False
        while not done and road.size < max_batches:
            n = road.size
            if n < self.min_batches:
                want = self.min_batches - n
            else:   # the batches the 1/N rule predicts are still needed (at least one)
                want = max(1, math.ceil(n * ((se / (self.rel_se * abs(k))) ** 2 - 1.0)))
            count = min(want, group, max_batches - n)
            r, l_ = self._batches(rng, src, (tan_eps, beta_deg), count)
            road = np.concatenate([road, r])
            lam = np.concatenate([lam, l_ / math.pi])
            # the stopping rule after each batch, as if they had come one at a time: the batches
            # beyond the first that meets it are dropped, so the result does not depend on the grouping
            for j in range(max(n + 1, self.min_batches), road.size + 1):
                if not np.sum(lam[:j]) > 0.0:
                    raise no_light(tan_eps, beta_deg)
                ratio, rse = ratio_se(road[:j], lam[:j])
                k, se = ratio / ideal, rse / ideal
                if se <= self.rel_se * abs(k):
                    road, lam, done = road[:j], lam[:j], True
                    break
        converged = bool(se <= self.rel_se * abs(k))
        extra = {"batches": int(road.size), "converged": converged, "rel_se": se / abs(k) if k else math.inf}
        return CellResult(tan_eps=tan_eps, beta_deg=beta_deg, k_a=float(k), se=float(se), converged=converged,
                          samples=int(road.size) * self.batch, seconds=time.perf_counter() - t0, extra=extra,
                          se_dof=float(road.size - 1))


def make_backend(instrument: Instrument, model: RoadModel, *, rel_se: float = DEFAULT_REL_SE, seed: int = 0,
                 batch: int = DEFAULT_BATCH, min_batches: int = DEFAULT_MIN_BATCHES,
                 max_samples: int = DEFAULT_MAX_SAMPLES, **unknown) -> MeshMonteCarloBackend:
    """The numpy ray-casting Monte Carlo (``roadgonio.engines.make_backend("numpy-mc-mesh", ...)``);
    settings as for ``numpy-mc`` (default batch 23^2 = 529, at least 64 batches: 33856 samples, about the
    8 x 4096 of before; at most 5e7 samples per cell)."""
    if unknown:
        raise InputError(f"unknown numpy-mc-mesh setting(s) {', '.join(sorted(unknown))}; expected rel_se, seed, "
                         "batch, min_batches, max_samples", field=sorted(unknown)[0])
    return MeshMonteCarloBackend(instrument, model, rel_se=rel_se, seed=seed, batch=batch, min_batches=min_batches,
                                 max_samples=max_samples)
