"""The MAC-regularised refinement of the per-view Gaussian maps, from the library and from
``macsplat reconstruct --refine``. (The maps themselves, world transform and pooling: test_gaussians.py.)"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from macsplat_cli.errors import InputError
from macsplat_cli.gaussians import GaussianMaps
from macsplat_cli.mac import MACConfig, mac_loss
from macsplat_cli.pipeline.refine import RefineConfig, refine
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig, Reconstruction
from macsplat_cli.pipeline.views import ViewConfig

from support.cli import run_cli
from support.scenes import PairFactory, PairSpec

# ------------------------------------------------------------------------------ refinement
SIZE = (256, 192)


@pytest.fixture(scope="module")
def pair(pair_files: PairFactory) -> tuple[Path, Path, Path]:
    """A textured room pair 12° apart, rendered at 256×192, and its true cameras."""
    files = pair_files(PairSpec("room", 12.0, SIZE, 60.0, scene_seed=3))
    return files.a, files.b, files.cameras


@pytest.fixture(scope="module")
def rec(pair: tuple[Path, Path, Path]) -> Reconstruction:
    cfg = ReconstructConfig(views=ViewConfig(size=SIZE[0], intrinsics=pair[2]))
    return Pipeline(cfg).run(pair[:2])


def _mac_value(rec: Reconstruction, maps: list[GaussianMaps], scale: int) -> float:
    inl = rec.pose.geometry.inliers
    xy0 = torch.tensor(inl.xy0 / scale, dtype=torch.float32)
    xy1 = torch.tensor(inl.xy1 / scale, dtype=torch.float32)
    c2w = [m.cam_to_world.float() for m in maps]
    out = mac_loss(maps[0], maps[1], xy0, xy1, torch.zeros(len(xy0), dtype=torch.long),
                   torch.tensor(inl.conf, dtype=torch.float32), c2w[0], c2w[1])  # fmt: skip
    return float(out.loss)


def test_refinement_lowers_the_loss_and_leaves_the_input_alone(rec: Reconstruction) -> None:
    before = [t.clone() for t in rec.maps[0].tensors()]
    out = refine(rec.views, rec.pose.geometry, rec.maps, RefineConfig(steps=12, scale=4, min_steps=100))
    assert out.steps == 12 and not out.stopped_early and len(out.history) == 12
    assert out.history[-1]["photo"] < 0.9 * out.history[0]["photo"]
    assert {"photo", "mac", "mac_pos", "mac_shape", "loss"} <= set(out.history[0])
    h, w = rec.maps[0].size
    assert [m.size for m in out.maps] == [(h // 4, w // 4)] * 2 and [m.batch for m in out.maps] == [1, 1]
    assert all(torch.equal(a.cam_to_world, b.cam_to_world) for a, b in zip(out.maps, rec.maps))
    assert not any(t.requires_grad for m in out.maps for t in m.tensors())
    for t0, t1 in zip(before, rec.maps[0].tensors()):
        assert torch.equal(t0, t1)


def test_mac_term_pulls_matched_gaussians_together(rec: Reconstruction) -> None:
    """With MAC (weighted up to make the effect clear in a few steps), the matched Gaussians of
    the two views end up closer than without it; without MAC the history has no MAC term."""
    strong = MACConfig(weight=25.0)
    cfg = RefineConfig(steps=8, scale=4, min_steps=100, mac=strong)
    with_mac = refine(rec.views, rec.pose.geometry, rec.maps, cfg)
    no_mac = refine(rec.views, rec.pose.geometry, rec.maps,
                    RefineConfig(steps=8, scale=4, min_steps=100, use_mac=False))  # fmt: skip
    assert "mac" not in no_mac.history[0]
    start = _mac_value(rec, [m.pooled(4) for m in rec.maps], 4)
    assert _mac_value(rec, with_mac.maps, 4) < 0.8 * min(start, _mac_value(rec, no_mac.maps, 4))


def test_refinement_stops_early_on_a_plateau(rec: Reconstruction) -> None:
    cfg = RefineConfig(steps=40, scale=4, min_steps=4, plateau_window=2, plateau_tol=10.0)
    out = refine(rec.views, rec.pose.geometry, rec.maps, cfg)
    assert out.stopped_early and out.steps == 4


def test_refinement_takes_one_map_per_view(rec: Reconstruction) -> None:
    both = GaussianMaps.cat([rec.maps[0], rec.maps[0]])
    with pytest.raises(InputError, match="B = 1"):
        refine(rec.views, rec.pose.geometry, [both, rec.maps[1]], RefineConfig(steps=1, scale=4))


# ------------------------------------------------------------------------------ CLI
@pytest.mark.parametrize("mac", [True, False])
def test_cli_reconstruct_refine(pair: tuple[Path, Path, Path], tmp_path: Path, mac: bool) -> None:
    args = ["reconstruct", pair[0], pair[1], "-o", tmp_path / "s.ply", "--size", str(SIZE[0]), "--refine", "3",
            "--report", tmp_path / "r.json", "--intrinsics", pair[2]] + ([] if mac else ["--no-mac"])  # fmt: skip
    code, _, err = run_cli(args)
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
    code, _, err = run_cli(["reconstruct", pair[0], pair[1], "-o", tmp_path / "s.ply", *option])
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
    out = refine(rec.views, rec.pose.geometry, rec.maps, RefineConfig(steps=4, scale=4, min_steps=100), lpips=model)
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
    code, _, err = run_cli(base)  # no --refine: the weights would be unused
    assert code == 2 and "--refine" in err and not (tmp_path / "s.ply").exists()
    code, _, err = run_cli([*base, "--refine", "2", "--refine-scale", "4", "--report", tmp_path / "r.json"])
    assert code == 0, err
    r = json.loads((tmp_path / "r.json").read_text())["refine"]
    assert r["lpips"] is True and r["loss_last"]["lpips"] > 0


def test_run_steps_is_the_loop_both_refinements_share() -> None:
    """:func:`~macsplat_cli.pipeline.refine.run_steps` (the two-view and the joint refinement's loop): Adam at the
    cosine rates on the loss it is given, every step reported, stopped when ``stop`` says so."""
    from macsplat_cli.pipeline.refine import run_steps
    from macsplat_cli.pipeline.refine_adam import Adam

    x = torch.tensor([3.0], requires_grad=True)
    opt = Adam([{"params": [x], "lr": 0.5, "initial_lr": 0.5}])
    seen: list[int] = []
    history, steps, stopped = run_steps(
        opt, RefineConfig(steps=50), lambda step: ((x**2).sum(), {"loss": float(x.detach() ** 2)}),
        lambda history, step: history[-1]["loss"] < 0.01, lambda step, most, terms: seen.append(step),
    )  # fmt: skip
    assert stopped and steps == len(history) == len(seen) < 50 and seen == list(range(1, steps + 1))
    assert history[-1]["loss"] < 0.01 < history[0]["loss"]
    _, steps, stopped = run_steps(opt, RefineConfig(steps=3), lambda step: ((x**2).sum(), {}), lambda h, s: False, None)
    assert (steps, stopped) == (3, False)


def _random_map(seed: int, valid: bool, pose: str, dtype: torch.dtype = torch.float32) -> GaussianMaps:
    """A one-view 5 × 7 map of random Gaussians (SH degree 1), some pixels invalid, with an identity or a turned
    pose (or none)."""
    g = torch.Generator().manual_seed(seed)
    h, w = 5, 7
    t = [torch.randn(1, h, w, *s, generator=g, dtype=dtype) for s in ((3,), (3,), (4,), (), (4, 3))]
    mask = torch.rand(1, h, w, generator=g) > 0.3 if valid else None
    c2w = None if pose == "none" else torch.eye(4, dtype=torch.float64)[None].clone()
    if pose == "turned" and c2w is not None:
        a = 0.3
        c2w[0, :3, :3] = torch.tensor([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        c2w[0, :3, 3] = torch.tensor([0.2, -1.0, 0.5])
    return GaussianMaps(*t, valid=mask, cam_to_world=c2w)


@pytest.mark.parametrize("valid", [True, False])
@pytest.mark.parametrize("pose", ["none", "identity", "turned"])
def test_a_steps_world_is_to_gaussians_bit_for_bit(valid: bool, pose: str) -> None:
    """Issue 40: the step's world Gaussians (:class:`refine._World`: indices and pose found once, the identity pose
    skipped) are :meth:`GaussianMaps.to_gaussians`' values and gradients, bit for bit."""
    from macsplat_cli.pipeline.refine import _World

    m = _random_map(4, valid, pose)
    for t in m.tensors():
        t.requires_grad_(True)
    world = _World.of(m)
    assert (world.R is None) == (pose != "turned") and (world.sel is None) == (not valid)
    ours, ref = world.gaussians(m), m.to_gaussians()
    cot = [torch.randn(t.shape, generator=torch.Generator().manual_seed(k)) for k, t in enumerate(ref.tensors())]
    for a, b in zip(ours.tensors(), ref.tensors()):
        assert torch.equal(a, b)
    grads = [torch.autograd.grad(g.tensors(), m.tensors(), cot) for g in (ours, ref)]
    for a, b in zip(*grads):
        assert torch.equal(a, b)
