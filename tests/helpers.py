"""Helpers and test data shared by test files of more than one tier (tests/unit, tests/plugin,
tests/system): plain functions and constants, no fixtures (those are in tests/conftest.py).
tests/ is on sys.path (pytest puts the folder of the root conftest.py there): ``from helpers import ...``."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from roadgonio.arrays import NumpyOps
from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel, RoadParams

SCENES = Path(__file__).resolve().parents[1] / "scenes"


# -- meshes (tests/unit/test_meshmc.py, tests/plugin/test_meshmc_plugin.py) ---------------------

def grid_mesh(path, xs, ys, height=lambda x, y: 0.0 * x, shuffle_seed=None):
    import trimesh
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), height(X, Y).ravel()], 1)
    ny = len(ys)
    F = []
    for i in range(len(xs) - 1):
        for j in range(ny - 1):
            a, b, c, d = i * ny + j, (i + 1) * ny + j, (i + 1) * ny + j + 1, i * ny + j + 1
            F += [[a, b, c], [a, c, d]]
    F = np.array(F)
    if shuffle_seed is not None:
        F = F[np.random.default_rng(shuffle_seed).permutation(len(F))]
    trimesh.Trimesh(V, F, process=False).export(path)
    return path


def with_mesh(inst: Instrument, mesh) -> Instrument:
    d = inst.to_dict()
    d["sample"] = {"mesh": str(mesh)}
    return Instrument.from_dict(d)


# -- directions and models (tests/unit/test_model.py, tests/plugin/test_model_plugin.py) ----------

def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _hemisphere(n, rng, zmin=1e-6):
    """Random directions in the upper hemisphere (uniform in solid angle, z >= zmin)."""
    z = rng.uniform(zmin, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)


def _model(variant="power", **kw):
    return RoadModel(RoadParams(**kw), variant)


# -- the uncertainty tests (tests/unit, tests/plugin and tests/system test_uncertainty*.py) -------

#: The model of the uncertainty tests (every term, no fit).
UNCERTAINTY_MODEL = RoadModel(RoadParams(k_diff=0.01, k_phong=0.5, n_phong=300, k_retro=0.005, n_retro=20,
                                         k_exp=0.05, p=2, h=1, mu=0.1), name="test")
#: Their SPEC: every input with a standard uncertainty.
UNCERTAINTY_SPEC = ("alpha_deg=0.01,eps_deg=0.05:rect,beta_deg=0.1,tilt_x_deg=0.02,tilt_y_deg=0.02,source_distance_m=0.002,"
                    "detector_distance_m=0.005")


# -- versions ------------------------------------------------------------------------------------

#: What every result says about the software that made it.
VERSION_KEYS = {"roadgonio", "roadgonio_source", "python", "platform", "numpy", "scipy", "mitsuba", "drjit"}


# -- random BSDF inputs (tests/plugin/test_plugin_bsdf.py, tests/unit/test_model.py) -------------

def rand_dirs(rng, n, max_cos=1.0):
    cz = rng.random(n) * max_cos
    phi = rng.random(n) * 2 * np.pi
    s = np.sqrt(1 - cz ** 2)
    w = np.stack([s * np.cos(phi), s * np.sin(phi), cz], -1)
    return w.astype(np.float32).astype(np.float64)          # exactly representable in float32


def rand_params(rng, h_max=20.0) -> dict:
    return dict(k_diff=rng.uniform(0, 1), k_phong=rng.uniform(0, 10), n_phong=10 ** rng.uniform(0, 4),
                k_retro=rng.uniform(0, 1), n_retro=10 ** rng.uniform(0, 3), k_exp=rng.uniform(0, 1),
                p=rng.uniform(0, 3), h=rng.uniform(-h_max, h_max), mu=rng.uniform(0, 2), g_a=0.0, g_b=-1.0,
                g_c=2.0, g_t=rng.uniform(-5, 5), theta_l_deg=rng.uniform(85.4, 90.0))


def _pixels(path):
    """A PNG as an (h, w, 3) int16 array."""
    from PIL import Image
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)


# -- the Mitsuba backend's tests (tests/plugin/test_render_backend.py, test_engine.py) -----------

#: A non-Lambertian model with every term (Phong lobe n = 1000, retro lobe, steep E term, grazing g).
#: Parameters of a model close to the fit of CIE R3 (paper's power reading), shared by the tests.
R3LIKE = dict(k_diff=0.028937, k_phong=1.8147, n_phong=34.467, k_retro=0.052577, n_retro=11.307,
              k_exp=0.088927, p=2.137, h=0.49843, mu=0.03123)

ROAD = RoadModel(RoadParams(k_diff=0.05, k_phong=1.0, n_phong=1000.0, k_retro=0.2, n_retro=50.0,
                            k_exp=0.1, p=1.0, h=2.0, mu=0.1, g_a=0.0, g_b=-1.0, g_c=2.6, g_t=2.0,
                            theta_l_deg=88.0))


def preset(name: str) -> Instrument:
    """An instrument preset of scenes/ loaded from its file."""
    return Instrument.load(SCENES / f"{name}.toml")


# -- flat meshes and cheap backend settings (tests/unit and tests/plugin: test_line_of_sight*, test_cellcheck*) --

def flat_mesh(path, inst: Instrument) -> Instrument:
    """``inst`` with its rectangular sample as a two-triangle mesh file at ``path``."""
    import trimesh
    hx, hy = inst.sample.size_x_m / 2, inst.sample.size_y_m / 2
    trimesh.Trimesh([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]], [[0, 1, 2], [0, 2, 3]],
                    process=False).export(path)
    return with_mesh(inst, path)


#: Cheap settings per backend, for tests that only ask whether a backend refuses a cell.
FAST_SETTINGS = {"quadrature": {"rtol": 1e-2}, "numpy-mc": {"rel_se": 5e-2, "batch": 1024, "min_batches": 2},
                 "reference": {"rtol": 5e-2, "min_log2": 6, "pilot_iterations": 0},
                 "numpy-mc-mesh": {"rel_se": 5e-2, "batch": 1024, "min_batches": 2}, "mitsuba": {"rel_se": 1e-2}}


def line_of_sight_edge_cells():
    """(instrument, cell, blocked) near the edge where the source disc starts to block the detector's
    view: about 50 um outside and 1.5-8 um inside, where the three ray-sampled checks the project had
    before disagreed (tests/unit/test_line_of_sight.py says how)."""
    from roadgonio.instrument.config import load_instrument
    portable = load_instrument("portable")
    near = portable.with_changes(source={"distance_m": 0.5, "radius_m": 0.04})
    speck = portable.with_changes(source={"distance_m": 0.5, "radius_m": 1e-4})
    return [
        (near, (9.489, 180.0), False), (near, (9.4996, 180.0), True),
        (near, (9.529, 179.5), False), (near, (9.5394, 179.5), True), (near, (9.5406, 179.5), True),
        (near, (9.652, 179.0), False), (near, (9.6622, 179.0), True),
        (near, (9.769, 178.7), False), (near, (9.7797, 178.7), True),
        (near, (9.985, 178.3), False), (near, (9.9954, 178.3), True),
        (speck, (47.7395, 179.9), True), (speck, (40.9174, 179.8), True), (speck, (40.9174, 179.78), False),
    ]


def backend_refuses(name: str, inst: Instrument, cell, model: RoadModel, tmp_path=None) -> bool:
    """Whether backend ``name`` (cheap settings) refuses ``cell`` because the source blocks the
    detector's view; any other refusal fails the test, and a computed cell must be finite."""
    import math

    from roadgonio.engines import make_backend
    from roadgonio.errors import GeometryError
    if name == "numpy-mc-mesh":
        inst = flat_mesh(tmp_path / "flat.ply", inst)
    try:
        res = make_backend(name, inst, model, settings=FAST_SETTINGS[name]).compute([cell])
    except GeometryError as err:
        assert "line of sight" in str(err), err
        return True
    assert math.isfinite(res[0].k_a)
    return False


