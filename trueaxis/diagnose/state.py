"""The twin's side of the gap: simulate the twin, read the gap at every measured point, and the machine state there.

    state = twin_state(cloud_points, cloud_normals, twin_machine, program_text, part="nas979")
    state.gap_um          # (N,) measured minus twin-predicted deviation along the normal, um

How the gap is read. The twin (the machine file, no extra effects) cuts the program in the virtual shop
(``trueaxis.sim.shop.simulate``) and is probed *at the measured points themselves*, along their normals. The twin's
envelope deviation there, s_twin(p_meas), is the distance from the measured point to the twin's surface along the
normal (positive = the twin's surface lies further out). With p_meas = p0 + d_meas n and the twin's surface at
p0 + d_twin n, s_twin(p_meas) = d_twin - d_meas, so

    gap = d_meas - d_twin = -s_twin(p_meas)          (um)

which needs no nominal point and no analytic surface (to first order in the um-sized deviations; the surface's
curvature over a few um is negligible).

Everything the candidates and the "where" analysis use about the moment a point was cut comes from this twin
simulation -- the cut sample, its time, commanded axes, axis velocities and directions of motion, programmed feed,
the tool pose and the cutting force estimated with the real engagement of the twin's cut -- never from a simulation
truth file.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..machine import ErrorTwin, Machine
from ..postproc.gcode import parse_program


@dataclass
class TwinState:
    """The gap and the twin-simulated machine state at N measured points (rows where the twin cut the point).

    points, normals : (N, 3) measured points (mm) and unit outward normals, part frame.
    gap_um : (N,) measured minus predicted deviation along the normal, um.
    t_s : (N,) program time of the cut, s.  t_end_s : float, program duration, s.
    q : (N, n_axes) commanded axes at the cut (mm, rad).  qdot : (N, n_axes) their velocities (mm/s, rad/s).
    direction : (N, n_axes) direction of motion of each axis at the cut (+1 / -1; the last direction it moved in
        when the axis stands still; 0 if it never moved).
    feed_mm_min : (N,) programmed feed of the cutting block.  block_line : (N,) 1-based source line.
    tip, axis : (N, 3) twin's tool tip (mm) and unit tool axis at the cut, part frame.
    height_mm : (N,) height of the contact above the tool tip along the tool axis, mm.
    force_n : (N, 3) cutting force on the tool estimated by the twin's simulation, part frame, N (zeros when the
        machine file has no [cutting] coefficients; ``has_force`` says which).
    axis_jacobian : (N, 6, n_axes) d(tip mm, unit axis)/d(q) at the cut (``ErrorTwin.axis_jacobian``).
    axis_names, rotary : the machine's axis names and its rotary ones.  machine : the twin (placed as the program says).
    part : "nas979" | "slots".  dropped : number of measured points the twin's program did not cut.
    """

    points: np.ndarray
    normals: np.ndarray
    gap_um: np.ndarray
    t_s: np.ndarray
    t_end_s: float
    q: np.ndarray
    qdot: np.ndarray
    direction: np.ndarray
    feed_mm_min: np.ndarray
    block_line: np.ndarray
    tip: np.ndarray
    axis: np.ndarray
    height_mm: np.ndarray
    force_n: np.ndarray
    has_force: bool
    axis_jacobian: np.ndarray
    axis_names: tuple
    rotary: tuple
    machine: Machine
    part: str
    dropped: int = 0
    timings: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.gap_um.shape[0])

    def subset(self, keep) -> "TwinState":
        """The state at the rows ``keep`` (bool mask or indices)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v[keep] if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == len(self) else v
        return TwinState(**out)


def place_from_setup(machine: Machine, program_text: str, part: str) -> Machine:
    """The twin placed as the program's setup comment says (``(trueaxis-setup: part=.. origin_mm=..)``).

    Raises ValueError when the program is for the other part or its origin is malformed."""
    from ..inspect.programs import read_setup

    setup = read_setup(program_text)
    if setup.get("part") and setup["part"] != part:
        raise ValueError(f"the program is for part {setup['part']!r}, not {part!r}")
    if "origin_mm" in setup:
        origin = np.asarray(setup["origin_mm"], float)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise ValueError("the program's setup comment origin_mm must be three numbers")
        if not np.allclose(origin, machine.workpiece_origin, atol=1e-9):
            machine = dataclasses.replace(machine, workpiece_origin=origin)
    return machine


def _last_direction(qdot_all: np.ndarray) -> np.ndarray:
    """(T, n) sign of each axis' motion, held through stops (the first direction before any motion)."""
    T, n = qdot_all.shape
    sgn = np.where(np.abs(qdot_all) > 1e-9, np.sign(qdot_all), 0.0)
    idx = np.arange(T)[:, None]
    last = np.maximum.accumulate(np.where(sgn != 0, idx, 0), axis=0)
    d = np.take_along_axis(sgn, last, axis=0)
    moved = sgn != 0
    first = np.where(moved.any(axis=0), moved.argmax(axis=0), 0)
    first_sign = sgn[first, np.arange(n)]
    return np.where(d == 0, first_sign[None, :], d)


def twin_state(points, normals, machine: Machine, program_text: str, part: str, *, want_force: bool = True,
               force_stride: int = 10) -> TwinState:
    """Simulate the twin ``machine`` cutting ``program_text`` and read the gap and the state at ``points``.

    points, normals : (N, 3) measured points (mm) and unit outward normals, part frame.
    machine : the twin (as loaded; the program's setup comment places the part).  part : "nas979" | "slots".
    want_force : estimate the cutting force at each cut (needs the machine's [cutting] coefficients; adds the
        force model's time to the simulation).
    Raises ValueError when no measured point was cut by the program.
    """
    import time

    from ..sim.effects import ForceDeflection, Effects
    from ..sim.shop import load_part, simulate

    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must be (N, 3) arrays of the same shape, got {points.shape} and "
                         f"{normals.shape}")
    t0 = time.perf_counter()
    machine = place_from_setup(machine, program_text, part)
    prog = parse_program(program_text, "<program>")
    has_force = bool(want_force and machine.cutting is not None)
    # A zero extra compliance: the shop then estimates the force (real engagement) without moving the tool.
    effects = Effects(force=ForceDeflection(np.zeros((3, 3)))) if has_force else Effects()
    res = simulate(prog, machine, effects, part=part, part_json=load_part(part), probe=(points, normals),
                   force_stride=force_stride)
    cut = np.isfinite(res.deviations_um)
    if not np.any(cut):
        raise ValueError("none of the measured points was cut by the program on the twin: is the cloud in the part "
                         "frame, and is this the program that cut it?")
    traj = res.trajectory
    s = res.sample[cut]
    twin = ErrorTwin(machine)
    q = traj.q[s]
    tip, u = twin.actual_pose(q)
    height = np.einsum("ij,ij->i", points[cut] - tip, u)
    direction = _last_direction(traj.qdot)[s]
    return TwinState(
        points=points[cut], normals=normals[cut], gap_um=-res.deviations_um[cut], t_s=traj.t[s],
        t_end_s=float(traj.t[-1]), q=q, qdot=traj.qdot[s], direction=direction,
        feed_mm_min=traj.feed_mm_min[s], block_line=res.block_line[cut], tip=tip, axis=u, height_mm=height,
        force_n=res.force_n[cut], has_force=has_force, axis_jacobian=twin.axis_jacobian(q),
        axis_names=tuple(machine.axis_names), rotary=tuple(machine.rotary_axes), machine=machine, part=part,
        dropped=int((~cut).sum()), timings={"twin_simulation_s": time.perf_counter() - t0, **res.timings})
