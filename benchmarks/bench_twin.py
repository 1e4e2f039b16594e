"""Benchmark: volumetric error plus both Jacobians for 1,000,000 poses of the five-axis machine, every parameter
non-zero (issue: the error twin). Goal: under 1 s on the 2-core reference machine. Prints the figures for the README.

    .venv/bin/python benchmarks/bench_twin.py [--poses 1000000]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.machine.workspace import sample_poses
from trueaxis.resources import machine_file


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--poses", type=int, default=1_000_000)
    ap.add_argument("--machine", default="nmv1500dcg")
    args = ap.parse_args()
    m = load_machine(machine_file(args.machine))
    values = m.parameter_values()
    rng = np.random.default_rng(0)
    # Every parameter non-zero: keep the file's values, give the zero ones a typical size (10 um / 10 urad).
    values = np.where(values == 0.0, rng.normal(0.0, 10.0, values.size), values)
    m = m.with_parameters(values)
    tw = ErrorTwin(m)
    q = sample_poses(m, args.poses, seed=1)
    force = rng.normal(0.0, 100.0, (args.poses, 3))
    print(f"machine {m.name}: {len(m.axis_names)} axes, {tw.n_params} error parameters, all non-zero; {args.poses} poses")

    # Compile the chain kernels (or load them from numba's cache) outside the timings.
    tw.pose_and_axis_jacobian(q[:1])
    tw.actual_pose(q[:1])
    t = time.perf_counter()
    tw.volumetric_error(q, force_n=force)
    t_full = time.perf_counter() - t
    t = time.perf_counter()
    tw.volumetric_error(q, force_n=force, method="differential")
    t_diff = time.perf_counter() - t
    t = time.perf_counter()
    for _, dp, du, Ja, Jp in tw.iter_errors_and_jacobians(q, force_n=force):
        pass
    t_all = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # before the dense axis Jacobian below
    t = time.perf_counter()
    tw.pose_and_axis_jacobian(q, force_n=force)
    t_pose_ja = time.perf_counter() - t
    t = time.perf_counter()
    tw.actual_pose(q, force_n=force)
    t_pose = time.perf_counter() - t
    us = 1e6 / args.poses
    print(f"volumetric error, full transforms:        {t_full:7.2f} s")
    print(f"volumetric error, differential form:      {t_diff:7.2f} s")
    print(f"actual pose + axis Jacobian (compiled):   {t_pose_ja:7.2f} s  ({t_pose_ja * us:.2f} us per pose, "
          "the post's solver step)")
    print(f"actual pose (compiled):                   {t_pose:7.2f} s  ({t_pose * us:.2f} us per pose)")
    print(f"error + axis and parameter Jacobians:     {t_all:7.2f} s  (streamed in chunks; goal < 1 s)")
    print(f"peak memory:                              {peak:7.0f} MB")


if __name__ == "__main__":
    main()
