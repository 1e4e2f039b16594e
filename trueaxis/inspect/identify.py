"""Identification: measured deviations back-propagated into the error twin's parameters (DESIGN §3, §7).

The model, point by point
-------------------------
A point x of the machined surface (outward unit normal n, part frame) was cut by one tool instance of the program:
the nominal tool pose whose surface touches x (*contact*). A flat end mill of radius R touches a flank point with its
side, the tool axis passing through x + R n, at the height h = (x - tip) . u above the tip along the tool axis u; it
touches a floor point with its end face (h = 0). To first order an error of that instance moves the surface at x
along n by the tool's error at the contact point,

    e_c = e_tip + h e_axis            (mm . urad = 1e-3 um)

(the tool-axis error turns the tool about its tip, so the lever is the contact's height along the axis). A tool moved
outward, +n, leaves material outside the nominal surface, and the deviation (+ = material outside) grows by n . e_c.
With the twin's parameter Jacobian J(q) (6 x P: um of tip and urad of axis error per um / urad of each parameter,
``ErrorTwin.parameter_jacobian``) this is linear in the parameters theta about the twin's own values theta0:

    deviation_i = gap_i + w_i . e(q_k; theta0) + w_i^T J(q_k; theta0) (theta - theta0) + noise_i,
    w_i = (n_i, 1e-3 h_i n_i)   (6,)

``gap_i`` is where the nominal tool surface of the program passes x along n (zero for an uncompensated program up
to chord errors; minus the compensation for a compensated one) and e(q; theta0) the twin's own error at the pose:
together they are the deviation the twin predicts for the program. The swept envelope makes this exact to first
order: a tangential miss of the nearest tool instance does not enter ``gap`` (it is taken along n only).

Solving
-------
Weighted least squares for the change of the parameters, with the rows grouped by tool instance: every point cut
by instance k shares J(q_k), so the normal matrix is sum_k J_k^T M_k J_k with the 6 x 6 moment M_k = sum w w^T of
its points, and a million points cost no more than the few thousand instances of the decimated tool path.

Which parameters the part sees. Each parameter is measured in its typical size (``typical_magnitude``, from
typical_error_magnitudes.md). The eigen-decomposition of the normal matrix in those units gives the combinations of
parameters and how well the data fix each (truncated SVD): a combination is *seen* when its standard deviation,
s / singular value with s the noise of the full fit, is below ``max_relative_std`` of a typical size. A parameter's
*seen share* is the squared length of its unit vector inside the seen combinations (1: the part determines it
alone; 0: it cannot see it). Parameters with a share of at least ``min_share`` are *identified*: solved for by least
squares with every other parameter held at the twin's value (the worst dropped while one is determined worse than
``max_relative_std``); only they change in the written twin. The rest are *not identifiable*: no effect on the part
(not reached), or their effect is (mostly) a combination of others'. The component values that set each error
function's level (``reference_parameters``) are always held: only the sum of the constant parts of all functions
along one direction reaches the tool. Standard deviations come from the residual variance, s^2 (A_S^T W A_S)^-1;
they measure the noise, not the bias that held parameters with true errors can leave in partly seen ones (a share
below 1). ``robust`` re-weights the rows by the soft-L1 (or Huber) loss, iteratively re-weighted least squares: the
stationary point of ``scipy.optimize.least_squares(loss="soft_l1")`` with ``f_scale`` from the residuals' MAD.

Identifiability is reported as the singular values in typical-size units (the RMS deviation a typical-size change
along each combination makes on the part, um), the condition numbers (all parameters with an effect; the identified
ones), and the combinations the part cannot see, named by their largest loadings. One part at one placement cannot
separate everything: a cone measured in the part frame sees the rotary axes' location errors mostly through one-
and two-per-turn patterns that several parameters share; with ``alignment="rigid"`` (deviations after a best fit)
the rigid motions are fitted as nuisance and every parameter that mimics a rigid motion of the part drops out.

Units: mm and rad inside, deviations and errors in um, angles in urad; reports name their units in their keys.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial import cKDTree

from ..machine import ErrorTwin, Machine, forward_nominal, load_machine
from ..machine.model import ROTATION_LETTER, SQUARENESS, unit_of
from ..postproc.gcode import Program, parse_program
from ..sim.trajectory import AXES, MM_PER_INCH, interpolate

UM_PER_MM = 1e3
LEVER = 1e-3  # um of contact displacement per (urad of tool-axis error x mm of lever)
ALIGNMENT_NAMES = ("TX", "TY", "TZ", "RX", "RY", "RZ")  # rigid motion of the part: um, um, um, urad, urad, urad
MAX_CACHE_BYTES = 384 * 2**20
CHUNK_POINTS = 1 << 16


# ------------------------------------------------------------------------------------------------- the tool path ----
@dataclass
class ToolPath:
    """Nominal cutting instances of a program, decimated along the path.

    q : (K, n_axes) commanded machine axes, mm and rad (columns ``machine.axis_names``).
    tip : (K, 3) nominal tool tip, mm, part frame.  axis : (K, 3) nominal unit tool axis, part frame.
    line : (K,) 0-based source line of the block each instance lies on.  t : (K,) program time, s.
    """

    q: np.ndarray
    tip: np.ndarray
    axis: np.ndarray
    line: np.ndarray
    t: np.ndarray

    def __len__(self) -> int:
        return int(self.q.shape[0])


def nominal_tool_path(program, machine: Machine, *, dt: float = 1e-3, spacing_mm: float = 0.1,
                      spacing_deg: float = 0.05) -> ToolPath:
    """The program's feed moves (G1/G2/G3) interpolated (``trueaxis.sim.trajectory.interpolate``) and decimated to
    one instance every ``spacing_mm`` of tip travel (part frame) or ``spacing_deg`` of rotary motion, whichever
    comes first, plus the exact end of every feed move (at a corner of the path the tool cuts the corner's arc from
    that one pose); poses through the machine's nominal kinematics.

    program : G-code text, a path, or a parsed ``Program`` (machine-axis program, program coordinates as the virtual
    shop takes them).  machine : its layout (errors are not used; the part placement ``workpiece_origin`` is).
    Returns a :class:`ToolPath` in program order.
    """
    prog = _parse(program)
    traj = interpolate(prog, machine, dt)
    cut = np.nonzero(traj.motion != 0)[0]
    if cut.size == 0:
        raise ValueError(f"{prog.source}: the program has no feed moves: nothing cut the part")
    q = traj.q[cut]
    tip, _ = forward_nominal(machine, q)
    rot = [c for c, a in enumerate(machine.axis_names) if machine.axes[a].is_rotary]
    step = np.linalg.norm(np.diff(tip, axis=0), axis=1) / spacing_mm
    if rot:
        step = np.maximum(step, np.degrees(np.abs(np.diff(q[:, rot], axis=0))).max(axis=1) / spacing_deg)
    travel = np.r_[0.0, np.cumsum(step)]
    keep = np.r_[True, np.floor(travel[1:]) != np.floor(travel[:-1])]
    keep[-1] = True
    # Exact ends of the feed moves (program units -> mm, rad), at the end time of their row.
    rows = np.nonzero((prog.motion != 0) & (traj.row_duration > 0))[0]
    cols = [AXES.index(a) for a in machine.axis_names]
    lin = np.where(prog.inch[rows], MM_PER_INCH, 1.0)[:, None]
    ends = np.concatenate([prog.end[rows, :3] * lin, np.radians(prog.end[rows, 3:])], axis=1)[:, cols]
    q_all = np.concatenate([q[keep], ends])
    t_all = np.r_[traj.t[cut][keep], traj.row_start_t[rows] + traj.row_duration[rows]]
    line_all = np.r_[traj.line[cut][keep], prog.line_index[rows]]
    order = np.argsort(t_all, kind="stable")
    q_all, t_all, line_all = q_all[order], t_all[order], line_all[order]
    tip_all, axis_all = forward_nominal(machine, q_all)
    return ToolPath(q_all, tip_all, axis_all, line_all.astype(int), t_all)


def _parse(program) -> Program:
    if isinstance(program, Program):
        return program
    text, source = program, "<string>"
    if isinstance(program, Path) or (isinstance(program, str) and "\n" not in program and Path(program).is_file()):
        source = str(program)
        text = Path(program).read_text(encoding="utf-8", errors="replace")
    return parse_program(text, source)


# ---------------------------------------------------------------------------------------------------- contacts ----
@dataclass
class Contacts:
    """Which tool instance cut each point.

    sample : (N,) int, index into the ToolPath (-1: no instance within ``max_gap_mm``).
    lever_mm : (N,) height of the contact above the tool tip along the tool axis (0 for end-face contacts).
    gap_um : (N,) where the nominal tool surface passes the point, along its normal (+ = outside), um.
    end_face : (N,) bool, cut by the end face (floor) rather than the side.
    """

    sample: np.ndarray
    lever_mm: np.ndarray
    gap_um: np.ndarray
    end_face: np.ndarray

    @property
    def found(self) -> np.ndarray:
        return self.sample >= 0


def find_contacts(points, normals, path: ToolPath, radius: float, length: float, *, level_mm: float = 2.0,
                  stride: int = 8, starts: int = 4, tie_um: float = 0.5, max_gap_mm: float = 0.5,
                  workers: int = 1) -> Contacts:
    """The instance of ``path`` whose flat-end-mill surface (radius, flute ``length``, mm) touches each point.

    points : (N, 3) nominal surface points, mm, part frame.  normals : (N, 3) unit outward normals.
    A side contact has the tool axis through y = x + R n; an end-face contact has its tip plane through x (y = x).
    The contact instance is the one whose axis segment passes nearest to y. Search: a KD-tree holds the axes of every
    ``stride``-th instance sampled every ``level_mm`` along the flutes (a million queries on the full path would
    cost seconds); among its ``starts`` nearest samples the nearest and the nearest one elsewhere on the path give
    two starts, and from each two Newton steps along the path on the stationarity of |y - foot(k)|^2 (foot: the
    axis point nearest y) plus a check of the neighbours give an instance. The nearest wins; within ``tie_um``
    the latest in the program (where passes repeat the same path, as the depth passes of a slot do, the last one to
    pass; their errors differ only through the pass depth). Points
    whose normal lies along the found instance's axis (floors) are searched again as end-face contacts. Points with
    no instance within ``max_gap_mm`` get sample -1.
    """
    x = _rows(points, "points")
    n = _rows(normals, "normals")
    if x.shape != n.shape:
        raise ValueError(f"points {x.shape} and normals {n.shape} differ in shape")
    K = len(path)
    if K == 0:
        raise ValueError("the tool path is empty")
    levels = np.arange(0.0, length + 1e-9, level_mm)
    if levels[-1] < length - 1e-9:
        levels = np.r_[levels, length]
    coarse = np.unique(np.r_[np.arange(0, K, max(1, int(stride))), K - 1])
    tree = cKDTree((path.tip[coarse, None, :] + levels[None, :, None] * path.axis[coarse, None, :]).reshape(-1, 3))
    owner = np.repeat(coarse, levels.size)
    starts = max(2, min(int(starts), tree.n))
    tip, axis = path.tip, path.axis
    # Per instance: tip, axis and their central differences along the path (one gather of 12 numbers per query).
    d_tip = np.gradient(tip, axis=0) if K > 1 else np.zeros_like(tip)
    d_axis = np.gradient(axis, axis=0) if K > 1 else np.zeros_like(axis)
    table = np.ascontiguousarray(np.concatenate([tip, axis, d_tip, d_axis], axis=1))

    def foot(y, k):
        """Point of instance k's axis segment nearest y (m, 3), and its derivative along the path index (m, 3)."""
        r = np.take(table, k, axis=0)
        h = np.clip(np.einsum("ij,ij->i", y - r[:, 0:3], r[:, 3:6]), 0.0, length)
        return r[:, 0:3] + h[:, None] * r[:, 3:6], r[:, 6:9] + h[:, None] * r[:, 9:12]

    def refine(y, k):
        for _ in range(2):
            f, t = foot(y, k)
            dk = np.einsum("ij,ij->i", y - f, t) / np.maximum(np.einsum("ij,ij->i", t, t), 1e-18)
            k = np.clip(np.rint(k + np.clip(dk, -stride - 2, stride + 2)).astype(np.int64), 0, K - 1)
        cand = np.stack([np.maximum(k - 1, 0), k, np.minimum(k + 1, K - 1)], axis=1)
        d = np.stack([np.linalg.norm(y - foot(y, cand[:, j])[0], axis=1) for j in range(3)], axis=1)
        j = np.argmin(d, axis=1)
        rows = np.arange(len(y))
        return cand[rows, j], d[rows, j]

    def nearest(y):
        # Two starts: the nearest tree sample, and the nearest one away from it along the path (more than two
        # strides). Passes that repeat a path at a small offset (semi-finishing, then finishing; a slot's depth
        # passes) lie side by side in the tree, and the right one need not be the nearest sample. The nearest axis
        # wins; within tie_um, the latest instance (the last tool to pass).
        _, i = tree.query(y, k=starts, workers=workers)
        own = owner[i.reshape(len(y), starts)]
        apart = np.abs(own - own[:, :1]) > 2 * stride
        second = np.where(apart.any(axis=1), own[np.arange(len(y)), np.argmax(apart, axis=1)], own[:, 0])
        k1, d1 = refine(y, own[:, 0])
        k2, d2 = refine(y, second)
        pick2 = (d2 < d1 - tie_um * 1e-3) | ((d2 <= d1 + tie_um * 1e-3) & (k2 > k1))
        return np.where(pick2, k2, k1)

    # In chunks that keep the temporaries in cache.
    sample = np.empty(x.shape[0], np.int64)
    end = np.zeros(x.shape[0], bool)
    for s in range(0, x.shape[0], CHUNK_POINTS):
        sl = slice(s, min(s + CHUNK_POINTS, x.shape[0]))
        xs, ns = x[sl], n[sl]
        k = nearest(xs + radius * ns)
        e = np.abs(np.einsum("ij,ij->i", ns, axis[k])) > math.cos(math.radians(45.0))
        if np.any(e):
            k[e] = nearest(xs[e])
        sample[sl], end[sl] = k, e
    t0, u = tip[sample], axis[sample]
    h_raw = np.einsum("ij,ij->i", x - t0, u)
    h = np.clip(h_raw, 0.0, length)
    # Gap along n only: a tangential miss of the nearest instance leaves the envelope unchanged to first order.
    side_gap = np.einsum("ij,ij->i", t0 + h[:, None] * u - x, n) - radius
    end_gap = -h_raw * np.sign(np.einsum("ij,ij->i", n, u))
    gap = np.where(end, end_gap, side_gap)
    lever = np.where(end, 0.0, h)
    ok = np.abs(gap) <= max_gap_mm
    ok &= end | ((h_raw >= -max_gap_mm) & (h_raw <= length + max_gap_mm))
    return Contacts(np.where(ok, sample, -1), np.where(ok, lever, 0.0), np.where(ok, gap * UM_PER_MM, np.nan), end)


