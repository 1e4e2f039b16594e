"""Cutting conditions in an inch program: the structured comment's values are read in metric units whatever the
program's (ap and ae in mm, fz in mm per tooth, f in mm per revolution, vc in m/min). An inch program's comment
written in inch (ap=0.08 for 0.08 in) was taken 25.4 times too small without a word (exit 0); it is said now, once,
with the values and units as read."""

from __future__ import annotations

from conftest import MACHINES
from trueaxis.machine import load_machine
from trueaxis.nc.setup import Setup
from trueaxis.postproc.post import post_text

MILL = """G{units} G17 G90 G94
G54
(trueaxis: ap={ap} ae={ae} fz=0.05 n=8000 d=10 z=4 mode=down)
G0 X{x0} Y{y0} Z{z0}
G1 X{x1} F{f}
G1 Y{y1}
M2
"""

LATHE = """G18 G{units} G90 G8 G40 G49
G54
G95 F{f}
(trueaxis: ap={ap} f=0.2 vc=180)
G0 X{x0} Z{z0}
G1 Z{z1}
M30
"""


def _warnings(text, machine):
    _, rep = post_text(text, load_machine(MACHINES / machine), "comprehensive", setup=Setup(offsets_zero=True))
    return [w for w in rep.warnings if "cutting conditions" in w and "metric units" in w]


def test_an_inch_milling_program_is_told_its_conditions_are_read_in_mm():
    inch = MILL.format(units=20, ap=0.02, ae=0.1, x0=0, y0=0, z0=-2, x1=2, y1=1, f=20)
    said = _warnings(inch, "xh714.toml")
    assert len(said) == 1  # once, however many blocks cut
    assert said[0].startswith("<string>:3: the program is in inch (G20)")
    assert "ap=0.02 ae=0.1 fz=0.05" in said[0] and "ap in mm" in said[0] and "fz in mm per tooth" in said[0]
    # a mm program's comment is in its own units: nothing to say
    mm = MILL.format(units=21, ap=0.5, ae=2.5, x0=0, y0=0, z0=-50, x1=50, y1=25, f=500)
    assert _warnings(mm, "xh714.toml") == []


def test_an_inch_lathe_program_is_told_its_conditions_are_read_in_metric_units():
    inch = LATHE.format(units=20, ap=0.08, f=0.008, x0=1.6, z0=-0.1, z1=-2)
    said = _warnings(inch, "lathe.toml")
    assert len(said) == 1 and "ap=0.08 f=0.2 vc=180" in said[0]
    assert "f in mm per revolution" in said[0] and "vc in m/min" in said[0]
    mm = LATHE.format(units=21, ap=2, f=0.2, x0=40, z0=-2, z1=-50)
    assert _warnings(mm, "lathe.toml") == []
