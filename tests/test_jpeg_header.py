"""The JPEG header reader (``_jpeg_header``): Pillow's size, EXIF orientation and 35 mm focal, or None."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from macsplat_cli._jpeg_header import jpeg_header
from macsplat_cli.images import _exif

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "motorcycle"


def _jpeg(width: int = 40, height: int = 24, *, exif: Image.Exif | None = None, **save: object) -> bytes:
    rgb = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, "JPEG", **({"exif": exif} if exif is not None else {}), **save)
    return buf.getvalue()


def _exif_block(orientation: int | None = None, focal_35mm: int | None = None) -> Image.Exif:
    exif = Image.Exif()
    if orientation is not None:
        exif[0x0112] = orientation
    if focal_35mm is not None:
        exif.get_ifd(0x8769)[0xA405] = focal_35mm
    return exif


def _pillow(data: bytes) -> tuple[tuple[int, int], int, float | None]:
    with Image.open(io.BytesIO(data)) as im:
        size = im.size
    return size, *_exif(data)


def _ours(data: bytes) -> tuple[tuple[int, int], int, float | None]:
    h = jpeg_header(data)
    assert h is not None
    return (h.width, h.height), h.orientation, h.focal_35mm


@pytest.mark.parametrize("orientation", [None, 0, 1, 3, 6, 8, 9])
@pytest.mark.parametrize("focal", [None, 0, 28])
@pytest.mark.parametrize("progressive", [False, True])
def test_agrees_with_pillow(orientation: int | None, focal: int | None, progressive: bool) -> None:
    """Size, orientation (0 and 9 read as 1) and focal (0 read as none) as Pillow's, baseline and progressive."""
    data = _jpeg(52, 30, exif=_exif_block(orientation, focal), progressive=progressive)
    assert _ours(data) == _pillow(data)


@pytest.mark.parametrize("name", ["left.jpg", "right.jpg"])
def test_the_example_photos(name: str) -> None:
    data = (EXAMPLE / name).read_bytes()
    assert _ours(data) == _pillow(data)


def test_big_endian_exif() -> None:
    """A Motorola-order EXIF block (``MM``), built by hand: orientation 6, focal 35."""
    ifd = lambda entries, nxt: (  # noqa: E731
        len(entries).to_bytes(2, "big") + b"".join(t.to_bytes(2, "big") + k.to_bytes(2, "big") + (1).to_bytes(4, "big")
                                                   + v for t, k, v in entries) + nxt.to_bytes(4, "big"))  # fmt: skip
    sub_at = 8 + 2 + 2 * 12 + 4
    tiff = b"MM\0*" + (8).to_bytes(4, "big")
    tiff += ifd([(0x0112, 3, (6).to_bytes(2, "big") + b"\0\0"), (0x8769, 4, sub_at.to_bytes(4, "big"))], 0)
    tiff += ifd([(0xA405, 3, (35).to_bytes(2, "big") + b"\0\0")], 0)
    plain = _jpeg()  # no EXIF block
    app1 = b"Exif\0\0" + tiff
    data = plain[:2] + b"\xff\xe1" + (len(app1) + 2).to_bytes(2, "big") + app1 + plain[2:]
    assert _ours(data) == _pillow(data) == ((40, 24), 6, 35.0)


def _with_segment(data: bytes, marker: int, body: bytes) -> bytes:
    return data[:2] + bytes([0xFF, marker]) + (len(body) + 2).to_bytes(2, "big") + body + data[2:]


@pytest.mark.parametrize(
    "make",
    [
        lambda d: d[:200],  # truncated before the scan
        lambda d: _with_segment(d, 0xE1, b'http://ns.adobe.com/xap/1.0/\0<x tiff:Orientation="6"/>'),  # XMP
        lambda d: _with_segment(d, 0xE1, d[d.index(b"Exif") : d.index(b"Exif") + 40]),  # two EXIF blocks
        lambda d: b"\x89PNG\r\n\x1a\n" + d[2:],  # not a JPEG
        lambda d: d[:2] + b"\xff" + d[2:],  # a fill byte before a marker
    ],
    ids=["truncated", "xmp", "two-exif", "png", "fill-byte"],
)
def test_unsure_headers_are_left_to_pillow(make) -> None:  # noqa: ANN001
    assert jpeg_header(make(_jpeg(exif=_exif_block(3, 28)))) is None


def test_a_rational_focal_is_left_to_pillow() -> None:
    """FocalLengthIn35mmFilm stored as a RATIONAL (not the standard's SHORT): Pillow's value is not an int."""
    exif = _exif_block(1)
    exif.get_ifd(0x8769)[0xA405] = 28.5
    assert jpeg_header(_jpeg(exif=exif)) is None


def test_loading_a_jpeg_imports_no_pillow(tmp_path: Path) -> None:
    """The photos of a run are JPEGs: reading them (size cap, EXIF, no alpha) needs no Pillow import."""
    path = tmp_path / "a.jpg"
    path.write_bytes(_jpeg(64, 48, exif=_exif_block(6, 28)))
    code = (
        "import sys\nfrom macsplat_cli.images import load_image\n"
        f"img = load_image({str(path)!r})\n"
        "print(img.width, img.height, img.focal_35mm, 'PIL' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["48", "64", "28.0", "False"]
