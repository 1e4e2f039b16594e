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
from ..inspect.parts import Nas979Params, SlotBlockParams, nas979_description, slot_block_description
from ..machine import Machine, load_machine
from ..resources import machine_file
from .effects import parse_effects
from .shop import simulate


def slot_of_points(part: dict, points) -> np.ndarray:
    """(N,) int: index of the slot (0, 1, 2) whose tool-centre path is nearest to each point in XY."""
    pts = np.asarray(points, float)[:, :2]
    slots = [f for f in part["features"] if f.get("type") == "slot"]
    best = np.full((pts.shape[0], len(slots)), np.inf)
    for k, feat in enumerate(slots):
        path = np.asarray(feat["tool_centre_path"], float)[:, :2]
        a, b = path[:-1], path[1:]
        ab = b - a
        t = np.clip(np.einsum("nkj,kj->nk", pts[:, None, :] - a, ab) / np.einsum("kj,kj->k", ab, ab), 0.0, 1.0)
        best[:, k] = np.linalg.norm(pts[:, None, :] - (a + t[..., None] * ab), axis=2).min(axis=1)
    return best.argmin(axis=1)


def slot_experiment(points: int = 6000, params: SlotBlockParams | None = None, machine: Machine | None = None,
                    seed: int = 0) -> dict:
    """Contour error of the three slots (um), none / geometric / comprehensive. See the module docstring."""
    from ..inspect.programs import slots_program

    m = machine or load_machine(machine_file("xh714"))
    p = params or SlotBlockParams()
    prog = slots_program(m, p)
    part = slot_block_description(p)
    effects = parse_effects({"force": {"use_machine_compliance": True}}, machine=m)
    res = simulate(prog.text, m, effects, part="slots", part_json=part, points=points, seed=seed)
    slot = slot_of_points(part, res.points)
    wall = (np.abs(res.normals[:, 2]) < 0.5) & np.isfinite(res.deviations_um)
    out = []
    for k, mode in enumerate(("none", "geometric", "comprehensive")):
        d = res.deviations_um[wall & (slot == k)]
        out.append({"slot": k + 1, "compensation": mode, "points": int(d.size),
                    "contour_error_um": float(np.mean(np.abs(d))), "rms_um": float(np.sqrt(np.mean(d**2))),
                    "max_abs_um": float(np.max(np.abs(d)))})
    return {"slots": out, "force_max_n": res.info.get("force_max_n", 0.0), "not_cut": res.info["not_cut"],
            "seconds": res.timings["total_s"]}


def cone_experiment(points: int = 20000, machine: Machine | None = None, params: Nas979Params | None = None,
                    compensation: str = "none", seed: int = 0) -> dict:
    """Roundness (um) at the part's evaluation heights and cone-angle error (urad) of a simulated cone."""
    from ..inspect.programs import nas979_program

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
