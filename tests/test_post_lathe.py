"""The post on a two-axis lathe: the tool tip lands on the nominal path in the XZ plane of its axes."""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
import re
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from conftest import MACHINES, ROOT
from post_checks import actual_points, distance_to_polyline, nominal_polyline
from rs274_helpers import assert_rs274_reads_as_we_do
from trueaxis.machine import load_machine
from trueaxis.nc.gcode import GcodeError, parse_program
from trueaxis.postproc.post import PostError, compensate
from trueaxis.postproc.solver import corrected_directions

# Facing, a shoulder and a 270 deg G18 arc (counter-clockwise seen from +Y: from -X about the centre round to -Z).
PROGRAM = """G18 G21 G90 G94 G8
G0 X40 Z-5
G1 Z-50 F100
G1 X60
G3 X70 Z-60 I10 K0
G0 X90 Z-5
M30
"""


@pytest.fixture(scope="module")
def lathe():
    return load_machine(MACHINES / "lathe.toml")


def test_a_lathe_corrects_in_the_plane_of_its_axes(lathe):
    B = corrected_directions(lathe)
    np.testing.assert_allclose(B.T @ B, np.diag([1.0, 0.0, 1.0]), atol=1e-15)  # the projector onto XZ


def test_lathe_output_lands_on_the_nominal_path_in_xz(lathe, tmp_path):
    report = {}
    out = compensate(PROGRAM, lathe, "geometric", report=report)
    actual, _, _ = actual_points(out, lathe)
    nominal = nominal_polyline(parse_program(PROGRAM), lathe)
    xz = lambda p: p * np.array([1.0, 0.0, 1.0])  # noqa: E731 - the turned radius ignores Y to second order
    d_um = distance_to_polyline(xz(actual), xz(nominal)) * 1e3
    assert d_um.max() < 0.1, d_um.max()
    # The correction is not trivial: the typical errors move the tip by microns, and the arc's correction varies.
    assert max(v["max_abs_um"] for v in report["correction"].values()) > 1.0
    assert report["arcs_linearised"] == 1
    assert_rs274_reads_as_we_do(out, tmp_path, name="lathe.ngc")


def test_comprehensive_mode_on_a_lathe_refuses_milling_conditions(lathe):
    with pytest.raises(PostError, match=r"turning takes the cutting conditions ap \(mm\), f \(mm/rev\) and vc "
                                        r"\(m/min\); the conditions given hold ae, fz, which are milling's"):
        compensate(PROGRAM, lathe, "comprehensive", conditions={"ap": 1, "ae": 1, "fz": 0.1})


def test_a_host_gives_the_turning_conditions_as_the_comment_would(lathe):
    """conditions={'ap', 'f', 'vc'} was refused as milling conditions 'from the command line' (QA pass): a Python
    host (CadQuery) had no way to give them but a comment in the G-code. Now they post as the comment does."""
    one = TURNING.replace("(trueaxis: ap=1 f=0.1 vc=200)\n", "")  # (given conditions hold for every block)
    bare = one.replace("(trueaxis: ap=2 f=0.2 vc=180)\n", "")
    assert bare.count("trueaxis:") == 0 and one.count("trueaxis:") == 1
    given = compensate(bare, lathe, "comprehensive", conditions={"ap": 2, "f": 0.2, "vc": 180}, offsets_zero=True)
    said = compensate(one, lathe, "comprehensive", offsets_zero=True)
    assert given == said.replace("(trueaxis: ap=2 f=0.2 vc=180)\n", "")
    assert given != compensate(bare, lathe, "geometric", offsets_zero=True)  # (the force is in it)


def test_comprehensive_mode_on_a_lathe_without_turning_coefficients_is_refused(lathe):
    bare = dataclasses.replace(lathe, cutting=None)
    with pytest.raises(PostError, match="needs the turning coefficients"):
        compensate(TURNING, bare, "comprehensive")


