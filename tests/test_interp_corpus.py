"""Interpreter corpus against LinuxCNC's own verdicts (issue 17: read what LinuxCNC reads, or say what is not read).

Every program of the table is run through ``rs274`` (LinuxCNC's interpreter, with a tool table) and through our reader.
The table says what rs274 does with it, and that is checked first, so the table cannot drift from LinuxCNC:

- ``ok``: rs274 reads it; we read it too, with the same moves: the same count and the same end points in machine
  coordinates (rs274's program coordinates plus the G5x and G92 offsets it announces) within 1e-4 program units;
- ``refused``: rs274 refuses it; we refuse it with ``file:line: reason``;
- ``not read``: rs274 reads it, we refuse it and say what is not read (the reason must contain the given text).
"""

from __future__ import annotations

import re
import subprocess

import numpy as np
import pytest

from rs274_helpers import parse_canon, require_rs274, tool_table_text
from trueaxis.nc.gcode import GcodeError, parse_program

OK, REFUSED = "ok", "refused"


def _arc_limit(units: str, arc: str, run: bool = False) -> str:
    """A program that ends with the arc ``arc`` from X0 Y0 (LinuxCNC's limits of an arc's radii, interp_arc.cc); with
    ``run``, after 20 half circles of radius 10 there and back (a run the compiled reader takes: it must hand the last
    arc to the reader, or read it as the reader would)."""
    back = "G2 X20 Y0 I10 J0\nG2 X0 Y0 I-10 J0\n" * 10 if run else ""
    return f"{units} G17 G90 F100\nG0 X0 Y0 Z0\n{back}{arc}\nM2\n"


# An I J K arc: radii differing by at most 0.028284 mm (0.0028284 in), or by more within 0.1 % of the larger, never by
# 100 times that; no radius below 0.00127 mm (0.00005 in). An R arc: its radius short of half the chord by at most
# 0.00127 mm (0.00005 in). (The reader had 0.05 mm and 0.002 in, also for R arcs, and no zero-radius or 100x limit.)
ARC_LIMITS = [
    ("arc_mm_spiral_in", OK, "G21", "G2 X20.0282 Y0 I10 J0"),
    ("arc_mm_spiral_out", REFUSED, "G21", "G2 X20.0283 Y0 I10 J0"),
    ("arc_mm_spiral_far", REFUSED, "G21", "G2 X20.045 Y0 I10 J0"),
    ("arc_mm_large_in", OK, "G21", "G2 X6002.8 Y0 I3000 J0"),
    ("arc_mm_large_out", REFUSED, "G21", "G2 X6002.9 Y0 I3000 J0"),
    ("arc_inch_spiral_in", OK, "G20", "G2 X2.0028 Y0 I1 J0"),
    ("arc_inch_spiral_out", REFUSED, "G20", "G2 X2.0029 Y0 I1 J0"),
    ("arc_mm_r_in", OK, "G21", "G2 X20 Y0 R9.999"),
    ("arc_mm_r_out", REFUSED, "G21", "G2 X20 Y0 R9.9987"),
    ("arc_inch_r_in", OK, "G20", "G2 X2 Y0 R.99996"),
    ("arc_inch_r_out", REFUSED, "G20", "G2 X2 Y0 R.99994"),
    ("arc_mm_zero_radius", REFUSED, "G21", "G2 X0.002 Y0 I0.001 J0"),
    ("arc_mm_small_radius", OK, "G21", "G2 X0.0026 Y0 Z-1 I0.0013 J0"),
    ("arc_inch_zero_radius", REFUSED, "G20", "G2 X0.00008 Y0 I0.00004 J0"),
    ("arc_inch_small_radius", OK, "G20", "G2 X0.00012 Y0 Z-1 I0.00006 J0"),
]

