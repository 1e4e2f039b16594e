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


@pytest.mark.parametrize("at, message", [("Q=1", "no axis Q"), ("X=abc", "is not a number"), ("X", "AXIS=VALUE")])
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
