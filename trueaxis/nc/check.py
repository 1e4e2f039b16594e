"""What a block may not contain, as LinuxCNC's ``interp_check`` says (checked against ``rs274``).

:func:`check_blocks` refuses, with ``file:line:`` and rs274's reason in our words:

- two G codes of one modal group in a block (``G1 G0 X10``, ``G90 G90``; G80 beside another motion code is let
  pass, as rs274 lets it: the other code moves), two M codes of one modal group (``M3 M4``), more than
  five M codes;
- two G codes that both use the axis words (``G0 G28 X1``: a motion and G10 / G28 / G30 / G52 / G92);
- words that nothing in the block uses: axis words with no motion mode (``G80 X1``, or ``X1`` before any G0 / G1;
  not G43.1's, which are its tool offset: ``G43.1 Z0`` before the first move is read),
  an R word with no arc, canned cycle or G10 (``R5``), I / J / K with no arc, P with no code that takes it, Q with no
  peck cycle, L with no cycle or G10;
  (with ``--passthrough-unsupported``, axis words after G80 are read as Fanuc controls read them, with the motion
  mode from before the cycle: the reader warns);
- a line number (N word) anywhere but at the start of the block; G4 without P or with a negative P;
- a canned cycle before any G98 / G99 (the retract plane would depend on the control's start-up mode: rs274 starts
  in G99, the reader in G98);
- G52 (LinuxCNC: a local offset that shares G92's; not evaluated by this reader) and cutter radius compensation
  G41 / G42 / G41.1 / G42.1 (the controller offsets the path by the tool radius; this post neither computes that path
  nor makes rs274's own refusals, an arc as the entry move or a concave corner the tool would gouge): both refused
  unless ``--passthrough-unsupported``, which keeps G52 as it is (no row; later positions read without its offset)
  and posts the programmed contour of a compensated path with its G41 / G42 kept.

Cost: one pass over the text finds the blocks that are not plain G0..G3 moves; only those are checked word by word,
with the motion mode in force taken from the last G0..G3 word before them; two more passes find I J K R words on
plain blocks in G0 / G1 mode. On ASCII text the first and the last pass are compiled (``fast_read``: the same
positions as the regular expressions, which other text keeps). A plain program costs a few per cent of its reading
time.
"""

from __future__ import annotations

import re

import numpy as np

from .grammar import NUMBER

__all__ = ["check_blocks"]

_NUM = NUMBER
# Where a block needs a word-by-word check (the rest are plain moves: N, one G0..G3, axis words, I J K R, F):
# a character that is no part of a plain move, a G code other than G0..G3, two G codes, an N word after a number.
_CANDIDATES = tuple(re.compile(p) for p in (
    r"[^NGXYZABCFIJKR0-9.+\- \t\r\n]",  # a character no plain move has (M, T, comments, lower case ...)
    r"G(?![ \t]*0?[0-3](?![0-9.]))",  # a G code other than G0..G3
    r"G[^G\n]*G",  # two G codes
    r"N(?<=[^\n]N)",  # an N word after the start of the line
    r"N[ \t]*[-+]",  # a signed N word
))
_IJKR_LEAD = re.compile(r"[^G\nIJKR]*+(?:\n[^G\nIJKR]*+)*+[IJKR]")
_IJKR_AFTER_LINEAR = re.compile(r"G0?[01](?![0-9.])[^G\nIJKR]*+(?:\n[^G\nIJKR]*+)*+[IJKR]")
_LAST_MOTION = re.compile(r"(?s).*G0?([0-3])(?![0-9.])")
_LINE_START = re.compile(r"^", re.MULTILINE)
_WORD = re.compile(r"(\([^)\n]*\)?)|(;[^\n]*)|([A-Za-z])[ \t]*(" + _NUM + r")?|([^\s])")

