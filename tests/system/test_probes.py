"""Probes of issue 21: a careful and a hostile user try every command and the Python API.

Each probe is one input, one command (or API call) and one expected outcome: exit status 2 with
ONE line naming the file/field/option and what was expected (no traceback), or a correct result
(checked independently of the code under test where a number is involved). A probe is judged as

* ``OK``: the expected outcome;
* ``silent-wrong``: exit 0 (or a returned value) where an error was expected, or a result that is
  not right (NaN presented as a number, two seeds with the same random numbers, a writer whose
  file its reader refuses...);
* ``traceback``: an exception that is not a :class:`~roadgonio.errors.RoadgonioError` (the user
  would see a traceback), including a float warning (warnings are errors in the tests);
* ``misleading``: exit 2, but the message does not name what it should, is not one line, or
  refuses a valid input.

The classes are those of the issue: ``input`` (ignored or coerced input), ``seeds``, ``blanks``
(tables with blanks or zeros), ``writers``, ``meshes``, ``extremes``, ``paths``, ``conventions``,
``overwrites``. With ``ROADGONIO_PROBE_TALLY=FILE`` set, every probe appends its verdict to FILE (a
JSON line), so that a run on older code gives the tally of what was wrong
(``python tests/system/test_probes.py FILE`` prints it).
"""
from __future__ import annotations

import contextlib
import io
import re
import json
import math
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from roadgonio.errors import RoadgonioError
from helpers import GOOD_INSTRUMENT, grid_mesh

CLASSES = ("input", "seeds", "blanks", "writers", "meshes", "extremes", "paths", "conventions", "overwrites")
COMMANDS = ("tables", "table", "fit", "ka", "render", "validate", "uncertainty", "correct", "design", "road",
            "compare", "classify", "api")

GOOD = GOOD_INSTRUMENT

#: A model close to the fit of CIE R3 (tests/conftest.py R3LIKE), so no probe waits for a fit.
R3LIKE = dict(k_diff=0.028937, k_phong=1.8147, n_phong=34.467, k_retro=0.052577, n_retro=11.307,
              k_exp=0.088927, p=2.137, h=0.49843, mu=0.03123)


# ----------------------------------------------------------------------------------------------
# Running a probe and judging it
# ----------------------------------------------------------------------------------------------

@dataclass
class Outcome:
    rc: int | None = None          # exit status (API: 0 returned, 2 RoadgonioError)
    out: str = ""
    err: str = ""
    value: Any = None              # what an API call returned
    exc: BaseException | None = None   # an exception a user would see as a traceback

    def json(self):
        return json.loads(self.out)


def cli(*argv: str) -> Outcome:
    """``roadgonio ARGV`` in this process (stdout and stderr captured; argparse's exit caught)."""
    from roadgonio.cli import main
    o, e = io.StringIO(), io.StringIO()
    res = Outcome()
    with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
        try:
            res.rc = main([str(a) for a in argv])
        except SystemExit as ex:          # argparse: its error line, status 2
            res.rc = ex.code if isinstance(ex.code, int) else 2
        except Exception as ex:           # noqa: BLE001 - a traceback for the user
            res.exc = ex
    res.out, res.err = o.getvalue(), e.getvalue()
    return res


def api(fn: Callable[[], Any]) -> Outcome:
    """A Python API call: a RoadgonioError is the API's 'exit 2' (its one-line message)."""
    res = Outcome()
    try:
        res.value = fn()
        res.rc = 0
    except RoadgonioError as ex:
        res.rc = 2
        res.err = f"roadgonio: error: {ex}\n"
    except Exception as ex:               # noqa: BLE001
        res.exc = ex
    return res


def sub(*argv: str, cwd: Path, timeout: float = 300) -> Outcome:
    """``roadgonio ARGV`` in a subprocess (what a user's terminal shows on stderr)."""
    env = {k: v for k, v in os.environ.items() if k not in ("ROADGONIO_PROBE_TALLY",)}
    p = subprocess.run([sys.executable, "-m", "roadgonio", *map(str, argv)], cwd=cwd, capture_output=True,
                       text=True, timeout=timeout, env=env)
    res = Outcome(rc=p.returncode, out=p.stdout, err=p.stderr)
    if "Traceback (most recent call last)" in p.stderr:
        res.exc = RuntimeError(p.stderr.strip().splitlines()[-1])
    return res


@dataclass
class Probe:
    pid: str
    cls: str
    command: str
    action: Callable[[Path], Outcome]
    expect: str = "error"                      # "error" | "ok" | "either"
    must: tuple[str, ...] = ()                 # words the error line must contain
    check: Callable[[Outcome, Path], None] | None = None   # raises AssertionError when the result is wrong
    needs_mitsuba: bool = False
    slow: bool = False
    ok_codes: tuple[int, ...] = (0,)           # exit statuses of a completed run (validate: 0, 1, 3)

    def __post_init__(self):
        assert self.cls in CLASSES and self.command in COMMANDS, (self.cls, self.command)
        assert self.expect in ("error", "ok", "either")


def error_lines(res: Outcome) -> list[str]:
    return [ln for ln in res.err.splitlines() if ln.strip()]


def judge(p: Probe, res: Outcome, tmp: Path) -> tuple[str, str]:
    """(verdict, why) of one probe's outcome (module docstring)."""
    if res.exc is not None:
        return "traceback", f"{type(res.exc).__name__}: {res.exc}"
    lines = error_lines(res)
    if res.rc == 2:
        if p.expect == "ok":
            return "misleading", "refused a valid input: " + " | ".join(lines)
        if len(lines) != 1:
            return "misleading", f"{len(lines)} lines on stderr: " + " | ".join(lines)
        line = lines[0]
        if "error:" not in line:
            return "misleading", "not an error line: " + line
        missing = [m for m in p.must if m.lower() not in line.lower()]
        if missing:
            return "misleading", f"the line does not name {missing}: {line}"
        return "OK", line
    if res.rc not in p.ok_codes:
        return "traceback", f"exit status {res.rc}: " + " | ".join(lines)
    if p.expect == "error":
        return "silent-wrong", "exit 0, expected an error naming " + ", ".join(p.must) + f"; stdout {res.out[:200]!r}"
    if p.check is not None:
        try:
            p.check(res, tmp)
        except AssertionError as ex:
            return "silent-wrong", f"wrong result: {ex}"
    return "OK", "correct result"


def record(p: Probe, verdict: str, why: str) -> None:
    path = os.environ.get("ROADGONIO_PROBE_TALLY")
    if path:
        with open(path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps({"probe": p.pid, "class": p.cls, "command": p.command, "verdict": verdict,
                                 "why": why[:300]}) + "\n")


# ----------------------------------------------------------------------------------------------
# Inputs the probes make
# ----------------------------------------------------------------------------------------------

def instrument(tmp: Path, text: str = GOOD, name: str = "inst.toml") -> Path:
    p = tmp / name
    p.write_text(text, encoding="utf-8")
    return p


def replace(old: str, new: str, text: str = GOOD, count: int = 1) -> str:
    assert old in text, old
    return text.replace(old, new, count)


def model_file(tmp: Path, params: dict | None = None, file: str = "r3like.json", **top) -> Path:
    p = tmp / file
    p.write_text(json.dumps({"variant": "power", "params": dict(R3LIKE) if params is None else params, **top}))
    return p


def r3_values() -> np.ndarray:
    from roadgonio.surface.rtable import bundled_table
    return bundled_table("R3").r.copy()


def table_file(tmp: Path, name: str, r: np.ndarray, suffix: str = ".csv") -> Path:
    from roadgonio.surface.rtable import RTable
    return RTable(r, name=name).write(tmp / f"{name}{suffix}")


def hand_table_file(tmp: Path, name: str, r: np.ndarray) -> Path:
    """A CSV r-table of ``r`` (x 1e4) as a user writes it by hand: not through roadgonio's writer,
    which refuses what its reader would (trial 10 D3)."""
    from roadgonio.surface.rtable import R_SCALE, grid_csv_text
    p = tmp / f"{name}.csv"
    p.write_text(grid_csv_text(r, name, scale=R_SCALE))
    return p


def edited(name: str, edit: Callable[[np.ndarray], None]) -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        r = r3_values()
        edit(r)
        return table_file(tmp, name, r)
    return make


def _set(i, j, v):
    def e(r):
        r[i, j] = v
    return e


zero00 = edited("zero00", _set(0, 0, 0.0))
blank00 = edited("blank00", _set(0, 0, np.nan))
blank20 = edited("blank20", _set(8, 0, np.nan))


