"""The post-processor: compensate an NC program with the error twin (DESIGN §5).

``compensate(program, machine, mode=...)`` reads machine-axis G-code, finds for every move the commanded axes whose
*actual* pose (the twin) is the *nominal* pose of the programmed axes, splits moves where the actual path would leave
the nominal one by more than the tolerance, and writes the program back in its own dialect: comments, line numbers
and non-motion blocks kept, every compensated motion block with its motion word and all its axis words, numbers at the
program's precision (at least 5 decimals in mm and 6 in inch for linear axes, 5 for rotary axes: enough that the
written numbers do not eat the 0.1 um / 1 urad budget).

What it refuses (``PostError``, ``file:line: reason``; nothing is written): a correction above the bound, a corrected
position outside an axis' travel, a program for axes the machine does not have, incremental canned cycles, and
whatever the reader refuses. G28/G30 and G53 moves are passed through unchanged (their targets are machine positions).

Cutting conditions for comprehensive mode, in order of precedence (the first that gives a field wins):
1. the caller's ``conditions`` (command line ``--ap --ae --fz --n --d --z --cut-mode``),
2. the program's structured comments ``(trueaxis: ap=.. ae=.. fz=.. n=.. d=.. z=.. mode=down)``, valid from where they
   stand (FreeCAD's post writes them from the job's tool controller and operation),
3. the setup's tool table: the diameter of the tool in the spindle (``--tool-table`` D, a setup file's diameter),
4. the machine file's tool (diameter = 2 x radius, flutes).
On a lathe the force is Kienzle's turning force from ``(trueaxis: ap=.. f=.. vc=..)`` instead, and each block's
direction of motion chooses the response surfaces (``trueaxis.postproc.turning``).
The force is the mechanistic model's mean force over a tooth period, in the feed frame turned to the machine frame:
z along the tool axis (in the machine frame: machine Z unless a head tilts the tool), x along the feed
direction normal to it, y = z x x. Rapids and plunges carry no force.
"""

from __future__ import annotations

import bisect
import contextlib
import functools
import gc
import math
import os
import re
import threading
import warnings
from dataclasses import dataclass, field
from typing import NamedTuple
from pathlib import Path

import numpy as np

from ..compiled import kernels_on_this_thread, run_twins, thread_slices
from ..machine import ErrorTwin, Machine, load_machine
from ..machine.cutting_force import CuttingCoefficients, CuttingConditions, mean_force
from ..machine.kinematics import machine_to_part_rotation
from ..machine.model import implausible_parameters
from ..nc.flatten import program_start
from ..nc.gcode import (
    ARC_CCW,
    ARC_CW,
    FEED,
    MM_PER_INCH,
    RAPID,
    ROW_CYCLE,
    ROW_MACHINE,
    ROW_PROGRAMMED,
    ROW_REFERENCE,
    WORD_BITS,
    GcodeError,
    Program,
    parse_program,
    TOKEN_PATTERN,
    tokenize_line,
    write_numbers,
    write_number,
)
from ..nc import fast_write
from ..resources import machine_file
from ..nc.grammar import NUMBER
from .arcs import fit_arcs, full_turns_close, plane_columns, radii_kept_within_limits, xyz_decimals
from .solver import corrected_directions, solve_commanded

MODES = ("none", "geometric", "comprehensive")
AXES = "XYZABC"
_CONDITIONS = re.compile(r"\(\s*trueaxis:([^)]*)\)", re.IGNORECASE)


def condition_marks(lines, source: str) -> list[tuple[int, dict]]:
    """The structured cutting-conditions comments ``(trueaxis: key=value ...)`` of a program: [(0-based line index,
    {key: value text})] in program order (milling and turning read the same comments; each takes its keys)."""
    marks = []
    for i, line in enumerate(lines):
        if "trueaxis" not in line.lower():
            continue
        for m in _CONDITIONS.finditer(line):
            fields = {}
            for item in m.group(1).split():
                if "=" not in item:
                    raise PostError(source, i + 1, f"structured comment: expected key=value, got {item!r}")
                k, v = item.split("=", 1)
                fields[k.strip().lower()] = v.strip()
            marks.append((i, fields))
    return marks
_MOTION_WORD = re.compile(r"^G0*([0-3])$", re.IGNORECASE)
# the motion group's codes a line holds (its modal motion: moves, cycles and G80), for the modal cycle in force
_G87 = re.compile(r"(?i)G\s*0*87(?![\d.])")
_MOTION_CODE = re.compile(r"(?i)G\s*0*(0|1|2|3|33\.1|38\.[2-5]|73|76|8[0-9])(?![\d.])")
_EIGHTY_SEVEN = re.compile(r"87(?![\d.])")
_AXIS_WORDS = sum(1 << WORD_BITS.index(a) for a in AXES)  # the bits of Program.words a block's axis words set


# the units the structured comments' cutting conditions are read in (milling's and turning's keys)
_CONDITION_UNITS = {"ap": "mm", "ae": "mm", "d": "mm", "fz": "mm per tooth", "f": "mm per revolution",
                    "vc": "m/min"}


def note_inch_conditions(poster, marks):
    """A warning, once per post, where an inch program (G20) gives cutting conditions in structured comments: they are
    read in the units the comment's keys are defined in (mm, mm per tooth or revolution, m/min) whatever the program's
    units, and an inch value written there (ap=0.08 for 0.08 in) would be taken 25.4 times too small, exit 0."""
    p = poster.p
    if not marks or not bool(np.any(p.inch)):
        return
    with _REPORT_LOCK:  # (milling's conditions are read on the chunks' threads)
        if getattr(poster, "_inch_conditions_said", False):
            return
        poster._inch_conditions_said = True
        line, fields = marks[0]
        said = " ".join(f"{k}={v}" for k, v in fields.items() if k in _CONDITION_UNITS)
        units = ", ".join(f"{k} in {_CONDITION_UNITS[k]}" for k in fields if k in _CONDITION_UNITS)
        poster.rep.warnings.append(
            f"{p.source}:{p.source_line_of(line)}: the program is in inch (G20), its cutting conditions ({said}) are "
            f"read in metric units as always ({units}): write them so, or give them on the command line")


def _g87_starts(text: str) -> list[int]:
    """The start of every match of ``_G87`` in text: its "87"s found first (a literal the pattern engine skips to;
    the whole pattern, starting with a letter of either case, is tried at every position: 0.17 s against 0.02 s on a
    million NIST lines), each then read backwards over the zeros and the white space to its G."""
    starts = []
    for m in _EIGHTY_SEVEN.finditer(text):
        j = m.start() - 1
        while j >= 0 and text[j] == "0":
            j -= 1
        while j >= 0 and text[j].isspace():  # (re's \s on str is str.isspace)
            j -= 1
        if j >= 0 and text[j] in "Gg":
            starts.append(j)
    return starts


_NUM = NUMBER  # the one number of nc/grammar.py
# A plain motion block: N G X Y Z A B C I J K R F, each optional, in this order, nothing else (the writer's fast path)
_PLAIN = re.compile(
    r"[ \t]*(?P<n>[Nn][0-9]+)?[ \t]*(?P<g>[Gg]0*[0-3](?![0-9.]))?[ \t]*"
    + "".join(rf"(?:[{c}{c.lower()}][ \t]*{_NUM}[ \t]*)?" for c in "XYZABCIJK")
    + rf"(?P<r>[Rr][ \t]*{_NUM})?[ \t]*(?P<f>[Ff][ \t]*{_NUM})?[ \t]*\Z"
)
_R_BIT = 1 << WORD_BITS.index("R")
# The Newton solve's tolerance (um, urad) and the rounding of the written numbers at their fewest decimals (5 in mm:
# 0.005 um; 6 in inch: 0.013 um; 5 in degrees: 0.087 urad per rotary axis, two of them, and their effect on the tip
# at a 200 mm lever arm, 0.02 um): both come off the split tolerance.
SOLVE_TOL_UM, SOLVE_TOL_URAD = 0.01, 0.02
WRITE_ROUNDING_UM, WRITE_ROUNDING_URAD = 0.03, 0.18
_REPORT_LOCK = threading.Lock()  # what the chunks' threads add to a report
MIN_TOL_UM = 0.05  # the smallest path tolerance: the written digits' rounding and the solve's residual fit in it
# moves compensated together: bounds memory (an arc samples 17 poses); 8000 cost the NIST post 0.3-0.6 s CPU more
ROW_CHUNK = 16_000
WRITE_WINDOW = 50_000  # moves whose axis words are formatted together
FAST_WRITE = True  # the compiled writer (fast_write) for plain blocks; False: every line by the Python path
CHUNK_THREADS = True  # chunks of moves compensated on two threads (``_compensate_chunks``); False: one after the other
# An arc's correction is sampled at least this often (mm of arc) to decide whether it stays an arc: the error
# tables' knots lie 10 mm or more apart, so a cubic's variation between them is followed closely.
ARC_SAMPLE_MM = 2.0


class PostError(GcodeError):
    """The post refuses the program: ``file:line: reason``."""


@dataclass
class PostReport:
    """What the post did, for ``--report r.json``."""

    source: str
    machine: str
    mode: str
    tol_um: float
    output_mode: str = "joint"  # joint positions, or tool-centre-point positions (.tcp)
    blocks_in: int = 0
    blocks_out: int = 0  # the output's lines, the header's comments (header_blocks of them) included
    header_blocks: int = 0
    moves: int = 0
    moves_split: int = 0
    arcs_kept: int = 0
    arcs_linearised: int = 0
    arcs_fitted: int = 0  # arcs written as G2/G3 blocks fitted to the corrected path (.arcs)
    arc_blocks_fitted: int = 0  # the blocks they became
    max_arc_deviation_um: float = 0.0  # the fitted arcs' largest distance from the nominal arc, through the twin
    sub_arcs_linearised: int = 0  # sub-arcs of fitted arcs that did not hold as arcs: straight pieces
    singular_blocks: list = field(default_factory=list)
    singular_block_count: int = 0
    singular_points: int = 0
    max_axis_error_singular_urad: float = 0.0
    input_format: str = "gcode"
    cl_points: int = 0
    cl_program_blocks: int = 0
    correction: dict = field(default_factory=dict)
    units_note: str = ""
    passthrough: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    max_residual_um: float = 0.0
    max_residual_urad: float = 0.0
    max_split_deviation_um: float = 0.0
    max_split_deviation_urad: float = 0.0
    setup: str = "none given"
    setup_used: list = field(default_factory=list)
    uncompensated: list = field(default_factory=list)
    cutting_conditions: list = field(default_factory=list)  # comprehensive mode: each set used, what was assumed
    # G92 / G10 L20 blocks whose values carry the correction of the position they are set from (.. line, what, the
    # correction added per axis in program units)
    offsets_shifted: list = field(default_factory=list)
    # canned cycles: the largest distance (um) between the X Y correction the twin asks for in a hole (R plane and
    # below) and the one written (the hole's bottom)
    max_cycle_deviation_um: float = 0.0
    # under tool length offsets: the twin's largest tool-axis error on the program's moves (urad), what a tool of
    # another length than the reference one turns into an uncorrected tip error (d x this)
    tool_axis_error_max_urad: float | None = None

    def as_dict(self) -> dict:
        return dict(self.__dict__)


# --------------------------------------------------------------------------------------------------- the API -----


def compensate(
    program,
    machine: Machine | str | os.PathLike,
    mode: str = "geometric",
    *,
    tol_um: float = 1.0,
    max_correction_mm: float = 0.5,
    singular_deg: float = 1.0,
    conditions: dict | None = None,
    passthrough_unsupported: bool = False,
    source: str | None = None,
    report: dict | None = None,
    cl_feed_mm_min: float | None = None,
    cl_branch="nearest",
    setup=None,
    var=None,
    tool_table=None,
    machine_units: str = "mm",
    offsets_zero: bool = False,
    header: bool = True,
    force: bool = False,
    arcs: bool | None = None,
    output_mode: str | None = None,
) -> str:
    """Compensated program text. ``program``: G-code text, CL data (CSV or APT, see ``cl``) or a path.
    ``machine``: a :class:`Machine`, or a machine file's path or a fixture machine's short name ('xh714'), as the
    command line's ``--machine`` (:func:`machine_of`). ``report``: a dict to fill with the report.

    The control's setup (DESIGN §5): ``var`` (LinuxCNC parameter file), ``tool_table`` (LinuxCNC tool table), both in
    ``machine_units``; ``setup`` a setup file (path) or a :class:`~trueaxis.nc.setup.Setup`; none of them: the
    machine file's default setup, if it names one. ``offsets_zero``: work offsets, G92 shifts and tool lengths that
    none of them gives are zero (without it a program that uses one is refused). ``header``: put the comment naming
    the machine, mode and setup at the top of the output. ``arcs``: arcs the post cannot keep as they are become
    G2/G3 blocks fitted to the corrected path where they hold the tolerance (``.arcs``), else straight pieces;
    None: on for a three-axis mill, off for five-axis machines and lathes (``arcs_default``). ``output_mode``: "joint"
    (the commanded joints) or "tcp" (their nominal forward kinematics in the control's tool-centre-point frame,
    ``.tcp``); None: the machine file's ``[kinematics] output_mode`` (default joint).

    Each of the report's warnings (a block left uncompensated, a value assumed) is also issued as a
    :class:`PostWarning` (``warnings.warn``): a host that passes no ``report`` sees them, and can turn them into
    errors with the ``warnings`` filters."""
    machine = machine_of(machine)
    text, source = _read_input(program, source)
    the_setup = resolve_setup(machine, setup=setup, var=var, tool_table=tool_table, machine_units=machine_units,
                              offsets_zero=offsets_zero)
    out, rep = post_text(text, machine, mode, tol_um=tol_um, max_correction_mm=max_correction_mm,
                         singular_deg=singular_deg, conditions=conditions,
                         passthrough_unsupported=passthrough_unsupported, source=source,
                         cl_feed_mm_min=cl_feed_mm_min, cl_branch=cl_branch, setup=the_setup, header=header,
                         force=force, arcs=arcs, output_mode=output_mode)
    if report is not None:
        report.update(rep.as_dict())
    for said in rep.warnings:
        warnings.warn(said, PostWarning, stacklevel=2)
    return out


def machine_of(machine) -> Machine:
    """The machine a host names: a :class:`Machine` as it is; a machine file's path or a fixture machine's short name
    (str or os.PathLike) read as the command line reads ``--machine`` (``resources.machine_file``, then
    ``load_machine``). Raises TypeError naming what is accepted for anything else."""
    if isinstance(machine, Machine):
        return machine
    if isinstance(machine, (str, os.PathLike)):
        return load_machine(machine_file(os.fspath(machine)))
    raise TypeError(f"machine: a Machine (trueaxis.machine.load_machine), a machine file's path or a fixture machine's "
                    f"short name (str or Path); got {type(machine).__name__}")


class PostWarning(UserWarning):
    """What the post says of a program it wrote anyway (``file:line: message``; the report's ``warnings``)."""


def resolve_setup(machine: Machine, *, setup=None, var=None, tool_table=None, machine_units: str = "mm",
                  offsets_zero: bool = False):
    """The :class:`Setup` from the files given (a setup file path or a Setup object in ``setup``), else from the
    machine file's default setup file (``[machine] setup``); with ``offsets_zero`` as the user said."""
    from ..nc.setup import Setup, load_setup

    if isinstance(setup, Setup):
        out = setup
        if var is not None or tool_table is not None:
            out = load_setup(var=var, tool_table=tool_table, machine_units=machine_units).merged(out)
        out.offsets_zero = out.offsets_zero or bool(offsets_zero)
        return out
    if setup is None and var is None and tool_table is None and getattr(machine, "setup", ""):
        setup = machine.setup
    return load_setup(var=var, tool_table=tool_table, setup_file=setup, machine_units=machine_units,
                      offsets_zero=offsets_zero)


def decode_program(data: bytes, source: str) -> tuple[str, str]:
    """(text, encoding) of a program file's bytes: NUL bytes refused; UTF-8, else Latin-1 (a byte per character: an
    ISO 8859-1 or Windows file's comments read as written, and written back in it: ``encoding``)."""
    if b"\x00" in data:
        raise PostError(source, 1, "binary data (NUL bytes): not G-code")
    try:
        return data.decode("utf-8"), "utf-8"
    except UnicodeDecodeError:
        return data.decode("latin-1"), "latin-1"


def _read_input(program, source):
    if isinstance(program, Path) or (isinstance(program, str) and "\n" not in program and Path(program).is_file()):
        path = Path(program)
        return decode_program(path.read_bytes(), str(path))[0], source or str(path)
    if not isinstance(program, str):
        raise TypeError(f"program must be G-code text or a path, got {type(program).__name__}")
    one_line = program.strip()
    if "\n" not in one_line and Path(one_line).suffix.lower() in _PROGRAM_SUFFIXES and " " not in one_line:
        # a file's name, not a program (read as G-code it said "word 'n' with no number"): the file is not there
        raise FileNotFoundError(f"{one_line}: no such file (the program is given as its text or its path)")
    return program, source or "<string>"


# The names of program files a string that is not a file may be meant as (``_read_input``).
_PROGRAM_SUFFIXES = {".ngc", ".nc", ".tap", ".gcode", ".cnc", ".txt", ".csv", ".apt", ".cls", ".cl"}


