"""The error twin's kinematic chain composed pose by pose, compiled with numba.

Why hand-written: the actual pose is a product of about a dozen small factors per pose (the part placement, two per
axis, the bed deflection). In numpy every factor is a handful of operations on (n, 3, 3) stacks, and with 3x3 matrices
the per-call overhead and the temporaries cost far more than the arithmetic. Here each pose's chain is built and
composed in compiled loops over a small workspace.

This module is pure maths on arrays. The twin (``twin.ErrorTwin``) evaluates the error values (the component functions
compiled too, by ``error_kernel``; it knows the loaded-set blend, compliance and response surfaces) and passes them in
per pose; the formulas
are those of ``ErrorTwin._evaluate``, which stays the reference and computes the parameter Jacobian. Per pose, with L
links in chain order (workpiece branch from the part to the bed, then the tool branch outwards):

    T = P^-1 . [workpiece links: F_k E_k] . B . [tool links: E_k F_k]

* P^-1 = (I, -origin): the part placement. B = (I, bed): the bed deflection, before the first tool-branch link.
* F_k, rotary: L G(q + z) L^-1 with L p = (I + [eps]x)(p - c) + c + off (tilt eps, offset off, pivot c, zero offset z)
  and G the turn by q + z about the line through c along the axis direction; L^-1 is exact, in closed form.
  F_k, linear: (I, q d_act), the axis moving along its actual (squareness-turned) direction d_act.
* E_k = (I + [e]x, delta - e x r): the axis' component errors (delta, e) at its reference point r: for a tool-branch
  link the tool tip moved by the link's nominal motion alone, G(q) applied to the origin (computed here), for a
  workpiece-branch link the origin.

The tool tip is T applied to the origin, the tool axis T's rotation applied to +z, normalised (the small-angle factors
are not exactly orthonormal). Units: mm and rad; derivatives per mm or rad of the axis.

Arguments shared by the kernels (n poses, L links, n_axes columns of q):

    q          (n, n_axes)  poses
    column     (L,) int     the link's column in q
    rotary     (L,) bool    rotary link (else linear)
    tool       (L,) bool    tool-branch link (else workpiece branch)
    direction  (L, 3)       unit direction of motion / rotation axis, nominal
    pivot      (L, 3) mm    a point of a rotary axis' line (all axes at zero)
    origin     (3,) mm      part origin in the machine frame
    bed_at     int          the bed factor sits before link bed_at (L: after the last link)
    tilt       (L, n, 3)    rad, a rotary link's line tilt eps            (ignored for linear links)
    offset     (L, n, 3)    mm,  a rotary link's line offset               (ignored for linear links)
    zero       (L, n)       rad, a rotary link's zero-angle offset         (ignored for linear links)
    d_act      (L, n, 3)    a linear link's actual direction               (ignored for rotary links)
    comp       (L, n, 6)    component errors (dx, dy, dz mm; ex, ey, ez rad)
    bed        (n, 3) mm    bed deflection

Each of these per-pose inputs may instead have 1 for its pose dimension (n): the same value for every pose (location
errors without a loaded set, the nominal chain's zeros), passed without being repeated.
"""

from __future__ import annotations

from ..compiled import numba  # numba, or the kernels compiled ahead of time (see ..compiled)
import numpy as np

# Inside the per-pose loop, 3-vectors and 3x3 matrices are tuples (3 floats; 9 floats, row-major): the compiled code
# keeps them in registers, with no array views (and their reference counting). The loop (``_chain_rows``) indexes its
# arrays in place and hands only tuples to the helpers, left to LLVM: an array handed to a helper, even one inlined
# into the kernel (numba IR), is reference-counted at each call. The helpers that take arrays (``_store``, ``_row``)
# serve the per-call set-up only. Compiling takes about 10 s, once: cache=True.
_EYE = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
_ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_ZERO3 = (0.0, 0.0, 0.0)
_Z = (0.0, 0.0, 1.0)

# Poses per block of the parallel kernels (numba prange; the twin takes them for PARALLEL_MIN poses and more).
PARALLEL_BLOCK = 1024
_jit = numba.njit(cache=True)
_jit_inline = numba.njit(cache=True, inline="always")


