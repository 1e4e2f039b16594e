"""The post's start-up: cubic tables' spline coefficients from the disk cache are scipy's own numbers, and the post
then imports no scipy.interpolate."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from trueaxis.machine import error_functions as ef
from trueaxis.machine.error_functions import table

ROOT = Path(__file__).resolve().parents[1]


def _scipy_form(fn):
    """compiled_form's cubic coefficients as scipy computes them (PPoly of the value spline and its derivative)."""
    sp = fn._value_spline()
    return sp.c.T.ravel(), sp.derivative().c.T.ravel()


@pytest.mark.parametrize("periodic", [False, True])
def test_cubic_coefficients_read_back_from_the_disk_cache_are_scipys_bytes(tmp_path, monkeypatch, periodic):
    monkeypatch.setenv("TRUEAXIS_CACHE_DIR", str(tmp_path))
    rng = np.random.default_rng(7 + periodic)
    if periodic:
        at = np.linspace(0.0, 2.0 * np.pi, 9)
    else:
        at = np.sort(np.concatenate([[-300.0, 100.0], rng.uniform(-300.0, 100.0, 7)]))
    values = rng.normal(0.0, 10.0, at.size)
    key = (at.tobytes(), periodic)
    monkeypatch.delitem(ef._SPLINES, key, raising=False)
    monkeypatch.delitem(ef._UNIT_COEFFICIENTS, key, raising=False)
    written = table(at, values, "cubic", periodic=periodic).compiled_form()  # computed by scipy, stored
    assert len(list((tmp_path / "splines").glob("*.npy"))) == 1
    ef._SPLINES.pop(key)  # the next one comes from the disk
    monkeypatch.delitem(ef._UNIT_COEFFICIENTS, key, raising=False)
    fn = table(at, values, "cubic", periodic=periodic)
    read = fn.compiled_form()
    c, dc = _scipy_form(fn)
    assert read[2].tobytes() == written[2].tobytes() == np.ascontiguousarray(c).tobytes()
    assert read[3].tobytes() == written[3].tobytes() == np.ascontiguousarray(dc).tobytes()


def test_a_damaged_cache_file_is_recomputed(tmp_path, monkeypatch):
    monkeypatch.setenv("TRUEAXIS_CACHE_DIR", str(tmp_path))
    at = np.array([0.0, 10.0, 25.0, 40.0, 70.0])
    values = np.array([1.0, -2.0, 3.0, 0.5, -1.0])
    table(at, values, "cubic").compiled_form()
    (path,) = (tmp_path / "splines").glob("*.npy")
    path.write_bytes(b"not an array")
    ef._SPLINES.pop((at.tobytes(), False))
    ef._UNIT_COEFFICIENTS.pop((at.tobytes(), False), None)
    fn = table(at, values, "cubic")
    assert fn.compiled_form()[2].tobytes() == np.ascontiguousarray(_scipy_form(fn)[0]).tobytes()


def test_the_post_imports_no_scipy_interpolate_once_the_cache_is_filled(tmp_path):
    """nmv1500dcg has cubic tables: its first post fills the cache, the second imports no scipy.interpolate."""
    prog = tmp_path / "p.ngc"
    prog.write_text("G21 G90 G94\nG0 X10 Y0 Z-100 B-5 C0\nG1 X11 Y1 Z-100 B-6 C10 F500\nX12 Y2 C20\nM30\n")
    script = (
        "import sys\n"
        "from trueaxis.machine import load_machine\n"
        "from trueaxis.postproc.post import post_text\n"
        "from trueaxis.nc.setup import Setup\n"
        "from trueaxis.resources import machine_file\n"
        f"text, rep = post_text(open({str(prog)!r}).read(), load_machine(machine_file('nmv1500dcg')),"
        " setup=Setup(offsets_zero=True))\n"
        "assert rep.moves == 3, rep.moves\n"
        "print('scipy.interpolate' in sys.modules)\n"
    )
    env = {**os.environ, "TRUEAXIS_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT)}
    runs = [subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
            for _ in range(2)]
    assert [r.stdout.strip() for r in runs] == ["True", "False"]


def test_a_short_post_imports_no_progress_bar(tmp_path):
    """tqdm (36 ms of a small post's start-up, its version read through importlib.metadata) only for a long program,
    which shows a bar; the short one's output is still written."""
    prog = tmp_path / "p.ngc"
    prog.write_text("G21 G90 G94\nG0 X10 Y0 Z-100 B-5 C0\nG1 X11 Y1 Z-100 B-6 C10 F500\nX12 Y2 C20\nM30\n")
    out = tmp_path / "p.out.ngc"
    script = (
        "import sys\n"
        "from trueaxis.cli import main\n"
        f"code = main(['post', {str(prog)!r}, '-o', {str(out)!r}, '--machine', 'nmv1500dcg', '--offsets-zero'])\n"
        "print(code, 'tqdm' in sys.modules)\n"
    )
    res = subprocess.run([sys.executable, "-c", script], env={**os.environ, "PYTHONPATH": str(ROOT)},
                         capture_output=True, text=True, check=True)
    assert res.stdout.strip().splitlines()[-1] == "0 False", res.stdout + res.stderr
    assert "G1" in out.read_text()
