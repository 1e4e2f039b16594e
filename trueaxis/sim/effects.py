"""Effects of the virtual shop that the error twin may not have (DESIGN §8), each off by default.

Two kinds, applied in this order by ``shop.simulate``:

1. On the axes (commanded q -> actual q, before the twin's kinematics and geometric errors):
   ``ServoLag`` (position loops per axis with feed-forward and a velocity loop, at the interpolation period),
   ``Backlash`` (lost motion at reversals, every axis), ``RotaryPeriodic`` (harmonics of a rotary axis' own angle).
2. In the kinematic chain: ``RotaryErrorMotion`` (the ISO 230-7 error motions of a rotary axis, as a small transform
   at that axis).
3. On the tool pose in the part frame (after ``ErrorTwin.actual_pose``): ``ForceDeflection`` (machine compliance times
   the cutting force), ``ToolDeflection`` (carbide cantilever), ``ThermalDrift`` (a measured series), ``Clamping``
   (a smooth deformation field of the clamped part) or ``ClampingBend`` (a bent part springing back), then
   ``ToolWear`` (the tool's radius and length along its cut path).

EFFECTS.toml (every table optional; a table present switches its effect on unless ``enabled = false``; unknown keys
are errors; lengths in um or mm as the key says, angles in urad)::

    [servo]                                   # first-order position loop per axis
    kv_per_s = { X = 30.0, Y = 30.0, Z = 30.0, B = 25.0, C = 25.0 }
    accel = { X = 2000.0, Y = 2000.0, Z = 2000.0, B = 360.0, C = 720.0 }   # mm/s^2 (linear), deg/s^2 (rotary)
    kff = { X = 0.9, Y = 0.9, Z = 0.9, B = 0.9, C = 0.9 }   # velocity feed-forward, 0..1 (default 0)
    aff = { X = 0.5 }                         # acceleration feed-forward, 0..1 (default 0; acts on the velocity loop)
    velocity_loop_ms = { X = 3.0 }            # first-order velocity loop time constant, ms (default 0 = ideal)
    smoothing_ms = 24.0                       # interpolator's acc/dec after interpolation (moving average), ms, or
                                              # "auto": the shortest keeping the feed moves within the accel limits

    [backlash.X]                              # one table per axis, rotary ones too ([backlash.C]: urad and deg)
    amplitude = 4.0                           # um (linear) or urad (rotary): total lost motion
    transition = 0.02                         # mm or deg of travel after a reversal over which it is taken up
    form = "tanh"                             # "tanh" (default) or "friction" (Dahl: 1 - exp(-s / transition))

    [rotary_periodic.C]
    harmonics_urad = [[1, 12.0, -5.0], [2, 3.0, 0.0]]   # [k per turn, cos, sin] of the axis' angle error

    [rotary_error_motion.C]                   # ISO 230-7 error motions, in the chain at C (see RotaryErrorMotion)
    EXC = { harmonics = [[1, 2.0, 0.0]] }     # radial (um): [k per turn, cos, sin] ...
    EYC = { harmonics = [[1, 0.0, -2.0]] }    #   (EXC, EYC = e cos, -e sin once per turn: an eccentric table)
    EZC = { harmonics = [[2, 0.5, 0.3]] }     # axial (um)
    EAC = { harmonics = [[1, 4.0, -2.5]] }    # tilt (urad), also EBC
    ECC = { harmonics = [[2, 8.0, 0.0]], linear_per_turn = 10.0 }   # angular positioning (urad), + slope per turn
    relative_to_zero = true                   # subtract each component's value at angle 0 (default)

    [force]                                   # deflection from the cutting force (needs cutting conditions)
    compliance_um_per_n = [[0.02, 0, 0], [0, 0.02, 0], [0, 0, 0.01]]  # extra, tool relative to workpiece, machine frame
    use_machine_compliance = true             # also pass the force to the twin ([force] of the machine file)

    [tool_deflection]
    stick_out_mm = 40.0                       # clamp to tip
    youngs_modulus_gpa = 600.0                # carbide
    diameter_factor = 0.8                     # I = pi (factor d)^4 / 64

    [thermal]
    file = "fixtures/thermal/spindle_thermal_drift_part1.csv"   # relative to the EFFECTS file, or absolute
    channels = { Z = "ch3_um", X = "ch1_um" } # machine direction -> column (um, tool relative to table)
    time_scale = 60.0                         # series seconds per program second
    time_offset_s = 3600.0                    # series time at program time 0
    amplitude_scale = 1.0
    relative_to_start = true                  # subtract the value at program time 0 (the part is set up then)

    [clamping]                                # Gaussian bump d(x) = A e exp(-|x - c|^2 / (2 l^2)), part frame
    amplitude_um = 5.0
    center = [0.0, 0.0, 0.0]
    length_mm = 30.0
    direction = [0.0, 0.0, 1.0]
    # or form = "bending": the part springs back from a beam's bending (ClampingBend): keys amplitude_um (mid-span
    # deflection), center, span_mm, beam (beam direction), direction (deflection direction), part frame

    [tool_wear]                               # flank wear along the cut path (ToolWear)
    vb_run_in_um = 30.0                       # VB reached by the run-in, um
    run_in_mm = 200.0                         # run-in path length, mm
    vb_rate_um_per_m = 10.0                   # steady VB growth, um per m of cut
    clearance_deg = 8.0                       # peripheral clearance: radius loss VB tan(alpha)
    end_clearance_deg = 0.0                   # end clearance: length loss VB tan(alpha_e) (0 = none)

Every effect works on arrays of samples (no per-sample Python loop), except the saturating part of the servo loop,
which steps through the few samples where the acceleration limit is active (see ``ServoLag``).
"""

from __future__ import annotations

import csv
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np
from scipy.signal import lfilter

from ..machine.kinematics import axis_motion, chain_links
from ..machine.model import Machine
from ..machine.transforms import compose
from ..nc.trajectory import PERIOD_S

UM = 1e-3
URAD = 1e-6


class EffectsFileError(ValueError):
    """An EFFECTS.toml the loader refuses; the message lists every problem with its key path."""


