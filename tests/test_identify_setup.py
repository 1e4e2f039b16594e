"""The part's set-up offset in the identification: a part clamped a few um off (or a work offset set a few um off)
moves everything the program cut by a constant translation. It is fitted as nuisance (a prior of a few um), reported
and never written; it must not come out as axis errors. Found by a QA pass: on the slot block a 3 um offset along Y
was ACCEPTED as EYY.P1 +11.2, EYX@400 +6.0, C0Y +6.2 (7 to 75 std from their truth, 0), and the full case wrote an
A0Z of 1000 urad. Run as a user does: program, simulate, inspect --identify --write."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from conftest import CUTTING_C45, MACHINES, mill_toml
from trueaxis.machine import load_machine

NOISE_UM = 1.0

# A three-axis vertical mill (the QA's): its error-free twin, and the true machine with real axis errors. Note EYX
# = 3 um at X = 0: the machine files' convention holds every component error at 0 at its axis' zero (its gauge), so
# in the twin's terms this truth is EYX@400 = -3 um plus a constant 3 um along Y, which no parameter may take: a
# set-up offset of the part.
VMC = mill_toml("shop VMC-1", ((-400.0, 400.0), (-250.0, 250.0), (-400.0, 50.0)), """flutes = 4
flute_length = 30.0

[workpiece]
origin = [0.0, 0.0, 0.0]

[location]
C0Y = %(C0Y)s
B0Z = %(B0Z)s

[component.X]
at = [-400.0, 0.0, 400.0]
EXX = [%(EXX)s]
EYX = [%(EYX)s]

[component.Y]
legendre = { EYY = [%(EYY)s] }

[component.Z]
at = [-400.0, 50.0]
EZZ = [%(EZZ)s, 0.0]

""" + CUTTING_C45)
TWIN = dict(C0Y=0.0, B0Z=0.0, EXX="0.0, 0.0, 0.0", EYX="0.0, 0.0, 0.0", EYY="0.0, 0.0", EZZ=0.0)
# the twin plus a constant 3 um along Y (the Legendre series' constant term, a gauge value): a pure set-up offset
SHIFTED = dict(TWIN, EYY="3.0, 0.0")
TRUE = dict(C0Y=50.0, B0Z=-30.0, EXX="-20.0, 0.0, 20.0", EYX="0.0, 3.0, 0.0", EYY="0.0, 10.0", EZZ=8.0)
# the truth in the twin's gauge (each component error 0 at its axis' zero), over the part (X > 0)
TRUE_IN_GAUGE = {"C0Y": 50.0, "B0Z": -30.0, "EXX@400": 20.0, "EYX@400": -3.0, "EYY.P1": 10.0, "EZZ@-400": 8.0}


def _cli(*args) -> int:
    from trueaxis.cli import main

    return main([str(a) for a in args])


def _identification(folder) -> dict:
    return json.loads((folder / "report.json").read_text())["identification"]


def _values(path) -> dict:
    m = load_machine(path)
    return dict(zip(m.parameter_names(), m.parameter_values()))


@pytest.fixture(scope="module")
def vmc(tmp_path_factory):
    """Folder with the twin, the slot program posted with it and the shifted machine's cut, 4000 points at 1 um."""
    d = tmp_path_factory.mktemp("vmc")
    (d / "twin.toml").write_text(VMC % TWIN)
    (d / "shifted.toml").write_text(VMC % SHIFTED)
    (d / "true.toml").write_text(VMC % TRUE)
    assert _cli("program", "slots", "--machine", d / "twin.toml", "-o", d / "slots.ngc") == 0
    return d


def _inspect(folder, cloud, part, program, name):
    out = folder / f"{name}.toml"
    code = _cli("inspect", cloud, "--part", part, "--identify", "--machine", folder / "twin.toml", "--program",
                program, "--write", out, "-o", folder / f"rep_{name}")
    return code, out, _identification(folder / f"rep_{name}")


