"""G-code for a CadQuery model, compensated with a machine's error twin: trueaxis' Python hook.

    .venv/bin/python docs/cadquery_example.py [--machine xh714] [--var linuxcnc.var] [-o out_folder]

1. ``import trueaxis.postproc.hosts.cadquery`` registers the test parts as CadQuery Workplane methods (CadQuery's
   plugin convention): ``cq.Workplane("XY").nas979()`` is the NAS 979 part on that workplane.
2. A small three-axis program: one finishing pass of a 10 mm end mill around the part's bounding box (outside it by
   the tool radius), at a depth taken from the model, with corner arcs (on a five-axis machine, ``--machine
   nmv1500dcg``, the rotary axes stand at 0 from the first block). Any CAM that writes G-code text will do.
3. ``trueaxis.postproc.compensate(text, machine, mode="geometric", ...)`` returns the program with every move
   corrected so that the machine, with its errors, puts the tool where the nominal program meant it; a ``PostError``
   (``file:line: reason``) says which block it refuses and why. The post never assumes a work offset: this program
   is written in machine coordinates, which ``offsets_zero=True`` says; a program run under the control's work
   offsets gives the control's parameter file instead (``var=``, ``--var`` here).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cadquery as cq
import numpy as np

import trueaxis.postproc.hosts.cadquery  # noqa: F401  (registers Workplane.nas979 and Workplane.slotBlock)
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.postproc import compensate
from trueaxis.nc.setup import SetupError
from trueaxis.postproc.post import PostError
from trueaxis.resources import machine_file


def contour_program(bbox, machine, depth_below_top: float = 5.0, feed: float = 800.0) -> str:
    """Climb-milling pass around ``bbox`` (part frame, mm) for a three-axis machine, in machine-axis G-code; on a
    five-axis machine the same pass with the rotary axes at 0, commanded in the first block (a program that never
    commands them leaves them wherever the control stands, and the post says so).

    The tool centre runs at the tool radius outside the box's XY outline (straight sides, quarter-circle corners)
    with its tip ``depth_below_top`` below the box's top. Machine axes are found from the twin's nominal kinematics:
    with the rotary axes at 0 the tip moves one for one with X, Y and Z, so the axes are the part coordinates minus
    the tip's part position at the machine zero.
    """
    r = machine.tool.radius
    rotary_at_zero = "".join(f" {a}0" for a in machine.axis_names if machine.axes[a].is_rotary)
    tip_at_zero = ErrorTwin(machine).nominal_pose(np.zeros((1, len(machine.axis_names))))[0][0]
    x0, x1 = bbox.xmin - tip_at_zero[0], bbox.xmax - tip_at_zero[0]
    y0, y1 = bbox.ymin - tip_at_zero[1], bbox.ymax - tip_at_zero[1]
    z_cut = bbox.zmax - depth_below_top - tip_at_zero[2]
    z_safe = bbox.zmax + 20.0 - tip_at_zero[2]
    f = "{:.4f}".format
    lines = [
        "%",
        "(trueaxis CadQuery example: contour around the part's bounding box)",
        "G21 G90 G17 G94",
        f"G0 X{f(x0)} Y{f(y1 + r + 10)} Z{f(z_safe)}{rotary_at_zero}",
        f"G0 Z{f(z_cut)}",
        f"G1 Y{f(y1 + r)} F{feed:.0f}",
        # clockwise seen from +Z around an outside contour: down (climb) milling with M3
        f"G1 X{f(x1)}",
        f"G2 X{f(x1 + r)} Y{f(y1)} I0 J{f(-r)}",
        f"G1 Y{f(y0)}",
        f"G2 X{f(x1)} Y{f(y0 - r)} I{f(-r)} J0",
        f"G1 X{f(x0)}",
        f"G2 X{f(x0 - r)} Y{f(y0)} I0 J{f(r)}",
        f"G1 Y{f(y1)}",
        f"G2 X{f(x0)} Y{f(y1 + r)} I{f(r)} J0",
        f"G1 Y{f(y1 + r + 10)}",
        f"G0 Z{f(z_safe)}",
        "M30",
        "%",
    ]
    return "\n".join(lines) + "\n"


def run(machine_name: str = "xh714", tol_um: float = 1.0, var: str | None = None):
    """The part, the nominal program, the compensated program and the post's report. ``var``: the control's
    parameter file (its work offsets); without it the program's coordinates are machine coordinates, as
    ``contour_program`` writes them, and the post is told so (``offsets_zero``)."""
    part = cq.Workplane("XY").nas979()
    machine = load_machine(machine_file(machine_name))
    program = contour_program(part.val().BoundingBox(), machine)
    report: dict = {}
    compensated = compensate(program, machine, mode="geometric", tol_um=tol_um, source="nas979_contour.ngc",
                             report=report, var=var, offsets_zero=var is None)
    return part, machine, program, compensated, report


def largest_corrections(correction: dict) -> str:
    """'X 1.2 um, ..., B 0.5 urad': the largest correction of each axis at the block ends, from the post's report
    (``max_abs_um`` for a linear axis, ``max_abs_urad`` for a rotary one)."""
    out = []
    for axis, stats in correction.items():
        unit = "um" if "max_abs_um" in stats else "urad"
        out.append(f"{axis} {stats['max_abs_' + unit]:.1f} {unit}")
    return ", ".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machine", default="xh714", help="machine file or fixture name (default xh714; on a five-axis "
                    "machine the rotary axes stand at 0)")
    ap.add_argument("--var", help="the control's parameter file (LinuxCNC .var, mm), where the program runs under its "
                    "work offsets (default: none; the program's coordinates are machine coordinates)")
    ap.add_argument("-o", "--output", default="cadquery_example_out", help="output folder")
    args = ap.parse_args(argv)
    try:
        part, machine, program, compensated, report = run(args.machine, var=args.var)
    except (PostError, SetupError) as exc:  # a refused program or setup: its one line (file:line: reason), as the command line says it
        print(exc, file=sys.stderr)
        return 3
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    cq.exporters.export(part, str(out / "nas979.step"))
    (out / "nas979_contour.ngc").write_text(program)
    (out / "nas979_contour_compensated.ngc").write_text(compensated)
    corr = largest_corrections(report["correction"])
    print(f"{out}: nas979.step, nas979_contour.ngc and its compensation for {machine.name} "
          f"({report['blocks_in']} blocks in, {report['blocks_out']} out with {report['header_blocks']} header "
          f"comments; largest corrections {corr})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
