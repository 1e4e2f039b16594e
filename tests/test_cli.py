"""The command line: trueaxis error / machine show / inspect, exit statuses."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import DATA

BC = str(DATA / "bc_table.toml")


def run(*args):
    return subprocess.run([sys.executable, "-m", "trueaxis.cli", *args], capture_output=True, text=True)


def test_python_m_trueaxis_runs_the_console_script_entry_point():
    """``python -m trueaxis`` failed ("No module named trueaxis.__main__"): it runs the same entry point as the
    console script ``trueaxis`` (pyproject: trueaxis.cli:run), its help, version and exit statuses."""
    r = subprocess.run([sys.executable, "-m", "trueaxis", "--help"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout == run("--help").stdout and r.stdout.startswith("usage: trueaxis ") and "inspect" in r.stdout
    r = subprocess.run([sys.executable, "-m", "trueaxis", "--version"], capture_output=True, text=True)
    from trueaxis import __version__

    assert (r.returncode, r.stdout.strip()) == (0, f"trueaxis {__version__}")
    r = subprocess.run([sys.executable, "-m", "trueaxis", "no-such-command"], capture_output=True, text=True)
    assert r.returncode == 2 and "invalid choice: 'no-such-command'" in r.stderr


def test_error_json_follows_design_conventions(tmp_path):
    machine = tmp_path / "m.toml"
    machine.write_text((DATA / "bc_table.toml").read_text().split("[location]")[0] + "[location]\nC0Y = 100.0\n")
    r = run("error", "--machine", str(machine), "--at", "X=0,Y=100,Z=0,B=0,C=0", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    np.testing.assert_allclose(out["position_error_um"], [-10.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(out["tool_axis_error_urad"], [0.0, 0.0, 0.0], atol=1e-9)


def test_error_reads_rotary_words_in_degrees_and_forces_in_newtons():
    from trueaxis.machine import ErrorTwin, load_machine

    r = run("error", "--machine", BC, "--at", "X=10,Y=-20,Z=-50,B=-30,C=45", "--force-n", "100,0,-50", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    dp, du = ErrorTwin(load_machine(BC)).volumetric_error(
        np.array([[10, -20, -50, np.radians(-30), np.radians(45)]]), force_n=[100, 0, -50])
    np.testing.assert_allclose(out["position_error_um"], dp[0], rtol=1e-12)
    np.testing.assert_allclose(out["tool_axis_error_urad"], du[0], rtol=1e-12)


@pytest.mark.parametrize("at, message", [("Q=1", "no axis Q"), ("X=abc", "is not a number"), ("X", "AXIS=VALUE"),
                                         # not an assumed 0, a last value winning, nor an extrapolated table
                                         ("X=50,Y=20,Z=-80", "missing: B C"), ("X=1,X=2", "X given twice"),
                                         ("X=500,Y=20,Z=-80,B=-30,C=45", "X=500 lies outside its travel [-200, 200] mm")])
def test_error_refuses_bad_poses_with_exit_2(at, message):
    r = run("error", "--machine", BC, "--at", at)
    assert r.returncode == 2
    assert message in r.stderr and "Traceback" not in r.stderr


def test_machine_show_lists_parameters_with_units():
    r = run("machine", "show", BC)
    assert r.returncode == 0, r.stderr
    assert "XOC" in r.stdout and "um" in r.stdout and "urad" in r.stdout


def test_inspect_refuses_a_missing_cloud_with_one_line_and_exit_2(tmp_path):
    r = run("inspect", str(tmp_path / "cloud.ply"), "--part", "nas979", "-o", str(tmp_path / "rep"))
    assert r.returncode == 2 and "cannot read the file" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "rep").exists()


def test_inspect_console_script_is_trueaxis_inspect(tmp_path, capsys):
    from trueaxis.cli import inspect_main

    assert inspect_main([str(tmp_path / "none.xyz"), "--part", "slots"]) == 2
    assert "trueaxis inspect:" in capsys.readouterr().err


def _caliper_models():
    """The lathe paper's four printed response surfaces, read from the paper's CSV: {(load sign, motion): coeffs}."""
    import csv

    from conftest import ROOT

    lines = (ROOT / "fixtures" / "papers" / "lathe_caliper_models.csv").read_text().splitlines()
    rows = csv.DictReader(line for line in lines if not line.startswith("#"))
    return {(r["load_sign"], r["motion"]): [float(r[k]) for k in ("c0", "c1_x", "c2_p", "c3_x2", "c4_xp", "c5_p2")]
            for r in rows}


@pytest.mark.parametrize("sign", ["+", "-"])
@pytest.mark.parametrize("direction", ["forward", "backward"])
def test_error_direction_reaches_each_of_the_lathe_papers_four_models(sign, direction):
    # The lathe's Z error under a load Pz minus its Z error without load is the paper's printed surface, evaluated by
    # hand here: dZ (mm) = c0 + c1 X + c2 P + c3 X^2 + c4 X P + c5 Pz^2, P = +-Pz in kN (the CSV's own rule).
    from conftest import MACHINES

    lathe = str(MACHINES / "lathe.toml")
    x, pz = 120.0, 0.8
    P = pz if sign == "+" else -pz
    c = _caliper_models()[(sign, direction)]
    expected_um = 1000.0 * (c[0] + c[1] * x + c[2] * P + c[3] * x**2 + c[4] * x * P + c[5] * pz**2)
    loaded = run("error", "--machine", lathe, "--at", f"X={x:g},Z=-200", f"--force-n=0,0,{1000 * P:g}",
                 "--direction", direction, "--json")
    free = run("error", "--machine", lathe, "--at", f"X={x:g},Z=-200", "--direction", direction, "--json")
    assert loaded.returncode == 0 and free.returncode == 0, loaded.stderr + free.stderr
    dz = json.loads(loaded.stdout)["position_error_um"][2] - json.loads(free.stdout)["position_error_um"][2]
    assert dz == pytest.approx(expected_um, abs=1e-9)
    # The four models differ by microns here, so the wrong one cannot pass.
    others = [1000.0 * (k[0] + k[1] * x + k[2] * (pz if s == "+" else -pz) + k[3] * x**2
                        + k[4] * x * (pz if s == "+" else -pz) + k[5] * pz**2)
              for (s, m), k in _caliper_models().items() if (s, m) != (sign, direction)]
    assert min(abs(dz - o) for o in others) > 0.5


def test_error_direction_is_refused_when_not_forward_or_backward():
    r = run("error", "--machine", BC, "--at", "X=1", "--direction", "sideways")
    assert r.returncode == 2 and "Traceback" not in r.stderr


def test_machine_nominal_writes_the_error_free_twin_a_loop_starts_from(tmp_path):
    from trueaxis.machine import ErrorTwin, load_machine
    from trueaxis.resources import machine_file

    out = tmp_path / "zero.toml"
    r = run("machine", "nominal", "nmv1500dcg", "-o", str(out))
    assert r.returncode == 0, r.stderr
    zero, full = load_machine(out), load_machine(machine_file("nmv1500dcg"))
    assert zero.axis_names == full.axis_names and zero.parameter_names() == full.parameter_names()
    assert not np.any(zero.parameter_values()) and np.any(full.parameter_values())
    assert zero.loaded is None and zero.compliance_um_per_n is None and not zero.surfaces
    q = np.array([[10.0, -20.0, -150.0, 0.3, 1.1], [-40.0, 30.0, -90.0, -0.5, -2.0]])
    p, u = ErrorTwin(zero).actual_pose(q)
    pn, un = ErrorTwin(zero).nominal_pose(q)
    assert np.array_equal(p, pn) and np.array_equal(u, un)  # no error anywhere: the nominal chain itself
    assert np.linalg.norm(ErrorTwin(full).actual_pose(q)[0] - pn, axis=1).min() > 1e-3  # (the fixture's errors: um)


def test_demo_takes_its_output_folder_as_o_like_every_other_command():
    from trueaxis.cli import build_parser

    ap = build_parser()
    assert ap.parse_args(["demo", "-o", "here"]).out == "here" == ap.parse_args(["demo", "--out", "here"]).out
    assert ap.parse_args(["demo"]).out == "demo_out"
