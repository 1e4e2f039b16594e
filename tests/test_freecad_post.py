"""The FreeCAD host of the post: trueaxis_post.py posts a real FreeCAD CAM job as FreeCAD's linuxcnc post does, with
the job's cutting conditions as structured comments, compensated by the trueaxis command.

The FreeCAD tests run tests/freecad_scripts/make_job.py in the real ``freecadcmd`` (a block with a pocket, an outside
profile and a pocket operation) and the real ``trueaxis`` console script. The other tests load the script in this
Python (it imports FreeCAD only inside ``export``) and check its pure parts against stand-in objects and a stand-in
trueaxis command.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import MACHINES, ROOT, missing, require_program
from rs274_helpers import run_rs274, var_text
from trueaxis.postproc.hosts.freecad import default_macro_dir, install_post, post_script_path
from trueaxis.postproc.post import without_header

XH714 = MACHINES / "xh714.toml"
TRUEAXIS = ROOT / ".venv" / "bin" / "trueaxis"
DRIVER = Path(__file__).resolve().parent / "freecad_scripts" / "make_job.py"
COMMENT_LINE = re.compile(r"^\(trueaxis: [^)]*\)\n", re.MULTILINE)


def load_post_module():
    spec = importlib.util.spec_from_file_location("trueaxis_post", post_script_path())
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def trueaxis_exe() -> str:
    """The trueaxis command of this checkout: .venv/bin/trueaxis, which make's venv target installs (make test from a
    fresh clone); else `trueaxis` on PATH (a checkout without its own .venv, a git worktree: put a command that runs
    this tree's code first on PATH, or the tests check another tree's trueaxis)."""
    if TRUEAXIS.exists():
        return str(TRUEAXIS)
    path = shutil.which("trueaxis")
    if path is None:
        missing(f"the trueaxis command is not here: no {TRUEAXIS} (make's venv target installs it) and no trueaxis on "
                "PATH")
    return path


# --- the real thing: FreeCAD job -> trueaxis_post -> trueaxis post -> rs274 ----------------------------------------

XDG = ("XDG_CONFIG_HOME", "XDG_DATA_HOME", "XDG_CACHE_HOME")


@pytest.fixture(scope="module")
def freecad_job(tmp_path_factory):
    """Outputs of make_job.py (see its docstring), as {name: text}, plus the job facts and what FreeCAD's console
    printed on stderr (its warnings and errors).

    FreeCAD runs with a private HOME (its settings and macro folder), where install_post puts the script, so FreeCAD
    loads it the way it loads any post processor and the user's own settings play no part.
    """
    freecadcmd = require_program("freecadcmd")
    out = tmp_path_factory.mktemp("freecad_job")
    home = tmp_path_factory.mktemp("home")
    with pytest.MonkeyPatch.context() as mp:
        for name in XDG:
            mp.delenv(name, raising=False)
        installed = install_post(default_macro_dir(home))
    env = {k: v for k, v in os.environ.items() if k not in XDG}
    # The control's setup, in inches as the standalone rs274 reads it: G54 2 inch below the machine zero and tool 1
    # 2 inch long (the part is drawn in machine coordinates: the two cancel, so the job's positions stay on the
    # machine's travel), FreeCAD's program selecting G54 and G43 H1.
    (out / "setup.var").write_text(var_text({1: [0.0, 0.0, -2.0, 0.0, 0.0, 0.0]}))
    (out / "setup.tbl").write_text("T1 P1 Z2.0 D0.2362 ;6 mm end mill\n")
    env.update(HOME=str(home), TRUEAXIS_TEST_OUT=str(out), TRUEAXIS_MACHINE=str(XH714), TRUEAXIS_BIN=trueaxis_exe(),
               TRUEAXIS_SETUP_ARGS=" ".join(setup_args(out)))
    proc = subprocess.run([freecadcmd, str(DRIVER)], cwd=out, env=env, stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"make_job.py failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    files = {p.name: p.read_text() for p in out.glob("*.ngc")}
    facts = json.loads((out / "job.json").read_text())
    assert Path(facts["post_script"]).resolve() == installed.resolve()
    return SimpleNamespace(dir=out, files=files, facts=facts, console=proc.stderr)  # FreeCAD's warnings and errors


def setup_args(folder):
    return ["--var", str(folder / "setup.var"), "--tool-table", str(folder / "setup.tbl"), "--machine-units", "inch"]


@pytest.mark.external
def test_post_equals_linuxcnc_post_compensated_by_trueaxis(freecad_job, tmp_path):
    linuxcnc = freecad_job.dir / "linuxcnc.ngc"
    direct = tmp_path / "direct.ngc"
    subprocess.run([trueaxis_exe(), "post", str(linuxcnc), "-o", str(direct), "--machine", str(XH714),
                    "--mode", "geometric", "--tol-um", "1", *setup_args(freecad_job.dir)], check=True,
                   capture_output=True, text=True)
    posted = freecad_job.files["trueaxis.ngc"]
    # the header names the setup files by their full paths, the same in both
    assert COMMENT_LINE.sub("", posted) == direct.read_text()
    assert posted != freecad_job.files["linuxcnc.ngc"]  # the machine has errors: the program changed
    assert freecad_job.files["trueaxis_return.ngc"] == posted


@pytest.mark.external
def test_the_job_posted_for_a_fixture_machine_by_its_short_name_is_the_same_program(freecad_job):
    # '--machine xh714' in the job's arguments: FreeCAD's working folder/xh714, not found (a QA pass)
    assert freecad_job.facts["short_name_refused"] is None
    assert freecad_job.files["trueaxis_short.ngc"] == freecad_job.files["trueaxis.ngc"]
    assert f"machine file {XH714} sha256" in freecad_job.files["trueaxis_short.ngc"]


@pytest.mark.external
def test_without_correction_the_post_is_the_linuxcnc_post_plus_conditions(freecad_job):
    assert without_header(COMMENT_LINE.sub("", freecad_job.files["trueaxis_none.ngc"])) == \
        freecad_job.files["linuxcnc.ngc"]
    header = freecad_job.files["trueaxis_none.ngc"].splitlines()[:7]
    assert header[0].startswith("(trueaxis post: trueaxis ") and "machine XH714" in header[0]
    assert header[2].endswith("setup.var)") and header[3].endswith("setup.tbl)")
    header = header[3:]
    assert header[1].startswith("(trueaxis setup: G54 Z-50.8 mm, from ") and "setup.var:5221-5226,5230" in header[1]
    assert header[2].startswith("(trueaxis setup: tool 1 offset Z50.8 mm by G43 H1, from ")


@pytest.mark.external
def test_line_numbers_and_no_comments_hold_for_the_compensated_and_split_blocks(freecad_job):
    numbered = without_header(freecad_job.files["trueaxis_numbered.ngc"]).splitlines()
    assert all(re.match(r"N\d+ ", line) for line in numbered)  # split blocks too (spacing: the linuxcnc post's)
    n = [int(line.split()[0][1:]) for line in numbered]
    assert n == list(range(n[0], n[0] + 10 * len(n), 10))
    assert not any("(" in line for line in numbered)  # neither the linuxcnc post's comments nor the conditions
    # the same compensated blocks as without the options
    plain = [line for line in without_header(freecad_job.files["trueaxis.ngc"]).splitlines() if line[:1] != "("]
    assert [" ".join(line.split()[1:]) for line in numbered] == [" ".join(line.split()) for line in plain]
    linuxcnc = freecad_job.files["linuxcnc.ngc"].splitlines()
    assert len(numbered) > len([line for line in linuxcnc if line[:1] != "("])  # moves were split, and numbered


def test_precision_below_the_corrections_is_said_and_options_parsed():
    post = load_post_module()
    text = "(trueaxis post: x)\nN100 G0 X1\nG1 X2\nN110 (trueaxis: ap=1)\nN120 G1 X3\n"
    out, notes = post.honour_linuxcnc_options(text, "--line-numbers --no-comments --precision 2")
    assert out == "(trueaxis post: x)\nN100 G0 X1\nN110 G1 X2\nN120 G1 X3\n"
    assert notes and "--precision 2" in notes[0] and "5 decimals" in notes[0]
    assert post.honour_linuxcnc_options(text, "--precision=6") == (text, [])


@pytest.mark.external
def test_conditions_stand_before_the_tool_change_and_each_operation(freecad_job):
    lines = freecad_job.files["trueaxis.ngc"].splitlines()
    tool = freecad_job.facts["tool"]
    fz = tool["horiz_feed_mm_min"] / (tool["spindle_rpm"] * tool["flutes"])
    assert (tool["diameter"], tool["flutes"], tool["spindle_rpm"], fz) == (6.0, 3, 8000.0, 0.025)
    expected = {
        "(TC: Default Tool)": "(trueaxis: n=8000 d=6 z=3)",
        "(Profile)": "(trueaxis: ap=4 fz=0.025 n=8000 d=6 z=3 mode=down)",
        "(Pocket)": "(trueaxis: ap=2.5 ae=3 fz=0.025 n=8000 d=6 z=3 mode=down)",
    }
    comments = [i for i, line in enumerate(lines) if line.startswith("(trueaxis:")]
    assert len(comments) == len(expected)
    for label, comment in expected.items():
        start = next(i for i, line in enumerate(lines) if line.strip() == label)  # the object's own path starts
        assert lines[start - 1] == comment
    tool_change = next(i for i, line in enumerate(lines) if line.strip().startswith("M6"))
    assert comments[0] < tool_change


@pytest.mark.external
def test_profile_run_counter_clockwise_is_written_as_down_milling(freecad_job):
    text = freecad_job.files["linuxcnc.ngc"]
    profile = text[text.index("(begin operation: Profile)"):text.index("(finish operation: Profile)")]
    arcs = re.findall(r"^(G[23]) ", profile, re.MULTILINE)
    assert freecad_job.facts["profile"]["Direction"] == "CCW" and arcs and set(arcs) == {"G3"}
    assert "mode=down" in freecad_job.facts["conditions"]["Profile"]


@pytest.mark.external
def test_rs274_reads_the_compensated_program(freecad_job, tmp_path):
    nominal = run_rs274(freecad_job.dir / "linuxcnc.ngc", {1: 50.0}, tmp_path / "nominal")
    moves = run_rs274(freecad_job.dir / "trueaxis.ngc", {1: 50.0}, tmp_path / "compensated")
    assert moves.returncode == 0, moves.stderr
    assert len(moves.kind) > len(nominal.kind)  # moves split where the error varies along them
    # corrections are micrometres (xh714: tens of um at most): the path's extent moves by less than 0.1 mm
    lo = np.abs(moves.end[:, :3].min(axis=0) - nominal.end[:, :3].min(axis=0))
    hi = np.abs(moves.end[:, :3].max(axis=0) - nominal.end[:, :3].max(axis=0))
    assert max(lo.max(), hi.max()) < 0.1


@pytest.mark.external
def test_freecad_program_read_back_by_rs274_with_the_setup_lies_on_the_nominal_path(freecad_job, tmp_path):
    # FreeCAD's program selects G54 and G43 H1; the post took them from the .var and tool table given in the job's
    # argument string. rs274 reads the compensated program with the same files (4 decimals of a mm: 0.05 um): every
    # feed end point, through the twin at that machine position, lies on the nominal path within 0.15 um.
    from post_checks import distance_to_polyline, nominal_polyline
    from rs274_helpers import run_rs274_setup
    from trueaxis.machine import ErrorTwin, load_machine
    from trueaxis.nc.gcode import ROW_PROGRAMMED, parse_program
    from trueaxis.nc.setup import load_setup

    var, tbl = freecad_job.dir / "setup.var", freecad_job.dir / "setup.tbl"
    moves = run_rs274_setup(freecad_job.dir / "trueaxis.ngc", var, tbl, tmp_path)
    assert moves.returncode == 0, moves.stderr
    setup = load_setup(var=var, tool_table=tbl, machine_units="inch")
    ours = parse_program(freecad_job.files["trueaxis.ngc"], setup=setup)
    assert len(moves.kind) == len(ours)
    feed = np.array([k in ("feed", "arc") for k in moves.kind]) & (ours.kind == ROW_PROGRAMMED)
    assert feed.sum() > 50
    m = load_machine(XH714)
    nominal = nominal_polyline(parse_program(freecad_job.files["linuxcnc.ngc"], setup=setup), m, arc_points=4000)
    d_um = distance_to_polyline(ErrorTwin(m).actual_pose(moves.end[feed][:, :3])[0], nominal) * 1e3
    assert d_um.max() < 0.15, d_um.max()


@pytest.mark.external
def test_a_refused_program_raises_with_the_block_and_writes_nothing(freecad_job):
    message = freecad_job.facts["refused_message"]
    assert message is not None and not freecad_job.facts["refused_file_written"]
    assert re.search(r"refused\.ngc:\d+: block 'G0 [^']*': correction of [XYZ] is .* above the bound", message)


@pytest.mark.external
def test_an_option_nobody_knows_is_an_error_not_an_exit_of_freecad(freecad_job):
    # Unknown options go on to the linuxcnc post, whose argparse exits (SystemExit: it would take FreeCAD with it),
    # and a bad --precision raised a bare ValueError: both are now the post's own error, naming the options.
    said = freecad_job.facts["bad_options"]
    assert said["--frobnicate 3"].startswith("TrueaxisPostError: trueaxis post: ") and "--frobnicate" in \
        said["--frobnicate 3"], said
    assert said["--precision abc"].startswith("TrueaxisPostError: trueaxis post: ") and "--precision" in \
        said["--precision abc"], said
    assert not freecad_job.facts["bad_option_file_written"]


@pytest.mark.external
def test_what_trueaxis_says_of_the_job_reaches_freecads_console_naming_the_output_file(freecad_job):
    # The job's G54 block moves Z alone before X and Y are known: trueaxis leaves it uncompensated and says so; the
    # FreeCAD post kept that to itself when the post succeeded (a QA pass). Now a warning in FreeCAD's console.
    out = freecad_job.dir / "trueaxis.ngc"
    said = [line for line in freecad_job.console.splitlines() if line.startswith(f"{out}:")]
    uncompensated = (r":\d+: block 'G0 Z-294\.000': the position of X Y is not known here \(no absolute move of it "
                     r"(before|since the tool change M6 at line \d+)\): block left as written, uncompensated")
    assert len(said) == 3 and all(re.fullmatch(re.escape(str(out)) + uncompensated, line) for line in said[:2]), said
    assert "before" in said[0] and "since the tool change M6" in said[1], said  # the second operation's, after M6
    assert "tool length offsets in force (tool 1 offset Z50.8 mm)" in said[2]
    assert "trueaxis_post_" not in freecad_job.console


# --- the script's pure parts, in this Python ----------------------------------------------------------------------

class Quantity:
    """FreeCAD quantity stand-in: Value in internal units (mm, mm/s)."""

    def __init__(self, value, per_second=False):
        self.Value, self.per_second = value, per_second

    def getValueAs(self, unit):
        assert unit == "mm/min" and self.per_second
        return self.Value * 60.0


def tool_controller(rpm=8000.0, diameter=6.0, flutes=3, feed_mm_min=600.0, spindle="Forward"):
    tool = SimpleNamespace(Diameter=Quantity(diameter), Flutes=flutes)
    return SimpleNamespace(Tool=tool, SpindleSpeed=rpm, ToolNumber=1, SpindleDir=spindle,
                           HorizFeed=Quantity(feed_mm_min / 60.0, per_second=True), Path=None)


def test_conditions_come_from_the_tool_controller_and_the_operation():
    post = load_post_module()
    tc = tool_controller()
    pocket = SimpleNamespace(ToolController=tc, StepDown=Quantity(2.5), StartDepth=Quantity(10.0),
                             FinalDepth=Quantity(5.0), StepOver=40, CutMode="Conventional", Path=None)
    assert post.conditions_comment(post.cutting_conditions(tc)) == "(trueaxis: n=8000 d=6 z=3)"
    assert (post.conditions_comment(post.cutting_conditions(pocket))
            == "(trueaxis: ap=2.5 ae=2.4 fz=0.025 n=8000 d=6 z=3 mode=up)")
    dressup = SimpleNamespace(Base=SimpleNamespace(Base=pocket, Path=None), Path=None)
    assert post.cutting_conditions(dressup) == post.cutting_conditions(pocket)
    assert post.cutting_conditions(SimpleNamespace(Label="G54", Path=None)) == []


def test_unknown_flutes_leave_out_flutes_and_feed_per_tooth():
    post = load_post_module()
    profile = SimpleNamespace(ToolController=tool_controller(flutes=0), StepDown=Quantity(6.0),
                              StartDepth=Quantity(3.0), FinalDepth=Quantity(0.0), Direction="CW", Side="Outside",
                              UseComp=True, Path=None)
    assert post.cutting_conditions(profile) == [("ap", "3"), ("n", "8000"), ("d", "6"), ("mode", "up")]


@pytest.mark.parametrize("direction, side, spindle, mode", [
    ("CCW", "Outside", "Forward", "down"), ("CW", "Outside", "Forward", "up"),
    ("CW", "Inside", "Forward", "down"), ("CCW", "Outside", "Reverse", "up"), ("CCW", "Outside", "None", None)])
def test_profile_direction_and_side_give_down_or_up_milling(direction, side, spindle, mode):
    post = load_post_module()
    op = SimpleNamespace(Direction=direction, Side=side, UseComp=True)
    assert post._cut_mode(op, SimpleNamespace(SpindleDir=spindle)) == mode


def test_our_arguments_are_taken_and_the_rest_go_to_linuxcnc():
    post = load_post_module()
    opts, rest = post.split_arguments("--no-header --machine 'my machine.toml' --mode comprehensive --tol-um 2 "
                                      "--precision 4 --modal")
    assert (opts.machine, opts.mode, opts.tol_um) == ("my machine.toml", "comprehensive", "2")
    assert rest == "--no-header --precision 4 --modal --no-show-editor"
    with pytest.raises(post.TrueaxisPostError, match="--machine FILE is required"):
        post.split_arguments("--no-header")
    with pytest.raises(ValueError, match="invalid choice"):
        post.split_arguments("--machine m.toml --mode fast")


def stand_in(tmp_path, body):
    """An executable stand-in for the trueaxis command: `trueaxis post IN -o OUT ...`."""
    exe = tmp_path / "trueaxis"
    exe.write_text(f"#!{sys.executable}\nimport shutil, sys\nargs = sys.argv[1:]\n" + textwrap.dedent(body))
    exe.chmod(0o755)
    return exe


def test_compensate_runs_the_command_and_returns_its_output(tmp_path, monkeypatch):
    post = load_post_module()
    exe = stand_in(tmp_path, """
        assert args[0] == "post" and args[2] == "-o" and "--machine" in args
        shutil.copyfile(args[1], args[3])
        open(args[3], "a").write("(" + " ".join(args[4:]).replace("(", "") + ")\\n")
    """)
    monkeypatch.setenv("TRUEAXIS_BIN", str(exe))
    opts, _ = post.split_arguments("--machine m.toml --mode none --tol-um 0.5 --max-correction-mm 0.2")
    out = post.compensate("G0 X1\n", opts)
    assert out == f"G0 X1\n(--machine {os.path.abspath('m.toml')} --mode none --tol-um 0.5 --max-correction-mm 0.2)\n"


def echoing_stand_in(tmp_path, monkeypatch):
    """A stand-in for the trueaxis command that copies the program and appends the options it was given."""
    exe = stand_in(tmp_path, """
        shutil.copyfile(args[1], args[3])
        open(args[3], "a").write("(" + " ".join(args[4:]).replace("(", "") + ")\\n")
    """)
    monkeypatch.setenv("TRUEAXIS_BIN", str(exe))


def test_arcs_and_output_mode_arguments_reach_the_command(tmp_path, monkeypatch):
    post = load_post_module()
    echoing_stand_in(tmp_path, monkeypatch)
    for given, passed in (("", ""), (" --arcs", " --arcs"), (" --no-arcs", " --no-arcs"),
                          (" --no-arcs --output-mode tcp", " --no-arcs --output-mode tcp")):
        opts, rest = post.split_arguments("--machine m.toml" + given + " --precision 4")
        assert rest == "--precision 4 --no-show-editor"
        out = post.compensate("G0 X1\n", opts)
        assert out.endswith(f"--mode geometric --tol-um 1{passed})\n"), out


def test_cutting_conditions_given_to_the_post_reach_the_command_not_linuxcnc(tmp_path, monkeypatch):
    # A Profile states no ae: the job's post arguments are where a user gives it; '--ae 2' went to the linuxcnc
    # post's parser, which raised SystemExit inside FreeCAD (a QA pass).
    post = load_post_module()
    echoing_stand_in(tmp_path, monkeypatch)
    opts, rest = post.split_arguments("--machine m.toml --mode comprehensive --ae 2 --ap 1.5 --cut-mode up "
                                      "--precision 4")
    assert rest == "--precision 4 --no-show-editor"
    out = post.compensate("G0 X1\n", opts)
    assert out.endswith("--mode comprehensive --tol-um 1 --ap 1.5 --ae 2 --cut-mode up)\n"), out



def test_a_fixture_machine_short_name_reaches_the_command_as_it_is(tmp_path, monkeypatch):
    # '--machine xh714' was made /FreeCAD's working folder/xh714, which trueaxis could not read, and the error listed
    # the short names as if they could be used (a QA pass): trueaxis post takes them, so the script passes them on
    post = load_post_module()
    echoing_stand_in(tmp_path, monkeypatch)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mill").write_text("")  # a file of that name in the working folder is the file (as for the CLI)
    for given, passed in (("xh714", "xh714"), ("~/m.toml", os.path.expanduser("~/m.toml")),
                          ("m.toml", str(tmp_path / "m.toml")), ("mill", str(tmp_path / "mill"))):
        opts, _ = post.split_arguments(f"--machine {given}")
        assert f"(--machine {passed} --mode geometric" in post.compensate("G0 X1\n", opts), given


@pytest.mark.parametrize("name", ["xh714", "m.toml", "sub/m.toml", "mill", "sub/mill", "nothere", "a.b"])
def test_the_script_tells_a_machine_path_from_a_short_name_as_trueaxis_does(name, tmp_path, monkeypatch):
    from trueaxis.resources import names_a_path

    post = load_post_module()
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    for existing in ("mill", "sub/mill"):
        (tmp_path / existing).write_text("")
    assert post.names_a_path(name) == names_a_path(name)


def test_the_real_command_takes_a_fixture_machine_by_its_short_name(tmp_path, monkeypatch, capsys):
    post = load_post_module()
    monkeypatch.setenv("TRUEAXIS_BIN", trueaxis_exe())
    monkeypatch.chdir(tmp_path)
    by_name, by_path = (post.compensate(SMALL_PROGRAM, post.split_arguments(f"--machine {m} --offsets-zero")[0])
                        for m in ("xh714", XH714))
    assert by_name == by_path and f"machine file {XH714} sha256" in by_name


def test_a_refusal_names_the_block_and_the_reason(tmp_path, monkeypatch):
    post = load_post_module()
    exe = stand_in(tmp_path, """
        sys.stderr.write(args[1] + ":2: corrected Z = 16.0000 lies outside its travel [-400, 0]\\n")
        sys.exit(2)
    """)
    monkeypatch.setenv("TRUEAXIS_BIN", str(exe))
    opts, _ = post.split_arguments("--machine m.toml")
    with pytest.raises(post.TrueaxisPostError) as err:
        post.compensate("G21\nG0 Z16.000 \nM2\n", opts, label="part.ngc")
    assert "part.ngc:2: block 'G0 Z16.000': corrected Z = 16.0000 lies outside its travel" in str(err.value)
    assert "exit 2" in str(err.value)



@pytest.mark.parametrize("given, said", [
    ("--tol-um abc", "argument --tol-um: a path tolerance in um is a number; got 'abc'"),
    ("--max-correction-mm 0,2", "argument --max-correction-mm: a correction bound in mm is a number; got '0,2'")])
def test_an_option_that_takes_a_number_says_which_and_what_it_got(given, said):
    # '--tol-um abc' said "got 'abc', None" (a QA pass): the option, and only its value
    post = load_post_module()
    with pytest.raises(ValueError) as err:
        post.split_arguments("--machine m.toml " + given)
    assert str(err.value) == said


@pytest.mark.parametrize("given, status, said", [
    ("--machine {tmp}/nothere.toml", 2,
     "trueaxis post: --machine {tmp}/nothere.toml: cannot read the file: no such file"),
    ("--machine nothere", 2, "trueaxis post: no machine file 'nothere' (fixture machines: "),
    ("--machine {tmp}/broken.toml", 3, "{tmp}/broken.toml: not valid TOML: "),
    ("--machine xh714 --tol-um -1", 2, "trueaxis post: error: argument --tol-um: '-1' must be > 0"),
    ("--machine xh714 --var {tmp}/none.var", 3, "{tmp}/none.var: parameter file not found")])
def test_an_option_or_file_the_command_cannot_use_is_said_as_such(given, status, said, tmp_path, monkeypatch):
    # a missing machine file was "trueaxis refused the program", with a note on the program's line numbers (a QA
    # pass): what the command could not use is said as such (argparse's usage lines left out)
    post = load_post_module()
    monkeypatch.setenv("TRUEAXIS_BIN", trueaxis_exe())
    (tmp_path / "broken.toml").write_text("[machine\n")
    opts, _ = post.split_arguments(given.format(tmp=tmp_path))
    with pytest.raises(post.TrueaxisPostError) as err:
        post.compensate(SMALL_PROGRAM, opts, label=str(tmp_path / "part.ngc"))
    lines = str(err.value).splitlines()
    assert lines[0] == f"trueaxis post: trueaxis cannot use the options or the files given to the post (exit " \
        f"{status}); nothing was written:"
    assert len(lines) == 2 and lines[1].startswith(said.format(tmp=tmp_path)), lines

def test_a_missing_command_says_how_to_point_at_it(monkeypatch):
    post = load_post_module()
    monkeypatch.delenv("TRUEAXIS_BIN", raising=False)
    monkeypatch.setenv("PATH", "")
    opts, _ = post.split_arguments("--machine m.toml")
    with pytest.raises(post.TrueaxisPostError, match="TRUEAXIS_BIN"):
        post.compensate("G0 X1\n", opts)


def test_files_are_written_atomically(tmp_path):
    post = load_post_module()
    target = tmp_path / "part.ngc"
    target.write_text("old\n")
    post.write_atomically(str(target), "G0 X1\n")
    assert target.read_text() == "G0 X1\n"
    assert [p.name for p in tmp_path.iterdir()] == ["part.ngc"]



def test_the_output_gets_the_permissions_the_command_line_gives_it(tmp_path):
    # mkstemp and a rename left the job's program 0600, readable by its owner alone (a QA pass); trueaxis' own
    # outputs (fileio) get the umask's permissions when new and keep their own when replaced, and a symbolic link
    # is written through: the post script does the same (it cannot import trueaxis: FreeCAD's Python)
    from trueaxis.fileio import atomic_write

    post = load_post_module()
    mask = os.umask(0o027)
    try:
        for writer, folder in ((post.write_atomically, tmp_path / "post"), (atomic_write, tmp_path / "cli")):
            folder.mkdir()
            writer(str(folder / "new.ngc"), "G0 X1\n")
            (folder / "kept.ngc").write_text("old\n")
            (folder / "kept.ngc").chmod(0o604)
            writer(str(folder / "kept.ngc"), "G0 X1\n")
            (folder / "target.ngc").write_text("old\n")
            (folder / "link.ngc").symlink_to("target.ngc")
            writer(str(folder / "link.ngc"), "G0 X1\n")
    finally:
        os.umask(mask)
    for folder in (tmp_path / "post", tmp_path / "cli"):
        assert (folder / "new.ngc").stat().st_mode & 0o777 == 0o640, folder
        assert (folder / "kept.ngc").stat().st_mode & 0o777 == 0o604, folder
        assert (folder / "link.ngc").is_symlink() and (folder / "target.ngc").read_text() == "G0 X1\n", folder
        assert sorted(p.name for p in folder.iterdir()) == ["kept.ngc", "link.ngc", "new.ngc", "target.ngc"]


def test_install_copies_the_script_into_the_given_folder(tmp_path):
    installed = install_post(tmp_path / "Macro")
    assert installed == tmp_path / "Macro" / "trueaxis_post.py"
    assert installed.read_bytes() == post_script_path().read_bytes()


def test_macro_folder_follows_freecad_settings_then_its_data_folder(tmp_path, monkeypatch):
    monkeypatch.delenv("XDG_CONFIG_HOME", raising=False)
    monkeypatch.delenv("XDG_DATA_HOME", raising=False)
    home = tmp_path / "home"
    assert default_macro_dir(home) == home / ".local" / "share" / "FreeCAD" / "Macro"  # nothing yet: XDG default
    (home / ".FreeCAD").mkdir(parents=True)
    assert default_macro_dir(home) == home / ".FreeCAD" / "Macro"  # an older FreeCAD's user folder
    custom = tmp_path / "my macros"
    custom.mkdir()
    cfg = home / ".config" / "FreeCAD" / "user.cfg"
    cfg.parent.mkdir(parents=True)
    cfg.write_text(f"""<?xml version="1.0" encoding="UTF-8" standalone="no" ?>
