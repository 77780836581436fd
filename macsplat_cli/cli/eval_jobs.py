"""``eval --jobs N``: the run as N shard processes on this machine (``eval --shard I/N`` each, with this command's
own arguments), then ``eval merge`` of their results into ``--out``: the same files as one process writes.

N is capped at the run's number of cases (counted here, once, as the shards will select them: a bad data set is
refused before any process starts) and at what the available memory holds (:data:`JOB_MEMORY_BYTES` a process);
the log says so when it caps. Each process gets ``cores / N`` threads (``NUMBA_NUM_THREADS``, ``OMP_NUM_THREADS``),
so the jobs share the machine instead of oversubscribing it. The shards' folders stay under ``--out/shards/`` (a
failed shard can be rerun alone with the ``--shard`` its log line names, then merged with ``macsplat eval merge``);
like ``coverage/``, ``shards/`` and each shard's folder are refused when they are links
(:func:`~.._atomic.check_folder`).

Each shard runs in its own process group. When this command stops early — Ctrl-C, SIGTERM, an error — it sends
SIGTERM to every group still running (the shards remove their partial files and exit), waits up to
:data:`STOP_WAIT_S` for them, then kills what is left: no shard outlives the command.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from .._atomic import check_folder
from ._common import err_console, escape, out_console
from ._eval_report import print_summary

if TYPE_CHECKING:
    from ..evaluation import EvalRun

__all__ = ["JOB_MEMORY_BYTES", "STOP_WAIT_S", "available_memory", "eval_jobs", "job_cap", "run_jobs"]

logger = logging.getLogger("macsplat_cli.cli.eval")

JOB_MEMORY_BYTES = 350 * 1024**2
"""Memory one shard process takes: an interpreter with torch, OpenCV and Numba running one small case (about 335 MB
measured, issue 37)."""
STOP_WAIT_S = 10.0
"""How long stopped shards get to remove their partial files and exit after SIGTERM before they are killed."""


def _threads(jobs: int) -> int:
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return max(1, cores // jobs)


def available_memory() -> int | None:
    """Bytes of memory available to new processes: ``MemAvailable`` of ``/proc/meminfo``, else the free physical
    pages (``os.sysconf``); None when neither can be read."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # kB
    with contextlib.suppress(AttributeError, OSError, ValueError):
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    return None


def job_cap(jobs: int, cases: int, memory: int | None) -> tuple[int, str | None]:
    """``--jobs`` capped at the run's ``cases`` and at the processes ``memory`` bytes hold (:data:`JOB_MEMORY_BYTES`
    each; None: not known, no cap), at least one; and why it was capped (None: not capped)."""
    by_memory = jobs if memory is None else max(1, memory // JOB_MEMORY_BYTES)
    n = max(1, min(jobs, cases, by_memory))
    if n == jobs:
        return n, None
    if n == max(1, cases) or memory is None:  # memory None: nothing but the cases caps it
        return n, f"--jobs {jobs} capped at {n}: the run has {cases} case(s)"
    return n, (f"--jobs {jobs} capped at {n}: {memory / 1e9:.1f} GB of memory available, about "
               f"{JOB_MEMORY_BYTES / 1e6:.0f} MB a process")  # fmt: skip


def _stop(procs: list[subprocess.Popen[str]]) -> None:
    """SIGTERM to the process group of every shard still running, then wait for them (:data:`STOP_WAIT_S`, then
    SIGKILL); Ctrl-C and SIGTERM held back meanwhile (and delivered after)."""
    from ..training.interrupts import interrupts_held

    with interrupts_held():
        running = [p for p in procs if p.poll() is None]
        for p in running:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + STOP_WAIT_S
        for p in running:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        for p in procs:
            with contextlib.suppress(OSError):
                if p.stderr is not None:
                    p.stderr.close()


def run_jobs(jobs: int, out: Path, *, quiet: bool) -> tuple[EvalRun, float]:
    """Run the shards, wait for them, merge them into ``out``; ``(merged run, seconds)``. The shards are stopped
    (:func:`_stop`) if this returns early.

    Raises:
        InputError: a shard that did not finish (its last error line, and how to rerun it).
        OutputPathError: ``out/shards`` or a shard's folder (or a file in it) is a link.
    """
    from ..errors import InputError
    from ..evaluation import ResultWriter
    from ..evaluation.shards import merge_shards
    from ._app import invocation

    args = invocation()
    threads = str(_threads(jobs))
    env = {**os.environ, "NUMBA_NUM_THREADS": threads, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads}
    check_folder(out / "shards")
    folders = [out / "shards" / f"{i}-of-{jobs}" for i in range(jobs)]
    for folder in folders:  # before any job: a link here would carry a shard's files out of --out
        ResultWriter.check(check_folder(folder))
    t0 = time.perf_counter()
    procs: list[subprocess.Popen[str]] = []
    failed: list[str] = []
    try:
        for i, folder in enumerate(folders):
            cmd = [sys.executable, "-m", "macsplat_cli", *args, "--jobs", "1", "--shard", f"{i}/{jobs}", "--out",
                   str(folder), "--quiet"]  # fmt: skip
            procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                          start_new_session=True))  # fmt: skip
        if not quiet:
            err_console.print(escape(f"{jobs} jobs, {threads} thread(s) each, into {out / 'shards'}"), highlight=False)
        for i, proc in enumerate(procs):
            _, err = proc.communicate()
            lines = [ln for ln in err.splitlines() if ln.strip()]
            if proc.returncode != 0 and not (folders[i] / "results.json").is_file():
                failed.append(f"job {i}/{jobs} (exit {proc.returncode}): {lines[-1] if lines else 'no message'}")
            elif not quiet:
                err_console.print(escape(f"job {i}/{jobs} finished"), highlight=False)
    finally:
        _stop(procs)
    if failed:
        raise InputError("; ".join(failed) + f"; rerun a job alone with --shard I/{jobs}, then macsplat eval merge")
    merged = merge_shards(folders, out)
    return merged.run, time.perf_counter() - t0


def eval_jobs(
    jobs: int, out: Path, shard: str | None, quiet: bool, json_out: bool, splatt3r_compatible: bool,
    count_cases: Callable[[], int],
) -> None:  # fmt: skip
    """``--jobs N``: ``count_cases()`` (the run's cases), :func:`job_cap`, :func:`run_jobs`, then the summary as one
    process prints it."""
    from .._json import to_jsonable
    from ..errors import InputError
    from ..evaluation import ResultWriter
    from ..evaluation.summary import summarize

    if shard is not None:
        raise InputError("--jobs and --shard: give one (--jobs N runs the N shards itself)")
    ResultWriter.check(out)
    check_folder(out / "shards")
    jobs, why = job_cap(jobs, count_cases(), available_memory())
    if why is not None:
        logger.warning(why)
    run, seconds = run_jobs(jobs, out, quiet=quiet)
    rows = summarize(run)
    writer = ResultWriter(out)
    if not quiet:
        print_summary(run, rows, writer, splatt3r_compatible, seconds)
    if json_out:
        out_console.print_json(json.dumps({"summary": to_jsonable(rows), "results": str(writer.json_path)}))
