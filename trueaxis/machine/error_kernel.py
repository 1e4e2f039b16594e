"""Component error values and their derivatives d/dq, many functions at many poses at once, compiled with numba.

Why: the twin needs, per pose, the six component errors of every axis and their slopes. Evaluated function by function
in numpy, each table search, spline and Fourier basis is built once for the value and once more for the derivative,
and the fixed cost of each numpy call dominates. Here every function is reduced once to a plain coefficient form
(``ErrorFunction.compiled_form``), functions of the same axis that share a basis (the same table positions, Legendre
domain or harmonics) form a *group*, and per pose each group does its shared work once: one interval search per table
grid, one cos/sin per harmonic, one mapping to [-1, 1]; each member then contracts its own coefficients, for the value
and the derivative together.

The arithmetic mirrors the reference evaluation of ``ErrorFunction.__call__`` and ``.derivative`` operation by operation
(``np.interp`` for linear tables, scipy's ``PPoly`` for cubic ones, numpy's Clenshaw recurrence ``legval`` for Legendre
series, the basis row times the values for Fourier series), so the numbers agree to round-off (a few ulps), including
the clamping outside a table or a Legendre domain (value held, slope zero) and the wrapping of periodic tables.

Layout (``CompiledErrors``): member m of group g writes ``scale_m * value`` to ``val[a_m, i, b_m]`` (and the
derivative to ``dval``) for pose i, its position being ``q[i, column_g]``; slots no member covers are set to zero.
"""

from __future__ import annotations

from ..compiled import aot_available, numba, run_twins, thread_slices  # numba, or ahead-of-time twins
import numpy as np

TWO_PI = 2.0 * np.pi

LINEAR, CUBIC, LEGENDRE, FOURIER = 0, 1, 2, 3

_BLOCK = 256  # poses per block of the kernel's loop

_jit = numba.njit(cache=True)
_jit_inline = numba.njit(cache=True, inline="always")


class CompiledErrors:
    """Error functions packed for the compiled evaluation.

    entries : iterable of (fn, column, a, b, scale): an ``ErrorFunction``, the column of q holding its axis' position,
              its output slot (a, b) and the factor its value and derivative are multiplied by.
    shape : (A, B), the slot grid: outputs are (A, n, B).
    """

    def __init__(self, entries, shape: tuple[int, int]):
        self.shape = (int(shape[0]), int(shape[1]))
        groups: dict = {}
        for fn, column, a, b, scale in entries:
            kind, grid, coef, dcoef = fn.compiled_form()
            key = (int(column), kind, bool(fn.periodic), grid.tobytes())
            groups.setdefault(key, (grid, []))[1].append((coef, dcoef, int(a), int(b), float(scale)))
        g_int, grid_all, m_int, coef_all, m_scale = [], [np.empty(0)], [], [np.empty(0)], []
        n_grid = n_coef = 0
        covered = np.zeros(self.shape, dtype=bool)
        for (column, kind, periodic, _), (grid, members) in groups.items():
            m_first = len(m_int)
            g_int.append((kind, column, int(periodic), n_grid, n_grid + grid.size, m_first, m_first + len(members)))
            grid_all.append(grid)
            n_grid += grid.size
            for coef, dcoef, a, b, scale in members:
                m_int.append((n_coef, n_coef + coef.size, n_coef + coef.size, n_coef + coef.size + dcoef.size, a, b))
                coef_all += [coef, dcoef]
                n_coef += coef.size + dcoef.size
                m_scale.append(scale)
                covered[a, b] = True
        self.groups = np.array(g_int, dtype=np.int64).reshape(-1, 7)
        self.grid = np.ascontiguousarray(np.concatenate(grid_all), dtype=float)
        self.members = np.array(m_int, dtype=np.int64).reshape(-1, 6)
        self.coef = np.ascontiguousarray(np.concatenate(coef_all), dtype=float)
        self.scale = np.array(m_scale, dtype=float)
        self.zero_slots = np.argwhere(~covered).astype(np.int64).reshape(-1, 2)
        self.n_harmonics = max([int(g[4] - g[3]) for g in g_int if g[0] == FOURIER], default=0)

    def evaluate(self, q: np.ndarray, derivative: bool = True, threads: bool = True):
        """Values (A, n, B) and, with derivative, d/dq (A, n, B) (else None) at poses q (n, n_columns).
        ``threads``: many poses may be shared among threads (False: on this thread, as from one of them)."""
        q = np.ascontiguousarray(q, dtype=float)
        n = q.shape[0]
        A, B = self.shape
        val = np.empty((A, n, B))
        dval = np.empty((A, n, B)) if derivative else val  # without derivatives it stands in, unwritten
        if threads and self._threaded(q, derivative, val, dval):
            return val, (dval if derivative else None)
        evaluate_packed(q, self.groups, self.grid, self.members, self.coef, self.scale, self.zero_slots,
                        self.n_harmonics, derivative, val, dval)
        return val, (dval if derivative else None)


    def twin_evaluate(self, q: np.ndarray, derivative: bool):
        """``evaluate(q, derivative, threads=False)`` by ``evaluate_packed``'s ahead-of-time twin only (no numba:
        callable from the kernels' threads), or None when no twin takes the arguments."""
        q = np.ascontiguousarray(q, dtype=float)
        A, B = self.shape
        val = np.empty((A, q.shape[0], B))
        dval = np.empty_like(val) if derivative else val
        args = (q, self.groups, self.grid, self.members, self.coef, self.scale, self.zero_slots, self.n_harmonics,
                derivative, val, dval)
        twin = getattr(evaluate_packed, "twin", None)
        fn = twin(*args) if twin is not None else None
        if fn is None:
            return None
        fn(*args)
        return val, (dval if derivative else None)

    def _threaded(self, q, derivative, val, dval) -> bool:
        """Many poses: ``evaluate_packed``'s ahead-of-time twin on threads, each on a contiguous share of the poses
        (each pose's values are computed alone: the same numbers), into ``val`` / ``dval``; False when not done."""
        parts = thread_slices(q.shape[0])
        if not parts or getattr(evaluate_packed, "twin", None) is None or not aot_available():
            return False
        A, B = self.shape
        calls = []
        for sl in parts:
            v = np.empty((A, sl.stop - sl.start, B))
            calls.append((q[sl], self.groups, self.grid, self.members, self.coef, self.scale, self.zero_slots,
                          self.n_harmonics, derivative, v, np.empty_like(v) if derivative else v))
        if run_twins(evaluate_packed, calls) is None:
            return False
        for sl, call in zip(parts, calls):
            val[:, sl] = call[-2]
            if derivative:
                dval[:, sl] = call[-1]
        return True


