"""A ``.safetensors`` reader for the checkpoint loaders (the format is simple; no extra dependency).

Checked against the ``safetensors`` package in ``tests/test_dinov3.py``.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path

import torch

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
        ``error(...)``: the file is truncated or its header is malformed.
    """
    p = Path(path)
    if sys.byteorder != "little":
        raise error(f"{p}: reading safetensors needs a little-endian machine")
    size = p.stat().st_size
    buf = bytearray(size)
    with open(p, "rb") as f:
        f.readinto(buf)
    if size < 8:
        raise error(f"{p}: not a safetensors file (only {size} bytes)")
    n = int.from_bytes(buf[:8], "little")
    if 8 + n > size:
        raise error(f"{p}: not a safetensors file (header length {n} exceeds the file size)")
    try:
        header = json.loads(bytes(buf[8 : 8 + n]).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise error(f"{p}: malformed safetensors header: {e}") from None
    if not isinstance(header, dict):
        raise error(f"{p}: malformed safetensors header (not a JSON object)")
    base = 8 + n
    out: dict[str, torch.Tensor] = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        try:
            dtype = _ST_DTYPES[info["dtype"]]
            shape = tuple(int(s) for s in info["shape"])
            begin, end = (int(o) for o in info["data_offsets"])
        except (KeyError, TypeError, ValueError):
            raise error(f"{p}: malformed safetensors entry for {name!r}: {info!r}") from None
        itemsize = torch.empty((), dtype=dtype).element_size()
        numel = math.prod(shape)
        if end - begin != numel * itemsize or begin < 0 or base + end > size:
            raise error(f"{p}: safetensors entry {name!r} has inconsistent offsets [{begin}, {end}]")
        if numel == 0:
            out[name] = torch.empty(shape, dtype=dtype)
        elif (base + begin) % itemsize == 0:
            out[name] = torch.frombuffer(buf, dtype=dtype, count=numel, offset=base + begin).reshape(shape)
        else:  # unaligned: copy the bytes first
            raw = torch.frombuffer(buf, dtype=torch.uint8, count=end - begin, offset=base + begin).clone()
            out[name] = raw.view(dtype).reshape(shape)
    return out
