"""Benchmark: ``inspect`` of a 10,000,000-point cone cloud end to end (a new process, as a user runs it).

Goal (issue "Bad input never passes", scale): under 60 s and 4 GB peak memory on 2 cores. The cloud is the NAS 979
cone with +-30 um offsets along the normal (``bench_inspect.cone_cloud``), written as binary PLY; the time is the
``trueaxis inspect`` process' wall time, the memory its peak resident set (``ru_maxrss`` of the child).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_inspect_large.py [--points 10000000]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_inspect import cone_cloud  # noqa: E402
from trueaxis.inspect.cloud import write_cloud_ply  # noqa: E402
from trueaxis.workpiece.parts import nas979_description  # noqa: E402

GOAL_S = 60.0
GOAL_GB = 4.0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=10_000_000)
    args = ap.parse_args()
    cone = nas979_description()["surfaces"][0]
    points, _ = cone_cloud(cone, args.points)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        write_cloud_ply(work / "cloud.ply", points)
        del points
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        start = time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "trueaxis.cli", "inspect", str(work / "cloud.ply"), "--part",
                              "nas979", "-o", str(work / "report")], capture_output=True, text=True, env=env)
        wall = time.perf_counter() - start
        peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024 ** 2  # kB on Linux
        if run.returncode != 0:
            raise RuntimeError(f"inspect failed: {run.stderr[-2000:]}")
        print(f"inspect of {args.points:,} cone points end to end: {wall:.1f} s, peak {peak_gb:.2f} GB "
              f"({'goal met' if wall <= GOAL_S and peak_gb <= GOAL_GB else 'goal NOT met'}: <= {GOAL_S:g} s and "
              f"<= {GOAL_GB:g} GB on 2 cores)")
        print(f"  {run.stdout.strip().splitlines()[-1] if run.stdout.strip() else ''}")


if __name__ == "__main__":
    main()