CORPUS = [
    # -- parameters and expressions
    ("params_named", OK, "G21 G90\n#1=2\n#<a>=[#1*3]\nG0 X#<a> Y[SQRT[2]]\nM2\n"),
    ("param_1111", OK, "#1111 = 12.5\nG21 G0 X#1111 Y[#1111 / 5]\nM2\n"),
    ("arith_precedence", OK, "G21\nG0 X[1+2*3] Y[2*3**2] Z[10 MOD 3]\nG0 X[-2 MOD 3] Y[8/2/2] Z[2**3**2]\nM2\n"),
    ("trig_functions", OK, "G21\nG0 X[SIN[30]] Y[COS[60]] Z[TAN[45]]\nG0 X[ASIN[0.5]] Y[ACOS[0.5]] Z[ATAN[1]/[-1]]\n"
                           "M2\n"),
    ("other_functions", OK, "G21\nG0 X[ABS[-3]] Y[EXP[1]] Z[LN[10]]\nG0 X[ROUND[-2.5]] Y[FIX[-2.5]] Z[FUP[-2.5]]\n"
                            "G0 X[ROUND[2.5]] Y[FIX[2.7]] Z[FUP[2.1]]\nM2\n"),
    ("logic", OK, "G21\nG0 X[1 EQ 1] Y[1 NE 1] Z[2 GT 1]\nG0 X[1 GE 1] Y[1 LT 1] Z[1 LE 2]\n"
                  "G0 X[3 AND 0 OR 1] Y[1 XOR 1] Z[0 OR 0]\nG0 X[1 EQ 1.00001] Y[2 GE 2.00001] Z[1 - 1 - 1]\nM2\n"),
    ("assign_after_line", OK, "G21\n#3=5 G0 X#3\nG0 Y#3\nM2\n"),
    ("unset_param_zero", OK, "G21\nG0 X[#77+1] Y#4000\nM2\n"),
    ("indirect_param", OK, "G21\n#1=5\n#5=7\nG0 X##1 Y#[#1+0]\nM2\n"),
    ("unary_minus", OK, "G21\n#1=2\nG0 X-#1 Y-[#1*2] Z+#1\nM2\n"),
    ("spaces_comments", OK, "G21\nG0 X [ 1 + 2 ] (a comment) Y 1 0\n# 2 = 4 ; set\nG0 Z#2\nM2\n"),
    ("lower_case", OK, "g21\n#<Big>=3\ng0 x#<big> y[sqrt[9]]\nm2\n"),
    ("exists", OK, "G21\n#<a>=1\nG0 X[EXISTS[#<a>]] Y[EXISTS[#<b>]]\nM2\n"),
    ("feed_param", OK, "G21\n#1=200\nG0 X0 Y0\nG1 X1 F#1\nG1 Y[#1/100] F[#1*2]\nM2\n"),
    ("inch_params", OK, "G20\n#1=0.5\nG0 X#1 Y[#1*2]\nG21\nG0 X#1\nM2\n"),
    ("param_g_code", OK, "G21\n#1=1\nG0 X0\nG#1 X2 F100\nM2\n"),
    ("arc_params", OK, "G21 G17 F100\nG0 X0 Y0\n#<r>=5\nG2 X[2*#<r>] Y0 I#<r> J0\nG3 X0 Y0 R#<r>\nM2\n"),
    ("global_named", OK, "G21\n#<_g>=4\no<s> sub\nG0 X#<_g>\n#<_g>=6\no<s> endsub\no<s> call\nG0 Y#<_g>\nM2\n"),
    # -- subroutines
    ("sub_args_restore", OK, "#1=7\no<s> sub\nG0 X#1 Y#2\n#1=9\no<s> endsub\nG21\no<s> call [3]\nG0 Z#1\nM2\n"),
    ("sub_numbered", OK, "G21\no100 sub\nG91 G0 X#1\no100 endsub\no100 call [1]\no100 call [2+1]\nG90 G0 Y1\nM2\n"),
    ("sub_nested", OK, "G21\no<b> sub\nG0 Y#1\no<b> endsub\no<a> sub\nG0 X#1\no<b> call [#1*2]\no<a> endsub\n"
                       "o<a> call [1]\no<a> call [2]\nM2\n"),
    ("sub_local_named", OK, "G21\no<s> sub\n#<k>=[#1+1]\nG0 X#<k>\no<s> endsub\no<s> call [1]\no<s> call [5]\nM2\n"),
    ("sub_return", OK, "G21\no<r> sub\nG0 X1\no6 if [#1 GT 0]\no<r> return\no6 endif\nG0 X2\no<r> endsub\n"
                       "o<r> call [1]\no<r> call [0]\nM2\n"),
    ("sub_thirty_args", OK, "G21\no<s> sub\nG0 X#30 Y#1 Z#29\no<s> endsub\no<s> call " +
     " ".join(f"[{i}]" for i in range(1, 31)) + "\nM2\n"),
    # -- control flow
    ("if_elseif", OK, "G21\n#1=2\no1 if [#1 EQ 1]\nG0 X1\no1 elseif [#1 EQ 2]\nG0 X2\no1 else\nG0 X3\no1 endif\nM2\n"),
    ("if_else", OK, "G21\n#1=5\no1 if [#1 EQ 1]\nG0 X1\no1 elseif [#1 EQ 2]\nG0 X2\no1 else\nG0 X3\no1 endif\nM2\n"),
    ("if_first", OK, "G21\n#1=1\no1 if [#1 EQ 1]\nG0 X1\no1 elseif [#1 EQ 1]\nG0 X2\no1 else\nG0 X3\no1 endif\n"
                     "M2\n"),
    ("if_nested", OK, "G21\n#1=1\n#2=0\no1 if [#1]\no2 if [#2]\nG0 X1\no2 else\nG0 X2\no2 endif\no1 endif\nM2\n"),
    ("while", OK, "G21\n#1=0\no1 while [#1 LT 3]\nG0 X#1\n#1=[#1+1]\no1 endwhile\nM2\n"),
    ("while_never", OK, "G21\n#1=5\no1 while [#1 LT 3]\nG0 X#1\no1 endwhile\nG0 Y1\nM2\n"),
    ("do_while", OK, "G21\n#1=0\no2 do\nG0 Y#1\n#1=[#1+1]\no2 while [#1 LT 3]\nM2\n"),
    ("do_once", OK, "G21\n#1=9\no2 do\nG0 Y#1\no2 while [#1 LT 3]\nM2\n"),
    ("repeat", OK, "G21\nG91\no3 repeat [4]\nG0 X1\no3 endrepeat\nG90\nG0 Y0\nM2\n"),
    ("repeat_nested", OK, "G21\nG91\no3 repeat [2]\no4 repeat [3]\nG0 X1\no4 endrepeat\nG0 Y1\no3 endrepeat\n"
                          "G90\nM2\n"),
    ("break", OK, "G21\n#1=0\no4 while [1]\n#1=[#1+1]\no5 if [#1 GT 3]\no4 break\no5 endif\nG0 X#1\no4 endwhile\n"
                  "M2\n"),
    ("continue", OK, "G21\n#1=0\no4 while [#1 LT 5]\n#1=[#1+1]\no5 if [#1 EQ 2]\no4 continue\no5 endif\nG0 X#1\n"
                     "o4 endwhile\nM2\n"),
    ("loop_arcs", OK, "G21 G17 F100\nG0 X10 Y0\n#1=0\no1 while [#1 LT 4]\n#1=[#1+1]\n"
                      "G3 X[10*COS[#1*90]] Y[10*SIN[#1*90]] I[-10*COS[[#1-1]*90]] J[-10*SIN[[#1-1]*90]]\n"
                      "o1 endwhile\nM2\n"),
    ("fanuc_m98_l", OK, "G21\nM98 P100 L2\nM30\nO100\nG91 G0 X1\nM99\n"),
    ("fanuc_m98", OK, "G21\nG0 X0\nM98 P200\nG0 Y1\nM30\nO200\nG0 Z-1\nM99\n"),
    # -- plain programs: arcs, cycles in G91, offsets
    ("arcs_r_turns", OK, "G21 F100\nG0 X0 Y0\nG2 X0 Y0 I5 J0 P2\nG3 X10 Y0 R5\nX0 Y0 R5\nM2\n"),
    ("arcs_planes", OK, "G21 F100\nG0 X0 Y0 Z0\nG18 G2 X10 Z0 I5 K0\nG19 G3 Y10 Z0 J5 K0\nG17 G91 G2 X-10 Y0 I-5 J0\n"
                        "M2\n"),
    ("cycle_g81_g91", OK, "G21 G90 F100\nG0 X0 Y0 Z10\nG91 G98 G81 X10 Y0 Z-5 R-2 L3\nG80\nG90 G0 Z10\nM2\n"),
    ("cycle_g81_g91_g99", OK, "G21 G90 F100\nG0 X0 Y0 Z10\nG91 G99 G81 X10 Y0 Z-5 R-2 L3\nG80\nG90 G0 Z10\nM2\n"),
    ("cycle_g82_g91_l", OK, "G21 G90 F100\nG0 X0 Y0 Z10\nG99\nG91 G82 X-4 Y3 Z-8 R-1 P0.2 L4\nG80\nM2\n"),
    ("cycle_g83_g91", OK, "G21 G90 F100\nG0 X0 Y0 Z10\nG91 G98 G83 X5 Y5 Z-6 R-2 Q2 L2\nG80\nG90 G0 Z10\nM2\n"),
    ("cycle_g73_g82", OK, "G21 G90 F100\nG0 X0 Y0 Z10\nG99 G73 X1 Y1 Z-3 R2 Q1\nG82 X2 Y2 Z-2 R2 P0.5\nG80\nM2\n"),
    ("cycle_modal", OK, "G21 G90 F100\nG0 X0 Y0 Z10\nG98 G81 X1 Y1 Z-1 R1\nX2 Y2\nY3\nG80\nG0 Z10\nM2\n"),
    ("cycle_modal_g99", OK, "G21 G90 F100\nG0 X0 Y0 Z10\nG99 G81 X1 Y1 Z-1 R1\nX2 Y2\nY3\nG80\nG0 Z10\nM2\n"),
    ("g92_offset", OK, "G21\nG0 X5 Y5\nG92 X0 Y0\nG0 X1 Y1\nG92.1\nG0 X1 Y1\nM2\n"),
    ("g10_l2_g55", OK, "G21\nG10 L2 P2 X10 Y20\nG55 G0 X1 Y1\nG54 G0 X1 Y1\nM2\n"),
    ("g10_params", OK, "G21\n#1=2\n#2=30\nG10 L2 P#1 X[#2/3] Y0\nG55 G0 X1 Y1\nG54\nM2\n"),
    ("fanuc_number", OK, "O0001\nG21 G90\nG0 X1 Y2\nM30\n"),
    ("many_groups", OK, "G21 G90 G94 G17 G40 G49 G80 G54\nG0 G90 G54 X1 Y1 S1000 M3\nM8\nG4 P0.5\nG64 P0.01\n"
                        "M5 M9\nM2\n"),
    ("block_delete", OK, "G21\nG0 X0\n/G0 X1\nM2\n"),
    # G43.1's axis words are its tool offset, not a move: no motion mode need be in force (a QA pass: refused before
    # the first move), none moves after G1 or G80; absolute in G91 too
    ("g43_1_first", OK, "G21 G90 G17 G94\nG43.1 Z0\nG0 X10 Y20 Z-100\nG1 X20 F300\nM2\n"),
    ("g43_1_xyz_first", OK, "G21\nG43.1 X1 Y2 Z5\nG0 X10 Y20 Z-10\nM2\n"),
    ("g43_1_in_g1", OK, "G21\nG0 X0 Y0 Z0\nG1 X1 F100\nG43.1 Z5\nX2\nM2\n"),
    ("g43_1_after_g80", OK, "G21\nG0 X0\nG80\nG43.1 Z5\nG0 X1\nM2\n"),
    ("g43_1_g91", OK, "G21 G91\nG43.1 Z5\nG0 X10 Z-10\nG43.1 Z7\nG0 X1\nM2\n"),
    ("g10_l1_first", OK, "G21\nG10 L1 P1 Z5\nT1 M6\nG43 H1\nG0 X1 Z0\nM2\n"),
    # ... and the other codes of the block take them too: a motion code (the offset, then a move to the same words
    # under it), G10, G28 / G30 (their intermediate point), G92
    ("g43_1_with_g1", OK, "G21\nG0 X10 Y20 Z-100\nG1 G43.1 Z5 F300\nG1 X20\nM2\n"),
    ("g43_1_with_g0_xz", OK, "G21\nG0 X10 Y20 Z-100\nG0 G43.1 X3 Z5\nG1 X20 F300\nM2\n"),
    ("g43_1_with_g91_g1", OK, "G21\nG0 X10 Y20 Z-100\nG91 G1 G43.1 Z5 F300\nG1 X1\nM2\n"),
    ("g43_1_with_g28", OK, "G21\nG0 X1 Y1 Z1\nG28 G43.1 Z5\nG0 X2\nM2\n"),
    ("g43_1_with_g30", OK, "G21\nG0 X1 Y1 Z1\nG30 G43.1 Z5\nG0 X2\nM2\n"),
    ("g43_1_with_g10_l2", OK, "G21\nG0 X1 Y1 Z1\nG10 L2 P1 G43.1 Z5\nG0 X2 Z0\nM2\n"),
    ("g43_1_with_g92", OK, "G21\nG0 X1 Y1 Z1\nG92 G43.1 Z5\nG0 X2 Z0\nM2\n"),
    ("percent", OK, "%\nG21\n#1=3\nG0 X#1\n%\n"),
    # -- refused by rs274
    ("two_motion", REFUSED, "G21\nG1 G0 X10\nM2\n"),
    ("two_spindle_m", REFUSED, "G21\nG0 X0\nM3 M4\nM2\n"),
    ("two_coolant_m", REFUSED, "G21\nG0 X0\nM7 M8\nM2\n"),
    ("two_planes", REFUSED, "G21\nG17 G18 G0 X1\nM2\n"),
    ("two_distance", REFUSED, "G21\nG90 G91 G0 X1\nM2\n"),
    ("two_units", REFUSED, "G21\nG20 G21\nM2\n"),
    ("two_systems", REFUSED, "G21\nG54 G55\nM2\n"),
    ("two_tlo", REFUSED, "G21\nG43 G49\nM2\n"),
    ("two_nonmodal", REFUSED, "G21\nG53 G4 P1\nM2\n"),
    ("two_axis_users", REFUSED, "G21\nG0 G28 X1\nM2\n"),
    ("r_no_use", REFUSED, "G21\nR5\nM2\n"),
    ("r_with_g1", REFUSED, "G21\nG0 X0\nG1 X1 R5 F100\nM2\n"),
    ("i_no_use", REFUSED, "G21\nG0 X0\nG1 X1 F10 I2\nM2\n"),
    ("p_no_use", REFUSED, "G21\nG0 X0\nG1 X1 F10 P2\nM2\n"),
    ("q_no_use", REFUSED, "G21\nG0 X0\nG1 X1 F10 Q1\nM2\n"),
    ("l_no_use", REFUSED, "G21\nG0 X0\nG1 X1 F10 L2\nM2\n"),
    ("negative_dwell", REFUSED, "G21\nG0 X0\nG4 P-1\nM2\n"),
    ("dwell_no_p", REFUSED, "G21\nG4\nM2\n"),
    ("n_not_first", REFUSED, "G21\nG0 X1 N10\nM2\n"),
    ("axes_no_motion", REFUSED, "G21\nX1\nM2\n"),
    ("axes_after_g80", REFUSED, "G21\nG0 X0\nG81 X1 Z-1 R1 F100\nG80\nX2\nM2\n"),
    ("axes_with_g80", REFUSED, "G21\nG0 X0\nG80 X1\nM2\n"),
    ("g43_1_with_g80", REFUSED, "G21\nG0 X0\nG80 G43.1 Z5\nM2\n"),
    ("g43_1_then_axes", REFUSED, "G21\nG43.1 Z5\nX1\nM2\n"),
    ("g43_axes_no_motion", REFUSED, "G21\nT1 M6\nG43 H1 Z5\nM2\n"),
    ("g43_2_axes_no_motion", REFUSED, "G21\nG43.2 Z5\nM2\n"),
    ("g43_1_i_word", REFUSED, "G21\nG0 X0\nG43.1 Z5 I1\nM2\n"),
    ("two_x_words", REFUSED, "G21\nG0 X1 X2\nM2\n"),
    ("no_feed", REFUSED, "G21\nG1 X1\nM2\n"),
    ("arc_off_circle", REFUSED, "G21 F100\nG0 X0 Y0\nG2 X10 Y0 I3 J0\nM2\n"),
    ("arc_no_centre", REFUSED, "G21 F100\nG0 X0 Y0\nG2 X1 Y1\nM2\n"),
    *[(name, verdict, _arc_limit(units, arc)) for name, verdict, units, arc in ARC_LIMITS],
    *[(name + "_in_a_run", verdict, _arc_limit(units, arc, run=True)) for name, verdict, units, arc in ARC_LIMITS],
    ("inverse_time_no_f", REFUSED, "G21\nG0 X0\nG93 G1 X1\nM2\n"),
    ("undefined_named", REFUSED, "G21\nG0 X#<nope>\nM2\n"),
    ("sqrt_negative", REFUSED, "G21\nG0 X[SQRT[-1]]\nM2\n"),
    ("divide_zero", REFUSED, "G21\nG0 X[1/0]\nM2\n"),
    ("negative_power", REFUSED, "G21\nG0 X[-2 ** 0.5]\nM2\n"),
    ("ln_zero", REFUSED, "G21\nG0 X[LN[0]]\nM2\n"),
    ("acos_range", REFUSED, "G21\nG0 X[ACOS[2]]\nM2\n"),
    ("unclosed_bracket", REFUSED, "G21\nG0 X[1+2\nM2\n"),
    ("missing_operand", REFUSED, "G21\nG0 X[1 +]\nM2\n"),
    ("unknown_function", REFUSED, "G21\nG0 X[FOO[1]]\nM2\n"),
    ("missing_sub", REFUSED, "G21\no<nowhere_to_be_found> call\nM2\n"),
    ("missing_m98", REFUSED, "G21\nG0 X0\nM98 P4321\nM30\n"),
    ("local_named_in_sub", REFUSED, "G21\n#<k>=1\no<s> sub\nG0 X#<k>\no<s> endsub\no<s> call\nM2\n"),
    ("gouging_corner", REFUSED, "G21\nT1 M6\nG0 X-10 Y-10\nG41 D1\nG1 X0 Y0 F100\nG1 X10 Y0\nG1 X10 Y0.5\n"
                                "G1 X20 Y0.5\nG40\nG0 X0 Y0\nM2\n"),
    # -- read by rs274, not by us (refused, saying what)
    ("g52", "G52", "G21\nG0 X0 Y0\nG52 X2 Y3\nG0 X1\nG52 X0 Y0\nM2\n"),
    ("cutter_comp", "cutter radius compensation", "G21\nT1 M6\nG0 X-10 Y-10\nG41 D1\nG1 X0 Y0 F100\nG1 X10 Y0\n"
                                                  "G1 X10 Y10\nG40 G0 X-10 Y-10\nM2\n"),
    ("system_named", "controller's state", "G21\nG0 X1\nG0 Y#<_x>\nM2\n"),
    ("system_numbered", "controller's state", "G21\nG0 X#5221\nM2\n"),
    ("m99_main", "M99 in the main program", "G21\nG0 X1\nM99\n"),
    ("cycle_no_retract_mode", "G98 / G99", "G21 G90 F100\nG0 X0 Y0 Z10\nG81 X1 Y1 Z-1 R1\nX2 Y2\nG80\nM2\n"),
]


