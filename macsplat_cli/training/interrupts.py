"""Holding Ctrl-C and SIGTERM back while a training step completes, so a checkpoint always sits at a step boundary."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any

__all__ = ["interrupts_held"]

_INTERRUPTS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM") if hasattr(signal, name))


@contextlib.contextmanager
def interrupts_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back while inside, and deliver them on the way out (main thread only).

    The handlers are swapped for one that only notes the signal (Python runs signal handlers in the main thread
    whatever thread the OS picked, so this holds them for the whole process); the previous handlers are put back
    and each noted signal is raised again, so Ctrl-C and SIGTERM act right after the block as they would have in it.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous: dict[int, Any] = {}

    def note(signum: int, frame: Any) -> None:
        held.append(signum)

    try:
        for s in _INTERRUPTS:
            if signal.getsignal(s) is not None:  # None: a handler installed outside Python, left alone
                previous[s] = signal.signal(s, note)
    except (ValueError, OSError):  # no signals here (an embedded interpreter)
        for s, h in previous.items():
            signal.signal(s, h)
        previous.clear()
    try:
        yield
    finally:
        for s, h in previous.items():  # a signal pending here is noted first (signal.signal checks before swapping)
            signal.signal(s, h)
        for s in dict.fromkeys(held):
            signal.raise_signal(s)
