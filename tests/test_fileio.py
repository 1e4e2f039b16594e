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


def test_a_noted_signal_stops_every_later_publish_and_leaves_the_old_files(tmp_path, monkeypatch):
    """A SIGINT whose KeyboardInterrupt was lost inside compiled code must still keep the output unwritten."""
    import trueaxis.fileio as fileio

    out, folder = tmp_path / "out.ngc", tmp_path / "report"
    out.write_text("previous")
    monkeypatch.setattr(fileio, "_signalled", None)
    fileio.atomic_write(out, "first")  # no signal: written
    assert out.read_text() == "first"
    fileio.note_signal(2)
    with pytest.raises(fileio.Interrupted) as caught:
        fileio.atomic_write(out, "second")
    assert caught.value.signum == 2
    temp = tmp_path / "tmpdir"
    temp.mkdir()
    with pytest.raises(fileio.Interrupted):
        fileio.publish_folder(temp, folder)
    assert out.read_text() == "first" and not folder.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.ngc", "tmpdir"]  # no temporary file left


def test_atomic_write_of_pieces_writes_them_in_order_without_joining(tmp_path):
    """A list of pieces (bytes and C-contiguous numpy arrays, any dtype) is written as their bytes one after the
    other: the same file as their concatenation."""
    import numpy as np

    table = np.arange(12, dtype="<f8").reshape(4, 3)
    digits = np.frombuffer(b"0123456789", dtype=np.uint8)[2:7]
    target = tmp_path / "out.bin"
    atomic_write(target, [b"head\n", table, digits])
    assert target.read_bytes() == b"head\n" + table.tobytes() + b"23456"


def test_a_published_folder_replaces_only_what_trueaxis_published_there(tmp_path):
    """publish_folder replaces an earlier report folder whole, but refuses (OutputPathError, nothing moved) a folder
    holding anything else: a user's folder named by mistake, or a report folder the user added a file to."""
    from trueaxis.fileio import FOLDER_MARKER, OutputPathError, check_replaceable_folder, publish_folder

    def report(text):
        temp = tmp_path / f"temp_{text}"
        temp.mkdir()
        (temp / "report.json").write_text(text)
        return temp

    out = tmp_path / "out"
    publish_folder(report("one"), out)
    assert sorted(p.name for p in out.iterdir()) == [FOLDER_MARKER, "report.json"]
    publish_folder(report("two"), out)  # an earlier report: replaced
    assert (out / "report.json").read_text() == "two"
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputPathError, match="notes.txt"):
        publish_folder(report("three"), out)
    assert (out / "notes.txt").read_text() == "mine" and (out / "report.json").read_text() == "two"
    users = tmp_path / "users"
    users.mkdir()
    (users / "cloud.ply").write_text("x")
    with pytest.raises(OutputPathError, match="cloud.ply"):
        check_replaceable_folder(users)
    check_replaceable_folder(tmp_path / "empty_or_missing")  # a folder that does not exist: fine


def test_a_diagnosis_folder_written_before_the_marker_may_be_replaced_but_not_one_with_other_files(tmp_path):
    import json

    from trueaxis.fileio import DIAGNOSIS_FILES_BEFORE_MARKER, OutputPathError, check_replaceable_folder

    old = tmp_path / "diagnosis"
    old.mkdir()
    for name in DIAGNOSIS_FILES_BEFORE_MARKER:
        (old / name).write_text("x")
    (old / "diagnosis.json").write_text(json.dumps({"format": 1, "verdict": "none of the candidates", "gap_um": {}}))
    check_replaceable_folder(old)
    (old / "notes.txt").write_text("mine")
    with pytest.raises(OutputPathError, match=r"notes.txt"):
        check_replaceable_folder(old)


def test_json_text_is_strict_json_with_non_finite_numbers_as_null():
    import json

    import numpy as np

    from trueaxis.fileio import json_text

    text = json_text({"cond": float("inf"), "v": np.array([1.5, np.nan]), "n": np.int64(3), "ok": np.bool_(True)})
    assert "Infinity" not in text and "NaN" not in text
    assert json.loads(text, parse_constant=lambda c: pytest.fail(c)) == {"cond": None, "v": [1.5, None], "n": 3,
                                                                         "ok": True}
