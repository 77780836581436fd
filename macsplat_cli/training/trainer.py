"""The training loop of ``macsplat train``: AdamW with warm-up + cosine, clipping, accumulation, AMP, validation,
atomic checkpoints, exact resume, and data-parallel training over processes started by ``torchrun``.

Files in the run folder (only rank 0 writes):

* ``run.json``: the run's configuration (a folder holding another run is refused unless resumed or forced);
* ``metrics.csv``: one row per optimiser step (loss terms, learning rate, seconds) and the validation rows;
* ``last.pt``: a macsplat predictor checkpoint (:mod:`macsplat_cli.neural.predictor_io`) that also carries the
  optimiser, scheduler, step, data position and RNG states — written every ``ckpt_every`` steps, at the end and
  on Ctrl-C or SIGTERM, always atomically (the previous one stays intact if writing fails, a full disk included:
  :class:`~macsplat_cli.errors.OutputPathError`);
* ``best.pt``: the predictor with the best (finite) validation PSNR (what ``reconstruct --backend neural --weights``
  takes).

**Exact resume.** ``last.pt`` always holds a state at a step boundary: the data position and RNG states are those
remembered after the last completed step (or skipped step), and the few statements that complete a step (optimiser,
scheduler, counters, metrics row) run with SIGINT/SIGTERM held back. An interruption anywhere — while a batch is
being drawn, during the forward or backward pass, while validating — therefore resumes to the same weights as an
uninterrupted run: the batch in flight is drawn again, and a validation that was due is run first.

**Resuming checks the file** before anything is restored: its structure, the keys, shapes and dtypes of the weights
and of the optimiser state against this run's model, finite values, the scheduler and RNG states, and a step within
``0 … steps``; anything else is refused with :class:`~macsplat_cli.errors.OutputPathError` naming the file and the
first problem.

A non-finite loss skips its step (counted in the metrics); ``max_bad_steps`` of them in a row stop the run with
:class:`TrainingError`, the last good checkpoint intact.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import logging
import math
import os
import shutil
import signal
import stat
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import torch
import torch.distributed as dist

from .._atomic import atomic_path, check_writable
from .._json import to_jsonable
from ..errors import InputError, MacsplatError, OutputPathError
from ..metrics import psnr, ssim
from ..neural.predictor import PairPredictor, prediction_from_outputs
from ..neural.predictor_io import PREDICTOR_FORMAT, predictor_config
from .loss import LossConfig, render_targets, training_loss
from .model import trainable_parameters
from .resume import check_training_checkpoint, read_training_checkpoint, rng_state, set_rng_state

__all__ = ["TrainConfig", "TrainResult", "TrainingError", "Trainer", "distributed_context"]

logger = logging.getLogger(__name__)


class TrainingError(MacsplatError):
    """Training cannot go on (the loss stayed non-finite); the last good checkpoint is kept."""

    exit_code = 3


@dataclass
class TrainConfig:
    """Settings of the loop (the model and the data are given separately).

    Args:
        out: the run folder.
        steps: optimiser steps in all.
        batch: pairs per process and micro-step.
        accumulate: micro-steps per optimiser step.
        lr: AdamW learning rate (the paper: 1e-5).
        weight_decay: AdamW weight decay.
        warmup: linear warm-up steps, then a cosine decay to 0 at ``steps``.
        grad_clip: gradient-norm clip (0: off).
        precision: ``"fp32"``, ``"bf16"`` or ``"fp16"`` (autocast; fp16 with a gradient scaler, CUDA only).
        val_every: validate (and keep ``best.pt``) every this many steps (0: only at the end).
        ckpt_every: write ``last.pt`` every this many steps.
        seed: seed of the data order and of everything random in the loop.
        workers: data-loader worker processes.
        max_bad_steps: non-finite losses in a row that stop the run.
        device: ``"cpu"`` or ``"cuda"``.
        loss: the objective's weights.
    """

    out: Path
    steps: int = 1000
    batch: int = 2
    accumulate: int = 1
    lr: float = 1e-5
    weight_decay: float = 0.05
    warmup: int = 50
    grad_clip: float = 0.5
    precision: str = "fp32"
    val_every: int = 100
    ckpt_every: int = 100
    seed: int = 0
    workers: int = 0
    max_bad_steps: int = 10
    device: str = "cpu"
    loss: LossConfig = field(default_factory=LossConfig)

    def validate(self) -> None:
        for name in ("steps", "batch", "accumulate", "max_bad_steps"):
            if getattr(self, name) < 1:
                raise InputError(f"--{name.replace('_', '-')} must be at least 1, got {getattr(self, name)}")
        for name in ("val_every", "ckpt_every", "warmup", "workers"):
            if getattr(self, name) < 0:
                raise InputError(f"--{name.replace('_', '-')} must be ≥ 0, got {getattr(self, name)}")
        for name in ("lr", "weight_decay", "grad_clip"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"--{name.replace('_', '-')} {v}: give a finite number ≥ 0")
        if self.precision not in ("fp32", "bf16", "fp16"):
            raise InputError(f"--precision {self.precision!r}: use fp32, bf16 or fp16")
        if self.precision == "fp16" and self.device != "cuda":
            raise InputError("--precision fp16 needs --device cuda (use bf16 on the CPU)")


@dataclass
class TrainResult:
    """What :meth:`Trainer.fit` did.

    Attributes:
        steps: the step reached.
        best_psnr: the best finite validation PSNR so far (None: none yet).
        skipped_steps: non-finite steps skipped so far.
        seconds: wall time of this call.
        history: the training rows of this call.
        written: the files this call wrote (each once, in the order first written).
    """

    steps: int
    best_psnr: float | None
    skipped_steps: int
    seconds: float
    history: list[dict[str, float]]
    written: list[Path] = field(default_factory=list)


# ============================================================================================= distributed
@dataclass
class DistributedContext:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def distributed_context(device: str) -> DistributedContext:
    """The process group of a ``torchrun`` launch (``RANK``/``WORLD_SIZE`` set), initialised; a single process
    otherwise. NCCL on CUDA, gloo on the CPU."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistributedContext()
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device == "cuda" else "gloo")
    if device == "cuda":
        torch.cuda.set_device(local)
    return DistributedContext(rank, world, local)


