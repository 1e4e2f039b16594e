"""Inspection of a CMM cloud against its part: deviations, form evaluation of the part's features, and the report
folder (``report.json`` + ``report.html`` with its PNG pictures), written atomically together.

    inspection = inspect_cloud("cmm.ply", "nas979", align="bestfit")
    write_report(inspection, "cmm_report")

The mathematics of distances and alignments is in ``trueaxis.inspect.deviation``; the fits (circles, cones, lines,
planes) are in ``trueaxis.inspect.form``. This module evaluates the features named in the part JSON with them and
assembles the figures. Units: reports carry um and urad with the unit in each key (DESIGN.md §7); inside, mm and rad.

Feature evaluation
------------------
NAS 979 (points assigned to the cone, within ``gate_mm`` of it):

- cone: least-squares cone (``form.fit_cone``), its axis (oriented base to top), the axis' tilt from nominal
  (urad), where it crosses the base plane, the apex, the half angle and its error (urad);
- roundness at each ``roundness`` feature height (along the fitted axis from where it crosses the nominal base
  plane): the points within ``slab_mm`` of the section, moved along the fitted generator onto it
  (``form.section_ring``), least squares (LSCI) and minimum zone (MZCI), um; fewer than 8 points: null with a reason;
- diameter at the ``diameter`` feature height, from the fitted cone (all cone points), and its error, um.

Slot block, per slot (points assigned to the slot's walls, arcs and floor):

- width of each straight segment: the distance between the least-squares lines of its two walls (XY traces of the
  wall points), measured along the nominal normal at the segment's midpoint; its error, um;
- straightness of each wall: minimum-zone straightness of its XY trace (points of all depths projected: a wall that
  leans adds its lean over the probed depths), um;
- parallelism of each segment's left wall to its right wall (the datum): peak-to-valley of the left wall's trace
  distances to the right wall's least-squares line (ISO 1101 zone of two lines parallel to the datum), um;
- position: the offset of the midline between the two walls from the nominal tool-centre path at each segment's
  midpoint, along the segment's left normal, um; the floor's depth error (mean z against the nominal), um;
- mean contour error: mean |deviation| over the slot's walls and arcs (the equivalent-cutting-force paper's figure).

Report folder
-------------
Written to a temporary folder beside the target, then renamed into place (an existing report folder is replaced
only after the new one is complete), so an error leaves nothing half-written.
"""

from __future__ import annotations

import base64
import dataclasses
import datetime
import html
import json
import math
import re
import shutil
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..fileio import OutputPathError, json_ready as _clean, publish_folder, resolve_output, temp_folder_beside
from . import deviation as dv
from .cloud import Cloud, CloudError, check_extent, read_cloud, write_deviation_csv, write_deviation_ply
from .flyers import MAX_BEYOND_GATE, rule_text, screen_flyers
from .tolerances import CHARACTERISTICS, feature_table, load_tolerances, summary
from ..workpiece.part import get_part
from ..workpiece.part import load_part as read_part

SIZE_KEYS = {k for k, v in CHARACTERISTICS.items() if v[0] == "size"}

__all__ = ["Inspection", "load_part", "inspect_cloud", "deviation_stats", "evaluate_nas979", "evaluate_slots",
           "write_report", "ALIGNMENTS"]

ALIGNMENTS = ("none", "bestfit", "datum")
EXTENT_TOLERANCE_MM = 1.0   # stock, probe radius and fixture allowance around the part's bounding box
EXTENT_OUTLIERS = 0.01      # flyers: up to 1 % of the points may lie outside the part's box (then beyond the gate)
MIN_RING_POINTS = 8
#: Largest ``form.ConeFit.error_amplification`` of a cone that is evaluated: above it a 1 um error of the points (a
#: probe's noise, a form error) could move the fitted cone by more than 1 mm at the part's size (axis position and
#: radius, tilt and half angle as displacements over the cloud's size): more than the 0.5 mm gate that says which
#: points are on the cone, so the fit determines nothing a tolerance could judge. A cone probed over its height and
#: turn gives about 10, a 2 mm band of its height about 70, a 60 deg arc about 90; one ring (every cone through that
#: circle fits it: the fit's Jacobian is rank-deficient) 10^4 and more, with noise of 10 um still 3,500.
MAX_CONE_AMPLIFICATION = 1000.0
MIN_CONTOUR_POINTS = 3  # points on each wall and arc of a slot for its mean contour error
#: Largest angular gap (deg) of a section's points about the cone's axis for its roundness to be evaluated: a
#: roundness is the form of the whole profile (ISO 12181-1); from an arc it is underestimated (an oval probed over
#: half its circumference shows a third of its roundness), so a section with a larger gap is "not measured".
MAX_SECTION_GAP_DEG = 30.0
ROUNDNESS_NOTE = ("Roundness of the unfiltered profiles (no ISO 12181-2 profile filter applied: probe noise and every "
                  "undulation count, so the values grow with the noise and the point density); sections are slabs "
                  "about their height, the points moved along the fitted cone's generator to it; a section whose "
                  f"points leave a gap above {MAX_SECTION_GAP_DEG:g} deg about the axis is not evaluated.")


def largest_gap_deg(angles) -> float:
    """The largest angle (deg) between neighbouring directions of ``angles`` (rad) around the full turn."""
    a = np.sort(np.mod(np.asarray(angles, dtype=np.float64), 2 * np.pi))
    if len(a) == 0:
        return 360.0
    return float(np.degrees(np.diff(np.r_[a, a[0] + 2 * np.pi]).max()))


@dataclass
class Inspection:
    """The outcome of ``inspect_cloud``.

    cloud : the Cloud as read (points in the file's frame). aligned : (n, 3) mm, the points in the part frame.
    normals : (n, 3) or None, the cloud's normals turned with the alignment. deviation : dv.Deviation.
    part : the part JSON dict. report : the report dict (JSON-ready). figures : data for the pictures.
    flyers : the ``trueaxis.inspect.flyers.FlyerScreen`` of the aligned cloud (the one ``--identify`` fits without).
    """

    cloud: Cloud
    aligned: np.ndarray
    normals: np.ndarray | None
    deviation: dv.Deviation
    part: dict
    report: dict
    figures: dict = field(default_factory=dict)
    flyers: object = None

    @property
    def deviation_um(self) -> np.ndarray:
        """(n,) signed deviation of each point, um (+ = material outside the nominal surface)."""
        return self.deviation.deviation_um

    def aligned_cloud(self) -> Cloud:
        """The cloud in the part frame (what the deviations refer to)."""
        return dataclasses.replace(self.cloud, points=self.aligned, normals=self.normals)


def load_part(part: str, part_dir=None, cad=None) -> dict:
    """The part JSON: ``part_dir/<part>.json``; with ``cad``, the JSON beside it (``<stem>.json``) if present; else
    the part's default description. Read by the one part loader (``trueaxis.workpiece.part.load_part``); raises
    InspectionError for an unknown part, a missing or unreadable file or a JSON for another part."""
    try:
        get_part(part)
    except ValueError as exc:
        raise dv.InspectionError(str(exc)) from None
    path = None
    if part_dir is not None:
        path = Path(part_dir) / f"{part}.json"
        if not path.is_file():
            raise dv.InspectionError(f"{path}: no such part JSON (write it with 'trueaxis part {part} -o {part_dir}')")
    elif cad is not None and Path(cad).with_suffix(".json").is_file():
        path = Path(cad).with_suffix(".json")
    try:
        return read_part(part, part_json=path)
    except (OSError, ValueError) as exc:
        raise dv.InspectionError(f"{path}: {exc}") from None


def deviation_stats(deviation_um) -> dict:
    """{"rms", "min", "max", "mean", "std", "p95", "points"} of signed deviations (n,) um; p95 is the 95th
    percentile of |deviation|. Empty input gives None values."""
    d = np.asarray(deviation_um, dtype=np.float64)
    if d.size == 0:
        return {"rms": None, "min": None, "max": None, "mean": None, "std": None, "p95": None, "points": 0}
    return {"rms": float(np.sqrt(np.mean(d ** 2))), "min": float(d.min()), "max": float(d.max()),
            "mean": float(d.mean()), "std": float(d.std()), "p95": float(np.percentile(np.abs(d), 95)),
            "points": int(d.size)}


# ------------------------------------------------------------------------------------------------------ the cone

