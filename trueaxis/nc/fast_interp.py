"""Runs of plain moves interpreted in compiled code (the reader's hot path, :mod:`.gcode`).

The reader (``gcode._Interpreter.run``) reads a plain block that the pre-scan (:mod:`.fast_read`) has read
("N300G1X4.6526Z-.0007", "X1 Y2 F300", "G2X1.Y2.I.5J0") in a few Python statements: the motion mode, the feed, the
target position, an arc's centre, a row of the motion table. :func:`straight_run` does the same for a whole run of
such lines at once, in compiled code, with the same operations in the same order (so the same numbers, bit for bit),
and stops at the first line it does not take, which the reader then reads as before. It takes a line when the
reader's fast path would emit a row for it without help:

- the pre-scan read it (``LINE_FAST``): an optional N, an optional G0..G3, the words X..C I J K R F;
- the motion mode in force after it (its G word, else the modal one) is G0 or G1 with no I J K R word, or G2 / G3
  with a centre word (I J K) of its plane and no R word, whose end point lies on the circle (the reader's test,
  decided here only when it passes by more than the last bits of ``hypot``);
- its F word (if any) is not negative; and G0, or a feed rate that is not zero, given on the line when inverse time
  (G93) is in force.

Everything else (R arcs, arcs the reader refuses or has to decide, canned cycles, a G1 with no feed, a negative F,
every other block) stops the run. What the reader keeps per row beyond the numbers, the state index (feed, modes,
offsets), changes only where the feed changes: :func:`straight_run` returns the feed after every row and the reader
maps the changes to its states.
"""

from __future__ import annotations

from ..compiled import numba  # numba, or the kernels compiled ahead of time (see ..compiled)
import numpy as np

__all__ = ["straight_run", "MIN_RUN"]

MIN_RUN = 16  # shorter runs of plain lines are read by the reader's own loop (a run costs some 20 us to hand over)

_F_BIT = 2048  # gcode._WORD_BIT["F"]


# plane (17, 18, 19) -> the axes of the arc's plane and its normal (gcode._PLANE_AXES)
_PLANE = np.array([[0, 1, 2], [2, 0, 1], [1, 2, 0]], np.int64)
_ULP_MARGIN = 8 * 2.0**-52  # relative: more than hypot's rounding in the reader and here (1 ulp each)


@numba.njit(cache=True, nogil=True)
def _arc_ok(x0, y0, x1, y1, c0, c1, arc_tol, arc_rmin):
    """The reader's test of an I J K arc's radii (``interp_arc.ijk_radii_refusal``, LinuxCNC's: neither below
    arc_rmin, their difference within arc_tol or 0.1 % of the larger, and within 100 arc_tol), +1 passed / -1 failed
    with a margin beyond the last bits of hypot (the reader's math.hypot and this one may differ in the last bit), 0
    too close to call here (the reader decides)."""
    rad1 = np.hypot(x0 - c0, y0 - c1)
    rad2 = np.hypot(x1 - c0, y1 - c1)
    big = max(rad1, rad2)
    small = min(rad1, rad2)
    dr = abs(rad1 - rad2)
    slack = _ULP_MARGIN * big
    if small - slack >= arc_rmin and dr + slack <= 100.0 * arc_tol and (
            dr + slack <= arc_tol or dr + slack <= 0.001 * big * (1.0 - _ULP_MARGIN)):
        return 1
    if small + slack < arc_rmin or dr - slack > 100.0 * arc_tol or (
            dr - slack > arc_tol and dr - slack > 0.001 * big * (1.0 + _ULP_MARGIN)):
        return -1
    return 0


