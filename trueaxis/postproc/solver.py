"""Compensation: the commanded axes q* whose actual pose is the nominal pose of q.

Newton's method on the twin, all poses at once (DESIGN §5). The first step is the differential-motion-matrix
compensation of the paper (q* = q - J^+ e, with J the axis Jacobian and e the volumetric error); the following Newton
steps remove what the first-order step leaves, until the actual pose matches the nominal pose within the tolerance.

Three-axis machines match the tool-tip position (3 equations, 3 axes); a two-axis lathe matches it in the XZ plane
of its axes (``corrected_directions``). Five-axis machines match the tip and the tool
axis (6 equations, of which 5 independent since the axis is a unit vector, 5 axes): a weighted Gauss-Newton step,
orientation rows scaled by ``orientation_weight_mm`` so that 1 urad weighs like 1 um at that lever arm. At a
singular pose (``hold`` mask) the free axis is held at its nominal value and the others do what they can: the tip is
still matched, the tool axis only in the direction the remaining rotary axis can turn it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..compiled import run_twins, thread_slices
from ..machine.twin import ErrorTwin
from .newton_kernel import gauss_newton_step, solve_unloaded


# A Newton step evaluates the pose alone first, and the Jacobian of the poses not converged after it, where the caller's
# last solve left fewer than this share of its poses not converged at that step (the pose kernel costs about 2/3 of
# the pose-and-Jacobian kernel).
LEAN_BELOW = 0.3


@dataclass
class SolveResult:
    """q : (N, n_axes) commanded axes (mm, rad).  position_residual_um / axis_residual_urad : (N,) norms of the
    remaining pose error. iterations : Newton steps taken. converged : (N,) bool. actual : (tip (N, 3) mm, unit axis
    (N, 3)), the twin's actual pose at q (the last Newton pass computed it; the same numbers ``actual_pose`` gives).
    nominal : (tip, unit axis), the nominal pose of q_nominal."""

    q: np.ndarray
    position_residual_um: np.ndarray
    axis_residual_urad: np.ndarray
    iterations: int
    converged: np.ndarray
    actual: tuple = ()
    nominal: tuple = ()


def solve_commanded(
    twin: ErrorTwin,
    q_nominal,
    force_n=None,
    motion=None,
    *,
    orientation: bool | None = None,
    hold: np.ndarray | None = None,
    tol_um: float = 0.01,
    tol_urad: float = 0.1,
    max_iter: int = 12,
    orientation_weight_mm: float = 100.0,
    hint: dict | None = None,
) -> SolveResult:
    """Commanded axes q* with actual(q*) = nominal(q_nominal), per pose.

    q_nominal : (N, n_axes) mm/rad.  force_n : (N,3) or (3,) N, the force on the tool while the pose is cut.
    orientation : match the tool axis too (default: when the machine has rotary axes).
    hold : (N, n_axes) bool, axes held at their nominal value (the free axis at a singular pose).
    hint : a dict the caller keeps from solve to solve (or None): the share of poses still not converged after each
    Newton step, which decides where the next solve evaluates the pose alone before the Jacobian (speed only: the
    numbers are the same either way).
    """
    m = twin.machine
    q0 = np.atleast_2d(np.asarray(q_nominal, dtype=float))
    n, k = q0.shape
    if orientation is None:
        orientation = len(m.rotary_axes) > 0
    p_nom, u_nom = twin.nominal_pose(q0)
    # Rows matched: the position along the directions the linear axes can correct, then (five-axis) the tool axis
    # weighted so that 1 urad counts like 1 um at orientation_weight_mm.
    B = corrected_directions(m)
    d = B.shape[0]
    M = np.zeros((d + (3 if orientation else 0), 6))
    M[:d, :3] = B
    if orientation:
        M[d:, 3:] = np.eye(3) * orientation_weight_mm
    free = np.ones((n, k), bool) if hold is None else ~np.asarray(hold, bool)
    if force_n is None and motion is None and d == 3 and np.array_equal(B, np.eye(3)) \
            and hasattr(twin, "unloaded_kernel_args"):
        return _solve_unloaded(twin, q0, (p_nom, u_nom), free, M, orientation, (tol_um, tol_urad), max_iter)
    q = q0.copy()
    pos_err = np.empty(n)
    ax_err = np.empty(n)
    p_act, u_act = np.empty((n, 3)), np.empty((n, 3))
    # Newton on the poses not yet converged only (most converge after the first, differential-motion step); one twin
    # pass per iteration gives the pose (the convergence check of the previous step) and the Jacobian of the next.
    todo = np.arange(n)
    it = 0
    while True:
        idx = slice(None) if it == 0 else todo  # (the first step takes every pose: views, not copies)
        qa = q[idx]
        f_todo, m_todo = _rows(force_n, idx, n), _rows(motion, idx, n)
        # The pose alone first (the twin's pose kernel: the same numbers as the pose the Jacobian's kernel gives)
        # where most poses are expected to converge at this step: the Jacobian is then computed for the others only.
        lean = it > 0 and hint is not None and hint.get(it, 0.0) < LEAN_BELOW
        if lean:
            p, u = twin.actual_pose(qa, f_todo, m_todo)
        else:
            p, u, Ja = twin.pose_and_axis_jacobian(qa, f_todo, m_todo)
        pos_err[idx], ax_err[idx] = _pose_residuals(p, u, p_nom[idx], u_nom[idx], B)
        fr = free[idx]
        done = pos_err[idx] <= tol_um
        if orientation:
            done &= (ax_err[idx] <= tol_urad) | ~fr.all(1)
        keep = ~done
        if hint is not None and todo.size:
            hint[it] = float(np.count_nonzero(keep)) / todo.size
        if it == max_iter or not keep.any():
            p_act[idx], u_act[idx] = p, u
            break
        p_act[todo[done]], u_act[todo[done]] = p[done], u[done]
        it += 1
        if not done.any():
            pass  # every pose goes on (the first step, as a rule): the arrays as they are, not copied
        elif lean:
            todo, qa, p, u, fr = todo[keep], qa[keep], p[keep], u[keep], fr[keep]
        else:
            todo, qa, p, u, Ja, fr = todo[keep], qa[keep], p[keep], u[keep], Ja[keep], fr[keep]
        if lean:
            Ja = twin.pose_and_axis_jacobian(qa, _rows(force_n, todo, n), _rows(motion, todo, n))[2]
        on = slice(None) if todo.size == n else todo  # (todo is every pose in order: views, not copies)
        q[todo] = gauss_newton_step_of(qa, p, u, p_nom[on], u_nom[on], M, Ja, fr)
    ok = pos_err <= tol_um
    if orientation:
        ok &= (ax_err <= tol_urad) | ~free.all(1)
    return SolveResult(q=q, position_residual_um=pos_err, axis_residual_urad=ax_err, iterations=it, converged=ok,
                       actual=(p_act, u_act), nominal=(p_nom, u_nom))


def _solve_unloaded(twin, q0, nominal, free, M, orientation, tol, max_iter) -> SolveResult:
    """``solve_commanded`` of unloaded poses on a mill, by the compiled ``solve_unloaded`` (the same numbers as the
    loop above, which stays for loads and lathes): many poses in contiguous shares on the kernels' threads (its
    ahead-of-time twin releases the GIL), each pose solved alone."""
    n, k = q0.shape
    c = np.ascontiguousarray
    q0, p_nom, u_nom, free, M = c(q0, float), c(nominal[0], float), c(nominal[1], float), c(free, bool), c(M, float)
    q, p, u, pos, ax = np.empty((n, k)), np.empty((n, 3)), np.empty((n, 3)), np.empty(n), np.empty(n)
    chain = twin.unloaded_kernel_args()
    fixed = (M, bool(orientation), float(tol[0]), float(tol[1]), int(max_iter), *chain)

    def call(sl):
        return (q0[sl], p_nom[sl], u_nom[sl], free[sl], *fixed, q[sl], p[sl], u[sl], pos[sl], ax[sl],
                np.zeros(2, np.int64))

    calls = [call(sl) for sl in thread_slices(n)] or [call(slice(None))]
    if len(calls) == 1 or run_twins(solve_unloaded, calls) is None:
        for args in calls:
            solve_unloaded(*args)
    if any(args[-1][1] for args in calls):
        raise np.linalg.LinAlgError("Singular matrix: a pose's Newton step has no unique solution")
    ok = pos <= tol[0]
    if orientation:
        ok &= (ax <= tol[1]) | ~free.all(1)
    return SolveResult(q=q, position_residual_um=pos, axis_residual_urad=ax,
                       iterations=max(int(args[-1][0]) for args in calls), converged=ok, actual=(p, u),
                       nominal=(p_nom, u_nom))


def gauss_newton_step_of(qa, p, u, p_nom, u_nom, M, Ja, free) -> np.ndarray:
    """(n, k) the poses qa after one weighted Gauss-Newton step: qa - x, (J^T J + H) x = J^T r per pose, with
    r = M [p - p_nom; u - u_nom], J = M Ja with the held axes' columns zero and H their unit diagonal (their step is
    zero). Compiled (``newton_kernel``); :func:`gauss_newton_step_numpy` is the same in numpy, its reference."""
    c = np.ascontiguousarray
    out = np.empty(qa.shape)
    if gauss_newton_step(c(qa, float), c(p, float), c(u, float), c(p_nom, float), c(u_nom, float), c(M, float),
                         c(Ja, float), c(free, bool), out):
        raise np.linalg.LinAlgError("Singular matrix: a pose's Newton step has no unique solution")
    return out


def gauss_newton_step_numpy(qa, p, u, p_nom, u_nom, M, Ja, free) -> np.ndarray:
    """:func:`gauss_newton_step_of` on stacks of small matrices (numpy's batched matmul and LAPACK's solve): the
    reference the compiled step is checked against (it was the solver's own step)."""
    k = qa.shape[1]
    r = np.hstack([p - p_nom, u - u_nom]) @ M.T
    J = (M @ Ja) * free[:, None, :]
    Jt = J.transpose(0, 2, 1)
    A = Jt @ J  # (a new C-ordered stack: its diagonals are every (k + 1)-th element of a row of k * k)
    A.reshape(A.shape[0], k * k)[:, :: k + 1] += ~free
    b = Jt @ r[..., None]
    return qa - np.linalg.solve(A, b)[..., 0]


def _rows(arr, idx, n):
    """Rows ``idx`` of a per-pose array (n, ...), or the array itself when it is shared by all poses (or None)."""
    if arr is None:
        return None
    a = np.asarray(arr, dtype=float)
    return a[idx] if a.ndim == 2 and a.shape[0] == n else a


def corrected_directions(machine) -> np.ndarray:
    """(d, 3) orthonormal rows: the tool-tip directions the machine's linear axes move along, the ones the post can
    correct. All three on a mill; X and Z on a two-axis lathe, whose error normal to the XZ plane (along the turned
    surface) changes the turned radius only at second order, (dy)^2 / 2r."""
    dirs = np.array([machine.axes[a].direction for a in machine.axis_names if not machine.axes[a].is_rotary], float)
    if dirs.shape[0] >= 3:
        return np.eye(3)
    basis, _ = np.linalg.qr(dirs.T)
    return basis.T


def _pose_residuals(p, u, p_nom, u_nom, B=None):
    dp = p - p_nom if B is None else (p - p_nom) @ B.T
    return np.linalg.norm(dp, axis=1) * 1e3, np.linalg.norm(u - u_nom, axis=1) * 1e6
