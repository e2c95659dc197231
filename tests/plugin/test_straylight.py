"""Stray light in the Mitsuba backend (issue 18): the light that the reflecting parts of a scene
(an XML wall, the [housing]) send to the footprint.

* one diffuse wall beside the footprint against the independent float64 reference
  (roadgonio/engines/strayref.py);
* a closed white dome over a Lambertian floor against its exact interreflection sum, reflection by
  reflection;
* black parts give the engine without stray light, bit for bit;
* reproducibility and batching, honest standard errors, the checks of [scene] and [housing].
(The render's stray picture: tests/system/test_render_stray.py.)

The reference shares the ray geometry with the Mitsuba backend (roadgonio.instrument.optics: the
detector rays, the source geometry, the plane hits; its docstring says so): a bug there would be in
both. That geometry is checked on its own, against closed forms and independent integrals, by
tests/unit/test_profiles.py.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from roadgonio.errors import GeometryError, InputError, ModelWarning
from roadgonio.instrument.config import Instrument, load_instrument
from roadgonio.surface.model import RoadModel, RoadParams

from helpers import R3LIKE
from tolerances import ALPHA, n_sigma, z_family

SCENES = Path(__file__).resolve().parents[2] / "scenes"
R3 = RoadModel(RoadParams(**R3LIKE), name="R3-like")
#: float32 rounding of a ratio of sums (k_A, the stray fraction) that no standard error covers.
F32_REL = 2e-6
#: float32 rounding of a mean of float32 block sums (the dome's probe signals), relative.
F32_SUM_REL = 1e-5

#: One wall, the plane y = -0.15 m (the sample's edge), x = -0.5 ... 0.5 m, 0.2 m high, facing +y.
WALL_XML = """<scene version="3.0.0">
    <default name="alpha_deg" value="1.0"/>
    <default name="delta_deg" value="0.0"/>
    <default name="detector_distance_m" value="1.0"/>
    <default name="pupil_radius_m" value="0.005"/>
    <default name="field_half_angle_deg" value="0.15"/>
    <default name="focus_m" value="1.0"/>
    <default name="source_radiance" value="509.3"/>
    <default name="sample_half_x_m" value="0.5"/>
    <default name="sample_half_y_m" value="0.15"/>
    <default name="wall_reflectance" value="0.8"/>
    <sensor type="lummeter" id="detector">
        <float name="alpha_deg" value="$alpha_deg"/>
        <float name="delta_deg" value="$delta_deg"/>
        <float name="distance_m" value="$detector_distance_m"/>
        <float name="pupil_radius_m" value="$pupil_radius_m"/>
        <float name="field_half_angle_deg" value="$field_half_angle_deg"/>
        <float name="focus_m" value="$focus_m"/>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
    </sensor>
    <shape type="disk" id="source"><emitter type="area"><float name="radiance" value="$source_radiance"/></emitter></shape>
    <shape type="rectangle" id="sample">
        <transform name="to_world"><scale x="$sample_half_x_m" y="$sample_half_y_m" z="1"/></transform>
        <bsdf type="roadbsdf"/>
    </shape>
    <shape type="rectangle" id="wall">
        <!-- the unit square onto x = -0.5 ... 0.5, z = 0 ... 0.2 at y = -0.15, normal +y -->
        <transform name="to_world"><matrix value="0.5 0 0 0  0 0 1 -0.15  0 -0.1 0 0.1  0 0 0 1"/></transform>
        <bsdf type="diffuse"><float name="reflectance" value="$wall_reflectance"/></bsdf>
    </shape>
