"""``benchmarks/gpu_smoke.py``: the no-GPU exit, a tiny CPU run of its steps, and its step runner.

The script is for a machine with a GPU; here it runs its steps on the CPU with ``--device cpu --tiny``.
"""

from __future__ import annotations

import importlib
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
import torch

from support import REPO

SMOKE = [sys.executable, "-m", "benchmarks.gpu_smoke"]  # run from the repository root, as the README says
GPU_HERE = shutil.which("nvidia-smi") is not None or Path("/dev/nvidia0").exists() or torch.cuda.is_available()


@pytest.fixture(scope="module")
def smoke() -> Iterator[ModuleType]:
    """``benchmarks.gpu_smoke``, imported the way ``python -m benchmarks.gpu_smoke`` runs it (repository root first)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(REPO))
        yield importlib.import_module("benchmarks.gpu_smoke")


def _rows(stdout: str) -> dict[str, list[str]]:
    """The Markdown table's rows by step: ``[result, seconds, peak MiB, note]``."""
    rows = {}
    for line in stdout.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and cells[0] not in ("step", "---"):
            rows[cells[0]] = cells[1:]
    return rows


_RUN_SCRIPT = """
import runpy, sys
sys.argv = ["gpu_smoke", *sys.argv[1:]]
try:
    runpy.run_module("benchmarks.gpu_smoke", run_name="__main__", alter_sys=True)
except SystemExit as e:
    print("exit", e.code)
print("torch imported:", "torch" in sys.modules)
"""


