"""Part programs of the two test parts (DESIGN §6): CL data in the part frame and machine-axis NC programs.

NAS 979 cone (``nas979_program``)
    5-axis simultaneous flank milling with a flat end mill on a five-axis machine (default: the B-C table of
    nmv1500dcg). The tool axis lies along the cone's generatrix and the tool's side touches the cone's offset surface
    (offset = the stock the pass leaves), tool tip at the base circle; the pass goes clockwise about the cone axis
    (down milling on an external surface) over 360 deg plus an overlap. A semi-finishing pass comes first when the
    stock is more than the finishing allowance. Each pass: rapid at a safe height, rapid down the tool axis to a
    clearance, plunge to the lead-in start, a tangential quarter-circle lead-in (in the plane of the cut direction
    and the surface normal, off the surface), the cut, the mirrored lead-out, rapid back up the tool axis.
``slot block`` (``slots_program``)
    Three identical slots (``SlotBlockParams``), full-width slotting in passes of ``axial_depth_per_pass`` along the
    tool-centre path; slot 1 posted with no compensation, slot 2 geometric, slot 3 comprehensive, each section posted
    on its own with ``trueaxis.postproc.post.compensate`` and the three concatenated into one program.

CL data: the one CL type ``trueaxis.nc.cl.ClData`` (``ClData.of_passes``): tool tip (mm) and unit tool axis in the
part frame, feed (mm/min; 0 = rapid), a kind per point (approach, plunge, lead_in, cut, lead_out, lift, retract) and
its pass; ``write_csv`` writes ``x,y,z,i,j,k,f``. The machine axes come from the one CL pipeline
``trueaxis.nc.cl.cl_axes`` (the CAM files' reader uses it too).

Programs are machine-axis G-code (X Y Z = tool tip with tool length compensation active; rotary words in degrees),
made with the machine's inverse kinematics. 5-axis moves use G93 (inverse time, F = feed / tip path length of the
block, 1/min). Cutting conditions are structured comments ``(trueaxis: ap=.. ae=.. fz=.. n=.. d=.. z=.. mode=down)``.
The header holds a setup comment that the virtual shop reads to place the part:
``(trueaxis-setup: part=nas979 origin_mm=X,Y,Z placement_mm=X,Y tool_d_mm=10 compensation=geometric twin=ID)``
(origin_mm: the part origin in M with all axes at zero; placement_mm: its offset from the C-axis line, or from the
machine zero on a machine without a C axis about Z; twin: ``twin_id`` of the twin that compensated it, absent when
uncompensated).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field

import numpy as np

from ..machine import Machine, forward_nominal
from ..nc.cl import ClData, cl_axes, machine_linear_positions  # noqa: F401  (re-exported)
from ..workpiece.nas979 import cone_title
from ..workpiece.parts import COMPENSATION_MODES, Nas979Params, SlotBlockParams

MODES = ("none", "geometric", "comprehensive")
SETUP_TAG = "trueaxis-setup"
_SETUP = re.compile(r"\(\s*trueaxis-setup:([^)]*)\)", re.IGNORECASE)


def _cone_frame(cone: dict):
    """Cone axis a and the basis (u, w) normal to it (u = part X projected), all unit, part frame."""
    a = np.asarray(cone["axis"], float)
    a = a / np.linalg.norm(a)
    ref = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ref - (ref @ a) * a
    u /= np.linalg.norm(u)
    return a, u, np.cross(a, u)


def cone_flank_poses(cone: dict, tool_radius: float, n_blocks: int, stock: float = 0.0, overlap_deg: float = 5.0,
                     start_deg: float = 0.0, theta_deg=None):
    """Tool tips (n+1, 3) mm and unit axes (n+1, 3) in the part frame for a flank pass around the cone, clockwise
    about the axis (down milling), tool axis along the generatrix, the tool's side at ``stock`` (mm) off the cone,
    tip at the base circle's height; ``n_blocks`` steps over 360 + overlap_deg from ``start_deg`` (about a, from u),
    or the angles ``theta_deg`` (increasing, deg of travel from the start) when given."""
    a, u, w = _cone_frame(cone)
    alpha = math.radians(cone["half_angle_deg"])
    rb = cone["base_radius"]
    c = np.asarray(cone.get("base_center", (0.0, 0.0, 0.0)), float)
    travel = np.linspace(0.0, 360.0 + overlap_deg, n_blocks + 1) if theta_deg is None else np.asarray(theta_deg, float)
    theta = -np.radians(start_deg + travel)
    radial = np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * w
    normal = math.cos(alpha) * radial + math.sin(alpha) * a
    g = math.cos(alpha) * a - math.sin(alpha) * radial  # generatrix direction, base towards top, unit
    return c + rb * radial + (tool_radius + stock) * normal, g


def _lead_arc(p0, t, n, radius, n_points, out: bool):
    """Quarter circle of ``radius`` (mm) in the plane (t, n) joining p0 tangentially: (n_points, 3) points.

    Lead-in (out=False): from p0 + r n - r t to p0, arriving along t. Lead-out (out=True): from p0 along t to
    p0 + r n + r t. The end at p0 is excluded."""
    phi = np.linspace(0.5 * math.pi, 0.0, n_points + 1)[:-1]
    if out:
        phi = phi[::-1]
        return p0 + radius * ((1 - np.cos(phi))[:, None] * n + np.sin(phi)[:, None] * t)
    return p0 + radius * ((1 - np.cos(phi))[:, None] * n - np.sin(phi)[:, None] * t)


def cone_flank_cl(cone: dict, tool_radius: float, *, stock_mm: float = 0.2, finish_mm: float = 0.1,
                  step_deg: float = 0.2, overlap_deg: float = 5.0, lead_radius: float | None = None,
                  lead_points: int = 10, clearance: float = 5.0, feed: float = 1000.0, plunge_feed: float = 300.0,
                  conditions: dict | None = None, theta_deg=None) -> ClData:
    """CL data of the cone flank milling: a semi-finishing pass leaving ``finish_mm`` when ``stock_mm`` exceeds it,
    then the finishing pass. Lengths in mm, angles in degrees, feeds in mm/min.

    conditions : fz, n, z, mode for the structured comment (ap and ae are computed: ap = generatrix length, ae =
    stock removed by the pass; d = 2 tool_radius).  theta_deg : angles of the cut poses (deg of travel about the
    axis, 0 .. 360 + overlap_deg), instead of the uniform ``step_deg``.
    """
    if not stock_mm > 0:
        raise ValueError(f"stock must be > 0 mm, got {stock_mm}")
    if not finish_mm > 0:
        raise ValueError(f"finishing allowance must be > 0 mm, got {finish_mm}")
    if not (0 < step_deg <= 5):
        raise ValueError(f"angle step must be in (0, 5] deg, got {step_deg}")
    lead_r = tool_radius if lead_radius is None else float(lead_radius)
    alpha = math.radians(cone["half_angle_deg"])
    h0, h1 = cone["height_range"]
    ap = (h1 - h0) / math.cos(alpha)
    a, _, _ = _cone_frame(cone)
    n_blocks = int(math.ceil((360.0 + overlap_deg) / step_deg))
    if stock_mm > finish_mm + 1e-9:
        plan = [("semi-finishing", finish_mm, stock_mm - finish_mm), ("finishing", 0.0, finish_mm)]
    else:
        plan = [("finishing", 0.0, stock_mm)]
    cond = {"fz": 0.05, "n": 5000.0, "z": 4, "mode": "down", **(conditions or {})}
    parts, passes = [], []
    for k, (name, offset, ae) in enumerate(plan):
        tip, g = cone_flank_poses(cone, tool_radius, n_blocks, offset, overlap_deg, theta_deg=theta_deg)
        # Cut direction t at the ends (unit tangent of the tip path), surface normal n = (tip - contact) direction.
        t0 = tip[1] - tip[0]
        t1 = tip[-1] - tip[-2]
        t0, t1 = t0 / np.linalg.norm(t0), t1 / np.linalg.norm(t1)
        a_, c_ = a, np.asarray(cone.get("base_center", (0.0, 0.0, 0.0)), float)

        def normal_at(p, gi):
            """Outward surface normal at a pose: (tip - axis point) made normal to g, unit."""
            v = p - c_
            v = v - (v @ a_) * a_
            v = v - (v @ gi) * gi
            return v / np.linalg.norm(v)

        nA, nB = normal_at(tip[0], g[0]), normal_at(tip[-1], g[-1])
        lead_in = _lead_arc(tip[0], t0, nA, lead_r, lead_points, out=False)
        lead_out = _lead_arc(tip[-1], t1, nB, lead_r, lead_points, out=True)
        approach = lead_in[0] + clearance * g[0]
        retract = lead_out[-1] + clearance * g[-1]
        pts = np.vstack([approach, lead_in, tip, lead_out, retract])
        axes = np.vstack([g[0], np.tile(g[0], (lead_points, 1)), g, np.tile(g[-1], (lead_points, 1)), g[-1]])
        kinds = (["approach"] + ["lead_in"] * lead_points + ["cut"] * len(tip) + ["lead_out"] * lead_points
                 + ["retract"])
        feeds = np.full(len(pts), feed)
        feeds[0] = 0.0
        feeds[1] = plunge_feed  # the lead-in start is reached by the plunge
        kinds[1] = "plunge"
        feeds[-1] = 0.0
        parts.append(ClData.of_passes(pts, axes, feeds, np.array(kinds), np.full(len(pts), k)))
        c = {"ap": round(ap, 3), "ae": round(ae, 4), **cond, "d": 2 * tool_radius}
        passes.append({"name": name, "offset_mm": offset, "ae_mm": ae, "conditions": c})
    return ClData.concatenate(parts, passes)


def slots_cl(params: SlotBlockParams | None = None, *, clearance: float = 2.0, feed: float = 1000.0,
             plunge_feed: float = 200.0, conditions: dict | None = None) -> tuple[ClData, list[int]]:
    """CL data of the three slots (tool axis +Z): per slot and pass, approach above the start, plunge to the pass
    depth, cut along the tool-centre path, lift out of the slot at the plunge feed (so the end of the slot is cut
    before any rapid). Returns (cl, slot index of each pass)."""
    p = params or SlotBlockParams()
    cond = {"fz": 0.05, "n": 5000.0, "z": 4, "mode": "down", **(conditions or {})}
    depths = p.pass_depths()
    parts, passes, slot_of = [], [], []
    z_axis = np.array([0.0, 0.0, 1.0])
    for s in range(len(COMPENSATION_MODES)):
        path = p.tool_centre_path(s)[:, :2]
        prev = 0.0
        for z in depths:
            k = len(passes)
            pts = np.vstack([[*path[0], clearance], [*path[0], z],
                             np.column_stack([path[1:], np.full(len(path) - 1, z)]), [*path[-1], clearance]])
            kinds = ["approach", "plunge"] + ["cut"] * (len(path) - 1) + ["lift"]
            feeds = np.r_[0.0, plunge_feed, np.full(len(path) - 1, feed), plunge_feed]
            parts.append(ClData.of_passes(pts, np.tile(z_axis, (len(pts), 1)), feeds, np.array(kinds), np.full(len(pts), k)))
            c = {"ap": round(prev - z, 4), "ae": p.tool_diameter, **cond, "d": p.tool_diameter}
            passes.append({"name": f"slot {s + 1} pass at z {z:g}", "offset_mm": 0.0, "conditions": c})
            slot_of.append(s)
            prev = z
    return ClData.concatenate(parts, passes), slot_of


# ----------------------------------------------------------------------------------------------- kinematics ----
def place_machine(machine: Machine, placement_mm=None) -> tuple[Machine, np.ndarray]:
    """The machine with its part origin moved to ``placement_mm`` = (x, y) mm off the C-axis line (off the machine
    zero without a C axis about Z); None keeps the machine file's origin. Returns (machine, placement (2,))."""
    base = np.zeros(2)
    c = machine.axes.get("C")
    if c is not None and c.is_rotary and abs(abs(np.asarray(c.direction) @ [0, 0, 1.0]) - 1) < 1e-12:
        base = np.asarray(c.pivot, float)[:2]
    origin = np.asarray(machine.workpiece_origin, float).copy()
    if placement_mm is None:
        return machine, origin[:2] - base
    pl = np.asarray(placement_mm, float).reshape(-1)
    if pl.shape != (2,) or not np.all(np.isfinite(pl)):
        raise ValueError(f"placement must be two finite numbers X,Y in mm, got {placement_mm!r}")
    origin[:2] = base + pl
    return dataclasses.replace(machine, workpiece_origin=origin), pl


