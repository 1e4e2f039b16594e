"""Driver run by ``freecadcmd``: a real FreeCAD CAM job, posted by FreeCAD's linuxcnc post and by trueaxis_post.

trueaxis_post.py must be installed in FreeCAD's macro folder (the test runs FreeCAD with a private HOME and installs
it there with trueaxis' install_post); FreeCAD loads it by name as for any post processor.

Environment (freecadcmd passes no arguments to a script):
  TRUEAXIS_TEST_OUT     folder for the outputs
  TRUEAXIS_MACHINE      machine file for the trueaxis post
  TRUEAXIS_BIN          the trueaxis executable (read by the post script itself)
  TRUEAXIS_SETUP_ARGS   the control's setup options for the trueaxis post (e.g. --var F --tool-table T)

The part: a 60 x 40 x 10 mm block with a 30 x 20 x 5 mm pocket, placed in the machine frame of the test machine
(top face at Z = -300, centred on X = Y = 0), since trueaxis reads program coordinates as machine axes. The job: one
6 mm three-flute end mill at 8000 rpm and 600 mm/min, an outside Profile run counter-clockwise (climb) and a Pocket
on the pocket floor (climb, 50 % step-over).

Outputs in TRUEAXIS_TEST_OUT:
  linuxcnc.ngc         FreeCAD's linuxcnc post, --no-header
  trueaxis.ngc         trueaxis_post, --no-header, geometric compensation
  trueaxis_return.ngc  what trueaxis_post's export returned for that file
  trueaxis_none.ngc    trueaxis_post with --mode none (no correction: the linuxcnc program plus the comments)
  trueaxis_numbered.ngc  trueaxis_post, geometric, with the linuxcnc post's --line-numbers --no-comments
  trueaxis_short.ngc   trueaxis_post, as trueaxis.ngc, the machine given by its fixture short name (the file's stem)
  job.json             what the job says (tool, speeds, operations) and the outcome of the posts refused
freecadcmd exits 0 even when a script raises, so any failure here ends the process with status 1.
"""

import json
import os
import sys
import traceback

