"""After a block that may move the machine where the text does not say -- a tool change (M6: LinuxCNC with
TOOL_CHANGE_QUILL_UP / _AT_G30 / _POSITION, a Fanuc or Hurco change macro), a probing move passed through -- the post
writes no axis word from the position it held before: ``G0 X60 Y20`` after ``T2 M6`` was written with the old Z
(``Z5.00117``), a dive at rapid with the new tool before its G43 on a control that had lifted Z, exit 0 (QA pass).
Such blocks are left as written, said, until the program gives every axis again, as at its start."""

from __future__ import annotations

import re

import pytest

from conftest import MACHINES
from trueaxis.machine import load_machine
from trueaxis.nc.gcode import GcodeError
from trueaxis.postproc.post import PostError, compensate, without_header

TOOLS = {1: 50.0, 2: 90.0}


@pytest.fixture(scope="module")
def nmv():
    return load_machine(MACHINES / "nmv1500dcg.toml")


def _post(text, machine, **kw):
    report = {}
    out = compensate(text, machine, "geometric", report=report, offsets_zero=True, **kw)
    return without_header(out).splitlines(), report


def test_after_a_tool_change_no_axis_word_is_written_from_before_it(nmv):
    prog = ("G21 G90 G17 G94 G54\nT1 M6\nG43 H1 G0 X0 Y0 Z5\nG1 Z-3 F100\nG1 X40\nG0 Z5\nT2 M6\nG0 X60 Y20\n"
            "G43 H2 Z5\nG1 Z-3\nM2\n")
    lines, report = _post(prog, nmv)
    assert lines[7] == "G0 X60 Y20"  # as written: no Z from before the change
    assert report["uncompensated"] == [{"line": 8, "axes": "Z", "since": "the tool change M6 at line 7"}]
    assert ("<string>:8: the position of Z is not known here (no absolute move of it since the tool change M6 at "
            "line 7): block left as written, uncompensated") in report["warnings"]
    # the next block gives Z: compensated again (X and Y known from the block before, where the control stands)
    words = dict(re.findall(r"([XYZ])(-?[\d.]+)", lines[8]))
    assert lines[8].startswith("G0 G43 X") and lines[8].endswith(" H2"), lines[8]
    assert 0 < abs(float(words["Z"]) - 5.0) < 0.01 and 0 < abs(float(words["X"]) - 60.0) < 0.01, lines[8]
    # the moves before the change, and the change's own block with every axis, are compensated
    assert lines[2] != "G43 H1 G0 X0 Y0 Z5" and lines[3].startswith("G1 X")
    whole = prog.replace("T2 M6\nG0 X60 Y20\n", "T2 M6 G0 X60 Y20 Z50\n")
    lines, report = _post(whole, nmv)
    assert report["uncompensated"] == [] and re.fullmatch(r"T2 M6 G0 X(59\.9|60\.0)\d+ Y\S+ Z\S+", lines[6]), lines


def test_after_a_probing_move_passed_through_the_position_is_given_again_first(nmv):
    prog = "G21 G90 G17 G94\nG0 X0 Y0 Z5\nG38.2 Z-20 F100\nG0 X10\nG91 G0 Z5\nG90 G0 X20 Y20\nG0 Z8\nG1 X30 F100\nM2\n"
    with pytest.raises(GcodeError, match="probing G38.2"):
        _post(prog, nmv)
    lines, report = _post(prog, nmv, passthrough_unsupported=True)
    assert lines[2:6] == ["G38.2 Z-20 F100", "G0 X10", "G91 G0 Z5", "G90 G0 X20 Y20"]  # as written
    assert [u["line"] for u in report["uncompensated"]] == [4, 5, 6]
    assert {u["since"] for u in report["uncompensated"]} == {"the probing G38.2 passed through at line 3"}
    assert re.fullmatch(r"G0 X(19\.9|20\.0)\d+ Y\S+ Z\S+", lines[6]), lines  # Z given: compensated again
    assert re.fullmatch(r"G1 X(29\.9|30\.0)\d+ Y\S+ Z\S+ F100", lines[7]), lines


