"""Runs of plain straight moves interpreted in compiled code (the reader's hot path, :mod:`.gcode`).

The reader (``gcode._Interpreter.run``) reads a plain block that the pre-scan (:mod:`.fast_read`) has read
("N300G1X4.6526Z-.0007", "X1 Y2 F300") in a few Python statements: the motion mode, the feed, the target position, a
row of the motion table. :func:`straight_run` does the same for a whole run of such lines at once, in compiled code,
with the same operations in the same order (so the same numbers, bit for bit), and stops at the first line it does not
take, which the reader then reads as before. It takes a line when the reader's fast path would emit a straight row
for it:

- the pre-scan read it (``LINE_FAST``): an optional N, an optional G0..G3, the words X..C I J K R F;
- no I J K R word, and the motion mode in force after it (its G word, else the modal one) is G0 or G1;
- its F word (if any) is not negative; and G0, or a feed rate that is not zero, given on the line when inverse time
  (G93) is in force.

Everything else (arcs, canned cycles, a G1 with no feed, a negative F, every other block) stops the run. What the
reader keeps per row beyond the numbers, the state index (feed, modes, offsets), changes only where the feed changes:
:func:`straight_run` returns the feed after every row and the reader maps the changes to its states.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["straight_run", "MIN_RUN"]

MIN_RUN = 16  # shorter runs of plain lines are read by the reader's own loop (a run costs some 20 us to hand over)

_F_BIT = 2048  # gcode._WORD_BIT["F"]


@numba.njit(cache=True, nogil=True)
def straight_run(status, gs, vals, lo, pos0, motion_mode, feed, absolute, inverse, diameter):
    """Interpret lines lo.. of a pre-scanned block (``fast_read.scan_lines``' status, g, vals) while each is a plain
    straight move (module docstring).

    pos0 (6,): the position before line lo (program units, degrees); motion_mode: the modal motion (G code * 10);
    feed: the feed rate in force; absolute (G90), inverse (G93), diameter (G7).

    Returns (count, start (count, 6), end (count, 6), motion (count,) 0 / 1, words (count,) the reader's word bits,
    feeds (count,) the feed in force after each line, g_seen: some line had a G word)."""
    m = status.shape[0]
    count = 0
    f_now = feed
    mode_now = motion_mode
    # the run's length first (nothing is changed for the line that stops it)
    for r in range(lo, m):
        if status[r] != 2:  # fast_read.LINE_FAST
            break
        g = gs[r]
        mode = mode_now if g < 0 else g * 10
        if mode > 10:
            break
        if vals[r, 6] == vals[r, 6] or vals[r, 7] == vals[r, 7] or vals[r, 8] == vals[r, 8] \
                or vals[r, 9] == vals[r, 9]:
            break  # I J K R: the reader refuses or reads them
        f_ = vals[r, 10]
        has_f = f_ == f_
        f_next = f_now
        if has_f:
            if f_ < 0.0:
                break  # the reader's message
            f_next = f_
        if not (mode == 0 or (f_next != 0.0 and (has_f or not inverse))):
            break
        f_now = f_next
        mode_now = mode
        count += 1
    start = np.empty((count, 6))
    end = np.empty((count, 6))
    motion = np.empty(count, np.int64)
    words = np.empty(count, np.int64)
    feeds = np.empty(count)
    pos = pos0.copy()
    f_now = feed
    mode_now = motion_mode
    g_seen = False
    for k in range(count):
        r = lo + k
        g = gs[r]
        if g >= 0:
            g_seen = True
        mode = mode_now if g < 0 else g * 10
        x = vals[r, 0]
        if diameter and x == x:
            x = 0.5 * x
        f_ = vals[r, 10]
        if f_ == f_:
            f_now = f_
        seen = 0
        for n in range(6):
            start[k, n] = pos[n]
            v = x if n == 0 else vals[r, n]
            if v == v:
                pos[n] = v if absolute else pos[n] + v
                seen |= 1 << n
            end[k, n] = pos[n]
        if f_ == f_:
            seen |= _F_BIT
        motion[k] = mode // 10
        words[k] = seen
        feeds[k] = f_now
        mode_now = mode
    return count, start, end, motion, words, feeds, g_seen


ENABLED = True  # False: every line by the reader's own loop (the reference; the same rows)


def feed_changes(feeds, feed) -> list:
    """Rows of a run (:func:`straight_run`'s feeds) where the feed differs from the one before (``feed`` before the
    first): where the reader refreshes its state."""
    prev = np.empty_like(feeds)
    prev[0] = feed
    prev[1:] = feeds[:-1]
    return np.nonzero(feeds != prev)[0].tolist()


def append_rows(run, li, state0, changed, r_start, r_end, r_line, r_motion, r_kind, r_words, r_state, kind):
    """Append a run (:func:`straight_run`, from line ``li``) to the reader's packed row arrays; ``state0``: the state
    index before it, ``changed``: (row, state index from there on). Returns (position after it as a list, motion
    mode)."""
    count, start, end, motion, words, _, _ = run
    r_start.frombytes(np.ascontiguousarray(start).tobytes())
    r_end.frombytes(np.ascontiguousarray(end).tobytes())
    r_line.frombytes(np.arange(li, li + count, dtype=np.int64).tobytes())
    r_motion.frombytes(motion.astype(np.int64).tobytes())
    r_kind.frombytes(np.full(count, kind, np.int64).tobytes())
    r_words.frombytes(words.astype(np.int64).tobytes())
    bounds = [0] + [c for c, _ in changed] + [count]
    states = np.repeat(np.array([state0] + [sid for _, sid in changed], np.int64), np.diff(bounds))
    r_state.frombytes(states.tobytes())
    return end[count - 1].tolist(), int(motion[count - 1]) * 10


@numba.njit(cache=True, nogil=True)
def run_lengths(status, gs, vals):
    """(m,) int64: how many lines from each line of a pre-scanned block on could be a run for :func:`straight_run`
    (read by the pre-scan, G0 / G1 / no G word, no I J K R word; the modal state may still stop the run earlier)."""
    m = status.shape[0]
    out = np.zeros(m, np.int64)
    n = 0
    for r in range(m - 1, -1, -1):
        if status[r] == 2 and gs[r] <= 1 and not (vals[r, 6] == vals[r, 6] or vals[r, 7] == vals[r, 7]
                                                  or vals[r, 8] == vals[r, 8] or vals[r, 9] == vals[r, 9]):
            n += 1
        else:
            n = 0
        out[r] = n
    return out
