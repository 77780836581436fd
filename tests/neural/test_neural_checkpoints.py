"""Checkpoint layouts: official MASt3R ``.pth`` / Hugging Face folder, Splatt3R Lightning ``.ckpt``.

State dicts are built from the key list and shapes the reference describes (``official_key_shapes`` in
``support/checkpoints.py``), independently of the module tree; the full ViT-L network is only instantiated on the
``meta`` device.
"""

from __future__ import annotations

# First, before torch: importing macsplat_cli sets OMP_WAIT_POLICY=PASSIVE, which OpenMP reads when torch
# loads (on 2 busy cores the default spinning made this file ~4x slower).
import argparse
import collections
import hashlib
import json
import logging
import math
import sys
import types
from pathlib import Path

import pytest
import torch

from macsplat_cli._state_dict import StateDictError, check_state_dict_keys, log_sha256, sha256_file
from macsplat_cli.errors import InputError
from macsplat_cli.lpips import LPIPSWeightsError
from macsplat_cli.neural import (
    BackboneConfig,
    CheckpointError,
    CheckpointNotFoundError,
    GaussianHead,
    GaussianHeadConfig,
    MASt3RBackbone,
    ModelConfigError,
    check_state_dict,
    load_mast3r,
    load_splatt3r,
)
from macsplat_cli.neural.dinov3 import DINOv3CheckpointError
from macsplat_cli.neural.fusion import (
    FusionCheckpointError,
    FusionConfig,
    ResidualSemanticFusion,
    load_fusion,
    save_fusion,
)

from support.checkpoints import TINY, TINY_ARGS, dpt_shapes, official_key_shapes, random_state_dict, save_pth

# The released model's constructor string as the reference quotes it (§1.1), plus what load_model appends.
OFFICIAL_ARGS = (
    "AsymmetricMASt3R(pos_embed='RoPE100', patch_embed_cls='ManyAR_PatchEmbed', img_size=(512, 512), "
    "head_type='catmlp+dpt', output_mode='pts3d+desc24', depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), "
    "enc_embed_dim=1024, enc_depth=24, enc_num_heads=16, dec_embed_dim=768, dec_depth=12, dec_num_heads=12, "
    "two_confs=True, desc_conf_mode=('exp', 0, inf), landscape_only=False)"
)


def _unique_count(shapes: dict[str, tuple[int, ...]]) -> int:
    return sum(math.prod(v) for k, v in shapes.items() if ".scratch.layer_rn." not in k)


def _pair(h: int = 32, w: int = 48) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    return torch.rand(1, 3, h, w, generator=g) * 2 - 1, torch.rand(1, 3, h, w, generator=g) * 2 - 1


# ============================================================================================= the full network (meta)
def test_full_config_matches_the_reference_key_list_and_parameter_count() -> None:
    cfg = BackboneConfig()
    with torch.device("meta"):
        model = MASt3RBackbone(cfg)
    want = official_key_shapes(cfg)
    got = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert set(got) == set(want), (sorted(set(got) ^ set(want)))[:5]
    assert got == want
    assert _unique_count(want) == 688_638_856  # the reference's analytic total
    assert sum(p.numel() for p in model.parameters()) == 688_638_856

    def count(*mods: torch.nn.Module) -> int:
        return sum(p.numel() for m in mods for p in m.parameters())

    assert count(model.patch_embed, model.enc_blocks, model.enc_norm) == 303_098_880
    assert count(model.decoder_embed, model.dec_blocks, model.dec_blocks2, model.dec_norm) + 768 == 227_668_992
    assert count(model.downstream_head1) == count(model.downstream_head2) == 78_935_492
    assert count(model.downstream_head1.dpt) == 20_201_668
    assert count(model.downstream_head1.head_local_features) == 58_733_824


def test_full_gaussian_head_matches_splatt3r_parameter_count() -> None:
    cfg = BackboneConfig(head_type="gaussian_head")
    with torch.device("meta"):
        head = GaussianHead(cfg)
        backbone = MASt3RBackbone(cfg)
    assert sum(p.numel() for p in head.downstream_head1.parameters()) == 20_202_958
    total = sum(p.numel() for p in head.parameters()) + sum(p.numel() for p in backbone.parameters())
    assert total == 729_044_772
    want = {}
    for h in (1, 2):
        want.update(dpt_shapes(f"downstream_head{h}.gaussian_dpt.dpt.", cfg, 14))
    assert {k: tuple(v.shape) for k, v in head.state_dict().items()} == want