def contact_weights(normals, lever_mm) -> np.ndarray:
    """w (N, 6): the deviation at each point per um of tip error and per urad of tool-axis error, (n, 1e-3 h n)."""
    n = np.asarray(normals, float)
    return np.concatenate([n, LEVER * np.asarray(lever_mm, float)[:, None] * n], axis=1)


def sensitivity_matrix(normals, contacts: Contacts, path: ToolPath, twin: ErrorTwin):
    """Dense sensitivities for small problems and checks.

    Returns S (N, P): d deviation (um) / d parameter (um or urad), columns ``twin.parameter_names``, and the
    deviation the twin predicts at its own parameters (N,) um; NaN rows where no contact was found.
    """
    found = contacts.found
    s = np.where(found, contacts.sample, 0)
    w = contact_weights(normals, contacts.lever_mm)
    uniq, inv = np.unique(s, return_inverse=True)
    J = twin.parameter_jacobian(path.q[uniq])
    ep, eu = twin.volumetric_error(path.q[uniq])
    S = np.einsum("ni,nip->np", w, J[inv])
    pred = contacts.gap_um + np.einsum("ni,ni->n", w, np.concatenate([ep, eu], axis=1)[inv])
    S[~found] = np.nan
    pred[~found] = np.nan
    return S, pred