</scene>
"""


def wall_instrument(tmp_path, reflectance: float = 0.8, max_bounces: int | None = 3) -> Instrument:
    (tmp_path / "wall.xml").write_text(WALL_XML)
    scene = {"xml": "wall.xml", "params": {"wall_reflectance": reflectance}}
    if max_bounces is not None:
        scene["max_bounces"] = max_bounces
    d = load_instrument("portable").to_dict()
    d["scene"] = scene
    return Instrument.from_dict(d, path=tmp_path / "wall.toml")


def housed(reflectance: float, **housing) -> Instrument:
    d = load_instrument(str(SCENES / "portable_housed.toml")).to_dict()
    d["housing"] = {**d["housing"], "wall_reflectance": reflectance, **housing}
    return Instrument.from_dict(d, path=SCENES / "portable_housed.toml")


def mitsuba(inst, model=R3, **kw):
    from roadgonio.engines import make_backend
    return make_backend("mitsuba", inst, model, **kw)


# ----------------------------------------------------------------------------------------------
# Against the independent float64 reference
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("cell,cone_deg", [((12.0, 0.0), None), ((3.0, 30.0), None), ((8.0, 90.0), None),
                                           ((12.0, 0.0), 15.0), ((3.0, 30.0), 15.0)])
def test_one_wall_agrees_with_the_float64_reference(tmp_path, cell, cone_deg):
    """k_A with the wall, k_A of the direct light and the stray fraction from the Mitsuba backend
    against the float64 reference (roadgonio/engines/strayref.py), each within 4 combined standard
    errors (plus float32 rounding). With one planar wall and the flat one-sided sample, light reaches
    the footprint with at most three reflections only along the direct path and the two first-order
    paths (source -> wall -> x0, source -> sample -> wall -> x0): with max_bounces = 3 both sides hold
    exactly these terms, so the bound of the omitted (second-order, rho^2) terms is 0 by
    construction. The stray light must be far outside the error bars (the test could not pass if the
    backend ignored the wall or lost a factor).

    With a hard emission cone of 15 deg (``beam_half_angle_deg``, inside which the footprint lies)
    the source lights only part of the wall: the stray fraction falls from 0.0063 to 0.0046 at
    tan eps 12 and from 0.26 to 0.18 at tan eps 3 (audit 22: the backend ignored the cone on the
    stray paths, and gave the uncut numbers)."""
    from roadgonio.engines.strayref import Wall, reference
    inst = wall_instrument(tmp_path)
    if cone_deg is not None:
        d = inst.to_dict()
        d["source"]["beam_half_angle_deg"] = cone_deg
        inst = Instrument.from_dict(d, path=tmp_path / "wall.toml")
    wall = Wall(y_m=-0.15, x0_m=-0.5, x1_m=0.5, height_m=0.2, reflectance=0.8)
    r = mitsuba(inst, rel_se=5e-4, seed=3).compute([cell])[0]
    assert r.converged, r              # a comparison of an unconverged result is no check
    ref = reference(inst, R3, wall, *cell, samples=1 << 21, batches=32, seed=5)
    for key, se_key in (("k_a", "se"), ("k_a_direct", "k_a_direct_se"), ("stray_fraction", "stray_fraction_se")):
        m, q = getattr(r, key), ref[key]
        # the t quantile of the smaller degrees of freedom (conservative for the combined SE)
        tol = n_sigma(min(r.se_dof, ref["se_dof"])) * math.hypot(getattr(r, se_key), ref[se_key]) + F32_REL * abs(q)
        assert abs(m - q) <= tol, (cell, key, m, q, tol)
    sigma = math.hypot(r.stray_fraction_se, ref["stray_fraction_se"])
    assert ref["stray_fraction"] > 20 * sigma, ref["stray_fraction"]
    assert abs(r.k_a - r.k_a_direct) > 20 * math.hypot(r.se, r.k_a_direct_se)


# ----------------------------------------------------------------------------------------------
# Energy: a closed white dome
# ----------------------------------------------------------------------------------------------

def dome_sums(mi, k_max: int, albedo: float, n_log2: int = 12, reps: int = 16, seed: int = 0):
    """Per replicate, the mean road and Lambert values (direct, stray) of rays probing the floor of
    the dome uniformly (see the test's docstring), the source's power and the floor's area."""
    import drjit as dr

    from roadgonio.engines.mitsuba import lattice as lat
    from roadgonio.engines.mitsuba.engine import cell_sources
    from roadgonio.engines.mitsuba.plugins import register_plugins
    from roadgonio.engines.mitsuba.plugins.ka_batch import _u32, canonical_source
    register_plugins()
    R, D_S, R_S, L = 1.0, 0.4, 0.05, 10.0

    class FloorProbe(mi.Sensor):
        """Rays straight down onto a uniform point of the floor disc (radius R), weight 1."""

        def sample_ray(self, time, sample1, sample2, sample3, active=True):
            p = mi.warp.square_to_uniform_disk_concentric(sample2) * (R * (1.0 - 1e-6))
            ray = mi.Ray3f(mi.Point3f(p.x, p.y, 1e-4), mi.Vector3f(0.0, 0.0, -1.0))
            return ray, mi.Spectrum(1.0)

    mi.register_sensor("floorprobe", lambda props: FloorProbe(props))
    scene = mi.load_dict({
        "type": "scene",
        "sample": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([1.1 * R, 1.1 * R, 1.0]),
                   "bsdf": {"type": "roadbsdf", "channels": "road_lambert", "k_diff": albedo / math.pi}},
        "dome": {"type": "sphere", "radius": R, "flip_normals": True,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "uniform", "value": 1.0}}},
        "probe": {"type": "floorprobe", "film": {"type": "hdrfilm", "width": 4, "height": 4}},
    }, optimize=False)
    shapes = {s.id(): s for s in scene.shapes()}
    integ = mi.load_dict({"type": "kabatch", "flat": True, "shadow": True})
    integ.set_sample(shapes["sample"])
    emitter, disc = canonical_source(R_S, L)
    integ.set_source(emitter)              # disc: kept alive here
    from roadgonio.instrument.config import Source
    inst = Instrument(source=Source(distance_m=D_S, radius_m=R_S))
    integ.set_cells(*cell_sources(inst, [(1.0, 30.0)]))
    integ.set_parts([shapes["sample"], shapes["dome"]], k_max, R_S, L)
    n = 1 << n_log2
    z = lat.generating_vector(n, lat.DIMENSIONS + integ.qmc_dims)
    shifts = np.concatenate([lat.shifts(seed, 0, n_log2, reps), lat.walk_shifts(seed, 0, n_log2, reps, integ.qmc_dims)], 1)
    lattice = integ.lattice_params(n, z, shifts)
    keys_all = lat.walk_keys(seed, 0, n_log2, reps, integ.walk_dims)
    keys = [_u32(keys_all[:, d]) for d in range(keys_all.shape[1])]
    rays, verts, misses = integ.trace_paths(scene, scene.sensors()[0], lattice, reps, keys)
    assert misses == 0
    bc, br = np.zeros(reps, dtype=np.int64), np.arange(reps)
    direct = integ.block_sums(scene, rays, lattice, bc, br).astype(np.float64).sum(axis=1) / n
    stray = np.zeros_like(direct)
    for k in integ.eye_vertices():
        stray += integ.stray_sums(scene, verts[k - 1], lattice, bc, br, keys, k).astype(np.float64).sum(axis=1) / n
    if integ.light_depth:
        stray += integ.light_sums(scene, rays, verts[0], lattice, bc, br, keys).astype(np.float64).sum(axis=1) / n
    dr.flush_malloc_cache()
    return direct, stray, math.pi * L * math.pi * R_S ** 2, math.pi * R * R


def interreflection(f0: np.ndarray, flux: float, albedo: float, reflections: int) -> np.ndarray:
    """sum_{k=1}^{reflections} f_k of the dome's recursion (test docstring) for each f_0."""
    f, d = np.asarray(f0, dtype=np.float64), flux - np.asarray(f0, dtype=np.float64)
    total = np.zeros_like(f)
    for _ in range(reflections):
        f, d = d / 2.0, albedo * f + d / 2.0
        total = total + f
    return total


