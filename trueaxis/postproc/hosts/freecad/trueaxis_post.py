# trueaxis post-processor for FreeCAD CAM (Path workbench): LinuxCNC G-code, compensated with a machine's error twin.
#
# Install: copy this file into FreeCAD's macro folder (`trueaxis freecad install` does it), then choose the post
# processor "trueaxis" in the Job and give it arguments such as
#     --machine /path/to/machine.toml --mode geometric --tol-um 1
# and the control's setup, as for `trueaxis post` (work offsets and tool lengths live in the control; a program that
# selects G54 or G43 H1 is refused unless they are given or --offsets-zero says zero is meant):
#     --var /path/to/linuxcnc.var --tool-table /path/to/tool.tbl --machine-units mm
#     --setup /path/to/setup.toml
#
# What it does, in order:
# 1. writes the G-code exactly as FreeCAD's own `linuxcnc` post does (it runs a fresh copy of that module), with one
#    addition: before each tool change and each operation a structured comment carrying the cutting conditions the
#    job knows, e.g. `(trueaxis: ap=6 ae=3 fz=0.025 n=8000 d=6 z=3 mode=down)` (trueaxis DESIGN §5);
# 2. runs `trueaxis post IN -o OUT --machine FILE --mode M --tol-um T [setup options]` on it (the command is
#    $TRUEAXIS_BIN, or --trueaxis-bin, or `trueaxis` on PATH: FreeCAD's Python does not import trueaxis itself);
#    --machine takes a machine file or a fixture machine's short name, as trueaxis post does;
# 3. writes the compensated program at the output file atomically (temporary file in the same folder, then rename),
#    with the permissions trueaxis gives its own outputs (a new file: the umask's; a replaced one: its own).
# What trueaxis says of a program it posted (a block left uncompensated, a value assumed) goes to FreeCAD's report
# view as warnings, each naming the output file and quoting the block; --strict makes any of them an error.
# If trueaxis refuses the program, export raises TrueaxisPostError naming the block and the reason, and nothing is
# written at the output file.
#
# Script API of FreeCAD 0.20/0.21 (TOOLTIP, TOOLTIP_ARGS, export(objectslist, filename, argstring)); FreeCAD 1.0
# runs such scripts through its wrapper for legacy posts (it calls export(..., "-", args) and writes what it returns).
# This module imports FreeCAD only inside export, so its pure parts can be tested with plain Python.

import argparse
import importlib.util
import json
import os
import re
import shlex
import shutil
import stat
import subprocess
import sys
import tempfile

TOOLTIP = """
trueaxis: LinuxCNC G-code from FreeCAD's linuxcnc post, with the job's cutting conditions as
(trueaxis: ...) comments, compensated for the machine's geometric (and force-induced) errors by
the trueaxis command line. Needs --machine FILE (or a fixture machine's short name); the
trueaxis command is taken from --trueaxis-bin, $TRUEAXIS_BIN or PATH.
"""

UNITS = "G21"  # read by FreeCAD to label the post processor's units (metric unless --inches is passed on)

MODES = ("none", "geometric", "comprehensive")

# FreeCAD's legacy LinuxCNC post: its module name across versions (0.20: PathScripts; 0.21 and 1.0: Path.Post;
# later releases keep the script API under the "_legacy" name).
LINUXCNC_MODULES = (
    "Path.Post.scripts.linuxcnc_legacy_post",
    "Path.Post.scripts.linuxcnc_post",
    "PathScripts.post.linuxcnc_post",
    "linuxcnc_post",
)


class TrueaxisPostError(RuntimeError):
    """The trueaxis post could not produce a compensated program; the message says which block and why."""


