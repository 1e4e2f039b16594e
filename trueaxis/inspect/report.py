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
import html
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import deviation as dv
from . import form
from .cloud import Cloud, CloudError, check_extent, read_cloud, write_deviation_csv, write_deviation_ply
from .tolerances import CHARACTERISTICS, feature_table, load_tolerances, summary

SIZE_KEYS = {k for k, v in CHARACTERISTICS.items() if v[0] == "size"}

__all__ = ["Inspection", "load_part", "inspect_cloud", "deviation_stats", "evaluate_nas979", "evaluate_slots",
           "write_report", "ALIGNMENTS"]

ALIGNMENTS = ("none", "bestfit", "datum")
EXTENT_TOLERANCE_MM = 1.0   # stock, probe radius and fixture allowance around the part's bounding box
FAR_MM = 1.0                # a point this far from every surface of the part cannot be on it
MIN_RING_POINTS = 8


@dataclass
class Inspection:
    """The outcome of ``inspect_cloud``.

    cloud : the Cloud as read (points in the file's frame). aligned : (n, 3) mm, the points in the part frame.
    normals : (n, 3) or None, the cloud's normals turned with the alignment. deviation : dv.Deviation.
    part : the part JSON dict. report : the report dict (JSON-ready). figures : data for the pictures.
    """

    cloud: Cloud
    aligned: np.ndarray
    normals: np.ndarray | None
    deviation: dv.Deviation
    part: dict
    report: dict
    figures: dict = field(default_factory=dict)

    @property
    def deviation_um(self) -> np.ndarray:
        """(n,) signed deviation of each point, um (+ = material outside the nominal surface)."""
        return self.deviation.deviation_um

    def aligned_cloud(self) -> Cloud:
        """The cloud in the part frame (what the deviations refer to)."""
        return dataclasses.replace(self.cloud, points=self.aligned, normals=self.normals)


def load_part(part: str, part_dir=None, cad=None) -> dict:
    """The part JSON: ``part_dir/<part>.json``; with ``cad``, the JSON beside it (``<stem>.json``) if present; else
    the generator's default description. Raises InspectionError for a missing file or a JSON for another part."""
    from .parts import nas979_description, slot_block_description

    if part not in ("nas979", "slots"):
        raise dv.InspectionError(f"unknown part {part!r}: expected nas979 or slots")
    path = None
    if part_dir is not None:
        path = Path(part_dir) / f"{part}.json"
        if not path.is_file():
            raise dv.InspectionError(f"{path}: no such part JSON (write it with 'trueaxis part {part} -o {part_dir}')")
    elif cad is not None and Path(cad).with_suffix(".json").is_file():
        path = Path(cad).with_suffix(".json")
    if path is None:
        return nas979_description() if part == "nas979" else slot_block_description()
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise dv.InspectionError(f"{path}: cannot read the part JSON ({exc})") from None
    if data.get("part") != part:
        raise dv.InspectionError(f"{path} describes part {data.get('part')!r}, not {part!r}")
    return data


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
        out["notes"] = [f"only {len(pts)} points on the cone (within {gate_mm} mm of it): no cone evaluation"]
        return out, figures
    fit = form.fit_cone(pts, initial_axis=a_nom, reference_plane=(c_nom, a_nom))
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
    }
    rings = []
    for feature in (f for f in part["features"] if f.get("type") == "roundness"):
        h = float(feature["height"])
        planar, index = form.section_ring(pts, base_point, up, h, slab_mm, half_angle_rad=-fit.half_angle_rad,
                                          return_index=True)
        entry = {"id": feature.get("id"), "height_mm": h, "points": int(len(index)), "slab_half_width_mm": slab_mm}
        if len(index) < MIN_RING_POINTS:
            entry.update(least_squares=None, minimum_zone=None, diameter_ls_mm=None,
                         note=f"fewer than {MIN_RING_POINTS} cone points within {slab_mm} mm of this height")
        else:
            ls = form.fit_circle_least_squares(planar)
            mz = form.minimum_zone_circle(planar)
            entry.update(least_squares=float(np.ptp(ls.residuals) * 1e3), minimum_zone=mz.width * 1e3,
                         diameter_ls_mm=2 * ls.radius,
                         nominal_diameter_mm=feature.get("nominal_diameter"))
            figures["rings"].append({"height_mm": h, "angle": np.arctan2(*(planar - ls.center).T[::-1]),
                                     "residual_um": ls.residuals * 1e3})
        rings.append(entry)
    out["roundness_um"] = rings
    diameter = next((f for f in part["features"] if f.get("type") == "diameter"), None)
    if diameter is not None:
        h = float(diameter["height"])
        # the radius shrinks along `up` for this cone: r(h) = r_base - h tan(alpha)
        measured = 2 * (r_base - h * tan_fit)
        out["diameter"] = {"height_mm": h, "nominal_mm": float(diameter["nominal_diameter"]), "measured_mm": measured,
                           "error_um": (measured - float(diameter["nominal_diameter"])) * 1e3,
                           "method": "from the least-squares cone at this height along its axis"}
    return out, figures


