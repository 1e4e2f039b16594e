"""The compensation's compiled Gauss-Newton step against its numpy form (batched matmul and LAPACK's solve), on the
twin's own Jacobians: a three-axis mill, a five-axis table with held axes (the singular cone's free axis), a lathe."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import MACHINES
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.postproc.solver import (corrected_directions, gauss_newton_step_numpy, gauss_newton_step_of,
                                      solve_commanded)


def _case(name, n, seed):
    m = load_machine(MACHINES / f"{name}.toml")
    twin = ErrorTwin(m)
    rng = np.random.default_rng(seed)
    lo = np.array([m.axes[a].travel[0] if m.axes[a].travel else -1.0 for a in m.axis_names])
    hi = np.array([m.axes[a].travel[1] if m.axes[a].travel else 1.0 for a in m.axis_names])
    q = lo + (hi - lo) * (0.2 + 0.6 * rng.random((n, len(lo))))
    p, u, Ja = twin.pose_and_axis_jacobian(q)
    # the nominal pose matched: where the nominal chain puts slightly other axes (a step of microns to undo)
    p_nom, u_nom = twin.nominal_pose(q + 1e-3 * rng.standard_normal(q.shape))
    B = corrected_directions(m)
    rot = bool(m.rotary_axes)
    M = np.zeros((B.shape[0] + (3 if rot else 0), 6))
    M[: B.shape[0], :3] = B
    if rot:
        M[B.shape[0]:, 3:] = 100.0 * np.eye(3)
    free = np.ones(q.shape, bool)
    if rot:  # every fifth pose holds its outer rotary axis (as at the singular cone)
        free[::5, -1] = False
    return q, p, u, p_nom, u_nom, M, Ja, free


@pytest.mark.parametrize("name", ["xh714", "nmv1500dcg", "lathe"])
def test_the_compiled_step_is_the_numpy_step_up_to_rounding(name):
    q, p, u, p_nom, u_nom, M, Ja, free = _case(name, 400, 7)
    step_c = gauss_newton_step_of(q, p, u, p_nom, u_nom, M, Ja, free)
    step_n = gauss_newton_step_numpy(q, p, u, p_nom, u_nom, M, Ja, free)
    moved = np.abs(step_n - q)
    assert moved.max() > 1e-4  # a step of microns (or microradians): the comparison sees one
    # the same step to rounding: a solve's rounding error is bounded by about cond(A) * eps * |x| (the normal
    # equations' condition number; the weighted tool-axis rows make it large on five axes), both ways
    J = (M @ Ja) * free[:, None, :]
    A = J.transpose(0, 2, 1) @ J + np.apply_along_axis(np.diag, 1, (~free).astype(float))
    bound = 4 * np.linalg.cond(A) * np.finfo(float).eps * np.abs(step_n - q).max(axis=1)
    diff = np.abs(step_c - step_n).max(axis=1)
    assert np.all(diff <= bound + 1e-15), (diff / bound).max()
    assert diff.max() < 1e-9  # mm or rad: three orders of magnitude below the written 1e-6 mm
    # held axes do not move, bit for bit
    assert np.array_equal(step_c[~free], q[~free])


def test_a_singular_step_is_refused_not_returned():
    q, p, u, p_nom, u_nom, M, Ja, free = _case("xh714", 3, 1)
    Ja = Ja.copy()
    Ja[1] = 0.0  # no axis moves the tip at pose 1: the normal equations have no solution
    with pytest.raises(np.linalg.LinAlgError):
        gauss_newton_step_of(q, p, u, p_nom, u_nom, M, Ja, free)
    with pytest.raises(np.linalg.LinAlgError):
        gauss_newton_step_numpy(q, p, u, p_nom, u_nom, M, Ja, free)


def test_the_solve_still_lands_on_the_nominal_pose():
    # the whole Newton loop with the compiled step: the actual pose at the commanded axes is the nominal pose at the
    # nominal axes, to the solver's tolerance, checked with the twin's actual pose (an evaluation of its own)
    m = load_machine(MACHINES / "nmv1500dcg.toml")
    twin = ErrorTwin(m)
    q, *_ = _case("nmv1500dcg", 300, 3)
    res = solve_commanded(twin, q)
    assert res.converged.all()
    pa, ua = twin.actual_pose(res.q)
    pn, un = twin.nominal_pose(q)
    assert np.linalg.norm(pa - pn, axis=1).max() * 1e3 <= 0.01
    assert np.linalg.norm(ua - un, axis=1).max() * 1e6 <= 0.1
    assert np.abs(res.q - q).max() > 1e-3  # the errors are tens of um: the check can fail


class _LoopTwin:
    """The twin without ``unloaded_kernel_args``: ``solve_commanded`` takes its numpy loop (the reference of the
    compiled ``solve_unloaded``), the twin's own kernels for each pose and Jacobian."""

    def __init__(self, twin):
        self._twin, self.machine = twin, twin.machine

    def nominal_pose(self, q):
        return self._twin.nominal_pose(q)

    def actual_pose(self, q, force_n=None, motion=None):
        return self._twin.actual_pose(q, force_n, motion)

    def pose_and_axis_jacobian(self, q, force_n=None, motion=None):
        return self._twin.pose_and_axis_jacobian(q, force_n, motion)


