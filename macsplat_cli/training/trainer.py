"""The training loop of ``macsplat train``: AdamW or Adam and their schedule (:mod:`.optim`), clipping,
accumulation, AMP, validation, atomic checkpoints, exact resume, and data-parallel training over processes started
by ``torchrun``.

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
import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from .._atomic import atomic_path, check_writable
from .._json import to_jsonable
from ..errors import InputError, MacsplatError, OutputPathError
from ..lpips import LPIPS
from ..neural.predictor import PairPredictor, prediction_from_outputs
from .checkpoint import predictor_payload, state_bytes, write_checkpoint
from .config import TrainConfig
from .distributed import all_ranks, barrier, distributed_context
from .interrupts import interrupts_held
from .loss import training_loss
from .model import trainable_parameters
from .optim import build_optimizer, build_scheduler
from .resume import check_training_checkpoint, read_training_checkpoint, rng_state, set_rng_state
from .run_log import MetricsLog, check_appendable
from .validation import validation_metrics

__all__ = ["TrainResult", "TrainingError", "Trainer"]

logger = logging.getLogger(__name__)


class TrainingError(MacsplatError):
    """Training cannot go on (the loss stayed non-finite); the last good checkpoint is kept."""

    exit_code = 3


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
    history: list[dict[str, Any]]
    written: list[Path] = field(default_factory=list)


# ============================================================================================= the loop
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
        lpips: LPIPS | None = None,
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
        self.device = (
            torch.device(config.device, self.ctx.local_rank) if config.device == "cuda" else torch.device(config.device)
        )
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
        self.optimizer = build_optimizer(params, config)
        self.scheduler = build_scheduler(self.optimizer, config)
        self.scaler = torch.amp.GradScaler("cuda", enabled=config.precision == "fp16")
        self.step = 0
        self.epoch = 0
        self.batch_in_epoch = 0
        self.best_psnr: float | None = None
        self.skipped = 0
        self.bad_in_a_row = 0
        self.validated_at = 0  # the step of the last completed validation
        self.history: list[dict[str, Any]] = []
        self.written: list[Path] = []  # the files written by this process, each once, in order
        self.stop_after: int | None = None  # tests: simulate an interruption after this many steps
        self.metrics = MetricsLog(self.out)
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
            self._check_same_recipe(run_json)
            if self.ctx.is_main:
                check_appendable(self.out / "metrics.csv")  # before any work, not at the first step
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
        barrier(self.ctx)  # the other processes start once rank 0 has accepted the folder

    def _check_same_recipe(self, run_json: Path) -> None:
        """A resumed run keeps its recipe: another one is refused naming both (before the checkpoint is read)."""
        try:
            before = json.loads(run_json.read_text())["recipe"]["name"]
        except (OSError, ValueError, KeyError, TypeError):
            return  # no readable recipe (an older run): the checkpoint's own checks decide
        now = (self.run_info.get("recipe") or {}).get("name")
        if now is not None and now != before:
            raise OutputPathError(f"{self.out} was trained with --recipe {before}: resume it with --recipe {before}, "
                                  f"or start over with --recipe {now} --force")  # fmt: skip

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
        payload = self._training_payload() if training_state else predictor_payload(self.predictor, self._meta())
        optimizer = self.optimizer if training_state else None
        write_checkpoint(path, payload, size=lambda: state_bytes(self.predictor, optimizer))
        if path not in self.written:
            self.written.append(path)
        return path

    def _training_payload(self) -> dict[str, Any]:
        """``last.pt``: the predictor, the optimiser, scheduler and scaler, and the counters, data position and RNG
        states of the last step boundary (:meth:`_mark`)."""
        pos = self._position
        return {
            **predictor_payload(self.predictor, self._meta()),
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
        """A row of ``metrics.csv`` (and TensorBoard), written by rank 0."""
        if not self.ctx.is_main:
            return
        self.metrics.write(row)
        if self.metrics.path not in self.written:
            self.written.append(self.metrics.path)

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
            self.predictor.eval()
            assert self.val_data is not None  # _validation_due: only with held-out pairs
            loader = make_loader(self.val_data, batch_size=1, workers=0, shuffle=False, seed=self.config.seed)
            return validation_metrics(self.predictor, loader, device=self.device, autocast=self._autocast,
                                      background=self.config.loss.background, lpips=self.lpips,
                                      near=self.config.loss.near_plane)  # fmt: skip
        finally:
            set_rng_state(rng)

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
                row = self._step(batches)
                if row is None:
                    continue
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
        self.metrics.flush()
        return TrainResult(self.step, self.best_psnr, self.skipped, time.perf_counter() - t0, self.history,
                           list(self.written))  # fmt: skip

    def _step(self, batches: Iterator[dict[str, torch.Tensor]]) -> dict[str, Any] | None:
        """One optimiser step over ``accumulate`` micro-batches: its metrics row, or None when a non-finite loss
        (on any process) skipped it."""
        self.predictor.train()
        for module in (self.predictor.dino, self.predictor.backbone):  # frozen modules stay in eval mode
            if module is not None and not any(p.requires_grad for p in module.parameters()):
                module.eval()
        self.optimizer.zero_grad(set_to_none=True)
        t_step = time.perf_counter()
        terms_sum, finite = self._accumulate(batches)
        if not all_ranks(finite, self.ctx, self.device):
            self._skip()
            return None
        with interrupts_held():  # the step is done as a whole, or not at all
            self.bad_in_a_row = 0
            if self.config.grad_clip > 0:
                self.scaler.unscale_(self.optimizer)
                torch.nn.utils.clip_grad_norm_(trainable_parameters(self.predictor), self.config.grad_clip)
            self.scaler.step(self.optimizer)
            self.scaler.update()
            self.scheduler.step()
            self.step += 1
            row = {"step": self.step, "kind": "train", **terms_sum, "lr": self.scheduler.get_last_lr()[0],
                   "seconds": time.perf_counter() - t_step, "skipped": self.skipped}  # fmt: skip
            self.history.append(row)
            self._mark()
            self._log(row)
        return row

    def _accumulate(self, batches: Iterator[dict[str, torch.Tensor]]) -> tuple[dict[str, float], bool]:
        """Forward and backward passes of the step's micro-batches (DDP synchronises on the last): the loss terms
        averaged over them, and whether every loss was finite on this process."""
        cfg = self.config
        terms_sum: dict[str, float] = {}
        finite = True
        for micro in range(cfg.accumulate):
            batch = next(batches)
            logger.debug("step %d: samples %s on rank %d", self.step + 1, batch["index"].tolist(), self.ctx.rank)
            sync = micro == cfg.accumulate - 1 or self.ctx.world_size == 1
            ddp = self.model if isinstance(self.model, torch.nn.parallel.DistributedDataParallel) else None
            context = ddp.no_sync() if not sync and ddp is not None else contextlib.nullcontext()  # DDP unless sync
            with context:
                terms = self._forward(batch, self.model)
                if not torch.isfinite(terms.loss):
                    finite = False
                self.scaler.scale(terms.loss / cfg.accumulate).backward()
            for k in ("photo", "mse", "perceptual", "mac", "matches"):
                terms_sum[k] = terms_sum.get(k, 0.0) + getattr(terms, k) / cfg.accumulate
            terms_sum["loss"] = terms_sum.get("loss", 0.0) + float(terms.loss.detach()) / cfg.accumulate
        return terms_sum, finite

    def _skip(self) -> None:
        """Skip a step whose loss was non-finite; ``max_bad_steps`` of them in a row stop the run."""
        with interrupts_held():  # a skipped step is done as a whole, or not at all
            self.skipped += 1
            self.bad_in_a_row += 1
            self.optimizer.zero_grad(set_to_none=True)
            self._mark()
        logger.warning("step %d: non-finite loss, step skipped (%d in a row)", self.step + 1, self.bad_in_a_row)
        if self.bad_in_a_row >= self.config.max_bad_steps:
            raise TrainingError(
                f"the loss was non-finite for {self.bad_in_a_row} steps in a row (step {self.step + 1}); "
                f"stopped, the last good checkpoint is {self.out / 'last.pt'} (try a lower --lr)"
            )

    def _validate_and_keep_best(self) -> None:
        """Validate; a finite PSNR above the best so far writes ``best.pt`` (a NaN one never counts)."""
        if not self.ctx.is_main:
            barrier(self.ctx)
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
        with interrupts_held():
            if better:
                self.best_psnr = value
            self.validated_at = self.step
            self._log({"step": self.step, "kind": "val", **metrics})
        barrier(self.ctx)
