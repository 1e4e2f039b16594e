"""Comprehensive compensation on a lathe: the turning force and the direction of motion of every block.

The lathe paper ("Entering the operative correction machining processes CNC") corrects a turning program for the
caliper's deviation under the cutting force, with one response surface per load sign and direction of motion of the
caliper (the machine file's ``[[force.surface]]``, evaluated by the twin). What the post adds:

- the force of each block: Kienzle's turning force (``trueaxis.machine.turning_force``) from the machine file's
  ``[cutting]`` (kc11, mc, force ratios) and the program's conditions ``(trueaxis: ap=2 f=0.2 vc=180)``, valid from
  where they stand (the command line's ``--ap`` overrides ap), directed by the block's feed direction in the XZ plane
  (an arc's: its tangent at the end for the block's end; along the arc, the tangent at each sampled point,
  ``arc_point_loads``). Rapids carry no force (the surfaces are then evaluated at P = 0, the "+" loading models);
- the direction of motion of each axis for each block: the sign of the block's displacement along it (an arc's: of its
  tangent, at the end or at the sampled point); a block that does not move an axis keeps that axis' last direction (the caliper rests against the
  side it last moved towards), forward before its first move. The surfaces pick their model by the direction of
  their position axis (``inputs[0]``), the load sign by the sign of their force component.

The post carries one load array per block through its solver and splitter; on a lathe in comprehensive mode that
array is (K, 3 + n_axes): the force on the tool (N, machine frame), then the direction of motion of each axis (+1 / -1).
``MotionTwin`` unpacks it for the error twin.
"""

from __future__ import annotations


import numpy as np

from ..machine.turning_force import TurningCoefficients, TurningConditions, force_on_tool, turning_force_components
from ..nc.gcode import ARC_CCW, ARC_CW, RAPID, feed_per_revolution_lines
from .post import PostError, condition_marks, note_inch_conditions

__all__ = ["MotionTwin", "lathe_loads"]


class MotionTwin:
    """The error twin, taking the post's per-block loads (K, 3 + n_axes): force (N), then direction of motion."""

    def __init__(self, twin):
        self._twin = twin
        self.machine = twin.machine

    def __getattr__(self, name):
        return getattr(self._twin, name)

    @staticmethod
    def _split(load, motion):
        if load is None:
            return None, motion
        load = np.asarray(load, dtype=float)
        return load[..., :3], (load[..., 3:] if motion is None else motion)

    def actual_pose(self, q, force_n=None, motion=None):
        return self._twin.actual_pose(q, *self._split(force_n, motion))

    def pose_and_axis_jacobian(self, q, force_n=None, motion=None):
        return self._twin.pose_and_axis_jacobian(q, *self._split(force_n, motion))

    def axis_jacobian(self, q, force_n=None, motion=None):
        return self._twin.axis_jacobian(q, *self._split(force_n, motion))

    def volumetric_error(self, q, force_n=None, motion=None, method: str = "full"):
        return self._twin.volumetric_error(q, *self._split(force_n, motion), method=method)


def block_directions(prog) -> np.ndarray:
    """(M, 3) direction of motion of every row of ``prog`` in program coordinates (X, Y, Z): a line's displacement,
    an arc's tangent at its end (not normalised)."""
    d = (prog.end - prog.start)[:, :3].copy()
    arcs = np.nonzero((prog.motion == ARC_CW) | (prog.motion == ARC_CCW))[0]
    if arcs.size:
        plane = prog.arc_plane[arcs]
        normal = np.select([plane[:, None] == 17, plane[:, None] == 18, plane[:, None] == 19],
                           [np.array([0, 0, 1.0]), np.array([0, 1.0, 0]), np.array([1.0, 0, 0])])
        sense = np.where(prog.motion[arcs] == ARC_CCW, 1.0, -1.0)
        d[arcs] = np.cross(normal, prog.end[arcs, :3] - prog.arc_center[arcs]) * sense[:, None]
    return d


def motion_signs(direction: np.ndarray) -> np.ndarray:
    """(M, k) +1 / -1 per row and axis from the rows' displacements (M, k): the sign of the displacement, the previous
    row's sign where it is zero, +1 before the first move of an axis."""
    sign = np.sign(direction)
    rows = np.arange(sign.shape[0])[:, None]
    last = np.maximum.accumulate(np.where(sign != 0, rows, -1), axis=0)  # the last row that moved the axis
    filled = np.take_along_axis(sign, np.maximum(last, 0), axis=0)
    return np.where(last >= 0, filled, 1.0)


