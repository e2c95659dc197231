"""From the r-table to the road: EN 13201-3 luminance metrics of a luminaire layout computed with a
measured or corrected r-table, with its uncertainty (docs/road.md).

Modules: :mod:`.layout` (the road and installation, a frozen dataclass from TOML), :mod:`.luminaire`
(EULUMDAT photometry through eulumdat-py), :mod:`.interp` (r-table interpolation as cell weights),
:mod:`.calc` (the EN 13201-3 field, grid, observers, luminance operator, illuminance, veiling
luminance), :mod:`.metrics` (L_av, U_o, U_l, EN 13201-2 M classes), :mod:`.evaluate` (one
evaluation; :class:`Installation`), :mod:`.mc` (Monte Carlo of the table's uncertainty),
:mod:`.report` (files and pictures), :mod:`.compare` (two tables side by side). The CIE classes by
S1 are :mod:`roadgonio.surface.cie`.

Typical use::

    from roadgonio.road import Installation, load_layout, load_luminaire
    inst = Installation(load_layout(), load_luminaire())      # bundled defaults
    result = inst.evaluate(bundled_table("R3"))
    result.values   # {'L_av': ..., 'U_o': ..., 'U_l': ..., 'TI': ..., 'R_EI': ...}; result.cls == 'M3'
"""
from roadgonio.road.evaluate import Installation, RoadResult
from roadgonio.road.layout import Layout, load_layout
from roadgonio.road.luminaire import Luminaire, load_luminaire

__all__ = ["Installation", "RoadResult", "Layout", "load_layout", "Luminaire", "load_luminaire"]
