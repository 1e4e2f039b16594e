"""The five-axis post: machine-axis programs and CL data; tip and tool axis compensated together, the singular cone,
splitting, inverse-time feeds, and CL data in (CSV, APT) through the inverse kinematics.

Bounds, and where they come from:
- solved points (block ends, split points): 0.1 um and 1 urad, the issue's bound. The solver stops at 0.01 um /
  0.1 urad; the written numbers (6 decimals here, as the input) add at most 0.0005 um and 1e-6 deg = 0.017 urad,
  i.e. 0.02 um at the 100-200 mm lever arms of these tables.
- the actual path between output points: the post's tolerance (tol_um = 1 um, 1 urad) at the piece midpoints, where
  the post checks it (same fraction of the move: the same instant under linear interpolation).
- the uncompensated program misses by tens of um and urad on these machines, so every check below can fail.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import numpy as np
import pytest

from conftest import MACHINES, ROOT
from post_checks import machine_rows
from rs274_helpers import assert_rs274_reads_as_we_do
from trueaxis.machine import ErrorTwin, forward_nominal, load_machine
from trueaxis.nc.cl import ClError, cl_to_program, read_cl
from trueaxis.nc.gcode import FEED, parse_program
from trueaxis.postproc.post import PostError, compensate, without_header
from trueaxis.sim.programs import cone_flank_program

CONE = {"axis": [math.sin(math.radians(10)), 0.0, math.cos(math.radians(10))], "half_angle_deg": 15.0,
        "base_radius": 40.0, "height_range": [0.0, 20.0]}
CL_CSV = ROOT / "fixtures" / "programs" / "cone_cl.csv"
CL_APT = ROOT / "fixtures" / "programs" / "cone_cl.apt"
TOL_UM = 1.0
POINT_UM, POINT_URAD = 0.1, 1.0
SINGULAR_DEG = 1.0


def hand_moves(tilt: str, sign: float) -> list:
    """A rapid into the singular cone, two cuts inside it (tilt 0, then 0.5 deg while C turns 45 deg), a long
    simultaneous move out of it (tilt to 30 deg, C +45 deg), and a long C move (110 deg): both need splitting."""
    return [
        f"G0 X20.000000 Y10.000000 Z40.000000 {tilt}0.000000 C0.000000",
        "G93",
        f"N910 G1 X25.000000 Y12.000000 Z38.000000 {tilt}0.000000 C0.000000 F60.0000",
        f"N920 G1 X25.000000 Y12.000000 Z38.000000 {tilt}{0.5 * sign:.6f} C45.000000 F60.0000",
        f"N930 G1 X30.000000 Y10.000000 Z30.000000 {tilt}{30.0 * sign:.6f} C90.000000 F10.0000",
        f"N940 G1 X30.000000 Y10.000000 Z30.000000 {tilt}{30.0 * sign:.6f} C200.000000 F5.0000",
        "G94",
    ]


def five_axis_program(machine) -> str:
    """The cone flank pass (12 blocks, G93) of the machine's inverse kinematics, then the hand-written moves."""
    tilt = [a for a in machine.rotary_axes if a != "C"][0]
    sign = -1.0 if np.degrees(machine.axes[tilt].travel[0]) < -90 else 1.0  # the tilt's long side: B -120..30, A -30..120
    text = cone_flank_program(machine, CONE, n_blocks=12)
    head, tail = text.split("M30\n")
    return head + "\n".join(hand_moves(tilt, sign)) + "\nM30\n" + tail


@pytest.fixture(scope="module", params=["nmv1500dcg", "smartcnc500"])
def case(request):
    m = load_machine(MACHINES / f"{request.param}.toml")
    src = five_axis_program(m)
    report = {}
    out = compensate(src, m, "geometric", tol_um=TOL_UM, singular_deg=SINGULAR_DEG, report=report)
    return m, src, out, report


# ------------------------------------------------------------------------------------------------ helpers -----


def _pose6(twin, q, actual=True):
    p, u = (twin.actual_pose(q) if actual else twin.nominal_pose(q))
    return p, u


def _walk(m, src, out):
    """Match the output's motion rows to the input's moves: for every output row, the input row (move) it belongs
    to and its fraction along that move (1 at the move's end). Fractions from the tip: the nominal tip path of the
    move sampled densely, then refined by Gauss-Newton (every move here moves the tip in the part frame)."""
    prog_in, prog_out = parse_program(src), parse_program(out)
    q_in, rows_in = machine_rows(prog_in, m)
    q_out, rows_out = machine_rows(prog_out, m)
    twin = ErrorTwin(m)
    q_start = np.vstack([machine_rows(prog_in, m)[0][:1] * 0, q_in[:-1]])
    q_start[0] = _start_of(prog_in, m)
    p_in, u_in = twin.nominal_pose(q_in)
    p_out, u_out = twin.actual_pose(q_out)
    # The input's end poses appear in order among the output's: walk both lists.
    owner = np.empty(len(q_out), int)
    j = 0
    for i in range(len(q_in)):
        while True:
            # the tip alone (inside the singular cone the tool axis keeps an error); 0.1 um
            d = np.linalg.norm(p_out[j] - p_in[i])
            owner[j] = i
            j += 1
            if d < 1e-4 or j == len(q_out):
                break
    assert j == len(q_out)
    frac = np.ones(len(q_out))
    ends = np.r_[np.nonzero(np.diff(owner))[0], len(owner) - 1]
    inner = np.setdiff1d(np.arange(len(owner)), ends)
    for k in inner:
        frac[k] = _fraction(twin, q_start[owner[k]], q_in[owner[k]], p_out[k], u_out[k])
    return dict(q_in=q_in, q_start=q_start, q_out=q_out, owner=owner, frac=frac, ends=ends, prog_in=prog_in,
                prog_out=prog_out, rows_in=rows_in, rows_out=rows_out, twin=twin)


