"""Cross-validation of the k_A backends: a Monte Carlo backend (the float32 Mitsuba renderer by
default, or the float64 numpy Monte Carlo) judged against a float64 reference, cell by cell, with
the right statistics for each kind of precision (docs/conventions.md section 5, :mod:`roadgonio.engines.result`):

* the Monte Carlo result carries a standard error ``se_mc``;
* the reference carries a **bound** (the RQMC reference of :mod:`roadgonio.engines.reference`
  by default: its 99.9 % ``confidence_bound``; or the tensor quadrature's deterministic
  ``error_bound``), or, for a mesh sample, only a standard error of its own (the numpy ray-casting Monte Carlo of :mod:`roadgonio.engines.meshmc`).

Standard errors combine in quadrature, a bound is added as a bound, never as an SE::

    sigma   = sqrt(se_mc^2 + se_ref^2)                       (se_ref = 0 for a bounded reference)
    allowed = n_sigma * sigma + bound_ref + floor * |k_ref|
    n_sigma = t_equivalent(N_SIGMA, dof)

where ``floor`` is the relative float32 floor of the renderer (:data:`FLOAT32_FLOOR`; 1e-12, its
round-off, for the float64 numpy Monte Carlo) and ``n_sigma`` the multiple of sigma that a Student-t error of sigma's
degrees of freedom ``dof`` exceeds as often as a normal error exceeds N_SIGMA (the SE's ``se_dof``,
combined by Welch-Satterthwaite with the reference's when its SE enters sigma; N_SIGMA itself for an
SE without degrees of freedom): an SE from 16 replicates (15 degrees of freedom, the Mitsuba
backend's first pass) makes z a t_15 variable, beyond 4 in 0.12 % of cells, not 0.006 %, so its
test is 5.48 sigma (docs/validation.md, "How heavy are the tails"). Each cell gets one verdict:

* **disagree**: ``|k_mc - k_ref| > allowed`` with a reference that converged (the difference is
  real whatever the reference's own error), or a Monte Carlo value that is not finite although the
  backend said it converged;
* **inconclusive**: the reference did not converge (a bound that was not reached says nothing),
  or its bound takes more than :data:`REF_SHARE` of the test's band (``n_sigma sigma + floor |k|``)
  or its standard error exceeds the tested one - then an agreement would only say the reference is
  too coarse to see the difference; or the Monte Carlo backend stopped at its sample cap before its
  target (its SE is honest, but the test is weaker than asked), or stopped with no value or no SE
  (a cell it says it cannot measure: float32 underflow, too few samples carrying the light);
* **agree**: otherwise.

``roadgonio validate`` exits 0 only if every cell agrees, 1 if any disagrees, 3 if none disagrees
but some are inconclusive. The RQMC reference is asked, per cell, for the bound that cell's test
needs (half of :data:`REF_SHARE` of the band), so it does no more work than the comparison uses.

The default cell set covers the extremes of the table: tan eps 0 and 12, beta 0 and 180, the
specular peak region (tan 4-12 x beta 0-10) and mid cells.
"""
from __future__ import annotations

import csv
import io
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from roadgonio.errors import EXIT_INCONCLUSIVE, InputError
from roadgonio.engines.result import t_equivalent, welch_satterthwaite
from roadgonio.instrument.config import Instrument
from roadgonio.surface.model import RoadModel

