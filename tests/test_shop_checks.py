"""The virtual shop re-runs the papers' cutting tests: the slot test's ordering and the cone's typical roundness."""

from __future__ import annotations

import math

import pytest

from trueaxis.workpiece.parts import SlotBlockParams
from trueaxis.sim.experiments import cone_experiment, slot_experiment


@pytest.mark.slow
def test_slot_experiment_orders_none_geometric_comprehensive():
    # Two passes of 0.6 mm instead of five: the same machine, force model and compensation, a third of the time.
    r = slot_experiment(points=1500, params=SlotBlockParams(slot_depth=1.2))
    none, geo, comp = (s["contour_error_um"] for s in r["slots"])
    assert r["not_cut"] == 0 and all(s["points"] > 100 for s in r["slots"])
    assert r["force_max_n"] > 20.0  # the slots are cut under a real force (full-width slotting, C45)
    # The machine's geometric errors are several um over the slot (uncompensated); geometric compensation leaves the
    # force-induced part; comprehensive compensation removes most of that as well (the paper: 56 > 34 > 23 um).
    assert none > 5.0 and none > 4 * geo and geo > 1.5 * comp


def test_cone_on_a_typical_uncalibrated_machine_is_in_the_published_roundness_range():
    r = cone_experiment(points=6000)
    assert r["not_cut"] == 0
    for ring in r["roundness"]:
        # typical_error_magnitudes.md: circularity about 10-50 um before kinematic calibration.
        assert 10.0 < ring["minimum_zone_um"] <= ring["least_squares_um"] < 50.0
    # Second formulation of the cone-angle error: the slope of the rings' mean normal deviation along the generatrix
    # (the radius shrinks with height, so material added at the top means a smaller half angle).
    low, high = r["roundness"][0], r["roundness"][-1]
    alpha = math.radians(15.0)
    from_rings = -(high["mean_deviation_um"] - low["mean_deviation_um"]) * math.cos(alpha) / (
        high["height_mm"] - low["height_mm"]) * 1e3
    assert abs(r["half_angle_error_urad"]) > 20.0  # the typical errors do change the angle
    assert abs(r["half_angle_error_urad"] - from_rings) < 0.05 * abs(from_rings) + 2.0
