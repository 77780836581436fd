"""``train --recipe paper|released-code``: each recipe's values reach the optimiser, the schedule, the data and the
loss; a step's loss equals the released code's formula; run.json names the bugs left out."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
import torch

from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.errors import DatasetError, InputError
from macsplat_cli.gaussians import GaussianMaps
from macsplat_cli.lpips import LPIPS
from macsplat_cli.metrics import ssim_map
from macsplat_cli.neural.predictor import PairPrediction
from macsplat_cli.training.config import TrainConfig
from macsplat_cli.training.loss import render_targets, training_loss
from macsplat_cli.training.optim import lr_factor
from macsplat_cli.training.recipes import RECIPES, RELEASED_CODE_BUGS, get_recipe
from macsplat_cli.training.setup import load_training_data

from support.cli import run_cli
from support.numerics import gamma

D = torch.float64


@pytest.fixture(scope="module")
def scannetpp(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """ScanNet++ tree: train split "room", val split "object", 6 frames each at 96×64."""
    return syn.write_scannetpp(tmp_path_factory.mktemp("recipes") / "scannetpp", frames=6, size=(96, 64))


def test_recipes_hold_what_they_claim() -> None:
    paper, released = get_recipe("paper", Path("run")), get_recipe("released-code", Path("run"))
    assert (paper.optimizer, paper.lr, paper.schedule, paper.loss.mac_weight) == ("adamw", 1e-5, "cosine", 0.25)
    assert (paper.loss.mac.lambda_pos, paper.loss.mac.lambda_shape, paper.loss.mac.lambda_app) == (1.0, 0.02, 0.1)
    assert paper.loss.mac.reduction == "sum" and paper.max_scale is None and paper.dino_variant == "vitl16"
    assert (released.optimizer, released.lr, released.weight_decay, released.schedule) == ("adam", 1e-6, 0.0, "step")
    assert (released.batch, released.size, released.crop, released.targets) == (1, (512, 512), "principal-point", 3)
    loss = released.loss
    assert (loss.mac_weight, loss.lpips_weight, loss.photo_reduction, loss.mac_weighting) == (0.2, 0.1, "mask", "c0c1")
    assert (loss.conf_floor, loss.max_matches, loss.mac.delta_pos, loss.mac.reduction) == (1.0, 4096, 0.05, "mean")
    assert (loss.matcher, loss.seed_stride, loss.near_plane, released.per_scene) == ("seeded", 8, 0.1, 20)
    assert released.max_scale == 0.5 and set(released.exclude_scenes) == {"303745abc7", "cc5237fd77"}
    assert released.steps_for(scenes=7, world_size=4) == math.ceil(200 * 7 / 4)  # 10 epochs × 20 samples a scene
    assert get_recipe("released-code", Path("run")).loss is not loss  # fresh objects: a run's changes never leak
    with pytest.raises(InputError, match="--recipe 'splatt3r': use paper or released-code"):
        get_recipe("splatt3r", Path("run"))
    assert list(RECIPES) == ["paper", "released-code"]


def test_step_schedule_drops_at_half_and_cosine_warms_up() -> None:
    step = TrainConfig(out=Path("x"), steps=10, warmup=0, schedule="step", lr_drop_at=0.5, lr_drop=0.1)
    assert [lr_factor(s, step) for s in range(10)] == [1.0] * 5 + [0.1] * 5
    cos = TrainConfig(out=Path("x"), steps=10, warmup=2)
    assert [lr_factor(s, cos) for s in range(2)] == [0.5, 1.0]
    assert lr_factor(2, cos) == 1.0 and lr_factor(10, cos) == pytest.approx(0.0, abs=1e-15)


def _prediction(h: int, w: int, seed: int) -> PairPrediction:
    """Both views' Gaussians a plane 2 m ahead (view 1's a little off), identical descriptors: every grid pixel
    matches itself, with known confidences."""
    g = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=D) + 0.5, torch.arange(w, dtype=D) + 0.5, indexing="ij")
    plane = torch.stack([(xs - w / 2) / 10, (ys - h / 2) / 10, torch.full_like(xs, 2.0)], -1)

    def maps(shift: float) -> GaussianMaps:
        return GaussianMaps(
            means=(plane + shift * torch.randn(h, w, 3, generator=g, dtype=D))[None],
            log_scales=(torch.randn(h, w, 3, generator=g, dtype=D) * 0.3 - 3.0)[None],
            quats=torch.randn(h, w, 4, generator=g, dtype=D)[None],
            opacity_logits=torch.randn(h, w, generator=g, dtype=D)[None],
            sh=torch.rand(h, w, 1, 3, generator=g, dtype=D)[None],
        )

    desc = torch.nn.functional.normalize(torch.randn(h, w, 8, generator=g, dtype=D), dim=-1)
    conf = torch.rand(2, h, w, generator=g, dtype=D) * 3 + 0.5
    return PairPrediction(
        pts3d=torch.zeros(1, 2, h, w, 3, dtype=D), conf=torch.ones(1, 2, h, w, dtype=D),
        desc=torch.stack([desc, desc])[None], desc_conf=conf[None], gaussians=(maps(0.0), maps(0.02)),
    )  # fmt: skip


def _huber(x: torch.Tensor, d: float) -> torch.Tensor:
    return torch.where(x < d, 0.5 * x * x / d, x - 0.5 * d)


def test_a_released_code_step_loss_equals_its_formula() -> None:
    """training_loss under the released-code recipe = Σerr²·m/(3·Σm) + 0.1·Σ(LPIPS map·m)/Σm + 0.2·MAC, MAC with
    weights (1+c₀)(1+c₁) on the seeded matcher's pairs, means over xyz / log σ / SH, Huber δ 0.05, clamps, one
    normaliser — recomputed here from the definitions (random LPIPS weights, float64)."""
    h, w, t = 32, 32, 3
    loss_cfg = get_recipe("released-code", Path("run")).loss
    pred = _prediction(h, w, 0)
    g = torch.Generator().manual_seed(1)
    c2w = torch.eye(4, dtype=D).repeat(1, 2, 1, 1)
    tc2w = torch.eye(4, dtype=D).repeat(1, t, 1, 1)
    tc2w[0, :, 0, 3] = torch.tensor([0.0, 0.05, -0.05], dtype=D)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]], dtype=D).repeat(1, t, 1, 1)
    batch = {
        "target": torch.rand(1, t, 3, h, w, generator=g, dtype=D), "target_K": K, "target_c2w": tc2w,
        "context_c2w": c2w, "target_mask": torch.rand(1, t, h, w, generator=g) > 0.3,
    }  # fmt: skip
    torch.manual_seed(2)
    lpips = LPIPS().double()
    terms = training_loss(pred, batch, loss_cfg, lpips)

    rgb = render_targets(pred.gaussians, 0, K[0], tc2w[0], c2w[0, 0], (h, w), near=loss_cfg.near_plane)
    m = batch["target_mask"][0].to(D)
    gt = batch["target"][0] * m[:, None]
    mse = (((rgb * m[:, None] - gt) ** 2) * m[:, None]).sum() / (3 * m.sum())
    dmap = torch.stack([lpips.spatial((rgb[i] * m[i]).permute(1, 2, 0), gt[i].permute(1, 2, 0)) for i in range(t)])
    perceptual = (dmap * m).sum() / m.sum()
    # MAC by hand: the seeded matcher starts from the stride-8 grid of view 0, whose pixels are their own reciprocal
    # nearest neighbours (identical descriptors), gated by c₀·c₁ > 1; at pixel centres the bilinear sampling
    # returns the pixel's own values. The matcher takes the confidences and forms the weights in float32, as the
    # network gives them
    g0, g1 = pred.gaussians
    conf = pred.desc_conf[0].float()
    num = den = 0.0
    for y in range(0, h, 8):  # the seeds
        for x in range(0, w, 8):
            c0, c1 = float(conf[0, y, x]), float(conf[1, y, x])
            if c0 * c1 <= loss_cfg.conf_threshold:
                continue
            wk = float((1 + conf[0, y, x]) * (1 + conf[1, y, x]))  # float32, as the matcher's
            pos = min(float(_huber((g0.means[0, y, x] - g1.means[0, y, x]).abs().mean(), 0.05)), 1.0)
            ls0, ls1 = g0.log_scales[0, y, x].sort().values, g1.log_scales[0, y, x].sort().values
            shape = min(float(_huber((ls0 - ls1).abs().mean(), 0.05)), 1.0)  # log σ = the log-scales
            op = abs(float(torch.sigmoid(g0.opacity_logits[0, y, x]) - torch.sigmoid(g1.opacity_logits[0, y, x])))
            col = min(float((g0.sh[0, y, x] - g1.sh[0, y, x]).abs().mean()), 2.0)
            num += wk * (1.0 * pos + 0.02 * shape + 0.1 * (min(op, 1.0) + col))
            den += wk
    assert terms.matches > 4 and den > 0
    mac = num / (den + loss_cfg.mac.eps)
    want = float(mse) + 0.1 * float(perceptual) + 0.2 * mac
    # float64: the photometric parts come from the same renders and LPIPS calls on both sides, and MAC's parts are
    # non-negative sums of ≤ 16 matches of ≤ 10 operations each, summed in another order: γ₆₄ relative
    assert float(terms.loss) == pytest.approx(want, rel=gamma(64, D), abs=0)
    assert terms.mse == pytest.approx(float(mse), rel=gamma(64, D), abs=0)
    assert terms.mac == pytest.approx(mac, rel=gamma(64, D), abs=0)
    # without LPIPS weights: D-SSIM's map averaged over the mask where SSIM's 11×11 window fits (5 px in)
    no_lpips = training_loss(pred, batch, loss_cfg, None)
    dssim = 1 - torch.stack([ssim_map((rgb[i] * m[i]).permute(1, 2, 0), gt[i].permute(1, 2, 0)) for i in range(t)])
    inner = m[:, 5:-5, 5:-5]
    want = float(mse) + 0.2 * float((dssim * inner).sum() / inner.sum()) + 0.2 * mac
    assert float(no_lpips.loss) == pytest.approx(want, rel=gamma(64, D), abs=0)


def test_excluded_scenes_leave_training(scannetpp: Path) -> None:
    _, _, info = load_training_data(scannetpp, exclude=("303745abc7",))  # not in this tree: nothing changes
    assert info["scenes"] == 1 and info["excluded_scenes"] == ["303745abc7"]
    with pytest.raises(DatasetError, match="no scene left once room are excluded"):
        load_training_data(scannetpp, exclude=("room",))


def test_cli_released_code_recipe_end_to_end(scannetpp: Path, tmp_path: Path) -> None:
    """The recipe's values in the run: Adam (no decoupled decay) at 1e-6, ×0.1 from half the steps, batch 1,
    3 targets, principal-point crops, the release's loss; run.json names each omitted bug and each override."""
    out = tmp_path / "run"
    args = ["train", "--data", scannetpp, "--out", out, "--model", "tiny", "--init", "random", "--size", "64x64",
            "--steps", "4", "--val-every", "0", "--workers", "0", "-q"]  # fmt: skip
    code, _, err = run_cli([*args, "--recipe", "released-code"])
    assert code == 0, err
    run = json.loads((out / "run.json").read_text())
    cfg = run["config"]
    assert (cfg["optimizer"], cfg["lr"], cfg["weight_decay"], cfg["schedule"], cfg["batch"]) == (
        "adam", 1e-6, 0.0, "step", 1)  # fmt: skip
    assert cfg["loss"]["mac_weight"] == 0.2 and cfg["loss"]["mac"]["reduction"] == "mean"
    assert cfg["loss"]["photo_reduction"] == "mask" and cfg["loss"]["conf_floor"] == 1.0
    assert cfg["loss"]["matcher"] == "seeded" and cfg["loss"]["near_plane"] == 0.1
    assert run["data"]["sampling"] == {"coverage": [0.3, 1.0], "targets": 3, "size": [64, 64],
                                       "crop": "principal-point", "per_scene": 20}  # fmt: skip
    recipe = run["recipe"]
    assert recipe["name"] == "released-code" and set(recipe["omitted_bugs"]) == set(RELEASED_CODE_BUGS)
    assert sorted(recipe["overridden"]) == ["--size", "--steps"] and recipe["not_reproduced"]
    state = torch.load(out / "last.pt", weights_only=True)
    group = state["training"]["optimizer"]["param_groups"][0]
    assert group["decoupled_weight_decay"] is False and group["weight_decay"] == 0.0
    assert group["lr"] == pytest.approx(1e-7, rel=1e-12)  # after step 2 of 4: ×0.1
    assert state["config"]["gaussian_head"]["max_scale"] == 0.5  # the cap travels with the model
    with (out / "metrics.csv").open() as f:
        lrs = [float(r["lr"]) for r in csv.DictReader(f) if r["kind"] == "train"]
    assert lrs == pytest.approx([1e-6, 1e-7, 1e-7, 1e-7], rel=1e-12)  # each row: the rate of the next step

    # resuming it under another recipe is refused, naming both, before anything is touched
    before = (out / "last.pt").read_bytes()
    code, _, err = run_cli([*args, "--resume"])
    assert code == 2 and err.strip() == (
        f"error: {out} was trained with --recipe released-code: resume it with --recipe released-code, or start "
        "over with --recipe paper --force"
    )
    assert (out / "last.pt").read_bytes() == before


def test_cli_refuses_an_unknown_recipe_in_one_line(tmp_path: Path) -> None:
    code, _, err = run_cli(["train", "--data", tmp_path, "--out", tmp_path / "run", "--recipe", "official"])
    assert code == 2 and err.strip() == "error: --recipe 'official': use paper or released-code"
    assert not (tmp_path / "run").exists()
