"""The README runs as printed: its Python API example, and every shell command of its code blocks
(extracted from README.md, not copied), in a temporary folder with ``roadgonio`` from this Python's
environment; the commands of docs/*.md at least parse."""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path
from tolerances import N_SIGMA

import pytest



ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOCS = ROOT / "docs"

#: Lines of the README's shell blocks that set up a clone rather than use roadgonio: not run here
#: (the set-up installs packages, the test command is this suite).
SETUP = ("git clone ", "cd ", "bash scripts/example.sh", "python3 -m pytest")   # prefixes: "... -n 2" too
#: Files the README's comments name (``# dir/a.csv, b.png``: b.png is in dir/ too).
FILE = re.compile(r"[\w./-]+\.(?:csv|png|json|jsonl|rtb|nc|toml|exr)\b")
#: A duration in a printed line (``0.1 s``), which the README cannot promise.
SECONDS = re.compile(r"\b\d+(?:\.\d+)? s\b")


def python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def fenced_blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of every fenced block, in order."""
    return re.findall(r"```(\w*)\n(.*?)```", text, flags=re.S)


def _split_comment(line: str) -> tuple[str, str]:
    """(code, comment) at the first ``#`` outside quotes that starts a word."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i], line[i + 1:]
    return line, ""


def shell_commands(block: str) -> list[tuple[str, str]]:
    """(command, comment) per command of a shell block: continuation lines joined, a comment-only
    line belongs to the command before it."""
    cmds: list[list[str]] = []
    open_cmd = False
    for raw in block.splitlines():
        code, comment = _split_comment(raw)
        code = code.rstrip()
        cont = code.endswith("\\")
        code = code[:-1].strip() if cont else code.strip()
        if not code and not open_cmd:
            if comment.strip() and cmds:
                cmds[-1][1] += " " + comment.strip()
            continue
        if open_cmd:
            cmds[-1][0] += " " + code
            cmds[-1][1] += " " + comment.strip()
        else:
            cmds.append([code, comment.strip()])
        open_cmd = cont
    return [(c, m.strip()) for c, m in cmds if c]


def named_files(argv: list[str], comment: str) -> list[str]:
    """The files a command's comment says it writes: a name with a folder is relative to the run
    folder and sets the folder of the bare names after it; the first folder is ``--out``."""
    folder = argv[argv.index("--out") + 1] if "--out" in argv else ""
    files = []
    for name in FILE.findall(comment):
        if "/" in name:
            folder = str(Path(name).parent)
            files.append(name)
        else:
            files.append(str(Path(folder) / name) if folder else name)
    return files


def readme_runs() -> list[tuple[list[tuple[str, str]], list[str]]]:
    """Per shell block of the README: its roadgonio commands (setup lines left out) and the lines
    of the text block that follows it, if any (what those commands print)."""
    blocks = fenced_blocks(README.read_text(encoding="utf-8"))
    runs = []
    for i, (lang, body) in enumerate(blocks):
        if lang != "bash":
            continue
        cmds = [(c, m) for c, m in shell_commands(body) if not c.startswith(SETUP)]
        expected = blocks[i + 1][1].splitlines() if i + 1 < len(blocks) and blocks[i + 1][0] == "text" else []
        if cmds:
            runs.append((cmds, expected))
    return runs


RUNS = readme_runs()


def _roadgonio() -> list[str]:
    exe = Path(sys.executable).with_name("roadgonio")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "roadgonio"]


@pytest.fixture(scope="module")
def fit_cache(tmp_path_factory):
    """One fit cache for the README's runs (R3 is fitted once, not once per block)."""
    return tmp_path_factory.mktemp("fit-cache")