def evaluate_nas979(points, dev: dv.Deviation, part: dict, gate_mm: float = 0.5, slab_mm: float = 0.5) -> tuple:
    """Cone, roundness and diameter of a NAS 979 cloud in the part frame (see the module docstring).

    points : (n, 3) mm, part frame. dev : their deviations. part : the part JSON.
    Returns (report entries dict, figure data dict).
    """
    from . import form  # here: the figure worker imports this module to draw, and needs no scipy

    cone = next(s for s in part["surfaces"] if s["type"] == "cone")
    ids = dev.surface_ids
    on_cone = (dev.surface == ids.index(cone["id"])) & (np.abs(dev.deviation_mm) <= gate_mm) \
        if cone["id"] in ids else np.zeros(len(points), bool)
    pts = points[on_cone]
    a_nom = dv._unit(cone["axis"])
    c_nom = np.asarray(cone["base_center"], float)
    alpha_nom = math.radians(float(cone["half_angle_deg"]))
    out: dict = {"cone_points": int(on_cone.sum())}
    figures: dict = {"rings": []}
    if len(pts) < 12:
        out["cone"] = None
        out["roundness_um"] = []
        out["cone_note"] = f"only {len(pts)} points on the cone (within {gate_mm} mm of it): no cone evaluation"
        out["notes"] = [out["cone_note"]]
        return out, figures
    fit = form.fit_cone(pts, initial_axis=a_nom, reference_plane=(c_nom, a_nom))
    if not fit.error_amplification <= MAX_CONE_AMPLIFICATION:
        span = float(np.ptp((pts - c_nom) @ a_nom))
        height = float(np.ptp(cone.get("height_range", [0.0, 0.0])))
        reason = (f"the cone's {len(pts)} points do not determine it (they span {span:.3f} mm of its {height:g} mm "
                  f"height along the axis): an error of 1 um in them could move the fitted axis, size or half angle "
                  f"by {_amplification_words(fit.error_amplification)} at the part's size (evaluated up to "
                  f"{MAX_CONE_AMPLIFICATION / 1e3:g} mm); its half angle, axis tilt and position, form and diameter, "
                  "and the sections taken along its axis, are not measured: probe it over its height")
        out.update(cone=None, cone_note=reason, notes=[reason], warnings=[reason],
                   cone_error_amplification=fit.error_amplification,
                   roundness_um=[{"id": f.get("id"), "height_mm": float(f["height"]), "points": 0,
                                  "least_squares": None, "minimum_zone": None, "diameter_ls_mm": None,
                                  "note": "not evaluated: the cone (whose axis the section is taken along) is not "
                                          "determined"}
                                 for f in part["features"] if f.get("type") == "roundness"])
        return out, figures
    # form.fit_cone's axis points from the apex into the cone (down for this cone): report it base to top
    up = -fit.axis if fit.axis @ a_nom < 0 else fit.axis
    tilt = math.acos(min(1.0, abs(float(fit.axis @ a_nom))))
    base_point = fit.axis_point
    r_base = fit.radius_at_axis_point
    tan_fit = math.tan(fit.half_angle_rad)
    out["cone"] = {
        "half_angle_deg": math.degrees(fit.half_angle_rad),
        "nominal_half_angle_deg": float(cone["half_angle_deg"]),
        "half_angle_error_urad": (fit.half_angle_rad - alpha_nom) * 1e6,
        "half_angle_std_urad": fit.half_angle_std_rad * 1e6,
        "axis": [float(v) for v in up],
        "nominal_axis": [float(v) for v in a_nom],
        "axis_tilt_urad": tilt * 1e6,
        "axis_point_mm": [float(v) for v in base_point],
        "axis_offset_um": [float(v) for v in (base_point - c_nom) * 1e3],
        "axis_point_note": "where the fitted axis crosses the nominal base plane; offset from the nominal base centre",
        "apex_mm": [float(v) for v in fit.apex],
        "base_radius_mm": r_base,
        "fit_rms_um": fit.rms * 1e3,
        "form_um": float(np.ptp(fit.residuals) * 1e3),
        "points": int(len(pts)),
        "error_amplification": fit.error_amplification,
    }
    e1, e2 = form._perpendicular_basis(up)
    around = (pts - base_point) @ np.column_stack([e1, e2])
    cone_gap = largest_gap_deg(np.arctan2(around[:, 1], around[:, 0]))
    out["cone"]["largest_gap_deg"] = cone_gap
    if cone_gap > MAX_SECTION_GAP_DEG:
        out.setdefault("warnings", []).append(
            f"the cone's points leave a gap of {cone_gap:.0f} deg about its axis: its axis, size and half angle "
            "come from a partial surface, where form errors move them (a diameter or axis offset may be off by "
            "the form error itself)")
    rings = []
    heights = (pts - base_point) @ up  # once for all sections; section_ring takes the exact slab from a superset
    for feature in (f for f in part["features"] if f.get("type") == "roundness"):
        h = float(feature["height"])
        near = np.flatnonzero(np.abs(heights - h) <= slab_mm * (1 + 1e-9) + 1e-9)
        planar, index = form.section_ring(pts[near], base_point, up, h, slab_mm, half_angle_rad=-fit.half_angle_rad,
                                          return_index=True)
        index = near[index]
        entry = {"id": feature.get("id"), "height_mm": h, "points": int(len(index)), "slab_half_width_mm": slab_mm}
        gap = largest_gap_deg(np.arctan2(planar[:, 1], planar[:, 0])) if len(index) else 360.0
        if len(index) < MIN_RING_POINTS:
            entry.update(least_squares=None, minimum_zone=None, diameter_ls_mm=None,
                         note=f"fewer than {MIN_RING_POINTS} cone points within {slab_mm} mm of this height")
        elif gap > MAX_SECTION_GAP_DEG:
            entry.update(least_squares=None, minimum_zone=None, diameter_ls_mm=None, largest_gap_deg=gap,
                         note=f"the section's points leave a gap of {gap:.0f} deg about the axis (more than "
                              f"{MAX_SECTION_GAP_DEG:g} deg): a roundness needs the whole profile, and one from an "
                              "arc is too small; not evaluated")
        else:
            ls = form.fit_circle_least_squares(planar)
            mz = form.minimum_zone_circle(planar, start=ls.center)  # the LS centre: a start within a zone width
            entry.update(least_squares=float(np.ptp(ls.residuals) * 1e3), minimum_zone=mz.width * 1e3,
                         largest_gap_deg=gap,
                         diameter_ls_mm=2 * ls.radius,
                         nominal_diameter_mm=feature.get("nominal_diameter"))
            figures["rings"].append({"height_mm": h, "angle": np.arctan2(*(planar - ls.center).T[::-1]),
                                     "residual_um": ls.residuals * 1e3, "minimum_zone_um": mz.width * 1e3})
        rings.append(entry)
    out["roundness_um"] = rings
    out["roundness_note"] = ROUNDNESS_NOTE
    diameter = next((f for f in part["features"] if f.get("type") == "diameter"), None)
    if diameter is not None:
        h = float(diameter["height"])
        # the radius shrinks along `up` for this cone: r(h) = r_base - h tan(alpha)
        measured = 2 * (r_base - h * tan_fit)
        out["diameter"] = {"height_mm": h, "nominal_mm": float(diameter["nominal_diameter"]), "measured_mm": measured,
                           "error_um": (measured - float(diameter["nominal_diameter"])) * 1e3,
                           "method": "from the least-squares cone at this height along its axis"}
    return out, figures


def _amplification_words(amplification: float) -> str:
    """``form.ConeFit.error_amplification`` as the move (in mm) a 1 um error of the points could make."""
    return "any amount" if not math.isfinite(amplification) else f"{amplification / 1e3:.3g} mm"


# ------------------------------------------------------------------------------------------------------ the slots

def _trace_line(xy):
    """Least-squares 2D line of a wall's XY trace, or None with fewer than 2 distinct points."""
    from . import form

    if len(xy) < 2 or np.ptp(xy, axis=0).max() == 0:
        return None
    return form.fit_line(xy)


def evaluate_slots(points, dev: dv.Deviation, part: dict, gate_mm: float = 0.5) -> tuple:
    """Per-slot width, straightness, parallelism, position, depth and deviation statistics (module docstring).

    points : (n, 3) mm, part frame. dev : their deviations. part : the slot block's JSON.
    Returns (report entries dict, figure data dict).
    """
    from . import form

    by_id = {s["id"]: s for s in part["surfaces"]}
    index = {sid: k for k, sid in enumerate(dev.surface_ids)}
    near = np.abs(dev.deviation_mm) <= gate_mm
    d_um = dev.deviation_um

    def members(sid):
        k = index.get(sid)
        return np.zeros(len(points), bool) if k is None else (dev.surface == k) & near

    slots = []
    for feature in (f for f in part["features"] if f.get("type") == "slot"):
        path = np.asarray(feature["tool_centre_path"], float)[:, :2]
        nominal_width = float(feature["nominal_width"])
        walls = feature["walls"]
        all_ids = walls + feature["arcs"] + [feature["floor"]]
        in_slot = np.zeros(len(points), bool)
        for sid in all_ids:
            in_slot |= members(sid)
        contour = np.zeros(len(points), bool)
        for sid in walls + feature["arcs"]:
            contour |= members(sid)
        segments, straightness, parallel = [], {}, []
        for k in range(len(path) - 1):
            a, b = path[k], path[k + 1]
            t = (b - a) / np.linalg.norm(b - a)
            n_left = np.array([-t[1], t[0]])
            mid = (a + b) / 2
            left_id, right_id = f"{feature['id']}_seg{k}_left", f"{feature['id']}_seg{k}_right"
            left_xy = points[members(left_id)][:, :2]
            right_xy = points[members(right_id)][:, :2]
            for sid, xy in ((left_id, left_xy), (right_id, right_xy)):
                straightness[sid] = (form.straightness(xy, method="minimum_zone") * 1e3 if len(xy) >= 3 else None)
            left, right = _trace_line(left_xy), _trace_line(right_xy)
            entry = {"segment": k, "points_left": int(len(left_xy)), "points_right": int(len(right_xy))}
            if left is None or right is None:
                entry.update(width_mm=None, width_error_um=None, position_um=None,
                             note=f"a wall of this segment has fewer than 2 distinct points within {gate_mm:g} mm of "
                                  f"it (left {len(left_xy)}, right {len(right_xy)} points)")
            else:
                def offset_at_mid(line):
                    # where the line crosses the nominal normal through the segment's midpoint, along n_left
                    d = line.direction
                    denom = d @ t
                    s = ((mid - line.point) @ t) / denom if abs(denom) > 1e-12 else 0.0
                    return float((line.point + s * d - mid) @ n_left)

                v_left, v_right = offset_at_mid(left), offset_at_mid(right)
                width = v_left - v_right
                entry.update(width_mm=width, width_error_um=(width - nominal_width) * 1e3,
                             position_um=(v_left + v_right) / 2 * 1e3)
                # parallelism of the left wall to the right wall (datum): spread of the left trace about a line
                # parallel to the datum's least-squares line
                normal = np.array([-right.direction[1], right.direction[0]])
                spread = (left_xy - right.point) @ normal
                entry["parallelism_um"] = float(np.ptp(spread) * 1e3)
                parallel.append({"segment": k, "parallelism_um": entry["parallelism_um"], "datum": right_id})
            segments.append(entry)
        widths = [s["width_mm"] for s in segments if s["width_mm"] is not None]
        positions = [s["position_um"] for s in segments if s["position_um"] is not None]
        floor = members(feature["floor"])
        depth = None
        if floor.any():
            z_nom = float(by_id[feature["floor"]]["point"][2])
            depth = {"nominal_mm": -z_nom, "measured_mm": float(-points[floor, 2].mean()),
                     "error_um": float((-points[floor, 2].mean() + z_nom) * 1e3), "points": int(floor.sum())}
        # the contour error is a mean over the whole contour: only when every wall and arc has points on it (two
        # stray points on one end cap are not the slot's contour)
        sparse = [sid for sid in walls + feature["arcs"] if members(sid).sum() < MIN_CONTOUR_POINTS]
        slots.append({
            "id": feature["id"], "compensation": feature.get("compensation"), "points": int(in_slot.sum()),
            "deviation_um": deviation_stats(d_um[in_slot]),
            "mean_contour_error_um": float(np.mean(np.abs(d_um[contour]))) if contour.any() and not sparse else None,
            "contour_note": None if not sparse else (
                f"not evaluated: {len(sparse)} of the contour's {len(walls + feature['arcs'])} walls and arcs have "
                f"fewer than {MIN_CONTOUR_POINTS} points within {gate_mm:g} mm ({', '.join(sparse[:3])}"
                f"{', ...' if len(sparse) > 3 else ''})"),
            "width": {"nominal_mm": nominal_width, "segments": segments,
                      "mean_mm": float(np.mean(widths)) if widths else None,
                      "mean_error_um": float((np.mean(widths) - nominal_width) * 1e3) if widths else None},
            "straightness_um": straightness,
            "parallelism_um": parallel,
            "position_um": {"segments": [{"segment": s["segment"], "offset_um": s["position_um"]} for s in segments],
                            # the largest offset is known only when every segment's is
                            "max_abs": float(np.max(np.abs(positions))) if positions and len(positions) == len(
                                segments) else None,
                            "note": "midline between the walls minus the nominal tool-centre path, along the "
                                    "segment's left normal, at its midpoint"},
            "depth": depth,
        })
    return {"slots": slots}, {}


