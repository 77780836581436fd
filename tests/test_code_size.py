"""Size rules of the package (issue 24): no module over 500 lines, no function body over 80 lines.

One idea per home: a module that outgrows 500 lines holds more than one idea and becomes a package; a function body
over 80 lines does several steps that want names. The body is counted from its first statement (the docstring
included) to its last line, so a long signature — a Typer command's options — does not count.
"""

from __future__ import annotations

import ast
from pathlib import Path

from support import REPO

PACKAGE = REPO / "macsplat_cli"
MAX_MODULE_LINES = 500
MAX_BODY_LINES = 80


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def long_bodies(source: str) -> list[tuple[str, int, int]]:
    """``(name, line, body lines)`` of every function whose body is over :data:`MAX_BODY_LINES` lines."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            n = node.end_lineno - node.body[0].lineno + 1  # type: ignore[operator]
            if n > MAX_BODY_LINES:
                out.append((node.name, node.lineno, n))
    return out


def test_the_rules_see_a_long_body_and_not_a_long_signature() -> None:
    args = ",\n".join(f"    a{i}: int = 0" for i in range(100))
    long_signature = f"def f(\n{args},\n) -> None:\n    pass\n"
    long_body = "def g():\n" + "".join(f"    x{i} = {i}\n" for i in range(81))
    assert long_bodies(long_signature) == []
    assert long_bodies(long_body) == [("g", 1, 81)]


def test_the_package_is_found() -> None:
    assert len(_modules()) > 100


def test_no_module_over_500_lines_and_no_function_body_over_80() -> None:
    found = []
    for path in _modules():
        text = path.read_text(encoding="utf-8")
        where = path.relative_to(PACKAGE)
        if text.count("\n") > MAX_MODULE_LINES:
            found.append(f"{where}: {text.count(chr(10))} lines (split it by idea into a package)")
        found += [f"{where}:{line} {name}: a {n}-line body (name its steps)" for name, line, n in long_bodies(text)]
    assert found == [], "\n".join(found)
