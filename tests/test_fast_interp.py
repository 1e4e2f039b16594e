"""The reader's compiled runs of straight moves (trueaxis.nc.fast_interp) give the motion table the reader's own
loop gives, number for number, and the post writes the same bytes with them as without them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import MACHINES, ROOT
from trueaxis.machine import load_machine
from trueaxis.nc import fast_interp, gcode
from trueaxis.nc.gcode import GcodeError, parse_program
from trueaxis.postproc.post import compensate
from trueaxis.nc.setup import Setup
from trueaxis.sim.programs import cone_flank_program

NIST = ROOT / "fixtures" / "programs" / "nist"
CONE = {"axis": [math.sin(math.radians(10)), 0.0, math.cos(math.radians(10))], "half_angle_deg": 15.0,
        "base_radius": 40.0, "height_range": [0.0, 20.0]}


def _runs(monkeypatch):
    """Count the lines the compiled runs take (a spy on straight_run)."""
    taken = [0]
    real = fast_interp.straight_run

    def spy(*args):
        res = real(*args)
        taken[0] += res[0]
        return res

    monkeypatch.setattr(fast_interp, "straight_run", spy)
    return taken


def _tables(text, monkeypatch, **kw):
    """(Program with the compiled runs, Program without them, lines the runs took)."""
    kw.setdefault("setup", Setup(offsets_zero=True))
    kw.setdefault("require_setup", True)
    taken = _runs(monkeypatch)
    monkeypatch.setattr(fast_interp, "ENABLED", True)
    fast = parse_program(text, "t.ngc", **kw)
    monkeypatch.setattr(fast_interp, "ENABLED", False)
    slow = parse_program(text, "t.ngc", **kw)
    return fast, slow, taken[0]


def _assert_same_program(a, b):
    assert vars(a).keys() == vars(b).keys()
    for key, v in vars(a).items():
        w = getattr(b, key)
        if isinstance(v, np.ndarray):
            assert v.dtype == w.dtype and v.shape == w.shape and v.tobytes() == w.tobytes(), key
        else:
            assert repr(v) == repr(w), key


@pytest.mark.parametrize("name", ["mtc_cover_rev_a.nc", "mtc_plate_1.nc", "d2mi_827-9999-904_op1.nc"])
def test_the_nist_programs_read_to_the_same_table_with_and_without_the_compiled_runs(monkeypatch, name):
    text = (NIST / name).read_text(encoding="latin-1")
    text = "".join(c if c.isascii() else "?" for c in text)  # the pre-scan (and so the runs) takes ASCII only
    fast, slow, taken = _tables(text, monkeypatch, passthrough_unsupported="d2mi" in name)
    _assert_same_program(fast, slow)
    assert taken > 0.2 * len(slow)


SYNTHETIC = """%
G21 G90 G17 G94
G0 X0 Y0 Z5
G1 Z-1 F300
""" + "".join(f"X{k}.{k % 7} Y{-k * 0.25:.4f}\n" for k in range(1, 40)) + """G91
""" + "".join(f"G1 X0.1 Y-.03 Z0.001{' F250' if k == 20 else ''}\n" for k in range(40)) + """G90 G7
""" + "".join(f"G0 X{20 + k} Z{k * 0.5}\n" for k in range(30)) + """G8 G93
""" + "".join(f"G1 X{k} Y{k % 5} Z1 F{100 + k % 3}\n" for k in range(40)) + """G94 F400
""" + "".join(f"N{k}G1X{k}.123456789012Y-{k}.5 A{k * 3} B{k} C-{k}.25\n" for k in range(40)) + """G20
""" + "".join(f"X{k * 0.01:.5f} Y.{k:03d}\n" for k in range(1, 40)) + """G0 X0 Y0 Z1
G2 X1 Y0 I.5 J0 F20
""" + "".join(f"G1 X{k * 0.02:.4f} F{10 + k}\n" for k in range(30)) + """M30
%
"""


@pytest.mark.parametrize("block", [4096, 7, 16])
def test_modal_runs_read_to_the_same_table(monkeypatch, block):
    """Incremental moves, G7 diameters, G93 feeds on every line, feed changes, A B C words, inch, an arc between
    runs, and runs cut at the pre-scan's block boundaries."""
    monkeypatch.setattr(gcode, "FAST_READ_BLOCK", block)
    fast, slow, taken = _tables(SYNTHETIC, monkeypatch)
    _assert_same_program(fast, slow)
    if block >= 16:
        assert taken > 0.5 * len(slow)