# ----------------------------------------------------------------------------------------- normal equations ----
class _Jacobians:
    """Parameter Jacobians (K, 6, P_active) of the instances used, cached when they fit in memory, else streamed."""

    def __init__(self, twin: ErrorTwin, q: np.ndarray, cols: np.ndarray):
        self.twin, self.q, self.cols = twin, q, cols
        self.cache = None
        self.errors = None
        if q.shape[0] * 6 * cols.size * 8 <= MAX_CACHE_BYTES:
            self.cache = np.empty((q.shape[0], 6, cols.size))
            self.errors = np.empty((q.shape[0], 6))
            for sl, ep, eu, _, jp in twin.iter_errors_and_jacobians(q):
                self.cache[sl] = jp[:, :, cols]
                self.errors[sl] = np.concatenate([ep, eu], axis=1)

    def chunks(self):
        if self.cache is not None:
            step = 4096
            for s in range(0, self.q.shape[0], step):
                sl = slice(s, min(s + step, self.q.shape[0]))
                yield sl, self.cache[sl]
            return
        for sl, _, _, _, jp in self.twin.iter_errors_and_jacobians(self.q):
            yield sl, jp[:, :, self.cols]

    def error6(self):
        if self.errors is None:
            ep, eu = self.twin.volumetric_error(self.q)
            self.errors = np.concatenate([ep, eu], axis=1)
        return self.errors

    def times(self, theta):
        """J_k theta (K, 6) for a parameter change theta (P_active,)."""
        out = np.empty((self.q.shape[0], 6))
        for sl, J in self.chunks():
            out[sl] = J @ theta
        return out