# -- the source's beam and the detector's map (tests/unit/test_profiles.py, tests/plugin/test_profile_plugin.py)

def ldt_text(g_deg, planes, c_deg=(0.0,), isym: int = 1) -> str:
    """An EULUMDAT file (one item per line) with the intensities ``planes`` (one row per stored C
    plane, cd/klm) at the gamma angles ``g_deg``; Isym 1 (rotational symmetry) stores one plane."""
    g_deg = np.asarray(g_deg, dtype=np.float64)
    c_deg = np.asarray(c_deg, dtype=np.float64)
    dc = float(c_deg[1] - c_deg[0]) if c_deg.size > 1 else 0.0
    lines = ["roadgonio tests", "1", str(isym), str(c_deg.size), f"{dc:g}", str(g_deg.size),
             f"{g_deg[1] - g_deg[0]:g}", "report", "test source", "T1", "test.ldt", "tests",
             "0", "0", "0", "0", "0", "0", "0", "0", "0", "100", "100", "1", "0",
             "1", "1", "LED", "1000", "4000", "80", "1"]
    lines += ["0"] * 10
    lines += [f"{c:.10g}" for c in c_deg]
    lines += [f"{g:.10g}" for g in g_deg]
    for row in np.atleast_2d(planes):
        lines += [f"{v:.12g}" for v in row]
    return "\r\n".join(lines) + "\r\n"


