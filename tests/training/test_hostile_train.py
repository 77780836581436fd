"""Hostile input to ``macsplat train`` (issue 23, second round): every case is one line on stderr and exit 2 (or an
exact resume), nothing partial left, nothing written outside the run folder.

* a damaged ``last.pt`` (truncated, empty, foreign, wrong shapes, missing keys, a string step, bad RNG states, a list
  for a state dict, a step beyond ``--steps`` …) is refused naming the file, and the run folder is left as it was;
* a NaN best PSNR in ``last.pt`` is "no best yet" (``best.pt`` is written again), and the summary names ``best.pt``
  only when this run wrote it;
* a full disk while ``torch.save`` writes (which torch reports as ``RuntimeError``) is an ``OutputPathError``, the
  previous checkpoint intact, no temporary file left — on a real tmpfs when this process may mount one, and always
  through ``RLIMIT_FSIZE``, which makes the same write fail the same way;
* an interruption after the batch was drawn, or a signal during the optimiser step, resumes to the weights of an
  uninterrupted run;
* 2,000 frames build their sampler without listing every pair's targets (the ``O(N³)`` tuples of before);
* a ``--batch`` larger than the training pairs is refused (it used to loop forever looking for a batch).
* a depth ``.npy`` holding strings is refused naming the file (issue 37, D1).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import io
import os
import shutil
import signal
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import macsplat_cli.training.data as training_data
import macsplat_cli.training.pairs as training_pairs
from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.cli import main
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.errors import InputError, OutputPathError
from macsplat_cli.images import save_image
from macsplat_cli.training.config import TrainConfig
from macsplat_cli.training.data import PairSamplingConfig
from macsplat_cli.training.model import ModelSpec, build_training_model, freeze_for_training
from macsplat_cli.training.setup import load_training_data
from macsplat_cli.training.trainer import Trainer

from support.cli import file_size_limit

SIZE = (64, 48)
FAST = ["--model", "tiny", "--init", "random", "--size", f"{SIZE[0]}x{SIZE[1]}", "--workers", "0"]


def _run(args: list[Any]) -> tuple[int, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    return code, err.getvalue()


def _lines(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.strip()]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A generic-layout room: 6 posed views 5° apart at 96×64, with depth."""
    root = tmp_path_factory.mktemp("hostile_train_data")
    room = syn.make_scene("room", 1)
    cams = syn.orbit_cameras(room, [0.0, 5.0, 10.0, 15.0, 20.0, 25.0], width=96, height=64)
    syn.write_dataset(root, room, [dataclasses.replace(c, name=f"f{i}") for i, c in enumerate(cams)], supersample=1)
    return root