#: Pass threshold in combined standard errors of infinitely many degrees of freedom (a normal z); an SE
#: of ``dof`` degrees of freedom gets the t quantile of the same probability, t_equivalent(N_SIGMA, dof).
N_SIGMA = 4.0
#: The reference's error bound may take at most this share of the test's band (n_sigma sigma + floor |k|);
#: a wider bound makes the cell inconclusive (an agreement would only say the reference is too coarse).
REF_SHARE = 0.25
#: The tightest relative target the validator asks of the RQMC reference (what the test needs, down to
#: this; was 1e-7, above what a converged Monte Carlo cell with k_A near 1 can need, so such a cell
#: was inconclusive or agreed depending on the random stream).
REF_RTOL_MIN = 1e-9
#: Verdicts, and the exit status of ``roadgonio validate`` for the worst one present.
VERDICTS = ("agree", "disagree", "inconclusive")
EXIT_STATUS = {"agree": 0, "disagree": 1, "inconclusive": EXIT_INCONCLUSIVE}
#: References: "auto" = the RQMC reference for a flat sample, the mesh Monte Carlo for a mesh sample.
def _references() -> tuple[str, ...]:
    from roadgonio.engines.registry import validate_backends
    return ("auto",) + validate_backends("reference")


REFERENCES = _references()

#: Relative float32 floor of the renderer, by backend name: a relative difference from the float64
#: quadrature that longer renders would not remove. Measured (R3-like model, quadrature rtol 1e-7,
#: mitsuba 3.9.1 llvm_ad_rgb, multijitter sampler): lab preset, 5 cells (tan 12/beta 0, 4/2, 0/0, 2/180,
#: 8/5) at rel_se 1e-4: |k_mitsuba - k_quad| / k_quad <= 1.0e-6 with every |z| <= 0.1 (SE 1.3e-6 ...
#: 1.4e-5); portable preset, 6 cells at rel_se 2e-5 (capped at 6.7e7 samples): <= 4.3e-5, every |z| <= 1.
#: No systematic float32 difference was resolved; 1e-5 is a conservative bound above the lab
#: measurement (float32 rounding of a 1 m footprint coordinate is 6e-8 relative).
#: The float64 numpy Monte Carlo's floor is its round-off: where k_A is exactly the reference's
#: (a Lambertian sample, zero apertures) it differs by a few ulp with an "SE" of round-off size,
#: and a floor of 0 called that 6.7 SE and "disagree" (audit 27); 1e-12 is far above the round-off of
#: its float64 sums and far below any SE it reaches.
FLOAT32_FLOOR: dict[str, float] = {"mitsuba": 1e-5, "numpy-mc": 1e-12}

CSV_FIELDS = ("tan_eps", "beta_deg", "verdict", "k_ref", "error_bound_ref", "confidence_bound_ref",
              "confidence_level_ref", "se_ref", "ref_converged", "k_mc", "se_mc",
              "mc_converged", "diff", "rel_diff", "sigma", "dof", "z", "n_sigma", "floor", "allowed", "needed_bound",
              "reason",
              "seconds_ref", "seconds_mc", "samples_ref", "samples_mc")


@dataclass(frozen=True)
class CellComparison:
    """The judgement of one cell (module docstring)."""

    tan_eps: float
    beta_deg: float
    verdict: str          # "agree" | "disagree" | "inconclusive"
    k_ref: float
    error_bound_ref: float       # deterministic error bound of the reference (the quadrature; else NaN)
    confidence_bound_ref: float  # the reference's confidence bound (the RQMC reference; else NaN) ...
    confidence_level_ref: float  # ... at this confidence level (NaN without one)
    se_ref: float         # standard error of the reference (NaN if it gives none); combined with se_mc
    #                       only when the reference has no bound (a mesh sample's Monte Carlo)
    ref_converged: bool
    k_mc: float
    se_mc: float
    mc_converged: bool
    diff: float           # k_mc - k_ref
    rel_diff: float
    sigma: float          # se_mc, or sqrt(se_mc^2 + se_ref^2) for a reference without a bound
    dof: float            # degrees of freedom of sigma (NaN: none given, a normal z)
    z: float              # diff / sigma
    n_sigma: float        # the threshold in sigma: t_equivalent(N_SIGMA, dof)
    floor: float          # relative float32 floor applied
    allowed: float        # n_sigma * sigma + the reference's bound (either kind) + floor * |k_ref|
    needed_bound: float   # the widest reference bound the test accepts: REF_SHARE * (n_sigma sigma + floor |k|)
    reason: str
    seconds_ref: float
    seconds_mc: float
    samples_ref: int
    samples_mc: int

    @property
    def ok(self) -> bool:
        return self.verdict == "agree"

    @property
    def bound_ref(self) -> float:
        """The reference's bound that enters ``allowed``: its confidence bound or its deterministic
        error bound, whichever it has (NaN: none)."""
        return self.confidence_bound_ref if math.isfinite(self.confidence_bound_ref) else self.error_bound_ref


