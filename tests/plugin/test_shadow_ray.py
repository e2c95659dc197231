"""The shadow ray of the batched engine (plugins/ka_batch.py, :func:`shadow_ray`): a part that shades
the footprint shades exactly where its edge is, to the ~10 um its float32 geometry allows.

User audit (session 36): ``SurfaceInteraction.spawn_ray_to`` lifts the shadow ray's origin off the
sample by Mitsuba's ray epsilon x (1 + |p|), ~1e-4 m, so a wall stood 0.1 mm lower and the holder
preset's k_A was 1-2e-4 low (12-25 of its SEs at rel-se 1e-5)."""
from __future__ import annotations

import numpy as np
import pytest


def _scene(mi, top_m):
    """The sample plane z = 0 and a black wall at x = 0.3 m (0.01 m thick) of height ``top_m``."""
    return mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([2.0, 2.0, 1.0])},
        "wall": {"type": "cube", "to_world": mi.ScalarTransform4f().translate([0.3, 0.0, top_m / 2])
                 .scale([0.005, 1.0, top_m / 2])},
    })


@pytest.mark.parametrize("miss_m", [3e-5, -3e-5])
def test_a_wall_shades_at_its_edge(mi, miss_m):
    """A lit point on the floor and a source 1 m away at grazing incidence (tan eps 12) whose line
    passes ``miss_m`` above (+) or below (-) the wall's top edge: the shadow ray is free or blocked
    accordingly at 30 um, where the ray spawned from the surface is lifted ~100 um and sees over a
    wall 30 um too high."""
    import drjit as dr
    from roadgonio.engines.mitsuba.plugins.ka_batch import shadow_ray
    eps = np.arctan(12.0)
    p = np.array([0.0, 0.0, 0.0])
    w = np.array([np.sin(eps), 0.0, np.cos(eps)])          # towards the source
    src = p + 1.0 * w
    top = float(w[2] / w[0] * (0.3 - 0.005))                  # the line's height at the wall's near face
    scene = _scene(mi, top - miss_m)
    pt, st = mi.Point3f(*map(float, p)), mi.Point3f(*map(float, src))
    ray = shadow_ray(pt, st)
    blocked = bool(dr.all(scene.ray_test(ray)))
    assert blocked == (miss_m < 0)
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.p, si.n = pt, mi.Normal3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(si.n)
    spawned = bool(dr.all(scene.ray_test(si.spawn_ray_to(st))))
    if miss_m < 0:
        assert not spawned, "Mitsuba's own spawned ray now sees the edge too: the lift may have changed"
