"""The writer's compiled fast path (trueaxis.nc.fast_write) writes what the Python path writes, byte for byte:
numbers as ``write_number``, plain blocks as ``rewrite_block``, whole posted programs as with the fast path off."""

from __future__ import annotations

import math
import re
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from conftest import MACHINES, ROOT, tilted_cone_case
from test_post import PROGRAM as POST_PROGRAM
from trueaxis.machine import load_machine
from trueaxis.nc import fast_write
from trueaxis.postproc import post as post_module
from trueaxis.nc.gcode import write_number
from trueaxis.postproc.post import _PLAIN, compensate, rewrite_block

NIST = ROOT / "fixtures" / "programs" / "nist"

# ------------------------------------------------------------------------------------------------ numbers -----

ties = st.builds(lambda k, m, s: s * k / 2.0**m, st.integers(0, 2**40), st.integers(0, 40), st.sampled_from([1, -1]))
near_ties = st.builds(
    lambda n, d, s, step: s * float(np.nextafter(float(f"{n}.5e-{d}"), np.inf * step)) if step else
    s * float(f"{n}.5e-{d}"), st.integers(0, 10**7), st.integers(0, 9), st.sampled_from([1, -1]),
    st.sampled_from([-1, 0, 1]))
values = st.one_of(
    st.floats(-1e6, 1e6, allow_nan=False),
    st.floats(-1e-6, 0.0),  # tiny negatives: no "-0"
    st.floats(1e-7, 1e6).map(lambda x: x),
    st.floats(-1e6, -1e-7),
    ties,
    near_ties,
    st.floats(allow_nan=False, allow_infinity=False),
)


def _fits(x, d):
    return Fraction(abs(x)) * 10**d < 2**53


@settings(max_examples=3000, deadline=None)
@given(values, st.integers(0, 9), st.booleans(), st.booleans())
@example(0.5, 0, True, False)
@example(2.5, 0, True, False)
@example(-2.5, 0, True, True)
@example(0.125, 2, False, False)
@example(-0.375, 2, False, True)
@example(-0.00004, 4, True, False)
@example(120.0, 3, True, True)
@example(1.0000049999999999, 5, True, False)
@example(-0.0, 5, True, True)
@example(4503599627370495.5, 0, True, False)
@example(0.25, 0, True, False)
@example(0.7500000000000001, 0, False, True)
def test_the_compiled_formatter_writes_what_write_number_writes(x, d, lz, tp):
    got = fast_write.format_number(x, d, leading_zero=lz, trailing_point=tp)
    if not _fits(x, d):
        assert got is None
        return
    assert got == write_number(x, d, leading_zero=lz, trailing_point=tp)


def test_the_formatter_on_a_sweep_of_ties_and_their_neighbours():
    rng = np.random.default_rng(1)
    for d in range(0, 10):
        n = rng.integers(0, 10**6, 2000)
        base = np.array([float(f"{k}.5e-{d}") for k in n.tolist()])
        for x in np.r_[base, np.nextafter(base, np.inf), np.nextafter(base, -np.inf), -base,
                       rng.uniform(-1e4, 1e4, 200)].tolist():
            assert fast_write.format_number(x, d) == write_number(x, d), (x, d)


def test_numbers_it_cannot_write_exactly_go_to_the_python_path():
    assert fast_write.format_number(float("nan"), 5) is None
    assert fast_write.format_number(float("inf"), 5) is None
    assert fast_write.format_number(1e12, 5) is None  # 1e17 >= 2**53
    assert fast_write.format_number(1.0, 23) is None
    assert fast_write.format_number(1e-30, 22) == "0"


@settings(max_examples=2000, deadline=None)
@given(st.floats(1e-20, 1e15), st.floats(1e-10, 1e22))
def test_the_two_product_is_error_free(a, b):
    p = a * b
    assume(math.isfinite(p) and p > 1e-290)
    e = fast_write._two_product_error(a, b, p)
    assert Fraction(a) * Fraction(b) == Fraction(p) + Fraction(e)


# ------------------------------------------------------------------------------------------------- blocks -----

BLANK = st.sampled_from(["", " ", "  ", "\t"])
NUMBER = st.one_of(
    st.sampled_from(["0", "1", "-1.5", "+.5", "3.", "-.25", "12.3456", "007", "-0"]),
    st.floats(-999, 999).map(lambda x: f"{x:.4f}"),
)
G_FORMS = st.sampled_from([None, "G0", "G1", "G00", "G01", "g1", "g01", "G001", "G2", "G03", "G3", "G0001"])
LETTERS = "XYZABCIJK"


