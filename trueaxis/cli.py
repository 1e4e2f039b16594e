"""The command line: ``trueaxis <command>`` (and ``inspect`` = ``trueaxis inspect``).

Thin glue: parse arguments, call the package, print. A usage error (an option, a value, a path) ends with one line on
stderr and exit status 2, never a traceback; an input the product refuses (a program, CL data, a machine file, a
setup, a cloud: ``file:line: reason``) with exit status 3, nothing written, or a computed result it refuses (an
identification that does not explain the part, with --write) with exit status 3, its report written, the twin not; a
failure of the system (a file that cannot be read or
written) with 1 (README "How it fails").
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

from .fileio import Interrupted, json_text

EXIT_BAD_INPUT = 2  # usage: an option, a value or a path
EXIT_REFUSED = 3  # an input or a computed result refused: nothing written


class UsageError(ValueError):
    """Bad command-line input: printed as one line, exit status 2."""


def _parse_at(text: str, machine) -> np.ndarray:
    """'X=10,Y=-5,B=30' -> (n_axes,) pose in mm and rad (rotary words in degrees). Every axis of ``machine`` once,
    inside its travel (the error tables are not extrapolated silently); UsageError otherwise."""
    axis_names, rotary = machine.axis_names, machine.rotary_axes
    pose = np.zeros(len(axis_names))
    given = []
    for item in filter(None, (s.strip() for s in text.split(","))):
        if "=" not in item:
            raise UsageError(f"--at: expected AXIS=VALUE, got {item!r}")
        name, value = (s.strip() for s in item.split("=", 1))
        name = name.upper()
        if name not in axis_names:
            raise UsageError(f"--at: the machine has no axis {name} (its axes: {' '.join(axis_names)})")
        try:
            v = float(value)
        except ValueError:
            raise UsageError(f"--at: {name}={value!r} is not a number") from None
        if not np.isfinite(v):
            raise UsageError(f"--at: {name} must be finite")
        if name in given:
            raise UsageError(f"--at: {name} given twice")
        given.append(name)
        pose[axis_names.index(name)] = np.radians(v) if name in rotary else v
        axis = machine.axes[name]
        if not axis.within_travel(pose[axis_names.index(name)]):
            lo, hi = np.degrees(axis.travel) if name in rotary else axis.travel
            raise UsageError(f"--at: {name}={v:g} lies outside its travel [{lo:g}, {hi:g}] "
                             f"{'deg' if name in rotary else 'mm'} (the error tables end there)")
    missing = [a for a in axis_names if a not in given]
    if missing:
        raise UsageError(f"--at: give every axis of the machine ({' '.join(axis_names)}); missing: {' '.join(missing)}")
    return pose


def _plain(values, unit: str = "") -> str:
    """Numbers as a reader writes them: '[0, 0, -100] mm', not numpy's reprs."""
    return "[" + ", ".join(f"{float(v):g}" for v in np.ravel(values)) + "]" + (f" {unit}" if unit else "")


def _parse_vector(text: str, option: str, n: int = 3) -> np.ndarray:
    try:
        v = np.array([float(s) for s in text.split(",")])
    except ValueError:
        raise UsageError(f"{option}: expected {n} comma-separated numbers, got {text!r}") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise UsageError(f"{option}: expected {n} finite comma-separated numbers, got {text!r}")
    return v


def _number(kind=float, *, low=None, high=None, low_open=False):
    """An argparse type: a finite ``kind`` within [low, high] (``low_open``: strictly above low). NaN, infinities and
    out-of-range values are usage errors (exit 2) before any work starts; a NaN bound would otherwise switch a safety
    check off silently."""
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'a whole number' if kind is int else 'a number'}") \
                from None
        if not np.isfinite(v):
            raise argparse.ArgumentTypeError(f"{text!r} must be finite")
        if low is not None and (v <= low if low_open else v < low):
            raise argparse.ArgumentTypeError(f"{text!r} must be {'>' if low_open else '>='} {low:g}")
        if high is not None and v > high:
            raise argparse.ArgumentTypeError(f"{text!r} must be <= {high:g}")
        return v
    return parse


POSITIVE = _number(low=0.0, low_open=True)
NON_NEGATIVE = _number(low=0.0)


def _non_negative_list(text: str) -> list:
    """An argparse type: comma-separated finite numbers >= 0."""
    parts = text.split(",")
    if len(parts) == 1 and len(text.split()) > 1:
        raise argparse.ArgumentTypeError(f"{text!r}: separate the numbers with commas (or repeat the option)")
    return [NON_NEGATIVE(t.strip()) for t in parts]


# ---------------------------------------------------------------------------------------------------- commands ----
def cmd_machine_check(args) -> int:
    from .machine import load_machine
    from .resources import machine_file  # a path, or a fixture machine's short name

    from .machine.model import implausible_parameters

    m = load_machine(machine_file(args.file))
    print(
        f"{args.file}: ok: {m.name} ({m.kind}, axes {' '.join(m.axis_names)},"
        f" {len(m.parameter_names())} geometric parameters)"
    )
    large = implausible_parameters(m)
    if large:
        print(f"trueaxis machine check: warning: {args.file}: {large}", file=sys.stderr)
    if m.is_five_axis:  # (G-code posts by the forward kinematics; CL data, test parts and TCP need the inverse)
        from .machine.kinematics import rotary_layout_problem

        problem = rotary_layout_problem(m)
        if problem:
            print(f"trueaxis machine check: warning: {args.file}: {problem}: CL data, the test parts' programs and "
                  "TCP output cannot be made for it", file=sys.stderr)
    return 0


def cmd_machine_nominal(args) -> int:
    from .fileio import atomic_write
    from .machine import load_machine
    from .machine.machine_file import dump_machine
    from .resources import machine_file

    m = load_machine(machine_file(args.file))
    nominal = m.error_free()
    nominal.note = (f"written by trueaxis machine nominal as the error-free twin of {m.name} ({m.source}): every "
                    "error parameter zero then, no force model")
    atomic_write(args.output, dump_machine(nominal))
    print(f"{args.output}: {m.name} with every one of its {len(m.parameter_names())} error parameters zero and no "
          "force model")
    return 0


