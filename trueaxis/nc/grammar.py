"""The lexical pieces of RS-274 that every reader, check and writer of ``trueaxis.nc`` shares (the tokenizer itself,
built from them, is ``gcode.TOKEN_PATTERN``). Kept apart so that ``flatten`` and ``check``, which ``gcode`` imports,
can import them too."""

# A number as RS-274 writes it: optional sign, digits with an optional point, or a point and digits; no exponent.
NUMBER = r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)"

# plane: (first, second, normal) axis indices as LinuxCNC orders them in ARC_FEED
PLANE_AXES = {17: (0, 1, 2), 18: (2, 0, 1), 19: (1, 2, 0)}
# the arc-centre word along each axis index
CENTER_WORD = {0: "I", 1: "J", 2: "K"}
