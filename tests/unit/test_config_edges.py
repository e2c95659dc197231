"""Config and table readers at their edges (mutation audit 10: each of these could be changed
without any test failing): a study's whole numbers and the corrected realisations' upper limit
(roadgonio/intercomparison/study.py), and the r-table CSV reader's row order
(roadgonio/surface/rtable.py)."""
from __future__ import annotations

import pytest

from helpers_intercomparison import coll, write_collimated
from roadgonio.errors import InputError
from roadgonio.intercomparison.study import study_from_dict
from roadgonio.surface.rtable import bundled_table, parse_csv


def _study(tmp_path, **study):
    write_collimated(tmp_path)
    return {"study": {"surface": "R3", **study}, "participant": [coll("A"), coll("B")], "shared": []}


@pytest.mark.parametrize("study, field, words", [
    ({"realisations": 20.5}, "study.realisations", "whole number"),
    ({"seed": 1.5}, "study.seed", "whole number"),
    ({"realisations": 20, "corrected_realisations": 21}, "study.corrected_realisations", "<= 20"),
])
def test_study_numbers_out_of_kind_or_range_are_refused(tmp_path, study, field, words):
    with pytest.raises(InputError) as err:
        study_from_dict(_study(tmp_path, **study), path=tmp_path / "study.toml")
    assert err.value.field == field and words in err.value.reason and str(tmp_path / "study.toml") in str(err.value)


def test_study_limits_themselves_are_accepted(tmp_path):
    """The limits themselves pass. A whole number written as 20.0 does not (audit 22: as an
    instrument file's max_bounces and the API's seed, a TOML float is not a whole number)."""
    s = study_from_dict(_study(tmp_path, realisations=20, corrected_realisations=20), path=tmp_path / "study.toml")
    assert s.realisations == 20 and s.corrected_realisations == 20
    from roadgonio.intercomparison.study import MAX_REALISATIONS
    assert study_from_dict(_study(tmp_path, realisations=MAX_REALISATIONS), path=tmp_path / "s.toml").realisations \
        == MAX_REALISATIONS
    with pytest.raises(InputError, match="whole number"):
        study_from_dict(_study(tmp_path, realisations=20.0), path=tmp_path / "study.toml")


def test_csv_rows_must_follow_the_tan_eps_grid(tmp_path):
    """Two data rows swapped (tan eps 0.5 before 0.25): the reader names the line and the tan eps it
    expected instead of putting r(0.5) at 0.25."""
    text = bundled_table("R3").to_csv_text()
    lines = text.splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("0.25,"))
    assert lines[k + 1].startswith("0.5,")
    lines[k], lines[k + 1] = lines[k + 1], lines[k]
    with pytest.raises(InputError) as err:
        parse_csv("\n".join(lines) + "\n", path="swapped.csv")
    assert err.value.line == k + 1 and "tan_eps = 0.25" in err.value.reason and "got 0.5" in err.value.reason
