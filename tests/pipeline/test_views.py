"""Stage 1: photos → views at the working size, with intrinsics by precedence (file > focal > EXIF > prior)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from macsplat_cli.cameras import Camera, CameraSet, save_cameras
from macsplat_cli.errors import CameraFileError, ImageReadError, InputError
from macsplat_cli.images import load_image
from macsplat_cli.pipeline.views import ViewConfig, load_views, prior_focal, working_size

EXIF_ORIENTATION, EXIF_IFD, EXIF_FOCAL_35MM = 0x0112, 0x8769, 0xA405


def _pattern(width: int, height: int, seed: int = 0) -> np.ndarray:
    """Smooth, position-dependent 8-bit colours (survive JPEG, identify orientation). [H, W, 3] uint8"""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    rgb = np.stack([x / width, y / height, 0.5 + 0.4 * np.sin(seed + (x + 2 * y) / 23.0)], -1)
    return np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8)


def _write_png(path: Path, rgb: np.ndarray) -> Path:
    Image.fromarray(rgb).save(path)
    return path


def _write_jpeg(path: Path, rgb: np.ndarray, *, orientation: int | None = None, focal_35mm: int | None = None) -> Path:
    exif = Image.Exif()
    if orientation is not None:
        exif[EXIF_ORIENTATION] = orientation
    if focal_35mm is not None:
        exif.get_ifd(EXIF_IFD)[EXIF_FOCAL_35MM] = focal_35mm
    Image.fromarray(rgb).save(path, quality=95, exif=exif)
    return path


def _camera(name: str, width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> Camera:
    return Camera(name, width, height, np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), np.eye(4))


# float64 intrinsics rescaled to the working size: f·(w/W) and (c)·(w/W) are 2 roundings on each side (the library's
# and the test's expression), so rescaled entries agree to 4u relative; zeros and ones stay exact
K_RTOL = 4 * np.finfo(np.float64).eps / 2
# The test's EXIF focal uses a 43.27 mm full-frame diagonal; the library the exact √(36² + 24²) = 43.2666 mm:
# 7.8e-5 relative, not rounding
EXIF_RTOL = abs(43.27 / math.hypot(36.0, 24.0) - 1) + 4 * np.finfo(np.float64).eps / 2


def _K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


# ------------------------------------------------------------------------------------ working size
@pytest.mark.parametrize(
    ("width", "height", "size", "expected"),
    [
        (4000, 3000, 512, (512, 384)),  # landscape
        (3000, 4000, 512, (384, 512)),  # portrait
        (1920, 1080, 512, (512, 288)),
        (1080, 1920, 768, (432, 768)),
        (741, 500, 512, (512, 352)),  # 345.5 rounds to 352
        (640, 480, 1024, (640, 480)),  # smaller than the working size: not upsampled
        (64, 64, 512, (64, 64)),
    ],
)
def test_working_size_examples(width: int, height: int, size: int, expected: tuple[int, int]) -> None:
    """Long side scaled to ``size`` (not up), each side rounded to a multiple of 16."""
    assert working_size(width, height, size) == expected


@given(
    width=st.integers(64, 6000),
    height=st.integers(64, 6000),
    size=st.sampled_from([256, 384, 512, 768, 1024]),
)
def test_working_size_properties(width: int, height: int, size: int) -> None:
    """Multiples of 16; the long side stays the long side; with a downscale the long side is ``size``."""
    w, h = working_size(width, height, size)
    assert w % 16 == 0 and h % 16 == 0 and w >= 16 and h >= 16
    assert max(w, h) <= size
    if width > height:
        assert w >= h
    elif height > width:
        assert h >= w
    if max(width, height) >= size:
        assert max(w, h) == size  # the sizes tried are multiples of 16
    s = min(1.0, size / max(width, height))
    for side, original in ((w, width), (h, height)):
        # the nearest multiple of 16 (at least 16), or the one below when rounding up would upsample
        # (original·s is 2 roundings of a value ≤ size: ≤ 2·eps·original·s off the exact half-way point)
        nearest = abs(side - original * s) <= 8 + 2 * np.finfo(float).eps * original * s
        nearest = nearest or (side == 16 and original * s < 16)
        assert nearest or side == (original // 16) * 16


@pytest.mark.parametrize(("width", "height"), [(120, 90), (1000, 760)])
def test_working_size_never_upsamples(width: int, height: int) -> None:
    """Neither side of the working image exceeds the photo's (the module promises the scale is never up)."""
    w, h = working_size(width, height, 1024)
    assert w <= width and h <= height


