"""The diagnosis report: ``diagnosis.json`` and ``diagnosis.html`` with matplotlib pictures, written together.

    diag, state = run_diagnosis(cloud, part, machine, program_text, candidates="all", split="region", noise_um=None)
    write_report(diag, state, "report_dir")

``diagnose_files(...)`` is the command ``trueaxis diagnose`` on files (its arguments are read in ``trueaxis.cli``).
"""

from __future__ import annotations

import base64
import html
import io
import math
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..inspect.cloud import CloudError
from ..inspect.deviation import cloud_normals_note, nominal_normals
from ..inspect.flyers import MAX_BEYOND_GATE
from ..fileio import json_text
from ..nc.gcode import parse_program
from .analysis import EXPLAIN_SHARE, Diagnosis, diagnose_state
from .candidates import LIBRARY, build_all
from ..postproc.programs import (ProgramError, check_axes, check_cut_share, check_part_against_program, placed_for,
                                 refuse_lathe)
from .state import TwinState, combine_states, pauses_between, twin_state

FORCE_CANDIDATES = ("force_deflection", "tool_deflection")


def parse_candidates(text: str | None) -> list[str]:
    """'all' or 'NAME,NAME' -> names; ValueError naming the unknown ones."""
    if text is None or text.strip() == "all":
        return list(LIBRARY)
    names = [s.strip() for s in text.split(",") if s.strip()]
    bad = [n for n in names if n not in LIBRARY]
    if bad or not names:
        raise ValueError(f"--candidates: unknown {', '.join(bad) or '(empty)'} (known: all, {', '.join(LIBRARY)})")
    return names


def part_description(part: str, part_json=None) -> dict:
    """The part's description (the JSON of its ``trueaxis.workpiece`` module): ``part_json`` as a dict, a path to a
    JSON file, or the part's typed parameters (``Nas979Params`` / ``SlotBlockParams``); None: the part at its default
    size. ValueError when it describes another part."""
    from ..workpiece.part import get_part, load_part

    if part_json is not None and not isinstance(part_json, (dict, str, os.PathLike)):
        part_json = get_part(part).description(part_json)
    return load_part(part, part_json)


def run_diagnosis(points, normals, part: str, machine, program_text: str, *, candidates="all", split="region",
                  noise_um=None, force_stride: int = 200, part_json=None,
                  program_name: str = "<program>") -> tuple[Diagnosis, TwinState]:
    """Twin simulation, candidates, judgement. points (N,3) mm part frame; normals (N,3) or None.

    part_json : the part's description (dict, JSON path, or ``Nas979Params`` / ``SlotBlockParams``; default: the
    part at its default size): its bounding box gates the cloud, its surfaces give missing normals, and its stock
    is what the twin's force model engages (a cone of another size must be described, else the force is wrong)."""
    return run_diagnosis_cuts([MeasuredCut(points, normals, program_text, program_name)], part, machine,
                              candidates=candidates, split=split, noise_um=noise_um, force_stride=force_stride,
                              part_json=part_json)


@dataclass
class MeasuredCut:
    """One measured part: its cloud (points (N, 3) mm, part frame; normals (N, 3) or None) and the program that cut
    it (text; its setup comment places the part on the machine)."""

    points: np.ndarray
    normals: np.ndarray | None
    program_text: str
    program_name: str = "<program>"
    part_json: object = None  # this part's description when it differs from the others' (see ``run_diagnosis``)
    cloud_name: str = ""


def run_diagnosis_cuts(cuts: list, part: str, machine, *, candidates="all", split="region", noise_um=None,
                       force_stride: int = 200, part_json=None, pauses_s=None,
                       progress=None) -> tuple[Diagnosis, TwinState]:
    """The diagnosis of one or more measured parts (``MeasuredCut``) cut one after another on one machine, in that
    order: each is read against the twin on its own (its gap and machine state), then all are judged together, the
    candidates sharing their parameters (one machine). A second placement of the part, or the same part cut after
    a warm-up, is what separates explanations one cut cannot tell apart (the report's separating measurement).

    pauses_s : with several cuts, the pause between the end of each cut and the start of the next (s, >= 0; one per
    gap, or one number for all): a drift runs on through it, so it is not assumed (0 when one part was cut right
    after the other). Every cut's cloud is checked before the first simulation.
    progress : a callable taking one line of text, told as each slow step starts (the twin's cut of each part, the
    candidates' fits), or None."""
    names = parse_candidates(candidates) if isinstance(candidates, str) or candidates is None else list(candidates)
    pauses = pauses_between(len(cuts), pauses_s)  # refused before any simulation

    def which(k, c):
        files = ", ".join(x for x in (c.cloud_name, c.program_name) if x)
        return f" (cut {k + 1} of {len(cuts)}: {files})" if len(cuts) > 1 else ""

    def for_cut(k, c, check):
        try:
            return check()
        except ValueError as exc:  # CloudError and ProgramError included; with several cuts, which one
            if not which(k, c):
                raise
            raise (type(exc) if type(exc) in (CloudError, ProgramError) else ValueError)(
                f"{exc}{which(k, c)}") from None

    # The cheap refusals of every cut before the first twin simulation (a bad second cloud is not found after the
    # first cut's minutes): the same cloud twice, a cloud outside its part, a program for the other part, normals.
    checked, notes = [], []
    for k, c in enumerate(cuts):
        for j, other in enumerate(cuts[:k]):
            # The same measurement, also when written again at another precision (0.1 um: far below any probe's
            # noise, far above a re-export's rounding), or with some points left out (``shared_points``).
            if shared_points(other.points, c.points) >= SAME_CLOUD_SHARE:
                raise CloudError(f"cloud {k + 1} is the same measurement as cloud {j + 1}{which(k, c)}: each part is "
                                 f"measured once (a cloud given twice would count its noise as signal)")
        pj = part_description(part, part_json if c.part_json is None else c.part_json)

        def gate(c=c, pj=pj):
            check_cloud_for_part(c.points, part, pj)
            placed = placed_for(machine, c.program_text, part)  # a program for the other part, a bad setup
            check_axes(placed, parse_program(c.program_text, c.program_name))  # posted for another machine
            check_part_against_program(part, pj, c.program_text)
            normals, given = nominal_normals(np.asarray(c.points, float), pj, c.normals)
            if given is not None and (given["inward"] or given["departed"]):
                notes.append(f"{c.cloud_name or 'the cloud'}: {cloud_normals_note(given)}")
            return normals

        checked.append((pj, for_cut(k, c, gate)))
    say = progress or (lambda line: None)
    states = []
    for k, (c, (pj, normals)) in enumerate(zip(cuts, checked)):
        say(f"the twin cutting {c.program_name}{f' (part {k + 1} of {len(cuts)})' if len(cuts) > 1 else ''} at "
            f"{len(c.points)} measured points (the virtual shop's 1 ms trajectory and the tool's envelope)")

        def read(c=c, pj=pj, normals=normals):
            st = twin_state(c.points, normals, machine, c.program_text, part,
                            want_force=any(n in FORCE_CANDIDATES for n in names), force_stride=force_stride,
                            part_json=pj, program_name=c.program_name)
            if len(st) < 20:
                raise CloudError(f"only {len(st)} measured points were cut by the program: too few to diagnose")
            check_cut_share(len(st), len(st) + st.dropped)  # as the identification and the virtual shop
            return set_apart_flyers(st, c.cloud_name)

        states.append(for_cut(k, c, read))
    state = combine_states(states, pauses)
    t0 = time.perf_counter()
    cands, skipped = build_all(names, state)
    if not cands:
        raise ValueError(f"--candidates: none of {', '.join(names)} applies to this machine and program (an axis it "
                         f"does not have or that does not move while cutting, no force estimate, or an effect that "
                         f"cannot move this part's surface)")
    say(f"fitting {len(cands)} candidate effects on training folds, judging them on held-out ones ({split} split)")
    diag = diagnose_state(state, cands, split=split, noise_um=noise_um, skipped=skipped)
    among_given(diag, names)
    if len(cuts) > 1 and any(m.startswith("thermal") for m in diag.chosen):
        # The drift's shape over several parts is read on the clock the pauses make: say so with the verdict (a pause
        # of 400 s given for 40 s named a drift 4.5 times too large beside a servo lag, at 0.59, in a QA pass).
        given = ", ".join(f"{p:g} s" for p in state.pauses_s)
        diag.notes.append(f"the drift is read on the clock the pauses given make ({given} between the parts): a wrong "
                          f"pause changes the drift's size and what goes with it")
        better = pause_the_data_prefer(states, pauses, diag, state.gap_um)
        if better is not None:
            diag.notes.append(better)
    diag.notes.extend(notes)
    state.timings["diagnosis_s"] = time.perf_counter() - t0
    return diag, state


