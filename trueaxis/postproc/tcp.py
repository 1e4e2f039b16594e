"""Tool-centre-point (TCP) output: positions for a control that runs its own nominal kinematics.

In joint mode (the default) the post writes the commanded joints q: the control moves each axis to its word. In TCP
mode (LinuxCNC ``xyzbc-trt-kins`` / ``xyzac-trt-kins`` in their TCP type, ``G43.4`` on Fanuc-style controls) the
control reads X Y Z as the tool tip in the table's frame and turns them into joints with its *nominal* kinematics.
So the post still solves the joints q whose *actual* pose (the twin) is the nominal tool pose, and then writes what
the control's nominal kinematics turns into exactly those q: the nominal forward kinematics of q, in the control's
TCP frame, and the rotary words of q unchanged.

The control's TCP frame ("world"): the machine frame M with every rotary axis at zero, fixed to the table, so that it
turns with it: ``world = P · p_W`` with ``p_W`` the model's nominal tool tip in the part frame and P the placement of
the part (``[workpiece] origin``, axes parallel). Work offsets (G54...) then act in that frame, as in joint mode at
zero rotary angles. LinuxCNC's parameters from the machine file (docs/linuxcnc.md): ``x-rot-point``, ``y-rot-point``
= C's ``pivot`` (x, y); B's line through ``(x-rot-point + x-offset, *, z-rot-point + z-offset)`` = B's ``pivot``
(A's: ``(*, y-rot-point + y-offset, z-rot-point + z-offset)``); ``tool-offset`` = the tool length of G43, which must
be 0 here: the control turns the tip, a tool length below the joints' point, about the rotary axes, and this frame
takes the joints' point as the tip (``refuse_tool_length``: a non-zero length is refused, not written wrong);
``conventional-directions`` per ``rotary_sense``.

Only table-table machines (both rotary axes on the workpiece branch) have such a frame (a head turns the tool, and
LinuxCNC's trt kinematics do not describe it); the post refuses TCP output for others."""

from __future__ import annotations

import numpy as np

OUTPUT_MODES = ("joint", "tcp")


def check_tcp_machine(machine) -> None:
    """ValueError unless the machine's TCP frame is defined: two rotary axes, both on the workpiece branch."""
    if not machine.is_five_axis:
        raise ValueError(f"TCP output needs a five-axis machine; {machine.name} has the axes "
                         f"{' '.join(machine.axis_names)}")
    heads = [a for a in machine.rotary_axes if machine.axes[a].branch != "workpiece"]
    if heads:
        raise ValueError(f"TCP output is for table-table machines (LinuxCNC xyzbc-trt-kins / xyzac-trt-kins): "
                         f"{machine.name} turns the tool with {' '.join(heads)}")


class TcpFrame:
    """The control's nominal kinematics between joints q (K, n_axes) mm / rad and TCP positions (K, 3) mm."""

    def __init__(self, twin, machine):
        check_tcp_machine(machine)
        self.twin = twin
        self.origin = np.asarray(machine.workpiece_origin, float)
        self.linear = [j for j, a in enumerate(machine.axis_names) if not machine.axes[a].is_rotary]

    def world(self, q) -> np.ndarray:
        """(K, 3) the TCP position of joints q: the nominal tool tip in the table's frame."""
        return self.twin.nominal_pose(q)[0] + self.origin

    def joints(self, world, q_rotary) -> np.ndarray:
        """(K, n_axes) the joints the control's nominal kinematics gives for TCP positions ``world`` (K, 3) with the
        rotary positions of ``q_rotary`` (K, n_axes; its linear columns are ignored). At fixed rotary angles the
        nominal tip is affine in X Y Z (tip = R xyz + t): R and t from four evaluations, then solved."""
        q = np.array(q_rotary, float)
        K = q.shape[0]
        base = q.copy()
        base[:, self.linear] = 0.0
        t = self.twin.nominal_pose(base)[0]
        R = np.empty((K, 3, 3))
        for i, col in enumerate(self.linear):
            unit = base.copy()
            unit[:, col] = 1.0
            R[:, :, i] = self.twin.nominal_pose(unit)[0] - t
        xyz = np.linalg.solve(R, (world - self.origin - t)[:, :, None])[:, :, 0]
        q[:, self.linear] = xyz
        return q

    def command_delta(self, q_cmd, q_nom) -> np.ndarray:
        """(K, n_axes) what is written in place of the nominal joints q_nom: joint mode writes q_cmd - q_nom; TCP
        mode the TCP position of q_cmd less the nominal joints' X Y Z (so that the program's own X Y Z plus this
        is the TCP position; the work offset acts on both alike), the rotary axes as in joint mode."""
        d = q_cmd - q_nom
        d[:, self.linear] = self.world(q_cmd) - q_nom[:, self.linear]
        return d

    def interpolate(self, ca, cb, s) -> np.ndarray:
        """(K, n_axes) the joints the control passes through at fraction s (scalar or (K,)) of a straight move from
        joints ca to cb (K, n_axes) in TCP mode: the TCP position and the rotary axes linear in s."""
        s = np.asarray(s, float)
        s2 = s[:, None] if s.ndim else s
        wa, wb = self.world(ca), self.world(cb)
        return self.joints(wa + s2 * (wb - wa), ca + s2 * (cb - ca))


