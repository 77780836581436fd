"""``macsplat train``: the loop end to end on a tiny model and a small synthetic data set.

* the CLI writes run.json, metrics.csv, last.pt and best.pt; best.pt is a predictor checkpoint that loads
  with ``weights_only=True`` and that ``reconstruct --backend neural --weights`` takes as it is;
* an interrupted and resumed run ends with the same weights as an uninterrupted one;
* two gloo processes under torchrun give the parameters of one process with the same global batch;
* the loss reaches the Gaussian head and the fusion module; non-finite losses are skipped, then stop the run;
* bad input: one line, exit 2, nothing lost.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.errors import OutputPathError
from macsplat_cli.neural.loading import load_pair_predictor
from macsplat_cli.training.config import TrainConfig
from macsplat_cli.training.data import PairSamplingConfig
from macsplat_cli.training.model import ModelSpec, build_training_model, freeze_for_training
from macsplat_cli.training.setup import load_training_data
from macsplat_cli.training.trainer import Trainer, TrainingError

from support.cli import run_cli

SIZE = (64, 48)
FAST = ["--model", "tiny", "--init", "random", "--size", f"{SIZE[0]}x{SIZE[1]}", "--workers", "0", "-q"]


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A generic-layout room: 6 posed views 5° apart at 96×64, with depth."""
    root = tmp_path_factory.mktemp("train_data")
    room = syn.make_scene("room", 1)
    cams = syn.orbit_cameras(room, [0.0, 5.0, 10.0, 15.0, 20.0, 25.0], width=96, height=64)  # trained at 64×48
    syn.write_dataset(root, room, [dataclasses.replace(c, name=f"f{i}") for i, c in enumerate(cams)], supersample=1)
    return root


def _trainer(data: Path, out: Path, steps: int, **changes: object) -> Trainer:
    sampling = PairSamplingConfig(size=SIZE, targets=1)
    train_ds, val_ds, _ = load_training_data(data, sampling=sampling, val_pairs=1)
    predictor = freeze_for_training(build_training_model(ModelSpec(model="tiny", init="random")))
    config = TrainConfig(out=out, steps=steps, batch=2, warmup=1, lr=1e-3, val_every=0, ckpt_every=2, **changes)
    trainer = Trainer(predictor, train_ds, val_ds, config)
    return trainer


def test_cli_trains_and_reconstruct_takes_the_checkpoint(data: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", data, "--out", out, "--steps", "3", "--batch", "2", "--val-every", "2",
                         "--ckpt-every", "2", *FAST])  # fmt: skip
    assert code == 0, err
    assert {p.name for p in out.iterdir()} == {"run.json", "metrics.csv", "last.pt", "best.pt"}
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    train_rows = [r for r in rows if r["kind"] == "train"]
    assert [int(r["step"]) for r in train_rows] == [1, 2, 3]
    assert all(float(r["loss"]) > 0 for r in train_rows) and [r["step"] for r in rows if r["kind"] == "val"] == [
        "2",
        "3",
    ]
    run = json.loads((out / "run.json").read_text())
    assert run["model"]["model"] == "tiny" and run["data"]["train_pairs"] > 0
    best = torch.load(out / "best.pt", weights_only=True)  # a plain, safe checkpoint with its configuration
    assert best["format"] == "macsplat-predictor" and best["config"]["gaussian_head"] is not None
    predictor = load_pair_predictor(weights=out / "best.pt")
    for k, v in predictor.state_dict().items():
        assert torch.equal(v, best["state_dict"][k])
    images = sorted((data / "images").iterdir())
    code, _, err = run_cli(["reconstruct", images[0], images[2], "-o", tmp_path / "s.ply", "--backend", "neural",
                         "--weights", out / "best.pt", "-q"])  # fmt: skip
    assert code in (0, 3), err  # loaded and run; an untrained network's geometry may be refused (exit 3), not crash


def test_interrupted_and_resumed_run_ends_with_the_same_weights(data: Path, tmp_path: Path) -> None:
    straight = _trainer(data, tmp_path / "a", steps=4)
    straight.prepare_run_folder(resume=False, force=False)
    straight.fit()
    interrupted = _trainer(data, tmp_path / "b", steps=4)
    interrupted.prepare_run_folder(resume=False, force=False)
    interrupted.stop_after = 2
    with pytest.raises(KeyboardInterrupt):
        interrupted.fit()
    assert torch.load(tmp_path / "b" / "last.pt", weights_only=True)["training"]["step"] == 2
    resumed = _trainer(data, tmp_path / "b", steps=4)
    resumed.prepare_run_folder(resume=True, force=False)
    assert resumed.step == 2
    resumed.fit()
    a, b = straight.predictor.state_dict(), resumed.predictor.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    init = build_training_model(ModelSpec()).state_dict()  # built once (inside the loop: a model per key, 25 CPU-s)
    assert not all(torch.equal(a[k], init[k]) for k in a)  # it did train


