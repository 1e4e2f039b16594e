"""Reading a block (LinuxCNC's ``interp_read.cc``): its tokens into G codes, M codes and the other words, comments
checked, macro values resolved, and what the reader must refuse or pass through named. A part of ``gcode``'s
interpreter."""

from __future__ import annotations

import re


def read_block(interp, raw: str, line_no: int, findall):
    """The words of the block ``raw`` (line ``line_no``; ``findall``: the tokenizer's ``findall``).

    Returns (G code texts, M code texts, {letter: value text} of the other words, the reason to refuse the block
    or None, the reason a block with a macro that moves nothing is passed through or None). Raises ``interp.err`` for
    a word with no number, a word twice, an unclosed comment, an unexpected character, an E word."""
    toks = findall(raw)
    gcodes = []
    mcodes = []
    vals = {}  # letter -> value text (non-G/M)
    refuse = None
    macro_nonmoving = None
    for com1, com2, letter, num, other in toks:
        if letter:
            if not num:
                raise interp.err(line_no, f"word '{letter}' with no number")
            L = letter.upper()
            if num[0] in "#[":
                value = interp.resolve(num)
                if value is None:
                    if L in "XYZABCUVWIJKR":
                        refuse = f"macro expression {L}{num} in a coordinate"
                    elif L in "GM":
                        refuse = f"macro expression {L}{num} as a G/M code"
                    else:
                        macro_nonmoving = f"macro expression {L}{num}"
                    continue
                num = repr(value)
            if L == "G":
                gcodes.append(num)
            elif L == "M":
                mcodes.append(num)
            elif L == "O":
                # Fanuc program number "O0001" alone is a label; LinuxCNC o-word control flow is not text
                rest = raw.upper().split("(", 1)[0]
                if re.search(r"O\s*[0-9]+\s*[A-Z]", rest) or "<" in raw:
                    refuse = "o-word subroutine / control flow"
                vals["O"] = num
            else:
                if L in vals and L != "N":
                    raise interp.err(line_no, f"more than one {L} word in the block")
                vals[L] = num
        elif com1:
            if not com1.endswith(")"):
                raise interp.err(line_no, "comment opened with '(' is not closed on its line")
        elif com2:
            pass
        else:
            if other == "/" and not gcodes and not mcodes and not vals:
                interp.block_delete_lines.append(line_no)  # executed, the switch off, as in rs274 (the post says so)
            elif other == "<" or other == ">":
                refuse = "o-word subroutine / control flow"
            elif other in "#[]=+-*":
                macro_nonmoving = macro_nonmoving or f"macro syntax '{other}'"
            else:
                raise interp.err(line_no, f"unexpected character {other!r}")
    g76 = any(re.fullmatch(r"0*76(\.0*)?", g.strip()) for g in gcodes)  # its E: the taper's length (LinuxCNC)
    if "E" in vals and not g76 and not any(m.strip().lstrip("0")[:2] in ("66", "67", "68") for m in mcodes):
        # LinuxCNC refuses an E word without G76/M66-M68 too; reading past it could misread "X1e2" as X1
        raise interp.err(line_no, f"E word 'E{vals['E']}': exponent notation (X1e2) is not RS-274, and E "
                         "words (thread lead, extruder) are not understood here")
    if refuse is None and macro_nonmoving and any(k in vals for k in "XYZABC"):
        refuse = macro_nonmoving + " in a block with axis words"
    return gcodes, mcodes, vals, refuse, macro_nonmoving
