"""Interpolation of an NC program's motion at a fixed period: the commanded axes q(t) of the virtual machine.

The program (``trueaxis.nc.gcode.Program``) gives one row per move in program units. Here every row becomes a
segment of machine-axis motion (mm, rad) with a duration from its feed, and the whole run is sampled on one clock
``t_k = k dt`` (default dt = 1 ms, a typical CNC interpolation period).

Conventions (LinuxCNC's, DESIGN §5)
-----------------------------------
- Machine axes: the program's coordinates are taken as the machine axes q (a machine-axis program; X Y Z are the
  tool tip with tool length compensation active). ``coordinates="machine"`` adds ``Program.offset`` (work offsets and
  G92; note that it also holds the tool length offset, which a tip-position program must not carry).
- Units: G20 lengths are converted to mm; rotary words (degrees) to rad.
- Feed, G94: F in program units per minute along the XYZ path length (arcs: the helical length); a move with no XYZ
  motion but rotary motion takes F in deg/min along the rotary path length sqrt(sum dA^2) in degrees. G93: the move
  lasts 1/F minutes. Rapids: every axis at its rapid rate (``rapid_mm_min`` for linear axes, ``rapid_deg_min`` for
  rotary ones), all axes arriving together (the slowest axis sets the duration), straight in axis space, then the
  command holds for ``rapid_settle_s`` (in-position wait).
- Every block lasts a whole number of periods (its time from the feed rounded up), as in a CNC interpolator, so that
  block ends are samples; the speed of a block is therefore at most one period's worth slower than programmed.
- Feed moves are interpolated at constant speed (no acceleration profile here: axis dynamics are the servo-lag effect
  of ``effects``). Arcs are interpolated exactly: the angle about the centre is linear in time, the normal-axis
  coordinate and any rotary axes too (a helix).
- Zero-duration rows (no motion) get no sample; the final position is sampled as the last sample.

Everything is vectorised over rows and samples (``np.searchsorted`` on cumulative durations); there is no Python loop
over samples or blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..machine.model import Machine
from .gcode import feed_per_revolution_lines

AXES = "XYZABC"
MM_PER_INCH = 25.4
PERIOD_S = 1e-3  # the interpolation period, s (a typical CNC's)


@dataclass
class Trajectory:
    """Commanded machine-axis motion sampled at a fixed period.

    t : (T,) s, sample times (k dt; the last sample is the end of the program).
    q : (T, n_axes) mm / rad, commanded axes, columns ``axis_names`` (the machine's canonical order).
    qdot : (T, n_axes) mm/s / rad/s, commanded axis velocity of the segment each sample lies on.
    row : (T,) int, Program row (motion table index) each sample lies on.
    line : (T,) int, 0-based source line index of that row (``Program.line_index``).
    motion : (T,) int, motion code of that row (0 rapid, 1 feed, 2 cw arc, 3 ccw arc).
    feed_mm_min : (T,) float, programmed path speed of the row in mm/min along XYZ (deg/min for rotary-only moves).
    dt : float, s.  axis_names : tuple of str.
    row_start_t, row_duration : (M,) s, start time and duration of every program row.
    """

    t: np.ndarray
    q: np.ndarray
    qdot: np.ndarray
    row: np.ndarray
    line: np.ndarray
    motion: np.ndarray
    feed_mm_min: np.ndarray
    dt: float
    axis_names: tuple
    row_start_t: np.ndarray
    row_duration: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])


def _program_axes(program, machine: Machine, coordinates: str):
    """Row start / end in machine-axis units (M, 6) mm and rad, plus arc centres (M, 3) mm."""
    if coordinates == "program":
        start, end = program.start.astype(float), program.end.astype(float)
        center = program.arc_center.astype(float)
    elif coordinates == "machine":
        start = program.to_machine(program.start)
        end = program.to_machine(program.end)
        c6 = np.zeros_like(program.start)
        c6[:, :3] = program.arc_center
        center = program.to_machine(c6)[:, :3]
    else:
        raise ValueError(f"coordinates must be 'program' or 'machine', got {coordinates!r}")
    lin = np.where(program.inch, MM_PER_INCH, 1.0)[:, None]
    sign = machine.word_signs6()[3:]  # [kinematics] rotary_sense: LinuxCNC trt words are the model's angles negated
    start = np.concatenate([start[:, :3] * lin, np.radians(start[:, 3:]) * sign], axis=1)
    end = np.concatenate([end[:, :3] * lin, np.radians(end[:, 3:]) * sign], axis=1)
    center = center * lin
    return start, end, center


def _arc_geometry(start, end, center, plane, motion, turns):
    """Per arc row: plane axis indices, start angle, signed sweep (rad), radius (mm), normal travel (mm).

    Plane axes follow LinuxCNC's ARC_FEED order: G17 (X, Y; normal Z), G18 (Z, X; normal Y), G19 (Y, Z; normal X);
    the angle is measured in (first, second) coordinates, counter-clockwise positive; G2 sweeps negative.
    """
    first = np.select([plane == 17, plane == 18, plane == 19], [0, 2, 1], 0)
    second = np.select([plane == 17, plane == 18, plane == 19], [1, 0, 2], 1)
    normal = np.select([plane == 17, plane == 18, plane == 19], [2, 1, 0], 2)
    idx = np.arange(start.shape[0])
    u0 = start[idx, first] - center[idx, first]
    v0 = start[idx, second] - center[idx, second]
    u1 = end[idx, first] - center[idx, first]
    v1 = end[idx, second] - center[idx, second]
    a0 = np.arctan2(v0, u0)
    a1 = np.arctan2(v1, u1)
    ccw = motion == 3
    sweep = np.where(ccw, np.mod(a1 - a0, 2 * np.pi), -np.mod(a0 - a1, 2 * np.pi))
    # A full circle (end == start) sweeps one whole turn; P > 1 adds turns.
    full = np.abs(sweep) < 1e-12
    sweep = np.where(full, np.where(ccw, 2 * np.pi, -2 * np.pi), sweep)
    extra = np.maximum(turns.astype(float) - 1.0, 0.0) * 2 * np.pi
    sweep = sweep + np.where(ccw, extra, -extra)
    radius = np.hypot(u0, v0)
    dn = end[idx, normal] - start[idx, normal]
    return first, second, normal, a0, sweep, radius, dn


def _refuse_feed_per_revolution(program, cut) -> None:
    """ValueError naming the first feed move under G95: its F is per spindle revolution, and the spindle speed (and
    under G96 the turned radius) that would make it a time is not read here. (It was read as per minute: F0.2 mm/rev
    made a 100 mm cut last 500 minutes of the virtual shop's clock.)"""
    if not program.lines:
        return
    per_rev = feed_per_revolution_lines(program.lines)[program.line_index] & cut
    if np.any(per_rev):
        i = int(np.argmax(per_rev))
        raise ValueError(f"{program.source}:{program.line_index[i] + 1}: feed per revolution (G95): a time along the "
                         "program needs the feed per minute, and the spindle speed is not read; give the program in "
                         "G94 (or G93) to simulate or diagnose it")


def _durations(program, delta, lin_len, rot_len_deg, dt, rapid_mm_min, rapid_deg_min, rapid_settle_s):
    """Each row's duration (s: whole interpolation periods, a rapid's settling time added), its moving time and its
    path speed (mm/min, or deg/min for a rotary-only move)."""
    m = len(program)
    motion = program.motion.astype(int)
    feed = program.feed.astype(float)
    feed_mm = feed * np.where(program.inch, MM_PER_INCH, 1.0)
    moving = (lin_len > 1e-12) | (rot_len_deg > 1e-12)
    duration = np.zeros(m)
    rapid = motion == 0
    if np.any(rapid):
        per_axis = np.concatenate(
            [np.abs(delta[:, :3]) / (rapid_mm_min / 60.0), np.degrees(np.abs(delta[:, 3:])) / (rapid_deg_min / 60.0)],
            axis=1,
        )
        duration = np.where(rapid, per_axis.max(axis=1), duration)
    cut = ~rapid & moving
    bad = cut & (feed <= 0)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(f"{program.source}:{program.line_index[i] + 1}: feed move with zero feed rate")
    _refuse_feed_per_revolution(program, cut)
    inv = program.inverse_time.astype(bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_g94 = np.where(lin_len > 1e-12, lin_len / feed_mm, rot_len_deg / feed) * 60.0
        t_g93 = 60.0 / feed
    duration = np.where(cut, np.where(inv, t_g93, t_g94), duration)
    duration = np.where(moving, duration, 0.0)
    # Like a CNC's interpolator, every block takes a whole number of interpolation periods (its time rounded up), so
    # that every block end is a sample: the tool passes through each corner and end point exactly, as the continuous
    # motion does, instead of skipping up to one period of path (17 um at 1000 mm/min) at every block end.
    duration = np.where(moving, np.ceil(duration / dt - 1e-9) * dt, 0.0)
    move_time = duration.copy()
    duration = np.where(rapid & moving, duration + max(0.0, float(rapid_settle_s)), duration)
    path_speed = np.where(duration > 0, np.where(lin_len > 1e-12, lin_len, rot_len_deg) / np.maximum(move_time, 1e-300)
                          * 60.0, 0.0)
    return duration, move_time, path_speed


def interpolate(
    program,
    machine: Machine,
    dt: float = PERIOD_S,
    *,
    rapid_mm_min: float = 10_000.0,
    rapid_deg_min: float = 3_600.0,
    coordinates: str = "program",
    rapid_settle_s: float = 0.2,
) -> Trajectory:
    """Sample a program's commanded machine axes at a fixed period.

    program : ``Program`` from ``trueaxis.nc.gcode.parse_program``.
    machine : the machine (its axes name the columns of q; the program may not use an axis it does not have).
    dt : interpolation period, s (> 0).
    rapid_mm_min, rapid_deg_min : rapid rates of linear (mm/min) and rotary (deg/min) axes.
    coordinates : "program" (default) or "machine" (see the module docstring).
    rapid_settle_s : the command holds the end of every rapid this long (s), the control's in-position wait, so that
        a lagging servo reaches it before the next feed move (without it a servo-lag effect would carry the rapid's
        lag into the cut).

    Returns a :class:`Trajectory`.
    """
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    if not (rapid_mm_min > 0 and rapid_deg_min > 0):
        raise ValueError("rapid rates must be positive")
    names = machine.axis_names
    unused = [a for a in program.axes_present if a not in names]
    if unused:
        raise ValueError(f"{program.source}: the program moves axes {' '.join(unused)} that {machine.name} does not have")
    m = len(program)
    if m == 0:
        raise ValueError(f"{program.source}: no motion in the program")
    cols = [AXES.index(a) for a in names]
    start, end, center = _program_axes(program, machine, coordinates)
    motion = program.motion.astype(int)
    is_arc = (motion == 2) | (motion == 3)
    delta = end - start

    # Path lengths: XYZ (mm) and rotary (deg); arcs use their helical length.
    lin_len = np.linalg.norm(delta[:, :3], axis=1)
    first, second, normal, a0, sweep, radius, dn = _arc_geometry(
        start, end, np.nan_to_num(center), program.arc_plane.astype(int), motion, program.arc_turns
    )
    arc_len = np.hypot(radius * sweep, dn)
    lin_len = np.where(is_arc, arc_len, lin_len)
    rot_len_deg = np.degrees(np.linalg.norm(delta[:, 3:], axis=1))

    duration, move_time, path_speed = _durations(program, delta, lin_len, rot_len_deg, dt, rapid_mm_min,
                                                 rapid_deg_min, rapid_settle_s)

    t_end = np.cumsum(duration)
    t_start = t_end - duration
    total = float(t_end[-1]) if m else 0.0
    n_samples = int(np.floor(total / dt + 1e-9)) + 1
    t = np.arange(n_samples) * dt
    # The row each sample lies on: the first row whose end time is after t (zero-duration rows are skipped).
    row = np.searchsorted(t_end, t, side="right")
    row = np.minimum(row, m - 1)
    # Skip trailing zero-duration rows for the last samples.
    last_moving = np.nonzero(duration > 0)[0]
    if last_moving.size == 0:
        raise ValueError(f"{program.source}: the program does not move any axis")
    row = np.minimum(row, last_moving[-1])
    dur = move_time[row]
    s = np.clip((t - t_start[row]) / np.where(dur > 0, dur, 1.0), 0.0, 1.0)

    q6 = start[row] + s[:, None] * delta[row]
    qdot6 = np.where((dur[:, None] > 0) & (s[:, None] < 1.0), delta[row] / np.where(dur > 0, dur, 1.0)[:, None], 0.0)
    arc = is_arc[row]
    if np.any(arc):
        r = row[arc]
        k = np.nonzero(arc)[0]
        ang = a0[r] + s[arc] * sweep[r]
        c0 = center[r, first[r]]
        c1 = center[r, second[r]]
        q6[k, first[r]] = c0 + radius[r] * np.cos(ang)
        q6[k, second[r]] = c1 + radius[r] * np.sin(ang)
        w = sweep[r] / np.maximum(dur[arc], 1e-300)  # rad/s
        qdot6[k, first[r]] = -radius[r] * np.sin(ang) * w
        qdot6[k, second[r]] = radius[r] * np.cos(ang) * w
    # Exact end point on the last sample.
    q6[-1] = end[row[-1]]
    return Trajectory(
        t=t,
        q=np.ascontiguousarray(q6[:, cols]),
        qdot=np.ascontiguousarray(qdot6[:, cols]),
        row=row,
        line=program.line_index[row].astype(int),
        motion=motion[row],
        feed_mm_min=path_speed[row],
        dt=float(dt),
        axis_names=tuple(names),
        row_start_t=t_start,
        row_duration=duration,
    )
