"""Benchmark of ``trueaxis diagnose`` on sets of virtual-shop cases: a TUNING set and two HELD-OUT sets (issue 14).

Every case cuts the NAS 979 cone on a *true* machine = the twin plus one or two effects of the virtual shop, in the
shop's own physical forms (``trueaxis.sim.effects``: per-axis position loops with feed-forward and a velocity loop,
backlash of every axis with a tanh or friction take-up, the ISO 230-7 error motions of the rotary axes in the
kinematic chain, a measured thermal series, a full compliance matrix, a bending carbide tool, small changes of the
twin's own location errors) or, outside the candidate library, a wearing tool or a part springing back from its
clamping. The part is measured by the virtual CMM (1 um probe noise) and ``trueaxis.diagnose.report.run_diagnosis``
(the library API) sees only the cloud, the program and the twin. Effects are scaled so that their RMS on the part is
1x, 3x or 10x the probe noise (one noise-free calibration run per case; the servo loop's scale refined by a secant).
Effect parameters are drawn per case from the set's seed (gains 25-45 1/s per axis, feed-forward about 0.9, phases of
the error-motion harmonics, transition lengths, compliance terms, ...), so no case is the image of a candidate.

THE SETS. ``SETS`` below holds each set's seed, machines, part placements and cone sizes. The tuning set runs
on nmv1500dcg (B-C, C's line through the machine zero); the held-out set, from another seed, on ac_trunnion (A-C)
and bc_offset (B-C), both with their rotary lines off the machine zero, with other placements and cone sizes. The
held-out set is generated ONLY from its own section of ``SETS``: tune the diagnosis on ``--set tuning`` and do not
run ``--set heldout`` until its rules are frozen (DESIGN §8); nothing in the tuning set depends on the held-out one.
The held-out set was looked at while the rules were still changing (2026-11-25 morning); ``heldout2`` (fresh seed,
other placements and cone sizes on the same two machines) was added after they were frozen and run once.

EXPECTED ANSWERS. ``EXPECTED`` maps each effect kind to the answer the diagnosis should give (ISO-230 style names:
``backlash_x`` ... ``backlash_b``, ``servo_lag``, ``rotary_radial_c``, ``rotary_axial_c``, ``rotary_tilt_c``,
``rotary_angular_c``, ``thermal_x`` (its flexible spline ``thermal_spline_x`` counts as it), ``force_deflection``,
``tool_deflection``, ``twin_parameters``; out-of-library effects and controls: ``none``, i.e. nothing chosen).
``normalise`` maps the diagnosis' answers onto these (the older ``rotary_periodic_c`` counts as the angular motion).
``TRUTH`` gives the true value of the parameters a fitted candidate reports, by parameter name,
for the std-coverage figure: adjust it there when the candidates' parameter names change.

SCORES (each printed per set, and for all the sets run together):
- strict attribution at >= 3x noise: the chosen set of effects equals the expected set (in-library cases); also
  split by whether the case is identifiable on its part at all (``identifiability``: on the noise-free cut, does any
  other plausible candidate or pair reproduce the true effect's deviations as well as the truth's own candidate, to
  within what the probe noise can separate -- expected paired z below ``Z_IDENTIFIABLE``?). On a case that is not,
  every selection rule is a coin toss among the equivalent explanations; the figure says how much of the benchmark
  one part can answer, and the rules are judged on the rest;
- controls flagged (any answer but "none"); out-of-library cases answered "none";
- confidence: share right among answers with confidence >= 0.7; share of right answers at >= 3x with confidence
  >= 0.7;
- median share of the above-noise gap removed (right answers at >= 3x; also over all >= 3x cases);
- held-out max gap not worse after the effect is added (right answers);
- parameter std covering the truth (|value - truth| <= 2 std for every parameter with a known truth; the share of
  right answers where it holds, and how many had no parameter with a known truth); a servo axis' truth is the tool's
  lag behind the program at steady speed, (1 - kff) / kv plus the interpolator smoothing's delay (M - 1) dt / 2;
- the confidence's calibration: right / all answers in each band of confidence;
- the confusion matrix (rows: expected answer; columns: answer given), and the time per case.

RUNNING. Cases run as Dask tasks: a ``dask.distributed.LocalCluster`` (2 workers, 1 thread each) by default, or
``--scheduler ADDRESS`` for a running cluster (this file is uploaded to its workers, which need trueaxis installed
and the repository's fixtures: the one trueaxis is imported from, or $TRUEAXIS_ROOT).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set tuning            # tune on this
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set tuning --cases 12 --points 600   # quick subset
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set tuning --kinds servo,backlash_B,none
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set heldout           # once the rules are frozen
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set heldout2          # added after the 11-25 freeze
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set heldout3          # added after the 11-27 freeze
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set heldout4          # after the second 11-27 freeze
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set heldout5          # after the third 11-27 freeze
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set heldout6          # after the fourth 11-27 freeze
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set heldout7          # after the 11-28 freeze
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set heldout8          # after the second 11-28 freeze
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set heldout9 --points 8000   # the demo's probing
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_sets.py --set all --json out.json   # every set

``--cases N`` keeps N cases spread over the list (the case numbers and seeds stay those of the full list);
``--kinds`` keeps the cases holding one of the named effect kinds (``none`` for the controls); ``--list`` prints the
case list without running it; ``--json FILE`` keeps every case's result and ``--rescore FILE`` prints its scores
again; ``--demo-timing`` times one diagnosis of a cone probed with the demo's 8000 points.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import re
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np



def _root() -> Path:
    """The repository (fixtures, thermal series): $TRUEAXIS_ROOT (set by ``main`` for its workers), this file's
    repository, or the one trueaxis is imported from (a worker that received this file by ``upload_file``)."""
    if os.environ.get("TRUEAXIS_ROOT"):
        return Path(os.environ["TRUEAXIS_ROOT"])
    here = Path(__file__).resolve().parents[1]
    if (here / "fixtures" / "machines").is_dir():
        return here
    import trueaxis

    return Path(trueaxis.__file__).resolve().parents[1]


ROOT = _root()
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

NOISE_UM = 1.0
MAGNITUDES = (3.0, 10.0, 1.0)  # multiples of the probe noise (RMS of the effect on the part)
MAX_SCALE = 20.0  # largest multiple of an effect's reference size a case scales it to (else: not visible, skipped)
SERIES = "fixtures/thermal/spindle_thermal_drift_part1.csv"

# --------------------------------------------------------------------------------------------------- the sets ----
SETS = {
    "tuning": {
        "seed": 14_001,
        "setups": [
            {"machine": "nmv1500dcg", "placement_mm": (0.0, 0.0), "cone": {}},
            {"machine": "nmv1500dcg", "placement_mm": (60.0, 0.0), "cone": {}},
            {"machine": "nmv1500dcg", "placement_mm": (30.0, 30.0), "cone": {"base_diameter": 72.0, "height": 18.0}},
        ],
    },
    # Held out: generated only from this section. Other seed, other machines (A-C and B-C, rotary lines off the
    # machine zero), other placements and cone sizes.
    "heldout": {
        "seed": 92_717,
        "setups": [
            {"machine": "ac_trunnion", "placement_mm": (35.0, -20.0), "cone": {"base_diameter": 64.0, "height": 16.0}},
            {"machine": "ac_trunnion", "placement_mm": (-30.0, 30.0), "cone": {}},
            {"machine": "bc_offset", "placement_mm": (45.0, -10.0),
             "cone": {"base_diameter": 70.0, "height": 18.0, "half_angle_deg": 12.0}},
            {"machine": "bc_offset", "placement_mm": (0.0, 0.0), "cone": {"half_angle_deg": 18.0, "height": 18.0}},
        ],
    },
    # A second held-out set, added on 2026-11-25 after the diagnosis' rules were frozen (commit "the tool-wear shadow
    # must beat the best of the explanations tied with the verdict") and run once without changing them: a fresh
    # seed, other placements and cone sizes on the same two held-out machines.
    "heldout2": {
        "seed": 58_213,
        "setups": [
            {"machine": "ac_trunnion", "placement_mm": (-25.0, -35.0), "cone": {"base_diameter": 76.0, "height": 19.0}},
            {"machine": "ac_trunnion", "placement_mm": (40.0, 15.0),
             "cone": {"half_angle_deg": 13.0, "axis_inclination_deg": 8.0}},
            # (-40, 20) first: not machinable on bc_offset (the part would need a safe height above Z's travel; all
            # 20 of its cases were harness errors), moved to (30, -35) before any of its cases was diagnosed.
            {"machine": "bc_offset", "placement_mm": (30.0, -35.0), "cone": {"base_diameter": 66.0, "height": 17.0}},
            {"machine": "bc_offset", "placement_mm": (20.0, 40.0),
             "cone": {"half_angle_deg": 16.0, "height": 19.0, "axis_inclination_deg": 12.0}},
        ],
    },
    # A third held-out set, added on 2026-11-27 after the rules were frozen at commit eeb4b67 ("the gain-ratio tie no
    # longer ties away an explanation better by Z_TIE_RATIO"), run once: a fresh seed, and a layout no set had, the
    # head-table machine (B tilting head on the tool branch, C table), beside new placements on the A-C and B-C
    # tables. (Each placement was checked to be machinable before any case was run.)
    "heldout3": {
        "seed": 31_877,
        "setups": [
            {"machine": "headtable", "placement_mm": (25.0, -30.0), "cone": {}},
            {"machine": "headtable", "placement_mm": (-20.0, 15.0),
             "cone": {"base_diameter": 66.0, "height": 18.0, "half_angle_deg": 16.0}},
            {"machine": "ac_trunnion", "placement_mm": (-40.0, -15.0), "cone": {"base_diameter": 70.0, "height": 17.0}},
            {"machine": "bc_offset", "placement_mm": (35.0, 25.0), "cone": {"half_angle_deg": 14.0}},
        ],
    },
    # A fourth held-out set, added on 2026-11-27 (second session) after the rules were frozen again at 4fab255 (a
    # pair's wear shadow, the leaders paired with the candidates not significant alone, a verdict beaten by Z_MIN is
    # none, the confidence's gain deficit mapped 2 % -> 5 %), run once: a fresh seed, new placements and cone sizes
    # on the three held-out layouts.
    "heldout4": {
        "seed": 88_215,
        "setups": [
            {"machine": "headtable", "placement_mm": (-30.0, -25.0), "cone": {"base_diameter": 70.0, "height": 18.0}},
            {"machine": "ac_trunnion", "placement_mm": (20.0, 35.0), "cone": {"half_angle_deg": 17.0}},
            {"machine": "bc_offset", "placement_mm": (-35.0, 10.0),
             "cone": {"base_diameter": 68.0, "height": 17.0, "half_angle_deg": 13.0}},
            {"machine": "headtable", "placement_mm": (35.0, 20.0),
             "cone": {"half_angle_deg": 14.0, "axis_inclination_deg": 10.0}},
        ],
    },
    # A fifth held-out set, added on 2026-11-27 (third session) after the rules were frozen at 3898ef9 (the verdict's
    # std covers the variants the held-out points cannot reject; the noise estimate's standard error in the test of a
    # gap against the noise), run once: a fresh seed, new placements and cone sizes on the three held-out layouts
    # (bc_offset at (-20, -30) was not machinable, moved to (25, 15) before any case ran).
    "heldout5": {
        "seed": 67_349,
        "setups": [
            {"machine": "bc_offset", "placement_mm": (25.0, 15.0), "cone": {"base_diameter": 74.0, "height": 19.0}},
            {"machine": "ac_trunnion", "placement_mm": (30.0, -30.0), "cone": {"half_angle_deg": 13.0, "height": 17.0}},
            {"machine": "headtable", "placement_mm": (15.0, 35.0),
             "cone": {"base_diameter": 68.0, "axis_inclination_deg": 6.0}},
            {"machine": "headtable", "placement_mm": (-35.0, 0.0), "cone": {"half_angle_deg": 17.0, "height": 18.0}},
        ],
    },
    # A sixth held-out set, added on 2026-11-27 (fourth session) after the rules were frozen again (a fit whose
    # bounded values pin a parameter the part determines at its plausible bound is not plausible: the plausibility
    # was judged on the truncated free solution only), run once: a fresh seed, new placements and cone sizes on the
    # three held-out layouts (bc_offset at (-30, 20) was not machinable, moved to (-20, 20) before any case ran).
    "heldout6": {
        "seed": 40_591,
        "setups": [
            {"machine": "ac_trunnion", "placement_mm": (-20.0, 25.0), "cone": {"base_diameter": 72.0, "height": 18.0}},
            {"machine": "bc_offset", "placement_mm": (15.0, -30.0), "cone": {"half_angle_deg": 16.0}},
            {"machine": "headtable", "placement_mm": (-25.0, -10.0),
             "cone": {"half_angle_deg": 14.0, "height": 17.0, "axis_inclination_deg": 8.0}},
            {"machine": "bc_offset", "placement_mm": (-20.0, 20.0), "cone": {"base_diameter": 70.0, "height": 19.0}},
        ],
    },
    # A seventh held-out set, added on 2026-11-28 after the rules were frozen again at the commit that added it
    # (twin_parameters keeps, of location errors that move the surface alike, the one reaching furthest within its
    # bound: candidates.resolved_columns), run once: a fresh seed, new placements and cone sizes on the three
    # held-out layouts (each placement checked machinable before any case ran).
    "heldout7": {
        "seed": 73_019,
        "setups": [
            {"machine": "ac_trunnion", "placement_mm": (25.0, 20.0), "cone": {"base_diameter": 66.0, "height": 18.0}},
            {"machine": "bc_offset", "placement_mm": (20.0, -20.0), "cone": {"half_angle_deg": 17.0, "height": 17.0}},
            {"machine": "headtable", "placement_mm": (10.0, -30.0),
             "cone": {"half_angle_deg": 15.0, "axis_inclination_deg": 9.0}},
            {"machine": "ac_trunnion", "placement_mm": (-35.0, 5.0),
             "cone": {"base_diameter": 70.0, "half_angle_deg": 16.0}},
        ],
    },
    # An eighth held-out set, added on 2026-11-28 (seventh session) after the rules were frozen again at the commit
    # before it (the leading candidates paired with a set-aside candidate of at most two parameters), run once: a
    # fresh seed, new placements and cone sizes on the three held-out layouts (bc_offset at (-25, -25) and (-15, 30)
    # were not machinable, moved to (-30, -5) before any case ran).
    "heldout8": {
        "seed": 26_473,
        "setups": [
            {"machine": "bc_offset", "placement_mm": (-30.0, -5.0),
             "cone": {"base_diameter": 68.0, "height": 18.0, "half_angle_deg": 15.0}},
            {"machine": "headtable", "placement_mm": (30.0, 5.0), "cone": {"base_diameter": 72.0, "height": 17.0}},
            {"machine": "ac_trunnion", "placement_mm": (15.0, -35.0),
             "cone": {"half_angle_deg": 14.0, "axis_inclination_deg": 7.0}},
            {"machine": "bc_offset", "placement_mm": (40.0, 20.0), "cone": {"height": 19.0, "half_angle_deg": 13.0}},
        ],
    },
    # A ninth held-out set, added on 2026-11-28 (ninth session) with the rules as they stand at the commit before it
    # (none changed since heldout8's freeze; the servo lags' report did), run once at the demo's probing (8000
    # points) and once at 600: a fresh seed, new placements and cone sizes on the three held-out layouts (each
    # placement checked machinable before any case ran).
    "heldout9": {
        "seed": 26_902,
        "setups": [
            {"machine": "ac_trunnion", "placement_mm": (25.0, -15.0), "cone": {"height": 17.0}},
            {"machine": "bc_offset", "placement_mm": (30.0, 45.0),
             "cone": {"base_diameter": 66.0, "height": 18.0, "half_angle_deg": 15.0, "axis_inclination_deg": 9.0}},
            {"machine": "headtable", "placement_mm": (15.0, 0.0),
             "cone": {"base_diameter": 64.0, "height": 18.0, "half_angle_deg": 18.0, "axis_inclination_deg": 11.0}},
            {"machine": "ac_trunnion", "placement_mm": (10.0, 25.0), "cone": {"base_diameter": 66.0}},
        ],
    },
    # A tenth held-out set, added on 2026-11-28 (eleventh session) after the part's set-up joined the library
    # (setup_translation; the rules frozen at the commit that adds this set), run once at 600 points: a fresh seed,
    # new placements and cone sizes on the three held-out layouts.
    "heldout10": {
        "seed": 58_117,
        "setups": [
            {"machine": "ac_trunnion", "placement_mm": (-15.0, 20.0), "cone": {"height": 19.0}},
            {"machine": "bc_offset", "placement_mm": (-25.0, 30.0), "cone": {"half_angle_deg": 16.0}},
            {"machine": "headtable", "placement_mm": (20.0, -20.0),
             "cone": {"base_diameter": 68.0, "axis_inclination_deg": 10.0}},
            {"machine": "ac_trunnion", "placement_mm": (0.0, -25.0), "cone": {"base_diameter": 70.0}},
        ],
    },
    # An eleventh held-out set, added on 2026-11-28 (twelfth session) after a verdict's std came to cover the values
    # of the explanations tied with it (tie_spread; the rules frozen at the commit that adds this set), run once at
    # 600 points: a fresh seed, new placements and cone sizes on the three held-out layouts.
    "heldout11": {
        "seed": 71_933,
        "setups": [
            {"machine": "ac_trunnion", "placement_mm": (20.0, 10.0), "cone": {"height": 18.5}},
            {"machine": "bc_offset", "placement_mm": (25.0, 35.0), "cone": {"half_angle_deg": 17.0}},
            {"machine": "headtable", "placement_mm": (-25.0, -20.0), "cone": {"base_diameter": 67.0}},
            {"machine": "ac_trunnion", "placement_mm": (-10.0, -15.0), "cone": {"base_diameter": 69.0}},
        ],
    },
}

OUT_OF_LIBRARY = ("tool_wear", "clamping_bend")

ROTARY_COMPONENTS = ("radial", "axial", "tilt", "angular")  # ISO 230-7 error motions of a rotary axis

# The answer expected for each effect kind of the shop: the diagnosis' candidate names (as agreed with the diagnosis
# side, /work/notes/14-requests.md: lower-case axis letters, ISO 230-7 component names). One table: adjust here.
EXPECTED = {
    **{f"backlash_{a}": f"backlash_{a.lower()}" for a in "XYZABC"},
    "servo": "servo_lag",
    **{f"rotary_{c}_{a}": f"rotary_{c}_{a.lower()}" for c in ROTARY_COMPONENTS for a in "ABC"},
    **{f"thermal_{d}": f"thermal_{d}" for d in "xyz"},
    "force": "force_deflection",
    "tool_deflection": "tool_deflection",
    "twin_parameters": "twin_parameters",
    "tool_wear": "none",
    "clamping_bend": "none",
    "none": "none",
}


def normalise(name: str) -> str:
    """A diagnosis' candidate name in the table's naming: lower case; the flexible thermal spline counts as its
    direction's thermal drift (thermal_spline_x -> thermal_x); the older names rotary_periodic_c (-> the angular
    error motion), servo and force are accepted."""
    low = name.strip().lower()
    if low.startswith("thermal_spline_"):
        return "thermal_" + low[-1]
    if low.startswith("rotary_periodic_"):
        return "rotary_angular_" + low[-1]
    return {"servo": "servo_lag", "force": "force_deflection"}.get(low, low)


def kinds_for(machine_axes: tuple) -> list[str]:
    """The in-library effect kinds a machine with these axes can hold on the flank-milled cone. Not Z's backlash nor
    a drift along Z: on a table machine the tool stays along machine Z, and moving a flank-milling tool along its own
    axis leaves the flank where it is (both move the surface by 0.000 um; they belong to a part with a floor)."""
    rot = [a for a in machine_axes if a in "ABC"]
    return ([f"backlash_{a}" for a in machine_axes if a != "Z"] + ["servo"]
            + [f"rotary_{c}_{a}" for a in rot for c in ROTARY_COMPONENTS]
            + ["thermal_x", "thermal_y", "force", "tool_deflection", "twin_parameters"])


def pairs_for(machine_axes: tuple) -> list[tuple]:
    """Two-effect cases: the issue's classes (a radial error motion of C once per turn with an angular one twice per
    turn; a force deflection with a rotary error; rotary backlash with a drift) and a servo loop with backlash."""
    tilt = next(a for a in machine_axes if a in "AB")
    return [("rotary_radial_C", "rotary_angular_C"), ("force", "rotary_radial_C"), ("thermal_x", f"backlash_{tilt}"),
            ("servo", "backlash_Y")]


def build_cases(set_name: str) -> list[dict]:
    """The case list of a set: deterministic from its section of SETS only."""
    from trueaxis.machine import load_machine

    cfg = SETS[set_name]
    rng = np.random.default_rng(cfg["seed"])
    setups = cfg["setups"]
    cases = []

    def add(kinds, mag, k_setup):
        cases.append({"set": set_name, "n": len(cases), "kinds": list(kinds), "mag": float(mag),
                      "setup": setups[k_setup], "seed": int(rng.integers(2**31 - 1))})

    axes = {s["machine"]: load_machine(ROOT / "fixtures/machines" / f"{s['machine']}.toml").axis_names for s in setups}
    kinds = list(dict.fromkeys(k for s in setups for k in kinds_for(axes[s["machine"]])))
    for mag in MAGNITUDES:
        for kind in kinds:
            # A random setup whose machine holds the effect (backlash_A only on an A-C machine, ...).
            usable = [i for i, s in enumerate(setups) if kind in kinds_for(axes[s["machine"]])]
            add([kind], mag, int(rng.choice(usable)))
        if mag != 1.0:
            for k_setup, s in enumerate(setups):
                # On C's line an error motion of C only turns the cone about itself: pairs with one go off it.
                on_axis = not any(s["placement_mm"])
                prs = [p for p in pairs_for(axes[s["machine"]])
                       if not (on_axis and any(k.startswith("rotary_") and k.endswith("C") for k in p))]
                for j in range(2):  # two pairs per setup, in turn
                    add(prs[(2 * k_setup + j) % len(prs)], mag, k_setup)
            for kind in OUT_OF_LIBRARY:
                add([kind], mag, int(rng.integers(len(setups))))
        add([], 0.0, int(rng.integers(len(setups))))  # a control
    out = cases
    for i, c in enumerate(out):
        c["n"] = i
    return out


# ------------------------------------------------------------------------------------ effects of one case ----
def effect_draws(kind: str, seed: int, machine) -> dict:
    """Random physical parameters of an effect at its reference size (scale 1), drawn from the case's seed."""
    rng = np.random.default_rng([seed, sum(map(ord, kind))])
    names = machine.axis_names
    if kind.startswith("backlash_"):
        rot = machine.axes[kind[-1]].is_rotary
        return {"amplitude": 40.0 if rot else 5.0, "transition": float(rng.uniform(0.02, 0.1) if rot else
                                                                       rng.uniform(0.01, 0.05)),
                "form": str(rng.choice(["tanh", "friction"]))}
    if kind == "servo":
        return {"kv": {a: float(rng.uniform(25.0, 45.0)) for a in names}, "kff0": float(rng.uniform(0.87, 0.93)),
                "tv_ms": {a: float(rng.uniform(1.0, 4.0)) for a in names},
                "aff": float(rng.choice([0.0, 0.5])),
                # mm/s^2 and deg/s^2; the interpolator smooths the feed moves to stay within them ("auto").
                "accel": {a: 4000.0 for a in names}}
    if kind.startswith("rotary_"):
        # One ISO 230-7 error motion of the axis: radial (two directions, once and twice per turn), axial (once and
        # twice), tilt (two directions, once per turn), angular positioning (twice and three times per turn), each
        # with random phases and a slope per turn; um (radial, axial) or urad (tilt, angular).
        comp, a = kind.split("_")[1], kind[-1]
        radial1, radial2, axial, tilt1, tilt2, pos = {"X": ("Y", "Z", "X", "B", "C", "A"),
                                                       "Y": ("X", "Z", "Y", "A", "C", "B"),
                                                       "Z": ("X", "Y", "Z", "A", "B", "C")}[machine.axes[a].about]
        ph = rng.uniform(0, 2 * np.pi, 4)
        h = lambda k, amp, p: [k, amp * math.cos(p), amp * math.sin(p)]  # noqa: E731
        names, rows, slope = {
            "radial": ([f"E{radial1}{a}", f"E{radial2}{a}"], [[h(1, 1.5, ph[0]), h(2, 0.4, ph[1])],
                                                             [h(1, 1.2, ph[2]), h(2, 0.3, ph[3])]], 0.5),
            "axial": ([f"E{axial}{a}"], [[h(1, 1.0, ph[0]), h(2, 0.4, ph[1])]], 0.3),
            "tilt": ([f"E{tilt1}{a}", f"E{tilt2}{a}"], [[h(1, 4.0, ph[0])], [h(1, 3.0, ph[1])]], 1.0),
            "angular": ([f"E{pos}{a}"], [[h(2, 20.0, ph[0]), h(3, 6.0, ph[1])]], 10.0),
        }[comp]
        return {"components": dict(zip(names, rows)),
                "linear_per_turn": {n: float(rng.uniform(-slope, slope)) for n in names}}
    if kind.startswith("thermal_"):
        return {"channel": str(rng.choice(["ch3_um", "ch4_um", "ch5_um"])),
                "time_offset_s": float(rng.uniform(20_000.0, 60_000.0)), "amplitude_scale": 1.0}
    if kind == "force":
        d = rng.uniform(0.01, 0.03, 3)
        c = np.diag(d)
        c[0, 2] = c[2, 0] = float(rng.uniform(-0.004, 0.004))
        c[0, 1] = c[1, 0] = float(rng.uniform(-0.003, 0.003))
        return {"compliance_um_per_n": c.tolist()}
    if kind == "tool_deflection":
        return {"stick_out_mm": float(rng.uniform(35.0, 45.0))}
    if kind == "twin_parameters":
        loc = machine.location_names()
        pick = [str(x) for x in rng.choice(loc, size=min(3, len(loc)), replace=False)]
        return {"changes": {n: float(rng.normal(0.0, 15.0)) for n in pick}}
    if kind == "tool_wear":
        return {"vb_run_in_um": float(rng.uniform(15.0, 30.0)), "run_in_mm": float(rng.uniform(100.0, 400.0)),
                "vb_rate_um_per_m": float(rng.uniform(10.0, 30.0)), "clearance_deg": float(rng.uniform(6.0, 12.0))}
    if kind == "clamping_bend":
        return {"beam": str(rng.choice(["X", "Y"])), "span_mm": float(rng.uniform(90.0, 130.0)),
                "center_offset_mm": float(rng.uniform(-15.0, 15.0))}
    raise ValueError(f"unknown effect kind {kind!r}")


