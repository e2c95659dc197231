"""The k_A table runner in a fresh interpreter: which rooms a quadrature table imports."""
from __future__ import annotations


def test_the_table_runner_does_not_import_the_mitsuba_room(tmp_path):
    """engines.runner sits below the backends: a quadrature table (journal, outputs, provenance)
    never imports roadgonio.engines.mitsuba, mitsuba or drjit."""
    import subprocess
    import sys
    code = ("import sys\n"
            "from roadgonio.engines import make_backend\n"
            "from roadgonio.engines.runner import ka_dataset, run_cells, write_outputs\n"
            "from roadgonio.instrument.config import load_instrument\n"
            "from roadgonio.surface.model import RoadModel\n"
            "inst, model = load_instrument('portable'), RoadModel.lambert()\n"
            "b = make_backend('quadrature', inst, model, accuracy='fast')\n"
            f"run = run_cells(b, [(1.0, 0.0)], instrument=inst, model=model, out_dir={str(tmp_path)!r}, progress=False)\n"
            "ds = ka_dataset(run, instrument=inst, model=model, backend=b, sample='lambert')\n"
            f"write_outputs(ds, {str(tmp_path)!r}, plot=False)\n"
            "print(sorted(m for m in sys.modules if m.startswith(('mitsuba', 'drjit', 'roadgonio.engines.mitsuba'))))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"
    assert (tmp_path / "ka.json").exists()
