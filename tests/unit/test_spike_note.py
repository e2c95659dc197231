"""A sample whose model has a peak at beta = 0 narrower than any aperture (trial 6, defect 1: the
paper's power reading fitted to CIE R2 and R4): surface.sample.unresolved_spike against a closed
form, the note every command prints once, and the bundled fits it flags."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from roadgonio.cli import main
from roadgonio.errors import ModelWarning
from roadgonio.surface.model import THETA_R_STAR, RoadModel, RoadParams
from roadgonio.surface.sample import SPIKE_DROP, SPIKE_WIDTH_DEG, resolve_sample, unresolved_spike

#: float64 round-off of the closed form (a power of a number near 1)
ROUND_OFF = 1e-9


def _exponent_only(h: float, mu: float) -> RoadModel:
    """eq. 4's empirical term alone (p = 0): r(beta) / r(0) = ((180 - beta) / 180)^W at every tan eps,
    W = exp(1 + h f(e)^2) (docs/conventions.md, section 3)."""
    return RoadModel(RoadParams(k_exp=0.05, p=0.0, h=h, mu=mu), variant="power")


def _closed_form_ratio(h: float, mu: float, tan_eps: np.ndarray) -> np.ndarray:
    ti = np.arctan(tan_eps)
    tr = math.radians(89.0)                           # alpha = 1 deg
    e = ti * tr / THETA_R_STAR
    f = np.sin(e) * np.cos(e) / (np.cos(e) ** 2 + mu)
    W = np.exp(1.0 + h * f ** 2)
    return (1.0 - SPIKE_WIDTH_DEG / 180.0) ** W


@pytest.mark.parametrize("h, mu", [(0.37, 0.0017), (0.05, 0.0017), (0.37, 0.05), (0.2, 0.005)])
def test_unresolved_spike_against_the_closed_form(h, mu):
    m = _exponent_only(h, mu)
    t, ratio = unresolved_spike(m)
    grid = np.array([0.25, 0.5, 0.75, 1, 1.25, 1.5, 1.75, 2, 2.5, 3, 3.5, 4, 4.5, 5, 5.5, 6, 6.5, 7, 7.5, 8,
                     8.5, 9, 9.5, 10, 10.5, 11, 11.5, 12])
    exact = _closed_form_ratio(h, mu, grid)
    flagged = exact < 1.0 - SPIKE_DROP
    assert np.array_equal(t, grid[flagged])
    assert np.allclose(ratio, exact[flagged], rtol=ROUND_OFF, atol=1e-300)   # (subnormals flushed)


def test_the_threshold_cases_both_ways():
    """The closed-form cases above straddle the threshold: one flags nothing, one flags cells."""
    assert not unresolved_spike(_exponent_only(0.05, 0.0017))[0].size
    assert unresolved_spike(_exponent_only(0.37, 0.0017))[0].size


@pytest.mark.parametrize("name, variant, spike", [("R2", "power", True), ("R4", "power", True),
                                                  ("R3", "power", False), ("R1", "power", False),
                                                  ("R2", "smooth", False), ("R4", "smooth", False)])
def test_bundled_fits(name, variant, spike):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        smp = resolve_sample(name, variant)
    notes = [w for w in caught if issubclass(w.category, ModelWarning)]
    assert bool(notes) == spike, [str(w.message) for w in notes]
    if spike:
        t, ratio = unresolved_spike(smp.model)
        assert t.max() == 12 and ratio.min() < 0.5           # the artefact the trial found: k_A 0.43 / 0.26
        assert "--model-variant smooth" in str(notes[0].message)


def test_the_command_line_says_it_once(capsys):
    """`ka` on R2 (power): one note on stderr (the sample is resolved more than once on the way),
    nothing on stdout's JSON; R2 smooth: no note."""
    argv = ["ka", "--instrument", "lab", "--sample", "R2", "--tan-eps", "12", "--beta", "0", "--backend",
            "quadrature", "--accuracy", "fast", "--json"]
    assert main(argv) == 0
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("roadgonio: note: R2 (power fit): r at beta = 0 is a spike")
    assert "note" not in out
    assert main(argv[:4] + ["R2", "--model-variant", "smooth"] + argv[5:]) == 0
    assert "note" not in capsys.readouterr().err


def test_auto_alternatives_never_use_a_spike_fit():
    """`correct --reference` picks the two CIE tables nearest to the measured one as alternatives
    for the model uncertainty; R2 is one of them for R1, R3, C1 and C2, and its power fit's spike
    (k_A 0.43 at grazing beta 0 for any instrument) would be passed off as model uncertainty: the
    alternative takes its smooth fit instead, and a note says so. Asked for explicitly, a table is
    fitted as asked."""
    from roadgonio.correction.reference import resolve_alternatives
    from roadgonio.surface.rtable import bundled_table
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        alts = resolve_alternatives("auto", bundled_table("R3"), reference_name="R3")
    assert "R2" in alts and alts["R2"].variant == "smooth"
    assert all(not unresolved_spike(m)[0].size for m in alts.values())
    notes = [str(w.message) for w in caught if issubclass(w.category, ModelWarning)]
    assert len(notes) == 1 and notes[0].startswith("the alternative reference R2")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        assert resolve_alternatives("R2", bundled_table("R3"), reference_name="R3")["R2"].variant == "power"