def _start_of(prog, m):
    cols = ["XYZABC".index(a) for a in m.axis_names]
    q = (prog.start + prog.offset)[0][cols].copy()
    for c, a in enumerate(m.axis_names):
        if m.axes[a].is_rotary:
            q[c] = np.radians(q[c])
    return q


def _fraction(twin, qa, qb, p, u, n=4001):
    f = np.linspace(0.0, 1.0, n)
    pn, un = twin.nominal_pose(qa + f[:, None] * (qb - qa))
    target = p  # the tip alone: inside the singular cone the tool axis keeps an error
    cur = pn
    t = f[np.argmin(np.linalg.norm(cur - target, axis=1))]
    for _ in range(6):
        h = 1e-6
        q3 = qa + np.array([t - h, t, t + h])[:, None] * (qb - qa)
        v, _ = twin.nominal_pose(q3)
        d = (v[2] - v[0]) / (2 * h)
        t = float(np.clip(t - d @ (v[1] - target) / (d @ d), 0.0, 1.0))
    return t


def _singular(m, q):
    tilt = [c for c, a in enumerate(m.axis_names) if m.axes[a].is_rotary and a != "C"][0]
    return np.abs(np.sin(q[:, tilt])) < np.sin(np.radians(SINGULAR_DEG))


# ------------------------------------------------------------------------------------- machine-axis input -----


def test_every_output_point_lands_on_the_nominal_pose_of_the_input(case):
    m, src, out, report = case
    w = _walk(m, src, out)
    twin = w["twin"]
    q_nom = w["q_start"][w["owner"]] + w["frac"][:, None] * (w["q_in"] - w["q_start"])[w["owner"]]
    pn, un = twin.nominal_pose(q_nom)
    pa, ua = twin.actual_pose(w["q_out"])
    d_um = np.linalg.norm(pa - pn, axis=1) * 1e3
    d_urad = np.linalg.norm(ua - un, axis=1) * 1e6
    sing = _singular(m, q_nom)
    assert d_um.max() < POINT_UM, d_um.max()
    assert d_urad[~sing].max() < POINT_URAD, d_urad[~sing].max()
    # Block ends are the input's own end poses, one to one (the walk found every one of them in order).
    assert len(w["ends"]) == len(w["q_in"])
    # Without compensation the same points miss by far more: the check can fail.
    raw = twin.actual_pose(q_nom)
    assert (np.linalg.norm(raw[0] - pn, axis=1) * 1e3).max() > 200 * POINT_UM
    assert (np.linalg.norm(raw[1] - un, axis=1) * 1e6)[~sing].max() > 20 * POINT_URAD
    assert report["max_residual_um"] < POINT_UM and report["max_residual_urad"] < POINT_URAD


def test_the_actual_path_between_output_points_stays_within_tolerance(case):
    m, src, out, report = case
    w = _walk(m, src, out)
    twin = w["twin"]
    own, fr = w["owner"], w["frac"]
    # Pieces: consecutive output rows of the same cutting move (the first piece starts at the previous move's end).
    same = np.r_[False, own[1:] == own[:-1]]
    first = ~same
    cut = w["prog_in"].motion[w["rows_in"]][own] == FEED
    k = np.nonzero(cut)[0]
    k = k[k > 0]
    qa = w["q_out"][k - 1]
    qb = w["q_out"][k]
    fa = np.where(first[k], 0.0, fr[k - 1])
    fb = fr[k]
    mid_cmd = 0.5 * (qa + qb)
    mid_nom = w["q_start"][own[k]] + (0.5 * (fa + fb))[:, None] * (w["q_in"] - w["q_start"])[own[k]]
    pa, ua = twin.actual_pose(mid_cmd)
    pn, un = twin.nominal_pose(mid_nom)
    sing = _singular(m, w["q_out"][k]) | _singular(m, w["q_out"][k - 1])
    dev_um = np.linalg.norm(pa - pn, axis=1) * 1e3
    dev_urad = np.linalg.norm(ua - un, axis=1) * 1e6
    assert dev_um.max() <= TOL_UM * 1.001, dev_um.max()
    assert dev_urad[~sing].max() <= max(TOL_UM, 1.0) * 1.001, dev_urad[~sing].max()
    # The long moves were split, and their pieces are not all equal (the split follows the deviation).
    assert report["moves_split"] >= 2
    n_pieces = np.bincount(own)
    assert n_pieces.max() >= 4
    # Without splitting (one piece per move) the long moves would leave the path by far more than the tolerance.
    ends = w["ends"]
    qa1 = np.vstack([w["q_out"][:1], w["q_out"][ends[:-1]]])
    mid1 = twin.actual_pose(0.5 * (qa1 + w["q_out"][ends]))[0]
    nom1 = twin.nominal_pose(0.5 * (w["q_start"] + w["q_in"]))[0]
    assert (np.linalg.norm(mid1 - nom1, axis=1) * 1e3).max() > 5 * TOL_UM


