"""``reconstruct --profile``: where the seconds and the memory of one run go, stage by stage.

Fed the same ``on_stage(stage, "start" | "end" | "fail")`` events as the progress display. Per stage: wall seconds,
the share of the command's time, the process's resident memory at the end of the stage and its peak so far
(``ru_maxrss``), and by how much the stage raised that peak. The first row is the command's start-up: from the
command's start to the first stage (importing torch, OpenCV and Numba, reading the settings).
"""

from __future__ import annotations

import resource
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from rich.table import Table

if TYPE_CHECKING:
    from rich.text import JustifyMethod

__all__ = ["StageProfile"]


def _rss_mib() -> float | None:
    """Resident memory now, MiB (Linux's ``/proc/self/statm``; None elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * resource.getpagesize() / 2**20


def _peak_mib() -> float:
    """Peak resident memory of this process so far, MiB (``ru_maxrss``: KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024


@dataclass
class _Row:
    stage: str
    seconds: float
    rss: float | None
    peak: float
    peak_growth: float
    failed: bool = False


@dataclass
class StageProfile:
    """Collects the rows; :meth:`table` renders them."""

    started: float = field(default_factory=time.perf_counter)
    rows: list[_Row] = field(default_factory=list)
    _open: dict[str, tuple[float, float]] = field(default_factory=dict)
    _first_stage: float | None = None

    def event(self, stage: str, kind: str) -> None:
        now = time.perf_counter()
        if kind == "start":
            if self._first_stage is None:
                self._first_stage = now
                self.rows.append(_Row("start-up (imports, settings)", now - self.started, _rss_mib(), _peak_mib(), 0.0))
            self._open[stage] = (now, _peak_mib())
            return
        t0, peak0 = self._open.pop(stage, (now, _peak_mib()))
        peak = _peak_mib()
        self.rows.append(_Row(stage, now - t0, _rss_mib(), peak, peak - peak0, failed=kind == "fail"))

    def table(self) -> Table:
        total = time.perf_counter() - self.started
        t = Table(title="where the time and memory went", title_justify="left", box=None, pad_edge=False)
        columns: tuple[tuple[str, JustifyMethod], ...] = (
            ("stage", "left"), ("seconds", "right"), ("share", "right"), ("RSS MiB", "right"), ("peak MiB", "right"),
            ("peak +MiB", "right"),
        )  # fmt: skip
        for name, justify in columns:
            t.add_column(name, justify=justify)
        for r in self.rows:
            rss = f"{r.rss:,.0f}" if r.rss is not None else "-"
            name = f"{r.stage} (failed)" if r.failed else r.stage
            t.add_row(name, f"{r.seconds:.3f}", f"{100 * r.seconds / total:.0f} %", rss, f"{r.peak:,.0f}",
                      f"{r.peak_growth:+,.0f}" if r.peak_growth else "")  # fmt: skip
        t.add_row("total (the command)", f"{total:.3f}", "100 %", "", f"{_peak_mib():,.0f}", "", style="bold")
        return t