@st.composite
def plain_blocks(draw):
    parts = [draw(BLANK)]
    if draw(st.booleans()):
        parts += [draw(st.sampled_from("Nn")) + str(draw(st.integers(0, 99999))), draw(BLANK)]
    g = draw(G_FORMS)
    if g:
        parts += [g, draw(BLANK)]
    for c in LETTERS:
        if draw(st.integers(0, 2)):
            letter = c if draw(st.integers(0, 4)) else c.lower()
            parts += [letter, draw(BLANK), draw(NUMBER), draw(BLANK)]
    if draw(st.integers(0, 3)) == 0:
        parts += [draw(st.sampled_from("Rr")), draw(BLANK), draw(NUMBER), draw(BLANK)]
    if draw(st.booleans()):
        parts += [draw(st.sampled_from("Ff")), draw(BLANK), draw(NUMBER), draw(BLANK)]
    return "".join(parts)


NOT_PLAIN = st.sampled_from([" M3", " S1000", " (comment)", " ;comment", "M8", " G17", "T1", " X1", "P2", " H1",
                             " N10", "G4", "G1.5", "X", " F", "/", "%", "\x0c", " X1.2.3", "G 1"])


def _expected(body, ending, motion, vals, letters, decs, lz, tp, sep, was_arc, arc=False, centre=()):
    words = [a + write_number(v, d, leading_zero=lz, trailing_point=tp) for a, v, d in zip(letters, vals, decs)]
    words += [c + write_number(v, d, leading_zero=lz, trailing_point=tp) for c, v, d in centre]
    return rewrite_block(body, motion, words, arc=arc, was_arc=was_arc, sep=sep) + ending


@settings(max_examples=1500, deadline=None)
@given(plain_blocks(), st.one_of(st.just(""), NOT_PLAIN), st.integers(0, 12), st.sampled_from(["", "\n", "\r\n"]),
       st.integers(0, 3), st.sampled_from(["XYZ", "XYZBC", "XZ", "XYZABC"]), st.data())
def test_the_compiled_rewrite_is_rewrite_block_for_plain_lines(block, junk, at, ending, motion, letters, data):
    body = block[:at] + junk + block[at:] if junk else block
    vals = data.draw(st.lists(st.floats(-2000, 2000), min_size=len(letters), max_size=len(letters)))
    decs = data.draw(st.lists(st.integers(0, 7), min_size=len(letters), max_size=len(letters)))
    lz, tp, sep = data.draw(st.booleans()), data.draw(st.booleans()), data.draw(st.sampled_from(["", " "]))
    arc = data.draw(st.booleans())  # a kept arc: its R word stays, or its centre words follow the axis words
    centre = ()
    if arc and data.draw(st.booleans()):
        centre = tuple(zip(data.draw(st.sampled_from(["IJ", "IK", "JK"])),
                           data.draw(st.lists(st.floats(-500, 500), min_size=2, max_size=2)),
                           data.draw(st.lists(st.integers(0, 7), min_size=2, max_size=2))))
    got = fast_write.rewrite_line(body + ending, motion, vals, letters, decs, leading_zero=lz, trailing_point=tp,
                                  sep=sep, arc=arc, centre=centre)
    plain = "(" not in body and ";" not in body and _PLAIN.match(body) is not None
    if not plain:
        assert got is None, (body, got)
        return
    for was_arc in (False, True):
        assert got == _expected(body, ending, motion, vals, letters, decs, lz, tp, sep, was_arc, arc, centre), body


@settings(max_examples=3000, deadline=None)
@given(st.text(alphabet="NnGgXYZABCIJKRrFfxyzMS0123.-+ \t();", max_size=24))
def test_the_compiled_grammar_is_the_plain_pattern(body):
    got = fast_write.rewrite_line(body, 1, [1.0, 2.0, 3.0], "XYZ", [5, 5, 5])
    plain = "(" not in body and ";" not in body and _PLAIN.match(body) is not None
    assert (got is not None) == plain, body
    if plain:
        assert got == _expected(body, "", 1, [1.0, 2.0, 3.0], "XYZ", [5, 5, 5], True, False, " ", False)


def test_lines_it_does_not_take():
    assert fast_write.rewrite_line("N10 G1 X1 Y2 M3", 1, [1.0], "X", [5]) is None
    assert fast_write.rewrite_line("G1 X1 (cut)", 1, [1.0], "X", [5]) is None
    assert fast_write.rewrite_line("G1 X1 Ä", 1, [1.0], "X", [5]) is None  # not ASCII
    assert fast_write.rewrite_line("G1 X1", 1, [1e15], "X", [5]) is None  # a number past 2**53 at 5 decimals
    assert fast_write.rewrite_line("G1 X1", 1, [1.0], "X", [5], sep="  ") is None
    assert fast_write.rewrite_line("N5 g01 x1 y2 R5 F 100\r\n", 0, [1.25, -0.5], "XY", [5, 5], leading_zero=False,
                                   sep="") == "N5G00X1.25Y-.5F 100\r\n"
    assert fast_write.rewrite_line("N5 G02 X1 Y2 r 5 F100", 2, [1.25, -0.5], "XY", [5, 5], arc=True) == \
        "N5 G02 X1.25 Y-0.5 r 5 F100"
    assert fast_write.rewrite_line("G3 X1 Y2 I1 J0", 3, [1.25, -0.5], "XY", [5, 5], arc=True,
                                   centre=[("I", 0.1, 4), ("J", -2.0, 4)], trailing_point=True) == \
        "G3 X1.25 Y-0.5 I0.1 J-2."


