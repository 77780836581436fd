"""Stage 2: descriptors with a confidence, behind one interface.

A descriptor backend is a callable ``View → Features``. The classical backend detects
SIFT keypoints and describes them with RootSIFT (SIFT, L1-normalised, square-rooted:
cosine similarity becomes the Hellinger kernel, which matches better than L2 on SIFT).

Confidence: the *distinctiveness* of each descriptor within its own image,
``c = 1 − max_{k≠i} cos(f_i, f_k)`` (keypoints at the same location, SIFT's extra
orientations, are not counted as rivals). A descriptor that resembles another one in the
same image (repetitive texture) is ambiguous whatever it matches, so the joint
confidence ``c0·c1`` of the matching stage gates it, playing the role of MASt3R's
descriptor confidence.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
import torch

from .types import Features, View

__all__ = ["DescriptorBackend", "SiftConfig", "SiftDescriptors", "distinctiveness"]

logger = logging.getLogger(__name__)


class DescriptorBackend(Protocol):
    """``View → Features``; ``name`` identifies the backend in the report."""

    name: str

    def __call__(self, view: View) -> Features: ...


@dataclass
class SiftConfig:
    """Args:
    max_keypoints: keep at most this many keypoints (strongest first); 0 = all.
    detect_size: long side of the image SIFT runs on (0 = the working size).
    root: RootSIFT (True) or plain L2-normalised SIFT.
    contrast_threshold: SIFT's contrast threshold (lower finds more keypoints in flat images).
    """

    max_keypoints: int = 4000
    detect_size: int = 0
    root: bool = True
    contrast_threshold: float = 0.02


def distinctiveness(desc: np.ndarray, xy: np.ndarray, *, max_block_elems: int = 1 << 24) -> np.ndarray:
    """``1 − max cosine similarity`` to any other descriptor more than 1.5 px away. [M]"""
    m = desc.shape[0]
    if m < 2:
        return np.ones(m, np.float32)
    a = torch.from_numpy(np.ascontiguousarray(desc, np.float32))
    p = torch.from_numpy(np.ascontiguousarray(xy, np.float32))
    rows = max(1, max_block_elems // m)
    best = torch.empty(m)
    for s in range(0, m, rows):
        sim = a[s : s + rows] @ a.T
        same_place = torch.cdist(p[s : s + rows], p) < 1.5
        sim[same_place] = -1.0
        best[s : s + rows] = sim.max(dim=1).values
    return (1.0 - best.clamp(-1.0, 1.0)).numpy().astype(np.float32)


class SiftDescriptors:
    """Classical descriptors: SIFT keypoints, RootSIFT descriptors, distinctiveness confidence."""

    def __init__(self, config: SiftConfig | None = None) -> None:
        self.config = config or SiftConfig()
        self.name = "classical:" + ("rootsift" if self.config.root else "sift")

    def __call__(self, view: View) -> Features:
        cfg = self.config
        img = view.gray
        scale = 1.0
        if cfg.detect_size and cfg.detect_size != max(view.width, view.height):
            scale = cfg.detect_size / max(view.width, view.height)
            img = cv2.resize(img, (round(view.width * scale), round(view.height * scale)), interpolation=cv2.INTER_AREA)
        u8 = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
        mask = None
        if not view.mask.all():
            mask = cv2.resize(view.mask.astype(np.uint8), (u8.shape[1], u8.shape[0]), interpolation=cv2.INTER_NEAREST)
        sift = cv2.SIFT_create(nfeatures=cfg.max_keypoints, contrastThreshold=cfg.contrast_threshold)
        kps, desc = sift.detectAndCompute(u8, mask)
        if desc is None or len(kps) == 0:
            return Features(
                np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros(0, np.float32), scale=np.zeros(0)
            )
        desc = desc.astype(np.float32)
        if cfg.root:
            desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)
            desc = np.sqrt(desc)
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        # OpenCV keypoints have pixel centres on integers; ours are at +0.5.
        xy = (np.array([k.pt for k in kps], np.float64) + 0.5) / scale
        size = np.array([k.size for k in kps], np.float64) / scale
        conf = distinctiveness(desc, xy)
        return Features(xy=xy, desc=desc, conf=conf, scale=size)