#: The confidence of a verdict when the user restricted the library (``--candidates``) is at most this: the
#: confidence is calibrated on the whole library (answers at >= 0.7 right 99 % of the time on the case sets), its
#: separation measured against the best rival; with candidates left out, the rivals left out are not measured, and
#: with none given the separation saturates (backlash on X diagnosed among backlash_y, servo_lag and thermal_x was
#: "servo_lag (confidence 0.77)", a QA pass). One chance in two, as for the other verdicts the part cannot settle.
RESTRICTED_CONF_CAP = 0.5
#: A verdict among the candidates given that leaves a held-out RMS above this many times the noise is said.
RESTRICTED_MISFIT = 1.3


def among_given(diag: Diagnosis, names: list) -> None:
    """A verdict of a library the user restricted: said to be among the candidates given, its confidence at most
    ``RESTRICTED_CONF_CAP`` (recorded in ``confidence_basis``: restricted_to, uncapped_confidence), and a note when
    it leaves more than ``RESTRICTED_MISFIT`` times the noise on held-out points. The whole library: nothing."""
    left_out = [n for n in LIBRARY if n not in names]
    if not left_out:
        return
    diag.confidence_basis["restricted_to"] = list(names)
    diag.confidence_basis["left_out"] = left_out
    if diag.chosen_fit is None:  # (said "none of the candidates given": ``verdict_words``)
        return
    diag.confidence_basis["uncapped_confidence"] = diag.confidence
    diag.confidence = min(diag.confidence, RESTRICTED_CONF_CAP)
    diag.notes.append(f"the verdict is the best among the candidates given ({', '.join(names)}), not the whole "
                      f"library: its confidence is held at {RESTRICTED_CONF_CAP:g} (the effects left out were not "
                      f"tried as rivals)")
    after = diag.gap_after["rms"]
    if after > RESTRICTED_MISFIT * diag.noise_um:
        diag.notes.append(f"{diag.verdict} leaves {after:.2f} um RMS on held-out points against a probe noise of "
                          f"{diag.noise_um:.2f} um: structure it does not describe (it removes "
                          f"{diag.chosen_fit.explained_share * 100:.0f} % of the gap above the noise, enough by the "
                          f"rules' {EXPLAIN_SHARE * 100:.0f} % for a candidate poorer than the real effect); an effect "
                          f"left out may describe it: diagnose with all candidates")


#: The pauses tried against the one given, as multiples of it (or, when 0 was given, of the mean cut's duration).
PAUSE_FACTORS = (0.0, 0.125, 0.25, 0.5, 0.75, 1.5, 2.0, 3.0, 4.0, 8.0)
#: How much better (chi-square, in noise variances) another pause must fit than the one given to be said.
PAUSE_CHI2 = 9.0


def pause_the_data_prefer(states: list, pauses, diag: Diagnosis, gap_um: np.ndarray) -> str | None:
    """A note when the verdict's drift fits the parts better with other pauses between them than the ones given
    (``PAUSE_FACTORS``, by more than ``PAUSE_CHI2`` noise variances), else None. The verdict's members are fitted
    anew on each clock (the drift's every time constant tried, the others in their fitted shape, bounded as the
    diagnosis fits): a check of the input, the verdict stays as it is."""
    from .analysis import _solve_bounded, family, plausible_bounds

    f = diag.chosen_fit
    given = np.asarray(pauses, float)
    scale = given if np.any(given > 0) else np.full_like(given, np.mean([st.t_end_s for st in states]))
    variants = f.member_variants or (f.variant,)

    def rss(p):
        cands = {c.name: c for c in build_all(f.members, combine_states(states, p))[0]}
        if any(m not in cands for m in f.members):
            return np.inf
        sets = [[]]
        for k, name in enumerate(f.members):
            c = cands[name]
            shapes = ([v for _, v in c.variants] if family(name) == "thermal" else
                      [c.variants[variants[k]][1]]) if c.variants else [c.columns]
            sets = [s + [v] for s in sets for v in shapes]
        bounds = plausible_bounds([cands[name] for name in f.members])
        best = np.inf
        for cols in sets:
            S = np.column_stack(cols)
            r = gap_um - S @ _solve_bounded(S, gap_um, bounds)[0]
            best = min(best, float(r @ r))
        return best

    at_given = rss(given)
    tried = [(rss(scale * k), scale * k) for k in PAUSE_FACTORS if not np.allclose(scale * k, given)]
    if not tried:
        return None
    r, p = min(tried, key=lambda t: t[0])
    gain = (at_given - r) / diag.noise_um ** 2
    if not gain > PAUSE_CHI2:
        return None
    said = ", ".join(f"{v:g} s" for v in p)
    return (f"the drift fits the parts better with {said} between them than with the pause given (chi-square "
            f"{gain:.0f} noise variances lower): check --pause-s; the drift's size and the verdict rest on it")


