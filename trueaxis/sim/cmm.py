"""The virtual CMM: probing patterns on the test parts, probe noise, the measured cloud and its truth sidecar.

Probing patterns are the parts' own (``probe_pattern`` of ``trueaxis.workpiece.nas979`` / ``slot_block``):

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
from pathlib import Path

import numpy as np

from ..fileio import atomic_write
from ..workpiece.part import part_of


def probe_pattern(part: dict, n_points: int):
    """Probing pattern of a part JSON: the part's own (``trueaxis.workpiece``), about n_points points (N, 3) mm and
    unit outward normals (N, 3), part frame."""
    if n_points < 1:
        raise ValueError(f"points must be >= 1, got {n_points}")
    return part_of(part).probe_pattern(part, n_points)


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