def _fewer_collections(fn):
    """``fn`` with Python's cyclic garbage collector looking at young objects every 100,000 allocations instead of
    every 700 (the thresholds put back after): a long post makes millions of small containers (rows, arcs, words)
    and makes no cycles worth collecting early, and each full collection walks every live one (0.5 s CPU of a
    million-block three-axis post)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        before = gc.get_threshold()
        if 0 < before[0] < 100_000:
            gc.set_threshold(100_000, *before[1:])
        try:
            return fn(*args, **kwargs)
        finally:
            gc.set_threshold(*before)

    return wrapper


@_fewer_collections
def post_text(text: str, machine: Machine, mode: str = "geometric", *, tol_um: float = 1.0,
              max_correction_mm: float = 0.5, singular_deg: float = 1.0, conditions: dict | None = None,
              passthrough_unsupported: bool = False, source: str = "<string>", cl_feed_mm_min: float | None = None,
              cl_branch="nearest", setup=None, header: bool = True, force: bool = False,
              arcs: bool | None = None, output_mode: str | None = None) -> tuple[str, PostReport]:
    """Compensate program text (G-code or CL data, told apart by content); returns (text, report).

    CL data (``GOTO/`` lines, or a CSV header naming x,y,z,i,j,k) first become machine-axis G-code through the
    machine's inverse kinematics (``cl.cl_program``: linearised within tol_um / 2 of the CL segments), which is then
    compensated within tol_um / 2, so the actual path stays within tol_um of the CL segments. Errors and the singular
    blocks of the report then name lines of the CL file.

    ``setup``: the control's setup (:class:`~trueaxis.nc.setup.Setup`; None: none given). A work offset, G92
    shift or tool length the program uses and the setup does not give is refused (``setup.offsets_zero``: zero).
    ``header``: the output starts (after a leading ``%`` and program number) with a comment naming the machine, the
    mode and the setup, and one line per offset and tool length used with where it came from.
    ``force``: post a program that already carries that header (it was compensated already: refused otherwise)."""
    if not force:
        _refuse_posted(text, source)
    refuse_other_machine(text, source, machine)
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}; got {mode!r}")
    if not (math.isfinite(tol_um) and tol_um > 0):
        raise ValueError(f"tolerance must be a finite number > 0, got {tol_um} um")
    if tol_um < MIN_TOL_UM:  # not a promise the written program can keep (6 blocks became 33,945, in a QA pass)
        raise ValueError(f"tolerance {tol_um:g} um is below what a written program holds: the numbers round at "
                         f"{WRITE_ROUNDING_UM:g} um and the solve stops at {SOLVE_TOL_UM:g} um; give at least "
                         f"{MIN_TOL_UM:g} um")
    if not (math.isfinite(max_correction_mm) and max_correction_mm > 0):  # NaN would switch the safety bound off
        raise ValueError(f"the largest correction allowed must be a finite number > 0, got {max_correction_mm} mm")
    if not (math.isfinite(singular_deg) and 0 <= singular_deg <= 90):
        raise ValueError(f"the singular tilt must be within [0, 90] deg, got {singular_deg}")
    output_mode = output_mode or getattr(machine, "output_mode", "joint")
    if output_mode != "joint":
        from .tcp import OUTPUT_MODES, check_tcp_machine

        if output_mode not in OUTPUT_MODES:
            raise ValueError(f"output mode must be one of {', '.join(OUTPUT_MODES)}; got {output_mode!r}")
        check_tcp_machine(machine)
    from ..nc.cl import cl_format

    if cl_format(text) is None and (cl_feed_mm_min is not None or cl_branch not in ("nearest", None)):
        raise ValueError(f"{source}: the CL options (a CL feed, a tilt branch) apply to CL data; this is G-code")
    if cl_format(text) is not None:
        out, rep = _post_cl(text, machine, mode, tol_um=tol_um, max_correction_mm=max_correction_mm,
                            singular_deg=singular_deg, conditions=conditions, source=source,
                            feed_mm_min=cl_feed_mm_min, branch=cl_branch, setup=setup, output_mode=output_mode)
        return (with_header(out, rep, machine) if header else out), rep
    from ..nc.setup import Setup, SetupError

    setup = setup if setup is not None else Setup()
    prog = parse_program(text, source, passthrough_unsupported=passthrough_unsupported, setup=setup,
                         require_setup=True, machine=machine)
    _refuse_units_not_stated(prog, setup, source)
    if setup.program_units is not None and prog.units != setup.program_units and len(prog):
        raise SetupError(f"{source}: the program is in {prog.units} ({'G20' if prog.units == 'inch' else 'G21'}), "
                         f"the setup ({setup.describe()}) is for programs in {setup.program_units}")
    rep = PostReport(source=source, machine=machine.name, mode=mode, tol_um=tol_um, output_mode=output_mode)
    rep.setup = setup.describe()
    rep.setup_used = prog.setup_used
    rep.blocks_in = len(prog.lines)
    rep.passthrough = [{"line": ln, "reason": r} for ln, r in prog.unsupported]
    rep.warnings = list(prog.warnings) + ([] if mode == "none" else _inputs_warnings(prog, machine, source))
    _check_axes(prog, machine, source)
    if prog.units != "mm":
        rep.units_note = (f"program in {prog.units} (G20); converted to mm for the {machine.name} model and back to "
                          "program units for output")
    # Nothing to compensate: mode none, no motion, or only G28/G30/G53 moves (machine positions, passed through).
    if mode == "none" or not np.isin(prog.kind, (ROW_PROGRAMMED, ROW_CYCLE)).any():
        rep.blocks_out = rep.blocks_in
        out = text
        if mode != "none":  # (the G28 / G30 / G53 moves said, none of them corrected)
            poster = _Poster(prog, machine, mode, tol_um, max_correction_mm, singular_deg, conditions, rep)
            poster.note_passed_through(error=output_mode != "tcp")
    else:
        _refuse_rewritten_tool_offset_words(prog, source)
        poster = _Poster(prog, machine, mode, tol_um, max_correction_mm, singular_deg, conditions, rep)
        poster.fit_arcs = arcs_default(machine) if arcs is None else bool(arcs)
        # the setup's tool diameters (mm): a cut's tool as the control knows it, before the machine file's tool
        poster.tool_diameters = {int(t): float(o.diameter) for t, o in getattr(setup, "tools", {}).items()
                                 if getattr(o, "diameter", None)}
        if output_mode == "tcp":
            from .tcp import TcpFrame, tcp_lines

            poster.tcp, poster.fit_arcs = TcpFrame(poster.twin, machine), False
            prog.lines = tcp_lines(prog, machine, source)  # the program's G43 H.. made the control's TCP code
        out, rep = poster.run()
        _refuse_long_lines(out, prog, source)
        if arcs and rep.arcs_linearised and (poster.orientation or poster.tcp is not None):
            # asked for and never done on such a program: said (it was silent); elsewhere the summary's count says
            # how many arcs a check or the G91 / G93 rule left as lines
            rep.warnings.append(_arcs_not_fitted_warning(source, rep.arcs_linearised, poster))
    if header:
        out = with_header(out, rep, machine)
    return out, rep


# LinuxCNC reads lines of at most 255 characters ("Command too long"; rs274ngc's LINELEN): a program with a longer one
# is refused whole.
MAX_LINE = 255
# A rewritten block grows by its axis words' digits (at most some 16 characters each, six axes): an input whose
# lines are all shorter than MAX_LINE less this cannot give a longer line (the header lines are shortened to fit).
_LINE_GROWTH = 100


def _refuse_units_not_stated(prog, setup, source: str):
    """A position before the program states G20 / G21 is read in mm; a control starts in its start-up units
    (LinuxCNC: its machine units, unless its start-up code says G20 / G21). Refused where the user said the control is
    in inches (``--machine-units inch`` with its files) or the setup is for inch programs: on an inch control a
    program without G20 came out corrected as if in mm, exit 0 (``Y3`` -> ``Y2.98107``, 481 um off as the control
    reads it; a QA pass)."""
    stated = prog.modes_stated.get("units")
    axis = ((prog.kind == ROW_PROGRAMMED) | (prog.kind == ROW_CYCLE)) & \
        ((prog.words.astype(np.int64) & _AXIS_WORDS) != 0)
    first = int(np.argmax(axis)) if axis.any() else None
    if first is None or (stated is not None and stated <= int(prog.line_index[first])):
        return
    line = int(prog.line_no[first])
    if setup.machine_units == "inch":
        raise PostError(source, line, "a position before the program states its units (G20 / G21), for a control "
                        "whose machine units are inches (--machine-units inch): the control reads it in its start-up "
                        "units (LinuxCNC: its machine units, or its start-up code's G20 / G21), which the post does "
                        "not assume; state G20 or G21 before the first move")
    if setup.program_units == "inch":
        from ..nc.setup import SetupError

        raise SetupError(f"{source}:{line}: a position before the program states its units (G20 / G21), read as mm, "
                         f"and the setup ({setup.describe()}) is for programs in inch: state G20 before the first move")


def passed_through_warnings(prog, rows, error_um=None) -> list[str]:
    """The warnings for the moves a post passes through as written because their positions are the machine's, one
    per kind, naming its lines: G53 moves (machine coordinates; a feed move among them cuts uncorrected) and G28 /
    G30 returns (their intermediate point and the home position). ``rows`` (K,): those rows of ``prog``;
    ``error_um`` (K,): how far each leaves the tool tip from its nominal position (NaN: not known; None: not said),
    the largest said with its line."""
    out = []
    for kind in (ROW_MACHINE, ROW_REFERENCE):
        pick = prog.kind[rows] == kind
        if not pick.any():
            continue
        lines = sorted({int(n) for n in prog.line_no[rows[pick]]})
        shown = ", ".join(str(n) for n in lines[:5]) + (f" and {len(lines) - 5} more" if len(lines) > 5 else "")
        many = "s" if len(lines) > 1 else ""
        if kind == ROW_MACHINE:
            what = f"{len(lines)} G53 move{many} (machine coordinates; lines {shown})"
        else:
            codes = {c for li in np.unique(prog.line_index[rows[pick]])
                     for c in re.findall(r"(?i)G0*(28|30)(?![.\d])", prog.lines[li])}
            what = (f"{len(lines)} {' / '.join(f'G{c}' for c in sorted(codes)) or 'G28 / G30'} block{many} (moves "
                    f"to an intermediate point and to the home position; lines {shown})")
        tail = ""
        err = None if error_um is None else error_um[pick]
        if err is not None and np.isfinite(err).any():
            k = int(np.nanargmax(err))
            tail = f", up to {err[k]:.2f} um (line {int(prog.line_no[rows[pick][k]])})"
            tail += "" if np.isfinite(err).all() else " where the position is known"
        out.append((lines[0], f"{prog.source}:{lines[0]}: {what} passed through uncompensated: the twin's error is "
                              f"not corrected there{tail}"))
    return [text for _, text in sorted(out)]


def _inputs_warnings(prog, machine: Machine, source: str) -> list[str]:
    """What the post says of its inputs before any work: error values no machine tool has (a unit slip?), and a
    program that selects no work system posted without a setup."""
    out = []
    large = implausible_parameters(machine)
    if large:
        out.append(f"{source}:1: the twin {machine.name}: {large}")
    assumed = next((u for u in prog.setup_used if u.get("assumed")), None)
    if assumed is not None:
        # said on stderr too, not only in the output's header: the control's active system may well have an offset
        out.append(f"{source}:{assumed['first_line']}: no work offset given: the program selects no work "
                   "system and no setup was given (--var, --setup; --offsets-zero to confirm zero), so its "
                   "coordinates are taken as machine coordinates; with an offset in the control's active "
                   "system (G54 at start-up) every correction is computed at the wrong place")
    return out


def _refuse_long_lines(out: str, prog, source: str):
    """PostError naming the input line when a line of the output is longer than LinuxCNC reads (a block near the
    limit that the rewritten words lengthen): a program the control refuses is not written."""
    if max(map(len, prog.lines), default=0) <= MAX_LINE - _LINE_GROWTH:  # (30 ms at a million lines)
        return
    out_lines = out.splitlines()
    long = [j for j, line in enumerate(out_lines) if len(line) > MAX_LINE]
    if not long:
        return
    line = out_lines[long[0]]
    # the input line it comes from: the one with the same comment (the usual cause), else the output's line is named
    cut = min((i for i in (line.find("("), line.find(";")) if i >= 0), default=-1)
    tail = line[cut:] if cut >= 0 else None
    where = next((i + 1 for i, text in enumerate(prog.lines) if tail and tail in text), None)
    said = "" if where is not None else f" (line {long[0] + 1} of the output)"
    raise PostError(source, where or 1, f"the compensated block{said} is {len(line)} characters long, over the "
                                        f"{MAX_LINE} LinuxCNC reads (it refuses the whole program): shorten its "
                                        "comment; nothing written")


def tool_offsets_in_force(prog) -> list[dict]:
    """The program's tool length offsets other than zero (its ``setup_used`` entries of tools), each with ``said``:
    "tool 1 offset Z63.5 mm" (every component given, a lathe's X too)."""
    return [{**u, "said": f"{u['what']} " + " ".join(f"{a}{v:g}" for a, v in zip("XYZ", u["values_mm_deg"]) if v)
             + " mm"} for u in prog.setup_used if u["what"].startswith("tool") and any(u["values_mm_deg"][:3])]


def arcs_default(machine: Machine) -> bool:
    """Whether arcs are fitted (``compensate(arcs=None)``): on a three-axis mill; not on a machine with rotary axes
    (its programs' arcs may turn a rotary axis, which the fit does not model) nor on a lathe (its loads follow the
    direction of motion along the arc: fitted arcs there are an option, ``arcs=True``)."""
    return machine.kind == "mill" and not machine.rotary_axes


def _arcs_not_fitted_warning(source: str, n: int, poster) -> str:
    """The warning for ``n`` arcs written as straight pieces although fitted arcs were asked for (``arcs=True``)."""
    if poster.tcp is not None:
        why = "TCP output writes straight pieces only (the control turns an arc's plane with the table)"
    else:
        why = ("arcs are fitted only where the tool orientation is not corrected (on this machine the correction "
               "turns the rotary axes along the arc, which a G2 / G3 block cannot carry)")
    return (f"{source}:1: --arcs: {n} arc{'s' if n != 1 else ''} written as straight pieces: {why}; the output is "
            "corrected all the same")


def _refuse_posted(text: str, source: str):
    """PostError when ``text`` carries the header of a trueaxis post, or a setup comment saying ``trueaxis program``
    compensated it (``programs.compensated_already``: the slot block's sections are posted without a post header):
    compensating it again would apply the correction twice."""
    from .programs import compensated_already

    at = text.find(HEADER_TAG)
    if at < 0:
        said = compensated_already(text)
        if said is not None:
            raise PostError(source, said[1], f"the program was compensated by trueaxis already (its setup comment "
                                             f"says {said[0][:160]}): posting it again would compensate it twice; "
                                             "--force to post it anyway")
        return
    line_no = text.count("\n", 0, at) + 1
    end = text.find(")", at)
    raise PostError(source, line_no, f"the program was posted by trueaxis already ({text[at:end + 1][:160]}): "
                                     "posting it again would compensate it twice; --force to post it anyway")


def refuse_other_machine(text: str, source: str, machine: Machine, use: tuple = ("this post is for", "post")):
    """PostError when the program's header says it was written for another machine (``programs.written_for``): its
    axis words are that machine's joints, which this machine's kinematics turns into another tool path (a cone for
    the NMV 1500 DCG posted for another B-C table: its nominal tip 7.4 mm off, in a QA pass). ``use``: what is done
    with the program on ``machine``, for the message: (the words before the machine's name, the verb) (the virtual
    shop's: ("this simulation is of", "simulate"))."""
    from .programs import header_name, written_for

    posted = written_for(text)
    if posted and posted[0] != header_name(machine):
        raise PostError(source, posted[1], f"the program was written for the machine {posted[0]!r}, {use[0]} "
                                           f"{header_name(machine)!r}: its axis words are that machine's joints; "
                                           f"{use[1]} the program written for this machine (or remove this line)")


def machine_fingerprint(machine: Machine) -> str:
    """"FILE sha256 HASH": the machine file and the first 12 hex digits of the SHA-256 of its bytes (of the machine's
    complete dump when it was not read from a file)."""
    import hashlib

    path = Path(machine.source)
    if machine.source not in ("", "<string>", "<memory>") and path.is_file():
        return f"{machine.source} sha256 {hashlib.sha256(path.read_bytes()).hexdigest()[:12]}"
    from ..machine.machine_file import dump_machine

    digest = hashlib.sha256(dump_machine(machine).encode("utf-8")).hexdigest()[:12]
    return f"{machine.source} [not a file; its dump] sha256 {digest}"


HEADER_TAG = "(trueaxis post: "


def read_post_header(text: str) -> dict | None:
    """What a trueaxis post's header (``header_lines``) says of a program: {"mode", "machine", "sha256" (the
    machine file's, 12 hex digits, or None)}; None for a program no trueaxis post wrote."""
    head = text[:20_000]
    m = re.search(r"^\(trueaxis post: trueaxis [^,]*, mode (\w+)(?:, output [^,]*)?, machine (.*)\)[ \t]*\r?$", head,
                  re.MULTILINE)
    if m is None:
        return None
    fp = re.search(r"^\(trueaxis post: machine file .* sha256 ([0-9a-f]{12})\)[ \t]*\r?$", head, re.MULTILINE)
    return {"mode": m.group(1), "machine": m.group(2).strip(), "sha256": fp.group(1) if fp else None}


def header_lines(rep: PostReport, machine: Machine) -> list:
    """The output's header comment lines (without line endings): the post, its machine, mode and setup, then every
    offset and tool length the program used with where it came from. Parentheses in names become brackets."""
    def clean(text):
        return str(text).replace("(", "[").replace(")", "]")

    from .. import __version__

    tcp = ", output tcp [tool centre point]" if rep.output_mode == "tcp" else ""
    lines = [f"{HEADER_TAG}trueaxis {__version__}, mode {rep.mode}{tcp}, machine {clean(machine.name)})",
             f"{HEADER_TAG}machine file {clean(machine_fingerprint(machine))})"]
    lines += [f"{HEADER_TAG}setup {clean(part)})" for part in rep.setup.split(", ")]
    for u in rep.setup_used:
        if u.get("assumed"):
            lines.append(f"(trueaxis setup: no work offset: {u['source']})")
            continue
        vals = u["values_mm_deg"]
        words = " ".join(f"{a}{write_number(v, 4)}" for a, v in zip("XYZABC", vals) if v != 0.0) or "0"
        rot = f" R{write_number(u['rotation_deg'], 4)}" if u.get("rotation_deg") else ""
        units = "mm, deg" if rot or any(vals[3:]) else "mm"
        how = f" by {u['applied_by']}" if u.get("applied_by") else ""
        absent = " ".join(u.get("zero_no_such_axis", ""))
        absent = f"; {absent} not given, 0: the machine has no {absent} axis" if absent else ""
        lines.append(f"(trueaxis setup: {u['what']} {words}{rot} {units}{how}, from {clean(u['source'])}{absent})")
    # Every comment's text without parentheses of its own (what and how words such as "tool offset (G43.1)" too):
    # LinuxCNC refuses a nested comment, the whole program.
    return [_fit("(" + clean(line[1:-1]) + ")") for line in lines]


def _fit(comment: str, limit: int = 250) -> str:
    """A comment line shortened in its middle to ``limit`` characters (LinuxCNC refuses lines of 256 and more)."""
    if len(comment) <= limit:
        return comment
    keep = (limit - 3) // 2
    return comment[:keep] + "..." + comment[len(comment) - (limit - 3 - keep):]


def with_header(text: str, rep: PostReport, machine: Machine) -> str:
    """``text`` with ``header_lines`` inserted after its leading ``%`` / program number lines, in its line endings."""
    pos = program_start(text)
    first = text[:4096].splitlines(keepends=True)[0] if text else "\n"
    ending = "\r\n" if first.endswith("\r\n") else "\n"
    lines = header_lines(rep, machine)
    rep.blocks_out += len(lines)
    rep.header_blocks = len(lines)
    return text[:pos] + "".join(line + ending for line in lines) + text[pos:]


def without_header(text: str) -> str:
    """``text`` with the lines ``with_header`` put in taken out (for comparing outputs with what the post wrote
    before it had a header)."""
    return "".join(line for line in text.splitlines(keepends=True)
                   if not line.startswith(("(trueaxis post: ", "(trueaxis setup: ")))


def _post_cl(text, machine, mode, *, tol_um, max_correction_mm, singular_deg, conditions, source, feed_mm_min,
             branch, setup=None, output_mode="joint"):
    from ..nc.cl import ClError, cl_program, read_cl

    try:
        cl = read_cl(text, source)
        gcode, line_map = cl_program(cl, machine, tol_um=tol_um / 2, feed_mm_min=feed_mm_min, branch=branch)
    except ClError as exc:  # the post refuses bad CL data like any refused input
        raise PostError(exc.source, exc.line_no, exc.reason) from exc
    try:
        out, rep = post_text(gcode, machine, mode, tol_um=tol_um / 2, max_correction_mm=max_correction_mm,
                             singular_deg=singular_deg, conditions=conditions, source=source, header=False,
                             setup=setup, output_mode=output_mode)  # LOADTL's tool: its length from the setup
    except GcodeError as exc:
        line = line_map[min(max(exc.line_no, 1), len(line_map)) - 1]
        raise PostError(source, line, f"{exc.reason} (CL point; line {exc.line_no} of the machine-axis program "
                                      "made from it)") from None
    # the warnings name the CL file's lines, as the refusals do (they named the machine-axis program's lines as the
    # CL file's: "gohome.apt:8" in a 5-line file, a QA pass)
    at = re.compile("^" + re.escape(source) + r":([0-9]+): ")
    for k, w in enumerate(rep.warnings):
        m = at.match(w)
        if m:
            line = line_map[min(max(int(m.group(1)), 1), len(line_map)) - 1]
            rep.warnings[k] = (f"{source}:{line}: {w[m.end():]} (CL point; line {m.group(1)} of the machine-axis "
                               "program made from it)")
    rep.tol_um = tol_um
    rep.input_format = f"cl-{cl.format}"
    rep.cl_points = len(cl)
    rep.cl_program_blocks = len(line_map)
    rep.blocks_in = len(text.splitlines())
    rep.singular_blocks = sorted({line_map[ln - 1] for ln in rep.singular_blocks})
    rep.singular_block_count = len(rep.singular_blocks)
    return out, rep


def _check_axes(prog: Program, machine: Machine, source: str):
    for letter in prog.axes_present:
        if letter not in machine.axes:
            col = AXES.index(letter)
            rows = np.nonzero(prog.end[:, col] != 0.0)[0]
            line = int(prog.line_no[rows[0]]) if rows.size else 1
            raise PostError(source, line, f"the program moves axis {letter}, which {machine.name} does not have "
                                          f"(its axes: {' '.join(machine.axis_names)})")


def _refuse_rewritten_tool_offset_words(prog: Program, source: str):
    """PostError at a block whose axis words are both G43.1's tool offset and words the post rewrites: a compensated
    move's end (``G1 G43.1 Z-50``: the offset Z-50, then a move to Z-50 under it) or a G92 / G10 L20 it shifts with
    the correction. Rewritten, the words would set the offset too: the block came out as ``G1 G43.1 X10.00275
    Y19.99149 Z-49.99472``, which the control reads as an offset of X 10, Y 20 (the tip 10 and 20 mm off on every
    later move; exit 0). Only programs that apply G43.1 are looked at (``setup_used``), and there only the lines the
    post rewrites."""
    if not any(u.get("applied_by") == "G43.1" for u in prog.setup_used):
        return
    g43_1 = re.compile(r"(?i)G[ \t]*0*43\.10*(?!\d)")
    moved = np.unique(prog.line_index[np.isin(prog.kind, (ROW_PROGRAMMED, ROW_CYCLE))])
    shifted = {li: what for li, _, what in prog.position_sets}
    for li in sorted(set(moved.tolist()) | set(shifted)):
        code, _ = _split_comment(_split_ending(prog.lines[li])[0])
        if g43_1.search(code):
            line = prog.source_line_of(li)
            other, what = (shifted[li], "the offset it sets") if li in shifted else ("a move", "the move's end")
            raise PostError(source, line, f"G43.1 and {other} in one block: its axis words are G43.1's tool offset "
                                          f"as well as {what}, which the post changes by the correction; so written "
                                          "they would change the tool offset too: put G43.1 in a block of its own")


# --------------------------------------------------------------------------------------------------- internals ---


class _PieceWords(NamedTuple):
    """The written pieces of split moves (``_Poster._piece_words``), by index k into the compensated rows."""

    first: dict  # k -> index of the piece's first point into ``words``
    pts: dict  # k -> (n, 6) program coordinates of its pieces' ends
    words: dict | None  # axis letter -> the formatted words of the piece ends the Python writer writes, in order ("":
    # the others, which the compiled writer writes); None: none (``_Poster._piece_texts``)


class _NoBar:
    """The progress bar of a short program: none."""

    def update(self, n):
        pass

    def close(self):
        pass


class _ArcModes:
    """How each compensated arc is written, by index k into the compensated rows: ``kept`` (K,) bool, the arcs kept as
    they are (their end and centre corrected), and ``split`` {k: "fit" | "lines"}, the others (fitted sub-arcs,
    straight pieces). ``get(k)``: "arc", "fit", "lines" or None (not an arc). The kept ones in an array, not a dict: a
    program has hundreds of thousands of them (a dict entry each cost a million-block post 0.4 s)."""

    def __init__(self, n: int):
        self.kept = np.zeros(n, bool)
        self.split: dict = {}

    def get(self, k):
        return "arc" if self.kept[k] else self.split.get(k)


class _WrittenEnd:
    """``written_end[r]`` (K, 6): the end written for the program rows r (K,) (program coordinates): ``end[r] +
    delta`` of the compensated rows ``rows`` (the same sum as in a table of them all), ``end[r]`` itself for the
    others. Asked for the rows it is asked for, not made for every row (a copy of the program's ends, 48 MB at a
    million rows)."""

    def __init__(self, end, n_rows, rows, delta):
        self.end, self.delta = end, delta
        self.k = np.full(n_rows, -1, np.int64)
        self.k[rows] = np.arange(rows.size)

    def correction(self, r):
        """(K, 6) the correction written at rows r (K,): ``self[r] - end[r]`` (zero for rows not compensated), as
        the written end minus the nominal one, the numbers every user of it has taken."""
        r = np.asarray(r)
        return self[r] - self.end[r]

    def __getitem__(self, r):
        r = np.asarray(r)
        out = self.end[r]  # (a new array)
        k = self.k[r]
        has = k >= 0
        if has.all():  # (as a rule: the same sums, without picking the rows out first)
            out += self.delta[k]
        else:
            out[has] += self.delta[k[has]]
        return out


class _ChunkEnd(threading.Event):
    """The written end of a chunk's last move, ``value`` (row, (6,) end) once set (None: the chunk stopped)."""

    value = None


class _ChunkAborted(Exception):
    """A chunk whose chunk before stopped with an error (which is the one raised)."""


class _Poster:
    def __init__(self, prog, machine, mode, tol_um, max_corr, singular_deg, conditions, rep):
        self.p = prog
        self.m = machine
        self.mode = mode
        self.tol_mm = tol_um * 1e-3
        self.tol_rad = max(tol_um, 1.0) * 1e-6  # orientation tolerance: 1 urad per um of position tolerance
        self.solve_tol_um = min(SOLVE_TOL_UM, tol_um / 10)
        self.max_corr = max_corr
        self.singular = np.radians(singular_deg)
        self.conditions = conditions or {}
        self.tool_diameters = {}
        self.rep = rep
        self.twin = ErrorTwin(machine)
        if machine.kind == "lathe" and mode == "comprehensive":
            from .turning import MotionTwin  # a lathe's loads carry each axis' direction of motion (see .turning)

            self.twin = MotionTwin(self.twin)
        self.names = machine.axis_names
        self.cols = [AXES.index(a) for a in self.names]
        self.orientation = any(a in prog.axes_present for a in machine.rotary_axes)
        self.rotary_columns = [j for j, a in enumerate(self.names) if machine.axes[a].is_rotary]
        self.word_sign = machine.word_signs()  # [kinematics] rotary_sense: -1 for LinuxCNC trt rotary words
        self.inch_rows = prog.inch
        self.stats = {"um": 0.0, "urad": 0.0, "urad_singular": 0.0, "singular_points": 0, "singular_lines": set()}
        self.fractions = {}  # program row -> piece boundaries (fractions of the move) of split moves
        self.fit_arcs = False  # arcs fitted to the corrected path (.arcs); set by post_text
        self._cycle_warned = False  # (the canned cycles' deviation is warned about once)
        self.arc_centres = {}  # program row -> (n, 3) centres (program coordinates) of a fitted arc's sub-arcs
        # chunks compensated side by side (``_compensate_chunks``): the report's sums and maxima under the lock, a
        # chunk's warnings and its own values (``_local``: the chunk before's end, its notes) kept in chunk order;
        # every ``_compensate`` runs inside a ``_chunk``
        self._lock = threading.RLock()
        self._local = threading.local()
        self.tcp = None  # TCP output (.tcp.TcpFrame): positions for the control's own nominal kinematics
        self._newton_hint = {}  # solve_commanded's hint: where its Newton steps evaluate the pose before the Jacobian

    # --- coordinates ------------------------------------------------------------------------------------------------
    def to_machine(self, prog6, inch):
        """(K,6) program-unit machine coordinates -> (K, n_axes) mm / rad."""
        q = prog6[:, self.cols].copy()
        for j, a in enumerate(self.names):
            if self.m.axes[a].is_rotary:
                q[:, j] = np.radians(q[:, j]) * self.word_sign[j]
            else:
                q[:, j] = np.where(inch, q[:, j] * MM_PER_INCH, q[:, j])
        return q

    def to_program_delta(self, dq, inch, prog_rows):
        """(K, n_axes) correction mm / rad of the program rows ``prog_rows`` (K,) -> (K, 6) program units (inch or
        mm, degrees), in the rows' work system (its XY rotation undone)."""
        out = np.zeros((dq.shape[0], 6))
        for j, a in enumerate(self.names):
            if self.m.axes[a].is_rotary:
                out[:, self.cols[j]] = np.degrees(dq[:, j]) * self.word_sign[j]
            else:
                out[:, self.cols[j]] = np.where(inch, dq[:, j] / MM_PER_INCH, dq[:, j])
        return self.p.to_program_delta(out, prog_rows)

    def command_delta(self, q_cmd, q_nom):
        """(K, n_axes) mm / rad written in place of the nominal joints: the correction q_cmd - q_nom, or in TCP output
        the commanded joints' TCP position less the nominal joints (``tcp.TcpFrame.command_delta``)."""
        return q_cmd - q_nom if self.tcp is None else self.tcp.command_delta(q_cmd, q_nom)

    # --- forces --------------------------------------------------------------------------------------------------
    def forces(self, rows, direction, q):
        """(K,3) N force on the tool for the given rows with feed directions (K,3) in the machine frame, at the
        rows' poses q (K, n_axes): the feed frame has z along the tool axis in the machine frame (machine Z on a
        three-axis mill and a table-table machine, turned by the head on a head machine) and x along the feed
        direction normal to it."""
        if self.mode != "comprehensive":
            return None
        if self.m.kind == "lathe":
            from .turning import lathe_loads  # Kienzle's turning force and the direction of motion (see .turning)

            return lathe_loads(self, rows)
        if not self.m.cutting:
            raise PostError(self.p.source, 1, f"comprehensive mode needs the [cutting] coefficients in {self.m.source}")
        coeffs = CuttingCoefficients.from_mapping(self.m.cutting)
        conds = self._conditions_per_line()
        K = len(rows)
        F = np.zeros((K, 3))
        # Tool axis in the machine frame: the part-frame tool axis turned back by the workpiece branch.
        tool_axis = np.einsum("nji,nj->ni", machine_to_part_rotation(self.m, q), self.twin.nominal_pose(q)[1])
        horiz = direction - np.einsum("ni,ni->n", direction, tool_axis)[:, None] * tool_axis
        norm = np.linalg.norm(horiz, axis=1)
        cutting = (self.p.motion[rows] != RAPID) & (norm > 1e-9)
        groups: dict = {}
        for k in np.nonzero(cutting)[0]:
            li = int(self.p.line_index[rows[k]])
            c = conds(li)
            if c is None:
                lack = " ".join(self._missing_conditions.get(li, []))
                raise PostError(self.p.source, int(self.p.line_no[rows[k]]),
                                f"comprehensive mode needs cutting conditions here ({lack} not given): put "
                                "(trueaxis: ap=.. ae=.. fz=.. n=.. d=.. z=.. mode=down) before the cut, or give them "
                                "on the command line")
            groups.setdefault(c, []).append(k)
        for key, ks in groups.items():
            self._say_conditions(dict(key), int(self.p.line_no[rows[ks[0]]]))
            cond = CuttingConditions.from_mapping(dict(key))
            f_feed = mean_force(coeffs, cond)
            ks = np.asarray(ks)
            x = horiz[ks] / norm[ks, None]
            z = tool_axis[ks]
            y = np.cross(z, x)
            F[ks] = f_feed[0] * x + f_feed[1] * y + f_feed[2] * z
        return F

    def _say_conditions(self, used: dict, line_no: int):
        """Record a set of cutting conditions in the report (once), with a warning for the milling mode when neither
        the program nor the caller gave it (down milling is taken then: up milling turns the feed-normal force's
        sign, and the corrections differed by a factor of two in a QA pass)."""
        with _REPORT_LOCK:  # the chunks of moves run on two threads
            if any(c["conditions"] == used for c in self.rep.cutting_conditions):
                return
            source, carried = self._condition_sources.get(tuple(sorted(used.items())), ({}, {}))
            assumed = [] if "mode" in used else ["mode=down"]
            self.rep.cutting_conditions.append({"conditions": used, "first_line": line_no, "assumed": assumed,
                                                "from": source, "carried": carried})
            if assumed:
                self.rep.warnings.append(f"{self.p.source}:{line_no}: comprehensive mode: the milling mode is not "
                                         f"given, down milling assumed (--cut-mode up|down, or mode= in the "
                                         f"(trueaxis: ...) conditions)")
            if carried:
                said = ", ".join(f"{f}={used[f]} from {where}" for f, where in sorted(carried.items()))
                self.rep.warnings.append(f"{self.p.source}:{line_no}: comprehensive mode: the conditions in force "
                                         f"here do not give {' '.join(sorted(carried))}: carried from an earlier "
                                         f"operation's ({said}); give them in this operation's conditions")

    def _conditions_per_line(self):
        """line index -> hashable conditions (tuple of items) valid there, or None."""
        marks = condition_marks(self.p.lines, self.p.source)
        note_inch_conditions(self, marks)
        tool = {"d": str(2 * self.m.tool.radius), "z": str(self.m.tool.flutes)}
        cli = {k: str(v) for k, v in self.conditions.items() if v is not None}
        starts = [i for i, _ in marks]

        tool_at = dict(zip(self.p.line_index.tolist(), self.p.tool.tolist()))  # the tool in the spindle at a line

        def at(line_index):
            merged = dict(tool)
            source = {key: "the machine file's tool" for key in tool}
            t = tool_at.get(line_index)
            if t in self.tool_diameters:  # the setup's tool table: the diameter of the tool that cuts here
                merged["d"], source["d"] = str(self.tool_diameters[t]), f"the setup's tool table (T{t})"
            k = np.searchsorted(starts, line_index, side="right")
            for i, f in marks[:k]:
                merged.update(f)
                source.update({key: f"line {i + 1}" for key in f})
            merged.update(cli)
            source.update({key: "the command line" for key in cli})
            missing = [key for key in ("ap", "ae", "fz") if key not in merged]
            if missing:
                self._missing_conditions[line_index] = missing
                return None
            try:
                CuttingConditions.from_mapping(merged)
            except ValueError as exc:
                raise PostError(self.p.source, line_index + 1, f"cutting conditions: {exc}") from None
            key = tuple(sorted(merged.items()))
            # A field from a comment before the one in force (another operation's, which the latest did not give)
            latest = f"line {marks[k - 1][0] + 1}" if k else None
            carried = {f: where for f, where in source.items() if where.startswith("line ") and where != latest}
            self._condition_sources.setdefault(key, (source, carried))
            return key

        self._missing_conditions, self._condition_sources = {}, {}
        return at

    # --- solving -------------------------------------------------------------------------------------------------
    def _pair(self):
        """(outer, inner) rotary links of a five-axis machine with orientation compensation, else None."""
        if not (self.orientation and self.m.is_five_axis):
            return None
        if not hasattr(self, "_pair_cache"):
            from ..machine.kinematics import _rotary_pair

            try:
                self._pair_cache = _rotary_pair(self.m)
            except NotImplementedError as exc:
                self._pair_cache = None
                self.rep.warnings.append(f"{self.p.source}:1: singular cone not handled for this layout: {exc}")
        return self._pair_cache

    def singular_at(self, q):
        """(K,) bool: nominal poses q (K, n_axes) inside the singular cone, |tilt| < singular_deg, where the outer
        rotary axis hardly turns the tool axis and is held at its nominal value."""
        pair = self._pair()
        if pair is None:
            return np.zeros(q.shape[0], bool)
        return np.abs(np.sin(q[:, pair[1].column])) < np.sin(self.singular)

    def solve(self, q, force, rows, poses=False):
        """Commanded poses for nominal poses q (K, n_axes), and (K,) bool: the free axis was held (singular cone);
        with ``poses`` also (actual tip, axis at the commanded poses, nominal tip, axis at q), which the solve computed
        (the split checks take them instead of evaluating the twin there again: the same numbers).

        Every solve is recorded: its residuals (for the report) and the blocks with points in the singular cone."""
        hold = np.zeros_like(q, bool)
        pair = self._pair()
        if pair is not None:
            hold[:, pair[0].column] = self.singular_at(q)
        held = hold.any(axis=1)  # the singular cone's held free axis
        if not self.orientation:
            # A program without rotary words on a machine with rotary axes: they stay where they are (their position
            # in the program, 0, plus the setup's offset) and are not written; X Y Z alone place the tip.
            hold[:, self.rotary_columns] = True
        res = solve_commanded(self.twin, q, force, orientation=self.orientation, hold=hold,
                              tol_um=self.solve_tol_um, tol_urad=SOLVE_TOL_URAD, hint=self._newton_hint)
        bad = ~res.converged
        if np.any(bad):
            k = int(np.argmax(bad))
            raise PostError(self.p.source, int(self.p.line_no[rows[k]]),
                            f"compensation did not converge (residual {res.position_residual_um[k]:.3g} um,"
                            f" {res.axis_residual_urad[k]:.3g} urad)")
        st = self.stats
        with self._lock:
            st["um"] = max(st["um"], float(res.position_residual_um.max(initial=0.0)))
            if self.orientation:
                st["urad"] = max(st["urad"], float(res.axis_residual_urad[~held].max(initial=0.0)))
                st["urad_singular"] = max(st["urad_singular"], float(res.axis_residual_urad[held].max(initial=0.0)))
            st["singular_points"] += int(held.sum())
            if held.any():  # (line_no is made for the whole program each time it is read)
                st["singular_lines"].update(int(x) for x in self.p.line_no[np.asarray(rows)[held]])
        return (res.q, held, res.actual + res.nominal) if poses else (res.q, held)

    def _clamp_rapids_at_the_limit(self, j, q_nom, q_cmd, rows, out):
        """A rapid whose end the program puts at the limit of axis j (a G28 home at the end of Z's stroke, then an XY
        rapid there) and whose correction would take it past the limit ends at the limit instead (a rapid does not
        cut; the warning says so): such programs were refused for 1.45 um (a QA pass). q_cmd is changed in place;
        returns what is still out of travel."""
        ax = self.m.axes[self.names[j]]
        rapid = (self.p.motion[rows] == RAPID) & ax.within_travel(q_nom[:, j])
        excess = np.minimum(np.abs(q_cmd[:, j] - ax.travel[0]), np.abs(q_cmd[:, j] - ax.travel[1]))
        clamp = out & rapid & (excess <= self.max_corr)
        if not np.any(clamp):
            return out
        q_cmd[clamp, j] = np.clip(q_cmd[clamp, j], ax.travel[0], ax.travel[1])
        k = int(np.argmax(clamp))
        unit, scale = ("urad", 1e6) if ax.is_rotary else ("um", 1e3)
        with _REPORT_LOCK:
            self.rep.warnings.append(f"{self.p.source}:{int(self.p.line_no[rows[k]])}: a rapid at the end of "
                                     f"{self.names[j]}'s travel: its correction ({excess[k] * scale:.3g} {unit} past "
                                     f"the limit) ends at the limit instead ({int(clamp.sum())} such point"
                                     f"{'s' if clamp.sum() > 1 else ''} in this chunk); a rapid does not cut")
        return out & ~clamp

    def check(self, q_nom, q_cmd, rows):
        """Correction bound and travel, per point; raises PostError naming the block."""
        dq = q_cmd - q_nom
        for j, a in enumerate(self.names):
            ax = self.m.axes[a]
            if ax.is_rotary:
                # The bound is in mm: an angular correction counts at a 100 mm lever arm.
                size = np.abs(dq[:, j]) * 100.0
            else:
                size = np.abs(dq[:, j])
            over = size > self.max_corr
            if np.any(over):
                k = int(np.argmax(over))
                unit = "deg" if ax.is_rotary else "mm"
                val = np.degrees(dq[k, j]) if ax.is_rotary else dq[k, j]
                lever = f" ({size[k]:.3g} mm at the 100 mm lever arm the bound counts an angle at)" \
                    if ax.is_rotary else ""
                # (any axis: near the pole a linear axis follows the fast rotary one; with --singular-deg 0 the X
                # correction was blamed on the machine file, a QA pass)
                pair = self._pair() if self.m.is_five_axis else None
                tilt = None if pair is None else float(np.degrees(q_nom[k, pair[1].column]))
                cone = max(5 * self.singular, np.radians(2.0))
                near = "" if tilt is None or abs(np.sin(np.radians(tilt))) > np.sin(cone) else (
                    f"; the tilt there is {tilt:.3g} deg, near the singular cone (--singular-deg "
                    f"{np.degrees(self.singular):g}), where the other rotary axis turns fast: a larger --singular-deg "
                    f"holds it there")
                raise PostError(self.p.source, int(self.p.line_no[rows[k]]),
                                f"correction of {a} is {val:+.4f} {unit}{lever}, above the bound of {self.max_corr} "
                                f"mm{near or f': check the machine file {self.m.source}'}")
            if ax.travel is not None:
                out = ~ax.within_travel(q_cmd[:, j])  # the one travel check
                if np.any(out):
                    out = self._clamp_rapids_at_the_limit(j, q_nom, q_cmd, rows, out)
                if np.any(out):
                    k = int(np.argmax(out))
                    v = np.degrees(q_cmd[k, j]) if ax.is_rotary else q_cmd[k, j]
                    t = np.degrees(ax.travel) if ax.is_rotary else ax.travel
                    word = f" (program word {a}{v * self.word_sign[j]:.6g}, rotary_sense {self.m.rotary_sense})" \
                        if self.word_sign[j] < 0 else ""
                    by = min(abs(v - t[0]), abs(v - t[1])) * (1.0 if ax.is_rotary else 1e3)
                    unit = "deg" if ax.is_rotary else "um"
                    if not ax.within_travel(q_nom[k, j]):  # the program's own position, before any correction
                        nominal = np.degrees(q_nom[k, j]) if ax.is_rotary else q_nom[k, j]
                        said = f" (program word {a}{nominal * self.word_sign[j]:.6g}, rotary_sense " \
                               f"{self.m.rotary_sense})" if self.word_sign[j] < 0 else ""
                        raise PostError(self.p.source, int(self.p.line_no[rows[k]]),
                                        f"{a} = {nominal:.10g}{said} (the program's position, in machine "
                                        f"coordinates) lies outside its travel [{t[0]:g}, {t[1]:g}]: the part or the "
                                        f"program does not fit this machine there")
                    raise PostError(self.p.source, int(self.p.line_no[rows[k]]),
                                    f"corrected {a} = {v:.10g}{word} lies outside its travel [{t[0]:g}, {t[1]:g}]"
                                    f" by {by:.4g} {unit}")

    # --- the run -------------------------------------------------------------------------------------------------
    def known_positions(self):
        """(end known (M,) bool, start known (M,) bool, the axes not known at each row's end (M,) bit mask) of the
        program's rows: an axis' position is known from its first absolute word (G90) on, and from a G28 / G30 that
        homes every axis; before that the control is wherever it stands, and so again after a block that may move it
        where the text does not say (``Program.positions_lost``: a tool change, a probing move passed through). Required
        are the machine's ``required_axes``: its linear axes and the rotary axes the program uses (the rule of the work
        offsets too)."""
        p = self.p
        need = [AXES.index(a) for a in self.m.required_axes(p.axes_present)]
        bits = sum(1 << c for c in need)
        given = np.where(p.incremental, 0, p.words.astype(np.int64) & bits)
        homing = (p.kind == ROW_REFERENCE) & (p.words == 0)
        second = np.r_[False, (p.line_index[1:] == p.line_index[:-1]) & (p.kind[:-1] == ROW_REFERENCE)]
        given = np.where(homing & ~second, bits, given)
        # each row's last loss: the first row of its line or after (a move in the M6 block is made after the change)
        lost_at = np.searchsorted(p.line_index, [li for li, _ in p.positions_lost], side="left")
        since = np.zeros(given.size, np.int64)  # the first row counted for each row: 0, or its last loss' first row
        if lost_at.size and given.size:
            mark = np.zeros(given.size + 1, np.int64)
            np.maximum.at(mark, lost_at, lost_at)
            since = np.maximum.accumulate(mark[:-1])
        have = np.zeros(given.size, np.int64)
        rows = np.arange(given.size)
        for c in need:  # an axis is known where its last absolute word is at or after the row's last loss
            last = np.maximum.accumulate(np.where(given >> c & 1, rows, -1)) if given.size else rows
            have |= np.where(last >= since, 1 << c, 0)
        missing = bits & ~have
        end_known = missing == 0
        return end_known, np.r_[False, end_known[:-1]], missing

    def _refuse_modes_not_stated(self, rows):
        """PostError for what a machine without a Y axis cannot be given as the program reads (QA pass, both exit 0
        before): an arc in the G17 / G19 plane (G17 where the program states none: a lathe control's start-up code
        sets G18, and the arc was written as straight pieces of the XY helix, 2.9 mm off the arc cut), and on a lathe
        an X word before the program says G7 or G8 (the control's start-up mode decides what X means: read as a
        radius, a diameter control lost 3.9 of a 7.3 um correction on every block)."""
        p, m = self.p, self.m
        if "Y" in m.axis_names or rows.size == 0:
            return
        arcs = rows[np.isin(p.motion[rows], (ARC_CW, ARC_CCW)) & (p.arc_plane[rows] != 18)]
        if arcs.size:
            r = arcs[0]
            stated = "" if "plane" in p.modes_stated else " (the program states no plane: G17 is read)"
            raise PostError(p.source, int(p.line_no[r]),
                            f"an arc in the G{int(p.arc_plane[r])} plane{stated} on {m.name}, which has no Y axis: "
                            "its arcs are in G18, which the control's start-up code may set but the program does "
                            "not say; state G18 before the arc")
        x_rows = rows[(p.words[rows].astype(np.int64) & 1) != 0]
        first = p.modes_stated.get("G7/G8")
        if m.kind == "lathe" and x_rows.size and (first is None or p.line_index[x_rows[0]] < first):
            raise PostError(p.source, int(p.line_no[x_rows[0]]),
                            "X is given before the program says G7 (X a diameter) or G8 (a radius): the control's "
                            "start-up mode decides what X means, and the post does not assume it; state G7 or G8 "
                            "before the first move")

    def _lost_since(self, row: int) -> str | None:
        """What made the control's position unknown before ``row`` (``Program.positions_lost``, with its source
        line), or None (the program's start)."""
        p = self.p
        # (appended as the program is read: in line order; a bisection, not a scan per row: a million-block program
        # with 1424 tool changes spent 0.8 s here)
        k = bisect.bisect_right(p.positions_lost, int(p.line_index[row]), key=lambda lost: lost[0])
        if k == 0:
            return None
        li, what = p.positions_lost[k - 1]
        return f"{what} at line {self.p.source_line_of(li)}"

    def run(self):
        p = self.p
        rows = np.nonzero((p.kind == ROW_PROGRAMMED) | (p.kind == ROW_CYCLE))[0]
        self._refuse_cycles_it_cannot_write()
        self._refuse_modes_not_stated(rows)
        # Positions are never invented: a block whose end the program has not yet fixed on every axis (or an arc
        # whose start it has not) keeps its own words, uncompensated, and the report and stderr say so.
        end_known, start_known, missing = self.known_positions()
        self.start_known = start_known
        self._refuse_position_sets_from_unknown(missing)
        unknown = ~end_known[rows] | (np.isin(p.motion[rows], (ARC_CW, ARC_CCW)) & ~start_known[rows])
        if np.any(unknown) and self.tcp is not None:
            r = rows[np.argmax(unknown)]
            lost = self._lost_since(r)
            since = f"since {lost}" if lost else "before"
            raise PostError(p.source, int(p.line_no[r]),
                            f"TCP output: the position of an axis is not known here (no absolute move of it {since}), "
                            "so the block cannot be written as a tool-tip position: give every axis' position first, "
                            "or --output-mode joint")
        if np.any(unknown):
            rows_unknown = rows[unknown]
            bad_lines = np.unique(p.line_index[rows_unknown])
            keep = ~np.isin(p.line_index[rows], bad_lines)
            lines_unknown = p.line_no[rows_unknown]  # (line_no makes the whole program's: once, not per row)
            for r, line in zip(rows_unknown.tolist(), lines_unknown.tolist()):
                if self.rep.uncompensated and self.rep.uncompensated[-1]["line"] == line:
                    continue
                if not int(p.words[r]) & _AXIS_WORDS and p.motion[r] in (RAPID, FEED):
                    continue  # no axis word, no motion ('N110G0G17G40G49G80G90'): as written, nothing to say
                axes = "".join(a for i, a in enumerate(AXES) if int(missing[r]) >> i & 1) or \
                    "".join(a for i, a in enumerate(AXES) if int(missing[r - 1]) >> i & 1 if r > 0)
                lost = self._lost_since(r)
                self.rep.uncompensated.append({"line": line, "axes": axes, **({"since": lost} if lost else {})})
                since = f"since {lost}" if lost else "before"
                self.rep.warnings.append(f"{p.source}:{line}: the position of {' '.join(axes)} is not known here "
                                         f"(no absolute move of it {since}): block left as written, uncompensated")
            rows = rows[keep]
            if rows.size == 0:  # not one move: no compensated program to write (its header would say one)
                r = rows_unknown[0]
                first = self.rep.uncompensated[0] if self.rep.uncompensated else {
                    "line": int(lines_unknown[0]),
                    "axes": "".join(a for i, a in enumerate(AXES) if int(missing[r]) >> i & 1)}
                raise PostError(p.source, first["line"], f"no move can be compensated: the position of "
                                f"{' '.join(first['axes'])} is never known (no absolute move of every axis, or a "
                                f"program for another kind of machine); nothing written")
        self.rep.moves = int(rows.size)
        self._note_block_delete(rows)
        self._note_tool_lengths(rows)
        idle = [a for a in self.names if self.m.axes[a].is_rotary and a not in p.axes_present]
        if idle:
            # a rotary axis the program never commands stands where the control left it, which the post cannot know
            self.rep.warnings.append(f"{p.source}:1: the program never commands {' '.join(idle)}: the corrections take "
                                     f"{'it' if len(idle) == 1 else 'them'} at 0, where "
                                     f"{'it' if len(idle) == 1 else 'they'} must stand when the program runs")
        if self.mode == "comprehensive" and not self.m.force_models():
            # the force is computed, but a twin the same under any load turns it into no correction: said, not silent
            self.rep.warnings.append(f"{p.source}:1: comprehensive mode: the twin of {self.m.name} has no force "
                                     "model (no [force] compliance, no [loaded] parameter set, no response surfaces): "
                                     "nothing is corrected for the cutting force, the program is compensated as in "
                                     "geometric mode")
        delta_prog = np.empty((rows.size, 6))
        pieces, arc_mode = {}, _ArcModes(rows.size)
        sq = np.zeros(len(self.names))
        mx = np.zeros(len(self.names))
        # Moves are independent once their nominal start and end are known: compensate them chunk by chunk, so
        # that memory stays bounded (arcs sample 17 points each) however long the program is.
        chunks = [slice(s, min(rows.size, s + ROW_CHUNK)) for s in range(0, rows.size, ROW_CHUNK)]
        # A bar on long programs, on a terminal only (tqdm's disable=None); tqdm imported only then (36 ms of a small
        # post's start-up, most of it its version look-up through importlib.metadata)
        bar = _NoBar()
        if len(chunks) > 2:
            from tqdm import tqdm

            bar = tqdm(total=rows.size, unit="move", desc="compensating", disable=None, leave=False)
        for sl, (d_prog, dq, pcs, (kept, modes)) in zip(chunks, self._compensate_chunks(rows, chunks)):
            delta_prog[sl] = d_prog
            pieces.update((sl.start + k, v) for k, v in pcs.items())
            arc_mode.kept[sl.start + kept] = True
            arc_mode.split.update((sl.start + k, v) for k, v in modes.items())
            sq += np.sum(dq**2, axis=0)
            mx = np.maximum(mx, np.abs(dq).max(axis=0, initial=0.0))
            bar.update(sl.stop - sl.start)
        bar.close()
        self._summarise(mx, np.sqrt(sq / max(rows.size, 1)))
        self._residual_check()
        self.note_passed_through(rows, delta_prog, end_known, error=self.tcp is None)
        if p.diameter.any():
            from .turning import diameter_words  # G7: X written as a diameter again

            self.p, delta_prog, pieces = diameter_words(p, rows, delta_prog, pieces)
        return self._write(rows, delta_prog, pieces, arc_mode)

    def note_passed_through(self, rows=None, delta_prog=None, end_known=None, error=True):
        """The warnings for the G53 and G28 / G30 moves, passed through as written (``passed_through_warnings``), with
        how far each leaves the tool tip from its nominal position (``error``; not in TCP output, where the
        control's kinematics place those positions). ``delta_prog``: the corrections written for the compensated
        ``rows`` (None: none); ``end_known``: ``known_positions``' first (None: made here)."""
        p = self.p
        special = np.nonzero((p.kind == ROW_REFERENCE) | (p.kind == ROW_MACHINE))[0]
        if special.size == 0:
            return
        error_um = self._passed_through_error_um(special, rows, delta_prog, end_known) if error else None
        self.rep.warnings += passed_through_warnings(p, special, error_um)

    def _passed_through_error_um(self, special, rows, delta_prog, end_known):
        """(K,) um, how far each of the G28 / G30 / G53 rows ``special`` (K,) leaves the tool tip from the nominal
        position of its end, NaN where that position is not known (an axis not given yet, a setup value not given).
        The axes the block sets in machine coordinates or by absolute words (a G53's words, the axes a home moves, a
        G90 intermediate point's words) go where the program says, uncorrected; its other axes stay where the block
        before left them, with the correction written there (carried on through a run of such blocks)."""
        p = self.p
        if end_known is None:
            end_known = self.known_positions()[0]
        written = None if delta_prog is None else self._written_ends(rows, delta_prog, p.kind[rows] == ROW_CYCLE)[0]
        words = p.words[special].astype(np.int64) & 63  # (bits 0-5: X Y Z A B C)
        exact = np.where((p.kind[special] == ROW_REFERENCE) & p.incremental[special], 0, words)
        before = np.maximum(special - 1, 0)
        after_point = (special > 0) & (p.kind[before] == ROW_REFERENCE) & (
            p.line_index[before] == p.line_index[special])  # (a home after its block's intermediate point)
        home = (p.kind[special] == ROW_REFERENCE) & (words == 0)
        exact = np.where(home, np.where(after_point, p.words[before].astype(np.int64) & 63, 63), exact)
        exact = (exact[:, None] >> np.arange(6) & 1).astype(bool)
        carried, c = np.zeros((special.size, 6)), np.zeros(6)
        for k, r in enumerate(special.tolist()):
            if k == 0 or r != special[k - 1] + 1:  # after a row of the program's own: the correction written there
                c = np.zeros(6) if written is None or r == 0 else written.correction([r - 1])[0]
            c = np.where(exact[k], 0.0, c)
            carried[k] = c
        inch = p.inch[special]
        q_written = self.to_machine(p.to_machine(p.end[special] + carried, special), inch)
        q_nominal = self.to_machine(p.to_machine(p.end[special], special), inch)
        error_um = np.linalg.norm(self.twin.actual_pose(q_written)[0] - self.twin.nominal_pose(q_nominal)[0],
                                  axis=1) * 1e3
        not_given = p.machine_rows_not_given if p.machine_rows_not_given is not None else np.zeros(0, np.int64)
        error_um[~end_known[special] | np.isin(special, not_given)] = np.nan
        return error_um

    def _refuse_position_sets_from_unknown(self, missing):
        """PostError for a G92 / G10 L20 that sets its offset from the position of an axis the program has not given
        yet (the control's position when the program starts): the offset, and every machine position after it, would
        be invented (it was taken as set from the program's zero, without a word). ``missing``: ``known_positions``'."""
        p = self.p
        for li, axes, what in p.position_sets:
            r = int(np.searchsorted(p.line_index, li, side="left")) - 1  # the last row before the block
            lost = [AXES[i] for i in axes if r < 0 or int(missing[r]) >> i & 1]
            if lost:
                raise PostError(p.source, self.p.source_line_of(li),
                                f"{what} sets its offset from the position of {' '.join(lost)}, "
                                "which the program has not given before it (the control's position "
                                "when it starts): the offset and every machine position after it "
                                "would be invented; move to an absolute position first, or set the "
                                "offset with G10 L2")

    def _note_tool_lengths(self, rows):
        """A warning when the program runs under tool length offsets: the twin's errors are its reference tool's
        (``[tool] length``, gauge line to tip); a tool whose length differs by d moves the tip by d times the tool
        axis' angular error, which the post does not correct (how the control's tool lengths relate to the reference
        tool is a convention of the shop the post is not told). Said with the size it reaches on this program's
        moves: the largest tool-axis error of the twin there (a sample of at most 4096 of them), per 10 mm."""
        p = self.p
        tools = tool_offsets_in_force(p)
        if not tools or rows.size == 0:
            return
        pick = rows[np.unique(np.linspace(0, rows.size - 1, min(rows.size, 4096)).astype(int))]
        q = self.to_machine(p.to_machine(p.end[pick], pick), p.inch[pick])
        u_act = self.twin.actual_pose(q)[1]
        u_nom = self.twin.nominal_pose(q)[1]
        worst_urad = float(np.linalg.norm(u_act - u_nom, axis=1).max()) * 1e6
        said = ", ".join(u["said"] for u in tools[:3]) + (" ..." if len(tools) > 3 else "")
        self.rep.tool_axis_error_max_urad = worst_urad
        if self.m.kind == "lathe":  # (a lathe's [tool] length is a placeholder its chain does not use)
            self.rep.warnings.append(
                f"{p.source}:{tools[0]['first_line']}: tool offsets in force ({said}): the twin takes its errors at "
                f"the tip the program's positions place, as a point of the slides; a tool's offsets are an arm from "
                f"the turret's reference on which the slides' angular errors act, moving the tip by d x the angle for "
                f"an offset d, up to {worst_urad * 0.01:.2f} um per 10 mm on this program's moves, which the post does "
                "not correct")
            return
        self.rep.warnings.append(
            f"{p.source}:{tools[0]['first_line']}: tool length offsets in force ({said}): the twin's errors are those "
            f"of its reference tool ({self.m.tool.length:g} mm, gauge line to tip); a tool longer or shorter by d "
            f"moves the tip by d x the tool-axis error, up to {worst_urad * 0.01:.2f} um per 10 mm on this program's "
            "moves, which the post does not correct")

    def _note_block_delete(self, rows):
        """A warning when a move is a block-delete block ('/'): the post compensates the program as it runs with the
        block-delete switch off (as rs274 reads it); with the switch on, the move after a skipped one starts
        elsewhere, whose path between its compensated ends is then not the one checked."""
        p = self.p
        if not p.block_delete_lines:
            return
        deleted = np.isin(p.line_index[rows], np.asarray(p.block_delete_lines) - 1)  # (the reader's 1-based lines)
        if deleted.any():
            line = int(p.line_no[rows[np.argmax(deleted)]])  # (a flattened program's source line)
            self.rep.warnings.append(f"{p.source}:{line}: block delete: the moves are compensated as the program runs "
                                     "with the block-delete switch off; with it on, the move after a skipped block "
                                     "starts elsewhere and only its ends are compensated")

    def _compensate_chunks(self, rows, chunks):
        """``_compensate`` of each chunk of ``rows``, the results in chunk order (a generator). The first chunk here,
        the others on two threads when the compiled kernels are the ahead-of-time ones (which release the GIL; numba's
        parallel kernels must not be entered from two threads) and numba was not needed for the first: each chunk
        computes what it computes alone (its own moves; the chunk before's written end, where its arcs need it, taken
        once that chunk has solved its ends), and its warnings and split count are taken in chunk order, so the
        output and the report are those of the chunks one after the other."""
        from ..compiled import aot_available, numba_imported, thread_count

        self._pair()  # (its warning, if any, once and first)
        before = _ChunkEnd()
        before.value = (-2, None)
        before.set()
        for i, sl in enumerate(chunks):
            if i == 1 and CHUNK_THREADS and len(chunks) > 2 and thread_count() > 1 and self.m.kind != "lathe" \
                    and aot_available() and not numba_imported():
                yield from self._compensate_threaded(rows, chunks[1:], before)
                return
            mine = _ChunkEnd()
            yield self._take_notes(self._chunk(rows[sl], before, mine))
            before = mine

    def _compensate_threaded(self, rows, chunks, before):
        """``_compensate_chunks`` of ``chunks`` on two threads, the first one's chunk before ending at ``before``."""
        from concurrent.futures import ThreadPoolExecutor

        ends = [before] + [_ChunkEnd() for _ in chunks]
        with ThreadPoolExecutor(max_workers=2, thread_name_prefix="trueaxis-chunk") as pool:
            futures = [pool.submit(self._chunk, rows[sl], ends[i], ends[i + 1], True) for i, sl in enumerate(chunks)]
            try:
                for f in futures:
                    yield self._take_notes(f.result())
            finally:
                for f in futures:
                    f.cancel()

    def _chunk(self, rows, before, mine, own_thread=False):
        """(``_compensate(rows)``, the chunk's notes): the chunk before ends at ``before`` (a ``_ChunkEnd``); this
        one's end goes to ``mine`` once its ends are solved (None if it stopped before). ``own_thread``: the chunk
        runs beside another one, on a thread of its own: its kernels run on that thread (not shared among the
        kernels' threads as well: the cores are busy with the chunks; the same numbers either way)."""
        local = self._local
        local.notes, local.end_before_from, local.publish = {"warnings": [], "moves_split": 0}, before, mine
        try:
            with kernels_on_this_thread() if own_thread else contextlib.nullcontext():
                return self._compensate(rows), local.notes
        finally:
            if not mine.is_set():
                mine.value = None
                mine.set()
            local.notes = local.end_before_from = local.publish = None

    def _take_notes(self, result):
        """A chunk's result, its notes (warnings, split count) taken into the report as the chunk itself would have."""
        out, notes = result
        self.rep.warnings.extend(notes["warnings"])
        self.rep.moves_split += notes["moves_split"]
        return out

    @property
    def _end_before_chunk(self):
        """(row, written end) of the last move of the chunk before this one (waits for its ends' solve)."""
        before = self._local.end_before_from
        before.wait()
        if before.value is None:
            raise _ChunkAborted("the chunk before stopped")
        return before.value

    def _note_warning(self, text: str):
        """A warning of this chunk's (taken into the report in chunk order by ``_take_notes``)."""
        self._local.notes["warnings"].append(text)

    def _note_moves_split(self, n: int):
        """Count ``n`` split moves of this chunk (the report's figure is the sum over the chunks)."""
        self._local.notes["moves_split"] += n

    def _compensate(self, rows):
        """Compensate the moves ``rows`` (indices into the program's rows): (correction of each end in program units
        (K, 6), the same in mm / rad (K, n_axes), split pieces {k: (n, 6) program-coordinate ends}, (the arcs kept as
        they are (k,), the other arcs' modes {k: "fit" | "lines"})); k indexes ``rows``. Split moves' piece boundaries
        go to ``self.fractions`` (by row)."""
        p = self.p
        inch = p.inch[rows]
        q_end = self.to_machine(p.to_machine(p.end[rows], rows), inch)
        q_start = self.to_machine(p.to_machine(p.start[rows], rows), inch)
        direction = np.zeros((rows.size, 3))
        lin = [j for j, a in enumerate(self.names) if not self.m.axes[a].is_rotary]
        direction[:, : len(lin)] = (q_end - q_start)[:, lin] if len(lin) == 3 else 0.0
        arcs = (p.motion[rows] == ARC_CW) | (p.motion[rows] == ARC_CCW)
        if np.any(arcs) and len(lin) == 3:
            direction[arcs] = self._arc_end_tangent(rows[arcs], q_end[arcs])
        force = self.forces(rows, direction, q_end)
        q_cmd, singular, end_poses = self.solve(q_end, force, rows, poses=True)
        self.check(q_end, q_cmd, rows)
        dq = q_cmd - q_end
        delta_prog = self.to_program_delta(dq if self.tcp is None else self.command_delta(q_cmd, q_end), inch, rows)
        # the chunk after may start its arcs from here (``_end_before_chunk``)
        self._local.publish.value = (int(rows[-1]), p.end[rows[-1]] + delta_prog[-1])
        self._local.publish.set()

        pieces, arc_kept, arc_mode = {}, np.zeros(0, np.int64), {}
        # straight feeds (and, in TCP output, rapids that turn a rotary axis) are split; one from a start the program
        # has not fixed is not: its end is compensated, its path cannot be judged
        straight = (p.motion[rows] == FEED) | self._tcp_rotary_rapids(rows, q_start, q_end)
        feed_rows = np.nonzero(straight & self.start_known[rows])[0]
        pieces.update(self._split_lines(rows, feed_rows, q_start, q_end, force, inch, q_cmd, end_poses))
        if np.any(arcs):
            arc_pieces, arc_kept, arc_mode = self._arcs(rows, np.nonzero(arcs)[0], q_start, (q_end, q_cmd), force,
                                                        inch, delta_prog)
            pieces.update(arc_pieces)
        return delta_prog, dq, pieces, (arc_kept, arc_mode)

    def _tcp_rotary_rapids(self, rows, q_start, q_end):
        """(K,) bool: the rapids of ``rows`` that turn a rotary axis, in TCP output (none in joint output), which are
        split like feed moves. A control in TCP kinematics (LinuxCNC's trt kinematics, a G43.4) plans every move,
        rapids too, as a straight line of the tool tip in the table's frame with the rotary axes linear; the input's
        rapid is joint-interpolated. Written as one block, a rapid of C -300 deg took the joints up to 86 mm outside
        the box of its ends and Z 35 mm below both (a QA pass); split, the tip follows the input's rapid path within
        the tolerance, as a feed move's does. (A rapid does not cut, but it must not go where the input's does not:
        clamps, the part, the table.)"""
        if self.tcp is None:
            return np.zeros(rows.size, bool)
        rot = self.rotary_columns
        return (self.p.motion[rows] == RAPID) & np.any(q_start[:, rot] != q_end[:, rot], axis=1)

    def _summarise(self, max_abs, rms):
        """Report the correction per axis: max and RMS over the move ends (um or urad)."""
        out = {}
        for j, a in enumerate(self.names):
            scale, unit = (1e6, "urad") if self.m.axes[a].is_rotary else (1e3, "um")
            out[a] = {f"max_abs_{unit}": float(max_abs[j] * scale), f"rms_{unit}": float(rms[j] * scale)}
        if "X" in out and self.m.kind == "lathe" and bool(np.any(self.p.diameter)):
            # a lathe's X correction is a radius; G7's X words are diameters and change by twice it (a QA pass
            # read 7.51 um in the summary against 15 um in the words)
            # (a number, as every entry of the correction: the largest change of the X words as written)
            out["X"]["max_abs_diameter_um"] = 2.0 * out["X"]["max_abs_um"]
        self.rep.correction = out

    def _residual_check(self):
        """Report: the largest pose residual over every solved point (block ends and split points); the tool-axis
        residual outside the singular cone, and apart the tool-axis error left inside it (its free axis held)."""
        st = self.stats
        self.rep.max_residual_um = st["um"]
        self.rep.max_residual_urad = st["urad"]
        self.rep.max_axis_error_singular_urad = st["urad_singular"]
        self.rep.singular_points = st["singular_points"]
        self.rep.singular_blocks = sorted(st["singular_lines"])
        self.rep.singular_block_count = len(self.rep.singular_blocks)

    def _arc_end_tangent(self, arc_rows, q_end_mm):
        p = self.p
        if p.rotation is None or not np.any(p.rotation[arc_rows]):
            center = p.arc_center[arc_rows] + p.offset[arc_rows, :3]
            center = np.where(p.inch[arc_rows, None], center * MM_PER_INCH, center)
            plane = p.arc_plane[arc_rows]
            normal = np.select([plane[:, None] == 17, plane[:, None] == 18, plane[:, None] == 19],
                               [np.array([0, 0, 1.0]), np.array([0, 1.0, 0]), np.array([1.0, 0, 0])])
            sense = np.where(p.motion[arc_rows] == ARC_CCW, 1.0, -1.0)
            return np.cross(normal, q_end_mm[:, :3] - center) * sense[:, None]
        # in program coordinates (the arc's plane is the work system's), then turned into the machine frame
        radial6 = np.zeros((arc_rows.size, 6))
        radial6[:, :3] = p.end[arc_rows, :3] - p.arc_center[arc_rows]
        plane = p.arc_plane[arc_rows]
        normal = np.select([plane[:, None] == 17, plane[:, None] == 18, plane[:, None] == 19],
                           [np.array([0, 0, 1.0]), np.array([0, 1.0, 0]), np.array([1.0, 0, 0])])
        sense = np.where(p.motion[arc_rows] == ARC_CCW, 1.0, -1.0)
        tang6 = np.zeros((arc_rows.size, 6))
        tang6[:, :3] = np.cross(normal, radial6[:, :3]) * sense[:, None]
        # a direction: turned by the rotation, not offset
        return p.to_machine(tang6, arc_rows)[:, :3] - p.to_machine(np.zeros_like(tang6), arc_rows)[:, :3]

    def _split_lines(self, rows, feed_idx, q_start, q_end, force, inch, q_cmd_end, end_poses, max_rounds=10):
        """Straight feed moves (and TCP output's rotary rapids, ``_tcp_rotary_rapids``): split until the actual path
        stays within tolerance of the nominal path.

        The nominal path is the one the control makes of the programmed move: the axes interpolated linearly (in five
        axes a curve in the part frame). The compensated move is linear in the commanded axes between its pieces'
        ends; at fractions 1/4, 1/2, 3/4 of each piece the actual pose is compared with the nominal pose at the same
        fraction of the move (the same instant: position and, in five axes, tool axis), so both the error's
        variation and the kinematics' non-linearity count. Inside the singular cone the ends keep a tool-axis error
        (free axis held): what is compared there is the deviation beyond the straight blend of the ends' residuals.

        All points of all moves live in flat arrays (move, fraction, commanded pose, residual) and only new points
        are solved, one batch per round. ``end_poses``: the solve's poses at the ends (``solve(poses=True)``)."""
        if feed_idx.size == 0:
            return {}
        idx = np.asarray(feed_idx, int)
        f_all = None if force is None else force
        residual = self._path_residual(q_start, q_end, f_all)
        q0, start_poses = self._commanded_starts(rows, idx, q_start, q_end, f_all, q_cmd_end, end_poses)
        I = np.r_[idx, idx]
        F = np.r_[np.zeros(idx.size), np.ones(idx.size)]
        C = np.vstack([q0, q_cmd_end[idx]])
        S = np.r_[self.singular_at(q_start[idx]), self.singular_at(q_end[idx])]
        R = residual(I, F, C, self._end_poses(idx, q_start, q_end, start_poses, end_poses))
        active = np.zeros(len(rows), bool)
        active[idx] = True
        scale = self._split_scale()
        worst_final = np.zeros(0)
        for _ in range(max_rounds):
            order = np.lexsort((F, I))
            I, F, C, R, S = I[order], F[order], C[order], R[order], S[order]
            ia = np.nonzero((I[1:] == I[:-1]) & active[I[:-1]])[0]
            if ia.size == 0:
                break
            owner, a, b = I[ia], F[ia], F[ia + 1]
            worst = self._chord_deviation(residual, owner, a, b, (C[ia], C[ia + 1]), (R[ia], R[ia + 1]),
                                          S[ia] | S[ia + 1], scale)
            bad = worst > 1.0
            worst_final = worst
            if not np.any(bad):
                break
            mv, fr = _subdivide(owner, a, b, worst, bad)
            q_nom = q_start[mv] + fr[:, None] * (q_end[mv] - q_start[mv])
            qc, _, known = self.solve(q_nom, None if f_all is None else f_all[mv], rows[mv], poses=True)
            self.check(q_nom, qc, rows[mv])
            I, F, C, S = np.r_[I, mv], np.r_[F, fr], np.vstack([C, qc]), np.r_[S, self.singular_at(q_nom)]
            R = np.vstack([R, residual(mv, fr, qc, known)])
            active[:] = False
            active[np.unique(owner[bad])] = True
        else:
            still = np.unique(owner[worst_final > 1.0]) if worst_final.size else np.array([], int)
            for i in still:
                self._note_warning(f"{self.p.source}:{int(self.p.line_no[rows[i]])}: the move was split "
                                   f"{max_rounds} times and still leaves the nominal path by more than the tolerance")
        return self._split_pieces(rows, I, F, C, q_start, q_end, inch)

    def _path_residual(self, q_start, q_end, f_all):
        """residual(i_move, fr, qc, known=None) -> (K, 3 or 6): the actual pose at commanded poses qc less the nominal
        pose at the fractions fr of the moves i_move (indices into the chunk's rows), position then tool axis;
        ``known``: (actual tip, axis, nominal tip, axis) there, computed already (then the twin is not called);
        ``residual.poses(i_move, fr, qc)`` computes them.

        Judged is the position error along the directions the axes can correct (all three on a mill, X and Z on a
        lathe, whose error along Y moves the turned radius by second order only and no axis can remove)."""
        n6 = 6 if self.orientation else 3
        correctable = corrected_directions(self.m)
        correctable = correctable.T @ correctable
        # A projection on axis directions (a mill's identity, a lathe's X and Z): each component of the product is one
        # of the error's own components or zero, whatever the matrix product's order of operations -- the same
        # numbers row by row (up to the sign of a zero, which no norm sees), taken as they are or zeroed.
        keep = np.diag(correctable).copy()
        axis_aligned = bool(np.all(correctable == np.diag(keep)) and np.all((keep == 0) | (keep == 1)))
        identity = axis_aligned and bool(np.all(keep == 1))
        span = q_end - q_start  # (the same numbers as q_end[i] - q_start[i] row by row)

        def poses(i_move, fr, qc):
            q_nom = q_start[i_move] + fr[:, None] * span[i_move]
            pn, un = self.twin.nominal_pose(q_nom)
            pa, ua = self.twin.actual_pose(qc, None if f_all is None else f_all[i_move])
            return pa, ua, pn, un

        def residual(i_move, fr, qc, known=None):
            pa, ua, pn, un = poses(i_move, fr, qc) if known is None else known
            if identity and n6 == 3:
                return pa - pn
            dp = pa - pn if identity else (pa - pn) * keep if axis_aligned else (pa - pn) @ correctable
            return np.hstack([dp, ua - un])[:, :n6]

        residual.poses = poses
        residual.row_wise = axis_aligned  # each row's residual computed alone: rows of several calls may be joined
        return residual

    def _commanded_starts(self, rows, idx, q_start, q_end, f_all, q_cmd_end, end_poses):
        """(K, n_axes) commanded start poses of the moves idx, and their poses (actual tip, axis there, nominal tip,
        axis at the nominal start; each (K, 3)). A move's commanded start is usually the previous move's commanded end
        (same pose, same force): reused, with its poses (``end_poses``, the solve's at the ends); the others are
        solved."""
        q0 = np.empty((idx.size, q_start.shape[1]))
        poses = tuple(np.empty((idx.size, 3)) for _ in range(4))
        same = idx > 0
        prev = idx[same] - 1
        same[same] = np.all(q_start[idx[same]] == q_end[prev], axis=1) & (
            True if f_all is None else np.all(f_all[idx[same]] == f_all[prev], axis=1))
        # (the reused moves' positions and their moves before, picked out once for the five arrays taken from there)
        at = np.flatnonzero(same)
        before = idx[at] - 1
        q0[at] = q_cmd_end[before]
        for mine, theirs in zip(poses, end_poses):
            mine[at] = theirs[before]
        if not same.all():
            fresh = idx[~same]
            q0[~same], _, solved = self.solve(q_start[fresh], None if f_all is None else f_all[fresh], rows[fresh],
                                              poses=True)
            for mine, theirs in zip(poses, solved):
                mine[~same] = theirs
        return q0, poses

    def _end_poses(self, idx, q_start, q_end, start_poses, end_poses):
        """(actual tip, axis, nominal tip, axis) (2K, 3) each at the starts then the ends of the moves idx, as
        ``residual`` takes them: the actual poses the solves computed; the nominal pose at the start the solve's (the
        start is the fraction 0), at the end the solve's where the fraction 1 gives the end's axes exactly, else
        evaluated at that fraction."""
        pa0, ua0, pn0, un0 = start_poses
        pa1, ua1, pn1, un1 = (x[idx] for x in end_poses)
        q_one = q_start[idx] + 1.0 * (q_end[idx] - q_start[idx])
        other = np.nonzero(~np.all(q_one == q_end[idx], axis=1))[0]
        if other.size:
            pn1[other], un1[other] = self.twin.nominal_pose(q_one[other])
        return np.vstack([pa0, pa1]), np.vstack([ua0, ua1]), np.vstack([pn0, pn1]), np.vstack([un0, un1])

    def _split_scale(self):
        """Per-component scale (3 or 6,) of the residuals: 1 / the tolerance a chord is judged by (1 / mm, 1 / rad).

        The tolerance is a promise about the written program: the ends' own residuals (the solver's tolerance) and
        the rounding of the written numbers come off it before the chord is judged. (At most half of it: a tolerance
        near the written digits is then kept to within their rounding.)"""
        n6 = 6 if self.orientation else 3
        tol_mm = max(self.tol_mm - 1e-3 * (self.solve_tol_um + WRITE_ROUNDING_UM), self.tol_mm / 2)
        tol_rad = max(self.tol_rad - 1e-6 * (SOLVE_TOL_URAD + WRITE_ROUNDING_URAD), self.tol_rad / 2)
        return np.r_[np.full(3, 1 / tol_mm), np.full(3, 1 / tol_rad)][:n6]

    def _chord_deviation(self, residual, owner, a, b, c_ends, r_ends, held, scale):
        """(K,) the worst scaled deviation (> 1: out of tolerance) of the chords between the fractions a and b of the
        moves owner, commanded poses c_ends = (ca, cb) and residuals r_ends = (ra, rb) at their ends, compared at 1/4,
        1/2, 3/4 of each chord; the report's largest deviation within tolerance is updated.

        Inside the singular cone (held: either end's free axis held) the ends keep a tool-axis error: judged is what
        the chord adds to the straight blend of the ends' residuals. Elsewhere the whole deviation."""
        (ca, cb), (ra, rb) = c_ends, r_ends
        fractions = (0.25, 0.5, 0.75)
        at = [a + sfrac * (b - a) for sfrac in fractions]
        c_at = [ca + sfrac * (cb - ca) if self.tcp is None else self.tcp.interpolate(ca, cb, sfrac)
                for sfrac in fractions]
        # the twin once for the three fractions' points (the same poses; one call, not three); the residuals and their
        # norms of the three at once where each row's are computed alone (``residual.row_wise``), else fraction by
        # fraction: the same numbers either way
        k = owner.size
        known = residual.poses(np.tile(owner, 3), np.concatenate(at), np.vstack(c_at))
        if residual.row_wise:
            e = residual(None, None, None, known)
        else:
            e = np.vstack([residual(owner, at[j], c_at[j], tuple(x[j * k : (j + 1) * k] for x in known))
                           for j in range(3)])
        if held.any():  # (elsewhere the blend is 0.0, and e - 0.0 is e)
            e = e - np.where(np.tile(held, 3)[:, None], np.vstack([(1 - s) * ra + s * rb for s in fractions]), 0.0)
        ep = np.linalg.norm(e[:, :3], axis=1).reshape(3, k)
        eu = np.linalg.norm(e[:, 3:], axis=1).reshape(3, k) if self.orientation else np.zeros((3, k))
        # the largest over the fractions (norms: never below the zero the maxima started from)
        dev_um, dev_urad = (ep * 1e3).max(axis=0), (eu * 1e6).max(axis=0)
        worst = np.maximum(ep * scale[0], eu * scale[-1]).max(axis=0)
        bad = worst > 1.0
        with self._lock:
            self.rep.max_split_deviation_um = max(self.rep.max_split_deviation_um, float(dev_um[~bad].max(initial=0)))
            self.rep.max_split_deviation_urad = max(self.rep.max_split_deviation_urad,
                                                    float(dev_urad[~bad].max(initial=0)))
        return worst

    def _split_pieces(self, rows, I, F, C, q_start, q_end, inch):
        """The split moves' pieces from the flat points (move I, fraction F, commanded pose C): {k: (n, 6) program
        coordinates of the inner piece ends}; their fractions (with 0 and 1) go to ``self.fractions`` by row."""
        p = self.p
        out = {}
        order = np.lexsort((F, I))
        I, F, C = I[order], F[order], C[order]
        counts = np.bincount(I, minlength=len(rows))
        split_rows = np.nonzero(counts > 2)[0]
        self._note_moves_split(int(split_rows.size))
        if split_rows.size == 0:
            return out
        inner = np.isin(I, split_rows) & (F > 0) & (F < 1)
        fr, mv, qc = F[inner], I[inner], C[inner]
        q_nom = q_start[mv] + fr[:, None] * (q_end[mv] - q_start[mv])
        start6 = p.start[rows[mv]]
        end6 = p.end[rows[mv]]
        nom6 = start6 + fr[:, None] * (end6 - start6)
        cmd6 = nom6 + self.to_program_delta(self.command_delta(qc, q_nom), inch[mv], rows[mv])
        bounds = np.split(np.arange(mv.size), np.nonzero(np.diff(mv))[0] + 1)
        for sel in bounds:
            i = int(mv[sel[0]])
            out[i] = cmd6[sel]
            self.fractions[int(rows[i])] = np.r_[0.0, fr[sel], 1.0]
        return out

    def _arcs(self, rows, arc_idx, q_start, solved_ends, force, inch, delta_prog):
        """Arcs whose correction is constant within tolerance stay arcs; others are fitted (``.arcs``, where
        ``fit_arcs``) or become straight pieces.

        All arcs are sampled and solved together (one Newton solve per stage, not per arc); ``solved_ends``: (nominal,
        commanded) poses of the chunk's block ends, whose solves the arcs' last points take. Returns (pieces
        {k: (n, 6)}, the arcs kept (k,) int, the others' modes {k: "fit" | "lines"}); k indexes ``rows``."""
        p = self.p
        out, modes = {}, {}
        arc_idx = np.asarray(arc_idx, int)
        # Stage 1: samples every ARC_SAMPLE_MM along each arc (4 to 16 intervals); the spread of the correction along
        # it decides arc or lines.
        r_arcs = rows[arc_idx]
        geometry = _arcs_geometry(p, r_arcs)
        sweep, radius = geometry[4], geometry[5]
        length = sweep * radius * np.where(p.inch[r_arcs], MM_PER_INCH, 1.0)
        n_s = np.clip(np.ceil(length / ARC_SAMPLE_MM), 4, 16).astype(int)
        pts6 = _arcs_points(p, r_arcs, n_s, geometry)
        owner = np.repeat(np.arange(arc_idx.size), n_s + 1)
        q_c, q_pts = self._solve_arc_points(rows, arc_idx, owner, pts6, force, solved_ends)
        lin = [j for j, a in enumerate(self.names) if not self.m.axes[a].is_rotary]
        d = (q_c - q_pts)[:, lin]
        last = np.cumsum(n_s + 1) - 1
        spread = np.zeros(arc_idx.size)
        np.maximum.at(spread, owner, np.abs(d - d[last[owner]]).max(axis=1))
        kept = spread <= self.tol_mm / 2
        # A full turn is kept only where its written start and end coincide: a control reads an end a digit off the
        # start as a short arc (or a turn less one), not a full circle (LinuxCNC's pmCircleInit).
        kept &= full_turns_close(self, rows, arc_idx, delta_prog)
        kept &= radii_kept_within_limits(self, rows, arc_idx, delta_prog)  # (rs274's limits, written)
        kept &= self.tcp is None  # TCP: the control turns an arc's plane with the table; straight pieces only
        arc_kept = arc_idx[kept]
        with self._lock:
            self.rep.arcs_kept += int(kept.sum())
        lin = arc_idx[~kept]
        if self.fit_arcs and lin.size:
            fitted, lin = fit_arcs(self, rows, lin, force, delta_prog)
            for k, (ends, centres) in fitted.items():
                out[k], modes[k] = ends, "fit"
                self.arc_centres[int(rows[k])] = centres
        if lin.size == 0:
            return out, arc_kept, modes
        # Stage 2: straight pieces, enough that the chord sagitta stays within half the tolerance; the correction's
        # variation is then followed point by point.
        r_lin = rows[lin]
        geometry = _arcs_geometry(p, r_lin)
        sweep, radius = geometry[4], geometry[5] * np.where(p.inch[r_lin], MM_PER_INCH, 1.0)
        step = 2 * np.arccos(np.maximum(0.0, 1 - (self.tol_mm / 2) / np.maximum(radius, 1e-9)))
        counts = np.maximum(2, np.ceil(sweep / step)).astype(int)
        pts6 = _arcs_points(p, r_lin, counts, geometry)
        owner = np.repeat(np.arange(lin.size), np.asarray(counts) + 1)
        q_c, q_pts = self._solve_arc_points(rows, lin, owner, pts6, force, solved_ends)
        self.check(q_pts, q_c, rows[lin][owner])
        cmd6 = pts6 + self.to_program_delta(self.command_delta(q_c, q_pts), p.inch[rows[lin]][owner], rows[lin][owner])
        first = np.r_[0, np.cumsum(np.asarray(counts) + 1)[:-1]]
        for k, i in enumerate(lin):
            out[int(i)] = cmd6[first[k] + 1 : first[k] + counts[k] + 1]
            modes[int(i)] = "lines"
        with self._lock:
            self.rep.arcs_linearised += int(lin.size)
        return out, arc_kept, modes

    def _solve_arc_points(self, rows, arc_idx, owner, pts6, force, ends=None):
        """Commanded and nominal machine poses (K, n_axes) for points ``pts6`` (K, 6) on the arcs ``arc_idx[owner]``.

        ``ends``: (nominal, commanded) poses of the chunk's block ends, solved already: an arc's last point is its end
        (``_arcs_points`` puts it there exactly), and where it gives the same nominal pose under the same load its
        commanded pose is taken from there (the same solve of the same numbers)."""
        p = self.p
        r = rows[arc_idx][owner]
        q_pts = self.to_machine(p.to_machine(pts6, r), p.inch[r])
        f = None if force is None else force[arc_idx][owner]
        if f is not None and f.shape[1] > 3:  # a lathe's loads: force and motion follow the arc (see .turning)
            from .turning import arc_point_loads

            f, ends = arc_point_loads(self, r, pts6, f), None
        taken = np.zeros(owner.size, bool)
        q_c = np.empty_like(q_pts)
        if ends is not None:
            last = np.nonzero(np.r_[owner[1:] != owner[:-1], True])[0]
            block = arc_idx[owner[last]]
            last = last[np.all(q_pts[last] == ends[0][block], axis=1)]
            taken[last] = True
            q_c[last] = ends[1][arc_idx[owner[last]]]
            # an arc's first point is its start (mostly to the bit, see _arcs_points): where it is the end of the
            # chunk's move before, under the same load, its commanded pose is that move's (the same solve again)
            first = np.nonzero(np.r_[True, owner[1:] != owner[:-1]])[0]
            before = arc_idx[owner[first]] - 1
            first, before = first[before >= 0], before[before >= 0]
            same = np.all(q_pts[first] == ends[0][before], axis=1)
            if force is not None:
                same &= np.all(f[first] == force[before], axis=1)
            first, before = first[same], before[same]
            taken[first] = True
            q_c[first] = ends[1][before]
        if taken.any():
            self._record_taken(q_pts[taken], r[taken])
        if not taken.all():
            q_c[~taken], _ = self.solve(q_pts[~taken], None if f is None else f[~taken], r[~taken])
        return q_c, q_pts

    def _record_taken(self, q, rows):
        """What ``solve`` records of its points (the residuals aside: recorded by the solve they come from), for points
        whose commanded poses were taken from another solve: the points and blocks in the singular cone."""
        held = self.singular_at(q)
        with self._lock:
            self.stats["singular_points"] += int(held.sum())
            if held.any():
                self.stats["singular_lines"].update(int(x) for x in self.p.line_no[np.asarray(rows)[held]])

    # --- writing -------------------------------------------------------------------------------------------------
    def _write(self, rows, delta_prog, pieces, arc_mode):
        """The output text: every line of the input, the compensated motion blocks rewritten (plus the extra pieces
        of split moves after them); returns (text, report)."""
        p = self.p
        axes_out = self._axes_out()
        numbers = _Numbers(p.format_info)
        is_cycle = p.kind[rows] == ROW_CYCLE
        written_end, first_row_of_line = self._written_ends(rows, delta_prog, is_cycle)
        # Each compensated move's corrected end; the axis words of the pieces of split moves and linearised arcs (the
        # block's own end last), formatted in one pass per axis.
        target = p.end[rows]  # (a new array: the sum in place)
        target += delta_prog
        inch_rows = p.inch[rows]
        split = self._piece_words(pieces, arc_mode, target, inch_rows, axes_out, numbers)
        line_of = p.line_index[rows]
        starts = np.r_[0, np.nonzero(np.diff(line_of))[0] + 1]
        ends = np.r_[starts[1:], rows.size]
        # The compiled writer (fast_write) takes the plain blocks with absolute axis words, not split, not canned
        # cycles; every other compensated line goes through ``_write_lines``.
        fast = self._fast_lines(rows, starts, ends, target, inch_rows, split.first, arc_mode, axes_out, numbers,
                                delta_prog, written_end, first_row_of_line)
        ends_written = (written_end, first_row_of_line)
        extra = 0
        if fast is not None:
            keep = ~fast["handled"]
            starts, ends = starts[keep], ends[keep]
            # split moves and fitted arcs: the compiled writer too, where their lines are plain (fast_write.pieces)
            fast["pieces"], taken, extra = self._fast_pieces(rows, starts, ends, is_cycle, arc_mode, split, axes_out,
                                                             numbers, ends_written, fast)
            starts, ends = starts[~taken], ends[~taken]
        out = list(p.lines) if fast is None else {}
        split = self._piece_texts(split, (ends - 1).tolist(), inch_rows, axes_out, numbers)
        extra += self._write_lines(out, rows, starts, ends, is_cycle, target, delta_prog, arc_mode, split, axes_out,
                                   numbers, ends_written)
        if p.position_sets:
            self._shift_position_sets(out, written_end, numbers)
        self.rep.blocks_out = len(p.lines) + extra
        if fast is None:
            return "".join(out), self.rep
        return self._fast_assemble(fast, out), self.rep

    def _shift_position_sets(self, out, written_end, numbers):
        """G92 and G10 L20 take their offset from the position the control holds, which the correction of the move
        before moved: their values move by that correction (program units), so that the control sets the offset the
        program means. Written as given, every later point was off by that correction (8-20 um, a QA pass)."""
        p = self.p
        for li, axes, what in p.position_sets:
            r = int(np.searchsorted(p.line_index, li, side="left")) - 1  # the last row before the block
            if r < 0:
                continue
            c = written_end.correction([r])[0]
            if not np.any(c[axes]):
                continue
            text = out[li] if isinstance(out, list) or li in out else p.lines[li]
            words = [t for t in tokenize_line(text) if t[0] == "word"]  # (comments, inline ones too, left alone)
            if any(re.fullmatch(r"(?i)G0*2[01]", w[1]) for w in words):
                raise PostError(p.source, self.p.source_line_of(li),
                                f"{what} with a change of units on its block: write the G20 / G21 "
                                "on a block of its own")
            fmt = numbers.formatter(bool(p.inch[r]))
            new, done = {}, set()
            for _, word, start, end in words:
                i = AXES.find(word[0].upper())
                if i in axes and i not in done:
                    try:
                        new[start, end] = fmt(word[0].upper(), float(word[1:]) + c[i])
                    except ValueError:  # (a value the flattened block does not write as a plain number)
                        break
                    done.add(i)
            if done != set(axes):
                raise PostError(p.source, self.p.source_line_of(li),
                                f"{what}: its axis values are not plain numbers here; the correction "
                                "the control's position carries cannot be added to them")
            for (start, end), value in sorted(new.items(), reverse=True):
                text = text[:start] + value + text[end:]
            out[li] = text
            self.rep.offsets_shifted.append({"line": self.p.source_line_of(li), "what": what, "by_program_units": {
                AXES[i]: float(c[i]) for i in axes}})

    def _axes_out(self):
        """The axis words every rewritten block carries: X Y Z and the program's other axes of the machine (a lathe:
        X Z and the program's)."""
        p = self.p
        axes_out = [a for a in AXES if a in self.names and (a in p.axes_present or a in "XYZ")]
        if self.m.kind == "lathe":
            axes_out = [a for a in axes_out if a in p.axes_present or a in "XZ"]
        return axes_out

    def _written_ends(self, rows, delta_prog, is_cycle):
        """(written_end, first_row_of_line (lines,)): the end point written for every program row (program
        coordinates; ``written_end[r]`` for rows r (K,), see ``_WrittenEnd``) and each line's first row (-1: none).

        Compensated moves end at their corrected ends, everything else (and canned cycles, rewritten from their hole
        and R level) as programmed. A block's incremental words and arc centres count from the end written for the
        row before it."""
        p = self.p
        moves = ~is_cycle
        if moves.all():  # (as a rule: the same rows, not copied)
            written_end = _WrittenEnd(p.end, len(p), rows, delta_prog)
        else:
            written_end = _WrittenEnd(p.end, len(p), rows[moves], delta_prog[moves])
        first_row_of_line = np.full(len(p.lines), -1)
        first_row_of_line[p.line_index[::-1]] = np.arange(len(p))[::-1]
        return written_end, first_row_of_line

    def _piece_words(self, pieces, arc_mode, target, inch_rows, axes_out, numbers):
        """The pieces of split moves and linearised or fitted arcs (not the kept arcs), their block's own end last:
        ``_PieceWords`` with each one's first index into the words and its (n, 6) points (the words: ``_piece_texts``,
        for the lines the compiled writer does not take)."""
        piece_keys = [k for k in pieces if arc_mode.get(k) != "arc"]
        piece_pts = [pieces[k] if arc_mode.get(k) in ("lines", "fit") else np.vstack([pieces[k], target[k]])
                     for k in piece_keys]
        piece_first = dict(zip(piece_keys, np.cumsum([0] + [len(x) for x in piece_pts]).tolist()))
        piece_pts_of = dict(zip(piece_keys, piece_pts))
        return _PieceWords(piece_first, piece_pts_of, None)

    def _piece_texts(self, split, keys, inch_rows, axes_out, numbers):
        """``split`` with the axis words of the pieces of the moves ``keys`` (those the Python writer writes; the
        others' words are left empty), formatted in one pass per axis."""
        keys = [k for k in keys if k in split.first]
        if not keys:
            return split
        n_all = sum(len(x) for x in split.pts.values())
        counts = [len(split.pts[k]) for k in keys]
        at = np.concatenate([np.arange(split.first[k], split.first[k] + n) for k, n in zip(keys, counts)])
        flat = np.vstack([split.pts[k] for k in keys])
        flat_inch = np.repeat(inch_rows[keys], counts)
        words = {}
        for a in axes_out:
            words[a] = [""] * n_all
            for i, text in zip(at.tolist(), numbers.words(a, flat[:, AXES.index(a)], flat_inch)):
                words[a][i] = text
        return split._replace(words=words)

    def _write_lines(self, out, rows, starts, ends, is_cycle, target, delta_prog, arc_mode, split, axes_out, numbers,
                     ends_written):
        """The Python writer: rewrite the lines of the row groups ``starts``/``ends`` into ``out`` (by line index);
        returns the number of blocks added (the later pieces of split moves)."""
        p = self.p
        sep = p.format_info.separator
        written_end, first_row_of_line = ends_written
        line_of = p.line_index[rows]
        inch_rows = p.inch[rows]
        # Python scalars for the per-line loop (numpy scalar access costs more than the rewrite itself).
        rows_l, motion_l, inch_l = rows.tolist(), p.motion.tolist(), p.inch.tolist()
        inverse_l, r_form_l = p.inverse_time.tolist(), (p.words & _R_BIT).astype(bool).tolist()
        cycle_l = is_cycle.tolist()
        incremental_l = p.incremental.tolist()
        formatters = {False: numbers.formatter(False), True: numbers.formatter(True)}
        piece_first = split.first
        extra = 0
        # The bulk of the axis words, formatted in one pass per axis and window of the loop's lines (memory stays
        # bounded): each line's corrected end (its last row's).
        window = [0, 0]  # the loop's lines [j_lo, j_hi) whose axis words are in axis_words
        axis_words = {}
        last_k = ends - 1
        for j, (k0, k1) in enumerate(zip(starts.tolist(), ends.tolist())):
            if j >= window[1]:
                window[:] = j, min(last_k.size, j + WRITE_WINDOW)
                ks = last_k[window[0] : window[1]]
                axis_words = {a: numbers.words(a, target[ks, AXES.index(a)], inch_rows[ks]) for a in axes_out}
            r0 = rows_l[k0]
            li = int(line_of[k0])
            body, ending = _split_ending(p.lines[li])
            fmt = formatters[inch_l[r0]]
            inc = incremental_l[r0]
            if cycle_l[k0]:
                if inc:
                    raise PostError(p.source, self.p.source_line_of(li),
                                    "incremental (G91) canned cycles are not compensated: write "
                                    "the cycle in G90, or post with --mode none")
                out[li] = self._cycle_line(body, list(range(k0, k1)), rows, delta_prog, fmt, sep) + ending
                continue
            k = k1 - 1
            r = rows_l[k]
            motion = motion_l[r]
            arc_kept = arc_mode.get(k) == "arc"
            is_split = k in piece_first
            inc = incremental_l[r]
            if inc or is_split or arc_kept:
                last_written = _written_before(np.array([li]), written_end, first_row_of_line, p)[0]
            if is_split:
                out[li], n_more = self._split_block(body, ending, k, r, motion, inc, inverse_l[r], last_written,
                                                    arc_mode, split, axes_out, fmt, sep)
                extra += n_more
                continue
            if inc:
                words = [fmt(a, _out_value(target[k], last_written, a, inc, fmt.decimals(a))) for a in axes_out]
            else:
                words = [axis_words[a][j - window[0]] for a in axes_out]
            if arc_kept and not r_form_l[r]:
                words += self._centre_words(r, delta_prog[k], last_written, fmt)
            out[li] = "".join([self._rewrite_motion(body, motion, words, arc_kept, r, sep), ending])
        return extra

    def _split_block(self, body, ending, k, r, motion, inc, inverse, last_written, arc_mode, split, axes_out, fmt,
                     sep):
        """(text, number of blocks added) of a split move (straight pieces, or a fitted arc's sub-arcs): the block
        itself goes to the first piece's end, so that its other words (F, S, M, N) act where they did; the remaining
        pieces follow as plain moves (G93: each with its share of the block's inverse-time feed)."""
        p = self.p
        o = split.first[k]
        pts = split.pts[k]
        n = len(pts)
        # A stop (M0 M1 M2 M30 M60) acts after the block's motion: it goes with the last piece (on the first, the
        # machine stopped mid-cut, or the program ended with the rest of the move uncut, exit 0, in a QA pass)
        body, stops = _stop_words_taken_out(body) if n > 1 else (body, [])
        if arc_mode.get(k) == "lines":
            motion = FEED
        centres = self.arc_centres.get(r) if arc_mode.get(k) == "fit" else None
        arc_start = last_written
        if centres is not None and np.isnan(centres[0, 0]):  # a fitted arc's first piece is straight
            motion = FEED
        # G93: each piece takes its share of the block's time (the control interpolates the axes linearly in time,
        # so a piece over the fraction df of the move takes df of it): inverse time F / df. A rapid (split in TCP
        # output) has no feed: its pieces take none.
        inverse = inverse and motion != RAPID
        if inverse:
            fractions = self.fractions.get(r)
            piece_f = p.feed[r] / np.diff(np.linspace(0.0, 1.0, n + 1) if fractions is None else fractions)
            body = _replace_feed(body, piece_f[0], fmt, sep)
        if inc:
            words = [fmt(a, _out_value(pts[0], last_written, a, inc, fmt.decimals(a))) for a in axes_out]
            last_written = pts[0]
        else:
            words = [split.words[a][o] for a in axes_out]
        if centres is not None and not np.isnan(centres[0, 0]):  # a fitted arc: its first sub-arc
            words += self._fit_centre_words(r, centres[0], arc_start, fmt)
        texts = [self._rewrite_motion(body, motion, words, False, r, sep), ending]
        # A block-delete block's pieces are block-delete blocks too: with the switch on, the control skips the whole
        # move, not its first piece only.
        skip = "/" if body.lstrip().startswith("/") else ""
        word = "G0" if motion == RAPID else "G1"
        for i_piece in range(1, n):
            arc = centres is not None and not np.isnan(centres[i_piece, 0])  # (else a sub-arc that did not hold)
            code = word if centres is None else _motion_text("G1", p.motion[r]) if arc else "G1"
            if inc:  # G91: the increments from the end written before (fitted sub-arcs too)
                piece = [code] + [fmt(a, _out_value(pts[i_piece], last_written, a, inc, fmt.decimals(a)))
                                  for a in axes_out]
                last_written = pts[i_piece]
            else:
                piece = [code] + [split.words[a][o + i_piece] for a in axes_out]
            if arc:
                piece += self._fit_centre_words(r, centres[i_piece], pts[i_piece - 1], fmt)
            if inverse:
                piece.append(fmt("F", piece_f[i_piece], inch=False))
            if i_piece == n - 1:
                piece += stops
            texts += [skip + sep.join(piece), ending]
        return "".join(texts), n - 1

    def _fast_lines(self, rows, starts, ends, target, inch_rows, piece_first, arc_mode, axes_out, numbers,
                    delta_prog, written_end, first_row_of_line):
        """The lines the compiled writer takes, or None (FAST_WRITE off, a program that is not ASCII, a separator it
        does not write): a dict with ``handled`` (per group of rows ``starts``/``ends``, bool) and what ``assemble``
        needs. Candidates: not canned cycles, absolute axis words, not split; ``fast_write.scan`` keeps the plain ones
        whose numbers it writes exactly. A kept arc's centre words (``_centre_words``) are computed here, for all
        kept arcs at once."""
        p = self.p
        info = p.format_info
        sep = fast_write.separator_code(info.separator)
        if not FAST_WRITE or sep is None or starts.size == 0:
            return None
        early = getattr(p, "_text_bytes", None)  # the reader's (line starts, bytes) of the same ASCII text
        if early is not None and early[0].size == len(p.lines) + 1:
            line_start, src = early
        else:
            text = "".join(p.lines)
            if not text.isascii():
                return None
            src = np.frombuffer(text.encode("ascii"), np.uint8)
            line_start = np.zeros(len(p.lines) + 1, np.int64)
            np.cumsum(np.fromiter(map(len, p.lines), np.int64, len(p.lines)), out=line_start[1:])
        last = ends - 1
        excluded = np.zeros(rows.size, bool)
        excluded[list(piece_first)] = True
        kept = arc_mode.kept
        # (a kept arc outside the G17/G18/G19 planes is left to the Python path, which refuses it)
        excluded |= kept & ~np.isin(p.arc_plane[rows], (17, 18, 19))
        cand = np.nonzero((p.kind[rows[starts]] != ROW_CYCLE) & ~p.incremental[rows[last]] & ~excluded[last])[0]
        cand_r0 = rows[starts[cand]]
        cand_line = p.line_index[cand_r0].astype(np.int64)
        cand_k = last[cand].astype(np.int64)
        cand_motion = p.motion[rows[cand_k]].astype(np.int64)
        cols = np.array([AXES.index(a) for a in axes_out], np.int64)
        dec = np.array([[numbers.decimals(a, inch) for a in axes_out] for inch in (False, True)], np.int64)
        dec = dec.reshape(2, len(axes_out))
        target = np.ascontiguousarray(target, float)
        inch = np.ascontiguousarray(inch_rows, np.bool_)
        # Kept arcs: the R word stays; without it, the centre words I J / I K / J K as _centre_words writes them.
        keep_r = kept[cand_k]
        n_extra = np.zeros(cand.size, np.int64)
        extra_val = np.zeros((cand.size, 2))
        extra_letter = np.zeros((cand.size, 2), np.uint8)
        extra_dec = np.zeros((cand.size, 2), np.int64)
        arcs = np.nonzero(keep_r & ((p.words[rows[cand_k]] & _R_BIT) == 0))[0]
        if arcs.size:
            last_written = _written_before(cand_line[arcs], written_end, first_row_of_line, p)
            which, values = self._centre_columns(rows[cand_k[arcs]], delta_prog[cand_k[arcs]], last_written)
            inch0 = p.inch[cand_r0[arcs]]
            n_extra[arcs] = 2
            extra_val[arcs] = values
            # (per letter and unit, not per arc: a program has hundreds of thousands of them)
            table = np.array([[numbers.decimals(c, inch) for inch in (False, True)] for c in "IJK"], np.int64)
            extra_letter[arcs] = np.frombuffer(b"IJK", np.uint8)[which]
            extra_dec[arcs] = table[which, inch0.astype(np.int64)[:, None]]
        # (each candidate is judged alone: the candidates shared among the kernels' threads, each share writing its
        # part of ok and spans)
        ok, spans = np.empty(cand.size, np.bool_), np.empty((cand.size, 7), np.int64)
        _shared(fast_write.scan, cand.size, lambda sl: (
            src, line_start, cand_line[sl], cand_k[sl], cand_motion[sl], target, cols, dec, inch, n_extra[sl],
            extra_val[sl], extra_dec[sl], ok[sl], spans[sl]))
        taken = np.flatnonzero(ok)
        handled = np.zeros(starts.size, bool)
        handled[cand[taken]] = True
        # the candidates' arrays as they are (not the taken ones picked out: a million rows each), "cand" the index of
        # each taken line's candidate in them
        return {"handled": handled, "src": src, "line_start": line_start, "line": cand_line[taken], "cand": taken,
                "k": cand_k, "motion": cand_motion, "spans": spans, "target": target, "cols": cols, "dec": dec,
                "inch": inch, "sep": sep, "letters": np.frombuffer("".join(axes_out).encode("ascii"), np.uint8),
                "n_extra": n_extra, "extra_val": extra_val, "extra_letter": extra_letter, "extra_dec": extra_dec,
                "keep_r": keep_r}

    def _fast_pieces(self, rows, starts, ends, is_cycle, arc_mode, split, axes_out, numbers, ends_written, fast):
        """The lines of split moves and fitted arcs the compiled writer takes (``fast_write.pieces``: absolute words,
        not G93, plain lines): (their text {"line", "blob", "start", "end"}, taken per group of rows starts/ends
        (bool), the number of blocks they add). The numbers are those ``_split_block`` writes: the pieces' ends as
        ``_piece_words`` has them, a fitted sub-arc's centre as ``_fit_centre_words`` computes it."""
        p = self.p
        taken = np.zeros(starts.size, bool)
        none = {"line": np.zeros(0, np.int64)}
        if not split.first or starts.size == 0:
            return none, taken, 0
        last = ends - 1
        keys = np.fromiter(split.first, np.int64, len(split.first))
        grp = np.nonzero(np.isin(last, keys) & ~is_cycle[starts])[0]
        r = rows[last[grp]]
        grp = grp[~p.incremental[r] & ~p.inverse_time[r]]
        if grp.size == 0:
            return none, taken, 0
        ks = last[grp].tolist()
        r = rows[last[grp]]
        pts = [split.pts[k] for k in ks]
        counts = np.fromiter(map(len, pts), np.int64, len(pts))
        piece_first = np.r_[0, np.cumsum(counts)].astype(np.int64)
        flat = np.ascontiguousarray(np.vstack(pts), float)
        modes = [arc_mode.get(k) for k in ks]
        fit = np.array([m == "fit" for m in modes], bool)
        own = p.motion[r].astype(np.int64)
        first_motion = np.where(np.array([m == "lines" for m in modes], bool), FEED, own)
        piece_code = np.repeat(np.where(first_motion == RAPID, 0, 1), counts).astype(np.int64)
        centre = self._fit_centres_flat(r, fit, piece_first, flat, ends_written)
        if centre is not None:
            first_motion = np.where(fit & np.isnan(centre["first"]), FEED, first_motion)
            piece_code = np.where(centre["fit"], np.where(centre["nan"], 1, np.repeat(own, counts)), piece_code)
        lines = p.line_index[r].astype(np.int64)
        cols = fast["cols"]
        dec = fast["dec"]
        n_flat = flat.shape[0]
        n_centre, c_val, c_letter, c_dec = (centre["n"], centre["val"], centre["letter"], centre["dec"]) \
            if centre is not None else (np.zeros(n_flat, np.int64), np.zeros((n_flat, 2)),
                                        np.zeros((n_flat, 2), np.uint8), np.zeros((n_flat, 2), np.int64))
        ok, blob, b_start, b_end = fast_write.pieces(
            fast["src"], fast["line_start"], lines, first_motion.astype(np.int64), piece_code, piece_first, flat,
            cols, fast["letters"], dec, np.ascontiguousarray(p.inch[r], np.bool_), n_centre, c_val, c_letter, c_dec,
            bool(p.format_info.leading_zero), bool(p.format_info.trailing_point), fast["sep"])
        taken[grp[ok]] = True
        return ({"line": lines[ok], "blob": blob, "start": b_start[ok], "end": b_end[ok]}, taken,
                int((counts[ok] - 1).sum()))

    def _fit_centres_flat(self, r, fit, piece_first, flat, ends_written):
        """The centre words of the fitted arcs' sub-arcs among the split lines of rows ``r`` (``fit``), per piece of
        the flat pieces ``flat`` (``_fit_centre_words`` for all of them at once: the same operations on the same
        numbers): {"n" (N,) 0 or 2, "val" (N, 2), "letter" (N, 2) uint8, "dec" (N, 2), "fit" (N,) bool (a fitted
        arc's piece), "nan" (N,) bool (a sub-arc that did not hold: straight), "first" (lines,) the first piece's
        centre X (NaN: straight, else not NaN)}, or None when no line is a fitted arc."""
        if not fit.any():
            return None
        p = self.p
        counts = np.diff(piece_first)
        n_flat = flat.shape[0]
        owner = np.repeat(np.arange(r.size), counts)
        is_fit = fit[owner]
        centres = np.full((n_flat, 3), np.nan)
        for c in np.nonzero(fit)[0].tolist():
            centres[piece_first[c] : piece_first[c + 1]] = self.arc_centres[int(r[c])]
        first = np.full(r.size, np.nan)
        first[fit] = centres[piece_first[:-1][fit], 0]
        nan = np.isnan(centres[:, 0])
        # each piece's written start: the end written before the line (first piece), else the piece before's end
        starts = np.empty((n_flat, 6))
        starts[1:] = flat[:-1]
        written_end, first_row_of_line = ends_written
        starts[piece_first[:-1]] = _written_before(p.line_index[r], written_end, first_row_of_line, p)
        numbers = _Numbers(p.format_info)
        scale = 10.0 ** xyz_decimals(p)  # (row 0 mm, row 1 inch)
        inch = p.inch[r][owner]
        sc = np.where(inch[:, None], scale[1][None, :], scale[0][None, :])
        written = np.round(starts[:, :3] * sc) / sc
        value = np.where(p.arc_incremental[r][owner][:, None], centres - written, centres)
        plane = p.arc_plane[r][owner]
        col0 = np.where(plane == 19, 1, 0)
        col1 = np.where(plane == 17, 1, 2)
        k = np.arange(n_flat)
        use = is_fit & ~nan
        letters = np.frombuffer(b"IJK", np.uint8)
        table = np.array([[numbers.decimals(c, flag) for flag in (False, True)] for c in "IJK"], np.int64)
        out = {"n": np.where(use, 2, 0).astype(np.int64), "fit": is_fit, "nan": nan, "first": first,
               "val": np.ascontiguousarray(np.stack([value[k, col0], value[k, col1]], axis=1), float),
               "letter": np.ascontiguousarray(np.stack([letters[col0], letters[col1]], axis=1)),
               "dec": np.ascontiguousarray(np.stack([table[col0, inch.astype(int)], table[col1, inch.astype(int)]],
                                                    axis=1), np.int64)}
        out["val"][~use] = 0.0
        return out

    def _fast_assemble(self, fast, texts):
        """The output text: the compiled writer's lines, the Python path's ``texts`` {line index: text}, every other
        line as it was (``"".join`` of them all, line by line)."""
        n_lines = len(self.p.lines)
        info = self.p.format_info
        mode = np.zeros(n_lines, np.int8)
        cand_of_line = np.zeros(n_lines, np.int64)
        mode[fast["line"]] = 1
        cand_of_line[fast["line"]] = fast["cand"]
        blob_start = np.zeros(n_lines, np.int64)
        blob_end = np.zeros(n_lines, np.int64)
        lis = sorted(texts)
        parts = [texts[li].encode("utf-8") for li in lis]
        if lis:
            lengths = np.fromiter(map(len, parts), np.int64, len(parts))
            mode[lis] = 2
            blob_end[lis] = np.cumsum(lengths)
            blob_start[lis] = blob_end[lis] - lengths
        blob = np.frombuffer(b"".join(parts), np.uint8)
        pieces = fast.get("pieces")
        if pieces is not None and pieces["line"].size:  # the compiled writer's split moves and fitted arcs
            mode[pieces["line"]] = 2
            blob_start[pieces["line"]] = blob.size + pieces["start"]
            blob_end[pieces["line"]] = blob.size + pieces["end"]
            blob = np.concatenate([blob, pieces["blob"]])
        # (each line is written alone: the lines shared among the kernels' threads, their bytes joined in order)
        shares = _shared(fast_write.assemble, n_lines, lambda sl: (
            fast["src"], fast["line_start"][sl.start : sl.stop + 1], mode[sl], cand_of_line[sl], fast["k"],
            fast["motion"], fast["spans"], fast["target"], fast["cols"], fast["letters"], fast["dec"], fast["inch"],
            fast["n_extra"], fast["extra_val"], fast["extra_letter"], fast["extra_dec"], fast["keep_r"],
            bool(info.leading_zero), bool(info.trailing_point), fast["sep"], blob, blob_start[sl], blob_end[sl]))
        return b"".join(shares).decode("utf-8")  # (the shares' bytes joined as they are: not copied to bytes first)

    def _centre_words(self, r, delta_end, last_written, fmt):
        """The centre words of one kept arc (``_centre_values``), formatted."""
        letters, values = self._centre_values(np.array([r]), delta_end[None], last_written[None])
        return [fmt(c, v) for c, v in zip(letters[0], values[0])]

    def _centre_values(self, r, delta_end, last_written):
        """Kept arcs' centre words: letters (K, 2) (I J, I K or J K by plane) and values (K, 2), program units. The
        centre moves by the end's correction (constant along a kept arc); incremental from the start (G91.1, the
        default) or absolute (G90.1). r : (K,) program rows; delta_end : (K, 6); last_written : (K, 6)."""
        which, values = self._centre_columns(r, delta_end, last_written)
        return np.array(list("IJK"))[which], values

    def _centre_columns(self, r, delta_end, last_written):
        """``_centre_values`` with the letters as their columns (K, 2) (0, 1, 2: I, J, K)."""
        p = self.p
        value = p.arc_center[r] + delta_end[:, :3] - np.where(p.arc_incremental[r][:, None], last_written[:, :3], 0.0)
        plane = p.arc_plane[r]
        first = np.where(plane == 19, 1, 0)  # G17: I J, G18: I K, G19: J K
        second = np.where(plane == 17, 1, 2)
        k = np.arange(r.size)
        return np.stack([first, second], axis=1), np.stack([value[k, first], value[k, second]], axis=1)

    def _fit_centre_words(self, r, centre, start, fmt):
        """The centre words of one sub-arc of a fitted arc: ``centre`` (3,) as ``.arcs`` fitted it (program
        coordinates), incremental from the written start (``start`` (6,), rounded as written: G91.1) or absolute."""
        p = self.p
        inch = bool(p.inch[r])
        if p.arc_incremental[r]:
            if not hasattr(self, "_fit_scale"):
                self._fit_scale = 10.0 ** xyz_decimals(p)  # (per unit, not per sub-arc: row 0 mm, row 1 inch)
            scale = self._fit_scale[int(inch)]
            written = np.round(np.asarray(start[:3], float) * scale) / scale
            centre = centre - written
        plane = int(p.arc_plane[r])
        cols = {17: (0, 1), 18: (0, 2), 19: (1, 2)}[plane]
        return [fmt("IJK"[c], centre[c]) for c in cols]

    def _rewrite_motion(self, body, motion, words, arc, row, sep):
        """A motion block with new axis words ``words`` (formatted): see ``rewrite_block``."""
        return rewrite_block(body, motion, words, arc=arc, was_arc=self.p.motion[row] in (ARC_CW, ARC_CCW), sep=sep)

    def _refuse_cycles_it_cannot_write(self):
        """PostError for a canned cycle the block rewrite (``_cycle_line``: hole X Y, depth Z and R along Z) cannot
        write: one in the G18 / G19 plane (its feeds not along Z) or G87 back boring (its hole is offset by I J K):
        the blocks came out with the depth in R and R at the hole (rs274 refused them; a control without that check
        would drill to the wrong depth), exit 0, in a QA pass."""
        p = self.p
        cyc = np.nonzero(p.kind == ROW_CYCLE)[0]
        if cyc.size == 0:
            return
        feeds = cyc[p.motion[cyc] == FEED]
        across = feeds[np.any(np.abs(p.end[feeds, :2] - p.start[feeds, :2]) > 1e-9, axis=1)]
        if across.size:
            raise PostError(p.source, int(p.line_no[across[0]]), "a canned cycle whose feeds are not along Z (the "
                                                                 "G18 / G19 plane): the post writes cycles in G17 "
                                                                 "only; write the holes as G1 moves")
        # G87 is modal like every cycle: the motion code in force at each cycle line (the last one before it). Read
        # only when a line holds a G87 at all (a million-line program's lines are not scanned one by one for it).
        text = "".join(p.lines)
        hits = _g87_starts(text)  # a G87 anywhere (one pass over the text)
        if not hits:
            return
        line_start = np.cumsum([0] + [len(line) for line in p.lines])
        hit_lines = np.unique(np.searchsorted(line_start, hits, side="right") - 1)
        if not any(_G87.search(_split_comment(p.lines[li])[0]) for li in hit_lines):  # in a comment only
            return
        lines = set(np.unique(p.line_index[cyc]).tolist())
        mode = None
        for li in range(max(lines) + 1):
            codes = _MOTION_CODE.findall(_split_comment(p.lines[li].rstrip("\r\n"))[0])
            mode = float(codes[-1]) if codes else mode
            if li in lines and mode == 87.0:
                raise PostError(p.source, self.p.source_line_of(li),
                                "G87 back boring: the post does not write it (its hole is offset "
                                "by I J K); write it as G0 / G1 moves")

    def _note_cycle_deviation(self, rr, ends, r_nominal, deltas, d_bottom):
        """A canned cycle writes one X Y per hole, corrected at its bottom: at the R plane and between (where the feed
        enters and runs) the correction the twin asks for differs by what the errors change along Z. The largest such
        difference is reported (``max_cycle_deviation_um``) and, over the tolerance, warned about once."""
        in_hole = ends[:, 2] <= r_nominal + 1e-9
        if not in_hole.any():
            return
        scale = np.where(self.p.inch[rr[in_hole]], MM_PER_INCH, 1.0) * 1e3  # program units -> um
        off = np.hypot(*(deltas[in_hole, :2] - d_bottom[:2]).T) * scale
        worst = float(off.max())
        self.rep.max_cycle_deviation_um = max(self.rep.max_cycle_deviation_um, worst)
        if worst > 1e3 * self.tol_mm and not self._cycle_warned:
            self._cycle_warned = True
            self.rep.warnings.append(
                f"{self.p.source}:{int(self.p.line_no[rr[0]])}: canned cycle: a hole's X Y is corrected at its bottom; "
                f"at its R plane the twin asks for a correction {worst:.2f} um away (over the {1e3 * self.tol_mm:g} um "
                "tolerance): the feed into the hole leaves its nominal axis by up to that; write the holes as G0 / G1 "
                "moves where that matters (the report's max_cycle_deviation_um is the largest over the program)")

    def _cycle_line(self, body, ks, rows, delta_prog, fmt, sep):
        """A canned-cycle block: hole position and depth from the correction at the bottom, R from the R level."""
        p = self.p
        rr = rows[ks]
        ends = p.end[rr]
        bottom = int(np.argmin(ends[:, 2]))
        d_bottom = delta_prog[ks[bottom]]
        hole = ends[bottom] + d_bottom
        # The R level: every cycle's first feed starts there. Its correction is solved at the row ending there.
        feeds = np.nonzero(p.motion[rr] == FEED)[0]
        first = int(feeds[0]) if feeds.size else 0
        r_nominal = p.start[rr[first], 2]
        at_r = np.nonzero(np.isclose(ends[:, 2], r_nominal) & (np.arange(len(rr)) < first))[0]
        d_r = delta_prog[ks[int(at_r[-1])]] if at_r.size else d_bottom
        r_level = r_nominal + d_r[2]
        self._note_cycle_deviation(rr, ends, r_nominal, delta_prog[ks], d_bottom)
        code, comment = _split_comment(body)
        toks = tokenize_line(code)
        keep = [t[1] for t in toks if not (t[0] == "word" and t[1][0].upper() in "XYZR")]
        words = [fmt("X", hole[0]), fmt("Y", hole[1]), fmt("Z", hole[2]), fmt("R", r_level)]
        pos = _word_position(keep)
        return sep.join(t for t in keep[:pos] + words + keep[pos:] if t.strip()) + comment


# --------------------------------------------------------------------------------------------------- helpers -----


# The most decimals written: 1 nm in mm, 2.5 nm in inch, 1e-6 deg (0.02 urad) for rotary words. Far below any
# machine's resolution; one over-long number in the input must not set the precision of every block (it did: ~64).
MAX_DECIMALS = {"mm": 6, "inch": 7, "rotary": 6}


class _Numbers:
    """Numbers in the input's dialect: its leading zero and trailing point, and per word letter the input's
    precision but at least 5 decimals (6 for inch lengths), so that writing does not eat the 0.1 um / 1 urad budget,
    and at most MAX_DECIMALS."""

    def __init__(self, info):
        self.info = info
        self._decimals = {}

    def decimals(self, letter: str, inch: bool) -> int:
        key = (letter, inch)
        if key not in self._decimals:
            floor = 5 if letter in "ABC" else (6 if inch else 5)
            cap = MAX_DECIMALS["rotary" if letter in "ABC" else ("inch" if inch else "mm")]
            self._decimals[key] = min(max(floor, self.info.decimals.get(letter, 0)), cap)
        return self._decimals[key]

    def formatter(self, inch: bool):
        """fmt(letter, value, inch=inch) -> the word, e.g. "X12.5"."""
        info = self.info

        def fmt(letter, value, inch=inch):
            return letter + write_number(float(value), self.decimals(letter, inch), leading_zero=info.leading_zero,
                                         trailing_point=info.trailing_point)

        fmt.decimals = lambda letter: self.decimals(letter, inch)  # (G91 increments: ``_out_value``)
        return fmt

    def words(self, letter: str, values, inch) -> list:
        """The words of ``letter`` for every value (K,), with the rows' inch flags (K,) bool."""
        out = [""] * len(values)
        for flag in (False, True):
            sel = np.nonzero(np.asarray(inch) == flag)[0]
            if sel.size == 0:
                continue
            texts = write_numbers(np.asarray(values)[sel], self.decimals(letter, flag),
                                  leading_zero=self.info.leading_zero, trailing_point=self.info.trailing_point)
            for i, t in zip(sel.tolist(), texts):
                out[i] = letter + t
        return out



def rewrite_block(body: str, motion: int, words: list, *, arc: bool, was_arc: bool, sep: str) -> str:
    """A motion block (no line ending) with new axis words ``words`` (formatted, e.g. ["X1.5", "Y2"]): its other words
    and comments kept, the motion word made ``motion`` (G0/G1 for straight moves, the arc's own for a kept arc),
    the axis words after the last G word. ``arc``: the block stays an arc (``words`` then end with its centre, or
    its R word stays); ``was_arc``: the source block was an arc (its P word goes when it becomes lines)."""
    if "(" not in body and ";" not in body:
        plain = _rewrite_plain(body, motion, words, arc, sep)
        if plain is not None:
            return plain
        code, comment = body, ""
    else:
        code, comment = _split_comment(body)  # a trailing comment keeps the space before it
    return _rewrite_tokens(code, motion, words, arc, was_arc, sep) + comment


def _rewrite_plain(code, motion, words, arc, sep):
    """``rewrite_block`` of the common block (N G X Y Z A B C I J K R F, each optional, in this order, nothing else)
    without walking its tokens; None for any other block."""
    plain = _PLAIN.match(code)
    if plain is None:
        return None
    n, g, r, f = plain.group("n", "g", "r", "f")
    keep = [n] if n else []
    keep.append(_motion_text(g, motion) if g else f"G{motion}")
    keep += words
    if r and arc:
        keep.append(r)
    if f:
        keep.append(f)
    return sep.join(keep)


def _rewrite_tokens(code, motion, words, arc, was_arc, sep):
    """``rewrite_block`` of any block's code (comments inside it kept in place)."""
    keep = []
    motion_done = False
    for m in TOKEN_PATTERN.finditer(code):
        text = m.group()
        letter = m.group(3)
        if letter is not None:
            letter = letter.upper()
            if letter in "XYZABCIJK":
                continue  # axis words are rewritten; the centre too (kept arcs) or dropped (straight moves)
            if letter == "R" and not arc:
                continue
            if letter == "P" and was_arc and not arc:
                continue  # a linearised arc's turns
            if letter == "G" and _MOTION_WORD.match(text.replace(" ", "")):
                text = _motion_text(text, motion)
                motion_done = True
        keep.append(text)
    if not motion_done:
        keep.insert(_after_line_number(keep), f"G{motion}")
    pos = _word_position(keep)
    return sep.join(keep[:pos] + words + keep[pos:])


def _shared(kernel, n, args_of) -> list:
    """``kernel(*args_of(sl))`` for contiguous shares ``sl`` of ``range(n)``, in order: on the kernels' threads where
    ``n`` is worth sharing and the kernel's ahead-of-time twin takes every share's arguments (twins release the GIL),
    else one call on ``slice(0, n)``. For kernels that treat each item of the range alone (the same numbers, the same
    bytes, shared or not)."""
    parts = thread_slices(n)
    if parts:
        out = run_twins(kernel, [args_of(sl) for sl in parts])
        if out is not None:
            return out
    return [kernel(*args_of(slice(0, n)))]


def _subdivide(owner, a, b, worst, bad):
    """(moves, fractions) of the new points that split the chords [a, b] of the moves owner found bad. Deviations of a
    chord shrink with the square of its length: about sqrt(worst) sub-pieces each."""
    nsub = np.where(bad, np.maximum(2, np.ceil(np.sqrt(worst))), 1).astype(int)
    rep_ = np.repeat(np.arange(owner.size), nsub - 1)
    j = np.arange(rep_.size) - np.repeat(np.cumsum(nsub - 1) - (nsub - 1), nsub - 1) + 1
    fr = a[rep_] + (b[rep_] - a[rep_]) * j / nsub[rep_]
    return owner[rep_], fr


def _written_before(lines, written_end, first_row_of_line, p):
    """(K, 6) the end point written before each line of ``lines`` (K,) (program coordinates of the line's own work
    system, zeros before the first move): the written end of the row before the line's first row, as the control
    holds it in the line's frame.

    Where the frame changed between the two rows (G92, G10 L2 / L20, another work system, a tool length, G20 / G21:
    ``p.offset``, ``p.rotation`` or ``p.inch`` differ), the control's position is the line's nominal start plus the
    correction written at the row before, turned and scaled into the new frame (the same machine point): a G91
    increment or an arc's start counted from the old frame's numbers was off by the frame's change (30 mm after
    ``G92 X0 Y0``, a 50 mm plunge after ``G43 H1``, a QA pass)."""
    r = first_row_of_line[lines]
    r_prev = r - 1
    out = written_end[np.maximum(r_prev, 0)]
    out[r_prev < 0] = 0.0
    a, b = np.maximum(r_prev, 0), r
    moved = (r_prev >= 0) & (np.any(p.offset[a] != p.offset[b], axis=1) | (p.inch[a] != p.inch[b]))
    if p.rotation is not None:
        moved |= (r_prev >= 0) & (p.rotation[a] != p.rotation[b])
    if not moved.any():
        return out
    i = np.nonzero(moved)[0]
    a, b = a[i], b[i]
    d = out[i] - p.end[a]  # the correction written at the row before, its frame's program units
    if p.rotation is not None:
        turn = np.radians(p.rotation[a] - p.rotation[b])
        c, s = np.cos(turn), np.sin(turn)
        d[:, 0], d[:, 1] = c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]
    scale = np.where(p.inch[a] == p.inch[b], 1.0, np.where(p.inch[b], 1.0 / MM_PER_INCH, MM_PER_INCH))
    d[:, :3] *= scale[:, None]
    out[i] = p.start[b] + d
    return out


