"""--json on stdout is strict JSON (the one writer, roadgonio.fileio.to_json: NaN/inf as null)."""
from __future__ import annotations

import json


def strict(text: str):
    def refuse(name):
        raise ValueError(f"{name} is not JSON")
    return json.loads(text, parse_constant=refuse)


def test_cli_json_on_stdout_is_strict(capsys):
    from roadgonio.cli import main
    # a deterministic backend has no standard error: se is NaN in the result, null on stdout
    assert main(["ka", "--instrument", "lab", "--sample", "lambert", "--backend", "quadrature", "--tan-eps", "1",
                 "--beta", "0", "--json"]) == 0
    d = strict(capsys.readouterr().out)
    assert d["se"] is None and d["error_bound"] >= 0.0
    for argv in (["tables", "--json"], ["table", "R3", "--json"]):
        assert main(argv) == 0
        strict(capsys.readouterr().out)
