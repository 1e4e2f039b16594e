"""The NC program as data (layer 3; docs/architecture.md).

``gcode``: one tokenizer and the RS-274 interpreter (program text into arrays of motion rows, LinuxCNC semantics),
with its parts as LinuxCNC's rs274ngc splits them: ``interp_read`` (a block's words), ``interp_arc`` (G2/G3),
``interp_cycles`` (G73, G81-G89); ``grammar`` (the number, the planes) and ``rows`` (the motion table's codes);
``fast_read``: the compiled pre-scan; ``flatten``: LinuxCNC's O-word subroutines, loops and parameters evaluated into
plain blocks; ``check``: what a block may not contain (rs274's own checks); ``cl``: CL data (CSV, APT GOTO/) read and
turned into machine-axis G-code through the machine's inverse kinematics; ``setup``: the controller's setup (LinuxCNC
.var file, tool table, setup file); ``fast_write``: the compiled writer of plain motion blocks; ``trajectory``: the
interpolator. Imports ``machine`` and the base modules only.
"""
