"""The post-processor: compensate an NC program with the error twin (DESIGN §5).

``compensate(program, machine, mode=...)`` reads machine-axis G-code, finds for every move the commanded axes whose
*actual* pose (the twin) is the *nominal* pose of the programmed axes, splits moves where the actual path would leave
the nominal one by more than the tolerance, and writes the program back in its own dialect: comments, line numbers
and non-motion blocks kept, every compensated motion block with its motion word and all its axis words, numbers at the
program's precision (at least 5 decimals in mm and 6 in inch for linear axes, 5 for rotary axes: enough that the
written numbers do not eat the 0.1 um / 1 urad budget).

What it refuses (``PostError``, ``file:line: reason``; nothing is written): a correction above the bound, a corrected
position outside an axis' travel, a program for axes the machine does not have, incremental canned cycles, and
whatever the reader refuses. G28/G30 and G53 moves are passed through unchanged (their targets are machine positions).

Cutting conditions for comprehensive mode, in order of precedence (the first that gives a field wins):
1. the caller's ``conditions`` (command line ``--ap --ae --fz --n --d --z --cut-mode``),
2. the program's structured comments ``(trueaxis: ap=.. ae=.. fz=.. n=.. d=.. z=.. mode=down)``, valid from where they
   stand (FreeCAD's post writes them from the job's tool controller and operation),
3. the machine file's tool (diameter = 2 x radius, flutes).
The force is the mechanistic model's mean force over a tooth period, in the feed frame turned to the machine frame:
x along the feed direction (XY plane), z along the tool axis, y = z x x. Rapids and plunges carry no force.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..machine import ErrorTwin, Machine
from ..machine.cutting_force import CuttingCoefficients, CuttingConditions, mean_force
from .gcode import (
    ARC_CCW,
    ARC_CW,
    FEED,
    MM_PER_INCH,
    RAPID,
    ROW_CYCLE,
    ROW_PROGRAMMED,
    GcodeError,
    Program,
    parse_program,
    tokenize_line,
    write_number,
)
from .solver import solve_commanded

MODES = ("none", "geometric", "comprehensive")
AXES = "XYZABC"
_CONDITIONS = re.compile(r"\(\s*trueaxis:([^)]*)\)", re.IGNORECASE)
_DISTANCE = re.compile(r"G\s*0*9([01])(?![0-9.])", re.IGNORECASE)
_ARC_DISTANCE = re.compile(r"G\s*0*9([01])\.1", re.IGNORECASE)
_MOTION_WORD = re.compile(r"^G0*([0-3])$", re.IGNORECASE)


class PostError(GcodeError):
    """The post refuses the program: ``file:line: reason``."""


@dataclass
class PostReport:
    """What the post did, for ``--report r.json``."""

    source: str
    machine: str
    mode: str
    tol_um: float
    blocks_in: int = 0
    blocks_out: int = 0
    moves: int = 0
    moves_split: int = 0
    arcs_kept: int = 0
    arcs_linearised: int = 0
    singular_blocks: list = field(default_factory=list)
    correction: dict = field(default_factory=dict)
    units_note: str = ""
    passthrough: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    max_residual_um: float = 0.0
    max_residual_urad: float = 0.0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


# --------------------------------------------------------------------------------------------------- the API -----


def compensate(
    program,
    machine: Machine,
    mode: str = "geometric",
    *,
    tol_um: float = 1.0,
    max_correction_mm: float = 0.5,
    singular_deg: float = 1.0,
    conditions: dict | None = None,
    passthrough_unsupported: bool = False,
    source: str | None = None,
    report: dict | None = None,
) -> str:
    """Compensated program text. ``program``: G-code text or a path. ``report``: a dict to fill with the report."""
    text, source = _read_input(program, source)
    out, rep = post_text(text, machine, mode, tol_um=tol_um, max_correction_mm=max_correction_mm,
                         singular_deg=singular_deg, conditions=conditions,
                         passthrough_unsupported=passthrough_unsupported, source=source)
    if report is not None:
        report.update(rep.as_dict())
    return out


def _read_input(program, source):
    if isinstance(program, Path) or (isinstance(program, str) and "\n" not in program and Path(program).is_file()):
        path = Path(program)
        data = path.read_bytes()
        if b"\x00" in data:
            raise PostError(str(path), 1, "binary file (NUL bytes): not G-code")
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            text = data.decode("latin-1")
        return text, source or str(path)
    if not isinstance(program, str):
        raise TypeError(f"program must be G-code text or a path, got {type(program).__name__}")
    return program, source or "<string>"


def post_text(text: str, machine: Machine, mode: str = "geometric", *, tol_um: float = 1.0,
              max_correction_mm: float = 0.5, singular_deg: float = 1.0, conditions: dict | None = None,
              passthrough_unsupported: bool = False, source: str = "<string>") -> tuple[str, PostReport]:
    """Compensate program text; returns (text, report)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}; got {mode!r}")
    if not (tol_um > 0):
        raise ValueError(f"tolerance must be positive, got {tol_um} um")
    prog = parse_program(text, source, passthrough_unsupported=passthrough_unsupported)
    rep = PostReport(source=source, machine=machine.name, mode=mode, tol_um=tol_um)
    rep.blocks_in = len(prog.lines)
    rep.passthrough = [{"line": ln, "reason": r} for ln, r in prog.unsupported]
    rep.warnings = list(prog.warnings)
    _check_axes(prog, machine, source)
    if prog.units != "mm":
        rep.units_note = (f"program in {prog.units} (G20); converted to mm for the {machine.name} model and back to "
                          "program units for output")
    if mode == "none" or len(prog) == 0:
        rep.blocks_out = rep.blocks_in
        return text, rep
    return _Poster(prog, machine, mode, tol_um, max_correction_mm, singular_deg, conditions, rep).run()