# ============================================================================================= the loop
def _lr_factor(step: int, warmup: int, total: int) -> float:
    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    progress = (step - warmup) / max(1, total - warmup)
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


class _WriteFailed(Exception):
    """torch.save failed inside :func:`atomic_path` (carries the error out, past the removal of the temporary file)."""


_INTERRUPTS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM") if hasattr(signal, name))


@contextlib.contextmanager
def _interrupts_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back while inside, and deliver them on the way out (main thread only).

    The handlers are swapped for one that only notes the signal (Python runs signal handlers in the main thread
    whatever thread the OS picked, so this holds them for the whole process); the previous handlers are put back
    and each noted signal is raised again, so Ctrl-C and SIGTERM act right after the block as they would have in it.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous: dict[int, Any] = {}

    def note(signum: int, frame: Any) -> None:
        held.append(signum)

    try:
        for s in _INTERRUPTS:
            if signal.getsignal(s) is not None:  # None: a handler installed outside Python, left alone
                previous[s] = signal.signal(s, note)
    except (ValueError, OSError):  # no signals here (an embedded interpreter)
        for s, h in previous.items():
            signal.signal(s, h)
        previous.clear()
    try:
        yield
    finally:
        for s, h in previous.items():  # a signal pending here is noted first (signal.signal checks before swapping)
            signal.signal(s, h)
        for s in dict.fromkeys(held):
            signal.raise_signal(s)


