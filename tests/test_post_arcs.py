"""Arcs kept as G2/G3 blocks fitted to the corrected path (trueaxis.postproc.arcs), checked against LinuxCNC's rs274.

The output is read by rs274 (no error, its arcs are the ones we wrote); its arcs, sampled densely as LinuxCNC's motion
interpolates them (centre, radius from the start changing linearly to the radius at the end, helical axis linear in the
angle), are put through the twin; the actual tool tip must lie on the nominal path (rs274's reading of the input,
sampled the same way) within the tolerance. ``arcs=False`` writes what the post wrote before the fit existed."""

from __future__ import annotations

import re

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from rs274_helpers import run_rs274
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.nc.gcode import parse_program
from trueaxis.postproc.post import post_text
from trueaxis.nc.setup import Setup

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "post_arcs"
TOL_UM = 1.0


@pytest.fixture(scope="module")
def xh714():
    return load_machine(ROOT / "fixtures" / "machines" / "xh714.toml")


def _post(name, machine, arcs, tol_um=TOL_UM):
    text = (DATA / f"{name}.ngc").read_text()
    return post_text(text, machine, "geometric", tol_um=tol_um, setup=Setup(offsets_zero=True), header=False,
                     arcs=arcs)


def _path_points(moves, start, step):
    """(n, 3) points along rs274's moves (program units) from ``start``, at most ``step`` apart, each move's own
    points in a list (arcs as LinuxCNC's motion interpolates them: pmCirclePoint)."""
    out = []
    p0 = np.asarray(start, float)
    for kind, end, centre, turn in zip(moves.kind, moves.end, moves.center, moves.rotation):
        e = end[:3]
        if kind == "arc":
            # in-plane axes: those with a centre coordinate; normal: the other one
            inplane = [i for i in range(3) if not np.isnan(centre[i])]
            (a, b), n = (inplane if inplane != [0, 2] else [2, 0]), 3 - sum(inplane)
            c = centre
            th0 = np.arctan2(p0[b] - c[b], p0[a] - c[a])
            th1 = np.arctan2(e[b] - c[b], e[a] - c[a])
            r0, r1 = np.hypot(p0[a] - c[a], p0[b] - c[b]), np.hypot(e[a] - c[a], e[b] - c[b])
            if turn > 0:
                sweep = (th1 - th0) % (2 * np.pi)
                sweep = 2 * np.pi if sweep == 0 else sweep
                sweep += 2 * np.pi * (turn - 1)
            else:
                sweep = (th0 - th1) % (2 * np.pi)
                sweep = 2 * np.pi if sweep == 0 else sweep
                sweep = -(sweep + 2 * np.pi * (-turn - 1))
            length = abs(sweep) * max(r0, r1) + abs(e[n] - p0[n])
            u = np.linspace(0.0, 1.0, int(np.ceil(length / step)) + 2)
            pts = np.empty((u.size, 3))
            rad = r0 + (r1 - r0) * u
            pts[:, a] = c[a] + rad * np.cos(th0 + sweep * u)
            pts[:, b] = c[b] + rad * np.sin(th0 + sweep * u)
            pts[:, n] = p0[n] + u * (e[n] - p0[n])
        else:
            u = np.linspace(0.0, 1.0, int(np.ceil(np.linalg.norm(e - p0) / step)) + 2)
            pts = p0 + u[:, None] * (e - p0)
        out.append((kind, pts))
        p0 = e
    return out


def _distance_to_polyline(points, polyline):
    """(K,) distance of points (K, 3) to the polyline (n, 3) (its two segments at the nearest vertex)."""
    tree = cKDTree(polyline)
    _, i = tree.query(points)
    best = np.full(len(points), np.inf)
    for j0 in (i - 1, i):
        j0 = np.clip(j0, 0, len(polyline) - 2)
        a, b = polyline[j0], polyline[j0 + 1]
        ab = b - a
        t = np.clip(np.einsum("ki,ki->k", points - a, ab) / np.maximum(np.einsum("ki,ki->k", ab, ab), 1e-300), 0, 1)
        best = np.minimum(best, np.linalg.norm(points - (a + t[:, None] * ab), axis=1))
    return best


