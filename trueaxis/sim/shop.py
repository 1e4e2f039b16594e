"""The virtual shop: machine a program on a *true* machine and measure the part on a virtual CMM (DESIGN §8).

    result = simulate("cone.ngc", load_machine("true.toml"), effects=load_effects("EFFECTS.toml"), part="nas979")
    write_cmm(result, "cmm.ply")          # cmm.ply (part frame, x y z nx ny nz) + cmm.truth.json (tests only)

Pipeline, per sample of the 1 ms interpolation (``trajectory``):
commanded axes -> axis effects (servo loops, backlash, rotary harmonics) -> the twin's actual pose (geometric errors,
``ErrorTwin.actual_pose``; with the cutting force when the effects ask for the machine's own compliance) and the
rotary axes' error motions in their places in the chain -> pose effects (force and tool deflection from the cutting
force with the real engagement, thermal drift) -> tool wear (radius and length along the cut path) ->
the machined surface as the envelope of the cutting instances (``envelope``) along each probe normal, with the part's
spring-back from its clamping deformation -> probe noise.

``simulate_program_file`` does the same for a program file whose setup comment places the part and names the tool it
was made for (``trueaxis simulate`` in ``trueaxis.cli``).
"""

from __future__ import annotations

import dataclasses

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..machine import ErrorTwin, Machine
from ..nc.gcode import Program, parse_program
from . import cmm as _cmm
from .cutting import cutting_forces, pass_index, structured_conditions
from ..machine.kinematics import machine_to_part_rotation
from .effects import Effects, load_effects
from .envelope import envelope_deviation, thin_instances
from ..nc.trajectory import Trajectory, interpolate
from ..workpiece.part import load_part, part_of  # noqa: F401  (load_part: the shop's callers read it here)

CHUNK = 20_000


@dataclass
class SimResult:
    """A simulated part and its measurement.

    points, normals : (N, 3) nominal probe points (mm) and unit outward normals, part frame.
    deviations_um : (N,) simulated deviation s* along the normal (positive = material left), um; NaN where not cut.
    measured : (N, 3) mm, measured points (s* plus probe noise along the normal); NaN rows where not cut.
    noise_um : (N,) the probe noise drawn, um.
    cut_time_s : (N,) program time at which the deepest cut at each point was made; NaN where not cut.
    sample : (N,) int, trajectory sample of that cut (-1 where not cut).
    block_line : (N,) int, 1-based source line of the block that cut the point (0 where not cut).
    axes_actual : (N, n_axes) actual axis positions at the cut (mm, rad); axes_commanded likewise.
    force_n : (N, 3) cutting force on the tool at the cut, part frame, N (zeros without force effects).
    trajectory : the commanded Trajectory.  machine, effects, part (JSON dict), timings (s), info (dict).
    """

    points: np.ndarray
    normals: np.ndarray
    deviations_um: np.ndarray
    measured: np.ndarray
    noise_um: np.ndarray
    cut_time_s: np.ndarray
    sample: np.ndarray
    block_line: np.ndarray
    axes_actual: np.ndarray
    axes_commanded: np.ndarray
    force_n: np.ndarray
    trajectory: Trajectory
    machine: Machine
    effects: Effects
    part: dict
    noise_sigma_um: float
    seed: int
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


def material_mask(part: dict):
    """Callable points (P, 3) -> bool: where the raw part has material, for the engagement of the first cut."""
    return part_of(part).material_mask(part)


def _pose_chunked(twin, q, force=None):
    n = q.shape[0]
    tip, u = np.empty((n, 3)), np.empty((n, 3))
    for s in range(0, n, CHUNK):
        sl = slice(s, min(n, s + CHUNK))
        tip[sl], u[sl] = twin.actual_pose(q[sl], force_n=None if force is None else force[sl])
    return tip, u


