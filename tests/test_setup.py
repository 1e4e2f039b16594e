"""The controller's setup goes into the post: LinuxCNC's parameter file and tool table, setup files for other
controls, refusal of offsets that were not given, the header and report naming every value used and its source.

Independent reference: LinuxCNC's standalone ``rs274`` reads the same program with the same ``.var`` and tool table;
its canonical calls (program coordinates, G5x / G92 offsets, XY rotation, tool offsets) give machine coordinates the
way LinuxCNC's canon composes them (tests/rs274_helpers.machine_moves). The standalone rs274 reads both files in
inches, so the files here are written in inches and posted with ``machine_units="inch"``.

rs274 prints 4 decimals of the program's units. For mm programs that is 0.05 um a coordinate, so a compensated
program read back by rs274 can be checked against the nominal path within 0.15 um directly. For inch programs it is
1.27 um: there rs274's machine positions must equal ours within that print resolution, and our exact machine
positions (the same interpretation) are checked within 0.15 um.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, mill_toml
from post_checks import distance_to_polyline, machine_rows, nominal_polyline
from rs274_helpers import require_rs274, run_rs274_setup, var_text
from trueaxis.machine import ErrorTwin, parse_machine
from trueaxis.nc.gcode import FEED, ARC_CW, ARC_CCW, ROW_PROGRAMMED, GcodeError, MM_PER_INCH, parse_program
from trueaxis.postproc.post import compensate
from trueaxis.nc.setup import SetupError, load_setup, read_setup_file, read_tool_table, read_var

NIST = ROOT / "fixtures" / "programs" / "nist"
INCH_PRINT_MM = 0.5e-4 * MM_PER_INCH  # rs274's rounding of an inch coordinate, mm

# A three-axis twin whose errors grow along the travel: positioning, straightness and angular errors as linear
# tables over +-2000 mm (so that any machine position lies inside them), squareness. Evaluated at the program
# coordinates instead of the machine coordinates, its corrections are wrong by micrometres.
MACHINE_TOML = mill_toml("position-dependent test mill", ((-2000.0, 2000.0),) * 3, """[location]
C0Y = 35.0
B0Z = -25.0
[component.X]
at = [-2000.0, 0.0, 2000.0]
EXX = [-200.0, 0.0, 200.0]
EYX = [60.0, 0.0, 100.0]
EBX = [-150.0, 0.0, 150.0]
[component.Y]
at = [-2000.0, 0.0, 2000.0]
EYY = [150.0, 0.0, -150.0]
EAY = [-120.0, 0.0, 120.0]
[component.Z]
at = [-2000.0, 0.0, 2000.0]
EZZ = [-100.0, 0.0, 100.0]
EXZ = [80.0, 0.0, -80.0]
EBZ = [60.0, 0.0, -60.0]
""")

# The part 3, 2, 8 inches (76.2, 50.8, 203.2 mm) from the machine origin in G54, other systems elsewhere; G58 (where
# the Hurco programs park) at the machine zero.
WORK_INCH = {1: [3.0, 2.0, -8.0, 0, 0, 0], 2: [1.5, -1.25, -6.5, 0, 0, 0], 5: [0.0, 0.0, 0.0, 0, 0, 0]}
TOOLS_INCH = "T1 P1 Z2.5 D0.25 ;a\nT2 P2 X0.01 Z3.125 D0.5\nT23 P23 Z1.75 D0.125 ;spot drill\n"


@pytest.fixture(scope="module")
def machine():
    return parse_machine(MACHINE_TOML, source="position-dependent")


@pytest.fixture
def files(tmp_path):
    var = tmp_path / "params.var"
    var.write_text(var_text(WORK_INCH, rotations={2: 25.0}, g28=[1.0, 2.0, 0.5, 0, 0, 0]))
    tbl = tmp_path / "tools.tbl"
    tbl.write_text(TOOLS_INCH)
    return var, tbl


def _setup(files, **kw):
    return load_setup(var=files[0], tool_table=files[1], machine_units="inch", **kw)


def _first_known_row(prog):
    """The first row where the program has given X, Y and Z: before it rs274 starts at the machine zero and the reader
    at the program zero, a start position neither knows (the post leaves those blocks as written)."""
    given = np.cumsum((prog.words[:, None] & np.array([1, 2, 4])) > 0, axis=0).min(axis=1) > 0
    k = int(np.argmax(given))
    assert given[k] and k < 5
    return k


def _mm(prog):
    return np.where(prog.inch[:, None] & np.array([1, 1, 1, 0, 0, 0], bool), MM_PER_INCH, 1.0)


# --- reading as LinuxCNC reads --------------------------------------------------------------------------------------

ROTATED = """G20 G17 G90 G94
G0 X1 Y1 Z1
G55
T2 M6
G43 H2
G0 X1 Y1 Z0.5
G1 X2 Y1.5 Z0.25 F20
G2 X2.5 Y1 I0.25 J-0.25
G92 X0 Y0
G1 X1 Y0.2
G92.1
G54 G1 X1 Y1
G56 G43 H1 G1 X0 Y0
G92.3
G55 G1 X0.5 Y0.5
G28 X1 Y1
G1 X1 Y1
G53 G0 X1 Y1
G49 G1 X0 Y0 Z1
G10 L2 P2 R30 X1
G0 X1 Y1
G3 X0 Y2 R1
G21 G1 X10 Y5
M2
"""


def test_var_and_tool_table_positions_equal_rs274s_machine_positions(tmp_path, files):
    # work systems with rotation (G55 at 25 deg), the current system from 5220, G92 from the program and G92.3,
    # tool offsets in X and Z (G43 H), G28 home from 5161-5163, G53, G10 L2 R, a change of units
    src = tmp_path / "rotated.ngc"
    src.write_text(ROTATED)
    theirs = run_rs274_setup(src, *files, tmp_path / "rs274")
    assert theirs.returncode == 0, theirs.stderr
    prog = parse_program(ROTATED, str(src), setup=_setup(files), require_setup=True)
    ours = prog.end_machine * _mm(prog)
    assert len(theirs.kind) == len(prog)
    # rs274 prints program coordinates and offsets at 4 decimals of the units in force (inch here): a machine
    # coordinate is off by at most the rounding of the position, of G92 and of the G5x offset it adds
    np.testing.assert_allclose(ours, theirs.end, atol=3 * INCH_PRINT_MM, rtol=0)
    assert np.any(prog.rotation == 25.0) and np.any(prog.rotation == 30.0)


def test_program_positions_need_the_setup_and_agree_with_rs274_only_with_it(tmp_path, files):
    # the same program read without the setup (zero offsets, --offsets-zero) is where rs274 is not
    src = tmp_path / "rotated.ngc"
    src.write_text(ROTATED)
    theirs = run_rs274_setup(src, *files, tmp_path / "rs274")
    zero = load_setup(offsets_zero=True)
    prog = parse_program(ROTATED, str(src), setup=zero, require_setup=True)
    assert np.abs(prog.end_machine * _mm(prog) - theirs.end).max() > 50.0


# --- real programs: compensated in machine coordinates -------------------------------------------------------------

def _feed_end_points(text, machine, setup):
    """Programmed feed and arc end points of a program as machine poses (mm), with the setup it runs with."""
    prog = parse_program(text, setup=setup)
    q, rows = machine_rows(prog, machine)
    feed = np.isin(prog.motion[rows], (FEED, ARC_CW, ARC_CCW))
    return q[feed], prog, rows[feed]


@pytest.mark.parametrize("name", ["mtc_cover_rev_a.nc"])
def test_nist_program_with_the_control_files_lands_on_the_nominal_path_in_machine_coordinates(
        tmp_path, machine, files, name):
    setup = _setup(files)
    src_text = (NIST / name).read_text()
    report = {}
    out = compensate(src_text, machine, "geometric", setup=setup, report=report, source=name)
    path = tmp_path / name
    path.write_text(out)
    # rs274 reads the output with the same files: the same machine positions as ours, to its printed digits
    theirs = run_rs274_setup(path, *files, tmp_path / "rs274")
    assert theirs.returncode == 0, theirs.stderr[-2000:]
    out_prog = parse_program(out, setup=setup)
    ours = out_prog.end_machine * _mm(out_prog)
    assert len(theirs.kind) == len(out_prog)
    k = _first_known_row(out_prog)
    np.testing.assert_allclose(ours[k:], theirs.end[k:], atol=2 * INCH_PRINT_MM, rtol=0)
    # every feed end point, through the twin at its machine position, lies on the nominal path within 0.15 um
    q, _, _ = _feed_end_points(out, machine, setup)
    assert q.shape[0] > 1000
    twin = ErrorTwin(machine)
    nominal = nominal_polyline(parse_program(src_text, setup=setup), machine, arc_points=400)
    d_um = distance_to_polyline(twin.actual_pose(q)[0], nominal) * 1e3
    assert d_um.max() < 0.15, d_um.max()
    # the placement matters: compensated as if G54 were zero, the same feeds miss the path by micrometres
    wrong = compensate(src_text, machine, "geometric", offsets_zero=True, source=name)
    q_wrong, _, _ = _feed_end_points(wrong, machine, setup)
    d_wrong = distance_to_polyline(twin.actual_pose(q_wrong)[0], nominal) * 1e3
    assert d_wrong.max() > 5.0
    # the report lists every offset used and where it came from
    used = {u["what"]: u for u in report["setup_used"]}
    assert used["G54"]["values_mm_deg"][:3] == pytest.approx([76.2, 50.8, -203.2])
    assert used["G54"]["source"] == f"{files[0]}:5221-5226,5230"
    assert used["G58"]["source"] == f"{files[0]}:5301-5306,5310"


MM_PROGRAM = """(a mm program: G54 from the control, tool lengths from its table, arcs in two planes)
G21 G17 G90 G94
G54
T1 M6
G43 H1
G0 X10 Y5 Z5
G1 Z-2 F300
G1 X60 Y8
G2 X80 Y28 I0 J20
G1 Y60
G3 X60 Y80 I-20 J0
G18 G2 X40 Z-2 I-10 K0
G17 G1 X10 Y80
G0 Z5
T2 M6
G43 H2
G55 G0 X10 Y10
G1 Z-1 F200
G1 X50 Y30
G3 X50 Y30 I10 J0
G0 Z10
M2
"""


def test_mm_program_read_back_by_rs274_lies_on_the_nominal_path_within_0_15_um(tmp_path, machine, files):
    # rs274 prints 4 decimals of a mm: its own machine positions of the output are checked, not ours. Arcs as
    # straight pieces (--no-arcs): their ends are this test's sample of the path (fitted arcs: the test below)
    setup = _setup(files)
    report = {}
    out = compensate(MM_PROGRAM, machine, "geometric", setup=setup, report=report, arcs=False)
    path = tmp_path / "out.ngc"
    path.write_text(out)
    theirs = run_rs274_setup(path, *files, tmp_path / "rs274")
    assert theirs.returncode == 0, theirs.stderr
    out_prog = parse_program(out, setup=setup)
    assert len(theirs.kind) == len(out_prog)
    feed = np.array([k in ("feed", "arc") for k in theirs.kind]) & (out_prog.kind == ROW_PROGRAMMED)
    assert feed.sum() > 20
    twin = ErrorTwin(machine)
    nominal = nominal_polyline(parse_program(MM_PROGRAM, setup=setup), machine, arc_points=4000)
    d_um = distance_to_polyline(twin.actual_pose(theirs.end[feed][:, :3])[0], nominal) * 1e3
    assert d_um.max() < 0.15, d_um.max()
    whats = [u["what"] for u in report["setup_used"]]
    assert whats == ["G54", "tool 1 offset", "G55", "tool 2 offset"]
    header = out.splitlines()[:8]
    assert header[0].startswith("(trueaxis post: trueaxis ") and header[0].endswith(
        ", mode geometric, machine position-dependent test mill)")
    assert header[2:4] == [f"(trueaxis post: setup {files[0]})", f"(trueaxis post: setup {files[1]})"]
    header = header[3:]
    assert header[1] == f"(trueaxis setup: G54 X76.2 Y50.8 Z-203.2 mm, from {files[0]}:5221-5226,5230)"
    assert header[2] == f"(trueaxis setup: tool 1 offset Z63.5 mm by G43 H1, from {files[1]}:1)"
    assert header[3] == f"(trueaxis setup: G55 X38.1 Y-31.75 Z-165.1 R25 mm, deg, from {files[0]}:5241-5246,5250)"
    assert header[4] == f"(trueaxis setup: tool 2 offset X0.254 Z79.375 mm by G43 H2, from {files[1]}:2)"


def test_fitted_arcs_under_work_offsets_and_a_rotated_system_lie_on_the_nominal_path(tmp_path, machine, files):
    # The same program with its arcs fitted (the default on a three-axis mill): G54, tool lengths, and the G55 system
    # turned by R25 with a full circle. rs274 reads it and ends where we do; the written arcs, sampled along their
    # length and put through the twin in machine coordinates, stay within the tolerance (1 um) of the nominal path.
    from post_checks import points_on_arc

    setup = _setup(files)
    report = {}
    out = compensate(MM_PROGRAM, machine, "geometric", setup=setup, report=report)
    assert report["arcs_fitted"] >= 1
    path = tmp_path / "out.ngc"
    path.write_text(out)
    theirs = run_rs274_setup(path, *files, tmp_path / "rs274")
    assert theirs.returncode == 0, theirs.stderr
    out_prog = parse_program(out, setup=setup)
    assert len(theirs.kind) == len(out_prog)
    mach = out_prog.to_machine(out_prog.end)
    np.testing.assert_allclose(theirs.end[:, :3], mach[:, :3], atol=2e-4)
    twin = ErrorTwin(machine)
    nominal = nominal_polyline(parse_program(MM_PROGRAM, setup=setup), machine, arc_points=4000)
    arcs = np.nonzero(np.isin(out_prog.motion, (2, 3)))[0]
    assert arcs.size > 4  # fitted sub-arcs
    pts = np.vstack([out_prog.to_machine(points_on_arc(out_prog, int(r), 200), np.full(201, r)) for r in arcs])
    d_um = distance_to_polyline(twin.actual_pose(pts[:, :3])[0], nominal) * 1e3
    assert d_um.max() <= 1.0 + 0.03, d_um.max()


# --- refusals ------------------------------------------------------------------------------------------------------

def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "trueaxis.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def machine_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("m") / "mill.toml"
    path.write_text(MACHINE_TOML)
    return path


def test_the_same_program_without_offsets_is_refused_and_accepted_with_offsets_zero(tmp_path, machine_file, files):
    src, out = tmp_path / "cover.nc", tmp_path / "out.nc"
    src.write_text((NIST / "mtc_cover_rev_a.nc").read_text())
    r = run_cli("post", src, "-o", out, "--machine", machine_file)
    assert r.returncode == 3 and not out.exists()
    # (line 5 is the first move: "G0" without axis words, a move of zero length, in the system active at start)
    assert r.stderr.strip() == (f"{src}:5: work offset G54 (X Y Z) was not given: give the control's setup (--var / "
                                "--setup), or --offsets-zero if zero is meant")
    r = run_cli("post", src, "-o", out, "--machine", machine_file, "--offsets-zero")
    assert r.returncode == 0, r.stderr
    lines = out.read_text().splitlines()
    assert lines[:2] == ["%", "O0000(NIST_MTC_CRADA_COVER_REV-A)"]  # the header comes after % and the O number
    assert lines[4:6] == ["(trueaxis post: setup none given)", "(trueaxis post: setup --offsets-zero)"]
    r = run_cli("post", src, "-o", out, "--machine", machine_file, "--var", files[0], "--machine-units", "inch",
                "--report", tmp_path / "r.json")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "r.json").read_text())["setup_used"][0]["what"] == "G54"


def test_a_rotary_offset_not_given_is_refused_when_only_plain_blocks_move_that_axis():
    # A C moved only by plain G1 blocks (read by the compiled runs) were not among the axes the program uses when the
    # setup was checked: G54's A and C, not given, were taken as 0 without a word and the program posted
    from trueaxis.machine import load_machine

    smart = load_machine(ROOT / "fixtures" / "machines" / "smartcnc500.toml")
    text = "G17 G21 G90 G94\nG10 L2 P1 X10 Y5 Z0\nG54 G0 X0 Y0 Z0\nG1 X10 A10 C0 F100\nG1 X20 A20 C5\nG1 X30 A30\nM2\n"
    with pytest.raises(GcodeError, match=r"^<string>:3: work offset G54 \(A C\) was not given"):
        compensate(text, smart)
    report = {}
    compensate(text.replace("Y5 Z0", "Y5 Z0 A0 C0"), smart, report=report)  # given by the program: posts
    assert report["setup_used"][0]["values_mm_deg"] == [10.0, 5.0, 0.0, 0.0, 0.0, 0.0]
    assert report["setup_used"][0]["source"] == "<string>:2 (G10 L2)"


def test_a_tool_length_not_given_is_refused_naming_the_tool(machine, files):
    text = "G21 G90\nG10 L2 P1 X0 Y0 Z0\nG54 G0 X0 Y0 Z0\nT7 M6\nG43 H7\nG1 X10 F100\nM2\n"
    with pytest.raises(GcodeError, match=r"^<string>:6: the length of tool 7 \(G43 H7\) was not given"):
        compensate(text, machine, setup=_setup(files))
    out = compensate(text, machine, setup=_setup(files, offsets_zero=True))
    assert "(trueaxis setup: tool 7 offset 0 mm by G43 H7, from --offsets-zero)" in out
    # a G10 L2 in the program gives the work offset: no setup needed for it
    assert "G54 0 mm, from <string>:2 [G10 L2]" in compensate(text.replace("G43 H7\n", ""), machine)


def test_g92_restored_from_the_control_needs_its_value(machine, files):
    text = "G21 G90\nG10 L2 P1 X0 Y0 Z0\nG54 G0 X0 Y0 Z0\nG92.3\nG1 X10 F100\nM2\n"
    with pytest.raises(GcodeError, match=r"^<string>:5: the G92 shift that G92.3 restores"):
        compensate(text, machine)
    assert "G92 0 mm" in compensate(text, machine, setup=_setup(files))


BAD_VAR_LINES = var_text(WORK_INCH).splitlines()


@pytest.mark.parametrize("what, var, tbl, message", [
    ("missing parameter", "\n".join(l for l in BAD_VAR_LINES if not l.startswith("5242")) + "\n", TOOLS_INCH,
     "params.var: parameter 5242 (G55 X Y Z A B C) is missing"),
    ("non-numeric parameter", "\n".join(l if not l.startswith("5221") else "5221\tabc" for l in BAD_VAR_LINES),
     TOOLS_INCH, "params.var:21: parameter 5221: 'abc' is not a number"),
    ("tool line", var_text(WORK_INCH), "T1 P1 Z2.5\nT2 P2 Zfoo\n", "tools.tbl:2: cannot read 'Zfoo'"),
    ("tool without T", var_text(WORK_INCH), "P1 Z2.5\n", "tools.tbl:1: no T word"),
])
def test_bad_setup_input_gets_one_line_and_exit_3_and_nothing_is_written(tmp_path, machine_file, what, var, tbl,
                                                                          message):
    (tmp_path / "params.var").write_text(var)
    (tmp_path / "tools.tbl").write_text(tbl)
    src, out = tmp_path / "in.ngc", tmp_path / "out.ngc"
    src.write_text(MM_PROGRAM)
    r = run_cli("post", src, "-o", out, "--machine", machine_file, "--var", tmp_path / "params.var",
                "--tool-table", tmp_path / "tools.tbl", "--machine-units", "inch")
    assert r.returncode == 3 and not out.exists()
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and "Traceback" not in r.stderr, r.stderr


def test_a_setup_for_inch_programs_refuses_a_mm_program(tmp_path, machine_file):
    setup = tmp_path / "hurco.toml"
    setup.write_text('[setup]\nunits = "inch"\nprogram_units = "inch"\n[work_offsets]\nG54 = { X = 3, Y = 2, Z = -8 }\n'
                     '[tools]\n1 = { length = 2.5 }\n2 = { length = 3.125 }\n')
    src, out = tmp_path / "in.ngc", tmp_path / "out.ngc"
    src.write_text(MM_PROGRAM.replace("G55", "G54"))
    r = run_cli("post", src, "-o", out, "--machine", machine_file, "--setup", setup)
    assert r.returncode == 3 and not out.exists()
    assert r.stderr.strip().endswith("is for programs in inch") and "the program is in mm (G21)" in r.stderr


# --- setup files for other controls ---------------------------------------------------------------------------------

def test_setup_file_with_tool_length_at_the_tool_change_equals_linuxcnc_with_g43(tmp_path, files):
    # A Hurco program (tool length applied at M6, no G43 in the program) with a setup file giving G54 and the
    # tool's length, against the same program with G43 H23 after the tool change, read by rs274 with the .var and
    # tool table that hold the same values.
    setup = tmp_path / "hurco.toml"
    setup.write_text('[setup]\nname = "Hurco VMX"\nunits = "inch"\nprogram_units = "inch"\ntool_length = "tool_change"\n'
                     '[work_offsets]\nG54 = { X = 3.0, Y = 2.0, Z = -8.0 }\nG58 = { X = 0, Y = 0, Z = 0 }\n'
                     '[tools]\n23 = { length = 1.75, diameter = 0.125 }\n[home]\nG28 = { X = 1, Y = 2, Z = 0.5 }\n')
    text = (NIST / "mtc_cover_rev_a.nc").read_text()
    prog = parse_program(text, setup=read_setup_file(setup), require_setup=True)
    g43 = tmp_path / "g43.nc"
    g43.write_text(text.replace("N120T23M6\n", "N120T23M6\nG43H23\n"))
    theirs = run_rs274_setup(g43, *files, tmp_path / "rs274")
    assert theirs.returncode == 0, theirs.stderr
    assert len(theirs.kind) == len(prog)
    # from the first row where the program has given X, Y and Z (before it rs274 starts at the machine zero, the
    # reader at the program zero: a start position that neither knows)
    k = _first_known_row(prog)
    np.testing.assert_allclose((prog.end_machine * _mm(prog))[k:], theirs.end[k:], atol=2 * INCH_PRINT_MM, rtol=0)
    used = {u["what"]: u for u in prog.setup_used}
    assert used["tool 23 offset"]["applied_by"] == "M6" and used["tool 23 offset"]["source"] == f"{setup}: tools.23"


def test_readers_keep_values_in_mm_with_their_sources(tmp_path, files):
    var = read_var(files[0], "inch")
    assert var.active == 1 and var.work_offsets[2].rotation_deg == 25.0
    np.testing.assert_allclose(var.work_offsets[1].values, [76.2, 50.8, -203.2, 0, 0, 0], rtol=1e-15)
    assert var.home["G28"].values[:3].tolist() == [25.4, 50.8, 12.7]
    tools = read_tool_table(files[1], "mm")
    assert tools.tools[2].offset.tolist() == [0.01, 0, 3.125, 0, 0, 0] and tools.tools[2].diameter == 0.5
    assert tools.tools[23].source == f"{files[1]}:3"
    (tmp_path / "dup.tbl").write_text("T1 P1 Z1\n\nT1 Z2\n")
    with pytest.raises(SetupError, match=r"dup.tbl:3: tool 1 given twice \(first at line 1\)"):
        read_tool_table(tmp_path / "dup.tbl")


def test_the_machine_file_names_a_default_setup(tmp_path):
    (tmp_path / "shop.toml").write_text('[setup]\nunits = "mm"\n[home]\nG28 = { X = 0, Y = 0, Z = 0 }\n'
                                        '[work_offsets]\nG54 = { X = 75, Y = 55, Z = -200 }\n')
    (tmp_path / "mill.toml").write_text(MACHINE_TOML.replace('format = 1\n', 'format = 1\nsetup = "shop.toml"\n'))
    src = tmp_path / "cover.nc"
    src.write_text((NIST / "mtc_cover_rev_a.nc").read_text())
    r = run_cli("post", src, "-o", tmp_path / "out.nc", "--machine", tmp_path / "mill.toml")
    # the program parks in G58, which the shop's setup does not give
    assert r.returncode == 3 and r.stderr.startswith(f"{src}:1463: work offset G58 (X Y Z) was not given")
    (tmp_path / "shop.toml").write_text((tmp_path / "shop.toml").read_text() + "G58 = { X = 0, Y = 0, Z = 0 }\n")
    r = run_cli("post", src, "-o", tmp_path / "out.nc", "--machine", tmp_path / "mill.toml", "--report",
                tmp_path / "r.json")
    assert r.returncode == 0, r.stderr
    used = json.loads((tmp_path / "r.json").read_text())["setup_used"]
    assert used[0]["what"] == "G54" and used[0]["source"] == f"{tmp_path / 'shop.toml'}: work_offsets.G54"
    assert used[0]["values_mm_deg"][:3] == [75.0, 55.0, -200.0]


def test_cadquery_hook_takes_the_setup_as_keywords(machine, files):
    from trueaxis.postproc.hosts import cadquery as hook  # cadquery is a dependency: imported plainly, never skipped

    out = hook.compensate(MM_PROGRAM, machine, "geometric", var=files[0], tool_table=files[1], machine_units="inch")
    assert out == compensate(MM_PROGRAM, machine, "geometric", setup=_setup(files))
    with pytest.raises(GcodeError, match="work offset G54"):
        hook.compensate(MM_PROGRAM, machine, "geometric")


def test_rs274_is_there():
    require_rs274()


def test_a_dynamic_tool_offset_in_the_header_is_no_nested_comment_rs274_refuses(tmp_path, machine, files):
    # G43.1 under a setup is named in the header ("tool offset (G43.1)"): written as is, its parentheses nest in the
    # header's comment and LinuxCNC refuses the whole program ("Nested comment found") though the post exited 0.
    program = "G21 G90 G17 G94\nG54\nT1 M6\nG43 H1\nG0 X10 Y10 Z-10\nG1 X50 Y20 F300\nG49\nG0 Z-100\n" \
              "G43.1 Z10\nG1 X0 Y0 Z-20\nM2\n"
    out = compensate(program, machine, "geometric", setup=_setup(files))
    header = [line for line in out.splitlines() if line.startswith("(trueaxis ")]
    assert any("tool offset [G43.1] Z10 mm by G43.1" in line for line in header), header
    assert all(line.count("(") == 1 and line.count(")") == 1 and line.endswith(")") for line in header)
    path = tmp_path / "out.ngc"
    path.write_text(out)
    theirs = run_rs274_setup(path, *files, tmp_path / "rs274")
    assert theirs.returncode == 0, theirs.stderr
    assert "Nested comment" not in theirs.stderr


@pytest.mark.parametrize("setter", ["G92 X10 Y10 Z0", "G10 L20 P1 X0 Y0 Z0", "G92 X5"])
def test_an_offset_set_from_the_current_position_carries_that_positions_correction(tmp_path, machine, files, setter):
    # G92 and G10 L20 set their offset from the position the control holds: after a compensated move that is the
    # corrected position, so written as given the offset took the correction and every later point was off by it
    # (8-20 um, exit 0, a QA pass). rs274 reads the output: the same machine positions as ours, on the nominal path.
    program = f"G21 G90 G17 G94\nG54\nG0 X30 Y-40 Z-30\n{setter}\nG0 X10 Y10 Z-10\nG1 X50 Y20 Z-20 F500\n" \
              "G2 X80 Y20 I15 J0\nG1 X-50 Y-30\nM2\n"
    setup = _setup(files)
    report = {}
    out = compensate(program, machine, "geometric", setup=setup, report=report, arcs=False)
    written = [line for line in out.splitlines() if line.startswith(setter.split(" X")[0])]
    assert len(written) == 1 and written[0] != setter  # its values carry the correction
    shifted = report["offsets_shifted"]
    assert [(e["line"], e["what"]) for e in shifted] == [(4, "G92" if setter.startswith("G92") else "G10 L20")]
    assert 0 < max(abs(v) for v in shifted[0]["by_program_units"].values()) < 0.05  # a correction: microns
    path = tmp_path / "out.ngc"
    path.write_text(out)
    theirs = run_rs274_setup(path, *files, tmp_path / "rs274")
    assert theirs.returncode == 0, theirs.stderr
    nominal_rs = run_rs274_setup(_write(tmp_path / "in.ngc", program), *files, tmp_path / "rs274_in")
    twin = ErrorTwin(machine)
    nominal = nominal_polyline(parse_program(program, setup=setup), machine)
    moves = [k in ("feed", "arc", "traverse") for k in theirs.kind]
    d_um = distance_to_polyline(twin.actual_pose(theirs.end[moves][:, :3])[0], nominal) * 1e3
    assert d_um.max() < 0.15, d_um.max()
    # and the last point, where the nominal program ends (rs274's reading of the input)
    last_um = np.linalg.norm(twin.actual_pose(theirs.end[-1:, :3])[0] - twin.nominal_pose(nominal_rs.end[-1:, :3])[0])
    assert last_um * 1e3 < 0.15


@pytest.mark.parametrize("change", [
    "G92 X0 Y0", "G92 X10 Y10\nG1 X45 Y-25\nG92.1", "G10 L20 P1 X0 Y0", "G10 L2 P1 X10 Y20 Z-40",
    "G55", "G43 H1", "G20", "G55 G91 G1 X-5 Y10 Z-2"])
@pytest.mark.parametrize("arcs", [False, True])
def test_an_incremental_move_after_a_frame_change_counts_from_the_new_frame(tmp_path, machine, files, change, arcs):
    # A G91 move (or arc) right after anything that changes the program frame -- G92, G92.1, G10 L20, G10 L2 of the
    # active system, another work system (G55 is turned 25 deg here), a tool length, a units switch -- took its
    # increment from the corrected end in the OLD frame: 30 mm after G92 X0 Y0, a 63.5 mm plunge after G43 H1,
    # exit 0 (a QA pass); an arc's start after it likewise (a G90 arc's I J count from it). rs274 reads the output:
    # every point on the nominal path, and the same last point; the arcs kept as arcs or written as lines.
    program = (f"G21 G90 G17 G94\nG54\nG0 X30 Y-40 Z-30\nG1 X40 Y-30 F500\n{change}\nG91 G1 X-5 Y10 Z-2\n"
               "G2 X10 Y0 I5 J0\nG1 X3 Y-4\nG3 X-10 Y0 I-5 J0\nG90\nG92 X0 Y0\nG2 X10 Y0 I5 J0\nM2\n")
    setup = _setup(files)
    out = compensate(program, machine, "geometric", setup=setup, arcs=arcs)
    theirs = run_rs274_setup(_write(tmp_path / "out.ngc", out), *files, tmp_path / "rs274")
    assert theirs.returncode == 0, theirs.stderr
    nominal_rs = run_rs274_setup(_write(tmp_path / "in.ngc", program), *files, tmp_path / "rs274_in")
    twin = ErrorTwin(machine)
    nominal = nominal_polyline(parse_program(program, setup=setup), machine)
    # Our own reading of the output is exact; rs274 prints 4 decimals of the program's units (1.27 um in inch).
    q, _ = machine_rows(parse_program(out, setup=setup), machine)
    ours_um = distance_to_polyline(twin.actual_pose(q)[0], nominal) * 1e3
    assert ours_um.max() < 0.15, ours_um.max()
    print_um = 2e3 * INCH_PRINT_MM if change == "G20" else 0.15
    moves = [k in ("feed", "arc", "traverse") for k in theirs.kind]
    d_um = distance_to_polyline(twin.actual_pose(theirs.end[moves][:, :3])[0], nominal) * 1e3
    assert d_um.max() < print_um, d_um.max()
    last_um = np.linalg.norm(twin.actual_pose(theirs.end[-1:, :3])[0] - twin.nominal_pose(nominal_rs.end[-1:, :3])[0])
    assert last_um * 1e3 < print_um


def _write(path, text):
    path.write_text(text)
    return path


def test_tool_length_offsets_are_said_with_the_tip_error_per_10_mm_they_leave(tmp_path, machine, files):
    # The twin's errors are those of its reference tool; a tool of another length moves the tip by the length
    # difference times the tool-axis error, which the post does not correct (the shop's tool-length convention is not
    # known to it). It exited 0 without a word (a QA pass: the machine file's tool length changed nothing): now said,
    # with the twin's largest tool-axis error on the program's moves, checked here at rs274's machine positions.
    setup = _setup(files)
    report = {}
    out = compensate(MM_PROGRAM, machine, "geometric", setup=setup, report=report, arcs=False)
    said = [w for w in report["warnings"] if "tool length offsets in force" in w]
    assert len(said) == 1 and "tool 1 offset Z63.5 mm" in said[0], report["warnings"]
    src = tmp_path / "in.ngc"
    src.write_text(MM_PROGRAM)
    theirs = run_rs274_setup(src, *files, tmp_path / "rs274")
    twin = ErrorTwin(machine)
    q = theirs.end[[k in ("feed", "arc", "traverse") for k in theirs.kind]][:, :3]
    du = np.linalg.norm(twin.actual_pose(q)[1] - twin.nominal_pose(q)[1], axis=1) * 1e6
    assert du.max() > 1.0  # the machine's angular errors: the figure can be wrong
    assert report["tool_axis_error_max_urad"] == pytest.approx(du.max(), rel=0.05)
    assert f"up to {du.max() * 0.01:.2f} um per 10 mm" in said[0] or \
        f"up to {report['tool_axis_error_max_urad'] * 0.01:.2f} um per 10 mm" in said[0]
    plain = {}  # without tool length offsets: nothing to say
    compensate(MM_PROGRAM.replace("G43 H1", "G49").replace("G43 H2", "G49"), machine, "geometric", setup=setup,
               report=plain, arcs=False)
    assert not any("tool length offsets" in w for w in plain["warnings"]) and plain["tool_axis_error_max_urad"] is None


@pytest.mark.parametrize("program, lost", [
    ("G21 G90\nG92 X0 Y0 Z0\nG0 X10 Y10 Z-20\nG1 X20 Y5 Z-30 F100\nM2\n", "X Y Z"),  # the classic start-of-program G92
    ("G21 G90\nG0 Z-20\nG92 X0 Y0\nG0 X10 Y10\nG1 X20 Y5 Z-30 F100\nM2\n", "X Y"),
    ("G21 G90\nG0 Z-20\nG10 L20 P1 X0\nG0 X10 Y10\nM2\n", "X"),
])
def test_an_offset_set_from_a_position_the_program_never_gave_is_refused(machine, program, lost):
    # The control's position when the program starts is not in the program: a G92 (or G10 L20) set from it was
    # taken as set from the program's zero, without a word (the offset and every machine position after it invented)
    with pytest.raises(Exception, match=rf"<string>:\d: G\S+( L20)? sets its offset from the position of {lost}, "
                                        "which the program has not given before it"):
        compensate(program, machine, "geometric", offsets_zero=True)


def test_a_program_without_g20_or_g21_on_an_inch_control_is_refused_not_read_as_mm(machine, tmp_path):
    # A QA pass: --var in inch (--machine-units inch) and a program that never says G20 / G21: read as mm and
    # corrected there (Y3 -> Y2.98107, exit 0), where LinuxCNC starts in its machine units and reads Y3 in inches. Now
    # refused naming the first position; with G20 (or G21) stated first it posts; an mm control reads mm as before.
    from trueaxis.postproc.post import PostError

    (tmp_path / "inch.var").write_text(var_text({1: [-4.330709, 0.0, -11.811024, 0.0, 0.0, 0.0]}))
    (tmp_path / "mm.var").write_text(var_text({1: [-110.0, 0.0, -300.0, 0.0, 0.0, 0.0]}))
    program = "G90 G17 G94 G54\nG0 X0 Y3 Z0.8\nG1 Z-0.1 F30\nG1 X8 Y3\nM30\n"
    inch = {"var": tmp_path / "inch.var", "machine_units": "inch"}
    with pytest.raises(PostError, match=r"^in.ngc:2: a position before the program states its units \(G20 / G21\), "
                                        r"for a control whose machine units are inches"):
        compensate(program, machine, source="in.ngc", **inch)
    for units in ("G20", "G21"):
        stated = program.replace("G90", f"{units} G90", 1)
        assert compensate(stated, machine, **inch) != stated
    late = program.replace("G1 Z-0.1 F30", "G20\nG1 Z-0.1 F30")  # stated after the first position: too late
    with pytest.raises(PostError, match=r"^in.ngc:2: a position before the program states its units"):
        compensate(late, machine, source="in.ngc", **inch)
    assert compensate(program, machine, var=tmp_path / "mm.var") != program  # an mm control reads mm
    # a setup file for inch programs: said as the units not stated (it was "the program is in mm (G21)")
    (tmp_path / "setup.toml").write_text('[setup]\nunits = "inch"\nprogram_units = "inch"\n[work_offsets]\n'
                                         'G54 = { X = -4.330709, Y = 0, Z = -11.811024 }\n')
    with pytest.raises(SetupError, match=r"^in.ngc:2: a position before the program states its units \(G20 / G21\), "
                                         r"read as mm, and the setup .* is for programs in inch"):
        compensate(program, machine, source="in.ngc", setup=tmp_path / "setup.toml")