def _actual_in_program_units(machine, pts, inch):
    """Actual tool tip (through the twin) of commanded program points (K, 3) of a three-axis mill with zero offsets,
    mapped back to program units through the nominal kinematics (an affine map, inverted here)."""
    twin = ErrorTwin(machine)
    scale = 25.4 if inch else 1.0
    q = pts * scale
    actual, _ = twin.actual_pose(q)
    o, _ = twin.nominal_pose(np.zeros((1, 3)))
    A = np.stack([twin.nominal_pose(np.eye(3)[[j]])[0][0] - o[0] for j in range(3)], axis=1)
    return np.linalg.solve(A, (actual - o).T).T / scale


def _rs274(text, tmp_path, name):
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / f"{name}.ngc"
    path.write_text(text)
    moves = run_rs274(path, {}, tmp_path / name)
    assert moves.returncode == 0, moves.stderr[-2000:]
    return moves


def _check_against_rs274(machine, name, tmp_path, inch, arcs=True, out=None, kinds=("arc",)):
    """(output, report, deviation (K,) um of the output's arcs from the nominal path, rs274's moves)."""
    src = (DATA / f"{name}.ngc").read_text()
    rep = None
    if out is None:
        out, rep = _post(name, machine, arcs=arcs)
    nominal = _rs274(src, tmp_path, "in")
    written = _rs274(out, tmp_path, "out")
    # rs274 prints 4 decimals: in inch that is 2.5 um. Its reading of the arcs (centres, ends, turns) is checked
    # against the exact written numbers within its print; the exact numbers then go through the twin.
    ours = parse_program(out)
    assert len(written.kind) == len(ours)
    np.testing.assert_allclose(written.end, ours.end, atol=5e-5)
    is_arc = np.array([k == "arc" for k in written.kind])
    for j in range(3):
        have = ~np.isnan(written.center[:, j]) & is_arc
        np.testing.assert_allclose(written.center[have, j], ours.arc_center[have, j], atol=5e-5)
    exact = written
    exact.end[:, :3] = ours.end[:, :3]
    exact.center = np.where(np.isnan(written.center), np.nan, ours.arc_center)
    step = 0.02 / (25.4 if inch else 1.0)
    nominal_path = np.vstack([pts for _, pts in _path_points(nominal, np.zeros(3), step)])
    start = ours.start[0, :3]
    sampled = _path_points(exact, start, 0.5 * step * 10)
    arc_pts = np.vstack([pts for kind, pts in sampled if kind in kinds])
    tip = _actual_in_program_units(machine, arc_pts, inch)
    dev_um = _distance_to_polyline(tip, nominal_path) * (25.4 if inch else 1.0) * 1e3
    return out, rep, dev_um, written


@pytest.mark.parametrize("name, inch", [("inch_half_circle", True), ("arcs_planes_low", False),
                                        ("arcs_incremental", False)])  # (G91: its arcs were all straight pieces)
def test_fitted_arcs_read_by_rs274_lie_on_the_nominal_arcs_through_the_twin(xh714, tmp_path, name, inch):
    out, rep, dev_um, written = _check_against_rs274(xh714, name, tmp_path, inch)
    assert rep.arcs_fitted >= 1
    # the tolerance, plus the nominal polyline's own chord error (0.02 mm chords: < 0.03 um here)
    assert dev_um.max() <= TOL_UM + 0.03, dev_um.max()
    assert rep.max_arc_deviation_um <= TOL_UM
    # rs274 read G2/G3 blocks, more than the input's arcs (fitted arcs are cut into sub-arcs), and no straight pieces
    # in place of the fitted ones
    assert sum(k == "arc" for k in written.kind) >= rep.arcs_kept + rep.arc_blocks_fitted
    # and the check is not trivially true: the input's own arcs leave the nominal path by far more
    _, _, dev_raw, _ = _check_against_rs274(xh714, name, tmp_path / "raw", inch,
                                            out=(DATA / f"{name}.ngc").read_text())
    assert dev_raw.max() > 5 * TOL_UM