def _motion_text(word: str, motion: int) -> str:
    """The motion word ``word`` (G0..G3 as written) made ``motion``, in the program's style (``G01`` or ``G1``)."""
    return f"G0{motion}" if word[1:].strip() in ("00", "01", "02", "03") else f"G{motion}"


def _out_value(target6, last6, letter, incremental: bool, decimals: int):
    """The value of axis word ``letter`` for the end ``target6``: itself (G90), or (G91) the increment from
    ``last6``, written as the difference of the two ends rounded to ``decimals`` as absolute words would be: the
    control adds the increments up, so rounded one by one their errors would add up along a G91 run (an arc split
    into 2,582 G91 pieces ended 5.6 um short, 20 um in inch); as differences of rounded ends they telescope to the
    rounded last end. ``round`` is correctly rounded, ties to even, as ``write_number``."""
    j = AXES.index(letter)
    if not incremental:
        return target6[j]
    scale = 10 ** decimals
    return (round(round(float(target6[j]), decimals) * scale) - round(round(float(last6[j]), decimals) * scale)) / scale


def _split_ending(line: str):
    stripped = line.rstrip("\r\n")
    return stripped, line[len(stripped):]


_STOP_CODES = (0.0, 1.0, 2.0, 30.0, 60.0)  # M codes LinuxCNC (and RS-274/NGC) executes after the block's motion


