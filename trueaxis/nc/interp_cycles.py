"""Canned cycles (G73, G81-G89) of the interpreter, expanded into the moves LinuxCNC's ``interp_cycles.cc`` makes.
A part of ``gcode._Interpreter`` (the methods of ``CycleConversion``)."""

from __future__ import annotations

from .grammar import PLANE_AXES
from .rows import FEED, RAPID, ROW_CYCLE

# A canned cycle block that would expand into more moves than this is refused (a tiny Q or a huge L: the table
# would not fit in memory, and no real program drills that way).
MAX_CYCLE_MOVES = 100_000


def _sticky_words(mm: int, fvals: dict, st: dict, same_mode: bool) -> None:
    """The cycle words that stay in force between the blocks of one cycle (P dwell, Q peck, I J K of G87), into st."""
    if mm in (820, 860, 880, 890, 740, 840):
        if "P" not in fvals and not same_mode and mm not in (740, 840):
            raise ValueError(f"dwell P missing with G{mm // 10}")
        st["p"] = fvals.get("P", st["p"])
    if mm in (730, 830):
        if "Q" not in fvals and not same_mode:
            raise ValueError(f"Q missing with G{mm // 10}")
        q = fvals.get("Q", st["q"])
        if q <= 0:
            raise ValueError("negative or zero Q in a peck cycle")
        st["q"] = q
    if mm == 870:
        if not same_mode and not all(k in fvals for k in "IJK"):
            raise ValueError("G87 needs I, J and K")
        for k in "ijk":
            st[k] = fvals.get(k.upper(), st[k])


def _hole(mm: int, aa, bb, r, cc, clear_cc, st: dict, absolute: bool, rapid_delta: float, trav, fd) -> None:
    """The moves of one hole at (aa, bb) after the positioning moves: down to cc and back to clear_cc, each cycle
    its way (trav: a rapid, fd: a feed move, to (first, second, normal) of the plane)."""
    if mm == 810 or mm == 820 or mm == 860:
        fd(aa, bb, cc)
        trav(aa, bb, clear_cc)
    elif mm in (730, 830):
        depth = r - st["q"]
        while depth > cc:
            fd(aa, bb, depth)
            if mm == 830:
                trav(aa, bb, r)
            trav(aa, bb, depth + rapid_delta)
            depth = depth - st["q"]
        fd(aa, bb, cc)
        trav(aa, bb, clear_cc)
    elif mm == 850:
        fd(aa, bb, cc)
        fd(aa, bb, r)
        trav(aa, bb, clear_cc)  # rs274 makes this move even when clear_cc == r
    elif mm in (740, 840, 890):
        fd(aa, bb, cc)
        fd(aa, bb, clear_cc)
    elif mm == 880:
        fd(aa, bb, cc)
    elif mm == 870:
        i_off, j_off, k = st["i"], st["j"], st["k"]
        middle = (cc + k) if not absolute else k
        ox, oy = aa + i_off, bb + j_off
        trav(ox, oy, r)
        trav(ox, oy, cc)
        trav(aa, bb, cc)
        fd(aa, bb, middle)
        fd(aa, bb, cc)
        trav(ox, oy, cc)
        trav(ox, oy, clear_cc)
        trav(aa, bb, clear_cc)


class CycleConversion:
    """The interpreter's canned cycles (mixed into ``gcode._Interpreter``)."""

    def cycle(self, line_no, li, mm, motion_here, fvals, ax, pos, plane, absolute, retract_r, inch, st, emit,
              words_mask, prior_mode):
        """Canned cycles G73, G81-G89 expanded into the moves LinuxCNC's interp_cycles.cc makes."""
        a0, a1, an = PLANE_AXES[plane]
        letter = {0: "X", 1: "Y", 2: "Z"}
        same_mode = prior_mode == mm
        given = dict(ax)
        if not same_mode and an not in given:
            raise ValueError(f"{letter[an]} missing in the first canned cycle block (G{mm / 10:g})")
        if "R" in fvals:
            r_word = fvals["R"]
        elif same_mode:
            r_word = st["r"]
        else:
            raise ValueError(f"R clearance plane missing in the first G{mm / 10:g} block")
        l_rep = int(fvals.get("L", 1))
        if l_rep < 1:
            raise ValueError("canned cycle repeat count L must be >= 1")
        cc_word = given.get(an, st["cc"])
        current_cc = pos[an]
        if st["il_flag"]:
            old_cc = st["il"]
        else:
            old_cc = st["il"] = current_cc
            st["il_flag"] = True
        if absolute:
            inc0 = inc1 = 0.0
            r = r_word
            cc = cc_word
            aa = given.get(a0, pos[a0])
            bb = given.get(a1, pos[a1])
        else:
            inc0, inc1 = given.get(a0, 0.0), given.get(a1, 0.0)
            r = r_word + old_cc
            cc = r + cc_word
            aa, bb = pos[a0], pos[a1]
        if r < cc:
            raise ValueError(f"R plane below the bottom of the cycle ({letter[an]})")
        rapid_delta = 0.010 if inch else 0.254

        def at(p0, p1, pn):
            t = list(pos)
            t[a0], t[a1], t[an] = p0, p1, pn
            return t

        def trav(p0, p1, pn, w=0):
            emit(RAPID, ROW_CYCLE, at(p0, p1, pn), li, w)

        def fd(p0, p1, pn):
            emit(FEED, ROW_CYCLE, at(p0, p1, pn), li, 0)

        if old_cc < r:
            trav(pos[a0], pos[a1], r)
            old_cc = r
            current_cc = old_cc
        clear_cc = r if retract_r else old_cc
        if current_cc <= r:
            # as LinuxCNC's CYCLE_MACRO: starting at or below the R plane, the first positioning move is made at the
            # clear level (the initial level in G98, the R plane in G99), not at the current height
            current_cc = clear_cc

        _sticky_words(mm, fvals, st, same_mode)
        # Moves the expansion makes (at most 8 per hole, 3 per peck): refused before it fills the memory.
        pecks = max(0.0, (r - cc) / st["q"]) if mm in (730, 830) else 0.0
        if l_rep * (8 + 3 * pecks) > MAX_CYCLE_MOVES:
            raise ValueError(f"canned cycle would expand into more than {MAX_CYCLE_MOVES} moves (L{l_rep}"
                             + (f", {pecks:.0f} pecks of Q{st['q']:g}" if pecks else "") + ")")
        first = True
        for _ in range(l_rep):
            aa += inc0
            bb += inc1
            trav(aa, bb, current_cc, words_mask if first else 0)
            if old_cc != r:
                trav(aa, bb, r)
            first = False
            _hole(mm, aa, bb, r, cc, clear_cc, st, absolute, rapid_delta, trav, fd)
            old_cc = current_cc = clear_cc
        # LinuxCNC leaves the interpreter at (aa, bb, clear_cc) even after G88
        pos[a0], pos[a1], pos[an] = aa, bb, clear_cc
        st["r"] = r_word
        st["cc"] = cc_word
