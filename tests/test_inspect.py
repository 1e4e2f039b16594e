"""Comparing a cloud with the CAD: exact deviations, alignments, form evaluation, refusals and the report folder."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import numpy as np
import pytest

from conftest import DATA
from trueaxis.inspect import deviation as dv
from trueaxis.inspect.cloud import write_cloud_ply
from trueaxis.workpiece.parts import (cone_signed_distance, cone_surface_points, nas979_description,
                                    slot_block_description)
from trueaxis.inspect.report import inspect_cloud, write_report

NAS = nas979_description()
CONE = NAS["surfaces"][0]
SLOTS = slot_block_description()
ALPHA = math.radians(CONE["half_angle_deg"])
AXIS = np.asarray(CONE["axis"])
U, W = dv._axis_basis(AXIS)


def run(*args):
    return subprocess.run([sys.executable, "-m", "trueaxis.cli", *args], capture_output=True, text=True)


def deformed_cone(eccentricity_mm=(0.0, 0.0), ovality_mm=0.0, taper_rad=0.0, heights=None, per_ring=360):
    """Rings on the cone with a known deformation: the axis moved by eccentricity (along u, w), the section radius
    R - s tan(alpha + taper) + ovality cos(2 theta). Returns points (n, 3) and the exact outward normals of the
    nominal cone (n, 3)."""
    heights = np.arange(1.0, 20.0) if heights is None else np.asarray(heights, float)
    theta = 2 * np.pi * np.arange(per_ring) / per_ring
    s, th = np.meshgrid(heights, theta, indexing="ij")
    s, th = s.ravel(), th.ravel()
    radial = np.cos(th)[:, None] * U + np.sin(th)[:, None] * W
    rho = CONE["base_radius"] - s * math.tan(ALPHA + taper_rad) + ovality_mm * np.cos(2 * th)
    shift = eccentricity_mm[0] * U + eccentricity_mm[1] * W
    points = s[:, None] * AXIS + rho[:, None] * radial + shift
    return points, math.cos(ALPHA) * radial + math.sin(ALPHA) * AXIS


def block_faces(n=400, seed=0):
    """Points on the NAS 979 wedge block's bottom, four sides and top face (outside the base circle)."""
    rng = np.random.default_rng(seed)
    zb = NAS["derived"]["z_bottom"]
    t = math.radians(10.0)
    bottom = np.column_stack([rng.uniform(-45, 45, n), rng.uniform(-45, 45, n), np.full(n, zb)])
    sides = []
    for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        a = rng.uniform(-45, 45, n)
        x = np.full(n, 50.0 * sx) if sx else a
        y = np.full(n, 50.0 * sy) if sy else a
        z = rng.uniform(zb + 1, -x * math.tan(t) - 1, n) if sx else rng.uniform(zb + 1, -x * math.tan(t) - 1)
        sides.append(np.column_stack([x, y, z]))
    ang = rng.uniform(0, 2 * np.pi, n)
    r = rng.uniform(42, 48, n)
    top = r[:, None] * (np.cos(ang)[:, None] * U + np.sin(ang)[:, None] * W)
    return np.vstack([bottom, *sides, top])


def rigid(rotvec, translation):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rotvec).as_matrix(), np.asarray(translation, float)


# ------------------------------------------------------------------------------------------------ deviations ----
def test_analytic_cone_patch_equals_the_exact_cone_distance():
    rng = np.random.default_rng(1)
    p, n = cone_surface_points(CONE, rng.uniform(0.2, 19.8, 50), 97)
    offset = rng.uniform(-0.05, 0.05, len(p))
    q = p + offset[:, None] * n
    d = dv.analytic_deviation(q, dv.analytic_surfaces(NAS))
    assert set(np.array(d.surface_ids)[d.surface]) == {"cone"}
    # points moved along the normal by a known amount: the distance is that amount (to rounding)
    np.testing.assert_allclose(d.deviation_mm, offset, atol=1e-12)
    np.testing.assert_allclose(d.deviation_mm, cone_signed_distance(q, CONE), atol=1e-12)


def test_cone_patch_beyond_its_rims_and_on_its_axis_measures_to_the_nearest_rim_point():
    """Points whose perpendicular foot falls beyond the frustum's rims are nearest to a rim circle: the distance to
    that circle, computed here from the circle alone; a point on the axis is as far from every point of its rim."""
    h0, h1 = CONE["height_range"]
    rng = np.random.default_rng(5)
    theta = rng.uniform(0, 2 * np.pi, 200)
    radial = np.cos(theta)[:, None] * U + np.sin(theta)[:, None] * W
    centre = np.asarray(CONE["base_center"], float)
    for h_rim, beyond in ((h1, 1.0), (h0, -1.0)):
        r_rim = CONE["base_radius"] - h_rim * math.tan(ALPHA)
        rim = centre + h_rim * AXIS + r_rim * radial
        # beyond the rim along the axis and outwards: the foot on the generator line lies past the rim
        q = rim + beyond * rng.uniform(0.5, 3.0, 200)[:, None] * AXIS + rng.uniform(0.0, 0.2, 200)[:, None] * radial
        signed, unsigned, normal = dv.patch_distance(q, CONE)
        np.testing.assert_allclose(unsigned, np.linalg.norm(q - rim, axis=1), rtol=0, atol=1e-12)
        np.testing.assert_allclose(normal * unsigned[:, None], np.sign(signed)[:, None] * (q - rim), atol=1e-12)
    on_axis = centre + np.array([0.5, 5.0, 19.5])[:, None] * AXIS
    signed, unsigned, _ = dv.patch_distance(on_axis, CONE)
    # on the axis every meridian is as near: the distance to the rim-clamped generator of any one, here along U
    heights = np.array([0.5, 5.0, 19.5])
    generator = np.linspace(h0, h1, 200_001)  # 0.1 um steps along the meridian's generator
    meridian = centre + generator[:, None] * AXIS + (CONE["base_radius"] - generator * math.tan(ALPHA))[:, None] * U
    nearest = np.array([np.linalg.norm(meridian - p, axis=1).min() for p in on_axis])
    np.testing.assert_allclose(signed, -nearest, rtol=0, atol=1e-8)


def test_raycast_on_the_fine_mesh_agrees_with_the_analytic_cone_within_the_chord_error():
    mesh = dv.cone_frustum_mesh(CONE, chord_error_mm=5e-5)
    assert mesh.chord_error_mm <= 5e-5
    rng = np.random.default_rng(2)
    p, n = cone_surface_points(CONE, rng.uniform(0.1, 19.9, 60), 211)
    offset = rng.uniform(-0.03, 0.03, len(p))
    q = p + offset[:, None] * n
    d_mesh, _, _ = dv.MeshDistance(mesh).signed_distance(q)
    d_exact = cone_signed_distance(q, CONE)
    diff_um = (d_mesh - d_exact) * 1e3
    # the inscribed mesh lies inside the cone by 0 .. chord error; float32 in Embree adds < 0.01 um
    assert diff_um.max() <= mesh.chord_error_mm * 1e3 + 0.01
    assert diff_um.min() >= -0.01
    assert mesh.chord_error_mm * 1e3 < 0.1


def test_nas979_mesh_matches_every_analytic_surface():
    mesh = dv.nas979_mesh(NAS)
    rng = np.random.default_rng(3)
    tri = mesh.vertices[mesh.triangles]
    pick = rng.integers(0, len(tri), 20_000)
    x = np.einsum("ij,ijk->ik", rng.dirichlet([1, 1, 1], len(pick)), tri[pick]) + rng.normal(0, 0.01, (len(pick), 3))
    exact = dv.analytic_deviation(x, dv.analytic_surfaces(NAS)).deviation_mm
    diff_um = (dv.MeshDistance(mesh).signed_distance(x)[0] - exact) * 1e3
    assert np.abs(diff_um).max() <= mesh.chord_error_mm * 1e3 + 0.01


def test_points_far_from_the_analytic_surfaces_fall_back_to_the_mesh():
    # without the block sides in the analytic set, points on a side are measured against the CAD mesh
    surfaces = [s for s in dv.analytic_surfaces(NAS) if not s["id"].startswith("block_side")]
    side = np.array([[50.003, 0.0, -14.0], [-49.998, 10.0, -15.0]])
    d = dv.deviation(side, surfaces, dv.MeshDistance(dv.nas979_mesh(NAS)))
    assert d.from_mesh.all()
    np.testing.assert_allclose(d.deviation_mm * 1e3, [3.0, -2.0], atol=0.01)