# The feature evaluations by ``Part.evaluation``: (points, deviations, part JSON, gate_mm) -> (report entries, figure
# data). A part whose features are of a kind already here names it; a new kind of feature adds its evaluation here.
EVALUATIONS = {"cone": evaluate_nas979, "slots": evaluate_slots}


# -------------------------------------------------------------------------------------------------- the pipeline

def inspect_cloud(cloud, part: str, part_dir=None, cad=None, align: str = "none", gate_mm: float = 0.5,
                  tolerances=None, program=None, machine=None, figure_worker=None, progress=None,
                  flyer_screen: bool | None = None) -> Inspection:
    """Read (or take) a cloud, check it can be the part, align it, measure its deviations, evaluate the features.

    cloud : path of a cloud file (``read_cloud``), or a Cloud. part : "nas979" | "slots". part_dir : folder with
    <part>.json (and slots.stl). cad : a STEP or mesh file of the part, with its JSON beside it (``<stem>.json``): the
    mesh is the reference where the JSON has no analytic surface; without the JSON the features cannot be evaluated
    and the inspection is refused, naming the JSON it needs. align : "none" | "bestfit" | "datum".
    tolerances : a tolerance TOML file (``trueaxis.inspect.tolerances``; merged over the part JSON's own), or None for
    the JSON's alone.
    program, machine : the NC program that cut the part and the machine file, named in the report's header (when
    known).
    figure_worker : a ``trueaxis.inspect.workers.FigureWorker``, or None: the deviation map and the histogram are sent
    to it as soon as the deviations are known (drawn while the features are evaluated); pass the same worker to
    :func:`write_report`.
    progress : a callable taking one line of text, told when a slow step starts (tessellating the CAD), or None.
    flyer_screen : run the flyer screen on the features' points (``flyers_in_features``): True, False, or None for
    clouds of at most ``FLYER_SCREEN_MAX_POINTS`` points (its neighbour search takes about 4 s a million points).

    Raises CloudError / InspectionError (ValueError) with a one-line message; nothing is written here.
    """
    if align not in ALIGNMENTS:
        raise dv.InspectionError(f"unknown alignment {align!r}: expected one of {', '.join(ALIGNMENTS)}")
    if cad is not None and not Path(cad).with_suffix(".json").is_file():
        # the features (cone, roundness sections, slot widths, walls, floors) are the JSON's analytic surfaces and
        # feature list: a STEP file alone has faces but not which slot, wall or section each one is, so every
        # feature would come out empty; refuse before the slow tessellation rather than report nulls
        json_name = Path(cad).with_suffix(".json").name
        raise dv.InspectionError(
            f"{cad}: no part JSON beside it ({json_name}): the {part} part's features are evaluated on the analytic "
            f"surfaces and feature list of that JSON, which a STEP file does not carry; write the STEP and the JSON "
            f"together with 'trueaxis part {part} -o DIR' (then --cad DIR/{part}.step or --part-dir DIR)")
    if not isinstance(cloud, Cloud):
        cloud = read_cloud(cloud)
    part_doc = load_part(part, part_dir, cad)
    limits = load_tolerances(tolerances, part_doc)  # a bad tolerance file is refused before any work
    has_json = cad is None or Path(cad).with_suffix(".json").is_file()
    surfaces = dv.analytic_surfaces(part_doc) if has_json else []

    cad_mesh: dv.CadMesh | None = None
    distance: dv.MeshDistance | None = None

    def mesh():
        nonlocal cad_mesh, distance
        if distance is None:
            if progress is not None and cad is not None and Path(cad).suffix.lower() in (".step", ".stp"):
                progress(f"{cad}: tessellating the STEP (OCCT, chord below 0.1 um: tens of seconds) for the points "
                         "no analytic surface of the JSON covers")
            cad_mesh = dv.load_mesh_file(cad, part_doc) if cad is not None else dv.part_mesh(part_doc, part_dir)
            distance = dv.MeshDistance(cad_mesh)
        return distance

    if not surfaces:
        mesh()
    # with the part JSON the CAD mesh is built only when a point needs it (farther than gate_mm from every analytic
    # surface, or a best-fit alignment): tessellating a STEP and loading open3d take tens of seconds, and a point
    # near an analytic surface gets its exact deviation from it either way
    bbox = (cad_mesh.vertices.min(axis=0), cad_mesh.vertices.max(axis=0)) if cad_mesh is not None \
        else dv.part_bbox(part_doc)
    try:
        check_extent(cloud.points, *bbox, EXTENT_TOLERANCE_MM, part=part, outliers=EXTENT_OUTLIERS)
    except CloudError as exc:
        raise CloudError(f"{cloud.source}: {exc}") from None

    if align == "none":
        motion = dv.RigidMotion()
    elif align == "bestfit":
        mesh()
        motion = dv.align_bestfit(cloud.points, surfaces, distance, cad_mesh)
    else:
        if not surfaces:
            raise dv.InspectionError("datum alignment needs the part JSON's datum surfaces (none with --cad alone)")
        motion = dv.align_datum(cloud.points, part_doc, surfaces)
    aligned = motion.apply(cloud.points)
    normals = motion.rotate(cloud.normals) if cloud.normals is not None else None
    dev = dv.deviation(aligned, surfaces, distance if distance is not None else mesh, gate_mm=gate_mm)

    beyond = np.abs(dev.deviation_mm) > gate_mm  # on no feature: counted apart from the headline figures
    refuse_beyond_gate(cloud.source, part, align, dev.deviation_mm, beyond, gate_mm)
    if figure_worker is not None:
        for item in _deviation_figure_inputs(part, part_doc, aligned, dev.deviation_um, beyond):
            figure_worker.submit(item)

    features, figures = EVALUATIONS[get_part(part).evaluation](aligned, dev, part_doc, gate_mm)
    if align == "bestfit":
        features.setdefault("warnings", []).extend(_bestfit_warnings(motion, dev, surfaces, beyond))
    d_um = dev.deviation_um
    # the headline figures are over the points on the part's surfaces (within the gate): a flyer 500 mm off would
    # make them its own (0.5 % of the points gave an RMS of 33,909 um); those beyond the gate are counted apart
    within = ~beyond if beyond.any() and not beyond.all() else np.ones(len(beyond), bool)
    per_surface = {}
    for k, sid in enumerate(dev.surface_ids):
        sel = (dev.surface == k) & within
        if sel.any():
            per_surface[sid] = deviation_stats(d_um[sel])
    if (dev.from_mesh & within).any():
        per_surface["cad_mesh"] = deviation_stats(d_um[dev.from_mesh & within])
    from .. import __version__

    if part_dir is not None:
        description = str(Path(part_dir) / f"{part}.json")
    elif cad is not None:
        description = f"{Path(cad).with_suffix('.json')} (with {cad})"
    else:
        description = "the default parameters of 'trueaxis part'"
    header = {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
        "part": get_part(part).title, "part_description": description, "cloud": str(cloud.source),
        "points": int(len(aligned)), "program": None if program is None else str(program),
        "machine_file": None if machine is None else str(machine), "alignment": _alignment_words(motion),
        "tolerances": str(tolerances) if tolerances is not None else (
            "from the part JSON" if limits else "none given"),
        "trueaxis_version": __version__,
    }
    report = {
        "trueaxis_report": "inspect", "version": 1, "header": header,
        "part": part, "cloud": str(cloud.source), "points": int(len(aligned)),
        "units": "lengths in the keys' units (mm, um), angles in deg or urad; deviations + = material outside the "
                 "nominal surface",
        "alignment": motion.as_dict(),
        "deviation_um": deviation_stats(d_um[within]),
        "deviation_note": "over the points within the gate of a nominal surface (those beyond it are in "
                          "beyond_gate)" if not within.all() else "over all points" + (
                              " (none within the gate)" if beyond.any() else " (every one within the gate)"),
        "deviation_by_surface_um": per_surface,
        "beyond_gate": {
            "gate_mm": gate_mm, "points": int(beyond.sum()), "share": float(beyond.mean()) if len(beyond) else 0.0,
            "deviation_um": deviation_stats(d_um[beyond]),
            "note": f"points farther than {gate_mm:g} mm from every nominal surface belong to no feature: no feature "
                    "is evaluated from them (a gross error of the part, or points that are not on it)"},
        "reference": {
            "analytic_points": int((~dev.from_mesh).sum()), "cad_mesh_points": int(dev.from_mesh.sum()),
            "analytic_surfaces": len(surfaces),
            "cad_mesh": {
                "source": str(cad), "triangles": None, "chord_error_bound_um": None,
                "note": f"not tessellated: every point lies within {gate_mm:g} mm of an analytic surface of the part "
                        "JSON, which gives its exact deviation"} if cad is not None and cad_mesh is None else (
                None if cad_mesh is None else {
                    "source": cad_mesh.source, "triangles": int(len(cad_mesh.triangles)),
                    "chord_error_bound_um": None if cad_mesh.chord_error_mm is None else cad_mesh.chord_error_mm * 1e3,
                    "note": cad_mesh.note}),
        },
        **features,
    }
    duplicates = cloud.repeats_dropped  # dropped by the reader (read_cloud), said here
    if duplicates:
        report.setdefault("warnings", []).append(
            f"{duplicates} of {duplicates + len(aligned)} points repeat another point exactly (the same x, y, z): "
            f"dropped, the figures and any identification use the {len(aligned)} distinct points; a cloud "
            "concatenated with itself, or a measurement exported twice?")
    report["duplicate_points"] = duplicates
    absorbed = None
    if align == "bestfit":
        # (datum needs the block's faces probed, which a `simulate` cloud has not: a QA pass tried it)
        absorbed = {key: f"not measured with --align bestfit: {why} (use --align datum with the block's faces probed, "
                         "or none for a part probed in its frame)" for key, why in get_part(part).bestfit_absorbs}
        report.setdefault("warnings", []).append(
            "the best fit onto the CAD takes away what a rigid move changes: "
            + ", ".join(CHARACTERISTICS[key][2] for key in absorbed)
            + " not measured (use --align datum with the block's faces probed, or none for a part probed in its frame)")
    report["feature_table"] = feature_table(report, part_doc, limits, not_measured=absorbed)
    if absorbed:
        mark_not_measured(report, absorbed)
    screen = None
    if flyer_screen or (flyer_screen is None and len(aligned) <= FLYER_SCREEN_MAX_POINTS):
        # the rule --identify and diagnose fit without; along the part's normals, as the deviations (a cloud's own
        # normals may scatter, or be colours read as normals: nominal_normals)
        screen = screen_flyers(aligned, dev.normal, d_um, gate_mm, surface=dev.surface)
        flyers_in_features(report, screen, EVALUATIONS[get_part(part).evaluation], aligned, dev, part_doc, gate_mm,
                           limits, absorbed)
    else:
        report["flyers_within_gate"] = {
            "points": None, "note": f"not screened: {len(aligned)} points, more than {FLYER_SCREEN_MAX_POINTS} (the "
                                    "screen's neighbour search takes about 4 s a million points); inspect --identify "
                                    "screens every cloud"}
    report["feature_summary"] = summary(report["feature_table"])
    figures.update(points=aligned, deviation_um=d_um, beyond_gate=beyond)
    if figure_worker is not None:
        figures["sent"] = figure_worker
    return Inspection(cloud, aligned, normals, dev, part_doc, report, figures, flyers=screen)