<FCParameters><FCParamGroup Name="Root"><FCParamGroup Name="BaseApp"><FCParamGroup Name="Preferences">
<FCParamGroup Name="Macro"><FCText Name="MacroPath">{custom}</FCText></FCParamGroup>
</FCParamGroup></FCParamGroup></FCParamGroup></FCParameters>
""")
    assert default_macro_dir(home) == custom
    # a configured folder that does not exist yet is still where FreeCAD looks: the install creates it there (it
    # went to the data folder, where FreeCAD never looked, and said 'installed': a QA pass)
    custom.rmdir()
    assert default_macro_dir(home) == custom
    assert install_post(default_macro_dir(home)) == custom / "trueaxis_post.py" and custom.is_dir()


# --- what trueaxis says of a program it posted: the user's file names, FreeCAD's console ---------------------------

SMALL_PROGRAM = "(begin preamble)\nG21 G90\nG0 Z-100\nG0 X10 Y10\nG1 X50 F500\nM2\n"  # FreeCAD's: a comment first


def warning_lines(text):
    return [line for line in text.splitlines() if line.strip()]


def test_warnings_of_a_posted_program_are_shown_with_the_output_file_and_the_block(tmp_path, monkeypatch, capsys):
    # trueaxis' warnings on stderr named the temporary copy (/tmp/trueaxis_post_.../part.ngc) and were dropped when
    # the post succeeded: the user never heard of a block left uncompensated (a QA pass)
    post = load_post_module()
    exe = stand_in(tmp_path, """
        shutil.copyfile(args[1], args[3])
        sys.stderr.write(args[1] + ":3: the position of X Y is not known here (no absolute move of it before): "
                         "block left as written, uncompensated\\n")
        sys.stderr.write(args[1] + ":1: the program never commands B C: the corrections take them at 0, where "
                         "they must stand when the program runs\\n")
    """)
    monkeypatch.setenv("TRUEAXIS_BIN", str(exe))
    opts, _ = post.split_arguments("--machine m.toml")
    out = post.compensate(SMALL_PROGRAM, opts, label="/jobs/part.ngc")
    assert out == SMALL_PROGRAM
    said = warning_lines(capsys.readouterr().err)
    assert said[:2] == [
        "/jobs/part.ngc:3: block 'G0 Z-100': the position of X Y is not known here (no absolute move of it before): "
        "block left as written, uncompensated",
        # a program-wide warning stands at line 1, here a comment: no block to quote
        "/jobs/part.ngc:1: the program never commands B C: the corrections take them at 0, where they must stand "
        "when the program runs"]
    assert len(said) == 3 and said[2].startswith("trueaxis post: Line numbers refer to the uncompensated program of "
                                                 "FreeCAD's linuxcnc post")
    assert "trueaxis_post_" not in "\n".join(said)


def test_a_program_posted_without_a_word_shows_nothing(tmp_path, monkeypatch, capsys):
    post = load_post_module()
    echoing_stand_in(tmp_path, monkeypatch)
    opts, _ = post.split_arguments("--machine m.toml")
    post.compensate(SMALL_PROGRAM, opts, label="/jobs/part.ngc")
    assert capsys.readouterr().err == ""


def test_strict_reaches_the_command_and_its_refusal_names_the_output_file(tmp_path, monkeypatch):
    post = load_post_module()
    exe = stand_in(tmp_path, """
        assert "--strict" in args
        sys.stderr.write(args[1] + ":3: the position of X Y is not known here: block left as written, "
                         "uncompensated\\n")
        sys.stderr.write("trueaxis post: --strict: 1 warning; " + args[3] + " not written\\n")
        sys.exit(3)
    """)
    monkeypatch.setenv("TRUEAXIS_BIN", str(exe))
    opts, rest = post.split_arguments("--machine m.toml --strict --precision 4")
    assert opts.strict and rest == "--precision 4 --no-show-editor"
    with pytest.raises(post.TrueaxisPostError) as err:
        post.compensate(SMALL_PROGRAM, opts, label="/jobs/part.ngc")
    said = str(err.value)
    assert "/jobs/part.ngc:3: block 'G0 Z-100': the position of X Y is not known here" in said
    assert "trueaxis post: --strict: 1 warning; /jobs/part.ngc not written" in said
    assert "compensated.ngc" not in said and "trueaxis_post_" not in said


def test_the_real_command_warnings_reach_the_user_with_the_output_file(tmp_path, monkeypatch, capsys):
    post = load_post_module()
    monkeypatch.setenv("TRUEAXIS_BIN", trueaxis_exe())
    opts, _ = post.split_arguments(f"--machine {XH714} --offsets-zero")
    out = post.compensate(SMALL_PROGRAM, opts, label=str(tmp_path / "part.ngc"))
    assert out.startswith("(trueaxis post: ")
    said = warning_lines(capsys.readouterr().err)
    assert said[0] == (f"{tmp_path / 'part.ngc'}:3: block 'G0 Z-100': the position of X Y is not known here (no "
                       "absolute move of it before): block left as written, uncompensated")
    assert len(said) == 2 and "trueaxis_post_" not in said[1]
    strict, _ = post.split_arguments(f"--machine {XH714} --offsets-zero --strict")
    with pytest.raises(post.TrueaxisPostError) as err:
        post.compensate(SMALL_PROGRAM, strict, label=str(tmp_path / "part.ngc"))
    assert str(err.value).splitlines()[1:3] == [said[0], f"trueaxis post: --strict: 1 warning; {tmp_path / 'part.ngc'} "
                                                          "not written"]


def test_the_report_names_the_jobs_output_file_not_a_temporary_copy(tmp_path, monkeypatch):
    # A QA pass (a CAM engineer on FreeCAD): with --report, the JSON's source and every warning named the post's
    # temporary copy (/tmp/trueaxis_post_.../report.ngc), deleted by then, and did not say what its line numbers refer
    # to. The real command: the report names the output file and carries the note; nothing of the temporary folder.
    post = load_post_module()
    monkeypatch.setenv("TRUEAXIS_BIN", trueaxis_exe())
    monkeypatch.chdir(tmp_path)
    report = tmp_path / "out" / "rep.json"
    report.parent.mkdir()
    label = str(tmp_path / "out" / "part.ngc")
    opts, _ = post.split_arguments(f"--machine xh714 --offsets-zero --report {report}")
    post.compensate("G21 G90\nG0 Z-100\nG0 X10 Y10 Z-100\nG1 X20 F100\nM2\n", opts, label=label)
    text = report.read_text()
    content = json.loads(text)
    assert "trueaxis_post_" not in text and content["source"] == label
    said = [w for w in content["warnings"] if "is not known here" in w]
    assert len(said) == 1 and said[0].startswith(f"{label}:2: the position of X Y is not known here"), said
    assert content["line_numbers"] == post.LINE_NUMBERS_NOTE
    assert content["moves"] == 2  # the rest of the report as trueaxis wrote it
