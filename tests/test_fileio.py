"""Atomic writing (trueaxis.fileio): a file is either the old one or the whole new one, never half-written."""

from __future__ import annotations

import pytest

from trueaxis.fileio import atomic_path, atomic_write


def test_atomic_write_replaces_the_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "sub" / "out.ngc"
    atomic_write(target, "G1 X1\r\n")
    assert target.read_bytes() == b"G1 X1\r\n"  # no newline translation
    atomic_write(target, b"\x00\x01")
    assert target.read_bytes() == b"\x00\x01"
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.ngc"]


def test_a_writer_that_fails_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "part.step"
    target.write_text("old")
    with pytest.raises(OSError, match="exporter failed"):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise OSError("exporter failed")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["part.step"]
