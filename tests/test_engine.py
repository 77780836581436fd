"""The engine: one assembly of a reconstruction for the CLI, the evaluation and the library.

* the CLI's scene and the evaluation's reconstruction of the same pair and settings are the same
  Gaussians (before the engine they were assembled twice, and the evaluation skipped settings);
* settings are validated once, before any work; models load once for many reconstructions;
* the typed report serialises to strict JSON.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import io
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from macsplat_cli import engine
from macsplat_cli.cameras import load_cameras
from macsplat_cli.cli import main
from macsplat_cli.engine import EngineConfig, Models, NeuralOptions, load_models, reconstruct, render_path
from macsplat_cli.errors import InputError
from macsplat_cli.evaluation import EngineReconstructor, ReconstructSettings
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.pipeline.matching import MatchConfig
from macsplat_cli.pipeline.refine import RefineConfig
from macsplat_cli.pipeline.run import Pipeline, ReconstructConfig, count_gaussians
from macsplat_cli.pipeline.views import ViewConfig
from macsplat_cli.ply import read_ply
from macsplat_cli.presets import Overrides

from support.scenes import PairFactory, PairSpec

SIZE = (192, 144)


@pytest.fixture(scope="module")
def pair(pair_files: PairFactory) -> tuple[Path, Path, Path]:
    """A textured room pair 12° apart at 192×144, and its true cameras (named after the files)."""
    files = pair_files(PairSpec("room", 12.0, SIZE, 60.0, scene_seed=5), camera_names=True)
    return files.a, files.b, files.cameras


def _config(cams: Path, steps: int = 0) -> EngineConfig:
    return EngineConfig(
        overrides=Overrides(size=SIZE[0], refine=steps, refine_scale=4),
        pipeline=ReconstructConfig(views=ViewConfig(intrinsics=cams)),
    )


def test_engine_without_refinement_is_the_pipeline_then_the_compaction(pair: tuple[Path, Path, Path]) -> None:
    """The engine's maps are the pipeline's; its scene is their compaction at the configured quality."""
    from macsplat_cli.pipeline.compact import compact_reconstruction
    from macsplat_cli.presets import compact_config

    rec = reconstruct(pair[:2], _config(pair[2]))
    ref = Pipeline(_config(pair[2]).settings().pipeline).run(pair[:2])
    # one result shape for any number of photos: every view's pose; the two-view geometry, a detail of the pair
    assert rec.pose is not None and rec.multiview is None and len(rec.poses) == len(rec.views) == 2
    for k, T in enumerate(rec.poses):
        assert np.array_equal(T, rec.pose.geometry.cam_to_world(k))
        assert np.array_equal(rec.cameras(original_size=False).cameras[k].cam_to_world, T)
        assert np.array_equal(rec.views[k].K, (rec.pose.geometry.K0, rec.pose.geometry.K1)[k])
    for m, r in zip(rec.maps, ref.maps):
        for a, b in zip(m.tensors(), r.tensors()):
            assert torch.equal(a, b)
    expected, _ = compact_reconstruction(ref, compact_config("balanced"))
    assert ref.background is not None and ref.background.gaussians is not None  # the far layer, not compacted
    expected = Gaussians.cat([expected, ref.background.gaussians])
    for a, b in zip(rec.gaussians.tensors(), expected.tensors()):
        assert torch.equal(a, b)
    assert rec.report.gaussians == len(rec.gaussians) == len(rec.compacted) + len(ref.background.gaussians)
    assert len(rec.compacted) < 0.6 * count_gaussians(ref.maps)
    doc = rec.report.to_json()
    assert doc["compact"]["preset"] == "balanced" and doc["compact"]["after"] == len(rec.compacted)
    assert "compact" in doc["times_s"] and rec.report.refine is None and "refine" not in doc
    best_config = _config(pair[2]).replace(quality="best", overrides=Overrides(size=SIZE[0], budget=1000, refine=0))
    best = reconstruct(pair[:2], best_config)
    assert len(best.gaussians) == 1000 and best.report.compact.steps[-1].name == "budget"


def test_cli_and_evaluation_build_the_same_refined_scene(pair: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """``reconstruct --refine`` and ``eval --refine`` run the same code: the same Gaussians, the same report."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["reconstruct", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "s.ply"), "--size", str(SIZE[0]),
                     "--intrinsics", str(pair[2]), "--refine", "3", "--refine-scale", "4", "-q",
                     "--report", str(tmp_path / "r.json")])  # fmt: skip
    assert code == 0, err.getvalue()
    cli_scene = read_ply(tmp_path / "s.ply")
    cli_report = json.loads((tmp_path / "r.json").read_text())

    # the two context frames as the evaluation hands them over, with their true cameras
    scene = SimpleNamespace(
        frames=[SimpleNamespace(image=p, camera=c) for p, c in zip(pair[:2], load_cameras(pair[2]))]
    )
    case = SimpleNamespace(context=(0, 1))
    recon = EngineReconstructor(EngineConfig(overrides=Overrides(refine=3, refine_scale=4)))
    rec = recon(scene, case, ReconstructSettings(size=SIZE[0], intrinsics="given"))  # type: ignore[arg-type]
    assert rec.report.refine is not None and rec.report.refine.steps == cli_report["refine"]["steps"]
    assert rec.report.refine.scale == cli_report["refine"]["scale"] == 4
    assert len(rec.gaussians) == len(cli_scene) == cli_report["gaussians"]
    # (a) the same code on the same inputs in one process (and the PLY stores the float32 values exactly)
    for a, b in zip(rec.gaussians.tensors(), cli_scene.tensors()):
        assert torch.equal(a, b)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"overrides": Overrides(conf_threshold=math.nan)}, "--conf-threshold nan"),
        ({"overrides": Overrides(conf_threshold=-1.0)}, "--conf-threshold -1.0"),
        ({"backend": "magic"}, "--backend 'magic'"),
        ({"neural": NeuralOptions(weights=Path("m.pth"))}, "--weights only apply to --backend neural"),
        ({"neural": NeuralOptions(precision="fp8")}, "--precision 'fp8'"),
        ({"backend": "neural"}, "needs the MASt3R checkpoint"),
        ({"backend": "neural", "neural": NeuralOptions(weights=Path("m.pth"), dino=Path("d.pth"))}, "--dino needs"),
        ({"refine": RefineConfig(lpips_weights=Path("vgg"))}, "--lpips-weights is used by the refinement"),
        ({"overrides": Overrides(refine=-1)}, "--refine -1"),
        ({"overrides": Overrides(refine=2, refine_scale=5)}, "--refine-scale 5: use 1 to 4"),
        ({"refine": RefineConfig(scale=1)}, "refine.scale 1: set it with EngineConfig.overrides.refine_scale"),
        ({"neural": NeuralOptions(device="tpu")}, "--device 'tpu': use cpu or cuda"),
        ({"backend": "neural", "neural": NeuralOptions(weights=Path("m.onnx"), dino=Path("d"))}, "drop --dino"),
        ({"pipeline": ReconstructConfig(views=ViewConfig(size=256))}, "set it with EngineConfig.overrides.size"),
        ({"pipeline": ReconstructConfig(matching=MatchConfig(conf_threshold=0.1))}, "overrides.conf_threshold"),
        ({"refine": RefineConfig(steps=5)}, "refine.steps 5: set it with EngineConfig.overrides.refine"),
        ({"quality": "ultra"}, "--quality 'ultra': use fast, balanced, best"),
        ({"overrides": Overrides(budget=0)}, "--budget 0"),
        ({"overrides": Overrides(budget=-5)}, "--budget -5"),
        ({"overrides": Overrides(budget=2.5)}, "--budget 2.5"),
        ({"overrides": Overrides(size=0)}, "--size 0"),
    ],
)
def test_bad_settings_fail_before_any_work(pair: tuple[Path, Path, Path], changes: dict, message: str) -> None:
    config = EngineConfig(**changes)
    calls = []
    with pytest.raises(InputError, match=message.replace("(", r"\(")):
        reconstruct(pair[:2], config, on_stage=lambda stage, event: calls.append(stage))
    assert calls == []  # not even the images were read


