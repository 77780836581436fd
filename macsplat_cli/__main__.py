"""``python -m macsplat_cli``."""

from .cli import run

run()
