"""The pose search as one stage object (issue 24): :class:`PoseSearch` and its typed :class:`PoseResult`.

Stub descriptor, matcher and pose slots (no images, no SIFT): which tier gives the pose and is recorded, the stages
each tier runs, the doubts as typed values and the refusal they cause, the report and cameras sections built from the
typed fields, and the self-calibrated views handed on as new objects (the loaded views are not changed).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from macsplat_cli.errors import ReconstructionError
from macsplat_cli.pipeline.pose import (
    LOW_CONFIDENCE_HINT,
    Doubt,
    PoseConfig,
    PoseResult,
    PoseSearch,
    PoseSearchConfig,
)
from macsplat_cli.pipeline.pose import confidence as acceptance
from macsplat_cli.pipeline.types import Features, Matches, TwoViewGeometry, View

W, H = 64, 48
K = np.array([[55.0, 0.0, 32.0], [0.0, 55.0, 24.0], [0.0, 0.0, 1.0]])


def _views(source: str = "prior") -> list[View]:
    image, mask = np.zeros((H, W, 3), np.float32), np.ones((H, W), bool)
    return [View(f"v{k}", Path(f"v{k}.png"), image, mask, K.copy(), (W, H), source) for k in range(2)]  # type: ignore[arg-type]


def _features(tag: str, n: int) -> list[Features]:
    """Features whose descriptors carry the tier's tag in their count (the stub matcher reads it back)."""
    rng = np.random.default_rng(len(tag))
    return [Features(rng.uniform(0, W, (n, 2)), np.ones((n, 4), np.float32), np.ones(n, np.float32)) for _ in range(2)]


class Describe:
    def __init__(self, name: str, n: int) -> None:
        self.name, self.n, self.calls = name, n, 0

    def __call__(self, views: list[View], pair: object = None) -> list[Features]:
        self.calls += 1
        return _features(self.name, self.n)


def match(f0: Features, f1: Features) -> Matches:
    idx = np.arange(len(f0))
    return Matches(f0.xy, f1.xy, np.ones(len(f0), np.float32), idx, idx, {"confident": len(f0)})


match.name = "stub-matcher"  # type: ignore[attr-defined]


class Pose:
    """A pose stage that fails on fewer than ``need`` matches, and verifies the others."""

    name = "stub-pose"

    def __init__(self, need: int, *, doubts: tuple[str, ...] = (), focal: float | None = None) -> None:
        self.need, self.doubts, self.focal = need, doubts, focal

    def __call__(self, v0: View, v1: View, matches: Matches, pair: object = None) -> TwoViewGeometry:
        if len(matches) < self.need:
            raise ReconstructionError(f"stub: {len(matches)} matches, need {self.need}")
        K0, K1 = v0.K.copy(), v1.K.copy()
        if self.focal is not None:
            K0[0, 0] = K0[1, 1] = K1[0, 0] = K1[1, 1] = self.focal
        return TwoViewGeometry(
            np.eye(3), np.array([1.0, 0.0, 0.0]), K0, K1, matches.subset(np.arange(len(matches)), "verified"),
            diagnostics={"inlier_ratio": 1.0, "stub": True}, doubts=list(self.doubts),
            focal_estimated=self.focal is not None, median_parallax_deg=2.0,
        )  # fmt: skip


def _search(pose: Pose, *, n: tuple[int, int, int] = (20, 40, 60), **config: object) -> PoseSearch:
    cfg = PoseSearchConfig(confidence=False, guided_band_px=None, **config)  # type: ignore[arg-type]
    return PoseSearch(
        cfg, PoseConfig(), describe=Describe("primary", n[0]), match=match, pose=pose,
        fallback=Describe("fallback", n[1]), wide=Describe("wide", n[2]),
    )  # fmt: skip


class Timer:
    def __init__(self) -> None:
        self.stages: list[str] = []

    def __call__(self, stage: str, fn):  # noqa: ANN001, ANN204
        self.stages.append(stage)
        return fn()


