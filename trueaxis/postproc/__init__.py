"""trueaxis.postproc (see DESIGN.md §2): the G-code reader, the post (``compensate``), CL data and the CAM hosts.

The Python hook for CAM scripts (CadQuery, build123d, anything that writes G-code text)::

    from trueaxis.postproc import compensate
    compensated = compensate(gcode_text, machine, mode="geometric")  # raises PostError: "file:line: reason"

``compensate`` and ``PostError`` are loaded on first use, so that importing the G-code reader alone stays light.
"""

__all__ = ["PostError", "compensate"]


def __getattr__(name):
    if name in __all__:
        from . import post

        return getattr(post, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
