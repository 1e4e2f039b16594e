"""Fuzzing the post: whatever text comes in, it is posted or refused with ``file:line: reason``, never a traceback.

Inputs are the fixture programs mutated (lines dropped, doubled, swapped, cut short, characters and numbers replaced)
and token soup (G/M codes, axis words, comments, bad and huge numbers, stray and non-ASCII characters). Each goes
through ``compensate(text, machine, "geometric")`` on the xh714 error twin with wide travel (as test_post.py widens it,
so that the random positions mostly post instead of stopping at the travel check), and a few through the command line.
Hypothesis runs derandomized: the same examples on every run, so CI is reproducible.
"""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import MACHINES, ROOT
from trueaxis.cli import main as cli_main
from trueaxis.machine import parse_machine
from trueaxis.nc.gcode import GcodeError, parse_program
from trueaxis.postproc.post import compensate, without_header

XH714 = MACHINES / "xh714.toml"
WIDE_TEXT = XH714.read_text().replace("[-200.0, 200.0]", "[-2000.0, 2000.0]").replace(
    "[-150.0, 150.0]", "[-2000.0, 2000.0]").replace("[-400.0, 0.0]", "[-2000.0, 2000.0]")
WIDE = parse_machine(WIDE_TEXT, source="xh714-wide")
FIXTURES = {p.name: p.read_text() for p in sorted((ROOT / "fixtures" / "programs").glob("*.ngc"))}
SOURCE = "fuzz.ngc"
# file:line: reason -- one line, a line number that exists in the file (or 1 for an empty one), a reason
DIAGNOSTIC = re.compile(r"^(?P<file>[^\n]+?):(?P<line>[0-9]+): (?P<reason>\S[^\n]*)$")