def _grouped(inv, a, b, k, symmetric=False):
    """sum over the points of each instance of a_i b_i^T: (k, da, db), by bincount (no per-point loop);
    ``symmetric``: a_i b_i^T is symmetric (a = omega w, b = w), so half the entries suffice."""
    out = np.empty((k, a.shape[1], b.shape[1]))
    for i in range(a.shape[1]):
        for j in range(i if symmetric else 0, b.shape[1]):
            out[:, i, j] = np.bincount(inv, a[:, i] * b[:, j], minlength=k)
            if symmetric:
                out[:, j, i] = out[:, i, j]
    return out


def _alignment_rows(points, normals):
    """g (N, 6): deviation per um of part translation and per urad of part rotation about the part origin."""
    return np.concatenate([normals, LEVER * np.cross(points, normals)], axis=1)


@dataclass
class _System:
    N: np.ndarray       # (Q, Q) normal matrix over [alignment?, active parameters]
    rhs: np.ndarray     # (Q,)
    scale: np.ndarray   # (Q,) column norms (equilibration)
    btb: float          # sum of omega b^2
    n: float            # number of rows
    wsum: float         # sum of omega


def _assemble(jac: _Jacobians, inv, w, b, omega, g=None) -> _System:
    k = jac.q.shape[0]
    ow = omega[:, None] * w
    M = _grouped(inv, ow, w, k, symmetric=True)                                  # (k, 6, 6)
    v = np.stack([np.bincount(inv, ow[:, i] * b, minlength=k) for i in range(6)], axis=1)
    P = jac.cols.size
    na = 0 if g is None else 6
    N = np.zeros((na + P, na + P))
    rhs = np.zeros(na + P)
    if g is not None:
        og = omega[:, None] * g
        N[:6, :6] = og.T @ g
        rhs[:6] = og.T @ b
        G = _grouped(inv, og, w, k)                              # (k, 6, 6): sum omega g w^T
    for sl, J in jac.chunks():
        Jf = J.reshape(-1, P)
        N[na:, na:] += Jf.T @ (M[sl] @ J).reshape(-1, P)
        rhs[na:] += Jf.T @ v[sl].reshape(-1)
        if g is not None:
            N[:6, na:] += np.einsum("kij,kjp->ip", G[sl], J)
    if g is not None:
        N[na:, :6] = N[:6, na:].T
    d = np.sqrt(np.maximum(np.diag(N), 0.0))
    return _System(N, rhs, d, float(np.sum(omega * b * b)), float(b.size), float(np.sum(omega)))


@dataclass
class _Spectrum:
    """Identifiability of the active columns, in typical-size units (a unit change = a typical-size error)."""

    singular_um: np.ndarray   # (R,) RMS deviation (um) of a typical-size change along each combination, descending
    vectors: np.ndarray       # (R, R) the combinations (columns), over the active columns
    kept: np.ndarray          # (R,) bool, combinations determined to better than max_relative_std
    share: np.ndarray         # (R,) share of each active column inside the kept combinations (0..1)
    s2: float                 # residual variance of the (numerically) full fit, um^2


def _spectrum(system: _System, act, typical, max_relative_std) -> _Spectrum:
    T = typical[act]
    Nt = system.N[np.ix_(act, act)] * T[:, None] * T[None, :]
    lam, V = np.linalg.eigh(Nt)
    lam, V = lam[::-1], V[:, ::-1]
    lam = np.maximum(lam, 0.0)
    rank = lam > 1e-13 * max(lam[0], 1e-300)
    c = V.T @ (system.rhs[act] * T)
    rss = system.btb - float(np.sum(c[rank] ** 2 / lam[rank]))
    s2 = max(rss, 0.0) / max(1.0, system.n - rank.sum())
    # std of the coefficient of combination j, in typical sizes: s / sqrt(lambda_j).
    kept = rank & (np.sqrt(s2) <= max_relative_std * np.sqrt(np.where(rank, lam, 1.0)))
    share = np.sum(V[:, kept] ** 2, axis=1)
    return _Spectrum(np.sqrt(lam / max(system.wsum, 1e-300)), V, kept, share, s2)


def _independent(system: _System, cols, tol: float = 1e-8):
    """The columns ``cols`` if their equilibrated normal matrix is positive definite (smallest eigenvalue > tol),
    else a subset taken greedily in the given order, each kept only if it stays independent of those before: the
    rigid motions a part leaves undetermined (the turn of a cone about its axis) drop out."""
    cols = np.asarray(cols, int)

    def ok(c):
        d = 1.0 / system.scale[c]
        return c.size == 0 or np.linalg.eigvalsh(system.N[np.ix_(c, c)] * d[:, None] * d[None, :])[0] > tol

    if ok(cols):
        return cols
    out: list[int] = []
    for c in cols:
        if ok(np.array(out + [int(c)])):
            out.append(int(c))
    return np.array(out, int)


