"""Load official MASt3R checkpoints into :class:`MASt3RBackbone`; what every official checkpoint loader shares.

Supported layouts (see ``models/mast3r.md`` and ``models/splatt3r.md``):

* **MASt3R ``.pth``** — ``torch.save`` of
  ``{"model": state_dict, "args": argparse.Namespace(model="AsymmetricMASt3R(...)")}``; the architecture
  comes from ``args.model`` (parsed, never evaluated, by :meth:`BackboneConfig.from_args_string`).
* **MASt3R Hugging Face folder** — ``config.json`` (the constructor's keyword arguments as JSON, e.g.
  ``{"enc_embed_dim": 1024, ..., "depth_mode": ["exp", -Infinity, Infinity]}``; a ``{"model": "AsymmetricMASt3R(...)"}``
  form is read too) plus ``model.safetensors`` (or ``pytorch_model.bin``). safetensors stores each shared tensor
  once, so the aliased ``…dpt.scratch.layer_rn.{i}`` / ``layer{i+1}_rn`` keys may appear under one name only.
* **Splatt3R Lightning ``.ckpt``** — read by :mod:`.splatt3r` with this module's safe reading and strict
  checks.

Files are read with ``torch.load(weights_only=True)``: only tensors and plain containers are built.
``argparse.Namespace`` (the ``args`` of a ``.pth``) is allow-listed. Training metadata that names other
Python classes (OmegaConf configs, Lightning containers, typing/numpy objects; see
:data:`INERT_GLOBAL_PREFIXES`) is replaced by inert placeholders, which run no code from the file;
any other class in the file raises :class:`CheckpointError`.

Loading is strict: every key must be known and have the model's shape, and every model key must be
present (except ``mask_token``, unused by inference, and the alias duplicates above). A mismatch raises
:class:`CheckpointError` naming the first bad key (in file order) and both shapes.
"""

from __future__ import annotations

import argparse
import functools
import logging
import pickle
import struct
import zipfile
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from torch import nn

from .._limits import read_json_file
from .._state_dict import StateDictError, check_state_dict_keys, log_sha256, read_safetensors
from .backbone import MASt3RBackbone
from .config import BackboneConfig
from .constructor import ModelConfigError

__all__ = [
    "INERT_GLOBAL_PREFIXES",
    "CheckpointError",
    "CheckpointFormat",
    "CheckpointNotFoundError",
    "LoadReport",
    "build_and_load",
    "check_state_dict",
    "load_mast3r",
    "read_mast3r_checkpoint",
    "tensor_dict",
    "torch_load_restricted",
]

logger = logging.getLogger(__name__)

CheckpointFormat = Literal["mast3r-pth", "mast3r-hf", "splatt3r-ckpt"]

MAST3R_FILE = "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth"
MAST3R_HF_REPO = "https://huggingface.co/naver/MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric"
_MAST3R_HINT = (
    f"macsplat needs the MASt3R checkpoint {MAST3R_FILE} (or a Hugging Face folder with config.json + "
    f"model.safetensors), from {MAST3R_HF_REPO} or the naver/mast3r README; licence CC BY-NC-SA 4.0, "
    "non-commercial use only (see models/mast3r.md)"
)

# Keys the model has but a checkpoint may lack: CroCo's pre-training mask token (unused at inference).
_OPTIONAL_KEYS = ("mask_token",)
INERT_GLOBAL_PREFIXES = (
    "omegaconf.",
    "typing.",
    "lightning.",
    "pytorch_lightning.",
    "lightning_fabric.",
    "numpy.",
    "pathlib.",
    "enum.",
    "collections.",
)
"""Module prefixes of Python globals that training checkpoints use for metadata; they load as inert placeholders."""
_INERT_BUILTINS = frozenset(
    f"builtins.{n}" for n in ("dict", "list", "tuple", "set", "frozenset", "str", "int", "float", "bool", "object")
)
# dict subclasses that pickle their items with SETITEMS: they load as plain dicts.
_DICT_LIKE_SUFFIXES = ("collections.defaultdict", "AttributeDict")
# What torch.load / its pickle scan raise for a damaged, truncated or non-torch file.
_LOAD_ERRORS = (
    pickle.UnpicklingError,
    RuntimeError,
    EOFError,
    OSError,
    ValueError,
    KeyError,
    IndexError,
    TypeError,
    struct.error,
    zipfile.BadZipFile,
)


