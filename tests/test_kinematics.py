"""Nominal kinematics: DESIGN §3's B-C example, LinuxCNC's trt kinematics, and the inverse kinematics."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import random_poses
from trueaxis.machine import forward_nominal, inverse_kinematics, parse_machine

TABLE = """
[machine]
name = "{name}"
kind = "mill"
format = 1
[kinematics]
bed_to_workpiece = ["{tilt}", "C"]
bed_to_tool = ["X", "Y", "Z"]
[axes]
X = {{ type = "linear", travel = [-300.0, 300.0] }}
Y = {{ type = "linear", travel = [-300.0, 300.0] }}
Z = {{ type = "linear", travel = [-300.0, 300.0] }}
{tilt} = {{ type = "rotary", travel = [-120.0, 120.0], pivot = [{tp}] }}
C = {{ type = "rotary", pivot = [{cp}] }}
[tool]
length = 100.0
radius = 5.0
[workpiece]
origin = [{origin}]
"""


def table_machine(tilt="B", tilt_pivot=(0, 0, 0), c_pivot=(0, 0, 0), origin=(0, 0, 0)):
    fmt = lambda v: ", ".join(f"{x:.17g}" for x in v)  # noqa: E731
    return parse_machine(TABLE.format(name=f"{tilt}-C table", tilt=tilt, tp=fmt(tilt_pivot), cp=fmt(c_pivot),
                                      origin=fmt(origin)))


def test_bc_table_tool_axis_is_the_design_formula():
    m = table_machine("B")
    q = random_poses(m, 200, seed=1)
    _, u = forward_nominal(m, q)
    B, C = q[:, 3], q[:, 4]
    np.testing.assert_allclose(u, np.column_stack([np.sin(B) * np.cos(C), np.sin(B) * np.sin(C), np.cos(B)]),
                               atol=1e-15)


# --- LinuxCNC trtfuncs.c, written out independently (xyzbcKinematicsForward / xyzacKinematicsForward, tool
# offset 0): joints in machine coordinates, pos = tool tip in the rotary table's coordinates. --------------------


def linuxcnc_xyzbc_forward(j, rot_point, x_offset, z_offset):
    X, Y, Z, b, c = j.T
    xr, yr, zr = rot_point
    dx, dz = x_offset, z_offset
    x = (np.cos(c) * np.cos(b) * (X - dx - xr) + np.sin(c) * (Y - yr) - np.cos(c) * np.sin(b) * (Z - dz - zr)
         + np.cos(c) * dx + xr)
    y = (-np.sin(c) * np.cos(b) * (X - dx - xr) + np.cos(c) * (Y - yr) + np.sin(c) * np.sin(b) * (Z - dz - zr)
         - np.sin(c) * dx + yr)
    z = np.sin(b) * (X - dx - xr) + np.cos(b) * (Z - dz - zr) + dz + zr
    return np.column_stack([x, y, z])


def linuxcnc_xyzac_forward(j, rot_point, y_offset, z_offset):
    X, Y, Z, a, c = j.T
    xr, yr, zr = rot_point
    dy, dz = y_offset, z_offset
    x = (np.cos(c) * (X - xr) + np.sin(c) * np.cos(a) * (Y - dy - yr) + np.sin(c) * np.sin(a) * (Z - dz - zr)
         + np.sin(c) * dy + xr)
    y = (-np.sin(c) * (X - xr) + np.cos(c) * np.cos(a) * (Y - dy - yr) + np.cos(c) * np.sin(a) * (Z - dz - zr)
         + np.cos(c) * dy + yr)
    z = -np.sin(a) * (Y - dy - yr) + np.cos(a) * (Z - dz - zr) + dz + zr
    return np.column_stack([x, y, z])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bc_table_agrees_with_linuxcnc_xyzbc_trt_kins(seed):
    # Mapping: LinuxCNC turns the table, so its b, c are the negatives of our relative-motion B, C (DESIGN §3).
    # Its C line passes through the rotation point r, its B line through r + (x_offset, 0, z_offset).
    rng = np.random.default_rng(seed)
    r = rng.uniform(-50, 50, 3)
    dx, dz = rng.uniform(-30, 30, 2)
    m = table_machine("B", tilt_pivot=r + [dx, 0, dz], c_pivot=r)
    q = random_poses(m, 1000, seed=seed)
    ours, _ = forward_nominal(m, q)
    joints = q.copy()
    joints[:, 3:] *= -1.0
    theirs = linuxcnc_xyzbc_forward(joints, r, dx, dz)
    np.testing.assert_allclose(ours, theirs, atol=1e-9, rtol=0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ac_table_agrees_with_linuxcnc_xyzac_trt_kins(seed):
    rng = np.random.default_rng(seed)
    r = rng.uniform(-50, 50, 3)
    dy, dz = rng.uniform(-30, 30, 2)
    m = table_machine("A", tilt_pivot=r + [0, dy, dz], c_pivot=r)
    q = random_poses(m, 1000, seed=seed)
    ours, _ = forward_nominal(m, q)
    joints = np.column_stack([q[:, 0], q[:, 1], q[:, 2], -q[:, 3], -q[:, 4]])
    theirs = linuxcnc_xyzac_forward(joints, r, dy, dz)
    np.testing.assert_allclose(ours, theirs, atol=1e-9, rtol=0)


# --- inverse kinematics --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("tilt", ["A", "B"])
@pytest.mark.parametrize("branch", [1, -1])
def test_inverse_kinematics_round_trips_on_both_branches(tilt, branch):
    m = table_machine(tilt, tilt_pivot=(3.0, -4.0, -80.0), c_pivot=(1.0, 2.0, 0.0), origin=(5.0, -5.0, 40.0))
    q = random_poses(m, 2000, seed=11)
    q = q[np.abs(np.sin(q[:, 3])) > 1e-3]
    p, u = forward_nominal(m, q)
    res = inverse_kinematics(m, p, u, branch=branch)
    p2, u2 = forward_nominal(m, res.q)
    np.testing.assert_allclose(p2, p, atol=1e-9)
    np.testing.assert_allclose(u2, u, atol=1e-12)
    assert np.all(np.sign(res.q[:, 3]) == branch)


def test_inverse_kinematics_nearest_branch_recovers_the_pose_it_started_from():
    m = table_machine("B", tilt_pivot=(0, 0, -100.0))
    q = random_poses(m, 1000, seed=12)
    p, u = forward_nominal(m, q)
    res = inverse_kinematics(m, p, u, previous=q)
    np.testing.assert_allclose(res.q, q, atol=1e-9)


def test_singular_pose_holds_the_free_axis_at_its_previous_value():
    m = table_machine("B", tilt_pivot=(0, 0, -100.0), c_pivot=(2.0, 1.0, 0.0))
    p = np.array([[10.0, 20.0, 30.0]])
    u = np.array([[0.0, 0.0, 1.0]])
    res = inverse_kinematics(m, p, u, previous=[0, 0, 0, 0, np.radians(37.0)])
    assert res.singular[0]
    assert res.q[0, 4] == pytest.approx(np.radians(37.0), abs=1e-15)
    assert res.q[0, 3] == pytest.approx(0.0, abs=1e-15)
    np.testing.assert_allclose(forward_nominal(m, res.q)[0], p, atol=1e-9)


def test_rotary_winding_takes_the_shortest_way_from_the_previous_pose():
    m = table_machine("B")
    u = np.array([[np.sin(0.5) * np.cos(0.1), np.sin(0.5) * np.sin(0.1), np.cos(0.5)]])
    res = inverse_kinematics(m, np.zeros((1, 3)), u, branch=1, previous=[0, 0, 0, 0, 4 * np.pi])
    assert res.q[0, 4] == pytest.approx(4 * np.pi + 0.1, abs=1e-12)


def test_out_of_travel_is_flagged():
    m = table_machine("B")
    # B travel is [-120, 120] deg: a tool axis pointing 150 deg away from +Z needs |B| = 150 deg.
    u = np.array([[np.sin(np.radians(150)), 0.0, np.cos(np.radians(150))]])
    res = inverse_kinematics(m, np.zeros((1, 3)), u)
    assert res.out_of_travel[0]


def test_inverse_kinematics_of_the_head_table_layout():
    m = parse_machine(TABLE.format(name="head", tilt="B", tp="0, 0, 150", cp="0, 0, 0", origin="0, 0, 0").replace(
        'bed_to_workpiece = ["B", "C"]\nbed_to_tool = ["X", "Y", "Z"]',
        'bed_to_workpiece = ["C"]\nbed_to_tool = ["X", "Y", "Z", "B"]'))
    q = random_poses(m, 500, seed=13)
    q = q[np.abs(np.sin(q[:, 3])) > 1e-3]
    p, u = forward_nominal(m, q)
    res = inverse_kinematics(m, p, u, previous=q)
    np.testing.assert_allclose(res.q, q, atol=1e-9)
