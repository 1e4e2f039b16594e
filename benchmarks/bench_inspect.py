"""Benchmark: deviations of 1,000,000 points from the NAS 979 cone CAD, ours against CloudCompare's C2M.
Goal (issue: inspection): our deviation computation no slower than CloudCompare's cloud-to-mesh distances on the same
cloud and the same mesh. Prints the figures for the README.

Ours: ``trueaxis.inspect.deviation.deviation`` on the part's analytic surfaces (all eight NAS 979 patches: each point
assigned to its nearest one, exact), timed alone and with reading the binary PLY; also the open3d raycast on the
fine mesh (what is used where no analytic surface exists). CloudCompare: ``-C2M_DIST`` on the same cloud (binary PLY)
and the same mesh (chord error 0.05 um), its own "ComputeDistances" time and the wall time of the whole run (loading
and writing the ASCII result included). Agreement of the two is printed too.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_inspect.py [--points 1000000]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from cloudcompare_helpers import cloudcompare_c2m, find_cloudcompare  # noqa: E402
from trueaxis.inspect import deviation as dv  # noqa: E402
from trueaxis.inspect.cloud import read_cloud, write_cloud_ply  # noqa: E402
from trueaxis.inspect.parts import nas979_description  # noqa: E402


def cone_cloud(cone: dict, n: int, seed: int = 0):
    """n points on the cone at random heights and angles, moved +-30 um along the normal; (points, offsets mm)."""
    rng = np.random.default_rng(seed)
    a = np.asarray(cone["axis"])
    u, w = dv._axis_basis(a)
    alpha = np.radians(cone["half_angle_deg"])
    s = rng.uniform(0.2, cone["height_range"][1] - 0.2, n)
    th = rng.uniform(0, 2 * np.pi, n)
    radial = np.cos(th)[:, None] * u + np.sin(th)[:, None] * w
    normal = np.cos(alpha) * radial + np.sin(alpha) * a
    offset = rng.uniform(-0.03, 0.03, n)
    points = s[:, None] * a + (cone["base_radius"] - s * np.tan(alpha))[:, None] * radial + offset[:, None] * normal
    return points, offset


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=1_000_000)
    args = ap.parse_args()
    part = nas979_description()
    cone = part["surfaces"][0]
    surfaces = dv.analytic_surfaces(part)
    points, offset = cone_cloud(cone, args.points)
    mesh = dv.cone_frustum_mesh(cone, chord_error_mm=5e-5)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        write_cloud_ply(work / "cloud.ply", points)
        mesh.write_ply(work / "cone_mesh.ply")

        t0 = time.perf_counter()
        cloud = read_cloud(work / "cloud.ply")
        t_read = time.perf_counter() - t0
        t0 = time.perf_counter()
        ours = dv.deviation(cloud.points, surfaces)
        t_ours = time.perf_counter() - t0
        t0 = time.perf_counter()
        scene = dv.MeshDistance(mesh)
        t_scene = time.perf_counter() - t0
        t0 = time.perf_counter()
        ray = scene.signed_distance(cloud.points)[0]
        t_ray = time.perf_counter() - t0

        print(f"cloud: {len(points):,} points on the NAS 979 cone (+-30 um); mesh: {len(mesh.triangles):,} triangles, "
              f"chord error {mesh.chord_error_mm * 1e3:.3f} um")
        print(f"ours, analytic (8 patches, exact):   {t_ours:7.3f} s   (+ {t_read:.3f} s reading the PLY)")
        print(f"ours, open3d raycast on the mesh:    {t_ray:7.3f} s   (+ {t_scene:.3f} s building the scene)")
        print(f"  |analytic - truth| max {np.abs(ours.deviation_mm - offset).max() * 1e3:.2e} um; "
              f"raycast - analytic {((ray - ours.deviation_mm) * 1e3).min():+.4f}..{((ray - ours.deviation_mm) * 1e3).max():+.4f} um")
        exe = find_cloudcompare()
        if exe is None:
            print("CloudCompare: not installed (Debian package cloudcompare); no comparison")
            return
        c2m, t_cc, wall, _ = cloudcompare_c2m(work / "cloud.ply", work / "cone_mesh.ply", work, exe)
        diff = (c2m - ours.deviation_mm) * 1e3
        print(f"CloudCompare C2M: compute {t_cc if t_cc is not None else float('nan'):7.3f} s (its log); "
              f"whole run {wall:.3f} s (loading, ASCII export)")
        print(f"  CloudCompare - ours: {diff.min():+.4f}..{diff.max():+.4f} um")
        ratio = (t_cc or wall) / t_ours
        print(f"speed: ours analytic is {ratio:.1f}x CloudCompare's compute time "
              f"({'goal met' if ratio >= 1 else 'goal NOT met'}: no slower than CloudCompare); ours with reading "
              f"vs CloudCompare's whole run: {wall / (t_ours + t_read):.1f}x")


if __name__ == "__main__":
    main()
