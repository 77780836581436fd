"""A photo-like sample pair as network input: what ``macsplat export-onnx`` traces a fixed-size graph at and
runs its parity check on (:func:`macsplat_cli.neural.onnx_export.export_onnx`'s ``sample``)."""

from __future__ import annotations

import numpy as np
import torch

from .orbits import orbit_pair
from .raycast import render
from .scenes import make_scene

__all__ = ["sample_pair"]


def sample_pair(size: tuple[int, int], seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A deterministic, photo-like pair at ``size = (W, H)``: a ray-traced room seen from two cameras
    15° apart (texture, edges, depth), so that the network sees what it was trained on. ``[1, 3, H, W]`` each."""
    w, h = size
    scene = make_scene("room", seed)
    cams = orbit_pair("room", 15, width=w, height=h, fov_deg=60.0)
    a, b = (torch.from_numpy(np.ascontiguousarray(render(scene, c).image, np.float32)) for c in cams)
    return a.permute(2, 0, 1)[None].clamp(0, 1).contiguous(), b.permute(2, 0, 1)[None].clamp(0, 1).contiguous()
