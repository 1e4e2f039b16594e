"""The G-code reader (trueaxis.nc.gcode): syntax, LinuxCNC semantics, errors, fuzzing, rs274 conformance."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trueaxis.nc.gcode import (
    ARC_CCW, ARC_CW, FEED, RAPID, ROW_CYCLE, ROW_REFERENCE, GcodeError, parse_file, parse_program,
    parse_tool_table, word_spans, write_number, write_numbers,
)

from rs274_helpers import PRINT_DECIMALS, run_rs274

PROGRAMS = Path(__file__).resolve().parents[1] / "fixtures" / "programs"
NIST = PROGRAMS / "nist"
# tool lengths (mm) for every tool the fixture programs use
TOOLS_MM = {t: 10.0 + 2.5 * t for t in range(0, 40)}
# rs274 prints 4 decimals: agreement within half a unit of the last digit, plus float noise
PRINT_TOL = 0.5 * 10.0 ** -PRINT_DECIMALS + 1e-9


def test_lines_reproduce_the_text_byte_for_byte():
    text = (NIST / "mtc_cover_rev_a.nc").read_bytes().decode("iso-8859-1")
    prog = parse_program(text, "mtc")
    assert "".join(prog.lines) == text


def test_a_flattened_program_keeps_every_line_without_macros_byte_for_byte():
    text = (NIST / "d2mi_827-9999-904_op1.nc").read_bytes().decode("iso-8859-1")
    prog = parse_program(text, "d2mi", passthrough_unsupported=True)  # its G41: the control's part
    src = text.splitlines(keepends=True)
    # the note after its leading '%' and program number (LinuxCNC reads a '%' only as the first line)
    assert prog.lines[:2] == src[:2] and prog.lines[2].startswith("(flattened by trueaxis")
    kept = [line for k, (line, n) in enumerate(zip(prog.lines, prog.source_line)) if k != 2 and "#" not in src[n - 1]]
    assert kept == [line for line in src if "#" not in line][:len(kept)]
    assert len(kept) > 1000


def test_inch_program_positions_stay_in_inches():
    prog = parse_file(NIST / "mtc_plate_1.nc")
    assert prog.units == "inch" and prog.inch.all()
    assert prog.axes_present == "XYZ"
    # N130G0G90G54X7.25Y-1.5S5000M3 is the first positioning move after the G0 of N110
    row = np.nonzero(prog.line_no == 13)[0][0]
    np.testing.assert_allclose(prog.end[row, :3], [7.25, -1.5, 0.0])


def test_modal_motion_and_incremental_positions():
    prog = parse_program("G21 G90\nG0 X1 Y2\nX3\nG91 G1 X1 Y-1 F100\nY-1\nG90 G0 Z5\n")
    np.testing.assert_allclose(prog.end[:, :3], [[1, 2, 0], [3, 2, 0], [4, 1, 0], [4, 0, 0], [4, 0, 5]])
    np.testing.assert_array_equal(prog.motion, [RAPID, RAPID, FEED, FEED, RAPID])
    np.testing.assert_allclose(prog.start[1:], prog.end[:-1])
    assert prog.feed[2] == 100.0


def test_comments_line_numbers_and_block_delete_are_tokenized():
    prog = parse_program("%\nO0001(PART)\nN10 G21 (units) G0 X1 ; trailing\n/N20 G0 X2\n%\nG0 X9\n")
    np.testing.assert_allclose(prog.end[:, 0], [1.0, 2.0])  # after the closing % nothing is interpreted


def test_distance_modes_are_recorded_per_row_and_comments_do_not_set_them():
    prog = parse_program("G21 G90\nG1 X1 F100 (G91 in a comment)\nG91 G1 X1 ; G90\nX2\nG90.1 G90 X3\n"
                         "G2 X4 I3.5 J0 ; G91.1\nG91.1 g91 G1 X1\n")
    assert prog.incremental.tolist() == [False, True, True, False, False, True]
    assert prog.arc_incremental.tolist() == [True, True, True, False, False, True]


def test_arc_centre_from_ijk_and_r_agree():
    ijk = parse_program("G21 G17 F100\nG0 X0 Y0\nG2 X10 Y0 I5 J0\n")
    r = parse_program("G21 G17 F100\nG0 X0 Y0\nG2 X10 Y0 R5\n")
    np.testing.assert_allclose(ijk.arc_center[-1], [5, 0, 0])
    np.testing.assert_allclose(r.arc_center[-1], [5, 0, 0], atol=1e-12)
    assert ijk.motion[-1] == ARC_CW and ijk.arc_plane[-1] == 17 and ijk.arc_turns[-1] == 1


def test_full_circle_with_turns():
    prog = parse_program("G21 F100\nG0 X0 Y0\nG3 X0 Y0 I5 J0 P3\n")
    assert prog.motion[-1] == ARC_CCW and prog.arc_turns[-1] == 3
    np.testing.assert_allclose(prog.arc_center[-1], [5, 0, 0])


def test_work_offset_and_tool_length_go_into_offset_not_positions():
    prog = parse_program("G21\nG10 L2 P2 X10 Y20 Z30\nG55 G0 X1 Y1 Z1\nT3 M6\nG43 H3 G0 Z1\n",
                         tool_table={3: 50.0})
    np.testing.assert_allclose(prog.end[-1, :3], [1, 1, 1])
    np.testing.assert_allclose(prog.offset[-1, :3], [10, 20, 80])
    np.testing.assert_allclose(prog.end_machine[-1, :3], [11, 21, 81])


def test_g28_rows_are_marked_and_return_to_machine_zero():
    prog = parse_program("G21\nG10 L2 P1 Z5\nG0 X1 Y1 Z1\nG91 G28 Z0\n")
    assert list(prog.kind[-2:]) == [ROW_REFERENCE, ROW_REFERENCE]
    np.testing.assert_allclose(prog.end_machine[-1, :3], [1, 1, 0])


def test_canned_cycle_expands_to_rapid_feed_rapid():
    prog = parse_program("G21 F50\nG0 X0 Y0 Z10\nG98 G81 X1 Y1 Z-2 R1\nG80\n")
    cyc = prog.kind == ROW_CYCLE
    np.testing.assert_allclose(prog.end[cyc, :3], [[1, 1, 10], [1, 1, 1], [1, 1, -2], [1, 1, 10]])
    np.testing.assert_array_equal(prog.motion[cyc], [RAPID, RAPID, FEED, RAPID])


def test_units_switch_converts_the_current_position():
    prog = parse_program("G21\nG0 X25.4\nG20\nG0 Y1\n")
    np.testing.assert_allclose(prog.end[-1, :2], [1.0, 1.0])
    np.testing.assert_allclose(prog.end_mm[-1, :2], [25.4, 25.4])
    assert prog.units == "mixed"


def test_fanuc_codes_pass_through_and_are_recorded():
    prog = parse_file(NIST / "d2mi_827-9999-904_op1.nc", passthrough_unsupported=True)  # G41: the control's part
    assert len(prog) > 1000
    reasons = {reason for _, reason in prog.unsupported}
    assert any("G08" in r for r in reasons)
    # G10 L2 P#501 X#510 with #501 = 1, #510 = 0. (literal parameters are substituted)
    assert prog.units == "inch"


@pytest.mark.parametrize("text, reason", [
    ("G21\nM98 P1000\n", "not in this file"),
    ("G21\nG0 X0\nG65 P9000 A1\n", "macro call"),
    ("G21\no100 call\n", "not in this file"),
])
def test_blocks_that_could_move_are_refused_with_file_and_line(text, reason):
    with pytest.raises(GcodeError) as info:
        parse_program(text, "job.ngc")
    assert str(info.value).startswith("job.ngc:")
    assert reason in str(info.value)
    prog = parse_program(text, "job.ngc", passthrough_unsupported=True)
    assert prog.unsupported


@pytest.mark.parametrize("text, line, reason", [
    ("", 1, "empty"),
    ("   \n\n", 1, "empty"),
    ("G21\nG0 X\n", 2, "no number"),
    ("G21\nG0 X1\x00\n", 2, "NUL"),
    ("G21\nG1 X1\n", 2, "zero feed"),
    ("G21 F10\nG0 X0 Y0\nG2 X10 Y0 I3 J0\n", 3, "not on the circle"),
    ("G21\n(open comment\n", 2, "not closed"),
])
def test_bad_input_raises_gcode_error_naming_the_line(text, line, reason):
    with pytest.raises(GcodeError) as info:
        parse_program(text, "f.ngc")
    assert str(info.value).startswith(f"f.ngc:{line}: ")
    assert reason in str(info.value)


def test_binary_file_is_refused(tmp_path):
    path = tmp_path / "b.nc"
    path.write_bytes(b"G0 X1\n\x00\x01\x02")
    with pytest.raises(GcodeError, match="binary"):
        parse_file(path)


def test_write_number_formats():
    assert write_number(1.23456789, 4) == "1.2346"
    assert write_number(1.5, 4) == "1.5"
    assert write_number(-0.00001, 4) == "0"
    assert write_number(0.25, 3, leading_zero=False) == ".25"
    assert write_number(-0.25, 3, leading_zero=False) == "-.25"
    assert write_number(120.0, 3, trailing_point=True) == "120."
    with pytest.raises(ValueError):
        write_number(float("nan"), 4)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.floats(-1e5, 1e5), st.floats(-1e-3, 1e-3), st.integers(-500, 500).map(lambda i: i / 8)),
                min_size=1, max_size=30),
       st.integers(0, 7), st.booleans(), st.booleans())
def test_write_numbers_writes_what_write_number_writes(values, decimals, leading_zero, trailing_point):
    # The writer's batch formatter against the one-number reference, including halves (ties) and tiny negatives.
    batch = write_numbers(np.array(values), decimals, leading_zero=leading_zero, trailing_point=trailing_point)
    one = [write_number(v, decimals, leading_zero=leading_zero, trailing_point=trailing_point) for v in values]
    assert batch == one


def test_write_numbers_refuses_non_finite_values():
    with pytest.raises(ValueError, match="non-finite"):
        write_numbers(np.array([1.0, np.inf]), 4)


def test_format_info_reports_input_precision():
    info = parse_file(NIST / "mtc_plate_1.nc").format_info
    assert info.decimals["X"] == 4 and not info.leading_zero and info.trailing_point and info.separator == ""


def test_format_info_is_the_same_read_in_blocks(monkeypatch):
    # The dialect is measured block by block (memory): the answer must not depend on where the blocks end.
    from trueaxis.nc import gcode

    text = "G21 G90\nG1 X.5 Y1.25 F100\n" + "G1 X1.5 Y2.\n" * 7 + "G1 X1.123456 (Y9.1234567)\nG1 Z-.5\n"
    whole = parse_program(text).format_info
    monkeypatch.setattr(gcode, "_STYLE_BLOCK_LINES", 2)
    blocks = parse_program(text).format_info
    assert whole == blocks
    assert whole.decimals["X"] == 6 and whole.decimals["Y"] == 2 and not whole.leading_zero and whole.trailing_point


def test_word_spans_locate_coordinates_in_the_raw_line():
    prog = parse_program("N10 G1 X1.5 Y-2 F100\n")
    line = prog.lines[0]
    start, end = word_spans(prog, 0)["Y"]
    assert line[start:end] == "-2"


def test_tool_table_reads_linuxcnc_format():
    assert parse_tool_table("T1 P1 D0.25 Z+1.0 ;a\nT7 P7 Z-0.5\n", units="inch") == {1: 25.4, 7: -12.7}


# ---------------------------------------------------------------------------------------------------------------
# fuzzing: parse returns a Program or raises GcodeError, never anything else

def _parse_or_gcode_error(text):
    try:
        parse_program(text, "fuzz")
    except GcodeError:
        pass


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.text(alphabet=st.characters(min_codepoint=1, max_codepoint=0x2FF), max_size=300))
def test_random_text_parses_or_raises_gcode_error(text):
    _parse_or_gcode_error(text)


_REAL = (NIST / "mtc_plate_1.nc").read_text().splitlines(keepends=True)[:60]
_REAL += (NIST / "d2mi_827-9999-904_op1.nc").read_bytes().decode("iso-8859-1").splitlines(keepends=True)[:60]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.sampled_from(["drop", "dup", "swap", "insert"]), st.integers(0, 10**6),
                          st.sampled_from(list("GXYZIJKRFMN0123456789.-#[]()%/; \n"))), max_size=8),
       st.integers(0, len(_REAL) - 30))
def test_mutated_real_programs_parse_or_raise_gcode_error(mutations, first):
    text = list("".join(_REAL[first:first + 30]))
    for op, pos, ch in mutations:
        if not text:
            break
        i = pos % len(text)
        if op == "drop":
            del text[i]
        elif op == "dup":
            text.insert(i, text[i])
        elif op == "swap" and i + 1 < len(text):
            text[i], text[i + 1] = text[i + 1], text[i]
        else:
            text.insert(i, ch)
    _parse_or_gcode_error("".join(text))


# ---------------------------------------------------------------------------------------------------------------
# conformance with LinuxCNC's rs274

CONFORMANCE = [NIST / "mtc_cover_rev_a.nc", NIST / "mtc_plate_1.nc", *sorted(PROGRAMS.glob("*.ngc"))]


@pytest.mark.external
@pytest.mark.parametrize("path", CONFORMANCE, ids=lambda p: p.name)
def test_moves_match_rs274(path, tmp_path):
    canon = run_rs274(path, TOOLS_MM, tmp_path)
    assert canon.returncode == 0, f"rs274 stopped on {path.name}: {canon.stderr[-400:]}"
    prog = parse_file(path, tool_table=TOOLS_MM)
    assert len(prog) == len(canon.kind), f"{len(prog)} moves here, {len(canon.kind)} from rs274"
    kinds = np.array(["traverse", "feed", "arc", "arc"])[prog.motion]
    assert list(kinds) == canon.kind
    dev = np.abs(prog.end - canon.end).max()
    assert dev <= PRINT_TOL, f"max end-point deviation {dev:.3g}"
    arcs = prog.motion >= ARC_CW
    if arcs.any():
        plane_axes = {17: [0, 1], 18: [0, 2], 19: [1, 2]}
        for row in np.nonzero(arcs)[0]:
            axes = plane_axes[int(prog.arc_plane[row])]
            assert np.abs(prog.arc_center[row, axes] - canon.center[row, axes]).max() <= PRINT_TOL
        sign = np.where(prog.motion[arcs] == ARC_CCW, 1, -1) * prog.arc_turns[arcs]
        np.testing.assert_array_equal(sign, canon.rotation[arcs])


def test_the_checks_split_lines_a_window_at_a_time_as_splitlines_does():
    # (check._lines: G93's checks read a line or two after the first F, not the whole rest of a long program)
    import random

    from trueaxis.nc.check import _lines

    rng = random.Random(1)
    pieces = ["a", "G1 X2", "\r", "\n", "\r\n", "\x0b", "\x0c", "\x1c", "\x85", "\u2028", " ", "F1.5"]
    for _ in range(3000):
        text = "".join(rng.choice(pieces) for _ in range(rng.randint(0, 300)))
        a = rng.randint(0, len(text))
        b = rng.randint(a, len(text))
        assert list(_lines(text, a, b, rng.randint(1, 20))) == text[a:b].splitlines(keepends=True)
