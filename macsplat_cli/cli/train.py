"""``macsplat train``: train the MAC-Splat predictor (Gaussian head + Residual Semantic Fusion) on posed images."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from ._app import app
from ._common import QuietOpt, VerboseOpt, command_context, err_console, escape
from ._options import DeviceOpt, DinoOpt, GaussianHeadOpt, WeightsOpt, choice
from .eval import LAYOUTS, LayoutOpt

if TYPE_CHECKING:  # the command imports torch only once it runs
    from rich.progress import Progress, TaskID

    from ..training.config import TrainConfig

logger = logging.getLogger("macsplat_cli.cli.train")


def _size(text: str) -> tuple[int, int]:
    from ..errors import InputError

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size {text!r}: give WIDTHxHEIGHT, e.g. 256x192") from None
    if w < 32 or h < 32 or w % 16 or h % 16:
        raise InputError(f"--size {text!r}: both sides must be multiples of 16, at least 32")
    return w, h


def _range(text: str, option: str) -> tuple[float, float]:
    import math

    from ..errors import InputError

    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"{option} {text!r}: give LOW,HIGH") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
        raise InputError(f"{option} {text!r}: give 0 ≤ LOW ≤ HIGH")
    return lo, hi


@app.command("train")
def train_command(
    ctx: typer.Context,
    data: Annotated[
        Path, typer.Option("--data", metavar="DIR", help="Posed images: ScanNet++ root, generic folder, CO3D, ICL.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Run folder (run.json, metrics.csv, last.pt, best.pt).")],
    layout: LayoutOpt = "auto",
    scenes: Annotated[str | None, typer.Option("--scenes", help="Only these scenes (comma-separated).")] = None,
    split: Annotated[
        str, typer.Option("--split", help="ScanNet++: training split list (validation: nvs_sem_val when present).")
    ] = "nvs_sem_train",
    recipe: Annotated[
        str,
        typer.Option(
            "--recipe",
            metavar="paper|released-code",
            help="The settings to reproduce: the paper's, or what the authors' released code computes (less its "
            "bugs). The options below override single values.",
        ),
    ] = "paper",  # fmt: skip
    steps: Annotated[
        int | None, typer.Option("--steps", min=1, help="Optimiser steps [paper: 1000; released-code: 200/scene].")
    ] = None,
    batch: Annotated[int | None, typer.Option("--batch", min=1, help="Pairs per process and step [2; 1].")] = None,
    accumulate: Annotated[int, typer.Option("--accumulate", min=1, help="Gradient accumulation steps.")] = 1,
    lr: Annotated[float | None, typer.Option("--lr", help="Learning rate [AdamW 1e-5; Adam 1e-6].")] = None,
    weight_decay: Annotated[float | None, typer.Option("--weight-decay", help="Weight decay [0.05; 0].")] = None,
    warmup: Annotated[
        int | None,
        typer.Option("--warmup", min=0, help="Warm-up steps, then the schedule [50, cosine; 0, ×0.1 at half]."),
    ] = None,
    grad_clip: Annotated[float | None, typer.Option("--grad-clip", help="Gradient-norm clip, 0: off [0.5].")] = None,
    precision: Annotated[str, typer.Option("--precision", metavar="fp32|bf16|fp16", help="AMP.")] = "fp32",
    size: Annotated[
        str | None, typer.Option("--size", metavar="WxH", help="Training image size [256x192; 512x512].")
    ] = None,
    targets: Annotated[int | None, typer.Option("--targets", min=1, help="Target views per pair [2; 3].")] = None,
    coverage: Annotated[
        str, typer.Option("--coverage", metavar="LOW,HIGH", help="Covisibility range of the context pairs.")
    ] = "0.3,1.0",
    val_every: Annotated[int, typer.Option("--val-every", min=0, help="Validate every K steps (0: at the end).")] = 100,
    val_pairs: Annotated[int, typer.Option("--val-pairs", min=1, help="Held-out pairs (without a val split).")] = 8,
    ckpt_every: Annotated[int, typer.Option("--ckpt-every", min=1, help="Write last.pt every K steps.")] = 100,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the data order and the initialisation.")] = 0,
    workers: Annotated[int, typer.Option("--workers", min=0, help="Data-loader worker processes.")] = 2,
    model: Annotated[str, typer.Option("--model", metavar="tiny|full", help="Architecture of --init random.")] = "full",
    init: Annotated[
        str, typer.Option("--init", metavar="weights|random", help="Start from the checkpoints, or at random.")
    ] = "weights",
    weights: WeightsOpt = None,
    gaussian_head: GaussianHeadOpt = None,
    dino: DinoOpt = None,
    no_dino: Annotated[bool, typer.Option("--no-dino", help="No DINOv3 fusion (ablation).")] = False,
    no_mac: Annotated[bool, typer.Option("--no-mac", help="Photometric loss only (ablation).")] = False,
    mac_weight: Annotated[float | None, typer.Option("--mac-weight", help="λ of the MAC loss [0.25; 0.2].")] = None,
    mac_weighting: Annotated[
        str | None,
        typer.Option(
            "--mac-weighting",
            metavar="c0c1p|c0c1",
            help="Match weights: c0·c1·p (the fusion learns through p) or the paper's c0·c1 [c0c1p; c0c1].",
        ),
    ] = None,
    lpips_weights: Annotated[
        Path | None, typer.Option("--lpips-weights", metavar="PATH", help="LPIPS VGG weights (else D-SSIM).")
    ] = None,
    train_backbone: Annotated[bool, typer.Option("--train-backbone", help="Unfreeze the MASt3R backbone.")] = False,
    device: DeviceOpt = "cpu",
    resume: Annotated[bool, typer.Option("--resume", help="Continue the run in --out from its last.pt.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Start over in an --out that holds another run.")] = False,
    verbose: VerboseOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Train the Gaussian head and the Residual Semantic Fusion with the photometric + MAC loss.

    --recipe picks every setting at once: [bold]paper[/] (default: the paper's values, macsplat's where it is
    silent) or [bold]released-code[/] (what the authors' released code computes, less its bugs, which run.json
    names); the options in brackets show both recipes' values and override them one by one.

    The MASt3R backbone and DINOv3 stay frozen (--train-backbone unfreezes the backbone; with --init random
    the backbone trains too, with a point-map regression on ground-truth depth). On one CPU or
    GPU as it is; on many through torchrun (DDP; only rank 0 writes). The run folder gets run.json,
    metrics.csv, last.pt (resumable: --resume) and best.pt (best validation PSNR), which
    [bold]reconstruct --backend neural --weights[/] takes as it is.

    [bold]Examples[/]

      macsplat train --data scannetpp/ --out runs/x --weights mast3r.pth --gaussian-head splatt3r.ckpt --dino dinov3.pth

      macsplat train --data my_scenes/ --out runs/tiny --model tiny --init random --steps 200

      macsplat train --data scannetpp/ --out runs/o --recipe released-code --gaussian-head splatt3r.ckpt ...

      torchrun --nproc-per-node 4 -m macsplat_cli train --data scannetpp/ --out runs/x --device cuda ...
    """
    with command_context(ctx, verbose, quiet) as state:
        if int(os.environ.get("RANK", "0")) > 0:  # under torchrun only rank 0 reports
            logging.getLogger("macsplat_cli").setLevel(logging.WARNING)
        from ..training import TrainSpec, train
        from ..training.model import INITS, MODELS

        chosen = {
            "steps": steps, "batch": batch, "lr": lr, "weight_decay": weight_decay, "warmup": warmup,
            "grad_clip": grad_clip, "size": _size(size) if size is not None else None, "targets": targets,
            "mac_weight": 0.0 if no_mac else mac_weight,
            "mac_weighting": mac_weighting.strip().lower() if mac_weighting is not None else None,
        }  # fmt: skip
        config, overridden = _config(
            recipe.strip().lower(), out, chosen, {"mac_weight": "--no-mac"} if no_mac else {}, accumulate=accumulate,
            precision=precision.strip().lower(), val_every=val_every, ckpt_every=ckpt_every, seed=seed,
            workers=workers, device=device.strip().lower(),
        )  # fmt: skip
        spec = TrainSpec(
            data=data, config=config, overridden=overridden, layout=choice("--layout", layout, LAYOUTS, sep=", "),
            split=split,
            scenes=[s.strip() for s in scenes.split(",") if s.strip()] if scenes else None,
            coverage=_range(coverage, "--coverage"), val_pairs=val_pairs, model=choice("--model", model, MODELS),
            init=choice("--init", init, INITS), weights=weights, gaussian_head=gaussian_head, dino=dino,
            no_dino=no_dino, lpips_weights=lpips_weights, train_backbone=train_backbone, resume=resume, force=force,
        )  # fmt: skip
        outcome = train(spec, _TrainProgress(state.quiet))
        if not state.quiet and outcome.is_main:
            err_console.print(escape(_summary(outcome.result, out)), highlight=False, soft_wrap=True)


