"""Write docs/papers.md: every number the four source papers state that trueaxis can compute, the paper's value next
to ours and how ours was obtained, and the papers' statements that carry no number or that the project cannot compute.

    python docs/make_papers_table.py            # rewrite docs/papers.md (runs the virtual shop's slot test: minutes)
    python docs/make_papers_table.py --check    # exit 1 when the committed file differs from what the code gives

Each row's "ours" cell is computed here, by the function named in its "how" cell; nothing is typed in by hand. The
papers' own figures are those of ../shared/data/papers (README.md and the two CSV files, copied to fixtures/papers).
"""

from __future__ import annotations

import argparse
import csv
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DOC_PATH = ROOT / "docs" / "papers.md"
PAPERS = ROOT / "fixtures" / "papers"
MACHINES = ROOT / "fixtures" / "machines"

P1 = "1. Equivalent cutting forces (XH714)"
P2 = "2. Performance test, NMV 1500 DCG"
P3 = "3. Differential motion matrix, SmartCNC500"
P4 = "4. Operative correction, CNC lathe"

# The paper's slot-test figures (README of the papers: mean contour error by CMM, um).
PAPER_CONTOUR_UM = {"none": 56.0, "geometric": 34.0, "comprehensive": 23.0}


@dataclass(frozen=True)
class Row:
    paper: str
    quantity: str
    paper_value: str
    ours: Callable[[], str]
    how: str
    slow: bool = False


def _machine(name: str):
    from trueaxis.machine import load_machine

    return load_machine(MACHINES / f"{name}.toml")


def xh714_component_errors() -> str:
    m = _machine("xh714")
    names = [n for a in m.axis_names if not m.axes[a].is_rotary for n in m.component_names(a)]
    return f"{len(names)} ({', '.join(sorted(names))})"


def group7_model_peaks() -> str:
    from trueaxis.machine.cutting_force import fit_coefficients, load_l16

    fit = fit_coefficients(load_l16(PAPERS / "milling_forces_l16.csv"))
    g = int(np.nonzero(fit.groups == 7)[0][0])
    return (f"model at group 7's ap, fz, ae: Fx {fit.predicted_n[g, 0]:.1f} N, Fy {fit.predicted_n[g, 1]:.1f} N "
            f"(best L16 fit, RMS {fit.rms_n:.1f} N over all groups)")


def paper_reductions() -> str:
    c = PAPER_CONTOUR_UM
    r_geo = 100 * (c["none"] - c["geometric"]) / c["none"]
    r_comp = 100 * (c["none"] - c["comprehensive"]) / c["none"]
    r_comp_geo = 100 * (c["geometric"] - c["comprehensive"]) / c["geometric"]
    return f"-{r_geo:.1f} %, -{r_comp:.1f} %, -{r_comp_geo:.1f} % (recomputed from the paper's 56, 34, 23 um)"


_SLOT_CACHE: dict = {}


def _slots() -> dict:
    if not _SLOT_CACHE:
        from trueaxis.sim.experiments import slot_experiment

        _SLOT_CACHE.update({s["compensation"]: s["contour_error_um"] for s in slot_experiment()["slots"]})
    return _SLOT_CACHE


def slot_contour_errors() -> str:
    s = _slots()
    return (f"{s['none']:.1f} um, {s['geometric']:.2f} um, {s['comprehensive']:.2f} um "
            "(typical, not the paper's, errors)")


def slot_reductions() -> str:
    s = _slots()
    return (f"-{100 * (s['none'] - s['geometric']) / s['none']:.0f} %, "
            f"-{100 * (s['none'] - s['comprehensive']) / s['none']:.0f} %, "
            f"-{100 * (s['geometric'] - s['comprehensive']) / s['geometric']:.0f} %")


def nmv_linear_location_errors() -> str:
    m = _machine("nmv1500dcg")
    linear = [n for n in m.location_names() if n[1] == "0"]
    return f"{len(linear)} ({', '.join(linear)}): squareness only"


def nmv_rotary_location_errors() -> str:
    m = _machine("nmv1500dcg")
    stated = ["XOB", "ZOB", "AOB", "COB", "XOC", "YOC", "AOC", "BOC"]
    ours = [n for n in m.location_names() if n[1] == "O"]
    missing = [n for n in stated if n not in ours]
    extra = [n for n in ours if n not in stated]
    return (f"{len(ours) - len(extra)} of the paper's 8 ({'all' if not missing else 'missing ' + ', '.join(missing)})"
            f", plus the zero-angle offsets {', '.join(extra)}")


