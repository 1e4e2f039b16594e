"""The command line's gates: numeric options, output paths that would destroy something, signals, system errors.
Every refusal is one line on stderr, no traceback, and nothing written."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import DATA, MACHINES

BC = str(DATA / "bc_table.toml")
PROGRAM = "G21 G90 G17\nG0 X0 Y0 Z10 B0 C0\nG1 X10 Y5 Z-1 F500\nG1 X20 Y-5 B10 C30\nM30\n"


def run(*args, cwd=None, umask=None):
    pre = (lambda: os.umask(umask)) if umask is not None else None
    return subprocess.run([sys.executable, "-m", "trueaxis.cli", *args], capture_output=True, text=True, cwd=cwd,
                          preexec_fn=pre)


def one_line_refusal(r, code=2, words=""):
    assert r.returncode == code, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 or r.stderr.startswith("usage:"), r.stderr
    assert words in r.stderr, r.stderr


@pytest.fixture()
def program(tmp_path):
    p = tmp_path / "in.ngc"
    p.write_text(PROGRAM)
    return p


@pytest.mark.parametrize("option, value", [
    ("--max-correction-mm", "nan"), ("--max-correction-mm", "inf"), ("--max-correction-mm", "0"),
    ("--tol-um", "-1"), ("--tol-um", "nan"), ("--singular-deg", "nan"), ("--fz", "-0.1"), ("--z", "0"),
    ("--cl-feed", "inf")])
def test_post_refuses_non_finite_or_out_of_range_options_before_any_work(tmp_path, program, option, value):
    out = tmp_path / "out.ngc"
    r = run("post", str(program), "-o", str(out), "--machine", BC, option, value)
    assert r.returncode == 2 and option in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


def test_post_library_refuses_a_nan_correction_bound_too(program):
    """The CLI's number gate has a twin in the library, for the hosts (CadQuery, FreeCAD) that call it directly."""
    from trueaxis.machine import load_machine
    from trueaxis.postproc.post import post_text

    with pytest.raises(ValueError, match="largest correction"):
        post_text(PROGRAM, load_machine(BC), max_correction_mm=float("nan"))


@pytest.mark.parametrize("args", [
    ["program", "nas979", "--step-deg", "0"], ["program", "nas979", "--tool-diameter", "nan"],
    ["simulate", "x.ngc", "--machine", BC, "--part", "nas979", "--points", "0"],
    ["simulate", "x.ngc", "--machine", BC, "--part", "nas979", "--noise-um", "inf"],
    ["simulate", "x.ngc", "--machine", BC, "--part", "nas979", "--points", "9"],  # (a cloud no command reads)
    ["simulate", "x.ngc", "--machine", BC, "--part", "nas979", "--seed", "-1"]])  # (numpy's message, unnamed)
def test_other_commands_refuse_zero_and_non_finite_options(tmp_path, args):
    r = run(*args, "-o", str(tmp_path / "o"))
    assert r.returncode == 2 and "Traceback" not in r.stderr and "must be" in r.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["cloud.csv", "cloud.xyz", "cloud.e57", "effects.toml"])
def test_simulate_writes_ply_only_and_says_so(tmp_path, program, name):
    # the cloud is a binary PLY whatever the name: -o x.csv (.xyz, .e57) got one under that name, exit 0, and an
    # effects file given as -o was overwritten with it (a QA pass); now refused before any work, the file untouched
    out = tmp_path / name
    out.write_text("[backlash.X]\namplitude = 8.0\n")
    r = run("simulate", str(program), "--machine", BC, "--part", "nas979", "-o", str(out))
    one_line_refusal(r, 2, "simulate writes a PLY cloud")
    assert out.read_text() == "[backlash.X]\namplitude = 8.0\n"


