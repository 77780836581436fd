"""A ``.safetensors`` reader for the checkpoint loaders (the format is simple; no extra dependency).

Checked against the ``safetensors`` package in ``tests/test_dinov3.py``.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Callable
from pathlib import Path

import torch

from .._limits import check_regular_file, parse_json
from ..errors import InputError

__all__ = ["read_safetensors"]

_ST_DTYPES: dict[str, torch.dtype] = {
    "F64": torch.float64,
    "F32": torch.float32,
    "F16": torch.float16,
    "BF16": torch.bfloat16,
    "I64": torch.int64,
    "I32": torch.int32,
    "I16": torch.int16,
    "I8": torch.int8,
    "U8": torch.uint8,
    "BOOL": torch.bool,
}
_MAX_DIMS = 16
_MAX_DIM_SIZE = 1 << 48  # larger than any file; also bounds the shape arithmetic of zero-size tensors


def read_safetensors(
    path: str | os.PathLike[str], error: Callable[[str], Exception] = InputError
) -> dict[str, torch.Tensor]:
    """Read a ``.safetensors`` file into CPU tensors (no dependency on the ``safetensors`` package).

    Format: an 8-byte little-endian header length ``n``, ``n`` bytes of JSON mapping each
    name to ``{"dtype", "shape", "data_offsets": [begin, end]}`` (offsets into the data
    that follows the header; an optional ``"__metadata__"`` entry), then the raw
    little-endian data.

    Args:
        path: the file.
        error: builds the exception for a malformed file from its message (the loader's error class).

    Raises:
        ``error(...)``: the file is not a regular file, is truncated, or its header is malformed: not JSON,
        nested too deeply, an unknown dtype, a shape that is not a list of non-negative sizes, or data
        offsets that fall outside the data or do not match the shape.
    """
    p = Path(path)
    if sys.byteorder != "little":
        raise error(f"{p}: reading safetensors needs a little-endian machine")
    size = check_regular_file(p, error, "a safetensors file")
    if size < 8:
        raise error(f"{p}: not a safetensors file (only {size} bytes)")
    buf = bytearray(size)
    with open(p, "rb") as f:
        got = f.readinto(buf)
    if got != size:
        raise error(f"{p}: the file changed while it was read ({got} of {size} bytes)")
    n = int.from_bytes(buf[:8], "little")
    if 8 + n > size:
        raise error(f"{p}: not a safetensors file (header length {n} exceeds the file size)")
    try:
        text = bytes(buf[8 : 8 + n]).decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{p}: malformed safetensors header: {e}") from None
    header = parse_json(text, f"{p}: malformed safetensors header", error)
    if not isinstance(header, dict):
        raise error(f"{p}: malformed safetensors header (not a JSON object)")
    base = 8 + n
    data_size = size - base
    out: dict[str, torch.Tensor] = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        dtype, shape, begin, end = _entry(p, name, info, error)
        itemsize = torch.empty((), dtype=dtype).element_size()
        numel = math.prod(shape)
        if not 0 <= begin <= end <= data_size:
            raise error(
                f"{p}: safetensors entry {name!r} has inconsistent offsets [{begin}, {end}]: outside the "
                f"{data_size} bytes of data (truncated file?)"
            )
        if end - begin != numel * itemsize:
            raise error(
                f"{p}: safetensors entry {name!r} has inconsistent offsets [{begin}, {end}] ({end - begin} bytes) for "
                f"its shape {list(shape)} of {info['dtype']} ({numel * itemsize} bytes)"
            )
        if numel == 0:
            out[name] = torch.empty(shape, dtype=dtype)
        elif (base + begin) % itemsize == 0:
            out[name] = torch.frombuffer(buf, dtype=dtype, count=numel, offset=base + begin).reshape(shape)
        else:  # unaligned: copy the bytes first
            raw = torch.frombuffer(buf, dtype=torch.uint8, count=end - begin, offset=base + begin).clone()
            out[name] = raw.view(dtype).reshape(shape)
    return out


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _entry(
    p: Path, name: str, info: object, error: Callable[[str], Exception]
) -> tuple[torch.dtype, tuple[int, ...], int, int]:
    """``(dtype, shape, begin, end)`` of one header entry, every field checked."""
    if not isinstance(info, dict) or not {"dtype", "shape", "data_offsets"} <= info.keys():
        raise error(f"{p}: malformed safetensors entry for {name!r}: {info!r:.200}")
    dtype = _ST_DTYPES.get(info["dtype"]) if isinstance(info["dtype"], str) else None
    if dtype is None:
        raise error(f"{p}: safetensors entry {name!r} has an unsupported dtype {info['dtype']!r:.100}")
    shape, offsets = info["shape"], info["data_offsets"]
    if not (
        isinstance(shape, list)
        and len(shape) <= _MAX_DIMS
        and all(_is_int(s) and s >= 0 for s in shape)
        and math.prod(s for s in shape if s) <= _MAX_DIM_SIZE
    ):
        raise error(
            f"{p}: safetensors entry {name!r} has an invalid shape {shape!r:.200} "
            f"(a list of at most {_MAX_DIMS} non-negative sizes)"
        )
    if not (isinstance(offsets, list) and len(offsets) == 2 and all(_is_int(o) for o in offsets)):
        raise error(f"{p}: safetensors entry {name!r} has invalid data offsets {offsets!r:.200} (two integers)")
    return dtype, tuple(shape), offsets[0], offsets[1]