# G code * 10 -> modal group (LinuxCNC's groups; 0 the non-modal group)
_G_GROUP = {}
for _group, _codes in {
    0: (40, 100, 280, 281, 300, 301, 520, 530, 920, 921, 922, 923),
    1: (0, 10, 20, 30, 50, 51, 52, 330, 331, 382, 383, 384, 385, 730, 740, 760, 800, 810, 820, 830, 840, 850, 860,
        870, 880, 890),
    2: (170, 180, 190, 171, 181, 191),
    3: (900, 910),
    4: (901, 911),
    5: (930, 940, 950),
    6: (200, 210),
    7: (400, 410, 420, 411, 421),
    8: (430, 431, 432, 490),
    10: (980, 990),
    12: (540, 550, 560, 570, 580, 590, 591, 592, 593),
    13: (610, 611, 640),
    14: (960, 970),
    15: (70, 80),
}.items():
    for _c in _codes:
        _G_GROUP[_c] = _group
_GROUP_NAME = {0: "non-modal", 1: "motion", 2: "plane", 3: "distance mode", 4: "arc distance mode",
               5: "feed mode", 6: "units", 7: "cutter compensation", 8: "tool length offset", 10: "canned cycle return",
               12: "coordinate system", 13: "path control", 14: "spindle mode", 15: "lathe diameter mode"}


def _m_group(m: int):
    if m in (0, 1, 2, 30, 60):
        return 4
    if m == 6:
        return 6
    if m in (3, 4, 5):
        return 7
    if m in (7, 8, 9):
        return 8
    if 48 <= m <= 53:
        return 9
    if 62 <= m <= 68:
        return 5
    if 100 <= m <= 199:
        return 10
    return None


_AXIS_USERS = (100, 280, 300, 520, 920)  # non-modal codes that take the axis words
_CYCLES = frozenset((730, 810, 820, 830, 840, 850, 860, 870, 880, 890))
_ARCS = (20, 30)
_P_G = frozenset((20, 30, 40, 100, 640, 50, 52, 760, 820, 860, 880, 890))
# (G8 P: Fanuc's look-ahead "G08 P1", which the reader passes through as such)
_P_M = frozenset((50, 51, 52, 53, 62, 63, 64, 65, 66, 98))
_G_NAME = lambda g: f"G{g // 10}" if g % 10 == 0 else f"G{g / 10:g}"  # noqa: E731


def check_blocks(text: str, source: str, passthrough: bool, line_map=None) -> None:
    """Raise :class:`~trueaxis.nc.gcode.GcodeError` at the first block rs274 would refuse (see the module
    docstring). ``line_map``: 1-based source line of each text line (a flattened program), or None."""
    state = _State(text)
    pos, n = 0, len(text)
    candidates = _Candidates(text, state.buf)
    while True:
        at = candidates.next(pos)
        if at < 0:
            break
        start = text.rfind("\n", 0, at) + 1
        end = text.find("\n", at)
        end = n if end < 0 else end + 1
        if start < pos:  # (cannot happen: a match never starts before pos)
            start = pos
        _plain_blocks(text, pos, start, state, source, line_map, passthrough)
        _check_block(text[start:end], state, passthrough, lambda reason, s=start: _raise(
            text, s, source, line_map, reason))
        pos = end
    _plain_blocks(text, pos, n, state, source, line_map, passthrough)


class _Candidates:
    """Where the next block that needs the checks word by word starts: the first match at or after a position of any
    of the candidate patterns, by the compiled scan on ASCII text (its bytes ``buf``), else by the patterns."""

    def __init__(self, text, buf):
        self.text, self.buf = text, buf
        # the next match of each candidate pattern (re-searched only once passed): one scan of the text per pattern
        self.nxt = None if buf is not None else [p.search(text) for p in _CANDIDATES]

    def next(self, pos) -> int:
        if self.buf is not None:
            from .fast_read import _PLAIN_BYTES, next_check_candidate

            return int(next_check_candidate(self.buf, _PLAIN_BYTES, pos))
        self.nxt = [m if m is None or m.start() >= pos else p.search(self.text, pos)
                    for m, p in zip(self.nxt, _CANDIDATES)]
        found = [m.start() for m in self.nxt if m is not None]
        return min(found) if found else -1


