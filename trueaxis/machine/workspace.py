"""Sampling a machine's workspace and summarising its volumetric error there."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import Machine
from .twin import ErrorTwin

UNLIMITED_ROTARY = (-np.pi, np.pi)


def axis_ranges(machine: Machine) -> np.ndarray:
    """(n_axes, 2) travel of each axis in mm / rad; unlimited rotary axes get one turn, [-pi, pi]."""
    out = []
    for a in machine.axis_names:
        tr = machine.axes[a].travel
        if tr is None:
            if not machine.axes[a].is_rotary:
                raise ValueError(f"linear axis {a} has no travel: cannot sample its workspace")
            tr = UNLIMITED_ROTARY
        out.append(tr)
    return np.asarray(out, dtype=float)


def sample_poses(machine: Machine, n: int, seed: int = 0) -> np.ndarray:
    """n poses (n, n_axes) drawn uniformly inside every axis' travel (mm, rad), reproducibly."""
    rng = np.random.default_rng(seed)
    r = axis_ranges(machine)
    return r[:, 0] + rng.random((n, r.shape[0])) * (r[:, 1] - r[:, 0])


@dataclass(frozen=True)
class VolumetricSummary:
    """Position error norms (um) and tool-axis error norms (urad) over sampled poses."""

    machine: str
    poses: int
    position_max_um: float
    position_rms_um: float
    orientation_max_urad: float
    orientation_rms_urad: float
    worst_pose: dict

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def volumetric_summary(machine: Machine, n: int = 20_000, seed: int = 0) -> VolumetricSummary:
    """Max and RMS of |position error| and |tool-axis error| over n random poses inside the travel."""
    q = sample_poses(machine, n, seed)
    dp, du = ErrorTwin(machine).volumetric_error(q)
    ep = np.linalg.norm(dp, axis=1)
    eu = np.linalg.norm(du, axis=1)
    i = int(np.argmax(ep))
    worst = {
        a: float(np.degrees(q[i, c]) if machine.axes[a].is_rotary else q[i, c]) for c, a in enumerate(machine.axis_names)
    }
    return VolumetricSummary(
        machine=machine.name,
        poses=n,
        position_max_um=float(ep.max()),
        position_rms_um=float(np.sqrt(np.mean(ep**2))),
        orientation_max_urad=float(eu.max()),
        orientation_rms_urad=float(np.sqrt(np.mean(eu**2))),
        worst_pose=worst,
    )
