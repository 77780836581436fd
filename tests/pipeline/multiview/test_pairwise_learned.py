"""The N-photo pairwise step's use of the slow tiers: which failed pairs get the learned tier."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest

from macsplat_cli.pipeline.multiview import pairwise
from macsplat_cli.pipeline.multiview.pairwise import LEARNED_TRIES_PER_JOIN, PairOutcome, match_all
from macsplat_cli.pipeline.pose import PoseConfig, PoseSearch, PoseSearchConfig


def _stage(*args: object) -> None:  # never called: match_pairs is replaced
    raise AssertionError("a stage ran")


def test_the_learned_tier_runs_on_a_few_pairs_per_join_and_the_sift_tiers_on_every_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Photos 0–2 register together; photo 3 fails with every one of them: all three pairs joining it get the SIFT
    tiers, only the first LEARNED_TRIES_PER_JOIN the learned one. Once a pair joins photo 3, no more tries."""
    calls: list[tuple[tuple[int, int], str]] = []
    accept: set[tuple[int, int]] = {(0, 1), (1, 2)}  # by the primary tier
    slow_accept: set[tuple[int, int]] = set()  # by a slow tier

    def fake(views: Sequence[object], pairs: Sequence[tuple[int, int]], search: PoseSearch) -> list[PairOutcome]:
        tiers = "primary" if search.fallback is None else ("learned" if search.learned is not None else "sift")
        out = []
        for p in pairs:
            calls.append((p, tiers))
            ok = p in accept or (tiers != "primary" and p in slow_accept)
            out.append(PairOutcome(p[0], p[1], object() if ok else None, None if ok else "no", 0.0))  # type: ignore[arg-type]
        return out

    monkeypatch.setattr(pairwise, "match_pairs", fake)
    search = PoseSearch(PoseSearchConfig(), PoseConfig(), describe=_stage, match=_stage, pose=_stage,
                        fallback=_stage, learned=object())  # type: ignore[arg-type]  # fmt: skip
    pairs = [(0, 1), (1, 2), (0, 3), (1, 3), (2, 3)]
    match_all([object()] * 4, pairs, search)  # type: ignore[list-item]
    slow = [c for c in calls if c[1] != "primary"]
    assert [p for p, _ in slow] == [(0, 3), (1, 3), (2, 3)]
    assert [t for _, t in slow] == ["learned"] * LEARNED_TRIES_PER_JOIN + ["sift"] * (3 - LEARNED_TRIES_PER_JOIN)

    calls.clear()
    slow_accept.add((0, 3))  # the first slow try joins photo 3: the other pairs are not tried again
    match_all([object()] * 4, pairs, search)  # type: ignore[list-item]
    assert [c for c in calls if c[1] != "primary"] == [((0, 3), "learned")]


def test_the_slow_tiers_try_a_few_pairs_per_join_the_most_similar_first(monkeypatch: pytest.MonkeyPatch) -> None:
    """Photos 0–3 register together; photo 4 fails with all four: the slow tiers run on SLOW_TRIES_PER_JOIN of those
    pairs only, in the order of the photos' similarity (not the pairs' order), the learned tier on the first ones."""
    calls: list[tuple[tuple[int, int], str]] = []
    accept = {(0, 1), (1, 2), (2, 3)}

    def fake(views: Sequence[object], pairs: Sequence[tuple[int, int]], search: PoseSearch) -> list[PairOutcome]:
        tiers = "primary" if search.fallback is None else ("learned" if search.learned is not None else "sift")
        out = []
        for p in pairs:
            calls.append((p, tiers))
            ok = p in accept
            out.append(PairOutcome(p[0], p[1], object() if ok else None, None if ok else "no", 0.0))  # type: ignore[arg-type]
        return out

    monkeypatch.setattr(pairwise, "match_pairs", fake)
    search = PoseSearch(PoseSearchConfig(), PoseConfig(), describe=_stage, match=_stage, pose=_stage,
                        fallback=_stage, learned=object())  # type: ignore[arg-type]  # fmt: skip
    sim = np.zeros((5, 5))
    sim[4, :4] = sim[:4, 4] = [0.1, 0.4, 0.2, 0.3]  # photo 4 looks most like photo 1, then 3, then 2
    pairs = [(0, 1), (1, 2), (2, 3), (0, 4), (1, 4), (2, 4), (3, 4)]
    outs = match_all([object()] * 5, pairs, search, lambda: sim)  # type: ignore[list-item]
    slow = [c for c in calls if c[1] != "primary"]
    assert pairwise.SLOW_TRIES_PER_JOIN == 3  # the expected list below is written for three
    assert slow == [((1, 4), "learned"), ((3, 4), "learned"), ((2, 4), "sift")]
    assert [o.reason for o in outs[3:]] == ["no"] * 4  # the pair not tried keeps its primary tier's refusal
