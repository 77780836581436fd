"""``macsplat train`` on a CPU: the tiny model on a small training set — loss curve, validation PSNR before and
after, with and without the MAC loss, and throughput / peak memory by batch size.

    python -m benchmarks.train_tiny                       # synthetic room + object scenes
    python -m benchmarks.train_tiny --data ../shared/data/co3d_apple --layout co3d-json
    python -m benchmarks.train_tiny --throughput          # pairs/s and peak RSS for batch 1, 2, 4
    python -m benchmarks.train_tiny --losses paper,released-code,none   # the two recipes' objectives, and no MAC

Validation: held-out pairs of the same scenes (PSNR/SSIM of the rendered targets, full images), and the
disagreement of matched Gaussians on the validation pairs (MAC's position and shape terms with unit weights and
no Huber: mean L1 distance of matched means in scene units, and mean L1 of their sorted log-eigenvalues).

``--losses``: whose objective each run trains with — ``paper`` (``train --recipe paper``'s loss), ``released-code``
(``--recipe released-code``'s: masked photometric terms, 0.2 · MAC averaged, δ 0.05, clamped, (1 + c) weights) or
``none`` (the paper's without MAC); everything else (optimiser, rate, sizes) is this script's, the same for all, so
that only the objective differs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._common import peak_rss_mib
from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.mac import MACConfig, mac_loss
from macsplat_cli.neural.predictor import prediction_from_outputs
from macsplat_cli.training.config import TrainConfig
from macsplat_cli.training.data import PairSamplingConfig, make_loader
from macsplat_cli.training.loss import LossConfig, sample_matches
from macsplat_cli.training.model import ModelSpec, build_training_model, freeze_for_training
from macsplat_cli.training.recipes import get_recipe
from macsplat_cli.training.setup import load_training_data
from macsplat_cli.training.trainer import Trainer


def synthetic_data(root: Path, size: tuple[int, int]) -> Path:
    """Two generic-layout scenes (room, object), 8 views each 4° apart, with depth."""
    for kind in ("room", "object"):
        scene = syn.make_scene(kind, 0)
        angles = [4.0 * i for i in range(8)]
        cams = syn.orbit_cameras(scene, angles, width=size[0], height=size[1])
        named = [dataclasses.replace(c, name=f"{kind}{i}") for i, c in enumerate(cams)]
        syn.write_dataset(root / kind, scene, named, supersample=1)
    return root


@torch.no_grad()
def disagreement(trainer: Trainer) -> dict[str, float]:
    """Mean L1 disagreement of matched Gaussians on the validation pairs: means (scene units) and sorted
    log-eigenvalues of the covariances (MAC's position and shape terms with unit weights, no Huber), on the matches
    of the default grid matcher whatever the run trained with (so that the runs compare on one rule)."""
    pos, shape, n = [], [], 0
    unit = MACConfig(lambda_pos=1.0, lambda_shape=1.0, lambda_app=1.0, delta_pos=1e-12, delta_shape=1e-12)  # L1
    if trainer.val_data is None:
        raise ValueError("disagreement needs the trainer's validation pairs")
    for batch in make_loader(trainer.val_data, batch_size=1, shuffle=False):
        ctx = batch["context"]
        pred = prediction_from_outputs(trainer.predictor(ctx[:, 0], ctx[:, 1]))
        xy0, xy1, _ = sample_matches(pred.desc[0], pred.desc_conf[0], LossConfig())  # one matcher for every run
        if not len(xy0) or pred.gaussians is None:
            continue
        out = mac_loss(pred.gaussians[0], pred.gaussians[1], xy0, xy1, torch.zeros(len(xy0), dtype=torch.long),
                       torch.ones(len(xy0)), config=unit, check_inputs=False)  # fmt: skip
        pos.append(float(out.position))
        shape.append(float(out.shape))
        n += len(xy0)
    return {
        "position": float(np.mean(pos)) if pos else float("nan"),
        "shape": float(np.mean(shape)) if shape else float("nan"),
        "matches": n,
    }


def objective(name: str) -> LossConfig:
    """``--losses`` entry → the loss of that recipe (``none``: the paper's without MAC), with the point-map term
    a from-scratch backbone needs."""
    loss = get_recipe("paper" if name == "none" else name, Path("unused")).loss  # its loss only: no run folder
    return dataclasses.replace(loss, geometry_weight=1.0, mac_weight=0.0 if name == "none" else loss.mac_weight)


def run(data: Path, layout: str, args: argparse.Namespace, loss: LossConfig, out: Path) -> dict:
    sampling = PairSamplingConfig(size=tuple(args.size), targets=args.targets)
    train_ds, val_ds, info = load_training_data(
        data, layout=layout, sampling=sampling, val_pairs=args.val_pairs, seed=0
    )
    model = build_training_model(ModelSpec(model="tiny", init="random", seed=0))
    predictor = freeze_for_training(model, train_backbone=True)  # as `macsplat train --init random`
    cfg = TrainConfig(out=out, steps=args.steps, batch=args.batch, lr=args.lr, warmup=20, val_every=0,
                      ckpt_every=args.steps, loss=loss)  # fmt: skip
    trainer = Trainer(predictor, train_ds, val_ds, cfg)
    trainer.prepare_run_folder(resume=False, force=True)
    before = {**trainer.validate(), **disagreement(trainer)}
    t0 = time.perf_counter()
    result = trainer.fit()
    seconds = time.perf_counter() - t0
    after = {**trainer.validate(), **disagreement(trainer)}
    losses = [r["loss"] for r in result.history]
    k = max(1, len(losses) // 10)
    curve = [(i + k, float(np.mean(losses[i : i + k]))) for i in range(0, len(losses), k)]
    return {"info": info, "before": before, "after": after, "curve": curve, "seconds": seconds,
            "pairs_per_s": args.steps * args.batch / seconds}  # fmt: skip


def throughput(data: Path, layout: str, args: argparse.Namespace) -> None:
    print("| batch | s/step | pairs/s | peak RSS MB |\n|---:|---:|---:|---:|")
    for b in (1, 2, 4):
        cmd = [sys.executable, "-m", "benchmarks.train_tiny", "--data", str(data), "--layout", layout, "--steps", "6",
               "--batch", str(b), "--size", *map(str, args.size), "--_one"]  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
        r = json.loads(out)
        print(f"| {b} | {r['s_per_step']:.2f} | {b / r['s_per_step']:.2f} | {r['rss_mb']:.0f} |")


def one(data: Path, layout: str, args: argparse.Namespace) -> None:
    """Child of --throughput: a few steps, time of the steps after the first, peak RSS of this process."""
    sampling = PairSamplingConfig(size=tuple(args.size), targets=args.targets)
    train_ds, _, _ = load_training_data(data, layout=layout, sampling=sampling, val_pairs=1, seed=0)
    predictor = freeze_for_training(build_training_model(ModelSpec(model="tiny", init="random")), train_backbone=True)
    with tempfile.TemporaryDirectory() as tmp:
        times: list[float] = []
        loss = LossConfig(geometry_weight=1.0)
        cfg = TrainConfig(out=Path(tmp), steps=args.steps, batch=args.batch, val_every=0, ckpt_every=10**6, loss=loss)
        trainer = Trainer(predictor, train_ds, None, cfg, on_step=lambda s, row: times.append(row["seconds"]))
        trainer.prepare_run_folder(resume=False, force=True)
        trainer.fit()
    rss = peak_rss_mib()
    print(json.dumps({"s_per_step": float(np.median(times[1:])), "rss_mb": rss}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None, help="training data (default: synthetic scenes)")
    ap.add_argument("--layout", default="auto")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--lr", type=float, default=3e-4, help="higher than the paper's 1e-5: a tiny model from scratch")
    ap.add_argument("--size", type=int, nargs=2, default=[128, 96], metavar=("W", "H"))
    ap.add_argument("--targets", type=int, default=2)
    ap.add_argument("--val-pairs", type=int, default=8)
    ap.add_argument("--throughput", action="store_true")
    ap.add_argument("--losses", default="paper,none", help="comma-separated: paper, released-code, none")
    ap.add_argument("--_one", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    unknown = set(args.losses.split(",")) - {"paper", "released-code", "none"}
    if unknown:
        ap.error(f"--losses: unknown {', '.join(sorted(unknown))} (use paper, released-code, none)")
    torch.set_num_threads(2)
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or synthetic_data(Path(tmp) / "data", (160, 120))
        if args._one:
            return one(data, args.layout, args)
        if args.throughput:
            return throughput(data, args.layout, args)
        rows = {}
        for name in args.losses.split(","):
            label = {"paper": "+ MAC (paper)", "released-code": "+ MAC (released-code)", "none": "w/o MAC"}[name]
            rows[label] = run(data, args.layout, args, objective(name), Path(tmp) / name)
        first = next(iter(rows))
        info = rows[first]["info"]
        print(f"data: {info['root'] if args.data else 'synthetic room + object'} ({info['train_pairs']} training, "
              f"{info['val_pairs']} validation pairs); tiny model, {args.steps} steps × batch {args.batch}, "
              f"{args.size[0]}x{args.size[1]}, lr {args.lr:g}\n")  # fmt: skip
        print("| run | val PSNR init → trained | val SSIM init → trained | matched position gap | matched shape gap |"
              " time s | pairs/s |\n|---|---:|---:|---:|---:|---:|---:|")  # fmt: skip
        for name, r in rows.items():
            b, a = r["before"], r["after"]
            print(f"| {name} | {b['psnr']:.2f} → {a['psnr']:.2f} | {b['ssim']:.3f} → {a['ssim']:.3f} | "
                  f"{b['position']:.4f} → {a['position']:.4f} | {b['shape']:.3f} → {a['shape']:.3f} | "
                  f"{r['seconds']:.0f} | {r['pairs_per_s']:.2f} |")  # fmt: skip
        print(f"\nloss curve ({first}), mean over windows of steps:")
        print(" ".join(f"{s}:{v:.4f}" for s, v in rows[first]["curve"]))


if __name__ == "__main__":
    main()
