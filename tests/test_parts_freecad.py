"""The test parts' STEP files open in FreeCAD 0.20 (a real freecadcmd) as the solids the part JSON describes."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from conftest import require_program
from trueaxis.workpiece.part import write_part

DRIVER = Path(__file__).resolve().parent / "freecad_scripts" / "read_step.py"


@pytest.mark.external
@pytest.mark.parametrize("part", ["nas979", "slots"])
def test_freecad_opens_the_step_with_the_analytic_volume(part, tmp_path):
    freecadcmd = require_program("freecadcmd")
    paths = write_part(part, tmp_path / "part")
    doc = json.loads(paths["json"].read_text())
    out = tmp_path / "facts.json"
    env = {**os.environ, "HOME": str(tmp_path), "TRUEAXIS_STEP": str(paths["step"]), "TRUEAXIS_TEST_OUT": str(out)}
    proc = subprocess.run([freecadcmd, str(DRIVER)], env=env, stdin=subprocess.DEVNULL, capture_output=True,
                          text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    facts = json.loads(out.read_text())
    assert facts["valid"] and facts["solids"] == 1
    # FreeCAD's own OCCT computes the volume of the B-rep; the JSON's comes from the closed-form frustum, wedge and
    # slot sweep. Exact B-rep surfaces: they agree to rounding.
    assert facts["volume_mm3"] == pytest.approx(doc["derived"]["volume_mm3"], rel=1e-7)