@pytest.mark.parametrize(
    ("need", "tier", "stages"),
    [
        (10, "fallback", ["descriptors", "matching", "pose", "descriptors (fallback)", "matching (fallback)",
                          "pose (fallback)"]),
        (50, "wide", ["descriptors", "matching", "pose", "descriptors (fallback)", "matching (fallback)",
                      "pose (fallback)", "descriptors (wide)", "matching (wide)", "pose (wide)"]),
    ],
)  # fmt: skip
def test_the_tier_that_gave_the_pose_is_recorded(need: int, tier: str, stages: list[str]) -> None:
    """20 primary matches verify fewer than ``fallback_min_inliers`` (100): the fallback (40) runs and wins; when
    it fails too, the wide tier (60). The result names the tier, its features and its matches (the evidence)."""
    timer = Timer()
    search = _search(Pose(need))
    result = search(_views("file"), None, timer)
    assert result.tier == tier and result.fallback_used
    assert timer.stages == [*stages, "pose confidence"]
    n = {"fallback": 40, "wide": 60}[tier]
    assert len(result.evidence) == len(result.geometry.inliers) == n and len(result.features[0]) == n
    report = result.report()
    assert report.get("descriptors_tier") == (tier if tier == "wide" else None)
    assert report["stub"] is True and report["inlier_ratio"] == result.inlier_ratio == 1.0


def test_primary_tier_and_no_pose_at_all() -> None:
    """Enough primary matches: no other tier runs. No tier with a pose: the fallback's failure is raised (the wide
    tier's is only logged)."""
    search = _search(Pose(10), fallback_min_inliers=10)
    result = search(_views("file"))
    assert result.tier == "primary" and not result.fallback_used
    assert search.fallback.calls == 0 and search.wide.calls == 0  # type: ignore[union-attr]
    with pytest.raises(ReconstructionError, match="stub: 40 matches, need 100"):
        _search(Pose(100))(_views("file"))


def test_doubts_are_typed_and_refuse_the_pose() -> None:
    """A doubt of the pose stage refuses the pose (the hint appended); accepted, it is a typed :class:`Doubt` and
    the report and the cameras section carry its message. Too few verified matches is a support doubt."""
    doubt = "the stub doubts this pose"
    with pytest.raises(ReconstructionError) as err:
        _search(Pose(10, doubts=(doubt,)))(_views("file"))
    assert str(err.value) == f"{doubt} ({LOW_CONFIDENCE_HINT})"
    result = _search(Pose(10, doubts=(doubt,)), accept_low_confidence=True)(_views("file"))
    assert result.doubts == [Doubt("pose", doubt)] and result.accepted_low_confidence
    assert result.confidence is None  # the checks are off in these tests
    assert result.report()["doubts"] == [doubt] and result.report()["accepted_low_confidence"] is True
    assert result.camera_confidence() == {
        "score": None, "checks": {}, "doubts": [doubt], "accepted_low_confidence": True
    }  # fmt: skip
    few = _search(Pose(10), accept_low_confidence=True, fallback_min_inliers=0)
    few.describe = Describe("primary", 12)
    result = few(_views("file"))
    assert [d.check for d in result.doubts] == ["support"] and "need at least 15" in result.doubts[0].message


def test_self_calibrated_views_are_new_objects() -> None:
    """The pose estimated the prior views' focal: the result's views are new ``estimated`` views with the
    geometry's K; the loaded views are unchanged. A view with given intrinsics is handed on as it is."""
    loaded = _views("prior")
    before = [(v.intrinsics_source, v.K.copy()) for v in loaded]
    result = _search(Pose(10, focal=70.0))(loaded)
    assert [(v.intrinsics_source, v.K.tolist()) for v in loaded] == [(s, k.tolist()) for s, k in before]
    assert [v.intrinsics_source for v in result.views] == ["estimated", "estimated"]
    assert result.views[0] is not loaded[0] and result.views[0].K is result.geometry.K0
    assert result.views[1].K is result.geometry.K1 and result.views[1].image is loaded[1].image
    mixed = [loaded[0], dataclasses.replace(loaded[1], intrinsics_source="file")]
    result = _search(Pose(10, focal=70.0))(mixed)
    assert result.views[1] is mixed[1] and result.views[0].intrinsics_source == "estimated"
    assert _search(Pose(10))(loaded).views == loaded  # nothing estimated: the same views


