"""Nominal kinematics: the chain from the part to the tool, forward and inverse, for N poses at once.

The relative chain (DESIGN §3). The machine file lists the axes of each branch from the bed outwards. A workpiece-branch
axis moves the table, which moves the *tool relative to the part* the other way; following ISO 841 we model the
relative motion only, so every axis factor ``G_k(q)`` moves the tool relative to the part by +q (translation along its
direction, or right-handed rotation about its line). With P the part placement, the tool pose in the part frame is

    T(q) = P^-1 . G_wn(q) ... G_w1(q) . G_t1(q) ... G_tm(q)

(workpiece axes from the part inwards to the bed, then tool axes from the bed outwards; "apply the axis nearest the bed
first"). The tool tip is the origin of the last frame and the tool axis its +z (tip towards spindle). Each factor is
written product-of-exponentials style: its line is given in M with every axis at zero.

Example, B-C table under a Y-X-Z spindle: p_W = P^-1 Rot_C(C) Rot_B(B) (X, Y, Z), u_W = R_C R_B (0, 0, 1).
A head axis on the tool branch turns the tool about its line, which rides on the axes below it: X Y Z then position
the tool tip as it would be with the head at zero (no tool-centre-point transform in the machine axes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import Machine
from .transforms import compose, rotation_about

Z_TOOL = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Link:
    """One axis in the relative chain. ``column`` is its column in pose arrays (machine.axis_names order)."""

    axis: str
    branch: str
    column: int
    rotary: bool
    direction: np.ndarray
    pivot: np.ndarray


def chain_links(machine: Machine) -> list[Link]:
    """The axes in relative-chain order: workpiece branch from the part to the bed, then the tool branch outwards."""
    col = {a: i for i, a in enumerate(machine.axis_names)}
    order = [(a, "workpiece") for a in reversed(machine.bed_to_workpiece)] + [(a, "tool") for a in machine.bed_to_tool]
    return [
        Link(a, br, col[a], machine.axes[a].is_rotary, machine.axes[a].direction, machine.axes[a].pivot)
        for a, br in order
    ]


def axis_motion(link: Link, q: np.ndarray):
    """Nominal factor G(q) of a link as (R, t), and its derivative dG/dq as (dR, dt).  q : (N,) mm or rad."""
    n = q.shape[0]
    if not link.rotary:
        R = np.broadcast_to(np.eye(3), (n, 3, 3))
        return (R, q[:, None] * link.direction), (None, np.broadcast_to(link.direction, (n, 3)))
    R = rotation_about(link.direction, q)
    c = link.pivot
    t = c - R @ c
    # d/dq [R (p - c) + c] = a x (R (p - c)): a skew generator on the left of R.
    a = link.direction
    dR = np.cross(a, R.transpose(0, 2, 1)).transpose(0, 2, 1)  # [a]x R, column by column
    return (R, t), (dR, -dR @ c)


def validate_poses(machine: Machine, q) -> np.ndarray:
    """Check a pose array at the door: (N, n_axes) or (n_axes,) finite floats, mm and rad."""
    q = np.asarray(q, dtype=float)
    n_axes = len(machine.axis_names)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != n_axes:
        raise ValueError(f"poses must have shape (N, {n_axes}) for axes {' '.join(machine.axis_names)}, got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("poses contain NaN or infinite values")
    return q


def forward_nominal(machine: Machine, q) -> tuple[np.ndarray, np.ndarray]:
    """Nominal tool tip (N,3) mm and unit tool axis (N,3) in the part frame, for poses q (N, n_axes) in mm/rad."""
    q = validate_poses(machine, q)
    n = q.shape[0]
    R = np.broadcast_to(np.eye(3), (n, 3, 3))
    t = np.broadcast_to(-machine.workpiece_origin, (n, 3))
    for link in chain_links(machine):
        (Rg, tg), _ = axis_motion(link, q[:, link.column])
        R, t = compose(R, t, Rg, tg)
    return t.copy(), R[:, :, 2].copy()


# --------------------------------------------------------------------------------------------------------------------
# Inverse kinematics of the five-axis layouts
# --------------------------------------------------------------------------------------------------------------------


@dataclass
class InverseResult:
    """Machine axes for target poses.  q : (N, n_axes) mm/rad.  singular : (N,) bool, the free axis was held.
    out_of_travel : (N,) bool, no branch puts every axis inside its travel (q holds the preferred branch anyway)."""

    q: np.ndarray
    singular: np.ndarray
    out_of_travel: np.ndarray
    branch: np.ndarray


class UnsupportedKinematics(NotImplementedError):
    """A five-axis layout whose inverse kinematics is not implemented (the tool axis from the machine axes): CL data,
    the test parts' programs and TCP output cannot be made for it."""