@pytest.mark.parametrize("name", ["xh714", "nmv1500dcg", "ac_trunnion", "headtable"])
@pytest.mark.parametrize("n", [700, 9000])  # (9000: shared among the kernels' threads, with ahead-of-time twins)
def test_the_compiled_solve_is_the_numpy_loop_bit_for_bit(name, n):
    # the whole solve in one kernel (component errors, chain, Jacobian, residual check, Newton step) gives the numbers
    # of the loop that calls the kernels one by one: commanded axes, residuals, poses, the converged flags
    m = load_machine(MACHINES / f"{name}.toml")
    twin = ErrorTwin(m)
    q, *_ = _case(name, n, 11)
    q = q + (np.random.default_rng(5).random(q.shape) - 0.5) * 0.5  # (not only the travel's middle)
    hold = np.zeros(q.shape, bool)
    rot = [m.axis_names.index(a) for a in m.rotary_axes]
    if rot:
        hold[::7, rot[0]] = True  # the singular cone's free axis held, as the post holds it
    for orientation in ([True, False] if rot else [False]):
        h = hold.copy()
        if not orientation:
            h[:, rot] = True  # (the post's rotary axes without rotary words: held)
        fused = solve_commanded(twin, q, orientation=orientation, hold=h)
        loop = solve_commanded(_LoopTwin(twin), q, orientation=orientation, hold=h)
        assert fused.converged.all() and loop.converged.all()
        assert np.abs(fused.q - q).max() > 1e-3  # errors of tens of um corrected: a solve that did nothing would fail
        for a, b in [(fused.q, loop.q), (fused.position_residual_um, loop.position_residual_um),
                     (fused.axis_residual_urad, loop.axis_residual_urad), (fused.converged, loop.converged),
                     *zip(fused.actual, loop.actual), *zip(fused.nominal, loop.nominal)]:
            assert np.array_equal(a, b)
        assert fused.iterations == loop.iterations >= 1


def test_the_compiled_solve_says_a_pose_it_cannot_solve():
    # a pose whose axes are all held cannot be moved onto its nominal pose: after max_iter steps it is reported not
    # converged, with its residual, as the numpy loop reports it (the post refuses the block then)
    m = load_machine(MACHINES / "xh714.toml")
    twin = ErrorTwin(m)
    q, *_ = _case("xh714", 5, 2)
    hold = np.zeros(q.shape, bool)
    hold[2] = True
    fused, loop = solve_commanded(twin, q, hold=hold), solve_commanded(_LoopTwin(twin), q, hold=hold)
    assert fused.converged.tolist() == [True, True, False, True, True] == loop.converged.tolist()
    assert fused.position_residual_um[2] == loop.position_residual_um[2] > 1.0
    assert fused.iterations == loop.iterations == 12
    assert np.array_equal(fused.q, loop.q) and np.array_equal(fused.q[2], q[2])
