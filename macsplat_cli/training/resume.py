"""Checking a ``last.pt`` before ``macsplat train --resume`` restores anything from it.

A resumable checkpoint is a dict (:mod:`macsplat_cli.neural.predictor_io` layout plus ``"training"``) whose every part
must fit the run being resumed; :func:`read_training_checkpoint` reads the file and :func:`check_training_checkpoint`
checks, in this order, and names the first problem:

* the file: a zip/pickle that ``torch.load(weights_only=True)`` reads (a truncated, empty or foreign file is refused);
* the layout: ``format``, the model ``config`` (the same as this run's), ``state_dict`` and ``training`` dicts;
* the weights: the model's keys exactly, each a dense tensor of the model's shape and dtype, finite;
* the optimiser (Adam or AdamW): as many parameter groups of the same sizes, known hyper-parameters of the right types
  and ranges, per-parameter state (``step``, ``exp_avg``, ``exp_avg_sq``) of each parameter's shape, finite,
  ``exp_avg_sq ≥ 0``;
* the scheduler: only keys this scheduler has, ``last_epoch`` equal to the step, finite learning rates;
* the gradient scaler (fp16): finite, positive settings;
* the counters: ``step`` an integer in ``0 … steps`` (a checkpoint beyond the run's ``--steps`` is refused),
  ``epoch``, ``batch_in_epoch``, ``skipped`` integers in ``0 … 2³¹``; ``best_psnr`` None or a number — NaN or −∞
  count as "no best yet" (a NaN would otherwise never be beaten, and ``best.pt`` never written again);
* the RNG states: torch's of the size this torch uses, NumPy's MT19937 (624 words, position ≤ 624), Python's
  (version 3, 625 words); they are restored on trial and put back when rejected.

Nothing is restored until everything has passed.
"""

from __future__ import annotations

import logging
import math
import random
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from ..errors import OutputPathError
from ..neural.predictor import PairPredictor
from ..neural.predictor_io import PREDICTOR_FORMAT, predictor_config

__all__ = ["COUNTER_MAX", "ResumeState", "check_training_checkpoint", "read_training_checkpoint"]

logger = logging.getLogger(__name__)

COUNTER_MAX = 2**31
"""Exclusive upper bound of the epoch, batch and skipped-step counters (far beyond any real run; keeps seeds sane)."""

_TRAINING_KEYS = ("optimizer", "scheduler", "scaler", "step", "epoch", "batch_in_epoch", "best_psnr", "skipped", "rng")
_ADAM_STATE = ("step", "exp_avg", "exp_avg_sq")


class _Bad(Exception):
    """One problem with the checkpoint (becomes an :class:`OutputPathError` naming the file)."""


@dataclass
class ResumeState:
    """The counters of a checked checkpoint (the tensors and optimiser states stay in ``obj``)."""

    obj: dict[str, Any]
    step: int
    epoch: int
    batch_in_epoch: int
    best_psnr: float | None
    skipped: int
    bad_in_a_row: int
    validated_at: int


def read_training_checkpoint(path: Path) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU; any failure to read it is an :class:`OutputPathError`."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - truncated zip, foreign pickle, empty file, I/O error: all one answer
        first = (str(e).strip().splitlines() or [""])[0].split(". ")[0][:200]  # torch's first sentence
        raise OutputPathError(
            f"{path}: not a readable checkpoint ({type(e).__name__}{': ' + first if first else ''}); "
            "nothing was resumed"
        ) from None


