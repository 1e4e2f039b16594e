"""The G-code reader: RS-274 / ISO 6983 text in, a table of motion rows out (DESIGN.md §5).

This is the project's one tokenizer. It reads what FreeCAD CAM (linuxcnc post), LinuxCNC and Fanuc-style controls
write, interprets it the way LinuxCNC's interpreter does, and returns a :class:`Program`: numpy arrays with one row per
move that the control makes (canned cycles and G28/G30 expanded into their moves), plus the untouched text of every
line so a writer can reproduce the non-motion lines byte for byte.

Coordinates
-----------
``Program.end`` / ``Program.start`` are *program coordinates*: absolute positions in the work coordinate system that is
active at that row (G54..G59.3, G92), in the units active at that row (G20 inch / G21 mm; rotary axes in degrees).
That is exactly what LinuxCNC's ``rs274`` prints in its canonical ``STRAIGHT_FEED`` / ``ARC_FEED`` calls (checked: it
reports positions *before* the G5x, G92 and tool length offsets, which it announces separately with
``SET_G5X_OFFSET`` and ``USE_TOOL_LENGTH_OFFSET``). The machine position is composed as LinuxCNC's canon does: program
position plus G92, turned by the work system's XY rotation (``Program.rotation``, deg), plus the G5x offset and the
tool offset. ``Program.offset`` holds the sum of those offsets at each row (the G92 shift turned by the rotation), so
the controlled point in machine coordinates is ``R end + offset`` (:attr:`Program.end_machine`,
:meth:`Program.to_machine`), ``end + offset`` in a system without rotation. The offsets at program start come from
the control's setup (``setup``: LinuxCNC's parameter file and tool table, or a setup file; see ``setup.py``);
``Program.setup_used`` lists what the rows used and where it came from.

Decisions (documented here once)
--------------------------------
- G28/G30 are executed as LinuxCNC does: a rapid to the intermediate point (if axis words are given), then a rapid of
  the named axes (all axes when none are named) to the stored reference point in *machine* coordinates (parameters
  5161-5166 / 5181-5186, default all zero as in ``rs274`` without a parameter file; override with
  ``reference_points``). Their rows have ``kind == ROW_REFERENCE`` so a compensating writer leaves those lines alone.
- A block with G0/G1 and no axis words is a zero-length move (LinuxCNC reports one too).
- Block delete ``/`` lines are executed (the block-delete switch is off, as in ``rs274``).
- Parameters, expressions, O-word control flow and M98 / M99 are evaluated before this reader by :mod:`.flatten`
  (the reader then sees a flat program), and every block first passes rs274's block checks (:mod:`.check`). With
  ``passthrough_unsupported`` a macro layer the pre-pass refuses reaches this reader, which substitutes literal
  parameters (``#501 = 1``) and passes the rest through (recorded in ``unsupported``) where it cannot move an axis.
- Fanuc-only codes that do not move an axis (``G08 P1``, ``M29``, unknown M codes, ``G05.1``) pass through and are
  recorded; subprogram calls and control flow the pre-pass does not evaluate (G65, G66, M98 to a program not in the
  file, o-word calls to other files) are refused, since the moves they make are not in the text. With
  ``passthrough_unsupported=True`` (``--passthrough-unsupported``) such a block is left as it is (no row) and recorded.
- Cutter radius compensation (G41/G42; read only with ``passthrough_unsupported``, :mod:`.check` refuses it
  otherwise): the rows are the programmed contour, not the tool centre path; the mode is in
  ``cutter_comp`` and a warning says so.
- Everything after M2/M30 or a closing ``%`` is kept as text and not interpreted.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from collections import deque
from functools import cached_property
from itertools import islice
from typing import Mapping, Sequence

import numpy as np

from .grammar import NUMBER, PLANE_AXES
from .interp_arc import ArcConversion, ijk_radii_refusal
from .interp_cycles import CycleConversion
from .interp_codes import (  # noqa: F401  (MAX_WORD_VALUE, WORD_BITS: this module's names too)
    AXES, LINEAR as _LINEAR, MAX_WORD_VALUE, MM_PER_INCH, SYSTEM_NAMES as _SYSTEM_NAMES, WORD_BIT as _WORD_BIT,
    WORD_BITS, add as _add)
from .interp_convert import Conversion
from .interp_read import read_block
from .interp_state import InterpState
from .rows import ARC_CCW, ARC_CW, FEED, RAPID, ROW_CYCLE, ROW_MACHINE, ROW_PROGRAMMED, ROW_REFERENCE

__all__ = [
    "GcodeError",
    "Program",
    "FormatInfo",
    "parse_program",
    "parse_file",
    "parse_tool_table",
    "write_number",
    "output_decimals",
    "tokenize_line",
    "word_spans",
    "AXES",
    "RAPID",
    "FEED",
    "ARC_CW",
    "ARC_CCW",
    "ROW_PROGRAMMED",
    "ROW_CYCLE",
    "ROW_REFERENCE",
    "ROW_MACHINE",
]

# One tokenizer for the whole project. Alternatives, in order:
#   1 a () comment (an unclosed one runs to the end of the line), 2 a ; comment,
#   3 a letter and 4 its value: a number, #n, or a bracketed expression (may be empty: "word with no number"),
#   5 any other non-blank character.
_TOKEN = re.compile(
    r"(\([^)\n]*\)?)|(;[^\n]*)"
    r"|([A-Za-z])[ \t]*(" + NUMBER + r"|#[0-9]+|\[[^\n(;]*?\](?:[^\n(;\[]*\])*)?"
    r"|([^\s])"
)
_TOKEN_KINDS = (None, "comment", "comment", "word", "word", "other")
# The tokenizer for writers that walk a block's tokens: group 3 is a word's letter (None for comments and others).
TOKEN_PATTERN = _TOKEN
_ASSIGN = re.compile(r"^[ \t]*(?:[Nn][0-9]+[ \t]*)?#([0-9]+)[ \t]*=[ \t]*(" + NUMBER + r")[ \t]*(?:\(.*\)|;.*)?[ \t]*$")
_PARAM_REF = re.compile(r"^(?:#([0-9]+)|\[[ \t]*#([0-9]+)[ \t]*\])$")
# the fast path's plain G0/G1 block, and its words (upper case, no comments, no other codes)
_FAST = re.compile(
    r"[ \t]*(?:N[0-9]+[ \t]*)?(?:G0?([0-3])(?![0-9.])[ \t]*)?"
    + "".join(rf"(?:{c}[ \t]*([-+]?(?:[0-9]{{1,9}}(?:\.[0-9]*)?|\.[0-9]+))[ \t]*)?" for c in "XYZABCIJKRF")
    + r"\r?\n?\Z"
)

# Lines end at \n, \r\n or a lone \r, as an editor counts them (str.splitlines also splits at \f, \v, \x1c-\x1e,
# \x85, \u2028 and \u2029, which would shift the line numbers of the messages).
_LINE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n)|[^\r\n]+\Z")
_OTHER_BREAKS = re.compile("[\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029]")
# The reader's compiled pre-scan of plain blocks (fast_read); False: the regular expression and float() on every line
# (the same results, slower). FAST_READ_BLOCK lines are scanned at a time (their values as Python floats).
FAST_READ = True
FAST_READ_BLOCK = 4096


#: G94 / G95 in a line's code (not in its comment): the feed mode it sets.
_FEED_MODE = re.compile(r"(?i)(?<![A-Z])G\s*0*9([45])(?![.\d])")


def feed_per_revolution_lines(lines) -> np.ndarray:
    """(L,) bool per line of ``lines``: the feed is per spindle revolution there (G95 in force; G94 at the start, as
    LinuxCNC starts). G93 is the Program's ``inverse_time``."""
    if not any(m.group(1) == "5" for m in _FEED_MODE.finditer("".join(lines))):
        return np.zeros(len(lines), bool)  # no G95 anywhere (the usual program): no per-line scan in Python
    mode, out = 94, np.empty(len(lines), bool)
    for i, line in enumerate(lines):
        code = line.split("(", 1)[0].split(";", 1)[0]
        for m in _FEED_MODE.finditer(code):
            mode = 90 + int(m.group(1))
        out[i] = mode == 95
    return out


