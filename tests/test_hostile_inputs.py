"""Hostile and odd inputs (issue 16): declared sizes are checked before anything is allocated.

Each case crafts a small malicious file (a PNG header claiming 30000×30000 pixels, a PLY header
claiming 10¹¹ vertices, a config asking for a million blocks, a safetensors header with negative
shapes, JSON nested 200,000 levels deep, ``/dev/zero`` behind an input path) and checks that the
CLI exits with status 2 and one ``error:`` line naming the problem, quickly and without a traceback.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli._limits import MAX_JSON_BYTES, MAX_RENDER_SIDE, check_render_size, json_depth, read_json_file
from macsplat_cli._state_dict import read_safetensors
from macsplat_cli.camera_formats import read_colmap_text, read_nerfstudio
from macsplat_cli.cameras import Camera, CameraSet, load_cameras, save_cameras
from macsplat_cli.errors import CameraFileError, ImageReadError, InputError, PlyFormatError
from macsplat_cli.images import load_image, save_image
from macsplat_cli.neural.checkpoints import CheckpointError, read_mast3r_checkpoint
from macsplat_cli.neural.config import BackboneConfig
from macsplat_cli.neural.constructor import ModelConfigError, parse_constructor_string
from macsplat_cli.neural.dinov3 import DINOv3CheckpointError, DINOv3Config, load_dinov3
from macsplat_cli.neural.fusion import (
    FusionCheckpointError,
    FusionConfig,
    ResidualSemanticFusion,
    load_fusion,
    save_fusion,
)
from macsplat_cli.ply import read_ply, write_ply
from macsplat_cli.render import render_camera

from support.checkpoints import TINY, random_state_dict, save_pth
from support.cli import run_cli
from support.gaussians import random_gaussians

K = np.array([[120.0, 0.0, 40.0], [0.0, 120.0, 30.0], [0.0, 0.0, 1.0]])
DEEP = 200_000  # JSON nesting that overflows Python's recursion limit
HAS_DEV_ZERO = os.path.exists("/dev/zero")


# ------------------------------------------------------------------------------ helpers
def run(*args: str | Path) -> tuple[int, str, str]:
    """``main(args)`` in process, stdout and stderr captured."""
    return run_cli(list(args))


def error_line(code: int, out: str, err: str) -> str:
    """The one ``error:`` line of a run that exited with status 2 (progress lines of failed stages allowed)."""
    assert code == 2, err
    assert out == "", out
    assert "Traceback" not in err and "internal error" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines and lines[-1].startswith("error: "), err
    assert sum("error:" in ln for ln in lines) == 1, err
    assert all("failed" in ln for ln in lines[:-1]), err
    return lines[-1]


def png_bytes(width: int, height: int) -> bytes:
    """A valid 1-bit greyscale PNG of ``width × height`` black pixels: tiny on disk, huge once decoded."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    row = b"\x00" * (1 + (width + 7) // 8)  # filter byte + packed bits
    z = zlib.compressobj(9)
    idat = b"".join(z.compress(row) for _ in range(height)) + z.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def deep_json(depth: int = DEEP) -> str:
    return "[" * depth + "]" * depth


def safetensors_bytes(header: dict, data: bytes) -> bytes:
    h = json.dumps(header).encode()
    return struct.pack("<Q", len(h)) + h + data


@pytest.fixture
def photos(tmp_path: Path) -> tuple[Path, Path]:
    """Two small valid photos (noise), enough to get past the image checks."""
    g = np.random.default_rng(0)
    folder = tmp_path / "in"
    folder.mkdir()
    a, b = folder / "a.png", folder / "b.png"
    save_image(a, g.random((64, 96, 3)).astype(np.float32))
    save_image(b, g.random((64, 96, 3)).astype(np.float32))
    return a, b


@pytest.fixture
def scene(tmp_path: Path) -> tuple[Path, Path]:
    folder = tmp_path / "scene"
    folder.mkdir()
    write_ply(folder / "scene.ply", random_gaussians(50, seed=1, sh_degree=0))
    save_cameras(folder / "cams.json", CameraSet([Camera("a", 80, 60, K, np.eye(4))]))
    return folder / "scene.ply", folder / "cams.json"


def _reconstruct(tmp_path: Path, a: Path, b: Path, *extra: str | Path) -> tuple[int, str, str]:
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    code, stdout, err = run("reconstruct", a, b, "-o", out / "scene.ply", "-q", *extra)
    assert list(out.iterdir()) == []  # nothing written
    return code, stdout, err


