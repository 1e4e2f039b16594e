"""The closed loop in the virtual shop: cut, measure, identify, compensate, cut again (DESIGN §1, §8).

    result = closed_loop(load_machine("fixtures/machines/nmv1500dcg.toml"))      # the true machine
    print(result.summary())

1. The part program (``trueaxis.postproc.programs``) is posted (``trueaxis.postproc.post.compensate``, geometric) with
   the *twin* the shop believes in (default: the true machine's layout with no errors at all).
2. The virtual shop (``trueaxis.sim.shop.simulate``) cuts it on the *true* machine and measures it (virtual CMM,
   probe noise); the deviations come from the measured cloud alone, as ``inspect`` computes them (exact distances to
   the part JSON's analytic surfaces, ``trueaxis.inspect.deviation``). Nothing of the simulator's truth (instances, axes at the cut) is used.
3. ``identify`` back-propagates the deviations into the twin's parameters; the post compensates the same program with
   the identified twin; the shop cuts and measures again.

Slot block: the part program posts slot 1 uncompensated, slot 2 geometric, slot 3 comprehensive. In the loop all
three slots get the same treatment: the uncompensated program (``slots_program(...).raw``) is posted whole with mode
"geometric", first with the starting twin, then with the identified one, so the three slots are three repeats.

``user_loop`` runs the loop as a user does, command by command (program, simulate, inspect --identify --write, program
again with the written twin), for as many rounds as asked.

Units: um for deviations, mm for geometry.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from .machine import Machine
from .postproc.post import compensate
from .inspect.form import roundness, section_ring
from .inspect.deviation import analytic_surfaces, deviation
from .identify import Identification, identify
from .workpiece.parts import cone_signed_distance
from .postproc.programs import part_program
from .workpiece.part import get_part


def error_free(machine: Machine) -> Machine:
    """The machine's layout with every error parameter zero and no force model (``Machine.error_free``)."""
    return machine.error_free()


# ----------------------------------------------------------------------------------------------- deviations ----
def cone_deviation_um(points, part: dict) -> np.ndarray:
    """Signed deviation (N,) um of measured points from the NAS 979 cone (+ = material outside)."""
    cone = next(s for s in part["surfaces"] if s["id"] == "cone")
    return cone_signed_distance(np.asarray(points, float), cone) * 1e3


# ----------------------------------------------------------------------------------------------- one round ----
@dataclass
class Cut:
    """One cut-and-measure round: the program, the measured cloud and its deviations (um)."""

    program: str
    points: np.ndarray
    normals: np.ndarray
    deviation_um: np.ndarray
    metrics: dict


def _measure(program: str, true: Machine, part_name: str, points: int, noise_um: float, seed: int,
             part_json=None) -> Cut:
    from .sim.shop import load_part, simulate

    part = load_part(part_name, part_json)
    res = simulate(program, true, part=part_name, part_json=part, points=points, noise_um=noise_um, seed=seed)
    cut = np.all(np.isfinite(res.measured), axis=1)
    pts, nrm = res.measured[cut], res.normals[cut]
    # The inspection's own deviations (exact distances to the part JSON's analytic surfaces); points farther than
    # half a millimetre from every surface are not on the part's inspection surfaces and are left out.
    dev = deviation(pts, analytic_surfaces(part)).deviation_um
    ok = np.abs(dev) <= 500.0
    pts, nrm, dev = pts[ok], nrm[ok], dev[ok]
    return Cut(program, pts, nrm, dev, _metrics(pts, nrm, dev, part))


def _metrics(points, normals, dev, part: dict) -> dict:
    m = {"points": int(dev.size), "rms_um": float(np.sqrt(np.mean(dev**2))), "mean_um": float(np.mean(dev)),
         "max_abs_um": float(np.max(np.abs(dev))), "range_um": float(np.ptp(dev))}
    # What the part's features ask for: roundness rings on a cone, the walls and floors of slots.
    ring_features = [f for f in part["features"] if f["type"] == "roundness"]
    if ring_features:
        cone = next(s for s in part["surfaces"] if s["id"] == ring_features[0]["surface"])
        alpha = math.radians(cone["half_angle_deg"])
        a = np.asarray(cone["axis"], float)
        h = (points - np.asarray(cone["base_center"], float)) @ (a / np.linalg.norm(a))
        rings = {}
        for feat in ring_features:
            # The probed ring nearest the feature's height (the probe pattern's rings need not hit it exactly).
            level = h[np.argmin(np.abs(h - feat["height"]))]
            if abs(level - feat["height"]) > 1.0:
                continue
            ring = section_ring(points, cone["base_center"], a, level, 0.05, half_angle_rad=alpha)
            if len(ring) >= 8:
                rings[feat["id"]] = float(roundness(ring) * 1e3)
        m["roundness_um"] = rings
        m["roundness_max_um"] = max(rings.values()) if rings else float("nan")
    if any(f["type"] == "slot" for f in part["features"]):
        walls = np.abs(normals[:, 2]) < 0.5
        m["walls_rms_um"] = float(np.sqrt(np.mean(dev[walls] ** 2))) if walls.any() else float("nan")
        m["floors_rms_um"] = float(np.sqrt(np.mean(dev[~walls] ** 2))) if (~walls).any() else float("nan")
    return m


