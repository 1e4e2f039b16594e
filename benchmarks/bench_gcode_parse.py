"""Parse speed of the G-code reader: NIST mtc_plate_1.nc repeated to 1,000,000 lines (target >= 300,000 lines/s)."""

import time
from pathlib import Path

from trueaxis.nc.gcode import parse_program

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "fixtures" / "programs" / "nist" / "mtc_plate_1.nc"
TARGET_LINES = 1_000_000


def main() -> None:
    lines = SOURCE.read_text().splitlines(keepends=True)
    body = [ln for ln in lines if not ln.startswith("%") and "M30" not in ln]
    reps = TARGET_LINES // len(body) + 1
    text = "".join(body * reps)
    text = "".join(text.splitlines(keepends=True)[:TARGET_LINES])
    n_lines = text.count("\n")
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        prog = parse_program(text, "bench")
        best = min(best, time.perf_counter() - t0)
    print(f"parsed {n_lines} lines ({len(prog)} moves) in {best:.2f} s: {n_lines / best:,.0f} lines/s "
          f"(target 300,000)")


if __name__ == "__main__":
    main()
