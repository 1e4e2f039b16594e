"""The error twin: kinematic chains, ISO 230 error parameters, force-induced errors, machine files.

Pure mathematics on arrays of poses (mm, rad); error values in um and urad. Start with::

    from trueaxis.machine import load_machine, ErrorTwin
    m = load_machine("fixtures/machines/nmv1500dcg.toml")
    twin = ErrorTwin(m)
    dp_um, du_urad = twin.volumetric_error(q)          # q: (N, n_axes) in mm and rad, columns m.axis_names
"""

from .kinematics import forward_nominal, inverse_kinematics
from .machine_file import MachineFileError, load_machine, parse_machine
from .model import Axis, ErrorSet, Machine, ResponseSurface, Tool
from .twin import ErrorTwin

__all__ = [
    "Axis",
    "ErrorSet",
    "ErrorTwin",
    "Machine",
    "MachineFileError",
    "ResponseSurface",
    "Tool",
    "forward_nominal",
    "inverse_kinematics",
    "load_machine",
    "parse_machine",
]