# ------------------------------------------------------------------------------------ intrinsics precedence
@pytest.fixture
def photos(tmp_path: Path) -> list[Path]:
    """Two 1000 × 700 JPEGs with an EXIF 35 mm focal of 28 mm."""
    return [
        _write_jpeg(tmp_path / f"{name}.jpg", _pattern(1000, 700, i), focal_35mm=28)
        for i, name in enumerate(("a", "b"))
    ]


def test_intrinsics_file_one_shared_camera(tmp_path: Path, photos: list[Path]) -> None:
    """One camera in the file serves both photos; K is rescaled per axis to the working size, exactly."""
    cam = _camera("any", 2000, 1400, 1800.0, 1750.0, 990.0, 710.0)
    save_cameras(tmp_path / "cams.json", CameraSet([cam]))
    views = load_views(photos, ViewConfig(size=512, intrinsics=tmp_path / "cams.json", focal=900.0))
    sx, sy = 512 / 2000, 352 / 1400
    for v in views:
        assert (v.width, v.height) == (512, 352) and v.original_size == (1000, 700)
        assert v.intrinsics_source == "file"  # the file wins over --focal and EXIF
        np.testing.assert_allclose(v.K, _K(1800.0 * sx, 1750.0 * sy, 990.0 * sx, 710.0 * sy), rtol=K_RTOL, atol=0)


def test_intrinsics_file_cameras_matched_by_name(tmp_path: Path, photos: list[Path]) -> None:
    """Two cameras, listed in the other order and named by file name or stem, go to their own photos."""
    cam_b = _camera("b.jpg", 1000, 700, 700.0, 700.0, 480.0, 360.0)
    cam_a = _camera("a", 1000, 700, 900.0, 910.0, 510.0, 340.0)
    save_cameras(tmp_path / "cams.json", CameraSet([cam_b, cam_a]))
    va, vb = load_views(photos, ViewConfig(size=512, intrinsics=tmp_path / "cams.json"))
    sx, sy = 512 / 1000, 352 / 700
    np.testing.assert_allclose(va.K, _K(900.0 * sx, 910.0 * sy, 510.0 * sx, 340.0 * sy), rtol=K_RTOL, atol=0)
    np.testing.assert_allclose(vb.K, _K(700.0 * sx, 700.0 * sy, 480.0 * sx, 360.0 * sy), rtol=K_RTOL, atol=0)
    assert va.intrinsics_source == vb.intrinsics_source == "file"


def test_intrinsics_file_wrong_camera_count(tmp_path: Path, photos: list[Path]) -> None:
    """Three unnamed cameras for two photos cannot be assigned."""
    cams = [_camera(f"c{i}", 1000, 700, 800.0, 800.0, 500.0, 350.0) for i in range(3)]
    save_cameras(tmp_path / "cams.json", CameraSet(cams))
    with pytest.raises(CameraFileError, match="3 cameras for 2 photos"):
        load_views(photos, ViewConfig(intrinsics=tmp_path / "cams.json"))


def test_intrinsics_file_naming_one_photo_but_not_the_other(tmp_path: Path, photos: list[Path]) -> None:
    """Issue 37 K1: a camera named after ``a.jpg`` and one named after no photo: not matched by order (``b.jpg``
    took the stranger), refused naming the photo without a camera."""
    cams = [_camera("a", 1000, 700, 900.0, 900.0, 500.0, 350.0), _camera("z", 1000, 700, 700.0, 700.0, 500.0, 350.0)]
    save_cameras(tmp_path / "cams.json", CameraSet(cams))
    with pytest.raises(CameraFileError, match=r"cams\.json: no camera named after 'b\.jpg'"):
        load_views(photos, ViewConfig(intrinsics=tmp_path / "cams.json"))


