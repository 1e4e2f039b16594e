"""The test parts (trueaxis.workpiece.parts): CAD volumes, STL fidelity, JSON surfaces, cone distance, overrides."""

from __future__ import annotations

import json
import math

import cadquery as cq
import numpy as np
import pytest
import trimesh
from scipy.optimize import minimize

from trueaxis.workpiece.part import part_names, write_part
from trueaxis.workpiece import parts  # noqa: E402
from trueaxis.workpiece.parts import (  # noqa: E402
    Nas979Params,
    SlotBlockParams,
    cone_signed_distance,
    cone_surface_points,
)

# An STL stores float32 coordinates: one ulp at 200 mm is 1.5e-5 mm. Distances between STL and exact geometry are
# compared with this slack on top of the chord error bound.
FLOAT32_SLACK_MM = 3e-5


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """Both parts written once with default parameters: {name: (paths, json document, trimesh mesh)}."""
    out = tmp_path_factory.mktemp("parts") / "nested" / "dir"
    result = {}
    for name in part_names():
        paths = write_part(name, out)
        doc = json.loads(paths["json"].read_text())
        mesh = trimesh.load_mesh(paths["stl"], file_type="stl")
        result[name] = (paths, doc, mesh)
    return result


def mesh_closest(mesh, points, reach=1.0):
    """Closest points on a mesh, float64 brute force over the triangles whose bounding box, grown by ``reach`` (mm),
    holds the query point (so only for points within ``reach`` of the surface).

    Returns (closest (N, 3), distance (N,), signed distance (N,), positive on the side the face normal points to).
    An independent formulation of point-to-surface distance (no cone algebra), for checks.
    """
    triangles = np.asarray(mesh.triangles, dtype=float)
    normals = np.asarray(mesh.face_normals, dtype=float)
    low, high = triangles.min(axis=1) - reach, triangles.max(axis=1) + reach
    closest = np.empty_like(points)
    distance = np.empty(len(points))
    signed = np.empty(len(points))
    for i, q in enumerate(points):
        idx = np.flatnonzero(np.all((low <= q) & (q <= high), axis=1))
        assert len(idx), "no triangle within reach of the query point"
        c = trimesh.triangles.closest_point(triangles[idx], np.repeat(q[None], len(idx), axis=0))
        d = np.linalg.norm(c - q, axis=1)
        j = int(np.argmin(d))
        closest[i], distance[i] = c[j], d[j]
        signed[i] = math.copysign(d[j], (q - c[j]) @ normals[idx[j]])
    return closest, distance, signed


# ---------------------------------------------------------------------------------------------------------------------
# NAS 979
# ---------------------------------------------------------------------------------------------------------------------


def test_nas979_step_reimports_with_analytic_volume(written):
    paths, doc, _ = written["nas979"]
    p = Nas979Params()
    solid = cq.importers.importStep(str(paths["step"])).val()
    assert solid.isValid()
    expected = math.pi * 20 / 3 * (40**2 + 40 * p.top_radius + p.top_radius**2) + 100 * 100 * (
        10 + 50 * math.tan(math.radians(10))
    )
    # The B-rep of planes and a cone is exact; OCCT's volume integration is good to ~1e-9 relative.
    assert solid.Volume() == pytest.approx(expected, rel=1e-6)
    assert doc["derived"]["volume_mm3"] == pytest.approx(expected, rel=1e-12)
    assert p.top_radius == pytest.approx(40 - 20 * math.tan(math.radians(15)), abs=1e-12)


def test_nas979_stl_watertight_and_volume_within_chord_bound(written):
    paths, doc, mesh = written["nas979"]
    p = Nas979Params()
    assert mesh.is_watertight and mesh.is_winding_consistent
    bound = doc["stl"]["chord_error_bound_mm"]
    assert 0 < bound <= 1.01e-3  # about 1 um: the asked linear deflection
    # The inscribed mesh loses at most (chord error x curved area); the planes only lose float32 rounding.
    lateral_area = math.pi * (p.base_radius + p.top_radius) * p.height / math.cos(math.radians(p.half_angle_deg))
    brep_volume = cq.importers.importStep(str(paths["step"])).val().Volume()
    allowed = bound * lateral_area + FLOAT32_SLACK_MM * mesh.area
    assert abs(mesh.volume - brep_volume) <= allowed
    assert mesh.volume < brep_volume  # inscribed polygons: the mesh lies inside the convex cone


