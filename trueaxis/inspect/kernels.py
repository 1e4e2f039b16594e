"""The inspection's compiled loops: one pass over a million points where numpy makes a dozen.

Why hand-written (numba). ``inspect`` of a 1,000,000-point cloud must be no slower than CloudCompare's C2M run
(issue 19). Two steps spent most of its time in numpy temporaries, not in arithmetic:

- the cone's Gauss-Newton passes (:func:`cone_normal_equations`): numpy built the (n, 6) Jacobian from about fifteen
  (n,)- and (n, 3)-arrays, then J^T J and J^T f, 0.1 s a pass; here each point's residual and Jacobian row are
  formed in registers and summed into the 6 x 6 normal equations at once (about 10 ms a pass);
- the per-point CSV (:func:`csv_rows`): numpy wrote every digit column of every number as a separate array pass and
  then dropped the padding bytes, 0.4 s for a million rows; here each row's bytes are written once.

Both are called with exact types by :mod:`trueaxis.inspect.form` and :mod:`trueaxis.inspect.cloud`, and compiled ahead
of time like the post's kernels (:mod:`trueaxis.compiled`, built by ``python -m trueaxis.warm``), so that ``inspect``
does not import numba; without that build numba's JIT compiles them once into its cache.

The arithmetic is the numpy formulas', per point in the same order; only the sums over the points are accumulated in
another order (sequentially here, pairwise or blocked in numpy and BLAS), which changes the normal equations by
rounding only. The CSV's digits are printf's (``tests/test_cloud.py`` compares them), the bytes those of the
numpy digit loop it replaced (compared once, on a 1,000,000-point report).
"""

from __future__ import annotations

import numpy as np

from ..compiled import numba  # numba, or the kernels compiled ahead of time (see ..compiled)


@numba.njit(cache=True)
def cone_normal_equations(points, base, axis, e1, e2, p1, p2, radius, alpha, residuals, normal, gradient):
    """One Gauss-Newton pass of the cone fit (``form._cone_model``) over all points, without the Jacobian array.

    points : (n, 3) float64, mm. base, axis : (3,) the cone's axis point and unit axis. e1, e2 : (3,) the
    parameterisation's directions normal to its start axis; p1, p2 : (3,) those directions projected normal to the
    axis and divided by the unnormalised axis' length (``project @ e1``, ``project @ e2``). radius : mm on the plane
    through ``base``; alpha : rad, half angle.

    Writes each point's signed distance (mm) into ``residuals`` (n,), J^T J into ``normal`` (6, 6) and J^T f into
    ``gradient`` (6,), J the (n, 6) Jacobian in (u, v, s, t, rho, alpha); returns sum f^2 (mm^2).
    """
    cos, sin = np.cos(alpha), np.sin(alpha)
    ae1 = axis[0] * e1[0] + axis[1] * e1[1] + axis[2] * e1[2]
    ae2 = axis[0] * e2[0] + axis[1] * e2[1] + axis[2] * e2[2]
    acc = np.zeros(27)  # 21 entries of the symmetric J^T J, 6 of J^T f
    cost = 0.0
    row = np.empty(6)
    for i in range(points.shape[0]):
        wx, wy, wz = points[i, 0] - base[0], points[i, 1] - base[1], points[i, 2] - base[2]
        h = wx * axis[0] + wy * axis[1] + wz * axis[2]
        rx, ry, rz = wx - h * axis[0], wy - h * axis[1], wz - h * axis[2]
        r = np.sqrt(rx * rx + ry * ry + rz * rz)
        inv = 1.0 / max(r, 1e-300)
        # the unit radial vector projected on the four directions the parameters move; w on the axis' two
        q0 = (rx * p1[0] + ry * p1[1] + rz * p1[2]) * inv
        q1 = (rx * p2[0] + ry * p2[1] + rz * p2[2]) * inv
        q2 = (rx * e1[0] + ry * e1[1] + rz * e1[2]) * inv
        q3 = (rx * e2[0] + ry * e2[1] + rz * e2[2]) * inv
        w0 = wx * p1[0] + wy * p1[1] + wz * p1[2]
        w1 = wx * p2[0] + wy * p2[1] + wz * p2[2]
        row[0] = -cos * h * q0 - sin * w0
        row[1] = -cos * h * q1 - sin * w1
        row[2] = -cos * q2 + sin * ae1
        row[3] = -cos * q3 + sin * ae2
        row[4] = -cos
        row[5] = -(r - radius) * sin - h * cos
        f = (r - radius) * cos - h * sin
        residuals[i] = f
        cost += f * f
        k = 0
        for a in range(6):
            ra = row[a]
            for b in range(a, 6):
                acc[k] += ra * row[b]
                k += 1
            acc[21 + a] += ra * f
    k = 0
    for a in range(6):
        for b in range(a, 6):
            normal[a, b] = acc[k]
            normal[b, a] = acc[k]
            k += 1
        gradient[a] = acc[21 + a]
    return cost