def run_rs274_verdict(text, tmp_path):
    """(returncode, message, machine end points (N, 6), move count) of rs274 reading ``text``."""
    exe = require_rs274()
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "tools.tbl").write_text(tool_table_text({1: 0.0}))
    (tmp_path / "in.ngc").write_text(text)
    for _ in range(5):  # rs274 now and then dies of a signal (SIGBUS) when two run at once: run it again then
        proc = subprocess.run([exe, "-t", "tools.tbl", "-g", "in.ngc", "out.txt"], stdin=subprocess.DEVNULL,
                              capture_output=True, text=True, timeout=60, cwd=tmp_path)
        if proc.returncode >= 0:
            break
    out = tmp_path / "out.txt"
    canon = out.read_text(errors="replace") if out.exists() else ""
    return proc.returncode, (proc.stdout + proc.stderr).strip(), machine_ends(canon)


_MOVE = re.compile(r"^\s*\d+\s+N\S*\s+(STRAIGHT_TRAVERSE|STRAIGHT_FEED|ARC_FEED)\(")
_OFFSET = re.compile(r"^\s*\d+\s+N\S*\s+SET_(G5X|G92)_OFFSET\((.*)\)")
_TOOL = re.compile(r"^\s*\d+\s+N\S*\s+USE_TOOL_LENGTH_OFFSET\((.*)\)")


