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


def require_program(name: str) -> str:
    """Path of an outside program; fail under CI, skip elsewhere, when it is missing."""
    path = shutil.which(name)
    if path is None:
        message = f"{name} is not installed (make test installs it: see the Makefile's DEBS_TEST)"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
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