def cmd_machine_show(args) -> int:
    from .machine import load_machine
    from .resources import machine_file  # a path, or a fixture machine's short name
    from .machine.model import unit_of

    m = load_machine(machine_file(args.file))
    print(f"{m.name}  ({m.kind}; {m.source})")
    if m.note:
        print(f"  note: {m.note}")
    print(f"  bed -> workpiece: {' -> '.join(m.bed_to_workpiece) or '(none)'}")
    print(f"  bed -> tool:      {' -> '.join(m.bed_to_tool) or '(none)'}")
    for a in m.axis_names:
        ax = m.axes[a]
        if ax.is_rotary:
            tr = "unlimited" if ax.travel is None else f"[{np.degrees(ax.travel[0]):g}, {np.degrees(ax.travel[1]):g}] deg"
            print(f"  {a}: rotary about {ax.about}, pivot {_plain(ax.pivot, 'mm')}, travel {tr}")
        else:
            tr = "unlimited" if ax.travel is None else f"[{ax.travel[0]:g}, {ax.travel[1]:g}] mm"
            print(f"  {a}: linear, travel {tr}")
    t = m.tool
    print(f"  tool: length {t.length:g} mm, radius {t.radius:g} mm, {t.flutes} flutes")
    print(f"  part origin in M: {_plain(m.workpiece_origin, 'mm')}")
    print("  location errors:")
    for n in m.location_names():
        print(f"    {n:6s} {m.errors.location.get(n, 0.0):10.3f} {unit_of(n)}")
    for axis, comps in m._component_items():
        for comp, fn in comps:
            print(f"  {comp}: {fn.kind}, {fn.values.size} values ({unit_of(comp)})")
    if m.compliance_um_per_n is not None:
        print(f"  compliance (um/N): {', '.join(_plain(row) for row in m.compliance_um_per_n)}")
    if m.loaded is not None:
        print(f"  loaded parameter set at {_plain(m.loaded_force_n, 'N')}")
    for s in m.surfaces:
        print(f"  response surface: E{s.axis} vs {s.position_axis}, P{s.force_direction.lower()} "
              f"(load {'+' if s.load_sign > 0 else '-'}, {'forward' if s.motion > 0 else 'backward'})")
    if m.cutting:
        print(f"  cutting: {m.cutting}")
    return 0


def cmd_error(args) -> int:
    from .machine import ErrorTwin, load_machine
    from .resources import machine_file  # a path, or a fixture machine's short name

    m = load_machine(machine_file(args.machine))
    pose = _parse_at(args.at, m)
    force = None if args.force_n is None else _parse_vector(args.force_n, "--force-n")
    # Direction of motion of every axis (+1 forward, -1 backward): it chooses among the lathe paper's response surfaces.
    motion = np.full((1, len(m.axis_names)), 1 if args.direction == "forward" else -1)
    dp, du = ErrorTwin(m).volumetric_error(pose[None, :], force_n=force, motion=motion)
    if args.json:
        print(json.dumps({"position_error_um": dp[0].tolist(), "tool_axis_error_urad": du[0].tolist()}))
    else:
        print(f"position error (um, part frame):   dx {dp[0, 0]:+.3f}  dy {dp[0, 1]:+.3f}  dz {dp[0, 2]:+.3f}")
        print(f"tool-axis error (urad, part frame): {du[0, 0]:+.3f}  {du[0, 1]:+.3f}  {du[0, 2]:+.3f}")
    return 0


def cmd_post(args) -> int:
    from .machine import load_machine
    from .resources import machine_file  # a path, or a fixture machine's short name
    from .postproc.post import decode_program, post_text, resolve_setup

    # options that would change nothing are refused, not ignored (a QA pass posted with --ap in geometric mode)
    cutting = [{"f": "--f-rev"}.get(k, f"--{k.replace('_', '-')}") for k in ("ap", "ae", "fz", "n", "d", "z",
                                                                               "cut_mode", "f", "vc")
               if getattr(args, k) is not None]
    if cutting and args.mode != "comprehensive":
        raise UsageError(f"{' '.join(cutting)}: cutting conditions apply to --mode comprehensive (the mode is "
                         f"{args.mode})")
    if args.machine_units is not None and not (args.var or args.tool_table):
        raise UsageError("--machine-units: the units of --var and --tool-table; neither is given")
    machine = load_machine(machine_file(args.machine))
    turning = [o for o, k in (("--f-rev", "f"), ("--vc", "vc")) if getattr(args, k) is not None]
    if turning and machine.kind != "lathe":
        raise UsageError(f"{' '.join(turning)}: turning conditions; {machine.name} is a mill (its conditions: --ap --ae "
                         "--fz --n --d --z --cut-mode)")
    setup = resolve_setup(machine, setup=args.setup, var=args.var, tool_table=args.tool_table,
                          machine_units=args.machine_units or "mm", offsets_zero=args.offsets_zero)
    if args.output == "-" and args.report == "-":
        raise UsageError("-o - and --report - both name stdout; name a file for one of them")
    # the program (a file, or stdin read whole), refused as a file would be (NUL bytes); its encoding is the output's
    # (a Latin-1 file's comments came out as UTF-8, which a control reading Latin-1 shows as two characters; QA pass)
    source = "<stdin>" if args.input == "-" else args.input
    if args.input != "-" and not Path(args.input).is_file():
        raise UsageError(f"{args.input}: no such file")
    text, encoding = decode_program(sys.stdin.buffer.read() if args.input == "-" else Path(args.input).read_bytes(),
                                    source)
    conditions = {k: getattr(args, k) for k in ("ap", "ae", "fz", "n", "d", "z", "f", "vc")}
    conditions["mode"] = args.cut_mode
    branch = {"nearest": "nearest", "+1": 1, "-1": -1}[args.cl_branch]
    out, report = post_text(text, machine, args.mode, tol_um=args.tol_um, max_correction_mm=args.max_correction_mm,
                            singular_deg=args.singular_deg, conditions=conditions,
                            passthrough_unsupported=args.passthrough_unsupported, source=source,
                            cl_feed_mm_min=args.cl_feed, cl_branch=branch, setup=setup, force=args.force,
                            arcs=args.arcs, output_mode=args.output_mode)
    print_warnings(report.warnings)
    if args.strict and report.warnings:
        print(f"trueaxis post: --strict: {len(report.warnings)} warning{'s' if len(report.warnings) > 1 else ''}; "
              f"{args.output} not written", file=sys.stderr)
        return EXIT_REFUSED
    _write_or_stdout(args.output, out.encode(encoding, errors="replace"))  # (a header character Latin-1 lacks: ?)
    if args.report:
        _write_or_stdout(args.report, json_text(report.as_dict()))
    corr = ", ".join(f"{a} {v.get('max_abs_um', v.get('max_abs_urad', 0.0)):.2f}"
                     + (f" (a radius: G7's X words change by twice it, {v['max_abs_diameter_um']:.2f})"
                        if "max_abs_diameter_um" in v else "")
                     for a, v in report.correction.items())
    if report.input_format.startswith("cl-"):  # the input's lines, its points, the machine-axis blocks made of them
        sizes = (f"CL data in ({report.input_format[3:]}: {report.blocks_in} lines, {report.cl_points} points) -> "
                 f"{report.cl_program_blocks} machine-axis blocks -> {report.blocks_out} out")
    else:
        sizes = f"{report.blocks_in} blocks in, {report.blocks_out} out"
    sizes += f" ({report.header_blocks} header comments)" if report.header_blocks else ""  # (a QA pass: 7 in, "11 out")
    print(f"{'<stdout>' if args.output == '-' else args.output}: {sizes}; {report.moves_split} moves split"
          f"{f', {report.arcs_linearised} arcs as lines' if report.arcs_linearised else ''}; "
          f"{f'max correction at the block ends {corr} (um/urad)' if corr else 'no block compensated'}; "
          f"{len(report.singular_blocks)} singular blocks", file=sys.stderr if "-" in (args.output, args.report)
          else sys.stdout)  # stdout carries the program (or the report) then
    return 0


def print_warnings(said) -> None:
    """The post's warnings on stderr, each one line as it says it: ``file:line: message`` (README)."""
    for warning in said:
        print(warning, file=sys.stderr)


