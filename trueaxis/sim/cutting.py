"""Cutting forces along a simulated run, with the engagement each pass really has.

The force model is the mechanistic (linear edge-force) model of Altintas, *Manufacturing Automation*, 2nd ed.,
Cambridge University Press 2012, ch. 2, as implemented in ``trueaxis.machine.cutting_force`` (coefficients from the
machine file's ``[cutting]`` table). What this module adds is the engagement:

- Passes: a pass is a maximal run of consecutive feed samples (rapids separate passes).
- The tool's flank is cut into slices along the flute (height z_j above the tip, width dz_j): ``fine_slices`` slices
  of ``fine_height_mm / fine_slices`` next to the tip, where slotting and pocketing passes of a few tenths of a
  millimetre engage, and ``n_heights`` slices over the rest of the flute, where flank milling engages. At each slice
  the contact point is on the material side of the tool: c_j = tip + z_j u + R m, with the feed frame of Altintas
  (x along the feed, projected normal to the tool axis; z the tool axis; y = z x x) and m = -y for down milling, +y for
  up milling (material side of a clockwise spindle; the program's ``mode``).
- Radial engagement of a slice: the stock the previous passes left there, measured exactly as the envelope of their
  tool instances along the line c_j + s (-m) (``envelope.envelope_deviation``): ae_j = max(s*, 0). Where no previous
  pass reaches within ``stock_search_mm`` of c_j (and for the first pass), the slice is in the raw stock and takes the
  program's ``ae`` (the structured comment), if the part's material mask says there is material at c_j; otherwise 0.
- Axial engagement: the slices with ae_j > 0 (and material) make up the flute contact length ap = sum dz.
- Force: the mean force over a tooth period of each slice, F_j = dz (fz A(ae_j) + B(ae_j)) in the feed frame, summed.
  The mean over a full tooth period of a slice does not depend on the helix lag, so the per-height mean force of a
  straight-fluted cutter (tabulated over ae once, linear in fz) is exact for the mean of the helical one.

Approximations (stated): the force is the tooth-period mean (no tooth-passing ripple, no runout, no dynamics); the
engagement is computed from the tool instances *before* force deflection (the deflection changes the chip by microns,
the stock by tenths of a millimetre); the previous passes' surface is their envelope (the same exactness as the
machined surface); a slice's chip is the one of a straight flute at its local ae (the contact of a tilted tool on a
curved stock is treated slice by slice, each slice as 2-D milling); the force is evaluated every ``stride`` samples
of a pass and linearly interpolated in between.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..machine.cutting_force import CuttingCoefficients, CuttingConditions, mean_force
from .envelope import envelope_deviation

MILLING_FIELDS = ("ap", "ae", "fz", "n", "d", "z", "mode", "helix")
TURNING_ONLY = ("f", "vc")  # the turning comment's own fields (DESIGN §5): a lathe's, which the shop does not cut


def structured_conditions(program, machine) -> list[dict]:
    """Cutting conditions valid at each source line: list (one per line of ``program.lines``) of dicts with keys of
    DESIGN §5 (ap ae fz n d z mode), as floats (mode as str); the machine's tool fills d and z.
    A comment applies from its own line on. The comments are read by the post's reader (``condition_marks``); the
    milling keys are checked here. Raises PostError (``file:line: reason``, a refused program) for a malformed
    comment, and names a turning comment's field as one (the shop mills)."""
    from ..postproc.post import condition_marks

    marks: dict[int, dict] = {}
    for i, fields in condition_marks(program.lines, program.source):  # (several comments on a line: in order)
        marks[i] = {**marks.get(i, {}), **fields}
    current = {"d": 2.0 * machine.tool.radius, "z": float(machine.tool.flutes)}
    out = []
    for i in range(len(program.lines)):
        if i in marks:
            current = {**current, **_milling_fields(marks[i], program.source, i + 1)}
        out.append(current)
    return out


def _milling_fields(fields: dict, source: str, line: int) -> dict:
    """One comment's milling conditions (mode as str, the others float); PostError for a field or value it refuses."""
    from ..postproc.post import PostError

    out = {}
    for k, v in fields.items():
        if k not in MILLING_FIELDS:
            turning = (" (f= and vc= are the turning comment's: a lathe program? the virtual shop mills)"
                       if k in TURNING_ONLY else "")
            raise PostError(source, line, f"structured comment: unknown milling field {k!r}{turning}")
        if k == "mode":
            if v not in ("down", "up"):
                raise PostError(source, line, f"mode must be down or up, got {v!r}")
            out[k] = v
            continue
        try:
            out[k] = float(v)
        except ValueError:
            raise PostError(source, line, f"{k}={v!r} is not a number") from None
    return out


