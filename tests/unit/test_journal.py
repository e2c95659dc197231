"""The journals of resumable runs (mutation audit 9b: nothing tested the reader's rule for a bad
line that is not the last, nor that the intercomparison's journal gives every record back under
its own key; both could be changed without a test failing)."""
from __future__ import annotations

import json

import pytest

from roadgonio.errors import InputError
from roadgonio.fileio import read_journal


def _record(d):
    return (d["a"], d["b"]), d["v"]


def _write(path, lines):
    path.write_text("".join(line + "\n" for line in lines), encoding="utf-8")


def test_a_cut_short_last_line_is_dropped_and_any_other_bad_line_is_an_error(tmp_path):
    head = json.dumps({"fingerprint": "fp"})
    good = [json.dumps({"a": i, "b": 10 - i, "v": i * 1.5}) for i in range(3)]
    path = tmp_path / "journal.jsonl"
    _write(path, [head, *good])
    assert read_journal(path, "fp", different="x", record=_record) == {(i, 10 - i): i * 1.5 for i in range(3)}
    _write(path, [head, *good, good[0][:7]])                 # interrupted while writing the last line
    assert read_journal(path, "fp", different="x", record=_record) == {(i, 10 - i): i * 1.5 for i in range(3)}
    for bad_at in (1, 2):                                     # a bad line before the last: not an interruption
        lines = [head, *good]
        lines.insert(1 + bad_at, '{"a": 1, "b"')
        _write(path, lines)
        with pytest.raises(InputError, match="corrupt journal line") as err:
            read_journal(path, "fp", different="x", record=_record)
        assert err.value.line == 2 + bad_at and err.value.path == str(path)
    _write(path, [json.dumps({"fingerprint": "other"}), *good])
    with pytest.raises(InputError, match="holds another run"):
        read_journal(path, "fp", different="another run", record=_record)
    # audit 28: a run refused before its first task (an unreachable scheduler) left its header alone,
    # and the next, different run was refused for it: it finished nothing, so nothing is lost
    _write(path, [json.dumps({"fingerprint": "other"})])
    assert read_journal(path, "fp", different="another run", record=_record) == {}


def test_the_intercomparison_journal_gives_every_record_back_under_its_own_key(tmp_path):
    """Records of one kind share their first key element (participant p) and differ in the second
    (the aperture idealised, the realisation of a correction): a reopened journal holds each one."""
    from roadgonio.intercomparison.run import _Journal
    recs = [{"kind": "ideal", "key": [0, "source_aperture"], "k": 1.0},
            {"kind": "ideal", "key": [0, "detector_pupil"], "k": 2.0},
            {"kind": "self", "key": [1, 0], "k": 3.0},
            {"kind": "self", "key": [1, 1], "k": 4.0},
            {"kind": "realisation", "key": [0], "k": 5.0},
            {"kind": "reference", "key": [1], "k": 6.0}]
    j = _Journal(tmp_path, "fp", fresh=False)
    for r in recs:
        j.add(r)
    j.close()
    again = _Journal(tmp_path, "fp", fresh=False)
    again.close()
    assert len(again.done) == len(recs)
    assert sorted(r["k"] for r in again.done.values()) == [r["k"] for r in recs]
    for r in recs:
        assert r in again.done.values()


@pytest.mark.parametrize("k_a,se,note,ok", [
    (0.93, 1e-3, None, True),
    (float("nan"), float("nan"), "the model is 0 at the nominal geometry: k_A is undefined", True),
    (-5.0, 1e-3, None, False),
    (float("nan"), 1e-3, None, False),
    (float("inf"), 1e-3, None, False),
    (0.93, -1e-3, None, False),
])
def test_a_ka_journal_with_a_value_no_backend_writes_is_refused(tmp_path, k_a, se, note, ok):
    """The user audit of session 19: a journal edited to hold k_A = -5 and a NaN was resumed (the -5
    went into ka.csv; the NaN cell counted as done and stayed blank). Such a line is a bad line of
    the journal: the one-line error naming it, as for any other (the backend's own undefined k_A, with
    its note, still reads back)."""
    from roadgonio.engines.result import CellResult
    from roadgonio.engines.runner import _read_journal
    from roadgonio.fileio import to_json
    extra = {"note": note} if note else {}
    cells = [CellResult(0.0, 0.0, 1.0, 1e-3, 10, 0.1), CellResult(2.0, 0.0, k_a, se, 10, 0.1, extra=extra),
             CellResult(3.0, 0.0, 1.0, 1e-3, 10, 0.1)]
    path = tmp_path / "ka_cells.jsonl"
    _write(path, [to_json({"fingerprint": "fp"}, indent=None)] + [to_json(c.to_dict(), indent=None) for c in cells])
    if ok:
        assert len(_read_journal(path, "fp")) == 3
    else:
        with pytest.raises(InputError, match="corrupt journal line") as err:
            _read_journal(path, "fp")
        assert err.value.line == 3 and err.value.path == str(path)


def test_an_exact_zero_se_has_no_degrees_of_freedom():
    """User audit, session 29: a Lambertian sample under a Lambert calibration gives k_A = 1 with se 0
    (every replicate the same), and ka --json / ka.nc said se_dof 15 beside it; inputs-outputs.md says
    NaN where the SE is not an estimate. An SE > 0 keeps its degrees of freedom, also through a journal."""
    import math
    from roadgonio.engines.result import CellResult
    exact = CellResult(12.0, 0.0, 1.0, 0.0, 4096, 0.0, se_dof=15.0)
    assert math.isnan(exact.se_dof) and "se_dof" not in exact.to_dict()
    est = CellResult(12.0, 0.0, 0.98, 1e-4, 4096, 0.0, se_dof=15.0)
    assert est.se_dof == 15.0 and CellResult(**json.loads(json.dumps(est.to_dict()))).se_dof == 15.0
    stray = CellResult(12.0, 0.0, 1.0, 0.0, 4096, 0.0, k_a_direct=1.0, k_a_direct_se=0.0, stray_fraction=0.01,
                       stray_fraction_se=1e-4, se_dof=15.0)
    assert stray.se_dof == 15.0          # the stray fraction's SE is an estimate of those replicates