def _check_axes(prog: Program, machine: Machine, source: str):
    for letter in prog.axes_present:
        if letter not in machine.axes:
            col = AXES.index(letter)
            rows = np.nonzero(prog.end[:, col] != 0.0)[0]
            line = int(prog.line_no[rows[0]]) if rows.size else 1
            raise PostError(source, line, f"the program moves axis {letter}, which {machine.name} does not have "
                                          f"(its axes: {' '.join(machine.axis_names)})")


# --------------------------------------------------------------------------------------------------- internals ---


class _Poster:
    def __init__(self, prog, machine, mode, tol_um, max_corr, singular_deg, conditions, rep):
        self.p = prog
        self.m = machine
        self.mode = mode
        self.tol_mm = tol_um * 1e-3
        self.tol_rad = max(tol_um, 1.0) * 1e-6  # orientation tolerance: 1 urad per um of position tolerance
        self.max_corr = max_corr
        self.singular = np.radians(singular_deg)
        self.conditions = conditions or {}
        self.rep = rep
        self.twin = ErrorTwin(machine)
        self.names = machine.axis_names
        self.cols = [AXES.index(a) for a in self.names]
        self.orientation = any(a in prog.axes_present for a in machine.rotary_axes)
        self.inch_rows = prog.inch

    # --- coordinates ------------------------------------------------------------------------------------------------
    def to_machine(self, prog6, inch):
        """(K,6) program-unit machine coordinates -> (K, n_axes) mm / rad."""
        q = prog6[:, self.cols].copy()
        for j, a in enumerate(self.names):
            if self.m.axes[a].is_rotary:
                q[:, j] = np.radians(q[:, j])
            else:
                q[:, j] = np.where(inch, q[:, j] * MM_PER_INCH, q[:, j])
        return q

    def to_program_delta(self, dq, inch):
        """(K, n_axes) correction mm / rad -> (K, 6) program units (inch or mm, degrees)."""
        out = np.zeros((dq.shape[0], 6))
        for j, a in enumerate(self.names):
            if self.m.axes[a].is_rotary:
                out[:, self.cols[j]] = np.degrees(dq[:, j])
            else:
                out[:, self.cols[j]] = np.where(inch, dq[:, j] / MM_PER_INCH, dq[:, j])
        return out

    # --- forces --------------------------------------------------------------------------------------------------
    def forces(self, rows, direction):
        """(K,3) N force on the tool for the given rows with feed directions (K,3) in the machine frame."""
        if self.mode != "comprehensive":
            return None
        if not self.m.cutting:
            raise PostError(self.p.source, 1, f"comprehensive mode needs the [cutting] coefficients in {self.m.source}")
        coeffs = CuttingCoefficients.from_mapping(self.m.cutting)
        conds = self._conditions_per_line()
        K = len(rows)
        F = np.zeros((K, 3))
        horiz = direction.copy()
        horiz[:, 2] = 0.0
        norm = np.linalg.norm(horiz, axis=1)
        cutting = (self.p.motion[rows] != RAPID) & (norm > 1e-9)
        groups: dict = {}
        for k in np.nonzero(cutting)[0]:
            c = conds(int(self.p.line_index[rows[k]]))
            if c is None:
                raise PostError(self.p.source, int(self.p.line_no[rows[k]]),
                                "comprehensive mode needs cutting conditions here: put (trueaxis: ap=.. ae=.. fz=.. "
                                "n=.. d=.. z=.. mode=down) before the cut, or give them on the command line")
            groups.setdefault(c, []).append(k)
        for key, ks in groups.items():
            cond = CuttingConditions.from_mapping(dict(key))
            f_feed = mean_force(coeffs, cond)
            ks = np.asarray(ks)
            x = horiz[ks] / norm[ks, None]
            z = np.array([0.0, 0.0, 1.0])
            y = np.cross(z, x)
            F[ks] = f_feed[0] * x + f_feed[1] * y + f_feed[2] * z
        return F

    def _conditions_per_line(self):
        """line index -> hashable conditions (tuple of items) valid there, or None."""
        marks = []
        for i, line in enumerate(self.p.lines):
            if "trueaxis" not in line.lower():
                continue
            for m in _CONDITIONS.finditer(line):
                fields = {}
                for item in m.group(1).split():
                    if "=" not in item:
                        raise PostError(self.p.source, i + 1, f"structured comment: expected key=value, got {item!r}")
                    k, v = item.split("=", 1)
                    fields[k.strip().lower()] = v.strip()
                marks.append((i, fields))
        tool = {"d": str(2 * self.m.tool.radius), "z": str(self.m.tool.flutes)}
        cli = {k: str(v) for k, v in self.conditions.items() if v is not None}
        starts = [i for i, _ in marks]

        def at(line_index):
            merged = dict(tool)
            k = np.searchsorted(starts, line_index, side="right")
            for _, f in marks[:k]:
                merged.update(f)
            merged.update(cli)
            if not all(key in merged for key in ("ap", "ae", "fz")):
                return None
            try:
                CuttingConditions.from_mapping(merged)
            except ValueError as exc:
                raise PostError(self.p.source, line_index + 1, f"cutting conditions: {exc}") from None
            return tuple(sorted(merged.items()))

        return at

    # --- solving -------------------------------------------------------------------------------------------------
    def solve(self, q, force, rows):
        hold = np.zeros_like(q, bool)
        if self.orientation and self.m.is_five_axis:
            from ..machine.kinematics import _rotary_pair

            outer, inner = _rotary_pair(self.m)
            sing = np.abs(np.sin(q[:, inner.column])) < np.sin(self.singular)
            hold[:, outer.column] = sing
        res = solve_commanded(self.twin, q, force, orientation=self.orientation, hold=hold,
                              tol_um=min(0.01, self.tol_mm * 1e3 / 10), tol_urad=0.1)
        bad = ~res.converged
        if np.any(bad):
            k = int(np.argmax(bad))
            raise PostError(self.p.source, int(self.p.line_no[rows[k]]),
                            f"compensation did not converge (residual {res.position_residual_um[k]:.3g} um,"
                            f" {res.axis_residual_urad[k]:.3g} urad)")
        return res.q, hold.any(axis=1)

    def check(self, q_nom, q_cmd, rows):
        """Correction bound and travel, per point; raises PostError naming the block."""
        dq = q_cmd - q_nom
        for j, a in enumerate(self.names):
            ax = self.m.axes[a]
            if ax.is_rotary:
                # The bound is in mm: an angular correction counts at a 100 mm lever arm.
                size = np.abs(dq[:, j]) * 100.0
            else:
                size = np.abs(dq[:, j])
            over = size > self.max_corr
            if np.any(over):
                k = int(np.argmax(over))
                unit = "deg" if ax.is_rotary else "mm"
                val = np.degrees(dq[k, j]) if ax.is_rotary else dq[k, j]
                raise PostError(self.p.source, int(self.p.line_no[rows[k]]),
                                f"correction of {a} is {val:+.4f} {unit}, above the bound of {self.max_corr} mm: "
                                f"check the machine file {self.m.source}")
            if ax.travel is not None:
                lo, hi = ax.travel
                out = (q_cmd[:, j] < lo - 1e-9) | (q_cmd[:, j] > hi + 1e-9)
                if np.any(out):
                    k = int(np.argmax(out))
                    v = np.degrees(q_cmd[k, j]) if ax.is_rotary else q_cmd[k, j]
                    t = np.degrees(ax.travel) if ax.is_rotary else ax.travel
                    raise PostError(self.p.source, int(self.p.line_no[rows[k]]),
                                    f"corrected {a} = {v:.4f} lies outside its travel [{t[0]:g}, {t[1]:g}]")

    # --- the run -------------------------------------------------------------------------------------------------
    def run(self):
        p = self.p
        rows = np.nonzero((p.kind == ROW_PROGRAMMED) | (p.kind == ROW_CYCLE))[0]
        self.rep.moves = int(rows.size)
        inch = p.inch[rows]
        q_end = self.to_machine(p.end_machine[rows], inch)
        q_start = self.to_machine((p.start + p.offset)[rows], inch)
        direction = np.zeros((rows.size, 3))
        lin = [j for j, a in enumerate(self.names) if not self.m.axes[a].is_rotary]
        direction[:, : len(lin)] = (q_end - q_start)[:, lin] if len(lin) == 3 else 0.0
        arcs = (p.motion[rows] == ARC_CW) | (p.motion[rows] == ARC_CCW)
        if np.any(arcs) and len(lin) == 3:
            direction[arcs] = self._arc_end_tangent(rows[arcs], q_end[arcs])
        force = self.forces(rows, direction)
        q_cmd, singular = self.solve(q_end, force, rows)
        self.check(q_end, q_cmd, rows)
        self.rep.singular_blocks = sorted({int(x) for x in p.line_no[rows[singular]]})
        delta_prog = self.to_program_delta(q_cmd - q_end, inch)
        self._summarise(q_cmd - q_end)

        # Pieces: per compensated row, a list of (program-coordinate end points (k,6)) incl. the final end.
        pieces = {}
        arc_mode = {}
        feed_rows = np.nonzero(p.motion[rows] == FEED)[0]
        pieces.update(self._split_lines(rows, feed_rows, q_start, q_end, force, inch))
        if np.any(arcs):
            arc_pieces, modes = self._arcs(rows, np.nonzero(arcs)[0], q_start, q_end, force, inch, delta_prog)
            pieces.update(arc_pieces)
            arc_mode.update(modes)
        self._residual_check(rows, q_cmd, q_end, force)
        return self._write(rows, delta_prog, pieces, arc_mode)

    def _summarise(self, dq):
        out = {}
        for j, a in enumerate(self.names):
            scale, unit = (1e6, "urad") if self.m.axes[a].is_rotary else (1e3, "um")
            v = dq[:, j] * scale
            out[a] = {f"max_abs_{unit}": float(np.abs(v).max()), f"rms_{unit}": float(np.sqrt(np.mean(v**2)))}
        self.rep.correction = out

    def _residual_check(self, rows, q_cmd, q_end, force):
        p_nom, u_nom = self.twin.nominal_pose(q_end)
        p_act, u_act = self.twin.actual_pose(q_cmd, force)
        self.rep.max_residual_um = float(np.linalg.norm(p_act - p_nom, axis=1).max() * 1e3)
        self.rep.max_residual_urad = float(np.linalg.norm(u_act - u_nom, axis=1).max() * 1e6) if self.orientation else 0.0

    def _arc_end_tangent(self, arc_rows, q_end_mm):
        p = self.p
        tang = np.zeros((arc_rows.size, 3))
        center = p.arc_center[arc_rows] + p.offset[arc_rows, :3]
        center = np.where(p.inch[arc_rows, None], center * MM_PER_INCH, center)
        plane = p.arc_plane[arc_rows]
        normal = np.select([plane[:, None] == 17, plane[:, None] == 18, plane[:, None] == 19],
                           [np.array([0, 0, 1.0]), np.array([0, 1.0, 0]), np.array([1.0, 0, 0])])
        sense = np.where(p.motion[arc_rows] == ARC_CCW, 1.0, -1.0)
        radial = q_end_mm[:, :3] - center
        tang = np.cross(normal, radial) * sense[:, None]
        return tang

    def _split_lines(self, rows, feed_idx, q_start, q_end, force, inch):
        """Straight feed moves: split until the actual path stays within tolerance of the nominal straight move."""
        out = {}
        if feed_idx.size == 0:
            return out
        p = self.p
        # Fractions of each move at the current piece boundaries; start with the whole move.
        todo = {int(i): np.array([0.0, 1.0]) for i in feed_idx}
        for _ in range(8):
            idx = np.array(sorted(todo))
            if idx.size == 0:
                break
            bounds = [todo[i] for i in idx]
            counts = np.array([b.size - 1 for b in bounds])
            a = np.concatenate([b[:-1] for b in bounds])
            b = np.concatenate([b[1:] for b in bounds])
            owner = np.repeat(idx, counts)
            qs, qe = q_start[owner], q_end[owner]
            f = None if force is None else force[owner]
            # Commanded piece ends (solve at both ends; the same points as neighbours: cached by value below).
            ca, _ = self.solve(qs + a[:, None] * (qe - qs), f, rows[owner])
            cb, _ = self.solve(qs + b[:, None] * (qe - qs), f, rows[owner])
            worst = np.zeros(owner.size)
            for s in (0.25, 0.5, 0.75):
                frac = a + s * (b - a)
                q_nom = qs + frac[:, None] * (qe - qs)
                pn, un = self.twin.nominal_pose(q_nom)
                pa, ua = self.twin.actual_pose(ca + s * (cb - ca), f)
                dev = np.linalg.norm(pa - pn, axis=1) / self.tol_mm
                if self.orientation:
                    dev = np.maximum(dev, np.linalg.norm(ua - un, axis=1) / self.tol_rad)
                worst = np.maximum(worst, dev)
            new_todo = {}
            for i in idx:
                sel = owner == i
                if np.all(worst[sel] <= 1.0):
                    continue
                bnd = todo[i]
                refined = [bnd[0]]
                for k, (lo, hi) in enumerate(zip(bnd[:-1], bnd[1:])):
                    w = worst[sel][k]
                    nsub = 1 if w <= 1.0 else int(np.ceil(np.sqrt(w))) + 1
                    refined.extend(lo + (hi - lo) * np.arange(1, nsub + 1) / nsub)
                new_todo[i] = np.array(refined)
            for i in idx:
                if i not in new_todo:
                    out[i] = todo[i]
            todo = new_todo
        for i, bnd in todo.items():
            out[i] = bnd
        # Convert fraction lists into program-coordinate end points of each piece.
        pieces = {}
        split_rows = [i for i, bnd in out.items() if bnd.size > 2]
        self.rep.moves_split = len(split_rows)
        if split_rows:
            fr = np.concatenate([out[i][1:-1] for i in split_rows])
            owner = np.concatenate([np.full(out[i].size - 2, i) for i in split_rows])
            qs, qe = q_start[owner], q_end[owner]
            q_nom = qs + fr[:, None] * (qe - qs)
            f = None if force is None else force[owner]
            q_c, _ = self.solve(q_nom, f, rows[owner])
            self.check(q_nom, q_c, rows[owner])
            start6 = p.start[rows[owner]]
            end6 = p.end[rows[owner]]
            nom6 = start6 + fr[:, None] * (end6 - start6)
            cmd6 = nom6 + self.to_program_delta(q_c - q_nom, inch[owner])
            for i in split_rows:
                pieces[i] = cmd6[owner == i]
        return pieces

    def _arcs(self, rows, arc_idx, q_start, q_end, force, inch, delta_prog):
        """Arcs whose correction is constant within tolerance stay arcs; others become straight pieces.

        All arcs are sampled and solved together (one Newton solve per stage, not per arc)."""
        p = self.p
        out, modes = {}, {}
        arc_idx = np.asarray(arc_idx, int)
        # Stage 1: 17 samples per arc; the spread of the correction along it decides arc or lines.
        n_s = 16
        pts6 = np.concatenate([_arc_points(p, rows[i], n_s) for i in arc_idx])
        owner = np.repeat(np.arange(arc_idx.size), n_s + 1)
        q_c, q_pts = self._solve_arc_points(rows, arc_idx, owner, pts6, force)
        d = (q_c - q_pts)[:, :3].reshape(arc_idx.size, n_s + 1, 3)
        spread = np.abs(d - d[:, -1:, :]).max(axis=(1, 2))
        kept = spread <= self.tol_mm / 2
        for i in arc_idx[kept]:
            modes[int(i)] = "arc"
        self.rep.arcs_kept += int(kept.sum())
        lin = arc_idx[~kept]
        if lin.size == 0:
            return out, modes
        # Stage 2: straight pieces, enough that the chord sagitta stays within half the tolerance; the correction's
        # variation is then followed point by point.
        counts = []
        for i in lin:
            r = rows[i]
            radius = np.linalg.norm(p.start[r, :3] - p.arc_center[r]) * (MM_PER_INCH if p.inch[r] else 1.0)
            step = 2 * np.arccos(max(0.0, 1 - (self.tol_mm / 2) / max(radius, 1e-9)))
            counts.append(max(2, int(np.ceil(_arc_sweep(p, r) / step))))
        pts6 = np.concatenate([_arc_points(p, rows[i], n) for i, n in zip(lin, counts)])
        owner = np.repeat(np.arange(lin.size), np.asarray(counts) + 1)
        q_c, q_pts = self._solve_arc_points(rows, lin, owner, pts6, force)
        self.check(q_pts, q_c, rows[lin][owner])
        cmd6 = pts6 + self.to_program_delta(q_c - q_pts, p.inch[rows[lin]][owner])
        first = np.r_[0, np.cumsum(np.asarray(counts) + 1)[:-1]]
        for k, i in enumerate(lin):
            out[int(i)] = cmd6[first[k] + 1 : first[k] + counts[k] + 1]
            modes[int(i)] = "lines"
        self.rep.arcs_linearised += int(lin.size)
        return out, modes

    def _solve_arc_points(self, rows, arc_idx, owner, pts6, force):
        """Commanded and nominal machine poses (K, n_axes) for points ``pts6`` (K, 6) on the arcs ``arc_idx[owner]``."""
        p = self.p
        r = rows[arc_idx][owner]
        q_pts = self.to_machine(pts6 + p.offset[r], p.inch[r])
        f = None if force is None else force[arc_idx][owner]
        q_c, _ = self.solve(q_pts, f, r)
        return q_c, q_pts

    # --- writing -------------------------------------------------------------------------------------------------
    def _write(self, rows, delta_prog, pieces, arc_mode):
        p = self.p
        info = p.format_info
        sep = info.separator
        axes_out = [a for a in AXES if a in self.names and (a in p.axes_present or a in "XYZ")]
        if self.m.kind == "lathe":
            axes_out = [a for a in axes_out if a in p.axes_present or a in "XZ"]
        rows_by_line: dict = {}
        for k, r in enumerate(rows):
            rows_by_line.setdefault(int(p.line_index[r]), []).append(k)
        incremental = _modal_per_line(p.lines, _DISTANCE, default="0")  # "1" = G91
        arc_incremental = _modal_per_line(p.lines, _ARC_DISTANCE, default="1")  # "1" = G91.1 (default)
        out_lines = []
        last_written = np.zeros(6)  # program coordinates of the last end point written (or passed through)
        all_rows_by_line: dict = {}
        for r in range(len(p)):
            all_rows_by_line.setdefault(int(p.line_index[r]), []).append(r)

        def fmt(letter, value, inch):
            dec = 5 if letter in "ABC" else (6 if inch else 5)
            dec = max(dec, info.decimals.get(letter, 0))
            return letter + write_number(float(value), dec, leading_zero=info.leading_zero,
                                         trailing_point=info.trailing_point)

        for li, line in enumerate(p.lines):
            ks = rows_by_line.get(li)
            if not ks:
                out_lines.append(line)
                for r in all_rows_by_line.get(li, []):
                    last_written = p.end[r].copy()
                continue
            body, ending = _split_ending(line)
            r0 = rows[ks[0]]
            inch = bool(p.inch[r0])
            if p.kind[r0] == ROW_CYCLE:
                if incremental[li] == "1":
                    raise PostError(p.source, li + 1, "incremental (G91) canned cycles are not compensated: write "
                                                      "the cycle in G90, or post with --mode none")
                out_lines.append(self._cycle_line(body, ks, rows, delta_prog, inch, fmt, sep) + ending)
                last_written = p.end[rows[ks[-1]]].copy()
                continue
            k = ks[-1]
            r = rows[k]
            target = p.end[r] + delta_prog[k]
            motion = int(p.motion[r])
            arc_kept = arc_mode.get(k) == "arc"
            rest = []
            if k in pieces and not arc_kept:
                # The block itself goes to the first piece's end, so that its other words (F, S, M, N) act where
                # they did; the remaining pieces follow as plain moves.
                pts = list(pieces[k]) if arc_mode.get(k) == "lines" else list(pieces[k]) + [target]
                if arc_mode.get(k) == "lines":
                    motion = FEED
                n = len(pts)
                if p.inverse_time[r]:
                    # G93: each piece takes its share of the block's time, so its inverse time is n times F.
                    body = _replace_feed(body, p.feed[r] * n, fmt, sep)
                target, rest = pts[0], pts[1:]
            new_body = self._rewrite_motion(body, motion, target, last_written, axes_out, inch, fmt, sep,
                                            incremental[li], arc=arc_kept, row=r,
                                            arc_incremental=arc_incremental[li], delta_end=delta_prog[k])
            out_lines.append(new_body + ending)
            last_written = target.copy()
            word = "G0" if motion == RAPID else "G1"
            for pt in rest:
                words = [word] + [fmt(a, _out_value(pt, last_written, a, incremental[li]), inch) for a in axes_out]
                if p.inverse_time[r]:
                    words.append(fmt("F", p.feed[r] * n, False))
                out_lines.append(sep.join(words) + ending)
                last_written = pt.copy()
        self.rep.blocks_out = len(out_lines)
        return "".join(out_lines), self.rep

    def _rewrite_motion(self, body, motion, target, last_written, axes_out, inch, fmt, sep, inc, arc, row,
                        arc_incremental, delta_end):
        p = self.p
        code, comment = _split_comment(body)
        toks = tokenize_line(code)
        keep = []
        motion_done = False
        for kind, text, _, _ in toks:
            if kind != "word":
                keep.append(text)
                continue
            letter = text[0].upper()
            if letter in AXES:
                continue
            if letter in "IJKR" and not arc:
                continue
            if letter in "IJK" and arc and arc_incremental == "1":
                continue
            if letter == "P" and not arc and motion in (FEED, RAPID) and p.motion[row] in (ARC_CW, ARC_CCW):
                continue
            if letter == "G" and _MOTION_WORD.match(text.replace(" ", "")):
                keep.append(f"G{motion}" if text[1:].strip() not in ("00", "01", "02", "03") else f"G0{motion}")
                motion_done = True
                continue
            keep.append(text)
        words = [fmt(a, _out_value(target, last_written, a, inc), inch) for a in axes_out]
        if arc:
            if arc_incremental == "1":
                plane = int(p.arc_plane[row])
                letters = {17: "IJ", 18: "IK", 19: "JK"}[plane]
                center = p.arc_center[row] + delta_end[:3]
                for letter in letters:
                    j = "IJK".index(letter)
                    words.append(fmt(letter, center[j] - last_written[j], inch))
        if not motion_done:
            keep.insert(_after_line_number(keep), f"G{motion}")
        pos = _word_position(keep)
        parts = keep[:pos] + words + keep[pos:]
        text = sep.join(t for t in parts if t.strip())
        return text + (comment if not comment.startswith(" ") or not sep else comment)

    def _cycle_line(self, body, ks, rows, delta_prog, inch, fmt, sep):
        """A canned-cycle block: hole position and depth from the correction at the bottom, R from the R level."""
        p = self.p
        rr = rows[ks]
        ends = p.end[rr]
        bottom = int(np.argmin(ends[:, 2]))
        d_bottom = delta_prog[ks[bottom]]
        hole = ends[bottom] + d_bottom
        # The R level: every cycle's first feed starts there. Its correction is solved at the row ending there.
        feeds = np.nonzero(p.motion[rr] == FEED)[0]
        first = int(feeds[0]) if feeds.size else 0
        r_nominal = p.start[rr[first], 2]
        at_r = np.nonzero(np.isclose(ends[:, 2], r_nominal) & (np.arange(len(rr)) < first))[0]
        d_r = delta_prog[ks[int(at_r[-1])]] if at_r.size else d_bottom
        r_level = r_nominal + d_r[2]
        code, comment = _split_comment(body)
        toks = tokenize_line(code)
        keep = [t[1] for t in toks if not (t[0] == "word" and t[1][0].upper() in "XYZR")]
        words = [fmt("X", hole[0], inch), fmt("Y", hole[1], inch), fmt("Z", hole[2], inch), fmt("R", r_level, inch)]
        pos = _word_position(keep)
        return sep.join(t for t in keep[:pos] + words + keep[pos:] if t.strip()) + comment


