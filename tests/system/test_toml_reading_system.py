"""On the command line a TOML syntax error is one line naming the file and the line, exit status 2
(tests/unit/test_toml_reading.py: every reader through the API)."""
from __future__ import annotations

import pytest

from roadgonio.cli import main
from helpers import GOOD_LAYOUT, broken, instrument_text, spec_text


def cli_cases(tmp_path):
    inst = broken(tmp_path, instrument_text(), 12, "inst.toml")
    layout = broken(tmp_path, GOOD_LAYOUT.read_text(encoding="utf-8"), 5, "layout.toml")
    spec = broken(tmp_path, spec_text(), 4, "spec.toml")
    return {
        "ka --instrument": (["ka", "--instrument", str(inst), "--sample", "lambert", "--backend", "quadrature",
                             "--tan-eps", "1", "--beta", "0"], inst, 12),
        "road --layout": (["road", "--table", "R3", "--layout", str(layout), "--no-plots"], layout, 5),
        "uncertainty --sigma": (["uncertainty", "--instrument", "portable", "--sample", "lambert", "--sigma", str(spec),
                                 "--backend", "quadrature"], spec, 4),
    }


@pytest.mark.parametrize("case", ["ka --instrument", "road --layout", "uncertainty --sigma"])
def test_the_command_line_says_file_and_line_in_one_line(tmp_path, capsys, case):
    argv, path, line = cli_cases(tmp_path)[case]
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("roadgonio: error:") and f"{path}:{line}: not valid TOML" in err[0], err[0]
