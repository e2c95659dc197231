"""roadgonio/fileio.py: a command's outputs appear together or not at all, and replace the earlier
run's outputs of the same command (mutation audit 10: not removing the earlier run's files, and not
taking back the files already moved when a later rename fails, passed every unit test); and the
numbers CSV reader (roadgonio/instrument/profiles.py) refuses a text line among the numbers (read
as a second header it was skipped)."""
from __future__ import annotations

import os

import pytest

from roadgonio import fileio
from roadgonio.errors import InputError
from roadgonio.fileio import OutputGroup
from roadgonio.instrument.profiles import read_numbers_csv


def test_an_earlier_runs_outputs_not_written_again_are_removed(tmp_path):
    out = tmp_path / "o"
    with OutputGroup(out, replaces=("a.txt", "b.png", "c.csv")) as g:
        g.text("a.txt", "1")
        g.text("b.png", "old picture")
    (out / "mine.txt").write_text("the user's")
    with OutputGroup(out, replaces=("a.txt", "b.png", "c.csv")) as g:
        g.text("a.txt", "2")
        g.text("c.csv", "3")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "c.csv", "mine.txt"]
    assert (out / "a.txt").read_text() == "2"


def test_a_run_that_fails_removes_and_replaces_nothing(tmp_path):
    out = tmp_path / "o"
    with OutputGroup(out, replaces=("a.txt", "b.txt")) as g:
        g.text("a.txt", "1")
        g.text("b.txt", "1")
    with pytest.raises(RuntimeError):
        with OutputGroup(out, replaces=("a.txt", "b.txt")) as g:
            g.text("a.txt", "2")
            raise RuntimeError("the command failed")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "b.txt"]
    assert (out / "a.txt").read_text() == "1"


def test_a_failed_rename_takes_back_the_files_already_moved(tmp_path, monkeypatch):
    """The second of three renames fails (a full or vanished folder): the first file, already in
    place, is removed again, so no partial set is left; the error names the file that failed."""
    out = tmp_path / "o"
    out.mkdir()
    real = os.replace
    calls = []

    def flaky(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise OSError(28, "No space left on device", str(src))
        return real(src, dst)

    monkeypatch.setattr(fileio.os, "replace", flaky)
    with pytest.raises(InputError) as err:
        with OutputGroup(out) as g:
            for name in ("a.txt", "b.txt", "c.txt"):
                g.text(name, name)
    assert "b.txt" in str(err.value) and "No space left" in str(err.value)
    assert list(out.iterdir()) == []


@pytest.mark.parametrize("failing_call", [2, 4, 5])
def test_a_failed_rename_keeps_the_earlier_runs_outputs_whole(tmp_path, monkeypatch, failing_call):
    """With an earlier run's files in place, a rename that fails half-way (setting aside the earlier
    b.txt, moving the new one in, or setting aside a file of ``replaces``) leaves exactly the earlier
    run's files with their contents (the user audit of session 19: the rollback deleted the new files,
    which had already overwritten the old ones, so both runs' results were lost)."""
    out = tmp_path / "o"
    names = ("a.txt", "b.txt")
    with OutputGroup(out, replaces=names + ("old.png",)) as g:
        for name in names:
            g.text(name, f"old {name}")
        g.text("old.png", "old picture")
    real = os.replace
    calls = []

    def flaky(src, dst):
        calls.append(dst)
        if len(calls) == failing_call:
            raise OSError(28, "No space left on device", str(src))
        return real(src, dst)

    monkeypatch.setattr(fileio.os, "replace", flaky)
    with pytest.raises(InputError, match="No space left"):
        with OutputGroup(out, replaces=names + ("old.png",)) as g:
            for name in names:
                g.text(name, f"new {name}")
    monkeypatch.setattr(fileio.os, "replace", real)
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "b.txt", "old.png"]
    assert all((out / n).read_text() == f"old {n}" for n in names)
    assert (out / "old.png").read_text() == "old picture"


def test_a_folder_where_an_output_belongs_is_an_error_before_anything_moves(tmp_path):
    out = tmp_path / "o"
    with OutputGroup(out, replaces=("a.txt", "b.png")) as g:
        g.text("a.txt", "old")
        g.text("b.png", "old picture")
    (out / "b.png").unlink()
    (out / "b.png").mkdir()
    (out / "b.png" / "the user's.txt").write_text("keep me")
    with pytest.raises(InputError, match="b.png"):
        with OutputGroup(out, replaces=("a.txt", "b.png")) as g:
            g.text("a.txt", "new")
            g.text("b.png", "new picture")
    assert (out / "a.txt").read_text() == "old"
    assert (out / "b.png" / "the user's.txt").read_text() == "keep me"


def test_a_text_line_among_the_numbers_is_an_error(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("0,1\n5,0.8\nten,0.5\n10,0.5\n")
    with pytest.raises(InputError) as err:
        read_numbers_csv(p, "source.beam_intensity_file")
    assert err.value.line == 3 and "ten,0.5" in str(err.value)
    p.write_text("theta_deg,I\n0,1\n5,0.8\nangle,I\n10,0.5\n")       # a second header is no header
    with pytest.raises(InputError) as err:
        read_numbers_csv(p, "source.beam_intensity_file", header=("theta_deg", "I"))
    assert err.value.line == 4


_KILLED_WRITER = """
import os, signal, sys
from roadgonio.fileio import OutputGroup, atomic_write_text
out = sys.argv[1]
atomic_write_text(os.path.join(out, "journal.jsonl"), "kept")     # complete: renamed into place
g = OutputGroup(out, replaces=("a.txt", "b.txt")).__enter__()
g.text("a.txt", "new a")
os.replace(os.path.join(out, "b.txt"), g.stage / ".roadgonio-tmp-previous-b.txt")   # set aside, as __exit__ does
open(os.path.join(out, ".roadgonio-tmp-%d@x-0123456789ab-c.txt" % os.getpid()), "w").close()  # another host's form
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_killed_runs_staging_folder_goes_with_the_next_run(tmp_path):
    """A SIGKILL leaves its staging folder (user audit, session 42: half an output set stayed hidden in
    --out beside the rerun's complete one): the next group in that folder removes it and puts back the
    earlier output the killed run had set aside; a running process's staging folder stays."""
    import subprocess
    import sys
    out = tmp_path / "o"
    with OutputGroup(out, replaces=("a.txt", "b.txt")) as g:
        g.text("a.txt", "old a")
        g.text("b.txt", "old b")
    p = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(out)], capture_output=True, text=True)
    assert p.returncode == -9, p.stderr
    stale = [e.name for e in out.iterdir() if e.name.startswith(fileio.TMP_PREFIX)]
    assert any(e.is_dir() for e in out.iterdir() if e.name.startswith(fileio.TMP_PREFIX)), stale
    assert not (out / "b.txt").exists()
    # a live process's staging folder (this one's parent) and another host's file are not touched
    live = out / f"{fileio.TMP_PREFIX}{os.getppid()}@{fileio._host()}-abcdefabcdef"
    live.mkdir()
    with OutputGroup(out, replaces=("a.txt",)) as g:
        g.text("a.txt", "newest a")
    names = sorted(e.name for e in out.iterdir())
    other_host = [n for n in names if n.endswith("@x-0123456789ab-c.txt")]
    assert names == sorted(["a.txt", "b.txt", "journal.jsonl", live.name] + other_host) and len(other_host) == 1
    assert (out / "b.txt").read_text() == "old b" and (out / "a.txt").read_text() == "newest a"
