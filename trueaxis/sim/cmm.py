"""The virtual CMM: probing patterns on the test parts, probe noise, the measured cloud and its truth sidecar.

Probing patterns come from the part JSON (``trueaxis.workpiece.parts``):

- ``nas979``: rings at heights along the cone axis (``cone_surface_points``), evenly spaced between ``margin_mm``
  above the base and below the top, about as many rings as points per unit of circumference;
- ``slots``: lines along every slot wall (planes) and corner/end arc at three depths (1/4, 1/2, 3/4 of the depth), and
  lines along the floor under the tool-centre path (at 0 and +-R/2 across it), points shared by length.

A measured point is the nominal point moved along its outward normal by the simulated deviation plus probe noise:
x = x0 + (s* + e) n, e ~ N(0, sigma^2) (seeded). The cloud is PLY in the part frame (x y z nx ny nz, mm), written with
``trueaxis.inspect.cloud.write_cloud_ply`` (atomic). The sidecar ``<name>.truth.json`` holds what produced it (true
machine file, effects, seed, noise, per-point cut time and block) for tests only: no product code path reads it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..fileio import atomic_write
from ..workpiece.parts import cone_surface_points


def _surface(part: dict, sid: str) -> dict:
    for s in part["surfaces"]:
        if s["id"] == sid:
            return s
    raise ValueError(f"part JSON has no surface {sid!r}")


def cone_pattern(part: dict, n_points: int, margin_mm: float = 1.0):
    """Rings on the NAS 979 cone: points (N, 3) mm and unit outward normals (N, 3), part frame."""
    cone = _surface(part, "cone")
    h0, h1 = cone["height_range"]
    if not 0 <= 2 * margin_mm < h1 - h0:
        raise ValueError(f"margin_mm {margin_mm} leaves no height to probe on the cone ({h0}-{h1} mm)")
    r_mid = 0.5 * (cone["base_radius"] + cone["top_radius"])
    span = h1 - h0 - 2 * margin_mm
    n_rings = max(1, int(round(math.sqrt(n_points * span / (2 * math.pi * r_mid)))))
    per_ring = max(1, n_points // n_rings)
    heights = np.linspace(h0 + margin_mm, h1 - margin_mm, n_rings) if n_rings > 1 else np.array([0.5 * (h0 + h1)])
    return cone_surface_points(cone, heights, per_ring)


def slot_pattern(part: dict, n_points: int, margin_mm: float = 0.5, floor_offsets=(-0.5, 0.0, 0.5)):
    """Lines on the slot walls, arcs and floors: points (N, 3) mm, unit outward normals (N, 3), part frame."""
    pieces = []  # (length, sampler)
    for feat in part["features"]:
        if feat.get("type") != "slot":
            continue
        depth = feat["nominal_depth"]
        zs = [-depth * f for f in (0.25, 0.5, 0.75)]
        for wid in feat["walls"]:
            s = _surface(part, wid)
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
            s = _surface(part, aid)
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


def probe_pattern(part: dict, n_points: int):
    """Probing pattern of a part JSON (``part["part"]`` is "nas979" or "slots")."""
    if n_points < 1:
        raise ValueError(f"points must be >= 1, got {n_points}")
    kind = part.get("part")
    if kind == "nas979":
        return cone_pattern(part, n_points)
    if kind == "slots":
        return slot_pattern(part, n_points)
    raise ValueError(f"unknown part {kind!r}: expected 'nas979' or 'slots'")


def measure(points, normals, deviation_um, noise_um: float = 0.0, seed: int = 0):
    """Measured points (N, 3) mm: x0 + (s* + e) n with e ~ N(0, noise_um^2) um; and the noise drawn (N,) um."""
    if noise_um < 0:
        raise ValueError(f"noise_um must be >= 0, got {noise_um}")
    rng = np.random.default_rng(seed)
    e = rng.normal(0.0, noise_um, size=len(points)) if noise_um > 0 else np.zeros(len(points))
    return points + ((np.asarray(deviation_um) + e) * 1e-3)[:, None] * normals, e


def truth_path(ply_path) -> Path:
    """``x/cmm.ply`` -> ``x/cmm.truth.json``."""
    p = Path(ply_path)
    return p.with_name(p.stem + ".truth.json")


def write_json_atomic(path, data: dict) -> None:
    """Write ``data`` as indented JSON, atomically (``trueaxis.fileio.atomic_write``)."""
    atomic_write(path, json.dumps(data, indent=1) + "\n")