def test_the_inch_half_circle_stays_a_handful_of_blocks(xh714):
    off, rep_off = _post("inch_half_circle", xh714, arcs=False)
    on, rep_on = _post("inch_half_circle", xh714, arcs=True)
    n_src = len((DATA / "inch_half_circle.ngc").read_text().splitlines())
    assert len(off.splitlines()) - n_src > 100  # linearised within 1 um: hundreds of lines
    assert len(on.splitlines()) - n_src <= 6  # a few sub-arcs
    assert rep_on.arcs_fitted == 1 and rep_on.arcs_linearised == 0


def test_arcs_in_every_plane_helix_and_full_circle_shrink(xh714):
    off, _ = _post("arcs_planes_low", xh714, arcs=False)
    on, rep = _post("arcs_planes_low", xh714, arcs=True)
    assert len(on.splitlines()) * 4 < len(off.splitlines())
    prog = parse_program(on)
    assert set(prog.arc_plane[np.isin(prog.motion, (2, 3))].tolist()) == {17, 18, 19}


@pytest.mark.parametrize("name, machine", [("inch_half_circle", "xh714"), ("lathe_pass", "lathe")])
def test_no_arcs_writes_the_bytes_written_before_the_fit(name, machine):
    # tests/data/post_arcs/*.before.out: written by the post before arcs.py existed (commit 4b10ab1)
    m = load_machine(ROOT / "fixtures" / "machines" / f"{machine}.toml")
    out, _ = _post(name, m, arcs=False)
    assert out == (DATA / f"{name}.before.out").read_text()


def test_a_full_turn_whose_written_ends_differ_is_no_longer_kept(xh714, tmp_path):
    # Before: the helix "G2 X20 Y10 I2 J0 Z-29 P2" (two turns, correction constant within tol / 2) was kept as an arc
    # whose corrected start and end differ by a digit; LinuxCNC reads that as a short arc plus one turn, not two
    # turns (pmCircleInit), and the helix leaves its path by a quarter of its rise. Now (--no-arcs too) it is
    # linearised; every other line is written as before.
    before = (DATA / "arcs_planes_low.before.out").read_text()
    now, _ = _post("arcs_planes_low", xh714, arcs=False)
    helix = next(i for i, line in enumerate(before.splitlines()) if line.endswith("P2"))
    b, n = before.splitlines(), now.splitlines()
    assert b[:helix] == n[:helix]
    k = len(n) - len(b)  # the helix' extra pieces
    assert k > 50 and len(b[helix + 1:]) == len(n[helix + 1 + k:])
    # every other line as before, but for the G91 words' last digit: increments are now written as differences of
    # the rounded ends (they telescope: rounded one by one they added up along a G91 run)
    number = re.compile(r"([XYZIJK])(-?[0-9.]+)")
    for old_line, new_line in zip(b[helix + 1:], n[helix + 1 + k:]):
        if old_line != new_line:
            assert number.sub("", old_line) == number.sub("", new_line)
            for (a, x), (c, y) in zip(number.findall(old_line), number.findall(new_line)):
                assert a == c and abs(float(x) - float(y)) <= 1.000001e-5
    _, _, dev_before, _ = _check_against_rs274(xh714, "arcs_planes_low", tmp_path / "before", False, out=before)
    assert dev_before.max() > 100.0  # um: the turn lost
    _, _, dev_now, _ = _check_against_rs274(xh714, "arcs_planes_low", tmp_path / "now", False, out=now)
    assert dev_now.max() <= TOL_UM + 0.03


def test_arcs_default_on_for_three_axis_mills_only(xh714):
    from trueaxis.postproc.post import arcs_default

    assert arcs_default(xh714)
    assert not arcs_default(load_machine(ROOT / "fixtures" / "machines" / "lathe.toml"))
    assert not arcs_default(load_machine(ROOT / "fixtures" / "machines" / "nmv1500dcg.toml"))
    default, _ = _post("inch_half_circle", xh714, arcs=None)
    on, _ = _post("inch_half_circle", xh714, arcs=True)
    assert default == on


