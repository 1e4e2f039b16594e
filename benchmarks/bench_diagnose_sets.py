"""``make bench`` entry of the diagnosis benchmark (issue 14): every case set (tuning and the seven held-out sets)
through Dask, every figure of the issue's "Done when", and the diagnosis time of a cone probed as ``make demo`` probes
it.

The full sets take about forty-five minutes on two cores; by default this runs 30 cases of each set spread over its list
(every kind of case is represented: the list interleaves the effect kinds, magnitudes, pairs, out-of-library cases
and controls). ``TRUEAXIS_BENCH_FULL=1`` runs them all; extra arguments go to ``diagnose_sets.py`` (see there).
Tune the diagnosis on ``diagnose_sets.py --set tuning`` only: this entry prints the held-out sets' figures too.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import diagnose_sets  # noqa: E402

if __name__ == "__main__":
    full = os.environ.get("TRUEAXIS_BENCH_FULL") == "1"
    args = ["--set", "all", "--points", "800", "--demo-timing"] + ([] if full else ["--cases", "30"])
    sys.exit(diagnose_sets.main(args + sys.argv[1:]))