def _finite(v) -> bool:
    return v is not None and isinstance(v, (int, float)) and math.isfinite(v)


def compare(ref, mc, floor: float = 0.0) -> CellComparison:
    """Judge a Monte Carlo CellResult ``mc`` against a reference CellResult ``ref`` of the same cell
    (module docstring): a reference with a bound (``confidence_bound`` or ``error_bound``) adds it as
    a bound, one with only an ``se`` combines it with the Monte Carlo SE in quadrature."""
    k_ref, k_mc = float(ref.k_a), float(mc.k_a)
    se_mc = float(mc.se)
    # a bounded reference (the quadrature's deterministic bound, the RQMC reference's confidence
    # bound) adds its bound; one with only a standard error combines it in quadrature
    conf = float(ref.confidence_bound) if _finite(ref.confidence_bound) else math.nan
    err_bound = float(ref.error_bound) if _finite(ref.error_bound) else math.nan
    level = float(ref.confidence_level) if _finite(conf) and _finite(ref.confidence_level) else math.nan
    bound = conf if _finite(conf) else err_bound
    has_se_ref = not _finite(bound) and _finite(ref.se)
    se_ref = float(ref.se) if _finite(ref.se) else math.nan
    bound_term = bound if _finite(bound) else (0.0 if has_se_ref else math.inf)
    sigma = math.sqrt(se_mc ** 2 + (se_ref ** 2 if has_se_ref else 0.0)) if _finite(se_mc) else math.nan
    dof = (welch_satterthwaite([se_mc ** 2, se_ref ** 2], [mc.se_dof, ref.se_dof]) if has_se_ref
           else float(mc.se_dof))
    n_sigma = float(t_equivalent(N_SIGMA, dof))
    d = k_mc - k_ref
    band = n_sigma * sigma + floor * abs(k_ref)
    allowed = band + bound_term
    needed = REF_SHARE * band
    # no sampling noise (SE 0: every sample gave the same value, e.g. a zero aperture): a difference in
    # SE is undefined (NaN), not +-inf, and the verdicts below speak of the difference itself (audit 21)
    z = d / sigma if _finite(sigma) and sigma > 0 else (0.0 if d == 0 else math.nan)
    in_se = _finite(sigma) and sigma > 0
    ref_ok = bool(ref.converged) and (_finite(bound) or has_se_ref) and _finite(k_ref)
    if not (_finite(k_mc) and _finite(se_mc)) and not bool(mc.converged):
        # the backend said it could not measure the cell (float32 underflow, too few samples carrying
        # the light, its cap): nothing to compare, not a difference (user audit: 'disagree', exit 1)
        note = (mc.extra or {}).get("note") if isinstance(mc.extra, dict) else None
        verdict, reason = "inconclusive", ("the Monte Carlo backend stated no " + ("value" if not _finite(k_mc) else "SE")
                                           + f" and stopped before its target (k = {k_mc:.6g}, SE = {se_mc:.2g}"
                                           + (f": {note}" if note else "") + ")")
    elif not (_finite(k_mc) and _finite(se_mc)):
        verdict, reason = "disagree", f"the {'Monte Carlo'} value or its SE is not finite (k = {k_mc}, SE = {se_mc})"
    elif not ref_ok:
        what = (f"bound {bound / abs(k_ref):.1e} relative" if _finite(bound) and k_ref else "no usable bound")
        verdict, reason = "inconclusive", f"the reference did not converge ({what}; raise its cap or loosen --rtol)"
    elif abs(d) > allowed:
        verdict, reason = "disagree", (f"|diff| = {abs(d):.3g} > allowed {allowed:.3g} "
                                       f"({n_sigma:.3g} SE + bound + floor); "
                                       + (f"{z:+.1f} SE" if in_se else "SE 0"))
    elif has_se_ref and se_ref > se_mc:
        verdict, reason = "inconclusive", (f"the reference's SE {se_ref:.2g} exceeds the tested SE {se_mc:.2g}: "
                                           "the check is weaker than the renderer")
    elif not has_se_ref and bound > needed:
        verdict, reason = "inconclusive", (f"the reference's bound {bound:.2g} is wider than the test needs "
                                           f"(<= {needed:.2g}, {REF_SHARE:g} of the band)")
    elif not bool(mc.converged):
        verdict, reason = "inconclusive", (f"the Monte Carlo backend stopped at its sample cap with SE "
                                           f"{se_mc / abs(k_mc) if k_mc else math.inf:.1e} relative, above its target")
    else:
        verdict, reason = "agree", (f"{z:+.2f} SE, within {allowed / sigma:.2f}" if in_se else
                                    f"|diff| = {abs(d):.3g} within allowed {allowed:.3g} (SE 0: no sampling noise)")
    return CellComparison(tan_eps=float(ref.tan_eps), beta_deg=float(ref.beta_deg), verdict=verdict, k_ref=k_ref,
                          error_bound_ref=err_bound, confidence_bound_ref=conf, confidence_level_ref=level,
                          se_ref=se_ref, ref_converged=bool(ref.converged), k_mc=k_mc, se_mc=se_mc,
                          mc_converged=bool(mc.converged), diff=d, rel_diff=d / k_ref if k_ref else math.nan,
                          sigma=sigma, dof=dof, z=z, n_sigma=n_sigma, floor=floor, allowed=allowed,
                          needed_bound=needed, reason=reason,
                          seconds_ref=float(ref.seconds), seconds_mc=float(mc.seconds),
                          samples_ref=int(ref.samples), samples_mc=int(mc.samples))