def test_arcs_asked_for_where_the_orientation_is_corrected_are_lines_and_said(tmp_path):
    # A five-axis program's arcs stay straight pieces with --arcs (the correction turns the rotary axes along the
    # arc): that was silent; the output is the one without --arcs, and a warning says why. Not said when not asked.
    m = load_machine(ROOT / "fixtures" / "machines" / "nmv1500dcg.toml")
    text = "G21 G90 G17 G54\nG0 X10 Y0 Z5 B0 C0\nG1 Z-1 F500\nG2 X0 Y10 I-10 J0\nG1 X-5\nM2\n"
    kw = dict(setup=Setup(offsets_zero=True), header=False)
    on, rep_on = post_text(text, m, "geometric", arcs=True, **kw)
    default, rep_default = post_text(text, m, "geometric", arcs=None, **kw)
    assert on == default and rep_on.arcs_linearised == 1 and rep_on.arcs_fitted == 0
    said = [w for w in rep_on.warnings if "--arcs" in w]
    assert len(said) == 1 and "1 arc written as straight pieces" in said[0] and "orientation" in said[0]
    assert not [w for w in rep_default.warnings if "--arcs" in w]


def test_cli_arcs_flags(tmp_path):
    src = DATA / "inch_half_circle.ngc"
    cmd = [sys.executable, "-m", "trueaxis.cli", "post", str(src), "--machine",
           str(ROOT / "fixtures" / "machines" / "xh714.toml"), "--offsets-zero", "-o", "-"]
    on = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    off = subprocess.run(cmd + ["--no-arcs"], capture_output=True, text=True, cwd=ROOT)
    assert on.returncode == 0 and off.returncode == 0, on.stderr + off.stderr
    assert len(on.stdout.splitlines()) < 20 < len(off.stdout.splitlines())


def test_lathe_arcs_fitted_on_request_lie_on_the_nominal_arc(tmp_path):
    # A lathe's arcs are fitted only when asked (--arcs): the 190 mm finishing arc, 220 lines as straight pieces,
    # becomes one G2. Checked as on the mill through rs274 and the twin, in the XZ plane (a lathe's error along Y
    # moves the turned radius by second order only and no axis can correct it; the post judges X and Z).
    lathe = load_machine(ROOT / "fixtures" / "machines" / "lathe.toml")
    out, rep = _post("lathe_pass", lathe, arcs=True)
    off, _ = _post("lathe_pass", lathe, arcs=False)
    assert rep.arcs_fitted == 1 and len(out.splitlines()) + 200 < len(off.splitlines())
    nominal = _rs274((DATA / "lathe_pass.ngc").read_text(), tmp_path, "in")
    written = _rs274(out, tmp_path, "out")
    ours = parse_program(out)
    np.testing.assert_allclose(written.end, ours.end, atol=5e-5)
    written.end[:, :3] = ours.end[:, :3]
    written.center = np.where(np.isnan(written.center), np.nan, ours.arc_center)
    nominal_path = np.vstack([pts for _, pts in _path_points(nominal, np.zeros(3), 0.02)])
    arc_pts = np.vstack([pts for kind, pts in _path_points(written, np.zeros(3), 0.1) if kind == "arc"])
    twin = ErrorTwin(lathe)
    actual, _ = twin.actual_pose(arc_pts[:, [0, 2]])
    o, _ = twin.nominal_pose(np.zeros((1, 2)))
    A = np.stack([twin.nominal_pose(np.eye(2)[[j]])[0][0] - o[0] for j in range(2)], axis=1)  # (3, 2)
    xz = np.linalg.lstsq(A, (actual - o).T, rcond=None)[0].T  # X and Z of the actual tip (Y dropped)
    tip = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
    dev_um = _distance_to_polyline(tip, nominal_path) * 1e3
    assert dev_um.max() <= TOL_UM + 0.03, dev_um.max()
    # the straight pieces' own check would not pass a nominal arc written as it was
    raw = _rs274((DATA / "lathe_pass.ngc").read_text(), tmp_path, "raw")
    raw_pts = np.vstack([pts for kind, pts in _path_points(raw, np.zeros(3), 0.1) if kind == "arc"])
    raw_actual, _ = twin.actual_pose(raw_pts[:, [0, 2]])
    raw_xz = np.linalg.lstsq(A, (raw_actual - o).T, rcond=None)[0].T
    raw_tip = np.column_stack([raw_xz[:, 0], np.zeros(len(raw_xz)), raw_xz[:, 1]])
    assert _distance_to_polyline(raw_tip, nominal_path).max() * 1e3 > 5 * TOL_UM