def split_lines(text: str) -> list:
    """The lines of ``text`` with their endings (``"".join(split_lines(t)) == t``), split at \n, \r\n and \r only."""
    # (ASCII text: its five other breaks looked for one by one, faster than the class over all of it)
    if (not any(c in text for c in "\x0b\x0c\x1c\x1d\x1e") if text.isascii() else _OTHER_BREAKS.search(text) is None):
        return text.splitlines(keepends=True)
    return _LINE.findall(text)


_PLANE_AXES = PLANE_AXES
_NOT_FAST = (False,) + (0,) * 12


def _regex_words(fm):
    """(True, G digit or -1, X Y Z A B C I J K R F: NaN where not given) of a plain block matched by ``_FAST``;
    ``_NOT_FAST`` for no match, or a match without a motion or axis word (not a move: the general path)."""
    if fm is None:
        return _NOT_FAST
    g, x, y, z, a_, b_, c_, i_, j_, k_, r_, f_ = fm.groups()
    if g is None and x is None and y is None and z is None and a_ is None and b_ is None and c_ is None:
        return _NOT_FAST
    nan = math.nan
    return (True, -1 if g is None else int(g), nan if x is None else float(x), nan if y is None else float(y),
            nan if z is None else float(z), nan if a_ is None else float(a_), nan if b_ is None else float(b_),
            nan if c_ is None else float(c_), nan if i_ is None else float(i_), nan if j_ is None else float(j_),
            nan if k_ is None else float(k_), nan if r_ is None else float(r_), nan if f_ is None else float(f_))
_I_BIT, _J_BIT, _K_BIT = _WORD_BIT["I"], _WORD_BIT["J"], _WORD_BIT["K"]


def _rotary_words(target: list, seen: int, absolute: bool, a_: float, b_: float, c_: float) -> int:
    """The fast path's A B C words (NaN: not given) into target; the words' bits added to seen."""
    for n, v in ((3, a_), (4, b_), (5, c_)):
        if v == v:
            target[n] = v if absolute else target[n] + v
            seen |= 1 << n
    return seen


def _incremental_words(target: list, x: float, y: float, z: float) -> int:
    """The fast path's X Y Z words (NaN: not given) added to target (G91); their bits."""
    seen = 0
    if x == x:
        target[0] += x
        seen = 1
    if y == y:
        target[1] += y
        seen |= 2
    if z == z:
        target[2] += z
        seen |= 4
    return seen


_OWORD = re.compile(
    r"^\s*(?:[Nn]\s*[0-9]+\s*)?[Oo]\s*(?:<[^>]*>|[0-9]+)\s*(?:sub|endsub|call|if|elseif|else|endif|while|"
    r"endwhile|do|repeat|endrepeat|return|break|continue)\b",
    re.IGNORECASE,
)


class GcodeError(Exception):
    """A program the reader refuses; ``str()`` is ``file:line: reason`` (line 1-based)."""

    def __init__(self, source: str, line_no: int, reason: str):
        self.source, self.line_no, self.reason = source, line_no, reason
        super().__init__(f"{source}:{line_no}: {reason}")


@dataclass
class FormatInfo:
    """How the input writes numbers, for a writer that keeps the program's dialect.

    decimals : letter -> most digits after the decimal point seen in that word (e.g. {"X": 4, "F": 0})
    leading_zero : True when numbers below 1 are written ``0.5`` (False: ``.5``), judged on the first such number
    trailing_point : True when whole numbers are written with a point (``Z0.``, ``F120.``)
    separator : text between words: " " or "" (judged on the first motion line)
    """

    decimals: dict
    leading_zero: bool
    trailing_point: bool
    separator: str