# ------------------------------------------------------------------------------ images
def test_decompression_bomb_png_is_refused_before_decoding(tmp_path: Path, photos: tuple[Path, Path]) -> None:
    """A ~110 kB PNG that decodes to 30000×30000 (900 MP) is refused from its header."""
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(png_bytes(30000, 30000))
    assert bomb.stat().st_size < 1_000_000
    line = error_line(*_reconstruct(tmp_path, bomb, photos[1]))
    assert "bomb.png" in line and "30000x30000" in line and "MACSPLAT_MAX_MEGAPIXELS" in line, line


def test_megapixel_cap_follows_the_environment(
    tmp_path: Path, photos: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MACSPLAT_MAX_MEGAPIXELS", "0.005")  # 5000 px: the 96×64 photos (6144 px) are too large
    with pytest.raises(ImageReadError, match=r"96x64.*MACSPLAT_MAX_MEGAPIXELS"):
        load_image(photos[0])
    monkeypatch.setenv("MACSPLAT_MAX_MEGAPIXELS", "0.007")
    assert load_image(photos[0]).width == 96
    monkeypatch.setenv("MACSPLAT_MAX_MEGAPIXELS", "lots")
    line = error_line(*_reconstruct(tmp_path, *photos))
    assert "MACSPLAT_MAX_MEGAPIXELS='lots'" in line, line


@pytest.mark.skipif(not HAS_DEV_ZERO, reason="needs /dev/zero")
def test_dev_zero_as_an_image_is_refused(tmp_path: Path, photos: tuple[Path, Path]) -> None:
    zero = tmp_path / "zero.png"
    zero.symlink_to("/dev/zero")
    line = error_line(*_reconstruct(tmp_path, zero, photos[1]))
    assert "zero.png" in line and "not a regular file" in line, line


def test_a_folder_as_an_image_is_refused(tmp_path: Path) -> None:
    (tmp_path / "dir.png").mkdir()
    with pytest.raises(ImageReadError, match="is a directory"):
        load_image(tmp_path / "dir.png")


# ------------------------------------------------------------------------------ camera, pose and intrinsics files
@pytest.mark.skipif(not HAS_DEV_ZERO, reason="needs /dev/zero")
def test_dev_zero_as_intrinsics_or_pose_is_refused(
    tmp_path: Path, photos: tuple[Path, Path], scene: tuple[Path, Path]
) -> None:
    zero = tmp_path / "zero.json"
    zero.symlink_to("/dev/zero")
    line = error_line(*_reconstruct(tmp_path, *photos, "--intrinsics", zero))
    assert "zero.json" in line and "not a regular file" in line, line
    line = error_line(*run("render", scene[0], "--pose", "/dev/zero", "-o", tmp_path / "out" / "v.png"))
    assert "/dev/zero" in line and "not a regular file" in line, line


def test_deeply_nested_json_camera_files(tmp_path: Path, photos: tuple[Path, Path], scene: tuple[Path, Path]) -> None:
    """JSON nested 200,000 levels deep (RecursionError in the parser): exit 2, not an internal error."""
    deep = tmp_path / "deep.json"
    deep.write_text(deep_json())
    line = error_line(*_reconstruct(tmp_path, *photos, "--intrinsics", deep))
    assert "deep.json" in line and "nested too deeply" in line, line
    line = error_line(*run("render", scene[0], "--pose", deep, "-o", tmp_path / "out" / "v.png"))
    assert "deep.json" in line and "nested too deeply" in line, line
    # Objects too, and nesting the parser accepts but beyond the cap (the formats need 5 levels).
    deep.write_text('{"a":' * DEEP + "1" + "}" * DEEP)
    with pytest.raises(CameraFileError, match="nested too deeply"):
        load_cameras(deep)
    deep.write_text(deep_json(500))
    with pytest.raises(CameraFileError, match="nested too deeply"):
        load_cameras(deep)
    with pytest.raises(CameraFileError, match="nested too deeply"):
        read_nerfstudio(deep)


def test_oversized_json_camera_file_is_refused(tmp_path: Path, scene: tuple[Path, Path]) -> None:
    big = tmp_path / "big.json"
    with open(big, "wb") as f:
        f.truncate(MAX_JSON_BYTES + 1)  # sparse: no disk used
    line = error_line(*run("render", scene[0], "--pose", big, "-o", tmp_path / "out" / "v.png"))
    assert "big.json" in line and "too large" in line, line


def test_colmap_text_must_be_a_regular_file(tmp_path: Path) -> None:
    (tmp_path / "cameras.txt").mkdir()
    (tmp_path / "images.txt").write_text("")
    with pytest.raises(CameraFileError, match="cameras.txt"):
        read_colmap_text(tmp_path)


def test_json_limits_helpers(tmp_path: Path) -> None:
    assert json_depth(1) == 0 and json_depth([]) == 1 and json_depth({"a": [[1], {"b": 2}]}) == 3
    p = tmp_path / "ok.json"
    p.write_text('{"cameras": [{"K": [[1, 0, 0]]}]}')
    assert read_json_file(p, InputError)["cameras"][0]["K"] == [[1, 0, 0]]
    with pytest.raises(InputError, match="no such file"):
        read_json_file(tmp_path / "missing.json", InputError)


# ------------------------------------------------------------------------------ render size
def test_render_size_is_bounded(tmp_path: Path, scene: tuple[Path, Path]) -> None:
    """--width 100000 --height 100000 (10 gigapixels): exit 2 before any framebuffer is allocated."""
    code, out, err = run(
        "render", scene[0], "--pose", scene[1], "-o", tmp_path / "v.png", "--width", "100000", "--height", "100000"
    )
    line = error_line(code, out, err)
    assert "100000x100000" in line and "too large" in line, line
    assert not (tmp_path / "v.png").exists()
    # A camera file may carry the size too; the library entry refuses it.
    g = random_gaussians(10, seed=0, sh_degree=0)
    with pytest.raises(InputError, match="too large"):
        render_camera(g, Camera("wide", MAX_RENDER_SIDE + 1, 16, K, np.eye(4)))
    with pytest.raises(InputError, match="too large"):
        check_render_size(12000, 12000)  # each side fits, the pixel count does not
    check_render_size(MAX_RENDER_SIDE, 1024)


# ------------------------------------------------------------------------------ PLY
def _ascii_ply(count: int) -> bytes:
    props = "".join(
        f"property float {n}\n"
        for n in ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2")
        + ("rot_0", "rot_1", "rot_2", "rot_3")
    )
    head = f"ply\nformat ascii 1.0\nelement vertex {count}\n{props}end_header\n"
    return head.encode() + b"0 0 0 0 0 0 0 0 0 0 1 0 0 0\n" * 3


def test_ply_header_claiming_1e11_vertices_is_refused(tmp_path: Path, scene: tuple[Path, Path]) -> None:
    """An ASCII header claiming 99,999,999,999 vertices (plyfile would allocate ~6 TiB)."""
    bad = tmp_path / "huge.ply"
    bad.write_bytes(_ascii_ply(99_999_999_999))
    line = error_line(*run("render", bad, "--pose", scene[1], "-o", tmp_path / "v.png"))
    assert "huge.ply" in line and "99999999999" in line, line
    # The same header with its 3 vertices reads fine.
    ok = tmp_path / "ok.ply"
    ok.write_bytes(_ascii_ply(3))
    assert len(read_ply(ok)) == 3


@pytest.mark.parametrize("fmt", ["binary_big_endian", "binary_little_endian"])
def test_binary_ply_with_more_vertices_than_bytes_is_refused(tmp_path: Path, fmt: str) -> None:
    head = f"ply\nformat {fmt} 1.0\nelement vertex 1000000000\nproperty double x\nproperty uchar flag\n"
    head += "element face 5\nproperty list uchar int vertex_indices\nend_header\n"
    bad = tmp_path / "short.ply"
    bad.write_bytes(head.encode() + bytes(900))
    with pytest.raises(PlyFormatError, match=r"1000000000 'vertex'.*9000000005 bytes"):
        read_ply(bad)


def test_ply_must_be_a_regular_file(tmp_path: Path) -> None:
    if not HAS_DEV_ZERO:
        pytest.skip("needs /dev/zero")
    with pytest.raises(PlyFormatError, match="not a regular file"):
        read_ply("/dev/zero")


# ------------------------------------------------------------------------------ model configurations
def _hf_folder(folder: Path, config: object | str, weights: bytes | None = None) -> Path:
    folder.mkdir()
    (folder / "config.json").write_text(config if isinstance(config, str) else json.dumps(config))
    (folder / "model.safetensors").write_bytes(weights if weights is not None else safetensors_bytes({}, b""))
    return folder


def test_mast3r_config_with_a_million_blocks_is_refused(tmp_path: Path, photos: tuple[Path, Path]) -> None:
    """``enc_depth: 1000000`` in config.json used to build a million blocks (minutes, memory climbing)."""
    folder = _hf_folder(tmp_path / "hf", {**TINY.to_kwargs(), "enc_depth": 1_000_000})
    line = error_line(*_reconstruct(tmp_path, *photos, "--backend", "neural", "--weights", folder))
    assert "config.json" in line and "enc_depth=1000000" in line, line


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"dec_depth": 65}, "dec_depth=65"),
        ({"enc_embed_dim": 65536, "enc_num_heads": 16}, "enc_embed_dim=65536"),
        ({"enc_num_heads": 512, "enc_embed_dim": 4096}, "enc_num_heads=512"),
        ({"mlp_ratio": float("inf")}, "mlp_ratio"),
        ({"mlp_ratio": 1e6}, "mlp_ratio"),
        ({"local_mlp_ratio": float("nan")}, "local_mlp_ratio"),
        ({"dpt_feature_dim": 10**6}, "dpt_feature_dim"),
        ({"local_feat_dim": 10**6}, "local_feat_dim"),
        ({"rope_freq": float("inf")}, "rope_freq"),
    ],
)
def test_backbone_config_bounds(change: dict, match: str) -> None:
    with pytest.raises(ModelConfigError, match=match):
        TINY.replace(**change)


