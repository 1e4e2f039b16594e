"""What a machine is: its axes, kinematic branches, reference tool, part placement and error parameters.

Plain data. Geometry in internal units (mm, rad); error values in the machine file's units (um, urad), named by
ISO 230-1 / ISO 230-7 (DESIGN §3). ``machine_file.load_machine`` builds these from TOML; ``twin`` evaluates them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .error_functions import ErrorFunction

AXIS_ORDER = "XYZABC"
ROTATION_LETTER = {"X": "A", "Y": "B", "Z": "C"}
DIRECTION_LETTER = {v: k for k, v in ROTATION_LETTER.items()}
ERROR_DIRECTIONS = "XYZABC"  # E<dir><axis>: X Y Z are translations (um), A B C rotations (urad)

# Squareness of linear axes (DESIGN §3): name -> (axis it tilts, rotation direction it tilts about)
SQUARENESS = {"C0Y": ("Y", "Z"), "B0Z": ("Z", "Y"), "A0Z": ("Z", "X")}


def is_angle_name(name: str) -> bool:
    """True for parameters in urad (angles), False for um (lengths). Works for location and component names."""
    base = name.split("@")[0].split(".")[0]
    if base.startswith("E") and len(base) == 3:
        return base[1] in "ABC"
    if base in SQUARENESS:
        return True
    return base[0] in "ABC"  # XOC/YOC/ZOB... are offsets; AOC/BOC/COC... are angles


def unit_of(name: str) -> str:
    return "urad" if is_angle_name(name) else "um"


# Beyond these a parameter is larger than a machine tool's geometric error is (um, urad): a unit slip, most likely
# (the machine file's units are um and urad; 35000 urad of squareness, 2 deg, was checked "ok" and posted; QA pass)
PLAUSIBLE_MAX = {"um": 1000.0, "urad": 2000.0}


def implausible_parameters(machine) -> str | None:
    """One sentence naming the parameters beyond ``PLAUSIBLE_MAX`` (the largest first), or None."""
    names, values = machine.parameter_names(), machine.parameter_values()
    units = [unit_of(n) for n in names]
    size = np.abs(values) / [PLAUSIBLE_MAX[u] for u in units]  # (the largest beyond its bound first)
    over = [i for i in np.argsort(-size, kind="stable") if abs(values[i]) > PLAUSIBLE_MAX[units[i]]]
    if not over:
        return None
    said = ", ".join(f"{names[i]} = {values[i]:g} {units[i]}" for i in over[:3])
    more = f" and {len(over) - 3} more" if len(over) > 3 else ""
    return (f"{said}{more}: larger than a machine tool's geometric error is (beyond {PLAUSIBLE_MAX['um']:g} um or "
            f"{PLAUSIBLE_MAX['urad']:g} urad); the file's values are in um and urad: a unit slip?")


TRAVEL_TOLERANCE = 1e-9  # mm or rad: a position computed at a travel limit is inside it


@dataclass(frozen=True)
class Axis:
    """One machine axis.

    kind : "linear" | "rotary".  direction : (3,) unit vector, the line of motion (linear) or of rotation (rotary),
    in M with all axes at zero.  pivot : (3,) mm, a point on a rotary axis' nominal line.  travel : (lo, hi) in mm or
    rad, or None (unlimited).  branch : "workpiece" | "tool".
    """

    name: str
    kind: str
    direction: np.ndarray
    pivot: np.ndarray
    travel: tuple[float, float] | None
    branch: str
    about: str | None = None

    @property
    def is_rotary(self) -> bool:
        return self.kind == "rotary"

    def within_travel(self, values) -> np.ndarray:
        """The one travel check: bool array, True where ``values`` (mm or rad) lie in the travel (all True when
        unlimited), with TRAVEL_TOLERANCE of slack for the rounding of a value computed at the limit."""
        if self.travel is None:
            return np.ones(np.shape(values), bool)
        values = np.asarray(values)
        return (values >= self.travel[0] - TRAVEL_TOLERANCE) & (values <= self.travel[1] + TRAVEL_TOLERANCE)


@dataclass(frozen=True)
class Tool:
    """The reference tool: a flat end mill unless said otherwise (mm, deg)."""

    length: float
    radius: float
    flutes: int = 4
    flute_length: float = 30.0
    helix_deg: float = 30.0


@dataclass
class ErrorSet:
    """Position-independent (location) errors and component error functions.

    location : name -> value (um or urad); absent names are zero.
    components : axis name -> component name (e.g. "EXX") -> ErrorFunction.
    """

    location: dict[str, float] = field(default_factory=dict)
    components: dict[str, dict[str, ErrorFunction]] = field(default_factory=dict)


@dataclass(frozen=True)
class ResponseSurface:
    """A second-degree response surface of the lathe paper: an error of ``axis`` in um.

    d = c0 + c1 x + c2 P + c3 x^2 + c4 x P + c5 P^2, with x the position of ``position_axis`` (mm) and P the signed
    force component on the tool along ``force_direction`` (kN). Chosen when the force's sign is ``load_sign`` and the
    position axis moves in direction ``motion`` (+1 forward, -1 backward).
    """

    axis: str
    position_axis: str
    force_direction: str
    load_sign: int
    motion: int
    coeffs: np.ndarray
    note: str = ""


@dataclass
class Machine:
    """A machine and its error twin parameters (see DESIGN §3-4)."""

    name: str
    kind: str
    axes: dict[str, Axis]
    bed_to_workpiece: tuple[str, ...]
    bed_to_tool: tuple[str, ...]
    tool: Tool
    workpiece_origin: np.ndarray
    errors: ErrorSet
    loaded: ErrorSet | None = None
    loaded_force_n: np.ndarray | None = None
    compliance_um_per_n: np.ndarray | None = None
    surfaces: tuple[ResponseSurface, ...] = ()
    cutting: dict | None = None
    note: str = ""
    source: str = "<memory>"
    setup: str = ""  # the control's default setup file (``[machine] setup``), a path; "" when none
    # How the programs' rotary words turn ([kinematics] rotary_sense): "iso" (ISO 841, the model's sense: the tool
    # relative to the workpiece, right-handed) or "linuxcnc-trt" (LinuxCNC's xyzbc/xyzac-trt-kins: the table turns
    # right-handed, so a word is the negative of the model's angle). Only programs' words change, nothing else.
    rotary_sense: str = "iso"
    # What the post writes ([kinematics] output_mode): "joint" (the commanded joints, for a control in joint mode) or
    # "tcp" (tool-centre-point positions for a control that runs its nominal table-table kinematics; see
    # postproc.tcp), and the code that switches the control's TCP on in place of the program's G43 ([kinematics]
    # tcp_code: "G43.4" Fanuc-style; "G43" for LinuxCNC's xyzbc/xyzac-trt-kins, whose kinematics are the TCP).
    output_mode: str = "joint"
    tcp_code: str = "G43.4"

    def word_signs6(self) -> np.ndarray:
        """(6,) the signs of :meth:`word_signs` over the columns X Y Z A B C (1 for axes the machine lacks)."""
        signs = np.ones(6)
        for a, s in zip(self.axis_names, self.word_signs()):
            signs[AXIS_ORDER.index(a)] = s
        return signs

    def word_signs(self) -> np.ndarray:
        """(n_axes,) +1 or -1: a program word of each axis is its sign times the model's position (degrees / mm)."""
        flip = self.rotary_sense == "linuxcnc-trt"
        return np.array([-1.0 if flip and self.axes[a].is_rotary else 1.0 for a in self.axis_names])

    # --- names ---------------------------------------------------------------------------------------------------
    @property
    def axis_names(self) -> tuple[str, ...]:
        """Axis letters in canonical order (X Y Z A B C): the column order of every pose array."""
        return tuple(a for a in AXIS_ORDER if a in self.axes)

    @property
    def rotary_axes(self) -> tuple[str, ...]:
        return tuple(a for a in self.axis_names if self.axes[a].is_rotary)

    @property
    def is_five_axis(self) -> bool:
        return len(self.rotary_axes) == 2

    def required_axes(self, commanded: str) -> tuple[str, ...]:
        """The axes whose position a program for this machine must fix, and whose work offset it must be given, in
        canonical order: every linear axis the machine has, and its rotary axes the program commands (``commanded``:
        the letters of the axes the program's words name). An axis the machine lacks is never required: nothing
        moves along it (a program that commands it is refused as such), so its offset component changes no position
        (a lathe's Y). A rotary axis the program leaves alone stands where the control left it."""
        return tuple(a for a in self.axis_names if not self.axes[a].is_rotary or a in commanded)

    def force_models(self) -> tuple[str, ...]:
        """What of the twin depends on the cutting force, as a machine file names it: "[force] compliance",
        "[loaded] parameter set", "[[force.surface]] response surfaces"; () when nothing does (the twin is the same
        under any load: a comprehensive compensation corrects no force, a simulation cuts with none)."""
        return tuple(name for name, has in (("[force] compliance", self.compliance_um_per_n is not None),
                                            ("[loaded] parameter set", self.loaded is not None),
                                            ("[[force.surface]] response surfaces", bool(self.surfaces))) if has)

    def location_names(self) -> list[str]:
        """Every location parameter this layout has, in a fixed order."""
        names = [n for n, (ax, _) in SQUARENESS.items() if ax in self.axes]
        for a in self.rotary_axes:
            names += rotary_location_names(a, self.axes[a].about)
        return names

    def component_names(self, axis: str) -> list[str]:
        return [f"E{d}{axis}" for d in ERROR_DIRECTIONS]

    # --- parameter vector ----------------------------------------------------------------------------------------
    def parameter_names(self) -> list[str]:
        """Names of the geometric parameter vector: every location name, then each component function's values."""
        names = list(self.location_names())
        for axis, comps in self._component_items():
            for comp, fn in comps:
                names += [f"{comp}{label}" for label in fn.labels]
        return names

    def parameter_values(self) -> np.ndarray:
        vals = [self.errors.location.get(n, 0.0) for n in self.location_names()]
        for _, comps in self._component_items():
            for _, fn in comps:
                vals += list(fn.values)
        return np.asarray(vals, dtype=float)

    def parameter_units(self) -> list[str]:
        return [unit_of(n) for n in self.parameter_names()]

    def with_parameters(self, values: np.ndarray) -> "Machine":
        """A copy whose geometric parameters are ``values`` (same order as ``parameter_names``)."""
        values = np.asarray(values, dtype=float)
        if values.shape != (len(self.parameter_names()),):
            raise ValueError(f"expected {len(self.parameter_names())} parameter values, got shape {values.shape}")
        names = self.location_names()
        location = {n: float(v) for n, v in zip(names, values[: len(names)]) if v != 0.0}
        i = len(names)
        components: dict[str, dict[str, ErrorFunction]] = {}
        for axis, comps in self._component_items():
            components[axis] = {}
            for comp, fn in comps:
                n = fn.values.size
                components[axis][comp] = replace(fn, values=values[i : i + n].copy())
                i += n
        return replace(self, errors=ErrorSet(location=location, components=components))

    def with_parameter_changes(self, values: np.ndarray) -> "Machine":
        """A copy whose geometric parameters are ``values`` (as ``with_parameters``) and whose loaded set, where it
        has one, moves by the same changes: the loaded set is the unloaded one plus the force-induced part
        (``value(F) = unloaded + s (loaded - unloaded)``), so a change of the unloaded errors alone would change the
        force-induced part by minus itself (a comprehensive post applying only (1 - s) of it). What an identification
        writes."""
        out = self.with_parameters(values)
        if self.loaded is None:
            return out
        old, new = self.errors, out.errors
        location = {k: v + new.location.get(k, 0.0) - old.location.get(k, 0.0) for k, v in self.loaded.location.items()}
        components = {}
        for axis, comps in self.loaded.components.items():
            components[axis] = {}
            for name, fl in comps.items():
                f0, f1 = old.components.get(axis, {}).get(name), new.components.get(axis, {}).get(name)
                components[axis][name] = fl if f0 is None else _shifted(fl, f0, f1)
        return replace(out, loaded=ErrorSet(location=location, components=components))

    def error_free(self) -> "Machine":
        """The machine's layout with every error parameter zero and no force model: a nominal twin (the twin a shop
        starts its closed loop from)."""
        zero = np.zeros(len(self.parameter_names()))
        # (no longer the file's content: its source is memory, so that nothing fingerprints it by the file's bytes)
        return replace(self.with_parameters(zero), loaded=None, loaded_force_n=None, compliance_um_per_n=None,
                       surfaces=(), source="<memory>")

    def _component_items(self):
        for axis in self.axis_names:
            comps = self.errors.components.get(axis, {})
            yield axis, [(c, comps[c]) for c in self.component_names(axis) if c in comps]


