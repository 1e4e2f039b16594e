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

- ``backlash_<axis>`` (every axis, rotary ones in urad): e = (b/2) d (1 - 2 tanh(s / lambda)) at the cut sample,
  d the direction of motion, s the travel since the last reversal, lambda from a grid (``REVERSAL_TRANSITIONS``,
  0 = a step) chosen by the fit. The shop takes the lost motion up (tanh or exponential friction form) on the
  servo-lagged axes, and the envelope picks the deepest cut of any tool instance.
- ``servo_lag``: per axis j a lag L_j = sum_m c_jm (ms) over first-order filters of the commanded velocity (time
  constants 4, 12, 35 ms, ``state.LAG_TAUS_S``), c_jm >= 0: a loop of gain kv and velocity feed-forward ff follows
  with e = -(1 - ff) (1/kv) w_{1/kv}, so the weights carry (1 - ff)/kv on the filter nearest 1/kv. Two variants of
  the same parameters (see ``servo_lag``): small lags (feed-forward) to first order at the twin's cut sample, large
  lags (plain loops) at the lagged tool's deepest cut. The shop steps a discrete loop per axis with its own gain,
  feed-forward, acceleration limits and planned rapids; the candidate has no limits.
- ``force_deflection``: a diagonal machine-frame compliance (c_X, c_Y >= 0 and an axial c_Z whose sign is free, as
  it also takes up the X/Y-Z coupling of a real matrix), times the force the twin's simulation estimated at the cut
  sample. The shop uses a full 3x3 matrix (and/or the machine's own force model) with the force recomputed on the
  deflected path at every sample.
- ``tool_deflection``: a straight lever, deflection = F_perp (c0 + c1 h) at contact height h, c0 >= 0: isotropic in
  the plane normal to the tool (a round tool). The shop bends a carbide cantilever (cubic in the load position, load
  at the centre of the engaged flute) and tilts the tool.
- ``thermal_<k>``: drift along one machine direction, D (1 - exp(-t/tau)) / (1 - exp(-T/tau)), tau from a grid
  of multiples of the program's duration T (infinite: linear); ``thermal_spline_<k>``: a linear spline of time
  through zero at the start, knots at T/3, 2T/3 and T. The shop interpolates a measured thermal series. With
  several cuts (``state.combine_states``) t runs on over them, T is their total, and each part sees the drift
  since its own set-up (the shape minus its value at the part's datum).
- ``rotary_<motion>_<axis>``: the ISO 230-7 error motions, radial (two directions normal to the axis), axial, tilt
  (about the two directions normal to it) and angular positioning, each component E<dir><axis> as harmonics 1-4 of
  the commanded angle, zero at angle 0, plus a term linear in the angle on an axis of limited travel (only that term
  on a short arc of a tilting axis, where harmonics cannot be told from a slope), through the
  twin's exact parameter Jacobian of a constant component error. The shop applies its error motions (any
  harmonics, a linear term per turn) as a transform at the axis, at the axis' actual angle.
- ``twin_parameters``: re-identification of the twin's own location errors (``machine.location_names()``) through
  the exact parameter Jacobian (``ErrorTwin.parameter_jacobian``) projected on the normals, so that a wrong value in
  the machine file is not mistaken for a missing effect; only the location errors this part resolves
  (``resolved_columns``: of offsets that move the surface alike, one parameter here, the one that reaches furthest
  within its bound). Component tables are left out (too many columns for one part; the identification command
  handles them).
- ``setup_translation``: the whole part displaced (TX, TY, TZ um, one set per part): its set-up or the CMM's
  alignment, not the machine. The shop has no such effect; it is a rival of the machine's effects that move the
  surface alike, so that a translation is not blamed on the machine. Its form is exact (``analysis.EXACT_FORM``).

Parameter units are given per parameter in ``Candidate.units``; values stay in those units throughout the reports.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ..machine import ErrorTwin
from .state import REVERSAL_TRANSITIONS, TwinState

#: Amplitudes (um for a linear axis, urad for a rotary one) at which the deepest cut with the play is read on a pass
#: boundary (it is not linear in b there); the fit takes the one that suits the training points best.
REVERSAL_AMPLITUDES_UM = (2.0, 5.0, 10.0, 20.0, 40.0)
REVERSAL_AMPLITUDES_URAD = (5.0, 15.0, 50.0, 150.0, 400.0)

AXIS_LETTERS = "XYZ"


@dataclass(frozen=True)
class Derived:
    """A derived parameter, in ``unit``: the sum of the parameters ``index``, less the mean over the groups
    ``minus_mean_of`` of each group's sum (a servo axis' lag less the mean lag of the axes). ``determined`` False:
    the part cannot tell its value (reported as read, and said to be undetermined); ``note`` says what it is or why."""

    name: str
    unit: str
    index: tuple
    minus_mean_of: tuple = ()
    determined: bool = True
    note: str = ""

    def vector(self, p: int, offset: int = 0) -> np.ndarray:
        """(p,) its weights over the fit's p parameters, this candidate's starting at ``offset``."""
        w = np.zeros(p)
        w[[offset + i for i in self.index]] = 1.0
        for group in self.minus_mean_of:
            w[[offset + i for i in group]] -= 1.0 / len(self.minus_mean_of)
        return w

    def reindexed(self, new: dict) -> "Derived":
        """The same over the parameters kept (``new``: old index -> new index); a group with none kept leaves the
        mean."""
        groups = tuple(g for g in (tuple(new[i] for i in g if i in new) for g in self.minus_mean_of) if g)
        return dataclasses.replace(self, index=tuple(new[i] for i in self.index if i in new), minus_mean_of=groups)


@dataclass
class Candidate:
    """One candidate effect evaluated at N points.

    name : library name.  columns : (N, p) sensitivity, um per parameter unit.  parameters : p names.
    units : p unit strings.  plausible : p (low, high) bounds of a physically plausible value (None = any).
    describe : one-line physical description.  form : per parameter, True when its bounds are the candidate's form
    (see ``form_bound``).  variants : [(label, (N, p) columns)]: alternative shapes of the same parameters (a
    non-linear shape parameter on a grid: backlash's transition length, thermal's time constant); the fit picks
    the one that fits the training points best, fold by fold (``columns`` is the first until then).
    derived : [Derived]: weighted sums of parameters reported with their own std (a servo axis' lag over its
    filters, and that lag less the axes' mean).
    """

    name: str
    columns: np.ndarray
    parameters: list
    units: list
    plausible: list = field(default_factory=list)
    describe: str = ""
    form: list = field(default_factory=list)
    variants: list = field(default_factory=list)
    derived: list = field(default_factory=list)

    def with_variant(self, i: int) -> "Candidate":
        """The candidate with its columns set to variant i (a copy; the variants stay listed)."""
        return dataclasses.replace(self, columns=self.variants[i][1])

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


def _angle_scale(state: TwinState, axis: str) -> float:
    """The candidates' unit of an axis error in the axis' own unit: 1e-3 mm per um (linear), 1e-6 rad per urad
    (rotary); times 1e3 for um of deviation."""
    return 1e-3 if axis in state.rotary else 1.0


def backlash(state: TwinState, axis: str) -> Candidate | None:
    if axis not in state.axis_names:
        return None
    j = state.axis_names.index(axis)
    rotary = axis in state.rotary
    resp = _axis_response(state, axis) * _angle_scale(state, axis)  # um per um (urad) of the axis
    d = state.direction[:, j]
    if not np.any(d):
        return None
    unit = "urad" if rotary else "um"
    bound = 500.0 if rotary else 60.0
    variants = []
    lm, depth = state.lost_motion, state.lost_motion_depth
    # Points a second pass cuts within TIED_CUT_UM of the twin's cut, with another play there: the deepest cut with
    # the play, which is not linear in b (read near each amplitude of the grid); elsewhere the play at the twin's cut.
    boundary = np.nonzero(np.any(np.isfinite(depth[:, 1:]) & (
        np.abs(lm[:, 1:, j, :] - lm[:, :1, j, :]).max(axis=2) > 1e-9), axis=1))[0]
    amps = REVERSAL_AMPLITUDES_URAD if rotary else REVERSAL_AMPLITUDES_UM
    # The transitions are the state's (``REVERSAL_TRANSITIONS``: its lost motion is read for each): the one that fits
    # the training points best is used (``Candidate.variants``, chosen fold by fold).
    for li, lam in enumerate(REVERSAL_TRANSITIONS):
        # e = (b/2) e_hat: -(b/2) d once taken up, +(b/2) d at the turning point after a full take-up the other way,
        # a play with memory in between (``TwinState.lost_motion``).
        label = f"transition {lam:g} {'deg' if rotary else 'mm'}"
        col = 0.5 * lm[:, 0, j, li] * resp
        if boundary.size == 0:
            variants.append((label, col[:, None]))
            continue
        per_cut = 0.5 * lm[boundary][:, :, j, li] * resp[boundary, None]  # (B, C) um per um (urad) of b
        for b in amps:
            c = col.copy()
            c[boundary] = np.min(depth[boundary] + b * per_cut, axis=1) / b
            variants.append((f"{label}, near {b:g} {unit}", c[:, None]))
    # A lost motion is positive (the axis lags its command): a fit that needs b < 0 is not a backlash.
    return Candidate(f"backlash_{axis.lower()}", variants[0][1], [f"lost_motion_{axis}"], [unit], [(0.0, bound)],
                     f"reversal error (lost motion) of {axis}: b/2 against the direction of motion, taken up over a "
                     f"transition travel after each reversal", variants=variants)


#: The share of an axis' own column a lag common to every axis must move the surface by to be taken as seen.
COMMON_LAG_SEEN = 0.1


def common_lag_share(columns: np.ndarray, per_axis: list) -> float:
    """How far the part sees a lag common to every axis: for each filter m, the rms of the sum over the axes of
    their columns through m (um per ms of one lag on every axis), over the largest rms of one axis' column; the
    largest over the filters. ``per_axis``: each axis' column indices, one per filter, in the filters' order."""
    share = 0.0
    for m in range(min(len(idx) for idx in per_axis)):
        cols = columns[:, [idx[m] for idx in per_axis]]
        own = np.sqrt(np.mean(cols**2, axis=0)).max()
        share = max(share, float(np.sqrt(np.mean(cols.sum(axis=1) ** 2)) / max(own, 1e-300)))
    return share


def servo_lag(state: TwinState) -> Candidate | None:
    """Per-axis following error: each axis' lag L_j (ms) as a positive mixture over the filters' time constants
    (the loop's 1/kv); L_j = (1 - ff_j) / kv_j with velocity feed-forward ff_j. Two variants of the same
    parameters, chosen by the fit:

    - "feed-forward": the lag is small (a few ms), the loop's tool is the twin's moved by e_j = -L_j w_j, to first
      order at the twin's cut sample: column (j, m) = -(n . M_j) w_jm;
    - "plain loops": the lag is the loop's time constant (no feed-forward, 6-60 ms), large enough for the lagged
      tool to cut a point at another sample than the twin's (the inside of a corner): the deviation at the lagged
      cut (``state.lagged_cut``), per axis to first order (``lag_axis``) plus the envelope's remainder
      (``lag_deviation`` minus the axes' sum) shared among the axes in proportion to their part, so that equal lags
      on every axis give the whole loop's deviation exactly."""
    if state.lag_velocity is None or not len(state.lag_taus_s):
        return None
    taus_ms = 1e3 * np.asarray(state.lag_taus_s, float)
    cut_cols, lag_cols, names, derived, per_axis = [], [], [], [], []
    la = state.lag_axis
    if la is not None:
        remainder = state.lag_deviation - la.sum(axis=1)  # (N, M)
        weight = np.abs(la) / np.maximum(np.abs(la).sum(axis=1, keepdims=True), 1e-300)
    for j, a in enumerate(state.axis_names):
        resp = _axis_response(state, a)  # mm per mm (rad)
        w = state.lag_velocity[:, j, :]  # mm/s (rad/s) through each loop's filter
        if not np.any(w):
            continue
        first = len(names)
        for m, t in enumerate(taus_ms):
            # Following error e = -L w (L ms of lag): deviation -resp w L 1e-3 mm = -resp w L um.
            cut_cols.append(-resp * w[:, m])
            if la is not None:
                lag_cols.append(la[:, j, m] + weight[:, j, m] * remainder[:, m])
            names.append(f"lag_{a}_{t:.0f}ms")
        per_axis.append((a, list(range(first, len(names)))))
    if not names:
        return None
    # On a smooth path a delay common to every axis leaves the tool on its path (the envelope: the tool's velocity is
    # tangent to the surface it cuts), so the part sees it only through second-order terms whose form the candidate
    # does not match (an interpolator's smoothing of 14 ms changed a cone by 0.14 um rms of a 10 um servo effect,
    # where the candidate's columns would move it by 1-2 um). Where the common delay's column stays below
    # ``COMMON_LAG_SEEN`` of an axis' own (``common_lag_share``; the cones 0.02-0.03, corners far more), each axis'
    # lag is reported as read and said to be undetermined, and its difference from the axes' mean lag, which the part
    # does see, is the estimate (the harness' servo cases on cones: the differences within a few hundredths of a ms
    # of the truth, the lags themselves off by up to 25 ms).
    variants = [("feed-forward (small lag, at the cut)", np.column_stack(cut_cols))]
    if lag_cols:
        variants.append(("plain loops (lag = time constant, at the lagged cut)", np.column_stack(lag_cols)))
    seen = max(common_lag_share(v, [idx for _, idx in per_axis]) for _, v in variants) >= COMMON_LAG_SEEN
    for a, idx in per_axis:
        derived.append(Derived(f"lag_{a}", "ms", tuple(idx), determined=seen,
                               note="" if seen else "a delay common to every axis is not seen on this part"))
    groups = tuple(tuple(idx) for _, idx in per_axis)
    for a, idx in per_axis:
        derived.append(Derived(f"lag_{a}_rel", "ms", tuple(idx), groups,
                               note="the axis' lag less the mean lag of the moving axes"))
    return Candidate("servo_lag", variants[0][1], names, ["ms"] * len(names), [(0.0, 100.0)] * len(names),
                     "following error of each axis' position loop: per axis a positive mixture of first-order loops "
                     "(time constant 1/kv), weight = lag left after velocity feed-forward, (1 - ff) / kv, ms; the "
                     "axis' lag is the sum of its weights",
                     form=[True] * len(names), variants=variants, derived=derived)


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


#: Time constants of the constrained thermal candidate, as multiples of the program's duration T (inf: a drift
#: linear in time, the start of a slow response).
THERMAL_TAUS_OF_T = (0.15, 0.4, 1.0, 3.0, math.inf)


def _drift_shapes(state: TwinState, since_part_start: bool = False) -> list:
    """[(label, (N,) shape)]: the monotone first-order responses (1 - exp(-t/tau)) / (1 - exp(-T/tau)) of the
    running time t (tau from ``THERMAL_TAUS_OF_T`` times the duration T; infinite: t / T), seen from each row's part
    datum (zero at the program start for one cut; for several cuts each part's drift since its own set-up), or, with
    ``since_part_start``, of the time since each part's start alone (a fresh start of what grows with the cut)."""
    T = max(state.t_end_s, 1e-9)

    def f(t, fac):
        return t / T if math.isinf(fac) else -np.expm1(-t / (fac * T)) / -math.expm1(-1.0 / fac)

    out = []
    for fac in THERMAL_TAUS_OF_T:
        if since_part_start:
            shape = f(state.since_datum_s(), fac)
        else:
            shape = f(state.t_s, fac) - (0.0 if state.t_datum_s is None else f(state.t_datum_s, fac))
        out.append((f"time constant {'inf' if math.isinf(fac) else f'{fac:g} T'}", shape))
    return out


def thermal(state: TwinState, k: int) -> Candidate:
    """Constrained thermal drift along machine direction k: a monotone first-order response to the spindle's running
    time, d(t) = D (1 - exp(-t/tau)) / (1 - exp(-T/tau)) (D: the drift at the program's end, um), zero at the start.
    A spindle already warm when the program starts gives the same form (a later stretch of the same exponential)."""
    letter = AXIS_LETTERS[k]
    proj = np.einsum("ij,ij->i", state.normals, _machine_direction(state, k))
    variants = [(label, (proj * shape)[:, None]) for label, shape in _drift_shapes(state)]
    return Candidate(f"thermal_{letter.lower()}", variants[0][1], [f"drift_{letter}_at_end"], ["um"],
                     [(-200.0, 200.0)],
                     f"thermal drift along machine {letter}: monotone first-order response to the spindle's running "
                     f"time, zero at the program start", variants=variants)


def uniform_wear(state: TwinState) -> Candidate:
    """Not a library candidate: the shadow of an effect outside the library, a cutter losing radius as it cuts
    (tool wear): the surface moves out along its own normal by a monotone first-order (run-in) or linear amount of
    the cut time. A verdict whose fit this form matches as well is not a verdict the part can support on its own
    (see ``analysis.diagnose_state``)."""
    variants = [(label, shape[:, None]) for label, shape in _drift_shapes(state, since_part_start=True)]
    return Candidate("uniform normal offset growing with the cut (tool wear, outside the library)", variants[0][1],
                     ["offset_at_end"], ["um"], [(-200.0, 200.0)], "tool wear-like shadow", variants=variants)


def thermal_spline(state: TwinState, k: int, knots: int = 3) -> Candidate:
    letter = AXIS_LETTERS[k]
    T = max(state.t_end_s, 1e-9)
    at = T * np.arange(1, knots + 1) / knots
    # Hat functions of a linear spline through 0 at the program start: parameter m is the drift at time at[m].
    grid = np.r_[0.0, at]

    def hats_at(t):
        return np.column_stack([np.interp(t, grid, np.eye(knots + 1)[m + 1]) for m in range(knots)])

    hats = hats_at(state.t_s)
    if state.t_datum_s is not None:  # several cuts: each part's drift since its own set-up
        hats -= hats_at(state.t_datum_s)
    proj = np.einsum("ij,ij->i", state.normals, _machine_direction(state, k))
    return Candidate(f"thermal_spline_{letter.lower()}", proj[:, None] * hats,
                     [f"drift_{letter}_at_{t:.0f}s" for t in at], ["um"] * knots, [(-200.0, 200.0)] * knots,
                     f"thermal drift along machine {letter}, flexible: linear spline of time, zero at the program "
                     f"start (chosen only when it beats the constrained form on held-out points by a margin)")


#: ISO 230-7 error motions of a rotary axis, by the component errors E<direction><axis> they are made of: radial
#: (the two directions normal to the axis), axial (along it), tilt (about the two directions normal to it) and
#: angular positioning (about the axis itself).
ERROR_MOTIONS = ("radial", "axial", "tilt", "angular")
HARMONICS = (1, 2, 3, 4)
#: An axis turning less than SHORT_ARC_DEG while cutting has its error motions as a slope in the angle only (an axis
#: of limited travel), none below MIN_ARC_DEG (a constant there: a location error).
SHORT_ARC_DEG = 30.0
MIN_ARC_DEG = 2.0


def _motion_components(state: TwinState, axis: str, motion: str) -> list[str]:
    about = state.machine.axes[axis].about
    normal = [d for d in "XYZ" if d != about]
    rot = {"X": "A", "Y": "B", "Z": "C"}
    dirs = {"radial": normal, "axial": [about], "tilt": [rot[d] for d in normal], "angular": [rot[about]]}[motion]
    return [f"E{d}{axis}" for d in dirs]


def _component_response(state: TwinState, axis: str) -> np.ndarray:
    """(N, 6) deviation (um) per um / urad of each constant component error E<X..C><axis> at the cut, through the
    twin's exact parameter Jacobian (a probe copy of the twin whose only component functions are constants of this
    axis), projected on the normals at the contact height."""
    key = ("component_response", axis)
    if key in state.memo:
        return state.memo[key]
    from ..machine.error_functions import legendre_series
    from ..machine.model import ERROR_DIRECTIONS, ErrorSet

    comps = {f"E{d}{axis}": legendre_series([0.0], (-1e3, 1e3)) for d in ERROR_DIRECTIONS}
    J = np.empty((len(state), 6, len(ERROR_DIRECTIONS)))
    for rows, m in state.placements():  # each cut with its twin as placed
        probe = dataclasses.replace(m, errors=ErrorSet(location=dict(m.errors.location), components={axis: comps}),
                                    loaded=None, loaded_force_n=None)
        names = probe.parameter_names()
        idx = [names.index(f"E{d}{axis}.P0") for d in ERROR_DIRECTIONS]
        J[rows] = ErrorTwin(probe).parameter_jacobian(state.q[rows])[:, :, idx]
    out = np.einsum("ij,ijk->ik", state.normals, J[:, :3] + 1e-3 * state.height_mm[:, None, None] * J[:, 3:])
    state.memo[key] = out
    return out


def rotary_error_motion(state: TwinState, axis: str, motion: str) -> Candidate | None:
    """ISO 230-7 error motion ``motion`` of rotary ``axis``: each of its components as harmonics 1..4 per turn of
    the commanded angle, plus a term linear in the angle (um or urad per rad) on an axis of limited travel (only that
    term where the axis turns less than ``SHORT_ARC_DEG`` while cutting: a tilting axis on a short arc). Each
    term is zero at the axis' zero angle (a_k (cos k theta - 1) + b_k sin k theta): a constant part of a component
    error is a location error, which ``twin_parameters`` holds."""
    if axis not in state.rotary:
        return None
    j = state.axis_names.index(axis)
    theta = state.q[:, j]
    # The term linear in the angle only for an axis of limited travel (a tilting axis): a continuous rotary axis'
    # error motion repeats every turn, and over the one turn of a pass a linear term is a drift in time, which the
    # thermal candidates describe.
    limited = state.machine.axes[axis].travel is not None
    short = np.ptp(theta) < np.radians(SHORT_ARC_DEG)
    if short and not limited:
        return None  # the axis hardly turns while cutting: no harmonic can be told from an offset
    if short and np.ptp(theta) < np.radians(MIN_ARC_DEG):
        return None  # not even a slope: the error motion is a constant here, a location error (twin_parameters)
    from ..machine.model import ERROR_DIRECTIONS

    R = _component_response(state, axis)
    cols, names, units, bounds = [], [], [], []
    for comp in _motion_components(state, axis, motion):
        r = R[:, ERROR_DIRECTIONS.index(comp[1])]
        angular = comp[1] in "ABC"
        u = "urad" if angular else "um"
        b = 300.0 if angular else 30.0
        # On a short arc (a tilting axis that moves a few degrees while cutting) harmonics cannot be told from a
        # polynomial of the angle: the error motion is its slope there (zero at angle 0, so not a location error).
        for k in () if short else HARMONICS:
            cols += [r * (np.cos(k * theta) - 1.0), r * np.sin(k * theta)]
            names += [f"{comp}_{k}cos", f"{comp}_{k}sin"]
            units += [u, u]
            bounds += [(-b, b), (-b, b)]
        if limited:
            cols.append(r * theta)
            names.append(f"{comp}_per_rad")
            units.append(f"{u}/rad")
            bounds.append((-b, b))
    label = {"radial": "radial error motion", "axial": "axial error motion", "tilt": "tilt error motion",
             "angular": "angular positioning error motion"}[motion]
    return Candidate(f"rotary_{motion}_{axis.lower()}", np.column_stack(cols), names, units, bounds,
                     f"ISO 230-7 {label} of {axis} ({', '.join(_motion_components(state, axis, motion))}): "
                     f"harmonics 1-4 per turn plus a term linear in the angle")


#: Share of its own size a twin location error's column must keep independent of the columns kept (``resolved_columns``)
#: to be re-identified.
TWIN_RESOLVED = 0.1
# A re-mounted table or a collision moves location errors by a few hundred um / urad, not by millimetres.
TWIN_SPAN = 300.0


def resolved_columns(cols: np.ndarray, seen: np.ndarray, span: float) -> np.ndarray:
    """Indices of the columns ``cols`` (N, k; um per unit of each parameter) among ``seen`` that a fit can tell
    apart on these points, chosen greedily: at each step, of the columns whose part independent of the ones kept is
    at least ``TWIN_RESOLVED`` of their own size, the one whose independent part moves the surface most at its
    plausible bound (``span`` units); until no column is left with an independent part that large.

    (Until 2026-11-28 a column-pivoted QR of the columns scaled to one size chose among a group of columns that move
    the surface alike the one with the largest independent share, whatever it could reach: a 10 um change of the C
    line's Y offset was taken up by a tilt of the B line, which needed 253 urad and another parameter at its bound,
    and the fit was set aside as not plausible.)"""
    idx = np.nonzero(seen)[0]
    size = np.linalg.norm(cols[:, idx], axis=0)
    resid = cols[:, idx] / size  # unit columns, made independent of the kept ones step by step (Gram-Schmidt)
    reach = size * span
    keep, free = [], np.ones(idx.size, bool)
    while True:
        share = np.linalg.norm(resid, axis=0)
        ok = free & (share >= TWIN_RESOLVED)
        if not ok.any():
            break
        j = int(np.argmax(np.where(ok, share * reach, -np.inf)))
        keep.append(idx[j])
        free[j] = False
        u = resid[:, j] / share[j]
        resid = resid - np.outer(u, u @ resid)
    return np.sort(np.asarray(keep, int))


def twin_parameters(state: TwinState, min_norm_um: float = 1e-3) -> Candidate | None:
    names = state.machine.location_names()
    if not names:
        return None
    Jp = np.empty((len(state), 6, len(names)))
    for rows, m in state.placements():  # each cut with its twin as placed; one set of location errors for all
        Jp[rows] = ErrorTwin(m).parameter_jacobian(state.q[rows])[:, :, : len(names)]
    # Tool-axis error (urad) turns the contact at height h (mm) by h * 1e-3 um per urad.
    cols = np.einsum("ij,ijk->ik", state.normals, Jp[:, :3] + 1e-3 * state.height_mm[:, None, None] * Jp[:, 3:])
    seen = np.sqrt(np.mean(cols**2, axis=0)) > min_norm_um
    if not np.any(seen):
        return None
    # Only the location errors this part resolves (two offsets that move the surface alike on this part, say an
    # offset of C's line and a tilt of B's, are one parameter here; the kept one takes up both), and of each group
    # of such the one that can take it up within its plausible bound: ``resolved_columns``.
    keep = resolved_columns(cols, seen, TWIN_SPAN)
    seen = np.zeros_like(seen)
    seen[keep] = True
    kept = [n for n, s in zip(names, seen) if s]
    from ..machine.model import unit_of

    units = [unit_of(n) for n in kept]
    return Candidate("twin_parameters", cols[:, seen], [f"d{n}" for n in kept], units,
                     [(-TWIN_SPAN, TWIN_SPAN)] * len(kept),
                     "changes of the twin's own location errors (re-identification), not a new effect")


#: um, the largest set-up displacement of a part taken as plausible (the inspection refuses a cloud further off)
SETUP_SPAN = 500.0


def setup_translation(state: TwinState) -> Candidate:
    """The whole part displaced by (TX, TY, TZ) um in the part frame: its set-up (the work offset's probing, the
    clamping) or the CMM's alignment, not an effect of the machine. The inspection takes any translation as the
    part's set-up (``inspect --identify``); here it is a rival of the machine's effects that move the surface alike
    (the twin's location errors on a cone cut about the C axis), so that a part measured 10 um off is not blamed on
    the machine (it was, at confidence 1.00: a QA pass). With several parts, a translation each (each its own
    set-up)."""
    pieces = [np.ones(len(state), bool)] if state.piece is None else [state.piece == k for k in
                                                                      range(int(state.piece.max()) + 1)]
    cols = np.zeros((len(state), 3 * len(pieces)))
    names = []
    for k, rows in enumerate(pieces):
        cols[rows, 3 * k : 3 * k + 3] = state.normals[rows]
        names += [f"T{a}" + (f"_part{k + 1}" if len(pieces) > 1 else "") for a in "XYZ"]
    return Candidate("setup_translation", cols, names, ["um"] * len(names), [(-SETUP_SPAN, SETUP_SPAN)] * len(names),
                     "the whole part displaced: its set-up on the machine or the CMM's alignment, not the machine")


LIBRARY = ("backlash_x", "backlash_y", "backlash_z", "backlash_a", "backlash_b", "backlash_c", "servo_lag",
           "force_deflection", "tool_deflection", "thermal_x", "thermal_y", "thermal_z",
           "thermal_spline_x", "thermal_spline_y", "thermal_spline_z",
           *(f"rotary_{m}_{a}" for a in "abc" for m in ERROR_MOTIONS), "twin_parameters", "setup_translation")


def build(name: str, state: TwinState) -> Candidate | None:
    """The candidate ``name`` (one of ``LIBRARY``) at the state's points; None when it does not apply to this
    machine / program (no such axis, the axis does not turn, no force estimate)."""
    if name not in LIBRARY:
        raise ValueError(f"unknown candidate {name!r} (known: {', '.join(LIBRARY)})")
    if name.startswith("backlash_"):
        return backlash(state, name[-1].upper())
    if name.startswith("thermal_spline_"):
        return thermal_spline(state, AXIS_LETTERS.index(name[-1].upper()))
    if name.startswith("thermal_"):
        return thermal(state, AXIS_LETTERS.index(name[-1].upper()))
    if name.startswith("rotary_"):
        _, motion, a = name.split("_")
        return rotary_error_motion(state, a.upper(), motion)
    fn = {"servo_lag": servo_lag, "force_deflection": force_deflection, "tool_deflection": tool_deflection,
          "twin_parameters": twin_parameters, "setup_translation": setup_translation}[name]
    return fn(state)


def visible(c: Candidate, min_um: float = 0.5) -> Candidate | None:
    """The candidate with only the parameters that can change the deviation by more than ``min_um`` (rms) within
    their plausible bounds; None when none can (the effect cannot be seen on this part and program)."""
    span = np.array([max(abs(b[0]), abs(b[1])) for b in c.plausible])
    sets = [v for _, v in c.variants] if c.variants else [c.columns]
    reach = np.max([np.sqrt(np.mean(v**2, axis=0)) for v in sets], axis=0) * span
    keep = np.isfinite(reach) & (reach > min_um)
    if not np.any(keep):
        return None
    idx = np.nonzero(keep)[0]
    new = {int(i): k for k, i in enumerate(idx)}
    derived = [d.reindexed(new) for d in c.derived]
    return Candidate(c.name, c.columns[:, idx], [c.parameters[i] for i in idx], [c.units[i] for i in idx],
                     [c.plausible[i] for i in idx], c.describe, [c.form_bound(i) for i in idx],
                     [(lab, v[:, idx]) for lab, v in c.variants], [d for d in derived if d.index])


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
