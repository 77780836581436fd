"""``eval --jobs N`` under hostile conditions (issue 37, J1–J3), with real shard processes on the plane data set.

* J1 a link planted at ``--out/shards`` or at a shard's folder is refused before any job starts (the shards were
  written through it);
* J2 SIGTERM to the command stops its shard processes and waits for them before it exits 143 (they ran on, orphaned);
* J3 N is capped at the run's number of cases and at what the available memory holds, and the log says so (8 jobs
  for 2 cases started 8 interpreters).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from macsplat_cli.cli.eval_jobs import JOB_MEMORY_BYTES, available_memory, job_cap

from support.cli import one_error_line, run_captured

COMMON = ["--split", "close,medium", "--max-pairs", "1", "--max-targets", "1", "--no-baselines", "--size", "64"]
"""A run of a few small cases (at least two on the plane)."""


def _eval(plane: Path, *args: object) -> list[str]:
    return [str(a) for a in ("eval", "--data", plane, *COMMON, *args)]


# ------------------------------------------------------------------------------------------------ J1
def test_a_link_at_out_shards_is_refused_before_any_job(
    capsys: pytest.CaptureFixture[str], plane: Path, tmp_path: Path
) -> None:
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "shards").symlink_to(tmp_path / "elsewhere")
    code, _, err = run_captured(capsys, *_eval(plane, "--jobs", "2", "--out", tmp_path / "out", "-q"))
    assert code == 2 and "shards: it is a symbolic link" in one_error_line(err), err
    assert list((tmp_path / "elsewhere").iterdir()) == []


def test_a_link_at_a_shard_folder_is_refused_before_any_job(
    capsys: pytest.CaptureFixture[str], plane: Path, tmp_path: Path
) -> None:
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "out" / "shards").mkdir(parents=True)
    (tmp_path / "out" / "shards" / "1-of-2").symlink_to(tmp_path / "elsewhere")
    code, _, err = run_captured(capsys, *_eval(plane, "--jobs", "2", "--out", tmp_path / "out", "-q"))
    assert code == 2 and "1-of-2: it is a symbolic link" in one_error_line(err), err
    assert list((tmp_path / "elsewhere").iterdir()) == []
    assert not (tmp_path / "out" / "shards" / "0-of-2").exists()  # no job started


# ------------------------------------------------------------------------------------------------ J2
def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    kids = []
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                stat = Path(entry.path, "stat").read_text()
                if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                    kids.append(int(entry.name))
    return kids


def _running(pid: int) -> bool:
    """Whether ``pid`` exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux's /proc")
def test_sigterm_stops_the_shard_processes_and_waits_for_them(plane: Path, tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "macsplat_cli", *_eval(plane, "--jobs", "2", "--out", tmp_path / "out", "-q")]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    kids: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while len(kids) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
            kids = _children(proc.pid)
        assert len(kids) == 2, f"the command started {len(kids)} shard processes (exit {proc.poll()})"
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 143, err
        assert [k for k in kids if _running(k)] == [], "shard processes still running after the command exited"
        assert not (tmp_path / "out" / "results.json").exists()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for k in kids:
            with contextlib.suppress(OSError):
                os.kill(k, signal.SIGKILL)


# ------------------------------------------------------------------------------------------------ J3
def test_job_cap_takes_the_fewest_of_jobs_cases_and_memory() -> None:
    big = 1000 * JOB_MEMORY_BYTES
    assert job_cap(4, 10, big) == (4, None) and job_cap(4, 10, None) == (4, None)
    n, why = job_cap(8, 2, big)
    assert n == 2 and why is not None and "the run has 2 case(s)" in why
    n, why = job_cap(1000, 5000, 3 * JOB_MEMORY_BYTES + 1)
    assert n == 3 and why is not None and "GB of memory available" in why
    assert job_cap(8, 2, JOB_MEMORY_BYTES // 2)[0] == 1  # at least one
    memory = available_memory()
    assert memory is None or memory > 0


def test_jobs_beyond_the_cases_are_capped_and_logged(
    capsys: pytest.CaptureFixture[str], plane: Path, tmp_path: Path
) -> None:
    code, _, err = run_captured(capsys, *_eval(plane, "--jobs", "8", "--out", tmp_path / "out", "-q"))
    assert code == 0, err
    assert "--jobs 8 capped at" in err and "case(s)" in err, err
    n = int(err.split("capped at ")[1].split(":")[0])
    assert 2 <= n < 8
    assert sorted(p.name for p in (tmp_path / "out" / "shards").iterdir()) == [f"{i}-of-{n}" for i in range(n)]