# ------------------------------------------------------------------------------------------------------ the slots

def _trace_line(xy):
    """Least-squares 2D line of a wall's XY trace, or None with fewer than 2 distinct points."""
    if len(xy) < 2 or np.ptp(xy, axis=0).max() == 0:
        return None
    return form.fit_line(xy)


def evaluate_slots(points, dev: dv.Deviation, part: dict, gate_mm: float = 0.5) -> tuple:
    """Per-slot width, straightness, parallelism, position, depth and deviation statistics (module docstring).

    points : (n, 3) mm, part frame. dev : their deviations. part : the slot block's JSON.
    Returns (report entries dict, figure data dict).
    """
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
                             note="a wall of this segment has fewer than 2 distinct points")
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
        slots.append({
            "id": feature["id"], "compensation": feature.get("compensation"), "points": int(in_slot.sum()),
            "deviation_um": deviation_stats(d_um[in_slot]),
            "mean_contour_error_um": float(np.mean(np.abs(d_um[contour]))) if contour.any() else None,
            "width": {"nominal_mm": nominal_width, "segments": segments,
                      "mean_mm": float(np.mean(widths)) if widths else None,
                      "mean_error_um": float((np.mean(widths) - nominal_width) * 1e3) if widths else None},
            "straightness_um": straightness,
            "parallelism_um": parallel,
            "position_um": {"segments": [{"segment": s["segment"], "offset_um": s["position_um"]} for s in segments],
                            "max_abs": float(np.max(np.abs(positions))) if positions else None,
                            "note": "midline between the walls minus the nominal tool-centre path, along the "
                                    "segment's left normal, at its midpoint"},
            "depth": depth,
        })
    return {"slots": slots}, {}


# -------------------------------------------------------------------------------------------------- the pipeline