def _least_squares(system: _System, chosen):
    """Weighted least squares over the columns ``chosen``, the others held: theta (Q,), covariance per unit variance
    (Q, Q), residual variance s^2 (um^2)."""
    Q = system.N.shape[0]
    theta = np.zeros(Q)
    cov = np.zeros((Q, Q))
    if chosen.size == 0:
        return theta, cov, system.btb / max(1.0, system.n)
    d = 1.0 / system.scale[chosen]
    A = system.N[np.ix_(chosen, chosen)] * d[:, None] * d[None, :]
    fac = cho_factor(A)
    theta[chosen] = cho_solve(fac, system.rhs[chosen] * d) * d
    cov[np.ix_(chosen, chosen)] = cho_solve(fac, np.eye(chosen.size)) * d[:, None] * d[None, :]
    t = theta[chosen]
    rss = system.btb - 2.0 * t @ system.rhs[chosen] + t @ system.N[np.ix_(chosen, chosen)] @ t
    return theta, cov, max(rss, 0.0) / max(1.0, system.n - chosen.size)


def _fit_identifiable(system: _System, chosen, typical, max_relative_std, na, noise_s2):
    """Least squares over ``chosen``; while a parameter's std (with the noise variance of the full model,
    ``noise_s2``: what the held parameters leave unexplained is bias, not noise) exceeds max_relative_std x its
    typical size, drop the worst and solve again. Returns (chosen, theta, cov, s2, dropped {column: std / typical})
    with s2 the residual variance of the fit over the chosen columns."""
    chosen = list(chosen)
    dropped = {}
    while True:
        theta, cov, s2 = _least_squares(system, np.array(chosen, int))
        params = [i for i, c in enumerate(chosen) if c >= na]
        if not params:
            break
        idx = np.array([chosen[i] for i in params])
        rel = np.sqrt(np.maximum(np.diag(cov)[idx], 0.0) * noise_s2) / typical[idx]
        worst = int(np.argmax(rel))
        if rel[worst] <= max_relative_std:
            break
        dropped[int(idx[worst])] = float(rel[worst])
        chosen.remove(int(idx[worst]))
    return np.array(chosen, int), theta, cov, s2, dropped


ALIGNMENT_TYPICAL = 1000.0  # um, urad: a best fit moves the part freely


def typical_magnitude(name: str, machine: Machine) -> float:
    """A typical size of an error parameter (um or urad), the "good default sigma" of typical_error_magnitudes.md:
    rotary-axis offsets 20 um, tilts 50 urad, zero-angle offsets 25 urad; squareness 20 urad; linear-axis
    positioning and straightness 4 um, angular 10 urad; rotary-axis positioning 25 urad, radial / axial 2 um,
    wobble 5 urad. Series coefficients take the size of their function."""
    base = name.split("@")[0].split(".")[0]
    if base in SQUARENESS:
        return 20.0
    if base in machine.location_names():
        axis = machine.axes[base[2]]
        if base[0] in "XYZ":
            return 20.0
        return 25.0 if base[0] == ROTATION_LETTER[axis.about] else 50.0
    d, axis_name = base[1], base[2]
    axis = machine.axes[axis_name]
    if axis.is_rotary:
        if d in "XYZ":
            return 2.0
        return 25.0 if d == ROTATION_LETTER[axis.about] else 5.0
    return 4.0 if d in "XYZ" else 10.0



@dataclass
class Identification:
    """What ``identify`` found. Values in the machine file's units (um / urad).

    names : (P,) every twin parameter.  prior, value : (P,) the twin's values before and after (only ``identified``
    ones changed).  std : (P,) standard deviation of the identified ones (NaN for the rest).
    identified : (P,) bool.  seen_share : (P,) share of each parameter inside the combinations the part determines
    (1: the part sees it alone; 0: not at all; NaN: no effect).  no_effect : (P,) bool.
    confounded_with : name -> [(name, coefficient), ...]: the identified parameters whose combination looks most
    like it.  poorly_determined : name -> (std / typical size, std) of those dropped for their uncertainty.
    alignment : the rigid motion fitted (alignment "rigid").  residual_um : (N,) per point after the fit (NaN where
    no contact).  singular_values_um : RMS deviation of a typical-size change along each combination, descending.
    unseen : the combinations the part cannot see.  machine : the twin with the identified values.
    """

    names: list
    prior: np.ndarray
    value: np.ndarray
    std: np.ndarray
    identified: np.ndarray
    seen_share: np.ndarray
    no_effect: np.ndarray
    confounded_with: dict
    poorly_determined: dict
    alignment: dict
    residual_um: np.ndarray
    deviation_rms_um: float
    predicted_rms_um: float
    residual_rms_um: float
    noise_um: float
    singular_values_um: np.ndarray
    condition_number: float
    condition_number_identified: float
    unseen: list
    machine: Machine
    n_points: int
    n_used: int
    n_instances: int
    options: dict = field(default_factory=dict)

    def as_report(self, max_listed: int = 12) -> dict:
        """The ``identification`` entry of report.json (DESIGN §7)."""
        params = []
        for i in np.nonzero(self.identified)[0]:
            name = self.names[i]
            u = unit_of(name)
            params.append({"name": name, f"value_{u}": _r(self.value[i]), f"std_{u}": _r(self.std[i]),
                           f"change_{u}": _r(self.value[i] - self.prior[i]), "seen_share": _r(self.seen_share[i], 3)})
        detail = []
        for i in np.nonzero(~self.identified)[0]:
            name = self.names[i]
            combo = ", ".join(f"{c:+.3g} {m}" for m, c in self.confounded_with.get(name, [])[:4])
            like = f"; its effect resembles {combo}" if combo else ""
            if self.no_effect[i]:
                detail.append({"name": name, "reason": "no effect on this part (not reached by the program)"})
            elif name in self.poorly_determined:
                rel, sd = self.poorly_determined[name]
                detail.append({"name": name, "seen_share": _r(self.seen_share[i], 3),
                               "reason": f"determined only to +-{sd:.3g} {unit_of(name)} ({rel:.2g} x its typical "
                                         f"size){like}"})
            else:
                detail.append({"name": name, "seen_share": _r(self.seen_share[i], 3),
                               "reason": f"the part sees {100 * self.seen_share[i]:.0f} % of it{like}"})
        return {
            "method": "weighted least squares on the contact sensitivities of the parameters the part sees"
                      + (f" (robust: IRLS {self.options.get('loss')})" if self.options.get("robust") else ""),
            "points": self.n_points,
            "points_used": self.n_used,
            "tool_instances": self.n_instances,
            "alignment_mode": self.options.get("alignment", "none"),
            "parameters": params,
            "not_identifiable": [d["name"] for d in detail],
            "not_identifiable_detail": detail,
            "alignment": self.alignment,
            "deviation_rms_um": _r(self.deviation_rms_um),
            "predicted_rms_um": _r(self.predicted_rms_um),
            "residual_rms_um": _r(self.residual_rms_um),
            "noise_estimate_um": _r(self.noise_um),
            "singular_values_um": [float(f"{v:.5g}") for v in self.singular_values_um],
            "singular_values_note": "RMS deviation (um) that a typical-size change of the parameters along each "
                                    "combination makes on this part (typical sizes: typical_error_magnitudes.md)",
            "condition_number": float(f"{self.condition_number:.6g}"),
            "condition_number_identified": float(f"{self.condition_number_identified:.6g}"),
            "unseen_combinations": self.unseen[:max_listed],
            "unseen_combinations_total": len(self.unseen),
            "max_relative_std": self.options.get("max_relative_std"),
            "min_share": self.options.get("min_share"),
        }