def effect_table(kind: str, draws: dict, s: float, machine) -> dict:
    """The EFFECTS tables of an effect at scale s (s = 1: the reference size of ``effect_draws``)."""
    if kind.startswith("backlash_"):
        return {"backlash": {kind[-1]: {"amplitude": draws["amplitude"] * s, "transition": draws["transition"],
                                        "form": draws["form"]}}}
    if kind == "servo":
        # The loop's steady lag is (1 - kff) / kv: scale it by s through kff, then (kff at 0) through kv.
        lag = s * (1.0 - draws["kff0"])
        kff = max(0.0, 1.0 - lag)
        kv = {a: v / max(1.0, lag) for a, v in draws["kv"].items()}
        return {"servo": {"kv_per_s": kv, "accel": draws["accel"], "kff": {a: kff for a in kv},
                          "aff": {a: draws["aff"] for a in kv}, "velocity_loop_ms": draws["tv_ms"],
                          "smoothing_ms": "auto"}}
    if kind.startswith("rotary_"):
        comps = {}
        for name, h in draws["components"].items():
            comps[name] = {"harmonics": [[k, c * s, sn * s] for k, c, sn in h]}
            if name in draws["linear_per_turn"]:
                comps[name]["linear_per_turn"] = draws["linear_per_turn"][name] * s
        return {"rotary_error_motion": {kind[-1]: comps}}
    if kind.startswith("thermal_"):
        return {"thermal": {"file": str(ROOT / SERIES), "channels": {kind[-1].upper(): draws["channel"]},
                            "time_scale": 60.0, "time_offset_s": draws["time_offset_s"],
                            "amplitude_scale": draws["amplitude_scale"] * s}}
    if kind == "force":
        return {"force": {"compliance_um_per_n": (np.asarray(draws["compliance_um_per_n"]) * s).tolist()}}
    if kind == "tool_deflection":
        return {"tool_deflection": {"stick_out_mm": draws["stick_out_mm"], "youngs_modulus_gpa": 600.0 / s}}
    if kind == "tool_wear":
        return {"tool_wear": {"vb_run_in_um": draws["vb_run_in_um"] * s, "run_in_mm": draws["run_in_mm"],
                              "vb_rate_um_per_m": draws["vb_rate_um_per_m"] * s,
                              "clearance_deg": draws["clearance_deg"]}}
    if kind == "clamping_bend":
        beam = [1.0, 0.0, 0.0] if draws["beam"] == "X" else [0.0, 1.0, 0.0]
        centre = [0.0, 0.0, -12.0]
        centre[0 if draws["beam"] == "X" else 1] += draws["center_offset_mm"]
        return {"clamping": {"form": "bending", "amplitude_um": 5.0 * s, "center": centre,
                             "span_mm": draws["span_mm"], "beam": beam, "direction": [0.0, 0.0, 1.0]}}
    if kind == "twin_parameters":
        return {}  # a change of the machine, not an effect table (see ``true_machine``)
    raise ValueError(kind)