# ============================================================================================= errors and report
class CheckpointError(StateDictError):
    """A checkpoint file is missing, unreadable, or does not match the network.

    Attributes (besides :class:`StateDictError`'s ``key``, ``file_shape``, ``model_shape``,
    ``missing_keys``, ``unexpected_keys``):
        path: the file (or folder) concerned.
    """

    def __init__(
        self,
        message: str,
        *,
        path: Path | str | None = None,
        key: str | None = None,
        file_shape: tuple[int, ...] | None = None,
        model_shape: tuple[int, ...] | None = None,
        missing_keys: Iterable[str] = (),
        unexpected_keys: Iterable[str] = (),
    ) -> None:
        self.path = Path(path) if path is not None else None
        super().__init__(
            message,
            key=key,
            file_shape=file_shape,
            model_shape=model_shape,
            missing_keys=missing_keys,
            unexpected_keys=unexpected_keys,
        )


class CheckpointNotFoundError(CheckpointError, FileNotFoundError):
    """A required checkpoint file does not exist; the message says which file and where to get it."""


@dataclass
class LoadReport:
    """What a loader did.

    Attributes:
        path: the file or folder read.
        format: which layout it had.
        missing_keys: model keys left at their initial values (only ``mask_token``, or any key with ``strict=False``).
        unexpected_keys: file keys that were dropped (only with ``strict=False``).
        ignored_keys: file keys deliberately not loaded (Splatt3R's LPIPS loss network, renderer buffers).
        notes: other adjustments (aliases filled in, ``dec_blocks2`` copied from ``dec_blocks``).
        sha256: hex digest of the weights file, computed only when DEBUG logging is on (else ``None``).
    """

    path: Path
    format: CheckpointFormat
    missing_keys: tuple[str, ...] = ()
    unexpected_keys: tuple[str, ...] = ()
    ignored_keys: tuple[str, ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)
    sha256: str | None = None


# ============================================================================================= restricted torch.load
class _InertGlobal:
    """Stand-in for a metadata class named in a checkpoint: records its arguments and state, runs nothing."""

    def __new__(cls, *args: Any, **kwargs: Any) -> _InertGlobal:
        obj = super().__new__(cls)
        obj.args = args
        return obj

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args = args

    def __setstate__(self, state: Any) -> None:
        self.state = state

    def __repr__(self) -> str:
        return "<inert placeholder>"


class _PlainDict:
    """Stand-in for a ``dict`` subclass (``defaultdict``, Lightning's ``AttributeDict``): builds a plain ``dict``."""

    def __new__(cls, *args: Any, **kwargs: Any) -> dict:  # type: ignore[misc]  # a dict, not an instance: on purpose
        return {}


def _is_inert(name: str) -> bool:
    return name in _INERT_BUILTINS or name.startswith(INERT_GLOBAL_PREFIXES)