def test_comprehensive_mode_on_a_lathe_without_conditions_names_the_block(lathe):
    with pytest.raises(PostError, match=r":3: comprehensive mode needs turning conditions"):
        compensate(PROGRAM, lathe, "comprehensive")


# ---------------------------------------------------------------------------------------------------------------------
# Comprehensive mode: the paper's response surfaces under the estimated turning force
# ---------------------------------------------------------------------------------------------------------------------

# Every combination of load sign and direction of motion of X (the surfaces' position axis), at 6 decimals (the
# written numbers then round by 0.0005 um). Conditions change midway.
TURNING = """G18 G21 G90 G94 G8
(trueaxis: ap=2 f=0.2 vc=180)
G0 X40.000000 Z-5.000000
G1 Z-50.000000 F100
G1 X60.000000
G1 Z-30.000000
G1 X50.000000
G1 Z-70.000000
G1 Z-60.000000
(trueaxis: ap=1 f=0.1 vc=200)
G1 X55.000000 Z-65.000000
G1 X45.000000 Z-55.000000
G0 X90.000000 Z-5.000000
M30
"""


def _paper_models():
    """The four printed surfaces from the paper's CSV (mm, X in mm, P in kN): {(load sign, motion): c0..c5}."""
    lines = (ROOT / "fixtures" / "papers" / "lathe_caliper_models.csv").read_text().splitlines()
    rows = csv.DictReader(line for line in lines if not line.startswith("#"))
    return {(r["load_sign"], r["motion"]): [float(r[k]) for k in ("c0", "c1_x", "c2_p", "c3_x2", "c4_xp", "c5_p2")]
            for r in rows}


def _written_xz(text):
    """(X, Z) of every motion block of a program we wrote (one per input block: nothing is split here)."""
    out = []
    for line in text.splitlines():
        if re.match(r"G[01]\b", line):
            x = re.search(r"X(-?[\d.]+)", line)
            z = re.search(r"Z(-?[\d.]+)", line)
            out.append((float(x.group(1)), float(z.group(1))))
    return np.array(out)


def test_comprehensive_z_corrections_equal_the_papers_surface_at_the_blocks_x_and_force(lathe):
    # Hand evaluation, independent of the twin and of the post's force code: Kienzle's main force
    # Fc = kc1.1 * ap * f^(1 - mc) (kappa_r 90 deg: h = f, b = ap), the feed and passive forces as the machine file's
    # fractions of it; the Z component of the force on the tool worked out block by block; the paper's printed
    # polynomial dZ = c0 + c1 X + c2 P + c3 X^2 + c4 X P + c5 Pz^2 (mm; P = +-Pz in kN) of the model of that load sign
    # and X's direction of motion. The comprehensive post's Z minus the geometric post's Z is -dZ.
    cutting = tomllib.loads((MACHINES / "lathe.toml").read_text())["cutting"]
    assert cutting["kappa_deg"] == 90.0

    def forces(ap, f):
        fc = cutting["kc11"] * ap * f ** (1.0 - cutting["mc"])
        return cutting["feed_ratio"] * fc, cutting["passive_ratio"] * fc

    ff, fp = forces(2.0, 0.2)
    ff2, fp2 = forces(1.0, 0.1)
    r = np.sqrt(0.5)
    # (X at the block's end mm, Z force on the tool N, direction of motion of X)
    blocks = [
        (40.0, 0.0, "forward"),  # rapid from X0: no force
        (40.0, +ff, "forward"),  # feed towards the chuck (-Z): the feed force pushes the tool +Z; X last moved +
        (60.0, +fp, "forward"),  # facing outwards (+X): the passive force pushes the tool off the face, +Z
        (60.0, -ff, "forward"),  # feed towards the tailstock (+Z): feed force -Z
        (50.0, +fp, "backward"),  # facing inwards (-X): passive force +Z; X moves -
        (50.0, +ff, "backward"),  # -Z feed; X last moved -
        (50.0, -ff, "backward"),  # +Z feed
        (55.0, r * (ff2 + fp2), "forward"),  # chamfer (+X, -Z): feed force (+Z part) and passive force (+Z part)
        (45.0, r * (fp2 - ff2), "backward"),  # (-X, +Z): the feed force's -Z part outweighs the passive force's +Z
        (90.0, 0.0, "forward"),  # rapid
    ]
    models = _paper_models()
    expected_um = []
    for x, fz_n, motion in blocks:
        P = fz_n / 1000.0
        c = models[("+" if P >= 0 else "-", motion)]
        expected_um.append(-1000.0 * (c[0] + c[1] * x + c[2] * P + c[3] * x**2 + c[4] * x * P + c[5] * P**2))
    # Every model is used, with loads of tens to hundreds of newtons, so a wrong choice or force cannot pass.
    assert {("+" if f >= 0 else "-", m) for _, f, m in blocks} == set(models)
    assert min(abs(f) for _, f, _ in blocks if f) > 30.0

    # A loose split tolerance keeps one written block per programmed one (the ends do not depend on it).
    geometric = _written_xz(compensate(TURNING, lathe, "geometric", tol_um=50.0))
    report = {}
    comprehensive = _written_xz(compensate(TURNING, lathe, "comprehensive", tol_um=50.0, report=report))
    assert report["moves_split"] == 0 and geometric.shape == comprehensive.shape == (len(blocks), 2)
    dz_um = (comprehensive[:, 1] - geometric[:, 1]) * 1000.0
    np.testing.assert_allclose(dz_um, expected_um, rtol=0, atol=0.01)
    # The surfaces are in Z only: X corrections agree (to the written digits and second-order cross terms).
    np.testing.assert_allclose(comprehensive[:, 0], geometric[:, 0], rtol=0, atol=2e-6)


