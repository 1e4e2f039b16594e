"""Benchmark: the whole post (``trueaxis post``: read, parse, compensate, write) against LinuxCNC's ``rs274``
interpreting the same file. Goal (issue: the post-processor): our post in at most half of rs274's time, peak memory
under 2 GB.

Two programs of ``--blocks`` blocks (default 1,000,000):

- five-axis: ``cone_flank_program`` (X Y Z B C machine axes, G93) on the NMV 1500 DCG fixture with every error
  parameter non-zero (the file's values, zeros given a typical 10 um / 10 urad as in bench_twin.py);
- three-axis: the NIST programs mtc_cover_rev_a.nc + mtc_plate_1.nc (inch, lines and arcs) repeated, on the xh714
  fixture with wide travel (as test_post.py widens it).

Each command runs once as a subprocess; wall time and the child's peak resident memory (``wait4``) are measured.

    .venv/bin/python benchmarks/bench_post.py [--blocks 1000000] [--work DIR] [--only five|three] [--profile]

Then a 100-block program (the head of each) end to end, process start to file written, warm (best and median of 5
runs, and the child's CPU time). ``--profile`` also runs the post in this process under cProfile, after a small post
that loads the kernels, and prints the time per phase (read, interpret, twin, solve, split, write) and the top costs.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
NIST = ROOT / "fixtures" / "programs" / "nist"
# the command line as this interpreter runs it (the venv's console script may belong to another checkout)
TRUEAXIS = [sys.executable, "-m", "trueaxis.cli"]
CONE = {"axis": [float(np.sin(np.radians(10))), 0.0, float(np.cos(np.radians(10)))], "half_angle_deg": 15.0,
        "base_radius": 40.0, "height_range": [0.0, 20.0]}


def five_axis_case(work: Path, blocks: int):
    """(program path, machine path): the cone flank pass with ``blocks`` moves; every error parameter non-zero."""
    from trueaxis.machine import load_machine
    from trueaxis.resources import machine_file
    from trueaxis.sim.programs import cone_flank_program

    m = load_machine(machine_file("nmv1500dcg"))
    prog = work / f"cone_{blocks}.ngc"
    mach = work / "nmv1500dcg_all_errors.toml"
    if not prog.exists():
        prog.write_text(cone_flank_program(m, CONE, n_blocks=blocks))
    if not mach.exists():
        values = m.parameter_values()
        rng = np.random.default_rng(0)
        values = np.where(values == 0.0, rng.normal(0.0, 10.0, values.size), values)
        mach.write_text(_machine_toml_with(m, values))
    return prog, mach


def _machine_toml_with(machine, values) -> str:
    """The machine file of ``machine`` with its error parameters set to ``values`` (checked by reading it back)."""
    from trueaxis.machine import parse_machine
    from trueaxis.machine.machine_file import dump_machine

    text = dump_machine(machine.with_parameters(values))
    back = parse_machine(text, source="bench").parameter_values()
    if not np.allclose(back, values, rtol=1e-9, atol=1e-12):
        raise SystemExit("the benchmark machine file does not read back with the parameters written")
    return text


def three_axis_case(work: Path, blocks: int):
    """(program path, machine path): NIST cover + plate repeated to ``blocks`` lines; xh714 with wide travel."""
    prog = work / f"nist_{blocks}.nc"
    mach = work / "xh714_wide.toml"
    if not prog.exists():
        body = []
        for name in ("mtc_cover_rev_a.nc", "mtc_plate_1.nc"):
            lines = (NIST / name).read_text(errors="replace").splitlines(keepends=True)
            body += [ln for ln in lines if not ln.startswith("%") and "M30" not in ln.upper()
                     and "M02" not in ln.upper() and not ln.upper().startswith("M2")]
        reps = blocks // len(body) + 1
        text = "".join((body * reps)[: blocks - 2])
        prog.write_text("%\n" + text + "M30\n%\n")
    if not mach.exists():
        text = (ROOT / "fixtures" / "machines" / "xh714.toml").read_text()
        for old in ("[-200.0, 200.0]", "[-150.0, 150.0]", "[-400.0, 0.0]"):
            text = text.replace(old, "[-2000.0, 2000.0]")
        mach.write_text(text)
    return prog, mach


def timed(cmd, cwd=None, stdin=subprocess.DEVNULL, env=None):
    """(seconds, peak RSS in MB of the child, return code, stderr tail, CPU seconds of the child) of one run."""
    t0 = time.perf_counter()
    with open(os.devnull, "wb") as devnull:
        proc = subprocess.Popen(cmd, cwd=cwd, stdin=stdin, stdout=devnull, stderr=subprocess.PIPE, env=env)
        err_chunks = []
        # stderr is small (one line per problem); read it while waiting
        err = proc.stderr.read()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        err_chunks.append(err)
    seconds = time.perf_counter() - t0
    return (seconds, usage.ru_maxrss / 1024.0, proc.returncode, b"".join(err_chunks).decode(errors="replace")[-500:],
            usage.ru_utime + usage.ru_stime)


def warm_up(prog: Path, mach: Path, work: Path):
    """Post the first 200 lines once, untimed: the first use of the compiled kernels compiles them (about 20 s, once
    per installation, then cached), which is not the post's running time."""
    with open(prog) as f:
        head = "".join(line for _, line in zip(range(200), f))
    small = work / f"warm_{prog.stem}.ngc"
    small.write_text(head + "M30\n")
    subprocess.run([*TRUEAXIS, "post", str(small), "-o", str(work / "warm.out.ngc"), "--machine", str(mach),
                    "--offsets-zero"],
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)