def torch_load_restricted(path: Path, *, what: str) -> Any:
    """``torch.load(path, map_location='cpu', weights_only=True)`` with the allow-list of the module docstring.

    Zip-format files are memory-mapped. Raises :class:`CheckpointError` for a file that is not a
    torch checkpoint or that names a Python class outside the allow-list.
    """
    is_zip = zipfile.is_zipfile(path)
    safe: list[Any] = [argparse.Namespace]
    if is_zip:
        try:
            unsafe = torch.serialization.get_unsafe_globals_in_checkpoint(str(path))
        except _LOAD_ERRORS as e:
            raise CheckpointError(f"{what} {path} is not a readable PyTorch checkpoint: {e}", path=path) from None
        refused = [n for n in unsafe if n != "argparse.Namespace" and not _is_inert(n)]
        if refused:
            raise CheckpointError(
                f"{what} {path} references Python global(s) {', '.join(refused)}, which macsplat does not unpickle "
                "(only tensors, plain containers and argparse.Namespace are loaded); "
                "re-save the state dict alone with torch.save",
                path=path,
            )
        for n in unsafe:
            if n == "argparse.Namespace":
                continue
            stub = _PlainDict if n.endswith(_DICT_LIKE_SUFFIXES) else _InertGlobal
            logger.debug("%s: %s is loaded as an inert placeholder", path.name, n)
            safe.append((stub, n))
    try:
        with torch.serialization.safe_globals(safe):
            return torch.load(path, map_location="cpu", weights_only=True, mmap=is_zip)
    except _LOAD_ERRORS as e:
        first = str(e).strip().splitlines()
        detail = next(
            (ln.strip() for ln in first if "Unsupported" in ln or "Can only" in ln), first[0] if first else ""
        )
        raise CheckpointError(f"{what} {path} cannot be read safely: {type(e).__name__}: {detail}", path=path) from None


# ============================================================================================= state-dict checks
def tensor_dict(obj: Any, path: Path, what: str) -> dict[str, torch.Tensor]:
    """``obj`` as a state dict (string keys, tensor values); else :class:`CheckpointError` naming ``what``."""
    if not isinstance(obj, Mapping):
        raise CheckpointError(f"{what} {path}: expected a state dict (a mapping), got {type(obj).__name__}", path=path)
    for k, v in obj.items():
        if not isinstance(k, str) or not isinstance(v, torch.Tensor):
            raise CheckpointError(
                f"{what} {path}: state-dict entry {k!r} is a {type(v).__name__}, not a tensor", path=path, key=str(k)
            )
    return dict(obj)


def _alias_groups(module: nn.Module) -> list[list[str]]:
    """Groups of state-dict keys that name the same tensor (e.g. ``layer1_rn.weight`` / ``layer_rn.0.weight``)."""
    by_id: dict[int, list[str]] = {}
    for k, v in module.state_dict(keep_vars=True).items():
        by_id.setdefault(id(v), []).append(k)
    return [g for g in by_id.values() if len(g) > 1]


def _fill_aliases(module: nn.Module, sd: dict[str, torch.Tensor]) -> list[str]:
    filled = []
    for group in _alias_groups(module):
        present = [k for k in group if k in sd]
        if present:
            for k in group:
                if k not in sd:
                    sd[k] = sd[present[0]]
                    filled.append(k)
    return filled


def _copy_dec_blocks2(module: nn.Module, sd: dict[str, torch.Tensor]) -> bool:
    """Upstream rule: a checkpoint without ``dec_blocks2.*`` gets a copy of ``dec_blocks.*`` (DUSt3R from CroCo)."""
    if not isinstance(module, MASt3RBackbone) or any(k.startswith("dec_blocks2.") for k in sd):
        return False
    src = {k: v for k, v in sd.items() if k.startswith("dec_blocks.")}
    if not src:
        return False
    for k, v in src.items():
        sd["dec_blocks2." + k[len("dec_blocks.") :]] = v
    return True