def _zerocol(r):
    r[:, 0] = 0.0


zerocol = edited("zerocol", _zerocol)


def _upto1(r):
    r[5:, :] = np.nan            # only tan eps <= 1 measured


upto1 = edited("upto1", _upto1)


def _beta45(r):
    r[:, 10:] = np.nan           # nothing beyond beta = 45 deg


beta45 = edited("beta45", _beta45)


def diag(tmp: Path) -> Path:
    """Values on the diagonal only: no grid cell with four tabulated corners (Q0 undefined)."""
    r = np.full_like(r3_values(), np.nan)
    k = np.arange(20)
    r[k, k] = r3_values()[k, k]
    return table_file(tmp, "diag", r)


def rtb_named(tmp: Path, name: str, file: str = "evil.rtb") -> Path:
    from roadgonio.surface.rtable import bundled_table
    lines = bundled_table("R3").to_rtb_text().splitlines()
    lines[1] = name
    p = tmp / file
    p.write_text("\n".join(lines) + "\n")
    return p


def ldt_with(tmp: Path, line: int, value: str) -> Path:
    """The bundled EULUMDAT file with one header line (1-based) replaced."""
    from roadgonio.road.luminaire import bundled_luminaire_path
    lines = bundled_luminaire_path().read_text(encoding="latin-1").splitlines()
    lines[line - 1] = value
    p = tmp / "lum.ldt"
    p.write_text("\r\n".join(lines) + "\r\n", encoding="latin-1")
    return p


PINHOLE = GOOD.replace("pupil_radius_m = 0.005", "pupil_radius_m = 0.0").replace(
    "field_half_angle_deg = 0.05", "field_half_angle_deg = 0.0")


def mesh_instrument(tmp: Path, xs, ys, text: str = PINHOLE) -> Path:
    grid_mesh(tmp / "grid.ply", xs, ys)
    return instrument(tmp, text.replace("size_x_m = 2.0\nsize_y_m = 0.5", 'mesh = "grid.ply"'))


class Streams:
    """Records the random streams a computation opens (numpy generators and seed sequences), as
    the first words of their state: two runs share random numbers iff they share a stream."""

    def __init__(self, monkeypatch):
        self.seen: set[tuple[int, ...]] = set()
        real_rng, real_ss = np.random.default_rng, np.random.SeedSequence
        seen = self.seen

        def key(ss) -> tuple[int, ...]:
            return tuple(int(v) for v in ss.generate_state(4))

        def rng(seed=None, *a, **k):
            if isinstance(seed, real_ss):
                seen.add(key(seed))
            elif seed is not None and not isinstance(seed, np.random.Generator):
                seen.add(key(real_ss(seed)))
            return real_rng(seed, *a, **k)

        class Recorded(real_ss):
            def __init__(self, entropy=None, *a, **k):
                super().__init__(entropy, *a, **k)
                seen.add(key(self))

        monkeypatch.setattr(np.random, "default_rng", rng)
        monkeypatch.setattr(np.random, "SeedSequence", Recorded)

    def take(self) -> set[tuple[int, ...]]:
        out = set(self.seen)
        self.seen.clear()
        return out


def shared_streams(monkeypatch, run: Callable[[int, Any], Any], a: tuple[int, Any], b: tuple[int, Any],
                   c: tuple[int, Any]) -> set:
    """Streams that run(a) and run(b) share and run(c) (an unrelated seed) does not: the ones a
    seed opens (streams of fixed seeds, e.g. a geometry check's, are in every run)."""
    from roadgonio.engines import bundle as forward
    s = Streams(monkeypatch)
    got = []
    for seed, arg in (a, b, c):
        forward._sobol_net.cache_clear()
        run(seed, arg)
        got.append(s.take())
    return (got[0] & got[1]) - got[2]


# ----------------------------------------------------------------------------------------------
# Checks of results (written apart from the code under test)
# ----------------------------------------------------------------------------------------------

def strict_json(text: str):
    """JSON as the standard defines it (no NaN, no Infinity)."""
    def bad(c):
        raise AssertionError(f"non-standard JSON constant {c}")
    return json.loads(text, parse_constant=bad)


def json_has(**expected):
    def check(res: Outcome, tmp: Path) -> None:
        d = strict_json(res.out)
        for k, v in expected.items():
            assert k in d, f"no {k} in {d}"
            assert d[k] == v, f"{k} = {d[k]!r}, expected {v!r}"
    return check


def no_float_junk(obj, where="result") -> None:
    """No NaN or infinity anywhere in a result presented as numbers."""
    if isinstance(obj, float):
        assert math.isfinite(obj), f"{where} holds {obj}"
    elif isinstance(obj, dict):
        for k, v in obj.items():
            no_float_junk(v, f"{where}.{k}")
    elif isinstance(obj, (list, tuple)):
        for k, v in enumerate(obj):
            no_float_junk(v, f"{where}[{k}]")


def inside(tmp: Path) -> None:
    """Nothing was created outside the probe's folder (its parent holds only it)."""
    here = {p.name for p in tmp.parent.iterdir()}
    assert here == {tmp.name}, f"created beside the working folder: {sorted(here - {tmp.name})}"


def quadrature_ka(inst_text: str, tmp: Path, cell=(1.0, 0.0), name: str = "ref.toml"):
    """k_A and its error bound of a flat-sample instrument by the deterministic quadrature."""
    import roadgonio as rg
    c = rg.ka_cell(str(instrument(tmp, inst_text, name)), str(model_file(tmp)), *cell, backend="quadrature",
                   rel_se=1e-6)
    return c.k_a, c.error_bound


# ----------------------------------------------------------------------------------------------
# The probes
# ----------------------------------------------------------------------------------------------

def _ka(*extra):
    return ("ka", "--backend", "quadrature", "--tan-eps", "1", "--beta", "0", *extra)


def P(*a, **k) -> Probe:
    return Probe(*a, **k)


PROBES: list[Probe] = []


def probe(*a, **k) -> None:
    PROBES.append(Probe(*a, **k))


# -- input: every input is checked where it enters ---------------------------------------------

probe("instrument-name-number", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t, '[instrument]\nname = 5\n' + GOOD), "--sample", "lambert")),
      must=("instrument.name", "text"))
probe("instrument-description-bool", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t, '[instrument]\ndescription = true\n' + GOOD),
                         "--sample", "lambert")), must=("instrument.description",))
probe("instrument-number-as-string", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t, replace("distance_m = 5.0", 'distance_m = "5.0"')),
                         "--sample", "lambert")), must=("source.distance_m", "number"))
probe("instrument-bool-as-number", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t, replace("radius_m = 0.005", "radius_m = true")),
                         "--sample", "lambert")), must=("source.radius_m",))
probe("instrument-calibration-unknown-key", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t, GOOD + '[calibration]\nmod = "lambert"\n'),
                         "--sample", "lambert")), must=("mod",))
probe("instrument-mesh-not-text", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t, replace("size_x_m = 2.0\nsize_y_m = 0.5", "mesh = 5")),
                         "--sample", "lambert")), must=("sample.mesh",))
probe("model-number-as-string", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t), "--sample",
                         model_file(t, {**R3LIKE, "k_diff": "0.03"}))), must=("params.k_diff", "number"))
probe("model-bool-as-number", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t), "--sample",
                         model_file(t, {**R3LIKE, "n_phong": True}))), must=("params.n_phong",))
probe("model-name-not-text", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t), "--sample", model_file(t, file="m.json", name=5))),
      must=("m.json", "name"))
probe("model-variant-not-text", "input", "api",
      lambda t: api(lambda: __import__("roadgonio").ka_cell(str(instrument(t)), str(model_file(t, variant=["power"])),
                                                            1, 0, backend="quadrature")), must=("variant",))
probe("empty-cells-text", "input", "ka",
      lambda t: cli("ka", "--instrument", instrument(t), "--sample", "lambert", "--backend", "quadrature",
                    "--cells", ""), must=("--cells",))
probe("empty-cells-list", "input", "api",
      lambda t: api(lambda: __import__("roadgonio").ka_table(str(instrument(t)), "lambert", backend="quadrature",
                                                             cells=[])), must=("cells",))
probe("cells-not-a-number", "input", "api",
      lambda t: api(lambda: __import__("roadgonio").ka_table(str(instrument(t)), "lambert", backend="quadrature",
                                                             cells=[("1", 0)])), must=("cells",))
probe("ldt-tilt-ignored", "input", "road",
      lambda t: cli("road", "--table", "R3", "--luminaire", ldt_with(t, 25, "10"), "--no-plots", "--out", t / "o"),
      must=("lum.ldt", "tilt"))