def true_machine(machine, kinds, draws, scales):
    """The twin with the case's small changes of its own location errors (kind twin_parameters), else the twin."""
    if "twin_parameters" not in kinds:
        return machine
    names = machine.parameter_names()
    v = machine.parameter_values().copy()
    s = scales["twin_parameters"]
    for n, dv in draws["twin_parameters"]["changes"].items():
        v[names.index(n)] += dv * s
    return machine.with_parameters(v)


# What a fitted candidate should report, by parameter name: (kind, parameter) -> truth in the candidate's units, from
# the case's draws and scale. A parameter not named here has no known truth (not counted). Adjust with the names.
def truth_of(kind: str, draws: dict, s: float, param: str, unit: str, machine, axes=()):

    if kind.startswith("backlash_"):
        if param.lower() in (f"lost_motion_{kind[-1]}".lower(), f"backlash_{kind[-1]}".lower(), "lost_motion"):
            return draws["amplitude"] * s
        return None
    if kind == "servo":
        t = effect_table("servo", draws, s, machine)["servo"]
        # An axis' lag less the mean lag of the moving axes (lag_X_rel, the candidate's derived difference; ``axes``
        # the axes it averages): the loops' (1 - kff) / kv. The interpolator's smoothing delays every axis alike and
        # drops out (its delay is not seen on the part: 0.14 um rms of a 10 um effect on heldout7 case 38). The lags
        # themselves (lag_X) are reported as not determined and have no truth here (until 2026-11-28 they were
        # checked against loop + smoothing delay: the fits read 2 to 60 ms against 9 to 41, std covering 65 %).
        m = re.fullmatch(r"lag_([XYZABC])_rel", param)
        if m and axes:
            loop = {a: 1e3 * (1 - t["kff"][a]) / t["kv_per_s"][a] for a in axes}
            return loop[m.group(1)] - sum(loop.values()) / len(loop)
        return None
    if kind.startswith("rotary_"):
        a = kind[-1]
        pos = {"X": "A", "Y": "B", "Z": "C"}[machine.axes[a].about]
        m = re.fullmatch(rf"(?:(E[XYZABC]{a})_|{a}_)(\d)(cos|sin)", param, re.I)
        if not m:
            return None
        name = (m.group(1) or f"E{pos}{a}").upper()
        if name not in draws["components"]:
            return None  # a component of another case kind (a pair holds it)
        k = int(m.group(2))
        for kk, c, sn in draws["components"][name]:
            if kk == k:
                return (c if m.group(3).lower() == "cos" else sn) * s
        return 0.0
    if kind == "force":
        m = re.fullmatch(r"compliance_([XYZ])", param)
        if m:
            i = "XYZ".index(m.group(1))
            return draws["compliance_um_per_n"][i][i] * s
        return None
    if kind == "twin_parameters":
        if param.startswith("d") and param[1:] in draws["changes"]:
            return draws["changes"][param[1:]] * s
        return None
    if kind.startswith("thermal_"):
        m = re.search(r"at_(\d+(?:\.\d+)?)s", param)
        if m:
            from trueaxis.sim.effects import ThermalDrift

            t = effect_table(kind, draws, s, machine)["thermal"]
            td = ThermalDrift(t["file"], t["channels"], t["time_scale"], t["time_offset_s"], t["amplitude_scale"])
            return float(td.drift_um(np.array([float(m.group(1))]))[0, "XYZ".index(kind[-1].upper())])
        return None
    return None


