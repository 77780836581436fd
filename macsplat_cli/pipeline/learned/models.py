"""kornia's ALIKED and LightGlue built without weights and filled, strictly, from the pinned files
(:mod:`.weights`); built once per process and settings (:func:`learned_models`).

kornia is imported here only when a model is built: a run that SIFT handles never loads it.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from typing import Any

import torch

from ..._state_dict import check_state_dict_keys
from .config import LearnedConfig
from .weights import LearnedWeightsError, load_weights, locate

__all__ = ["DERIVED_BUFFERS", "LearnedModels", "build_aliked", "build_lightglue", "learned_models"]

logger = logging.getLogger(__name__)

DERIVED_BUFFERS = {"aliked": ("dkd.hw_grid",), "lightglue": ("confidence_thresholds",)}
"""Buffers each model computes from its settings at construction (never in the files); every other key is
filled from the file."""

ALIKED_LAYOUT = torch.channels_last
"""ALIKED's convolutions in the channels-last layout: the backbone 25 % faster on this CPU (oneDNN), the same
outputs (benchmarks/history/learned.md)."""

LIGHTGLUE_LAYERS = 9
"""LightGlue's transformer layers (the checkpoint's ``self_attn.i`` / ``cross_attn.i``)."""


def _load_strict(model: torch.nn.Module, state: dict[str, torch.Tensor], source: str, what: str, *,
                 assign: bool = False) -> None:  # fmt: skip
    """Every parameter and non-derived buffer of ``model`` from ``state``; an unknown key, a missing key or another
    shape raises :class:`LearnedWeightsError` (``assign``: ``state``'s tensors become the model's, not copied)."""
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    check_state_dict_keys(expected, state, LearnedWeightsError, source=source, model=what,
                          optional=DERIVED_BUFFERS[what])  # fmt: skip
    model.load_state_dict(state, strict=False, assign=assign)


def build_aliked(config: LearnedConfig, state: dict[str, torch.Tensor]) -> torch.nn.Module:
    """kornia's ALIKED (``config.detector``, top-k mode: ``config.max_keypoints`` strongest maxima), strictly loaded,
    in evaluation mode, its weights in :data:`ALIKED_LAYOUT`."""
    from kornia.feature import ALIKED

    model = ALIKED(model_name=config.detector, max_num_keypoints=config.max_keypoints, detection_threshold=0.0)
    _load_strict(model, state, config.detector, "aliked")
    return model.to(memory_format=ALIKED_LAYOUT).eval()


def lightglue_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The official checkpoint's keys in kornia's names (``self_attn.i.*`` → ``transformers.i.self_attn.*``, and
    ``cross_attn`` alike)."""
    out = {}
    for k, v in state.items():
        for i in range(LIGHTGLUE_LAYERS):
            for attn in ("self_attn", "cross_attn"):
                if k.startswith(f"{attn}.{i}."):
                    k = f"transformers.{i}.{attn}." + k[len(f"{attn}.{i}.") :]
        out[k] = v
    return out


def build_lightglue(config: LearnedConfig, state: dict[str, torch.Tensor]) -> torch.nn.Module:
    """kornia's LightGlue for ALIKED descriptors (128-D), built without weights (no download), strictly loaded (the
    file's tensors assigned, not copied: 47 MB, a third of the load time), in evaluation mode."""
    from kornia.feature import LightGlue

    conf: dict[str, Any] = {
        **LightGlue.features["aliked"], "weights": None, "depth_confidence": config.depth_confidence,
        "width_confidence": config.width_confidence, "filter_threshold": config.filter_threshold,
    }  # fmt: skip
    model = LightGlue(None, **conf)
    _load_strict(model, lightglue_state(state), "aliked_lightglue", "lightglue", assign=True)
    return model.eval()


class LearnedModels:
    """ALIKED and its LightGlue, loaded (``load_seconds``: the files read, hashed and loaded)."""

    def __init__(self, config: LearnedConfig) -> None:
        t0 = time.perf_counter()
        self.config = config
        self.aliked = build_aliked(config, load_weights(config.detector))
        self.lightglue = build_lightglue(config, load_weights("aliked-lightglue"))
        self.load_seconds = time.perf_counter() - t0
        self.lock = threading.Lock()
        logger.debug("learned matcher loaded in %.2f s", self.load_seconds)


_LOCK = threading.Lock()


@functools.cache
def _cached(config: LearnedConfig, files: tuple[tuple[str, int, int], ...]) -> LearnedModels:
    return LearnedModels(config)


def _files_key(config: LearnedConfig) -> tuple[tuple[str, int, int], ...]:
    """The located files with their size and modification time: another file (or a changed one) is loaded anew."""
    out = []
    for model in (config.detector, "aliked-lightglue"):
        st = (path := locate(model)).stat()
        out.append((str(path), st.st_size, st.st_mtime_ns))
    return tuple(out)


def learned_models(config: LearnedConfig) -> LearnedModels:
    """The models for ``config``, loaded on the first call and kept for the process (per located file).

    Raises:
        LearnedWeightsError: a file is missing, truncated, of another hash or does not fit (nothing is kept).
    """
    if config.detector not in ("aliked-n16",):
        raise LearnedWeightsError(f"unknown learned detector {config.detector!r} (known: aliked-n16)")
    with _LOCK:
        return _cached(config, _files_key(config))