def _r(v, digits=4):
    v = float(v)
    return round(v, digits) if math.isfinite(v) else None


# --------------------------------------------------------------------------------------------------- identify ----
def identify(points, normals, deviation_um, program, machine: Machine, *, parameters=None, robust=False,
             loss: str = "soft_l1", alignment: str = "none", max_relative_std: float = 0.2, min_share: float = 0.6,
             weights=None, path: ToolPath | None = None, max_gap_mm: float = 0.5,
             irls_iterations: int = 10) -> Identification:
    """Identify the twin's error parameters from a measured part.

    points : (N, 3) measured points, mm, part frame.  normals : (N, 3) unit outward normals of the nominal surface.
    deviation_um : (N,) signed deviation from the nominal surface, um (+ = material outside); the nominal point is
        points - deviation n.
    program : the program that cut the part (text, path or ``Program``; machine axes).
    machine : the twin the identification starts from (its values are theta0), with the part placement the program
        used (``workpiece_origin``).
    parameters : None (all), or names and the groups "location" / "component" to consider; the others stay fixed.
    robust : iteratively re-weighted with ``loss`` ("soft_l1" | "huber").
    alignment : "none" (deviations in the part frame, as fixed by the fixture) | "rigid" (the deviations came from a
        best fit: the six rigid motions are fitted as nuisance).
    max_relative_std : a combination of parameters (in typical sizes, ``typical_magnitude``) counts as seen when
        the data determine it to better than this share of a typical size; an identified parameter must be
        determined that well too.
    min_share : a parameter is identified when at least this share of it lies in the seen combinations.
    weights : (N,) optional row weights (relative; 1 / variance).  path : a ToolPath to reuse.
    """
    x = _rows(points, "points")
    n = _rows(normals, "normals")
    dev = np.asarray(deviation_um, float).reshape(-1)
    if x.shape != n.shape or dev.shape != (x.shape[0],):
        raise ValueError(f"points {x.shape}, normals {n.shape} and deviation_um {dev.shape} must agree in length")
    if not np.all(np.isfinite(dev)):
        raise ValueError("deviation_um contains NaN or infinite values")
    if alignment not in ("none", "rigid"):
        raise ValueError(f"alignment must be 'none' or 'rigid', got {alignment!r}")
    if loss not in ("soft_l1", "huber"):
        raise ValueError(f"loss must be 'soft_l1' or 'huber', got {loss!r}")
    if not (max_relative_std > 0 and 0 < min_share <= 1):
        raise ValueError(f"max_relative_std must be > 0 and min_share in (0, 1]; got {max_relative_std}, {min_share}")
    if np.any(np.abs(np.linalg.norm(n, axis=1) - 1.0) > 1e-3):
        raise ValueError("normals must be unit vectors")
    omega0 = np.ones(x.shape[0]) if weights is None else np.asarray(weights, float).reshape(-1)
    if omega0.shape != dev.shape or np.any(~np.isfinite(omega0)) or np.any(omega0 < 0):
        raise ValueError("weights must be (N,) finite and >= 0")

    twin = ErrorTwin(machine)
    names = list(twin.parameter_names)
    prior = machine.parameter_values()
    path = path if path is not None else nominal_tool_path(program, machine)
    x0 = x - (dev * 1e-3)[:, None] * n
    contacts = find_contacts(x0, n, path, machine.tool.radius, machine.tool.flute_length, max_gap_mm=max_gap_mm)
    use = contacts.found & (omega0 > 0)
    if use.sum() < 10:
        raise ValueError(f"only {int(use.sum())} of {x.shape[0]} points lie on a surface the program cut "
                         f"(within {max_gap_mm} mm): is it the program that made this part, with this placement?")
    idx = np.nonzero(use)[0]
    uniq, inv = np.unique(contacts.sample[idx], return_inverse=True)
    w = contact_weights(n[idx], contacts.lever_mm[idx])
    g = _alignment_rows(x0[idx], n[idx]) if alignment == "rigid" else None
    na = 0 if g is None else 6

    cols = np.nonzero(_considered(names, machine, parameters))[0]
    jac = _Jacobians(twin, path.q[uniq], cols)
    pred = contacts.gap_um[idx] + np.einsum("ni,ni->n", w, jac.error6()[inv])
    b = dev[idx] - pred                                          # what the twin does not explain yet
    omega = omega0[idx] / np.mean(omega0[idx])
    typical = np.r_[np.full(na, ALIGNMENT_TYPICAL), [typical_magnitude(names[c], machine) for c in cols]]
    col_names = list(ALIGNMENT_NAMES[:na]) + [names[c] for c in cols]

    system = _assemble(jac, inv, w, b, omega, g)
    active = system.scale > 1e-9 * max(system.scale.max(), 1e-300)
    act = np.nonzero(active)[0]
    spec = _spectrum(system, act, typical, max_relative_std)
    share = np.full(system.N.shape[0], np.nan)
    share[act] = spec.share
    seen = act[(act >= na) & (spec.share >= min_share)]
    seen = seen[np.argsort(-spec.share[np.searchsorted(act, seen)], kind="stable")]
    candidates = _independent(system, np.r_[_independent(system, act[act < na]), seen])
    chosen, theta, cov, s2, dropped = _fit_identifiable(system, candidates, typical, max_relative_std, na,
                                                         spec.s2)
    residual = _residual(jac, inv, w, g, b, theta, na)
    if robust:
        # IRLS on the same columns: soft-L1 rho(z) = 2 (sqrt(1 + z^2) - 1), Huber; scale from the residuals' MAD.
        f_scale = max(1.4826 * float(np.median(np.abs(residual - np.median(residual)))), 1e-6)
        for _ in range(irls_iterations):
            z = np.abs(residual) / f_scale
            rw = 1.0 / np.sqrt(1.0 + z**2) if loss == "soft_l1" else np.minimum(1.0, 1.0 / np.maximum(z, 1e-300))
            omega = omega0[idx] / np.mean(omega0[idx]) * rw
            system = _assemble(jac, inv, w, b, omega, g)
            old = theta
            theta, cov, s2 = _least_squares(system, chosen)
            residual = _residual(jac, inv, w, g, b, theta, na)
            if np.max(np.abs(theta - old), initial=0.0) <= 1e-6 * max(1.0, np.max(np.abs(theta), initial=0.0)):
                break
    std_all = np.sqrt(np.maximum(np.diag(cov), 0.0) * s2)

    # The combinations the part cannot see, named by their largest loadings (in typical sizes).
    unseen = []
    for j in np.nonzero(~spec.kept)[0]:
        v = spec.vectors[:, j]
        top = np.argsort(-np.abs(v))[:4]
        unseen.append({"singular_value_um": float(f"{spec.singular_um[j]:.4g}"),
                       "combination": [{"name": col_names[act[t]], "weight": round(float(v[t]), 3)} for t in top
                                       if abs(v[t]) >= 0.05]})
    sv = spec.singular_um
    cond = float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else math.inf
    if chosen.size:
        T = typical[chosen]
        lam_s = np.linalg.eigvalsh(system.N[np.ix_(chosen, chosen)] * T[:, None] * T[None, :])
        cond_s = float(math.sqrt(lam_s[-1] / lam_s[0])) if lam_s[0] > 0 else math.inf
    else:
        cond_s = math.nan

    value = prior.copy()
    std = np.full(len(names), np.nan)
    identified = np.zeros(len(names), bool)
    no_effect = np.ones(len(names), bool)
    no_effect[cols[active[na:]]] = False
    seen = np.full(len(names), np.nan)
    seen[cols] = share[na:]
    for j in chosen[chosen >= na]:
        c = cols[j - na]
        value[c] = prior[c] + theta[j]
        std[c] = std_all[j]
        identified[c] = True
    confounded = {}
    params_chosen = chosen[chosen >= na]
    if params_chosen.size:
        fac = cho_factor(system.N[np.ix_(params_chosen, params_chosen)]
                         + 1e-12 * np.diag(np.diag(system.N[np.ix_(params_chosen, params_chosen)])))
        for j in act[act >= na]:
            if j in set(params_chosen.tolist()):
                continue
            coef = cho_solve(fac, system.N[params_chosen, j])
            order = np.argsort(-np.abs(coef) * typical[params_chosen])[:4]
            confounded[col_names[j]] = [(col_names[params_chosen[o]], float(coef[o])) for o in order
                                        if abs(coef[o]) * typical[params_chosen[o]] > 1e-3 * typical[j]]
    poorly = {col_names[j]: (rel, rel * typical[j]) for j, rel in dropped.items()}
    align = {}
    for i in range(na):
        u = "um" if ALIGNMENT_NAMES[i].startswith("T") else "urad"
        fitted = i in set(chosen.tolist())
        align[f"{ALIGNMENT_NAMES[i]}_{u}"] = _r(theta[i]) if fitted else None  # None: the part does not fix it
        align[f"{ALIGNMENT_NAMES[i]}_std_{u}"] = _r(std_all[i]) if fitted else None

    residual_all = np.full(x.shape[0], np.nan)
    residual_all[idx] = residual
    return Identification(
        names=names, prior=prior, value=value, std=std, identified=identified, seen_share=seen,
        no_effect=no_effect, confounded_with=confounded, poorly_determined=poorly, alignment=align,
        residual_um=residual_all, deviation_rms_um=float(np.sqrt(np.mean(dev[idx] ** 2))),
        predicted_rms_um=float(np.sqrt(np.mean(b**2))), residual_rms_um=float(np.sqrt(np.mean(residual**2))),
        noise_um=float(math.sqrt(spec.s2)), singular_values_um=sv, condition_number=cond,
        condition_number_identified=cond_s, unseen=unseen, machine=machine.with_parameters(value),
        n_points=int(x.shape[0]), n_used=int(idx.size), n_instances=int(uniq.size),
        options={"robust": bool(robust), "loss": loss if robust else None, "alignment": alignment,
                 "max_relative_std": max_relative_std, "min_share": min_share, "parameters": parameters},
    )