# ------------------------------------------------------------------------------------------- worker side ----
# The force tables of the cutting model take ~1.5 s per call and depend only on the tool and the coefficients: cache
# them in each worker (the shop's code is not changed).
_TABLE_ARGS: dict = {}
_SETUPS: dict = {}


def _install_force_table_cache():
    from trueaxis.sim import cutting as _cutting

    if getattr(_cutting, "_bench_cached", False):
        return
    orig = _cutting._force_tables

    @functools.lru_cache(maxsize=16)
    def cached(key, d, z, mode):
        return orig(_TABLE_ARGS[key], d, z, mode)

    def tables(coeffs, d, z, mode, n_ae=256):
        key = repr(coeffs)
        _TABLE_ARGS[key] = coeffs
        return cached(key, float(d), float(z), str(mode))

    _cutting._force_tables = tables
    _cutting._bench_cached = True


def setup_for(setup: dict, points: int):
    """(twin, program, part JSON, noise-free base deviations) of a setup, cached per worker process."""
    key = (json.dumps(setup, sort_keys=True), points)
    if key not in _SETUPS:
        from trueaxis.workpiece.parts import Nas979Params, nas979_description
        from trueaxis.postproc.programs import nas979_program
        from trueaxis.machine import load_machine
        from trueaxis.sim.shop import simulate

        _install_force_table_cache()
        m = load_machine(ROOT / "fixtures/machines" / f"{setup['machine']}.toml")
        params = Nas979Params(**setup["cone"])
        prog = nas979_program(m, params, compensation="none", step_deg=2.0, chord_tol_um=None,
                              placement_mm=setup["placement_mm"])
        pj = nas979_description(params)
        base = simulate(prog.text, prog.machine, None, part="nas979", part_json=pj, points=points)
        _SETUPS[key] = (m, prog, pj, base.deviations_um)
    return _SETUPS[key]