def test_report_naming_the_output_or_the_input_is_refused_and_the_input_kept(tmp_path, program):
    out = tmp_path / "out.ngc"
    r = run("post", str(program), "-o", str(out), "--machine", BC, "--report", str(out))
    one_line_refusal(r, 2, "same file")
    assert not out.exists()
    r = run("post", str(program), "-o", str(tmp_path / "o2.ngc"), "--machine", BC, "--report", str(program))
    one_line_refusal(r, 2, "would overwrite the input")
    r = run("post", str(program), "-o", str(program), "--machine", BC)
    one_line_refusal(r, 2, "would overwrite the input")
    assert program.read_text() == PROGRAM
    # the input named once ("would overwrite the input input PATH" named the positional's name as well), an option's
    # input with its option
    assert r.stderr == f"trueaxis post: -o {program} would overwrite the input {program}; name another output\n"
    machine = tmp_path / "m.toml"
    machine.write_text(Path(BC).read_text())
    r = run("post", str(program), "-o", str(machine), "--machine", str(machine))
    assert r.returncode == 2 and r.stderr == (f"trueaxis post: -o {machine} would overwrite the input {machine} "
                                              "(--machine); name another output\n")


@pytest.mark.parametrize("option, text", [
    ("--var", "5221 -100.0\n5222 0.0\n5223 -300.0\n"), ("--tool-table", "T3 P3 Z50 D10 ;\n"),
    ("--setup", '[setup]\nunits = "mm"\n[work_offsets]\nG54 = {X = -100, Z = -300}\n')])
def test_the_controls_setup_files_are_inputs_the_output_may_not_overwrite(tmp_path, program, option, text):
    """-o naming the --var, --tool-table or --setup file replaced the control's setup with G-code, exit 0 (QA pass)."""
    setup = tmp_path / "setup.file"
    setup.write_text(text)
    r = run("post", str(program), "-o", str(setup), "--machine", BC, option, str(setup))
    assert r.returncode == 2 and r.stderr == (f"trueaxis post: -o {setup} would overwrite the input {setup} "
                                              f"({option}); name another output\n")
    assert setup.read_text() == text


def test_an_output_through_a_symbolic_link_replaces_the_target_and_keeps_the_link(tmp_path, program):
    target = tmp_path / "real.ngc"
    target.write_text("old")
    link = tmp_path / "link.ngc"
    link.symlink_to(target)
    r = run("post", str(program), "-o", str(link), "--machine", BC)
    assert r.returncode == 0, r.stderr
    assert link.is_symlink() and link.resolve() == target
    assert target.read_text().startswith("G21") or "G1" in target.read_text()
    # a link to the input is the input
    link_in = tmp_path / "link_in.ngc"
    link_in.symlink_to(program)
    one_line_refusal(run("post", str(program), "-o", str(link_in), "--machine", BC), 2, "overwrite the input")
    assert program.read_text() == PROGRAM


def test_device_files_and_folders_are_refused_as_outputs_and_folders_as_inputs(tmp_path, program):
    one_line_refusal(run("post", str(program), "-o", "/dev/null", "--machine", BC), 2, "not a regular file")
    assert Path("/dev/null").is_char_device()
    one_line_refusal(run("post", str(program), "-o", str(tmp_path), "--machine", BC), 2, "is a folder")
    one_line_refusal(run("post", str(tmp_path), "-o", str(tmp_path / "o.ngc"), "--machine", BC), 2, "is a folder")
    # a report folder that is a file
    cloud_like = tmp_path / "c.ply"
    cloud_like.write_text("ply\n")
    one_line_refusal(run("inspect", str(program), "--part", "nas979", "-o", str(program)), 2)
    assert program.read_text() == PROGRAM


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o027, 0o640)])
def test_new_outputs_honour_the_umask_and_replaced_ones_keep_their_mode(tmp_path, program, umask, mode):
    out = tmp_path / "out.ngc"
    r = run("post", str(program), "-o", str(out), "--machine", BC, "--report", str(tmp_path / "r.json"), umask=umask)
    assert r.returncode == 0, r.stderr
    assert out.stat().st_mode & 0o777 == mode
    assert (tmp_path / "r.json").stat().st_mode & 0o777 == mode
    out.chmod(0o600)
    assert run("post", str(program), "-o", str(out), "--machine", BC, umask=umask).returncode == 0
    assert out.stat().st_mode & 0o777 == 0o600


