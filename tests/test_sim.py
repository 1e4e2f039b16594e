"""Checks of the virtual shop: trajectory, envelope (analytic cases), effects, and end-to-end properties."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import DATA, MACHINES, ROOT
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.nc.gcode import parse_program
from trueaxis.machine.kinematics import machine_to_part_rotation
from trueaxis.sim.effects import Backlash, EffectsFileError, _servo_axis, load_effects, parse_effects
from trueaxis.sim.envelope import envelope_deviation, line_tool_intersection, thin_instances
from trueaxis.sim.programs import boss_probe, cone_flank_program, square_boss_program
from trueaxis.sim.shop import load_part, simulate, write_cmm
from trueaxis.nc.trajectory import interpolate

R, L = 5.0, 30.0


def perfect(machine):
    return machine.with_parameters(np.zeros(len(machine.parameter_names())))


@pytest.fixture(scope="module")
def xh714():
    return load_machine(MACHINES / "xh714.toml")


@pytest.fixture(scope="module")
def bc():
    return load_machine(DATA / "bc_table.toml")


@pytest.fixture(scope="module")
def cone():
    return load_part("nas979")["surfaces"][0]


# --------------------------------------------------------------------------------------------------- trajectory ----
def test_trajectory_feed_and_arc_are_exact(xh714):
    prog = parse_program("G21 G90 G94 G17\nG0 X0 Y0 Z-300\nG1 X60 F1200\nG2 X70 Y-10 I0 J-10\nM30\n")
    tr = interpolate(prog, xh714, dt=1e-3)
    line_t = 60 / (1200 / 60)  # 3 s
    arc_t = (10 * math.pi / 2) / (1200 / 60)
    rapid_t = 300 / (10_000 / 60) + 0.2  # plus the in-position wait
    assert tr.t[-1] == pytest.approx(rapid_t + line_t + arc_t, abs=1e-3)
    arc = tr.motion == 2
    r = np.hypot(tr.q[arc, 0] - 60, tr.q[arc, 1] + 10)
    np.testing.assert_allclose(r, 10.0, atol=1e-12)  # on the circle, not on chords
    assert np.all(np.diff(tr.q[arc, 0]) >= 0) and np.all(np.diff(tr.q[arc, 1]) <= 0)  # clockwise from the top
    speed = np.linalg.norm(tr.qdot[tr.motion == 1], axis=1)
    np.testing.assert_allclose(speed, 20.0)
    np.testing.assert_allclose(tr.q[-1], [70, -10, -300])


def test_trajectory_inverse_time_and_rotary_units(bc):
    prog = parse_program("G21 G90\nG93 G1 X10 B-30 C90 F2\nG94 G1 C180 F3600\nM30\n")
    tr = interpolate(prog, bc, dt=1e-3)
    names = bc.axis_names
    assert tr.row_duration[0] == pytest.approx(30.0)  # 1 / 2 min
    assert tr.row_duration[1] == pytest.approx(90 / 3600 * 60)  # rotary-only move at deg/min
    np.testing.assert_allclose(tr.q[-1, names.index("C")], math.pi)
    np.testing.assert_allclose(tr.q[-1, names.index("B")], math.radians(-30))


def test_trajectory_refuses_bad_input(xh714):
    prog = parse_program("G1 X10 A5 F100\n")
    with pytest.raises(ValueError, match="does not have"):
        interpolate(prog, xh714)
    with pytest.raises(ValueError, match="dt"):
        interpolate(parse_program("G1 X1 F10\n"), xh714, dt=0)


def test_trajectory_refuses_a_feed_per_revolution_and_takes_it_back_under_g94(xh714):
    # G95's F is per spindle revolution: read as per minute, F0.2 made this 10 mm cut last 50 minutes of the clock.
    with pytest.raises(ValueError, match=r":2: feed per revolution \(G95\)"):
        interpolate(parse_program("G0 X0 Y0 Z5\nG95 G1 X10 F0.2\nM2\n"), xh714)
    tr = interpolate(parse_program("G95\nG94 G1 X10 F600\nM2\n"), xh714, dt=1e-3)  # G94 again: a time of 1 s
    assert tr.t[-1] == pytest.approx(1.0, abs=2e-3)
    tr = interpolate(parse_program("G0 X0 Y0 Z5 (G95 in a comment)\nG1 X10 F600\nM2\n"), xh714, dt=1e-3)
    assert tr.t[-1] > 0.99


# ----------------------------------------------------------------------------------------------------- envelope ----
def _straight_pass(offset, n=4001, axis=(0, 0, 1)):
    x = np.linspace(-20, 20, n)
    tips = np.column_stack([x, np.full(n, offset), np.full(n, -5.0)])
    return tips, np.tile(np.asarray(axis, float), (n, 1))


def test_straight_pass_leaves_a_plane_at_its_offset():
    # Tool axis at y = 0.010 mm: the wall y = -5 (material on the -y side) is cut 10 um short, s* = +10 um.
    tips, axes = _straight_pass(0.010)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-10, 10, 3000), np.full(3000, -R), rng.uniform(-4.5, 24, 3000)])
    nrm = np.tile([0.0, 1.0, 0.0], (3000, 1))
    res = envelope_deviation(pts, nrm, tips, axes, R, L)
    # Samples 10 um apart: the scallop is at most h^2 / (8 R) = 0.0025 um.
    np.testing.assert_allclose(res.deviation_um, 10.0, atol=0.003)


def test_end_face_cuts_a_floor_at_the_tip_height():
    tips, axes = _straight_pass(0.0)
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-10, 10, 2000), rng.uniform(-4.9, 4.9, 2000), np.full(2000, -5.0 - 0.003)])
    res = envelope_deviation(pts, np.tile([0.0, 0.0, 1.0], (2000, 1)), tips, axes, R, L)
    np.testing.assert_allclose(res.deviation_um, 3.0, atol=1e-9)  # the floor is 3 um above the probed points


def test_tilted_tool_side_is_exact():
    # Tool axis tilted by 20 deg about X, moving along X: its side sweeps a plane inclined by 20 deg. A probe point
    # at depth d behind that plane (into the material), probed along the plane's normal, sees s* = d.
    beta = math.radians(20)
    u = np.array([0.0, -math.sin(beta), math.cos(beta)])
    side = np.array([0.0, -math.cos(beta), -math.sin(beta)])  # unit, normal to u and X: towards the material
    n = 4001
    x = np.linspace(-20, 20, n)
    tips = np.column_stack([x, np.zeros(n), np.zeros(n)])
    axes = np.tile(u, (n, 1))
    rng = np.random.default_rng(2)
    h = rng.uniform(1, 25, 1000)
    d = rng.uniform(-0.05, 0.05, 1000)
    pts = np.column_stack([rng.uniform(-10, 10, 1000), np.zeros(1000), np.zeros(1000)]) + h[:, None] * u + (R + d)[:, None] * side
    nrm = np.tile(-side, (1000, 1))
    res = envelope_deviation(pts, nrm, tips, axes, R, L)
    np.testing.assert_allclose(res.deviation_mm, d, atol=3e-6)  # scallop of 10 um steps: h^2 / (8 R) = 2.5e-6 mm


def test_line_through_the_solid_enters_at_the_analytic_point():
    # A line along +x through the axis of a vertical tool at the origin enters at x = -R; a line down the axis enters
    # the end face at the tip; a line that misses has s_in = inf.
    x0 = np.array([[-10.0, 0.0, 5.0], [0.0, 0.0, -3.0], [0.0, 7.0, 5.0]])
    n = np.array([[1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    tip = np.zeros((3, 3))
    ax = np.tile([0, 0, 1.0], (3, 1))
    s_in, s_out = line_tool_intersection(x0, n, tip, ax, R, L)
    np.testing.assert_allclose(s_in[:2], [5.0, 3.0])
    np.testing.assert_allclose(s_out[:2], [15.0, 33.0])
    assert np.isinf(s_in[2])


def test_thinning_changes_the_envelope_by_less_than_its_tolerance():
    tips, axes = _straight_pass(0.0, n=40001)  # 1 um steps
    keep = thin_instances(tips, axes, R, L, tol_mm=1e-5)
    assert keep.sum() < len(keep) / 5
    rng = np.random.default_rng(4)
    pts = np.column_stack([rng.uniform(-10, 10, 2000), np.full(2000, -R), rng.uniform(0, 20, 2000)])
    nrm = np.tile([0.0, 1.0, 0.0], (2000, 1))
    full = envelope_deviation(pts, nrm, tips, axes, R, L, search_mm=0.1)
    thin = envelope_deviation(pts, nrm, tips[keep], axes[keep], R, L, search_mm=0.1)
    assert np.max(np.abs(full.deviation_um - thin.deviation_um)) <= 0.01


def test_envelope_refuses_bad_input():
    with pytest.raises(ValueError, match="unit"):
        envelope_deviation(np.zeros((2, 3)), np.ones((2, 3)), np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)), R, L)
    with pytest.raises(ValueError, match="NaN"):
        envelope_deviation(np.full((1, 3), np.nan), np.array([[0, 0, 1.0]]), np.zeros((1, 3)), np.array([[0, 0, 1.0]]),
                           R, L)


# ------------------------------------------------------------------------------------------------------ effects ----
def test_servo_loop_matches_the_stepped_saturating_loop():
    dt = 1e-3
    t = np.arange(3000) * dt
    qc = np.where(t < 0.5, 0.0, (t - 0.5) * 50.0) + 3 * np.sin(20 * t) * (t > 1.5)
    q = _servo_axis(qc, 30.0, 500.0, dt)
    ref = np.zeros_like(qc)
    v = 0.0
    for k in range(len(qc) - 1):
        vc = 30.0 * (qc[k] - ref[k])
        v = min(max(vc, v - 500.0 * dt), v + 500.0 * dt)
        ref[k + 1] = ref[k] + v * dt
    np.testing.assert_allclose(q, ref, atol=1e-8)
    # Steady ramp: the lag is v / Kv.
    ramp = _servo_axis(np.arange(5000) * dt * 10.0, 25.0, None, dt)
    assert ramp[-1] - (4999 * dt * 10.0) == pytest.approx(-10.0 / 25.0, rel=1e-6)


def _servo(machine, kv, accel=2000.0):
    axes = machine.axis_names
    table = {"kv_per_s": {a: kv for a in axes}}
    if accel is not None:
        table["accel"] = {a: accel for a in axes}
    return parse_effects({"servo": table}, machine=machine)


def test_servo_equal_gains_lag_along_a_straight_line_only(xh714):
    # Kv 50 /s, 2 m/s^2 on every axis; a 3-D feed move at 1200 mm/min after a 300 mm rapid. The loop's velocity step
    # at the feed start is Kv v = 1 m/s^2 < a, so the feed never saturates; the rapid is planned within the limit.
    kv, v = 50.0, 20.0
    eff = _servo(xh714, kv)
    prog = parse_program("G21 G90 G94\nG0 X0 Y0 Z-300\nG1 X60 Y40 Z-310 F1200\nM30\n")
    dt = 1e-3
    tr = interpolate(prog, xh714, dt=dt, rapid_settle_s=eff.servo.settle_time(xh714))
    qa = eff.apply_axes(tr.q, xh714, dt, traj=tr)
    # The rapid: no overshoot, monotone, acceleration within the limit, in position before the feed starts.
    rapid = np.nonzero(tr.motion == 0)[0]
    z = qa[rapid, 2]
    assert np.all(np.diff(z) <= 1e-12) and z.min() >= -300.0 - 1e-9
    acc = np.abs(np.diff(qa, 2, axis=0)) / dt**2
    assert acc.max() <= 2000.0 * (1 + 1e-6)
    assert np.abs(qa[rapid[-1]] - tr.q[rapid[-1]]).max() < 1e-4  # in position (0.1 um) when the cut starts
    feed = np.nonzero(tr.motion == 1)[0]
    # Steady state (20 time constants after the start, before the end): lag v/Kv along the path, none across it.
    d = np.array([60.0, 40.0, -10.0]) / np.linalg.norm([60.0, 40.0, -10.0])
    t0 = tr.t[feed[0]]
    steady = feed[(tr.t[feed] > t0 + 20 / kv) & (tr.t[feed] < tr.t[feed[-1]] - 0.01)]
    assert steady.size > 1000
    e = tr.q[steady] - qa[steady]
    along = e @ d
    across = np.linalg.norm(e - along[:, None] * d, axis=1)
    assert across.max() < 1e-4  # mm: < 0.1 um
    np.testing.assert_allclose(along, v / kv, rtol=0.01)


def test_servo_equal_gains_shrink_a_circle_by_the_first_order_amount(xh714):
    # A first-order loop 1/(1 + s/Kv) passes a circle of angular rate w = v/R with gain 1/sqrt(1 + (w/Kv)^2): the
    # radius shrinks by R (1 - 1/sqrt(1 + x^2)) ~ R x^2 / 2, x = v/(Kv R). The loop closed at dt (forward Euler) has
    # the gain Kv dt / |exp(j w dt) - 1 + Kv dt| instead (radius loss (1 - Kv dt) times the continuous one, to
    # first order: 5 % less here).
    R, F, kv, dt = 10.0, 3000.0, 30.0, 1e-3
    v = F / 60.0
    eff = _servo(xh714, kv)
    prog = parse_program(f"G21 G90 G94 G17\nG0 X{R} Y0 Z-300\nG2 X{R} Y0 I{-R} J0 P3 F{F}\nM30\n")
    tr = interpolate(prog, xh714, dt=dt, rapid_settle_s=eff.servo.settle_time(xh714))
    qa = eff.apply_axes(tr.q, xh714, dt, traj=tr)
    arc = np.nonzero(tr.motion == 2)[0]
    late = arc[arc > arc[0] + int(1.0 / dt)]  # after the transient (30 time constants)
    r = np.hypot(qa[late, 0], qa[late, 1])
    shrink = R - r.mean()
    x = v / (kv * R)
    assert shrink == pytest.approx(R * x**2 / 2, rel=0.10)
    w = v / R
    exact_discrete = R * (1 - kv * dt / abs(np.exp(1j * w * dt) - 1 + kv * dt))
    assert shrink == pytest.approx(exact_discrete, rel=1e-3)
    assert r.std() < 1e-9  # equal gains: still round


def test_servo_with_acceleration_limits_on_the_slot_block(xh714):
    # The slot block of the withheld-effect benchmark, equal gains 80 /s. Its feed (1000 mm/min = 16.7 mm/s) needs
    # Kv |dv| <= 80 * 16.7 = 1.3 m/s^2 at any block junction (45 deg corners, plunges, retracts) < 2 m/s^2, so the
    # limits must not change the surface: the rapids are planned within them and settle before the cut (before the
    # fix the rapids' 167 mm/s steps overshot by mm and gouged the slots). What is left is the first-order loop's
    # corner cut: at a corner turning by theta the lagged path passes the vertex at ln 2 sin(theta / 2) v / Kv
    # (the mean absolute deviation from the median of the loop's exponential delay), 55 um at the slots' 45 deg
    # corners, seen on the outer corner arcs (tool radius from the vertex); everywhere else < 1 um.
    from trueaxis.workpiece.parts import SlotBlockParams, slot_block_description
    from trueaxis.postproc.programs import slots_program

    params = SlotBlockParams(slot_depth=1.2)
    prog = slots_program(xh714, params)
    pj = slot_block_description(params)
    run = lambda eff: simulate(prog.text, prog.machine, eff, part="slots", part_json=pj, points=600,  # noqa: E731
                               force_stride=50)
    base = run(None)
    lim = run(_servo(prog.machine, 80.0, 2000.0))
    free = run(_servo(prog.machine, 80.0, None))
    d = lim.deviations_um - base.deviations_um
    assert np.all(np.isfinite(d))
    np.testing.assert_allclose(lim.deviations_um, free.deviations_um, atol=0.01)
    corner_cut_um = math.log(2) * math.sin(math.radians(22.5)) * (1000.0 / 60.0) / 80.0 * 1e3
    assert np.abs(d).max() <= 1.05 * corner_cut_um
    # The points that move are on the outer arcs of the corners: a tool radius from a vertex of the cutting path.
    tr = lim.trajectory
    cutting_rows = np.unique(tr.row[tr.motion == 1])
    first = np.searchsorted(tr.row, cutting_rows)
    xy, dirs = tr.q[first, :2], tr.qdot[first, :2]
    cross = dirs[1:, 0] * dirs[:-1, 1] - dirs[1:, 1] * dirs[:-1, 0]
    turn = np.r_[False, np.abs(cross) > 1e-6 * np.linalg.norm(dirs[1:], axis=1) ** 2]
    vertices = xy[turn]
    moved = np.abs(d) > 1.0
    assert 0 < moved.sum() <= 0.05 * d.size
    dist = np.linalg.norm(lim.points[moved, None, :2] - vertices[None], axis=2).min(axis=1)
    np.testing.assert_allclose(dist, prog.machine.tool.radius, atol=0.1)


def test_backlash_lags_by_half_and_takes_up_at_reversal(xh714):
    x = np.concatenate([np.linspace(0, 1, 1001), np.linspace(1, -1, 2001)[1:]])
    q = np.zeros((x.size, 3))
    q[:, 0] = x
    out = Backlash("X", amplitude=10.0, transition=0.01).apply(q, xh714)
    e = (out[:, 0] - x) * 1e3  # um
    assert e[500] == pytest.approx(-5.0)  # moving +: lags
    assert e[-1] == pytest.approx(5.0)  # moving -: lags the other way
    assert e[1001] == pytest.approx(-5.0 + 10.0 * math.tanh(0.001 / 0.01), abs=1e-6) or abs(e[1001]) < 5


def test_effects_file_is_strict(tmp_path, bc):
    good = tmp_path / "E.toml"
    good.write_text(
        '[servo]\nkv_per_s = { X = 30.0, C = 25.0 }\naccel = { X = 2000.0 }\n'
        '[backlash.X]\namplitude = 4.0\ntransition = 0.02\n'
        '[rotary_periodic.C]\nharmonics_urad = [[1, 12.0, -5.0]]\n'
        '[force]\nuse_machine_compliance = true\n'
        '[tool_deflection]\nstick_out_mm = 40.0\n'
        f'[thermal]\nfile = "{ROOT / "fixtures/thermal/spindle_thermal_drift_part1.csv"}"\n'
        'channels = { Z = "ch3_um" }\ntime_scale = 60.0\n'
        '[clamping]\namplitude_um = 5.0\ncenter = [0, 0, 0]\nlength_mm = 30.0\ndirection = [0, 0, 1]\n'
    )
    e = load_effects(good, bc)
    assert e.servo.kv_per_s["C"] == 25.0 and e.backlash[0].amplitude == 4.0 and e.needs_force
    bad = tmp_path / "bad.toml"
    bad.write_text('[servo]\nkv_per_s = { Q = 30.0 }\nkv = 3\n[backlash.X]\namplitude = -1\n[unknown]\na = 1\n')
    with pytest.raises(EffectsFileError) as exc:
        load_effects(bad, bc)
    msg = str(exc.value)
    for part in ("kv_per_s.Q", "[servo].kv: unknown key", "[backlash.X].amplitude", "[unknown]"):
        assert part in msg
    with pytest.raises(EffectsFileError, match="not a rotary axis"):
        parse_effects({"rotary_periodic": {"X": {"harmonics_urad": [[1, 1.0, 0.0]]}}}, machine=bc)
    # what the shop would only meet when it runs (numpy's or the loop's text, no file or key named, exit 2: a QA
    # pass): a thermal file that is no series, a column it does not have, a loop gain the 1 ms period cannot step
    thermal = tmp_path / "thermal.toml"
    thermal.write_text(f'[thermal]\nfile = "{ROOT / "fixtures/thermal/LICENSE"}"\nchannels = {{ X = "ch1_um" }}\n'
                       '[servo]\nkv_per_s = { X = 2000.0 }\n')
    with pytest.raises(EffectsFileError) as exc:
        load_effects(thermal, bc)
    msg = str(exc.value)
    assert "[thermal].file:" in msg and "is not a time series" in msg
    assert "[servo].kv_per_s.X: a position loop's gain must be below 1000 /s" in msg
    column = tmp_path / "column.toml"
    column.write_text(f'[thermal]\nfile = "{ROOT / "fixtures/thermal/spindle_thermal_drift_part1.csv"}"\n'
                      'channels = { X = "chX_um" }\n')
    with pytest.raises(EffectsFileError, match=r"\[thermal\]\.channels\.X: no column 'chX_um'"):
        load_effects(column, bc)


def test_machine_to_part_rotation_of_a_bc_table(bc):
    q = np.zeros((1, 5))
    q[0, 3], q[0, 4] = math.radians(-30), math.radians(90)
    R_ = machine_to_part_rotation(bc, q)[0]
    _, u = ErrorTwin(perfect(bc)).nominal_pose(q)
    np.testing.assert_allclose(R_ @ [0, 0, 1.0], u[0], atol=1e-12)


# ------------------------------------------------------------------------------------------------- end to end ----
def test_perfect_3axis_machine_reproduces_the_boss(xh714):
    pts, nrm = boss_probe(n_per_side=1000)
    res = simulate(square_boss_program(), perfect(xh714), part="slots", probe=(pts, nrm))
    d = res.deviations_um
    assert not np.any(np.isnan(d))
    assert np.sqrt(np.mean(d**2)) < 0.3
    assert np.max(np.abs(d)) < 0.05


def test_3axis_deviation_equals_twin_error_on_the_normal(xh714):
    # Linear axes only: the twin's error at the cut is nearly uniform along the tool, so s* ~ dp . n.
    pts, nrm = boss_probe(n_per_side=500)
    res = simulate(square_boss_program(), xh714, part="slots", probe=(pts, nrm))
    dp, du = ErrorTwin(xh714).volumetric_error(res.axes_actual)
    # Contact point: the angular error turns the tool about its tip; at height h the contact moves by du x h.
    h = (pts - ErrorTwin(xh714).nominal_pose(res.axes_actual)[0]) @ np.array([0, 0, 1.0])
    pred = np.einsum("ij,ij->i", dp + 1e-3 * h[:, None] * du, nrm)
    assert np.max(np.abs(res.deviations_um - pred)) < 0.5


def test_perfect_5axis_machine_reproduces_the_cone(bc, cone):
    m0 = perfect(bc)
    res = simulate(cone_flank_program(m0, cone, n_blocks=1800), m0, part="nas979", points=10_000)
    d = res.deviations_um
    assert not np.any(np.isnan(d))
    assert np.sqrt(np.mean(d**2)) < 0.3


def test_xoc_deviation_matches_first_order_prediction(bc, cone):
    names = bc.parameter_names()
    v = np.zeros(len(names))
    v[names.index("XOC")] = 20.0
    true = bc.with_parameters(v)
    prog = cone_flank_program(perfect(bc), cone, n_blocks=1800)
    res = simulate(prog, true, part="nas979", points=10_000)
    dp, du = ErrorTwin(true).volumetric_error(res.axes_actual)
    pred = np.einsum("ij,ij->i", dp, res.normals)  # XOC moves the C line: a translation, no tool-axis error
    assert np.max(np.abs(du)) < 1e-6
    assert np.ptp(res.deviations_um) > 20  # the check is not vacuous: the deviation swings with C
    assert np.max(np.abs(res.deviations_um - pred)) < 0.5


def test_cmm_cloud_and_truth_are_written(tmp_path, xh714):
    from trueaxis.inspect.cloud import read_cloud

    pts, nrm = boss_probe(n_per_side=100)
    res = simulate(square_boss_program(), xh714, part="slots", probe=(pts, nrm), noise_um=1.0, seed=7)
    truth = write_cmm(res, tmp_path / "cmm.ply")
    cloud = read_cloud(tmp_path / "cmm.ply")
    assert cloud.points.shape == (400, 3)
    data = json.loads(truth.read_text())
    assert data["seed"] == 7 and len(data["per_point"]["cut_time_s"]) == 400
    along = np.einsum("ij,ij->i", cloud.points - pts, nrm) * 1e3
    np.testing.assert_allclose(along, res.deviations_um + res.noise_um, atol=1e-6)
    assert 0.7 < np.std(res.noise_um) < 1.3


def test_probe_patterns_cover_the_parts():
    from trueaxis.sim.cmm import probe_pattern

    cone_part = load_part("nas979")
    p, n = probe_pattern(cone_part, 5000)
    assert 4500 < len(p) <= 5000
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    from trueaxis.workpiece.parts import cone_signed_distance

    np.testing.assert_allclose(cone_signed_distance(p, cone_part["surfaces"][0]), 0.0, atol=1e-9)
    slots = load_part("slots")
    p, n = probe_pattern(slots, 3000)
    assert len(p) > 2500 and np.all(p[:, 2] < 0)


@pytest.mark.slow
def test_force_and_tool_deflection_with_real_engagement(cone):
    # A semi-finishing pass leaves 0.2 mm; the finishing pass's engagement must come out near 0.2 mm, and the
    # deflection must leave material (positive deviation) larger near the tool tip (the tool bends).
    m0 = perfect(load_machine(MACHINES / "nmv1500dcg.toml"))
    prog = cone_flank_program(m0, cone, n_blocks=900, semi_stock=0.2)
    eff = parse_effects({"tool_deflection": {"stick_out_mm": 40.0}})
    res = simulate(prog, m0, eff, part="nas979", points=4000, force_stride=20)
    assert res.info["ae_by_pass_mm"][0] == pytest.approx(0.5)  # raw stock: the program's ae
    assert res.info["ae_by_pass_mm"][1] == pytest.approx(0.2, abs=0.01)  # what the semi-finishing pass left
    assert res.info["ap_by_pass_mm"][1] == pytest.approx(20 / math.cos(math.radians(15)), abs=1.0)
    d = res.deviations_um
    assert np.all(np.isfinite(d)) and np.median(d) > 1.0
    h = (res.points @ np.asarray(cone["axis"]))
    low, high = d[h < 6].mean(), d[h > 14].mean()
    assert low > high


def test_the_envelope_progress_bar_is_not_written_off_a_terminal(capfd):
    # trueaxis simulate asks for the bar; redirected into a log (stderr not a terminal) it must write nothing
    tips, axes = _straight_pass(0.010)
    pts = np.column_stack([np.linspace(-5, 5, 50), np.full(50, -R), np.full(50, 10.0)])
    res = envelope_deviation(pts, np.tile([0.0, 1.0, 0.0], (50, 1)), tips, axes, R, L, progress=True, chunk_points=10)
    np.testing.assert_allclose(res.deviation_um, 10.0, atol=0.003)
    out, err = capfd.readouterr()
    assert out == "" and err == "", err


def test_an_effects_file_that_switches_nothing_on_is_said(xh714):
    # An effects file with everything off, or asking for the force model of a machine that has none, ran as the
    # machine alone without a word (a QA pass): the run's notes say it
    pts, nrm = boss_probe(n_per_side=50)
    machine = xh714.error_free()  # (no force model)
    quiet = simulate(square_boss_program(), machine, parse_effects({"backlash": {"X": {"amplitude": 5.0,
                                                                                       "enabled": False}}},
                                                                   machine=machine),
                     part="slots", probe=(pts, nrm))
    assert any("no effect is switched on" in n for n in quiet.info.get("notes", [])), quiet.info
    asked = simulate(square_boss_program(), machine, parse_effects({"force": {"use_machine_compliance": True}},
                                                                   machine=machine), part="slots", probe=(pts, nrm))
    assert any("has none: no force deflection in this run" in n for n in asked.info.get("notes", [])), asked.info
    on = simulate(square_boss_program(), machine, parse_effects({"backlash": {"X": {"amplitude": 5.0}}},
                                                                machine=machine), part="slots", probe=(pts, nrm))
    assert not on.info.get("notes")


def test_the_smoothing_the_run_used_is_in_its_truth(xh714, tmp_path):
    # "auto" smoothing is the interpolator's choice for the program: the truth file said "auto", so a servo lag could
    # not be checked against it (a QA pass). The value used is in the run's info (and so in the truth file): the
    # slot program's largest velocity step at a feed corner over the acceleration limit, in whole 1 ms periods.
    from trueaxis.workpiece.parts import SlotBlockParams, slot_block_description
    from trueaxis.postproc.programs import slots_program
    from trueaxis.sim.shop import write_cmm

    params = SlotBlockParams(slot_depth=0.6)
    prog = slots_program(xh714, params)
    axes = prog.machine.axis_names
    eff = parse_effects({"servo": {"kv_per_s": {a: 40.0 for a in axes}, "accel": {a: 500.0 for a in axes},
                                   "smoothing_ms": "auto"}}, machine=prog.machine)
    r = simulate(prog.text, prog.machine, eff, part="slots", part_json=slot_block_description(params), points=200,
                 force_stride=50)
    used = r.info["servo_smoothing_ms"]
    feed = r.trajectory.motion != 0
    v = np.diff(r.trajectory.q, axis=0) / r.trajectory.dt
    dv = np.abs(np.diff(v, axis=0))[feed[1:-1] | feed[2:]]
    expect = math.ceil(dv.max() / 500.0 / r.trajectory.dt - 1e-9) * r.trajectory.dt * 1e3
    assert used > 0 and used == pytest.approx(expect, abs=r.trajectory.dt * 1e3)
    truth = json.loads(write_cmm(r, tmp_path / "cmm.ply").read_text())
    assert truth["info"]["servo_smoothing_ms"] == used
