"""Driver run by ``freecadcmd``: open a STEP file in FreeCAD and say what FreeCAD sees (volume, faces, bounding box).

Environment (freecadcmd passes no arguments to a script): TRUEAXIS_STEP (the file), TRUEAXIS_TEST_OUT (a JSON file
to write). freecadcmd exits 0 even when a script raises, so any failure ends the process with status 1.
"""

import json
import os
import sys
import traceback

try:
    import Part  # FreeCAD's OCCT binding

    shape = Part.read(os.environ["TRUEAXIS_STEP"])
    box = shape.BoundBox
    facts = {"volume_mm3": shape.Volume, "solids": len(shape.Solids), "faces": len(shape.Faces),
             "valid": shape.isValid(), "bbox": [box.XMin, box.YMin, box.ZMin, box.XMax, box.YMax, box.ZMax]}
    with open(os.environ["TRUEAXIS_TEST_OUT"], "w") as f:
        json.dump(facts, f)
except Exception:  # noqa: BLE001 - any failure must reach the test as a non-zero exit
    traceback.print_exc()
    sys.exit(1)
sys.exit(0)