def safe_height(machine: Machine, hull_points: np.ndarray, q_rot: np.ndarray, clearance: float = 10.0) -> float:
    """Machine Z (mm) at which the tool tip clears the part (``hull_points``, part frame, whose convex hull holds it)
    by ``clearance`` for every rotary position between those of ``q_rot`` (rad; C over a full turn when it moves).
    Raises ValueError when that lies above Z's travel."""
    names = machine.axis_names
    rot = [c for c, a in enumerate(names) if machine.axes[a].is_rotary]
    grids = []
    for c in rot:
        lo, hi = float(np.min(q_rot[:, c])), float(np.max(q_rot[:, c]))
        if names[c] == "C" or hi - lo > math.radians(300):
            grids.append(np.radians(np.arange(0.0, 360.0, 5.0)))
        else:
            grids.append(np.linspace(min(lo, 0.0), max(hi, 0.0), 16))
    q = np.zeros((1, len(names)))
    if rot:
        mesh = np.meshgrid(*grids, indexing="ij")
        q = np.zeros((mesh[0].size, len(names)))
        for c, m in zip(rot, mesh):
            q[:, c] = m.ravel()
    lin = machine_linear_positions(machine, q, hull_points)
    zi = [a for a in names if not machine.axes[a].is_rotary].index("Z")
    z = float(lin[:, :, zi].max()) + clearance
    tr = machine.axes["Z"].travel
    if tr is not None and z > tr[1]:
        raise ValueError(f"no safe height: the part reaches Z {z - clearance:.1f} mm (+{clearance:g} clearance) above "
                         f"Z's travel ({tr[1]:g} mm) at some rotary position; a placement moves the part in X and Y "
                         f"only: the part origin lower (the machine file's [workpiece] origin) or more Z travel is needed")
    if tr is not None:
        z = min(z + 10.0, tr[1] - 1.0) if z + 10.0 <= tr[1] - 1.0 else z
    return z