def pass_index(motion) -> np.ndarray:
    """(T,) int: pass number of each sample (0, 1, ...), -1 for rapids. A pass is a run of feed samples."""
    motion = np.asarray(motion)
    feed = motion != 0
    start = feed & ~np.concatenate([[False], feed[:-1]])
    k = np.cumsum(start) - 1
    return np.where(feed, k, -1)


@dataclass
class ForceResult:
    """Cutting force along the run (cutting instances only).

    force_part : (I, 3) N, force of the workpiece on the tool, part frame.
    ap_mm : (I,) flute contact length.  ae_mm : (I,) mean radial engagement over the contact.
    z_contact_mm : (I,) centre of the contact above the tip.  passes : (I,) pass index.
    """

    force_part: np.ndarray
    ap_mm: np.ndarray
    ae_mm: np.ndarray
    z_contact_mm: np.ndarray
    passes: np.ndarray


def _force_tables(coeffs, d, z, mode, n_ae=256):
    """Mean force per mm of height in the feed frame over an ae grid: (grid (n,), A (n,3) N/mm per mm of fz, B (n,3))."""
    grid = np.linspace(0.0, d, n_ae)
    c1 = CuttingConditions(ap_mm=1.0, ae_mm=grid, fz_mm=1.0, tool_diameter_mm=d, flutes=int(z), helix_deg=0.0, mode=mode)
    c0 = CuttingConditions(ap_mm=1.0, ae_mm=grid, fz_mm=0.0, tool_diameter_mm=d, flutes=int(z), helix_deg=0.0, mode=mode)
    B = mean_force(coeffs, c0, n_angles=4096, n_slices=1)
    A = mean_force(coeffs, c1, n_angles=4096, n_slices=1) - B
    return grid, A, B