def smartcnc_errors_per_rotary_axis() -> str:
    m = _machine("smartcnc500")
    out = []
    for a in m.rotary_axes:
        comps = m.component_names(a)
        loc = [n for n in m.location_names() if n[1] == "O" and n.endswith(a) and n != f"{a}O{a}"]
        out.append(f"{a}: {len(comps)} component + {len(loc)} location = {len(comps) + len(loc)}")
    return "; ".join(out) + " (zero-angle offsets AOA, COC apart)"


def _lathe_csv() -> list[dict]:
    lines = (PAPERS / "lathe_caliper_models.csv").read_text(encoding="utf-8").splitlines()
    return list(csv.DictReader(line for line in lines if not line.startswith("#")))


def lathe_model_count() -> str:
    m = _machine("lathe")
    kinds = sorted(f"{'+' if s.load_sign > 0 else '-'}/{'forward' if s.motion > 0 else 'backward'}"
                   for s in m.surfaces)
    return f"{len(m.surfaces)} response surfaces ({', '.join(kinds)})"


def lathe_coefficients() -> str:
    m = _machine("lathe")
    keys = ("c0", "c1_x", "c2_p", "c3_x2", "c4_xp", "c5_p2")
    worst = 0.0
    for row in _lathe_csv():
        sign = 1 if row["load_sign"] == "+" else -1
        motion = 1 if row["motion"] == "forward" else -1
        s = next(s for s in m.surfaces if s.load_sign == sign and s.motion == motion)
        printed = np.array([float(row[k]) for k in keys])
        worst = max(worst, float(np.max(np.abs(s.coeffs / 1000.0 - printed) / np.maximum(np.abs(printed), 1e-300))))
    return f"all 24 equal the printed ones (largest relative difference {worst:.1e}, um vs mm)"


def lathe_comprehensive_post() -> str:
    """The operative correction posted: comprehensive minus geometric Z correction of a facing-out block, against the
    printed model 1 evaluated at its X and Kienzle's force."""
    from trueaxis.postproc.post import compensate, without_header

    m = _machine("lathe")
    prog = "G18 G21 G90 G94 G8\n(trueaxis: ap=2 f=0.2 vc=180)\nG0 X40.000000 Z-5.000000\nG1 Z-50.000000 F100\nM30\n"
    z = []
    for mode in ("geometric", "comprehensive"):
        out = compensate(prog, m, mode, tol_um=50.0)
        z.append(float(without_header(out).splitlines()[3].split("Z")[1].split()[0]))
    cutting = tomllib.loads((MACHINES / "lathe.toml").read_text(encoding="utf-8"))["cutting"]
    fc = cutting["kc11"] * 2.0 * 0.2 ** (1.0 - cutting["mc"])
    P = cutting["feed_ratio"] * fc / 1000.0
    c = [float(_lathe_csv()[0][k]) for k in ("c0", "c1_x", "c2_p", "c3_x2", "c4_xp", "c5_p2")]
    printed_um = 1000.0 * (c[0] + c[1] * 40 + c[2] * P + c[3] * 1600 + c[4] * 40 * P + c[5] * P**2)
    posted_um = -(z[1] - z[0]) * 1000.0
    return (f"posted deviation {posted_um:.3f} um, printed model 1 at X 40 mm, Pz {P:.3f} kN: {printed_um:.3f} um "
            "(Kienzle force from the lathe fixture's typical C45 values)")