def run_case(name, prog: Path, mach: Path, work: Path):
    warm_up(prog, mach, work)
    out = work / f"{prog.stem}.out.ngc"
    # the NIST programs select G54 / G58: their offsets are not at hand, zero is said explicitly
    t_post, mem_post, rc, err, cpu_post = timed([*TRUEAXIS, "post", str(prog), "-o", str(out), "--machine", str(mach),
                                       "--offsets-zero"])
    if rc != 0:
        print(f"{name}: trueaxis post failed (exit {rc}): {err}", file=sys.stderr)
    rs274 = shutil.which("rs274")
    t_rs, mem_rs, rc_rs, cpu_rs = float("nan"), float("nan"), None, float("nan")
    if rs274:
        tbl = work / "tools.tbl"
        tbl.write_text("".join(f"T{t} P{t} D0.1 Z+0.0 ;\n" for t in range(1, 40)))
        with open(os.devnull, "rb") as devnull:
            # HOME of its own: LinuxCNC 2.9's rs274 keeps the tool table in $HOME/.tool.mmap, shared by every rs274
            # of the user (another one running reads or truncates it: "Requested tool 23 not found", SIGBUS)
            home = work / "rs274_home"
            home.mkdir(exist_ok=True)
            t_rs, mem_rs, rc_rs, err_rs, cpu_rs = timed(
                [rs274, "-t", str(tbl), "-g", str(prog), str(work / "canon.txt")], cwd=work, stdin=devnull,
                env={**os.environ, "HOME": str(home)})
        if rc_rs != 0:
            print(f"{name}: rs274 exit {rc_rs}: {err_rs}", file=sys.stderr)
    n_lines = sum(1 for _ in open(prog, "rb"))
    return {"case": name, "lines": n_lines, "post_s": t_post, "post_mb": mem_post, "post_rc": rc,
            "rs274_s": t_rs, "rs274_mb": mem_rs, "rs274_rc": rc_rs, "post_cpu": cpu_post, "rs274_cpu": cpu_rs,
            "out_lines": sum(1 for _ in open(out, "rb")) if out.exists() else 0}


def small_program(prog: Path, mach: Path, work: Path, blocks: int = 100, runs: int = 5):
    """A ``blocks``-block program end to end (process start to file written), warm: ``runs`` runs after one untimed
    one; (best wall s, median wall s, median CPU s of the child, the program's path)."""
    with open(prog) as f:
        head = "".join(line for _, line in zip(range(blocks), f))
    small = work / f"small{blocks}_{prog.stem}.ngc"
    small.write_text(head + "M30\n")
    cmd = [*TRUEAXIS, "post", str(small), "-o", str(work / f"{small.stem}.out.ngc"), "--machine", str(mach),
           "--offsets-zero"]
    # warm includes Python's bytecode cache (a session that sets PYTHONDONTWRITEBYTECODE recompiles every module)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False, env=env)
    walls, cpus = [], []
    for _ in range(runs):
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        walls.append(time.perf_counter() - t0)
        cpus.append(usage.ru_utime + usage.ru_stime)
        if os.waitstatus_to_exitcode(status) != 0:
            raise SystemExit(f"the small-program post failed: {' '.join(cmd)}")
    return min(walls), float(np.median(walls)), float(np.median(cpus)), small


def profile_post(prog: Path, mach: Path, top: int = 25):
    """cProfile of the post (read, parse, compensate, write to memory) in this process; prints the top costs."""
    from trueaxis.machine import load_machine
    from trueaxis.postproc.post import post_text

    from trueaxis.nc.setup import Setup

    machine = load_machine(mach)
    text = prog.read_text()
    # warm: the compiled kernels' caches loaded (and the twin's tables built) before the profile, as in a long run,
    # which uses numba's JIT (its parallel kernels; so that cProfile names each kernel, the ahead-of-time twins are
    # left out here: the same numbers)
    from trueaxis import compiled

    compiled._aot = None
    compiled._jit_all()
    head = "".join(text.splitlines(keepends=True)[:6000]) + "M30\n"
    post_text(head, machine, "geometric", source="warm", setup=Setup(offsets_zero=True))
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    post_text(text, machine, "geometric", source=str(prog), setup=Setup(offsets_zero=True))
    prof.disable()
    wall = time.perf_counter() - t0
    _print_phases(pstats.Stats(prof), wall, prog.name)
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("cumulative").print_stats(top)
    print(f"--- cProfile of the post on {prog.name} (cumulative, top {top}) ---")
    print(buf.getvalue())
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(top)
    print("--- same, by own time ---")
    print(buf.getvalue())