#: The largest cloud a plain inspection screens for flyers by default (0.4 s at 100,000 points; docs/inspection.md).
FLYER_SCREEN_MAX_POINTS = 100_000
#: Change of a characteristic's value (um or urad) without the flyers from which the warning names it.
FLYER_CHANGE_SHOWN = 0.05


def flyers_in_features(report: dict, screen, evaluate, points: np.ndarray, dev: dv.Deviation, part_doc: dict,
                       gate_mm: float, limits: dict, absorbed: dict | None) -> None:
    """Say the flyers the features are evaluated with: the points within the gate that the flyer screen
    (``trueaxis.inspect.flyers``, ``screen``) sets apart. The feature values keep them (the measured data, the basis
    of a conformance decision: a screen cannot tell a probe's mis-trigger from a burr or a dent, which is form);
    the features are evaluated again without them, and each feature-table row gets ``without_flyers`` (actual,
    deviation, result), ``report["flyers_within_gate"]`` the count, the largest and where they are, and a warning
    names the values that change (three 0.3 mm flyers of 3996 points had made a roundness of 19.2 um 311.4 um
    without a word). Nothing changes for a cloud without such points (``flyers_within_gate.points`` = 0).

    evaluate : the part's feature evaluation (``EVALUATIONS``). points : (n, 3) mm, part frame; dev : their
    deviations. limits, absorbed : as for ``feature_table``."""
    local = screen.local
    entry = {"points": int(local.sum()), "local_sigma_um": screen.local_sigma_um, "rule": rule_text(gate_mm),
             "values": "the feature values keep them (as measured); without_flyers in each feature-table row"}
    report["flyers_within_gate"] = entry
    if not local.any():
        return
    d_um = dev.deviation_um
    worst = np.flatnonzero(local)[np.argsort(-np.abs(d_um[local]), kind="stable")]
    entry["largest_um"] = float(d_um[worst[0]])
    entry["where"] = [{"x_mm": float(points[k, 0]), "y_mm": float(points[k, 1]), "z_mm": float(points[k, 2]),
                       "deviation_um": float(d_um[k])} for k in worst[:20]]
    keep = ~local
    without = dv.Deviation(dev.deviation_mm[keep], dev.normal[keep], dev.surface[keep], dev.surface_ids,
                           dev.from_mesh[keep], dev.chord_error_mm)
    features, _ = evaluate(points[keep], without, part_doc, gate_mm)
    changed = []
    for row, other in zip(report["feature_table"], feature_table(features, part_doc, limits, not_measured=absorbed)):
        row["without_flyers"] = {k: other[k] for k in ("actual", "deviation", "result")}
        a, b = row["deviation"], other["deviation"]
        if (a is None) != (b is None) or row["result"] != other["result"] or (
                a is not None and abs(a - b) >= FLYER_CHANGE_SHOWN):
            changed.append((0.0 if a is None or b is None else -abs(a - b), row, other))
    changed.sort(key=lambda c: c[0])
    words = [f"{re.sub(r' [(].*?[)]', '', row['characteristic'])} ({row['feature']}) {_flyer_value(row)} -> "
             f"{_flyer_value(other)}{'' if other['deviation'] is None else ' ' + row['deviation_unit']}"
             for _, row, other in changed]
    shown = "; ".join(words[:4]) + (f"; and {len(words) - 4} more" if len(words) > 4 else "")
    report.setdefault("warnings", []).append(
        f"{entry['points']} of {len(local)} points within the {gate_mm:g} mm gate depart from nearly every neighbour "
        f"(flyers by the screen --identify and diagnose apply; largest {entry['largest_um']:+.1f} um): the feature "
        "values keep them, as measured; without them: " + (shown or "no value changes by 0.05 or more")
        + "; re-probe there, or look for a burr or a dent (where: flyers_within_gate in report.json)")


def _flyer_value(row: dict) -> str:
    """A feature-table row's value in the flyer warning: its deviation (um or urad; the unit is the caller's), and
    the result where it was judged against a tolerance."""
    if row["deviation"] is None:
        return "not measured"
    judged = f" ({row['result']})" if row["result"] in ("pass", "fail", "uncertain") else ""
    sign = "+" if row["key"] in SIZE_KEYS else ""
    return f"{row['deviation']:{sign}.1f}{judged}"


def refuse_beyond_gate(source, part: str, align: str, deviation_mm: np.ndarray, beyond: np.ndarray,
                       gate_mm: float) -> None:
    """Refuse (InspectionError) a cloud with more than ``flyers.MAX_BEYOND_GATE`` of its points beyond the gate, the
    rule ``diagnose`` applies: not flyers but a cloud in another frame, unit or of another part, whose figures from
    the few points that happen to lie near a surface would be taken as measured (a cone turned 180 deg about Z,
    64.9 % beyond the gate, gave a half angle error of +3498 urad and a form of 1177 um, exit 0).

    source : the cloud's name, for the message. deviation_mm : (n,) mm, each point's deviation in the part frame.
    beyond : (n,) bool, the points beyond the gate. gate_mm : the gate (mm)."""
    if not beyond.mean() > MAX_BEYOND_GATE:
        return
    hint = {"none": "--align bestfit (a cloud within about a mm of the part frame: a refinement, not a search) or "
                    "--align datum (the block's faces probed)",
            "bestfit": "--align datum (the block's faces probed); the best fit did not bring it onto the part",
            "datum": "--align bestfit (a cloud in another frame); the datum alignment did not bring it onto the part"}
    raise dv.InspectionError(
        f"{source}: {int(beyond.sum())} of {len(beyond)} points ({beyond.mean() * 100:.1f} %) lie more than "
        f"{gate_mm:g} mm from every surface of the {part} part (median {np.median(np.abs(deviation_mm)):.3f} mm), "
        f"more than the {MAX_BEYOND_GATE * 100:g} % a measurement's flyers may take: this cloud cannot be the {part} "
        f"part in its frame, in mm, with --align {align}; try {hint[align]}")


def _bestfit_warnings(motion: dv.RigidMotion, dev: dv.Deviation, surfaces: list, beyond: np.ndarray) -> list[str]:
    """A best fit on cones alone: a move along a cone's axis changes its size at every height, so the fit takes a
    size error away (and the diameter with it). Said, with the move along the axis, when no other surface has
    points."""
    kinds = {k: s["type"] for k, s in enumerate(surfaces)}
    probed = {kinds.get(int(k)) for k in np.unique(dev.surface[~beyond & ~dev.from_mesh])}
    if probed != {"cone"}:
        return []
    cone = next(s for s in surfaces if s["type"] == "cone")
    along = float(motion.translation @ dv._unit(cone["axis"])) * 1e3
    return [f"the best fit saw only the cone: it moved the part {along:+.1f} um along the cone's axis, which takes a "
            f"size error away with it (the diameter, the axis position and tilt are not measured this way); use "
            f"--align datum (with the block's faces probed) or none"]


def identification_input(inspection: Inspection) -> tuple[Cloud, np.ndarray, dict]:
    """What ``--identify`` fits: (the aligned cloud, its deviations (um), the report's entries on the flyers) without
    the flyers (``trueaxis.inspect.flyers``: beyond the inspection's gate, or departing from their neighbours; the
    rule the diagnosis applies). Ten 3 mm flyers in 3000 points turned an XOC change of +20 um into "NO CHANGE",
    the noise read as 164 um (a QA pass)."""
    cloud = inspection.aligned_cloud()
    gate_mm = (inspection.report.get("beyond_gate") or {}).get("gate_mm", 0.5)
    screen = inspection.flyers if inspection.flyers is not None else \
        screen_flyers(cloud.points, inspection.deviation.normal, inspection.deviation_um, gate_mm,
                      surface=inspection.deviation.surface)  # as inspect's
    entries = {"flyers_set_apart": screen.as_dict()}
    if not screen.n_apart:
        return cloud, inspection.deviation_um, entries
    entries["flyers_note"] = screen.sentence("the identification")
    keep = screen.keep
    kept = dataclasses.replace(cloud, points=cloud.points[keep],
                               normals=None if cloud.normals is None else cloud.normals[keep])
    return kept, inspection.deviation_um[keep], entries


