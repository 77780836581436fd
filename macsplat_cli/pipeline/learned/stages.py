"""The learned matcher in the pipeline's slots: ALIKED in the ``describe`` slot (:class:`LearnedDescriptors`),
LightGlue in the ``matcher`` slot (:class:`LightGlueMatcher`, with the guard of its matches,
:mod:`.guard`), the two as one tier of the pose search (:class:`LearnedTier`).

ALIKED runs on the photo's detail image at ``detect_size`` on the long side (never upsampled), without its dense
descriptor map (:func:`.aliked_sparse.aliked_sparse`: kornia's forward, 0.5 GB less memory); its keypoints
(pixel centres at integers, kornia's convention) are mapped to working-resolution pixels (centres at +0.5).
LightGlue needs each image's size to normalise the keypoints: :class:`LearnedFeatures` carries it.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..slots import DescribeStage, MatchStage, PairPass
from ..types import Features, Matches, View
from .aliked_sparse import aliked_sparse
from .config import LearnedConfig
from .guard import learned_doubts
from .models import LearnedModels, learned_models
from .weights import WEIGHTS, LearnedWeightsError, locate

__all__ = ["LearnedDescriptors", "LearnedFeatures", "LearnedTier", "LightGlueMatcher", "learned_tier"]

logger = logging.getLogger(__name__)


@dataclass
class LearnedFeatures(Features):
    """:class:`Features` with what LightGlue needs besides: ``image_wh`` the (width, height) of the image the
    keypoints were detected on, ``to_detect`` the (x, y) scale from working pixels to that image's."""

    image_wh: tuple[int, int] = (0, 0)
    to_detect: tuple[float, float] = (1.0, 1.0)

    def detect_xy(self) -> np.ndarray:
        """The keypoints in the detection image's pixels, centres at integers. [M, 2] float64"""
        return self.xy * np.array(self.to_detect) - 0.5


class LearnedDescriptors:
    """ALIKED keypoints and descriptors of each view (the ``describe`` slot); ``conf`` is the keypoint score."""

    def __init__(self, config: LearnedConfig) -> None:
        self.config = config
        self.name = f"learned:{config.detector}"

    def _one(self, models: LearnedModels, view: View) -> LearnedFeatures:
        cfg = self.config
        src = view.detail if view.detail is not None else view.image
        h_src, w_src = src.shape[:2]
        s = min(1.0, cfg.detect_size / max(w_src, h_src))
        w_d, h_d = max(1, round(w_src * s)), max(1, round(h_src * s))
        img = src if (w_d, h_d) == (w_src, h_src) else cv2.resize(src, (w_d, h_d), interpolation=cv2.INTER_AREA)
        x = torch.from_numpy(np.ascontiguousarray(img, np.float32)).permute(2, 0, 1)[None]
        with torch.inference_mode(), models.lock:
            kp_t, desc_t, conf_t = aliked_sparse(models.aliked, x)
        kp = kp_t.double().numpy()
        to_work = np.array([view.width / w_d, view.height / h_d])
        xy = (kp + 0.5) * to_work
        desc = desc_t.float().numpy()
        conf = conf_t.float().numpy()
        if not view.mask.all():
            col = np.clip(xy[:, 0].astype(np.int64), 0, view.width - 1)
            row = np.clip(xy[:, 1].astype(np.int64), 0, view.height - 1)
            keep = view.mask[row, col]
            xy, desc, conf = xy[keep], desc[keep], conf[keep]
        return LearnedFeatures(xy=xy, desc=np.ascontiguousarray(desc), conf=np.ascontiguousarray(conf),
                               image_wh=(w_d, h_d), to_detect=(1 / to_work[0], 1 / to_work[1]))  # fmt: skip

    def __call__(self, views: Sequence[View], pair: PairPass = None) -> list[Features]:
        models = learned_models(self.config)
        return [self._one(models, v) for v in views]


class LightGlueMatcher:
    """LightGlue on two views' :class:`LearnedFeatures` (the ``matcher`` slot): its mutual matches above
    ``filter_threshold``; ``conf`` is LightGlue's match score, ``counts["lightglue"]`` their number."""

    def __init__(self, config: LearnedConfig) -> None:
        self.config = config
        self.name = "learned:lightglue"

    def __call__(self, f0: Features, f1: Features) -> Matches:
        if not isinstance(f0, LearnedFeatures) or not isinstance(f1, LearnedFeatures):
            raise TypeError("LightGlueMatcher matches LearnedFeatures (ALIKED), not other descriptors")
        empty = np.zeros(0, np.int64)
        if len(f0) == 0 or len(f1) == 0:
            return Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.float32), empty, empty, {"lightglue": 0})
        models = learned_models(self.config)

        def side(f: LearnedFeatures) -> dict[str, torch.Tensor]:
            return {
                "keypoints": torch.from_numpy(f.detect_xy()).float()[None],
                "descriptors": torch.from_numpy(f.desc)[None],
                "image_size": torch.tensor([f.image_wh], dtype=torch.float32),
            }

        with torch.inference_mode(), models.lock:
            out = models.lightglue({"image0": side(f0), "image1": side(f1)})
        pairs = out["matches"][0].numpy().astype(np.int64)
        scores = out["scores"][0].float().numpy()
        idx0, idx1 = pairs[:, 0], pairs[:, 1]
        return Matches(f0.xy[idx0], f1.xy[idx1], scores.astype(np.float32), idx0, idx1, {"lightglue": len(idx0)})

    def doubts(self, features: list[Features], verified: Matches, final: Matches, log10_nfa: float | None) -> list[str]:
        """Why a pose from these matches is refused besides the acceptance's checks (:func:`.guard.learned_doubts`).
        The pose search asks the matcher that gave the pose, whichever tier it ran in (``--matcher auto``'s last
        tier, ``--matcher aliked``'s only one): the guard goes wherever LightGlue's matches go."""
        return learned_doubts(features, verified, final, log10_nfa)


def _no_load() -> None:
    return None


@dataclass
class LearnedTier:
    """The learned matcher as a tier of the pose search: its descriptors, its matcher, and ``load`` (loads the
    models once, timed as its own stage by the search; the describe and match stages would load them otherwise)."""

    describe: DescribeStage
    match: MatchStage
    config: LearnedConfig
    load: Callable[[], object] = _no_load

    @property
    def name(self) -> str:
        return f"{self.describe.name}+{self.match.name}"


_WARNED: set[str] = set()


def learned_tier(config: LearnedConfig, *, required: bool) -> LearnedTier | None:
    """The learned tier when its weight files are installed (located, not yet read: the files are hash-checked
    when the tier first runs); otherwise None, said once per process (``required``: raise instead).

    Raises:
        LearnedWeightsError: ``required`` and a file is missing (the message gives the pip command).
    """
    try:
        for model in (config.detector, "aliked-lightglue"):
            if model not in WEIGHTS:
                raise LearnedWeightsError(f"unknown learned detector {model!r} (known: aliked-n16)")
            locate(model)
    except LearnedWeightsError as e:
        if required:
            raise
        if str(e) not in _WARNED:
            _WARNED.add(str(e))
            logger.info("--matcher auto: SIFT only (%s)", e)
        return None
    return LearnedTier(LearnedDescriptors(config), LightGlueMatcher(config), config,
                       load=functools.partial(learned_models, config))  # fmt: skip
