"""plugin_manifest.json agrees with pyproject.toml and with the code it names."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import inspect
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


def _subcommand_tree(parser) -> dict:
    """{"machine check": subparser, "post": subparser, ...}: the leaves of the argparse tree (words joined by blanks)."""
    leaves = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                deeper = _subcommand_tree(sub)
                leaves.update({f"{name} {k}": v for k, v in deeper.items()} if deeper else {name: sub})
    return leaves


def resolve(target: str):
    """'package.module:attr.attr' -> the object."""
    module, _, attr = target.partition(":")
    obj = importlib.import_module(module)
    for part in filter(None, attr.split(".")):
        obj = getattr(obj, part)
    return obj


def test_subcommands_are_exactly_the_parsers_commands():
    assert sorted(MANIFEST["subcommands"]) == sorted(_subcommand_tree(build_parser()))


def test_python_hook_is_the_compensate_api():
    from trueaxis.nc.gcode import GcodeError
    from trueaxis.postproc.post import MODES

    hook = MANIFEST["hooks"]["python"]
    compensate = resolve(hook["api"])
    assert callable(compensate) and hook["api"] == "trueaxis.postproc:compensate"
    params = inspect.signature(compensate).parameters
    assert list(params)[:3] == ["program", "machine", "mode"] and params["mode"].default == "geometric"
    assert hook["signature"].startswith("compensate(program, machine, mode='geometric'")
    assert tuple(hook["modes"]) == MODES
    assert issubclass(resolve(hook["error"]), GcodeError)
    assert callable(resolve(hook["machine_loader"]))


def test_freecad_hook_names_the_shipped_post_script_its_export_and_its_installer():
    from trueaxis.postproc.hosts.freecad import post_script_path

    hook = MANIFEST["hooks"]["freecad"]
    script = ROOT / hook["post_script"]
    assert script.is_file() and script.resolve() == post_script_path()
    assert script.name == f"{hook['post_processor_name']}_post.py"  # FreeCAD lists *_post.py by that stem
    spec = importlib.util.spec_from_file_location("trueaxis_post_manifest", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # imports FreeCAD only inside export
    export = getattr(module, hook["entry"])
    assert callable(export)
    assert hook["entry_signature"] == f"{hook['entry']}({', '.join(inspect.signature(export).parameters)})"
    assert callable(resolve(hook["install_function"]))
    assert hook["install_command"] in _subcommand_tree(build_parser())


def test_cadquery_hook_registers_the_named_workplane_methods():
    import cadquery as cq

    hook = MANIFEST["hooks"]["cadquery"]
    module = importlib.import_module(hook["module"])
    register = resolve(hook["register"])
    assert callable(register) and register is module.register
    register()
    for method, target in hook["workplane_methods"].items():
        assert getattr(cq.Workplane, method) is resolve(target)
    assert (ROOT / hook["example"]).is_file()


def test_machine_layouts_are_the_fixture_machines_layouts():
    from trueaxis.machine import load_machine

    def layout(m):
        if m.kind == "lathe":
            return f"{len(m.axis_names)}-axis lathe".replace("2-axis", "two-axis")
        if not m.rotary_axes:
            return "three-axis mill"
        table = [a for a in m.rotary_axes if a in m.bed_to_workpiece]
        return {2: "five-axis table-table", 1: "five-axis head-table", 0: "five-axis head-head"}[len(table)]

    assert sorted(MANIFEST["machine_layouts"]) == sorted({layout(load_machine(ROOT / f))
                                                         for f in MANIFEST["machine_files"]})


def test_input_formats_resolve_and_read_their_examples(tmp_path):
    commands = _subcommand_tree(build_parser())
    for fmt in MANIFEST["formats_in"]:
        reader = resolve(fmt["reader"])
        assert callable(reader), fmt
        assert all(c in commands for c in fmt.get("commands", [])), fmt
        assert fmt["extensions"] and all(e.startswith(".") and e == e.lower() for e in fmt["extensions"]), fmt
        if "example" in fmt:
            example = ROOT / fmt["example"]
            assert example.suffix in fmt["extensions"], fmt
            # every listed extension is read the same (the readers go by content, not by name)
            for ext in fmt["extensions"]:
                copy = tmp_path / f"example{ext}"
                copy.write_bytes(example.read_bytes())
                assert reader(copy) is not None, (fmt["name"], ext)


def test_cloud_formats_read_a_small_cloud_of_each_extension(tmp_path):
    fmt = next(f for f in MANIFEST["formats_in"] if f["reader"] == "trueaxis.inspect.cloud:read_cloud")
    points = "0 0 0\n1 0 0\n0 1 0\n"
    texts = {".xyz": points, ".csv": "x,y,z\n0,0,0\n1,0,0\n0,1,0\n",
             ".ply": "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n" + points}
    assert sorted(fmt["extensions"]) == sorted(texts)
    for ext, text in texts.items():
        path = tmp_path / f"cloud{ext}"
        path.write_text(text)
        assert resolve(fmt["reader"])(path).points.shape == (3, 3)


def test_output_formats_resolve_to_writers_and_commands():
    commands = _subcommand_tree(build_parser())
    for fmt in MANIFEST["formats_out"]:
        assert callable(resolve(fmt["writer"])), fmt
        assert all(c in commands for c in fmt.get("commands", [])), fmt
        assert fmt["extensions"] and all(e.startswith(".") for e in fmt["extensions"]), fmt


def test_machine_files_are_exactly_the_fixture_machines_and_load():
    from trueaxis.machine import load_machine

    listed = sorted(MANIFEST["machine_files"])
    assert listed == sorted(str(p.relative_to(ROOT)) for p in (ROOT / "fixtures" / "machines").glob("*.toml"))
    kinds = {load_machine(ROOT / f).kind for f in listed}
    assert kinds == set(MANIFEST["machine_kinds"])