def counts(rows: Sequence[CellComparison]) -> dict[str, int]:
    return {v: sum(r.verdict == v for r in rows) for v in VERDICTS}


def overall(rows: Sequence[CellComparison]) -> str:
    """The worst verdict present: disagree > inconclusive > agree."""
    c = counts(rows)
    return "disagree" if c["disagree"] else ("inconclusive" if c["inconclusive"] else "agree")


def resolve_reference(instrument: Instrument, reference: str) -> str:
    if reference not in REFERENCES:
        raise InputError(f"expected --reference {', '.join(REFERENCES)}, got {reference!r}", field="reference")
    if reference == "auto":
        return "numpy-mc-mesh" if instrument.sample.mesh is not None else "reference"
    return reference


def _check_modelled(instrument: Instrument, ref_name: str) -> None:
    """validate needs a float64 reference of the whole instrument: none models a ``[housing]`` or a
    ``[scene]`` (their parts are Mitsuba's alone), so such an instrument is refused up front with what
    the user can do instead (the backends' own message would name a --backend validate does not have)."""
    from roadgonio.engines.registry import BACKENDS, unmodelled_parts
    for sec, what, part in unmodelled_parts(BACKENDS[ref_name], instrument):
        raise InputError(f"validate compares against a float64 reference, which does not model {what} ({part}); validate "
                         f"the instrument without its [{sec}] (the same geometry bare), or compute its k_A with "
                         "'roadgonio ka --backend mitsuba' (docs/validation.md, Known limits)",
                         path=instrument.path, field=sec)