@pytest.mark.parametrize("k_max", [2, 3, 4, 8, 16])
def test_closed_white_dome_converges_to_the_interreflection_sum(mi, k_max):
    """A hemispherical dome of radius R (Lambertian, reflectance 1) closed by the floor disc z = 0,
    the sample (Lambertian, albedo rho), with the cell's source disc inside. Exact exchange
    factors: a point P of the dome sees the floor in the same solid angles as the lower half of the
    sphere (every line from P into the lower half crosses the equatorial disc), and a point of a
    sphere sees any part of it in proportion to its area (the integrating-sphere property), so
    every dome point sends exactly 1/2 of what it reflects to the floor and 1/2 to the dome, and
    the floor sends everything it reflects to the dome. With f_k, d_k the power reaching the floor
    and the dome after k reflections, f_0 the source's direct power on the floor and
    d_0 = Phi - f_0 (the closed dome catches the rest; Phi = pi L A_S)::

        f_{k+1} = d_k / 2,        d_{k+1} = rho f_k + d_k / 2.

    Rays probing the floor uniformly (straight down, weight 1) see the floor radiance
    rho E / pi, so their mean is rho / (pi A) times the power reaching the floor: the direct part
    rho f_0 / (pi A), and with max_bounces = K the stray part rho / (pi A) sum_{k=1}^{K-1} f_k (the
    Lambert channel: the same with rho = 1 at the floor). The test takes f_0 from each replicate's
    direct Lambert signal and checks every replicate's stray signal against the recursion (the
    difference within 4 standard errors (the t quantile of the replicates' degrees of freedom) +
    float32 rounding), in both channels. As K grows the road
    channel's total tends to the analytic rho Phi / ((1 - rho) pi A): everything the source emits
    is absorbed by the floor (sum_k f_k = Phi / (1 - rho)); the last step checks that limit with
    the recursion's own tail beyond K."""
    rho = 0.3
    direct, stray, flux, area = dome_sums(mi, k_max, rho)
    f0 = math.pi * area * direct[:, 1]
    for ch, a in ((0, rho), (1, 1.0)):
        pred = a / (math.pi * area) * interreflection(f0, flux, a, k_max - 1)
        diff = stray[:, ch] - pred
        se = diff.std(ddof=1) / math.sqrt(len(diff))
        k = n_sigma(len(diff) - 1)              # an SE of len(diff) replicates: the t quantile
        assert abs(diff.mean()) <= k * se + F32_SUM_REL * pred.mean(), (k_max, ch, diff.mean(), se, pred.mean())
        assert pred.mean() > 50 * se            # the stray light is large against its error
    total = direct[:, 0] + stray[:, 0]
    tail = rho / (math.pi * area) * (interreflection(f0, flux, rho, 400) - interreflection(f0, flux, rho, k_max - 1))
    limit = rho * flux / ((1.0 - rho) * math.pi * area)
    se = (total + tail).std(ddof=1) / math.sqrt(len(total))
    assert abs((total + tail).mean() - limit) <= n_sigma(len(total) - 1) * se + F32_SUM_REL * limit
    if k_max == 16:
        assert tail.mean() < 0.01 * limit       # within 1 % of the analytic sum after 16 reflections


# ----------------------------------------------------------------------------------------------
# Black parts: the engine without stray light, bit for bit
# ----------------------------------------------------------------------------------------------

CELLS = [(12.0, 0.0), (12.0, 2.0), (6.0, 10.0), (2.0, 0.0), (0.0, 0.0), (1.0, 90.0), (4.0, 180.0)]


@pytest.mark.parametrize("accuracy", ["fast", "default", "precise"])
def test_black_housing_gives_the_bare_instrument_bit_for_bit(accuracy):
    """A housing with reflectance-0 walls only shades (it is no reflecting part: the fast direct path
    runs), and it shades nothing of this instrument: every preset gives the numbers of the same
    instrument without the housing, bit for bit; the stray fraction is 0 exactly."""
    d = housed(0.0).to_dict()
    del d["housing"]
    bare = mitsuba(Instrument.from_dict(d), accuracy=accuracy).compute(CELLS)
    b = mitsuba(housed(0.0), accuracy=accuracy)
    assert not b.rs.stray and b.rs.info["reflecting_parts"] == []
    black = b.compute(CELLS)
    assert [(r.k_a, r.se, r.samples) for r in black] == [(r.k_a, r.se, r.samples) for r in bare]
    assert all(r.stray_fraction == 0.0 and r.k_a_direct == r.k_a for r in black)


@pytest.mark.parametrize("name", ["housed", "holder"])
def test_paths_through_black_parts_give_the_direct_numbers_bit_for_bit(name):
    """The stray-light machinery forced on (paths with 3 reflections, light paths, MIS) over parts
    that reflect nothing: the stray sums are exactly 0, so k_A, its SE, the plan and the samples are
    those of the engine without stray light, bit for bit (portable in a black housing, and
    scenes/holder.toml, whose XML walls are black); k_a_direct = k_a and the stray fraction is 0."""
    from roadgonio.engines.mitsuba.engine import BatchEngine
    inst = housed(0.0) if name == "housed" else load_instrument(str(SCENES / "holder.toml"))
    plain = mitsuba(inst, rel_se=1e-3).compute(CELLS)
    b = mitsuba(inst, rel_se=1e-3)
    b.engine = BatchEngine(b.rs, max_bounces=3)
    assert b.engine.stray and b.engine.integrator.light_depth == 2
    forced = b.compute(CELLS)
    assert [(r.k_a, r.se, r.samples) for r in forced] == [(r.k_a, r.se, r.samples) for r in plain]
    assert all(r.stray_fraction == 0.0 and r.stray_fraction_se == 0.0 and r.k_a_direct == r.k_a for r in forced)


