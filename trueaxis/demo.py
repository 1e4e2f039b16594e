"""``make demo``: the main job end to end on built-in defaults, through the same commands a user types.

1. The error twins of the fixture machines: volumetric-error summary, and the error field of the five-axis machine.
2. The NAS 979 cone as CAD (``trueaxis part``) and as a compensated five-axis program (``trueaxis program``).
3. A true machine with an effect its twin lacks (backlash on X) cuts the cone in the virtual shop and the virtual CMM
   measures it (``trueaxis simulate``).
4. ``inspect`` compares the cloud with the CAD; ``trueaxis diagnose`` says where the gap to the twin lies, which effect
   causes it and how far it shrinks once that effect is added.
5. The closed loop: a machine with typical geometric errors cuts, the deviations are back-propagated into its twin,
   the post compensates with the identified twin, and the shop cuts again.

Everything lands in the output folder (default ``demo_out``); the two HTML reports are printed at the end.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .fileio import json_text
from .machine import ErrorTwin, load_machine
from .machine.workspace import volumetric_summary
from .resources import machine_file, machine_files

FIVE_AXIS_DEMO_MACHINE = "nmv1500dcg"

# The effect the twin lacks in the demo: 8 um of lost motion at every reversal of X, taken up over 20 um of travel.
DEMO_EFFECTS = """# demo: the true machine = the twin plus an effect the twin does not model
[backlash.X]
amplitude = 8.0        # um of lost motion at reversals
transition = 0.02      # mm of travel over which it is taken up
"""


def run_demo(out: Path, points: int = 8000, noise_um: float = 1.0) -> int:
    from .cli import main as trueaxis

    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    _section("1. the error twins of the fixture machines (values typical, not measured)")
    machine_summary(out)

    _section("2. the NAS 979 cone: CAD and a geometric-compensated five-axis program")
    twin_file = str(machine_file(FIVE_AXIS_DEMO_MACHINE))
    _run(trueaxis, ["part", "nas979", "-o", str(out / "part")])
    _run(trueaxis, ["program", "nas979", "--machine", twin_file, "--compensate", "geometric",
                    "-o", str(out / "cone.ngc"), "--cl", str(out / "cone_cl.csv")])

    _section("3. a true machine with backlash on X (the twin lacks it) cuts the cone; the virtual CMM measures it")
    effects = out / "effects.toml"
    effects.write_text(DEMO_EFFECTS, encoding="utf-8")
    _run(trueaxis, ["simulate", str(out / "cone.ngc"), "--machine", twin_file, "--effects", str(effects),
                    "--part", "nas979", "--part-dir", str(out / "part"), "-o", str(out / "cmm.ply"),
                    "--points", str(points), "--noise-um", str(noise_um), "--seed", "1"])

    _section("4. inspect the cloud against the CAD, then diagnose the gap to the twin")
    _run(trueaxis, ["inspect", str(out / "cmm.ply"), "--part", "nas979", "--part-dir", str(out / "part"),
                    "-o", str(out / "inspect")])
    _run(trueaxis, ["diagnose", "--cloud", str(out / "cmm.ply"), "--part", "nas979", "--machine", twin_file,
                    "--program", str(out / "cone.ngc"), "--noise-um", str(noise_um), "-o", str(out / "diagnosis")])
    diagnosis = json.loads((out / "diagnosis" / "diagnosis.json").read_text(encoding="utf-8"))
    _say_diagnosis(diagnosis)

    _section("5. the closed loop: cut, measure, identify, compensate with the identified twin, cut again")
    loop_summary(out)

    print(f"\nreports: {(out / 'inspect' / 'report.html').resolve().as_uri()}")
    print(f"         {(out / 'diagnosis' / 'diagnosis.html').resolve().as_uri()}")
    print(f"demo done in {time.perf_counter() - t0:.0f} s; everything is in {out}/")
    return 0


def _section(title: str) -> None:
    print(f"\n== {title}")


def _run(command, argv: list[str]) -> None:
    print("$ trueaxis " + " ".join(argv))
    rc = command(argv)
    if rc:
        raise SystemExit(f"demo: 'trueaxis {argv[0]}' failed with exit status {rc}")


def _say_diagnosis(d: dict) -> None:
    where = ", ".join(f"{w['variable']}" for w in d.get("where", [])[:3])
    chosen = d.get("chosen") or []
    which = ", ".join(f"{c['effect']} (confidence {c.get('confidence', 0):.2f})" for c in chosen) or "none of the candidates"
    before, after = d["gap_um"]["before"], d["gap_um"]["after"]
    print(f"where: the gap follows {where}")
    print(f"which: {which}")
    print(f"how far: held-out gap RMS {before['rms']:.2f} -> {after['rms']:.2f} um, "
          f"P95 {before['p95']:.2f} -> {after['p95']:.2f} um, max {before['max']:.2f} -> {after['max']:.2f} um")


def machine_summary(out: Path) -> None:
    header = f"{'machine':44s} {'poses':>7s} {'pos max':>9s} {'pos RMS':>9s} {'axis max':>10s} {'axis RMS':>10s}"
    print(header)
    print(f"{'':44s} {'':>7s} {'um':>9s} {'um':>9s} {'urad':>10s} {'urad':>10s}")
    summaries = []
    for path in machine_files():
        m = load_machine(path)
        s = volumetric_summary(m, n=20_000, seed=0)
        summaries.append({"file": path.name, **s.as_dict()})
        print(
            f"{path.stem + ': ' + m.name:44.44s} {s.poses:7d} {s.position_max_um:9.2f} {s.position_rms_um:9.2f}"
            f" {s.orientation_max_urad:10.2f} {s.orientation_rms_urad:10.2f}"
        )
    (out / "volumetric_summary.json").write_text(json_text(summaries))
    picture = plot_error_field(load_machine(machine_file(FIVE_AXIS_DEMO_MACHINE)), out / "error_field_nmv1500dcg.png")
    print(f"error field of the five-axis machine: {picture}")


def loop_summary(out: Path, points: int = 4000) -> None:
    from .loop import closed_loop

    # Twice: as a user runs it by default (the set-up's accuracy not given: any translation of the part is its
    # set-up's, the machine's share of it included, and stays on the next part), and told that the virtual shop sets
    # the part up exactly (``--setup-sigma-um 0``).
    true = load_machine(machine_file(FIVE_AXIS_DEMO_MACHINE))
    for title, options, name in (
            ("the set-up's accuracy not given (the default): a translation of the part is its set-up's", None,
             "closed_loop.json"),
            ("told that the virtual shop sets the part up exactly (--setup-sigma-um 0)", {"setup_sigma_um": 0.0},
             "closed_loop_setup_known.json")):
        result = closed_loop(true, part="nas979", points=points, identify_options=options)
        print(f"({title})")
        print(result.summary())
        (out / name).write_text(json_text(result.as_dict()))


def plot_error_field(machine, path: Path) -> Path:
    """Three panels: |position error| over X-Y (rotary axes at zero), and position and tool-axis error over B-C."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    twin = ErrorTwin(machine)
    names = machine.axis_names
    rot = list(machine.rotary_axes)
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8), constrained_layout=True)

    # (a) X-Y map at mid Z, rotary axes at zero.
    tx, ty = machine.axes["X"].travel, machine.axes["Y"].travel
    gx, gy = np.meshgrid(np.linspace(*tx, 61), np.linspace(*ty, 46))
    q = np.zeros((gx.size, len(names)))
    q[:, names.index("X")] = gx.ravel()
    q[:, names.index("Y")] = gy.ravel()
    if "Z" in names:
        q[:, names.index("Z")] = np.mean(machine.axes["Z"].travel)
    dp, _ = twin.volumetric_error(q)
    mag = np.linalg.norm(dp, axis=1).reshape(gx.shape)
    im = axes[0].pcolormesh(gx, gy, mag, shading="auto", cmap="viridis")
    s = 4
    axes[0].quiver(gx[::s, ::s], gy[::s, ::s], dp[:, 0].reshape(gx.shape)[::s, ::s], dp[:, 1].reshape(gx.shape)[::s, ::s],
                   color="white")
    axes[0].set(title=f"|position error| over X-Y ({', '.join(rot)} = 0)", xlabel="X (mm)", ylabel="Y (mm)")
    fig.colorbar(im, ax=axes[0], label="um")

    # (b, c) over the two rotary axes, linear axes at zero.
    if len(rot) == 2:
        r0 = machine.axes[rot[0]].travel or (-np.pi, np.pi)
        r1 = machine.axes[rot[1]].travel or (-np.pi, np.pi)
        g0, g1 = np.meshgrid(np.linspace(*r0, 61), np.linspace(*r1, 73))
        q = np.zeros((g0.size, len(names)))
        q[:, names.index(rot[0])] = g0.ravel()
        q[:, names.index(rot[1])] = g1.ravel()
        dp, du = twin.volumetric_error(q)
        for ax, val, label, title in (
            (axes[1], np.linalg.norm(dp, axis=1), "um", "|position error| over the rotary axes"),
            (axes[2], np.linalg.norm(du, axis=1), "urad", "|tool-axis error| over the rotary axes"),
        ):
            im = ax.pcolormesh(np.degrees(g0), np.degrees(g1), val.reshape(g0.shape), shading="auto", cmap="magma")
            ax.set(title=title + " (X Y Z = 0)", xlabel=f"{rot[0]} (deg)", ylabel=f"{rot[1]} (deg)")
            fig.colorbar(im, ax=ax, label=label)
    fig.suptitle(f"{machine.name}: volumetric error in the part frame (typical values, not measured)")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
