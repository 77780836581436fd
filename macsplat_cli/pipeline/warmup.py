"""The stages' CPU kernels compiled (or loaded from Numba's cache) before the stages reach them.

:func:`compile_in_background` starts a daemon thread that loads the kernels a run uses, in the order the stages need
them, so that a first run's compilation overlaps the stages before them instead of adding to them. Numba compiles
one function at a time in a process (a global lock), so a first run was as long as the sum of its kernels'
compilations; when the renderer's kernels are not in the cache yet, a second process compiles them into it while
this one compiles the others, and the thread then loads them from the cache (``benchmarks/first_run.py``). Numba is
first imported in that thread: the modules the engine and the settings import do not load it
(``tests/test_engine.py``), so its import overlaps the images and SIFT stages. A stage that gets to a kernel first
compiles it itself (Numba's lock makes the thread wait); a failure here only costs that.
"""

from __future__ import annotations

import logging
import subprocess
import threading

__all__ = ["compile_in_background", "threads", "wait_for_renderer"]

logger = logging.getLogger(__name__)

STAGES = ("matching", "multiview", "depth", "compact", "render")
"""The stages with kernels, in the order a run reaches them (``multiview``: only with more than two photos)."""
_RENDER_CHILD = "from macsplat_cli.render import compile_kernels; compile_kernels()"
"""What the second process runs: the renderer's kernels, the last a run needs and the longest to compile (~12 s of a
first run's ~27 s on two cores)."""

CHILD_WAIT_S = 300.0
"""The longest a render waits for the second process (its compilation takes ~15 s on two loaded cores); then it
compiles here."""

threads: list[threading.Thread] = []
"""The background threads started in this process (one per call that had stages left to load)."""
_queued: set[str] = set()
_children: list[subprocess.Popen[bytes]] = []


def compile_in_background(photos: int) -> None:
    """Load the kernels a run of ``photos`` photos uses, each stage's once per process, in a daemon thread (module
    docstring). Two photos skip the N-photo stages' kernels: compiled first, they held Numba's lock while the depth
    stage waited."""
    names = [n for n in STAGES if n not in _queued and (photos > 2 or n != "multiview")]
    if not names:
        return
    _queued.update(names)
    threads.append(threading.Thread(target=_load, args=(names,), name="macsplat-compile", daemon=True))
    threads[-1].start()


def _load(names: list[str]) -> None:
    """The thread's work: each stage of ``names`` (:data:`STAGES`) loads its kernels in turn, the renderer's once its
    process (:func:`_render_in_child`), if one was started, is done."""
    from .. import render
    from . import compact, depth, matching, multiview

    stages = {"matching": matching, "multiview": multiview, "depth": depth, "compact": compact, "render": render}
    if "render" in names:
        _render_in_child()
    for name in names:
        try:
            if name == "render":
                wait_for_renderer()  # then the kernels load from the cache (or compile here, had the child failed)
            stages[name].compile_kernels()
        except Exception as e:  # noqa: BLE001 - the stage compiles its kernel on first use anyway
            logger.debug("background compilation of %s failed: %s", name, e)


def _render_in_child() -> subprocess.Popen[bytes] | None:
    """A process compiling the renderer's kernels into Numba's cache, started when they are not there yet and a
    second CPU can run it (None when they are, on one kernel thread — one CPU, or ``eval --jobs`` filling the cores:
    a second process would only add its imports —, or when no process could be started)."""
    from multiprocessing import spawn

    from .._threads import kernel_threads
    from ..render import kernels_uncached

    python = spawn.get_executable()  # multiprocessing's interpreter: an app embedding Python sets it to a Python
    if not python or kernel_threads() < 2 or not kernels_uncached():
        return None
    try:
        quiet = subprocess.DEVNULL
        child = subprocess.Popen([python, "-c", _RENDER_CHILD], stdin=quiet, stdout=quiet, stderr=quiet)
    except OSError as e:  # no process: the thread compiles them
        logger.debug("no process to compile the renderer's kernels: %s", e)
        return None
    _children.append(child)
    return child


def wait_for_renderer() -> None:
    """Before a run's first render: wait for the process compiling the renderer's kernels, if one was started (at
    most :data:`CHILD_WAIT_S`): its kernels then load from the cache instead of compiling here a second time."""
    for child in _children:
        try:
            child.wait(CHILD_WAIT_S)
        except subprocess.TimeoutExpired:
            logger.debug("the renderer's kernels did not compile in %.0f s in their process", CHILD_WAIT_S)
