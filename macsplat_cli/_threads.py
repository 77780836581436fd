"""The CPU kernels' threads: a range split among daemon threads, each running a ``nogil`` Numba kernel.

The kernels are compiled serial (``for i in range(start, stop)``) and parallelised here instead of with Numba's
``parallel=True``: the parfor lowering costs seconds of compilation per kernel on a first run (every fresh install
and CI run pays it), and Python threads over ``nogil`` code run as concurrently. The workers are daemon threads, so
they never hold the process open (see ``cli.run``).
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable
from typing import Any, Literal, TypedDict

__all__ = ["JitOptions", "kernel_threads", "parallel_for"]

_MAX_THREADS = 64


class JitOptions(TypedDict, total=False):
    """The keyword arguments of ``numba.njit`` that the kernels set (one type for every kernel module's ``_JIT``)."""

    cache: bool
    nogil: bool
    fastmath: bool
    error_model: Literal["python", "numpy"]


def kernel_threads() -> int:
    """Threads for the CPU kernels: ``NUMBA_NUM_THREADS`` when set (as Numba's own pool would), else the CPUs this
    process may run on."""
    env = os.environ.get("NUMBA_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return min(int(env), _MAX_THREADS)
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        n = os.cpu_count() or 1
    return max(1, min(n, _MAX_THREADS))


class _Pool:
    """Daemon workers that run ``(fn, args, done)`` jobs from one queue."""

    def __init__(self) -> None:
        self._jobs: queue.SimpleQueue[tuple[Callable[..., Any], tuple[Any, ...], _Done]] = queue.SimpleQueue()
        self._workers: list[threading.Thread] = []
        self._lock = threading.Lock()

    def ensure(self, n: int) -> None:
        with self._lock:
            while len(self._workers) < n:
                t = threading.Thread(target=self._work, name=f"macsplat-kernel-{len(self._workers)}", daemon=True)
                t.start()
                self._workers.append(t)

    def _work(self) -> None:
        while True:
            fn, args, done = self._jobs.get()
            try:
                fn(*args)
            except BaseException as e:  # noqa: BLE001 - handed to the caller, which re-raises it
                done.error = e
            finally:
                del fn, args  # the job's arrays are not held while this worker waits (render/_workspace.py)
                done.event.set()

    def submit(self, fn: Callable[..., Any], args: tuple[Any, ...]) -> _Done:
        done = _Done()
        self._jobs.put((fn, args, done))
        return done


class _Done:
    __slots__ = ("error", "event")

    def __init__(self) -> None:
        self.event = threading.Event()
        self.error: BaseException | None = None


_POOL = _Pool()


def _after_fork_in_child() -> None:
    """A forked child (a data-loader worker) inherits the pool's state but none of its threads: start afresh."""
    global _POOL
    _POOL = _Pool()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


class _Batch:
    """The chunks of one :func:`parallel_for` call, taken one at a time by whoever is free (the caller too)."""

    def __init__(self, fn: Callable[..., Any], bounds: list[int], args: tuple[Any, ...]) -> None:
        self.fn, self.bounds, self.args = fn, bounds, args
        self._next = 0
        self._lock = threading.Lock()
        self.error: BaseException | None = None

    def run(self) -> None:
        while self.error is None:
            with self._lock:
                i = self._next
                self._next += 1
            if i >= len(self.bounds) - 1:
                return
            try:
                self.fn(self.bounds[i], self.bounds[i + 1], *self.args)
            except BaseException as e:  # noqa: BLE001 - re-raised by the caller
                self.error = self.error or e


def parallel_for(fn: Callable[..., Any], n: int, *args: Any, chunks_per_thread: int = 1) -> None:
    """``fn(start, stop, *args)`` over ``[0, n)`` in contiguous chunks, ``chunks_per_thread`` per thread (more
    than one balances uneven work), taken by the pool's threads and the calling one; returns when every chunk is
    done and re-raises the first error. ``fn`` must release the GIL (a ``nogil`` kernel) to run concurrently, and
    the chunks must not write the same memory."""
    threads = min(kernel_threads(), max(1, n))
    if threads <= 1:
        fn(0, n, *args)
        return
    k = min(n, threads * max(1, chunks_per_thread))
    batch = _Batch(fn, [n * i // k for i in range(k + 1)], args)
    _POOL.ensure(threads - 1)
    helpers = [_POOL.submit(batch.run, ()) for _ in range(threads - 1)]
    batch.run()
    for done in helpers:
        done.event.wait()
        batch.error = batch.error or done.error
    if batch.error is not None:
        raise batch.error