def validate(instrument: Instrument, model: RoadModel, cells: Sequence[tuple[float, float]] | None = None, *,
             against: str = "mitsuba", reference: str = "auto", rel_se: float = 1e-3, rtol: float | None = None,
             seed: int = 0, floor: float | None = None, mitsuba_variant: str | None = None,
             mc_settings: dict[str, Any] | None = None,
             ref_settings: dict[str, Any] | None = None,
             on_cell: Callable[[CellComparison], None] | None = None) -> dict[str, Any]:
    """Run the Monte Carlo backend and the reference on ``cells`` and judge each cell; returns a
    report dict with ``rows`` (:class:`CellComparison`), ``counts``, ``verdict``, ``exit_status``,
    ``settings`` and timings. ``rtol`` fixes the reference's target (default: per cell, what the
    test needs)."""
    from roadgonio.engines.registry import make_backend, validate_backends
    checked = validate_backends("checked")
    if against not in checked:
        raise InputError(f"expected --against {' or '.join(checked)}, got {against!r}", field="against")
    ref_name = resolve_reference(instrument, reference)
    _check_modelled(instrument, ref_name)
    if ref_name == "numpy-mc-mesh" and against == "numpy-mc":
        raise InputError("a mesh sample is checked against the numpy ray-casting Monte Carlo; --against numpy-mc "
                         "(flat samples only) has nothing to compare there", field="against")
    from roadgonio.engines.cells import EXTREME_CELLS
    cells = list(EXTREME_CELLS) if cells is None else list(cells)
    if floor is None:
        floor = FLOAT32_FLOOR.get(against, 0.0)
    t0 = time.perf_counter()
    ref_kw = dict(ref_settings or {})
    if ref_name == "quadrature":
        ref_kw.setdefault("rtol", 1e-5 if rtol is None else rtol)
    elif ref_name == "reference":
        ref_kw.setdefault("seed", seed)
        if rtol is not None:
            ref_kw.setdefault("rtol", rtol)
    else:
        ref_kw.setdefault("seed", seed + 1)     # the mesh Monte Carlo: a stream apart from the tested one
        ref_kw.setdefault("rel_se", rel_se)
    ref = make_backend(ref_name, instrument, model, settings=ref_kw)
    mc = make_backend(against, instrument, model, rel_se=rel_se, seed=seed, mitsuba_variant=mitsuba_variant,
                      settings=mc_settings)
    # every cell either backend refuses, before either computes one (a refusal mid-list printed the
    # rows before it and then failed: user audit, session 24)
    from roadgonio.engines.cellcheck import check_requested
    for b in (mc, ref):
        check_requested(b, instrument, model, cells)
    rows: list[CellComparison] = []
    for cell in cells:
        m = mc.compute([cell])[0]
        if ref_name == "reference" and rtol is None:
            # ask the reference for half the bound this cell's test accepts
            band = (t_equivalent(N_SIGMA, m.se_dof) * m.se + floor * abs(m.k_a) if _finite(m.se) and _finite(m.k_a)
                    else math.nan)
            target = 0.5 * REF_SHARE * band / abs(m.k_a) if _finite(band) and m.k_a else ref.rtol
            q = ref.compute_cell(cell[0], cell[1], rtol=min(max(target, REF_RTOL_MIN), 0.5))
        else:
            q = ref.compute([cell])[0]
        row = compare(q, m, floor)
        rows.append(row)
        if on_cell is not None:
            on_cell(row)
    verdict = overall(rows)
    return {"verdict": verdict, "exit_status": EXIT_STATUS[verdict], "counts": counts(rows),
            "ok": verdict == "agree", "rows": rows, "n_sigma": N_SIGMA, "ref_share": REF_SHARE, "floor": floor,
            "against": against, "reference": ref_name, "seconds": time.perf_counter() - t0,
            "settings": {ref_name: ref.settings(), against: mc.settings()},
            "instrument": instrument.to_dict(), "model": model.to_json_dict()}