@contextlib.contextmanager
def post_warnings():
    """The post's warnings (``PostWarning``) of the posts run inside printed as the post command prints them
    (``print_warnings``), not as Python shows a warning (its category, and the source line that raised it); other
    warnings shown as before."""
    import warnings

    from .postproc.post import PostWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PostWarning)
        try:
            yield
        finally:
            print_warnings(str(w.message) for w in caught if issubclass(w.category, PostWarning))
    for w in caught:
        if not issubclass(w.category, PostWarning):
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)


def _write_or_stdout(path: str, text: str | bytes) -> None:
    """``-``: stdout (no atomic file then); else the file, written atomically. Bytes as they are, text as UTF-8."""
    if path == "-":
        if isinstance(text, bytes):
            sys.stdout.flush()
            sys.stdout.buffer.write(text)
            sys.stdout.buffer.flush()
        else:
            sys.stdout.write(text)
            sys.stdout.flush()
        return
    from .fileio import atomic_write

    atomic_write(path, text)


def _parse_placement(text):
    """'X,Y' (mm) -> (2,) array, or None."""
    return None if text is None else _parse_vector(text, "--placement-mm", 2)


def cmd_part(args) -> int:
    from .workpiece.part import get_part, write_part

    part = get_part(args.part)
    params = part.params_type.from_overrides(args.param or [])  # ValueError (one line, exit 2) before anything is written
    paths = write_part(part.name, Path(args.output), params)
    doc = json.loads(paths["json"].read_text(encoding="utf-8"))
    stl = doc["stl"]
    print(f"{args.part}: wrote {paths['step']}, {paths['stl']} ({stl['triangles']} triangles, chord tolerance "
          f"{stl['chord_tolerance_mm'] * 1e3:g} um, chord error bound {stl['chord_error_bound_mm'] * 1e3:.2f} um), "
          f"{paths['json']}")
    return 0


# `trueaxis program` options that only some parts' programs take: option -> keyword of the program function
_PROGRAM_OPTIONS = {"--compensate": "compensation", "--tool-diameter": "tool_diameter", "--stock-um": "stock_um",
                    "--finish-um": "finish_um", "--step-deg": "step_deg", "--chord-tol-um": "chord_tol_um"}


def cmd_program(args) -> int:
    import inspect

    from .fileio import atomic_write
    from .machine import load_machine
    from .postproc.programs import PROGRAMS
    from .resources import machine_file
    from .workpiece.part import get_part

    part = get_part(args.part)
    make = PROGRAMS[part.name]
    takes = inspect.signature(make).parameters
    options = {}
    for option, keyword in _PROGRAM_OPTIONS.items():
        value = getattr(args, option.lstrip("-").replace("-", "_"))
        if value is None:
            continue
        if keyword not in takes:
            raise UsageError(f"{option} does not apply to the {part.title}")
        options[keyword] = value
    machine = load_machine(machine_file(args.machine or part.default_machine))
    with post_warnings():  # the programs' posts: each warning 'file:line: message', as the post command says them
        prog = make(machine, part.params_type.from_overrides(args.param or []),
                    placement_mm=_parse_placement(args.placement_mm), **options)
    atomic_write(args.output, prog.text)
    if args.cl:
        prog.cl.write_csv(args.cl)
    print(f"{args.output}: {args.part} on {machine.name}: {len(prog.text.splitlines())} lines, {len(prog.cl.tip)} CL "
          f"points ({prog.info['summary']}); placement {prog.info['placement_mm']} mm, safe Z {prog.safe_z:.3f} mm"
          + (f"; CL data in {args.cl}" if args.cl else ""))
    return 0


# the fewest probe points a simulated measurement is made of (``simulate --points``)
MIN_SIM_POINTS = 10


def cmd_simulate(args) -> int:
    """``trueaxis simulate PROGRAM --machine TRUE.toml [--effects E.toml] --part PART [--part-dir DIR] -o cmm.ply
    [--points N] [--noise-um S] [--seed K]``: the virtual shop's cloud and its truth sidecar; a one-line summary.
    The shop cuts with the tool the program was made for when its setup comment says (``tool_d_mm``), as a shop
    loads the tool the program names, and the summary says so when it is not the machine file's tool; a program
    for another size of the part than --part-dir describes is refused (exit 3)."""
    import numpy as np

    from .machine import load_machine
    from .postproc.programs import check_cut_share
    from .resources import machine_file
    from .sim.shop import simulate_program_file, write_cmm

    if args.noise_um < 0:
        raise UsageError("--noise-um must be >= 0")
    # the cloud is a PLY (binary, with normals) whatever the name: another extension got one under its name (a QA
    # pass: -o x.csv, .xyz, .e57, and an effects .toml overwritten with a cloud, exit 0)
    if Path(args.output).suffix.lower() != ".ply":
        raise UsageError(f"-o {args.output}: simulate writes a PLY cloud (binary, with normals); name it .ply")
    machine = load_machine(str(machine_file(args.machine)))
    res = simulate_program_file(args.program, machine, args.part, effects_path=args.effects, part_dir=args.part_dir,
                                points=args.points or 200_000, noise_um=args.noise_um or 0.0, seed=args.seed or 0)
    cut = np.isfinite(res.deviations_um)
    # a program that cuts almost none of the part (a lathe's, another placement's) is no cut of it: nothing written
    check_cut_share(int(cut.sum()), int(res.info["points"]), "probe points of the part")
    truth = write_cmm(res, args.output)
    d = res.deviations_um[cut]
    not_cut = int(res.info.get("not_cut", 0))
    if not_cut:
        print(f"warning: {not_cut} of {res.info['points']} probe points were not cut by the program (left out of "
              f"{args.output}); is the program cutting the whole part?", file=sys.stderr)
    # The cut surface's deviation, then the cloud's (with the probe noise): the noise-free figure alone read as the
    # cloud's (rms 0.02 um for a cloud of 50 um noise, in a QA pass).
    measured = d + np.asarray(res.noise_um, float)[cut] if np.size(res.noise_um) == np.size(cut) else d
    asked, pattern = args.points or 200_000, int(res.info["points"])
    grid = f"; the probe pattern's grid holds {pattern} of the {asked} asked" if pattern != asked else ""
    print(f"{args.output}: {d.size} points ({not_cut} not cut{grid}); the cut surface's deviation (noise-free) mean "
          f"{d.mean():+.2f} um, rms {np.sqrt(np.mean(d**2)):.2f} um, range {d.min():+.2f}..{d.max():+.2f} um; the "
          f"cloud's with the probe noise (sigma {args.noise_um or 0.0:g} um) rms {np.sqrt(np.mean(measured**2)):.2f} "
          f"um; truth in {truth}; {res.timings['total_s']:.1f} s{_tool_note(res.machine.tool, machine.tool)}")
    for note in res.info.get("notes", []):  # what this run leaves out of the true machine (its force model)
        print(f"  note: {note}")
    return 0


def _tool_note(cut_with, machine_files) -> str:
    """'; cut with the program's tool ...' when the shop cut with another tool than the machine file's, else ''."""
    if cut_with.radius == machine_files.radius:
        return ""
    return (f"; cut with the program's tool, d {2 * cut_with.radius:g} mm (its setup comment's tool_d_mm; the machine "
            f"file's: d {2 * machine_files.radius:g} mm)")


