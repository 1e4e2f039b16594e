"""The codes of the interpreter's motion table (``gcode.Program``): what a row is and why it exists. Apart from
``gcode`` so that the interpreter's parts (``interp_arc``, ``interp_cycles``) and the writers share them."""

# motion codes (Program.motion)
RAPID, FEED, ARC_CW, ARC_CCW = 0, 1, 2, 3
# why a row exists (Program.kind)
ROW_PROGRAMMED = 0  # the block's own move
ROW_CYCLE = 1  # a move of an expanded canned cycle (G73, G81-G89)
ROW_REFERENCE = 2  # a move of G28/G30 (intermediate point or reference point)
ROW_MACHINE = 3  # a G53 move in machine coordinates
# Arc turns (P) are stored as int16.
MAX_ARC_TURNS = 32767
