"""The kernels compiled ahead of time (trueaxis.compiled) give the post's bytes that numba's JIT gives, and a post
with them does not import numba; arguments they were not compiled for go to numba."""

from __future__ import annotations

import hashlib
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import MACHINES, ROOT
from trueaxis import compiled

NIST = ROOT / "fixtures" / "programs" / "nist"


def test_only_the_exact_argument_types_fit():
    spec = [("a", "<f8", 2, True), ("a", "|u1", 1, False), ("i",), ("b",), ("f",)]
    a2 = np.zeros((3, 2))
    buf = np.frombuffer(b"G1 X1\n", np.uint8)  # read-only: fine where the kernel only reads
    assert compiled._fits((a2, buf, 3, True, 1.5), spec)
    assert compiled._fits((a2, buf, np.int64(3), np.bool_(False), np.float64(1.5)), spec)
    bad = [
        (a2.astype(np.float32), buf, 3, True, 1.5),  # dtype
        (a2[:, :1], buf, 3, True, 1.5),  # not C-contiguous
        (np.zeros(6), buf, 3, True, 1.5),  # dimensions
        (np.zeros((3, 2))[::-1], buf, 3, True, 1.5),  # reversed: not C order
        (np.frombuffer(np.zeros(6).tobytes(), float).reshape(3, 2), buf, 3, True, 1.5),  # read-only, written to
        (a2, buf, True, True, 1.5),  # a bool where an int64 goes
        (a2, buf, 2**63, True, 1.5),  # out of int64
        (a2, buf, 3.0, True, 1.5),  # a float where an int64 goes
        (a2, buf, 3, 1, 1.5),  # an int where a bool goes
        (a2, buf, 3, True, 1),  # an int where a float goes
        (a2, buf, 3, True, np.float32(1.5)),
        (a2, buf, 3, True),  # too few
        ([[0.0, 0.0]], buf, 3, True, 1.5),  # a list
    ]
    for args in bad:
        assert not compiled._fits(args, spec)


def test_the_kernel_modules_take_numba_from_the_stand_in():
    import trueaxis.machine.chain_kernel as ck
    import trueaxis.nc.fast_read as fr

    for mod in (ck, fr):
        assert mod.numba is compiled.numba or mod.numba.__name__ == "numba"


_POST = r"""
import hashlib, json, sys
import numpy as np
from trueaxis.machine import load_machine, parse_machine
from trueaxis.postproc.post import compensate
from trueaxis import compiled
work, machines = sys.argv[1], sys.argv[2]
out = {}
text = open(machines + "/xh714.toml").read()
for old in ("[-200.0, 200.0]", "[-150.0, 150.0]", "[-400.0, 0.0]"):
    text = text.replace(old, "[-2000.0, 2000.0]")
xh = parse_machine(text, source="xh714-wide")
plate = open(work + "/plate.nc").read()
small = "".join(plate.splitlines(keepends=True)[:120]) + "M30\n"
out["small"] = hashlib.sha256(compensate(small, xh, "geometric", offsets_zero=True).encode()).hexdigest()
out["numba imported by a small post"] = "numba" in sys.modules
m = load_machine(machines + "/nmv1500dcg.toml")
rng = np.random.default_rng(0)
values = m.parameter_values()
m = m.with_parameters(np.where(values == 0.0, rng.normal(0.0, 10.0, values.size), values))
cone = open(work + "/cone.ngc").read()
for mode in ("geometric", "comprehensive"):
    out["cone " + mode] = hashlib.sha256(compensate(cone, m, mode).encode()).hexdigest()
    for units in ("inch", "mm"):
        prog = plate if units == "inch" else plate.replace("G20", "G21")
        out[f"plate {units} {mode}"] = hashlib.sha256(
            compensate(prog, xh, mode, offsets_zero=True).encode()).hexdigest()
out["aot"] = compiled.aot_available()
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def programs(tmp_path_factory):
    """The NIST plate (ASCII, with cutting conditions) and a five-axis cone pass, as files."""
    from trueaxis.machine import load_machine
    from trueaxis.sim.programs import cone_flank_program

    work = tmp_path_factory.mktemp("programs")
    plate = (NIST / "mtc_plate_1.nc").read_text(encoding="latin-1")
    lines = "".join(c if c.isascii() else "?" for c in plate).splitlines(keepends=True)
    (work / "plate.nc").write_text("".join(lines[:1] + ["(trueaxis: ap=0.6 ae=7 fz=0.2 n=1200 d=10 z=4 mode=down)\n"]
                                           + lines[1:]))
    m = load_machine(MACHINES / "nmv1500dcg.toml")
    cone = {"axis": [math.sin(math.radians(10)), 0.0, math.cos(math.radians(10))], "half_angle_deg": 15.0,
            "base_radius": 40.0, "height_range": [0.0, 20.0]}
    (work / "cone.ngc").write_text(cone_flank_program(m, cone, n_blocks=400))
    return work


def _post_hashes(work, env):
    res = subprocess.run([sys.executable, "-c", _POST, str(work), str(MACHINES)], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT), **env}, check=False)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def aot_dir(tmp_path_factory):
    """A fresh ahead-of-time build of the current source (the installed one may be older)."""
    folder = tmp_path_factory.mktemp("aot")
    res = subprocess.run([sys.executable, "-m", "trueaxis.warm"], capture_output=True, text=True, check=False,
                         env={**os.environ, "PYTHONPATH": str(ROOT), "TRUEAXIS_AOT_DIR": str(folder)})
    assert res.returncode == 0, res.stderr[-2000:]
    return folder


@pytest.mark.slow
def test_posts_with_the_ahead_of_time_kernels_are_the_jit_posts_byte_for_byte(aot_dir, programs):
    spec = json.loads((aot_dir / "_aot_kernels.json").read_text())
    assert {"trueaxis.machine.chain_kernel.pose_and_axis_jacobian", "trueaxis.nc.fast_read.scan_lines",
            "trueaxis.nc.fast_write.assemble", "trueaxis.machine.error_kernel.evaluate_packed"} <= set(
        spec["kernels"])
    aot = _post_hashes(programs, {"TRUEAXIS_AOT_DIR": str(aot_dir)})
    jit = _post_hashes(programs, {"TRUEAXIS_AOT": "0"})
    assert aot.pop("aot") and not jit.pop("aot")
    assert aot.pop("numba imported by a small post") is False  # the point: no numba at start-up
    assert jit.pop("numba imported by a small post") is True
    assert aot == jit


@pytest.mark.slow
def test_a_build_from_other_source_is_not_used(aot_dir, tmp_path):
    spec = json.loads((aot_dir / "_aot_kernels.json").read_text())
    stale = tmp_path / "stale"
    stale.mkdir()
    (stale / spec["file"]).write_bytes((aot_dir / spec["file"]).read_bytes())
    spec["source"] = hashlib.sha256(b"other source").hexdigest()
    (stale / "_aot_kernels.json").write_text(json.dumps(spec))
    code = ("import sys; from trueaxis import compiled; print(compiled.aot_available())")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT), "TRUEAXIS_AOT_DIR": str(stale)})
    assert res.stdout.strip() == "False"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT), "TRUEAXIS_AOT_DIR": str(aot_dir)})
    assert res.stdout.strip() == "True"


_THREADS = r"""
import json, sys
import numpy as np
from trueaxis import compiled
from trueaxis.machine import ErrorTwin, load_machine
from trueaxis.machine.twin import PARALLEL_MIN
m = load_machine(sys.argv[1])
rng = np.random.default_rng(1)
values = m.parameter_values()
m = m.with_parameters(np.where(values == 0.0, rng.normal(0.0, 10.0, values.size), values))
twin = ErrorTwin(m)
n = 3 * PARALLEL_MIN + 17
lo = np.array([twin.machine.axes[a].travel[0] if twin.machine.axes[a].travel is not None else -3.0
               for a in m.axis_names])