class Trainer:
    """Trains a :class:`PairPredictor` (its trainable parameters) on a :class:`~.data.PairDataset`.

    Args:
        predictor: the model, frozen where it should be (:func:`~.model.freeze_for_training`).
        train_data: the training pairs.
        val_data: held-out pairs for validation (None: no validation, ``best.pt`` is the last model).
        config: the loop's settings.
        lpips: LPIPS model for the perceptual term (None: D-SSIM).
        run_info: what ``run.json`` records besides the loop's settings (data, model).
        on_step: called on rank 0 after each optimiser step with the step and its metrics.

    Raises:
        InputError: a bad setting, nothing to train, or fewer training pairs per process than ``config.batch``
            (an epoch would hold no batch).
    """

    def __init__(
        self,
        predictor: PairPredictor,
        train_data: Any,
        val_data: Any | None,
        config: TrainConfig,
        *,
        lpips: torch.nn.Module | None = None,
        run_info: dict[str, Any] | None = None,
        on_step: Callable[[int, dict[str, float]], None] | None = None,
    ) -> None:
        config.validate()
        self.config = config
        self.ctx = distributed_context(config.device)
        per_process = len(train_data) // self.ctx.world_size
        if per_process < config.batch:
            raise InputError(
                f"--batch {config.batch} is more than the {per_process} training pair(s) per process: an epoch would "
                "hold no batch; lower --batch"
            )
        self.device = torch.device(config.device, self.ctx.local_rank if config.device == "cuda" else None)
        self.predictor = predictor.to(self.device)
        self.train_data, self.val_data = train_data, val_data
        self.lpips = lpips.to(self.device).eval() if lpips is not None else None
        self.run_info = run_info or {}
        self.on_step = on_step
        params = trainable_parameters(predictor)
        if not params:
            raise InputError("nothing to train: every parameter is frozen")
        self.model: torch.nn.Module = predictor
        if self.ctx.world_size > 1:
            self.model = torch.nn.parallel.DistributedDataParallel(  # the DPT's last refinement unit is unused
                predictor, device_ids=[self.ctx.local_rank] if config.device == "cuda" else None,
                find_unused_parameters=True,
            )  # fmt: skip
        self.optimizer = torch.optim.AdamW(params, lr=config.lr, weight_decay=config.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda s: _lr_factor(s, config.warmup, config.steps)
        )
        self.scaler = torch.amp.GradScaler("cuda", enabled=config.precision == "fp16")
        self.step = 0
        self.epoch = 0
        self.batch_in_epoch = 0
        self.best_psnr: float | None = None
        self.skipped = 0
        self.bad_in_a_row = 0
        self.validated_at = 0  # the step of the last completed validation
        self.history: list[dict[str, float]] = []
        self.written: list[Path] = []  # the files written by this process, each once, in order
        self.stop_after: int | None = None  # tests: simulate an interruption after this many steps
        self._tensorboard: Any = None  # a SummaryWriter when tensorboard is installed, False when not
        self._position: dict[str, Any] = {}  # the data position and RNG at the last step boundary (_mark)
        self._mark()

    # ------------------------------------------------------------------ files
    @property
    def out(self) -> Path:
        return Path(self.config.out)

    def prepare_run_folder(self, *, resume: bool, force: bool) -> None:
        """Create the run folder; refuse one holding another run unless ``resume`` or ``force``.

        Raises:
            OutputPathError: the folder holds another run, cannot be written, or ``resume`` finds no checkpoint or
                one that cannot be resumed (:mod:`.resume`).
        """
        run_json = self.out / "run.json"
        if resume:
            if not (self.out / "last.pt").is_file():
                raise OutputPathError(f"--resume {self.out}: no last.pt to resume from")
            if self.ctx.is_main:
                _check_appendable(self.out / "metrics.csv")  # before any work, not at the first step
            self.load_checkpoint(self.out / "last.pt")
            return
        if self.ctx.is_main and run_json.exists() and not force:
            raise OutputPathError(
                f"{self.out} holds another run (run.json): pass --resume {self.out} to continue it, or --force to "
                "start over in it"
            )
        if self.ctx.is_main:
            check_writable(run_json)
            doc = {"config": dataclasses.asdict(self.config), **self.run_info, "world_size": self.ctx.world_size}
            try:
                self.out.mkdir(parents=True, exist_ok=True)
                with atomic_path(run_json) as tmp:
                    tmp.write_text(json.dumps(to_jsonable(doc), indent=2) + "\n")
                (self.out / "metrics.csv").unlink(missing_ok=True)
            except OSError as e:
                raise OutputPathError(f"{run_json}: the run folder could not be written ({e.strerror or e})") from None
        _barrier(self.ctx)  # the other processes start once rank 0 has accepted the folder

    def _meta(self) -> dict[str, Any]:
        return {"step": self.step, "best_psnr": self.best_psnr, "config": to_jsonable(dataclasses.asdict(self.config))}

    def save_checkpoint(self, name: str = "last.pt", *, training_state: bool = True) -> Path | None:
        """Write a predictor checkpoint (with the training state for ``last.pt``) atomically (rank 0).

        Raises:
            OutputPathError: it could not be written (a full disk, a folder that went away); the previous file of that
                name is intact and no partial file is left.
        """
        if not self.ctx.is_main:
            return None
        path = self.out / name
        payload = self._training_payload() if training_state else self._predictor_payload()
        try:
            with atomic_path(path) as tmp:
                try:
                    torch.save(payload, tmp)
                except (OSError, RuntimeError) as e:  # torch's zip writer reports a failed write as RuntimeError
                    why = self._write_failure(e, tmp, training_state)
                    e.__traceback__ = None  # let go of torch's writer (and its open file) now
                    raise _WriteFailed(why) from None
        except _WriteFailed as e:
            raise OutputPathError(
                f"{path}: the checkpoint could not be written ({e}); the previous one is intact"
            ) from None
        except OSError as e:  # creating or renaming the temporary file
            raise OutputPathError(
                f"{path}: the checkpoint could not be written ({e.strerror or e}); the previous one is intact"
            ) from None
        if path not in self.written:
            self.written.append(path)
        return path

    def _write_failure(self, e: BaseException, tmp: Path, training_state: bool) -> str:
        """Why a checkpoint write failed, in words: OSError's own reason; else, when the disk lacks the room, the free
        space (once the partial ``tmp`` is removed) against the checkpoint's size; else torch's first sentence."""
        if isinstance(e, OSError):
            return str(e.strerror or e)
        tensors = list(self.predictor.state_dict().values())
        if training_state:
            tensors += [v for s in self.optimizer.state.values() for v in s.values() if isinstance(v, torch.Tensor)]
        need = sum(t.numel() * t.element_size() for t in tensors)
        with contextlib.suppress(OSError):
            free = shutil.disk_usage(tmp.parent).free + tmp.stat().st_blocks * 512
            if free < need:
                return f"no space left: {free / 2**20:.1f} MiB free, about {need / 2**20:.1f} MiB needed"
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        return f"the write failed: {first[:200]}"

    def _predictor_payload(self) -> dict[str, Any]:
        """``best.pt``: a predictor checkpoint (:func:`~macsplat_cli.neural.predictor_io.save_predictor_checkpoint`'s
        layout, which ``load_pair_predictor`` reads)."""
        return {
            "format": PREDICTOR_FORMAT,
            "version": 1,
            "config": predictor_config(self.predictor),
            "state_dict": {k: v.detach().cpu() for k, v in self.predictor.state_dict().items()},
            "meta": self._meta(),
        }

    def _training_payload(self) -> dict[str, Any]:
        """``last.pt``: the predictor, the optimiser, scheduler and scaler, and the counters, data position and RNG
        states of the last step boundary (:meth:`_mark`)."""
        pos = self._position
        return {
            **self._predictor_payload(),
            "training": {
                "optimizer": self.optimizer.state_dict(),
                "scheduler": self.scheduler.state_dict(),
                "scaler": self.scaler.state_dict(),
                "step": self.step,
                "epoch": pos["epoch"],
                "batch_in_epoch": pos["batch_in_epoch"],
                "best_psnr": self.best_psnr,
                "skipped": pos["skipped"],
                "bad_in_a_row": pos["bad_in_a_row"],
                "validated_at": self.validated_at,
                "rng": pos["rng"],
            },
        }

    def load_checkpoint(self, path: Path) -> None:
        """Restore model, optimiser, scheduler, data position and RNG from a ``last.pt``, once all of it is checked.

        Raises:
            OutputPathError: the file cannot be read, or does not fit this run (:mod:`.resume`); nothing is restored.
        """
        obj = read_training_checkpoint(path)
        state = check_training_checkpoint(
            obj, path, model=self.predictor, optimizer=self.optimizer, scheduler=self.scheduler, scaler=self.scaler,
            steps=self.config.steps,
        )  # fmt: skip
        t = obj["training"]
        try:
            self.predictor.load_state_dict(obj["state_dict"])
            self.optimizer.load_state_dict(t["optimizer"])
            self.scheduler.load_state_dict(dict(t["scheduler"]))
            self.scaler.load_state_dict(t["scaler"])
            set_rng_state(t["rng"])
        except (RuntimeError, ValueError, TypeError, KeyError) as e:  # checked above: not expected
            raise OutputPathError(f"{path}: cannot resume from it: {str(e).splitlines()[0][:200]}") from None
        self.step, self.epoch, self.batch_in_epoch = state.step, state.epoch, state.batch_in_epoch
        self.best_psnr, self.skipped, self.bad_in_a_row = state.best_psnr, state.skipped, state.bad_in_a_row
        self.validated_at = state.validated_at
        self._mark()
        logger.info("resumed %s at step %d (epoch %d, batch %d)", path, self.step, self.epoch, self.batch_in_epoch)

    def _log(self, row: dict[str, Any]) -> None:
        if not self.ctx.is_main:
            return
        if self._tensorboard is None:
            self._tensorboard = _tensorboard_writer(self.out)
        if self._tensorboard is not False:
            for k, v in row.items():
                if k not in ("step", "kind") and isinstance(v, (int, float)):
                    self._tensorboard.add_scalar(f"{row['kind']}/{k}", v, row["step"])
        path = self.out / "metrics.csv"
        fields = ["step", "kind", "loss", "photo", "mse", "perceptual", "mac", "matches", "lr", "seconds", "skipped",
                  "psnr", "ssim", "lpips"]  # fmt: skip
        try:
            with _open_for_append(path) as f:
                new = f.tell() == 0
                w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
                if new:
                    w.writeheader()
                w.writerow(row)
        except OSError as e:
            raise OutputPathError(f"{path}: the metrics could not be written ({e.strerror or e})") from None
        if path not in self.written:
            self.written.append(path)

    # ------------------------------------------------------------------ position
    def _mark(self) -> None:
        """Remember the state a checkpoint resumes from. Called where no step is half done — at the start and at the
        end of each step or skipped step, with interruptions held back — so that an interruption anywhere else
        resumes exactly (the batches of the step in flight are drawn again)."""
        self._position = {
            "epoch": self.epoch,
            "batch_in_epoch": self.batch_in_epoch,
            "skipped": self.skipped,
            "bad_in_a_row": self.bad_in_a_row,
            "rng": rng_state(),
        }

    def _rewind(self) -> None:
        """Back to the last step boundary (after an interruption): data position, counters and RNG."""
        pos = self._position
        self.epoch, self.batch_in_epoch = pos["epoch"], pos["batch_in_epoch"]
        self.skipped, self.bad_in_a_row = pos["skipped"], pos["bad_in_a_row"]
        set_rng_state(pos["rng"])
        self.optimizer.zero_grad(set_to_none=True)

    # ------------------------------------------------------------------ data
    def _batches(self) -> Iterator[dict[str, torch.Tensor]]:
        """Batches from the current data position on, epoch after epoch (a resumed epoch starts at its next batch:
        the sampler skips the samples already done, nothing is loaded for them)."""
        from .data import make_loader

        while True:
            self.train_data.set_epoch(self.epoch)
            loader = make_loader(
                self.train_data, batch_size=self.config.batch, workers=self.config.workers, shuffle=True,
                seed=self.config.seed, rank=self.ctx.rank, world_size=self.ctx.world_size,
                start_batch=self.batch_in_epoch,
            )  # fmt: skip
            for batch in loader:
                self.batch_in_epoch += 1
                yield batch
            self.epoch += 1
            self.batch_in_epoch = 0

    def _autocast(self) -> Any:
        dtype = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(self.config.precision)
        return torch.autocast(device_type=self.device.type, dtype=dtype or torch.float32, enabled=dtype is not None)

    def _forward(self, batch: dict[str, torch.Tensor], model: torch.nn.Module) -> Any:
        ctx = batch["context"].to(self.device)
        with self._autocast():
            outputs = model(ctx[:, 0], ctx[:, 1])
        pred = prediction_from_outputs([o.float() for o in outputs])
        return training_loss(pred, batch, self.config.loss, self.lpips)

    # ------------------------------------------------------------------ validation
    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """PSNR and SSIM of the rendered targets of every validation pair (full images).

        The global RNG states are the same after as before (a validation never changes what training does next).
        """
        from .data import make_loader

        rng = rng_state()
        try:
            return self._validate(make_loader)
        finally:
            set_rng_state(rng)

    def _validate(self, make_loader: Callable[..., Any]) -> dict[str, float]:
        self.predictor.eval()
        loader = make_loader(self.val_data, batch_size=1, workers=0, shuffle=False, seed=self.config.seed)
        psnrs, ssims, lpipss = [], [], []
        for batch in loader:
            ctx = batch["context"].to(self.device)
            with self._autocast():
                outputs = self.predictor(ctx[:, 0], ctx[:, 1])
            pred = prediction_from_outputs([o.float() for o in outputs])
            h, w = batch["target"].shape[-2:]
            rgb = render_targets(pred.gaussians, 0, batch["target_K"][0], batch["target_c2w"][0],
                                 batch["context_c2w"][0, 0], (h, w), self.config.loss.background)  # fmt: skip
            gt = batch["target"][0].to(rgb.device)
            for r, g in zip(rgb.clamp(0, 1), gt):
                psnrs.append(float(psnr(r.permute(1, 2, 0), g.permute(1, 2, 0))))
                ssims.append(float(ssim(r.permute(1, 2, 0), g.permute(1, 2, 0))))
            if self.lpips is not None:
                lpipss.extend(float(v) for v in self.lpips(rgb.clamp(0, 1), gt))
        out = {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims))}
        return {**out, "lpips": float(np.mean(lpipss))} if lpipss else out

    def _validation_due(self, step: int) -> bool:
        cfg = self.config
        return self.val_data is not None and ((cfg.val_every > 0 and step % cfg.val_every == 0) or step == cfg.steps)

    # ------------------------------------------------------------------ training
    def fit(self) -> TrainResult:
        """Train until ``config.steps``; Ctrl-C or SIGTERM writes ``last.pt`` (the last step boundary) and re-raises.

        Raises:
            KeyboardInterrupt: interrupted (``last.pt`` written; the trainer is back at the last step boundary).
            TrainingError: the loss stayed non-finite for ``max_bad_steps`` steps.
            OutputPathError: a file of the run folder could not be written.
        """
        cfg = self.config
        t0 = time.perf_counter()
        self.history = []
        batches = self._batches()
        self._mark()
        try:
            if self.step > 0 and self.validated_at < self.step and self._validation_due(self.step):
                self._validate_and_keep_best()  # interrupted after its step, before its validation
            while self.step < cfg.steps:
                if self.stop_after is not None and self.step >= self.stop_after:
                    raise KeyboardInterrupt
                self.predictor.train()
                for module in (self.predictor.dino, self.predictor.backbone):  # frozen modules stay in eval mode
                    if module is not None and not any(p.requires_grad for p in module.parameters()):
                        module.eval()
                self.optimizer.zero_grad(set_to_none=True)
                terms_sum: dict[str, float] = {}
                finite = True
                t_step = time.perf_counter()
                for micro in range(cfg.accumulate):
                    batch = next(batches)
                    logger.debug(
                        "step %d: samples %s on rank %d", self.step + 1, batch["index"].tolist(), self.ctx.rank
                    )
                    sync = micro == cfg.accumulate - 1 or self.ctx.world_size == 1
                    context = self.model.no_sync() if not sync else contextlib.nullcontext()
                    with context:
                        terms = self._forward(batch, self.model)
                        if not torch.isfinite(terms.loss):
                            finite = False
                        self.scaler.scale(terms.loss / cfg.accumulate).backward()
                    for k in ("photo", "mse", "perceptual", "mac", "matches"):
                        terms_sum[k] = terms_sum.get(k, 0.0) + getattr(terms, k) / cfg.accumulate
                    terms_sum["loss"] = terms_sum.get("loss", 0.0) + float(terms.loss.detach()) / cfg.accumulate
                finite = _all_ranks(finite, self.ctx, self.device)
                if not finite:
                    with _interrupts_held():  # a skipped step is done as a whole, or not at all
                        self.skipped += 1
                        self.bad_in_a_row += 1
                        self.optimizer.zero_grad(set_to_none=True)
                        self._mark()
                    logger.warning(
                        "step %d: non-finite loss, step skipped (%d in a row)", self.step + 1, self.bad_in_a_row
                    )
                    if self.bad_in_a_row >= cfg.max_bad_steps:
                        raise TrainingError(
                            f"the loss was non-finite for {self.bad_in_a_row} steps in a row (step {self.step + 1}); "
                            f"stopped, the last good checkpoint is {self.out / 'last.pt'} (try a lower --lr)"
                        )
                    continue
                with _interrupts_held():  # the step is done as a whole, or not at all
                    self.bad_in_a_row = 0
                    if cfg.grad_clip > 0:
                        self.scaler.unscale_(self.optimizer)
                        torch.nn.utils.clip_grad_norm_(trainable_parameters(self.predictor), cfg.grad_clip)
                    self.scaler.step(self.optimizer)
                    self.scaler.update()
                    self.scheduler.step()
                    self.step += 1
                    row = {"step": self.step, "kind": "train", **terms_sum, "lr": self.scheduler.get_last_lr()[0],
                           "seconds": time.perf_counter() - t_step, "skipped": self.skipped}  # fmt: skip
                    self.history.append(row)
                    self._mark()
                    self._log(row)
                if self.on_step is not None and self.ctx.is_main:
                    self.on_step(self.step, row)
                if self._validation_due(self.step):
                    self._validate_and_keep_best()
                if (cfg.ckpt_every and self.step % cfg.ckpt_every == 0) or self.step == cfg.steps:
                    self.save_checkpoint()
        except KeyboardInterrupt:
            self._rewind()
            self.save_checkpoint()
            raise
        if self.val_data is None:
            self.save_checkpoint("best.pt", training_state=False)
        if self._tensorboard:
            self._tensorboard.flush()
        return TrainResult(self.step, self.best_psnr, self.skipped, time.perf_counter() - t0, self.history,
                           list(self.written))  # fmt: skip

    def _validate_and_keep_best(self) -> None:
        """Validate; a finite PSNR above the best so far writes ``best.pt`` (a NaN one never counts)."""
        if not self.ctx.is_main:
            _barrier(self.ctx)
            self.validated_at = self.step
            return
        metrics = self.validate()
        logger.info("step %d: validation PSNR %.2f dB, SSIM %.3f", self.step, metrics["psnr"], metrics["ssim"])
        value = metrics["psnr"]
        better = not math.isnan(value) and (self.best_psnr is None or value > self.best_psnr)
        if better:
            self.save_checkpoint("best.pt", training_state=False)  # written first: an interruption re-validates
        elif math.isnan(value):
            logger.warning("step %d: the validation PSNR is NaN: best.pt is not updated", self.step)
        with _interrupts_held():
            if better:
                self.best_psnr = value
            self.validated_at = self.step
            self._log({"step": self.step, "kind": "val", **metrics})
        _barrier(self.ctx)