def _merge(into: dict, more: dict) -> dict:
    """Deep merge of EFFECTS tables (two error motions of one axis, or two backlash axes, share a table)."""
    for k, v in more.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v
    return into


def _part_kwargs(part_json: dict) -> dict:
    """The cone's dimensions for ``run_diagnosis`` when it accepts them (``part_json``): the held-out cones are not
    the default size, and the twin's force model needs the stock's shape."""
    import inspect

    from trueaxis.diagnose.report import run_diagnosis

    return {"part_json": part_json} if "part_json" in inspect.signature(run_diagnosis).parameters else {}


def run_case(case: dict, points: int, noise_um: float = NOISE_UM, second: str = "") -> dict:
    """Cut, measure and diagnose one case; returns a plain dict (see ``score``). A failure of the harness or the
    shop is returned as a skipped case with its message (counted and printed), so that one case cannot stop a run.
    second : "placement": the same true machine cuts the cone a second time at another placement (``second_setup``)
    right after the first, each part probed with half the points, and both are diagnosed together (the separating
    measurement the reports ask for); "cone": the second cone also of a larger half-angle; "": one part."""
    try:
        return _run_case(case, points, noise_um, second)
    except Exception as exc:  # noqa: BLE001
        import traceback

        return {**{k: case[k] for k in ("set", "n", "kinds", "mag", "seed")},
                "setup": f"{case['setup']['machine']}@{tuple(case['setup']['placement_mm'])}",
                "skipped": f"HARNESS ERROR {type(exc).__name__}: {exc}", "harness_error": traceback.format_exc(),
                "t_case": 0.0}


#: Where the second part goes (``--second-placement``): another distance from the rotary table's axis, the first
#: machinable of these (a part off the axis goes to its centre; a centred one 50 mm off it).
SECOND_OFF_AXIS_MM = 25.0


#: ``--second cone``: the second part's cone half-angle this much larger (deg): the normal's mix of the radial and
#: the axial direction changes, which a radial and an axial error motion project on alike on one cone.
SECOND_HALF_ANGLE_DEG = 6.0


def second_setup(setup: dict, points: int, other_cone: bool = False) -> dict:
    """The setup of the second part: the same machine and cone (``other_cone``: a half-angle ``SECOND_HALF_ANGLE_DEG``
    larger) at another distance from the rotary axis, the first machinable placement of a fixed list
    (deterministic)."""
    x, y = setup["placement_mm"]
    if other_cone:
        from trueaxis.workpiece.parts import Nas979Params

        half = setup["cone"].get("half_angle_deg", Nas979Params().half_angle_deg)
        setup = {**setup, "cone": {**setup["cone"], "half_angle_deg": half + SECOND_HALF_ANGLE_DEG}}
    if math.hypot(x, y) >= SECOND_OFF_AXIS_MM:
        tries = [(0.0, 0.0), (x / 2.0, y / 2.0), (-x, -y)]
    else:
        tries = [(50.0, 0.0), (-50.0, 0.0), (0.0, 50.0), (0.0, -50.0)]
    for p in tries:
        s2 = {**setup, "placement_mm": p}
        try:
            setup_for(s2, points)
            return s2
        except Exception:  # noqa: BLE001 - not machinable there: the next one
            continue
    raise ValueError(f"no machinable second placement among {tries}")