def test_singular_blocks_hold_the_free_axis_and_are_listed(case):
    m, src, out, report = case
    lines = src.splitlines()
    g0 = next(i for i, ln in enumerate(lines) if ln.startswith("G0 X20.000000")) + 1
    want = {g0} | {i + 1 for i, ln in enumerate(lines) if ln.startswith(("N910", "N920", "N930"))}
    # N930 starts inside the cone (tilt 0.5 deg): its first pieces are solved there; N940 never comes near it.
    assert set(report["singular_blocks"]) == want
    assert report["singular_block_count"] == len(want) and report["singular_points"] >= len(want)
    # Inside the cone the free axis C is commanded where the program has it (held), the tip still lands.
    w = _walk(m, src, out)
    c = m.axis_names.index("C")
    q_nom = w["q_start"][w["owner"]] + w["frac"][:, None] * (w["q_in"] - w["q_start"])[w["owner"]]
    sing = _singular(m, q_nom)
    assert sing.sum() >= 3
    np.testing.assert_allclose(np.degrees(w["q_out"][sing, c]), np.degrees(q_nom[sing, c]), atol=2e-6)
    # ... and its tool-axis error is left (reported), since C is not used: the figure is the twin's, not zero.
    assert report["max_axis_error_singular_urad"] > 5.0


def test_inverse_time_feeds_of_split_blocks_keep_the_block_time(case):
    m, src, out, _ = case
    w = _walk(m, src, out)
    pin, pout = w["prog_in"], w["prog_out"]
    f_in = pin.feed[w["rows_in"]]
    f_out = pout.feed[w["rows_out"]]
    g93 = pin.inverse_time[w["rows_in"]] & (pin.motion[w["rows_in"]] == FEED)
    assert np.all(pout.inverse_time[w["rows_out"]] == g93[w["owner"]])
    inv = np.divide(1.0, f_out, out=np.zeros_like(f_out), where=f_out > 0)
    time_out = np.bincount(w["owner"], weights=np.where(g93[w["owner"]], inv, 0.0), minlength=len(f_in))
    # F is written with 4-6 decimals: 1/F exact to 1e-9 relative at these feeds.
    np.testing.assert_allclose(time_out[g93], 1.0 / f_in[g93], rtol=1e-6)
    # Each piece takes the share of its fraction of the move (fractions recovered from the written 6-decimal
    # positions of moves 5 mm / 45 deg and longer: good to 1e-6).
    split = np.nonzero(np.bincount(w["owner"]) > 1)[0]
    assert split.size
    unequal = 0
    for i in split:
        sel = np.nonzero(w["owner"] == i)[0]
        f = np.r_[0.0, w["frac"][sel]]
        np.testing.assert_allclose(f_in[i] / f_out[sel], np.diff(f), rtol=0, atol=1e-6)
        unequal += np.ptp(np.diff(f)) > 1e-3
    assert unequal >= 1  # the adaptive split makes unequal pieces: "n pieces, n x F each" would be wrong there


@pytest.mark.external
def test_rs274_reads_the_five_axis_output(tmp_path, case):
    m, src, out, _ = case
    assert_rs274_reads_as_we_do(out, tmp_path)


def test_identical_input_gives_identical_output(case):
    m, src, out, _ = case
    assert compensate(src, m, "geometric", tol_um=TOL_UM, singular_deg=SINGULAR_DEG) == out


# ----------------------------------------------------------------------------------------------- CL input -----


@pytest.fixture(scope="module")
def nmv():
    return load_machine(MACHINES / "nmv1500dcg.toml")


def test_csv_and_apt_read_the_same_poses():
    a, b = read_cl(CL_CSV), read_cl(CL_APT)
    assert (a.format, b.format) == ("csv", "apt") and len(a) == len(b) == 37
    np.testing.assert_array_equal(a.tip, b.tip)
    np.testing.assert_array_equal(a.axis, b.axis)
    np.testing.assert_array_equal(a.rapid, b.rapid)
    assert a.rapid[0] and not a.rapid[1:].any()
    np.testing.assert_array_equal(a.feed[1:], 1000.0)


def test_cl_without_linearisation_is_the_machine_axis_program(nmv):
    """The CL fixture holds cone_flank_poses(CONE, 5, 36): its machine axes are cone_flank_program's (the same inverse
    kinematics, branch -1 which 'nearest' picks on this table, C unwound), its G93 feeds the same."""
    ours = parse_program(cl_to_program(read_cl(CL_CSV), nmv, linearise=False))
    ref = parse_program(cone_flank_program(nmv, CONE, n_blocks=36))
    assert len(ours) == len(ref)
    # fixture rounding (6 decimals of mm, 9 of the unit vector) and output rounding (6 decimals): 2e-6
    np.testing.assert_allclose(ours.end, ref.end, atol=2e-6)
    np.testing.assert_array_equal(ours.inverse_time, ref.inverse_time)
    np.testing.assert_allclose(ours.feed, ref.feed, rtol=2e-6, atol=1e-4)
    # ... so the post gives the same compensated program (to its last written digit, 1e-6).
    a = parse_program(compensate(cl_to_program(read_cl(CL_CSV), nmv, linearise=False), nmv, "geometric"))
    b = parse_program(compensate(cone_flank_program(nmv, CONE, n_blocks=36), nmv, "geometric"))
    assert len(a) == len(b)
    np.testing.assert_allclose(a.end, b.end, atol=4e-6)