def test_a_destination_the_system_refuses_is_one_line_exit_1_naming_the_users_path(program):
    # /sys refuses new files even to root (a chmod'ed folder would not stop root)
    r = run("post", str(program), "-o", "/sys/trueaxis_out.ngc", "--machine", BC, "--offsets-zero")
    one_line_refusal(r, 1, "/sys/trueaxis_out.ngc")
    assert ".tmp" not in r.stderr
    # /proc refuses with ENOENT: the same refusal (it was exit 2, a missing input, naming the temporary file)
    r = run("post", str(program), "-o", "/proc/trueaxis_out.ngc", "--machine", BC, "--offsets-zero")
    one_line_refusal(r, 1, "/proc/trueaxis_out.ngc: cannot write here")
    assert ".tmp" not in r.stderr


@pytest.mark.parametrize("place", ["/proc/trueaxis_report", "/sys/trueaxis_report"])
def test_a_report_folder_the_system_refuses_is_exit_1_naming_the_users_path(tmp_path, place):
    # /proc said "[Errno 2] No such file or directory: '/proc/.trueaxis_report.a0d8xvyw.tmp'", exit 2 (a missing
    # input), /sys exit 1: both are the system's refusal of the user's path
    assert run("program", "nas979", "-o", str(tmp_path / "c.ngc")).returncode == 0
    sim = run("simulate", str(tmp_path / "c.ngc"), "--machine", "nmv1500dcg", "--part", "nas979", "-o",
              str(tmp_path / "c.ply"), "--points", "600")
    assert sim.returncode == 0, sim.stderr
    r = run("inspect", str(tmp_path / "c.ply"), "--part", "nas979", "-o", place)
    one_line_refusal(r, 1, f"{place}: cannot write here")
    assert ".tmp" not in r.stderr


def _big_program(path: Path, blocks: int):
    import numpy as np

    t = np.linspace(0, 40 * np.pi, blocks)
    lines = ["G21 G90 G17", "G0 X0 Y0 Z10 B0 C0", "G1 F800"]
    # B kept away from 0 (the singular pose, where C's corrections grow past the bound and the post stops early)
    lines += [f"X{40 * np.cos(a):.4f} Y{40 * np.sin(a):.4f} Z{-5 + np.sin(3 * a):.4f} B{-20 + 10 * np.sin(a / 7):.3f} "
              f"C{np.degrees(a):.3f}" for a in t]
    path.write_text("\n".join(lines + ["M30", ""]))


def _wait_until_computing(proc, timeout=60.0):
    """Until the process has loaded the compiled kernels, ahead of time (a long post no longer imports numba) or
    numba's (it is past start-up and inside the post)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            maps = Path(f"/proc/{proc.pid}/maps").read_text()
            if "_aot_kernels" in maps or "llvmlite" in maps:
                return
        except OSError:
            pass
        time.sleep(0.05)
    pytest.fail("the post never loaded its compiled kernels")


@pytest.mark.slow
@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_ends_the_post_quickly_with_one_line_and_leaves_the_previous_output(tmp_path, sig, code):
    prog = tmp_path / "big.ngc"
    _big_program(prog, 150_000)
    out = tmp_path / "out.ngc"
    out.write_text("previous output")
    proc = subprocess.Popen([sys.executable, "-m", "trueaxis.cli", "post", str(prog), "-o", str(out),
                             "--machine", str(MACHINES / "nmv1500dcg.toml")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_until_computing(proc)
    time.sleep(0.5)
    sent = time.monotonic()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    took = time.monotonic() - sent
    assert proc.returncode == code, (proc.returncode, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert took < 3.0, took  # the issue asks for a second; margin for a loaded CI machine
    assert out.read_text() == "previous output"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.ngc", "out.ngc"]


def test_version_and_plain_numbers_in_machine_show():
    from trueaxis import __version__

    r = run("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"trueaxis {__version__}"
    r = run("machine", "show", str(MACHINES / "nmv1500dcg.toml"))
    assert r.returncode == 0 and "np.float64" not in r.stdout
    assert "pivot [0, 0, -100] mm" in r.stdout and "part origin in M: [0, 0, 50] mm" in r.stdout


def test_a_reader_that_goes_away_ends_the_command_quietly():
    """`trueaxis machine show M | head -1`: no 'Broken pipe' message, SIGPIPE's status."""
    p = subprocess.run(f"{sys.executable} -m trueaxis.cli machine show {MACHINES / 'lathe.toml'} | head -c 10; "
                       "exit ${PIPESTATUS[0]}", shell=True, executable="/bin/bash", capture_output=True, text=True)
    assert p.stderr == "" and p.returncode in (0, 141)