@dataclass
class Program:
    """An interpreted NC program: one row per move, plus every source line.

    Row arrays (M = number of moves), positions in program units (see the module docstring):
    start, end : (M, 6) float, X Y Z A B C at the start / end of the move, program coordinates (work system active
        at the row); rotary axes in degrees
    offset : (M, 6) float, G5x + G92 + tool length offset at the row; machine position = end + offset
    motion : (M,) int8, RAPID 0, FEED 1, ARC_CW 2, ARC_CCW 3
    kind : (M,) int8, ROW_PROGRAMMED 0, ROW_CYCLE 1, ROW_REFERENCE 2 (G28/G30), ROW_MACHINE 3 (G53)
    arc_center : (M, 3) float, X Y Z of the arc centre (normal coordinate = the start's); NaN for straight moves
    arc_plane : (M,) int8, 17 / 18 / 19 for arcs, 0 otherwise
    arc_turns : (M,) int16, number of turns (P word, default 1) for arcs, 0 otherwise
    feed : (M,) float, F in program units per minute, or 1/min under G93 (inverse time); 0 before any F
    inverse_time : (M,) bool, G93 active
    inch : (M,) bool, G20 active (the row's lengths are in inches)
    cutter_comp : (M,) int8, 40 off, 41 left, 42 right
    tool : (M,) int32, tool in the spindle (after M6); 0 when none
    incremental : (M,) bool, G91 (incremental axis words) active
    arc_incremental : (M,) bool, G91.1 (incremental arc centres, the default) active; False under G90.1
    diameter : (M,) bool, G7 (lathe diameter mode) active: the block's X word was a diameter, X here is the radius
    line_index : (M,) int32, 0-based index into ``lines`` of the block that made the row
    words : (M,) uint16, bit mask of the words the block had (bit i for ``WORD_BITS[i]``, XYZABCIJKRPF); 0 for
        rows of expanded cycles and G28/G30's second move

    lines : list of str, the raw lines with their line endings (``"".join(lines) == text``)
    units : "mm", "inch" or "mixed"
    axes_present : the axis letters the program uses, in XYZABC order
    warnings : list of str, ``file:line: message``
    unsupported : list of (line_no, reason), 1-based, for blocks passed through uninterpreted
    rotation : (M,) float, XY rotation of the row's work system, deg (G10 L2 R, parameter 5230 + 20 (k - 1))
    setup_used : list of dict, the work offsets, G92 shifts and tool offsets the rows used, in order of first use:
        ``what`` ("G54", "G92", "tool 3 offset"), ``values_mm_deg`` (6,), ``rotation_deg``, ``source`` (file:parameters,
        file:line, or "not given"), ``applied_by`` (tool offsets: "G43 H3", "M6"), ``first_line``
    """

    source: str
    start: np.ndarray
    end: np.ndarray
    offset: np.ndarray
    motion: np.ndarray
    kind: np.ndarray
    arc_center: np.ndarray
    arc_plane: np.ndarray
    arc_turns: np.ndarray
    feed: np.ndarray
    inverse_time: np.ndarray
    inch: np.ndarray
    cutter_comp: np.ndarray
    tool: np.ndarray
    incremental: np.ndarray
    arc_incremental: np.ndarray
    diameter: np.ndarray
    line_index: np.ndarray
    words: np.ndarray
    lines: list
    units: str
    axes_present: str
    warnings: list = field(default_factory=list)
    unsupported: list = field(default_factory=list)
    rotation: np.ndarray | None = None
    setup_used: list = field(default_factory=list)
    source_line: np.ndarray | None = None  # flattened programs (see .flatten): 1-based source line of each text line
    # The blocks that set an offset from the position the control holds (G92, G10 L20 with axis words): (line index,
    # axis indices (0..5) given, "G92" or "G10 L20"). A post that moves that position must move their values too.
    position_sets: list = field(default_factory=list)
    # 1-based lines that start with '/' (block delete): read as executed (the switch off, as rs274 reads them)
    block_delete_lines: list = field(default_factory=list)
    # (K,) int64, the G28 / G30 / G53 rows whose machine position rests on a value of the setup not given, taken as
    # zero (a home position, a work offset component, a G92 shift, a tool length): they pass through a post, which
    # refuses the program's own moves under such a value; None: none
    machine_rows_not_given: np.ndarray | None = None
    # (line index, what) of the blocks after which the control's position is not known from the text: a tool change
    # (M6: a control may lift Z or go to a change position first, LinuxCNC's TOOL_CHANGE_QUILL_UP / _AT_G30 /
    # _POSITION, a Fanuc or Hurco change macro), a block passed through whose moves are not in the text (probing
    # G38.x, a macro call, ...). A post writes no axis word from a position held before one until the program gives it.
    positions_lost: list = field(default_factory=list)
    # "G7/G8", "plane" -> the line index of the block that first states it (absent: never stated, the control's
    # start-up mode is what the program runs in; a lathe post refuses to assume it)
    modes_stated: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.motion.shape[0])

    @property
    def line_no(self) -> np.ndarray:
        """(M,) int32, 1-based source line of each row."""
        return self.line_index + 1 if self.source_line is None else self.source_line[self.line_index]

    def source_line_of(self, li: int) -> int:
        """The 1-based source line of line index ``li`` of ``lines`` (a flattened program's flat line: its source's)."""
        return li + 1 if self.source_line is None else int(self.source_line[li])

    @property
    def end_machine(self) -> np.ndarray:
        """(M, 6) float, end points in machine coordinates (work, G92 and tool length offsets applied)."""
        return self.to_machine(self.end)

    @property
    def start_machine(self) -> np.ndarray:
        """(M, 6) float, start points in machine coordinates."""
        return self.to_machine(self.start)

    def to_machine(self, points: np.ndarray, rows=None) -> np.ndarray:
        """Machine coordinates (program units) of program-coordinate points (K, 6) of the rows ``rows`` (K,) (all
        rows when None): the XY rotation of the row's work system, then ``offset``."""
        rows = slice(None) if rows is None else rows
        off = self.offset[rows]
        rot = None if self.rotation is None else self.rotation[rows]
        if rot is None or not np.any(rot):
            return points + off
        out = points.copy()
        c, s = np.cos(np.radians(rot)), np.sin(np.radians(rot))
        out[..., 0] = c * points[..., 0] - s * points[..., 1]
        out[..., 1] = s * points[..., 0] + c * points[..., 1]
        return out + off

    def to_program_delta(self, delta: np.ndarray, rows=None) -> np.ndarray:
        """A displacement (K, 6) in machine coordinates as a displacement in the rows' program coordinates (the
        work system's rotation undone; offsets do not change a displacement)."""
        rows = slice(None) if rows is None else rows
        rot = None if self.rotation is None else self.rotation[rows]
        if rot is None or not np.any(rot):
            return delta
        out = delta.copy()
        c, s = np.cos(np.radians(rot)), np.sin(np.radians(rot))
        out[..., 0] = c * delta[..., 0] + s * delta[..., 1]
        out[..., 1] = -s * delta[..., 0] + c * delta[..., 1]
        return out

    @property
    def end_mm(self) -> np.ndarray:
        """(M, 6) float, end points in program coordinates with lengths in mm (rotary axes stay in degrees)."""
        scale = np.where(self.inch[:, None] & _LINEAR[None, :], MM_PER_INCH, 1.0)
        return self.end * scale

    @cached_property
    def format_info(self) -> FormatInfo:
        """How the input writes numbers (decimals per word letter, leading zero, trailing point, separator)."""
        # One compiled pass over the program's bytes (fast_read.number_style: the comments skipped), in blocks of
        # lines (a word never spans a line) so that the bytes of a long program are not all copied at once.
        from .fast_read import number_style

        most = np.full(26, -1, np.int64)
        trailing_point = False
        leading_zero = None  # judged on the first number below 1
        early = getattr(self, "_number_styles", None)  # (the same passes over the same bytes, made while reading)
        for b, i in enumerate(range(0, len(self.lines), _STYLE_BLOCK_LINES)):
            if early is not None:
                block_decimals, block_point, leading = early[b]
            else:
                block = "".join(self.lines[i : i + _STYLE_BLOCK_LINES]).encode("latin-1", "replace")
                block_decimals, block_point, leading = number_style(np.frombuffer(block, np.uint8))
            np.maximum(most, block_decimals, out=most)
            trailing_point |= bool(block_point)
            if leading_zero is None and leading >= 0:
                leading_zero = leading == 1
        leading_zero = True if leading_zero is None else leading_zero
        decimals = {chr(65 + k): int(most[k]) for k in np.nonzero(most >= 0)[0].tolist()}
        separator = ""
        for i in self.line_index[:50]:
            if re.search(r"[0-9.][ \t]+[A-Za-z]", self.lines[int(i)].split("(", 1)[0]):
                separator = " "
                break
        return FormatInfo(decimals, leading_zero, trailing_point, separator)


_STYLE_BLOCK_LINES = 50_000


# ----------------------------------------------------------------------------------------------------------------
# number formatting for the writer


def write_number(value: float, decimals: int, *, leading_zero: bool = True, trailing_point: bool = False) -> str:
    """Format ``value`` with at most ``decimals`` digits after the point, trailing zeros dropped.

    ``write_number(-0.00004, 4) == "0"``, ``write_number(1.5, 4) == "1.5"``, ``write_number(0.25, 3,
    leading_zero=False) == ".25"``, ``write_number(120, 3, trailing_point=True) == "120."``. Never writes ``-0`` and
    never uses exponent notation. Raises ValueError for NaN/inf or negative ``decimals``.
    """
    if not math.isfinite(value):
        raise ValueError(f"cannot write a non-finite number ({value}) into G-code")
    if decimals < 0:
        raise ValueError(f"decimals must be >= 0, got {decimals}")
    text = f"{value:.{decimals}f}"
    if "." in text:
        text = text.rstrip("0")
    if text.startswith("-") and text.strip("-0.") == "":
        text = text[1:]
    if text.endswith("."):
        if not trailing_point:
            text = text[:-1]
    elif trailing_point and "." not in text:
        text += "."
    if not leading_zero:
        if text.startswith("0.") and len(text) > 2:
            text = text[1:]
        elif text.startswith("-0.") and len(text) > 3:
            text = "-" + text[2:]
    return text