def _config(
    name: str, out: Path, chosen: dict[str, Any], labels: dict[str, str], **loop: Any
) -> tuple[TrainConfig, list[str]]:
    """The named recipe's config for ``out`` with the options given on the command line in place of its values
    and the loop's options (``loop``), and the names of the options that replaced the recipe's values (``labels``:
    a value's option when it is not ``--`` + its name)."""
    import dataclasses

    from ..training.recipes import get_recipe

    config = get_recipe(name, out)
    given = {k: v for k, v in chosen.items() if v is not None}
    loss = {k: given.pop(k) for k in ("mac_weight", "mac_weighting") if k in given}
    if "steps" in given:
        given["steps_per_scene"] = None
    config = dataclasses.replace(config, **given, **loop, loss=dataclasses.replace(config.loss, **loss))
    overridden = [labels.get(k, "--" + k.replace("_", "-")) for k, v in chosen.items() if v is not None]
    return config, overridden


def _summary(result: Any, out: Path) -> str:
    """The closing line: steps, the best PSNR, and the files this run wrote — best.pt only when it was written."""
    best = f"best validation PSNR {result.best_psnr:.2f} dB, " if result.best_psnr is not None else ""
    order = {name: i for i, name in enumerate(("best.pt", "last.pt", "metrics.csv"))}
    written = sorted(result.written, key=lambda p: order.get(Path(p).name, len(order)))
    text = f"{result.steps} step(s) in {result.seconds:.1f} s ({result.skipped_steps} skipped); {best}"
    text += f"wrote {', '.join(str(p) for p in written)}" if written else "wrote nothing"
    if not any(Path(p).name == "best.pt" for p in written):
        best_pt = out / "best.pt"
        text += f"; {best_pt} unchanged" if best_pt.is_file() else "; no best.pt (no finite validation PSNR yet)"
    return text


class _TrainProgress:
    """The run's :class:`~macsplat_cli.training.runner.TrainProgress` on stderr: a Rich bar over the optimiser steps
    with the latest loss terms, below the run's one-line description; nothing when quiet."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.progress: Progress | None = None
        self.task: TaskID | None = None

    def start(self, total: int, step: int, about: str) -> None:
        if self.quiet:
            return
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.progress = Progress(
            TextColumn("train"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
            TextColumn("{task.fields[last]}", markup=False), console=err_console, transient=False,
        )  # fmt: skip
        self.task = self.progress.add_task("", total=total, completed=step, last="")
        self.progress.start()
        err_console.print(escape(about), highlight=False)

    def step(self, step: int, row: dict[str, float]) -> None:
        if self.progress is not None and self.task is not None:
            mac = f", mac {row['mac']:.4f}" if row.get("mac") else ""
            self.progress.update(self.task, completed=step, last=f"loss {row['loss']:.4f}{mac}")

    def stop(self) -> None:
        if self.progress is not None:
            self.progress.stop()