class _State:
    """What the checks need of the modal state: the motion mode (None: none yet, as rs274 starts), the plane and
    the arc distance mode; and the text's bytes for the compiled scans (None: the text is not ASCII)."""

    def __init__(self, text=""):
        self.buf = np.frombuffer(text.encode("ascii"), np.uint8) if text.isascii() else None
        self.motion = None
        self.plane = 170
        self.arc_abs = False
        self.feed_reset = False  # G93 / G94 / G95 set the feed rate to 0 (rs274) and no F word since
        self.retract_set = False  # G98 or G99 programmed


def _plain_blocks(text, a, b, state, source, line_map, passthrough):
    """Update ``state`` over the plain blocks text[a:b]; refuse axis words there while no motion mode is in force,
    and check every arc there block by block while arc centres are absolute (G90.1)."""
    if state.arc_abs or state.feed_reset:
        offset = a
        for line in _lines(text, a, b):
            _check_block(line, state, passthrough, lambda reason, s=offset: _raise(text, s, source, line_map, reason))
            offset += len(line)
            if not (state.arc_abs or state.feed_reset):
                # (G93's first F word, say): the rest is plain blocks again, checked as such (not line by line)
                return _plain_blocks(text, offset, b, state, source, line_map, passthrough)
        return
    if state.motion is None or (state.motion == 800 and not passthrough):
        offset = a
        first_g = text.find("G", a, b)  # the loop stops at the line that holds it: the lines after it not split
        for line in text[a:b if first_g < 0 else first_g + 1].splitlines(keepends=True):
            s = line.strip()
            if s:
                if "G" in s:
                    break
                if re.search("[XYZABC]", s):
                    _raise(text, offset, source, line_map, _no_motion(state.motion))
            offset += len(line)
    if a >= b:
        return
    if state.motion in (None, 0, 10, 800):
        bad = _IJKR_LEAD.match(text, a, b)
        if bad is not None:
            _raise(text, bad.end() - 1, source, line_map, _ijkr_no_use(bad.group()[-1]))
    if state.buf is not None:
        from .fast_read import ijkr_after_linear

        at = int(ijkr_after_linear(state.buf, a, b))
        if at >= 0:
            _raise(text, at, source, line_map, _ijkr_no_use(text[at]))
    else:
        bad = _IJKR_AFTER_LINEAR.search(text, a, b)
        if bad is not None:
            _raise(text, bad.end() - 1, source, line_map, _ijkr_no_use(bad.group()[-1]))
    gap = _LAST_MOTION.match(text, a, b)
    if gap is not None:
        state.motion = int(gap.group(1)) * 10


def _lines(text, a, b, window=4096):
    """The lines of text[a:b] as ``splitlines(keepends=True)`` gives them, split a window at a time: a caller that
    stops after a few lines (G93's first F word) does not split the rest of a long program (a million-line program:
    0.15 s and a list of every line)."""
    while a < b:
        end = min(b, a + window)
        lines = text[a:end].splitlines(keepends=True)
        if end < b:
            if len(lines) <= 1:  # a line longer than the window
                window *= 2
                continue
            lines.pop()  # it may go on past the window (or its "\r" be the first half of a "\r\n")
        yield from lines
        a += sum(map(len, lines))


def _ijkr_no_use(letter):
    if letter == "R":
        return "R word with no G code that uses it (an arc, a canned cycle or G10)"
    return f"{letter} word with no arc (G2 / G3), G87 or G10 to use it"


def _no_motion(motion):
    if motion == 800:
        return ("axis words with G80 in force: no motion mode uses them (rs274 refuses them; Fanuc controls move with "
                "the motion mode from before the cycle, which --passthrough-unsupported reads)")
    return "axis words with no motion mode in force (no G0, G1, G2 or G3 yet): rs274 refuses them"