def _residual(jac: _Jacobians, inv, w, g, b, theta, na):
    Jt = jac.times(theta[na:])                         # (K, 6)
    r = b - np.einsum("ni,ni->n", w, Jt[inv])
    if g is not None:
        r -= g @ theta[:na]
    return r


def reference_parameters(machine: Machine) -> list[str]:
    """The component values that fix each error function's level (its *gauge*): the table value at the axis' zero
    (or the node nearest it) and a Legendre series' constant term. Only the sum of the constant parts of all the
    functions along one direction reaches the tool, so no measurement can share it out among the axes; the machine
    files' convention (component errors zero at each axis' zero) fixes it, and the identification holds these values.
    Fourier series have no constant term."""
    out = []
    for axis, comps in machine._component_items():
        for comp, fn in comps:
            if fn.kind in ("linear", "cubic"):
                out.append(f"{comp}{fn.labels[int(np.argmin(np.abs(fn.at)))]}")
            elif fn.kind == "legendre":
                out.append(f"{comp}{fn.labels[0]}")
    return out


def _considered(names, machine: Machine, parameters) -> np.ndarray:
    """Which parameters the identification may change: the ``parameters`` asked for, less the reference values."""
    loc = set(machine.location_names())
    if parameters is None:
        out = np.ones(len(names), bool)
    else:
        if isinstance(parameters, str):
            parameters = [p.strip() for p in parameters.split(",") if p.strip()]
        out = np.zeros(len(names), bool)
        for p in parameters:
            if p == "location":
                out |= np.array([nm in loc for nm in names])
            elif p in ("component", "components"):
                out |= np.array([nm not in loc for nm in names])
            else:
                hit = np.array([nm == p or nm.split("@")[0].split(".")[0] == p for nm in names])
                if not hit.any():
                    raise ValueError(f"parameter {p!r} is not a parameter of {machine.name} "
                                     f"(it has {', '.join(names[:8])}, ...)")
                out |= hit
    held = set(reference_parameters(machine))
    return out & np.array([nm not in held for nm in names])


