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
import math
from dataclasses import dataclass, field

import numpy as np

from ..inspect.cloud import CloudError
from ..machine import ErrorTwin, Machine
from ..nc.gcode import parse_program
from ..postproc.programs import check_axes, placed_for


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
    lost_motion : (N, C, n_axes, L) each axis' offset over half its lost motion, for the take-up transitions
        ``REVERSAL_TRANSITIONS`` (``lost_motion_state``: a play with memory), at C = 3 cuts of each point: the
        twin's, and its earliest and latest cuts within ``TIED_CUT_UM`` of it (a pass boundary; the same sample
        where there is none).
    lost_motion_depth : (N, C) the twin's depth at those cuts relative to its deepest, um (>= 0 to a rounding).
    lag_velocity : (N, n_axes, M) each axis' commanded velocity at the cut through first-order filters of unit DC
        gain with the time constants ``lag_taus_s`` (``lag_filtered_velocity``), mm/s or rad/s: a position loop of
        time constant tau_m and velocity feed-forward ff follows with the error -(1 - ff) tau_m w.
    lag_deviation : (N, M) the deviation a first-order position loop of time constant tau_m on every axis (no
        feed-forward: lag = tau_m) adds at each point, per ms of lag (um/ms), read at the lagged tool's deepest cut
        (``lagged_cut``).
    lag_axis : (N, n_axes, M) the deviation per ms of a further lag of one axis alone there (um/ms).
    axis_names, rotary : the machine's axis names and its rotary ones.  machine : the twin (placed as the program says).
    part : "nas979" | "slots".  dropped : number of measured points the twin's program did not cut.
    piece : (N,) which of several cuts (parts cut one after another on one machine, ``combine_states``) each row is
        of; None for one cut.  machines : each cut's twin as its program places it (by ``piece``; empty: ``machine``).
    t_datum_s : (N,) program time at which the row's part was set up (its datum probed, so a drift is seen from
        there), s; None: 0 (one cut).  pauses_s : the pauses between the cuts' programs (s, as given; one cut: ()).
    flyers : per cut, the measured points set apart as flyers before the diagnosis (``FlyerScreen.as_dict`` with the
        cloud's name; ``trueaxis.inspect.flyers``); their rows are not in the state.
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
    lost_motion: np.ndarray | None = None
    lost_motion_depth: np.ndarray | None = None
    lag_velocity: np.ndarray | None = None
    lag_deviation: np.ndarray | None = None
    lag_axis: np.ndarray | None = None
    lag_taus_s: tuple = ()
    piece: np.ndarray | None = None
    machines: tuple = ()
    t_datum_s: np.ndarray | None = None
    pauses_s: tuple = ()
    flyers: tuple = ()
    timings: dict = field(default_factory=dict)
    memo: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.gap_um.shape[0])

    def subset(self, keep) -> "TwinState":
        """The state at the rows ``keep`` (bool mask or indices)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v[keep] if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == len(self) else v
        out["memo"] = {}
        return TwinState(**out)

    def placements(self) -> list:
        """[(rows, twin)]: the rows (bool mask) of each cut with its twin as placed (one entry for one cut)."""
        if self.piece is None or not self.machines:
            return [(np.ones(len(self), bool), self.machine)]
        return [(self.piece == k, m) for k, m in enumerate(self.machines) if np.any(self.piece == k)]

    def since_datum_s(self) -> np.ndarray:
        """(N,) time since each row's part was set up, s (the program time for one cut)."""
        return self.t_s if self.t_datum_s is None else self.t_s - self.t_datum_s


