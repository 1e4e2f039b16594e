"""The reader's compiled pre-scan (trueaxis.nc.fast_read) against what it replaces: the regular expression
``_FAST`` and ``float()``, line by line, and ``parse_program`` with and without it on real and random programs."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import test_post_fuzz as fz  # its random programs (mutated fixtures, token soup)
from conftest import ROOT, missing
from trueaxis.nc import fast_read, gcode
from trueaxis.nc.gcode import _FAST, GcodeError, parse_program, split_lines

SETTINGS = settings(max_examples=1500, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# the G-code alphabet, upper and lower case, with blanks and line endings
ALPHABET = "NGXYZABCIJKRFxyzabcijkrfgnM0123456789000.+- \t\r\n"
PIECES = st.sampled_from(["N10", "N", "G0", "G00", "G1", "G01", "G02", "G3", "G03", "G4", "G000", "G1.", "G01.0", "G",
                          "X", "Y", "Z", "A", "B", "C", "I", "J", "K", "R", "F", "x", "g1", "1", "-", "+", ".", "0",
                          "12345", "1234567890", "123456789", ".5", "5.", " ", "\t", "\r", "\n", "\r\n", "(c)", ";"])
TEXT = st.one_of(st.text(ALPHABET, max_size=40), st.lists(PIECES, max_size=16).map("".join))


def scan(text: str):
    """Per line of ``split_lines(text)``: (status, g, values) from the pre-scan."""
    starts, buf = fast_read.scan_text(text)
    n = len(starts) - 1
    status, g, vals = fast_read.scan_lines(buf, starts, 0, n)
    return status, g, vals


def regex_line(line: str):
    """What the reader's regex path makes of one line: (status, g, values)."""
    m = _FAST.match(line)
    if m is None:
        return fast_read.LINE_NO_MATCH, -1, None
    grp = m.groups()
    if all(v is None for v in grp[:7]):
        return fast_read.LINE_NO_MOTION, -1, None
    g = -1 if grp[0] is None else int(grp[0])
    return fast_read.LINE_FAST, g, [np.nan if v is None else float(v) for v in grp[1:]]


def same_float(a: float, b: float) -> bool:
    return (a != a and b != b) or (a == b and np.signbit(a) == np.signbit(b))


def check_text(text: str) -> None:
    lines = split_lines(text)
    status, g, vals = scan(text)
    assert len(status) == len(lines)
    for i, line in enumerate(lines):
        want_status, want_g, want_vals = regex_line(line)
        got = int(status[i])
        if got == fast_read.LINE_SLOW:
            assert want_status == fast_read.LINE_FAST, repr(line)
            continue
        assert got == want_status, (repr(line), got, want_status)
        if got == fast_read.LINE_FAST:
            assert int(g[i]) == want_g, repr(line)
            assert all(same_float(a, b) for a, b in zip(vals[i].tolist(), want_vals)), (repr(line), vals[i])


def test_fast_is_case_sensitive_upper_case():
    assert _FAST.match("G1 X1\n") and not _FAST.match("g1 X1\n") and not _FAST.match("G1 x1\n")
    check_text("g1 x1\nG1 x1\nG1 X1\n")
    assert scan("g1 x1\nG1 X1\n")[0].tolist() == [fast_read.LINE_NO_MATCH, fast_read.LINE_FAST]


@pytest.mark.parametrize("text", [
    "", "\n", "\r", "\r\n", "\n\r", "X1", "X1\r", "X1\n\r", "G0\n", "G00X1", "G000X1", "G01.X1", "G04X1", "G1.0X1",
    "G12X1", "G02.X1", "G0 2X1", "N10G1X1Y2Z3A4B5C6I7J8K9R10F11\n", "NG1X1", "N1", "F100", "I1J1", "X.", "X-.",
    "X1234567890", "X123456789.123", "X 1", "X- 1", "X1X2", "Y1X1", "X1 Y2\t Z3  \r\n", "  \tG1X1", "X+.5", "X-0",
    "X5.", "X1.23456789012345678901234567", "X0.00000000000000000000001", "X1.0000000000000000000000000",
    "X999999999.999999", "X9007199254740993", "Z.0000000000000000000001",
    "X458.426155426689970", "X.000840886217526361411", "X69056069.9852663089",
    "X.9007199254740993", "X.9007199254740992", "X900719925.4740991", "G3X1Y2I3J4\rG2X1\nX1e5\n",
])
def test_examples(text):
    check_text(text)


