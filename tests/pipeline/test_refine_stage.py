"""Stage 7's entry on N photos: ``best`` refines at full resolution only where the photos agree at it (issue 41)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from macsplat_cli.pipeline.gaussian_init import GaussianInitConfig, view_gaussians
from macsplat_cli.pipeline.refine_config import AUTO_STEPS, RefineConfig
from macsplat_cli.pipeline.refine_stage import PROBE_NEIGHBOURS, PROBE_PHOTOS, _probes, sharp_gain_db
from macsplat_cli.pipeline.types import View
from macsplat_cli.presets import (
    MULTIVIEW_BALANCED_STEPS,
    MULTIVIEW_BEST_STEPS,
    MULTIVIEW_SHARP_MIN_GAIN_DB,
    Overrides,
    configure,
    refine_for_agreement,
)

from support.scenes import room_photos

W, H = 128, 96


@pytest.fixture(scope="module")
def photos() -> tuple[list[View], list[np.ndarray], list[np.ndarray]]:
    """Three photos of a textured room 6° apart, their exact depths and cameras (camera 0 the world frame)."""
    return room_photos(W, H)


def _maps(views: list[View], depths: list[np.ndarray], poses: list[np.ndarray]) -> list:
    from macsplat_cli.pipeline.types import DepthMap

    return [view_gaussians(v, DepthMap(d, (d > 0).astype(np.float32)), v.K, T, GaussianInitConfig())
            for v, d, T in zip(views, depths, poses)]  # fmt: skip


def _turned(T: np.ndarray, deg: float) -> np.ndarray:
    """``T`` with its rotation turned ``deg`` about the camera's vertical axis (its centre kept)."""
    t = math.radians(deg)
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ np.array([[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]])
    return out


def test_sharp_gaussians_win_where_the_cameras_agree_and_lose_where_one_is_off(photos: tuple) -> None:
    """Exact cameras and depths: the other photos' full-resolution Gaussians predict each photo better than pooled
    ones. The middle camera registered 1.5° off (its Gaussians placed by that pose, as a registration error does):
    the sharp detail lands on the wrong pixels and the pooled Gaussians predict better (the development sets)."""
    views, depths, poses = photos
    exact = sharp_gain_db(_maps(views, depths, poses), views, poses, 2)
    off = [poses[0], _turned(poses[1], 1.5), poses[2]]
    wrong = sharp_gain_db(_maps(views, depths, off), views, off, 2)
    assert exact > MULTIVIEW_SHARP_MIN_GAIN_DB >= wrong, (exact, wrong)


def test_the_measure_probes_a_few_photos_each_from_its_nearest_cameras() -> None:
    """On many photos the measure renders :data:`PROBE_PHOTOS` of them, spread from first to last, each from its
    :data:`PROBE_NEIGHBOURS` nearest cameras (its cost no longer grows as photos²); on three, every photo from both
    others."""
    line = [np.eye(4) for _ in range(12)]
    for k, T in enumerate(line):
        T[0, 3] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 20][k]  # the last camera far from the rest
    probes = _probes(line)
    assert len(probes) == PROBE_PHOTOS and min(probes) == 0 and max(probes) == 11
    assert probes[0] == list(range(1, 1 + PROBE_NEIGHBOURS))
    assert probes[11] == list(range(11 - PROBE_NEIGHBOURS, 11))
    assert all(k not in near and len(near) == PROBE_NEIGHBOURS for k, near in probes.items())
    assert _probes(line[:3]) == {0: [1, 2], 1: [0, 2], 2: [0, 1]}


def test_best_on_three_photos_falls_back_to_the_pooled_refinement_where_the_photos_disagree() -> None:
    """The preset's full resolution is the photos' to decline (``coarse``: 1/2 at :data:`AUTO_STEPS`, ``best``'s
    refinement before full resolution; ``balanced``'s own steps); a scale or steps the user gave are kept; two
    photos have nothing to choose."""
    four = configure("best", "classical", photos=4).refine
    assert (four.scale, four.steps, four.coarse) == (1, MULTIVIEW_BEST_STEPS, (2, AUTO_STEPS))
    pooled = refine_for_agreement(four, -0.3)
    assert (pooled.scale, pooled.steps, pooled.coarse) == (2, AUTO_STEPS, None)
    assert refine_for_agreement(four, 0.5) == four
    assert refine_for_agreement(four, math.nan).scale == 2  # nothing measured: the pooled refinement
    assert configure("best", "classical", Overrides(refine=10), photos=4).refine.coarse == (2, 10)
    for given in (Overrides(refine_scale=1), Overrides(refine_scale=2), Overrides(refine=0)):
        assert configure("best", "classical", given, photos=4).refine.coarse is None
    assert configure("best", "classical").refine.coarse is None
    balanced = configure("balanced", "classical", photos=4).refine
    assert (balanced.scale, balanced.steps, balanced.coarse) == (
        1,
        MULTIVIEW_BALANCED_STEPS,
        (2, MULTIVIEW_BALANCED_STEPS),
    )
    assert configure("balanced", "classical").refine.coarse is None
    assert refine_for_agreement(RefineConfig(steps=5, scale=1), -1.0).scale == 1  # not the photos' to choose


def test_the_refine_stage_measures_first_and_reports_what_it_chose(monkeypatch: pytest.MonkeyPatch) -> None:
    """The stage measures the photos (:func:`sharp_gain_db`) only where the preset left the scale to them, refines
    at the scale the rule gives, and reports the measure."""
    from macsplat_cli.pipeline import refine_stage
    from macsplat_cli.pipeline.multiview import joint
    from macsplat_cli.report import RefineReport

    ran: list[tuple[int, int]] = []

    def fake_joint(rec: object, config: RefineConfig, sets: object, on_step: object) -> tuple:
        ran.append((config.scale, config.steps))
        return "result", RefineReport(config.steps, config.steps, False, 0.0, config.scale, False, False, {}, {}, {})

    monkeypatch.setattr(joint, "joint_reconstruction", fake_joint)
    monkeypatch.setattr(refine_stage, "check_scale", lambda maps, scale: None)
    measured: list[int] = []
    gain = [-0.4]
    monkeypatch.setattr(refine_stage, "sharp_gain_db", lambda maps, views, poses, f: measured.append(f) or gain[0])

    def rec(size: tuple[int, int]) -> SimpleNamespace:
        maps = [SimpleNamespace(size=size) for _ in range(3)]
        return SimpleNamespace(maps=maps, views=[0, 1, 2], poses=[0, 1, 2],
                               multiview=SimpleNamespace(match_sets=lambda: []))  # fmt: skip

    best = configure("best", "classical", photos=3).refine
    _, report = refine_stage.refine_stage(rec((384, 512)), best)  # type: ignore[arg-type]
    gain[0] = 0.6
    _, sharp = refine_stage.refine_stage(rec((384, 512)), best)  # type: ignore[arg-type]
    refine_stage.refine_stage(rec((384, 512)), RefineConfig(steps=5, scale=1))  # type: ignore[arg-type]
    gain[0] = -0.4
    _, odd = refine_stage.refine_stage(rec((383, 512)), best)  # type: ignore[arg-type]  # cannot be pooled
    assert ran == [(2, AUTO_STEPS), (1, MULTIVIEW_BEST_STEPS), (1, 5), (1, MULTIVIEW_BEST_STEPS)]
    assert measured == [2, 2] and odd.joint == {}
    assert report.joint == {"sharp_gain_db": -0.4} and report.scale == 2 and sharp.joint == {"sharp_gain_db": 0.6}