def _arc_lines(n, plane):
    """Quarter circles of radius 1 around the origin in the plane's axes, the centre given relative (I J K)."""
    names = {17: "XYIJ", 18: "ZXKI", 19: "YZJK"}[plane]
    out, angle = [], 0.0
    for k in range(n):
        a0, a1 = math.cos(angle), math.sin(angle)
        angle += math.pi / 2
        b0, b1 = math.cos(angle), math.sin(angle)
        out.append(f"{'G3 ' if k == 0 else ''}{names[0]}{b0:.6f} {names[1]}{b1:.6f} {names[2]}{-a0:.6f} "
                   f"{names[3]}{-a1:.6f}\n")
    return out


ARCS = ("G21 G90 G94 G17\nG0 X1 Y0 Z0\nG1 F200 X1\n" + "".join(_arc_lines(24, 17))
        + "G18\nG0 X0 Y0 Z1\nG1 X0\n" + "".join(_arc_lines(24, 18))
        + "G19\nG0 X0 Y1 Z0\nG1 Y1\n" + "".join(_arc_lines(24, 19))
        # G90.1: absolute centres; G91 incremental ends
        + "G17 G90.1\nG0 X1 Y0 Z0\n" + "".join(f"G2 X{1 if k % 2 else -1} Y0 I0 J0\n" for k in range(20))
        + "G91.1 G91\n" + "".join(f"G3 X{-2 if k % 2 == 0 else 2} Y0 I{-1 if k % 2 == 0 else 1} J0\n"
                                 for k in range(20))
        + "G90\nG0 X10 Y0\n")
# end points off the circle (radius 10): well within the tolerance, near its limit (LinuxCNC's 0.02 sqrt 2 mm, 0.28 %
# of the radius), beyond it
OFF = ("0.001", "0.0282842", "0.02828427124746", "0.0282843")


@pytest.mark.parametrize("cut", [None, *OFF])
def test_arcs_read_to_the_same_table(monkeypatch, cut):
    """I J K arcs in the three planes, absolute (G90.1) and relative centres, incremental ends, and end points near
    the reader's limit of the circle (it decides those itself)."""
    offs = OFF[: OFF.index(cut) + 1] if cut else ()
    text = ARCS + "".join(f"G2 X-1{d} Y0 I-10 J0\nG0 X10 Y0\n" for d in offs) + "M30\n"
    if cut == OFF[-1]:  # off the circle by more than the tolerance: the same refusal
        msgs = []
        for on in (True, False):
            monkeypatch.setattr(fast_interp, "ENABLED", on)
            with pytest.raises(GcodeError) as info:
                parse_program(text, "t.ngc", setup=Setup(offsets_zero=True), require_setup=True)
            msgs.append(str(info.value))
        assert msgs[0] == msgs[1] and "not on the circle" in msgs[0]
        return
    fast, slow, taken = _tables(text, monkeypatch)
    _assert_same_program(fast, slow)
    assert len(slow.arc_center) == len(slow) and np.isfinite(slow.arc_center[slow.motion >= 2]).all()
    assert taken > 0.6 * len(slow)


@pytest.mark.parametrize("bad, message, line", [("F-5", "negative feed", 43), ("X40 F0", "feed", 43),
                                                ("G93\nG1 X3", "feed", 44)])
def test_a_run_stops_where_the_reader_refuses(monkeypatch, bad, message, line):
    text = "G21 G90 G94\nG1 F100\n" + "".join(f"X{k}\n" for k in range(40)) + bad + "\n" + \
           "".join(f"Y{k}\n" for k in range(40))
    msgs = []
    for on in (True, False):
        monkeypatch.setattr(fast_interp, "ENABLED", on)
        with pytest.raises(GcodeError) as info:
            parse_program(text, "t.ngc", setup=Setup(offsets_zero=True), require_setup=True)
        msgs.append(str(info.value))
    assert msgs[0] == msgs[1]
    assert message in msgs[0] and f"t.ngc:{line}:" in msgs[0]