probe("ldt-lorl-over-100", "input", "road",
      lambda t: cli("road", "--table", "R3", "--luminaire", ldt_with(t, 23, "250"), "--no-plots", "--out", t / "o"),
      must=("lum.ldt", "LORL"))
probe("ldt-absolute-photometry", "input", "road",
      lambda t: cli("road", "--table", "R3", "--luminaire", ldt_with(t, 27, "-1"), "--no-plots", "--out", t / "o"),
      must=("lum.ldt", "lamps"))
probe("layout-unknown-key", "input", "road",
      lambda t: cli("road", "--table", "R3", "--layout", instrument(t, "[road]\nlanes = 2\nlanse = 3\n", "lay.toml"),
                    "--no-plots", "--out", t / "o"), must=("lay.toml",))
probe("sigma-unknown-key", "input", "uncertainty",
      lambda t: cli("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), "--sigma", "alpah_deg=0.1",
                    "--no-aperture", "--trials", "200", "--out", t / "u"), must=("alpah_deg",))
probe("design-vary-unknown-key", "input", "design",
      lambda t: cli("design", "--instrument", instrument(t), "--sample", model_file(t), "--vary",
                    "source.radius=0.01:0.02:2", "--backend", "quadrature", "--workers", "0", "--out", t / "d"),
      must=("source.radius",))
probe("correct-u-measured-text", "input", "correct",
      lambda t: cli("correct", "--measured", "R3", "--instrument", instrument(t), "--u-measured", "abc",
                    "--backend", "quadrature", "--out", t / "c"), must=("--u-measured",))
probe("validate-empty-cells", "input", "validate",
      lambda t: cli("validate", "--instrument", instrument(t), "--sample", "lambert", "--against", "numpy-mc",
                    "--cells", "", "--out", t / "v"), must=("--cells",))
probe("instrument-scene-unknown-key", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t, GOOD + '[scene]\nxlm = "holder.xml"\n'), "--sample", "lambert")),
      must=("inst.toml", "scene", "xlm"))
probe("instrument-scene-params-without-xml", "input", "ka",
      lambda t: cli("ka", "--instrument", instrument(t, GOOD + '[scene.params]\nholder_h_m = 0.1\n'), "--sample",
                    "lambert", "--backend", "mitsuba", "--cells", "1:0", "--accuracy", "fast"),
      must=("inst.toml", "scene.xml"), needs_mitsuba=True)
probe("model-variant-misspelt", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t), "--sample", model_file(t, file="m.json", varaint="smooth"))),
      must=("m.json", "varaint", "variant"))


def _model_without_variant(tmp: Path) -> Path:
    """A model file whose only variant key is misspelt (user audit, session 29: the line said only
    "missing key 'variant'", not which key was meant)."""
    p = tmp / "m2.json"
    p.write_text(json.dumps({"varaint": "smooth", "params": dict(R3LIKE)}))
    return p


probe("model-param-misspelt", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t), "--sample",
                         model_file(t, {**{k: v for k, v in R3LIKE.items() if k != "k_phong"},
                                        "k_phng": R3LIKE["k_phong"]}, file="m3.json"))),
      must=("m3.json", "k_phng", "did you mean 'k_phong'", "variant 'power' takes k_diff"))
probe("model-variant-misspelt-alone", "input", "ka",
      lambda t: cli(*_ka("--instrument", instrument(t), "--sample", _model_without_variant(t))),
      must=("m2.json", "'varaint'", "missing key 'variant'"))
probe("sigma-file-sigma-as-text", "input", "uncertainty",
      lambda t: cli("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), "--sigma",
                    instrument(t, '[sigma]\nalpha_deg = {sigma = "0.01"}\n', "spec.toml"), "--no-aperture",
                    "--trials", "200", "--out", t / "u"), must=("spec.toml", "sigma.alpha_deg.sigma"))
probe("sigma-file-unknown-key", "input", "uncertainty",
      lambda t: cli("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), "--sigma",
                    instrument(t, 'alpha_deg = 0.01\nbeta = 0.1\n', "spec.toml"), "--no-aperture",
                    "--trials", "200", "--out", t / "u"), must=("spec.toml", "beta"))
probe("layout-number-as-text", "input", "road",
      lambda t: cli("road", "--table", "R3", "--layout", instrument(t, '[road]\nlanes = "2"\n', "lay.toml"),
                    "--no-plots", "--out", t / "o"), must=("lay.toml", "lanes"))
probe("design-empty-cells", "input", "design",
      lambda t: cli("design", "--instrument", instrument(t), "--sample", model_file(t), "--vary",
                    "source.radius_m=0.005:0.01:2", "--cells", "", "--backend", "quadrature", "--workers", "0",
                    "--out", t / "d"), must=("--cells",))
probe("ka-cells-only-commas", "input", "ka",
      lambda t: cli("ka", "--instrument", instrument(t), "--sample", "lambert", "--backend", "quadrature",
                    "--cells", " , "), must=("--cells",))
probe("api-design-vary-one-text", "input", "api",
      lambda t: api(lambda: __import__("roadgonio").design_study(str(instrument(t)), "source.radius_m=0.005:0.01:2",
                                                                 str(model_file(t)), backend="quadrature", workers=0,
                                                                 cells=[(1, 0)])), expect="ok",
      check=lambda r, t: _assert(r.value.sizes.get("source.radius_m", r.value.sizes.get("point")) == 2,
                                 dict(r.value.sizes)))
probe("api-design-vary-values-text", "input", "api",
      lambda t: api(lambda: __import__("roadgonio").design_study(str(instrument(t)), {"source.radius_m": ["0.01", "x"]},
                                                                 str(model_file(t)), backend="quadrature", workers=0,
                                                                 cells=[(1, 0)])), must=("source.radius_m", "numbers"))
probe("table-unknown-name", "input", "table", lambda t: cli("table", "R9"), must=("R9",))
probe("option-not-a-number", "input", "uncertainty",
      lambda t: cli("uncertainty", "--instrument", "lab", "--sample", "lambert", "--sigma", "alpha_deg=0.01",
                    "--trials", "1e5"), must=("--trials", "whole number"))
probe("classify-not-a-table", "input", "classify", lambda t: cli("classify", instrument(t)), must=("inst.toml",))
probe("compare-missing-file", "input", "compare",
      lambda t: cli("compare", "R3", t / "nothere.csv", "--out", t / "c"), must=("nothere.csv",))
probe("tables-json", "input", "tables", lambda t: cli("tables", "--json"), expect="ok",
      check=lambda r, t: no_float_junk(strict_json(r.out)))
probe("fit-fix-nan", "input", "fit", lambda t: cli("fit", "R3", "--fix", "k_diff=nan", "--out", t / "f"),
      must=("k_diff",))
probe("fit-fixed-bool", "input", "api",
      lambda t: api(lambda: __import__("roadgonio").fit("R3", fixed={"k_diff": True})), must=("fixed",))
probe("render-spp-not-square", "input", "render",
      lambda t: cli("render", "--instrument", instrument(t), "--sample", "lambert", "--tan-eps", "1", "--beta", "0",
                    "--out", t / "r", "--spp", "3"), must=("--spp",))
probe("roadparams-string", "input", "api",
      lambda t: api(lambda: __import__("roadgonio.surface.model", fromlist=["x"]).RoadParams(k_diff="0.1")),
      must=("k_diff",))
probe("roadmodel-name-number", "input", "api",
      lambda t: api(lambda: __import__("roadgonio.surface.model", fromlist=["x"]).RoadModel(
          __import__("roadgonio.surface.model", fromlist=["x"]).RoadParams(k_diff=0.1), name=5)), must=("name",))
probe("table-dataarray-name-number", "input", "api",
      lambda t: api(lambda: __import__("roadgonio").table_info(_da_named(5))), must=("name",))


def _road_after_room_import(t):
    import roadgonio as rg
    import roadgonio.road.mc  # noqa: F401 - what any road work does first
    fn = getattr(rg, "road_metrics", None) or rg.road
    return api(lambda: fn("R3"))


probe("api-road-function-after-room-import", "input", "api", _road_after_room_import, expect="ok",
      check=lambda r, t: _assert(r.value[0]["class"] == "M3", r.value[0]["class"]))


def _da_named(name):
    import roadgonio as rg
    da = rg.read_table("R3")
    da.attrs["name"] = name
    return da


# -- seeds: the full seed reaches the generator; two accepted seeds never share numbers ----------