# (label, file suffix, function name): the post's phases as cProfile's cumulative times of these functions
PHASES = [
    ("read: compiled pre-scan (fast_read)", "nc/fast_read.py", "scan_lines"),
    ("read: compiled runs of plain moves (fast_interp)", "nc/fast_interp.py", "straight_run"),
    ("read + interpret (parse_program, all)", "nc/gcode.py", "parse_program"),
    ("twin: pose (+ axis Jacobian), all calls", "machine/twin.py", "_compose"),
    ("solve: Newton at the block ends (incl. twin)", "postproc/post.py", "solve"),
    ("split: lines (incl. twin and solves)", "postproc/post.py", "_split_lines"),
    ("split: arcs (incl. twin and solves)", "postproc/post.py", "_arcs"),
    ("write (the dialect back, fast_write incl.)", "postproc/post.py", "_write"),
]


def _print_phases(stats, wall, name):
    """Where the post spends its time: cumulative seconds of the phase functions (phases overlap: the twin runs
    inside the solve and the split)."""
    total = {}
    for (fname, _, func), (_, _, _, ct, _) in stats.stats.items():
        for label, suffix, f in PHASES:
            if fname.endswith(suffix) and func == f:
                total[label] = total.get(label, 0.0) + ct
    print(f"--- phases of the post on {name} (in-process, kernels loaded; {wall:.2f} s wall under cProfile) ---")
    for label, _, _ in PHASES:
        print(f"  {label:48s} {total.get(label, 0.0):7.2f} s")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", type=int, default=1_000_000, help="blocks per program (default 1,000,000)")
    ap.add_argument("--work", help="folder for the generated programs and outputs (default: a temporary folder)")
    ap.add_argument("--only", choices=["five", "three"], help="run one case only")
    ap.add_argument("--profile", action="store_true", help="also profile the post in this process (cProfile)")
    args = ap.parse_args()
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_post_"))
    work.mkdir(parents=True, exist_ok=True)
    cases = []
    if args.only in (None, "five"):
        t = time.perf_counter()
        prog, mach = five_axis_case(work, args.blocks)
        print(f"five-axis program ready ({time.perf_counter() - t:.1f} s): {prog}")
        cases.append(("five-axis cone, nmv1500dcg (all errors)", prog, mach))
    if args.only in (None, "three"):
        prog, mach = three_axis_case(work, args.blocks)
        print(f"three-axis program ready: {prog}")
        cases.append(("three-axis NIST cover+plate, xh714 wide", prog, mach))
    rows = [run_case(name, prog, mach, work) for name, prog, mach in cases]
    print()
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; wall and (CPU) seconds")
    print(f"{'case':42s} {'lines':>9s} {'post s':>14s} {'post MB':>8s} {'rs274 s':>14s} {'rs274 MB':>8s} "
          f"{'post/rs274':>10s} {'(CPU)':>6s}  goal (<= 0.5 wall, < 2048 MB)")
    for r in rows:
        ratio = r["post_s"] / r["rs274_s"] if r["rs274_s"] == r["rs274_s"] else float("nan")
        ok = "met" if ratio <= 0.5 and r["post_mb"] < 2048 and r["post_rc"] == 0 else "MISSED"
        cpu_ratio = r["post_cpu"] / r["rs274_cpu"] if r["rs274_cpu"] == r["rs274_cpu"] else float("nan")
        print(f"{r['case']:42s} {r['lines']:9d} {r['post_s']:6.2f} ({r['post_cpu']:5.2f}) {r['post_mb']:8.0f} "
              f"{r['rs274_s']:6.2f} ({r['rs274_cpu']:5.2f}) {r['rs274_mb']:8.0f} {ratio:10.2f} ({cpu_ratio:4.2f})  {ok}"
              + ("" if r["post_rc"] == 0 else f" (post exit {r['post_rc']})")
              + ("" if r["rs274_rc"] in (0, None) else f" (rs274 exit {r['rs274_rc']})"))
    print()
    from trueaxis.compiled import aot_available

    print(f"small program, process start to file written, warm (goal <= 0.3 s; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; kernels compiled ahead of time: "
          f"{'yes' if aot_available() else 'NO (python -m trueaxis.warm builds them): numba JIT'}):")
    for name, prog, mach in cases:
        best, med, cpu, small = small_program(prog, mach, work)
        print(f"  {name:42s} 100 blocks: best {best:.2f} s, median {med:.2f} s wall, {cpu:.2f} s CPU  "
              f"{'met' if best <= 0.3 else 'MISSED'}")
    if args.profile:
        for _, prog, mach in cases:
            profile_post(prog, mach)


if __name__ == "__main__":
    main()
