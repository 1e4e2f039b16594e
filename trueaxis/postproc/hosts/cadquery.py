"""The CadQuery host: the test parts as Workplane methods, and the Python hook that compensates G-code.

CadQuery's plugin convention (its documentation, "Extending CadQuery"; the CadQuery/cadquery-plugins collection): a
plugin is a function whose first argument is the Workplane, attached to ``cq.Workplane`` as a method, and importing the
plugin module attaches it. Importing this module therefore registers:

- ``Workplane.nas979(**overrides)``: the NAS 979 cone-frustum test part (keyword overrides of ``Nas979Params``, mm and
  deg), its part frame placed on the calling workplane's plane, the solid pushed on the stack;
- ``Workplane.slotBlock(**overrides)``: the slot block (overrides of ``SlotBlockParams``), the same way.

``register()`` does the same explicitly (idempotent) and ``unregister()`` takes the methods away again.

The hook for programs made from CadQuery models (by a CAM library, or by hand from the model's edges) is the API
``trueaxis.postproc.compensate(text, machine, mode="geometric")``: machine-axis G-code text in, compensated text out,
``PostError`` (``file:line: reason``) when the post refuses; ``machine`` a ``Machine``, a machine file's path or a
fixture machine's short name, as the command line's ``--machine``. The control's setup goes in as keywords, as on the
command line: ``var=``, ``tool_table=``, ``machine_units=``, ``setup=`` (a setup file), ``offsets_zero=``
(docs/setup_file.md); ``arcs=`` (arcs fitted to the corrected path as G2/G3: True / False, default on for a
three-axis mill) and ``output_mode=`` ("joint" or "tcp", default the machine file's), as ``--arcs`` / ``--no-arcs``
and ``--output-mode``. See ``docs/cadquery_example.py``::

    import cadquery as cq
    import trueaxis.postproc.hosts.cadquery  # registers Workplane.nas979 / Workplane.slotBlock
    from trueaxis.machine import load_machine
    from trueaxis.postproc import compensate

    part = cq.Workplane("XY").nas979()
    gcode = my_cam(part)  # machine-axis G-code for the part
    compensated = compensate(gcode, load_machine("machine.toml"), mode="geometric")
"""

from __future__ import annotations

import cadquery as cq

from ...workpiece.parts import nas979_workplane, slot_block_workplane
from ..post import compensate

# Workplane method name -> plugin function (CadQuery's names are camelCase: ``slotBlock`` like ``cboreHole``).
PLUGINS = {"nas979": nas979_workplane, "slotBlock": slot_block_workplane}


def register() -> None:
    """Attach the test parts to ``cadquery.Workplane`` as methods (CadQuery's plugin convention); idempotent."""
    for name, function in PLUGINS.items():
        setattr(cq.Workplane, name, function)


def unregister() -> None:
    """Remove the methods that ``register`` attached (others of the same name are left alone)."""
    for name, function in PLUGINS.items():
        if getattr(cq.Workplane, name, None) is function:
            delattr(cq.Workplane, name)


register()

__all__ = ["PLUGINS", "compensate", "register", "unregister"]