def inspection_warnings(report: dict) -> list[str]:
    """What a reader of the terminal must not miss, one line each: characteristics that could not be measured, and
    points beyond the gate (in no feature). report : ``Inspection.report``."""
    out = list(report.get("warnings") or [])
    missing = [f"{row['feature']} {row['characteristic']}" for row in report.get("feature_table", [])
               if row["result"] == "not measured"]
    if missing:
        shown = "; ".join(missing[:4]) + (f"; and {len(missing) - 4} more" if len(missing) > 4 else "")
        out.append(f"{len(missing)} characteristic{'s' if len(missing) > 1 else ''} not measured ({shown}): "
                   f"see the notes in report.json")
    gate = report.get("beyond_gate") or {}
    if gate.get("points"):
        share = f"{gate['share'] * 100:.1f} %" if gate["share"] >= 1e-3 else "< 0.1 %"
        out.append(f"{gate['points']} of {report['points']} points ({share}) lie more than "
                   f"{gate['gate_mm']:g} mm from every nominal surface and belong to no feature: a gross error of the "
                   "part, or points not on it")
    identification = report.get("identification")
    if isinstance(identification, dict) and identification.get("flyers_note"):
        out.append(identification["flyers_note"])
    return out


def _alignment_words(motion: dv.RigidMotion) -> str:
    """The alignment in one line: method, and for a fit the motion it removed."""
    if motion.method == "none":
        return "none: the cloud was taken as measured in the part frame"
    t, w = motion.translation_um, motion.rotation_urad
    moved = (f"removed translation ({t[0]:+.2f}, {t[1]:+.2f}, {t[2]:+.2f}) um, rotation ({w[0]:+.1f}, {w[1]:+.1f}, "
             f"{w[2]:+.1f}) urad")
    words = {"bestfit": "best fit onto the CAD", "datum": "3-2-1 datum frame (A, B, C planes)"}
    return f"{words.get(motion.method, motion.method)}; {moved}"


# -------------------------------------------------------------------------------------------------- the writing

def _nice(value: float, up: bool = False) -> float:
    """A round number near value > 0 (1, 2 or 5 times a power of ten), or the next one at or above it (also 1.5, 3,
    4, 6, 8 times a power of ten), for scales."""
    exponent = math.floor(math.log10(value))
    mantissa = value / 10 ** exponent
    if up:
        return next(m for m in (1, 1.5, 2, 3, 4, 5, 6, 8, 10) if m >= mantissa * (1 - 1e-12)) * 10 ** exponent
    return (1 if mantissa < 1.5 else 2 if mantissa < 3.5 else 5 if mantissa < 7.5 else 10) * 10 ** exponent


def _profile_for_plot(angle, residual, limit: int = 2000, bins: int = 1440):
    """A roundness profile ready to draw: sorted by angle, all points when there are at most ``limit``; else, per
    bin of 360/bins deg, the highest and the lowest residual (so no peak is lost). Returns (angle (m,) rad,
    residual or highest (m,), lowest (m,) or None)."""
    order = np.argsort(angle)
    angle, residual = angle[order], residual[order]
    if len(angle) <= limit:
        return angle, residual, None
    index = np.minimum(((angle + np.pi) / (2 * np.pi) * bins).astype(np.int64), bins - 1)
    starts = np.flatnonzero(np.r_[True, index[1:] != index[:-1]])
    centre = (index[starts] + 0.5) * (2 * np.pi / bins) - np.pi
    return centre, np.maximum.reduceat(residual, starts), np.minimum.reduceat(residual, starts)


MAP_POINTS = 15_000  # points drawn in the deviation map (all of them are in deviations.ply and .csv)


def _deviation_figure_inputs(part: str, part_doc: dict, points: np.ndarray, d: np.ndarray,
                             beyond: np.ndarray | None = None) -> list[dict]:
    """The inputs of the deviation map and the histogram (``draw_figure``): they need the deviations only, so they
    can be drawn while the features are evaluated. points : (n, 3) mm, part frame; d : (n,) um. beyond : (n,) bool or
    None, the points beyond the gate (on no feature): left out of both pictures (a flyer 500 mm off would make the
    histogram one bar and the map a dot), and counted in the caption."""
    outliers = 0 if beyond is None else int(beyond.sum())
    if outliers and outliers < len(points):
        points, d = points[~beyond], d[~beyond]
    else:
        outliers = 0
    rng = np.random.default_rng(0)
    show = np.sort(rng.choice(len(points), size=MAP_POINTS, replace=False)) if len(points) > MAP_POINTS \
        else slice(None)
    limit = _nice(float(np.percentile(np.abs(d), 99)) or 1.0, up=True)
    slots = [(f["id"], np.asarray(f["tool_centre_path"], float)[:, :2], f.get("compensation", ""))
             for f in part_doc.get("features", []) if f.get("type") == "slot"]
    counts, edges = np.histogram(d, bins=80)
    return [{"kind": "deviation_map", "view": get_part(part).map_view, "points": points[show], "deviation_um": d[show],
             "limit": limit, "total": len(points), "extent": np.ptp(points, axis=0), "slots": slots,
             "outliers": outliers},
            {"kind": "histogram", "counts": counts, "edges": edges, "outliers": outliers}]


def _feature_figure_inputs(inspection: Inspection) -> list[dict]:
    """The inputs of the pictures of the evaluated features: roundness, identified parameters, component tables."""
    report = inspection.report
    out = []
    rings = inspection.figures.get("rings") or []
    if rings:
        out.append({"kind": "roundness", "rings": rings})
    identification = report.get("identification") if isinstance(report.get("identification"), dict) else {}
    parameters = identification.get("parameters")
    if parameters:
        names = [p["name"] for p in parameters]
        values = [next((v for k, v in p.items() if k.startswith("value_")), None) for p in parameters]
        stds = [next((v for k, v in p.items() if k.startswith("std_")), None) for p in parameters]
        units = [next((k[6:] for k in p if k.startswith("value_")), "") for p in parameters]
        out.append({"kind": "identified", "names": names, "values": values, "stds": stds, "units": units,
                    "status": (identification.get("verdict") or {}).get("status", "accepted")})
        components = _component_tables(names, values, stds, units)
        if components:
            out.append({"kind": "components", "components": components})
    return out


def warm_up_drawing() -> None:
    """Import matplotlib's object API, the Agg canvas and the 3D axes, and load the fonts: what the first picture
    would otherwise pay for (the figure worker does this while the parent computes)."""
    import io

    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d import Axes3D  # noqa: F401 - registers the "3d" projection

    fig = Figure(figsize=(1, 1))
    fig.text(0.5, 0.5, "0")
    fig.savefig(io.BytesIO(), format="png", dpi=10)


