"""The compiled chain (``chain_kernel``) against the twin's numpy chain, and its axis Jacobian against differences."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import random_poses
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.machine.kinematics import forward_nominal
from trueaxis.resources import machine_file, machine_files

N_POSES = 2000


def every_parameter_non_zero(name: str):
    """A fixture machine with its file's values and a typical size (10 um / 10 urad) for the zero ones, so that every
    term of the chain (each tilt, offset, zero offset, squareness and component) is exercised."""
    m = load_machine(machine_file(name))
    values = m.parameter_values()
    rng = np.random.default_rng(0)
    return m.with_parameters(np.where(values == 0.0, rng.normal(0.0, 10.0, values.size), values))


def load(machine, n: int, seed: int):
    """Force on the tool (n,3) N and directions of motion (n, n_axes), random."""
    rng = np.random.default_rng(seed)
    return rng.normal(0.0, 150.0, (n, 3)), rng.choice([-1.0, 1.0], (n, len(machine.axis_names)))


@pytest.mark.parametrize("loaded", [False, True], ids=["unloaded", "force+motion"])
@pytest.mark.parametrize("name", [f.stem for f in machine_files()])
def test_compiled_chain_equals_the_numpy_chain(name, loaded):
    m = every_parameter_non_zero(name)
    tw = ErrorTwin(m)
    q = random_poses(m, N_POSES, seed=11)
    force, motion = load(m, N_POSES, seed=12) if loaded else (None, None)

    p, u, J = tw.pose_and_axis_jacobian(q, force, motion)
    p_ref, u_ref, J_ref = tw._evaluate(q, force, motion, errors=True, jacobian=True, cols="axes")
    # Same formulas, other order of operations (the tip right to left instead of left to right, explicit sums instead
    # of einsum): they differ by round-off, a few ulps of the largest intermediate (1e-13 mm on a 1000 mm chain).
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(u, u_ref, rtol=0, atol=1e-12)
    scale = np.abs(J_ref).max(axis=(0, 1))  # per axis column: mm/mm or mm/rad
    np.testing.assert_allclose(J / scale, J_ref / scale, rtol=0, atol=1e-12)

    # The pose alone is the same numbers as with the Jacobian (the post relies on it), and the nominal chain is the
    # kinematics' one.
    p_only, u_only = tw.actual_pose(q, force, motion)
    np.testing.assert_array_equal(p_only, p)
    np.testing.assert_array_equal(u_only, u)
    np.testing.assert_array_equal(tw.axis_jacobian(q, force, motion), J)
    p_nom, u_nom = tw.nominal_pose(q)
    p_kin, u_kin = forward_nominal(m, q)
    np.testing.assert_allclose(p_nom, p_kin, rtol=0, atol=1e-12)
    np.testing.assert_allclose(u_nom, u_kin, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["nmv1500dcg", "headtable", "lathe"])
def test_compiled_axis_jacobian_matches_central_differences(name):
    # nmv1500dcg: the post's five-axis machine; headtable: a rotary head, whose reference point moves with its angle;
    # lathe: response surfaces, whose bed deflection depends on the position.
    m = every_parameter_non_zero(name)
    tw = ErrorTwin(m)
    n = 200
    q = random_poses(m, n, seed=13)
    force, motion = load(m, n, seed=14)
    p, _, J = tw.pose_and_axis_jacobian(q, force, motion)
    lever = np.abs(p).max()
    for j, axis in enumerate(m.axis_names):
        h = 1e-6 if m.axes[axis].is_rotary else 1e-5
        qp, qm = q.copy(), q.copy()
        qp[:, j] += h
        qm[:, j] -= h
        fd = (np.hstack(tw.actual_pose(qp, force, motion)) - np.hstack(tw.actual_pose(qm, force, motion))) / (2 * h)
        # Round-off of a central difference, 1e-16 x |p| / h, dominates the h^2 truncation (1e-12 x the third
        # derivative, about |p| for a rotary axis).
        np.testing.assert_allclose(J[:, :, j], fd, rtol=0, atol=4 * 2.2e-16 * lever / h, err_msg=f"axis {axis}")
