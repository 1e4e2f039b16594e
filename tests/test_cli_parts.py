"""The command line of the test parts: ``trueaxis part``, ``trueaxis program``, ``trueaxis simulate``."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from conftest import CUTTING_C45, mill_toml
from trueaxis.cli import main

PERFECT_3AX = mill_toml("perfect 3-axis mill (test)", tail="""flutes = 4
flute_length = 30.0
[workpiece]
origin = [0.0, 0.0, -300.0]
""" + CUTTING_C45)

PERFECT_BC = """
[machine]
name = "perfect B-C table (test)"
kind = "mill"
format = 1
[kinematics]
bed_to_workpiece = ["B", "C"]
bed_to_tool = ["Y", "X", "Z"]
[axes]
X = { type = "linear", travel = [-200.0, 200.0] }
Y = { type = "linear", travel = [-150.0, 150.0] }
Z = { type = "linear", travel = [-300.0, 100.0] }
B = { type = "rotary", about = "Y", travel = [-120.0, 30.0], pivot = [0.0, 0.0, -100.0] }
C = { type = "rotary", about = "Z", pivot = [0.0, 0.0, 0.0] }
[tool]
length = 100.0
radius = 5.0
flutes = 4
flute_length = 30.0
[workpiece]
origin = [0.0, 0.0, 50.0]
"""


def _one_line_error(capsys):
    err = capsys.readouterr().err.strip()
    assert err and len(err.splitlines()) == 1 and "Traceback" not in err
    return err


# -------------------------------------------------------------------------------------------------------- part ----
@pytest.mark.parametrize("part", ["nas979", "slots"])
def test_part_writes_step_stl_json(tmp_path, capsys, part):
    param = "height=18" if part == "nas979" else "slot_depth=2.4"
    assert main(["part", part, "-o", str(tmp_path / "out"), "--param", param]) == 0
    files = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert files == [f"{part}.json", f"{part}.step", f"{part}.stl"]
    doc = json.loads((tmp_path / "out" / f"{part}.json").read_text())
    name, value = param.split("=")
    assert doc["parameters"][name] == float(value)
    assert doc["stl"]["chord_tolerance_mm"] > 0 and "chord tolerance" in capsys.readouterr().out


@pytest.mark.parametrize("param", ["height=abc", "nope=3", "height", "half_angle_deg=95", "height=200"])
def test_part_refuses_bad_params_with_exit_2_and_writes_nothing(tmp_path, capsys, param):
    out = tmp_path / "out"
    assert main(["part", "nas979", "-o", str(out), "--param", param]) == 2
    err = _one_line_error(capsys)
    assert err.startswith("trueaxis part:")
    assert not out.exists()


# ----------------------------------------------------------------------------------------------------- program ----
def test_program_nas979_writes_program_and_cl(tmp_path, capsys):
    out, cl = tmp_path / "cone.ngc", tmp_path / "cl.csv"
    assert main(["program", "nas979", "-o", str(out), "--cl", str(cl), "--compensate", "none", "--step-deg", "3",
                 "--chord-tol-um", "5", "--placement-mm", "5,-5", "--stock-um", "80"]) == 0
    text = out.read_text()
    assert "(trueaxis-setup: part=nas979 origin_mm=5.000,-5.000,50.000 placement_mm=5.000,-5.000" in text
    assert len(re.findall(r"\(trueaxis: ap=", text)) == 1  # 80 um of stock: the finishing pass alone
    assert cl.read_text().splitlines()[0] == "x,y,z,i,j,k,f"


def test_a_placement_at_negative_x_is_read_as_the_value_it_is(tmp_path, capsys):
    # "--placement-mm -5,5" (a placement at negative X) was read by argparse as an unknown option, exit 2.
    out = tmp_path / "cone.ngc"
    assert main(["program", "nas979", "-o", str(out), "--compensate", "none", "--step-deg", "4",
                 "--chord-tol-um", "5", "--placement-mm", "-5,5"]) == 0
    assert "placement_mm=-5.000,5.000" in out.read_text()


def test_the_cl_csv_a_program_writes_posts_with_its_rapids_as_rapids(tmp_path, capsys):
    """`program --cl` writes f = 0 on its rapids; `post` of that file reads them as rapids (it refused the file)."""
    out, cl, posted = tmp_path / "cone.ngc", tmp_path / "cl.csv", tmp_path / "posted.ngc"
    assert main(["program", "nas979", "-o", str(out), "--cl", str(cl), "--compensate", "none", "--step-deg", "3",
                 "--chord-tol-um", "5"]) == 0
    rows = [line.split(",") for line in cl.read_text().splitlines()[1:]]
    rapids = sum(float(r[6]) == 0.0 for r in rows)
    assert rapids >= 2  # the approach and the move between the passes
    from trueaxis.resources import machine_file

    assert main(["post", str(cl), "-o", str(posted), "--machine", str(machine_file("nmv1500dcg"))]) == 0
    moves = [ln for ln in posted.read_text().splitlines() if re.search(r"\bG0?[01]\b", ln)]
    assert sum(bool(re.search(r"\bG0?0\b", ln)) for ln in moves) == rapids


def test_program_refuses_bad_input(tmp_path, capsys):
    out = tmp_path / "p.ngc"
    assert main(["program", "nas979", "-o", str(out), "--placement-mm", "1,2,3"]) == 2
    assert "--placement-mm" in _one_line_error(capsys)
    assert main(["program", "nas979", "-o", str(out), "--machine", "xh714"]) == 2
    assert "five-axis" in _one_line_error(capsys)
    # the slot block on a lathe said "no safe height ... at some rotary position" (the lathe has no rotary axis)
    assert main(["program", "slots", "-o", str(out), "--machine", "lathe"]) == 2
    assert _one_line_error(capsys) == ("trueaxis program: the slot block needs a three-axis mill (X Y Z; a five-axis "
                                       "mill does too); Two-axis CNC lathe (caliper response-surface paper) is a "
                                       "lathe with axes X Z")
    assert main(["program", "slots", "-o", str(out), "--compensate", "none"]) == 2
    _one_line_error(capsys)
    # A part the machine cannot reach there is a refused input, exit 3 for both parts (the nas979's was 2, a usage
    # error, while the slot block's was 3).
    assert main(["program", "nas979", "-o", str(out), "--placement-mm", "190,0"]) == 3  # off the table
    assert "pass 1: axis X needs" in _one_line_error(capsys)
    assert main(["program", "slots", "-o", str(out), "--placement-mm", "900,0"]) == 3
    assert "outside its travel" in _one_line_error(capsys)
    assert not out.exists()


def test_program_prints_the_posts_warnings_as_the_post_command_does(tmp_path):
    """A machine with [cutting] and no force model: the slot block's comprehensive slot warns. The warning was Python's
    (``programs.py:603: PostWarning: ...`` and the source line that raised it); it is ``file:line: message`` now."""
    import subprocess
    import sys

    machine = tmp_path / "m.toml"
    machine.write_text(PERFECT_3AX)
    r = subprocess.run([sys.executable, "-m", "trueaxis.cli", "program", "slots", "--machine", str(machine), "-o",
                        str(tmp_path / "s.ngc")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert r.stderr.splitlines() == [
        "slots[slot 3 as generated, before the post]:1: comprehensive mode: the twin of perfect 3-axis mill (test) "
        "has no force model (no [force] compliance, no [loaded] parameter set, no response surfaces): nothing is "
        "corrected for the cutting force, the program is compensated as in geometric mode"]
    assert "PostWarning" not in r.stderr and "compensate(" not in r.stderr


# ---------------------------------------------------------------------------------------------------- simulate ----
@pytest.fixture(scope="module")
def slot_sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("slotsim")
    machine = d / "perfect.toml"
    machine.write_text(PERFECT_3AX)
    prog = d / "slots.ngc"
    assert main(["program", "slots", "--machine", str(machine), "-o", str(prog), "--param", "slot_depth=1.2"]) == 0
    part_dir = d / "part"
    part_dir.mkdir()
    from trueaxis.workpiece.parts import SlotBlockParams, slot_block_description

    (part_dir / "slots.json").write_text(json.dumps(slot_block_description(SlotBlockParams(slot_depth=1.2))))
    return d, machine, prog, part_dir


def test_simulate_perfect_machine_cuts_the_slots_exactly(slot_sim, capsys):
    d, machine, prog, part_dir = slot_sim
    out = d / "cmm.ply"
    assert main(["simulate", str(prog), "--machine", str(machine), "--part", "slots", "--part-dir", str(part_dir),
                 "-o", str(out), "--points", "1500"]) == 0
    said = capsys.readouterr().out
    truth = json.loads((d / "cmm.truth.json").read_text())
    dev = np.array(truth["per_point"]["deviation_um"])
    assert truth["points_not_cut"] == 0 and dev.size > 1000
    # the probe pattern's grid holds its own number of points: said beside "not cut" when it is not the number asked
    # (a QA pass read 199,888 points written for 200,000 asked under "(0 not cut)")
    grid = "" if dev.size == 1500 else f"; the probe pattern's grid holds {dev.size} of the 1500 asked"
    assert f"{dev.size} points (0 not cut{grid})" in said
    assert np.sqrt(np.mean(dev**2)) < 0.3


def test_simulate_says_the_clouds_rms_with_its_noise_beside_the_noise_free_surface(slot_sim, capsys):
    # The summary once gave only the cut surface's deviation, which read as the cloud's (rms 0.02 um for a cloud of
    # 50 um noise); the cloud's figure is checked against the cloud read back.
    from trueaxis.inspect.cloud import read_cloud

    d, machine, prog, part_dir = slot_sim
    out = d / "noisy.ply"
    assert main(["simulate", str(prog), "--machine", str(machine), "--part", "slots", "--part-dir", str(part_dir),
                 "-o", str(out), "--points", "1500", "--noise-um", "50", "--seed", "1"]) == 0
    said = capsys.readouterr().out
    free = float(re.search(r"\(noise-free\) mean [-+\d.]+ um, rms ([\d.]+) um", said).group(1))
    noisy = float(re.search(r"with the probe noise \(sigma 50 um\) rms ([\d.]+) um", said).group(1))
    truth = json.loads((d / "noisy.truth.json").read_text())["per_point"]
    cloud = read_cloud(out).points
    assert free < 0.3 and noisy == pytest.approx(np.sqrt(np.mean(np.square(
        np.array(truth["deviation_um"]) + np.array(truth["noise_um"])))), abs=0.01)
    assert 45.0 < noisy < 55.0 and len(cloud) == len(truth["deviation_um"])


def test_simulate_reports_points_not_cut(slot_sim, capsys):
    d, machine, prog, part_dir = slot_sim
    text = prog.read_text()
    one_slot = text[:text.index("(slot 2 of 3")] + "M30\n%\n"  # slot 1 only
    short = d / "one_slot.ngc"
    short.write_text(one_slot)
    assert main(["simulate", str(short), "--machine", str(machine), "--part", "slots", "--part-dir", str(part_dir),
                 "-o", str(d / "one.ply"), "--points", "600"]) == 0
    err = capsys.readouterr().err
    n = int(re.search(r"warning: (\d+) of (\d+) probe points were not cut", err).group(1))
    assert 300 < n < 500  # about two slots of three


def test_simulate_notes_a_force_model_of_the_true_machine_it_does_not_apply(slot_sim, capsys):
    # A true machine with compliance cut with no force and said nothing: its comprehensive slot looked worse than the
    # geometric one. The note says so, and how to apply it; an effects file that applies it silences it.
    from trueaxis.machine import load_machine
    from trueaxis.sim.effects import Effects, ForceDeflection
    from trueaxis.sim.shop import unapplied_force_note

    d, _, prog, part_dir = slot_sim
    machine = d / "compliant.toml"
    machine.write_text(PERFECT_3AX + "[force]\ncompliance_um_per_n = [[0.02, 0, 0], [0, 0.02, 0], [0, 0, 0.01]]\n")
    assert main(["simulate", str(prog), "--machine", str(machine), "--part", "slots", "--part-dir", str(part_dir),
                 "-o", str(d / "compliant.ply"), "--points", "300"]) == 0
    said = capsys.readouterr().out.splitlines()
    assert len(said) == 2 and said[1] == (
        "  note: the true machine's force model ([force] compliance) is not applied in this run: the tool cut with no "
        "force on it, so a comprehensive compensation looks worse than a geometric one; to apply it, give --effects "
        "with [force] use_machine_compliance = true")
    true = load_machine(machine)
    assert unapplied_force_note(true, Effects(force=ForceDeflection(np.eye(3), False))) == said[1][len("  note: "):]
    assert unapplied_force_note(true, Effects(force=ForceDeflection(None, True))) is None
    assert unapplied_force_note(load_machine(slot_sim[1]), Effects()) is None  # no force model: nothing to say


def test_simulate_refuses_a_program_for_the_other_part(slot_sim, capsys):
    # a refused input (exit 3), as the diagnosis and the identification refuse it: one check, programs.placed_for
    d, machine, prog, part_dir = slot_sim
    assert main(["simulate", str(prog), "--machine", str(machine), "--part", "nas979", "-o", str(d / "x.ply")]) == 3
    assert _one_line_error(capsys) == "trueaxis simulate: the program is for part 'slots', not 'nas979'"
    assert not (d / "x.ply").exists()


def _perfect_cone(tmp_path, name, *options):
    """(machine file, program) of the cone on the perfect B-C table, uncompensated, with the ``program`` options."""
    machine = tmp_path / "perfect.toml"
    machine.write_text(PERFECT_BC)
    prog = tmp_path / name
    assert main(["program", "nas979", "--machine", str(machine), "-o", str(prog), "--compensate", "none",
                 *options]) == 0
    return machine, prog


def _simulate_cone(tmp_path, machine, prog):
    """``simulate`` of the cone program on the machine, 3000 points into tmp_path / c.ply: its exit status."""
    return main(["simulate", str(prog), "--machine", str(machine), "--part", "nas979", "-o", str(tmp_path / "c.ply"),
                 "--points", "3000"])


def test_simulate_cuts_with_the_tool_the_program_was_made_for_and_says_so(tmp_path, capsys):
    # The shop cut an 8 mm tool's program with the machine file's 10 mm tool: 1000 um off everywhere, exit 0.
    machine, prog = _perfect_cone(tmp_path, "cone8.ngc", "--tool-diameter", "8")
    capsys.readouterr()
    assert _simulate_cone(tmp_path, machine, prog) == 0
    said = capsys.readouterr().out
    assert said.rstrip().endswith("; cut with the program's tool, d 8 mm (its setup comment's tool_d_mm; the machine "
                                  "file's: d 10 mm)")
    dev = np.array(json.loads((tmp_path / "c.truth.json").read_text())["per_point"]["deviation_um"])
    assert dev.size > 2900 and np.sqrt(np.mean(dev**2)) < 0.3 and np.abs(dev).max() < 0.5  # as the 10 mm cone's


def test_simulate_refuses_a_program_for_another_size_of_the_part(tmp_path, capsys):
    # A cone of base diameter 70 simulated against the default 80 mm part: exit 0, rms 4830 um. Refused as the
    # diagnosis refuses it, by the same check.
    from trueaxis.diagnose import report
    from trueaxis.postproc import programs

    assert report.check_part_against_program is programs.check_part_against_program
    machine, prog = _perfect_cone(tmp_path, "cone70.ngc", "--param", "base_diameter=70", "--step-deg", "3",
                                  "--chord-tol-um", "5")
    capsys.readouterr()
    assert _simulate_cone(tmp_path, machine, prog) == 3
    assert _one_line_error(capsys) == ("trueaxis simulate: the program cuts a cone of base_diameter 70; the part's "
                                       "description gives base_diameter 80.0: give the description `trueaxis part` "
                                       "wrote for it (--part-dir)")
    assert not (tmp_path / "c.ply").exists() and not (tmp_path / "c.truth.json").exists()


def test_simulate_refuses_a_program_written_for_another_machine_as_the_post_does(tmp_path, capsys):
    # Its axis words are that machine's joints: the shop cut another path (exit 0 with thousands of um, or exit 2
    # "no probe point was cut: nothing to write"). Refused where its header names the machine, exit 3, by the post's
    # check (post.refuse_other_machine).
    from trueaxis.machine import load_machine
    from trueaxis.postproc.programs import header_name
    from trueaxis.resources import machine_file

    machine, prog = _perfect_cone(tmp_path, "cone.ngc", "--step-deg", "3", "--chord-tol-um", "5")
    capsys.readouterr()
    other = machine_file("bc_offset")
    assert main(["simulate", str(prog), "--machine", str(other), "--part", "nas979", "-o", str(tmp_path / "c.ply"),
                 "--points", "3000"]) == 3
    line = next(k for k, t in enumerate(prog.read_text().splitlines(), 1) if t.startswith("(machine: "))
    assert _one_line_error(capsys) == (
        f"{prog}:{line}: the program was written for the machine 'perfect B-C table [test]', this simulation is of "
        f"{header_name(load_machine(other))!r}: its axis words are that machine's joints; simulate the program "
        "written for this machine (or remove this line)")
    assert not (tmp_path / "c.ply").exists() and not (tmp_path / "c.truth.json").exists()
    assert main(["post", str(prog), "-o", str(tmp_path / "p.ngc"), "--machine", str(other)]) == 3
    assert _one_line_error(capsys).startswith(f"{prog}:{line}: the program was written for the machine 'perfect B-C "
                                              "table [test]', this post is for ")


def test_simulate_perfect_machine_cuts_the_cone(tmp_path, capsys):
    machine, prog = _perfect_cone(tmp_path, "cone.ngc", "--placement-mm", "10,-5")
    assert _simulate_cone(tmp_path, machine, prog) == 0
    truth = json.loads((tmp_path / "c.truth.json").read_text())
    dev = np.array(truth["per_point"]["deviation_um"])
    assert truth["points_not_cut"] == 0
    assert np.sqrt(np.mean(dev**2)) < 0.3 and np.abs(dev).max() < 0.5


@pytest.mark.parametrize("body, line, reason", [
    ("10,0,5,0,0,1,500\n12,0,5,0,0,1,-100\n", 3, "feed must be positive"),
    ("10,0,5,0,0,1,500\n12,0,5,0,0,0,500\n", 3, "tool-axis vector"),
    ("10,0,5,0,0,1,500\n12,0,abc,0,0,1,500\n", 3, "not a number"),
])
def test_post_refuses_bad_cl_data_with_its_line(tmp_path, capsys, body, line, reason):
    """Bad CL data through `trueaxis post`: exit 3, one line `file:line: reason`, nothing written."""
    from trueaxis.resources import machine_file

    cl, posted = tmp_path / "bad.csv", tmp_path / "out.ngc"
    cl.write_text("x,y,z,i,j,k,f\n" + body)
    assert main(["post", str(cl), "-o", str(posted), "--machine", str(machine_file("nmv1500dcg"))]) == 3
    err = _one_line_error(capsys)
    assert err.startswith(f"{cl}:{line}:") and reason in err
    assert not posted.exists()


@pytest.mark.parametrize("command, option", [
    (["program", "nas979", "-o", "{tmp}/x.ngc", "--machine", "{missing}"], "--machine"),
    (["post", "{program}", "-o", "{tmp}/x.ngc", "--machine", "{missing}"], "--machine"),
    (["diagnose", "--cloud", "{program}", "--part", "nas979", "--program", "{program}", "--machine", "{missing}",
      "-o", "{tmp}/x"], "--machine"),
    (["simulate", "{program}", "--part", "nas979", "-o", "{tmp}/x.ply", "--machine", "{missing}"], "--machine"),
    (["simulate", "{program}", "--part", "nas979", "-o", "{tmp}/x.ply", "--machine", "xh714", "--effects",
      "{missing}"], "--effects"),
    (["error", "--at", "X=0", "--machine", "{missing}"], "--machine"),
    (["machine", "check", "{missing}"], "file"),
])
def test_a_missing_machine_file_is_a_usage_error_that_names_the_option(tmp_path, capsys, command, option):
    # It was exit 3 with a bare "nothere.toml: file not found" (the refusal of a bad machine file), where every other
    # missing input is a usage error naming the command and the option.
    prog = tmp_path / "p.ngc"
    prog.write_text("G21 G90\nG0 X0 Y0 Z0\nM30\n")
    missing = tmp_path / "nothere.toml"
    assert main([a.format(missing=missing, program=prog, tmp=tmp_path) for a in command]) == 2
    assert _one_line_error(capsys) == f"trueaxis {command[0]}: {option} {missing}: cannot read the file: no such file"
    assert sorted(f.name for f in tmp_path.iterdir()) == ["p.ngc"]


def test_every_command_takes_a_fixture_machine_by_its_short_name(tmp_path, capsys):
    """`post --machine nmv1500dcg` as `program --machine nmv1500dcg` (it said "file not found"); an unknown name is a
    usage error that lists the fixture machines."""
    prog, posted = tmp_path / "p.ngc", tmp_path / "out.ngc"
    prog.write_text("G21 G90 G54\nG0 X10 Y10 Z50 B0 C0\nG1 X20 F500\nM30\n")
    assert main(["post", str(prog), "-o", str(posted), "--machine", "nmv1500dcg", "--offsets-zero"]) == 0
    from trueaxis.resources import machine_file

    assert f"machine file {machine_file('nmv1500dcg')} sha256" in posted.read_text()  # the header names the file
    capsys.readouterr()
    assert main(["machine", "show", "xh714"]) == 0
    assert "XH714" in capsys.readouterr().out
    assert main(["post", str(prog), "-o", str(tmp_path / "x.ngc"), "--machine", "nosuch"]) == 2
    err = _one_line_error(capsys)
    assert "nosuch" in err and "nmv1500dcg" in err and "xh714" in err


LATHE_PROGRAM = """%
G18 G21 G90 G7 G40 G49
G10 L2 P1 X0 Z-100
G54
T1 M6
G96 D2500 S180 M3
G95 F0.2
(trueaxis: ap=2 f=0.2 vc=180)
G0 X84 Z2
G1 Z-60
G1 X90
G0 Z2
M5
M30
%
"""


def test_a_lathe_is_refused_for_a_milled_part_by_every_command_that_reads_it_against_the_part(tmp_path, capsys):
    # A QA pass: a lathe program on a cone cloud was identified (NO CHANGE, residual 204 um, the twin written) from
    # the 250 of 8000 points its passes reached, diagnosed into "unknown field 'f'" (exit 2: the turning comment),
    # and simulated for six minutes into 241 points (exit 0). One check (programs.placed_for), exit 3, nothing written.
    from trueaxis.inspect.cloud import write_cloud_ply
    from trueaxis.resources import machine_file
    from trueaxis.sim.cmm import probe_pattern
    from trueaxis.workpiece.part import load_part

    pts, nrm = probe_pattern(load_part("nas979"), 2000)
    cloud, prog, lathe = tmp_path / "cone.ply", tmp_path / "t1.ngc", str(machine_file("lathe"))
    write_cloud_ply(cloud, pts, nrm)
    prog.write_text(LATHE_PROGRAM)
    said = ("Two-axis CNC lathe (caliper response-surface paper) is a lathe: it cannot have cut the nas979 part (the "
            "test parts are milled with a flat end mill): a lathe's twin is not simulated, identified or diagnosed "
            "from a measured part")
    runs = {"inspect": ["inspect", str(cloud), "--part", "nas979", "--identify", "--machine", lathe, "--program",
                        str(prog), "--write", str(tmp_path / "twin.toml"), "-o", str(tmp_path / "rep")],
            "diagnose": ["diagnose", "--cloud", str(cloud), "--part", "nas979", "--machine", lathe, "--program",
                         str(prog), "-o", str(tmp_path / "diag")],
            "simulate": ["simulate", str(prog), "--machine", lathe, "--part", "nas979", "-o", str(tmp_path / "x.ply")]}
    for command, argv in runs.items():
        assert main(argv) == 3, command
        assert _one_line_error(capsys) == f"trueaxis {command}: {said}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cone.ply", "t1.ngc"]


def test_simulate_refuses_a_program_that_cuts_almost_none_of_the_part(slot_sim, capsys):
    # A program that cut 241 of 200,000 probe points was written as a cloud, exit 0 with a warning: below
    # programs.MIN_CUT_SHARE (10 %) it is refused, exit 3, nothing written (a third of the part, one slot: written).
    d, machine, prog, part_dir = slot_sim
    text = prog.read_text()
    lines = text[:text.index("(slot 2 of 3")].splitlines()
    first_cut = next(i for i, ln in enumerate(lines) if re.match(r"G0?1\b", ln))
    short = d / "a_few.ngc"
    short.write_text("\n".join(lines[:first_cut + 1]) + "\nM30\n%\n")  # the first feed move of slot 1
    out = d / "few.ply"
    assert main(["simulate", str(short), "--machine", str(machine), "--part", "slots", "--part-dir", str(part_dir),
                 "-o", str(out), "--points", "600"]) == 3
    err = _one_line_error(capsys)
    assert re.fullmatch(r"trueaxis simulate: the program cuts only (\d+) of the 594 probe points of the part \(\d\.\d "
                        r"%; at least 10 % and 10 points needed\): is it the program that made this part, with this "
                        r"placement\?", err), err
    assert not out.exists() and not (d / "few.truth.json").exists()


def test_simulate_refuses_a_turning_comment_in_a_milling_program_naming_its_line(slot_sim, capsys):
    # The turning comment's f= was "structured comment: unknown field 'f'", a ValueError: exit 2, a usage error, for a
    # refused program. Now the program's refusal (exit 3, file:line) naming the comment as the turning one.
    d, machine, prog, part_dir = slot_sim
    lines = prog.read_text().splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.startswith("(trueaxis:"))
    turned = d / "turned.ngc"
    turned.write_text("\n".join(lines[:at + 1] + ["(trueaxis: ap=2 f=0.2 vc=180)"] + lines[at + 1:]) + "\n")
    out, effects = d / "turned.ply", d / "force.toml"  # (the conditions are read for the cutting force)
    effects.write_text("[force]\ncompliance_um_per_n = [[0.02, 0, 0], [0, 0.02, 0], [0, 0, 0.01]]\n")
    assert main(["simulate", str(turned), "--machine", str(machine), "--part", "slots", "--part-dir", str(part_dir),
                 "--effects", str(effects), "-o", str(out), "--points", "300"]) == 3
    assert _one_line_error(capsys) == (f"{turned}:{at + 2}: structured comment: unknown milling field 'f' (f= and vc= "
                                       "are the turning comment's: a lathe program? the virtual shop mills)")
    assert not out.exists()


def test_turning_conditions_from_the_command_line_post_as_the_comment_does(tmp_path, capsys):
    # a lathe's conditions (ap, f per revolution, vc) could be given in a comment or by a Python host, but only ap on
    # the command line: --f-rev and --vc now; the moves written are the comment's to the byte; a mill refuses them
    with_comment = tmp_path / "c.ngc"
    with_comment.write_text(LATHE_PROGRAM)
    without = tmp_path / "n.ngc"
    without.write_text(LATHE_PROGRAM.replace("(trueaxis: ap=2 f=0.2 vc=180)\n", ""))
    assert main(["post", str(with_comment), "-o", str(tmp_path / "c.out"), "--machine", "lathe", "--mode",
                 "comprehensive"]) == 0
    assert main(["post", str(without), "-o", str(tmp_path / "n.out"), "--machine", "lathe", "--mode", "comprehensive",
                 "--ap", "2", "--f-rev", "0.2", "--vc", "180"]) == 0
    moves = [[line for line in (tmp_path / f"{n}.out").read_text().splitlines() if not line.startswith("(")]
             for n in ("c", "n")]
    assert moves[0] == moves[1] and any("X" in line and "Z" in line for line in moves[0])
    assert moves[0] != [line for line in without.read_text().splitlines() if not line.startswith("(")]  # corrected
    capsys.readouterr()
    assert main(["post", str(without), "-o", str(tmp_path / "x.out"), "--machine", "lathe", "--mode",
                 "comprehensive"]) == 3
    assert "--ap --f-rev --vc" in capsys.readouterr().err
    assert main(["post", str(without), "-o", str(tmp_path / "m.out"), "--machine", "xh714", "--mode", "comprehensive",
                 "--vc", "180"]) == 2
    assert "--vc: turning conditions" in capsys.readouterr().err and not (tmp_path / "m.out").exists()