def test_report_is_built_from_the_typed_fields() -> None:
    """The report's ``pose`` section: the stage's diagnostics, ``focal_estimated``, ``median_parallax_deg`` and
    ``doubts`` (no ``confidence`` when the checks are off); ``descriptors_tier`` only for the wide tiers and only
    while the tier's own pose stands (the guided re-matching replaced it: left out, as before)."""
    result = _search(Pose(10))(_views("file"))
    assert isinstance(result, PoseResult)
    assert result.report() == {
        "inlier_ratio": 1.0, "stub": True, "focal_estimated": False, "median_parallax_deg": 2.0, "doubts": []
    }  # fmt: skip
    assert result.camera_confidence() is None
    wide = dataclasses.replace(result, tier="wide+plane-tiebreak", plane_tiebreak=[300, 100])
    assert wide.report()["descriptors_tier"] == "wide+plane-tiebreak" and wide.report()["plane_tiebreak"] == [300, 100]
    guided = dataclasses.replace(wide, guided=True)
    assert "descriptors_tier" not in guided.report() and "plane_tiebreak" not in guided.report()


class Consistent(Describe):
    """Features whose index-wise matches agree with the stub pose (R = I, t along x: a match moves right along its
    row), spread over the photo."""

    def __call__(self, views: list[View], pair: object = None) -> list[Features]:
        self.calls += 1
        rng = np.random.default_rng(7)
        xy0 = rng.uniform((0, 0), (W - 12, H), (self.n, 2))
        xy1 = xy0 + np.c_[rng.uniform(1.0, 10.0, self.n), np.zeros(self.n)]
        return [Features(xy, np.ones((self.n, 4), np.float32), np.ones(self.n, np.float32)) for xy in (xy0, xy1)]


def test_a_tier_whose_matches_do_not_support_its_pose_lets_the_next_one_run(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 25: the primary tier verifies plenty (no fallback by count), but its own putative matches do not
    single the pose out (random matches: the a contrario test fails); the fallback tier runs and its pose, which
    its matches support, stands. The rotation's uncertainty is not gated here (64×48 photos)."""
    monkeypatch.setattr(acceptance, "MAX_ROTATION_3SIGMA_DEG", 360.0)
    cfg = PoseSearchConfig(guided_band_px=None, fallback_min_inliers=10, accept_low_confidence=True)
    search = PoseSearch(
        cfg, PoseConfig(), describe=Describe("primary", 200), match=match, pose=Pose(10),
        fallback=Consistent("fallback", 80), wide=Describe("wide", 60),
    )  # fmt: skip
    result = search(_views("file"))
    assert result.tier == "fallback" and search.wide.calls == 0  # type: ignore[union-attr]
    assert result.confidence is not None and result.confidence.evidence is not None
    assert result.confidence.evidence.log10_nfa < acceptance.MAX_LOG10_NFA
    assert "evidence" not in {d.check for d in result.doubts}
    summary = result.report()["evidence"]
    assert summary["tier"] == "fallback" and summary["putative_matches"] == 80 and "log10 NFA" in summary["rule"]
    # the fallback's matches are random too: nothing supports a pose; the wide tier runs, and the refusal names
    # the figure that failed
    search.fallback = Describe("fallback", 80)
    search.config = dataclasses.replace(cfg, accept_low_confidence=False)
    with pytest.raises(ReconstructionError, match=r"matches found before the pose do not single it out \(log10 NFA"):
        search(_views("file"))
    assert search.wide.calls == 1  # type: ignore[union-attr]


def test_a_pose_the_pose_stage_doubts_does_not_send_the_search_on() -> None:
    """The pose stage's own doubt (an unobservable focal length, say) is about the geometry: other tiers' matches
    would not lift it, and it refuses the pose anyway; so the evidence test does not run the later tiers for it
    (they would only cost time on a pair that is refused)."""
    cfg = PoseSearchConfig(guided_band_px=None, fallback_min_inliers=10, accept_low_confidence=True)
    search = PoseSearch(
        cfg, PoseConfig(), describe=Describe("primary", 200), match=match, pose=Pose(10, doubts=("stub doubt",)),
        fallback=Consistent("fallback", 80), wide=Describe("wide", 60),
    )  # fmt: skip
    result = search(_views("file"))
    assert result.tier == "primary" and search.fallback.calls == 0 and search.wide.calls == 0  # type: ignore[union-attr]
    assert [d.check for d in result.doubts][:2] == ["pose", "evidence"]