# ----------------------------------------------------------------------------------------------- G-code out ----
def _words(machine: Machine, row: np.ndarray) -> str:
    out = []
    for c, a in enumerate(machine.axis_names):
        v = math.degrees(row[c]) * machine.word_signs()[c] if machine.axes[a].is_rotary else row[c]
        out.append(f"{a}{v + 0.0:.6f}")
    return " ".join(out)


def conditions_comment(c: dict) -> str:
    """``(trueaxis: ap=.. ae=.. fz=.. n=.. d=.. z=.. mode=..)`` from a conditions dict."""
    return (f"(trueaxis: ap={c['ap']:g} ae={c['ae']:g} fz={c['fz']:g} n={c['n']:g} d={c['d']:g} z={int(c['z'])} "
            f"mode={c['mode']})")


def twin_id(machine: Machine) -> str:
    """A short id of a twin's error values (12 hex digits of the SHA-256 of its parameter names and values, bit for
    bit): the setup comment's ``twin``, so that an identification can tell which twin compensated a program."""
    import hashlib

    h = hashlib.sha256("\n".join(machine.parameter_names()).encode())
    h.update(np.ascontiguousarray(machine.parameter_values(), dtype="<f8").tobytes())
    return h.hexdigest()[:12]


def setup_comment(part: str, origin, placement, tool_d: float, compensation: str, twin: str | None = None) -> str:
    """``(trueaxis-setup: part=.. origin_mm=X,Y,Z placement_mm=X,Y tool_d_mm=.. compensation=.. twin=..)``; twin:
    ``twin_id`` of the twin that compensated the program (left out when None)."""
    o = ",".join(f"{v:.3f}" for v in origin)
    p = ",".join(f"{v:.3f}" for v in placement)
    t = f" twin={twin}" if twin else ""
    return (f"({SETUP_TAG}: part={part} origin_mm={o} placement_mm={p} tool_d_mm={tool_d:g} "
            f"compensation={compensation}{t})")


