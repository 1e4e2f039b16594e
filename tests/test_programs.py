"""Part programs of the test parts (trueaxis.postproc.programs): CL data geometry, kinematics, slot sections, rs274."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest

from conftest import MACHINES
from rs274_helpers import run_rs274
from trueaxis.workpiece.parts import Nas979Params, SlotBlockParams, cone_signed_distance
from trueaxis.nc.cl import ClData, cl_axes, read_cl
from trueaxis.postproc.programs import (cone_flank_cl, nas979_program, read_setup, slots_program,
                                       twin_id)
from trueaxis.machine import forward_nominal, load_machine
from trueaxis.nc.gcode import parse_program

R = 5.0


def perfect(machine):
    return machine.with_parameters(np.zeros(len(machine.parameter_names())))


@pytest.fixture(scope="module")
def nmv():
    return load_machine(MACHINES / "nmv1500dcg.toml")


@pytest.fixture(scope="module")
def xh714():
    return load_machine(MACHINES / "xh714.toml")


@pytest.fixture(scope="module")
def cone():
    return Nas979Params().cone_surface()


@pytest.fixture(scope="module")
def cone_prog(nmv):
    """Coarse nas979 program (uniform 2 deg steps, no refinement: few blocks), uncompensated, part off the C axis."""
    return nas979_program(nmv, compensation="none", step_deg=2.0, chord_tol_um=None, placement_mm=(10.0, -5.0))


@pytest.fixture(scope="module")
def slots_prog(xh714):
    return slots_program(xh714)


def _axis_words(text: str, names) -> np.ndarray:
    """(M, n_axes) axis words of every G0/G1 block (mm, deg), in ``names`` order."""
    rows = []
    for line in text.splitlines():
        if re.match(r"^G[01]\s", line):
            rows.append([float(re.search(rf"{a}(-?[0-9.]+)", line).group(1)) for a in names])
    return np.array(rows)


# ----------------------------------------------------------------------------------------------- nas979 CL ----
def test_cl_tool_side_is_tangent_to_the_offset_cone_along_the_generatrix(cone):
    cl = cone_flank_cl(cone, R, stock_mm=0.2, finish_mm=0.1, step_deg=3.0)
    assert [p["name"] for p in cl.passes] == ["semi-finishing", "finishing"]
    a = np.asarray(cone["axis"])
    alpha = math.radians(cone["half_angle_deg"])
    ap = cone["height_range"][1] / math.cos(alpha)
    for k, offset in ((0, 0.1), (1, 0.0)):
        cut = (cl.kind == "cut") & (cl.pass_no == k)
        tip, u = cl.tip[cut], cl.axis[cut]
        np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-12)
        # Tool axis along the generatrix: the angle to the cone axis is the half angle, and u lies in the meridian
        # plane of the tip (u, a and the tip's radial direction are coplanar).
        np.testing.assert_allclose(u @ a, math.cos(alpha), atol=1e-12)
        radial = tip - np.outer(tip @ a, a)
        np.testing.assert_allclose(np.einsum("ij,ij->i", np.cross(u, a), radial), 0.0, atol=1e-9)
        # The tool-axis segment over the cone's height lies at R + offset from the cone: the side touches the offset
        # surface along the whole generatrix (exact signed distance of the analytic cone).
        for s in np.linspace(0.0, ap, 5):
            np.testing.assert_allclose(cone_signed_distance(tip + s * u, cone), R + offset, atol=1e-9)
        # The tip is at the base: the tool's end disk touches the base plane at most (no gouge of the wedge).
        assert np.all(tip @ a - R * math.sin(alpha) >= -1e-9)
        # Clockwise about a (down milling on the external cone), covering a full turn plus the overlap.
        ang = np.unwrap(np.arctan2(np.cross(a, [1.0, 0, 0]) @ tip.T, (tip - np.outer(tip @ a, a)) @ [1.0, 0, 0]))
        assert np.all(np.diff(ang) < 0) and ang[0] - ang[-1] > 2 * np.pi


def test_lead_in_and_lead_out_stay_off_the_surface(cone):
    cl = cone_flank_cl(cone, R, stock_mm=0.1, finish_mm=0.1, step_deg=3.0)
    assert [p["name"] for p in cl.passes] == ["finishing"]
    alpha = math.radians(cone["half_angle_deg"])
    ap = cone["height_range"][1] / math.cos(alpha)
    for kind in ("plunge", "lead_in", "lead_out", "approach", "retract"):
        sel = cl.kind == kind
        assert sel.any(), kind
        for s in np.linspace(0.0, ap, 5):
            d = cone_signed_distance(cl.tip[sel] + s * cl.axis[sel], cone)
            assert np.all(d > R + 0.01), kind  # the tool's side clear of the cone (finishing offset 0)
    # The lead-in arrives and the lead-out leaves tangentially: the last lead-in step is along the first cut step.
    idx = np.nonzero(cl.kind == "cut")[0]
    step_in = cl.tip[idx[0]] - cl.tip[idx[0] - 1]
    step_cut = cl.tip[idx[1]] - cl.tip[idx[0]]
    cos = step_in @ step_cut / np.linalg.norm(step_in) / np.linalg.norm(step_cut)
    assert cos > math.cos(math.radians(10))
    np.testing.assert_allclose(cl.feed[cl.kind == "approach"], 0.0)


def test_cl_csv_has_the_header_and_one_row_per_point(tmp_path, cone):
    cl = cone_flank_cl(cone, R, stock_mm=0.2, step_deg=5.0)
    path = tmp_path / "cl.csv"
    cl.write_csv(path)
    lines = path.read_text().splitlines()
    assert lines[0] == "x,y,z,i,j,k,f"
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    assert data.shape == (len(cl.tip), 7)
    np.testing.assert_allclose(data[:, :3], cl.tip, atol=1e-6)
    np.testing.assert_allclose(data[:, 3:6], cl.axis, atol=1e-6)


def test_refuses_bad_stock(cone):
    with pytest.raises(ValueError, match="stock"):
        cone_flank_cl(cone, R, stock_mm=0.0)


# ------------------------------------------------------------------------------------------- nas979 program ----
def test_program_poses_through_forward_kinematics_reproduce_the_cl(cone_prog):
    m = cone_prog.machine
    names = m.axis_names
    words = _axis_words(cone_prog.raw, names)
    q = np.column_stack([np.radians(words[:, c]) if m.axes[a].is_rotary else words[:, c]
                         for c, a in enumerate(names)])
    tip, u = forward_nominal(m, q)
    # Every CL point is a block of the program, in order (plus the rapids at the safe height around each pass).
    cl = cone_prog.cl
    zc = names.index("Z")
    at_safe = np.isclose(words[:, zc], cone_prog.safe_z, atol=1e-6)
    assert (~at_safe).sum() == len(cl.tip)
    np.testing.assert_allclose(tip[~at_safe], cl.tip, atol=2e-5)  # 6 decimals in the program
    np.testing.assert_allclose(u[~at_safe], cl.axis, atol=1e-6)
    # The setup comment says where the part is: its origin is the placement off the C axis (C pivot at 0, 0).
    setup = read_setup(cone_prog.raw)
    assert setup["part"] == "nas979"
    np.testing.assert_allclose(setup["origin_mm"], [10.0, -5.0, 50.0])
    np.testing.assert_allclose(m.workpiece_origin, [10.0, -5.0, 50.0])


def test_a_cl_file_of_a_program_pass_lands_on_the_program_s_axes(cone_prog):
    """One CL type, one path to the axes: the finishing pass written as a CAM CL file (CSV, 6 decimals), read back
    and solved the CAM way (``cl_axes``, branch "nearest", one pass, from the pass's approach) gives the part
    program's axes ("first-fit", pass by pass) to the file's rounding, and its own axes put the tool on the file's
    poses exactly."""
    m = cone_prog.machine
    cl = cone_prog.cl
    sel = np.nonzero(cl.pass_no == len(cl.passes) - 1)[0][1:-1]  # plunge .. lead-out: feeds > 0, no rapid inside
    cam = read_cl(cl.rows(sel).csv_text(), source="pass.csv")
    assert isinstance(cam, ClData) and cam.pass_no is None and len(cam) == sel.size
    q_cam, b = cl_axes(cam, m, previous=cone_prog.q[sel[0] - 1])  # from the pass's approach: C wound alike
    assert np.all(b == -1)  # the B -120..+30 table tilts negative on both paths
    tip, u = forward_nominal(m, q_cam)
    np.testing.assert_allclose(tip, cam.tip, rtol=0, atol=1e-9)
    np.testing.assert_allclose(u, cam.axis / np.linalg.norm(cam.axis, axis=1, keepdims=True), rtol=0, atol=1e-12)
    # 6-decimal rounding of tip (5e-7 mm) and axis (5e-7: C moves by up to 5e-7 / sin(B) = 6e-6 rad at B = -5 deg;
    # times the ~100 mm lever of the pivots for the linear axes)
    rot = np.array([m.axes[a].is_rotary for a in m.axis_names])
    np.testing.assert_allclose(q_cam[:, rot], cone_prog.q[sel][:, rot], rtol=0, atol=1e-5)
    np.testing.assert_allclose(q_cam[:, ~rot], cone_prog.q[sel][:, ~rot], rtol=0, atol=5e-4)


def test_program_structure_and_safe_height(cone_prog, nmv):
    text = cone_prog.raw
    assert text.startswith("%\n") and text.rstrip().endswith("M30\n%")
    conds = re.findall(r"\(trueaxis: ap=([0-9.]+) ae=([0-9.]+) fz=\S+ n=\S+ d=10 z=4 mode=down\)", text)
    assert [float(ae) for _, ae in conds] == pytest.approx([0.1, 0.1])  # 200 um stock: semi + finishing
    assert float(conds[0][0]) == pytest.approx(20 / math.cos(math.radians(15)), abs=1e-3)
    # The safe height clears the part at any B, C between the program's: every part point stays below it.
    assert cone_prog.safe_z <= nmv.axes["Z"].travel[1]
    prog = parse_program(text)
    assert np.all(prog.inverse_time[prog.motion == 1][1:] | (prog.feed[prog.motion == 1][1:] > 0))


def test_refinement_meets_the_chord_tolerance(nmv):
    prog = nas979_program(perfect(nmv), compensation="none", stock_um=100, step_deg=2.0, chord_tol_um=0.5)
    assert prog.info["chord_error_um"] <= 0.5
    assert len(prog.cl.passes) == 1


def test_compensated_program_differs_from_the_raw_one_by_little(cone_prog, nmv):
    geo = nas979_program(nmv, compensation="geometric", step_deg=2.0, chord_tol_um=None, placement_mm=(10.0, -5.0))
    # The setup comment names the mode and the twin that compensates (twin_id), so an identification can tell.
    assert geo.raw == cone_prog.raw.replace("compensation: none", "compensation: geometric").replace(
        "compensation=none", f"compensation=geometric twin={twin_id(nmv)}")
    assert read_setup(geo.text)["twin"] == twin_id(nmv) != twin_id(perfect(nmv))
    names = nmv.axis_names
    raw, comp = _axis_words(geo.raw, names), _axis_words(geo.text, names)
    if len(raw) == len(comp):  # moves were not split
        d = np.abs(comp - raw)
        assert 0 < d[:, :3].max() < 0.5
        assert d[:, 3:].max() < 0.05  # deg


# ---------------------------------------------------------------------------------------------- slot program ----
def _sections(text):
    parts = re.split(r"\(slot \d of 3: compensation \w+\)\n", text)
    assert len(parts) == 4
    return [p.split("(end of slot")[0] for p in parts[1:]]


def test_slot_sections_differ_only_where_compensation_applies(slots_prog, xh714):
    p = SlotBlockParams()
    raw = [s.splitlines() for s in slots_prog.info["sections_raw"]]
    posted = [s.splitlines() for s in _sections(slots_prog.text)]
    # Uncompensated, the three sections are the same program shifted by the slot pitch.
    w = [_axis_words("\n".join(s), "XYZ") for s in raw]
    for k in (1, 2):
        np.testing.assert_allclose(w[k] - w[0], np.tile([k * p.slot_pitch_x, 0, 0], (len(w[0]), 1)), atol=1e-9)
    # Slot 1 (none) is passed through; non-motion lines are identical in all three posted sections.
    assert "\n".join(posted[0]) == "\n".join(raw[0][1:-1])
    non_motion = [[ln for ln in s if not re.match(r"^G[01]\s", ln)] for s in posted]
    assert non_motion[0] == non_motion[1] == non_motion[2]
    # Motion blocks: same motion words and count; slots 2 and 3 moved by the compensation (micrometres), 3 apart
    # from 2 on the feed moves where the cutting force applies.
    motion = [[ln.split()[0] for ln in s if re.match(r"^G[01]\s", ln)] for s in posted]
    assert motion[0] == motion[1] == motion[2]
    c = [_axis_words("\n".join(s), "XYZ") for s in posted]
    d_geo = c[1] - w[1]
    d_com = c[2] - w[2]
    assert 1e-3 < np.abs(d_geo).max() < 0.2
    feed = np.array([m == "G1" for m in motion[0]])
    assert np.abs(d_com).max() < 0.2
    assert np.abs(d_com[feed] - d_geo[feed]).max() > 1e-3  # the force part of the comprehensive correction
    # Cutting conditions are stated for comprehensive mode.
    assert re.search(r"\(trueaxis: ap=0\.6 ae=10 fz=0\.05 n=5000 d=10 z=4 mode=down\)", "\n".join(posted[2]))


def test_slot_cl_follows_the_tool_centre_paths(slots_prog):
    p = SlotBlockParams()
    cl = slots_prog.cl
    assert isinstance(cl, ClData) and len(cl.passes) == 3 * len(p.pass_depths())
    cut = cl.kind == "cut"
    np.testing.assert_allclose(cl.axis, np.tile([0, 0, 1.0], (len(cl.tip), 1)))
    assert set(np.round(cl.tip[cut, 2], 9)) == set(np.round(p.pass_depths(), 9))
    ends = {tuple(np.round(r, 6)) for r in cl.tip[cut, :2]}
    for k in range(3):
        assert {tuple(np.round(r, 6)) for r in p.tool_centre_path(k)[1:, :2]} <= ends


# ------------------------------------------------------------------------------------------------------ rs274 ----
@pytest.mark.external
def test_rs274_reads_both_programs(tmp_path, nmv, slots_prog):
    cone = nas979_program(nmv, compensation="geometric", step_deg=3.0, chord_tol_um=None)
    for name, prog, n_axes in (("cone", cone, 5), ("slots", slots_prog, 3)):
        path = tmp_path / f"{name}.ngc"
        path.write_text(prog.text)
        moves = run_rs274(path, {1: 100.0}, tmp_path / name)
        assert moves.returncode == 0, moves.stderr
        assert "error" not in moves.stderr.lower(), moves.stderr
        words = _axis_words(prog.text, prog.machine.axis_names)
        assert len(moves.kind) == len(words)
        cols = [("XYZABC".index(a)) for a in prog.machine.axis_names]
        np.testing.assert_allclose(moves.end[:, cols], words, atol=6e-5)


def test_programs_state_their_work_offset_and_the_setup_they_expect(cone_prog, slots_prog, nmv):
    from trueaxis.postproc.post import compensate

    for prog, zero in ((cone_prog, "G10 L2 P1 X0 Y0 Z0 B0 C0"), (slots_prog, "G10 L2 P1 X0 Y0 Z0")):
        lines = prog.text.splitlines()
        assert any(line.startswith("(setup expected: work offset G54 = machine zero") for line in lines)
        i = lines.index(zero)
        assert lines[i + 1] == "G54" and "G43" not in prog.raw and "G49" in lines[i - 1]
        # the program itself gives its offset: the post needs no setup and names where the offset came from
        p = parse_program(prog.raw, require_setup=True)
        assert [u["what"] for u in p.setup_used] == ["G54"]
        assert p.setup_used[0]["source"] == f"<string>:{i + 1} (G10 L2)"
    out = compensate(cone_prog.raw, cone_prog.machine, "geometric", source="cone.ngc")
    assert any(line.startswith("(trueaxis setup: G54 0 mm, from cone.ngc:") for line in out.splitlines()[:8])


def test_placed_for_puts_the_programs_tool_in_the_spindle():
    # The setup comment's tool_d_mm is the tool the program was made for: the shop (simulate), the diagnosis and the
    # identification cut with it; the machine file's length and flutes stay (the axis words assume that length).
    from trueaxis.postproc.programs import ProgramError, placed_for, setup_comment

    nmv = load_machine(MACHINES / "nmv1500dcg.toml")
    text = setup_comment("nas979", nmv.workpiece_origin, (0.0, 0.0), 8.0, "none") + "\nG0 X0\n"
    placed = placed_for(nmv, text, "nas979")
    assert placed.tool == dataclasses.replace(nmv.tool, radius=4.0) and nmv.tool.radius == 5.0
    assert placed_for(nmv, "G0 X0\n").tool == nmv.tool  # a program that does not say: the machine file's tool
    with pytest.raises(ProgramError, match="tool_d_mm=-8 is not a positive number"):
        placed_for(nmv, text.replace("tool_d_mm=8", "tool_d_mm=-8"))


@pytest.mark.parametrize("name", ["nmv1500dcg", "bc_offset"])
def test_a_five_axis_slot_programs_lifts_and_plunges_run_at_their_feed_as_rs274_reads_them(name, tmp_path):
    # A QA pass: each pass's lift out of the slot was written "F200.0" while G93 (inverse time) was still in force
    # from the cut: rs274 lifted at 520-1000 mm/min instead of 200. Every plunge and lift now runs at its CL feed in
    # units per minute, as rs274 reads the program; the cuts stay inverse time.
    prog = slots_program(load_machine(MACHINES / f"{name}.toml"), post=False)  # (the post keeps the feed words)
    path = tmp_path / "slots.ngc"
    path.write_text(prog.text)
    run_rs274(path, {1: 0.0}, tmp_path / "rs")
    canon = (tmp_path / "rs" / "canon.txt").read_text().splitlines()
    feed, last, lifts, plunges = 0.0, None, [], []
    for line in canon:
        m = re.search(r"SET_FEED_RATE\(([-\d.]+)\)", line)
        if m:
            feed = float(m.group(1))
        m = re.search(r"STRAIGHT_(FEED|TRAVERSE)\(([^)]*)\)", line)
        if m:
            end = np.array([float(v) for v in m.group(2).split(",")])
            if m.group(1) == "FEED" and last is not None and np.allclose(end[[0, 1, 3, 4, 5]], last[[0, 1, 3, 4, 5]]):
                (lifts if end[2] > last[2] else plunges).append(feed)
            last = end
    n_passes = sum(1 for k in prog.cl.kind if k == "lift")
    assert len(lifts) == n_passes > 0 and len(plunges) == n_passes, (len(lifts), len(plunges), n_passes)
    assert lifts == [200.0] * n_passes and plunges == [200.0] * n_passes
    assert "G93" in prog.text  # (the cuts in inverse time, as before)
