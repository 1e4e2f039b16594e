"""TCP output (trueaxis.postproc.tcp): the control's own nominal kinematics turn the written tool-tip positions into
the joints whose actual pose (the twin) is the nominal pose.

The control is LinuxCNC's xyzbc-trt-kins / xyzac-trt-kins, its inverse kinematics written out here from trtfuncs.c
(independently of trueaxis): LinuxCNC 2.9 (the installed rs274's version; the rotary axes turn the table, the
default) and LinuxCNC 2.10's ``conventional-directions`` pin set (ISO's sense). Its HAL pins come from the machine
file as docs/linuxcnc.md says; the interpreter adds the tool length to Z (G43) and the kinematics take it off again
(``tool-offset`` pin)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from rs274_helpers import run_rs274
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.nc.gcode import parse_program
from trueaxis.postproc.post import PostError, post_text
from trueaxis.nc.setup import Setup

ROOT = Path(__file__).resolve().parents[1]
TOOL_MM = 87.5  # the tool length of G43 H1 at the control (any: it cancels)


def xyzbc_inverse(pos, b_deg, c_deg, xr, yr, zr, dx, dz, dt, version):
    """LinuxCNC xyzbcKinematicsInverse: joints X Y Z from pos (K, 3) (world + tool length in Z) and the b, c words.
    version "2.9": the table's sense (no conventional-directions pin); "2.10-conventional": the pin set (con = 1)."""
    b, c = np.radians(b_deg), np.radians(c_deg)
    x, y, z = (pos[:, i] for i in range(3))
    dz = dz + dt
    if version == "2.9":
        dpx = -np.cos(b) * dx - np.sin(b) * dz + dx
        dpz = np.sin(b) * dx - np.cos(b) * dz + dz
        X = (np.cos(c) * np.cos(b) * (x - xr) - np.sin(c) * np.cos(b) * (y - yr) + np.sin(b) * (z - zr) + dpx + xr)
        Y = np.sin(c) * (x - xr) + np.cos(c) * (y - yr) + yr
        Z = (-np.cos(c) * np.sin(b) * (x - xr) + np.sin(c) * np.sin(b) * (y - yr) + np.cos(b) * (z - zr) + dpz + zr)
    else:
        con = 1.0
        dpx = -np.cos(b) * dx + np.sin(b) * dz + dx
        dpz = -np.sin(b) * dx - np.cos(b) * dz + dz
        X = (np.cos(c) * np.cos(b) * (x - xr) + con * np.sin(c) * np.cos(b) * (y - yr)
             - con * np.sin(b) * (z - zr) + dpx + xr)
        Y = -con * np.sin(c) * (x - xr) + np.cos(c) * (y - yr) + yr
        Z = (con * np.cos(c) * np.sin(b) * (x - xr) + np.sin(c) * np.sin(b) * (y - yr) + np.cos(b) * (z - zr)
             + dpz + zr)
    return np.column_stack([X, Y, Z])


def xyzac_inverse(pos, a_deg, c_deg, xr, yr, zr, dy, dz, dt):
    """LinuxCNC 2.9 xyzacKinematicsInverse (the table's sense)."""
    a, c = np.radians(a_deg), np.radians(c_deg)
    x, y, z = (pos[:, i] for i in range(3))
    dz = dz + dt
    X = np.cos(c) * (x - xr) - np.sin(c) * (y - yr) + xr
    Y = (np.sin(c) * np.cos(a) * (x - xr) + np.cos(c) * np.cos(a) * (y - yr) - np.sin(a) * (z - zr)
         - np.cos(a) * dy + np.sin(a) * dz + dy + yr)
    Z = (np.sin(c) * np.sin(a) * (x - xr) + np.cos(c) * np.sin(a) * (y - yr) + np.cos(a) * (z - zr)
         - np.sin(a) * dy - np.cos(a) * dz + dz + zr)
    return np.column_stack([X, Y, Z])


