# ruff: noqa  (kept as the user-auditor wrote it, session 40; only this line added)
"""Independent float64 truth (outside eq. 4) and instrument integrator (Lambert calibration).
No roadgonio import. Conventions from docs/conventions.md sections 1, 2, 4, 5."""
import numpy as np
from scipy.stats import qmc

TAN = np.array([0, .25, .5, .75, 1, 1.25, 1.5, 1.75, 2, 2.5, 3, 3.5, 4, 4.5, 5, 5.5, 6, 6.5, 7, 7.5, 8,
                8.5, 9, 9.5, 10, 10.5, 11, 11.5, 12])
BETA = np.array([0, 2, 5, 10, 15, 20, 25, 30, 35, 40, 45, 60, 75, 90, 105, 120, 135, 150, 165, 180.])
ALPHA = np.radians(1.0)

# truth parameters
KD = 0.012
KS1, M1 = 0.35, 0.25   # sharp GGX lobe
KS2, M2 = 0.0, 0.35
BUMP_A, BUMP_B0, BUMP_W = 0.35, 40.0, 20.0  # smooth bump in beta on diffuse part, grows with sin^2 eps


def ggx(cos_h, m):
    c2 = cos_h * cos_h
    d = c2 * (m * m - 1) + 1
    return m * m / (np.pi * d * d)


def beckmann(cos_h, m):
    c2 = np.clip(cos_h * cos_h, 1e-12, 1)
    t2 = (1 - c2) / c2
    return np.exp(-t2 / (m * m)) / (np.pi * m * m * c2 * c2)


def brdf(wi, wo):
    """wi, wo: arrays (...,3), unit, pointing away from surface. Returns f in sr^-1."""
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    ch = np.clip(h[..., 2], 0, 1)
    phi_i = np.arctan2(wi[..., 1], wi[..., 0])
    phi_o = np.arctan2(wo[..., 1], wo[..., 0])
    b = np.abs(np.mod(phi_i - phi_o - np.pi + np.pi, 2 * np.pi) - np.pi)   # beta in [0, pi]
    s2 = 1 - wi[..., 2] ** 2
    bump = 1 + BUMP_A * s2 * np.exp(-((np.degrees(b) - BUMP_B0) / BUMP_W) ** 2)
    return KD * bump + KS1 * ggx(ch, M1) + KS2 * ggx(ch, M2)


def w_src(eps, beta, delta=0.0):
    phi = delta + np.pi - beta
    return np.stack([np.sin(eps) * np.cos(phi), np.sin(eps) * np.sin(phi), np.cos(eps) * np.ones_like(phi)], -1)


def w_det(alpha=ALPHA, delta=0.0):
    return np.array([np.cos(alpha) * np.cos(delta), np.cos(alpha) * np.sin(delta), np.sin(alpha)])


def r_true(tan, beta_deg):
    eps = np.arctan(tan)
    wi = w_src(eps, np.radians(beta_deg))
    wo = np.broadcast_to(w_det(), wi.shape)
    return brdf(wi, wo) * np.cos(eps) ** 3


def basis(w):
    a = np.array([0, 0, 1.0]) if abs(w[2]) < 0.9 else np.array([1.0, 0, 0])
    e1 = np.cross(w, a); e1 /= np.linalg.norm(e1)
    e2 = np.cross(w, e1)
    return e1, e2


def disc(u, v):
    r = np.sqrt(u); t = 2 * np.pi * v
    return r * np.cos(t), r * np.sin(t)


class Instrument:
    def __init__(self, DS, RS, DD, RD, gamma_deg, F=None, sx=None, sy=None):
        self.DS, self.RS, self.DD, self.RD = DS, RS, DD, RD
        self.g = np.radians(gamma_deg); self.F = DD if F is None else F
        self.sx, self.sy = sx, sy


PORTABLE = Instrument(1.0, 0.025, 1.0, 0.005, 0.15, sx=1.0, sy=0.3)
WIDE = Instrument(1.2, 0.04, 2.0, 0.02, 0.3, sx=12.0, sy=6.0)


def ka_cell(inst, tan, beta_deg, pts):
    """pts: (N,6) QMC points in [0,1). Lambert calibration k_A = sum W f / sum W / f_nom."""
    eps = np.arctan(tan)
    wo = w_det()
    e1, e2 = basis(wo)
    P0 = inst.DD * wo
    axis = -wo
    px, py = disc(pts[:, 0], pts[:, 1])
    fx, fy = disc(pts[:, 2], pts[:, 3])
    p = P0 + inst.RD * (px[:, None] * e1 + py[:, None] * e2)
    Rf = inst.F * np.tan(inst.g)
    q = P0 + inst.F * axis + Rf * (fx[:, None] * e1 + fy[:, None] * e2)
    d = q - p
    L = np.linalg.norm(d, axis=1)
    d = d / L[:, None]
    cosax = d @ axis
    Wd = cosax ** 2 / L ** 2
    t = -p[:, 2] / d[:, 2]
    x = p + t[:, None] * d
    assert np.all(np.abs(x[:, 0]) < inst.sx / 2) and np.all(np.abs(x[:, 1]) < inst.sy / 2)
    wo_x = -d
    wi0 = w_src(eps, np.radians(beta_deg))
    s1, s2 = basis(wi0)
    sx, sy = disc(pts[:, 4], pts[:, 5])
    s = inst.DS * wi0 + inst.RS * (sx[:, None] * s1 + sy[:, None] * s2)
    v = s - x
    dist = np.linalg.norm(v, axis=1)
    wi = v / dist[:, None]
    cos_i = wi[:, 2]
    cos_s = wi @ wi0
    Ws = np.clip(cos_i, 0, None) * np.clip(cos_s, 0, None) / dist ** 2
    W = Wd * Ws
    f = brdf(wi, wo_x)
    fnom = brdf(wi0[None], wo[None])[0]
    return np.sum(W * f) / np.sum(W) / fnom


def cie_mask():
    """cells present in CIE R3 (396)"""
    import csv
    rows = [l for l in open('/work/main/roadgonio/data/rtables/R3.csv') if not l.startswith('#')][1:]
    m = np.zeros((29, 20), bool)
    for i, l in enumerate(rows):
        vals = l.strip().split(',')[1:]
        for j, v in enumerate(vals):
            m[i, j] = v.strip() != ''
    return m


def write_table(path, arr, header, fmt='{:.6g}'):
    with open(path, 'w') as fh:
        fh.write('# source: ' + header + '\n')
        fh.write('tan_eps,' + ','.join(f'{b:g}' for b in BETA) + '\n')
        for i, t in enumerate(TAN):
            fh.write(f'{t:g},' + ','.join('' if not np.isfinite(v) else fmt.format(v) for v in arr[i]) + '\n')


def read_table(path):
    rows = [l for l in open(path) if not l.startswith('#')]
    out = np.full((29, 20), np.nan)
    for i, l in enumerate(rows[1:30]):
        vals = l.strip().split(',')[1:]
        for j, v in enumerate(vals):
            if v.strip():
                out[i, j] = float(v)
    return out
