"""The virtual shop re-running the papers' cutting tests (checks of the shop itself; README figures).

``slot_experiment``
    The slot test of the equivalent-cutting-force paper: the xh714 machine with its (typical) geometric errors, its
    equivalent-load parameter set and its compliance acting through the cutting force of the real engagement, cuts
    the three-slot block (slot 1 uncompensated, slot 2 geometric, slot 3 comprehensive compensation, posted with the
    twin of the same machine); the virtual CMM probes the walls. Contour error of a slot: the mean absolute normal
    deviation of its wall points (the paper's CMM contour error, 56 / 34 / 23 um there).
``cone_experiment``
    The NAS 979 cone flank-milled on nmv1500dcg with its typical errors and an uncompensated program: roundness at
    the part's evaluation heights (least squares and minimum zone) and the cone-angle error, against the 10-50 um
    circularity that typical_error_magnitudes.md gives for uncalibrated machines.
"""

from __future__ import annotations

import math

import numpy as np

from ..inspect import form
from ..inspect.deviation import analytic_surfaces, deviation
from ..inspect.report import evaluate_slots
from ..workpiece.parts import Nas979Params, SlotBlockParams, nas979_description, slot_block_description
from ..machine import Machine, load_machine
from ..resources import machine_file
from .effects import parse_effects
from .shop import simulate


def slot_experiment(points: int = 6000, params: SlotBlockParams | None = None, machine: Machine | None = None,
                    seed: int = 0) -> dict:
    """Contour error of the three slots (um), none / geometric / comprehensive. See the module docstring."""
    from ..postproc.programs import slots_program

    m = machine or load_machine(machine_file("xh714"))
    p = params or SlotBlockParams()
    prog = slots_program(m, p)
    part = slot_block_description(p)
    effects = parse_effects({"force": {"use_machine_compliance": True}}, machine=m)
    res = simulate(prog.text, m, effects, part="slots", part_json=part, points=points, seed=seed)
    # Measured the way ``inspect`` measures a real slot block: deviations from the part's analytic surfaces, then
    # each slot's mean contour error over its walls and arcs.
    measured = res.measured[np.all(np.isfinite(res.measured), axis=1)]
    report, _ = evaluate_slots(measured, deviation(measured, analytic_surfaces(part)), part)
    out = [{"slot": k + 1, "compensation": s["compensation"], "points": s["points"],
            "contour_error_um": s["mean_contour_error_um"], "rms_um": s["deviation_um"]["rms"],
            "max_abs_um": max(abs(s["deviation_um"]["min"]), abs(s["deviation_um"]["max"]))}
           for k, s in enumerate(report["slots"])]
    return {"slots": out, "force_max_n": res.info.get("force_max_n", 0.0), "not_cut": res.info["not_cut"],
            "seconds": res.timings["total_s"]}


def cone_experiment(points: int = 20000, machine: Machine | None = None, params: Nas979Params | None = None,
                    compensation: str = "none", seed: int = 0) -> dict:
    """Roundness (um) at the part's evaluation heights and cone-angle error (urad) of a simulated cone."""
    from ..postproc.programs import nas979_program

    m = machine or load_machine(machine_file("nmv1500dcg"))
    p = params or Nas979Params()
    prog = nas979_program(m, p, compensation=compensation)
    part = nas979_description(p)
    res = simulate(prog.text, m, None, part="nas979", part_json=part, points=points, seed=seed)
    ok = np.isfinite(res.deviations_um)
    measured = res.measured[ok]
    cone = next(s for s in part["surfaces"] if s["id"] == "cone")
    axis = np.asarray(cone["axis"], float)
    base = np.asarray(cone["base_center"], float)
    half = math.radians(cone["half_angle_deg"])
    rings = []
    heights = np.unique(np.round((res.points[ok] - base) @ axis, 9))
    for f in (f for f in part["features"] if f["type"] == "roundness"):
        h = float(heights[np.argmin(np.abs(heights - f["height"]))])  # the probed ring nearest the asked height
        ring, idx = form.section_ring(measured, base, axis, h, tolerance=0.05, half_angle_rad=half, return_index=True)
        rings.append({"feature": f["id"], "height_mm": h, "mean_deviation_um": float(res.deviations_um[ok][idx].mean()),
                      "least_squares_um": 1e3 * form.roundness(ring, "least_squares"),
                      "minimum_zone_um": 1e3 * form.roundness(ring, "minimum_zone")})
    fit = form.fit_cone(measured, initial_axis=axis, initial_apex=base)
    d = res.deviations_um[ok]
    return {"roundness": rings, "half_angle_deg": math.degrees(fit.half_angle_rad),
            "half_angle_error_urad": 1e6 * (fit.half_angle_rad - half),
            "deviation_rms_um": float(np.sqrt(np.mean(d**2))), "deviation_range_um": [float(d.min()), float(d.max())],
            "not_cut": res.info["not_cut"], "seconds": res.timings["total_s"]}
