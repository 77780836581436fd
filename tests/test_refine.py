"""Per-view Gaussian maps (world transform, pooling) and the MAC-regularised refinement,
from the library and from ``macsplat reconstruct --refine``."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli import synthetic as syn
from macsplat_cli.cameras import CameraSet, save_cameras
from macsplat_cli.cli import main
from macsplat_cli.gaussians import quat_to_rotmat
from macsplat_cli.images import save_image
from macsplat_cli.mac import MACConfig, mac_loss
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig, Reconstruction
from macsplat_cli.pipeline.types import PixelGaussians
from macsplat_cli.pipeline.views import ViewConfig
from macsplat_cli.refine import RefineConfig, _mac_maps, refine

D = torch.float64


def _random_maps(h: int, w: int, seed: int, valid: torch.Tensor | None = None) -> PixelGaussians:
    g = torch.Generator().manual_seed(seed)
    T = torch.eye(4, dtype=D)
    T[:3, :3] = quat_to_rotmat(torch.randn(4, generator=g, dtype=D))
    T[:3, 3] = torch.randn(3, generator=g, dtype=D)
    means = torch.randn(h, w, 3, generator=g, dtype=D)
    means[..., 2] += 4
    return PixelGaussians(
        means=means,
        log_scales=torch.randn(h, w, 3, generator=g, dtype=D) - 3,
        quats=torch.randn(h, w, 4, generator=g, dtype=D),
        opacity_logits=torch.randn(h, w, generator=g, dtype=D),
        sh=torch.randn(h, w, 1, 3, generator=g, dtype=D),
        valid=torch.ones(h, w, dtype=torch.bool) if valid is None else valid,
        cam_to_world=T,
    )


# ------------------------------------------------------------------------------ PixelGaussians
def test_to_world_moves_means_and_rotations_into_the_world_frame() -> None:
    valid = torch.tensor([[True, False, True], [True, True, False]])
    m = _random_maps(2, 3, 0, valid)
    g = m.to_world()
    R, t = m.cam_to_world[:3, :3], m.cam_to_world[:3, 3]
    assert len(g) == int(valid.sum())
    torch.testing.assert_close(g.means, m.means[valid] @ R.T + t)
    torch.testing.assert_close(quat_to_rotmat(g.quats), R @ quat_to_rotmat(m.quats[valid]))
    torch.testing.assert_close(g.log_scales, m.log_scales[valid])  # rotation does not change the scales
    torch.testing.assert_close(g.opacity_logits, m.opacity_logits[valid])


def test_pooled_averages_the_valid_pixels_of_each_block() -> None:
    valid = torch.ones(4, 4, dtype=torch.bool)
    valid[0, 1] = False  # block (0, 0) averages 3 pixels
    valid[2:, 2:] = False  # block (1, 1) is empty
    m = _random_maps(4, 4, 1, valid)
    p = m.pooled(2)
    assert p.size == (2, 2)
    np.testing.assert_array_equal(p.valid.numpy(), [[True, True], [True, False]])
    block = m.means[:2, :2][valid[:2, :2]]
    torch.testing.assert_close(p.means[0, 0], block.mean(0))
    torch.testing.assert_close(p.log_scales[0, 0], m.log_scales[:2, :2][valid[:2, :2]].mean(0) + np.log(2))
    torch.testing.assert_close(p.sh[1, 0], m.sh[2:, :2].reshape(4, 1, 3).mean(0))
    torch.testing.assert_close(torch.linalg.vector_norm(p.quats[0, 0]), torch.tensor(1.0, dtype=D))
    assert m.pooled(1) is m
    with pytest.raises(ValueError, match="pooled"):
        _random_maps(3, 4, 2).pooled(2)


# ------------------------------------------------------------------------------ refinement
SIZE = (256, 192)


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A textured room pair 12° apart, rendered at 256×192, and its true cameras."""
    folder = tmp_path_factory.mktemp("refine_pair")
    scene = syn.make_scene("room", 3)
    cam0, cam1 = syn.orbit_pair("room", 12.0, width=SIZE[0], height=SIZE[1], fov_deg=60.0)
    save_image(folder / "a.png", syn.render(scene, cam0).image)
    save_image(folder / "b.png", syn.render(scene, cam1).image)
    save_cameras(folder / "cameras.json", CameraSet([cam0, cam1]))
    return folder / "a.png", folder / "b.png", folder / "cameras.json"


@pytest.fixture(scope="module")
def rec(pair: tuple[Path, Path, Path]) -> Reconstruction:
    cfg = ReconstructConfig(views=ViewConfig(size=SIZE[0], intrinsics=pair[2]))
    return Pipeline(cfg).run(pair[:2])


def _mac_value(rec: Reconstruction, maps: list[PixelGaussians], scale: int) -> float:
    inl = rec.geometry.inliers
    xy0 = torch.tensor(inl.xy0 / scale, dtype=torch.float32)
    xy1 = torch.tensor(inl.xy1 / scale, dtype=torch.float32)
    c2w = [m.cam_to_world.float()[None] for m in maps]
    out = mac_loss(*_mac_maps(maps), xy0, xy1, torch.zeros(len(xy0), dtype=torch.long),
                   torch.tensor(inl.conf, dtype=torch.float32), c2w[0], c2w[1])  # fmt: skip
    return float(out.loss)


