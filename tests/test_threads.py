"""_threads.parallel_for: every index once, in chunks; errors re-raised; one thread runs inline."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from macsplat_cli import _threads


def _mark(start: int, stop: int, out: np.ndarray, seen: list) -> None:
    out[start:stop] += 1
    seen.append((start, stop, threading.get_ident()))


@pytest.mark.parametrize("threads", ["1", "2", "3"])
@pytest.mark.parametrize(("n", "per_thread"), [(1, 1), (7, 1), (100, 8), (5, 8)])
def test_every_index_once(monkeypatch: pytest.MonkeyPatch, threads: str, n: int, per_thread: int) -> None:
    monkeypatch.setenv("NUMBA_NUM_THREADS", threads)
    out, seen = np.zeros(n, int), []
    _threads.parallel_for(_mark, n, out, seen, chunks_per_thread=per_thread)
    np.testing.assert_array_equal(out, 1)
    chunks = sorted((a, b) for a, b, _ in seen)
    assert chunks[0][0] == 0 and chunks[-1][1] == n and all(b == c for (_, b), (c, _) in zip(chunks, chunks[1:]))
    assert len(chunks) == min(n, int(threads) * per_thread) if int(threads) > 1 else len(chunks) == 1


def test_an_error_in_any_chunk_is_raised_after_all_finished(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NUMBA_NUM_THREADS", "2")
    started, finished = [], []

    def work(start: int, stop: int) -> None:
        started.append(start)
        time.sleep(0.02)
        finished.append(start)
        if start == 5:
            raise ValueError(f"chunk {start}")

    with pytest.raises(ValueError, match="chunk 5"):
        _threads.parallel_for(work, 10, chunks_per_thread=5)
    assert sorted(started) == sorted(finished) and 5 in finished  # nothing still running when it is raised


def test_workers_are_daemons(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NUMBA_NUM_THREADS", "2")
    _threads.parallel_for(lambda a, b: None, 4)
    workers = [t for t in threading.enumerate() if t.name.startswith("macsplat-kernel-")]
    assert workers and all(t.daemon for t in workers)  # they never keep the process (or the CLI's fast exit) alive


def test_kernel_threads_follows_numba_num_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NUMBA_NUM_THREADS", "3")
    assert _threads.kernel_threads() == 3
    monkeypatch.delenv("NUMBA_NUM_THREADS")
    assert _threads.kernel_threads() >= 1


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="no fork on this platform")
def test_a_forked_child_gets_its_own_workers(monkeypatch: pytest.MonkeyPatch) -> None:
    """The parent's workers do not exist in a forked child (a data-loader worker): the child starts its own."""
    import multiprocessing as mp

    monkeypatch.setenv("NUMBA_NUM_THREADS", "2")
    _threads.parallel_for(lambda a, b: None, 4)  # the parent's pool has a worker now
    ctx = mp.get_context("fork")
    with ctx.Pool(1) as pool:
        assert pool.apply_async(_child_sum, (100,)).get(timeout=30) == 100


def _child_sum(n: int) -> int:
    out = np.zeros(n, int)
    _threads.parallel_for(_mark, n, out, [], chunks_per_thread=4)
    return int(out.sum())