def simulate(
    program,
    machine: Machine,
    effects: Effects | None = None,
    part: str = "nas979",
    part_json=None,
    part_dir=None,
    points: int = 200_000,
    noise_um: float = 0.0,
    seed: int = 0,
    dt: float = 1e-3,
    *,
    probe=None,
    rapid_mm_min: float = 10_000.0,
    search_mm="auto",
    thin_tol_um: float = 0.01,
    force_stride: int = 10,
    progress: bool = False,
) -> SimResult:
    """Machine ``program`` on ``machine`` (the true machine: twin parameters) with ``effects`` and measure it.

    program : G-code text, a path to it, or a parsed ``Program`` (machine-axis program, see ``trajectory``).
    machine : the true machine.  effects : ``Effects`` (None = none).
    part : "nas979" | "slots"; part_json : path or dict of the part JSON; part_dir : folder holding <part>.json
        (default: the generator's default parameters).
    points : number of probe points (about; the pattern rounds).  noise_um : probe noise sigma, um.  seed : noise seed.
    dt : interpolation period, s.  probe : optional (points (N,3), normals (N,3)) instead of the part's pattern.
    search_mm : window of the envelope along each normal, mm, or "auto" (see ``envelope_deviation``).
    thin_tol_um : largest change of the envelope allowed when thinning instances along straight motion (0 = none).
    force_stride : the force (and engagement) is evaluated every force_stride samples and interpolated.
    """
    timings = {}
    t0 = time.perf_counter()
    effects = effects or Effects()
    if isinstance(program, Program):
        prog = program
    else:
        text, source = program, "<string>"
        if isinstance(program, Path) or (isinstance(program, str) and "\n" not in program and Path(program).is_file()):
            source = str(program)
            text = Path(program).read_text(encoding="utf-8", errors="replace")
        prog = parse_program(text, source)
    part_data = load_part(part, part_json, part_dir) if probe is None or part_json is not None else {"part": part}
    # The in-position hold after each rapid: 0.2 s, or longer if the servo loop needs it to plan the rapid within its
    # acceleration limits and settle (``ServoLag.settle_time``), so that no rapid's lag is carried into the cut.
    settle = 0.2 if effects.servo is None else max(0.2, effects.servo.settle_time(machine, rapid_mm_min))
    traj = interpolate(prog, machine, dt, rapid_mm_min=rapid_mm_min, rapid_settle_s=settle)
    timings["interpolate_s"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    info = {}  # (what the run chose and found, for the truth file)
    q_act = effects.apply_axes(traj.q, machine, dt, traj=traj, info=info)
    twin = ErrorTwin(machine)

    def geometric_pose(q, force=None):
        """The twin's pose, then the rotary axes' error motions in their places in the chain."""
        p, v = _pose_chunked(twin, q, force)
        for motion in effects.rotary_error_motion:
            p, v = motion.apply_pose(p, v, q, machine)
        return p, v

    tip, u = geometric_pose(q_act)
    cutting = traj.motion != 0
    ci = np.nonzero(cutting)[0]
    force_part = np.zeros((len(traj), 3))
    info.update(samples=len(traj), cutting_samples=int(ci.size))
    notes = [n for n in (unapplied_force_note(machine, effects), _idle_effects_note(machine, effects)) if n]
    if notes:
        info["notes"] = notes
    if effects.needs_force and ci.size:
        conds_by_line = structured_conditions(prog, machine)
        conds = [conds_by_line[i] for i in traj.line[ci]]
        vel = np.gradient(tip[ci], traj.t[ci], axis=0) if ci.size > 1 else np.zeros((ci.size, 3))
        fr = cutting_forces(tip[ci], u[ci], vel, pass_index(traj.motion)[ci], conds, machine,
                            material=material_mask(part_data) if "surfaces" in part_data else None,
                            stride=force_stride)
        force_part[ci] = fr.force_part
        R = machine_to_part_rotation(machine, q_act[ci])
        f_machine = np.einsum("nji,nj->ni", R, fr.force_part)  # R^T F: part frame -> machine frame
        if effects.force is not None and effects.force.use_machine_compliance:
            tip[ci], u[ci] = geometric_pose(q_act[ci], f_machine)
        if effects.force is not None and effects.force.compliance_um_per_n is not None:
            d_m = f_machine @ np.asarray(effects.force.compliance_um_per_n).T * 1e-3
            tip[ci] += np.einsum("nij,nj->ni", R, d_m)
        if effects.tool_deflection is not None:
            tip[ci], u[ci] = effects.tool_deflection.displace(tip[ci], u[ci], fr.force_part, fr.z_contact_mm,
                                                              2 * machine.tool.radius)
        info.update(ap_mean_mm=float(fr.ap_mm.mean()), ae_mean_mm=float(fr.ae_mm.mean()),
                    force_max_n=float(np.linalg.norm(fr.force_part, axis=1).max()),
                    ae_by_pass_mm=[float(fr.ae_mm[fr.passes == p].mean()) for p in np.unique(fr.passes)],
                    ap_by_pass_mm=[float(fr.ap_mm[fr.passes == p].mean()) for p in np.unique(fr.passes)])
    if effects.thermal is not None:
        R = machine_to_part_rotation(machine, q_act)
        tip += np.einsum("nij,nj->ni", R, effects.thermal.drift_um(traj.t) * 1e-3)
    R_tool, L_tool = machine.tool.radius, machine.tool.flute_length
    radius = None
    if effects.tool_wear is not None:
        path = effects.tool_wear.cut_path_mm(tip, cutting)
        dr, dl = effects.tool_wear.losses_mm(path)
        if np.any(dr >= R_tool):
            raise ValueError(f"tool wear: the radius loss reaches {dr.max():.3f} mm, the whole tool radius")
        radius = R_tool - dr
        tip = tip + dl[:, None] * u
        info["tool_wear"] = {"cut_path_mm": float(path[-1]), "radius_loss_um": float(dr[-1] * 1e3),
                             "length_loss_um": float(dl[-1] * 1e3)}
    timings["poses_s"] = time.perf_counter() - t1

    # Cutting instances, thinned along straight steady motion.
    t2 = time.perf_counter()
    breaks = np.r_[True, traj.row[ci][1:] != traj.row[ci][:-1]] if ci.size else None
    keep = (thin_instances(tip[ci], u[ci], R_tool, L_tool, thin_tol_um * 1e-3, breaks=breaks)
            if thin_tol_um > 0 and ci.size else np.ones(ci.size, bool))
    inst = ci[keep]
    info["instances"] = int(inst.size)
    if probe is None:
        pts, nrm = _cmm.probe_pattern(part_data, points)
    else:
        pts, nrm = (np.asarray(a, float) for a in probe)
    # Clamping: the part is cut deformed and springs back when released. The material point z (released) sat at
    # z + d(z) while cut, so the released surface meets the probe line p + s n where the clamped (cut) surface meets
    # the line through p + d_t(p) (d's tangential part) at s + d_n(p): the envelope is taken on the shifted probe
    # points and d_n is subtracted. Exact to first order in the field's gradient times the deviation (not in the
    # gradient times the tool radius, as moving the tool by d(tip) would be).
    pts_env, d_n = pts, 0.0
    if effects.clamping is not None:
        d_clamp, _ = effects.clamping.field(pts)
        d_n = np.einsum("ij,ij->i", d_clamp, nrm)
        pts_env = pts + d_clamp - d_n[:, None] * nrm
    env = envelope_deviation(pts_env, nrm, tip[inst], u[inst], R_tool if radius is None else radius[inst], L_tool,
                             search_mm=search_mm, progress=progress)
    env.deviation_mm = env.deviation_mm - d_n
    timings["envelope_s"] = time.perf_counter() - t2
    info["pairs"] = env.n_pairs
    info["points"] = int(pts.shape[0])
    info["not_cut"] = int(np.isnan(env.deviation_mm).sum())

    dev_um = env.deviation_um
    cut = env.instance >= 0
    sample = np.where(cut, inst[np.maximum(env.instance, 0)], -1)
    measured, noise = _cmm.measure(pts, nrm, np.nan_to_num(dev_um), noise_um, seed)
    measured[~cut] = np.nan
    s = np.maximum(sample, 0)
    nan_rows = lambda a: np.where(cut[:, None], a, np.nan)  # noqa: E731
    timings["total_s"] = time.perf_counter() - t0
    return SimResult(
        points=pts,
        normals=nrm,
        deviations_um=dev_um,
        measured=measured,
        noise_um=noise,
        cut_time_s=np.where(cut, traj.t[s], np.nan),
        sample=sample,
        block_line=np.where(cut, traj.line[s] + 1, 0),
        axes_actual=nan_rows(q_act[s]),
        axes_commanded=nan_rows(traj.q[s]),
        force_n=np.where(cut[:, None], force_part[s], 0.0),
        trajectory=traj,
        machine=machine,
        effects=effects,
        part=part_data,
        noise_sigma_um=float(noise_um),
        seed=int(seed),
        timings=timings,
        info=info,
    )


def unapplied_force_note(machine: Machine, effects: Effects) -> str | None:
    """A note when the true machine has a force model (``Machine.force_models``) that a run with ``effects`` does not
    apply (only ``[force] use_machine_compliance = true`` in the effects hands the cutting force to the twin), else
    None: the tool then cuts with no force on the twin, and a comprehensively compensated cut (the slot block's
    third slot) looks worse than a geometric one."""
    models = machine.force_models()
    if not models or (effects.force is not None and effects.force.use_machine_compliance):
        return None
    return (f"the true machine's force model ({', '.join(models)}) is not applied in this run: the tool cut with no "
            "force on it, so a comprehensive compensation looks worse than a geometric one; to apply it, give "
            "--effects with [force] use_machine_compliance = true")


def _idle_effects_note(machine: Machine, effects: Effects) -> str | None:
    """A note when an effects file was given that switches nothing on, or asks for the true machine's force model
    where it has none: the run is then the true machine alone (said, not left silent: a QA pass)."""
    if effects.source == "<none>":
        return None
    if effects.force is not None and effects.force.use_machine_compliance and not machine.force_models() \
            and effects.force.compliance_um_per_n is None:
        return (f"{effects.source}: [force] use_machine_compliance asks for the true machine's force model, and "
                f"{machine.name} has none: no force deflection in this run")
    on = [f.name for f in dataclasses.fields(effects) if f.name != "source" and getattr(effects, f.name)]
    if not on:
        return f"{effects.source}: no effect is switched on: the run is the true machine alone"
    return None


def write_cmm(result: SimResult, out_ply, binary: bool = True) -> Path:
    """Write the measured cloud (cut points only) as PLY in the part frame and ``<name>.truth.json`` beside it.

    Returns the truth file's path. The truth file is for tests; no product code reads it.
    """
    from ..inspect.cloud import write_cloud_ply

    out_ply = Path(out_ply)
    cut = np.isfinite(result.deviations_um)
    if not np.any(cut):
        raise ValueError("no probe point was cut: nothing to write (is the program cutting the part?)")
    comments = [f"trueaxis virtual CMM: part {result.part.get('part')}, machine {result.machine.name}",
                f"probe noise sigma {result.noise_sigma_um:g} um, seed {result.seed}"]
    write_cloud_ply(out_ply, result.measured[cut], result.normals[cut], binary=binary, comments=comments)
    truth = {
        "note": "truth of a simulated measurement, for tests only",
        "machine_file": result.machine.source,
        "machine_name": result.machine.name,
        "effects_file": result.effects.source,
        "effects": result.effects.as_dict(),
        "part": result.part.get("part"),
        "seed": result.seed,
        "noise_sigma_um": result.noise_sigma_um,
        "dt_s": result.trajectory.dt,
        "axis_names": list(result.trajectory.axis_names),
        "points_written": int(cut.sum()),
        "points_not_cut": int((~cut).sum()),
        "info": result.info,
        "timings_s": result.timings,
        "per_point": {
            "nominal_mm": result.points[cut].round(9).tolist(),
            "deviation_um": result.deviations_um[cut].round(6).tolist(),
            "noise_um": result.noise_um[cut].round(6).tolist(),
            "cut_time_s": result.cut_time_s[cut].round(6).tolist(),
            "block_line": result.block_line[cut].tolist(),
            "axes_actual": result.axes_actual[cut].round(9).tolist(),
            "force_n": result.force_n[cut].round(4).tolist(),
        },
    }
    path = _cmm.truth_path(out_ply)
    _cmm.write_json_atomic(path, truth)
    return path


def simulate_program_file(program_path, machine: Machine, part: str, *, effects_path=None, part_dir=None,
                          points: int = 200_000, noise_um: float = 0.0, seed: int = 0, progress: bool = True,
                          ) -> SimResult:
    """Machine the program file ``program_path`` on the true ``machine`` (with the effects file ``effects_path``, or
    none) and measure ``part`` with the virtual CMM (``points`` probe points, ``noise_um`` probe noise, ``seed``).

    The shop sets the machine up as the program's setup comment ``(trueaxis-setup: part=.. origin_mm=X,Y,Z
    tool_d_mm=D ...)`` (written by ``trueaxis.postproc.programs``) says, through ``programs.placed_for`` as the
    diagnosis and the identification do: its origin replaces the machine file's ``[workpiece] origin`` (said on
    stderr), and it cuts with the tool the program was made for (``tool_d_mm``; the result's ``machine.tool``). A
    program for the other part, or for another size of the part than the description (``part_dir``, or the part's
    default; ``programs.check_part_against_program``), is refused with ProgramError, and a program whose header says
    it was written for another machine with PostError (``post.refuse_other_machine``, as the post refuses it); other
    errors raise ValueError with a clear message."""
    import sys

    from ..postproc.post import refuse_other_machine
    from ..postproc.programs import check_part_against_program, placed_for

    program_path = Path(program_path)
    if not program_path.is_file():
        raise ValueError(f"{program_path}: no such program file")
    text = program_path.read_text(encoding="utf-8", errors="replace")
    # a program written for another machine: its axis words are that machine's joints (the post's check)
    refuse_other_machine(text, str(program_path), machine, ("this simulation is of", "simulate"))
    placed = placed_for(machine, text, part)
    part_data = load_part(part, None, part_dir)
    check_part_against_program(part, part_data, text, option="--part-dir")
    if not np.allclose(placed.workpiece_origin, machine.workpiece_origin, atol=1e-9):
        print(f"part placed as the program says: origin {placed.workpiece_origin.tolist()} mm in M (machine file: "
              f"{machine.workpiece_origin.tolist()})", file=sys.stderr)
    effects = load_effects(effects_path, placed) if effects_path else None
    return simulate(program_path, placed, effects, part=part, part_json=part_data, points=int(points),
                    noise_um=float(noise_um), seed=int(seed), progress=progress)
