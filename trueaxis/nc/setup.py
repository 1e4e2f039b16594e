"""The controller's setup: work offsets, G92 shift, home positions and tool offsets that live in the control, not in
the program (DESIGN §5, "Controller setup").

Three sources, read strictly (every problem is a :class:`SetupError` whose text is one line, ``file:line: message``):

- LinuxCNC's parameter file (``.var``, :func:`read_var`): ``NUMBER VALUE`` per line, as ``interp_parameter_io`` reads
  it. Used here: G28 home 5161-5166 and G30 home 5181-5186 (X Y Z A B C, machine coordinates), the G92 shift
  5211-5216 (applied at start when 5210 is 1), the active system 5220 (1 = G54 ... 9 = G59.3), and the work offsets
  G54..G59.3 at 5221 + 20 (k - 1) (X Y Z A B C at +0..+5, the XY rotation R in degrees at +9). Every one of these
  must be in the file (a parameter file LinuxCNC wrote has them all): a missing or non-numeric one is refused.
- LinuxCNC's tool table (:func:`read_tool_table`): ``T P X Y Z A B C U V W D I J Q ;comment``, each word a letter and
  a number; T is required; X..C are the tool's offsets (Z its length), D its diameter.
- A setup file (TOML, :func:`read_setup_file`, docs/setup_file.md) for controls without those files (Fanuc, Hurco):
  work offsets by name, tool lengths and radii by number, how the control applies the tool length (``G43 H`` or at
  the tool change), the units of the values, the program units the setup is meant for.

Both LinuxCNC files are in the machine's units (LinuxCNC's ``[TRAJ] LINEAR_UNITS``; the standalone ``rs274`` reads
them in inches), given by the caller. Everything is kept in mm and degrees here. Each value remembers where it came
from (``params.var:5221-5226``), for the report and the output header.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .grammar import NUMBER

MM_PER_INCH = 25.4
AXES = "XYZABC"
# work systems, index 1..9 as LinuxCNC numbers them (parameter 5220, G10 L2 P)
SYSTEMS = ("G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3")
TOOL_LENGTH_MODES = ("G43", "tool_change")
_LINEAR = np.array([True, True, True, False, False, False])


class SetupError(ValueError):
    """Bad setup input; ``str()`` is one line, ``file:line: message`` (or ``file: message``)."""


def system_name(index: int) -> str:
    """1 -> "G54", ..., 9 -> "G59.3"."""
    return SYSTEMS[index - 1]


def system_index(name: str) -> int:
    """"G54" -> 1, ..., "G59.3" -> 9 (case-insensitive)."""
    key = name.strip().upper()
    if key not in SYSTEMS:
        raise KeyError(name)
    return SYSTEMS.index(key) + 1


@dataclass
class Offset:
    """A work offset, G92 shift or home position: values (6,) X Y Z mm, A B C deg; rotation about Z (deg, work
    offsets only); where it came from."""

    values: np.ndarray
    source: str
    rotation_deg: float = 0.0


@dataclass
class ToolOffset:
    """A tool's offsets (6,) X Y Z mm (Z: the tool length), A B C deg; diameter (mm, or None); where it came from."""

    offset: np.ndarray
    source: str
    diameter: float | None = None

    @property
    def length(self) -> float:
        return float(self.offset[2])