# ------------------------------------------------------------------------------------------- 3-vector and 3x3 ----
@_jit
def _mm(A, B):
    """A B."""
    return (
        A[0] * B[0] + A[1] * B[3] + A[2] * B[6], A[0] * B[1] + A[1] * B[4] + A[2] * B[7],
        A[0] * B[2] + A[1] * B[5] + A[2] * B[8],
        A[3] * B[0] + A[4] * B[3] + A[5] * B[6], A[3] * B[1] + A[4] * B[4] + A[5] * B[7],
        A[3] * B[2] + A[4] * B[5] + A[5] * B[8],
        A[6] * B[0] + A[7] * B[3] + A[8] * B[6], A[6] * B[1] + A[7] * B[4] + A[8] * B[7],
        A[6] * B[2] + A[7] * B[5] + A[8] * B[8],
    )


@_jit
def _mv(A, x):
    """A x."""
    return (A[0] * x[0] + A[1] * x[1] + A[2] * x[2], A[3] * x[0] + A[4] * x[1] + A[5] * x[2],
            A[6] * x[0] + A[7] * x[1] + A[8] * x[2])


@_jit
def _madd(A, s, B):
    """A + s B."""
    return (A[0] + s * B[0], A[1] + s * B[1], A[2] + s * B[2], A[3] + s * B[3], A[4] + s * B[4], A[5] + s * B[5],
            A[6] + s * B[6], A[7] + s * B[7], A[8] + s * B[8])


@_jit
def _skew(v):
    """[v]x: [v]x w = v x w."""
    return (0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0)


@_jit
def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@_jit
def _add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@_jit
def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@_jit_inline
def _vec(arr, i, j, k0):
    """arr[i, j, k0:k0 + 3] of a 3-d array, as a vector."""
    return (arr[i, j, k0], arr[i, j, k0 + 1], arr[i, j, k0 + 2])


@_jit_inline
def _row(arr, i):
    """arr[i, :3] of a 2-d array, as a vector."""
    return (arr[i, 0], arr[i, 1], arr[i, 2])


@_jit_inline
def _store(arr, i, x):
    """arr[i, :len(x)] = x."""
    for j in range(len(x)):
        arr[i, j] = x[j]


# ----------------------------------------------------------------------------------------------- the factors ----
@_jit
def _line_frame(a, c, eps, off):
    """The parts of a rotary link's F = L G L^-1 that do not depend on its angle: RL, tL, RLi, tLi (L and L^-1) and
    K = [a]x, K K. (Computed once per kernel call where the location errors are the same for every pose: the same
    numbers as per pose.)

    a : unit axis; c : pivot (mm); eps : tilt (rad); off : offset (mm).
    """
    # L p = (I + [eps]x)(p - c) + c + off;  L^-1 = ((I - [eps]x + eps eps^T) / (1 + |eps|^2), -L^-1 tL), exact.
    RL = _madd(_EYE, 1.0, _skew(eps))
    tL = _sub(off, _cross(eps, c))
    s = 1.0 + (eps[0] * eps[0] + eps[1] * eps[1] + eps[2] * eps[2])
    RLi = ((1.0 + eps[0] * eps[0]) / s, (eps[2] + eps[0] * eps[1]) / s, (-eps[1] + eps[0] * eps[2]) / s,
           (-eps[2] + eps[1] * eps[0]) / s, (1.0 + eps[1] * eps[1]) / s, (eps[0] + eps[1] * eps[2]) / s,
           (eps[1] + eps[2] * eps[0]) / s, (-eps[0] + eps[2] * eps[1]) / s, (1.0 + eps[2] * eps[2]) / s)
    tLi = _mv(RLi, tL)
    tLi = (-tLi[0], -tLi[1], -tLi[2])
    K = _skew(a)
    return RL, tL, RLi, tLi, K, _mm(K, K)