def _raise(text, offset, source, line_map, reason):
    from .gcode import GcodeError

    line = text.count("\n", 0, offset) + text.count("\r", 0, offset) - text.count("\r\n", 0, offset) + 1
    if line_map is not None:
        line = line_map[min(line, len(line_map)) - 1]
    raise GcodeError(source, line, reason)


def _block_words(block: str, fail):
    """The block's G codes (x10), M codes and other words {letter: value}; None for a block the reader judges itself
    (a % line, macro syntax, a word with no number, a number out of range)."""
    gcodes, mcodes, letters = [], [], {}
    first = True
    stripped = block.lstrip()
    if stripped[:1] == "%":
        return None
    for com1, com2, letter, num, other in _WORD.findall(block):
        if com1 or com2:
            continue
        if other:
            if other == "/" and first:
                continue
            return None  # macro syntax (passed through) or a character the reader refuses with its own message
        if not num:
            return None  # "word with no number": the reader's message
        L = letter.upper()
        if L == "N" and not first:
            fail(f"line number N{num} is not at the start of the block (rs274 reads an N word only there)")
        if L == "N" and num[0] in "+-":
            fail(f"line number N{num} has a sign (rs274 reads an unsigned number)")
        first = False
        try:
            if L == "G":
                gcodes.append(int(round(float(num) * 10)))
            elif L == "M":
                mcodes.append(int(round(float(num))))
            elif L != "N":
                letters[L] = float(num)
        except (OverflowError, ValueError):
            return None  # a number out of range: the reader's message
        if L == "Q" and letters.get(L) == -1.0:
            del letters[L]  # rs274 marks an absent Q with -1: Q-1 reads as no Q word there
    return gcodes, mcodes, letters


def _modal_groups(gcodes, mcodes, fail) -> dict:
    """{modal group: G code} of the block; two codes of one group (G or M), or more than five M codes, fail."""
    # two codes of one modal group
    seen = {}
    for g in gcodes:
        grp = _G_GROUP.get(g)
        if grp is None:
            continue
        if grp in seen and not (grp == 1 and 800 in (seen[grp], g)):
            fail(f"two G codes of one modal group ({_GROUP_NAME[grp]}) in a block: {_G_NAME(seen[grp])} and "
                 f"{_G_NAME(g)}")
        if grp != 1 or g != 800 or 1 not in seen:
            seen[grp] = g
    mseen = {}
    for m in mcodes:
        grp = _m_group(m)
        if grp is None:
            continue
        if grp in mseen:
            fail(f"two M codes of one modal group in a block: M{mseen[grp]} and M{m}")
        mseen[grp] = m
    if len(mcodes) > 5:
        fail(f"more than five M codes in a block ({len(mcodes)})")
    return seen