@numba.njit(cache=True, nogil=True)
def straight_run(status, gs, vals, lo, pos0, motion_mode, feed, absolute, inverse, diameter, plane, arc_abs,
                 arc_tol, arc_rmin):
    """Interpret lines lo.. of a pre-scanned block (``fast_read.scan_lines``' status, g, vals) while each is a plain
    straight move or an I J K arc the reader's inlined arc path takes (module docstring).

    pos0 (6,): the position before line lo (program units, degrees); motion_mode: the modal motion (G code * 10);
    feed: the feed rate in force; absolute (G90), inverse (G93), diameter (G7), plane (17 / 18 / 19), arc_abs
    (G90.1), arc_tol and arc_rmin (the reader's tolerances of an arc's radii: ``interp_arc``, program units).

    Returns (count, start (count, 6), end (count, 6), motion (count,) 0..3, words (count,) the reader's word bits,
    feeds (count,) the feed in force after each line, g_seen: some line had a G word, centres (count, 3): the arcs'
    centres (NaN on straight rows))."""
    m = status.shape[0]
    a0 = _PLANE[plane - 17, 0]
    a1 = _PLANE[plane - 17, 1]
    an = _PLANE[plane - 17, 2]
    start = np.empty((m - lo, 6))
    end = np.empty((m - lo, 6))
    motion = np.empty(m - lo, np.int64)
    words = np.empty(m - lo, np.int64)
    feeds = np.empty(m - lo)
    centres = np.full((m - lo, 3), np.nan)
    pos = pos0.copy()
    target = pos0.copy()
    f_now = feed
    mode_now = motion_mode
    g_seen = False
    count = 0
    for r in range(lo, m):
        if status[r] != 2:  # fast_read.LINE_FAST
            break
        g = gs[r]
        mode = mode_now if g < 0 else g * 10
        if mode > 30 or vals[r, 9] == vals[r, 9]:
            break  # R arcs (and canned cycles): the reader
        arcw = vals[r, 6] == vals[r, 6] or vals[r, 7] == vals[r, 7] or vals[r, 8] == vals[r, 8]
        if (mode <= 10) == arcw:
            break  # I J K on a straight move, or an arc without them: the reader's message
        f_ = vals[r, 10]
        has_f = f_ == f_
        f_next = f_now
        if has_f:
            if f_ < 0.0:
                break  # the reader's message
            f_next = f_
        if not (mode == 0 or (f_next != 0.0 and (has_f or not inverse))):
            break
        x = vals[r, 0]
        if diameter and x == x:
            x = 0.5 * x
        seen = 0
        for n in range(6):
            v = x if n == 0 else vals[r, n]
            target[n] = pos[n]
            if v == v:
                target[n] = v if absolute else pos[n] + v
                seen |= 1 << n
        if has_f:
            seen |= _F_BIT
        k = count
        if arcw:
            w0 = vals[r, 6 + a0]
            w1 = vals[r, 6 + a1]
            if not (w0 == w0 or w1 == w1):
                break  # no centre word in the plane: the reader
            if vals[r, 6 + an] == vals[r, 6 + an]:
                break  # a centre word along the plane's normal: the reader refuses it
            o0 = w0 if w0 == w0 else 0.0
            o1 = w1 if w1 == w1 else 0.0
            if arc_abs:
                c0, c1 = o0, o1
            else:
                c0, c1 = pos[a0] + o0, pos[a1] + o1
            if _arc_ok(pos[a0], pos[a1], target[a0], target[a1], c0, c1, arc_tol, arc_rmin) != 1:
                break  # off the circle, or too close to call: the reader
            for n in range(3):
                if vals[r, 6 + n] == vals[r, 6 + n]:
                    seen |= 1 << (6 + n)
            centres[k, a0] = c0
            centres[k, a1] = c1
            centres[k, an] = pos[an]
        if g >= 0:
            g_seen = True
        for n in range(6):
            start[k, n] = pos[n]
            end[k, n] = target[n]
            pos[n] = target[n]
        f_now = f_next
        mode_now = mode
        motion[k] = mode // 10
        words[k] = seen
        feeds[k] = f_now
        count += 1
    return (count, start[:count], end[:count], motion[:count], words[:count], feeds[:count], g_seen,
            centres[:count])

ENABLED = True  # False: every line by the reader's own loop (the reference; the same rows)


def feed_changes(feeds, feed) -> list:
    """Rows of a run (:func:`straight_run`'s feeds) where the feed differs from the one before (``feed`` before the
    first): where the reader refreshes its state."""
    prev = np.empty_like(feeds)
    prev[0] = feed
    prev[1:] = feeds[:-1]
    return np.nonzero(feeds != prev)[0].tolist()


def append_rows(run, li, state0, changed, r_start, r_end, r_line, r_motion, r_kind, r_words, r_state, kind,
                r_arc_runs, plane):
    """Append a run (:func:`straight_run`, from line ``li``) to the reader's packed row arrays; ``state0``: the state
    index before it, ``changed``: (row, state index from there on); its arcs go to ``r_arc_runs`` as (rows (k,),
    centres (k, 3), plane), one turn each. Returns (position after it as a list, motion mode)."""
    count, start, end, motion, words, _, _, centres = run
    r_start.frombytes(np.ascontiguousarray(start).tobytes())
    r_end.frombytes(np.ascontiguousarray(end).tobytes())
    r_line.frombytes(np.arange(li, li + count, dtype=np.int64).tobytes())
    r_motion.frombytes(motion.astype(np.int64).tobytes())
    r_kind.frombytes(np.full(count, kind, np.int64).tobytes())
    r_words.frombytes(words.astype(np.int64).tobytes())
    bounds = [0] + [c for c, _ in changed] + [count]
    states = np.repeat(np.array([state0] + [sid for _, sid in changed], np.int64), np.diff(bounds))
    r_state.frombytes(states.tobytes())
    arcs = np.nonzero(motion >= 2)[0]
    if arcs.size:
        first = len(r_line) - count
        r_arc_runs.append((arcs + first, centres[arcs], plane))
    return end[count - 1].tolist(), int(motion[count - 1]) * 10


@numba.njit(cache=True, nogil=True)
def run_lengths(status, gs, vals):
    """(m,) int64: how many lines from each line of a pre-scanned block on could be a run for :func:`straight_run`
    (read by the pre-scan, no R word; the modal state may still stop the run earlier)."""
    m = status.shape[0]
    out = np.zeros(m, np.int64)
    n = 0
    for r in range(m - 1, -1, -1):
        if status[r] == 2 and vals[r, 9] != vals[r, 9]:
            n += 1
        else:
            n = 0
        out[r] = n
    return out
