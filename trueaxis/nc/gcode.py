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
from array import array
from dataclasses import dataclass, field
from functools import cached_property
from typing import Mapping, Sequence

import numpy as np

from .grammar import NUMBER, PLANE_AXES
from .interp_arc import ArcConversion
from .interp_cycles import CycleConversion
from .interp_read import read_block
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

AXES = "XYZABC"
MM_PER_INCH = 25.4


# Program.words bit mask: which words the source block had (bit i for letter WORD_BITS[i])
WORD_BITS = "XYZABCIJKRPF"
_WORD_BIT = {c: 1 << i for i, c in enumerate(WORD_BITS)}

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
_DECIMALS = re.compile(r"([A-Za-z])[ \t]*[-+]?[0-9]*\.([0-9]*)")
_LEADING_ZERO = re.compile(r"[XYZIJKR][-+]?(0?)\.[0-9]")
# From a comment's start to the end of its line (what the writer's dialect checks look past)
_COMMENT_TO_EOL = re.compile(r"[(;][^\r\n]*")

# Lines end at \n, \r\n or a lone \r, as an editor counts them (str.splitlines also splits at \f, \v, \x1c-\x1e,
# \x85, \u2028 and \u2029, which would shift the line numbers of the messages).
_LINE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n)|[^\r\n]+\Z")
_OTHER_BREAKS = re.compile("[\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029]")
# The reader's compiled pre-scan of plain blocks (fast_read); False: the regular expression and float() on every line
# (the same results, slower). FAST_READ_BLOCK lines are scanned at a time (their values as Python floats).
FAST_READ = True
FAST_READ_BLOCK = 4096
# Word values (coordinates, offsets, feeds) must stay below this in size: 1000 km, or 25,400 km in inches, is no
# machine's travel, and bounded values keep every sum, square and unit conversion downstream finite. The fast path's
# regular expression takes at most 9 digits before the point, so larger values go through the checked general path.
MAX_WORD_VALUE = 1e9

_SYSTEM_NAMES = ("G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3")
_AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2, "A": 3, "B": 4, "C": 5}
_LINEAR = np.array([True, True, True, False, False, False])
_LINEAR_T = (True, True, True, False, False, False)


def split_lines(text: str) -> list:
    """The lines of ``text`` with their endings (``"".join(split_lines(t)) == t``), split at \n, \r\n and \r only."""
    if _OTHER_BREAKS.search(text) is None:
        return text.splitlines(keepends=True)
    return _LINE.findall(text)


def _add(pos: list, delta) -> None:
    """pos += delta, in place, for the 6-element position list."""
    for i in range(6):
        pos[i] += float(delta[i])
_PLANE_AXES = PLANE_AXES
_KNOWN_M = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 19, 30, 48, 49, 50, 51, 52, 53, 60, 61, 62, 63, 64, 65, 66, 67, 68, 70, 71, 72, 73}
_MOVING_M = {98: "subprogram call M98", 99: "subprogram return M99"}
# G codes (x10) whose moves the reader cannot reproduce: refused (or passed through on request)
_MOVING_G = {
    650: "macro call G65", 660: "modal macro call G66", 661: "modal macro call G66.1",
    330: "spindle-synchronised motion G33", 331: "rigid tapping G33.1", 760: "threading cycle G76",
    382: "probing G38.2", 383: "probing G38.3", 384: "probing G38.4", 385: "probing G38.5",
    50: "spline G5", 51: "spline G5.1", 52: "NURBS G5.2",
    520: "local coordinate offset G52 (later positions read without it)",
    171: "plane G17.1", 181: "plane G18.1", 191: "plane G19.1",
}
_MOTION_G = (0, 10, 20, 30, 730, 740, 810, 820, 830, 840, 850, 860, 870, 880, 890)
_CYCLE_G = frozenset(_MOTION_G[4:])
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

    def __len__(self) -> int:
        return int(self.motion.shape[0])

    @property
    def line_no(self) -> np.ndarray:
        """(M,) int32, 1-based source line of each row."""
        return self.line_index + 1 if self.source_line is None else self.source_line[self.line_index]

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
        # One pass of regular expressions over the program's code (its comments cut out), not one per line.
        # In blocks of lines (a word never spans a line), so that the byte-wise pass stays small in memory.
        decimals: dict = {}
        trailing_point = False
        leading_zero = None  # judged on the first number below 1
        for i in range(0, len(self.lines), _STYLE_BLOCK_LINES):
            code = _COMMENT_TO_EOL.sub("", "".join(self.lines[i : i + _STYLE_BLOCK_LINES]))
            block_decimals, block_point = _number_style(code)
            for letter, n in block_decimals.items():
                decimals[letter] = max(n, decimals.get(letter, -1))
            trailing_point |= block_point
            if leading_zero is None and (m := _LEADING_ZERO.search(code)):
                leading_zero = m.group(1) == "0"
        leading_zero = True if leading_zero is None else leading_zero
        separator = ""
        for i in self.line_index[:50]:
            if re.search(r"[0-9.][ \t]+[A-Za-z]", self.lines[int(i)].split("(", 1)[0]):
                separator = " "
                break
        return FormatInfo(decimals, leading_zero, trailing_point, separator)


_STYLE_BLOCK_LINES = 50_000


