"""The beam profile and the sensitivity map through the command line (docs/conventions.md section 4.1):
files named relative to the instrument file, a one-line error naming the table file, its line and
the key (exit 2), and a cell beyond a table's angles refused naming the cell."""
from __future__ import annotations

import json

from helpers import write_map_csv, write_table_csv
from roadgonio.cli import main

INSTRUMENT = """[observation]
alpha_deg = 1.0
[source]
distance_m = 1.0
radius_m = 0.025
beam_intensity_file = "beam.csv"
aperture_edge_radiance = 0.6
[detector]
distance_m = 1.0
pupil_radius_m = 0.005
field_half_angle_deg = 0.15
field_sensitivity = "map.csv"
[sample]
size_x_m = 1.0
size_y_m = 0.3
"""


def _files(tmp_path, theta_end=40.0):
    import numpy as np
    th = np.linspace(0.0, theta_end, 21)
    write_table_csv(tmp_path / "beam.csv", "theta_deg,I", th, np.cos(np.radians(th)) ** 3)
    write_map_csv(tmp_path / "map.csv", lambda x, y: 1.0 + 0.2 * y, 9)
    (tmp_path / "inst.toml").write_text(INSTRUMENT)
    return tmp_path / "inst.toml"


def one_line(capsys, rc):
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("roadgonio: error:"), err
    return err[0]


#: How many error bounds (quadrature) dropping the beam profile or the sensitivity map must move k_A
#: at the test's cell: far beyond the integration error, so that a CLI that resolved the files but
#: dropped one of them cannot pass (measured at DROPPED_FILE_RTOL: the beam 150, the map 1.2e4).
DROPPED_FILE_BOUNDS = 20.0
#: The quadrature's accuracy for that comparison (the beam profile, cos^3 theta, moves k_A by 1e-4 only).
DROPPED_FILE_RTOL = 1e-6


def test_a_profiled_instrument_file_runs_from_another_folder(tmp_path, capsys, monkeypatch):
    """The command line's k_A of an instrument whose profile files are named relative to it, run
    from another folder, is the API's k_A of the loaded instrument, bit for bit, and that instrument
    uses both files: without either, k_A moves by more than DROPPED_FILE_BOUNDS error bounds."""
    from roadgonio import api
    from roadgonio.instrument.config import load_instrument
    inst = _files(tmp_path)
    monkeypatch.chdir(tmp_path.parent)
    rc = main(["ka", "--instrument", str(inst), "--sample", "R3", "--backend", "quadrature", "--tan-eps", "4",
               "--beta", "2", "--rel-se", "1e-4", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0, out

    def k_a(path, rel_se):
        return api.ka_cell(load_instrument(path), "R3", 4.0, 2.0, backend="quadrature", rel_se=rel_se)
    assert out["k_a"] == k_a(inst, 1e-4).k_a, out
    full = k_a(inst, DROPPED_FILE_RTOL)
    for key in ("beam_intensity_file", "field_sensitivity"):
        text = "\n".join(ln for ln in INSTRUMENT.splitlines() if not ln.startswith(key))
        (tmp_path / f"without_{key}.toml").write_text(text)
        other = k_a(tmp_path / f"without_{key}.toml", DROPPED_FILE_RTOL)
        assert full.converged and other.converged, (key, full, other)
        assert abs(other.k_a - full.k_a) > DROPPED_FILE_BOUNDS * (full.error_bound + other.error_bound), (key, full, other)


def test_a_bad_table_is_one_line_naming_file_line_and_key(tmp_path, capsys):
    inst = _files(tmp_path)
    (tmp_path / "beam.csv").write_text("theta_deg,I\n0,1\n10,0.9\n10,0.8\n")
    rc = main(["ka", "--instrument", str(inst), "--sample", "R3", "--backend", "quadrature", "--tan-eps", "4",
               "--beta", "2"])
    line = one_line(capsys, rc)
    assert "beam.csv:4" in line and "source.beam_intensity_file" in line and "increase" in line


def test_a_cell_beyond_the_table_is_refused_naming_it(tmp_path, capsys):
    inst = _files(tmp_path, theta_end=8.0)
    rc = main(["ka", "--instrument", str(inst), "--sample", "R3", "--backend", "quadrature", "--tan-eps", "0",
               "--beta", "0"])
    line = one_line(capsys, rc)
    assert "ends at theta = 8 deg" in line and "tan eps = 0" in line