@pytest.mark.parametrize("name", ["nmv1500dcg", "smartcnc500"])
def test_posted_cl_lands_on_the_cl_poses_and_stays_on_the_cl_path(name):
    m = load_machine(MACHINES / f"{name}.toml")
    cl = read_cl(CL_APT)
    report = {}
    # The APT file loads tool 1 (G43 H1); its length is the reference tool's, so zero offset is meant here.
    out = compensate(CL_APT, m, "geometric", tol_um=TOL_UM, report=report, offsets_zero=True)
    assert report["input_format"] == "cl-apt" and report["cl_points"] == len(cl)
    q, _ = machine_rows(parse_program(out), m)
    # The last move is the APT END's retract of Z, not a CL pose: the rest must be on the CL path.
    assert abs(q[-1, 2] - (m.axes["Z"].travel[1] - 1.0)) < 0.05 and np.allclose(q[-1, [0, 1, 3, 4]], q[-2, [0, 1, 3, 4]],
                                                                                 atol=0.05)
    q = q[:-1]
    twin = ErrorTwin(m)
    pa, ua = twin.actual_pose(q)
    # Every CL pose is reached (nearest output pose within 0.1 um and 1 urad).
    d = np.linalg.norm(pa[None, :, :] - cl.tip[:, None, :], axis=2)
    j = d.argmin(axis=1)
    assert (d[np.arange(len(cl)), j] * 1e3).max() < POINT_UM
    assert (np.linalg.norm(ua[j] - cl.axis, axis=1) * 1e6).max() < POINT_URAD
    assert np.all(np.diff(j) > 0)
    # Every output point lies on the CL segments, tool axis on the interpolated CL axis (slerp).
    seg, t, dist = _on_polyline(pa, cl.tip)
    assert (dist * 1e3).max() < POINT_UM
    axis_ref = _slerp(cl.axis[seg], cl.axis[seg + 1], t)
    assert (np.linalg.norm(ua - axis_ref, axis=1) * 1e6).max() < POINT_URAD
    # Between output points the actual tip stays within the tolerance of the CL segments (half for the joint-linear
    # path of the machine-axis program, half for the compensation).
    mid = twin.actual_pose(0.5 * (q[1:] + q[:-1]))[0]
    _, _, dmid = _on_polyline(mid, cl.tip)
    assert (dmid * 1e3).max() <= TOL_UM, (dmid * 1e3).max()
    # Without linearisation the joint-linear path would leave the CL segments by far more.
    q0, _ = machine_rows(parse_program(cl_to_program(cl, m, linearise=False)), m)
    _, _, d0 = _on_polyline(forward_nominal(m, 0.5 * (q0[1:] + q0[:-1]))[0], cl.tip)
    assert (d0 * 1e3).max() > 50 * TOL_UM


def _on_polyline(p, poly):
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(np.einsum("nkj,kj->nk", p[:, None, :] - a[None], ab) / np.einsum("kj,kj->k", ab, ab), 0, 1)
    d = np.linalg.norm(p[:, None, :] - (a[None] + t[..., None] * ab[None]), axis=2)
    seg = d.argmin(axis=1)
    return seg, t[np.arange(len(p)), seg], d[np.arange(len(p)), seg]


def _slerp(a, b, t):
    w = np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1, 1))
    s = np.sin(w)
    v = (np.sin((1 - t) * w) / s)[:, None] * a + (np.sin(t * w) / s)[:, None] * b
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_csv_and_apt_post_to_the_same_moves_and_apt_keeps_its_setup(nmv):
    a = without_header(compensate(CL_CSV, nmv, "geometric")).splitlines()
    with pytest.raises(PostError, match=r"cone_cl.apt:\d+: the length of tool 1 \(G43 H1\) was not given"):
        compensate(CL_APT, nmv, "geometric")  # LOADTL/1 selects a tool length the post was not given
    b = without_header(compensate(CL_APT, nmv, "geometric", offsets_zero=True)).splitlines()
    # The APT file's setup, where it stands: PARTNO, CUTTER, LOADTL, SPINDL before the first move; END after the last.
    head = ["(PARTNO CONE FLANK)", "(trueaxis: d=10)", "T1 M6", "G43 H1", "S5000 M3"]
    assert b[3:8] == head
    end = b.index("M5")
    assert b[end - 1].startswith("G0 ") and b[end + 1] == "M9" and b[end + 2:] == ["G94", "M30", "%"]
    z = float(next(w for w in b[end - 1].split() if w.startswith("Z"))[1:])
    assert z == pytest.approx(100.0 - 1.0, abs=0.01)  # Z travel's top less the margin, then compensated
    # Every other line the same as the CSV's (line 2 is the comment naming the source)
    assert a[:1] + a[2:-3] == b[:1] + b[2:3] + b[8:end - 2]


@pytest.mark.parametrize("statement, words", [
    ("SPINDL/RPM,1200,CCLW", ["S1200 M4"]), ("SPINDL/OFF", ["M5"]), ("COOLNT/MIST", ["M7"]), ("COOLNT/OFF", ["M9"]),
    ("LOADTL/3,ADJUST,13", ["T3 M6", "G43 H13"]), ("PPRINT/ROUGH (SIDE)", ["(PPRINT ROUGH [SIDE])"])])