@numba.njit(cache=True)
def csv_rows(scaled, decimals, codes, names, name_lengths, out):
    """Write CSV rows: each row's integers ``scaled[i, j]`` (a number times 10^decimals[j], rounded) as fixed-point
    decimals separated by commas, then ``,`` and ``names[codes[i]]`` when ``codes`` is not empty, then a newline.

    scaled : (n, k) int64. decimals : (k,) int64, 0..18. codes : (n,) int64 indices into names, or (0,) for no name
    column. names : (m, w) uint8 ASCII, name_lengths : (m,) int64. out : uint8 buffer, large enough (the caller
    sizes it from the widest number). Returns the number of bytes written.
    """
    at = 0
    digits = np.empty(20, np.uint8)
    with_names = codes.shape[0] > 0
    for i in range(scaled.shape[0]):
        for j in range(scaled.shape[1]):
            if j:
                out[at] = 44  # ','
                at += 1
            v = scaled[i, j]
            d = decimals[j]
            if v < 0:
                out[at] = 45  # '-'
                at += 1
                v = -v
            count = 0
            while True:  # digits right to left; at least one before the point
                digits[count] = 48 + v % 10
                v //= 10
                count += 1
                if v == 0 and count > d:
                    break
            for k in range(count - 1, -1, -1):
                out[at] = digits[k]
                at += 1
                if k == d and d > 0:
                    out[at] = 46  # '.'
                    at += 1
        if with_names:
            out[at] = 44
            at += 1
            c = codes[i]
            for k in range(name_lengths[c]):
                out[at] = names[c, k]
                at += 1
        out[at] = 10  # '\n'
        at += 1
    return at


#: A point nearer the cone's axis than this (mm) is on it: there the radial vector is rounding noise of the
#: axial one (1e-16 mm, not perpendicular to the axis), so any meridian is taken, as every one is equally near.
ON_AXIS_MM = 1e-9


@numba.njit(cache=True)
def cone_patch_distance(points, centre, axis, fallback, h0, r0, ca, sa, length, signed, unsigned, normal):
    """Exact distance of each point to a cone frustum patch (``deviation._cone_patch``'s formulas, per point).

    points : (n, 3) float64, mm. centre, axis : (3,) the base centre and unit axis. fallback : (3,) a radial unit
    vector for points on the axis. h0 : mm, the patch's lower height; r0 : mm, its radius there; ca, sa : cos and sin
    of the half angle; length : mm, the generator's length. Writes the signed distance (+ outside the material) into
    ``signed`` (n,), its magnitude into ``unsigned`` (n,) and the unit gradient into ``normal`` (n, 3).
    """
    for i in range(points.shape[0]):
        vx, vy, vz = points[i, 0] - centre[0], points[i, 1] - centre[1], points[i, 2] - centre[2]
        h = vx * axis[0] + vy * axis[1] + vz * axis[2]
        rx, ry, rz = vx - h * axis[0], vy - h * axis[1], vz - h * axis[2]
        rho = np.sqrt(rx * rx + ry * ry + rz * rz)
        if rho < ON_AXIS_MM:  # on the axis (to rounding, whose direction is noise): every meridian alike
            ex, ey, ez = fallback[0], fallback[1], fallback[2]
        else:
            ex, ey, ez = rx / rho, ry / rho, rz / rho
        # in the meridian half plane: the perpendicular foot on the generator, clamped to the patch
        along = (h - h0) * ca - (rho - r0) * sa
        along = min(max(along, 0.0), length)
        foot_h = h0 + along * ca
        foot_rho = r0 - along * sa
        dx = points[i, 0] - (centre[0] + foot_h * axis[0] + foot_rho * ex)
        dy = points[i, 1] - (centre[1] + foot_h * axis[1] + foot_rho * ey)
        dz = points[i, 2] - (centre[2] + foot_h * axis[2] + foot_rho * ez)
        distance = np.sqrt(dx * dx + dy * dy + dz * dz)
        sign = 1.0 if (h - h0) * sa + (rho - r0) * ca >= 0 else -1.0
        signed[i] = sign * distance
        unsigned[i] = distance
        if distance < 1e-12:  # on the surface: its outward normal
            normal[i, 0], normal[i, 1], normal[i, 2] = ca * ex + sa * axis[0], ca * ey + sa * axis[1], \
                ca * ez + sa * axis[2]
        else:
            normal[i, 0], normal[i, 1], normal[i, 2] = sign * dx / distance, sign * dy / distance, \
                sign * dz / distance