@_jit_inline
def _store_frame(frames, link, frame):
    """frames[link] = the 42 numbers of a ``_line_frame`` (RL, tL, RLi, tLi, K, K K)."""
    RL, tL, RLi, tLi, K, KK = frame
    for j in range(9):
        frames[link, j] = RL[j]
        frames[link, 12 + j] = RLi[j]
        frames[link, 24 + j] = K[j]
        frames[link, 33 + j] = KK[j]
    for j in range(3):
        frames[link, 9 + j] = tL[j]
        frames[link, 21 + j] = tLi[j]


@_jit
def _located_rotary(q, a, c, eps, off, z, deriv):
    """F = L G(q + z) L^-1 of a rotary link as (R, t), and dF/dq as (dR, dt) (zeros unless deriv).

    a : unit axis; c : pivot (mm); eps : tilt (rad); off : offset (mm); z : zero offset (rad).
    """
    return _turned(q, c, z, _line_frame(a, c, eps, off), deriv)


@_jit
def _turned(q, c, z, frame, deriv):
    """``_located_rotary`` from the link's ``_line_frame``."""
    RL, tL, RLi, tLi, K, KK = frame
    # G(theta) by Rodrigues: R = I + sin K + (1 - cos) K K, t = c - R c, with K = [a]x.
    theta = q + z
    RG = _madd(_madd(_EYE, np.sin(theta), K), 1.0 - np.cos(theta), KK)
    tG = _sub(c, _mv(RG, c))
    # F = (RL RG RLi, RL (RG tLi + tG) + tL)
    R = _mm(_mm(RL, RG), RLi)
    t = _add(_mv(RL, _add(_mv(RG, tLi), tG)), tL)
    if not deriv:
        return R, t, _ZERO9, _ZERO3
    # dF/dq = L G' L^-1 = (RL dRG RLi, RL (dRG tLi + dtG)), with dG/dtheta = ([a]x RG, -[a]x RG c).
    dRG = _mm(K, RG)
    dR = _mm(_mm(RL, dRG), RLi)
    dt = _mv(RL, _sub(_mv(dRG, tLi), _mv(dRG, c)))
    return R, t, dR, dt


@_jit
def _component(delta, e, r, ddelta, de, dr, deriv):
    """E = (I + [e]x, delta - e x r), and dE/dq = ([de]x, ddelta - de x r - e x dr) (zeros unless deriv)."""
    R = _madd(_EYE, 1.0, _skew(e))
    t = _sub(delta, _cross(e, r))
    if not deriv:
        return R, t, _ZERO9, _ZERO3
    return R, t, _skew(de), _sub(_sub(ddelta, _cross(de, r)), _cross(e, dr))


@_jit
def _reference_point(q, a, c, rotary, tool):
    """The component errors' reference point r and dr/dq: G(q) applied to the origin for a tool-branch link (linear:
    q a; rotary: c - R c, R the turn by q about the line through c along a), the origin for a workpiece link."""
    if not tool:
        return _ZERO3, _ZERO3
    if not rotary:
        return (q * a[0], q * a[1], q * a[2]), a
    K = _skew(a)
    RG = _madd(_madd(_EYE, np.sin(q), K), 1.0 - np.cos(q), _mm(K, K))
    dRc = _mv(_mm(K, RG), c)
    return _sub(c, _mv(RG, c)), (-dRc[0], -dRc[1], -dRc[2])


@_jit_inline
def _line_frames(rotary, direction, pivot, tilt, offset):
    """(L, 42): every rotary link's ``_line_frame`` when the location errors are the same for every pose (tilt and
    offset with 1 for their pose dimension), for ``_chain_rows``; else (0, 42): computed pose by pose."""
    n_links = rotary.shape[0]
    shared = tilt.shape[1] == 1 and offset.shape[1] == 1
    frames = np.zeros((n_links if shared else 0, 42))
    if shared:
        for link in range(n_links):
            if rotary[link]:
                _store_frame(frames, link, _line_frame(_row(direction, link), _row(pivot, link),
                                                       _vec(tilt, link, 0, 0), _vec(offset, link, 0, 0)))
    return frames