@dataclass
class Setup:
    """What the post knows of the control. Missing entries are unknown (not zero): a program that needs one is
    refused, unless ``offsets_zero`` (the user said zero is meant).

    work_offsets : system index (1..9) -> Offset
    g92 : the G92 shift in force at program start (None: unknown), g92_stored: the stored one (G92.3 restores it)
    active : the work system active at program start (None: unknown; G54 assumed for programs that select none)
    home : {"G28": Offset, "G30": Offset} (machine coordinates)
    tools : tool (or H offset) number -> ToolOffset
    tool_length : "G43" (applied by G43 H) or "tool_change" (applied at M6, as Hurco and some Fanuc setups do)
    program_units : "mm" / "inch" when the setup is meant for programs in those units (None: any)
    machine_units : the control's machine units where the user gave them with a LinuxCNC file (None: not given)
    """

    work_offsets: dict = field(default_factory=dict)
    g92: Offset | None = None
    g92_stored: Offset | None = None
    active: int | None = None
    active_source: str = ""
    home: dict = field(default_factory=dict)
    tools: dict = field(default_factory=dict)
    tool_length: str = "G43"
    program_units: str | None = None
    machine_units: str | None = None
    offsets_zero: bool = False
    files: list = field(default_factory=list)

    @property
    def given(self) -> bool:
        """True when anything came from a file."""
        return bool(self.files)

    def describe(self) -> str:
        """One line naming the setup, for the output header: its files (or that none was given) and options."""
        parts = list(self.files) or ["none given"]
        if self.tool_length != "G43":
            parts.append(f"tool length at {self.tool_length.replace('_', ' ')}")
        if self.offsets_zero:
            parts.append("--offsets-zero")
        return ", ".join(parts)

    def merged(self, other: "Setup") -> "Setup":
        """This setup completed by ``other`` (entries of ``self`` win); files listed together."""
        out = Setup(
            work_offsets={**other.work_offsets, **self.work_offsets},
            g92=self.g92 or other.g92,
            g92_stored=self.g92_stored or other.g92_stored,
            active=self.active if self.active is not None else other.active,
            active_source=self.active_source if self.active is not None else other.active_source,
            home={**other.home, **self.home},
            tools={**other.tools, **self.tools},
            tool_length=self.tool_length if self.tool_length != "G43" else other.tool_length,
            program_units=self.program_units or other.program_units,
            machine_units=self.machine_units or other.machine_units,
            offsets_zero=self.offsets_zero or other.offsets_zero,
            files=self.files + [f for f in other.files if f not in self.files],
        )
        return out


def _scale(units: str, where: str) -> float:
    if units not in ("mm", "inch"):
        raise SetupError(f"{where}: units must be 'mm' or 'inch', got {units!r}")
    return MM_PER_INCH if units == "inch" else 1.0


def _to_mm(values, scale: float) -> np.ndarray:
    v = np.array(values, float)
    return np.where(_LINEAR, v * scale, v)


def _read_text(path, what: str) -> str:
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise SetupError(f"{path}: {what} not found") from None
    except OSError as exc:
        raise SetupError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    if b"\x00" in data:
        raise SetupError(f"{path}:1: binary data (NUL byte): not a {what}")
    return data.decode("utf-8", errors="replace")


