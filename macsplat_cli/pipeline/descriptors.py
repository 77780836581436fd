"""Stage 2: descriptors with a confidence, behind one interface.

A descriptor backend is a callable ``View → Features``. The classical backend detects
SIFT keypoints and describes them with RootSIFT (SIFT, L1-normalised, square-rooted:
cosine similarity becomes the Hellinger kernel, which matches better than L2 on SIFT).

Keypoints are detected on a higher-resolution copy of the photo (``detect_size``, 768 px
on the long side by default, never upsampled) and mapped to working-resolution pixels:
sub-pixel precision at the working size improves the pose. The defaults come from a
measurement on real indoor and object-centric pairs (co3d, ICL-NUIM, NYU, Middlebury,
15 pairs from 4° to 83°): SIFT's contrast threshold is the lever on low-texture photos
(0.04 gave 270–700 keypoints and 6 failed pairs; 0.005 gave 2 failures, the two widest),
RootSIFT beats plain SIFT, and VGG/BoostDesc/TEBLID on SIFT keypoints were no better
for 5–20× the time (VGG) or failed more often (TEBLID, BoostDesc).

SIFT has no learned confidence: every descriptor gets confidence 1 here, and the
matching stage derives one from its distinctiveness against the other view
(:mod:`.matching`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from .types import Features, View

__all__ = ["DescriptorBackend", "SiftConfig", "SiftDescriptors"]

logger = logging.getLogger(__name__)


class DescriptorBackend(Protocol):
    """A per-view descriptor backend, ``View → Features``; ``name`` identifies the backend in the report.

    The pipeline's ``describe`` slot takes both views (and the ``pair`` stage's output, for a two-view
    network); a per-view backend goes there wrapped in :class:`~.stages.PerViewDescriptors`, which describes the
    views in parallel threads when the backend sets ``thread_safe = True``.
    """

    name: str

    def __call__(self, view: View) -> Features: ...


CONTRAST_THRESHOLD = 0.005
"""SIFT's contrast threshold, the lever on low-texture photos: on 15 real pairs OpenCV's 0.04 gave 270–700
keypoints and 6 failed pairs, 0.005 two (the widest); see benchmarks/history/settings.md."""


@dataclass
class SiftConfig:
    """Args:
    max_keypoints: keep at most this many keypoints (strongest first); 0 = all.
    detect_size: long side of the image SIFT runs on, px (capped at the photo's size); 0 = the photo's.
    root: RootSIFT (True) or plain L2-normalised SIFT.
    affine: affine-simulated SIFT (ASIFT, ``cv2.AffineFeature``): many tilted views of the
        image, for wide baselines. Slower; used as a fallback.
    max_tilt: largest simulated tilt for ``affine``.
    """

    max_keypoints: int = 8000
    detect_size: int = 768
    root: bool = True
    affine: bool = False
    max_tilt: float = 3.0


class SiftDescriptors:
    """Classical descriptors: SIFT keypoints with RootSIFT descriptors (confidence 1).

    Thread-safe (a detector per call): :class:`~.stages.PerViewDescriptors` describes both views at once.
    """

    thread_safe = True

    def __init__(self, config: SiftConfig | None = None) -> None:
        self.config = config or SiftConfig()
        self.name = "classical:" + ("a" if self.config.affine else "") + ("rootsift" if self.config.root else "sift")

    def _detector(self) -> cv2.Feature2D:
        cfg = self.config
        if not cfg.affine:
            return cv2.SIFT.create(nfeatures=cfg.max_keypoints, contrastThreshold=CONTRAST_THRESHOLD)
        # AffineFeature applies nfeatures per simulated view; a few hundred each is plenty.
        sift = cv2.SIFT.create(nfeatures=max(cfg.max_keypoints // 16, 200), contrastThreshold=4 * CONTRAST_THRESHOLD)
        return cv2.AffineFeature.create(sift, maxTilt=int(cfg.max_tilt))

    def __call__(self, view: View) -> Features:
        cfg = self.config
        src = view.detail if view.detail is not None else view.image
        h_src, w_src = src.shape[:2]
        s = min(1.0, cfg.detect_size / max(w_src, h_src)) if cfg.detect_size else 1.0
        w_d, h_d = max(1, round(w_src * s)), max(1, round(h_src * s))
        img = src if (w_d, h_d) == (w_src, h_src) else cv2.resize(src, (w_d, h_d), interpolation=cv2.INTER_AREA)
        gray = img @ np.array([0.299, 0.587, 0.114], np.float32)
        u8 = np.clip(np.rint(gray * 255.0), 0, 255).astype(np.uint8)
        mask = None
        if not view.mask.all():
            mask = cv2.resize(view.mask.astype(np.uint8), (w_d, h_d), interpolation=cv2.INTER_NEAREST)
        kps, raw = self._detector().detectAndCompute(u8, mask)
        if raw is None or len(kps) == 0:
            empty = np.zeros(0, np.float32)
            return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32), empty, scale=empty)
        desc = np.array(raw, np.float32)
        if cfg.root:
            desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)
            desc = np.sqrt(desc)
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        # OpenCV keypoints have pixel centres on integers; ours are at +0.5. Scale per axis
        # from the detection image to the working image (exact with +0.5 centres).
        xy = np.array([k.pt for k in kps], np.float64) + 0.5
        xy *= np.array([view.width / w_d, view.height / h_d])
        size = np.array([k.size for k in kps], np.float64) * view.width / w_d
        return Features(xy=xy, desc=desc, conf=np.ones(len(kps), np.float32), scale=size)