@pytest.mark.parametrize(
    ("cam_size", "hint"),
    [((800, 800), False), ((700, 1000), True), ((1000, 720), False)],  # 1000 × 720: aspect off by 2.9 %
)
def test_intrinsics_file_that_does_not_fit(
    tmp_path: Path, photos: list[Path], cam_size: tuple[int, int], hint: bool
) -> None:
    """A camera whose aspect ratio differs from the photo's by > 1 % is refused; a rotated one gets a hint."""
    w, h = cam_size
    save_cameras(tmp_path / "cams.json", CameraSet([_camera("c", w, h, 800.0, 800.0, w / 2, h / 2)]))
    with pytest.raises(CameraFileError, match="do not fit") as info:
        load_views(photos, ViewConfig(intrinsics=tmp_path / "cams.json"))
    assert "cams.json" in str(info.value) and f"{w}x{h}" in str(info.value)
    assert ("rotated?" in str(info.value)) is hint


def test_intrinsics_file_that_fits_within_one_percent(tmp_path: Path, photos: list[Path]) -> None:
    """A camera for a slightly cropped size (aspect within 1 %) is accepted and rescaled per axis."""
    save_cameras(tmp_path / "cams.json", CameraSet([_camera("c", 2000, 1396, 1500.0, 1500.0, 1000.0, 698.0)]))
    v = load_views(photos[:1], ViewConfig(size=512, intrinsics=tmp_path / "cams.json"))[0]
    np.testing.assert_allclose(v.K, _K(1500 * 512 / 2000, 1500 * 352 / 1396, 256.0, 176.0), rtol=K_RTOL, atol=0)


def test_intrinsics_file_principal_point_outside(tmp_path: Path, photos: list[Path]) -> None:
    """A principal point outside the image is refused."""
    save_cameras(tmp_path / "cams.json", CameraSet([_camera("c", 1000, 700, 800.0, 800.0, 1200.0, 350.0)]))
    with pytest.raises(CameraFileError, match="principal point outside"):
        load_views(photos, ViewConfig(intrinsics=tmp_path / "cams.json"))


def test_focal_beats_exif(photos: list[Path]) -> None:
    """``focal`` (pixels of the original photo) wins over EXIF; it is scaled per axis like K."""
    views = load_views(photos, ViewConfig(size=512, focal=1234.0))
    sx, sy = 512 / 1000, 352 / 700
    for v in views:
        assert v.intrinsics_source == "focal"
        np.testing.assert_allclose(v.K, _K(1234.0 * sx, 1234.0 * sy, 256.0, 176.0), rtol=K_RTOL, atol=0)


@pytest.mark.parametrize("focal", [0.0, -5.0, math.nan, math.inf])
def test_bad_focal(photos: list[Path], focal: float) -> None:
    """A non-positive or non-finite focal is an input error."""
    with pytest.raises(InputError, match="--focal must be a positive number"):
        load_views(photos, ViewConfig(focal=focal))


def test_exif_35mm_focal(photos: list[Path]) -> None:
    """EXIF FocalLengthIn35mmFilm = 28: f = 28 · diagonal / 43.27 mm (original pixels), scaled to the working size."""
    views = load_views(photos, ViewConfig(size=512))
    f = 28.0 * math.hypot(1000, 700) / 43.27
    for v in views:
        assert v.intrinsics_source == "exif"
        np.testing.assert_allclose(v.K, _K(f * 512 / 1000, f * 352 / 700, 256.0, 176.0), rtol=EXIF_RTOL, atol=0)


def test_prior_when_exif_is_ignored_or_absent(tmp_path: Path, photos: list[Path]) -> None:
    """``use_exif=False`` or no EXIF: 60° (``prior_fov_deg``) across the long side, landscape and portrait."""
    v = load_views(photos[:1], ViewConfig(size=512, use_exif=False))[0]
    f = 1000 / (2 * math.tan(math.radians(30)))
    assert v.intrinsics_source == "prior" and f == pytest.approx(prior_focal(1000, 700), rel=K_RTOL, abs=0)
    np.testing.assert_allclose(v.K, _K(f * 512 / 1000, f * 352 / 700, 256.0, 176.0), rtol=K_RTOL, atol=0)

    portrait = _write_png(tmp_path / "p.png", _pattern(300, 400))
    v = load_views([portrait], ViewConfig(size=256, prior_fov_deg=50.0))[0]
    f = 400 / (2 * math.tan(math.radians(25)))
    assert v.intrinsics_source == "prior" and (v.width, v.height) == (192, 256)
    np.testing.assert_allclose(v.K, _K(f * 192 / 300, f * 256 / 400, 96.0, 128.0), rtol=K_RTOL, atol=0)