# ------------------------------------------------------------------------------------------------ end to end ---

# The post's test program (tests/test_post.py) with more plain-block spellings: R on a line, lower case, no separator,
# a non-plain word (M8).
PROGRAM = POST_PROGRAM.replace("N60 G91", "N55 G1 X60 Y70\nN56 g01 x61 y71 f200\nN57 G00X62Y72Z-100\n"
                                          "N58 X63 Y73 Z-101 M8\nN60 G91")


def _both(text, machine, monkeypatch, **kw):
    """(output with the fast path, output without it, fraction of the compensated lines the fast path took)."""
    seen = []
    fast_lines = post_module._Poster._fast_lines

    def spy(self, *args):
        res = fast_lines(self, *args)
        seen.append(None if res is None else float(res["handled"].mean()))
        return res

    monkeypatch.setattr(post_module._Poster, "_fast_lines", spy)
    monkeypatch.setattr(post_module, "FAST_WRITE", True)
    fast = compensate(text, machine, "geometric", **kw)
    monkeypatch.setattr(post_module, "FAST_WRITE", False)
    slow = compensate(text, machine, "geometric", **kw)
    return fast, slow, seen[0]


@pytest.fixture(scope="module")
def xh714():
    return load_machine(MACHINES / "xh714.toml")


def _layout_variant(text: str, variant: str) -> str:
    """The program without the space between words ("no separator", comments kept) or with CRLF line ends ("crlf");
    as it is for any other variant."""
    if variant == "no separator":
        return "\n".join(re.sub(r"(?<=[0-9.]) (?=[A-Za-z])", "", ln) if "(" not in ln else ln
                         for ln in text.split("\n"))
    if variant == "crlf":
        return text.replace("\n", "\r\n")
    return text


@pytest.mark.parametrize("variant", ["as is", "no separator", "crlf", "trailing point", "inch"])
def test_the_test_program_posts_the_same_with_and_without_the_fast_path(xh714, monkeypatch, variant):
    text = _layout_variant(PROGRAM, variant)
    if variant == "trailing point":
        text = text.replace("X150", "X150.").replace("Z-105", "Z-105.")
    elif variant == "inch":
        text = text.replace("G21", "G20")
        text = re.sub(r"([XYZIJRxyzijr])(-?)(\d+)", lambda m: f"{m[1]}{m[2]}{int(m[3]) / 40:g}", text)
    fast, slow, taken = _both(text, xh714, monkeypatch)
    assert fast == slow
    assert taken is not None and taken > 0.3


@pytest.mark.parametrize("name", ["mtc_cover_rev_a.nc", "mtc_plate_1.nc", "d2mi_827-9999-904_op1.nc",
                                  "d2mi ascii"])
def test_the_nist_programs_post_the_same_with_and_without_the_fast_path(xh714_wide, monkeypatch, name):
    if name == "d2mi ascii":  # CRLF line endings through the fast path (the file itself is not ASCII)
        text = (NIST / "d2mi_827-9999-904_op1.nc").read_text(encoding="latin-1")
        text = "".join(c if c.isascii() else "?" for c in text)
    else:
        text = (NIST / name).read_text(errors="replace")
    # their work offsets and tool lengths are not at hand: zero, said explicitly (the setup has its own tests);
    # d2mi compensates its cutter radius (G41): the control's part, passed through on request
    fast, slow, taken = _both(text, xh714_wide, monkeypatch, offsets_zero=True,
                              passthrough_unsupported="d2mi" in name)
    assert fast == slow
    if text.isascii():
        assert taken is not None and taken > 0.2
    else:
        assert taken is None  # not ASCII: the whole program by the Python path


def test_a_five_axis_program_posts_the_same_with_and_without_the_fast_path(monkeypatch):
    m, text = tilted_cone_case(3000)
    fast, slow, taken = _both(text, m, monkeypatch)
    assert fast == slow
    assert taken > 0.9


# -------------------------------------------------------------------- split moves and fitted arcs (pieces) -----

