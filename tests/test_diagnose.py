"""Checks of the diagnosis: candidate sensitivities against the simulator, withheld effects named, controls left
alone, the report's schema, and the command's refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import MACHINES, ROOT
from trueaxis.diagnose.analysis import diagnose_state, estimate_noise_um
from trueaxis.diagnose.candidates import LIBRARY, build, build_all
from trueaxis.diagnose.report import run_diagnosis
from trueaxis.diagnose.state import twin_state
from trueaxis.inspect.parts import SlotBlockParams, slot_block_description
from trueaxis.inspect.programs import slots_program
from trueaxis.machine import load_machine
from trueaxis.sim.effects import parse_effects
from trueaxis.sim.shop import simulate, write_cmm

POINTS = 400


@pytest.fixture(scope="module")
def slots():
    """xh714 cutting one 0.6 mm pass per slot: the smallest real program of the slot block."""
    m = load_machine(MACHINES / "xh714.toml")
    params = SlotBlockParams(slot_depth=0.6)
    prog = slots_program(m, params)
    prog.part_json = slot_block_description(params)
    base = simulate(prog.text, prog.machine, None, part="slots", part_json=prog.part_json, points=POINTS)
    cut = np.isfinite(base.deviations_um)
    base.points, base.normals, base.deviations_um = base.points[cut], base.normals[cut], base.deviations_um[cut]
    return m, prog, base


def _cut(m, prog, effects, noise=0.0, seed=1, points=POINTS):
    """The slot block cut with ``effects``; only the probe points the shallow program cut (the default part's
    pattern also probes the deeper walls)."""
    eff = parse_effects(effects, machine=prog.machine) if effects else None
    r = simulate(prog.text, prog.machine, eff, part="slots", part_json=prog.part_json, points=points, noise_um=noise,
                 seed=seed, force_stride=50)
    cut = np.isfinite(r.deviations_um)
    for name in ("points", "normals", "deviations_um", "measured", "noise_um"):
        setattr(r, name, getattr(r, name)[cut])
    return r


def test_gap_reads_the_simulated_deviation_difference(slots):
    # The gap read at the measured points equals (true - twin) deviation + noise at the nominal points.
    m, prog, base = slots
    r = _cut(m, prog, {"backlash": {"Y": {"amplitude": 6.0, "transition": 0.02}}}, noise=0.5)
    st = twin_state(r.measured, r.normals, m, prog.text, "slots", want_force=False)
    assert np.array_equal(r.points, base.points)
    expect = r.deviations_um - base.deviations_um + r.noise_um
    np.testing.assert_allclose(st.gap_um, expect, atol=0.02)  # envelope scallop differences only


def test_twin_parameter_sensitivity_matches_finite_difference(slots):
    m, prog, base = slots
    st = twin_state(base.points, base.normals, m, prog.text, "slots", want_force=False)
    cand = build("twin_parameters", st)
    j = cand.parameters.index("dC0Y")
    names = m.parameter_names()
    v = m.parameter_values().copy()
    v[names.index("C0Y")] += 20.0  # urad
    moved = simulate(prog.text, prog.machine.with_parameters(
        np.where(np.arange(v.size) == names.index("C0Y"), v, prog.machine.parameter_values())), None, part="slots",
        probe=(base.points, base.normals))
    fd = moved.deviations_um - base.deviations_um
    assert np.ptp(fd) > 1.0  # not vacuous
    np.testing.assert_allclose(cand.columns[:, j] * 20.0, fd, atol=0.05)


def test_thermal_and_backlash_sensitivities_match_the_simulator(slots, tmp_path):
    m, prog, base = slots
    st = twin_state(base.points, base.normals, m, prog.text, "slots", want_force=False)
    # A linear drift in Z: the linear-spline candidate holds it exactly.
    T = st.t_end_s
    series = tmp_path / "drift.csv"
    series.write_text("time_s,ch_um\n0,0\n1000,100\n")
    r = _cut(m, prog, {"thermal": {"file": str(series), "channels": {"Z": "ch_um"}}})
    cand = build("thermal_z", st)
    rate = 0.1  # um/s
    theta = rate * T * np.arange(1, 4) / 3
    np.testing.assert_allclose(cand.columns @ theta, r.deviations_um - base.deviations_um, atol=0.02)
    # A sharp backlash on Y: the step candidate agrees away from the reversals.
    r = _cut(m, prog, {"backlash": {"Y": {"amplitude": 8.0, "transition": 0.001}}})
    cand = build("backlash_y", st)
    diff = r.deviations_um - base.deviations_um
    assert np.ptp(diff) > 4.0
    assert np.median(np.abs(cand.columns[:, 0] * 8.0 - diff)) < 0.05


def _named(slots, effects, noise=1.0, seed=3, candidates=None):
    m, prog, _ = slots
    r = _cut(m, prog, effects, noise=noise, seed=seed)
    diag, state = run_diagnosis(r.measured, r.normals, "slots", m, prog.text,
                                candidates=candidates or "all")
    return diag, state


def test_backlash_x_is_named_on_the_cone():
    # On the slot block X only ever cuts moving +, so its backlash is a constant shift that a drift mimics; on the
    # cone X reverses twice per turn and the step is unmistakable.
    from trueaxis.inspect.programs import nas979_program

    m = load_machine(MACHINES / "nmv1500dcg.toml")
    prog = nas979_program(m, compensation="none", step_deg=4.0, chord_tol_um=None)
    eff = parse_effects({"backlash": {"X": {"amplitude": 6.0, "transition": 0.02}}}, machine=prog.machine)
    r = simulate(prog.text, prog.machine, eff, part="nas979", points=300, noise_um=1.0, seed=2)
    diag, _ = run_diagnosis(r.measured, r.normals, "nas979", m, prog.text,
                            candidates=[n for n in LIBRARY if n not in ("force_deflection", "tool_deflection")])
    assert diag.chosen == ["backlash_x"]
    assert diag.shrink_above_noise > 0.7
    value = diag.chosen_fit.value[0]
    assert value == pytest.approx(6.0, abs=3 * diag.chosen_fit.std[0] + 0.5)


def test_thermal_z_is_named(slots):
    diag, _ = _named(slots, {"thermal": {"file": str(ROOT / "fixtures/thermal/spindle_thermal_drift_part1.csv"),
                                         "channels": {"Z": "ch3_um"}, "time_scale": 60.0, "time_offset_s": 60000.0,
                                         "amplitude_scale": 0.5}},
                     candidates=[n for n in LIBRARY if n not in ("force_deflection", "tool_deflection")])
    assert diag.chosen == ["thermal_z"]


def test_force_deflection_is_named(slots):
    # An anisotropic machine compliance (X 0.04, Y 0.03 um/N) on the three-axis slot block: tool bending matches the
    # gap's shape almost as well, but a round tool bends alike in X and Y, so it is ruled out, and said so.
    diag, _ = _named(slots, {"force": {"compliance_um_per_n": [[0.04, 0, 0], [0, 0.03, 0], [0, 0, 0.02]]}})
    assert diag.chosen == ["force_deflection"]
    f = diag.chosen_fit
    assert f.value[0] > f.value[1] > 0
    assert "tool_deflection" not in diag.tied.get("force_deflection", [])
    assert f.difference_z("compliance_X", "compliance_Y") > 4.0


def _fake_fit(name, params, value, cov, pred, n_parameters):
    from trueaxis.diagnose.analysis import Fit

    return Fit(name=name, members=[name], parameters=params, units=["um/N"] * len(params), value=np.array(value),
               std=np.sqrt(np.diag(cov)), held_out_pred_um=pred, gain_um2=1.0, z=10.0, f_stat=1.0, f_p=0.0,
               plausible=True, rank=len(params), n_parameters=n_parameters, cov=np.array(cov))


@pytest.mark.parametrize("anisotropic,vertical", [(True, True), (False, True), (True, False)])
def test_tool_ruled_out_only_by_a_significant_anisotropy_on_a_vertical_tool(anisotropic, vertical):
    # Two fits that match the gap equally: tool bending (2 parameters) is preferred by parsimony unless the machine
    # compliance found differs between X and Y by more than Z_SIGNATURE sigma while the tool stands along machine Z.
    from trueaxis.diagnose.analysis import _prefer

    g = np.random.default_rng(0).normal(0, 1, 300)
    pred = 0.9 * g
    cx, cy = (0.05, 0.03) if anisotropic else (0.05, 0.048)
    cov = np.diag([0.002**2, 0.002**2, 0.01**2])  # X - Y: 7 sigma, or 0.7 sigma
    force = _fake_fit("force_deflection", ["compliance_X", "compliance_Y", "compliance_Z"], [cx, cy, 0.0], cov,
                      pred.copy(), 3)
    tool = _fake_fit("tool_deflection", ["tip_compliance", "compliance_slope"], [0.04, 0.0],
                     np.diag([0.002**2, 0.001**2]), pred.copy(), 2)
    notes = []
    chosen, tied = _prefer(tool, [tool, force], g, vertical, notes)
    if anisotropic and vertical:
        assert chosen is force and tied == []
        assert notes and notes[0].startswith("tool_deflection ruled out") and "7.1 standard deviations" in notes[0]
    else:
        assert chosen is tool and tied == [force] and notes == []


def test_control_says_none_of_the_candidates(slots):
    m, prog, _ = slots
    r = _cut(m, prog, None, noise=1.0, seed=11)
    st = twin_state(r.measured, r.normals, m, prog.text, "slots", want_force=False)
    cands, _ = build_all([n for n in LIBRARY if n not in ("force_deflection", "tool_deflection")], st)
    diag = diagnose_state(st, cands)
    assert diag.verdict == "none of the candidates" and diag.chosen == []
    # ~200 independent neighbour pairs: the MAD scale scatters by ~10 %, so 3 sigma is 30 %.
    assert estimate_noise_um(st) == pytest.approx(1.0, rel=0.3)


def test_report_schema_and_cli(slots, tmp_path):
    from trueaxis.cli import main

    m, prog, _ = slots
    r = _cut(m, prog, {"backlash": {"Y": {"amplitude": 8.0}}}, noise=1.0, seed=5, points=300)
    write_cmm(r, tmp_path / "cmm.ply")
    (tmp_path / "p.ngc").write_text(prog.text)
    out = tmp_path / "rep"
    rc = main(["diagnose", "--cloud", str(tmp_path / "cmm.ply"), "--part", "slots", "--machine", "xh714",
               "--program", str(tmp_path / "p.ngc"), "--candidates", "backlash_x,backlash_y,thermal_x,twin_parameters",
               "--noise-um", "1.0", "-o", str(out)])
    assert rc == 0
    data = json.loads((out / "diagnosis.json").read_text())
    assert (out / "diagnosis.html").read_text().count("data:image/png") >= 3
    assert {"where", "chosen", "candidates", "gap_um", "shrink"} <= set(data)
    assert data["where"][0]["variable"] and "held_out_r2" in data["where"][0]
    assert data["chosen"][0]["effect"] == "backlash_y" and 0 < data["chosen"][0]["confidence"] <= 1
    assert {"rms", "p95", "max"} <= set(data["gap_um"]["before"]) and data["gap_um"]["after"]["rms"] < \
        data["gap_um"]["before"]["rms"]
    p = data["chosen"][0]["parameters"][0]
    assert p["value_um"] == pytest.approx(8.0, abs=1.5) and p["std_um"] > 0


@pytest.mark.parametrize("extra,msg", [
    (["--candidates", "backlash_q"], "unknown"),
    (["--noise-um", "-1"], "noise"),
    (["--cloud-missing"], None),
])
def test_cli_refuses_bad_input_with_exit_2(tmp_path, capsys, extra, msg):
    from trueaxis.cli import main

    (tmp_path / "p.ngc").write_text("G0 X0\n")
    (tmp_path / "c.xyz").write_text("0 0 0\n1 0 0\nnan 0 0\n")
    args = ["diagnose", "--cloud", str(tmp_path / ("nope.ply" if extra == ["--cloud-missing"] else "c.xyz")),
            "--part", "slots", "--machine", "xh714", "--program", str(tmp_path / "p.ngc"), "-o", str(tmp_path / "r")]
    if msg == "noise":  # an option out of range: argparse's usage error
        with pytest.raises(SystemExit) as stop:
            main(args + extra)
        assert stop.value.code == 2
        return
    rc = main(args + ([] if extra == ["--cloud-missing"] else extra))
    assert rc == 2  # usage: an unknown candidate (an option's value), a cloud that does not exist (a path)
    err = capsys.readouterr().err
    assert err.strip() and "Traceback" not in err
    if msg:
        assert msg in err
    assert not (tmp_path / "r").exists()


def _synthetic(slots, parts, noise=1.0, seed=0):
    """The slot block's twin state with a gap made of the candidates' own columns (name -> parameter vector) plus
    noise: a check of the judgement alone, without the shop's richer forms."""
    m, prog, base = slots
    st = twin_state(base.points, base.normals, m, prog.text, "slots", want_force=False)
    names = ["backlash_x", "backlash_y", "thermal_x", "thermal_y", "thermal_z", "twin_parameters"]
    cands, _ = build_all(names, st)
    by = {c.name: c for c in cands}
    g = np.random.default_rng(seed).normal(0.0, noise, len(st))
    for name, theta in parts.items():
        g = g + by[name].columns @ np.asarray(theta, float)
    st.gap_um = g
    return st, cands


