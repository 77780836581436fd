"""The GPU smoke check's process plumbing: finding the GPUs, sampling their memory while a step runs, and running one
step as a child process into a table row (:class:`Result`). Used by :mod:`benchmarks.gpu_smoke`.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

SAMPLE_MS = 100
"""nvidia-smi sampling period (ms); PyTorch's and onnxruntime's allocators keep what they reserved, so a peak
lasts until the process ends and a coarse period does not miss it."""
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


@dataclass
class Result:
    """One row of the table. ``status``: ``ok``, ``failed`` or ``skipped``; ``peak_mib`` None when unknown."""

    step: str
    status: str
    seconds: float | None = None
    peak_mib: float | None = None
    note: str = ""
    stderr_tail: list[str] = field(default_factory=list)


# ============================================================================================= device detection
def nvidia_gpus() -> list[str]:
    """The GPUs ``nvidia-smi -L`` lists (empty without nvidia-smi or a working driver)."""
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return []
    try:
        out = subprocess.run([exe, "-L"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return []
    return [ln.strip() for ln in out.stdout.splitlines() if ln.startswith("GPU ")] if out.returncode == 0 else []


def gpu_present() -> bool:
    """An NVIDIA GPU is attached: nvidia-smi lists one, or the driver exposes a device node (no torch import)."""
    return bool(nvidia_gpus()) or Path("/dev/nvidia0").exists()


def smi_index() -> str:
    """nvidia-smi's ``-i`` for the GPU the steps use: the first of ``CUDA_VISIBLE_DEVICES`` (an index or a UUID,
    as nvidia-smi takes them), else 0. Where nvidia-smi refuses it, the memory column shows ``-``."""
    return os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",")[0].strip() or "0"


# ============================================================================================= peak memory
class GpuMemoryPoll:
    """Peak of the GPU's used memory (MiB) from ``nvidia-smi -lms``, minus the value when it started."""

    def __init__(self, index: str) -> None:
        self.exe = shutil.which("nvidia-smi")
        self.args = ["--query-gpu=memory.used", "--format=csv,noheader,nounits", "-i", index]
        self.base: float | None = None
        self.peak: float | None = None
        self._proc: subprocess.Popen[str] | None = None
        self._thread: threading.Thread | None = None

    def _read_one(self) -> float | None:
        if self.exe is None:
            return None
        try:
            out = subprocess.run([self.exe, *self.args], capture_output=True, text=True, timeout=30)
            return float(out.stdout.split()[0]) if out.returncode == 0 else None
        except (OSError, subprocess.SubprocessError, ValueError, IndexError):
            return None

    def _follow(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        for line in self._proc.stdout:
            try:
                value = float(line.split(",")[0])
            except (ValueError, IndexError):
                continue
            self.peak = value if self.peak is None else max(self.peak, value)

    def __enter__(self) -> GpuMemoryPoll:
        if self.exe is None:
            return self
        self.base = self._read_one()
        self.peak = self.base
        try:
            self._proc = subprocess.Popen(
                [self.exe, *self.args, "-lms", str(SAMPLE_MS)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                text=True,
            )  # fmt: skip
        except OSError:
            return self
        self._thread = threading.Thread(target=self._follow, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._proc is not None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
            if self._thread is not None:
                self._thread.join(timeout=10)

    @property
    def used_mib(self) -> float | None:
        return None if self.base is None or self.peak is None else max(self.peak - self.base, 0.0)


# ============================================================================================= running one step
def last_line(text: str) -> str:
    """The last non-empty line of a process's output (progress redraws and ANSI colours removed)."""
    for line in reversed(re.split(r"[\r\n]+", _ANSI.sub("", text))):
        if line.strip():
            return line.strip()
    return ""


def run_process(
    step: str,
    argv: Sequence[str],
    *,
    cwd: Path,
    env: dict[str, str],
    timeout: float,
    gpu: bool,
    logs: Path,
    check: Callable[[], str] | None = None,
) -> Result:
    """Run ``argv`` in its own session; wall time, peak memory, and ok/failed with the last stderr line.

    stdout and stderr go to ``logs/<step>.out`` and ``.err``. A process still running after ``timeout`` seconds
    is killed with its process group. ``check`` (run after exit 0) returns the row's note, or raises
    ``AssertionError`` saying what is wrong with the step's output.
    """
    logs.mkdir(parents=True, exist_ok=True)
    out_path, err_path = logs / f"{step}.out", logs / f"{step}.err"
    poll = GpuMemoryPoll(smi_index()) if gpu else None
    timed_out = threading.Event()
    with open(out_path, "wb") as out, open(err_path, "wb") as err, poll or contextlib.nullcontext():
        t0 = time.perf_counter()
        try:
            proc = subprocess.Popen(list(argv), cwd=cwd, env=env, stdout=out, stderr=err, start_new_session=True)
        except OSError as e:
            return Result(step, "failed", time.perf_counter() - t0, None, f"cannot start {argv[0]}: {e}")

        def kill() -> None:
            timed_out.set()
            try:
                os.killpg(proc.pid, signal.SIGKILL)  # the group this step's process leads (torchrun's workers too)
            except ProcessLookupError:
                pass

        timer = threading.Timer(timeout, kill)
        timer.start()
        try:
            _, status, usage = os.wait4(proc.pid, 0)  # rusage of this process tree alone
        finally:
            timer.cancel()
        proc.returncode = os.waitstatus_to_exitcode(status)
        seconds = time.perf_counter() - t0
    peak = poll.used_mib if poll is not None else usage.ru_maxrss / 1024  # Linux: ru_maxrss in KiB
    stderr = err_path.read_text(errors="replace")
    tail = [ln for ln in _ANSI.sub("", stderr).replace("\r", "\n").splitlines() if ln.strip()][-15:]
    if timed_out.is_set():
        return Result(step, "failed", seconds, peak, f"timed out after {timeout:g} s", tail)
    if proc.returncode != 0:
        why = last_line(stderr) or last_line(out_path.read_text(errors="replace")) or "(no output)"
        return Result(step, "failed", seconds, peak, f"exit {proc.returncode}: {why}", tail)
    note = ""
    if check is not None:
        try:
            note = check()
        except (AssertionError, OSError, ValueError, KeyError) as e:
            return Result(step, "failed", seconds, peak, f"exit 0 but {e}", tail)
    return Result(step, "ok", seconds, peak, note)