def rotary_layout_problem(machine: Machine) -> str | None:
    """Why the inverse kinematics cannot serve ``machine`` (a five-axis mill), or None when it can."""
    try:
        _rotary_pair(machine)
    except (UnsupportedKinematics, ValueError) as exc:
        return str(exc)
    return None


def _rotary_pair(machine: Machine):
    """(outer, inner) rotary links: outer acts on the part side of the relative chain, inner nearer the tool."""
    rot = [lk for lk in chain_links(machine) if lk.rotary]
    if len(rot) != 2:
        raise ValueError(f"inverse kinematics needs two rotary axes; {machine.name} has {len(rot)}")
    outer, inner = rot
    if abs(outer.direction @ Z_TOOL) < 1 - 1e-12 or abs(inner.direction @ Z_TOOL) > 1e-12:
        raise UnsupportedKinematics(
            "inverse kinematics is implemented for an outer rotary axis about Z and an inner one perpendicular to Z"
            f" (B-C, A-C tables, B head on a C table); {machine.name} has {outer.axis} about {outer.direction},"
            f" {inner.axis} about {inner.direction}"
        )
    return outer, inner


def _inner_angle(inner_dir, u_local):
    """Angle theta of a rotation about inner_dir (perpendicular to z) that turns z towards u_local's projection."""
    side = np.cross(inner_dir, Z_TOOL)  # R(theta) z = cos(theta) z + sin(theta) (a x z)
    return np.arctan2(u_local @ side, u_local @ Z_TOOL)


def _wind(angle, previous, travel):
    """Choose angle + 2 pi k nearest to previous; inside travel when possible."""
    k = np.round((previous - angle) / (2 * np.pi))
    cand = angle + 2 * np.pi * k
    if travel is not None:
        lo, hi = travel
        for shift in (0.0, 2 * np.pi, -2 * np.pi):
            alt = cand + shift
            better = ((cand < lo) | (cand > hi)) & (alt >= lo) & (alt <= hi)
            cand = np.where(better, alt, cand)
    return cand


def machine_to_part_rotation(machine: Machine, q) -> np.ndarray:
    """(T, 3, 3): turns a vector given in the machine frame M (at the bed) into the part frame at poses q (T, n).

    It is the rotation part of the workpiece branch of the relative chain (DESIGN §3): for a B-C table R_C(C) R_B(B).
    """
    q = np.asarray(q, float)
    R = np.broadcast_to(np.eye(3), (q.shape[0], 3, 3))
    for link in chain_links(machine):
        if link.branch != "workpiece":
            continue
        (Rg, _), _ = axis_motion(link, q[:, link.column])
        R = R @ Rg
    return np.ascontiguousarray(R)


def linear_axis_map(machine: Machine, q):
    """With the rotary axes of poses q fixed, the tool tip in the part frame is affine in the linear axes:
    tip = p0 + M q_linear. Returns (linear column indices, p0 (N, 3) mm: the tip with the linear axes at zero,
    M (N, 3, n_linear)): three unit probes of the forward kinematics give the map."""
    names = machine.axis_names
    linear = [c for c, a in enumerate(names) if not machine.axes[a].is_rotary]
    q0 = np.array(q, float, ndmin=2)
    q0[:, linear] = 0.0
    p0, _ = forward_nominal(machine, q0)
    cols = []
    for c in linear:
        qc = q0.copy()
        qc[:, c] += 1.0
        cols.append(forward_nominal(machine, qc)[0] - p0)
    return linear, p0, np.stack(cols, axis=-1)