def cmd_diagnose(args) -> int:
    from .diagnose.report import diagnose_files, summary_lines
    from .resources import machine_file

    if args.noise_um is not None and not args.noise_um > 0:
        raise UsageError("--noise-um must be > 0")
    n_parts = len(args.cloud)
    if len(args.program) != n_parts:  # (first: the --pause-s checks below count the parts by their clouds)
        raise UsageError(f"{n_parts} cloud(s) and {len(args.program)} program(s): give one --program per --cloud, in "
                         "the order the parts were cut")
    gaps = "one number" if n_parts == 2 else f"one number for all gaps, or {n_parts - 1} numbers (one per gap)"
    if n_parts > 1 and args.pause_s is None:
        raise UsageError(f"{n_parts} parts: give --pause-s, the pause between one part's cut and the next (s; 0 when "
                         f"cut right after each other; {gaps}): a drift runs on through it")
    if args.pause_s is not None and len(args.pause_s) not in (1, max(n_parts - 1, 1)):
        raise UsageError(f"--pause-s: {len(args.pause_s)} numbers given; {n_parts} parts take {gaps}")
    if args.pause_s is not None and n_parts == 1:
        raise UsageError("--pause-s: one part given; the pause is the time between parts cut one after another")
    from .inspect.workers import single_blas_thread

    # BLAS on one thread: the diagnosis' products are small or tall and thin, where OpenBLAS' threads only wait for
    # each other on a busy machine (the demo's case: 29 s against 1.8 s at load 2-3)
    t0 = time.perf_counter()

    def progress(line):  # on a terminal only, as the post's bar: a redirected log keeps the summary and the warnings
        print(f"trueaxis diagnose: [{time.perf_counter() - t0:4.0f} s] {line} ...", file=sys.stderr, flush=True)

    part_json = _diagnose_part_jsons(args)
    with single_blas_thread():
        diag, data = diagnose_files(args.cloud, args.part, str(machine_file(args.machine)), args.program, args.output,
                                    candidates=args.candidates, split=args.split, noise_um=args.noise_um,
                                    part_json=None if not part_json else
                                    part_json[0] if len(part_json) == 1 else part_json,
                                    pauses_s=args.pause_s, plan_next=args.plan_next,
                                    progress=progress if sys.stderr.isatty() else None)
    for line in summary_lines(diag, args.output, named_candidates=args.candidates not in (None, "all"),
                              next_part=data.get("next_part")):
        print(line)
    for warning in data["warnings"]:
        print(f"trueaxis diagnose: warning: {warning}", file=sys.stderr)
    return 0


def _diagnose_part_jsons(args) -> list:
    """diagnose's part descriptions: the --part-json files, or <part>.json in each --part-dir (empty: the default)."""
    if getattr(args, "part_dir", None):
        return [str(Path(d) / f"{args.part}.json") for d in args.part_dir]
    return list(getattr(args, "part_json", None) or [])


def cmd_demo(args) -> int:
    from .demo import run_demo

    return run_demo(Path(args.out))


def cmd_freecad_install(args) -> int:
    from .postproc.hosts.freecad import default_macro_dir, install_post

    folder = args.dir if args.dir is not None else default_macro_dir()
    try:
        target = install_post(folder)
    except OSError as exc:  # a folder we may not write, a file where the folder should be
        raise UsageError(f"cannot install into {folder}: {exc.strerror or exc}") from None
    print(f"{target}: installed; in a FreeCAD CAM Job choose the post processor 'trueaxis' with arguments such as "
          "--machine /path/to/machine.toml; FreeCAD runs the trueaxis command: put it on PATH, or set TRUEAXIS_BIN to "
          f"it ({Path(sys.executable).with_name('trueaxis')})")
    return 0


def cmd_inspect(args) -> int:
    """Compare a cloud with its part and write the report folder (trueaxis.inspect.report does the work)."""
    from .inspect.workers import FigureWorker, keep_freed_memory, single_blas_thread

    if args.identify and not (args.machine and args.program):
        raise UsageError("--identify needs --machine TWIN.toml and --program PROG.ngc")
    if not args.identify and (args.machine or args.program or args.write or args.setup_sigma_um is not None):
        raise UsageError("--machine, --program, --write and --setup-sigma-um go with --identify")
    if args.align == "bestfit" and args.setup_sigma_um is not None:  # (it was taken and not used; a QA pass)
        raise UsageError("--setup-sigma-um: with --align bestfit the best fit takes the part's set-up (no set-up "
                         "offset is fitted); give it with --align none or datum")
    out_dir = Path(args.output) if args.output is not None else \
        Path(args.cloud).with_name(Path(args.cloud).stem + "_report")
    if args.machine:  # a file, or a fixture machine's short name, as every other command takes it
        from .resources import machine_file

        args.machine = str(machine_file(args.machine))
    # the pictures are drawn by a second process started now (matplotlib imports while the cloud is read), and the
    # inspection's BLAS runs on one thread (trueaxis.inspect.workers: same numbers, faster on a busy machine)
    keep_freed_memory()  # fewer page faults for the large temporary arrays (same values)
    # imported before the worker forks: the child then has the report module (and its kernels) without importing it
    from .inspect.report import identification_input, inspect_cloud, inspection_warnings, write_report

    with FigureWorker() as figures:

        with single_blas_thread():
            result = inspect_cloud(args.cloud, args.part, part_dir=args.part_dir, cad=args.cad, align=args.align,
                                   tolerances=args.tolerances, program=args.program, machine=args.machine,
                                   figure_worker=figures, progress=lambda line: print(line, file=sys.stderr),
                                   flyer_screen=True if args.identify else None)  # --identify screens in any case
        identification = None
        if args.identify:
            from .identify import run_identification
            from .inspect.flyers import residual_above_noise_note

            cloud, deviation_um, flyers = identification_input(result)  # the flyers set apart, as the diagnosis does
            report, identification = run_identification(cloud, deviation_um, result.part, machine=args.machine,
                                                        program=args.program, write=args.write, alignment=args.align,
                                                        setup_sigma_um=args.setup_sigma_um)
            result.report["identification"] = {**report, **flyers}
            note = residual_above_noise_note(identification.residual_rms_um,
                                             flyers["flyers_set_apart"]["local_sigma_um"],
                                             kept=[*identification.taken_by_setup, *identification.not_significant],
                                             setup_given=args.setup_sigma_um is not None
                                             or args.align == "bestfit")
            if note:
                result.report["identification"]["unexplained_note"] = note
        with single_blas_thread():
            write_report(result, out_dir, figure_worker=figures)
    r = result.report
    d = r["deviation_um"]
    line = (f"{out_dir}: {r['points']} points vs {args.part} ({r['alignment']['method']} alignment): deviation rms "
            f"{d['rms']:.2f} um, range {d['min']:+.2f}..{d['max']:+.2f} um")
    if d["points"] < r["points"]:  # the points beyond the gate (on no feature) are counted apart, not in the figures
        line += f" over {d['points']} points on the part ({r['points'] - d['points']} beyond the gate apart)"
    if r.get("cone"):
        std = r["cone"].get("half_angle_std_urad")
        line += f"; half angle error {r['cone']['half_angle_error_urad']:+.1f}" + (
            f" +- {std:.1f}" if std is not None and math.isfinite(std) else "") + " urad"
        flyers = (r.get("flyers_within_gate") or {}).get("points")
        without = next((row.get("without_flyers") for row in r["feature_table"] if row["key"] == "half_angle_urad"
                        and row.get("without_flyers")), None)
        if flyers and without and without["deviation"] is not None:  # the flyer warning gives the rest
            line += f" ({without['deviation']:+.1f} without the {flyers} flyer{'s' if flyers > 1 else ''})"
    counts = r["feature_summary"]
    if counts["pass"] or counts["fail"] or counts["uncertain"]:
        line += (f"; {counts['pass']} characteristic{'s' if counts['pass'] != 1 else ''} in tolerance, "
                 f"{counts['fail']} out" + (f", {counts['uncertain']} UNCERTAIN (the fit's 2 std straddle a limit)"
                                            if counts["uncertain"] else ""))
    if counts["not measured"]:
        line += f", {counts['not measured']} NOT MEASURED"
    print(line)
    for warning in inspection_warnings(r):
        print(f"trueaxis inspect: warning: {warning}", file=sys.stderr)
    if identification is None:
        return 0
    for text in identification.verdict_lines():
        print(text)
    if r["identification"].get("unexplained_note"):
        print(f"  note: {r['identification']['unexplained_note']}")
    print(f"  program: {r['identification']['program_compensation']['note']}")
    if r["identification"]["program_compensation"].get("warning"):
        print(f"trueaxis inspect: warning: {r['identification']['program_compensation']['warning']}", file=sys.stderr)
    if r["identification"].get("placement_assumed"):  # the words the diagnosis says it in
        print(f"  program: {r['identification']['placement_assumed']}")
    if args.write and not identification.accepted:
        print(f"trueaxis inspect: {args.write} not written: identification refused ("
              + "; ".join(identification.reasons) + f"); see {out_dir / 'report.json'}", file=sys.stderr)
        return EXIT_REFUSED
    if args.write:
        print(f"  {args.write}: written ({identification.verdict})")
    return 0