def _turning_conditions(poster):
    """Per program row: the turning conditions valid there (TurningConditions or None)."""
    p = poster.p
    marks = condition_marks(p.lines, p.source)
    if getattr(poster, "rep", None) is not None:  # (a poster made for the forces alone has none)
        note_inch_conditions(poster, marks)
    cli = {k: v for k, v in poster.conditions.items() if v is not None}  # --ap, or a host's conditions=
    milling = sorted(set(cli) - {"ap", "f", "vc"})
    if milling:
        raise PostError(p.source, 1, f"turning takes the cutting conditions ap (mm), f (mm/rev) and vc (m/min); "
                                     f"the conditions given hold {', '.join(milling)}, which are milling's")
    starts = np.array([i for i, _ in marks], dtype=np.int64)
    by_mark = []
    merged: dict = {}
    for i, fields in marks:
        merged = {**merged, **fields}
        by_mark.append(dict(merged))
    k = np.searchsorted(starts, p.line_index, side="right")  # marks at or before each row's line
    out = np.empty(len(p), dtype=object)
    cache: dict = {}
    for r, km in enumerate(k.tolist()):
        fields = {**(by_mark[km - 1] if km else {}), **cli}
        key = tuple(sorted(fields.items()))
        if key not in cache:
            if "ap" in fields and "f" in fields:
                try:
                    cache[key] = TurningConditions.from_mapping({n: float(v) for n, v in fields.items()})
                except ValueError as exc:
                    raise PostError(p.source, int(p.line_index[r]) + 1, f"turning conditions: {exc}") from None
                # the report names each set used, as milling's does (its list was empty on a lathe: a QA pass)
                if getattr(poster, "rep", None) is not None:  # (a poster made for the forces alone has none)
                    poster.rep.cutting_conditions.append({"conditions": {n: str(v) for n, v in fields.items()},
                                                          "first_line": int(p.line_index[r]) + 1, "assumed": []})
            else:
                cache[key] = None
        out[r] = cache[key]
    return out


def _program_state(poster):
    """Everything per program row, computed once for the whole program: conditions, directions, motion signs."""
    p = poster.p
    direction = block_directions(p)
    cols = ["XYZ".index(a) for a in poster.names]  # a lathe's axes are linear
    return _turning_conditions(poster), direction, motion_signs(direction[:, cols])


def lathe_loads(poster, rows) -> np.ndarray:
    """(K, 3 + n_axes) loads of the program rows ``rows``: the force on the tool (N, machine frame) and each axis'
    direction of motion (+1 / -1). Raises PostError without turning coefficients or without conditions at a cut."""
    p, m = poster.p, poster.m
    if not m.cutting:
        raise PostError(p.source, 1, f"comprehensive mode on a lathe needs the turning coefficients [cutting] "
                                     f"kc11, mc (and feed_ratio, passive_ratio) in {m.source}")
    try:
        coeffs = TurningCoefficients.from_mapping(m.cutting)
    except ValueError as exc:
        raise PostError(p.source, 1, f"{m.source}: {exc}") from None
    state = poster.__dict__.get("_turning_state")
    if state is None:
        state = poster._turning_state = _program_state(poster)
    conditions, direction, signs = state
    rows = np.asarray(rows)
    force = np.zeros((rows.size, 3))
    d_xz = direction[rows][:, [0, 2]]
    cutting = (p.motion[rows] != RAPID) & (np.linalg.norm(d_xz, axis=1) > 0.0)
    groups: dict = {}
    for k in np.nonzero(cutting)[0].tolist():
        c = conditions[rows[k]]
        if c is None:
            raise PostError(p.source, int(p.line_no[rows[k]]),
                            "comprehensive mode needs turning conditions here: put (trueaxis: ap=.. f=.. vc=..) "
                            "before the cut (depth of cut mm, feed mm/rev, cutting speed m/min), or give them on the "
                            "command line (--ap --f-rev --vc)")
        groups.setdefault(c, []).append(k)
    _say_feed_disagreements(poster, rows, conditions, groups)
    for c, ks in groups.items():
        try:
            components = turning_force_components(coeffs, c)
        except ValueError as exc:
            raise PostError(p.source, int(p.line_no[rows[ks[0]]]), f"turning force: {exc}") from None
        force[ks] = force_on_tool(components, d_xz[ks])
    return np.hstack([force, signs[rows]])