def test_a_sub_arc_that_cannot_hold_becomes_straight_pieces_alone(xh714, tmp_path, monkeypatch):
    # With one bisection allowed, the inch half circle's second quarter does not hold as an arc (its correction bends
    # more than 1 um from any arc through its ends): that quarter alone becomes straight pieces, the rest stays G2.
    from trueaxis.postproc import arcs as arcs_module

    monkeypatch.setattr(arcs_module, "MAX_DEPTH", 1)
    out, rep, dev_um, written = _check_against_rs274(xh714, "inch_half_circle", tmp_path, True,
                                                     kinds=("arc", "feed"))
    assert rep.arcs_fitted == 1 and rep.sub_arcs_linearised == 1
    feeds = [k for k in written.kind if k != "traverse"]
    assert "arc" in feeds and feeds.count("feed") > 20
    assert dev_um.max() <= TOL_UM + 0.03, dev_um.max()


@pytest.mark.parametrize("machine_name, arcs", [("xh714", True), ("xh714", False), ("nmv1500dcg", False)])
def test_arc_ends_taken_from_the_block_ends_solve_change_nothing(machine_name, arcs, monkeypatch):
    """An arc's last sample point is its block's end: its commanded pose is taken from the end's solve. Posting with
    every point solved again gives the same bytes and the same report (singular points and blocks included: the
    five-axis program's arcs at B0 lie in the singular cone)."""
    from trueaxis.postproc import post as post_module

    if machine_name == "xh714":
        from trueaxis.machine import parse_machine

        text = (ROOT / "fixtures" / "programs" / "arcs_planes.ngc").read_text()
        machine_text = (ROOT / "fixtures" / "machines" / "xh714.toml").read_text()
        for old in ("[-200.0, 200.0]", "[-150.0, 150.0]", "[-400.0, 0.0]"):
            machine_text = machine_text.replace(old, "[-2000.0, 2000.0]")
        machine = parse_machine(machine_text, source="xh714-wide")
    else:
        machine = load_machine(ROOT / "fixtures" / "machines" / f"{machine_name}.toml")
        text = ("G21 G90 G17 G94\nG0 X10 Y5 Z-20 B0 C0\nG1 X20 Y5 Z-20 F500\nG2 X30 Y15 I0 J10\n"
                "G3 X20 Y25 I-10 J0\nG1 X20 Y30 B0.3 C10\nG2 X30 Y40 I10 J0\nM30\n")

    def post():
        return post_text(text, machine, "geometric", source="t.ngc", setup=Setup(offsets_zero=True), arcs=arcs)

    out, rep = post()
    real = post_module._Poster._solve_arc_points
    monkeypatch.setattr(post_module._Poster, "_solve_arc_points",
                        lambda self, rows, arc_idx, owner, pts6, force, ends=None:
                        real(self, rows, arc_idx, owner, pts6, force, None))
    again, rep_again = post()
    assert out == again
    assert rep.as_dict() == rep_again.as_dict()
    if machine_name == "nmv1500dcg":
        assert rep.singular_points > 0


# ------------------------------------------------------------- arc points taken from the block ends' solve -----


