"""Shared pytest configuration: the ``slow`` marker, isolated environment for CLI tests."""

from __future__ import annotations

import logging

import pytest

import macsplat_cli  # noqa: F401  (first: sets OMP_WAIT_POLICY before any test imports torch)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--runslow", action="store_true", default=False, help="also run tests marked slow")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
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
