"""Flyers (points that are no measurement of the surface) are set apart by one rule (``trueaxis.inspect.flyers``)
before the diagnosis and before ``inspect --identify``'s identification, and said: a few flyers turned a backlash
named at 1.00 into "none of the candidates" and an XOC change of +20 um into "NO CHANGE", silently (a QA pass)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from conftest import MACHINES
from trueaxis.inspect.flyers import LOCAL_K, screen_flyers
from trueaxis.machine import load_machine
from trueaxis.machine.machine_file import dump_machine


def _plane(n_side=60, noise=1.0, seed=0, step_um=0.0):
    """A 60 x 60 grid (1 mm pitch) on a plane, its deviation the noise plus a smooth ramp and, with step_um, a step
    along a line across it (a backlash reversal)."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n_side, dtype=float), np.arange(n_side, dtype=float))
    pts = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    normals = np.tile([0.0, 0.0, 1.0], (x.size, 1))
    dev = rng.normal(0.0, noise, x.size) + 0.1 * pts[:, 0] + step_um * (pts[:, 0] + 0.3 * pts[:, 1] > 30.0)
    return pts, normals, dev


@pytest.mark.parametrize("step_um", [0.0, 3.0, 10.0, 30.0])
@pytest.mark.parametrize("noise", [1.0, 0.0])
def test_a_clean_cloud_loses_no_point_steps_included(step_um, noise):
    pts, normals, dev = _plane(noise=noise, step_um=step_um, seed=int(step_um))
    screen = screen_flyers(pts, normals, dev)
    assert screen.n_apart == 0 and screen.sentence() is None


def test_flyers_beyond_the_gate_and_within_it_are_set_apart_and_said():
    pts, normals, dev = _plane(seed=7, step_um=10.0)
    rng = np.random.default_rng(1)
    far = rng.choice(dev.size, 3, replace=False)
    near = rng.choice(np.setdiff1d(np.arange(dev.size), far), 60, replace=False)
    near[1] = near[0] + 1  # two flyers side by side (a QA cloud's random ones held such pairs)
    dev[far] += 1000.0
    dev[near] += 20.0 * rng.choice([-1.0, 1.0], near.size)
    screen = screen_flyers(pts + (dev / 1000.0)[:, None] * normals, normals, dev)
    assert set(np.flatnonzero(screen.beyond_gate)) == set(far)
    assert set(np.flatnonzero(screen.local)) == set(near)
    info = screen.as_dict()
    n = len(set(near)) + 3
    assert info["set_apart"] == n and info["beyond_gate_largest_um"] > 990 and abs(info["local_largest_um"]) > 15
    said = screen.sentence("the diagnosis")
    assert said.startswith(f"{n} of 3600 points set apart as flyers and left out of the diagnosis: 3 beyond the 0.5 mm "
                           "gate") and f"more than {LOCAL_K:g} robust sigma" in said


@pytest.fixture(scope="module")
def cone_cut(tmp_path_factory):
    """nmv1500dcg's cone program (geometric), cut with an 8 um backlash of X and on a machine whose XOC is 20 um
    from the twin's, 1500 points at 1 um noise each."""
    from trueaxis.cli import main

    d = tmp_path_factory.mktemp("flyers")
    twin = load_machine(MACHINES / "nmv1500dcg.toml")
    v = twin.parameter_values().copy()
    v[twin.parameter_names().index("XOC")] += 20.0
    (d / "xoc.toml").write_text(dump_machine(twin.with_parameters(v)))
    (d / "bx.toml").write_text("[backlash.X]\namplitude = 8.0\ntransition = 0.02\n")
    twin_file = str(MACHINES / "nmv1500dcg.toml")
    assert main(["program", "nas979", "--machine", twin_file, "-o", str(d / "cone.ngc")]) == 0
    for name, machine, effects in (("bx", twin_file, ["--effects", str(d / "bx.toml")]),
                                   ("xoc", str(d / "xoc.toml"), [])):
        assert main(["simulate", str(d / "cone.ngc"), "--machine", machine, *effects, "--part", "nas979", "-o",
                     str(d / f"{name}.ply"), "--points", "1500", "--noise-um", "1", "--seed", "3"]) == 0
    return d


def _with_flyers(src, dst, n_far=3, n_near=30, seed=0):
    """The cloud with n_far points moved 1 mm and n_near 0.3 mm (within the inspection's gate) along their normals."""
    from trueaxis.inspect.cloud import read_cloud, write_cloud_ply

    c = read_cloud(src)
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(c.points), n_far + n_near, replace=False)
    pts = c.points.copy()
    pts[idx[:n_far]] += 1.0 * c.normals[idx[:n_far]]
    pts[idx[n_far:]] += 0.3 * c.normals[idx[n_far:]]
    write_cloud_ply(dst, pts, c.normals)


def test_the_diagnosis_sets_flyers_apart_and_says_so(cone_cut, tmp_path, capsys):
    from trueaxis.cli import main

    d = cone_cut
    _with_flyers(d / "bx.ply", tmp_path / "fly.ply")
    capsys.readouterr()
    assert main(["diagnose", "--cloud", str(tmp_path / "fly.ply"), "--part", "nas979", "--machine",
                 str(MACHINES / "nmv1500dcg.toml"), "--program", str(d / "cone.ngc"), "-o", str(tmp_path / "rep"),
                 "--candidates", "backlash_x,backlash_y,servo_lag,thermal_x,twin_parameters"]) == 0
    cap = capsys.readouterr()
    data = json.loads((tmp_path / "rep" / "diagnosis.json").read_text())
    # "none" (0.60) with them; (the candidates given: the confidence the whole library's rules give is recorded)
    assert data["verdict"] == "backlash_x" and data["confidence_basis"]["uncapped_confidence"] > 0.9
    said = re.search(r"33 of (\d+) points set apart as flyers and left out of the diagnosis: 3 beyond the 0.5 mm gate",
                     cap.err)
    (flyers,) = data["flyers_set_apart"]
    assert said and flyers["beyond_gate"] == 3 and flyers["local"] == 30 and data["points"] == int(said.group(1)) - 33
    assert any("set apart as flyers" in w for w in data["warnings"])
    assert "set apart as flyers" in (tmp_path / "rep" / "diagnosis.html").read_text()


