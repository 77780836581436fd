"""How many settings the stage configs hold, per stage, and which of them nothing sets (issue 38).

    python -m benchmarks.config_size

A *leaf setting* is a dataclass field whose default is not itself a dataclass (those are counted through). A
field is *set* when its name is assigned somewhere in ``macsplat_cli/``, ``benchmarks/`` or ``tests/``: a keyword
of a call to its class or to ``replace(...)``, or an attribute assignment ``x.name = ...`` (by name, so a field
that shares its name with another class's set field counts as set). Prints one Markdown table: leaves per stage of
``ReconstructConfig``, of ``EngineConfig``, and the fields nothing sets. Measured: benchmarks/history/settings.md.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
from pathlib import Path
from typing import Any

from benchmarks._common import print_header, row

REPO = Path(__file__).resolve().parents[1]
SEARCHED = ("macsplat_cli", "benchmarks", "tests")


def leaves(obj: Any, prefix: str = "") -> list[tuple[str, type, str]]:
    """``(dotted path, owning class, field name)`` of every leaf setting under the dataclass instance ``obj``."""
    out = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        path = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out += leaves(value, path + ".")
        else:
            out.append((path, type(obj), f.name))
    return out


def _callee(node: ast.Call) -> str:
    func = node.func
    return func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else ""


@functools.cache
def set_names(roots: tuple[str, ...] = SEARCHED) -> tuple[dict[str, set[str]], set[str]]:
    """``(class name → keywords of calls to it, names set by replace(...) or attribute assignment)`` over the
    Python files under ``roots``."""
    by_class: dict[str, set[str]] = {}
    anywhere: set[str] = set()
    for root in roots:
        for path in sorted((REPO / root).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Call):
                    names = {k.arg for k in node.keywords if k.arg}
                    callee = _callee(node)
                    if callee == "replace":
                        anywhere |= names
                    else:
                        by_class.setdefault(callee, set()).update(names)
                elif isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign)):
                    targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                    for t in targets:
                        for sub in ast.walk(t):
                            if isinstance(sub, ast.Attribute) and isinstance(sub.ctx, ast.Store):
                                anywhere.add(sub.attr)
    return by_class, anywhere


def unset(obj: Any, prefix: str = "") -> list[str]:
    """The dotted paths of the leaf settings under ``obj`` that nothing sets (:func:`set_names`)."""
    by_class, anywhere = set_names()
    return [path for path, cls, name in leaves(obj, prefix)
            if name not in anywhere and name not in by_class.get(cls.__name__, set())]  # fmt: skip


def counts() -> dict[str, int]:
    """Leaf settings per top-level field of ``ReconstructConfig`` (its stages), its total and ``EngineConfig``'s."""
    from macsplat_cli.engine import EngineConfig
    from macsplat_cli.pipeline.run import ReconstructConfig

    config = ReconstructConfig()
    out = {f.name: len(leaves(getattr(config, f.name))) if dataclasses.is_dataclass(getattr(config, f.name)) else 1
           for f in dataclasses.fields(config)}  # fmt: skip
    out["ReconstructConfig"] = len(leaves(config))
    out["EngineConfig"] = len(leaves(EngineConfig()))
    return out


def main() -> None:
    from macsplat_cli.engine import EngineConfig

    n = counts()
    print_header(["config", "leaf settings"], "lr")
    for name, k in n.items():
        print(row([name, str(k)]))
    missing = unset(EngineConfig())
    print()
    print_header([f"set by nothing ({len(missing)})"], "l")
    for path in missing:
        print(row([path]))


if __name__ == "__main__":
    main()
