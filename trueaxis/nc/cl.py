"""CL data in, machine-axis G-code out (DESIGN §5): tool-tip points with tool-axis vectors in the part frame.

Two formats, told apart by content (:func:`cl_format`):

- **CSV**: the first line that is not blank and not a ``#`` comment is a header naming the columns; ``x y z i j k``
  are required, ``f`` (or ``feed``: mm/min) is optional, other columns are ignored. Separator ``,`` (or ``;``, or tabs
  and blanks when the header has neither). An empty ``f`` cell keeps the previous feed; ``f = 0`` marks a rapid (the
  convention of CL CSVs, and what ``trueaxis program --cl`` writes). The first point is reached with a rapid; every
  other row is a cutting move unless its feed is 0.
- **APT** (CL print style): ``GOTO/x,y,z,i,j,k`` (``GOTO/x,y,z`` keeps the previous tool axis, +Z at the start),
  ``FEDRAT/f`` (mm/min; ``FEDRAT/f,MMPM``, ``FEDRAT/MMPM,f``, ``IPM`` in inch/min), ``RAPID`` (the next GOTO is a rapid),
  ``FROM/x,y,z[,i,j,k]`` (a rapid to the start), ``UNITS/MM`` or ``UNITS/INCHES``, ``TLAXIS/i,j,k`` (the tool axis of
  the GOTOs that follow); ``$$`` starts a comment and a trailing ``$`` continues a statement on the next line.
  The program's setup is written as the control's words where it stands (:data:`APT_SETUP`): ``LOADTL/n[,ADJUST,h]``
  -> ``T n M6`` and ``G43 H n`` (or ``H h``), ``SPINDL/[RPM,]s[,CLW|CCLW]`` -> ``S s M3`` / ``M4``, ``SPINDL/OFF`` ->
  ``M5``, ``COOLNT/ON|FLOOD|MIST|OFF`` -> ``M8`` / ``M7`` / ``M9``, ``CUTTER/d`` -> the structured comment
  ``(trueaxis: d=...)`` the post's force model reads, ``GOHOME`` -> ``G28``, ``END`` -> a rapid retract of Z to 1 mm below the top of
  its travel, then spindle and coolant off, ``PARTNO`` / ``PPRINT`` -> comments. ``MULTAX``, ``FINI``, ``INTOL``,
  ``OUTTOL`` and ``TOLER`` change nothing. Any other statement is refused with ``file:line: reason``: a statement
  skipped silently could be a setup the machine then lacks.

Lengths in mm in the part frame (APT ``UNITS/INCHES`` is converted), tool axis from tip towards the spindle (it is
normalised). A point that repeats the one before (tip within 1 nm, tool axis within 1 nrad) is no move and is dropped.

One CL type, :class:`ClData`, for these files and for the test parts' programs (``trueaxis.postproc.programs``,
made with :meth:`ClData.of_passes`: a kind and a pass per point), and one path from CL to machine axes,
:func:`cl_axes` (pass by pass, each from where the one before ended), which :func:`cl_program` / :func:`cl_to_program`
and the part programs use. The poses become machine axes through the machine's inverse kinematics:

- **branch** (sign of the tilt axis): kept along the path and changed only where the other branch is the only one
  inside the travel; a change inside a cut is refused. The first branch is the one nearest ``previous`` or, without
  it, the one whose tilt stays farthest inside its travel (a B -120..+30 table tilts negative). The part programs
  ask for "first-fit" instead: per pass -1, or +1 where -1 leaves any axis' travel.
- **winding**: the outer (rotary-table) axis takes the shortest way from each pose to the next (``np.unwrap``); the
  whole path is shifted by whole turns to fit a limited travel, else refused. At a singular pose (tool axis along the
  outer axis) the outer axis stays where it was.
- **linearisation** (five-axis non-linearity): the control interpolates the axes linearly, so between two CL points
  the tool tip leaves the straight CL segment and the tool axis the great circle between the two vectors. Segments are
  split (the CL pose interpolated: tip linear, axis by slerp, then inverse kinematics) until the joint-linear path
  stays within ``tol_um`` of the segment and within ``tol_um`` urad of the interpolated axis.
- **feeds**: cutting moves are written in G93 inverse time, F = feed / (tool-tip path length in the part frame), so
  each piece of a split segment takes its share of the segment's time. A move with no tip motion (a pure
  reorientation) takes the time the tool's gauge point (tool length away from the tip) needs at the feed.

Output: ``%``, a comment, ``G21 G90 G17``, rapids as ``G94 G0``, cuts as ``G93 G1 ... F``, the setup statements'
blocks before the move that follows them, ``G94 M30 %``; 6 decimals.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..machine import Machine, forward_nominal, inverse_kinematics
from ..machine.kinematics import _rotary_pair, linear_axis_map
from .gcode import MM_PER_INCH, GcodeError

__all__ = ["ClData", "ClError", "RAPID_KINDS", "cl_format", "read_cl", "cl_axes", "travel_problem",
           "machine_linear_positions", "cl_to_program", "cl_program"]

_REQUIRED = ("x", "y", "z", "i", "j", "k")
_FEED_NAMES = ("f", "feed")
_GOTO = re.compile(r"^\s*GOTO\s*/", re.IGNORECASE)
_GOTO_LINE = re.compile(r"^[^\S\r\n]*GOTO\s*/", re.IGNORECASE | re.MULTILINE)  # _GOTO at any line start
_TEXT_LINE = re.compile(r"[^\r\n]+")
_APT_STATEMENT = re.compile(r"^\s*([A-Za-z][A-Za-z0-9_]*)\s*(?:/(.*))?$", re.DOTALL)
_MOVING_APT = {"GODLTA": "GODLTA (relative move)", "CIRCLE": "CIRCLE (arc)", "MOVARC": "MOVARC (arc)",
               "GOFWD": "GOFWD (drive-surface motion)", "GOLFT": "GOLFT (drive-surface motion)",
               "GORGT": "GORGT (drive-surface motion)", "GOBACK": "GOBACK (drive-surface motion)",
               "INDIRV": "INDIRV (drive-surface motion)", "CYCLE": "CYCLE (canned cycle)"}
_DIGITS = 6


class ClError(GcodeError):
    """Bad CL data: ``file:line: reason`` (a GcodeError, so the CLI reports it like any refused program; the post
    re-raises it as its PostError)."""


@dataclass(frozen=True)
class SetupBlock:
    """A block of the program's setup (tool change, spindle, coolant, ...) written before CL point ``before``
    (``before`` = number of points: after the last move). words: the G-code words; retract: a rapid of Z to the top
    of its travel (APT END), which needs the machine; line: the APT line it comes from."""

    before: int
    words: str
    line: int
    retract: bool = False


# The kinds of point of a part program's CL data (``ClData.kind``); approach and retract are rapids, lift goes up the
# tool axis at feed out of the cut.
RAPID_KINDS = ("approach", "retract")


@dataclass
class ClData:
    """CL poses, part frame: the one CL type, read from CAM files (``read_cl``) or made by the test parts' programs
    (``ClData.of_passes``, ``trueaxis.postproc.programs``).

    tip (N,3) mm; axis (N,3) unit vectors (tip towards the spindle); feed (N,) mm/min of the move *to* the point
    (NaN: none given yet, the last one holds; a part program's rapids carry 0); rapid (N,) bool, the move to this
    point is a rapid; line (N,) 1-based source line of each point (a part program's: the point's number); source,
    format ("csv", "apt", "passes"); setup: SetupBlock, in program order.
    kind (N,) str or None: what each point of a part program is (approach | plunge | lead_in | cut | lead_out | lift |
    retract). pass_no (N,) int or None: the pass of each point (None: one pass). passes: one dict per pass (name,
    offset_mm, conditions).
    """

    tip: np.ndarray
    axis: np.ndarray
    feed: np.ndarray
    rapid: np.ndarray
    line: np.ndarray
    source: str
    format: str
    setup: tuple = ()  # SetupBlock, in program order
    kind: np.ndarray | None = None
    pass_no: np.ndarray | None = None
    passes: list = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.tip.shape[0])

    @classmethod
    def of_passes(cls, tip, axis, feed, kind, pass_no, passes=None, source: str = "part program CL") -> "ClData":
        """A part program's CL data: points with their kinds and passes; rapids are the approach and retract points."""
        kind = np.asarray(kind)
        return cls(np.asarray(tip, float), np.asarray(axis, float), np.asarray(feed, float), np.isin(kind, RAPID_KINDS),
                   np.arange(1, len(kind) + 1), source, "passes", (), kind, np.asarray(pass_no, int),
                   list(passes or []))

    @classmethod
    def concatenate(cls, parts: list["ClData"], passes: list[dict]) -> "ClData":
        """Part programs' CL data one after the other (their kinds and passes), with the passes given."""
        return cls.of_passes(*(np.concatenate([getattr(c, f) for c in parts])
                               for f in ("tip", "axis", "feed", "kind", "pass_no")), passes=passes,
                             source=parts[0].source)

    def rows(self, sel) -> "ClData":
        """The points ``sel`` (indices or a mask), with their lines, kinds and passes; no setup blocks."""
        pick = (lambda a: None if a is None else a[sel])
        return replace(self, tip=self.tip[sel], axis=self.axis[sel], feed=self.feed[sel], rapid=self.rapid[sel],
                       line=self.line[sel], setup=(), kind=pick(self.kind), pass_no=pick(self.pass_no))

    def csv_text(self) -> str:
        """CSV ``x,y,z,i,j,k,f`` (mm, unit vector, mm/min; f = 0 on a rapid), one row per CL point."""
        rows = np.column_stack([self.tip, self.axis, self.feed])
        body = "\n".join(",".join(f"{v:.6f}" for v in r[:6]) + f",{r[6]:.1f}" for r in rows)
        return "x,y,z,i,j,k,f\n" + body + "\n"

    def write_csv(self, path) -> None:
        from ..fileio import atomic_write

        atomic_write(path, self.csv_text())


# ----------------------------------------------------------------------------------------------------- reading -----


def cl_format(text: str) -> str | None:
    """"apt" when a line starts with ``GOTO/``, "csv" when the first data line is a header naming x y z i j k (or a
    comma/semicolon separated header naming at least x y z), else None (G-code)."""
    # One search over the text, not a match per line: a G-code program of a million lines passes through here.
    # (fast looks first: a slash and the word in any case, 0.04 s on a million lines, where the line-start pattern
    # takes 0.15 s; G-code has slashes in comments and block deletes)
    if "/" in text and "goto" in text.lower() and _GOTO_LINE.search(text):
        return "apt"
    head = next((s for s in (m.group().strip() for m in _TEXT_LINE.finditer(text)) if s and not s.startswith("#")),
                None)
    cols = _header_columns(head) if head is not None else None
    # A separated header naming x, y and z is CL data too (read_cl then says which column is missing).
    if cols is not None and (all(c in cols for c in _REQUIRED) or (_separator(head) and {"x", "y", "z"} <= set(cols))):
        return "csv"
    return None


# a column name with its unit: "x_mm", "x [mm]", "x(mm)", "f_mm_min", "feed [mm/min]"
_UNIT_SUFFIX = re.compile(r"([a-z][a-z0-9]*)\s*(?:_([a-z_/]+)|\[\s*([a-z_/]+)\s*\]|\(\s*([a-z_/]+)\s*\))")
_MM_UNITS = {"x": ("mm",), "y": ("mm",), "z": ("mm",), "f": ("mm_min", "mm/min", "mmpm"),
             "feed": ("mm_min", "mm/min", "mmpm")}


def _header_columns(line: str, units: dict | None = None):
    """The header's column names (lower case), a unit suffix taken off the coordinates' and the feed's names
    (``x_mm``, ``X [mm]``, ``f [mm/min]``: into ``units`` {name: unit} when given); None when it is not a header."""
    sep = _separator(line)
    cells = [c.strip().strip('"').strip().lower() for c in (line.split(sep) if sep else line.split())]
    if not cells:
        return None
    names = []
    for c in cells:
        m = _UNIT_SUFFIX.fullmatch(c)
        if m and m.group(1) in _MM_UNITS:
            names.append(m.group(1))
            if units is not None:
                units[m.group(1)] = next(u for u in m.groups()[1:] if u)
        elif re.fullmatch(r"[a-z_][a-z0-9_]*", c):
            names.append(c)
        else:
            return None
    return names


def _separator(line: str):
    return "," if "," in line else (";" if ";" in line else None)


def read_cl(text_or_path, source: str | None = None) -> ClData:
    """CL data from text or a path (CSV or APT, told apart by content). Raises ClError ``file:line: reason``."""
    if isinstance(text_or_path, Path) or (isinstance(text_or_path, str) and "\n" not in text_or_path
                                          and Path(text_or_path).is_file()):
        path = Path(text_or_path)
        text = path.read_bytes().decode("utf-8", errors="replace")
        source = source or str(path)
    else:
        text = text_or_path
        source = source or "<string>"
    kind = cl_format(text)
    if kind == "apt":
        cl = _read_apt(text, source)
    elif kind == "csv":
        cl = _read_csv(text, source)
    else:
        raise ClError(source, 1, "not CL data: expected GOTO/ statements or a CSV header naming x,y,z,i,j,k")
    if len(cl) == 0:
        raise ClError(source, 1, "no CL points")
    return cl


def _finish(tip, axis, feed, rapid, line, source, fmt, setup=()) -> ClData:
    tip = np.asarray(tip, float).reshape(-1, 3)
    axis = np.asarray(axis, float).reshape(-1, 3)
    line = np.asarray(line, int)
    bad = ~(np.isfinite(tip).all(1) & np.isfinite(axis).all(1))
    if np.any(bad):
        raise ClError(source, int(line[np.argmax(bad)]), "not a finite number")
    norm = np.linalg.norm(axis, axis=1)
    zero = norm < 1e-9
    if np.any(zero):
        raise ClError(source, int(line[np.argmax(zero)]), "tool-axis vector (i, j, k) is zero")
    feed = np.asarray(feed, float)
    badf = np.isfinite(feed) & (feed <= 0) | np.isinf(feed)
    if np.any(badf):
        raise ClError(source, int(line[np.argmax(badf)]), f"feed must be positive, got {feed[np.argmax(badf)]:g}")
    # Feeds are modal: a point without one keeps the previous (NaN before the first).
    given = np.where(np.isfinite(feed), np.arange(feed.size), -1)
    last = np.maximum.accumulate(given) if feed.size else given
    feed = np.where(last >= 0, feed[np.maximum(last, 0)], np.nan)
    axis = axis / norm[:, None]
    rapid = np.asarray(rapid, bool)
    # A point repeated (the tip within 1 nm and the tool axis within 1 nrad of the one before, as CAM output often
    # has) is no move: dropped (its feed stays modal for the points after it). Kept, its zero length made an
    # inverse-time feed of 8e11 the reader refused as "number out of range" (a QA pass).
    same = np.r_[False, (np.linalg.norm(np.diff(tip, axis=0), axis=1) <= 1e-6)
                 & (np.linalg.norm(np.diff(axis, axis=0), axis=1) <= 1e-9)] if len(tip) else np.zeros(0, bool)
    if same.any():
        keep = ~same
        before = np.r_[0, np.cumsum(keep)]  # points kept before each original index
        setup = [replace(b, before=int(before[b.before])) for b in setup]
        tip, axis, feed, rapid, line = tip[keep], axis[keep], feed[keep], rapid[keep], line[keep]
    return ClData(tip, axis, feed, rapid, line, source, fmt, tuple(setup))


def _read_csv(text: str, source: str) -> ClData:
    lines = text.splitlines()
    data = [(n + 1, s) for n, s in enumerate(ln.strip() for ln in lines) if s and not s.startswith("#")]
    (head_no, head), rows = data[0], data[1:]
    units: dict = {}
    cols = _header_columns(head, units)
    other = {c: u for c, u in units.items() if u not in _MM_UNITS[c]}
    if other:
        c, u = next(iter(other.items()))
        raise ClError(source, head_no, f"CSV header gives column {c} in {u!r}: CL data in CSV are read in mm (a feed "
                                       "in mm/min); convert the file, or write it as APT with UNITS/INCHES")
    sep = _separator(head)
    missing = [c for c in _REQUIRED if c not in cols]
    if missing:
        raise ClError(source, head_no, f"CSV header lacks column(s) {', '.join(missing)} (needs x,y,z,i,j,k[,f])")
    dup = [c for c in set(cols) if cols.count(c) > 1 and c in _REQUIRED + _FEED_NAMES]
    if dup:
        raise ClError(source, head_no, f"CSV header names column {dup[0]} twice")
    idx = [cols.index(c) for c in _REQUIRED]
    fcol = next((cols.index(c) for c in _FEED_NAMES if c in cols), None)
    n = len(rows)
    line_no = np.array([r[0] for r in rows], int)
    cells = [r[1].split(sep) if sep else r[1].split() for r in rows]
    width = np.array([len(c) for c in cells], int)
    short = width != len(cols)
    if np.any(short):
        k = int(np.argmax(short))
        raise ClError(source, int(line_no[k]), f"expected {len(cols)} values (header: {head}), got {width[k]}")
    table = np.array(cells, dtype=object).reshape(n, len(cols))

    def numbers(col, allow_empty):
        raw = np.char.strip(table[:, col].astype(str))
        empty = raw == ""
        out = np.full(n, np.nan)
        try:
            out[~empty] = raw[~empty].astype(float)
        except ValueError:
            for k in np.nonzero(~empty)[0]:
                try:
                    float(raw[k])
                except ValueError:
                    raise ClError(source, int(line_no[k]),
                                  f"column {cols[col]}: {str(raw[k])!r} is not a number") from None
        if not allow_empty and np.any(empty):
            k = int(np.argmax(empty))
            raise ClError(source, int(line_no[k]), f"column {cols[col]} is empty")
        if np.any(np.isnan(out[~empty]) | np.isinf(out[~empty])):
            k = int(np.nonzero(~empty & ~np.isfinite(out))[0][0])
            raise ClError(source, int(line_no[k]), f"column {cols[col]}: not a finite number")
        return out

    vals = np.column_stack([numbers(c, False) for c in idx]) if n else np.zeros((0, 6))
    feed = numbers(fcol, True) if (fcol is not None and n) else np.full(n, np.nan)
    # A feed of 0 marks a rapid (the convention of CL CSVs, and what ``ClData.csv_text`` writes for its rapids); the
    # first point is reached by a rapid in any case. A negative feed stays an error (``_finish``).
    rapid = feed == 0
    feed = np.where(rapid, np.nan, feed)
    if n:
        rapid[0] = True
    return _finish(vals[:, :3], vals[:, 3:], feed, rapid, line_no, source, "csv")


def _apt_statements(text: str, source: str):
    """(line_no, statement) with ``$$`` comments removed and ``$`` continuations joined."""
    out, buf, start = [], "", None
    for n, raw in enumerate(text.splitlines(), 1):
        s = raw.split("$$", 1)[0].rstrip()
        if start is None:
            start = n
        if s.endswith("$"):
            buf += s[:-1]
            continue
        buf += s
        if buf.strip():
            out.append((start, buf.strip()))
        buf, start = "", None
    if buf.strip():
        out.append((start, buf.strip()))
    return out


def _apt_numbers(args: str, source: str, line: int, what: str):
    try:
        return [float(v) for v in args.split(",")]
    except ValueError:
        raise ClError(source, line, f"{what}: expected numbers separated by commas, got {args.strip()!r}") from None


def _comment(text: str) -> str:
    """Text as a G-code comment (parentheses inside would end it early)."""
    return "(" + text.replace("(", "[").replace(")", "]").strip() + ")"


def _apt_setup(word: str, args: str | None, source: str, line: int, scale: float, state: dict) -> str:
    """G-code blocks (lines joined by newlines) for an APT setup statement other than END (module docstring).
    ``state`` carries the spindle speed between SPINDL statements."""
    if word in ("PARTNO", "PPRINT"):  # free text
        return _comment(f"{word} {args or ''}")
    if word == "GOHOME":
        return "G94\nG28"
    parts = [p.strip().upper() for p in (args or "").split(",") if p.strip()]
    names = [p for p in parts if re.fullmatch(r"[A-Z]+", p)]
    nums = []
    for p in parts:
        if p not in names:
            try:
                nums.append(float(p))
            except ValueError:
                raise ClError(source, line, f"{word}/: {p!r} is neither a number nor a keyword") from None
    if word == "LOADTL":
        if names not in ([], ["ADJUST"]) or len(nums) != (2 if names else 1):
            raise ClError(source, line, "LOADTL/ reads LOADTL/n or LOADTL/n,ADJUST,h; other modifiers are not read")
        if not all(math.isfinite(v) and v == int(v) and v >= 0 for v in nums):
            raise ClError(source, line, "LOADTL/: tool and length register are whole numbers >= 0")
        n = nums[0]
        h = int(nums[1]) if names else int(n)
        return f"T{int(n)} M6\nG43 H{h}"
    if word == "SPINDL":
        if names == ["OFF"] and not nums:
            return "M5"
        direction = {"CLW": "M3", "CCLW": "M4"}
        unknown = [p for p in names if p not in ("RPM", "ON", *direction)]
        if unknown or len(nums) > 1:
            raise ClError(source, line, f"SPINDL/{args.strip() if args else ''}: reads SPINDL/[RPM,]s[,CLW|CCLW], "
                                        "SPINDL/ON and SPINDL/OFF (surface speed and ranges are not read)")
        if nums:
            if not (math.isfinite(nums[0]) and nums[0] > 0):
                raise ClError(source, line, "SPINDL/: the speed must be a positive number of rpm")
            state["rpm"] = nums[0]
        turn = next((direction[p] for p in names if p in direction), "M3")
        if "rpm" not in state:
            raise ClError(source, line, "SPINDL/ON before any spindle speed")
        return f"S{state['rpm']:g} {turn}"
    if word == "COOLNT":
        codes = {"ON": "M8", "FLOOD": "M8", "MIST": "M7", "OFF": "M9"}
        if len(names) != 1 or nums or names[0] not in codes:
            raise ClError(source, line, "COOLNT/ reads ON, FLOOD, MIST or OFF")
        return codes[names[0]]
    if word == "CUTTER":
        if not nums or not (math.isfinite(nums[0]) and nums[0] > 0) or names:
            raise ClError(source, line, "CUTTER/ needs the tool diameter (a positive number) first")
        return f"(trueaxis: d={nums[0] * scale:g})"
    raise AssertionError(word)  # APT_SETUP and this function list the same words


RETRACT_MARGIN_MM = 1.0  # APT END retracts Z to this much below the top of its travel
_APT_NOTHING = {"MULTAX", "FINI", "INTOL", "OUTTOL", "TOLER"}  # statements that change nothing in the output
APT_SETUP = {"LOADTL", "SPINDL", "COOLNT", "CUTTER", "PARTNO", "PPRINT", "GOHOME", "END"}


def _read_apt(text: str, source: str) -> ClData:
    tip, axis, feed, rapid, lines = [], [], [], [], []
    setup: list[SetupBlock] = []
    spindle: dict = {}
    ended = False
    scale = 1.0
    f_now = math.nan
    rapid_next = False
    home_at = None  # the line of a GOHOME the tool path has not left with a RAPID or FROM
    u_now = [0.0, 0.0, 1.0]
    for line, stmt in _apt_statements(text, source):
        m = _APT_STATEMENT.match(stmt)
        if not m:
            raise ClError(source, line, f"not an APT statement: {stmt!r}")
        word, args = m.group(1).upper(), m.group(2)
        if ended and word != "FINI":
            raise ClError(source, line, f"{word} after END: END ends the program")
        if word in ("GOTO", "FROM"):
            if args is None:
                raise ClError(source, line, f"{word}/ needs x,y,z[,i,j,k]")
            v = _apt_numbers(args, source, line, word)
            if len(v) not in (3, 6):
                raise ClError(source, line, f"{word}/ needs 3 or 6 numbers (x,y,z[,i,j,k]), got {len(v)}")
            if len(v) == 6:
                u_now = v[3:]
            if home_at is not None and word == "GOTO" and not rapid_next:
                # the move from the home position is no segment of the tool path: its length, and so its time,
                # is not the CL chord's (a QA pass: timed from the chord, it ran at 4835 mm/min for 800)
                raise ClError(source, line, f"GOTO after GOHOME (line {home_at}): the move from the home position is "
                                            "not a segment of the tool path, so its feed cannot be timed; put RAPID "
                                            "before it, or start again with FROM")
            home_at = None
            tip.append([c * scale for c in v[:3]])
            axis.append(list(u_now))
            feed.append(f_now)
            rapid.append(rapid_next or word == "FROM" or not tip[:-1])
            lines.append(line)
            rapid_next = False
        elif word == "FEDRAT":
            if args is None:
                raise ClError(source, line, "FEDRAT/ needs a feed")
            parts = [p.strip().upper() for p in args.split(",")]
            unit = [p for p in parts if p.isalpha()]
            nums = [p for p in parts if not p.isalpha()]
            if len(nums) != 1 or len(unit) > 1:
                raise ClError(source, line, f"FEDRAT/ expected one feed and an optional unit, got {args.strip()!r}")
            if unit and unit[0] in ("MMPR", "IPR"):
                raise ClError(source, line, f"FEDRAT per revolution ({unit[0]}) is not supported: give mm/min")
            if unit and unit[0] not in ("MMPM", "IPM"):
                raise ClError(source, line, f"FEDRAT unit {unit[0]} not understood (MMPM or IPM)")
            try:
                f_now = float(nums[0])
            except ValueError:
                raise ClError(source, line, f"FEDRAT: {nums[0]!r} is not a number") from None
            if not (math.isfinite(f_now) and f_now > 0):
                raise ClError(source, line, f"feed must be positive, got {nums[0]}")
            f_now *= MM_PER_INCH if (unit and unit[0] == "IPM") or (not unit and scale != 1.0) else 1.0
        elif word == "RAPID":
            rapid_next = True
        elif word == "UNITS":
            u = (args or "").strip().upper()
            if u in ("MM", "MILLIMETERS", "MILLIMETRES"):
                scale = 1.0
            elif u in ("INCHES", "INCH", "IN"):
                scale = MM_PER_INCH
            else:
                raise ClError(source, line, f"UNITS/{u}: expected MM or INCHES")
        elif word == "TLAXIS":
            v = _apt_numbers(args or "", source, line, "TLAXIS")
            if len(v) != 3:
                raise ClError(source, line, "TLAXIS/ needs i,j,k")
            u_now = v
        elif word == "END":
            setup.append(SetupBlock(len(tip), "M5\nM9", line, retract=True))
            ended = True
        elif word in APT_SETUP:
            if word == "GOHOME":
                home_at = line
            words = _apt_setup(word, args, source, line, scale, spindle)
            setup.append(SetupBlock(len(tip), words, line))
        elif word in _MOVING_APT:
            raise ClError(source, line, f"{_MOVING_APT[word]} is not read here: give the tool path as GOTO points")
        elif word not in _APT_NOTHING:
            raise ClError(source, line, f"APT statement {word} is not read here (read: GOTO, FROM, FEDRAT, RAPID, "
                                        f"UNITS, TLAXIS, {', '.join(sorted(APT_SETUP | _APT_NOTHING))})")
    return _finish(tip, axis, feed, rapid, lines, source, "apt", setup)


# ------------------------------------------------------------------------------------------- machine axes -----


def _fail(cl: ClData, k: int, reason: str):
    raise ClError(cl.source, int(cl.line[k]), reason)


def _in_travel(machine: Machine, name: str, values):
    return machine.axes[name].within_travel(values)


def _margin(machine: Machine, name: str, values):
    tr = machine.axes[name].travel
    if tr is None:
        return np.zeros(np.shape(values))
    return np.minimum(values - tr[0], tr[1] - values)


def _ik_pick(machine, tip, axis, prev, branch):
    """Inverse kinematics on both branches towards ``prev`` (N, n_axes), the result of branch (N,) +-1 per pose."""
    r1 = inverse_kinematics(machine, tip, axis, branch=1, previous=prev)
    r2 = inverse_kinematics(machine, tip, axis, branch=-1, previous=prev)
    q = np.where((branch > 0)[:, None], r1.q, r2.q)
    return q, r1.singular


def _solve_path(cl: ClData, machine: Machine, branch, previous):
    """(N, n_axes) machine axes along the CL path, continuous (branch kept, shortest winding), and (N,) branch."""
    outer, inner = _rotary_pair(machine)
    n = len(cl)
    names = machine.axis_names
    r1 = inverse_kinematics(machine, cl.tip, cl.axis, branch=1)
    r2 = inverse_kinematics(machine, cl.tip, cl.axis, branch=-1)
    i1, i2 = r1.q[:, inner.column], r2.q[:, inner.column]
    ok1, ok2 = _in_travel(machine, inner.axis, i1), _in_travel(machine, inner.axis, i2)
    none = ~ok1 & ~ok2
    if np.any(none):
        k = int(np.argmax(none))
        tr = np.degrees(machine.axes[inner.axis].travel)
        _fail(cl, k, f"tool axis ({', '.join(f'{v:.6g}' for v in cl.axis[k])}) needs {inner.axis} = "
                     f"{np.degrees(i1[k]):+.4f} or {np.degrees(i2[k]):+.4f} deg, outside its travel [{tr[0]:g}, {tr[1]:g}]")
    prev0 = None if previous is None else np.asarray(previous, float).reshape(len(names))
    if branch in (1, -1, "+1", "-1", "+", "-"):
        b0 = 1 if branch in (1, "+1", "+") else -1
        ok = ok1 if b0 > 0 else ok2
        if not np.all(ok):
            k = int(np.argmin(ok))
            _fail(cl, k, f"branch {b0:+d}: {inner.axis} = {np.degrees((i1 if b0 > 0 else i2)[k]):+.4f} deg lies "
                         "outside its travel")
        b = np.full(n, b0)
    elif branch == "nearest":
        forced = np.where(ok1 & ~ok2, 1, np.where(ok2 & ~ok1, -1, 0))
        if prev0 is not None:
            d1, d2 = abs(i1[0] - prev0[inner.column]), abs(i2[0] - prev0[inner.column])
            first = -1 if (ok2[0] and (d2 < d1 or not ok1[0])) else 1
        else:
            m1 = np.where(ok1, _margin(machine, inner.axis, i1), -np.inf).mean()
            m2 = np.where(ok2, _margin(machine, inner.axis, i2), -np.inf).mean()
            first = -1 if m2 > m1 else 1
        if forced[0] == 0:
            forced[0] = first
        # Keep the branch until the other one is the only one inside the travel: forward fill of the forced choices.
        last = np.maximum.accumulate(np.where(forced != 0, np.arange(n), 0))
        b = forced[last]
        flip = np.nonzero((b[1:] != b[:-1]) & ~cl.rapid[1:])[0]
        if flip.size:
            k = int(flip[0]) + 1
            _fail(cl, k, f"the tilt axis {inner.axis} would change branch inside a cut here ({inner.axis} "
                         f"{np.degrees((i1 if b[k - 1] > 0 else i2)[k]):+.4f} deg is outside its travel): retract "
                         "with a RAPID before this point, or change the tool axes")
    else:
        raise ValueError(f"branch must be +1, -1 or 'nearest', got {branch!r}")
    # Winding: the chosen branch's outer angle, held where singular, then the shortest way from pose to pose. The
    # singular poses a pass starts with (the tool along the outer axis, where any angle serves) take the angle of its
    # first pose that is not: a path that starts vertical and tilts in then needs no turn inside the cut (held at
    # the angle before, a tilt toward +X turned C by 180 deg in one segment, refused; a QA pass).
    o = np.where(b > 0, r1.q[:, outer.column], r2.q[:, outer.column])
    sing = r1.singular
    o_start = 0.0 if prev0 is None else prev0[outer.column]
    idx = np.where(~sing, np.arange(n), -1)
    last = np.maximum.accumulate(idx)
    first = int(np.argmax(~sing)) if (~sing).any() else -1
    o = np.where(last >= 0, o[np.maximum(last, 0)], o_start if first < 0 else o[first])
    o = _turned_across_singular_runs(o, sing, cl.tip)
    steps = np.diff(o)
    steps = (steps + np.pi) % (2 * np.pi) - np.pi
    o0 = o[0] + 2 * np.pi * np.round((o_start - o[0]) / (2 * np.pi))
    o = o0 + np.r_[0.0, np.cumsum(steps)]
    tr = machine.axes[outer.axis].travel
    if tr is not None:
        lo, hi = o.min(), o.max()
        ks = np.arange(math.ceil((tr[0] - lo) / (2 * np.pi) - 1e-12), math.floor((tr[1] - hi) / (2 * np.pi) + 1e-12) + 1)
        if ks.size == 0:
            out = ~_in_travel(machine, outer.axis, o)
            _fail(cl, int(np.argmax(out)), f"the {outer.axis} axis winds {np.degrees(hi - lo):.1f} deg along the path, "
                                           f"more than its travel allows: split the path and unwind between the parts")
        o = o + 2 * np.pi * ks[np.argmin(np.abs(ks))]
    prev = np.zeros((n, len(names)))
    prev[:, outer.column] = o
    prev[:, inner.column] = np.where(b > 0, i1, i2)
    q, _ = _ik_pick(machine, cl.tip, cl.axis, prev, b)
    # The linear axes of a pose off the singular cone from its angles within a turn of zero (the solution without
    # ``previous``): the sine of a wound angle loses its last bits (sin(-2 pi) is 2.4e-16, not 0).
    raw = np.where((b > 0)[:, None], r1.q, r2.q)
    linear = [c for c, a in enumerate(names) if not machine.axes[a].is_rotary]
    q[np.ix_(~sing, linear)] = raw[np.ix_(~sing, linear)]
    return q, b


def _turned_across_singular_runs(o: np.ndarray, sing: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """The outer axis' angles ``o`` (N,) rad with each run of singular poses between two that are not turned from the
    one before to the one after, the shortest way, on the run's segments whose both ends are singular (the tool stays
    along the outer axis there, where any angle serves), in proportion to the tip's path length; they held the one
    before, and a path tilted one way, then vertical, then tilted another way turned in its last segment, refused as
    a jump of the axes. A run of one pose has no such segment: held as before."""
    ns = np.flatnonzero(~sing)
    if ns.size < 2:
        return o
    gaps = np.flatnonzero(np.diff(ns) > 2)  # runs of two or more singular poses between ns[g] and ns[g + 1]
    if gaps.size == 0:
        return o
    o = o.copy()
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(tip, axis=0), axis=1))]
    for g in gaps:
        a, b = int(ns[g]) + 1, int(ns[g + 1]) - 1  # the run's first and last singular pose
        turn = (o[b + 1] - o[a - 1] + np.pi) % (2 * np.pi) - np.pi
        span = s[b] - s[a]
        frac = (s[a:b + 1] - s[a]) / span if span > 0 else np.arange(b - a + 1) / (b - a)
        o[a:b + 1] = o[a - 1] + frac * turn
    return o