def test_holder_scene_holds_no_reflecting_part():
    """scenes/holder.toml: its wall and rails are black, so the engine without stray light runs."""
    b = mitsuba(load_instrument(str(SCENES / "holder.toml")), rel_se=1e-2)
    assert not b.rs.stray
    assert sorted(b.rs.info["black_parts"]) == ["rail_left", "rail_right", "wall"]


# ----------------------------------------------------------------------------------------------
# Reproducibility, batching, standard errors
# ----------------------------------------------------------------------------------------------

def test_stray_cells_are_reproducible_and_independent_of_their_batch():
    """Same seed, same numbers bit for bit; a cell alone gets the numbers it gets in a batch (the
    paths and light paths depend on (seed, pass, lattice size, replicate, point) only)."""
    b = mitsuba(housed(0.05), rel_se=1.0, first_pass=2048, seed=4)
    batch = b.compute(CELLS)
    again = b.compute(CELLS)
    key = lambda r: (r.k_a, r.se, r.k_a_direct, r.k_a_direct_se, r.stray_fraction, r.stray_fraction_se)
    assert [key(r) for r in again] == [key(r) for r in batch]
    for cell, r in zip(CELLS[::3], batch[::3]):
        assert key(b.compute([cell])[0]) == key(r)
    assert all(r.stray_fraction > 0.0 for r in batch)


def test_stray_standard_errors_are_honest():
    """24 seeds, one pass of three cells in a reflecting housing: the scatter of k_A, k_a_direct and
    the stray fraction over the seeds against their mean claimed SE. With 23 degrees of freedom,
    23 (s / SE)^2 is chi-square distributed if the SE is right; the bounds on s / SE are its
    quantiles at ALPHA / 2 per side, shared out over the nine checks (tests/tolerances.py)."""
    from scipy.stats import chi2
    m = 9
    lo, hi = (math.sqrt(chi2.ppf(q, 23) / 23) for q in (ALPHA / (2 * m), 1 - ALPHA / (2 * m)))
    cells = [(12.0, 0.0), (10.0, 45.0), (0.5, 180.0)]
    vals = {k: [] for k in ("k_a", "k_a_direct", "stray_fraction")}
    ses = {k: [] for k in vals}
    for seed in range(24):
        res = mitsuba(housed(0.1), rel_se=1.0, first_pass=4096, seed=seed).compute(cells)
        for key, se_key in (("k_a", "se"), ("k_a_direct", "k_a_direct_se"), ("stray_fraction", "stray_fraction_se")):
            vals[key].append([getattr(r, key) for r in res])
            ses[key].append([getattr(r, se_key) for r in res])
    for key in vals:
        v, s = np.array(vals[key]), np.array(ses[key])
        ratio = v.std(axis=0, ddof=1) / np.sqrt((s ** 2).mean(axis=0))
        assert np.all((ratio > lo) & (ratio < hi)), (key, ratio, lo, hi)


def _absolute(inst: Instrument) -> Instrument:
    d = inst.to_dict()
    d["calibration"] = {"mode": "absolute"}
    return Instrument.from_dict(d, path=inst.path)


def test_calibration_modes_carry_the_stray_light(tmp_path):
    """absolute: k_a = k_a_direct / (1 - stray fraction) with k_a_direct = k_lam_direct eta; a
    reference equal to the sample: k_A = 1 exactly, with the sample's stray fraction."""
    from roadgonio.engines.calibration import illuminance_ratio
    inst = housed(0.1)
    lam = mitsuba(inst, rel_se=3e-3, seed=1).compute([(3.0, 20.0)])[0]
    absolute = mitsuba(_absolute(inst), rel_se=3e-3, seed=1).compute([(3.0, 20.0)])[0]
    eta = illuminance_ratio(inst, 3.0, 20.0)[0]
    assert absolute.k_a_direct == pytest.approx(lam.k_a_direct * eta, rel=1e-12)
    assert absolute.k_a == pytest.approx(lam.k_a_direct * eta / (1.0 - lam.stray_fraction), rel=1e-12)
    assert absolute.stray_fraction == lam.stray_fraction > 0.0


@pytest.mark.parametrize("model,cell,target", [(R3, (12.0, 90.0), 5e-4),
                                               (RoadModel.lambert(), (3.0, 90.0), 2e-4)])
def test_absolute_calibration_converges_on_what_it_reports(model, cell, target):
    """(User audit, session 43) Under the absolute calibration a housed cell reports
    k_A = eta R / G_d / ideal (the road's total over the Lambert sample's direct light), but the
    backend stopped on the Lambert ratio R / G: R3 at tan 12, beta 90 said "converged" at a relative
    SE of 1.04e-3 for 5e-4 asked, and a Lambertian sample (R / G = 1 exactly, SE 0) stopped after its
    first 4096 samples at 2.1e-3 for 2e-4. The cell now converges on the reported k_A; its SE is the
    delta method's over the same replicates, and k_A is that ratio to rounding."""
    r = mitsuba(_absolute(housed(0.05)), model, rel_se=target).compute([cell])[0]
    assert r.converged and r.stray_fraction > 0.0
    assert r.se <= target * abs(r.k_a)
    x = r.extra
    assert r.se == pytest.approx(abs(r.k_a) * x["absolute_ratio_se"] / x["absolute_ratio"], rel=1e-12)
    assert r.k_a == pytest.approx(x["eta"] * x["absolute_ratio"] / x["ideal_ratio"], rel=1e-9)


