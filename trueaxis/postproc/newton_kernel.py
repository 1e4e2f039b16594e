"""The compensation's Gauss-Newton step, pose by pose, compiled with numba.

Why hand-written: the step is a handful of products of small matrices per pose (the weighted residual, the weighted
Jacobian, its normal equations and their solve: 6 x 5 at most). In numpy each is an operation on an (n, k, k) stack
plus a LAPACK call per pose in ``numpy.linalg.solve``, and the per-call overhead and temporaries cost far more than
the arithmetic (about 1 s of a million-block five-axis post). Here the whole step is one loop over a small workspace.

The numbers are those of ``solver.solve_commanded``'s numpy form up to rounding (the order of the sums, and LU with
partial pivoting in place of LAPACK's): the step is a difference of micrometres on positions of hundreds of mm, so the
commanded axes agree to about 1e-14 mm, eight orders of magnitude below the written digits.
"""

from __future__ import annotations

from ..compiled import numba  # numba, or the kernels compiled ahead of time (see ..compiled)
from ..machine.chain_kernel import _chain_rows
from ..machine.error_kernel import _evaluate_rows
import numpy as np

_jit = numba.njit(cache=True)


@_jit
def gauss_newton_step(qa, p, u, p_nom, u_nom, M, Ja, free, q_out):
    """q_out[i] = qa[i] - x_i, x_i solving (J_i^T J_i + H_i) x = J_i^T r_i per pose (n poses, k axes).

    qa (n, k) mm/rad: the poses.  p, u (n, 3): actual tip mm, unit tool axis at qa.  p_nom, u_nom (n, 3): the nominal
    pose matched.  M (m, 6): the rows matched (position directions, tool-axis rows weighted), m <= 6.
    Ja (n, 6, k): d(tip, axis)/d(axes) at qa.  free (n, k) bool: axes not held; J_i = (M Ja_i) with the held axes'
    columns zero, H_i the unit diagonal of the held axes (their step is zero).
    Returns the number of poses whose normal equations are singular (their row of q_out is left as qa).
    """
    return _step_rows(qa, p, u, p_nom, u_nom, M, Ja, free, q_out)


@_jit
def _step_rows(qa, p, u, p_nom, u_nom, M, Ja, free, q_out):
    """``gauss_newton_step``'s work, for kernels that call it (``solve_unloaded``)."""
    n, k = qa.shape
    m = M.shape[0]
    e = np.empty(6)
    r = np.empty(m)
    J = np.empty((m, k))
    A = np.empty((k, k))
    b = np.empty(k)
    singular = 0
    for i in range(n):
        for c in range(3):
            e[c] = p[i, c] - p_nom[i, c]
            e[3 + c] = u[i, c] - u_nom[i, c]
        for a in range(m):
            s = 0.0
            for c in range(6):
                s += e[c] * M[a, c]
            r[a] = s
            for j in range(k):
                if free[i, j]:
                    s = 0.0
                    for c in range(6):
                        s += M[a, c] * Ja[i, c, j]
                    J[a, j] = s
                else:
                    J[a, j] = 0.0
        for j in range(k):
            for l in range(j, k):
                s = 0.0
                for a in range(m):
                    s += J[a, j] * J[a, l]
                A[j, l] = s
                A[l, j] = s
            if not free[i, j]:
                A[j, j] += 1.0
            s = 0.0
            for a in range(m):
                s += J[a, j] * r[a]
            b[j] = s
        if _solve_in_place(A, b, k):
            for j in range(k):
                q_out[i, j] = qa[i, j] - b[j]
        else:
            singular += 1
            for j in range(k):
                q_out[i, j] = qa[i, j]
    return singular


@_jit
def _solve_in_place(A, b, k):
    """Solve A x = b (k x k) by Gaussian elimination with partial pivoting, x into b; False when a pivot is 0."""
    for col in range(k):
        piv = col
        big = abs(A[col, col])
        for row in range(col + 1, k):
            if abs(A[row, col]) > big:
                big = abs(A[row, col])
                piv = row
        if big == 0.0:
            return False
        if piv != col:
            for c in range(col, k):
                A[col, c], A[piv, c] = A[piv, c], A[col, c]
            b[col], b[piv] = b[piv], b[col]
        d = A[col, col]
        for row in range(col + 1, k):
            f = A[row, col] / d
            if f != 0.0:
                for c in range(col + 1, k):
                    A[row, c] -= f * A[col, c]
                b[row] -= f * b[col]
    for row in range(k - 1, -1, -1):
        s = b[row]
        for c in range(row + 1, k):
            s -= A[row, c] * b[c]
        b[row] = s / A[row, row]
    return True


# Poses per block of ``solve_unloaded``: its work arrays stay in cache.
SOLVE_BLOCK = 256


