"""What every weight loader shares: the strict key/shape check of a state dict and the sha256 debug log.

Used by the MASt3R/Splatt3R (:mod:`.checkpoints`), DINOv3 (:mod:`.dinov3`), fusion (:mod:`.fusion`) and
LPIPS (:mod:`macsplat_cli.lpips`) loaders. Each loader keeps its own error class, a subclass of
:class:`StateDictError`, which :func:`check_state_dict_keys` is given and raises.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from pathlib import Path

import torch

from ..errors import InputError

__all__ = ["StateDictError", "check_state_dict_keys", "log_sha256", "sha256_file"]


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
