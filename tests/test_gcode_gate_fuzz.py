"""The G-code input gate fuzzed against LinuxCNC (issue 17): generated blocks, with parameters and expressions in
their words, read by ``rs274`` and by us.

- whatever we read, rs274 reads too, along the same path (end points in machine coordinates within 1e-4); what we
  refuse and rs274 reads, we refuse saying what is not read (the option that passes it, or "not evaluated here");
- ``trueaxis post`` on generated programs never shows a traceback: exit 0, 1 or 2 with one line on stderr, and rs274
  reads what it writes.

- generated expression trees (every operator and function) have the value rs274 gives them, or both refuse them;
- generated control flow (subroutines, if / else, while, do-while, repeat, nested) and canned cycles (G73, G81-G89 in
  G90 and G91, G98 and G99, L repeats, modal holes) run the path rs274 runs.

Bounded: one rs274 run per example, derandomized, 740 examples in all (about 40 s on one core).
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import MACHINES
from test_interp_corpus import drop_repeats, run_rs274_verdict
from trueaxis.cli import main as cli_main
from trueaxis.nc.gcode import GcodeError, parse_program

SETTINGS = settings(deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
HEAD = "G21 G90 G17 G94 G98 F100\n#1=2\n#<v>=3\nG0 X0 Y0 Z0\n"
# what a refusal of a program rs274 reads must say: which feature is not read, and how to pass it
NOT_READ = ("--passthrough-unsupported", "not evaluated here", "not supported")

NUMBER = st.one_of(st.integers(-20, 20).map(str), st.floats(-20, 20, allow_nan=False).map(lambda v: f"{v:.3f}"))
EXPRESSION = st.one_of(
    NUMBER,
    st.sampled_from(["#1", "#<v>", "-#1", "#2", "[#1*#<v>]", "[SQRT[2]]", "[ATAN[1]/[1]]", "[#1 GT 1]", "[1/0]",
                     "[SIN[30]*4]", "[10 MOD 3]", "[2**3]", "[-2**0.5]", "#<undefined>", "[LN[0]]", "[FIX[2.5]]",
                     "[ROUND[2.5]]", "[#1+]", "[ABS[-3]]", "#5221"]),
    st.builds(lambda a, op, b: f"[{a} {op} {b}]", NUMBER, st.sampled_from(["+", "-", "*", "/", "MOD", "EQ", "LT"]),
              NUMBER),
)
CODE = st.sampled_from(["G0", "G1", "G2", "G3", "G4", "G17", "G18", "G19", "G20", "G21", "G28", "G52", "G53", "G54",
                        "G55", "G80", "G90", "G91", "G90.1", "G91.1", "G92", "G92.1", "G93", "G94", "G40", "G41",
                        "G43", "G49", "G64", "G73", "G81", "G82", "G83", "G85", "G89", "G98", "G99", "M0", "M1",
                        "M3", "M4", "M5", "M7", "M8", "M9", "M6"])
WORD = st.builds(lambda letter, value: f"{letter}{value}", st.sampled_from(list("XYZXYZIJRPQLFN")), EXPRESSION)
BLOCK = st.lists(st.one_of(CODE, WORD, WORD), min_size=1, max_size=4).map(" ".join)


LEAF = st.one_of(st.integers(-9, 9).map(str), st.floats(-9, 9, allow_nan=False).map(lambda v: f"{v:.3f}"),
                 st.sampled_from(["#1", "#<v>", "#2"]))
FUNCTIONS = ["ABS", "SIN", "COS", "TAN", "SQRT", "FIX", "FUP", "ROUND", "EXP", "LN", "ASIN", "ACOS"]
OPERATORS = ["+", "-", "*", "/", "MOD", "**", "EQ", "NE", "GT", "GE", "LT", "LE", "AND", "OR", "XOR"]
TREE = st.recursive(LEAF, lambda inner: st.one_of(
    st.builds(lambda a, op, b: f"[{a} {op} {b}]", inner, st.sampled_from(OPERATORS), inner),
    st.builds(lambda a, op, b, op2, c: f"[{a} {op} {b} {op2} {c}]", inner, st.sampled_from(OPERATORS), inner,
              st.sampled_from(OPERATORS), inner),
    st.builds(lambda f, a: f"{f}[{a}]", st.sampled_from(FUNCTIONS), inner),
    st.builds(lambda a, b: f"ATAN[{a}]/[{b}]", inner, inner),
), max_leaves=6)


def ours(text):
    try:
        return parse_program(text, "fuzz.ngc"), None
    except GcodeError as exc:
        return None, str(exc)


@settings(SETTINGS, max_examples=200)
@given(block=BLOCK)
def test_generated_blocks_are_read_as_rs274_reads_them_or_refused_saying_what(block):
    text = HEAD + block + "\nM2\n"
    prog, refusal = ours(text)
    with tempfile.TemporaryDirectory() as tmp:
        rc, message, rs_end = run_rs274_verdict(text, Path(tmp))
    if prog is not None:
        assert rc == 0, f"we read a block rs274 refuses: {block!r}: {message[-200:]}"
        mine, theirs = drop_repeats(prog.end_machine), drop_repeats(rs_end)
        assert len(mine) == len(theirs), block
        np.testing.assert_allclose(mine, theirs, atol=1e-4, err_msg=block)
    elif rc == 0:
        # (rs274 marks an absent Q word with -1, so it takes "Q-1 Q-1" for no Q at all; we refuse two Q words)
        assert any(s in refusal for s in NOT_READ) or "more than one Q word" in refusal, \
            f"we refuse a block rs274 reads: {block!r}: {refusal}"
    else:
        assert refusal.startswith("fuzz.ngc:") and len(refusal.splitlines()) == 1


@settings(SETTINGS, max_examples=40)
@given(blocks=st.lists(BLOCK, min_size=1, max_size=3))
def test_the_post_command_never_shows_a_traceback_and_rs274_reads_its_output(blocks):
    text = HEAD + "\n".join(blocks) + "\nG1 X5 Y5 Z-1\nM2\n"
    with tempfile.TemporaryDirectory() as tmp:
        src, out = Path(tmp) / "in.ngc", Path(tmp) / "out.ngc"
        src.write_text(text)
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = cli_main(["post", str(src), "-o", str(out), "--machine", str(MACHINES / "xh714.toml")])
        assert code in (0, 1, 2, 3), (code, err.getvalue())  # 3: a refused program (README, how it fails)
        if code:
            assert len(err.getvalue().strip().splitlines()) == 1, err.getvalue()
            assert not out.exists()
            return
        rc, message, _ = run_rs274_verdict(out.read_text(), Path(tmp))
        assert rc == 0, f"rs274 refuses our output: {message[-300:]}"


@settings(SETTINGS, max_examples=200)
@given(expression=TREE)
def test_generated_expressions_have_the_value_rs274_gives_them(expression):
    """The evaluator against LinuxCNC's: the value rs274 moves to (printed to 4 decimals), or both refuse."""
    text = HEAD + f"G0 X{expression}\nM2\n"
    prog, refusal = ours(text)
    with tempfile.TemporaryDirectory() as tmp:
        rc, message, rs_end = run_rs274_verdict(text, Path(tmp))
    if rc != 0:
        assert prog is None, f"we read {expression!r}, rs274 refuses it: {message[-200:]}"
        return
    if prog is None:
        # rs274 reads values of any size; the reader takes words below 1e9 (a bound, said so)
        assert "out of range" in refusal, f"we refuse {expression!r} which rs274 reads: {refusal}"
        return
    x = prog.end[-1, 0]
    assert abs(x - rs_end[-1, 0]) <= 5e-5 + 1e-9 * abs(x), (expression, x, rs_end[-1, 0])