#: How the references are named in the summary and the picture (the registry's names: "reference" is the
#: RQMC reference, whose name alone read "the reference reference").
REFERENCE_LABELS = {"reference": "RQMC reference (99.9 % confidence bound)",
                    "quadrature": "quadrature reference (error bound)",
                    "numpy-mc-mesh": "mesh Monte Carlo reference (SE)"}


def reference_label(name: str) -> str:
    return REFERENCE_LABELS.get(name, f"{name} reference")


def band_text(report: dict[str, Any]) -> str:
    """'4 SE' (SEs without degrees of freedom), or the t quantiles the cells' SEs took for the
    N_SIGMA test, e.g. '5.48 SE (4 sigma at 15 degrees of freedom)'."""
    ks = sorted({round(r.n_sigma, 2) for r in report["rows"] if math.isfinite(r.n_sigma)})
    dofs = sorted({round(r.dof) for r in report["rows"] if math.isfinite(r.dof)})
    if not dofs or not ks:
        return f"{report['n_sigma']:g} SE"
    k = f"{ks[0]:.3g}" if len(ks) == 1 else f"{ks[0]:.3g}-{ks[-1]:.3g}"
    d = f"{dofs[0]}" if len(dofs) == 1 else f"{dofs[0]}-{dofs[-1]}"
    return f"{k} SE ({report['n_sigma']:g} sigma at {d} degrees of freedom)"


def floor_name(report: dict[str, Any]) -> str:
    """What the floor of ``report`` is: the float32 renderer's, or the float64 round-off of numpy-mc."""
    return "float32 floor" if report.get("against") == "mitsuba" else "round-off floor"


def summary_line(report: dict[str, Any]) -> str:
    c = report["counts"]
    n = sum(c.values())
    return (f"validate: {c['agree']} agree, {c['disagree']} disagree, {c['inconclusive']} inconclusive "
            f"(of {n} cells; {report['against']} against the {reference_label(report['reference'])}, "
            f"{band_text(report)} + bound"
            + (f" + {floor_name(report)} {report['floor']:.1e}" if report["floor"] > 0 else "")
            + f"; {report['seconds']:.1f} s)")


def not_measured(r: CellComparison) -> bool:
    """A cell with no number to compare: a NaN k_A or SE (the Mitsuba backend's where float32
    underflows, a reference that gave none), not a difference of 0 SE."""
    return any(math.isnan(v) for v in (r.k_mc, r.se_mc, r.k_ref))


def failed_cell_text(r: CellComparison) -> str:
    """How the FAILED line names a cell that disagrees: its difference in SE, the difference itself
    when the SE is 0 (no sampling noise), or that it was not measured (a NaN k_A or SE is not 'SE 0')."""
    cell = f"({r.tan_eps:g}, {r.beta_deg:g})"
    if not_measured(r):
        side = "the reference's" if math.isnan(r.k_ref) else "its"
        return f"{cell} not measured ({side} k_A or SE is NaN)"
    if not math.isnan(r.z):
        return f"{cell} {r.z:+.1f} SE"
    return f"{cell} diff {r.diff:+.2g}, SE 0"


def failed_line(rows: Sequence[CellComparison]) -> str:
    """The command line's ``FAILED:`` line: every cell that disagrees (:func:`failed_cell_text`)."""
    return "FAILED: " + ", ".join(failed_cell_text(r) for r in rows if r.verdict == "disagree")


