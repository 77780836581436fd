"""What every weight loader shares: the strict key/shape check of a state dict, a ``.safetensors`` reader and
the sha256 debug log.

Used by the MASt3R/Splatt3R (:mod:`.neural.checkpoints`), DINOv3 (:mod:`.neural.dinov3`), fusion
(:mod:`.neural.fusion`), predictor (:mod:`.neural.predictor_io`) and LPIPS (:mod:`.lpips`) loaders. Each loader
keeps its own error class, a subclass of :class:`StateDictError`, which :func:`check_state_dict_keys` is given
and raises (and :func:`read_safetensors` builds from a message).

The safetensors reader needs no extra dependency (the format is simple); it is checked against the
``safetensors`` package in ``tests/neural/test_dinov3.py``.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import sys
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from pathlib import Path

import torch

from ._limits import check_regular_file, parse_json
from .errors import InputError

__all__ = ["StateDictError", "check_state_dict_keys", "log_sha256", "read_safetensors", "sha256_file"]


class StateDictError(InputError):
    """A weight file does not match its network (base of the loaders' error classes).

    Attributes:
        key: the first offending state-dict key, or None.
        file_shape: that key's shape in the file (None when the file lacks it).
        model_shape: that key's shape in the model (None when the model has no such key).
        missing_keys: model keys absent from the file (when known).
        unexpected_keys: file keys the model does not have (when known).
    """

    def __init__(
        self,
        message: str,
        *,
        key: str | None = None,
        file_shape: tuple[int, ...] | None = None,
        model_shape: tuple[int, ...] | None = None,
        missing_keys: Iterable[str] = (),
        unexpected_keys: Iterable[str] = (),
    ) -> None:
        self.key = key
        self.file_shape = file_shape
        self.model_shape = model_shape
        self.missing_keys = tuple(missing_keys)
        self.unexpected_keys = tuple(unexpected_keys)
        super().__init__(message)


def check_state_dict_keys(
    expected: Mapping[str, Sequence[int]],
    state_dict: Mapping[str, torch.Tensor],
    error: Callable[..., Exception],
    *,
    source: str,
    model: str = "the model",
    optional: Collection[str] = (),
    allow_missing: bool = False,
    allow_unexpected: bool = False,
    key_prefix: str = "",
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Compare a state dict's keys and shapes with the model's; raise on the first mismatch.

    The file's keys are scanned in file order (a key of another shape, or one the model lacks), then
    the model's keys in model order (one the file lacks). The message names the key and both shapes.

    Args:
        expected: model key → shape (``{k: v.shape for k, v in module.state_dict().items()}``; ``meta``
            tensors do).
        state_dict: the file's tensors.
        error: the loader's error class (or a ``functools.partial`` of it), called as
            ``error(message, key=, file_shape=, model_shape=, missing_keys=, unexpected_keys=)``;
            a :class:`StateDictError` subclass accepts these.
        source: what the message starts with (the file).
        model: how the message names the model (``"DINOv3 vits16"``).
        optional: model keys that never count as missing.
        allow_missing: missing keys are returned instead of raised.
        allow_unexpected: unknown file keys are returned instead of raised.
        key_prefix: prepended to key names in the message and the error (``"encoder."`` for a Splatt3R file).

    Returns:
        ``(missing_keys, unexpected_keys)`` without the prefix.

    Raises:
        ``error``: a key has another shape (always), or a disallowed missing / unexpected key.
    """
    shapes = {k: tuple(int(s) for s in v) for k, v in expected.items()}
    optional = set(optional)
    unexpected = [k for k in state_dict if k not in shapes]
    missing = [k for k in shapes if k not in state_dict and k not in optional]
    wrong = [k for k, v in state_dict.items() if k in shapes and _shape(v) != shapes[k]]
    counts = f"in all {len(wrong)} key(s) of another shape"
    if not allow_unexpected:
        counts += f", {len(unexpected)} unexpected"
    if not allow_missing:
        counts += f", {len(missing)} missing"

    def fail(message: str, key: str, file_shape: tuple[int, ...] | None) -> Exception:
        return error(
            f"{source}: {message}; {counts}",
            key=key_prefix + key,
            file_shape=file_shape,
            model_shape=shapes.get(key),
            missing_keys=[key_prefix + k for k in missing],
            unexpected_keys=[key_prefix + k for k in unexpected],
        )

    for k, v in state_dict.items():
        file_shape = _shape(v)
        name = repr(key_prefix + k)
        found = f"shape {list(file_shape)}" if file_shape is not None else f"a {type(v).__name__}, not a tensor,"
        if k not in shapes:
            if not allow_unexpected:
                raise fail(f"unexpected key {name} ({found} in the file; not in {model})", k, file_shape)
        elif file_shape != shapes[k]:
            raise fail(f"key {name} has {found} in the file but shape {list(shapes[k])} in {model}", k, file_shape)
    if missing and not allow_missing:
        k = missing[0]
        raise fail(f"key {key_prefix + k!r} (shape {list(shapes[k])} in {model}) is missing from the file", k, None)
    return tuple(missing), tuple(unexpected)


def _shape(value: object) -> tuple[int, ...] | None:
    return tuple(value.shape) if isinstance(value, torch.Tensor) else None


def sha256_file(path: Path | str, chunk: int = 1 << 24) -> str:
    """SHA-256 hex digest of a file, read in ``chunk``-byte pieces."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def log_sha256(path: Path | str, log: logging.Logger, what: str = "weights") -> str | None:
    """Log ``path``'s sha256 at debug level on ``log`` (the loader's logger) and return it.

    Hashing a 1 GB checkpoint takes seconds, so nothing is read unless DEBUG is enabled on ``log``;
    then None is returned.
    """
    if not log.isEnabledFor(logging.DEBUG):
        return None
    digest = sha256_file(path)
    log.debug("%s %s sha256 %s", what, path, digest)
    return digest


# ============================================================================================= safetensors
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