class ProgramError(ValueError):
    """A program refused as the input of a command that needs it to fit a twin and a part (exit 3, as a refused
    cloud): written for another part, moving axes the twin does not have, a malformed setup comment, or (the
    identification, the diagnosis) one that did not cut the measured part."""


def placed_for(machine: Machine, program_text: str, part: str | None = None) -> Machine:
    """The machine set up as the program's setup comment says, as the shop floor sets it up to run the program (the
    virtual shop, the diagnosis and the identification all take it from here): the part placed at ``origin_mm``,
    and the tool the program was made for in the spindle (``tool_d_mm``: a flat end mill of that diameter; the
    machine file's tool length, flutes and flute length stay, as the program's axis words assume that length). What
    the comment does not say stays the machine file's. Raises ProgramError for a program of another part (``part``
    given), a malformed origin or a tool diameter that is not a positive number, and a lathe (``refuse_lathe``)."""
    refuse_lathe(machine, part)
    setup = read_setup(program_text)
    if part is not None and setup.get("part") and setup["part"] != part:
        raise ProgramError(f"the program is for part {setup['part']!r}, not {part!r}")
    origin = setup.get("origin_mm")
    if origin is not None:
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise ProgramError("the program's setup comment origin_mm must be three numbers")
        if not np.allclose(origin, machine.workpiece_origin, atol=1e-9):
            machine = dataclasses.replace(machine, workpiece_origin=origin.astype(float))
    if "tool_d_mm" in setup:
        try:
            diameter = float(setup["tool_d_mm"])
        except ValueError:
            diameter = math.nan
        if not (math.isfinite(diameter) and diameter > 0):
            raise ProgramError(f"the program's setup comment tool_d_mm={setup['tool_d_mm']} is not a positive number")
        if not math.isclose(diameter, 2 * machine.tool.radius, rel_tol=0.0, abs_tol=1e-9):
            machine = dataclasses.replace(machine, tool=dataclasses.replace(machine.tool, radius=diameter / 2))
    return machine


# The least share of the measured (or probed) points a program must cut for its part to be read against its cut: a
# program that reaches a few per cent of them did not make that part (a lathe program reached 250 of 8000 cone
# points); a cloud may hold uncut surfaces besides (the stock's datum faces), so the bar is low.
MIN_CUT_SHARE = 0.1


def check_cut_share(n_cut: int, n_points: int, what: str = "measured points") -> None:
    """ProgramError when the program cut fewer than ``MIN_CUT_SHARE`` of ``n_points`` (or fewer than 10)."""
    if n_cut >= 10 and n_cut >= MIN_CUT_SHARE * n_points:
        return
    raise ProgramError(f"the program cuts only {n_cut} of the {n_points} {what} ({100 * n_cut / max(n_points, 1):.1f}"
                       f" %; at least {100 * MIN_CUT_SHARE:g} % and 10 points needed): is it the program that made "
                       f"this part, with this placement?")


def placement_assumed(program_text: str, machine: Machine) -> str | None:
    """What ``placed_for`` takes from the machine file because the program's setup comment does not say it (no
    comment, or one without ``origin_mm`` / ``tool_d_mm``): one sentence, said by the identification and the
    diagnosis alike (and added to a refusal, where a part placed elsewhere is the likely cause), or None when the
    program says both."""
    setup = read_setup(program_text)
    assumed = []
    if "origin_mm" not in setup:
        assumed.append("the part at the machine file's [workpiece] origin, "
                       f"{', '.join(f'{v:g}' for v in machine.workpiece_origin)} mm in M (placement 0)")
    if "tool_d_mm" not in setup:
        assumed.append(f"the machine file's tool, d {2 * machine.tool.radius:g} mm")
    if not assumed:
        return None
    missing = " or ".join(k for k in ("origin_mm", "tool_d_mm") if k not in setup)
    why = "the program has no trueaxis-setup comment" if not setup else f"the program's setup comment gives no {missing}"
    return f"{why}: assumed {' and '.join(assumed)}"


def refuse_lathe(machine: Machine, part: str | None) -> None:
    """ProgramError for a lathe: the test parts (the NAS 979 cone, the slot block) are milled with a flat end mill,
    which is all the virtual shop cuts, so a lathe cannot have cut a measured part and its twin is not simulated,
    identified or diagnosed from one (a lathe program on a cone cloud had been identified from the 3 % of points its
    passes happened to reach, and simulated for six minutes into 241 points)."""
    if machine.kind != "lathe":
        return
    what = f"the {part} part" if part else "the measured part"
    raise ProgramError(f"{machine.name} is a lathe: it cannot have cut {what} (the test parts are milled with a flat "
                       f"end mill): a lathe's twin is not simulated, identified or diagnosed from a measured part")


def check_part_against_program(part: str, part_json: dict, program_text: str, option: str = "--part-json") -> None:
    """ProgramError when the part's description (``option``'s, or the default part) is not the part the program cuts
    (a NAS 979 program names its cone in its title): another description would give the cut another surface and
    other normals, read as a machine error. Silent for a program that does not say."""
    from ..workpiece.part import get_part

    why = get_part(part).program_mismatch(part_json, program_text)
    if why:
        raise ProgramError(f"{why}: give the description `trueaxis part` wrote for it ({option})")