def machine_ends(canon: str) -> np.ndarray:
    """rs274's end points plus the G5x, G92 and tool length offsets in force at each move (machine coordinates)."""
    moves = parse_canon(canon)
    g5x, g92, tool, offsets = np.zeros(6), np.zeros(6), np.zeros(6), []
    for line in canon.splitlines():
        m = _OFFSET.match(line)
        t = _TOOL.match(line)
        if m:
            vals = [float(v) for v in m.group(2).split(",")]
            if m.group(1) == "G5X":
                g5x = np.array(vals[1:7])
            else:
                g92 = np.array(vals[:6])
        elif t:  # "x y z, a b c, u v w"
            tool = np.array([float(v) for v in t.group(1).replace(",", " ").split()[:6]])
        elif _MOVE.match(line):
            offsets.append(g5x + g92 + tool)
    return moves.end + np.array(offsets).reshape(-1, 6)


_CASES = [pytest.param(*c, id=c[0]) for c in CORPUS]


@pytest.mark.parametrize("name, verdict, text", _CASES)
def test_each_program_is_read_as_rs274_reads_it_or_refused_with_the_reason(tmp_path, name, verdict, text):
    rc, message, rs_end = run_rs274_verdict(text, tmp_path)
    # the table's verdict is LinuxCNC's
    assert (rc == 0) == (verdict != REFUSED), f"rs274 {'refused' if rc else 'read'} it: {message[-300:]}"
    try:
        ours = parse_program(text, f"{name}.ngc")
    except GcodeError as exc:
        assert verdict != OK, f"we refuse what rs274 reads the same way we should: {exc}"
        assert re.match(rf"{name}\.ngc:[0-9]+: \S", str(exc)), str(exc)
        if verdict != REFUSED:
            assert verdict in str(exc)
        return
    assert verdict == OK, f"we read a program rs274 refuses ({message[-200:]})"
    # the same path: the same sequence of end points, zero-length moves aside (a canned cycle's rapid to a plane
    # it is already at is one for us and none for rs274)
    mine, theirs = drop_repeats(ours.end_machine), drop_repeats(rs_end)
    assert len(mine) == len(theirs)
    np.testing.assert_allclose(mine, theirs, atol=1e-4)