# Long moves that split and arcs that are fitted (or linearised) in all three planes, with line numbers, comments,
# G91 runs, G93 and a rapid among them: the compiled writer takes the plain ones, the Python path the rest.
SPLIT_PROGRAM = """%
O1000 (split pieces and fitted arcs)
N10 G21 G90 G17 G94 F500
N20 G0 X-1500 Y-1200 Z-900
N30 G1 X1500 Y1200 Z-100 F800
N40 G1 X-1400 Y1100 Z-800 (a comment on a split line)
N50 G3 X1400 Y1100 I1400 J0
N60 G91 G1 X-300 Y-900
N65 G3 X-100 Y100 R100
N70 G90 G18
N71 G2 X-1500 Z-300 I-1200 K500
N80 G19
N81 G3 Y-1000 Z-900 R1300
N90 G17 G3 X1400 Y1100 R2000
N100 g01 x-1500 y-1000 z-200 f300
N110 G93 G1 X1500 Y1000 Z-800 F0.5
N120 G94 G1 X-1500 Y0 Z-500 F600
N130 G0 X1500 Y-1200 Z-100
N140 G90.1
N141 G3 X-1500 Y-1200 I0 J-1200
N142 G2 X1500 Y-1200 I0 J-1200
N150 M2
%
"""


def _both_pieces(text, machine, monkeypatch, **kw):
    """(fast output, Python output, candidates the compiled piece writer took, candidates it was given)."""
    seen = [0, 0]
    kernel = fast_write.pieces

    def spy(*args):
        res = kernel(*args)
        seen[0] += int(res[0].sum())
        seen[1] += res[0].size
        return res

    monkeypatch.setattr(fast_write, "pieces", spy)
    monkeypatch.setattr(post_module, "FAST_WRITE", True)
    fast = compensate(text, machine, "geometric", **kw)
    monkeypatch.setattr(post_module, "FAST_WRITE", False)
    slow = compensate(text, machine, "geometric", **kw)
    return fast, slow, seen[0], seen[1]


@pytest.mark.parametrize("arcs", [True, False])
@pytest.mark.parametrize("variant", ["as is", "no separator", "crlf", "inch", "no leading zero"])
def test_split_moves_and_fitted_arcs_post_the_same_with_and_without_the_compiled_writer(xh714_wide, monkeypatch,
                                                                                        variant, arcs):
    text = _layout_variant(SPLIT_PROGRAM, variant)
    if variant == "inch":
        text = text.replace("G21", "G20").replace("F500", "F20").replace("F800", "F30").replace("F600", "F25")
        text = re.sub(r"([XYZIJKRxyzijkr])(-?)(\d+)", lambda m: f"{m[1]}{m[2]}{int(m[3]) / 40:g}", text)
    elif variant == "no leading zero":
        text = text.replace("F0.5", "F.5").replace("X1500 Y1000", "X1500 Y1000.")
    fast, slow, taken, given_ = _both_pieces(text, xh714_wide, monkeypatch, offsets_zero=True, tol_um=0.2,
                                             arcs=arcs)
    assert fast == slow
    assert taken > 0  # the compiled writer wrote split lines ...
    assert taken < given_ or variant == "no separator"  # ... and left the commented one to the Python path


def test_the_piece_writer_leaves_lines_it_cannot_write_exactly():
    src = np.frombuffer(b"N1 G1 X1 Y2 (note)\nN2 G1 X1 Y2 F100\n", np.uint8)
    line_start = np.array([0, 19, 36], np.int64)
    pts = np.array([[1.5, 2.5, 0, 0, 0, 0], [3.0, 4.0, 0, 0, 0, 0], [1e300, 0, 0, 0, 0, 0], [3.0, 4.0, 0, 0, 0, 0]])
    args = (src, line_start, np.array([0, 1], np.int64), np.array([1, 1], np.int64), np.array([1, 1, 1, 1], np.int64),
            np.array([0, 2, 4], np.int64), pts, np.array([0, 1], np.int64), np.frombuffer(b"XY", np.uint8).copy(),
            np.array([[5, 5], [6, 6]], np.int64), np.zeros(2, np.bool_), np.zeros(4, np.int64), np.zeros((4, 2)),
            np.zeros((4, 2), np.uint8), np.zeros((4, 2), np.int64), True, False, 32)
    ok, blob, b_start, b_end = fast_write.pieces(*args)
    assert ok.tolist() == [False, False]  # a comment; a number beyond 2**53 at 5 decimals
    pts[2, 0] = -0.25
    ok, blob, b_start, b_end = fast_write.pieces(*args)
    assert ok.tolist() == [False, True]
    assert blob[b_start[1] : b_end[1]].tobytes() == b"N2 G1 X-0.25 Y0 F100\nG1 X3 Y4\n"