def _program(machine, tilt, model_deg):
    """A joint-mode five-axis program (G43 H1 active) with the given model angles (deg) of tilt and C per move."""
    sign = machine.word_signs6()
    col = "XYZABC".index(tilt)
    lines = ["G21 G90 G94 G17", "G43 H1", "G0 X0 Y0 Z30 " + f"{tilt}0 C0", "F800"]
    xyz = [(20, -10, 5), (-15, 12, 8), (5, 15, 12), (-8, -6, 20)]
    for (x, y, z), (t, c) in zip(xyz, model_deg):
        lines.append(f"G1 X{x} Y{y} Z{z} {tilt}{t * sign[col]:g} C{c * sign[5]:g}")
    return "\n".join(lines + ["M2"]) + "\n"


CASES = {
    "bc-2.9": ("bc_offset.toml", "B", "linuxcnc-trt", "2.9"),
    "bc-2.10-conventional": ("bc_offset.toml", "B", "iso", "2.10-conventional"),
    "ac-2.9": ("ac_trunnion.toml", "A", "linuxcnc-trt", "2.9"),
}


def _control_joints(m, tilt, version, written):
    """(K, n_axes) model joints (mm, rad) the LinuxCNC control reaches for written TCP words (K, 6): pins from the
    machine file as docs/linuxcnc.md maps them, world = the written position (work offsets 0), the interpreter adds
    the tool length to Z and the kinematics' tool-offset pin takes it off."""
    piv = {a: np.asarray(m.axes[a].pivot, float) for a in m.rotary_axes}
    pos = written[:, :3] + [0.0, 0.0, TOOL_MM]
    xr, yr = piv["C"][0], piv["C"][1]
    t = "ABC".index(tilt)
    if tilt == "B":
        zr, dx = piv["B"][2], piv["B"][0] - piv["C"][0]
        joints = xyzbc_inverse(pos, written[:, 4], written[:, 5], xr, yr, zr, dx, 0.0, TOOL_MM, version)
    else:
        zr, dy = piv["A"][2], piv["A"][1] - piv["C"][1]
        joints = xyzac_inverse(pos, written[:, 3], written[:, 5], xr, yr, zr, dy, 0.0, TOOL_MM)
    sign = m.word_signs6()
    rot = np.column_stack([written[:, 3 + t] * sign[3 + t], written[:, 5] * sign[5]])
    return np.column_stack([joints - [0.0, 0.0, TOOL_MM], np.radians(rot)])