def _number_style(code: str) -> tuple[dict, bool]:
    """Over every word ``letter [sign] digits . digits`` of ``code`` (what ``_DECIMALS`` matches): the most digits
    after the point per letter (upper case), and whether a length or feed word is written with a bare trailing point.

    Vectorised over the text's bytes, one pass per character class (a million-line program has millions of numbers;
    a regex match per number costs more than the whole post of its block)."""
    b = np.frombuffer(code.encode("latin-1", "replace"), np.uint8)
    digit = (b >= 48) & (b <= 57)
    dots = np.nonzero(b == 46)[0]
    if dots.size == 0:
        return {}, False
    other = np.nonzero(~digit)[0]  # includes every dot
    # digits after the point: up to the next non-digit
    k = np.searchsorted(other, dots, side="right")
    frac = np.where(k < other.size, other[np.minimum(k, other.size - 1)], b.size) - dots - 1
    # before the point: digits, then an optional sign, then spaces or tabs, then the letter
    before = np.searchsorted(other, dots, side="left") - 1  # the last non-digit before the point
    pos = np.where(before >= 0, other[np.maximum(before, 0)], -1)
    signed = (pos >= 0) & np.isin(b[np.maximum(pos, 0)], (43, 45))
    pos = np.where(signed, pos - 1, pos)
    blank = (b == 32) | (b == 9)
    nonblank = np.nonzero(~blank)[0]
    j = np.searchsorted(nonblank, pos, side="right") - 1  # last non-blank at or before pos
    ok = (pos >= 0) & (j >= 0)
    pos = np.where(ok, nonblank[np.maximum(j, 0)], -1)
    letter_b = np.where(ok, b[np.maximum(pos, 0)], 0)
    upper = np.where((letter_b >= 97) & (letter_b <= 122), letter_b - 32, letter_b)
    ok &= (upper >= 65) & (upper <= 90)
    decimals: dict = {}
    for code_point in np.unique(upper[ok]).tolist():
        decimals[chr(code_point)] = int(frac[ok & (upper == code_point)].max())
    bare = ok & (frac == 0) & np.isin(upper, np.frombuffer(b"XYZABCF", np.uint8))
    return decimals, bool(bare.any())


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

    return read_flat(text, source, passthrough_unsupported, split_lines, lambda t: _Interpreter(
        t, source, passthrough_unsupported, tool_table, reference_points, setup, require_setup).run())