@SETTINGS
@given(TEXT)
def test_grammar_and_values_equal_the_regex_and_float(text):
    check_text(text)


DIGITS = st.text("0123456789", max_size=25)
DECIMAL = st.builds(lambda sign, a, point, b: sign + a + point + b, st.sampled_from(["", "-", "+"]), DIGITS,
                    st.sampled_from([".", ".", ""]), DIGITS).filter(lambda s: any(c.isdigit() for c in s))
SHORT = st.builds(lambda sign, a, b, z: f"{sign}{a}.{b}{'0' * z}", st.sampled_from(["", "-"]),
                  st.integers(0, 999_999_999).map(str), st.integers(0, 10**15).map(str), st.integers(0, 12))
# 15 to 19 significant digits, at most 9 before the point: around the 2**53 limit of the exact conversion


def _point(digits: str, k: int) -> str:
    """``digits`` with a decimal point k places from the right."""
    return digits[:-k] + "." + digits[-k:] if k < len(digits) else "." + "0" * (k - len(digits)) + digits


LONG = st.builds(lambda m, k: _point(str(m), k), st.integers(10**14, 10**19), st.integers(10, 22))
FLOATS = st.floats(-1e9, 1e9, allow_nan=False).flatmap(
    lambda v: st.sampled_from([repr(v), f"{v:.4f}", f"{v:.6f}", f"{v:.17f}", f"{v:.3f}".replace("0.", ".", 1)]))


@SETTINGS
@given(st.one_of(DECIMAL, SHORT, LONG, FLOATS), st.sampled_from("XYZABCIJKRF"))
def test_numbers_equal_float(num, letter):
    line = f"G1{letter}{num}\n"
    status, g, vals = scan(line)
    want = regex_line(line)
    if want[0] != fast_read.LINE_NO_MATCH and letter in "XYZABC":
        assert int(status[0]) in (fast_read.LINE_FAST, fast_read.LINE_SLOW), line
    check_text(line)
    if int(status[0]) == fast_read.LINE_FAST:
        k = "XYZABCIJKRF".index(letter)
        assert same_float(float(vals[0, k]), float(num)), (num, vals[0, k])


def test_short_numbers_are_read_not_left_to_python():
    status, _, vals = scan("X-123456789.123456\nY.000000000000000000001\nZ1.50000000000000000000000000\n")
    assert status.tolist() == [fast_read.LINE_FAST] * 3
    assert vals[:, :3].diagonal().tolist() == [-123456789.123456, 1e-21, 1.5]
    status, _, _ = scan("X1.2345678901234567\n")
    assert status.tolist() == [fast_read.LINE_SLOW]


# --- parse_program with and without the pre-scan -----------------------------------------------------------------

FIELDS = ["start", "end", "offset", "motion", "kind", "arc_center", "arc_plane", "arc_turns", "feed", "inverse_time",
          "inch", "cutter_comp", "tool", "incremental", "arc_incremental", "line_index", "words"]


def parse(text, fast, monkeypatch, **kwargs):
    monkeypatch.setattr(gcode, "FAST_READ", fast)
    try:
        return parse_program(text, "t.ngc", **kwargs)
    except GcodeError as exc:
        return ("GcodeError", str(exc))
    except ValueError as exc:
        return ("ValueError", str(exc))


def assert_same_parse(text, monkeypatch, **kwargs):
    a = parse(text, True, monkeypatch, **kwargs)
    b = parse(text, False, monkeypatch, **kwargs)
    if isinstance(a, tuple) or isinstance(b, tuple):
        assert a == b
        return a
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape, f
        if x.dtype.kind == "f":
            assert np.array_equal(x, y, equal_nan=True), f
            assert np.array_equal(np.signbit(x), np.signbit(y)), f
        else:
            assert np.array_equal(x, y), f
    assert (a.lines, a.units, a.axes_present, a.warnings, a.unsupported) == \
        (b.lines, b.units, b.axes_present, b.warnings, b.unsupported)
    return a


PROGRAMS = sorted(p for p in (ROOT / "fixtures" / "programs").rglob("*") if p.suffix in (".ngc", ".nc"))


@pytest.mark.parametrize("path", PROGRAMS, ids=lambda p: p.name)
def test_fixture_programs_parse_the_same(path, monkeypatch):
    text = path.read_text(errors="replace")
    assert_same_parse(text, monkeypatch)
    assert_same_parse(text, monkeypatch, passthrough_unsupported=True)


