"""The stage interfaces of the pipeline: one :class:`~typing.Protocol` per slot.

=========  ===============================================================
slot       signature
=========  ===============================================================
pair       ``(views) → P``: a two-view network's one pass (or no slot)
describe   ``(views, pair) → [Features, Features]``
matcher    ``(features0, features1) → Matches``
pose       ``(view0, view1, matches, pair) → TwoViewGeometry``
depth      ``(views, geometry, pair) → [DepthMap, DepthMap]``
gaussians  ``(views, geometry, depths, pair) → [GaussianMaps, GaussianMaps]``
=========  ===============================================================

``pair`` is the output of the ``pair`` slot (``None`` when the pipeline has none): a backend that needs both
views at once (a two-view network) computes it once and every later stage receives it explicitly. Each backend
has a ``name`` (the report names the backend of every stage). The classical backends are in :mod:`.stages`, the
network ones in :mod:`.neural`; this module imports no stage, so any stage module may name the slots.
"""

from __future__ import annotations

from typing import Any, Protocol

from ..gaussians import GaussianMaps
from .types import DepthMap, Features, Matches, TwoViewGeometry, View

__all__ = ["DepthStage", "DescribeStage", "GaussianStage", "MatchStage", "PairStage", "PoseStage"]


class PairStage(Protocol):
    name: str

    def __call__(self, views: list[View]) -> Any: ...


class DescribeStage(Protocol):
    name: str

    def __call__(self, views: list[View], pair: Any) -> list[Features]: ...


class MatchStage(Protocol):
    name: str

    def __call__(self, f0: Features, f1: Features) -> Matches: ...


class PoseStage(Protocol):
    name: str

    def __call__(self, v0: View, v1: View, matches: Matches, pair: Any) -> TwoViewGeometry: ...


class DepthStage(Protocol):
    name: str

    def __call__(self, views: list[View], geometry: TwoViewGeometry, pair: Any) -> list[DepthMap]: ...


class GaussianStage(Protocol):
    name: str

    def __call__(
        self, views: list[View], geometry: TwoViewGeometry, depths: list[DepthMap], pair: Any
    ) -> list[GaussianMaps]: ...