for _bad in (-1, 2 ** 63, 1.5, True, "3"):
    probe(f"api-seed-{_bad!r}", "seeds", "api",
          (lambda b: lambda t: api(lambda: __import__("roadgonio").ka_cell(
              str(instrument(t)), "lambert", 1, 0, backend="numpy-mc", seed=b, rel_se=0.05)))(_bad), must=("seed",))
probe("api-seed-max-accepted", "seeds", "api",
      lambda t: api(lambda: __import__("roadgonio").ka_cell(str(instrument(t)), "lambert", 1, 0, backend="numpy-mc",
                                                            seed=2 ** 63 - 1, rel_se=0.05)), expect="ok",
      check=lambda r, t: _assert(abs(r.value.k_a - 1.0) < 1e-12, f"lambert k_A {r.value.k_a}"))
probe("api-seed-numpy-int", "seeds", "api",
      lambda t: api(lambda: __import__("roadgonio").ka_cell(str(instrument(t)), "lambert", 1, 0, backend="numpy-mc",
                                                            seed=np.int64(3), rel_se=0.05)), expect="ok")
probe("cli-ka-seed-2^63", "seeds", "ka",
      lambda t: cli("ka", "--instrument", instrument(t), "--sample", "lambert", "--backend", "numpy-mc", "--tan-eps",
                    "1", "--beta", "0", "--seed", str(2 ** 63)), must=("--seed",))
probe("cli-uncertainty-seed-negative", "seeds", "uncertainty",
      lambda t: cli("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), "--sigma", "alpha_deg=0.01",
                    "--no-aperture", "--trials", "200", "--seed", "-1", "--out", t / "u"), must=("--seed",))
probe("cli-road-seed-2^63", "seeds", "road",
      lambda t: cli("road", "--table", "R3", "--u", table_file(t, "u", r3_values() * 0.01), "--seed", str(2 ** 63),
                    "--no-plots", "--out", t / "o"), must=("--seed",))
probe("cli-design-seed-negative", "seeds", "design",
      lambda t: cli("design", "--instrument", instrument(t), "--sample", model_file(t), "--vary",
                    "source.radius_m=0.01:0.02:2", "--backend", "numpy-mc", "--seed", "-5", "--workers", "0",
                    "--out", t / "d"), must=("--seed",))
probe("cli-fit-seed-2^63", "seeds", "fit", lambda t: cli("fit", "R3", "--seed", str(2 ** 63), "--out", t / "f"),
      must=("--seed",))
probe("cli-correct-seed-negative", "seeds", "correct",
      lambda t: cli("correct", "--measured", "R3", "--instrument", instrument(t), "--seed", "-1",
                    "--backend", "quadrature", "--out", t / "c"), must=("--seed",))
probe("api-design-seed-2^63", "seeds", "api",
      lambda t: api(lambda: __import__("roadgonio").design_study(str(instrument(t)), ["source.radius_m=0.005:0.01:2"],
                                                                 str(model_file(t)), backend="numpy-mc", seed=2 ** 63,
                                                                 workers=0)), must=("seed",))
probe("api-uncertainty-seed-max", "seeds", "api",
      lambda t: api(lambda: __import__("roadgonio").estimate_uncertainty(str(instrument(t)), str(model_file(t)),
                                                                         "alpha_deg=0.01", trials=500, aperture=False,
                                                                         seed=2 ** 63 - 1).seed), expect="ok",
      check=lambda r, t: _assert(r.value == 2 ** 63 - 1, r.value))
probe("render-seed-2^40", "seeds", "render",
      lambda t: cli("render", "--instrument", instrument(t), "--sample", "lambert", "--tan-eps", "1", "--beta", "0",
                    "--out", t / "r", "--seed", str(2 ** 40)), must=("--seed", "32-bit"), needs_mitsuba=True)
probe("render-seed-2^32-1", "seeds", "render",
      lambda t: cli("render", "--instrument", instrument(t), "--sample", "lambert", "--tan-eps", "1", "--beta", "0",
                    "--out", t / "r", "--seed", str(2 ** 32 - 1), "--resolution", "32", "--spp", "4", "--json"),
      expect="ok", check=lambda r, t: _assert(strict_json(r.out)["seed"] == 2 ** 32 - 1, r.out[:200]),
      needs_mitsuba=True)
probe("cli-ka-seed-not-whole", "seeds", "ka",
      lambda t: cli("ka", "--instrument", instrument(t), "--sample", "lambert", "--backend", "numpy-mc", "--tan-eps",
                    "1", "--beta", "0", "--seed", "1.5"), must=("--seed",))
probe("cli-design-seed-10^30", "seeds", "design",
      lambda t: cli("design", "--instrument", instrument(t), "--sample", model_file(t), "--vary",
                    "source.radius_m=0.01:0.02:2", "--backend", "numpy-mc", "--seed", str(10 ** 30), "--workers", "0",
                    "--out", t / "d"), must=("--seed",))
probe("cli-road-seed-text", "seeds", "road",
      lambda t: cli("road", "--table", "R3", "--u", table_file(t, "u", r3_values() * 0.01), "--seed", "abc",
                    "--no-plots", "--out", t / "o"), must=("--seed",))
probe("api-road-seed-negative", "seeds", "api",
      lambda t: api(lambda: __import__("roadgonio").road_metrics("R3", u=str(table_file(t, "u", r3_values() * 0.01)),
                                                                 seed=-3)), must=("seed",))
probe("cli-validate-seed-2^63", "seeds", "validate",
      lambda t: cli("validate", "--instrument", instrument(t), "--sample", "lambert", "--against", "numpy-mc",
                    "--seed", str(2 ** 63), "--out", t / "v"), must=("--seed",))


def _assert(cond, msg):
    assert cond, msg


def _design_seeds(t):
    """Per-point seeds of two root seeds: in range, full width, and never the same point seed."""
    from roadgonio.engines.cluster import seeds_for
    roots = [0, 1, 2, 2 ** 31, 2 ** 31 + 1, 2 ** 32, 2 ** 62, 2 ** 63 - 1, 12345, 12345 + 2 ** 32]
    n = 64
    table = {r: seeds_for(r, n) for r in roots}
    for r, s in table.items():
        assert all(isinstance(v, int) and 0 <= v <= 2 ** 63 - 1 for v in s), f"root {r}: seed out of range"
        assert len(set(s)) == n, f"root {r}: two points share a seed"
        assert seeds_for(r, 8) == s[:8], f"root {r}: point seeds depend on the number of points"
    for a in roots:
        for b in roots:
            if a < b:
                same = [k for k in range(n) if table[a][k] == table[b][k]]
                assert not same, f"roots {a} and {b} give point {same[0]} the same seed"
    assert max(max(s) for s in table.values()) >= 2 ** 32, "point seeds are reduced to 32 bits"
    return True


probe("design-point-seeds", "seeds", "design", lambda t: api(lambda: _design_seeds(t)), expect="ok")


def _stream_probe(backend: str, cells=((1.0, 2.0), (2.0, 0.0))):
    """Seed 5 at one cell and seed 5 + 10^6 * 2^32 at another must not share a random stream (a seed
    read as 32-bit words joined to the cell's keys did: [5, 10^6, 2 10^6] both times)."""
    def action(t, monkeypatch):
        import roadgonio as rg
        inst, smp = str(instrument(t)), str(model_file(t))

        def run(seed, cell):
            rg.ka_cell(inst, smp, *cell, backend=backend, seed=seed, rel_se=0.2)
        return api(lambda: shared_streams(monkeypatch, run, (5, cells[0]), (5 + (10 ** 6 << 32), cells[1]),
                                          (987654321, cells[0])))
    return action


def _no_shared(r, t):
    assert not r.value, f"{len(r.value)} random stream(s) shared by two different seeds"


for _b in ("numpy-mc", "reference", "numpy-mc-mesh"):
    probe(f"streams-{_b}", "seeds", "api", _stream_probe(_b), expect="ok", check=_no_shared)
probe("streams-mitsuba", "seeds", "ka", _stream_probe("mitsuba"), expect="ok", check=_no_shared, needs_mitsuba=True)


def _streams_of(run_of_seed):
    """Streams shared by seeds 1 and 2^32 + 1 of a Monte Carlo whose only key is the seed."""
    def action(t, monkeypatch):
        return api(lambda: shared_streams(monkeypatch, lambda seed, _: run_of_seed(t, seed), (1, None),
                                          (2 ** 32 + 1, None), (987654321, None)))
    return action


probe("streams-uncertainty", "seeds", "uncertainty",
      _streams_of(lambda t, seed: __import__("roadgonio").estimate_uncertainty(
          str(instrument(t)), str(model_file(t)), "alpha_deg=0.01", trials=500, aperture=False, seed=seed)),
      expect="ok", check=_no_shared)