def test_released_and_tiny_configs_are_within_bounds() -> None:
    BackboneConfig()
    BackboneConfig.tiny()
    for name in ("vits16", "vitl16", "tiny"):
        DINOv3Config.preset(name)
    # ViT-7B's sizes (40 blocks of width 4096, SwiGLU 8192) are accepted.
    DINOv3Config("vit7b16", embed_dim=4096, depth=40, num_heads=32, ffn="swiglu", ffn_hidden_dim=8192)


def test_constructor_string_nesting_and_null_bytes() -> None:
    """Parser recursion, parser stack overflow, null bytes and megabyte strings: a typed error, never a crash."""
    for s in ["AsymmetricMASt3R(enc_depth=" + "-" * n + "1)" for n in (990, 3000, 50_000)] + [
        "AsymmetricMASt3R(enc_depth=" + "(" * 5000 + "1" + ")" * 5000 + ")",
        "AsymmetricMASt3R(enc_depth=1\x00)",
        "AsymmetricMASt3R(enc_depth=1" + " " * 1_000_000 + ")",
    ]:
        with pytest.raises(ModelConfigError):
            parse_constructor_string(s)


def test_deeply_nested_mast3r_config_json(tmp_path: Path, photos: tuple[Path, Path]) -> None:
    folder = _hf_folder(tmp_path / "hf", deep_json())
    line = error_line(*_reconstruct(tmp_path, *photos, "--backend", "neural", "--weights", folder))
    assert "config.json" in line and "nested too deeply" in line, line
    (folder / "config.json").write_text(json.dumps({**TINY.to_kwargs(), "img_size": json.loads(deep_json(900))}))
    with pytest.raises(CheckpointError, match="nested too deeply"):
        read_mast3r_checkpoint(folder)


