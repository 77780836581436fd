"""The layering rule of ``ARCHITECTURE.md``, checked on the source: arrows point down, never in a cycle.

Every module of ``macsplat_cli`` is parsed with :mod:`ast` (nothing is imported) and every ``import`` in it is
an edge: at module level, inside a function (imported when it runs), or under ``if TYPE_CHECKING:`` (for the
type checker only); relative and absolute alike. The tests assert:

* every module has a layer (:data:`LAYERS`, the table of ``ARCHITECTURE.md``);
* no edge points to a higher layer (a smaller number) — function-level and typing imports included;
* within a layer, an edge between two of its homes only where :data:`PEERS` allows it
  (``neural/`` does not reach into ``datasets/``);
* a private module (``_name``) is imported only from inside its own package;
* no cycle among the module-level imports, nor among all of them (a function-level import that closes a
  cycle is a cycle the module structure hides).
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = "macsplat_cli"
PACKAGE_DIR = Path(__file__).resolve().parents[1] / ROOT

LAYERS: dict[str, tuple[int, str]] = {
    # 1: the commands
    "cli": (1, "the commands: map options to an EngineConfig, write files"),
    "__main__": (1, "python -m macsplat_cli: runs the CLI"),
    # 2: the library boundary and its two big callers
    "engine": (2, "load the models, build the pipeline, run it (the library boundary)"),
    "evaluation": (2, "eval and bench: run the engine over data sets"),
    "training": (2, "macsplat train: trains the predictor on data sets"),
    "viewer": (2, "macsplat view: serves a scene and its cameras to a browser page"),
    # 3: the stages
    "pipeline": (3, "the stages of reconstruct (pose, depth, compact, refine, neural backend) and their chain"),
    "presets": (3, "quality / backend presets turned into the pipeline's config"),
    # 4: the building blocks the stages use
    "neural": (4, "the networks, their checkpoints and ONNX form"),
    "render": (4, "the rasterizer"),
    "datasets": (4, "data-set loaders and the synthetic scene generator"),
    "mac": (4, "the Multi-Attribute Consistency losses"),
    "lpips": (4, "the LPIPS-VGG loss from user files"),
    # 5: low modules: shared math, types and I/O, importing nothing above them
    "__init__": (5, "the package root: the version and the OpenMP default; imports nothing"),
    "errors": (5, "the typed errors and their exit codes"),
    "_atomic": (5, "atomic file writes"),
    "_threads": (5, "the CPU kernels' threads"),
    "_kernel_cache": (5, "the CPU kernels' on-disk cache, stamped with their imports"),
    "_limits": (5, "input size limits, safe JSON parsing"),
    "_checks": (5, "shape and value checks"),
    "_json": (5, "JSON conversion of dataclasses and arrays"),
    "_log": (5, "logging setup"),
    "_state_dict": (5, "weight files: state-dict key/shape checks, safetensors, sha256"),
    "camera_math": (5, "shared pinhole arithmetic"),
    "rotations": (5, "rotation conversions"),
    "sh": (5, "spherical harmonics"),
    "metrics": (5, "image and pose metrics"),
    "cameras": (5, "Camera, CameraSet and their files"),
    "camera_formats": (5, "other tools' camera files"),
    "distortion": (5, "lens distortion models and their fold check"),
    "images": (5, "image reading and writing"),
    "gaussians": (5, "the Gaussian containers"),
    "ply": (5, "the 3DGS PLY format"),
    "report": (5, "the run report"),
    "trajectory": (5, "camera paths for novel views"),
}
"""Home (path under ``macsplat_cli``, dotted, a package or a module) → (layer, why it sits there)."""

PEERS: dict[tuple[str, str], str] = {
    ("evaluation", "engine"): "eval and bench reconstruct through the engine",
}
"""Imports allowed between two homes of layer 2 or 4 (importer, imported) → why; the other homes of these
layers are independent of each other. Layers 1, 3 and 5 are one body each: their homes import each other
freely (still without cycles)."""
INDEPENDENT_LAYERS = (2, 4)


@dataclass(frozen=True)
class Edge:
    source: str  # dotted, without the root: "neural.predictor"
    target: str
    line: int
    kind: str  # "module", "function" or "typing"

    def where(self) -> str:
        return f"{self.source} → {self.target} (line {self.line}, {self.kind})"


def _module_name(path: Path, directory: Path) -> str:
    parts = list(path.relative_to(directory).with_suffix("").parts)
    if parts[-1] == "__init__" and len(parts) > 1:
        parts.pop()
    return ".".join(parts)


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


class _Imports(ast.NodeVisitor):
    """Every import of one module with where it runs: module level, in a function, under TYPE_CHECKING."""

    def __init__(self) -> None:
        self.found: list[tuple[ast.Import | ast.ImportFrom, str]] = []
        self._function = 0
        self._typing = 0

    def _kind(self) -> str:
        return "typing" if self._typing else "function" if self._function else "module"

    def visit_FunctionDef(self, node: ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda) -> None:
        self._function += 1
        self.generic_visit(node)
        self._function -= 1

    visit_AsyncFunctionDef = visit_FunctionDef
    visit_Lambda = visit_FunctionDef

    def visit_If(self, node: ast.If) -> None:
        test = node.test
        typing = (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
            isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
        )
        self.visit(node.test)
        self._typing += typing
        for child in node.body:
            self.visit(child)
        self._typing -= typing
        for child in node.orelse:
            self.visit(child)

    def visit_Import(self, node: ast.Import) -> None:
        self.found.append((node, self._kind()))

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        self.found.append((node, self._kind()))


def _parse(directory: Path) -> tuple[set[str], list[Edge]]:
    """All modules under ``directory`` (dotted, without the root) and their imports of each other."""
    files = sorted(directory.rglob("*.py"))
    modules = {_module_name(f, directory) for f in files}
    edges: list[Edge] = []
    for f in files:
        source = _module_name(f, directory)
        visitor = _Imports()
        visitor.visit(ast.parse(f.read_text(encoding="utf-8"), filename=str(f)))
        for node, kind in visitor.found:
            for target in dict.fromkeys(_targets(node, source, _is_package(f), modules)):
                if target != source:
                    edges.append(Edge(source, target, node.lineno, kind))
    return modules, edges


def _resolve(dotted: str, modules: set[str]) -> str | None:
    """The longest module of ``macsplat_cli`` that ``dotted`` (absolute, with the root) names, else None."""
    parts = dotted.split(".")
    if parts[0] != ROOT:
        return None
    parts = parts[1:]
    while parts:
        if ".".join(parts) in modules:
            return ".".join(parts)
        parts.pop()
    return "__init__"


def _targets(node: ast.Import | ast.ImportFrom, source: str, is_package: bool, modules: set[str]) -> Iterator[str]:
    if isinstance(node, ast.Import):
        for alias in node.names:
            target = _resolve(alias.name, modules)
            if target is not None:
                yield target
        return
    if node.level:
        package = [ROOT, *source.split(".")] if source != "__init__" else [ROOT]
        if not is_package:
            package.pop()
        base = package[: len(package) - (node.level - 1)]
        if node.module:
            base = [*base, *node.module.split(".")]
    else:
        base = (node.module or "").split(".")
    prefix = ".".join(base)
    if _resolve(prefix, modules) is None:
        return
    for alias in node.names:  # `from pkg import submodule` imports the submodule
        yield _resolve(f"{prefix}.{alias.name}", modules)  # type: ignore[misc]


def _home(module: str) -> str | None:
    """The entry of :data:`LAYERS` that holds ``module`` (longest prefix)."""
    parts = module.split(".")
    while parts:
        name = ".".join(parts)
        if name in LAYERS:
            return name
        parts.pop()
    return None


def _layer(module: str) -> int:
    home = _home(module)
    assert home is not None, module
    return LAYERS[home][0]


def _private_package(module: str) -> str | None:
    """The package a private module belongs to (``neural`` for ``neural._x``; ``""`` for the root's), else None."""
    parts = module.split(".")
    if not any(p.startswith("_") and not p.startswith("__") for p in parts):
        return None
    i = max(k for k, p in enumerate(parts) if p.startswith("_") and not p.startswith("__"))
    return ".".join(parts[:i])


def violations(modules: set[str], edges: list[Edge]) -> list[str]:
    """Every breach of the layering rule, one line each (``kind: source → target`` first)."""
    out = [f"no layer: {m}" for m in sorted(modules) if _home(m) is None]
    for e in edges:
        if _home(e.source) is None or _home(e.target) is None:
            continue
        src, dst = _layer(e.source), _layer(e.target)
        head = f"{e.source} → {e.target}"
        if dst < src:
            out.append(f"upward: {head} | layer {src} → {dst}, line {e.line}, {e.kind}")
        hs, ht = _home(e.source), _home(e.target)
        if src == dst and src in INDEPENDENT_LAYERS and hs != ht and (hs, ht) not in PEERS:
            out.append(f"sideways: {head} | {hs} → {ht} in layer {src}, line {e.line}, {e.kind}")
        owner = _private_package(e.target)
        if owner is not None and owner and not (e.source == owner or e.source.startswith(owner + ".")):
            out.append(f"private: {head} | a private module of {owner}/, line {e.line}, {e.kind}")
    return out


def cycles(edges: list[Edge]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
        graph.setdefault(e.target, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:  # recursion depth: the longest import chain (a few dozen)
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def _one_cycle(component: list[str], edges: list[Edge]) -> str:
    """A shortest import loop through the component's first module, each step with its line and kind."""
    inside = [e for e in edges if e.source in component and e.target in component]
    start = component[0]
    came: dict[str, Edge] = {}
    frontier = [start]
    while frontier and start not in came:
        nxt = []
        for v in frontier:
            for e in inside:
                if e.source == v and e.target not in came:
                    came[e.target] = e
                    nxt.append(e.target)
        frontier = nxt
    steps, v = [], start
    while True:
        steps.append(came[v])
        v = came[v].source
        if v == start:
            break
    return "; ".join(e.where() for e in reversed(steps))


def _cycle_key(component: list[str]) -> str:
    return "cycle: " + " ↔ ".join(component)


@pytest.fixture(scope="module")
def graph() -> tuple[set[str], list[Edge]]:
    return _parse(PACKAGE_DIR)


def test_the_parser_sees_every_kind_of_import(tmp_path: Path) -> None:
    """Relative and absolute, module level, in a function, under TYPE_CHECKING, ``from pkg import module``."""
    pkg = tmp_path / ROOT
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "low.py").write_text("X = 1\n")
    (pkg / "sub" / "__init__.py").write_text("from . import a\n")
    (pkg / "sub" / "a.py").write_text(
        "from typing import TYPE_CHECKING\nimport os\nfrom .. import low\nfrom ..low import X\n"
        "if TYPE_CHECKING:\n    from macsplat_cli.sub import b\n"
        "def f():\n    import macsplat_cli.sub.b\n    from .b import Y\n"
    )
    (pkg / "sub" / "b.py").write_text("Y = 2\nclass C:\n    from .. import low as _low\n")
    modules, edges = _parse(pkg)
    assert modules == {"__init__", "low", "sub", "sub.a", "sub.b"}
    assert {(e.source, e.target, e.kind) for e in edges} == {
        ("sub", "sub.a", "module"),
        ("sub.a", "low", "module"),
        ("sub.a", "sub.b", "typing"),
        ("sub.a", "sub.b", "function"),
        ("sub.b", "low", "module"),
    }
    assert cycles(edges) == []
    assert cycles([*edges, Edge("sub.b", "sub.a", 1, "function")]) == [["sub.a", "sub.b"]]


def test_every_module_has_a_layer(graph: tuple[set[str], list[Edge]]) -> None:
    modules, _ = graph
    assert [m for m in sorted(modules) if _home(m) is None] == []


def test_no_import_points_up_sideways_or_into_a_private_module(graph: tuple[set[str], list[Edge]]) -> None:
    found = violations(*graph)
    assert found == [], "\n" + "\n".join(found)


def test_no_cycle_among_module_level_imports(graph: tuple[set[str], list[Edge]]) -> None:
    _, edges = graph
    found = [_cycle_key(c) for c in cycles([e for e in edges if e.kind == "module"])]
    assert found == [], "\n" + "\n".join(found)


def test_no_cycle_among_all_imports(graph: tuple[set[str], list[Edge]]) -> None:
    """Function-level imports too: a cycle they close is still a cycle of the design."""
    _, edges = graph
    detail = [f"{_cycle_key(c)}: {_one_cycle(c, edges)}" for c in cycles(edges)]
    assert detail == [], "\n" + "\n".join(detail)