class _ArgumentError(ValueError):
    pass


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of exiting: an exit inside FreeCAD would take the application with it."""

    def error(self, message):
        raise _ArgumentError(message)


def _numeric(what):
    """An argparse type: the text of a number, kept as written (trueaxis checks its range); ``what`` the option
    takes, for the message."""
    def number(text):
        try:
            float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} is a number; got {text!r}") from None
        return text
    return number


def _build_parser():
    p = _Parser(prog="trueaxis", add_help=False, allow_abbrev=False)
    p.add_argument("--machine", help="machine file (TOML) of the machine that will run the program, or a fixture "
                   "machine's short name (xh714, nmv1500dcg, ...), as for trueaxis post (required)")
    p.add_argument("--mode", default="geometric", choices=MODES,
                   help="none | geometric | comprehensive (default geometric)")
    p.add_argument("--tol-um", default="1", type=_numeric("a path tolerance in um"),
                   help="path tolerance, um (default 1)")
    p.add_argument("--max-correction-mm", default=None, type=_numeric("a correction bound in mm"),
                   help="largest correction allowed, mm (trueaxis' default 0.5)")
    p.add_argument("--report", default=None, help="also write trueaxis' report (JSON) here")
    p.add_argument("--var", default=None, help="the control's setup: LinuxCNC parameter file (work offsets, G92)")
    p.add_argument("--tool-table", default=None, help="the control's setup: LinuxCNC tool table (tool lengths)")
    p.add_argument("--machine-units", default=None, choices=("mm", "inch"),
                   help="units of the .var and tool table (LinuxCNC's LINEAR_UNITS; trueaxis' default mm)")
    p.add_argument("--setup", default=None, help="the control's setup file (TOML) for other controls")
    p.add_argument("--offsets-zero", action="store_true",
                   help="work offsets and tool lengths that the setup does not give are zero")
    p.add_argument("--arcs", dest="arcs", action="store_const", const=True, default=None,
                   help="arcs fitted to the corrected path as G2/G3 (trueaxis' default: on for a three-axis mill)")
    p.add_argument("--no-arcs", dest="arcs", action="store_const", const=False,
                   help="arcs whose correction varies along them become straight pieces")
    p.add_argument("--output-mode", default=None, choices=("joint", "tcp"),
                   help="joint positions, or tool-centre-point positions (trueaxis' default: the machine file's)")
    p.add_argument("--strict", action="store_true",
                   help="every warning of trueaxis is an error: nothing is written (trueaxis post --strict)")
    for key, what in (("ap", "axial depth, mm"), ("ae", "radial engagement, mm"), ("fz", "feed per tooth, mm"),
                      ("n", "spindle speed, rpm"), ("d", "tool diameter, mm"), ("z", "flutes")):
        p.add_argument(f"--{key}", default=None, help=f"comprehensive mode: {what} for every operation (over what the "
                       "job's operations state)")
    p.add_argument("--cut-mode", default=None, choices=("down", "up"), help="comprehensive mode: down or up milling")
    p.add_argument("--trueaxis-bin", default=None,
                   help="the trueaxis executable (default: $TRUEAXIS_BIN, else trueaxis on PATH)")
    p.add_argument("--no-show-editor", action="store_true", help="don't pop up the editor before writing output")
    return p


parser = _build_parser()


def split_arguments(argstring):
    """(our options, argument string for the linuxcnc post) from the job's post-processor argument string.

    Our options are parsed here; everything else (--no-header, --no-comments, --precision, ...) goes to linuxcnc
    unchanged, always with --no-show-editor (the editor, if any, shows the compensated program).
    """
    ours, rest = parser.parse_known_args(shlex.split(argstring or ""))
    if not ours.machine:
        raise TrueaxisPostError("trueaxis post: --machine FILE is required (the machine file of the machine that "
                                "will run this program)")
    return ours, " ".join(shlex.quote(a) for a in rest + ["--no-show-editor"])


# --- cutting conditions: what the job knows ------------------------------------------------------------------------

def _number(value):
    """A quantity's value in FreeCAD's internal units (mm, mm/s), or a plain number; None when unset."""
    if value is None:
        return None
    value = getattr(value, "Value", value)
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def _feed_mm_per_min(speed):
    if speed is None:
        return None
    if hasattr(speed, "getValueAs"):
        return float(speed.getValueAs("mm/min"))
    value = _number(speed)  # internal unit mm/s
    return None if value is None else value * 60.0


def _format(value):
    """Shortest plain decimal for a comment field: 8000, 6, 0.025 (no exponent)."""
    text = format(value, ".6g")
    if "e" in text:
        text = f"{value:.6f}".rstrip("0").rstrip(".")
    return text


def _operation_of(obj):
    """The operation under a chain of dressups (a dressup's Base is the path object it dresses)."""
    seen = 0
    while not hasattr(obj, "ToolController") and hasattr(getattr(obj, "Base", None), "Path") and seen < 50:
        obj = obj.Base
        seen += 1
    return obj


def _is_tool_controller(obj):
    return hasattr(obj, "Tool") and hasattr(obj, "SpindleSpeed") and hasattr(obj, "ToolNumber")


def _cut_mode(op, tc):
    """'down' (climb) or 'up' (conventional) milling, when the operation says it and the spindle turns."""
    spindle = getattr(tc, "SpindleDir", "Forward")
    if spindle not in ("Forward", "Reverse"):
        return None
    climb = None
    cut_mode = getattr(op, "CutMode", None)
    if cut_mode in ("Climb", "Conventional"):  # pocket, face milling, adaptive, ...
        climb = cut_mode == "Climb"
    elif getattr(op, "Direction", None) in ("CW", "CCW") and getattr(op, "Side", None) in ("Outside", "Inside") \
            and getattr(op, "UseComp", True):
        # Profile (FreeCAD 0.20/0.21): Direction is the way round the outer boundary. With a spindle turning M3
        # (clockwise seen from above) the teeth climb into material on the left of the feed: an outside profile
        # run CCW, or an inside one run CW, is down milling.
        climb = (op.Direction == "CCW") != (op.Side == "Inside")
    if climb is None:
        return None
    if spindle == "Reverse":
        climb = not climb
    return "down" if climb else "up"


def cutting_conditions(obj):
    """Fields ``ap ae fz n d z mode`` (DESIGN §5) that FreeCAD knows for a tool controller or an operation.

    Only what the job states is returned: spindle speed (ToolController.SpindleSpeed), tool diameter and flutes
    (Tool.Diameter, Tool.Flutes when > 0), feed per tooth = HorizFeed / (n z), axial depth = StepDown (the deepest
    pass; the last pass of a depth that is not a multiple of it is shallower), radial engagement = StepOver % x d for
    operations that step over (pockets, facing), down/up milling from the operation's CutMode or Direction and Side.
    Returns [(key, text)] in DESIGN §5's order; empty for other objects (fixtures, comments, ...).
    """
    if not hasattr(obj, "ToolController") and _is_tool_controller(obj):
        tc, op = obj, None
    else:
        op = _operation_of(obj)
        tc = getattr(op, "ToolController", None)
        if tc is None:
            return []
    tool = getattr(tc, "Tool", None)
    n = _number(getattr(tc, "SpindleSpeed", None))
    d = _number(getattr(tool, "Diameter", None))
    z = _number(getattr(tool, "Flutes", None))
    n = n if n and n > 0 else None
    d = d if d and d > 0 else None
    z = int(z) if z and z >= 1 else None
    fields = {}
    if op is not None:
        step_down = _number(getattr(op, "StepDown", None))
        start, final = _number(getattr(op, "StartDepth", None)), _number(getattr(op, "FinalDepth", None))
        if step_down and step_down > 0:
            depth = start - final if start is not None and final is not None else None
            fields["ap"] = min(step_down, depth) if depth and depth > 0 else step_down
        step_over = _number(getattr(op, "StepOver", None))
        if d and step_over and 0 < step_over <= 100:
            fields["ae"] = step_over / 100.0 * d
        feed = _feed_mm_per_min(getattr(tc, "HorizFeed", None))
        if feed and n and z:
            fields["fz"] = feed / (n * z)
    if n:
        fields["n"] = n
    if d:
        fields["d"] = d
    if z:
        fields["z"] = z
    out = [(k, _format(v)) for k, v in fields.items()]
    if op is not None:
        mode = _cut_mode(op, tc)
        if mode:
            out.append(("mode", mode))
    return out


def conditions_comment(fields):
    """``(trueaxis: n=8000 d=6 z=3)`` for the fields of cutting_conditions; '' when there are none."""
    if not fields:
        return ""
    return "(trueaxis: " + " ".join(f"{k}={v}" for k, v in fields) + ")"


# --- the LinuxCNC post, with the comments ---------------------------------------------------------------------------

def _linuxcnc_origin():
    for name in LINUXCNC_MODULES:
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError, AttributeError):
            continue
        if spec is not None and spec.origin and spec.origin.endswith(".py"):
            return spec.origin
    return None


