"""The error twin: DESIGN §3 single-parameter cases, the two formulations, and both Jacobians."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import DATA, random_poses
from trueaxis.machine import ErrorTwin, parse_machine

BASE = (DATA / "bc_table.toml").read_text().split("[location]")[0]


def only(location: str = "", extra: str = ""):
    """The test B-C machine with nothing but the given location errors (TOML lines) and extra sections."""
    return parse_machine(BASE + "[location]\n" + location + "\n" + extra)


def err(machine, pose, **kw):
    dp, du = ErrorTwin(machine).volumetric_error(np.atleast_2d(pose), **kw)
    return dp[0], du[0]


# ------------------------------------------------------------------------------------ single-parameter cases -----
# Axis order of the test machine: X Y Z B C (mm, rad).


def test_c0y_at_y100_gives_minus_10um_in_x():
    dp, du = err(only("C0Y = 100.0"), [0, 100, 0, 0, 0])
    np.testing.assert_allclose(dp, [-10.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(du, 0.0, atol=1e-9)


def test_b0z_turns_z_towards_plus_x_and_a0z_towards_minus_y():
    # B0Z: Z to (B0Z, 0, 1); A0Z: Z to (0, -A0Z, 1).  At Z = 100 mm, 50 urad -> 5 um.
    np.testing.assert_allclose(err(only("B0Z = 50.0"), [0, 0, 100, 0, 0])[0], [5.0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(err(only("A0Z = 50.0"), [0, 0, 100, 0, 0])[0], [0, -5.0, 0], atol=1e-9)


def test_squareness_causes_no_error_at_the_axis_zero():
    np.testing.assert_allclose(err(only("C0Y = 100.0\nB0Z = 40.0"), [150, 0, 0, 0, 0])[0], 0.0, atol=1e-12)


@pytest.mark.parametrize("c_deg, expected", [(0, [0, 0, 0]), (90, [20, -20, 0]), (180, [40, 0, 0]), (-90, [20, 20, 0])])
def test_xoc_moves_the_c_line_so_the_part_turns_about_the_offset_line(c_deg, expected):
    # The tool turns by +C about a line moved +20 um in X: error = off - R_C off.
    dp, du = err(only("XOC = 20.0"), [0, 0, 0, 0, np.radians(c_deg)])
    np.testing.assert_allclose(dp, expected, atol=1e-9)
    np.testing.assert_allclose(du, 0.0, atol=1e-12)


def test_aoc_tilts_the_c_line_about_its_pivot_so_the_tool_axis_errs_by_twice_the_tilt_at_180():
    # Tool axis z, C turns it about a line tilted by AOC about X: at C = 180 deg the axis error is 2 AOC about X,
    # i.e. actual axis = (0, -2 AOC, 1) to first order... in the part frame: R_C(180) applied after.
    a = 40.0
    _, du = err(only(f"AOC = {a}"), [0, 0, 0, 0, np.pi])
    np.testing.assert_allclose(np.hypot(du[0], du[1]), 2 * a, rtol=1e-6)
    _, du0 = err(only(f"AOC = {a}"), [0, 0, 0, 0, 0.0])
    np.testing.assert_allclose(du0, 0.0, atol=1e-9)


def test_zero_offset_coc_acts_like_an_extra_c_rotation():
    coc = 50.0  # urad
    dp, _ = err(only(f"COC = {coc}"), [100, 0, 0, 0, 0])
    # The tool tip (100, 0, 0) in M turns by exactly 50 urad about the C line through the pivot (1, 2, 0).
    lever = np.array([100 - 1.0, 0 - 2.0, 0.0])
    a = coc * 1e-6
    turned = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ lever
    np.testing.assert_allclose(dp, 1e3 * (turned - lever), atol=1e-9)


def test_component_error_alone_is_the_error_at_the_reference_point():
    extra = "[component.X]\nat = [-200.0, 200.0]\nEXX = [-4.0, 4.0]\nEYX = [2.0, 6.0]\n"
    dp, du = err(only("", extra), [100, 0, 0, 0, 0])
    np.testing.assert_allclose(dp, [2.0, 5.0, 0.0], atol=1e-9)


def test_angular_component_error_has_the_lever_arm_of_the_axes_below_the_tool():
    # EBX (about Y) of the X axis, measured at the tool tip with Z = 0; at Z = 200 mm the tip is 200 mm from the
    # reference point along +Z, so the error is EBX x (0, 0, 200) = (200 EBX, 0, 0).
    extra = "[component.X]\nat = [-200.0, 200.0]\nEBX = [10.0, 10.0]\n"
    dp, du = err(only("", extra), [50, 0, 0, 0, 0])
    np.testing.assert_allclose(dp, 0.0, atol=1e-9)
    dp, du = err(only("", extra), [50, 0, 100, 0, 0])
    np.testing.assert_allclose(dp, [1.0, 0.0, 0.0], atol=1e-9)  # 10 urad * 100 mm = 1 um
    # The tool axis tips towards +X; its z component drops by theta^2 / 2 = 5e-5 urad (unit vector).
    np.testing.assert_allclose(du, [10.0, 0.0, -5e-5], atol=1e-9)


def test_rotary_component_error_turns_about_the_reference_point_not_the_axis_line():
    # DESIGN §3: component errors are defined at the tool tip with the other axes at zero, here the M origin; an
    # ECC of 30 urad therefore turns the tool about that point (lever (100, 0, 0)), whereas the zero offset COC turns
    # it about the C line through the pivot (1, 2, 0).  Their difference is a pure translation (an EXC/EYC).
    extra = "[component.C]\nfourier = { ECC = [[1, 0.0, 0.0], [2, 30.0, 0.0]] }\n"
    dp, _ = err(only("", extra), [100, 0, 0, 0, 0])  # cos(2*0) = 1 -> 30 urad
    np.testing.assert_allclose(dp, 1e3 * np.cross([0, 0, 30e-6], [100.0, 0, 0]), atol=1e-9)


# ------------------------------------------------------------------------------------ the two formulations -------


def test_full_and_differential_forms_differ_only_at_second_order(bc_machine):
    q = random_poses(bc_machine, 2000, seed=3)
    values = bc_machine.parameter_values()

    def gap(k):
        m = bc_machine.with_parameters(k * values)
        tw = ErrorTwin(m)
        a = np.hstack(tw.volumetric_error(q, method="full"))
        b = np.hstack(tw.volumetric_error(q, method="differential"))
        return np.abs(a - b).max(axis=0), np.abs(a).max()

    g1, size1 = gap(1.0)
    g2, size2 = gap(2.0)
    # Errors scale with k, the formulations' difference with k^2: doubling every parameter quadruples the gap.
    assert size2 / size1 == pytest.approx(2.0, rel=1e-3)
    np.testing.assert_allclose(g2[:3] / g1[:3], 4.0, rtol=0.05)
    # And the gap is bounded by (largest angular error)^2 x (largest lever arm): 200 urad total tilt, 600 mm.
    ang = 1e-6 * np.abs(values[[bc_machine.parameter_names().index(n) for n in bc_machine.location_names()
                                 if bc_machine.parameter_units()[bc_machine.parameter_names().index(n)] == "urad"]]).sum()
    bound_um = 1e3 * (ang + 100e-6) ** 2 * 600.0
    assert g1[:3].max() < bound_um
    assert g1[:3].max() > 0.0  # the two really are different formulas


def test_unit_tool_axis_stays_unit(bc_machine):
    q = random_poses(bc_machine, 500, seed=4)
    _, u = ErrorTwin(bc_machine).actual_pose(q)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-15)


# ------------------------------------------------------------------------------------ Jacobians vs differences --


def test_axis_jacobian_matches_central_differences(bc_machine, rng):
    tw = ErrorTwin(bc_machine)
    q = random_poses(bc_machine, 50, seed=5)
    force = rng.normal(0, 150, (50, 3))
    J = tw.axis_jacobian(q, force_n=force)
    for j, axis in enumerate(bc_machine.axis_names):
        rotary = bc_machine.axes[axis].is_rotary
        h = 1e-6 if rotary else 1e-5
        qp, qm = q.copy(), q.copy()
        qp[:, j] += h
        qm[:, j] -= h
        fd = (np.hstack(tw.actual_pose(qp, force)) - np.hstack(tw.actual_pose(qm, force))) / (2 * h)
        # Round-off of a central difference: 1e-16 x (|p| ~ 600 mm) / h, plus h^2 truncation (negligible here).
        tol = 4 * 2.2e-16 * 600 / h
        np.testing.assert_allclose(J[:, :, j], fd, atol=tol, err_msg=f"axis {axis}")


def test_parameter_jacobian_matches_central_differences(bc_machine, rng):
    tw = ErrorTwin(bc_machine)
    q = random_poses(bc_machine, 40, seed=6)
    force = rng.normal(0, 150, (40, 3))
    J = tw.parameter_jacobian(q, force_n=force)
    values = bc_machine.parameter_values()
    h = 0.05  # um or urad
    for k, name in enumerate(bc_machine.parameter_names()):
        vp, vm = values.copy(), values.copy()
        vp[k] += h
        vm[k] -= h
        ep = np.hstack(ErrorTwin(bc_machine.with_parameters(vp)).volumetric_error(q, force_n=force))
        em = np.hstack(ErrorTwin(bc_machine.with_parameters(vm)).volumetric_error(q, force_n=force))
        fd = (ep - em) / (2 * h)
        # Round-off: 1e-16 x 6e5 um / h ~ 1e-9; the model is affine in every component value and nearly so in the
        # location values (their second derivatives are ~1e-10 per unit^2).
        np.testing.assert_allclose(J[:, :, k], fd, atol=1e-7, err_msg=name)


def test_parameter_jacobian_times_values_is_the_differential_error(bc_machine):
    # The differential form is linear in the parameters: J(theta = 0) @ theta reproduces it (unloaded).
    q = random_poses(bc_machine, 300, seed=7)
    zero = bc_machine.with_parameters(np.zeros(len(bc_machine.parameter_names())))
    J0 = ErrorTwin(zero).parameter_jacobian(q)
    lin = np.einsum("nkp,p->nk", J0, bc_machine.parameter_values())
    diff = np.hstack(ErrorTwin(bc_machine).differential_error(q))
    np.testing.assert_allclose(lin, diff, atol=1e-9)


def test_jacobians_in_one_pass_equal_the_separate_calls(bc_machine):
    tw = ErrorTwin(bc_machine)
    q = random_poses(bc_machine, 30, seed=8)
    Ja, Jp = tw.jacobians(q)
    np.testing.assert_allclose(Ja, tw.axis_jacobian(q), atol=1e-14)
    np.testing.assert_allclose(Jp, tw.parameter_jacobian(q), atol=1e-12)


# ------------------------------------------------------------------------------------ force-induced errors -------


def test_compliance_deflects_the_tool_by_c_times_f_in_the_part_frame():
    m = only("", "[force]\ncompliance_um_per_n = [[0.02, 0.0, 0.0], [0.0, 0.03, 0.0], [0.0, 0.0, 0.01]]\n")
    F = np.array([100.0, -50.0, 20.0])
    dp, _ = err(m, [0, 0, 0, 0, 0], force_n=F)
    np.testing.assert_allclose(dp, [2.0, -1.5, 0.2], atol=1e-9)
    # With the table turned by C = 90 deg the machine-frame deflection appears turned in the part frame.
    dp, _ = err(m, [0, 0, 0, 0, np.pi / 2], force_n=F)
    np.testing.assert_allclose(dp, [1.5, 2.0, 0.2], atol=1e-9)  # R_C(90 deg) (2, -1.5, 0.2)


def test_loaded_parameter_set_is_blended_with_the_force_component():
    extra = (
        "[component.X]\nat = [-200.0, 200.0]\nEXX = [0.0, 0.0]\n"
        "[loaded]\nforce_n = [110.0, 180.0, 0.0]\n[loaded.location]\nC0Y = 60.0\n"
        "[loaded.component.X]\nat = [-200.0, 200.0]\nEXX = [8.0, 8.0]\n"
    )
    m = only("C0Y = 20.0", extra)
    pose = [100, 100, 0, 0, 0]
    unloaded = err(m, pose)[0]
    np.testing.assert_allclose(unloaded, [-2.0, 0, 0], atol=1e-9)  # C0Y 20 urad x 100 mm
    full = err(m, pose, force_n=[110.0, 180.0, 0.0])[0]
    np.testing.assert_allclose(full, [8.0 - 6.0, 0, 0], atol=1e-9)  # EXX 8 um, C0Y 60 urad
    half = err(m, pose, force_n=[55.0, 90.0, 0.0])[0]
    np.testing.assert_allclose(half, [4.0 - 4.0, 0, 0], atol=1e-9)