# --------------------------------------------------------------------------------------------------- helpers -----


def _out_value(target6, last6, letter, inc):
    j = AXES.index(letter)
    return target6[j] - last6[j] if inc == "1" else target6[j]


def _split_ending(line: str):
    stripped = line.rstrip("\r\n")
    return stripped, line[len(stripped):]


def _split_comment(body: str):
    """Code and trailing comment text (kept verbatim, with the space before it)."""
    toks = tokenize_line(body)
    for kind, text, start, _ in toks:
        if kind == "comment":
            j = start
            while j > 0 and body[j - 1] in " \t":
                j -= 1
            # Only a comment at the end of the line is split off; inline comments stay in the code.
            if all(t[0] == "comment" for t in toks if t[2] >= start):
                return body[:j], body[j:]
    return body, ""


def _word_position(tokens):
    """Where axis words go: right after the last G word, or after the line number."""
    pos = max([i for i, t in enumerate(tokens) if t[:1].upper() == "G"], default=-1) + 1
    return max(pos, _after_line_number(tokens))


def _after_line_number(tokens):
    return 1 if tokens and tokens[0][:1].upper() == "N" else 0


def _replace_feed(body, feed, fmt, sep):
    code, comment = _split_comment(body)
    toks = tokenize_line(code)
    out = [fmt("F", feed, False) if (t[0] == "word" and t[1][0].upper() == "F") else t[1] for t in toks]
    return sep.join(out) + comment


