"""Logging setup for the CLI: one Rich handler on stderr for the ``macsplat_cli`` logger."""

from __future__ import annotations

import logging

from rich.console import Console
from rich.logging import RichHandler

__all__ = ["remove_logging", "setup_logging"]


def setup_logging(console: Console, *, verbose: bool = False, quiet: bool = False) -> None:
    """Route library logs to ``console``: DEBUG with ``verbose``, WARNING with ``quiet``, else INFO."""
    logger = logging.getLogger("macsplat_cli")
    for h in list(logger.handlers):
        logger.removeHandler(h)
    handler = RichHandler(console=console, show_time=False, show_path=False, markup=False, rich_tracebacks=True)
    handler.setFormatter(logging.Formatter("%(message)s"))
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)
    logger.propagate = False


def remove_logging() -> None:
    """Detach the handler installed by :func:`setup_logging` (library use after a CLI call)."""
    logger = logging.getLogger("macsplat_cli")
    for h in list(logger.handlers):
        logger.removeHandler(h)
    logger.propagate = True
    logger.setLevel(logging.NOTSET)