def test_full_config_shape_mismatch_names_the_first_bad_key() -> None:
    with torch.device("meta"):
        model = MASt3RBackbone(BackboneConfig())
        sd = dict(model.state_dict())
        sd["enc_blocks.3.mlp.fc1.weight"] = torch.empty(2048, 1024)
        sd["dec_norm.weight"] = torch.empty(5)
    with pytest.raises(CheckpointError) as info:
        check_state_dict(model, sd, path="full.pth")
    e = info.value
    assert e.key == "enc_blocks.3.mlp.fc1.weight"
    assert e.file_shape == (2048, 1024) and e.model_shape == (4096, 1024)
    assert "enc_blocks.3.mlp.fc1.weight" in str(e) and "[2048, 1024]" in str(e) and "[4096, 1024]" in str(e)


# ============================================================================================= constructor strings
def test_official_args_string_gives_the_released_config() -> None:
    assert BackboneConfig.from_args_string(OFFICIAL_ARGS) == BackboneConfig()
    assert BackboneConfig.from_args_string(TINY_ARGS) == TINY
    # Without desc_conf_mode (README demo, Splatt3R): upstream's default 1 + exp(x).
    demo = OFFICIAL_ARGS.replace(", desc_conf_mode=('exp', 0, inf)", "")
    assert BackboneConfig.from_args_string(demo).desc_conf_mode == ("exp", 1.0, math.inf)
    # Round trip through macsplat's own writer.
    assert BackboneConfig.from_args_string(TINY.to_args_string()) == TINY
    assert BackboneConfig.from_args_string(BackboneConfig().to_args_string()) == BackboneConfig()
    splatt3r = OFFICIAL_ARGS.replace("'catmlp+dpt'", "'gaussian_head'").replace(
        "'pts3d+desc24'", "'pts3d+gaussian+desc24'"
    )
    assert BackboneConfig.from_args_string(splatt3r[:-1] + ", use_offsets=True, sh_degree=1)").head_type == (
        "gaussian_head"
    )
    alt = "AsymmetricMASt3R(depth_mode=('exp', -np.inf, float('inf')), conf_mode=['exp', +1, math.inf])"
    cfg = BackboneConfig.from_args_string(alt)
    assert cfg.depth_mode == ("exp", -math.inf, math.inf) and cfg.conf_mode == ("exp", 1.0, math.inf)


@pytest.mark.parametrize(
    "bad",
    [
        "AsymmetricMASt3R(",  # syntax error
        "__import__('os').system('touch /tmp/pwned')",
        "AsymmetricMASt3R(enc_depth=__import__('os').getpid())",
        "AsymmetricMASt3R(enc_depth=open('/etc/passwd'))",
        "AsymmetricMASt3R(enc_depth=12 + 12)",
        "AsymmetricMASt3R(enc_depth=depth)",
        "AsymmetricMASt3R(24)",
        "AsymmetricMASt3R(**{'enc_depth': 24})",
        "AsymmetricMASt3R(enc_depth=24, enc_depth=12)",
        "AsymmetricMASt3R(frobnicate=1)",
        "AsymmetricCroCo3DStereo(enc_depth=24)",
        "models.AsymmetricMASt3R(enc_depth=24)",
        "AsymmetricMASt3R(enc_depth='24')",
        "AsymmetricMASt3R(enc_depth=True)",
        "AsymmetricMASt3R(output_mode='pts3d')",
        "AsymmetricMASt3R(pos_embed='cosine')",
        "AsymmetricMASt3R(head_type='linear')",
        "AsymmetricMASt3R(depth_mode=('square', -inf, inf))",
        "AsymmetricMASt3R(conf_mode=('exp', 1))",
        "AsymmetricMASt3R(two_confs=False)",
        "AsymmetricMASt3R(patch_size=8)",
        "AsymmetricMASt3R(enc_embed_dim=1000)",  # 1000 / 16 heads is not an integer head size
        "[AsymmetricMASt3R()]",
    ],
)
def test_bad_args_strings_raise_a_typed_error(bad: str) -> None:
    with pytest.raises(ModelConfigError) as info:
        BackboneConfig.from_args_string(bad)
    assert isinstance(info.value, InputError)
    assert not Path("/tmp/pwned").exists()


