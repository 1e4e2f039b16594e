"""A stop (M0 M1 M2 M30 M60) acts after its block's motion: on a split move or a fitted arc it goes with the last
piece. On the first one (as written before), the machine stopped mid-cut or the program ended with the rest of the move
uncut, exit 0 (a QA pass). Checked through LinuxCNC's rs274: the stop comes after the move's whole end."""

from __future__ import annotations

import re
import subprocess

import numpy as np
import pytest

from conftest import MACHINES
from rs274_helpers import private_env, require_rs274
from trueaxis.machine import load_machine
from trueaxis.postproc.post import _stop_words_taken_out, compensate, without_header


def _canon(tmp_path, text, name):
    path = tmp_path / name
    path.write_text(text)
    res = subprocess.run([require_rs274(), "-g", str(path)], capture_output=True, text=True, stdin=subprocess.DEVNULL,
                         env=private_env(tmp_path), timeout=60, check=False)
    assert res.returncode == 0, res.stderr[-500:]
    return [line.split(None, 2)[2] for line in res.stdout.splitlines() if line.strip()[:1].isdigit()]


def _end_of(call):
    return np.array([float(v) for v in call[call.index("(") + 1 : call.index(")")].split(",")[:3]])


@pytest.mark.parametrize("stop", ["M0", "M01", "M60", "M2", "m30"])
def test_a_split_moves_stop_comes_after_its_last_piece(tmp_path, stop):
    nmv = load_machine(MACHINES / "nmv1500dcg.toml")
    prog = f"%\nG21 G90 G17 G94 F300\nG0 X-150 Y-100 Z5\nG1 Z-1\nN40 G1 X150 Y100 {stop} (stop: {stop})\nG0 Z20\nM5\n%\n"
    out = compensate(prog, nmv, "geometric", offsets_zero=True)
    body = without_header(out).splitlines()
    at = [i for i, line in enumerate(body) if re.search(rf"(?i)\b{stop}\b(?![^(]*\))", line.split("(")[0])]
    assert len(at) == 1 and len(body) > 7, body  # split into pieces; the stop written once
    line = body[at[0]]
    assert not line.startswith("N40") and body[at[0] + 1].startswith("G0"), body  # the last piece, not the first
    assert "(stop:" in body[[i for i, b in enumerate(body) if b.startswith("N40")][0]]  # the comment stays first
    canon = _canon(tmp_path, out, "out.ngc")
    kind = "PROGRAM_END" if stop.upper() in ("M2", "M30") else ("PALLET_SHUTTLE" if stop == "M60" else
                                                                  ("OPTIONAL_PROGRAM_STOP" if stop == "M01"
                                                                   else "PROGRAM_STOP"))
    first = next(i for i, c in enumerate(canon) if c.startswith(kind))
    feeds = [c for c in canon[:first] if c.startswith("STRAIGHT_FEED")]
    # every piece is cut before the stop (the plunge, then the pieces from N40 to the stop's line), the last one at
    # the move's end (within its correction, a few um)
    assert len(feeds) == 1 + at[0] - next(i for i, b in enumerate(body) if b.startswith("N40")) + 1, canon
    assert np.abs(_end_of(feeds[-1]) - [150.0, 100.0, -1.0]).max() < 0.02, feeds[-1]


def test_a_fitted_arcs_stop_comes_after_its_last_sub_arc(tmp_path):
    xh = load_machine(MACHINES / "xh714.toml")
    prog = "N10 G21 G90 G17 G94 F300\nN20 G0 X70 Y-50 Z-50\nN30 G1 Z-60\nN40 G2 X170 Y50 R100 M0\nN50 G0 Z-40\nN60 M2\n"
    out = without_header(compensate(prog, xh, "geometric", offsets_zero=True))
    arcs = [line for line in out.splitlines() if re.match(r"(N40 )?G2", line)]
    assert len(arcs) >= 2 and "M0" not in arcs[0] and arcs[-1].endswith(" M0"), arcs
    canon = _canon(tmp_path, out, "arc.ngc")
    stop = canon.index("PROGRAM_STOP()")
    assert sum(c.startswith("ARC_FEED") for c in canon[:stop]) == len(arcs)


@pytest.mark.parametrize("body, kept, stops", [
    ("G1 X150 Y100 M0", "G1 X150 Y100", ["M0"]),
    ("N10 G1 X1 M30 (end M2)", "N10 G1 X1 (end M2)", ["M30"]),
    ("M02 G1 X1", "G1 X1", ["M02"]),
    ("G1 X1 M3 S100 M1", "G1 X1 M3 S100", ["M1"]),
    ("G1 X1 m 60", "G1 X1", ["m60"]),
    ("G1 X1 M10 M300 M6", "G1 X1 M10 M300 M6", []),  # not stops (M6 and user codes act before the motion)
    ("G1X1M0F100", "G1X1 F100", ["M0"]),
])
def test_the_stop_words_of_a_block(body, kept, stops):
    assert _stop_words_taken_out(body) == (kept, stops)