def drop_repeats(end: np.ndarray) -> np.ndarray:
    """End points (N, 6) without the moves that end where the previous one ended (within 1e-4)."""
    keep = np.ones(len(end), bool)
    keep[1:] = np.abs(np.diff(end, axis=0)).max(axis=1) > 1e-4
    return end[keep]


def test_refusals_name_the_source_line_of_a_flattened_program():
    text = "G21\n#1=0\no1 while [#1 LT 3]\n#1=[#1+1]\nG0 X[1/[#1-2]]\no1 endwhile\nM2\n"
    with pytest.raises(GcodeError) as info:
        parse_program(text, "job.ngc")
    assert str(info.value).startswith("job.ngc:5: division by zero")


def test_flattened_rows_name_their_source_lines():
    prog = parse_program("G21\no<s> sub\nG0 X#1\no<s> endsub\no<s> call [1]\no<s> call [2]\nG0 Y1\nM2\n")
    assert prog.line_no.tolist() == [3, 3, 7]
    assert prog.lines[0].startswith("(flattened by trueaxis")
    assert any("flattened" in w for w in prog.warnings)


def test_a_program_without_macros_is_not_touched():
    text = "G21 G90\nG0 X1 Y2\nG1 X3 F100\nM2\n"
    prog = parse_program(text)
    assert "".join(prog.lines) == text and prog.source_line is None