def test_lpips_weights_are_a_usage_error_only_where_no_refinement_runs() -> None:
    """``balanced`` refines three photos or more by itself (:func:`~macsplat_cli.presets.refine_steps`): there the
    LPIPS weights have a refinement to serve, on two photos they need ``--refine``."""
    config = EngineConfig(refine=RefineConfig(lpips_weights=Path("vgg")))
    with pytest.raises(InputError, match="--lpips-weights is used by the refinement"):
        config.validate(photos=2)
    config.validate(photos=3)
    with pytest.raises(InputError, match="--lpips-weights is used by the refinement"):
        EngineConfig(quality="fast", refine=config.refine).validate(photos=3)


def test_models_load_once_for_many_reconstructions(
    pair: tuple[Path, Path, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    loads = []
    models = load_models(_config(pair[2]))
    real = engine._load_models
    monkeypatch.setattr(engine, "_load_models", lambda config: loads.append(1) or real(config))
    for _ in range(2):
        reconstruct(pair[:2], _config(pair[2]), models=models)
    assert loads == []
    reconstruct(pair[:2], _config(pair[2]))
    assert loads == [1]
    assert isinstance(models, Models) and models.predictor is None


def test_report_is_strict_json(pair: tuple[Path, Path, Path]) -> None:
    rec = reconstruct(pair[:2], _config(pair[2]))
    rec.report.pose["median_sampson_px"] = float("nan")  # a measurement that could not be made
    rec.report.pose["scalar"] = np.float32(1.5)
    doc = json.loads(json.dumps(rec.report.to_json(), allow_nan=False))
    assert doc["pose"]["median_sampson_px"] is None and doc["pose"]["scalar"] == 1.5
    assert doc["images"][0]["working_size"] == list(SIZE) and doc["scale"] == "relative"
    # float64 sums of the stage times in two orders: ≤ 2γₙ ≤ 2n·eps of the total
    parts = [v for k, v in doc["times_s"].items() if k != "total"]
    assert doc["times_s"]["total"] == pytest.approx(sum(parts), rel=2 * len(parts) * np.finfo(float).eps, abs=0)
    assert "neural" not in doc and "outputs" not in doc
    rec.report.add_time("extra", 2.0)
    assert rec.report.times_s["total"] == doc["times_s"]["total"] + 2.0  # the same one addition (JSON keeps repr)


def test_fast_preset_leaves_out_the_slanted_refinement_and_detects_sift_smaller() -> None:
    """``--quality fast`` configures the classical stages for speed; the other presets keep the defaults."""
    from macsplat_cli.engine import EngineConfig, Models, build_pipeline
    from macsplat_cli.presets import FAST_SIFT

    fast = build_pipeline(EngineConfig(quality="fast"), Models()).config
    balanced = build_pipeline(EngineConfig(), Models()).config
    assert fast.depth.slanted_iters == 0 < balanced.depth.slanted_iters
    assert (fast.descriptors.detect_size, fast.descriptors.max_keypoints) == FAST_SIFT
    assert balanced.descriptors.detect_size > FAST_SIFT[0]
    assert dataclasses.replace(fast.depth, slanted_iters=balanced.depth.slanted_iters) == balanced.depth


def _modules_after(code: str, loaded: str) -> list[str]:
    """The modules a fresh interpreter has loaded after running ``code``, of those the expression ``loaded`` (over
    a module name ``m``) selects."""
    import json
    import subprocess
    import sys

    script = f"import json, sys\n{code}\nprint(json.dumps(sorted(m for m in sys.modules if {loaded})))\n"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    return json.loads(out)


def test_validation_imports_no_backend_to_check_the_values() -> None:
    """The values are checked with the names of :mod:`macsplat_cli.presets`: no network module is loaded for it."""
    code = (
        "from macsplat_cli.engine import EngineConfig, NeuralOptions\n"
        "from pathlib import Path\n"
        "EngineConfig(backend='neural', quality='fast', neural=NeuralOptions(weights=Path('m.onnx'))).validate()\n"
        "EngineConfig(backend='neural', neural=NeuralOptions(weights=Path('m.pth'), device='cuda')).validate()"
    )
    assert _modules_after(code, "m.startswith(('macsplat_cli.neural', 'onnxruntime'))") == []


def test_the_engine_and_its_settings_import_no_kernels() -> None:
    """Importing the engine and resolving a run's settings loads neither Numba nor the renderer: the kernels are
    imported by the background compilation thread, beside the first stages (``--quality fast``'s start-up)."""
    code = (
        "from macsplat_cli.engine import EngineConfig\n"
        "from macsplat_cli.presets import Overrides\n"
        "from macsplat_cli.cli._options import parse_refine\n"
        "EngineConfig(quality='fast', overrides=Overrides(refine=parse_refine('auto'))).settings()"
    )
    loaded = "m.split('.')[0] in ('numba', 'llvmlite') or m.startswith('macsplat_cli.render')"
    assert _modules_after(code, loaded) == []


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_cuda_is_checked_when_the_models_load_before_the_weights_stage(pair: tuple[Path, Path, Path]) -> None:
    """``--device cuda`` without CUDA: the same usage error, raised by the loading, before any stage event."""
    config = EngineConfig(backend="neural", neural=NeuralOptions(weights=Path("m.pth"), device="cuda"))
    config.validate()  # the values are fine
    calls = []
    for run in (
        lambda: load_models(config),
        lambda: reconstruct(pair[:2], config, on_stage=lambda s, e: calls.append(s)),
    ):
        with pytest.raises(InputError, match="--device cuda: CUDA is not available"):
            run()
    assert calls == []


def test_settings_apply_the_presets_once_and_leave_the_config_alone() -> None:
    """``EngineConfig.settings()``: the working size, τ, the fast stages and the compaction from one call; the
    configuration itself is not modified (τ goes down once, nothing is written back)."""
    config = EngineConfig(quality="fast", overrides=Overrides(conf_threshold=0.1, budget=500))
    before = copy.deepcopy(config)
    s = config.settings()
    assert s.pipeline.views.size == 384 and s.pipeline.matching.conf_threshold == 0.1
    assert s.pipeline.depth.slanted_iters == 0 and s.compact.name == "fast" and s.compact.budget == 500
    assert s.neural is None and s.refine.steps == 0
    assert config == before
    assert EngineConfig(quality="best", overrides=Overrides(size=256)).settings().pipeline.views.size == 256
    neural = EngineConfig(backend="neural", quality="fast").settings()
    assert neural.pipeline.matching.conf_threshold == 1.0 and not neural.pipeline.matching.ratio_confidence
    assert neural.pipeline.search.fallback is False and neural.pipeline.search.guided_band_px is None
    assert neural.neural is not None and neural.neural.fusion == "auto"
    tau = EngineConfig(backend="neural", overrides=Overrides(conf_threshold=2.0)).settings().pipeline.matching
    assert tau.conf_threshold == 2.0
    assert EngineConfig(backend="neural", quality="best").settings().neural.fusion == "always"


def test_render_path_renders_the_novel_views_in_one_call(pair: tuple[Path, Path, Path]) -> None:
    """The library's novel views are the CLI's (``--renders``): the path between the cameras, 8-bit."""
    from macsplat_cli.images import to_uint8
    from macsplat_cli.render import render_camera
    from macsplat_cli.trajectory import interpolate_cameras

    rec = reconstruct(pair[:2], _config(pair[2]))
    views = render_path(rec, 3)
    assert len(views) == 3 and views[0].shape == (SIZE[1], SIZE[0], 3) and views[0].dtype == np.uint8
    cams = interpolate_cameras(list(rec.cameras(original_size=False)), 3)
    with torch.no_grad():
        assert np.array_equal(views[1], to_uint8(render_camera(rec.gaussians, cams[1]).rgb))


_COMPILE_CHECK = r"""
import json
import sys
from macsplat_cli import engine
from macsplat_cli.pipeline import _match_kernels as m, warmup
from macsplat_cli.pipeline.compact import _kernels as o
from macsplat_cli.pipeline.depth import _patchmatch_kernels as p, _sgm_kernels as s
from macsplat_cli.pipeline.multiview import _covis_kernels as c, _schur_kernels as b, _sh_views_kernels as v
from macsplat_cli.render import _kernels as r, _project_kernels as pr

rec = engine.reconstruct(sys.argv[1:3])
warmup.threads[0].join()
engine.render_path(rec, 2)
kernels = [m._chunks, s._straight, s._winner_rows, p._initial_rows, p._refine_rows, r._count_runs,
           r._fill_runs, r._forward_tiles, pr.project_range, pr.depth_order, pr._gather_range, o.zbuffers,
           o.seen_rows, o.mergeable]
multiview = [b.schur_term, c.kept, v.view_spread]
pair = {k.__name__: len(k.signatures) for k in kernels + multiview}
warmup.compile_in_background(3)  # what more photos add: the N-photo stages' kernels alone
warmup.threads[-1].join()
print(json.dumps([pair, {k.__name__: len(k.signatures) for k in multiview}, len(warmup.threads)]))
"""


def test_background_compilation_compiles_the_signatures_the_stages_use(pair: tuple[Path, Path, Path]) -> None:
    """The engine's background thread compiles each kernel for exactly the argument types the stages pass: after a
    reconstruction and a rendered path in a fresh process, every kernel has one signature, not two. Two photos
    leave the N-photo stages' kernels alone; a later run of more photos adds them (one signature each), in a
    second thread."""
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    res = subprocess.run([sys.executable, "-c", _COMPILE_CHECK, str(pair[0]), str(pair[1])], capture_output=True,
                         text=True, env={**os.environ, "PYTHONPATH": str(root)}, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    counts, multiview, threads = json.loads(res.stdout.strip().splitlines()[-1])
    assert {k: n for k, n in counts.items() if k in multiview} == dict.fromkeys(multiview, 0), counts
    assert all(n == 1 for k, n in counts.items() if k not in multiview), counts
    assert multiview == dict.fromkeys(multiview, 1) and threads == 2, (multiview, threads)


def test_stage_clock_times_each_stage_and_tells_its_events() -> None:
    """One stage timer for the pipeline and the engine: start/end around a stage, fail when it raises, its time."""
    from macsplat_cli.pipeline.run import StageClock

    events: list[tuple[str, str]] = []
    clock = StageClock(lambda stage, event: events.append((stage, event)))
    assert clock("images", lambda: 7) == 7
    with pytest.raises(ZeroDivisionError):
        clock("pose", lambda: 1 / 0)
    assert events == [("images", "start"), ("images", "end"), ("pose", "start"), ("pose", "fail")]
    assert list(clock.times) == ["images"] and clock.times["images"] >= 0.0


def test_the_photos_and_the_settings_are_checked_once(
    pair: tuple[Path, Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``macsplat reconstruct`` counts the photos and validates its settings once, in the engine, before any model
    or stage."""
    from macsplat_cli import _limits

    calls: list[int] = []
    validated: list[bool] = []
    real, real_validate = _limits.check_photo_count, EngineConfig.validate

    def counted(n: int, *args: object, **kwargs: object) -> None:
        calls.append(n)
        real(n, *args, **kwargs)  # type: ignore[arg-type]

    def validate(self: EngineConfig, **kwargs: bool) -> None:
        validated.append(True)
        real_validate(self, **kwargs)

    class Stop(Exception):
        pass

    def stop(*args: object) -> None:
        raise Stop

    monkeypatch.setattr(_limits, "check_photo_count", counted)
    monkeypatch.setattr(EngineConfig, "validate", validate)
    monkeypatch.setattr(engine, "_build_pipeline", stop)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(["reconstruct", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "s.ply"), "-q"])
    assert code != 0 and "Stop" in err.getvalue()  # stopped where the pipeline would be built
    assert calls == [2] and validated == [True]