# ------------------------------------------------------------------------------------------------------ parser ----
class _Parser(argparse.ArgumentParser):
    """argparse's parser without abbreviated options: ``--mod`` is not taken for ``--mode`` (a mistyped prefix could
    pick another option than the one meant, without a word); the subcommands' parsers are of this class too."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__
    from .workpiece.part import part_names

    p = _Parser(prog="trueaxis", description="Machine-tool error compensation: post, inspect, diagnose.",
                epilog="Exit status: 0 done; 1 the system refused (a file that cannot be read or "
                       "written); 2 usage (an option, a value, a path), nothing written; 3 an "
                       "input refused (a program, CL data, a machine file, a setup, a cloud, "
                       "tolerances; a --strict warning), nothing written, or a computed result "
                       "refused (an identification refused: its changes do not hold; its report "
                       "says why, the twin is not written); "
                       "130 / 143 interrupted (SIGINT / SIGTERM); 141 the reader of standard "
                       "output went away (a pipe closed).")
    p.add_argument("--version", action="version", version=f"trueaxis {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    mach = sub.add_parser("machine", help="check or show a machine file, or write a nominal (error-free) one")
    msub = mach.add_subparsers(dest="machine_command", required=True)
    c = msub.add_parser("check", help="validate a machine file (exit 3 and one line per problem if bad)")
    c.add_argument("file")
    c.set_defaults(func=cmd_machine_check)
    s = msub.add_parser("show", help="print a machine's layout and parameters")
    s.add_argument("file")
    s.set_defaults(func=cmd_machine_show)
    z = msub.add_parser("nominal", help="write the machine's error-free twin (every error zero, no force model): "
                                        "the twin a closed loop starts from")
    z.add_argument("file")
    z.add_argument("-o", "--output", required=True, help="machine file to write (TOML, atomically)")
    z.set_defaults(func=cmd_machine_nominal)

    e = sub.add_parser("error", help="volumetric error at one pose (um, urad; part frame)")
    e.add_argument("--machine", required=True, help="machine file (TOML) or a fixture's short name (e.g. xh714)")
    e.add_argument("--at", required=True, help="pose: every axis of the machine once, inside its travel, e.g. "
                   "X=10,Y=20,Z=-5,B=30,C=45 (mm, deg)")
    e.add_argument("--force-n", help="force of the workpiece on the tool, FX,FY,FZ in N (machine frame)")
    e.add_argument("--direction", choices=["forward", "backward"], default="forward",
                   help="direction of motion of the axes: chooses the response surfaces of that motion (the lathe "
                        "paper's models 1-2 forward, 3-4 backward; default forward)")
    e.add_argument("--json", action="store_true", help="print JSON")
    e.set_defaults(func=cmd_error)

    po = sub.add_parser("post", help="compensate an NC program with a machine's error twin")
    po.add_argument("input", help="G-code program (machine axes), or CL data in the part frame: CSV with a header "
                    "naming x,y,z,i,j,k[,f] or APT (GOTO/x,y,z,i,j,k, FEDRAT/f, RAPID); told apart by content; - for stdin")
    po.add_argument("-o", "--output", required=True, help="compensated program (written atomically); - for stdout "
                    "(messages stay on stderr)")
    po.add_argument("--machine", required=True, help="machine file (TOML) or a fixture's short name (e.g. xh714)")
    po.add_argument("--mode", default="geometric", choices=["none", "geometric", "comprehensive"],
                    help="what is corrected: geometric (the twin's geometric errors; the default), comprehensive "
                         "(and the deflection under the cutting force, from the program's cutting conditions), none")
    po.add_argument("--tol-um", type=_number(low=0.0, low_open=True), default=1.0,
                    help="path tolerance, um (default 1; at least 0.05, what a written program holds)")
    po.add_argument("--max-correction-mm", type=POSITIVE, default=0.5, help="largest correction allowed (default 0.5)")
    po.add_argument("--singular-deg", type=_number(low=0.0, high=90.0), default=1.0,
                    help="tilt below which the free rotary axis is held (default 1 deg)")
    po.add_argument("--report", help="write the report JSON here (- for stdout)")
    po.add_argument("--passthrough-unsupported", action="store_true",
                    help="leave blocks the reader does not understand as they are (G43.4, unknown G and M codes, "
                         "macros it cannot evaluate, G52, cutter radius compensation G41/G42: refused otherwise; "
                         "each one a warning on stderr)")
    po.add_argument("--strict", action="store_true",
                    help="every warning is an error: exit 3, nothing written")
    po.add_argument("--output-mode", choices=["joint", "tcp"], default=None,
                    help="joint: the commanded joints (a control in joint mode); tcp: tool-centre-point positions for "
                         "a control running its nominal table-table kinematics (LinuxCNC xyzbc/xyzac-trt-kins, G43.4; "
                         "docs/linuxcnc.md); default: the machine file's [kinematics] output_mode, else joint")
    po.add_argument("--arcs", action=argparse.BooleanOptionalAction, default=None,
                    help="arcs whose correction varies along them: written as G2/G3 blocks fitted to the corrected "
                         "path (checked through the twin within --tol-um, bisected where needed), or (--no-arcs) as "
                         "straight pieces; default: on for a three-axis mill, off for five-axis machines and lathes")
    for key, what in (("ap", "axial depth, mm"), ("ae", "radial engagement, mm"), ("fz", "feed per tooth, mm"),
                      ("n", "spindle speed, rpm"), ("d", "tool diameter, mm"), ("z", "flutes")):
        po.add_argument(f"--{key}", type=POSITIVE if key != "z" else _number(int, low=1), help=f"cutting conditions: {what} "
                        "(overrides the program's structured comments)")
    po.add_argument("--cut-mode", choices=["down", "up"], help="cutting conditions: down or up milling")
    po.add_argument("--f-rev", dest="f", type=POSITIVE, help="turning conditions: feed per revolution, mm (with --ap "
                    "and --vc; overrides the program's structured comments)")
    po.add_argument("--vc", type=POSITIVE, help="turning conditions: cutting speed, m/min")
    po.add_argument("--var", metavar="PARAMS.var", help="the control's setup: LinuxCNC parameter file (work offsets "
                    "G54..G59.3 with rotation, G92, active system, G28/G30 homes)")
    po.add_argument("--tool-table", metavar="TOOLS.tbl", help="the control's setup: LinuxCNC tool table (tool "
                    "offsets X..C, Z = length; D diameter)")
    po.add_argument("--machine-units", choices=["mm", "inch"], default=None,
                    help="units of the .var and tool table: LinuxCNC's [TRAJ] LINEAR_UNITS (default mm; the "
                         "standalone rs274 uses inch)")
    po.add_argument("--setup", metavar="SETUP.toml", help="the control's setup for other controls: work offsets, tool "
                    "lengths, how tool length is applied (docs/setup_file.md); default: the machine file's "
                    "[machine] setup")
    po.add_argument("--force", action="store_true",
                    help="post a program that already carries a trueaxis header (compensated already: refused "
                         "otherwise)")
    po.add_argument("--offsets-zero", action="store_true",
                    help="work offsets, G92 shifts and tool lengths not given are zero (without it a program that "
                         "uses one is refused)")
    po.add_argument("--cl-feed", type=POSITIVE, help="CL data: feed, mm/min, for cuts before the data gives one")
    po.add_argument("--cl-branch", choices=["nearest", "+1", "-1"], default="nearest",
                    help="CL data: sign of the tilt axis (default: kept along the path, the one farthest inside "
                         "its travel to start)")
    po.set_defaults(func=cmd_post)

    pa = sub.add_parser("part", help="write a test part: STEP, STL (chord tolerance stated) and JSON")
    pa.add_argument("part", choices=part_names())
    pa.add_argument("-o", "--output", required=True, help="output folder")
    pa.add_argument("--param", action="append", metavar="NAME=VALUE",
                    help="override a part dimension (mm, deg); repeatable")
    pa.set_defaults(func=cmd_part)

    pg = sub.add_parser("program", help="NC program of a test part, through the machine's inverse kinematics")
    pg.add_argument("part", choices=part_names())
    pg.add_argument("--machine", help="machine file (TOML; default nmv1500dcg for nas979, xh714 for slots)")
    pg.add_argument("-o", "--output", required=True, help="program file (written atomically)")
    pg.add_argument("--compensate", choices=["none", "geometric", "comprehensive"],
                    help="nas979: compensation of the program (default geometric); slots: each slot has its own")
    pg.add_argument("--tool-diameter", type=POSITIVE, help="nas979: flat end mill diameter, mm (10)")
    pg.add_argument("--stock-um", type=POSITIVE,
                    help="nas979: radial stock on the cone before flank milling, um (200)")
    pg.add_argument("--finish-um", type=POSITIVE,
                    help="nas979: stock the finishing pass removes; more stock adds a semi-finishing pass, um (100)")
    pg.add_argument("--step-deg", type=_number(low=0.0, high=90.0, low_open=True),
                    help="nas979: largest angle about the cone axis per block, deg (1; refined to --chord-tol-um)")
    pg.add_argument("--chord-tol-um", type=POSITIVE,
                    help="nas979: largest mid-block departure of the interpolated tool from the offset surface, um")
    pg.add_argument("--placement-mm", help="part origin X,Y off the C axis (off the machine zero without C), mm "
                    "(default: the machine file's [workpiece] origin)")
    pg.add_argument("--param", action="append", metavar="NAME=VALUE", help="part dimension override; repeatable")
    pg.add_argument("--cl", help="write the CL data (part frame) as CSV x,y,z,i,j,k,f here")
    pg.set_defaults(func=cmd_program)

    sm = sub.add_parser("simulate", help="machine a program on a true machine and measure it on a virtual CMM")
    sm.add_argument("program", help="machine-axis NC program; its trueaxis-setup comment places the part and names "
                    "the tool it was made for (tool_d_mm), which the shop then cuts with (the summary says so)")
    sm.add_argument("--machine", required=True, help="the true machine (machine file, TOML, or a fixture's short name)")
    sm.add_argument("--effects", help="effects the twin may not have (TOML)")
    sm.add_argument("--part", required=True, choices=part_names())
    sm.add_argument("--part-dir", help="folder holding <part>.json (default: the default part parameters); a "
                    "program whose title names another size of the part is refused (exit 3)")
    sm.add_argument("-o", "--output", required=True, help="CMM cloud (PLY, part frame); <name>.truth.json beside it")
    sm.add_argument("--points", type=_number(int, low=MIN_SIM_POINTS), default=200_000,
                    help=f"probe points (200000; at least {MIN_SIM_POINTS}, and 20 for diagnose)")
    sm.add_argument("--noise-um", type=NON_NEGATIVE, default=0.0, help="probe noise sigma, um (0)")
    sm.add_argument("--seed", type=_number(int, low=0), default=0, help="noise seed (0)")
    sm.set_defaults(func=cmd_simulate)

    fc = sub.add_parser("freecad", help="FreeCAD CAM integration")
    fcsub = fc.add_subparsers(dest="freecad_command", required=True)
    fi = fcsub.add_parser("install", help="copy the trueaxis post processor into FreeCAD's macro folder")
    fi.add_argument("--dir", type=Path, help="folder to install into (default: FreeCAD's user macro folder, from its "
                    "user.cfg MacroPath, else ~/.local/share/FreeCAD/Macro or ~/.FreeCAD/Macro)")
    fi.set_defaults(func=cmd_freecad_install)

    dg = sub.add_parser("diagnose", help="the sim-to-real gap: where it lies, which effect explains it, how far it shrinks")
    dg.add_argument("--cloud", required=True, action="append",
                    help="measured CMM cloud in the part frame, mm (the formats inspect reads: PLY, CSV/TXT, XYZ, E57, "
                    "DMIS output .dmo); repeat with --program for several parts "
                    "cut one after another on the machine (a second placement), in the order they were cut")
    dg.add_argument("--part", required=True, choices=part_names())
    dg.add_argument("--machine", required=True, help="the twin (machine file, TOML, or a fixture's short name)")
    dg.add_argument("--program", required=True, action="append",
                    help="the NC program that cut the part (one per --cloud, in the same order)")
    part_of = dg.add_mutually_exclusive_group()
    part_of.add_argument("--part-json", default=None, action="append", help="the part's description (JSON written by "
                         "`trueaxis part`; default: the part at its default size); once for all clouds, or once per "
                         "--cloud")
    part_of.add_argument("--part-dir", default=None, action="append", help="folder holding <part>.json from "
                         "`trueaxis part`, as inspect and simulate take it (the same as --part-json DIR/<part>.json); "
                         "once for all clouds, or once per --cloud")
    dg.add_argument("--pause-s", type=_non_negative_list, default=None, action="extend",
                    help="several parts: the pause between the end of one part's program and the start of the next, "
                    "s (0: cut right after each other); one number for all, or one per gap in the order cut "
                    "(comma-separated, or the option repeated). Required with several --cloud: a thermal drift "
                    "runs on through it")
    dg.add_argument("--candidates", default="all", help="all, or a comma-separated list of candidate effects")
    dg.add_argument("--split", default="region", choices=["region", "time", "random"],
                    help="how held-out points are kept apart from the fitted ones (default region)")
    dg.add_argument("--noise-um", type=POSITIVE, help="probe noise sigma, um (default: estimated from the data)")
    dg.add_argument("--plan-next", action="store_true", help="when one part leaves the verdict uncertain beside a "
                    "rival its signatures do not separate, find the placement of a second part that does (a twin "
                    "simulation per placement tried, about 5 s each)")
    dg.add_argument("-o", "--output", default="diagnosis", help="report folder (default ./diagnosis)")
    dg.set_defaults(func=cmd_diagnose)

    d = sub.add_parser("demo", help="run the end-to-end demonstration on built-in defaults")
    d.add_argument("-o", "--out", default="demo_out", help="output folder (default demo_out; -o as the other "
                   "commands take it)")
    d.set_defaults(func=cmd_demo)

    i = sub.add_parser("inspect", help="compare a CMM cloud with the part: deviations, form, report folder")
    i.add_argument("cloud", help="CMM cloud in the part frame, mm: PLY (ascii/binary), CSV/TXT (',' ';' tab or "
                   "whitespace, optional header x,y,z[,i,j,k] and name column), XYZ, E57, DMIS output (.dmo); "
                   "normals optional")
    i.add_argument("--part", required=True, choices=part_names())
    ref = i.add_mutually_exclusive_group()
    ref.add_argument("--part-dir", help="folder holding <part>.json (and slots.stl) from 'trueaxis part' "
                     "(default: the default part parameters)")
    ref.add_argument("--cad", help="CAD of the part: STEP (tessellated to < 0.1 um chord error; slow) or STL/PLY/OBJ, "
                     "with <stem>.json beside it (the features and analytic surfaces; refused without it)")
    i.add_argument("--align", default="none", choices=["none", "bestfit", "datum"],
                   help="none: cloud already in the part frame (default); bestfit: ICP onto the CAD, the rigid motion "
                        "removed is reported; datum: 3-2-1 frame from the probed datum planes (both refine a cloud "
                        "within about a mm of the part frame; they do not search for the part)")
    i.add_argument("-o", "--output", help="report folder (default: <cloud stem>_report beside the cloud)")
    i.add_argument("--tolerances", metavar="FILE", help="tolerances of the part's features (TOML, see "
                   "docs/tolerances.md), over those of the part JSON; the report's feature table says pass or fail")
    i.add_argument("--identify", action="store_true", help="identify twin parameters from the deviations")
    i.add_argument("--machine", help="with --identify: the machine's error twin (machine file, TOML, or a fixture's "
                                     "short name)")
    i.add_argument("--program", help="with --identify: the program that cut the part")
    i.add_argument("--write", help="with --identify: write the updated machine file here (only when the fit is "
                   "accepted or changes nothing; a refused fit writes nothing and exits 3)")
    i.add_argument("--setup-sigma-um", type=NON_NEGATIVE, default=None, metavar="UM",
                   help="with --identify: the accuracy of the part's set-up (how far it may sit off in its frame, "
                        "um), fitted as nuisance and never written (default: not known, the set-up offset free, so no "
                        "translation of the part is written into the twin; 0: the set-up is known exactly)")
    i.set_defaults(func=cmd_inspect)
    return p


def _located_errors() -> tuple:
    """The error classes whose messages already say ``file:line: reason`` (machine files, G-code). Taken from the
    modules only when a command has imported them: a command that never reads a machine file or a program (inspect
    of a cloud) then does not pay the 2 s of importing the twin's interpolators, and an error of those classes can
    only come from a module that is loaded."""
    found = []
    for module, name in (("trueaxis.machine.machine_file", "MachineFileError"),
                         ("trueaxis.nc.gcode", "GcodeError"), ("trueaxis.nc.setup", "SetupError")):
        if module in sys.modules:
            found.append(getattr(sys.modules[module], name))
    return tuple(found)


# inputs that are always file paths (a machine file may be a fixture's name): one that does not exist is a usage error
_NAMED_FILES = ("input", "program", "cloud", "--cloud", "--program", "--cad", "--effects")
# inputs that name a file or a fixture machine (``resources.machine_file``): a path that does not exist is a usage error
_MACHINE_FILES = ("--machine", "file")


def _missing(option: str, path) -> bool:
    """Whether the input ``path`` of ``option`` names a file that does not exist (``-``: stdin; a fixture machine's
    short name is looked up by ``resources.machine_file``, which names the fixtures when there is none)."""
    from .resources import names_a_path

    if path is None or path == "-" or Path(path).exists():
        return False
    return option in _NAMED_FILES or (option in _MACHINE_FILES and names_a_path(path))


def _refusal_errors() -> tuple:
    """The error classes of inputs the product refuses whose messages do not carry a line (clouds, tolerances, the
    inspection, effects files, a program the diagnosis or the identification cannot use): exit status 3 like the
    located ones. Taken lazily, as in :func:`_located_errors`."""
    found = []
    for module, name in (("trueaxis.inspect.cloud", "CloudError"), ("trueaxis.inspect.tolerances", "ToleranceError"),
                         ("trueaxis.inspect.deviation", "InspectionError"), ("trueaxis.sim.effects", "EffectsFileError"),
                         ("trueaxis.postproc.programs", "ProgramError"),
                         ("trueaxis.machine.kinematics", "UnsupportedKinematics")):
        if module in sys.modules:
            found.append(getattr(sys.modules[module], name))
    return tuple(found)


def _paths(args) -> tuple[list, list]:
    """The command's input files and outputs, for the output gate: ([(option, path)], [(option, path, folder)]), folder
    as ``fileio.check_outputs`` takes it."""
    g = lambda name: getattr(args, name, None)  # noqa: E731 (options a subcommand does not have are None)
    cmd = args.command
    if cmd == "post":
        return [("input", g("input")), ("--machine", g("machine")), ("--var", g("var")),
                ("--tool-table", g("tool_table")), ("--setup", g("setup"))], \
            [("-o", g("output"), False), ("--report", g("report"), False)]
    if cmd == "program":
        return [("--machine", g("machine"))], [("-o", g("output"), False), ("--cl", g("cl"), False)]
    if cmd == "part":
        return [], [("-o", g("output"), True)]
    if cmd == "error":
        return [("--machine", g("machine"))], []
    if cmd == "machine":
        return [("file", g("file"))], ([("-o", g("output"), False)] if g("output") else [])
    if cmd == "simulate":
        from .sim.cmm import truth_path

        out = g("output")
        return [("program", g("program")), ("--machine", g("machine")), ("--effects", g("effects"))], \
            [("-o", out, False), ("the truth file", None if out is None else truth_path(out), False)]
    if cmd == "diagnose":  # --cloud and --program repeat (several parts cut one after another)
        return [*(("--cloud", c) for c in g("cloud") or []), ("--machine", g("machine")),
                *(("--program", p) for p in g("program") or []), *(("--part-json", p) for p in g("part_json") or []),
                *(("--part-dir's JSON", p) for p in _diagnose_part_jsons(args) if g("part_dir"))], \
            [("-o", g("output"), "replaced")]
    if cmd == "inspect":
        out = g("output") if g("output") is not None else Path(args.cloud).with_name(Path(args.cloud).stem + "_report")
        # the files read besides the named ones: the part JSON of --part-dir, the JSON beside --cad
        part_json = None if g("part_dir") is None else Path(g("part_dir")) / f"{args.part}.json"
        cad_json = None if g("cad") is None else Path(g("cad")).with_suffix(".json")
        return [("cloud", g("cloud")), ("--cad", g("cad")), ("--machine", g("machine")), ("--program", g("program")),
                ("--tolerances", g("tolerances")), ("--part-dir's JSON", part_json), ("--cad's JSON", cad_json)], \
            [("-o", out, "replaced"), ("--write", g("write"), False)]
    if cmd == "demo":
        return [], [("--out", g("out"), True)]
    return [], []


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that ``finally`` blocks and the atomic writers clean up."""


