"""docs/papers.md: every row's "ours" is what docs/make_papers_table.py computes from the code."""

from __future__ import annotations

import importlib.util
import sys

import pytest

from conftest import ROOT

DOC = ROOT / "docs" / "papers.md"


def _script():
    name = "make_papers_table"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ROOT / "docs" / "make_papers_table.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses look their module up while the class is made
        spec.loader.exec_module(module)
    return sys.modules[name]


def _doc_rows() -> dict[int, list[str]]:
    rows = {}
    for line in DOC.read_text(encoding="utf-8").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
        if len(cells) == 6 and cells[0].isdigit():
            rows[int(cells[0])] = cells
    return rows


def test_every_fast_row_of_docs_papers_md_is_reproduced_by_the_code():
    # Each row's paper, quantity, paper's value and how are the script's; its "ours" is recomputed now. (The two
    # rows of the slot test in the virtual shop take minutes: the slow test below covers them.)
    script, doc = _script(), _doc_rows()
    assert sorted(doc) == list(range(1, len(script.ROWS) + 1))
    for i, row in enumerate(script.ROWS, 1):
        assert doc[i][1:4] == [row.paper, row.quantity, row.paper_value] and doc[i][5] == row.how, i
        if not row.slow:
            assert doc[i][4] == row.ours(), (i, row.quantity)


def test_the_papers_checkable_figures_agree_where_they_must():
    # Counts and coefficients are exact; the lathe post reproduces the printed surface to the written digits.
    script = _script()
    assert script.xh714_component_errors().startswith("18 ")
    assert script.nmv_rotary_location_errors().startswith("8 of the paper's 8 (all)")
    assert script.smartcnc_errors_per_rotary_axis().startswith("A: 6 component + 4 location = 10; C: 6 component")
    assert script.lathe_model_count().startswith("4 response surfaces")
    worst = float(script.lathe_coefficients().split("largest relative difference ")[1].split(",")[0])
    assert worst < 1e-12
    text = script.lathe_comprehensive_post()
    posted = float(text.split("posted deviation ")[1].split(" um")[0])
    printed = float(text.split("kN: ")[1].split(" um")[0])
    assert abs(posted - printed) <= 0.0015  # both printed to 0.001 um


@pytest.mark.slow
def test_docs_papers_md_is_what_the_script_writes():
    script = _script()
    assert script.render(script.table()) == DOC.read_text(encoding="utf-8")