def test_apt_setup_statements_become_the_controls_words_before_the_next_move(nmv, statement, words):
    text = CL_APT.read_text().replace("RAPID\n", f"RAPID\n{statement}\n", 1)
    out = cl_to_program(read_cl(text), nmv).splitlines()
    first_move = next(i for i, s in enumerate(out) if s.startswith("G94 G0"))
    assert out[first_move - len(words):first_move] == words


@pytest.mark.parametrize("statement, message", [
    ("TURRET/2", "APT statement TURRET is not read"), ("SPINDL/200,SFM", "surface speed"),
    ("COOLNT/THRU", "ON, FLOOD, MIST or OFF"), ("LOADTL/1.5", "whole numbers"), ("CUTTER/0", "tool diameter")])
def test_apt_statements_not_read_are_refused_with_their_line(statement, message):
    text = CL_APT.read_text().replace("RAPID\n", f"RAPID\n{statement}\n", 1)
    line = text.splitlines().index(statement) + 1
    with pytest.raises(ClError, match=rf":{line}: .*{message}"):
        read_cl(text, "cl.apt")


def test_apt_end_needs_a_z_travel_for_its_retract(bc_machine):
    import dataclasses

    z = dataclasses.replace(bc_machine.axes["Z"], travel=None)
    m = dataclasses.replace(bc_machine, axes={**bc_machine.axes, "Z": z})
    with pytest.raises(ClError, match="END retracts Z"):
        cl_to_program(read_cl(CL_APT), m)


def test_the_cl_path_keeps_its_branch_and_winds_the_shortest_way(nmv):
    q, _ = machine_rows(parse_program(cl_to_program(read_cl(CL_CSV), nmv)), nmv)
    b, c = q[:, 3], q[:, 4]
    assert np.all(b < 0)  # one branch all along (the one far inside B -120..30)
    assert np.abs(np.diff(c)).max() < np.radians(20)  # no 360 deg jumps
    # The 365 deg pass is wound, not wrapped: C ends where cone_flank_program's unwrapped C ends.
    ref = parse_program(cone_flank_program(nmv, CONE, n_blocks=36))
    assert np.degrees(c[-1]) == pytest.approx(ref.end[-1, 5], abs=2e-6) and np.degrees(c[-1] - c[0]) < -360


def test_a_singular_cl_pose_holds_the_outer_axis(nmv):
    # Tilted 2 deg towards +Y, up to the pole (tool axis along C), and back to the same side.
    text = ("x,y,z,i,j,k,f\n10,0,5,0,0.0348995,0.9993908,1000\n10,2,5,0,0,1,\n10,4,5,0,0.0348995,0.9993908,\n")
    report = {}
    out = compensate(text, nmv, "geometric", report=report, source="sing.csv")
    q, _ = machine_rows(parse_program(cl_to_program(text, nmv, linearise=False)), nmv)
    assert q[1, 4] == q[0, 4] == q[2, 4]  # tool axis along C: C stays where it was
    # The blocks inside the 1 deg cone (around the pole) are listed, by their CL lines.
    assert report["singular_blocks"] and set(report["singular_blocks"]) <= {3, 4}
    assert report["max_residual_um"] < POINT_UM and "G93" in out


def test_a_cl_path_through_the_pole_is_refused_quickly_with_its_line(nmv):
    # In along +X, out along +Y: C has to turn 90 deg at the pole, the tip swings with it.
    text = ("x,y,z,i,j,k,f\n10,0,5,0.0348995,0,0.9993908,1000\n10,2,5,0,0,1,\n10,4,5,0,0.0348995,0.9993908,\n")
    with pytest.raises(PostError) as info:
        compensate(text, nmv, "geometric", source="pole.csv")
    assert str(info.value).startswith("pole.csv:4:") and "singular" in str(info.value)


GOOD_CSV = "x,y,z,i,j,k,f\n10,0,5,0,0,1,1000\n12,0,5,0,0.05,1,\n"


@pytest.mark.parametrize("text, line, words", [
    ("x,y,z,i,j\n1,2,3,0,0\n", 1, "lacks column(s) k"),
    (GOOD_CSV + "14,0,abc,0,0,1,\n", 4, "not a number"),
    (GOOD_CSV + "14,0,5,0,0,0,\n", 4, "zero"),
    (GOOD_CSV + "14,0,5,0,0,1\n", 4, "expected 7 values"),
    (GOOD_CSV + "14,0,5,0,0,1,-5\n", 4, "positive"),
    ("x,y,z,i,j,k\n10,0,5,0,0,1\n12,0,5,0,0,1\n", 3, "no feed"),
    ("x,y,z,i,j,k,f\n10,0,5,0,0,1,1000\n12,0,5,0.4,0,-0.9,\n", 3, "outside its travel"),
    ("RAPID\nGOTO/10,0,5,0,0,1\nFEDRAT/500\nGOTO/12,0,5,0,0\n", 4, "3 or 6 numbers"),
    ("GOTO/10,0,5,0,0,1\nFEDRAT/0.1,MMPR\nGOTO/12,0,5\n", 2, "per revolution"),
    ("GOTO/10,0,5,0,0,1\nFEDRAT/500\nCIRCLE/0,0,5,0,0,1,10\n", 3, "CIRCLE"),
    ("GOTO/10,0,5,0,0,1\nFEDRAT/500\nGOTO/12,x,5\n", 3, "numbers"),
])
def test_bad_cl_input_is_refused_with_file_and_line(nmv, text, line, words):
    with pytest.raises(PostError) as info:
        compensate(text, nmv, "geometric", source="bad.cl")
    assert str(info.value).startswith(f"bad.cl:{line}: ") and words in str(info.value), str(info.value)