def test_second_effect_kept_only_when_it_clearly_helps(slots):
    # Backlash Y of 8 um with a Z drift: a drift of a few tenths of a um is below what a second effect must add
    # (a share of the first one's gain and Z_PAIR on held-out points), one of several um is named with it.
    st, cands = _synthetic(slots, {"backlash_y": [8.0], "thermal_z": [0.3, 0.6, 0.9]})
    diag = diagnose_state(st, cands, noise_um=1.0)
    assert diag.chosen == ["backlash_y"]
    st, cands = _synthetic(slots, {"backlash_y": [8.0], "thermal_z": [3.0, 6.0, 9.0]})
    diag = diagnose_state(st, cands, noise_um=1.0)
    assert sorted(diag.chosen) == ["backlash_y", "thermal_z"]
    f = diag.chosen_fit
    last = [i for i, p in enumerate(f.parameters) if p.startswith("drift_Z")][-1]
    assert f.value[last] == pytest.approx(9.0, abs=3 * f.std[last] + 0.5)


def test_compliances_are_bounded_to_physical_signs(slots):
    # A gap that a *negative* lateral compliance would mimic: the bounded fit stays at zero and the candidate is
    # flagged not plausible (the tool would be pulled into the material).
    from trueaxis.diagnose.analysis import fit_candidate, make_folds

    m, prog, base = slots
    st = twin_state(base.points, base.normals, m, prog.text, "slots", force_stride=200)
    force = build("force_deflection", st)
    tool = build("tool_deflection", st)
    assert force.parameters == ["compliance_X", "compliance_Y", "compliance_Z"]
    assert force.plausible[0][0] == 0.0 and force.plausible[1][0] == 0.0 and tool.plausible[0][0] == 0.0
    g = force.columns @ np.array([-0.05, -0.05, 0.0]) + np.random.default_rng(1).normal(0, 0.3, len(st))
    f = fit_candidate([force], g, make_folds(st))
    assert not f.plausible
    assert np.all(f.value[:2] >= -1e-12) and np.all(f.value[:2] < 0.01)
    # A positive, anisotropic one is fitted inside the bounds, and its X - Y difference is seen.
    g = force.columns @ np.array([0.04, 0.02, 0.0]) + np.random.default_rng(2).normal(0, 1.0, len(st))
    f = fit_candidate([force], g, make_folds(st))
    assert f.plausible
    assert f.difference_z("compliance_X", "compliance_Y") > 4.0