def test_absolute_stray_standard_error_is_honest():
    """24 seeds, one pass: the scatter of the absolute calibration's k_A (with stray light) over the
    seeds against its mean claimed SE (the delta method of R / G_d), chi-square bounds as in
    test_stray_standard_errors_are_honest, shared over the two cells."""
    from scipy.stats import chi2
    m = 2
    lo, hi = (math.sqrt(chi2.ppf(q, 23) / 23) for q in (ALPHA / (2 * m), 1 - ALPHA / (2 * m)))
    cells = [(12.0, 90.0), (3.0, 20.0)]
    inst = _absolute(housed(0.1))
    res = [mitsuba(inst, rel_se=1.0, first_pass=4096, seed=seed).compute(cells) for seed in range(24)]
    v = np.array([[r.k_a for r in row] for row in res])
    s = np.array([[r.se for r in row] for row in res])
    ratio = v.std(axis=0, ddof=1) / np.sqrt((s ** 2).mean(axis=0))
    assert np.all((ratio > lo) & (ratio < hi)), (ratio, lo, hi)


def test_an_exact_k_a_says_the_target_has_nothing_to_reach():
    """A Lambertian sample under the Lambert calibration: k_A = 1 with SE 0 at the first pass, and
    the stray fraction's SE is what that pass gives; the cell says so (it said nothing while
    --rel-se 1e-4 changed nothing)."""
    r = mitsuba(housed(0.05), RoadModel.lambert(), rel_se=1e-4).compute([(3.0, 90.0)])[0]
    assert r.k_a == 1.0 and r.se == 0.0 and r.stray_fraction > 0.0
    assert "nothing to reach" in r.extra["note"] and "absolute calibration" in r.extra["note"]


# ----------------------------------------------------------------------------------------------
# What the scene requires, and the checks
# ----------------------------------------------------------------------------------------------

def test_housing_floor_is_road_around_the_sample():
    """The box's floor around the 1 m x 0.3 m sample is the same road (the sample's BRDF in both
    channels: a Lambert calibration replaces the sample only): strips at x < -0.5, x > 0.5 and
    y > 0.15 (the box reaches y = -0.075 only, inside the sample); with black walls the floor, in the
    sample's plane, cannot light the footprint, so no stray light is traced."""
    b = mitsuba(housed(0.05), rel_se=1.0, first_pass=256)
    floor = sorted(p for p in b.rs.part_ids if p.startswith("housing_floor_"))
    assert floor == ["housing_floor_x_max", "housing_floor_x_min", "housing_floor_y_max"]
    bsdf = next(s for s in b.rs.parts if s.id() == "housing_floor_x_min").bsdf()
    assert bsdf.channels == "road" and bsdf.model_values() == R3.params.to_dict()
    b = mitsuba(housed(0.0), rel_se=1.0, first_pass=256)
    assert not b.rs.stray and "housing_floor_x_min" in b.rs.info["black_parts"]


def test_reflecting_parts_switch_the_stray_light_on(tmp_path):
    from roadgonio.engines.mitsuba.scene import default_max_bounces
    b = mitsuba(wall_instrument(tmp_path, 0.8, max_bounces=None), rel_se=1.0, first_pass=256)
    rho = b.rs.info["part_reflectance_max"]
    assert abs(rho - 0.8) < 0.01                 # the wall's diffuse reflectance, by its own sampling
    assert b.rs.stray and b.engine.max_bounces == default_max_bounces(rho) >= 30 and b.rs.part_ids == ["wall"]
    b = mitsuba(wall_instrument(tmp_path, 0.0, max_bounces=None), rel_se=1.0, first_pass=256)
    assert not b.rs.stray and b.rs.info["black_parts"] == ["wall"]
    b = mitsuba(wall_instrument(tmp_path, 0.8, max_bounces=1), rel_se=1.0, first_pass=256)
    assert not b.rs.stray                       # max_bounces = 1: the sample's own reflection only


def test_scene_keys_are_checked(tmp_path):
    d = load_instrument("portable").to_dict()
    for scene, field in (({"xlm": "a.xml"}, "scene.xlm"), ({"max_bounces": 0}, "scene.max_bounces"),
                         ({"max_bounces": 2.5}, "scene.max_bounces"), ({"params": 3}, "scene.params")):
        with pytest.raises(InputError) as err:
            Instrument.from_dict({**d, "scene": scene}, path=tmp_path / "x.toml")
        assert err.value.field == field and "x.toml" in str(err.value)
    p = tmp_path / "typo.toml"
    p.write_text((SCENES / "holder.toml").read_text().replace('xml = "holder.xml"', 'xlm = "holder.xml"'))
    with pytest.raises(InputError) as err:
        Instrument.load(p)
    assert "xlm" in str(err.value) and "typo.toml" in str(err.value)


def test_an_xml_scene_with_a_housing_and_other_lights(tmp_path):
    """(audit 22) An XML scene with a [housing] crashed with a traceback (`Emitter.shape()`), and
    light sources other than the source in the XML were dropped without a word. The merged scene
    computes (the black holder in a housing of 0.05 gets stray light from the housing's walls); a
    constant background or a second lit shape is one InputError naming the XML file."""
    import shutil
    shutil.copy(SCENES / "holder.xml", tmp_path / "holder.xml")
    text = (SCENES / "holder.toml").read_text()
    (tmp_path / "housed.toml").write_text(text + "\n[housing]\nwall_reflectance = 0.05\n")
    inst = Instrument.load(tmp_path / "housed.toml")
    r = mitsuba(inst, rel_se=1e-2, seed=1).compute([(12.0, 0.0)])[0]
    bare = mitsuba(Instrument.load(SCENES / "holder.toml"), rel_se=1e-2, seed=1).compute([(12.0, 0.0)])[0]
    assert r.stray_fraction > 10 * r.stray_fraction_se and bare.stray_fraction == 0.0
    xml = (SCENES / "holder.xml").read_text()
    for extra, words in (('<emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>',
                          "ConstantBackgroundEmitter"),
                         ('<shape type="rectangle" id="lamp"><transform name="to_world"><translate z="2"/></transform>'
                          '<emitter type="area"><rgb name="radiance" value="100"/></emitter></shape>',
                          "AreaLight on shape 'lamp'")):
        (tmp_path / "holder.xml").write_text(xml.replace("</scene>", extra + "\n</scene>"))
        with pytest.raises(InputError, match="light other than the source") as err:
            mitsuba(Instrument.load(tmp_path / "housed.toml"))
        assert words in str(err.value) and "holder.xml" in str(err.value)


