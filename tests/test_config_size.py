"""Size rules of the stage settings (issue 38): each stage keeps the knobs a user or a preset turns, every other
value is a named module constant beside the code; no setting that nothing sets.

The counts come from ``benchmarks/config_size.py`` (``python -m benchmarks.config_size`` prints them): a leaf is a
dataclass field whose default is not a dataclass; a field is set when its name is assigned somewhere in
``macsplat_cli/``, ``benchmarks/`` or ``tests/`` (a keyword of a call to its class or to ``replace``, or an attribute
assignment).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from benchmarks import config_size as cs
from macsplat_cli.pipeline.run import ReconstructConfig

MAX_RECONSTRUCT_LEAVES = 60
MAX_STAGE_LEAVES = 10
MAX_POSE_STAGE_LEAVES = 15  # pose + search: the pose, its search and its acceptance


def test_the_counter_sees_nested_settings_and_unset_ones() -> None:
    @dataclass
    class Inner:
        a_setting_nothing_sets_xq: int = 1
        hellinger: bool = False  # ShortlistConfig(hellinger=...) sets ShortlistConfig's: by class, not by name

    @dataclass
    class Outer:
        inner: Inner = field(default_factory=Inner)
        size: int = 3  # set: ViewConfig.size is assigned by name (replace(..., size=...))

    assert [p for p, _, _ in cs.leaves(Outer())] == ["inner.a_setting_nothing_sets_xq", "inner.hellinger", "size"]
    assert cs.unset(Outer()) == ["inner.a_setting_nothing_sets_xq", "inner.hellinger"]


def test_reconstruct_config_keeps_the_knobs_that_matter() -> None:
    n = cs.counts()
    stages = {k: v for k, v in n.items() if k not in ("ReconstructConfig", "EngineConfig")}
    assert n["ReconstructConfig"] <= MAX_RECONSTRUCT_LEAVES, n
    assert stages["pose"] + stages["search"] <= MAX_POSE_STAGE_LEAVES, n
    over = {k: v for k, v in stages.items() if k not in ("pose", "search") and v > MAX_STAGE_LEAVES}
    assert over == {}, f"stages over {MAX_STAGE_LEAVES} settings (make the rest module constants): {over}"


def test_every_stage_setting_is_set_by_something() -> None:
    assert cs.unset(ReconstructConfig()) == [], "settings nothing sets: make them module constants beside their code"