def _run_case(case: dict, points: int, noise_um: float, second: str = "") -> dict:

    from trueaxis.diagnose.report import MeasuredCut, run_diagnosis_cuts
    from trueaxis.sim.effects import parse_effects
    from trueaxis.sim.shop import simulate

    t0 = time.perf_counter()
    if second:
        points = points // 2  # the same number of probe points over the two parts
    m, prog, pj, base = setup_for(case["setup"], points)
    placed = prog.machine
    kinds = case["kinds"]
    out = {k: case[k] for k in ("set", "n", "kinds", "mag", "seed")}
    out["setup"] = f"{case['setup']['machine']}@{tuple(case['setup']['placement_mm'])}" + (
        f" cone {case['setup']['cone']}" if case["setup"]["cone"] else "")
    out["expected"] = "+".join(sorted({EXPECTED[k] for k in kinds} - {"none"})) or "none"
    draws = {k: effect_draws(k, case["seed"], m) for k in kinds}

    def run(scales, noise=0.0, seed=0, cut_prog=None, t_start_s=0.0, cut_pj=None):
        """The true machine cuts ``cut_prog`` (default: the case's program; its part ``cut_pj``), starting
        ``t_start_s`` after the first program's start (the measured thermal series runs on)."""
        cut_prog, cut_pj = cut_prog or prog, cut_pj or pj
        tables: dict = {}
        for k in kinds:
            _merge(tables, effect_table(k, draws[k], scales[k], m))
        if t_start_s and "thermal" in tables:
            tables["thermal"]["time_offset_s"] += tables["thermal"]["time_scale"] * t_start_s
        true = true_machine(cut_prog.machine, kinds, draws, scales)
        eff = parse_effects(tables, machine=true) if tables else None
        return simulate(cut_prog.text, true, eff, part="nas979", part_json=cut_pj, points=points, noise_um=noise,
                        seed=seed, force_stride=50)

    def rms_of(res):
        return float(np.sqrt(np.nanmean((res.deviations_um - base) ** 2)))

    scales = {}
    try:
        for k in kinds:
            # Each effect alone at its reference size, then scaled to the target (a secant for the servo loop,
            # whose effect is not linear in the scale).
            target = case["mag"] * noise_um
            others = {kk: 0.0 for kk in kinds if kk != k}
            ref = rms_of(run({**others, k: 1.0}))
            if ref * MAX_SCALE < target:
                out.update(skipped=f"{k} not visible on this part ({ref:.3f} um rms at its reference size)",
                           t_case=time.perf_counter() - t0)
                return out
            s = target / ref
            if k == "servo":
                pts = [(1.0, ref)]
                for _ in range(3):
                    rms = rms_of(run({**others, k: s}))
                    if abs(rms / target - 1.0) < 0.05:
                        break
                    s0, r0 = pts[-1]
                    pts.append((s, rms))
                    p = np.log(rms / r0) / np.log(s / s0) if s != s0 and rms > 0 and r0 > 0 else 1.0
                    s *= (target / max(rms, 1e-9)) ** (1.0 / min(max(p, 0.5), 3.0))
            scales[k] = s
        r = run(scales, noise=noise_um, seed=1000 + case["n"] + case["seed"] % 1000)
        if "servo" in kinds:
            # The interpolator's smoothing (a causal moving average of M samples) delays a ramp by (M - 1) dt / 2 on
            # every axis, on top of the loop's (1 - kff) / kv: the tool's lag behind the program, which the
            # candidate's per-axis lag measures.
            sv = parse_effects(effect_table("servo", draws["servo"], scales["servo"], m), machine=placed).servo
            tr = r.trajectory
            q = sv.plan_rapids(np.asarray(tr.q, float), placed, float(tr.dt), tr)
            steps = int(round(sv.smoothing_s(q, placed, float(tr.dt), tr) / float(tr.dt)))
            draws["servo"]["smoothing_delay_s"] = max(steps - 1, 0) * float(tr.dt) / 2.0
    except ValueError as exc:
        out.update(skipped=f"the shop refuses the scaled effect: {exc}", t_case=time.perf_counter() - t0)
        return out
    cut = np.isfinite(r.deviations_um)
    out["effect_rms_um"] = float(np.sqrt(np.mean((r.deviations_um - base)[cut] ** 2))) if kinds else 0.0
    out["scales"] = scales
    if out["effect_rms_um"] > 3.0 * case["mag"] * noise_um * max(1, len(kinds)):
        # Scaled to the target the effect did not stay near it (an effect far from linear in its scale): not a case.
        out.update(skipped=f"scaled to {case['mag']:.0f}x it moves the surface by {out['effect_rms_um']:.1f} um rms",
                   t_case=time.perf_counter() - t0)
        return out
    cuts = [MeasuredCut(r.measured[cut], r.normals[cut], prog.text)]
    if second == "planned":
        # The product plans the second part from the first one's diagnosis (``trueaxis.diagnose.next_part``);
        # without a plan (a confident verdict, or no placement that separates) the fixed rule's placement.
        from trueaxis.diagnose.next_part import plan_next_part

        d1, st1 = run_diagnosis_cuts(cuts, "nas979", m, **_part_kwargs(pj))
        plan = plan_next_part(d1, st1, m, "nas979", pj, prog.text, want_force=st1.has_force)
        out["plan"] = None if plan is None else {"placement_mm": plan.placement_mm, "z_here": plan.z_here,
                                                 "z_next": plan.z_next}
        setup_b = ({**case["setup"], "placement_mm": tuple(plan.placement_mm)} if plan is not None
                   and plan.placement_mm is not None else second_setup(case["setup"], points))
        setup_for(setup_b, points)
    if second:
        if second != "planned":
            setup_b = second_setup(case["setup"], points, other_cone=second == "cone")
        _, prog_b, pj_b, _ = setup_for(setup_b, points)
        t_b = float(r.trajectory.t[-1])
        r_b = run(scales, noise=noise_um, seed=2000 + case["n"] + case["seed"] % 1000, cut_prog=prog_b,
                  t_start_s=t_b, cut_pj=pj_b)
        cut_b = np.isfinite(r_b.deviations_um)
        cuts.append(MeasuredCut(r_b.measured[cut_b], r_b.normals[cut_b], prog_b.text, part_json=pj_b))
        out["setup"] += f" + {tuple(setup_b['placement_mm'])}" + (f" cone {setup_b['cone']}" if second == "cone"
                                                                   else "")
    t1 = time.perf_counter()
    try:
        # The second part is cut right after the first (the shop's clock: t_start_s = the first cut's end).
        diag, _ = run_diagnosis_cuts(cuts, "nas979", m, **_part_kwargs(pj),
                                     pauses_s=[0.0] * (len(cuts) - 1) if len(cuts) > 1 else None)
    except Exception as exc:  # a crash of the diagnosis is a wrong answer, reported with its message
        out.update(answer="ERROR", error=f"{type(exc).__name__}: {exc}", conf=0.0, t_sim=t1 - t0,
                   t_diag=time.perf_counter() - t1, t_case=time.perf_counter() - t0)
        return out
    t2 = time.perf_counter()
    answer = "+".join(sorted(normalise(c) for c in diag.chosen)) or "none"
    basis = {k: (v if isinstance(v, (str, type(None))) else float(v)) for k, v in diag.confidence_basis.items()
             if isinstance(v, (str, int, float, type(None)))}
    out.update(answer=answer, raw_answer=list(diag.chosen), conf=float(diag.confidence),
               alternatives=list(diag.alternatives), verdict=diag.verdict, confidence_basis=basis,
               closest=[{k: c[k] for k in ("effect", "explained_share_above_noise", "why_not")} for c in diag.closest],
               fits=[{"name": f.name, "share": float(f.explained_share), "z": float(f.z), "n": int(f.n_parameters),
                      "significant": bool(f.significant), "plausible": bool(f.plausible), "explains": bool(f.explains),
                      "spline_held": bool(f.extra.get("not_beyond_constrained", False))}
                     for f in sorted(diag.fits + diag.pairs, key=lambda f: -f.gain_um2)[:10]],
               shrink=float(diag.shrink_above_noise), shrink_raw=float(diag.shrink_raw),
               before=dict(diag.gap_before), after=dict(diag.gap_after), sigma=float(diag.noise_um),
               t_sim=t1 - t0, t_diag=t2 - t1, t_case=time.perf_counter() - t0)
    # Parameters against the truth (by name, see ``truth_of``).
    cover, known = [], 0
    f = diag.chosen_fit
    if f is not None and out["answer"] == out["expected"]:
        # The fitted parameters, and the derived ones the candidate reports (per-axis servo lags, ms).
        derived = [(d["name"], d.get("unit", ""), d["value"], d["std"]) for d in (f.extra or {}).get("derived", [])
                   if d.get("determined", True)]
        # the axes a servo lag difference averages over: those with lags in the fit
        lag_axes = sorted({x.split("_")[1] for x in f.parameters if re.fullmatch(r"lag_[XYZABC]_\d+ms", x)})
        for name, unit, v, sd in [*zip(f.parameters, f.units, f.value, f.std), *derived]:
            for k in kinds:
                t = truth_of(k, draws[k], scales.get(k, 1.0), name, unit, m, lag_axes)
                if t is not None:
                    known += 1
                    cover.append({"name": name, "unit": unit, "value": float(v), "std": float(sd), "truth": float(t),
                                  "covered": bool(abs(v - t) <= 2 * sd)})
                    break
        out["parameters"] = [dict(name=n, unit=u, value=float(v), std=float(sd))
                             for n, u, v, sd in zip(f.parameters, f.units, f.value, f.std)]
    out["truth_checks"] = cover
    if kinds:  # the noise-free cuts: can the part tell the effect from the candidates at all?
        clean = [(run(scales), prog.text, pj)]
        if second:
            clean.append((run(scales, cut_prog=prog_b, t_start_s=t_b, cut_pj=pj_b), prog_b.text, pj_b))
        if out["expected"] != "none":
            out["identifiable"] = identifiability(clean, m, out["expected"], noise_um)
        else:  # an effect outside the library
            out["distinguishable"] = distinguishability(clean, m, noise_um)
    return out


def _diagnose_clean(clean, m, noise_um: float):
    """(diagnosis, state) of the noise-free cuts ``clean`` ([(shop result, program text, part description)], one per
    part, cut one after another without a pause), as the diagnosis reads measured ones."""
    from trueaxis.diagnose.report import MeasuredCut, run_diagnosis_cuts

    cuts = [MeasuredCut(c.measured[np.isfinite(c.deviations_um)], c.normals[np.isfinite(c.deviations_um)], text,
                        part_json=pj) for c, text, pj in clean]
    return run_diagnosis_cuts(cuts, "nas979", m, noise_um=noise_um,
                              pauses_s=[0.0] * (len(cuts) - 1) if len(cuts) > 1 else None)


#: A rival ties with the true effect's candidate when the paired z its held-out advantage is expected to reach at
#: the probe noise stays below this: no rule on this part can then pick the truth reliably.
Z_IDENTIFIABLE = 3.0


def identifiability(clean, m, expected: str, noise_um: float) -> dict:
    """Can this part tell the true effect from the other candidates at all? On the noise-free cuts of the same
    machine (``clean``: [(shop result, program text, part description)], one per part), the candidate (or pair) of
    the expected answer and every other plausible candidate and pair are fitted (held out, as the diagnosis fits
    them); a rival whose noise-free held-out residual the probe noise cannot separate from the truth's -- expected
    paired z of the truth's advantage

        z = sqrt(N) (ms_rival - ms_truth) / (2 sigma rms(pred_truth - pred_rival))

    below ``Z_IDENTIFIABLE`` -- makes the case not identifiable on this part: any rule choosing among the
    candidates is a coin toss there; so does a truth whose own fit is not plausible. The diagnosis' own rules play no
    part in this (only its candidates and fits)."""
    from trueaxis.diagnose.analysis import fit_candidate, make_folds
    from trueaxis.diagnose.candidates import LIBRARY, build_all

    diag, state = _diagnose_clean(clean, m, noise_um)
    g = state.gap_um
    want = sorted(expected.split("+"))
    fits = diag.fits + diag.pairs
    effects = lambda f: sorted({normalise(x) for x in f.members})  # noqa: E731
    truth = [f for f in fits if effects(f) == want]
    if not truth:
        cands, _ = build_all(LIBRARY, state)
        by = {normalise(c.name): c for c in cands if not c.name.startswith("thermal_spline_")}
        if not all(w in by for w in want):
            return {"identifiable": None, "why": "the expected candidate does not apply to this part"}
        truth = [fit_candidate([by[w] for w in want], g, make_folds(state, diag.split))]
    t = max(truth, key=lambda f: f.gain_um2)
    ms_t = float(np.mean((g - t.held_out_pred_um) ** 2))
    worst = (math.inf, None)
    for f in fits:
        if effects(f) == want or not f.plausible:
            continue
        ms_r = float(np.mean((g - f.held_out_pred_um) ** 2))
        sep = float(np.sqrt(np.mean((t.held_out_pred_um - f.held_out_pred_um) ** 2)))
        z = math.sqrt(g.size) * (ms_r - ms_t) / max(2.0 * noise_um * sep, 1e-12)
        if z < worst[0]:
            worst = (z, f.name)
    # The truth's own fit must be plausible too: one that runs into its bounds on the noise-free cut (two error
    # motions of one axis whose columns alias on a round part) can be no verdict under any rule.
    return {"identifiable": bool(worst[0] >= Z_IDENTIFIABLE and t.plausible), "z_truth_over_closest_rival": worst[0],
            "closest_rival": worst[1], "truth_plausible": bool(t.plausible)}