def _say_feed_disagreements(poster, rows, conditions, groups):
    """A warning, once, where the program feeds per revolution (G95) at another feed than its conditions comment's
    f: the force is computed from the comment's f, while the machine feeds at F (a QA pass: F0.4 under a comment
    f=0.2 cut about 1.8 times the force corrected for, without a word)."""
    if getattr(poster, "rep", None) is None or getattr(poster, "_feed_said", False):
        return
    p = poster.p
    state = poster.__dict__.get("_feed_mode")
    if state is None:  # per line: G95 in force
        state = poster._feed_mode = feed_per_revolution_lines(p.lines)
    for c, ks in groups.items():
        r = np.asarray(rows)[ks]
        per_rev = state[p.line_index[r]]
        feed_mm = p.feed[r] * np.where(p.inch[r], 25.4, 1.0)
        off = per_rev & (feed_mm > 0) & (np.abs(feed_mm - c.f_mm) > 0.01 * c.f_mm)
        if off.any():
            k = int(np.argmax(off))
            poster._feed_said = True
            poster.rep.warnings.append(
                f"{p.source}:{int(p.line_no[r[k]])}: the program feeds F{p.feed[r[k]]:g} per revolution (G95), its "
                f"conditions comment says f={c.f_mm:g} mm/rev: the force is computed from the comment's f; correct the "
                "comment (or the F word)")
            return


def diameter_words(prog, rows, delta_prog, pieces):
    """The program as the writer must write it when blocks are in G7 (lathe diameter mode): the reader keeps X as the
    radius (LinuxCNC halves a G7 X word), so the X of those rows' ends, corrections and split pieces is doubled back.

    prog : Program;  rows : (K,) the compensated rows;  delta_prog : (K, 6) their corrections, program units;
    pieces : {k: (n, 6)} split pieces of rows[k]. Returns (program, delta_prog, pieces) to write. Refuses (PostError)
    what it would not write right: arcs and canned cycles in G7 (their centre words and cycle words are radii or
    positions the writer computes from the written ends), and incremental moves in a program that uses G7 (an
    increment across a G7/G8 switch mixes radius and diameter)."""
    from dataclasses import replace

    from ..nc.gcode import ROW_CYCLE

    diameter = prog.diameter
    bad = diameter & ((prog.motion == ARC_CW) | (prog.motion == ARC_CCW) | (prog.kind == ROW_CYCLE))
    if bad.any():
        r = int(np.argmax(bad))
        raise PostError(prog.source, int(prog.line_no[r]), "arcs and canned cycles in lathe diameter mode (G7) are not "
                                                           "compensated: program them in radius mode (G8)")
    if prog.incremental.any():
        r = int(np.argmax(prog.incremental))
        raise PostError(prog.source, int(prog.line_no[r]), "incremental moves (G91) in a program that uses lathe "
                                                           "diameter mode (G7) are not compensated: write it in G90")
    scale = np.where(diameter, 2.0, 1.0)
    start, end = prog.start.copy(), prog.end.copy()
    start[:, 0] *= scale
    end[:, 0] *= scale
    delta = delta_prog.copy()
    delta[:, 0] *= scale[rows]
    out = {}
    for k, pts in pieces.items():
        pts = np.array(pts, dtype=float)
        pts[:, 0] *= scale[rows[k]]
        out[k] = pts
    return replace(prog, start=start, end=end), delta, out


def arc_point_loads(poster, rows, points6, loads) -> np.ndarray:
    """(n, 3 + n_axes) loads at points on arcs: the force and the direction of motion follow the arc's tangent there.

    rows : (n,) the arc row of each point;  points6 : (n, 6) the points, program coordinates;  loads : (n, 3 + n_axes)
    the rows' block loads (``lathe_loads``: taken at the end tangent), whose direction of motion stays where the
    tangent has no component along an axis."""
    p, m = poster.p, poster.m
    rows = np.asarray(rows)
    plane = p.arc_plane[rows]
    normal = np.select([plane[:, None] == 17, plane[:, None] == 18, plane[:, None] == 19],
                       [np.array([0, 0, 1.0]), np.array([0, 1.0, 0]), np.array([1.0, 0, 0])])
    sense = np.where(p.motion[rows] == ARC_CCW, 1.0, -1.0)
    tangent = np.cross(normal, points6[:, :3] - p.arc_center[rows]) * sense[:, None]
    out = np.array(loads, dtype=float)
    d_xz = tangent[:, [0, 2]]
    moving = np.linalg.norm(d_xz, axis=1) > 0.0
    if np.any(moving):
        coeffs = TurningCoefficients.from_mapping(m.cutting)
        conditions = poster._turning_state[0]
        for c in set(conditions[rows[moving]].tolist()):
            sel = moving & (conditions[rows] == c)
            out[sel, :3] = force_on_tool(turning_force_components(coeffs, c), d_xz[sel])
    cols = ["XYZ".index(a) for a in poster.names]
    signs = np.sign(tangent[:, cols])
    out[:, 3:] = np.where(signs != 0, signs, out[:, 3:])
    return out
