"""The FreeCAD CAM host: the post-processor script ``trueaxis_post.py`` and its installation.

The script runs inside FreeCAD's own Python (not this package's environment): it writes the program as FreeCAD's
linuxcnc post does, with the job's cutting conditions as ``(trueaxis: ...)`` comments, and compensates it by calling
the ``trueaxis post`` command. FreeCAD finds post processors named ``*_post.py`` in its macro folder; in a Job the
post processor is then called ``trueaxis``.
"""

from __future__ import annotations

import os
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

SCRIPT_NAME = "trueaxis_post.py"


def post_script_path() -> Path:
    """Path of the FreeCAD post-processor script shipped with trueaxis."""
    return Path(__file__).resolve().parent / SCRIPT_NAME


def _configured_macro_dirs(home: Path) -> list[Path]:
    """MacroPath set in FreeCAD's user.cfg (0.20 Debian and 0.21+: XDG config; older: ~/.FreeCAD), when set."""
    config_home = Path(os.environ.get("XDG_CONFIG_HOME") or home / ".config")
    found = []
    for cfg in (config_home / "FreeCAD" / "user.cfg", home / ".FreeCAD" / "user.cfg"):
        try:
            root = ET.parse(cfg).getroot()
        except (OSError, ET.ParseError):
            continue
        for group in root.iter("FCParamGroup"):
            if group.get("Name") != "Macro":
                continue
            for text in group.iter("FCText"):
                if text.get("Name") == "MacroPath" and text.text and text.text.strip():
                    found.append(Path(text.text.strip()).expanduser())
    return found


def default_macro_dir(home: Path | None = None) -> Path:
    """FreeCAD's user macro folder.

    In order: the MacroPath of FreeCAD's user.cfg (FreeCAD looks there for post processors whether the folder exists
    yet or not: the install creates it; it went to the data folder instead, where FreeCAD never looked); then the
    default folder of a
    FreeCAD whose user data folder exists (``$XDG_DATA_HOME/FreeCAD/Macro``, which the Debian 0.20 build and 0.21+
    use, then ``~/.FreeCAD/Macro`` of older builds); else the XDG one.
    """
    home = Path(home) if home is not None else Path.home()
    for configured in _configured_macro_dirs(home):
        return configured
    data_home = Path(os.environ.get("XDG_DATA_HOME") or home / ".local" / "share")
    candidates = [data_home / "FreeCAD" / "Macro", home / ".FreeCAD" / "Macro"]
    for macro in candidates:
        if macro.is_dir() or macro.parent.is_dir():
            return macro
    return candidates[0]


def install_post(dest_dir: Path | None = None) -> Path:
    """Copy the post-processor script into dest_dir (default: FreeCAD's macro folder); return the installed file."""
    dest = Path(dest_dir).expanduser() if dest_dir is not None else default_macro_dir()
    dest.mkdir(parents=True, exist_ok=True)
    target = dest / SCRIPT_NAME
    tmp = dest / f".{SCRIPT_NAME}.tmp"
    shutil.copyfile(post_script_path(), tmp)
    os.replace(tmp, target)
    return target


__all__ = ["SCRIPT_NAME", "default_macro_dir", "install_post", "post_script_path"]
