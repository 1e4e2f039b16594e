"""Arcs kept as arcs: G2/G3 blocks fitted to the corrected path and checked through the twin.

An input arc's corrected path is the twin's inverse of the nominal arc: the commanded positions whose actual tool tip
lies on the nominal arc. Where the machine's errors vary along the arc, that path is no longer the nominal arc shifted
(the case ``post`` keeps as it is), but it is still close to *an* arc. This module finds that arc, and proves it:

1. An arc is first cut into sub-arcs of at most half a turn (a chord then fixes the centre well; a full circle becomes
   two halves).
2. Each sub-arc keeps its corrected start and end exactly (as they will be written, rounded to the output's decimals);
   its centre lies on the perpendicular bisector of that chord (so the radius to the start and to the end agree to
   the written digits, far inside the controller's check) at the offset that brings the arc closest, in the least
   squares sense, to the corrected path at eight interior points (Gauss-Newton in one unknown). The helical axis runs
   linearly from start to end, as the controller moves it.
3. The sub-arc as the controller will interpolate it, from the written (rounded) numbers, is sampled densely (every
   0.5 mm, 8 to 64 intervals), put through the twin (actual tool tip at each commanded point), and its distance to the
   nominal arc (a helix, in the part frame) is measured. Within the tolerance: kept. Otherwise the sub-arc is bisected
   (its mid-point's corrected position solved) and both halves fitted again, down to ``MAX_DEPTH`` levels; a sub-arc
   that still does not hold becomes straight pieces (as the post linearises an arc: chords within half the tolerance
   of the corrected path), the rest of its arc stays G2/G3.

The controller's interpolation (LinuxCNC: ``pmCircleInit`` / ``pmCirclePoint``): the centre from the start and the
centre words (incremental, G91.1, or absolute, G90.1), the radius from the centre to the start, changing linearly with
the angle to the radius at the end (a spiral, here of a few nanometres), the helical axis linear in the angle.
LinuxCNC's check (``interp_arc.cc``, ``arc_data_ijk``): refused when the radii to start and end differ by more than
100 x ``CENTER_ARC_RADIUS_TOLERANCE`` (default 0.028 mm / 0.0028 in), or by more than it *and* more than 0.1 %; and
a radius below 0.00127 mm (0.00005 in) is a zero-radius arc. A fitted sub-arc's radii must agree within the smallest
tolerance a configuration may set (``MIN_CENTER_ARC_RADIUS_TOLERANCE``: 0.001 mm, 0.00004 in), so any setting takes it.

Only three-axis motion is fitted (no rotary word in the program), in the absolute mode (G90), without inverse time
(G93) and from a start written by the block before (not a canned cycle's); other arcs take the straight pieces.
In comprehensive mode the block before ends on its own load, the arc starts on its own: the step between them stays
(as it does for straight pieces), so the first sub-arc of such an arc may end as straight pieces."""

from __future__ import annotations

import numpy as np

from ..nc.gcode import ARC_CCW, MM_PER_INCH, ROW_CYCLE
from ..nc.grammar import PLANE_AXES
from ..nc.interp_arc import RADIUS_MIN, SPIRAL_ABS, SPIRAL_ABS_MIN, SPIRAL_REL

MAX_DEPTH = 6  # bisections of a sub-arc that does not hold before its arc becomes straight pieces
FIT_POINTS = 8  # interior corrected points a sub-arc's centre is fitted to
CHECK_STEP_MM = 0.5  # the written arc is checked through the twin at least this often ...
CHECK_MIN, CHECK_MAX = 8, 64  # ... with this many intervals per sub-arc


_PLANE_COLUMNS = np.array([PLANE_AXES[17], PLANE_AXES[18], PLANE_AXES[19]])


def plane_columns(planes) -> tuple[np.ndarray, np.ndarray]:
    """The X Y Z columns (first, second: ``nc.grammar.PLANE_AXES``) of arcs in the planes (K,) 17, 18 or 19."""
    k = np.asarray(planes, int) - 17
    return _PLANE_COLUMNS[k, 0], _PLANE_COLUMNS[k, 1]


