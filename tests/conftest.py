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
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + " and CI=true")
        pytest.skip(message)
    return path


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