SETTINGS = settings(max_examples=250, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def physical_lines(text: str) -> int:
    """Lines as an editor counts them (\\n, \\r\\n or a lone \\r end a line)."""
    return max(1, len(re.findall(r"\r\n|\r|\n", text)) + (0 if re.search(r"[\r\n]\Z", text) else 1))


def check_posts_or_refuses(text: str, source: str = SOURCE):
    """The property: compensated text, or a GcodeError whose message is ``source:line: reason`` naming a real line."""
    try:
        out = compensate(text, WIDE, "geometric", source=source)
    except GcodeError as exc:  # PostError is a GcodeError
        message = str(exc)
        m = DIAGNOSTIC.match(message)
        assert m, f"not 'file:line: reason': {message!r}"
        assert m.group("file") == source, message
        assert 1 <= int(m.group("line")) <= physical_lines(text), (message, physical_lines(text))
        return exc
    assert isinstance(out, str)
    # what the post writes, its own reader reads, with the same number of lines where nothing was split
    again = parse_program(out, "out.ngc")
    assert len(again.lines) >= len(parse_program(text, source).lines)
    return out


# --- strategies ----------------------------------------------------------------------------------------------------

NUMBERS = st.one_of(
    st.integers(-2000, 2000).map(str),
    st.floats(-1500, 1500, allow_nan=False).map(lambda v: f"{v:.4f}"),
    st.floats(-2, 2, allow_nan=False).map(lambda v: f"{v:.6f}".replace("0.", ".", 1)),
    st.sampled_from(["", ".", "-", "+", "--1", "1.2.3", "1e5", "1E-3", "nan", "inf", "-inf", "0x1F", "1_000",
                     "9" * 40, "1" + "0" * 400, "-" + "9" * 320 + ".5", "0.0000000001", "+.5", "-.", "٣", "１"]),
)
LETTERS = st.sampled_from(list("XYZABCIJKRPQLFSTHDNUVWEOxyzijkfr"))
WORD = st.builds(lambda letter, num, space: f"{letter}{space}{num}", LETTERS, NUMBERS, st.sampled_from(["", "", " "]))
CODES = st.sampled_from([
    "G0", "G1", "G2", "G3", "G00", "G01", "G02", "G03", "G4 P0.5", "G10 L2 P1", "G10 L20 P2", "G10 L1 P1 Z5",
    "G17", "G18", "G19", "G20", "G21", "G28", "G28.1", "G30", "G40", "G41 D1", "G42", "G43", "G43 H1", "G43.1 Z2",
    "G49", "G53", "G54", "G55", "G59.3", "G61", "G64", "G73", "G80", "G81", "G82", "G83", "G84", "G85", "G86", "G87",
    "G88", "G89", "G90", "G91", "G90.1", "G91.1", "G92", "G92.1", "G92.2", "G92.3", "G93", "G94", "G95", "G98",
    "G99", "G5", "G33", "G38.2", "G65", "G08 P1", "G05.1", "G7", "G999", "G1.5", "M0", "M1", "M2", "M3", "M5", "M6",
    "M8", "M9", "M30", "M29", "M98 P100", "M99", "M1234", "T1", "T2 M6", "S1000", "F100", "F0", "F-5", "N10",
    "N99999", "O0001", "o100 sub", "o100 endsub", "O<x> call",
])
JUNK = st.sampled_from([
    "(comment)", "(unclosed", ";semicolon comment", "( nested (paren) )", ")", "%", "/", "#1=5", "#2 = -1.5", "#1",
    "[#1]", "[1+2]", "#<named>", "*", "=", "<", ">", "?", "@", "!", "$", "&", "'", '"', "\\", "{", "}", "~", "^",
    "\t", " ", "\x7f", "\x01", "\x1b", "\ufeff", "\u00a0", "\u2028", "\x0c", "\x0b", "\x85", "\r", "é", "€", "Ω",
    "中", "🙂", "(trueaxis: ap=2 ae=1 fz=0.05 n=5000 d=10 z=4 mode=down)", "(trueaxis: garbage)", "(trueaxis: ap=x)",
])
TOKEN = st.one_of(WORD, WORD, CODES, CODES, JUNK, st.text(min_size=1, max_size=3))
# Mostly blocks a control could take (codes, axis words with sensible numbers), so that many soups post; a junk line
# now and then.
AXIS_WORD = st.builds(lambda letter, v: f"{letter}{v:.4f}".rstrip("0").rstrip("."),
                      st.sampled_from(list("XYZXYZIJRF")), st.floats(-300, 300, allow_nan=False))
COMMON = st.sampled_from(["G0", "G1", "G1", "G2", "G3", "G17", "G18", "G19", "G20", "G21", "G90", "G91", "G91.1",
                          "G90.1", "G93", "G94", "G54", "G55", "G92", "G92.1", "G43 H1", "G49", "G40", "G41", "G80",
                          "G81 R5", "G83 R5 Q2", "G98", "G99", "G28", "G53", "M3", "M5", "T1 M6", "F100", "S500",
                          "N20", "(note)"])
BLOCK = st.lists(st.one_of(COMMON, COMMON, CODES, AXIS_WORD, AXIS_WORD, AXIS_WORD, AXIS_WORD), min_size=1,
                 max_size=5).map(" ".join)
JUNK_LINE = st.lists(TOKEN, min_size=0, max_size=7).flatmap(
    lambda toks: st.sampled_from([" ", ""]).map(lambda sep: sep.join(toks)))
LINE = st.one_of(*[BLOCK] * 12, JUNK_LINE)
ENDING = st.sampled_from(["\n", "\n", "\n", "\r\n", "\r"])
SOUP = st.builds(lambda lines, ends, head: head + "".join(l + e for l, e in zip(lines, ends)),
                 st.lists(LINE, min_size=1, max_size=12), st.lists(ENDING, min_size=12, max_size=12),
                 st.sampled_from(["", "G21 G90 G17 G94 F300\n", "G21 G90 G17 G94 F300\n", "%\nG20 G90 F10\n"]))


@st.composite
def mutated_fixture(draw):
    """A fixture program with a few mutations applied."""
    name = draw(st.sampled_from(sorted(FIXTURES)))
    lines = FIXTURES[name].splitlines(keepends=True)
    for _ in range(draw(st.integers(1, 4))):
        if not lines:
            lines = ["\n"]
        i = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["drop", "double", "swap", "truncate", "char", "number", "insert", "token",
                                   "cut_file"]))
        line = lines[i]
        if op == "drop":
            del lines[i]
        elif op == "double":
            lines.insert(i, line)
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "truncate":
            lines[i] = line[: draw(st.integers(0, len(line)))] + "\n"
        elif op == "char" and line:
            k = draw(st.integers(0, len(line) - 1))
            lines[i] = line[:k] + draw(st.one_of(JUNK, st.characters())) + line[k + 1:]
        elif op == "number":
            nums = list(re.finditer(r"[-+]?[0-9]*\.?[0-9]+", line))
            if nums:
                m = nums[draw(st.integers(0, len(nums) - 1))]
                lines[i] = line[: m.start()] + draw(NUMBERS) + line[m.end():]
        elif op == "insert":
            lines.insert(i, draw(LINE) + "\n")
        elif op == "token":
            k = draw(st.integers(0, len(line)))
            lines[i] = line[:k] + " " + draw(TOKEN) + " " + line[k:]
        elif op == "cut_file":
            lines = lines[: i + 1]
    return "".join(lines)


