"""Rigid and small-angle transforms on batches of poses, as (R, t) pairs.

A transform maps coordinates x to ``R @ x + t``. ``R`` is ``(..., 3, 3)`` and ``t`` is ``(..., 3)``; leading dimensions
broadcast, so a constant transform ``(3, 3), (3,)`` composes with a batch ``(N, 3, 3), (N, 3)``. Units: mm and rad.

Keeping R and t apart (rather than 4x4 homogeneous matrices) saves a third of the arithmetic and lets us apply a chain
to points and directions without building full matrices.
"""

from __future__ import annotations

import numpy as np

UNIT = {"X": np.array([1.0, 0.0, 0.0]), "Y": np.array([0.0, 1.0, 0.0]), "Z": np.array([0.0, 0.0, 1.0])}


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]x: ``skew(v) @ w == cross(v, w)``.  v : (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def rotation_about(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Right-handed rotation by ``angle`` (rad, shape (...)) about the unit vector ``axis`` (3,): (..., 3, 3)."""
    a = np.asarray(axis, dtype=float)
    angle = np.asarray(angle, dtype=float)
    c, s = np.cos(angle)[..., None, None], np.sin(angle)[..., None, None]
    K = skew(a)
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def compose(Ra, ta, Rb, tb):
    """(Ra, ta) o (Rb, tb): apply b first, then a."""
    return Ra @ Rb, np.einsum("...ij,...j->...i", Ra, tb) + ta


def inverse(R, t):
    """Exact inverse of an affine map (R need not be orthonormal: small-angle matrices are not)."""
    Ri = np.linalg.inv(R)
    return Ri, -np.einsum("...ij,...j->...i", Ri, t)
