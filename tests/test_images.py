"""Image, depth and video writers; photo modes the reader turns into RGB (and alpha)."""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from macsplat_cli.errors import ImageReadError, InputError, OutputPathError
from macsplat_cli.images import load_image, save_depth, save_image, to_uint8, write_video


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


# ------------------------------------------------------------------------------ photo modes (issue 23)
def _patches() -> np.ndarray:
    """Eight flat colour patches (primaries, secondaries, black, white, greys), 8×8 px each. [16, 32, 3] uint8"""
    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 0), (0, 0, 0), (255, 255, 255), (64, 64, 64),
               (200, 120, 40)]  # fmt: skip
    img = np.zeros((16, 32, 3), np.uint8)
    for k, c in enumerate(colours):
        img[8 * (k // 4) : 8 * (k // 4) + 8, 8 * (k % 4) : 8 * (k % 4) + 8] = c
    return img


def _ycck_jpeg(rgb: np.ndarray) -> bytes:
    """A YCCK JPEG (Adobe transform 2, as Photoshop writes CMYK) of ``rgb`` [H, W, 3] uint8, K = 0.

    Adobe's CMYK is stored inverted (255 − ink), and YCCK is the YCbCr transform of the first three stored
    channels inverted again, i.e. of 255 − RGB; Pillow writes the four components as given (its CMYK JPEGs are
    Adobe-inverted, so the components go in inverted) and the Adobe marker's transform byte is set to 2.
    """
    from PIL import Image

    r, g, b = (255.0 - rgb[..., i] for i in range(3))
    y = 0.299 * r + 0.587 * g + 0.114 * b
    cb = 128 - 0.168736 * r - 0.331264 * g + 0.5 * b
    cr = 128 + 0.5 * r - 0.418688 * g - 0.081312 * b
    comp = np.clip(np.rint(np.stack([y, cb, cr, np.full_like(y, 255.0)], -1)), 0, 255).astype(np.uint8)
    im = Image.frombytes("CMYK", (rgb.shape[1], rgb.shape[0]), (255 - comp).tobytes())
    buf = io.BytesIO()
    im.save(buf, "JPEG", quality=100, subsampling=0)
    data = bytearray(buf.getvalue())
    at = data.find(b"Adobe")
    assert at > 0 and data[at + 11] == 0  # APP14: "Adobe", version, flags0, flags1, transform
    data[at + 11] = 2
    return bytes(data)


@pytest.mark.parametrize("kind", ["cmyk-jpeg", "ycck-jpeg", "cmyk-tiff", "palette-png", "palette-tiff"])
def test_cmyk_ycck_and_palette_photos_give_their_rgb_colours(tmp_path: Path, kind: str) -> None:
    """CMYK/YCCK JPEGs (Adobe's inverted CMYK: an inverted decoder would turn red into cyan) and palette images
    come back as their RGB colours (issue 23 asked whether a CMYK JPEG's colours were right: they are)."""
    from PIL import Image

    rgb = _patches()
    path = tmp_path / f"p.{kind.split('-')[1].replace('tiff', 'tif').replace('jpeg', 'jpg')}"
    if kind == "ycck-jpeg":
        path.write_bytes(_ycck_jpeg(rgb))
        assert Image.open(path).mode == "CMYK"
    else:
        im = Image.fromarray(rgb)
        im = im.convert("CMYK") if kind.startswith("cmyk") else im.quantize(8)
        im.save(path, **({"quality": 100, "subsampling": 0} if path.suffix == ".jpg" else {}))
    img = load_image(path)
    assert img.rgb.shape == (16, 32, 3)
    centres = img.rgb[4::8, 4::8] * 255  # the middle of each patch [2, 4, 3]
    np.testing.assert_allclose(centres, rgb[4::8, 4::8].astype(np.float32), atol=3)
    assert img.alpha is None or (img.alpha == 1).all()


@pytest.mark.parametrize("kind", ["la-png", "la-tiff", "grey-png-trns", "palette-png-trns"])
def test_transparency_of_grey_and_palette_photos_becomes_alpha(tmp_path: Path, kind: str) -> None:
    """Grey+alpha and palette+alpha files, and a PNG's transparent colour, keep their transparency (OpenCV drops
    it for the TIFFs and the grey PNG's colour key; before: no alpha, the masked region reconstructed)."""
    from PIL import Image

    grey = np.tile(np.arange(0, 256, 8, dtype=np.uint8), (16, 1))  # [16, 32]
    opaque = np.ones((16, 32), bool)
    opaque[:, :8] = False
    a = np.where(opaque, 255, 0).astype(np.uint8)
    if kind in ("la-png", "la-tiff"):
        im = Image.fromarray(np.dstack([grey, a]), "LA")
    elif kind == "grey-png-trns":  # colour key: grey value 0 is transparent, only the masked region is black
        grey = np.where(opaque, np.maximum(grey, 8), 0).astype(np.uint8)
        im = Image.fromarray(grey, "L")
    else:  # palette entry 0 transparent; entry k is grey 8·k
        im = Image.fromarray(np.where(opaque, np.maximum(grey // 8, 1), 0).astype(np.uint8), "P")
        im.putpalette([v for k in range(256) for v in (min(8 * k, 255),) * 3])
        grey = np.where(opaque, np.maximum(grey, 8), 0).astype(np.uint8)
    path = tmp_path / ("a.tif" if kind.endswith("tiff") else "a.png")
    im.save(path, **({"transparency": 0} if kind.endswith("trns") else {}))
    img = load_image(path)
    assert img.alpha is not None, kind
    np.testing.assert_array_equal(img.alpha > 0.5, opaque)
    np.testing.assert_allclose(img.rgb[opaque] * 255, np.repeat(grey[opaque][:, None], 3, 1), atol=0.5)


def test_sixteen_bit_grey_png_keeps_its_values(tmp_path: Path) -> None:
    """Pillow's "I;16" (16-bit grey) PNG: value/65535 in all three channels."""
    from PIL import Image

    raw = (np.arange(16 * 32, dtype=np.uint32).reshape(16, 32) * 127).astype(np.uint16)
    Image.fromarray(raw).save(tmp_path / "g16.png")
    assert Image.open(tmp_path / "g16.png").mode.startswith("I;16")
    img = load_image(tmp_path / "g16.png")
    assert img.bit_depth == 16 and img.alpha is None
    for c in range(3):
        np.testing.assert_array_equal(img.rgb[..., c], raw.astype(np.float32) / 65535.0)


# ------------------------------------------------------------------------------ the megapixel cap (issue 37 I1)
def _radiance_rle(width: int, height: int) -> bytes:
    """A flat Radiance RGBE image, run-length encoded: a few bytes per row whatever its width."""

    def runs(value: int, n: int) -> bytes:
        out = bytearray()
        while n > 0:
            k = min(127, n)
            out += bytes([128 + k, value])
            n -= k
        return bytes(out)

    row = bytes([2, 2, width >> 8, width & 255]) + b"".join(runs(v, width) for v in (128, 100, 60, 129))
    return b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n" % (height, width) + row * height


def _float_images(width: int, height: int) -> dict[str, bytes]:
    """The formats OpenCV decodes and Pillow cannot size: Radiance HDR, PFM, PAM."""
    rgb = np.full((height, width, 3), 0.5, np.float32)
    files = {".hdr": _radiance_rle(width, height)}
    for ext, img in ((".pfm", rgb), (".pam", (rgb * 255).astype(np.uint8))):
        ok, buf = cv2.imencode(ext, img)
        assert ok
        files[ext] = buf.tobytes()
    return files


@pytest.mark.parametrize("ext", [".hdr", ".pfm", ".pam"])
def test_megapixel_cap_holds_for_formats_pillow_cannot_size(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, ext: str
) -> None:
    """A 1.1 MP photo OpenCV decodes but Pillow cannot size is refused under a 1 MP cap, before decoding, as a
    PNG of that size is; under the cap it loads at its size."""
    path = tmp_path / f"big{ext}"
    path.write_bytes(_float_images(1100, 1000)[ext])
    decoded: list[object] = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a: decoded.append(a))
    monkeypatch.setenv("MACSPLAT_MAX_MEGAPIXELS", "1")
    with pytest.raises(ImageReadError, match=rf"big\{ext}: 1100x1000 is 1\.1 megapixels, above the limit of 1 "):
        load_image(path)
    assert decoded == []
    monkeypatch.undo()
    small = tmp_path / f"small{ext}"
    small.write_bytes(_float_images(40, 30)[ext])
    img = load_image(small)
    assert (img.width, img.height) == (40, 30)


def test_image_whose_size_no_header_gives_is_refused_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Bytes with no size that Pillow or the Radiance/PFM/PAM headers give are not handed to OpenCV."""
    path = tmp_path / "odd.hdr"
    path.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y many +X 10\n" + bytes(64))
    decoded: list[object] = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a: decoded.append(a))
    with pytest.raises(ImageReadError, match=r"odd\.hdr: .*its size cannot be read from its header"):
        load_image(path)
    assert decoded == []


@pytest.mark.parametrize("ext", [".mp4", ".gif"])
def test_video_frame_rates_at_both_ends_of_the_range_are_written(tmp_path: Path, ext: str) -> None:
    """MIN_VIDEO_FPS and MAX_VIDEO_FPS give readable videos in both formats; just outside, InputError and no file
    (below, Pillow's GIF frame duration overflowed and OpenCV's MPEG-4 writer did not open)."""
    from macsplat_cli.images import MAX_VIDEO_FPS, MIN_VIDEO_FPS

    frames = [np.full((16, 24, 3), 40 * i, np.uint8) for i in range(3)]
    for fps in (MIN_VIDEO_FPS, MAX_VIDEO_FPS):
        write_video(tmp_path / f"v{fps:g}{ext}", frames, fps=fps)
    for fps in (MIN_VIDEO_FPS / 2, MAX_VIDEO_FPS * 1.01, float("inf")):
        with pytest.raises(InputError, match="--fps"):
            write_video(tmp_path / f"bad{ext}", frames, fps=fps)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"v{f:g}{ext}" for f in (MIN_VIDEO_FPS, MAX_VIDEO_FPS))
