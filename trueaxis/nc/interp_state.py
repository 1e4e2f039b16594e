"""The interpreter's state (LinuxCNC's ``setup`` structure): units and scales, work systems with their rotations and
versions, G92, the tool offsets, the modes, the position, and the row accumulators; and the few operations on it that
every part of the interpreter uses (``offsets``, ``machine_of``, ``program_of``, ``meta``, ``refresh_state``,
``emit``). A part of ``gcode._Interpreter`` (the methods of ``InterpState``): the state is the interpreter's
attributes, in current program units (lengths) and degrees, as LinuxCNC keeps it."""

from __future__ import annotations

import math
from array import array

import numpy as np

from .interp_arc import RADIUS_MIN, SPIRAL_ABS
from .interp_codes import AXES


class InterpState:
    """The interpreter's state and its operations (mixed into ``gcode._Interpreter``)."""

    def start_state(self) -> None:
        """The state at program start: LinuxCNC's defaults, then what the setup gives."""
        self.inch = False
        self.u_scale = np.array([1.0, 1, 1, 1, 1, 1])  # mm per program unit, per axis
        self.g5x = np.zeros((10, 6))  # index 1..9: G54..G59.3
        self.rot = [0.0] * 10  # XY rotation of each work system, deg (LinuxCNC's R, parameter 5230 + 20 (k - 1))
        self.active = 1
        self.g92 = np.zeros(6)
        self.tlo = np.zeros(6)
        self.start_setup()
        # an I J K arc's radii may differ by arc_tol (more within 0.1 %), none be below arc_rmin (``interp_arc``)
        self.arc_tol, self.arc_rmin = SPIRAL_ABS[False], RADIUS_MIN[False]
        self.pos = [0.0] * 6  # program coordinates (a list: numpy is slow for 6 numbers at a time)
        self.off_now = [0.0] * 6  # G5x + G92 + tool length offset, refreshed after every block that can change it
        self.motion_mode = 0  # G code *10 of the modal motion (0, 10, 20, 30, 730, 810..890, 800)
        self.pre_cycle_mode = 0  # the motion mode before a canned cycle (Fanuc's G80 with axis words)
        self.plane = 17
        self.absolute = True
        self.arc_abs = False
        self.inverse = False
        self.diameter = False  # G7 (lathe diameter mode: X words are diameters, halved as LinuxCNC does; I is not)
        self.modes_stated: dict = {}  # "G7/G8", "plane", "units" -> the line index the program first states it on
        self.feed = 0.0
        self.retract_r = False  # G99
        self.cutter = 40
        self.tool = 0
        self.next_tool = 0
        self.cycle_words = {"r": 0.0, "cc": 0.0, "p": 0.0, "q": 0.0, "i": 0.0, "j": 0.0, "k": 0.0, "il": 0.0,
                            "il_flag": False}
        self.refs = {k: v.copy() for k, v in self.ref_mm.items()}  # machine coords, mm (converted on use)
        self.ref_given = dict(self.ref_given0)  # a home position given by the user, or set by G28.1 / G30.1
        self.ref_missing = None  # (line number, reason) of the first G28 / G30 to a home position not given
        self.home_not_given_rows = []  # the rows of G28 / G30 that end at a home position not given (taken as zero)
        self.used_axes = set()
        self.units_seen = set()
        self.percent_seen = 0
        self.ended = False
        # Row accumulators: flat lists, turned into arrays once at the end. What rarely changes between rows
        # (feed, modes, tool, offsets) is stored once per distinct state and indexed per row.
        # start / end points as packed doubles (8 bytes a number, not a float object each: a million-block program)
        self.r_start, self.r_end = array("d"), array("d")
        # and the per-row integers packed too (no list of a million references for every full garbage collection
        # to walk)
        self.r_line, self.r_motion, self.r_kind = array("q"), array("q"), array("q")
        self.r_words, self.r_state = array("q"), array("q")
        self.r_arc = {}  # row -> (centre (3,), plane, turns)
        # the compiled runs' arcs as arrays, not a tuple each: (rows (k,), centres (k, 3), plane), one turn each
        self.r_arc_runs = []
        self.states = {}
        self.cur_state = 0
        self.meta_now = self.meta()
        if self.setup is not None:
            self.off_now = self.offsets().tolist()
            self.refresh_state()

    def start_setup(self) -> None:
        """What is known of the control's setup, and where each value came from. A value's "version" changes when
        the program changes it, so that the rows' states can name the value they used (setup_used)."""
        setup = self.setup
        zero_ok = self.zero_ok = self.offsets_zero
        self.g5x_known = np.full((10, 6), zero_ok)
        self.g5x_src = ["--offsets-zero" if zero_ok else "not given"] * 10
        self.g5x_ver = [0] * 10
        self.hist = {}  # ("g5x", index, version) / ("g92", version) / ("tlo", version) -> record for setup_used
        self.g92_reason = ""
        self.g92_ver = 0
        self.tlo_ver = 0
        self.tlo_reason = ""
        self.tlo_h = -1  # the tool whose offsets are in force (-1 none, -2 G43.1 given in the program)
        self.selects_work = False
        self.g92_stored = None  # (values mm, source) of the shift G92.3 restores; None: unknown
        if setup is not None and setup.g92_stored is not None:
            self.g92_stored = (np.asarray(setup.g92_stored.values, float), setup.g92_stored.source)
        elif zero_ok:
            self.g92_stored = (np.zeros(6), "--offsets-zero")
        self.tool_change_mode = setup is not None and setup.tool_length == "tool_change"
        if setup is not None:
            for k, off in setup.work_offsets.items():
                self.g5x[k] = off.values
                self.rot[k] = float(off.rotation_deg)
                self.g5x_known[k] = True
                self.g5x_src[k] = off.source
            if setup.active is not None:
                self.active = int(setup.active)
            if setup.g92 is not None:
                self.g92[:] = setup.g92.values
        self.hist[("g92", 0)] = {"values": self.g92.copy(), "source": setup.g92.source if setup is not None and
                                 setup.g92 is not None else "none at program start"}
        self.hist[("tlo", 0)] = {"tool": -1, "values": np.zeros(6), "source": ""}
        for k in range(1, 10):
            self.hist[("g5x", k, 0)] = {"values": self.g5x[k].copy(), "rotation": self.rot[k],
                                        "source": self.g5x_src[k], "known": self.g5x_known[k].copy()}

    def offsets(self):
        """G5x + G92 + tool offsets, the G92 shift turned by the system's rotation: machine = R p + offsets."""
        active, g92 = self.active, self.g92
        r = self.rot[active]
        if r == 0.0:
            return self.g5x[active] + g92 + self.tlo
        c, s = math.cos(math.radians(r)), math.sin(math.radians(r))
        g = g92.copy()
        g[0], g[1] = c * g92[0] - s * g92[1], s * g92[0] + c * g92[1]
        return self.g5x[active] + g + self.tlo

    def machine_of(self, p):
        """Machine position (current units) of program position p: R (p + G92) + G5x + tool offset."""
        active, g92, g5x, tlo = self.active, self.g92, self.g5x, self.tlo
        u = [p[i] + g92[i] for i in range(6)]
        r = self.rot[active]
        if r != 0.0:
            c, s = math.cos(math.radians(r)), math.sin(math.radians(r))
            u[0], u[1] = c * u[0] - s * u[1], s * u[0] + c * u[1]
        return [u[i] + g5x[active, i] + tlo[i] for i in range(6)]

    def program_of(self, m):
        """The inverse of machine_of."""
        active, g92, g5x, tlo = self.active, self.g92, self.g5x, self.tlo
        u = [m[i] - g5x[active, i] - tlo[i] for i in range(6)]
        r = self.rot[active]
        if r != 0.0:
            c, s = math.cos(math.radians(r)), math.sin(math.radians(r))
            u[0], u[1] = c * u[0] + s * u[1], -s * u[0] + c * u[1]
        return [u[i] - g92[i] for i in range(6)]

    def meta(self):
        """The setup in force, for the rows' states: rotation, system and the versions of the values used, and
        what is unknown (work axes not given, G92 / tool length reasons)."""
        active = self.active
        unknown = "".join(AXES[i] for i in range(6) if not self.g5x_known[active, i])
        return (self.rot[active], active, self.g5x_ver[active], self.g92_ver, self.tlo_ver, unknown,
                self.g92_reason, self.tlo_reason)

    def refresh_state(self) -> None:
        """The index of the state in force (feed, modes, tool, offsets, setup) into ``cur_state``."""
        states = self.states
        self.cur_state = states.setdefault((self.feed,) + self.state_key_rest(), len(states))

    def state_key_rest(self) -> tuple:
        """The state's key after its feed: the modes, tool, offsets and setup in force."""
        return (self.inverse, self.inch, self.cutter, self.tool, not self.absolute, not self.arc_abs,
                tuple(self.off_now), self.meta_now, self.diameter)

    def feed_states(self, feeds) -> list:
        """The state indices of ``feeds`` (a float array) in turn, nothing else changing (a run of plain moves whose
        feed changes), as ``refresh_state`` would give them one by one: a new state for each feed not seen before, in
        the order of first appearance; the last one and its feed are in force after. (Each distinct feed looked up
        once: a G93 program changes its feed on most lines.)"""
        if feeds.size == 0:
            return []
        states, rest = self.states, self.state_key_rest()
        _, first, inverse = np.unique(feeds, return_index=True, return_inverse=True)
        ids = np.empty(first.size, np.int64)
        for j in np.argsort(first, kind="stable").tolist():
            ids[j] = states.setdefault((float(feeds[first[j]]),) + rest, len(states))
        out = ids[inverse.reshape(-1)].tolist()
        self.feed, self.cur_state = float(feeds[-1]), out[-1]
        return out

    def emit(self, motion, kind, target, li, words=0, center=None, pl=0, turns=0):
        """One row from the position to ``target`` (which becomes the position)."""
        pos = self.pos
        if center is not None:
            self.r_arc[len(self.r_line)] = (center, pl, turns)
        self.r_start.extend(pos)
        self.r_end.extend(target)
        self.r_line.append(li)
        self.r_motion.append(motion)
        self.r_kind.append(kind)
        self.r_words.append(words)
        self.r_state.append(self.cur_state)
        pos[:] = target