def test_nas979_stl_triangles_within_chord_bound_of_cone(written):
    _, doc, mesh = written["nas979"]
    cone = doc["surfaces"][0]
    on_cone = np.abs(cone_signed_distance(mesh.vertices, cone)) < 1e-4
    triangles = np.asarray(mesh.triangles)[np.all(on_cone[mesh.faces], axis=1)]
    triangles = triangles[np.abs(mesh.face_normals[np.all(on_cone[mesh.faces], axis=1)] @ cone["axis"]) < 0.99]
    assert len(triangles) > 1000
    # Barycentric samples over every cone triangle: deepest point of the flat facets below the cone.
    g = np.linspace(0, 1, 9)
    u, v = np.meshgrid(g, g)
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    samples = (triangles[:, None, 0] + u[None, :, None] * (triangles[:, None, 1] - triangles[:, None, 0])
               + v[None, :, None] * (triangles[:, None, 2] - triangles[:, None, 0])).reshape(-1, 3)
    depth = cone_signed_distance(samples, cone)
    assert depth.max() <= FLOAT32_SLACK_MM  # facets are inscribed
    assert -depth.min() <= doc["stl"]["chord_error_bound_mm"] + FLOAT32_SLACK_MM


def test_nas979_json_cone_points_lie_on_stl(written):
    _, doc, mesh = written["nas979"]
    cone = doc["surfaces"][0]
    assert cone["type"] == "cone" and cone["height_range"] == [0.0, 20.0]
    np.testing.assert_allclose(cone["axis"], [math.sin(math.radians(10)), 0, math.cos(math.radians(10))], atol=1e-15)
    heights = [f["height"] for f in doc["features"] if f["type"] == "roundness"]
    assert heights == [2.0, 10.0, 18.0]
    points, _ = cone_surface_points(cone, heights, 48)
    _, distance, _ = mesh_closest(mesh, points)
    assert distance.max() <= doc["stl"]["chord_error_bound_mm"] + FLOAT32_SLACK_MM


def test_cone_signed_distance_matches_mesh_distance_near_surface(written):
    _, doc, mesh = written["nas979"]
    cone = doc["surfaces"][0]
    rng = np.random.default_rng(979)
    points, normals = cone_surface_points(cone, [3.0, 7.5, 12.0, 16.5], 24)
    offset = rng.uniform(-0.5, 0.5, len(points))
    queries = points + offset[:, None] * normals
    _, _, mesh_signed = mesh_closest(mesh, queries)
    exact = cone_signed_distance(queries, cone)
    np.testing.assert_allclose(exact, offset, atol=1e-12)
    # The mesh lies inside the cone by at most the chord error, so distances agree within it.
    assert np.abs(exact - mesh_signed).max() <= doc["stl"]["chord_error_bound_mm"] + FLOAT32_SLACK_MM


