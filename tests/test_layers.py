"""The package tree is the architecture (docs/architecture.md): every import of a trueaxis module, module-level or
inside a function, goes to the same package or to a lower layer, and the packages import each other without a cycle.

Layers, lowest first:

1. base: ``trueaxis`` itself, ``fileio``, ``resources``, ``compiled`` (numba or the ahead-of-time kernels) (and ``units`` / ``errors`` should they appear);
2. ``machine``;
3. ``nc``;
4. ``workpiece``;
5. the libraries ``postproc`` (compensation, the post), ``inspect``, ``sim``, ``identify``, ``diagnose``. Peers are
   ordered in that sequence and a peer may import only the peers before it (the virtual shop measures with the
   inspection's clouds and surfaces; the diagnosis runs the shop and reads clouds; nothing imports the diagnosis);
6. the application: ``cli`` (and ``__main__``, ``python -m trueaxis``), ``demo``, ``loop`` (the closed loop), ``warm``
   and the host glue ``postproc.hosts`` (FreeCAD post script, CadQuery plugin), which keeps its public import path.

The imports are read with ``ast`` (nothing is imported), so the test is quick and sees function-level imports too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "trueaxis"

# unit (a package, or a group of top-level modules) -> layer; a module belongs to the longest prefix listed
UNITS = {
    "trueaxis": ("base", 1),
    "trueaxis.fileio": ("base", 1),
    "trueaxis.resources": ("base", 1),
    "trueaxis.compiled": ("base", 1),
    "trueaxis.units": ("base", 1),
    "trueaxis.errors": ("base", 1),
    "trueaxis.machine": ("machine", 2),
    "trueaxis.nc": ("nc", 3),
    "trueaxis.workpiece": ("workpiece", 4),
    "trueaxis.postproc": ("postproc", 5),
    "trueaxis.inspect": ("inspect", 5),
    "trueaxis.sim": ("sim", 5),
    "trueaxis.identify": ("identify", 5),
    "trueaxis.diagnose": ("diagnose", 5),
    "trueaxis.postproc.hosts": ("application", 6),
    "trueaxis.cli": ("application", 6),
    "trueaxis.__main__": ("application", 6),  # python -m trueaxis: the command line
    "trueaxis.demo": ("application", 6),
    "trueaxis.loop": ("application", 6),
    "trueaxis.warm": ("application", 6),
}
PEER_ORDER = ("postproc", "inspect", "sim", "identify", "diagnose")  # layer 5: each may import those before it


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules() -> dict:
    """Module name -> path of every module under trueaxis/."""
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def unit_of(module: str):
    best = None
    for prefix in UNITS:
        if module == prefix or module.startswith(prefix + "."):
            if best is None or len(prefix) > len(best):
                best = prefix
    return None if best is None else UNITS[best]


def imports_of(module: str, path: Path, modules: dict) -> list:
    """(line, imported module) for every trueaxis import in the file, relative imports resolved; ``from P import m``
    names the module P.m when m is a module."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "trueaxis"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "trueaxis":
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                found.append((node.lineno, sub if sub in modules else target))
    return found


def edges():
    """(importer, line, imported, importer's unit, imported unit) for every trueaxis import."""
    modules = all_modules()
    out = []
    for module, path in modules.items():
        for line, target in imports_of(module, path, modules):
            out.append((module, line, target, unit_of(module), unit_of(target)))
    return out


def layer_violations() -> list:
    out = []
    for module, line, target, (u_a, l_a), (u_b, l_b) in edges():
        if u_a == u_b:
            continue
        if l_b > l_a:
            out.append(f"{module}:{line} imports {target} (layer {l_b} {u_b}) from layer {l_a} {u_a}")
        elif l_a == l_b == 5 and PEER_ORDER.index(u_b) > PEER_ORDER.index(u_a):
            out.append(f"{module}:{line} imports {target} ({u_b} comes after {u_a} among the layer-5 peers)")
        elif l_a == l_b != 5:
            out.append(f"{module}:{line} imports {target}: two units {u_a} / {u_b} in layer {l_a}")
    return out


def unit_cycles() -> list:
    """Cycles of the unit graph (each as a list of units), found by depth-first search."""
    graph: dict = {}
    for _, _, _, (u_a, _), (u_b, _) in edges():
        if u_a != u_b:
            graph.setdefault(u_a, set()).add(u_b)
    cycles, state = [], {}

    def visit(u, stack):
        state[u] = 1
        stack.append(u)
        for v in sorted(graph.get(u, ())):
            if state.get(v) == 1:
                cycles.append(stack[stack.index(v):] + [v])
            elif v not in state:
                visit(v, stack)
        stack.pop()
        state[u] = 2

    for u in sorted(graph):
        if u not in state:
            visit(u, [])
    return cycles