def test_slot_walls_arcs_and_floors_are_exact_and_assigned_to_their_slot():
    from trueaxis.workpiece.slot_block import slot_pattern

    p, n = slot_pattern(SLOTS, 3000)
    offset = np.random.default_rng(4).uniform(-0.01, 0.01, len(p))
    d = dv.analytic_deviation(p + offset[:, None] * n, dv.analytic_surfaces(SLOTS))
    np.testing.assert_allclose(d.deviation_mm, offset, atol=1e-12)
    ids = np.array(d.surface_ids)[d.surface]
    for mode in ("none", "geometric", "comprehensive"):
        assert np.any(ids == f"slot_{mode}_floor") and np.any(ids == f"slot_{mode}_start_cap")


# ----------------------------------------------------------------------------------------- known deformation ----
def test_known_eccentricity_ovality_and_taper_come_out_of_the_cone_evaluation():
    e_mm, b_mm, taper = (0.0, 0.010), 0.003, 50e-6
    p, _ = deformed_cone(e_mm, b_mm, taper)
    rep = inspect_cloud(_cloud(p), "nas979").report
    cone = rep["cone"]
    # ovality cos(2 theta) is orthogonal to the cone's parameters on full rings: the fit sees the taper alone; its
    # second-order pull, b^2 / R over the height, is ~0.002 urad
    assert cone["half_angle_error_urad"] == pytest.approx(taper * 1e6, abs=0.05)
    assert cone["axis_tilt_urad"] < 0.05
    np.testing.assert_allclose(cone["axis_offset_um"], (e_mm[1] * W) * 1e3, atol=1e-3)
    assert [r["height_mm"] for r in rep["roundness_um"]] == [2.0, 10.0, 18.0]
    for ring in rep["roundness_um"]:
        # a section radius r0 + b cos(2 theta), sampled at multiples of 1 deg (the extremes included): 2 b exactly
        assert ring["least_squares"] == pytest.approx(2 * b_mm * 1e3, abs=1e-4)
        assert ring["minimum_zone"] == pytest.approx(2 * b_mm * 1e3, abs=1e-4)
        assert ring["points"] == 360
    # diameter at the reference height: 2 (R - h tan(alpha + taper)) against 2 (R - h tan(alpha))
    h = rep["diameter"]["height_mm"]
    expected = -2 * h * (math.tan(ALPHA + taper) - math.tan(ALPHA)) * 1e3
    assert rep["diameter"]["error_um"] == pytest.approx(expected, abs=1e-3)


def test_a_perfect_cone_has_zero_deviation_and_form_error():
    p, _ = deformed_cone()
    rep = inspect_cloud(_cloud(p), "nas979").report
    assert rep["deviation_um"]["rms"] < 1e-6 and rep["points"] == len(p)
    assert abs(rep["cone"]["half_angle_error_urad"]) < 1e-3
    assert all(r["least_squares"] < 1e-6 and r["minimum_zone"] < 1e-6 for r in rep["roundness_um"])


def _cloud(points, normals=None):
    from trueaxis.inspect.cloud import Cloud

    return Cloud(points=np.asarray(points, float), normals=normals, source="<test>")


# ------------------------------------------------------------------------------------------------- alignment ----
def test_bestfit_recovers_a_known_rigid_motion_and_reports_it():
    perfect = np.vstack([deformed_cone(per_ring=120)[0], block_faces(200)])
    rotation, translation = rigid([40e-6, -25e-6, 60e-6], [0.030, -0.020, 0.015])
    moved = perfect @ rotation.T + translation
    result = inspect_cloud(_cloud(moved), "nas979", align="bestfit")
    al = result.report["alignment"]
    # the removed motion is the inverse of the applied one: x = R^T (y - t)
    np.testing.assert_allclose(al["translation_um"], -rotation.T @ translation * 1e3, atol=1e-3)
    from scipy.spatial.transform import Rotation

    np.testing.assert_allclose(al["rotation_urad"], Rotation.from_matrix(rotation.T).as_rotvec() * 1e6, atol=1e-3)
    assert al["not_determined"] == []
    assert result.report["deviation_um"]["rms"] < 1e-4
    assert np.abs(result.aligned - perfect).max() < 1e-9


def test_bestfit_on_a_cone_alone_names_the_rotation_it_cannot_see():
    p, _ = deformed_cone(per_ring=90)
    rotation, translation = rigid([0.0, 30e-6, 0.0], [0.010, 0.0, 0.0])
    result = inspect_cloud(_cloud(p @ rotation.T + translation), "nas979", align="bestfit")
    al = result.report["alignment"]
    assert len(al["not_determined"]) == 1 and "rotation about the line" in al["not_determined"][0]
    assert "(0.1736, 0.0000, 0.9848)" in al["not_determined"][0]  # the cone axis
    assert result.report["deviation_um"]["rms"] < 1e-4


def test_datum_alignment_uses_the_block_bottom_and_sides():
    perfect = np.vstack([deformed_cone(per_ring=90)[0], block_faces(300)])
    rotation, translation = rigid([30e-6, 20e-6, -50e-6], [0.020, 0.010, -0.030])
    result = inspect_cloud(_cloud(perfect @ rotation.T + translation), "nas979", align="datum")
    al = result.report["alignment"]
    assert [d["surface"] for d in al["datums"]][0] == "block_bottom"
    assert np.abs(result.aligned - perfect).max() < 1e-9
    assert result.report["cone"]["half_angle_error_urad"] == pytest.approx(0.0, abs=1e-3)


def test_datum_alignment_names_the_missing_datums():
    p, _ = deformed_cone(per_ring=60)
    with pytest.raises(dv.InspectionError, match="missing datum A .*block_bottom.*datum B"):
        inspect_cloud(_cloud(p), "nas979", align="datum")


def test_datum_b_probed_one_point_above_the_other_is_refused_in_words():
    """Datum B's two points on a vertical line (along A's normal) do not fix the rotation about it: one line, an
    InspectionError (exit 3 through the CLI), where it was a 'Singular matrix' with a numpy warning."""
    cone = deformed_cone(per_ring=60)[0]
    zb = NAS["derived"]["z_bottom"]
    rng = np.random.default_rng(8)
    bottom = np.column_stack([rng.uniform(-45, 45, 50), rng.uniform(-45, 45, 50), np.full(50, zb)])
    side_b = np.array([[-50.0, 0.0, zb + 3.0], [-50.0, 0.0, zb + 8.0]])  # block_side_xneg, one above the other
    side_c = np.column_stack([rng.uniform(-45, 45, 5), np.full(5, -50.0), np.full(5, zb + 3.0)])
    with pytest.raises(dv.InspectionError, match="datum B's points do not fix the rotation"):
        inspect_cloud(_cloud(np.vstack([cone, bottom, side_b, side_c])), "nas979", align="datum")


def test_a_bestfit_on_the_cone_alone_says_it_takes_a_size_error_away():
    """A uniform +5 um on the cone is a size error; a best fit on the cone alone moves the part along the axis
    (5 um / sin 15 deg) and the diameter error vanishes: said in a warning with that move, not on a cone with the
    block's faces."""
    from trueaxis.inspect.report import inspection_warnings

    p, n = deformed_cone(per_ring=120)
    report = inspect_cloud(_cloud(p + 0.005 * n), "nas979", align="bestfit").report
    warnings = [w for w in inspection_warnings(report) if "best fit saw only the cone" in w]
    assert len(warnings) == 1
    moved = float(re.search(r"moved the part ([-+0-9.]+) um", warnings[0]).group(1))
    assert abs(moved) == pytest.approx(5.0 / math.sin(ALPHA), rel=0.01)
    both = inspect_cloud(_cloud(np.vstack([p + 0.005 * n, block_faces(300)])), "nas979", align="bestfit").report
    assert not [w for w in inspection_warnings(both) if "best fit saw only the cone" in w]


