"""roadgonio design with the Mitsuba backend: the line-of-sight pre-filter against the rendered
rays, a backend's refusal."""
from __future__ import annotations

import numpy as np

from roadgonio.design.feasibility import blocked_cells
from roadgonio.instrument.config import load_instrument


def test_line_of_sight_check_agrees_with_the_rendered_ray_hits(mi):
    """The design's occlusion check and the Mitsuba scene's own ray test (rays that hit the source
    disc instead of the sample) flag the same cells."""
    from roadgonio.engines.mitsuba.scene import build_scene
    from roadgonio.errors import GeometryError
    from roadgonio.surface.model import RoadModel
    inst = load_instrument("portable").with_changes(source={"distance_m": 0.5, "radius_m": 0.04})
    cells = [(t, 180.0) for t in (8.5, 9, 9.5, 10, 12)] + [(10.0, 165.0), (12.0, 150.0)]
    rs = build_scene(inst, RoadModel.lambert())
    rendered = []
    for c in cells:
        try:
            rs.place_source(*c)
        except GeometryError:
            rendered.append(c)
    assert rendered == blocked_cells(inst, cells) == [(9.5, 180.0), (10, 180.0), (12, 180.0)]


def test_backend_refusal_is_a_reason_not_a_crash(tmp_path, monkeypatch):
    """A beam limit a backend cannot model is refused per point by the backend (on the worker);
    the point is kept, infeasible, with the backend's reason; the other point is computed. (Every
    backend models a clipping beam limit since session 22: a backend without that capability is
    stood in for by the registry's entry of the Mitsuba backend with it switched off.)"""
    import dataclasses

    import roadgonio.engines.registry as registry
    from roadgonio import design_study as run_design
    monkeypatch.setitem(registry.BACKENDS, "mitsuba",
                        dataclasses.replace(registry.BACKENDS["mitsuba"], beam_clipping=False))
    ds = run_design("portable", ["source.beam_half_angle_deg=1,60"], ["R3"], cells="4:2", backend="mitsuba",
                    accuracy="fast", workers=0, progress=False, plots=False)
    kind, reason = ds["kind"].values, ds["reason"].values
    assert kind[0] == "backend" and "beam limit" in reason[0] and "R3" in reason[0]
    assert ds["geometry_ok"].values.tolist() == [False, True] and np.isfinite(ds["k_a"].values[1]).all()
