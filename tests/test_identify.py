"""Checks of the identification: contact sensitivities against the virtual shop, recovery of the parameters a part
sees, the identified machine file, and the closed loop (slow)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from conftest import MACHINES
from trueaxis.inspect.cloud import Cloud
from trueaxis.identify import (find_contacts, identify, nominal_tool_path, reference_parameters,
                               run_identification, sensitivity_matrix)
from trueaxis.loop import closed_loop, cone_deviation_um, error_free
from trueaxis.workpiece.parts import Nas979Params, cone_surface_points
from trueaxis.postproc.programs import nas979_program, placed_for
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.machine.machine_file import dump_machine, parse_machine
from trueaxis.sim.shop import load_part, simulate

NOISE_UM = 0.5


@pytest.fixture(scope="module")
def nmv():
    return load_machine(MACHINES / "nmv1500dcg.toml")


@pytest.fixture(scope="module")
def cone_program(nmv):
    """A reduced cone program (2 deg blocks refined to a 0.2 um chord error), posted for an error-free twin."""
    return nas979_program(error_free(nmv), compensation="none", step_deg=2.0, chord_tol_um=0.2)


def _with(machine, **values):
    names = machine.parameter_names()
    v = machine.parameter_values().copy()
    for k, x in values.items():
        v[names.index(k)] += x
    return machine.with_parameters(v)


# ------------------------------------------------------------------------------------------------- contacts ----
def test_contact_gap_is_what_a_perfect_machine_leaves(nmv, cone_program):
    # The gap of each point's contact instance, taken along the normal, is the deviation the virtual shop machines on
    # a perfect machine (the envelope of all instances): a few tenths of um of chord error here. The finishing pass
    # is found, not the semi-finishing one 100 um further out.
    cone = Nas979Params().cone_surface()
    pts, nrm = cone_surface_points(cone, [2.0, 10.0, 18.0], 120)
    path = nominal_tool_path(cone_program.text, cone_program.machine)
    c = find_contacts(pts, nrm, path, 5.0, 30.0)
    assert c.found.all() and not c.end_face.any()
    perfect = simulate(cone_program.text, cone_program.machine, part="nas979", probe=(pts, nrm)).deviations_um
    assert np.max(np.abs(perfect)) < 1.0
    assert np.max(np.abs(c.gap_um - perfect)) < 0.2
    # The lever is the height along the generatrix, h / cos(15 deg).
    np.testing.assert_allclose(c.lever_mm, np.repeat([2.0, 10.0, 18.0], 120) / np.cos(np.radians(15.0)), atol=0.05)


# --------------------------------------------------------------------------- sensitivities vs the virtual shop ----
@pytest.mark.parametrize("name, delta", [("XOC", 20.0), ("AOC", 60.0), ("C0Y", 200.0), ("EBB@-15", 100.0)])
def test_sensitivity_matches_finite_difference_of_the_virtual_shop(nmv, cone_program, name, delta):
    # Two formulations: the first-order contact sensitivity (twin Jacobian, lever along the tool, projection on the
    # normal) and the difference of two envelopes machined by the virtual shop with the parameter changed.
    cone = Nas979Params().cone_surface()
    pts, nrm = cone_surface_points(cone, [2.0, 10.0, 18.0], 60)
    base = dataclasses.replace(nmv, workpiece_origin=cone_program.machine.workpiece_origin)
    changed = _with(base, **{name: delta})
    d0 = simulate(cone_program.text, base, part="nas979", probe=(pts, nrm)).deviations_um
    d1 = simulate(cone_program.text, changed, part="nas979", probe=(pts, nrm)).deviations_um
    path = nominal_tool_path(cone_program.text, cone_program.machine)
    S, _ = sensitivity_matrix(nrm, find_contacts(pts, nrm, path, 5.0, 30.0), path, ErrorTwin(base))
    predicted = S[:, base.parameter_names().index(name)] * delta
    assert np.ptp(predicted) > 3.0  # the check is not vacuous: the change moves the surface by um
    # Second-order terms (delta^2 / R over the tool radius, the product with the other errors) stay under 0.1 um;
    # the rest is the envelope's discretisation.
    assert np.max(np.abs((d1 - d0) - predicted)) < 0.5


# ---------------------------------------------------------------------------------------- recovery and report ----
# Location errors the cone sees at this sampling (3000 points, 0.5 um noise), at typical sizes. XOB is not among
# them: the B line's X offset barely changes the cone at the small B angles of this program, and what it does
# change, XOC does too.
SEEN_TRUTH = {"ZOB": -15.0, "XOC": -22.0, "YOC": 30.0, "AOC": -40.0, "BOC": 60.0}


@pytest.fixture(scope="module")
def measured_cone(nmv):
    """A cone cut on a machine whose errors are location errors the cone sees (typical sizes), others zero,
    measured with 0.5 um probe noise; deviations from the analytic cone."""
    twin = error_free(nmv)
    prog = nas979_program(twin, compensation="none", step_deg=2.0, chord_tol_um=0.2)
    true = dataclasses.replace(_with(twin, **SEEN_TRUTH), workpiece_origin=prog.machine.workpiece_origin)
    res = simulate(prog.text, true, part="nas979", points=3000, noise_um=NOISE_UM, seed=11)
    ok = np.all(np.isfinite(res.measured), axis=1)
    pts, nrm = res.measured[ok], res.normals[ok]
    return prog, true, pts, nrm, cone_deviation_um(pts, load_part("nas979"))


def _check_recovered(result, truth_machine, k=3.0):
    truth = truth_machine.parameter_values()
    ident = np.nonzero(result.identified)[0]
    assert ident.size
    err = result.value[ident] - truth[ident]
    bad = [(result.names[i], result.value[i], truth[i], result.std[i]) for i, e in zip(ident, err)
           if abs(e) > k * result.std[i]]
    assert not bad, f"outside {k} sigma: {bad}"


def test_identification_recovers_what_the_cone_sees_within_three_sigma(measured_cone):
    prog, true, pts, nrm, dev = measured_cone
    result = identify(pts, nrm, dev, prog.text, prog.machine, parameters="location")
    names = result.names
    # With the set-up free, a change the data do not determine alone whose translation of the part the set-up hides
    # beyond a typical set-up error is held (its translation would reach the next part unchecked), and said so.
    for n in SEEN_TRUTH:
        if n != "ZOB":
            assert result.identified[names.index(n)] or n in result.hidden_by_alignment, f"{n} neither"
    for n, (change, hidden) in result.hidden_by_alignment.items():  # (XOC here: -21.8, truth -22, 22.9 um hidden)
        assert hidden > 5.0 and not result.identified[names.index(n)], (n, change, hidden)
    assert result.identified[names.index("AOC")] and result.hidden_by == "the part's free set-up offset"
    # ZOB moves this cone as a whole along Z (its effect on the part is a translation, to a hundredth of a um): one
    # cone in one placement cannot tell it from the part's set-up offset, which takes it (free, its accuracy not
    # given: ZOB is the set-up's, kept); it was written as a measured ZOB before.
    assert not result.identified[names.index("ZOB")] and result.taken_by_setup == ["ZOB"]
    # (its TZ was ZOB's -15 um; with XOC held, the set-up also takes XOC's translation of the tilted cone)
    # With the set-up known exactly (no set-up offset in the model) the part does identify it.
    known = identify(pts, nrm, dev, prog.text, prog.machine, parameters="location", setup_sigma_um=0.0)
    assert known.identified[names.index("ZOB")] and not known.setup_offset
    assert all(known.identified[names.index(n)] for n in SEEN_TRUTH) and not known.hidden_by_alignment
    # said on the terminal and in the report (a QA pass: nothing said what was assumed)
    assert known.setup_known and not result.setup_known
    assert "  set-up: known exactly, as given (--setup-sigma-um 0)" in "\n".join(known.verdict_lines())
    assert known.as_report()["setup_note"].startswith("known exactly") and result.as_report()["setup_note"] is None
    _check_recovered(known, true)
    _check_recovered(result, true)
    # The fit leaves the probe noise (0.5 um) and the first-order model's few tenths; with the set-up free, also the
    # form of the change held (XOC: 1.39 um left, said by the residual note as a kept parameter).
    assert known.residual_rms_um < 0.7 and result.residual_rms_um < 1.5
    rep = result.as_report()
    # Says what it cannot see: the C axis' zero-angle offset turns the cone about its own axis (almost invisible on
    # a surface of revolution), and nothing outside the considered set changes.
    assert {"COC", "XOB"} <= set(rep["not_identifiable"])
    assert rep["unseen_combinations_total"] >= 1
    assert np.all(result.value[~result.identified] == result.prior[~result.identified])
    p = {d["name"]: d for d in rep["parameters"]}
    assert set(p["YOC"]) >= {"value_um", "std_um"} and set(p["AOC"]) >= {"value_urad", "std_urad"}
    held = {d["name"]: d for d in rep["not_identifiable_detail"]}
    assert "XOC" not in p and held["XOC"]["category"] == "hidden_by_alignment"
    assert "the part's free set-up offset took out of the data" in held["XOC"]["reason"]
    assert rep["condition_number"] > rep["condition_number_identified"] >= 1.0


def test_robust_identification_ignores_outliers(measured_cone):
    prog, true, pts, nrm, dev = measured_cone
    spoiled = dev.copy()
    rng = np.random.default_rng(5)
    bad = rng.choice(dev.size, dev.size // 50, replace=False)
    spoiled[bad] += rng.choice([-1.0, 1.0], bad.size) * 40.0  # 2 % of the points 40 um off (dirt, burrs)
    robust = identify(pts, nrm, spoiled, prog.text, prog.machine, parameters="location", robust=True)
    _check_recovered(robust, true)
    plain = identify(pts, nrm, spoiled, prog.text, prog.machine, parameters="location")
    i = plain.names.index("AOC")
    assert abs(robust.value[i] - true.parameter_values()[i]) < abs(plain.value[i] - true.parameter_values()[i]) + 1.0


def test_alignment_makes_rigid_motions_unidentifiable(measured_cone):
    # After a best fit the part's rigid motions are gone from the deviations; the offsets of the B line move the
    # whole cone and must then be reported as not identifiable.
    prog, true, pts, nrm, dev = measured_cone
    free = identify(pts, nrm, dev, prog.text, prog.machine, parameters="location")
    aligned = identify(pts, nrm, dev, prog.text, prog.machine, parameters="location", alignment="rigid")
    assert aligned.identified.sum() < free.identified.sum()
    assert set(aligned.as_report()["alignment"]) >= {"TX_um", "RZ_urad"}


def test_bestfit_writes_no_change_whose_effect_the_alignment_hides(measured_cone):
    # A best fit takes every rigid motion of the part out of the deviations (on the cone, a move along its axis is
    # its size). A change whose effect a rigid motion reproduces is then fitted to nothing on that share, no held-out
    # point can check it, and the written twin applies it to the next part: the defect wrote XOC / YOC / BOC worth
    # 41 um RMS of rigid motion here (and a nas979 loop's next part came out 17 um undersize). The best fit,
    # linearised: the least-squares rigid motion of the deviations taken out, each point moved with it.
    prog, true, pts, nrm, dev = measured_cone
    rows = np.concatenate([nrm, 1e-3 * np.cross(pts, nrm)], axis=1)     # um per um of move, per urad of turn
    rigid = rows @ np.linalg.lstsq(rows, dev, rcond=None)[0]
    aligned = identify(pts - (rigid * 1e-3)[:, None] * nrm, nrm, dev - rigid, prog.text, prog.machine,
                       alignment="bestfit")
    change = aligned.value - aligned.prior
    path = nominal_tool_path(prog.text, prog.machine)
    contacts = find_contacts(pts - (dev * 1e-3)[:, None] * nrm, nrm, path, prog.machine.tool.radius,
                             prog.machine.tool.flute_length)
    S, _ = sensitivity_matrix(nrm, contacts, path, ErrorTwin(prog.machine))
    effect = S[contacts.found] @ change                                  # what the written changes do to the part
    hidden = rows[contacts.found] @ np.linalg.lstsq(rows[contacts.found], effect, rcond=None)[0]
    assert np.sqrt(np.mean(hidden**2)) <= 0.5 * aligned.noise_um + 1e-6
    # Not vacuous: the fit asked for the C line's offsets, each hiding tens of um, and held them, said why.
    assert {"XOC", "YOC"} <= set(aligned.hidden_by_alignment)
    assert min(aligned.hidden_by_alignment[k][1] for k in ("XOC", "YOC")) > 10.0
    assert not aligned.identified[[aligned.names.index(k) for k in ("XOC", "YOC")]].any()
    categories = {d["name"]: d["category"] for d in aligned.as_report()["not_identifiable_detail"]}
    assert categories["XOC"] == categories["YOC"] == "hidden_by_alignment"


def test_verdict_refuses_changes_the_alignment_hides():
    from trueaxis.identify import _verdict

    confirmed = {"points": 500, "confirmed": True}
    assert _verdict(2, 5.0, 5.0, 0.5, confirmed, 3.0)[0] == "accepted"
    status, reasons = _verdict(2, 5.0, 5.0, 0.5, confirmed, 3.0, hidden=(12.0, 0.25, []))
    assert status == "refused" and "12.00 um" in reasons[0] and "best-fit alignment hides" in reasons[0]


def test_reference_values_are_held(nmv):
    held = reference_parameters(nmv)
    assert "EXX@0" in held and "EYX.P0" in held and "EBB@0" in held
    assert not any(h.startswith("ECC") for h in held)  # Fourier series have no constant term


# ------------------------------------------------------------------------------------------------ machine file ----
@pytest.mark.parametrize("name", ["nmv1500dcg", "xh714", "headtable", "smartcnc500", "lathe"])
def test_machine_file_round_trip(name):
    m = load_machine(MACHINES / f"{name}.toml")
    text = dump_machine(m)
    back = parse_machine(text)
    assert back.parameter_names() == m.parameter_names()
    np.testing.assert_array_equal(back.parameter_values(), m.parameter_values())
    assert dump_machine(back) == text
    if m.loaded is not None:
        np.testing.assert_array_equal(back.with_parameters(back.parameter_values()).loaded_force_n, m.loaded_force_n)


def test_identified_machine_file_round_trip(tmp_path, nmv, measured_cone):
    prog, true, pts, nrm, dev = measured_cone
    twin_file = tmp_path / "twin.toml"
    twin_file.write_text(dump_machine(error_free(nmv)))
    program_file = tmp_path / "cone.ngc"
    program_file.write_text(prog.text)
    out = tmp_path / "identified.toml"
    report, result = run_identification(Cloud(pts, nrm, "cmm.ply"), dev, load_part("nas979"), machine=twin_file,
                                        program=program_file, write=out, parameters="location")
    assert result.verdict == "accepted" and report["written"] == str(out)
    written = load_machine(out)
    names = written.parameter_names()
    by_name = {p["name"]: p for p in report["parameters"]}
    for n, v in zip(names, written.parameter_values()):
        if n in by_name:
            assert v == pytest.approx(by_name[n].get("value_um", by_name[n].get("value_urad")), abs=1e-4)
        else:
            assert v == 0.0  # not identified: the twin's own value
    np.testing.assert_array_equal(parse_machine(dump_machine(written)).parameter_values(), written.parameter_values())
    np.testing.assert_allclose(written.workpiece_origin, nmv.workpiece_origin)  # the file's origin, not the program's


# --------------------------------------------------------------------------------------------- the closed loop ----
@pytest.mark.slow
@pytest.mark.parametrize("part, machine_file, options", [
    ("nas979", "nmv1500dcg.toml", {"step_deg": 2.0, "chord_tol_um": 0.2}),
    ("slots", "xh714.toml", {}),
])
def test_closed_loop_cuts_the_deviation_by_80_percent(part, machine_file, options):
    # The true machine: the fixture's typical error values (every one a twin parameter, no other effect); the shop
    # starts from an error-free twin, identifies once and cuts again. The virtual shop sets the part up exactly, and
    # says so (set-up known: no set-up offset). Told nothing, the identification leaves any translation of the part
    # to its set-up (free, the default) and the next part keeps the machine's share of it: the slot block at its one
    # depth (the squareness of Z, A0Z and B0Z, and the constant level of the axes' errors move it as a whole) 62 %
    # lower; the cone, whose C line offsets move it by tens of um, below (test_the_default_closed_loop...).
    true = load_machine(MACHINES / machine_file)
    result = closed_loop(true, part=part, points=3000, noise_um=NOISE_UM, program_options=options,
                         identify_options={"setup_sigma_um": 0.0})
    print(result.summary())
    assert result.before.metrics["rms_um"] > 10.0
    assert result.rms_reduction >= 0.8
    if part == "nas979":
        assert result.after.metrics["roundness_max_um"] < result.before.metrics["roundness_max_um"]
    # a written change whose value the part does not pin down alone (within 2 std of zero change) says so, in the
    # report and on the terminal: one term of a combination, not a measurement of that error
    ident = result.identification
    entries = ident.as_report()["parameters"]
    lines = [ln for ln in ident.verdict_lines() if " change " in ln]
    for e in entries:
        u = "um" if "change_um" in e else "urad"
        if abs(abs(e[f"change_{u}"]) - 2.0 * e[f"std_{u}"]) > 1e-3:  # (not on the edge, where rounding decides)
            assert e["determined_alone"] == (abs(e[f"change_{u}"]) > 2.0 * e[f"std_{u}"])
        said = [ln for ln in lines if ln.split()[0] == e["name"]]
        assert len(said) == 1 and ("not determined alone" in said[0]) == (not e["determined_alone"])


@pytest.mark.slow
def test_the_default_closed_loop_of_the_cone_leaves_the_translation_and_corrects_the_form():
    # The set-up's accuracy not given (the default), a translation of the cone is its set-up's: the machine's share
    # of it (the C line offsets move the cone by tens of um) stays on the next part, which is no worse; its form is
    # corrected (roundness 19.8 -> 2.6 um on 2026-11-28). With the set-up known (the test above) 95 % lower.
    true = load_machine(MACHINES / "nmv1500dcg.toml")
    result = closed_loop(true, part="nas979", points=3000, noise_um=NOISE_UM,
                         program_options={"step_deg": 2.0, "chord_tol_um": 0.2})
    print(result.summary())
    assert result.identification.accepted
    assert 0.3 < result.rms_reduction < 0.8  # better, not as good as with the set-up known
    before, after = result.before.metrics, result.after.metrics
    # (19.9 -> 2.6 um before the changes not determined alone were held for their unchecked translation, 2026-11-28;
    # 19.9 -> 9.3 um since, the part's RMS 35.7 -> 12 um where it was 20)
    assert after["roundness_max_um"] < 0.6 * before["roundness_max_um"]
    assert result.identification.setup_offset["prior_sigma_um"] is None
    # The changes' translation of this cone (the C line offsets), which the free set-up took out of the data, is
    # written unchecked: said (on the slot block cut under its force such changes made the next part 17 um RMS
    # instead of 9, without a word). Here it happens to be near the machine's own, and the next part is better.
    ident = result.identification
    assert ident.setup_hidden_rms_um > 10.0 and "no point checked it" in ident.setup_hidden_note
    assert any("warning: the changes move this part by" in line for line in ident.verdict_lines())


# ------------------------------------------------------------------------------- identification through the CLI ----
# The user's commands (trueaxis.cli.main, in process): program with the twin, cut and measure on a true machine,
# inspect --identify --write. The twin is the nmv1500dcg fixture; a reduced cone program (2 deg blocks, 0.2 um chords).
TWIN_FILE = MACHINES / "nmv1500dcg.toml"
CONE_ARGS = ("--step-deg", "2", "--chord-tol-um", "0.2")
# A true machine that differs from the twin: offsets of a few um, tilts of tens of urad, and XOB, which the cone
# barely sees (the identification must not pretend to know what it absorbs).
CHANGES = {"XOC": 3.0, "YOC": -4.0, "AOC": 30.0, "BOC": -20.0, "XOB": 5.0}


def _cli(*args) -> int:
    from trueaxis.cli import main

    return main([str(a) for a in args])


def _report(folder):
    import json

    return json.loads((folder / "report.json").read_text())["identification"]


def _html_sections(folder):
    """report.html cut in two: "top" (up to the first section after the summary, where the verdict box stands) and
    "identification" (its section)."""
    page = (folder / "report.html").read_text()
    start = page.index("<h2>Identification")
    return {"top": page[:page.index("<h2>", page.index("<h2>Summary") + 1)],
            "identification": page[start:page.index("<h2>", start + 1)]}


def _check_lists(rep, section):
    """The page's lists: parameters estimated but not significant are listed as such, not as "not identifiable",
    which holds only what the part cannot identify (not the held gauge values)."""
    import re

    unseen = re.search(r"Not identifiable from this part: ([^<]*)\.</p>", section).group(1).split(", ")
    assert rep["not_significant"], "the case has parameters estimated but not significant"
    for entry in rep["not_significant"]:
        assert entry["name"] not in unseen
        assert entry["name"] in re.search(r"Estimated, not significant[^<]*", section).group(0)
    detail = {d["name"]: d["reason"] for d in rep["not_identifiable_detail"]}
    assert unseen and all(not detail[name].startswith("held") for name in unseen)
    # Each kept parameter says why by category too (the list mixes them): the not-significant ones as such, the held
    # ones as held, and the counts add up to the list.
    category = {d["name"]: d["category"] for d in rep["not_identifiable_detail"]}
    assert all(category[e["name"]] == "not_significant" for e in rep["not_significant"])
    assert all((category[n] in ("gauge", "not_asked")) == detail[n].startswith("held") for n in category)
    counts = rep["not_identifiable_by_category"]
    assert sum(counts.values()) == len(rep["not_identifiable"]) and counts.get("not_significant") == len(
        rep["not_significant"])


def _written_values(path):
    m = load_machine(path)
    return dict(zip(m.parameter_names(), m.parameter_values()))


@pytest.fixture(scope="module")
def shop(tmp_path_factory):
    """Folder with the cone program compensated (geometric) by the twin, its cut on the twin itself (perfect.ply)
    and on the changed machine (changed.ply), 3000 points at 0.5 um noise."""
    d = tmp_path_factory.mktemp("shop")
    twin = load_machine(TWIN_FILE)
    (d / "true.toml").write_text(dump_machine(_with(twin, **CHANGES)))
    assert _cli("program", "nas979", "--machine", TWIN_FILE, "-o", d / "cone.ngc", *CONE_ARGS) == 0
    for name, true in (("perfect", TWIN_FILE), ("changed", d / "true.toml")):
        assert _cli("simulate", d / "cone.ngc", "--machine", true, "--part", "nas979", "-o", d / f"{name}.ply",
                    "--points", 3000, "--noise-um", NOISE_UM, "--seed", 3) == 0
    return d


@pytest.mark.parametrize("mode", ["geometric", "comprehensive", "none"])
def test_perfect_machine_keeps_the_twin_whatever_the_compensation(shop, tmp_path, capsys, mode):
    # The true machine is the twin: the part is what the twin predicts for the commanded axes (for a compensated
    # program, the nominal part), so the written twin must be the twin within 3 std and the residual not above the
    # deviation (the defect: AOC and BOC moved by 205 urad, residual 22.6 um, written without a word).
    prog = shop / "cone.ngc"
    if mode != "geometric":
        prog = tmp_path / f"cone_{mode}.ngc"
        assert _cli("program", "nas979", "--machine", TWIN_FILE, "-o", prog, "--compensate", mode, *CONE_ARGS) == 0
    cloud = shop / "perfect.ply" if mode == "geometric" else tmp_path / "perfect.ply"
    if mode != "geometric":
        assert _cli("simulate", prog, "--machine", TWIN_FILE, "--part", "nas979", "-o", cloud, "--points", 3000,
                    "--noise-um", NOISE_UM, "--seed", 4) == 0
    capsys.readouterr()
    out = tmp_path / "new.toml"
    code = _cli("inspect", cloud, "--part", "nas979", "--identify", "--machine", TWIN_FILE, "--program", prog,
                "--write", out, "-o", tmp_path / "rep")
    printed = capsys.readouterr().out
    assert code == 0, printed
    rep = _report(tmp_path / "rep")
    v = rep["verdict"]
    assert v["residual_after_rms_um"] <= v["deviation_rms_um"]
    assert v["residual_before_rms_um"] < 1.5 * NOISE_UM  # the model of the compensated part is right
    std = {p["name"]: p.get("std_um", p.get("std_urad")) for p in rep["parameters"]}
    before, after = _written_values(TWIN_FILE), _written_values(out)
    for name in before:
        assert abs(after[name] - before[name]) <= (3 * std[name] if name in std else 0.0), name
    # The verdict is on the terminal: status, residual before / after, and what the program said.
    assert "identification " in printed and "residual RMS" in printed and "program: " in printed
    if mode != "none":
        assert f"compensation={mode} by this twin" in printed


def test_changed_machine_is_identified_within_three_std_and_written(shop, tmp_path, capsys):
    out = tmp_path / "new.toml"
    code = _cli("inspect", shop / "changed.ply", "--part", "nas979", "--identify", "--machine", TWIN_FILE,
                "--program", shop / "cone.ngc", "--write", out, "-o", tmp_path / "rep")
    printed = capsys.readouterr().out
    assert code == 0, printed
    rep = _report(tmp_path / "rep")
    assert rep["verdict"]["status"] == "accepted" and rep["written"] == str(out)
    assert rep["verdict"]["heldout"]["confirmed"]
    # The user's file is edited in place: every comment of the twin's file is in the written one.
    comments = [line.split("#", 1)[1] for line in TWIN_FILE.read_text().splitlines() if "#" in line]
    text = out.read_text()
    assert rep["comments_kept"]
    assert comments and all(c in text for c in comments)
    assert rep["verdict"]["residual_after_rms_um"] < 1.5 * NOISE_UM < rep["verdict"]["deviation_rms_um"]
    page = _html_sections(tmp_path / "rep")
    assert "Identification ACCEPTED" in page["top"] and "<h3>Identified parameters</h3>" in page["identification"]
    _check_lists(rep, page["identification"])
    # the translation of this cone that the written changes carry and the free set-up hid: said, whatever its size
    assert rep["setup_hidden_rms_um"] > 0.0
    if rep["setup_hidden_note"]:
        assert "no point checked it" in page["top"] and "warning: the changes move this part" in printed
    truth, written = _written_values(shop / "true.toml"), _written_values(out)
    reported = {p["name"]: p for p in rep["parameters"]}
    assert {"AOC", "YOC"} <= set(reported)
    for name, p in reported.items():
        std = p.get("std_um", p.get("std_urad"))
        assert abs(written[name] - truth[name]) <= 3 * std, (name, written[name], truth[name], std)
        assert "ACCEPTED" in printed and name in printed



def test_write_into_the_report_folder_is_refused_before_any_work(shop, tmp_path, capsys):
    """`-o DIR` is replaced whole, so `--write DIR/x.toml` cannot stand: the identified twin was written into DIR,
    then the report refused DIR for holding a file trueaxis did not write there (exit 2, "nothing written", with
    x.toml written and no report). Refused at the output gate, before any work: exit 2, nothing written, an earlier
    report in DIR left as it was."""
    rep, out = tmp_path / "rep", tmp_path / "rep" / "x.toml"
    args = ("inspect", shop / "changed.ply", "--part", "nas979", "--identify", "--machine", TWIN_FILE, "--program",
            shop / "cone.ngc", "-o", rep)
    for nested in (out, tmp_path / "rep" / "sub" / ".." / "x.toml"):
        capsys.readouterr()
        assert _cli(*args, "--write", nested) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "lies inside -o" in err[0] and "replaced whole" in err[0]
        assert not rep.exists()
    assert _cli(*args) == 0  # a report there: a second refusal leaves it as it was
    before = sorted(p.name for p in rep.iterdir())
    assert _cli(*args, "--write", out) == 2
    assert sorted(p.name for p in rep.iterdir()) == before and not out.exists()
    assert _cli(*args, "--write", tmp_path / "x.toml") == 0 and (tmp_path / "x.toml").exists()  # beside it: fine


def test_the_clouds_own_normals_are_not_used_and_what_they_were_is_said(shop, tmp_path, capsys):
    """The identification projects the twin's error on the part's normals, along which the deviation is measured. A
    cloud's own normals were used as given (only those pointing inward flipped): scattered by 1.4 deg the verdict
    turned into a refusal, by 3.6 deg into "no change", exit 0 (QA pass). Now the points alone decide: every way the
    cloud's normals are given (all inward, a third inward, scattered by about 4 deg, a CMM's approach direction across
    the cone axis) gives the identification of the cloud without normals, and what they were is said."""
    from trueaxis.inspect.cloud import read_cloud, write_cloud_ply

    cloud = read_cloud(shop / "changed.ply")
    args = ("--part", "nas979", "--identify", "--machine", TWIN_FILE, "--program", shop / "cone.ngc")
    write_cloud_ply(tmp_path / "bare.ply", cloud.points)
    assert _cli("inspect", tmp_path / "bare.ply", *args, "-o", tmp_path / "rep") == 0
    reference = _report(tmp_path / "rep")
    assert reference["cloud_normals"] is None and reference["verdict"]["status"] == "accepted"
    rng = np.random.default_rng(3)
    n = cloud.normals
    scattered = n + rng.normal(0.0, 0.05, n.shape)  # about 4 deg
    across = n - np.outer(n @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0])  # the part's z dropped (the cone's axis is near z)
    every_third = np.where((np.arange(len(n)) % 3 == 0)[:, None], -n, n)
    for name, normals, inward, departed in (("inward", -n, len(n), 0), ("third", every_third, (len(n) + 2) // 3, 0),
                                            ("scattered", scattered, None, None), ("across", across, 0, None)):
        write_cloud_ply(tmp_path / f"{name}.ply", cloud.points, normals)
        capsys.readouterr()
        assert _cli("inspect", tmp_path / f"{name}.ply", *args, "-o", tmp_path / f"rep_{name}") == 0, name
        printed = capsys.readouterr().out
        rep = _report(tmp_path / f"rep_{name}")
        given = rep["cloud_normals"]
        assert given["given"] == len(n) and (inward is None or given["inward"] == inward), (name, given)
        assert departed is None or given["departed"] == departed, (name, given)
        if name == "scattered":
            assert 0 < given["departed"] < len(n) and 5.0 < given["largest_deg"] < 20.0, given
        if name == "across":  # (the cone's 15 deg half angle, tilted 10 deg)
            assert given["departed"] > 0.9 * len(n) and 20.0 < given["largest_deg"] < 30.0, given
        assert "normals are not used" in printed and "normals are not used" in rep["normals"]
        assert rep["points_used"] == reference["points_used"] and rep["verdict"] == reference["verdict"], name
        assert [p["name"] for p in rep["parameters"]] == [p["name"] for p in reference["parameters"]]
        for mine, theirs in zip(rep["parameters"], reference["parameters"]):
            assert mine.get("value_um", mine.get("value_urad")) == theirs.get("value_um", theirs.get("value_urad"))


def test_a_cloud_given_twice_identifies_the_same_twin_as_once(shop, tmp_path, capsys):
    """Exact repeats of a point carry no information, yet counted twice they doubled the apparent information: the
    QA's cone concatenated with itself changed the identified twin (AOC -28.2 -> -64.6 urad, YOC held, EXC.sin2 +9.1
    um taken). They are dropped by the reader: the same parameters and the same twin written, to round-off, and the
    warning says how many were dropped."""
    from trueaxis.inspect.cloud import read_cloud, write_cloud_ply

    cloud = read_cloud(shop / "changed.ply")
    n = len(cloud)
    write_cloud_ply(tmp_path / "twice.ply", np.vstack([cloud.points] * 2), np.vstack([cloud.normals] * 2))
    args = ("--part", "nas979", "--identify", "--machine", TWIN_FILE, "--program", shop / "cone.ngc")
    assert _cli("inspect", shop / "changed.ply", *args, "-o", tmp_path / "once", "--write", tmp_path / "once.toml") == 0
    capsys.readouterr()
    assert _cli("inspect", tmp_path / "twice.ply", *args, "-o", tmp_path / "twice", "--write",
                tmp_path / "twice.toml") == 0
    err = capsys.readouterr().err
    once, twice = _report(tmp_path / "once"), _report(tmp_path / "twice")
    assert twice["points_used"] == once["points_used"] and twice["verdict"]["status"] == once["verdict"]["status"]
    assert [p["name"] for p in twice["parameters"]] == [p["name"] for p in once["parameters"]]
    for mine, theirs in zip(twice["parameters"], once["parameters"]):
        for key in ("value_um", "value_urad", "std_um", "std_urad"):
            if key in theirs:
                assert mine[key] == pytest.approx(theirs[key], rel=1e-9, abs=1e-9), (mine["name"], key)
    # the normals went through one more write and read (renormalised: 1 ulp), hence round-off, not bits
    np.testing.assert_allclose(load_machine(tmp_path / "twice.toml").parameter_values(),
                               load_machine(tmp_path / "once.toml").parameter_values(), rtol=1e-9, atol=1e-9)
    assert (f"warning: {n} of {2 * n} points repeat another point exactly (the same x, y, z): dropped, the figures "
            f"and any identification use the {n} distinct points") in err


def test_a_program_with_axes_the_twin_lacks_is_refused_with_exit_3(shop, tmp_path, capsys):
    """The cone's B-C program against a three-axis twin (xh714): a program the product refuses is exit 3 (README's
    exit table, as the diagnosis gives); it was exit 2, the usage status. One line, nothing written."""
    from trueaxis.cli import EXIT_REFUSED

    capsys.readouterr()
    code = _cli("inspect", shop / "changed.ply", "--part", "nas979", "--identify", "--machine", MACHINES / "xh714.toml",
                "--program", shop / "cone.ngc", "--write", tmp_path / "x.toml", "-o", tmp_path / "rep")
    err = capsys.readouterr().err.strip().splitlines()
    # (its header names the machine it was written for: that refusal comes first; without the header, its axes)
    assert code == EXIT_REFUSED and len(err) == 1 and "the program was written for the machine 'NMV 1500 DCG" in err[0]
    assert not (tmp_path / "rep").exists() and not (tmp_path / "x.toml").exists()
    text = (shop / "cone.ngc").read_text()
    (tmp_path / "cone.ngc").write_text("".join(ln for ln in text.splitlines(keepends=True)
                                               if not ln.startswith("(machine: ")))
    code = _cli("inspect", shop / "changed.ply", "--part", "nas979", "--identify", "--machine", MACHINES / "xh714.toml",
                "--program", tmp_path / "cone.ngc", "--write", tmp_path / "x.toml", "-o", tmp_path / "rep")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_REFUSED and len(err) == 1 and "moves axes B C" in err[0]
    assert not (tmp_path / "rep").exists() and not (tmp_path / "x.toml").exists()

def test_aliasing_of_a_poorly_seen_parameter_is_inside_the_std(nmv):
    # XOB (20 um) alone: the cone barely sees it, and what it does to the part the identified parameters absorb.
    # Their noise-only std would call the absorbed change real (> 3 noise std from the truth, zero); the reported std
    # (noise and the typical-size prior on the held parameters) covers it.
    prog = nas979_program(nmv, compensation="geometric", step_deg=2.0, chord_tol_um=0.2)
    true = dataclasses.replace(_with(nmv, XOB=20.0), workpiece_origin=prog.machine.workpiece_origin)
    res = simulate(prog.text, true, part="nas979", points=3000, noise_um=NOISE_UM, seed=1)
    ok = np.all(np.isfinite(res.measured), axis=1)
    pts, nrm = res.measured[ok], res.normals[ok]
    dev = cone_deviation_um(pts, load_part("nas979"))
    # What XOB does to this cone is mostly a translation of it, which the part's set-up offset takes: nothing is
    # written (the aliasing of the held parameters is checked below with the set-up known exactly).
    assert identify(pts, nrm, dev, prog.text, prog.machine).verdict == "no change"
    result = identify(pts, nrm, dev, prog.text, prog.machine, setup_sigma_um=0.0)
    ident = np.nonzero(result.identified)[0]
    assert not result.identified[result.names.index("XOB")] and ident.size
    change = result.value[ident] - true.parameter_values()[ident]
    assert np.any(np.abs(change) > 3 * result.std_noise[ident])       # the bias is real and beyond the noise
    assert np.all(np.abs(change) <= 3 * result.std[ident])            # and inside the reported std
    np.testing.assert_allclose(result.std[ident] ** 2, result.std_noise[ident] ** 2 + result.std_alias[ident] ** 2)
    assert "prior" in result.as_report()["std_method"]


def test_bestfit_alignment_is_fitted_as_nuisance_through_the_cli(shop, tmp_path, capsys):
    # --align bestfit removed the six rigid motions from the deviations: the identification fits them as nuisance
    # (reported under "alignment") and no parameter may take what a rigid motion of the part does.
    code = _cli("inspect", shop / "changed.ply", "--part", "nas979", "--align", "bestfit", "--identify",
                "--machine", TWIN_FILE, "--program", shop / "cone.ngc", "--write", tmp_path / "new.toml",
                "-o", tmp_path / "rep")
    assert code == 0, capsys.readouterr()
    rep = _report(tmp_path / "rep")
    assert rep["alignment_mode"] == "bestfit"
    assert sum(v is not None for k, v in rep["alignment"].items() if "_std_" not in k) >= 5
    truth, written = _written_values(shop / "true.toml"), _written_values(tmp_path / "new.toml")
    for p in rep["parameters"]:
        std = p.get("std_um", p.get("std_urad"))
        assert abs(written[p["name"]] - truth[p["name"]]) <= 3 * std, p
    # Not vacuous: the same best-fitted deviations identified without the nuisance columns (what the CLI did before:
    # alignment "none" whatever --align said) leave the part's rigid-motion-like share to the parameters, which
    # then move away from the truth.
    from trueaxis.inspect.report import inspect_cloud

    fitted = inspect_cloud(shop / "changed.ply", "nas979", align="bestfit")
    text = (shop / "cone.ngc").read_text()
    plain = identify(fitted.aligned, load_part_normals(fitted.aligned), fitted.deviation_um, text,
                     placed_for(load_machine(TWIN_FILE), text))
    ident = np.nonzero(plain.identified)[0]
    off = np.abs(plain.value[ident] - np.array([truth[plain.names[i]] for i in ident])) / plain.std_noise[ident]
    # refused, or every change held (the free set-up hides their translation), or written far from the truth
    assert plain.verdict == "refused" or ident.size == 0 or off.max() > 10.0


def load_part_normals(points):
    from trueaxis.inspect.deviation import nominal_normals

    return nominal_normals(points, load_part("nas979"))[0]


def test_datum_alignment_of_a_misplaced_cloud_gives_the_fixture_frame_result(shop, tmp_path):
    # The stock block's datum faces (not cut by the program) are probed with the cone; the cloud is then misplaced on
    # the CMM. --align datum brings it back to the part frame and removes no machine-error mode: the identification
    # must match the one of the cloud in the fixture frame with --align none.
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from test_inspect import block_faces, rigid

    from trueaxis.inspect.cloud import read_cloud, write_cloud_ply

    cone = read_cloud(shop / "changed.ply").points
    faces = block_faces(400, seed=2)
    faces = faces[faces[:, 2] < -faces[:, 0] * np.tan(np.radians(10.0)) - 0.5]   # the datum faces, not the top
    # The faces without probe noise: the 3-2-1 frame is then exact and the two identifications must agree to
    # rounding (with 0.5 um noise on the faces the frame moves the cone by ~0.1 um, which the parameters that
    # mimic a translation, XOC and EXX@100, amplify by a few).
    placed = np.vstack([cone, faces])
    rotation, translation = rigid([40e-6, -30e-6, 80e-6], [0.050, -0.030, 0.020])
    write_cloud_ply(tmp_path / "fixture.ply", placed)
    write_cloud_ply(tmp_path / "moved.ply", placed @ rotation.T + translation)
    reps = {}
    for name, cloud, align in (("fixture", "fixture", "none"), ("moved", "moved", "datum"),
                               ("unaligned", "moved", "none")):
        assert _cli("inspect", tmp_path / f"{cloud}.ply", "--part", "nas979", "--align", align, "--identify",
                    "--machine", TWIN_FILE, "--program", shop / "cone.ngc", "-o", tmp_path / f"rep_{name}") == 0
        reps[name] = {p["name"]: p for p in _report(tmp_path / f"rep_{name}")["parameters"]}
    assert _report(tmp_path / "rep_moved")["alignment_mode"] == "datum"
    assert _report(tmp_path / "rep_moved")["alignment"] == {}          # no nuisance: nothing the machine cut is moved
    assert set(reps["fixture"]) == set(reps["moved"]) and reps["fixture"]
    for name, p in reps["fixture"].items():
        u = "um" if "value_um" in p else "urad"
        assert abs(reps["moved"][name][f"value_{u}"] - p[f"value_{u}"]) < 0.01 * p[f"std_noise_{u}"] + 1e-3, name
    # Not vacuous: the misplaced cloud taken as it is (80 urad, 50 um off) gives another twin.
    a = reps["unaligned"].get("AOC", {"value_urad": 0.0})["value_urad"]
    assert abs(a - reps["fixture"]["AOC"]["value_urad"]) > 3 * reps["fixture"]["AOC"]["std_noise_urad"]


def test_a_fit_the_held_out_points_contradict_is_refused_and_nothing_written(shop, tmp_path, capsys, nmv):
    # Deviations that a parameter's pattern explains on the fitted blocks of the path and contradicts on the held-out
    # ones (XOC's sensitivity, +10 um on the fitted blocks, -10 um on the held-out): the fit is significant and
    # lowers the residual, the held-out points get worse, and --write refuses with one line and exit 3. The set-up is
    # said to be known exactly (--setup-sigma-um 0): XOC's pattern on the cone is mostly a translation of the part,
    # which a set-up offset would take (no change, nothing written either), and the check under test is the held-out
    # one.
    from trueaxis.cli import EXIT_REFUSED
    from trueaxis.inspect.cloud import read_cloud, write_cloud_ply
    from trueaxis.identify import ToolPath

    text = (shop / "cone.ngc").read_text()
    placed = placed_for(nmv, text, "nas979")
    cloud = read_cloud(shop / "perfect.ply")
    nrm = load_part_normals(cloud.points)
    path = nominal_tool_path(text, placed)
    twin = ErrorTwin(placed)
    tip, axis = twin.actual_pose(path.q)
    twin_path = ToolPath(path.q, tip, axis, path.line, path.t)
    c = find_contacts(cloud.points, nrm, twin_path, 5.0, 30.0)
    S, _ = sensitivity_matrix(nrm, c, twin_path, twin)
    uniq, inv = np.unique(c.sample, return_inverse=True)
    held = (((np.arange(uniq.size) * 20) // uniq.size)[inv] % 5) == 2     # identify's default held-out blocks
    pattern = 10.0 * S[:, placed.parameter_names().index("XOC")] * np.where(held, -1.0, 1.0)
    write_cloud_ply(tmp_path / "odd.ply", cloud.points + (pattern * 1e-3)[:, None] * nrm)
    out = tmp_path / "new.toml"
    code = _cli("inspect", tmp_path / "odd.ply", "--part", "nas979", "--identify", "--machine", TWIN_FILE,
                "--program", shop / "cone.ngc", "--write", out, "-o", tmp_path / "rep", "--setup-sigma-um", 0)
    captured = capsys.readouterr()
    assert code == EXIT_REFUSED and not out.exists()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "not written" in err[0] and "held-out" in err[0]
    assert "REFUSED" in captured.out
    rep = _report(tmp_path / "rep")
    assert rep["verdict"]["status"] == "refused" and rep["written"] is None
    assert any("held-out" in r for r in rep["verdict"]["reasons"])
    # the page says it too, at the top, and never calls the refused changes identified
    page = _html_sections(tmp_path / "rep")
    assert "Identification REFUSED" in page["top"] and "held-out points do not confirm" in page["top"]
    assert "Identified parameters" not in page["identification"]
    assert "Changes the refused fit proposed (not applied)" in page["identification"]
    _check_lists(rep, page["identification"])



def test_a_fit_the_held_out_check_cannot_try_is_never_accepted(shop, tmp_path, capsys):
    """Twelve points on one ring of the changed machine's cone: the fit is significant and explains them (27 um ->
    0.6 um), but none of them lies in a held-out block of the tool path, so the held-out check never ran; the fit was
    ACCEPTED with "heldout": {} and the twin written. Without its check it is refused: exit 3, nothing written, and
    the report says why."""
    from trueaxis.cli import EXIT_REFUSED

    assert _cli("simulate", shop / "cone.ngc", "--machine", shop / "true.toml", "--part", "nas979", "-o",
                tmp_path / "ring.ply", "--points", 12, "--noise-um", NOISE_UM, "--seed", 5) == 0
    capsys.readouterr()
    out = tmp_path / "new.toml"
    code = _cli("inspect", tmp_path / "ring.ply", "--part", "nas979", "--identify", "--machine", TWIN_FILE,
                "--program", shop / "cone.ngc", "--write", out, "-o", tmp_path / "rep")
    captured = capsys.readouterr()
    assert code == EXIT_REFUSED and not out.exists()
    assert "REFUSED" in captured.out and "held-out check could not run" in captured.err
    verdict = _report(tmp_path / "rep")["verdict"]
    assert verdict["status"] == "refused" and verdict["heldout"]["confirmed"] is False
    assert verdict["heldout"]["points"] < 10 and "held-out check could not run" in verdict["reasons"][0]
    assert verdict["residual_after_rms_um"] < verdict["residual_before_rms_um"]  # the fit itself looked good

@pytest.mark.slow
@pytest.mark.parametrize("part, fixture, changes, compensate, program_args", [
    ("nas979", "nmv1500dcg.toml", CHANGES, "geometric", CONE_ARGS),
    ("slots", "xh714.toml", {"C0Y": 25.0, "B0Z": -20.0, "A0Z": 15.0, "EXX@100": 3.0}, None, ()),
])
def test_users_closed_loop_converges_in_two_rounds(tmp_path, part, fixture, changes, compensate, program_args):
    # The lean version of benchmarks/bench_closed_loop.py: program with the twin, cut on a changed machine, inspect
    # --identify --write, program again with the written twin, cut again.
    from trueaxis.loop import user_loop

    (tmp_path / "true.toml").write_text(dump_machine(_with(load_machine(MACHINES / fixture), **changes)))
    # The slot block at one depth cannot tell A0Z and B0Z (15 and 20 urad: 4.5 and 6 um at its depth) from a set-up
    # offset of the part: the virtual shop sets it up exactly and the user says so (--setup-sigma-um 0); the cone's
    # small changes here are told apart from a free set-up (the default). See test_identify_setup.py for a set-up
    # that is not known.
    rounds = user_loop(tmp_path, part, MACHINES / fixture, tmp_path / "true.toml", rounds=2, compensate=compensate,
                       points=2000, noise_um=NOISE_UM, program_args=program_args,
                       inspect_args=("--setup-sigma-um", 0) if part == "slots" else ())
    first, second = rounds
    assert first.verdict == "accepted" and first.written and second.twin == first.written
    assert first.misfit_rms_um > 3 * NOISE_UM and first.residual_rms_um < 1.5 * NOISE_UM
    assert second.misfit_rms_um < 1.5 * NOISE_UM                  # the written twin explains the next part
    assert second.rms_um <= first.rms_um
    if part == "nas979":
        assert second.rms_um < 1.5 * NOISE_UM                     # compensated with the written twin: the nominal cone
        # the set-up free (the default): the misfit with the part's set-up offset fitted is reported beside
        assert second.misfit_placed_rms_um <= second.misfit_rms_um + 1e-9 and first.misfit_placed_rms_um is not None
    else:
        assert second.slots_rms_um["geometric"] < 1.5 * NOISE_UM < first.slots_rms_um["geometric"]
        assert abs(second.slots_rms_um["none"] - first.slots_rms_um["none"]) < 0.1  # slot 1 is never compensated


def test_foreign_program_posted_elsewhere_is_modelled_at_its_commanded_axes(shop, tmp_path, capsys):
    # A program from elsewhere: no trueaxis-setup comment, compensated by `trueaxis post` (as any post would do it).
    # The model needs only its commanded axes; the terminal says what was assumed.
    assert _cli("program", "nas979", "--machine", TWIN_FILE, "-o", tmp_path / "raw.ngc", "--compensate", "none",
                *CONE_ARGS) == 0
    raw = "\n".join(line for line in (tmp_path / "raw.ngc").read_text().splitlines()
                    if "trueaxis-setup" not in line and "compensation:" not in line) + "\n"
    (tmp_path / "foreign_raw.ngc").write_text(raw)
    assert _cli("post", tmp_path / "foreign_raw.ngc", "--machine", TWIN_FILE, "-o", tmp_path / "foreign.ngc") == 0
    assert "trueaxis-setup" not in (tmp_path / "foreign.ngc").read_text()
    assert _cli("simulate", tmp_path / "foreign.ngc", "--machine", shop / "true.toml", "--part", "nas979", "-o",
                tmp_path / "cmm.ply", "--points", 3000, "--noise-um", NOISE_UM, "--seed", 5) == 0
    capsys.readouterr()
    out = tmp_path / "new.toml"
    assert _cli("inspect", tmp_path / "cmm.ply", "--part", "nas979", "--identify", "--machine", TWIN_FILE,
                "--program", tmp_path / "foreign.ngc", "--write", out, "-o", tmp_path / "rep") == 0
    printed = capsys.readouterr().out
    # no setup comment, but the post's header says what it did (it was read as 'none' or unknown before)
    assert "compensation=geometric by this twin (its post header" in printed
    rep = _report(tmp_path / "rep")
    # where the part was assumed placed, in the words the diagnosis says it (programs.placement_assumed)
    origin = ", ".join(f"{v:g}" for v in load_machine(TWIN_FILE).workpiece_origin)
    assert rep["placement_assumed"] == ("the program has no trueaxis-setup comment: assumed the part at the machine "
                                        f"file's [workpiece] origin, {origin} mm in M (placement 0) and the machine "
                                        "file's tool, d 10 mm")
    assert f"\n  program: {rep['placement_assumed']}\n" in printed
    assert rep["verdict"]["status"] == "accepted" and rep["program_compensation"]["mode"] == "geometric"
    assert rep["verdict"]["residual_after_rms_um"] < 1.5 * NOISE_UM
    truth, written = _written_values(shop / "true.toml"), _written_values(out)
    for p in rep["parameters"]:
        assert abs(written[p["name"]] - truth[p["name"]]) <= 3 * p.get("std_um", p.get("std_urad")), p


def test_a_program_a_trueaxis_post_wrote_is_read_as_compensated_by_its_header():
    # The post kept the program's setup comment 'compensation=none', and the identification reported 'none' for a
    # program it had compensated (a QA pass). Its header says the mode and the machine file's digest.
    from trueaxis.identify import program_compensation
    from trueaxis.postproc.post import compensate

    twin = load_machine(MACHINES / "xh714.toml")
    text = "(trueaxis-setup: part=slots compensation=none)\nG21 G90\nG0 X10 Y10 Z-20\nG1 X20 F100\nM2\n"
    assert program_compensation(text, twin)["mode"] == "none"
    posted = compensate(text, twin, "geometric", offsets_zero=True)
    said = program_compensation(posted, twin)
    assert said["mode"] == "geometric" and said["posted"] and said["same_twin"] is True
    other = program_compensation(posted, load_machine(MACHINES / "nmv1500dcg.toml"))
    assert other["same_twin"] is False and "by another twin (its post header" in other["note"]
    # another twin: a warning besides the note (another round's program was accepted with twice the true errors,
    # the note read as information; QA pass); none for this twin's own program
    assert "make sure it is the program that cut this part" in other["warning"] and "warning" not in said


def test_a_program_written_for_another_machine_is_refused_and_no_twin_written(tmp_path, measured_cone):
    # A QA pass: an XH714 program identified with --machine nmv1500dcg was ACCEPTED and the NMV twin rewritten from a
    # part the NMV did not cut; post and simulate refuse such a program by its header. Refused here too, before any
    # work, naming both machines; nothing written.
    from trueaxis.postproc.post import PostError

    prog, true, pts, nrm, dev = measured_cone
    assert "(machine: NMV 1500 DCG" in prog.text
    program_file = tmp_path / "cone.ngc"
    program_file.write_text(prog.text)
    out = tmp_path / "identified.toml"
    with pytest.raises(PostError, match=r"the program was written for the machine 'NMV 1500 DCG layout \[B-C "
                                        r"tilting-rotary table\]', the twin given is 'Head-table"):
        run_identification(Cloud(pts, nrm, "cmm.ply"), dev, load_part("nas979"), machine=MACHINES / "headtable.toml",
                           program=program_file, write=out)
    assert not out.exists()


def test_an_identified_twins_note_says_what_its_figures_are(tmp_path, measured_cone):
    # A QA pass: the twin written from `machine nominal` kept "every error parameter zero" in its note after values
    # were written, and gave the fit's residual (the part's set-up offset fitted) as if it were the next part's RMS.
    from trueaxis.cli import main

    prog, true, pts, nrm, dev = measured_cone
    assert main(["machine", "nominal", "nmv1500dcg", "-o", str(tmp_path / "twin0.toml")]) == 0
    note0 = load_machine(tmp_path / "twin0.toml").note
    assert note0.startswith("written by trueaxis machine nominal as the error-free twin of NMV 1500 DCG") and \
        "every error parameter zero then" in note0
    program_file = tmp_path / "cone.ngc"
    program_file.write_text(prog.text)
    out = tmp_path / "twin1.toml"
    report, result = run_identification(Cloud(pts, nrm, "cmm.ply"), dev, load_part("nas979"),
                                        machine=tmp_path / "twin0.toml", program=program_file, write=out)
    assert result.verdict == "accepted" and result.setup_offset
    note = load_machine(out).note
    assert note.startswith(note0) and "the fit's residual RMS" in note and "the part's set-up offset fitted" in note


def test_the_setup_accuracy_with_a_best_fit_is_refused_not_ignored(tmp_path, measured_cone, capsys):
    # A QA pass: --setup-sigma-um with --align bestfit was taken and changed nothing (the best fit takes the set-up),
    # and the bestfit note suggested giving it. Refused by the command (exit 2) and by the domain function.
    from trueaxis.cli import main

    prog, true, pts, nrm, dev = measured_cone
    program_file = tmp_path / "cone.ngc"
    program_file.write_text(prog.text)
    with pytest.raises(ValueError, match="with the best-fit alignment: the best fit takes the part's set-up"):
        run_identification(Cloud(pts, nrm, "cmm.ply"), dev, load_part("nas979"), machine=MACHINES / "nmv1500dcg.toml",
                           program=program_file, alignment="bestfit", setup_sigma_um=0.0)
    np.savetxt(tmp_path / "cmm.xyz", pts)
    assert main(["inspect", str(tmp_path / "cmm.xyz"), "--part", "nas979", "--identify", "--machine", "nmv1500dcg",
                 "--program", str(program_file), "--align", "bestfit", "--setup-sigma-um", "5"]) == 2
    assert "--setup-sigma-um: with --align bestfit the best fit takes the part's set-up" in capsys.readouterr().err
    from trueaxis.inspect.flyers import residual_above_noise_note

    note = residual_above_noise_note(3.0, 0.5, kept=["XOC"], setup_given=True)
    assert note and "--setup-sigma-um" not in note


def test_a_no_change_verdict_lists_its_significant_changes_apart_from_the_insignificant_ones():
    # A QA pass: half the cone (y > 0) measured off nmv1500dcg against its error-free twin: NO CHANGE (the changes
    # explain too little of the part), and "not significant, kept: ... AOC -27.22 +- 3.40" (8 std). The significant
    # changes a no-change verdict does not write are listed as such; "not significant" holds those below 3 std.
    from trueaxis.nc.gcode import parse_program

    m = load_machine(MACHINES / "nmv1500dcg.toml")
    twin = error_free(m)
    prog = nas979_program(twin)
    res = simulate(prog.text, m, part="nas979", points=4000, noise_um=0.5, seed=0)
    ok = np.all(np.isfinite(res.measured), axis=1) & (res.measured[:, 1] > 0)
    pts, nrm = res.measured[ok], res.normals[ok]
    r = identify(pts, nrm, cone_deviation_um(pts, load_part("nas979")), parse_program(prog.text),
                 placed_for(twin, prog.text, "nas979"))
    assert r.verdict == "no change" and "AOC" in r.too_small
    assert all(abs(c) >= 3.0 * s for c, s in r.too_small.values())
    assert all(abs(c) < 3.0 * s for c, s in r.not_significant.values()) and "AOC" not in r.not_significant
    said = "\n".join(r.verdict_lines())
    assert "significant, but together too small to write, kept: AOC -27.22 +- 3.40" in said, said
    assert "not significant, kept: " not in said or "AOC" not in said.split("not significant, kept: ")[1]
    rep = r.as_report()
    assert [e["name"] for e in rep["too_small_to_write"]] == list(r.too_small)
    assert {d["category"] for d in rep["not_identifiable_detail"] if d["name"] == "AOC"} == {"too_small"}
