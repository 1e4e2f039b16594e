"""The sim-to-real gap (DESIGN §8): where it lies, which unmodelled effect explains it, how far it shrinks.

    trueaxis diagnose --cloud cmm.ply --part nas979 --machine TWIN.toml --program prog.ngc -o report/

Modules: ``state`` (the twin cuts the program in the virtual shop; the gap and the machine state at every measured
point), ``candidates`` (the library of candidate effects, sensitivities linear in their parameters), ``analysis``
(held-out folds, noise estimate, where / which / how far), ``report`` (JSON + HTML with pictures, the command).

Candidate effect names (``--candidates all`` or a comma-separated list of these):

- ``backlash_x``, ``backlash_y``, ``backlash_z``: lost motion of a linear axis, a step with the direction of motion.
- ``servo_lag``: following error of first-order position loops, transients at corners and stops included: a
  positive mixture of loops with lag times 4, 12 and 35 ms shared by the axes (the lag time is the sum of the
  weights, ms) and each further axis' lag-time mismatch against the first moving axis.
- ``force_deflection``: machine compliance (diagonal: X, Y and Z apart) times the estimated cutting force.
- ``tool_deflection``: tool bending, force normal to the tool times a compliance linear in the contact height.
- ``thermal_x``, ``thermal_y``, ``thermal_z``: drift along a machine direction, a linear spline of time from zero.
- ``rotary_periodic_c``, ``rotary_periodic_b``, ``rotary_periodic_a``: once/twice-per-turn harmonics of a rotary
  axis' angle error.
- ``twin_parameters``: re-identification of the twin's own location errors (a wrong value, not a missing effect).

A candidate that cannot move the surface on the given part and program (no such axis, an axis that does not turn, a
direction along the tool on a flank-milled cone, no [cutting] coefficients for a force) is listed as not applicable.
"""