@pytest.mark.skipif(GPU_HERE, reason="an NVIDIA GPU is attached here")
def test_without_a_gpu_it_says_so_and_exits_0_without_importing_torch() -> None:
    run = subprocess.run([sys.executable, "-c", _RUN_SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert run.stdout.splitlines() == ["no CUDA device: nothing to check", "exit 0", "torch imported: False"]
    plain = subprocess.run(SMOKE, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert (plain.returncode, plain.stdout.strip()) == (0, "no CUDA device: nothing to check")


def test_help_imports_no_torch() -> None:
    run = subprocess.run([sys.executable, "-c", _RUN_SCRIPT, "--help"], cwd=REPO, capture_output=True, text=True,
                         timeout=60)  # fmt: skip
    assert "--tiny" in run.stdout and "--steps" in run.stdout
    assert run.stdout.splitlines()[-2:] == ["exit 0", "torch imported: False"]


def test_cpu_tiny_run_prints_one_table_of_ok_rows(tmp_path: Path) -> None:
    """The real steps (reconstruct through the neural backend, bf16 train) in subprocesses, on the CPU."""
    run = subprocess.run(
        [*SMOKE, "--device", "cpu", "--tiny", "--steps", "reconstruct,train", "--train-steps",
         "2", "--workdir", str(tmp_path / "work")],
        cwd=REPO, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert run.stdout.count("| step | result | seconds | peak RSS MiB | note |") == 1
    rows = _rows(run.stdout)
    assert list(rows) == ["prepare", "reconstruct", "train"]
    assert all(r[0] == "ok" for r in rows.values()), rows
    for step in ("reconstruct", "train"):
        seconds, mib = float(rows[step][1]), float(rows[step][2].replace(",", ""))
        assert seconds > 0 and mib > 50, rows[step]  # a Python process with torch loaded
    assert rows["reconstruct"][3].endswith("Gaussians") and rows["train"][3].startswith("2 steps bf16")
    # the commands the steps ran, as printed while they run
    assert "python -m macsplat_cli reconstruct" in run.stderr and "--backend neural --weights weights/mast3r.pth" in (
        run.stderr
    )
    assert "python -m macsplat_cli train --data scannetpp" in run.stderr and "--precision bf16 --device cpu" in (
        run.stderr
    )
    assert (tmp_path / "work" / "train" / "last.pt").is_file()  # --workdir is kept


# ------------------------------------------------------------------------------ the runner and the plan
def test_a_failed_step_gives_its_exit_code_and_last_stderr_line(smoke: ModuleType, tmp_path: Path) -> None:
    argv = [sys.executable, "-c", "import sys; print('loading\\r50 %', file=sys.stderr); "
            "print('error: \\x1b[1mno such file\\x1b[0m', file=sys.stderr); sys.exit(2)"]  # fmt: skip
    r = smoke.run_process("x", argv, cwd=tmp_path, env={}, timeout=60, gpu=False, logs=tmp_path / "logs")
    assert (r.status, r.note) == ("failed", "exit 2: error: no such file")
    assert r.seconds > 0 and r.peak_mib > 1 and r.stderr_tail == ["loading", "50 %", "error: no such file"]
    assert (tmp_path / "logs" / "x.err").read_text().startswith("loading")
    assert "| x | failed |" in smoke.table([r], gpu=False) and smoke.exit_code([r]) == 1


def test_a_hung_step_is_killed_at_its_timeout(smoke: ModuleType, tmp_path: Path) -> None:
    argv = [sys.executable, "-c", "import time; time.sleep(60)"]
    r = smoke.run_process("hang", argv, cwd=tmp_path, env={}, timeout=0.5, gpu=False, logs=tmp_path)
    assert (r.status, r.note) == ("failed", "timed out after 0.5 s") and r.seconds < 30


def test_an_exit_0_with_wrong_output_fails_the_step(smoke: ModuleType, tmp_path: Path) -> None:
    def check() -> str:
        raise AssertionError("no Gaussians were written")

    r = smoke.run_process("y", [sys.executable, "-c", "pass"], cwd=tmp_path, env={}, timeout=60, gpu=False,
                          logs=tmp_path, check=check)  # fmt: skip
    assert (r.status, r.note) == ("failed", "exit 0 but no Gaussians were written")
    ok = smoke.run_process("z", [sys.executable, "-c", "pass"], cwd=tmp_path, env={}, timeout=60, gpu=False,
                           logs=tmp_path, check=lambda: "fine")  # fmt: skip
    assert (ok.status, ok.note) == ("ok", "fine") and smoke.exit_code([ok]) == 0


def test_step_selection_adds_what_a_step_needs(smoke: ModuleType) -> None:
    assert smoke.select_steps("render") == ["reconstruct", "render"]
    assert smoke.select_steps("train,onnx") == ["export-onnx", "reconstruct-onnx", "train"]
    assert smoke.select_steps("all") == list(smoke.STEPS)
    with pytest.raises(ValueError, match="unknown step 'nope'"):
        smoke.select_steps("train,nope")
    with pytest.raises(SystemExit) as e:
        smoke.parse_args(["--steps", "nope"])
    assert e.value.code == 2


def test_a_failed_step_skips_the_steps_that_need_it_and_the_run_exits_1(
    smoke: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def checkpoints(folder: Path, *, tiny: bool) -> dict[str, Path]:
        folder.mkdir(parents=True)
        for name in ("mast3r", "splatt3r", "dino", "fusion"):
            (folder / name).write_bytes(b"w")
        return {name: folder / name for name in ("mast3r", "splatt3r", "dino", "fusion")}

    def data(root: Path, size: tuple[int, int]) -> tuple[Path, Path, Path]:
        root.mkdir()
        return root, root / "a.jpg", root / "b.jpg"

    ran: list[list[str]] = []

    def run_process(step: str, argv: list[str], **kwargs: object) -> object:
        ran.append(argv)
        if step == "reconstruct":
            return smoke.Result(step, "failed", 1.0, 10.0, "exit 3: error: the pose is doubtful")
        return smoke.Result(step, "ok", 1.0, 10.0, "fine")

    monkeypatch.setattr(smoke, "write_checkpoints", checkpoints)
    monkeypatch.setattr(smoke, "write_data", data)
    monkeypatch.setattr(smoke, "run_process", run_process)
    code = smoke.main(["--device", "cpu", "--tiny", "--steps", "render,torchrun", "--workdir", str(tmp_path)])
    rows = _rows(capsys.readouterr().out)
    assert code == 1
    assert {k: v[0] for k, v in rows.items()} == {
        "prepare": "ok", "reconstruct": "failed", "torchrun": "ok", "render": "skipped"
    }  # fmt: skip
    assert rows["reconstruct"][3] == "exit 3: error: the pose is doubtful" and rows["render"][3] == "needs reconstruct"
    assert [a[1:5] for a in ran] == [["-m", "macsplat_cli", "reconstruct", "scannetpp/a.jpg"],
                                     ["-m", "torch.distributed.run", "--standalone", "--nproc-per-node"]]  # fmt: skip


_FAKE_SMI = """#!/bin/sh
case "$*" in
  -L) echo "GPU 0: NVIDIA H100 80GB HBM3 (UUID: GPU-0)";;
  *"-i 0 -lms 100") for v in 1000 1500 4000 1200; do echo "$v"; sleep 0.05; done; exec sleep 30;;
  *"-i 0") echo 1000;;
  *) echo "No devices were found" >&2; exit 6;;
esac
"""


@pytest.fixture
def fake_smi(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An ``nvidia-smi`` on PATH: one GPU, index 0, whose used memory streams as 1000, 1500, 4000, 1200 MiB."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "nvidia-smi").write_text(_FAKE_SMI)
    (bin_dir / "nvidia-smi").chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    return bin_dir


def test_gpu_peak_memory_is_the_highest_nvidia_smi_reading_above_the_one_before(
    smoke: ModuleType, fake_smi: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    argv = [sys.executable, "-c", "import time; time.sleep(1.0)"]
    r = smoke.run_process("gpu", argv, cwd=tmp_path, env=dict(os.environ), timeout=60, gpu=True, logs=tmp_path)
    assert (r.status, r.peak_mib) == ("ok", 3000.0)
    text = smoke.table([r], gpu=True)
    assert text.startswith("| step | result | seconds | peak GPU MiB | note |") and _rows(text)["gpu"][2] == "3,000"
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "1,0")  # GPU 1, which this nvidia-smi does not know: no figure
    r = smoke.run_process("gpu", argv, cwd=tmp_path, env=dict(os.environ), timeout=60, gpu=True, logs=tmp_path)
    assert (r.status, r.peak_mib) == ("ok", None) and _rows(smoke.table([r], gpu=True))["gpu"][2] == "-"


@pytest.mark.skipif(torch.cuda.is_available(), reason="this torch has CUDA")
def test_a_gpu_that_torch_cannot_use_is_a_failure(
    smoke: ModuleType, fake_smi: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert smoke.nvidia_gpus() == ["GPU 0: NVIDIA H100 80GB HBM3 (UUID: GPU-0)"] and smoke.gpu_present()
    assert smoke.main([]) == 1
    out = capsys.readouterr().out
    assert out.startswith("error: GPU 0: NVIDIA H100 80GB HBM3 (UUID: GPU-0) is attached but torch ")
    assert "sees no CUDA device" in out
