"""The one TOML reader (roadgonio.fileio.read_toml): a syntax error in every kind of TOML file
roadgonio reads names the file and the LINE, in the API and on the command line (one line, exit 2)."""
from __future__ import annotations

import pytest

from roadgonio.errors import InputError
from helpers import GOOD_LAYOUT, broken, instrument_text, spec_text


def best_toml(tmp_path) -> str:
    """An instrument file as `roadgonio design` writes it (best.toml)."""
    from roadgonio.design.outputs import toml_text
    from roadgonio.instrument.config import load_instrument
    return toml_text(load_instrument("portable").to_dict(), "written by roadgonio design\n")


def readers(tmp_path):
    from roadgonio.instrument.config import Instrument, load_instrument
    from roadgonio.road.layout import read_layout
    from roadgonio.uncertainty.spec import parse_sigma_spec
    return {
        "instrument": (instrument_text(), Instrument.load),
        "instrument by name or path": (instrument_text(), load_instrument),
        "best.toml": (best_toml(tmp_path), Instrument.load),
        "layout": (GOOD_LAYOUT.read_text(encoding="utf-8"), read_layout),
        "SPEC": (spec_text(), parse_sigma_spec),
    }


KINDS = ["instrument", "instrument by name or path", "best.toml", "layout", "SPEC"]


@pytest.mark.parametrize("kind", KINDS)
def test_a_syntax_error_names_the_file_and_its_line(tmp_path, kind):
    good, read = readers(tmp_path)[kind]
    n = len(good.splitlines())
    assert n >= 4
    for line in (3, n):
        p = broken(tmp_path, good, line, f"bad{line}.toml")
        with pytest.raises(InputError) as err:
            read(p)
        assert err.value.path == str(p) and err.value.line == line, (str(err.value), line)
        assert str(err.value).startswith(f"{p}:{line}: not valid TOML: ") and "\n" not in str(err.value)
    # and the good file reads
    good_path = tmp_path / "good.toml"
    good_path.write_text(good, encoding="utf-8")
    read(good_path)


@pytest.mark.parametrize("kind", KINDS)
def test_missing_and_unreadable_files(tmp_path, kind):
    _, read = readers(tmp_path)[kind]
    with pytest.raises(InputError, match="no such") as err:
        read(tmp_path / "missing.toml")
    assert err.value.path == str(tmp_path / "missing.toml")
    latin = tmp_path / "latin.toml"
    latin.write_bytes("# caf\xe9\n".encode("latin-1"))
    with pytest.raises(InputError, match=r":1: not UTF-8 text \(byte 0xE9 .*save the .* as UTF-8") as err:
        read(latin)
    assert err.value.path == str(latin)


def test_end_of_document_and_python_3_11_messages():
    """tomllib on Python 3.11-3.13 puts the position only in the message; both forms are parsed."""
    import tomllib

    from roadgonio.fileio import toml_error_position
    for text, line in (("a = 1\nb = [1,\n", 3), ("a = 1\n\n[b\n", 3), ("x = \n", 1)):
        with pytest.raises(tomllib.TOMLDecodeError) as err:
            tomllib.loads(text)
        got_line, _, reason = toml_error_position(err.value, text)
        assert got_line == line and "line" not in reason, (text, str(err.value))
