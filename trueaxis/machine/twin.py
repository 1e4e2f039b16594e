"""The error twin: the actual tool pose of a machine with ISO 230 errors and force-induced errors.

Each axis factor of the nominal chain (see ``kinematics``) becomes, with errors,

    tool branch:       G*_k(q) = E_k(q; r_k) . L_k G_k(q + z_k) L_k^-1
    workpiece branch:  G*_k(q) = L_k G_k(q + z_k) L_k^-1 . E_k(q; 0)

* ``E_k`` is the small-angle transform of DESIGN §3 built from the axis' six component errors
  (E_X<k>, E_Y<k>, E_Z<k>; E_A<k>, E_B<k>, E_C<k>) at the reference point ``r_k``: the tool tip with the other axes at
  zero, expressed in the frame of the body that carries the axis (M with all axes at zero). The component errors
  are errors of the *relative* motion (tool relative to part), as a tool-to-table measurement reads them; their angular
  part turns everything downstream about the reference point, so lever arms come from the other axes' positions.
* ``L_k`` is the location error: for a rotary axis the offsets (XOC, YOC, ...) and tilts (AOC, BOC, ...) of its line,
  the tilts about its pivot; for a linear axis the squareness (C0Y, B0Z, A0Z) turns its direction. At q = 0 it alone
  causes no error. ``z_k`` is a rotary axis' zero-angle offset (COC, BOB, AOA).
* Force-induced errors enter as a translation at the bed: the compliance matrix times the force on the tool, plus the
  lathe paper's response surfaces; the equivalent-load parameter set blends each axis' parameters with the force
  component along that axis (``value(F) = unloaded + F_k / F_load,k (loaded - unloaded)``).

Two formulations are kept: ``actual_pose`` multiplies the full transforms; ``differential_error`` is the first-order
differential-motion form of the differential-motion-matrix paper (each error twist carried along the nominal chain to
the tool tip and summed). They agree up to second order in the errors.

The full product is computed twice over, by design: the poses and axis Jacobians go through the compiled kernel of
``chain_kernel`` (the component errors and their slopes evaluated beforehand for all links at once, compiled too, by
``error_kernel``); ``_evaluate`` composes the same chain in numpy with the derivatives by every parameter, for the
parameter Jacobian, from each error function's reference evaluation (``__call__``, ``derivative``, ``basis``), and is
the compiled path's reference.

Units: poses q in mm and rad; positions in mm; error parameters in um and urad (machine file units).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..compiled import THREADS_MIN, aot_available, kernels_shared, run_threads, run_twins, thread_slices
from . import chain_kernel
from .error_kernel import CompiledErrors
from .kinematics import Z_TOOL, Link, axis_motion, chain_links, validate_poses
from .model import ERROR_DIRECTIONS, SQUARENESS, Machine, is_angle_name
from .transforms import UNIT, skew

UM = 1e-3  # mm per um
URAD = 1e-6  # rad per urad
DEFAULT_CHUNK = 20_000
# From this many poses on, the compiled chain runs on all threads (the kernels' ahead-of-time twins on threads of
# their own, else numba prange; NUMBA_NUM_THREADS sets how many).
PARALLEL_MIN = THREADS_MIN


def _internal(name: str) -> float:
    """Scale from a parameter's file unit (um / urad) to internal units (mm / rad)."""
    return URAD if is_angle_name(name) else UM


@dataclass(frozen=True)
class _LocationSource:
    name: str
    kind: str  # "offset" | "tilt" | "zero" | "square"
    vector: np.ndarray  # unit direction of the offset, of the tilt's rotation, or of the squareness rotation


@dataclass
class _Deriv:
    """Derivative of one factor with respect to some Jacobian columns.

    dR : None, ("skew", w (N|1, 3)) meaning [w]x, or ("mat", M (N|1, 3, 3)).  dt : None or (N|1, 3).
    cols : (k,) column indices; weights : (N|1, k) chain-rule weights per column.
    """

    cols: np.ndarray
    weights: np.ndarray
    dR: tuple | None
    dt: np.ndarray | None


def _rot_apply(dR, x):
    if dR is None:
        return 0.0
    kind, m = dR
    if kind == "skew":
        return np.cross(m, x)
    return np.einsum("...ij,...j->...i", m, x)


