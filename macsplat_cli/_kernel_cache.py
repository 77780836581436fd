"""Numba's on-disk kernel cache, stamped with the sources a kernel's module imports as well as its own.

Numba stamps a cached kernel with its own source file only (a hash of its contents). A kernel that calls or inlines a
jitted function of another module (``render/_kernels.py`` → ``_lanes.exp_neg``) or folds another module's constants
into its code at compile time (``render.constants``, ``sh.C0``) would load stale machine code after that other
module changed while its own file did not — what a ``git pull`` over an editable install does. Here the stamp also
covers the package-relative imports of the kernel's module: transitively through the modules that import Numba (the
kernels), one level into the others (their constants). A change in any of them recompiles the kernel once.

:func:`install` puts the locator first in Numba's list; every kernel module calls it before its first ``@njit``.
It keeps Numba's own choice of cache folder (``NUMBA_CACHE_DIR``, ``__pycache__`` beside the module, the user-wide
folder) and only adds to the stamp; ``NUMBA_CACHE_LOCATOR_CLASSES`` (Numba's override) still replaces it.
"""

from __future__ import annotations

import ast
import functools
import hashlib
from pathlib import Path
from typing import Any

from numba.core import caching

__all__ = ["install", "sources_digest"]

_ROOTS: list[Path] = []


def install(root: Path | None = None) -> None:
    """Stamp the kernels defined under ``root`` (default: this package) with their imports' sources (idempotent)."""
    root = (root or Path(__file__).parent).resolve()
    if root not in _ROOTS:
        _ROOTS.append(root)
    classes = caching.CacheImpl._locator_classes
    if _ImportsStamped not in classes:
        classes.insert(0, _ImportsStamped)


@functools.cache
def _imports(path: Path, mtime_ns: int, size: int) -> tuple[tuple[Path, ...], bool]:
    """The package-relative imports of the module at ``path`` (the files that exist), and whether it imports Numba
    (``mtime_ns``, ``size``: the memo's key, so that an edited file is read again)."""
    tree = ast.parse(path.read_bytes(), str(path))
    found: list[Path] = []
    numba = False
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            numba |= any(a.name.split(".")[0] == "numba" for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                numba |= (node.module or "").split(".")[0] == "numba"
                continue
            base = path.parent
            for _ in range(node.level - 1):
                base = base.parent
            stem = base.joinpath(*node.module.split(".")) if node.module else base
            names = [stem] if node.module else [base / a.name for a in node.names]
            for p in names:
                for file in (p.with_suffix(".py"), p / "__init__.py"):
                    if file.is_file():
                        found.append(file.resolve())
                        break
    return tuple(found), numba


def _imports_of(path: Path) -> tuple[tuple[Path, ...], bool]:
    st = path.stat()
    return _imports(path, st.st_mtime_ns, st.st_size)


def sources_digest(path: Path) -> bytes:
    """SHA-256 of the sources the module at ``path`` imports from its package: through the modules that import
    Numba, and the other modules they name (not theirs)."""
    path = path.resolve()
    seen = {path}
    queue = [path]
    while queue:
        imports, numba = _imports_of(queue.pop())
        if not numba:
            continue
        for p in imports:
            if p not in seen:
                seen.add(p)
                queue.append(p)
    digest = hashlib.sha256()
    for p in sorted(seen - {path}):
        st = p.stat()
        digest.update(str(p).encode() + b"\0" + _file_digest(p, st.st_mtime_ns, st.st_size))
    return digest.digest()


@functools.cache
def _file_digest(path: Path, mtime_ns: int, size: int) -> bytes:
    """SHA-256 of the file at ``path``, read once per version (every kernel of a module asks for the same files)."""
    return hashlib.sha256(path.read_bytes()).digest()


class _ImportsStamped(caching._CacheLocator):
    """Numba's locator for a kernel under one of the :func:`install` roots, its stamp extended with
    :func:`sources_digest`."""

    def __init__(self, inner: Any, py_file: str) -> None:
        self._inner = inner
        self._py_file = Path(py_file)

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> _ImportsStamped | None:
        path = Path(py_file).resolve()
        if not any(root in path.parents for root in _ROOTS):
            return None
        others: list[Any] = list(caching.CacheImpl._locator_classes)
        for other in others:
            if other is not cls:
                inner = other.from_function(py_func, py_file)
                if inner is not None:
                    return cls(inner, py_file)
        return None

    def ensure_cache_path(self) -> None:
        self._inner.ensure_cache_path()

    def get_cache_path(self) -> str:
        return str(self._inner.get_cache_path())

    def get_disambiguator(self) -> str:
        return str(self._inner.get_disambiguator())

    def get_source_stamp(self) -> Any:
        return (self._inner.get_source_stamp(), sources_digest(self._py_file))