def cutting_forces(
    tips,
    axes,
    velocity,
    passes,
    conditions,
    machine,
    *,
    material=None,
    n_heights: int = 16,
    fine_height_mm: float = 2.0,
    fine_slices: int = 20,
    stride: int = 10,
    stock_search_mm: float = 1.0,
) -> ForceResult:
    """Force on the tool at every cutting instance, with the real engagement (see the module docstring).

    tips, axes : (I, 3) tool tips (mm) and unit axes, part frame, in time order (cutting instances only).
    velocity : (I, 3) mm/s, tool-tip velocity relative to the part (gives the feed direction).
    passes : (I,) int pass index (non-decreasing).
    conditions : list of I dicts (or one dict) with fz (mm), ae (mm, raw stock), mode, d, z (see structured_conditions).
    machine : gives the tool (radius, flute length) and the ``[cutting]`` coefficients.
    material : callable points (P, 3) -> (P,) bool, True where the raw part has material; None = everywhere.
    """
    if machine.cutting is None:
        raise ValueError(f"{machine.source}: the machine file has no [cutting] coefficients; forces need them")
    coeffs = CuttingCoefficients.from_mapping(machine.cutting)
    tips = np.asarray(tips, float)
    axes = np.asarray(axes, float)
    n = tips.shape[0]
    if isinstance(conditions, dict):
        conditions = [conditions] * n
    R = machine.tool.radius
    L = machine.tool.flute_length
    passes = np.asarray(passes, int)

    # Feed frame per instance.
    x = velocity - np.einsum("ij,ij->i", velocity, axes)[:, None] * axes
    norm = np.linalg.norm(x, axis=1)
    moving = norm > 1e-9
    # Hold the last feed direction through stops.
    idx = np.maximum.accumulate(np.where(moving, np.arange(n), 0))
    x = x[idx] / np.maximum(norm[idx], 1e-300)[:, None]
    y = np.cross(axes, x)

    # Instances evaluated: every stride-th of each pass, plus each pass' last.
    first_of_pass = np.r_[True, passes[1:] != passes[:-1]]
    last_of_pass = np.r_[passes[1:] != passes[:-1], True]
    pos_in_pass = np.arange(n) - np.maximum.accumulate(np.where(first_of_pass, np.arange(n), 0))
    ev = np.nonzero((pos_in_pass % max(1, stride) == 0) | last_of_pass)[0]

    fz = np.array([c.get("fz", np.nan) for c in conditions])
    ae_raw = np.array([c.get("ae", np.nan) for c in conditions])
    modes = np.array([c.get("mode", "down") for c in conditions])
    if np.any(~np.isfinite(fz[ev])):
        raise ValueError("cutting forces need fz (feed per tooth) in the program's (trueaxis: ...) comment")
    side = np.where(modes == "up", 1.0, -1.0)  # m = side * y

    fine = min(fine_height_mm, L)
    edges = np.unique(np.concatenate([np.linspace(0.0, fine, fine_slices + 1), np.linspace(fine, L, n_heights + 1)]))
    dz = np.diff(edges)
    zj = 0.5 * (edges[1:] + edges[:-1])
    n_heights = zj.size
    m_dir = side[ev, None] * y[ev]  # (E,3) towards the material
    contact = tips[ev, None, :] + zj[None, :, None] * axes[ev, None, :] + R * m_dir[:, None, :]  # (E,K,3)
    E = ev.size
    ae = np.full((E, n_heights), np.nan)
    # Stock left by the previous passes: envelope of their instances along -m at each contact point.
    for p in np.unique(passes[ev]):
        sel = passes[ev] == p
        prev = passes < p
        if not np.any(prev):
            continue
        pts = contact[sel].reshape(-1, 3)
        nrm = np.repeat(-m_dir[sel], n_heights, axis=0)
        res = envelope_deviation(pts, nrm, tips[prev], axes[prev], R, L, search_mm=stock_search_mm)
        ae[sel] = np.maximum(res.deviation_mm, 0.0).reshape(-1, n_heights)
    has_material = np.ones((E, n_heights), bool) if material is None else material(contact.reshape(-1, 3)).reshape(
        E, n_heights)
    ae = np.where(np.isnan(ae), ae_raw[ev, None], ae)
    ae = np.where(has_material, np.nan_to_num(ae), 0.0)
    ae = np.clip(ae, 0.0, 2 * R)

    force_ff = np.zeros((E, 3))
    for mode in np.unique(modes[ev]):
        d = np.array([conditions[i].get("d", 2 * R) for i in ev])
        zf = np.array([conditions[i].get("z", machine.tool.flutes) for i in ev])
        sel = modes[ev] == mode
        for dd, zz in {(float(a), float(b)) for a, b in zip(d[sel], zf[sel])}:
            s2 = sel & (d == dd) & (zf == zz)
            grid, A, B = _force_tables(coeffs, dd, zz, str(mode))
            a = ae[s2]  # (e, K)
            Aj = np.stack([np.interp(a, grid, A[:, c]) for c in range(3)], axis=-1)
            Bj = np.stack([np.interp(a, grid, B[:, c]) for c in range(3)], axis=-1)
            engaged = (a > 0)[..., None]
            force_ff[s2] = np.sum(dz[:, None] * engaged * (fz[ev][s2, None, None] * Aj + Bj), axis=1)
    engaged = ae > 0
    ap = (engaged * dz).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        z_c = np.where(ap > 0, (engaged * zj * dz).sum(axis=1) / np.maximum(ap, 1e-300), 0.0)
        ae_mean = np.where(ap > 0, (ae * engaged * dz).sum(axis=1) / np.maximum(ap, 1e-300), 0.0)
    f_part_ev = force_ff[:, :1] * x[ev] + force_ff[:, 1:2] * y[ev] + force_ff[:, 2:] * axes[ev]

    # Interpolate over the instance index within each pass (evaluated instances bracket every sample of their pass).
    out = np.zeros((n, 3))
    ap_all = np.zeros(n)
    ae_all = np.zeros(n)
    zc_all = np.zeros(n)
    i_all = np.arange(n)
    for p in np.unique(passes):
        sel = passes == p
        e = passes[ev] == p
        xs = ev[e]
        for c in range(3):
            out[sel, c] = np.interp(i_all[sel], xs, f_part_ev[e, c])
        ap_all[sel] = np.interp(i_all[sel], xs, ap[e])
        ae_all[sel] = np.interp(i_all[sel], xs, ae_mean[e])
        zc_all[sel] = np.interp(i_all[sel], xs, z_c[e])
    return ForceResult(out, ap_all, ae_all, zc_all, passes)