hi = np.array([twin.machine.axes[a].travel[1] if twin.machine.axes[a].travel is not None else 3.0
               for a in m.axis_names])
q = lo + (hi - lo) * rng.random((n, len(lo)))
force = rng.normal(0.0, 100.0, (n, 3))
out = {}
threaded = [twin.actual_pose(q, force), twin.pose_and_axis_jacobian(q, force), twin.nominal_pose(q),
            twin.actual_pose(q), twin.pose_and_axis_jacobian(q)]
out["numba imported by the threaded kernels"] = "numba" in sys.modules
# the serial kernels, poses in small batches (below PARALLEL_MIN)
cut = range(0, n, 1000)
serial = [[np.concatenate(x) for x in zip(*[f(q[i:i + 1000], force[i:i + 1000]) for i in cut])]
          for f in (twin.actual_pose, twin.pose_and_axis_jacobian)]
serial.append([np.concatenate(x) for x in zip(*[twin.nominal_pose(q[i:i + 1000]) for i in cut])])
serial += [[np.concatenate(x) for x in zip(*[f(q[i:i + 1000]) for i in cut])]
           for f in (twin.actual_pose, twin.pose_and_axis_jacobian)]
# numba's parallel kernels (the twins off)
compiled._aot = None
compiled._jit_all()
parallel = [twin.actual_pose(q, force), twin.pose_and_axis_jacobian(q, force), twin.nominal_pose(q),
            twin.actual_pose(q), twin.pose_and_axis_jacobian(q)]
out["same as serial"] = all(np.array_equal(a, b) for x, y in zip(threaded, serial) for a, b in zip(x, y))
out["same as numba parallel"] = all(np.array_equal(a, b) for x, y in zip(threaded, parallel) for a, b in zip(x, y))
print(json.dumps(out))
"""


@pytest.mark.slow
def test_long_programs_run_the_twins_on_threads_with_the_numbers_of_the_serial_and_parallel_kernels(aot_dir):
    # A long program's twin: the serial kernels' ahead-of-time twins on threads (they release the GIL), instead of
    # numba's parallel kernels, whose import and first load cost ~0.7 s: bit for bit the same poses and Jacobians,
    # with force (the error values evaluated first, then the chain on threads) and without (both on each thread).
    res = subprocess.run([sys.executable, "-c", _THREADS, str(MACHINES / "nmv1500dcg.toml")], capture_output=True,
                         text=True, check=False, env={**os.environ, "PYTHONPATH": str(ROOT),
                                                      "TRUEAXIS_AOT_DIR": str(aot_dir), "NUMBA_NUM_THREADS": "2"})
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out == {"numba imported by the threaded kernels": False, "same as serial": True,
                   "same as numba parallel": True}


def test_a_forked_child_makes_its_own_kernel_threads():
    # the parent's pool threads do not exist in a forked child: it must not wait for them
    compiled.run_threads(abs, [-1, -2])
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            code = 0 if compiled.run_threads(abs, [-3, -4]) == [3, 4] else 1
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
