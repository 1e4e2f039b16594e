"""The three-axis post: compensated programs put the actual tool on the nominal path; dialect and safety rules."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from conftest import MACHINES, ROOT
from post_checks import actual_points, distance_to_polyline, machine_rows, nominal_polyline
from rs274_helpers import assert_rs274_reads_as_we_do, run_rs274
from trueaxis.machine import ErrorTwin, load_machine, parse_machine
from trueaxis.nc.gcode import parse_program
from hypothesis import given, settings
from hypothesis import strategies as st

from trueaxis.postproc import post as post_module
from trueaxis.postproc.post import PostError, _rewrite_plain, _rewrite_tokens, compensate, without_header

XH714 = MACHINES / "xh714.toml"

PROGRAM = """%
(test program: plunge, lines, arcs, incremental move, canned cycle)
G21 G90 G17 G94
N10 G0 X0 Y0 Z-10
N20 G1 Z-105 F300 (plunge)
N30 G1 X150 Y80
N40 G2 X100 Y30 I-50 J0
N50 X50 Y80 I0 J50
N60 G91 G1 X-20 Y-10
N70 G90 G0 Z-20
N80 G98 G81 X10 Y10 Z-103 R-98
N90 X20 Y15
N100 G80
M2
%
"""


@pytest.fixture(scope="module")
def xh714():
    return load_machine(XH714)


@pytest.fixture(scope="module")
def posted(xh714):
    report = {}
    out = compensate(PROGRAM, xh714, "geometric", tol_um=1.0, report=report)
    return out, report


def test_every_output_end_point_lands_on_the_nominal_path(xh714, posted):
    out, _ = posted
    actual, _, _ = actual_points(out, xh714)
    nominal = nominal_polyline(parse_program(PROGRAM), xh714)
    d_um = distance_to_polyline(actual, nominal) * 1e3
    # 0.1 um is the bound; the written numbers (5 decimals, 0.005 um) and the solver (0.01 um) stay below it.
    assert d_um.max() < 0.1, d_um.max()


def test_programmed_end_points_land_exactly_where_the_nominal_program_goes(xh714, posted):
    out, _ = posted
    nominal = parse_program(PROGRAM)
    q_nom, _ = machine_rows(nominal, xh714)
    actual, prog_out, rows_out = actual_points(out, xh714)
    # Lines with N words are the original blocks: compare their end points one to one.
    def numbered_ends(prog, pts, rows):
        lines = [prog.lines[prog.line_index[r]].split()[0] for r in rows]
        return {ln: pts[k] for k, ln in enumerate(lines) if ln.startswith("N") and ln not in ("N40", "N50")}
    twin = ErrorTwin(xh714)
    want = numbered_ends(nominal, twin.nominal_pose(q_nom)[0], np.nonzero(nominal.kind == 0)[0])
    got = numbered_ends(prog_out, actual, rows_out)
    for key in ("N10", "N60", "N70"):
        np.testing.assert_allclose(got[key], want[key], atol=1e-4 * 1e-3 * 1e3)


def test_the_actual_path_between_output_points_stays_within_tolerance(xh714, posted):
    out, report = posted
    prog = parse_program(out)
    q, rows = machine_rows(prog, xh714)
    twin = ErrorTwin(xh714)
    feed = prog.motion[rows] == 1
    q_prev = np.vstack([q[:1], q[:-1]])
    mid = 0.5 * (q + q_prev)[feed]
    actual_mid = twin.actual_pose(mid)[0]
    nominal = nominal_polyline(parse_program(PROGRAM), xh714)
    d_um = distance_to_polyline(actual_mid, nominal) * 1e3
    assert d_um.max() <= report["tol_um"] * 1.05
    assert report["moves_split"] >= 1


def test_rs274_reads_the_compensated_program(tmp_path, posted):
    out, _ = posted
    assert_rs274_reads_as_we_do(out, tmp_path)


def test_identical_input_gives_byte_identical_output(xh714, posted):
    again = compensate(PROGRAM, xh714, "geometric", tol_um=1.0)
    assert again == posted[0]


def test_comments_line_numbers_and_non_motion_blocks_are_kept(posted):
    out, _ = posted
    for keep in ("%", "(test program: plunge, lines, arcs, incremental move, canned cycle)", "G21 G90 G17 G94",
                 "N100 G80", "M2"):
        assert keep + "\n" in out
    assert "(plunge)" in out
    for n in ("N10 ", "N20 ", "N30 ", "N60 ", "N80 ", "N90 "):
        assert out.count(n) == 1


def test_every_compensated_motion_block_carries_all_its_axis_words(posted):
    out, _ = posted
    prog = parse_program(out)
    for r in np.nonzero(prog.kind == 0)[0]:
        code = prog.lines[prog.line_index[r]].split("(")[0].upper()
        letters = {w[0] for w in code.split()}
        assert {"X", "Y", "Z"} <= letters, code


def test_incremental_move_carries_the_corrected_increment(xh714, posted):
    out, _ = posted
    line = next(ln for ln in out.splitlines() if ln.startswith("N60"))
    words = dict((w[0], float(w[1:])) for w in line.split()[3:])
    assert abs(words["X"] + 20) < 0.02 and abs(words["Y"] + 10) < 0.02 and words["X"] != -20


def test_canned_cycle_hole_position_and_depth_are_corrected(xh714, posted):
    out, _ = posted
    line = next(ln for ln in out.splitlines() if ln.startswith("N80"))
    w = {t[0]: float(t[1:]) for t in line.split() if t[0] in "XYZR"}
    twin = ErrorTwin(xh714)
    # The twin works in the part frame: compare actual and nominal poses there (xh714's part origin is Z -300).
    hole_nominal, _ = twin.nominal_pose(np.array([[10.0, 10.0, -103.0]]))
    r_nominal, _ = twin.nominal_pose(np.array([[10.0, 10.0, -98.0]]))
    np.testing.assert_allclose(twin.actual_pose(np.array([[w["X"], w["Y"], w["Z"]]]))[0], hole_nominal, atol=1e-5)
    # R is corrected for its own level; X and Y are the hole's, so only the height is checked at R.
    np.testing.assert_allclose(twin.actual_pose(np.array([[w["X"], w["Y"], w["R"]]]))[0][0, 2], r_nominal[0, 2],
                               atol=2e-4)


def test_arcs_stay_arcs_when_the_correction_is_constant():
    text = (MACHINES / "xh714.toml").read_text()
    # A machine whose only error is a constant offset of the X positioning: the correction is the same everywhere.
    const = parse_machine(text.split("[location]")[0].replace("[loaded]", "[x]")
                          + "[component.X]\nat = [-200.0, 200.0]\nEXX = [3.0, 3.0]\n", source="const")
    report = {}
    out = compensate(PROGRAM, const, "geometric", report=report)
    assert report["arcs_kept"] == 2 and report["arcs_linearised"] == 0
    n40 = next(ln for ln in out.splitlines() if ln.startswith("N40"))
    assert "G2" in n40 and "I-50" in n40 and "X99.997" in n40


def test_kept_arc_with_absolute_centres_gets_its_centre_corrected(tmp_path):
    # G90.1: I J are the centre's coordinates, which move with the (constant) correction like the end point does.
    text = (MACHINES / "xh714.toml").read_text()
    const = parse_machine(text.split("[location]")[0].replace("[loaded]", "[x]")
                          + "[component.X]\nat = [-200.0, 200.0]\nEXX = [3.0, 3.0]\n", source="const")
    program = "G21 G90 G90.1 G17\nG0 X150 Y80 Z-100\nG1 Z-105 F300\nG2 X100 Y30 I100 J80\nM2\n"
    report = {}
    out = compensate(program, const, "geometric", report=report)
    assert report["arcs_kept"] == 1
    arc = without_header(out).splitlines()[3]  # the header comment (machine, mode, setup) comes first
    assert "G2" in arc and "X99.997" in arc and "I99.997" in arc and "J80" in arc, arc
    assert_rs274_reads_as_we_do(out, tmp_path)


_WORD = st.builds(lambda v: f"{v:.4f}".rstrip("0").rstrip("."), st.floats(-999, 999))


@settings(max_examples=300, deadline=None)
@given(st.booleans(), st.sampled_from(["", "G0", "G1", "G01", "g1", "G2", "G03"]),
       st.lists(st.sampled_from("XYZABCIJK"), unique=True), st.booleans(), st.booleans(), _WORD,
       st.sampled_from([0, 1, 2, 3]), st.booleans(), st.sampled_from([" ", ""]))
def test_the_writers_fast_path_writes_what_the_token_walk_writes(n, g, letters, r, f, value, motion, arc, sep):
    letters = sorted(letters, key="XYZABCIJK".index)
    words = [w for w in ["N120" if n else "", g] if w] + [c + value for c in letters]
    words += ["R" + value] if r else []
    words += ["F" + value] if f else []
    code = sep.join(words)
    new = ["X1.5", "Y-2", "Z0.25"]
    plain = _rewrite_plain(code, motion, new, arc, sep)
    assert plain is not None, code
    assert plain == _rewrite_tokens(code, motion, new, arc, True, sep)


def test_the_post_in_small_chunks_writes_what_it_writes_in_one(xh714, monkeypatch):
    # Moves are compensated and written chunk by chunk (bounded memory): chunk borders must not change what is written
    # beyond the solver's own tolerance (its batch decides how many Newton steps each pose gets).
    whole = compensate(PROGRAM, xh714, "geometric")
    monkeypatch.setattr(post_module, "ROW_CHUNK", 3)
    monkeypatch.setattr(post_module, "WRITE_WINDOW", 2)
    chunked = compensate(PROGRAM, xh714, "geometric")
    a, b = parse_program(whole), parse_program(chunked)
    assert len(a.lines) == len(b.lines)
    assert np.abs(a.end - b.end).max() < 2e-5  # 0.02 um: the solver's tolerance, plus the last written digit


def test_mode_none_returns_the_input_unchanged_under_the_header(xh714):
    out = compensate(PROGRAM, xh714, "none")
    assert without_header(out) == PROGRAM
    assert out.splitlines()[1].startswith("(trueaxis post: trueaxis ") and "mode none" in out.splitlines()[1]


def test_a_correction_above_the_bound_stops_with_the_block_named(xh714):
    with pytest.raises(PostError) as info:
        compensate(PROGRAM, xh714, "geometric", max_correction_mm=0.005)
    assert str(info.value).startswith("<string>:") and "above the bound" in str(info.value)


def test_a_position_outside_the_travel_stops_with_the_block_named(xh714):
    with pytest.raises(PostError) as info:
        compensate(PROGRAM.replace("N70 G90 G0 Z-20", "N70 G90 G0 X250 Z-20"), xh714, "geometric")
    assert "<string>:10:" in str(info.value) and "outside its travel" in str(info.value)


def test_a_program_for_axes_the_machine_lacks_is_refused(xh714):
    with pytest.raises(PostError) as info:
        compensate("G21 G90\nG1 X1 Y1 Z-10 A30 F100\nM2\n", xh714, "geometric")
    assert "<string>:2:" in str(info.value) and "axis A" in str(info.value)


@pytest.mark.parametrize("data, reason", [(b"", "empty"), (b"\x00\x01\x02G1 X1", "binary")])
def test_cli_refuses_empty_and_binary_files_with_exit_3_and_writes_nothing(tmp_path, data, reason):
    src = tmp_path / "in.ngc"
    src.write_bytes(data)
    out = tmp_path / "out.ngc"
    r = subprocess.run([sys.executable, "-m", "trueaxis.cli", "post", str(src), "-o", str(out), "--machine",
                        str(XH714)], capture_output=True, text=True)
    assert r.returncode == 3 and reason in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_cli_writes_program_and_report(tmp_path):
    src = tmp_path / "in.ngc"
    src.write_text(PROGRAM)
    out, rep = tmp_path / "out.ngc", tmp_path / "r.json"
    r = subprocess.run([sys.executable, "-m", "trueaxis.cli", "post", str(src), "-o", str(out), "--machine",
                        str(XH714), "--report", str(rep)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    report = json.loads(rep.read_text())
    assert report["blocks_in"] == len(PROGRAM.splitlines())
    assert report["blocks_out"] == len(out.read_text().splitlines())
    # the summary says how many of the blocks out are the header's comments (7 blocks in were "11 out", a QA pass)
    header = [ln for ln in out.read_text().splitlines() if ln.startswith(("(trueaxis post: ", "(trueaxis setup: "))]
    assert report["header_blocks"] == len(header) > 0
    assert (f"{report['blocks_in']} blocks in, {report['blocks_out']} out ({len(header)} header comments); "
            in r.stdout), r.stdout
    assert set(report["correction"]) == {"X", "Y", "Z"}
    assert report["max_residual_um"] < 0.01


def test_comprehensive_mode_cancels_the_force_induced_error_too(xh714):
    prog = PROGRAM.replace("N30 G1 X150 Y80", "(trueaxis: ap=0.6 ae=7 fz=0.2 n=1200 d=10 z=4 mode=down)\nN30 G1 X150 Y80")
    report = {}
    out = compensate(prog, xh714, "comprehensive", report=report)
    geo = compensate(prog, xh714, "geometric")
    assert out != geo
    # The N30 end point, cut with the force of its own conditions, lands on the nominal point.
    from trueaxis.machine.cutting_force import CuttingCoefficients, CuttingConditions, mean_force

    f_feed = mean_force(CuttingCoefficients.from_mapping(xh714.cutting),
                        CuttingConditions.from_mapping({"ap": 0.6, "ae": 7, "fz": 0.2, "n": 1200, "d": 10, "z": 4}))
    x = np.array([150.0, 80.0, 0.0]) / np.hypot(150.0, 80.0)
    y = np.cross([0, 0, 1.0], x)
    force = f_feed[0] * x + f_feed[1] * y + f_feed[2] * np.array([0, 0, 1.0])
    line = next(ln for ln in out.splitlines() if ln.startswith("N30"))
    w = {t[0]: float(t[1:]) for t in line.split() if t[0] in "XYZ"}
    # N30 is split: its first piece; compare with the nominal point at the same fraction of the move.
    q = np.array([[w["X"], w["Y"], w["Z"]]])
    twin = ErrorTwin(xh714)
    p_act = twin.actual_pose(q, force_n=force)[0][0]
    start, end = twin.nominal_pose(np.array([[0, 0, -105.0], [150, 80, -105.0]]))[0]
    t = np.dot(p_act - start, end - start) / np.dot(end - start, end - start)
    np.testing.assert_allclose(p_act, start + t * (end - start), atol=1e-4)


def test_comprehensive_mode_without_conditions_is_refused(xh714):
    with pytest.raises(PostError) as info:
        compensate(PROGRAM, xh714, "comprehensive")
    assert "cutting conditions" in str(info.value)


@pytest.mark.external
@pytest.mark.parametrize("name", ["mtc_cover_rev_a.nc", "mtc_plate_1.nc"])
def test_nist_inch_programs_post_and_rs274_reads_them(tmp_path, name):
    # A three-axis machine with the xh714 errors and enough travel for the NIST parts (their work offsets are
    # unknown, so program coordinates are machine coordinates here: --offsets-zero, said explicitly).
    text = XH714.read_text().replace("[-200.0, 200.0]", "[-2000.0, 2000.0]").replace(
        "[-150.0, 150.0]", "[-2000.0, 2000.0]").replace("[-400.0, 0.0]", "[-2000.0, 2000.0]")
    m = parse_machine(text, source="xh714-wide")
    src = (ROOT / "fixtures" / "programs" / "nist" / name).read_text(errors="replace")
    report = {}
    out = compensate(src, m, "geometric", report=report, offsets_zero=True)
    assert "inch" in report["units_note"]
    path = tmp_path / name
    path.write_text(out)
    moves = run_rs274(path, {t: 0.0 for t in range(1, 40)}, tmp_path)
    assert moves.returncode == 0, moves.stderr[-2000:]
    actual, out_prog, out_rows = actual_points(out, m)
    # the blocks before the program has given every axis, at its start and after each tool change (M6: a control may
    # lift Z first), are left as written (uncompensated): not checked
    src_lines = src.splitlines()
    changes = [i + 1 for i, line in enumerate(src_lines) if re.search(r"M0?6(?!\d)", line.split("(")[0])]
    left = report["uncompensated"]
    at_start = [u for u in left if "since" not in u]
    assert len(at_start) <= 2 and len(left) <= len(at_start) + len(changes)
    for u in left:
        if "since" in u:  # the first block after a tool change, or the next ones before every axis is given
            change = max(c for c in changes if c < u["line"])
            assert u["since"] == f"the tool change M6 at line {change}" and u["line"] - change <= 2, u
    left_text = {src_lines[u["line"] - 1].strip() for u in left}
    keep = np.array([out_prog.lines[out_prog.line_index[r]].strip() not in left_text for r in out_rows])
    assert (~keep).sum() == len([r for r in np.nonzero(parse_program(src).kind == 0)[0]
                                 if parse_program(src).line_no[r] in {u["line"] for u in left}])
    actual = actual[keep]
    nominal = nominal_polyline(parse_program(src), m, arc_points=400)
    # arcs sampled at 400 points: sagitta of a 2-inch arc over 1/400 of a turn is about 0.3 um; check with that slack
    d_um = distance_to_polyline(actual, nominal) * 1e3
    assert np.percentile(d_um, 99) < 0.1 and d_um.max() < 0.5


BLOCK_DELETE = """G21 G90 G17 G94
G0 X10 Y10 Z-100
G1 X20 F300
/G1 X180 Y120
G1 X50 Y20
/G2 X80 Y20 I15 J0
G1 X60 Y40
M2
"""


@pytest.mark.parametrize("switch", [(), ("-b",)])
def test_a_split_block_delete_move_is_skipped_whole_with_the_switch_on(tmp_path, xh714, switch):
    # The long '/' move is split: its pieces after the first were written without the '/', so with the block-delete
    # switch on the control skipped the first piece only and went to X180 Y120 anyway. Now every piece carries it:
    # rs274 reads the output with the switch off and on, and the twin's actual end points equal the input's nominal
    # ones read the same way.
    report = {}
    out = compensate(BLOCK_DELETE, xh714, "geometric", tol_um=1.0, report=report)
    assert report["moves_split"] >= 1
    assert any("block delete" in w and ":4:" in w for w in report["warnings"])
    (tmp_path / "in.ngc").write_text(BLOCK_DELETE)
    (tmp_path / "out.ngc").write_text(out)
    nominal = run_rs274(tmp_path / "in.ngc", {}, tmp_path / "rs_in", switch)
    written = run_rs274(tmp_path / "out.ngc", {}, tmp_path / "rs_out", switch)
    assert nominal.returncode == 0 and written.returncode == 0, written.stderr
    twin = ErrorTwin(xh714)
    ends = twin.nominal_pose(nominal.end[:, :3])[0]
    # the output's moves (split pieces in between) pass through the input's ends in order, each to rs274's 4 decimals
    actual = twin.actual_pose(written.end[:, :3])[0]
    hits = [int(np.argmin(np.linalg.norm(actual - e, axis=1))) for e in ends]
    assert hits == sorted(hits)
    d_um = np.array([np.linalg.norm(actual[h] - e) for h, e in zip(hits, ends)]) * 1e3
    assert d_um.max() < 0.15, d_um.max()
    far = np.abs(written.end[:, 0] - 180).min()
    assert (far < 1) == (not switch)  # the X180 move is run with the switch off only


@pytest.mark.parametrize("comment_length, refused", [(240, True), (120, False)])
def test_a_block_the_rewrite_makes_longer_than_linuxcnc_reads_is_refused(tmp_path, comment_length, refused):
    # The input line (249 characters) is read by rs274; rewritten with its corrected words (decimals, a Z word) it
    # became 275, and LinuxCNC refuses such a program whole ("Command too long") while the post exited 0.
    line = "G1 X60 (" + "x" * comment_length + ")"
    text = "G21 G90 G17 G94\nG0 X10 Y10 Z-100\nG1 X50 Y20 F300\n" + line + "\nM2\n"
    src, out = tmp_path / "in.ngc", tmp_path / "out.ngc"
    src.write_text(text)
    (tmp_path / "rs_in").mkdir()
    assert run_rs274(src, {}, tmp_path / "rs_in").returncode == 0  # the input is a program LinuxCNC reads
    r = subprocess.run([sys.executable, "-m", "trueaxis.cli", "post", str(src), "-o", str(out), "--machine",
                        str(XH714), "--offsets-zero"], capture_output=True, text=True)
    if refused:
        assert r.returncode == 3 and not out.exists()
        assert f"{src}:4: the compensated block is " in r.stderr and "over the 255 LinuxCNC reads" in r.stderr
    else:
        assert r.returncode == 0, r.stderr
        assert max(map(len, out.read_text().splitlines())) <= 255
        assert run_rs274(out, {}, tmp_path / "rs_out").returncode == 0


def test_a_canned_cycles_deviation_above_its_bottom_is_reported_and_checked_by_the_twin(xh714, posted):
    # A cycle writes one X Y per hole, corrected at the bottom; at the R plane the twin's error differs (2 um on this
    # machine, a QA pass found it reported as 0). The report's figure against the twin itself: the actual tip at the
    # written hole X Y and R level, less the nominal one at the programmed X Y and R, horizontally.
    out, report = posted
    twin = ErrorTwin(xh714)
    holes = [(10.0, 10.0), (20.0, 15.0)]  # N80 and N90, R-98 (G21: mm)
    lines = [ln for ln in without_header(out).splitlines() if ln.startswith(("N80", "N90"))]
    got = []
    for (xn, yn), line in zip(holes, lines):
        words = dict(re.findall(r"([XYZR])(-?[\d.]+)", line))
        xw, yw = float(words["X"]), float(words["Y"])
        rw = float(re.search(r"R(-?[\d.]+)", lines[0]).group(1))  # (R is modal: N80's)
        actual = twin.actual_pose(np.array([[xw, yw, rw]]))[0][0]
        nominal = twin.nominal_pose(np.array([[xn, yn, -98.0]]))[0][0]
        got.append(np.hypot(*(actual - nominal)[:2]) * 1e3)
    assert max(got) > 0.2  # the errors change along Z on this machine: the check can fail
    assert abs(report["max_cycle_deviation_um"] - max(got)) < 0.05, (report["max_cycle_deviation_um"], got)


def test_the_hook_says_a_mistyped_file_name_is_no_file(xh714, tmp_path):
    # compensate('nonexistent_file.ngc', m) read the name as G-code: "word 'n' with no number" (a QA pass)
    with pytest.raises(FileNotFoundError, match="nonexistent_file.ngc: no such file"):
        compensate(str(tmp_path / "nonexistent_file.ngc"), xh714)
    one_line = compensate("G21 G90 G0 X10 Y10 Z-100", xh714, offsets_zero=True)  # a one-line program stays one
    assert "G0 X10.00" in one_line
