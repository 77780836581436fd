"""Fixtures of the viewer's tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from support.viewer_scene import PlaneScene, write_plane_scene


@pytest.fixture
def plane_scene(tmp_path: Path) -> PlaneScene:
    return write_plane_scene(tmp_path)