@pytest.fixture(scope="module")
def run2(data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run folder after 2 steps (validated at each): run.json, metrics.csv, last.pt, best.pt."""
    out = tmp_path_factory.mktemp("hostile_train_run") / "run"
    code, err = _run(["train", "--data", data, "--out", out, "--steps", "2", "--batch", "1", "--val-every", "1",
                      "--ckpt-every", "1", *FAST, "-q"])  # fmt: skip
    assert code == 0, err
    return out


def _resume_args(data: Path, out: Path, steps: int = 3) -> list[Any]:
    return ["train", "--data", data, "--out", out, "--steps", str(steps), "--batch", "1", "--val-every", "1",
            "--ckpt-every", "1", *FAST, "--resume"]  # fmt: skip


# ------------------------------------------------------------------------------------------------ 1. damaged last.pt
def _edit(change: Callable[[dict[str, Any]], None]) -> Callable[[bytes, dict[str, Any]], Any]:
    def make(raw: bytes, good: dict[str, Any]) -> Any:
        obj = copy.deepcopy(good)
        change(obj)
        return obj

    return make


def _first(obj: dict[str, Any]) -> str:
    return next(iter(obj["state_dict"]))


def _some_param_state(obj: dict[str, Any]) -> dict[str, Any]:
    state = obj["training"]["optimizer"]["state"]
    return state[next(iter(state))]


DAMAGE: dict[str, tuple[Callable[[bytes, dict[str, Any]], Any], str]] = {
    "truncated": (lambda raw, good: raw[: len(raw) // 2], "not a readable checkpoint"),
    "empty": (lambda raw, good: b"", "not a readable checkpoint"),
    "foreign bytes": (lambda raw, good: b"not a checkpoint\n" * 64, "not a readable checkpoint"),
    "wrong weight shape": (
        _edit(lambda o: o["state_dict"].__setitem__(_first(o), torch.zeros(3, 3))),
        "has shape [3, 3]",
    ),
    "missing weight": (_edit(lambda o: o["state_dict"].pop(_first(o))), "state_dict lacks"),
    "state dict is a list": (_edit(lambda o: o.__setitem__("state_dict", [1, 2])), "expected a dict of tensors"),
    "missing optimizer": (_edit(lambda o: o["training"].pop("optimizer")), "training lacks 'optimizer'"),
    "string step": (_edit(lambda o: o["training"].__setitem__("step", "2")), "training.step"),
    "step 1e12": (_edit(lambda o: o["training"].__setitem__("step", 10**12)), "beyond this run's --steps 3"),
    "torch rng of 7 bytes": (
        _edit(lambda o: o["training"]["rng"].__setitem__("torch", torch.zeros(7, dtype=torch.uint8))),
        "training.rng['torch']",
    ),
    "python rng too short": (
        _edit(lambda o: o["training"]["rng"].__setitem__("python", (3, (1, 2), None))),
        "training.rng['python']",
    ),
    "optimizer moment of the wrong shape": (
        _edit(lambda o: _some_param_state(o).__setitem__("exp_avg", torch.zeros(2))),
        "exp_avg",
    ),
    "string learning rate": (
        _edit(lambda o: o["training"]["optimizer"]["param_groups"][0].__setitem__("lr", "fast")),
        "['lr']",
    ),
    "scheduler epoch a string": (
        _edit(lambda o: o["training"]["scheduler"].__setitem__("last_epoch", "x")),
        "last_epoch",
    ),
}


@pytest.mark.parametrize("variant", list(DAMAGE))
def test_a_damaged_last_pt_is_refused_naming_the_file(data: Path, run2: Path, tmp_path: Path, variant: str) -> None:
    out = tmp_path / "run"
    shutil.copytree(run2, out)
    raw = (out / "last.pt").read_bytes()
    make, expected = DAMAGE[variant]
    damaged = make(raw, torch.load(out / "last.pt", weights_only=True))
    if isinstance(damaged, bytes):
        (out / "last.pt").write_bytes(damaged)
    else:
        torch.save(damaged, out / "last.pt")
    before = _snapshot(out)
    code, err = _run([*_resume_args(data, out), "-q"])
    lines = _lines(err)
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("error:"), err
    assert str(out / "last.pt") in lines[0] and expected in lines[0], lines[0]
    assert _snapshot(out) == before  # nothing written, nothing removed, no temporary file


class _Costly:
    """An entry whose repr is counted (a stand-in for a tensor, whose repr takes milliseconds to format)."""

    calls = 0

    def __repr__(self) -> str:
        _Costly.calls += 1
        return "c"


def test_the_checks_messages_do_not_format_a_whole_state_dict() -> None:
    """The checks build each message before they know whether it is needed: a state dict's repr in every message
    took ~2 s per ``--resume`` of the tiny model (more with the full one); a container that long is named by type."""
    from macsplat_cli.training.resume import _show

    bigs = ({str(i): _Costly() for i in range(500)}, [_Costly()] * 500, tuple([_Costly()] * 500))
    assert all(len(repr(big)) > 60 for big in bigs)  # what the full repr would have given: the type's name
    _Costly.calls = 0
    assert [_show(big) for big in bigs] == ["a dict", "a list", "a tuple"]
    assert _Costly.calls == 0
    assert _show([1, 2]) == "[1, 2]" and _show({"lr": "fast"}) == "{'lr': 'fast'}"  # short ones as before


# ------------------------------------------------------------------------------------------------ 2. NaN best PSNR
def _with_best(run2: Path, out: Path, best: float) -> None:
    shutil.copytree(run2, out)
    obj = torch.load(out / "last.pt", weights_only=True)
    obj["training"]["best_psnr"] = best
    torch.save(obj, out / "last.pt")


def test_a_nan_best_psnr_is_no_best_yet_and_best_pt_is_written_again(data: Path, run2: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    _with_best(run2, out, float("nan"))
    before = (out / "best.pt").read_bytes()
    code, err = _run(_resume_args(data, out))
    assert code == 0, err
    assert (out / "best.pt").read_bytes() != before  # NaN is beaten by the first finite PSNR
    assert torch.load(out / "best.pt", weights_only=True)["meta"]["step"] == 3
    best = torch.load(out / "last.pt", weights_only=True)["training"]["best_psnr"]
    assert isinstance(best, float) and np.isfinite(best)
    summary = _lines(err)[-1]
    assert f"wrote {out / 'best.pt'}" in summary, summary


def test_the_summary_names_best_pt_only_when_it_was_written(data: Path, run2: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    _with_best(run2, out, 1e9)  # unbeatable: this run writes no best.pt
    before = (out / "best.pt").read_bytes()
    code, err = _run(_resume_args(data, out))
    assert code == 0, err
    assert (out / "best.pt").read_bytes() == before
    summary = _lines(err)[-1]
    assert str(out / "last.pt") in summary and f"{out / 'best.pt'} unchanged" in summary, summary
    assert f"wrote {out / 'best.pt'}" not in summary, summary


@pytest.mark.parametrize("kind", ["link", "fifo"])
def test_resume_does_not_append_metrics_through_a_planted_link(
    data: Path, run2: Path, tmp_path: Path, kind: str
) -> None:
    """A link (or FIFO) planted at ``metrics.csv`` is refused with exit 2; the link's target is not written."""
    out = tmp_path / "run"
    shutil.copytree(run2, out)
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (out / "metrics.csv").unlink()
    if kind == "link":
        (out / "metrics.csv").symlink_to(victim)
    else:
        os.mkfifo(out / "metrics.csv")
    code, err = _run([*_resume_args(data, out), "-q"])
    assert code == 2 and len(_lines(err)) == 1 and "metrics.csv" in err, err
    assert victim.read_text() == "precious\n"


@pytest.mark.parametrize("name", ["run.json", "best.pt"])
def test_a_link_at_an_output_of_a_new_run_is_refused_before_the_data_loads(
    data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    import macsplat_cli.training.setup as setup

    loads: list[object] = []
    monkeypatch.setattr(setup, "load_training_data", lambda *a, **k: loads.append(a) or 1 / 0)
    out = tmp_path / "run"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (out / name).symlink_to(victim)
    code, err = _run(["train", "--data", data, "--out", out, "--steps", "2", "--force", *FAST, "-q"])
    assert code == 2 and len(_lines(err)) == 1 and name in err and "symbolic link" in err, err
    assert loads == [] and victim.read_text() == "precious\n"


# ------------------------------------------------------------------------------------------------ 3. full disk
def _trainer(data: Path, out: Path, steps: int, *, val: bool = False, batch: int = 1, **changes: Any) -> Trainer:
    sampling = PairSamplingConfig(size=SIZE, targets=1)
    train_ds, val_ds, _ = load_training_data(data, sampling=sampling, val_pairs=1)
    predictor = freeze_for_training(build_training_model(ModelSpec(model="tiny", init="random")))
    config = TrainConfig(out=out, steps=steps, batch=batch, warmup=1, lr=1e-3, val_every=0, ckpt_every=100, **changes)
    return Trainer(predictor, train_ds, val_ds if val else None, config)


def test_a_failed_torch_save_is_an_output_path_error_and_keeps_the_previous_checkpoint(
    data: Path, tmp_path: Path
) -> None:
    """torch's zip writer reports a failed write as RuntimeError ("unexpected pos"), not OSError."""
    trainer = _trainer(data, tmp_path / "r", steps=2)
    trainer.prepare_run_folder(resume=False, force=False)
    trainer.save_checkpoint()
    before = _snapshot(tmp_path / "r")
    with file_size_limit(1 << 20), pytest.raises(OutputPathError) as e:  # last.pt is ~20 MB
        trainer.save_checkpoint()
    assert str(tmp_path / "r" / "last.pt") in str(e.value) and "previous one is intact" in str(e.value)
    assert _snapshot(tmp_path / "r") == before  # no partial file, no temporary file


@pytest.fixture
def small_tmpfs(tmp_path: Path) -> Iterator[Path]:
    """A real 4 MiB tmpfs (needs the right to mount: root outside a locked-down sandbox; skipped otherwise)."""
    where = tmp_path / "tmpfs"
    where.mkdir()
    try:
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(where)], check=True,
                       capture_output=True, timeout=10)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], capture_output=True, timeout=10)


