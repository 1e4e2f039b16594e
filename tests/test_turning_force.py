"""Kienzle's turning force and its direction on a lathe (trueaxis.machine.turning_force)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import MACHINES
from trueaxis.machine import load_machine
from trueaxis.machine.machine_file import MachineFileError, parse_machine
from trueaxis.machine.turning_force import (
    TurningCoefficients,
    TurningConditions,
    force_on_tool,
    turning_force_components,
)


def test_kienzle_force_with_a_lead_angle_follows_chip_thickness_and_width():
    # kappa_r 60 deg: h = f sin 60, b = ap / sin 60; Fc = kc11 b h^(1 - mc), worked by hand.
    k = TurningCoefficients(kc11=1800.0, mc=0.25, feed_ratio=0.5, passive_ratio=0.3, kappa_deg=60.0)
    fc, ff, fp = turning_force_components(k, TurningConditions(ap_mm=3.0, f_mm=0.3))
    h, b = 0.3 * math.sin(math.pi / 3), 3.0 / math.sin(math.pi / 3)
    assert fc == pytest.approx(1800.0 * b * h**0.75, rel=1e-14)
    assert (ff, fp) == (pytest.approx(0.5 * fc, rel=1e-14), pytest.approx(0.3 * fc, rel=1e-14))
    # Doubling the depth doubles the force; doubling the feed multiplies it by 2^(1 - mc).
    fc2 = turning_force_components(k, TurningConditions(6.0, 0.3))[0]
    fc3 = turning_force_components(k, TurningConditions(3.0, 0.6))[0]
    assert fc2 == pytest.approx(2 * fc, rel=1e-14) and fc3 == pytest.approx(2**0.75 * fc, rel=1e-14)


def test_speed_correction_applies_only_when_asked_for():
    k = TurningCoefficients(kc11=2000.0, mc=0.2, vc_ref=100.0, vc_exponent=0.1)
    fc = turning_force_components(k, TurningConditions(2.0, 0.2, vc_m_min=200.0))[0]
    assert fc == pytest.approx(2000.0 * 2.0 * 0.2**0.8 * 0.5**0.1, rel=1e-14)
    with pytest.raises(ValueError, match="needs the cutting speed"):
        turning_force_components(k, TurningConditions(2.0, 0.2))


@pytest.mark.parametrize(
    "direction, expected",
    [
        ((0.0, -1.0), (30.0, 100.0, 40.0)),  # towards the chuck: feed force +Z, passive +X
        ((0.0, 1.0), (30.0, 100.0, -40.0)),  # towards the tailstock: feed force -Z, passive +X
        ((-1.0, 0.0), (40.0, 100.0, 30.0)),  # facing inwards: feed force +X, passive +Z
        ((1.0, 0.0), (-40.0, 100.0, 30.0)),  # facing outwards: feed force -X, passive +Z
        ((1.0, -1.0), ((-40.0 + 30.0) / math.sqrt(2), 100.0, (40.0 + 30.0) / math.sqrt(2))),  # chamfer
    ],
)
def test_force_on_the_tool_opposes_the_feed_and_pushes_off_the_material(direction, expected):
    np.testing.assert_allclose(force_on_tool((100.0, 40.0, 30.0), np.array([direction]))[0], expected, atol=1e-12)


def test_lathe_machine_file_reads_turning_coefficients_and_refuses_milling_ones():
    lathe = load_machine(MACHINES / "lathe.toml")
    assert TurningCoefficients.from_mapping(lathe.cutting).kc11 == 2220.0
    text = (MACHINES / "lathe.toml").read_text()
    head = text.split("[cutting]")[0]
    with pytest.raises(MachineFileError, match="cutting.Ktc: unknown key"):
        parse_machine(head + "[cutting]\nkc11 = 2000.0\nmc = 0.2\nKtc = 1.0\n")
    with pytest.raises(MachineFileError, match="cutting.mc: missing"):
        parse_machine(head + "[cutting]\nkc11 = 2000.0\n")
    with pytest.raises(MachineFileError, match="mc must lie in"):
        parse_machine(head + "[cutting]\nkc11 = 2000.0\nmc = 1.5\n")