def test_a_bestfit_never_passes_the_characteristics_it_takes_away(tmp_path):
    """A cone 20 um off its axis with a size error of +5 um: with no alignment the diameter and the axis position
    fail their tolerances; a best fit moves the part onto the cone and "passed" both (-0.001 um, 0.0 um). Under
    --align bestfit what the part says a best fit absorbs (diameter, axis position and tilt) is "not measured", with
    the block's faces probed too; the half angle, form and roundness are measured either way."""
    p, n = deformed_cone((0.020, 0.0), per_ring=120)
    (tmp_path / "tol.toml").write_text("[cone_angle]\nhalf_angle_urad = [-50.0, 50.0]\n[diameter_ref]\n"
                                       "diameter_um = [-5.0, 5.0]\n[axis_direction]\ntilt_urad = 100.0\n[cone]\n"
                                       "form_um = 30.0\naxis_offset_um = 10.0\n[default]\nroundness_um = 10.0\n")
    cone = p + 0.005 * n
    none = _rows(inspect_cloud(_cloud(cone), "nas979", tolerances=tmp_path / "tol.toml").report)
    assert none[("diameter_ref", "diameter at h = 10 mm")]["result"] == "fail"
    offset = none[("cone", "axis position at the base plane (distance from nominal)")]
    assert offset["result"] == "fail" and offset["actual"] == pytest.approx(20.0, abs=0.01)
    for cloud in (cone, np.vstack([cone, block_faces(300)])):
        report = inspect_cloud(_cloud(cloud), "nas979", align="bestfit", tolerances=tmp_path / "tol.toml").report
        rows = {row["key"]: row for row in report["feature_table"] if row["key"] != "roundness_um"}
        for key in ("diameter_um", "axis_offset_um", "tilt_urad"):
            assert rows[key]["result"] == "not measured" and rows[key]["actual"] is None
            assert "not measured with --align bestfit" in rows[key]["note"]
        assert rows["half_angle_urad"]["result"] == rows["form_um"]["result"] == "pass"
        assert report["feature_summary"]["not measured"] == 3
        assert any("takes away what a rigid move changes" in w for w in report["warnings"])
        # ... and the report's sections say so where they hold those values (the HTML showed the diameter measured)
        assert set(report["diameter"]["not_measured"]) == {"measured_mm", "error_um"}
        assert set(report["cone"]["not_measured"]) == {"axis_tilt_urad", "axis_offset_um"}
    from trueaxis.inspect.report import _table

    html = _table(report["diameter"])
    assert "74.64" in html.split("measured")[0] and html.count("not measured with --align bestfit") == 2


def test_a_bestfit_on_the_slot_block_does_not_measure_slot_positions_depths_and_contours():
    """The whole block 30 um off in Y and 20 um deep: with no alignment every slot's position is 30 um off and its
    depth 20 um deep; a best fit moved the block back and changed them with no word. Under --align bestfit they are
    "not measured"; the widths, straightness and parallelism (which no rigid move changes) are the same."""
    from trueaxis.workpiece.slot_block import slot_pattern

    p, _ = slot_pattern(SLOTS, 6000)
    moved = p + [0.0, 0.030, -0.020]
    none = inspect_cloud(_cloud(moved), "slots").report
    assert all(s["position_um"]["max_abs"] == pytest.approx(30.0, abs=0.01) for s in none["slots"])
    rows = inspect_cloud(_cloud(moved), "slots", align="bestfit").report["feature_table"]
    for row in rows:
        if row["key"] in ("position_um", "depth_um", "contour_um"):
            assert row["result"] == "not measured" and "--align bestfit" in row["note"]
        else:
            twin = next(r for r in none["feature_table"]
                        if (r["feature"], r["characteristic"]) == (row["feature"], row["characteristic"]))
            assert row["result"] == "no tolerance" and row["actual"] == pytest.approx(twin["actual"], abs=1e-6)


# --------------------------------------------------------------------------------------------------- slots ----
def test_slot_width_position_straightness_and_parallelism_of_known_changes():
    from trueaxis.workpiece.slot_block import slot_pattern

    p, n = slot_pattern(SLOTS, 6000)
    d = dv.analytic_deviation(p, dv.analytic_surfaces(SLOTS))
    ids = np.array(d.surface_ids)[d.surface]
    moved = p.copy()
    wider = np.char.startswith(ids, "slot_none_seg") | np.char.startswith(ids, "slot_none_corner") | \
        np.char.endswith(ids, "_cap") & np.char.startswith(ids, "slot_none")
    moved[wider] -= 0.020 * n[wider]  # walls 20 um into the material: the slot is 40 um wider
    shifted = np.char.startswith(ids, "slot_geometric")
    moved[shifted] += [0.0, 0.015, 0.0]  # the whole slot 15 um along +Y
    rep = inspect_cloud(_cloud(moved), "slots").report
    slots = {s["compensation"]: s for s in rep["slots"]}
    for seg in slots["none"]["width"]["segments"]:
        assert seg["width_error_um"] == pytest.approx(40.0, abs=1e-6)
        assert seg["position_um"] == pytest.approx(0.0, abs=1e-6)
        assert seg["parallelism_um"] == pytest.approx(0.0, abs=1e-6)
    # position along each segment's left normal: +Y on the X segment, cos 45 deg of it on the diagonal, 0 along Y
    positions = [s["position_um"] for s in slots["geometric"]["width"]["segments"]]
    np.testing.assert_allclose(positions, [15.0, 15.0 / math.sqrt(2), 0.0], atol=1e-6)
    assert slots["geometric"]["position_um"]["max_abs"] == pytest.approx(15.0, abs=1e-6)
    assert all(v < 1e-6 for v in slots["comprehensive"]["straightness_um"].values())
    assert slots["comprehensive"]["mean_contour_error_um"] < 1e-6
    assert slots["none"]["mean_contour_error_um"] == pytest.approx(20.0, abs=1e-6)
    assert slots["none"]["depth"]["error_um"] == pytest.approx(0.0, abs=1e-9)


# ----------------------------------------------------------------------------------------------- virtual shop ----
@pytest.fixture(scope="module")
def shop_cloud(tmp_path_factory):
    """A cone cut on a B-C machine with XOC = 20 um, measured with 4000 points (the virtual shop)."""
    from trueaxis.machine import load_machine
    from trueaxis.sim.programs import cone_flank_program
    from trueaxis.sim.shop import simulate, write_cmm

    bc = load_machine(DATA / "bc_table.toml")
    names = bc.parameter_names()
    perfect = bc.with_parameters(np.zeros(len(names)))
    values = np.zeros(len(names))
    values[names.index("XOC")] = 20.0
    res = simulate(cone_flank_program(perfect, CONE, n_blocks=900), bc.with_parameters(values), part="nas979",
                   points=4000)
    path = tmp_path_factory.mktemp("shop") / "cmm.ply"
    write_cmm(res, path)
    return path, res


def test_deviations_of_a_virtual_shop_cloud_are_the_simulated_ones(shop_cloud, tmp_path):
    path, res = shop_cloud
    result = inspect_cloud(path, "nas979")
    truth = res.deviations_um[np.isfinite(res.deviations_um)]
    # the virtual CMM moves each nominal point along the cone normal by the simulated deviation: exact
    np.testing.assert_allclose(result.deviation_um, truth, atol=1e-6)
    assert np.ptp(truth) > 20  # XOC makes the deviation swing around the cone
    # an eccentric cone: the roundness stays small, the axis moves by about XOC
    offset = np.linalg.norm(result.report["cone"]["axis_offset_um"])
    assert 10 < offset < 30
    best = inspect_cloud(path, "nas979", align="bestfit")
    assert best.report["deviation_um"]["rms"] < 0.2 * result.report["deviation_um"]["rms"]
    assert np.linalg.norm(best.report["alignment"]["translation_um"]) > 10
    out = write_report(best, tmp_path / "rep")
    assert json.loads((out / "report.json").read_text())["alignment"]["method"] == "bestfit"