def test_every_module_has_a_layer():
    assert [m for m in all_modules() if unit_of(m) is None] == []


def test_every_trueaxis_import_names_an_existing_module():
    modules = all_modules()
    missing = [f"{m}:{line} imports {t}" for m, line, t, _, _ in edges() if t not in modules]
    assert missing == []


def test_no_module_imports_a_higher_layer_or_a_later_peer():
    assert layer_violations() == []


def test_no_import_cycle_between_packages():
    assert unit_cycles() == []


@pytest.mark.parametrize("bad, expected", [
    ("from trueaxis.cli import main\n", "layer 6 application"),
    ("from ..diagnose.state import TwinState\n", "diagnose comes after sim"),
])
def test_the_check_sees_an_upward_import(tmp_path, monkeypatch, bad, expected):
    """The walker itself: a module-level and a relative import upwards, planted in a copy of sim, are both reported
    (so an empty list above means something)."""
    copy = tmp_path / "trueaxis"
    import shutil

    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    target = copy / "sim" / "envelope.py"
    target.write_text(target.read_text(encoding="utf-8") + "\n\ndef _planted():\n    " + bad, encoding="utf-8")
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    monkeypatch.setitem(globals(), "PACKAGE", copy)
    found = [v for v in layer_violations() if v.startswith("trueaxis.sim.envelope:")]
    assert len(found) == 1 and expected in found[0]


# Below the application layer no module knows the command line. diagnose/report.py still takes an argparse namespace
# (its own issue removes it; then take it off this list).
ARGS_STILL_BELOW: set = set()


def test_no_argparse_below_the_application_layer():
    found = set()
    for module, path in all_modules().items():
        if unit_of(module)[1] == 6:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        called = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}  # args.split(): a string's method
        for node in ast.walk(tree):
            argparse_import = (isinstance(node, ast.Import) and any(a.name == "argparse" for a in node.names)) or \
                (isinstance(node, ast.ImportFrom) and node.module == "argparse")
            # fields read off something named args (not methods called on it): a namespace travelling into the domain
            namespace = isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                and node.value.id == "args" and id(node) not in called
            getattr_args = isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr" \
                and node.args and isinstance(node.args[0], ast.Name) and node.args[0].id == "args"
            if argparse_import or namespace or getattr_args:
                found.add(path.relative_to(ROOT).as_posix())
    assert found <= ARGS_STILL_BELOW, sorted(found - ARGS_STILL_BELOW)


# The program as data reads like LinuxCNC's interpreter split by concern: no function of trueaxis/nc longer than this
# (ast: end_lineno - lineno, the docstring and comments counted). Exceptions, each with its reason:
MAX_FUNCTION_LINES = 100
LONG_FUNCTIONS_ALLOWED = {
    # a numba kernel, compiled ahead of time too (its source hash names the build): one line's scan, a state machine
    # over the line's bytes that keeps its state in registers; split, it would pass that state through calls
    "trueaxis/nc/fast_read.py:_scan_line": "compiled kernel",
}


def function_lengths(path: Path) -> dict:
    """{qualified name: lines (end_lineno - lineno)} of every function and method of a module."""
    out = {}

    def walk(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                out[prefix + child.name] = child.end_lineno - child.lineno
                walk(child, prefix + child.name + ".")
            elif isinstance(child, ast.ClassDef):
                walk(child, prefix + child.name + ".")
            else:
                walk(child, prefix)

    walk(ast.parse(path.read_text(encoding="utf-8"), str(path)), "")
    return out


def test_no_function_of_the_nc_package_is_over_100_lines():
    long = {}
    for path in sorted((PACKAGE / "nc").glob("*.py")):
        for name, n in function_lengths(path).items():
            if n > MAX_FUNCTION_LINES:
                long[f"{path.relative_to(ROOT).as_posix()}:{name}"] = n
    assert set(long) <= set(LONG_FUNCTIONS_ALLOWED), {k: v for k, v in long.items() if k not in LONG_FUNCTIONS_ALLOWED}
    # an exception that is no longer needed is taken off the list
    assert set(LONG_FUNCTIONS_ALLOWED) <= set(long), sorted(set(LONG_FUNCTIONS_ALLOWED) - set(long))


def test_the_length_check_sees_a_long_function(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES + 1))
    path = tmp_path / "m.py"
    path.write_text(f"class C:\n    def run(self):\n    {body.replace(chr(10), chr(10) + '    ')}\n        return 0\n")
    assert function_lengths(path)["C.run"] == MAX_FUNCTION_LINES + 2
