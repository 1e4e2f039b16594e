"""The CadQuery host: the parts as Workplane plugins, and docs/cadquery_example.py compensating G-code made from one."""

from __future__ import annotations

import re
import runpy
import warnings

import cadquery as cq
import numpy as np
import pytest

from conftest import ROOT
from post_checks import actual_points, distance_to_polyline, machine_rows, nominal_polyline
from trueaxis.machine import load_machine
from trueaxis.workpiece.parts import nas979_workplane, slot_block_workplane
from trueaxis.nc.gcode import parse_program
from trueaxis.postproc.hosts import cadquery as cq_host

EXAMPLE = ROOT / "docs" / "cadquery_example.py"


@pytest.fixture(scope="module")
def example():
    """The example module's run(): (part, machine, program, compensated, report)."""
    module = runpy.run_path(str(EXAMPLE), run_name="cadquery_example")
    return module["run"]()


def test_importing_the_host_registers_the_parts_as_workplane_methods():
    assert cq.Workplane.nas979 is nas979_workplane
    assert cq.Workplane.slotBlock is slot_block_workplane


def test_unregister_and_register_take_the_methods_away_and_back():
    cq_host.unregister()
    try:
        assert not hasattr(cq.Workplane, "nas979") and not hasattr(cq.Workplane, "slotBlock")
    finally:
        cq_host.register()
        cq_host.register()  # idempotent
    assert cq.Workplane.nas979 is nas979_workplane


def test_the_plugin_places_the_part_on_the_calling_workplane():
    plain = nas979_workplane().val().BoundingBox()
    moved = cq.Workplane("XY", origin=(100.0, -20.0, 5.0)).nas979().val().BoundingBox()
    np.testing.assert_allclose([moved.xmin, moved.ymin, moved.zmin, moved.xmax, moved.ymax, moved.zmax],
                               [plain.xmin + 100, plain.ymin - 20, plain.zmin + 5, plain.xmax + 100, plain.ymax - 20,
                                plain.zmax + 5], atol=1e-6)


def test_the_plugin_passes_overrides_to_the_part_parameters():
    block = cq.Workplane("XY").slotBlock(block_length_x=230.0, block_height_z=40.0).val().BoundingBox()
    assert (block.xlen, block.zlen) == (pytest.approx(230.0), pytest.approx(40.0))


def test_compensate_is_the_python_hook_of_the_package():
    from trueaxis.postproc import compensate
    from trueaxis.postproc.post import compensate as post_compensate

    assert cq_host.compensate is compensate is post_compensate


def test_example_program_runs_around_the_part(example):
    part, machine, program, _, _ = example
    bb = part.val().BoundingBox()
    prog = parse_program(program)
    # the tool centre stays the tool radius outside the part's outline (machine XY = part XY on this machine)
    feed = prog.motion == 1
    xy = prog.end[feed, :2]
    outside = np.maximum(np.maximum(bb.xmin - xy[:, 0], xy[:, 0] - bb.xmax),
                         np.maximum(bb.ymin - xy[:, 1], xy[:, 1] - bb.ymax))
    assert np.all(outside >= machine.tool.radius - 1e-9)


def test_example_compensated_program_lands_on_the_nominal_path(example):
    _, machine, program, compensated, report = example
    assert compensated != program and report["moves"] > 0
    actual, _, _ = actual_points(compensated, machine)
    nominal = nominal_polyline(parse_program(program), machine)
    d_um = distance_to_polyline(actual, nominal) * 1e3
    # as in test_post.py: written numbers at 5 decimals (0.005 um) and a solver at 0.01 um stay below 0.1 um
    assert d_um.max() < 0.1, d_um.max()
    # and the machine's errors were not negligible to begin with (the check is not trivially true)
    uncompensated, _, _ = actual_points(program, machine)
    assert distance_to_polyline(uncompensated, nominal).max() * 1e3 > 5.0


def test_example_script_writes_its_files(tmp_path):
    module = runpy.run_path(str(EXAMPLE), run_name="cadquery_example")
    assert module["main"](["-o", str(tmp_path)]) == 0
    for name in ("nas979.step", "nas979_contour.ngc", "nas979_contour_compensated.ngc"):
        assert (tmp_path / name).stat().st_size > 0