# ---------------------------------------------------------------------------------------- CLI and the report ----
def test_cli_writes_report_json_html_and_pictures(tmp_path):
    p, n = deformed_cone((0.0, 0.005), 0.002, 20e-6, per_ring=180)
    cloud = tmp_path / "cone.ply"
    write_cloud_ply(cloud, p, n)
    r = run("inspect", str(cloud), "--part", "nas979", "-o", str(tmp_path / "rep"))
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert {"rms", "min", "max", "p95"} <= set(rep["deviation_um"])
    assert {"height_mm", "least_squares", "minimum_zone"} <= set(rep["roundness_um"][0])
    assert {"half_angle_deg", "half_angle_error_urad", "axis"} <= set(rep["cone"])
    assert rep["points"] == len(p)
    for name in ("report.html", "deviation_map.png", "roundness.png", "histogram.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 1000
    assert "data:image/png;base64," in (tmp_path / "rep" / "report.html").read_text()
    assert not [f for f in tmp_path.iterdir() if f.name.startswith(".")]  # no temporary folder left


def test_cli_reads_csv_and_xyz_clouds(tmp_path):
    p, _ = deformed_cone(per_ring=72)
    np.savetxt(tmp_path / "c.csv", p, delimiter=",", header="x,y,z", comments="")
    np.savetxt(tmp_path / "c.xyz", p)
    for name in ("c.csv", "c.xyz"):
        r = run("inspect", str(tmp_path / name), "--part", "nas979", "-o", str(tmp_path / (name + "_rep")))
        assert r.returncode == 0, r.stderr
        assert json.loads((tmp_path / (name + "_rep") / "report.json").read_text())["points"] == len(p)


def _refusal(tmp_path, name, content, message, code=3):
    cloud = tmp_path / name
    if isinstance(content, bytes):
        cloud.write_bytes(content)
    elif content is not None:
        cloud.write_text(content)
    r = run("inspect", str(cloud), "--part", "nas979", "-o", str(tmp_path / "rep"))
    assert r.returncode == code, r.stdout  # 3: a cloud refused; 2: a path that does not exist (usage)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "rep").exists()
    assert not [f for f in tmp_path.iterdir() if f.name.startswith(".rep")]


def test_refuses_an_empty_cloud(tmp_path):
    _refusal(tmp_path, "empty.xyz", "", "empty")


def test_refuses_an_unreadable_cloud(tmp_path):
    _refusal(tmp_path, "missing.ply", None, "cannot read", code=2)
    _refusal(tmp_path, "junk.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n"
             b"property double x\nproperty double y\nproperty double z\nend_header\n\x00\x01", "truncated")


def test_refuses_nan_and_infinite_points(tmp_path):
    _refusal(tmp_path, "nan.xyz", "38 0 1\nnan 1 2\n", "NaN or infinite")
    _refusal(tmp_path, "inf.csv", "x,y,z\n38,0,1\n1,inf,2\n", "NaN or infinite")


def test_refuses_a_cloud_that_cannot_be_the_part_and_says_how_far_off(tmp_path):
    p, _ = deformed_cone(per_ring=36)
    np.savetxt(tmp_path / "shifted.xyz", p + [150.0, 0.0, 0.0])
    _refusal(tmp_path, "shifted.xyz", None, "exceeds the nas979 part by 1")
    np.savetxt(tmp_path / "metres.xyz", p * 1e-3)  # inside the box, on no surface
    _refusal(tmp_path, "metres.xyz", None, "where the nas979 part spans")  # a unit mistake, said so
    np.savetxt(tmp_path / "slots.xyz", p + [100.0, 40.0, -2.0])
    r = run("inspect", str(tmp_path / "slots.xyz"), "--part", "slots", "-o", str(tmp_path / "rep"))
    assert r.returncode == 3 and "exceeds the slots part" in r.stderr and not (tmp_path / "rep").exists()


def test_identify_needs_its_machine_and_program(tmp_path):
    p, _ = deformed_cone(per_ring=36)
    np.savetxt(tmp_path / "c.xyz", p)
    r = run("inspect", str(tmp_path / "c.xyz"), "--part", "nas979", "--identify")
    assert r.returncode == 2 and "--identify needs --machine" in r.stderr


def test_a_failed_inspection_keeps_the_previous_report(tmp_path):
    p, _ = deformed_cone(per_ring=36)
    np.savetxt(tmp_path / "good.xyz", p)
    assert run("inspect", str(tmp_path / "good.xyz"), "--part", "nas979", "-o", str(tmp_path / "rep")).returncode == 0
    before = (tmp_path / "rep" / "report.json").read_text()
    (tmp_path / "bad.xyz").write_text("1 2 nan\n")
    assert run("inspect", str(tmp_path / "bad.xyz"), "--part", "nas979", "-o", str(tmp_path / "rep")).returncode == 3
    assert (tmp_path / "rep" / "report.json").read_text() == before


# ------------------------------------------------------------------------------ tolerances and the feature table ----
def _rows(report):
    return {(r["feature"], r["characteristic"]): r for r in report["feature_table"]}


def test_feature_table_judges_known_deviations_against_toml_tolerances(tmp_path):
    b_mm, taper = 0.003, 50e-6  # roundness 6 um in every section, half-angle error +50 urad
    p, _ = deformed_cone((0.0, 0.0), b_mm, taper, per_ring=180)
    (tmp_path / "tol.toml").write_text(
        "[default]\nroundness_um = 10.0\n[roundness_high]\nroundness_um = 5.0\n"
        "[cone_angle]\nhalf_angle_urad = [-30.0, 30.0]\n[diameter_ref]\ndiameter_um = [-20.0, 20.0]\n")
    rep = inspect_cloud(_cloud(p), "nas979", tolerances=tmp_path / "tol.toml").report
    rows = {r["feature"]: r for r in rep["feature_table"] if r["feature"] != "cone"}
    assert rows["roundness_low"]["result"] == "pass" and rows["roundness_mid"]["result"] == "pass"
    assert rows["roundness_high"]["result"] == "fail"  # its own 5 um over the default 10 um
    assert rows["roundness_high"]["actual"] == pytest.approx(2 * b_mm * 1e3, abs=1e-4)
    assert rows["roundness_high"]["tolerance"] == {"lower": 0.0, "upper": 5.0}
    angle = rows["cone_angle"]
    assert angle["nominal"] == 15.0 and angle["unit"] == "deg" and angle["deviation_unit"] == "urad"
    assert angle["deviation"] == pytest.approx(taper * 1e6, abs=0.05) and angle["result"] == "fail"
    # out by more than U = 2 std of the fit (the oval's residuals: 6.2 urad); against +-40 it was "uncertain"
    assert angle["uncertainty"]["k"] == 2.0 and 50.0 - 2 * angle["uncertainty"]["std"] > 30.0
    expected = -2 * 10.0 * (math.tan(ALPHA + taper) - math.tan(ALPHA)) * 1e3  # -17.5 um at h = 10 mm
    assert rows["diameter_ref"]["deviation"] == pytest.approx(expected, abs=1e-3)
    assert rows["diameter_ref"]["result"] == "pass"
    assert rows["axis_direction"]["result"] == "no tolerance"
    assert rep["feature_summary"] == {"pass": 3, "fail": 2, "uncertain": 0, "no tolerance": 3, "not measured": 0}


@pytest.mark.parametrize("deviation, std, tolerance, result", [
    (-165.1, 286.9, (-200.0, 200.0), "uncertain"),  # the QA pass' 12 points: judged "pass" before
    (-165.1, 10.0, (-200.0, 200.0), "pass"), (-185.0, 10.0, (-200.0, 200.0), "uncertain"),
    (-225.0, 10.0, (-200.0, 200.0), "fail"), (-215.0, 10.0, (-200.0, 200.0), "uncertain"),
    (150.0, None, (-200.0, 200.0), "pass"), (150.0, float("nan"), (-200.0, 200.0), "pass"),
    (4.5, 0.4, 5.0, "uncertain"), (3.9, 0.5, 5.0, "pass"), (6.1, 0.5, 5.0, "fail"),
])
def test_a_fits_uncertainty_decides_with_iso_14253_1s_rule(deviation, std, tolerance, result):
    """Conformance proven inside the tolerance less U = 2 std, non-conformance outside it by more than U, else
    "uncertain" (12 points gave -165 +- 287 urad, judged "pass" against +-200 urad; QA pass); no std: as before."""
    from trueaxis.inspect.tolerances import _row, summary

    key = "half_angle_urad" if isinstance(tolerance, tuple) else "roundness_um"
    row = _row("f", key, "c", "urad", 0.0, deviation, deviation, tolerance, std=std)
    assert row["result"] == result
    assert ("uncertainty" in row) == (std is not None) and summary([row])[result] == 1


def test_tolerances_in_the_part_json_apply_and_the_toml_wins(tmp_path):
    part = json.loads(json.dumps(NAS))
    next(f for f in part["features"] if f["id"] == "roundness_mid")["tolerances"] = {"roundness_um": 1.0}
    (tmp_path / "nas979.json").write_text(json.dumps(part))
    p, _ = deformed_cone((0.0, 0.0), 0.002, 0.0, per_ring=180)  # roundness 4 um
    rep = inspect_cloud(_cloud(p), "nas979", part_dir=tmp_path).report
    mid = next(r for r in rep["feature_table"] if r["feature"] == "roundness_mid")
    assert mid["result"] == "fail" and mid["tolerance"]["upper"] == 1.0
    (tmp_path / "tol.toml").write_text("[roundness_mid]\nroundness_um = 5.0\n")
    rep = inspect_cloud(_cloud(p), "nas979", part_dir=tmp_path, tolerances=tmp_path / "tol.toml").report
    mid = next(r for r in rep["feature_table"] if r["feature"] == "roundness_mid")
    assert mid["result"] == "pass" and mid["tolerance"]["upper"] == 5.0


@pytest.mark.parametrize("text, message", [
    ("[roundness_top]\nroundness_um = 5.0\n", "no feature 'roundness_top'"),
    ("[cone_angle]\nhalf_angle_urad = 40.0\n", "expected [lower, upper]"),
    ("[roundness_mid]\nroundness_um = [0, 5]\n", "one upper limit"),
    ("[roundness_mid]\nwidth_um = [-5, 5]\n", "has no width_um"),
    ("[default]\nflatness_um = 5\n", "unknown characteristic"),
    ("[cone_angle\n", "not valid TOML"),
])
def test_bad_tolerance_files_are_refused_naming_the_key(tmp_path, text, message):
    p, n = deformed_cone(per_ring=36)
    write_cloud_ply(tmp_path / "c.ply", p, n)
    (tmp_path / "tol.toml").write_text(text)
    r = run("inspect", str(tmp_path / "c.ply"), "--part", "nas979", "--tolerances", str(tmp_path / "tol.toml"),
            "-o", str(tmp_path / "rep"))
    assert r.returncode == 3 and message in r.stderr and "tol.toml" in r.stderr, r.stderr
    assert not (tmp_path / "rep").exists()


def test_report_folder_has_the_deviations_as_ply_scalar_field_and_csv(tmp_path):
    from plyfile import PlyData

    p, n = deformed_cone((0.0, 0.004), 0.002, 0.0, per_ring=90)
    result = inspect_cloud(_cloud(p, n), "nas979")
    out = write_report(result, tmp_path / "rep")
    vertex = PlyData.read(str(out / "deviations.ply"))["vertex"]
    np.testing.assert_array_equal(vertex["scalar_deviation_um"], result.deviation_um)
    np.testing.assert_array_equal(np.column_stack([vertex["x"], vertex["y"], vertex["z"]]), result.aligned)
    table = np.loadtxt(out / "deviations.csv", delimiter=",", skiprows=1, usecols=(0, 1, 2, 3))
    np.testing.assert_allclose(table[:, 3], result.deviation_um, atol=5e-5)
    assert set(np.loadtxt(out / "deviations.csv", delimiter=",", skiprows=1, usecols=4, dtype=str)) == {"cone"}
    rep = json.loads((out / "report.json").read_text())
    assert {"deviations.ply", "deviations.csv"} <= set(rep["files"])


def test_cad_without_its_part_json_is_refused_asking_for_the_json(tmp_path):
    # a STEP alone carries faces, not which slot, wall or section each is: every feature would be null
    p, n = deformed_cone(per_ring=36)
    write_cloud_ply(tmp_path / "c.ply", p, n)
    (tmp_path / "slots.step").write_text("ISO-10303-21;\nEND-ISO-10303-21;\n")
    r = run("inspect", str(tmp_path / "c.ply"), "--part", "slots", "--cad", str(tmp_path / "slots.step"),
            "-o", str(tmp_path / "rep"))
    assert r.returncode == 3 and "no part JSON beside it (slots.json)" in r.stderr, r.stderr
    assert "trueaxis part slots -o DIR" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "rep").exists()