def write_numbers(values, decimals: int, *, leading_zero: bool = True, trailing_point: bool = False) -> list:
    """``write_number`` of every value in ``values`` (a 1-D array): the same strings, for the writer's bulk of axis
    words (list passes over the batch instead of one call per number)."""
    v = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"cannot write a non-finite number ({v[~np.isfinite(v)][0]}) into G-code")
    if decimals < 0:
        raise ValueError(f"decimals must be >= 0, got {decimals}")
    form = f"%.{decimals}f"
    out = [form % x for x in v.tolist()]
    if decimals > 0:
        out = [t.rstrip("0") for t in out]  # every text has a point: "1.5", "120.", "-0."
    out = [t[1:] if t in ("-0.", "-0") else t for t in out]
    if decimals > 0 and not trailing_point:
        out = [t[:-1] if t[-1] == "." else t for t in out]
    elif decimals == 0 and trailing_point:
        out = [t + "." for t in out]
    if not leading_zero:
        out = [("." + t[2:] if t[:2] == "0." and len(t) > 2 else "-." + t[3:] if t[:3] == "-0." and len(t) > 3 else t)
               for t in out]
    return out


def output_decimals(info: FormatInfo, letter: str, units: str) -> int:
    """Decimals to write for ``letter``: the input's precision, at least 4 in mm and 5 in inch (lengths only)."""
    floor = 5 if units == "inch" else 4
    if letter.upper() in "ABC":
        floor = 4
    return max(info.decimals.get(letter.upper(), 0), floor)


# ----------------------------------------------------------------------------------------------------------------
# tokenizer


def tokenize_line(line: str) -> list:
    """Tokens of one line: list of (kind, text, start, end) with kind in comment / word / other.

    For a word, text is the letter and its value as written (``"X-.0531"``); start/end are column offsets in the
    line. This is the same regular expression the parser uses.
    """
    # m.lastindex is the alternative that matched (1, 2 comment; 3, 4 word; 5 other): one lookup per token, which
    # matters to the writer that calls this for every motion block
    kinds = _TOKEN_KINDS
    return [(kinds[m.lastindex], m.group(), *m.span()) for m in _TOKEN.finditer(line)]


def word_spans(program: Program, row: int) -> dict:
    """Column spans of the words of the block behind ``row``: letter -> (start, end) of its *value* in the raw line.

    Cheap on demand (it re-tokenizes one line); letters that occur more than once (G, M) keep the last.
    """
    line = program.lines[int(program.line_index[row])]
    spans = {}
    for m in _TOKEN.finditer(line):
        if m.group(3):
            spans[m.group(3).upper()] = (m.start(4), m.end(4)) if m.group(4) is not None else (m.end(3), m.end(3))
    return spans


def parse_tool_table(text: str, units: str = "mm") -> dict:
    """Read a LinuxCNC tool table (``T1 P1 D0.25 Z+0.0 ;comment``): tool number -> Z length in **mm**.

    ``units`` is the unit the table is written in ("mm" or "inch"; a standalone ``rs274`` reads tables in inch).
    Raises ValueError naming the line when a row has no T word or a malformed number.
    """
    if units not in ("mm", "inch"):
        raise ValueError(f"units must be 'mm' or 'inch', got {units!r}")
    scale = MM_PER_INCH if units == "inch" else 1.0
    table = {}
    for n, raw in enumerate(text.splitlines(), 1):
        body = raw.split(";", 1)[0].strip()
        if not body:
            continue
        words = dict(re.findall(r"([A-Za-z])\s*([-+]?[0-9.]+)", body))
        words = {k.upper(): v for k, v in words.items()}
        try:
            tool = int(float(words["T"]))
            table[tool] = float(words.get("Z", "0")) * scale
        except (KeyError, ValueError) as exc:
            raise ValueError(f"tool table line {n}: cannot read {raw!r} ({exc})") from None
    return table


# ----------------------------------------------------------------------------------------------------------------
# the interpreter


def parse_file(path, *, encoding: str | None = None, **kwargs) -> Program:
    """Read ``path`` and parse it with :func:`parse_program` (UTF-8, falling back to ISO-8859-1 for old Fanuc files)."""
    data = open(path, "rb").read()
    if b"\x00" in data:
        raise GcodeError(str(path), 1, "binary file (NUL bytes): not G-code")
    if encoding is None:
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            text = data.decode("iso-8859-1")
    else:
        text = data.decode(encoding)
    return parse_program(text, str(path), **kwargs)


def parse_program(
    text: str,
    source: str = "<string>",
    *,
    passthrough_unsupported: bool = False,
    tool_table: Mapping[int, float] | None = None,
    reference_points: Mapping[str, Sequence[float]] | None = None,
    setup=None,
    require_setup: bool = False,
    machine=None,
) -> Program:
    """Interpret RS-274 text as LinuxCNC does and return its motion table.

    text : the program; str (bytes are refused: decode first, or use :func:`parse_file`)
    source : name used in messages (``file:line: reason``)
    passthrough_unsupported : leave blocks that could move an axis but are not understood (macros, subprogram calls)
        as they are, recorded in ``Program.unsupported``, instead of raising GcodeError
    tool_table : tool number -> tool length (Z) in **mm**, for G43 (see :func:`parse_tool_table`)
    reference_points : {"G28": (6,), "G30": (6,)} reference points in machine coordinates, mm / degrees (default zero)
    setup : the controller's setup (:class:`trueaxis.nc.setup.Setup`): work offsets (with their XY rotation),
        G92 shift, active system, home positions and tool offsets at program start; it completes ``tool_table`` and
        ``reference_points``. What it does not give is unknown; ``Program.setup_used`` lists what the rows used.
    require_setup : refuse (GcodeError naming the offset) a move made under a work offset, G92 shift or tool length
        that is unknown: a work system the program selects (G54..G59.3) that neither the setup nor a G10 in the
        program gives, a G92.3 restore without the stored shift, a tool length (G43 H, or M6 when the setup applies
        lengths at the tool change) of a tool not given; unless ``setup.offsets_zero``. Without it such values are
        zero (LinuxCNC's defaults) and listed as "not given" in ``setup_used``.
    machine : the :class:`~trueaxis.machine.Machine` the program is for (None: one with every axis): of a work
        offset, only the components of its ``required_axes`` are required; a linear axis' component it lacks is taken
        as 0 and ``setup_used`` says so (``zero_no_such_axis``)
    """
    if isinstance(text, (bytes, bytearray)):
        raise GcodeError(source, 1, "got bytes, expected text: decode the file first (or use parse_file)")
    if not isinstance(text, str):
        raise GcodeError(source, 1, f"expected program text (str), got {type(text).__name__}")
    if "\x00" in text:
        raise GcodeError(source, text[: text.index("\x00")].count("\n") + 1, "binary data (NUL byte): not G-code")
    if not text.strip():
        raise GcodeError(source, 1, "empty program: no blocks")
    from .flatten import read_flat  # parameters, expressions, O-words and M98 evaluated; rs274's block checks

    early = _EarlyScan.start_for(text)

    def interpret(t):
        reader = _Interpreter(t, source, passthrough_unsupported, tool_table, reference_points, setup, require_setup,
                              machine)
        reader.early = early if t is text else None  # (a flattened program reads other text)
        prog = reader.run()
        styles = reader.early.styles() if reader.early is not None else None
        if styles is not None and len(prog.lines) == reader.early.n_lines:
            prog._number_styles = styles  # (format_info's per-block passes, made beside the checks)
            prog._text_bytes = reader.early.pre  # (line starts, bytes) of "".join(prog.lines), for the writer
        return prog

    return read_flat(text, source, passthrough_unsupported, split_lines, interpret)


# A long ASCII program's text-only compiled passes run on a thread of their own while the block checks run (from this
# many bytes on, and with the kernels compiled ahead of time, which release the GIL).
EARLY_SCAN_MIN_BYTES = 1 << 20