probe("streams-road", "seeds", "road",
      _streams_of(lambda t, seed: road_api()("R3", u=str(table_file(t, "u", r3_values() * 0.02)), trials=500,
                                             seed=seed)), expect="ok", check=_no_shared)


def _seed_changes_result(action_of_seed, value_of):
    def action(t):
        def go():
            a, b, a2 = (value_of(action_of_seed(t, s)) for s in (1, 2 ** 32 + 1, 1))
            return a, b, a2
        return api(go)

    def check(r, t):
        a, b, a2 = r.value
        assert np.array_equal(a, a2), "the same seed gave different numbers"
        assert not np.array_equal(a, b), "seeds 1 and 2^32 + 1 gave the same numbers"
    return action, check


def _unc(t, seed):
    import roadgonio as rg
    return rg.estimate_uncertainty(str(instrument(t)), str(model_file(t)), "alpha_deg=0.01,eps_deg=0.02",
                                   trials=2000, aperture=False, seed=seed)


_a, _c = _seed_changes_result(_unc, lambda res: np.asarray(res.cases["no_aperture"].mc["u"]))
probe("uncertainty-seeds-differ", "seeds", "uncertainty", _a, expect="ok", check=_c)


def road_api():
    """The API's road function (``road_metrics``; ``road`` before issue 21, shadowed by the room
    ``roadgonio.road`` as soon as that is imported)."""
    import roadgonio.api as A
    return getattr(A, "road_metrics", None) or A.road


def _road_u(t, seed):
    s = road_api()("R3", u=str(table_file(t, "u", r3_values() * 0.02)), trials=2000, seed=seed, correlation="independent")
    return np.array([s[0]["uncertainty"]["independent"][k]["u"] for k in ("L_av", "U_o", "U_l")])


_a, _c = _seed_changes_result(_road_u, lambda v: v)
probe("road-seeds-differ", "seeds", "road", _a, expect="ok", check=_c)


def _correct_streams(t, monkeypatch):
    import roadgonio as rg

    def run(seed, _):
        rg.correct("R3", str(instrument(t)), backend="quadrature", accuracy="fast", rays=16, seed=seed, plots=False,
                   starts=4, rounds=2)
    return api(lambda: shared_streams(monkeypatch, run, (0, None), (1 << 32, None), (987654321, None)))


probe("correct-streams", "seeds", "correct", _correct_streams, expect="ok", check=_no_shared, slow=False)


# -- blanks and zeros: a quantity that needs a missing value is reported missing ----------------

probe("table-r00-zero", "blanks", "table", lambda t: cli("table", zero00(t), "--json"), expect="ok",
      check=json_has(S1=None, S2=None))
probe("table-r00-zero-text", "blanks", "table", lambda t: cli("table", zero00(t)), expect="ok",
      check=lambda r, t: _assert("S1 = missing" in r.out, r.out))
probe("table-r20-blank", "blanks", "table", lambda t: cli("table", blank20(t), "--json"), expect="ok",
      check=json_has(S1=None))
probe("table-no-complete-cell", "blanks", "table", lambda t: cli("table", diag(t), "--json"), expect="ok",
      check=json_has(Q0=None, S1=None, S2=None))
probe("table-info-api-missing", "blanks", "api", lambda t: api(lambda: __import__("roadgonio").table_info(
    str(zero00(t)))), expect="ok", check=lambda r, t: _assert(r.value["S1"] is None, f"S1 = {r.value['S1']!r}"))
probe("tables-all-zero", "blanks", "table",
      lambda t: cli("table", table_file(t, "zeros", np.where(np.isfinite(r3_values()), 0.0, np.nan)), "--json"),
      expect="ok", check=json_has(S1=None, S2=None))
probe("classify-r00-zero", "blanks", "classify", lambda t: cli("classify", zero00(t)), must=("zero00.csv", "S1"))
probe("classify-no-s1", "blanks", "classify", lambda t: cli("classify", diag(t), "--json"), must=("diag.csv", "S1"))


def _compare_check(r, t):
    d = strict_json(r.out)
    assert d["characteristics"]["zerocol.csv"]["S1"] is None, d["characteristics"]    # named by its file
    for k in ("ratio_min", "ratio_max", "ratio_median"):
        assert d[k] is None or math.isfinite(d[k]), (k, d[k])
    text = (t / "c" / "compare.csv").read_text()
    assert "inf" not in text.lower() and "nan" not in text.lower(), "compare.csv holds inf/nan"


probe("compare-zero-column", "blanks", "compare",
      lambda t: cli("compare", "R3", zerocol(t), "--json", "--no-plots", "--out", t / "c"), expect="ok",
      check=_compare_check)
probe("compare-zero-reference", "blanks", "compare",
      lambda t: cli("compare", zerocol(t), "R3", "--json", "--no-plots", "--out", t / "c2"), expect="ok",
      check=lambda r, t: no_float_junk({k: v for k, v in strict_json(r.out).items()}))
probe("compare-no-common-cells", "blanks", "compare",
      lambda t: cli("compare", zero00(t), diag(t), "--no-plots", "--out", t / "c3"), expect="either",
      must=("diag",), check=lambda r, t: _assert("nan" not in r.out.lower() and "inf" not in r.out.lower(), r.out))


probe("compare-zero-column-plots", "blanks", "compare",
      lambda t: cli("compare", "R3", zerocol(t), "--json", "--out", t / "cp"), expect="ok",
      check=lambda r, t: _assert((t / "cp" / "compare.png").stat().st_size > 10_000, "no picture"))


def _road_missing(*missing):
    def check(r, t):
        d = strict_json(r.out)
        for k in missing:
            assert d[k] is None, f"{k} = {d[k]} from a table that lacks the cells it needs"
        assert d["class"] is None, f"class {d['class']} from incomplete metrics"
        assert d.get("missing"), "no note saying which metrics are missing and why"
    return check


probe("road-table-tan-le-1", "blanks", "road",
      lambda t: cli("road", "--table", upto1(t), "--json", "--no-plots", "--out", t / "o"), expect="ok",
      check=_road_missing("L_av", "U_o", "U_l", "TI"))
probe("road-table-beta-le-45", "blanks", "road",
      lambda t: cli("road", "--table", beta45(t), "--json", "--no-plots", "--out", t / "o"), expect="ok",
      check=_road_missing("L_av", "U_o", "U_l", "TI"))
probe("road-table-blanks-text", "blanks", "road",
      lambda t: cli("road", "--table", "R3", "--table", upto1(t), "--no-plots", "--out", t / "o"), expect="ok",
      check=lambda r, t: _assert("missing" in r.out and not re.search(r"\b(nan|inf)\b", r.out.lower()), r.out))
probe("road-table-blank-00-is-fine", "blanks", "road",
      lambda t: cli("road", "--table", blank00(t), "--json", "--no-plots", "--out", t / "o"), expect="ok",
      check=lambda r, t: _assert(strict_json(r.out)["class"] == "M3", r.out[:300]))
def _dark_table(scale: float):
    from roadgonio.surface.rtable import RTable
    return RTable(np.where(np.isfinite(r3_values()), scale, np.nan), name="dark")


# an array, not a file: a CSV this dark is refused as r in sr^-1 (road-table-in-sr below)
probe("road-no-light", "blanks", "road",
      lambda t: api(lambda: road_api()(_dark_table(1e-12), plots=False)), expect="ok",
      check=lambda r, t: _assert(all(v is None or (math.isfinite(v) and v >= 0) for k, v in r.value[0].items()
                                     if k in ("L_av", "U_o", "U_l", "TI")), str(r.value[0])[:400]))
probe("road-table-in-sr", "input", "road",
      lambda t: cli("road", "--table", hand_table_file(t, "insr", r3_values() / 1e4), "--no-plots", "--out", t / "o"),
      must=("insr.csv", "sr^-1", "r x 1e4"))


probe("road-blanks-plots", "blanks", "road",
      lambda t: cli("road", "--table", "R3", "--table", beta45(t), "--json", "--out", t / "o"), expect="ok",
      check=lambda r, t: _assert((t / "o" / "road_luminance.png").stat().st_size > 10_000, "no picture"))


def _road_u_blanks(r, t):
    d = strict_json(r.out)
    no_float_junk(d)
    assert d["L_av"] is None


probe("road-u-with-blanks", "blanks", "road",
      lambda t: cli("road", "--table", upto1(t), "--u", table_file(t, "u", r3_values() * 0.02), "--trials", "500",
                    "--json", "--no-plots", "--out", t / "o"), expect="ok", check=_road_u_blanks)