def test_k_rescaling_is_exact_per_axis(tmp_path: Path) -> None:
    """With +0.5 pixel centres, scaling K per axis maps the photo's corners and centre to the working image's:
    a ray through the original pixel (u, v) goes through (u·w/W, v·h/H) at the working size."""
    photo = _write_png(tmp_path / "x.png", _pattern(1000, 740))  # 1000 × 740 → 512 × 384: sx ≠ sy
    cam = _camera("x", 1000, 740, 880.0, 870.0, 503.0, 371.0)
    save_cameras(tmp_path / "cams.json", CameraSet([cam]))
    v = load_views([photo], ViewConfig(size=512, intrinsics=tmp_path / "cams.json"))[0]
    assert (v.width, v.height) == (512, 384)
    uv = np.array([[0.0, 0.0], [1000.0, 740.0], [500.0, 370.0], [0.5, 0.5], [999.5, 739.5]])
    rays = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(cam.K).T
    back = rays @ v.K.T
    # a 3×3 inverse and two 3-term products of pixel coordinates ≤ 1000 (K well conditioned: f ≈ cx): ≤ γ₁₆·1000
    np.testing.assert_allclose(back[:, :2], uv * [512 / 1000, 384 / 740], rtol=0, atol=16 * 1000 * np.finfo(float).eps)


def test_views_carry_a_detail_image(tmp_path: Path) -> None:
    """``View.detail``: the photo at up to 1024 px on the long side, same aspect, never upsampled."""
    big = _write_png(tmp_path / "big.png", _pattern(2000, 1400))
    small = _write_png(tmp_path / "small.png", _pattern(640, 480))
    vb, vs = load_views([big, small], ViewConfig(size=512))
    assert vb.detail is not None and vs.detail is not None
    assert vb.detail.shape[1] == 1024 and abs(vb.detail.shape[0] - 1400 * 1024 / 2000) <= 1
    assert vs.detail.shape == (480, 640, 3)


# ------------------------------------------------------------------------------------ image reading
def test_exif_orientation_6_loads_upright(tmp_path: Path) -> None:
    """A landscape JPEG tagged "rotate 90° clockwise" loads as a portrait with the rotated pixels."""
    stored = _pattern(160, 96)
    path = _write_jpeg(tmp_path / "r.jpg", stored, orientation=6, focal_35mm=28)
    img = load_image(path)
    assert (img.width, img.height) == (96, 160)
    upright = np.rot90(stored, -1).astype(np.float32) / 255.0  # clockwise
    assert np.abs(img.rgb - upright).mean() < 0.01
    assert np.abs(img.rgb - np.rot90(stored, 1).astype(np.float32) / 255.0).mean() > 0.1  # not the other way
    v = load_views([path], ViewConfig(size=512))[0]
    assert v.original_size == (96, 160) and (v.width, v.height) == (96, 160)
    f = 28.0 * math.hypot(96, 160) / 43.27
    np.testing.assert_allclose(v.K, _K(f, f, 48.0, 80.0), rtol=EXIF_RTOL, atol=0)
    assert v.intrinsics_source == "exif"


def test_sixteen_bit_png_keeps_precision(tmp_path: Path) -> None:
    """16-bit values come back as value/65535, not quantised to 8 bits."""
    rng = np.random.default_rng(0)
    raw = rng.integers(0, 65536, (80, 96, 3), dtype=np.uint16)
    path = tmp_path / "deep.png"
    assert cv2.imwrite(str(path), raw)  # OpenCV writes BGR
    img = load_image(path)
    assert img.bit_depth == 16
    np.testing.assert_array_equal(img.rgb, raw[..., ::-1].astype(np.float32) / 65535.0)
    assert np.mean(np.abs(img.rgb * 255 - np.rint(img.rgb * 255)) > 1e-3) > 0.9  # not multiples of 1/255
    v = load_views([path], ViewConfig(size=512))[0]  # 96 × 80: already a working size, no resampling
    np.testing.assert_array_equal(v.image, img.rgb)


