"""plugin_manifest.json agrees with pyproject.toml and with the code it names."""

from __future__ import annotations

import importlib
import json
import tomllib

from conftest import ROOT
from trueaxis.cli import build_parser

MANIFEST = json.loads((ROOT / "plugin_manifest.json").read_text())
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_name_and_version_match_pyproject():
    import trueaxis

    assert MANIFEST["name"] == PYPROJECT["project"]["name"]
    assert MANIFEST["version"] == PYPROJECT["project"]["version"] == trueaxis.__version__


def test_commands_match_the_console_scripts_and_resolve():
    assert MANIFEST["commands"] == PYPROJECT["project"]["scripts"]
    for target in MANIFEST["commands"].values():
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func))


def test_subcommands_exist_in_the_parser():
    parser = build_parser()
    for sub in MANIFEST["subcommands"]:
        words = sub.split()
        args = words + (["x"] if words[0] == "machine" else [])
        if words[0] == "error":
            args += ["--machine", "m.toml", "--at", "X=0"]
        if words[0] in ("part", "program"):
            args += ["nas979", "-o", "out"]
        if words[0] == "simulate":
            args += ["p.ngc", "--machine", "m.toml", "--part", "nas979", "-o", "c.ply"]
        parsed = parser.parse_args(args)
        assert parsed.command == words[0]


def test_machine_files_are_exactly_the_fixture_machines_and_load():
    from trueaxis.machine import load_machine

    listed = sorted(MANIFEST["machine_files"])
    assert listed == sorted(str(p.relative_to(ROOT)) for p in (ROOT / "fixtures" / "machines").glob("*.toml"))
    kinds = {load_machine(ROOT / f).kind for f in listed}
    assert kinds == set(MANIFEST["machine_kinds"])