def _slots_identified(vmc, name, seed, capsys):
    """The slot program cut on the machine ``name``.toml of the folder (4000 points, NOISE_UM, ``seed``), inspected
    and identified against the twin: (exit code, written twin, report's identification, what the terminal said)."""
    assert _cli("simulate", vmc / "slots.ngc", "--machine", vmc / f"{name}.toml", "--part", "slots", "-o",
                vmc / f"{name}.ply", "--noise-um", NOISE_UM, "--points", 4000, "--seed", seed) == 0
    capsys.readouterr()
    code, out, rep = _inspect(vmc, vmc / f"{name}.ply", "slots", vmc / "slots.ngc", name)
    return code, out, rep, capsys.readouterr().out


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_set_up_offset_of_the_slot_block_is_no_axis_error(vmc, capsys):
    # The QA's reproduction: the true machine is the twin plus a constant 3 um along Y. Nothing about the axes
    # changed: the written twin is the twin, and the offset is reported as the part's set-up offset.
    code, out, rep, printed = _slots_identified(vmc, "shifted", 2, capsys)
    assert code == 0, printed
    assert rep["verdict"]["status"] == "no change" and rep["parameters"] == []
    assert _values(out) == _values(vmc / "twin.toml")
    setup = rep["setup_offset"]
    assert setup["TY_um"] == pytest.approx(3.0, abs=0.3)
    assert abs(setup["TX_um"]) < 0.3 and abs(setup["TZ_um"]) < 0.3
    # the residual with the set-up offset is the probe noise
    assert rep["verdict"]["residual_after_rms_um"] < 1.2 * NOISE_UM < rep["verdict"]["residual_before_rms_um"]
    assert "set-up offset of the part (free; fitted, not written): " in printed and "TY +" in printed


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_real_axis_errors_beside_a_constant_are_identified_and_the_constant_is_the_set_up(vmc, capsys):
    # The QA's full case: real axis errors, and a constant 3 um along Y (EYX at X = 0) that the twin's gauge leaves
    # to the set-up. The written values are the truth in the twin's gauge within 3 std (EYY.P1 came out 21.2 +- 0.25
    # um, truth 10, and another run wrote A0Z = 1014 urad: the constant taken by axis errors); the constant is the
    # set-up offset; and what the part cannot tell from a set-up offset (EZZ@-400: a constant along Z at the slots'
    # depth) is not written.
    code, out, rep, printed = _slots_identified(vmc, "true", 3, capsys)
    assert code == 0, printed
    assert rep["verdict"]["status"] == "accepted"
    written, twin = _values(out), _values(vmc / "twin.toml")
    changed = {p["name"]: p for p in rep["parameters"]}
    assert {"C0Y", "EXX@400", "EYY.P1"} <= set(changed)
    for name, p in changed.items():
        std = p.get("std_um", p.get("std_urad"))
        assert abs(written[name] - TRUE_IN_GAUGE.get(name, 0.0)) <= 3 * std, (name, written[name], std)
    assert all(written[n] == twin[n] for n in written if n not in changed)
    assert "A0Z" not in changed and "EZZ@-400" not in changed
    assert rep["setup_offset"]["TY_um"] == pytest.approx(3.0, abs=0.3)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_set_up_offset_of_the_cone_is_no_axis_error(tmp_path, capsys):
    # The NAS 979 cone cut on a machine equal to its twin, the part measured 3, -2, 4 um off in its frame (the
    # cloud translated): no axis error is written, the offset is the part's set-up offset.
    twin = MACHINES / "nmv1500dcg.toml"
    (tmp_path / "twin.toml").write_text(twin.read_text())
    assert _cli("program", "nas979", "--machine", twin, "-o", tmp_path / "cone.ngc", "--step-deg", 2,
                "--chord-tol-um", 0.2) == 0
    assert _cli("simulate", tmp_path / "cone.ngc", "--machine", twin, "--part", "nas979", "-o", tmp_path / "cut.ply",
                "--points", 3000, "--noise-um", 0.5, "--seed", 3) == 0
    from trueaxis.inspect.cloud import read_cloud, write_cloud_ply

    cloud = read_cloud(tmp_path / "cut.ply")
    offset_um = np.array([3.0, -2.0, 4.0])
    write_cloud_ply(tmp_path / "off.ply", cloud.points + offset_um * 1e-3, cloud.normals)
    capsys.readouterr()
    code, out, rep = _inspect(tmp_path, tmp_path / "off.ply", "nas979", tmp_path / "cone.ngc", "off")
    assert code == 0, capsys.readouterr().out
    assert rep["verdict"]["status"] == "no change" and rep["parameters"] == []
    assert _values(out) == _values(twin)
    setup = rep["setup_offset"]
    found = np.array([setup["TX_um"], setup["TY_um"], setup["TZ_um"]])
    assert np.all(np.abs(found - offset_um) < 0.5), found


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_part_set_up_off_writes_the_same_twin_as_one_set_up_right(tmp_path, capsys):
    # The default path: the cone posted with an error-free twin, cut by the nmv1500dcg fixture (tens of um of
    # location errors), measured once as cut and once 15 um off along Y (a part clamped off). With a set-up prior of
    # 5 um assumed when none was given, the shifted part was ACCEPTED with YOC 36.89 instead of 28.02 (truth 30),
    # the set-up reported as TY +0.27 +- 0.01, and the next part came out 10.7 um RMS instead of 3.4 (a QA pass).
    # The set-up's accuracy not given, the set-up offset is free: both parts write the same twin, and the shift is
    # the set-up's.
    true = MACHINES / "nmv1500dcg.toml"
    assert _cli("machine", "nominal", "nmv1500dcg", "-o", tmp_path / "twin.toml") == 0
    assert _cli("program", "nas979", "--machine", tmp_path / "twin.toml", "-o", tmp_path / "cone.ngc", "--step-deg",
                2, "--chord-tol-um", 0.2) == 0
    assert _cli("simulate", tmp_path / "cone.ngc", "--machine", true, "--part", "nas979", "-o", tmp_path / "cut.ply",
                "--points", 3000, "--noise-um", NOISE_UM, "--seed", 2) == 0
    from trueaxis.inspect.cloud import read_cloud, write_cloud_ply

    cloud = read_cloud(tmp_path / "cut.ply")
    write_cloud_ply(tmp_path / "off.ply", cloud.points + np.array([0.0, 0.015, 0.0]), cloud.normals)
    found = {}
    for name in ("cut", "off"):
        capsys.readouterr()
        code, out, rep = _inspect(tmp_path, tmp_path / f"{name}.ply", "nas979", tmp_path / "cone.ngc", name)
        printed = capsys.readouterr().out
        assert code == 0 and rep["verdict"]["status"] == "accepted", printed
        assert "set-up offset of the part (free; fitted, not written)" in printed
        assert "the set-up's accuracy was not given (--setup-sigma-um)" in rep["setup_offset"]["note"]
        found[name] = (_values(out), {p["name"]: p.get("std_um", p.get("std_urad")) for p in rep["parameters"]},
                       rep["setup_offset"]["TY_um"])
    (cut, std, ty_cut), (off, std_off, ty_off) = found["cut"], found["off"]
    assert set(std) == set(std_off) and {"YOC", "AOC"} <= set(std)
    for name in cut:  # the same twin: the shift moves no written value by a hundredth of its std
        assert abs(off[name] - cut[name]) <= 0.01 * std.get(name, 1.0), (name, cut[name], off[name])
    assert ty_off - ty_cut == pytest.approx(15.0, abs=0.3)  # (the shift moves the points along the surface too)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_translation_of_the_slot_block_is_the_free_set_ups_and_its_parameters_are_kept(tmp_path, capsys):
    # The slot block cut at one depth by the xh714 fixture from an error-free twin, the set-up's accuracy not given:
    # the squareness of Z moves the block only as a translation does there, so with the set-up offset free the
    # normal matrix was singular and the identification stopped ("9-th leading minor of the array is not positive
    # definite", exit 2). Those parameters are now the set-up's, kept and said; the rest is fitted.
    assert _cli("machine", "nominal", "xh714", "-o", tmp_path / "twin.toml") == 0
    assert _cli("program", "slots", "--machine", tmp_path / "twin.toml", "-o", tmp_path / "slots.ngc") == 0
    assert _cli("simulate", tmp_path / "slots.ngc", "--machine", MACHINES / "xh714.toml", "--part", "slots", "-o",
                tmp_path / "cut.ply", "--noise-um", NOISE_UM, "--points", 6000, "--seed", 1) == 0
    capsys.readouterr()
    code, out, rep = _inspect(tmp_path, tmp_path / "cut.ply", "slots", tmp_path / "slots.ngc", "cut")
    printed = capsys.readouterr().out
    # Fitted, not written: B0Z, mostly a translation at the block's one depth and so pinned only by what else it
    # does, comes out far beyond its typical size (truth -25 urad) and the fit is refused (a QA pass: written, it
    # made the next block 2-2.7 x worse).
    assert code == 3 and rep["verdict"]["status"] == "refused" and not out.exists(), printed
    assert re.search(r"B0Z [+-][\d.]+ \([\d.]+ x 20\)", rep["verdict"]["reasons"][0]), rep["verdict"]["reasons"]
    taken = {d["name"] for d in rep["not_identifiable_detail"] if d["category"] == "taken_by_setup"}
    assert taken and all(n.startswith(("EZZ", "EYZ", "EXZ", "A0Z", "B0Z")) for n in taken), taken
    assert "a translation of this part, the set-up's (free), kept: " in printed
    assert rep["verdict"]["residual_after_rms_um"] < 1.3 * NOISE_UM


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_far_change_with_the_set_up_free_is_refused(tmp_path, capsys):
    # The cone from an error-free twin, cut by the nmv1500dcg fixture with a backlash the twin lacks (4 um on X, 3 on
    # Y). With the set-up free the backlash drove YOC to +103 um (truth 30, 9 std off) against a set-up offset of
    # -132 um, and EXC.sin2 to -22 um (truth +0.7), ACCEPTED: the next cone came out 92 um RMS instead of 37 (a QA
    # pass). A change beyond 6 typical sizes is not taken from one part with the set-up free; with the set-up's accuracy given the same cloud gives YOC
    # within 3 std of its truth.
    from trueaxis.identify import IMPLAUSIBLE_TYPICAL

    (tmp_path / "bl.toml").write_text("[backlash.X]\namplitude = 4.0\ntransition = 0.02\n\n"
                                      "[backlash.Y]\namplitude = 3.0\ntransition = 0.02\n")
    assert _cli("machine", "nominal", "nmv1500dcg", "-o", tmp_path / "twin.toml") == 0
    assert _cli("program", "nas979", "--machine", tmp_path / "twin.toml", "-o", tmp_path / "cone.ngc") == 0
    assert _cli("simulate", tmp_path / "cone.ngc", "--machine", MACHINES / "nmv1500dcg.toml", "--effects",
                tmp_path / "bl.toml", "--part", "nas979", "-o", tmp_path / "cut.ply", "--points", 4000, "--noise-um",
                NOISE_UM, "--seed", 4) == 0
    capsys.readouterr()
    code, out, rep = _inspect(tmp_path, tmp_path / "cut.ply", "nas979", tmp_path / "cone.ngc", "free")
    printed = capsys.readouterr().out
    assert code == 3 and rep["verdict"]["status"] == "refused" and not out.exists(), printed
    far = re.findall(r"(\S+) ([+-][\d.]+) \(([\d.]+) x ([\d.]+)\)", rep["verdict"]["reasons"][0])
    assert far and all(float(k) > IMPLAUSIBLE_TYPICAL for _, _, k, _ in far), far
    assert "EXC.sin2" in [n for n, *_ in far]  # -22 um, truth +0.7 (11 typical sizes)
    assert "--setup-sigma-um" in rep["verdict"]["reasons"][0]
    code = _cli("inspect", tmp_path / "cut.ply", "--part", "nas979", "--identify", "--machine", tmp_path / "twin.toml",
                "--program", tmp_path / "cone.ngc", "-o", tmp_path / "rep_known", "--setup-sigma-um", 0)
    known = {p["name"]: p for p in _identification(tmp_path / "rep_known")["parameters"]}
    assert code == 0 and abs(known["YOC"]["value_um"] - 30.0) < 3 * known["YOC"]["std_um"]