def test_cone_signed_distance_matches_parametric_minimisation():
    cone = Nas979Params(half_angle_deg=20, axis_inclination_deg=25).cone_surface()
    a = np.asarray(cone["axis"])
    apex = np.asarray(cone["apex"])
    alpha = math.radians(cone["half_angle_deg"])
    u, w = parts._axis_basis(a)

    def surface(s, theta):  # s >= 0: distance from the apex along a generatrix
        return apex + s * (-math.cos(alpha) * a + math.sin(alpha) * (math.cos(theta) * u + math.sin(theta) * w))

    rng = np.random.default_rng(15)
    queries = np.concatenate([
        rng.uniform([-60, -60, -40], [60, 60, 150], size=(40, 3)),  # everywhere, beyond the apex too
        apex + rng.normal(scale=3.0, size=(5, 3)),                   # around the apex
        np.outer(np.linspace(-30, 200, 5), a),                       # on the axis
    ])
    distances = cone_signed_distance(queries, cone)
    for q, d in zip(queries, distances):
        v = q - apex
        phi = math.atan2(v @ w, v @ u)
        best = math.inf
        for theta0 in (phi, phi + math.pi):
            res = minimize(lambda x: float(np.sum((surface(x[0], x[1]) - q) ** 2)),
                           x0=[max(-(v @ a) / math.cos(alpha), 0.0), theta0],
                           bounds=[(0, None), (None, None)], method="L-BFGS-B",
                           options={"ftol": 1e-15, "gtol": 1e-12})
            best = min(best, math.sqrt(res.fun))
        assert abs(abs(d) - best) <= 1e-5 * max(1.0, best)
        # Sign, independently: inside the solid cone iff the angle between (q - apex) and -a is below alpha.
        angle_to_down_axis = math.acos(np.clip(-(v @ a) / max(np.linalg.norm(v), 1e-300), -1, 1))
        if abs(angle_to_down_axis - alpha) > 1e-9:
            assert (d < 0) == (angle_to_down_axis < alpha)


def test_cone_surface_points_are_on_the_cone_with_unit_outward_normals():
    cone = Nas979Params().cone_surface()
    points, normals = cone_surface_points(cone, np.array([0.0, 5.0, 20.0]), 7)
    assert points.shape == normals.shape == (21, 3)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(cone_signed_distance(points, cone), 0.0, atol=1e-12)
    np.testing.assert_allclose(cone_signed_distance(points + 0.25 * normals, cone), 0.25, atol=1e-12)
    np.testing.assert_allclose(cone_signed_distance(points - 0.25 * normals, cone), -0.25, atol=1e-12)
    # Ring radius at height s: R - s tan(alpha).
    a = np.asarray(cone["axis"])
    radial = points - np.outer(points @ a, a)
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1)[14:], 40 - 20 * math.tan(math.radians(15)), atol=1e-12)
    with pytest.raises(ValueError):
        cone_signed_distance(np.zeros((3, 2)), cone)


def test_nas979_overrides_change_the_geometry():
    p = Nas979Params.from_overrides(["half_angle_deg=12", "height=25", "axis_inclination_deg=0", "block_min_thickness=15"])
    assert (p.half_angle_deg, p.height, p.axis_inclination_deg, p.block_min_thickness) == (12, 25, 0, 15)
    solid = parts.build_nas979(p).val()
    r = 40 - 25 * math.tan(math.radians(12))
    expected = math.pi * 25 / 3 * (1600 + 40 * r + r * r) + 100 * 100 * 15
    assert solid.Volume() == pytest.approx(expected, rel=1e-6)
    assert solid.Volume() != pytest.approx(parts.build_nas979().val().Volume(), rel=1e-3)
    doc = parts.nas979_description(p)
    assert doc["parameters"]["half_angle_deg"] == 12 and doc["surfaces"][0]["half_angle_deg"] == 12
    np.testing.assert_allclose(doc["surfaces"][0]["axis"], [0, 0, 1], atol=1e-15)
    assert parts.nas979_workplane(height=25).val().Volume() == pytest.approx(
        parts.build_nas979(Nas979Params(height=25)).val().Volume(), rel=1e-9)


@pytest.mark.parametrize("overrides, message", [
    (["cone_height=3"], "unknown nas979 parameter 'cone_height'"),
    (["height=abc"], "not a number"),
    (["height"], "NAME=VALUE"),
    (["height=nan"], "not finite"),
    (["height=200"], "closes the cone"),
    (["base_diameter=120"], "does not fit"),
])
def test_nas979_bad_overrides_raise_value_error(overrides, message):
    with pytest.raises(ValueError, match=message):
        Nas979Params.from_overrides(overrides)