def test_example_script_runs_on_a_five_axis_machine_and_lands_on_the_nominal_pose(tmp_path, capsys):
    # --machine nmv1500dcg wrote its files, then died on the rotary axes' report (max_abs_urad, not max_abs_um);
    # its program never commanded B and C, which the post took at 0 with a warning (a QA pass)
    from trueaxis.machine import ErrorTwin
    from trueaxis.postproc.post import PostWarning

    module = runpy.run_path(str(EXAMPLE), run_name="cadquery_example")
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always", PostWarning)
        assert module["main"](["--machine", "nmv1500dcg", "-o", str(tmp_path)]) == 0
    assert not [w for w in said if "never commands" in str(w.message)]
    printed = capsys.readouterr().out
    corrections = re.search(r"largest corrections X (\S+) um, Y (\S+) um, Z (\S+) um, B (\S+) urad, C (\S+) urad\)",
                            printed)
    assert corrections, printed
    assert all(float(v) > 0.5 for v in corrections.groups()[:4])  # X Y Z (um) and B (urad) correct; C is held
    program = (tmp_path / "nas979_contour.ngc").read_text()
    assert program.splitlines()[3].endswith(" B0 C0")
    machine = load_machine(ROOT / "fixtures" / "machines" / "nmv1500dcg.toml")
    compensated = (tmp_path / "nas979_contour_compensated.ngc").read_text()
    actual, prog, _ = actual_points(compensated, machine)
    nominal = nominal_polyline(parse_program(program), machine)
    assert distance_to_polyline(actual, nominal).max() * 1e3 < 0.1  # as on the three-axis machine
    uncompensated, _, _ = actual_points(program, machine)
    assert distance_to_polyline(uncompensated, nominal).max() * 1e3 > 2.0
    # the tool axis (nominal: upright): its tilt about Y is corrected through B, to the B words' fifth decimal of a
    # degree (half of it: 0.087 urad) and the solver's 0.02 urad; its tilt about X is not reachable at B = 0, the
    # singular pose of a B-C table, where C is held (the report's singular blocks): it keeps its largest value
    twin = ErrorTwin(machine)
    before = twin.actual_pose(machine_rows(parse_program(program), machine)[0])[1]
    after = twin.actual_pose(machine_rows(prog, machine)[0])[1]
    assert np.abs(before[:, 0]).max() * 1e6 > 5.0
    assert np.abs(after[:, 0]).max() * 1e6 < 0.5e-5 * np.pi / 180 * 1e6 + 0.02
    assert np.abs(after[:, 1]).max() == pytest.approx(np.abs(before[:, 1]).max(), abs=0.01e-6)  # (split moves)


def test_the_hook_takes_the_arcs_and_output_mode_keywords():
    machine = load_machine(ROOT / "fixtures" / "machines" / "xh714.toml")
    program = (ROOT / "tests" / "data" / "post_arcs" / "inch_half_circle.ngc").read_text()
    fitted = cq_host.compensate(program, machine, arcs=True, offsets_zero=True)
    lines = cq_host.compensate(program, machine, arcs=False, offsets_zero=True)
    assert cq_host.compensate(program, machine, offsets_zero=True) == fitted  # on by default on a three-axis mill
    assert len(fitted.splitlines()) + 100 < len(lines.splitlines())
    with pytest.raises(ValueError, match="five-axis"):
        cq_host.compensate(program, machine, output_mode="tcp", offsets_zero=True)


def test_the_hook_takes_a_machine_file_or_a_fixture_short_name_as_the_command_line_does():
    # compensate(text, "xh714") failed with AttributeError: 'str' object has no attribute 'name' (a QA pass)
    xh714 = ROOT / "fixtures" / "machines" / "xh714.toml"
    program = "G21 G90\nG0 X0 Y0 Z-100\nG1 X50 Y20 F500\nM2\n"
    by_machine = cq_host.compensate(program, load_machine(xh714), offsets_zero=True)
    assert f"machine file {xh714} sha256" in by_machine and "G1 X50 Y20 F500" not in by_machine  # corrected
    for given in ("xh714", str(xh714), xh714):
        assert cq_host.compensate(program, given, offsets_zero=True) == by_machine, given
    with pytest.raises(FileNotFoundError, match=r"no machine file 'nothere' \(fixture machines: .*xh714"):
        cq_host.compensate(program, "nothere", offsets_zero=True)
    with pytest.raises(TypeError, match="machine: a Machine .*, a machine file's path or a fixture machine's short "
                                        "name .*; got dict"):
        cq_host.compensate(program, {"name": "xh714"}, offsets_zero=True)


def test_example_script_runs_without_a_warning_by_default_and_says_what_it_took(tmp_path, capsys):
    # A QA pass: the documented example warned "no work offset given" on its own default run. Its program is written
    # in machine coordinates, which it now tells the post (offsets_zero); the header says zero was taken as meant.
    from trueaxis.postproc.post import PostWarning

    module = runpy.run_path(str(EXAMPLE), run_name="cadquery_example")
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always", PostWarning)
        assert module["main"](["-o", str(tmp_path)]) == 0
    assert not [w for w in said if issubclass(w.category, PostWarning)], [str(w.message) for w in said]
    header = [ln for ln in (tmp_path / "nas979_contour_compensated.ngc").read_text().splitlines()
              if ln.startswith(("(trueaxis post: ", "(trueaxis setup: "))]
    assert "(trueaxis setup: G54 0 mm, from --offsets-zero)" in header, header
    assert f"out with {len(header)} header comments" in capsys.readouterr().out


def test_example_script_says_a_refusal_in_one_line(tmp_path, capsys):
    # A QA pass: --var with offsets that put the contour out of travel ended in a 20-line traceback, where the
    # docstring promises the post's one line (file:line: reason). Exit 3 and that line.
    from rs274_helpers import var_text

    (tmp_path / "far.var").write_text(var_text({1: [0.0, 0.0, 500.0, 0.0, 0.0, 0.0]}))
    module = runpy.run_path(str(EXAMPLE), run_name="cadquery_example")
    assert module["main"](["--var", str(tmp_path / "far.var"), "-o", str(tmp_path / "out")]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("nas979_contour.ngc:") and "outside its travel" in err[0], err