def test_the_corpus_covers_each_verdict_richly():
    verdicts = [v for _, v, _ in CORPUS]
    assert verdicts.count(OK) >= 40 and verdicts.count(REFUSED) >= 30 and len(CORPUS) >= 80


def test_a_flattened_program_posts_and_rs274_reads_the_output_along_the_source_path(tmp_path):
    """The post writes the flat program (saying so in its first line after the header); rs274 reads it along the path it reads in the
    source, up to the compensation (the xh714 twin corrects by at most a few um here)."""
    from conftest import MACHINES
    from trueaxis.machine import load_machine
    from trueaxis.postproc.post import compensate, without_header

    text = ("G21 G90 G17 F300\nG0 X0 Y0 Z-5\n#<_step>=4\no<row> sub\nG1 X[#1*#<_step>] Y0 Z-11\nG1 Y20\n"
            "G2 X[#1*#<_step>+2] Y20 I1 J0\no<row> endsub\n#1=0\no1 while [#1 LT 5]\no<row> call [#1]\n"
            "#1=[#1+1]\no1 endwhile\nG0 Z-5\nM2\n")
    out = compensate(text, load_machine(MACHINES / "xh714.toml"), "geometric")
    assert without_header(out).splitlines()[0].startswith("(flattened by trueaxis")  # after the post's header
    rc_in, msg_in, src_end = run_rs274_verdict(text, tmp_path / "in")
    rc_out, msg_out, out_end = run_rs274_verdict(out, tmp_path / "out")
    assert rc_in == 0 and rc_out == 0, (msg_in, msg_out)
    assert len(src_end) == 1 + 5 * 3 + 1
    assert len(out_end) >= len(src_end)  # moves may be split where the error varies along them
    # every source end point is reached by the output within the compensation's size
    d = np.abs(out_end[:, None, :3] - src_end[None, :, :3]).max(axis=2).min(axis=0)
    assert d.max() < 0.02, d.max()