def test_slot_passes_beyond_what_a_slot_needs_are_refused():
    # 0.0001 mm per pass wrote 90,000 passes (720,025 lines, 113 s, no word: a QA pass)
    with pytest.raises(ValueError, match=r"makes 30000 passes per slot; at most 200"):
        SlotBlockParams.from_overrides(["axial_depth_per_pass=0.0001"])
    assert len(SlotBlockParams.from_overrides(["axial_depth_per_pass=0.015"]).pass_depths()) == 200


def test_workplane_conveniences_refuse_unknown_names_and_place_on_a_workplane():
    with pytest.raises(ValueError, match="unknown"):
        parts.nas979_workplane(apex_angle=30)
    with pytest.raises(ValueError, match="unknown"):
        parts.slot_block_workplane(slot_count=4)
    placed = parts.nas979_workplane(cq.Workplane("XY", origin=(0, 0, 50)))
    assert placed.val().BoundingBox().zmin == pytest.approx(50 + Nas979Params().z_bottom, abs=1e-6)


# ---------------------------------------------------------------------------------------------------------------------
# Slot block
# ---------------------------------------------------------------------------------------------------------------------


def test_slot_block_step_and_stl_volumes(written):
    paths, doc, mesh = written["slots"]
    solid = cq.importers.importStep(str(paths["step"])).val()
    assert solid.isValid()
    # Swept outline of one slot: 2 rho L + pi rho^2, plus at each 45 deg bend rho^2 (phi/2 - tan(phi/2)).
    rho, length = 5.0, 30 + 20 * math.sqrt(2) + 30
    phi = math.pi / 4
    slot_area = 2 * rho * length + math.pi * rho**2 + 2 * rho**2 * (phi / 2 - math.tan(phi / 2))
    expected = 210 * 80 * 30 - 3 * 3.0 * slot_area
    assert solid.Volume() == pytest.approx(expected, rel=1e-6)
    assert doc["derived"]["volume_mm3"] == pytest.approx(expected, rel=1e-12)
    assert mesh.is_watertight
    arc_area = 3 * 3.0 * 2 * math.pi * rho  # all arcs of the three slots add to three full circles
    allowed = doc["stl"]["chord_error_bound_mm"] * arc_area + FLOAT32_SLACK_MM * mesh.area
    assert abs(mesh.volume - solid.Volume()) <= allowed


def test_slot_walls_are_at_the_stated_width_and_depth(written):
    paths, doc, mesh = written["slots"]
    p = SlotBlockParams()
    solid = parts.build_slot_block(p).val()
    surfaces = {s["id"]: s for s in doc["surfaces"]}
    slots = [f for f in doc["features"] if f["type"] == "slot"]
    assert [s["compensation"] for s in slots] == ["none", "geometric", "comprehensive"]
    eps = 1e-3
    wall_points = []
    for slot in slots:
        assert slot["nominal_width"] == 10.0 and slot["nominal_depth"] == 3.0
        path = np.asarray(slot["tool_centre_path"])
        np.testing.assert_allclose(path[:, 2], -3.0)
        assert slot["pass_depths"][-1] == pytest.approx(-3.0) and len(slot["pass_depths"]) == 5
        for k, (start, end) in enumerate(zip(path[:-1], path[1:])):
            left, right = surfaces[f"{slot['id']}_seg{k}_left"], surfaces[f"{slot['id']}_seg{k}_right"]
            n_left, n_right = np.asarray(left["normal"]), np.asarray(right["normal"])
            np.testing.assert_allclose(n_left, -n_right, atol=1e-15)
            # Walls face each other across the slot (normals out of the material point into the slot): the right
            # wall lies one slot width along the left wall's normal ...
            gap = (np.asarray(right["point"]) - np.asarray(left["point"])) @ n_left
            assert gap == pytest.approx(10.0, abs=1e-12)
            # ... and lie where the solid's material starts: just inside the slot is empty, just beyond is metal.
            mid = (start + end) / 2
            mid[2] = -1.5
            for wall in (left, right):
                n = np.asarray(wall["normal"])
                on_wall = mid - 5.0 * n
                assert abs((on_wall - wall["point"]) @ n) < 1e-12
                assert not solid.isInside(cq.Vector(*(on_wall + eps * n)))
                assert solid.isInside(cq.Vector(*(on_wall - eps * n)))
                wall_points.append(on_wall)
            # Depth: the floor at -3 under the tool-centre path.
            floor = surfaces[slot["floor"]]
            assert floor["point"][2] == -3.0 and floor["normal"] == [0.0, 0.0, 1.0]
            bottom = np.array([mid[0], mid[1], -3.0])
            assert not solid.isInside(cq.Vector(*(bottom + [0, 0, eps])))
            assert solid.isInside(cq.Vector(*(bottom - [0, 0, eps])))
    # The same wall points lie on the STL.
    _, distance, _ = mesh_closest(mesh, np.asarray(wall_points))
    assert distance.max() <= FLOAT32_SLACK_MM