@_jit
def _unit(u):
    """u / |u| and |u|."""
    norm = np.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    return (u[0] / norm, u[1] / norm, u[2] / norm), norm


# ------------------------------------------------------------------------------------------------- the kernels ----
@numba.njit(cache=True)
def pose(q, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset, zero, d_act, comp, bed):
    """Tool tip (n, 3) mm and unit tool axis (n, 3), part frame (arguments: module docstring)."""
    n, n_axes = q.shape
    tip, axis = np.empty((n, 3)), np.empty((n, 3))
    # No derivatives: comp stands in for dcomp, empty arrays for dbed and J, all unread.
    _chain_rows(0, n, q, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset, zero, d_act, comp, bed,
                comp, np.empty((1, 3, n_axes)), False, tip, axis, np.empty((0, 6, n_axes)))
    return tip, axis


@numba.njit(cache=True, parallel=True)
def pose_parallel(q, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset, zero, d_act, comp, bed):
    """``pose``, the poses in blocks of PARALLEL_BLOCK over the threads: the same numbers (each pose is computed
    alone, by the same operations)."""
    n, n_axes = q.shape
    tip, axis = np.empty((n, 3)), np.empty((n, 3))
    dbed, J = np.empty((1, 3, n_axes)), np.empty((0, 6, n_axes))  # (unread: no derivatives)
    nb = (n + PARALLEL_BLOCK - 1) // PARALLEL_BLOCK
    for b in numba.prange(nb):
        _chain_rows(b * PARALLEL_BLOCK, min(n, (b + 1) * PARALLEL_BLOCK), q, column, rotary, tool, direction, pivot,
                    origin, bed_at, tilt, offset, zero, d_act, comp, bed, comp, dbed, False, tip, axis, J)
    return tip, axis


@numba.njit(cache=True)
def pose_and_axis_jacobian(q, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset, zero, d_act,
                           comp, bed, dcomp, dbed):
    """Tool tip (n, 3) mm, unit tool axis (n, 3) and d(tip, unit axis)/dq (n, 6, n_axes), per mm or rad.

    dcomp (L, n|1, 6) : d comp / dq along the link's own axis.
    dbed (n|1, 3, n_axes) : d bed / dq per q column.
    The tip and axis are the same numbers ``pose`` gives.
    """
    n, n_axes = q.shape
    tip, axis, J = np.empty((n, 3)), np.empty((n, 3)), np.zeros((n, 6, n_axes))
    _chain_rows(0, n, q, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset, zero, d_act, comp,
                bed, dcomp, dbed, True, tip, axis, J)
    return tip, axis, J


@numba.njit(cache=True, parallel=True)
def pose_and_axis_jacobian_parallel(q, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset, zero,
                                    d_act, comp, bed, dcomp, dbed):
    """``pose_and_axis_jacobian``, the poses in blocks of PARALLEL_BLOCK over the threads: the same numbers."""
    n, n_axes = q.shape
    tip, axis, J = np.empty((n, 3)), np.empty((n, 3)), np.zeros((n, 6, n_axes))
    nb = (n + PARALLEL_BLOCK - 1) // PARALLEL_BLOCK
    for b in numba.prange(nb):
        _chain_rows(b * PARALLEL_BLOCK, min(n, (b + 1) * PARALLEL_BLOCK), q, column, rotary, tool, direction, pivot,
                    origin, bed_at, tilt, offset, zero, d_act, comp, bed, dcomp, dbed, True, tip, axis, J)
    return tip, axis, J


@_jit
def _applied(R, t, p, u):
    """The factor (R, t) applied to the point p and to the direction u: (R p + t, R u)."""
    return _add(_mv(R, p), t), _mv(R, u)