def inverse_kinematics(
    machine: Machine,
    tip,
    axis,
    *,
    branch: str | int = "nearest",
    previous=None,
    singular_tol_rad: float = 1e-9,
) -> InverseResult:
    """Machine axes that put the nominal tool tip at ``tip`` with tool axis ``axis`` (both (N,3), part frame).

    branch : +1 / -1 picks the sign of the inner (tilt) axis; "nearest" takes, per pose, the branch inside the travel
        that is nearest to ``previous`` (or +1 when there is no previous pose).
    previous : (n_axes,) or (N, n_axes) pose to wind the rotary axes towards (shortest motion) and to hold the free
        axis at, at the singular pose (tilt = 0, where the outer axis does not change the tool axis).
    singular_tol_rad : |sin(tilt)| below this counts as singular.
    """
    tip = np.atleast_2d(np.asarray(tip, dtype=float))
    u = np.atleast_2d(np.asarray(axis, dtype=float))
    if tip.shape != u.shape or tip.shape[1] != 3:
        raise ValueError(f"tip and axis must both be (N, 3); got {tip.shape} and {u.shape}")
    if not (np.all(np.isfinite(tip)) and np.all(np.isfinite(u))):
        raise ValueError("tip or axis contains NaN or infinite values")
    norm = np.linalg.norm(u, axis=1)
    if np.any(norm < 1e-12):
        raise ValueError("tool-axis vectors must not be zero")
    u = u / norm[:, None]
    n = tip.shape[0]
    names = machine.axis_names
    outer, inner = _rotary_pair(machine)
    prev = np.zeros((n, len(names))) if previous is None else np.broadcast_to(np.asarray(previous, float), (n, len(names)))

    # Orientation: u = R_outer(o) R_inner(i) z.  cos(i) = u . z (outer about z), and o is the azimuth difference.
    cos_i = np.clip(u @ Z_TOOL, -1.0, 1.0)
    tilt = np.arccos(cos_i)
    singular = np.sin(tilt) < singular_tol_rad
    side = np.cross(inner.direction, Z_TOOL)
    az_u = np.arctan2(u[:, 1], u[:, 0])
    az_side = np.arctan2(side[1], side[0])
    travel_i = machine.axes[inner.axis].travel
    travel_o = machine.axes[outer.axis].travel

    sols = []
    for s in (1.0, -1.0):
        i_ang = s * tilt
        # R_inner(i) z has azimuth az_side (i > 0) or az_side + pi (i < 0); the outer axis turns it onto u's azimuth.
        o_ang = az_u - (az_side + (0.0 if s > 0 else np.pi))
        # Singular pose: hold the outer axis, solve the tilt in the frame it leaves.
        o_ang = np.where(singular, prev[:, outer.column], o_ang)
        u_local = np.einsum("nji,nj->ni", rotation_about(outer.direction, o_ang), u)
        i_ang = np.where(singular, _inner_angle(inner.direction, u_local), i_ang)
        o_ang = _wind(o_ang, prev[:, outer.column], travel_o)
        ok = np.ones(n, bool)
        if travel_i is not None:
            ok &= (i_ang >= travel_i[0] - 1e-12) & (i_ang <= travel_i[1] + 1e-12)
        if travel_o is not None:
            ok &= (o_ang >= travel_o[0] - 1e-12) & (o_ang <= travel_o[1] + 1e-12)
        dist = np.abs(i_ang - prev[:, inner.column]) + np.abs(o_ang - prev[:, outer.column])
        sols.append((i_ang, o_ang, ok, dist))

    if branch in (1, "+", "+1"):
        pick = np.zeros(n, int)
    elif branch in (-1, "-", "-1"):
        pick = np.ones(n, int)
    elif branch == "nearest":
        ok0, ok1 = sols[0][2], sols[1][2]
        d0, d1 = sols[0][3], sols[1][3]
        if previous is None:
            d0, d1 = np.zeros(n), np.ones(n)
        pick = np.where(ok0 & ~ok1, 0, np.where(ok1 & ~ok0, 1, np.where(d1 < d0, 1, 0)))
    else:
        raise ValueError(f"branch must be +1, -1 or 'nearest', got {branch!r}")
    i_ang = np.where(pick == 0, sols[0][0], sols[1][0])
    o_ang = np.where(pick == 0, sols[0][1], sols[1][1])
    in_travel = np.where(pick == 0, sols[0][2], sols[1][2])

    q = np.zeros((n, len(names)))
    q[:, inner.column] = i_ang
    q[:, outer.column] = o_ang
    linear, p0, M = linear_axis_map(machine, q)
    if len(linear) == 3:
        sol = np.linalg.solve(M, (tip - p0)[..., None])[..., 0]
    else:
        sol = np.einsum("nij,nj->ni", np.linalg.pinv(M), tip - p0)
    q[:, linear] = sol
    out = np.zeros(n, bool)
    for c, a in enumerate(names):
        tr = machine.axes[a].travel
        if tr is not None:
            out |= (q[:, c] < tr[0] - 1e-9) | (q[:, c] > tr[1] + 1e-9)
    return InverseResult(q=q, singular=singular, out_of_travel=out | ~in_travel, branch=np.where(pick == 0, 1, -1))