# --------------------------------------------------------------------------------------------- the pieces ----
@_jit_inline
def _wrap(x, x0, periodic):
    """A periodic table's position brought into [x0, x0 + 2 pi): x0 + mod(x - x0, 2 pi), as numpy's mod."""
    if periodic:
        return x0 + (x - x0) % TWO_PI
    return x


@_jit_inline
def _clamp(x, lo, hi):
    """np.clip for one value (NaN passes through)."""
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x


@_jit_inline
def _interval(grid, g0, g1, x):
    """The table interval of x in grid[g0:g1], relative to g0: the last j <= n - 2 with grid[g0 + j] <= x (x already
    clamped to the table), as searchsorted(side="right") - 1 clipped to [0, n - 2], and scipy's PPoly interval."""
    lo, hi = g0, g1 - 2
    while lo < hi:
        mid = (lo + hi + 1) >> 1
        if grid[mid] <= x:
            lo = mid
        else:
            hi = mid - 1
    return lo - g0


@_jit_inline
def _legval(coef, c0, c1, x):
    """numpy.polynomial.legendre.legval(x, coef[c0:c1]) for one x: the same Clenshaw recurrence, step by step."""
    size = c1 - c0
    if size == 1:
        return coef[c0] + 0.0 * x
    b0 = coef[c1 - 2]
    b1 = coef[c1 - 1]
    nd = size
    for i in range(3, size + 1):
        tmp = b0
        nd = nd - 1
        b0 = coef[c1 - i] - (b1 * (nd - 1)) / nd
        b1 = tmp + (b1 * x * (2 * nd - 1)) / nd
    return b0 + b1 * x


# -------------------------------------------------------------------------------------- one group, all poses ----
@_jit_inline
def _table_group(q, i0, i1, col, kind, periodic, grid, g0, g1, members, m0, m1, coef, scale, deriv, val, dval):
    """Linear or cubic tables over the same positions grid[g0:g1]: one search per pose for all members.

    Linear member coefficients: the n node values (the last one of a periodic table carrying the first), then the n - 1
    slopes. Cubic: (n - 1, 4) PPoly coefficients (cubic term first) per interval, then (n - 1, 3) of the derivative.
    """
    n_knots = g1 - g0
    x0, x1 = grid[g0], grid[g1 - 1]
    for i in range(i0, i1):
        x = _wrap(q[i, col], x0, periodic)
        inside = x >= x0 and x <= x1
        xc = _clamp(x, x0, x1)
        j = _interval(grid, g0, g1, xc)
        s = xc - grid[g0 + j]
        for m in range(m0, m1):
            c0, d0, a, b = members[m, 0], members[m, 2], members[m, 4], members[m, 5]
            if kind == LINEAR:
                slope = coef[d0 + j]
                # np.interp: the last node's value at the table's end, else slope (x - x_j) + v_j.
                v = coef[c0 + n_knots - 1] if xc == x1 else slope * s + coef[c0 + j]
                dv = slope
            else:
                # scipy PPoly: sum over powers of s, ascending, each coefficient times the running power.
                k = c0 + 4 * j
                v = 0.0
                z = 1.0
                for p in range(4):
                    v = v + coef[k + 3 - p] * z
                    z *= s
                dv = 0.0
                if deriv:  # (the slope only where it is asked for)
                    k = d0 + 3 * j
                    z = 1.0
                    for p in range(3):
                        dv = dv + coef[k + 2 - p] * z
                        z *= s
            val[a, i, b] = v * scale[m]
            if deriv:
                # Outside the table the value is held: zero slope.
                dval[a, i, b] = (dv if inside else 0.0) * scale[m]