def check_axes(machine: Machine, program) -> None:
    """ProgramError when ``program`` (a parsed ``Program``) moves axes ``machine`` does not have (a program posted
    for another machine: the twin cannot cut it)."""
    unused = [a for a in program.axes_present if a not in machine.axis_names]
    if unused:
        raise ProgramError(f"{program.source}: the program moves axes {' '.join(unused)} that {machine.name} does "
                           f"not have: is it the program for this machine?")


def written_for(text: str) -> tuple[str, int] | None:
    """(the machine's name, 1-based line) the program's header says it was written for (``(machine: NAME)``, the
    name's parentheses as brackets, as ``part_program`` writes it), or None when it does not say."""
    m = re.search(r"^\(machine: (.*)\)\s*$", text[:20_000], re.MULTILINE)
    return None if m is None else (m.group(1).strip(), text.count("\n", 0, m.start()) + 1)


def header_name(machine: Machine) -> str:
    """The machine's name as a program header writes it (its parentheses as brackets)."""
    return machine.name.replace("(", "[").replace(")", "]").strip()


def compensated_already(text: str) -> tuple[str, int] | None:
    """("compensation=MODE[ twin=ID]", the setup comment's 1-based line) when the program's setup comment says
    ``trueaxis program`` compensated it (``compensation`` other than ``none``: a cone posted geometric or
    comprehensive, the slot block's ``per-slot``), else None (no setup comment, or compensation=none). Read item by
    item, so that a malformed item elsewhere in the comment does not hide what it says of the compensation."""
    m = _SETUP.search(text)
    if m is None:
        return None
    said = dict(item.partition("=")[::2] for item in m.group(1).split())
    mode = said.get("compensation", "none")
    if mode.lower() == "none":
        return None
    twin = f" twin={said['twin']}" if said.get("twin") else ""
    return f"compensation={mode}{twin}", text.count("\n", 0, m.start()) + 1


def read_setup(text: str) -> dict:
    """The setup comment of a program (first one): {"part", "origin_mm" (3,), "placement_mm" (2,), ...}; {} if none.
    Raises ValueError for a malformed one."""
    m = _SETUP.search(text)
    if not m:
        return {}
    out = {}
    for item in m.group(1).split():
        k, sep, v = item.partition("=")
        if not sep:
            raise ValueError(f"setup comment: expected key=value, got {item!r}")
        if k in ("origin_mm", "placement_mm"):
            try:
                out[k] = np.array([float(s) for s in v.split(",")])
            except ValueError:
                raise ValueError(f"setup comment: {k}={v!r} is not numbers") from None
        else:
            out[k] = v
    return out


def _pass_blocks(machine: Machine, cl: ClData, q: np.ndarray, sel: np.ndarray, safe_z: float) -> list[str]:
    """G-code of one pass (rows ``sel`` of the CL data): rapids at safe Z, approach, plunge, feed moves, retract."""
    names = machine.axis_names
    zc = names.index("Z")
    five = machine.is_five_axis
    up = lambda row: np.r_[row[:zc], safe_z, row[zc + 1:]]  # noqa: E731  (tool axis = machine Z on these layouts)
    lines = [f"G0 {_words(machine, up(q[sel[0]]))}"]
    out_feed = "G94"
    for i in sel:
        kind = cl.kind[i]
        if kind in ("approach", "retract", "plunge", "lift"):
            # in units per minute: a lift after a five-axis pass's G93 moves was read as an inverse time (F200 lifts
            # at 520-1000 mm/min, rs274's reading; a QA pass)
            if out_feed != "G94":
                lines.append("G94")
                out_feed = "G94"
            if kind in ("approach", "retract"):
                lines.append(f"G0 {_words(machine, q[i])}")
            else:
                lines.append(f"G1 {_words(machine, q[i])} F{cl.feed[i]:.1f}")
        else:
            if five:
                if out_feed != "G93":
                    lines.append("G93")
                    out_feed = "G93"
                seg = float(np.linalg.norm(cl.tip[i] - cl.tip[i - 1]))
                lines.append(f"G1 {_words(machine, q[i])} F{cl.feed[i] / max(seg, 1e-6):.4f}")
            else:
                lines.append(f"G1 {_words(machine, q[i])} F{cl.feed[i]:.1f}")
    if out_feed != "G94":
        lines.append("G94")
    lines.append(f"G0 {_words(machine, up(q[sel[-1]]))}")
    return lines


@dataclass
class PartProgram:
    """A generated program: ``text`` (posted), ``raw`` (before compensation), ``cl`` (CL data), ``q`` (N, n_axes)
    machine axes of the CL points (mm, rad), ``machine`` (with the placement applied), ``safe_z`` (mm), ``info``."""

    text: str
    raw: str
    cl: ClData
    q: np.ndarray
    machine: Machine
    safe_z: float
    info: dict = field(default_factory=dict)


def _header(title: list[str], machine: Machine, setup: str, n_rpm: float) -> list[str]:
    """The program's head: title, machine, the virtual shop's setup comment, the setup the program expects (stated,
    and made by the program itself: G54 set to the machine zero by G10 L2 P1, no tool length offset), units and
    modes, the tool change and the spindle."""
    zero = " ".join(f"{a}0" for a in machine.axis_names)
    return (["%"] + [f"({t})" for t in title] +
            [f"(machine: {header_name(machine)})", setup,
             "(X Y Z: tool tip in machine coordinates, the twin's axes with the machine file's tool of length "
             f"{machine.tool.length:g} mm; rotary axes in degrees)",
             "(setup expected: work offset G54 = machine zero [set below by G10 L2 P1], no G92 shift, no tool "
             "length offset [G49]: post it without a setup)",
             "G21 G90 G17 G94 G40 G49", f"G10 L2 P1 {zero}", "G54", "T1 M6", f"S{n_rpm:g} M3"])