def check_state_dict(
    module: nn.Module,
    state_dict: Mapping[str, torch.Tensor],
    *,
    path: Path | str = "<state dict>",
    strict: bool = True,
    optional: Collection[str] = _OPTIONAL_KEYS,
    key_prefix: str = "",
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Compare a state dict's keys and shapes with ``module``'s (works on ``meta`` modules).

    Args:
        key_prefix: prepended to key names in messages and in the error's key lists (``"encoder."``
            for a Splatt3R file).

    Returns ``(missing_keys, unexpected_keys)`` (without the prefix); optional keys never count as missing.

    Raises:
        CheckpointError: a key has the wrong shape (always), or, with ``strict``, a key is unknown or a
            model key is missing. The message names the first bad key in file order and both shapes
            (the check every loader shares, :func:`macsplat_cli._state_dict.check_state_dict_keys`).
    """
    expected = {k: v.shape for k, v in module.state_dict(keep_vars=True).items()}
    return check_state_dict_keys(
        expected,
        state_dict,
        functools.partial(CheckpointError, path=Path(path)),
        source=str(Path(path)),
        optional=optional,
        allow_missing=not strict,
        allow_unexpected=not strict,
        key_prefix=key_prefix,
    )


def build_and_load(
    factory: Any, sd: dict[str, torch.Tensor], *, path: Path, strict: bool, key_prefix: str = ""
) -> tuple[nn.Module, tuple[str, ...], tuple[str, ...], list[str]]:
    """Build the module on ``meta``, check ``sd`` against it, then load the file's tensors in place (no copy)."""
    with torch.device("meta"):
        module: nn.Module = factory()
    notes = []
    if _copy_dec_blocks2(module, sd):
        notes.append("dec_blocks2.* copied from dec_blocks.* (absent from the file)")
    filled = _fill_aliases(module, sd)
    if filled:
        notes.append(f"{len(filled)} aliased key(s) filled from their twin (e.g. {filled[0]})")
    missing, unexpected = check_state_dict(module, sd, path=path, strict=strict, key_prefix=key_prefix)
    missing_all = [k for k in module.state_dict() if k not in sd]
    if any(k not in _OPTIONAL_KEYS for k in missing_all):
        # Non-strict load with missing weights: they need a real initialisation, so build on the CPU.
        module = factory()
    sd = {k: (v.float() if v.is_floating_point() and v.dtype != torch.float32 else v) for k, v in sd.items()}
    module.load_state_dict({k: v for k, v in sd.items() if k not in unexpected}, strict=False, assign=True)
    for name, p in list(module.named_parameters()):
        if p.is_meta:  # an optional key the file lacked (mask_token): zeros, its upstream initial value
            owner = module.get_submodule(name.rpartition(".")[0]) if "." in name else module
            setattr(owner, name.rpartition(".")[2], nn.Parameter(torch.zeros(p.shape), requires_grad=p.requires_grad))
    return module, tuple(missing_all), unexpected, notes


# ============================================================================================= MASt3R
def _hf_files(folder: Path) -> tuple[Path, Path]:
    """``(config.json, weights)`` of a Hugging Face folder (``model.safetensors``, else ``pytorch_model.bin``)."""
    config = folder / "config.json"
    if not config.is_file():
        raise CheckpointNotFoundError(
            f"{config} is missing: a MASt3R Hugging Face folder needs it. {_MAST3R_HINT}", path=config
        )
    for name in ("model.safetensors", "pytorch_model.bin"):
        if (folder / name).is_file():
            return config, folder / name
    raise CheckpointNotFoundError(
        f"{folder / 'model.safetensors'} is missing: a MASt3R Hugging Face folder needs it. {_MAST3R_HINT}",
        path=folder / "model.safetensors",
    )


def _read_safetensors(path: Path) -> dict[str, torch.Tensor]:
    try:
        return read_safetensors(path, lambda message: CheckpointError(f"MASt3R weights {message}", path=path))
    except OSError as e:
        raise CheckpointError(f"MASt3R weights {path} cannot be read: {type(e).__name__}: {e}", path=path) from None


def _config_from_json(path: Path) -> BackboneConfig:
    data = read_json_file(path, lambda message: CheckpointError(message, path=path), "a model config")
    if not isinstance(data, dict):
        raise CheckpointError(f"{path}: expected a JSON object of model keyword arguments", path=path)
    try:
        if isinstance(data.get("model"), str):
            return BackboneConfig.from_args_string(data["model"])
        return BackboneConfig.from_kwargs(data)
    except ModelConfigError as e:
        raise CheckpointError(f"{path}: {e}", path=path) from None


