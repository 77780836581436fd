"""Reusable buffers for the CPU kernels' arrays: a render's arrays of a few MB come from buffers an earlier render
used instead of fresh memory from the OS.

Why: glibc gives a freed block of a few MB back to the OS (it trims the heap or unmaps it), so the next render's
arrays fault again on every page they touch — at 100 k Gaussians and 256² about 4,000 page faults a step, 8–19 ms
of system time in a ~100 ms step (``benchmarks/history/render.md``). The host's allocator is left as it is.

How a buffer is shared without ever leaking data or being overwritten while read: the pool hands out *views* of
its buffers (``buffer[:nbytes].view(dtype).reshape(shape)``, whose ``base`` is the buffer) and a buffer is free
only while the pool's own reference is its only one (:func:`sys.getrefcount`). Whatever still holds a view — an
autograd node's saved arrays awaiting the backward, a tensor handed to the caller (``torch.from_numpy`` keeps the
view alive) — keeps the buffer out of reach of every later render; a view dropped makes it reusable. A buffer comes
back with the last user's values in it: :func:`empty` is for arrays a kernel writes in full (or reads only where it
wrote), :func:`zeros` and :func:`full` for the others.

Memory: the pool keeps a buffer only while renders keep taking it — one not taken during the last
:data:`IDLE_RENDERS` renders (:func:`next_render`) is dropped — and never more than :data:`KEEP_BYTES` in all (a
request that would go over it gets a plain allocation), none over :data:`MAX_BYTES`; :func:`release` forgets every
buffer now.
"""

from __future__ import annotations

import math
import sys
import threading

import numpy as np

__all__ = ["empty", "full", "next_render", "pooled_bytes", "release", "zeros"]

KEEP_BYTES = 64 << 20
"""Most bytes the pool holds in all (in use and free): a 256² step at 100 k Gaussians takes 35 MiB, the refinement's
step on the example (two views of 45 k at 256 × 176) 30 MiB; beyond it a render's arrays are plain allocations (a
1080p render at 1 M would pool 121 MiB, and its peak memory grow by as much, for a few % of its time)."""
MAX_BYTES = 32 << 20
"""Larger arrays are plain allocations: numpy asks the OS for huge pages for them (few faults), and pooled they would
pin hundreds of MB after one large render (at 1 M Gaussians and 1080p: the records, 61 MB; the tile lists, 100 MB)."""
IDLE_RENDERS = 4
"""A free buffer not taken during this many renders is dropped (a larger render's buffers do not outlive it long)."""
MIN_BYTES = 64 << 10
"""Smaller arrays are plain allocations: malloc serves them from its free lists without touching the OS."""
_SLACK = 2
"""A buffer serves requests down to 1/_SLACK of its size (the visible Gaussians' count varies between renders)."""
_PAGE = 4096  # a new buffer's size: the request and 1/16 of headroom (the next render's growth), in whole pages


class _Buffer:
    __slots__ = ("array", "free_refs", "taken")

    def __init__(self, nbytes: int, render: int) -> None:
        self.array = np.empty(nbytes, np.uint8)
        self.free_refs = sys.getrefcount(self.array)  # the count while no view exists
        self.taken = render

    def free(self) -> bool:
        return sys.getrefcount(self.array) == self.free_refs


class _Pool:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._buffers: list[_Buffer] = []
        self._render = 0

    def next_render(self) -> None:
        with self._lock:
            self._render += 1
            self._buffers = [b for b in self._buffers if not b.free() or self._render - b.taken <= IDLE_RENDERS]

    def release(self) -> None:
        with self._lock:
            self._buffers = []

    def pooled_bytes(self) -> int:
        with self._lock:
            return sum(b.array.nbytes for b in self._buffers)

    def take(self, nbytes: int) -> np.ndarray | None:
        """A free buffer of ``nbytes`` to ``_SLACK × nbytes`` bytes (and a page; the smallest), else a new one; None
        when a new one would take the pool over :data:`KEEP_BYTES`."""
        with self._lock:
            most = _SLACK * nbytes + _PAGE
            fits = [b for b in self._buffers if nbytes <= b.array.nbytes <= most and b.free()]
            if fits:
                best = min(fits, key=lambda b: b.array.nbytes)
            else:
                size = _PAGE * math.ceil((nbytes + nbytes // 16) / _PAGE)
                total = sum(b.array.nbytes for b in self._buffers)
                for b in sorted((b for b in self._buffers if b.free()), key=lambda b: b.taken):
                    if total + size <= KEEP_BYTES:
                        break
                    self._buffers.remove(b)  # the least recently taken free buffers go first
                    total -= b.array.nbytes
                if total + size > KEEP_BYTES:
                    return None
                best = _Buffer(size, self._render)
                self._buffers.append(best)
            best.taken = self._render
            return best.array[:nbytes]


_POOL = _Pool()


def empty(shape: int | tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """An array of ``shape`` and ``dtype`` (C order) on a pooled buffer, its values those of the buffer's last user:
    for an array that is written in full before it is read."""
    dtype = np.dtype(dtype)
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    nbytes = math.prod(shape) * dtype.itemsize
    buf = _POOL.take(nbytes) if MIN_BYTES <= nbytes <= MAX_BYTES else None
    if buf is None:
        return np.empty(shape, dtype)
    return buf.view(dtype).reshape(shape)


def zeros(shape: int | tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """:func:`empty`, filled with zeros."""
    return full(shape, 0, dtype)


def full(shape: int | tuple[int, ...], value: float, dtype: np.dtype | type) -> np.ndarray:
    """:func:`empty`, filled with ``value``."""
    out = empty(shape, dtype)
    out.fill(value)
    return out


def next_render() -> None:
    """Count one render (drops the buffers idle for :data:`IDLE_RENDERS` renders)."""
    _POOL.next_render()


def release() -> None:
    """Forget every buffer: the free ones are freed now, those in use when their last view goes."""
    _POOL.release()


def pooled_bytes() -> int:
    """Bytes the pool holds, in use and free."""
    return _POOL.pooled_bytes()
