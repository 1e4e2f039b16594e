"""Shared test fixtures and the policy for outside programs (FreeCAD, rs274, CloudCompare).

An outside program that is missing fails the test when CI=true (the Makefile installs it), and skips it with the
reason otherwise.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data"
MACHINES = ROOT / "fixtures" / "machines"


def require_program(name: str, package: str = "", needed_for: str = "") -> str:
    """Path of an outside program: the one place of the rule that a missing program fails the test under CI=true
    (the Makefile installs it) and skips it with the reason elsewhere."""
    path = shutil.which(name)
    if path is None:
        message = (f"{name} is not installed ({f'Debian package {package}; ' if package else ''}make test installs it: "
                   f"see the Makefile's DEBS_TEST){'; ' + needed_for + ' need it' if needed_for else ''}")
        missing(message)
    return path


def missing(message: str) -> None:
    """Something ``make test`` installs or builds is not here: fail the test under CI=true, skip it with the reason
    elsewhere (the one place of that rule)."""
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(message + " and CI=true")
    pytest.skip(message)


@pytest.fixture(scope="session")
def bc_machine():
    from trueaxis.machine import load_machine

    return load_machine(DATA / "bc_table.toml")


def random_poses(machine, n, seed=0):
    from trueaxis.machine.workspace import sample_poses

    return sample_poses(machine, n, seed)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="module")
def xh714_wide():
    """The XH714 with travels of +-2 m: the NIST programs (and programs repeated from them) stay inside them."""
    from trueaxis.machine import parse_machine

    text = (MACHINES / "xh714.toml").read_text()
    for old in ("[-200.0, 200.0]", "[-150.0, 150.0]", "[-400.0, 0.0]"):
        text = text.replace(old, "[-2000.0, 2000.0]")
    return parse_machine(text, source="xh714-wide")


def tilted_cone_case(n_blocks: int = 3000):
    """(machine, program text): the nmv1500dcg with every parameter that is zero drawn from N(0, 10) (seed 0), and the
    flank program of a cone whose axis leans 10 deg, ``n_blocks`` blocks: a five-axis post with every error at work."""
    import math

    from trueaxis.machine import load_machine
    from trueaxis.sim.programs import cone_flank_program

    m = load_machine(MACHINES / "nmv1500dcg.toml")
    cone = {"axis": [math.sin(math.radians(10)), 0.0, math.cos(math.radians(10))], "half_angle_deg": 15.0,
            "base_radius": 40.0, "height_range": [0.0, 20.0]}
    values = m.parameter_values()
    m = m.with_parameters(np.where(values == 0.0, np.random.default_rng(0).normal(0.0, 10.0, values.size), values))
    return m, cone_flank_program(m, cone, n_blocks=n_blocks)


# A [cutting] table for test machines: C45's mechanistic milling coefficients (N/mm^2 and N/mm), as the fixtures'.
CUTTING_C45 = """[cutting]
material = "C45"
Ktc = 2000.0
Krc = 750.0
Kac = 400.0
Kte = 30.0
Kre = 45.0
Kae = 5.0
"""


def mill_toml(name: str, travel: tuple = ((-200.0, 200.0), (-150.0, 150.0), (-400.0, 0.0)), tail: str = "") -> str:
    """A three-axis test mill's machine file (the XH714's layout: the table on Y then X, Z on the tool; a 10 mm, 100 mm
    tool): ``travel`` of X, Y, Z in mm, then ``tail`` (the tool's further keys, location errors, tables, ...)."""
    (x0, x1), (y0, y1), (z0, z1) = travel
    return f"""
[machine]
name = "{name}"
kind = "mill"
format = 1
[kinematics]
bed_to_workpiece = ["Y", "X"]
bed_to_tool = ["Z"]
[axes]
X = {{ type = "linear", travel = [{x0!r}, {x1!r}] }}
Y = {{ type = "linear", travel = [{y0!r}, {y1!r}] }}
Z = {{ type = "linear", travel = [{z0!r}, {z1!r}] }}
[tool]
length = 100.0
radius = 5.0
""" + tail
