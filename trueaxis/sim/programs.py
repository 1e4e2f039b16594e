"""Small machine-axis programs that exercise the virtual shop (its checks and benchmarks; not the part generators).

- ``square_boss_program``: 3-axis contour around a square boss (lines and G2 corner arcs), climb milling.
- ``cone_flank_program``: bare 5-axis flank passes around the NAS 979 cone on a B-C table (no lead-in, no retracts),
  machine-axis G-code through the machine's inverse kinematics, G93 inverse-time feed; optional semi-finishing pass.

The part programs proper (CL data, lead-in/out, safe retracts, compensation, the slot block) are in
``trueaxis.postproc.programs``; ``cone_flank_poses`` is re-exported from there.
"""

from __future__ import annotations

import math

import numpy as np

from ..postproc.programs import cone_flank_poses  # noqa: F401  (re-export)
from ..machine import inverse_kinematics


def square_boss_program(half: float = 20.0, radius: float = 5.0, z_tip: float = -12.0, z_origin: float = -300.0,
                        feed: float = 1000.0, offset: float = 0.0) -> str:
    """Tool-centre contour around the boss [-half, half]^2 (part frame), clockwise seen from +Z (down milling on an
    external boss), tool tip at part z = z_tip; machine Z = part z + z_origin (xh714 places the part at z -300)."""
    r = radius + offset
    h = half
    z = z_tip + z_origin
    lines = [
        "%", "(square boss contour)", "G21 G90 G94 G17",
        "(trueaxis: ap=10 ae=0.5 fz=0.05 n=5000 d=10 z=4 mode=down)",
        f"G0 X{-h:.6f} Y{h + r + 5:.6f} Z{z + 50:.6f}",
        f"G0 Z{z:.6f}",
        f"G1 Y{h + r:.6f} F{feed:.1f}",
        f"G1 X{h:.6f} Y{h + r:.6f}",
        f"G2 X{h + r:.6f} Y{h:.6f} I0 J{-r:.6f}",
        f"G1 X{h + r:.6f} Y{-h:.6f}",
        f"G2 X{h:.6f} Y{-h - r:.6f} I{-r:.6f} J0",
        f"G1 X{-h:.6f} Y{-h - r:.6f}",
        f"G2 X{-h - r:.6f} Y{-h:.6f} I0 J{r:.6f}",
        f"G1 X{-h - r:.6f} Y{h:.6f}",
        f"G2 X{-h:.6f} Y{h + r:.6f} I{r:.6f} J0",
        f"G1 X{-h + 2:.6f}",
        f"G1 Y{h + r + 5:.6f}",
        f"G0 Z{z + 50:.6f}",
        "M30", "%",
    ]
    return "\n".join(lines) + "\n"


def boss_probe(half: float = 20.0, z_range=(-9.0, -1.0), n_per_side: int = 500, margin: float = 1.0):
    """Points (N,3) and outward normals on the four boss walls (part frame)."""
    rng = np.random.default_rng(3)
    pts, nrm = [], []
    for normal in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        nx, ny = normal
        s = rng.uniform(-half + margin, half - margin, n_per_side)
        z = rng.uniform(*z_range, n_per_side)
        if nx == 0:
            p = np.column_stack([s, np.full(n_per_side, ny * half), z])
        else:
            p = np.column_stack([np.full(n_per_side, nx * half), s, z])
        pts.append(p)
        nrm.append(np.broadcast_to([nx, ny, 0.0], p.shape))
    return np.concatenate(pts), np.ascontiguousarray(np.concatenate(nrm), dtype=float)


def cone_flank_program(machine, cone: dict, n_blocks: int = 3600, speed_mm_min: float = 1000.0,
                       semi_stock: float | None = None, fz: float = 0.05) -> str:
    """Machine-axis G-code (X Y Z B C, G93) of the cone flank pass(es) for a B-C table machine."""
    names = machine.axis_names
    out = ["%", "(cone flank milling, machine axes)", "G21 G90 G17"]
    passes = ([semi_stock] if semi_stock else []) + [0.0]
    previous = None
    for k, stock in enumerate(passes):
        tip, axis = cone_flank_poses(cone, machine.tool.radius, n_blocks, stock)
        res = inverse_kinematics(machine, tip, axis, branch=-1)
        q = res.q.copy()
        ci = names.index("C")
        q[:, ci] = np.unwrap(q[:, ci])
        if previous is not None:
            q[:, ci] += 2 * np.pi * np.round((previous[ci] - q[0, ci]) / (2 * np.pi))
        seg = np.linalg.norm(np.diff(tip, axis=0), axis=1)
        inv_f = speed_mm_min / np.maximum(seg, 1e-9)  # 1 / minutes
        ae = 0.5 if k == 0 else (semi_stock or 0.5)
        out.append(f"(trueaxis: ap=20 ae={ae:g} fz={fz:g} n=5000 d={2 * machine.tool.radius:g} "
                   f"z={machine.tool.flutes} mode=down)")

        def words(row):
            ws = []
            for c, nme in enumerate(names):
                v = math.degrees(row[c]) * machine.word_signs()[c] if machine.axes[nme].is_rotary else row[c]
                ws.append(f"{nme}{v:.6f}")
            return " ".join(ws)

        out.append("G94 G0 " + words(q[0]))
        out.append("G93")
        for i in range(1, len(q)):
            out.append(f"G1 {words(q[i])} F{inv_f[i - 1]:.4f}")
        out.append("G94")
        previous = q[-1]
    out += ["M30", "%"]
    return "\n".join(out) + "\n"