@pytest.mark.parametrize("case", list(CASES))
def test_tcp_output_through_linuxcnc_inverse_kinematics_lands_on_the_nominal_pose(case, tmp_path):
    from test_post_arcs import _distance_to_polyline

    file, tilt, sense, version = CASES[case]
    base = load_machine(ROOT / "fixtures" / "machines" / file)
    m = dataclasses.replace(base, rotary_sense=sense, tcp_code="G43")
    src = _program(m, tilt, [(-20, 30), (-35, 120), (-10, 200), (-50, -40)])
    setup = Setup(offsets_zero=True)
    out, rep = post_text(src, m, "geometric", tol_um=1.0, setup=setup, output_mode="tcp")
    assert rep.output_mode == "tcp" and "output tcp" in out
    # rs274 (LinuxCNC's interpreter) reads it, G43 and all, and sees what we write (4 printed decimals)
    path = tmp_path / "out.ngc"
    path.write_text(out)
    moves = run_rs274(path, {1: TOOL_MM}, tmp_path / "rs274")
    assert moves.returncode == 0, moves.stderr[-2000:]
    ours = parse_program(out, setup=setup)
    assert len(ours) == len(moves.kind)
    np.testing.assert_allclose(moves.end, ours.end, atol=5e-5)
    twin = ErrorTwin(m)
    sign = m.word_signs6()
    t = "ABC".index(tilt)

    def model(ends):  # program words of a joint-mode program -> model joints
        return np.column_stack([ends[:, :3], np.radians(ends[:, [3 + t, 5]] * sign[[3 + t, 5]])])

    q_out = _control_joints(m, tilt, version, ours.end)
    p_act, u_act = twin.actual_pose(q_out)
    # 1. every input move's end pose is reached exactly (solver and written digits: 0.1 um, 1 urad), in order
    nominal = parse_program(src, setup=setup)
    p_nom, u_nom = twin.nominal_pose(model(nominal.end))
    err = np.linalg.norm(p_act[None] - p_nom[:, None], axis=2)  # (input ends, output ends)
    best = np.argmin(err, axis=1)
    assert np.all(np.diff(best) > 0) and best[-1] == len(ours) - 1
    pos_um = err[np.arange(len(best)), best] * 1e3
    axis_urad = np.linalg.norm(u_act[best] - u_nom, axis=1) * 1e6
    assert pos_um.max() <= 0.1, pos_um
    # (the first end, tilt 0, lies in the singular cone: its free axis is held and a tool-axis error stays, as the
    # report says; joint output leaves the same)
    singular = np.abs(nominal.end[:, 3 + t]) < 1.0
    assert singular.tolist() == [True] + [False] * (len(best) - 1) and rep.singular_block_count >= 1
    assert axis_urad[~singular].max() <= 1.0, axis_urad
    # 2. between the written points the control moves the tool tip straight in the table's frame and the rotary
    # axes linearly; the actual tip stays within the tolerance of the nominal path (the joint-linear input moves)
    qn = model(nominal.end)
    f = np.linspace(0.0, 1.0, 4001)
    path_nom = np.vstack([twin.nominal_pose(qn[i] + f[:, None] * (qn[i + 1] - qn[i]))[0] for i in range(len(qn) - 1)])
    worst = 0.0
    for s in (0.25, 0.5, 0.75):
        w = ours.end[:-1] + s * (ours.end[1:] - ours.end[:-1])
        p_mid, _ = twin.actual_pose(_control_joints(m, tilt, version, w[1:]))  # (the first move starts unknown)
        worst = max(worst, float(_distance_to_polyline(p_mid, path_nom).max() * 1e3))
    assert worst <= 1.0 + 0.05, worst
    # and the TCP positions are not the joints: the table's turn moved them by millimetres
    joint_out, _ = post_text(src, m, "geometric", tol_um=1.0, setup=setup)
    assert np.abs(parse_program(joint_out, setup=setup).end[-1, :3] - ours.end[-1, :3]).max() > 1.0


# A QA pass's program: a rapid that turns C by -300 deg. Written as one block, the control (planning it as a straight
# line of the tip in the table's frame) took the joints to X 116, Y -47.5..59 and Z 25.5, where the input's rapid
# (joint-interpolated) stays within X 10..30, Y -15..20, Z 60..70.
RAPID_TURN = ("G21 G90 G17 G94\nT1 M6\nG43 H1\nG0 X10 Y20 Z60 B20 C0\nG0 X30 Y-15 Z70 B25 C-300\nG0 X35\n"
              "G1 X36 F300\nM2\n")


def _rapid_path_deviation(m, twin, written, q_from, q_to, version="2.9"):
    """(um, (3, 2) joint X Y Z range): how far the actual tip leaves the nominal tip's path along the input's
    joint-interpolated move q_from -> q_to (model joints) when the control runs the written TCP blocks ``written``
    (K, 6; the first at q_from) the TCP way (tip straight in the table's frame, rotary words linear); and the range of
    the control's joints X Y Z along the way."""
    from test_post_arcs import _distance_to_polyline

    s = np.linspace(0.0, 1.0, 21)[:, None]
    w = np.vstack([a + s * (b - a) for a, b in zip(written[:-1], written[1:])])
    q = _control_joints(m, "B", version, w)
    p_act, _ = twin.actual_pose(q)
    f = np.linspace(0.0, 1.0, 40001)[:, None]
    p_nom, _ = twin.nominal_pose(q_from + f * (q_to - q_from))
    dev_um = float(_distance_to_polyline(p_act, p_nom).max() * 1e3)
    return dev_um, np.column_stack([q[:, :3].min(axis=0), q[:, :3].max(axis=0)])


