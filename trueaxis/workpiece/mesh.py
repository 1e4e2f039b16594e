"""Meshes of the parts: ``CadMesh`` (a closed outward mesh with its chord error) and the NAS 979 part meshed from
its JSON with numpy (chord error bounded analytically), fast where OCCT needs tens of seconds for the same bound.

The inspection measures points against these meshes where the part JSON has no analytic surface
(``trueaxis.inspect.deviation``); a part supplies its own mesh through ``Part.mesh`` or is tessellated from its CAD.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .parts import _axis_basis


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    return v / np.linalg.norm(v)


@dataclass(frozen=True)
class CadMesh:
    """A closed triangle mesh of the part, outward-facing triangles (counter-clockwise seen from outside).

    vertices : (V, 3) float64, mm, part frame
    triangles : (T, 3) int64 vertex indices
    chord_error_mm : float or None, largest distance between the mesh and the CAD surface (None: not known)
    source : str, where the mesh came from
    note : str, how the chord error was bounded
    """

    vertices: np.ndarray
    triangles: np.ndarray
    chord_error_mm: float | None
    source: str
    note: str = ""

    def write_ply(self, path) -> None:
        """Binary little-endian PLY (double vertices, int faces), for CloudCompare and viewers."""
        header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(self.vertices)}\n"
                  "property double x\nproperty double y\nproperty double z\n"
                  f"element face {len(self.triangles)}\nproperty list uchar int vertex_indices\nend_header\n")
        faces = np.zeros(len(self.triangles), dtype=[("n", "u1"), ("v", "<i4", (3,))])
        faces["n"] = 3
        faces["v"] = self.triangles
        with open(path, "wb") as out:
            out.write(header.encode("ascii"))
            out.write(np.ascontiguousarray(self.vertices, dtype="<f8").tobytes())
            out.write(faces.tobytes())


def _segments_for_chord(radius: float, chord_error_mm: float) -> int:
    """Equal angular steps around a circle so that the sagitta R (1 - cos(dtheta / 2)) <= chord_error_mm."""
    if not chord_error_mm > 0:
        raise ValueError(f"chord_error_mm must be > 0, got {chord_error_mm}")
    half = math.acos(max(1.0 - chord_error_mm / radius, -1.0))
    return max(8, math.ceil(math.pi / half))


def _orient(vertices, triangles, outward):
    """Flip triangles whose normal points against the wanted outward direction (T, 3)."""
    tri = vertices[triangles]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", normal, outward) < 0
    triangles = triangles.copy()
    triangles[flip] = triangles[flip][:, [0, 2, 1]]
    return triangles


def _sagitta(radius, angles):
    gaps = np.diff(np.r_[angles, angles[0] + 2 * np.pi])
    return radius * (1 - math.cos(gaps.max() / 2)), gaps.max()


# Embree's closest-point query runs in float32: on a sliver triangle (40 mm x 0.1 mm) its closest point was off by
# up to 15 um in our checks. Every triangle here is kept within this aspect ratio (long side / short side).
MAX_ASPECT = 8.0


def _grid(rings: list[np.ndarray]):
    """Triangles (2 per quad) joining consecutive rings (K, m, 3) of equal count m, closed around; vertex indices
    into the stacked rings. Returns (vertices (K m, 3), triangles)."""
    rings = np.asarray(rings)
    k_count, m = rings.shape[:2]
    j = np.arange(m)
    nxt = (j + 1) % m
    tris = []
    for i in range(k_count - 1):
        a, b = i * m, (i + 1) * m
        tris += [np.column_stack([a + j, a + nxt, b + nxt]), np.column_stack([a + j, b + nxt, b + j])]
    return rings.reshape(-1, 3), np.vstack(tris)


def _annulus_rings(centre, radial, r_inner, r_outer, step):
    """Rings at radii from r_inner to r_outer (arrays (m,) per ray, or floats) in geometric steps whose ratio keeps
    the quads' aspect <= MAX_ASPECT: radius ratio 1 + MAX_ASPECT * step per row (step = angular step, rad)."""
    r_inner = np.broadcast_to(np.asarray(r_inner, float), (len(radial),))
    r_outer = np.broadcast_to(np.asarray(r_outer, float), (len(radial),))
    ratio = float(np.max(r_outer / r_inner))
    rows = max(1, math.ceil(math.log(ratio) / math.log(1.0 + MAX_ASPECT * step)))
    f = np.arange(rows + 1) / rows
    radii = r_inner[None, :] * (r_outer / r_inner)[None, :] ** f[:, None]  # (rows + 1, m)
    return [centre + radii[i][:, None] * radial for i in range(rows + 1)]


