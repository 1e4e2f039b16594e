"""Chunks of moves compensated side by side (``post._Poster._compensate_chunks``): the same output bytes and report
as the chunks one after the other, whatever the chunk size; the first chunk's error is the one raised."""

from __future__ import annotations

import pytest

from conftest import ROOT, missing, tilted_cone_case
from trueaxis import compiled
from trueaxis.postproc import post as post_module
from trueaxis.postproc.post import PostError, compensate
from test_fast_write import SPLIT_PROGRAM

NIST = ROOT / "fixtures" / "programs" / "nist"


@pytest.fixture(autouse=True)
def _ahead_of_time_kernels():
    if not compiled.aot_available():
        missing("the ahead-of-time kernels are not built (make test builds them: python -m trueaxis.warm); chunks run "
                "side by side with them only")


def _both(text, machine, monkeypatch, chunk, **kw):
    """((output, report) on threads, the same one chunk after the other, chunks that ran on threads)."""
    seen = []
    threaded = post_module._Poster._compensate_threaded

    def spy(self, rows, chunks, before):
        seen.append(len(chunks))
        yield from threaded(self, rows, chunks, before)

    monkeypatch.setattr(post_module._Poster, "_compensate_threaded", spy)
    # (a test before may have imported numba, which keeps a post's chunks one after the other: not here, where
    # numba's threading layer, if used at all, is entered from both threads only in this test)
    monkeypatch.setattr(compiled, "numba_imported", lambda: False)
    monkeypatch.setattr(post_module, "ROW_CHUNK", chunk)
    out = []
    for flag in (True, False):
        monkeypatch.setattr(post_module, "CHUNK_THREADS", flag)
        rep = {}
        out.append((compensate(text, machine, "geometric", report=rep, **kw), rep))
    return out[0], out[1], sum(seen)


@pytest.mark.parametrize("chunk", [1, 2, 3, 7])
def test_split_moves_and_fitted_arcs_across_chunks_are_the_same_on_threads(xh714_wide, monkeypatch, chunk):
    # fitted arcs start from the chunk before's last end; split moves count in the report
    threaded, serial, n = _both(SPLIT_PROGRAM, xh714_wide, monkeypatch, chunk, offsets_zero=True, tol_um=0.2,
                                arcs=True)
    assert threaded == serial
    assert n > 0
    assert serial[1]["arcs_fitted"] > 0


def test_the_split_count_is_the_whole_programs_in_any_chunking(xh714_wide, monkeypatch):
    # The report's moves_split sums the chunks (it was the last chunk's count: 8,000 moves a chunk, so a long
    # program's report and terminal line understated it): one chunk, chunks of 2 on threads, one after the other.
    monkeypatch.setattr(post_module, "ROW_CHUNK", 10**9)
    whole = {}
    compensate(SPLIT_PROGRAM, xh714_wide, "geometric", report=whole, offsets_zero=True, tol_um=0.2, arcs=True)
    threaded, serial, _ = _both(SPLIT_PROGRAM, xh714_wide, monkeypatch, 2, offsets_zero=True, tol_um=0.2, arcs=True)
    assert whole["moves_split"] >= 2
    assert threaded[1]["moves_split"] == serial[1]["moves_split"] == whole["moves_split"]


@pytest.mark.parametrize("name", ["mtc_cover_rev_a.nc", "mtc_plate_1.nc"])
def test_the_nist_programs_are_the_same_on_threads(xh714_wide, monkeypatch, name):
    text = (NIST / name).read_text(errors="replace")
    threaded, serial, n = _both(text, xh714_wide, monkeypatch, 97, offsets_zero=True)
    assert threaded == serial
    assert n > 10


def test_a_five_axis_program_is_the_same_on_threads(monkeypatch):
    m, text = tilted_cone_case(3000)
    threaded, serial, n = _both(text, m, monkeypatch, 400)
    assert threaded == serial
    assert n > 5


def test_the_first_chunk_with_an_error_names_its_block(xh714_wide, monkeypatch):
    # two moves beyond the travel, in different chunks: the earlier one is refused, as one chunk after the other
    lines = ["G21 G90 G17 G94 F500", "G0 X0 Y0 Z-100"] + [f"G1 X{i % 50} Y{i % 7} Z-100" for i in range(400)]
    lines[150] = "G1 X2100 Y0 Z-100"
    lines[330] = "G1 X-2100 Y0 Z-100"
    text = "\n".join(lines + ["M2"]) + "\n"
    errors = []
    for flag in (True, False):
        monkeypatch.setattr(post_module, "CHUNK_THREADS", flag)
        monkeypatch.setattr(post_module, "ROW_CHUNK", 20)
        with pytest.raises(PostError) as exc:
            compensate(text, xh714_wide, "geometric", offsets_zero=True)
        errors.append(str(exc.value))
    assert errors[0] == errors[1]
    assert ":151:" in errors[0]