def test_comprehensive_lathe_output_lands_on_the_nominal_path_under_the_load(lathe, tmp_path):
    # Put through the twin with each block's load, the written end points land on the programmed ones in XZ (a loose
    # split tolerance: one written block per programmed one).
    out = compensate(TURNING, lathe, "comprehensive", tol_um=50.0)
    written = _written_xz(out)
    from trueaxis.machine import ErrorTwin
    from trueaxis.postproc.turning import MotionTwin, lathe_loads

    class _Poster:  # what lathe_loads reads of the post
        def __init__(self):
            self.p, self.m, self.conditions, self.names = parse_program(TURNING), lathe, {}, lathe.axis_names

    poster = _Poster()
    loads = lathe_loads(poster, np.arange(len(poster.p)))
    p_act, _ = MotionTwin(ErrorTwin(lathe)).actual_pose(written, loads)
    p_nom, _ = ErrorTwin(lathe).nominal_pose(poster.p.end[:, [0, 2]])
    err_um = np.abs((p_act - p_nom)[:, [0, 2]]) * 1e3
    assert err_um.max() < 0.01, err_um.max()
    assert_rs274_reads_as_we_do(out, tmp_path, name="lathe_comprehensive.ngc")


def test_trueaxis_post_cli_compensates_a_turning_program_in_comprehensive_mode(lathe, tmp_path):
    src, dst = tmp_path / "turn.ngc", tmp_path / "turn_out.ngc"
    src.write_text(TURNING)
    r = subprocess.run([sys.executable, "-m", "trueaxis.cli", "post", str(src), "-o", str(dst), "--machine",
                        str(MACHINES / "lathe.toml"), "--mode", "comprehensive"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert dst.read_text() == compensate(TURNING, lathe, "comprehensive")


def test_freecad_post_script_compensates_a_turning_program_in_comprehensive_mode(lathe, tmp_path, monkeypatch):
    # FreeCAD's post script runs the trueaxis command; here the real one, on a hand-written turning program.
    from trueaxis.postproc.hosts.freecad import post_script_path

    spec = importlib.util.spec_from_file_location("trueaxis_post", post_script_path())
    post = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(post)
    exe = tmp_path / "trueaxis"
    exe.write_text(f"#!{sys.executable}\nimport sys\nfrom trueaxis.cli import main\nsys.exit(main())\n")
    exe.chmod(0o755)
    monkeypatch.setenv("TRUEAXIS_BIN", str(exe))
    opts, _ = post.split_arguments(f"--machine {MACHINES / 'lathe.toml'} --mode comprehensive")
    assert post.compensate(TURNING, opts) == compensate(TURNING, lathe, "comprehensive")


def _in_diameter_mode(program: str) -> str:
    """The program with G7 after its first line and every X word doubled (the same moves in diameter mode)."""
    lines = program.splitlines(keepends=True)
    body = [re.sub(r"X(-?[\d.]+)", lambda m: f"X{2 * float(m.group(1)):.6f}", line) for line in lines[1:]]
    return lines[0] + "G7\n" + "".join(body)


@pytest.mark.parametrize("mode", ["geometric", "comprehensive"])
def test_diameter_mode_program_is_compensated_like_its_radius_mode_twin(lathe, tmp_path, mode):
    # G7: X words are diameters (LinuxCNC halves them). The same moves written in G7 and in G8 must come out as the
    # same positions: the G7 output's X words are the G8 output's doubled (to the written digits).
    g7 = _in_diameter_mode(TURNING)
    out_g7 = compensate(g7, lathe, mode)
    out_g8 = compensate(TURNING, lathe, mode)
    read_g7, read_g8 = parse_program(out_g7), parse_program(out_g8)
    assert read_g7.diameter[-1] and not read_g8.diameter.any()
    np.testing.assert_allclose(read_g7.end, read_g8.end, rtol=0, atol=1e-6)
    xs7 = [float(x) for x in re.findall(r"X(-?[\d.]+)", out_g7)]
    xs8 = [float(x) for x in re.findall(r"X(-?[\d.]+)", out_g8)]
    assert len(xs7) == len(xs8) and max(abs(a - 2 * b) for a, b in zip(xs7, xs8)) <= 1.5e-6
    assert_rs274_reads_as_we_do(out_g7, tmp_path, name="lathe_g7.ngc")


def test_the_summary_says_a_lathe_x_correction_is_a_radius_when_g7_words_are_diameters(lathe, tmp_path):
    # The summary's X correction is a radius; in G7 the written X words change by twice it (a QA pass compared 7.51 um
    # in the summary with 15 um in the words). Said in the report and on the terminal; not in G8.
    report = {}
    compensate(_in_diameter_mode(TURNING), lathe, "geometric", report=report)
    x = report["correction"]["X"]
    assert x["max_abs_diameter_um"] == 2.0 * x["max_abs_um"] > 0.0
    assert all(isinstance(v, float) for axis in report["correction"].values() for v in axis.values())
    report = {}
    compensate(TURNING, lathe, "geometric", report=report)
    assert "max_abs_diameter_um" not in report["correction"]["X"]
    src = tmp_path / "g7.ngc"
    src.write_text(_in_diameter_mode(TURNING))
    run = subprocess.run([sys.executable, "-m", "trueaxis", "post", str(src), "--machine", str(MACHINES / "lathe.toml"),
                          "--offsets-zero", "-o", str(tmp_path / "out.ngc")], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert re.search(r"X \d+\.\d\d \(a radius: G7's X words change by twice it, \d+\.\d\d\)", run.stdout), run.stdout


def test_arcs_in_diameter_mode_are_refused_with_the_block(lathe):
    with pytest.raises(PostError, match=r":6: arcs and canned cycles in lathe diameter mode \(G7\)"):
        compensate(_in_diameter_mode(PROGRAM), lathe, "geometric")


def test_comprehensive_corrections_along_a_lathe_arc_follow_its_tangent(lathe):
    # A half circle (G18) cut towards the tailstock: the feed direction turns through 180 deg, so the force along Z and X's direction of
    # motion change along the arc. At every written point of the linearised arc the comprehensive minus geometric Z
    # is minus the paper's surface at that point's X and the force of the tangent there, worked by hand: the point's
    # angle on the circle (the written point projected on it: the corrections move it by microns, which changes the
    # force's direction by 1e-3 rad at most), the tangent along the travel, Kienzle's force split into feed and
    # passive parts along and across it. Points where the force or the tangent's X part nearly vanish (where a model
    # switch could fall either side of a point) are left out.
    program = """G18 G21 G90 G94 G8
(trueaxis: ap=1 f=0.15 vc=150)
G0 X40.000000 Z-5.000000
G1 Z-60.000000 F100
G2 X40.000000 Z-40.000000 I0 K10.000000
G0 X90.000000 Z-5.000000
M30
"""
    geo = compensate(program, lathe, "geometric", tol_um=0.2)
    com = compensate(program, lathe, "comprehensive", tol_um=0.2)
    pg, pc = _written_xz(geo), _written_xz(com)
    assert pg.shape == pc.shape and len(pg) > 100  # the arc linearised into the same points in both modes
    centre = np.array([40.0, -50.0])
    # The G2 block's pieces: the written points on the circle (within the corrections' microns), after the line's end
    # (the arc's start, which carries the line's load).
    on_circle = np.nonzero(np.abs(np.linalg.norm(pg - centre, axis=1) - 10.0) < 1e-2)[0]
    assert np.all(np.diff(on_circle) == 1) and pg[on_circle[0], 1] < -59.9
    arc = on_circle[1:]
    rel = pg[arc] - centre
    radius = np.linalg.norm(rel, axis=1)
    unit = rel / radius[:, None]
    nominal_x = centre[0] + 10.0 * unit[:, 0]
    # The travel's sense from the order of the points: the tangent turns the radius by +-90 deg.
    turn = np.sign(rel[:-1, 0] * rel[1:, 1] - rel[:-1, 1] * rel[1:, 0])
    assert np.all(turn == turn[0])
    tangent = turn[0] * np.stack([-unit[:, 1], unit[:, 0]], axis=1)  # (X, Z)
    cutting = tomllib.loads((MACHINES / "lathe.toml").read_text())["cutting"]
    fc = cutting["kc11"] * 1.0 * 0.15 ** (1.0 - cutting["mc"])
    ff, fp = cutting["feed_ratio"] * fc, cutting["passive_ratio"] * fc
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    normal[normal.sum(axis=1) < 0] *= -1.0  # off the material: the side of +X +Z
    fz_n = -ff * tangent[:, 1] + fp * normal[:, 1]
    models = _paper_models()
    P = fz_n / 1000.0
    expected_um = np.array([
        -1000.0 * (lambda c: c[0] + c[1] * x + c[2] * p + c[3] * x**2 + c[4] * x * p + c[5] * p**2)(
            models[("+" if p >= 0 else "-", "forward" if tx > 0 else "backward")])
        for x, p, tx in zip(nominal_x, P, tangent[:, 0])
    ])
    clear = (np.abs(fz_n) > 5.0) & (np.abs(tangent[:, 0]) > 0.05)
    assert clear.sum() > 0.8 * clear.size
    kinds = {("+" if p >= 0 else "-", tx > 0) for p, tx in zip(P[clear], tangent[clear, 0])}
    assert len(kinds) >= 3  # the arc goes through several of the paper's models
    dz_um = (pc[arc, 1] - pg[arc, 1]) * 1000.0
    np.testing.assert_allclose(dz_um[clear], expected_um[clear], rtol=0, atol=0.01)


def test_the_lathe_report_names_each_set_of_turning_conditions_used(lathe):
    # Milling's report listed them; a lathe's list was empty although ap f vc were used (a QA pass).
    report = {}
    compensate(TURNING, lathe, "comprehensive", report=report)
    assert [(c["conditions"], c["first_line"]) for c in report["cutting_conditions"]] == [
        ({"ap": "2", "f": "0.2", "vc": "180"}, 3), ({"ap": "1", "f": "0.1", "vc": "200"}, 11)]


def test_a_g95_feed_that_disagrees_with_the_conditions_comment_is_said(lathe):
    # The force comes from the comment's f; a program feeding F0.4 per revolution under a comment f=0.2 cut about
    # 1.8 times the force corrected for, without a word (a QA pass). Said; the same feed, or G94, says nothing.
    program = ("G18 G21 G90 G95 G8\nG0 X120 Z-5\n(trueaxis: ap=2 f=0.2 vc=180)\nG1 X80 Z-10 F{feed}\nG1 Z-100\n"
               "G0 X190\nM2\n")
    for feed, said in (("0.4", True), ("0.2", False)):
        report = {}
        compensate(program.format(feed=feed), lathe, "comprehensive", report=report, offsets_zero=True)
        told = [w for w in report["warnings"] if "per revolution (G95), its conditions comment says" in w]
        assert len(told) == int(said), report["warnings"]
        if said:
            assert told[0].startswith("<string>:4: the program feeds F0.4 per revolution (G95)") and "f=0.2" in told[0]
    report = {}
    compensate(program.format(feed="100").replace("G95", "G94"), lathe, "comprehensive", report=report,
               offsets_zero=True)
    assert not any("per revolution (G95), its" in w for w in report["warnings"])


# A lathe program that sets its work offset with G10 L2 in X and Z, the axes it has (a QA pass: refused for the G54 Y
# component that was not given, the only way through --offsets-zero, which zeroes every missing value).
LATHE_G10 = "G18 G21 G90 G94 G8\nG10 L2 P1 X10 Z-100\nG54 G0 X40 Z-5\nG1 Z-50 F100\nG1 X60\nM30\n"


def test_a_lathe_work_offset_needs_no_y_component_and_the_header_says_zero_was_taken(lathe):
    from trueaxis.nc.setup import parse_setup

    report = {}
    out = compensate(LATHE_G10, lathe, report=report)
    lines = out.splitlines()
    assert lines[3] == ("(trueaxis setup: G54 X10 Z-100 mm, from <string>:2 [G10 L2]; Y not given, 0: the machine "
                        "has no Y axis)")
    assert report["setup_used"][0]["zero_no_such_axis"] == "Y"
    # corrected at the machine positions X 50..70, Z -105..-150 (the offset applied): the twin's 3-7 um there
    assert lines[6:9] == ["G54 G0 X40.00496 Z-4.99694", "G1 X40.00703 Z-49.99282 F100", "G1 X60.00683 Z-49.99227"]
    # the same corrections as with the control's offset given in a setup file
    shop = parse_setup({"setup": {"units": "mm"}, "work_offsets": {"G54": {"X": 10.0, "Z": -100.0}}}, "shop.toml")
    given = compensate(LATHE_G10.replace("G10 L2 P1 X10 Z-100", "(offset in the control)"), lathe, setup=shop)
    assert given.splitlines()[6:9] == lines[6:9]
    # a component along an axis the lathe has is required as before
    with pytest.raises(GcodeError, match=r"^<string>:3: work offset G54 \(X\) was not given"):
        compensate(LATHE_G10.replace("X10 Z-100", "Z-100"), lathe)
    # no G54 word (the system active at start), no setup: the offset is the program's G10, not "no work offset"
    report = {}
    out = compensate(LATHE_G10.replace("G54 G0", "G0"), lathe, report=report)
    assert out.splitlines()[3] == lines[3] and out.splitlines()[6:9] == ["G0 X40.00496 Z-4.99694"] + lines[7:9]
    assert not any("no work offset" in w for w in report["warnings"]), report["warnings"]


# LinuxCNC's threading cycle with every word it reads (P Z I J R K Q H E L): rs274 reads it.
G76_PROGRAM = """G18 G21 G90 G8 G40 G49
G10 L2 P1 X0 Z-100
G54
T1 M6
G97 S500 M3
G0 X25 Z5
G76 P1.5 Z-30 I-1 J0.1 K0.9 Q29.5 L2 E1 H3 R1.5
G0 X30 Z10
M30
"""


def test_a_g76_threading_cycle_is_refused_for_itself_and_passed_through_with_all_its_words(lathe, tmp_path):
    # Its R word was refused as "R word with no G code that uses it", then its E word as "exponent notation", and
    # --passthrough-unsupported did not help: G76's own reason comes first, and the block passes through as written.
    from rs274_helpers import run_rs274

    with pytest.raises(GcodeError, match=r"^g76.ngc:7: threading cycle G76 \(the moves it makes are not in the text; "
                                         r"--passthrough-unsupported leaves the block as it is\)$"):
        compensate(G76_PROGRAM, lathe, "geometric", source="g76.ngc")
    out = compensate(G76_PROGRAM, lathe, "geometric", passthrough_unsupported=True)
    assert "\nG76 P1.5 Z-30 I-1 J0.1 K0.9 Q29.5 L2 E1 H3 R1.5\n" in out
    (tmp_path / "in.ngc").write_text(G76_PROGRAM)
    (tmp_path / "out.ngc").write_text(out)
    before = run_rs274(tmp_path / "in.ngc", {1: 0.0}, tmp_path / "a")
    after = run_rs274(tmp_path / "out.ngc", {1: 0.0}, tmp_path / "b")
    assert before.returncode == after.returncode == 0 and before.kind == after.kind and len(before.kind) == 153
    # the cycle starts where the corrected G0 before it ends: its X moves by that correction everywhere, its Z where
    # it returns to the start (Z > 0), and not where the thread ends (the programmed Z-30 and its taper): as written
    shift = after.end[0] - before.end[0]
    assert 1e-3 < np.abs(shift).max() < 0.01
    cycle, moved = before.end[1:-1], after.end[1:-1] - before.end[1:-1]
    at_start = cycle[:, 2] > 0
    assert at_start.sum() == 60 and (~at_start).sum() == 91
    np.testing.assert_allclose(moved[:, 0], shift[0], atol=1.5e-4)
    np.testing.assert_allclose(moved[:, 2], np.where(at_start, shift[2], 0.0), atol=1.5e-4)
    np.testing.assert_allclose(moved[:, [1, 3, 4, 5]], 0.0, atol=1e-12)


def test_a_lathe_arc_in_a_plane_the_program_never_states_is_refused(lathe):
    """No G18 in the program: read as G17, the arc became 55 straight pieces of the XY helix, 2.9 mm off the G18 arc a
    lathe control (start-up code G18) cuts, exit 0 (QA pass). Refused, naming the line; with G18 stated it posts."""
    prog = "G21 G90 G8\nG0 X30 Z-95\nG1 Z-100 F100\nG2 X40 Z-110 R10\nG1 Z-130\nM2\n"
    with pytest.raises(PostError, match=r"^<string>:4: an arc in the G17 plane \(the program states no plane: G17 is "
                                        r"read\) on .*, which has no Y axis: .* state G18 before the arc"):
        compensate(prog, lathe, "geometric", offsets_zero=True)
    with pytest.raises(PostError, match=r":4: an arc in the G19 plane on "):
        compensate(prog.replace("G8\n", "G8 G19\n"), lathe, "geometric", offsets_zero=True)
    assert "G2 " in compensate("G18 " + prog, lathe, "geometric", offsets_zero=True, arcs=True)


def test_x_before_g7_or_g8_on_a_lathe_is_refused(lathe):
    """Neither G7 nor G8: X was read as a radius; on a control that starts in G7 (diameter) 3.9 of a 7.3 um radial
    correction was lost on every block, no warning (QA pass). Refused until the program says which; a Z move before
    it is fine, and --mode none posts as it did."""
    prog = "G18 G21 G90\nG0 Z-95\nG0 X60\nG1 Z-150 F100\nG1 X80\nM2\n"
    with pytest.raises(PostError, match=r"^<string>:3: X is given before the program says G7 \(X a diameter\) or G8 "):
        compensate(prog, lathe, "geometric", offsets_zero=True)
    for mode in ("G7", "G8"):
        assert compensate(prog.replace("G90\n", f"G90 {mode}\n"), lathe, "geometric", offsets_zero=True)
    assert compensate(prog.replace("G90\nG0 Z-95\n", "G90\nG0 Z-95\nG8\n"), lathe, "geometric", offsets_zero=True)
    assert "G0 X60" in compensate(prog, lathe, "none", offsets_zero=True)


def test_strict_posts_a_feed_per_revolution_program(lathe, tmp_path):
    """Every G95 program carried a note meant for simulate and diagnose (which refuse G95 themselves), so --strict
    refused every feed-per-revolution lathe program (QA pass)."""
    prog = tmp_path / "g95.ngc"
    prog.write_text("G18 G21 G90 G95 G8\nG0 X30 Z-95\nG1 Z-130 F0.2\nG1 X40\nM2\n")
    r = subprocess.run([sys.executable, "-m", "trueaxis.cli", "post", str(prog), "-o", str(tmp_path / "o.ngc"),
                        "--machine", str(MACHINES / "lathe.toml"), "--offsets-zero", "--strict"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stderr == "", r.stderr


def test_a_lathe_tool_offset_warning_speaks_of_the_offsets_arm_not_a_mill_tool_length(lathe):
    # A QA pass (a CAM engineer on a lathe): the warning spoke of the twin's "reference tool (50 mm, gauge line to
    # tip)", a milling tool's length the lathe file says is a placeholder its chain does not use. It now speaks of the
    # offsets' arm, on which the slides' angular errors act, with the same figure: the twin's largest tool-frame angle
    # on the program's moves, checked here at the machine positions the offsets give (X 40+5, Z -25+20 ...).
    from trueaxis.machine import ErrorTwin
    from trueaxis.nc.setup import Offset, Setup, ToolOffset

    setup = Setup(work_offsets={1: Offset(np.zeros(6), "test")}, active=1,
                  tools={1: ToolOffset(np.array([5.0, 0.0, 20.0, 0.0, 0.0, 0.0]), "lt.tbl")})
    program = "G18 G21 G90 G94 G8 G54\nT1 M6\nG43 H1\nG0 X40 Z-25\nG1 Z-70 F100\nG1 X60\nM30\n"
    report = {}
    with pytest.warns(UserWarning, match="tool offsets in force"):
        compensate(program, lathe, "geometric", setup=setup, report=report)
    said = [w for w in report["warnings"] if "offsets in force" in w]
    assert len(said) == 1 and "tool 1 offset X5 Z20 mm" in said[0], report["warnings"]
    assert "reference tool" not in said[0] and "gauge line" not in said[0] and "arm" in said[0]
    twin = ErrorTwin(lathe)
    q = np.array([[45.0, -5.0], [45.0, -50.0], [65.0, -50.0]])
    du_urad = np.linalg.norm(twin.actual_pose(q)[1] - twin.nominal_pose(q)[1], axis=1) * 1e6
    assert du_urad.max() > 1.0  # the lathe's angular errors: a wrong figure would show
    assert report["tool_axis_error_max_urad"] == pytest.approx(du_urad.max(), rel=1e-6)
    assert f"up to {du_urad.max() * 0.01:.2f} um per 10 mm" in said[0]


def test_a_g33_threading_pass_is_refused_for_what_it_is_not_for_moves_missing_from_the_text(lathe):
    # A QA pass: G33's refusal said "the moves it makes are not in the text", though its move is (one straight pass to
    # Z-30). The reason is the spindle: its feed is bound to the spindle's turn, which the post does not compensate.
    program = "G18 G21 G90 G94 G8\nG0 X20 Z-5\nG33 Z-30 K1.5\nG0 X30\nM30\n"
    with pytest.raises(GcodeError, match=r"^g33.ngc:3: spindle-synchronised motion G33 \(its feed is bound to the "
                                         r"spindle's turn, a thread's lead: the post does not compensate threading "
                                         r"passes; --passthrough-unsupported leaves the block as it is\)$"):
        compensate(program, lathe, "geometric", source="g33.ngc")
    out = compensate(program, lathe, "geometric", passthrough_unsupported=True)
    assert "\nG33 Z-30 K1.5\n" in out
