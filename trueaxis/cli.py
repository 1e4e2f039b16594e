"""The command line: ``trueaxis <command>`` (and ``inspect`` = ``trueaxis inspect``).

Thin glue: parse arguments, call the package, print. A bad input ends with one line per problem on stderr and exit
status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

EXIT_BAD_INPUT = 2


class UsageError(ValueError):
    """Bad command-line input: printed as one line, exit status 2."""


def _parse_at(text: str, axis_names, rotary) -> np.ndarray:
    """'X=10,Y=-5,B=30' -> (n_axes,) pose in mm and rad (rotary words in degrees); missing axes are 0."""
    pose = np.zeros(len(axis_names))
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
        pose[axis_names.index(name)] = np.radians(v) if name in rotary else v
    return pose


def _parse_vector(text: str, option: str, n: int = 3) -> np.ndarray:
    try:
        v = np.array([float(s) for s in text.split(",")])
    except ValueError:
        raise UsageError(f"{option}: expected {n} comma-separated numbers, got {text!r}") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise UsageError(f"{option}: expected {n} finite comma-separated numbers, got {text!r}")
    return v


# ---------------------------------------------------------------------------------------------------- commands ----
def cmd_machine_check(args) -> int:
    from .machine import load_machine

    m = load_machine(args.file)
    print(
        f"{args.file}: ok: {m.name} ({m.kind}, axes {' '.join(m.axis_names)},"
        f" {len(m.parameter_names())} geometric parameters)"
    )
    return 0


def cmd_machine_show(args) -> int:
    from .machine import load_machine
    from .machine.model import unit_of

    m = load_machine(args.file)
    print(f"{m.name}  ({m.kind}; {m.source})")
    if m.note:
        print(f"  note: {m.note}")
    print(f"  bed -> workpiece: {' -> '.join(m.bed_to_workpiece) or '(none)'}")
    print(f"  bed -> tool:      {' -> '.join(m.bed_to_tool) or '(none)'}")
    for a in m.axis_names:
        ax = m.axes[a]
        if ax.is_rotary:
            tr = "unlimited" if ax.travel is None else f"[{np.degrees(ax.travel[0]):g}, {np.degrees(ax.travel[1]):g}] deg"
            print(f"  {a}: rotary about {ax.about}, pivot {list(ax.pivot)} mm, travel {tr}")
        else:
            tr = "unlimited" if ax.travel is None else f"[{ax.travel[0]:g}, {ax.travel[1]:g}] mm"
            print(f"  {a}: linear, travel {tr}")
    t = m.tool
    print(f"  tool: length {t.length:g} mm, radius {t.radius:g} mm, {t.flutes} flutes")
    print(f"  part origin in M: {list(m.workpiece_origin)} mm")
    print("  location errors:")
    for n in m.location_names():
        print(f"    {n:6s} {m.errors.location.get(n, 0.0):10.3f} {unit_of(n)}")
    for axis, comps in m._component_items():
        for comp, fn in comps:
            print(f"  {comp}: {fn.kind}, {fn.values.size} values ({unit_of(comp)})")
    if m.compliance_um_per_n is not None:
        print(f"  compliance (um/N): {m.compliance_um_per_n.tolist()}")
    if m.loaded is not None:
        print(f"  loaded parameter set at {m.loaded_force_n.tolist()} N")
    for s in m.surfaces:
        print(f"  response surface: E{s.axis} vs {s.position_axis}, P{s.force_direction.lower()} "
              f"(load {'+' if s.load_sign > 0 else '-'}, {'forward' if s.motion > 0 else 'backward'})")
    if m.cutting:
        print(f"  cutting: {m.cutting}")
    return 0


def cmd_error(args) -> int:
    from .machine import ErrorTwin, load_machine

    m = load_machine(args.machine)
    pose = _parse_at(args.at, m.axis_names, m.rotary_axes)
    force = None if args.force_n is None else _parse_vector(args.force_n, "--force-n")
    dp, du = ErrorTwin(m).volumetric_error(pose[None, :], force_n=force)
    if args.json:
        print(json.dumps({"position_error_um": dp[0].tolist(), "tool_axis_error_urad": du[0].tolist()}))
    else:
        print(f"position error (um, part frame):   dx {dp[0, 0]:+.3f}  dy {dp[0, 1]:+.3f}  dz {dp[0, 2]:+.3f}")
        print(f"tool-axis error (urad, part frame): {du[0, 0]:+.3f}  {du[0, 1]:+.3f}  {du[0, 2]:+.3f}")
    return 0


def cmd_demo(args) -> int:
    from .demo import run_demo

    return run_demo(Path(args.out))


def cmd_inspect(args) -> int:
    print("trueaxis inspect: not yet available (the inspection issue is open)", file=sys.stderr)
    return EXIT_BAD_INPUT


# ------------------------------------------------------------------------------------------------------ parser ----
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="trueaxis", description="Machine-tool error compensation: post, inspect, diagnose.")
    sub = p.add_subparsers(dest="command", required=True)

    mach = sub.add_parser("machine", help="check or show a machine file")
    msub = mach.add_subparsers(dest="machine_command", required=True)
    c = msub.add_parser("check", help="validate a machine file (exit 2 and one line per problem if bad)")
    c.add_argument("file")
    c.set_defaults(func=cmd_machine_check)
    s = msub.add_parser("show", help="print a machine's layout and parameters")
    s.add_argument("file")
    s.set_defaults(func=cmd_machine_show)

    e = sub.add_parser("error", help="volumetric error at one pose (um, urad; part frame)")
    e.add_argument("--machine", required=True, help="machine file (TOML)")
    e.add_argument("--at", required=True, help="pose, e.g. X=10,Y=20,Z=-5,B=30,C=45 (mm, deg)")
    e.add_argument("--force-n", help="force of the workpiece on the tool, FX,FY,FZ in N (machine frame)")
    e.add_argument("--json", action="store_true", help="print JSON")
    e.set_defaults(func=cmd_error)

    d = sub.add_parser("demo", help="run the end-to-end demonstration on built-in defaults")
    d.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    d.set_defaults(func=cmd_demo)

    i = sub.add_parser("inspect", help="compare a CMM cloud with the part (not yet available)")
    i.add_argument("rest", nargs=argparse.REMAINDER)
    i.set_defaults(func=cmd_inspect)
    return p


def main(argv=None) -> int:
    from .machine import MachineFileError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except MachineFileError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_BAD_INPUT
    except (UsageError, ValueError, FileNotFoundError) as exc:
        print(f"trueaxis {args.command}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


def inspect_main(argv=None) -> int:
    """Console script ``inspect``: the same as ``trueaxis inspect``."""
    return main(["inspect", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