def draw_figure(inputs: dict) -> tuple[str, bytes, str, dict]:
    """One picture from its inputs (``_deviation_figure_inputs``, ``_feature_figure_inputs``): (file name, PNG
    bytes, caption, {key: the plotted data for report.json}). Pure function of its inputs: the same bytes in the
    figure worker and in-process."""
    import io

    # matplotlib's object API, not pyplot: no global figure state, and 0.2 s less to import
    from matplotlib.figure import Figure

    kind = inputs["kind"]
    data: dict = {}
    colour_label = "deviation (um), + = material outside"
    if kind == "deviation_map":
        pts, d, limit = inputs["points"], inputs["deviation_um"], inputs["limit"]
        if inputs["view"] == "3d":
            fig = Figure(figsize=(8.5, 6.0))
            ax = fig.add_axes([0.0, 0.02, 0.8, 0.92], projection="3d")
            sc = ax.scatter(*pts.T, c=d, cmap="coolwarm", vmin=-limit, vmax=limit, s=2)
            ax.set_xlabel("x (mm)", labelpad=8)
            ax.set_ylabel("y (mm)", labelpad=8)
            ax.set_zlabel("z (mm)", labelpad=4)
            ax.set_box_aspect(inputs["extent"] + 1e-9)  # the extent of all points, not of those shown
            # the colour bar stands clear of the 3D axes' z label: its own column, with a gap
            cax = fig.add_axes([0.86, 0.2, 0.025, 0.6])
            fig.colorbar(sc, cax=cax).set_label(colour_label)
        else:
            fig = Figure(figsize=(10, 4.8))
            ax = fig.subplots()
            fig.subplots_adjust(left=0.07, right=0.98, bottom=0.1, top=0.92)
            sc = ax.scatter(pts[:, 0], pts[:, 1], c=d, cmap="coolwarm", vmin=-limit, vmax=limit, s=2)
            ax.set_aspect("equal")
            ax.set_xlabel("x (mm)")
            ax.set_ylabel("y (mm)")
            for slot_id, path, compensation in inputs["slots"]:
                ax.plot(*path.T, color="0.3", lw=0.8, ls="--")
                ax.annotate(f"{slot_id}\ncompensation: {compensation}",
                            (path[0] + path[1]) / 2, xytext=(0, -24), textcoords="offset points", ha="center",
                            va="top", fontsize=9, annotation_clip=False,
                            bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.6", alpha=0.9))
            ax.set_ylim(bottom=ax.get_ylim()[0] - 16)  # room for the slots' labels below their first segments
            fig.colorbar(sc, ax=ax, shrink=0.7, pad=0.03).set_label(colour_label)
        ax.set_title("Deviation from the nominal part (part frame)")
        name = "deviation_map.png"
        shown, total = len(pts), inputs["total"]
        left_out = inputs.get("outliers", 0)
        caption = (f"Deviation colour map on the part ({shown:,} of {total:,} points shown"
                   + (f", the {left_out:,} beyond the gate (on no feature) left out" if left_out else "")
                   + f"; colour scale +-{limit:g} um, the round number at or above the 99th percentile of |deviation|; "
                   "all points with their deviations are in deviations.ply and deviations.csv).")
        data["deviation_map"] = {"file": name, "colour_limit_um": limit, "points_shown": int(shown),
                                 "data": "deviations.ply"}
    elif kind == "histogram":
        counts, edges = inputs["counts"], inputs["edges"]
        fig = Figure(figsize=(7.5, 4))
        ax = fig.subplots()
        ax.stairs(counts, edges, fill=True, color="steelblue")
        ax.set_xlabel("deviation (um), + = material outside")
        ax.set_ylabel("points")
        ax.set_title("Histogram of deviations")
        fig.subplots_adjust(left=0.11, right=0.97, bottom=0.14, top=0.9)
        left_out = inputs.get("outliers", 0)
        name, caption = "histogram.png", "Histogram of the signed deviations (80 bins)" + (
            f" of the points on the part's features; the {left_out:,} beyond the gate are left out (counted in the "
            "summary)." if left_out else ".")
        data["histogram"] = {"file": name, "bin_edges_um": edges, "counts": counts}
    elif kind == "roundness":
        rings = inputs["rings"]
        fig = Figure(figsize=(4.8 * len(rings), 5.4))
        axes = fig.subplots(1, len(rings), subplot_kw={"projection": "polar"})
        axes = np.atleast_1d(axes)
        data["roundness"] = []
        span = max(max(float(np.abs(ring["residual_um"]).max()) for ring in rings), 1e-6)
        step = _nice(span / 2)  # one radial scale for all sections, so they compare at a glance
        top = step * math.ceil(span / step)
        base = 2 * top  # the nominal circle: the profile is drawn at base + residual
        for ax, ring in zip(axes, rings):
            angle, r, low = _profile_for_plot(ring["angle"], ring["residual_um"])
            if low is None:
                ax.plot(np.r_[angle, angle[:1]], np.r_[r, r[:1]] + base, lw=1, color="C0")
            else:  # a dense profile: the band between each 0.25 deg bin's lowest and highest point
                ax.fill_between(np.r_[angle, angle[:1]], np.r_[low, low[:1]] + base, np.r_[r, r[:1]] + base,
                                color="C0", lw=0.6)
            ax.plot(np.linspace(0, 2 * np.pi, 361), np.full(361, base), "k--", lw=0.7)
            ax.set_ylim(0, base + top)
            ticks = np.arange(-top, top + step / 2, step)
            ax.set_yticks(base + ticks)
            ax.set_yticklabels([f"{t:+g} um" if t else "0" for t in ticks], fontsize=7)
            ax.set_rlabel_position(100)
            ax.tick_params(axis="x", labelsize=8)
            ax.set_title(f"h = {ring['height_mm']:g} mm\nRONt: minimum zone {ring['minimum_zone_um']:.2f} um, "
                         f"LS {np.ptp(ring['residual_um']):.2f} um", fontsize=9, pad=18)
            entry = {"height_mm": ring["height_mm"], "reference": "least-squares circle",
                     "angle_deg": np.round(np.degrees(angle), 3)}
            if low is None:
                entry["residual_um"] = np.round(r, 4)
            else:
                entry.update(residual_max_um=np.round(r, 4), residual_min_um=np.round(low, 4),
                             note="1440 bins of 0.25 deg: the highest and lowest residual in each")
            data["roundness"].append(entry)
        fig.suptitle(f"Roundness profiles: radial deviation from the least-squares circle (dashed), radial scale in um "
                     f"(grid every {step:g} um)", fontsize=10)
        fig.subplots_adjust(left=0.04, right=0.96, bottom=0.06, top=0.76, wspace=0.45)
        name = "roundness.png"
        caption = ("Roundness profiles of the sections about their least-squares circles (dashed); the radial axis is "
                   "the deviation in um, the same scale for every section. Angles counter-clockwise seen from the "
                   "cone's top, 0 deg along w x a (a the cone's axis, w the world axis least parallel to it: for the "
                   "default cone about +X, tilted with the axis); the profiles are in report.json. Unfiltered.")
        data["roundness_file"] = name
    elif kind == "identified":
        names, values, stds, units = inputs["names"], inputs["values"], inputs["stds"], inputs["units"]
        fig = Figure(figsize=(max(5.0, 0.6 * len(names) + 2), 4))
        ax = fig.subplots()
        x = np.arange(len(names))
        ax.bar(x, [v or 0.0 for v in values], yerr=[2 * (s or 0.0) for s in stds], capsize=3, color="C2")
        ax.set_xticks(x, [f"{n}\n({u})" for n, u in zip(names, units)], fontsize=8)
        ax.axhline(0, color="k", lw=0.6)
        refused = inputs.get("status") == "refused"
        ax.set_ylabel("value the refused fit proposed (um or urad)" if refused else "identified value (um or urad)")
        ax.set_title("REFUSED: values the fit proposed, not applied; error bars +-2 std" if refused
                     else "Identified parameters, error bars +-2 std")
        fig.subplots_adjust(left=0.12, right=0.97, bottom=0.2, top=0.9)
        name, caption = "identified.png", ("Values a refused identification proposed (not applied: the twin's "
                                           "values stand), with +-2 standard deviations." if refused else
                                           "Identified twin parameters with +-2 standard deviations.")
        data["identified"] = {"file": name, "names": names, "values": values, "std": stds, "units": units}
    elif kind == "components":
        components = inputs["components"]
        fig = Figure(figsize=(5.0 * min(len(components), 3), 3.6 * math.ceil(len(components) / 3)))
        axes = np.atleast_1d(fig.subplots(math.ceil(len(components) / 3), min(len(components), 3))).ravel()
        for ax, (component, table) in zip(axes, components.items()):
            ax.errorbar(table["position"], table["value"], yerr=2 * np.asarray(table["std"]), marker="o",
                        capsize=3, color="C3")
            ax.axhline(0, color="k", lw=0.6)
            ax.set_title(component, fontsize=10)
            ax.set_xlabel(f"{component[-1]} position ({'deg' if component[-1] in 'ABC' else 'mm'})")
            ax.set_ylabel(f"error ({table['unit']})")
        for ax in axes[len(components):]:
            ax.set_visible(False)
        fig.subplots_adjust(left=0.08, right=0.97, bottom=0.15, top=0.8, wspace=0.35, hspace=0.6)
        fig.suptitle("Identified component errors against the axis position, error bars +-2 std", fontsize=10)
        name = "components.png"
        caption = ("Identified component errors (tables of values at axis positions) against the position of their "
                   "axis, with +-2 standard deviations.")
        data["components"] = {"file": name, **components}
    else:
        raise ValueError(f"unknown figure kind {kind!r}")
    # fixed layouts, no tight bounding box: each figure is drawn once (a tight layout draws it twice)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    return name, buffer.getvalue(), caption, data


def _figure_inputs(inspection: Inspection, worker=None) -> list[dict]:
    """The inputs of every picture of the report, less those ``inspect_cloud`` sent to ``worker`` already."""
    fig_data = inspection.figures
    if worker is not None and fig_data.get("sent") is worker:
        inputs = []
    else:
        inputs = _deviation_figure_inputs(inspection.report["part"], inspection.part, fig_data["points"],
                                          fig_data["deviation_um"], fig_data.get("beyond_gate"))
    return inputs + _feature_figure_inputs(inspection)


def _save_figures(drawn: list, folder: Path) -> tuple[list[tuple[str, str]], dict]:
    """Write the drawn pictures (``draw_figure``'s results) into ``folder``; returns ([(file name, caption)], the
    plotted data for report.json)."""
    written, data = [], {}
    for name, png, caption, entries in drawn:
        (folder / name).write_bytes(png)
        written.append((name, caption))
        data.update(entries)
    return written, data


def _figures(inspection: Inspection, folder: Path) -> tuple[list[tuple[str, str]], dict]:
    """Draw the pictures here and write the PNGs into ``folder`` (see ``_save_figures``)."""
    return _save_figures([draw_figure(item) for item in _figure_inputs(inspection)], folder)


def _component_tables(names, values, stds, units) -> dict:
    """Identified component-error table values (``EXX@-100``: EXX at X = -100) grouped per component, sorted by
    position: {component: {"position", "value", "std", "unit"}}."""
    tables: dict = {}
    for name, value, std, unit in zip(names, values, stds, units):
        match = re.fullmatch(r"(E[XYZABC][XYZABC])@(-?[0-9.eE+-]+)", str(name))
        if match is None or value is None:
            continue
        table = tables.setdefault(match.group(1), {"position": [], "value": [], "std": [], "unit": unit})
        table["position"].append(float(match.group(2)))
        table["value"].append(float(value))
        table["std"].append(float(std or 0.0))
    for table in tables.values():
        order = np.argsort(table["position"])
        for key in ("position", "value", "std"):
            table[key] = [table[key][i] for i in order]
    return tables


# ------------------------------------------------------------------------------------------------------- the page

# human labels of report keys; a key not listed is shown with its underscores as spaces and its unit in brackets
_LABELS = {
    "rms": "RMS", "min": "minimum", "max": "maximum", "mean": "mean", "std": "standard deviation",
    "p95": "95th percentile of |deviation|", "points": "points",
    "half_angle_deg": "half angle", "nominal_half_angle_deg": "nominal half angle",
    "half_angle_error_urad": "half-angle error", "half_angle_std_urad": "half-angle standard deviation",
    "axis": "axis direction (base to top)", "nominal_axis": "nominal axis direction",
    "axis_tilt_urad": "axis tilt from nominal", "axis_point_mm": "axis point at the nominal base plane",
    "axis_offset_um": "axis offset from the nominal base centre", "apex_mm": "apex",
    "base_radius_mm": "radius at the base plane", "fit_rms_um": "fit residual RMS",
    "form_um": "form (peak-to-valley about the cone)", "cone_points": "points on the cone",
    "height_mm": "height", "nominal_mm": "nominal", "measured_mm": "measured", "error_um": "error",
    "translation_um": "translation", "rotation_urad": "rotation (rotation vector)", "method": "method",
    "iterations": "iterations", "rms_after_um": "RMS after alignment", "not_determined": "not determined",
}
_DECIMALS = {"um": 2, "urad": 1, "mm": 4, "deg": 5}


def _unit_of_key(key: str) -> str:
    tail = key.rsplit("_", 1)[-1]
    return tail if tail in _DECIMALS else ""


def _label(key: str) -> str:
    unit = _unit_of_key(key)
    text = _LABELS.get(key) or (key[: -len(unit) - 1] if unit else key).replace("_", " ")
    return f"{text} ({unit})" if unit else text


def _value(value, unit: str = "") -> str:
    """A number rounded for its unit (um 0.01, urad 0.1, mm 0.0001, deg 0.00001), vectors in brackets, lists
    joined; None as an en dash."""
    if value is None:
        return "&ndash;"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "&ndash;"
        decimals = _DECIMALS.get(unit, 4)
        text = f"{value:.{decimals}f}"
        return "0" if float(text) == 0 else text
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, (int, float)) for v in value):
            return "(" + ", ".join(_value(float(v), unit) for v in value) + ")"
        return "; ".join(html.escape(str(v)) for v in value) or "none"
    if isinstance(value, dict):
        return html.escape(", ".join(f"{k}: {v}" for k, v in value.items()))
    return html.escape(str(value))


