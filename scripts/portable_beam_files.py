"""The table and map files of the bundled example scenes/portable_beam.toml (an illustrative LED
behind a lens and a luminance meter with a measured-looking field-uniformity map; the numbers are
made up, typical of such parts, not measurements of a device). Run from the repository::

    python scripts/portable_beam_files.py   # writes scenes/portable_beam_led.ldt, _aperture.csv, _field.png

* ``portable_beam_led.ldt``: EULUMDAT, rotationally symmetric (Isym 1), gamma 0 ... 180 deg every
  2.5 deg, I(gamma) = 1000 cd/klm (0.85 exp(-gamma^2 / (2 (15 deg)^2)) + 0.15 cos^2 gamma) for
  gamma <= 90 deg, 0 behind: a collimated core and a Lambertian-like skirt.
* ``portable_beam_aperture.csv``: rho, relative radiance 1 - 0.35 rho^4 (the lens's rim darker).
* ``portable_beam_field.png``: 33 x 33 pixels, 16-bit greyscale, k_D = 1 - 0.04 rho^2 + 0.02 x
  (rows from the top, x to the right as the meter looks: docs/conventions.md section 4.1).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def led_ldt() -> str:
    g = np.arange(0.0, 180.0 + 1e-9, 2.5)
    gr = np.radians(g)
    i = np.where(g <= 90.0, 0.85 * np.exp(-g ** 2 / (2 * 15.0 ** 2)) + 0.15 * np.cos(gr) ** 2, 0.0)
    i = 1000.0 * np.maximum(i, 0.0)
    head = ["roadgonio example LED behind a lens (illustrative)", "1", "1", "1", "0", str(g.size), "2.5",
            "scripts/portable_beam_files.py", "illustrative LED with lens", "LED-1", "portable_beam_led.ldt",
            "2026-12-01", "0", "0", "0", "50", "50", "0", "0", "0", "0", "100", "100", "1", "0",
            "1", "1", "LED", "1000", "4000", "80", "1"]
    lines = head + ["0"] * 10 + ["0"] + [f"{v:g}" for v in g] + [f"{v:.6f}" for v in i]
    return "\r\n".join(lines) + "\r\n"


def aperture_csv() -> str:
    rho = np.linspace(0.0, 1.0, 11)
    return "rho,relative_radiance\n" + "".join(f"{r:.1f},{1.0 - 0.35 * r ** 4:.6f}\n" for r in rho)


def field_png(path: Path, n: int = 33) -> None:
    from PIL import Image
    c = -1.0 + (2.0 * np.arange(n) + 1.0) / n
    X, Y = np.meshgrid(c, c[::-1])
    k = 1.0 - 0.04 * (X ** 2 + Y ** 2) + 0.02 * X
    Image.fromarray(np.round(k / k.max() * 65535.0).astype(np.uint16)).save(path)


if __name__ == "__main__":
    (SCENES / "portable_beam_led.ldt").write_bytes(led_ldt().encode("ascii"))
    (SCENES / "portable_beam_aperture.csv").write_text(aperture_csv())
    field_png(SCENES / "portable_beam_field.png")
    print("wrote", ", ".join(f"scenes/portable_beam_{n}" for n in ("led.ldt", "aperture.csv", "field.png")))