def pauses_between(n_cuts: int, pauses_s) -> np.ndarray:
    """The pauses between ``n_cuts`` cuts (s, >= 0): one number for every gap, or one per gap in the order cut;
    ValueError otherwise. None with several cuts is refused: a drift runs on through a pause, so none is assumed."""
    if n_cuts < 2:
        return np.zeros(0)
    if pauses_s is None:
        raise ValueError(f"{n_cuts} parts: give the pause between one part's cut and the next (s; 0 when cut right "
                         f"after each other): a drift runs on through it (--pause-s)")
    pauses = np.atleast_1d(np.asarray(pauses_s, float)).reshape(-1)
    pauses = np.full(n_cuts - 1, pauses[0]) if pauses.size == 1 else pauses
    if pauses.size != n_cuts - 1 or not np.all(np.isfinite(pauses) & (pauses >= 0.0)):
        raise ValueError(f"the pauses between {n_cuts} parts: one number >= 0 for all, or {n_cuts - 1} (one per gap, "
                         f"in the order cut), s; got {np.asarray(pauses_s, float).tolist()}")
    return pauses


def combine_states(states: list, pauses_s=()) -> TwinState:
    """One state of several cuts measured on one machine, cut one after another (the second placement of a part, or
    the same program again after a warm-up): the rows of all, the clock running on (cut k starts ``pauses_s[k - 1]``
    seconds after cut k - 1 has ended: the machine's clock, which a drift follows whether or not it cuts), each row
    knowing its cut (``piece``), that cut's placed twin (``machines``) and the time its part was set up
    (``t_datum_s``: a drift is seen from each part's datum). The candidates then share their parameters over the
    cuts: one machine, one backlash, one drift, one set of location errors.

    pauses_s : the pauses between the cuts (``pauses_between``)."""
    pauses = pauses_between(len(states), pauses_s)
    if len(states) == 1:
        return states[0]
    first = states[0]
    for st in states[1:]:
        if st.axis_names != first.axis_names or st.part != first.part or st.lag_taus_s != first.lag_taus_s:
            raise ValueError("the cuts to diagnose together must be of one machine and one part")
    offsets = np.cumsum([0.0] + [st.t_end_s + w for st, w in zip(states[:-1], pauses)])
    n = [len(st) for st in states]
    out = {}
    for f in dataclasses.fields(TwinState):
        vals = [getattr(st, f.name) for st in states]
        v0 = vals[0]
        if f.name == "t_s":
            out[f.name] = np.concatenate([v + o for v, o in zip(vals, offsets)])
        elif isinstance(v0, np.ndarray) and v0.ndim >= 1 and v0.shape[0] == n[0]:
            out[f.name] = np.concatenate(vals)
        else:
            out[f.name] = v0
    out["t_end_s"] = float(offsets[-1] + states[-1].t_end_s)
    out["has_force"] = all(st.has_force for st in states)
    out["dropped"] = sum(st.dropped for st in states)
    out["piece"] = np.repeat(np.arange(len(states)), n)
    out["machines"] = tuple(st.machine for st in states)
    out["t_datum_s"] = np.repeat(offsets, n)
    out["pauses_s"] = tuple(float(w) for w in pauses)
    out["flyers"] = tuple(x for st in states for x in st.flyers)
    out["timings"] = {k: sum(st.timings.get(k, 0.0) for st in states) for k in first.timings}
    out["memo"] = {}
    return TwinState(**out)


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


#: Transitions over which a lost motion is taken up after a reversal (mm for a linear axis, deg for a rotary one; 0:
#: a step): the backlash candidate's variants.
REVERSAL_TRANSITIONS = (0.0, 0.005, 0.02, 0.06, 0.2)

#: Time constants (s) of the servo-lag candidate's filters. A position loop's time constant 1/Kv is 6-60 ms on real
#: machine tools (Kv 1-10 (m/min)/mm = 17-170 /s; 22-40 ms at kv 25-45 /s); three filters spaced by about 3x bracket
#: that range: a loop with a time constant between two of them is matched by a positive mixture of the two to a few
#: per cent of its transient. With velocity feed-forward ff the loop's error is (1 - ff) times the plain loop's, so
#: the mixture's weights are (1 - ff) tau, the lag the drive leaves. More filters would add parameters whose columns
#: differ only at the few points cut within ~3 tau of a velocity change.
LAG_TAUS_S = (0.004, 0.012, 0.035)
#: How far from the twin's cut sample a lagged tool's cut is looked for (s): 4 tau_max.
LAG_WINDOW_S = 4.0 * max(LAG_TAUS_S)


