"""``benchmarks/pose_protocol.py``: the Clopper–Pearson bound, and cases reproducible from their id, split apart.

Nothing is rendered or reconstructed here (the benchmark does that); these are its bookkeeping's invariants.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from types import ModuleType

import pytest

from support import REPO


@pytest.fixture(scope="module")
def protocol() -> Iterator[ModuleType]:
    """``benchmarks.pose_protocol``, imported the way ``python -m`` runs it (repository root first)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(REPO))
        yield importlib.import_module("benchmarks.pose_protocol")


def test_clopper_pearson_upper_bound(protocol: ModuleType) -> None:
    upper = protocol.clopper_pearson_upper
    for n in (1, 4, 36, 598, 5000):  # none seen in n: 1 − α^(1/n)
        assert upper(0, n) == pytest.approx(1 - 0.05 ** (1 / n), rel=1e-9)
    assert upper(0, 598) < 0.005 < upper(0, 597)  # the cases per width the 0.5 % target needs
    assert upper(1, 10) == pytest.approx(0.39416, abs=1e-5)  # the 95 % quantile of Beta(2, 9)
    assert upper(10, 10) == 1.0 and upper(0, 0) == 1.0
    bounds = [upper(k, 50) for k in range(51)]
    assert all(a < b for a, b in zip(bounds, bounds[1:])) and all(k / 50 < b for k, b in enumerate(bounds[:-1]))
    assert protocol.binomial_cdf(3, 10, 0.5) == pytest.approx(176 / 1024, rel=1e-12)


def test_a_case_is_reproducible_from_its_id_and_the_splits_are_disjoint(protocol: ModuleType) -> None:
    draw = {"intrinsics": "given", "size": (640, 480)}
    one = protocol.draw_case("heldout", "outdoor", 60, 1, **draw)
    every = protocol.cases(["tuning", "heldout"], list(protocol.KINDS), list(protocol.WIDTHS), 2, **draw)
    assert one in every and one["id"] == "heldout/outdoor/60/1"
    assert protocol.cases(["heldout"], ["outdoor"], [60], 3, **draw)[1] == one  # whatever else runs
    seeds = {s: {c["scene_seed"] for c in every if c["split"] == s} for s in protocol.SPLITS}
    assert seeds["tuning"].isdisjoint(seeds["heldout"])
    for c in every:
        lo, hi = protocol.SPLITS[c["split"]].scene_seeds
        assert lo <= c["scene_seed"] < hi and 40 <= c["fov"] <= 90 and 0 <= c["noise"] <= 4
        if c["kind"] == "tabletop":  # 30–60° above the table, where an orbit of the width exists
            assert c["elevation"] <= min(60.0, (180 - c["width"]) / 2 - 3)
            assert c["elevation"] >= 30 or c["width"] > 110
    assert 0.1 < sum(c["repetitive"] for c in every) / len(every) < 0.4
