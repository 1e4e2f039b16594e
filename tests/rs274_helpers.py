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


def private_env(workdir: Path) -> dict:
    """The environment for one rs274 run: HOME in its own folder. LinuxCNC 2.9's rs274 keeps the tool table in a
    memory-mapped file ``$HOME/.tool.mmap``, shared by every rs274 of the user: runs in parallel (pytest -n 2) read
    each other's tools ("Requested tool 23 not found") or die of SIGBUS when another one truncates it."""
    import os

    env = dict(os.environ)
    env["HOME"] = str(workdir)
    return env


def tool_table_text(lengths_mm: dict) -> str:
    """A LinuxCNC tool table for ``rs274`` (which reads it in inches) from tool -> length in mm."""
    rows = []
    for tool, length in sorted(lengths_mm.items()):
        rows.append(f"T{tool} P{tool} D0.1 Z{length / 25.4:+.8f} ;tool {tool}")
    return "\n".join(rows) + "\n"


def run_rs274(program: Path, tool_lengths_mm: dict, workdir: Path, flags: tuple = ()) -> CanonMoves:
    """Interpret ``program`` with rs274 and return its moves (``flags``: more options, e.g. ``("-b",)`` for the
    block-delete switch on)."""
    exe = require_rs274()
    workdir.mkdir(parents=True, exist_ok=True)
    tbl = workdir / "tools.tbl"
    tbl.write_text(tool_table_text(tool_lengths_mm))
    out = workdir / "canon.txt"
    proc = subprocess.run([exe, *flags, "-t", str(tbl), "-g", str(program), str(out)], stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=120, cwd=workdir, env=private_env(workdir))
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
    from trueaxis.nc.gcode import parse_program

    path = Path(workdir) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    moves = run_rs274(path, tool_lengths_mm or {}, Path(workdir))
    assert moves.returncode == 0, moves.stderr[-2000:]
    ours = parse_program(text)
    assert len(moves.kind) == len(ours)
    np.testing.assert_allclose(moves.end, ours.end, atol=5e-5)
    return moves


# ---------------------------------------------------------------------------------- with the control's setup ----
_SETUP_CALL = re.compile(r"^\s*\d+\s+N\S*\s+(USE_LENGTH_UNITS|SET_G5X_OFFSET|SET_G92_OFFSET|SET_XY_ROTATION|"
                         r"USE_TOOL_LENGTH_OFFSET|STRAIGHT_TRAVERSE|STRAIGHT_FEED|ARC_FEED|SELECT_PLANE)\((.*)\)\s*$")


@dataclass
class MachineMoves:
    """rs274's moves in machine coordinates, mm / deg: kind (N,) str, end (N, 6), line (N,) the block's sequence
    number as rs274 prints it (or -1), computed from its canonical calls as LinuxCNC's canon does: the position it
    prints (program coordinates) plus the G92 shift, turned by the XY rotation, plus the G5x offset and the tool
    offset (USE_TOOL_LENGTH_OFFSET), each in the length units in force when it was printed."""

    kind: list
    end: np.ndarray
    stderr: str
    returncode: int


def machine_moves(text: str) -> MachineMoves:
    """Machine-coordinate moves (mm) from rs274's canonical output text (see MachineMoves)."""
    scale = 1.0  # mm per unit of the numbers printed now
    g5x = np.zeros(6)
    g92 = np.zeros(6)
    tool = np.zeros(6)
    rot = 0.0
    plane = _PLANE["CANON_PLANE_XY"]
    lin = np.array([1, 1, 1, 0, 0, 0], bool)
    kinds, ends = [], []

    def mm(values):
        v = np.array(values, float)
        return np.where(lin, v * scale, v)

    for line in text.splitlines():
        m = _SETUP_CALL.match(line)
        if not m:
            continue
        name, args = m.group(1), m.group(2)
        if name == "USE_LENGTH_UNITS":
            scale = 25.4 if "INCHES" in args else 1.0
            continue
        if name == "SELECT_PLANE":
            plane = _PLANE.get(args.strip(), plane)
            continue
        if name == "SET_XY_ROTATION":
            rot = float(args)
            continue
        if name == "USE_TOOL_LENGTH_OFFSET":
            # "(x y z, a b c, u v w)"
            groups = [g.split() for g in args.split(",")]
            tool = mm([float(v) for v in groups[0]] + [float(v) for v in groups[1]])
            continue
        vals = [float(v) for v in args.replace(" ", "").split(",")]
        if name == "SET_G5X_OFFSET":
            g5x = mm(vals[1:7])
            continue
        if name == "SET_G92_OFFSET":
            g92 = mm(vals[:6])
            continue
        if name == "ARC_FEED":
            first, second, normal = plane
            p = [0.0] * 6
            p[first], p[second], p[normal] = vals[0], vals[1], vals[5]
            p[3:6] = vals[6:9]
            kinds.append("arc")
        else:
            p = vals[:6]
            kinds.append("traverse" if name == "STRAIGHT_TRAVERSE" else "feed")
        u = mm(p) + g92
        c, s = np.cos(np.radians(rot)), np.sin(np.radians(rot))
        u[0], u[1] = c * u[0] - s * u[1], s * u[0] + c * u[1]
        ends.append(u + g5x + tool)
    return MachineMoves(kinds, np.array(ends, float).reshape(-1, 6), "", 0)


def run_rs274_setup(program: Path, var: Path, tools: Path, workdir: Path) -> MachineMoves:
    """rs274 with a parameter file and a tool table (copies: rs274 rewrites its parameter file on exit), its moves in
    machine coordinates (mm). The standalone rs274's machine units are inches: the files must be written in inches."""
    import shutil

    exe = require_rs274()
    workdir.mkdir(parents=True, exist_ok=True)
    var_copy, tbl_copy = workdir / "rs274.var", workdir / "rs274.tbl"
    shutil.copyfile(var, var_copy)
    shutil.copyfile(tools, tbl_copy)
    out = workdir / "canon_setup.txt"
    proc = subprocess.run([exe, "-v", str(var_copy), "-t", str(tbl_copy), "-g", str(program), str(out)],
                          stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=120, cwd=workdir,
                          env=private_env(workdir))
    moves = machine_moves(out.read_text(errors="replace"))
    moves.stderr, moves.returncode = proc.stdout + proc.stderr, proc.returncode
    return moves


def var_text(work_offsets: dict | None = None, rotations: dict | None = None, g92=None, active: int = 1,
             g28=None, g30=None) -> str:
    """A complete LinuxCNC parameter file (every parameter trueaxis and LinuxCNC require): work offsets
    {system index 1..9: (X, Y, Z, A, B, C)}, rotations {index: deg}, a G92 shift in force (or None), the active
    system, G28 / G30 homes; values in the file's units, written with repr (exact)."""
    work_offsets, rotations = work_offsets or {}, rotations or {}
    rows = []
    for base, home in ((5161, g28), (5181, g30)):
        rows += [(base + i, v) for i, v in enumerate(list(home if home is not None else [0.0] * 6))]
    rows.append((5210, 1.0 if g92 is not None else 0.0))
    rows += [(5211 + i, v) for i, v in enumerate(list(g92 if g92 is not None else [0.0] * 6))]
    rows.append((5220, float(active)))
    for k in range(1, 10):
        base = 5221 + 20 * (k - 1)
        rows += [(base + i, v) for i, v in enumerate(list(work_offsets.get(k, [0.0] * 6)))]
        rows.append((base + 9, float(rotations.get(k, 0.0))))
    return "".join(f"{n}\t{float(v)!r}\n" for n, v in rows)