def xyz_decimals(p) -> np.ndarray:
    """(2, 3) the decimals X Y Z are written with: in mm (row 0), in inch (row 1)."""
    from .post import _Numbers

    numbers = _Numbers(p.format_info)
    return np.array([[numbers.decimals(a, inch) for a in "XYZ"] for inch in (False, True)])


def arc_points_at(p, rows, t) -> np.ndarray:
    """(K, 6) nominal points of the arcs ``rows`` (K,) at fractions ``t`` (K,) of them (program coordinates): angle
    and radius linear in the fraction, the helical axis and any other axis linear; t = 1 is the end exactly."""
    from .post import _arcs_geometry

    rows = np.asarray(rows, int)
    t = np.asarray(t, float)
    ii, jj, nn, a0, sweep, rad0, rad1 = _arcs_geometry(p, rows)
    k = np.arange(rows.size)
    c, s, e = p.arc_center[rows], p.start[rows], p.end[rows]
    sign = np.where(p.motion[rows] == ARC_CCW, 1.0, -1.0)
    ang = a0 + sign * sweep * t
    rad = rad0 + (rad1 - rad0) * t
    pts = s + t[:, None] * (e - s)
    pts[k, ii] = c[k, ii] + rad * np.cos(ang)
    pts[k, jj] = c[k, jj] + rad * np.sin(ang)
    pts[t == 1.0] = e[t == 1.0]
    return pts