def distinguishability(clean, m, noise_um: float) -> dict:
    """Can this part tell an effect outside the library from every candidate? On the noise-free cuts (``clean``, as
    in ``identifiability``), each plausible candidate and pair is fitted as the diagnosis fits them; one whose
    held-out residual ms_r the probe noise would not show -- expected z of the residual above the noise,
    sqrt(N / 2) ms_r / sigma^2 (the chi-square test of a mean square of N points against sigma^2), below
    ``Z_IDENTIFIABLE`` -- reproduces the effect within the noise, and no rule can answer "none of the candidates"
    there (a clamped part's spring-back on a cone cut with C turning is a function of the part's angle, as the C
    axis' error motions are). The diagnosis' own rules play no part in this."""
    diag, state = _diagnose_clean(clean, m, noise_um)
    g = state.gap_um
    best = (math.inf, None)
    for f in diag.fits + diag.pairs:
        if not f.plausible:
            continue
        z = math.sqrt(g.size / 2.0) * float(np.mean((g - f.held_out_pred_um) ** 2)) / noise_um**2
        if z < best[0]:
            best = (z, f.name)
    return {"distinguishable": bool(best[0] >= Z_IDENTIFIABLE), "z_residual_of_closest": best[0],
            "closest": best[1]}


def identifiable(r: dict) -> bool | None:
    """Whether a scored case is identifiable on its part (None: not judged). Runs before 2026-11-28 (seventh session)
    stored the rivals' test alone: their truth_plausible is applied here, so that their rescores read alike."""
    idf = r.get("identifiable") or {}
    if idf.get("identifiable") is None:
        return None
    return bool(idf["identifiable"] and idf.get("truth_plausible", True))


# ------------------------------------------------------------------------------------------------- scoring ----
def share(xs):
    xs = list(xs)
    return (float(np.mean(xs)) if xs else float("nan")), len(xs)


def score(rows: list[dict], title: str) -> dict:
    """Print and return the figures of the issue's "Done when" for these rows."""
    done = [r for r in rows if "answer" in r]
    skipped = [r for r in rows if "skipped" in r]
    right = lambda r: r["answer"] == r["expected"]  # noqa: E731
    lib = [r for r in done if r["kinds"] and r["expected"] != "none"]
    strong = [r for r in lib if r["mag"] >= 3.0]
    weak = [r for r in lib if r["mag"] < 3.0]
    controls = [r for r in done if not r["kinds"]]
    ool = [r for r in done if r["kinds"] and r["expected"] == "none"]
    hi = [r for r in done if r["conf"] >= 0.7]
    strong_right = [r for r in strong if right(r)]
    errors = [r for r in rows if "harness_error" in r]
    fig = {
        "cases": len(rows), "run": len(done), "skipped": len(skipped), "harness_errors": len(errors),
        "strict_attribution_3x": share(right(r) for r in strong),
        "weak_1x_right": share(right(r) for r in weak),
        # Is the case answerable on one part at all (``identifiability``)? And how the rules do on each kind.
        "identifiable_3x": share(bool(identifiable(r)) for r in strong),
        "strict_attribution_3x_identifiable": share(right(r) for r in strong if identifiable(r)),
        "strict_attribution_3x_not_identifiable": share(right(r) for r in strong if identifiable(r) is False),
        "controls_flagged": share(r["answer"] != "none" for r in controls),
        "out_of_library_none": share(r["answer"] == "none" for r in ool),
        "out_of_library_distinguishable": share(bool((r.get("distinguishable") or {}).get("distinguishable"))
                                                for r in ool if r.get("distinguishable")),
        "out_of_library_none_distinguishable": share(r["answer"] == "none" for r in ool
                                                     if (r.get("distinguishable") or {}).get("distinguishable")),
        "right_among_conf_ge_0.7": share(right(r) for r in hi),
        "right_3x_with_conf_ge_0.7": share(r["conf"] >= 0.7 for r in strong_right),
        "median_shrink_above_noise_right_3x": (float(np.median([r["shrink"] for r in strong_right]))
                                               if strong_right else float("nan"), len(strong_right)),
        "median_shrink_above_noise_all_3x": (float(np.median([r["shrink"] for r in strong]))
                                             if strong else float("nan"), len(strong)),
        "max_gap_not_worse_right": share(r["after"]["max"] <= r["before"]["max"] + 1e-9
                                         for r in done if right(r) and r["expected"] != "none"),
        "std_covers_truth_right": share(all(c["covered"] for c in r["truth_checks"])
                                        for r in done if right(r) and r.get("truth_checks")),
        "right_without_known_truth": sum(1 for r in done if right(r) and r["expected"] != "none"
                                         and not r.get("truth_checks")),
        "median_time_per_case_s": float(np.median([r["t_case"] for r in done])) if done else float("nan"),
        "median_diagnose_s": float(np.median([r["t_diag"] for r in done])) if done else float("nan"),
    }
    # Calibration of the confidence: the share of right answers among the answers in each band of confidence.
    bands = [(0.0, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 0.9), (0.9, 1.01)]
    fig["calibration"] = [{"band": f"{lo:.1f}-{min(hi, 1.0):.1f}", "answers": len(b),
                           "right": sum(1 for r in b if right(r))}
                          for lo, hi in bands for b in [[r for r in done if lo <= r["conf"] < hi]]]
    pct = lambda v: "  n/a" if v[1] == 0 or not math.isfinite(v[0]) else f"{100 * v[0]:4.0f} % of {v[1]}"  # noqa
    print(f"\n==== {title}: {fig['run']} cases run, {fig['skipped']} skipped (effect not visible / refused"
          f"{'; ' + str(len(errors)) + ' HARNESS ERRORS' if errors else ''}) ====")
    print(f"strict attribution at >= 3x noise          {pct(fig['strict_attribution_3x'])}   (goal >= 90 %)")
    print(f"  identifiable on the part (>= 3x)          {pct(fig['identifiable_3x'])}   (no rival within "
          f"z {Z_IDENTIFIABLE:.0f} of the truth on the noise-free cut, the truth's fit plausible)")
    print(f"  strict attribution, identifiable cases    {pct(fig['strict_attribution_3x_identifiable'])}")
    print(f"  strict attribution, not identifiable      {pct(fig['strict_attribution_3x_not_identifiable'])}")
    print(f"1x noise cases named right                 {pct(fig['weak_1x_right'])}")
    print(f"controls flagged                           {pct(fig['controls_flagged'])}   (goal 0)")
    print(f"out-of-library answered 'none'             {pct(fig['out_of_library_none'])}   (goal 100 %)")
    if fig["out_of_library_distinguishable"][1]:
        print(f"  distinguishable on the part               {pct(fig['out_of_library_distinguishable'])}   (no "
              f"plausible candidate within the noise of it on the noise-free cut, z {Z_IDENTIFIABLE:.0f})")
        print(f"  'none', distinguishable cases             {pct(fig['out_of_library_none_distinguishable'])}")
    print(f"right among answers with confidence >= 0.7 {pct(fig['right_among_conf_ge_0.7'])}   (goal >= 95 %)")
    print(f"right answers >= 3x with confidence >= 0.7 {pct(fig['right_3x_with_conf_ge_0.7'])}   (goal >= 80 %)")
    v = fig["median_shrink_above_noise_right_3x"]
    w = fig["median_shrink_above_noise_all_3x"]
    print(f"median above-noise gap removed, right >= 3x {'n/a' if not v[1] else f'{100 * v[0]:.0f} %'} "
          f"(of {v[1]}; all >= 3x: {'n/a' if not w[1] else f'{100 * w[0]:.0f} %'})   (goal >= 80 %)")
    print(f"held-out max gap not worse, right answers  {pct(fig['max_gap_not_worse_right'])}   (goal >= 90 %)")
    print(f"std covers the truth (2 std), right answers {pct(fig['std_covers_truth_right'])}   (goal >= 90 %; "
          f"{fig['right_without_known_truth']} right answers had no parameter with a known truth)")
    print("confidence calibration (answers in each band of confidence: right / all): " + "; ".join(
        f"{c['band']}: {c['right']}/{c['answers']}" for c in fig["calibration"]))
    print(f"time per case (median): {fig['median_time_per_case_s']:.1f} s, of which diagnose "
          f"{fig['median_diagnose_s']:.1f} s")
    # Rows: the effects the true machine had (with the expected answer where it differs); columns: the answers,
    # numbered (legend below) to keep the table narrow.
    truth = lambda r: ("+".join(sorted(r["kinds"])) or "control") + (  # noqa: E731
        " (-> none)" if r["expected"] == "none" else "")
    labels_t = sorted({truth(r) for r in done})
    labels_a = sorted({r["answer"] for r in done}, key=lambda a: (a != "none", a))
    conf = Counter((truth(r), r["answer"]) for r in done)
    if done:
        w = max(len(x) for x in labels_t) + 1
        print("\nconfusion matrix (rows: effects of the true machine, expected answer in EXPECTED; '-> none' where "
              "no candidate describes them; columns: answer given, numbered)")
        print(" " * w + "".join(f"{i + 1:>4d}" for i in range(len(labels_a))))
        for t in labels_t:
            print(f"{t:{w}s}" + "".join(f"{conf[(t, a)] or '.':>4}" for a in labels_a))
        print("answers: " + "; ".join(f"{i + 1} {a}" for i, a in enumerate(labels_a)))
        fig["confusion"] = {t: {a: conf[(t, a)] for a in labels_a if conf[(t, a)]} for t in labels_t}
    return fig


