"""trueaxis: a machine tool's error twin, used to compensate NC programs and to read CMM measurements.

Subpackages: ``machine`` (the error twin, pure mathematics), ``postproc`` (NC programs in and out),
``inspect`` (test parts, CMM clouds, identification), ``sim`` (the virtual shop), ``diagnose`` (the sim-to-real gap).
"""

__version__ = "0.1.0"