def z_bars(rows: Sequence[CellComparison], limit: float = 3 * N_SIGMA) -> list[tuple[float, str]]:
    """What validate.png's upper panel draws for each cell: (bar height, label). A finite z within
    +-``limit`` is its own bar, unlabelled; one beyond is clipped at the axis and labelled with its
    value; an infinite z is clipped and labelled '+inf' / '-inf'; a cell without an SE (SE 0: z
    undefined) is at the axis' end on its side when it disagrees, at 0 when it agrees, labelled 'SE 0';
    a cell not measured (:func:`not_measured`) has no bar and is labelled 'not measured'."""
    out = []
    for r in rows:
        if not_measured(r):
            out.append((0.0, "not measured"))
        elif math.isinf(r.z):
            out.append((math.copysign(limit, r.z), "+inf" if r.z > 0 else "-inf"))
        elif math.isnan(r.z):
            out.append((math.copysign(limit, r.diff) if r.verdict == "disagree" else 0.0, "SE 0"))
        elif abs(r.z) > limit:
            out.append((math.copysign(limit, r.z), f"{r.z:+.3g}"))
        else:
            out.append((float(r.z), ""))
    return out


def rows_csv(rows: Sequence[CellComparison]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        # a missing value is a blank cell, never "nan" (docs/inputs-outputs.md, "Missing values")
        w.writerow({k: ((f"{v:.9g}" if math.isfinite(v) else "") if isinstance(v, float) else v)
                    for k, v in asdict(r).items()})
    return buf.getvalue()


def report_json(report: dict[str, Any]) -> dict[str, Any]:
    """The JSON document of a report (validate.json, ``--json``)."""
    doc = {k: v for k, v in report.items() if k != "rows"}
    doc["cells"] = [asdict(r) for r in report["rows"]]
    return doc


#: validate.png draws k_A on a log axis when the values span more than this factor
K_A_LOG_SPAN = 10.0


def _bar(errors):
    """Error-bar half-lengths: 0 where an error is not finite (none stated, or inf)."""
    import numpy as np
    e = np.asarray(errors, dtype=np.float64)
    return np.where(np.isfinite(e), e, 0.0)


def plot(report: dict[str, Any], path: str | Path) -> Path:
    """Two panels: the difference of each cell in combined standard errors (with its pass band),
    coloured by verdict, and both k_A values with their uncertainties."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from roadgonio.fileio import atomic_savefig
    rows = report["rows"]
    labels = [f"{r.tan_eps:g} / {r.beta_deg:g}" for r in rows]
    x = np.arange(len(rows))
    band = np.array([r.allowed / r.sigma if r.sigma > 0 and math.isfinite(r.allowed) else N_SIGMA for r in rows])
    colour = {"agree": "tab:blue", "disagree": "tab:red", "inconclusive": "tab:orange"}
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(max(7.0, 0.6 * len(rows) + 2), 7.5), sharex=True)
    # a z beyond the axis, infinite or undefined (SE 0) is clipped at the axis' end, hatched and labelled
    # there; a cell not measured (NaN k_A) has no bar, a cross at 0 and its label (z_bars)
    bars = z_bars(rows, 3 * N_SIGMA)
    ax1.bar(x, [h for h, _ in bars], color=[colour[r.verdict] for r in rows],
            hatch=["//" if label and label != "not measured" else None for _, label in bars])
    boxed = dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.85)
    for i, (h, label) in enumerate(bars):
        if label == "not measured":
            ax1.plot(x[i], 0.0, "x", color=colour[rows[i].verdict], ms=9, mew=2)
            # upwards, inside the panel (user audit, session 44: downwards it ran across the axis into
            # the panel below)
            ax1.annotate(label, (x[i], 0.0), xytext=(0, 8), textcoords="offset points", rotation=90, ha="center",
                         va="bottom", fontsize=8, bbox=boxed)
        elif label:
            up = h >= 0
            ax1.plot(x[i], h, "^" if up else "v", color="k", ms=7)
            ax1.annotate(label, (x[i], h), xytext=(0, 7 if up else -7), textcoords="offset points", ha="center",
                         va="bottom" if up else "top", fontsize=8, fontweight="bold", bbox=boxed)
    ax1.step(np.r_[x - 0.5, x[-1] + 0.5], np.r_[band, band[-1]], where="post", color="k", ls="--", lw=1,
             label=f"allowed: {band_text(report)}\n+ reference bound + {floor_name(report)}")
    ax1.step(np.r_[x - 0.5, x[-1] + 0.5], -np.r_[band, band[-1]], where="post", color="k", ls="--", lw=1)
    lo, hi = ax1.get_ylim()         # room for the labels beyond the clipped bars
    ax1.set_ylim(min(lo, -1.3 * 3 * N_SIGMA) if any(label and h < 0 for h, label in bars) else lo,
                 max(hi, 1.3 * 3 * N_SIGMA) if any(label and h > 0 for h, label in bars) else hi)
    ax1.axhline(0, color="0.5", lw=0.8)
    ax1.set_ylabel(f"(k_{report['against']} - k_ref) / SE")
    from matplotlib.patches import Patch
    handles = ax1.get_legend_handles_labels()[0] + [Patch(color=c, label=v) for v, c in colour.items()]
    # headroom above the band for the legend (audit 27: it covered the upper "allowed" line)
    lo, hi = ax1.get_ylim()
    ax1.set_ylim(lo, hi + 0.8 * (hi - lo))
    ax1.legend(handles=handles, loc="upper right", fontsize=8)
    c = report["counts"]
    ax1.set_title(f"k_A: {report['against']} vs the {reference_label(report['reference'])}\n"
                  f"{report['verdict'].upper()}: {c['agree']} agree, {c['disagree']} disagree, "
                  f"{c['inconclusive']} inconclusive", fontsize=10)
    kq = np.array([r.k_ref for r in rows])
    km = np.array([r.k_mc for r in rows])
    err_ref = [r.bound_ref if math.isfinite(r.bound_ref) else r.se_ref for r in rows]
    # an error that is not finite (no SE stated: inf) draws no bar (user audit: nan_to_num made inf the
    # largest float, and matplotlib's layout failed with a singular matrix, writing nothing)
    ax2.errorbar(x - 0.12, kq, yerr=_bar(err_ref), fmt="o", ms=5,
                 label=f"{reference_label(report['reference'])} (float64)")
    ax2.errorbar(x + 0.12, km, yerr=_bar([r.se_mc for r in rows]), fmt="s", ms=5, mfc="none",
                 label=f"{report['against']} (+-1 SE)")
    ax2.axhline(1.0, color="0.5", lw=0.8)
    ax2.set_ylabel("k_A")
    # k_A over decades (a lobe far narrower than the apertures: 0.8 and 926 in one report) on a log axis,
    # limited to the values with a margin: on a linear one the cells near 1 sat on zero and an error bar
    # of an unresolved cell stretched it to 1e12 (user audit, session 44)
    shown = np.r_[kq, km]
    shown = shown[np.isfinite(shown) & (shown > 0)]
    if shown.size and shown.max() > K_A_LOG_SPAN * shown.min():
        ax2.set_yscale("log")
        ax2.set_ylim(shown.min() / 2.0, shown.max() * 2.0)
        ax2.set_ylabel("k_A (log scale)")
    ax2.set_xticks(x)
    ax2.set_xticklabels(labels, rotation=45, ha="right")
    ax2.set_xlabel("cell: tan eps / beta (deg)")
    ax2.legend(loc="best", fontsize=8)
    fig.tight_layout()
    out = atomic_savefig(fig, path)
    plt.close(fig)
    return out


def write_outputs(report: dict[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """validate.csv, validate.json and validate.png in ``out_dir``, all or none (one atomic group)."""
    from roadgonio.fileio import OutputGroup
    out_dir = Path(out_dir)
    with OutputGroup(out_dir) as out:
        out.text("validate.csv", rows_csv(report["rows"]))
        out.json("validate.json", report_json(report))
        out.figure("validate.png", lambda p: plot(report, p))
    return {"csv": out_dir / "validate.csv", "json": out_dir / "validate.json", "png": out_dir / "validate.png"}
