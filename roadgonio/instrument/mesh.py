"""The sample surface as a triangle mesh (docs/conventions.md section 4): the flat rectangle of
``[sample] size_x_m`` x ``size_y_m`` or the instrument's mesh file, read with trimesh and checked.

The sample is one-sided: its faces must face +z (the renderer sees no light on a face turned
away). Any backend that needs the sample as triangles takes it from :func:`sample_trimesh`; the
conversion to a renderer's own mesh type lives with that renderer
(:func:`roadgonio.engines.mitsuba.scene.to_mitsuba_mesh`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roadgonio.errors import InputError


def rectangle_trimesh(size_x_m: float, size_y_m: float, delta_deg: float = 0.0):
    """Two triangles: the rectangle ``size_x_m`` x ``size_y_m`` on z = 0 centred on the origin, facing +z,
    its side ``size_x_m`` along the observation azimuth ``delta_deg``."""
    import trimesh
    t = rectangle_triangles(size_x_m, size_y_m, delta_deg)
    return trimesh.Trimesh(vertices=t.vertices, faces=t.faces, process=False)


def load_trimesh(path: str | Path):
    """A trimesh-readable mesh file as one ``trimesh.Trimesh``; errors name the file."""
    import trimesh
    path = Path(path)
    try:
        raw = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises many kinds
        raise InputError(f"cannot read the sample mesh ({err})", path=path, field="sample.mesh") from None
    if hasattr(raw, "faces") and len(raw.faces):
        # audit 28: trimesh drops the triangles of a vertex that is not a finite number, and the hole
        # was reported as detector rays missing the sample
        corners = np.asarray(raw.vertices, dtype=np.float64)[np.asarray(raw.faces)]
        bad = ~np.isfinite(corners).all(axis=(1, 2))
        if bad.any():
            v = np.flatnonzero(~np.isfinite(np.asarray(raw.vertices, dtype=np.float64)).all(axis=1))
            raise InputError(f"{int(bad.sum())} triangle(s) of the sample mesh have a vertex that is not a finite number "
                             f"(vertex {int(v[0]) + 1}, counting from 1{', ...' if v.size > 1 else ''}); expected "
                             "finite coordinates in metres", path=path, field="sample.mesh")
    # the file read once: processed as trimesh.load's default would (merged vertices)
    mesh = trimesh.Trimesh(vertices=raw.vertices, faces=raw.faces, process=True) if hasattr(raw, "faces") else raw
    if not hasattr(mesh, "faces") or len(mesh.faces) == 0:
        # trimesh drops the faces of vertices that are not finite numbers (a NaN vertex left "no triangles")
        raise InputError("the sample mesh has no triangles (or none whose vertices are finite numbers)", path=path,
                         field="sample.mesh")
    from roadgonio.instrument.config import MAX_LENGTH_M
    span = mesh_span(mesh)
    if not span <= MAX_LENGTH_M:        # audit 22: a mesh in millimetres passed, the same rectangle did not
        raise InputError(f"the sample mesh spans {span:.4g} units: expected metres, at most {MAX_LENGTH_M:g} m (no "
                         "instrument is larger; a mesh drawn in millimetres must be scaled by 0.001)", path=path,
                         field="sample.mesh")
    return mesh


def mesh_span(mesh) -> float:
    """The largest extent of ``mesh`` along x, y or z (its file's units)."""
    return float(np.max(np.asarray(mesh.bounds[1], dtype=np.float64) - np.asarray(mesh.bounds[0], dtype=np.float64)))


def mesh_location(path) -> dict:
    """Where an error about the sample mesh points: its file and key (``path`` and ``field`` of
    :class:`~roadgonio.errors.InputError` or :class:`~roadgonio.errors.GeometryError`); nothing
    without a file (the plain rectangle)."""
    return {} if path is None else {"path": path, "field": "sample.mesh"}


def check_mesh_orientation(mesh, where: str = "sample mesh", path=None) -> None:
    """The sample is one-sided (faces must face +z): refuse a mesh facing downwards (the error names
    ``path``, the mesh file, when given)."""
    normals = np.asarray(mesh.face_normals, dtype=np.float64)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    nz = float(np.sum(normals[:, 2] * area) / max(np.sum(area), 1e-300))
    if nz <= 0.0 and (abs(nz) < 1e-9 or getattr(mesh, "is_watertight", False)):
        # audit 22: a closed solid or a vertical surface was told to reverse its winding, which cannot help
        raise InputError(f"the {where}'s face normals average to z = {nz:.3g}: a closed solid or a vertical "
                         "surface has no side facing up; the sample is one open surface facing +z (its top only)",
                         **mesh_location(path))
    if nz <= 0.0:
        raise InputError(f"the {where}'s faces point downwards (area-weighted mean normal z = {nz:.3g}); "
                         "the sample surface is one-sided: reverse the face winding so that it faces +z",
                         **mesh_location(path))


@dataclass(frozen=True)
class Triangles:
    """Vertices (n x 3, metres) and faces (m x 3 vertex indices) of a triangle mesh: what a renderer
    needs of the sample, without loading trimesh for the plain rectangle (trimesh's import takes
    0.35 s of every `roadgonio ka` run otherwise)."""
    vertices: np.ndarray
    faces: np.ndarray


def rectangle_triangles(size_x_m: float, size_y_m: float, delta_deg: float = 0.0) -> Triangles:
    """The two triangles of :func:`rectangle_trimesh` as plain arrays (same vertices, same winding):
    the side ``size_x_m`` runs along the observation azimuth ``delta_deg`` (docs/conventions.md
    section 4), i.e. the rectangle is turned by delta about the vertical."""
    hx, hy = size_x_m / 2.0, size_y_m / 2.0
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    c, s = math.cos(math.radians(delta_deg)), math.sin(math.radians(delta_deg))
    if delta_deg % 360.0 == 0.0:
        c, s = 1.0, 0.0                 # exactly the unturned rectangle
    xy = np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]], axis=1)
    return Triangles(np.column_stack([xy, np.zeros(4)]), np.array([[0, 1, 2], [0, 2, 3]]))