def test_a_part_that_reflects_more_than_it_receives_is_refused(tmp_path):
    """(audit 27) A holder wall with diffuse reflectance 1.5 ran and added a third more stray light
    without a word ([housing] refuses wall_reflectance > 1). Its directional albedo, estimated from
    the BSDF's own sampling, is checked: 1.5 is one InputError naming the XML file and the part; a
    reflectance of 1 (albedo 1 exactly) and other BSDFs of the scene language pass, each albedo
    where it belongs (a plain Lambertian's is its reflectance)."""
    import shutil

    from roadgonio.engines.mitsuba import set_variant
    from roadgonio.engines.mitsuba.scene import ALBEDO_TOL, directional_albedo_max
    mi = set_variant()
    shutil.copy(SCENES / "holder.toml", tmp_path / "holder.toml")
    xml = (SCENES / "holder.xml").read_text()
    black = '<float name="reflectance" value="0"/>'
    assert black in xml
    import warnings
    for value, ok in (("1.5", False), ("-0.5", False), ("1.0", True), ("0.5", True)):
        (tmp_path / "holder.xml").write_text(xml.replace(black, f'<float name="reflectance" value="{value}"/>'))
        inst = Instrument.load(tmp_path / "holder.toml")
        if ok:
            assert mitsuba(inst, rel_se=1e-2).rs.stray
        else:
            # user audit, session 43: -0.5 was taken for a black part (stray light off, no word), and
            # 1.5 was first warned about as "parts reflecting up to 1" before the error
            words = "reflects more light than it receives" if value == "1.5" else "reflects a negative amount"
            with warnings.catch_warnings(record=True) as said, pytest.raises(InputError, match=words) as err:
                warnings.simplefilter("always")
                mitsuba(inst, rel_se=1e-2)
            assert "holder.xml" in str(err.value) and "'wall'" in str(err.value)
            assert not [w for w in said if issubclass(w.category, ModelWarning)], [str(w.message) for w in said]
    for d, lo, hi in (({"type": "diffuse", "reflectance": 0.3}, 0.3 - 1e-6, 0.3 + 1e-6),
                      ({"type": "diffuse", "reflectance": 1.2}, 1.2 - 1e-6, 1.2 + 1e-6),
                      ({"type": "roughplastic", "alpha": 0.3}, 0.0, 1.0 + ALBEDO_TOL),
                      ({"type": "roughconductor", "alpha": 0.05}, 0.5, 1.0 + ALBEDO_TOL)):
        assert lo <= directional_albedo_max(mi.load_dict(d)) <= hi, d


def test_housing_errors_name_the_cell_and_the_wall():
    from roadgonio.engines.mitsuba.engine import BatchEngine  # noqa: F401  (the backend runs the checks)
    with pytest.raises(GeometryError, match=r"tan eps = 12, beta = 0.*housing_wall_x_min"):
        mitsuba(housed(0.05, x_m=[-0.99, 1.05]), rel_se=1.0, first_pass=256).compute([(1.0, 0.0), (12.0, 0.0)])
    with pytest.raises(InputError, match=r"baffle 0 .*blocks the detector's view") as err:   # a check of the file
        mitsuba(housed(0.05, baffles=[{"x_m": 0.5, "height_m": 0.02}]), rel_se=1.0)
    assert err.value.field == "housing.baffles.0.height_m"
    with pytest.raises(InputError, match="housing"):
        from roadgonio.engines import make_backend
        make_backend("quadrature", housed(0.05), R3)


def test_table_outputs_carry_the_stray_light(tmp_path):
    from roadgonio.engines.runner import ka_dataset, run_cells, write_outputs
    inst = housed(0.05)
    b = mitsuba(inst, accuracy="fast")
    run = run_cells(b, CELLS[:3], instrument=inst, model=R3, out_dir=tmp_path, progress=False)
    ds = ka_dataset(run, instrument=inst, model=R3, backend=b, sample="R3")
    meta = write_outputs(ds, tmp_path, plot=False)
    for f in ("ka_direct.csv", "ka_direct_se.csv", "stray_fraction.csv", "stray_fraction_se.csv"):
        assert (tmp_path / f).exists() and f in meta["files"].values()
    assert meta["summary"]["stray_fraction_max"] == max(r.stray_fraction for r in run.results) > 0.0
    # the file holds a fraction while the console prints per cent: its header says which (trial 10 D10)
    assert "a fraction: 0.3 is 30 %" in (tmp_path / "stray_fraction.csv").read_text().splitlines()[0]


@pytest.mark.parametrize("profile", [{"beam_sigma_deg": 12.0}, {"beam_cos_power": 20.0, "aperture_edge_radiance": 0.3}])
def test_light_paths_carry_the_source_profile(profile):
    """A profiled source (issue 18 item 4) lights the stray paths by its profile: the light paths
    from the source (MIS with the eye paths) give the k_A and stray fraction of the eye paths with
    next-event estimation alone (which weigh every source sample by the profile; tested against the
    quadrature in test_profile_plugin). Walls of 0.2, where the light paths carry most of the stray
    light; without the profile on the light paths k_A is 8-17 % higher at these cells (measured)."""
    d = housed(0.2).to_dict()
    d["source"].update(profile)
    inst = Instrument.from_dict(d, path=SCENES / "portable_housed.toml")
    cells = [(3.0, 30.0), (8.0, 90.0), (11.0, 40.0)]
    both = mitsuba(inst, rel_se=3e-3, seed=1)
    assert both.engine.integrator.light_depth == 2
    eye = mitsuba(inst, rel_se=3e-3, seed=2)
    eye.engine.integrator.light_depth = 0                 # eye paths + next-event estimation only
    for a, b in zip(both.compute(cells), eye.compute(cells)):
        assert a.stray_fraction > 0.05
        for key, se in (("k_a", "se"), ("stray_fraction", "stray_fraction_se")):
            va, vb = getattr(a, key), getattr(b, key)
            assert abs(va - vb) <= n_sigma(min(a.se_dof, b.se_dof)) * math.hypot(getattr(a, se), getattr(b, se)), (key, a, b)