def _stop_words_taken_out(body: str):
    """(body without its stop words, the stop words as written): the M0 M1 M2 M30 M60 words of a block's code (not
    of its comments), which act after the block's motion."""
    stops, spans = [], []
    for m in TOKEN_PATTERN.finditer(body):
        if m.group(3) in ("M", "m") and m.group(4):
            try:
                code = float(m.group(4))
            except ValueError:  # (a parameter or an expression: flattened before the post; left where it is)
                continue
            if code in _STOP_CODES:
                stops.append(m.group().replace(" ", "").replace("\t", ""))
                spans.append(m.span())
    for a, b in reversed(spans):  # (one space where the word was between two others)
        before, after = body[:a].rstrip(" \t"), body[b:].lstrip(" \t")
        body = before + (" " if before.strip() and after else "") + after
    return body, stops


def _split_comment(body: str):
    """Code and trailing comment text (kept verbatim, with the space before it)."""
    code, comment, _ = _split_comment_tokens(body)
    return code, comment


def _split_comment_tokens(body: str):
    """As ``_split_comment``, plus the tokens of the code when it is the whole body (else None)."""
    toks = tokenize_line(body)
    for kind, text, start, _ in toks:
        if kind == "comment":
            j = start
            while j > 0 and body[j - 1] in " \t":
                j -= 1
            # Only a comment at the end of the line is split off; inline comments stay in the code.
            if all(t[0] == "comment" for t in toks if t[2] >= start):
                return body[:j], body[j:], None
    return body, "", toks