# ============================================================================================= MASt3R .pth
def test_pth_loads_strictly_and_matches_a_direct_load(tmp_path: Path) -> None:
    sd = random_state_dict(TINY)
    path = save_pth(tmp_path / "tiny.pth", sd)
    model, report = load_mast3r(path)
    assert report.format == "mast3r-pth"
    assert report.missing_keys == () and report.unexpected_keys == ()
    assert not model.training
    assert model.config == TINY
    for k, v in model.state_dict().items():
        assert torch.equal(v, sd[k]), k
    reference = MASt3RBackbone(TINY).eval()
    reference.load_state_dict(sd, strict=True)
    img1, img2 = _pair()
    with torch.no_grad():
        a1, a2 = model(img1, img2)
        b1, b2 = reference(img1, img2)
    assert torch.equal(a1.pts3d, b1.pts3d) and torch.equal(a2.desc, b2.desc)
    assert a2.conf.min() >= 1.0


def test_pth_without_mask_token_still_loads(tmp_path: Path) -> None:
    sd = random_state_dict(TINY)
    del sd["mask_token"]
    model, report = load_mast3r(save_pth(tmp_path / "m.pth", sd))
    assert report.missing_keys == ("mask_token",)
    assert torch.equal(model.mask_token, torch.zeros(1, 1, TINY.dec_embed_dim))
    assert not model.mask_token.is_meta


def test_pth_wrong_shape_names_the_first_bad_key_in_file_order(tmp_path: Path) -> None:
    sd = random_state_dict(TINY)
    sd["enc_blocks.1.attn.qkv.weight"] = torch.zeros(10, 64)
    sd["downstream_head2.head_local_features.fc2.bias"] = torch.zeros(3)
    with pytest.raises(CheckpointError) as info:
        load_mast3r(save_pth(tmp_path / "bad.pth", sd))
    e = info.value
    assert isinstance(e, InputError) and e.exit_code == 2
    assert e.key == "enc_blocks.1.attn.qkv.weight"
    assert (e.file_shape, e.model_shape) == ((10, 64), (192, 64))
    assert "'enc_blocks.1.attn.qkv.weight'" in str(e) and "[10, 64]" in str(e) and "[192, 64]" in str(e)


def test_pth_unexpected_key(tmp_path: Path) -> None:
    sd = random_state_dict(TINY)
    sd["downstream_head1.extra.weight"] = torch.zeros(2, 2)
    path = save_pth(tmp_path / "extra.pth", sd)
    with pytest.raises(CheckpointError) as info:
        load_mast3r(path)
    assert info.value.key == "downstream_head1.extra.weight"
    assert info.value.unexpected_keys == ("downstream_head1.extra.weight",)
    assert "[2, 2]" in str(info.value)
    model, report = load_mast3r(path, strict=False)
    assert report.unexpected_keys == ("downstream_head1.extra.weight",)
    assert torch.equal(model.enc_norm.weight, sd["enc_norm.weight"])


def test_pth_missing_key(tmp_path: Path) -> None:
    sd = random_state_dict(TINY)
    del sd["dec_blocks.2.cross_attn.projk.bias"]
    path = save_pth(tmp_path / "missing.pth", sd)
    with pytest.raises(CheckpointError) as info:
        load_mast3r(path)
    assert info.value.key == "dec_blocks.2.cross_attn.projk.bias"
    assert info.value.missing_keys == ("dec_blocks.2.cross_attn.projk.bias",)
    model, report = load_mast3r(path, strict=False)
    assert "dec_blocks.2.cross_attn.projk.bias" in report.missing_keys
    assert not any(p.is_meta for p in model.parameters())
    with torch.no_grad():
        v1, _ = model(*_pair(16, 16))
    assert torch.isfinite(v1.pts3d).all()


def test_pth_without_dec_blocks2_copies_dec_blocks(tmp_path: Path) -> None:
    sd = {k: v for k, v in random_state_dict(TINY).items() if not k.startswith("dec_blocks2.")}
    model, report = load_mast3r(save_pth(tmp_path / "croco.pth", sd))
    assert any("dec_blocks2" in n for n in report.notes)
    assert torch.equal(model.dec_blocks2[1].cross_attn.projq.weight, sd["dec_blocks.1.cross_attn.projq.weight"])