def sample_triangles(instrument):
    """The sample's triangles for a renderer (``instrument``: an instrument.config.Instrument; not
    imported here, config -> housing -> mesh would close a circle): the rectangle as :class:`Triangles`, or the checked mesh
    file (:func:`sample_trimesh`); both have ``vertices`` and ``faces``."""
    if instrument.sample.mesh is None:
        return rectangle_triangles(instrument.sample.size_x_m, instrument.sample.size_y_m,
                                   instrument.observation.delta_deg)
    return sample_trimesh(instrument)


def sample_trimesh(instrument):
    """The instrument's sample as a checked trimesh: its rectangle, or its mesh file (which must face +z)."""
    smp = instrument.sample
    if smp.mesh is None:
        return rectangle_trimesh(smp.size_x_m, smp.size_y_m, instrument.observation.delta_deg)
    tm = load_trimesh(smp.mesh)
    check_mesh_orientation(tm, path=smp.mesh)
    _note_mesh_scale(tm, instrument)
    return tm


#: A sample mesh spanning more than this many times the instrument's largest distance is said in a
#: note (user audit, session 38: a 0.5 m x 0.2 m sample drawn in millimetres was read as 500 m x 200 m
#: without a word; under the 1000 m limit, and a flat one gives the same k_A, but not a bumpy one). 10,
#: not 50: a 0.3 m sample in millimetres under the lab's 10 m was missed at 50.
MESH_SPAN_NOTE_RATIO = 10.0


def _note_mesh_scale(mesh, instrument) -> None:
    src, det = instrument.source, instrument.detector
    scale = max(v for v in (getattr(src, "distance_m", None), getattr(src, "height_m", None),
                            getattr(det, "distance_m", None), 1e-9) if v is not None)
    span = mesh_span(mesh)
    if span > MESH_SPAN_NOTE_RATIO * scale:
        import warnings

        from roadgonio.errors import ModelWarning
        warnings.warn(ModelWarning(
            f"{instrument.sample.mesh}: the sample mesh spans {span:.4g} m, {span / scale:.0f} times the instrument's "
            f"largest distance ({scale:g} m): drawn in millimetres? (a mesh is in metres; scale it by 0.001)"),
            stacklevel=2)
