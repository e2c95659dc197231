"""The pictures and the table of docs/beam.md: the illuminance E(x_E, y_E) over the detector footprint
of the portable instrument with and without a beam profile, and k_A against the width of a Gaussian
beam (wide: the uniform disc; narrow: the collimated beam). Run from the repository::

    python scripts/beam_figures.py          # writes docs/beam/illuminance.png, docs/beam/ka_sigma.png

and prints the table the page quotes. float64 numpy only (the quadrature and numpy-mc backends, and
roadgonio.engines.calibration.illuminance: the backends' own integral of E).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from roadgonio.arrays import NumpyOps
from roadgonio.engines import make_backend
from roadgonio.engines.calibration import illuminance
from roadgonio.instrument import optics
from roadgonio.instrument.config import Instrument, load_instrument
from roadgonio.surface.model import road_brdf
from roadgonio.surface.sample import resolve_sample

OUT = Path(__file__).resolve().parents[1] / "docs" / "beam"
CELL_E = (1.0, 30.0)
PROFILE = {"beam_sigma_deg": 5.0, "aperture_edge_radiance": 0.5}
CELLS = [(12.0, 0.0), (4.0, 2.0), (1.0, 30.0)]
SIGMAS = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 256.0]


def collimated_limit(inst: Instrument, model, tan_eps: float, beta_deg: float, n: int = 1 << 20, seed: int = 1):
    """k_A of the sigma -> 0 limit (every source point emits along the axis only: the footprint is lit
    where the disc projects along the axis, from exactly w_i): plain Monte Carlo over pupil x field."""
    rng = np.random.default_rng(seed)
    geo = optics.detector_geometry(inst)
    src = optics.source_geometry(inst, tan_eps, beta_deg)
    w_i = inst.w_i(tan_eps, beta_deg)
    P = model.params.to_dict()
    u = rng.random((4, n))
    o, d, w = optics.detector_ray(NumpyOps, geo, optics.concentric_disc(NumpyOps, u[0], u[1]),
                                  optics.concentric_disc(NumpyOps, u[2], u[3]))
    x, y, _ = optics.hit_plane(NumpyOps, o, d)
    off = np.stack([x, y, np.zeros_like(x)], -1) - src.centre
    lit = np.linalg.norm(off - (off @ w_i)[:, None] * w_i, axis=1) <= src.radius_m
    f = road_brdf(NumpyOps, P, tuple(np.full(n, c) for c in w_i), (-d[0], -d[1], -d[2]), model.variant, model.terms())
    w_o = inst.w_o()
    f0 = float(road_brdf(NumpyOps, P, tuple(np.array([c]) for c in w_i), tuple(np.array([c]) for c in w_o),
                         model.variant, model.terms())[0])
    return float(np.sum(w * lit * f) / np.sum(w * lit)) / f0


def main() -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    OUT.mkdir(parents=True, exist_ok=True)
    base = load_instrument("portable")
    prof = base.with_changes(source=PROFILE)
    model = resolve_sample("R3").model

    # -- E over the footprint --------------------------------------------------------------------
    fx, fy = optics.footprint_boundary(base)
    x0, x1 = fx.min() - 0.05, fx.max() + 0.05
    ym = max(3 * np.ptp(fy), 0.03)
    X, Y = np.meshgrid(np.linspace(x0, x1, 240), np.linspace(-ym, ym, 120))
    e_u = illuminance(base, *CELL_E, X, Y)
    e_p = illuminance(prof, *CELL_E, X, Y)
    e0_u = float(illuminance(base, *CELL_E, 0.0, 0.0))
    e0_p = float(illuminance(prof, *CELL_E, 0.0, 0.0))
    fig, axes = plt.subplots(3, 1, figsize=(8.5, 8.5), gridspec_kw={"height_ratios": [1, 1, 1.1]})
    from scipy.spatial import ConvexHull
    scale = np.ptp(fx) / np.ptp(fy)                    # an elongated footprint: hull in scaled coordinates
    hull = ConvexHull(np.stack([fx, fy * scale], -1)).vertices
    for ax, e, e0, title in ((axes[0], e_u, e0_u, "uniform Lambertian disc"),
                             (axes[1], e_p, e0_p, "Gaussian beam sigma 5 deg, aperture radiance 1 - 0.5 rho^2")):
        im = ax.imshow(e / e0, extent=(x0, x1, -ym, ym), origin="lower", aspect="auto", cmap="viridis", vmin=0,
                       vmax=1.6)
        ax.plot(np.r_[fx[hull], fx[hull][:1]], np.r_[fy[hull], fy[hull][:1]], color="red", lw=1.2)
        ax.set_title(f"E(x, y) / E_0, {title}", fontsize=10)
        ax.set_ylabel("y (m)")
        fig.colorbar(im, ax=ax, shrink=0.9)
    ax = axes[2]
    j = np.argmin(np.abs(Y[:, 0]))
    ax.plot(X[j], e_u[j] / e0_u, label="uniform disc")
    ax.plot(X[j], e_p[j] / e0_p, label="profiled (sigma 5 deg, a 0.5)")
    ax.axvspan(fx.min(), fx.max(), color="red", alpha=0.08, label="footprint")
    ax.set_xlabel("x on the sample (m; detector towards +x)")
    ax.set_ylabel("E / E_0 at y = 0")
    ax.legend(fontsize=8)
    fig.suptitle(f"portable instrument, tan eps = {CELL_E[0]:g}, beta = {CELL_E[1]:g} deg: illuminance over the "
                 "footprint (red)", fontsize=11)
    fig.tight_layout()
    fig.savefig(OUT / "illuminance.png", dpi=90)
    plt.close(fig)

    # -- k_A against sigma -----------------------------------------------------------------------
    uni = make_backend("quadrature", base, model, rtol=1e-6).compute(CELLS)
    coll = [collimated_limit(base, model, *c) for c in CELLS]
    rows = []
    for s in SIGMAS:
        inst = base.with_changes(source={"beam_sigma_deg": s})
        if s >= 2.0:
            res = make_backend("quadrature", inst, model, rtol=1e-6).compute(CELLS)
            err = [r.error_bound for r in res]
        else:    # the quadrature does not converge on the narrow peak: Monte Carlo with its SE
            res = make_backend("numpy-mc", inst, model, rel_se=2e-4, seed=1).compute(CELLS)
            err = [r.se for r in res]
        rows.append((s, [r.k_a for r in res], err, [r.converged for r in res]))
    print("sigma_deg | " + " | ".join(f"k_A {t:g}/{b:g} (error)" for t, b in CELLS))
    for s, k, e, ok in rows:
        print(f"{s:g} | " + " | ".join(f"{a:.5f} ({b:.1e}{'' if c else ', not converged'})" for a, b, c in zip(k, e, ok)))
    print("uniform disc | " + " | ".join(f"{r.k_a:.5f} ({r.error_bound:.1e})" for r in uni))
    print("collimated limit | " + " | ".join(f"{c:.5f}" for c in coll))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for i, (t, b) in enumerate(CELLS):
        line, = ax.semilogx([r[0] for r in rows], [r[1][i] for r in rows], "o-", label=f"tan eps {t:g}, beta {b:g}")
        ax.axhline(uni[i].k_a, color=line.get_color(), ls="--", lw=0.8)
        ax.axhline(coll[i], color=line.get_color(), ls=":", lw=0.8)
        theta = optics.footprint_emission_angle_deg(base, t, b)
        ax.axvline(theta, color=line.get_color(), ls="-", lw=0.5, alpha=0.5)
    ax.set_xlabel("beam_sigma_deg (Gaussian radiance profile)")
    ax.set_ylabel("k_A (Lambert calibration, R3)")
    ax.set_title("k_A against the beam width: dashed = uniform disc, dotted = collimated beam,\n"
                 "thin vertical = largest angle at which the source sees the footprint", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "ka_sigma.png", dpi=90)
    plt.close(fig)
    print(f"wrote {OUT / 'illuminance.png'} and {OUT / 'ka_sigma.png'}")


if __name__ == "__main__":
    main()