def _footer() -> list[str]:
    return ["M5", "M30", "%"]


def refine_cone_steps(machine: Machine, cone: dict, tool_radius: float, offsets, *, step_deg: float = 0.2,
                      overlap_deg: float = 5.0, tol_um: float = 0.05, max_blocks: int = 40_000):
    """Angles (deg of travel) of the cut poses so that the linear interpolation of the machine axes between blocks
    leaves the tool's side off the cone's offset surface by at most ``tol_um`` (um) at mid-block, checked at the tip
    and at the top of the cone along the tool, for every offset (mm) in ``offsets``. Starts from ``step_deg`` and
    splits each block by sqrt(error / tol) (the mid-chord error is quadratic in the step).
    Returns (theta_deg (n+1,), max error um after refinement)."""
    from ..workpiece.parts import cone_signed_distance

    theta = np.linspace(0.0, 360.0 + overlap_deg, int(math.ceil((360.0 + overlap_deg) / step_deg)) + 1)
    h1 = cone["height_range"][1]
    ap = h1 / math.cos(math.radians(cone["half_angle_deg"]))
    err = np.zeros(1)
    for _ in range(3):
        err = np.zeros(len(theta) - 1)
        for off in offsets:
            tip, g = cone_flank_poses(cone, tool_radius, 0, off, overlap_deg, theta_deg=theta)
            cl = ClData.of_passes(tip, g, np.ones(len(tip)), np.array(["cut"] * len(tip)), np.zeros(len(tip), int))
            q, _ = cl_axes(cl, machine, branch="first-fit")
            tm, um = forward_nominal(machine, 0.5 * (q[:-1] + q[1:]))
            for lever in (0.0, ap):
                d = cone_signed_distance(tm + lever * um, cone) - (tool_radius + off)
                err = np.maximum(err, np.abs(d) * 1e3)
        split = np.ceil(np.sqrt(np.maximum(err, 1e-30) / tol_um)).astype(int)
        if np.all(split <= 1):
            break
        split = np.maximum(split, 1)
        if split.sum() > max_blocks:
            raise ValueError(f"the cone needs more than {max_blocks} blocks per pass for a {tol_um:g} um chord "
                             "tolerance on this machine and placement")
        frac = [np.arange(m) / m for m in split]
        theta = np.r_[np.concatenate([t0 + f * (t1 - t0) for t0, t1, f in zip(theta[:-1], theta[1:], frac)]),
                      theta[-1]]
    return theta, float(err.max())


def nas979_program(machine: Machine, params: Nas979Params | None = None, *, compensation: str = "geometric",
                   tool_diameter: float = 10.0, stock_um: float = 200.0, finish_um: float = 100.0,
                   placement_mm=None, step_deg: float = 1.0, chord_tol_um: float | None = 0.05, fz: float = 0.05,
                   n_rpm: float = 5000.0, post: bool = True, post_options: dict | None = None) -> PartProgram:
    """NC program of the NAS 979 cone flank milling (see the module docstring) on a five-axis ``machine``.

    tool_diameter (mm), stock_um / finish_um (radial stock before the flank milling / allowance of the finishing pass,
    um), placement_mm (x, y) off the C-axis line (None: the machine file's part origin), step_deg: angle about the cone
    axis between blocks, refined where the machine's rotary axes turn fast until the interpolated tool leaves the
    offset surface by at most chord_tol_um (um; None: uniform step_deg), fz (mm) and n_rpm: cutting conditions
    (feed = fz z n). compensation: none | geometric |
    comprehensive, applied with ``trueaxis.postproc.post.compensate``. post : False: the raw program, as with
    compensation "none" (the keyword every part's program takes).
    """
    if compensation not in MODES:
        raise ValueError(f"compensation must be one of {', '.join(MODES)}, got {compensation!r}")
    if not post:
        compensation = "none"
    if not machine.is_five_axis:
        raise ValueError(f"the NAS 979 cone needs a five-axis machine; {machine.name} has axes "
                         f"{' '.join(machine.axis_names)}")
    if not tool_diameter > 0:
        raise ValueError(f"tool diameter must be > 0 mm, got {tool_diameter}")
    p = params or Nas979Params()
    cone = p.cone_surface()
    placed, placement = place_machine(machine, placement_mm)
    z_fl = machine.tool.flutes
    feed = fz * z_fl * n_rpm
    offsets = [0.0] + ([finish_um * 1e-3] if stock_um > finish_um + 1e-6 else [])
    theta, chord_um = ((None, None) if chord_tol_um is None else
                       refine_cone_steps(placed, cone, tool_diameter / 2, offsets, step_deg=step_deg, tol_um=chord_tol_um))
    cl = cone_flank_cl(cone, tool_diameter / 2, stock_mm=stock_um * 1e-3, finish_mm=finish_um * 1e-3,
                       step_deg=step_deg, feed=feed, plunge_feed=feed * 0.3,
                       conditions={"fz": fz, "n": n_rpm, "z": z_fl, "mode": "down"}, theta_deg=theta)
    generatrix = (cone["height_range"][1] - cone["height_range"][0]) / math.cos(math.radians(p.half_angle_deg))
    if generatrix > machine.tool.flute_length:
        raise ValueError(f"the cone's generatrix ({generatrix:.2f} mm) is longer than the tool's flutes "
                         f"({machine.tool.flute_length:g} mm)")
    q, _ = cl_axes(cl, placed, branch="first-fit")
    safe_z = safe_height(placed, _nas979_hull(p), q)
    setup = setup_comment("nas979", placed.workpiece_origin, placement, tool_diameter, compensation,
                          twin_id(machine) if compensation != "none" else None)
    title = [f"trueaxis NAS 979 cone frustum: 5-axis flank milling, flat end mill d {tool_diameter:g} mm",
             cone_title(p),
             f"stock {stock_um:g} um; " + "; ".join(f"{ps['name']} pass leaves {ps['offset_mm'] * 1e3:g} um"
                                                   for ps in cl.passes),
             f"placement X{placement[0]:g} Y{placement[1]:g} mm off the C axis; part origin in M "
             f"{' '.join(f'{v:g}' for v in placed.workpiece_origin)} mm; safe Z {safe_z:.3f} mm",
             f"compensation: {compensation}"]
    lines = _header(title, placed, setup, n_rpm)
    for k, ps in enumerate(cl.passes):
        sel = np.nonzero(cl.pass_no == k)[0]
        lines.append(f"(pass {k + 1} of {len(cl.passes)}: {ps['name']}, leaves {ps['offset_mm'] * 1e3:g} um)")
        lines.append(conditions_comment(ps["conditions"]))
        lines += _pass_blocks(placed, cl, q, sel, safe_z)
    lines += _footer()
    raw = "\n".join(lines) + "\n"
    text = raw
    report = {}
    if compensation != "none":
        from .post import compensate

        # force: the raw program's setup comment already names the compensation it is being posted with
        # (source: the program the post reads, the one generated here; line numbers are that program's)
        text = compensate(raw, placed, compensation, source="nas979[as generated, before the post]",
                          report=report, **{**(post_options or {}), "force": True})
    return PartProgram(text, raw, cl, q, placed, safe_z,
                       {"placement_mm": placement.tolist(), "feed_mm_min": feed, "passes": cl.passes,
                        "chord_error_um": chord_um, "cut_blocks_per_pass": int((cl.kind == "cut").sum()) // len(cl.passes),
                        "post_report": report, "summary": ", ".join(ps["name"] for ps in cl.passes)})


