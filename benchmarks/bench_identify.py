"""Benchmark: identification of the twin's parameters from 1,000,000 measured points on the NAS 979 cone (issue:
inspection). Goal: under 10 s on the 2-core reference machine. Prints the figures.

    .venv/bin/python benchmarks/bench_identify.py [--points 1000000]

The cloud is synthetic, made with the first-order model the identifier fits (the true machine's error at each point's
contact instance, along its normal, plus 0.5 um of probe noise): the virtual shop's envelope would take minutes for a
million points and this measures the identifier, not the shop. The program is the NAS 979 flank-milling program of the
nmv1500dcg layout, posted for an error-free twin; the true machine is nmv1500dcg's typical error values.
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import time

import numpy as np

from trueaxis.inspect.identify import contact_weights, find_contacts, identify, nominal_tool_path
from trueaxis.inspect.parts import Nas979Params, cone_surface_points
from trueaxis.inspect.programs import nas979_program
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.resources import machine_file


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--noise-um", type=float, default=0.5)
    args = ap.parse_args()
    true = load_machine(machine_file("nmv1500dcg"))
    zero = np.zeros(len(true.parameter_names()))
    nominal = dataclasses.replace(true.with_parameters(zero), loaded=None, loaded_force_n=None,
                                  compliance_um_per_n=None, surfaces=())
    prog = nas979_program(nominal, compensation="none")
    cone = Nas979Params().cone_surface()
    rings = 200
    pts, nrm = cone_surface_points(cone, np.linspace(1.0, 19.0, rings), max(1, args.points // rings))

    # Synthetic measurement: the true machine's first-order deviation plus noise.
    path = nominal_tool_path(prog.text, prog.machine)
    c = find_contacts(pts, nrm, path, true.tool.radius, true.tool.flute_length)
    ok = c.found
    uniq, inv = np.unique(c.sample[ok], return_inverse=True)
    ep, eu = ErrorTwin(dataclasses.replace(true, workpiece_origin=prog.machine.workpiece_origin)).volumetric_error(
        path.q[uniq])
    dev = c.gap_um[ok] + np.einsum("ni,ni->n", contact_weights(nrm[ok], c.lever_mm[ok]), np.c_[ep, eu][inv])
    dev += np.random.default_rng(0).normal(0.0, args.noise_um, dev.size)
    measured = pts[ok] + (dev * 1e-3)[:, None] * nrm[ok]
    print(f"{ok.sum()} points on the cone, {len(path)} tool instances in the program, "
          f"{len(true.parameter_names())} twin parameters; deviation RMS {np.sqrt(np.mean(dev**2)):.2f} um")

    t = time.perf_counter()
    result = identify(measured, nrm[ok], dev, prog.text, prog.machine)
    elapsed = time.perf_counter() - t
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"identify: {elapsed:.2f} s for {result.n_used} points ({result.n_instances} contact instances), "
          f"peak RSS {rss:.0f} MB; goal < 10 s: {'met' if elapsed < 10 else 'NOT met'}")
    print(f"residual RMS {result.residual_rms_um:.3f} um (noise {args.noise_um} um); identified: "
          + ", ".join(f"{result.names[i]} {result.value[i]:+.2f} +- {result.std[i]:.2f} "
                      f"(true {true.parameter_values()[i]:+.2f})" for i in np.nonzero(result.identified)[0]))


if __name__ == "__main__":
    main()