def print_row(r: dict) -> None:
    tag = f"[{r['set'][:4]} {r['n']:3d}]"
    what = "+".join(r["kinds"]) or "control"
    if "skipped" in r:
        print(f"{tag} skip {what} {r['mag']:.0f}x on {r['setup']}: {r['skipped']}", flush=True)
        return
    ok = "ok " if r["answer"] == r["expected"] else "BAD"
    extra = f" error {r['error']}" if "error" in r else (
        f" conf {r['conf']:.2f} shrink {100 * r['shrink']:5.1f} % max {r['before']['max']:.1f}->{r['after']['max']:.1f}"
        f" um alts {','.join(r['alternatives']) or '-'}")
    print(f"{tag} {ok} {what:32s} {r['mag']:4.0f}x (rms {r.get('effect_rms_um', 0):5.2f} um) on {r['setup']} -> "
          f"{r['answer']}{extra} [{r['t_case']:.0f} s]", flush=True)


# ---------------------------------------------------------------------------------------------------- main ----
def select(cases: list[dict], n_cases: int, kinds: str, setup: int | None = None) -> list[dict]:
    if setup is not None:
        cases = [c for c in cases if c["setup"] == SETS[c["set"]]["setups"][setup]]
    if kinds:
        want = set(kinds.split(","))
        cases = [c for c in cases if want & (set(c["kinds"]) or {"none"})]
    if n_cases and n_cases < len(cases):
        idx = np.unique(np.linspace(0, len(cases) - 1, n_cases).round().astype(int))
        cases = [cases[i] for i in idx]
    return cases


def demo_timing(points: int = 8000) -> float:
    """Wall time (s) of ``run_diagnosis`` on a cone probed as ``make demo`` probes it (8000 points), in this process;
    the case: the tuning set's first setup with the B backlash at 3x the noise."""
    from trueaxis.diagnose.report import run_diagnosis
    from trueaxis.sim.effects import parse_effects
    from trueaxis.sim.shop import simulate

    setup = SETS["tuning"]["setups"][0]
    m, prog, pj, _ = setup_for(setup, points)
    tilt = next(a for a in m.axis_names if a in "AB")
    eff = parse_effects({"backlash": {tilt: {"amplitude": 60.0, "transition": 0.05}}}, machine=prog.machine)
    r = simulate(prog.text, prog.machine, eff, part="nas979", part_json=pj, points=points, noise_um=NOISE_UM, seed=7)
    cut = np.isfinite(r.deviations_um)
    t0 = time.perf_counter()
    diag, _ = run_diagnosis(r.measured[cut], r.normals[cut], "nas979", m, prog.text, **_part_kwargs(pj))
    dt = time.perf_counter() - t0
    print(f"\ndiagnosis of a cone probed as make demo probes it ({int(cut.sum())} points, backlash_{tilt}): "
          f"{dt:.1f} s in one process (goal <= 60 s on 2 cores); answer {'+'.join(diag.chosen) or 'none'}")
    return dt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", default="tuning", help="tuning | heldout | heldout2 ... heldout9 | both (tuning "
                    "and heldout) | all "
                    "(every set), or a comma list")
    ap.add_argument("--cases", type=int, default=0, help="run this many cases per set, spread over the list (0 = all)")
    ap.add_argument("--kinds", default="", help="only cases holding one of these effect kinds (comma list; 'none' "
                    "for the controls)")
    ap.add_argument("--setup", type=int, default=None, help="only the cases of this setup (index in the set's "
                    "setups list)")
    ap.add_argument("--points", type=int, default=800, help="probe points per part (800)")
    ap.add_argument("--scheduler", default=None, help="address of a running Dask scheduler (default: a local cluster)")
    ap.add_argument("--workers", type=int, default=2, help="local cluster: worker processes (1 thread each)")
    ap.add_argument("--json", default=None, help="write every case's result to this JSON file")
    ap.add_argument("--list", action="store_true", help="print the case list and stop")
    ap.add_argument("--demo-timing", action="store_true", help="also time one diagnosis at the demo's 8000 points")
    ap.add_argument("--rescore", default=None, help="print the scores of a --json file of an earlier run and stop")
    ap.add_argument("--second", choices=["placement", "cone", "planned"], default="", help="each case cuts the cone "
                    "twice, the second time at another distance from the rotary axis (cone: and a larger half-angle; "
                    "planned: where the first part's diagnosis plans it, trueaxis.diagnose.next_part), half the "
                    "points on each, both diagnosed together")
    args = ap.parse_args(argv)
    if args.rescore:
        rows = json.loads(Path(args.rescore).read_text())["cases"]
        for s in dict.fromkeys(r["set"] for r in rows):
            score([r for r in rows if r["set"] == s], s)
        return 0
    sets = {"both": ("tuning", "heldout"), "all": tuple(SETS)}.get(args.set) or tuple(args.set.split(","))
    unknown = [x for x in sets if x not in SETS]
    if unknown:
        ap.error(f"--set: unknown {', '.join(unknown)} (known: {', '.join(SETS)}, both, all)")
    cases = [c for s in sets for c in select(build_cases(s), args.cases, args.kinds, args.setup)]
    if args.list:
        for c in cases:
            print(c["set"], c["n"], "+".join(c["kinds"]) or "control", f"{c['mag']:.0f}x", c["setup"])
        return 0
    t_all = time.perf_counter()
    from dask.distributed import Client, LocalCluster, as_completed

    # Worker processes: one BLAS thread each (two cores, two workers), this file importable on every worker.
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    os.environ["TRUEAXIS_ROOT"] = str(ROOT)
    os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "benchmarks"),
                                                *filter(None, [os.environ.get("PYTHONPATH")])])
    cluster = None
    if args.scheduler:
        client = Client(args.scheduler)
    else:
        cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    client.upload_file(__file__)
    import diagnose_sets as mod  # this file as a module, so that workers import it by name (and keep its caches)

    two = f" over two parts ({args.second}; {args.points // 2} points each)" if args.second else ""
    print(f"{len(cases)} cases ({', '.join(sets)}), {args.points} points{two}, noise {NOISE_UM} um, "
          f"scheduler {client.scheduler.address}", flush=True)
    futures = [client.submit(mod.run_case, c, args.points, NOISE_UM, args.second, pure=False)
               for c in cases]
    rows = []
    for fut in as_completed(futures):
        r = fut.result()
        rows.append(r)
        print_row(r)
    rows.sort(key=lambda r: (r["set"], r["n"]))
    figures = {s: score([r for r in rows if r["set"] == s], s) for s in sets}
    if len(sets) > 1:
        figures["all"] = score(rows, "all sets run together")
    print(f"\ntotal {time.perf_counter() - t_all:.0f} s on {len(client.scheduler_info()['workers'])} workers")
    client.close()
    if cluster is not None:
        cluster.close()
    if args.demo_timing:
        figures["demo_diagnose_s"] = demo_timing()
    if args.json:
        Path(args.json).write_text(json.dumps({"figures": figures, "cases": rows}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