# ------------------------------------------------------------------------------------------------- axis effects ----
@dataclass(frozen=True)
class ServoLag:
    """Position loop of each axis: a proportional loop of gain Kv on the following error, the drive's acceleration
    limited, and the rapids' commanded motion planned within that limit as a control does.

    kv_per_s : axis -> Kv, 1/s (axes not named follow the command exactly).
    accel : axis -> acceleration limit a, mm/s^2 (linear) or deg/s^2 (rotary); absent = unlimited.
    kff : axis -> velocity feed-forward gain (0..1, typically 0.9); aff : axis -> acceleration feed-forward gain (0..1);
    velocity_loop_ms : axis -> time constant of the velocity loop, ms (0 = ideal). See "Feed-forward" below.

    Model (continuous form; q in mm or rad, t in s). The following error e = q_cmd - q obeys
        de/dt = v_cmd - v,   v = Kv e   (unsaturated: de/dt = v_cmd - Kv e),   |dv/dt| <= a.
    With equal gains every axis lags by the same time 1/Kv, so a straight feed move at path speed v lags v/Kv along
    the path and not at all across it; a circle of radius R at speed v shrinks by R (1 - 1/sqrt(1 + (v/(Kv R))^2))
    ~ R (v / (Kv R))^2 / 2 (the gain of 1/(1 + j w/Kv) at w = v/R); a sharp corner turning by theta at speed v is
    cut by ln(2) sin(theta/2) v/Kv at its vertex (55 um at 45 deg, 1000 mm/min, Kv 80 /s).

    Discrete form at the interpolation period dt (a position loop closed at dt, its velocity command held over the
    period): q[k+1] = q[k] + v[k] dt, v[k] = Kv (q_cmd[k] - q[k]) clamped to |v[k] - v[k-1]| <= a dt. Unsaturated,
    q[k+1] = (1 - Kv dt) q[k] + Kv dt q_cmd[k], stable and free of overshoot for 0 < Kv dt < 1 (required); a
    constant-speed ramp lags exactly v/Kv; a sinusoid of angular frequency w is scaled by
    |Kv dt / (exp(j w dt) - 1 + Kv dt)| (-> 1/sqrt(1 + (w/Kv)^2) as dt -> 0; at Kv dt = 0.08 the radius loss of a
    circle is ~8 % smaller than the continuous one).

    Command planning. An acceleration-limited loop only follows commands that respect the limit: a velocity step Dv
    needs Kv |Dv| <= a, and an abrupt stop at speed v lags v/Kv but needs v^2/(2a) to brake, so it overshoots when
    v > 2a/Kv (50 mm/s at Kv 80 /s, a 2 m/s^2). The interpolator's rapids are such steps (every axis at its rapid
    rate from the first period to the last: 10 m/min at Kv 80 /s lags 2.1 mm and needs 6.9 mm to stop), so, as a CNC
    plans its rapid traverse with acceleration and deceleration, every rapid block's command is re-profiled along its
    own straight line in axis space: a trapezoidal (or triangular) speed profile starting and ending at rest, peak
    speed the interpolator's, path acceleration the largest every limited axis allows (|dq_i| s'' <= a_i), from the
    block's start time, ending within the block's time (its motion plus the in-position hold ``rapid_settle_s``;
    ``settle_time`` gives the hold this loop needs). Feed moves keep the interpolator's constant speed: at their block
    junctions the clamp above is the drive's saturation (inactive while Kv |Dv| <= a). Rapids are known only when the
    trajectory's row and motion code are given (``apply(..., traj=...)``, as ``shop.simulate`` does); without them
    the command is taken as it is.

    The interpolator's acceleration limits (``smoothing_ms``, default 0): the command is first smoothed by a moving
    average over that time (``smooth_command``, the "acceleration/deceleration after interpolation" of a CNC), so that
    the velocity steps at block junctions become ramps of dv / T that the drive can follow without saturating;
    "auto" takes the shortest time that keeps every limited axis within its limit on the feed moves
    (``smoothing_s``).

    Feed-forward and the velocity loop (``kff``, ``aff``, ``velocity_loop_ms``; per axis, default 0), as a real drive
    has them. The interpolator's velocity v_c[k] = (q_cmd[k+1] - q_cmd[k]) / dt and acceleration
    a_c[k] = (v_c[k] - v_c[k-1]) / dt are fed forward; the velocity loop is a first-order lag of time constant T_v
    (beta = 1 - exp(-dt / T_v), beta = 1 for an ideal loop):

        v_ref[k] = Kv (q_cmd[k] - q[k]) + kff v_c[k] + aff a_c[k] dt (1 - beta) / beta
        v[k] = v[k-1] + beta (v_ref[k] - v[k-1]),  clamped to |v[k] - v[k-1]| <= a dt
        q[k+1] = q[k] + v[k] dt

    A constant-speed ramp then lags by exactly (1 - kff) v / Kv (any T_v); the acceleration term cancels the velocity
    loop's lag v (1 - beta) / beta per sample under a constant acceleration (T_v a as dt -> 0), so that with kff = aff
    = 1 a parabola is followed without error. With kff = aff = T_v = 0 it is the loop above; with Kv dt < 1 it is stable
    for any T_v (see ``servo_axis_ff``). It is stepped sample by sample in a compiled loop
    (``_servo_ff_loop``, numba): exact for this model, saturation included.

    The vectorised solution: the linear part is ``scipy.signal.lfilter``; where the clamp is active the loop is
    stepped sample by sample until it is unsaturated again, and the linear solution after it is corrected by the
    decaying difference (the loop is linear there, so the difference decays as (1 - Kv dt)^k). Exact for this model.
    """

    kv_per_s: dict
    accel: dict = field(default_factory=dict)
    kff: dict = field(default_factory=dict)
    aff: dict = field(default_factory=dict)
    velocity_loop_ms: dict = field(default_factory=dict)
    smoothing_ms: float | str = 0.0

    #: in-position width of ``settle_time``: mm (linear), rad (rotary)
    IN_POSITION = {False: 1e-4, True: 1e-6}

    def _accel_rad(self, machine: Machine, name):
        a = self.accel.get(name)
        if a is not None and machine.axes[name].is_rotary:
            a = math.radians(a)
        return None if a is None else float(a)

    def settle_time(self, machine: Machine, rapid_mm_min: float = 10_000.0, rapid_deg_min: float = 3_600.0) -> float:
        """Hold after a rapid (s) for the planned rapid and the loop's decay to within IN_POSITION of its end: per
        axis the deceleration v/a of a rapid at the full rapid rate (0 if unlimited), then ln(e0 / width) / Kv, e0 the
        lag left when the command stops (a/Kv^2 after a ramp at a, v/Kv after an unlimited stop), plus the smoothing
        time and five velocity-loop time constants."""
        t = 0.0
        for name, kv in self.kv_per_s.items():
            rot = machine.axes[name].is_rotary
            v = math.radians(rapid_deg_min / 60.0) if rot else rapid_mm_min / 60.0
            a = self._accel_rad(machine, name)
            ramp, e0 = (0.0, v / kv) if a is None else (v / a, a / kv**2)
            t = max(t, ramp + max(0.0, math.log(e0 / self.IN_POSITION[rot])) / kv)
        # The smoothed command arrives smoothing_ms later; a velocity loop settles within a few of its time constants.
        smooth = 0.1 if self.smoothing_ms == "auto" else 1e-3 * float(self.smoothing_ms)  # "auto": at most 100 ms
        return t + smooth + 5e-3 * max(self.velocity_loop_ms.values(), default=0.0)

    def smoothing_s(self, q, machine: Machine, dt: float, traj=None) -> float:
        """The smoothing time (s): ``smoothing_ms``, or with "auto" the shortest that keeps every limited axis'
        acceleration at the feed moves' velocity steps within its limit: max over axes of max |dv| / a (the command's
        velocity steps between consecutive samples; rapids, planned apart, excluded when traj is given)."""
        if self.smoothing_ms != "auto":
            return float(self.smoothing_ms) * 1e-3
        v = np.diff(q, axis=0) / dt
        dv = np.abs(np.diff(v, axis=0))
        if traj is not None:
            feed = np.asarray(traj.motion) != 0
            dv = dv[feed[1:-1] | feed[2:]]
        t = 0.0
        for col, name in enumerate(machine.axis_names):
            a = self._accel_rad(machine, name)
            if a is not None and dv.size:
                t = max(t, float(dv[:, col].max()) / a)
        return math.ceil(t / dt - 1e-9) * dt

    def plan_rapids(self, q, machine: Machine, dt: float, traj):
        """Commanded axes with every rapid block re-profiled within the acceleration limits (see the class)."""
        names = machine.axis_names
        lim = np.array([self._accel_rad(machine, n) or np.inf for n in names])
        if not np.isfinite(lim).any() or traj is None or len(q) < 2:
            return q
        q = q.copy()
        row = np.asarray(traj.row)
        starts = np.r_[0, np.nonzero(np.diff(row))[0] + 1]
        # Last sample of each row: a rapid's command holds its end point there (the in-position hold; the sample at
        # the block end itself may belong to either row, as t = k dt meets the summed block times within rounding).
        ends = np.r_[starts[1:] - 1, len(row) - 1]
        for k0, k1 in zip(starts, ends):
            if traj.motion[k0] != 0 or k1 <= k0:
                continue
            d = q[k1] - q[k0]
            tol = 1e-12 * max(1.0, float(np.abs(q[k0 : k1 + 1]).max()))
            steps = int(np.count_nonzero(np.any(np.abs(np.diff(q[k0 : k1 + 1], axis=0)) > tol, axis=1)))
            if steps == 0:
                continue
            with np.errstate(divide="ignore"):
                amax = float(np.min(np.where(np.abs(d) > 0, lim / np.abs(d), np.inf)))  # path accel, 1/s^2
            if not np.isfinite(amax):
                continue
            vmax = 1.0 / (steps * dt)  # path speed, 1/s (the interpolator's)
            ta = vmax / amax
            if vmax * ta >= 1.0:  # triangular: never reaches vmax
                ta = math.sqrt(1.0 / amax)
                vmax = amax * ta
            tp = 1.0 / vmax + ta
            avail = (k1 - k0) * dt
            if tp > avail + 1e-9:
                raise ValueError(f"servo: the rapid on line {int(traj.line[k0]) + 1} needs {tp:.3f} s at the "
                                 f"acceleration limits but its block lasts {avail:.3f} s; raise rapid_settle_s to at "
                                 f"least {self.settle_time(machine):.3f} s")
            tau = np.arange(k1 - k0 + 1) * dt
            s = np.where(tau < ta, 0.5 * amax * tau**2,
                         np.where(tau < tp - ta, 0.5 * amax * ta**2 + vmax * (tau - ta),
                                  1.0 - 0.5 * amax * np.clip(tp - tau, 0.0, None) ** 2))
            s = np.clip(np.where(tau >= tp, 1.0, s), 0.0, 1.0)
            q[k0 : k1 + 1] = q[k0] + s[:, None] * d
        return q

    def apply(self, q, machine: Machine, dt: float, traj=None, info: dict | None = None):
        """Commanded axes (T, n) -> actual axes (T, n); traj: the ``Trajectory`` of q (row, motion, line), which
        lets the rapids be planned within the acceleration limits. ``info``: a dict that takes the smoothing used,
        ``servo_smoothing_ms`` ("auto" is the interpolator's choice for this program)."""
        q = self.plan_rapids(np.asarray(q, float), machine, dt, traj)
        smoothing = self.smoothing_s(q, machine, dt, traj)
        if info is not None:
            info["servo_smoothing_ms"] = 1e3 * smoothing
        q = smooth_command(q, smoothing, dt)
        out = q.copy()
        for col, name in enumerate(machine.axis_names):
            if name not in self.kv_per_s:
                continue
            kv, amax = float(self.kv_per_s[name]), self._accel_rad(machine, name)
            kff, aff = float(self.kff.get(name, 0.0)), float(self.aff.get(name, 0.0))
            tv = 1e-3 * float(self.velocity_loop_ms.get(name, 0.0))
            if kff == 0.0 and aff == 0.0 and tv == 0.0:
                out[:, col] = _servo_axis(q[:, col], kv, amax, dt)
            else:
                out[:, col] = servo_axis_ff(q[:, col], kv, dt, kff=kff, aff=aff, tv_s=tv, amax=amax)
        return out


