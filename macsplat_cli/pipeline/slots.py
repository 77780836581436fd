"""The stage interfaces of the pipeline: one :class:`~typing.Protocol` per slot, and the stage clock's.

=========  ===============================================================
slot       signature
=========  ===============================================================
pair       ``(views) → NetworkPair``: a two-view network's one pass (or no slot)
describe   ``(views, pair) → [Features, Features]``
matcher    ``(features0, features1) → Matches``
pose       ``(view0, view1, matches, pair) → TwoViewGeometry``
depth      ``(views, geometry, pair) → [DepthMap, DepthMap]``
gaussians  ``(views, geometry, depths, pair) → [GaussianMaps, GaussianMaps]``
=========  ===============================================================

``pair`` is the output of the ``pair`` slot, a :data:`PairPass`: the network's pass
(:class:`~.neural.pair.NetworkPair`), or None when the pipeline has no ``pair`` slot (the classical backend). A
backend that needs both views at once computes it once and every later stage receives it explicitly; the classical
stages take it and leave it unread. Each backend has a ``name`` (the report names the backend of every stage). The
classical backends are in :mod:`.stages`, the network ones in :mod:`.neural`; this module imports no stage (the
pass's type only for the type checker), so any stage module may name the slots.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Literal, Protocol, TypeAlias, TypeVar

from ..gaussians import GaussianMaps
from .types import DepthMap, Features, Matches, TwoViewGeometry, View

if TYPE_CHECKING:
    from .neural.pair import NetworkPair

__all__ = [
    "DepthStage", "DescribeStage", "GaussianStage", "MatchStage", "PairPass", "PairStage", "PoseStage", "StageEvent",
    "StageTimer",
]  # fmt: skip

T = TypeVar("T")

PairPass: TypeAlias = "NetworkPair | None"
"""What the ``pair`` slot hands every later stage: the network's pass on both views, or None without a ``pair``
slot (the classical backend)."""

StageEvent = Callable[[str, Literal["start", "end", "fail"]], None]
"""``on_stage(stage, event)``: called around every stage (progress display)."""


class StageTimer(Protocol):
    """``timed(stage, fn)``: runs ``fn()`` as the named stage (progress events, wall time) and returns its result
    (:class:`~.run.StageClock`)."""

    def __call__(self, stage: str, fn: Callable[[], T]) -> T: ...


class PairStage(Protocol):
    name: str

    def __call__(self, views: list[View]) -> NetworkPair: ...


class DescribeStage(Protocol):
    name: str

    def __call__(self, views: list[View], pair: PairPass) -> list[Features]: ...


class MatchStage(Protocol):
    name: str

    def __call__(self, f0: Features, f1: Features) -> Matches: ...


class PoseStage(Protocol):
    name: str

    def __call__(self, v0: View, v1: View, matches: Matches, pair: PairPass) -> TwoViewGeometry: ...


class DepthStage(Protocol):
    name: str

    def __call__(self, views: list[View], geometry: TwoViewGeometry, pair: PairPass) -> list[DepthMap]: ...


class GaussianStage(Protocol):
    name: str

    def __call__(
        self, views: list[View], geometry: TwoViewGeometry, depths: list[DepthMap], pair: PairPass
    ) -> list[GaussianMaps]: ...