# ------------------------------------------------------------------------------- the report in a real browser ----
_IMAGE_PROBE = ("<script>window.addEventListener('load', function () { var imgs = Array.prototype.slice.call("
                "document.images); document.body.setAttribute('data-images', imgs.length + ':' + imgs.filter("
                "function (i) { return i.complete && i.naturalWidth > 0; }).length); });</script>")


@pytest.mark.external
def test_html_report_renders_in_headless_chromium_with_its_images_and_header(tmp_path):
    from conftest import require_program
    from PIL import Image

    exe = require_program("chromium", "chromium", "the browser check of the HTML report")
    p, n = deformed_cone((0.0, 0.004), 0.003, 30e-6, per_ring=120)
    (tmp_path / "tol.toml").write_text("[default]\nroundness_um = 10.0\n")  # roundness 6 um: pass
    result = inspect_cloud(_cloud(p, n), "nas979", tolerances=tmp_path / "tol.toml", program="cone.ngc",
                           machine="nmv1500dcg.toml")
    out = write_report(result, tmp_path / "rep")
    page = out / "report.html"
    # the page as it is, plus a probe that records on load how many images decoded (naturalWidth > 0)
    probe = tmp_path / "probe.html"
    probe.write_text(page.read_text(encoding="utf-8").replace("</body>", _IMAGE_PROBE + "</body>"), encoding="utf-8")
    common = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--virtual-time-budget=5000"]
    dom = subprocess.run(common + ["--dump-dom", probe.as_uri()], capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, dom.stderr[-1000:]
    images = [name for name in json.loads((out / "report.json").read_text())["files"] if name.endswith(".png")]
    assert len(images) == 3  # deviation map, histogram, roundness
    assert f'data-images="{len(images)}:{len(images)}"' in dom.stdout, dom.stdout[-300:]
    # the header a metrologist signs: date, part, program, machine file, version, alignment
    assert "id=\"report-header\"" in dom.stdout
    for text in ("date (UTC)", "NAS 979 cone frustum", "cone.ngc", "nmv1500dcg.toml", "trueaxis version",
                 "alignment", "Feature table", "Sign-off"):
        assert text in dom.stdout, text
    shot = tmp_path / "shot.png"
    run_shot = subprocess.run(common + [f"--screenshot={shot}", "--window-size=1200,2400", page.as_uri()],
                              capture_output=True, text=True, timeout=120)
    assert run_shot.returncode == 0 and shot.is_file(), run_shot.stderr[-1000:]
    pixels = np.asarray(Image.open(shot).convert("L"), dtype=float)
    assert pixels.shape == (2400, 1200)
    # rendered, not blank: dark text on white, and the green rows of the feature table
    assert (pixels < 100).mean() > 0.002 and (pixels > 240).mean() > 0.5
    colour = np.asarray(Image.open(shot).convert("RGB"), dtype=int)
    assert np.any((colour[..., 1] > 230) & (colour[..., 0] < 225) & (colour[..., 2] < 225))  # a "pass" row


def test_report_json_carries_the_header_and_the_plotted_figures(tmp_path):
    p, n = deformed_cone((0.0, 0.0), 0.003, 0.0, per_ring=120)
    result = inspect_cloud(_cloud(p, n), "nas979", program="cone.ngc")
    # identification as run_identification reports it (DESIGN §7): value and std with their units
    result.report["identification"] = {"parameters": [{"name": "XOC", "value_um": -21.853, "std_um": 0.114},
                                                      {"name": "AOC", "value_urad": -38.84, "std_urad": 1.43}],
                                       "not_identifiable": ["COC"], "residual_rms_um": 0.5}
    out = write_report(result, tmp_path / "rep")
    rep = json.loads((out / "report.json").read_text())
    header = rep["header"]
    assert header["part"] == "NAS 979 cone frustum" and header["program"] == "cone.ngc"
    assert header["machine_file"] is None and header["trueaxis_version"] and header["date_utc"].endswith("UTC")
    assert header["alignment"].startswith("none")
    figures = rep["figures"]
    assert sum(figures["histogram"]["counts"]) == len(p)
    for ring, section in zip(figures["roundness"], rep["roundness_um"]):
        # the plotted profile is the least-squares residual of the section: its peak-to-valley is the LS roundness
        assert np.ptp(ring["residual_um"]) == pytest.approx(section["least_squares"], abs=2e-4)
    assert figures["identified"]["names"] == ["XOC", "AOC"] and figures["identified"]["std"] == [0.114, 1.43]
    page = (out / "report.html").read_text()
    assert "<td>XOC</td><td>-21.85</td><td>&ndash;</td><td>0.11</td><td>um</td>" in page  # no change given
    assert "<td>AOC</td><td>-38.8</td><td>&ndash;</td><td>1.4</td><td>urad</td>" in page
    assert "identified.png" in rep["files"] and "mean -0.0" not in page
    assert "components" not in figures  # no component-error tables identified


def test_identified_component_errors_are_plotted_against_position(tmp_path):
    p, n = deformed_cone(per_ring=60)
    result = inspect_cloud(_cloud(p, n), "nas979")
    table = [("EXX@100", 2.0, 0.3), ("EXX@-100", -2.1, 0.3), ("EXX@0", 0.1, 0.2), ("EAC@90", 4.0, 1.0),
             ("EAC@0", 1.0, 1.0), ("XOC", 5.0, 0.1)]
    result.report["identification"] = {"parameters": [
        {"name": name, f"value_{'urad' if name[1] in 'ABC' else 'um'}": v,
         f"std_{'urad' if name[1] in 'ABC' else 'um'}": sd} for name, v, sd in table]}
    out = write_report(result, tmp_path / "rep")
    rep = json.loads((out / "report.json").read_text())
    components = rep["figures"]["components"]
    assert components["EXX"] == {"position": [-100.0, 0.0, 100.0], "value": [-2.1, 0.1, 2.0],
                                 "std": [0.3, 0.2, 0.3], "unit": "um"}
    assert components["EAC"]["position"] == [0.0, 90.0] and components["EAC"]["unit"] == "urad"
    assert "components.png" in rep["files"] and (out / "components.png").stat().st_size > 1000


def test_dense_roundness_profiles_are_drawn_as_bins_that_keep_every_peak():
    from trueaxis.inspect.report import _profile_for_plot

    rng = np.random.default_rng(6)
    angle = rng.uniform(-np.pi, np.pi, 50_000)
    residual = 3.0 * np.cos(3 * angle) + rng.normal(0, 0.5, angle.size)
    centre, high, low = _profile_for_plot(angle, residual)
    assert len(centre) <= 1440 and np.all(np.diff(centre) > 0)
    assert high.max() == residual.max() and low.min() == residual.min() and np.all(high >= low)
    bin_of = np.minimum(((angle + np.pi) / (2 * np.pi) * 1440).astype(int), 1439)
    k = bin_of[np.argmax(residual)]
    assert abs(centre[np.argmax(high)] - ((k + 0.5) * 2 * np.pi / 1440 - np.pi)) < 1e-12


# ------------------------------------------------------------------------------------------ the figure worker ----
def _report_files(folder):
    """Every file of a report folder as bytes, report.json and report.html without their date line."""
    out = {}
    for path in sorted(folder.iterdir()):
        data = path.read_bytes()
        if path.suffix in (".json", ".html"):
            data = b"".join(line for line in data.splitlines(keepends=True) if b"date_utc" not in line
                            and b"date (UTC)" not in line)
        out[path.name] = data
    return out


def test_the_figure_worker_writes_the_same_report_byte_for_byte(tmp_path):
    from trueaxis.inspect.workers import FigureWorker, single_blas_thread

    p, n = deformed_cone((0.002, -0.001), 0.003, 1e-5, per_ring=240)
    p = np.vstack([p, block_faces(150)])
    here = write_report(inspect_cloud(_cloud(p), "nas979"), tmp_path / "here")
    with FigureWorker() as worker, single_blas_thread():
        assert worker.running
        result = inspect_cloud(_cloud(p), "nas979", figure_worker=worker)
        there = write_report(result, tmp_path / "worker", figure_worker=worker)
        assert worker.failures == []
    files_here, files_there = _report_files(here), _report_files(there)
    assert set(files_here) == {"report.json", "report.html", "deviations.ply", "deviations.csv",
                               "deviation_map.png", "histogram.png", "roundness.png", ".trueaxis-output"}
    assert files_here == files_there


def test_the_figure_worker_falls_back_to_drawing_here_when_its_process_dies(tmp_path):
    import os
    import signal

    from trueaxis.inspect.report import _figure_inputs, draw_figure
    from trueaxis.inspect.workers import FigureWorker

    p, _ = deformed_cone(per_ring=60)
    inputs = _figure_inputs(inspect_cloud(_cloud(p), "nas979"))
    with FigureWorker() as worker:
        os.kill(worker._pid, signal.SIGKILL)
        for item in inputs:
            worker.submit(item)
        drawn = worker.results()
        assert worker.failures and not worker.running
    assert [d[1] for d in drawn] == [draw_figure(item)[1] for item in inputs]


def test_single_blas_thread_sets_one_thread_and_restores_the_count():
    import os

    from trueaxis.inspect.workers import _loaded_openblas, single_blas_thread

    libraries = _loaded_openblas()
    assert libraries, "numpy's OpenBLAS is loaded and found"
    before = [getter() for _, getter in libraries]
    env = os.environ.get("OPENBLAS_NUM_THREADS")
    with single_blas_thread():
        assert [getter() for _, getter in libraries] == [1] * len(libraries)
        assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
    assert [getter() for _, getter in libraries] == before and os.environ.get("OPENBLAS_NUM_THREADS") == env


def test_keep_freed_memory_reuses_the_heap_for_large_temporary_arrays():
    # in a child process: the malloc setting lasts for the rest of the process
    code = """
import resource, numpy as np
from trueaxis.inspect.workers import keep_freed_memory
def faults():
    start = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        a = np.ones(1_000_000); b = a * 2; del a, b
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - start
faults(); before = faults()
assert keep_freed_memory()
faults(); after = faults()
print(before, after)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    before, after = int(out[0]), int(out[1])
    # 20 arrays of 8 MB: hundreds of page faults each when every array is mapped afresh (fewer with numpy's huge
    # pages); next to none once the heap keeps the freed memory
    assert before > 2_000 and after < before / 10


def test_the_cad_mesh_is_built_only_when_a_point_is_far_from_every_analytic_surface(tmp_path):
    (tmp_path / "nas979.json").write_text(json.dumps(NAS))
    dv.nas979_mesh(NAS).write_ply(tmp_path / "nas979.ply")
    p, n = deformed_cone(per_ring=90)
    near = inspect_cloud(_cloud(p), "nas979", cad=tmp_path / "nas979.ply")
    cad = near.report["reference"]["cad_mesh"]
    assert cad["triangles"] is None and cad["note"].startswith("not tessellated")
    assert cad["source"] == str(tmp_path / "nas979.ply") and near.report["reference"]["analytic_points"] == len(p)
    # a tenth of the points 0.8 mm outside the cone (beyond the 0.5 mm gate): the mesh is loaded and consulted; the
    # cone stays their nearest surface, so their deviations are the exact 0.8 mm
    moved = p.copy()
    moved[::10] += 0.8 * n[::10]
    far = inspect_cloud(_cloud(moved), "nas979", cad=tmp_path / "nas979.ply")
    assert far.report["reference"]["cad_mesh"]["triangles"] > 1000
    assert np.allclose(far.deviation_um[::10], 800.0, atol=1e-6)
    assert np.array_equal(far.deviation_um[1::10], near.deviation_um[1::10])


def test_tessellating_a_step_is_announced_before_it_starts(tmp_path):
    (tmp_path / "nas979.json").write_text(json.dumps(NAS))
    (tmp_path / "nas979.step").write_text("ISO-10303-21;\nEND-ISO-10303-21;\n")  # unreadable: refused after the line
    p, n = deformed_cone(per_ring=60)
    p[::10] += 0.8 * n[::10]  # beyond the gate: these points need the CAD
    lines = []
    with pytest.raises(dv.InspectionError, match="cannot read the STEP"):
        inspect_cloud(_cloud(p), "nas979", cad=tmp_path / "nas979.step", progress=lines.append)
    assert len(lines) == 1 and lines[0].startswith(f"{tmp_path / 'nas979.step'}: tessellating the STEP")
    lines.clear()
    inspect_cloud(_cloud(p[1::10]), "nas979", cad=tmp_path / "nas979.step", progress=lines.append)
    assert lines == []  # every point near the cone: the STEP is not even read


# ------------------------------------------------------------------------- what cannot be measured is said so ----
def test_a_section_probed_over_half_its_circle_is_not_measured_and_the_cone_says_why():
    """An oval of 10 um probed over half the circle shows about a third of its roundness (a silent pass): a section
    whose points leave a gap above MAX_SECTION_GAP_DEG is "not measured", the cone's partial coverage is a warning;
    the full oval's minimum-zone roundness is 2 x 10 um / cos(15 deg) (the normal offset, radially)."""
    from trueaxis.inspect.report import MAX_SECTION_GAP_DEG, inspection_warnings

    heights, theta = np.arange(1.0, 20.0, 0.25), np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    s, th = (v.ravel() for v in np.meshgrid(heights, theta, indexing="ij"))
    radial = np.cos(th)[:, None] * U + np.sin(th)[:, None] * W
    normal = math.cos(ALPHA) * radial + math.sin(ALPHA) * AXIS
    full = s[:, None] * AXIS + (CONE["base_radius"] - s * math.tan(ALPHA))[:, None] * radial \
        + (0.010 * np.cos(2 * th))[:, None] * normal
    report = inspect_cloud(_cloud(full), "nas979").report
    for ring in report["roundness_um"]:
        assert ring["minimum_zone"] == pytest.approx(20.0 / math.cos(ALPHA), abs=0.05)
        assert ring["largest_gap_deg"] < MAX_SECTION_GAP_DEG
    half = inspect_cloud(_cloud(full[th < np.pi]), "nas979").report
    # half the circle: a gap of 180 deg plus one sampling step (0.5 deg), seen from the fitted axis
    assert all(ring["minimum_zone"] is None and re.search(r"gap of 18[01] deg", ring["note"])
               for ring in half["roundness_um"])
    rows = [row for row in half["feature_table"] if row["key"] == "roundness_um"]
    assert rows and all(row["result"] == "not measured" for row in rows)
    warnings = inspection_warnings(half)
    assert any(re.search(r"gap of 18[01] deg about its axis", w) for w in warnings)
    assert any("3 characteristics not measured" in w for w in warnings)



def test_a_cone_probed_on_one_ring_is_not_measured_and_never_passes(tmp_path):
    """Twelve points on one ring (as `simulate --points 12` probes it) fit a whole family of cones: the fit made up a
    75 deg half angle, a diameter of -75 mm and an axis that "passed" its tolerances, with a standard error of 6e-7
    urad. The cone's characteristics are "not measured", the report says why; two rings determine it again."""
    p, n = deformed_cone((0.004, -0.003), 0.0, 0.0, heights=[10.0], per_ring=12)
    p = p + np.random.default_rng(5).normal(0.0, 0.001, len(p))[:, None] * n
    write_cloud_ply(tmp_path / "ring.ply", p, n)
    (tmp_path / "tol.toml").write_text("[default]\nroundness_um = 10.0\n[cone_angle]\nhalf_angle_urad = [-50.0, 50.0]\n"
                                       "[diameter_ref]\ndiameter_um = [-20.0, 20.0]\n[axis_direction]\n"
                                       "tilt_urad = 100.0\n[cone]\nform_um = 30.0\naxis_offset_um = 25.0\n")
    r = run("inspect", str(tmp_path / "ring.ply"), "--part", "nas979", "--tolerances", str(tmp_path / "tol.toml"),
            "-o", str(tmp_path / "rep"))
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert report["cone"] is None and report["cone_error_amplification"] > 1000
    assert "do not determine it" in report["cone_note"] and "span 0.0" in report["cone_note"]
    assert {row["result"] for row in report["feature_table"]} == {"not measured"}
    cone_rows = [row for row in report["feature_table"] if row["key"] != "roundness_um"]
    assert len(cone_rows) == 5 and all("do not determine it" in row["note"] for row in cone_rows)
    assert "8 NOT MEASURED" in r.stdout and "half angle error" not in r.stdout
    assert "do not determine it" in r.stderr
    # the same ring and one more, 16 mm apart: the cone is determined, its eccentricity measured
    p2, n2 = deformed_cone((0.004, -0.003), 0.0, 0.0, heights=[2.0, 18.0], per_ring=12)
    two = inspect_cloud(_cloud(p2, n2), "nas979", tolerances=tmp_path / "tol.toml").report
    assert two["cone"]["error_amplification"] < 20
    assert math.hypot(*two["cone"]["axis_offset_um"]) == pytest.approx(5.0, abs=0.01)

def test_a_slot_wall_beyond_the_gate_is_not_measured_nor_its_worst_of_characteristics():
    """A wall moved 0.6 mm (beyond the 0.5 mm gate) leaves its segment's width unmeasured: the position and
    parallelism ("largest |offset|", "worst segment") are then unknown too, not the worst of the others; the points
    beyond the gate are counted."""
    from trueaxis.inspect.report import inspection_warnings
    from trueaxis.workpiece.slot_block import slot_pattern

    p, n = slot_pattern(SLOTS, 6000)
    d = dv.analytic_deviation(p, dv.analytic_surfaces(SLOTS))
    ids = np.array(d.surface_ids)[d.surface]
    moved = p + np.where(ids == "slot_none_seg0_left", -0.6, 0.0)[:, None] * n
    report = inspect_cloud(_cloud(moved), "slots").report
    slot = next(s for s in report["slots"] if s["id"] == "slot_none")
    assert slot["width"]["segments"][0]["width_mm"] is None and "left 0" in slot["width"]["segments"][0]["note"]
    assert slot["position_um"]["max_abs"] is None
    rows = {row["key"]: row for row in report["feature_table"] if row["feature"] == "slot_none"}
    assert rows["position_um"]["result"] == rows["parallelism_um"]["result"] == "not measured"
    assert report["beyond_gate"]["points"] == int((ids == "slot_none_seg0_left").sum())
    assert any("not measured" in w for w in inspection_warnings(report))


def test_a_slot_contour_from_two_stray_points_is_not_measured():
    """Only the first slot probed, and two stray points on another slot's end cap: that slot's mean contour error
    needs every wall and arc, so it is "not measured" (it passed on two points)."""
    from trueaxis.workpiece.slot_block import slot_pattern

    p, n = slot_pattern(SLOTS, 6000)
    d = dv.analytic_deviation(p, dv.analytic_surfaces(SLOTS))
    ids = np.array(d.surface_ids)[d.surface]
    others = ~np.char.startswith(ids.astype(str), "slot_none")
    caps = np.flatnonzero(others & np.char.startswith(ids.astype(str), "slot_geometric") & np.char.find(
        ids.astype(str), "arc").__ge__(0))[:2]
    keep = ~others
    keep[caps] = True
    report = inspect_cloud(_cloud(p[keep]), "slots").report
    geometric = next(s for s in report["slots"] if s["id"] == "slot_geometric")
    assert geometric["mean_contour_error_um"] is None and "not evaluated" in geometric["contour_note"]
    none = next(s for s in report["slots"] if s["id"] == "slot_none")
    assert none["mean_contour_error_um"] == pytest.approx(0.0, abs=1e-6)


def test_a_flyer_does_not_refuse_the_cloud_and_is_counted_beyond_the_gate():
    p, _ = deformed_cone(per_ring=90)
    report = inspect_cloud(_cloud(np.vstack([p, [[0.0, 0.0, 40.0]]])), "nas979").report
    assert report["beyond_gate"]["points"] == 1
    assert report["cone"]["half_angle_error_urad"] == pytest.approx(0.0, abs=1e-3)


def test_a_cloud_turned_180_deg_about_z_is_refused_with_its_share_beyond_the_gate_and_nothing_written(tmp_path):
    """A cone turned 180 deg about Z (--align none, the default) has 64 % of its points beyond the gate: it was
    inspected (exit 0, a warning) with a half angle error of +3498 urad and a form of 1177 um as its figures. Refused
    (exit 3, nothing written), saying the share and the alignments that bring such a cloud onto the part; the best
    fit does."""
    p, _ = deformed_cone(per_ring=90)
    turned = p * np.array([-1.0, -1.0, 1.0])  # 180 deg about Z
    beyond = np.abs(dv.analytic_deviation(turned, dv.analytic_surfaces(NAS)).deviation_mm) > 0.5
    assert (beyond.sum(), len(p)) == (1090, 1710)
    write_cloud_ply(tmp_path / "turned.ply", turned)
    r = run("inspect", str(tmp_path / "turned.ply"), "--part", "nas979", "-o", str(tmp_path / "rep"))
    assert r.returncode == 3 and r.stdout == ""
    assert "1090 of 1710 points (63.7 %) lie more than 0.5 mm from every surface" in r.stderr
    assert "more than the 10 % a measurement's flyers may take" in r.stderr
    assert ("try --align bestfit (a cloud within about a mm of the part frame: a refinement, not a search) or "
            "--align datum") in r.stderr
    assert not (tmp_path / "rep").exists()
    fitted = inspect_cloud(_cloud(turned), "nas979", align="bestfit").report
    assert fitted["beyond_gate"]["points"] == 0 and abs(fitted["cone"]["half_angle_error_urad"]) < 1e-3


def test_inspect_and_diagnose_refuse_above_one_share_of_points_beyond_the_gate():
    """One threshold for both commands (``flyers.MAX_BEYOND_GATE``, 10 %): 171 of 1710 points 1 mm off are flyers
    (the figures those of the clean cone), 172 refuse the cloud."""
    from trueaxis.diagnose import report as diagnose_report
    from trueaxis.inspect import flyers

    assert diagnose_report.MAX_BEYOND_GATE is flyers.MAX_BEYOND_GATE == 0.1
    p, n = deformed_cone(per_ring=90)
    off = np.arange(len(p)) % 10 == 3
    assert off.sum() == 171
    report = inspect_cloud(_cloud(p + np.where(off, 1.0, 0.0)[:, None] * n), "nas979").report
    assert report["beyond_gate"]["points"] == 171 and report["beyond_gate"]["share"] == 0.1
    assert abs(report["cone"]["half_angle_error_urad"]) < 1e-3 and report["deviation_um"]["rms"] < 1e-6
    off[4] = True
    with pytest.raises(dv.InspectionError, match=r"172 of 1710 points \(10\.1 %\) lie more than 0\.5 mm"):
        inspect_cloud(_cloud(p + np.where(off, 1.0, 0.0)[:, None] * n), "nas979")


def test_a_cloud_given_three_times_is_read_once_and_its_repeats_counted(tmp_path):
    """The same cloud concatenated three times: the 2n points that repeat another exactly are dropped by the reader
    (they doubled the weight of their points in the fits: a QA pass's twin changed) and counted in the warning and
    report.json; every figure is then that of the cloud given once, to the last digit."""
    from trueaxis.inspect.report import inspection_warnings

    p, n = deformed_cone((0.010, 0.0), 0.002, per_ring=90)
    write_cloud_ply(tmp_path / "once.ply", p, n)
    once = inspect_cloud(str(tmp_path / "once.ply"), "nas979").report
    assert once["duplicate_points"] == 0 and not any("repeat another point" in w for w in inspection_warnings(once))
    write_cloud_ply(tmp_path / "thrice.ply", np.vstack([p, p, p]), np.vstack([n, n, n]))
    r = run("inspect", str(tmp_path / "thrice.ply"), "--part", "nas979", "-o", str(tmp_path / "rep"))
    assert r.returncode == 0, r.stderr
    assert (f"warning: {2 * len(p)} of {3 * len(p)} points repeat another point exactly (the same x, y, z): dropped, "
            f"the figures and any identification use the {len(p)} distinct points") in r.stderr
    thrice = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert thrice["duplicate_points"] == 2 * len(p) == 3420 and thrice["points"] == len(p) == 1710
    assert thrice["deviation_um"] == once["deviation_um"]
    assert thrice["cone"]["half_angle_error_urad"] == once["cone"]["half_angle_error_urad"]
    assert thrice["cone"]["form_um"] == once["cone"]["form_um"]
    assert [row["actual"] for row in thrice["feature_table"]] == [row["actual"] for row in once["feature_table"]]


def test_flyers_within_the_gate_are_said_with_the_feature_values_without_them(tmp_path):
    """Three points of the h = 2 mm ring pushed 0.3 mm out (within the gate: in the features) made the roundness
    there and the cone's form about 300 um, with no word from plain inspect while --identify named them flyers. The
    same screen now runs in every inspection: the feature values stay the measured ones (with the points), each
    row gets the value without them, which is the value of the cloud without those points (an inspection of that
    cloud, the reference), and the terminal, report.json and the page say it. A clean cloud: nothing is said and no
    row changes."""
    from trueaxis.inspect.report import inspection_warnings

    p, n = deformed_cone((0.010, 0.0), 0.002, per_ring=90)
    p = p + np.random.default_rng(4).normal(0.0, 0.0005, len(p))[:, None] * n  # 0.5 um probe noise
    pushed = np.array([95, 120, 150])  # on the ring at h = 2 mm (ring-major: 90 points a ring)
    flown = p.copy()
    flown[pushed] += 0.3 * n[pushed]
    clean = inspect_cloud(_cloud(p), "nas979").report
    assert clean["flyers_within_gate"]["points"] == 0
    assert not any("without_flyers" in row for row in clean["feature_table"])
    assert not any("flyers" in w for w in inspection_warnings(clean))
    reference = inspect_cloud(_cloud(np.delete(flown, pushed, axis=0)), "nas979").report
    write_cloud_ply(tmp_path / "flown.ply", flown, n)
    r = run("inspect", str(tmp_path / "flown.ply"), "--part", "nas979", "-o", str(tmp_path / "rep"))
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "rep" / "report.json").read_text())
    said = report["flyers_within_gate"]
    # 300 um pushed, on the cone's own 10 um eccentricity and 2 um ovality: within 12 um (and the noise) of 300
    assert said["points"] == 3 and all(abs(w["deviation_um"] - 300.0) < 13.0 for w in said["where"])
    assert said["largest_um"] == max(w["deviation_um"] for w in said["where"])
    rows = {(row["feature"], row["key"]): row for row in report["feature_table"]}
    low = rows[("roundness_low", "roundness_um")]
    assert low["actual"] > 299.0 and rows[("cone", "form_um")]["actual"] > 299.0  # the measured values, as before
    for row, ref in zip(report["feature_table"], reference["feature_table"]):
        assert row["without_flyers"]["actual"] == pytest.approx(ref["actual"], rel=1e-12, abs=1e-12), row["key"]
    assert low["without_flyers"]["actual"] < 10.0
    assert report["cone"]["half_angle_error_urad"] != pytest.approx(reference["cone"]["half_angle_error_urad"])
    warning = next(w for w in r.stderr.splitlines() if "depart from nearly every neighbour" in w)
    assert "3 of 1710 points within the 0.5 mm gate" in warning
    assert "the feature values keep them, as measured" in warning
    assert (f"roundness at h = 2 mm (roundness_low) {low['actual']:.1f} -> {low['without_flyers']['actual']:.1f} um"
            in warning)
    half = rows[("cone_angle", "half_angle_urad")]["without_flyers"]["deviation"]
    assert f"({half:+.1f} without the 3 flyers)" in r.stdout
    page = (tmp_path / "rep" / "report.html").read_text()
    assert "without the flyers (deviation, result)" in page and "depart from nearly every neighbour" in page


