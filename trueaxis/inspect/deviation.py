"""Signed deviations of a measured cloud from the part, and the alignments that put the cloud in the part frame.

Sign convention (DESIGN.md §7): a deviation is **positive where there is material outside the nominal surface**, i.e.
the measured point lies on the out-of-material side of the nominal surface (along its outward normal). Lengths are mm
inside the code; reports convert to um.

Two references, one rule:

- **Analytic surfaces** of the part JSON (``trueaxis.workpiece.parts``): cone, planes (annulus, box or wall-segment
  extents) and cylinders (slot arcs). Each point is assigned to its nearest *bounded* surface patch and its
  deviation is the exact signed distance to that patch. Surfaces a part's JSON does not list but its parameters
  define are added from ``Part.derived_surfaces`` (the slot block's four side faces, ``derived: true``) so that the
  datum alignment and points probed on the sides have an analytic reference too.
- **The CAD mesh**, through open3d's ``RaycastingScene.compute_closest_points``, where the JSON has no analytic
  surface: a point farther than ``gate_mm`` from every analytic patch is measured against the mesh as well, and the
  mesh wins when it is nearer by more than its chord error (a CAD face the JSON does not describe: a fillet, a
  chamfer, a user's own feature). With no analytic surfaces at all every point is measured against the mesh (the CLI
  refuses ``--cad`` without its JSON: the surfaces' ids and tolerances come from it). The mesh is fine enough that its chord error is below 0.1 um; the bound is stated with the mesh.

Meshes: a part that has its own mesh (``Part.mesh``) gives it: the NAS 979 part is meshed directly from its analytic
description (``trueaxis.workpiece.mesh``, numpy; the chord error is the sagitta ``R (1 - cos(dtheta / 2))`` of the
widest angular step on the base circle, every other face is planar). Any other part (the slot block) is tessellated
with OCCT (through cadquery) from its generator at an angular deflection that keeps the chord error on its 5 mm arcs
below 0.1 um; OCCT needs tens of seconds to mesh the cone to that tolerance, so it is not used for NAS 979 unless a
STEP file is given with ``--cad``. Nothing here branches on a part's name: what differs per part is the ``Part``'s
(``trueaxis.workpiece.part``: derived surfaces, mesh, chord bound, bounding box, datums).

Alignments (cloud -> part frame, a rigid motion ``x -> R x + t``):

- ``none``: the cloud is in the part frame already.
- ``bestfit``: point-to-plane ICP against the CAD: open3d's ``registration_icp`` (point-to-plane, target sampled
  on the CAD mesh with its triangle normals) for the coarse pose, then Gauss-Newton on the exact signed distances
  (analytic or mesh closest points, i.e. point-to-plane with exact feet) until the step is below 1e-12 mm. The
  motion it removed is reported (translations um, rotations urad): it hides whatever machine errors caused it.
  Directions the cloud cannot fix (rotation about the axis of a cone probed alone) are left at zero and named.
- ``datum``: a 3-2-1 frame from the part's datum features (``Part.datums``) measured in the cloud (least-squares
  planes): NAS 979, A = block bottom (3 points at least), B = a block side normal to X (xneg or xpos, 2 points), C = a
  block side normal to Y (yneg or ypos, 1 point); slot block, A = block top, B = front side (y = 0, or back y = W),
  C = left end (x = 0, or right end x = L). A missing datum is refused, naming it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..workpiece.mesh import (MAX_ASPECT, CadMesh, _axis_basis, _unit, cone_frustum_mesh,  # noqa: F401
                               nas979_mesh)
from ..workpiece.part import part_of
from .kernels import ON_AXIS_MM, cone_patch_distance

__all__ = [
    "InspectionError", "analytic_surfaces", "patch_distance", "SurfaceDeviation", "analytic_deviation",
    "CadMesh", "MAX_ASPECT", "cone_frustum_mesh", "nas979_mesh", "occ_mesh", "load_mesh_file", "part_mesh", "MeshDistance",
    "Deviation", "deviation", "part_bbox", "RigidMotion", "align_bestfit", "align_datum",
]

CHUNK = 250_000  # points per block in the patch-distance tables (memory: CHUNK x surfaces doubles)


class InspectionError(ValueError):
    """A cloud or part that cannot be inspected; the message is one line saying why."""


# ----------------------------------------------------------------------------------------------- analytic surfaces

def _known_part(part: dict):
    """The ``Part`` a part JSON describes, or None for a JSON of no known part."""
    try:
        return part_of(part)
    except ValueError:
        return None


def analytic_surfaces(part: dict) -> list[dict]:
    """The analytic surface patches of a part JSON, plus the slot block's derived side faces.

    part : the part JSON dict (``nas979_description``, ``slot_block_description`` or a file written by ``write_part``).
    Returns a list of surface dicts (see ``trueaxis.workpiece.parts``); the input is not modified.
    """
    surfaces = [dict(s) for s in part.get("surfaces", [])]
    known = {s["id"] for s in surfaces}
    the_part = _known_part(part)
    if the_part is not None:
        surfaces += [s for s in the_part.derived_surfaces(part) if s["id"] not in known]
    # a slot floor's region is the tool-centre path swept by a disk: attach the path so the patch can be bounded
    floors = {f["floor"]: f for f in part.get("features", []) if f.get("type") == "slot" and "floor" in f}
    for s in surfaces:
        if s["id"] in floors:
            feature = floors[s["id"]]
            s["swept_path_xy"] = [list(p[:2]) for p in feature["tool_centre_path"]]
            s["swept_radius"] = feature["nominal_width"] / 2
    for s in surfaces:
        if s.get("type") not in ("cone", "plane", "cylinder"):
            raise InspectionError(f"part JSON surface {s.get('id')!r} has unknown type {s.get('type')!r}")
    return surfaces


def _finish(points, foot, signed_offset, fallback_normal):
    """Signed distance to a clamped foot point: |p - foot| with the sign of the offset along the surface normal;
    the normal is the unit vector from the foot to the point (times the sign), or the surface normal at distance 0."""
    delta = points - foot
    unsigned = np.linalg.norm(delta, axis=1)
    sign = np.where(signed_offset >= 0, 1.0, -1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        normal = sign[:, None] * delta / unsigned[:, None]
    small = unsigned < 1e-12
    if small.any():
        normal[small] = np.broadcast_to(fallback_normal, points.shape)[small]
    return sign * unsigned, unsigned, normal


def _cone_patch(points, s):
    """Frustum patch: in the meridian half plane (h along the axis, rho from it) the generator is the segment from
    (h0, R - h0 tan a) to (h1, R - h1 tan a); the foot is the perpendicular foot clamped to it. Exact."""
    c = np.asarray(s["base_center"], float)
    a = _unit(s["axis"])
    alpha = math.radians(float(s["half_angle_deg"]))
    radius = float(s["base_radius"])
    h0, h1 = (float(v) for v in s.get("height_range", [0.0, radius / math.tan(alpha)]))
    ca, sa = math.cos(alpha), math.sin(alpha)
    # generator direction in (h, rho): g = (cos a, -sin a) (the radius shrinks with h); outward normal n = (sin a, cos a)
    r0 = radius - h0 * math.tan(alpha)
    points = np.ascontiguousarray(points, dtype=np.float64)
    n = len(points)
    signed, unsigned, normal = np.empty(n), np.empty(n), np.empty((n, 3))
    # one compiled pass per point (trueaxis.inspect.kernels): the numpy form of the same formulas made some twenty
    # temporary arrays and took 0.2 s of a million-point inspection
    cone_patch_distance(points, c, a, np.ascontiguousarray(_axis_basis(a)[0]), h0, r0, ca, sa, (h1 - h0) / ca,
                        signed, unsigned, normal)
    return signed, unsigned, normal


def _clamp_angle(phi, lo, hi):
    """Clamp angles phi (rad) into the arc [lo, hi] (rad, lo < hi <= lo + 2 pi) by circular distance."""
    rel = np.mod(phi - lo, 2 * np.pi)
    span = hi - lo
    inside = rel <= span
    to_hi = rel - span
    to_lo = 2 * np.pi - rel
    return np.where(inside, lo + rel, np.where(to_hi <= to_lo, hi, lo))


def _clamp_to_swept_disk(xy, path, radius):
    """Nearest points (m, 2) of the region swept by a disk of ``radius`` along the polyline ``path`` (P, 2)."""
    best = np.full(len(xy), np.inf)
    nearest = np.zeros_like(xy)
    for a, b in zip(path[:-1], path[1:]):
        d = b - a
        tau = np.clip(((xy - a) @ d) / (d @ d), 0.0, 1.0)
        q = a + tau[:, None] * d
        dist = np.linalg.norm(xy - q, axis=1)
        better = dist < best
        best = np.where(better, dist, best)
        nearest[better] = q[better]
    outside = best > radius
    out = xy.copy()
    out[outside] = nearest[outside] + (xy[outside] - nearest[outside]) * (radius / best[outside])[:, None]
    return out


def _plane_patch(points, s):
    """Plane patch with annulus (center, radius_range), box (x/y/z_range: exact for axis-aligned rectangles, the
    bounding box of a trapezoid side) or slot-wall (segment + z_range) extents; unbounded with none."""
    p0 = np.asarray(s["point"], float)
    n = _unit(s["normal"])
    offset = (points - p0) @ n
    foot = points - offset[:, None] * n
    if "radius_range" in s:
        centre = np.asarray(s.get("center", s["point"]), float)
        r0, r1 = s["radius_range"]
        r0 = 0.0 if r0 is None else float(r0)
        r1 = np.inf if r1 is None else float(r1)
        v = foot - centre
        r = np.linalg.norm(v, axis=1)
        rc = np.clip(r, r0, r1)
        # within ON_AXIS_MM of the centre the in-plane vector is rounding noise (not in the plane): the centre
        centre_hit = r <= ON_AXIS_MM
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(centre_hit, 0.0, rc / r)
        if r0 > 0 and np.any(centre_hit):  # the centre of an annulus: any direction to its inner circle
            u = _axis_basis(n)[0]
            v[centre_hit] = u
            scale[centre_hit] = r0
        foot = centre + v * scale[:, None]
    elif "swept_path_xy" in s:
        foot = foot.copy()
        foot[:, :2] = _clamp_to_swept_disk(foot[:, :2], np.asarray(s["swept_path_xy"], float),
                                           float(s["swept_radius"]))
    elif "segment" in s:
        a = np.asarray(s["segment"]["start"], float)
        b = np.asarray(s["segment"]["end"], float)
        d = b - a
        tau = np.clip(((foot[:, :2] - a) @ d) / (d @ d), 0.0, 1.0)
        foot = foot.copy()
        foot[:, :2] = a + tau[:, None] * d
    else:
        foot = foot.copy()
    for k, key in enumerate(("x_range", "y_range", "z_range")):
        if key in s:
            lo, hi = s[key]
            foot[:, k] = np.clip(foot[:, k], -np.inf if lo is None else lo, np.inf if hi is None else hi)
    return _finish(points, foot, offset, n)


def _cylinder_patch(points, s):
    """Cylinder patch about a Z-parallel axis (slot arcs), with angle_range_deg and z_range extents. A concave wall
    ("normal_sense": "towards_axis") has its material outside the radius: the deviation is radius - r there."""
    centre = np.asarray(s["center"], float)[:2]
    radius = float(s["radius"])
    towards = s.get("normal_sense", "away_from_axis") == "towards_axis"
    xy = points[:, :2] - centre
    r = np.hypot(xy[:, 0], xy[:, 1])
    phi = np.arctan2(xy[:, 1], xy[:, 0])
    if "angle_range_deg" in s:
        lo, hi = np.radians(s["angle_range_deg"])
        phi_c = _clamp_angle(phi, lo, hi)
    else:
        phi_c = phi
    z = points[:, 2]
    if "z_range" in s:
        z = np.clip(z, *s["z_range"])
    radial = np.column_stack([np.cos(phi_c), np.sin(phi_c), np.zeros(len(points))])
    foot = np.column_stack([centre + radius * radial[:, :2], z])
    offset = (radius - r) if towards else (r - radius)
    return _finish(points, foot, offset, -radial if towards else radial)


_PATCHES = {"cone": _cone_patch, "plane": _plane_patch, "cylinder": _cylinder_patch}


def patch_distance(points, surface: dict):
    """Exact signed distance of points to one bounded analytic surface patch.

    points : (n, 3) float, mm, part frame. surface : a surface dict of the part JSON.
    Returns (signed (n,) mm, + on the out-of-material side; unsigned (n,) mm; normal (n, 3) unit, the gradient of the
    signed distance: the outward surface normal for a foot inside the patch, the direction from the clamped foot
    otherwise).
    """
    points = np.asarray(points, dtype=np.float64)
    return _PATCHES[surface["type"]](points, surface)


@dataclass(frozen=True)
class SurfaceDeviation:
    """Deviations from the nearest analytic patch.

    deviation_mm : (n,) signed, + = material outside the nominal surface
    distance_mm : (n,) unsigned distance to that patch (= |deviation_mm|)
    normal : (n, 3) unit gradient of the signed distance (outward normal at the foot)
    surface : (n,) int, index into surface_ids of each point's nearest patch
    surface_ids : list of str
    """

    deviation_mm: np.ndarray
    distance_mm: np.ndarray
    normal: np.ndarray
    surface: np.ndarray
    surface_ids: list


def _lower_bound(points, surface: dict):
    """A lower bound of the distance of each point to a bounded patch, cheaper than the distance itself: the
    distance to the patch's unbounded plane (|offset along the normal|) or cylinder (|r - radius|); None for a cone
    (measured in full)."""
    if surface["type"] == "plane":
        # p . n - p0 . n: one product over the points, no (n, 3) temporary (a bound: rounding is harmless here)
        normal = _unit(surface["normal"])
        return np.abs(points @ normal - float(np.asarray(surface["point"], float) @ normal))
    if surface["type"] == "cylinder":
        xy = points[:, :2] - np.asarray(surface["center"], float)[:2]
        return np.abs(np.hypot(xy[:, 0], xy[:, 1]) - float(surface["radius"]))
    return None


def analytic_deviation(points, surfaces: list[dict]) -> SurfaceDeviation:
    """Signed deviation of each point from its nearest analytic surface patch (exact).

    points : (n, 3) float, mm, part frame. surfaces : list of surface dicts (``analytic_surfaces``), at least one.
    Ties between patches (a point on a shared edge) go to the first listed. Vectorised over points and surfaces, in
    blocks of ``CHUNK`` points; a patch is measured only at the points its unbounded surface could win
    (:func:`_lower_bound`).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {points.shape}")
    if not surfaces:
        raise ValueError("no analytic surfaces to measure against")
    n = len(points)
    deviation_mm = np.empty(n)
    distance_mm = np.empty(n)
    normal = np.empty((n, 3))
    surface = np.empty(n, dtype=np.int64)
    for start in range(0, n, CHUNK):
        block = points[start:start + CHUNK]
        best_d = np.full(len(block), np.inf)
        best_s = np.zeros(len(block))
        best_n = np.zeros((len(block), 3))
        best_i = np.zeros(len(block), dtype=np.int64)
        for k, s in enumerate(surfaces):
            # a patch lies no nearer than its unbounded surface: where that bound is no better than the nearest
            # patch so far, the patch cannot win (ties go to the first listed), so only the others are measured
            bound = _lower_bound(block, s)
            rows = np.flatnonzero(bound < best_d) if bound is not None else slice(None)
            signed, unsigned, nrm = patch_distance(block[rows], s)
            better = unsigned < best_d[rows]
            take = rows[better] if bound is not None else np.flatnonzero(better)
            best_d[take], best_s[take], best_n[take], best_i[take] = unsigned[better], signed[better], nrm[better], k
        sl = slice(start, start + len(block))
        deviation_mm[sl], distance_mm[sl], normal[sl], surface[sl] = best_s, best_d, best_n, best_i
    return SurfaceDeviation(deviation_mm, distance_mm, normal, surface, [s["id"] for s in surfaces])