FLAT_BODY = ["(a flat one)", "G21 G90 G17", "#1 = 10", "G0 X0 Y0 Z-5", "G1 X#1 Y5 Z-11 F200", "G0 Z-5"]


@pytest.mark.parametrize("name, lines", [
    ("percent", ["%"] + FLAT_BODY + ["M30", "%"]),
    ("program_number", ["%", "O1234"] + FLAT_BODY + ["M30", "%"]),
    ("program_name", ["%", "O0000(NAME)"] + FLAT_BODY + ["M30", "(not executed)", "%", "(after the closing %)"]),
    ("percent_ends_it", ["%"] + FLAT_BODY + ["%"]),
    ("m2", FLAT_BODY + ["M2"]),
])
@pytest.mark.parametrize("ending", ["\n", "\r\n"])
def test_a_flattened_program_keeps_its_percent_lines_first_and_last_and_rs274_reads_the_output(tmp_path, name, lines,
                                                                                               ending):
    """The post's header and the flat program's note go after the leading '%' and program number, and the closing
    '%' stays last: LinuxCNC reads a '%' only as the first line ("Bad character '%' used" before any motion, when
    the header came first), and a program opened with '%' keeps its closing one after M30 too."""
    from conftest import MACHINES
    from trueaxis.machine import load_machine
    from trueaxis.postproc.post import compensate, without_header

    text = ending.join(lines) + ending
    out = compensate(text, load_machine(MACHINES / "xh714.toml"), "geometric")
    rc_in, msg_in, src_end = run_rs274_verdict(text, tmp_path / "in")
    rc_out, msg_out, out_end = run_rs274_verdict(out, tmp_path / "out")
    assert rc_in == 0 and rc_out == 0, (msg_in, msg_out)
    assert len(out_end) == len(src_end) == 3
    np.testing.assert_allclose(out_end[:, :3], src_end[:, :3], atol=0.01)  # the correction: a few um
    out_lines = out.splitlines()
    start = 2 if lines[1].startswith("O") else 1 if lines[0] == "%" else 0
    assert out_lines[:start] == lines[:start]
    assert without_header(out).splitlines()[start].startswith("(flattened by trueaxis")
    assert out_lines[-1] == ("%" if "%" in lines else lines[-1])
    assert all(line.endswith(ending) for line in out.splitlines(keepends=True))


