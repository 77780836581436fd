"""The background compilation's second process: started only when the renderer's kernels are not in Numba's cache."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from macsplat_cli import render
from macsplat_cli.pipeline import warmup

ROOT = Path(__file__).resolve().parents[2]

_FIRST_RUN = r"""
from multiprocessing import spawn
from macsplat_cli.pipeline import warmup
from macsplat_cli.render import kernels_uncached

uncached = kernels_uncached()
child = warmup._render_in_child()
started = child is not None and child.args == [spawn.get_executable(), "-c", warmup._RENDER_CHILD]
if child is not None:
    child.kill()
    child.wait()
print(uncached, started)
"""


def test_no_process_is_started_when_the_kernels_are_cached() -> None:
    """Once the projection kernel is in the cache (this process compiled or loaded it), a run starts no process."""
    render.compile_kernels()
    assert not render.kernels_uncached()
    assert warmup._render_in_child() is None


@pytest.mark.parametrize(("threads", "started"), [("2", "True"), ("1", "False")])
def test_an_empty_numba_cache_starts_the_process_that_compiles_the_renderer(
    tmp_path: Path, threads: str, started: str
) -> None:
    """With an empty cache (a first run), the probe of Numba's index says so and, given a second kernel thread, the
    process is started with the renderer's compilation (killed here at once: its compilation is the first run's, not
    this test's); on one thread it is not."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "PYTHONPATH": str(ROOT), "NUMBA_NUM_THREADS": threads}
    res = subprocess.run([sys.executable, "-c", _FIRST_RUN], capture_output=True, text=True, env=env, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split() == ["True", started], res.stdout