def test_slot_wall_segments_trim_at_the_bends(written):
    _, doc, _ = written["slots"]
    surfaces = {s["id"]: s for s in doc["surfaces"]}
    # Slot "none" starts at (15, 15): segment 0 runs along +X to (45, 15), then a 45 deg left turn.
    left0 = surfaces["slot_none_seg0_left"]
    np.testing.assert_allclose(left0["normal"], [0, -1, 0], atol=1e-15)  # material at y > 20, normal into the slot
    np.testing.assert_allclose(left0["segment"]["start"], [15, 20], atol=1e-12)
    np.testing.assert_allclose(left0["segment"]["end"], [45 - 5 * math.tan(math.pi / 8), 20], atol=1e-12)
    right0 = surfaces["slot_none_seg0_right"]
    np.testing.assert_allclose(right0["segment"]["end"], [45, 10], atol=1e-12)  # outer side: arc follows
    corner = surfaces["slot_none_corner1"]
    assert corner["type"] == "cylinder" and corner["radius"] == 5.0
    np.testing.assert_allclose(corner["angle_range_deg"], [-90, -45], atol=1e-12)


def test_slot_overrides_and_bad_values():
    p = SlotBlockParams.from_overrides(["slot_depth=2", "slot_path=0,0;40,0;40,40", "tool_diameter=8"])
    assert p.slot_path == ((0.0, 0.0), (40.0, 0.0), (40.0, 40.0))
    solid = parts.build_slot_block(p).val()
    assert solid.Volume() == pytest.approx(p.block_volume(), rel=1e-6)
    assert solid.Volume() != pytest.approx(parts.build_slot_block().val().Volume(), rel=1e-4)
    with pytest.raises(ValueError, match="unknown slots parameter 'slot_count'"):
        SlotBlockParams.from_overrides(["slot_count=4"])
    with pytest.raises(ValueError, match="not 'x,y'"):
        SlotBlockParams.from_overrides(["slot_path=0,0;30"])
    with pytest.raises(ValueError, match="not inside"):
        SlotBlockParams.from_overrides(["block_length_x=150"])
    with pytest.raises(ValueError, match="cuts through"):
        SlotBlockParams.from_overrides(["slot_depth=30"])


def test_write_part_creates_the_folder_and_leaves_no_temp_files(written, tmp_path):
    paths, doc, _ = written["slots"]
    folder = paths["json"].parent
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        f"{n}.{e}" for n in part_names() for e in ("json", "step", "stl"))
    for name in part_names():
        d = written[name][1]
        assert d["part"] == name and d["version"] == 1 and d["units"] == "mm"
        assert set(d) >= {"frame", "parameters", "source_note", "surfaces", "features", "stl"}
        assert d["stl"]["chord_tolerance_mm"] > 0 and d["stl"]["angular_tolerance_rad"] > 0
    assert "not at hand" in written["nas979"][1]["source_note"]
    with pytest.raises(ValueError, match="unknown part"):
        write_part("cube", tmp_path)
    with pytest.raises(ValueError, match="takes Nas979Params"):
        write_part("nas979", tmp_path, SlotBlockParams())