def _servo_axis(qc, kv, amax, dt):
    alpha = kv * dt
    if not 0 < alpha < 1:
        raise ValueError(f"servo: Kv dt must be in (0, 1), got {alpha:g}")
    n = qc.shape[0]
    y = lfilter([alpha], [1.0, alpha - 1.0], qc, zi=[(1.0 - alpha) * qc[0]])[0]
    q = np.empty(n)
    q[0] = qc[0]
    q[1:] = y[:-1]
    if amax is None or n < 3:
        return q
    dv_max = amax * dt * (1 + 1e-9)
    decay_len = int(min(n, math.ceil(math.log(1e-18) / math.log(1 - alpha)) + 1))
    k = 1
    while True:
        v = kv * (qc[k - 1 :] - q[k - 1 :])
        viol = np.nonzero(np.abs(np.diff(v)) > dv_max)[0]
        if viol.size == 0:
            return q
        j = k + int(viol[0])  # v[j] - v[j-1] violates: step the saturated loop from sample j
        v_prev = kv * (qc[j - 1] - q[j - 1])
        qj = q[j]
        while j < n - 1:
            vc = kv * (qc[j] - qj)
            vj = min(max(vc, v_prev - amax * dt), v_prev + amax * dt)
            qj = qj + vj * dt
            q_lin_next = q[j + 1]
            j += 1
            q[j] = qj
            v_prev = vj
            if vj == vc:
                break
        if j >= n - 1:
            return q
        # The linear solution from here on, corrected by the decaying difference.
        delta = qj - q_lin_next
        m = min(decay_len, n - j)
        q[j + 1 : j + m] += delta * (1 - alpha) ** np.arange(1, m)
        k = j


def smooth_command(q, T: float, dt: float):
    """Acceleration/deceleration after interpolation, as CNCs bound the acceleration at block junctions: every axis'
    command (T_samples, n) is replaced by its causal moving average over M = round(T / dt) samples (all axes alike,
    so that a straight move stays on its line). A velocity step dv becomes a ramp of dv / (M dt) over M samples; a
    ramp lags by (M - 1) dt / 2; a corner is rounded. T = 0: unchanged. Before the first sample the command is taken
    at rest at its first value."""
    m = int(round(T / dt))
    if m <= 1:
        return q
    pad = np.concatenate([np.repeat(q[:1], m, axis=0), q])
    c = np.cumsum(pad, axis=0)
    return (c[m:] - c[:-m]) / m


@numba.njit(cache=True)
def _servo_ff_loop(qc, vff, aff_term, kv, beta, dv_max, dt):  # pragma: no cover - compiled
    n = qc.shape[0]
    q = np.empty(n)
    q[0] = qc[0]
    v = 0.0
    for k in range(n - 1):
        v_ref = kv * (qc[k] - q[k]) + vff[k] + aff_term[k]
        vn = v + beta * (v_ref - v)
        if vn > v + dv_max:
            vn = v + dv_max
        elif vn < v - dv_max:
            vn = v - dv_max
        v = vn
        q[k + 1] = q[k] + v * dt
    return q


def servo_axis_ff(qc, kv: float, dt: float, *, kff: float = 0.0, aff: float = 0.0, tv_s: float = 0.0,
                  amax: float | None = None):
    """One axis' position loop with velocity / acceleration feed-forward and a first-order velocity loop (see
    ``ServoLag``). qc : (T,) commanded positions (mm or rad) at period dt (s); amax : acceleration limit (mm/s^2 or
    rad/s^2; None = unlimited). Returns the actual positions (T,). Starts at rest on the command."""
    qc = np.ascontiguousarray(qc, dtype=float)
    if not 0 < kv * dt < 1:
        raise ValueError(f"servo: Kv dt must be in (0, 1), got {kv * dt:g}")
    if not (0.0 <= kff <= 1.0 and 0.0 <= aff <= 1.0 and tv_s >= 0.0):
        raise ValueError(f"servo: kff and aff must be in [0, 1] and the velocity loop's time >= 0 (got kff {kff:g}, "
                         f"aff {aff:g}, {tv_s * 1e3:g} ms)")
    beta = 1.0 if tv_s == 0.0 else -math.expm1(-dt / tv_s)
    # The unsaturated loop, states (q[k], v[k-1]), has the matrix [[1 - b Kv dt, (1 - b) dt], [-b Kv, 1 - b]]: its
    # determinant is 1 - b < 1 (complex poles inside the unit circle) and a real pole at -1 would need
    # b Kv dt > 4 - 2 b > 2, so Kv dt < 1 keeps it stable for every velocity loop.
    vc = np.zeros_like(qc)
    if qc.size > 1:
        vc[:-1] = np.diff(qc) / dt
    ac = np.diff(vc, prepend=0.0) / dt
    aff_term = aff * ac * dt * (1.0 - beta) / beta
    dv_max = np.inf if amax is None else float(amax) * dt
    return _servo_ff_loop(qc, kff * vc, aff_term, float(kv), float(beta), dv_max, float(dt))