def write_table_csv(path, header: str, x, y) -> Path:
    """A two-column CSV (``header`` then one row per node, full precision)."""
    rows = [header] + [f"{a!r},{b!r}" for a, b in zip(np.asarray(x, dtype=float).tolist(),
                                                        np.asarray(y, dtype=float).tolist())]
    Path(path).write_text("\n".join(rows) + "\n")
    return Path(path)


def map_centres(n: int) -> np.ndarray:
    """The pixel-centre coordinates of an n-pixel side of a sensitivity map over [-1, 1]."""
    return -1.0 + (2.0 * np.arange(n) + 1.0) / n


def write_map_csv(path, fn, nx: int, ny: int | None = None) -> Path:
    """A sensitivity map of ``fn(x, y)`` (x right, y up) at the pixel centres, rows from the top."""
    ny = nx if ny is None else ny
    x = map_centres(nx)
    y = map_centres(ny)[::-1]
    X, Y = np.meshgrid(x, y)
    np.savetxt(path, fn(X, Y), delimiter=",", fmt="%.17g")
    return Path(path)


# -- TOML reading (tests/unit/test_toml_reading.py, tests/system/test_toml_reading_system.py) --
GOOD_LAYOUT = Path(__file__).resolve().parents[1] / "roadgonio" / "data" / "road" / "default_layout.toml"


def broken(tmp_path, good: str, line: int, name: str) -> Path:
    """``good`` with line ``line`` (1-based) replaced by a key without a value."""
    lines = good.splitlines()
    lines[line - 1] = "broken_key ="
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p


def refused_in_one_line(call, path, words) -> None:
    """``call()`` raises an InputError whose message is one line naming ``path`` and every one of ``words``."""
    import pytest

    from roadgonio.errors import InputError
    with pytest.raises(InputError) as ei:
        call()
    msg = str(ei.value)
    assert str(path) in msg and "\n" not in msg, msg
    for w in words:
        assert w in msg, msg


def instrument_text() -> str:
    from roadgonio.instrument.config import load_instrument
    return Path(load_instrument("portable").path).read_text(encoding="utf-8")


def spec_text() -> str:
    return "# misalignment\n[sigma]\nalpha_deg = 0.01\neps_deg = \"0.05:rect\"\nsource_distance_m = 0.002\n"


#: A small valid instrument file (flat 2 m x 0.5 m sample): the start of the input-error tests and probes.
GOOD_INSTRUMENT = """[observation]
alpha_deg = 1.0
[source]
distance_m = 5.0
radius_m = 0.005
[detector]
distance_m = 10.0
pupil_radius_m = 0.005
field_half_angle_deg = 0.05
[sample]
size_x_m = 2.0
size_y_m = 0.5
"""


# -- progress bars on a terminal (tests/unit/test_intercomparison.py, tests/unit/test_fit.py) ---------

def on_a_zero_size_terminal(monkeypatch, work):
    """Run ``work()`` with stderr on a fresh pseudo-terminal, which reports 0 x 0 (like the one of
    ``script``); returns what was written to it."""
    import os
    import sys
    import threading
    master, slave = os.openpty()
    assert os.get_terminal_size(slave) == (0, 0)
    chunks = []

    def drain():
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:
                return
            if not data:
                return
            chunks.append(data)
    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    term = open(slave, "w", encoding="utf-8", closefd=False)
    monkeypatch.setattr(sys, "stderr", term)
    monkeypatch.setenv("COLUMNS", "100")
    monkeypatch.setenv("LINES", "30")
    try:
        work()
    finally:
        term.flush()
        monkeypatch.undo()
        os.close(slave)
        reader.join(timeout=5)
        os.close(master)
    return b"".join(chunks).decode("utf-8", "replace")


