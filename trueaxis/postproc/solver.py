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

from ..machine.twin import ErrorTwin


@dataclass
class SolveResult:
    """q : (N, n_axes) commanded axes (mm, rad).  position_residual_um / axis_residual_urad : (N,) norms of the
    remaining pose error. iterations : Newton steps taken. converged : (N,) bool."""

    q: np.ndarray
    position_residual_um: np.ndarray
    axis_residual_urad: np.ndarray
    iterations: int
    converged: np.ndarray


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
) -> SolveResult:
    """Commanded axes q* with actual(q*) = nominal(q_nominal), per pose.

    q_nominal : (N, n_axes) mm/rad.  force_n : (N,3) or (3,) N, the force on the tool while the pose is cut.
    orientation : match the tool axis too (default: when the machine has rotary axes).
    hold : (N, n_axes) bool, axes held at their nominal value (the free axis at a singular pose).
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
    q = q0.copy()
    it = 0
    # One twin pass per iteration: the pose and axis Jacobian at q serve both the convergence check of the previous
    # step and the next step (the pose is the same numbers actual_pose gives).
    p, u, Ja = twin.pose_and_axis_jacobian(q, force_n, motion)
    pos_err = ax_err = None
    for it in range(1, max_iter + 1):
        r = np.hstack([p - p_nom, u - u_nom]) @ M.T
        J = np.einsum("rs,nsi->nri", M, Ja)
        J = J * free[:, None, :]
        # Normal equations, batched; held axes get a unit diagonal so their step is zero.
        A = np.einsum("nri,nrj->nij", J, J) + np.einsum("ni,ij->nij", ~free, np.eye(k))
        b = np.einsum("nri,nr->ni", J, r)
        q = q - np.linalg.solve(A, b[..., None])[..., 0]
        p, u = twin.actual_pose(q, force_n, motion)
        pos_err, ax_err = _pose_residuals(p, u, p_nom, u_nom, B)
        if np.all(pos_err <= tol_um) and (not orientation or np.all((ax_err <= tol_urad) | ~free.all(1))):
            break
        if it < max_iter:
            Ja = twin.axis_jacobian(q, force_n, motion)
    if pos_err is None:
        pos_err, ax_err = _residuals(twin, q, p_nom, u_nom, force_n, motion, B)
    ok = pos_err <= tol_um
    if orientation:
        ok &= (ax_err <= tol_urad) | ~free.all(1)
    return SolveResult(q=q, position_residual_um=pos_err, axis_residual_urad=ax_err, iterations=it, converged=ok)


def corrected_directions(machine) -> np.ndarray:
    """(d, 3) orthonormal rows: the tool-tip directions the machine's linear axes move along, the ones the post can
    correct. All three on a mill; X and Z on a two-axis lathe, whose error normal to the XZ plane (along the turned
    surface) changes the turned radius only at second order, (dy)^2 / 2r."""
    dirs = np.array([machine.axes[a].direction for a in machine.axis_names if not machine.axes[a].is_rotary], float)
    if dirs.shape[0] >= 3:
        return np.eye(3)
    basis, _ = np.linalg.qr(dirs.T)
    return basis.T


def _residuals(twin, q, p_nom, u_nom, force_n, motion, B=None):
    p, u = twin.actual_pose(q, force_n, motion)
    return _pose_residuals(p, u, p_nom, u_nom, B)


def _pose_residuals(p, u, p_nom, u_nom, B=None):
    dp = p - p_nom if B is None else (p - p_nom) @ B.T
    return np.linalg.norm(dp, axis=1) * 1e3, np.linalg.norm(u - u_nom, axis=1) * 1e6