@_jit
def _chain_rows(lo, hi, q, column, rotary, tool, direction, pivot, origin, bed_at, tilt, offset, zero, d_act, comp,
                bed, dcomp, dbed, deriv, tip, axis, J):
    """Poses lo..hi-1 (a workspace of their own): the tip and unit axis into ``tip`` and ``axis``; with ``deriv`` the
    axis Jacobian into J (zeros there; ``dcomp`` and ``dbed`` read only then).

    Per pose: the K = 2 L + 2 factors of the chain (P^-1, then the links, workpiece: F E, tool: E F, the bed before
    link bed_at) made from the tool end, each applied to the point and to the axis as soon as it is made (right to
    left: the origin and +z to the tip and the raw axis). With deriv they are kept in chain order, R (K, 9), t (K, 3),
    their d/dq (dR, dt) and the q column each depends on (col; -1: none, the bed's derivative being dbed's), with the
    point and the axis seen on the right of each (p_after, u_after), for the Jacobian's pass from the left.

    The arrays are indexed where they are, not handed to helpers inside the loop: an array handed to an inlined
    helper is reference-counted at each call (numba's NRT_incref / NRT_decref, two thirds of the loop's time when the
    factors were built by helpers taking the arrays); the helpers here take and return tuples."""
    n_links = column.shape[0]
    n_axes = q.shape[1]
    K = 2 * n_links + 2
    R, t, dR, dt = np.empty((K, 9)), np.empty((K, 3)), np.empty((K, 9)), np.empty((K, 3))
    col = np.empty(K, np.int64)
    p_after, u_after = np.empty((K, 3)), np.empty((K, 3))
    frames = _line_frames(rotary, direction, pivot, tilt, offset)  # the rotary links' line frames, or (0, 42)
    shared_frames = frames.shape[0] > 0
    for i in range(lo, hi):
        # Pose i's row of a per-pose input (row 0 where it is shared: 1 for its pose dimension)
        il = i if tilt.shape[1] > 1 else 0
        ic = i if comp.shape[1] > 1 else 0
        ib = i if bed.shape[0] > 1 else 0
        p, u_raw = _ZERO3, _Z
        k = K  # the next factor made is factor k - 1 in chain order
        k_bed = -1
        for link in range(n_links, -1, -1):
            if link < n_links:
                qa = q[i, column[link]]
                a = (direction[link, 0], direction[link, 1], direction[link, 2])
                c = (pivot[link, 0], pivot[link, 1], pivot[link, 2])
                if rotary[link] and shared_frames:
                    frame = ((frames[link, 0], frames[link, 1], frames[link, 2], frames[link, 3], frames[link, 4],
                              frames[link, 5], frames[link, 6], frames[link, 7], frames[link, 8]),
                             (frames[link, 9], frames[link, 10], frames[link, 11]),
                             (frames[link, 12], frames[link, 13], frames[link, 14], frames[link, 15], frames[link, 16],
                              frames[link, 17], frames[link, 18], frames[link, 19], frames[link, 20]),
                             (frames[link, 21], frames[link, 22], frames[link, 23]),
                             (frames[link, 24], frames[link, 25], frames[link, 26], frames[link, 27], frames[link, 28],
                              frames[link, 29], frames[link, 30], frames[link, 31], frames[link, 32]),
                             (frames[link, 33], frames[link, 34], frames[link, 35], frames[link, 36], frames[link, 37],
                              frames[link, 38], frames[link, 39], frames[link, 40], frames[link, 41]))
                    RF, tF, dRF, dtF = _turned(qa, c, zero[link, il], frame, deriv)
                elif rotary[link]:
                    RF, tF, dRF, dtF = _located_rotary(qa, a, c, (tilt[link, il, 0], tilt[link, il, 1],
                                                                  tilt[link, il, 2]),
                                                       (offset[link, il, 0], offset[link, il, 1], offset[link, il, 2]),
                                                       zero[link, il], deriv)
                else:
                    d = (d_act[link, il, 0], d_act[link, il, 1], d_act[link, il, 2])
                    RF, tF, dRF, dtF = _EYE, (qa * d[0], qa * d[1], qa * d[2]), _ZERO9, d
                r, dr = _reference_point(qa, a, c, rotary[link], tool[link])
                delta = (comp[link, ic, 0], comp[link, ic, 1], comp[link, ic, 2])
                e = (comp[link, ic, 3], comp[link, ic, 4], comp[link, ic, 5])
                if deriv:
                    RE, tE, dRE, dtE = _component(delta, e, r, (dcomp[link, ic, 0], dcomp[link, ic, 1],
                                                                 dcomp[link, ic, 2]),
                                                  (dcomp[link, ic, 3], dcomp[link, ic, 4], dcomp[link, ic, 5]), dr,
                                                  True)
                else:
                    RE, tE, dRE, dtE = _component(delta, e, r, _ZERO3, _ZERO3, _ZERO3, False)
                # the link's two factors, the later one in chain order first (tool branch: E F; workpiece: F E)
                for which in range(2):
                    if (which == 0) == tool[link]:
                        Rs, ts, dRs, dts = RF, tF, dRF, dtF
                    else:
                        Rs, ts, dRs, dts = RE, tE, dRE, dtE
                    k -= 1
                    if deriv:
                        for j in range(9):
                            R[k, j] = Rs[j]
                            dR[k, j] = dRs[j]
                        for j in range(3):
                            t[k, j] = ts[j]
                            dt[k, j] = dts[j]
                            p_after[k, j] = p[j]
                            u_after[k, j] = u_raw[j]
                        col[k] = column[link]
                    p, u_raw = _applied(Rs, ts, p, u_raw)
            if link == bed_at:  # the bed, just before link bed_at in chain order
                tB = (bed[ib, 0], bed[ib, 1], bed[ib, 2])
                k -= 1
                k_bed = k
                if deriv:
                    for j in range(9):
                        R[k, j] = _EYE[j]
                    for j in range(3):
                        t[k, j] = tB[j]
                        p_after[k, j] = p[j]
                        u_after[k, j] = u_raw[j]
                    col[k] = -1
                p, u_raw = _applied(_EYE, tB, p, u_raw)
        tP = (-origin[0], -origin[1], -origin[2])  # P^-1, factor 0
        if deriv:
            for j in range(9):
                R[0, j] = _EYE[j]
            for j in range(3):
                t[0, j] = tP[j]
                p_after[0, j] = p[j]
                u_after[0, j] = u_raw[j]
            col[0] = -1
        p, u_raw = _applied(_EYE, tP, p, u_raw)
        u, norm = _unit(u_raw)
        for j in range(3):
            tip[i, j] = p[j]
            axis[i, j] = u[j]
        if not deriv:
            continue
        # d(chain)/dq through factor k: RA (dR_k p_after_k + dt_k) and RA dR_k u_after_k, RA the rotations before k.
        idb = i if dbed.shape[0] > 1 else 0
        RA = _EYE
        for k in range(K):
            cq = col[k]
            if cq >= 0:
                dRk = (dR[k, 0], dR[k, 1], dR[k, 2], dR[k, 3], dR[k, 4], dR[k, 5], dR[k, 6], dR[k, 7], dR[k, 8])
                dp = _mv(RA, _add(_mv(dRk, (p_after[k, 0], p_after[k, 1], p_after[k, 2])),
                                  (dt[k, 0], dt[k, 1], dt[k, 2])))
                du = _mv(RA, _mv(dRk, (u_after[k, 0], u_after[k, 1], u_after[k, 2])))
                for j in range(3):
                    J[i, j, cq] += dp[j]
                    J[i, 3 + j, cq] += du[j]
            elif k == k_bed:
                for c2 in range(n_axes):
                    dp = _mv(RA, (dbed[idb, 0, c2], dbed[idb, 1, c2], dbed[idb, 2, c2]))
                    for j in range(3):
                        J[i, j, c2] += dp[j]
            RA = _mm(RA, (R[k, 0], R[k, 1], R[k, 2], R[k, 3], R[k, 4], R[k, 5], R[k, 6], R[k, 7], R[k, 8]))
        # The unit axis u = raw / |raw|: du = (I - u u^T) d raw / |raw|.
        for c in range(n_axes):
            s = u[0] * J[i, 3, c] + u[1] * J[i, 4, c] + u[2] * J[i, 5, c]
            for j in range(3):
                J[i, 3 + j, c] = (J[i, 3 + j, c] - u[j] * s) / norm