def load_linuxcnc():
    """A fresh copy of FreeCAD's linuxcnc post module.

    Fresh on every export: that module keeps its options in globals that --no-header and friends only ever switch
    off, and stamps its header with the time it was imported.
    """
    origin = _linuxcnc_origin()
    if origin is None:
        raise TrueaxisPostError("trueaxis post: FreeCAD's linuxcnc post was not found (looked for "
                                + ", ".join(LINUXCNC_MODULES) + ")")
    spec = importlib.util.spec_from_file_location("linuxcnc_post", origin)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not (callable(getattr(module, "export", None)) and callable(getattr(module, "parse", None))):
        raise TrueaxisPostError(f"trueaxis post: {origin} is not the script-style linuxcnc post (no export/parse)")
    return module


def linuxcnc_gcode(objectslist, argstring):
    """G-code of FreeCAD's linuxcnc post for the objects, with a conditions comment before each object's path."""
    lc = load_linuxcnc()
    parse = lc.parse

    def parse_with_conditions(pathobj):
        comment = conditions_comment(cutting_conditions(pathobj))
        head = lc.linenumber() + comment + "\n" if comment else ""
        return head + parse(pathobj)

    lc.parse = parse_with_conditions
    try:
        gcode = lc.export(objectslist, "-", argstring)
    except SystemExit:  # its argparse on an option it does not know: an exit inside FreeCAD would take FreeCAD along
        raise TrueaxisPostError(f"trueaxis post: an option neither trueaxis nor FreeCAD's linuxcnc post knows, or a "
                                f"value it cannot take, among {argstring!r}\n{TOOLTIP_ARGS}") from None
    except ValueError as exc:  # a value it takes and then cannot use (--precision abc)
        raise TrueaxisPostError(f"trueaxis post: FreeCAD's linuxcnc post cannot use its options {argstring!r}: "
                                f"{exc}") from None
    if gcode is None:
        raise TrueaxisPostError(f"trueaxis post: FreeCAD's linuxcnc post refused the job (arguments {argstring!r}, "
                                "or an object that is not a path: see the report view)")
    return gcode, lc