def refuse_tool_length(prog, source: str) -> None:
    """PostError when a tool length offset other than zero is in force: the control's TCP kinematics (LinuxCNC's trt
    kinematics with its ``tool-offset`` pin, a Fanuc G43.4) turn the tool tip, a tool length below the joints' point,
    about the rotary axes, which ``TcpFrame`` does not model yet (it takes the joints' point as the tip): the written
    tip missed by about L sin B, 13.5 mm at B 10 deg with an 87.5 mm tool, exit 0 (a QA pass). Until it does, TCP
    output is written for a zero tool length only (the tool table's length 0, or ``--offsets-zero`` without it, and
    the control's ``tool-offset`` 0)."""
    from .post import PostError, tool_offsets_in_force

    used = tool_offsets_in_force(prog)
    if used:
        raise PostError(source, int(used[0]["first_line"]), f"TCP output with a tool length offset in force "
                                                            f"({used[0]['said']}): not written, the TCP frame does not "
                                                            "model the tip a tool length below the joints yet (it "
                                                            "would miss by about L sin B); use --output-mode joint")


def refuse_machine_positions_turned(prog, machine, source: str) -> None:
    """PostError for a G53 move or a G28 / G30 return in TCP output where a rotary axis stands off zero (mod 360 deg)
    at its start or end. Their words are the joints' positions, written as given; under TCP kinematics the control
    reads them as the tip's position in the table's frame, which is the joints' only with the rotary axes at zero
    (LinuxCNC's trt kinematics are the identity there): elsewhere the tool goes somewhere else entirely, on a straight
    line of the tip while the table turns (a QA pass: passed through with a warning only)."""
    from ..nc.gcode import AXES, ROW_MACHINE, ROW_REFERENCE
    from .post import PostError

    rows = np.nonzero(np.isin(prog.kind, (ROW_MACHINE, ROW_REFERENCE)))[0]
    cols = [AXES.index(a) for a in machine.rotary_axes]
    if rows.size == 0 or not cols:
        return
    ends = np.stack([prog.to_machine(prog.start[rows], rows), prog.to_machine(prog.end[rows], rows)])[..., cols]
    off_zero = np.abs((ends + 180.0) % 360.0 - 180.0) > 1e-9  # deg
    turned = np.nonzero(off_zero.any(axis=(0, 2)))[0]
    if turned.size:
        r = int(rows[turned[0]])
        what = "G53 move" if prog.kind[r] == ROW_MACHINE else "G28 / G30 return"
        raise PostError(source, int(prog.line_no[r]), f"TCP output: a {what} with a rotary axis off zero is not "
                                                      "written (its words are joint positions; under TCP kinematics "
                                                      "the control reads them as the tip's position in the table's "
                                                      "frame, the same only with the rotary axes at zero): move it "
                                                      "where the rotary axes stand at 0, or --output-mode joint")


def tcp_lines(prog, machine, source: str) -> list:
    """The program's lines for TCP output: every ``G43`` (tool length compensation from the table, ``G43 H..``) made
    the machine's TCP code (``[kinematics] tcp_code``, default ``G43.4``: Fanuc-style tool centre point with the tool
    length of H; LinuxCNC's trt kinematics take ``G43``, kept as it is). Refused (PostError): a tool length other
    than zero in force (``refuse_tool_length``), no G43 before the first move (the control's TCP transform needs the
    tool length), and canned cycles (their Z moves are along the table's Z in TCP mode, not the tool's)."""
    import re

    from ..nc.gcode import ROW_CYCLE, ROW_PROGRAMMED
    from .post import PostError, _split_comment, _split_ending

    refuse_tool_length(prog, source)
    refuse_machine_positions_turned(prog, machine, source)
    code = getattr(machine, "tcp_code", "G43.4")
    if np.any(prog.kind == ROW_CYCLE):
        r = int(np.argmax(prog.kind == ROW_CYCLE))
        raise PostError(source, int(prog.line_no[r]), "TCP output: canned cycles are not written in TCP mode (the "
                                                      "control drills along the table's Z): program the holes as "
                                                      "moves, or --output-mode joint")
    g43 = re.compile(r"(?i)\bG0*43(?![.\d])")
    moves = np.nonzero(prog.kind == ROW_PROGRAMMED)[0]
    first_move = int(prog.line_index[moves[0]]) if moves.size else len(prog.lines)
    out, seen = [], None
    for i, line in enumerate(prog.lines):
        body, ending = _split_ending(line)
        text, comment = _split_comment(body)
        if g43.search(text):
            seen = i if seen is None else seen
            if code != "G43":
                text = g43.sub(code, text)
            line = text + comment + ending
        out.append(line)
    if seen is None or seen > first_move:
        raise PostError(source, first_move + 1, f"TCP output needs the tool length: put G43 H.. before the first "
                                                f"move (written as {code} H..; the control's TCP transform turns the "
                                                "tool tip)")
    return out
