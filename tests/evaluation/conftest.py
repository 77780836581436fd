"""Fixtures of the evaluation's tests: a small synthetic plane data set and the oracle backend."""

from __future__ import annotations

from pathlib import Path

import pytest

from macsplat_cli.evaluation.reconstructors import BACKENDS

from support.evaluation import ORACLE, write_plane_dataset


@pytest.fixture(scope="module")
def plane(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The plane data set of ``support.evaluation``, once per module (a module may define its own)."""
    return write_plane_dataset(tmp_path_factory.mktemp("plane") / "plane")


@pytest.fixture
def oracle_backend(monkeypatch: pytest.MonkeyPatch) -> None:
    """``--backend oracle``: the ground-truth reconstructor, for this test."""
    monkeypatch.setitem(BACKENDS, "oracle", lambda config, models=None: ORACLE)
