"""The Mitsuba k_A backend in a fresh interpreter where no variant was chosen."""
from __future__ import annotations


def test_without_a_chosen_variant_the_backend_says_what_to_call():
    import subprocess
    import sys
    code = ("import os, mitsuba\n"
            "from roadgonio.errors import BackendError\n"
            "from roadgonio.instrument.config import load_instrument\n"
            "from roadgonio.surface.model import RoadModel\n"
            "from roadgonio.engines.mitsuba.backend import make_backend\n"
            "env = dict(os.environ)\n"
            "try:\n"
            "    make_backend(load_instrument('portable'), RoadModel.lambert())\n"
            "except BackendError as e:\n"
            "    print('ERR', e)\n"
            "print('variant', mitsuba.variant(), 'env same', dict(os.environ) == env)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "ERR no Mitsuba variant is selected" in r.stdout and "set_variant" in r.stdout
    assert "variant None env same True" in r.stdout