def test_a_full_disk_is_one_line_and_exit_2(data: Path, small_tmpfs: Path) -> None:
    out = small_tmpfs / "run"
    code, err = _run(["train", "--data", data, "--out", out, "--steps", "1", "--batch", "1", "--val-every", "0",
                      *FAST, "-q"])  # fmt: skip
    lines = _lines(err)
    assert code == 2, err
    assert len(lines) == 1 and "could not be written" in lines[0] and "no space left" in lines[0], err
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary file
    assert not (out / "last.pt").exists() or (out / "last.pt").stat().st_size > 0


# ------------------------------------------------------------------------------------------------ 4. exact resume
STEPS = 3


@pytest.fixture(scope="module")
def straight(data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, torch.Tensor]:
    trainer = _trainer(data, tmp_path_factory.mktemp("straight") / "r", steps=STEPS)
    trainer.prepare_run_folder(resume=False, force=False)
    trainer.fit()
    return {k: v.clone() for k, v in trainer.predictor.state_dict().items()}


def _resume_and_compare(data: Path, out: Path, straight: dict[str, torch.Tensor], at_step: int) -> None:
    assert torch.load(out / "last.pt", weights_only=True)["training"]["step"] == at_step
    resumed = _trainer(data, out, steps=STEPS)
    resumed.prepare_run_folder(resume=True, force=False)
    resumed.fit()
    got = resumed.predictor.state_dict()
    assert all(torch.equal(straight[k], got[k]) for k in straight), "the resumed run differs"