def test_tcp_rapid_that_turns_the_table_is_split_to_follow_the_input_rapid(tmp_path):
    base = load_machine(ROOT / "fixtures" / "machines" / "bc_offset.toml")
    m = dataclasses.replace(base, rotary_sense="linuxcnc-trt", tcp_code="G43")
    setup = Setup(offsets_zero=True)
    out, rep = post_text(RAPID_TURN, m, "geometric", tol_um=1.0, setup=setup, output_mode="tcp", header=False)
    lines = out.splitlines()
    path = tmp_path / "out.ngc"
    path.write_text(out)
    moves = run_rs274(path, {1: TOOL_MM}, tmp_path / "rs274")
    assert moves.returncode == 0, moves.stderr[-2000:]
    ours = parse_program(out, setup=setup)
    np.testing.assert_allclose(moves.end, ours.end, atol=5e-5)
    # through LinuxCNC's inverse kinematics (written out above) and the twin: the tip follows the input's rapid (the
    # blocks from the first rapid's end to the turning one's; G0 X35 and G1 X36 after them)
    twin = ErrorTwin(m)
    q_from = np.r_[10.0, 20.0, 60.0, np.radians([-20.0, 0.0])]
    q_to = np.r_[30.0, -15.0, 70.0, np.radians([-25.0, 300.0])]
    dev_um, box = _rapid_path_deviation(m, twin, ours.end[:-2], q_from, q_to)
    assert dev_um <= 1.0 + 0.05, dev_um
    # the joints stay in the box of the input's move (plus the correction, tens of um), not 86 mm outside it
    np.testing.assert_allclose(box, [[10.0, 30.0], [-15.0, 20.0], [60.0, 70.0]], atol=0.1)
    # the rapid is written as rapids (G0, no feed word), many of them; the XYZ-only rapid after it stays one block
    assert lines[:3] == RAPID_TURN.splitlines()[:3] and lines[-1] == "M2"
    blocks = lines[3:-1]  # one row of ``ours`` each: the first rapid, the turning one's pieces, G0 X35, G1 X36
    assert len(blocks) == len(ours) and len(blocks) > 100
    assert all(x.startswith("G0 ") and "F" not in x for x in blocks[:-1]) and blocks[-1].startswith("G1 ")
    assert rep.moves_split == 1  # G0 X35 (X only) one block, as G1 X36
    # joint output: the rapid stays one block (the control interpolates the joints as the input does)
    joint_out, _ = post_text(RAPID_TURN, m, "geometric", tol_um=1.0, setup=setup, header=False)
    assert len(joint_out.splitlines()) == len(RAPID_TURN.splitlines())


def test_tcp_rapid_pieces_take_no_inverse_time_feed():
    base = load_machine(ROOT / "fixtures" / "machines" / "bc_offset.toml")
    m = dataclasses.replace(base, rotary_sense="linuxcnc-trt", tcp_code="G43")
    src = RAPID_TURN.replace("G94", "G93").replace("F300", "F10")
    out, _ = post_text(src, m, "geometric", tol_um=1.0, setup=Setup(offsets_zero=True), output_mode="tcp",
                       header=False)
    rapids = [x for x in out.splitlines() if x.startswith("G0 ")]
    feeds = [x for x in out.splitlines() if x.startswith("G1 ")]
    assert len(rapids) > 100 and not any("F" in x for x in rapids)
    assert len(feeds) == 1 and feeds[0].endswith(" F10")


def test_tcp_code_g43_4_replaces_the_programs_g43():
    m = load_machine(ROOT / "fixtures" / "machines" / "nmv1500dcg.toml")
    src = _program(m, "B", [(-20, 30), (-35, 120), (-10, 200), (-50, -40)])
    setup = Setup(offsets_zero=True)
    fanuc, _ = post_text(src, m, "geometric", setup=setup, output_mode="tcp", header=False)
    linuxcnc, _ = post_text(src, dataclasses.replace(m, tcp_code="G43"), "geometric", setup=setup,
                            output_mode="tcp", header=False)
    assert "G43.4 H1" in fanuc.splitlines() and "G43 H1" in linuxcnc.splitlines()
    assert fanuc.replace("G43.4 H1", "G43 H1") == linuxcnc


