"""No function of the post is longer than about a screenful (issue 21: "no function over about 100 lines in the
interpreter or the post"): every function and method in ``trueaxis/postproc/*.py``, nested ones included, spans at
most ``MAX_LINES`` lines from its ``def`` to its last line (``end_lineno - lineno``, read with ``ast``; nothing is
imported)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 100
CHECKED = sorted((ROOT / "trueaxis" / "postproc").glob("*.py"))


def long_functions(source: str, name: str, limit: int = MAX_LINES) -> list[str]:
    """'name:line: function spans N lines' for every function of ``source`` longer than ``limit``."""
    out = []
    for node in ast.walk(ast.parse(source, name)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            span = node.end_lineno - node.lineno
            if span > limit:
                out.append(f"{name}:{node.lineno}: {node.name} spans {span} lines (at most {limit})")
    return out


def test_the_post_modules_are_found():
    assert "post.py" in {p.name for p in CHECKED}


def test_no_function_in_the_post_is_longer_than_the_limit():
    found = [msg for path in CHECKED for msg in long_functions(path.read_text(), str(path.relative_to(ROOT)))]
    assert not found, "\n".join(found)


def test_the_check_sees_a_long_method_and_spares_a_short_one():
    body = "".join(f"        x{i} = {i}\n" for i in range(MAX_LINES))  # def line + MAX_LINES lines: span MAX_LINES
    src = f"class A:\n    def short(self):\n{body}\n    def long(self):\n{body}        x = 0\n"
    assert long_functions(src, "m.py") == [f"m.py:{MAX_LINES + 4}: long spans {MAX_LINES + 1} lines (at most 100)"]