def test_an_interruption_after_the_batch_was_drawn_resumes_exactly(
    data: Path, tmp_path: Path, straight: dict[str, torch.Tensor], monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "r"
    trainer = _trainer(data, out, steps=STEPS)
    trainer.prepare_run_folder(resume=False, force=False)
    real, calls = trainer._forward, {"n": 0}

    def interrupted(batch: Any, model: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 2:  # step 2: its batch drawn, the forward pass under way
            raise KeyboardInterrupt
        return real(batch, model)

    monkeypatch.setattr(trainer, "_forward", interrupted)
    with pytest.raises(KeyboardInterrupt):
        trainer.fit()
    _resume_and_compare(data, out, straight, at_step=1)


def test_a_signal_during_the_optimizer_step_resumes_exactly(
    data: Path, tmp_path: Path, straight: dict[str, torch.Tensor], monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGINT while the step is being applied (the weights updated, the scheduler not yet): the step completes first."""
    out = tmp_path / "r"
    trainer = _trainer(data, out, steps=STEPS)
    trainer.prepare_run_folder(resume=False, force=False)
    scheduler_type = type(trainer.scheduler)
    real = scheduler_type.step

    def step_with_signal(self: Any, *args: Any, **kwargs: Any) -> Any:
        if self is trainer.scheduler and trainer.step == 1:  # step 2: the optimiser has updated the weights
            os.kill(os.getpid(), signal.SIGINT)
        return real(self, *args, **kwargs)

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with monkeypatch.context() as patch:  # on the class: an instance attribute would land in state_dict()
            patch.setattr(scheduler_type, "step", step_with_signal)
            with pytest.raises(KeyboardInterrupt):
                trainer.fit()
    finally:
        signal.signal(signal.SIGINT, previous)
    _resume_and_compare(data, out, straight, at_step=2)


# ------------------------------------------------------------------------------------------------ 5. many frames
def _many_frames(root: Path, n: int) -> Path:
    """``n`` frames of 16×16 on a circle around the origin, looking at it, without depth (pairs by angle)."""
    (root / "images").mkdir(parents=True)
    save_image(root / "images" / "f0.png", np.random.default_rng(0).integers(0, 255, (16, 16, 3), dtype=np.uint8))
    png = (root / "images" / "f0.png").read_bytes()
    K = np.array([[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]])
    cams = []
    for i in range(n):
        t = 2 * np.pi * i / n
        c = np.array([3 * np.sin(t), 0.0, -3 * np.cos(t)])
        z = -c / np.linalg.norm(c)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        T = np.eye(4)
        T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
        T[:3, 3] = c
        cams.append(Camera(f"f{i}", 16, 16, K, T))
        if i:
            (root / "images" / f"f{i}.png").write_bytes(png)
    save_cameras(root / "cameras.json", CameraSet(cams))
    return root


def test_two_thousand_frames_build_the_sampler_without_listing_every_pair(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before: a tuple of candidate targets per ordered pair, ~1.2 M pairs × ~600 targets (O(N³)): MemoryError.

    Now the pairs are two int32 arrays and the targets are derived per sample: no TrainPair is built at all."""
    root = _many_frames(tmp_path / "many", 2000)
    built = {"n": 0}
    real = training_pairs.TrainPair

    def counted(*args: Any, **kwargs: Any) -> Any:
        built["n"] += 1
        if built["n"] > 1000:
            raise AssertionError("more than 1000 candidate tuples materialised")
        return real(*args, **kwargs)

    monkeypatch.setattr(training_pairs, "TrainPair", counted)  # where the pairs are built
    monkeypatch.setattr(training_data, "TrainPair", counted)
    train_ds, val_ds, info = load_training_data(root, sampling=PairSamplingConfig(size=(16, 16)), val_pairs=8)
    assert info["train_pairs"] > 10**6 and info["val_pairs"] == 8
    assert built["n"] == 0
    sample = train_ds.sample(len(train_ds) - 1)[0]  # a sample draws its targets among its pair's, by angle
    assert sample["target"].shape == (2, 3, 16, 16)
    pair = train_ds.pair(len(train_ds) - 1)
    assert 0 < len(pair.targets) < 2000 and not set(pair.context) & set(pair.targets)


# ------------------------------------------------------------------------------------------------ 6. --batch too large
def test_a_batch_larger_than_the_training_pairs_is_refused(data: Path, tmp_path: Path) -> None:
    """It used to look for a batch forever (every epoch empty)."""
    with pytest.raises(InputError, match="--batch 64 is more than the [0-9]+ training pair"):
        _trainer(data, tmp_path / "r", steps=1, batch=64)
    assert not (tmp_path / "r").exists()


# -------------------------------------------------------------------------------------------- 7. a depth .npy of text
def test_a_depth_npy_of_strings_is_refused_naming_the_file(data: Path, tmp_path: Path) -> None:
    """Issue 37 (D1): it crashed with "ValueError: could not convert string to float", naming no file."""
    root = tmp_path / "data"
    shutil.copytree(data, root)
    first = sorted(root.rglob("depth/*.png"))[0]
    first.unlink()
    np.save(first.with_suffix(".npy"), np.full((64, 96), "x", dtype="<U1"))  # the photos are 96 x 64
    code, err = _run(["train", "--data", root, "--out", tmp_path / "run", "--steps", "1", "--batch", "1", *FAST, "-q"])
    assert code == 2 and _lines(err) == [f"error: {first.with_suffix('.npy')}: not a numeric depth map (dtype <U1); "
                                         "give integers or floats"], err  # fmt: skip
    assert not (tmp_path / "run").exists()