def test_small_blocks_parse_the_same(monkeypatch):
    monkeypatch.setattr(gcode, "FAST_READ_BLOCK", 7)
    for path in PROGRAMS:
        assert_same_parse(path.read_text(errors="replace"), monkeypatch)


def test_cone_flank_program_parses_the_same(monkeypatch):
    from trueaxis.machine import load_machine
    from trueaxis.resources import machine_file
    from trueaxis.sim.programs import cone_flank_program

    cone = {"axis": [float(np.sin(np.radians(10))), 0.0, float(np.cos(np.radians(10)))], "half_angle_deg": 15.0,
            "base_radius": 40.0, "height_range": [0.0, 20.0]}
    text = cone_flank_program(load_machine(machine_file("nmv1500dcg")), cone, n_blocks=2000)
    prog = assert_same_parse(text, monkeypatch)
    assert len(prog) >= 2000


@pytest.mark.parametrize("text", [
    "G21 G90 F100\nG1 X1 F-5\n", "G21 G90\nG1 X1\n", "G21 G90 G93\nG1 X1 F10\nG1 X2\n", "G21 G90 F100\nG2 X1 I0 J0\n",
    "G21 G91 F100\nG1 X1.5 Y-0 Z-.25\nG0 X-0 A10 B-5 C.5\nG90\nG3 X1 Y1 R1\n",
    "G21 G90 F100\nG1 X1.12345678901234567 Y2\nG1 X123456789.123456789 F12.0000000000000000000000001\n",
    "G21 G90 F100\nG1 X1\nM2\nG1 X2\n", "G20 G90 F10\r\nG1 X1\rG18 G2 X2 Z1 I.5 K.5\r\nG19 G3 Y1 Z0 J0 K-1\n",
    "G90 F100\nG1 X1 (é)\nG1 X2\n", "F100\nG1 X1\nG1 X-1e5\n",
])
def test_examples_parse_the_same(text, monkeypatch):
    assert_same_parse(text, monkeypatch)