def test_flyer_screen_of_plain_inspect_stops_above_its_size_unless_asked(monkeypatch):
    """The screen's neighbour search costs about 4 s a million points (the inspection of a million: 2 s): a plain
    inspection screens clouds up to FLYER_SCREEN_MAX_POINTS and says in report.json that a larger one was not
    screened; asked (--identify asks), it screens any size."""
    from trueaxis.inspect import report as report_module

    p, n = deformed_cone((0.010, 0.0), 0.002, per_ring=90)
    p[[95, 120, 150]] += 0.3 * n[[95, 120, 150]]
    monkeypatch.setattr(report_module, "FLYER_SCREEN_MAX_POINTS", len(p) - 1)
    unscreened = inspect_cloud(_cloud(p, n), "nas979").report
    assert unscreened["flyers_within_gate"]["points"] is None
    assert "not screened: 1710 points, more than 1709" in unscreened["flyers_within_gate"]["note"]
    assert not any("without_flyers" in row for row in unscreened["feature_table"])
    assert inspect_cloud(_cloud(p, n), "nas979", flyer_screen=True).report["flyers_within_gate"]["points"] == 3
    monkeypatch.setattr(report_module, "FLYER_SCREEN_MAX_POINTS", len(p))
    assert inspect_cloud(_cloud(p, n), "nas979").report["flyers_within_gate"]["points"] == 3