# ------------------------------------------------------------------------------------------------------------ meshes

def occ_mesh(shape, linear_mm: float, angular_rad: float, source: str) -> CadMesh:
    """Tessellate a cadquery Shape with OCCT (absolute linear deflection, angular deflection). The chord error is
    OCCT's linear deflection unless the caller measures a tighter bound."""
    vertices, triangles = shape.tessellate(linear_mm, angular_rad)
    vertices = np.array([v.toTuple() for v in vertices], dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    mesh = CadMesh(vertices, triangles, linear_mm, source, f"OCCT linear deflection {linear_mm:g} mm")
    return _outward(mesh)


def _outward(mesh: CadMesh) -> CadMesh:
    """Turn a consistently wound closed mesh outwards (positive signed volume)."""
    tri = mesh.vertices[mesh.triangles]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    if volume < 0:
        return CadMesh(mesh.vertices, mesh.triangles[:, [0, 2, 1]], mesh.chord_error_mm, mesh.source, mesh.note)
    return mesh


def _measured_chord_bound(mesh: CadMesh, part: dict) -> tuple[float, str] | None:
    """The chord error of a mesh of one of our parts, measured on its curved faces (``Part.stl_chord_bound``)."""
    the_part = _known_part(part)
    if the_part is None:
        return None
    try:
        bound, span, _ = the_part.stl_chord_bound(mesh.vertices, mesh.triangles, the_part.params_from(part), part)
    except (KeyError, StopIteration, ValueError):
        return None
    if span == 0.0:
        return None  # no triangle matched the part's curved faces: not this part's mesh
    return bound, f"measured on the mesh's curved faces: widest angular span {span:.3e} rad"


def load_mesh_file(path, part: dict | None = None, linear_mm: float = 1e-3, angular_rad: float = 0.004) -> CadMesh:
    """The CAD of a part from a file: STEP (.step/.stp, tessellated with OCCT) or a mesh (.stl/.ply/.obj, read with
    trimesh, vertices merged). The chord error is measured on the curved faces of our parts when ``part`` is given;
    otherwise it is OCCT's deflection (STEP) or unknown (mesh files).

    The default angular deflection 0.004 rad keeps the sagitta below 0.1 um on radii up to 50 mm; OCCT takes tens of
    seconds for the NAS 979 cone at this setting.
    """
    path = Path(path)
    if not path.is_file():
        raise InspectionError(f"{path}: no such CAD file")
    ext = path.suffix.lower()
    if ext in (".step", ".stp"):
        import cadquery as cq

        try:
            shape = cq.importers.importStep(str(path)).val()
        except Exception as exc:  # OCCT raises its own types; one line is enough for the user
            raise InspectionError(f"{path}: cannot read the STEP file ({type(exc).__name__})") from exc
        mesh = occ_mesh(shape, linear_mm, angular_rad, str(path))
    elif ext in (".stl", ".ply", ".obj"):
        import trimesh

        try:
            loaded = trimesh.load_mesh(str(path), process=True)
        except Exception as exc:
            raise InspectionError(f"{path}: cannot read the mesh ({type(exc).__name__}: {exc})") from exc
        if not hasattr(loaded, "faces") or len(loaded.faces) == 0:
            raise InspectionError(f"{path}: the file holds no triangles")
        mesh = _outward(CadMesh(np.asarray(loaded.vertices, float), np.asarray(loaded.faces, np.int64), None,
                                str(path), "chord error not stated by the file"))
    else:
        raise InspectionError(f"{path}: unknown CAD extension {path.suffix!r} (expected .step, .stp, .stl, .ply, .obj)")
    if part is not None:
        measured = _measured_chord_bound(mesh, part)
        if measured is not None:
            mesh = CadMesh(mesh.vertices, mesh.triangles, measured[0], mesh.source, measured[1])
    return mesh


def part_mesh(part: dict, part_dir=None) -> CadMesh:
    """The CAD mesh of a part JSON, chord error below 0.1 um.

    The part's own mesh (``Part.mesh``: NAS 979 is meshed from its JSON) when it has one; else ``part_dir/<part>.stl``
    when it exists and its stated chord error bound is below 0.1 um, else the generator's solid tessellated with OCCT
    (linear 1e-3 mm, angular 0.01 rad: the sagitta on the slot block's 5 mm arcs is 0.06 um), chord error measured
    on the curved faces.
    """
    the_part = _known_part(part)
    if the_part is None:
        raise InspectionError(f"no CAD mesh for part {part.get('part')!r}")
    own = the_part.mesh(part)
    if own is not None:
        return own
    stl = Path(part_dir) / f"{the_part.name}.stl" if part_dir is not None else None
    bound = part.get("stl", {}).get("chord_error_bound_mm")
    if stl is not None and stl.is_file() and bound is not None and bound < 1e-4:
        mesh = load_mesh_file(stl, part)
        return mesh
    mesh = occ_mesh(the_part.build(the_part.params_from(part)).val(), 1e-3, 0.01,
                    f"{the_part.title} generator (OCCT tessellation)")
    measured = _measured_chord_bound(mesh, part)
    if measured is not None:
        mesh = CadMesh(mesh.vertices, mesh.triangles, measured[0], mesh.source, measured[1])
    return mesh


class MeshDistance:
    """Signed distances to a CAD mesh through open3d's ``RaycastingScene`` (Embree BVH, float32).

    The closest point on the mesh comes from ``compute_closest_points``; the distance |p - closest| is then taken in
    float64 about a local origin (the mesh's bounding-box centre, so float32 rounding stays below 0.01 um on a
    100 mm part), and its sign is that of (p - closest) . n with n the closest triangle's outward normal (consistent
    at convex and concave edges, where p - closest lies in the edges' normal cone).
    """

    def __init__(self, mesh: CadMesh):
        import open3d as o3d

        self.mesh = mesh
        self.origin = (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
        local = (mesh.vertices - self.origin).astype(np.float32)
        tmesh = o3d.t.geometry.TriangleMesh()
        tmesh.vertex.positions = o3d.core.Tensor(local)
        tmesh.triangle.indices = o3d.core.Tensor(mesh.triangles.astype(np.int32))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(tmesh)
        tri = mesh.vertices[mesh.triangles]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.triangle_normals = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)

    def signed_distance(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """points (n, 3) mm -> (signed distance (n,) mm, + outside; unit gradient (n, 3); closest triangle (n,))."""
        import open3d as o3d

        local = np.asarray(points, dtype=np.float64) - self.origin
        answer = self.scene.compute_closest_points(o3d.core.Tensor(local.astype(np.float32)))
        closest = answer["points"].numpy().astype(np.float64)
        triangle = answer["primitive_ids"].numpy().astype(np.int64)
        delta = local - closest
        unsigned = np.linalg.norm(delta, axis=1)
        n_tri = self.triangle_normals[triangle]
        sign = np.where(np.einsum("ij,ij->i", delta, n_tri) >= 0, 1.0, -1.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            gradient = sign[:, None] * delta / unsigned[:, None]
        small = unsigned < 1e-9
        gradient[small] = n_tri[small]
        return sign * unsigned, gradient, triangle


# ------------------------------------------------------------------------------------------------ combined deviation

@dataclass(frozen=True)
class Deviation:
    """Deviation of each point from the part.

    deviation_mm : (n,) signed, + = material outside the nominal surface
    normal : (n, 3) unit outward normal at the foot (gradient of the signed distance)
    surface : (n,) int, index into surface_ids of the analytic patch the point is assigned to; -1 = the CAD mesh
    surface_ids : list of str
    from_mesh : (n,) bool, the deviation came from the CAD mesh
    chord_error_mm : float or None, the mesh's chord error (bounds the error of the mesh-based deviations)
    """

    deviation_mm: np.ndarray
    normal: np.ndarray
    surface: np.ndarray
    surface_ids: list
    from_mesh: np.ndarray
    chord_error_mm: float | None = None

    @property
    def deviation_um(self) -> np.ndarray:
        return self.deviation_mm * 1e3


def deviation(points, surfaces: list[dict], mesh: MeshDistance | None = None, gate_mm: float = 0.5,
              mesh_for=None) -> Deviation:
    """Signed deviation of each point from the part: analytic where the JSON describes the surface, the CAD mesh
    where it does not (see the module docstring for the rule).

    points : (n, 3) float, mm, part frame. surfaces : analytic patches (may be empty: then mesh only).
    mesh : MeshDistance or None; a callable returning one (built lazily, only when a point needs it) is accepted too.
    gate_mm : points nearer than this to an analytic patch are taken as on it without consulting the mesh.
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    if surfaces:
        ana = analytic_deviation(points, surfaces)
        dev, nrm, surf = ana.deviation_mm.copy(), ana.normal.copy(), ana.surface.copy()
        far = ana.distance_mm > gate_mm
        ids = ana.surface_ids
    else:
        dev, nrm, surf = np.full(n, np.inf), np.zeros((n, 3)), np.full(n, -1)
        far = np.ones(n, dtype=bool)
        ids = []
    from_mesh = np.zeros(n, dtype=bool)
    chord = None
    if far.any():
        if callable(mesh) and not isinstance(mesh, MeshDistance):
            mesh = mesh()
        if mesh is None:
            if not surfaces:
                raise InspectionError("no analytic surfaces and no CAD mesh to measure against")
        else:
            chord = mesh.mesh.chord_error_mm
            d_mesh, g_mesh, _ = mesh.signed_distance(points[far])
            slack = (chord or 0.0) + 1e-4
            nearer = np.abs(d_mesh) < np.abs(dev[far]) - slack
            idx = np.flatnonzero(far)[nearer]
            dev[idx], nrm[idx], surf[idx] = d_mesh[nearer], g_mesh[nearer], -1
            from_mesh[idx] = True
    elif isinstance(mesh, MeshDistance):
        chord = mesh.mesh.chord_error_mm
    return Deviation(dev, nrm, surf, ids, from_mesh, chord)


def part_bbox(part: dict) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounding box (min (3,), max (3,)) of a part in its frame, mm, from its JSON (``Part.bbox``)."""
    the_part = _known_part(part)
    if the_part is None:
        raise InspectionError(f"unknown part {part.get('part')!r}")
    return the_part.bbox(part)


# -------------------------------------------------------------------------------------------------------- alignment

@dataclass(frozen=True)
class RigidMotion:
    """A rigid motion x -> rotation @ x + translation (cloud -> part frame).

    rotation : (3, 3) proper orthogonal. translation : (3,) mm, the motion of the part origin.
    not_determined : descriptions of directions the data could not fix (left at zero).
    method : "none" | "bestfit" | "datum". info : extra figures (iterations, residuals, datums used).
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    method: str = "none"
    not_determined: list = field(default_factory=list)
    info: dict = field(default_factory=dict)

    def apply(self, points) -> np.ndarray:
        """points (n, 3) mm -> (n, 3) mm."""
        return np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    def rotate(self, vectors) -> np.ndarray:
        return np.asarray(vectors, dtype=np.float64) @ self.rotation.T

    @property
    def rotation_urad(self) -> np.ndarray:
        """(3,) rotation vector (axis times angle) of the motion, urad, part frame."""
        if np.array_equal(self.rotation, np.eye(3)):
            return np.zeros(3)  # no rotation (no alignment): without scipy.spatial's import (0.3 s)
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(self.rotation).as_rotvec() * 1e6

    @property
    def translation_um(self) -> np.ndarray:
        return self.translation * 1e3

    def as_dict(self) -> dict:
        return {
            "method": self.method,
            "applied_as": "x_part = R x_cloud + t; t is the motion of the part origin",
            "translation_um": [float(v) for v in self.translation_um],
            "rotation_urad": [float(v) for v in self.rotation_urad],
            "rotation_note": "rotation vector (axis times angle) about the part origin, part frame",
            "not_determined": list(self.not_determined),
            **self.info,
        }


def _small_rotation(omega) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(omega, dtype=np.float64)).as_matrix()


def _describe_null(direction: np.ndarray, centre: np.ndarray, scale: float) -> str:
    """A (6,) null direction (dt, domega * scale) of the centred problem, as words: a rotation about a line or a
    translation."""
    dt, dw = direction[:3], direction[3:] / scale
    if np.linalg.norm(dw) * scale > 0.5 * np.linalg.norm(direction):
        axis = dw / np.linalg.norm(dw)
        if axis[np.argmax(np.abs(axis))] < 0:
            axis, dw, dt = -axis, -dw, -dt
        # a rotation about a line through p0: dt = -dw x (p0 - centre) -> the point of the line nearest the centre
        p0 = centre + np.cross(dw, dt) / (dw @ dw)
        return f"rotation about the line through {_triple(p0, 3)} mm along {_triple(axis, 4)}"
    return f"translation along {_triple(dt / np.linalg.norm(dt), 4)}"


def _triple(v, decimals: int) -> str:
    """'(x, y, z)' at the given decimals, with no '-0.000' (rounding first, then adding 0.0 turns -0.0 into 0.0)."""
    r = np.round(np.asarray(v, float), decimals) + 0.0
    return "(" + ", ".join(f"{x:.{decimals}f}" for x in r) + ")"


def _icp_coarse(points, mesh: CadMesh, max_distance_mm: float, samples: int = 200_000) -> np.ndarray:
    """open3d point-to-plane ICP of the cloud onto points sampled on the CAD mesh (with triangle normals).
    Returns the (4, 4) transform cloud -> part."""
    import open3d as o3d

    legacy = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                       o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    legacy.compute_triangle_normals()
    target = legacy.sample_points_uniformly(number_of_points=samples, use_triangle_normal=True)
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    result = o3d.pipelines.registration.registration_icp(
        source, target, max_distance_mm, np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50))
    return np.asarray(result.transformation)


def align_bestfit(points, surfaces: list[dict], mesh: MeshDistance | None, cad: CadMesh | None = None,
                  max_distance_mm: float = 2.0, iterations: int = 30, rank_tolerance: float = 1e-6) -> RigidMotion:
    """Best-fit rigid motion of the cloud onto the part: minimise the sum of squared signed distances.

    Method: point-to-plane ICP (Chen & Medioni, "Object modelling by registration of multiple range images", Image
    Vision Comput. 10 (1992)): open3d's ``registration_icp`` against points sampled on the CAD mesh gives the coarse
    pose (its plane at a sampled point departs from the surface by the curvature times the sample spacing squared, so
    it stops near 0.1 um); Gauss-Newton on the exact signed distances (``deviation``: feet on the analytic patches or
    on the fine mesh) finishes: with d_i(x) the signed distance and n_i its gradient, a small motion (dt, dw) about the
    cloud's centroid changes d_i by n_i . dt + (q_i x n_i) . dw. Directions whose singular value is below
    ``rank_tolerance`` times the largest (of the scaled Jacobian) are not moved and are named in ``not_determined``.

    points : (n, 3) mm. surfaces : analytic patches. mesh : MeshDistance for the exact distances (and the coarse ICP,
    through ``cad``). Returns the RigidMotion cloud -> part.
    """
    points = np.asarray(points, dtype=np.float64)
    rotation, translation = np.eye(3), np.zeros(3)
    coarse = None
    if cad is not None:
        coarse = _icp_coarse(points, cad, max_distance_mm)
        rotation, translation = coarse[:3, :3].copy(), coarse[:3, 3].copy()
    centre = points.mean(axis=0)
    scale = float(np.sqrt(((points - centre) ** 2).sum(axis=1).mean())) or 1.0

    def gauss_newton(rotation, translation):
        null = np.zeros((0, 6))
        steps = 0
        for steps in range(1, iterations + 1):
            moved = points @ rotation.T + translation
            dev = deviation(moved, surfaces, mesh)
            c_now = moved.mean(axis=0)
            arm = moved - c_now
            # columns: translation (mm) and rotation scaled by the cloud's size so both are mm of surface motion
            jac = np.column_stack([dev.normal, np.cross(arm, dev.normal) / scale])
            u, sing, vt = np.linalg.svd(jac, full_matrices=False)
            keep = sing > rank_tolerance * sing[0]
            step = vt[keep].T @ ((u[:, keep].T @ -dev.deviation_mm) / sing[keep])
            dt, dw = step[:3], step[3:] / scale
            small = _small_rotation(dw)
            # rotate about the current centroid, then translate
            rotation = small @ rotation
            translation = small @ (translation - c_now) + c_now + dt
            null = vt[~keep]
            null_centre = c_now
            if np.linalg.norm(dt) < 1e-12 and np.linalg.norm(dw) * scale < 1e-12:
                break
        return rotation, translation, null, null_centre, steps

    rotation, translation, null, null_centre, steps = gauss_newton(rotation, translation)
    null_text = [_describe_null(v, null_centre, scale) for v in null]
    if len(null):
        # the coarse ICP may have wandered along a direction the data cannot see (a cone turned about its axis):
        # take that component out of the motion, so the report shows only what the cloud determines, then let
        # Gauss-Newton (whose steps stay out of those directions) take up the second-order remainder
        from scipy.spatial.transform import Rotation

        c_now = (points @ rotation.T + translation).mean(axis=0)
        omega = Rotation.from_matrix(rotation).as_rotvec()
        motion = np.r_[c_now - centre, omega * scale]
        motion -= null.T @ (null @ motion)
        rotation = _small_rotation(motion[3:] / scale)
        translation = centre + motion[:3] - rotation @ centre
        rotation, translation, _, _, more = gauss_newton(rotation, translation)
        steps += more
    rms = float(np.sqrt(np.mean(deviation(points @ rotation.T + translation, surfaces, mesh).deviation_mm ** 2)))
    info = {"iterations": steps, "rms_after_um": rms * 1e3,
            "coarse": "open3d registration_icp point-to-plane" if coarse is not None else "none",
            "note": "the best fit removes this rigid motion from the deviations; machine errors that move the part "
                    "rigidly (offsets, squareness seen as tilts) are hidden by it: read them here"}
    return RigidMotion(rotation, translation, "bestfit", null_text, info)


def align_datum(points, part: dict, surfaces: list[dict], gate_mm: float = 1.0) -> RigidMotion:
    """3-2-1 alignment on the part's datum planes measured in the cloud (``Part.datums``).

    Points within ``gate_mm`` of a datum patch (the cloud roughly in the part frame) are that datum's. Datum A is
    the least-squares plane of its points; B the least-squares plane of its points constrained normal to A; C the
    least-squares offset of its points along the direction normal to A and B. The measured frame (normals and the
    corner where the three planes meet) is moved onto the nominal one. Raises InspectionError naming missing datums.
    """
    from .form import fit_plane

    points = np.asarray(points, dtype=np.float64)
    the_part = _known_part(part)
    plan = the_part.datums if the_part is not None else None
    if not plan:
        raise InspectionError(f"no datum scheme for part {part.get('part')!r}")
    by_id = {s["id"]: s for s in surfaces}
    ana = analytic_deviation(points, surfaces)
    counts = {sid: int(np.sum((ana.surface == k) & (ana.distance_mm <= gate_mm)))
              for k, sid in enumerate(ana.surface_ids)}
    chosen, missing = [], []
    for label, candidates, minimum in plan:
        present = [c for c in candidates if c in by_id]
        best = max(present, key=lambda c: counts.get(c, 0)) if present else None
        if best is None or counts.get(best, 0) < minimum:
            have = ", ".join(f"{c}: {counts.get(c, 0)}" for c in candidates)
            missing.append(f"datum {label} ({' or '.join(candidates)}; needs {minimum} points, has {have})")
        else:
            chosen.append((label, best))
    if missing:
        probed = ", ".join(f"{sid} ({n})" for sid, n in counts.items() if n) or "none"
        raise InspectionError("datum alignment: missing " + "; ".join(missing) + f"; surfaces probed: {probed}")
    sets = {label: points[(ana.surface == ana.surface_ids.index(sid)) & (ana.distance_mm <= gate_mm)]
            for label, sid in chosen}
    nominal_n = {label: _unit(by_id[sid]["normal"]) for label, sid in chosen}
    nominal_p = {label: np.asarray(by_id[sid]["point"], float) for label, sid in chosen}

    try:
        plane_a = fit_plane(sets["A"])
    except ValueError as exc:
        raise InspectionError(f"datum alignment: datum A points do not span a plane ({exc})") from None
    e3 = plane_a.normal * np.sign(plane_a.normal @ nominal_n["A"])
    n_b = nominal_n["B"]
    if len(sets["B"]) >= 3:
        try:
            n_b = fit_plane(sets["B"]).normal
        except ValueError:
            # collinear B points (one probing line): the plane holds that line and is normal to A
            direction = np.linalg.svd(sets["B"] - sets["B"].mean(axis=0))[2][0]
            n_b = np.cross(direction, e3)
    else:
        direction = sets["B"][-1] - sets["B"][0]
        n_b = np.cross(direction / max(np.linalg.norm(direction), 1e-300), e3)
    n_b = n_b * np.sign(n_b @ nominal_n["B"])
    e1 = n_b - (n_b @ e3) * e3
    if not np.linalg.norm(e1) > 1e-6:  # n_b is a unit vector, or the sine of B's line's angle to A's normal
        # B's points on a line along A's normal (one above the other), or a B plane parallel to A: the rotation
        # about A's normal is not fixed (refused here, where it would be a singular matrix)
        raise InspectionError("datum alignment: datum B's points do not fix the rotation about datum A's normal "
                              "(they lie on a line normal to datum A, or on a plane parallel to it): probe datum B "
                              "at points apart along the face, not one above the other")
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e3, e1)
    s_c = np.sign(e2 @ nominal_n["C"])
    measured_axes = np.column_stack([e1, e2 * s_c, e3])
    # nominal frame from the nominal normals (orthogonal for both parts)
    E3 = nominal_n["A"]
    E1 = nominal_n["B"] - (nominal_n["B"] @ E3) * E3
    E1 /= np.linalg.norm(E1)
    E2 = np.cross(E3, E1) * np.sign(np.cross(E3, E1) @ nominal_n["C"])
    nominal_axes = np.column_stack([E1, E2, E3])
    rotation = nominal_axes @ measured_axes.T
    # corner: the point on all three measured planes (offsets = mean of each datum's points along its direction)
    m_dirs = np.vstack([e3, e1, e2 * s_c])
    m_offsets = np.array([sets["A"].mean(axis=0) @ e3, sets["B"].mean(axis=0) @ e1,
                          sets["C"].mean(axis=0) @ (e2 * s_c)])
    corner = np.linalg.solve(m_dirs, m_offsets)
    n_dirs = np.vstack([E3, E1, E2])
    n_offsets = np.array([nominal_p["A"] @ E3, nominal_p["B"] @ E1, nominal_p["C"] @ E2])
    nominal_corner = np.linalg.solve(n_dirs, n_offsets)
    translation = nominal_corner - rotation @ corner
    info = {"datums": [{"label": label, "surface": sid, "points": int(len(sets[label]))} for label, sid in chosen],
            "datum_A_flatness_um": float(np.ptp(plane_a.residuals) * 1e3),
            "note": "3-2-1: A = least-squares plane, B = least-squares plane normal to A, C = least-squares offset"}
    return RigidMotion(rotation, translation, "datum", [], info)


NORMAL_DEPARTURE_DEG = 5.0  # a cloud's own normal further than this from the part's is counted in what is said


def nominal_normals(points, part: dict, cloud_normals=None) -> tuple[np.ndarray, dict | None]:
    """The part's unit outward normals at the points (its nearest analytic patch's, at the foot point), and what the
    cloud's own normals were against them.

    The deviation is measured along the part's normal, and the model (identification, diagnosis) projects the
    machine's error on it: a cloud's own normals are not used. Estimated or exported normals scatter by degrees, a
    CMM may export its probe's approach direction, a colour column may be read as a normal: taken as given, 1.4 deg of
    scatter turned an accepted identification into a refusal, 3.6 deg into "no change", exit 0 (QA pass).

    points : (N, 3) part frame, mm. part : the part JSON dict. cloud_normals : (N, 3) or None.
    Returns (normals (N, 3), None when the cloud has no normals, else {"given": N, "inward": how many point into the
    part, "departed": how many lie further than NORMAL_DEPARTURE_DEG from the part's either way round,
    "largest_deg": the largest such angle}).
    """
    nominal = analytic_deviation(points, analytic_surfaces(part)).normal
    if cloud_normals is None:
        return nominal, None
    given = np.asarray(cloud_normals, dtype=np.float64)
    length = np.linalg.norm(given, axis=1)
    cos = np.einsum("ij,ij->i", given, nominal) / np.where(length > 0, length, 1.0)
    cos = np.where(length > 0, cos, 0.0)  # (a zero normal: at right angles, counted)
    angle = np.degrees(np.arccos(np.clip(np.abs(cos), 0.0, 1.0)))  # either way round
    return nominal, {"given": int(len(given)), "inward": int(np.count_nonzero(cos < 0)),
                     "departed": int(np.count_nonzero(angle > NORMAL_DEPARTURE_DEG)),
                     "largest_deg": float(angle.max(initial=0.0))}


def cloud_normals_note(info: dict | None) -> str | None:
    """One sentence on a cloud's own normals (``nominal_normals``' dict), None when it has none."""
    if info is None:
        return None
    said = [f"{info['inward']} point into the part"] if info["inward"] else []
    if info["departed"]:
        said.append(f"{info['departed']} lie more than {NORMAL_DEPARTURE_DEG:g} deg from the part's, the largest "
                    f"{info['largest_deg']:.1f} deg")
    return (f"the cloud's own {info['given']} normals are not used, the part's are" +
            (f" ({'; '.join(said)})" if said else ""))