@settings(max_examples=300, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(st.data())
def test_random_programs_parse_the_same(data):
    text = data.draw(st.one_of(fz.mutated_fixture(), fz.SOUP))
    with pytest.MonkeyPatch.context() as mp:
        assert_same_parse(text, mp)
        assert_same_parse(text, mp, passthrough_unsupported=True)


# ------------------------------------------------------------------------------------ number_style (format_info) ----
# The reference: the regular expressions and the byte-wise numpy pass format_info used before the compiled scan.
_REF_LEADING_ZERO = re.compile(r"[XYZIJKR][-+]?(0?)\.[0-9]")
_REF_COMMENT_TO_EOL = re.compile(r"[(;][^\r\n]*")


def _reference_number_style(code: str):
    b = np.frombuffer(code.encode("latin-1", "replace"), np.uint8)
    digit = (b >= 48) & (b <= 57)
    dots = np.nonzero(b == 46)[0]
    if dots.size == 0:
        return {}, False
    other = np.nonzero(~digit)[0]
    k = np.searchsorted(other, dots, side="right")
    frac = np.where(k < other.size, other[np.minimum(k, other.size - 1)], b.size) - dots - 1
    before = np.searchsorted(other, dots, side="left") - 1
    pos = np.where(before >= 0, other[np.maximum(before, 0)], -1)
    signed = (pos >= 0) & np.isin(b[np.maximum(pos, 0)], (43, 45))
    pos = np.where(signed, pos - 1, pos)
    blank = (b == 32) | (b == 9)
    nonblank = np.nonzero(~blank)[0]
    j = np.searchsorted(nonblank, pos, side="right") - 1
    ok = (pos >= 0) & (j >= 0)
    pos = np.where(ok, nonblank[np.maximum(j, 0)], -1)
    letter_b = np.where(ok, b[np.maximum(pos, 0)], 0)
    upper = np.where((letter_b >= 97) & (letter_b <= 122), letter_b - 32, letter_b)
    ok &= (upper >= 65) & (upper <= 90)
    decimals = {}
    for code_point in np.unique(upper[ok]).tolist():
        decimals[chr(code_point)] = int(frac[ok & (upper == code_point)].max())
    bare = ok & (frac == 0) & np.isin(upper, np.frombuffer(b"XYZABCF", np.uint8))
    return decimals, bool(bare.any())


def _reference_style(text: str):
    code = _REF_COMMENT_TO_EOL.sub("", text)
    decimals, bare = _reference_number_style(code)
    m = _REF_LEADING_ZERO.search(code)
    return decimals, bare, (-1 if m is None else int(m.group(1) == "0"))


def _compiled_style(text: str):
    dec, bare, leading = fast_read.number_style(np.frombuffer(text.encode("latin-1", "replace"), np.uint8))
    return {chr(65 + k): int(dec[k]) for k in range(26) if dec[k] >= 0}, bool(bare), int(leading)


def test_number_style_is_the_regular_expressions_answer():
    import random

    rng = random.Random(18)
    alphabet = list("XYZxyzABCFIJKRGNPQ0123456789..--+  \t()\n\r;") + ["é", "\u2028", "0.", "X.", "X-0.", "Z+.", "0"]
    texts = ["", "G1 X1 Y2\n", "X.5", "X-0.25 (Y.5)\nY0.5", "X00.5 Y0.5", "x .5", "(X0.5\rX.5", "X- 1.5 Y -2.",
             "5-3.2 X1.", "X1.2.3"]
    for _ in range(3000):
        texts.append("".join(rng.choice(alphabet) for _ in range(rng.randint(1, 40))))
    for name in ("mtc_plate_1.nc", "mtc_cover_rev_a.nc", "d2mi_827-9999-904_op1.nc"):
        texts.append((ROOT / "fixtures" / "programs" / "nist" / name).read_text(errors="replace"))
    for text in texts:
        assert _compiled_style(text) == _reference_style(text), repr(text[:200])


@given(TEXT)
@SETTINGS
def test_number_style_is_the_regular_expressions_answer_on_random_text(text):
    assert _compiled_style(text) == _reference_style(text)


# --------------------------------------------------------------------- the block checks' scans (nc.check) ----
def _reference_candidate(text, pos):
    from trueaxis.nc.check import _CANDIDATES

    found = [m.start() for m in (p.search(text, pos) for p in _CANDIDATES) if m is not None]
    return min(found) if found else -1


def _reference_ijkr(text, a, b):
    from trueaxis.nc.check import _IJKR_AFTER_LINEAR

    m = _IJKR_AFTER_LINEAR.search(text, a, b)
    return -1 if m is None else m.end() - 1


def _check_scans_agree(text):
    text = "".join(c if c.isascii() else "?" for c in text)
    buf = np.frombuffer(text.encode("ascii"), np.uint8)
    for pos in sorted({0, 1, len(text) // 3, len(text) // 2, len(text)}):
        if pos <= len(text):
            assert fast_read.next_check_candidate(buf, fast_read._PLAIN_BYTES, pos) == _reference_candidate(text, pos)
    for a, b in ((0, len(text)), (len(text) // 4, len(text)), (0, (2 * len(text)) // 3), (1, len(text) - 1)):
        if 0 <= a <= b <= len(text):
            assert fast_read.ijkr_after_linear(buf, a, b) == _reference_ijkr(text, a, b), (text, a, b)


CHECK_PIECES = st.sampled_from(["G0", "G00", "G01", "G1", "G2", "G03", "G 1", "G\t0", "G 01", "G011", "G1.", "G0.",
                                "G4", "G10", "G", "N", "N10", " N5", "N-1", "N +2", "X1", "I2", "J", "K.5", "R3",
                                "F100", "M3", "(c)", ";", " ", "\t", "\n", "\r", "\r\n", "0", "1", ".", "-", "g1",
                                "x"])
CHECK_TEXT = st.one_of(st.text("GNXIJKR01234.+- \t\r\nM(;", max_size=40), st.lists(CHECK_PIECES, max_size=20)
                       .map("".join))


@given(CHECK_TEXT)
@SETTINGS
def test_the_block_checks_compiled_scans_are_their_patterns(text):
    _check_scans_agree(text)


def test_the_block_checks_compiled_scans_on_the_nist_programs():
    for name in ("mtc_plate_1.nc", "mtc_cover_rev_a.nc", "d2mi_827-9999-904_op1.nc"):
        _check_scans_agree((ROOT / "fixtures" / "programs" / "nist" / name).read_text(errors="replace"))


def assert_same_with_early_scan(text, monkeypatch, **kwargs):
    """``parse_program`` with the early scan (the text-only passes on a thread of their own while the checks run) and
    without: the same Program, the same format_info (its number styles from the early scan)."""
    monkeypatch.setattr(gcode, "EARLY_SCAN_MIN_BYTES", 0)
    a = parse(text, True, monkeypatch, **kwargs)
    monkeypatch.setattr(gcode, "EARLY_SCAN_MIN_BYTES", 1 << 62)
    b = parse(text, True, monkeypatch, **kwargs)
    if isinstance(a, tuple) or isinstance(b, tuple):
        assert a == b
        return
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), f
    assert (a.lines, a.units, a.axes_present, a.warnings, a.unsupported) == \
        (b.lines, b.units, b.axes_present, b.warnings, b.unsupported)
    assert a.format_info == b.format_info


def test_the_early_scan_reads_the_same(monkeypatch):
    from trueaxis.compiled import aot_available
    from trueaxis.machine import load_machine
    from trueaxis.resources import machine_file
    from trueaxis.sim.programs import cone_flank_program

    if not aot_available():
        missing("the ahead-of-time kernels are not built (make test builds them: python -m trueaxis.warm); the early "
                "scan runs with them only")
    cone = {"axis": [float(np.sin(np.radians(10))), 0.0, float(np.cos(np.radians(10)))], "half_angle_deg": 15.0,
            "base_radius": 40.0, "height_range": [0.0, 20.0]}
    texts = [cone_flank_program(load_machine(machine_file("nmv1500dcg")), cone, n_blocks=3000)]
    texts += [p.read_text(errors="replace") for p in PROGRAMS]
    monkeypatch.setattr(gcode, "_STYLE_BLOCK_LINES", 500)  # several number-style blocks
    for text in texts:
        assert_same_with_early_scan(text, monkeypatch)
        assert_same_with_early_scan(text, monkeypatch, passthrough_unsupported=True)
    monkeypatch.setattr(gcode, "FAST_READ_BLOCK", 7)  # blocks that runs of plain moves skip into
    for text in texts:
        assert_same_with_early_scan(text, monkeypatch)


@settings(max_examples=200, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(st.data())
def test_random_programs_read_the_same_with_the_early_scan(data):
    text = data.draw(st.one_of(fz.mutated_fixture(), fz.SOUP))
    with pytest.MonkeyPatch.context() as mp:
        assert_same_with_early_scan(text, mp)


def test_a_post_is_the_same_with_the_early_scan(monkeypatch):
    """The writer takes the early scan's bytes and line starts (and format_info its number styles): the same output."""
    from trueaxis.compiled import aot_available
    from trueaxis.machine import load_machine
    from trueaxis.nc.setup import Setup
    from trueaxis.postproc.post import post_text
    from trueaxis.resources import machine_file
    from trueaxis.sim.programs import cone_flank_program

    if not aot_available():
        missing("the ahead-of-time kernels are not built (make test builds them: python -m trueaxis.warm); the early "
                "scan runs with them only")
    machine = load_machine(machine_file("nmv1500dcg"))
    cone = {"axis": [float(np.sin(np.radians(10))), 0.0, float(np.cos(np.radians(10)))], "half_angle_deg": 15.0,
            "base_radius": 40.0, "height_range": [0.0, 20.0]}
    text = cone_flank_program(machine, cone, n_blocks=3000)
    outs = []
    for threshold in (0, 1 << 62):
        monkeypatch.setattr(gcode, "EARLY_SCAN_MIN_BYTES", threshold)
        outs.append(post_text(text, machine, "geometric", source="t.ngc", setup=Setup(offsets_zero=True))[0])
    assert outs[0] == outs[1]


G87_PIECES = st.sampled_from(["G", "g", "87", "087", "0087", "8", "7", " ", "\t", "\n", "\x1c", "\u00a0", "0", "1",
                              ".", "X", "8787", "G87", "G 87", "G0 87", "(", ")"])


@given(st.one_of(st.text("Gg0187. \t\n\x1c", max_size=40), st.lists(G87_PIECES, max_size=20).map("".join)))
@SETTINGS
def test_the_g87_scan_finds_what_its_pattern_finds(text):
    """The post's G87 look (its "87"s first, then back to the G) gives the starts of the pattern's matches."""
    from trueaxis.postproc.post import _G87, _g87_starts

    assert _g87_starts(text) == [m.start() for m in _G87.finditer(text)], text


def test_the_g87_scan_on_the_nist_programs():
    from trueaxis.postproc.post import _G87, _g87_starts

    for name in ("mtc_plate_1.nc", "mtc_cover_rev_a.nc", "d2mi_827-9999-904_op1.nc"):
        text = (ROOT / "fixtures" / "programs" / "nist" / name).read_text(errors="replace")
        text += "\nG87 X1\ng 0087Y2\nG\t87.\nG870\n"
        assert _g87_starts(text) == [m.start() for m in _G87.finditer(text)] != []
