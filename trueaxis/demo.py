"""``make demo``: the main job end to end on built-in defaults.

At this stage of the project: load every fixture machine, print its volumetric-error summary over the workspace,
and draw the error field of the five-axis machine.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .machine import ErrorTwin, load_machine
from .machine.workspace import volumetric_summary
from .resources import machine_file, machine_files

FIVE_AXIS_DEMO_MACHINE = "nmv1500dcg"


def run_demo(out: Path) -> int:
    out.mkdir(parents=True, exist_ok=True)
    print("trueaxis demo: the error twins of the fixture machines (values typical, not measured)\n")
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
    (out / "volumetric_summary.json").write_text(json.dumps(summaries, indent=2))
    picture = plot_error_field(load_machine(machine_file(FIVE_AXIS_DEMO_MACHINE)), out / "error_field_nmv1500dcg.png")
    print(f"\nerror field of the five-axis machine: {picture}")
    print(f"summary: {out / 'volumetric_summary.json'}")
    return 0


def plot_error_field(machine, path: Path) -> Path:
    """Three panels: |position error| over X-Y (rotary axes at zero), and position and tool-axis error over B-C."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    twin = ErrorTwin(machine)
    names = machine.axis_names
    lin = [a for a in names if not machine.axes[a].is_rotary]
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
