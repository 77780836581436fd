"""From a data folder to the training and validation pairs of ``macsplat train``.

Validation pairs come from the held-out split when the data set has one (ScanNet++ ``nvs_sem_val``, the
scenes Splatt3R evaluates on); otherwise ``val_pairs`` candidate pairs are held out (drawn with the seed),
and the training pairs are the rest. Scenes named in ``exclude`` are left out of both (the MAC-Splat release leaves
out ScanNet++ ``303745abc7`` and ``cc5237fd77``). The pairs stay compact (:class:`~.data.CandidatePairs`:
``O(N²)`` memory for a scene of ``N`` frames, targets derived per sample), so a scene of thousands of frames starts
at once.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..datasets import EvalDataset, detect_layout, load_dataset
from ..errors import DatasetError
from .data import PairDataset, PairSamplingConfig, candidate_pairs

__all__ = ["load_training_data"]

logger = logging.getLogger(__name__)

VAL_SPLIT = "nvs_sem_val"


def load_training_data(
    root: Path,
    *,
    layout: str = "auto",
    split: str = "nvs_sem_train",
    scenes: list[str] | None = None,
    sampling: PairSamplingConfig | None = None,
    val_pairs: int = 8,
    seed: int = 0,
    exclude: tuple[str, ...] = (),
) -> tuple[PairDataset, PairDataset | None, dict[str, Any]]:
    """The training and validation :class:`PairDataset` of a data folder, and a summary for ``run.json``.

    Raises:
        DatasetError: a missing, empty or malformed data set, or one without a valid pair.
    """
    sampling = sampling or PairSamplingConfig()
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"--data {root}: no such folder")
    kind = detect_layout(root) if layout == "auto" else layout
    dataset = _without(load_dataset(root, kind, scannetpp_split=split, scenes=scenes), exclude)
    pairs = candidate_pairs(dataset, sampling)
    once = dataclasses.replace(sampling, per_scene=None, samples_per_epoch=None)  # validation: each pair once
    val_ds: PairDataset | None = None
    has_val_split = kind == "scannetpp" and any(
        (root / d / "splits" / f"{VAL_SPLIT}.txt").is_file() for d in (".", "raw")
    )
    if has_val_split and scenes is None:
        val_set = _without(load_dataset(root, kind, scannetpp_split=VAL_SPLIT), exclude)
        val_candidates = candidate_pairs(val_set, sampling)
        rng = np.random.default_rng(seed)
        keep = np.sort(rng.permutation(len(val_candidates))[:val_pairs])
        val_ds = PairDataset(val_set, val_candidates.subset(keep), once, seed=seed, depth=True)
        train_pairs = pairs
    elif len(pairs) > 1:
        n_val = min(val_pairs, max(1, len(pairs) // 5))
        held = np.zeros(len(pairs), dtype=bool)
        held[np.random.default_rng(seed).permutation(len(pairs))[:n_val]] = True
        train_pairs = pairs.subset(np.flatnonzero(~held))
        val_ds = PairDataset(dataset, pairs.subset(np.flatnonzero(held)), once, seed=seed, depth=True)
    else:
        train_pairs = pairs
        logger.warning("only one training pair: no validation (best.pt is the last model)")
    train_ds = PairDataset(dataset, train_pairs, sampling, seed=seed, depth=True)
    info = {
        "root": str(root),
        "layout": kind,
        "scenes": len(dataset.scenes),
        "train_pairs": len(train_pairs),
        "val_pairs": 0 if val_ds is None else len(val_ds),
        "validation": "split " + VAL_SPLIT if has_val_split and scenes is None else "held-out pairs",
        "sampling": {
            "coverage": list(sampling.coverage),
            "targets": sampling.targets,
            "size": list(sampling.size),
            "crop": sampling.crop,
            "per_scene": sampling.per_scene,
        },
        "excluded_scenes": list(exclude),
    }
    return train_ds, val_ds, info


def _without(dataset: EvalDataset, exclude: tuple[str, ...]) -> EvalDataset:
    """``dataset`` without the scenes named in ``exclude`` (refused when that leaves none)."""
    if not exclude:
        return dataset
    kept = [s for s in dataset.scenes if s.name not in exclude]
    if not kept:
        raise DatasetError(f"{dataset.root}: no scene left once {', '.join(exclude)} are excluded")
    return dataclasses.replace(dataset, scenes=kept)