def test_a_part_the_twin_does_not_explain_is_said_so_beside_the_verdict(tmp_path, capsys):
    # A backlash of 8 um on X, which no twin parameter describes: "no change" with a residual of 2.3 um against a
    # probe noise of 1 um said nothing of it (a QA pass; with the set-up offset free, the default since, the verdict
    # is "refused", the note the same). The note compares the residual with the cloud's own noise,
    # read from neighbouring points; the same part without the backlash gets no note.
    twin = MACHINES / "nmv1500dcg.toml"
    assert _cli("program", "nas979", "--machine", twin, "-o", tmp_path / "cone.ngc", "--step-deg", 2,
                "--chord-tol-um", 0.2) == 0
    (tmp_path / "bx.toml").write_text("[backlash.X]\namplitude = 8.0\ntransition = 0.02\n")
    notes = {}
    for name, effects in (("bx", ["--effects", tmp_path / "bx.toml"]), ("clean", [])):
        assert _cli("simulate", tmp_path / "cone.ngc", "--machine", twin, *effects, "--part", "nas979", "-o",
                    tmp_path / f"{name}.ply", "--points", 3000, "--noise-um", 1.0, "--seed", 4) == 0
        (tmp_path / "twin.toml").write_text(twin.read_text())
        capsys.readouterr()
        code, _, rep = _inspect(tmp_path, tmp_path / f"{name}.ply", "nas979", tmp_path / "cone.ngc", name)
        printed = capsys.readouterr().out
        # the backlash: refused (its fit does not hold on held-out points), the note beside it; the clean part: no
        # change (the set-up free, the default: a translation of YOC and the set-up would fit nothing of a backlash)
        assert (code, rep["verdict"]["status"]) == ((3, "refused") if name == "bx" else (0, "no change")), printed
        notes[name] = (rep.get("unexplained_note"), printed)
    note, printed = notes["bx"]
    noise = float(re.search(r"the cloud's own noise \(([\d.]+) um", note).group(1))
    assert 0.85 < noise < 1.15 and "trueaxis diagnose" in note and f"  note: {note}" in printed
    assert notes["clean"][0] is None and "note:" not in notes["clean"][1]