# --- compensation by the trueaxis command ---------------------------------------------------------------------------

def trueaxis_command(opts):
    """The trueaxis executable: --trueaxis-bin, else $TRUEAXIS_BIN, else `trueaxis` on PATH."""
    exe = opts.trueaxis_bin or os.environ.get("TRUEAXIS_BIN") or shutil.which("trueaxis")
    if not exe:
        raise TrueaxisPostError("trueaxis post: the trueaxis command was not found: set TRUEAXIS_BIN to the trueaxis "
                                "executable (e.g. /path/to/.venv/bin/trueaxis), pass --trueaxis-bin, or put it on PATH")
    return os.path.expanduser(exe)


_DIAGNOSTIC = re.compile(r"^(?P<file>.+?):(?P<line>\d+): (?P<reason>.*)$")
_NOT_A_BLOCK = re.compile(r"^(?:N\d+\s*)?(?:\([^)]*\)\s*)*(?:;.*)?%?$")  # blank, comments only, or %
LINE_NUMBERS_NOTE = ("Line numbers refer to the uncompensated program of FreeCAD's linuxcnc post (post with the "
                     "linuxcnc post processor to see it).")


def warn(message):
    """A warning for the user: FreeCAD's report view (Console.PrintWarning) inside FreeCAD, else stderr."""
    try:
        import FreeCAD
    except ImportError:
        print(message, file=sys.stderr)
        return
    FreeCAD.Console.PrintWarning(message + "\n")