def test_one_over_long_number_does_not_set_the_precision_of_every_block(tmp_path):
    """Precision is the dialect's (at least the input's usual decimals, at most 6 in mm), never one number's 40."""
    prog = tmp_path / "long.ngc"
    prog.write_text("G21 G90 G17\nG0 X0 Y0 Z10 B0 C0\nG1 X10.1234567890123456789012345678901234567890 Y5 Z-1 F500\n"
                    "G1 X20 Y-5 B10 C30\nM30\n")
    out = tmp_path / "out.ngc"
    r = run("post", str(prog), "-o", str(out), "--machine", BC)
    assert r.returncode == 0, r.stderr
    words = [w for line in out.read_text().splitlines() if not line.startswith("(")
             for w in line.split() if w[0] in "XYZBC" and "." in w]
    assert words and max(len(w.split(".")[1]) for w in words) == 6


def test_inspect_refuses_an_output_folder_holding_other_files_before_any_work(tmp_path):
    """`inspect -o DIR` replaces DIR whole: a folder with a user's file in it (here the tolerance file it reads) is
    refused with exit 2 and left as it was; an earlier report folder is replaced."""
    import subprocess
    import sys

    import numpy as np

    from trueaxis.inspect.cloud import write_cloud_ply
    from trueaxis.workpiece.parts import nas979_description

    cone = nas979_description()["surfaces"][0]
    axis = np.asarray(cone["axis"])
    e1 = np.cross([0.0, 1.0, 0.0], axis)
    e2 = np.cross(axis, e1)
    h, th = np.meshgrid(np.linspace(1, 19, 10), np.linspace(0, 2 * np.pi, 90, endpoint=False))
    radius = (cone["base_radius"] - h * np.tan(np.radians(cone["half_angle_deg"]))).ravel()
    points = h.ravel()[:, None] * axis + radius[:, None] * (np.cos(th).ravel()[:, None] * e1
                                                           + np.sin(th).ravel()[:, None] * e2)
    write_cloud_ply(tmp_path / "c.ply", points)
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "tol.toml").write_text("[cone]\nhalf_angle_urad = 50.0\n")
    run = subprocess.run([sys.executable, "-m", "trueaxis.cli", "inspect", str(tmp_path / "c.ply"), "--part",
                          "nas979", "--tolerances", str(folder / "tol.toml"), "-o", str(folder)],
                         capture_output=True, text=True)
    assert run.returncode == 2 and "tol.toml" in run.stderr
    assert sorted(p.name for p in folder.iterdir()) == ["tol.toml"]
    report = tmp_path / "report"
    for _ in range(2):  # the second run replaces the first one's report
        run = subprocess.run([sys.executable, "-m", "trueaxis.cli", "inspect", str(tmp_path / "c.ply"), "--part",
                              "nas979", "-o", str(report)], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr


def test_an_empty_output_path_and_a_report_folder_to_stdout_are_refused(tmp_path, program):
    # inspect -o - made a folder named '-'; -o '' fell back to the default report folder (a QA pass)
    cloud = tmp_path / "c.xyz"
    cloud.write_text("0 0 0\n1 0 0\n")
    for out, said in (("-", "-o -: a folder cannot go to standard output"), ("", "-o: an empty path")):
        r = run("inspect", str(cloud), "--part", "nas979", "-o", out, cwd=tmp_path)
        one_line_refusal(r, 2, said)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.xyz", "in.ngc"]  # (nothing written)
    r = run("post", str(program), "-o", "", "--machine", BC, "--offsets-zero")
    one_line_refusal(r, 2, "-o: an empty path")


@pytest.mark.parametrize("argv, said", [
    (["post", "in.ngc", "-o", "out.ngc", "--machine", "m.toml", "--mod", "none"], "unrecognized arguments: --mod"),
    (["post", "in.ngc", "-o", "out.ngc", "--machine", "m.toml", "--offsets-zer"], "unrecognized arguments: --offsets-zer"),
    (["machine", "nominal", "m.toml", "--out", "n.toml"], "required: -o/--output")])
def test_an_abbreviated_option_is_refused_not_taken_for_the_option_it_begins(argv, said, capsys):
    # argparse takes a unique prefix for the option by default: a mistyped one picked an option without a word
    from trueaxis.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert said in capsys.readouterr().err


def test_a_numerical_failure_on_the_data_is_a_refusal_not_a_usage_error(capsys):
    """numpy's LinAlgError is a ValueError: "trueaxis inspect: Singular matrix" came out with exit 2, the usage status,
    for cloud normals all pointing one way (QA pass). It is exit 3 (the data refused), one line that says what."""
    import numpy as np

    from trueaxis.cli import EXIT_REFUSED, _report_error

    assert _report_error("inspect", np.linalg.LinAlgError("Singular matrix")) == EXIT_REFUSED == 3
    err = capsys.readouterr().err
    assert err == ("trueaxis inspect: the data given leave a computation without a unique solution (numpy: Singular "
                   "matrix): nothing written\n")
    assert _report_error("inspect", ValueError("--points must be positive")) == 2  # usage stays usage


def test_a_latin1_program_is_written_back_in_latin1(tmp_path):
    """A Latin-1 program's comment bytes (NIST d2mi: 0xB0 for the degree sign) came out as UTF-8 (0xC2 0xB0), which a
    control reading Latin-1 shows as two characters (QA pass): the output keeps the input's encoding, file or stdin."""
    prog = b"G21 G90 G17 G94\nG0 X10 Y10 Z-20\n( 1/4\" X 90\xb0 SPOT DRILL )\nG1 X20 F100\nM2\n"
    src = tmp_path / "latin.ngc"
    src.write_bytes(prog)
    r = run("post", str(src), "-o", str(tmp_path / "out.ngc"), "--machine", BC, "--offsets-zero")
    assert r.returncode == 0, r.stderr
    out = (tmp_path / "out.ngc").read_bytes()
    assert b"( 1/4\" X 90\xb0 SPOT DRILL )\n" in out and b"\xc2" not in out
    piped = subprocess.run([sys.executable, "-m", "trueaxis.cli", "post", "-", "-o", "-", "--machine", BC,
                            "--offsets-zero"], input=prog, capture_output=True, timeout=120, check=False)
    assert piped.returncode == 0 and piped.stdout == out
    utf8 = prog.replace(b"\xb0", "\u00b0".encode())  # a UTF-8 one stays UTF-8
    src.write_bytes(utf8)
    assert run("post", str(src), "-o", str(tmp_path / "u.ngc"), "--machine", BC, "--offsets-zero").returncode == 0
    assert "90\u00b0 SPOT".encode() in (tmp_path / "u.ngc").read_bytes()
