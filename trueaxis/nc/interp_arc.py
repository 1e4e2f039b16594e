"""Arcs (G2 / G3) of the interpreter, as LinuxCNC's ``interp_arc.cc`` computes them: the centre from I J K (or R),
the end point checked on the circle, the turns of P. A part of ``gcode._Interpreter`` (the methods of
``ArcConversion``)."""

from __future__ import annotations

import math

from .grammar import CENTER_WORD, PLANE_AXES
from .rows import ARC_CCW, ARC_CW, MAX_ARC_TURNS, ROW_PROGRAMMED

# LinuxCNC's tolerances of an arc's radii (interp_internal.hh), in program units, by G20 (True) or G21 (False):
# RADIUS_MIN (RADIUS_TOLERANCE): a radius below it is a zero-radius arc, and an R arc's radius may fall short of half
# its chord by at most it; SPIRAL_ABS (the default CENTER_ARC_RADIUS_TOLERANCE, 2 x 0.001 in x sqrt 2 and 2 x 0.01 mm x
# sqrt 2): an I J K arc's radii to its start and end may differ by it, by more only within SPIRAL_REL of the larger,
# never by 100 times it (interp_arc.cc, arc_data_ijk); SPIRAL_ABS_MIN (MIN_CENTER_ARC_RADIUS_TOLERANCE): the smallest
# spiral tolerance a configuration may set, which the post's own arcs keep to.
RADIUS_MIN = {True: 0.00005, False: 0.00127}
SPIRAL_ABS = {True: 2 * 0.001 * math.sqrt(2), False: 2 * 0.01 * math.sqrt(2)}
SPIRAL_REL = 0.001
SPIRAL_ABS_MIN = {True: 0.00004, False: 0.001}


def ijk_radii_refusal(r1: float, r2: float, spiral_abs: float, radius_min: float) -> str | None:
    """Why LinuxCNC refuses an I J K arc whose radii to its start and end are r1 and r2 (program units), or None:
    arc_data_ijk's two checks, in its order and with its arithmetic."""
    if r1 < radius_min or r2 < radius_min:
        return (f"arc of zero radius (radius {r1:.5g} at the start, {r2:.5g} at the end: LinuxCNC refuses a radius "
                f"below {radius_min:g})")
    abs_err = abs(r1 - r2)
    if abs_err > spiral_abs * 100.0 or (abs_err / max(r1, r2) > SPIRAL_REL and abs_err > spiral_abs):
        return (f"arc end point is not on the circle: radius {r1:.5g} at the start, {r2:.5g} at the end (LinuxCNC "
                f"refuses a difference beyond {spiral_abs:.4g} and {SPIRAL_REL:.1%} of the radius, or beyond "
                f"{100 * spiral_abs:.4g})")
    return None


def arc_center_r(start, end, radius, cw, tol):
    """Centre of an R-format arc in its plane, as LinuxCNC's arc_data_r computes it. start/end: (2,) first/second."""
    abs_r = abs(radius)
    mid0, mid1 = (start[0] + end[0]) / 2.0, (start[1] + end[1]) / 2.0
    half = math.hypot(mid0 - end[0], mid1 - end[1])
    if half == 0.0:
        raise ValueError("an R-format arc cannot be a full circle (start equals end): use I J K")
    if half - abs_r > tol:
        raise ValueError(f"arc radius R{radius:g} too small to reach the end point")
    if half / abs_r > 1.0 - 1e-12:
        half = abs_r
    if (cw and radius > 0) or ((not cw) and radius < 0):
        theta = math.atan2(end[1] - start[1], end[0] - start[0]) - math.pi / 2
    else:
        theta = math.atan2(end[1] - start[1], end[0] - start[0]) + math.pi / 2
    offset = abs_r * math.cos(math.asin(half / abs_r))
    return mid0 + offset * math.cos(theta), mid1 + offset * math.sin(theta)


class ArcConversion:
    """The interpreter's arc moves (mixed into ``gcode._Interpreter``: ``self.err`` names the block)."""

    def arc(self, line_no, li, mm, fvals, ax, pos, plane, absolute, arc_abs, inch, feed, inverse, emit, words_mask):
        if inverse and "F" not in fvals:
            raise self.err(line_no, "G93 inverse-time feed needs an F word on every feed block")
        if feed == 0.0:
            raise self.err(line_no, "arc with zero feed rate (no F word yet)")
        target = list(pos)
        for i, v in ax:
            target[i] = v if absolute else pos[i] + v
        self.arc_to(line_no, li, mm, fvals, target, pos, plane, arc_abs, inch, emit, words_mask)

    def arc_to(self, line_no, li, mm, fvals, target, pos, plane, arc_abs, inch, emit, words_mask):
        """Emit the arc from ``pos`` to ``target`` (program coordinates); centre from I J K (or R) in ``fvals``."""
        a0, a1, an = PLANE_AXES[plane]
        cw = mm == 20
        tol = RADIUS_MIN[bool(inch)]  # (an R arc's radius short of half its chord)
        # rs274's checks of the centre words: none along the plane's normal (a K in G17 would otherwise be dropped
        # from the output, an arc the control refuses), and not together with R
        normal_word = CENTER_WORD[an]
        if normal_word in fvals:
            raise ValueError(f"{normal_word} word given for an arc in the G{plane} plane (its centre words are "
                             f"{' and '.join(sorted((CENTER_WORD[a0], CENTER_WORD[a1])))})")
        if "R" in fvals and any(w in fvals for w in "IJK"):
            raise ValueError("R and I J K words given for one arc: radius format or centre format, not both")
        if "R" in fvals:
            c0, c1 = arc_center_r((pos[a0], pos[a1]), (target[a0], target[a1]), fvals["R"], cw, tol)
        else:
            w0, w1 = CENTER_WORD[a0], CENTER_WORD[a1]
            if w0 not in fvals and w1 not in fvals:
                raise ValueError(f"G{mm // 10} arc in the G{plane} plane needs R or {w0}/{w1}")
            o0, o1 = fvals.get(w0, 0.0), fvals.get(w1, 0.0)
            if arc_abs:
                c0, c1 = o0, o1
            else:
                c0, c1 = pos[a0] + o0, pos[a1] + o1
            refusal = ijk_radii_refusal(math.hypot(pos[a0] - c0, pos[a1] - c1),
                                        math.hypot(target[a0] - c0, target[a1] - c1), SPIRAL_ABS[bool(inch)], tol)
            if refusal:
                raise ValueError(refusal)
        turns = 1
        if "P" in fvals:
            turns = int(fvals["P"])
            if turns < 1 or turns != fvals["P"] or turns > MAX_ARC_TURNS:
                raise ValueError(f"arc P (turns) must be a whole number from 1 to {MAX_ARC_TURNS}, got {fvals['P']:g}")
        center = [0.0, 0.0, 0.0]
        center[a0], center[a1], center[an] = c0, c1, pos[an]
        emit(ARC_CW if cw else ARC_CCW, ROW_PROGRAMMED, target, li, words_mask, tuple(center), plane, turns)
