"""The virtual shop's physical effects against analytic expectations: servo loops with feed-forward, rotary backlash,
rotary-axis error motions in the chain, clamping spring-back by bending, tool wear."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from conftest import DATA, MACHINES
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.machine.kinematics import forward_nominal
from trueaxis.sim.effects import (Backlash, ClampingBend, EffectsFileError, RotaryErrorMotion, RotaryPeriodic,
                                  ToolWear, _servo_axis, parse_effects, servo_axis_ff)
from trueaxis.sim.programs import boss_probe, square_boss_program
from trueaxis.sim.shop import simulate

DT = 1e-3


def perfect(machine):
    return machine.with_parameters(np.zeros(len(machine.parameter_names())))


@pytest.fixture(scope="module")
def bc():
    return load_machine(DATA / "bc_table.toml")


@pytest.fixture(scope="module")
def xh714():
    return load_machine(MACHINES / "xh714.toml")


# ------------------------------------------------------------------------------------------------------- servo ----
@pytest.mark.parametrize("kv, kff, tv_ms", [(25.0, 0.9, 0.0), (45.0, 0.9, 3.0), (33.0, 0.5, 6.0), (40.0, 0.0, 2.0)])
def test_ramp_lags_by_v_one_minus_kff_over_kv(kv, kff, tv_ms):
    v = 12.0  # mm/s
    qc = np.arange(4000) * DT * v
    q = servo_axis_ff(qc, kv, DT, kff=kff, tv_s=tv_ms * 1e-3)
    lag = qc[-2] - q[-2]  # the last sample is the command's stop
    assert lag == pytest.approx(v * (1 - kff) / kv, rel=1e-9, abs=1e-12)


def test_without_feed_forward_the_loop_is_the_plain_saturating_loop():
    t = np.arange(3000) * DT
    qc = np.where(t < 0.5, 0.0, (t - 0.5) * 50.0) + 3 * np.sin(20 * t) * (t > 1.5)
    np.testing.assert_allclose(servo_axis_ff(qc, 30.0, DT, amax=500.0), _servo_axis(qc, 30.0, 500.0, DT), atol=1e-8)


def test_acceleration_feed_forward_cancels_the_velocity_loops_lag():
    # Constant acceleration a with full velocity feed-forward: the first-order velocity loop lags a dt (1-b)/b per
    # sample (b = 1 - exp(-dt/Tv)), which the position loop turns into e = a dt (1-b) / (b Kv) (-> Tv a / Kv);
    # acceleration feed-forward 1 removes it.
    a, kv, tv = 400.0, 30.0, 4e-3
    t = np.arange(1500) * DT
    qc = 0.5 * a * t**2
    b = -math.expm1(-DT / tv)
    e_expected = a * DT * (1 - b) / (b * kv)
    e0 = qc[-2] - servo_axis_ff(qc, kv, DT, kff=1.0, tv_s=tv)[-2]
    e1 = qc[-2] - servo_axis_ff(qc, kv, DT, kff=1.0, aff=1.0, tv_s=tv)[-2]
    assert e0 == pytest.approx(e_expected, rel=1e-6)
    assert e0 == pytest.approx(tv * a / kv, rel=0.15)  # the continuous-time figure, to the discretisation
    assert abs(e1) < 1e-9 * a


def test_servo_refuses_impossible_loops():
    qc = np.zeros(10)
    with pytest.raises(ValueError, match="Kv dt"):
        servo_axis_ff(qc, 1500.0, DT, kff=0.5)
    with pytest.raises(ValueError, match="kff"):
        servo_axis_ff(qc, 30.0, DT, kff=1.5)


def test_rotary_axis_loop_from_the_effects_file_lags_in_radians(bc):
    eff = parse_effects({"servo": {"kv_per_s": {"C": 35.0, "X": 30.0}, "kff": {"C": 0.9, "X": 0.9},
                                   "velocity_loop_ms": {"C": 2.0}}}, machine=bc)
    w = math.radians(30.0)  # rad/s
    q = np.zeros((3000, 5))
    q[:, 4] = np.arange(3000) * DT * w
    out = eff.servo.apply(q, bc, DT)
    assert q[-2, 4] - out[-2, 4] == pytest.approx(w * 0.1 / 35.0, rel=1e-9)
    with pytest.raises(EffectsFileError, match="at most 1"):
        parse_effects({"servo": {"kv_per_s": {"C": 35.0}, "kff": {"C": 1.2}}}, machine=bc)
    with pytest.raises(EffectsFileError, match="no kv_per_s"):
        parse_effects({"servo": {"kv_per_s": {"C": 35.0}, "kff": {"X": 0.9}}}, machine=bc)


# ---------------------------------------------------------------------------------------------------- backlash ----
@pytest.mark.parametrize("form", ["tanh", "friction"])
def test_rotary_backlash_in_urad_with_its_take_up_law(bc, form):
    c = np.radians(np.concatenate([np.linspace(0, 90, 9001), np.linspace(90, 0, 9001)[1:]]))
    q = np.zeros((c.size, 5))
    q[:, 4] = c
    b_urad, lam_deg = 40.0, 0.5
    out = Backlash("C", b_urad, lam_deg, form).apply(q, bc)
    e = (out[:, 4] - c) * 1e6  # urad
    assert e[4000] == pytest.approx(-b_urad / 2)  # turning +: lags
    assert e[-1] == pytest.approx(b_urad / 2)  # turning -: lags the other way
    s = np.abs(c[9001:] - c[9000])  # travel after the reversal, rad
    x = s / math.radians(lam_deg)
    taken = np.tanh(x) if form == "tanh" else 1 - np.exp(-x)
    np.testing.assert_allclose(e[9001:], 0.5 * b_urad * -1 * (1 - 2 * taken), atol=1e-9)
    assert e[9001 + 30] == pytest.approx(-0.5 * b_urad * (1 - 2 * taken[30]))  # checked where it is half taken up
    assert 0.3 < taken[30] < 0.7


@pytest.mark.parametrize("form", ["tanh", "friction"])
def test_backlash_is_a_play_with_memory(form):
    # A long run +, back by 12 nm (a compensated program's rounding), on + again, then a full reversal: at the 12 nm
    # the offset moves by a few thousandths of the play, not across it (a law restarting at every reversal jumped by
    # b there, and stayed thrown until the travel took it up again); the full reversal follows the class law.
    lam = 0.02
    x = np.concatenate([np.linspace(0.0, 1.0, 1001), 1.0 - 1.2e-5 * np.arange(1, 5) / 4,
                        0.999988 + np.linspace(0.0, 0.3, 301)[1:], 1.299988 - np.linspace(0.0, 0.1, 101)[1:]])
    e = Backlash("X", 8.0, lam, form).lost_motion_state(x, lam)
    assert e[1000] == pytest.approx(-1.0)  # moving +, taken up: lags by b/2
    assert np.max(np.abs(e[1000:1305] + 1.0)) < 2e-3  # the 12 nm back and on: hardly moves (tanh 1e-6, friction 1e-3)
    assert np.max(np.abs(np.diff(e))) < 0.6  # continuous along 1 mm steps (a restart would jump by up to 2)
    s = np.abs(x[1305:] - x[1304])  # the - run from the turning point, after a full take-up +
    f = np.tanh(s / lam) if form == "tanh" else 1 - np.exp(-s / lam)
    np.testing.assert_allclose(e[1305:], -1.0 * (1 - 2 * f), atol=5e-3)


def test_a_reversal_part_way_through_the_take_up_continues_from_there():
    # 5 um after a reversal (a quarter of the 20 um transition) the motion turns back: the offset, part taken up,
    # returns along the law from where it was, by tanh's inverse (its travel-equivalent), not from a full take-up.
    lam = 0.02
    x = np.concatenate([np.linspace(0.0, 0.5, 501), 0.5 - np.linspace(0.0, 0.005, 6)[1:],
                        0.495 + np.linspace(0.0, 0.1, 101)[1:]])
    e = Backlash("X", 8.0, lam).lost_motion_state(x, lam)
    e_turn = -1.0 * (1 - 2 * np.tanh(0.005 / lam))  # - run, 5 um after the turning point
    assert e[505] == pytest.approx(e_turn)
    s0 = np.arctanh((1 - e_turn) / 2)  # the + run starts where the offset is
    np.testing.assert_allclose(e[506:], 1 - 2 * np.tanh(np.abs(x[506:] - x[505]) / lam + s0), atol=1e-12)
    assert abs(e[506] - e[505]) < 0.06


# ----------------------------------------------------------------------------------------- rotary error motions ----
def _c_turn(machine, x=30.0, n=721):
    q = np.zeros((n, len(machine.axis_names)))
    q[:, 0] = x
    q[:, 4] = np.linspace(0, 2 * np.pi, n)
    return q


def test_radial_error_motion_once_per_turn_shifts_the_circle_centre(bc):
    m = perfect(bc)
    q = _c_turn(m)
    tip, u = forward_nominal(m, q)
    e_um = 3.0
    motion = RotaryErrorMotion("C", (("EXC", ((1, e_um, 0.0),), 0.0), ("EYC", ((1, 0.0, -e_um),), 0.0)),
                               relative_to_zero=False)
    tip2, u2 = motion.apply_pose(tip, u, q, m)
    shift = (tip2 - tip) * 1e3
    np.testing.assert_allclose(shift, np.tile([e_um, 0.0, 0.0], (len(q), 1)), atol=1e-9)
    # The cut circle's centre (least squares) moves by e along X; its radius stays.
    def centre(pts):
        A = np.column_stack([2 * pts[:, 0], 2 * pts[:, 1], np.ones(len(pts))])
        return np.linalg.lstsq(A, pts[:, 0] ** 2 + pts[:, 1] ** 2, rcond=None)[0][:2]

    # Nominally the circle is centred on C's line (its pivot (1, 2) mm, in the part frame as well: origin on Z).
    np.testing.assert_allclose(centre(tip), m.axes["C"].pivot[:2] - m.workpiece_origin[:2], atol=1e-9)
    np.testing.assert_allclose(centre(tip2) - centre(tip), [e_um * 1e-3, 0.0], atol=1e-10)
    np.testing.assert_allclose(u2, u, atol=1e-15)


def test_angular_positioning_motion_equals_the_axis_angle_error(bc):
    m = perfect(bc)
    q = _c_turn(m)
    q[:, 3] = math.radians(-25.0)
    q[:, 1] = 12.0
    h = ((1, 20.0, 5.0), (2, 3.0, -4.0))
    motion = RotaryErrorMotion("C", (("ECC", h, 15.0),), relative_to_zero=False)
    tip2, u2 = motion.apply_pose(*forward_nominal(m, q), q, m)
    q_err = RotaryPeriodic("C", h).apply(q, m)  # the harmonics as an axis angle error, plus the linear part
    q_err[:, 4] += 15.0e-6 * q[:, 4] / (2 * np.pi)
    tip3, u3 = forward_nominal(m, q_err)
    np.testing.assert_allclose(tip2, tip3, atol=1e-12)
    np.testing.assert_allclose(u2, u3, atol=1e-14)


def test_error_motions_agree_with_the_twins_component_errors(tmp_path):
    # nmv1500dcg holds all six C components as Fourier series (C's pivot at the origin, the twin's reference point):
    # the twin with them minus the twin without them is the same transform at C, placed in the chain by another code.
    text = (MACHINES / "nmv1500dcg.toml").read_text()
    comp = re.search(r"^\[component\.C\]\nfourier = \{(.*)\}\n", text, re.M)
    without = tmp_path / "no_c.toml"
    without.write_text(text.replace(comp.group(0), ""))
    m_with, m_without = load_machine(MACHINES / "nmv1500dcg.toml"), load_machine(without)
    series = dict(re.findall(r"(E[XYZABC]C) = (\[\[.*?\]\])", comp.group(1)))
    import json

    comps = tuple((name, tuple(tuple(r) for r in json.loads(v)), 0.0) for name, v in series.items())
    assert len(comps) == 6
    motion = RotaryErrorMotion("C", comps, relative_to_zero=False)
    rng = np.random.default_rng(4)
    q = np.column_stack([rng.uniform(-150, 150, 500), rng.uniform(-100, 100, 500), rng.uniform(-250, 50, 500),
                         rng.uniform(-1.5, 0.4, 500), rng.uniform(-np.pi, np.pi, 500)])
    tw_with, tw_without = ErrorTwin(m_with).actual_pose(q), ErrorTwin(m_without).actual_pose(q)
    ours = motion.apply_pose(*tw_without, q, m_without)
    effect = np.abs(tw_with[0] - tw_without[0]).max() * 1e3
    assert effect > 1.0  # not vacuous: the components move the tip by um
    # Second order: the twin's location errors (<= 70 urad) times the effect, and the small-angle E of the twin.
    np.testing.assert_allclose(ours[0], tw_with[0], atol=2e-6)  # mm: 0.002 um
    np.testing.assert_allclose(ours[1], tw_with[1], atol=1e-8)  # rad: 0.01 urad of 5 urad tilts


def test_error_motion_table_parses_iso_names_and_refuses_others(bc):
    eff = parse_effects({"rotary_error_motion": {"C": {"EXC": {"harmonics": [[1, 2.0, 0.0]]},
                                                       "ECC": {"harmonics": [[2, 8.0, 1.0]], "linear_per_turn": 10.0}},
                                                 "B": {"EZB": {"harmonics": [[1, 1.0, 0.0]]}}}}, machine=bc)
    assert [m.axis for m in eff.rotary_error_motion] == ["C", "B"]
    d, eps = eff.rotary_error_motion[0].values(np.array([0.0, np.pi]))
    np.testing.assert_allclose(d[:, 0] * 1e3, [0.0, -4.0])  # relative to the value at angle 0
    np.testing.assert_allclose(eps[:, 2] * 1e6, [0.0, 5.0])
    with pytest.raises(EffectsFileError) as exc:
        parse_effects({"rotary_error_motion": {"C": {"EXB": {"harmonics": [[1, 1.0, 0.0]]}}, "X": {}}}, machine=bc)
    assert "EXB: unknown key" in str(exc.value) and "X is not a rotary axis" in str(exc.value)


# ---------------------------------------------------------------------------------------------------- clamping ----
def _bend():
    return ClampingBend(12.0, np.array([0.0, 0.0, -5.0]), 60.0, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))


def test_bending_field_is_the_beams_elastic_line_with_plane_sections():
    cb = _bend()
    rng = np.random.default_rng(5)
    x = rng.uniform(-30, 30, (200, 3))
    d, grad = cb.field(x)
    xi = x[:, 1]
    s = xi / 60.0 + 0.5
    w = 12e-3 * 16 / 5 * (s - 2 * s**3 + s**4)
    np.testing.assert_allclose(d[:, 0], w, atol=1e-15)
    assert cb.field(np.array([[0.0, 0.0, 0.0], [0.0, 30.0, 0.0], [0.0, -30.0, 0.0]]))[0][:, 0] == pytest.approx(
        [12e-3, 0.0, 0.0], abs=1e-15)
    h = 1e-4
    fd = np.stack([(cb.field(x + h * e)[0] - cb.field(x - h * e)[0]) / (2 * h) for e in np.eye(3)], axis=2)
    np.testing.assert_allclose(grad, fd, atol=1e-11)


def test_bent_part_springs_back_on_the_boss_walls(xh714):
    cb = _bend()
    pts, nrm = boss_probe(n_per_side=200)
    eff = parse_effects({"clamping": {"form": "bending", "amplitude_um": 12.0, "center": [0.0, 0.0, -5.0],
                                      "span_mm": 60.0, "beam": [0.0, 1.0, 0.0], "direction": [1.0, 0.0, 0.0]}},
                        machine=xh714)
    assert isinstance(eff.clamping, ClampingBend) and eff.clamping.span_mm == cb.span_mm
    res = simulate(square_boss_program(), perfect(xh714), eff, part="slots", probe=(pts, nrm))
    base = simulate(square_boss_program(), perfect(xh714), None, part="slots", probe=(pts, nrm))
    d, _ = cb.field(pts)
    pred = -np.einsum("ij,ij->i", d, nrm) * 1e3  # released: the surface cut at y sits at y - d(y)
    assert np.ptp(pred) > 15.0
    np.testing.assert_allclose(res.deviations_um - base.deviations_um, pred, atol=0.02)


# -------------------------------------------------------------------------------------------------------- wear ----
def test_wear_law_is_run_in_plus_linear_growth():
    w = ToolWear(vb_run_in_um=40.0, run_in_mm=50.0, vb_rate_um_per_m=100.0, clearance_deg=10.0,
                 end_clearance_deg=5.0)
    l = np.array([0.0, 50.0, 1000.0])
    np.testing.assert_allclose(w.flank_wear_um(l), [0.0, 40 * (1 - math.exp(-1)) + 5.0, 40 * (1 - math.exp(-20)) + 100])
    # The law's rate integrated over the path gives the law (trapezoid, fine grid).
    grid = np.linspace(0, 800, 80001)
    rate = 40.0 / 50.0 * np.exp(-grid / 50.0) + 0.1
    assert np.trapezoid(rate, grid) == pytest.approx(float(w.flank_wear_um(800.0)), rel=1e-8)
    dr, dl = w.losses_mm(np.array([200.0]))
    assert dr[0] / dl[0] == pytest.approx(math.tan(math.radians(10)) / math.tan(math.radians(5)))
    feeding = np.array([False, True, True, False, True])
    tip = np.array([[0, 0, 0], [3, 4, 0], [6, 8, 0], [100, 0, 0], [100, 0, 2.0]])
    np.testing.assert_allclose(ToolWear.cut_path_mm(tip, feeding), [0, 5, 10, 10, 12])


def test_worn_tool_leaves_its_radius_loss_along_the_boss(xh714):
    wear = {"vb_run_in_um": 60.0, "run_in_mm": 20.0, "vb_rate_um_per_m": 300.0, "clearance_deg": 10.0}
    eff = parse_effects({"tool_wear": wear}, machine=xh714)
    pts, nrm = boss_probe(n_per_side=200)
    res = simulate(square_boss_program(), perfect(xh714), eff, part="slots", probe=(pts, nrm))
    base = simulate(square_boss_program(), perfect(xh714), None, part="slots", probe=(pts, nrm))
    # Path of the tool centre from the first feed sample (5 mm approach, then the walls clockwise: +Y wall from
    # x = -20, quarter arcs of radius 5 at the corners, +X wall downwards).
    h, r = 20.0, 5.0
    top = nrm[:, 1] > 0.5
    right = nrm[:, 0] > 0.5
    path = np.where(top, 5.0 + pts[:, 0] + h, 5.0 + 2 * h + math.pi * r / 2 + (h - pts[:, 1]))
    w = ToolWear(**wear)
    pred = w.losses_mm(path)[0] * 1e3
    sel = top | right
    got = (res.deviations_um - base.deviations_um)[sel]
    assert np.ptp(pred[sel]) > 3.0
    np.testing.assert_allclose(got, pred[sel], atol=0.02)
    assert res.info["tool_wear"]["radius_loss_um"] > pred[sel].max()


def test_interpolator_smoothing_bounds_acceleration_and_lags_a_ramp_by_half_its_window():
    from trueaxis.sim.effects import smooth_command

    v, T = 20.0, 24e-3
    t = np.arange(400) * DT
    q = np.column_stack([np.where(t < 0.1, 0.0, (t - 0.1) * v), -np.where(t < 0.1, 0.0, (t - 0.1) * v)])
    qs = smooth_command(q, T, DT)
    m = round(T / DT)
    np.testing.assert_allclose(q[-1] - qs[-1], [v * (m - 1) * DT / 2, -v * (m - 1) * DT / 2], rtol=1e-9)
    acc = np.diff(qs[:, 0], 2) / DT**2
    assert acc.max() == pytest.approx(v / (m * DT), rel=1e-9)  # the velocity step became a ramp over T
    np.testing.assert_allclose(qs[:, 0], -qs[:, 1], atol=1e-12)  # every axis alike: a straight move stays straight
    np.testing.assert_array_equal(smooth_command(q, 0.0, DT), q)


def test_auto_smoothing_keeps_the_feed_moves_within_the_acceleration_limits(xh714):
    # A feed move that turns by 90 deg at 20 mm/s: a velocity step of 20 mm/s on both axes. "auto" picks the shortest
    # window with 20 mm/s / T <= a, and the smoothed command then never exceeds a (it stays unsaturated).
    a = 1000.0
    eff = parse_effects({"servo": {"kv_per_s": {"X": 30.0, "Y": 30.0}, "accel": {"X": a, "Y": a},
                                   "smoothing_ms": "auto"}}, machine=xh714)
    t = np.arange(1000) * DT
    q = np.zeros((t.size, 3))
    q[:, 0] = np.minimum(t, 0.5) * 20.0
    q[:, 1] = np.maximum(t - 0.5, 0.0) * 20.0
    T = eff.servo.smoothing_s(q, xh714, DT)
    assert T == pytest.approx(0.020)
    from trueaxis.sim.effects import smooth_command

    acc = np.abs(np.diff(smooth_command(q, T, DT), 2, axis=0)) / DT**2
    assert acc.max() <= a * (1 + 1e-9)
    with pytest.raises(EffectsFileError, match="needs acceleration limits"):
        parse_effects({"servo": {"kv_per_s": {"X": 30.0}, "smoothing_ms": "auto"}}, machine=xh714)
