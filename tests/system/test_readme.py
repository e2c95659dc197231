"""The README's Python API example runs as printed (it is extracted from README.md, not copied)."""
from __future__ import annotations

import re
from pathlib import Path
from tolerances import N_SIGMA



README = Path(__file__).resolve().parents[2] / "README.md"


def python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_readme_python_api_example_runs(mi, tmp_path, monkeypatch, capsys):
    section = README.read_text(encoding="utf-8").split("## Python API", 1)[1].split("\n## ", 1)[0]
    blocks = python_blocks(section)
    assert len(blocks) == 1 and "import roadgonio as rg" in blocks[0]
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[0], str(README) + " (Python API example)", "exec"), {"__name__": "__readme__"})
    out = capsys.readouterr().out
    k_quad, bound = (float(v) for v in re.search(r"k_A\(12, 0\) = ([0-9.]+) \+- ([0-9.e-]+)", out).groups())
    k_mi, se = (float(v) for v in re.search(r"Mitsuba: ([0-9.]+) \+- ([0-9.e-]+)", out).groups())
    assert 0.5 < k_quad < 1.0                          # the portable preset's specular deficit at grazing
    assert abs(k_mi - k_quad) <= N_SIGMA * se + bound + 1e-4   # the engines agree (N_SIGMA SE + bound + printed digits)
    assert (tmp_path / "R3_corrected.csv").exists()


def test_docs_the_help_points_to_exist():
    """--help and the README point at docs/conventions.md: it exists and has its sections."""
    from roadgonio.cli import build_parser
    page = README.parent / "docs" / "conventions.md"
    text = page.read_text(encoding="utf-8")
    for heading in ("## 1. Frame and angles", "## 2. Quantities", "## 3. The road BRDF model", "## 4. The instrument",
                    "## 5. The aperture-effect factor k_A"):
        assert heading in text
    assert "diameter" not in text and "docs/conventions.md" in build_parser().format_help()
    assert "DESIGN.md" not in README.read_text(encoding="utf-8")
