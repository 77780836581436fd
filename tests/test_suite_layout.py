"""The test suite's own layout rules, checked on the source so that they stay true.

* ``tests/`` mirrors ``macsplat_cli/``: every folder under ``tests/`` (but ``support/``) names a package of
  ``macsplat_cli`` at the same path (or a module, while it is being split into one), and tests of a top-level module
  sit in ``tests/`` itself.
* No test module imports another: shared helpers live in ``tests/support/`` (one module per topic).
* Test folders have no ``__init__.py`` (pytest's ``prepend`` import mode imports a test module by its basename), so
  test module basenames are unique across the folders.
* The ``slow`` marker's tests are skipped by a plain ``pytest -q`` (``conftest.py``) and run by CI: ``.ci/run`` gives
  its full pytest run ``--runslow``, after its lint, format and type checks.
"""

from __future__ import annotations

import ast
import re
from collections import Counter
from pathlib import Path

TESTS = Path(__file__).resolve().parent
PACKAGE = TESTS.parent / "macsplat_cli"
SUPPORT = "support"


def _test_folders() -> list[Path]:
    """Folders under ``tests/`` holding tests (not ``support/``, caches or hidden folders), relative to ``tests/``."""
    out = []
    for d in sorted(p for p in TESTS.rglob("*") if p.is_dir()):
        rel = d.relative_to(TESTS)
        if rel.parts[0] == SUPPORT or any(part.startswith((".", "__")) for part in rel.parts):
            continue
        out.append(rel)
    return out


def _test_modules() -> list[Path]:
    return sorted(p for p in TESTS.rglob("test_*.py") if SUPPORT not in p.relative_to(TESTS).parts[:1])


def _imported_modules(path: Path) -> set[str]:
    """Every module name ``path`` imports (absolute imports, anywhere in the file)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def test_every_test_folder_mirrors_a_package() -> None:
    folders = _test_folders()
    assert folders, "tests/ has no subfolders: the layout check would pass vacuously"
    strays = [
        str(rel)
        for rel in folders
        if not (PACKAGE / rel / "__init__.py").is_file() and not (PACKAGE / rel).with_suffix(".py").is_file()
    ]
    assert not strays, f"tests/ folders with no macsplat_cli package (or module) at the same path: {strays}"


def test_no_test_module_imports_another() -> None:
    test_names = {p.stem for p in _test_modules()}
    offenders = []
    for path in [*_test_modules(), *(TESTS / SUPPORT).rglob("*.py"), TESTS / "conftest.py"]:
        for name in _imported_modules(path):
            top = name.split(".")[0]
            if top in test_names or top.startswith("test_") or top in ("conftest", "_helpers"):
                offenders.append(f"{path.relative_to(TESTS)} imports {name}")
    assert not offenders, "shared helpers belong in tests/support/: " + "; ".join(sorted(offenders))


def test_test_folders_are_not_packages_and_basenames_are_unique() -> None:
    inits = [str(rel) for rel in _test_folders() if (TESTS / rel / "__init__.py").exists()]
    assert not inits and not (TESTS / "__init__.py").exists(), f"__init__.py in test folders: {inits}"
    counts = Counter(p.name for p in _test_modules())
    assert not [n for n, c in counts.items() if c > 1], f"test module basenames used twice: {counts.most_common(3)}"


def test_the_slow_tests_are_marked_and_ci_runs_them_after_its_checks() -> None:
    marked = [p.name for p in _test_modules() if re.search(r"pytest\.mark\.slow\b", p.read_text(encoding="utf-8"))]
    assert marked, "no test is marked slow: the marker's skip has nothing to skip"
    lines = [ln.strip() for ln in (TESTS.parent / ".ci" / "run").read_text(encoding="utf-8").splitlines()]
    full = [i for i, ln in enumerate(lines) if ln.startswith("pytest_rc python -m pytest -q") and "--runslow" in ln]
    assert full, f".ci/run never runs the slow tests of {marked} (its full pytest run lacks --runslow)"
    for check in ("ruff check .", "ruff format --check .", "mypy"):  # mypy: the files pyproject.toml names
        at = [i for i, ln in enumerate(lines) if ln.startswith(check)]
        assert at and at[0] < full[0], f".ci/run does not run {check!r} before its tests"


def test_the_slowest_modules_listed_for_ci_exist_and_ci_keeps_their_order() -> None:
    """conftest's ``SLOWEST_MODULES`` (the order CI's workers take the modules in) names modules that exist, each once,
    and ``.ci/run`` keeps that order (xdist would reorder the modules by their number of tests)."""
    tree = ast.parse((TESTS / "conftest.py").read_text(encoding="utf-8"))
    listed = next(
        (
            ast.literal_eval(node.value)
            for node in tree.body
            if isinstance(node, ast.Assign) and [getattr(t, "id", None) for t in node.targets] == ["SLOWEST_MODULES"]
        ),
        (),
    )
    assert listed and len(set(listed)) == len(listed), listed
    missing = [m for m in listed if not (TESTS.parent / m).is_file()]
    assert not missing, f"conftest.SLOWEST_MODULES names modules that do not exist: {missing}"
    run = (TESTS.parent / ".ci" / "run").read_text(encoding="utf-8")
    assert re.search(r"^XDIST=\(.*--dist loadfile --no-loadscope-reorder", run, re.M), "xdist would reorder them"