# -- SE honesty of a Monte Carlo backend (tests/unit/test_montecarlo.py, tests/unit/test_meshmc.py) --

#: The cells of the SE-honesty tests: specular and grazing, on and off the plane of observation.
SE_HONESTY_CELLS = [(12.0, 0.0), (8.0, 0.0), (4.0, 2.0), (4.0, 0.0), (2.0, 0.0), (1.0, 0.0)]


def assert_se_is_honest(make_mc, reference, seeds) -> None:
    """``make_mc(seed)`` a Monte Carlo backend, ``reference`` a converged float64 reference backend
    of the same instrument: over every seed x cell of :data:`SE_HONESTY_CELLS`, z = (k_A - k_A,ref) /
    hypot(SE, SE_ref), mapped through Student's t of that SE's degrees of freedom (the two SEs'
    ``se_dof`` combined by Welch-Satterthwaite, written here) to a normal quantile, must look normal:
    mean square <= chi2.isf(ALPHA, m) / m (the sum of m squared normal values is chi-square with m
    degrees of freedom) and none beyond z_family(m). Either side not converged fails (a z of an
    unconverged side means nothing)."""
    import math

    from scipy.stats import chi2, norm, t as student_t
    from tolerances import ALPHA, z_family
    ref = {(r.tan_eps, r.beta_deg): r for r in reference.compute(SE_HONESTY_CELLS)}
    z = []
    for seed in seeds:
        for r in make_mc(seed).compute(SE_HONESTY_CELLS):
            c = ref[(r.tan_eps, r.beta_deg)]
            assert r.converged and c.converged, (r, c)
            assert r.se_dof >= 1 and c.se_dof >= 1, (r, c)
            a, b = r.se ** 2, c.se ** 2
            dof = (a + b) ** 2 / (a * a / r.se_dof + b * b / c.se_dof)
            z.append(norm.isf(student_t.sf((r.k_a - c.k_a) / math.sqrt(a + b), dof)))
    z = np.array(z)
    m = z.size
    assert float(np.mean(z * z)) <= chi2.isf(ALPHA, m) / m, (float(np.sqrt(np.mean(z * z))), m)
    assert float(np.max(np.abs(z))) <= z_family(m), (float(np.max(np.abs(z))), m)


def _tilt(w, k):
    th = np.arccos(np.clip(w[:, 2], -1, 1)) * k
    s = np.maximum(np.hypot(w[:, 0], w[:, 1]), 1e-300)
    return np.stack([w[:, 0] / s * np.sin(th), w[:, 1] / s * np.sin(th), np.cos(th)], -1)


def _turn(w, k):
    """``w`` turned about the vertical by the angle that moves it k theta sideways (the same arc as
    :func:`_tilt`'s change of theta by k theta)."""
    th = np.arccos(np.clip(w[:, 2], -1, 1))
    s = np.maximum(np.hypot(w[:, 0], w[:, 1]), 1e-300)
    dphi = k * th / s
    c, n = np.cos(dphi), np.sin(dphi)
    return np.stack([c * w[:, 0] - n * w[:, 1], n * w[:, 0] + c * w[:, 1], w[:, 2]], -1)


def kappa(model, wl, ws, ref, d=1e-6):
    """The conditioning that float32 evaluations of f are judged against (tests/plugin/test_plugin_bsdf.py):
    the larger of |d ln f / d ln theta_light| and the same derivative sideways, along the arc of the
    light's azimuth (float64 model, central differences). Sideways counts since session 20: at the
    polar extremum of a narrow lobe's flank (the microfacet truth with a = 0.08 near the mirror) the
    polar derivative is near 0 while the azimuthal one is not, and a float32 evaluation there was off
    by 1.08 tolerances."""
    ref = np.maximum(ref, 1e-300)
    polar = np.abs(model.brdf(_tilt(wl, 1 + d), ws) - model.brdf(_tilt(wl, 1 - d), ws)) / (2 * d * ref)
    side = np.abs(model.brdf(_turn(wl, d), ws) - model.brdf(_turn(wl, -d), ws)) / (2 * d * ref)
    return np.maximum(polar, side)