def test_a_flattened_program_with_percent_and_number_names_its_source_lines():
    text = "%\r\nO1234\r\n#1=10\r\nG0 X#1\r\nG1 X[#1*2] F100\r\nM30\r\n(x)\r\n%\r\n(after)\r\n"
    prog = parse_program(text, "a.ngc")
    assert prog.lines[:2] == ["%\r\n", "O1234\r\n"] and prog.lines[2].startswith("(flattened by trueaxis")
    assert prog.lines[3:] == ["G0 X10\r\n", "G1 X20 F100\r\n", "M30\r\n", "%\r\n"]
    assert prog.line_no.tolist() == [4, 5]
    assert [int(n) for n in prog.source_line[:len(prog.lines)]] == [1, 2, 2, 4, 5, 6, 8]
    assert prog.warnings[0].startswith("a.ngc:3: flattened")
    with pytest.raises(GcodeError) as info:
        parse_program(text.replace("#1*2", "1/0"), "a.ngc")
    assert str(info.value).startswith("a.ngc:5: division by zero")


def test_a_programs_start_is_its_percent_and_program_number_lines():
    from trueaxis.nc.flatten import program_start

    assert program_start("%\nO1234\nG0 X1\n") == len("%\nO1234\n")
    assert program_start("%\r\nO0000(NAME)\r\n(c)\r\n") == len("%\r\nO0000(NAME)\r\n")
    assert program_start("G21\n%\n") == 0
    assert program_start("o100 sub\nG0 X#1\no100 endsub\n") == 0  # an O-word subroutine, not a program number
    assert program_start("%") == 0  # without a line ending: the file's only line


def test_brackets_and_hashes_in_comments_leave_the_program_untouched():
    text = "G21 G90 (tool #3 [rough])\nG0 X1 Y2 ; note [a]\nG1 X3 F100\nM2\n%\n"
    prog = parse_program(text)
    assert "".join(prog.lines) == text and prog.source_line is None


def test_flat_lines_keep_the_programs_line_endings():
    prog = parse_program("G21\r\n#1=2\r\nG0 X#1 (a)\r\nG0 Y[#1*2]\r\nM2\r\n")
    assert all(line.endswith("\r\n") for line in prog.lines)
    assert prog.lines[2:4] == ["G0 X2 (a)\r\n", "G0 Y4\r\n"]