SMALL = st.recursive(st.sampled_from(["#1", "#2", "#3", "#<_g>", "1", "2.5", "-3", "0"]), lambda inner: st.one_of(
    st.builds(lambda a, op, b: f"[{a} {op} {b}]", inner, st.sampled_from(["+", "-", "*", "GT", "LT", "EQ", "MOD"]),
              inner),
    st.builds(lambda f, a: f"{f}[{a}]", st.sampled_from(["ABS", "FIX", "ROUND", "SIN"]), inner)), max_leaves=3)
SUBS = ("o<s1> sub\nG0 X#1 Y[#1*2]\n#1=[#1+1]\no<s1> endsub\n"
        "o<s2> sub\n#<_g>=[#<_g>+#1]\no<s1> call [#<_g>]\nG0 Z#1\no<s2> endsub\n")


@st.composite
def statements(draw, depth=0, labels=None):
    labels = labels if labels is not None else [100]
    out = []
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["move", "move", "assign", "call"] + (["if", "while", "repeat", "do"]
                                                                          if depth < 2 else [])))
        if kind == "move":
            out.append(f"G0 X{draw(SMALL)} Y{draw(SMALL)}")
        elif kind == "assign":
            out.append(f"{draw(st.sampled_from(['#1', '#2', '#3', '#<_g>']))}={draw(SMALL)}")
        elif kind == "call":
            out.append(f"o<s{draw(st.integers(1, 2))}> call [{draw(SMALL)}]")
        else:
            labels[0] += 1
            lab = labels[0]
            body = draw(statements(depth + 1, labels))
            if kind == "if":
                other = draw(statements(depth + 1, labels))
                out.append(f"o{lab} if [{draw(SMALL)}]\n{body}\no{lab} else\n{other}\no{lab} endif")
            elif kind == "while":
                c = f"#{20 + depth}"
                out.append(f"{c}=0\no{lab} while [{c} LT {draw(st.integers(0, 3))}]\n{body}\n{c}=[{c}+1]\n"
                           f"o{lab} endwhile")
            elif kind == "do":
                c = f"#{20 + depth}"
                out.append(f"{c}=0\no{lab} do\n{body}\n{c}=[{c}+1]\no{lab} while [{c} LT {draw(st.integers(0, 3))}]")
            else:
                out.append(f"o{lab} repeat [{draw(st.integers(0, 3))}]\n{body}\no{lab} endrepeat")
    return "\n".join(out)


