"""Checks shared by the post-processor tests: where the compensated program really puts the tool."""

from __future__ import annotations

import numpy as np

from trueaxis.machine import ErrorTwin
from trueaxis.nc.gcode import ARC_CCW, ARC_CW, MM_PER_INCH, ROW_PROGRAMMED, parse_program

AXES = "XYZABC"


def machine_rows(program, machine, kinds=(ROW_PROGRAMMED,)):
    """Programmed rows of a parsed program as machine poses (N, n_axes) in mm / rad, plus their row indices."""
    rows = np.nonzero(np.isin(program.kind, kinds))[0]
    cols = [AXES.index(a) for a in machine.axis_names]
    q = program.to_machine(program.end[rows], rows)[:, cols].copy()
    for j, a in enumerate(machine.axis_names):
        if machine.axes[a].is_rotary:
            q[:, j] = np.radians(q[:, j])
        else:
            q[:, j] = np.where(program.inch[rows], q[:, j] * MM_PER_INCH, q[:, j])
    return q, rows


def nominal_polyline(program, machine, arc_points=4000):
    """The nominal tool-tip path of a program as dense points (K, 3) mm in the part frame: straight moves as their
    end points, arcs sampled densely (sagitta of 50 mm arcs at 4000 points: 1e-5 um)."""
    twin = ErrorTwin(machine)
    pts = []
    cols = [AXES.index(a) for a in machine.axis_names]
    for r in range(len(program)):
        if program.motion[r] in (ARC_CW, ARC_CCW):
            six = points_on_arc(program, r, arc_points)
        else:
            six = np.vstack([program.start[r], program.end[r]])
        six = program.to_machine(six, np.full(len(six), r))
        q = six[:, cols].copy()
        for j, a in enumerate(machine.axis_names):
            q[:, j] = np.radians(q[:, j]) if machine.axes[a].is_rotary else q[:, j] * (
                MM_PER_INCH if program.inch[r] else 1.0)
        pts.append(twin.nominal_pose(q)[0])
    return np.vstack(pts)


def distance_to_polyline(points, poly, piece_mm: float = 0.2, k: int = 8):
    """Distance (mm) from each point (N,3) to the polyline poly (K,3): exact point-to-segment distances.

    Segments are cut into pieces no longer than ``piece_mm`` (a KD-tree over their midpoints; all pairs would need
    N x K memory). A piece whose midpoint is D away is at least D - h away (h: the longest half-piece), so after a
    first guess from the ``k`` nearest midpoints, every piece whose midpoint lies within guess + h is measured: exact.
    """
    from scipy.spatial import cKDTree

    a, b = poly[:-1], poly[1:]
    n_cut = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / piece_mm).astype(int))
    seg = np.repeat(np.arange(a.shape[0]), n_cut)
    step = np.arange(seg.size) - np.repeat(np.cumsum(n_cut) - n_cut, n_cut)
    lo, hi = step / n_cut[seg], (step + 1) / n_cut[seg]
    pa = a[seg] + lo[:, None] * (b - a)[seg]
    pb = a[seg] + hi[:, None] * (b - a)[seg]
    h = 0.5 * np.linalg.norm(pb - pa, axis=1).max()
    tree = cKDTree(0.5 * (pa + pb))
    _, idx = tree.query(points, k=min(k, pa.shape[0]))
    idx = idx.reshape(len(points), -1)
    guess = _point_segment_distance(points[:, None, :], pa[idx], pb[idx]).min(axis=1)
    near = tree.query_ball_point(points, guess + h + 1e-12)
    return np.array([_point_segment_distance(p[None, :], pa[j], pb[j]).min() for p, j in zip(points, near)])


def _point_segment_distance(p, a, b):
    ab = b - a
    t = np.clip(np.einsum("...j,...j->...", p - a, ab) / np.maximum(np.einsum("...j,...j->...", ab, ab), 1e-300),
                0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def actual_points(program_text, machine, force_n=None, setup=None):
    """Where the twin puts the tool tip at every programmed end point of a (compensated) program: (N,3) mm.
    ``setup``: the control's setup the program runs with (trueaxis.nc.setup.Setup)."""
    prog = parse_program(program_text, setup=setup)
    q, rows = machine_rows(prog, machine)
    return ErrorTwin(machine).actual_pose(q, force_n)[0], prog, rows


def _arc_sweep(p, r: int) -> float:
    """Sweep (rad) of the arc of row r, turns included."""
    plane = int(p.arc_plane[r])
    i, j = {17: (0, 1), 18: (2, 0), 19: (1, 2)}[plane]
    c = p.arc_center[r]
    s, e = p.start[r], p.end[r]
    a0 = np.arctan2(s[j] - c[j], s[i] - c[i])
    a1 = np.arctan2(e[j] - c[j], e[i] - c[i])
    ccw = p.motion[r] == ARC_CCW
    sweep = (a1 - a0) % (2 * np.pi) if ccw else (a0 - a1) % (2 * np.pi)
    if sweep < 1e-12:
        sweep = 2 * np.pi
    return float(sweep + 2 * np.pi * (max(int(p.arc_turns[r]), 1) - 1))


def points_on_arc(p, r: int, n: int) -> np.ndarray:
    """(n+1, 6) points along the arc of row r (program coordinates), from its start to its end; helical axis linear.
    One arc at a time: the tests' own reference, written apart from the post's vectorised ``_arcs_points``."""
    plane = int(p.arc_plane[r])
    i, j = {17: (0, 1), 18: (2, 0), 19: (1, 2)}[plane]
    normal = 3 - i - j
    c = p.arc_center[r]
    s, e = p.start[r], p.end[r]
    a0 = np.arctan2(s[j] - c[j], s[i] - c[i])
    sweep = _arc_sweep(p, r)
    sign = 1.0 if p.motion[r] == ARC_CCW else -1.0
    rad0 = np.hypot(s[i] - c[i], s[j] - c[j])
    rad1 = np.hypot(e[i] - c[i], e[j] - c[j])
    t = np.linspace(0.0, 1.0, n + 1)
    ang = a0 + sign * sweep * t
    rad = rad0 + (rad1 - rad0) * t
    pts = s[None, :] + t[:, None] * (e - s)[None, :]
    pts[:, i] = c[i] + rad * np.cos(ang)
    pts[:, j] = c[j] + rad * np.sin(ang)
    pts[:, normal] = s[normal] + t * (e[normal] - s[normal])
    pts[-1] = e
    return pts
