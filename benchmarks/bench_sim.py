"""Benchmark: the virtual shop on the NAS 979 cone. Goal (issue: the virtual shop): about 20,000 program blocks at
1 ms, 200,000 probe points, under 60 s on the 2-core reference machine. Prints the figures for the README.

The program is a semi-finishing pass (0.2 mm stock) and a finishing pass of 10,000 blocks each, written by
``trueaxis.sim.programs.cone_flank_program`` (machine-axis G-code, G93); the true machine is the NMV 1500 DCG fixture
with servo lag, backlash on X and Y, the tool deflection and the machine's compliance under the cutting force, and the
measured thermal drift on Z.

    .venv/bin/python benchmarks/bench_sim.py [--points 200000] [--blocks 10000]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from trueaxis.machine import load_machine
from trueaxis.resources import machine_file
from trueaxis.sim.effects import parse_effects
from trueaxis.sim.programs import cone_flank_program
from trueaxis.sim.shop import load_part, simulate

ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--blocks", type=int, default=10_000, help="blocks per pass (two passes)")
    ap.add_argument("--no-effects", action="store_true")
    args = ap.parse_args()
    m = load_machine(machine_file("nmv1500dcg"))
    cone = load_part("nas979")["surfaces"][0]
    prog = cone_flank_program(m, cone, n_blocks=args.blocks, semi_stock=0.2)
    effects = None if args.no_effects else parse_effects({
        "servo": {"kv_per_s": {a: 30.0 for a in m.axis_names}, "accel": {"X": 2000.0, "Y": 2000.0, "Z": 2000.0,
                                                                        "B": 720.0, "C": 720.0}},
        "backlash": {"X": {"amplitude": 3.0, "transition": 0.02}, "Y": {"amplitude": 3.0, "transition": 0.02}},
        "force": {"use_machine_compliance": True},
        "tool_deflection": {"stick_out_mm": 40.0},
        "thermal": {"file": str(ROOT / "fixtures/thermal/spindle_thermal_drift_part1.csv"),
                    "channels": {"Z": "ch3_um"}, "time_scale": 60.0, "time_offset_s": 3600.0},
    }, machine=m)
    t0 = time.perf_counter()
    res = simulate(prog, m, effects, part="nas979", points=args.points, progress=True)
    wall = time.perf_counter() - t0
    d = res.deviations_um
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"cone: {prog.count(chr(10))} lines, {res.info['samples']} samples at 1 ms, {res.info['instances']} "
          f"cutting instances, {res.info['points']} points, {res.info['pairs']:,} exact pairs")
    print("timings: " + ", ".join(f"{k} {v:.1f}" for k, v in res.timings.items()) + f"; wall {wall:.1f} s; "
          f"peak RSS {rss:.0f} MB")
    print(f"deviation: mean {np.nanmean(d):+.2f} um, rms {np.sqrt(np.nanmean(d**2)):.2f} um, "
          f"range {np.nanmin(d):+.2f}..{np.nanmax(d):+.2f} um, not cut {res.info['not_cut']}")


if __name__ == "__main__":
    main()