def _table(mapping: dict, skip=(), unit: str = "") -> str:
    """Key-value rows with human labels; each value rounded for its key's unit (or ``unit`` for all); a value the
    section's ``not_measured`` names reads "not measured" with why (a best fit took it away: never a figure)."""
    absent = mapping.get("not_measured") or {}
    rows = "".join(f"<tr><th>{html.escape(_label(k))}</th><td>"
                   + (html.escape(absent[k]) if k in absent else _value(v, unit or _unit_of_key(k)))
                   + "</td></tr>" for k, v in mapping.items() if k not in skip and not isinstance(v, dict))
    return f"<table class='kv'>{rows}</table>"


#: Where a characteristic the feature table reads also stands in the report's sections (section, field): a best
#: fit's "not measured" is said there too (``mark_not_measured``), not only in the table.
DETAIL_FIELDS = {"diameter_um": [("diameter", "measured_mm"), ("diameter", "error_um")],
                 "tilt_urad": [("cone", "axis_tilt_urad")], "axis_offset_um": [("cone", "axis_offset_um")],
                 "position_um": [("slots", "largest_position_offset_um")], "depth_um": [("slots", "depth_error_um")],
                 "contour_um": [("slots", "mean_contour_error_um")]}


def mark_not_measured(report: dict, absorbed: dict) -> None:
    """Name, in each section of ``report`` holding it, a characteristic that is not measured (``absorbed``: key ->
    why): the section's ``not_measured`` maps the field to why (the value stays, as the fit gave it)."""
    for key, why in absorbed.items():
        for section, field in DETAIL_FIELDS.get(key, ()):
            entries = report.get(section)
            for entry in entries if isinstance(entries, list) else [entries] if isinstance(entries, dict) else []:
                entry.setdefault("not_measured", {})[field] = why


def _header_html(header: dict) -> str:
    labels = [("date_utc", "date (UTC)"), ("part", "part"), ("part_description", "part description"),
              ("cloud", "cloud"), ("points", "points"), ("program", "program"), ("machine_file", "machine file"),
              ("alignment", "alignment"), ("tolerances", "tolerances"), ("trueaxis_version", "trueaxis version")]
    cells = "".join(f"<tr><th>{html.escape(label)}</th><td>{_value(header.get(key))}</td></tr>"
                    for key, label in labels)
    return f"<table class='header' id='report-header'>{cells}</table>"