@_jit
def solve_unloaded(q0, p_nom, u_nom, free, M, orientation, tol_um, tol_urad, max_iter, column, rotary, tool,
                   direction, pivot, origin, bed_at, tilt, offset, zero, d_act, bed, dbed, groups, grid, members, coef,
                   scale, zero_slots, n_harmonics, q_out, p_out, u_out, pos_out, ax_out, info):
    """``solver.solve_commanded`` of unloaded poses on a mill (every tip direction corrected), whole: per pose the
    component errors (``error_kernel``), the chain and its axis Jacobian (``chain_kernel``), the residual's check and
    the Newton step, until the pose is within tolerance or ``max_iter`` steps are taken; the same operations on the
    same numbers as the numpy driver's, with no array per step between them.

    q0 (n, k): the nominal poses, from which the solve starts; p_nom, u_nom (n, 3) their nominal tip and axis; free
    (n, k) bool, M (m, 6), orientation, tol_um, tol_urad, max_iter: as ``solve_commanded`` takes them; then the chain's
    layout and unloaded values (``chain_kernel``: column .. d_act, bed (1, 3), dbed (1, 3, k)) and the packed component
    functions (``error_kernel.evaluate_packed``: groups .. n_harmonics).
    Out: q_out (n, k) commanded poses, p_out, u_out (n, 3) the actual pose there, pos_out (n,) um and ax_out (n,) urad
    the residuals' norms; info (2,) int64: the most Newton steps a pose took, and the number of singular steps (a pose
    whose normal equations have no unique solution: its step is not taken)."""
    n, k = q0.shape
    n_links = column.shape[0]
    info[0] = 0
    info[1] = 0
    for i0 in range(0, n, SOLVE_BLOCK):
        i1 = min(n, i0 + SOLVE_BLOCK)
        todo = np.arange(i0, i1)
        qa = q0[i0:i1].copy()
        it = 0
        J = np.zeros((qa.shape[0], 6, k))
        tip, axis = _poses_of(qa, True, J, n_links, column, rotary, tool, direction, pivot, origin, bed_at, tilt,
                              offset, zero, d_act, bed, dbed, groups, grid, members, coef, scale, zero_slots,
                              n_harmonics)
        while True:
            m = todo.shape[0]
            keep = np.zeros(m, np.bool_)
            n_keep = 0
            for r in range(m):
                g = todo[r]
                dx, dy, dz = tip[r, 0] - p_nom[g, 0], tip[r, 1] - p_nom[g, 1], tip[r, 2] - p_nom[g, 2]
                ux, uy, uz = axis[r, 0] - u_nom[g, 0], axis[r, 1] - u_nom[g, 1], axis[r, 2] - u_nom[g, 2]
                # (numpy's norm of a row of three: the squares summed left to right)
                pos_out[g] = np.sqrt(dx * dx + dy * dy + dz * dz) * 1e3
                ax_out[g] = np.sqrt(ux * ux + uy * uy + uz * uz) * 1e6
                done = pos_out[g] <= tol_um
                if orientation:
                    all_free = True
                    for j in range(k):
                        all_free = all_free and free[g, j]
                    done = done and (ax_out[g] <= tol_urad or not all_free)
                if done or it == max_iter:
                    for j in range(k):
                        q_out[g, j] = qa[r, j]
                    for j in range(3):
                        p_out[g, j] = tip[r, j]
                        u_out[g, j] = axis[r, j]
                if not done:
                    keep[r] = True
                    n_keep += 1
            if it == max_iter or n_keep == 0:
                break
            it += 1
            sel = np.nonzero(keep)[0]
            rows = todo[sel]
            qk = qa[sel]
            if it > 1:  # the Jacobian of the poses going on (the first step's came with its poses)
                J = np.zeros((sel.shape[0], 6, k))
                _poses_of(qk, True, J, n_links, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset,
                          zero, d_act, bed, dbed, groups, grid, members, coef, scale, zero_slots, n_harmonics)
            else:
                J = J[sel]
            qa = np.empty_like(qk)
            info[1] += _step_rows(qk, tip[sel], axis[sel], p_nom[rows], u_nom[rows], M, J, free[rows], qa)
            todo = rows
            # the pose alone at the new commanded axes (most are within tolerance now: no Jacobian for them)
            tip, axis = _poses_of(qa, False, np.empty((0, 6, k)), n_links, column, rotary, tool, direction, pivot,
                                  origin, bed_at, tilt, offset, zero, d_act, bed, dbed, groups, grid, members, coef,
                                  scale, zero_slots, n_harmonics)
        info[0] = max(info[0], it)


@_jit
def _poses_of(q, deriv, J, n_links, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset, zero, d_act,
              bed, dbed, groups, grid, members, coef, scale, zero_slots, n_harmonics):
    """Actual tip (m, 3) and unit axis (m, 3) at the unloaded poses q (m, k), and with ``deriv`` their axis Jacobian
    into J (m, 6, k), zeros on entry: the component errors, then the chain (``ErrorTwin._compose``'s kernels)."""
    m = q.shape[0]
    val = np.empty((n_links, m, 6))
    dval = np.empty((n_links, m, 6)) if deriv else val
    _evaluate_rows(q, groups, grid, members, coef, scale, zero_slots, n_harmonics, deriv, val, dval)
    tip, axis = np.empty((m, 3)), np.empty((m, 3))
    _chain_rows(0, m, q, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset, zero, d_act, val, bed,
                dval, dbed, deriv, tip, axis, J)
    return tip, axis