# ----------------------------------------------------------------------------------------------- the loop ----
@dataclass
class LoopResult:
    """Before and after one identification loop. ``before`` / ``after``: :class:`Cut`. ``twin``: the twin the first
    program was posted with; ``identification``: what ``identify`` found (its ``machine`` posted the second)."""

    part: str
    before: Cut
    after: Cut
    identification: Identification
    twin: Machine
    timings_s: dict = field(default_factory=dict)

    @property
    def rms_reduction(self) -> float:
        """1 - rms_after / rms_before."""
        return 1.0 - self.after.metrics["rms_um"] / self.before.metrics["rms_um"]

    def as_dict(self) -> dict:
        ident = self.identification.as_report()
        return {"part": self.part, "before": self.before.metrics, "after": self.after.metrics,
                "rms_reduction": self.rms_reduction,
                "identified": ident["parameters"], "not_identifiable_count": len(ident["not_identifiable"]),
                "residual_rms_um": ident["residual_rms_um"], "condition_number": ident["condition_number"],
                "condition_number_identified": ident["condition_number_identified"], "timings_s": self.timings_s}

    def summary(self) -> str:
        b, a = self.before.metrics, self.after.metrics
        lines = [f"{self.part}: RMS deviation {b['rms_um']:.2f} -> {a['rms_um']:.2f} um "
                 f"({100 * self.rms_reduction:.0f} % lower), max |dev| {b['max_abs_um']:.2f} -> "
                 f"{a['max_abs_um']:.2f} um"]
        if "roundness_um" in b:
            for k in b["roundness_um"]:
                lines.append(f"  {k}: {b['roundness_um'][k]:.2f} -> {a['roundness_um'].get(k, float('nan')):.2f} um")
        r = self.identification
        ids = np.nonzero(r.identified)[0]
        # '*': written as one term of the combination the part needs, its own value not determined (within 2 std of
        # no change, the aliasing counted), as the identification's own lines say
        alone = {i: abs(r.value[i] - r.prior[i]) > 2.0 * r.std[i] for i in ids}
        lines.append("  identified: " + ", ".join(f"{r.names[i]} {r.value[i]:+.2f} +- {r.std[i]:.2f}"
                                                 + ("" if alone[i] else "*") for i in ids))
        if not all(alone.values()):
            lines.append("  (* in combination: the part needs the sum of these changes, not each value alone)")
        return "\n".join(lines)


def closed_loop(true_machine: Machine, twin: Machine | None = None, part: str = "nas979", *, points: int = 4000,
                noise_um: float = 0.5, seed: int = 0, program_options: dict | None = None,
                identify_options: dict | None = None, post_options: dict | None = None) -> LoopResult:
    """One loop of cut, measure, identify, compensate, cut, measure in the virtual shop.

    true_machine : the machine that cuts (its errors are the truth; only twin parameters, no other effects).
    twin : the twin the shop starts with (default ``error_free(true_machine)``; same layout, its parameter values
        are the starting point of the identification).
    part : "nas979" (five-axis machine) | "slots".  points : probe points per measurement.  noise_um : probe noise.
    program_options : keywords for the part's program (``trueaxis.postproc.programs.PROGRAMS``; e.g. step_deg).
    identify_options : keywords for ``identify``.  post_options : keywords for ``compensate``.
    """
    get_part(part)  # ValueError naming the known parts
    twin = error_free(true_machine) if twin is None else twin
    if twin.parameter_names() != true_machine.parameter_names():
        raise ValueError("the twin and the true machine must share their parameter structure (same layout and tables)")
    timings = {}
    t = time.perf_counter()
    pp = part_program(part, twin, post=False, **(program_options or {}))
    raw = pp.raw
    placed_twin = pp.machine
    true = dataclasses.replace(true_machine, workpiece_origin=placed_twin.workpiece_origin.copy())
    post = {"source": f"{part}.ngc", **(post_options or {})}
    program0 = compensate(raw, placed_twin, "geometric", **post)
    timings["program_s"] = time.perf_counter() - t

    t = time.perf_counter()
    before = _measure(program0, true, part, points, noise_um, seed)
    timings["cut_and_measure_before_s"] = time.perf_counter() - t
    t = time.perf_counter()
    result = identify(before.points, before.normals, before.deviation_um, program0, placed_twin,
                      **(identify_options or {}))
    timings["identify_s"] = time.perf_counter() - t
    t = time.perf_counter()
    # A refused identification leaves the twin as it was (what ``inspect --write`` does).
    program1 = compensate(raw, result.machine if result.accepted else placed_twin, "geometric", **post)
    after = _measure(program1, true, part, points, noise_um, seed + 1)
    timings["post_cut_and_measure_after_s"] = time.perf_counter() - t
    return LoopResult(part, before, after, result, placed_twin, timings)