# ------------------------------------------------------------------------------------------- whole posts -----


def _posts(text, machine, mode, monkeypatch, **kw):
    monkeypatch.setattr(fast_interp, "ENABLED", True)
    fast = compensate(text, machine, mode, **kw)
    monkeypatch.setattr(fast_interp, "ENABLED", False)
    slow = compensate(text, machine, mode, **kw)
    return fast, slow


CONDITIONS = "(trueaxis: ap=0.6 ae=7 fz=0.2 n=1200 d=10 z=4 mode=down)\n"


@pytest.mark.parametrize("mode", ["geometric", "comprehensive"])
@pytest.mark.parametrize("units", ["inch", "mm"])
def test_the_nist_plate_posts_the_same_bytes_with_and_without_the_compiled_runs(xh714_wide, monkeypatch, mode,
                                                                                 units):
    text = (NIST / "mtc_plate_1.nc").read_text(encoding="latin-1")
    text = "".join(c if c.isascii() else "?" for c in text)  # the pre-scan (and so the runs) takes ASCII only
    lines = text.splitlines(keepends=True)
    text = "".join(lines[:1] + [CONDITIONS] + lines[1:])
    if units == "mm":  # the same numbers read as mm
        text = text.replace("G20", "G21")
    taken = _runs(monkeypatch)
    fast, slow = _posts(text, xh714_wide, mode, monkeypatch, offsets_zero=True)
    assert fast == slow
    assert taken[0] > 300


@pytest.mark.parametrize("mode", ["geometric", "comprehensive"])
def test_the_five_axis_cone_posts_the_same_bytes_with_and_without_the_compiled_runs(monkeypatch, mode):
    m = load_machine(MACHINES / "nmv1500dcg.toml")
    rng = np.random.default_rng(0)
    values = m.parameter_values()
    m = m.with_parameters(np.where(values == 0.0, rng.normal(0.0, 10.0, values.size), values))
    text = cone_flank_program(m, CONE, n_blocks=1500)
    taken = _runs(monkeypatch)
    fast, slow = _posts(text, m, mode, monkeypatch)
    assert fast == slow
    assert taken[0] > 1400


@pytest.mark.parametrize("bad, message", [("G1 X5 R2 F100", "R word"), ("G1 X5 I2 F100", "I word"),
                                          ("G0 X1 Y2 B5 C3 M3 M4", "two M codes")])
def test_the_block_checks_still_refuse_after_g93s_first_feed(bad, message):
    """G93 resets the feed (the checks then read block by block); after the first F word the plain blocks are
    checked by the whole-text pass again (the cost of a G93 program), which still finds what rs274 refuses."""
    moves = "".join(f"G1 X{k} Y{k % 3} Z1 F{1000 + k}\n" for k in range(60))
    text = "G21 G90 G17 G94\nG0 X0 Y0 Z5\nG93\n" + moves + bad + "\n" + moves + "M30\n"
    with pytest.raises(GcodeError) as info:
        parse_program(text, "t.ngc", setup=Setup(offsets_zero=True), require_setup=True)
    assert f"t.ngc:{4 + 60}:" in str(info.value) and message in str(info.value)


def test_a_run_whose_feed_changes_on_most_lines_reads_to_the_same_states(monkeypatch):
    """A run of plain moves whose feed changes line by line, feeds coming back (G93 programs write one per line): the
    states of the compiled run (each distinct feed looked up once) are the reader's line by line, in the same order."""
    feeds = [350.25, 350.5, 350.25, 351.0, 350.5, 352.0, 351.0, 350.25] * 40
    text = "G21 G90 G17 G94\nG0 X0 Y0 Z0\nF100\n" + "".join(
        f"G1 X{0.1 * k:.4f} Y{0.05 * k:.4f} F{f}\n" for k, f in enumerate(feeds)) + "G93\n" + "".join(
        f"G1 X{5 - 0.1 * k:.4f} F{f * 10}\n" for k, f in enumerate(feeds[:90])) + "M30\n"
    fast, slow, taken = _tables(text, monkeypatch)
    assert taken > 300
    _assert_same_program(fast, slow)
