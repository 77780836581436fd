"""Numba's on-disk cache of the kernels follows the sources they import (:mod:`macsplat_cli._kernel_cache`)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from macsplat_cli import _kernel_cache

# a kernel module that inlines a jitted helper of a sibling module and folds a constant of a plain module
KERNEL = """
import numba as nb
from .helper import twice
from .constants import OFFSET

@nb.njit(cache=True)
def kernel(x):
    return twice(x) + OFFSET
"""
HELPER = """
import numba as nb

@nb.njit(inline="always", cache=True)
def twice(x):
    return {factor} * x
"""
CALL = """
import sys
from pathlib import Path
sys.path.insert(0, {root!r})
from macsplat_cli import _kernel_cache
if {stamped}:
    _kernel_cache.install(Path({root!r}) / "pkg")
from pkg.kernel import kernel
print(kernel(10), len(kernel.stats.cache_hits))
"""


def _package(root: Path, factor: int, offset: int) -> None:
    pkg = root / "pkg"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "kernel.py").write_text(KERNEL)
    (pkg / "helper.py").write_text(HELPER.format(factor=factor))
    (pkg / "constants.py").write_text(f"OFFSET = {offset}\n")


def _run(root: Path, stamped: bool) -> tuple[int, int]:
    """``kernel(10)`` in a fresh interpreter, and how many cached compilations it loaded."""
    env_script = CALL.format(root=str(root), stamped=stamped)
    out = subprocess.run([sys.executable, "-c", env_script], capture_output=True, text=True, check=True).stdout
    value, hits = out.split()
    return int(value), int(hits)


def test_an_edited_import_recompiles_the_kernel_that_inlined_it(tmp_path: Path) -> None:
    """Numba alone (``stamped=False``) loads the first build from its cache after the helper's edit: 21, not 31."""
    _package(tmp_path, factor=2, offset=1)
    assert _run(tmp_path, stamped=True) == (21, 0)  # compiled, then written to the cache
    assert _run(tmp_path, stamped=True) == (21, 1)  # loaded from the cache
    _package(tmp_path, factor=3, offset=1)  # only the inlined helper changes
    assert _run(tmp_path, stamped=True) == (31, 0)
    _package(tmp_path, factor=3, offset=5)  # only the folded constant changes
    assert _run(tmp_path, stamped=True) == (35, 0)


def test_the_digest_covers_the_kernels_imports_and_stops_at_plain_modules(tmp_path: Path) -> None:
    _package(tmp_path, factor=2, offset=1)
    pkg = tmp_path / "pkg"
    (pkg / "constants.py").write_text("from .far import FAR\nOFFSET = 1\n")  # a plain module's own import
    (pkg / "far.py").write_text("FAR = 1\n")
    before = _kernel_cache.sources_digest(pkg / "kernel.py")
    (pkg / "far.py").write_text("FAR = 2\n")
    assert _kernel_cache.sources_digest(pkg / "kernel.py") == before
    (pkg / "constants.py").write_text("from .far import FAR\nOFFSET = 2\n")
    assert _kernel_cache.sources_digest(pkg / "kernel.py") != before