class _EarlyScan:
    """The reader's compiled passes that need the text alone, over a long ASCII program, on a thread of their own
    while the block checks (``check``) and the splitting into lines run on the caller's: the bytes and line starts
    (``fast_read.scan_text``), the pre-scan of every line (``fast_read.scan_lines`` over all of them: each line is read
    alone, so any block of lines is a slice of it) and the number style of every ``_STYLE_BLOCK_LINES`` lines
    (``fast_read.number_style``, for ``Program.format_info``). The same kernels on the same bytes as the reader's own
    calls: the same results. Nothing here raises: a failure leaves the reader to make its own passes."""

    def __init__(self, text):
        import threading

        self.text, self.pre, self.lines, self._styles, self.n_lines = text, None, None, None, -1
        self._thread = threading.Thread(target=self._run, name="trueaxis-prescan", daemon=True)
        self._thread.start()

    @classmethod
    def start_for(cls, text):
        """An early scan of ``text``, or None (short, not ASCII, the pre-scan off, or no kernels compiled ahead of
        time: numba's kernels would hold the GIL)."""
        if not FAST_READ or len(text) < EARLY_SCAN_MIN_BYTES or not text.isascii():
            return None
        from ..compiled import aot_available

        return cls(text) if aot_available() else None

    def _run(self):
        try:
            from . import fast_read

            pre = fast_read.scan_text(self.text)
            if pre is None:
                return
            starts, buf = pre
            n = starts.size - 1
            lines = fast_read.scan_lines(buf, starts, 0, n)
            styles = [fast_read.number_style(buf[starts[i] : starts[min(n, i + _STYLE_BLOCK_LINES)]])
                      for i in range(0, n, _STYLE_BLOCK_LINES)]
            self.pre, self.lines, self._styles, self.n_lines = pre, lines, styles, n
        except Exception:  # noqa: BLE001 -- the reader makes its own passes
            self.pre = self.lines = self._styles = None

    def result(self):
        """(pre, all lines' scan) once the thread is done, or None."""
        self._thread.join()
        return None if self.pre is None else (self.pre, self.lines)

    def styles(self):
        self._thread.join()
        return self._styles


def _first_of_each(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(ids, return_index=True)`` for ids that come in long runs (a setup id per row): the first of each
    value is at the start of a run, so only the runs' starts are sorted."""
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]]) if ids.size else np.zeros(0, np.int64)
    uniq, at = np.unique(ids[starts], return_index=True)
    return uniq, starts[at]