class ArcFitter:
    """Fits the arcs of one chunk of moves for a ``post._Poster`` (its program, twin, solver and tolerance)."""

    def __init__(self, poster):
        from .post import WRITE_ROUNDING_UM
        from .solver import corrected_directions

        self.ps = poster
        self.p = poster.p
        # written decimals per program axis column (X Y Z) and unit system
        self.decimals = dict(zip((False, True), xyz_decimals(self.p)))
        cd = corrected_directions(poster.m)
        self.correctable = cd.T @ cd
        # what the check allows: the tolerance less the rounding of a centre word at a tie (the written numbers
        # themselves are modelled as written)
        self.tol_mm = max(poster.tol_mm - 1e-3 * WRITE_ROUNDING_UM, poster.tol_mm / 2)
        self.max_deviation_um = 0.0
        self.sub_arcs_linearised = 0  # sub-arcs that did not hold at the deepest bisection: straight pieces

    # --- rounding as written ------------------------------------------------------------------------------------
    def _round(self, xyz, inch):
        """(K, 3) program-coordinate X Y Z rounded to the written decimals of each row (inch (K,) bool)."""
        out = np.empty_like(xyz)
        for flag in (False, True):
            sel = inch == flag
            if np.any(sel):
                d = self.decimals[flag]
                out[sel] = np.round(xyz[sel] * 10.0**d) / 10.0**d
        return out

    # --- the run ------------------------------------------------------------------------------------------------
    def fit(self, rows, arc_idx, start_cmd, end_cmd, force):
        """Fit the arcs ``rows[arc_idx]``. start_cmd, end_cmd : (A, 6) their corrected start (as the block before
        writes it) and end, program coordinates; force : the chunk's loads (indexed like ``rows``) or None.

        Returns (fitted {k: (ends (n, 6), centres (n, 3))} by index k into ``rows``, the indices that did not hold)."""
        p = self.p
        arc_idx = np.asarray(arc_idx, int)
        r_arcs = rows[arc_idx]
        from .post import _arcs_geometry

        _, _, _, _, sweep, _, _ = _arcs_geometry(p, r_arcs)
        n0 = np.maximum(1, np.ceil(sweep / np.pi - 1e-9)).astype(int)  # sub-arcs of at most half a turn
        owner = np.repeat(np.arange(arc_idx.size), n0)
        j = np.arange(owner.size) - np.repeat(np.cumsum(n0) - n0, n0)
        ta = j / n0[owner]
        tb = (j + 1) / n0[owner]
        tb[j == n0[owner] - 1] = 1.0
        # corrected points at the inner boundaries
        inner = j > 0
        pa = np.empty((owner.size, 6))
        pa[~inner] = start_cmd[owner[~inner]]
        if np.any(inner):
            pa[inner] = self._corrected(rows, arc_idx, owner[inner], ta[inner], force)
        pb = np.empty((owner.size, 6))
        last = j == n0[owner] - 1
        pb[last] = end_cmd[owner[last]]
        pb[~last] = pa[np.nonzero(~last)[0] + 1]
        done_t, done_end, done_centre, done_owner = [], [], [], []
        failed = np.zeros(arc_idx.size, bool)  # (kept for arcs that cannot be fitted at all)
        for depth in range(MAX_DEPTH + 1):
            if owner.size == 0:
                break
            centre, ok = self._fit_and_check(rows, arc_idx, owner, ta, tb, pa, pb, force)
            ok &= ~failed[owner]
            done_t.append(ta[ok])
            done_end.append(pb[ok])
            done_centre.append(centre[ok])
            done_owner.append(owner[ok])
            bad = ~ok & ~failed[owner]
            if depth == MAX_DEPTH:
                if np.any(bad):  # the sub-arcs that still do not hold: straight pieces
                    o, t0, ends = self._lines(rows, arc_idx, owner[bad], ta[bad], tb[bad], pb[bad], force)
                    done_t.append(t0)
                    done_end.append(ends)
                    done_centre.append(np.full((len(t0), 3), np.nan))  # no centre: a straight piece
                    done_owner.append(o)
                    self.sub_arcs_linearised += int(bad.sum())
                break
            # bisect: the mid-point's corrected position is solved
            o, a, b, A, B = owner[bad], ta[bad], tb[bad], pa[bad], pb[bad]
            mid = 0.5 * (a + b)
            M = self._corrected(rows, arc_idx, o, mid, force) if o.size else np.zeros((0, 6))
            owner = np.r_[o, o]
            ta, tb = np.r_[a, mid], np.r_[mid, b]
            pa, pb = np.vstack([A, M]), np.vstack([M, B])
        owner = np.concatenate(done_owner) if done_owner else np.zeros(0, int)
        t = np.concatenate(done_t) if done_t else np.zeros(0)
        ends = np.vstack(done_end) if done_end else np.zeros((0, 6))
        centres = np.vstack(done_centre) if done_centre else np.zeros((0, 3))
        keep = ~failed[owner]
        owner, t, ends, centres = owner[keep], t[keep], ends[keep], centres[keep]
        order = np.lexsort((t, owner))
        owner, ends, centres = owner[order], ends[order], centres[order]
        out = {}
        bounds = np.r_[0, np.nonzero(np.diff(owner))[0] + 1, owner.size]
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            if hi > lo:
                out[int(arc_idx[owner[lo]])] = (ends[lo:hi], centres[lo:hi])
        return out, arc_idx[failed]

    def _lines(self, rows, arc_idx, owner, ta, tb, pb, force):
        """Straight pieces in place of the sub-arcs [ta, tb] of ``arc_idx[owner]`` that do not hold as arcs, as the
        post linearises a whole arc: enough that the chord's sagitta stays within half the tolerance, the correction
        followed point by point. Returns (owner, start fraction, end point (6,)) per piece, the sub-arc's own end
        ``pb`` last."""
        from .post import _arcs_geometry

        p = self.p
        r = rows[arc_idx][owner]
        _, _, _, _, sweep, rad0, rad1 = _arcs_geometry(p, r)
        radius = np.maximum(rad0, rad1) * np.where(p.inch[r], MM_PER_INCH, 1.0)
        step = 2 * np.arccos(np.maximum(0.0, 1 - (self.ps.tol_mm / 2) / np.maximum(radius, 1e-9)))
        n = np.maximum(2, np.ceil(sweep * (tb - ta) / step)).astype(int)
        po = np.repeat(np.arange(owner.size), n)
        j = np.arange(po.size) - np.repeat(np.cumsum(n) - n, n)
        t0 = ta[po] + (tb - ta)[po] * j / n[po]
        t1 = ta[po] + (tb - ta)[po] * (j + 1) / n[po]
        last = j == n[po] - 1
        ends = np.empty((po.size, 6))
        ends[last] = pb[po[last]]
        if np.any(~last):
            ends[~last] = self._corrected(rows, arc_idx, owner[po[~last]], t1[~last], force)
        return owner[po], t0, ends

    def _corrected(self, rows, arc_idx, owner, t, force):
        """(K, 6) corrected (commanded) program-coordinate points of the arcs ``arc_idx[owner]`` at fractions t."""
        ps, p = self.ps, self.p
        r = rows[arc_idx][owner]
        pts6 = arc_points_at(p, r, t)
        q_pts = ps.to_machine(p.to_machine(pts6, r), p.inch[r])
        q_c, _ = ps.solve(q_pts, self._loads(force, arc_idx, owner, r, pts6), r)
        ps.check(q_pts, q_c, r)
        return pts6 + ps.to_program_delta(q_c - q_pts, p.inch[r], r)

    def _loads(self, force, arc_idx, owner, r, pts6):
        if force is None:
            return None
        f = force[arc_idx][owner]
        if f.shape[1] > 3:  # a lathe's loads: force and motion follow the arc (see .turning)
            from .turning import arc_point_loads

            f = arc_point_loads(self.ps, r, pts6, f)
        return f

    def _fit_and_check(self, rows, arc_idx, owner, ta, tb, pa, pb, force):
        """Centre (G, 3) absolute program coordinates, as written, of each sub-arc [ta, tb] of ``arc_idx[owner]``
        from pa to pb (G, 6), and (G,) bool: the written sub-arc holds (controller's radius check and the tolerance
        through the twin)."""
        ps, p = self.ps, self.p
        r = rows[arc_idx][owner]
        G = owner.size
        g = np.arange(G)
        inch = p.inch[r]
        ii, jj = plane_columns(p.arc_plane[r])
        nn = 3 - ii - jj
        ccw = p.motion[r] == ARC_CCW
        sign = np.where(ccw, 1.0, -1.0)
        S = self._round(pa[:, :3], inch)
        E = self._round(pb[:, :3], inch)
        # corrected path at interior points
        m = FIT_POINTS
        fo = np.repeat(g, m)
        ft = ta[fo] + (tb - ta)[fo] * np.tile(np.arange(1, m + 1) / (m + 1), G)
        c = self._corrected(rows, arc_idx, owner[fo], ft, force)
        s2 = np.stack([S[g, ii], S[g, jj]], axis=1)
        e2 = np.stack([E[g, ii], E[g, jj]], axis=1)
        c2 = np.stack([c[np.arange(fo.size), ii[fo]], c[np.arange(fo.size), jj[fo]]], axis=1)
        mid = 0.5 * (s2 + e2)
        chord = e2 - s2
        clen = np.linalg.norm(chord, axis=1)
        ok = clen > 0  # a chord of zero length would be read as a full circle
        h = 0.5 * clen
        nvec = np.stack([-chord[:, 1], chord[:, 0]], axis=1) / np.where(ok, clen, 1.0)[:, None]
        # start: the nominal centre moved by the mean correction of the ends
        c_nom = p.arc_center[r]
        c0 = np.stack([c_nom[g, ii], c_nom[g, jj]], axis=1)
        nom_a = arc_points_at(p, r, ta)
        nom_b = arc_points_at(p, r, tb)
        shift = 0.5 * ((s2 - np.stack([nom_a[g, ii], nom_a[g, jj]], axis=1))
                       + (e2 - np.stack([nom_b[g, ii], nom_b[g, jj]], axis=1)))
        sigma = np.einsum("gi,gi->g", c0 + shift - mid, nvec)
        for _ in range(8):  # Gauss-Newton on the centre's offset along the bisector
            C = mid + sigma[:, None] * nvec
            d = c2 - C[fo]
            dist = np.linalg.norm(d, axis=1)
            R = np.sqrt(h**2 + sigma**2)
            f = dist - R[fo]
            J = -np.einsum("ki,ki->k", d, nvec[fo]) / np.maximum(dist, 1e-300) - (sigma / np.maximum(R, 1e-300))[fo]
            num = np.bincount(fo, J * f, G)
            den = np.bincount(fo, J * J, G)
            sigma = sigma - np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
        C2 = mid + sigma[:, None] * nvec
        # the centre as written: incremental from the written start (G91.1) or absolute (G90.1)
        centre = S.copy()
        centre[g, ii] = C2[:, 0]
        centre[g, jj] = C2[:, 1]
        incr = p.arc_incremental[r]
        centre = np.where(incr[:, None], S + self._round(centre - S, inch), self._round(centre, inch))
        centre[g, nn] = S[g, nn]
        cw2 = np.stack([centre[g, ii], centre[g, jj]], axis=1)
        r0 = np.linalg.norm(s2 - cw2, axis=1)
        r1 = np.linalg.norm(e2 - cw2, axis=1)
        diff_max = np.where(inch, SPIRAL_ABS_MIN[True], SPIRAL_ABS_MIN[False])  # (any configuration's)
        r_min = np.where(inch, RADIUS_MIN[True], RADIUS_MIN[False])
        ok &= (np.abs(r0 - r1) <= diff_max) & (np.minimum(r0, r1) >= r_min)
        # the written sub-arc as the controller interpolates it
        th0 = np.arctan2(s2[:, 1] - cw2[:, 1], s2[:, 0] - cw2[:, 0])
        th1 = np.arctan2(e2[:, 1] - cw2[:, 1], e2[:, 0] - cw2[:, 0])
        sweep = np.where(ccw, (th1 - th0) % (2 * np.pi), (th0 - th1) % (2 * np.pi))
        sweep = np.where(sweep == 0.0, 2 * np.pi, sweep)
        scale = np.where(inch, MM_PER_INCH, 1.0)
        length = sweep * np.maximum(r0, r1) * scale
        nv = np.clip(np.ceil(length / CHECK_STEP_MM), CHECK_MIN, CHECK_MAX).astype(int)
        vo = np.repeat(g, nv + 1)
        u = (np.arange(vo.size) - np.repeat(np.cumsum(nv + 1) - (nv + 1), nv + 1)) / nv[vo]
        ang = th0[vo] + (sign * sweep)[vo] * u
        rad = r0[vo] + (r1 - r0)[vo] * u
        t_nom = ta[vo] + (tb - ta)[vo] * u
        nom6 = arc_points_at(p, r[vo], t_nom)
        cmd6 = nom6.copy()  # other axes (none moving on a three-axis arc) as the nominal
        k = np.arange(vo.size)
        cmd6[k, ii[vo]] = cw2[vo, 0] + rad * np.cos(ang)
        cmd6[k, jj[vo]] = cw2[vo, 1] + rad * np.sin(ang)
        cmd6[k, nn[vo]] = S[vo, nn[vo]] + u * (E[vo, nn[vo]] - S[vo, nn[vo]])
        rv = r[vo]
        q_cmd = ps.to_machine(p.to_machine(cmd6, rv), p.inch[rv])
        q_nom = ps.to_machine(p.to_machine(nom6, rv), p.inch[rv])
        loads = self._loads(force, arc_idx, owner[vo], rv, nom6)
        pa_, _ = ps.twin.actual_pose(q_cmd, loads)
        pn_, _ = ps.twin.nominal_pose(q_nom)
        tip = pn_ + (pa_ - pn_) @ self.correctable
        dev = self._distance_to_nominal(rv, tip, t_nom) * 1e3
        worst = np.zeros(G)
        np.maximum.at(worst, vo, dev)
        ok &= worst <= self.tol_mm * 1e3
        if np.any(ok):
            self.max_deviation_um = max(self.max_deviation_um, float(worst[ok].max()))
        return centre, ok

    def _distance_to_nominal(self, rows, tip, t_hint) -> np.ndarray:
        """(K,) mm: distance of part-frame points ``tip`` (K, 3) from the nominal arcs ``rows`` (K,) (a helix, or a
        spiral where the input's radii differ), measured as the radial and axial offsets from the arc's point at the
        same angle (the axial one over-estimates the distance on a steep helix: on the safe side). The nominal
        kinematics of a three-axis motion is rigid (and scaled by 25.4 in inch): the arc's frame is mapped by it."""
        from .post import _arcs_geometry

        ps, p = self.ps, self.p
        # the arcs' frames once per arc (the points of an arc share it): the same numbers, point by point
        arcs, at = np.unique(rows, return_inverse=True)
        k = np.arange(arcs.size)
        ii, jj, nn, a0, sweep, rad0, rad1 = _arcs_geometry(p, arcs)
        centre6 = p.start[arcs].copy()
        centre6[k, ii] = p.arc_center[arcs][k, ii]
        centre6[k, jj] = p.arc_center[arcs][k, jj]

        def image(pts6):
            return ps.twin.nominal_pose(ps.to_machine(p.to_machine(pts6, arcs), p.inch[arcs]))[0]

        o = image(centre6)
        axes = []
        for col in (ii, jj, nn):
            unit = centre6.copy()
            unit[k, col] += 1.0
            axes.append((image(unit) - o)[at])
        o, nn, a0, sweep, rad0, rad1 = o[at], nn[at], a0[at], sweep[at], rad0[at], rad1[at]
        k = np.arange(rows.size)
        sign = np.where(p.motion[rows] == ARC_CCW, 1.0, -1.0)
        d = tip - o
        # coordinates in program units along the arc's in-plane axes and its normal
        # (an axis the machine does not have, a lathe's Y, maps to nothing: its coordinate is the plane's, 0)
        x, y, z = (np.einsum("ki,ki->k", d, a) / np.maximum(np.einsum("ki,ki->k", a, a), 1e-300) for a in axes)
        rho = np.hypot(x, y)
        phi_hint = sweep * t_hint
        turn = sign * (np.arctan2(y, x) - a0)
        phi = phi_hint + ((turn - phi_hint + np.pi) % (2 * np.pi) - np.pi)
        frac = phi / sweep
        r_nom = rad0 + (rad1 - rad0) * frac
        s_n, e_n = p.start[rows][k, nn], p.end[rows][k, nn]
        z_nom = (e_n - s_n) * frac  # from the start's (the frame's origin) height
        scale = np.linalg.norm(axes[0], axis=1)  # mm per program unit
        return np.hypot(rho - r_nom, z - z_nom) * scale