def test_lobe_sampling_at_the_light_paths_first_vertex_agrees_with_the_cosine():
    """The light paths reflect at their first vertex l_1 by the part's own BSDF sampling (the road's
    forward lobe where a grazing source lights the floor; ``KaBatch.light_lobe``), and every
    strategy that finds the same two-reflection path weighs it with that sampling's density,
    computed per cell (``KaBatch._light_pdf``). Against the former estimator (cosine reflection at
    l_1 and the cosine density in the weights) at grazing cells, walls of 0.2, the same samples
    (one pass of 2^18 points a cell), other seeds: k_A and the stray fraction agree within the
    combined standard errors, and the lobe's are smaller (what it is for). Sampling the lobe but
    weighing with the cosine density (a reverse pdf that disagrees with the sampling; measured once)
    moves k_A by +0.5 %, +0.5 %, -0.7 % (9-36 SE) and the stray fraction by 0.006 at the off-specular
    cells (24-28 SE): this test fails then."""
    cells = [(11.0, 35.0), (12.0, 60.0), (12.0, 0.0)]
    # at 3 reflections, where the lobe was measured (the default for walls of 0.2 is 7 since session 38:
    # there the lobe's SE at tan eps 12, beta 60 was 1.7x the cosine's in one run, docs/straylight.md)
    three = _with_bounces(housed(0.2), 3)
    with pytest.warns(ModelWarning, match="max_bounces = 3 cuts"):
        lobe = mitsuba(three, rel_se=1.0, first_pass=1 << 18, seed=1)
    assert lobe.engine.integrator.light_lobe and lobe.engine.integrator.light_depth == 2
    with pytest.warns(ModelWarning, match="max_bounces = 3 cuts"):
        cosine = mitsuba(three, rel_se=1.0, first_pass=1 << 18, seed=2)
    cosine.engine.integrator.light_lobe = False
    for a, b in zip(lobe.compute(cells), cosine.compute(cells)):
        assert a.samples == b.samples == 1 << 18
        assert a.stray_fraction > 0.01
        z = z_family(2 * len(cells), dof=min(a.se_dof, b.se_dof))
        for key, se in (("k_a", "se"), ("stray_fraction", "stray_fraction_se")):
            va, vb = getattr(a, key), getattr(b, key)
            assert abs(va - vb) <= z * math.hypot(getattr(a, se), getattr(b, se)), (key, a, b)
        assert a.se < b.se, (a.tan_eps, a.beta_deg, a.se, b.se)


#: WALL_XML with a black roof at z = 0.21 m over y = -0.16 ... 0.15 m, x = -0.6 ... 0.6 m: at cell
#: (tan eps 1, beta 90) it hides the whole wall from the whole source disc (the lines from the disc
#: to the wall cross z = 0.21 at y <= 0.12), while the footprint still sees the source (the lines
#: cross it at y >= 0.2) and the wall (below z = 0.2 all the way).
ROOF = """    <shape type="rectangle" id="roof">
        <transform name="to_world"><scale x="0.6" y="0.155" z="1"/><translate x="0" y="-0.005" z="0.21"/></transform>
        <bsdf type="diffuse"><float name="reflectance" value="0"/></bsdf>
    </shape>
</scene>"""


def test_a_part_the_source_cannot_see_sends_no_light(tmp_path):
    """With max_bounces = 2 the only stray path is source -> wall -> footprint. A black roof that hides
    the wall from the source leaves none: the stray fraction is 0 and k_A is the direct light's,
    which the roof does not touch (equal to the run without it, same seed). Without the roof the
    same cell has stray light far outside its error bar, so the test can fail: the next-event
    estimation at a part's vertex must test the segment to the source for shading (without the
    shadow ray it lit the wall through the roof, and no other test has a part shaded from the source)."""
    cell = (1.0, 90.0)
    (tmp_path / "roofed.xml").write_text(WALL_XML.replace("</scene>", ROOF))
    results = {}
    for name, xml in (("open", None), ("roofed", "roofed.xml")):
        inst = wall_instrument(tmp_path, 0.8, max_bounces=2)
        if xml is not None:
            d = inst.to_dict()
            d["scene"] = {**d["scene"], "xml": xml}
            inst = Instrument.from_dict(d, path=tmp_path / "roofed.toml")
        results[name] = mitsuba(inst, rel_se=1.0, first_pass=4096, seed=2).compute([cell])[0]
    op, roofed = results["open"], results["roofed"]
    assert op.stray_fraction > 20 * op.stray_fraction_se
    assert roofed.stray_fraction == 0.0 and roofed.k_a == roofed.k_a_direct
    # a reflecting part that sends no light: the cell looks for it up to STRAY_SEARCH_MAX samples
    # (session 22: rare stray paths made overconfident SEs), then converges and says so
    from roadgonio.engines.mitsuba.passes import STRAY_SEARCH_MAX
    assert roofed.converged and roofed.samples >= STRAY_SEARCH_MAX and "no stray light seen" in roofed.extra["note"]
    tol = n_sigma(min(op.se_dof, roofed.se_dof)) * math.hypot(op.k_a_direct_se, roofed.k_a_direct_se)
    assert abs(roofed.k_a_direct - op.k_a_direct) <= tol + F32_REL


