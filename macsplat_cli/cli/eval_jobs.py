"""``eval --jobs N``: the run as N shard processes on this machine (``eval --shard I/N`` each, with this command's
own arguments), then ``eval merge`` of their results into ``--out``: the same files as one process writes.

Each process gets ``cores / N`` threads (``NUMBA_NUM_THREADS``, ``OMP_NUM_THREADS``), so the jobs share the machine
instead of oversubscribing it. The shards' folders stay under ``--out/shards/`` (a failed shard can be rerun alone
with the ``--shard`` its log line names, then merged with ``macsplat eval merge``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from ._common import err_console, escape

__all__ = ["run_jobs"]


def _threads(jobs: int) -> int:
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return max(1, cores // jobs)


def run_jobs(jobs: int, out: Path, *, quiet: bool) -> tuple[object, float]:
    """Run the shards, wait for them, merge them into ``out``; ``(merged run, seconds)``.

    Raises:
        InputError: a shard that did not finish (its last error line, and how to rerun it).
    """
    from ..errors import InputError
    from ..evaluation.shards import merge_shards
    from ._app import invocation

    args = invocation()
    threads = str(_threads(jobs))
    env = {**os.environ, "NUMBA_NUM_THREADS": threads, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads}
    folders = [out / "shards" / f"{i}-of-{jobs}" for i in range(jobs)]
    t0 = time.perf_counter()
    procs = []
    for i, folder in enumerate(folders):
        cmd = [sys.executable, "-m", "macsplat_cli", *args, "--jobs", "1", "--shard", f"{i}/{jobs}", "--out",
               str(folder), "--quiet"]  # fmt: skip
        procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
    if not quiet:
        err_console.print(escape(f"{jobs} jobs, {threads} thread(s) each, into {out / 'shards'}"), highlight=False)
    failed = []
    for i, proc in enumerate(procs):
        _, err = proc.communicate()
        lines = [ln for ln in err.splitlines() if ln.strip()]
        if proc.returncode != 0 and not (folders[i] / "results.json").is_file():
            failed.append(f"job {i}/{jobs} (exit {proc.returncode}): {lines[-1] if lines else 'no message'}")
        elif not quiet:
            err_console.print(escape(f"job {i}/{jobs} finished"), highlight=False)
    if failed:
        raise InputError("; ".join(failed) + f"; rerun a job alone with --shard I/{jobs}, then macsplat eval merge")
    merged = merge_shards(folders, out)
    return merged.run, time.perf_counter() - t0