def test_readme_shows_commands_to_run():
    """The extraction finds what the README shows: the worked example and the sessions, every
    command a roadgonio command (the test must not skip what it does not understand)."""
    assert len(RUNS) >= 3
    for cmds, _ in RUNS:
        for cmd, _ in cmds:
            assert cmd.split()[0] == "roadgonio", f"README shows a command the test does not run: {cmd}"
    example = (ROOT / "scripts" / "example.sh").read_text(encoding="utf-8")
    job = re.search(r"^(roadgonio ka .*?)\s*\"\$@\"$", example, flags=re.M).group(1)
    assert any(cmd == job for cmds, _ in RUNS for cmd, _ in cmds), "the worked example is not example.sh's job"


@pytest.mark.parametrize("cmds, expected", RUNS, ids=[f"block{i + 1}" for i in range(len(RUNS))])
def test_readme_shell_commands_run(cmds, expected, tmp_path, fit_cache):
    """Each README shell block, in a fresh folder (with the clone's scenes/, as after cloning):
    every command exits 0 and writes the files its comment names; a text block after the shell
    block is what it prints, durations aside."""
    (tmp_path / "scenes").symlink_to(ROOT / "scenes", target_is_directory=True)
    env = dict(os.environ, ROADGONIO_CACHE=str(fit_cache), MPLBACKEND="Agg")
    printed = []
    for cmd, comment in cmds:
        argv = shlex.split(cmd)
        r = subprocess.run(_roadgonio() + argv[1:], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, f"{cmd}\nexit {r.returncode}\n{r.stdout}\n{r.stderr}"
        for name in named_files(argv, comment):
            assert (tmp_path / name).is_file(), f"{cmd}: the README says it writes {name}; not found"
        printed += r.stdout.splitlines()
    got = {SECONDS.sub("<t> s", line.rstrip()) for line in printed}
    for line in expected:
        assert SECONDS.sub("<t> s", line.rstrip()) in got, f"the README shows {line!r}; printed:\n" + "\n".join(printed)


def test_readme_python_api_example_runs(tmp_path, monkeypatch, capsys):
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
    header = (tmp_path / "R3_corrected.csv").read_text().splitlines()[0]
    assert "divided by k_A" in header and "fglichttechnik" not in header, header   # trial 11 D11: not CIE R3's
    shown = re.search(r"```python\n.*?```\s*It prints\s*```text\n(.*?)```", section, flags=re.S).group(1)
    assert out.splitlines() == shown.splitlines()       # the README shows what it prints (same seeds, same numbers)


def test_docs_commands_parse():
    """Every roadgonio command shown in README.md and docs/*.md is accepted by the command line's
    parser (options and choices as they are now); the README's are also run, above."""
    from roadgonio.cli import build_parser
    pages = [README, *sorted(DOCS.glob("*.md"))]
    seen = 0
    for page in pages:
        for lang, body in fenced_blocks(page.read_text(encoding="utf-8")):
            if lang != "bash":
                continue
            for cmd, _ in shell_commands(body):
                argv = shlex.split(cmd.rstrip("&").strip())
                if argv[0] != "roadgonio":
                    continue
                try:
                    build_parser().parse_args(argv[1:])
                except SystemExit as e:
                    pytest.fail(f"{page.name}: `{cmd}` does not parse (exit {e.code})")
                seen += 1
    assert seen >= 15


def test_docs_the_help_points_to_exist():
    """--help and the README point at docs/conventions.md: it exists and has its sections; the
    README's links to docs/ pages resolve."""
    from roadgonio.cli import build_parser
    page = README.parent / "docs" / "conventions.md"
    text = page.read_text(encoding="utf-8")
    for heading in ("## 1. Frame and angles", "## 2. Quantities", "## 3. The road BRDF model", "## 4. The instrument",
                    "## 5. The aperture-effect factor k_A"):
        assert heading in text
    assert "diameter" not in text and "docs/conventions.md" in build_parser().format_help()
    readme = README.read_text(encoding="utf-8")
    assert "DESIGN.md" not in readme
    for page in [README, *DOCS.glob("*.md")]:
        for link in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", page.read_text(encoding="utf-8")):
            assert (page.parent / link).exists(), f"{page.name} links to {link}, which does not exist"