def _word_position(tokens):
    """Where axis words go: right after the last G word, or after the line number."""
    pos = max([i for i, t in enumerate(tokens) if t[:1].upper() == "G"], default=-1) + 1
    return max(pos, _after_line_number(tokens))


def _after_line_number(tokens):
    return 1 if tokens and tokens[0][:1].upper() == "N" else 0


def _replace_feed(body, feed, fmt, sep):
    code, comment = _split_comment(body)
    toks = tokenize_line(code)
    out = [fmt("F", feed, inch=False) if (t[0] == "word" and t[1][0].upper() == "F") else t[1] for t in toks]
    return sep.join(out) + comment


def _arcs_geometry(p: Program, rs):
    """Per arc row in ``rs``: in-plane axis indices i, j and the normal one, start angle (rad), sweep (rad, from start
    to end in the arc's sense, a full turn when they coincide, plus the extra turns of P), start and end radius
    (program units)."""
    ii, jj = plane_columns(p.arc_plane[rs])
    c, s, e = p.arc_center[rs], p.start[rs], p.end[rs]
    ar = np.arange(rs.size)
    ci, cj = c[ar, ii], c[ar, jj]
    si, sj, ei, ej = s[ar, ii], s[ar, jj], e[ar, ii], e[ar, jj]
    a0 = np.arctan2(sj - cj, si - ci)
    a1 = np.arctan2(ej - cj, ei - ci)
    ccw = p.motion[rs] == ARC_CCW
    sweep = np.where(ccw, (a1 - a0) % (2 * np.pi), (a0 - a1) % (2 * np.pi))
    sweep = np.where(sweep < 1e-12, 2 * np.pi, sweep)
    sweep = sweep + 2 * np.pi * (np.maximum(p.arc_turns[rs].astype(int), 1) - 1)
    return ii, jj, 3 - ii - jj, a0, sweep, np.hypot(si - ci, sj - cj), np.hypot(ei - ci, ej - cj)


