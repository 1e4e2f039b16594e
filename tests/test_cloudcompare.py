"""Our deviations against an independent program: CloudCompare's cloud-to-mesh distances (C2M) on the same cloud and
the same fine mesh of the NAS 979 cone. They must agree within 0.5 um plus the mesh's chord error."""

from __future__ import annotations

import numpy as np
import pytest

from cloudcompare_helpers import cloudcompare_c2m, require_cloudcompare
from trueaxis.inspect import deviation as dv
from trueaxis.inspect.cloud import write_cloud_ply
from trueaxis.workpiece.parts import cone_surface_points, nas979_description

pytestmark = pytest.mark.external


@pytest.fixture(scope="module")
def cone_case(tmp_path_factory):
    exe = require_cloudcompare()
    work = tmp_path_factory.mktemp("cc")
    part = nas979_description()
    cone = part["surfaces"][0]
    rng = np.random.default_rng(11)
    points, normals = cone_surface_points(cone, rng.uniform(0.5, 19.5, 40), 250)
    # +-30 um of form error along the normal: material left (+) and removed (-)
    offset_mm = rng.uniform(-0.030, 0.030, len(points))
    points = points + offset_mm[:, None] * normals
    mesh = dv.cone_frustum_mesh(cone, chord_error_mm=5e-5)
    mesh.write_ply(work / "cone_mesh.ply")
    write_cloud_ply(work / "cloud.ply", points)
    c2m_mm, _, _, log = cloudcompare_c2m(work / "cloud.ply", work / "cone_mesh.ply", work, exe)
    return part, mesh, points, offset_mm, c2m_mm, log


def test_analytic_deviations_agree_with_cloudcompare_c2m(cone_case):
    part, mesh, points, offset_mm, c2m_mm, log = cone_case
    assert len(c2m_mm) == len(points), log[-500:]
    ours = dv.deviation(points, dv.analytic_surfaces(part)).deviation_mm
    np.testing.assert_allclose(ours, offset_mm, atol=1e-12)
    bound_um = 0.5 + mesh.chord_error_mm * 1e3
    diff_um = (c2m_mm - ours) * 1e3
    assert np.abs(diff_um).max() <= bound_um, f"max |CloudCompare - ours| = {np.abs(diff_um).max():.4f} um"


def test_raycast_deviations_agree_with_cloudcompare_c2m(cone_case):
    part, mesh, points, _, c2m_mm, _ = cone_case
    ours = dv.MeshDistance(mesh).signed_distance(points)[0]
    # the same mesh: only the float32 arithmetic of the two programs differs
    assert np.abs((c2m_mm - ours) * 1e3).max() <= 0.5
