"""Run CloudCompare's command line for cloud-to-mesh distances (C2M), for cross-checks and the benchmark.

``CloudCompare -SILENT -AUTO_SAVE OFF -C_EXPORT_FMT ASC -O cloud.ply -O mesh.ply -C2M_DIST -SAVE_CLOUDS FILE out.asc``
loads the cloud (first) and the mesh, computes the signed distance of each point to the nearest triangle (positive
on the side of the triangle's normal) and writes the cloud as ``x y z distance`` per line, in the input order.
CloudCompare stores coordinates as float32. It needs a display only for its GUI: ``QT_QPA_PLATFORM=offscreen``.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

EXECUTABLE = "CloudCompare"


def find_cloudcompare() -> str | None:
    return shutil.which(EXECUTABLE)


def require_cloudcompare() -> str:
    """Path of CloudCompare (conftest.require_program: fails under CI=true when missing, skips elsewhere)."""
    from conftest import require_program  # here, not at the top: the benchmark imports this module without pytest

    return require_program(EXECUTABLE, "cloudcompare", "the C2M cross-checks")


def cloudcompare_c2m(cloud_ply: Path, mesh_ply: Path, workdir: Path, exe: str | None = None):
    """Signed C2M distances (n,) mm, CloudCompare's own compute time (s, from its log, or None), the wall time of
    the whole run (s, loading and saving included) and its log."""
    exe = exe or find_cloudcompare()
    out = Path(workdir) / "c2m.asc"
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    start = time.perf_counter()
    proc = subprocess.run([exe, "-SILENT", "-AUTO_SAVE", "OFF", "-C_EXPORT_FMT", "ASC", "-O", str(cloud_ply),
                           "-O", str(mesh_ply), "-C2M_DIST", "-SAVE_CLOUDS", "FILE", str(out)],
                          capture_output=True, text=True, env=env, timeout=600, cwd=workdir)
    wall = time.perf_counter() - start
    log = proc.stdout + proc.stderr
    if proc.returncode != 0 or not out.is_file():
        raise RuntimeError(f"CloudCompare failed (exit {proc.returncode}): {log[-2000:]}")
    table = np.loadtxt(out, ndmin=2)
    times = [float(t) for t in re.findall(r"\[ComputeDistances\] Time: ([0-9.]+) s", log)]
    return table[:, -1], (sum(times) if times else None), wall, log
