"""The three-slot block of the equivalent-cutting-force paper (DESIGN.md section 6) as a ``Part``.

The geometry (``SlotBlockParams``, ``build_slot_block``, ``slot_block_description``) is in ``parts.py`` beside the
cone's, with the part frame and the JSON schema; this module is what makes it a ``Part``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .part import surface
from .parts import SlotBlockParams, _slots_chord_bound, build_slot_block, slot_block_description


def slot_pattern(part: dict, n_points: int, margin_mm: float = 0.5, floor_offsets=(-0.5, 0.0, 0.5)):
    """Lines on the slot walls, arcs and floors: points (N, 3) mm, unit outward normals (N, 3), part frame."""
    pieces = []  # (length, sampler)
    for feat in part["features"]:
        if feat.get("type") != "slot":
            continue
        depth = feat["nominal_depth"]
        zs = [-depth * f for f in (0.25, 0.5, 0.75)]
        for wid in feat["walls"]:
            s = surface(part, wid)
            a = np.array(s["segment"]["start"], float)
            b = np.array(s["segment"]["end"], float)
            nrm = np.array(s["normal"], float)
            length = float(np.linalg.norm(b - a)) - 2 * margin_mm
            if length <= 0:
                continue
            t_dir = (b - a) / np.linalg.norm(b - a)
            for z in zs:
                pieces.append((length, ("line", a + margin_mm * t_dir, t_dir, length, z, nrm)))
        for aid in feat["arcs"]:
            s = surface(part, aid)
            lo, hi = np.radians(s["angle_range_deg"])
            r = s["radius"]
            length = r * (hi - lo) - 2 * margin_mm
            if length <= 0:
                continue
            for z in zs:
                pieces.append((length, ("arc", np.array(s["center"], float), r, lo + margin_mm / r, hi - margin_mm / r, z)))
        path = np.asarray(feat["tool_centre_path"], float)
        rho = feat["tool_diameter"] / 2
        for k in range(len(path) - 1):
            a, b = path[k, :2], path[k + 1, :2]
            t_dir = (b - a) / np.linalg.norm(b - a)
            left = np.array([-t_dir[1], t_dir[0]])
            length = float(np.linalg.norm(b - a))
            for off in floor_offsets:
                pieces.append((length, ("line", a + off * rho * left, t_dir, length, -depth, np.array([0.0, 0.0, 1.0]))))
    if not pieces:
        raise ValueError("the part JSON has no slot features to probe")
    lengths = np.array([p[0] for p in pieces])
    counts = np.maximum(1, np.round(n_points * lengths / lengths.sum()).astype(int))
    pts, nrms = [], []
    for (_, spec), c in zip(pieces, counts):
        u = (np.arange(c) + 0.5) / c
        if spec[0] == "line":
            _, a, t_dir, length, z, nrm = spec
            xy = a + (u * length)[:, None] * t_dir
            pts.append(np.column_stack([xy, np.full(c, z)]))
            nrms.append(np.broadcast_to(nrm, (c, 3)))
        else:
            _, center, r, lo, hi, z = spec
            ang = lo + u * (hi - lo)
            radial = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(c)])
            pts.append(np.column_stack([center[:2] + r * radial[:, :2], np.full(c, z)]))
            nrms.append(-radial)  # concave wall: out of the material = towards the axis
    return np.concatenate(pts), np.ascontiguousarray(np.concatenate(nrms))




def _block_sides(part: dict) -> list[dict]:
    """The slot block's four side faces, from its parameters (``derived: true``)."""
    p = part["parameters"]
    length, width, height = p["block_length_x"], p["block_width_y"], p["block_height_z"]
    z = [-height, 0.0]
    note = "derived by trueaxis.inspect.deviation from the block's parameters"
    return [
        {"id": "block_side_xneg", "type": "plane", "point": [0.0, 0.0, 0.0], "normal": [-1.0, 0.0, 0.0],
         "y_range": [0.0, width], "z_range": z, "derived": True, "note": note},
        {"id": "block_side_xpos", "type": "plane", "point": [length, 0.0, 0.0], "normal": [1.0, 0.0, 0.0],
         "y_range": [0.0, width], "z_range": z, "derived": True, "note": note},
        {"id": "block_side_yneg", "type": "plane", "point": [0.0, 0.0, 0.0], "normal": [0.0, -1.0, 0.0],
         "x_range": [0.0, length], "z_range": z, "derived": True, "note": note},
        {"id": "block_side_ypos", "type": "plane", "point": [0.0, width, 0.0], "normal": [0.0, 1.0, 0.0],
         "x_range": [0.0, length], "z_range": z, "derived": True, "note": note},
    ]


@dataclass(frozen=True)
class SlotBlock:
    """The slot block: three slots posted with no, geometric and comprehensive compensation (default: xh714)."""

    name: str = "slots"
    title: str = "slot block"
    default_machine: str = "xh714"
    params_type: type = SlotBlockParams
    evaluation: str = "slots"
    map_view: str = "plan"
    # A = block top, B = front side (y = 0, or back y = W), C = left end (x = 0, or right end x = L)
    datums: tuple = (("A", ("block_top",), 3), ("B", ("block_side_yneg", "block_side_ypos"), 2),
                     ("C", ("block_side_xneg", "block_side_xpos"), 1))
    # a best fit moves the block onto its slots: the slots' common offset from their nominal paths, their common depth
    # error and the share of the contour error a rigid move explains are taken away
    bestfit_absorbs: tuple = (
        ("position_um", "the fit moves the block onto the slots' midlines"),
        ("depth_um", "the fit moves the block onto the slots' floors"),
        ("contour_um", "the fit moves the block onto the slots' walls, taking the common part of their error away"))

    def build(self, params=None):
        return build_slot_block(params)

    def description(self, params=None) -> dict:
        return slot_block_description(params)

    def stl_chord_bound(self, vertices, faces, params, description):
        """Chord error bound on the slots' arcs (cylinders of radius rho about the path's vertices)."""
        bound, widest = _slots_chord_bound(vertices, faces, params if params is not None else SlotBlockParams())
        return bound, widest, ("rho (1 - cos(dphi / 2)) on the slots' arcs (rho = tool_diameter / 2), dphi the widest "
                               "angular span of any STL triangle on an arc; planes are exact up to float32 rounding "
                               "(1e-5 mm)")

    def probe_pattern(self, description, n_points):
        return slot_pattern(description, n_points)

    def program_mismatch(self, description, program_text):
        """None: a slot program's title does not name the block's dimensions (nothing to compare)."""
        return None

    def material_mask(self, description):
        """The block below its top face z = 0."""
        return lambda p: p[:, 2] <= 0.0

    def params_from(self, description):
        return SlotBlockParams.from_kwargs(**{k: (tuple(map(tuple, v)) if k == "slot_path" else v)
                                              for k, v in description["parameters"].items()})

    def derived_surfaces(self, description):
        """The block's four side faces (the JSON lists only its top and bottom), from its parameters."""
        return _block_sides(description) if "parameters" in description else []

    def bbox(self, description):
        p = description["parameters"]
        return np.array([0.0, 0.0, -p["block_height_z"]]), np.array([p["block_length_x"], p["block_width_y"], 0.0])

    def mesh(self, description):
        return None  # tessellated from the CAD (OCCT), or the STL written beside the JSON


PART = SlotBlock()