def test_the_lines_said_are_the_sources_in_a_flattened_program(nmv):
    # parameters and an O-word subroutine: the flat program's lines are not the file's
    prog = ("G21 G90 G17 G94\n#1 = 60\n#2 = 20\no100 sub\nG0 X#1 Y#2 Z5\no100 endsub\nG0 X0 Y0 Z5\nT2 M6\n"
            "G0 X#1 Y#2\nG0 Z5\nM2\n")
    _, report = _post(prog, nmv)
    assert report["uncompensated"] == [{"line": 9, "axes": "Z", "since": "the tool change M6 at line 8"}]


def test_tcp_output_refuses_a_block_whose_position_a_tool_change_left_unknown():
    bc = load_machine(MACHINES / "nmv1500dcg.toml")
    prog = "G21 G90 G94\nT1 M6\nG43 H1 G0 X10 Y0 Z50 B0 C0\nG1 X20 F100\nT2 M6\nG0 X30 Y5\nG43 H2 Z50\nM2\n"
    with pytest.raises(PostError, match=r":6: TCP output: the position of an axis is not known here \(no absolute "
                                        r"move of it since the tool change M6 at line 5\)"):
        compensate(prog, bc, "geometric", offsets_zero=True, output_mode="tcp")


def test_the_setups_provenance_names_the_source_lines_of_a_flattened_program():
    """The header and the report named the flat program's lines (g10p.ngc:3 for a G10 at line 5; on the NIST d2mi
    program :944 for :948), the error growing along the file (QA pass)."""
    xh = load_machine(MACHINES / "xh714.toml")
    prog = "G21 G90 G17\n#1 = 5\n#2 = 6\n#3 = 7\nG10 L2 P2 X-10 Y#1 Z-250\nG55 G0 X1 Y1 Z1\nM2\n"
    report = {}
    out = compensate(prog, xh, "geometric", report=report)
    assert "(trueaxis setup: G55 X-10 Y5 Z-250 mm, from <string>:5 [G10 L2])" in out.splitlines()
    assert [(u["source"], u["first_line"]) for u in report["setup_used"]] == [("<string>:5 (G10 L2)", 6)]


def test_the_posts_refusals_name_the_source_line_of_a_flattened_program():
    # (they named the flat program's line: here 3 for the file's 5)
    xh = load_machine(MACHINES / "xh714.toml")
    prog = "G21 G90 G17\n#1 = 5\n#2 = 6\nG0 X0 Y0 Z-20\nG99 G91 G81 X#1 Y#2 Z-3 R-8 L3 F100\nM2\n"
    with pytest.raises(PostError, match=r"^<string>:5: incremental \(G91\) canned cycles are not compensated"):
        compensate(prog, xh, "geometric", offsets_zero=True)


def test_a_block_without_axis_words_is_not_said_to_be_uncompensated():
    """'N110G0G17G40G49G80G90' (NIST mtc_plate_1, a G0 with no axis word before any position) was listed as
    uncompensated with a warning: noise. It is left as written and not said; a program of such blocks only is still
    refused (no move to compensate)."""
    xh = load_machine(MACHINES / "xh714.toml")
    report = {}
    out = compensate("N100G21\nN110G0G17G40G49G80G90\nN120 G0 X1 Y1 Z-10\nG1 X2 F10\nM2\n", xh, "geometric",
                     report=report, offsets_zero=True)
    assert "N110G0G17G40G49G80G90" in out.splitlines() and report["uncompensated"] == []
    assert not any("not known" in w for w in report["warnings"])
    with pytest.raises(PostError, match=r"<string>:2: no move can be compensated: the position of X Y Z is never"):
        compensate("G21 G90\nG0\nM2\n", xh, "geometric", offsets_zero=True)


def test_the_header_goes_after_the_first_percent_not_after_the_programs_end():
    """For a file of '%' lines only, the header came after the second '%', LinuxCNC's end of the program (QA pass)."""
    from trueaxis.nc.flatten import program_start

    assert [program_start(t) for t in ("%\n%\n", "%\nO100\nG0 X1\n", "%\nO1\n%\n", "G0\n")] == [2, 7, 5, 0]