def test_read_cl_refuses_what_is_not_cl():
    with pytest.raises(ClError) as info:
        read_cl("G1 X1 Y2\n", source="p.ngc")
    assert str(info.value).startswith("p.ngc:1:")


def test_cli_posts_cl_data_and_refuses_bad_cl_with_exit_3(tmp_path):
    out, rep = tmp_path / "out.ngc", tmp_path / "r.json"
    nmv_file = str(MACHINES / "nmv1500dcg.toml")
    r = subprocess.run([sys.executable, "-m", "trueaxis.cli", "post", str(CL_CSV), "-o", str(out), "--machine",
                        nmv_file, "--report", str(rep)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    report = json.loads(rep.read_text())
    assert report["input_format"] == "cl-csv" and report["cl_points"] == 37
    assert report["max_residual_um"] < POINT_UM and "G93" in out.read_text()
    # the summary: the input's lines and points, the machine-axis blocks made of them, the blocks written
    n_lines = len(CL_CSV.read_text().splitlines())
    assert (f"{out}: CL data in (csv: {n_lines} lines, 37 points) -> {report['cl_program_blocks']} machine-axis blocks "
            f"-> {report['blocks_out']} out ({report['header_blocks']} header comments); ") in r.stdout
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,z,i,j,k,f\n10,0,5,0,0,1,1000\n12,0,5,0,0,nan,\n")
    out2 = tmp_path / "out2.ngc"
    r = subprocess.run([sys.executable, "-m", "trueaxis.cli", "post", str(bad), "-o", str(out2), "--machine",
                        nmv_file], capture_output=True, text=True)
    assert r.returncode == 3 and f"{bad}:3:" in r.stderr and "Traceback" not in r.stderr
    assert not out2.exists()


def test_comprehensive_force_frame_follows_a_tilted_head():
    """On a head machine the feed frame's z is the tilted tool axis: the output end point, put through the twin with
    the force built here from the head angle (tool axis (sin B, 0, cos B) for +B about Y, ISO 841), lands on the
    nominal pose; with the force frame of machine Z it would not."""
    from trueaxis.machine.cutting_force import CuttingCoefficients, CuttingConditions, mean_force

    m = load_machine(MACHINES / "headtable.toml")
    b = 30.0
    prog = (f"G21 G90 G94\n(trueaxis: ap=2 ae=3 fz=0.1 n=3000 d=10 z=4 mode=down)\n"
            f"G0 X0 Y0 Z-240 B{b} C0\nG1 X40 Y0 Z-240 B{b} C0 F600\nM2\n")
    report = {}
    out = compensate(prog, m, "comprehensive", report=report)
    assert out != compensate(prog, m, "geometric")
    line = [ln for ln in out.splitlines() if ln.startswith("G1")][-1]
    w = {t[0]: float(t[1:]) for t in line.split() if t[0] in "XYZBC"}
    q_cmd = np.array([[w["X"], w["Y"], w["Z"], np.radians(w["B"]), np.radians(w["C"])]])
    f_feed = mean_force(CuttingCoefficients.from_mapping(m.cutting),
                        CuttingConditions.from_mapping({"ap": 2, "ae": 3, "fz": 0.1, "n": 3000, "d": 10, "z": 4}))
    z = np.array([np.sin(np.radians(b)), 0.0, np.cos(np.radians(b))])
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    force = f_feed[0] * x + f_feed[1] * np.cross(z, x) + f_feed[2] * z
    twin = ErrorTwin(m)
    p_nom, u_nom = twin.nominal_pose(np.array([[40.0, 0.0, -240.0, np.radians(b), 0.0]]))
    p_act, u_act = twin.actual_pose(q_cmd, force_n=force)
    # 5-decimal output: 0.005 um per word; the solver's 0.01 um.
    assert np.linalg.norm(p_act - p_nom) * 1e3 < 0.1
    assert np.linalg.norm(u_act - u_nom) * 1e6 < 1.0
    flat = f_feed[0] * np.array([1.0, 0, 0]) + f_feed[1] * np.array([0, 1.0, 0]) + f_feed[2] * np.array([0, 0, 1.0])
    p_flat, _ = twin.actual_pose(q_cmd, force_n=flat)
    assert np.linalg.norm(p_flat - p_nom) * 1e3 > 0.1  # the frame matters at this size


def test_a_rotary_correction_above_the_bound_near_the_pole_names_the_singular_cone(tmp_path):
    # "correction of C is -0.3288 deg, above the bound of 0.5 mm: check the machine file" mixed units and blamed the
    # machine file; the cause was a tilt of 1 deg just outside --singular-deg 1 (a QA pass). Now both are said, and a
    # larger singular cone posts the program.
    from trueaxis.postproc.post import PostError, compensate

    m = load_machine(MACHINES / "nmv1500dcg.toml")
    text = ("G21 G90 G17 G94\nG0 X30 Y0 Z50 B0.5 C0\nG1 Z20 F500\nG1 X30 Y10 Z20 B0.5 C30\nG1 X20 Y10 Z20 B0.3 C60\n"
            "G1 X20 Y0 Z20 B0 C90\nG1 X20 Y0 Z20 B-2 C90\nG0 Z80\nM2\n")
    with pytest.raises(PostError) as info:
        compensate(text, m, "geometric", offsets_zero=True)
    said = str(info.value)
    assert re.search(r"correction of C is [-+][\d.]+ deg \(([\d.]+) mm at the 100 mm lever arm", said), said
    assert "near the singular cone (--singular-deg 1)" in said and "check the machine file" not in said
    compensate(text, m, "geometric", offsets_zero=True, singular_deg=3.0)  # held in the cone: posted


def test_a_goto_after_gohome_is_refused_and_the_cl_warnings_name_the_cl_files_lines(nmv):
    # A QA pass: GOHOME then GOTO posted the move from home as a G93 cut timed from the CL chord before GOHOME (10 mm
    # at 800 mm/min), where the tool moved 60 mm from home: 4835 mm/min, exit 0. Refused now (RAPID or FROM first);
    # with RAPID it posts, and the G28's warning names the CL file's GOHOME line (it named the machine-axis
    # program's line 8 of a 7-line file).
    from trueaxis.postproc.post import PostError

    text = "FEDRAT/800\nGOTO/0,0,5,0,0.1,1\nGOTO/10,0,5\nGOHOME\nGOTO/20,0,5\n"
    with pytest.raises(ClError, match=r"^home.apt:5: GOTO after GOHOME \(line 4\): the move from the home position "):
        read_cl(text, "home.apt")
    with pytest.raises(PostError, match=r"^home.apt:5: GOTO after GOHOME"):
        compensate(text, nmv, source="home.apt", offsets_zero=True)
    report = {}
    rapid = text.replace("GOHOME\n", "GOHOME\nRAPID\n")
    out = compensate(rapid, nmv, source="home.apt", offsets_zero=True, report=report)
    after = out.splitlines()[out.splitlines().index("G28") + 1]
    assert after.startswith("G0 ")  # the move from home a rapid, as the CL data say
    said = [w for w in report["warnings"] if "G28" in w]
    assert len(said) == 1 and said[0].startswith("home.apt:4: ") and "of the machine-axis program made from it" in \
        said[0], report["warnings"]


def test_a_correction_blown_up_at_the_pole_names_the_singular_cone_not_the_machine_file(nmv):
    # A QA pass: --singular-deg 0 with a move through B = 0: "correction of X is -5.2 mm ...: check the machine file".
    # The linear axis follows the rotary one that turns fast at the pole: the singular cone is named, as for a rotary.
    program = "G21 G90 G17 G94\nG0 X-50 Y65 Z95 B0 C0\nG1 Y55 F800\nG1 X50\nM30\n"
    with pytest.raises(PostError, match=r"^s0.ngc:2: correction of X is .* mm, above the bound of 0.5 mm; the tilt "
                                        r"there is 0 deg, near the singular cone \(--singular-deg 0\)"):
        compensate(program, nmv, source="s0.ngc", offsets_zero=True, singular_deg=0.0)
    assert compensate(program, nmv, offsets_zero=True) != program  # the default cone holds C there


def test_a_layout_the_inverse_kinematics_does_not_cover_is_said_by_machine_check_and_refused_by_program(tmp_path):
    # A QA pass: C on the bed and B on C (the rotary axes swapped): `machine check` said ok, and `trueaxis program`
    # died with a NotImplementedError traceback, exit 1. Now a warning in machine check and one line, exit 3.
    text = (MACHINES / "nmv1500dcg.toml").read_text()
    assert 'bed_to_workpiece = ["B", "C"]' in text
    (tmp_path / "cb.toml").write_text(text.replace('bed_to_workpiece = ["B", "C"]', 'bed_to_workpiece = ["C", "B"]'))
    cli = [sys.executable, "-m", "trueaxis.cli"]
    r = subprocess.run([*cli, "machine", "check", str(tmp_path / "cb.toml")], capture_output=True, text=True)
    assert r.returncode == 0 and "inverse kinematics is implemented for an outer rotary axis about Z" in r.stderr
    assert "CL data, the test parts' programs and TCP output cannot be made for it" in r.stderr
    r = subprocess.run([*cli, "program", "nas979", "--machine", str(tmp_path / "cb.toml"), "-o",
                        str(tmp_path / "cb.ngc")], capture_output=True, text=True)
    assert r.returncode == 3 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert r.stderr.startswith("trueaxis program: inverse kinematics is implemented for") and \
        not (tmp_path / "cb.ngc").exists()
    r = subprocess.run([*cli, "machine", "check", "nmv1500dcg"], capture_output=True, text=True)
    assert r.returncode == 0 and "warning" not in r.stderr


def test_a_repeated_cl_point_is_no_move_and_posts_as_without_it(nmv):
    # A QA pass: a CL point repeated (common in CAM output) made a zero-length G93 move, F8e11, refused as "number out
    # of range". It is dropped: the same program as without it, its feed modal for the points after it, an APT setup
    # statement between the two still before the next move.
    plain = "x,y,z,i,j,k,f\n0,0,5,0,0.1,1,\n10,0,5,0,0.1,1,800\n20,0,5,0,0.1,1,\n"
    repeated = "x,y,z,i,j,k,f\n0,0,5,0,0.1,1,\n10,0,5,0,0.1,1,800\n10,0,5,0,0.1,1,\n20,0,5,0,0.1,1,\n"
    assert cl_to_program(read_cl(repeated), nmv) == cl_to_program(read_cl(plain), nmv)
    apt = "FEDRAT/800\nGOTO/0,0,5,0,0.1,1\nGOTO/10,0,5\nSPINDL/1000\nGOTO/10,0,5\nGOTO/20,0,5\n"
    cl = read_cl(apt)
    assert len(cl) == 3 and [b.before for b in cl.setup] == [2] and list(cl.line) == [2, 3, 6]
    out = cl_to_program(cl, nmv).splitlines()
    assert out[out.index("S1000 M3") + 1].startswith("G1 ") and sum(s.startswith("G1 ") for s in out) == 2


def test_cl_csv_columns_named_with_their_unit_are_read_in_mm_or_refused_naming_the_unit(nmv):
    # A QA pass: a header "x_mm,y_mm,z_mm,..." (or "X [mm]") was taken for G-code ("word 'x' with no number"). The
    # columns' mm (and the feed's mm/min) are read; another unit is refused naming the column.
    plain = cl_to_program(read_cl("x,y,z,i,j,k,f\n0,0,5,0,0.1,1,\n10,0,5,0,0.1,1,800\n"), nmv)
    for head in ("x_mm,y_mm,z_mm,i,j,k,f", "X [mm],Y [mm],Z [mm],I,J,K,F [mm/min]", "x(mm);y(mm);z(mm);i;j;k;feed_mmpm"):
        sep = ";" if ";" in head else ","
        text = head + "\n" + "\n".join(r.replace(",", sep) for r in ("0,0,5,0,0.1,1,", "10,0,5,0,0.1,1,800")) + "\n"
        assert cl_to_program(read_cl(text), nmv) == plain, head
    with pytest.raises(ClError, match=r"^u.csv:1: CSV header gives column x in 'in': CL data in CSV are read in mm"):
        read_cl("x_in,y_in,z_in,i,j,k,f\n0,0,5,0,0.1,1,\n", "u.csv")


def test_a_cl_path_that_starts_vertical_and_tilts_in_posts_without_a_turn_in_the_cut(nmv):
    # A QA pass: a CL path vertical, then tilted toward +X inside the cut, was refused ("the machine axes jump on this
    # CL segment"): the vertical poses held C at its start (0) and the tilt needed C = -180. The path reversed posted.
    # The vertical poses a pass starts with take the angle of its first tilted pose: no turn of C inside the cut.
    from trueaxis.nc.cl import cl_axes

    text = ("x,y,z,i,j,k,f\n0,0,5,0,0,1,\n10,0,5,0,0,1,800\n20,0,5,0,0,1,\n"
            "30,0,5,0.173648178,0,0.984807753,\n")
    out = compensate(text, nmv, offsets_zero=True)
    q, _ = cl_axes(read_cl(text), nmv)
    c = np.degrees(q[:, nmv.axis_names.index("C")])
    assert np.ptp(c) < 1e-9 and abs(abs(c[0]) - 180.0) < 1e-6  # C held at the tilt's angle from the start
    q_out, _ = machine_rows(parse_program(out), nmv)
    assert np.degrees(np.ptp(q_out[:, nmv.axis_names.index("C")])) < 0.5
    reverse = ("x,y,z,i,j,k,f\n30,0,5,0.173648178,0,0.984807753,\n20,0,5,0,0,1,800\n10,0,5,0,0,1,\n")
    assert compensate(reverse, nmv, offsets_zero=True)  # (as before)


def test_a_cl_path_tilted_then_vertical_then_tilted_the_other_way_turns_c_while_vertical(nmv):
    # Beyond the QA's case: tilted toward -X, two vertical points, tilted toward +X. The vertical poses held C at the
    # angle before and the 180 deg turn came in the last segment, into the tilt: refused as a jump. Now C turns on the
    # segment between the two vertical poses (the tool along C there: any angle serves) and the program's nominal tip,
    # sampled along every block as the control interpolates it, stays on the CL polyline.
    from post_checks import distance_to_polyline
    from trueaxis.nc.cl import cl_axes

    text = ("x,y,z,i,j,k,f\n0,0,5,-0.173648178,0,0.984807753,\n10,0,5,0,0,1,800\n20,0,5,0,0,1,\n"
            "30,0,5,0.173648178,0,0.984807753,\n")
    cl = read_cl(text)
    q, _ = cl_axes(cl, nmv)
    c = np.degrees(q[:, nmv.axis_names.index("C")])
    assert c[1] == pytest.approx(c[0], abs=1e-9) and c[3] == pytest.approx(c[2], abs=1e-9)
    assert abs(abs(c[2] - c[1]) - 180.0) < 1e-6  # the whole turn between the vertical poses
    q_out, _ = machine_rows(parse_program(cl_to_program(cl, nmv)), nmv)
    f = np.linspace(0.0, 1.0, 9)[1:, None, None]
    samples = (q_out[:-1] + f * (q_out[1:] - q_out[:-1])).reshape(-1, q_out.shape[1])
    tip, _ = forward_nominal(nmv, samples)
    assert distance_to_polyline(tip, cl.tip).max() * 1e3 < 1.0  # um: within the CL path's tolerance
    assert compensate(text, nmv, offsets_zero=True)
