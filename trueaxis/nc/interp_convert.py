"""The general path of the reader (LinuxCNC's ``interp_convert``): a block that is not a plain move, converted one
modal group at a time in LinuxCNC's order of execution: the G codes of the block (motion mode, feed mode, plane,
units, cutter compensation, work system, distance modes, retract mode), feed and tool words, M codes (tool change,
program end), tool length offset, the non-modal group (G10, G28 / G30, G92), then the motion (G53, straight, arc,
canned cycle). A part of ``gcode._Interpreter`` (the methods of ``Conversion``); the state is the interpreter's
(``interp_state``), arcs and cycles are ``interp_arc`` and ``interp_cycles``."""

from __future__ import annotations

import numpy as np

from .interp_arc import RADIUS_MIN, SPIRAL_ABS
from .interp_check import check_block
from .interp_codes import AXIS_INDEX, CYCLE_G, KNOWN_M, LINEAR, LINEAR_T, MM_PER_INCH, MOTION_G, add
from .rows import FEED, RAPID, ROW_MACHINE, ROW_PROGRAMMED, ROW_REFERENCE


class Conversion:
    """The interpreter's conversion of a general block (mixed into ``gcode._Interpreter``)."""

    def convert_block(self, li, line_no, gcodes, mcodes, vals, refuse, macro_nonmoving) -> None:
        """Execute one block read by ``interp_read.read_block``; ``self.ended`` after M2 / M30."""
        checked = check_block(self, line_no, gcodes, mcodes, vals, refuse, macro_nonmoving)
        if checked is None:
            return
        gnums, mnums, fvals, words_mask = checked
        if 70 in gnums or (80 in gnums and "P" not in fvals):
            self.diameter = 70 in gnums  # G7 / G8 (LinuxCNC's lathe modes), in force for this block's words
            self.modes_stated.setdefault("G7/G8", li)
        diameter = self.diameter
        ax = [(AXIS_INDEX[k], 0.5 * fvals[k] if diameter and k == "X" else fvals[k])
              for k in "XYZABC" if k in fvals]
        for k in "XYZABC":
            if k in fvals:
                self.used_axes.add(k)
        new_motion, nonmodal, g53, meta_changed, tlo_codes = self.convert_g(line_no, gnums, vals)
        # feed, spindle, tool
        if "F" in fvals:
            self.feed = fvals["F"]
        if "T" in fvals:
            self.next_tool = int(fvals["T"])
        if mnums:
            meta_changed |= self.convert_m(line_no, mnums)
        if tlo_codes:
            meta_changed |= self.tool_length(line_no, gnums, fvals, ax)
            if 431 in gnums and new_motion is None and nonmodal not in (100, 280, 300, 920):
                # G43.1 took the axis words as its offset and nothing else in the block uses them: no move with the
                # modal motion mode (rs274's enhance_block). A motion code, G10, G28, G30 or G92 in the block takes
                # them too (``G1 G43.1 Z5``: the offset Z5, then a move to Z5 under it; ``G28 G43.1 Z5`` homes Z
                # through Z5).
                ax = []
        if new_motion in (0, 10, 20, 30, 800):
            self.cycle_words["il_flag"] = False
        if gnums or mnums or "F" in fvals:
            self.off_now = self.offsets().tolist()
            if meta_changed:
                self.meta_now = self.meta()
            self.refresh_state()
        if nonmodal is not None:
            ax = self.convert_nonmodal(li, line_no, nonmodal, fvals, ax, words_mask)
        if self.ended and not ax and new_motion is None:
            return
        if nonmodal is not None:
            self.off_now = self.offsets().tolist()
            self.meta_now = self.meta()
            self.refresh_state()
        if new_motion is not None or ax:
            self.convert_motion(li, line_no, new_motion, g53, fvals, ax, words_mask)

    def convert_g(self, line_no, gnums, vals):
        """The block's G codes in the order written (each modal group's effect but the motion and the non-modal
        group, which come later): (new motion mode or None, non-modal code or None, G53, the setup changed, a tool
        length code is there)."""
        new_motion = nonmodal = None
        meta_changed = g53 = tlo_codes = False
        for g in gnums:
            if g in MOTION_G:
                new_motion = g
            elif g == 800:
                if new_motion is None:
                    new_motion = 800
            elif g == 930:
                self.inverse = True
            elif g in (940, 950):
                # (G95: the post writes the F words as given; simulate and diagnose refuse it, naming the block,
                # trajectory._refuse_feed_per_revolution: no warning here, which made every lathe post fail --strict)
                self.inverse = False
            elif g in (170, 180, 190):
                self.plane = g // 10
                self.modes_stated.setdefault("plane", line_no - 1)
            elif g in (200, 210):
                self.set_units(g == 200)
                self.modes_stated.setdefault("units", line_no - 1)
            elif g in (400, 410, 420, 411, 421):
                self.cutter = g // 10
                if self.cutter != 40:
                    self.warn(line_no, f"G{self.cutter} cutter radius compensation: rows follow the programmed "
                              "contour, not the tool centre")
            elif g in (430, 431, 432, 490):
                tlo_codes = True  # handled after the tool change (tool_length)
            elif (540 <= g <= 590 and g % 10 == 0) or g in (591, 592, 593):
                self.select_work((g - 530) // 10 if g % 10 == 0 else 7 + (g - 591))
                meta_changed = True
            elif g in (900, 910):
                self.absolute = g == 900
            elif g in (901, 911):
                self.arc_abs = g == 901
            elif g in (980, 990):
                self.retract_r = g == 990
            elif g in (40, 100, 280, 281, 300, 301, 920, 921, 922, 923):
                nonmodal = g
            elif g == 530:
                g53 = True
            elif g == 70:
                pass  # G7, lathe diameter mode: taken before the axis words (convert_block)
            elif g in (610, 611, 640, 960, 970):
                pass  # path control and spindle modes: no effect on positions
            elif g == 80:
                if "P" in vals:
                    self.unsupported_block(line_no, "Fanuc G08 P (look-ahead) is not an RS-274 code")
                # else LinuxCNC's G8 (lathe radius mode), the default: nothing to do
            else:
                self.not_understood(line_no, "G43.4 / G43.5 tool centre point control: the post reads and "
                                    "writes machine-axis (joint) positions, not tool-tip positions"
                                    if g in (434, 435) else f"G{g / 10:g} not understood")
        return new_motion, nonmodal, g53, meta_changed, tlo_codes

    def set_units(self, want_inch: bool) -> None:
        """G20 / G21: every length of the state to the new unit (LinuxCNC keeps its state in program units)."""
        self.units_seen.add("inch" if want_inch else "mm")
        if want_inch == self.inch:
            return
        f = (1 / MM_PER_INCH) if want_inch else MM_PER_INCH
        for arr in (self.g92, self.tlo):
            arr[LINEAR] *= f
        pos = self.pos
        pos[:] = [p * f if lin_i else p for p, lin_i in zip(pos, LINEAR_T)]
        self.g5x[:, LINEAR] *= f
        cycle = self.cycle_words
        for key in ("r", "cc", "q", "il", "i", "j", "k"):
            cycle[key] *= f
        self.feed *= f if not self.inverse else 1.0
        self.inch = want_inch
        self.arc_tol, self.arc_rmin = SPIRAL_ABS[want_inch], RADIUS_MIN[want_inch]
        self.u_scale = np.where(LINEAR, MM_PER_INCH if want_inch else 1.0, 1.0)

    def select_work(self, new_active: int) -> None:
        """G54..G59.3: the program position follows the new system (the machine position stays)."""
        self.selects_work = True
        active, rot, g5x = self.active, self.rot, self.g5x
        if new_active == active:
            return
        if rot[active] == 0.0 and rot[new_active] == 0.0:
            add(self.pos, g5x[active] - g5x[new_active])
            self.active = new_active
        else:  # the machine position stays; the program position follows the rotation
            m_pos = self.machine_of(self.pos)
            self.active = new_active
            self.pos[:] = self.program_of(m_pos)

    def convert_m(self, line_no, mnums) -> bool:
        """M codes: the tool change (with its length, where the control applies it at M6), the program end;
        unknown ones refused or passed through. True when the setup in force changed."""
        meta_changed = False
        for m in mnums:
            if m == 6:
                self.tool = tool = self.next_tool
                self.positions_lost.append((line_no - 1, "the tool change M6"))
                if self.tool_change_mode:
                    # the control applies the new tool's length at the change (Hurco, some Fanuc setups)
                    new, self.tlo_h, self.tlo_reason = self.tool_offsets(tool, self.u_scale, self.zero_ok, line_no,
                                                                         "M6")
                    m_pos = self.machine_of(self.pos)
                    self.tlo = new
                    self.pos[:] = self.program_of(m_pos)
                    self.tlo_ver += 1
                    meta_changed = True
                    self.hist[("tlo", self.tlo_ver)] = {"tool": tool, "values": new * self.u_scale,
                                                        "source": self.tool_source(tool, self.zero_ok), "how": "M6"}
            elif m in (2, 30):
                self.ended = True
            elif m not in KNOWN_M and not (100 <= m <= 199):
                self.not_understood(line_no, f"M{m} is not an RS-274 code")
        return meta_changed

    def tool_length(self, line_no, gnums, fvals, ax):
        """G43 / G43.1 / G43.2 / G49, after the tool change (G43.1: the block's axis words ``ax`` are its offset):
        whether the setup changed."""
        meta_changed = False
        zero_ok, u_scale = self.zero_ok, self.u_scale
        for g in gnums:
            if g not in (430, 431, 432, 490):
                continue
            tlo = self.tlo
            if g == 430:
                h = int(fvals["H"]) if "H" in fvals else self.tool
                new, self.tlo_h, self.tlo_reason = self.tool_offsets(h, u_scale, zero_ok, line_no, f"G43 H{h}")
                rec = {"tool": h, "source": self.tool_source(h, zero_ok), "how": f"G43 H{h}"}
            elif g == 431:
                new = tlo.copy()
                for i, v in ax:
                    new[i] = v
                self.tlo_h, self.tlo_reason = -2, ""
                rec = {"tool": -2, "source": f"{self.source}:{line_no} (G43.1)", "how": "G43.1"}
            elif g == 432:
                h = int(fvals.get("H", 0))
                add_, _, reason = self.tool_offsets(h, u_scale, zero_ok, line_no, f"G43.2 H{h}")
                new = tlo + add_
                self.tlo_reason = self.tlo_reason or reason
                rec = {"tool": h, "source": self.tool_source(h, zero_ok), "how": f"G43.2 H{h} (added)"}
            else:
                new = np.zeros(6)
                self.tlo_h, self.tlo_reason = -1, ""
                rec = {"tool": -1, "source": "", "how": "G49"}
            if self.rot[self.active] == 0.0:
                add(self.pos, tlo - new)
                self.tlo = new
            else:
                m_pos = self.machine_of(self.pos)
                self.tlo = new
                self.pos[:] = self.program_of(m_pos)
            self.tlo_ver += 1
            meta_changed = True
            rec["values"] = self.tlo * u_scale
            self.hist[("tlo", self.tlo_ver)] = rec
        return meta_changed

    def convert_nonmodal(self, li, line_no, nonmodal, fvals, ax, words_mask):
        """The non-modal group: G10, G28 / G30 (and their .1), G92 and its variants (G4 has no effect on
        positions). Returns the axis words left for the motion."""
        if nonmodal == 100:
            # the active system may change: the machine position stays, the program position moves
            changed = self.g10(line_no, fvals, ax, self.g5x, self.rot, self.active, self.g92, self.tlo, self.pos,
                               self.u_scale, self.machine_of, self.program_of)
            if changed is not None:
                idx, letters = changed
                if int(fvals.get("L", -1)) == 20 and letters:
                    self.position_sets.append((li, list(letters), "G10 L20"))
                for i in letters:
                    self.g5x_known[idx, i] = True
                self.g5x_src[idx] = f"{self.source}:{line_no} (G10 L{int(fvals.get('L', -1))})"
                self.g5x_ver[idx] += 1
                self.hist[("g5x", idx, self.g5x_ver[idx])] = {
                    "values": self.g5x[idx] * self.u_scale, "rotation": self.rot[idx], "source": self.g5x_src[idx],
                    "known": self.g5x_known[idx].copy()}
            return []
        if nonmodal in (280, 300):
            key = "G28" if nonmodal == 280 else "G30"
            not_given = not self.zero_ok and not self.ref_given[key]
            if not_given and self.ref_missing is None:
                # the home position lives in the control (#5161-5166 / #5181-5186): zero would be an invented move
                # (refused under require_setup with the program's other missing values, the first in line order)
                first = 5161 if key == "G28" else 5181
                self.ref_missing = (line_no, f"{key} moves to its home position (#{first}-{first + 5}, stored in "
                                             "the control), which was not given")
            self.reference_return(li, key, ax, words_mask)
            if not_given:
                self.home_not_given_rows.append(len(self.r_line) - 1)  # (the home's row, the block's last)
            return []
        if nonmodal in (281, 301):
            self.refs["G28" if nonmodal == 281 else "G30"] = np.array(self.machine_of(self.pos)) * self.u_scale
            self.ref_given["G28" if nonmodal == 281 else "G30"] = True
        elif nonmodal in (920, 921, 922, 923):
            if nonmodal == 920 and ax:
                self.position_sets.append((li, [i for i, _ in ax], "G92"))
            return self.g92_shift(line_no, nonmodal, ax)
        return ax

    def reference_return(self, li, key, ax, words_mask) -> None:
        """G28 / G30: a rapid to the intermediate point (axis words), then the named axes (all when none is named)
        to the stored reference point, in machine coordinates."""
        pos, u_scale, refs = self.pos, self.u_scale, self.refs
        if ax:
            target = list(pos)
            for i, v in ax:
                target[i] = v if self.absolute else pos[i] + v
            self.emit(RAPID, ROW_REFERENCE, target, li, words_mask)
            moving = [i for i, _ in ax]
        else:
            moving = list(range(6))
        if self.rot[self.active] == 0.0:
            home = refs[key] / u_scale - self.offsets()
            target = list(pos)
            for i in moving:
                target[i] = float(home[i])
        else:  # as LinuxCNC: the home point in program coordinates, its named axes taken
            home = self.program_of([float(refs[key][i] / u_scale[i]) for i in range(6)])
            target = list(pos)
            for i in moving:
                target[i] = home[i]
        self.emit(RAPID, ROW_REFERENCE, target, li, 0)

    def g92_shift(self, line_no, nonmodal, ax):
        """G92 (set), G92.1 / G92.2 (clear), G92.3 (restore the stored shift); the machine position stays. Returns
        the axis words left for the motion."""
        g92, pos, u_scale = self.g92, self.pos, self.u_scale
        old_g92 = g92.copy()
        if nonmodal == 920:
            for i, v in ax:
                g92[i] = pos[i] + g92[i] - v
            ax = []
            self.g92_stored = (g92 * u_scale, f"{self.source}:{line_no} (G92)")
            src, self.g92_reason = self.g92_stored[1], ""
        elif nonmodal in (921, 922):
            g92[:] = 0.0
            src, self.g92_reason = f"{self.source}:{line_no} (G92.{nonmodal - 920})", ""
            if nonmodal == 921:
                self.g92_stored = (np.zeros(6), src)
        elif self.g92_stored is not None:
            g92[:] = self.g92_stored[0] / u_scale
            src, self.g92_reason = f"{self.g92_stored[1]}, restored by G92.3 at line {line_no}", ""
        else:
            g92[:] = 0.0
            src = "--offsets-zero" if self.zero_ok else "not given"
            self.g92_reason = "" if self.zero_ok else \
                "the G92 shift that G92.3 restores (stored in the control) was not given"
        # the machine position stays: the program position moves by the change (G92 is applied before the
        # system's rotation, so the same formula holds in a rotated system)
        add(pos, old_g92 - g92)
        self.g92_ver += 1
        self.hist[("g92", self.g92_ver)] = {"values": g92 * u_scale, "source": src}
        return ax

    def convert_motion(self, li, line_no, motion_here, g53, fvals, ax, words_mask) -> None:
        """The block's motion: the modal motion mode with the block's axis words (G80 with axis words as Fanuc
        reads it, G53 in machine coordinates, a straight move, an arc, a canned cycle)."""
        prior_mode = self.motion_mode
        if motion_here is not None:
            self.motion_mode = motion_here
        if motion_here is None and not ax:
            return
        mm = self.motion_mode
        if motion_here in CYCLE_G and prior_mode not in CYCLE_G:
            self.pre_cycle_mode = prior_mode
        if mm == 800:
            if not ax:
                return
            pre_cycle_mode = self.pre_cycle_mode
            if pre_cycle_mode not in (0, 10, 20, 30):
                raise self.err(line_no, "axis words with G80 and no motion mode to fall back to")
            # Fanuc: G80 ends the cycle and the G0/G1 modal from before the cycle moves on (LinuxCNC refuses axis
            # words here; a program LinuxCNC accepts never reaches this line)
            self.warn(line_no, f"axis words after G80: moved with G{pre_cycle_mode // 10}, the motion "
                      "mode before the canned cycle (Fanuc behaviour; LinuxCNC refuses this)")
            mm = self.motion_mode = pre_cycle_mode
        pos, feed = self.pos, self.feed
        if g53:
            self.machine_move(li, line_no, mm, ax, words_mask)
        elif mm in (0, 10):
            target = list(pos)
            if self.absolute:
                for i, v in ax:
                    target[i] = v
            else:
                for i, v in ax:
                    target[i] += v
            if mm == 10:
                if self.inverse and "F" not in fvals:
                    raise self.err(line_no, "G93 inverse-time feed needs an F word on every feed block")
                if feed == 0.0:
                    raise self.err(line_no, "G1 with zero feed rate (no F word yet)")
            self.emit(RAPID if mm == 0 else FEED, ROW_PROGRAMMED, target, li, words_mask)
        elif mm in (20, 30):
            self.arc(line_no, li, mm, fvals, ax, pos, self.plane, self.absolute, self.arc_abs, self.inch, feed,
                     self.inverse, self.emit, words_mask)
        else:
            if self.inverse:
                raise self.err(line_no, "canned cycle in G93 inverse-time mode")
            if feed == 0.0:
                raise self.err(line_no, "canned cycle with zero feed rate (no F word yet)")
            if self.cutter != 40:
                raise self.err(line_no, "canned cycle with cutter radius compensation on")
            self.cycle(line_no, li, mm, motion_here, fvals, ax, pos, self.plane, self.absolute, self.retract_r,
                       self.inch, self.cycle_words, self.emit, words_mask, prior_mode)

    def machine_move(self, li, line_no, mm, ax, words_mask) -> None:
        """G53 G0 / G1: the axis words are machine coordinates."""
        if mm not in (0, 10):
            raise self.err(line_no, "G53 needs G0 or G1")
        if not self.absolute:
            raise self.err(line_no, "G53 in incremental mode (G91)")
        if self.rot[self.active] == 0.0:
            target = list(self.pos)
            off = self.offsets()
            for i, v in ax:
                target[i] = v - off[i]
        else:
            m_pos = self.machine_of(self.pos)
            for i, v in ax:
                m_pos[i] = v
            target = self.program_of(m_pos)
        if mm == 10 and self.feed == 0.0:
            raise self.err(line_no, "G1 with zero feed rate (no F word yet)")
        self.emit(RAPID if mm == 0 else FEED, ROW_MACHINE, target, li, words_mask)
