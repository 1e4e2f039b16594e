"""What a block may not contain, and its values' ranges (LinuxCNC's ``interp_check``): codes whose moves are not in the
text (refused, or passed through on request), numbers out of range, a negative feed, a tool number out of range. A
part of ``gcode._Interpreter``'s general path; rs274's own block checks run before the reader (``check``)."""

from __future__ import annotations

from .interp_codes import MAX_WORD_VALUE, MOVING_G, MOVING_M, POSITION_LOST_G, SYNCED_G, WORD_BIT


def check_block(interp, line_no: int, gcodes, mcodes, vals: dict, refuse, macro_nonmoving):
    """The block's G codes (x10), M codes, word values (floats) and word bits, checked: (gnums, mnums, fvals,
    words_mask); None when the block is passed through uninterpreted (recorded in ``interp.unsupported``)."""
    gnums = []
    for g in gcodes:
        gnums.append(int(round(float(g) * 10)))
    mnums = [int(round(float(m))) for m in mcodes]
    if refuse is None:
        for g in gnums:
            if g in MOVING_G:
                refuse = MOVING_G[g]
        for m in mnums:
            if m in MOVING_M:
                refuse = MOVING_M[m]
        if refuse is None and any(k in vals for k in "UVW"):
            refuse = "U V W axes are not supported"
    if refuse is not None:
        if interp.passthrough:
            interp.unsupported_block(line_no, refuse)
            if any(g in POSITION_LOST_G for g in gnums) or any(m in MOVING_M for m in mnums):
                interp.positions_lost.append((line_no - 1, f"the {refuse} passed through"))
            return None
        synced = next((SYNCED_G[g] for g in gnums if g in SYNCED_G and MOVING_G[g] == refuse), None)
        raise interp.err(line_no, refuse + f" ({synced or 'the moves it makes are not in the text'}; "
                         "--passthrough-unsupported leaves the block as it is)")
    if macro_nonmoving:
        interp.unsupported_block(line_no, macro_nonmoving)

    fvals = {}
    for k, v in vals.items():
        fv = float(v)
        if not abs(fv) < MAX_WORD_VALUE and k not in "NO":
            raise interp.err(line_no, f"number out of range: {k}{v[:20]}{'...' if len(v) > 20 else ''} "
                             f"(the reader takes values below {MAX_WORD_VALUE:.0e})")
        fvals[k] = fv
    if fvals.get("F", 0.0) < 0.0:
        raise interp.err(line_no, f"negative feed rate F{vals['F']}")
    if "T" in fvals and not 0 <= fvals["T"] <= 2**31 - 1:
        raise interp.err(line_no, f"tool number T{fvals['T']:g} out of range (0 .. 2147483647)")
    words_mask = 0
    for k in vals:
        words_mask |= WORD_BIT.get(k, 0)
    return gnums, mnums, fvals, words_mask