def _nas979_hull(p: Nas979Params) -> np.ndarray:
    """Points (part frame, mm) whose convex hull holds the part: the wedge's 8 corners and the top circle."""
    t = math.radians(p.axis_inclination_deg)
    hl, hw = p.block_length_x / 2, p.block_width_y / 2
    corners = np.array([[x, y, z] for x in (-hl, hl) for y in (-hw, hw) for z in (p.z_bottom, -x * math.tan(t))])
    a, u, w = _cone_frame(p.cone_surface())
    th = np.radians(np.arange(0, 360, 5.0))
    ring = p.height * a + p.top_radius / math.cos(math.radians(2.5)) * (np.cos(th)[:, None] * u + np.sin(th)[:, None] * w)
    return np.vstack([corners, ring])


def slots_program(machine: Machine, params: SlotBlockParams | None = None, *, post: bool = True, placement_mm=None,
                  fz: float = 0.05, n_rpm: float = 5000.0, clearance: float = 2.0,
                  post_options: dict | None = None) -> PartProgram:
    """NC program of the slot block (see the module docstring): slot k posted with mode COMPENSATION_MODES[k].

    post : False: no slot posted (``text`` is ``raw``). placement_mm (x, y): part origin off the C-axis line / machine zero (None: the machine file's origin).
    Sections are marked ``(slot k of 3: compensation MODE)`` ... ``(end of slot k)``."""
    from .post import compensate

    linear = [a for a in machine.axis_names if not machine.axes[a].is_rotary]
    if machine.kind != "mill" or not {"X", "Y", "Z"} <= set(linear):
        raise ValueError(f"the slot block needs a three-axis mill (X Y Z; a five-axis mill does too); {machine.name} "
                         f"is a {machine.kind} with axes {' '.join(machine.axis_names)}")
    p = params or SlotBlockParams()
    placed, placement = place_machine(machine, placement_mm)
    z_fl = machine.tool.flutes
    feed = fz * z_fl * n_rpm
    cl, slot_of = slots_cl(p, clearance=clearance, feed=feed, plunge_feed=feed * 0.2,
                           conditions={"fz": fz, "n": n_rpm, "z": z_fl, "mode": "down"})
    q, _ = cl_axes(cl, placed, branch="first-fit")
    hull = np.array([[x, y, z] for x in (0, p.block_length_x) for y in (0, p.block_width_y)
                     for z in (-p.block_height_z, 0.0)])
    safe_z = safe_height(placed, hull, q, clearance=10.0)
    # post=False: no slot is compensated, and the setup comment says so (a post of the raw program is not refused)
    setup = setup_comment("slots", placed.workpiece_origin, placement, p.tool_diameter, "per-slot" if post else "none",
                          twin_id(machine) if post else None)
    title = [f"trueaxis slot block: three slots, flat end mill d {p.tool_diameter:g} mm, depth {p.slot_depth:g} mm "
             f"in passes of {p.axial_depth_per_pass:g} mm",
             "slot 1: no compensation, slot 2: geometric, slot 3: comprehensive; each section posted on its own",
             f"placement X{placement[0]:g} Y{placement[1]:g} mm; part origin in M "
             f"{' '.join(f'{v:g}' for v in placed.workpiece_origin)} mm; safe Z {safe_z:.3f} mm"]
    header = _header(title, placed, setup, n_rpm)
    head_text = "\n".join(header) + "\n"
    raw_sections, posted, reports = [], [], []
    slot_of = np.asarray(slot_of)
    for s, mode in enumerate(COMPENSATION_MODES):
        sec = [f"(slot {s + 1} of 3: compensation {mode})"]
        last = None
        for k in np.nonzero(slot_of == s)[0]:
            c = cl.passes[k]["conditions"]
            if c != last:
                sec.append(conditions_comment(c))
                last = c
            sec += _pass_blocks(placed, cl, q, np.nonzero(cl.pass_no == k)[0], safe_z)
        sec.append(f"(end of slot {s + 1})")
        sec_text = "\n".join(sec) + "\n"
        raw_sections.append(sec_text)
        if not post:
            posted.append(sec_text)
            continue
        rep = {}
        # force: the head's setup comment already says compensation=per-slot, of the program these sections make
        out = compensate(head_text + sec_text, placed, mode,
                         source=f"slots[slot {s + 1} as generated, before the post]", report=rep, header=False,
                         **{**(post_options or {}), "force": True})
        if not out.startswith(head_text):
            raise RuntimeError("the post changed the program header; cannot splice the slot sections")
        posted.append(out[len(head_text):])
        reports.append(rep)
    tail = "\n".join(_footer()) + "\n"
    raw = head_text + "".join(raw_sections) + tail
    text = head_text + "".join(posted) + tail
    return PartProgram(text, raw, cl, q, placed, safe_z,
                       {"placement_mm": placement.tolist(), "feed_mm_min": feed, "passes": cl.passes,
                        "sections_raw": raw_sections, "sections": posted, "post_reports": reports,
                        "summary": f"{len(cl.passes)} passes in 3 slots (none, geometric, comprehensive)"})