def _disk(centre, normal, radial, radius, step):
    """A planar disk: rings from the rim in to half the radius (aspect-limited quads, the rim's own vertices), and an
    inner 64-gon fan circumscribing the innermost ring (overlapping it, coplanar: no gap for distance queries).
    Returns (vertices, triangles, outward normals)."""
    rings = _annulus_rings(centre, radial, radius / 2, radius, step)
    v_ring, t_ring = _grid(rings)
    k = 64
    phi = 2 * np.pi * np.arange(k) / k
    u, w = _axis_basis(normal)
    inner_r = (radius / 2) / math.cos(math.pi / k) * 1.0001
    poly = centre + inner_r * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * w)
    v_fan = np.vstack([poly, centre])
    t_fan = np.column_stack([np.full(k, k), np.arange(k), (np.arange(k) + 1) % k]) + len(v_ring)
    vertices = np.vstack([v_ring, v_fan])
    triangles = np.vstack([t_ring, t_fan])
    return vertices, triangles, np.broadcast_to(normal, (len(triangles), 3))


def _cone_lateral(c, a, alpha, radial, h0, h1, r_lo, step):
    """Rings along the generators from height h0 to h1, rows short enough for MAX_ASPECT."""
    r_hi = r_lo - (h1 - h0) * math.tan(alpha)
    generator = (h1 - h0) / math.cos(alpha)
    rows = max(1, math.ceil(generator / (MAX_ASPECT * r_hi * step)))
    rings = []
    for f in np.arange(rows + 1) / rows:
        h = h0 + f * (h1 - h0)
        rings.append(c + h * a + (r_lo - (h - h0) * math.tan(alpha)) * radial)
    vertices, triangles = _grid(rings)
    # outward normal at each triangle: the cone normal at its centroid's angle
    centroid = vertices[triangles].mean(axis=1) - c
    radial_c = centroid - (centroid @ a)[:, None] * a
    radial_c /= np.linalg.norm(radial_c, axis=1, keepdims=True)
    return vertices, triangles, math.cos(alpha) * radial_c + math.sin(alpha) * a


def _assemble(pieces, note, source, chord):
    vertices, triangles, outward, offset = [], [], [], 0
    for v, t, o in pieces:
        vertices.append(v)
        triangles.append(t + offset)
        outward.append(o)
        offset += len(v)
    vertices = np.vstack(vertices)
    triangles = _orient(vertices, np.vstack(triangles).astype(np.int64), np.vstack(outward))
    return CadMesh(vertices, triangles, chord, source, note)


def cone_frustum_mesh(cone: dict, chord_error_mm: float = 5e-5) -> CadMesh:
    """Closed mesh of a cone frustum (lateral surface, base and top caps) of a part JSON cone surface.

    cone : ``"type": "cone"`` surface dict (base_center, axis, half_angle_deg, base_radius, height_range).
    chord_error_mm : largest mesh-to-cone distance wanted; the angular step is chosen on the base circle (the largest).

    Why the bound holds: each lateral quad joins two generators, which meet at the apex, so it is planar; it lies
    between its secant plane and the cone, no farther from the cone than the sagitta R (1 - cos(dtheta / 2)) of its
    base chord. The caps are planar and exact. Triangles keep an aspect ratio <= MAX_ASPECT (see there); the caps'
    inner fans overlap their rings instead of sharing vertices, so the mesh is closed but not edge-conforming there.
    """
    c = np.asarray(cone["base_center"], float)
    a = _unit(cone["axis"])
    alpha = math.radians(float(cone["half_angle_deg"]))
    radius = float(cone["base_radius"])
    h0, h1 = (float(v) for v in cone["height_range"])
    r_lo, r_hi = radius - h0 * math.tan(alpha), radius - h1 * math.tan(alpha)
    n = _segments_for_chord(r_lo, chord_error_mm)
    angles = 2 * np.pi * np.arange(n) / n
    step = 2 * np.pi / n
    u, w = _axis_basis(a)
    radial = np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * w
    pieces = [_cone_lateral(c, a, alpha, radial, h0, h1, r_lo, step),
              _disk(c + h0 * a, -a, radial, r_lo, step), _disk(c + h1 * a, a, radial, r_hi, step)]
    chord, gap = _sagitta(r_lo, angles)
    return _assemble(pieces, f"R (1 - cos(dtheta / 2)) with R = {r_lo:g} mm, widest step dtheta = {gap:.3e} rad; "
                     "caps exact", "cone frustum meshed from the part JSON (numpy)", chord)


