"""The CLI maps options to the engine's configuration and nothing else: each ``reconstruct`` flag, parsed by the
command's own Typer declaration, gives the :class:`~macsplat_cli.engine.EngineConfig` field it names, and the
stage settings the engine makes of it (:meth:`~macsplat_cli.engine.EngineConfig.settings`). No reconstruction runs.

Also the CLI's import cost: importing it, and asking any command for ``--help``, loads no torch, OpenCV or Numba.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest
import typer.main

from macsplat_cli.cli import app, main
from macsplat_cli.cli.reconstruct import reconstruct_config
from macsplat_cli.engine import EngineConfig, NeuralOptions
from macsplat_cli.errors import InputError
from macsplat_cli.pipeline.descriptors import SiftConfig
from macsplat_cli.pipeline.matching import MatchConfig
from macsplat_cli.pipeline.refine import AUTO_STEPS, RefineConfig
from macsplat_cli.pipeline.run import ReconstructConfig
from macsplat_cli.presets import FAST_SIFT, Overrides, StageSettings

ARGS = ["a.jpg", "b.jpg", "-o", "s.ply"]


def _config(*options: str) -> EngineConfig:
    """The configuration ``macsplat reconstruct a.jpg b.jpg -o s.ply OPTIONS`` builds."""
    command = typer.main.get_command(app).commands["reconstruct"]  # type: ignore[attr-defined]
    params = command.make_context("reconstruct", [*ARGS, *options]).params
    names = inspect.signature(reconstruct_config).parameters
    return reconstruct_config(**{k: v for k, v in params.items() if k in names})


def _settings(*options: str) -> StageSettings:
    config = _config(*options)
    config.validate(files=False)
    return config.settings()


def test_defaults_are_the_balanced_classical_pipeline() -> None:
    config = _config()
    assert (config.backend, config.quality, config.overrides) == ("classical", "balanced", Overrides())
    assert config.neural == NeuralOptions() and config.refine == RefineConfig()
    s = _settings()
    default = ReconstructConfig()
    assert s.pipeline.views.size == 512 and s.pipeline.matching == MatchConfig()
    assert s.pipeline.descriptors == SiftConfig() and s.pipeline.depth == default.depth
    assert s.pipeline.background.enabled and not s.pipeline.search.accept_low_confidence
    assert s.compact.name == "balanced" and s.compact.budget is None
    assert s.refine.steps == 0 and s.neural is None


def test_quality_fast_is_the_small_working_size_and_the_light_stages() -> None:
    s = _settings("--quality", "fast")
    assert s.pipeline.views.size == 384
    assert (s.pipeline.descriptors.detect_size, s.pipeline.descriptors.max_keypoints) == FAST_SIFT
    assert s.pipeline.depth.slanted_iters == 0 and s.compact.name == "fast"
    assert _config("--quality", " FAST ").quality == "fast"


def test_quality_best_keeps_the_stages_and_the_size_overrides_the_preset() -> None:
    s = _settings("--quality", "best", "--size", "256")
    assert s.pipeline.views.size == 256 and s.compact.name == "best" and not s.compact.adaptive
    assert s.pipeline.descriptors == SiftConfig() and s.pipeline.depth == ReconstructConfig().depth
    assert _settings("--quality", "fast", "--size", "512").pipeline.views.size == 512


def test_budget_bounds_the_compaction() -> None:
    assert _config("--budget", "5000").overrides.budget == 5000
    assert _settings("--budget", "5000").compact.budget == 5000


def test_conf_threshold_is_the_matching_tau_of_either_backend() -> None:
    assert _config("--conf-threshold", "0.2").overrides.conf_threshold == 0.2
    assert _settings("--conf-threshold", "0.2").pipeline.matching.conf_threshold == 0.2
    neural = ["--backend", "neural", "--weights", "w.pth"]
    assert _settings(*neural).pipeline.matching.conf_threshold == 1.0
    assert _settings(*neural, "--conf-threshold", "3").pipeline.matching.conf_threshold == 3.0


def test_refine_flags_make_one_refine_config() -> None:
    """``--refine STEPS|auto|off`` is the steps override; how it refines is ``EngineConfig.refine`` (its steps the
    engine's to set)."""
    assert _config("--refine", "auto").overrides.refine == AUTO_STEPS == 25
    assert _config("--refine", "auto").refine == RefineConfig()
    assert _config("--refine", "AUTO").overrides.refine == 25
    assert _config("--refine", "off").overrides.refine == 0 == _config("--refine", " Off ").overrides.refine
    config = _config("--refine", "7", "--refine-scale", "1", "--no-mac", "--lpips-weights", "vgg")
    assert config.refine == RefineConfig(use_mac=False, lpips_weights=Path("vgg"))
    assert config.overrides.refine_scale == 1
    assert config.settings().refine == RefineConfig(steps=7, scale=1, use_mac=False, lpips_weights=Path("vgg"))
    assert _settings("--refine", "7").refine.steps == 7
    for bad in ("abc", "-2", "1.5", "", "auto,3"):
        with pytest.raises(InputError, match="--refine"):
            _config("--refine", bad)


def test_refine_defaults_to_the_presets() -> None:
    """Without --refine: ``best`` refines (auto), ``fast`` and ``balanced`` do not; --refine 0 turns it off."""
    assert _config("--quality", "best").overrides.refine is None  # the preset decides, in the engine
    assert _settings("--quality", "best").refine.steps == AUTO_STEPS
    assert _settings("--quality", "balanced").refine.steps == 0 and _settings().refine.steps == 0
    assert _settings("--quality", "fast").refine.steps == 0
    assert _settings("--quality", "best", "--refine", "0").refine.steps == 0
    assert _settings("--quality", "fast", "--refine", "auto").refine.steps == AUTO_STEPS


def test_intrinsics_far_layer_and_low_confidence_reach_the_pipeline() -> None:
    c = _config("--intrinsics", "k.json", "--focal", "900", "--no-far-layer", "--accept-low-confidence").pipeline
    assert (c.views.intrinsics, c.views.focal) == (Path("k.json"), 900.0)
    assert not c.background.enabled and c.search.accept_low_confidence


def test_neural_flags_make_the_neural_options_and_stage_settings() -> None:
    files = ["--weights", "w.pth", "--gaussian-head", "h.ckpt", "--dino", "d.pth", "--fusion", "f.pt"]
    config = _config("--backend", " Neural", *files, "--device", "CUDA", "--precision", "BF16")
    assert config.backend == "neural"
    assert config.neural == NeuralOptions(
        weights=Path("w.pth"), gaussian_head=Path("h.ckpt"), dino=Path("d.pth"), fusion=Path("f.pt"), device="cuda",
        precision="bf16",
    )  # fmt: skip
    s = config.settings()
    assert s.neural is not None and (s.neural.precision, s.neural.fusion) == ("bf16", "always")
    assert s.pipeline.search.fallback is False and s.pipeline.search.guided_band_px is None
    assert not s.pipeline.matching.ratio_confidence
    assert _settings("--backend", "neural", "--weights", "w.pth", "--quality", "fast").neural.fusion == "auto"


def test_matcher_chooses_the_pose_search_tiers() -> None:
    """``--matcher``: sift no learned tier; auto (default) adds it after the SIFT tiers; aliked the learned matcher
    alone; a learned matcher with the neural backend, or an unknown name, is a usage error."""
    from macsplat_cli.pipeline.learned import LearnedConfig

    assert _config().matcher == "auto" and _config("--matcher", " SIFT").matcher == "sift"
    assert _settings().pipeline.search == _settings("--matcher", "auto").pipeline.search
    auto = _settings("--matcher", "auto").pipeline.search
    assert auto.learned == LearnedConfig() and not auto.learned_primary
    assert auto.fallback and auto.wide
    assert _settings("--matcher", "sift").pipeline.search.learned is None
    forced = _settings("--matcher", "aliked").pipeline.search
    assert forced.learned == LearnedConfig() and forced.learned_primary
    assert not forced.fallback and not forced.wide
    with pytest.raises(InputError, match="--matcher"):
        _settings("--matcher", "orb")
    with pytest.raises(InputError, match="--matcher aliked"):
        _config("--backend", "neural", "--weights", "w.pth", "--matcher", "aliked").validate(files=False)
    assert _settings("--backend", "neural", "--weights", "w.pth").pipeline.search.learned is None


def _run_python(code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout


def test_cli_import_and_help_load_no_torch_opencv_or_numba() -> None:
    """``macsplat --help`` stays fast: the CLI imports the library only inside the commands."""
    code = (
        "import contextlib, io, json, sys\n"
        "from macsplat_cli.cli import main\n"
        "heavy = ('torch', 'cv2', 'numba', 'onnxruntime')\n"
        "seen = {'import': [m for m in heavy if m in sys.modules]}\n"
        "for cmd in ([], ['reconstruct'], ['render'], ['eval'], ['bench'], ['train'], ['export-onnx']):\n"
        "    with contextlib.redirect_stdout(io.StringIO()):\n"
        "        code = main([*cmd, '--help'])\n"
        "    seen[' '.join(cmd) or 'macsplat'] = [m for m in heavy if m in sys.modules] + ([code] if code else [])\n"
        "print(json.dumps(seen))\n"
    )
    seen = json.loads(_run_python(code))
    assert seen == {k: [] for k in seen} and len(seen) == 8


def test_help_names_the_presets_choices() -> None:
    """The metavars come from the one list of names (:mod:`macsplat_cli.presets`)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["reconstruct", "--help"]) == 0
    text = " ".join(out.getvalue().split())
    assert "fast|balanced|best" in text and "classical|neural" in text and "auto|sift|aliked" in text