def _check_block(block: str, state, passthrough: bool, fail):
    """Check one block and update ``state`` (:class:`_State`) with its modal codes."""
    motion = state.motion
    words = _block_words(block, fail)
    if words is None:
        return
    gcodes, mcodes, letters = words
    if any(g not in _G_GROUP for g in gcodes):
        return  # a code the reader refuses or passes through with its own message (G65, G5.3, G08 P1 ...)
    seen = _modal_groups(gcodes, mcodes, fail)
    g0 = seen.get(0)
    g1 = seen.get(1)
    axes = any(a in letters for a in "XYZABCUVW")
    if g0 in _AXIS_USERS and g1 is not None and g1 != 800:
        fail(f"two G codes that both use the axis words: {_G_NAME(g1)} and {_G_NAME(g0)}")
    if g0 in (520, 920) and not axes:
        fail(f"{_G_NAME(g0)} with no axis word")
    if g0 == 520 and not passthrough:
        fail("G52 (local coordinate offset) is not read here: LinuxCNC keeps it as the G92 offset, never a move; "
             "set the offset with G92 or G54..G59.3, or pass --passthrough-unsupported to keep the block as it is "
             "(later positions are then read without the offset)")
    if seen.get(7) in (410, 420, 411, 421) and not passthrough:
        fail(f"cutter radius compensation {_G_NAME(seen[7])} is not computed by this post (nor rs274's refusals of "
             "an arc as entry move and of gouging concave corners); pass --passthrough-unsupported to post the "
             "programmed contour with the compensation left to the control")
    if g1 is not None:
        state.motion = g1
    if 2 in seen:
        state.plane = seen[2]
    if 4 in seen:
        state.arc_abs = seen[4] == 901
    if 10 in seen:
        state.retract_set = True
    if g1 in _CYCLES and not state.retract_set:
        fail(f"canned cycle {_G_NAME(g1)} with no G98 / G99 programmed before it: where it retracts depends on the "
             "control's start-up mode (rs274 starts in G99, this reader in G98); program G98 or G99")
    if 5 in seen:
        state.feed_reset = True
    if "F" in letters:
        state.feed_reset = False

    # G43.1's axis words are its tool offset: with no motion code in the block they use no motion mode, so none need
    # be in force (rs274's enhance_block: G43.1 Z0 before the first move, or after G80, is read)
    offset_words = seen.get(8) == 431 and g1 is None
    if g1 is not None:
        to_be = g1
    elif axes and g0 not in _AXIS_USERS and not offset_words:
        to_be = motion
    else:
        to_be = None
    if axes and g0 not in _AXIS_USERS and not offset_words:
        if to_be is None or (to_be == 800 and not (passthrough and g1 is None)):
            fail(_no_motion(to_be if g1 is not None or motion == 800 else None))
    if state.feed_reset and (to_be in (10, 20, 30) or to_be in _CYCLES):
        fail(f"{_G_NAME(to_be)} with zero feed rate: a feed mode code (G93 / G94 / G95) sets the feed rate to 0 in "
             "rs274; give an F word after it")
    if g0 == 530 and to_be not in (0, 10) and not (passthrough and to_be == 800 and g1 is None):
        fail("G53 (a move in machine coordinates) needs axis words and G0 or G1")
    # (G76's R: the depth degression of LinuxCNC's threading cycle, which reads it)
    if "R" in letters and not (to_be in _ARCS or to_be in _CYCLES or to_be == 760 or g0 == 100 or 19 in mcodes):
        fail(_ijkr_no_use("R"))
    for w in "IJK":
        if w in letters and not (to_be in (20, 30, 50, 51, 330, 331, 760, 870) or g0 == 100):
            fail(_ijkr_no_use(w))
    if "P" in letters and not (any(g in _P_G or g == 80 for g in gcodes) or (to_be in _P_G)
                               or any(m in _P_M or 100 <= m <= 199 for m in mcodes)):
        fail("P word with no G or M code that uses it (G4 dwell, G10, G64, arc turns, G82 / G86 / G88 / G89 "
             "dwell, M62..M66)")
    if "Q" in letters and not (to_be in (730, 830, 50, 760) or 640 in gcodes or 66 in mcodes):
        fail("Q word with no G code that uses it (G73 / G83 peck, G64)")
    if "L" in letters and not (g0 == 100 or to_be in _CYCLES or to_be == 760 or 66 in mcodes or 98 in mcodes):
        fail("L word with no canned cycle or G10 to use it")
    if g0 == 40:
        if "P" not in letters:
            fail("G4 dwell without a P word (its time)")
        if letters["P"] < 0:
            fail(f"G4 with a negative dwell time P{letters['P']:g}")
    if to_be in _ARCS and state.arc_abs and "R" not in letters:
        need = {170: "IJ", 180: "IK", 190: "JK"}.get(state.plane, "")
        missing = [w for w in need if w not in letters]
        if missing:
            fail(f"{missing[0]} word missing in an arc with absolute centre (G90.1)")
