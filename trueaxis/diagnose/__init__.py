"""The sim-to-real gap (DESIGN §8): where it lies, which unmodelled effect explains it, how far it shrinks.

    trueaxis diagnose --cloud cmm.ply --part nas979 --machine TWIN.toml --program prog.ngc -o report/
    trueaxis diagnose --cloud a.ply --program a.ngc --cloud b.ply --program b.ngc --pause-s S ...   # parts cut in turn

Several measured parts cut one after another on the machine (a second placement of the part, the same program
after a warm-up) are diagnosed together: each is read against the twin on its own, then the candidates are fitted
to all at once with one set of parameters (``report.run_diagnosis_cuts``, ``state.combine_states``).

Modules: ``state`` (the twin cuts the program in the virtual shop; the gap and the machine state at every measured
point), ``candidates`` (the library of candidate effects, sensitivities linear in their parameters), ``analysis``
(held-out folds, noise estimate, where / which / how far), ``report`` (JSON + HTML with pictures, the command).

Candidate effect names (``--candidates all`` or a comma-separated list of these), named the ISO 230 way where a
name exists:

- ``backlash_x/y/z/a/b/c``: reversal error (lost motion) of any axis, linear or rotary, taken up over a transition
  travel after each reversal (the transition chosen from a grid by the fit).
- ``servo_lag``: following error of each axis' position loop, its own lag per axis (what velocity feed-forward
  leaves, (1 - ff) / kv) as a positive mixture over loop time constants 4, 12, 35 ms; rotary axes included.
- ``force_deflection``: machine compliance (diagonal: X, Y and Z apart) times the estimated cutting force.
- ``tool_deflection``: tool bending, force normal to the tool times a compliance linear in the contact height.
- ``thermal_x/y/z``: drift along a machine direction, a monotone first-order response to the running time;
  ``thermal_spline_x/y/z``: the same drift as a free linear spline, named only when it beats the first-order form
  on held-out points by a margin.
- ``rotary_radial_<axis>``, ``rotary_axial_<axis>``, ``rotary_tilt_<axis>``, ``rotary_angular_<axis>``: the ISO
  230-7 error motions of a rotary axis (e.g. C: EXC/EYC, EZC, EAC/EBC, ECC), harmonics 1 to 4 per turn (plus a
  term linear in the angle on an axis of limited travel).
- ``twin_parameters``: re-identification of the twin's own location errors (a wrong value, not a missing effect).

A candidate that cannot move the surface on the given part and program (no such axis, an axis that does not turn, a
direction along the tool on a flank-milled cone, no [cutting] coefficients for a force) is listed as not applicable.
"""
