"""Shared pytest configuration: the ``slow`` marker, isolated environment for CLI tests, the session fixtures of
``support/`` (the synthetic pairs' photos, the tiny checkpoints) and the evaluation tests' plane data set and oracle
backend (a module may define its own ``plane``).

``tests/`` mirrors ``macsplat_cli/`` in folders without ``__init__.py`` (pytest's default ``prepend`` import mode): a
test module is imported by its basename, so basenames are unique across the folders, and this file's folder,
``tests/``, is put on ``sys.path`` before any test module is imported, so ``import support.<topic>`` works from
every subfolder (and from a single test file run alone). No test module imports another
(``test_suite_layout.py``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

import macsplat_cli  # noqa: F401  (first: sets OMP_WAIT_POLICY before any test imports torch)

# The CLI's Rich consoles are module objects whose width is read from COLUMNS when they are made, which is when a
# test module first imports the CLI (at collection, or inside a test): set before any of that, so the width does not
# depend on which test ran first in a process (two tests read wrapped tables under pytest-xdist otherwise).
# _plain_terminal sets the same values for each test.
os.environ["COLUMNS"] = "200"
os.environ["NO_COLOR"] = "1"
os.environ.pop("FORCE_COLOR", None)

if TYPE_CHECKING:
    from support.scenes import PairFactory


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--runslow", action="store_true", default=False, help="also run tests marked slow")


# The slowest modules, slowest first (each module's seconds in .ci/run's main run at ea8330e, 2026-11-29). A
# pytest-xdist worker (.ci/run: --dist loadfile --no-loadscope-reorder) takes one whole module at a time, in collection
# order: these go first, so that the short modules even out the two workers' ends (xdist's own order, most tests first,
# put test_onnx.py 39th and test_determinism.py 75th of 110: one worker still on a long module after the other had
# finished). A module not listed keeps its place after them; test_suite_layout checks that each one listed exists.
SLOWEST_MODULES = (
    "tests/neural/test_onnx.py",
    "tests/pipeline/test_reconstruct.py",
    "tests/pipeline/multiview/test_multiview.py",
    "tests/training/test_train.py",
    "tests/training/test_hostile_train.py",
    "tests/test_determinism.py",
    "tests/neural/test_hostile_onnx.py",
    "tests/pipeline/multiview/test_joint.py",
    "tests/test_engine.py",
    "tests/cli/test_cli_render.py",
    "tests/datasets/test_scannetpp.py",
    "tests/cli/test_hostile_cli.py",
    "tests/test_gpu_smoke.py",
    "tests/pipeline/pose/test_pose.py",
    "tests/pipeline/pose/test_pose_confidence.py",
    "tests/viewer/test_viewer_browser.py",
    "tests/evaluation/test_eval_shards.py",
    "tests/pipeline/test_undistort.py",
    "tests/test_stress.py",
    "tests/datasets/test_synthetic.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if hasattr(config, "workerinput"):  # a pytest-xdist worker: the slowest modules first (a stable sort)
        rank = {m: i for i, m in enumerate(SLOWEST_MODULES)}
        items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(autouse=True)
def _plain_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    """Deterministic Rich output in CLI tests: no colours, a fixed width."""
    monkeypatch.setenv("NO_COLOR", "1")
    monkeypatch.setenv("COLUMNS", "200")
    monkeypatch.delenv("FORCE_COLOR", raising=False)


@pytest.fixture(autouse=True)
def _library_logs_reach_caplog(monkeypatch: pytest.MonkeyPatch) -> None:
    """The CLI's logging setup turns propagation off on ``macsplat_cli``; caplog needs it on."""
    monkeypatch.setattr(logging.getLogger("macsplat_cli"), "propagate", True)


@pytest.fixture(scope="session")
def pair_files(tmp_path_factory: pytest.TempPathFactory) -> PairFactory:
    """Synthetic pairs' photos and true cameras, written once per session (:class:`support.scenes.PairFactory`)."""
    from support.scenes import PairFactory

    return PairFactory(tmp_path_factory)


@pytest.fixture(scope="session")
def tiny_checkpoints(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """:func:`support.checkpoints.write_tiny_checkpoints` once per session, in a shared folder: read them, write
    elsewhere."""
    from support.checkpoints import write_tiny_checkpoints

    return write_tiny_checkpoints(tmp_path_factory.mktemp("tiny_checkpoints"))


@pytest.fixture(scope="module")
def plane(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """:func:`support.evaluation.write_plane_dataset`, once per module that asks for it."""
    from support.evaluation import write_plane_dataset

    return write_plane_dataset(tmp_path_factory.mktemp("plane") / "plane")


@pytest.fixture
def oracle_backend(monkeypatch: pytest.MonkeyPatch) -> None:
    """``--backend oracle``: the ground-truth reconstructor (:data:`support.evaluation.ORACLE`), for this test."""
    from macsplat_cli.evaluation.reconstructors import BACKENDS

    from support.evaluation import ORACLE

    monkeypatch.setitem(BACKENDS, "oracle", lambda config, models=None: ORACLE)