@settings(SETTINGS, max_examples=150)
@given(body=statements())
def test_generated_control_flow_runs_the_path_rs274_runs(body):
    """Subroutines, if / else, while, do-while and repeat nested at random: the flat program moves where rs274 moves."""
    text = "G21 G90 G17 G94 F100\n#<_g>=1\n" + SUBS + "G0 X0 Y0 Z0\n" + body + "\nM2\n"
    prog, refusal = ours(text)
    with tempfile.TemporaryDirectory() as tmp:
        rc, message, rs_end = run_rs274_verdict(text, Path(tmp))
    if rc != 0:
        assert prog is None, f"we read a program rs274 refuses: {message[-200:]}\n{text}"
        return
    assert prog is not None, f"we refuse what rs274 reads: {refusal}\n{text}"
    assert len(prog) == len(rs_end), text
    np.testing.assert_allclose(prog.end_machine, rs_end, atol=1e-4, err_msg=text)


COORD = st.integers(-20, 20).map(lambda v: f"{v / 2:g}")


@st.composite
def cycle_programs(draw):
    """A canned cycle in G90 or G91, G98 or G99, with its words, a repeat count now and then, and modal holes."""
    code = draw(st.sampled_from(["G81", "G82", "G83", "G73", "G85", "G89"]))
    dist = draw(st.sampled_from(["G90", "G91"]))
    words = [f"X{draw(COORD)}", f"Y{draw(COORD)}", f"Z{draw(st.integers(-12, 2).map(lambda v: f'{v / 2:g}'))}",
             f"R{draw(st.integers(-4, 6).map(lambda v: f'{v / 2:g}'))}"]
    if code in ("G83", "G73"):
        words.append(f"Q{draw(st.sampled_from(['0.5', '1', '2.5']))}")
    if code in ("G82", "G89"):
        words.append("P0.5")
    if draw(st.booleans()):
        words.append(f"L{draw(st.integers(1, 3))}")
    holes = [" ".join(draw(st.lists(st.builds(lambda a, v: f"{a}{v}", st.sampled_from("XY"), COORD), min_size=1,
                                    max_size=2, unique_by=lambda w: w[0])))
             for _ in range(draw(st.integers(0, 2)))]
    start_z = draw(st.sampled_from(["5", "0.5", "-1"]))
    return (f"G21 G90 G17 G94 F100\nG0 X0 Y0 Z{start_z}\n{dist} {draw(st.sampled_from(['G98', 'G99']))} {code} "
            + " ".join(words) + "\n" + "".join(h + "\n" for h in holes) + "G80\nG90 G0 Z10\nM2\n")