# -- writers: what a writer writes, its reader reads ------------------------------------------

def _write(values, suffix=".csv"):
    """Write a table through the API and read it back: the writer refuses (one line, the reader's
    reason) or its reader reads what it wrote; a file the reader refuses is a wrong result."""
    def action(t):
        import roadgonio as rg
        da = rg.read_table("R3")
        da.values[...] = values(da.values.copy())
        res = api(lambda: rg.write_table(da, t / f"w{suffix}"))
        if res.rc != 0:
            return res
        back = api(lambda: rg.read_table(t / f"w{suffix}"))
        if back.rc == 2:
            return Outcome(rc=0, value=("unreadable", back.err.strip()))
        return back
    return action


def _readable(check=None):
    def run(r, t):
        assert not (isinstance(r.value, tuple) and r.value[0] == "unreadable"), f"the writer wrote a file its reader refuses: {r.value[1]}"
        if check is not None:
            check(r, t)
    return run


def _neg(v):
    v[3, 3] = -0.001
    return v


def _inf(v):
    v[3, 3] = np.inf
    return v


def _implausible(v):
    v[3, 3] = 20.0
    return v


def _diag_only(v):
    out = np.full_like(v, np.nan)
    k = np.arange(20)
    out[k, k] = v[k, k]
    return out


probe("write-negative", "writers", "api", _write(_neg), must=("must not be negative",), expect="either", check=_readable())
probe("write-negative-rtb", "writers", "api", _write(_neg, ".rtb"), must=("must not be negative",), expect="either", check=_readable())
probe("write-inf", "writers", "api", _write(_inf), must=("finite",), expect="either", check=_readable())
probe("write-all-nan", "writers", "api", _write(lambda v: v * np.nan), must=("no values",), expect="either",
      check=_readable())
probe("write-implausible", "writers", "api", _write(_implausible), must=("plausible",), expect="either",
      check=_readable())
probe("write-rtb-zero", "writers", "api", _write(lambda v: v * 0.0 + np.where(np.isfinite(v), 0.0, np.nan), ".rtb"),
      must=("RTB",), expect="either", check=_readable())
probe("write-rtb-no-q0", "writers", "api", _write(_diag_only, ".rtb"), expect="either", must=("Q0",),
      check=_readable(lambda r, t: _assert(int(np.isfinite(r.value.values).sum()) == 20, "cells lost")))
probe("table-to-rtb-with-zero", "writers", "table", lambda t: cli("table", zero00(t), "--to", t / "z.rtb"),
      must=("RTB", "0"))


def _model_round_trip(t):
    from roadgonio.surface.model import RoadModel, RoadParams
    m = RoadModel(RoadParams(**R3LIKE), name="a name\nwith a line", meta={"note": float("nan")})
    m.save(t / "m.json")
    back = RoadModel.load(t / "m.json")
    assert back.params == m.params and back.name == m.name
    return True


probe("model-round-trip", "writers", "api", lambda t: api(lambda: _model_round_trip(t)), expect="ok")


def _instrument_round_trip(t):
    from roadgonio.instrument.config import Instrument
    inst = Instrument.load(instrument(t, '[instrument]\nname = "caf\u00e9 \U0001F600 \\u007f"\n' + GOOD))
    text = inst.to_toml()
    (t / "back.toml").write_text(text, encoding="utf-8")
    back = Instrument.load(t / "back.toml")
    assert back.name == inst.name and back.source == inst.source
    return True


probe("instrument-round-trip-unicode", "writers", "api", lambda t: api(lambda: _instrument_round_trip(t)),
      expect="ok")


# -- meshes: an edge or a vertex under a detector ray is a hit --------------------------------

def _mesh_vs_flat(backend: str, xs, ys, text: str = PINHOLE):
    def action(t):
        import roadgonio as rg
        inst = mesh_instrument(t, xs, ys, text)
        return api(lambda: rg.ka_cell(str(inst), str(model_file(t)), 1, 0, backend=backend, seed=3, rel_se=3e-3))

    def check(r, t):
        from roadgonio.engines.validate import FLOAT32_FLOOR
        k_ref, bound = quadrature_ka(text, t)
        c = r.value
        # plus the renderer's float32 floor: since the first pass of 4096 samples the SE of this
        # cell is 1.5e-6, below the float32 differences of a mesh and a flat plane (8e-6)
        floor = FLOAT32_FLOOR.get(backend, 0.0) * abs(k_ref)
        assert abs(c.k_a - k_ref) <= 5 * c.se + bound + floor, f"mesh {c.k_a} +- {c.se} vs flat {k_ref}"
    return action, check


#: Detectors whose rays meet a grid's vertices and edges: a single ray (pinhole, no field) on the
#: sample centre; a pupil focused on the sample centre with no field (every ray passes through the
#: centre); pupil and field (the rim rays of the hit check run along the edge y = 0).
FOCUSED = GOOD.replace("field_half_angle_deg = 0.05", "field_half_angle_deg = 0.0")
DETECTORS = (("pinhole", PINHOLE), ("focused", FOCUSED), ("field", GOOD))
GRIDS = (("vertex-2x2", [-1, 0, 1], [-0.25, 0, 0.25]), ("vertex-4x4", np.linspace(-1, 1, 5), np.linspace(-0.25, 0.25, 5)),
         ("edge-2x1", [-1, 0, 1], [-0.25, 0.25]), ("diagonal-3x3", np.linspace(-1, 1, 4), np.linspace(-0.25, 0.25, 4)))
for _name, _xs, _ys in GRIDS:
    for _det, _text in DETECTORS:
        _a, _c = _mesh_vs_flat("numpy-mc-mesh", _xs, _ys, _text)
        probe(f"mesh-{_name}-{_det}-meshmc", "meshes", "api", _a, expect="ok", check=_c)
        _a, _c = _mesh_vs_flat("mitsuba", _xs, _ys, _text)
        probe(f"mesh-{_name}-{_det}-mitsuba", "meshes", "ka", _a, expect="ok", check=_c, needs_mitsuba=True)


def _flat_focused(backend):
    """The plain rectangle is two triangles whose shared diagonal runs through the sample centre."""
    def action(t):
        import roadgonio as rg
        return api(lambda: rg.ka_cell(str(instrument(t, FOCUSED)), str(model_file(t)), 1, 0, backend=backend, seed=3,
                                      rel_se=3e-3))

    def check(r, t):
        k_ref, bound = quadrature_ka(FOCUSED, t)
        assert abs(r.value.k_a - k_ref) <= 5 * r.value.se + bound, f"{r.value.k_a} +- {r.value.se} vs {k_ref}"
    return action, check


_a, _c = _flat_focused("numpy-mc-mesh")
probe("rectangle-focused-meshmc", "meshes", "api", _a, expect="ok", check=_c)
_a, _c = _flat_focused("mitsuba")
probe("rectangle-focused-mitsuba", "meshes", "ka", _a, expect="ok", check=_c, needs_mitsuba=True)


# -- extremes: one-line errors or correct numbers, no float warnings, the true reason -----------

def _ka_model(t, text, backend="quadrature", *extra):
    return cli("ka", "--instrument", instrument(t, text), "--sample", model_file(t), "--backend", backend,
               "--tan-eps", "1", "--beta", "0", "--json", *extra)


for _backend in ("quadrature", "numpy-mc", "reference"):
    probe(f"source-radius-1e-300-{_backend}", "extremes", "ka",
          (lambda b: lambda t: _ka_model(t, replace("radius_m = 0.005", "radius_m = 1e-300"), b))(_backend),
          expect="either", must=("source.radius_m",),
          check=lambda r, t: _assert(math.isfinite(strict_json(r.out)["k_a"]), r.out))
probe("pupil-radius-1e-300", "extremes", "ka",
      lambda t: _ka_model(t, replace("pupil_radius_m = 0.005", "pupil_radius_m = 1e-300"), "numpy-mc"),
      expect="either", must=("detector.pupil_radius_m",),
      check=lambda r, t: _assert(math.isfinite(strict_json(r.out)["k_a"]), r.out))
probe("source-distance-1e300", "extremes", "ka",
      lambda t: _ka_model(t, replace("distance_m = 5.0", "distance_m = 1e300")), must=("source.distance_m",))
probe("detector-distance-1e300", "extremes", "ka",
      lambda t: _ka_model(t, replace("distance_m = 10.0", "distance_m = 1e300")), must=("detector.distance_m",))
