"""Image, depth and video writers."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from macsplat_cli.errors import InputError, OutputPathError
from macsplat_cli.images import save_depth, save_image, to_uint8, write_video


def test_to_uint8_clamps_and_rounds() -> None:
    x = torch.tensor([[[-0.5, 0.5, 2.0]], [[float("nan"), 1 / 255 * 0.49, 1 / 255 * 0.51]]])
    assert to_uint8(x).tolist() == [[[0, 128, 255]], [[0, 0, 1]]]


@pytest.mark.parametrize("ext", [".png", ".jpg", ".webp", ".tif", ".bmp"])
def test_save_image_formats(tmp_path: Path, ext: str) -> None:
    img = np.zeros((8, 10, 3), np.float32)
    img[..., 0] = 1.0  # pure red
    save_image(tmp_path / f"a{ext}", img)
    back = cv2.imread(str(tmp_path / f"a{ext}"))[..., ::-1]
    assert back.shape == (8, 10, 3) and back[..., 0].min() > 240 and back[..., 2].max() < 15
    assert [p.name for p in tmp_path.iterdir()] == [f"a{ext}"]


def test_save_depth_formats(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    d = np.array([[0.0, 1.2345], [70.0, float("nan")]], np.float32)
    expected = np.array([[0.0, 1.2345], [70.0, 0.0]], np.float32)  # non-finite → 0 (no depth)
    save_depth(tmp_path / "d.npy", d)
    np.testing.assert_array_equal(np.load(tmp_path / "d.npy"), expected)
    save_depth(tmp_path / "d.tif", d)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "d.tif"), cv2.IMREAD_UNCHANGED), expected)
    save_depth(tmp_path / "d.png", d)
    png = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and png.tolist() == [[0, 1234], [65535, 0]]  # 1234.5 rounds to even
    assert "clipped" in caplog.text


def test_unsupported_formats_and_paths(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unsupported image format"):
        save_image(tmp_path / "a.gifx", np.zeros((2, 2, 3)))
    with pytest.raises(InputError, match="unsupported depth format"):
        save_depth(tmp_path / "a.jpg", np.zeros((2, 2)))
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputPathError, match="is a file"):
        save_image(tmp_path / "file" / "a.png", np.zeros((2, 2, 3)))
    with pytest.raises(InputError, match="no frames"):
        write_video(tmp_path / "v.mp4", [])
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


@pytest.mark.parametrize("ext", [".mp4", ".gif"])
def test_write_video(tmp_path: Path, ext: str) -> None:
    frames = [np.full((16, 24, 3), 20 * i, np.uint8) for i in range(6)]
    write_video(tmp_path / f"v{ext}", frames, fps=12)
    cap = cv2.VideoCapture(str(tmp_path / f"v{ext}"))
    n = 0
    while True:
        ok, f = cap.read()
        if not ok:
            break
        assert f.shape == (16, 24, 3)
        assert abs(int(f.mean()) - 20 * n) <= 4
        n += 1
    cap.release()
    assert n == 6
    assert [p.name for p in tmp_path.iterdir()] == [f"v{ext}"]