ROWS: tuple[Row, ...] = (
    Row(P1, "component errors in the three-axis model", "18", xh714_component_errors,
        "`Machine.component_names` of each linear axis of fixtures/machines/xh714.toml"),
    Row(P1, "peak forces of group 7 (Table 2), the equivalent load's source", "Fx 102.00 N, Fy 186.32 N",
        group7_model_peaks, "`cutting_force.fit_coefficients` on fixtures/papers/milling_forces_l16.csv "
        "(D 10 mm, 4 flutes, helix 30 deg, down milling assumed; docs/force_fit.md)"),
    Row(P1, "mean contour error of the three slots (none / geometric / comprehensive)", "56 um, 34 um, 23 um",
        slot_contour_errors,
        "`sim.experiments.slot_experiment()`: xh714 with typical errors, virtual CMM, 6,000 points",
        slow=True),
    Row(P1, "reductions (geometric vs none, comprehensive vs none, comprehensive vs geometric)", "-39 %, -59 %, -32 %",
        paper_reductions, "arithmetic on the paper's own three contour errors"),
    Row(P1, "the same reductions in the virtual shop", "-39 %, -59 %, -32 %", slot_reductions,
        "`sim.experiments.slot_experiment()` (the row above)", slow=True),
    Row(P2, "ISO 230-1 location errors of the linear axes", "9", nmv_linear_location_errors,
        "`Machine.location_names` of fixtures/machines/nmv1500dcg.toml; the axes' zero offsets and the three "
        "orientations that fix the reference frame are not parameters of the twin"),
    Row(P2, "ISO 230-7 location errors of B and C", "8 (XOB ZOB AOB COB XOC YOC AOC BOC)", nmv_rotary_location_errors,
        "`Machine.location_names` of fixtures/machines/nmv1500dcg.toml"),
    Row(P3, "errors of each rotary axis identified by the six-circle ballbar method", "10",
        smartcnc_errors_per_rotary_axis,
        "`Machine.component_names` and `location_names` of fixtures/machines/smartcnc500.toml (the ballbar "
        "identification itself is not implemented)"),
    Row(P4, "response-surface models (load sign x direction of motion)", "4", lathe_model_count,
        "`Machine.surfaces` of fixtures/machines/lathe.toml"),
    Row(P4, "coefficients of the four second-degree surfaces", "24 (lathe_caliper_models.csv)", lathe_coefficients,
        "fixtures/machines/lathe.toml `[[force.surface]] coeffs` / 1000 against the CSV"),
    Row(P4, "the operative correction applied to a turning program", "no number (the paper feeds the correction to "
        "the interpolator)", lathe_comprehensive_post,
        "`postproc.post.compensate` comprehensive minus geometric on fixtures/machines/lathe.toml"),
)

NO_NUMBER = (
    (P1, "the L16 test's cutting coefficients: the summary at hand gives none (ours, with their spread over "
         "near-equal minima: docs/force_fit.md)"),
    (P1, "the 18 component errors' values and the equivalent-load parameters: not given as numbers in the summary at "
         "hand; the xh714 fixture carries typical values"),
    (P1, "110 N along X and 180 N along Y, the equivalent load: an input (the xh714 fixture's `[loaded] force_n`), not "
         "something to compute; it is close to, not equal to, group 7's measured 102.00 / 186.32 N"),
    (P2, "the identified reduced axis error parameters and the NAS 979 cone's measured errors: not given as numbers "
         "in the summary at hand"),
    (P3, "the SmartCNC500's identified errors and its compensation results: not given as numbers in the summary "
         "at hand"),
    (P4, "the range of X the surfaces were measured over and the unit of Pz: not stated (the fixture assumes X 0-200 "
         "mm and Pz in kN, the only unit that makes the coefficients plausible), nor which machine axis Pz acts along "
         "(the fixture reads it as the force along the machine's Z); the order of the four models follows the "
         "paper's sentence, an assumption"),
)


def table(rows: Sequence[Row] = ROWS) -> list[tuple[Row, str]]:
    return [(row, row.ours()) for row in rows]


def render(computed: list[tuple[Row, str]]) -> str:
    lines = [
        "# The papers' numbers, reproduced",
        "",
        "Every number the four source papers state (as summarised in `../shared/data/papers`) that trueaxis can "
        "compute: the paper's value, ours, and how ours was obtained. Written by `python docs/make_papers_table.py` "
        "from the code; `tests/test_papers_table.py` recomputes every row and compares it with this file.",
        "",
        "| # | paper | quantity | paper | ours | how |",
        "|---:|---|---|---|---|---|",
    ]
    for i, (row, ours) in enumerate(computed, 1):
        lines.append(f"| {i} | {row.paper} | {row.quantity} | {row.paper_value} | {ours} | {row.how} |")
    lines += ["", "## Where a paper gives no number, or none the project can compute", ""]
    lines += [f"- {paper}: {text}." for paper, text in NO_NUMBER]
    lines.append("")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare with the committed file instead of writing it")
    args = parser.parse_args(argv)
    text = render(table())
    if args.check:
        if DOC_PATH.read_text(encoding="utf-8") != text:
            print(f"{DOC_PATH}: differs from what docs/make_papers_table.py writes; regenerate it", file=sys.stderr)
            return 1
        return 0
    DOC_PATH.write_text(text, encoding="utf-8")
    print(f"wrote {DOC_PATH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