# --- the property --------------------------------------------------------------------------------------------------

def test_every_fixture_program_posts_or_is_refused_with_a_line():
    for name, text in FIXTURES.items():
        check_posts_or_refuses(text, name)


@SETTINGS
@given(mutated_fixture())
def test_mutated_fixture_programs_post_or_stop_with_file_line_reason(text):
    check_posts_or_refuses(text)


@SETTINGS
@given(SOUP)
def test_token_soup_posts_or_stops_with_file_line_reason(text):
    check_posts_or_refuses(text)


@settings(max_examples=40, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(st.one_of(mutated_fixture(), SOUP))
def test_the_command_line_posts_or_prints_one_line_and_exits_2(tmp_path_factory, capsys, text):
    # The command line in this process (a subprocess per example would take minutes): exit 0 and a file (stderr:
    # only `file:line:` warnings), or exit 3 (a program refused), one `file:line: reason` line and no file.
    work = tmp_path_factory.mktemp("cli")
    src, out = work / "in.ngc", work / "out.ngc"
    src.write_bytes(text.encode("utf-8"))
    machine = work / "wide.toml"
    machine.write_text(WIDE_TEXT)
    capsys.readouterr()
    code = cli_main(["post", str(src), "-o", str(out), "--machine", str(machine)])
    err = capsys.readouterr().err
    if code == 0:
        assert out.exists()
        assert all(DIAGNOSTIC.match(line) and line.startswith(str(src)) for line in err.splitlines()), err
    else:
        assert code == 3 and not out.exists()
        lines = err.strip().splitlines()
        assert len(lines) == 1 and DIAGNOSTIC.match(lines[0]) and lines[0].startswith(str(src)), err


@pytest.mark.parametrize("text", ["G21 G90\nG28\nM2\n", "G21 G90\nG53 G0 X0 Y0\nM2\n"])
def test_a_program_whose_only_moves_are_reference_or_machine_moves_posts(text):
    # G28/G30/G53 targets are machine positions: nothing to compensate, the program passes through unchanged.
    assert without_header(compensate(text, WIDE, "geometric", source=SOURCE)) == text


# --- the command line on inputs a user gets wrong ------------------------------------------------------------------

def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "trueaxis.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=120)


@pytest.fixture(scope="module")
def wide_machine(tmp_path_factory):
    path = tmp_path_factory.mktemp("machine") / "xh714_wide.toml"
    path.write_text(WIDE_TEXT)
    return path


def test_cli_posts_an_inch_program_for_a_mm_machine_and_the_report_says_so(tmp_path, wide_machine):
    src, out, rep = tmp_path / "inch.ngc", tmp_path / "out.ngc", tmp_path / "r.json"
    src.write_text("G20 G90 G17 G94\nG0 X1 Y1 Z-4\nG1 X2 Y1.5 F10\nM2\n")
    r = run_cli("post", src, "-o", out, "--machine", wide_machine, "--report", rep)
    assert r.returncode == 0, r.stderr
    import json

    note = json.loads(rep.read_text())["units_note"]
    assert "inch" in note and "mm" in note
    # the output stays in inches: G20 kept, numbers near the inch input
    text = without_header(out.read_text())
    assert text.startswith("G20 G90 G17 G94\n") and re.search(r"X2\.0*\d* Y1\.[45]", text)


@pytest.mark.parametrize("name, data, reason", [
    ("empty", b"", "empty"),
    ("blank lines", b"\n \n\t\n", "empty"),
    ("binary with NUL bytes", b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "binary"),
    ("axes the machine lacks", b"G21 G90\nG1 X1 Y1 Z-10 B30 F100\nM2\n", "axis B"),
    ("bytes that are not text", bytes(range(0x80, 0x100)) * 4, "unexpected character"),
])
def test_cli_refuses_bad_input_with_one_line_and_exit_3_and_writes_nothing(tmp_path, wide_machine, name, data,
                                                                           reason):
    src, out = tmp_path / "in.ngc", tmp_path / "out.ngc"
    src.write_bytes(data)
    r = run_cli("post", src, "-o", out, "--machine", wide_machine)
    assert r.returncode == 3, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert reason in r.stderr and r.stderr.startswith(f"{src}:"), r.stderr
    assert not out.exists() and r.stdout == ""