def test_loss_reaches_the_head_and_the_fusion(data: Path, tmp_path: Path) -> None:
    trainer = _trainer(data, tmp_path / "g", steps=1)
    batch = next(iter(trainer._batches()))
    terms = trainer._forward(batch, trainer.model)
    terms.loss.backward()
    p = trainer.predictor
    assert terms.matches > 0 and terms.mac > 0
    assert any(x.grad is not None and x.grad.abs().sum() > 0 for x in p.gaussian_head.parameters())
    assert any(x.grad is not None and x.grad.abs().sum() > 0 for x in p.fusion.parameters())  # through the MAC weights
    assert all(x.grad is None for x in p.backbone.parameters()) and all(x.grad is None for x in p.dino.parameters())


def test_non_finite_losses_are_skipped_then_stop_the_run(
    data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    trainer = _trainer(data, tmp_path / "n", steps=6, max_bad_steps=3)
    trainer.prepare_run_folder(resume=False, force=False)
    real = trainer._forward
    calls = {"n": 0}

    def flaky(batch, model):  # noqa: ANN001, ANN202
        calls["n"] += 1
        terms = real(batch, model)
        if calls["n"] >= 3:  # steps 1-2 fine, then NaN forever
            terms.loss = terms.loss * float("nan")
        return terms

    monkeypatch.setattr(trainer, "_forward", flaky)
    with pytest.raises(TrainingError, match="non-finite for 3 steps in a row"):
        trainer.fit()
    assert trainer.step == 2 and trainer.skipped == 3
    last = torch.load(tmp_path / "n" / "last.pt", weights_only=True)
    assert last["training"]["step"] == 2  # the last good checkpoint, intact
    assert all(torch.isfinite(v).all() for v in last["state_dict"].values() if v.is_floating_point())


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--data", "MISSING"], "MISSING"),
        (["--init", "weights"], "--init weights needs --weights"),
        (["--size", "100x48"], "multiples of 16"),
        (["--coverage", "0.8,0.2"], "--coverage"),
        (["--precision", "fp16"], "fp16 needs --device cuda"),
        (["--resume"], "no last.pt"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(data: Path, tmp_path: Path, extra: list[str], message: str) -> None:
    extra = [str(tmp_path / a) if a == "MISSING" else a for a in extra]
    args = ["train", "--data", data, "--out", tmp_path / "r", "--steps", "1", *FAST, *extra]  # later options win
    code, _, err = run_cli(args)
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], err
    assert not (tmp_path / "r" / "last.pt").exists()


def test_out_holding_another_run_is_refused_unless_resumed_or_forced(data: Path, tmp_path: Path) -> None:
    out = tmp_path / "r"
    args = ["train", "--data", data, "--out", out, "--steps", "1", "--val-every", "0", *FAST]
    assert run_cli(args)[0] == 0
    before = (out / "last.pt").read_bytes()
    code, _, err = run_cli(args)
    assert code == 2 and "holds another run" in err and (out / "last.pt").read_bytes() == before
    assert run_cli([*args, "--force"])[0] == 0
    code, _, err = run_cli([*args[:6], "2", *args[7:], "--resume"])  # continue to step 2
    assert code == 0, err
    assert torch.load(out / "last.pt", weights_only=True)["training"]["step"] == 2


def test_two_gloo_processes_match_one_process_with_the_same_global_batch(data: Path, tmp_path: Path) -> None:
    """torchrun, 2 CPU processes with batch 1 each = 1 process with batch 2, after one optimiser step."""
    common = ["train", "--data", str(data), "--steps", "1", "--val-every", "0", "--lr", "1e-3", "--warmup", "0", *FAST]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    one = subprocess.run([sys.executable, "-m", "macsplat_cli", *common, "--out", str(tmp_path / "one"),
                          "--batch", "2"], env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert one.returncode == 0, one.stderr
    two = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2", "--master-port",
                          "29517", "-m", "macsplat_cli", *common, "--out", str(tmp_path / "two"), "--batch", "1"],
                         env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert two.returncode == 0, two.stderr[-2000:]
    a = torch.load(tmp_path / "one" / "last.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "two" / "last.pt", weights_only=True)["state_dict"]
    init = build_training_model(ModelSpec(model="tiny", init="random")).state_dict()
    changed = [k for k in a if not torch.equal(a[k], init[k])]
    assert changed, "the step changed nothing"
    # One Adam(W) step moves each weight by lr·g/(|g| + ε) (+ the same weight decay in both runs): at most lr, and
    # for |g| ≫ ε nearly exactly lr whatever the rounding of g. Where a gradient is a sum that cancels to within
    # its rounding (|g| ≲ γₙ·Σ|terms|), the two summation orders (one batch of 2 vs the all-reduce of two batches
    # of 1) may give it any sign and size below that rounding, and Adam's normalisation turns that into any step in
    # [−lr, lr]: no per-element bound exists there. So: every weight within one step plus rounding, and such
    # elements rare (measured: 0 or 1 of 49,152 by CPU kernel set). Mixing up the samples would move most weights.
    lr, diffs = 1e-3, torch.cat([(a[k].double() - b[k].double()).abs().flatten() for k in a])
    scale = max(float(a[k].abs().max()) for k in a)
    assert float(diffs.max()) <= 2 * lr + 4 * torch.finfo(torch.float32).eps * scale
    assert int((diffs > 0.05 * lr).sum()) <= 1e-3 * diffs.numel(), int((diffs > 0.05 * lr).sum())


def test_trains_on_a_scannetpp_tree_with_its_validation_split(tmp_path: Path) -> None:
    """A fisheye-only ScanNet++ tree (undistorted on the fly): nvs_sem_train pairs train, nvs_sem_val validate."""
    root = syn.write_scannetpp(tmp_path / "scannetpp", layout="fisheye", frames=6, size=(96, 64))
    code, _, err = run_cli(["train", "--data", root, "--out", tmp_path / "r", "--steps", "1", *FAST])
    assert code == 0, err
    run = json.loads((tmp_path / "r" / "run.json").read_text())
    assert run["data"]["layout"] == "scannetpp" and run["data"]["validation"] == "split nvs_sem_val"
    assert run["data"]["train_pairs"] > 0 and run["data"]["val_pairs"] > 0


def test_a_failed_checkpoint_write_keeps_the_previous_one(
    data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Disk full while checkpointing: one line, exit 2, the last checkpoint intact."""
    trainer = _trainer(data, tmp_path / "d", steps=4)
    trainer.prepare_run_folder(resume=False, force=False)
    trainer.stop_after = 2
    with pytest.raises(KeyboardInterrupt):
        trainer.fit()
    before = (tmp_path / "d" / "last.pt").read_bytes()
    real_save = torch.save

    def full_disk(obj, f, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        real_save(obj, f, *args, **kwargs)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    resumed = _trainer(data, tmp_path / "d", steps=4)
    resumed.prepare_run_folder(resume=True, force=False)
    with pytest.raises(OutputPathError, match="No space left on device.*previous one is intact"):
        resumed.fit()
    assert (tmp_path / "d" / "last.pt").read_bytes() == before
    assert not [p for p in (tmp_path / "d").iterdir() if p.name.startswith(".")]  # no temporary file left


def test_point_regression_is_zero_for_the_true_point_maps() -> None:
    """The from-scratch geometry term: 0 for the ground-truth point maps of both views in view 0's frame."""
    from macsplat_cli.training.loss import point_regression

    cams = syn.orbit_pair("room", 15.0, width=32, height=24, fov_deg=60.0)
    room = syn.make_scene("room", 0)
    depth = torch.stack([torch.from_numpy(syn.render(room, c).depth).float() for c in cams])
    K = torch.stack([torch.tensor(c.K) for c in cams])
    c2w = torch.stack([torch.tensor(c.cam_to_world) for c in cams])
    ys, xs = np.mgrid[0:24, 0:32]
    pix = np.stack([xs + 0.5, ys + 0.5, np.ones((24, 32))], -1)
    pts = []
    for k, c in enumerate(cams):
        cam = pix @ np.linalg.inv(c.K).T * depth[k].numpy()[..., None]
        T = np.linalg.inv(cams[0].cam_to_world) @ c.cam_to_world
        pts.append(cam @ T[:3, :3].T + T[:3, 3])
    pts3d = torch.from_numpy(np.stack(pts)).float()
    assert float(point_regression(pts3d, depth, K, c2w)) < 1e-5
    assert float(point_regression(pts3d * 1.1, depth, K, c2w)) > 0.05
    assert point_regression(pts3d, torch.zeros_like(depth), K, c2w) is None


def test_init_random_trains_the_backbone_with_the_geometry_term(data: Path, tmp_path: Path) -> None:
    args = ["train", "--data", data, "--out", tmp_path / "r", "--steps", "1", "--val-every", "0", *FAST]
    code, _, err = run_cli(args)
    assert code == 0, err
    run = json.loads((tmp_path / "r" / "run.json").read_text())
    assert run["model"]["train_backbone"] is True and run["config"]["loss"]["geometry_weight"] == 1.0