try:
    import FreeCAD
    import Part
    from FreeCAD import Vector
    from PathScripts import PathJob, PathPocketShape, PathProfile
    from PathScripts import PathPreferences
    from PathScripts.PathPostProcessor import PostProcessor

    OUT = os.environ["TRUEAXIS_TEST_OUT"]
    MACHINE = os.environ["TRUEAXIS_MACHINE"]
    TOP_Z = -300.0

    doc = FreeCAD.newDocument("trueaxis_post_test")
    block = doc.addObject("Part::Feature", "Block")
    block.Shape = Part.makeBox(60, 40, 10, Vector(-30, -20, TOP_Z - 10)).cut(
        Part.makeBox(30, 20, 5, Vector(-15, -10, TOP_Z - 5)))
    doc.recompute()

    job = PathJob.Create("Job", [block])
    tc = job.Tools.Group[0]
    tc.Tool.Diameter = 6.0
    tc.Tool.Flutes = 3
    tc.SpindleSpeed = 8000.0
    tc.HorizFeed = "600 mm/min"
    tc.VertFeed = "200 mm/min"
    model = job.Model.Group[0]  # the job's clone of the block

    profile = PathProfile.Create("Profile", parentJob=job)
    profile.Direction = "CCW"
    profile.setExpression("StepDown", None)  # else the setup sheet's default expression wins at recompute
    profile.StepDown = 4.0

    floor = ["Face%d" % (i + 1) for i, f in enumerate(model.Shape.Faces)
             if abs(f.CenterOfMass.z - (TOP_Z - 5)) < 1e-6 and f.normalAt(0, 0).z > 0.99]
    assert len(floor) == 1, floor
    pocket = PathPocketShape.Create("Pocket", parentJob=job)
    pocket.Base = [(model, floor)]
    pocket.StepOver = 50
    pocket.setExpression("StepDown", None)
    pocket.StepDown = 2.5
    pocket.OffsetPattern = "Offset"
    doc.recompute()
    for op in (profile, pocket):
        assert len(op.Path.Commands) > 10, "%s has no tool path" % op.Label

    try:  # the post list exactly as FreeCAD's Post command builds it (fixtures, tool changes, operations)
        from PathScripts import PathPost
        postlist = PathPost.CommandPathPost().buildPostList(job)[0]
    except Exception:
        postlist = [tc, profile, pocket]

    linuxcnc = PostProcessor.load("linuxcnc")
    linuxcnc.export(postlist, os.path.join(OUT, "linuxcnc.ngc"), "--no-header --no-show-editor")

    assert "trueaxis" in PathPreferences.allAvailablePostProcessors(), PathPreferences.searchPathsPost()
    trueaxis = PostProcessor.load("trueaxis")
    module = trueaxis.script
    args = "--machine %s --mode geometric --tol-um 1 --no-header --no-show-editor %s" % (
        MACHINE, os.environ.get("TRUEAXIS_SETUP_ARGS", ""))
    returned = trueaxis.export(postlist, os.path.join(OUT, "trueaxis.ngc"), args)
    with open(os.path.join(OUT, "trueaxis_return.ngc"), "w") as f:
        f.write(returned)

    trueaxis.export(postlist, os.path.join(OUT, "trueaxis_none.ngc"), args.replace("geometric", "none"))
    trueaxis.export(postlist, os.path.join(OUT, "trueaxis_numbered.ngc"), args + " --line-numbers --no-comments")
    short_name = os.path.splitext(os.path.basename(MACHINE))[0]  # a fixture machine: trueaxis finds it by name
    try:
        trueaxis.export(postlist, os.path.join(OUT, "trueaxis_short.ngc"), args.replace(MACHINE, short_name, 1))
        short_name_refused = None
    except module.TrueaxisPostError as exc:
        short_name_refused = str(exc)

    refused_path = os.path.join(OUT, "refused.ngc")
    try:
        trueaxis.export(postlist, refused_path, args + " --max-correction-mm 0.000001")
        refused = None
    except module.TrueaxisPostError as exc:
        refused = str(exc)
    # options neither the script nor the linuxcnc post knows, or a bad value for the latter: an error to report, not
    # the linuxcnc post's argparse exiting (SystemExit inside FreeCAD)
    bad_options = {}
    for extra in ("--frobnicate 3", "--precision abc"):
        try:
            trueaxis.export(postlist, os.path.join(OUT, "bad_option.ngc"), args + " " + extra)
            bad_options[extra] = "accepted"
        except module.TrueaxisPostError as exc:
            bad_options[extra] = "TrueaxisPostError: " + str(exc).splitlines()[0]
        except BaseException as exc:  # noqa: BLE001 - what escaped is the finding
            bad_options[extra] = f"{type(exc).__name__}: {exc}"

    facts = {
        "postlist": [o.Label for o in postlist],
        "post_script": module.__file__,
        "tool": {"diameter": tc.Tool.Diameter.Value, "flutes": tc.Tool.Flutes, "spindle_rpm": tc.SpindleSpeed,
                 "horiz_feed_mm_min": float(tc.HorizFeed.getValueAs("mm/min")), "spindle_dir": tc.SpindleDir},
        "profile": {"Direction": profile.Direction, "Side": profile.Side, "StepDown": profile.StepDown.Value},
        "pocket": {"CutMode": pocket.CutMode, "StepOver": pocket.StepOver, "StepDown": pocket.StepDown.Value},
        "conditions": {o.Label: module.conditions_comment(module.cutting_conditions(o)) for o in postlist},
        "refused_message": refused,
        "short_name_refused": short_name_refused,
        "refused_file_written": os.path.exists(refused_path),
        "bad_options": bad_options,
        "bad_option_file_written": os.path.exists(os.path.join(OUT, "bad_option.ngc")),
    }
    with open(os.path.join(OUT, "job.json"), "w") as f:
        json.dump(facts, f, indent=2)
except BaseException:
    traceback.print_exc()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(1)
sys.stdout.flush()
os._exit(0)
