"""Thin commands (issue 38 item 3): ``eval``, ``bench`` and ``train`` map their options onto a spec and call the
library (:func:`macsplat_cli.evaluation.run`, :func:`~macsplat_cli.evaluation.benchmark`,
:func:`macsplat_cli.training.train`); every choice option of every command is declared one way: a plain string with
its choices in the metavar, refused in one ``error:`` line by :func:`macsplat_cli.cli._options.choice`."""

from __future__ import annotations

import ast
import enum
import typing
from pathlib import Path

import pytest

from macsplat_cli.cli import app

from support.cli import run_cli

CLI = Path(__file__).resolve().parents[2] / "macsplat_cli" / "cli"
MAX_BODY_LINES = 35
"""A function of a thin command module: the options mapped onto a spec, the library called, the output drawn."""


def _bodies(path: Path) -> dict[str, int]:
    """Every function of ``path`` → the lines of its body (its docstring left out)."""
    out = {}
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                body = body[1:] or body
            out[node.name] = body[-1].end_lineno - body[0].lineno + 1  # type: ignore[operator]
    return out


@pytest.mark.parametrize("module", ["eval.py", "bench.py", "train.py"])
def test_the_command_modules_keep_no_orchestration(module: str) -> None:
    """Before, ``cli/eval.py`` drew the cases (``select_cases``, 62 lines) and ran them (``_eval``, 75); ``_bench``
    and ``_train`` did the same for theirs."""
    long = {name: n for name, n in _bodies(CLI / module).items() if n > MAX_BODY_LINES}
    assert not long, f"{module}: functions over {MAX_BODY_LINES} lines: {long}"


def test_every_choice_option_is_a_string_with_its_choices_in_the_metavar() -> None:
    """No Enum option: ``eval --layout`` and ``render --backend`` were Enums, the other commands' choices strings."""
    enums = []
    for command in app.registered_commands:
        assert command.callback is not None
        for name, hint in typing.get_type_hints(command.callback, include_extras=True).items():
            types = typing.get_args(hint) if typing.get_origin(hint) is typing.Annotated else (hint,)
            if any(isinstance(t, type) and issubclass(t, enum.Enum) for t in types):
                enums.append(f"{command.callback.__name__}: {name}")
    assert len(app.registered_commands) >= 8 and not enums, enums


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["eval", "--layout", "tree"], "--layout 'tree': use auto, generic, scannetpp, co3d-json, icl-nuim, nyu-rgbd"),
        (["eval", "--intrinsics", "guess"], "--intrinsics 'guess': use given or estimated"),
        (["eval", "--split-by", "depth"], "--split-by 'depth': use auto, coverage, angle"),
        (["bench", "--assignment", "all"], "--assignment 'all': use bin or threshold"),
        (["bench", "--quality", "fast,ultra"], "--quality 'ultra': use fast, balanced, best"),
        (["train", "--layout", "tree"], "--layout 'tree': use auto, generic, scannetpp, co3d-json, icl-nuim, nyu-rgbd"),
        (["train", "--model", "huge"], "--model 'huge': use tiny or full"),
    ],
)
def test_a_bad_choice_is_one_error_line(tmp_path: Path, args: list[str], line: str) -> None:
    code, _, err = run_cli([*args, "--data", tmp_path, "--out", tmp_path / "out"])
    assert code == 2 and err.strip() == f"error: {line}"
    assert not (tmp_path / "out").exists()


def test_render_choices_are_refused_in_one_line(tmp_path: Path) -> None:
    scene = tmp_path / "s.ply"
    code, _, err = run_cli(["render", scene, "--pose", tmp_path / "c.json", "--backend", "opengl"])
    assert code == 2 and err.strip() == "error: --backend 'opengl': use auto, numba, torch, gsplat"