def machine_linear_positions(machine: Machine, q_rot: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Linear axes (P, K, n_linear) in mm that put the tool tip on ``points`` (K, 3, part frame) with the rotary axes
    of poses ``q_rot`` (P, n_axes; linear columns ignored). With the rotary axes fixed the tip is affine in the linear
    axes, so three unit probes give the map."""
    _, p0, M = linear_axis_map(machine, q_rot)
    rhs = np.asarray(points, float)[None, :, :] - p0[:, None, :]  # (P, K, 3)
    return np.einsum("pij,pkj->pki", np.linalg.pinv(M), rhs)


def travel_problem(machine: Machine, q: np.ndarray) -> str:
    """The first axis whose values in ``q`` (N, n_axes) mm/rad leave its travel (``Axis.within_travel``), said in
    words with its range (deg for rotary axes); "" when every axis stays inside."""
    for c, a in enumerate(machine.axis_names):
        tr = machine.axes[a].travel
        if tr is None:
            continue
        lo, hi = float(q[:, c].min()), float(q[:, c].max())
        if not machine.axes[a].within_travel([lo, hi]).all():
            f = math.degrees if machine.axes[a].is_rotary else (lambda v: v)
            return (f"axis {a} needs [{f(lo):.3f}, {f(hi):.3f}], outside its travel [{f(tr[0]):g}, {f(tr[1]):g}]")
    return ""


def _three_axis(cl: ClData, machine: Machine) -> np.ndarray:
    """Machine axes of CL points on a machine without a rotary pair: the tool axis must stay +Z."""
    names = machine.axis_names
    if np.any(np.abs(cl.axis - [0, 0, 1.0]) > 1e-12):
        raise ValueError(f"{machine.name} has no rotary axes: the tool axis must stay +Z")
    q = np.zeros((len(cl), len(names)))
    lin = [c for c, a in enumerate(names) if not machine.axes[a].is_rotary]
    q[:, lin] = machine_linear_positions(machine, q[:1], cl.tip)[0]
    return q


def cl_axes(cl: ClData, machine: Machine, *, branch="nearest", previous=None) -> tuple[np.ndarray, np.ndarray]:
    """The one way from CL poses to machine axes: (N, n_axes) mm/rad and the tilt branch (N,) (+-1; 0 without rotary
    axes), pass by pass (``cl.pass_no``; CAM data is one pass), each pass starting from where the one before ended.

    On a five-axis machine each pass is solved by the inverse kinematics with the branch kept along the pass and the
    outer rotary axis wound the shortest way from pose to pose and fitted into its travel (module docstring).
    branch : "nearest" (the first pass's branch nearest ``previous``, or the one farthest inside the travel), +1, -1,
    or "first-fit" (the part programs: per pass -1, else +1 where -1 leaves a travel, linear axes included).
    previous : (n_axes,) the pose before the first point. On a machine without a rotary pair the tool axis must stay
    +Z. Raises ClError (``source:line: reason``) or, for "first-fit" when neither branch fits, ValueError naming the
    pass and the axis.
    """
    q = np.zeros((len(cl), len(machine.axis_names)))
    b = np.zeros(len(cl), int)
    passes = [np.arange(len(cl))] if cl.pass_no is None else [np.nonzero(cl.pass_no == k)[0]
                                                               for k in np.unique(cl.pass_no)]
    for k, sel in enumerate(passes):
        part = cl.rows(sel) if cl.pass_no is not None else cl
        if not machine.is_five_axis:
            qk, bk = _three_axis(part, machine), np.zeros(len(sel), int)
        elif branch == "first-fit":
            qk = None
            for b0 in (-1, 1):
                try:
                    qk, bk = _solve_path(part, machine, b0, previous)
                except ClError:
                    continue
                if not travel_problem(machine, qk):
                    break
                qk = None
            if qk is None:
                raw = inverse_kinematics(machine, part.tip, part.axis, branch=-1).q
                name = cl.passes[int(cl.pass_no[sel[0]])]["name"] if cl.passes and cl.pass_no is not None else ""
                which = f"pass {k + 1} ({name})" if name else f"pass {k + 1}"  # 'pass 1 ():' without a name
                # A path the machine cannot reach is a refused input (exit 3, like a program's block out of travel).
                _fail(cl, int(sel[0]), f"{which}: {travel_problem(machine, raw) or 'no tilt branch fits'}; "
                      "move the part (placement) or check the machine file")
        else:
            qk, bk = _solve_path(part, machine, branch, previous)
        q[sel], b[sel] = qk, bk
        previous = qk[-1]
    return q, b


def _check_linear_travel(cl, machine, q, point):
    for c, a in enumerate(machine.axis_names):
        if machine.axes[a].is_rotary or machine.axes[a].travel is None:
            continue
        out = ~_in_travel(machine, a, q[:, c])
        if np.any(out):
            k = int(np.argmax(out))
            lo, hi = machine.axes[a].travel
            _fail(cl, int(point[k]), f"{a} = {q[k, c]:.4f} mm for this CL pose lies outside its travel [{lo:g}, {hi:g}]")


def _slerp(a, b, t):
    """Unit vectors along the great circle from a to b (both (K,3) unit) at fractions t (K,)."""
    dot = np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)
    w = np.arccos(dot)
    s = np.sin(w)
    small = s < 1e-9
    s_safe = np.where(small, 1.0, s)
    ca = np.where(small, 1 - t, np.sin((1 - t) * w) / s_safe)
    cb = np.where(small, t, np.sin(t * w) / s_safe)
    v = ca[:, None] * a + cb[:, None] * b
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _angle(a, b):
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))


def _path_deviation(p, u, ta, tb, ua, ub):
    """Distance (mm) of tips p from the segments [ta, tb], and angle (rad) of axes u from the CL axis interpolated at
    the tip's place along the segment (from the great-circle arc [ua, ub] where the tip does not move)."""
    d = tb - ta
    L2 = np.einsum("ij,ij->i", d, d)
    moving = L2 > 1e-12
    t = np.clip(np.einsum("ij,ij->i", p - ta, d) / np.where(moving, L2, 1.0), 0.0, 1.0)
    dist = np.linalg.norm(p - (ta + t[:, None] * d), axis=1)
    ang = _angle(u, _slerp(ua, ub, t))
    if np.any(~moving):
        ang = np.where(moving, ang, _angle_to_arc(u, ua, ub))
    return dist, ang


def _angle_to_arc(u, a, b):
    n = np.cross(a, b)
    nn = np.linalg.norm(n, axis=1)
    ends = np.minimum(_angle(u, a), _angle(u, b))
    ok = nn > 1e-12
    nh = n / np.where(ok, nn, 1.0)[:, None]
    off = np.arcsin(np.clip(np.abs(np.einsum("ij,ij->i", u, nh)), 0.0, 1.0))
    v = u - np.einsum("ij,ij->i", u, nh)[:, None] * nh
    inside = _angle(a, v) + _angle(v, b) <= _angle(a, b) + 1e-12
    return np.where(ok & inside, off, ends)


def _linearise(cl, machine, q, b, tol_mm, tol_rad, max_rounds=16):
    """Split CL segments until the joint-linear path stays on them. Returns per output point: q (M, n_axes), CL
    segment end index (M,) and fraction along it (M,) (1 at the CL points themselves).

    The points of all segments live in flat arrays (segment, fraction, q), sorted anew each round; only the segments
    that still have a piece out of tolerance are looked at again."""
    n = len(cl)
    cut = np.nonzero(~cl.rapid[1:])[0] + 1  # segment k runs from CL point k-1 to k
    K = np.r_[cut, cut]
    F = np.r_[np.zeros(cut.size), np.ones(cut.size)]
    Q = np.vstack([q[cut - 1], q[cut]])
    active = np.zeros(n + 1, bool)
    active[cut] = True
    for _ in range(max_rounds):
        order = np.lexsort((F, K))
        K, F, Q = K[order], F[order], Q[order]
        ia = np.nonzero((K[1:] == K[:-1]) & active[K[:-1]])[0]
        if ia.size == 0:
            break
        owner, fa, fb, qa, qb = K[ia], F[ia], F[ia + 1], Q[ia], Q[ia + 1]
        ta, tb = cl.tip[owner - 1], cl.tip[owner]
        ua, ub = cl.axis[owner - 1], cl.axis[owner]
        worst = np.zeros(owner.size)
        for s in (0.25, 0.5, 0.75):
            p, u = forward_nominal(machine, qa + s * (qb - qa))
            dist, ang = _path_deviation(p, u, ta, tb, ua, ub)
            worst = np.maximum(worst, np.maximum(dist / tol_mm, ang / tol_rad))
        bad = worst > 1.0
        if not np.any(bad):
            break
        stuck = bad & ((fb - fa) < 1e-6)
        if np.any(stuck):
            # A piece a millionth of its segment long that still leaves it: the axes jump there, as the outer axis
            # does where the path goes through the singular pose (tool axis along it) and comes out elsewhere.
            k = int(owner[np.argmax(stuck)])
            raise ClError(cl.source, int(cl.line[k]), "the machine axes jump on this CL segment (it passes through "
                                                      "or next to the singular tool axis with the rotary table "
                                                      "turning): keep the tool axis off the table's axis here, or "
                                                      "reach this pose with a RAPID")
        # Chord deviations shrink with the square of the piece: about sqrt(worst) sub-pieces each.
        nsub = np.where(bad, np.maximum(2, np.ceil(np.sqrt(worst))), 1).astype(int)
        rep = np.repeat(np.arange(owner.size), nsub - 1)
        j = np.arange(rep.size) - np.repeat(np.cumsum(nsub - 1) - (nsub - 1), nsub - 1) + 1
        fr = fa[rep] + (fb[rep] - fa[rep]) * j / nsub[rep]
        sk = owner[rep]
        prev = qa[rep] + ((fr - fa[rep]) / (fb[rep] - fa[rep]))[:, None] * (qb[rep] - qa[rep])
        tip = cl.tip[sk - 1] + fr[:, None] * (cl.tip[sk] - cl.tip[sk - 1])
        ax = _slerp(cl.axis[sk - 1], cl.axis[sk], fr)
        qn, _ = _ik_pick(machine, tip, ax, prev, b[sk])
        K, F, Q = np.r_[K, sk], np.r_[F, fr], np.vstack([Q, qn])
        active[:] = False
        active[np.unique(owner[bad])] = True
    else:
        k = int(np.nonzero(active)[0][0])
        raise ClError(cl.source, int(cl.line[k]), "the joint-linear path does not converge onto the CL segment "
                                                  "(a singular tool axis?): check the CL data here")
    # Every output point: the segments' inner and end points, plus the CL points reached by rapids (and the first).
    keep = F > 0
    others = np.setdiff1d(np.arange(n), cut)
    K = np.r_[K[keep], others]
    F = np.r_[F[keep], np.ones(others.size)]
    Q = np.vstack([Q[keep], q[others]])
    order = np.lexsort((F, K))
    return Q[order], K[order], F[order]


def cl_program(cl: ClData, machine: Machine, *, tol_um: float = 1.0, linearise: bool = True,
               feed_mm_min: float | None = None, branch="nearest", previous=None, title: str | None = None):
    """Machine-axis G-code text for CL poses, and per output line (0-based) the CL source line it comes from."""
    if not machine.is_five_axis:
        raise ClError(cl.source, int(cl.line[0]), f"CL data needs a five-axis machine; {machine.name} has axes "
                                                  f"{' '.join(machine.axis_names)}")
    try:
        q, b = cl_axes(cl, machine, branch=branch, previous=previous)
    except NotImplementedError as exc:
        raise ClError(cl.source, int(cl.line[0]), str(exc)) from None
    n = len(cl)
    _check_linear_travel(cl, machine, q, np.arange(n))
    # Feeds: modal, the caller's default before the first one.
    feed = cl.feed.copy()
    idx = np.where(np.isfinite(feed), np.arange(n), -1)
    last = np.maximum.accumulate(idx)
    default = np.nan if feed_mm_min is None else float(feed_mm_min)
    feed = np.where(last >= 0, feed[np.maximum(last, 0)], default)
    nofeed = ~cl.rapid & ~np.isfinite(feed)
    if np.any(nofeed):
        _fail(cl, int(np.argmax(nofeed)), "no feed for this cutting move: give an f column (CSV), FEDRAT/ (APT) or a "
                                          "default feed")
    tol_mm, tol_rad = tol_um * 1e-3, max(tol_um, 1.0) * 1e-6
    if linearise:
        q_out, seg, frac = _linearise(cl, machine, q, b, tol_mm, tol_rad)
        _check_linear_travel(cl, machine, q_out, seg)
    else:
        q_out, seg, frac = q, np.arange(n), np.ones(n)
    # G93 inverse time per output move: feed / tool-tip chord in the part frame (pieces of a CL segment lie on it).
    frac_prev = np.r_[0.0, np.where(seg[1:] == seg[:-1], frac[:-1], 0.0)]
    seg_len = np.linalg.norm(cl.tip[seg] - cl.tip[np.maximum(seg - 1, 0)], axis=1)
    turn = _angle(cl.axis[seg], cl.axis[np.maximum(seg - 1, 0)])
    length = np.where(seg_len > 1e-6, seg_len, machine.tool.length * turn) * (frac - frac_prev)
    rapid = cl.rapid[seg] & (frac == 1.0)
    with np.errstate(divide="ignore"):
        inv_time = np.where(rapid, 0.0, feed[seg] / np.maximum(length, 1e-9))

    names = machine.axis_names
    rot = np.array([machine.axes[a].is_rotary for a in names])
    vals = np.where(rot[None, :], np.degrees(q_out), q_out) * machine.word_signs()  # [kinematics] rotary_sense
    name = (title or f"CL data {cl.source}").replace("(", "[").replace(")", "]")
    out = ["%", f"({name}, machine axes for {machine.name.replace('(', '[').replace(')', ']')})", "G21 G90 G17"]
    line_map = [int(cl.line[0])] * 3
    words = [" ".join(f"{a}{v:.{_DIGITS}f}" for a, v in zip(names, row)) for row in vals]
    g93 = False
    first_piece = np.r_[True, seg[1:] != seg[:-1]]
    pending = list(cl.setup)

    def write_setup(before: int):
        nonlocal g93
        while pending and pending[0].before <= before:
            block = pending.pop(0)
            text = block.words
            if block.retract:  # out of the material before the spindle stops
                text = _retract(machine, cl, block) + "\n" + text
            if g93 and ("G0" in text.split() or "G28" in text.split()):
                text = "G94\n" + text.removeprefix("G94\n")
                g93 = False
            for w in text.split("\n"):
                out.append(w)
                line_map.append(block.line)

    for m in range(q_out.shape[0]):
        src = int(cl.line[seg[m]])
        if first_piece[m]:
            write_setup(int(seg[m]))
        if rapid[m]:
            out.append(f"G94 G0 {words[m]}" if g93 or m == 0 else f"G0 {words[m]}")
            g93 = False
        else:
            if not g93:
                out.append("G93")
                line_map.append(src)
                g93 = True
            out.append(f"G1 {words[m]} F{inv_time[m]:.4f}")
        line_map.append(src)
    write_setup(n)
    out += ["G94", "M30", "%"]
    line_map += [int(cl.line[-1])] * 3
    return "\n".join(out) + "\n", line_map


def _retract(machine: Machine, cl: ClData, block: SetupBlock) -> str:
    """APT END's retract: a rapid of Z alone (the tool axis of a table machine) to 1 mm below the top of its travel,
    which leaves room for the compensation of the move (it is corrected like any other)."""
    z = machine.axes.get("Z")
    if z is None or z.travel is None:
        raise ClError(cl.source, block.line, "END retracts Z to the top of its travel: the machine file gives no Z "
                                             "travel")
    return f"G0 Z{z.travel[1] - RETRACT_MARGIN_MM:.{_DIGITS}f}"


def cl_to_program(cl, machine: Machine, **kwargs) -> str:
    """Machine-axis G-code text (G93 inverse time for the cuts) for CL data (a ClData, CL text or a path).

    Keywords: tol_um (linearisation tolerance, um and urad; default 1), linearise (default True), feed_mm_min (feed
    before the first one in the data), branch ("nearest", +1, -1), previous ((n_axes,) mm/rad pose the path starts
    from, for the branch and the winding), title (the program's comment).
    """
    if not isinstance(cl, ClData):
        cl = read_cl(cl)
    return cl_program(cl, machine, **kwargs)[0]