def _explain(stderr, temporary, program_lines, label):
    """trueaxis' messages as the user can read them: its ``file:line: reason`` lines about the program with the block
    quoted, and every temporary path (``temporary``: the program and the output written in the post's temporary
    folder, which the user never sees) named ``label``, the job's output file. A list of lines."""
    program_path = temporary[0]
    out = []
    for line in stderr.strip().splitlines():
        m = _DIAGNOSTIC.match(line)
        if m and os.path.basename(m.group("file")) == os.path.basename(program_path):
            k = int(m.group("line"))
            block = program_lines[k - 1].strip() if 0 < k <= len(program_lines) else "?"
            quoted = "" if _NOT_A_BLOCK.match(block) else f" block '{block}':"  # (a whole program's stand at line 1)
            out.append(f"{label}:{k}:{quoted} {m.group('reason')}")
            continue
        for path in temporary:
            line = line.replace(path, label)
        out.append(line)
    return out


def names_a_path(name):
    """Whether trueaxis reads --machine ``name`` as a path (a ``.toml`` name, or a file that exists) rather than as a
    fixture machine's short name ('xh714'): trueaxis.resources.names_a_path's rule, replicated (FreeCAD's Python does
    not import trueaxis), after ``~`` is expanded."""
    path = os.path.expanduser(name)
    return os.path.splitext(path)[1] == ".toml" or os.path.exists(path)


def _command(exe, program, output, opts, report=None):
    """The `trueaxis post` command line for the post's options: paths made absolute (FreeCAD's working folder is not
    the user's), a fixture machine's short name passed as it is (trueaxis finds it); ``report``: where trueaxis
    writes its report (a temporary file: ``_write_report`` gives it the user's names)."""
    machine = os.path.abspath(os.path.expanduser(opts.machine)) if names_a_path(opts.machine) else opts.machine
    cmd = [exe, "post", program, "-o", output, "--machine", machine, "--mode", opts.mode, "--tol-um", str(opts.tol_um)]
    if opts.max_correction_mm is not None:
        cmd += ["--max-correction-mm", str(opts.max_correction_mm)]
    if report:
        cmd += ["--report", report]
    for option, value in (("--var", opts.var), ("--tool-table", opts.tool_table), ("--setup", opts.setup)):
        if value:
            cmd += [option, os.path.abspath(os.path.expanduser(value))]
    if opts.machine_units:
        cmd += ["--machine-units", opts.machine_units]
    for flag in ("offsets_zero", "strict"):
        if getattr(opts, flag):
            cmd.append("--" + flag.replace("_", "-"))
    if opts.arcs is not None:
        cmd.append("--arcs" if opts.arcs else "--no-arcs")
    if opts.output_mode:
        cmd += ["--output-mode", opts.output_mode]
    for key in ("ap", "ae", "fz", "n", "d", "z", "cut_mode"):  # the cutting conditions, as `trueaxis post` takes them
        if getattr(opts, key, None) is not None:
            cmd += [f"--{key.replace('_', '-')}", str(getattr(opts, key))]
    return cmd


def _names_the_program(said, label):
    """Whether any of the lines from _explain is about the program (``label:line: ...``)."""
    about_the_program = re.compile(re.escape(label) + r":\d+: ")
    return any(about_the_program.match(line) for line in said)


def _failure(status, said, label):
    """The message of a `trueaxis post` that wrote nothing (exit ``status``; ``said``: its lines from _explain, the
    program named ``label``): a refused program names its blocks; a file or an option it cannot use (exit 2: usage,
    3: a machine or setup file refused) is said as such, without argparse's usage lines."""
    if _names_the_program(said, label):
        return f"trueaxis refused the program (exit {status}); nothing was written.\n" + "\n".join(said) + "\n" + \
            LINE_NUMBERS_NOTE
    if any(line.startswith("usage: ") for line in said):
        said = [line for line in said if not line.startswith(("usage: ", " "))]
    why = "\n".join(said) or "(no message)"
    if status in (2, 3):
        return f"trueaxis post: trueaxis cannot use the options or the files given to the post (exit {status}); " \
            f"nothing was written:\n{why}"
    return f"trueaxis post: the trueaxis command failed (exit {status}); nothing was written:\n{why}"