@dataclass(frozen=True)
class Backlash:
    """Lost motion at direction reversals of one axis, taken up smoothly.

    amplitude : total lost motion b, um (linear) or urad (rotary).  transition : travel after a reversal over which it
    is taken up, mm or deg. Moving steadily in direction d the axis lags by b/2: e = -(b/2) d; after a reversal
    to d at travel s from the turning point, e = (b/2) d (1 - 2 f(s / transition)), with the take-up f:

    - ``form = "tanh"``: f = tanh (a gap closed with a soft start and end);
    - ``form = "friction"``: f = 1 - exp(-x), the first-order (Dahl) friction law dF/ds = k (1 - F sgn(v) / F_c)
      of a preloaded nut or a clamped rotary table's seal friction: steepest right at the reversal, then the
      elastic take-up creeps in (at s = transition 63 % taken up against tanh's 76 %, at 3 transitions 95 % against
      99.5 %).

    Works in the axis' own units: a rotary axis' b in urad and transition in deg (both turned into rad). Before the
    first motion the axis is taken as settled in its first direction. That law holds from a full take-up the other
    way; a run that starts part-taken-up (a reversal after a short travel) continues from its offset
    (``lost_motion_state``), so the play has memory.
    """

    axis: str
    amplitude: float
    transition: float = 0.01
    form: str = "tanh"

    def apply(self, q, machine: Machine):
        col = machine.axis_names.index(self.axis)
        rotary = machine.axes[self.axis].is_rotary
        b = self.amplitude * (URAD if rotary else UM)
        lam = math.radians(self.transition) if rotary else self.transition
        if self.form not in ("tanh", "friction"):
            raise ValueError(f"backlash {self.axis}: form must be 'tanh' or 'friction', got {self.form!r}")
        out = q.copy()
        out[:, col] += 0.5 * b * self.lost_motion_state(q[:, col], lam)
        return out

    def lost_motion_state(self, x, lam: float) -> np.ndarray:
        """(T,) the axis' offset from its command over b/2, in [-1, 1], along the commanded positions x (T,).

        A play with memory: in each run of one direction d (the direction of the step that brought the axis to the
        sample, held through stops) the offset approaches -d along the travel s from the run's start as
        d (1 - 2 f(s / transition + s0)), s0 = f^-1((1 - d e0) / 2) continuing from the offset e0 the run starts
        with. From a full take-up the other way (e0 = d) that is the law in the class docstring; a reversal of a few
        nanometres (a compensated program's rounding) moves the offset by as little, where a law that restarts
        at every reversal would throw it across the whole play. Before the first motion the axis is taken up in its
        first direction. The loop runs over the runs (reversals), each run in closed form."""
        x = np.asarray(x, float)
        n = x.shape[0]
        step = np.diff(x, prepend=x[:1])
        sgn = np.where(np.abs(step) > 1e-12, np.sign(step), 0.0)
        idx = np.arange(n)
        last = np.maximum.accumulate(np.where(sgn != 0, idx, 0))
        d = sgn[last]
        first = np.nonzero(sgn)[0]
        d = np.where(d == 0, sgn[first[0]] if first.size else 1.0, d)
        starts = np.concatenate([[0], np.nonzero(d[1:] != d[:-1])[0] + 1, [n]])
        f = np.tanh if self.form == "tanh" else (lambda v: -np.expm1(-v))
        finv = np.arctanh if self.form == "tanh" else (lambda y: -np.log1p(-y))
        e = np.empty(n)
        e[: starts[1]] = -d[0]  # taken up in the first direction
        for a, z in zip(starts[1:-1], starts[2:]):
            di = d[a]
            y0 = min(max(0.5 * (1.0 - di * e[a - 1]), 0.0), 1.0 - 1e-15)
            s = np.abs(x[a:z] - x[a - 1])
            e[a:z] = di * (1.0 - 2.0 * f((s / lam if lam > 0 else np.inf) + finv(y0)))
        return e


@dataclass(frozen=True)
class RotaryPeriodic:
    """Angular positioning error of a rotary axis as harmonics of its own angle theta (commanded), urad:
    e(theta) = sum_k c_k cos(k theta) + s_k sin(k theta); the axis turns to theta + e."""

    axis: str
    harmonics_urad: tuple

    def apply(self, q, machine: Machine):
        col = machine.axis_names.index(self.axis)
        theta = q[:, col]
        e = np.zeros_like(theta)
        for k, c, s in self.harmonics_urad:
            e += c * np.cos(k * theta) + s * np.sin(k * theta)
        out = q.copy()
        out[:, col] += e * URAD
        return out


#: ISO 230-7 error motions of a rotary axis about X / Y / Z: (radial 1, radial 2, axial, tilt 1, tilt 2, positioning)
ERROR_MOTION_NAMES = {"X": ("EYA", "EZA", "EXA", "EBA", "ECA", "EAA"), "Y": ("EXB", "EZB", "EYB", "EAB", "ECB", "EBB"),
                      "Z": ("EXC", "EYC", "EZC", "EAC", "EBC", "ECC")}