def test_refinement_lowers_the_loss_and_leaves_the_input_alone(rec: Reconstruction) -> None:
    before = [t.clone() for t in rec.maps[0].tensors()]
    out = refine(rec.views, rec.geometry, rec.maps, RefineConfig(steps=12, scale=4, min_steps=100))
    assert out.steps == 12 and not out.stopped_early and len(out.history) == 12
    assert out.history[-1]["photo"] < 0.9 * out.history[0]["photo"]
    assert {"photo", "mac", "mac_pos", "mac_shape", "loss"} <= set(out.history[0])
    h, w = rec.maps[0].size
    assert [m.size for m in out.maps] == [(h // 4, w // 4)] * 2
    assert not any(t.requires_grad for m in out.maps for t in m.tensors())
    for t0, t1 in zip(before, rec.maps[0].tensors()):
        assert torch.equal(t0, t1)


def test_mac_term_pulls_matched_gaussians_together(rec: Reconstruction) -> None:
    """With MAC (weighted up to make the effect clear in a few steps), the matched Gaussians of
    the two views end up closer than without it; without MAC the history has no MAC term."""
    strong = MACConfig(weight=25.0)
    cfg = RefineConfig(steps=8, scale=4, min_steps=100, mac=strong)
    with_mac = refine(rec.views, rec.geometry, rec.maps, cfg)
    no_mac = refine(rec.views, rec.geometry, rec.maps, RefineConfig(steps=8, scale=4, min_steps=100, use_mac=False))
    assert "mac" not in no_mac.history[0]
    start = _mac_value(rec, [m.pooled(4) for m in rec.maps], 4)
    assert _mac_value(rec, with_mac.maps, 4) < 0.8 * min(start, _mac_value(rec, no_mac.maps, 4))


def test_refinement_stops_early_on_a_plateau(rec: Reconstruction) -> None:
    cfg = RefineConfig(steps=40, scale=4, min_steps=4, plateau_window=2, plateau_tol=10.0)
    out = refine(rec.views, rec.geometry, rec.maps, cfg)
    assert out.stopped_early and out.steps == 4


# ------------------------------------------------------------------------------ CLI
def _main(args: list[str | Path]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("mac", [True, False])
def test_cli_reconstruct_refine(pair: tuple[Path, Path, Path], tmp_path: Path, mac: bool) -> None:
    args = ["reconstruct", pair[0], pair[1], "-o", tmp_path / "s.ply", "--size", str(SIZE[0]), "--refine", "3",
            "--report", tmp_path / "r.json", "--intrinsics", pair[2]] + ([] if mac else ["--no-mac"])  # fmt: skip
    code, _, err = _main(args)
    assert code == 0, err
    report = json.loads((tmp_path / "r.json").read_text())
    r = report["refine"]
    assert r["max_steps"] == 3 and 1 <= r["steps"] <= 3 and r["mac"] is mac and r["scale"] == 2
    assert ("mac" in r["loss_last"]) is mac
    assert report["times_s"]["refine"] > 0
    # refined maps are pooled 2×2: about a quarter of the unrefined Gaussians
    assert 0 < report["gaussians"] <= (SIZE[0] // 2) * (SIZE[1] // 2) * 2


@pytest.mark.parametrize(
    ("option", "message"),
    [(["--refine", "abc"], "--refine"), (["--refine", "-2"], "--refine"), (["--refine-scale", "9"], "refine-scale")],
)
def test_cli_bad_refine_values(pair: tuple[Path, Path, Path], tmp_path: Path, option: list[str], message: str) -> None:
    code, _, err = _main(["reconstruct", pair[0], pair[1], "-o", tmp_path / "s.ply", *option])
    assert code == 2
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "s.ply").exists()


def test_refinement_with_an_lpips_term(rec: Reconstruction) -> None:
    """An LPIPS model (random weights here) adds its term; the loss still goes down."""
    from macsplat_cli.lpips import LPIPS

    torch.manual_seed(0)
    model = LPIPS()
    for lin in model.lins:
        lin.weight.abs_()  # the official linear layers are non-negative
    out = refine(rec.views, rec.geometry, rec.maps, RefineConfig(steps=4, scale=4, min_steps=100), lpips=model)
    assert all(np.isfinite(h["lpips"]) and h["lpips"] > 0 for h in out.history)
    assert out.history[-1]["loss"] < out.history[0]["loss"]


def test_cli_refine_with_lpips_weights(pair: tuple[Path, Path, Path], tmp_path: Path) -> None:
    from macsplat_cli.lpips import LPIPS

    model = LPIPS()
    convs = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)
    torch.save({f"features.{i}.{p}": getattr(model.features[i], p).detach() for i in convs for p in ("weight", "bias")},
               tmp_path / "vgg16-397923af.pth")  # fmt: skip
    torch.save({f"lin{k}.model.1.weight": lin.weight.detach().abs() for k, lin in enumerate(model.lins)},
               tmp_path / "vgg.pth")  # fmt: skip
    base = ["reconstruct", pair[0], pair[1], "-o", tmp_path / "s.ply", "--size", str(SIZE[0]), "-q",
            "--lpips-weights", tmp_path]  # fmt: skip
    code, _, err = _main(base)  # no --refine: the weights would be unused
    assert code == 2 and "--refine" in err and not (tmp_path / "s.ply").exists()
    code, _, err = _main([*base, "--refine", "2", "--refine-scale", "4", "--report", tmp_path / "r.json"])
    assert code == 0, err
    r = json.loads((tmp_path / "r.json").read_text())["refine"]
    assert r["lpips"] is True and r["loss_last"]["lpips"] > 0