def test_pth_with_an_architecture_mismatch_in_args(tmp_path: Path) -> None:
    path = save_pth(tmp_path / "tiny.pth", random_state_dict(TINY), args=OFFICIAL_ARGS)
    with pytest.raises(CheckpointError) as info:
        load_mast3r(path)
    assert info.value.key == "patch_embed.proj.weight"
    assert (info.value.file_shape, info.value.model_shape) == ((64, 3, 16, 16), (1024, 3, 16, 16))


def test_pth_with_a_malicious_args_string(tmp_path: Path) -> None:
    path = save_pth(tmp_path / "evil.pth", random_state_dict(TINY), args="__import__('os').system('true')")
    with pytest.raises(CheckpointError, match="args.model"):
        load_mast3r(path)


class _OpensAFile:
    """Unpickling this would create a file (a stand-in for arbitrary code in a pickle)."""

    def __init__(self, target: Path) -> None:
        self.target = target

    def __reduce__(self) -> tuple:
        return (open, (str(self.target), "w"))


def test_pth_refuses_to_unpickle_code(tmp_path: Path) -> None:
    target = tmp_path / "created_by_unpickling"
    path = tmp_path / "code.pth"
    torch.save(
        {"model": random_state_dict(TINY), "args": argparse.Namespace(model=TINY_ARGS), "x": _OpensAFile(target)}, path
    )
    with pytest.raises(CheckpointError, match="io.open"):
        load_mast3r(path)
    assert not target.exists()


def test_missing_files_say_what_is_needed_and_where_to_get_it(tmp_path: Path) -> None:
    with pytest.raises(CheckpointNotFoundError) as info:
        load_mast3r(tmp_path / "nope.pth")
    msg = str(info.value)
    assert "nope.pth" in msg and "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric" in msg and "huggingface.co" in msg
    assert info.value.exit_code == 2
    with pytest.raises(CheckpointNotFoundError) as info:
        load_splatt3r(tmp_path / "nope.ckpt")
    assert "epoch=19-step=1200.ckpt" in str(info.value) and "brandonsmart/splatt3r_v1.0" in str(info.value)


def test_not_a_checkpoint(tmp_path: Path) -> None:
    path = tmp_path / "junk.pth"
    path.write_bytes(b"this is not a checkpoint" * 10)
    with pytest.raises(CheckpointError):
        load_mast3r(path)