# ------------------------------------------------------------------------------------- the post's hooks -----


def written_start(poster, rows, arc_idx, delta_prog):
    """(A, 6) the end the block before each arc ``rows[arc_idx]`` writes (program coordinates), and (A,) bool:
    known (the row before is a compensated move, not a canned cycle, in this chunk or the one before)."""
    p = poster.p
    r = rows[arc_idx]
    row_before, end_before = poster._end_before_chunk  # a chunk's first move starts where the chunk before ends
    known = np.where(arc_idx > 0, rows[np.maximum(arc_idx - 1, 0)] == r - 1, r - 1 == row_before)
    known &= p.kind[np.maximum(r - 1, 0)] != ROW_CYCLE
    start = p.end[rows[np.maximum(arc_idx - 1, 0)]] + delta_prog[np.maximum(arc_idx - 1, 0)]
    if arc_idx.size and arc_idx[0] == 0 and end_before is not None:
        start[0] = end_before
    return start, known


def full_turns_close(poster, rows, arc_idx, delta_prog):
    """(A,) bool: the arc is no full turn, or its written start and end coincide in its plane (a control reads an
    end a digit off the start as a short arc, not a circle: LinuxCNC's pmCircleInit)."""
    p = poster.p
    r = rows[arc_idx]
    ii, jj = plane_columns(p.arc_plane[r])
    k = np.arange(r.size)
    full = (p.start[r, ii] == p.end[r, ii]) & (p.start[r, jj] == p.end[r, jj])
    if not np.any(full):
        return np.ones(r.size, bool)
    start, known = written_start(poster, rows, arc_idx, delta_prog)
    end = p.end[r] + delta_prog[arc_idx]
    decimals, inch = xyz_decimals(p), p.inch[r].astype(int)
    same = known.copy()
    for col in (ii, jj):
        dec = decimals[inch, col]
        same &= np.round(start[k, col] * 10.0**dec) == np.round(end[k, col] * 10.0**dec)
    return ~full | same