def _check_appendable(path: Path) -> None:
    """Refuse a ``path`` that exists and is a link or not a regular file (appending would write through it)."""
    if path.is_symlink():
        raise OutputPathError(f"{path}: is a symbolic link; macsplat appends only to regular files")
    if path.exists() and not path.is_file():
        raise OutputPathError(f"{path}: exists and is not a regular file; macsplat appends only to regular files")


def _open_for_append(path: Path) -> TextIO:
    """Open ``path`` to append text, refusing a link or anything but a regular file (a link planted at the name
    would be written through). ``O_NOFOLLOW`` and ``O_NONBLOCK`` (a FIFO without a reader fails instead of blocking)
    keep the refusal true when the name is swapped after :func:`_check_appendable`."""
    _check_appendable(path)
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    fd = os.open(path, flags, 0o666)
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OutputPathError(f"{path}: exists and is not a regular file; macsplat appends only to regular files")
    return os.fdopen(fd, "a", newline="", encoding="utf-8")


def _tensorboard_writer(folder: Path) -> Any:
    """A TensorBoard writer into the run folder when tensorboard is installed (optional), else False."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        logger.debug("tensorboard is not installed: metrics go to metrics.csv only")
        return False
    return SummaryWriter(log_dir=str(folder / "tensorboard"))


def _all_ranks(flag: bool, ctx: DistributedContext, device: torch.device) -> bool:
    """``flag`` on every process (a step is skipped everywhere when one process saw a non-finite loss)."""
    if ctx.world_size == 1:
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MIN)
    return bool(t.item() > 0.5)


def _barrier(ctx: DistributedContext) -> None:
    if ctx.world_size > 1:
        dist.barrier()
