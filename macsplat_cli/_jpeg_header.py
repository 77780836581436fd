"""A JPEG's size, EXIF orientation and 35 mm focal length read from its header, without Pillow.

:func:`~macsplat_cli.images.load_image` needs these three before (the size: the megapixel cap) and after (the
orientation, the focal length) OpenCV decodes the pixels; Pillow gives them for every format, but importing it
costs ~0.15 s of a two-photo ``--quality fast`` run. For a JPEG this reader walks the marker segments up to the
first scan and the EXIF block's two IFDs. It answers only where it is sure to agree with Pillow
(``Image.open(...).size``, ``getexif()``): anything else — not a JPEG, a truncated or odd segment, two SOF or two
EXIF segments, an XMP block (Pillow reads ``tiff:Orientation`` there when EXIF has none), an EXIF field of a type or
count other than one SHORT or LONG, an offset out of the block — gives None, and the caller asks Pillow.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = ["JpegHeader", "jpeg_header"]

_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
"""Start-of-frame markers (every coding process): their segment holds the image's height and width."""
_SOS, _APP1 = 0xDA, 0xE1
_EXIF, _XMP = b"Exif\0\0", b"http://ns.adobe.com/xap/1.0/"
_ORIENTATION, _EXIF_IFD, _FOCAL_35MM = 0x0112, 0x8769, 0xA405
_SHORT, _LONG = 3, 4
_Order = Literal["little", "big"]
_MAX_ENTRIES = 1000
"""More entries than this in one IFD: not a camera's EXIF block (left to Pillow)."""


@dataclass(frozen=True)
class JpegHeader:
    """What :func:`~macsplat_cli.images.load_image` takes from a JPEG's header.

    Attributes:
        width: pixels, as stored (before the orientation).
        height: pixels, as stored.
        orientation: EXIF orientation 1..8 (1 without EXIF or out of range, as ``images._exif`` maps Pillow's).
        focal_35mm: EXIF FocalLengthIn35mmFilm in millimetres when present and positive, else None.
    """

    width: int
    height: int
    orientation: int
    focal_35mm: float | None


def _segments(data: bytes) -> tuple[tuple[int, int], bytes | None] | None:
    """(width, height) from the one SOF segment and the one EXIF block (or None) before the first scan; None
    when the marker walk is anything but plain."""
    if not data.startswith(b"\xff\xd8\xff"):
        return None
    i, size, exif = 2, None, None
    while True:
        if i + 4 > len(data) or data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == _SOS:
            return (size, exif) if size is not None else None
        n = int.from_bytes(data[i + 2 : i + 4], "big")
        if marker in (0x00, 0x01, 0xD8, 0xD9, 0xFF) or 0xD0 <= marker <= 0xD7 or n < 2 or i + 2 + n > len(data):
            return None
        body = data[i + 4 : i + 2 + n]
        if marker in _SOF:
            if size is not None or len(body) < 5:
                return None
            size = (int.from_bytes(body[3:5], "big"), int.from_bytes(body[1:3], "big"))
        elif marker == _APP1 and body.startswith(_EXIF):
            if exif is not None:
                return None  # Pillow joins the blocks
            exif = body[len(_EXIF) :]
        elif marker == _APP1 and body.startswith(_XMP):
            return None
        i += 2 + n


def _ifd(tiff: bytes, offset: int, order: _Order) -> dict[int, int] | None:
    """An IFD's tags whose value is one SHORT or LONG, as ints; None if malformed, a tag repeats, or one of the
    tags read here has another type or count."""
    if offset < 8 or offset + 2 > len(tiff):
        return None
    count = int.from_bytes(tiff[offset : offset + 2], order)
    if count > _MAX_ENTRIES or offset + 2 + 12 * count > len(tiff):
        return None
    out: dict[int, int] = {}
    for k in range(count):
        e = offset + 2 + 12 * k
        tag, kind, n = (int.from_bytes(tiff[e + a : e + b], order) for a, b in ((0, 2), (2, 4), (4, 8)))
        if tag in out:
            return None
        if kind in (_SHORT, _LONG) and n == 1:
            out[tag] = int.from_bytes(tiff[e + 8 : e + (10 if kind == _SHORT else 12)], order)
        elif tag in (_ORIENTATION, _EXIF_IFD, _FOCAL_35MM):
            return None
    return out


def _exif_fields(tiff: bytes) -> tuple[int, float | None] | None:
    """(orientation, 35 mm focal or None) from an EXIF block's TIFF structure; None where unsure."""
    order: _Order
    if tiff[:4] == b"II*\0":
        order = "little"
    elif tiff[:4] == b"MM\0*":
        order = "big"
    else:
        return None
    ifd0 = _ifd(tiff, int.from_bytes(tiff[4:8], order), order)
    if ifd0 is None:
        return None
    focal = None
    if _EXIF_IFD in ifd0:
        sub = _ifd(tiff, ifd0[_EXIF_IFD], order)
        if sub is None:
            return None
        f35 = sub.get(_FOCAL_35MM)
        focal = float(f35) if f35 else None
    orientation = ifd0.get(_ORIENTATION, 1) or 1
    return (orientation if 1 <= orientation <= 8 else 1), focal


def jpeg_header(data: bytes) -> JpegHeader | None:
    """The header of the JPEG file ``data`` (module docstring), or None: not a JPEG, or one whose header this
    reader cannot be sure to read as Pillow does."""
    found = _segments(data)
    if found is None:
        return None
    (w, h), exif = found
    if w == 0 or h == 0:
        return None
    fields = (1, None) if exif is None else _exif_fields(exif)
    return None if fields is None else JpegHeader(w, h, fields[0], fields[1])
