"""The machined surface as the envelope of the swept tool, measured along probe normals.

The tool is a flat end mill: the solid cylinder of radius R from the tip up the flute length L (its side is the flank,
its bottom disk the end face). A tool *instance* is one sampled pose: tip p (mm) and unit axis u (tip towards the
spindle), both in the part frame. For a probe point x0 on the nominal surface with unit normal n pointing out of the
material, the line x0 + s n (s in mm) is intersected exactly with every nearby instance; the line enters instance i at
s_in(i). The material left after cutting ends where the deepest cut lands:

    s* = min_i s_in(i)         (positive: material left outside the nominal surface, i.e. undercut)

This is an exact line-solid intersection (a quadratic for the side, a slab for the end face and the flute end), not a
first-order projection of a pose error on the normal. Approximations: the tool is a perfect cylinder (no flute
geometry, runout or corner radius); the machined surface is the union of the sampled instances (the sweep between two
samples is not filled in: for the flank moving perpendicular to the tool axis the gap is at most h^2 / (8 R) for a
sample spacing h, 0.007 um for 16.7 um steps = 1000 mm/min at 1 ms and R = 5 mm); at a point several disjoint cuts
along the line would leave slivers, which the minimum ignores.

Candidate pruning (exact, conservative): consecutive instances are grouped (a group's tool axes stay within
``group_mm`` of each other, measured along the path of both ends of the flute); each group is a capsule around the mean
axis segment, radius rho_g (the farthest its instances' axis points get from the mean segment). A probe point can meet
an instance of group g within |s| <= search only if its distance to the group's mean segment is at most
R + search + rho_g. Candidate groups come from a ``scipy.spatial.cKDTree`` over points sampled along the mean segments,
then the exact point-to-segment distance; every instance of a surviving group is intersected exactly. Pairs are
processed in chunks (memory bounded by ``chunk_pairs``), reduced per point with ``np.minimum.reduceat``.

Thinning (``thin_instances``): along straight, steady motion, an instance whose removal cannot change the envelope by
more than ``tol_mm`` is dropped. The bound used for a stride of m samples of step h (the largest displacement of the
flute's two ends per sample) is m^2 (h^2 / R + a) / 8 <= tol, with a the second difference of the pose (a bound on
the deviation from straight, steady motion: tip plus L times the axis change), evaluated as the worst value over a
window, and instances with a motion component along the tool axis (where the end face's rim, not the flank, makes the
surface) are never dropped. Block boundaries are always kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import minimum_filter1d
from scipy.spatial import cKDTree


@dataclass
class EnvelopeResult:
    """Deviation of the machined surface along each probe normal.

    deviation_mm : (N,) float, s* in mm (positive = material left outside the nominal surface); NaN where no instance
        cuts within the search window.
    instance : (N,) int, index (into the instance arrays given) of the instance that made the deepest cut; -1 if none.
    n_pairs : int, point-instance pairs intersected exactly.
    """

    deviation_mm: np.ndarray
    instance: np.ndarray
    n_pairs: int

    @property
    def deviation_um(self) -> np.ndarray:
        return self.deviation_mm * 1e3


def line_tool_intersection(x0, n, tip, axis, radius, length: float):
    """Exact intersection of lines with flat-end-mill solids (cylinder of radius R from the tip up ``length``).

    radius : float, or (P,) per line (a worn tool's radius changes along the cut).

    x0, n : (P, 3) line points and unit directions, mm.  tip, axis : (P, 3) tool tips (mm) and unit axes.
    Returns s_in, s_out : (P,) float, the parameters where each line x0 + s n enters and leaves the solid
    (+inf, -inf where it misses). The side is the quadratic |w_perp + s n_perp|^2 = R^2, the end face and the flute end
    the slab 0 <= (w + s n) . u <= L, with w = x0 - tip.
    """
    x0, n, tip, axis = (np.asarray(v, float) for v in (x0, n, tip, axis))
    w = x0 - tip
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
    ux, uy, uz = axis[:, 0], axis[:, 1], axis[:, 2]
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    a0 = wx * ux + wy * uy + wz * uz  # height of x0 above the tip
    da = nx * ux + ny * uy + nz * uz  # rate of height along the line
    # With unit n and u: |n_perp|^2 = 1 - da^2, w_perp . n_perp = w . n - a0 da, |w_perp|^2 = |w|^2 - a0^2.
    A = 1.0 - da * da
    B = (wx * nx + wy * ny + wz * nz) - a0 * da
    C = (wx * wx + wy * wy + wz * wz) - a0 * a0 - radius * radius
    disc = B * B - A * C
    has_side = A > 1e-12
    root = np.sqrt(np.maximum(disc, 0.0))
    # Numerically stable roots: no cancellation when the line grazes the side.
    qq = -(B + np.copysign(root, B))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = qq / A
        r2 = np.where(qq != 0, C / qq, r1)
    inside_r = C <= 0
    s1 = np.where(has_side, np.minimum(r1, r2), np.where(inside_r, -np.inf, np.inf))
    s2 = np.where(has_side, np.maximum(r1, r2), np.where(inside_r, np.inf, -np.inf))
    miss = has_side & (disc < 0)
    s1[miss] = np.inf
    # Axial slab 0 <= a0 + s da <= L.
    along = np.abs(da) > 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = -a0 / da
        t2 = (length - a0) / da
    inside = (a0 >= 0) & (a0 <= length)
    lo = np.where(along, np.minimum(t1, t2), np.where(inside, -np.inf, np.inf))
    hi = np.where(along, np.maximum(t1, t2), np.where(inside, np.inf, -np.inf))
    s_in = np.maximum(s1, lo)
    s_out = np.minimum(s2, hi)
    hit = s_in <= s_out
    return np.where(hit, s_in, np.inf), np.where(hit, s_out, -np.inf)


def thin_instances(tips, axes, radius: float, length: float, tol_mm: float = 1e-5, breaks=None, max_stride: int = 64):
    """Keep mask (I,) of instances whose removal could change the envelope by more than ``tol_mm`` (see module doc).

    tips, axes : (I, 3) mm, unit.  breaks : (I,) bool, instances that must be kept (block boundaries), optional.
    """
    tips = np.asarray(tips, float)
    axes = np.asarray(axes, float)
    n = tips.shape[0]
    keep = np.ones(n, bool)
    if n < 3 or tol_mm <= 0:
        return keep
    top = tips + length * axes
    step = np.maximum(np.linalg.norm(np.diff(tips, axis=0), axis=1), np.linalg.norm(np.diff(top, axis=0), axis=1))
    h = np.concatenate([step[:1], np.maximum(step[:-1], step[1:]), step[-1:]])
    acc = np.zeros(n)
    acc[1:-1] = np.maximum(
        np.linalg.norm(tips[2:] - 2 * tips[1:-1] + tips[:-2], axis=1),
        np.linalg.norm(top[2:] - 2 * top[1:-1] + top[:-2], axis=1),
    )
    axial = np.zeros(n)
    d = np.diff(tips, axis=0)
    ax_step = np.abs(np.einsum("ij,ij->i", d, axes[:-1]))
    axial[:-1] = ax_step
    axial[1:] = np.maximum(axial[1:], ax_step)
    with np.errstate(divide="ignore"):
        m = np.floor(np.sqrt(8.0 * tol_mm / (h * h / radius + acc + 1e-300)))
    m = np.clip(m, 1, max_stride)
    m = np.where(axial * m > tol_mm, 1, m)
    # Worst stride over the neighbourhood a dropped run spans.
    m = minimum_filter1d(m, size=2 * max_stride + 1, mode="nearest")
    budget = np.cumsum(1.0 / m)
    keep = np.diff(np.floor(budget), prepend=-1.0) > 0
    keep[0] = keep[-1] = True
    keep |= m <= 1
    if breaks is not None:
        b = np.asarray(breaks, bool)
        keep |= b
        keep[1:] |= b[:-1]
    return keep


def _groups(tips, axes, length, group_mm, max_group):
    """Split consecutive instances into groups; returns start indices (G,) and sizes (G,)."""
    n = tips.shape[0]
    top = tips + length * axes
    step = np.zeros(n)
    step[1:] = np.maximum(np.linalg.norm(np.diff(tips, axis=0), axis=1), np.linalg.norm(np.diff(top, axis=0), axis=1))
    cum = np.cumsum(step)
    key = np.floor(cum / group_mm)
    new = np.ones(n, bool)
    new[1:] = key[1:] != key[:-1]
    # Cap the group size: count since the last break.
    idx = np.arange(n)
    last = np.maximum.accumulate(np.where(new, idx, 0))
    new |= ((idx - last) % max_group == 0)
    starts = np.nonzero(new)[0]
    sizes = np.diff(np.append(starts, n))
    return starts, sizes


def _segment_distance(x, a, b):
    """Distance from points x (P,3) to segments [a, b] (P,3)."""
    ab = b - a
    t = np.einsum("ij,ij->i", x - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(x - (a + t[:, None] * ab), axis=1)


def _envelope(
    points,
    normals,
    tips,
    axes,
    radius: float,
    length: float,
    *,
    search_mm: float = 0.3,
    group_mm: float = 0.25,
    max_group: int = 64,
    sample_mm: float = 1.0,
    chunk_points: int = 4096,
    chunk_pairs: int = 2_000_000,
    progress: bool = False,
) -> EnvelopeResult:
    """The envelope at a fixed search window (see ``envelope_deviation``).

    search_mm : the window |s| <= search_mm in which cuts are looked for (a deeper gouge is still found when an instance
        reaching into the window makes it); points with no cut in the window get NaN.
    group_mm, max_group, sample_mm : pruning granularity (see the module docstring); they do not change the result.
    chunk_points, chunk_pairs : memory bounds.  progress : show a tqdm bar over point chunks.
    """
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    tips = np.asarray(tips, float)
    axes = np.asarray(axes, float)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must both be (N, 3); got {points.shape} and {normals.shape}")
    if tips.ndim != 2 or tips.shape[1] != 3 or axes.shape != tips.shape:
        raise ValueError(f"tips and axes must both be (I, 3); got {tips.shape} and {axes.shape}")
    # radius: one for every instance, or (I,) per instance (a wearing tool, ``effects.ToolWear``).
    per_instance = np.ndim(radius) > 0
    radius = np.asarray(radius, float) if per_instance else float(radius)
    if per_instance and radius.shape != (tips.shape[0],):
        raise ValueError(f"radius must be a number or one per instance ({tips.shape[0]}), got shape {radius.shape}")
    if not (np.all(radius > 0) and length > 0 and search_mm > 0):
        raise ValueError("radius, length and search_mm must be positive")
    for name, arr in (("points", points), ("normals", normals), ("tips", tips), ("axes", axes)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contain NaN or infinite values")
    nrm = np.linalg.norm(normals, axis=1)
    if np.any(np.abs(nrm - 1) > 1e-6):
        raise ValueError("normals must be unit vectors")
    n_pts = points.shape[0]
    best = np.full(n_pts, np.inf)
    best_i = np.full(n_pts, -1, dtype=np.int64)
    if tips.shape[0] == 0 or n_pts == 0:
        return EnvelopeResult(np.full(n_pts, np.nan), best_i, 0)

    # Groups of consecutive instances and their capsules (mean axis segment a-b, radius rho).
    starts, sizes = _groups(tips, axes, length, group_mm, max_group)
    gid = np.repeat(np.arange(starts.size), sizes)
    cnt = sizes[:, None].astype(float)
    ga = np.add.reduceat(tips, starts, axis=0) / cnt
    gu = np.add.reduceat(axes, starts, axis=0) / cnt
    gb = ga + length * gu
    # rho: farthest distance of an instance's axis point from the mean segment at the same height (affine in height,
    # so the ends bound it), plus the mean segment's own deviation from straight (none: it is straight).
    d0 = np.linalg.norm(tips - ga[gid], axis=1)
    d1 = np.linalg.norm(tips + length * axes - gb[gid], axis=1)
    rho = np.maximum.reduceat(np.maximum(d0, d1), starts)
    # Sample the mean segments for the KD-tree.
    k = max(1, int(np.ceil(length / sample_mm)))
    hz = length / k
    z = (np.arange(k) + 0.5) / k
    samples = (ga[:, None, :] + z[None, :, None] * (gb - ga)[:, None, :]).reshape(-1, 3)
    sample_group = np.repeat(np.arange(starts.size), k)
    reach = float(np.max(radius)) + search_mm
    r_query = reach + float(rho.max()) + 0.5 * hz * max(1.0, float(np.linalg.norm(gu, axis=1).max()))
    tree = cKDTree(samples)

    n_pairs = 0
    chunks = range(0, n_pts, chunk_points)
    if progress:
        from tqdm import tqdm

        chunks = tqdm(chunks, desc="envelope", unit="chunk", total=(n_pts + chunk_points - 1) // chunk_points,
                      disable=None)  # None: shown on a terminal only, never written into a redirected log
    for c0 in chunks:
        sl = slice(c0, min(n_pts, c0 + chunk_points))
        pts = points[sl]
        ptree = cKDTree(pts)
        sdm = ptree.sparse_distance_matrix(tree, r_query, output_type="ndarray")
        if sdm.size == 0:
            continue
        key = np.unique(sdm["i"].astype(np.int64) * starts.size + sample_group[sdm["j"]])
        pi = key // starts.size
        gg = key % starts.size
        # Exact capsule test.
        dist = _segment_distance(pts[pi], ga[gg], gb[gg])
        ok = dist <= reach + rho[gg]
        pi, gg = pi[ok], gg[ok]
        if pi.size == 0:
            continue
        # Expand (point, group) to (point, instance); pairs stay sorted by point.
        reps = sizes[gg]
        total = int(reps.sum())
        # Split into sub-chunks of whole (point, group) entries, about chunk_pairs pairs each.
        cum = np.cumsum(reps)
        cut = np.searchsorted(cum, np.arange(chunk_pairs, total, chunk_pairs), side="right")
        edges = np.unique(np.concatenate([[0], cut, [pi.size]]))
        for lo, hi in zip(edges[:-1], edges[1:]):
            p_sub, g_sub, r_sub = pi[lo:hi], gg[lo:hi], reps[lo:hi]
            pp = np.repeat(p_sub, r_sub)
            offs = np.arange(pp.size) - np.repeat(np.cumsum(r_sub) - r_sub, r_sub)
            ii = np.repeat(starts[g_sub], r_sub) + offs
            s_in, _ = line_tool_intersection(pts[pp], normals[sl][pp], tips[ii], axes[ii],
                                             radius[ii] if per_instance else radius, length)
            n_pairs += pp.size
            # Per point minimum and its first arg-minimum (pairs are sorted by point).
            seg = np.nonzero(np.diff(pp, prepend=-1))[0]
            smin = np.minimum.reduceat(s_in, seg)
            seg_len = np.diff(np.append(seg, pp.size))
            is_min = s_in == np.repeat(smin, seg_len)
            arg = np.minimum.reduceat(np.where(is_min, np.arange(pp.size), pp.size), seg)
            upts = pp[seg] + c0
            better = smin < best[upts]
            best[upts[better]] = smin[better]
            best_i[upts[better]] = ii[arg[better]]
    dev = np.where(np.isfinite(best) & (best <= search_mm), best, np.nan)
    best_i = np.where(np.isnan(dev), -1, best_i)
    return EnvelopeResult(dev, best_i, n_pairs)


def envelope_deviation(points, normals, tips, axes, radius: float, length: float, *, search_mm="auto",
                       search_max_mm: float = 1.0, pilot_points: int = 2000, **kwargs) -> EnvelopeResult:
    """Deviation s* of the machined surface from each probe point along its normal (exact line-solid intersection).

    points : (N, 3) mm, nominal surface points, part frame.  normals : (N, 3) unit, out of the material.
    tips, axes : (I, 3) actual tool tips (mm) and unit tool axes of the cutting instances, part frame, in time order.
    radius, length : tool radius (a number, or (I,) per instance) and flute length, mm.
    search_mm : the window |s| <= search_mm (mm) in which cuts are looked for; points with no cut in it get NaN. The
        number of candidate pairs grows as sqrt(search_mm). "auto": a pilot run on ``pilot_points`` evenly chosen
        points with ``search_max_mm`` sets it to 1.25 max |s*| + 5 um, and the points that then come out NaN are run
        again with ``search_max_mm`` (so the result equals a run at search_max_mm).
    Other keywords (group_mm, max_group, sample_mm, chunk_points, chunk_pairs, progress): see ``_envelope``.
    """
    if search_mm != "auto":
        return _envelope(points, normals, tips, axes, radius, length, search_mm=float(search_mm), **kwargs)
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    n = points.shape[0]
    progress = kwargs.pop("progress", False)
    pick = np.unique(np.linspace(0, n - 1, min(n, pilot_points)).astype(int)) if n else np.zeros(0, int)
    pilot = _envelope(points[pick], normals[pick], tips, axes, radius, length, search_mm=search_max_mm, **kwargs)
    dev = pilot.deviation_mm[np.isfinite(pilot.deviation_mm)]
    search = search_max_mm if dev.size == 0 else min(search_max_mm, 1.25 * float(np.abs(dev).max()) + 0.005)
    res = _envelope(points, normals, tips, axes, radius, length, search_mm=search, progress=progress, **kwargs)
    redo = np.nonzero(np.isnan(res.deviation_mm))[0]
    if redo.size and search < search_max_mm:
        again = _envelope(points[redo], normals[redo], tips, axes, radius, length, search_mm=search_max_mm, **kwargs)
        res.deviation_mm[redo] = again.deviation_mm
        res.instance[redo] = again.instance
        res.n_pairs += again.n_pairs
    res.n_pairs += pilot.n_pairs
    return res