def test_servo_filters_reproduce_a_first_order_loop_transient():
    # A step of the commanded velocity (a move starting from rest, or the component of a corner): the candidate's
    # filtered velocity is v0 (1 - exp(-t/tau)) exactly, and a first-order loop (the shop's, without limits) follows
    # with the error tau w, to within dt/2 of tau.
    from types import SimpleNamespace

    from trueaxis.diagnose.state import lag_filtered_velocity
    from trueaxis.sim.effects import _servo_axis

    dt, v0, k0, T = 1e-3, 16.7, 50, 400
    v = np.where(np.arange(T) >= k0, v0, 0.0)
    q = np.cumsum(v) * dt  # q[k] - q[k-1] = v0 dt from k0 on
    traj = SimpleNamespace(q=q[:, None], dt=dt, motion=np.ones(T, int))
    taus = (0.004, 0.0125, 0.035)
    w = lag_filtered_velocity(traj, taus)[:, 0, :]
    t = np.arange(T) * dt - (k0 - 1) * dt  # time since the velocity step (held over the period ending at k0)
    for m, tau in enumerate(taus):
        expect = np.where(t > 0, v0 * (1.0 - np.exp(-np.maximum(t, 0.0) / tau)), 0.0)
        np.testing.assert_allclose(w[:, m], expect, atol=1e-9 * v0)
    # The loop of lag time 12.5 ms (Kv 80 /s): following error against tau w over the transient.
    e = q - _servo_axis(q, 80.0, None, dt)
    np.testing.assert_allclose(e, taus[1] * w[:, 1], atol=0.05 * v0 * taus[1])
    # A rapid's velocity is taken as settled.
    traj.motion = np.where(np.arange(T) < 200, 0, 1)
    assert np.all(lag_filtered_velocity(traj, taus)[:200] == 0.0)


def test_servo_lag_corner_transient_is_named(slots):
    # The shop's loop (acceleration-limited, rapids planned) with equal gains but Y 10 % slower: the corners of the
    # slots are cut inside by ln2 sin(theta/2) v/Kv, the diagonal leg shows the mismatch. Named servo_lag, the lag
    # time and the mismatch recovered.
    kv = {"X": 80.0, "Y": 80.0 / 1.1, "Z": 80.0}
    diag, state = _named(slots, {"servo": {"kv_per_s": kv, "accel": {"X": 2000.0, "Y": 2000.0, "Z": 2000.0}}})
    assert diag.chosen == ["servo_lag"]
    assert diag.shrink_above_noise > 0.8
    fit = diag.chosen_fit
    lag = sum(v for p, v in zip(fit.parameters, fit.value) if p.startswith("lag_") and "mismatch" not in p)
    assert 9.0 < lag < 16.0  # ms; the loop's is 12.5
    assert fit.value[fit.parameters.index("lag_mismatch_Y")] == pytest.approx(1.25, abs=0.6)