def _shifted(loaded: ErrorFunction, before: ErrorFunction, after: ErrorFunction) -> ErrorFunction:
    """``loaded`` plus the change ``after - before`` of the unloaded function: the values added where the two
    functions share their form (kind, table positions, domain, harmonics), else a table's values moved by the change
    at its own positions (exact for a linear change between shared positions)."""
    same = (loaded.kind == before.kind and loaded.values.shape == before.values.shape
            and all(np.array_equal(getattr(loaded, k), getattr(before, k)) for k in ("at", "harmonics"))
            and loaded.domain == before.domain)
    if same:
        return replace(loaded, values=loaded.values + (after.values - before.values))
    if loaded.kind in ("linear", "cubic"):
        return replace(loaded, values=loaded.values + after(loaded.at) - before(loaded.at))
    raise ValueError(f"the loaded set's {loaded.kind} function has another form than the unloaded one: the change "
                     "cannot be carried into it")


def rotary_location_names(axis: str, about: str) -> list[str]:
    """ISO 230-7 location errors of a rotary axis: two offsets, two tilts, the zero-angle offset.

    For C about Z: XOC YOC (um), AOC BOC (urad), COC (urad).
    """
    perpendicular = [d for d in "XYZ" if d != about]
    offsets = [f"{d}O{axis}" for d in perpendicular]
    tilts = [f"{ROTATION_LETTER[d]}O{axis}" for d in perpendicular]
    return offsets + tilts + [f"{ROTATION_LETTER[about]}O{axis}"]