def compensate(gcode, opts, label="program.ngc"):
    """The program compensated by `trueaxis post` (text); TrueaxisPostError with trueaxis' reasons on failure.

    label : the name the user knows the program by (the job's output file); trueaxis' messages name it, not the
    temporary copy. What trueaxis says of a program it posted is shown (``warn``) before the text is returned.
    """
    exe = trueaxis_command(opts)
    with tempfile.TemporaryDirectory(prefix="trueaxis_post_") as work:
        src = os.path.join(work, os.path.basename(label) or "program.ngc")
        dst = os.path.join(work, "compensated.ngc")
        report = os.path.join(work, "report.json") if opts.report else None
        with open(src, "w", encoding="utf-8", newline="") as f:
            f.write(gcode)
        try:
            proc = subprocess.run(_command(exe, src, dst, opts, report), stdin=subprocess.DEVNULL, capture_output=True,
                                  text=True)
        except OSError as exc:
            raise TrueaxisPostError(f"trueaxis post: could not run {exe}: {exc}") from None
        said = _explain(proc.stderr or "", (src, dst), gcode.splitlines(), label)
        if proc.returncode != 0 or not os.path.exists(dst):
            said = said or _explain(proc.stdout or "", (src, dst), gcode.splitlines(), label)
            raise TrueaxisPostError(_failure(proc.returncode, said, label))
        for line in said:
            warn(line)
        if _names_the_program(said, label):
            warn("trueaxis post: " + LINE_NUMBERS_NOTE)
        if report:
            _write_report(report, os.path.abspath(os.path.expanduser(opts.report)), (src, dst), label)
        with open(dst, "r", encoding="utf-8", newline="") as f:
            return f.read()


def _write_report(report, target, temporary, label):
    """trueaxis' report (JSON at ``report``) written at ``target`` with the names the user knows: the temporary copies'
    paths (``temporary``) replaced by ``label`` (the job's output file) wherever they stand (its source, its
    warnings), and the note on what its line numbers refer to. (A QA pass: the report named a deleted temporary
    file, its line numbers unexplained.)"""
    def named(value):
        if isinstance(value, str):
            for path in temporary:
                value = value.replace(path, label)
            return value
        if isinstance(value, list):
            return [named(v) for v in value]
        if isinstance(value, dict):
            return {k: named(v) for k, v in value.items()}
        return value

    with open(report, "r", encoding="utf-8") as f:
        content = named(json.load(f))
    content["line_numbers"] = LINE_NUMBERS_NOTE
    write_atomically(target, json.dumps(content, indent=2, allow_nan=False))


_CONDITIONS_LINE = re.compile(r"^(?:N\d+ ?)?\(trueaxis: [^)]*\)\r?\n", re.MULTILINE)
_N_WORD = re.compile(r"^N\d+ ?")
_HEADER = ("(trueaxis post: ", "(trueaxis setup: ")
# decimals trueaxis writes at least (mm, inch): fewer would round the micrometre corrections away
MIN_DECIMALS = {"mm": 5, "inch": 6}


def _linuxcnc_option(args, name):
    """The value of ``--name V`` / ``--name=V`` among the linuxcnc post's arguments (a list), True for a bare flag,
    else None."""
    for k, a in enumerate(args):
        if a == name:
            return args[k + 1] if k + 1 < len(args) and not args[k + 1].startswith("--") else True
        if a.startswith(name + "="):
            return a.split("=", 1)[1]
    return None