def test_flyers_are_counted_apart_from_the_headline_figures(tmp_path):
    """0.5 % of the points 500 mm off (flyers the product itself says belong to no feature) made the headline
    "deviation rms 33908.67 um" and a one-bar histogram. The headline, the by-surface figures and the pictures are
    over the points on the part (within the gate): the same as the cloud without the flyers; those are counted and
    described apart."""
    p, n = deformed_cone((0.010, 0.0), 0.002, per_ring=90)
    clean = inspect_cloud(_cloud(p), "nas979").report
    flyers = np.arange(len(p)) % 200 == 7  # 0.5 %
    moved = np.where(flyers[:, None], p + 500.0 * n, p)
    write_cloud_ply(tmp_path / "fly.ply", moved)
    r = run("inspect", str(tmp_path / "fly.ply"), "--part", "nas979", "-o", str(tmp_path / "rep"))
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "rep" / "report.json").read_text())
    for key in ("rms", "min", "max", "p95"):
        assert report["deviation_um"][key] == pytest.approx(clean["deviation_um"][key], abs=1e-6)
    assert report["deviation_um"]["points"] == len(p) - flyers.sum()
    assert report["deviation_by_surface_um"]["cone"]["rms"] == pytest.approx(clean["deviation_by_surface_um"]["cone"]
                                                                                ["rms"], abs=1e-6)
    apart = report["beyond_gate"]
    assert apart["points"] == flyers.sum() and apart["deviation_um"]["min"] > 100_000  # far from every surface
    histogram = report["figures"]["histogram"]
    assert sum(histogram["counts"]) == len(p) - flyers.sum() and histogram["bin_edges_um"][-1] < 100
    assert f"{clean['deviation_um']['rms']:.2f} um" in r.stdout
    assert f"({flyers.sum()} beyond the gate apart)" in r.stdout
    page = (tmp_path / "rep" / "report.html").read_text()
    assert f"{flyers.sum()} beyond the 0.5 mm gate" in page

