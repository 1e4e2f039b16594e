"""trueaxis.postproc (layer 5, docs/architecture.md): the post (``compensate``), its solver, the lathe, the test parts'
NC programs, and the CAM hosts (``hosts``, application layer). The G-code reader and CL data are ``trueaxis.nc``.

The Python hook for CAM scripts (CadQuery, build123d, anything that writes G-code text)::

    from trueaxis.postproc import compensate
    compensated = compensate(gcode_text, machine, mode="geometric")  # raises PostError: "file:line: reason"

``machine``: a ``Machine`` (``trueaxis.machine.load_machine``), a machine file's path or a fixture machine's short name.

``compensate`` and ``PostError`` are loaded on first use, so that importing this package alone stays light.
"""

__all__ = ["PostError", "compensate"]


def __getattr__(name):
    if name in __all__:
        from . import post

        return getattr(post, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