def _on_sigterm(signum, frame):
    from .fileio import note_signal

    note_signal(signum)
    raise _Terminated()


def _on_sigint(signum, frame):
    from .fileio import note_signal

    note_signal(signum)  # the raise below can be lost in compiled code: then the next publish refuses
    raise KeyboardInterrupt


def _interruption(exc: BaseException | None) -> BaseException | None:
    """The KeyboardInterrupt or SIGTERM behind ``exc``, or None (a compiled kernel reports a KeyboardInterrupt raised
    while it ran as a SystemError whose context is the KeyboardInterrupt)."""
    for _ in range(10):
        if exc is None or isinstance(exc, (KeyboardInterrupt, _Terminated, Interrupted)):
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


EXIT_FAILURE = 1
EXIT_SIGINT = 130
EXIT_SIGTERM = 143
EXIT_BROKEN_PIPE = 141  # as a shell reports a process ended by SIGPIPE


#: Options whose value is a comma list of numbers: "--placement-mm -40,20" is their value, not an option (argparse
#: reads a token starting with "-" that is not a plain number as an option).
VECTOR_OPTIONS = ("--placement-mm", "--force-n")


def _joined_vectors(argv: list) -> list:
    """argv with each vector option and a value starting with a minus sign joined as "--option=value"."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        if a in VECTOR_OPTIONS and i + 1 < len(argv) and re.match(r"^-[\d.]", argv[i + 1]):
            out.append(f"{a}={argv[i + 1]}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


def main(argv=None) -> int:
    """Run one command. Exit status: 0 done; 2 usage (one line per problem on stderr, nothing written); 3 an input
    or a computed result refused (``file:line: reason`` where it has a line; nothing written); 1 the system refused (a file that cannot be read or written: one
    line); 130 / 143 interrupted by SIGINT / SIGTERM (one line; earlier outputs intact, no temporary file left)."""
    import signal

    from .fileio import check_outputs, raise_if_signalled

    args = build_parser().parse_args(_joined_vectors(sys.argv[1:] if argv is None else list(argv)))
    if threading_main():
        signal.signal(signal.SIGTERM, _on_sigterm)
        signal.signal(signal.SIGINT, _on_sigint)
    try:
        inputs, outputs = _paths(args)
        for option, path in inputs:
            if path is not None and Path(path).is_dir():
                raise UsageError(f"{option} {path}: is a folder; name a file")
            if _missing(option, path):
                raise UsageError(f"{option} {path}: cannot read the file: no such file")
        check_outputs(inputs, outputs)
        status = int(args.func(args) or 0)
        raise_if_signalled()  # a signal whose exception compiled code swallowed still ends the run as interrupted
        return status
    except (KeyboardInterrupt, _Terminated, Interrupted) as exc:
        return _report_interruption(args.command, exc)
    except Exception as exc:  # noqa: BLE001 - sorted by _report_error; what it does not know is raised again
        return _report_error(args.command, exc)


def _report_error(command: str, exc: Exception) -> int:
    """One line on stderr and the exit status for an error the user can act on; anything else is raised again."""
    from .fileio import OutputPathError

    if isinstance(exc, _located_errors()):  # already 'file:line: reason'
        print(str(exc), file=sys.stderr)
        return EXIT_REFUSED
    if isinstance(exc, _refusal_errors()):  # an input the product refuses (a cloud, tolerances, effects)
        print(f"trueaxis {command}: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    if type(exc).__name__ == "LinAlgError":  # numpy's (a ValueError): degenerate data, not a usage error
        print(f"trueaxis {command}: the data given leave a computation without a unique solution (numpy: {exc}): "
              "nothing written", file=sys.stderr)
        return EXIT_REFUSED
    if isinstance(exc, (UsageError, OutputPathError, ValueError, FileNotFoundError)):
        print(f"trueaxis {command}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if isinstance(exc, BrokenPipeError):  # the reader went away (`trueaxis machine show M | head`): nothing to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    if isinstance(exc, OSError):  # permissions, a full disk, a read-only file system: the system's word, one line
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"trueaxis {command}: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_FAILURE
    cause = _interruption(exc) if isinstance(exc, SystemError) else None
    if cause is not None:
        return _report_interruption(command, cause)
    raise exc


def _report_interruption(command: str, exc: BaseException) -> int:
    import signal

    if threading_main():  # a signal still pending (or a second one) must not turn the exit status into a traceback
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    term = isinstance(exc, _Terminated) or (isinstance(exc, Interrupted) and exc.signum == signal.SIGTERM)
    print(f"trueaxis {command}: {'terminated' if term else 'interrupted'}; outputs not finished were not written",
          file=sys.stderr)
    return EXIT_SIGTERM if term else EXIT_SIGINT


def threading_main() -> bool:
    """True in the main thread, where signal handlers may be installed (not when a host calls ``main`` elsewhere)."""
    import threading

    return threading.current_thread() is threading.main_thread()


def inspect_main(argv=None) -> int:
    """``inspect ARGS``: the same as ``trueaxis inspect ARGS``."""
    return main(["inspect", *(sys.argv[1:] if argv is None else argv)])


def _exit(code: int) -> None:
    """End the process with ``code``. After a signal the status is given with ``os._exit`` (streams flushed, the
    atomic writers' temporary files already removed while the interruption unwound): an interruption still pending in
    the interpreter's shutdown would otherwise turn 130 into death by SIGINT."""
    if code in (EXIT_SIGINT, EXIT_SIGTERM):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


def run() -> None:
    """Console script ``trueaxis``."""
    _exit(main())


def inspect_run() -> None:
    """Console script ``inspect``."""
    _exit(inspect_main())


if __name__ == "__main__":
    run()