def _number(text: str, where: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise SetupError(f"{where}: {what}: {text!r} is not a number") from None
    if not math.isfinite(v) or abs(v) >= 1e9:
        raise SetupError(f"{where}: {what}: {text!r} is not a finite number below 1e9")
    return v


# -------------------------------------------------------------------------------------------- LinuxCNC .var ----
def var_parameters(text: str, source: str) -> tuple[dict, dict]:
    """(number -> value, number -> 1-based line) of a LinuxCNC parameter file. Blank lines are skipped; any other line
    must be ``NUMBER VALUE`` (more fields are ignored, as LinuxCNC does); a number given twice is refused."""
    values, lines = {}, {}
    for n, raw in enumerate(text.splitlines(), 1):
        fields = raw.split()
        if not fields:
            continue
        where = f"{source}:{n}"
        if len(fields) < 2:
            raise SetupError(f"{where}: expected 'NUMBER VALUE', got {raw.strip()!r}")
        try:
            number = int(fields[0])
        except ValueError:
            raise SetupError(f"{where}: parameter number {fields[0]!r} is not a whole number") from None
        if number in values:
            raise SetupError(f"{where}: parameter {number} given twice (first at line {lines[number]})")
        values[number] = _number(fields[1], where, f"parameter {number}")
        lines[number] = n
    return values, lines


def read_var(path, units: str = "mm") -> Setup:
    """The setup in a LinuxCNC parameter file (``units``: the machine's linear units, mm or inch)."""
    scale = _scale(units, str(path))
    source = str(path)
    values, _ = var_parameters(_read_text(path, "parameter file"), source)

    def need(numbers, what):
        missing = [k for k in numbers if k not in values]
        if missing:
            raise SetupError(f"{source}: parameter {missing[0]} ({what}) is missing; a parameter file written by "
                             "LinuxCNC has it")
        return [values[k] for k in numbers]

    setup = Setup(files=[source])
    for key, base in (("G28", 5161), ("G30", 5181)):
        v = need(range(base, base + 6), f"{key} home position X Y Z A B C")
        setup.home[key] = Offset(_to_mm(v, scale), f"{source}:{base}-{base + 5}")
    applied = need([5210], "G92 in force, 1 or 0")[0]
    g92 = Offset(_to_mm(need(range(5211, 5217), "G92 shift X Y Z A B C"), scale), f"{source}:5211-5216")
    setup.g92_stored = g92
    setup.g92 = g92 if applied != 0.0 else Offset(np.zeros(6), f"{source}:5210 (G92 not in force)")
    active = need([5220], "active work system")[0]
    if active not in range(1, 10):
        raise SetupError(f"{source}: parameter 5220 (active work system) must be 1 to 9 (G54 to G59.3), got {active:g}")
    setup.active, setup.active_source = int(active), f"{source}:5220"
    for k in range(1, 10):
        base = 5221 + 20 * (k - 1)
        name = system_name(k)
        v = need(range(base, base + 6), f"{name} X Y Z A B C")
        r = need([base + 9], f"{name} rotation R")[0]
        setup.work_offsets[k] = Offset(_to_mm(v, scale), f"{source}:{base}-{base + 5},{base + 9}", float(r))
    return setup


# -------------------------------------------------------------------------------------- LinuxCNC tool table ----
_TOOL_WORD = re.compile(r"^([A-Za-z])(" + NUMBER + r")$")
_TOOL_LETTERS = "TPXYZABCUVWDIJQ"


def read_tool_table(path, units: str = "mm") -> Setup:
    """The tools of a LinuxCNC tool table (``units``: the machine's linear units, mm or inch)."""
    scale = _scale(units, str(path))
    source = str(path)
    setup = Setup(files=[source])
    lines = {}
    for n, raw in enumerate(_read_text(path, "tool table").splitlines(), 1):
        body = raw.split(";", 1)[0].strip()
        if not body:
            continue
        where = f"{source}:{n}"
        words = {}
        for token in body.split():
            m = _TOOL_WORD.match(token)
            if m is None or m.group(1).upper() not in _TOOL_LETTERS:
                raise SetupError(f"{where}: cannot read {token!r}: tool table words are a letter of "
                                 f"{' '.join(_TOOL_LETTERS)} and a number")
            letter = m.group(1).upper()
            if letter in words:
                raise SetupError(f"{where}: {letter} given twice")
            words[letter] = _number(m.group(2), where, letter)
        if "T" not in words:
            raise SetupError(f"{where}: no T word (tool number)")
        tool = words["T"]
        if tool != int(tool) or tool < 0:
            raise SetupError(f"{where}: tool number T{tool:g} is not a whole number >= 0")
        tool = int(tool)
        if tool in lines:
            raise SetupError(f"{where}: tool {tool} given twice (first at line {lines[tool]})")
        lines[tool] = n
        offset = _to_mm([words.get(a, 0.0) for a in AXES], scale)
        diameter = words["D"] * scale if "D" in words else None
        setup.tools[tool] = ToolOffset(offset, where, diameter)
    return setup


# ------------------------------------------------------------------------------------------------ setup file ----
_SETUP_KEYS = {"setup", "work_offsets", "g92", "home", "tools"}
_HEAD_KEYS = {"name", "units", "program_units", "tool_length", "active"}


def read_setup_file(path) -> Setup:
    """A setup file (TOML; docs/setup_file.md)."""
    source = str(path)
    text = _read_text(path, "setup file")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SetupError(f"{source}: not valid TOML: {exc}") from None
    return parse_setup(data, source)


def _table(value, where):
    if not isinstance(value, dict):
        raise SetupError(f"{where}: expected a table, got {type(value).__name__}")
    return value


def _value(value, where) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or abs(value) >= 1e9:
        raise SetupError(f"{where}: expected a finite number, got {value!r}")
    return float(value)


def _axes_table(value, where, scale, extra=()) -> tuple[np.ndarray, dict]:
    t = _table(value, where)
    out = np.zeros(6)
    rest = {}
    for key, v in t.items():
        k = key.upper()
        if k in AXES:
            out[AXES.index(k)] = _value(v, f"{where}.{key}")
        elif k in extra:
            rest[k] = _value(v, f"{where}.{key}")
        else:
            raise SetupError(f"{where}.{key}: unknown key (expected {' '.join(AXES + ''.join(extra))})")
    return _to_mm(out, scale), rest


def parse_setup(data: dict, source: str = "<setup>") -> Setup:
    """A setup from the TOML data of a setup file; axes not named in an entry are zero."""
    for key in data:
        if key not in _SETUP_KEYS:
            raise SetupError(f"{source}: {key}: unknown key (expected {', '.join(sorted(_SETUP_KEYS))})")
    head = _table(data.get("setup", {}), f"{source}: setup")
    for key in head:
        if key not in _HEAD_KEYS:
            raise SetupError(f"{source}: setup.{key}: unknown key (expected {', '.join(sorted(_HEAD_KEYS))})")
    units = head.get("units")
    if units is None:
        raise SetupError(f"{source}: setup.units is required: \"mm\" or \"inch\" (the units of the values)")
    scale = _scale(units, f"{source}: setup.units")
    setup = Setup(files=[source])
    pu = head.get("program_units")
    if pu is not None and pu not in ("mm", "inch"):
        raise SetupError(f"{source}: setup.program_units must be \"mm\" or \"inch\", got {pu!r}")
    setup.program_units = pu
    mode = head.get("tool_length", "G43")
    if mode not in TOOL_LENGTH_MODES:
        raise SetupError(f"{source}: setup.tool_length must be one of {', '.join(TOOL_LENGTH_MODES)}, got {mode!r}")
    setup.tool_length = mode
    if "active" in head:
        try:
            setup.active = system_index(str(head["active"]))
        except KeyError:
            raise SetupError(f"{source}: setup.active: {head['active']!r} is not a work system "
                             f"({' '.join(SYSTEMS)})") from None
        setup.active_source = f"{source}: setup.active"
    for name, entry in _table(data.get("work_offsets", {}), f"{source}: work_offsets").items():
        try:
            k = system_index(name)
        except KeyError:
            raise SetupError(f"{source}: work_offsets.{name}: not a work system ({' '.join(SYSTEMS)})") from None
        values, rest = _axes_table(entry, f"{source}: work_offsets.{name}", scale, extra=("R",))
        setup.work_offsets[k] = Offset(values, f"{source}: work_offsets.{name}", rest.get("R", 0.0))
    if "g92" in data:
        values, _ = _axes_table(data["g92"], f"{source}: g92", scale)
        setup.g92 = setup.g92_stored = Offset(values, f"{source}: g92")
    for name, entry in _table(data.get("home", {}), f"{source}: home").items():
        if name.upper() not in ("G28", "G30"):
            raise SetupError(f"{source}: home.{name}: expected G28 or G30")
        values, _ = _axes_table(entry, f"{source}: home.{name}", scale)
        setup.home[name.upper()] = Offset(values, f"{source}: home.{name}")
    for number, entry in _table(data.get("tools", {}), f"{source}: tools").items():
        where = f"{source}: tools.{number}"
        try:
            tool = int(number)
        except ValueError:
            raise SetupError(f"{where}: the key must be a tool (or H offset) number") from None
        if tool < 0:
            raise SetupError(f"{where}: the tool number must be >= 0")
        t = _table(entry, where)
        unknown = set(t) - {"length", "radius", "diameter", "x", "X"}
        if unknown:
            raise SetupError(f"{where}.{sorted(unknown)[0]}: unknown key (expected length, radius or diameter, x)")
        if "length" not in t:
            raise SetupError(f"{where}: length is required")
        offset = np.zeros(6)
        offset[2] = _value(t["length"], f"{where}.length") * scale
        for key in ("x", "X"):
            if key in t:
                offset[0] = _value(t[key], f"{where}.{key}") * scale
        diameter = None
        if "radius" in t and "diameter" in t:
            raise SetupError(f"{where}: give radius or diameter, not both")
        if "radius" in t:
            diameter = 2 * _value(t["radius"], f"{where}.radius") * scale
        elif "diameter" in t:
            diameter = _value(t["diameter"], f"{where}.diameter") * scale
        setup.tools[tool] = ToolOffset(offset, where, diameter)
    return setup


def load_setup(*, var=None, tool_table=None, setup_file=None, machine_units: str = "mm",
               offsets_zero: bool = False) -> Setup:
    """The setup from the files given (any of them; LinuxCNC's files win over the setup file where both give a
    value); ``offsets_zero``: what none of them gives is zero, by the user's word."""
    out = Setup()
    if var is not None:
        out = out.merged(read_var(var, machine_units))
    if tool_table is not None:
        out = out.merged(read_tool_table(tool_table, machine_units))
    if var is not None or tool_table is not None:
        out.machine_units = machine_units  # (the LinuxCNC files' units are the control's machine units)
    if setup_file is not None:
        out = out.merged(read_setup_file(setup_file))
    out.offsets_zero = bool(offsets_zero)
    return out
