"""The Part protocol (trueaxis.workpiece.part): every part module is found, satisfies the protocol and is the one place
that knows its part; nothing else branches on a part's name."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from trueaxis.postproc.programs import PROGRAMS
from trueaxis.workpiece.part import Part, get_part, load_part, part_names, parts
from trueaxis.workpiece.parts import cone_signed_distance

ROOT = Path(__file__).resolve().parents[1]

# Files that may still branch on a part's name: none (the inspection asks the Part); any file that starts fails.
STILL_BRANCHING: set[str] = set()
_BRANCH = re.compile(r"""(==|!=)\s*["'](nas979|slots)["']|["'](nas979|slots)["']\s*(==|!=)""")


def test_the_registry_finds_the_two_parts_each_satisfying_the_protocol():
    assert part_names() == ("nas979", "slots")
    for name, part in parts().items():
        assert isinstance(part, Part) and part.name == name
        assert part.description()["part"] == name
        assert isinstance(part.params_type(), part.params_type)


def test_every_part_has_an_nc_program():
    assert set(PROGRAMS) == set(part_names())


def test_an_unknown_part_is_refused_naming_the_known_ones():
    with pytest.raises(ValueError, match=r"unknown part 'cube'; known: nas979, slots"):
        get_part("cube")


def test_the_cone_probe_pattern_lies_on_the_cone_with_outward_normals():
    part = get_part("nas979")
    doc = load_part("nas979")
    pts, nrm = part.probe_pattern(doc, 500)
    cone = next(s for s in doc["surfaces"] if s["id"] == "cone")
    assert np.max(np.abs(cone_signed_distance(pts, cone))) < 1e-9
    # a step along the normal leaves the material (positive distance): the normal points outwards
    np.testing.assert_allclose(cone_signed_distance(pts + 1e-3 * nrm, cone), 1e-3, atol=1e-9)
    assert not part.material_mask(doc)(pts + np.array([0.0, 0.0, 100.0])).any()  # above the top: no material


@pytest.mark.parametrize("n_points", [60, 600, 2000, 4000, 8000])
def test_the_cone_probe_pattern_probes_the_parts_own_sections(n_points):
    """At 4000 points the rings fell 0.53 mm either side of the mid-height section, and the inspection's roundness
    there (within 0.5 mm of it) was never measured (QA pass): the ring nearest each roundness / diameter section is
    moved onto it, unless it is an end ring (the probed span stays); rings far apart stay as they were."""
    doc = load_part("nas979")
    pts, _ = get_part("nas979").probe_pattern(doc, n_points)
    cone = next(s for s in doc["surfaces"] if s["id"] == "cone")
    axis = np.asarray(cone["axis"]) / np.linalg.norm(cone["axis"])
    h = np.unique(np.round((pts - np.asarray(cone["base_center"])) @ axis, 9))
    sections = sorted({f["height"] for f in doc["features"] if "height" in f})
    assert sections == [2.0, 10.0, 18.0]
    assert abs(h[0] - 1.0) < 1e-9 and abs(h[-1] - 19.0) < 1e-9 and np.all(np.diff(h) > 0)
    regular = np.linspace(1.0, 19.0, h.size)
    for s_h in sections:
        k = int(np.argmin(np.abs(regular - s_h)))
        if 0 < k < h.size - 1:  # the nearest ring an inner one: on the section
            assert np.min(np.abs(h - s_h)) < 1e-9, (s_h, h)
    assert np.count_nonzero(np.abs(h - regular) > 1e-9) <= len(sections)  # no other ring moved
    if n_points >= 2000:  # every section within the inspection's 0.5 mm of a ring: all measured
        assert all(np.min(np.abs(h - s_h)) <= 0.5 for s_h in sections), h


def test_load_part_refuses_a_json_of_the_other_part():
    with pytest.raises(ValueError, match="part JSON is for 'slots', not 'nas979'"):
        load_part("nas979", load_part("slots"))


def test_no_module_outside_the_part_modules_branches_on_a_part_name():
    branching = set()
    for path in sorted((ROOT / "trueaxis").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith("trueaxis/workpiece/") or rel == "trueaxis/postproc/programs.py":
            continue
        if _BRANCH.search(path.read_text(encoding="utf-8")):
            branching.add(rel)
    assert branching <= STILL_BRANCHING, sorted(branching - STILL_BRANCHING)


@pytest.mark.parametrize("name", ["nas979", "slots"])
def test_each_part_s_bounding_box_holds_its_probe_pattern_and_its_mesh(name):
    part = get_part(name)
    doc = load_part(name)
    lo, hi = part.bbox(doc)
    pts, _ = part.probe_pattern(doc, 400)
    assert np.all(pts >= lo - 1e-9) and np.all(pts <= hi + 1e-9)
    mesh = part.mesh(doc)
    if mesh is not None:  # the box is tight: the mesh touches every face of it (to its chord error, 0.05 um)
        assert np.all(mesh.vertices >= lo - 1e-9) and np.all(mesh.vertices <= hi + 1e-9)
        np.testing.assert_allclose(mesh.vertices.min(axis=0), lo, rtol=0, atol=mesh.chord_error_mm)
        np.testing.assert_allclose(mesh.vertices.max(axis=0), hi, rtol=0, atol=mesh.chord_error_mm)


@pytest.mark.parametrize("name", ["nas979", "slots"])
def test_each_part_s_datums_name_surfaces_of_its_json_or_derived_from_it(name):
    part = get_part(name)
    doc = load_part(name)
    ids = {s["id"] for s in doc["surfaces"]} | {s["id"] for s in part.derived_surfaces(doc)}
    assert [label for label, _, _ in part.datums] == ["A", "B", "C"]
    for _, candidates, _ in part.datums:
        assert set(candidates) <= ids
    assert part.params_from(doc) == part.params_type()  # the JSON's parameters give back the defaults
