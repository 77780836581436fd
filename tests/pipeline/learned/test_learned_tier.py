"""The learned tier of the pose search (issue 39): it runs after the SIFT tiers, only when their pose fails or its
own matches do not support it, with its own descriptors and matcher, and competes on evidence as they do.

Stub slots (no images, no weights): the tier order and the stages each runs, the tier recorded, whose failure
stands, and that a supported SIFT pose never pays for the learned tier.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from macsplat_cli.errors import ReconstructionError
from macsplat_cli.pipeline import run
from macsplat_cli.pipeline.learned import LearnedConfig, LearnedTier, LightGlueMatcher
from macsplat_cli.pipeline.learned.guard import MAX_LOG10_NFA
from macsplat_cli.pipeline.pose import PoseConfig, PoseSearch, PoseSearchConfig
from macsplat_cli.pipeline.pose import confidence as acceptance
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig, classical_stages
from macsplat_cli.pipeline.types import Features, Matches, TwoViewGeometry, View
from macsplat_cli.presets import learned_search

W, H = 64, 48
K = np.array([[55.0, 0.0, 32.0], [0.0, 55.0, 24.0], [0.0, 0.0, 1.0]])


def _views() -> list[View]:
    image, mask = np.zeros((H, W, 3), np.float32), np.ones((H, W), bool)
    return [View(f"v{k}", Path(f"v{k}.png"), image, mask, K.copy(), (W, H), "file") for k in range(2)]


class Describe:
    """``n`` features per view with distinct random unit descriptors; ``consistent``: index-wise matches that agree
    with the stub pose (R = I, t along x) up to ``noise_px`` across the epipolar lines, else random ones;
    ``repeated``: each descriptor of view 0 twice, at the keypoint and at a twin at least 20 px away."""

    def __init__(self, name: str, n: int, *, consistent: bool = False, noise_px: float = 0.0,
                 repeated: bool = False) -> None:  # fmt: skip
        self.name, self.n, self.consistent, self.calls = name, n, consistent, 0
        self.noise_px, self.repeated = noise_px, repeated

    def __call__(self, views: list[View], pair: object = None) -> list[Features]:
        self.calls += 1
        rng = np.random.default_rng(self.n)
        xy0 = rng.uniform((0, 0), (W - 12, H), (self.n, 2))
        shift = np.c_[rng.uniform(1.0, 10.0, self.n), np.zeros(self.n)]
        shift[:, 1] = rng.normal(0.0, self.noise_px, self.n)
        xy1 = xy0 + shift if self.consistent else rng.uniform((0, 0), (W, H), (self.n, 2))
        desc = rng.normal(size=(2, self.n, 128)).astype(np.float32)
        desc /= np.linalg.norm(desc, axis=2, keepdims=True)
        feats = [Features(xy, d, np.ones(self.n, np.float32)) for xy, d in zip((xy0, xy1), desc)]
        if self.repeated:  # the twins come after the matched keypoints: the matches' indices stay
            twin_xy = np.c_[(xy0[:, 0] + 32.0) % W, (xy0[:, 1] + 24.0) % H]
            feats[0] = Features(np.r_[xy0, twin_xy], np.r_[desc[0], desc[0]], np.ones(2 * self.n, np.float32))
        return feats


class Match:
    """Index-wise matches of the first ``len(f1)`` features (the twins of :class:`Describe` stay unmatched)."""

    def __init__(self, name: str) -> None:
        self.name, self.calls = name, 0

    def __call__(self, f0: Features, f1: Features) -> Matches:
        self.calls += 1
        n = min(len(f0), len(f1))
        idx = np.arange(n)
        return Matches(f0.xy[:n], f1.xy[:n], np.ones(n, np.float32), idx, idx, {self.name: n})


class LightGlue(LightGlueMatcher):
    """LightGlue's guard (:meth:`LightGlueMatcher.doubts`, the real one) on :class:`Match`'s index-wise matches."""

    def __init__(self) -> None:
        self.name, self.calls = "lightglue", 0

    __call__ = Match.__call__


class Pose:
    """Fails on fewer than ``need`` matches; otherwise R = I, t along x, every match verified."""

    name = "stub-pose"

    def __init__(self, need: int) -> None:
        self.need = need

    def __call__(self, v0: View, v1: View, matches: Matches, pair: object = None) -> TwoViewGeometry:
        if len(matches) < self.need:
            raise ReconstructionError(f"stub: {len(matches)} matches, need {self.need}")
        verified = matches.subset(np.arange(len(matches)), "verified")
        return TwoViewGeometry(np.eye(3), np.array([1.0, 0.0, 0.0]), v0.K.copy(), v1.K.copy(), verified,
                               median_parallax_deg=2.0)  # fmt: skip


def _search(need: int, *, learned_n: int = 120, consistent: bool = False, evidence: bool = False,
            sift: tuple[int, int, int] = (20, 40, 60), noise_px: float = 0.0, repeated: bool = False,
            **config: object) -> PoseSearch:  # fmt: skip
    cfg = PoseSearchConfig(confidence=evidence, guided_band_px=None, accept_low_confidence=True, **config)  # type: ignore[arg-type]
    describe = Describe("learned:stub", learned_n, consistent=consistent, noise_px=noise_px, repeated=repeated)
    tier = LearnedTier(describe, LightGlue(), LearnedConfig())
    return PoseSearch(
        cfg, PoseConfig(), describe=Describe("primary", sift[0]), match=Match("filtered"), pose=Pose(need),
        fallback=Describe("fallback", sift[1]), wide=Describe("wide", sift[2]), learned=tier,
    )  # fmt: skip


class Timer:
    def __init__(self) -> None:
        self.stages: list[str] = []

    def __call__(self, stage: str, fn):  # noqa: ANN001, ANN204
        self.stages.append(stage)
        return fn()


def test_the_learned_tier_runs_last_when_every_sift_tier_fails() -> None:
    timer = Timer()
    search = _search(100)
    result = search(_views(), None, timer)
    assert result.tier == "learned" and len(result.geometry.inliers) == 120
    assert timer.stages[-5:] == [
        "weights (learned)", "descriptors (learned)", "matching (learned)", "pose (learned)", "pose confidence"
    ]  # fmt: skip
    assert timer.stages.index("pose (wide)") < timer.stages.index("descriptors (learned)")
    assert result.geometry.inliers.counts == {"lightglue": 120, "verified": 120}  # its own matcher
    assert result.matcher == result.report()["matcher"] == "learned:stub+lightglue"
    assert search.learned is not None and search.learned.match.calls == 1 and search.match.calls == 3  # type: ignore[attr-defined]


def test_a_sift_pose_that_stands_never_runs_the_learned_tier() -> None:
    search = _search(10, fallback_min_inliers=10)
    result = search(_views())
    assert result.tier == "primary" and result.matcher == "primary+filtered" and "matcher" not in result.report()
    assert search.learned is not None and search.learned.describe.calls == 0  # type: ignore[attr-defined]


def test_when_the_learned_tier_fails_too_the_sift_failure_stands() -> None:
    with pytest.raises(ReconstructionError, match="stub: 40 matches, need 200"):
        _search(200, learned_n=150)(_views())


def test_the_learned_pose_replaces_an_unsupported_sift_pose_only_when_its_matches_support_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """SIFT's random matches verify a pose they do not single out (the a contrario test fails): the learned tier
    runs; its consistent matches support its pose, which stands. Random learned matches do not replace it."""
    monkeypatch.setattr(acceptance, "MAX_ROTATION_3SIGMA_DEG", 360.0)  # 64×48 photos: the uncertainty is not gated
    search = _search(10, consistent=True, evidence=True, sift=(200, 150, 100), fallback_min_inliers=10)
    result = search(_views())
    assert result.tier == "learned" and "evidence" not in {d.check for d in result.doubts}
    search = _search(10, consistent=False, evidence=True, sift=(200, 150, 100), fallback_min_inliers=10)
    result = search(_views())
    assert result.tier != "learned" and "evidence" in {d.check for d in result.doubts}
    assert search.learned is not None and search.learned.describe.calls == 1  # type: ignore[attr-defined]


def _learned_doubts(result: object) -> list[str]:
    return [d.message for d in result.doubts if "learned matches" in d.message]  # type: ignore[attr-defined]


def test_a_learned_pose_on_a_repeated_texture_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """The learned matches verify the pose, but each of view 0's matched keypoints has a twin (the same descriptor
    elsewhere in the photo): refused, however strong the evidence; without the twins the same pose stands."""
    monkeypatch.setattr(acceptance, "MAX_ROTATION_3SIGMA_DEG", 360.0)  # 64×48 photos: the uncertainty is not gated
    result = _search(10, consistent=True, evidence=True, sift=(200, 150, 100), fallback_min_inliers=10,
                     repeated=True)(_views())  # fmt: skip
    assert result.tier == "learned"
    assert any("repeated" in m for m in _learned_doubts(result)), result.doubts
    result = _search(10, consistent=True, evidence=True, sift=(200, 150, 100), fallback_min_inliers=10)(_views())
    assert result.tier == "learned" and not result.doubts


def test_a_learned_pose_needs_stronger_evidence_than_a_sift_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """30 learned matches along the pose within 1 px: meaningful for SIFT's bar (log10 NFA < -3), not for the
    learned tier's (:data:`~macsplat_cli.pipeline.learned.guard.MAX_LOG10_NFA`); 120 of them pass both."""
    monkeypatch.setattr(acceptance, "MAX_ROTATION_3SIGMA_DEG", 360.0)  # 64×48 photos: the uncertainty is not gated
    result = _search(25, learned_n=30, consistent=True, noise_px=0.7, evidence=True, sift=(10, 10, 10))(_views())
    assert result.tier == "learned" and result.confidence is not None
    assert MAX_LOG10_NFA < result.confidence.checks["log10_nfa"] < -3.0
    assert any("log10 NFA" in m for m in _learned_doubts(result)), result.doubts
    result = _search(25, learned_n=120, consistent=True, noise_px=0.7, evidence=True, sift=(10, 10, 10))(_views())
    assert result.tier == "learned" and result.confidence is not None and not _learned_doubts(result)
    assert result.confidence.checks["log10_nfa"] < MAX_LOG10_NFA


