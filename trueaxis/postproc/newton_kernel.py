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