def _arcs_points(p: Program, rs, counts, geometry=None) -> np.ndarray:
    """(sum(counts + 1), 6) points along the arcs ``rs`` (program coordinates), counts[i] + 1 from each one's start to
    its end, angle and radius linear in the fraction, the helical axis (and every other axis) linear. ``geometry``: the
    arcs' ``_arcs_geometry``, if the caller has it."""
    rs = np.asarray(rs, int)
    counts = np.asarray(counts, int)
    if rs.size == 0:
        return np.zeros((0, 6))
    ar = np.arange(rs.size)
    ii, jj, nn, a0, sweep, rad0, rad1 = _arcs_geometry(p, rs) if geometry is None else geometry
    c, s, e = p.arc_center[rs], p.start[rs], p.end[rs]
    ci, cj = c[ar, ii], c[ar, jj]
    ccw = p.motion[rs] == ARC_CCW
    sign = np.where(ccw, 1.0, -1.0)
    npts = counts + 1
    owner = np.repeat(ar, npts)
    first = np.r_[0, np.cumsum(npts)[:-1]]
    j = np.arange(owner.size) - first[owner]
    t = j * (1.0 / counts)[owner]  # as np.linspace(0, 1, n + 1): i * (1 / n), the last exactly 1
    last = first + counts
    t[last] = 1.0
    ang = a0[owner] + (sign * sweep)[owner] * t
    rad = rad0[owner] + (rad1 - rad0)[owner] * t
    so, eo = s[owner], e[owner]
    pts = so + t[:, None] * (eo - so)  # (the helical axis' column is this, linear in the fraction)
    io, jo = ii[owner], jj[owner]
    k = np.arange(owner.size)
    pts[k, io] = ci[owner] + rad * np.cos(ang)
    pts[k, jo] = cj[owner] + rad * np.sin(ang)
    pts[last] = e
    return pts