def radii_kept_within_limits(poster, rows, arc_idx, delta_prog):
    """(A,) bool: the arc, kept as it is (its end and centre moved by its end's correction, from the end the block
    before writes), stays within LinuxCNC's limits of an arc's radii (``nc.interp_arc``, at the default tolerance the
    input was read with), with a margin for the written digits. An input arc near a limit can be pushed past it by
    the difference of its ends' corrections (at most the spread a kept arc may have): rs274 would refuse the output.
    Such an arc is fitted instead. Looked at only where the input arc itself is that near (else True)."""
    p = poster.p
    r = rows[arc_idx]
    ok = np.ones(r.size, bool)
    if r.size == 0:
        return ok
    ii, jj = plane_columns(p.arc_plane[r])
    inch = p.inch[r].astype(bool)
    decimals = xyz_decimals(p)
    step = 10.0 ** -np.minimum(decimals[inch.astype(int), ii], decimals[inch.astype(int), jj]).astype(float)
    margin = 3.0 * step  # (start, end and centre each rounded to the written digits)
    reach = margin + np.sqrt(3.0) * poster.tol_mm / 2 / np.where(inch, MM_PER_INCH, 1.0)
    spiral = np.where(inch, SPIRAL_ABS[True], SPIRAL_ABS[False])
    r_min = np.where(inch, RADIUS_MIN[True], RADIUS_MIN[False])

    def within(start, end, centre, m, sel):
        k = np.arange(start.shape[0])
        a, b = ii[sel], jj[sel]
        r1 = np.hypot(start[k, a] - centre[k, a], start[k, b] - centre[k, b])
        r2 = np.hypot(end[k, a] - centre[k, a], end[k, b] - centre[k, b])
        dr, tol = np.abs(r1 - r2), spiral[sel]
        return (np.minimum(r1, r2) >= r_min[sel] + m) & (dr <= 100.0 * tol - m) & (
            (dr <= tol - m) | (dr <= SPIRAL_REL * np.maximum(r1, r2) - m))

    near = ~within(p.start[r], p.end[r], p.arc_center[r], reach, slice(None))
    if not near.any():
        return ok
    start, known = written_start(poster, rows, arc_idx[near], delta_prog)
    delta = delta_prog[arc_idx[near]]
    ok[near] = ~known | within(start, p.end[r[near]] + delta, p.arc_center[r[near]] + delta[:, :3], margin[near],
                               near)
    return ok


