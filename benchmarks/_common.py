"""What the benchmark scripts share: Markdown tables, timing (also of the pipeline's stages), peak memory, JSON.

Every script prints Markdown tables (:func:`row`, :func:`rule`) to paste into ``benchmarks/README.md`` or a page
of ``benchmarks/history/``. Stages are timed through the engine's progress callback (:class:`StageTimer`, passed
as ``on_stage`` to :func:`macsplat_cli.engine.reconstruct` or :meth:`~macsplat_cli.pipeline.run.Pipeline.run`),
never by replacing the pipeline's functions.
"""

from __future__ import annotations

import json
import resource
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from macsplat_cli.pipeline.pose import PoseResult
    from macsplat_cli.pipeline.run import Reconstruction


def row(cells: Sequence[str]) -> str:
    """One Markdown table row: ``| a | b |``."""
    return "| " + " | ".join(cells) + " |"


def rule(aligns: str) -> str:
    """The Markdown separator row, one character per column: ``l`` left (``---``), ``r`` right (``---:``)."""
    return "|" + "".join({"l": "---|", "r": "---:|"}[a] for a in aligns)


def print_header(columns: Sequence[str], aligns: str) -> None:
    """Print a table's header row and separator (``aligns`` as in :func:`rule`)."""
    assert len(columns) == len(aligns), (columns, aligns)
    print(row(columns))
    print(rule(aligns), flush=True)


def median_seconds(fn: Callable[[], Any], reps: int) -> float:
    """Median wall time of ``fn()`` over ``reps`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def peak_rss_mib() -> float:
    """This process's peak resident set size so far, MiB (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


class StageTimer:
    """An ``on_stage(stage, event)`` callback that times the stages: ``seconds[stage]`` (summed when a stage runs
    more than once), also for a stage that failed (``failed`` lists those)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.failed: list[str] = []
        self._start: dict[str, float] = {}

    def __call__(self, stage: str, event: str) -> None:
        now = time.perf_counter()
        if event == "start":
            self._start[stage] = now
            return
        self.seconds[stage] = self.seconds.get(stage, 0.0) + now - self._start.pop(stage, now)
        if event == "fail":
            self.failed.append(stage)


def write_json(path: Path, obj: Any, *, indent: int = 2, default: Callable[[Any], Any] | None = None) -> None:
    """Write ``obj`` as JSON (``default`` converts what ``json`` cannot)."""
    path.write_text(json.dumps(obj, indent=indent, default=default))


def pair_pose(rec: Reconstruction) -> PoseResult:
    """The pose search's result of a two-photo reconstruction (``rec.pose``, set whenever the pipeline estimated a
    pose)."""
    if rec.pose is None:
        raise RuntimeError("this reconstruction has no estimated pose (given poses?)")
    return rec.pose


def progress(message: str) -> None:
    """A line on stderr (the tables go to stdout)."""
    print(message, file=sys.stderr, flush=True)


def render_scene_params(n: int, seed: int = 0):  # noqa: ANN201 - torch imported lazily
    """The rasterizer benchmarks' scene (``bench_render.py``, ``gsplat_parity.py``, ``projection_peer.py``): ``n``
    Gaussians uniform in [-1, 1]² × [2, 4] before an identity camera, scales 0.005–0.03, random rotations, opacity
    logits U(-2, 2), SH degree 0 — ``(generator, [means, log_scales, quats, opacity_logits, sh])``, the generator
    left where the scene's draws end (the callers draw their target image from it)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * 2.0 - torch.tensor([1.0, 1.0, -2.0])
    params = [
        means,
        torch.log(torch.rand(n, 3, generator=g) * 0.025 + 0.005),
        torch.randn(n, 4, generator=g),
        torch.rand(n, generator=g) * 4 - 2,
        torch.randn(n, 1, 3, generator=g) * 0.5,
    ]
    return g, params
