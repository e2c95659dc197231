"""The Mitsuba k_A backend's checks that run before Mitsuba: the LLVM version, unknown settings."""
from __future__ import annotations

import pytest

from roadgonio.errors import BackendError, InputError

from helpers import ROAD, preset


def test_llvm_older_than_16_is_refused():
    from roadgonio.engines.mitsuba import check_llvm_version
    with pytest.raises(BackendError, match="LLVM >= 16"):
        check_llvm_version((15, 0, 6))
    check_llvm_version((16, 0, 0))
    check_llvm_version((19, 1, 7))


def test_unknown_setting_is_an_input_error():
    from roadgonio.engines.mitsuba.backend import make_backend
    with pytest.raises(InputError, match="unknown setting"):
        make_backend(preset("portable"), ROAD, samples_per_pixel=3)
    with pytest.raises(InputError, match="per-cell renderer.*first_pass"):
        make_backend(preset("portable"), ROAD, spp=16)