def honour_linuxcnc_options(text, linuxcnc_args):
    """The compensated program with the linuxcnc post's output options applied to what trueaxis added too:
    ``--no-comments``: the structured cutting-conditions comments this script put in for trueaxis are taken out
    again (the header that names the machine file stays: it is what makes a second post refuse the program);
    ``--line-numbers``: every block after the header is numbered again, split blocks included, from the linuxcnc
    post's first number in its steps of 10. Returns (text, notes): notes for the user (``--precision`` below what the
    corrections need: the compensated blocks keep trueaxis' decimals)."""
    args = shlex.split(linuxcnc_args or "")
    notes = []
    precision = _linuxcnc_option(args, "--precision")
    if precision not in (None, True):
        try:
            asked = int(precision)
        except ValueError:
            asked = None
        units = "inch" if _linuxcnc_option(args, "--inches") else "mm"
        if asked is not None and asked < MIN_DECIMALS[units]:
            notes.append(f"trueaxis post: --precision {asked}: the compensated blocks carry {MIN_DECIMALS[units]} "
                         f"decimals ({units}): fewer would round the corrections (micrometres) away")
    if _linuxcnc_option(args, "--no-comments"):
        text = _CONDITIONS_LINE.sub("", text)
    if _linuxcnc_option(args, "--line-numbers"):
        lines = text.splitlines(keepends=True)
        numbers = [int(m.group(0)[1:].strip()) for line in lines if (m := _N_WORD.match(line))]
        n, step = (numbers[0] if numbers else 100), 10  # the linuxcnc post's LINENR and LINEINCR
        out = []
        for line in lines:
            if line.startswith(_HEADER) or not line.strip() or line.strip() == "%":
                out.append(line)
                continue
            out.append(f"N{n} " + _N_WORD.sub("", line, count=1))
            n += step
        text = "".join(out)
    return text, notes


def write_atomically(filename, text):
    """Write text at filename through a temporary file in the same folder and a rename, as trueaxis writes its own
    outputs (trueaxis/fileio.py's rule, replicated here: FreeCAD's Python does not import trueaxis): a symbolic link
    is written through (its target replaced, the link kept); a new file gets the permissions the umask gives (mkstemp
    alone leaves 0600, for its owner only), a replaced file keeps its own."""
    target = os.path.realpath(filename)
    if os.path.exists(target):
        mode = stat.S_IMODE(os.stat(target).st_mode)
    else:
        umask = os.umask(0o022)  # read the umask: set one, put it back
        os.umask(umask)
        mode = 0o666 & ~umask
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(target) + ".", suffix=".tmp",
                               dir=os.path.dirname(target))
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _show_editor(lc, gcode):
    """FreeCAD's G-code editor on the compensated program, as the linuxcnc post shows it (GUI only)."""
    post_utils = getattr(lc, "PostUtils", None)
    if post_utils is None or len(gcode) > 100000:
        return gcode
    dia = post_utils.GCodeEditorDialog()
    dia.editor.setText(gcode)
    return dia.editor.toPlainText() if dia.exec_() else gcode


def export(objectslist, filename, argstring):
    """Post the objects (tool controllers, operations, fixtures) to `filename` ('-': return only); returns the G-code.

    Raises TrueaxisPostError when the arguments are wrong or trueaxis refuses the program; then nothing is written.
    """
    import FreeCAD

    try:
        opts, linuxcnc_args = split_arguments(argstring)
    except _ArgumentError as exc:
        raise TrueaxisPostError(f"trueaxis post: {exc}\n{TOOLTIP_ARGS}") from None
    gcode, lc = linuxcnc_gcode(objectslist, linuxcnc_args)
    label = filename if filename and filename != "-" else "program.ngc"  # the job's output file, as FreeCAD gave it
    try:
        final = compensate(gcode, opts, label)
    except TrueaxisPostError as exc:
        FreeCAD.Console.PrintError(str(exc) + "\n")
        raise
    final, notes = honour_linuxcnc_options(final, linuxcnc_args)
    for note in notes:
        warn(note)
    if FreeCAD.GuiUp and not opts.no_show_editor:
        final = _show_editor(lc, final)
    if filename and filename != "-":
        write_atomically(filename, final)
    return final


def _tooltip_args():
    text = parser.format_help()
    try:
        origin = _linuxcnc_origin()
    except Exception:  # outside FreeCAD: our own options only
        origin = None
    if origin:
        try:
            text += "\nPassed on to FreeCAD's linuxcnc post:\n" + load_linuxcnc().TOOLTIP_ARGS
        except Exception:
            pass
    return text


TOOLTIP_ARGS = _tooltip_args()