# Two clouds of which this share of the smaller one's points are the other's (to 0.1 um) are one measurement: no two
# probings of a part land on the same points to 0.1 um (a measurement given twice, once with a few points dropped,
# passed as two parts).
SAME_CLOUD_SHARE = 0.5


def shared_points(a, b, tol_mm: float = 1e-4) -> float:
    """The share of the smaller of the clouds a, b ((n, 3) mm) whose points are points of the other, to ``tol_mm``
    (on a grid of that size: a point on a cell border may be missed, a share, not an exact count)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if len(a) == 0 or len(b) == 0:
        return 0.0
    if len(a) > len(b):
        a, b = b, a
    key = lambda p: np.round(p / tol_mm).astype(np.int64)  # noqa: E731
    inter = np.intersect1d(key(a).view([("", np.int64)] * 3).ravel(), key(b).view([("", np.int64)] * 3).ravel())
    return inter.size / len(a)


MAX_GAP_RMS_UM = 500.0  # the post's default correction bound: a larger gap is not a machine effect but a wrong input


def set_apart_flyers(st: TwinState, cloud_name: str = "") -> TwinState:
    """The state without the cloud's flyers (``trueaxis.inspect.flyers``, the rule ``inspect --identify`` applies
    too: the inspection's gate on the gap, then the local screen), which are recorded in ``state.flyers``; a cloud
    mostly beyond the gate, or whose gap over the points kept is beyond ``MAX_GAP_RMS_UM``, is refused (CloudError):
    not a measurement of that cut. (Three 1 mm flyers in 3000 points turned a backlash at 1.00 into "none of the
    candidates", a QA pass.)"""
    from ..inspect.flyers import screen_flyers

    screen = screen_flyers(st.points, st.normals, st.gap_um)
    kept = st.gap_um[screen.keep]
    all_rms = float(np.sqrt(np.mean(st.gap_um ** 2)))
    gap_rms = float(np.sqrt(np.mean(kept ** 2))) if kept.size else all_rms
    if screen.beyond_gate.mean() > MAX_BEYOND_GATE or not gap_rms <= MAX_GAP_RMS_UM:
        raise CloudError(f"the cloud lies {all_rms:.0f} um (RMS) from the part this program cuts on this twin "
                         f"({screen.beyond_gate.sum()} of {len(st)} points beyond the {screen.gate_mm:g} mm gate): not "
                         f"a measurement of that cut (another part, another frame, another program?); a machine's "
                         f"sim-to-real gap stays below {MAX_GAP_RMS_UM:.0f} um (the post's correction bound)")
    if not screen.n_apart:
        return st
    if screen.keep.sum() < 20:
        raise CloudError(f"only {int(screen.keep.sum())} measured points left once the flyers are set apart: too few "
                         f"to diagnose")
    out = st.subset(screen.keep)
    out.flyers = (dict(screen.as_dict(), cloud=cloud_name, sentence=screen.sentence("the diagnosis")),)
    return out


def flyer_warnings(state: TwinState) -> list[str]:
    """The flyers set apart before the diagnosis, one line per cloud (the terminal and the report)."""
    return [f"{f['cloud']}: {f['sentence']}" if f.get("cloud") else f["sentence"] for f in state.flyers]


MIN_POINTS = 20  # the fewest measured points a diagnosis takes


def check_cloud_for_part(points, part: str, part_json: dict | None = None) -> None:
    """The input gate of a measured cloud (as ``inspect`` has it): finite points inside the part's bounding box, 1 mm
    allowance; a cloud of another part, or in another frame or unit, is refused before any simulation."""
    from ..inspect.cloud import check_extent
    from ..inspect.deviation import part_bbox
    from ..inspect.report import EXTENT_TOLERANCE_MM
    from ..sim.shop import load_part

    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CloudError(f"a cloud is points of three coordinates (x, y, z); got an array of shape {pts.shape}")
    if len(pts) < MIN_POINTS:
        raise CloudError(f"a diagnosis needs a cloud of at least {MIN_POINTS} points; this one has {len(pts)}")
    check_extent(pts, *part_bbox(load_part(part, part_json)), EXTENT_TOLERANCE_MM, part=part)


# ---------------------------------------------------------------------------------------------------- JSON ----
def _fit_dict(f) -> dict:
    return {"effect": f.name, "members": f.members,
            "parameters": [{"name": n, f"value_{u.replace('/', '_per_')}": float(v),
                            f"std_{u.replace('/', '_per_')}": float(s), "unit": u}
                           for n, u, v, s in zip(f.parameters, f.units, f.value, f.std)],
            "held_out_gain_um2": f.gain_um2, "held_out_rms_after_um": f.rms_after_um,
            "explained_share_above_noise": f.explained_share, "z": f.z, "f_stat": f.f_stat, "f_p_value": f.f_p,
            "significant": f.significant, "plausible": f.plausible, "explains": f.explains,
            "n_parameters": f.n_parameters, "effective_rank": f.rank, **f.extra}


def _clock_text(state: TwinState) -> str:
    """How the parts' times were put together (several cuts): the pauses given between them."""
    said = ", ".join(f"{p:g} s" for p in state.pauses_s)
    return (f"the parts were cut one after another with {'a pause' if len(state.pauses_s) == 1 else 'pauses'} of "
            f"{said} between them (as given): the drift's time runs on through "
            f"{'it' if len(state.pauses_s) == 1 else 'them'}, part to part, each part's drift seen from its own set-up")


#: A part whose held-out residual after the verdict exceeds this many times the probe noise is named in a warning
#: (several parts): the verdict does not describe it as it describes the others.
PER_CUT_MISFIT = 1.3
#: Without a verdict, a part whose gap RMS exceeds this many times every other part's (and the noise) is named.
PER_CUT_OUTLIER = 5.0


def per_cut_figures(diag: Diagnosis, state: TwinState) -> list[dict]:
    """Per measured part (several cuts): points, the gap's RMS before and the held-out RMS after the verdict, um."""
    if state.piece is None:
        return []
    g = state.gap_um
    after = g - (diag.chosen_fit.held_out_pred_um if diag.chosen_fit is not None else 0.0)
    out = []
    for k in range(int(state.piece.max()) + 1):
        rows = state.piece == k
        out.append({"cut": k + 1, "points": int(rows.sum()), "gap_rms_um_before": float(np.sqrt(np.mean(g[rows] ** 2))),
                    "held_out_rms_um_after": float(np.sqrt(np.mean(after[rows] ** 2)))})
    return out


def max_growth_warning(diag: Diagnosis, notes: bool = False) -> list[str]:
    """A warning when the verdict's effect, added, makes the held-out gap's max grow by more than 3 noise sigma: the
    bulk explained, the extremes not (a QA pass: a servo lag "shrink 88 %" while the held-out max went 14.1 -> 22.1
    um at 1 um noise). With ``notes``, instead, the note for a smaller growth (within the noise's extremes): said with
    what the effect fitted on every point leaves, since each held-out region is predicted from a fit on the others
    (a QA pass: backlash on the slot block, held-out max 7.00 -> 8.88 um unexplained, where the shop cut again with
    the fitted effect left 3.90 um)."""
    if diag.chosen_fit is None or diag.gap_after["max"] <= diag.gap_before["max"]:
        return []
    strong = diag.gap_after["max"] > diag.gap_before["max"] + 3.0 * diag.noise_um
    if strong == notes:
        return []
    growth = f"the held-out gap's max grows ({diag.gap_before['max']:.2f} -> {diag.gap_after['max']:.2f} um)"
    every = diag.chosen_fit.extra.get("all_points")
    fitted = "" if every is None else (f"; fitted on every point it leaves RMS {every['rms']:.2f}, max "
                                       f"{every['max']:.2f} um")
    if strong:
        return [f"with {diag.verdict} added, {growth} while its RMS goes {diag.gap_before['rms']:.2f} -> "
                f"{diag.gap_after['rms']:.2f} um: the verdict describes the bulk of the gap, not where it is "
                f"largest{fitted}"]
    return [f"with {diag.verdict} added, {growth}: each region of the part is predicted from the effect fitted on "
            f"the others{fitted}"]


def per_cut_warnings(diag: Diagnosis, state: TwinState) -> list[str]:
    """A warning for each part the verdict leaves well above the noise (a cloud given with another part's program,
    or an effect the verdict does not describe on that part)."""
    figures = per_cut_figures(diag, state)
    if diag.chosen_fit is None:
        # No verdict: a part whose gap is many times the others' (and the noise's) is named: a set-up, frame or
        # program error of that part is likelier than a machine effect seen on it alone.
        out = []
        for c in figures:
            others = [o["gap_rms_um_before"] for o in figures if o is not c]
            if others and c["gap_rms_um_before"] > PER_CUT_OUTLIER * max(max(others), diag.noise_um):
                out.append(f"part {c['cut']}: its gap is {c['gap_rms_um_before']:.2f} um RMS against "
                           f"{max(others):.2f} um at most on the others: is that cloud in the frame its program "
                           f"cut (datum, offsets), and the one its program cut?")
        return out
    if state.piece is None and diag.gap_after["rms"] > PER_CUT_MISFIT * diag.noise_um:
        # one part as well (a cloud given with the program of another placement left 1.33-1.49 times the noise, and
        # nothing was said: a QA pass)
        return [f"the verdict leaves {diag.gap_after['rms']:.2f} um RMS on held-out points against a probe noise of "
                f"{diag.noise_um:.2f} um: structure it does not describe (is the cloud the one this program cut, at "
                f"its placement? an effect outside the library?)"]
    return [f"part {c['cut']}: the verdict leaves {c['held_out_rms_um_after']:.2f} um RMS on its held-out points "
            f"against a probe noise of {diag.noise_um:.2f} um: structure it does not describe there (is that cloud "
            f"the one its program cut? an effect outside the library?)"
            for c in figures if c["held_out_rms_um_after"] > PER_CUT_MISFIT * diag.noise_um]


def _chosen_dicts(diag: Diagnosis) -> list[dict]:
    """The verdict's JSON entries (none or one): its parameters and the derived ones, with their std and unit."""
    chosen = []
    if diag.chosen_fit is not None:
        f = diag.chosen_fit
        chosen.append({"effect": f.name, "members": f.members,
                       "parameters": _fit_dict(f)["parameters"],
                       "derived_parameters": [{"name": d["name"], f"value_{d['unit']}": d["value"],
                                               f"std_{d['unit']}": d["std"], "unit": d["unit"],
                                               "determined": d.get("determined", True), "note": d.get("note", "")}
                                              for d in f.extra.get("derived", [])],
                       "variant": f.extra.get("variant"), "confidence": diag.confidence,
                       "plausible": f.plausible, "alternatives": diag.alternatives,
                       "separating_measurement": diag.separating_measurement})
    return chosen


def diagnosis_dict(diag: Diagnosis, state: TwinState, inputs: dict | None = None) -> dict:
    chosen = _chosen_dicts(diag)
    return {
        "format": 1,
        "inputs": inputs or {},
        "verdict": diag.verdict,
        "confidence_in_verdict": diag.confidence,
        "points": len(state), "points_not_cut_by_twin": state.dropped,
        "flyers_set_apart": [{k: v for k, v in f.items() if k != "sentence"} for f in state.flyers],
        "points_per_cut": [len(state)] if state.piece is None else np.bincount(state.piece).tolist(),
        "per_cut": per_cut_figures(diag, state),
        "clock": None if state.piece is None else _clock_text(state),
        "noise_sigma_um": diag.noise_um, "noise_estimated": diag.noise_estimated,
        "split": diag.split,
        "where": diag.where,
        "chosen": chosen,
        "alternatives": diag.alternatives,
        "separating_measurement": diag.separating_measurement,
        "notes": diag.notes,
        "warnings": [],
        "closest_candidates": diag.closest,
        "confidence_basis": diag.confidence_basis,
        "candidates": [_fit_dict(f) for f in diag.fits],
        "candidates_not_applicable": diag.skipped,
        "gap_um": {"before": diag.gap_before, "after": diag.gap_after},
        "shrink": {"raw_rms_reduction": diag.shrink_raw, "above_noise": diag.shrink_above_noise,
                   "formula_above_noise": "1 - (rms_after^2 - sigma^2) / (rms_before^2 - sigma^2)"},
        "timings_s": {k: float(v) for k, v in state.timings.items()},
    }


# ------------------------------------------------------------------------------------------------ pictures ----
def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return buf.getvalue()


#: candidates.png: a bar's colour by what the rules made of the fit (the legend names those shown).
CANDIDATE_COLOURS = {"verdict": "tab:blue", "significant": "tab:green",
                     "set aside (at its bounds, or a spline no better than the drift)": "tab:orange",
                     "not significant": "tab:gray"}


def candidate_kind(f, diag: Diagnosis) -> str:
    """What the rules made of a single candidate's fit: a key of ``CANDIDATE_COLOURS``."""
    if diag.chosen_fit is not None and f.name in diag.chosen:
        return "verdict"
    if not f.significant:
        return "not significant"
    if not f.plausible or f.extra.get("not_beyond_constrained"):
        return "set aside (at its bounds, or a spline no better than the drift)"
    return "significant"


def pictures(diag: Diagnosis, state: TwinState) -> dict:
    """name -> PNG bytes: gap map, gap vs the top state variables, candidates, before/after."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .analysis import state_variables

    out = {}
    g = state.gap_um
    lim = float(np.percentile(np.abs(g), 99)) or 1.0
    p = state.points
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, (i, j, lab) in zip(axs, ((0, 1, "x-y (top)"), (0, 2, "x-z (front)"))):
        sc = ax.scatter(p[:, i], p[:, j], c=g, cmap="coolwarm", vmin=-lim, vmax=lim, s=6)
        ax.set_aspect("equal")
        ax.set_title(f"gap on the part, {lab}")
        ax.set_xlabel("xyz"[i] + " mm")
        ax.set_ylabel("xyz"[j] + " mm")
    fig.colorbar(sc, ax=axs, label="gap: measured - twin, um")
    out["gap_map.png"] = _png(fig)

    variables = state_variables(state)
    top = [w["variable"] for w in diag.where[:6]]
    fig, axs = plt.subplots(2, 3, figsize=(12, 6.5))
    for ax, name in zip(axs.ravel(), top):
        x, kind, unit = variables[name]
        ax.scatter(x, g, s=3, alpha=0.4)
        r2 = next(w["held_out_r2"] for w in diag.where if w["variable"] == name)
        ax.set_title(f"{name}: held-out R2 {r2:.2f}")
        ax.set_xlabel(unit)
        ax.set_ylabel("gap, um")
    fig.tight_layout()
    out["gap_vs_state.png"] = _png(fig)

    fig, ax = plt.subplots(figsize=(9, 0.35 * max(4, len(diag.fits)) + 1))
    names = [f.name for f in diag.fits][::-1]
    rms = [f.rms_after_um for f in diag.fits][::-1]
    kinds = [candidate_kind(f, diag) for f in diag.fits][::-1]
    ax.barh(names, rms, color=[CANDIDATE_COLOURS[k] for k in kinds])
    ax.axvline(diag.gap_before["rms"], color="k", ls="--", label="before")
    ax.axvline(diag.noise_um, color="tab:red", ls=":", label="noise sigma")
    from matplotlib.patches import Patch

    ax.set_xlabel("held-out gap RMS after adding the candidate, um")
    ax.legend(handles=ax.get_legend_handles_labels()[0] + [Patch(color=CANDIDATE_COLOURS[k], label=k)
                                                          for k in CANDIDATE_COLOURS if k in kinds])
    out["candidates.png"] = _png(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    after = g - (diag.chosen_fit.held_out_pred_um if diag.chosen_fit is not None else 0.0)
    bins = np.linspace(-max(lim, 1e-3) * 1.2, max(lim, 1e-3) * 1.2, 60)
    ax.hist(g, bins=bins, alpha=0.5, label=f"before (rms {diag.gap_before['rms']:.2f} um)")
    ax.hist(after, bins=bins, alpha=0.5, label=f"after {diag.verdict} (rms {diag.gap_after['rms']:.2f} um)")
    ax.set_xlabel("held-out gap, um")
    ax.set_ylabel("measured points")
    ax.legend()
    out["before_after.png"] = _png(fig)
    return out


def _html(data: dict, pngs: dict) -> str:
    e = html.escape
    rows = "".join(f"<tr><td>{e(w['variable'])}</td><td>{w['held_out_r2']:.3f}</td></tr>" for w in data["where"])
    cands = "".join(
        f"<tr><td>{e(c['effect'])}</td><td>{c['held_out_rms_after_um']:.3f}</td><td>{c['held_out_gain_um2']:.3f}</td>"
        f"<td>{c['z']:.1f}</td><td>{'yes' if c['significant'] else 'no'}</td><td>{'yes' if c['plausible'] else 'no'}"
        f"</td></tr>" for c in data["candidates"])
    basis = data.get("confidence_basis") or {}
    given = " given" if basis.get("restricted_to") else ""
    chosen = "".join(f"<p><b>{e(c['effect'])}</b> (confidence {c['confidence']:.2f}): {e(parameters_text(c))}</p>"
                     for c in data["chosen"]) or (f"<p><b>none of the candidates{given}</b> explains the gap "
                                                  f"(confidence {data['confidence_in_verdict']:.2f}).</p>")
    if data["chosen"] and ("indistinguishable" in data.get("verdict", "") or given):  # as the terminal says it
        chosen = f"<p>Verdict: {e(verdict_words(data['verdict'], basis))}</p>" + chosen
    if given:
        chosen += f"<p>Candidates given: {e(', '.join(basis['restricted_to']))}.</p>"
    alt = ""
    if data["alternatives"]:
        alt = (f"<p>Almost as good: {e(', '.join(data['alternatives']))}. "
               f"To separate them: {e(data['separating_measurement'] or 'a second placement')}.</p>")
    alt += "".join(f"<p>Note: {e(r)}.</p>" for r in data.get("notes", []))
    alt = "".join(f"<p style='border:2px solid #c0392b;background:#fdecea;padding:4px'>Warning: {e(w)}</p>"
                  for w in data.get("warnings", [])) + alt
    if not data["chosen"] and data.get("closest_candidates"):
        said = closest_text(data["closest_candidates"])
        alt += f"<p>{e(said[:1].upper() + said[1:])}.</p>"
    b, a = data["gap_um"]["before"], data["gap_um"]["after"]
    imgs = "".join(f'<h3>{e(k)}</h3><img src="data:image/png;base64,{base64.b64encode(v).decode()}">'
                   for k, v in pngs.items())
    per_cut = data.get("points_per_cut") or []
    cuts = f" on {len(per_cut)} parts cut in turn ({' + '.join(map(str, per_cut))})" if len(per_cut) > 1 else ""
    if data.get("per_cut"):
        clouds = data["inputs"].get("cloud") or []
        programs = data["inputs"].get("program") or []

        def name(names, k):
            return e(str(names[k - 1])) if len(names) >= k else ""

        cut_rows = "".join(f"<tr><td>{c['cut']}</td><td>{name(clouds, c['cut'])}</td>"
                           f"<td>{name(programs, c['cut'])}</td><td>{c['points']}</td>"
                           f"<td>{c['gap_rms_um_before']:.3f}</td><td>{c['held_out_rms_um_after']:.3f}</td></tr>"
                           for c in data["per_cut"])
        cut_table = ("<table><tr><th>part</th><th>cloud</th><th>program</th><th>points</th><th>gap RMS um</th>"
                     f"<th>held-out RMS after um</th></tr>{cut_rows}</table><p>{e(data.get('clock') or '')}.</p>")
    else:
        cut_table = ""
    alt += "".join(f"<p><b>{e(line.strip())}</b></p>" for line in next_part_lines(data.get("next_part")))
    skipped = data.get("candidates_not_applicable") or []
    not_applicable = (f"<p>Not applicable to this machine and program (an axis it does not have or that does not "
                      f"move while cutting, no force estimate, or no effect on this part's surface): "
                      f"{e(', '.join(skipped))}.</p>" if skipped else "")
    return f"""<!DOCTYPE html><html><head><meta charset="utf-8"><title>trueaxis diagnosis</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}td,th{{padding:2px 8px;border-bottom:1px solid #ddd}}</style>
</head><body><h1>Sim-to-real gap: diagnosis</h1>
<p>{data['points']} points{cuts} ({data['points_not_cut_by_twin']} not cut by the twin's program), probe noise sigma
{data['noise_sigma_um']:.3f} um ({'estimated' if data['noise_estimated'] else 'given'}), held-out split: {e(data['split'])}.</p>
{cut_table}
<h2>Which</h2>{chosen}{alt}
<h2>How far</h2><table><tr><th></th><th>RMS um</th><th>P95 um</th><th>max um</th></tr>
<tr><td>before</td><td>{b['rms']:.3f}</td><td>{b['p95']:.3f}</td><td>{b['max']:.3f}</td></tr>
<tr><td>after</td><td>{a['rms']:.3f}</td><td>{a['p95']:.3f}</td><td>{a['max']:.3f}</td></tr></table>
<p>Shrink: raw RMS {data['shrink']['raw_rms_reduction'] * 100:.1f} %, above the noise
{e(shown_share(data['shrink']['above_noise']))}.</p>
<h2>Where</h2><p>The gap's mean along the normal is {b['mean']:+.3f} um (RMS {b['rms']:.3f} um): a uniform offset,
which no variable below ranks (their R2 is about the mean).</p>
<table><tr><th>variable</th><th>held-out R2</th></tr>{rows}</table>
<h2>Candidates</h2><table><tr><th>effect</th><th>held-out RMS after, um</th><th>gain um2</th><th>z</th>
<th>significant</th><th>plausible</th></tr>{cands}</table>
{not_applicable}
{imgs}</body></html>
"""


def write_report(diag: Diagnosis, state: TwinState, out_dir, inputs: dict | None = None,
                 warnings: list | None = None, next_part: dict | None = None) -> dict:
    """Write diagnosis.json, diagnosis.html and the PNGs as the folder ``out_dir``: everything is written into a
    temporary folder beside it first, which then replaces ``out_dir`` whole (``fileio.publish_folder``: a folder
    holding files trueaxis did not write there is refused, and no picture of an earlier run stays beside the new
    report). next_part : the plan of a separating part (``NextPart.as_dict``) or None. Returns the JSON dict."""
    out_dir = Path(out_dir)
    data = diagnosis_dict(diag, state, inputs)
    data["warnings"] = list(warnings or [])
    data["next_part"] = next_part
    from ..fileio import check_replaceable_folder, publish_folder, temp_folder_beside

    check_replaceable_folder(out_dir)  # before the pictures' seconds
    pngs = pictures(diag, state)
    tmp = temp_folder_beside(out_dir, suffix="")
    try:
        for k, v in pngs.items():
            (tmp / k).write_bytes(v)
        (tmp / "diagnosis.html").write_text(_html(data, pngs), encoding="utf-8")
        (tmp / "diagnosis.json").write_text(json_text(data), encoding="utf-8")
        publish_folder(tmp, out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return data


def diagnose_files(cloud, part: str, machine, program, output, *, candidates="all", split: str = "region",
                   noise_um: float | None = None, part_json=None, pauses_s=None, plan_next: bool = False,
                   progress=None) -> tuple[Diagnosis, dict]:
    """``trueaxis diagnose`` on files: read the cloud (any format ``read_cloud`` reads), the twin (machine file) and
    the program, diagnose, and write the report into ``output``. Returns (the diagnosis, the report's JSON dict).
    Errors raise ValueError; nothing is written then.

    cloud, program : a path each, or lists of paths of one length: several parts measured and the programs that
    cut them, in the order they were cut on the machine (diagnosed together, see ``run_diagnosis_cuts``); then
    part_json may be a list of one description per cloud too.
    machine, output : paths.  part : "nas979" | "slots".  candidates : "all", "NAME,NAME" or a list.
    split : "region" | "time" | "random".  noise_um : probe noise sigma (um, > 0) or None (estimated).
    part_json : the part's description (see ``run_diagnosis``).  pauses_s : several parts: the pause(s) between
    them, s (see ``run_diagnosis_cuts``; required there).  plan_next : when one part leaves the verdict uncertain
    beside a rival, plan the placement of a second part that separates them (``next_part``; a few twin simulations);
    without it, only how far the measured part separates them (no simulation).
    progress : a callable told each slow step in one line of text (the CLI prints it on a terminal), or None."""
    from ..inspect.cloud import read_cloud
    from ..machine import load_machine

    if noise_um is not None and not (np.isfinite(noise_um) and noise_um > 0):
        raise ValueError("--noise-um must be a finite number > 0")
    names = parse_candidates(candidates) if isinstance(candidates, str) or candidates is None else list(candidates)
    clouds = list(cloud) if isinstance(cloud, (list, tuple)) else [cloud]
    programs = [Path(p) for p in (program if isinstance(program, (list, tuple)) else [program])]
    if len(clouds) != len(programs):
        raise ValueError(f"{len(clouds)} cloud(s) and {len(programs)} program(s): give one --program per --cloud, in "
                         f"the order the parts were cut")
    for p in programs:
        if not p.is_file():
            raise ValueError(f"{p}: no such program file")
    each = list(part_json) if isinstance(part_json, (list, tuple)) else [part_json] * len(clouds)
    if len(each) != len(clouds):
        raise ValueError(f"{len(each)} part descriptions for {len(clouds)} clouds: give one for all, or one per "
                         f"--cloud in the same order")
    m = load_machine(machine)
    refuse_lathe(m, part)  # (before the notes on the programs' placement below, which a lathe's refusal needs not)
    texts = [p.read_text(encoding="utf-8", errors="replace") for p in programs]
    cuts, repeats = [], []
    for c, p, text, pj in zip(clouds, programs, texts, each):
        pts = read_cloud(c)  # drops exact repeats of a point (said below, as inspect says it)
        cuts.append(MeasuredCut(pts.points, pts.normals, text, str(p), pj, cloud_name=str(c)))
        if pts.repeats_dropped:
            repeats.append(f"{c}: {pts.repeats_dropped} of {pts.repeats_dropped + len(pts)} points repeat another "
                           f"point exactly (the same x, y, z): dropped, the diagnosis uses the {len(pts)} distinct "
                           "points; a cloud concatenated with itself, or a measurement exported twice?")
    posted_for = program_machine_warnings(m, list(zip(texts, programs)))
    try:
        diag, state = run_diagnosis_cuts(cuts, part, m, candidates=names, split=split, noise_um=noise_um,
                                         pauses_s=pauses_s, progress=progress)
    except ValueError as exc:  # a refusal says too when a program was written for another machine: the likely cause
        if not posted_for:
            raise
        raise type(exc)(f"{str(exc).rstrip('.?')}; note: {'; '.join(posted_for)}") from None
    one = len(clouds) == 1
    inputs = {"cloud": str(clouds[0]) if one else [str(c) for c in clouds], "part": part, "machine": str(machine),
              "program": str(programs[0]) if one else [str(p) for p in programs],
              "candidates": names, "split": split, "noise_um": noise_um,
              "part_json": [str(x) if isinstance(x, (str, Path)) else None for x in each] if not one else
              (str(part_json) if isinstance(part_json, (str, Path)) else None)}
    if not one:
        inputs["pauses_s"] = list(state.pauses_s)
    warnings = repeats + flyer_warnings(state) + posted_for + input_warnings(state, noise_um, diag)
    warnings += per_cut_warnings(diag, state)
    warnings += max_growth_warning(diag)
    diag.notes.extend(max_growth_warning(diag, notes=True))
    if state.dropped:  # said on the terminal too, not only in the page's point count
        measured = state.dropped + len(state) + sum(f["set_apart"] for f in state.flyers)
        warnings.append(f"{state.dropped} of {measured} measured points were not cut by the "
                        "program on the twin (another feature of the part, or a program that does not cut there): "
                        "left out of the diagnosis")
    plan = None
    if one:
        from .next_part import plan_next_part

        members = set(diag.chosen) | set(diag.alternatives)
        found = plan_next_part(diag, state, m, part, part_description(part, each[0]), texts[0], search=plan_next,
                               want_force=bool(members & set(FORCE_CANDIDATES)), progress=progress)
        plan = None if found is None else found.as_dict(part, str(machine))
        if found is None and plan_next:  # asked for, none planned: said why (it was silent, a QA pass)
            from .next_part import no_plan_reason

            why = no_plan_reason(diag, texts[0]) or "no rival is another effect than the verdict's"
            warnings.append(f"--plan-next: no second part planned: {why}")
    elif plan_next:  # (it was ignored without a word, a QA pass)
        warnings.append("--plan-next plans the next part from one measured part; with several given it plans none")
    if progress is not None:
        progress(f"writing the report and its pictures into {output}")
    data = write_report(diag, state, output, inputs, warnings, next_part=plan)
    return diag, data


def program_machine_warnings(machine, programs: list) -> list[str]:
    """A program posted for another machine (its header names the machine), what was assumed of a program's setup
    that it does not say (``programs.placement_assumed``, as the identification says it), one line each; read before
    any simulation, and added to a refusal. programs : [(text, path)], one per cut."""
    from ..postproc.programs import header_name, placement_assumed, program_compensation, written_for

    out = []
    name = header_name(machine)
    models = machine.force_models()
    for program_text, program in programs:
        assumed = placement_assumed(program_text, machine)  # said as the identification says it
        if assumed:
            out.append(f"{program}: {assumed}")
        posted = written_for(program_text)
        if posted and posted[0] != name:
            out.append(f"{program} was written for the machine {posted[0]!r}, the twin given is "
                       f"{name!r}: a diagnosis against another machine's twin names that machine's differences")
            continue
        said = program_compensation(program_text, machine)
        if said["same_twin"] is False:
            # Compensated by another twin: the part departs from nominal by what the twins differ by, but the gap is
            # the part against this twin's cut of the program as written (docs/identification.md), whoever
            # compensated it. (It said the gap held the twins' difference, and to diagnose with the other twin: a
            # QA pass, XOC 20 um apart, gap 1.01 um = the noise with the machine's twin; 21 um and a wrong verdict
            # with the other.)
            out.append(f"{program}: {said['note'].split(';')[0]}: the part's deviation from nominal holds what the "
                       "two twins differ by, the gap diagnosed here does not (it is the part against this twin's cut "
                       "of the program as written, whoever compensated it): the diagnosis needs --machine to be the "
                       "twin of the machine that cut the part")
        if said["mode"] == "comprehensive" and models:
            out.append(f"{program}: compensated for the cutting force with the twin's force model ("
                       f"{', '.join(models)}), while the twin's cut here is made without force (as the virtual shop's "
                       "by default): the force correction the program carries shows in the gap, as a force "
                       "deflection")
    return out


#: A probe noise given more than this factor from the data's estimate (``estimate_noise_um``) is said; and one that a
#: verdict's held-out residual falls clearly below (by ``analysis.CHI_Z`` standard errors of its mean square).
NOISE_GIVEN_FACTOR = 1.5


def input_warnings(state: TwinState, noise_um: float | None, diag: Diagnosis | None = None) -> list[str]:
    """What in the measured data looks wrong against the inputs, one line each: a probe noise given far from the
    one the data show (the 0.5-2 band let 1.9 um given for 1.0 print "127 % above the noise" at 1.00, and 0.5 um
    given for 1.0 read a control as a gap no candidate explains, a QA pass), or one the verdict's held-out residual
    is clearly below (a noise the residual undercuts is not the noise)."""
    from .analysis import CHI_Z, estimate_noise_um, noise_estimate_rel_se

    if noise_um is None:
        return []
    seen = estimate_noise_um(state)
    n = max(len(state), 1)
    why = []
    if not 1.0 / NOISE_GIVEN_FACTOR <= noise_um / max(seen, 1e-300) <= NOISE_GIVEN_FACTOR:
        why.append(f"the data show a probe noise of about {seen:.2f} um (the gap's differences between neighbouring "
                   f"points)")
    after = None if diag is None or diag.chosen_fit is None else diag.gap_after["rms"]
    if after is not None and after**2 < noise_um**2 * (1.0 - CHI_Z * math.sqrt(2.0 / n)):
        why.append(f"the verdict leaves {after:.2f} um RMS on held-out points, below the noise given (a noise the "
                   f"residual undercuts is not the noise; the data show about {seen:.2f} um)")
    before = None if diag is None else diag.gap_before["rms"]
    if not why and diag is not None and diag.chosen_fit is None and \
            before**2 > noise_um**2 * (1.0 + CHI_Z * math.sqrt(2.0 / n)) and \
            before**2 <= seen**2 * (1.0 + CHI_Z * math.sqrt(2.0 / n + 4.0 * noise_estimate_rel_se(state) ** 2)):
        # "none of the candidates" where the gap is the noise the data show: 0.7 um given for 1.0 turned a twin that
        # predicts the part into a gap no candidate explains, without a word (a QA pass)
        why.append(f"the gap's RMS {before:.2f} um is the probe noise the data show (about {seen:.2f} um, the gap's "
                   f"differences between neighbouring points): with that noise there is no gap to explain")
    if not why:
        return []
    return [f"--noise-um {noise_um:g} um, but {'; and '.join(why)}: the shares above the noise, the test of a gap "
            f"against the noise and the parameters' std rest on it; check --noise-um, or leave it out to have it "
            f"estimated"]


def shown_share(share: float) -> str:
    """A share above the noise as printed: at most 100 % (more is a held-out residual below the noise given: within
    its sampling when the noise is right, else said by ``input_warnings``)."""
    return f"{min(share, 1.0) * 100:.0f} %"


def summary_lines(diag: Diagnosis, output, named_candidates: bool = False, next_part: dict | None = None) -> list[str]:
    """The command's summary on the terminal. named_candidates : the user named the candidates (then those that do
    not apply to this machine and part are listed; of the whole library they are only in the report). next_part :
    the report's plan of a separating part, or None."""
    b, a = diag.gap_before, diag.gap_after
    out = [f"{output}: {verdict_words(diag.verdict, diag.confidence_basis)} (confidence {diag.confidence:.2f}); "
           f"held-out gap rms {b['rms']:.2f} -> {a['rms']:.2f} um (mean {b['mean']:+.2f} -> {a['mean']:+.2f}), "
           f"max {b['max']:.2f} -> {a['max']:.2f} um; "
           f"shrink {diag.shrink_raw * 100:.0f} % raw, "
           f"{shown_share(diag.shrink_above_noise)} above the noise (sigma {diag.noise_um:.2f} um)"]
    if diag.alternatives:
        out.append(f"  almost as good: {', '.join(diag.alternatives)}; to separate: "
                   f"{diag.separating_measurement or 'a second placement of the part, or the other test part'}")
    if diag.chosen_fit is not None:
        out.append(f"  parameters: {parameters_text(_chosen_dicts(diag)[0])}")
    for note in diag.notes:
        out.append(f"  note: {note}")
    if diag.chosen_fit is None and diag.closest:  # the page's words, from the same list
        out.append(f"  {closest_text(diag.closest)}")
    if diag.skipped and named_candidates:
        out.append(f"  not applicable here: {', '.join(str(s) for s in diag.skipped)}")
    out += next_part_lines(next_part)
    return out


def closest_text(closest: list) -> str:
    """The closest candidates of a diagnosis with no verdict (``analysis.closest_candidates``) in one line, as the
    terminal and the page say them."""
    return "closest candidates (none explains the gap): " + "; ".join(
        f"{c['effect']}: {c['explained_share_above_noise'] * 100:.0f} % of the gap above the noise (held-out RMS "
        f"{c['held_out_rms_after_um']:.2f} um), {c['why_not'] or ''}" for c in closest)


def verdict_words(verdict: str, confidence_basis: dict) -> str:
    """The verdict as the terminal and the page say it: of a library the user restricted, "among the candidates
    given" ("none of the candidates given")."""
    if not confidence_basis.get("restricted_to"):
        return verdict
    return f"{verdict} given" if verdict == "none of the candidates" else f"{verdict}, among the candidates given"


def parameters_text(chosen: dict) -> str:
    """A verdict's parameters in words, from its JSON entry: the derived ones first where it has them (a servo axis'
    lag less the axes' mean, which the part determines; the lags themselves, read but not determined), then the
    fitted ones."""
    def of(p, key):  # its value_<unit> or std_<unit>
        return p[next(k for k in p if k.startswith(key))]

    def said(p):
        return f"{p['name']} = {of(p, 'value_'):.4g} ± {of(p, 'std_'):.2g} {p['unit']}"

    fitted = ", ".join(said(p) for p in chosen["parameters"])
    derived = chosen.get("derived_parameters") or []
    if not derived:
        return fitted
    known = [p for p in derived if p.get("determined", True)]
    unknown = [p for p in derived if not p.get("determined", True)]
    text = ", ".join(said(p) for p in known)
    if unknown:
        read = ", ".join(f"{p['name']} {of(p, 'value_'):.3g}" for p in unknown)
        why = unknown[0].get("note") or "not determined"
        text += f"{'; ' if text else ''}not determined: {read} {unknown[0]['unit']} as read ({why})"
    notes = sorted({p["note"] for p in known if p.get("note")})
    if notes:
        text += f" ({'; '.join(notes)})"
    return f"{text}; from the fitted terms {fitted}"


def next_part_lines(plan: dict | None) -> list[str]:
    """The plan of a separating second part in words (terminal and HTML); [] without a plan."""
    if not plan:
        return []
    drift = ", ".join(plan.get("left_out") or [])
    drift = (f"; {drift}: a drift, told apart by the same cut repeated at another time, not at another place"
             if drift else "")
    here = ", ".join(f"{k} z {v:.1f}" for k, v in plan["z_here"].items())
    z3 = f"z {plan['separates_at_z']:g}"
    if not plan["z_here"]:
        return [f"  next part: none planned{drift}"]
    if not plan.get("searched", True):
        return [f"  next part: on this part the signatures of {plan['verdict']} and its rivals differ by {here} ({z3} "
                f"separates): --plan-next finds the placement of a second part that separates them (a twin "
                f"simulation per placement tried){drift}"]
    if plan["placement_mm"] is None and not plan["tried"]:
        return [f"  next part: none planned: on this part the signatures of {plan['verdict']} and its rivals differ "
                f"already ({here}; {z3} separates), the gap fits each of them only approximately{drift}"]
    if plan["placement_mm"] is None:
        best = ", ".join(f"{k} z {v:.1f}" for k, v in plan["z_next"].items())
        return [f"  next part: no placement tried separates {plan['verdict']} from its rivals (on this part {here}; "
                f"at the best placement {best or 'none machinable'}, {z3} needed): another cone or the slot "
                f"block{drift}"]
    x, y = plan["placement_mm"]
    nxt = ", ".join(f"{k} z {v:.1f}" for k, v in plan["z_next"].items())
    return [f"  next part: cut the part again at placement {x:g}, {y:g} mm ({plan['command']}): with it "
            f"{plan['verdict']} and its rivals differ by {nxt} (on this part alone {here}; {z3} separates); then "
            f"diagnose both parts together (--cloud and --program twice, --pause-s){drift}"]