@settings(SETTINGS, max_examples=150)
@given(text=cycle_programs())
def test_generated_canned_cycles_in_g90_and_g91_run_the_path_rs274_runs(text):
    prog, refusal = ours(text)
    with tempfile.TemporaryDirectory() as tmp:
        rc, message, rs_end = run_rs274_verdict(text, Path(tmp))
    if rc != 0:
        assert prog is None, f"we read a program rs274 refuses: {message[-200:]}\n{text}"
        return
    assert prog is not None, f"we refuse what rs274 reads: {refusal}\n{text}"
    mine, theirs = drop_repeats(prog.end_machine), drop_repeats(rs_end)
    assert len(mine) == len(theirs), text
    np.testing.assert_allclose(mine, theirs, atol=1e-4, err_msg=text)


# An arc's centre words as rs274 checks them: none along the plane's normal, R not with I J K. Each block inside a
# run of plain arcs (G17: the compiled reader's path, runs of 16 lines and more) and alone (the reader's own), read by
# rs274 and by us: both refuse, and the arc with its own plane's words only is read by both along the same path.
def _arc_run(x0):
    return "".join(f"G{2 + k % 2} X{x0 + (k + 1) * 2} Y0 I1 J0\n" for k in range(20))


@pytest.mark.parametrize("plane, bad, good", [
    ("", "G2 X40 Y0 I1 J0 K5", "G2 X40 Y0 I1 J0"),
    ("G18", "G2 X40 Z2 I0 J0 K2", "G2 X40 Z2 I0 K2"),
    ("G19", "G2 Y2 Z2 I0 J0 K2", "G2 Y2 Z2 J0 K2"),
    ("", "G2 X40 Y0 R1 I1", "G2 X40 Y0 R1"),
])
@pytest.mark.parametrize("in_run", [False, True])
def test_an_arcs_centre_words_are_checked_as_rs274_checks_them(tmp_path, plane, bad, good, in_run):
    head = "G21 G90 G17 G94 F100\nG0 X0 Y0 Z0\n" + (_arc_run(-2) if in_run else "G1 X38 Y0\n")
    tail = _arc_run(40) if in_run and not plane else ""
    for block, refused in ((bad, True), (good, False)):
        text = head + (plane + "\n" if plane else "") + block + "\n" + tail + "M2\n"
        prog, refusal = ours(text)
        rc, message, rs_end = run_rs274_verdict(text, tmp_path / f"rs{int(refused)}")
        assert (rc != 0) == refused, (block, message[-200:])
        if refused:
            line = text.count("\n", 0, text.index(block)) + 1
            assert refusal is not None and refusal.startswith(f"fuzz.ngc:{line}: "), (block, refusal)
            assert ("word given for an arc" in refusal) or ("R and I J K" in refusal)
        else:
            assert refusal is None, refusal
            np.testing.assert_allclose(drop_repeats(prog.end_machine), drop_repeats(rs_end), atol=1e-4)