def test_tcp_output_refuses_what_it_cannot_write(tmp_path):
    m = load_machine(ROOT / "fixtures" / "machines" / "nmv1500dcg.toml")
    setup = Setup(offsets_zero=True)
    src = _program(m, "B", [(-20, 30), (-35, 120), (-10, 200), (-50, -40)])
    with pytest.raises(PostError, match="tool length"):
        post_text(src.replace("G43 H1\n", ""), m, "geometric", setup=setup, output_mode="tcp")
    with pytest.raises(ValueError, match="five-axis"):
        post_text(src, load_machine(ROOT / "fixtures" / "machines" / "xh714.toml"), "geometric", setup=setup,
                  output_mode="tcp")
    with pytest.raises(ValueError, match="table-table"):
        post_text(src, load_machine(ROOT / "fixtures" / "machines" / "headtable.toml"), "geometric", setup=setup,
                  output_mode="tcp")
    # A tool length in force: the control turns the tip, a tool length below the joints' point, which the TCP frame
    # does not model: refused (a QA pass: the tip written 13.5 mm off at B 10 deg with an 87.5 mm tool, exit 0)
    from trueaxis.nc.setup import load_setup

    tools = tmp_path / "tools.tbl"
    tools.write_text("T1 P1 Z87.5 D10\n")
    with pytest.raises(PostError, match=r":\d+: TCP output with a tool length offset in force \(tool 1 offset "
                                        r"Z87.5 mm\)"):
        post_text(src, m, "geometric", setup=load_setup(tool_table=tools, offsets_zero=True), output_mode="tcp")


def test_tcp_output_refuses_machine_positions_where_the_table_is_turned():
    # G53 / G28 / G30 words are joint positions; under TCP kinematics the control reads them as the tip in the table's
    # frame, the same only with the rotary axes at zero (the trt kinematics are the identity there: checked with
    # _control_joints). With the table turned they were passed through with a warning only (a QA pass).
    m = load_machine(ROOT / "fixtures" / "machines" / "bc_offset.toml")
    setup = Setup(offsets_zero=True)
    src = _program(m, "B", [(-20, 30), (-35, 120), (-10, 200), (-50, -40)])
    w = np.array([[10.0, 20.0, 30.0, 0.0, 0.0, 0.0], [-40.0, 5.0, 60.0, 0.0, 360.0, 720.0]])
    np.testing.assert_allclose(_control_joints(m, "B", "2.9", w)[:, :3], w[:, :3], atol=1e-9)
    turned = src.replace("M2\n", "G53 G0 Z90\nM2\n")
    with pytest.raises(PostError, match=r":9: TCP output: a G53 move with a rotary axis off zero is not written"):
        post_text(turned, m, "geometric", setup=setup, output_mode="tcp")
    at_zero = src.replace("M2\n", "G0 B0 C360\nG53 G0 Z90\nM2\n")
    out, _ = post_text(at_zero, m, "geometric", setup=setup, output_mode="tcp", header=False)
    assert "G53 G0 Z90" in out.splitlines()
    joint, _ = post_text(turned, m, "geometric", setup=setup, output_mode="joint", header=False)
    assert "G53 G0 Z90" in joint.splitlines()  # joint output: the joints, as written


def test_machine_file_output_mode_is_read_and_written_back(tmp_path):
    from trueaxis.machine.machine_file import dump_machine

    text = (ROOT / "fixtures" / "machines" / "nmv1500dcg.toml").read_text()
    text = text.replace('bed_to_tool = ["Y", "X", "Z"]',
                        'bed_to_tool = ["Y", "X", "Z"]\noutput_mode = "tcp"\ntcp_code = "G43"', 1)
    path = tmp_path / "m.toml"
    path.write_text(text)
    m = load_machine(path)
    assert (m.output_mode, m.tcp_code) == ("tcp", "G43")
    again = tmp_path / "again.toml"
    again.write_text(dump_machine(m))
    m2 = load_machine(again)
    assert (m2.output_mode, m2.tcp_code) == ("tcp", "G43")
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('output_mode = "tcp"', 'output_mode = "tool-tip"'))
    with pytest.raises(Exception, match="output_mode"):
        load_machine(bad)