probe("focus-1e300", "extremes", "ka",
      lambda t: _ka_model(t, replace("field_half_angle_deg = 0.05", "field_half_angle_deg = 0.05\nfocus_m = 1e300")),
      must=("detector.focus_m",))
probe("sample-size-1e300", "extremes", "ka",
      lambda t: _ka_model(t, replace("size_x_m = 2.0", "size_x_m = 1e300")), must=("sample.size_x_m",))
probe("sample-size-1e300-mitsuba", "extremes", "ka",
      lambda t: _ka_model(t, replace("size_x_m = 2.0", "size_x_m = 1e300"), "mitsuba"), must=("sample.size_x_m",),
      needs_mitsuba=True)
probe("alpha-1e-300", "extremes", "ka",
      lambda t: _ka_model(t, replace("alpha_deg = 1.0", "alpha_deg = 1e-300")), must=("alpha",))
probe("tan-eps-1e300", "extremes", "ka",
      lambda t: cli("ka", "--instrument", instrument(t), "--sample", model_file(t), "--backend", "quadrature",
                    "--tan-eps", "1e300", "--beta", "0"), must=("tan",))
probe("uncertainty-trials-1e10", "extremes", "uncertainty",
      lambda t: cli("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), "--sigma",
                    "alpha_deg=0.01", "--no-aperture", "--trials", "10000000000", "--out", t / "u"),
      must=("--trials", "ROADGONIO_MAX_TRIALS"))
probe("uncertainty-batch-1e12", "extremes", "uncertainty",
      lambda t: cli("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), "--sigma",
                    "alpha_deg=0.01", "--no-aperture", "--adaptive", "--batch", "1000000000000", "--out", t / "u"),
      must=("--batch",))
probe("road-trials-1e10", "extremes", "road",
      lambda t: cli("road", "--table", "R3", "--u", table_file(t, "u", r3_values() * 0.01), "--trials", "10000000000",
                    "--no-plots", "--out", t / "o"), must=("--trials", "ROADGONIO_MAX_TRIALS"))
probe("correct-rays-1e10", "extremes", "correct",
      lambda t: cli("correct", "--measured", "R3", "--instrument", instrument(t), "--rays", str(2 ** 34),
                    "--backend", "quadrature", "--out", t / "c"), must=("--rays", "ROADGONIO_MAX_RAYS"))
probe("design-points-1e8", "extremes", "design",
      lambda t: cli("design", "--instrument", instrument(t), "--sample", model_file(t), "--vary",
                    "source.radius_m=0.001:0.004:100000000", "--backend", "quadrature", "--workers", "0",
                    "--out", t / "d"), must=("--vary", "ROADGONIO_MAX_DESIGN_POINTS"))
probe("render-spp-huge", "extremes", "render",
      lambda t: cli("render", "--instrument", instrument(t), "--sample", "lambert", "--tan-eps", "1", "--beta", "0",
                    "--out", t / "r", "--spp", str(2 ** 40)), must=("--spp",), needs_mitsuba=True)
probe("numpy-mc-batch-1e12", "extremes", "api",
      lambda t: api(lambda: __import__("roadgonio").ka_cell(str(instrument(t)), "lambert", 1, 0, backend="numpy-mc",
                                                            settings={"batch": 10 ** 12})), must=("batch",))
probe("ka-variant-scalar-rgb", "extremes", "ka",
      lambda t: sub("ka", "--instrument", instrument(t), "--sample", "lambert", "--tan-eps", "1", "--beta", "0",
                    "--variant", "scalar_rgb", cwd=t), must=("--variant", "scalar_rgb"), needs_mitsuba=True)
probe("render-variant-scalar-rgb", "extremes", "render",
      lambda t: sub("render", "--instrument", instrument(t), "--sample", "lambert", "--tan-eps", "1", "--beta", "0",
                    "--out", t / "r", "--variant", "scalar_rgb", cwd=t), must=("--variant", "scalar_rgb"),
      needs_mitsuba=True)
probe("stderr-one-line-distance-1e300", "extremes", "ka",
      lambda t: sub("ka", "--instrument", instrument(t, replace("distance_m = 5.0", "distance_m = 1e300")), "--sample",
                    "lambert", "--backend", "reference", "--tan-eps", "1", "--beta", "0", cwd=t),
      must=("source.distance_m",))
probe("stderr-one-line-focus-1e300", "extremes", "ka",
      lambda t: sub("ka", "--instrument", instrument(t, replace("field_half_angle_deg = 0.05",
                                                                "field_half_angle_deg = 0.05\nfocus_m = 1e300")),
                    "--sample", "lambert", "--backend", "quadrature", "--tan-eps", "1", "--beta", "0", cwd=t),
      must=("detector.focus_m",))
probe("correct-u-measured-1e-300", "extremes", "correct",
      lambda t: sub("correct", "--measured", "R3", "--instrument", instrument(t), "--u-measured", "1e-300",
                    "--backend", "quadrature", "--accuracy", "fast", "--no-plots",
                    "--out", t / "c", cwd=t), must=("--u-measured",))


def _quiet_finite_json(r, t):
    assert not r.err.strip(), f"stderr: {r.err[:300]}"
    no_float_junk(strict_json(r.out))


probe("road-table-times-1e-300", "extremes", "road",          # as a file: refused as r in sr^-1
      lambda t: sub("road", "--table", hand_table_file(t, "tiny", r3_values() * 1e-300), "--no-plots", "--json",
                    "--out", t / "o", cwd=t), must=("tiny.csv", "sr^-1"))
probe("road-array-times-1e-300", "extremes", "road",
      lambda t: api(lambda: road_api()(_dark_table(1e-300), plots=False)), expect="ok",
      check=lambda r, t: no_float_junk(r.value[0]))
probe("uncertainty-sigma-1e-300", "extremes", "uncertainty",
      lambda t: sub("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), "--sigma",
                    "alpha_deg=1e-300", "--no-aperture", "--trials", "200", "--no-plots", "--json", "--out", t / "u",
                    cwd=t), expect="ok", check=_quiet_finite_json)
probe("fit-tiny-values", "extremes", "fit",
      lambda t: cli("fit", hand_table_file(t, "tiny", r3_values() * 1e-290), "--json", "--no-plot", "--out", t / "f"),
      expect="either", must=("tiny.csv",),
      check=lambda r, t: _assert(strict_json(r.out)["max_dev_pct"] < 50, r.out[:300]))


# -- paths: output folders derived from names stay where they belong ---------------------------

def _in_cwd(action):
    def run(t):
        work = t / "work"
        work.mkdir()
        cwd = os.getcwd()
        os.chdir(work)
        try:
            return action(work)
        finally:
            os.chdir(cwd)

    def check(r, t):
        inside(t / "work")
        assert (t / "work" / "out").is_dir() or any((t / "work").glob("fit-*")), "no output folder"
    return run, check


EVIL = '[instrument]\nname = "../../escaped"\n' + GOOD
for _cmd, _args in (
        ("ka", lambda w: ("ka", "--instrument", instrument(w, EVIL), "--sample", "lambert", "--backend", "quadrature",
                          "--cells", "1:0")),
        ("uncertainty", lambda w: ("uncertainty", "--instrument", instrument(w, EVIL), "--sample", model_file(w),
                                   "--sigma", "alpha_deg=0.01", "--no-aperture", "--trials", "200", "--no-plots")),
        ("design", lambda w: ("design", "--instrument", instrument(w, EVIL), "--sample", model_file(w), "--vary",
                              "source.radius_m=0.005:0.005:1", "--cells", "1:0", "--backend", "quadrature",
                              "--workers", "0", "--no-plots")),
        ("validate", lambda w: ("validate", "--instrument", instrument(w, EVIL), "--sample", model_file(w), "--against",
                                "numpy-mc", "--reference", "quadrature", "--cells", "1:0", "--rel-se", "0.05")),
        ("fit", lambda w: ("fit", rtb_named(w, "../../escaped"), "--no-plot")),
        ("compare", lambda w: ("compare", rtb_named(w, "../../a"), rtb_named(w, "/tmp/b", "b.rtb"), "--no-plots")),
        ("road", lambda w: ("road", "--table", rtb_named(w, "../../a"), "--no-plots")),
        ("correct", lambda w: ("correct", "--measured", rtb_named(w, "../../a"), rtb_named(w, "../../b", "b.rtb"),
                               "--instrument", instrument(w), "--reference", "R3", "--alternatives", "none",
                               "--backend", "quadrature", "--accuracy", "fast", "--no-plots"))):
    _r, _k = _in_cwd((lambda f: lambda w: cli(*f(w)))(_args))
    probe(f"name-escapes-{_cmd}", "paths", _cmd, _r, expect="ok", check=_k,
          ok_codes=(0, 1, 3) if _cmd == "validate" else (0,))