def fit_arcs(poster, rows, arc_idx, force, delta_prog):
    """Arcs fitted to their corrected path (``.arcs``): ({k: (ends (n, 6), centres (n, 3))}, the indices k
    left to straight pieces). Fitted are three-axis arcs without G93 whose start the row before writes, in G90 or
    G91 (its sub-arcs' ends written as the increments between rounded ends: the control's position is the rounded
    end, as the fit takes it; G91 arcs were all written as straight pieces, 15 blocks became 1690 in a QA pass)."""
    p = poster.p
    r = rows[arc_idx]
    start, known = written_start(poster, rows, arc_idx, delta_prog)
    ok = known & ~p.inverse_time[r] & ~p.diameter[r] & (not poster.orientation)
    if not np.any(ok):
        return {}, arc_idx
    idx = arc_idx[ok]
    start_cmd = start[ok]
    end_cmd = p.end[rows[idx]] + delta_prog[idx]
    fitter = ArcFitter(poster)
    fitted, failed = fitter.fit(rows, idx, start_cmd, end_cmd, force)
    with poster._lock:  # (chunks side by side: ``post._Poster._compensate_chunks``)
        poster.rep.arcs_fitted += len(fitted)
        poster.rep.arc_blocks_fitted += sum(len(v[0]) for v in fitted.values())
        poster.rep.max_arc_deviation_um = max(poster.rep.max_arc_deviation_um, fitter.max_deviation_um)
        poster.rep.sub_arcs_linearised += fitter.sub_arcs_linearised
    return fitted, np.sort(np.r_[arc_idx[~ok], failed]).astype(int)
