"""Atomic file output and small I/O helpers.

* One file: :func:`atomic_write` writes to a temporary file in the destination folder and renames it
  into place, so an interrupted run never leaves a half-written result behind; a stop at once (a
  second Ctrl-C during a Mitsuba pass, :func:`roadgonio.interrupts.critical`) waits for it to end,
  so it leaves no temporary file either.
* Several files of one command: :class:`OutputGroup` writes them all into a hidden staging folder
  inside the destination and moves them into place only when every one was written, so a command's
  outputs appear together or not at all (a full disk or a failing plot leaves the folder as it was).
* A run killed outright (SIGKILL, a power cut) cannot clean up: its temporary files and staging
  folder carry the process id and host that made them, and the next :class:`OutputGroup` in that
  folder removes those of processes of this host that no longer run (:func:`remove_stale`), after
  putting back an earlier output the killed run had set aside and not replaced.
* Files get the permissions of any file the user creates (``0666`` less the umask, typically
  ``0644``), not the ``0600`` of :func:`tempfile.mkstemp`.
* Every ``OSError`` on an output (read-only folder, missing or unwritable parent, ``/proc``, disk
  full) becomes an :class:`~roadgonio.errors.InputError` naming the file: one line, exit status 2.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import re
import secrets
import shutil
import socket
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from roadgonio.errors import InputError
from roadgonio.interrupts import critical

#: Prefix of temporary files and staging folders (hidden; removed on success and on errors).
TMP_PREFIX = ".roadgonio-tmp-"
#: The name of one temporary file or staging folder: the prefix, ``<pid>@<host>-<12 hex>``, and for a
#: file ``-<its final name>``; set-aside earlier outputs inside a staging folder are ``previous-<name>``
_TMP_NAME = re.compile(re.escape(TMP_PREFIX) + r"(\d+)@([A-Za-z0-9.]*)-[0-9a-f]{12}(?:-.+)?$")


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9.]", "", socket.gethostname())[:40]


def _tmp_token() -> str:
    """``<pid>@<host>-<12 hex>``: whose temporary file it is (:func:`remove_stale`) and a unique part."""
    return f"{os.getpid()}@{_host()}-{secrets.token_hex(6)}"


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:        # another user's process (EPERM): it runs
        return True
    return True


def remove_stale(folder: str | Path) -> list[str]:
    """Remove the temporary files and staging folders in ``folder`` left by a roadgonio process of this
    host that no longer runs (one killed outright; user audit, session 42: a SIGKILL during the writing
    left ``.roadgonio-tmp-.../`` with half an output set beside the next run's complete one). An earlier
    output the killed run had set aside (``previous-<name>``) and not replaced goes back in place. Those
    of running processes, of other hosts and of names of another form stay. Returns the names removed."""
    folder = Path(folder)
    removed: list[str] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    host = _host()
    for e in entries:
        m = _TMP_NAME.match(e.name)
        if m is None or m.group(2) != host or _running(int(m.group(1))):
            continue
        path = Path(e.path)
        try:
            if path.is_dir() and not path.is_symlink():
                for kept in path.glob(f"{TMP_PREFIX}previous-*"):
                    dest = folder / kept.name[len(f"{TMP_PREFIX}previous-"):]
                    if not (dest.exists() or dest.is_symlink()):
                        os.replace(kept, dest)
                shutil.rmtree(path)
            else:
                path.unlink()
            removed.append(e.name)
        except OSError:  # pragma: no cover - best effort
            pass
    return removed

#: How a journal or results folder of another run (:data:`FRESH_HINT`), or one that cannot be read
#: (:data:`MOVE_HINT`), is to be dealt with, for the commands that have --fresh; ``correct`` has none
#: and says the hint of :data:`NO_FRESH_HINTS` instead (:func:`without_fresh`)
FRESH_HINT = "use another --out folder, or --fresh to discard it"
MOVE_HINT = "move the folder away or use --fresh"
NO_FRESH_HINTS = {FRESH_HINT: "use another --out folder, or remove this one", MOVE_HINT: "move the folder away"}


def without_fresh(err: InputError) -> InputError:
    """``err`` with its --fresh hint replaced by :data:`NO_FRESH_HINTS`, for a command without --fresh
    (audit 21: correct said to use --fresh, which it does not have)."""
    reason = err.reason
    for hint, instead in NO_FRESH_HINTS.items():
        reason = reason.replace(hint, instead)
    if reason == err.reason:
        return err
    return InputError(reason, path=err.path, line=err.line, field=err.field, argument=err.argument)


def output_error(path: str | Path, err: OSError) -> InputError:
    """The one-line error of a failed output: the file, and the system's reason."""
    reason = err.strerror or str(err)
    return InputError(f"cannot write this output file ({reason})", path=path)


def _make_dir(folder: Path, target: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        # a file where a folder of the path belongs: say which (user audit, session 44: "File exists")
        blocker = next((p for p in (folder, *folder.parents) if p.exists() and not p.is_dir()), None)
        if blocker is not None:
            raise InputError(f"cannot write this output file: {blocker} is a file, not a folder", path=target) from None
        raise output_error(target, err) from None
    if not folder.is_dir():
        raise InputError("cannot write this output file (its folder is not a directory)", path=target)


def _create(path: Path) -> int:
    """A new file at ``path`` opened for writing, with mode 0666 less the umask (like ``open``)."""
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)


def atomic_write(path: str | Path, writer: Callable[[Path], None]) -> Path:
    """Call ``writer(tmp_path)`` then rename ``tmp_path`` to ``path`` atomically. The folder is
    created if needed; an ``OSError`` becomes an :class:`InputError` naming ``path``."""
    path = Path(path)
    _make_dir(path.parent, path)
    tmp_path = path.parent / f"{TMP_PREFIX}{_tmp_token()}-{path.name}"
    with critical():
        try:
            os.close(_create(tmp_path))
            writer(tmp_path)
            os.replace(tmp_path, path)
        except OSError as err:
            raise output_error(path, err) from None
        finally:
            try:
                if tmp_path.exists():
                    tmp_path.unlink()
            except OSError:  # pragma: no cover - best effort
                pass
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


class OutputGroup:
    """The output files of one command, written together or not at all.

    .. code-block:: python

        with OutputGroup(out_dir) as out:
            out.text("a.csv", text)
            out.json("a.json", doc)
            table.write_csv(out.path("b.csv"))     # any writer, into the staging folder
            out.figure("a.png", lambda p: fig.savefig(p))

    Inside the block every file goes to a hidden staging folder in ``out_dir``; when the block ends
    without an error they are renamed into ``out_dir`` (same file system: each rename is atomic and
    allocates nothing, so a full disk fails before any output appears). On an error the staging
    folder is removed and ``out_dir`` keeps what it had, also when a rename fails half-way (the files
    an earlier run left are set aside in the staging folder before each rename and put back on a
    failure; a folder where an output file belongs is an error before anything moves). An
    ``OSError`` is re-raised as an
    :class:`InputError` naming the output file it concerns.
    """

    def __init__(self, out_dir: str | Path, *, replaces: Sequence[str] = ()):
        self.out_dir = Path(out_dir)
        self.stage: Path | None = None
        self.names: list[str] = []
        #: the command's own output names: those this group did not write are removed once the new
        #: files are in place (an earlier run's file, e.g. a picture not asked for this time, never
        #: stays beside the new ones; and nothing is removed by a run that fails)
        self.replaces = tuple(replaces)

    def __enter__(self) -> "OutputGroup":
        _make_dir(self.out_dir, self.out_dir)
        remove_stale(self.out_dir)
        stage = self.out_dir / f"{TMP_PREFIX}{_tmp_token()}"
        try:
            stage.mkdir()
        except OSError as err:
            raise output_error(self.out_dir, err) from None
        self.stage = stage
        return self

    def path(self, name: str) -> Path:
        """Where to write output ``name`` now (in the staging folder)."""
        if self.stage is None:
            raise RuntimeError("OutputGroup.path() outside its with-block")
        if Path(name).name != name or name.startswith("."):
            raise ValueError(f"output names are plain file names, got {name!r}")
        if name not in self.names:
            self.names.append(name)
        return self.stage / name

    def text(self, name: str, text: str) -> Path:
        p = self.path(name)
        p.write_text(text, encoding="utf-8")
        return self.out_dir / name

    def json(self, name: str, obj: Any) -> Path:
        return self.text(name, to_json(obj) + "\n")

    def figure(self, name: str, save: Callable[[Path], Any]) -> Path:
        save(self.path(name))
        return self.out_dir / name

    def _final_of(self, filename: str | None, stage: Path | None) -> Path:
        """The output file an OSError concerns (its staging path mapped to the destination)."""
        if filename and stage is not None:
            f = Path(filename)
            if f.parent == stage:
                return self.out_dir / f.name
        return self.out_dir

    def __exit__(self, exc_type, exc, tb) -> bool:
        stage, self.stage = self.stage, None
        try:
            if exc_type is None:
                moved: list[Path] = []
                kept: list[tuple[Path, Path]] = []    # (destination, the earlier file set aside in the stage)
                try:
                    for name in self.names:
                        src = stage / name
                        if not src.exists():
                            raise InputError("the command did not write this output file", path=self.out_dir / name)
                        dest = self.out_dir / name
                        if dest.is_dir() and not dest.is_symlink():
                            raise output_error(dest, IsADirectoryError(21, "Is a directory", str(dest)))
                        with open(src, "rb") as fh:     # on disk before any rename
                            os.fsync(fh.fileno())

                    def set_aside(dest: Path) -> None:
                        if dest.exists() or dest.is_symlink():
                            keep = stage / f"{TMP_PREFIX}previous-{dest.name}"
                            os.replace(dest, keep)
                            kept.append((dest, keep))
                    for name in self.names:
                        set_aside(self.out_dir / name)
                        os.replace(stage / name, self.out_dir / name)
                        moved.append(self.out_dir / name)
                    for name in self.replaces:
                        if name not in self.names:
                            set_aside(self.out_dir / name)
                except OSError as err:
                    # not a partial set: take back what was already moved, and put the earlier
                    # files back where they were (an earlier run's results are never lost)
                    for p in moved:
                        try:
                            p.unlink()
                        except OSError:  # pragma: no cover
                            pass
                    for dest, keep in reversed(kept):
                        try:
                            os.replace(keep, dest)
                        except OSError:  # pragma: no cover
                            pass
                    raise output_error(self._final_of(getattr(err, "filename", None), stage), err) from None
                return False
            if isinstance(exc, OSError):
                raise output_error(self._final_of(getattr(exc, "filename", None), stage), exc) from None
            return False
        finally:
            if stage is not None:
                shutil.rmtree(stage, ignore_errors=True)


def read_journal(path: str | Path, fingerprint: str, *, different: str,
                 record: Callable[[dict], tuple[Any, Any]]) -> dict[Any, Any]:
    """The finished records of a resumable run's journal (JSON lines: a header with the run's
    ``fingerprint``, then one record per line), as ``{key: value}`` from ``record(line_dict)``.

    A missing or empty journal gives ``{}``, and so does one of another run that finished nothing
    (its header alone). A last line cut short by an interruption is dropped (its work is done
    again); any other bad line, an unreadable file, or a header of another run with finished records
    (``different`` says what differs) is the one-line :class:`InputError` naming the journal.
    ``record`` raises KeyError, TypeError or ValueError on a line that is not a record."""
    path = Path(path)
    done: dict[Any, Any] = {}
    if not path.exists():
        return done
    try:
        with path.open(encoding="utf-8") as f:
            lines = f.read().splitlines()
    except OSError as err:
        raise InputError(f"cannot read this journal ({err.strerror or err}); {MOVE_HINT}",
                         path=path) from None
    except UnicodeDecodeError:
        raise InputError(f"this journal is not a text file; {MOVE_HINT}", path=path) from None
    if not lines:
        return done
    try:
        head = json.loads(lines[0])
    except json.JSONDecodeError:
        raise InputError(f"the journal's first line is not valid JSON; {MOVE_HINT}",
                         path=path, line=1) from None
    if not isinstance(head, dict) or head.get("fingerprint") != fingerprint:
        if not any(line.strip() for line in lines[1:]):
            # nothing finished: nothing to lose (audit 28: a run refused before its first task, e.g. by
            # an unreachable scheduler, left its header, and the next run was refused for it)
            return done
        raise InputError(f"this folder holds {different}; {FRESH_HINT}", path=path, line=1)
    for k, line in enumerate(lines[1:], start=2):
        try:
            key, value = record(json.loads(line))
        except (KeyError, TypeError, ValueError):         # json.JSONDecodeError is a ValueError
            if k == len(lines):     # cut short by an interruption: that work is done again
                break
            raise InputError(f"corrupt journal line; {MOVE_HINT}", path=path, line=k) from None
        done[key] = value
    return done


def check_run_folder(out_dir: str | Path, meta_name: str, fingerprint: str, *, what: str = "run",
                     fresh: bool = False) -> None:
    """Refuse to replace the results of a different run: ``out_dir/meta_name`` (a JSON object) holds
    the fingerprint (:func:`fingerprint`) of the run that wrote the folder; another fingerprint (or none) is the one-line
    error naming that file and ``--fresh``; ``fresh`` skips the check. The shared behaviour of every command that writes a run's results (``ka``, ``fit``,
    ``uncertainty``; ``correct`` and ``design`` check their journals the same way).

    Nothing is removed here: the command's writer, an :class:`OutputGroup` with ``replaces`` (the
    command's own file names), removes the earlier run's files that the new run does not write, once
    the new ones are in place; a run that stops before (bad input found later, an error, Ctrl-C) leaves
    the folder as it was."""
    out_dir = Path(out_dir)
    meta = out_dir / meta_name
    if fresh:
        return
    if not meta.exists():
        return
    try:
        old = json.loads(meta.read_text(encoding="utf-8")).get("fingerprint")
    except OSError as err:
        raise InputError(f"cannot read this file ({err.strerror or err}) to check which run it belongs to; "
                         f"{FRESH_HINT}", path=meta) from None
    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
        old = None
    if old != fingerprint:
        why = (f"holds the results of a different {what} (inputs, settings or roadgonio version differ)" if old else
               "holds results without a run fingerprint (an older roadgonio or another tool)")
        raise InputError(f"this folder {why}; use another --out folder, or --fresh to discard them", path=meta)


def check_writable(out_dir: str | Path) -> Path:
    """Fail before the work, not after it: the output folder can be created and written (a
    staging folder is made and removed). Raises the one-line :class:`InputError` of an output.
    The folders the check made are removed again (deepest first, while empty), so a run stopped
    before its outputs (Ctrl-C: "nothing was written") leaves no empty folder behind (trial 11
    D11); the writer makes them again."""
    out_dir = Path(out_dir)
    made = [p for p in (out_dir, *out_dir.parents) if not p.exists()]
    with OutputGroup(out_dir):
        pass
    for p in made:
        try:
            p.rmdir()
        except OSError:
            break
    return out_dir


def read_user_text(path: str | Path, what: str, *, missing: str | None = None) -> str:
    """The text of a user's input file, UTF-8 with or without a byte-order mark, or the one-line
    :class:`InputError` naming the file: ``no such {what}`` (or ``missing``), ``cannot read the
    {what} (reason)``, or, for text in another encoding, the line of the first byte UTF-8 cannot read
    (user audit, session 37: a UTF-16 model.json, as Windows PowerShell's ``>`` writes, was a
    traceback; a BOM made a TOML file "not valid TOML"; a Latin-1 CSV's error was codec jargon)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(missing or f"no such {what}", path=path) from None
    except OSError as err:
        raise InputError(f"cannot read the {what} ({err.strerror or err})", path=path) from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = raw.count(b"\n", 0, err.start) + 1
        utf16 = raw[:2] in (b"\xff\xfe", b"\xfe\xff")
        raise InputError(("not UTF-8 text but UTF-16 (as Windows PowerShell's '>' writes)" if utf16 else
                          f"not UTF-8 text (byte 0x{raw[err.start]:02X} cannot be read)")
                         + f"; save the {what} as UTF-8", path=path, line=None if utf16 else line) from None


def read_toml(path: str | Path, what: str = "TOML file", *, missing: str | None = None) -> dict[str, Any]:
    """The tables of a TOML file, or the one-line :class:`InputError` naming the file: ``no such
    {what}`` (or ``missing``), ``cannot read the {what} (reason)``, or ``not valid TOML: reason``
    with the LINE of the syntax error (and its column). The one TOML reader of roadgonio: instrument
    files, road layouts, misalignment SPEC files."""
    import tomllib
    path = Path(path)
    text = read_user_text(path, what, missing=missing)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        line, column, reason = toml_error_position(err, text)
        at = f" (column {column})" if column is not None else ""
        raise InputError(f"not valid TOML: {reason}{at}", path=path, line=line) from None


def toml_error_position(err: Exception, text: str) -> tuple[int | None, int | None, str]:
    """(line, column, reason) of a ``tomllib.TOMLDecodeError`` raised on ``text``: from its
    attributes (Python >= 3.14) or, on 3.11-3.13 where they are only in the message ("Invalid
    value (at line 5, column 14)", "... (at end of document)"), parsed from it."""
    import re
    message = str(err)
    at = re.search(r"\s*\(at line (\d+), column (\d+)\)\s*$", message)
    end = re.search(r"\s*\(at end of document\)\s*$", message)
    cut = at or end
    reason = getattr(err, "msg", None) or (message[:cut.start()] if cut else message)
    line, column = getattr(err, "lineno", None), getattr(err, "colno", None)
    if line is None and at is not None:
        line, column = int(at.group(1)), int(at.group(2))
    elif line is None and end is not None:
        line, column = text.count("\n") + 1, None
    return line, column, reason


_PLAIN = frozenset((float, int, bool, str, type(None)))


def _jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays and non-finite floats for strict JSON."""
    try:
        import numpy as np
        if isinstance(obj, np.ndarray):
            return [_jsonable(v) for v in obj.tolist()]
        if isinstance(obj, np.generic):
            obj = obj.item()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        if all(type(v) in _PLAIN for v in obj):     # fast path: a column of numbers (journals of 580 cells)
            return [None if type(v) is float and not math.isfinite(v) else v for v in obj]
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def to_json(obj: Any, indent: int | None = 2) -> str:
    """Strict JSON (NaN and infinities as null, numpy values as numbers)."""
    return json.dumps(_jsonable(obj), indent=indent, allow_nan=False)


def fingerprint(payload: Mapping[str, Any], length: int = 16) -> str:
    """The fingerprint of what determines a result (a journal's or a checkpoint's header): the
    first ``length`` hex digits of the SHA-256 of ``payload`` with the roadgonio version added
    (``{**payload, "roadgonio": __version__}``), as compact strict JSON (:func:`to_json`). Callers
    put in the numbers (instrument and model values, backend settings, seeds...), not names."""
    from roadgonio._version import __version__
    return hashlib.sha256(to_json({**payload, "roadgonio": __version__}, indent=None).encode()).hexdigest()[:length]


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    return atomic_write_text(path, to_json(obj) + "\n")


def atomic_savefig(fig, path: str | Path, **kwargs) -> Path:
    """Save a matplotlib figure atomically (format from the final suffix)."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    kwargs.setdefault("dpi", 120)
    return atomic_write(path, lambda p: fig.savefig(p, format=fmt, **kwargs))


def write_netcdf(ds, path: str | Path) -> Path:
    """Write an ``xarray.Dataset`` as netCDF atomically (netCDF-3 64-bit offset through scipy, which
    every install has): attributes that netCDF cannot hold (mappings, lists, booleans, whole numbers
    beyond 32 bits such as a 63-bit seed) are written as JSON text; booleans data variables become
    int8 (xarray records their dtype and reads them back)."""
    import numpy as np

    def holds(v) -> bool:
        if isinstance(v, bool) or not isinstance(v, (str, int, float, np.integer, np.floating)):
            return False
        return not isinstance(v, (int, np.integer)) or -2 ** 31 <= int(v) < 2 ** 31
    enc = ds.copy()
    for k, v in list(enc.attrs.items()):
        if not holds(v):
            enc.attrs[k] = to_json(v, indent=None)
    for name in list(enc.variables):
        for k, v in list(enc[name].attrs.items()):
            if not holds(v):
                enc[name].attrs[k] = to_json(v, indent=None)
    return atomic_write(path, lambda p: enc.to_netcdf(p, engine="scipy", format="NETCDF3_64BIT"))


def read_netcdf(path: str | Path, booleans: tuple[str, ...] = ()):
    """Open a netCDF file written by :func:`write_netcdf` (loaded into memory; ``booleans`` come back
    as booleans)."""
    import xarray as xr
    try:
        with xr.open_dataset(path, engine="scipy") as ds:
            ds = ds.load()
    except FileNotFoundError:
        raise InputError("no such file", path=path) from None
    except (OSError, ValueError, TypeError) as err:
        raise InputError(f"not a netCDF file roadgonio can read ({err})", path=path) from None
    for v in booleans:
        if v in ds:
            ds[v] = ds[v].astype(bool)
    return ds


def safe_name(name: str, fallback: str = "unnamed", max_len: int = 80) -> str:
    """A name (an instrument's, a table's, a sample's) made safe as ONE folder or file name: letters,
    digits, '-', '_' and '.', anything else '_', no leading dot (so never '.' or '..'), at most
    ``max_len`` characters; ``fallback`` when nothing is left. Output folders derived from names
    use it, so a name like '../x' cannot make a folder escape the working folder."""
    out = "".join(c if (c.isascii() and c.isalnum()) or c in "-_." else "_" for c in str(name)).lstrip(".")
    return out[:max_len] or fallback