class _Interpreter(ArcConversion, CycleConversion):
    """One lean pass over the lines; state in current program units like LinuxCNC's interpreter. Arcs
    (``interp_arc``) and canned cycles (``interp_cycles``) are its parts in their own modules."""

    def __init__(self, text, source, passthrough, tool_table, reference_points, setup=None, require_setup=False):
        self.text = text
        self.source = source
        self.passthrough = passthrough
        self.setup = setup
        self.require_setup = require_setup
        self.offsets_zero = bool(setup is not None and setup.offsets_zero)
        # tool number -> (6,) offsets X Y Z A B C in mm / deg (Z: the length), and where each came from
        self.tool_off_mm: dict = {}
        self.tool_src: dict = {}
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
        for k, v in self.ref_mm.items():
            if v.shape != (6,):
                raise ValueError(f"reference point {k} must have 6 values (X Y Z A B C), got shape {v.shape}")
        self.warnings: list = []
        self.unsupported: list = []
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
        lines = split_lines(self.text)
        # state, in current program units (lengths) and degrees
        inch = False
        self.inch = False
        u_scale = np.array([1.0, 1, 1, 1, 1, 1])  # mm per program unit, per axis
        g5x = np.zeros((10, 6))  # index 1..9: G54..G59.3
        rot = [0.0] * 10  # XY rotation of each work system, deg (LinuxCNC's R, parameter 5230 + 20 (k - 1))
        active = 1
        g92 = np.zeros(6)
        tlo = np.zeros(6)
        # What is known of the control's setup, and where each value came from. A value's "version" changes when the
        # program changes it, so that the rows' states can name the value they used (setup_used).
        setup = self.setup
        zero_ok = self.offsets_zero
        g5x_known = np.full((10, 6), zero_ok)
        g5x_src = ["--offsets-zero" if zero_ok else "not given"] * 10
        g5x_ver = [0] * 10
        hist = {}  # ("g5x", index, version) / ("g92", version) / ("tlo", version) -> record for setup_used
        g92_reason = ""
        g92_ver = [0]
        tlo_ver = [0]
        tlo_reason = ""
        tlo_h = -1  # the tool whose offsets are in force (-1 none, -2 G43.1 given in the program)
        selects_work = False
        g92_stored = None  # (values mm, source) of the shift G92.3 restores; None: unknown
        if setup is not None and setup.g92_stored is not None:
            g92_stored = (np.asarray(setup.g92_stored.values, float), setup.g92_stored.source)
        elif zero_ok:
            g92_stored = (np.zeros(6), "--offsets-zero")
        tool_change_mode = setup is not None and setup.tool_length == "tool_change"
        if setup is not None:
            for k, off in setup.work_offsets.items():
                g5x[k] = off.values
                rot[k] = float(off.rotation_deg)
                g5x_known[k] = True
                g5x_src[k] = off.source
            if setup.active is not None:
                active = int(setup.active)
            if setup.g92 is not None:
                g92[:] = setup.g92.values
        hist[("g92", 0)] = {"values": g92.copy(), "source": setup.g92.source if setup is not None and
                            setup.g92 is not None else "none at program start"}
        hist[("tlo", 0)] = {"tool": -1, "values": np.zeros(6), "source": ""}
        for k in range(1, 10):
            hist[("g5x", k, 0)] = {"values": g5x[k].copy(), "rotation": rot[k], "source": g5x_src[k],
                                   "known": g5x_known[k].copy()}
        arc_tol = 0.05  # arc end point off the circle by more than this (and 0.1 %): refused, like LinuxCNC
        pos = [0.0] * 6  # program coordinates (a list: numpy is slow for 6 numbers at a time)
        off_now = [[0.0] * 6]  # G5x + G92 + tool length offset, refreshed after every block that can change it
        motion_mode = 0  # G code *10 of the modal motion (0, 10, 20, 30, 730, 810..890, 800)
        plane = 17
        absolute = True
        arc_abs = False
        inverse = False
        diameter = False  # G7 (lathe diameter mode: X words are diameters, halved as LinuxCNC does; I is not)
        feed = 0.0
        retract_r = False  # G99
        cutter = 40
        tool = 0
        next_tool = 0
        cycle = {"r": 0.0, "cc": 0.0, "p": 0.0, "q": 0.0, "i": 0.0, "j": 0.0, "k": 0.0, "il": 0.0, "il_flag": False}
        refs = {k: v.copy() for k, v in self.ref_mm.items()}  # machine coords, mm (converted on use)
        used_axes = set()
        units_seen = set()
        percent_seen = 0

        # row accumulators (flat lists; converted to arrays at the end)
        # Row accumulators: flat lists, turned into arrays once at the end. What rarely changes between rows
        # (feed, modes, tool, offsets) is stored once per distinct state and indexed per row.
        # start / end points as packed doubles (8 bytes a number, not a float object each: a million-block program)
        r_start, r_end = array("d"), array("d")
        # and the per-row integers packed too (no list of a million references for every full garbage collection
        # to walk)
        r_line, r_motion, r_kind, r_words, r_state = array("q"), array("q"), array("q"), array("q"), array("q")
        r_arc = {}  # row -> (centre (3,), plane, turns)
        states: dict = {}
        cur_state = [0]

        def offsets():
            """G5x + G92 + tool offsets, the G92 shift turned by the system's rotation: machine = R p + offsets."""
            r = rot[active]
            if r == 0.0:
                return g5x[active] + g92 + tlo
            c, s = math.cos(math.radians(r)), math.sin(math.radians(r))
            g = g92.copy()
            g[0], g[1] = c * g92[0] - s * g92[1], s * g92[0] + c * g92[1]
            return g5x[active] + g + tlo

        def machine_of(p):
            """Machine position (current units) of program position p: R (p + G92) + G5x + tool offset."""
            u = [p[i] + g92[i] for i in range(6)]
            r = rot[active]
            if r != 0.0:
                c, s = math.cos(math.radians(r)), math.sin(math.radians(r))
                u[0], u[1] = c * u[0] - s * u[1], s * u[0] + c * u[1]
            return [u[i] + g5x[active, i] + tlo[i] for i in range(6)]

        def program_of(m):
            """The inverse of machine_of."""
            u = [m[i] - g5x[active, i] - tlo[i] for i in range(6)]
            r = rot[active]
            if r != 0.0:
                c, s = math.cos(math.radians(r)), math.sin(math.radians(r))
                u[0], u[1] = c * u[0] + s * u[1], -s * u[0] + c * u[1]
            return [u[i] - g92[i] for i in range(6)]

        def meta():
            """The setup in force, for the rows' states: rotation, system and the versions of the values used, and
            what is unknown (work axes not given, G92 / tool length reasons)."""
            unknown = "".join(AXES[i] for i in range(6) if not g5x_known[active, i])
            return (rot[active], active, g5x_ver[active], g92_ver[0], tlo_ver[0], unknown, g92_reason, tlo_reason)

        meta_now = [meta()]

        def refresh_state():
            key = (feed, inverse, inch, cutter, tool, not absolute, not arc_abs, tuple(off_now[0]), meta_now[0],
                   diameter)
            cur_state[0] = states.setdefault(key, len(states))

        if setup is not None:
            off_now[0] = offsets().tolist()
            refresh_state()

        def emit(motion, kind, target, li, words=0, center=None, pl=0, turns=0):
            if center is not None:
                r_arc[len(r_line)] = (center, pl, turns)
            r_start.extend(pos)
            r_end.extend(target)
            r_line.append(li)
            r_motion.append(motion)
            r_kind.append(kind)
            r_words.append(words)
            r_state.append(cur_state[0])
            pos[:] = target

        fast_match = _FAST.match
        word_bit = _WORD_BIT
        pre_cycle_mode = 0
        token_findall = _TOKEN.findall
        axis_index = _AXIS_INDEX
        ended = False
        nan = math.nan

        # The compiled pre-scan (fast_read): which lines are plain blocks, their G digit and values, read exactly as
        # the regular expression and float() read them; FAST_READ_BLOCK lines at a time.
        pre = None
        if FAST_READ and lines:
            from . import fast_read

            from . import fast_interp  # runs of plain straight moves read in compiled code

            pre = fast_read.scan_text(self.text)
            if pre is not None and len(pre[0]) != len(lines) + 1:
                pre = None  # not split as split_lines splits (cannot happen for ASCII text): no pre-scan
        blk_lo = blk_hi = 0
        blk_code = blk_vals = None
        n_lines = len(lines)

        skip_to = 0  # lines before it were read by fast_interp
        for li, raw in enumerate(lines):
            if li < skip_to:
                continue
            if ended:
                break
            # Fast path: a plain G0/G1 block ("N300G1X4.6526Z-.0007", "X1 Y2 F300") in G0/G1 mode.
            if pre is not None:
                if li >= blk_hi:
                    blk_lo, blk_hi = li, min(n_lines, li + FAST_READ_BLOCK)
                    b_status, b_g, b_vals = fast_read.scan_lines(pre[1], pre[0], blk_lo, blk_hi)
                    # code: the G digit (-1: none) for a block read here, 4: by the regex, 5: not a fast block
                    blk_code = np.where(b_status == fast_read.LINE_FAST, b_g,
                                        np.where(b_status == fast_read.LINE_SLOW, 4, 5)).tolist()
                    # one flat list of floats (no list per line: fewer objects for the garbage collector)
                    blk_vals = b_vals.ravel().tolist()
                    blk_run = (fast_interp.run_lengths(b_status, b_g, b_vals).tolist() if fast_interp.ENABLED
                               else [0] * len(blk_code))
                g = blk_code[li - blk_lo]
                if g < 4 and blk_run[li - blk_lo] >= fast_interp.MIN_RUN:
                    run = fast_interp.straight_run(b_status, b_g, b_vals, li - blk_lo, np.array(pos, float),
                                                   motion_mode, feed, absolute, inverse, diameter, plane, arc_abs,
                                                   arc_tol)
                    if run[0]:
                        state0, changed = cur_state[0], []
                        for c in fast_interp.feed_changes(run[5], feed):  # the states, where the feed changes
                            feed = float(run[5][c])
                            refresh_state()
                            changed.append((c, cur_state[0]))
                        pos, motion_mode = fast_interp.append_rows(run, li, state0, changed, r_start, r_end, r_line,
                                                                   r_motion, r_kind, r_words, r_state, ROW_PROGRAMMED,
                                                                   r_arc, plane)
                        if run[6]:
                            cycle["il_flag"] = False
                        skip_to = li + run[0]
                        continue
                if g < 4:
                    fast = True
                    o = (li - blk_lo) * 11
                    x, y, z, a_, b_, c_, i_, j_, k_, r_, f_ = blk_vals[o:o + 11]
                else:
                    fast = False
                    if g == 4:  # a number with more digits than the pre-scan reads exactly: the regex path
                        fast = None
            else:
                fast = None
            if fast is None:
                fm = fast_match(raw)
                if fm is not None:
                    g, x, y, z, a_, b_, c_, i_, j_, k_, r_, f_ = fm.groups()
                    if g is None and x is None and y is None and z is None and a_ is None and b_ is None \
                            and c_ is None:
                        fast = False  # no motion word and no axis word: not a move (general path)
                    else:
                        fast = True
                        g = -1 if g is None else int(g)
                        x = nan if x is None else float(x)
                        y = nan if y is None else float(y)
                        z = nan if z is None else float(z)
                        a_ = nan if a_ is None else float(a_)
                        b_ = nan if b_ is None else float(b_)
                        c_ = nan if c_ is None else float(c_)
                        i_ = nan if i_ is None else float(i_)
                        j_ = nan if j_ is None else float(j_)
                        k_ = nan if k_ is None else float(k_)
                        r_ = nan if r_ is None else float(r_)
                        f_ = nan if f_ is None else float(f_)
                else:
                    fast = False
            if diameter and fast and x == x:
                x = 0.5 * x  # G7: the X word is a diameter
            # (values: NaN where the block has no such word; g: -1 where it has no G word)
            if fast:
                mode = motion_mode if g < 0 else g * 10
                if f_ == f_:
                    new_feed = f_
                    if new_feed < 0.0:
                        raise self.err(li + 1, f"negative feed rate F{fast_match(raw).group(12)}")
                    if new_feed != feed:
                        feed = new_feed
                        refresh_state()
                if mode == 0 or (mode <= 30 and feed != 0.0 and (f_ == f_ or not inverse)):
                    target = pos[:]
                    seen = 0
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
                        if x == x:
                            target[0] += x
                            seen = 1
                        if y == y:
                            target[1] += y
                            seen |= 2
                        if z == z:
                            target[2] += z
                            seen |= 4
                    if a_ == a_ or b_ == b_ or c_ == c_:
                        for n, v in ((3, a_), (4, b_), (5, c_)):
                            if v == v:
                                target[n] = v if absolute else target[n] + v
                                seen |= 1 << n
                    if f_ == f_:
                        seen |= 2048
                    arcw = i_ == i_ or j_ == j_ or k_ == k_ or r_ == r_
                    if g >= 0:
                        cycle["il_flag"] = False
                    if mode <= 10 and not arcw:
                        motion_mode = mode
                        # emit(), inlined: this line is the hot path
                        r_start.fromlist(pos)
                        r_end.fromlist(target)
                        r_line.append(li)
                        r_motion.append(mode // 10)
                        r_kind.append(ROW_PROGRAMMED)
                        r_words.append(seen)
                        r_state.append(cur_state[0])
                        pos = target
                        continue
                    if mode >= 20 and r_ != r_:
                        # I J K arc, inlined (the other hot path); R arcs and odd cases go through arc_to
                        a0, a1, an = _PLANE_AXES[plane]
                        ijk = (i_, j_, k_)
                        w0, w1 = ijk[a0], ijk[a1]
                        if w0 == w0 or w1 == w1:
                            o0 = w0 if w0 == w0 else 0.0
                            o1 = w1 if w1 == w1 else 0.0
                            if arc_abs:
                                c0, c1 = o0, o1
                            else:
                                c0, c1 = pos[a0] + o0, pos[a1] + o1
                            rad1 = math.hypot(pos[a0] - c0, pos[a1] - c1)
                            rad2 = math.hypot(target[a0] - c0, target[a1] - c1)
                            dr = abs(rad1 - rad2)
                            if rad1 > 0.0 and (dr <= arc_tol or dr <= 0.001 * max(rad1, rad2)):
                                for letter, v in (("I", i_), ("J", j_), ("K", k_)):
                                    if v == v:
                                        seen |= word_bit[letter]
                                center = [0.0, 0.0, 0.0]
                                center[a0], center[a1], center[an] = c0, c1, pos[an]
                                motion_mode = mode
                                r_arc[len(r_line)] = (center, plane, 1)
                                r_start.fromlist(pos)
                                r_end.fromlist(target)
                                r_line.append(li)
                                r_motion.append(2 if mode == 20 else 3)
                                r_kind.append(ROW_PROGRAMMED)
                                r_words.append(seen)
                                r_state.append(cur_state[0])
                                pos = target
                                continue
                    if mode >= 20:
                        motion_mode = mode
                        extra = {}
                        for letter, v in (("I", i_), ("J", j_), ("K", k_), ("R", r_)):
                            if v == v:
                                extra[letter] = v
                                seen |= word_bit[letter]
                        try:
                            self.arc_to(li + 1, li, mode, extra, target, pos, plane, arc_abs, inch, emit, seen)
                        except ValueError as exc:
                            raise self.err(li + 1, str(exc)) from None
                        continue
                # anything else: the general path below handles (or reports) it
            line_no = li + 1
            stripped = raw.strip()
            if not stripped:
                continue
            if stripped[0] == "%":
                percent_seen += 1
                if percent_seen >= 2:
                    ended = True
                continue
            if (stripped[0] in "oO" or stripped[:1] in "nN") and _OWORD.match(raw):
                if self.passthrough:
                    self.unsupported_block(line_no, "o-word subroutine / control flow")
                    continue
                raise self.err(line_no, "o-word subroutine / control flow is not supported (the moves it makes "
                               "are not in the text)")
            if "#" in raw:
                m = _ASSIGN.match(raw.rstrip("\r\n"))
                if m:
                    self.params[int(m.group(1))] = float(m.group(2))
                    continue
            gcodes, mcodes, vals, refuse, macro_nonmoving = read_block(self, raw, line_no, token_findall)
            if not gcodes and not mcodes and not vals:
                if macro_nonmoving:
                    self.unsupported_block(line_no, macro_nonmoving)
                continue

            try:
                gnums = []
                for g in gcodes:
                    gnums.append(int(round(float(g) * 10)))
                mnums = [int(round(float(m))) for m in mcodes]
                if refuse is None:
                    for g in gnums:
                        if g in _MOVING_G:
                            refuse = _MOVING_G[g]
                    for m in mnums:
                        if m in _MOVING_M:
                            refuse = _MOVING_M[m]
                    if refuse is None and any(k in vals for k in "UVW"):
                        refuse = "U V W axes are not supported"
                if refuse is not None:
                    if self.passthrough:
                        self.unsupported_block(line_no, refuse)
                        continue
                    raise self.err(line_no, refuse + " (the moves it makes are not in the text; "
                                   "--passthrough-unsupported leaves the block as it is)")
                if macro_nonmoving:
                    self.unsupported_block(line_no, macro_nonmoving)

                fvals = {}
                for k, v in vals.items():
                    fv = float(v)
                    if not abs(fv) < MAX_WORD_VALUE and k not in "NO":
                        raise self.err(line_no, f"number out of range: {k}{v[:20]}{'...' if len(v) > 20 else ''} "
                                       f"(the reader takes values below {MAX_WORD_VALUE:.0e})")
                    fvals[k] = fv
                if fvals.get("F", 0.0) < 0.0:
                    raise self.err(line_no, f"negative feed rate F{vals['F']}")
                if "T" in fvals and not 0 <= fvals["T"] <= 2**31 - 1:
                    raise self.err(line_no, f"tool number T{fvals['T']:g} out of range (0 .. 2147483647)")
                words_mask = 0
                for k in vals:
                    words_mask |= _WORD_BIT.get(k, 0)
                if 70 in gnums or (80 in gnums and "P" not in fvals):
                    diameter = 70 in gnums  # G7 / G8 (LinuxCNC's lathe modes), in force for this block's words
                ax = [(axis_index[k], 0.5 * fvals[k] if diameter and k == "X" else fvals[k])
                      for k in "XYZABC" if k in fvals]
                for k in "XYZABC":
                    if k in fvals:
                        used_axes.add(k)

                # -- modal and non-modal G codes, in LinuxCNC's order of execution ---------------------------
                new_motion = None
                nonmodal = None
                meta_changed = False
                g53 = False
                for g in gnums:
                    if g in _MOTION_G:
                        new_motion = g
                    elif g == 800:
                        if new_motion is None:
                            new_motion = 800
                    elif g == 930:
                        inverse = True
                    elif g in (940, 950):
                        if g == 950:
                            self.warn(line_no, "G95 feed per revolution: feed values are per revolution")
                        inverse = False
                    elif g in (170, 180, 190):
                        plane = g // 10
                    elif g in (200, 210):
                        want_inch = g == 200
                        units_seen.add("inch" if want_inch else "mm")
                        if want_inch != inch:
                            f = (1 / MM_PER_INCH) if want_inch else MM_PER_INCH
                            lin = _LINEAR
                            for arr in (g92, tlo):
                                arr[lin] *= f
                            pos[:] = [p * f if lin_i else p for p, lin_i in zip(pos, _LINEAR_T)]
                            g5x[:, lin] *= f
                            cycle["r"] *= f
                            cycle["cc"] *= f
                            cycle["q"] *= f
                            cycle["il"] *= f
                            for key in "ijk":
                                cycle[key] *= f
                            feed *= f if not inverse else 1.0
                            inch = want_inch
                            arc_tol = 0.002 if inch else 0.05
                            u_scale = np.where(_LINEAR, MM_PER_INCH if inch else 1.0, 1.0)
                    elif g in (400, 410, 420, 411, 421):
                        cutter = g // 10
                        if cutter != 40:
                            self.warn(line_no, f"G{cutter} cutter radius compensation: rows follow the programmed "
                                      "contour, not the tool centre")
                    elif g in (430, 431, 432, 490):
                        pass  # handled after the tool change below
                    elif (540 <= g <= 590 and g % 10 == 0) or g in (591, 592, 593):
                        new_active = (g - 530) // 10 if g % 10 == 0 else 7 + (g - 591)
                        selects_work = meta_changed = True
                        if new_active != active:
                            if rot[active] == 0.0 and rot[new_active] == 0.0:
                                _add(pos, g5x[active] - g5x[new_active])
                                active = new_active
                            else:  # the machine position stays; the program position follows the rotation
                                m_pos = machine_of(pos)
                                active = new_active
                                pos[:] = program_of(m_pos)
                    elif g == 900:
                        absolute = True
                    elif g == 910:
                        absolute = False
                    elif g == 901:
                        arc_abs = True
                    elif g == 911:
                        arc_abs = False
                    elif g == 980:
                        retract_r = False
                    elif g == 990:
                        retract_r = True
                    elif g in (40, 100, 280, 281, 300, 301, 920, 921, 922, 923):
                        nonmodal = g
                    elif g == 530:
                        g53 = True
                    elif g == 70:
                        pass  # G7, lathe diameter mode: taken before the axis words (above)
                    elif g in (610, 611, 640, 960, 970):
                        pass  # path control and spindle modes: no effect on positions
                    elif g == 80:
                        if "P" in vals:
                            self.unsupported_block(line_no, "Fanuc G08 P (look-ahead) is not an RS-274 code")
                        # else LinuxCNC's G8 (lathe radius mode), the default: nothing to do
                    else:
                        self.not_understood(line_no, "G43.4 / G43.5 tool centre point control: the post reads and "
                                            "writes machine-axis (joint) positions, not tool-tip positions"
                                            if g in (434, 435) else f"G{g / 10:g} not understood")

                # feed, spindle, tool
                if "F" in fvals:
                    feed = fvals["F"]
                if "T" in fvals:
                    next_tool = int(fvals["T"])
                for m in mnums:
                    if m == 6:
                        tool = next_tool
                        if tool_change_mode:
                            # the control applies the new tool's length at the change (Hurco, some Fanuc setups)
                            new, tlo_h, tlo_reason = self.tool_offsets(tool, u_scale, zero_ok, line_no, "M6")
                            m_pos = machine_of(pos)
                            tlo = new
                            pos[:] = program_of(m_pos)
                            tlo_ver[0] += 1
                            meta_changed = True
                            hist[("tlo", tlo_ver[0])] = {"tool": tool, "values": new * u_scale,
                                                         "source": self.tool_source(tool, zero_ok), "how": "M6"}
                    elif m in (2, 30):
                        ended = True
                    elif m not in _KNOWN_M and not (100 <= m <= 199):
                        self.not_understood(line_no, f"M{m} is not an RS-274 code")
                # tool length offset
                for g in gnums:
                    if g not in (430, 431, 432, 490):
                        continue
                    if g == 430:
                        h = int(fvals["H"]) if "H" in fvals else tool
                        new, tlo_h, tlo_reason = self.tool_offsets(h, u_scale, zero_ok, line_no, f"G43 H{h}")
                        rec = {"tool": h, "source": self.tool_source(h, zero_ok), "how": f"G43 H{h}"}
                    elif g == 431:
                        new = tlo.copy()
                        for i, v in ax:
                            new[i] = v
                        ax = []
                        tlo_h, tlo_reason = -2, ""
                        rec = {"tool": -2, "source": f"{self.source}:{line_no} (G43.1)", "how": "G43.1"}
                    elif g == 432:
                        h = int(fvals.get("H", 0))
                        add, _, reason = self.tool_offsets(h, u_scale, zero_ok, line_no, f"G43.2 H{h}")
                        new = tlo + add
                        tlo_reason = tlo_reason or reason
                        rec = {"tool": h, "source": self.tool_source(h, zero_ok), "how": f"G43.2 H{h} (added)"}
                    else:
                        new = np.zeros(6)
                        tlo_h, tlo_reason = -1, ""
                        rec = {"tool": -1, "source": "", "how": "G49"}
                    if rot[active] == 0.0:
                        _add(pos, tlo - new)
                        tlo = new
                    else:
                        m_pos = machine_of(pos)
                        tlo = new
                        pos[:] = program_of(m_pos)
                    tlo_ver[0] += 1
                    meta_changed = True
                    rec["values"] = tlo * u_scale
                    hist[("tlo", tlo_ver[0])] = rec

                if new_motion is not None:
                    if new_motion in (0, 10, 20, 30, 800):
                        cycle["il_flag"] = False
                    motion_here = new_motion
                else:
                    motion_here = None

                if gnums or mnums or "F" in fvals:
                    off_now[0] = offsets().tolist()
                    if meta_changed:
                        meta_now[0] = meta()
                    refresh_state()
                # -- non-modal: G10, G28, G30, G92, G4 -------------------------------------------------------
                if nonmodal == 100:
                    # the active system may change: the machine position stays, the program position moves
                    changed = self.g10(line_no, fvals, ax, g5x, rot, active, g92, tlo, pos, u_scale, machine_of,
                                       program_of)
                    if changed is not None:
                        idx, letters = changed
                        for i in letters:
                            g5x_known[idx, i] = True
                        g5x_src[idx] = f"{self.source}:{line_no} (G10 L{int(fvals.get('L', -1))})"
                        g5x_ver[idx] += 1
                        hist[("g5x", idx, g5x_ver[idx])] = {"values": g5x[idx] * u_scale, "rotation": rot[idx],
                                                            "source": g5x_src[idx], "known": g5x_known[idx].copy()}
                    ax = []
                elif nonmodal in (280, 300):
                    key = "G28" if nonmodal == 280 else "G30"
                    if ax:
                        target = list(pos)
                        for i, v in ax:
                            target[i] = v if absolute else pos[i] + v
                        emit(RAPID, ROW_REFERENCE, target, li, words_mask)
                        moving = [i for i, _ in ax]
                    else:
                        moving = list(range(6))
                    if rot[active] == 0.0:
                        home = refs[key] / u_scale - offsets()
                        target = list(pos)
                        for i in moving:
                            target[i] = float(home[i])
                    else:  # as LinuxCNC: the home point in program coordinates, its named axes taken
                        home = program_of([float(refs[key][i] / u_scale[i]) for i in range(6)])
                        target = list(pos)
                        for i in moving:
                            target[i] = home[i]
                    emit(RAPID, ROW_REFERENCE, target, li, 0)
                    ax = []
                elif nonmodal in (281, 301):
                    refs["G28" if nonmodal == 281 else "G30"] = np.array(machine_of(pos)) * u_scale
                elif nonmodal in (920, 921, 922, 923):
                    old_g92 = g92.copy()
                    if nonmodal == 920:
                        for i, v in ax:
                            g92[i] = pos[i] + g92[i] - v
                        ax = []
                        g92_stored = (g92 * u_scale, f"{self.source}:{line_no} (G92)")
                        src, g92_reason = g92_stored[1], ""
                    elif nonmodal in (921, 922):
                        g92[:] = 0.0
                        src, g92_reason = f"{self.source}:{line_no} (G92.{nonmodal - 920})", ""
                        if nonmodal == 921:
                            g92_stored = (np.zeros(6), src)
                    elif g92_stored is not None:
                        g92[:] = g92_stored[0] / u_scale
                        src, g92_reason = f"{g92_stored[1]}, restored by G92.3 at line {line_no}", ""
                    else:
                        g92[:] = 0.0
                        src = "--offsets-zero" if zero_ok else "not given"
                        g92_reason = "" if zero_ok else \
                            "the G92 shift that G92.3 restores (stored in the control) was not given"
                    # the machine position stays: the program position moves by the change (G92 is applied before
                    # the system's rotation, so the same formula holds in a rotated system)
                    _add(pos, old_g92 - g92)
                    g92_ver[0] += 1
                    hist[("g92", g92_ver[0])] = {"values": g92 * u_scale, "source": src}

                if ended and not ax and motion_here is None:
                    break

                # -- motion ---------------------------------------------------------------------------------
                if nonmodal is not None:
                    off_now[0] = offsets().tolist()
                    meta_now[0] = meta()
                    refresh_state()
                prior_mode = motion_mode
                if motion_here is not None:
                    motion_mode = motion_here
                if motion_here is None and not ax:
                    continue
                mm = motion_mode
                if motion_here in _CYCLE_G and prior_mode not in _CYCLE_G:
                    pre_cycle_mode = prior_mode
                if mm == 800:
                    if not ax:
                        continue
                    if pre_cycle_mode not in (0, 10, 20, 30):
                        raise self.err(line_no, "axis words with G80 and no motion mode to fall back to")
                    # Fanuc: G80 ends the cycle and the G0/G1 modal from before the cycle moves on (LinuxCNC
                    # refuses axis words here; a program LinuxCNC accepts never reaches this line)
                    self.warn(line_no, f"axis words after G80: moved with G{pre_cycle_mode // 10}, the motion "
                              "mode before the canned cycle (Fanuc behaviour; LinuxCNC refuses this)")
                    mm = motion_mode = pre_cycle_mode
                if g53:
                    if mm not in (0, 10):
                        raise self.err(line_no, "G53 needs G0 or G1")
                    if not absolute:
                        raise self.err(line_no, "G53 in incremental mode (G91)")
                    if rot[active] == 0.0:
                        target = list(pos)
                        off = offsets()
                        for i, v in ax:
                            target[i] = v - off[i]
                    else:
                        m_pos = machine_of(pos)
                        for i, v in ax:
                            m_pos[i] = v
                        target = program_of(m_pos)
                    if mm == 10 and feed == 0.0:
                        raise self.err(line_no, "G1 with zero feed rate (no F word yet)")
                    emit(RAPID if mm == 0 else FEED, ROW_MACHINE, target, li, words_mask)
                    if ended:
                        break
                    continue
                if mm in (0, 10):
                    target = list(pos)
                    if absolute:
                        for i, v in ax:
                            target[i] = v
                    else:
                        for i, v in ax:
                            target[i] += v
                    if mm == 10:
                        if inverse and "F" not in fvals:
                            raise self.err(line_no, "G93 inverse-time feed needs an F word on every feed block")
                        if feed == 0.0:
                            raise self.err(line_no, "G1 with zero feed rate (no F word yet)")
                    emit(RAPID if mm == 0 else FEED, ROW_PROGRAMMED, target, li, words_mask)
                elif mm in (20, 30):
                    self.arc(line_no, li, mm, fvals, ax, pos, plane, absolute, arc_abs, inch, feed, inverse,
                             emit, words_mask)
                else:
                    if inverse:
                        raise self.err(line_no, "canned cycle in G93 inverse-time mode")
                    if feed == 0.0:
                        raise self.err(line_no, "canned cycle with zero feed rate (no F word yet)")
                    if cutter != 40:
                        raise self.err(line_no, "canned cycle with cutter radius compensation on")
                    self.cycle(line_no, li, mm, motion_here, fvals, ax, pos, plane, absolute, retract_r, inch,
                               cycle, emit, words_mask, prior_mode)
                if ended:
                    break
            except GcodeError:
                raise
            except (ValueError, OverflowError, ZeroDivisionError, KeyError) as exc:
                raise self.err(line_no, str(exc) or type(exc).__name__) from None

        m = len(r_line)
        state_rows = list(states)  # dicts keep insertion order: index == state id
        sid = np.array(r_state, np.int64)
        st_feed = np.array([k[0] for k in state_rows] or [0.0], float)
        st_flags = np.array([k[1:7] for k in state_rows] or [(False, False, 40, 0, False, True)],
                            np.int64).reshape(-1, 6)
        st_off = np.array([k[7] for k in state_rows] or [(0.0,) * 6], float).reshape(-1, 6)
        st_diameter = np.array([k[9] for k in state_rows] or [False], bool)
        # the setup in force per state: few distinct ones (states differ mostly by feed, e.g. under G93)
        meta_index: dict = {}
        meta_of_state = np.array([meta_index.setdefault(k[8], len(meta_index)) for k in state_rows]
                                 or [meta_index.setdefault(meta_now[0], 0)], np.int64)
        metas = list(meta_index)
        mid = meta_of_state[sid]
        rotation = np.array([mt[0] for mt in metas], float)[mid].reshape(m)
        setup_used = self.setup_report(mid, np.array(r_kind, np.int64), np.array(r_line, np.int64), metas, hist,
                                       selects_work, used_axes)
        arc_center = np.full((m, 3), np.nan)
        arc_plane = np.zeros(m, np.int8)
        arc_turns = np.zeros(m, np.int16)
        if r_arc:
            idx = np.fromiter(r_arc.keys(), np.int64, len(r_arc))
            arc_center[idx] = [v[0] for v in r_arc.values()]
            arc_plane[idx] = [v[1] for v in r_arc.values()]
            arc_turns[idx] = [v[2] for v in r_arc.values()]
        words = np.array(r_words, np.uint16)
        mask = int(np.bitwise_or.reduce(words)) if m else 0
        used_axes.update(c for c in AXES if mask & _WORD_BIT[c])
        units = "mixed" if len(units_seen) > 1 else ("inch" if units_seen == {"inch"} else "mm")
        start = np.array(r_start, float).reshape(m, 6)
        end = np.array(r_end, float).reshape(m, 6)
        offset = st_off[sid].reshape(m, 6)
        feed_rows = st_feed[sid].reshape(m)
        # Numbers too large for a float (a 400-digit X), or sums of huge ones, must not reach a writer as inf/NaN.
        finite = (np.isfinite(start).all(axis=1) & np.isfinite(end).all(axis=1) & np.isfinite(offset).all(axis=1)
                  & np.isfinite(feed_rows) & (np.isfinite(arc_center).all(axis=1) | (arc_plane == 0)))
        if not finite.all():
            bad = int(np.argmin(finite))
            raise self.err(int(r_line[bad]) + 1, "number out of range: a position, offset or feed is not finite")
        return Program(
            source=self.source,
            start=start,
            end=end,
            offset=offset,
            motion=np.array(r_motion, np.int8),
            kind=np.array(r_kind, np.int8),
            arc_center=arc_center,
            arc_plane=arc_plane,
            arc_turns=arc_turns,
            feed=feed_rows,
            inverse_time=st_flags[sid, 0].astype(bool).reshape(m),
            inch=st_flags[sid, 1].astype(bool).reshape(m),
            cutter_comp=st_flags[sid, 2].astype(np.int8).reshape(m),
            tool=st_flags[sid, 3].astype(np.int32).reshape(m),
            incremental=st_flags[sid, 4].astype(bool).reshape(m),
            arc_incremental=st_flags[sid, 5].astype(bool).reshape(m),
            diameter=st_diameter[sid].reshape(m),
            line_index=np.array(r_line, np.int32),
            words=words,
            lines=lines,
            units=units,
            axes_present="".join(a for a in AXES if a in used_axes),
            warnings=self.warnings,
            unsupported=self.unsupported,
            rotation=rotation,
            setup_used=setup_used,
        )

    def setup_report(self, sid, kind, line, st_meta, hist, selects_work, used_axes):
        # sid: (M,) index of each row's setup in st_meta
        """What the rows used of the control's setup (one entry per value, in the order of first use), and, under
        ``require_setup``, the refusal of the first move made under a value that was not given."""
        out, seen = [], set()
        if sid.size == 0:
            return out
        uniq, first = np.unique(sid, return_index=True)
        setup_given_active = self.setup is not None and self.setup.active is not None
        moving = (kind == ROW_PROGRAMMED) | (kind == ROW_CYCLE)
        checked = set(np.unique(sid[moving]).tolist())
        axes_used = "XYZ" + "".join(a for a in "ABC" if a in used_axes)
        for s_id, row in sorted(zip(uniq.tolist(), first.tolist()), key=lambda t: t[1]):
            r, active, g5x_ver, g92_ver, tlo_ver, unknown, g92_reason, tlo_reason = st_meta[s_id]
            line_no = int(line[row]) + 1
            if self.require_setup and s_id in checked:
                missing = "".join(a for a in unknown if a in axes_used)
                if missing and (selects_work or setup_given_active):
                    raise self.err(line_no, f"work offset {_SYSTEM_NAMES[active - 1]} ({' '.join(missing)}) was not "
                                   "given: give the control's setup (--var / --setup), or --offsets-zero if zero is "
                                   "meant")
                for reason in (g92_reason, tlo_reason):
                    if reason:
                        raise self.err(line_no, f"{reason}: give the control's setup (--tool-table / --var / "
                                       "--setup), or --offsets-zero if zero is meant")
            key = ("g5x", active, g5x_ver)
            if key not in seen:
                seen.add(key)
                rec = hist[key]
                entry = {"what": _SYSTEM_NAMES[active - 1], "values_mm_deg": [float(v) for v in rec["values"]],
                         "rotation_deg": float(rec["rotation"]), "source": rec["source"], "first_line": line_no}
                if not rec["known"][:3].all() and not (selects_work or setup_given_active):
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
        return out

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