# A part's name -> the function making its NC program for a machine: f(machine, params, *, post, placement_mm, ...)
# -> PartProgram; post=False gives the raw program (a new part adds its entry here beside its module in trueaxis.workpiece).
PROGRAMS = {"nas979": nas979_program, "slots": slots_program}


def part_program(part: str, machine: Machine, params=None, **options) -> PartProgram:
    """The NC program of the part called ``part`` on ``machine`` (``PROGRAMS``); options: the function's keywords."""
    if part not in PROGRAMS:
        raise ValueError(f"no NC program for part {part!r}; programs exist for {', '.join(PROGRAMS)}")
    return PROGRAMS[part](machine, params, **options)


# A program compensated by another twin than the one given is legitimate (the model is the twin at the axes the program
# commands), and the usual mix-up of a closed loop: another round's program fitted the part better than the right one
# and was accepted with twice the true errors (QA pass). Said on stderr, not only in the notes.
OTHER_TWIN_WARNING = ("the program was compensated by another twin than the one given: make sure it is the program "
                      "that cut this part (not another round's); a wrong program's changes are wrong however well "
                      "they fit")


def program_compensation(program_text: str, twin: Machine) -> dict:
    """What the program says about its compensation (its ``trueaxis-setup`` comment: ``compensation`` and ``twin``,
    the twin's id, ``trueaxis.postproc.programs.twin_id``), compared with ``twin``. The identification does not
    depend on it (its model is the twin at the axes the program commands, whoever compensated them); the note says
    what was read or assumed (the diagnosis says it too: its twin's cut is the same model). Returns {"mode",
    "twin_id", "same_twin" (bool or None), "note"}, and "warning" (``OTHER_TWIN_WARNING``) where another twin did."""
    from .post import machine_fingerprint, read_post_header

    posted = read_post_header(program_text)
    if posted is not None:  # a trueaxis post wrote it: its header says the mode and the machine file it used
        mine = machine_fingerprint(twin).rsplit(" ", 1)[-1]
        same = None if posted["sha256"] is None else posted["sha256"] == mine
        by = {True: f"this twin (its post header: machine file sha256 {mine})",
              False: f"another twin (its post header: machine file sha256 {posted['sha256']}, this one's is {mine})",
              None: "a trueaxis post whose header names no machine file"}[same]
        return {"mode": posted["mode"], "twin_id": posted["sha256"], "same_twin": same, "posted": True,
                "note": f"compensation={posted['mode']} by {by}; a setup comment it carries is the program's before "
                        "the post; the model is the twin at the axes the program commands",
                **({"warning": OTHER_TWIN_WARNING} if same is False else {})}
    setup = read_setup(program_text)
    mode, tid = setup.get("compensation"), setup.get("twin")
    mine = twin_id(twin)
    if not setup:
        note = ("the program has no trueaxis-setup comment: assumed its axis words are the axes commanded at the cut "
                "(compensated or not, by whoever); the model is the twin at those axes")
    elif mode == "none":
        note = ("the program's setup comment says compensation=none (a post run on it afterwards would not show "
                "there); the model is the twin at the axes the program commands, compensated or not")
    elif tid is None:
        note = (f"the program says compensation={mode or 'unknown'} but not by which twin: assumed its axis words "
                "are the axes commanded at the cut; the model is the twin at those axes")
    elif tid == mine:
        note = f"compensation={mode} by this twin ({tid}); the model is the twin at the commanded axes"
    else:
        note = (f"compensation={mode} by another twin ({tid}, this one is {mine}); the model is this twin at the "
                "axes the program commands")
    same = None if tid is None else tid == mine
    return {"mode": mode, "twin_id": tid, "same_twin": same, "note": note,
            **({"warning": OTHER_TWIN_WARNING} if same is False else {})}