def _rows(a, what):
    a = np.asarray(a, float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what} must be (N, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} contain NaN or infinite values")
    return a


# --------------------------------------------------------------------------------------------- part normals ----
def part_normals(points, part: dict) -> np.ndarray:
    """Unit outward normals of the nominal surface at ``points`` for a cloud that has none (the NAS 979 cone)."""
    if part.get("part") != "nas979":
        raise ValueError("the cloud has no normals and the part has no analytic normal field: give a cloud with "
                         "normals (nx ny nz)")
    cone = next(s for s in part["surfaces"] if s["id"] == "cone")
    a = np.asarray(cone["axis"], float)
    a = a / np.linalg.norm(a)
    c = np.asarray(cone["base_center"], float)
    alpha = math.radians(cone["half_angle_deg"])
    v = np.asarray(points, float) - c
    radial = v - np.outer(v @ a, a)
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-300)
    return math.cos(alpha) * radial + math.sin(alpha) * a


# ---------------------------------------------------------------------------------------------------- the CLI ----
def machine_for_program(machine: Machine, program_text: str, part: str | None = None) -> Machine:
    """The machine with the part placed where the program's setup comment says (``origin_mm``), as the virtual shop
    and the shop floor do; refuses a program written for another part."""
    from .programs import read_setup

    setup = read_setup(program_text)
    if part is not None and setup.get("part") and setup["part"] != part:
        raise ValueError(f"the program is for part {setup['part']!r}, not {part!r}")
    origin = setup.get("origin_mm")
    if origin is not None:
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise ValueError("the program's setup comment origin_mm must be three numbers")
        machine = dataclasses.replace(machine, workpiece_origin=origin.astype(float))
    return machine


def run_identification(cloud, deviation_um, part: dict, args) -> dict:
    """``inspect CLOUD --part P --identify --machine TWIN.toml --program prog.ngc [--write NEW.toml] [--robust]``.

    cloud : ``trueaxis.inspect.cloud.Cloud`` (points mm, normals or None, part frame).  deviation_um : (N,) signed
    deviation, um (+ = material outside).  part : the part JSON dict.  args : namespace with ``machine`` (path),
    ``program`` (path), ``write`` (path or None) and optionally ``robust`` (bool), ``alignment`` ("none" | "rigid"),
    ``parameters`` (comma-separated names or "location"/"component"), ``max_relative_std`` (float).
    Returns the report's "identification" dict; writes the identified machine file when asked (atomically).
    """
    from ..fileio import atomic_write
    from ..machine.machine_file import dump_machine

    if getattr(args, "machine", None) is None:
        raise ValueError("--identify needs --machine TWIN.toml (the twin to start from)")
    if getattr(args, "program", None) is None:
        raise ValueError("--identify needs --program PROG (the program that cut the part)")
    original = load_machine(args.machine)
    program_path = Path(args.program)
    if not program_path.is_file():
        raise ValueError(f"{program_path}: no such program file")
    text = program_path.read_text(encoding="utf-8", errors="replace")
    placed = machine_for_program(original, text, part.get("part"))
    normals = cloud.normals if cloud.normals is not None else part_normals(cloud.points, part)
    result = identify(cloud.points, normals, deviation_um, parse_program(text, str(program_path)), placed,
                      parameters=getattr(args, "parameters", None), robust=bool(getattr(args, "robust", False)),
                      alignment=getattr(args, "alignment", None) or "none",
                      max_relative_std=float(getattr(args, "max_relative_std", None) or 0.2))
    report = result.as_report()
    report["machine_file"] = str(args.machine)
    report["program"] = str(program_path)
    if getattr(args, "write", None):
        out = dataclasses.replace(original.with_parameters(result.value), note=_identified_note(original, result))
        atomic_write(args.write, dump_machine(out))
        report["written"] = str(args.write)
    return report


def _identified_note(original: Machine, result: Identification) -> str:
    changed = [result.names[i] for i in np.nonzero(result.identified)[0]]
    head = original.note + "\n" if original.note else ""
    return (f"{head}Identified by trueaxis from a measured part ({result.n_used} points, residual RMS "
            f"{result.residual_rms_um:.2f} um): changed {', '.join(changed) if changed else 'nothing'}; every other "
            "value is the twin's own.")