def _expect(ok: bool, message: str) -> None:
    if not ok:
        raise _Bad(message)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_real(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


_SHOWN_ITEMS = 20
"""A plain dict, list, tuple or set with more entries than this has a repr over 60 characters (each entry takes at
least three): :func:`_show` names its type without building the repr (a state dict's repr took seconds)."""


def _show(v: Any) -> str:
    if type(v) in (dict, list, tuple, set, frozenset) and len(v) > _SHOWN_ITEMS:
        return f"a {type(v).__name__}"
    text = repr(v) if not isinstance(v, torch.Tensor) else f"a tensor of shape {list(v.shape)}"
    return text if len(text) <= 60 else f"a {type(v).__name__}"


def _counter(t: Mapping[str, Any], key: str, hi: int = COUNTER_MAX) -> int:
    v = t[key]
    _expect(_is_int(v), f"training.{key} is {_show(v)}, expected an integer")
    _expect(0 <= v < hi, f"training.{key} is {v}, outside 0 … {hi - 1}")
    return int(v)


def _tensor(v: Any, where: str, like: torch.Tensor | None = None, *, shape: tuple[int, ...] | None = None) -> None:
    _expect(isinstance(v, torch.Tensor), f"{where} is {_show(v)}, expected a tensor")
    _expect(v.layout == torch.strided and not v.is_meta, f"{where} is not a dense tensor")
    want = tuple(like.shape) if like is not None else shape
    _expect(want is None or tuple(v.shape) == want, f"{where} has shape {list(v.shape)}, expected {list(want or ())}")
    if like is not None:
        _expect(v.dtype == like.dtype, f"{where} is {v.dtype}, expected {like.dtype}")
    if v.is_floating_point() or v.is_complex():
        _expect(bool(torch.isfinite(v).all()), f"{where} holds non-finite values")


def _check_weights(sd: Any, model: torch.nn.Module) -> None:
    _expect(isinstance(sd, dict), f"state_dict is {_show(sd)}, expected a dict of tensors")
    want = model.state_dict()
    missing = [k for k in want if k not in sd]
    if missing:
        raise _Bad(f"state_dict lacks {missing[0]!r}" + (f" and {len(missing) - 1} more" if missing[1:] else ""))
    extra = [k for k in sd if k not in want]
    if extra:
        raise _Bad(f"state_dict has {extra[0]!r}, which this model does not")
    for k, v in want.items():
        _tensor(sd[k], f"state_dict[{k!r}]", v)


def _check_hyper(key: str, saved: Any, current: Any, where: str, *, same_flags: bool = False) -> None:
    """``saved`` of the kind of ``current`` (a flag, a number ≥ 0, a tuple of numbers); with ``same_flags``, a flag
    (an implementation choice such as ``foreach``, ``fused``, ``amsgrad``) must equal this run's."""
    if isinstance(current, bool) or current is None:
        _expect(saved is None or isinstance(saved, bool), f"{where}[{key!r}] is {_show(saved)}, expected a flag")
        _expect(not same_flags or saved == current, f"{where}[{key!r}] is {saved}, this run's {current}")
    elif _is_real(current):
        _expect(_is_real(saved) and math.isfinite(saved), f"{where}[{key!r}] is {_show(saved)}, expected a number")
        _expect(saved >= 0 and (key != "eps" or saved > 0), f"{where}[{key!r}] is {saved}, out of range")
    elif isinstance(current, (tuple, list)):
        _expect(
            isinstance(saved, (tuple, list))
            and len(saved) == len(current)
            and all(_is_real(x) and math.isfinite(x) for x in saved),
            f"{where}[{key!r}] is {_show(saved)}, expected {len(current)} numbers",
        )
        if key == "betas":
            _expect(all(0 <= x < 1 for x in saved), f"{where}['betas'] is {_show(saved)}, outside [0, 1)")
    else:
        _expect(
            type(saved) is type(current), f"{where}[{key!r}] is {_show(saved)}, expected a {type(current).__name__}"
        )


def _check_optimizer(sd: Any, optimizer: torch.optim.Optimizer) -> None:
    where = "training.optimizer"
    _expect(isinstance(sd, dict) and set(sd) == {"state", "param_groups"}, f"{where} is not an optimiser state")
    groups, state = sd["param_groups"], sd["state"]
    current = optimizer.state_dict()["param_groups"]
    _expect(
        isinstance(groups, list) and len(groups) == len(current),
        f"{where} has {len(groups) if isinstance(groups, list) else 'no list of'} parameter group(s), expected "
        f"{len(current)}",
    )
    params_by_id: dict[int, torch.Tensor] = {}
    for i, (g, cur, live) in enumerate(zip(groups, current, optimizer.param_groups)):
        gw = f"{where}.param_groups[{i}]"
        _expect(isinstance(g, dict), f"{gw} is {_show(g)}, expected a dict")
        ids = g.get("params")
        _expect(
            isinstance(ids, list) and all(_is_int(x) for x in ids) and len(set(ids)) == len(ids),
            f"{gw}['params'] is not a list of distinct parameter ids",
        )
        _expect(len(ids) == len(live["params"]), f"{gw} has {len(ids)} parameters, this run {len(live['params'])}")
        for key in ("lr", "betas", "eps", "weight_decay"):
            _expect(key in g, f"{gw} lacks {key!r}")
        for key, value in g.items():
            if key == "params":
                continue
            if key in cur:
                _check_hyper(key, value, cur[key], gw, same_flags=True)
            else:
                _expect(value is None or isinstance(value, (bool, int, float, str)), f"{gw}[{key!r}] is unexpected")
        for pid, p in zip(ids, live["params"]):
            _expect(pid not in params_by_id, f"{where}: parameter id {pid} is in two groups")
            params_by_id[pid] = p
    _expect(isinstance(state, dict), f"{where}.state is {_show(state)}, expected a dict")
    amsgrad = any(bool(g.get("amsgrad")) for g in groups)
    for pid, s in state.items():
        sw = f"{where}.state[{pid!r}]"
        _expect(pid in params_by_id, f"{sw} belongs to no parameter")
        keys = _ADAM_STATE + (("max_exp_avg_sq",) if amsgrad else ())
        _expect(isinstance(s, dict) and set(s) == set(keys), f"{sw} is not an Adam(W) state ({', '.join(keys)})")
        p = params_by_id[pid]
        step = s["step"]
        if isinstance(step, torch.Tensor):
            _tensor(step, f"{sw}['step']", shape=tuple(step.shape))
            _expect(step.numel() == 1 and float(step) >= 0, f"{sw}['step'] is not a count")
        else:
            _expect(_is_real(step) and math.isfinite(step) and step >= 0, f"{sw}['step'] is {_show(step)}")
        for key in keys[1:]:
            _tensor(s[key], f"{sw}[{key!r}]", p.detach())
        _expect(bool((s["exp_avg_sq"] >= 0).all()), f"{sw}['exp_avg_sq'] holds negative values")


def _check_scheduler(sd: Any, scheduler: Any, step: int) -> None:
    where = "training.scheduler"
    current = scheduler.state_dict()
    _expect(isinstance(sd, dict), f"{where} is {_show(sd)}, expected a dict")
    unknown = [k for k in sd if k not in current]
    if unknown:
        raise _Bad(f"{where} has {unknown[0]!r}, which this scheduler does not")
    for key in ("base_lrs", "last_epoch"):
        _expect(key in sd, f"{where} lacks {key!r}")
    _expect(_is_int(sd["last_epoch"]), f"{where}['last_epoch'] is {_show(sd['last_epoch'])}, expected an integer")
    _expect(sd["last_epoch"] == step, f"{where}['last_epoch'] is {sd['last_epoch']}, but the step is {step}")
    n = len(current["base_lrs"])
    for key in ("base_lrs", "_last_lr"):
        if key in sd:
            v = sd[key]
            _expect(
                isinstance(v, list) and len(v) == n and all(_is_real(x) and math.isfinite(x) and x >= 0 for x in v),
                f"{where}[{key!r}] is {_show(v)}, expected {n} learning rate(s)",
            )
    if "lr_lambdas" in sd:
        v = sd["lr_lambdas"]
        _expect(
            isinstance(v, list) and len(v) == n and all(x is None for x in v), f"{where}['lr_lambdas'] is unexpected"
        )
    for key, value in sd.items():
        if key not in ("base_lrs", "_last_lr", "lr_lambdas", "last_epoch"):
            _check_hyper(key, value, current[key], where)


def _check_scaler(sd: Any, scaler: torch.amp.GradScaler) -> None:
    where = "training.scaler"
    _expect(isinstance(sd, dict), f"{where} is {_show(sd)}, expected a dict")
    if not scaler.is_enabled():
        return  # fp32/bf16: a disabled scaler ignores its state
    for key in ("scale", "growth_factor", "backoff_factor", "growth_interval", "_growth_tracker"):
        _expect(key in sd, f"{where} lacks {key!r} (this run uses fp16)")
        v = sd[key]
        _expect(_is_real(v) and math.isfinite(v) and v >= 0, f"{where}[{key!r}] is {_show(v)}")
    _expect(sd["scale"] > 0 and _is_int(sd["growth_interval"]) and sd["growth_interval"] >= 1, f"{where} is unusable")


def _check_rng(state: Any) -> None:
    where = "training.rng"
    _expect(isinstance(state, dict), f"{where} is {_show(state)}, expected a dict")
    for key in ("torch", "numpy", "numpy_pos", "numpy_gauss", "python"):
        _expect(key in state, f"{where} lacks {key!r}")
    t = state["torch"]
    _tensor(t, f"{where}['torch']", torch.get_rng_state())
    mt = state["numpy"]
    _tensor(mt, f"{where}['numpy']", shape=(624,))
    _expect(mt.dtype == torch.int64 and bool(((mt >= 0) & (mt < 2**32)).all()), f"{where}['numpy'] is not MT19937")
    pos = state["numpy_pos"]
    _expect(_is_int(pos) and 0 <= pos <= 624, f"{where}['numpy_pos'] is {_show(pos)}")
    gauss = state["numpy_gauss"]
    _expect(
        isinstance(gauss, (tuple, list)) and len(gauss) == 2 and _is_int(gauss[0]) and _is_real(gauss[1]),
        f"{where}['numpy_gauss'] is {_show(gauss)}",
    )
    py = state["python"]
    ok = isinstance(py, (tuple, list)) and len(py) == 3 and py[0] == 3 and isinstance(py[1], (tuple, list))
    ok = ok and len(py[1]) == 625 and all(_is_int(x) and 0 <= x < 2**32 for x in py[1]) and py[1][-1] <= 624
    _expect(ok and (py[2] is None or _is_real(py[2])), f"{where}['python'] is not Python's random state")


def rng_state() -> dict[str, Any]:
    """The global RNG states (torch CPU, NumPy, Python) as checkpointable values."""
    # legacy=True: the tuple (name, keys, pos, has_gauss, cached_gaussian)
    np_state = cast(tuple[str, np.ndarray, int, int, float], np.random.get_state(legacy=True))
    return {
        "torch": torch.get_rng_state(),
        "numpy": torch.from_numpy(np_state[1].astype(np.int64)),
        "numpy_pos": int(np_state[2]),
        "numpy_gauss": (int(np_state[3]), float(np_state[4])),
        "python": random.getstate(),
    }


def set_rng_state(state: Mapping[str, Any]) -> None:
    """Restore :func:`rng_state`'s values; on failure the previous states are put back and the error re-raised."""
    before = rng_state()
    try:
        torch.set_rng_state(state["torch"])
        has_gauss, cached = state["numpy_gauss"]
        np.random.set_state(
            ("MT19937", state["numpy"].numpy().astype(np.uint32), state["numpy_pos"], has_gauss, cached)
        )
        version, internal, gauss = state["python"]
        random.setstate((version, tuple(internal), gauss))
    except BaseException:
        torch.set_rng_state(before["torch"])
        np.random.set_state(
            ("MT19937", before["numpy"].numpy().astype(np.uint32), before["numpy_pos"], *before["numpy_gauss"])
        )
        random.setstate(before["python"])
        raise


def check_training_checkpoint(
    obj: Any,
    path: Path,
    *,
    model: PairPredictor,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    scaler: torch.amp.GradScaler,
    steps: int,
) -> ResumeState:
    """Check a loaded ``last.pt`` against the run resuming it (module docstring); restores nothing.

    Args:
        obj: what :func:`read_training_checkpoint` gave.
        path: the file (for the messages).
        model: the predictor being trained (the unwrapped module).
        optimizer, scheduler, scaler: this run's, freshly built.
        steps: this run's total steps.

    Raises:
        OutputPathError: the first problem, naming ``path``.
    """
    try:
        return _check(obj, path, model, optimizer, scheduler, scaler, steps)
    except _Bad as e:
        raise OutputPathError(f"{path}: cannot resume from it: {e}") from None


def _check(
    obj: Any, path: Path, model: PairPredictor, optimizer: Any, scheduler: Any, scaler: Any, steps: int
) -> ResumeState:
    _expect(
        isinstance(obj, dict) and obj.get("format") == PREDICTOR_FORMAT and isinstance(obj.get("training"), dict),
        "not a resumable macsplat training checkpoint",
    )
    _expect(
        obj.get("config") == predictor_config(model), "its model configuration differs from this run's (--model/--init)"
    )
    _check_weights(obj.get("state_dict"), model)
    t = obj["training"]
    missing = [k for k in _TRAINING_KEYS if k not in t]
    _expect(not missing, f"training lacks {', '.join(map(repr, missing))}")
    step = t["step"]
    _expect(_is_int(step), f"training.step is {_show(step)}, expected an integer")
    _expect(step >= 0, f"training.step is {step}, expected 0 or more")
    more = f" (give --steps {step} or more to go on)" if step < COUNTER_MAX else ""
    _expect(step <= steps, f"it is at step {step}, beyond this run's --steps {steps}{more}")
    epoch, batch, skipped = _counter(t, "epoch"), _counter(t, "batch_in_epoch"), _counter(t, "skipped")
    bad_in_a_row = _counter(t, "bad_in_a_row") if "bad_in_a_row" in t else 0
    validated_at = _counter(t, "validated_at", step + 1) if "validated_at" in t else step
    best = t["best_psnr"]
    _expect(best is None or _is_real(best), f"training.best_psnr is {_show(best)}, expected a number or None")
    if best is not None and (math.isnan(best) or best == -math.inf):
        logger.warning("%s: its best validation PSNR is %s: taken as none yet (the next validation writes best.pt)",
                       path, best)  # fmt: skip
        best = None
    _check_optimizer(t["optimizer"], optimizer)
    _check_scheduler(t["scheduler"], scheduler, step)
    _check_scaler(t["scaler"], scaler)
    _check_rng(t["rng"])
    try:  # the last word on the RNG states is theirs: restore on trial, put back
        before = rng_state()
        set_rng_state(t["rng"])
        set_rng_state(before)
    except (ValueError, TypeError, RuntimeError, OverflowError) as e:
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise _Bad(f"training.rng is not a valid RNG state ({why})") from None
    return ResumeState(obj, step, epoch, batch, None if best is None else float(best), skipped, bad_in_a_row,
                       validated_at)  # fmt: skip