def lag_filtered_velocity(traj, taus_s=LAG_TAUS_S) -> np.ndarray:
    """(T, n_axes, M) the commanded axis velocity of ``traj`` through first-order filters of unit DC gain,
    h_tau(t) = exp(-t/tau)/tau, one per time constant in ``taus_s``.

    The velocity over the period ending at sample k is (q[k] - q[k-1]) / dt (what a position loop closed at dt sees);
    the filter is the exact sampled form of h_tau for a velocity held over each period,
    w[k] = a w[k-1] + (1 - a) v[k], a = exp(-dt/tau). A first-order loop de/dt = v - e/tau then follows with the error
    e = -tau w (to within dt/2 of tau at the sampled times).

    Rapids are taken as settled: their velocity is set to zero, as a control holds the axes in position after a
    rapid before the next feed move (the twin's rapids are unplanned steps at the rapid rate; their lag is not in the
    cut). The filter's state decays through the rapid and the hold like a loop coming to rest."""
    from scipy.signal import lfilter

    q = np.asarray(traj.q, float)
    dt = float(traj.dt)
    v = np.zeros_like(q)
    v[1:] = np.diff(q, axis=0) / dt
    rapid = np.asarray(traj.motion) == 0
    v[rapid] = 0.0
    out = np.empty(q.shape + (len(taus_s),))
    for m, tau in enumerate(taus_s):
        a = math.exp(-dt / float(tau))
        out[:, :, m] = lfilter([1.0 - a], [1.0, -a], v, axis=0)
    return out