@pytest.mark.parametrize(
    ("change", "match"),
    [({"depth": 1000}, "depth"), ({"embed_dim": 1 << 20, "num_heads": 16}, "embed_dim"),
     ({"patch_size": 4096}, "patch_size"), ({"ffn_hidden_dim": 1 << 20}, "ffn_hidden_dim"),
     ({"n_storage_tokens": 10**6}, "n_storage_tokens"), ({"num_heads": 1024, "embed_dim": 4096}, "num_heads")],
)  # fmt: skip
def test_dinov3_config_bounds(change: dict, match: str) -> None:
    kw = {"name": "x", "embed_dim": 64, "depth": 2, "num_heads": 2, "ffn": "mlp", "ffn_hidden_dim": 128, **change}
    with pytest.raises(InputError, match=match):
        DINOv3Config(**kw)


def test_dinov3_safetensors_with_a_hundred_thousand_blocks(tmp_path: Path) -> None:
    """Empty tensors cost a header line each: depth must be bounded before the encoder is built."""
    header = {"cls_token": {"dtype": "F32", "shape": [1, 1, 0], "data_offsets": [0, 0]},
              "patch_embed.proj.weight": {"dtype": "F32", "shape": [0, 3, 16, 16], "data_offsets": [0, 0]},
              "blocks.0.mlp.fc1.weight": {"dtype": "F32", "shape": [16, 0], "data_offsets": [0, 0]}}  # fmt: skip
    for i in range(100_000):
        header[f"blocks.{i}.norm1.weight"] = {"dtype": "F32", "shape": [0], "data_offsets": [0, 0]}
    header["rope_embed.periods"] = {"dtype": "F32", "shape": [1], "data_offsets": [0, 4]}
    header["cls_token"]["shape"] = [1, 1, 4]
    header["cls_token"]["data_offsets"] = [4, 20]
    p = tmp_path / "blocks.safetensors"
    p.write_bytes(safetensors_bytes(header, struct.pack("<5f", 100.0, 0, 0, 0, 0)))
    with pytest.raises(DINOv3CheckpointError, match=r"blocks\.safetensors.*depth"):
        load_dinov3(p)


