"""``macsplat train``'s library entry point (:func:`macsplat_cli.training.train`): a recipe's
:class:`~macsplat_cli.training.config.TrainConfig` (one dataclass for the recipe's values and the loop's) and the
run's files in a :class:`~macsplat_cli.training.TrainSpec`, trained without typer, nothing drawn."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from macsplat_cli.datasets import synthetic as syn
from macsplat_cli.errors import InputError
from macsplat_cli.training import TrainConfig, TrainSpec, train
from macsplat_cli.training.recipes import get_recipe
from macsplat_cli.training.runner import RUN_FILES

SIZE = (64, 48)


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A generic-layout room: 4 posed views 5° apart at 96×64, with depth."""
    root = tmp_path_factory.mktemp("runner_data")
    room = syn.make_scene("room", 1)
    cams = syn.orbit_cameras(room, [0.0, 5.0, 10.0, 15.0], width=96, height=64)
    syn.write_dataset(root, room, [dataclasses.replace(c, name=f"f{i}") for i, c in enumerate(cams)], supersample=1)
    return root


def test_a_recipe_is_the_runs_config() -> None:
    """The recipe's values and the loop's in one dataclass: ``released-code``'s steps follow the scenes until
    ``steps`` is chosen."""
    released = get_recipe("released-code", Path("run"))
    assert isinstance(released, TrainConfig) and released.recipe == "released-code"
    assert released.steps_for(scenes=3, world_size=1) == 600
    chosen = dataclasses.replace(released, steps=7, steps_per_scene=None)
    assert chosen.steps_for(scenes=3, world_size=1) == 7
    names = [f.name for f in dataclasses.fields(TrainConfig)]
    assert len(names) == len(set(names)) and {"size", "crop", "targets", "lr", "batch", "loss"} <= set(names)


def test_train_runs_a_spec_without_the_command(data: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "run"
    config = dataclasses.replace(
        get_recipe("paper", out), steps=2, size=SIZE, targets=1, val_every=0, ckpt_every=2, lr=1e-3, warmup=1
    )
    outcome = train(TrainSpec(data=data, config=config, overridden=["--steps"], model="tiny", init="random"))
    assert outcome.is_main and outcome.result.steps == 2
    assert {p.name for p in out.iterdir()} == set(RUN_FILES)
    assert capsys.readouterr() == ("", "")  # the library draws nothing
    run = json.loads((out / "run.json").read_text())
    assert run["recipe"] == {"name": "paper", "overridden": ["--steps"]}
    assert run["config"]["size"] == list(SIZE) and run["config"]["steps"] == 2
    assert run["config"]["loss"]["geometry_weight"] == 1.0  # a random backbone learns geometry...
    assert config.loss.geometry_weight == 0.0  # ...in the run's copy: the caller's config is not changed


def test_train_checks_the_spec_before_anything_is_read(tmp_path: Path) -> None:
    config = get_recipe("paper", tmp_path / "run")
    with pytest.raises(InputError, match="--init weights needs --weights"):
        train(TrainSpec(data=tmp_path / "nowhere", config=config))
    with pytest.raises(InputError, match="--resume and --force contradict each other"):
        train(TrainSpec(data=tmp_path / "nowhere", config=config, init="random", resume=True, force=True))
    assert not (tmp_path / "run").exists()