# ------------------------------------------------------------------------------------- the loop as a user runs it ----
@dataclass
class Round:
    """One round of the user's loop: the program posted with ``twin``, cut on the true machine, measured, identified.

    rms_um / max_abs_um : the part's deviation (inspect's report).  slots_rms_um : per slot (slot block).
    misfit_rms_um : what the twin leaves unexplained on this part before the identification; residual_rms_um after.
    verdict : accepted | no change | refused.  written : the twin file written (None when refused).
    misfit_placed_rms_um : the misfit with the part's set-up offset (a translation of the part) fitted alone: what
    the twin can learn where the set-up is free (the default), the machine's translation being the set-up's."""

    round: int
    twin: str
    program: str
    rms_um: float
    max_abs_um: float
    slots_rms_um: dict
    misfit_rms_um: float
    residual_rms_um: float
    verdict: str
    written: str | None
    exit_code: int
    misfit_placed_rms_um: float | None = None


def user_loop(folder, part: str, twin_file, true_file, *, rounds: int = 3, compensate: str | None = "geometric",
              points: int = 4000, noise_um: float = 0.5, program_args=(), seed: int = 0,
              inspect_args=(), simulate_args=()) -> list[Round]:
    """The closed loop as a user runs it, command by command (``trueaxis.cli.main``), in ``folder``:

        trueaxis program PART --machine TWIN_k.toml [--compensate MODE] -o rK.ngc
        trueaxis simulate rK.ngc --machine TRUE.toml --part PART -o rK.ply --points N --noise-um S --seed SEED+K
        trueaxis inspect rK.ply --part PART --identify --machine TWIN_k.toml --program rK.ngc --write twinK.toml

    and the next round programs with the written twin (the same twin again when the identification refused).
    compensate : the program's mode for the cone (none | geometric | comprehensive); None for the slot block (its
    slots are posted none, geometric and comprehensive). program_args : more ``program`` options (e.g. a coarser
    ``--step-deg``). inspect_args : more ``inspect`` options (e.g. ``--setup-sigma-um 0``: the virtual shop sets the
    part up exactly). simulate_args : more ``simulate`` options (e.g. ``--effects`` with the machine's force).
    Returns one :class:`Round` per round. A command that fails for bad input raises RuntimeError.
    """
    import json
    from pathlib import Path

    from .cli import EXIT_REFUSED, main

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    twin = str(twin_file)
    out = []
    for k in range(1, rounds + 1):
        prog, cloud, new, rep = (folder / f"r{k}.ngc", folder / f"r{k}.ply", folder / f"twin{k}.toml",
                                 folder / f"r{k}_report")
        cmd = ["program", part, "--machine", twin, "-o", str(prog), *map(str, program_args)]
        if compensate is not None:
            cmd += ["--compensate", compensate]
        for c in (cmd, ["simulate", str(prog), "--machine", str(true_file), "--part", part, "-o", str(cloud),
                        "--points", str(points), "--noise-um", str(noise_um), "--seed", str(seed + k),
                        *map(str, simulate_args)]):
            if main(c) != 0:
                raise RuntimeError(f"trueaxis {' '.join(c)} failed")
        code = main(["inspect", str(cloud), "--part", part, "--identify", "--machine", twin, "--program", str(prog),
                     "--write", str(new), "-o", str(rep), *map(str, inspect_args)])
        if code not in (0, EXIT_REFUSED):
            raise RuntimeError(f"trueaxis inspect {cloud} failed (exit {code})")
        r = json.loads((rep / "report.json").read_text())
        ident = r["identification"]
        slots = {s["compensation"]: s["deviation_um"]["rms"] for s in r.get("slots", [])}
        d = r["deviation_um"]
        out.append(Round(k, twin, str(prog), d["rms"], max(abs(d["min"]), abs(d["max"])), slots,
                         ident["verdict"]["residual_before_rms_um"], ident["verdict"]["residual_after_rms_um"],
                         ident["verdict"]["status"], ident.get("written"), code,
                         ident["verdict"].get("residual_placed_rms_um")))
        if code == 0:
            twin = str(new)
    return out