def test_dinov3_hf_config_values_are_checked(tmp_path: Path) -> None:
    folder = _hf_folder(tmp_path / "hf", deep_json())
    with pytest.raises(DINOv3CheckpointError, match="nested too deeply"):
        load_dinov3(folder)
    (folder / "config.json").write_text("[1, 2]")
    with pytest.raises(DINOv3CheckpointError, match="JSON object"):
        load_dinov3(folder)


def test_fusion_config_bounds(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="depth"):
        FusionConfig(depth=1_000_000)
    with pytest.raises(ValueError, match="hidden_dim"):
        FusionConfig(hidden_dim=1 << 20)
    config = {"desc_dim": 24, "dino_dim": 64, "hidden_dim": 16, "depth": 1_000_000}
    payload = {"format": "macsplat.residual_semantic_fusion", "version": 1, "config": config, "state_dict": {}}
    torch.save(payload, tmp_path / "f.pth")
    with pytest.raises(FusionCheckpointError, match="depth"):
        load_fusion(tmp_path / "f.pth")


# ------------------------------------------------------------------------------ safetensors
@pytest.mark.parametrize(
    ("shape", "offsets", "match"),
    [
        ([-2, -2], [0, 16], "shape"),
        ([-1, 4], [16, 0], "shape"),
        ([-1, 4], [0, 16], "shape"),
        ([2, 2], [8, 24], "offsets"),  # past the end of the data
        ([4], [8, 4], "offsets"),  # end before begin
        ([3], [0, 16], "offsets"),  # 12 bytes of shape, 16 of offsets
        ([True, 4], [0, 16], "shape"),
        ("44", [0, 16], "shape"),
        ([1 << 62, 1 << 62, 0], [0, 0], "shape"),
    ],
)
def test_safetensors_shapes_and_offsets_are_validated(tmp_path: Path, shape: object, offsets: list, match: str) -> None:
    p = tmp_path / "w.safetensors"
    p.write_bytes(safetensors_bytes({"t": {"dtype": "F32", "shape": shape, "data_offsets": offsets}}, bytes(16)))
    with pytest.raises(InputError, match=match):
        read_safetensors(p)


def test_safetensors_deep_header_and_dev_zero(tmp_path: Path) -> None:
    p = tmp_path / "deep.safetensors"
    h = deep_json().encode()
    p.write_bytes(struct.pack("<Q", len(h)) + h)
    with pytest.raises(InputError, match="nested too deeply"):
        read_safetensors(p)
    if HAS_DEV_ZERO:
        with pytest.raises(InputError, match="not a regular file"):
            read_safetensors("/dev/zero")


def _bad_safetensors() -> bytes:
    return safetensors_bytes({"patch_embed.proj.weight": {"dtype": "F32", "shape": [-2, -2], "data_offsets": [0, 16]}},
                             bytes(16))  # fmt: skip


def test_negative_shapes_in_the_mast3r_folder(tmp_path: Path, photos: tuple[Path, Path]) -> None:
    folder = _hf_folder(tmp_path / "hf", TINY.to_kwargs(), _bad_safetensors())
    line = error_line(*_reconstruct(tmp_path, *photos, "--backend", "neural", "--weights", folder))
    assert "model.safetensors" in line and "patch_embed.proj.weight" in line and "[-2, -2]" in line, line


def test_negative_shapes_in_dino_weights(tmp_path: Path, photos: tuple[Path, Path]) -> None:
    weights = save_pth(tmp_path / "mast3r.pth", random_state_dict(TINY))
    fusion = tmp_path / "fusion.pth"
    save_fusion(ResidualSemanticFusion(FusionConfig(dino_dim=64, hidden_dim=16)), fusion)
    dino = tmp_path / "dino.safetensors"
    dino.write_bytes(_bad_safetensors())
    opts = ("--backend", "neural", "--weights", weights, "--dino", dino, "--fusion", fusion)
    line = error_line(*_reconstruct(tmp_path, *photos, *opts))
    assert "dino.safetensors" in line and "[-2, -2]" in line, line
