"""The library of candidate effects: parametric additions to the twin, linear in their parameters.

Each candidate turns the twin-simulated machine state at N measured points (``state.TwinState``) into a sensitivity
matrix S (N, p): the change of the deviation along the normal (um) per unit of each parameter, so that the candidate
predicts ``gap_um ~ S @ theta``. All are first-order perturbations of the tool pose at the moment the point was cut,
projected on the probe normal at the contact height h above the tool tip:

    d(deviation) = n . (dp + h du)          dp, du: tip and tool-axis change in the part frame

An axis error dq_j enters through the twin's axis Jacobian, dp + h du = (J_p[:, j] + h J_u[:, j]) dq_j; a
displacement along machine direction k enters through the part-frame direction of linear axis k (its Jacobian
column), which is the machine-to-part rotation applied to e_k.

How they differ from the virtual shop's effects (``trueaxis.sim.effects``; DESIGN §8 -- written independently, and
deliberately poorer, so that a fit is a test and not an identity):

- ``backlash_x/y/z``: a pure step, -(b/2) sign(velocity) (the last direction while the axis stands), applied at the
  cut sample. The shop takes the lost motion up smoothly (tanh over a transition travel) after every reversal, on the
  servo-lagged axes, and the envelope picks the deepest cut of any tool instance.
- ``servo_lag``: the following error of a first-order position loop per axis, e_j = -tau_j (h_tau_j * v_j), v_j the
  commanded axis velocity, h_tau(t) = exp(-t/tau)/tau (unit DC gain), tau_j = 1/Kv_j the lag time. It is not only the
  steady lag v/Kv (along the path on a straight wall, invisible with equal gains) but its transient, which is what a
  real loop leaves on the part: the inside of every corner (ln2 sin(theta/2) v/Kv for a turn by theta), the stops.
  Linear in its parameters: the shared loop is a positive mixture of loops with fixed lag times tau_m (4, 12, 35 ms,
  ``state.LAG_TAUS_S``), weights c_m >= 0 in ms, so that the response's DC gain, the lag time, is sum_m c_m (a loop of
  lag tau_m is c_m = tau_m exactly; one in between is bracketed by its neighbours); and a gain mismatch, each further
  moving axis' lag time minus the first one's (d_j ms, first order, on the 12 ms loop), which is what a contour shows
  at steady speed. 3 + (moving axes - 1) parameters rather than a mixture per axis (3 per axis): the corner transient
  is shared by the axes when their gains are alike, the mismatch is a steady effect, and fewer columns keep the
  held-out fit honest and the candidate from mimicking others. Each loop is evaluated where its lagged tool cuts the
  point (``state.lagged_cut``): the loop's tool is the twin's tool tau earlier plus a small transient, so the twin's
  own instances, shifted in time and moved by the transient to first order, give the envelope. The shop steps a
  discrete loop per axis with its own gain, acceleration limits (saturation at corners when Kv |dv| > a) and rapids
  planned within them; the candidate has no limits, no rapids (taken as settled), one shared dynamics and a
  first-order mismatch.
- ``force_deflection``: a diagonal machine-frame compliance (c_X, c_Y >= 0 and an axial c_Z whose sign is free, as
  it also takes up the X/Y-Z coupling of a real matrix), times the force the twin's simulation estimated at the cut
  sample. The shop uses a full 3x3 matrix (and/or the machine's own force model) with the force recomputed on the
  deflected path at every sample.
- ``tool_deflection``: a straight lever, deflection = F_perp (c0 + c1 h) at contact height h, c0 >= 0: isotropic in
  the plane normal to the tool (a round tool). The shop bends a carbide cantilever (cubic in the load position, load
  at the centre of the engaged flute) and tilts the tool.
- ``thermal_x/y/z``: drift along one machine direction as a linear spline of program time through zero at the start,
  knots at T/3, 2T/3 and T (the parameters are the drift there, um). The shop interpolates a measured thermal series.
- ``rotary_periodic_c/_b/_a``: once- and twice-per-turn harmonics of the commanded angle, as a first-order axis
  error through the Jacobian. The shop may hold any harmonic and applies it before the full kinematics.
- ``twin_parameters``: re-identification of the twin's own location errors (``machine.location_names()``) through
  the exact parameter Jacobian (``ErrorTwin.parameter_jacobian``) projected on the normals, so that a wrong value in
  the machine file is not mistaken for a missing effect. Component tables are left out (too many columns for one
  part; the identification command handles them).

Parameter units are given per parameter in ``Candidate.units``; values stay in those units throughout the reports.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..machine import ErrorTwin
from .state import TwinState

AXIS_LETTERS = "XYZ"


@dataclass
class Candidate:
    """One candidate effect evaluated at N points.

    name : library name.  columns : (N, p) sensitivity, um per parameter unit.  parameters : p names.
    units : p unit strings.  plausible : p (low, high) bounds of a physically plausible value (None = any).
    describe : one-line physical description.
    """

    name: str
    columns: np.ndarray
    parameters: list
    units: list
    plausible: list = field(default_factory=list)
    describe: str = ""
    form: list = field(default_factory=list)

    def form_bound(self, i: int) -> bool:
        """True when parameter i's bounds are a constraint of the candidate's form (the weights of a positive
        mixture), not a physical plausibility: a free fit outside them only says that the mixture's columns are
        nearly collinear, and the fit is judged plausible on the bounded values."""
        return bool(self.form and self.form[i])

    @property
    def n_parameters(self) -> int:
        return int(self.columns.shape[1])


def _axis_response(state: TwinState, axis: str) -> np.ndarray:
    """(N,) n . (J_p + h J_u)[:, axis]: deviation change (mm) per mm / rad of the axis at the cut."""
    j = state.axis_names.index(axis)
    J = state.axis_jacobian[:, :, j]
    return np.einsum("ij,ij->i", state.normals, J[:, :3] + state.height_mm[:, None] * J[:, 3:])


def _machine_direction(state: TwinState, k: int) -> np.ndarray:
    """(N, 3) part-frame unit direction of machine direction k (0 X, 1 Y, 2 Z) at each cut."""
    letter = AXIS_LETTERS[k]
    if letter in state.axis_names:
        d = state.axis_jacobian[:, :3, state.axis_names.index(letter)]
        return d / np.linalg.norm(d, axis=1, keepdims=True)
    return np.tile(np.eye(3)[k], (len(state), 1))


def backlash(state: TwinState, axis: str) -> Candidate | None:
    if axis not in state.axis_names:
        return None
    j = state.axis_names.index(axis)
    col = -0.5 * state.direction[:, j] * _axis_response(state, axis)  # um per um of lost motion
    return Candidate(f"backlash_{axis.lower()}", col[:, None], [f"lost_motion_{axis}"], ["um"], [(-60.0, 60.0)],
                     f"lost motion of {axis} at reversals: a step of b/2 against the direction of motion")


def servo_lag(state: TwinState) -> Candidate | None:
    if state.lag_deviation is None or not len(state.lag_taus_s):
        return None
    taus_ms = 1e3 * np.asarray(state.lag_taus_s, float)
    mid = len(taus_ms) // 2
    ax = state.lag_axis
    moving = [j for j in range(len(state.axis_names)) if np.ptp(ax[:, j, :]) > 1e-9 or abs(ax[0, j, 0]) > 1e-9]
    if not moving:
        return None  # no axis' lag moves the surface: no lag can be seen
    # The loop shared by all axes, a positive mixture of first-order loops of lag tau_m: the deviation of loop m per
    # ms of lag (c_m = tau_m gives loop m exactly; the lag time is sum c_m).
    cols = [state.lag_deviation[:, m] for m in range(len(taus_ms))]
    names = [f"lag_{t:.0f}ms" for t in taus_ms]
    bounds = [(0.0, 100.0)] * len(taus_ms)
    # A gain mismatch, to first order: each further moving axis' lag time minus the first one's, d_j, on the middle
    # filter (the first moving axis is the reference: a common change of all lag times is the shared loop's).
    cols += [ax[:, j, mid] for j in moving[1:]]
    names += [f"lag_mismatch_{state.axis_names[j]}" for j in moving[1:]]
    bounds += [(-30.0, 30.0)] * (len(moving) - 1)
    return Candidate("servo_lag", np.column_stack(cols), names, ["ms"] * len(names), bounds,
                     "following error of the position loops (first order, lag time 1000 / kv ms): a positive mixture "
                     "of first-order loops shared by all axes, plus each axis' mismatch of lag time",
                     form=[True] * len(taus_ms) + [False] * (len(names) - len(taus_ms)))


def force_deflection(state: TwinState) -> Candidate | None:
    if not state.has_force:
        return None
    cols = []
    for k in range(3):
        e = _machine_direction(state, k)
        cols.append(np.einsum("ij,ij->i", state.normals, e) * np.einsum("ij,ij->i", state.force_n, e))  # um per um/N
    # A compliance matrix is positive semi-definite: its diagonal terms are >= 0 (the tool yields along the force).
    # The axial term also takes up the X/Y-Z coupling of a real matrix (on a floor, c_zx F_x can outweigh c_zz F_z),
    # so its sign is left free.
    return Candidate("force_deflection", np.column_stack(cols),
                     ["compliance_X", "compliance_Y", "compliance_Z"], ["um/N"] * 3,
                     [(0.0, 0.5), (0.0, 0.5), (-0.5, 0.5)],
                     "machine compliance (diagonal in the machine frame, X, Y and Z apart) times the estimated "
                     "cutting force")


def tool_deflection(state: TwinState) -> Candidate | None:
    if not state.has_force:
        return None
    F, u = state.force_n, state.axis
    f_perp = F - np.einsum("ij,ij->i", F, u)[:, None] * u
    c0 = np.einsum("ij,ij->i", state.normals, f_perp)
    return Candidate("tool_deflection", np.column_stack([c0, c0 * state.height_mm]),
                     ["tip_compliance", "compliance_slope"], ["um/N", "um/N/mm"], [(0.0, 0.5), (-0.05, 0.05)],
                     "tool bending: force normal to the tool times a compliance linear in the contact height")


def thermal(state: TwinState, k: int, knots: int = 3) -> Candidate:
    letter = AXIS_LETTERS[k]
    T = max(state.t_end_s, 1e-9)
    at = T * np.arange(1, knots + 1) / knots
    # Hat functions of a linear spline through 0 at the program start: parameter m is the drift at time at[m].
    grid = np.r_[0.0, at]
    hats = np.column_stack([np.interp(state.t_s, grid, np.eye(knots + 1)[m + 1]) for m in range(knots)])
    proj = np.einsum("ij,ij->i", state.normals, _machine_direction(state, k))
    return Candidate(f"thermal_{letter.lower()}", proj[:, None] * hats,
                     [f"drift_{letter}_at_{t:.0f}s" for t in at], ["um"] * knots, [(-200.0, 200.0)] * knots,
                     f"thermal drift along machine {letter}: linear spline of time, zero at the program start")


def rotary_periodic(state: TwinState, axis: str) -> Candidate | None:
    if axis not in state.rotary:
        return None
    j = state.axis_names.index(axis)
    theta = state.q[:, j]
    if np.ptp(theta) < np.radians(30.0):
        return None  # the axis hardly turns while cutting: no harmonic can be told from an offset
    r = _axis_response(state, axis) * 1e-3  # um per urad
    cols = np.column_stack([r * f(k * theta) for k in (1, 2) for f in (np.cos, np.sin)])
    names = [f"{axis}_{k}{w}" for k in (1, 2) for w in ("cos", "sin")]
    return Candidate(f"rotary_periodic_{axis.lower()}", cols, names, ["urad"] * 4, [(-300.0, 300.0)] * 4,
                     f"angular positioning error of {axis}: once- and twice-per-turn harmonics of its angle")


def twin_parameters(state: TwinState, min_norm_um: float = 1e-3) -> Candidate | None:
    machine = state.machine
    names = machine.location_names()
    if not names:
        return None
    Jp = ErrorTwin(machine).parameter_jacobian(state.q)[:, :, : len(names)]
    # Tool-axis error (urad) turns the contact at height h (mm) by h * 1e-3 um per urad.
    cols = np.einsum("ij,ijk->ik", state.normals, Jp[:, :3] + 1e-3 * state.height_mm[:, None, None] * Jp[:, 3:])
    seen = np.sqrt(np.mean(cols**2, axis=0)) > min_norm_um
    if not np.any(seen):
        return None
    kept = [n for n, s in zip(names, seen) if s]
    from ..machine.model import unit_of

    units = [unit_of(n) for n in kept]
    return Candidate("twin_parameters", cols[:, seen], [f"d{n}" for n in kept], units, [(-100.0, 100.0)] * len(kept),
                     "changes of the twin's own location errors (re-identification), not a new effect")


LIBRARY = ("backlash_x", "backlash_y", "backlash_z", "servo_lag", "force_deflection", "tool_deflection",
           "thermal_x", "thermal_y", "thermal_z", "rotary_periodic_c", "rotary_periodic_b", "rotary_periodic_a",
           "twin_parameters")


def build(name: str, state: TwinState) -> Candidate | None:
    """The candidate ``name`` (one of ``LIBRARY``) at the state's points; None when it does not apply to this
    machine / program (no such axis, the axis does not turn, no force estimate)."""
    if name.startswith("backlash_"):
        return backlash(state, name[-1].upper())
    if name.startswith("thermal_"):
        return thermal(state, AXIS_LETTERS.index(name[-1].upper()))
    if name.startswith("rotary_periodic_"):
        return rotary_periodic(state, name[-1].upper())
    fn = {"servo_lag": servo_lag, "force_deflection": force_deflection, "tool_deflection": tool_deflection,
          "twin_parameters": twin_parameters}.get(name)
    if fn is None:
        raise ValueError(f"unknown candidate {name!r} (known: {', '.join(LIBRARY)})")
    return fn(state)


def visible(c: Candidate, min_um: float = 0.5) -> Candidate | None:
    """The candidate with only the parameters that can change the deviation by more than ``min_um`` (rms) within
    their plausible bounds; None when none can (the effect cannot be seen on this part and program)."""
    reach = np.sqrt(np.mean(c.columns**2, axis=0)) * np.array([max(abs(b[0]), abs(b[1])) for b in c.plausible])
    keep = np.isfinite(reach) & (reach > min_um)
    if not np.any(keep):
        return None
    idx = np.nonzero(keep)[0]
    return Candidate(c.name, c.columns[:, idx], [c.parameters[i] for i in idx], [c.units[i] for i in idx],
                     [c.plausible[i] for i in idx], c.describe, [c.form_bound(i) for i in idx])


def build_all(names, state: TwinState) -> tuple[list[Candidate], list[str]]:
    """(candidates that apply, names that do not apply here: no such axis, no force estimate, or an effect that
    cannot move the surface on this part and program, see ``visible``)."""
    out, skipped = [], []
    for n in names:
        c = build(n, state)
        c = None if c is None or not np.all(np.isfinite(c.columns)) else visible(c)
        if c is None:
            skipped.append(n)
        else:
            out.append(c)
    return out, skipped