def _modal_per_line(lines, pattern, default):
    """Per line, the modal value of a two-state G group after the line (regex group 1)."""
    state = default
    out = []
    for line in lines:
        if "G" in line or "g" in line:
            code = line.split("(", 1)[0].split(";", 1)[0]
            for m in pattern.finditer(code):
                state = m.group(1)
        out.append(state)
    return out


def _arc_sweep(p: Program, r: int) -> float:
    plane = int(p.arc_plane[r])
    i, j = {17: (0, 1), 18: (2, 0), 19: (1, 2)}[plane]
    c = p.arc_center[r]
    s, e = p.start[r], p.end[r]
    a0 = np.arctan2(s[j] - c[j], s[i] - c[i])
    a1 = np.arctan2(e[j] - c[j], e[i] - c[i])
    ccw = p.motion[r] == ARC_CCW
    sweep = (a1 - a0) % (2 * np.pi) if ccw else (a0 - a1) % (2 * np.pi)
    if sweep < 1e-12:
        sweep = 2 * np.pi
    return float(sweep + 2 * np.pi * (max(int(p.arc_turns[r]), 1) - 1))


def _arc_points(p: Program, r: int, n: int) -> np.ndarray:
    """(n+1, 6) points along an arc (program coordinates), from its start to its end; helical axis linear."""
    plane = int(p.arc_plane[r])
    i, j = {17: (0, 1), 18: (2, 0), 19: (1, 2)}[plane]
    normal = 3 - i - j
    c = p.arc_center[r]
    s, e = p.start[r], p.end[r]
    a0 = np.arctan2(s[j] - c[j], s[i] - c[i])
    sweep = _arc_sweep(p, r)
    sign = 1.0 if p.motion[r] == ARC_CCW else -1.0
    rad0 = np.hypot(s[i] - c[i], s[j] - c[j])
    rad1 = np.hypot(e[i] - c[i], e[j] - c[j])
    t = np.linspace(0.0, 1.0, n + 1)
    ang = a0 + sign * sweep * t
    rad = rad0 + (rad1 - rad0) * t
    pts = s[None, :] + t[:, None] * (e - s)[None, :]
    pts[:, i] = c[i] + rad * np.cos(ang)
    pts[:, j] = c[j] + rad * np.sin(ang)
    pts[:, normal] = s[normal] + t * (e[normal] - s[normal])
    pts[-1] = e
    return pts