def nas979_mesh(part: dict, chord_error_mm: float = 5e-5) -> CadMesh:
    """Closed mesh of the NAS 979 part (frustum on its wedge block) from its JSON, chord error <= chord_error_mm.

    The cone's lateral surface, the block-top face between the base circle and the block outline (rays at the same
    angles, plus the block-top corners' angles so that the outline is met at its corners) and the top cap share the
    ring angles; the block's bottom and sides are two triangles each. Only the cone's lateral surface is curved.
    """
    cone = next(s for s in part["surfaces"] if s["type"] == "cone")
    p = part["parameters"]
    z_bottom = float(part["derived"]["z_bottom"])
    c = np.asarray(cone["base_center"], float)
    a = _unit(cone["axis"])
    u, w = _axis_basis(a)
    alpha = math.radians(float(cone["half_angle_deg"]))
    radius, height = float(cone["base_radius"]), float(cone["height_range"][1])
    r_top = radius - height * math.tan(alpha)
    half_l, half_w = p["block_length_x"] / 2, p["block_width_y"] / 2
    # block-top face: the plane a . x = 0; a point (x, y, -x tan t) there is x / cos t along u plus y along w
    cos_t = float(a[2])
    uh, wh = half_l / cos_t, half_w
    n = _segments_for_chord(radius, chord_error_mm)
    step = 2 * np.pi / n
    corners = np.arctan2([wh, wh, -wh, -wh], [uh, -uh, -uh, uh])
    angles = np.unique(np.mod(np.r_[2 * np.pi * np.arange(n) / n, corners], 2 * np.pi))
    radial = np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * w
    with np.errstate(divide="ignore"):
        s_out = np.minimum(uh / np.abs(np.cos(angles)), wh / np.abs(np.sin(angles)))
    v_top, t_top = _grid(_annulus_rings(c, radial, radius, s_out, step))
    bottom = np.array([[half_l, half_w], [-half_l, half_w], [-half_l, -half_w], [half_l, -half_w]])

    def top_z(xy):
        return -xy[0] * math.tan(math.atan2(a[0], a[2]))

    block = []
    block.append((np.column_stack([bottom, np.full(4, z_bottom)]), np.array([[0, 1, 2], [0, 2, 3]]),
                  np.broadcast_to([0.0, 0.0, -1.0], (2, 3))))
    for k in range(4):  # side k joins bottom corners k and k + 1 (counter-clockwise seen from above)
        p0, p1 = bottom[k], bottom[(k + 1) % 4]
        quad = np.array([[*p0, z_bottom], [*p1, z_bottom], [*p1, top_z(p1)], [*p0, top_z(p0)]])
        mid = (p0 + p1) / 2
        out = np.array([np.sign(mid[0]) if abs(mid[0]) > 1e-9 else 0.0, np.sign(mid[1]) if abs(mid[1]) > 1e-9
                        else 0.0, 0.0])
        block.append((quad, np.array([[0, 1, 2], [0, 2, 3]]), np.broadcast_to(out, (2, 3))))
    pieces = [_cone_lateral(c, a, alpha, radial, 0.0, height, radius, step),
              _disk(c + height * a, a, radial, r_top, step),
              (v_top, t_top, np.broadcast_to(a, (len(t_top), 3))), *block]
    chord, gap = _sagitta(radius, angles)
    return _assemble(pieces, f"cone: R (1 - cos(dtheta / 2)) with R = {radius:g} mm, widest step {gap:.3e} rad; "
                     "planes exact", "NAS 979 part meshed from its JSON (numpy)", chord)