@dataclass(frozen=True)
class RotaryErrorMotion:
    """The ISO 230-7 error motions of one rotary axis, as the small transform of that axis in the kinematic chain.

    components : ISO name -> (harmonics, linear_per_turn). The names are E + error direction + axis letter
    (``ERROR_MOTION_NAMES``: for C radial EXC and EYC, axial EZC, tilt EAC and EBC, angular positioning ECC);
    directions X Y Z A B C are machine directions (translations along, rotations about X, Y, Z). Each component is

        e(theta) = sum_k c_k cos(k theta) + s_k sin(k theta) + linear_per_turn theta / (2 pi)   (- e(0))

    in um (translations) or urad (rotations), theta the axis' actual angle (rad); ``relative_to_zero`` subtracts
    e(0) so that the axis at zero carries no error (the machine files' convention for component tables; the rest of
    a constant error is a location error).

    Where it acts (DESIGN §3's relative chain T = P^-1 G_1 ... G_n, ``machine.kinematics``): the error transform
    E(x) = R_eps (x - c) + c + d (exact rotation by the vector eps about the axis' pivot c, then the translation d; in
    the frame of the body that carries the axis, M at zero) is inserted next to the axis' factor: after it on the
    workpiece branch (between the table and its carrier: G_C E G_B for a B-C table), before it on the tool branch
    (E G_B for a head), as the twin places its component errors. The tool pose T becomes A E A^-1 T, A the nominal
    chain up to that place. (The twin's own errors change A by a few urad: their product with this effect is of
    second order, < 0.01 um at 100 urad x 100 mm.) A radial error once per turn written as d = e (cos t, -sin t, 0) on
    C is an eccentric table: in the part frame a constant shift (a circle cut with C turning moves its centre by e).
    """

    axis: str
    components: tuple  # ((name, ((k, cos, sin), ...), linear_per_turn), ...)
    relative_to_zero: bool = True

    def values(self, theta):
        """(T, 3) translation d (mm) and (T, 3) rotation eps (rad), machine directions, at angles theta (T,)."""
        theta = np.asarray(theta, float)
        d = np.zeros((theta.size, 3))
        eps = np.zeros((theta.size, 3))
        for name, harmonics, slope in self.components:
            e = slope * theta / (2 * np.pi)
            for k, c, s_ in harmonics:
                e = e + c * np.cos(k * theta) + s_ * np.sin(k * theta)
                if self.relative_to_zero:
                    e = e - c
            letter = name[1]
            if letter in "XYZ":
                d[:, "XYZ".index(letter)] += e * UM
            else:
                eps[:, "ABC".index(letter)] += e * URAD
        return d, eps

    def apply_pose(self, tip, u, q, machine: Machine):
        """Tool tips (T,3) mm and unit axes (T,3) in the part frame moved by the error motion at axes q (T, n)."""
        links = chain_links(machine)
        k = next(i for i, lk in enumerate(links) if lk.axis == self.axis)
        upto = links[: k + 1] if links[k].branch == "workpiece" else links[:k]
        n = tip.shape[0]
        R = np.broadcast_to(np.eye(3), (n, 3, 3))
        t = np.broadcast_to(-machine.workpiece_origin, (n, 3))
        for lk in upto:
            (Rg, tg), _ = axis_motion(lk, q[:, lk.column])
            R, t = compose(R, t, Rg, tg)
        d, eps = self.values(q[:, links[k].column])
        ang = np.linalg.norm(eps, axis=1)
        axis_e = np.where(ang[:, None] > 0, eps / np.where(ang > 0, ang, 1.0)[:, None], np.array([0.0, 0.0, 1.0]))
        # Exact rotation by eps (Rodrigues, per sample: the axis of eps changes with theta).
        K = np.zeros((n, 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis_e[:, 2], axis_e[:, 1], -axis_e[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = axis_e[:, 2], -axis_e[:, 1], axis_e[:, 0]
        Re = np.eye(3) + np.sin(ang)[:, None, None] * K + (1 - np.cos(ang))[:, None, None] * (K @ K)
        c = links[k].pivot
        # Local coordinates x = A^-1 tip, then E, then back: tip' = A (R_eps (x - c) + c + d).
        x = np.einsum("nji,nj->ni", R, tip - t)
        x_new = np.einsum("nij,nj->ni", Re, x - c) + c + d
        tip_new = np.einsum("nij,nj->ni", R, x_new) + t
        u_loc = np.einsum("nji,nj->ni", R, u)
        u_new = np.einsum("nij,nj->ni", R, np.einsum("nij,nj->ni", Re, u_loc))
        return tip_new, u_new


# ------------------------------------------------------------------------------------------------- pose effects ----
@dataclass(frozen=True)
class ForceDeflection:
    """Machine compliance under the cutting force: tool relative to workpiece, d = C F (um, machine frame), turned
    into the part frame. ``use_machine_compliance`` also hands the force to the twin (its own [force] model)."""

    compliance_um_per_n: np.ndarray | None = None
    use_machine_compliance: bool = False


@dataclass(frozen=True)
class ToolDeflection:
    """The tool as a carbide cantilever (clamped at ``stick_out_mm`` above the tip), bent by the force component
    normal to its axis, applied at the centre of the flute contact (height z_c above the tip): with a = L - z_c from
    the clamp and EI = E pi (f d)^4 / 64, the tip moves by F (a^3 / 3 + a^2 (L - a) / 2) / EI and the axis tilts by
    F a^2 / (2 EI). Between the load and the tip the elastic line is straight, so the rigid tool tangent to it there
    (this tip and tilt) is exact below the load point; above it, the tangent tool is slightly outside the bent one.
    k at the tip for a = L: 3 EI / L^3 (5.7 N/um for d 10 mm, L 40 mm)."""

    stick_out_mm: float = 40.0
    youngs_modulus_gpa: float = 600.0
    diameter_factor: float = 0.8

    def displace(self, tip, axis, force_part, z_contact, diameter):
        """Deflected tip (N,3) and unit axis (N,3); force_part (N,3) N on the tool, part frame; z_contact (N,) mm."""
        E = self.youngs_modulus_gpa * 1e3  # N/mm^2
        I = math.pi * (self.diameter_factor * diameter) ** 4 / 64.0
        L = self.stick_out_mm
        a = np.clip(L - np.asarray(z_contact, float), 0.0, L)
        f_perp = force_part - np.einsum("ij,ij->i", force_part, axis)[:, None] * axis
        tip_c = (a**3 / 3.0 + a**2 * (L - a) / 2.0) / (E * I)
        slope_c = a**2 / (2.0 * E * I)
        new_tip = tip + tip_c[:, None] * f_perp
        new_axis = axis - slope_c[:, None] * f_perp
        return new_tip, new_axis / np.linalg.norm(new_axis, axis=1, keepdims=True)


@dataclass(frozen=True)
class ThermalDrift:
    """Drift of the tool relative to the table from a measured series (um), per machine direction X/Y/Z.

    The program clock t maps onto the series' time as time_offset_s + time_scale t (linear interpolation); the value
    is scaled by amplitude_scale and, with relative_to_start, taken relative to program time 0.
    """

    file: str
    channels: dict
    time_scale: float = 1.0
    time_offset_s: float = 0.0
    amplitude_scale: float = 1.0
    relative_to_start: bool = True

    def drift_um(self, t):
        """(T, 3) um, machine frame, at program times t (T,) s."""
        times, cols = _read_series(self.file)
        ts = self.time_offset_s + self.time_scale * np.asarray(t, float)
        if ts.min() < times[0] or ts.max() > times[-1]:
            raise ValueError(
                f"thermal: the program maps onto series time {ts.min():.0f}-{ts.max():.0f} s, outside the series "
                f"({times[0]:.0f}-{times[-1]:.0f} s); change time_scale or time_offset_s"
            )
        out = np.zeros((ts.size, 3))
        for direction, name in self.channels.items():
            if name not in cols:
                raise ValueError(f"thermal: no column {name!r} in {self.file} (has {', '.join(cols)})")
            v = np.interp(ts, times, cols[name])
            if self.relative_to_start:
                v = v - np.interp(self.time_offset_s, times, cols[name])
            out[:, "XYZ".index(direction)] = v * self.amplitude_scale
        return out


_SERIES_CACHE: dict = {}


def _series_problems(path, channels) -> list[str]:
    """What an effects file's thermal series cannot give, one line each (read here, not when the shop first asks: a
    file that is no series printed numpy's "setting an array element with a sequence", exit 2; a QA pass)."""
    try:
        _, cols = _read_series(path)
    except (OSError, UnicodeDecodeError, ValueError, IndexError) as exc:
        return [f"[thermal].file: {path} is not a time series (a CSV header with time_s and the channels, then rows "
                f"of numbers): {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"]
    out = []
    for d, name in (channels or {}).items() if isinstance(channels, dict) else ():
        if isinstance(name, str) and name not in cols:
            out.append(f"[thermal].channels.{d}: no column {name!r} in {path} (its columns: {', '.join(cols)})")
    return out


def _read_series(path):
    key = str(Path(path).resolve())
    if key not in _SERIES_CACHE:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.reader(line for line in fh if not line.startswith("#"))]
        header, data = rows[0], np.array(rows[1:], dtype=float)
        if "time_s" not in header:
            raise ValueError(f"thermal: {path} has no time_s column")
        cols = {h: data[:, i] for i, h in enumerate(header)}
        _SERIES_CACHE[key] = (cols.pop("time_s"), cols)
    return _SERIES_CACHE[key]


@dataclass(frozen=True)
class Clamping:
    """Clamping deformation of the part: while clamped, the material point x sits at x + d(x), with the smooth field
    d(x) = A e exp(-|x - c|^2 / (2 l^2)) (um, part frame). The cut made at y ends, after unclamping, at y - d(y):
    the shop applies it on the probe side (``shop.simulate``: the envelope taken at the shifted probe points)."""

    amplitude_um: float
    center: np.ndarray
    length_mm: float
    direction: np.ndarray

    def field(self, x):
        """Displacement (N,3) mm and gradient (N,3,3) at points x (N,3) mm."""
        r = x - self.center
        g = np.exp(-np.einsum("ij,ij->i", r, r) / (2 * self.length_mm**2))
        e = self.direction / np.linalg.norm(self.direction)
        d = self.amplitude_um * UM * g[:, None] * e
        grad = -self.amplitude_um * UM * (g / self.length_mm**2)[:, None, None] * e[None, :, None] * r[:, None, :]
        return d, grad


@dataclass(frozen=True)
class ClampingBend:
    """A part bent by its clamps and springing back when they are released (Euler-Bernoulli beam kinematics).

    While clamped, the part (a block held at two ends, pressed at its middle or, equally, by a uniform clamp load) is
    a simply supported beam along the unit direction ``beam`` between supports at xi = -span/2 and +span/2 about
    ``center`` (xi = (x - center) . beam), deflected along the unit ``direction`` (normal to beam) by the uniform-load
    elastic line normalised to the amplitude w0 at mid-span:

        w(xi) = w0 (16/5) (s - 2 s^3 + s^4),   s = xi / span + 1/2     (w = w0 at xi = 0, 0 at the supports)

    Plane sections stay plane and normal to the neutral plane (through ``center``, normal to ``direction``), so a
    material point at eta = (x - center) . direction from it also moves along the beam by -eta w'(xi):

        d(x) = w(xi) e_d - eta w'(xi) e_b          (um, part frame)

    The surface cut at y in the clamped state ends, after the part springs back, at y - d(y), applied on the probe
    side as for ``Clamping``. Outside the supports the polynomial is continued (it is smooth there).
    """

    amplitude_um: float
    center: np.ndarray
    span_mm: float
    beam: np.ndarray
    direction: np.ndarray

    def _w(self, xi):
        L = self.span_mm
        s = xi / L + 0.5
        w = (16.0 / 5.0) * (s - 2 * s**3 + s**4)
        dw = (16.0 / 5.0) * (1 - 6 * s**2 + 4 * s**3) / L
        ddw = (16.0 / 5.0) * (-12 * s + 12 * s**2) / L**2
        return w, dw, ddw

    def field(self, x):
        """Displacement (N,3) mm and gradient (N,3,3) (d_i / dx_j) at points x (N,3) mm."""
        eb = self.beam / np.linalg.norm(self.beam)
        ed = self.direction - (self.direction @ eb) * eb
        ed = ed / np.linalg.norm(ed)
        r = np.asarray(x, float) - self.center
        xi, eta = r @ eb, r @ ed
        w, dw, ddw = self._w(xi)
        a = self.amplitude_um * UM
        d = a * (w[:, None] * ed - (eta * dw)[:, None] * eb)
        grad = a * (dw[:, None, None] * ed[None, :, None] * eb[None, None, :]
                    - dw[:, None, None] * eb[None, :, None] * ed[None, None, :]
                    - (eta * ddw)[:, None, None] * eb[None, :, None] * eb[None, None, :])
        return d, grad


@dataclass(frozen=True)
class ToolWear:
    """The cutter wearing along its cut: flank wear VB grows with the cut path length, and the worn edge cuts a
    smaller radius (and, on the end face, a shorter tool).

    Flank wear over the cut path length l (mm of tool-tip path in the part frame while feeding, G1/G2/G3; rapids do
    not wear it), the usual three-stage curve's first two stages (initial run-in, then steady linear growth):

        VB(l) = vb_run_in_um (1 - exp(-l / run_in_mm)) + vb_rate_um_per_m l / 1000         (um)

    The worn flank land, at clearance angle alpha, moves the cutting edge inwards by VB tan(alpha) (radial wear,
    peripheral clearance ``clearance_deg``, typically 6-12 deg) and the end cutting edge upwards by VB tan(alpha_e)
    (``end_clearance_deg``; 0 = no length wear). The radius and the tip of every tool instance follow:
    R(l) = R0 - VB tan(alpha), tip(l) = tip + VB tan(alpha_e) u.
    """

    vb_run_in_um: float = 30.0
    run_in_mm: float = 200.0
    vb_rate_um_per_m: float = 10.0
    clearance_deg: float = 8.0
    end_clearance_deg: float = 0.0

    def flank_wear_um(self, path_mm):
        """VB (um) after a cut path of path_mm (mm)."""
        l = np.asarray(path_mm, float)
        return self.vb_run_in_um * -np.expm1(-l / self.run_in_mm) + self.vb_rate_um_per_m * l * 1e-3

    def losses_mm(self, path_mm):
        """(radius loss, length loss) in mm after path_mm of cut."""
        vb = self.flank_wear_um(path_mm) * UM
        return vb * math.tan(math.radians(self.clearance_deg)), vb * math.tan(math.radians(self.end_clearance_deg))

    @staticmethod
    def cut_path_mm(tip, feeding):
        """(T,) cumulative tool-tip path (mm) over feed samples: tip (T,3) part frame, feeding (T,) bool."""
        step = np.linalg.norm(np.diff(tip, axis=0), axis=1) * feeding[1:]
        return np.r_[0.0, np.cumsum(step)]


@dataclass(frozen=True)
class Effects:
    """The effects of one run; None = off."""

    servo: ServoLag | None = None
    backlash: tuple = ()
    rotary_periodic: tuple = ()
    force: ForceDeflection | None = None
    tool_deflection: ToolDeflection | None = None
    thermal: ThermalDrift | None = None
    clamping: Clamping | ClampingBend | None = None
    source: str = "<none>"
    rotary_error_motion: tuple = ()
    tool_wear: ToolWear | None = None

    @property
    def needs_force(self) -> bool:
        return self.force is not None or self.tool_deflection is not None

    def apply_axes(self, q, machine: Machine, dt: float, traj=None, info: dict | None = None):
        """Commanded axes (T, n) -> actual axes (T, n): servo lag, then backlash, then rotary harmonics.
        traj: the ``Trajectory`` of q (lets the servo plan the rapids within its acceleration limits); info: a dict
        that takes what the run chose (the servo's smoothing)."""
        out = np.asarray(q, float)
        if self.servo is not None:
            out = self.servo.apply(out, machine, dt, traj=traj, info=info)
        for b in self.backlash:
            out = b.apply(out, machine)
        for r in self.rotary_periodic:
            out = r.apply(out, machine)
        return out

    def as_dict(self) -> dict:
        """Plain description for reports and the CMM truth file."""
        import dataclasses

        def plain(x):
            if dataclasses.is_dataclass(x):
                return {f.name: plain(getattr(x, f.name)) for f in dataclasses.fields(x)}
            if isinstance(x, np.ndarray):
                return x.tolist()
            if isinstance(x, (tuple, list)):
                return [plain(v) for v in x]
            if isinstance(x, dict):
                return {k: plain(v) for k, v in x.items()}
            return x

        return plain(self)


# ----------------------------------------------------------------------------------------------------- the file ----
_ALLOWED = {
    "servo": {"kv_per_s", "accel", "kff", "aff", "velocity_loop_ms", "smoothing_ms", "enabled"},
    "force": {"compliance_um_per_n", "use_machine_compliance", "enabled"},
    "tool_deflection": {"stick_out_mm", "youngs_modulus_gpa", "diameter_factor", "enabled"},
    "thermal": {"file", "channels", "time_scale", "time_offset_s", "amplitude_scale", "relative_to_start", "enabled"},
    "clamping": {"form", "amplitude_um", "center", "length_mm", "direction", "span_mm", "beam", "enabled"},
    "tool_wear": {"vb_run_in_um", "run_in_mm", "vb_rate_um_per_m", "clearance_deg", "end_clearance_deg", "enabled"},
}
_PER_AXIS = {"backlash": {"amplitude", "transition", "form", "enabled"}, "rotary_periodic": {"harmonics_urad", "enabled"},
             "rotary_error_motion": {"relative_to_zero", "enabled"}}  # plus the ISO component names, checked below


def load_effects(path, machine: Machine | None = None) -> Effects:
    """Read an EFFECTS.toml (see the module docstring); raise EffectsFileError listing every problem.

    machine : when given, axis names are checked against it (and backlash/harmonics of rotary axes).
    """
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise EffectsFileError(f"{path}: file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise EffectsFileError(f"{path}: not valid TOML: {exc}") from None
    return parse_effects(data, source=str(path), base=path.parent, machine=machine)


def parse_effects(data: dict, source: str = "<dict>", base=None, machine: Machine | None = None) -> Effects:
    """Effects from the parsed TOML tables (see ``load_effects``)."""
    problems: list[str] = []
    base = Path(base) if base is not None else Path.cwd()
    axes = machine.axis_names if machine is not None else tuple("XYZABC")

    def num(where, v, positive=False, nonneg=False):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            problems.append(f"{where}: expected a finite number, got {v!r}")
            return None
        if positive and not v > 0:
            problems.append(f"{where}: must be > 0, got {v!r}")
            return None
        if nonneg and v < 0:
            problems.append(f"{where}: must be >= 0, got {v!r}")
            return None
        return float(v)

    def vec3(where, v):
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            a = None
        if a is None or a.shape != (3,) or not np.all(np.isfinite(a)):
            problems.append(f"{where}: expected 3 numbers, got {v!r}")
            return None
        return a

    def boolean(where, v):
        if not isinstance(v, bool):
            problems.append(f"{where}: expected true or false, got {v!r}")
            return False
        return v

    def enabled(where, table):
        return boolean(f"{where}.enabled", table.get("enabled", True))

    for key in data:
        if key not in _ALLOWED and key not in _PER_AXIS:
            problems.append(f"[{key}]: unknown table (known: {', '.join(sorted([*_ALLOWED, *_PER_AXIS]))})")
    for key, allowed in _ALLOWED.items():
        table = data.get(key)
        if table is None:
            continue
        if not isinstance(table, dict):
            problems.append(f"[{key}]: expected a table")
            continue
        for k in table:
            if k not in allowed:
                problems.append(f"[{key}].{k}: unknown key (known: {', '.join(sorted(allowed))})")

    servo = force = tool = thermal = clamping = tool_wear = None
    t = data.get("servo")
    if isinstance(t, dict) and enabled("[servo]", t):
        kv, acc, kff, aff, tv = {}, {}, {}, {}, {}
        for name, out, kwargs in (("kv_per_s", kv, {"positive": True}), ("accel", acc, {"positive": True}),
                                  ("kff", kff, {"nonneg": True}), ("aff", aff, {"nonneg": True}),
                                  ("velocity_loop_ms", tv, {"nonneg": True})):
            table = t.get(name, {})
            if not isinstance(table, dict):
                problems.append(f"[servo].{name}: expected a table axis = value")
                continue
            for ax, v in table.items():
                if ax not in axes:
                    problems.append(f"[servo].{name}.{ax}: unknown axis (machine axes: {' '.join(axes)})")
                out[ax] = num(f"[servo].{name}.{ax}", v, **kwargs)
                if name == "kv_per_s" and out[ax] is not None and out[ax] * PERIOD_S >= 1.0:
                    # (the loop is stepped at the interpolation period: numpy's "Kv dt must be in (0, 1), got 2",
                    # exit 2, named neither the file nor the key; a QA pass)
                    problems.append(f"[servo].kv_per_s.{ax}: a position loop's gain must be below "
                                    f"{1.0 / PERIOD_S:g} /s (the shop's {PERIOD_S * 1e3:g} ms period), got {v!r}")
                if name in ("kff", "aff") and out[ax] is not None and out[ax] > 1.0:
                    problems.append(f"[servo].{name}.{ax}: a feed-forward gain is at most 1, got {v!r}")
        if "kv_per_s" not in t:
            problems.append("[servo].kv_per_s: required")
        for name, table in (("kff", kff), ("aff", aff), ("velocity_loop_ms", tv)):
            for ax in table:
                if ax not in kv:
                    problems.append(f"[servo].{name}.{ax}: {ax} has no kv_per_s (no loop to feed forward into)")
        sm = t.get("smoothing_ms", 0.0)
        if sm != "auto":
            sm = num("[servo].smoothing_ms", sm, nonneg=True) or 0.0
        elif not acc:
            problems.append('[servo].smoothing_ms = "auto" needs acceleration limits (accel)')
        servo = ServoLag(kv, acc, kff, aff, tv, sm)
    t = data.get("force")
    if isinstance(t, dict) and enabled("[force]", t):
        c = None
        if "compliance_um_per_n" in t:
            try:
                c = np.asarray(t["compliance_um_per_n"], dtype=float)
            except (TypeError, ValueError):
                c = None
            if c is None or c.shape != (3, 3) or not np.all(np.isfinite(c)):
                problems.append("[force].compliance_um_per_n: expected a 3x3 matrix of numbers (um/N)")
                c = None
        use = boolean("[force].use_machine_compliance", t.get("use_machine_compliance", False))
        if c is None and not use:
            problems.append("[force]: give compliance_um_per_n or use_machine_compliance = true")
        force = ForceDeflection(c, use)
    t = data.get("tool_deflection")
    if isinstance(t, dict) and enabled("[tool_deflection]", t):
        kw = {k: num(f"[tool_deflection].{k}", t[k], positive=True) for k in t if k != "enabled"}
        tool = ToolDeflection(**{k: v for k, v in kw.items() if v is not None})
    t = data.get("thermal")
    if isinstance(t, dict) and enabled("[thermal]", t):
        f = t.get("file")
        if not isinstance(f, str):
            problems.append("[thermal].file: required, a path to the series CSV")
        else:
            fp = Path(f) if Path(f).is_absolute() else base / f
            if not fp.exists():
                problems.append(f"[thermal].file: {fp} does not exist")
            else:
                problems += _series_problems(fp, t.get("channels"))
            f = str(fp)
        ch = t.get("channels")
        if not isinstance(ch, dict) or not ch:
            problems.append("[thermal].channels: required, a table direction = column, e.g. { Z = \"ch3_um\" }")
            ch = {}
        for d, name in ch.items():
            if d not in ("X", "Y", "Z"):
                problems.append(f"[thermal].channels.{d}: directions are X, Y, Z")
            if not isinstance(name, str):
                problems.append(f"[thermal].channels.{d}: expected a column name")
        kw = {}
        for k in ("time_scale", "time_offset_s", "amplitude_scale"):
            if k in t:
                kw[k] = num(f"[thermal].{k}", t[k], positive=(k == "time_scale"), nonneg=(k == "time_offset_s"))
        if "relative_to_start" in t:
            kw["relative_to_start"] = boolean("[thermal].relative_to_start", t["relative_to_start"])
        thermal = ThermalDrift(f if isinstance(f, str) else "", dict(ch), **{k: v for k, v in kw.items() if v is not None})
    t = data.get("tool_wear")
    if isinstance(t, dict) and enabled("[tool_wear]", t):
        kw = {k: num(f"[tool_wear].{k}", t[k], positive=k == "run_in_mm", nonneg=k != "run_in_mm")
              for k in t if k != "enabled"}
        for k in ("clearance_deg", "end_clearance_deg"):
            if kw.get(k) is not None and kw[k] >= 45.0:
                problems.append(f"[tool_wear].{k}: a clearance angle is below 45 deg, got {kw[k]:g}")
        tool_wear = ToolWear(**{k: v for k, v in kw.items() if v is not None})
    t = data.get("clamping")
    form = t.get("form", "bump") if isinstance(t, dict) else None
    if isinstance(t, dict) and form not in ("bump", "bending"):
        problems.append(f"[clamping].form: 'bump' or 'bending', got {form!r}")
    elif isinstance(t, dict) and form == "bending" and enabled("[clamping]", t):
        keys = ("amplitude_um", "center", "span_mm", "beam", "direction")
        missing = [k for k in keys if k not in t]
        extra = [k for k in ("length_mm",) if k in t]
        if missing or extra:
            problems.append(f"[clamping] (bending): missing {', '.join(missing) or '-'}; not used: {', '.join(extra) or '-'}")
        else:
            a = num("[clamping].amplitude_um", t["amplitude_um"])
            c = vec3("[clamping].center", t["center"])
            sp = num("[clamping].span_mm", t["span_mm"], positive=True)
            b = vec3("[clamping].beam", t["beam"])
            d = vec3("[clamping].direction", t["direction"])
            if b is not None and d is not None:
                nb, nd = np.linalg.norm(b), np.linalg.norm(d)
                if nb == 0 or nd == 0 or np.linalg.norm(np.cross(b / nb, d / nd)) < 0.5:
                    problems.append("[clamping]: beam and direction must be non-zero and far from parallel")
                elif None not in (a, sp) and c is not None:
                    clamping = ClampingBend(a, c, sp, b / nb, d / nd)
    elif isinstance(t, dict) and enabled("[clamping]", t):
        missing = [k for k in ("amplitude_um", "center", "length_mm", "direction") if k not in t]
        extra = [k for k in ("span_mm", "beam") if k in t]
        if missing or extra:
            problems.append(f"[clamping]: missing {', '.join(missing) or '-'}; not used: {', '.join(extra) or '-'}")
        else:
            a = num("[clamping].amplitude_um", t["amplitude_um"])
            c = vec3("[clamping].center", t["center"])
            ln = num("[clamping].length_mm", t["length_mm"], positive=True)
            d = vec3("[clamping].direction", t["direction"])
            if d is not None and np.linalg.norm(d) == 0:
                problems.append("[clamping].direction: must not be zero")
            if None not in (a, ln) and c is not None and d is not None:
                clamping = Clamping(a, c, ln, d)

    backlash, periodic, motions = [], [], []
    for key, allowed in _PER_AXIS.items():
        table = data.get(key)
        if table is None:
            continue
        if not isinstance(table, dict):
            problems.append(f"[{key}]: expected tables [{key}.AXIS]")
            continue
        for ax, sub in table.items():
            where = f"[{key}.{ax}]"
            if ax not in axes:
                problems.append(f"{where}: unknown axis (machine axes: {' '.join(axes)})")
                continue
            if not isinstance(sub, dict):
                problems.append(f"{where}: expected a table")
                continue
            iso = ()
            if key == "rotary_error_motion":
                about = machine.axes[ax].about if machine is not None and machine.axes[ax].is_rotary else None
                if machine is not None and about is None:
                    problems.append(f"{where}: {ax} is not a rotary axis")
                    continue
                iso = tuple(f"E{d}{ax}" for d in "XYZABC")
            for k in sub:
                if k not in allowed and k not in iso:
                    problems.append(f"{where}.{k}: unknown key (known: {', '.join(sorted([*allowed, *iso]))})")
            if not enabled(where, sub):
                continue
            if key == "backlash":
                if "amplitude" not in sub:
                    problems.append(f"{where}.amplitude: required (um or urad)")
                    continue
                amp = num(f"{where}.amplitude", sub["amplitude"], nonneg=True)
                tr = num(f"{where}.transition", sub.get("transition", 0.01), positive=True)
                form = sub.get("form", "tanh")
                if form not in ("tanh", "friction"):
                    problems.append(f"{where}.form: 'tanh' or 'friction', got {form!r}")
                elif amp is not None and tr is not None:
                    backlash.append(Backlash(ax, amp, tr, form))
            elif key == "rotary_error_motion":
                comps = []
                for name in iso:
                    if name not in sub:
                        continue
                    c = sub[name]
                    cw = f"{where}.{name}"
                    if not isinstance(c, dict) or set(c) - {"harmonics", "linear_per_turn"}:
                        problems.append(f"{cw}: expected {{ harmonics = [[k, cos, sin], ...], linear_per_turn = x }}")
                        continue
                    rows = []
                    for i, row in enumerate(c.get("harmonics", [])):
                        if (not isinstance(row, list) or len(row) != 3 or not all(
                                isinstance(v, (int, float)) and not isinstance(v, bool) for v in row)
                                or int(row[0]) != row[0] or row[0] < 1):
                            problems.append(f"{cw}.harmonics[{i}]: expected [k >= 1 integer, cos, sin]")
                        else:
                            rows.append((int(row[0]), float(row[1]), float(row[2])))
                    slope = num(f"{cw}.linear_per_turn", c.get("linear_per_turn", 0.0))
                    if slope is not None:
                        comps.append((name, tuple(rows), slope))
                if not comps:
                    problems.append(f"{where}: give at least one of {', '.join(iso)}")
                else:
                    rel = boolean(f"{where}.relative_to_zero", sub.get("relative_to_zero", True))
                    motions.append(RotaryErrorMotion(ax, tuple(comps), rel))
            else:
                if machine is not None and not machine.axes[ax].is_rotary:
                    problems.append(f"{where}: {ax} is not a rotary axis")
                h = sub.get("harmonics_urad")
                ok = isinstance(h, list) and len(h) > 0
                rows = []
                if ok:
                    for i, row in enumerate(h):
                        if (not isinstance(row, list) or len(row) != 3 or not all(
                                isinstance(v, (int, float)) and not isinstance(v, bool) for v in row)
                                or int(row[0]) != row[0] or row[0] < 1):
                            problems.append(f"{where}.harmonics_urad[{i}]: expected [k >= 1 integer, cos, sin]")
                        else:
                            rows.append((int(row[0]), float(row[1]), float(row[2])))
                else:
                    problems.append(f"{where}.harmonics_urad: required, a list of [k, cos, sin]")
                if rows:
                    periodic.append(RotaryPeriodic(ax, tuple(rows)))
    if problems:
        raise EffectsFileError(f"{source}:\n  " + "\n  ".join(problems))
    return Effects(servo, tuple(backlash), tuple(periodic), force, tool, thermal, clamping, source=source,
                   rotary_error_motion=tuple(motions), tool_wear=tool_wear)
