"""Read and strictly validate a machine file (TOML, format 1; DESIGN §4, docs/machine_file.md).

Every problem is collected with its key path, and all of them are reported together by ``MachineFileError``: one line
per problem, so a user fixes a file in one go.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np

from .error_functions import fourier_series, legendre_series, table
from .model import (
    AXIS_ORDER,
    DIRECTION_LETTER,
    ERROR_DIRECTIONS,
    SQUARENESS,
    Axis,
    ErrorSet,
    Machine,
    ResponseSurface,
    Tool,
    rotary_location_names,
    unit_of,
)
from .transforms import UNIT
from .turning_force import TURNING_KEYS, TurningCoefficients

DEFAULT_ABOUT = {"A": "X", "B": "Y", "C": "Z"}
CUTTING_KEYS = ("Ktc", "Krc", "Kac", "Kte", "Kre", "Kae")


class MachineFileError(ValueError):
    """A machine file that cannot be used; ``problems`` holds one "key.path: message" line per problem."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = list(problems)
        super().__init__("\n".join(f"{source}: {p}" for p in self.problems))


# Physical ranges: a value beyond these is a typing error, not a machine (DESIGN §4 units). They keep 1e308 and the
# like from reaching the twin, where they would overflow to infinity far from the key that caused it.
LIMIT_LENGTH_MM = 10_000.0          # travel, pivots, part origin, tool sizes: no machine tool is 10 m from its origin
LIMIT_ERROR_UM = 10_000.0           # a location or component error of 10 mm is a wrong file, not a machine
LIMIT_ERROR_URAD = 100_000.0        # 0.1 rad = 5.7 deg
LIMIT_COMPLIANCE_UM_PER_N = 100.0   # 0.01 N/um: softer than any machine tool structure
LIMIT_FORCE_N = 100_000.0
LIMIT_CUTTING = 100_000.0           # N/mm2 or N/mm