def lagged_cut(points, normals, traj, anchors, tips, axes, radius, length, move, taus_s=LAG_TAUS_S,
               window_s: float | None = None):
    """Where a first-order loop of each lag time tau_m cuts each point, to first order in its transient.

    The machined surface is the envelope of the tool instances (the deepest cut along the normal), so a lagged tool
    need not cut a point at the twin's cut sample. The loop's tool at sample k is q_c(k) - tau w(k): the twin's
    commanded pose tau earlier, q_c(k - n) (n = tau / dt; rapids taken as settled), plus the transient
    rho(k) = q_c(k) - q_c(k - n) - tau w(k), which vanishes at steady speed and is the corner transient at a corner,
    the remaining travel at a stop. So the lagged tool's instances are the twin's own (exact geometry, the same
    instances shifted in time), each moved by the small rho; instance j of the twin, moved by rho(j + n), cuts the
    point at s_j + (m_j . M rho) / (m_j . n) (s_j its exact depth by line-solid intersection, m_j the tool's outward
    surface normal where the line enters it, M the axes' tool displacement at the twin's cut). The deepest over the
    samples within ``window_s`` (default 4 tau_max) of the anchors (the twin's first and last tied cut samples: a
    point on a pass boundary is cut as deep by two passes) is the lagged cut.

    points, normals : (N, 3).  traj : the twin's ``Trajectory``.  anchors : (N, A) sample indices, the first the
        twin's cut sample.  tips, axes : (T, 3) the twin's tool tip and axis at every sample (part frame; only those
        within the windows are read).  radius, length : the tool's.
    move : (N, 3, n_axes) (J_p + h J_u) at the cut sample, tool displacement (mm) per mm / rad of each axis, taken as
        constant over the window.
    Returns, per filter m, at the lagged cut: the loop's deviation there divided by tau_m, um per ms (N, M); and the
    deviation per ms of a further lag of each axis alone there, -(m . M_j) / (m . n) w_j, um per ms (N, n_axes, M).
    """
    from ..sim.envelope import line_tool_intersection

    wv = lag_filtered_velocity(traj, taus_s)
    T, n_ax = traj.q.shape
    dt = float(traj.dt)
    # The commanded motion with the rapids removed (taken as settled, as in ``lag_filtered_velocity``).
    v = np.zeros_like(traj.q)
    v[1:] = np.diff(traj.q, axis=0) / dt
    v[np.asarray(traj.motion) == 0] = 0.0
    qf = np.cumsum(v, axis=0) * dt
    half = int(math.ceil((window_s if window_s is not None else 4.0 * max(taus_s)) / dt))
    offs = np.arange(-half, half + 1)
    anchors = np.asarray(anchors, int).reshape(len(points), -1)
    N, A = anchors.shape
    W = A * offs.size
    M = len(taus_s)
    out_dev = np.empty((N, M))
    out_axis = np.empty((N, n_ax, M))
    cutting = np.asarray(traj.motion) != 0
    chunk = max(1, 200_000 // W)
    for a0 in range(0, N, chunk):
        sl = slice(a0, min(N, a0 + chunk))
        K = np.clip(anchors[sl, :, None] + offs[None, None, :], 0, T - 1).reshape(-1, W)
        n = K.shape[0]
        P = np.repeat(points[sl], W, 0)
        Nn = np.repeat(normals[sl], W, 0)
        s_in, _ = line_tool_intersection(P, Nn, tips[K.ravel()], axes[K.ravel()], radius, length)
        s_k = np.where(cutting[K], s_in.reshape(n, W), np.inf)
        s0 = s_k[:, half]  # the first anchor: the twin's cut sample
        rel = np.where(np.isfinite(s0)[:, None], s_k - np.where(np.isfinite(s0), s0, 0.0)[:, None], np.inf)
        rel[:, half] = 0.0
        # The tool's outward surface normal where the line enters instance j: a move delta of the tool changes the
        # entry by (m . delta) / (m . n) (= n . delta at the twin's cut, where m = -n on a flank).
        x = P + np.where(np.isfinite(s_in), s_in, 0.0)[:, None] * Nn
        tp, ax = tips[K.ravel()], axes[K.ravel()]
        wrel = x - tp
        h = np.einsum("ij,ij->i", wrel, ax)
        rad = wrel - h[:, None] * ax
        rn = np.linalg.norm(rad, axis=1)
        side = rn >= radius * (1.0 - 1e-6)
        mvec = np.where(side[:, None], rad / np.maximum(rn, 1e-12)[:, None],
                        np.where((h <= 0.5 * length)[:, None], -ax, ax))
        mn = np.minimum(np.einsum("ij,ij->i", mvec, Nn), -0.2)  # grazing entries: a bounded gain
        resp = (np.einsum("ik,ikj->ij", mvec, np.repeat(move[sl], W, 0)) / mn[:, None]).reshape(n, W, n_ax)
        rows = np.arange(n)
        for m, tau in enumerate(taus_s):
            sh = int(round(float(tau) / dt))
            Ks = np.minimum(K + sh, T - 1)
            rho = qf[Ks] - qf[K] - float(tau) * wv[Ks, :, m]  # (n, W, n_axes), mm / rad
            part = resp * rho * 1e3  # um
            tot = np.where(np.isfinite(rel), rel * 1e3 + part.sum(axis=2), np.inf)
            kk = np.argmin(tot, axis=1)
            out_dev[sl, m] = tot[rows, kk] / (1e3 * float(tau))
            out_axis[sl, :, m] = -resp[rows, kk] * wv[Ks[rows, kk], :, m]
    return out_dev, out_axis


#: Two cuts of a point within this depth (um) of each other are both candidates for the one that made the surface
#: once an effect moves the tool: a pass boundary, or two passes to the same depth (the deeper with the effect wins).
TIED_CUT_UM = 3.0


def _tied_samples(res, points, normals, twin, machine, tie_um: float = TIED_CUT_UM) -> np.ndarray:
    """(N, 2) the earliest and the latest sample whose twin tool cuts each point within about ``tie_um`` of its
    deepest cut; -1 where none. Each is the deepest cut of the envelope with the tool's radius grown by up to
    ``tie_um`` towards the early (the late) end of the program, so that a cut within that much of the deepest wins
    by its time alone."""
    from ..sim.envelope import envelope_deviation

    traj = res.trajectory
    ci = np.nonzero(np.asarray(traj.motion) != 0)[0]
    tip, u = twin.actual_pose(traj.q[ci])
    frac = np.linspace(0.0, 1.0, ci.size) if ci.size > 1 else np.zeros(ci.size)
    out = np.full((len(points), 2), -1, int)
    for k, bias in enumerate((1.0 - frac, frac)):
        env = envelope_deviation(points, normals, tip, u, machine.tool.radius + 1e-3 * tie_um * bias,
                                 machine.tool.flute_length)
        out[:, k] = np.where(env.instance >= 0, ci[np.maximum(env.instance, 0)], -1)
    return out


def _relative_depth(points, normals, cuts, twin, q, machine) -> np.ndarray:
    """(N, C) where the twin's tool at each of the samples ``cuts`` (N, C) cuts each point along its normal,
    relative to the first column's cut, um."""
    from ..sim.envelope import line_tool_intersection

    N, C = cuts.shape
    tip, u = twin.actual_pose(q[cuts.ravel()])
    s_in, _ = line_tool_intersection(np.repeat(points, C, 0), np.repeat(normals, C, 0), tip, u,
                                     machine.tool.radius, machine.tool.flute_length)
    s_in = s_in.reshape(N, C)
    rel = 1e3 * (s_in - s_in[:, :1])
    return np.where(np.isfinite(rel), rel, np.inf)


def lost_motion_state(x: np.ndarray, transitions) -> np.ndarray:
    """(T, L) an axis' offset from its command over half its lost motion b/2 (in [-1, 1]) along its commanded
    positions x (T,), for a take-up f = tanh over each transition (L,) (mm or rad; 0: a step).

    The play with memory (the diagnosis' own form of it): in each run of one direction d (the direction of the
    step that brought the axis to the sample, held through stops) the offset is d (1 - 2 tanh(s / transition + s0)),
    s the travel since the run's start and s0 = atanh((1 - d e0) / 2) from the offset e0 the run starts with: after a
    long travel the other way e0 = d, s0 = 0; after a reversal of a few nanometres the offset hardly moves. Before
    any motion the axis is taken up in its first direction. The loop is over runs (reversals), each in closed form."""
    x = np.asarray(x, float)
    T = x.shape[0]
    out = np.empty((T, len(transitions)))
    d = _last_direction(np.diff(x, prepend=x[:1])[:, None])[:, 0]
    d = np.where(d == 0, 1.0, d)
    starts = np.concatenate([[0], np.nonzero(d[1:] != d[:-1])[0] + 1, [T]])
    for li, lam in enumerate(transitions):
        e = out[:, li]
        e[: starts[1]] = -d[0]
        for a, z in zip(starts[1:-1], starts[2:]):
            y0 = min(max(0.5 * (1.0 - d[a] * e[a - 1]), 0.0), 1.0 - 1e-15)
            s = np.abs(x[a:z] - x[a - 1]) / lam if lam > 0 else np.full(z - a, np.inf)
            e[a:z] = d[a] * (1.0 - 2.0 * np.tanh(s + np.arctanh(y0)))
    return out


def twin_state(points, normals, machine: Machine, program_text: str, part: str, *, want_force: bool = True,
               force_stride: int = 10, part_json: dict | None = None, program_name: str = "<program>") -> TwinState:
    """Simulate the twin ``machine`` cutting ``program_text`` and read the gap and the state at ``points``.

    points, normals : (N, 3) measured points (mm) and unit outward normals, part frame.
    machine : the twin (as loaded; the program's setup comment places the part).  part : "nas979" | "slots".
    part_json : the part's description (``trueaxis.workpiece`` JSON dict; default: the part's default size),
        for the stock's shape the force model engages.
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
    machine = placed_for(machine, program_text, part)  # where the program's setup comment places the part
    prog = parse_program(program_text, program_name)
    check_axes(machine, prog)
    has_force = bool(want_force and machine.cutting is not None)
    # A zero extra compliance: the shop then estimates the force (real engagement) without moving the tool.
    effects = Effects(force=ForceDeflection(np.zeros((3, 3)))) if has_force else Effects()
    res = simulate(prog, machine, effects, part=part, part_json=load_part(part, part_json), probe=(points, normals),
                   force_stride=force_stride)
    cut = np.isfinite(res.deviations_um)
    if not np.any(cut):
        raise CloudError("none of the measured points was cut by the program on the twin: is the cloud in the part "
                         "frame, and is this the program that cut it?")
    traj = res.trajectory
    s = res.sample[cut]
    twin = ErrorTwin(machine)
    q = traj.q[s]
    tip, u = twin.actual_pose(q)
    height = np.einsum("ij,ij->i", points[cut] - tip, u)
    # The direction of the step that brought each axis to the sample (the motion a lost motion depends on, as
    # ``lost_motion_state`` and the shop's ``Backlash`` have it): ``qdot`` at a block's first sample is already the next
    # block's, and an axis' extremum (where a surface point is cut) is where a block turns it.
    direction = _last_direction(np.diff(traj.q, axis=0, prepend=traj.q[:1]))[s]
    jac = twin.axis_jacobian(q)
    lag_velocity = lag_filtered_velocity(traj, LAG_TAUS_S)[s]
    move = jac[:, :3] + height[:, None, None] * jac[:, 3:]  # (N, 3, n_axes) tool displacement per axis
    # The lagged cut (see ``lagged_cut``) around the twin's first and last tied cut samples.
    tied = _tied_samples(res, points[cut], normals[cut], twin, machine)
    tied = np.where(tied >= 0, tied, s[:, None])
    anchors = np.column_stack([s, tied[:, 1]])
    half = int(math.ceil(LAG_WINDOW_S / traj.dt))
    ks = np.unique(np.clip(anchors.ravel()[:, None] + np.arange(-half, half + 1)[None, :], 0, len(traj) - 1))
    tips_all = np.zeros((len(traj), 3))
    axes_all = np.tile([0.0, 0.0, 1.0], (len(traj), 1))
    tips_all[ks], axes_all[ks] = twin.actual_pose(traj.q[ks])
    lag_dev, lag_axis = lagged_cut(points[cut], normals[cut], traj, anchors, tips_all, axes_all, machine.tool.radius,
                                   machine.tool.flute_length, move, LAG_TAUS_S, LAG_WINDOW_S)
    rotary = set(machine.rotary_axes)
    # The play at the twin's cut and at its earliest and latest tied cuts (N, 3 cuts, n_axes, L), and the twin's
    # depth at those cuts relative to the deepest (N, 3), mm: the backlash candidate takes the deepest with the play.
    cuts = np.column_stack([s, tied])
    lost = np.stack([lost_motion_state(traj.q[:, j], [math.radians(x) if a in rotary else x
                                                      for x in REVERSAL_TRANSITIONS])[cuts]
                     for j, a in enumerate(machine.axis_names)], axis=2)
    lost_rel = _relative_depth(points[cut], normals[cut], cuts, twin, traj.q, machine)
    return TwinState(
        points=points[cut], normals=normals[cut], gap_um=-res.deviations_um[cut], t_s=traj.t[s],
        t_end_s=float(traj.t[-1]), q=q, qdot=traj.qdot[s], direction=direction,
        feed_mm_min=traj.feed_mm_min[s], block_line=res.block_line[cut], tip=tip, axis=u, height_mm=height,
        force_n=res.force_n[cut], has_force=has_force, axis_jacobian=jac,
        axis_names=tuple(machine.axis_names), rotary=tuple(machine.rotary_axes), machine=machine, part=part,
        dropped=int((~cut).sum()), lost_motion=lost, lost_motion_depth=lost_rel,
        lag_velocity=lag_velocity,
        lag_deviation=lag_dev,
        lag_axis=lag_axis,
        lag_taus_s=tuple(LAG_TAUS_S),
        timings={"twin_simulation_s": time.perf_counter() - t0, **res.timings})