# -- conventions: the rectangle's x runs along the observation azimuth --------------------------

D90 = replace("alpha_deg = 1.0", "alpha_deg = 1.0\ndelta_deg = 90")


def _rotated(backend: str, delta: float = 90.0):
    text = replace("alpha_deg = 1.0", f"alpha_deg = 1.0\ndelta_deg = {delta:g}")

    def action(t):
        import roadgonio as rg
        seed = {} if backend == "quadrature" else {"seed": 3}
        return api(lambda: rg.ka_cell(str(instrument(t, text, "rot.toml")), str(model_file(t)), 1, 0,
                                      backend=backend, rel_se=3e-3, **seed))

    def check(r, t):
        # the whole instrument turned about the vertical: the same k_A (the BRDF depends on the
        # relative azimuth only), computed at delta = 0 by the deterministic quadrature
        k0, bound = quadrature_ka(GOOD, t)
        c = r.value
        tol = bound + (c.error_bound if math.isfinite(c.error_bound) else 0.0) + 5 * (c.se if math.isfinite(c.se) else 0)
        assert abs(c.k_a - k0) <= tol + 1e-12, f"delta {delta}: {c.k_a} vs {k0} at delta 0"
    return action, check


for _backend, _delta, _mi in (("quadrature", 90.0, False), ("quadrature", -135.0, False), ("reference", 90.0, False),
                              ("numpy-mc-mesh", 90.0, False), ("mitsuba", 90.0, True)):
    _a, _c = _rotated(_backend, _delta)
    probe(f"delta-{_delta:g}-{_backend}", "conventions", "api" if not _mi else "ka", _a, expect="ok", check=_c,
          needs_mitsuba=_mi)
probe("delta-90-design-feasible", "conventions", "design",
      lambda t: cli("design", "--instrument", instrument(t, D90), "--sample", model_file(t), "--vary",
                    "source.radius_m=0.005:0.005:1", "--cells", "1:0", "--backend", "quadrature", "--workers", "0",
                    "--no-plots", "--json", "--out", t / "d"), expect="ok",
      check=lambda r, t: _assert(strict_json(r.out)["feasible"] == 1, r.out[:400]))


# -- overwrites: a folder holding a different run's results is not silently replaced ----------

def _twice(first, second, fresh=None):
    def action(t):
        r1 = cli(*first(t))
        if r1.rc != 0:
            return r1
        return cli(*second(t)) if fresh is None else cli(*second(t), fresh)
    return action


probe("fit-out-different-table", "overwrites", "fit",
      _twice(lambda t: ("fit", "R3", "--no-plot", "--out", t / "F"), lambda t: ("fit", "C1", "--no-plot", "--out", t / "F")),
      must=("model.json", "--fresh"))
probe("fit-out-different-table-fresh", "overwrites", "fit",
      _twice(lambda t: ("fit", "R3", "--no-plot", "--out", t / "F"), lambda t: ("fit", "C1", "--no-plot", "--out", t / "F"),
             "--fresh"), expect="ok",
      check=lambda r, t: _assert(json.loads((t / "F" / "model.json").read_text())["name"] == "C1", "not C1"))
probe("fit-out-same-again", "overwrites", "fit",
      _twice(lambda t: ("fit", "R3", "--no-plot", "--out", t / "F"), lambda t: ("fit", "R3", "--no-plot", "--out", t / "F")),
      expect="ok")
_U = ("--sigma", "alpha_deg=0.01", "--no-aperture", "--trials", "500", "--no-plots")
probe("uncertainty-out-different-seed", "overwrites", "uncertainty",
      _twice(lambda t: ("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), *_U, "--out", t / "U"),
             lambda t: ("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), *_U, "--seed", "2",
                        "--out", t / "U")), must=("uncertainty.json", "--fresh"))
probe("uncertainty-out-different-seed-fresh", "overwrites", "uncertainty",
      _twice(lambda t: ("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), *_U, "--out", t / "U"),
             lambda t: ("uncertainty", "--instrument", instrument(t), "--sample", model_file(t), *_U, "--seed", "2",
                        "--out", t / "U"), "--fresh"), expect="ok",
      check=lambda r, t: _assert(json.loads((t / "U" / "uncertainty.json").read_text())["seed"] == 2, "not seed 2"))
probe("ka-out-different-sample", "overwrites", "ka",
      _twice(lambda t: ("ka", "--instrument", instrument(t), "--sample", "lambert", "--backend", "quadrature",
                        "--cells", "1:0", "--out", t / "K"),
             lambda t: ("ka", "--instrument", instrument(t), "--sample", model_file(t), "--backend", "quadrature",
                        "--cells", "1:0", "--out", t / "K")), must=("--fresh",))


def _api_fit_twice(t):
    import roadgonio as rg
    rg.fit("R3", out=t / "F", plot=False)
    return api(lambda: rg.fit("C2", out=t / "F", plot=False))


probe("api-fit-out-different", "overwrites", "api", _api_fit_twice, must=("model.json", "fresh"))


# ----------------------------------------------------------------------------------------------

def _params():
    out = []
    for p in PROBES:
        marks = [pytest.mark.slow] if p.slow else []
        out.append(pytest.param(p, id=f"{p.cls}:{p.command}:{p.pid}", marks=marks))
    return out


#: Fits made by the probes of this module, by what determines them (fit_table is reproducible for a
#: seed: tests/unit/test_fit.py), so that R3, fitted by five probes before their second command, is
#: fitted once: each probe checks what a command does around the fit (folders, names, messages), not
#: the fit (~9 s each; the fit probes took 75 s, now ~25 s)
_FITS: dict[tuple, Any] = {}


@pytest.fixture(autouse=True)
def _one_fit_per_table(monkeypatch):
    import roadgonio.surface.fit as fitmod
    real = fitmod.fit_table

    def fit_table(table, variant=fitmod.DEFAULT_VARIANT, *, seed=0, fixed=None, progress=None, **kw):
        key = (fitmod.table_hash(table), table.name, variant, seed, tuple(sorted((fixed or {}).items())),
               tuple(sorted(kw.items())))
        if key not in _FITS:
            _FITS[key] = real(table, variant, seed=seed, fixed=fixed, progress=progress, **kw)
        elif progress is not None:
            progress(1, 1)
        return _FITS[key]
    monkeypatch.setattr(fitmod, "fit_table", fit_table)


@pytest.mark.parametrize("p", _params())
def test_probe(p: Probe, tmp_path, monkeypatch, request):
    if p.needs_mitsuba:
        request.getfixturevalue("mi")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("ROADGONIO_CACHE", str(tmp_path.parent / "fit-cache"))
    work = tmp_path / "p"
    work.mkdir()
    import inspect
    try:
        res = p.action(work, monkeypatch) if len(inspect.signature(p.action).parameters) == 2 else p.action(work)
    except BaseException as ex:      # a timeout (pytest-timeout) or a probe's own failure: still recorded
        record(p, "traceback", f"the probe did not end: {type(ex).__name__}: {ex}")
        raise
    verdict, why = judge(p, res, work)
    record(p, verdict, why)
    assert verdict == "OK", f"{verdict}: {why}"


def test_every_class_and_command_is_probed():
    assert {p.cls for p in PROBES} == set(CLASSES)
    assert {p.command for p in PROBES} == set(COMMANDS)
    assert len({p.pid for p in PROBES}) == len(PROBES), "probe ids repeat"


def tally(path: str) -> str:
    """The table of verdicts per class from a ROADGONIO_PROBE_TALLY file."""
    last = {}
    for ln in Path(path).read_text().splitlines():
        if ln.strip():
            row = json.loads(ln)
            last[row["probe"]] = row            # a probe run again: its last verdict
    rows = list(last.values())
    verdicts = ("OK", "silent-wrong", "traceback", "misleading")
    lines = [f"{'class':12} " + " ".join(f"{v:>12}" for v in verdicts) + f" {'total':>6}"]
    for c in CLASSES:
        mine = [r for r in rows if r["class"] == c]
        lines.append(f"{c:12} " + " ".join(f"{sum(r['verdict'] == v for r in mine):12d}" for v in verdicts)
                     + f" {len(mine):6d}")
    lines.append(f"{'all':12} " + " ".join(f"{sum(r['verdict'] == v for r in rows):12d}" for v in verdicts)
                 + f" {len(rows):6d}")
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover
    print(tally(sys.argv[1]))
