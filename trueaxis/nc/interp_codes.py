"""The interpreter's code tables (which G and M codes it reads, which it refuses, the words' bits and axes), apart from
``gcode`` so that the interpreter's parts (``interp_state``, ``interp_check``, ``interp_convert``) share them without
importing the reader."""

from __future__ import annotations

import numpy as np

AXES = "XYZABC"
MM_PER_INCH = 25.4

# Program.words bit mask: which words the source block had (bit i for letter WORD_BITS[i])
WORD_BITS = "XYZABCIJKRPF"
WORD_BIT = {c: 1 << i for i, c in enumerate(WORD_BITS)}

# Word values (coordinates, offsets, feeds) must stay below this in size: 1000 km, or 25,400 km in inches, is no
# machine's travel, and bounded values keep every sum, square and unit conversion downstream finite. The fast path's
# regular expression takes at most 9 digits before the point, so larger values go through the checked general path.
MAX_WORD_VALUE = 1e9

SYSTEM_NAMES = ("G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3")
AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2, "A": 3, "B": 4, "C": 5}
LINEAR = np.array([True, True, True, False, False, False])
LINEAR_T = (True, True, True, False, False, False)

KNOWN_M = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 19, 30, 48, 49, 50, 51, 52, 53, 60, 61, 62, 63, 64, 65, 66, 67, 68, 70, 71,
           72, 73}
MOVING_M = {98: "subprogram call M98", 99: "subprogram return M99"}
# G codes (x10) whose moves the reader cannot reproduce: refused (or passed through on request)
MOVING_G = {
    650: "macro call G65", 660: "modal macro call G66", 661: "modal macro call G66.1",
    330: "spindle-synchronised motion G33", 331: "rigid tapping G33.1", 760: "threading cycle G76",
    382: "probing G38.2", 383: "probing G38.3", 384: "probing G38.4", 385: "probing G38.5",
    50: "spline G5", 51: "spline G5.1", 52: "NURBS G5.2",
    520: "local coordinate offset G52 (later positions read without it)",
    171: "plane G17.1", 181: "plane G18.1", 191: "plane G19.1",
}
# why those whose moves are in the text are refused all the same (the others: their moves are not in the text)
SYNCED_G = {
    330: "its feed is bound to the spindle's turn, a thread's lead: the post does not compensate threading passes",
    331: "its feed is bound to the spindle's turn, the tap's pitch, and it returns to its start: the post does not "
         "compensate tapping"}
# those of them after which the control's position is not known from the text (not G52's offset, not the planes)
POSITION_LOST_G = frozenset(MOVING_G) - {520, 171, 181, 191}
MOTION_G = (0, 10, 20, 30, 730, 740, 810, 820, 830, 840, 850, 860, 870, 880, 890)
CYCLE_G = frozenset(MOTION_G[4:])


def add(pos: list, delta) -> None:
    """pos += delta, in place, for the 6-element position list."""
    for i in range(6):
        pos[i] += float(delta[i])