def test_the_default_reflections_follow_the_parts_reflectance(tmp_path):
    """(user audit, session 38) with walls of 0.2 the default 3 reflections biased k_A at tan eps 5,
    beta 0 by +1.7 % (35 SE), silently: the light cut off is of order rho^(K-1) (measured 1.7, 0.53,
    0.15, 0.04 % at K = 3 ... 6, docs/straylight.md), so the default K keeps rho^(K-1) <= STRAY_TAIL,
    and a K given below what the scene needs, or capped, is said (ModelWarning)."""
    import warnings

    from roadgonio.engines.mitsuba.scene import STRAY_TAIL, default_max_bounces, truncation_share
    from roadgonio.instrument.config import MAX_BOUNCES_LIMIT
    assert [default_max_bounces(r) for r in (0.0, 0.01, 0.02, 0.05, 0.2, 0.5, 0.9, 1.0)] == [3, 3, 4, 4, 7, 13, 64, 64]
    for rho in np.linspace(0.01, 0.87, 60):
        k = default_max_bounces(rho)
        assert truncation_share(rho, k) <= STRAY_TAIL * (1 + 1e-9)
        assert k == 3 or truncation_share(rho, k - 1) > STRAY_TAIL            # the least such K
    assert default_max_bounces(0.95) == MAX_BOUNCES_LIMIT and truncation_share(0.95, 64) > STRAY_TAIL
    with warnings.catch_warnings():
        warnings.simplefilter("error", ModelWarning)      # the default of a housing of 0.2 says nothing
        b = mitsuba(housed(0.2), rel_se=1.0, first_pass=256)
    assert b.engine.max_bounces == 7
    assert mitsuba(housed(0.05), rel_se=1.0, first_pass=256).engine.max_bounces == 4
    with pytest.warns(ModelWarning, match=r"max_bounces = 3 cuts .* bias k_A by a relative amount of order 0\.04.*default is 7"):
        mitsuba(_with_bounces(housed(0.2), 3), rel_se=1.0, first_pass=256)
    with pytest.warns(ModelWarning, match=r"the most reflections followed \(64\)"):
        mitsuba(housed(0.97), rel_se=1.0, first_pass=256)


def _with_bounces(inst, k: int):
    d = inst.to_dict()
    d["scene"] = {**(d.get("scene") or {}), "max_bounces": k}
    return Instrument.from_dict(d, path=inst.path)


#: Two parts without ids (an XML scene may leave them unnamed: Mitsuba gives both the id ''), the
#: brighter one first, above the sample out of every line of sight.
UNNAMED = """    <shape type="rectangle">
        <transform name="to_world"><scale x="0.1" y="0.05" z="1"/><translate x="0" y="0.6" z="0.5"/></transform>
        <bsdf type="diffuse"><float name="reflectance" value="0.9"/></bsdf>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><scale x="0.1" y="0.05" z="1"/><translate x="0.3" y="0.6" z="0.5"/></transform>
        <bsdf type="diffuse"><float name="reflectance" value="0.1"/></bsdf>
    </shape>
</scene>"""


def test_parts_without_ids_each_count_for_the_default_reflections(tmp_path):
    """The default number of reflections follows the brightest part, also where parts share the id ''
    (review, session 38: the parts' reflectances were kept by id, so the last unnamed part's 0.1 hid the
    first one's 0.9)."""
    from roadgonio.engines.mitsuba.scene import default_max_bounces
    (tmp_path / "unnamed.xml").write_text(WALL_XML.replace("</scene>", UNNAMED))
    d = wall_instrument(tmp_path, 0.0, max_bounces=None).to_dict()
    d["scene"] = {**d["scene"], "xml": "unnamed.xml"}
    inst = Instrument.from_dict(d, path=tmp_path / "unnamed.toml")
    with pytest.warns(ModelWarning, match="the most reflections followed"):
        b = mitsuba(inst, rel_se=1.0, first_pass=256)
    rho = b.rs.info["part_reflectance_max"]
    assert abs(rho - 0.9) < 0.01 and b.engine.max_bounces == default_max_bounces(rho) == 64


def test_a_point_source_in_a_housing_is_the_limit_of_a_small_disc():
    """(user audit, session 39) R_S = 0 is the limit of a small Lambertian disc, I_0 cos theta_s about its
    axis (docs/conventions.md section 5); Mitsuba's point emitter is isotropic and lit the housing's walls
    and lid behind the source: at tan eps 11, beta 40 with walls of 0.2 the stray light was 80 % of the road
    signal against 64 % at R_S = 1 mm, k_A 1.65 against 1.39. Now the two agree within the family-wise
    threshold of the combined SEs (the disc's 1 mm changes k_A by far less than the SEs here)."""
    d = housed(0.2).to_dict()
    d["source"]["radius_m"] = 0.0
    point = Instrument.from_dict(d, path=SCENES / "portable_housed.toml")
    d["source"]["radius_m"] = 0.001
    disc = Instrument.from_dict(d, path=SCENES / "portable_housed.toml")
    cells = [(11.0, 40.0), (5.0, 0.0)]
    a = mitsuba(point, rel_se=2e-3, seed=1).compute(cells)
    b = mitsuba(disc, rel_se=2e-3, seed=2).compute(cells)
    for p, q in zip(a, b):
        for key, se in (("k_a", "se"), ("stray_fraction", "stray_fraction_se")):
            x, y = getattr(p, key), getattr(q, key)
            band = z_family(2 * len(cells)) * math.hypot(getattr(p, se), getattr(q, se))
            assert abs(x - y) <= band, (p.tan_eps, p.beta_deg, key, x, y, band)