@_jit_inline
def _legendre_group(q, i0, i1, col, grid, g0, members, m0, m1, coef, scale, deriv, val, dval):
    """Legendre series over the same domain (grid[g0], grid[g0 + 1]): the position mapped to [-1, 1] once per pose.
    Member coefficients: the series, then its derivative series (legder; empty for a constant)."""
    lo, hi = grid[g0], grid[g0 + 1]
    for i in range(i0, i1):
        u = (2.0 * q[i, col] - (lo + hi)) / (hi - lo)
        inside = abs(u) <= 1.0
        uc = _clamp(u, -1.0, 1.0)
        for m in range(m0, m1):
            c0, c1, d0, d1 = members[m, 0], members[m, 1], members[m, 2], members[m, 3]
            a, b = members[m, 4], members[m, 5]
            val[a, i, b] = _legval(coef, c0, c1, uc) * scale[m]
            if deriv:
                dv = _legval(coef, d0, d1, uc) * (2.0 / (hi - lo)) if d1 > d0 else 0.0
                dval[a, i, b] = (dv if inside else 0.0) * scale[m]


@_jit_inline
def _fourier_group(q, i0, i1, col, grid, g0, g1, members, m0, m1, coef, scale, deriv, val, dval, cs, sn):
    """Fourier series with the same harmonics grid[g0:g1]: cos and sin of k q once per harmonic and pose.
    Member coefficients: a_1, b_1, a_2, b_2, ... (the basis row [cos k1 q, sin k1 q, ...] times them)."""
    h = g1 - g0
    for i in range(i0, i1):
        x = q[i, col]
        for k in range(h):
            kq = x * grid[g0 + k]
            cs[k] = np.cos(kq)
            sn[k] = np.sin(kq)
        for m in range(m0, m1):
            c0, a, b = members[m, 0], members[m, 4], members[m, 5]
            v = 0.0
            dv = 0.0
            for k in range(h):
                v += cs[k] * coef[c0 + 2 * k] + sn[k] * coef[c0 + 2 * k + 1]
            if deriv:  # (the slope only where it is asked for)
                for k in range(h):
                    hk = grid[g0 + k]
                    dv += (-hk * sn[k]) * coef[c0 + 2 * k] + (hk * cs[k]) * coef[c0 + 2 * k + 1]
            val[a, i, b] = v * scale[m]
            if deriv:
                dval[a, i, b] = dv * scale[m]


# ------------------------------------------------------------------------------------------------ the kernel ----
@_jit
def evaluate_packed(q, groups, grid, members, coef, scale, zero_slots, n_harmonics, deriv, val, dval):
    """Fill val (A, n, B) and, with deriv, dval with the packed functions at the poses q (n, n_columns).

    groups (G, 7) int: kind, q column, periodic, grid start, grid end, first member, end of members.
    members (M, 6) int: coefficient start and end, derivative-coefficient start and end, output slot a, b.
    coef, grid: the flat coefficient and grid arrays; scale (M,): each member's factor; zero_slots (Z, 2): the slots
    no member writes.
    """
    _evaluate_rows(q, groups, grid, members, coef, scale, zero_slots, n_harmonics, deriv, val, dval)


@_jit
def _evaluate_rows(q, groups, grid, members, coef, scale, zero_slots, n_harmonics, deriv, val, dval):
    """``evaluate_packed``'s work, for kernels that call it (a kernel the post calls from Python, which has an
    ahead-of-time twin, is not called from compiled code: ``trueaxis.compiled``)."""
    n = q.shape[0]
    for z in range(zero_slots.shape[0]):
        a, b = zero_slots[z, 0], zero_slots[z, 1]
        for i in range(n):
            val[a, i, b] = 0.0
            if deriv:
                dval[a, i, b] = 0.0
    cs, sn = np.empty(n_harmonics), np.empty(n_harmonics)
    # Poses in blocks, every group over a block before the next block: the outputs of a block stay in cache.
    for i0 in range(0, n, _BLOCK):
        i1 = min(n, i0 + _BLOCK)
        for g in range(groups.shape[0]):
            kind, col, periodic = groups[g, 0], groups[g, 1], groups[g, 2] != 0
            g0, g1, m0, m1 = groups[g, 3], groups[g, 4], groups[g, 5], groups[g, 6]
            if kind == LINEAR or kind == CUBIC:
                _table_group(q, i0, i1, col, kind, periodic, grid, g0, g1, members, m0, m1, coef, scale, deriv, val,
                             dval)
            elif kind == LEGENDRE:
                _legendre_group(q, i0, i1, col, grid, g0, members, m0, m1, coef, scale, deriv, val, dval)
            else:
                _fourier_group(q, i0, i1, col, grid, g0, g1, members, m0, m1, coef, scale, deriv, val, dval, cs, sn)
