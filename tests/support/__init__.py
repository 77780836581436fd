"""Helpers shared by the test modules, one module per topic, imported as ``support.<topic>`` (``tests/`` is on
``sys.path``: see ``tests/conftest.py``):

* ``numerics``: rounding-error bounds from the arithmetic (unit roundoff, γₙ, a network's forward error), the rotation
  conversions' budgets, a bounded comparison;
* ``cli``: ``macsplat ARGS`` in process, its one ``error:`` line, a file-size limit;
* ``gaussians``: random Gaussians in front of a camera, a centred pinhole;
* ``scenes``: synthetic pairs rendered once per session (and the session fixture ``pair_files``);
* ``checkpoints``: tiny random-weight checkpoints in the official layouts (and the session fixture
  ``tiny_checkpoints``);
* ``neural``: the neural stages' scene and the oracle backbone that returns its exact point maps;
* ``evaluation``: the evaluation tests' textured plane and data sets.

No test module imports another (``tests/test_suite_layout.py``).
"""

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
"""The repository root."""
