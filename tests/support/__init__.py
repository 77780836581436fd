"""Helpers shared by the test modules (imported as ``support.<topic>``, with ``tests/`` on ``sys.path`` as for
``_helpers``); no test module imports another."""