def test_inspect_identify_sets_flyers_apart_and_says_so(cone_cut, tmp_path, capsys):
    from trueaxis.cli import main

    d = cone_cut
    _with_flyers(d / "xoc.ply", tmp_path / "fly.ply", n_far=10, n_near=0)
    capsys.readouterr()
    # (the shop sets the part up exactly, and the user says so: with the set-up free, XOC's 20 um, mostly a
    # translation of the cone that its value alone does not fix, is held since 2026-11-28)
    assert main(["inspect", str(tmp_path / "fly.ply"), "--part", "nas979", "--identify", "--machine",
                 str(MACHINES / "nmv1500dcg.toml"), "--program", str(d / "cone.ngc"), "-o", str(tmp_path / "rep"),
                 "--setup-sigma-um", "0"]) == 0
    cap = capsys.readouterr()
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())["identification"]
    assert rep["verdict"]["status"] == "accepted", rep["verdict"]  # "NO CHANGE", noise 173 um, with the flyers
    xoc = next(p for p in rep["parameters"] if p["name"] == "XOC")
    assert xoc["change_um"] == pytest.approx(20.0, abs=3 * xoc["std_um"] + 1.0)
    assert rep["flyers_set_apart"]["beyond_gate"] == 10
    assert re.search(r"10 of \d+ points set apart as flyers and left out of the identification", cap.err)


def test_the_residual_note_names_the_parameters_kept_as_a_second_cause():
    # A residual above the cloud's noise was always said to be an effect the twin's parameters do not describe; on a
    # slot block whose parameters were only held back (not significant against a set-up offset, or the set-up's) the
    # twin describes it, and the note sent the user to `diagnose` alone (a QA pass). With parameters kept, both causes.
    from trueaxis.inspect.flyers import LOCAL_TO_NOISE, UNEXPLAINED_FACTOR, residual_above_noise_note

    local = 1.0 * LOCAL_TO_NOISE  # a cloud noise of 1 um
    assert residual_above_noise_note(UNEXPLAINED_FACTOR * 0.99, local) is None
    plain = residual_above_noise_note(2.21, local)
    assert plain.startswith("the identification leaves 2.21 um RMS, above the cloud's own noise (1.00 um")
    assert plain.endswith("do not describe; `trueaxis diagnose` looks for it")
    kept = residual_above_noise_note(2.21, local, kept=["EZZ@-300", "YOC"])
    assert "either the part holds an effect" in kept and "changes of the parameters kept (EZZ@-300, YOC)" in kept
    assert "--setup-sigma-um" in kept and "`trueaxis diagnose`" in kept
    # the set-up's accuracy given: not advised again (a QA pass read the advice after giving --setup-sigma-um 0)
    given = residual_above_noise_note(2.21, local, kept=["EZZ@-300"], setup_given=True)
    assert "--setup-sigma-um" not in given and "a second placement of the part separates them" in given


def test_a_few_points_on_another_surface_are_not_flyers_against_their_nearest_points():
    # A QA pass: 22 exact probe points on the block's datum faces beside a cone scan were set apart as flyers (0.0 um
    # each): their nearest points were the cone's, 35 um off. With the surface each point is measured against, the
    # neighbours are those on its own surface and a surface of a few points is not screened; a real flyer among the
    # many points of a surface is still found, and without the labels the screen is as before.
    pts, _, d = _plane(noise=1.0, seed=3)
    d = d + 35.0  # the scanned surface 35 um off
    datum = np.column_stack([np.linspace(0.0, 59.0, 22), np.full(22, -0.5), np.zeros(22)])  # beside it, sparse, exact
    pts, d = np.vstack([pts, datum]), np.r_[d, np.zeros(22)]
    surface = np.r_[np.zeros(len(d) - 22, int), np.ones(22, int)]
    d[100] += 40.0  # one flyer on the scanned surface
    unlabelled = screen_flyers(pts, None, d)
    assert unlabelled.local[-22:].sum() > 0  # the datum points against the scan's (the QA's case)
    labelled = screen_flyers(pts, None, d, surface=surface)
    assert not labelled.local[-22:].any() and labelled.local[100]
    assert labelled.local.sum() == 1


def test_a_noise_free_cloud_is_said_as_such_not_as_an_effect_the_twin_lacks():
    # A QA pass: a noise-free virtual-shop cloud was refused by the identification as driven by "a backlash, a servo
    # lag", the note reading "above the cloud's own noise (0.00 um)". Said as a cloud without probe noise.
    from trueaxis.inspect.flyers import residual_above_noise_note

    note = residual_above_noise_note(0.52, 0.001, kept=["XOC"])
    assert note.startswith("the cloud shows no probe noise (0.001 um between neighbouring points)") and \
        "simulate --noise-um" in note and "diagnose" not in note
    assert "above the cloud's own noise (0.50 um" in residual_above_noise_note(1.5, 0.5 * 1.0934, kept=["XOC"])
