"""Run LinuxCNC's standalone ``rs274`` interpreter and read its canonical moves, for conformance tests.

``rs274 -t tools.tbl -g in.ngc out.txt`` prints one canonical call per line, e.g.
``   31 N160   STRAIGHT_FEED(7.2500, -1.5000, 0.0000, 0.0000, 0.0000, 0.0000)``. Positions are program coordinates (the
active work system, before G5x / G92 / tool length offsets) in the program's units, rounded to 4 decimals.
``ARC_FEED(first_end, second_end, first_axis, second_axis, rotation, axis_end_point, a, b, c)`` names its axes by the
plane: XY -> (X, Y, Z), XZ -> (Z, X, Y), YZ -> (Y, Z, X).

The standalone ``rs274`` reads its tool table in **inches**.
"""

from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

RS274 = "rs274"
PRINT_DECIMALS = 4  # rs274 prints %.4f

_CALL = re.compile(r"^\s*\d+\s+N\S*\s+(STRAIGHT_TRAVERSE|STRAIGHT_FEED|ARC_FEED|SELECT_PLANE)\((.*)\)\s*$")
_PLANE = {"CANON_PLANE_XY": (0, 1, 2), "CANON_PLANE_XZ": (2, 0, 1), "CANON_PLANE_YZ": (1, 2, 0)}


def require_rs274() -> str:
    """Path of LinuxCNC's ``rs274`` (conftest.require_program: fails under CI=true when missing, skips elsewhere)."""
    from conftest import require_program

    return require_program(RS274, "linuxcnc-uspace", "the G-code conformance tests")


@dataclass
class CanonMoves:
    """rs274's moves: kinds (N,) str in {"traverse", "feed", "arc"}, end (N, 6) X Y Z A B C, center (N, 3) (NaN for
    straight moves), rotation (N,) int (signed turns; 0 for straight moves)."""

    kind: list
    end: np.ndarray
    center: np.ndarray
    rotation: np.ndarray
    stderr: str
    returncode: int


def tool_table_text(lengths_mm: dict) -> str:
    """A LinuxCNC tool table for ``rs274`` (which reads it in inches) from tool -> length in mm."""
    rows = []
    for tool, length in sorted(lengths_mm.items()):
        rows.append(f"T{tool} P{tool} D0.1 Z{length / 25.4:+.8f} ;tool {tool}")
    return "\n".join(rows) + "\n"


def run_rs274(program: Path, tool_lengths_mm: dict, workdir: Path) -> CanonMoves:
    """Interpret ``program`` with rs274 and return its moves. Raises AssertionError when rs274 stops on an error."""
    exe = require_rs274()
    workdir.mkdir(parents=True, exist_ok=True)
    tbl = workdir / "tools.tbl"
    tbl.write_text(tool_table_text(tool_lengths_mm))
    out = workdir / "canon.txt"
    proc = subprocess.run([exe, "-t", str(tbl), "-g", str(program), str(out)], stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=120, cwd=workdir)
    moves = parse_canon(out.read_text(errors="replace"))
    moves.stderr, moves.returncode = proc.stdout + proc.stderr, proc.returncode
    return moves


def parse_canon(text: str) -> CanonMoves:
    """Moves from rs274's canonical output text."""
    kind, end, center, rotation = [], [], [], []
    plane = _PLANE["CANON_PLANE_XY"]
    for line in text.splitlines():
        m = _CALL.match(line)
        if not m:
            continue
        name, args = m.group(1), m.group(2)
        if name == "SELECT_PLANE":
            plane = _PLANE.get(args.strip(), plane)
            continue
        vals = [float(v) for v in args.replace(" ", "").split(",")]
        if name in ("STRAIGHT_TRAVERSE", "STRAIGHT_FEED"):
            kind.append("traverse" if name == "STRAIGHT_TRAVERSE" else "feed")
            end.append(vals[:6])
            center.append([np.nan] * 3)
            rotation.append(0)
        else:
            first, second, normal = plane
            e = [0.0] * 6
            c = [np.nan] * 3
            e[first], e[second], e[normal] = vals[0], vals[1], vals[5]
            e[3:6] = vals[6:9]
            c[first], c[second] = vals[2], vals[3]
            kind.append("arc")
            end.append(e)
            center.append(c)
            rotation.append(int(vals[4]))
    return CanonMoves(kind, np.array(end, float).reshape(-1, 6), np.array(center, float).reshape(-1, 3),
                      np.array(rotation, int), "", 0)


def assert_rs274_reads_as_we_do(text: str, workdir: Path, tool_lengths_mm: dict | None = None,
                                name: str = "out.ngc") -> CanonMoves:
    """rs274 interprets the program ``text`` without error, with as many moves as our reader and the same end points
    (within rs274's 4 printed decimals). Returns rs274's moves."""
    from trueaxis.postproc.gcode import parse_program

    path = Path(workdir) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    moves = run_rs274(path, tool_lengths_mm or {}, Path(workdir))
    assert moves.returncode == 0, moves.stderr[-2000:]
    ours = parse_program(text)
    assert len(moves.kind) == len(ours)
    np.testing.assert_allclose(moves.end, ours.end, atol=5e-5)
    return moves