def read_mast3r_checkpoint(
    path: Path | str, *, config: BackboneConfig | None = None
) -> tuple[dict[str, torch.Tensor], BackboneConfig, CheckpointFormat, Path]:
    """Read a MASt3R ``.pth`` file or Hugging Face folder.

    Args:
        path: the ``.pth`` file, the HF folder, or the ``model.safetensors`` inside it.
        config: architecture to use instead of the one recorded in the checkpoint.

    Returns:
        ``(state_dict, config, format, weights_file)``.
    """
    path = Path(path)
    if not path.exists():
        raise CheckpointNotFoundError(f"MASt3R checkpoint not found: {path}. {_MAST3R_HINT}", path=path)
    if path.is_dir() or path.suffix == ".safetensors":
        if path.is_dir():
            config_file, weights = _hf_files(path)
        else:
            config_file, weights = path.parent / "config.json", path
            if config is None and not config_file.is_file():
                raise CheckpointNotFoundError(
                    f"{config_file} is missing: {path.name} needs the config.json beside it. {_MAST3R_HINT}",
                    path=config_file,
                )
        cfg = config if config is not None else _config_from_json(config_file)
        if weights.suffix == ".safetensors":
            raw: Any = _read_safetensors(weights)
        else:
            raw = torch_load_restricted(weights, what="MASt3R weights")
        return tensor_dict(raw, weights, "MASt3R weights"), cfg, "mast3r-hf", weights

    ckpt = torch_load_restricted(path, what="MASt3R checkpoint")
    if isinstance(ckpt, Mapping) and "model" in ckpt:
        sd = tensor_dict(ckpt["model"], path, "MASt3R checkpoint")
        args = ckpt.get("args")
    elif isinstance(ckpt, Mapping) and "state_dict" in ckpt:
        raise CheckpointError(
            f"{path} looks like a Lightning checkpoint (it has 'state_dict'); load it with load_splatt3r", path=path
        )
    else:
        sd = tensor_dict(ckpt, path, "MASt3R checkpoint")
        args = None
    if config is not None:
        cfg = config
    elif args is None:
        cfg = BackboneConfig()
        logger.warning("%s has no 'args' entry: assuming the released ViT-L/ViT-B MASt3R architecture", path.name)
    else:
        model_string = getattr(args, "model", None)
        if not isinstance(model_string, str):
            raise CheckpointError(f"{path}: 'args' has no 'model' constructor string", path=path)
        try:
            cfg = BackboneConfig.from_args_string(model_string)
        except ModelConfigError as e:
            raise CheckpointError(f"{path}: its args.model string is not supported: {e}", path=path) from None
        logger.debug("%s: %s", path.name, model_string)
    return sd, cfg, "mast3r-pth", path


def load_mast3r(
    path: Path | str, *, config: BackboneConfig | None = None, strict: bool = True
) -> tuple[MASt3RBackbone, LoadReport]:
    """Build a :class:`MASt3RBackbone` from a MASt3R checkpoint (``.pth`` or Hugging Face folder) on the CPU.

    The module is returned in eval mode. With ``strict=False`` unknown keys are dropped and missing keys keep
    their initial values (both listed in the report); wrong shapes always raise.

    Raises:
        CheckpointNotFoundError: the file (or a file of the HF folder) does not exist.
        CheckpointError: unreadable or unsafe file, unsupported configuration, or mismatched keys/shapes.
    """
    sd, cfg, fmt, weights = read_mast3r_checkpoint(path, config=config)
    digest = log_sha256(weights, logger, "MASt3R weights")
    model, missing, unexpected, notes = build_and_load(lambda: MASt3RBackbone(cfg), sd, path=weights, strict=strict)
    for note in notes:
        logger.debug("%s: %s", weights.name, note)
    if unexpected:
        logger.warning("%s: %d unexpected key(s) ignored, e.g. %s", weights.name, len(unexpected), unexpected[0])
    report = LoadReport(Path(path), fmt, missing, unexpected, (), tuple(notes), digest)
    assert isinstance(model, MASt3RBackbone)
    return model.eval(), report
