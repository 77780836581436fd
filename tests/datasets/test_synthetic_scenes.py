"""The tabletop and outdoor scenes and the periodic textures of ``datasets/synthetic`` (issue 25's protocol cases)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from macsplat_cli.datasets import synthetic as S
from macsplat_cli.errors import InputError


def _view(kind: S.SceneKind, angle: float = 30.0, **kwargs: object) -> tuple[S.Scene, S.SyntheticView]:
    scene = S.make_scene(kind, 3, **kwargs)  # type: ignore[arg-type]
    cam, _ = S.orbit_pair(scene, angle, width=64, height=48, fov_deg=70.0, seed=3)
    return scene, S.render(scene, cam)


def _textured(image: np.ndarray) -> float:
    """Mean absolute difference of neighbouring pixels: 0 for flat colours."""
    return float(np.abs(np.diff(image, axis=1)).mean())


def test_the_kinds_are_one_literal_with_a_layout_each() -> None:
    assert S.SCENE_KINDS == ("room", "object", "tabletop", "outdoor")
    assert set(S.SCENE_LAYOUTS) == set(S.SCENE_KINDS)
    with pytest.raises(InputError, match="tabletop, outdoor"):
        S.make_scene("garage")  # type: ignore[arg-type]


def test_tabletop_is_mostly_a_near_table_seen_from_above() -> None:
    scene, view = _view("tabletop")
    assert np.isfinite(view.image).all() and view.mask.all()
    assert _textured(view.image) > 0.02
    # 45° above the table, 1 m from its centre: the centre pixel lies on the table or a thing on it, about 1 m away
    assert 0.8 < view.depth[24, 32] < 1.1
    points = S.cast_rays(scene, view.camera, np.array([[32.0, 24.0], [32.0, 44.0]])).points
    assert np.all(np.abs(points[:, 1]) < 0.2)  # the table top is y = 0; the things rise to at most 0.16 m


def test_outdoor_spans_two_orders_of_magnitude_of_depth_and_has_sky() -> None:
    _, view = _view("outdoor")
    d = view.depth[view.mask]
    assert np.isfinite(view.image).all() and _textured(view.image) > 0.02
    assert d.min() < 8.0 and d.max() > 35.0 and d.max() / d.min() > 10.0
    assert 0.02 < 1.0 - view.mask.mean() < 0.6  # sky above the facades (a flat colour)


@pytest.mark.parametrize("kind", ["tabletop", "outdoor"])
def test_orbit_pairs_of_the_new_kinds_keep_the_angle(kind: S.SceneKind) -> None:
    for angle in (10.0, 90.0):
        c0, c1 = S.orbit_pair(kind, angle, seed=1)
        axes = c0.cam_to_world[:3, 2], c1.cam_to_world[:3, 2]
        assert math.degrees(math.acos(float(np.clip(axes[0] @ axes[1], -1, 1)))) == pytest.approx(angle, abs=1e-6)
    c0, _ = S.orbit_pair("tabletop", 100.0, seed=1, elevation_deg=30.0, jitter=False)
    target = S.SCENE_LAYOUTS["tabletop"][0]
    assert math.degrees(math.asin((target[1] - c0.center[1]) / np.linalg.norm(c0.center - target))) == pytest.approx(30)
    with pytest.raises(InputError, match="not reachable"):
        S.orbit_pair("tabletop", 100.0, seed=1)  # 45° above the table: the axes are at most 90° apart


def test_repetitive_changes_only_the_large_surfaces_patterns() -> None:
    plain, rep = S.make_scene("room", 0), S.make_scene("room", 0, repetitive=True)
    assert [p.texture.pattern for p in plain.primitives] == ["random"] * len(plain.primitives)
    patterns = [p.texture.pattern for p in rep.primitives]
    assert set(patterns[:6]) <= set(S.PERIODIC_PATTERNS) and set(patterns[6:]) == {"random"}  # walls; objects
    for a, b in zip(plain.primitives, rep.primitives):
        assert type(a) is type(b) and a.bounding_sphere()[1] == b.bounding_sphere()[1]
        assert a.texture.seed == b.texture.seed and a.texture.albedo == b.texture.albedo


@pytest.mark.parametrize(("pattern", "period"), [("bricks", (0.24, 0.16)), ("tiles", (0.3, 0.3)), ("grid", (0.1, 0.1))])
def test_a_periodic_texture_repeats_exactly(pattern: str, period: tuple[float, float]) -> None:
    quad = S.Quad((0, 0, 0), (2.0, 0, 0), (0, 2.0, 0), S.Texture(seed=4, pattern=pattern))  # type: ignore[arg-type]
    rng = np.random.default_rng(0)
    uv = rng.uniform(0.05, 1.2, (200, 2))
    colours = [quad.surface(np.stack([uv[:, 0] + du, uv[:, 1] + dv, np.zeros(200)]), np.zeros(200))[1]
               for du, dv in ((0.0, 0.0), (period[0], 0.0), (0.0, period[1]))]  # fmt: skip
    np.testing.assert_allclose(colours[1], colours[0], atol=1e-5)
    np.testing.assert_allclose(colours[2], colours[0], atol=1e-5)
    assert colours[0].std(0).max() > 0.02  # not flat: joints, motifs and speckle
    random = S.Quad((0, 0, 0), (2.0, 0, 0), (0, 2.0, 0), S.Texture(seed=4))
    shifted = [random.surface(np.stack([uv[:, 0] + du, uv[:, 1], np.zeros(200)]), np.zeros(200))[1]
               for du in (0.0, period[0])]  # fmt: skip
    assert np.abs(shifted[1] - shifted[0]).mean() > 0.05