class ErrorTwin:
    """A machine's error model, evaluated on arrays of poses.

    Parameters
    ----------
    machine : Machine (from ``load_machine``).
    """

    def __init__(self, machine: Machine):
        self.machine = machine
        self.links: list[Link] = chain_links(machine)
        self.n_axes = len(machine.axis_names)
        self.parameter_names = machine.parameter_names()
        self.n_params = len(self.parameter_names)
        index = {n: self.n_axes + i for i, n in enumerate(self.parameter_names)}
        self._col = index
        self._location_sources = {lk.axis: self._sources(lk) for lk in self.links}
        # Component parameter columns: axis -> comp -> (cols,)
        self._comp_cols = {}
        i = self.n_axes + len(machine.location_names())
        for axis, comps in machine._component_items():
            for comp, fn in comps:
                self._comp_cols[(axis, comp)] = np.arange(i, i + fn.values.size)
                i += fn.values.size
        # The chain's layout as the compiled kernel takes it (chain_kernel's docstring).
        tool_links = [k for k, lk in enumerate(self.links) if lk.branch == "tool"]
        self._layout = (
            np.array([lk.column for lk in self.links], dtype=np.int64),
            np.array([lk.rotary for lk in self.links], dtype=bool),
            np.array([lk.branch == "tool" for lk in self.links], dtype=bool),
            np.array([lk.direction for lk in self.links], dtype=float).reshape(-1, 3),
            np.array([lk.pivot for lk in self.links], dtype=float).reshape(-1, 3),
            np.asarray(machine.workpiece_origin, dtype=float),
            tool_links[0] if tool_links else len(self.links),
        )
        # The compiled path's inputs that do not depend on the poses (``_chain_values``; the packed component
        # functions too, on first use: ``_components``).
        L = len(self.links)
        self._constant_location = self._location_arrays(None, 1)
        d_nominal = np.array([lk.direction for lk in self.links], dtype=float).reshape(L, 1, 3)
        self._nominal_values = (np.zeros((L, 1, 3)), np.zeros((L, 1, 3)), np.zeros((L, 1)), d_nominal,
                                np.zeros((L, 1, 6)), np.zeros((1, 3)))
        self._zero_derivatives = (np.zeros((L, 1, 6)), np.zeros((1, 3, self.n_axes)))

    # ----------------------------------------------------------------------------------------------- public API ----
    def nominal_pose(self, q):
        """Nominal tool tip (N,3) mm and unit tool axis (N,3), part frame."""
        q = validate_poses(self.machine, q)
        P, U = np.empty((q.shape[0], 3)), np.empty((q.shape[0], 3))
        for sl in _chunks(q.shape[0]):
            P[sl], U[sl], _ = self._compose(q[sl], None, None, errors=False, jacobian=False)
        return P, U

    def actual_pose(self, q, force_n=None, motion=None):
        """Actual tool tip (N,3) mm and unit tool axis (N,3), part frame, full product of transforms.

        force_n : (N,3) or (3,) force of the workpiece on the tool, N, machine frame; None = unloaded.
        motion : (N, n_axes) direction of motion of each axis (sign), for the response surfaces; None = forward.
        """
        q = validate_poses(self.machine, q)
        P, U = np.empty((q.shape[0], 3)), np.empty((q.shape[0], 3))
        for sl in _chunks(q.shape[0]):
            P[sl], U[sl], _ = self._compose(q[sl], _slice(force_n, sl), _slice(motion, sl), errors=True, jacobian=False)
        return P, U

    def volumetric_error(self, q, force_n=None, motion=None, method: str = "full"):
        """Position error (N,3) um and tool-axis error (N,3) urad: actual minus nominal, part frame.

        method : "full" (product of homogeneous transforms) or "differential" (first-order differential-motion form).
        """
        q = validate_poses(self.machine, q)
        if method == "differential":
            return self.differential_error(q, force_n, motion)
        if method != "full":
            raise ValueError(f"method must be 'full' or 'differential', got {method!r}")
        out_p, out_u = np.empty((q.shape[0], 3)), np.empty((q.shape[0], 3))
        for sl in _chunks(q.shape[0]):
            f, m = _slice(force_n, sl), _slice(motion, sl)
            pa, ua, _ = self._compose(q[sl], f, m, errors=True, jacobian=False)
            pn, un, _ = self._compose(q[sl], None, None, errors=False, jacobian=False)
            out_p[sl] = (pa - pn) / UM
            out_u[sl] = (ua - un) / URAD
        return out_p, out_u

    def axis_jacobian(self, q, force_n=None, motion=None):
        """d(tip mm, unit axis)/d(q mm | rad) of the actual pose: (N, 6, n_axes), exact for the full model."""
        q = validate_poses(self.machine, q)
        J = np.empty((q.shape[0], 6, self.n_axes))
        for sl in _chunks(q.shape[0]):
            J[sl] = self._compose(q[sl], _slice(force_n, sl), _slice(motion, sl), errors=True, jacobian=True)[2]
        return J

    def pose_and_axis_jacobian(self, q, force_n=None, motion=None):
        """Actual pose and its axis Jacobian in one pass: tip (N,3), unit axis (N,3), J (N, 6, n_axes); the same
        numbers as ``actual_pose`` and ``axis_jacobian``."""
        q = validate_poses(self.machine, q)
        n = q.shape[0]
        P, U = np.empty((n, 3)), np.empty((n, 3))
        J = np.empty((n, 6, self.n_axes))
        for sl in _chunks(n):
            P[sl], U[sl], J[sl] = self._compose(q[sl], _slice(force_n, sl), _slice(motion, sl), errors=True,
                                                jacobian=True)
        return P, U, J

    def parameter_jacobian(self, q, force_n=None, motion=None):
        """d(position error um, tool-axis error urad)/d(parameter um | urad): (N, 6, n_params), exact.

        Columns follow ``machine.parameter_names()`` (location errors, then component-table values).
        """
        q = validate_poses(self.machine, q)
        J = np.empty((q.shape[0], 6, self.n_params))
        for sl in _chunks(q.shape[0], max(1, DEFAULT_CHUNK * 20 // max(self.n_params, 1))):
            Jc = self._evaluate(q[sl], _slice(force_n, sl), _slice(motion, sl), True, True, cols="params")[2]
            J[sl] = Jc
        # Internal columns are per mm / per rad of the parameter: convert to file units, rows to um / urad.
        scale = np.array([_internal(n) for n in self.parameter_names])
        J *= scale
        J[:, :3] /= UM
        J[:, 3:] /= URAD
        return J

    def jacobians(self, q, force_n=None, motion=None):
        """Axis and parameter Jacobians in one pass: (N,6,n_axes) and (N,6,n_params), units as the two methods."""
        q = validate_poses(self.machine, q)
        Ja = np.empty((q.shape[0], 6, self.n_axes))
        Jp = np.empty((q.shape[0], 6, self.n_params))
        for sl, _, _, ja, jp in self.iter_errors_and_jacobians(q, force_n, motion):
            Ja[sl], Jp[sl] = ja, jp
        return Ja, Jp

    def iter_errors_and_jacobians(self, q, force_n=None, motion=None, chunk: int | None = None):
        """Stream over chunks of poses: yields (slice, position error (n,3) um, tool-axis error (n,3) urad,
        axis Jacobian (n,6,n_axes), parameter Jacobian (n,6,n_params)), units as ``axis_jacobian`` and
        ``parameter_jacobian``. For millions of poses, whose dense parameter Jacobian would not fit in memory.
        """
        q = validate_poses(self.machine, q)
        if chunk is None:
            chunk = max(256, 4_000_000 // (6 * (self.n_axes + self.n_params)))  # ~32 MB of Jacobian per chunk
        scale = np.array([_internal(n) for n in self.parameter_names])
        row = np.array([1 / UM] * 3 + [1 / URAD] * 3)[:, None]
        for sl in _chunks(q.shape[0], chunk):
            f, m = _slice(force_n, sl), _slice(motion, sl)
            pa, ua, J = self._evaluate(q[sl], f, m, True, True, cols="all")
            pn, un, _ = self._compose(q[sl], None, None, errors=False, jacobian=False)
            Jp = J[:, :, self.n_axes :]
            Jp *= scale * row
            yield sl, (pa - pn) / UM, (ua - un) / URAD, J[:, :, : self.n_axes], Jp

    # -------------------------------------------------------------------------------------------- the error values --
    def _sources(self, link: Link) -> list[_LocationSource]:
        m = self.machine
        if not link.rotary:
            return [_LocationSource(n, "square", UNIT[rot]) for n, (ax, rot) in SQUARENESS.items() if ax == link.axis]
        about = m.axes[link.axis].about
        out = []
        for d in "XYZ":
            if d != about:
                out.append(_LocationSource(f"{d}O{link.axis}", "offset", UNIT[d]))
        for d in "XYZ":
            if d != about:
                out.append(_LocationSource(f"{'ABC'['XYZ'.index(d)]}O{link.axis}", "tilt", UNIT[d]))
        out.append(_LocationSource(f"{'ABC'['XYZ'.index(about)]}O{link.axis}", "zero", link.direction))
        return out

    def _blend(self, axis: str, force_n, n: int):
        """Share s of the loaded set for this axis' parameters, (n,), and whether a loaded set exists."""
        m = self.machine
        if m.loaded is None or force_n is None:
            return None
        d = m.axes[axis].direction
        ref = float(m.loaded_force_n @ d)
        if ref == 0.0:
            return None
        return np.broadcast_to(np.asarray(force_n, float), (n, 3)) @ d / ref

    def _location_values(self, axis: str, force_n, n: int):
        """name -> (values (n,) internal units, d value / d unloaded parameter (n,))."""
        m = self.machine
        s = self._blend(axis, force_n, n)
        out = {}
        for src in self._location_sources[axis]:
            v0 = m.errors.location.get(src.name, 0.0)
            if s is not None and src.name in m.loaded.location:
                # Absent from the loaded set means measured unchanged under load.
                val = v0 + s * (m.loaded.location[src.name] - v0)
                dval = 1.0 - s
            else:
                val, dval = np.full(n, v0), np.ones(n)
            out[src.name] = (np.asarray(val) * _internal(src.name), np.asarray(dval))
        return out

    def _component_values(self, link: Link, q_axis, force_n, n: int, deriv: bool = True):
        """Per-component values (n,6) and d/dq (n,6) in mm and rad; plus per-component Jacobian factors."""
        m = self.machine
        comps = m.errors.components.get(link.axis, {})
        loaded = m.loaded.components.get(link.axis, {}) if m.loaded is not None else {}
        s = self._blend(link.axis, force_n, n)
        val = np.zeros((n, 6))
        dval = np.zeros((n, 6))
        blend = {}
        for j, d in enumerate(ERROR_DIRECTIONS):
            name = f"E{d}{link.axis}"
            scale = URAD if d in "ABC" else UM
            fn = comps.get(name)
            v = fn(q_axis) if fn is not None else 0.0
            dv = fn.derivative(q_axis) if (fn is not None and deriv) else 0.0
            factor = np.ones(n)
            if s is not None and name in loaded:
                fl = loaded[name]
                v = v + s * (fl(q_axis) - v)
                if deriv:
                    dv = dv + s * (fl.derivative(q_axis) - dv)
                factor = 1.0 - s
            val[:, j] = v * scale
            dval[:, j] = dv * scale
            blend[name] = factor
        return val, dval, blend

    def _bed_deflection(self, q, force_n, motion, n):
        """Translation at the bed (n,3) mm from compliance and response surfaces, and d/dq per axis column."""
        m = self.machine
        d = np.zeros((n, 3))
        dd = {}
        if force_n is None:
            return d, dd
        F = np.broadcast_to(np.asarray(force_n, float), (n, 3))
        if m.compliance_um_per_n is not None:
            d += F @ m.compliance_um_per_n.T * UM
        names = m.axis_names
        for s in m.surfaces:
            col = names.index(s.position_axis)
            x = q[:, col]
            P = F[:, "XYZ".index(s.force_direction)] / 1000.0
            sign = np.where(P >= 0, 1, -1)
            mot = np.ones(n) if motion is None else np.where(np.asarray(motion)[:, col] >= 0, 1, -1)
            use = (sign == s.load_sign) & (mot == s.motion)
            c = s.coeffs
            val = c[0] + c[1] * x + c[2] * P + c[3] * x**2 + c[4] * x * P + c[5] * P**2
            dval = c[1] + 2 * c[3] * x + c[4] * P
            e = UNIT[s.axis]
            d += np.where(use, val, 0.0)[:, None] * e * UM
            dd[col] = dd.get(col, 0.0) + np.where(use, dval, 0.0)[:, None] * e * UM
        return d, dd

    # ----------------------------------------------------------------------------------------------- the chain ----
    def _factors(self, q, force_n, motion, errors: bool, jacobian: bool, cols: str):
        """The chain as a list of factors (R, t) with their derivatives (list of _Deriv)."""
        m = self.machine
        n = q.shape[0]
        want_axes = jacobian and cols in ("axes", "all")
        want_params = jacobian and cols in ("params", "all")
        factors = [((np.eye(3), -m.workpiece_origin), [])]
        bed_inserted = False
        for link in self.links:
            if link.branch == "tool" and not bed_inserted:
                factors.append(self._bed_factor(q, force_n, motion, n, errors, want_axes))
                bed_inserted = True
            qa = q[:, link.column]
            col = np.array([link.column])
            if not errors:
                (R, t), (dR, dt) = axis_motion(link, qa)
                derivs = [_Deriv(col, np.ones((1, 1)), None if dR is None else ("mat", dR), dt)] if want_axes else []
                factors.append(((R, t), derivs))
                continue
            loc = self._location_values(link.axis, force_n, n)
            F, F_derivs = self._located_motion(link, qa, loc, want_axes, want_params)
            E, E_derivs = self._component_factor(link, qa, force_n, n, want_axes, want_params)
            if link.branch == "tool":
                factors += [(E, E_derivs), (F, F_derivs)]
            else:
                factors += [(F, F_derivs), (E, E_derivs)]
        if not bed_inserted:
            factors.append(self._bed_factor(q, force_n, motion, n, errors, want_axes))
        return factors

    def _bed_factor(self, q, force_n, motion, n, errors, want_axes):
        if not errors:
            return (np.eye(3), np.zeros(3)), []
        d, dd = self._bed_deflection(q, force_n, motion, n)
        derivs = [_Deriv(np.array([c]), np.ones((1, 1)), None, v) for c, v in dd.items()] if want_axes else []
        return (np.eye(3), d), derivs

    def _actual_direction(self, link: Link, loc, n: int):
        """A linear axis' direction (n,3) turned by its squareness values (first order, DESIGN §3)."""
        d_act = np.broadcast_to(link.direction, (n, 3)).copy()
        for src in self._location_sources[link.axis]:
            d_act += loc[src.name][0][:, None] * np.cross(src.vector, link.direction)
        return d_act

    def _line_errors(self, link: Link, loc, n: int):
        """A rotary axis' line errors: tilt eps (n,3) rad, offset (n,3) mm and zero-angle offset (n,) rad."""
        eps = np.zeros((n, 3))
        off = np.zeros((n, 3))
        zero = np.zeros(n)
        for src in self._location_sources[link.axis]:
            v = loc[src.name][0]
            if src.kind == "offset":
                off += v[:, None] * src.vector
            elif src.kind == "tilt":
                eps += v[:, None] * src.vector
            else:
                zero = zero + v
        return eps, off, zero

    def _located_motion(self, link: Link, qa, loc, want_axes, want_params):
        """L G(q + z) L^-1 as (R, t) and its derivatives by q and by each location parameter."""
        n = qa.shape[0]
        derivs = []
        sources = self._location_sources[link.axis]
        if not link.rotary:
            d_act = self._actual_direction(link, loc, n)
            R = np.broadcast_to(np.eye(3), (n, 3, 3))
            t = qa[:, None] * d_act
            if want_axes:
                derivs.append(_Deriv(np.array([link.column]), np.ones((1, 1)), None, d_act))
            if want_params:
                for src in sources:
                    g = qa[:, None] * np.cross(src.vector, link.direction)
                    derivs.append(_Deriv(np.array([self._col[src.name]]), loc[src.name][1][:, None], None, g))
            return (R, t), derivs
        c = link.pivot
        eps, off, zero = self._line_errors(link, loc, n)
        # L p = (I + [eps]x)(p - c) + c + off; its exact inverse in closed form.
        RL = np.eye(3) + skew(eps)
        tL = off - np.cross(eps, c)
        RLi = (np.eye(3) - skew(eps) + np.einsum("ni,nj->nij", eps, eps)) / (1.0 + np.sum(eps**2, 1))[:, None, None]
        tLi = -np.einsum("nij,nj->ni", RLi, tL)
        (RG, tG), (dRG, dtG) = axis_motion(link, qa + zero)
        R_GLi = RG @ RLi
        t_GLi = np.einsum("nij,nj->ni", RG, tLi) + tG
        R_LG = RL @ RG
        R = R_LG @ RLi
        t = np.einsum("nij,nj->ni", RL, t_GLi) + tL
        if want_axes or want_params:
            # d/dq of L G L^-1 (also d/d zero offset): L G' L^-1.
            dR_q = RL @ dRG @ RLi
            dt_q = np.einsum("nij,nj->ni", RL, np.einsum("nij,nj->ni", dRG, tLi) + dtG)
        if want_axes:
            derivs.append(_Deriv(np.array([link.column]), np.ones((1, 1)), ("mat", dR_q), dt_q))
        if want_params:
            for src in sources:
                w = loc[src.name][1][:, None]
                col = np.array([self._col[src.name]])
                if src.kind == "zero":
                    derivs.append(_Deriv(col, w, ("mat", dR_q), dt_q))
                    continue
                if src.kind == "tilt":
                    dRL = np.broadcast_to(skew(src.vector), (n, 3, 3))
                    dtL = np.broadcast_to(-np.cross(src.vector, c), (n, 3))
                else:
                    dRL = np.zeros((n, 3, 3))
                    dtL = np.broadcast_to(src.vector, (n, 3))
                # d(L^-1) = -L^-1 dL L^-1;  d(L G L^-1) = dL (G L^-1) + (L G) d(L^-1)
                dRLi = -RLi @ dRL @ RLi
                dtLi = -np.einsum("nij,nj->ni", RLi, np.einsum("nij,nj->ni", dRL, tLi) + dtL)
                dR = dRL @ R_GLi + R_LG @ dRLi
                dt = np.einsum("nij,nj->ni", dRL, t_GLi) + dtL + np.einsum("nij,nj->ni", R_LG, dtLi)
                derivs.append(_Deriv(col, w, ("mat", dR), dt))
        return (R, t), derivs

    def _reference_point(self, link: Link, qa):
        """Reference point r_k (n,3) of the component errors and dr/dq, in the carrying body's frame (mm)."""
        n = qa.shape[0]
        if link.branch == "workpiece":
            return np.zeros((n, 3)), np.zeros((n, 3))
        (R, t), (dR, dt) = axis_motion(link, qa)
        return t, dt  # G(q) applied to the tip at the origin

    def _component_factor(self, link: Link, qa, force_n, n, want_axes, want_params):
        val, dval, blend = self._component_values(link, qa, force_n, n, deriv=want_axes)
        delta, eps = val[:, :3], val[:, 3:]
        r, dr = self._reference_point(link, qa)
        R = np.eye(3) + skew(eps)
        t = delta - np.cross(eps, r)
        derivs = []
        if want_axes:
            deps = dval[:, 3:]
            dt = dval[:, :3] - np.cross(deps, r) - np.cross(eps, dr)
            derivs.append(_Deriv(np.array([link.column]), np.ones((1, 1)), ("skew", deps), dt))
        if want_params:
            comps = self.machine.errors.components.get(link.axis, {})
            for j, d in enumerate(ERROR_DIRECTIONS):
                name = f"E{d}{link.axis}"
                if name not in comps:
                    continue
                fn = comps[name]
                weights = fn.basis(qa) * blend[name][:, None]
                e = UNIT["XYZ"[j % 3]]
                if j < 3:
                    derivs.append(_Deriv(self._comp_cols[(link.axis, name)], weights, None, np.broadcast_to(e, (n, 3))))
                else:
                    w = np.broadcast_to(e, (n, 3))
                    derivs.append(_Deriv(self._comp_cols[(link.axis, name)], weights, ("skew", w), -np.cross(e, r)))
        return (R, t), derivs

    # --------------------------------------------------------------------------------- the chain, compiled ----
    @cached_property
    def _components(self) -> CompiledErrors:
        return self._compiled(self.machine.errors.components)

    @cached_property
    def _loaded_components(self) -> CompiledErrors | None:
        return self._compiled(self.machine.loaded.components) if self.machine.loaded is not None else None

    def _compiled(self, components) -> CompiledErrors:
        """An error set's component functions packed for ``error_kernel``: the value of component j (EX.. EC..) of
        link k, in mm or rad, goes to slot (k, j)."""
        entries = []
        for k, link in enumerate(self.links):
            comps = components.get(link.axis, {})
            for j, d in enumerate(ERROR_DIRECTIONS):
                fn = comps.get(f"E{d}{link.axis}")
                if fn is not None:
                    entries.append((fn, link.column, k, j, URAD if d in "ABC" else UM))
        return CompiledErrors(entries, (len(self.links), 6))

    def _location_arrays(self, force_n, n: int):
        """Every link's location errors as ``chain_kernel`` takes them: tilt (L, n, 3), offset (L, n, 3), zero (L, n)
        and d_act (L, n, 3) (zero where they do not apply)."""
        L = len(self.links)
        tilt, offset, d_act = np.zeros((L, n, 3)), np.zeros((L, n, 3)), np.zeros((L, n, 3))
        zero = np.zeros((L, n))
        for k, link in enumerate(self.links):
            loc = self._location_values(link.axis, force_n, n)
            if link.rotary:
                tilt[k], offset[k], zero[k] = self._line_errors(link, loc, n)
            else:
                d_act[k] = self._actual_direction(link, loc, n)
        return tilt, offset, zero, d_act

    def _chain_values(self, q, force_n, motion, errors: bool, jacobian: bool):
        """The per-pose inputs of ``chain_kernel`` (its docstring): the error values of every link.

        Returns (tilt, offset, zero, d_act, comp, bed), then (dcomp, dbed) when jacobian. Inputs that are the same for
        every pose come with 1 for their pose dimension: the location errors unless a loaded set blends them with the
        force, the bed without force, its derivative without response surfaces, and every error value of the nominal
        chain (zero, each linear axis moving along its nominal direction).
        """
        n = q.shape[0]
        if not errors:
            return self._nominal_values + (self._zero_derivatives if jacobian else ())
        m = self.machine
        blended = force_n is not None and m.loaded is not None
        location = self._location_arrays(force_n, n) if blended and m.loaded.location else self._constant_location
        comp, dcomp = self._components.evaluate(q, derivative=jacobian)
        if blended and self._loaded_components is not None:
            self._blend_components(q, force_n, comp, dcomp)
        dbed = self._zero_derivatives[1]
        if force_n is None:
            bed = self._nominal_values[5]
        else:
            bed, dd = self._bed_deflection(q, force_n, motion, n)
            if jacobian and dd:
                dbed = np.zeros((n, 3, self.n_axes))
                for c, v in dd.items():
                    dbed[:, :, c] = v
        values = (*location, comp, bed)
        return values + (dcomp, dbed) if jacobian else values

    def _blend_components(self, q, force_n, comp, dcomp):
        """Blend, in place, the component values (and slopes, unless None) of the axes with a loaded set towards it:
        value(F) = unloaded + s (loaded - unloaded), s the force's share of the loaded-set force along the axis, as
        ``_component_values``."""
        n = q.shape[0]
        comp_l, dcomp_l = self._loaded_components.evaluate(q, derivative=dcomp is not None)
        for k, link in enumerate(self.links):
            loaded = self.machine.loaded.components.get(link.axis, {})
            s = self._blend(link.axis, force_n, n)
            if s is None or not loaded:
                continue
            for j, d in enumerate(ERROR_DIRECTIONS):
                if f"E{d}{link.axis}" in loaded:
                    comp[k, :, j] += s * (comp_l[k, :, j] - comp[k, :, j])
                    if dcomp is not None:
                        dcomp[k, :, j] += s * (dcomp_l[k, :, j] - dcomp[k, :, j])

    def _compose(self, q, force_n, motion, errors: bool, jacobian: bool):
        """Tip (n,3), unit axis (n,3) and, with jacobian, the axis Jacobian (n, 6, n_axes) (else None), by the
        compiled chain: the numbers of ``_evaluate(..., cols="axes")`` up to round-off."""
        q = np.ascontiguousarray(q)
        # many poses: the serial kernels' ahead-of-time twins on threads, each on its share of the poses, else numba's
        # parallel kernels (the same numbers, pose by pose); few (or on a thread of the caller's own, inside
        # ``compiled.kernels_on_this_thread``): the serial ones (no thread start-up)
        parallel = q.shape[0] >= PARALLEL_MIN and kernels_shared(q.shape[0])
        if errors and force_n is None and parallel:
            out = self._threaded_unloaded(q, jacobian)
            if out is not None:
                return out
        values = self._chain_values(q, force_n, motion, errors, jacobian)
        if parallel:
            out = _threaded(chain_kernel.pose_and_axis_jacobian if jacobian else chain_kernel.pose, q, self._layout,
                            values)
            if out is not None:
                return out if jacobian else (*out, None)
        if jacobian:
            kernel = chain_kernel.pose_and_axis_jacobian_parallel if parallel else chain_kernel.pose_and_axis_jacobian
            return kernel(q, *self._layout, *values)
        kernel = chain_kernel.pose_parallel if parallel else chain_kernel.pose
        return (*kernel(q, *self._layout, *values), None)

    def unloaded_kernel_args(self) -> tuple:
        """What a compiled kernel needs to compose the unloaded chain (no force: geometric errors alone), as
        ``_compose`` passes it: the layout (column .. bed_at), the location errors (tilt, offset, zero, d_act), the
        bed and its derivative (zero without force), then the packed component functions (groups .. n_harmonics,
        ``error_kernel.evaluate_packed``'s arguments). (``postproc.newton_kernel.solve_unloaded`` takes them.)"""
        c = self._components
        return (*self._layout, *self._constant_location, self._nominal_values[5], self._zero_derivatives[1], c.groups,
                c.grid, c.members, c.coef, c.scale, c.zero_slots, c.n_harmonics)

    def _threaded_unloaded(self, q, jacobian: bool):
        """``_compose`` of many poses without force: each thread evaluates the component errors of its share of the
        poses and composes their chains (both by the kernels' ahead-of-time twins; the other inputs are the same for
        every pose, as ``_chain_values`` gives them without force), the shares joined; None without twins."""
        parts = thread_slices(q.shape[0])
        if not parts:
            return None
        kernel = chain_kernel.pose_and_axis_jacobian if jacobian else chain_kernel.pose
        twin = getattr(kernel, "twin", None)
        shared = self._constant_location, self._nominal_values[5], self._zero_derivatives[1]

        def share(sl):
            evaluated = self._components.twin_evaluate(q[sl], jacobian)
            if evaluated is None or twin is None:
                return None
            comp, dcomp = evaluated
            args = (q[sl], *self._layout, *shared[0], comp, shared[1]) + ((dcomp, shared[2]) if jacobian else ())
            fn = twin(*args)
            return None if fn is None else fn(*args)

        results = run_threads(share, parts)
        if any(r is None for r in results):
            return None
        out = tuple(np.concatenate(x) for x in zip(*results))
        return out if jacobian else (*out, None)

    # ------------------------------------------------------------------------------------ the chain, in numpy ----
    def _evaluate(self, q, force_n, motion, errors: bool, jacobian: bool, cols: str = "all"):
        """Tip (n,3), unit axis (n,3), and the Jacobian (n, 6, k) over the requested columns (or None).

        The parameter Jacobian's path, and the reference of the compiled ``_compose``."""
        n = q.shape[0]
        factors = self._factors(q, force_n, motion, errors, jacobian, cols)
        # Prefix rotations (part side) and the total transform.
        R_acc = np.broadcast_to(np.eye(3), (n, 3, 3))
        t_acc = np.zeros((n, 3))
        prefix = []
        for (R, t), _ in factors:
            prefix.append(R_acc)
            t_acc = _matvec(R_acc, np.broadcast_to(t, (n, 3))) + t_acc
            R_acc = R_acc @ R
        u_raw = R_acc[:, :, 2]
        norm = np.linalg.norm(u_raw, axis=1)
        u = u_raw / norm[:, None]
        if not jacobian:
            return t_acc, u, None
        # Suffix: the tip point and the tool axis seen on the right-hand side of each factor.
        p_after = [None] * len(factors)
        u_after = [None] * len(factors)
        p = np.zeros((n, 3))
        v = np.broadcast_to(Z_TOOL, (n, 3))
        for i in range(len(factors) - 1, -1, -1):
            p_after[i], u_after[i] = p, v
            (R, t), _ = factors[i]
            p = np.einsum("...ij,...j->...i", R, p) + t
            v = np.einsum("...ij,...j->...i", R, v)
        offset = {"axes": 0, "params": self.n_axes, "all": 0}[cols]
        width = {"axes": self.n_axes, "params": self.n_params, "all": self.n_axes + self.n_params}[cols]
        J = np.zeros((n, 6, width))
        for i, (_, derivs) in enumerate(factors):
            RA = prefix[i]
            for dv in derivs:
                dp = _rot_apply(dv.dR, p_after[i]) + (0.0 if dv.dt is None else dv.dt)
                dp = _matvec(RA, np.broadcast_to(dp, (n, 3)))
                # Columns of one derivative are contiguous: a slice, not fancy indexing.
                c0 = int(dv.cols[0]) - offset
                c1 = c0 + dv.cols.size
                w = dv.weights
                if dv.dR is not None:
                    du = _matvec(RA, np.broadcast_to(_rot_apply(dv.dR, u_after[i]), (n, 3)))
                if w.shape == (1, 1):
                    J[:, :3, c0] += dp
                    if dv.dR is not None:
                        J[:, 3:, c0] += du
                    continue
                w = np.broadcast_to(w, (n, c1 - c0))
                J[:, :3, c0:c1] += dp[:, :, None] * w[:, None, :]
                if dv.dR is not None:
                    J[:, 3:, c0:c1] += du[:, :, None] * w[:, None, :]
        # Unit tool axis: project the raw axis derivative (the small-angle matrices are not exactly orthonormal).
        proj = (np.eye(3) - np.einsum("ni,nj->nij", u, u)) / norm[:, None, None]
        J[:, 3:] = proj @ J[:, 3:]
        return t_acc, u, J

    # --------------------------------------------------------------------------------- differential-motion form ---
    def differential_error(self, q, force_n=None, motion=None):
        """First-order position error (N,3) um and tool-axis error (N,3) urad: each axis' error twist carried along
        the nominal chain to the tool tip and summed (differential-motion-matrix method).
        """
        q = validate_poses(self.machine, q)
        out_p, out_u = np.empty((q.shape[0], 3)), np.empty((q.shape[0], 3))
        for sl in _chunks(q.shape[0]):
            out_p[sl], out_u[sl] = self._differential(q[sl], _slice(force_n, sl), _slice(motion, sl))
        return out_p, out_u

    def _differential(self, q, force_n, motion):
        m = self.machine
        n = q.shape[0]
        # Nominal chain: part placement, the axes, with the bed between the branches.
        nominal = [(np.broadcast_to(np.eye(3), (n, 3, 3)), np.broadcast_to(-m.workpiece_origin, (n, 3)))]
        # Error twists (eps, delta) inserted just before (on the part side of) factor index i.
        twists: list[tuple[int, np.ndarray, np.ndarray]] = []
        bed_twist = None
        for link in self.links:
            if link.branch == "tool" and bed_twist is None:
                bed_twist = len(nominal)
            qa = q[:, link.column]
            loc = self._location_values(link.axis, force_n, n)
            val, _, _ = self._component_values(link, qa, force_n, n)
            eps_c, delta_c = val[:, 3:], val[:, :3]
            i = len(nominal)
            nominal.append(axis_motion(link, qa)[0])
            # Component errors: on the carrying body's side of the axis (tool branch: before G; workpiece: after G).
            if link.branch == "tool":
                r, _ = self._reference_point(link, qa)
                twists.append((i, eps_c, delta_c - np.cross(eps_c, r)))
            else:
                twists.append((i + 1, eps_c, delta_c))
            # Location errors: L G L^-1 ~ G + [lambda] G - G [lambda]; zero offset: G(q + z) ~ G + z G'.
            delta_l = np.zeros((n, 3))
            for src in self._location_sources[link.axis]:
                v = loc[src.name][0][:, None]
                if src.kind == "square":
                    delta_l += v * qa[:, None] * np.cross(src.vector, link.direction)
                elif src.kind == "offset":
                    twists.append((i, np.zeros((n, 3)), v * src.vector))
                    twists.append((i + 1, np.zeros((n, 3)), -v * src.vector))
                elif src.kind == "tilt":
                    w = v * src.vector
                    twists.append((i, w, -np.cross(w, link.pivot)))
                    twists.append((i + 1, -w, np.cross(w, link.pivot)))
                else:
                    w = v * link.direction
                    twists.append((i, w, -np.cross(w, link.pivot)))
            if np.any(delta_l):
                twists.append((i, np.zeros((n, 3)), delta_l))
        if bed_twist is None:
            bed_twist = len(nominal)
        d, _ = self._bed_deflection(q, force_n, motion, n)
        twists.append((bed_twist, np.zeros((n, 3)), d))

        # Prefix rotations and the tip / axis seen after each prefix.
        k = len(nominal)
        prefix_R = [None] * (k + 1)
        R_acc = np.broadcast_to(np.eye(3), (n, 3, 3))
        for i in range(k):
            prefix_R[i] = R_acc
            R_acc = R_acc @ nominal[i][0]
        prefix_R[k] = R_acc
        suffix_p = [None] * (k + 1)
        suffix_u = [None] * (k + 1)
        p = np.zeros((n, 3))
        v = np.broadcast_to(Z_TOOL, (n, 3))
        suffix_p[k], suffix_u[k] = p, v
        for i in range(k - 1, -1, -1):
            R, t = nominal[i]
            p = np.einsum("nij,nj->ni", R, p) + t
            v = np.einsum("nij,nj->ni", R, v)
            suffix_p[i], suffix_u[i] = p, v
        dp = np.zeros((n, 3))
        du = np.zeros((n, 3))
        for i, eps, delta in twists:
            RA = prefix_R[i]
            dp += np.einsum("nij,nj->ni", RA, delta + np.cross(eps, suffix_p[i]))
            du += np.einsum("nij,nj->ni", RA, np.cross(eps, suffix_u[i]))
        return dp / UM, du / URAD


def _matvec(R, x):
    """R x for (n,3,3) R and (n,3) x (matmul beats einsum for stacks of 3x3)."""
    return (R @ x[..., None])[..., 0]


# The pose dimension of each per-pose input of chain_kernel (tilt, offset, zero, d_act, comp, bed, dcomp, dbed)
_POSE_AXIS = (1, 1, 1, 1, 1, 0, 1, 0)


def _threaded(kernel, q, layout, values):
    """``kernel(q, *layout, *values)`` as its ahead-of-time twin on threads, each on a contiguous share of the poses
    (the per-pose inputs cut to it, shared ones as they are), the outputs joined; None where no twin takes them."""
    parts = thread_slices(q.shape[0])
    if not parts or getattr(kernel, "twin", None) is None or not aot_available():
        return None  # (numba's parallel kernel then: the inputs are not cut for nothing)
    calls = []
    for sl in parts:
        cut = tuple(v if v.shape[ax] == 1 else np.ascontiguousarray(v[sl] if ax == 0 else v[:, sl])
                    for v, ax in zip(values, _POSE_AXIS))
        calls.append((q[sl], *layout, *cut))
    results = run_twins(kernel, calls)
    if results is None:
        return None
    return tuple(np.concatenate(out) for out in zip(*results))


def _chunks(n: int, size: int = DEFAULT_CHUNK):
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


def _slice(arr, sl):
    if arr is None:
        return None
    a = np.asarray(arr, dtype=float)
    return a[sl] if a.ndim == 2 else a