class _Interpreter(InterpState, Conversion, ArcConversion, CycleConversion):
    """One lean pass over the lines; state in current program units like LinuxCNC's interpreter. Its parts are in
    their own modules, as rs274ngc's: the state (``interp_state``), a block's words (``interp_read``), its checks
    (``interp_check``), the conversion by modal group (``interp_convert``), arcs (``interp_arc``) and canned cycles
    (``interp_cycles``); here the block loop with the fast path of plain moves, and the rows into a Program."""

    def __init__(self, text, source, passthrough, tool_table, reference_points, setup=None, require_setup=False,
                 machine=None):
        self.text = text
        self.source = source
        self.passthrough = passthrough
        self.setup = setup
        self.require_setup = require_setup
        self.machine = machine
        self.offsets_zero = bool(setup is not None and setup.offsets_zero)
        # tool number -> (6,) offsets X Y Z A B C in mm / deg (Z: the length), and where each came from
        self.tool_off_mm: dict = {}
        self.tool_src: dict = {}
        self.positions_lost: list = []  # (line index, what): see Program.positions_lost
        for k, v in (tool_table or {}).items():
            off = np.zeros(6)
            if np.ndim(v) == 0:
                off[2] = float(v)
            else:
                off[:] = np.asarray(v, float)
            self.tool_off_mm[int(k)] = off
            self.tool_src[int(k)] = "tool table"
        refs = dict(reference_points or {})
        if setup is not None:
            for t, tool_offset in setup.tools.items():
                self.tool_off_mm[int(t)] = np.asarray(tool_offset.offset, float).copy()
                self.tool_src[int(t)] = tool_offset.source
            for key, home in setup.home.items():
                refs.setdefault(key, home.values)
        self.ref_mm = {
            "G28": np.array(refs.get("G28", np.zeros(6)), float),
            "G30": np.array(refs.get("G30", np.zeros(6)), float),
        }
        # which home positions the user gave (a program's G28.1 / G30.1 sets one too, see interp_convert)
        self.ref_given0 = {key: key in refs for key in self.ref_mm}
        for k, v in self.ref_mm.items():
            if v.shape != (6,):
                raise ValueError(f"reference point {k} must have 6 values (X Y Z A B C), got shape {v.shape}")
        self.warnings: list = []
        self.unsupported: list = []
        self.position_sets: list = []  # (line index, axis indices, what): G92 / G10 L20 set from the current position
        self.block_delete_lines: list = []  # 1-based lines starting with '/' (block delete), read with the switch off
        self.params: dict = {}

    # -- helpers ------------------------------------------------------------------------------------------------
    def err(self, line_no, reason):
        return GcodeError(self.source, line_no, reason)

    def warn(self, line_no, message):
        self.warnings.append(f"{self.source}:{line_no}: {message}")

    def unsupported_block(self, line_no, reason):
        self.unsupported.append((line_no, reason))
        self.warn(line_no, f"passed through uninterpreted: {reason}")

    def not_understood(self, line_no, reason):
        """A code the reader does not understand: it may change the meaning of what follows (G43.4 tool centre point,
        a work offset G10 L2 sets), so it is refused unless the user asked for it to be passed through."""
        if not self.passthrough:
            raise self.err(line_no, reason + " (it may change what the program's positions mean; "
                           "--passthrough-unsupported leaves the block as it is)")
        self.unsupported_block(line_no, reason)

    def run(self) -> Program:
        """Read every line: a plain G0 / G1 / G2 / G3 block on the fast path below (its few values in locals), any other
        block through :meth:`block` (the state's attributes, synchronised around it); the rows into a Program."""
        lines = split_lines(self.text)
        self.start_state()
        r_start, r_end, r_line, r_motion = self.r_start, self.r_end, self.r_line, self.r_motion
        r_kind, r_words, r_state, r_arc, cycle = self.r_kind, self.r_words, self.r_state, self.r_arc, self.cycle_words
        pos, motion_mode, feed, cur_state, absolute, inverse, diameter, plane, arc_abs, arc_tol, arc_rmin = \
            self.fast_locals()
        fast_match, hypot, n_lines = _FAST.match, math.hypot, len(lines)
        pre, min_run = self.pre_scan(lines)
        numbered, drain, blk_lo, blk_hi = enumerate(lines), deque(maxlen=0).extend, 0, 0  # drain: consumes
        for li, raw in numbered:
            fast = None  # the fast path: a plain G0-G3 block ("N300G1X4.6526Z-.0007", "X1 Y2 F300"); else block()
            if pre is not None:
                if li >= blk_hi:  # the next FAST_READ_BLOCK lines
                    blk_lo, blk_hi, blk, blk_code, blk_vals, blk_run = self.scan_block(pre, li, n_lines)
                i = li - blk_lo
                g = int(blk_code[i])
                if g < 4 and blk_run[i] >= min_run:
                    run = self.fast_run(blk, li, blk_lo, pos, motion_mode, feed)
                    if run is not None:  # its lines after this one skipped (in C)
                        pos, motion_mode, feed, cur_state, n_run = run
                        drain(islice(numbered, n_run - 1))
                        continue
                fast = g < 4 or (None if g == 4 else False)  # 4: more digits than the pre-scan reads: the regex
                if fast:
                    x, y, z, a_, b_, c_, i_, j_, k_, r_, f_ = blk_vals[i].tolist()
            if fast is None:
                fast, g, x, y, z, a_, b_, c_, i_, j_, k_, r_, f_ = _regex_words(fast_match(raw))
            if fast:  # (values: NaN where the block has no such word; g: -1 where it has no G word)
                if diameter and x == x:
                    x = 0.5 * x  # G7: the X word is a diameter
                mode = motion_mode if g < 0 else g * 10
                if f_ == f_ and f_ != feed:
                    feed, cur_state = self.fast_feed(li, raw, f_)
                if mode == 0 or (mode <= 30 and feed != 0.0 and (f_ == f_ or not inverse)):
                    target, seen = pos[:], 0
                    if absolute:
                        if x == x:
                            target[0] = x
                            seen = 1
                        if y == y:
                            target[1] = y
                            seen |= 2
                        if z == z:
                            target[2] = z
                            seen |= 4
                    else:
                        seen = _incremental_words(target, x, y, z)
                    if a_ == a_ or b_ == b_ or c_ == c_:
                        seen = _rotary_words(target, seen, absolute, a_, b_, c_)
                    if f_ == f_:
                        seen |= 2048
                    if g >= 0:
                        cycle["il_flag"] = False
                    code = -1  # the row's motion code where the block is read here (emit() inlined: the hot path)
                    if mode <= 10 and not (i_ == i_ or j_ == j_ or k_ == k_ or r_ == r_):
                        code = mode // 10
                    elif mode >= 20 and r_ != r_:  # an I J K arc (the other hot path); R arcs, odd cases: arc_to
                        a0, a1, an = _PLANE_AXES[plane]
                        ijk = (i_, j_, k_)
                        w0, w1 = ijk[a0], ijk[a1]
                        o0 = w0 if w0 == w0 else 0.0
                        o1 = w1 if w1 == w1 else 0.0
                        if arc_abs:
                            c0, c1 = o0, o1
                        else:
                            c0, c1 = pos[a0] + o0, pos[a1] + o1
                        if (w0 == w0 or w1 == w1) and ijk[an] != ijk[an] and ijk_radii_refusal(  # (else arc_to)
                                hypot(pos[a0] - c0, pos[a1] - c1), hypot(target[a0] - c0, target[a1] - c1), arc_tol,
                                arc_rmin) is None:
                            center = [0.0, 0.0, 0.0]
                            center[a0], center[a1], center[an] = c0, c1, pos[an]
                            r_arc[len(r_line)] = (center, plane, 1)
                            seen |= (_I_BIT if i_ == i_ else 0) | (_J_BIT if j_ == j_ else 0) | \
                                (_K_BIT if k_ == k_ else 0)
                            code = 2 if mode == 20 else 3
                    if code >= 0:
                        motion_mode = mode
                        r_start.fromlist(pos)
                        r_end.fromlist(target)
                        r_line.append(li)
                        r_motion.append(code)
                        r_kind.append(ROW_PROGRAMMED)
                        r_words.append(seen)
                        r_state.append(cur_state)
                        pos = target
                        continue
                    if mode >= 20:
                        motion_mode = mode
                        self.pos = pos
                        self.fast_arc(li, mode, target, seen, i_, j_, k_, r_)
                        continue
            self.pos, self.motion_mode = pos, motion_mode  # the general path, on the state's attributes
            if self.block(li, raw):  # the program's end
                break
            pos, motion_mode, feed, cur_state = self.pos, self.motion_mode, self.feed, self.cur_state
            absolute, inverse, diameter, plane, arc_abs, arc_tol, arc_rmin = self.fast_locals()[4:]
        return self.assemble(lines)

    def fast_locals(self):
        """The state the fast path holds in locals (it writes back the position, motion mode and feed)."""
        return (self.pos, self.motion_mode, self.feed, self.cur_state, self.absolute, self.inverse, self.diameter,
                self.plane, self.arc_abs, self.arc_tol, self.arc_rmin)

    def fast_feed(self, li, raw, f_):
        """A plain block's new F word: (the feed, the state with it)."""
        if f_ < 0.0:
            raise self.err(li + 1, f"negative feed rate F{_FAST.match(raw).group(12)}")
        self.feed = f_
        self.refresh_state()
        return f_, self.cur_state

    def pre_scan(self, lines):
        """The compiled pre-scan (fast_read) of the whole text (line starts, bytes), or None (regular expressions
        only), and the shortest run of plain moves read in compiled code. ``scan_block`` then reads which lines are
        plain blocks, their G digit and values, exactly as the regular expression and float() read them,
        FAST_READ_BLOCK lines at a time."""
        self.early_lines = None
        if not (FAST_READ and lines):
            return None, 0
        from . import fast_interp, fast_read  # runs of plain straight moves read in compiled code

        early = self.early.result() if getattr(self, "early", None) is not None else None
        self.early_lines = None if early is None else early[1]
        pre = fast_read.scan_text(self.text) if early is None else early[0]
        if pre is not None and len(pre[0]) != len(lines) + 1:
            pre = None  # not split as split_lines splits (cannot happen for ASCII text): no pre-scan
        return pre, fast_interp.MIN_RUN

    def scan_block(self, pre, lo, n_lines):
        """The pre-scan of FAST_READ_BLOCK lines from lo: (lo, hi, the kernel's arrays, code per line, values per line
        (lines, 11), run length per line), as arrays: the loop reads the lines it does not hand to ``fast_run`` (a few
        per cent of a long program's lines), not every line's 11 values as Python floats."""
        from . import fast_interp, fast_read

        hi = min(n_lines, lo + FAST_READ_BLOCK)
        if self.early_lines is not None:  # (the early scan's lines lo..hi-1: each line read alone, the same values)
            b_status, b_g, b_vals = (x[lo:hi] for x in self.early_lines)
        else:
            b_status, b_g, b_vals = fast_read.scan_lines(pre[1], pre[0], lo, hi)
        # code: the G digit (-1: none) for a block read here, 4: by the regex, 5: not a fast block
        code = np.where(b_status == fast_read.LINE_FAST, b_g, np.where(b_status == fast_read.LINE_SLOW, 4, 5))
        runs = fast_interp.run_lengths(b_status, b_g, b_vals) if fast_interp.ENABLED else np.zeros(code.size, np.int64)
        return lo, hi, (b_status, b_g, b_vals), code, b_vals, runs

    def fast_run(self, blk, li, lo, pos, motion_mode, feed):
        """A run of plain straight moves from line li, read in compiled code (fast_interp): (position, motion
        mode, feed, state, the run's number of lines), or None when it reads none."""
        from . import fast_interp

        b_status, b_g, b_vals = blk
        run = fast_interp.straight_run(b_status, b_g, b_vals, li - lo, np.array(pos, float), motion_mode, feed,
                                       self.absolute, self.inverse, self.diameter, self.plane, self.arc_abs,
                                       self.arc_tol, self.arc_rmin)
        if not run[0]:
            return None
        state0 = self.cur_state
        rows = fast_interp.feed_changes(run[5], feed)  # the states, where the feed changes
        changed = list(zip(rows, self.feed_states(run[5][rows])))
        if changed:
            feed = self.feed
        pos, motion_mode = fast_interp.append_rows(run, li, state0, changed, self.r_start, self.r_end, self.r_line,
                                                   self.r_motion, self.r_kind, self.r_words, self.r_state,
                                                   ROW_PROGRAMMED, self.r_arc_runs, self.plane)
        if run[6]:
            self.cycle_words["il_flag"] = False
        return pos, motion_mode, feed, self.cur_state, run[0]

    def fast_arc(self, li, mode, target, seen, i_, j_, k_, r_):
        """A plain arc block the inline I J K path did not take (an R arc, an end point off the circle)."""
        extra = {}
        for letter, v in (("I", i_), ("J", j_), ("K", k_), ("R", r_)):
            if v == v:
                extra[letter] = v
                seen |= _WORD_BIT[letter]
        try:
            self.arc_to(li + 1, li, mode, extra, target, self.pos, self.plane, self.arc_abs, self.inch, self.emit,
                        seen)
        except ValueError as exc:
            raise self.err(li + 1, str(exc)) from None

    def block(self, li, raw):
        """A line the fast path did not take: blank, %, o-word, a literal parameter assignment, or a block for
        ``interp_read.read_block`` and ``interp_convert``; its errors as ``file:line: reason``. True at the program's
        end (M2, M30, the second %)."""
        line_no = li + 1
        stripped = raw.strip()
        if not stripped:
            return
        if stripped[0] == "%":
            self.percent_seen += 1
            if self.percent_seen >= 2:
                self.ended = True
            return self.ended
        if (stripped[0] in "oO" or stripped[:1] in "nN") and _OWORD.match(raw):
            if self.passthrough:
                self.unsupported_block(line_no, "o-word subroutine / control flow")
                return
            raise self.err(line_no, "o-word subroutine / control flow is not supported (the moves it makes "
                           "are not in the text)")
        if "#" in raw:
            m = _ASSIGN.match(raw.rstrip("\r\n"))
            if m:
                self.params[int(m.group(1))] = float(m.group(2))
                return
        gcodes, mcodes, vals, refuse, macro_nonmoving = read_block(self, raw, line_no, _TOKEN.findall)
        if not gcodes and not mcodes and not vals:
            if macro_nonmoving:
                self.unsupported_block(line_no, macro_nonmoving)
            return
        try:
            self.convert_block(li, line_no, gcodes, mcodes, vals, refuse, macro_nonmoving)
        except GcodeError:
            raise
        except (ValueError, OverflowError, ZeroDivisionError, KeyError) as exc:
            raise self.err(line_no, str(exc) or type(exc).__name__) from None
        return self.ended

    def assemble(self, lines) -> Program:
        """The row accumulators into a :class:`Program` (the states' values per row, the setup used)."""
        r_line, r_arc, used_axes = self.r_line, self.r_arc, self.used_axes
        m = len(r_line)
        # the states' keys (feed, 6 flags, offsets, setup, diameter; dicts keep insertion order: index == state id),
        # column by column: transposed by zip in C (a G93 program has a state per block: a million tuples)
        cols = tuple(zip(*self.states)) or ((0.0,), (False,), (False,), (40,), (0,), (False,), (True,), ((0.0,) * 6,),
                                            (self.meta_now,), (False,))
        sid = np.array(self.r_state, np.int64)
        st_feed = np.array(cols[0], float)
        st_flags = np.array(cols[1:7], np.int64).T.reshape(-1, 6)
        st_off = np.array(cols[7], float).reshape(-1, 6)
        st_diameter = np.array(cols[9], bool)
        # the setup in force per state: few distinct ones (states differ mostly by feed, e.g. under G93), numbered in
        # the order of first use
        meta_index = {k: i for i, k in enumerate(dict.fromkeys(cols[8]))}
        meta_of_state = np.fromiter(map(meta_index.__getitem__, cols[8]), np.int64, len(cols[8]))
        metas = list(meta_index)
        mid = meta_of_state[sid]
        rotation = np.array([mt[0] for mt in metas], float)[mid].reshape(m)
        # the axes the rows' words name (the compiled runs' too), before the setup's check of what they require
        words = np.array(self.r_words, np.uint16)
        mask = int(np.bitwise_or.reduce(words)) if m else 0
        used_axes.update(c for c in AXES if mask & _WORD_BIT[c])
        kind = np.array(self.r_kind, np.int64)
        setup_used = self.setup_report(mid, kind, np.array(r_line, np.int64), metas, self.hist, self.selects_work,
                                       used_axes)
        arc_center = np.full((m, 3), np.nan)
        arc_plane = np.zeros(m, np.int8)
        arc_turns = np.zeros(m, np.int16)
        if r_arc:
            idx = np.fromiter(r_arc.keys(), np.int64, len(r_arc))
            arc_center[idx] = [v[0] for v in r_arc.values()]
            arc_plane[idx] = [v[1] for v in r_arc.values()]
            arc_turns[idx] = [v[2] for v in r_arc.values()]
        for rows, centres, plane in self.r_arc_runs:  # (other rows than r_arc's)
            arc_center[rows] = centres
            arc_plane[rows] = plane
            arc_turns[rows] = 1
        units_seen = self.units_seen
        units = "mixed" if len(units_seen) > 1 else ("inch" if units_seen == {"inch"} else "mm")
        # the accumulators' memory itself (array("d") is float64; no row is added to them after this): not copied
        start = np.frombuffer(self.r_start, np.float64).reshape(m, 6)
        end = np.frombuffer(self.r_end, np.float64).reshape(m, 6)
        offset = st_off[sid].reshape(m, 6)
        feed_rows = st_feed[sid].reshape(m)
        # Numbers too large for a float (a 400-digit X), or sums of huge ones, must not reach a writer as inf/NaN.
        # (Checked on the whole arrays first: a row-wise all() over six columns costs a million-row program 0.1 s.)
        if not (np.isfinite(start).all() and np.isfinite(end).all() and np.isfinite(offset).all()
                and np.isfinite(feed_rows).all() and (np.isfinite(arc_center) | (arc_plane == 0)[:, None]).all()):
            finite = (np.isfinite(start).all(axis=1) & np.isfinite(end).all(axis=1) & np.isfinite(offset).all(axis=1)
                      & np.isfinite(feed_rows) & (np.isfinite(arc_center).all(axis=1) | (arc_plane == 0)))
            bad = int(np.argmin(finite))
            raise self.err(int(r_line[bad]) + 1, "number out of range: a position, offset or feed is not finite")
        return Program(
            source=self.source, start=start, end=end, offset=offset,
            motion=np.array(self.r_motion, np.int8), kind=np.array(self.r_kind, np.int8),
            arc_center=arc_center, arc_plane=arc_plane, arc_turns=arc_turns, feed=feed_rows,
            inverse_time=st_flags[sid, 0].astype(bool).reshape(m),
            inch=st_flags[sid, 1].astype(bool).reshape(m),
            cutter_comp=st_flags[sid, 2].astype(np.int8).reshape(m),
            tool=st_flags[sid, 3].astype(np.int32).reshape(m),
            incremental=st_flags[sid, 4].astype(bool).reshape(m),
            arc_incremental=st_flags[sid, 5].astype(bool).reshape(m),
            diameter=st_diameter[sid].reshape(m), line_index=np.array(r_line, np.int32), words=words, lines=lines,
            units=units, axes_present="".join(a for a in AXES if a in used_axes), warnings=self.warnings,
            unsupported=self.unsupported, rotation=rotation, setup_used=setup_used, position_sets=self.position_sets,
            block_delete_lines=self.block_delete_lines, positions_lost=self.positions_lost,
            modes_stated=self.modes_stated,
            machine_rows_not_given=self.machine_rows_not_given(mid, kind, metas, self.required_axes(used_axes)),
        )

    def setup_report(self, sid, kind, line, st_meta, hist, selects_work, used_axes):
        # sid: (M,) index of each row's setup in st_meta
        """What the rows used of the control's setup (one entry per value, in the order of first use), and, under
        ``require_setup``, the refusal of the first move made under a value that was not given."""
        out, seen = [], set()
        missing_home = self.ref_missing if self.require_setup else None
        if missing_home is not None:
            # only a move made after it depends on where the home is (a program that ends with G28 posts as it is)
            after = (np.asarray(line)[(kind == ROW_PROGRAMMED) | (kind == ROW_CYCLE)] + 1) > missing_home[0]
            missing_home = missing_home if after.any() else None

        def refuse(line_no, reason, options="--var / --setup"):
            # the program's first missing value in line order: a G28 / G30 home, or this offset
            if missing_home is not None and missing_home[0] <= line_no:
                line_no, reason, options = *missing_home, "--var / --setup"
            raise self.err(line_no, f"{reason}: give the control's setup ({options}), or --offsets-zero if zero is "
                                    "meant")

        if sid.size == 0:
            if missing_home is not None:
                refuse(*missing_home)
            return out
        uniq, first = _first_of_each(sid)
        setup_given_active = self.setup is not None and self.setup.active is not None
        moving = (kind == ROW_PROGRAMMED) | (kind == ROW_CYCLE)
        checked = set(_first_of_each(sid[moving])[0].tolist())
        required = self.required_axes(used_axes)
        for s_id, row in sorted(zip(uniq.tolist(), first.tolist()), key=lambda t: t[1]):
            r, active, g5x_ver, g92_ver, tlo_ver, unknown, g92_reason, tlo_reason = st_meta[s_id]
            line_no = int(line[row]) + 1
            if self.require_setup and s_id in checked:
                missing = "".join(a for a in unknown if a in required)
                if missing and (selects_work or setup_given_active):
                    refuse(line_no, f"work offset {_SYSTEM_NAMES[active - 1]} ({' '.join(missing)}) was not given")
                for reason in (g92_reason, tlo_reason):
                    if reason:
                        refuse(line_no, reason, "--tool-table / --var / --setup")
            key = ("g5x", active, g5x_ver)
            if key not in seen:
                seen.add(key)
                rec = hist[key]
                entry = {"what": _SYSTEM_NAMES[active - 1], "values_mm_deg": [float(v) for v in rec["values"]],
                         "rotation_deg": float(rec["rotation"]), "source": rec["source"], "first_line": line_no}
                # a linear axis the machine lacks: its component moves nothing, 0 whatever the control holds
                absent = "".join(a for i, a in enumerate("XYZ") if a not in required and not rec["known"][i])
                if absent:
                    entry["zero_no_such_axis"] = absent
                if not all(rec["known"][i] for i, a in enumerate("XYZ") if a in required) and not (
                        selects_work or setup_given_active):
                    entry["source"] = ("the program selects no work system and the setup gives none: program "
                                       "coordinates are machine coordinates")
                    entry["assumed"] = True
                out.append(entry)
            key = ("g92", g92_ver)
            if key not in seen and (g92_ver > 0 or np.any(hist[key]["values"] != 0.0)):
                seen.add(key)
                rec = hist[key]
                out.append({"what": "G92", "values_mm_deg": [float(v) for v in rec["values"]],
                            "source": rec["source"], "first_line": line_no})
            key = ("tlo", tlo_ver)
            rec = hist[key]
            if key not in seen and rec["tool"] != -1:
                seen.add(key)
                what = "tool offset (G43.1)" if rec["tool"] == -2 else f"tool {rec['tool']} offset"
                out.append({"what": what, "values_mm_deg": [float(v) for v in rec["values"]],
                            "source": rec["source"], "applied_by": rec["how"], "first_line": line_no})
        if missing_home is not None:
            refuse(*missing_home)
        return out

    def machine_rows_not_given(self, mid, kind, metas, required):
        # mid: (M,) index of each row's setup in metas
        """``Program.machine_rows_not_given``: the G28 / G30 / G53 rows under a setup with a value not given (a work
        offset component of the ``required`` axes, a G92 shift, a tool length), and those ending at a home position
        not given."""
        machine_rows = np.nonzero((kind == ROW_REFERENCE) | (kind == ROW_MACHINE))[0]
        if machine_rows.size == 0:
            return None
        lacking = np.array([any(a in required for a in mt[5]) or bool(mt[6]) or bool(mt[7]) for mt in metas], bool)
        rows = np.union1d(machine_rows[lacking[mid[machine_rows]]], np.array(self.home_not_given_rows, np.int64))
        return rows.astype(np.int64) if rows.size else None

    def required_axes(self, used_axes) -> str:
        """The axes whose work offset components a move needs (``Machine.required_axes``; without a machine, one with
        every axis: X Y Z and the rotary axes the program commands)."""
        if self.machine is not None:
            return "".join(self.machine.required_axes("".join(used_axes)))
        return "XYZ" + "".join(a for a in "ABC" if a in used_axes)

    def resolve(self, text):
        """Value of ``#n`` / ``[#n]`` when #n was assigned a literal; None for anything else."""
        m = _PARAM_REF.match(text.replace(" ", ""))
        if not m:
            return None
        n = int(m.group(1) or m.group(2))
        return self.params.get(n)

    def g10(self, line_no, fvals, ax, g5x, rot, active, g92, tlo, pos, u_scale, machine_of, program_of):
        """G10 L1 (tool offsets), L2 / L20 (work offsets; L2 with its rotation R); other L values are recorded and
        ignored. Returns (system index, axis indices set) for L2 / L20, else None."""
        L = int(fvals.get("L", -1))
        if L in (2, 20):
            p = int(fvals.get("P", 0))
            if not 0 <= p <= 9:
                raise ValueError(f"G10 L{L} P{p}: coordinate system must be P0..P9")
            idx = active if p == 0 else p
            if L == 20 and ("R" in fvals or rot[active] != 0.0 or rot[idx] != 0.0):
                raise ValueError("G10 L20 with a rotated work system is not supported")
            old = g5x[active].copy()
            old_rot = rot[active]
            m_pos = machine_of(pos)
            for i, v in ax:
                if L == 2:
                    g5x[idx, i] = v
                else:  # L20: the current point gets coordinate v in system idx
                    g5x[idx, i] = pos[i] + old[i] - v
            if "R" in fvals:
                rot[idx] = float(fvals["R"])
            if idx == active:
                if old_rot == 0.0 and rot[active] == 0.0:
                    _add(pos, old - g5x[active])
                else:
                    pos[:] = program_of(m_pos)
            return idx, [i for i, _ in ax]
        if L == 1:
            t = int(fvals.get("P", 0))
            off = self.tool_off_mm.setdefault(t, np.zeros(6)).copy()
            for i, v in ax:
                off[i] = v * u_scale[i]
            self.tool_off_mm[t] = off
            self.tool_src[t] = f"{self.source}:{line_no} (G10 L1 P{t})"
            return None
        self.not_understood(line_no, f"G10 L{L} not supported")
        return None

    def tool_offsets(self, h, u_scale, zero_ok, line_no, how):
        """(offsets (6,) in program units, tool number in force, reason it is unknown or "") of tool / H number h."""
        off = self.tool_off_mm.get(h)
        if off is not None:
            return off / u_scale, h, ""
        if h == 0 or zero_ok:
            return np.zeros(6), h, ""
        self.warn(line_no, f"{how}: tool {h} is not in the tool table or setup; length 0 used")
        return np.zeros(6), h, f"the length of tool {h} ({how}) was not given"

    def tool_source(self, h, zero_ok):
        if h in self.tool_src:
            return self.tool_src[h]
        return "H0: no offset" if h == 0 else ("--offsets-zero" if zero_ok else "not given")