@pytest.mark.parametrize("name, mode", [("mtc_plate_1.nc", "geometric"), ("mtc_plate_1.nc", "comprehensive")])
def test_arc_points_taken_from_the_ends_solve_post_the_same_as_solved_again(monkeypatch, name, mode):
    # An arc's first point (its start, where it is the end of the move before under the same load) and its last
    # point take their commanded poses from the chunk's solve of the block ends: the same bytes as solving them again.
    from trueaxis.postproc import post as post_module

    text = (ROOT / "fixtures" / "programs" / "nist" / name).read_text(errors="replace")
    machine_text = (ROOT / "fixtures" / "machines" / "xh714.toml").read_text()
    for old in ("[-200.0, 200.0]", "[-150.0, 150.0]", "[-400.0, 0.0]"):
        machine_text = machine_text.replace(old, "[-2000.0, 2000.0]")
    from trueaxis.machine import parse_machine

    machine = parse_machine(machine_text, source="xh714-wide")
    conditions = {"ap": 1.0, "ae": 1.0, "fz": 0.05, "n": 5000.0, "d": 10.0, "z": 4}
    original = post_module._Poster._solve_arc_points
    taken = [0]

    def counting(self, rows, arc_idx, owner, pts6, force, ends=None):
        before = self.stats["singular_points"]
        solves = []
        solve = self.solve

        def spy(q, *a, **k):
            solves.append(q.shape[0])
            return solve(q, *a, **k)

        self.solve = spy
        try:
            out = original(self, rows, arc_idx, owner, pts6, force, ends)
        finally:
            del self.solve
        taken[0] += owner.size - sum(solves)
        assert self.stats["singular_points"] == before  # (a three-axis mill: no singular cone)
        return out

    def again(self, rows, arc_idx, owner, pts6, force, ends=None):
        return original(self, rows, arc_idx, owner, pts6, force, None)

    outs = []
    for patch in (counting, again):
        monkeypatch.setattr(post_module._Poster, "_solve_arc_points", patch)
        outs.append(post_text(text, machine, mode, source=name, setup=Setup(offsets_zero=True),
                              conditions=conditions))
    assert outs[0][0] == outs[1][0]
    assert outs[0][1].as_dict() == outs[1][1].as_dict()
    assert taken[0] > 0


def _near_limit_arcs() -> str:
    """Twelve 1 mm arcs whose radii to start and end differ by 0.02828 mm, 4 nm inside LinuxCNC's limit (0.02 sqrt 2
    mm, for a radius difference over 0.1 %), clockwise and counter-clockwise about the table: small enough that the
    correction is constant along each, within tol / 2, so that each is kept as it is."""
    blocks = []
    for x, y in [(100, 100), (150, 50), (-150, 120), (50, -120), (-100, 120), (-160, -100)]:
        for g in (2, 3):
            blocks.append(f"G0 X{x} Y{y} Z-105\nG1 Z-110 F300\nG{g} X{x + 2.02828:.5f} Y{y} I1 J0\nG0 Z-100\n")
    return "G21 G17 G90 G94\n" + "".join(blocks) + "M2\n"


def test_an_arc_near_linuxcncs_radius_limit_is_not_kept_past_it(xh714, tmp_path, monkeypatch):
    # A kept arc is written with its end and centre moved by its end's correction, from the start the block before
    # writes: the difference of its ends' corrections (up to the spread a kept arc may have) changes the difference of
    # its radii. Near LinuxCNC's limit that pushed arcs past it: rs274 refused the output ("Radius to end of arc
    # differs from radius to start", r1 0.9999 r2 1.0283), which the post had written with exit 0. Such arcs are now
    # fitted (radii within the smallest tolerance a configuration may set); the others stay kept.
    import trueaxis.postproc.post as post_module

    text = _near_limit_arcs()
    assert parse_program(text)  # (the input is within the limit: the reader and rs274 read it)
    _rs274(text, tmp_path, "in")
    out, rep = post_text(text, xh714, "geometric", setup=Setup(offsets_zero=True), header=False)
    assert 0 < rep.arcs_kept < 12 and rep.arcs_linearised == 0  # (the others fitted, none straight pieces)
    written = _rs274(out, tmp_path, "out")
    assert sum(k == "arc" for k in written.kind) >= 12
    # without the check, every arc is kept and rs274 refuses the output
    monkeypatch.setattr(post_module, "radii_kept_within_limits", lambda poster, rows, arc_idx, delta: np.ones(
        len(arc_idx), bool))
    out_before, rep_before = post_text(text, xh714, "geometric", setup=Setup(offsets_zero=True), header=False)
    assert rep_before.arcs_kept == 12
    (tmp_path / "before.ngc").write_text(out_before)
    moves = run_rs274(tmp_path / "before.ngc", {}, tmp_path / "before")
    assert moves.returncode != 0 and "Radius to end of arc differs" in moves.stderr