def test_sha256_is_logged_at_debug_only(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = save_pth(tmp_path / "tiny.pth", random_state_dict(TINY))
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    with caplog.at_level(logging.INFO, logger="macsplat_cli"):
        _, report = load_mast3r(path)
    assert report.sha256 is None and digest not in caplog.text
    with caplog.at_level(logging.DEBUG, logger="macsplat_cli"):
        _, report = load_mast3r(path)
    assert report.sha256 == digest and digest in caplog.text


def test_fusion_loader_logs_its_sha256_through_the_shared_helper(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = save_fusion(ResidualSemanticFusion(FusionConfig(dino_dim=16, hidden_dim=8)), tmp_path / "f.pth")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert sha256_file(path) == digest and sha256_file(path, chunk=7) == digest
    with caplog.at_level(logging.INFO, logger="macsplat_cli"):
        load_fusion(path)
        assert log_sha256(path, logging.getLogger("macsplat_cli.neural.fusion"), "x") is None  # DEBUG off: not read
    assert digest not in caplog.text
    with caplog.at_level(logging.DEBUG, logger="macsplat_cli"):
        load_fusion(path)
    assert f"fusion weights {path} sha256 {digest}" in caplog.text


# ============================================================================================= shared strict check
@pytest.mark.parametrize("error", [CheckpointError, DINOv3CheckpointError, FusionCheckpointError, LPIPSWeightsError])
def test_shared_check_raises_the_loaders_own_error_class(error: type[Exception]) -> None:
    expected = {"a.weight": (4, 3), "a.bias": (4,), "b.weight": (2, 4)}
    sd = {"a.weight": torch.zeros(4, 3), "b.weight": torch.zeros(2, 5), "a.bias": torch.zeros(3)}
    with pytest.raises(error) as info:
        check_state_dict_keys(expected, sd, error, source="f.pth", model="net")
    e = info.value
    assert type(e) is error and isinstance(e, StateDictError) and isinstance(e, InputError)
    # First bad key in file order, both shapes, and how many keys are wrong in all.
    assert e.key == "b.weight" and e.file_shape == (2, 5) and e.model_shape == (2, 4)
    assert str(e).startswith("f.pth: key 'b.weight' has shape [2, 5] in the file but shape [2, 4] in net")
    assert "2 key(s) of another shape, 0 unexpected, 0 missing" in str(e)


def test_shared_check_missing_unexpected_and_non_tensors() -> None:
    expected = {"a": (2,), "b": (3,), "opt": (1,)}
    with pytest.raises(StateDictError, match=r"key 'p.b' \(shape \[3\] in net\) is missing from the file") as info:
        check_state_dict_keys(expected, {"a": torch.zeros(2)}, StateDictError, source="s", model="net",
                              optional={"opt"}, key_prefix="p.")  # fmt: skip
    assert info.value.key == "p.b" and info.value.file_shape is None and info.value.missing_keys == ("p.b",)
    sd = {"a": torch.zeros(2), "b": torch.zeros(3), "extra": torch.zeros(5, 5), "note": "text"}
    with pytest.raises(StateDictError, match=r"unexpected key 'extra' \(shape \[5, 5\] in the file; not in net\)"):
        check_state_dict_keys(expected, sd, StateDictError, source="s", model="net", optional={"opt"})
    got = check_state_dict_keys(
        expected, sd, StateDictError, source="s", optional={"opt"}, allow_unexpected=True, allow_missing=True
    )
    assert got == ((), ("extra", "note"))
    assert check_state_dict_keys(expected, {"a": torch.zeros(2)}, StateDictError, source="s", allow_missing=True) == (
        ("b", "opt"),
        (),
    )
    with pytest.raises(StateDictError, match="'a' has a str, not a tensor, in the file") as info:
        check_state_dict_keys(expected, {"a": "oops"}, StateDictError, source="s", allow_missing=True)
    assert info.value.key == "a" and info.value.file_shape is None and info.value.model_shape == (2,)


# ============================================================================================= Hugging Face folder
def test_hugging_face_folder(tmp_path: Path) -> None:
    safetensors_torch = pytest.importorskip("safetensors.torch")
    sd = random_state_dict(TINY, seed=5)
    reference = MASt3RBackbone(TINY)
    reference.load_state_dict(sd)
    folder = tmp_path / "hf"
    folder.mkdir()
    safetensors_torch.save_model(reference, str(folder / "model.safetensors"))
    kwargs = TINY.to_kwargs()
    (folder / "config.json").write_text(json.dumps(kwargs))  # writes -Infinity / Infinity
    stored = safetensors_torch.load_file(str(folder / "model.safetensors"))
    assert len(stored) < len(sd)  # shared tensors are stored once: the loader must fill the aliases
    model, report = load_mast3r(folder)
    assert report.format == "mast3r-hf" and report.missing_keys == ()
    assert any("alias" in n for n in report.notes)
    for k, v in model.state_dict().items():
        assert torch.equal(v, sd[k]), k
    # Also accepted: the weights file itself, and infinities written as strings.
    kwargs["depth_mode"] = ["exp", "-inf", "inf"]
    (folder / "config.json").write_text(json.dumps(kwargs))
    model2, _ = load_mast3r(folder / "model.safetensors")
    assert torch.equal(model2.enc_norm.bias, sd["enc_norm.bias"])


def test_hugging_face_folder_missing_parts(tmp_path: Path) -> None:
    folder = tmp_path / "hf"
    folder.mkdir()
    with pytest.raises(CheckpointNotFoundError, match="config.json"):
        load_mast3r(folder)
    (folder / "config.json").write_text(json.dumps(TINY.to_kwargs()))
    with pytest.raises(CheckpointNotFoundError, match="model.safetensors"):
        load_mast3r(folder)
    (folder / "config.json").write_text(json.dumps({"enc_depth": 2, "frobnicate": 1}))
    (folder / "model.safetensors").write_bytes(b"")
    with pytest.raises(CheckpointError, match="frobnicate"):
        load_mast3r(folder)


# ============================================================================================= Splatt3R .ckpt
def _save_splatt3r(path: Path, sh_coeffs: int = 1, seed: int = 0) -> tuple[dict, dict]:
    """A Lightning-style checkpoint; its hyper-parameters hold an object of a (fake) ``omegaconf`` class."""
    cfg = TINY.replace(head_type="gaussian_head", desc_conf_mode=("exp", 1.0, math.inf))
    backbone_sd = random_state_dict(cfg, seed=seed)
    torch.manual_seed(seed)
    head_sd = GaussianHead(cfg, GaussianHeadConfig(sh_coeffs=sh_coeffs)).state_dict()
    state = {"encoder." + k: v for k, v in {**backbone_sd, **head_sd}.items()}
    state["lpips_criterion.net.slice1.0.weight"] = torch.zeros(64, 3, 3, 3)
    state["lpips_criterion.scaling_layer.shift"] = torch.zeros(1, 3, 1, 1)

    module = types.ModuleType("omegaconf")

    class DictConfig:
        def __init__(self, content: dict) -> None:
            self._content = content

        def __reduce__(self) -> tuple:  # what a real one does is irrelevant: it must never run
            return (DictConfig, (self._content,))

    DictConfig.__module__ = "omegaconf"
    DictConfig.__qualname__ = "DictConfig"
    module.DictConfig = DictConfig
    sys.modules["omegaconf"] = module
    try:
        torch.save(
            {
                "state_dict": state,
                "hyper_parameters": {"config": DictConfig({"use_offsets": True})},
                "epoch": 19,
                "global_step": 1200,
                "pytorch-lightning_version": "2.3.0",
                "optimizer_states": [{"state": {}, "param_groups": [{"lr": 1e-5}]}],
                "loops": {"fit_loop": collections.defaultdict(int, {"epoch_progress": 19})},
            },
            path,
        )
    finally:
        del sys.modules["omegaconf"]
    return backbone_sd, head_sd


def test_splatt3r_checkpoint_loads(tmp_path: Path) -> None:
    path = tmp_path / "splatt3r.ckpt"
    backbone_sd, head_sd = _save_splatt3r(path)
    cfg = TINY.replace(head_type="gaussian_head", desc_conf_mode=("exp", 1.0, math.inf))
    backbone, head, report = load_splatt3r(path, backbone_config=cfg)
    assert report.format == "splatt3r-ckpt"
    assert set(report.ignored_keys) == {"lpips_criterion.net.slice1.0.weight", "lpips_criterion.scaling_layer.shift"}
    assert report.missing_keys == () and report.unexpected_keys == ()
    assert head.config.sh_coeffs == 1  # inferred from the last convolution's 14 channels
    for k, v in backbone.state_dict().items():
        assert torch.equal(v, backbone_sd[k]), k
    for k, v in head.state_dict().items():
        assert torch.equal(v, head_sd[k]), k
    img1, img2 = _pair()
    with torch.no_grad():
        v1, v2 = backbone(img1, img2)
        g1, g2 = head(v1, v2, (img1 + 1) / 2, (img2 + 1) / 2)
    assert v1.desc_conf.min() >= 1.0  # Splatt3R's construction: desc_conf = 1 + exp(x)
    assert g2.means.shape == (1, 32, 48, 3) and g2.sh.shape == (1, 32, 48, 1, 3)


def test_splatt3r_checkpoint_infers_sh_size_and_checks_shapes(tmp_path: Path) -> None:
    path = tmp_path / "sh4.ckpt"
    _save_splatt3r(path, sh_coeffs=4)
    cfg = TINY.replace(head_type="gaussian_head", desc_conf_mode=("exp", 1.0, math.inf))
    _, head, _ = load_splatt3r(path, backbone_config=cfg)
    assert head.config.sh_coeffs == 4
    # Without a config the released size is assumed: the tiny file then fails on its first key, with "encoder.".
    with pytest.raises(CheckpointError) as info:
        load_splatt3r(path)
    assert info.value.key == "encoder.patch_embed.proj.weight"
    assert info.value.model_shape == (1024, 3, 16, 16)


def test_splatt3r_loader_rejects_a_mast3r_file(tmp_path: Path) -> None:
    path = save_pth(tmp_path / "m.pth", random_state_dict(TINY))
    with pytest.raises(CheckpointError, match="state_dict"):
        load_splatt3r(path)