def inspect_cloud(cloud, part: str, part_dir=None, cad=None, align: str = "none", gate_mm: float = 0.5,
                  tolerances=None) -> Inspection:
    """Read (or take) a cloud, check it can be the part, align it, measure its deviations, evaluate the features.

    cloud : path of a cloud file (``read_cloud``), or a Cloud. part : "nas979" | "slots". part_dir : folder with
    <part>.json (and slots.stl). cad : a STEP or mesh file of the part, with its JSON beside it (``<stem>.json``): the
    mesh is the reference where the JSON has no analytic surface; without the JSON the features cannot be evaluated
    and the inspection is refused, naming the JSON it needs. align : "none" | "bestfit" | "datum". tolerances : a tolerance
    TOML file (``trueaxis.inspect.tolerances``; merged over the part JSON's own), or None for the JSON's alone.

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
            cad_mesh = dv.load_mesh_file(cad, part_doc) if cad is not None else dv.part_mesh(part_doc, part_dir)
            distance = dv.MeshDistance(cad_mesh)
        return distance

    if cad is not None or not surfaces:
        mesh()
    bbox = (cad_mesh.vertices.min(axis=0), cad_mesh.vertices.max(axis=0)) if cad_mesh is not None \
        else dv.part_bbox(part_doc)
    try:
        check_extent(cloud.points, *bbox, EXTENT_TOLERANCE_MM, part=part)
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

    far = np.abs(dev.deviation_mm) > FAR_MM
    if far.mean() > 0.5:
        raise dv.InspectionError(
            f"{cloud.source}: {far.sum()} of {len(far)} points lie more than {FAR_MM:g} mm from every surface of the "
            f"{part} part (median {np.median(np.abs(dev.deviation_mm)):.3f} mm): this cloud cannot be the {part} "
            "part in its frame, in mm")

    if part == "nas979":
        features, figures = evaluate_nas979(aligned, dev, part_doc, gate_mm)
    else:
        features, figures = evaluate_slots(aligned, dev, part_doc, gate_mm)
    d_um = dev.deviation_um
    per_surface = {}
    for k, sid in enumerate(dev.surface_ids):
        sel = (dev.surface == k)
        if sel.any():
            per_surface[sid] = deviation_stats(d_um[sel])
    if dev.from_mesh.any():
        per_surface["cad_mesh"] = deviation_stats(d_um[dev.from_mesh])
    report = {
        "trueaxis_report": "inspect", "version": 1,
        "part": part, "cloud": str(cloud.source), "points": int(len(aligned)),
        "units": "lengths in the keys' units (mm, um), angles in deg or urad; deviations + = material outside the "
                 "nominal surface",
        "alignment": motion.as_dict(),
        "deviation_um": deviation_stats(d_um),
        "deviation_by_surface_um": per_surface,
        "reference": {
            "analytic_points": int((~dev.from_mesh).sum()), "cad_mesh_points": int(dev.from_mesh.sum()),
            "analytic_surfaces": len(surfaces),
            "cad_mesh": None if cad_mesh is None else {
                "source": cad_mesh.source, "triangles": int(len(cad_mesh.triangles)),
                "chord_error_bound_um": None if cad_mesh.chord_error_mm is None else cad_mesh.chord_error_mm * 1e3,
                "note": cad_mesh.note},
        },
        **features,
    }
    report["feature_table"] = feature_table(report, part_doc, limits)
    report["feature_summary"] = summary(report["feature_table"])
    figures.update(points=aligned, deviation_um=d_um)
    return Inspection(cloud, aligned, normals, dev, part_doc, report, figures)


# -------------------------------------------------------------------------------------------------- the writing

def _figures(inspection: Inspection, folder: Path) -> list[tuple[str, str]]:
    """Write the PNGs into ``folder``; returns [(file name, caption)]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig_data = inspection.figures
    pts, d = fig_data["points"], fig_data["deviation_um"]
    rng = np.random.default_rng(0)
    show = rng.choice(len(pts), size=min(len(pts), 40_000), replace=False) if len(pts) > 40_000 else slice(None)
    limit = float(np.percentile(np.abs(d), 99)) or 1.0
    written = []

    fig = plt.figure(figsize=(7.5, 6))
    if inspection.report["part"] == "nas979":
        ax = fig.add_subplot(projection="3d")
        sc = ax.scatter(*pts[show].T, c=d[show], cmap="coolwarm", vmin=-limit, vmax=limit, s=2)
        ax.set_zlabel("z (mm)")
        ax.set_box_aspect(np.ptp(pts, axis=0) + 1e-9)
    else:
        ax = fig.add_subplot()
        sc = ax.scatter(pts[show, 0], pts[show, 1], c=d[show], cmap="coolwarm", vmin=-limit, vmax=limit, s=2)
        ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    fig.colorbar(sc, ax=ax, shrink=0.7, label="deviation (um), + = material outside")
    ax.set_title("Deviation from the nominal part (part frame)")
    fig.savefig(folder / "deviation_map.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    written.append(("deviation_map.png", "Deviation colour map on the part (colour scale clipped at the 99th "
                    "percentile of |deviation|)."))

    fig, ax = plt.subplots(figsize=(7, 4))
    ax.hist(d, bins=80, color="steelblue")
    ax.set_xlabel("deviation (um)")
    ax.set_ylabel("points")
    ax.set_title("Histogram of deviations")
    fig.savefig(folder / "histogram.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    written.append(("histogram.png", "Histogram of the signed deviations."))

    rings = fig_data.get("rings") or []
    if rings:
        fig, axes = plt.subplots(1, len(rings), subplot_kw={"projection": "polar"}, figsize=(4.2 * len(rings), 4.4))
        axes = np.atleast_1d(axes)
        for ax, ring in zip(axes, rings):
            order = np.argsort(ring["angle"])
            r = ring["residual_um"][order]
            span = max(float(np.ptp(r)), 1e-6)
            base = span  # radial axis: residual + an offset so that the profile reads as a ring
            ax.plot(np.r_[ring["angle"][order], ring["angle"][order][:1]], np.r_[r, r[:1]] + base, lw=1)
            ax.plot(np.linspace(0, 2 * np.pi, 200), np.full(200, base), "k--", lw=0.6)
            ax.set_ylim(0, base + r.max() + 0.1 * span)
            ax.set_yticklabels([])
            ax.set_title(f"h = {ring['height_mm']:g} mm\nLS roundness {np.ptp(r):.2f} um", fontsize=9)
        fig.savefig(folder / "roundness.png", dpi=110, bbox_inches="tight")
        plt.close(fig)
        written.append(("roundness.png", "Roundness profiles about the least-squares circles (dashed), radial "
                        "deviation magnified."))
    return written


def _html(report: dict, images: list[tuple[str, str]], folder: Path) -> str:
    def rows(mapping):
        return "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(_fmt(v))}</td></tr>"
                       for k, v in mapping.items())

    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>trueaxis inspection: "
             f"{html.escape(report['part'])}</title><style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 8px;text-align:left}"
             "img{max-width:100%}</style></head><body>",
             f"<h1>Inspection of {html.escape(report['cloud'])} against {html.escape(report['part'])}</h1>",
             f"<p>{report['points']} points; {html.escape(report['units'])}.</p>",
             "<h2>Deviation (um)</h2><table>" + rows(report["deviation_um"]) + "</table>",
             "<h2>Alignment</h2><table>" + rows(report["alignment"]) + "</table>"]
    if report.get("feature_table"):
        parts.append(_feature_table_html(report["feature_table"]))
    if report.get("cone"):
        parts.append("<h2>Cone</h2><table>" + rows(report["cone"]) + "</table>")
    if report.get("diameter"):
        parts.append("<h2>Diameter</h2><table>" + rows(report["diameter"]) + "</table>")
    if report.get("roundness_um"):
        parts.append("<h2>Roundness (um)</h2><table><tr><th>height (mm)</th><th>least squares</th>"
                     "<th>minimum zone</th><th>points</th></tr>" + "".join(
                         f"<tr><td>{r['height_mm']:g}</td><td>{_fmt(r['least_squares'])}</td>"
                         f"<td>{_fmt(r['minimum_zone'])}</td><td>{r['points']}</td></tr>"
                         for r in report["roundness_um"]) + "</table>")
    for slot in report.get("slots", []):
        parts.append(f"<h2>{html.escape(slot['id'])} ({html.escape(str(slot['compensation']))})</h2>")
        parts.append("<table>" + rows({"points": slot["points"], "mean contour error (um)":
                                       slot["mean_contour_error_um"], "mean width (mm)": slot["width"]["mean_mm"],
                                       "mean width error (um)": slot["width"]["mean_error_um"],
                                       "max |position| (um)": slot["position_um"]["max_abs"],
                                       "depth error (um)": (slot["depth"] or {}).get("error_um")}) + "</table>")
        parts.append("<table><tr><th>segment</th><th>width (mm)</th><th>width error (um)</th><th>position (um)</th>"
                     "<th>parallelism (um)</th></tr>" + "".join(
                         f"<tr><td>{s['segment']}</td><td>{_fmt(s['width_mm'])}</td><td>{_fmt(s['width_error_um'])}"
                         f"</td><td>{_fmt(s['position_um'])}</td><td>{_fmt(s.get('parallelism_um'))}</td></tr>"
                         for s in slot["width"]["segments"]) + "</table>")
        parts.append("<table><tr><th>wall</th><th>straightness (um)</th></tr>" + "".join(
            f"<tr><td>{html.escape(k)}</td><td>{_fmt(v)}</td></tr>" for k, v in slot["straightness_um"].items())
            + "</table>")
    if report.get("identification") is not None:
        parts.append("<h2>Identification</h2><pre>" + html.escape(json.dumps(report["identification"], indent=1))
                     + "</pre>")
    parts.append("<h2>Pictures</h2>")
    for name, caption in images:
        data = base64.b64encode((folder / name).read_bytes()).decode("ascii")
        parts.append(f"<figure><img alt='{html.escape(name)}' src='data:image/png;base64,{data}'>"
                     f"<figcaption>{html.escape(caption)} ({html.escape(name)})</figcaption></figure>")
    parts.append("</body></html>\n")
    return "\n".join(parts)


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

    colour = {"pass": "#d9f2d9", "fail": "#f8d0d0"}
    body = "".join(
        f"<tr style='background:{colour.get(r['result'], '#ffffff')}'><td>{html.escape(r['feature'])}</td>"
        f"<td>{html.escape(r['characteristic'])}</td><td>{value(r['nominal'], r['unit'])}</td>"
        f"<td>{value(r['actual'], r['unit'])}</td><td>{value(r['deviation'], r['deviation_unit'])}</td>"
        f"<td>{limits(r)}</td><td><b>{html.escape(r['result'])}</b></td></tr>" for r in rows)
    return ("<h2>Feature table</h2><table class='features'><tr><th>feature</th><th>characteristic</th>"
            "<th>nominal</th><th>actual</th><th>deviation</th><th>tolerance</th><th>result</th></tr>" + body
            + "</table>")


def _fmt(value) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, dict):
        return json.dumps(value)
    return str(value)


def _clean(value):
    """JSON-ready: numpy scalars and arrays to Python, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


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


def write_report(inspection: Inspection, out_dir) -> Path:
    """Write ``out_dir/report.json``, ``report.html``, the PNGs and the per-point deviations (``deviations.ply``,
    ``deviations.csv``), all or nothing.

    The folder is built as a temporary sibling and renamed into place; an existing ``out_dir`` (a previous report)
    is moved aside first and removed once the new one is in place. Returns the folder.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise dv.InspectionError(f"{out}: exists and is not a folder")
    parent = out.parent if str(out.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    temp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=parent))
    try:
        report = _clean(inspection.report)
        images = _figures(inspection, temp)
        _write_point_files(inspection, temp)
        report["files"] = ["report.json", "report.html", "deviations.ply", "deviations.csv"] + \
            [name for name, _ in images]
        (temp / "report.json").write_text(json.dumps(report, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        (temp / "report.html").write_text(_html(report, images, temp), encoding="utf-8")
        old = None
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=parent))
            os.rmdir(old)
            os.replace(out, old)
        os.replace(temp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(temp, ignore_errors=True)
        raise
    return out