def _html(report: dict, images: list[tuple[str, str]], folder: Path) -> str:
    header = report["header"]
    title = f"Inspection report: {_title(report['part'])}"
    style = ("body{font-family:'DejaVu Sans',Arial,sans-serif;max-width:1150px;margin:auto;padding:0 16px;"
             "color:#222}h1{margin-bottom:4px}h2{border-bottom:1px solid #999;margin-top:28px}"
             "table{border-collapse:collapse;margin:6px 0}td,th{border:1px solid #bbb;padding:3px 9px;"
             "text-align:left;vertical-align:top}th{background:#f1f1f1;font-weight:600}"
             "table.features td:nth-child(n+3){text-align:right;white-space:nowrap}"
             "table.header{width:100%}table.header th{width:22%}img{max-width:100%;border:1px solid #ddd}"
             "figcaption{font-size:90%;color:#444;margin-bottom:18px}.signature td{height:36px;width:260px}"
             ".warning{border:2px solid #c0392b;background:#fdecea;padding:4px 12px;margin:10px 0}"
             "@media print{h2{page-break-after:avoid}figure{page-break-inside:avoid}}")
    d = report["deviation_um"]
    parts = [f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{style}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>", _header_html(header)]
    counts = report.get("feature_summary") or {}
    gate = report.get("beyond_gate") or {}
    apart = "" if not gate.get("points") or gate["points"] == report["points"] else (
        f" over the {d['points']:,} points on the part's surfaces; {gate['points']:,} beyond the {gate['gate_mm']:g} "
        f"mm gate (on no feature, up to {_value(_largest(gate.get('deviation_um')), 'um')} um) counted apart")
    parts.append(f"<h2>Summary</h2><p>{report['points']:,} points; deviation RMS {_value(d['rms'], 'um')} um, "
                 f"range {_value(d['min'], 'um')} to {_value(d['max'], 'um')} um{apart} (+ = material outside the "
                 f"nominal surface). Characteristics: {counts.get('pass', 0)} in tolerance, {counts.get('fail', 0)} "
                 f"out of tolerance, {counts.get('uncertain', 0)} uncertain (the fit's 2 std straddle a limit), "
                 f"{counts.get('no tolerance', 0)} without a tolerance, "
                 f"{counts.get('not measured', 0)} not measured.</p>")
    if isinstance(report.get("identification"), dict):
        parts.append(_verdict_html(report["identification"]))
    warnings = inspection_warnings(report)
    if warnings:
        parts.append("<div class='warning'><strong>Read first:</strong><ul>"
                     + "".join(f"<li>{html.escape(w)}</li>" for w in warnings) + "</ul></div>")
    if report.get("feature_table"):
        parts.append(_feature_table_html(report["feature_table"]))
    parts.append("<h2>Deviation from the nominal surfaces (um)</h2>" + _table(d, unit="um"))
    by_surface = report.get("deviation_by_surface_um") or {}
    if by_surface:
        rows = "".join(f"<tr><td>{html.escape(sid)}</td><td>{s['points']:,}</td><td>{_value(s['rms'], 'um')}</td>"
                       f"<td>{_value(s['mean'], 'um')}</td><td>{_value(s['min'], 'um')}</td>"
                       f"<td>{_value(s['max'], 'um')}</td></tr>" for sid, s in by_surface.items())
        parts.append("<h3>By surface</h3><table><tr><th>surface</th><th>points</th><th>RMS (um)</th><th>mean (um)"
                     "</th><th>minimum (um)</th><th>maximum (um)</th></tr>" + rows + "</table>")
    if report.get("cone"):
        parts.append("<h2>Cone (least-squares fit)</h2>" + _table(report["cone"], skip=("axis_point_note",)))
    if report.get("roundness_um"):
        rows = "".join(f"<tr><td>{html.escape(str(r.get('id')))}</td><td>{_value(r['height_mm'], 'mm')}</td>"
                       f"<td>{_value(r['least_squares'], 'um')}</td><td>{_value(r['minimum_zone'], 'um')}</td>"
                       f"<td>{_value(r.get('diameter_ls_mm'), 'mm')}</td><td>{r['points']:,}</td></tr>"
                       for r in report["roundness_um"])
        parts.append("<h2>Roundness</h2><p>" + html.escape(ROUNDNESS_NOTE) + "</p>"
                     "<table><tr><th>section</th><th>height (mm)</th><th>least squares, RONt "
                     "(um)</th><th>minimum zone, RONt (um)</th><th>least-squares diameter (mm)</th><th>points</th>"
                     "</tr>" + rows + "</table>")
    if report.get("diameter"):
        parts.append("<h2>Diameter</h2>" + _table(report["diameter"]))
    for slot in report.get("slots", []):
        parts.append(f"<h2>Slot {html.escape(slot['id'])} (compensation: {html.escape(str(slot['compensation']))})"
                     "</h2>")
        parts.append(_table({"points": slot["points"], "mean_contour_error_um": slot["mean_contour_error_um"],
                             "mean_width_mm": slot["width"]["mean_mm"],
                             "mean_width_error_um": slot["width"]["mean_error_um"],
                             "largest_position_offset_um": slot["position_um"]["max_abs"],
                             "depth_error_um": (slot["depth"] or {}).get("error_um"),
                             "not_measured": slot.get("not_measured") or {}}))
        parts.append("<table><tr><th>segment</th><th>width (mm)</th><th>width error (um)</th><th>position (um)</th>"
                     "<th>parallelism (um)</th></tr>" + "".join(
                         f"<tr><td>{s['segment']}</td><td>{_value(s['width_mm'], 'mm')}</td>"
                         f"<td>{_value(s['width_error_um'], 'um')}</td><td>{_value(s['position_um'], 'um')}</td>"
                         f"<td>{_value(s.get('parallelism_um'), 'um')}</td></tr>"
                         for s in slot["width"]["segments"]) + "</table>")
        parts.append("<table><tr><th>wall</th><th>straightness, minimum zone (um)</th></tr>" + "".join(
            f"<tr><td>{html.escape(k)}</td><td>{_value(v, 'um')}</td></tr>"
            for k, v in slot["straightness_um"].items()) + "</table>")
    alignment = report["alignment"]
    parts.append("<h2>Alignment</h2>" + _table(alignment, skip=("applied_as", "rotation_note")))
    parts.append(f"<p>{html.escape(str(alignment.get('applied_as', '')))}; "
                 f"{html.escape(str(alignment.get('rotation_note', '')))}.</p>")
    identification = report.get("identification")
    if isinstance(identification, dict):
        parts.append(_identification_html(identification))
    elif identification is not None:
        parts.append("<h2>Identification</h2><p>" + html.escape(str(identification)) + "</p>")
    parts.append("<h2>Pictures</h2>")
    for name, caption in images:
        data = base64.b64encode((folder / name).read_bytes()).decode("ascii")
        parts.append(f"<figure><img alt='{html.escape(name)}' src='data:image/png;base64,{data}'>"
                     f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("<h2>Sign-off</h2><table class='signature'><tr><th>inspected by</th><td></td><th>date</th><td></td>"
                 "</tr><tr><th>approved by</th><td></td><th>date</th><td></td></tr></table>")
    parts.append(f"<p style='font-size:85%;color:#555'>Files: {html.escape(', '.join(report.get('files', [])))}. "
                 f"{html.escape(report['units'])}.</p></body></html>\n")
    return "\n".join(parts)


#: The identification's verdict on the page: (headline, what it means for the twin, box colours).
_VERDICT_WORDS = {
    "accepted": ("ACCEPTED", "the identified values below replace the twin's (written where --write was given)",
                 "#1e7b34", "#e6f4ea"),
    "refused": ("REFUSED", "the fit does not explain the part: its changes below are not applied and nothing is "
                "written; the twin's values stand", "#c0392b", "#fdecea"),
    "no change": ("NO CHANGE", "nothing to change: the twin's values stand", "#555555", "#f1f1f1"),
}


def _verdict_html(identification: dict) -> str:
    """The identification's verdict in a box (at the top of the page): status, what it means, its reasons, the
    residuals and the held-out check."""
    verdict = identification.get("verdict") or {}
    status = verdict.get("status")
    if status is None:  # a report without a verdict (written before there was one)
        return ""
    headline, meaning, edge, fill = _VERDICT_WORDS.get(status, (str(status).upper(), "", "#555555", "#f1f1f1"))
    out = [f"<div class='verdict' id='identification-verdict' style='border:2px solid {edge};background:{fill};"
           f"padding:4px 12px;margin:10px 0'><strong>Identification {html.escape(headline)}</strong>: "
           f"{html.escape(meaning)}."]
    reasons = verdict.get("reasons") or []
    if reasons:
        out.append("<ul>" + "".join(f"<li>{html.escape(str(r))}</li>" for r in reasons) + "</ul>")
    figures = [f"residual RMS {_value(verdict.get('residual_before_rms_um'), 'um')} um with the twin as is, "
               f"{_value(verdict.get('residual_after_rms_um'), 'um')} um after the fit; deviation RMS "
               f"{_value(verdict.get('deviation_rms_um'), 'um')} um"]
    heldout = verdict.get("heldout") or {}
    if "before_rms_um" in heldout:
        figures.append(f"held-out points ({heldout.get('points', 0):,}): {_value(heldout['before_rms_um'], 'um')} -> "
                       f"{_value(heldout['after_rms_um'], 'um')} um where the fit predicted "
                       f"{_value(heldout['fit_before_rms_um'], 'um')} -> {_value(heldout['fit_after_rms_um'], 'um')} "
                       f"um ({'confirmed' if heldout.get('confirmed') else 'not confirmed'})")
    elif heldout.get("not_run"):
        figures.append("held-out check not run")
    out.append("<p>" + html.escape("; ".join(figures)) + ".</p>")
    if identification.get("setup_hidden_note"):  # an accepted twin that moves the next part unchecked: in the box
        out.append(f"<p><strong>Warning</strong>: {html.escape(identification['setup_hidden_note'])}.</p>")
    out.append("</div>")
    return "".join(out)


def _identification_html(identification: dict) -> str:
    """The identification section: its verdict (a refused fit's changes are never shown as identified), the
    parameters, those estimated but not significant, those the part cannot identify, and those held."""
    verdict = identification.get("verdict") or {}
    status = verdict.get("status")
    out = ["<h2>Identified parameters</h2>"]
    if status is not None:
        headline = _VERDICT_WORDS.get(status, (str(status).upper(),))[0]
        out = [f"<h2>Identification: {html.escape(headline)}</h2>",
               f"<p>Verdict <strong>{html.escape(headline)}</strong>"
               + "".join(f"; {html.escape(str(r))}" for r in verdict.get("reasons") or [])
               + " (the box at the top).</p>"]
    params = identification.get("parameters") or []
    if params:
        title = "Changes the refused fit proposed (not applied)" if status == "refused" else \
            "Identified parameters"
        rows = []
        for p in params:
            unit = next((k[6:] for k in p if k.startswith("value_")), "")
            rows.append(f"<tr><td>{html.escape(str(p.get('name')))}</td><td>{_value(p.get('value_' + unit), unit)}"
                        f"</td><td>{_value(p.get('change_' + unit), unit)}</td>"
                        f"<td>{_value(p.get('std_' + unit), unit)}</td><td>{html.escape(unit)}</td></tr>")
        out.append(f"<h3>{title}</h3><table><tr><th>parameter</th><th>value</th><th>change</th>"
                   "<th>standard deviation</th><th>unit</th></tr>" + "".join(rows) + "</table>")
    setup = identification.get("setup_offset") or {}
    if setup.get("TX_um") is not None:
        out.append("<p>Set-up offset of the part (a translation of the part in its frame, fitted with the changes "
                   "and never written to the twin): " + html.escape(", ".join(
                       f"{a} {_value(setup.get(a + '_um'), 'um')} +- {_value(setup.get(a + '_std_um'), 'um')}"
                       for a in ("TX", "TY", "TZ") if setup.get(a + "_um") is not None)) + " um"
                   + (f" ({html.escape(str(setup['note']))})" if setup.get("note") else "") + ".</p>")
    not_significant = identification.get("not_significant") or []
    too_small = identification.get("too_small_to_write") or []

    def change(entry):
        unit = next((k[7:] for k in entry if k.startswith("change_")), "")
        return (f"{entry['name']} {_value(entry.get('change_' + unit), unit)} +- "
                f"{_value(entry.get('std_' + unit), unit)} {unit}")
    if too_small:
        out.append("<p>Estimated and significant, but together too small to be written (the verdict; kept at the "
                   "twin's value): " + html.escape(", ".join(change(e) for e in too_small)) + ".</p>")
    if not_significant:
        out.append("<p>Estimated, not significant (kept at the twin's value): "
                   + html.escape(", ".join(change(e) for e in not_significant)) + ".</p>")
    # the detail sorts the rest: held (a gauge value, or not asked for) or not identifiable from this part
    estimated = {e["name"] for e in not_significant} | {e["name"] for e in too_small}
    detail = [d for d in identification.get("not_identifiable_detail") or [] if d.get("name") not in estimated]
    held = [d["name"] for d in detail if str(d.get("reason", "")).startswith("held")]
    unseen = [d["name"] for d in detail if not str(d.get("reason", "")).startswith("held")]
    if unseen:
        out.append("<p>Not identifiable from this part: " + html.escape(", ".join(map(str, unseen))) + ".</p>")
    if held:
        out.append("<p>Held (the reference value of an error function, or not asked for): "
                   + html.escape(", ".join(map(str, held))) + ".</p>")
    out.append(_table({k: v for k, v in identification.items()
                       if isinstance(v, (int, float, str)) and not isinstance(v, bool)}))
    return "\n".join(out)


def _largest(stats: dict | None) -> float | None:
    """The largest |deviation| of ``deviation_stats``' figures, or None."""
    if not stats or stats.get("min") is None:
        return None
    return max(abs(stats["min"]), abs(stats["max"]))


def _title(name: str) -> str:
    """What the report calls a part (``Part.title``; the name itself for a report of a part no longer known)."""
    try:
        return get_part(name).title
    except ValueError:
        return name


def _feature_table_html(rows: list[dict]) -> str:
    def limits(row):
        t = row["tolerance"]
        if t is None:
            return ""
        return f"{t['lower']:+.1f} / {t['upper']:+.1f} {row['deviation_unit']}" if row["key"] in SIZE_KEYS \
            else f"&le; {t['upper']:.1f} {row['deviation_unit']}"

    def value(v, unit):
        if v is None:
            return "n/a"
        return f"{v:.4f} {unit}" if unit in ("mm", "deg") else f"{v:.2f} {unit}"

    def without(row):  # the flyer screen's points left out (flyers_in_features): only when it set some apart
        other = row.get("without_flyers")
        if not flyers or other is None:
            return ""
        return f"<td>{value(other['deviation'], row['deviation_unit'])}, {html.escape(other['result'])}</td>"

    flyers = any("without_flyers" in r for r in rows)
    colour = {"pass": "#d9f2d9", "fail": "#f8d0d0", "uncertain": "#fff1c2"}
    body = "".join(
        f"<tr style='background:{colour.get(r['result'], '#ffffff')}'><td>{html.escape(r['feature'])}</td>"
        f"<td>{html.escape(r['characteristic'])}</td><td>{value(r['nominal'], r['unit'])}</td>"
        f"<td>{value(r['actual'], r['unit'])}</td><td>{value(r['deviation'], r['deviation_unit'])}</td>"
        f"<td>{limits(r)}</td><td><b>{html.escape(r['result'])}</b></td>{without(r)}</tr>" for r in rows)
    return ("<h2>Feature table</h2><table class='features'><tr><th>feature</th><th>characteristic</th>"
            "<th>nominal</th><th>actual</th><th>deviation</th><th>tolerance</th><th>result</th>"
            + ("<th>without the flyers (deviation, result)</th>" if flyers else "") + "</tr>" + body + "</table>")


def _write_point_files(inspection: Inspection, folder: Path) -> None:
    """``deviations.ply`` (binary; the deviation as the scalar field ``deviation_um``, CloudCompare's convention
    ``scalar_deviation_um``) and ``deviations.csv`` (x_mm, y_mm, z_mm, deviation_um, surface) of the aligned points."""
    dev = inspection.deviation
    names = list(dev.surface_ids) + ["cad_mesh"]
    codes = np.where(dev.from_mesh | (dev.surface < 0), len(names) - 1, dev.surface)
    comments = [f"trueaxis inspect: {inspection.report['part']} part frame, mm; deviation um, + = material outside",
                f"cloud {Path(str(inspection.cloud.source)).name}"]
    write_deviation_ply(folder / "deviations.ply", inspection.aligned, inspection.deviation_um, inspection.normals,
                        comments=[c.replace("\n", " ") for c in comments])
    write_deviation_csv(folder / "deviations.csv", inspection.aligned, inspection.deviation_um, (names, codes))


def write_report(inspection: Inspection, out_dir, figure_worker=None) -> Path:
    """Write ``out_dir/report.json``, ``report.html``, the PNGs and the per-point deviations (``deviations.ply``,
    ``deviations.csv``), all or nothing.

    The folder is built as a temporary sibling and renamed into place; an existing ``out_dir`` (a previous report)
    is moved aside first and removed once the new one is in place. Returns the folder. figure_worker : a
    ``FigureWorker`` (the one given to :func:`inspect_cloud`, if any): the pictures are drawn there while this
    process writes the point files; None: drawn here, the point files written by a thread meanwhile.
    """
    try:
        out = resolve_output(out_dir, folder=True)  # a link to a folder: the folder it names
    except OutputPathError as exc:
        raise dv.InspectionError(str(exc)) from None
    temp = temp_folder_beside(out)
    try:
        report = _clean(inspection.report)
        if figure_worker is not None:
            for item in _figure_inputs(inspection, figure_worker):
                figure_worker.submit(item)
            _write_point_files(inspection, temp)  # while the worker draws
            images, figure_data = _save_figures(figure_worker.results(), temp)
        else:
            # the point files (numpy formatting, which releases the GIL) are written while matplotlib draws
            with ThreadPoolExecutor(max_workers=1) as pool:
                points_written = pool.submit(_write_point_files, inspection, temp)
                images, figure_data = _figures(inspection, temp)
                points_written.result()  # re-raises its error, if any
        report["figures"] = _clean(figure_data)
        report["files"] = ["report.json", "report.html", "deviations.ply", "deviations.csv"] + \
            [name for name, _ in images]
        (temp / "report.json").write_text(json.dumps(report, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        (temp / "report.html").write_text(_html(report, images, temp), encoding="utf-8")
        publish_folder(temp, out)
    except BaseException:
        shutil.rmtree(temp, ignore_errors=True)
        raise
    return out