def near_mirror(rng, ws, spread):
    wl = ws * np.array([-1.0, -1.0, 1.0]) + rng.normal(0, spread, ws.shape)
    wl[:, 2] = np.abs(wl[:, 2]) + 1e-3
    wl /= np.linalg.norm(wl, axis=1)[:, None]
    return wl.astype(np.float32).astype(np.float64)


# -- the collimated limit of a narrow beam (tests/unit/test_profiles.py, tests/plugin/test_profile_plugin.py)

def basis(a):
    """Two unit vectors completing the unit vector ``a`` to an orthonormal frame."""
    helper = np.array([0.0, 1.0, 0.0]) if abs(a[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u1 = np.cross(a, helper)
    u1 /= np.linalg.norm(u1)
    return u1, np.cross(a, u1)


def source_direction(inst, tan_eps, beta_deg):
    """Unit vector from the sample centre towards the nominal source of cell (tan eps, beta)."""
    eps, phi_i = math.atan(tan_eps), math.radians(inst.observation.delta_deg + 180.0 - beta_deg)
    return np.array([math.sin(eps) * math.cos(phi_i), math.sin(eps) * math.sin(phi_i), math.cos(eps)])


def collimated_limit(inst: Instrument, model, tan_eps, beta_deg, n_batches=16, n=1 << 17, seed=3):
    """k_A (Lambert calibration) of the sigma -> 0 limit, independent float64 Monte Carlo: every
    source point emits along the axis only, so a footprint point inside the disc's projection along
    the axis (|perpendicular offset| <= R_S) is lit from exactly w_i(eps, beta) with E = const, and
    every other point is dark; k_A = <f(w_i, w_o)>_lit detected rays / f(nominal). Returns (k, se)."""
    from roadgonio.surface.model import road_brdf
    rng = np.random.default_rng(seed)
    alpha = math.radians(inst.observation.alpha_deg)
    w_o = np.array([math.cos(alpha), 0.0, math.sin(alpha)])
    det = inst.detector
    a = -w_o
    u1, u2 = basis(a)
    w_i = source_direction(inst, tan_eps, beta_deg)
    c = inst.source.distance_m * w_i
    P_ = model.params.to_dict()
    col = lambda v, m: tuple(np.full(m, x) for x in v)          # noqa: E731
    f0 = float(road_brdf(NumpyOps, P_, col(w_i, 1), col(w_o, 1), model.variant, model.terms())[0])
    tg = math.tan(math.radians(det.field_half_angle_deg))
    num, den = [], []
    for _ in range(n_batches):
        r1, p1, r2, p2 = rng.random((4, n))
        pr, fr = det.pupil_radius_m * np.sqrt(r1), np.sqrt(r2)
        Pp = det.distance_m * w_o + pr[:, None] * (np.cos(2 * np.pi * p1)[:, None] * u1 + np.sin(2 * np.pi * p1)[:, None] * u2)
        Q = det.distance_m * w_o + det.distance_m * a + det.distance_m * tg * fr[:, None] * (
            np.cos(2 * np.pi * p2)[:, None] * u1 + np.sin(2 * np.pi * p2)[:, None] * u2)
        D = Q - Pp
        D /= np.linalg.norm(D, axis=1)[:, None]
        W = (D @ a) ** 4
        X = Pp + (-Pp[:, 2] / D[:, 2])[:, None] * D
        off = X - c
        lit = np.linalg.norm(off - (off @ w_i)[:, None] * w_i[None, :], axis=1) <= inst.source.radius_m
        f = road_brdf(NumpyOps, P_, col(w_i, n), (-D[:, 0], -D[:, 1], -D[:, 2]), model.variant, model.terms())
        num.append(np.mean(W * lit * f))
        den.append(np.mean(W * lit))
    num, den = np.array(num), np.array(den)
    k = num.mean() / den.mean()
    se = np.std(num - k * den, ddof=1) / math.sqrt(n_batches) / den.mean()
    return k / f0, se / f0