class _Checker:
    """Collects problems while reading; each ``get_*`` returns a usable default so reading can go on."""

    def __init__(self):
        self.problems: list[str] = []

    def fail(self, path: str, message: str):
        self.problems.append(f"{path}: {message}")

    def table(self, data, path, allowed, required=()):
        if not isinstance(data, dict):
            self.fail(path, f"expected a table, got {type(data).__name__}")
            return {}
        for key in data:
            if key not in allowed:
                self.fail(f"{path}.{key}" if path else key, "unknown key")
        for key in required:
            if key not in data:
                self.fail(f"{path}.{key}" if path else key, "missing")
        return data

    def number(self, value, path, positive=False, nonnegative=False, default=None, limit=None):
        """A finite number (within +-limit when given); else the problem is recorded and ``default`` returned."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(path, f"expected a number, got {type(value).__name__} {value!r}")
            return default
        if not math.isfinite(value):
            self.fail(path, f"must be finite, got {value}")
            return default
        if limit is not None and abs(value) > limit:
            self.fail(path, f"{value:g} is beyond the physical range +-{limit:g}")
            return default
        if positive and value <= 0:
            self.fail(path, f"must be positive, got {value}")
            return default
        if nonnegative and value < 0:
            self.fail(path, f"must not be negative, got {value}")
            return default
        return float(value)

    def numbers(self, value, path, length=None, limit=None):
        if not isinstance(value, list):
            self.fail(path, f"expected an array of numbers, got {type(value).__name__}")
            return None
        if length is not None and len(value) != length:
            self.fail(path, f"expected {length} numbers, got {len(value)}")
            return None
        out = [self.number(v, f"{path}[{i}]", limit=limit) for i, v in enumerate(value)]
        return None if any(v is None for v in out) else np.asarray(out, dtype=float)

    def string(self, value, path, choices=None):
        if not isinstance(value, str):
            self.fail(path, f"expected a string, got {type(value).__name__}")
            return None
        if choices is not None and value not in choices:
            self.fail(path, f"must be one of {', '.join(choices)}; got {value!r}")
            return None
        return value


def load_machine(path: str | Path) -> Machine:
    """Read a machine file; raise MachineFileError listing every problem (key path in each line)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark, as some Windows editors write, is not TOML
    except FileNotFoundError:
        raise MachineFileError(str(path), ["file not found"]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MachineFileError(str(path), [f"cannot read: {exc}"]) from None
    return parse_machine(text, source=str(path))


def parse_machine(text: str, source: str = "<string>") -> Machine:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise MachineFileError(source, [f"not valid TOML: {exc}"]) from None
    ck = _Checker()
    machine = _read(data, ck, source)
    if ck.problems:
        raise MachineFileError(source, ck.problems)
    return machine


def _read(data, ck: _Checker, source: str) -> Machine | None:
    ck.table(
        data,
        "",
        {"machine", "kinematics", "axes", "tool", "workpiece", "location", "component", "force", "loaded", "cutting"},
        required=("machine", "kinematics", "axes", "tool"),
    )
    head = ck.table(data.get("machine", {}), "machine", {"name", "kind", "format", "note", "setup"},
                    ("name", "kind", "format"))
    name = ck.string(head.get("name", ""), "machine.name") or ""
    kind = ck.string(head.get("kind", "mill"), "machine.kind", ("mill", "lathe")) or "mill"
    if "format" in head and head["format"] != 1:
        ck.fail("machine.format", f"this trueaxis reads format 1, the file says {head['format']!r}")
    note = ck.string(head.get("note", ""), "machine.note") or ""
    # the default setup of the control (docs/setup_file.md), relative to the machine file's folder
    setup = ck.string(head.get("setup", ""), "machine.setup") or ""
    if setup and source not in ("<string>", "<memory>"):
        setup = str(Path(source).parent / setup)

    axes = _read_axes(data.get("axes", {}), ck)
    wp, tl = _read_kinematics(data.get("kinematics", {}), axes, ck)
    rotary_sense = data.get("kinematics", {}).get("rotary_sense", "iso") if isinstance(data.get("kinematics"),
                                                                                        dict) else "iso"
    if rotary_sense not in ROTARY_SENSES:
        ck.fail("kinematics.rotary_sense", f"expected one of {', '.join(map(repr, ROTARY_SENSES))}, got "
                f"{rotary_sense!r}")
        rotary_sense = "iso"
    kin = data.get("kinematics", {}) if isinstance(data.get("kinematics"), dict) else {}
    output_mode = kin.get("output_mode", "joint")
    if output_mode not in OUTPUT_MODES:
        ck.fail("kinematics.output_mode", f"expected one of {', '.join(map(repr, OUTPUT_MODES))}, got "
                f"{output_mode!r}")
        output_mode = "joint"
    tcp_code = kin.get("tcp_code", "G43.4")
    if tcp_code not in TCP_CODES:
        ck.fail("kinematics.tcp_code", f"expected one of {', '.join(map(repr, TCP_CODES))}, got {tcp_code!r}")
        tcp_code = "G43.4"
    axes = {a: Axis(**{**ax.__dict__, "branch": "workpiece" if a in wp else "tool"}) for a, ax in axes.items()}

    t = ck.table(
        data.get("tool", {}), "tool", {"length", "radius", "flutes", "flute_length", "helix_deg"}, ("length", "radius")
    )
    flutes = t.get("flutes", 4)
    if isinstance(flutes, bool) or not isinstance(flutes, int) or flutes < 1:
        ck.fail("tool.flutes", f"expected a positive whole number, got {flutes!r}")
        flutes = 4
    tool = Tool(
        length=ck.number(t.get("length", 100.0), "tool.length", positive=True, default=100.0, limit=LIMIT_LENGTH_MM),
        radius=ck.number(t.get("radius", 5.0), "tool.radius", positive=True, default=5.0, limit=LIMIT_LENGTH_MM),
        flutes=flutes,
        flute_length=ck.number(t.get("flute_length", 30.0), "tool.flute_length", positive=True, default=30.0,
                               limit=LIMIT_LENGTH_MM),
        helix_deg=ck.number(t.get("helix_deg", 30.0), "tool.helix_deg", nonnegative=True, default=30.0, limit=89.0),
    )
    w = ck.table(data.get("workpiece", {}), "workpiece", {"origin"})
    origin = ck.numbers(w.get("origin", [0.0, 0.0, 0.0]), "workpiece.origin", 3, limit=LIMIT_LENGTH_MM)
    origin = np.zeros(3) if origin is None else origin

    layout = Machine(name, kind, axes, wp, tl, tool, origin, ErrorSet(), source=source)
    errors = _read_error_set(data, "", layout, ck)

    loaded = loaded_force = None
    if "loaded" in data:
        ld = ck.table(data["loaded"], "loaded", {"force_n", "location", "component"}, ("force_n",))
        loaded_force = ck.numbers(ld.get("force_n", [0.0, 0.0, 0.0]), "loaded.force_n", 3, limit=LIMIT_FORCE_N)
        loaded = _read_error_set(ld, "loaded.", layout, ck)

    compliance, surfaces = None, ()
    if "force" in data:
        f = ck.table(data["force"], "force", {"compliance_um_per_n", "surface"})
        if "compliance_um_per_n" in f:
            rows = f["compliance_um_per_n"]
            if not isinstance(rows, list) or len(rows) != 3:
                ck.fail("force.compliance_um_per_n", "expected a 3x3 array (rows of 3 numbers)")
            else:
                got = [ck.numbers(r, f"force.compliance_um_per_n[{i}]", 3, limit=LIMIT_COMPLIANCE_UM_PER_N) for i, r in enumerate(rows)]
                if all(g is not None for g in got):
                    compliance = np.vstack(got)
        surfaces = tuple(_read_surfaces(f.get("surface", []), axes, ck))

    cutting = None
    if "cutting" in data:
        # A mill's [cutting] holds the milling coefficients (all six), a lathe's the turning ones (Kienzle's kc11
        # and mc required; see trueaxis.machine.turning_force).
        keys, required = (TURNING_KEYS, ("kc11", "mc")) if kind == "lathe" else (CUTTING_KEYS, CUTTING_KEYS)
        c = ck.table(data["cutting"], "cutting", {"material", *keys}, required)
        cutting = {"material": ck.string(c.get("material", ""), "cutting.material") or ""}
        for key in keys:
            if key in c:
                cutting[key] = ck.number(c[key], f"cutting.{key}", nonnegative=True, default=0.0, limit=LIMIT_CUTTING)
        if kind == "lathe" and all(key in cutting for key in ("kc11", "mc")):
            try:
                TurningCoefficients.from_mapping(cutting)
            except ValueError as exc:
                ck.fail("cutting", str(exc))

    return Machine(
        name=name,
        kind=kind,
        axes=axes,
        bed_to_workpiece=wp,
        bed_to_tool=tl,
        tool=tool,
        workpiece_origin=origin,
        errors=errors,
        loaded=loaded,
        loaded_force_n=loaded_force,
        compliance_um_per_n=compliance,
        surfaces=surfaces,
        cutting=cutting,
        note=note,
        source=source,
        setup=setup,
        rotary_sense=rotary_sense,
        output_mode=output_mode,
        tcp_code=tcp_code,
    )


def _read_axes(data, ck: _Checker) -> dict[str, Axis]:
    ck.table(data, "axes", set(AXIS_ORDER))
    axes = {}
    for name in AXIS_ORDER:
        if name not in data:
            continue
        path = f"axes.{name}"
        spec = ck.table(data[name], path, {"type", "travel", "about", "pivot"}, ("type",))
        kind = ck.string(spec.get("type", "linear"), f"{path}.type", ("linear", "rotary")) or "linear"
        if kind == "linear" and name not in "XYZ":
            ck.fail(f"{path}.type", f"axis {name} is a rotary axis letter; linear axes are X, Y, Z")
        if kind == "rotary" and name not in "ABC":
            ck.fail(f"{path}.type", f"axis {name} is a linear axis letter; rotary axes are A, B, C")
        travel = None
        if "travel" in spec:
            tr = ck.numbers(spec["travel"], f"{path}.travel", 2,
                            limit=36_000.0 if name in "ABC" else LIMIT_LENGTH_MM)
            if tr is not None:
                if tr[0] >= tr[1]:
                    ck.fail(f"{path}.travel", f"must be [low, high] with low < high, got "
                                              f"[{', '.join(f'{float(v):g}' for v in tr)}]")
                else:
                    travel = tuple(np.radians(tr)) if kind == "rotary" else (float(tr[0]), float(tr[1]))
        pivot = np.zeros(3)
        about = None
        if kind == "rotary":
            about = ck.string(spec.get("about", DEFAULT_ABOUT.get(name, "Z")), f"{path}.about", ("X", "Y", "Z")) or "Z"
            if "pivot" in spec:
                p = ck.numbers(spec["pivot"], f"{path}.pivot", 3, limit=LIMIT_LENGTH_MM)
                pivot = p if p is not None else pivot
            direction = UNIT[about]
        else:
            for key in ("about", "pivot"):
                if key in spec:
                    ck.fail(f"{path}.{key}", "only rotary axes have this key")
            direction = UNIT.get(name, UNIT["X"])
        axes[name] = Axis(name, kind, direction, pivot, travel, branch="", about=about)
    if not axes:
        ck.fail("axes", "no axes")
    return axes


ROTARY_SENSES = ("iso", "linuxcnc-trt")
OUTPUT_MODES = ("joint", "tcp")  # what the post writes: joints, or tool-centre-point positions (postproc.tcp)
TCP_CODES = ("G43.4", "G43")  # the code written in place of the program's G43 in TCP output


def _read_kinematics(data, axes, ck: _Checker):
    k = ck.table(data, "kinematics", {"bed_to_workpiece", "bed_to_tool", "rotary_sense", "output_mode", "tcp_code"},
                 ("bed_to_workpiece", "bed_to_tool"))
    branches = []
    for key in ("bed_to_workpiece", "bed_to_tool"):
        value = k.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            ck.fail(f"kinematics.{key}", "expected an array of axis letters")
            value = []
        for v in value:
            if v not in axes:
                ck.fail(f"kinematics.{key}", f"axis {v!r} is not defined in [axes]")
        branches.append(tuple(v for v in value if v in axes))
    listed = branches[0] + branches[1]
    for a in sorted(set(listed)):
        if listed.count(a) > 1:
            ck.fail("kinematics", f"axis {a} appears more than once")
    for a in axes:
        if a not in listed:
            ck.fail("kinematics", f"axis {a} is defined in [axes] but is on neither branch")
    return branches[0], branches[1]


def _read_error_set(data, prefix: str, layout: Machine, ck: _Checker) -> ErrorSet:
    location = {}
    valid = layout.location_names()
    if "location" in data:
        loc = ck.table(data["location"], f"{prefix}location", set(valid) | _all_location_names())
        for key, value in loc.items():
            if key not in valid:
                if key in _all_location_names():
                    ck.fail(f"{prefix}location.{key}", f"{key} does not exist for this machine's axes ({_layout_word(layout)})")
                continue
            v = ck.number(value, f"{prefix}location.{key}",
                          limit=_error_limit(key))
            if v is not None and v != 0.0:
                location[key] = v
    components = {}
    comp_data = data.get("component", {})
    if not isinstance(comp_data, dict):
        ck.fail(f"{prefix}component", "expected tables [component.AXIS]")
        comp_data = {}
    for axis_name, spec in comp_data.items():
        path = f"{prefix}component.{axis_name}"
        if axis_name not in layout.axes:
            ck.fail(path, f"axis {axis_name!r} is not defined in [axes]")
            continue
        components[axis_name] = _read_components(spec, path, layout.axes[axis_name], ck)
    return ErrorSet(location=location, components=components)


def _error_limit(name: str) -> float:
    """Physical range of an error parameter's value in the file's unit (um or urad)."""
    return LIMIT_ERROR_URAD if unit_of(name) == "urad" else LIMIT_ERROR_UM


def _all_location_names() -> set[str]:
    names = set(SQUARENESS)
    for axis, about in (("A", "X"), ("B", "Y"), ("C", "Z")):
        for about_dir in "XYZ":
            names |= set(rotary_location_names(axis, about_dir))
    return names


def _layout_word(layout: Machine) -> str:
    return " ".join(layout.axis_names)


def _read_components(spec, path: str, axis: Axis, ck: _Checker):
    names = [f"E{d}{axis.name}" for d in ERROR_DIRECTIONS]
    allowed = {"at", "interpolation", "legendre", "fourier", *names}
    ck.table(spec, path, allowed)
    out = {}
    to_internal = np.radians if axis.is_rotary else (lambda v: np.asarray(v, dtype=float))
    travel_deg = None if axis.travel is None else (np.degrees(axis.travel) if axis.is_rotary else axis.travel)
    table_names = [n for n in names if n in spec]
    if table_names:
        interp = ck.string(spec.get("interpolation", "linear"), f"{path}.interpolation", ("linear", "cubic")) or "linear"
        at = ck.numbers(spec.get("at"), f"{path}.at") if "at" in spec else None
        if "at" not in spec:
            ck.fail(f"{path}.at", f"missing: the tables {', '.join(table_names)} need their positions")
        if at is not None:
            ok = True
            if at.size < 2:
                ck.fail(f"{path}.at", "needs at least 2 positions")
                ok = False
            elif np.any(np.diff(at) <= 0):
                i = int(np.argmax(np.diff(at) <= 0))
                ck.fail(f"{path}.at", f"positions must increase strictly: at[{i}] = {at[i]:g}, at[{i + 1}] = {at[i + 1]:g}")
                ok = False
            if ok and travel_deg is not None:
                lo, hi = travel_deg
                eps = 1e-9 * max(1.0, abs(lo), abs(hi))
                if at[0] < lo - eps or at[-1] > hi + eps:
                    unit = "deg" if axis.is_rotary else "mm"
                    ck.fail(
                        f"{path}.at",
                        f"table [{at[0]:g}, {at[-1]:g}] {unit} lies outside the travel [{lo:g}, {hi:g}] {unit}",
                    )
                    ok = False
            periodic = bool(axis.is_rotary and ok and abs((at[-1] - at[0]) - 360.0) < 1e-9)
            if axis.is_rotary and ok and at[-1] - at[0] > 360.0 + 1e-9:
                ck.fail(f"{path}.at", "a rotary table spans at most 360 deg")
                ok = False
            if interp == "cubic" and ok and at.size < 3:
                ck.fail(f"{path}.interpolation", "cubic interpolation needs at least 3 positions")
                ok = False
            for n in table_names:
                vals = ck.numbers(spec[n], f"{path}.{n}", limit=_error_limit(n))
                if vals is None or not ok:
                    continue
                if vals.size != at.size:
                    ck.fail(f"{path}.{n}", f"has {vals.size} values for {at.size} positions in {path}.at")
                    continue
                if periodic and vals[0] != vals[-1]:
                    ck.fail(f"{path}.{n}", "a table over a full turn must end where it starts (first value = last value)")
                    continue
                unit = "deg" if axis.is_rotary else "mm"
                out[n] = table(to_internal(at), vals, interp, periodic=periodic, label_unit=unit)
    elif "at" in spec:
        ck.fail(f"{path}.at", "positions given but no component table")
    for form in ("legendre", "fourier"):
        if form not in spec:
            continue
        series = ck.table(spec[form], f"{path}.{form}", set(names))
        if form == "fourier" and not axis.is_rotary:
            ck.fail(f"{path}.fourier", "Fourier series are for rotary axes")
            continue
        for n, coeffs in series.items():
            p = f"{path}.{form}.{n}"
            if n not in names:
                continue
            if n in out:
                ck.fail(p, f"{n} is given twice (as a table and as a series)")
                continue
            if form == "legendre":
                c = ck.numbers(coeffs, p, limit=_error_limit(n))
                if c is None or c.size == 0:
                    continue
                if axis.travel is None and not axis.is_rotary:
                    ck.fail(p, "a Legendre series needs the axis' travel (its domain)")
                    continue
                domain = axis.travel if axis.travel is not None else (-np.pi, np.pi)
                out[n] = legendre_series(c, domain)
            else:
                if not isinstance(coeffs, list) or not coeffs:
                    ck.fail(p, "expected rows [k, cos amplitude, sin amplitude]")
                    continue
                rows = [ck.numbers(r, f"{p}[{i}]", 3, limit=max(_error_limit(n), 360.0)) for i, r in enumerate(coeffs)]
                if any(r is None for r in rows):
                    continue
                k = np.array([r[0] for r in rows])
                if np.any(k < 1) or np.any(k != np.round(k)):
                    ck.fail(p, "harmonic numbers k must be whole numbers >= 1")
                    continue
                out[n] = fourier_series(rows)
    return out


def _read_surfaces(data, axes, ck: _Checker):
    if not isinstance(data, list):
        ck.fail("force.surface", "expected an array of tables [[force.surface]]")
        return
    for i, s in enumerate(data):
        path = f"force.surface[{i}]"
        s = ck.table(s, path, {"axis", "inputs", "load_sign", "motion", "coeffs", "note"},
                     ("axis", "inputs", "load_sign", "motion", "coeffs"))
        axis = ck.string(s.get("axis", "Z"), f"{path}.axis", ("X", "Y", "Z"))
        inputs = s.get("inputs", [])
        pos_axis = force_dir = None
        if not (isinstance(inputs, list) and len(inputs) == 2 and all(isinstance(v, str) for v in inputs)):
            ck.fail(f"{path}.inputs", "expected [axis position, force component], e.g. [\"X\", \"Pz\"]")
        else:
            if inputs[0] not in axes or axes[inputs[0]].is_rotary:
                ck.fail(f"{path}.inputs[0]", f"{inputs[0]!r} is not a linear axis of this machine")
            else:
                pos_axis = inputs[0]
            f = inputs[1]
            if len(f) == 2 and f[0] in "PF" and f[1].upper() in "XYZ":
                force_dir = f[1].upper()
            else:
                ck.fail(f"{path}.inputs[1]", f"{f!r} is not a force component (Px Py Pz or Fx Fy Fz)")
        sign = ck.string(s.get("load_sign", "+"), f"{path}.load_sign", ("+", "-"))
        motion = ck.string(s.get("motion", "forward"), f"{path}.motion", ("forward", "backward"))
        coeffs = ck.numbers(s.get("coeffs", []), f"{path}.coeffs", 6)
        note = s.get("note", "")
        if None not in (axis, pos_axis, force_dir, sign, motion) and coeffs is not None:
            yield ResponseSurface(axis, pos_axis, force_dir, 1 if sign == "+" else -1,
                                  1 if motion == "forward" else -1, coeffs, str(note))


# ------------------------------------------------------------------------------------------------------ writing ----
def dump_machine(machine: Machine) -> str:
    """A complete machine file (TOML, format 1) for ``machine``: ``parse_machine(dump_machine(m))`` gives back the same
    layout, tool, placement, error parameters (bit for bit), loaded set, force model and cutting coefficients.

    Geometry is written in mm and degrees, error values in um and urad (DESIGN §4). Component errors keep their form:
    tables (one ``at`` and ``interpolation`` per axis, as the reader wants them), Legendre and Fourier series. A
    periodic rotary table is written with its last value equal to its first (the model never uses the last one).
    Comments of the original file are not kept: :func:`update_machine_text` keeps them.
    """
    out = ["[machine]", f"name = {_toml_str(machine.name)}", f"kind = {_toml_str(machine.kind)}", "format = 1"]
    if machine.note:
        out.append(f"note = {_toml_str(machine.note)}")
    if machine.setup:
        out.append(f"setup = {_toml_str(machine.setup)}")
    out += ["", "[kinematics]", f"bed_to_workpiece = {_toml_list(machine.bed_to_workpiece)}",
            f"bed_to_tool = {_toml_list(machine.bed_to_tool)}"]
    if machine.rotary_sense != "iso":
        out.append(f"rotary_sense = {_toml_str(machine.rotary_sense)}")
    if machine.output_mode != "joint":
        out.append(f"output_mode = {_toml_str(machine.output_mode)}")
    if machine.tcp_code != "G43.4":
        out.append(f"tcp_code = {_toml_str(machine.tcp_code)}")
    out += ["", "[axes]"]
    for name in machine.axis_names:
        ax = machine.axes[name]
        items = [f'type = "{ax.kind}"']
        if ax.travel is not None:
            tr = _degrees(ax.travel) if ax.is_rotary else ax.travel
            items.append(f"travel = {_toml_floats(tr)}")
        if ax.is_rotary:
            items.append(f'about = "{ax.about}"')
            items.append(f"pivot = {_toml_floats(ax.pivot)}")
        out.append(f"{name} = {{ {', '.join(items)} }}")
    t = machine.tool
    out += ["", "[tool]", f"length = {_toml_float(t.length)}", f"radius = {_toml_float(t.radius)}",
            f"flutes = {int(t.flutes)}", f"flute_length = {_toml_float(t.flute_length)}",
            f"helix_deg = {_toml_float(t.helix_deg)}",
            "", "[workpiece]", f"origin = {_toml_floats(machine.workpiece_origin)}"]
    out += _dump_error_set(machine, machine.errors, "")
    if machine.loaded is not None:
        out += ["", "[loaded]", f"force_n = {_toml_floats(machine.loaded_force_n)}"]
        out += _dump_error_set(machine, machine.loaded, "loaded.")
    if machine.compliance_um_per_n is not None or machine.surfaces:
        out += ["", "[force]"]
        if machine.compliance_um_per_n is not None:
            rows = ", ".join(_toml_floats(r) for r in np.asarray(machine.compliance_um_per_n))
            out.append(f"compliance_um_per_n = [{rows}]")
        for s in machine.surfaces:
            out += ["", "[[force.surface]]", f'axis = "{s.axis}"',
                    f'inputs = ["{s.position_axis}", "P{s.force_direction.lower()}"]',
                    f'load_sign = "{"+" if s.load_sign > 0 else "-"}"',
                    f'motion = "{"forward" if s.motion > 0 else "backward"}"', f"coeffs = {_toml_floats(s.coeffs)}"]
            if s.note:
                out.append(f"note = {_toml_str(s.note)}")
    if machine.cutting is not None:
        out += ["", "[cutting]"]
        for key, value in machine.cutting.items():
            out.append(f"{key} = {_toml_str(value) if isinstance(value, str) else _toml_float(value)}")
    return "\n".join(out) + "\n"


def update_machine_text(text: str, machine: Machine) -> tuple[str, bool]:
    """``text`` (a machine file) with its error parameters replaced by ``machine``'s, the user's comments, order and
    layout kept (tomlkit edits the document in place; only values that changed are rewritten).

    Only the error sections and the note change: ``[location]``, ``[component.*]``, ``[loaded]`` (a parameter that
    became 0 is written as 0, with its comment), ``[machine] note``. The result is checked by reading it back: when it does not give ``machine``'s
    parameters bit for bit (a form the edit cannot express, e.g. a Legendre series replaced by a table), the complete
    :func:`dump_machine` text is returned instead. Returns (text, comments_kept).
    """
    import tomlkit

    fresh = dump_machine(machine)
    try:
        doc = tomlkit.parse(text)
        new = tomllib.loads(fresh)
        for section in ("location", "component", "loaded"):
            if section in new or section in doc:
                _merge_values(doc, new, section)
        if "note" in new["machine"] and doc["machine"].get("note") != new["machine"]["note"]:
            doc["machine"]["note"] = new["machine"]["note"]  # an identified machine says so in its note
        edited = tomlkit.dumps(doc)
        same = dump_machine(parse_machine(edited, source=machine.source)) == fresh
    except (tomlkit.exceptions.TOMLKitError, tomllib.TOMLDecodeError, MachineFileError, ValueError):
        same = False
    return (edited, True) if same else (fresh, False)


def _merge_values(doc, new: dict, key: str) -> None:
    """Set ``doc[key]`` to ``new[key]`` in place, recursing into tables so that the comments of the keys kept stay."""
    if key not in new:  # the section is all zero now: zero its numbers, keep its keys and comments
        _zero(doc[key])
        return
    value = new[key]
    if key not in doc or not isinstance(value, dict) or not hasattr(doc[key], "keys"):
        if key not in doc or doc[key] != value:
            doc[key] = value
        return
    for sub in value:
        _merge_values(doc[key], value, sub)
    for sub in [k for k in doc[key] if k not in value]:
        _zero_key(doc[key], sub)


def _zero_key(table, key) -> None:
    v = table[key]
    if hasattr(v, "keys"):
        _zero(v)
    elif isinstance(v, (int, float)) and not isinstance(v, bool):
        table[key] = 0.0
    elif isinstance(v, list) and all(isinstance(x, (int, float)) for x in v) and key != "at":
        table[key] = [0.0] * len(v)


def _zero(table) -> None:
    for k in list(table.keys()):
        _zero_key(table, k)


def _dump_error_set(machine: Machine, errors: ErrorSet, prefix: str) -> list[str]:
    out = []
    names = [n for n in machine.location_names() if errors.location.get(n, 0.0) != 0.0]
    if names:
        out += ["", f"[{prefix}location]"] + [f"{n} = {_toml_float(errors.location[n])}" for n in names]
    for axis_name in machine.axis_names:
        comps = errors.components.get(axis_name, {})
        if not comps:
            continue
        axis = machine.axes[axis_name]
        out += ["", f"[{prefix}component.{axis_name}]"]
        tables = {n: f for n, f in comps.items() if f.kind in ("linear", "cubic")}
        if tables:
            kinds = {f.kind for f in tables.values()}
            ats = {f.at.tobytes() for f in tables.values()}
            if len(kinds) > 1 or len(ats) > 1:
                raise ValueError(f"component tables of axis {axis_name} must share their positions and interpolation "
                                 "to be written (one [component.AXIS] table)")
            first = next(iter(tables.values()))
            at = _degrees(first.at) if axis.is_rotary else first.at
            out += [f'interpolation = "{first.kind}"', f"at = {_toml_floats(at)}"]
            for n in machine.component_names(axis_name):
                if n in tables:
                    values = np.array(tables[n].values, float)
                    if tables[n].periodic:
                        values[-1] = values[0]
                    out.append(f"{n} = {_toml_floats(values)}")
        for form in ("legendre", "fourier"):
            series = [(n, comps[n]) for n in machine.component_names(axis_name) if n in comps and comps[n].kind == form]
            if not series:
                continue
            items = []
            for n, f in series:
                if form == "legendre":
                    items.append(f"{n} = {_toml_floats(f.values)}")
                else:
                    ab = np.asarray(f.values, float).reshape(-1, 2)
                    rows = ", ".join(f"[{int(k)}, {_toml_float(a)}, {_toml_float(b)}]"
                                     for k, (a, b) in zip(f.harmonics, ab))
                    items.append(f"{n} = [{rows}]")
            out.append(f"{form} = {{ {', '.join(items)} }}")
    return out


def _degrees(radians) -> np.ndarray:
    """Degrees from the internal radians, rounded to 12 significant digits (30.0, not 29.999999999999996)."""
    return np.array([float(f"{v:.12g}") for v in np.degrees(np.asarray(radians, float))])


def _toml_float(v) -> str:
    v = float(v)
    if not math.isfinite(v):
        raise ValueError(f"cannot write a non-finite number ({v}) to a machine file")
    return repr(v + 0.0)


def _toml_floats(values) -> str:
    return "[" + ", ".join(_toml_float(v) for v in np.asarray(values, float).reshape(-1)) + "]"


def _toml_list(words) -> str:
    return "[" + ", ".join(_toml_str(w) for w in words) + "]"


def _toml_str(s: str) -> str:
    """A TOML basic string: backslash, quote and control characters escaped."""
    out = []
    for ch in str(s):
        if ch == "\\":
            out.append("\\\\")
        elif ch == '"':
            out.append('\\"')
        elif ch == "\n":
            out.append("\\n")
        elif ch == "\t":
            out.append("\\t")
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


__all__ = ["MachineFileError", "dump_machine", "load_machine", "parse_machine", "DIRECTION_LETTER"]
