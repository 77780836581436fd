"""One quality, one scene: ``macsplat reconstruct``, :func:`macsplat_cli.engine.reconstruct`, ``macsplat eval``'s
reconstructor and ``macsplat bench``'s give byte-identical Gaussians for the same options, because every one of them
resolves its settings in :func:`macsplat_cli.presets.configure` (before, ``--quality best`` refined in
``reconstruct`` only: the refine preset was applied by that command). ``--refine`` is one option type in all three
commands (``STEPS|auto|off``, :func:`macsplat_cli.cli._options.parse_refine`).
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import torch

from macsplat_cli import evaluation
from macsplat_cli.cameras import load_cameras
from macsplat_cli.cli import main
from macsplat_cli.cli._options import parse_refine_list
from macsplat_cli.engine import EngineConfig, reconstruct
from macsplat_cli.errors import InputError
from macsplat_cli.evaluation import EngineReconstructor, ReconstructSettings, make_reconstructor
from macsplat_cli.evaluation.bench import grid, setting_config
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.pipeline.refine import AUTO_STEPS
from macsplat_cli.pipeline.run import ReconstructConfig, Reconstruction
from macsplat_cli.pipeline.views import ViewConfig
from macsplat_cli.ply import read_ply
from macsplat_cli.presets import Overrides

from support.scenes import PairFactory, PairSpec

SIZE = (128, 96)


@pytest.fixture(scope="module")
def pair(pair_files: PairFactory) -> tuple[Path, Path, Path]:
    """A textured room pair 12° apart at 128×96, and its true cameras (named after the files)."""
    files = pair_files(PairSpec("room", 12.0, SIZE, 60.0, scene_seed=5), camera_names=True)
    return files.a, files.b, files.cameras


def _run(args: list[Any]) -> None:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    assert code == 0, err.getvalue()


def _captured(monkeypatch: pytest.MonkeyPatch, name: str, args: list[Any]) -> Any:
    """The spec a command hands the library's entry point ``evaluation.name`` (replaced: no data set is read)."""
    seen: list[Any] = []
    done = {"run": SimpleNamespace(check=lambda: None), "benchmark": []}[name]  # what the command reads back (-q)
    monkeypatch.setattr(evaluation, name, lambda spec, progress=None: seen.append(spec) or done)
    _run(args)
    [spec] = seen
    return spec


def _case(pair: tuple[Path, Path, Path]) -> tuple[Any, Any, ReconstructSettings]:
    """The two context frames as the evaluation hands them over, with their true cameras."""
    frames = [SimpleNamespace(image=p, camera=c) for p, c in zip(pair[:2], load_cameras(pair[2]))]
    scene = SimpleNamespace(frames=frames)
    return scene, SimpleNamespace(context=(0, 1)), ReconstructSettings(size=SIZE[0], intrinsics="given")


def _same(a: Gaussians, b: Gaussians) -> bool:
    return len(a) == len(b) and all(torch.equal(x, y) for x, y in zip(a.tensors(), b.tensors()))


@pytest.mark.parametrize(("quality", "refine"), [("best", None), ("fast", "3")])
def test_one_quality_gives_one_scene_in_every_command(
    pair: tuple[Path, Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, quality: str, refine: str | None
) -> None:
    """``best`` without ``--refine`` refines :data:`AUTO_STEPS` steps in all four; ``fast --refine 3`` three."""
    refine_args = ["--refine", refine] if refine is not None else []
    options = ["--quality", quality, "--size", SIZE[0], *refine_args]
    _run(["reconstruct", pair[0], pair[1], "-o", tmp_path / "s.ply", "--intrinsics", pair[2], *options, "-q"])
    cli = read_ply(tmp_path / "s.ply")

    # the library, with the same choices
    config = EngineConfig(
        quality=quality,  # type: ignore[arg-type]
        overrides=Overrides(size=SIZE[0], refine=int(refine) if refine is not None else None),
        pipeline=ReconstructConfig(views=ViewConfig(intrinsics=pair[2])),
    )
    lib = reconstruct(pair[:2], config)

    # eval: the engine settings the command builds from the same options, through the evaluation's reconstructor
    data = ["--data", tmp_path, "--out", tmp_path / "results", "-q"]
    engine = _captured(monkeypatch, "run", ["eval", *data, *options]).engine
    scene, case, settings = _case(pair)
    ev = EngineReconstructor(engine)(scene, case, settings)

    # bench: the grid point the command makes of the same options, its engine settings as run_bench makes them
    spec = _captured(monkeypatch, "benchmark", ["bench", *data, *options])
    [point] = grid(spec.backends, spec.sizes, spec.taus, spec.steps, spec.qualities, spec.matchers)
    base = EngineConfig(neural=spec.neural)  # as evaluation.benchmark hands it to run_bench
    bn = make_reconstructor(setting_config(base, point))(scene, case, settings)

    steps = AUTO_STEPS if refine is None else int(refine)
    results: list[Reconstruction] = [lib, ev, bn]
    for rec in results:
        assert rec.report.refine is not None and rec.report.refine.steps == steps
        assert rec.report.compact is not None and rec.report.compact.preset == quality
        assert _same(rec.gaussians, cli)
    assert point.refine_steps == steps


def test_refine_is_one_option_type_in_every_command(
    pair: tuple[Path, Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``STEPS|auto|off`` in ``reconstruct``, ``eval`` and ``bench`` (a comma list of it there), the same values
    and the same refusal."""
    data = ["--data", tmp_path, "--out", tmp_path / "results", "-q"]
    for text, steps in (("auto", AUTO_STEPS), ("off", 0), ("7", 7)):
        engine = _captured(monkeypatch, "run", ["eval", *data, "--refine", text]).engine
        assert engine.overrides.refine == steps and engine.settings().refine.steps == steps
    assert _captured(monkeypatch, "benchmark", ["bench", *data, "--refine", "off,auto,7"]).steps == [0, AUTO_STEPS, 7]
    assert parse_refine_list(None) == [None]  # not given: each quality's
    assert [s.refine_steps for s in grid(qualities=["fast", "balanced", "best"])] == [0, 0, AUTO_STEPS]
    for command in (["reconstruct", pair[0], pair[1], "-o", tmp_path / "s.ply"], ["eval", *data], ["bench", *data]):
        err = io.StringIO()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            assert main([str(a) for a in [*command, "--refine", "-3"]]) == 2
        assert "--refine '-3': give a number of steps, auto or off" in err.getvalue()
    with pytest.raises(InputError, match="--refine"):
        parse_refine_list("2,,x")
