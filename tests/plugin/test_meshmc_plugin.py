"""The ray-cast Monte Carlo of a mesh sample (roadgonio.engines.meshmc) against Mitsuba on the same mesh."""
from __future__ import annotations

import math

import numpy as np
import pytest

from roadgonio.engines import make_backend
from roadgonio.instrument.config import load_instrument

from helpers import grid_mesh, with_mesh
from tolerances import z_family


@pytest.mark.slow
def test_corrugated_mesh_agrees_with_mitsuba(tmp_path, mi, r3like):
    """A corrugated sample (2 mm grooves, 40 um deep: slopes up to 3.6 deg, steeper than the 1 deg
    observation, so the detector sees the faces towards it, and the light at tan eps 12 (4.8 deg)
    is partly shadowed): the renderer and the independent numpy ray caster agree within their
    combined SE + float32 floor."""
    from roadgonio.engines.validate import FLOAT32_FLOOR
    inst = load_instrument("lab")
    import trimesh
    grooves = trimesh.load(grid_mesh(tmp_path / "g.ply", np.linspace(-0.6, 0.6, 4801), np.linspace(-0.03, 0.03, 2),
                                     height=lambda x, y: 2e-5 * np.cos(2 * np.pi * x / 2e-3)))
    # a floor 0.1 mm below catches the few rays that slip through float32 cracks between the renderer's
    # triangles (both integrators see it, so it changes nothing between them)
    floor = trimesh.load(grid_mesh(tmp_path / "f.ply", np.linspace(-0.6, 0.6, 2), np.linspace(-0.03, 0.03, 2),
                                   height=lambda x, y: -1e-4 + 0.0 * x))
    trimesh.util.concatenate([grooves, floor]).export(tmp_path / "groove.ply")
    m_inst = with_mesh(inst, tmp_path / "groove.ply")
    model = r3like
    cells = [(12.0, 0.0), (4.0, 0.0), (1.0, 90.0)]
    for cell in cells:
        a = make_backend("numpy-mc-mesh", m_inst, model, rel_se=3e-3, seed=1).compute([cell])[0]
        b = make_backend("mitsuba", m_inst, model, rel_se=3e-3, seed=2).compute([cell])[0]
        assert a.converged and b.converged, (cell, a, b)
        allowed = z_family(len(cells)) * math.hypot(a.se, b.se) + FLOAT32_FLOOR["mitsuba"] * abs(a.k_a)
        assert abs(a.k_a - b.k_a) <= allowed, (cell, a.k_a, b.k_a)