def _aliked_search(monkeypatch: pytest.MonkeyPatch, *, repeated: bool) -> PoseSearch:
    """The pose search as ``--matcher aliked`` builds it (:func:`~macsplat_cli.presets.learned_search`,
    :func:`~macsplat_cli.pipeline.run.classical_stages`): the learned matcher as the only tier, a stub in place of
    the installed one (consistent matches; ``repeated``: each matched keypoint of view 0 has a twin)."""
    describe = Describe("learned:stub", 120, consistent=True, repeated=repeated)
    stub = LearnedTier(describe, LightGlue(), LearnedConfig())
    monkeypatch.setattr(run, "learned_tier", lambda config, *, required: stub)
    search = learned_search(PoseSearchConfig(guided_band_px=None), "aliked")
    config = dataclasses.replace(ReconstructConfig(), search=search)
    stages = classical_stages(config, pose=Pose(10))
    assert stages.describe is describe and stages.fallback is None and stages.wide is None and stages.learned is None
    return Pipeline(config, stages).search


def test_matcher_aliked_refuses_a_pose_on_a_repeated_texture_as_auto_does(monkeypatch: pytest.MonkeyPatch) -> None:
    """``--matcher aliked`` runs the learned matcher as the primary (and only) tier: the guard follows the matcher,
    not the tier, so the pose that ``auto``'s learned tier refuses (the test above) is refused there too (it was
    accepted: the guard ran in the learned tier only); without the twins the same pose stands."""
    monkeypatch.setattr(acceptance, "MAX_ROTATION_3SIGMA_DEG", 360.0)  # 64×48 photos: the uncertainty is not gated
    with pytest.raises(ReconstructionError, match="lie on a texture repeated elsewhere in the photo"):
        _aliked_search(monkeypatch, repeated=True)(_views())
    result = _aliked_search(monkeypatch, repeated=False)(_views())
    assert result.tier == "primary" and result.matcher == "learned:stub+lightglue" and not result.doubts
