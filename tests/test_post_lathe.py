"""The post on a two-axis lathe: the tool tip lands on the nominal path in the XZ plane of its axes."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import MACHINES
from post_checks import actual_points, distance_to_polyline, nominal_polyline
from rs274_helpers import assert_rs274_reads_as_we_do
from trueaxis.machine import load_machine
from trueaxis.postproc.gcode import parse_program
from trueaxis.postproc.post import PostError, compensate
from trueaxis.postproc.solver import corrected_directions

# Facing, a shoulder and a 270 deg G18 arc (counter-clockwise seen from +Y: from -X about the centre round to -Z).
PROGRAM = """G18 G21 G90 G94
G0 X40 Z-5
G1 Z-50 F100
G1 X60
G3 X70 Z-60 I10 K0
G0 X90 Z-5
M30
"""


@pytest.fixture(scope="module")
def lathe():
    return load_machine(MACHINES / "lathe.toml")


def test_a_lathe_corrects_in_the_plane_of_its_axes(lathe):
    B = corrected_directions(lathe)
    np.testing.assert_allclose(B.T @ B, np.diag([1.0, 0.0, 1.0]), atol=1e-15)  # the projector onto XZ


def test_lathe_output_lands_on_the_nominal_path_in_xz(lathe, tmp_path):
    report = {}
    out = compensate(PROGRAM, lathe, "geometric", report=report)
    actual, _, _ = actual_points(out, lathe)
    nominal = nominal_polyline(parse_program(PROGRAM), lathe)
    xz = lambda p: p * np.array([1.0, 0.0, 1.0])  # noqa: E731 - the turned radius ignores Y to second order
    d_um = distance_to_polyline(xz(actual), xz(nominal)) * 1e3
    assert d_um.max() < 0.1, d_um.max()
    # The correction is not trivial: the typical errors move the tip by microns, and the arc's correction varies.
    assert max(v["max_abs_um"] for v in report["correction"].values()) > 1.0
    assert report["arcs_linearised"] == 1
    assert_rs274_reads_as_we_do(out, tmp_path, name="lathe.ngc")


def test_comprehensive_mode_on_a_lathe_without_milling_coefficients_is_refused(lathe):
    with pytest.raises(PostError, match="cutting"):
        compensate(PROGRAM, lathe, "comprehensive", conditions={"ap": 1, "ae": 1, "fz": 0.1})
