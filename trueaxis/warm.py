"""Fill the caches the post loads at start-up, once (the Makefile's venv target runs it after installing).

``python -m trueaxis.warm`` compiles the numba kernels the post and the inspection use (``fast_read``, ``fast_write``, the twin's
``error_kernel`` and ``chain_kernel``, with and without force) and stores them in numba's cache (``cache=True``), and
stores the cubic tables' unit splines of the fixture machines (``error_functions._unit_coefficients``), so that the
first post does not spend ~20 s compiling nor import scipy. It posts small programs on every fixture machine in every
mode and checks nothing else: the tests check the post. Safe to run again (it then only loads the caches).

Then it compiles the kernels the post calls ahead of time (:mod:`trueaxis.compiled`, ``numba.pycc``) into an extension
module next to the package, so that a small program posts without importing numba at all (about 0.45 s of CPU less
at start-up); best effort: without it the post uses numba's JIT and its cache, with the same output.
"""

from __future__ import annotations

import sys
import time

import numpy as np


def _mid(ax) -> float:
    """A linear axis' position about mid-travel (mm, whole), a rotary axis' 0."""
    return 0.0 if ax.is_rotary or ax.travel is None else float(round(0.5 * (ax.travel[0] + ax.travel[1])))


def _programs(machine) -> list:
    """Small programs for ``machine`` (its linear axes about mid-travel): plain blocks (the compiled reader and
    writer), an arc (three-axis mills), rotary moves (five-axis)."""
    names = machine.axis_names
    mid = {a: _mid(machine.axes[a]) for a in names}

    def block(**delta):
        return " ".join(f"{a}{mid[a] + delta.get(a, 0.0):g}" for a in names if a in mid and (a in delta or
                                                                                            not machine.axes[a].is_rotary))

    cut = "(trueaxis: ap=1 ae=2 fz=0.05 n=5000 d=10 z=4 mode=down)\n"
    if names == ("X", "Z"):
        return [f"G18 G21 G90 G8\nG0 {block()}\n(trueaxis: ap=1 f=0.2 vc=180)\nG1 {block(Z=-10)} F100\n"
                f"G1 {block(X=5, Z=-15)}\nM30\n"]
    if machine.rotary_axes:
        rot = [a for a in names if machine.axes[a].is_rotary]
        r0, r1 = rot[0], rot[-1]
        run = "".join(f"{block(X=2 + 0.1 * k, Y=3, **{r0: -7, r1: 30 + k})}\n" for k in range(20))  # fast_interp
        return [f"%\nG21 G90 G17 G94\nG0 {block(**{r0: -5, r1: 0})}\n{cut}G1 {block(X=0.5, Y=1, **{r0: -6, r1: 10})} F500\n"
                f"G1 {block(X=1, Y=2, **{r0: -7, r1: 20})}\n{block(X=2, Y=3, **{r0: -7, r1: 30})}\n{run}M30\n%\n"]
    run = "".join(f"{block(X=100 + k, Y=50, Z=-1)}\n" for k in range(20))  # a run for fast_interp
    return [f"%\nG21 G90 G17 G94\nG0 {block()}\n{cut}G1 {block(X=10, Y=5, Z=-1)} F500\n{block(X=20, Y=10, Z=-1)}\n"
            f"G2 {block(X=30, Y=20, Z=-1)} I10 J0\nG1 {block(X=100, Y=50, Z=-1)}\n{run}M30\n%\n"]


def warm(out=sys.stderr) -> None:
    from .machine import ErrorTwin, load_machine
    from .machine.error_functions import _unit_coefficients
    from .postproc.post import post_text
    from .nc.setup import Setup
    from .machine.twin import PARALLEL_MIN
    from .resources import machine_files

    t0 = time.perf_counter()
    for path in machine_files():
        m = load_machine(path)
        for es in (m.errors, m.loaded):
            for comps in (es.components.values() if es is not None else ()):
                for fn in comps.values():
                    if fn.kind == "cubic":
                        _unit_coefficients(fn.at, fn.periodic)
        twin = ErrorTwin(m)
        # the chain's parallel kernels (long programs), with and without force
        q = np.tile([_mid(m.axes[a]) for a in m.axis_names], (PARALLEL_MIN, 1))
        for force in (None, np.array([10.0, 20.0, -30.0])):
            twin.pose_and_axis_jacobian(q, force)
            twin.actual_pose(q, force)
        twin.nominal_pose(q)
        for text in _programs(m):
            for mode in ("geometric", "comprehensive"):
                try:
                    post_text(text, m, mode, source=f"warm:{path.stem}", setup=Setup(offsets_zero=True))
                except Exception as e:  # noqa: BLE001 -- best effort: a program this machine refuses fills caches too
                    print(f"trueaxis.warm: {path.stem} {mode}: {e}", file=out)
    _warm_inspection()
    print(f"trueaxis.warm: the post's and the inspection's compiled kernels and spline tables cached "
          f"({time.perf_counter() - t0:.1f} s)", file=out)


def _warm_inspection() -> None:
    """The inspection's kernels (:mod:`trueaxis.inspect.kernels`) with the types ``inspect`` calls them with: the
    deviations from the NAS 979 part's surfaces, a cone fitted and a deviation CSV written, from a small cloud on the
    default cone."""
    import os
    import tempfile

    from .inspect.cloud import write_deviation_csv
    from .inspect.deviation import analytic_deviation, analytic_surfaces
    from .inspect.form import fit_cone
    from .workpiece.parts import nas979_description

    theta, h = np.meshgrid(np.linspace(0.0, 2.0 * np.pi, 36, endpoint=False), np.linspace(1.0, 19.0, 6))
    radius = 40.0 - h * np.tan(np.radians(15.0))
    points = np.column_stack([(radius * np.cos(theta)).ravel(), (radius * np.sin(theta)).ravel(), h.ravel()])
    fit_cone(points, initial_axis=[0.0, 0.0, 1.0])
    analytic_deviation(points, analytic_surfaces(nas979_description()))
    with tempfile.TemporaryDirectory() as tmp:
        csv = os.path.join(tmp, "warm.csv")
        write_deviation_csv(csv, points, np.zeros(len(points)))
        write_deviation_csv(csv, points, np.zeros(len(points)), surface=(["cone"], np.zeros(len(points), int)))


def main() -> None:
    """The numba caches (:func:`warm`), then the kernels compiled ahead of time (:func:`trueaxis.compiled.build_aot`,
    which warms first): best effort, a failed build leaves the post on numba."""
    try:
        from .compiled import build_aot

        build_aot(warm)
    except Exception as exc:  # noqa: BLE001 -- best effort (no C compiler, say): the post runs on numba's JIT
        print(f"trueaxis.warm: the kernels were not compiled ahead of time ({type(exc).__name__}: {exc}); the post "
              "uses numba's JIT", file=sys.stderr)
        warm()


if __name__ == "__main__":
    main()