def test_grayscale_png(tmp_path: Path) -> None:
    """A one-channel image is replicated to three channels."""
    gray = _pattern(96, 64)[..., 0]
    path = _write_png(tmp_path / "g.png", gray)
    v = load_views([path], ViewConfig(size=512))[0]
    assert v.image.shape == (64, 96, 3)
    for c in range(3):  # u8/255 in float32 against float64: one float32 rounding of a value ≤ 1
        np.testing.assert_allclose(v.image[..., c], gray / 255.0, rtol=0, atol=np.finfo(np.float32).eps / 2)
    assert v.mask.all()


def test_rgba_alpha_becomes_the_mask(tmp_path: Path) -> None:
    """Alpha < 0.5 → mask False (127/255 is out, 128/255 is in); colour is read without the alpha."""
    rgb = _pattern(96, 64)
    alpha = np.full((64, 96), 255, np.uint8)
    alpha[:, :32] = 0
    alpha[:, 32:48] = 127
    alpha[:, 48:64] = 128
    path = _write_png(tmp_path / "a.png", np.dstack([rgb, alpha]))
    v = load_views([path], ViewConfig(size=512))[0]
    assert v.mask.dtype == bool and v.mask.shape == (64, 96)
    assert not v.mask[:, :48].any() and v.mask[:, 48:].all()
    np.testing.assert_allclose(v.image, rgb / 255.0, rtol=0, atol=np.finfo(np.float32).eps / 2)  # as above


def test_rgba_mask_is_resampled_to_the_working_size(tmp_path: Path) -> None:
    """A downscaled alpha keeps the masked region (left half transparent)."""
    alpha = np.full((256, 512), 255, np.uint8)
    alpha[:, :256] = 0
    path = _write_png(tmp_path / "a.png", np.dstack([_pattern(512, 256), alpha]))
    v = load_views([path], ViewConfig(size=256))[0]
    assert v.mask.shape == (128, 256)
    assert not v.mask[:, :128].any() and v.mask[:, 128:].all()


@pytest.mark.parametrize(("width", "height"), [(63, 200), (200, 40), (10, 10)])
def test_too_small_image(tmp_path: Path, width: int, height: int) -> None:
    """Under 64 px on a side: ImageReadError naming the file and "too small"."""
    path = _write_png(tmp_path / "tiny.png", _pattern(width, height))
    with pytest.raises(ImageReadError, match=r"tiny\.png.*too small"):
        load_views([path])


def test_smallest_accepted_image(tmp_path: Path) -> None:
    """Exactly 64 × 64 is accepted."""
    v = load_views([_write_png(tmp_path / "ok.png", _pattern(64, 64))])[0]
    assert (v.width, v.height) == (64, 64)


@pytest.mark.parametrize(
    "content",
    [
        b"not an image at all",
        b"\x89PNG\r\n\x1a\n" + b"\x00" * 40,
        pytest.param(b"", id="empty"),
    ],
)
def test_corrupt_file(tmp_path: Path, content: bytes) -> None:
    """Bytes that are not a decodable image: ImageReadError naming the file."""
    path = tmp_path / "broken.png"
    path.write_bytes(content)
    with pytest.raises(ImageReadError, match=r"broken\.png"):
        load_views([path])


def test_missing_file_and_directory(tmp_path: Path) -> None:
    """A missing path or a directory: ImageReadError naming it."""
    with pytest.raises(ImageReadError, match=r"nowhere\.jpg: no such file"):
        load_views([tmp_path / "nowhere.jpg"])
    (tmp_path / "folder.png").mkdir()
    with pytest.raises(ImageReadError, match=r"folder\.png"):
        load_views([tmp_path / "folder.png"])


def test_same_stem_gets_distinct_names(tmp_path: Path) -> None:
    """Two photos with the same stem (different folders) get distinct view names."""
    (tmp_path / "x").mkdir()
    (tmp_path / "y").mkdir()
    a = _write_png(tmp_path / "x" / "img.png", _pattern(64, 64))
    b = _write_png(tmp_path / "y" / "img.png", _pattern(64, 64, 1))
    va, vb = load_views([a, b])
    assert va.name == "img" and vb.name != va.name
